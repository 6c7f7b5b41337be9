"""Writing a ROS 2 log's messages in another layout: a single MCAP file, a rosbag2 directory (MCAP or
SQLite storage, compressed per file or per message, split over several files) or a ROS 1 bag, as the
recording tools write them (for tests and benchmarks of the readers on every layout)."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from formats import ros2
from formats.layouts import Layout, MessageMigrator, _rosbag2_metadata
from formats.log import LogWriter
from formats.signatures import ROSBAG2_METADATA
from relpoint.errors import UsageError


@dataclass(frozen=True)
class LayoutSpec:
    """A layout to write: rosbag2 ``storage`` (``mcap``/``sqlite3``) with ``compression`` (``none``,
    ``file``, ``message``) split over ``files`` files, or a ROS 1 bag with ``compression`` ``none``,
    ``bz2`` or ``lz4``."""

    layout: Layout
    storage: str = "mcap"
    compression: str = "none"
    files: int = 1

    @property
    def label(self) -> str:
        if self.layout is Layout.ROS1:
            return "rosbag1" + ("" if self.compression == "none" else f" {self.compression} chunks")
        if self.layout is Layout.MCAP:
            return "single mcap"
        parts = [f"rosbag2 {self.storage}"]
        if self.files > 1:
            parts.append(f"split x{self.files}")
        if self.compression != "none":
            parts.append(f"zstd per {self.compression}")
        return ", ".join(parts)


RawMessage = tuple[str, str, int, bytes]


def raw_messages(path: Path) -> Iterator[RawMessage]:
    """``(topic, typename, log_time_ns, cdr_bytes)`` of every message of a ROS 2 log, in log-time order."""
    with AnyReader([path]) as reader:
        if not reader.is2:
            raise UsageError(f"{path}: copying needs a ROS 2 (CDR) log", "give an MCAP file or rosbag2 directory")
        for connection, log_time, raw in reader.messages():
            yield connection.topic, ros2.normalise_typename(connection.msgtype), log_time, bytes(raw)


def write_layout(messages: Iterable[RawMessage], target: str | os.PathLike[str], spec: LayoutSpec) -> Path:
    """Write CDR ``messages`` (standard ROS 2 types, time order) as a new log at ``target`` in ``spec``'s layout.

    rosbag2 directories are written by rosbags' writer, as ``ros2 bag record`` would write them; a split
    bag is ``spec.files`` consecutive parts with one metadata.yaml. ROS 1 bags carry the ROS 1 (Noetic)
    definitions, messages migrated field by field. Returns ``target``.
    """
    target = Path(target)
    if target.exists():
        raise UsageError(f"{target} exists already", "give a new path")
    messages = list(messages)
    if spec.layout is Layout.MCAP:
        _write_mcap(messages, target)
    elif spec.layout is Layout.ROS1:
        _write_ros1(messages, target, spec.compression)
    else:
        _write_rosbag2(messages, target, spec)
    return target


def _write_mcap(messages: list[RawMessage], target: Path) -> None:
    with LogWriter(target) as writer:
        for topic, typename, stamp_ns, raw in messages:
            writer.write(topic, typename, ros2.deserialize(raw, typename), stamp_ns)


def _write_ros1(messages: list[RawMessage], target: Path, compression: str) -> None:
    from rosbags.rosbag1 import Writer as Ros1Writer  # writers: imported when writing, not to read

    noetic = get_typestore(Stores.ROS1_NOETIC)
    migrate = MessageMigrator(ros2.typestore(), noetic)
    writer = Ros1Writer(target)
    if compression != "none":
        writer.set_compression(Ros1Writer.CompressionFormat[compression.upper()])
    with writer:
        connections: dict[str, Any] = {}
        for topic, typename, stamp_ns, raw in messages:
            if topic not in connections:
                if typename not in noetic.fielddefs:  # not in Noetic's store (tf2_msgs): ROS 1 text of the ROS 2 type
                    types = get_types_from_msg(ros2.typestore().generate_msgdef(typename, ros_version=1)[0], typename)
                    types.pop("std_msgs/msg/Header", None)
                    noetic.register(types)
                connections[topic] = writer.add_connection(topic, typename, typestore=noetic)
            message = migrate(ros2.deserialize(raw, typename), typename)
            writer.write(connections[topic], stamp_ns, bytes(noetic.serialize_ros1(message, typename)))


def _write_rosbag2(messages: list[RawMessage], target: Path, spec: LayoutSpec) -> None:
    from rosbags.rosbag2 import Writer as Rosbag2Writer  # writers: imported when writing, not to read
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[spec.storage]
    parts = max(1, min(spec.files, len(messages)))
    bounds = [round(k * len(messages) / parts) for k in range(parts + 1)]
    with tempfile.TemporaryDirectory(dir=target.parent) as scratch:
        part_dirs = []
        for k in range(parts):
            part = Path(scratch) / f"{target.name}_{k}"
            writer = Rosbag2Writer(part, version=8, storage_plugin=plugin)
            if spec.compression != "none":
                writer.set_compression(CompressionMode[spec.compression.upper()], CompressionFormat.ZSTD)
            with writer:
                connections: dict[str, Any] = {}
                for topic, typename, stamp_ns, raw in messages[bounds[k] : bounds[k + 1]]:
                    if topic not in connections:
                        connections[topic] = writer.add_connection(topic, typename, typestore=ros2.typestore())
                    writer.write(connections[topic], stamp_ns, raw)
            part_dirs.append(part)
        if parts == 1:
            shutil.move(part_dirs[0], target)
            return
        target.mkdir()
        infos = []
        for part in part_dirs:
            info = _rosbag2_metadata(part)
            for name in info["relative_file_paths"]:
                shutil.move(part / name, target / name)
            infos.append(info)
        (target / ROSBAG2_METADATA).write_text(yaml.safe_dump(_merge_metadata(infos), sort_keys=False))


def _merge_metadata(infos: list[dict[str, Any]]) -> dict[str, Any]:
    """One rosbag2 metadata document for consecutive parts, as a split recording has."""
    merged = dict(infos[0])
    starts = [i["starting_time"]["nanoseconds_since_epoch"] for i in infos]
    ends = [i["starting_time"]["nanoseconds_since_epoch"] + i["duration"]["nanoseconds"] for i in infos]
    counts: dict[str, int] = {}
    topics: dict[str, Any] = {}
    for info in infos:
        for entry in info["topics_with_message_count"]:
            name = entry["topic_metadata"]["name"]
            topics.setdefault(name, entry["topic_metadata"])
            counts[name] = counts.get(name, 0) + entry["message_count"]
    merged.update(
        relative_file_paths=[name for i in infos for name in i["relative_file_paths"]],
        files=[entry for i in infos for entry in i.get("files", [])],
        starting_time={"nanoseconds_since_epoch": min(starts)},
        duration={"nanoseconds": max(ends) - min(starts)},
        message_count=sum(i["message_count"] for i in infos),
        topics_with_message_count=[{"topic_metadata": meta, "message_count": counts[name]} for name, meta in topics.items()],
    )  # fmt: skip
    return {"rosbag2_bagfile_information": merged}
