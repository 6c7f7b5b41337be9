"""Reading and writing relpoint logs: ``ros2`` profile, CDR-encoded standard messages.

The contract is ``docs/log-format.md``. :class:`LogWriter` writes a log (atomically) as a single MCAP
file; :class:`LogReader` reads a log in any layout of :mod:`formats.layouts` (a single MCAP file, a
rosbag2 directory with mcap or sqlite3 storage, split or compressed, a ROS 1 bag), checks it against the
contract, summarises it and yields its messages decoded into relpoint's core types, in time order. Topic
names are defaults that :class:`Topics` overrides, so real robot bags with other names read unchanged.

Library choice (measured by ``benchmarks/io.py`` on a 10,000-iteration log): reading goes through
rosbags' ``AnyReader``, which read it about 2.5x faster than the ``mcap`` package's reader with either
rosbags' CDR codec or ``mcap-ros2-support``'s decoder, verifies every chunk's CRC, and decodes
``uint8[]`` payloads straight into numpy arrays. Writing uses the ``mcap`` package's writer with
rosbags' CDR serialiser and the typestore's standard message definitions.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import os
import sqlite3
import struct
import tempfile
import zlib
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from apsw import Error as SqliteError  # rosbags reads sqlite3 storage through apsw
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2.errors import ReaderError

try:  # the zstd codec rosbags decompresses rosbag2 files and messages with
    from compression.zstd import ZstdError
except ImportError:  # Python < 3.14
    from backports.zstd import ZstdError

import relpoint
from formats import ros2
from formats.atomic import atomic_path
from formats.layouts import (
    Layout,
    MessageMigrator,
    Storage,
    check_storage,
    complete_typestore,
    decompress_bag,
    describe_storage,
    detect_layout,
    open_reader,
)
from formats.outputs import json_text, unreadable_input
from formats.topics import Topics
from formats.trajectory_files import format_stamp
from relpoint.errors import InputError, UsageError
from relpoint.types import GroundTruthLandmarks, Intrinsics, OdometryMeasurement, PointObservation, Pose, PositionFix

log = logging.getLogger(__name__)

PROFILE = "ros2"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
ROS1_ENCODING = "ros1"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


#: Message type each role must carry.
ROLE_TYPES: dict[str, str] = {
    "points": ros2.POINT_CLOUD2,
    "ground_truth_pose": ros2.POSE_STAMPED,
    "ground_truth_landmarks": ros2.POINT_CLOUD2,
    "odometry": ros2.ODOMETRY,
    "fix": ros2.POSE_WITH_COVARIANCE_STAMPED,
    "depth": ros2.IMAGE,
    "camera_info": ros2.CAMERA_INFO,
    "color": ros2.IMAGE,
}

#: Other message types a role takes: image_transport's compressed images (``compressed`` colour,
#: ``compressedDepth`` depth), as real bags usually store them.
ROLE_ALSO_TYPES: dict[str, tuple[str, ...]] = {
    "depth": (ros2.COMPRESSED_IMAGE,),
    "color": (ros2.COMPRESSED_IMAGE,),
}


def role_accepts(role: str, typename: str | None) -> bool:
    """Whether a topic of ``typename`` can serve ``role`` (its type, or one of :data:`ROLE_ALSO_TYPES`)."""
    return typename == ROLE_TYPES[role] or typename in ROLE_ALSO_TYPES.get(role, ())


#: Words in a topic's name that say which images it holds: a topic named for colour alone is no depth
#: camera's, one named for depth no colour camera's (RealSense's /camera/aligned_depth_to_color/image_raw
#: names both, and is depth).
_IMAGE_WORDS: dict[str, tuple[str, ...]] = {"depth": ("depth",), "color": ("color", "colour", "rgb")}


def may_serve(role: str, topic: str, typename: str | None) -> bool:
    """Whether a topic of ``typename`` could carry ``role``'s messages: its type is one the role takes,
    and, for images, its name does not say it holds the other kind only (candidates to name with an option)."""
    if not role_accepts(role, typename):
        return False
    if role not in _IMAGE_WORDS:
        return True
    name = topic.lower()
    other = next(r for r in _IMAGE_WORDS if r != role)
    return any(w in name for w in _IMAGE_WORDS[role]) or not any(w in name for w in _IMAGE_WORDS[other])


#: The command-line option that renames each role's topic.
ROLE_OPTIONS: dict[str, str] = {
    "points": "--points-topic",
    "ground_truth_pose": "--ground-truth-topic",
    "ground_truth_landmarks": "--landmarks-topic",
    "odometry": "--odom-topic",
    "fix": "--fix-topic",
    "depth": "--depth-topic",
    "camera_info": "--camera-info-topic",
    "color": "--color-topic",
}


#: The order of records of one stamp (:meth:`LogReader.records`): relpoint's own writers' order, the
#: truth first, then what the sensor saw at that instant, then the odometry that holds from it and the fix.
ROLE_ORDER: dict[str, int] = {
    role: rank
    for rank, role in enumerate(
        ("ground_truth_landmarks", "camera_info", "ground_truth_pose", "color", "depth", "points", "odometry", "fix")
    )
}


#: Most that ``log_time - header.stamp`` may differ between the topics of one pass over a log (ns). The
#: records are merged by stamp, which holds back up to this much of the log; recorders' receive latency
#: is well below it, while topics stamped on different clocks (sim time and wall time, a device clock)
#: differ by far more and cannot be merged.
MAX_STAMP_SKEW_NS = 10_000_000_000

#: ``log_time - header.stamp`` (ns) beyond which a topic is reported as off the log format (which has
#: them equal): merging by stamp still works, but times shown from log_time are not the stamps.
STAMP_OFFSET_WARNING_NS = 1_000_000_000


@dataclass(frozen=True)
class Record:
    """One decoded message: its role, ``header.stamp`` in ns, and the core-type value.

    Values by role: ``points`` PointObservation; ``ground_truth_pose`` Pose; ``ground_truth_landmarks``
    GroundTruthLandmarks; ``odometry`` OdometryMeasurement; ``fix`` PositionFix; ``camera_info``
    Intrinsics; ``depth`` (H, W) float32 metres; ``color`` (H, W, 3) uint8.
    """

    role: str
    stamp_ns: int
    value: Any


@dataclass(frozen=True)
class TopicInfo:
    """What a log holds on one topic."""

    topic: str
    typename: str
    message_encoding: str
    count: int
    first_ns: int | None
    last_ns: int | None

    @property
    def duration_s(self) -> float:
        return 0.0 if self.first_ns is None or self.last_ns is None else (self.last_ns - self.first_ns) * 1e-9

    @property
    def rate_hz(self) -> float | None:
        return (self.count - 1) / self.duration_s if self.count > 1 and self.duration_s > 0 else None


def _corrupt(path: Path, layout: Layout, error: BaseException) -> InputError:
    if isinstance(error, PermissionError):
        return unreadable_input(path, error)
    detail = str(error) or type(error).__name__
    if isinstance(error, ReaderError) and "not in timestamp order" in detail:
        # valid MCAP (its messages may come in any order), but without chunk indexes rosbags reads
        # them only in log-time order; `mcap recover` copies the chunks and writes their indexes
        storage = "MCAP file" if layout is Layout.MCAP else "bag's MCAP storage file"
        return InputError(
            f"{path}: the {storage} is unindexed (no chunk indexes or summary) and its messages are not in "
            "log-time order: relpoint reads such a file only with its index",
            "write an indexed copy with `mcap recover IN.mcap -o OUT.mcap` (the MCAP CLI) and read that",
        )
    return InputError(f"{path}: the {layout.noun} is truncated or corrupt ({detail})", layout.repair_hint)


#: Errors the bag readers and their decompressors raise on damaged files: a chunk whose CRC does not match
#: (MCAP), a damaged index (ROS 1), a malformed database page (SQLite), a broken zstd frame (rosbag2).
_READ_ERRORS: tuple[type[BaseException], ...] = (
    AnyReaderError, ReaderError, Ros1ReaderError, SqliteError, sqlite3.Error, ZstdError, OSError, struct.error,
    zlib.error, ValueError, EOFError, KeyError, IndexError, OverflowError, MemoryError, RuntimeError,
    AssertionError, TypeError, AttributeError, UnicodeDecodeError,
)  # fmt: skip


class _Decoder:
    """Message bytes to standard ROS 2 messages with an open reader's typestore (built from the log's own
    definitions); ROS 1 messages are migrated to the ROS 2 types."""

    def __init__(self, reader: AnyReader) -> None:
        self._reader = reader
        self._migrate = None if reader.is2 else MessageMigrator(reader.typestore)

    def __call__(self, raw: bytes | memoryview, typename: str) -> Any:
        try:
            message = self._reader.deserialize(raw, typename)
            return message if self._migrate is None else self._migrate(message, typename)
        except Exception as error:  # rosbags raises assorted errors on malformed messages
            raise InputError(f"a {typename} message cannot be decoded ({type(error).__name__}: {error})") from None


class LogReader:
    """A relpoint log opened for reading (read-only; the file is never modified).

    Parameters
    ----------
    path:
        The log: a ``.mcap`` file, a rosbag2 directory or a ROS 1 ``.bag`` (see :mod:`formats.layouts`).
    topics:
        Topic names of the roles (defaults: the log format's).

    Raises
    ------
    InputError
        If the log is missing, of no known layout, truncated or corrupt.
    """

    def __init__(self, path: str | os.PathLike[str], topics: Topics | None = None) -> None:
        self.path = Path(path)
        self.topics = topics or Topics()
        #: Counts of skipped data, e.g. ``{"points: non-finite points": 12}``: the most one pass over the
        #: log met (every pass over a topic meets the same messages, so reading it again adds nothing).
        self.skipped: Counter[str] = Counter()
        #: What a pass found doubtful about the log's time stamps (each once), for run.json.
        self.warnings: list[str] = []
        # Per topic, from the summary pass: the range of log_time - header.stamp (up to the first stamp
        # that does not increase) and that first stamp with the one before it.
        self._offsets: dict[str, tuple[int, int]] = {}
        self._backwards: dict[str, tuple[int, int]] = {}
        self._offsets_told = False
        #: How the log is laid out on disk.
        self.layout = detect_layout(self.path)
        check_storage(self.path, self.layout)
        self._scratch: tempfile.TemporaryDirectory[str] | None = None
        # Opening parses every message definition: a pass hands its open reader to the next one.
        self._spare: AnyReader | None = None
        compressed = self.layout is Layout.ROSBAG2 and self.storage().compression_mode == "file"
        self._read_path = self._decompressed() if compressed else self.path
        self._channels = self._read_channels()

    def _decompressed(self) -> Path:
        """A bag compressed per file, decompressed once for all the passes over it (removed with the reader)."""
        self._scratch = tempfile.TemporaryDirectory(prefix=".relpoint-")
        try:
            copy = decompress_bag(self.path, Path(self._scratch.name))
            check_storage(copy, self.layout)
        except InputError as error:
            raise _corrupt(self.path, self.layout, ValueError(f"decompressed: {error.message}")) from None
        except _READ_ERRORS as error:
            raise _corrupt(self.path, self.layout, error) from None
        return copy

    # -- summary ---------------------------------------------------------------------------------

    def _open(self) -> AnyReader:
        """An open reader of the log: the one the last finished pass left, else a new one.

        The log is opened once for any number of passes made one after the other; a pass that starts
        while another is under way gets a reader of its own (each reader reads from one file position).
        """
        if self._spare is not None:
            reader, self._spare = self._spare, None
            return reader
        reader = open_reader(self._read_path)
        try:
            reader.open()
            complete_typestore(reader)
        except _READ_ERRORS as error:
            raise _corrupt(self.path, self.layout, error) from None
        return reader

    def _release(self, reader: AnyReader) -> None:
        """Keep a finished pass's reader for the next pass (close it when one is kept already)."""
        if self._spare is None:
            self._spare = reader
        else:
            reader.close()

    def close(self) -> None:
        """Close the open reader and remove a decompressed copy; later passes open the log again."""
        if self._spare is not None:
            reader, self._spare = self._spare, None
            reader.close()
        if self._scratch is not None:
            self._scratch.cleanup()
            self._scratch = None

    def __enter__(self) -> LogReader:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self.close()

    def storage(self) -> Storage:
        """Storage id, files, sizes and compression (what ``ros2 bag info`` shows above the topics)."""
        return describe_storage(self.path, self.layout)

    def _read_channels(self) -> dict[str, TopicInfo]:
        """Every topic with type, count and time range; one pass over the records checks every chunk's CRC."""
        first: dict[tuple[str, str], int] = {}  # per (topic, type): a topic may carry several types
        last: dict[tuple[str, str], int] = {}
        counts: Counter[str] = Counter()
        typed_counts: Counter[tuple[str, str]] = Counter()
        stamped: dict[tuple[str, str], bool | None] = {}  # (topic, type) -> ROS 1 serialised, None: no header
        previous: dict[str, int] = {}
        reader = self._open()
        try:
            # No CDR decoding here: the pass reads record headers, each stamped message's header.stamp
            # straight from its bytes, and verifies chunk checksums.
            for connection, log_time, raw in reader.messages():
                topic = connection.topic
                counts[topic] += 1
                key = (topic, connection.msgtype)
                typed_counts[key] += 1
                first.setdefault(key, log_time)
                last[key] = log_time
                if key not in stamped:
                    encoding = getattr(connection.ext, "serialization_format", ROS1_ENCODING)
                    header = ros2.normalise_typename(connection.msgtype) in ros2.HEADER_FIRST_TYPES
                    stamped[key] = (encoding == ROS1_ENCODING) if header else None
                if stamped[key] is not None and topic not in self._backwards:
                    self._note_stamp(topic, log_time, ros2.raw_stamp_ns(raw, bool(stamped[key])), previous)
            if self.layout is Layout.ROSBAG2:
                self._check_counts(reader, counts)
            topics: dict[str, TopicInfo] = {}
            for connection in self._typed_connections(reader, typed_counts):
                key = (connection.topic, connection.msgtype)
                # ROS 1 connections name no serialisation format: their messages are ROS 1-serialised
                encoding = getattr(connection.ext, "serialization_format", ROS1_ENCODING)
                topics[connection.topic] = TopicInfo(
                    connection.topic, ros2.normalise_typename(connection.msgtype), encoding,
                    typed_counts[key], first.get(key), last.get(key),
                )  # fmt: skip
        except _READ_ERRORS as error:
            reader.close()
            raise _corrupt(self.path, self.layout, error) from None
        except BaseException:
            reader.close()
            raise
        self._spare = reader
        return topics

    def _typed_connections(self, reader: AnyReader, typed_counts: Counter[tuple[str, str]]) -> list[Any]:
        """One connection per topic, whose type the topic is listed and read as. A topic that carries
        several types (two publishers, one of another type) is read as the type its role takes, else as
        its most frequent one; the others' messages are not read, which a warning says."""
        by_topic: dict[str, list[Any]] = {}
        for connection in reader.connections:
            kinds = by_topic.setdefault(connection.topic, [])
            if all(c.msgtype != connection.msgtype for c in kinds):
                kinds.append(connection)
        role_of = {topic: role for role, topic in self.topics.roles().items()}
        chosen = []
        for topic, kinds in by_topic.items():
            role = role_of.get(topic)
            accepted = [c for c in kinds if role is not None and role_accepts(role, ros2.normalise_typename(c.msgtype))]
            best = max(accepted or kinds, key=lambda c: typed_counts[(topic, c.msgtype)])
            chosen.append(best)
            others = [c for c in kinds if c is not best and typed_counts[(topic, c.msgtype)]]
            if others:
                left = ", ".join(f"{typed_counts[(topic, c.msgtype)]} {ros2.normalise_typename(c.msgtype)}"
                                 for c in others)  # fmt: skip
                warning = (f"{topic} carries more than one message type: read as "
                           f"{ros2.normalise_typename(best.msgtype)} ({typed_counts[(topic, best.msgtype)]} messages); "
                           f"its {left} messages are not read")  # fmt: skip
                log.warning("%s", warning)
                self.warnings.append(warning)
        return chosen

    def _note_stamp(self, topic: str, log_time: int, stamp: int | None, previous: dict[str, int]) -> None:
        """Widen ``topic``'s range of log_time - stamp, unless its stamps stopped increasing here."""
        if stamp is None:
            return
        before = previous.get(topic)
        if before is not None and stamp <= before:
            self._backwards[topic] = (stamp, before)
            return
        previous[topic] = stamp
        offset = log_time - stamp
        low, high = self._offsets.get(topic, (offset, offset))
        self._offsets[topic] = (min(low, offset), max(high, offset))

    def _check_counts(self, reader: AnyReader, counts: Counter[str]) -> None:
        """The messages read must be the ones metadata.yaml records: sqlite3 storage has no checksum, and a
        storage file cut short or swapped for another shows only here."""
        recorded: Counter[str] = Counter()
        for connection in reader.connections:
            recorded[connection.topic] += connection.msgcount
        for topic, count in recorded.items():
            if counts[topic] != count:
                raise InputError(
                    f"{self.path}: the rosbag2 bag is truncated or corrupt ({counts[topic]} messages on {topic}, "
                    f"metadata.yaml records {count})",
                    self.layout.repair_hint,
                )

    @property
    def topic_infos(self) -> dict[str, TopicInfo]:
        """Topic -> what the log holds there, for every topic in the file."""
        return dict(self._channels)

    def role_present(self, role: str) -> bool:
        """Whether the log has messages of the right type on ``role``'s topic."""
        info = self._channels.get(self.topics.roles()[role])
        return info is not None and info.count > 0 and role_accepts(role, info.typename)

    def available_roles(self) -> set[str]:
        """Roles the log can provide."""
        return {role for role in ROLE_TYPES if self.role_present(role)}

    def require(self, *roles: str) -> None:
        """Raise :class:`InputError` unless every role's topic is present with messages of the right type."""
        for role in roles:
            topic = self.topics.roles()[role]
            info = self._channels.get(topic)
            option = ROLE_OPTIONS[role]
            if info is None or info.count == 0:
                present = ", ".join(
                    f"{t} ({i.typename})" for t, i in self._channels.items() if role_accepts(role, i.typename)
                )
                hint = f"name the right topic with {option}" + (
                    f"; {ROLE_TYPES[role]} topics here: {present}" if present else ""
                )
                raise InputError(f"{self.path}: no messages on {topic} (needed: {ROLE_TYPES[role]})", hint)
            if not role_accepts(role, info.typename):
                raise InputError(
                    f"{self.path}: {topic} carries {info.typename or 'schemaless data'}, not {ROLE_TYPES[role]}",
                    f"name a {ROLE_TYPES[role]} topic with {option}",
                )
            if info.message_encoding not in (MESSAGE_ENCODING, ROS1_ENCODING):
                raise InputError(
                    f"{self.path}: {topic} is encoded as {info.message_encoding!r}, not CDR",
                    "relpoint reads ROS 2 (CDR) logs",
                )

    def duration_s(self) -> float:
        starts = [i.first_ns for i in self._channels.values() if i.first_ns is not None]
        ends = [i.last_ns for i in self._channels.values() if i.last_ns is not None]
        return (max(ends) - min(starts)) * 1e-9 if starts else 0.0

    # -- messages --------------------------------------------------------------------------------

    def messages(self, topics: Iterable[str]) -> Iterator[tuple[str, str, int, Any]]:
        """Raw decoded messages ``(topic, typename, log_time_ns, message)`` of any type, in log-time order."""
        wanted = set(topics)
        reader = self._open()
        try:
            decode = _Decoder(reader)
            connections = [c for c in reader.connections if c.topic in wanted]
            for connection, log_time, raw in reader.messages(connections=connections):
                typename = ros2.normalise_typename(connection.msgtype)
                yield connection.topic, typename, log_time, decode(raw, typename)
        except _READ_ERRORS as error:
            reader.close()
            raise _corrupt(self.path, self.layout, error) from None
        except GeneratorExit:  # the caller stopped early: the reader is sound (every pass seeks to its start)
            self._release(reader)
            raise
        except BaseException:
            reader.close()
            raise
        self._release(reader)

    def records(self, roles: Iterable[str]) -> Iterator[Record]:
        """Decoded messages of ``roles`` in ``header.stamp`` order (the order the estimators need).

        Recorders log a message when they receive it, so across topics log-time order is not stamp
        order (a cloud stamped at capture reaches the recorder after the odometry of that instant). The
        messages are read in log-time order and merged by stamp in a buffer that holds a record until
        the log time has passed its stamp by more than the largest ``log_time - header.stamp`` of the
        topics read (measured in the summary pass). Records of equal stamps come in the order of
        :data:`ROLE_ORDER`, whatever order a recorder logged them in (a fix received before the cloud
        of its instant changed a FastSLAM run's ATE by 16 %).

        Checks that stamps strictly increase per topic (else :class:`InputError`), and that the topics
        read share one clock (their ``log_time - header.stamp`` within :data:`MAX_STAMP_SKEW_NS`). Invalid
        data inside valid messages (non-finite points, empty clouds, malformed messages) is skipped,
        counted in :attr:`skipped` (once however many passes read it) and logged once per kind.
        """
        counts: Counter[str] = Counter()  # this pass's
        roles = [r for r in roles if self.role_present(r)]
        topic_roles = {self.topics.roles()[r]: r for r in roles}
        # Calibration is not a time series: a static publisher stamps its CameraInfo 0, or repeats one
        # stamp. It neither sets the merge's horizon nor has to increase; each message holds until the next.
        horizon = self._merge_horizon([t for t, r in topic_roles.items() if r != "camera_info"])
        held: list[tuple[int, int, int, Record]] = []  # (stamp, role's rank, arrival, record), a heap
        arrival = itertools.count()
        previous: dict[str, int] = {}
        reader = self._open()
        try:
            decode = _Decoder(reader)
            connections = [
                c for c in reader.connections
                if c.topic in topic_roles and role_accepts(topic_roles[c.topic], ros2.normalise_typename(c.msgtype))
            ]  # fmt: skip
            for connection, log_time, raw in reader.messages(connections=connections):
                # every message from here on is stamped at or after log_time - horizon
                while horizon is not None and held and held[0][0] < log_time - horizon:
                    yield heapq.heappop(held)[3]
                topic = connection.topic
                role = topic_roles[topic]
                if len(raw) > ros2.MAX_MESSAGE_BYTES:  # refused before a byte of it is decoded
                    self._skip(counts, f"{topic}: oversized messages",
                               f"{len(raw)} bytes, over the limit of {ros2.MAX_MESSAGE_BYTES} bytes")  # fmt: skip
                    continue
                try:
                    record = self._convert(role, decode(raw, ros2.normalise_typename(connection.msgtype)), counts)
                except InputError as error:
                    self._skip(counts, f"{topic}: {getattr(error, 'kind', 'malformed messages')}", str(error))
                    continue
                except (AttributeError, TypeError, ValueError, IndexError, KeyError, OverflowError) as error:
                    # The bytes decoded under the file's own schema but are not the message they claim.
                    self._skip(counts, f"{topic}: malformed messages", f"{type(error).__name__}: {error}")
                    continue
                before = previous.get(topic)
                if before is not None and record.stamp_ns <= before and role != "camera_info":
                    raise self._not_increasing(topic, record.stamp_ns, before)
                previous[topic] = record.stamp_ns
                if horizon is None:  # one topic: its stamps increase in log order
                    yield record
                    continue
                # a stamp the summary pass could not read from the bytes may lag more: wait for it too
                horizon = max(horizon, log_time - record.stamp_ns)
                heapq.heappush(held, (record.stamp_ns, ROLE_ORDER[role], next(arrival), record))
                while held and held[0][0] < log_time - horizon:
                    yield heapq.heappop(held)[3]
            while held:
                yield heapq.heappop(held)[3]
        except _READ_ERRORS as error:
            reader.close()
            raise _corrupt(self.path, self.layout, error) from None
        except GeneratorExit:  # the caller stopped early: the reader is sound (every pass seeks to its start)
            self._release(reader)
            raise
        except BaseException:
            reader.close()
            raise
        self._release(reader)

    def _not_increasing(self, topic: str, stamp_ns: int, before_ns: int) -> InputError:
        return InputError(
            f"{self.path}: {topic} stamp {format_stamp(stamp_ns)} s is not after the previous "
            f"{format_stamp(before_ns)} s (stamps must strictly increase per topic)",
            "fix the recording's stamps, or cut the log before that point with `mcap filter`",
        )

    def _merge_horizon(self, topics: list[str]) -> int | None:
        """The largest ``log_time - header.stamp`` of ``topics``, by which a pass holds records back to merge
        them by stamp; ``None`` for one topic, which needs no merging.

        Raises :class:`InputError` when the topics' offsets lie more than :data:`MAX_STAMP_SKEW_NS` apart
        (stamped on different clocks); warns once of a topic whose offset is over
        :data:`STAMP_OFFSET_WARNING_NS`.
        """
        self._warn_of_offsets()
        offsets = {topic: self._offsets[topic] for topic in topics if topic in self._offsets}
        if len(topics) < 2:
            return None
        if not offsets:
            return 0
        (lowest, (low, _)), (highest, (_, high)) = (
            min(offsets.items(), key=lambda item: item[1][0]), max(offsets.items(), key=lambda item: item[1][1])
        )  # fmt: skip
        if high - low > MAX_STAMP_SKEW_NS:
            for topic in (lowest, highest):  # a topic whose stamps go backwards is the clearer error
                if topic in self._backwards:
                    raise self._not_increasing(topic, *self._backwards[topic])
            raise InputError(
                f"{self.path}: log_time - header.stamp is {low * 1e-9:.3f} s on {lowest} but {high * 1e-9:.3f} s "
                f"on {highest}: their stamps are not on one clock (or the recording stalled), so their messages "
                "cannot be put in stamp order",
                "stamp every topic from one clock, or leave a topic out (e.g. --no-odometry, --no-fixes)",
            )
        return high

    def _warn_of_offsets(self) -> None:
        """Warn once, for every role's topic, of a ``log_time - header.stamp`` over
        :data:`STAMP_OFFSET_WARNING_NS` (the log format has them equal)."""
        if self._offsets_told:
            return
        self._offsets_told = True
        far = {}
        roles = self.topics.roles()
        for topic in dict.fromkeys(t for r, t in roles.items() if r != "camera_info"):
            low, high = self._offsets.get(topic, (0, 0))
            offset = high if abs(high) >= abs(low) else low
            if abs(offset) > STAMP_OFFSET_WARNING_NS:
                far[topic] = offset
        if far:
            warning = (f"log_time - header.stamp reaches {max(far.values(), key=abs) * 1e-9:.3f} s on "
                       f"{', '.join(sorted(far))} (the log format has them equal): messages are ordered and "
                       "timed by header.stamp")  # fmt: skip
            log.warning("%s", warning)
            self.warnings.append(warning)

    def _skip(self, counts: Counter[str], kind: str, detail: str, count: int = 1) -> None:
        """Count ``count`` items of ``kind`` in this pass's ``counts``; :attr:`skipped` keeps the largest pass."""
        if kind not in self.skipped:
            log.warning("skipping %s (%s); further ones are counted in the summary", kind, detail)
        counts[kind] += count
        self.skipped[kind] = max(self.skipped[kind], counts[kind])

    def _convert(self, role: str, message: Any, counts: Counter[str]) -> Record | None:
        value: Any
        if role == "points":
            observation, dropped = ros2.msg_to_observation(message)
            if dropped:
                self._skip(counts, f"{self.topics.points}: non-finite points", "NaN or inf coordinates", dropped)
            if len(observation) == 0:
                self._skip(counts, f"{self.topics.points}: empty clouds", "no valid point in the message")
            return Record(role, observation.stamp_ns, observation)
        if role == "ground_truth_pose":
            value = ros2.msg_to_pose(message)
        elif role == "ground_truth_landmarks":
            value = ros2.msg_to_landmarks(message)
        elif role == "odometry":
            value = ros2.msg_to_odometry(message)
        elif role == "fix":
            value = ros2.msg_to_fix(message)
        elif role == "camera_info":
            value = ros2.msg_to_intrinsics(message)
        elif role == "depth":
            value = ros2.msg_to_depth(message)
        elif role == "color":
            value = ros2.msg_to_rgb(message)
        else:  # pragma: no cover - roles are fixed above
            raise UsageError(f"unknown role {role!r}")
        return Record(role, ros2.stamp_ns_of(message), value)

    def metadata(self) -> dict[str, dict[str, str]]:
        """The file's metadata records by name (e.g. ``relpoint.simulation``); only single MCAP files have them."""
        if self.layout is not Layout.MCAP:
            return {}
        try:
            with self.path.open("rb") as stream:
                return {m.name: dict(m.metadata) for m in make_reader(stream).iter_metadata()}
        except (*_READ_ERRORS, McapError, OSError) as error:
            raise _corrupt(self.path, self.layout, error) from None


class LogWriter:
    """Writes a relpoint log atomically: nothing appears at ``path`` until :meth:`close` succeeds.

    Use as a context manager. Channels are registered on first use, so the file holds only the topics
    written. The same calls in the same order give a byte-identical file.

    Parameters
    ----------
    path: the ``.mcap`` file to create (replaced if it exists).
    compression: chunk compression, ``zstd`` (default), ``lz4`` or ``none``.
    metadata: optional metadata records ``{name: {key: value}}`` (e.g. the simulation settings).
    chunk_size: target uncompressed chunk size in bytes.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        compression: str = "zstd",
        metadata: dict[str, dict[str, str]] | None = None,
        chunk_size: int = 1 << 20,
    ) -> None:
        if compression not in COMPRESSIONS:
            raise UsageError(f"unknown compression {compression!r}", f"choose one of {', '.join(COMPRESSIONS)}")
        self.path = Path(path)
        self._atomic = atomic_path(self.path)
        self._tmp = self._atomic.__enter__()
        self._stream = self._tmp.open("wb")
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=COMPRESSIONS[compression])
        self._writer.start(profile=PROFILE, library=f"relpoint/{relpoint.__version__}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: Counter[str] = Counter()
        for name, data in (metadata or {}).items():
            self._writer.add_metadata(name, data)
        self._closed = False

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort(exc_type, exc, tb)

    def _channel(self, topic: str, typename: str) -> int:
        if topic in self._channels:
            return self._channels[topic]
        if typename not in self._schemas:
            self._schemas[typename] = self._writer.register_schema(
                name=typename, encoding=SCHEMA_ENCODING, data=ros2.message_definition(typename).encode()
            )
        self._channels[topic] = self._writer.register_channel(
            topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=self._schemas[typename]
        )
        return self._channels[topic]

    def write(self, topic: str, typename: str, message: Any, stamp_ns: int) -> None:
        """Write one message; ``log_time`` and ``publish_time`` are ``stamp_ns``, or 0 for a stamp before
        1970 (a negative ROS time, which a header holds; MCAP's times are unsigned)."""
        channel_id = self._channel(topic, typename)
        log_time = max(int(stamp_ns), 0)
        self._writer.add_message(
            channel_id=channel_id,
            log_time=log_time,
            publish_time=log_time,
            data=ros2.serialize(message, typename),
            sequence=self._sequence[topic],
        )
        self._sequence[topic] += 1

    def write_observation(self, observation: PointObservation, topic: str = "/points") -> None:
        self.write(topic, ros2.POINT_CLOUD2, ros2.observation_to_msg(observation), observation.stamp_ns)

    def write_ground_truth_pose(self, pose: Pose, topic: str = "/ground_truth/pose") -> None:
        self.write(topic, ros2.POSE_STAMPED, ros2.pose_to_msg(pose), pose.stamp_ns)

    def write_ground_truth_landmarks(
        self, stamp_ns: int, landmarks: GroundTruthLandmarks, topic: str = "/ground_truth/landmarks"
    ) -> None:
        self.write(topic, ros2.POINT_CLOUD2, ros2.landmarks_to_msg(stamp_ns, landmarks), stamp_ns)

    def write_odometry(
        self, odometry: OdometryMeasurement, topic: str = "/odom", child_frame_id: str = "sensor"
    ) -> None:
        self.write(
            topic, ros2.ODOMETRY, ros2.odometry_to_msg(odometry, child_frame_id=child_frame_id), odometry.stamp_ns
        )

    def write_fix(self, fix: PositionFix, topic: str = "/fix") -> None:
        self.write(topic, ros2.POSE_WITH_COVARIANCE_STAMPED, ros2.fix_to_msg(fix), fix.stamp_ns)

    def write_camera_info(
        self, stamp_ns: int, intrinsics: Intrinsics, topic: str = "/camera/depth/camera_info"
    ) -> None:
        self.write(topic, ros2.CAMERA_INFO, ros2.camera_info_to_msg(stamp_ns, intrinsics), stamp_ns)

    def write_depth(
        self, stamp_ns: int, depth_m: Any, topic: str = "/camera/depth/image", encoding: str = "16UC1"
    ) -> None:
        self.write(topic, ros2.IMAGE, ros2.depth_image_to_msg(stamp_ns, depth_m, encoding=encoding), stamp_ns)

    def write_color(self, stamp_ns: int, rgb: Any, topic: str = "/camera/color/image") -> None:
        self.write(topic, ros2.IMAGE, ros2.color_image_to_msg(stamp_ns, rgb), stamp_ns)

    def close(self) -> None:
        """Finish the file and move it into place."""
        if self._closed:
            return
        self._closed = True
        self._writer.finish()
        self._stream.close()
        self._atomic.__exit__(None, None, None)

    def abort(self, exc_type: Any = None, exc: Any = None, tb: Any = None) -> None:
        """Discard the partial file."""
        if self._closed:
            return
        self._closed = True
        self._stream.close()
        try:
            self._atomic.__exit__(exc_type or RuntimeError, exc or RuntimeError("aborted"), tb)
        except BaseException as error:  # the context manager re-raises the error it was given
            if exc is not None and error is not exc:
                raise


def metadata_json(values: dict[str, Any]) -> dict[str, str]:
    """Metadata values as JSON strings with sorted keys (deterministic)."""
    return {key: json_text(value, sort_keys=True) for key, value in sorted(values.items())}
