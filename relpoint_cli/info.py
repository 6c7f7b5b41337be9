"""``relpoint info``: what a log holds and what can run on it."""

from __future__ import annotations

import dataclasses
import logging
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import click
import numpy as np

from formats import ros2
from formats.layouts import Storage
from formats.log import ROLE_OPTIONS, ROLE_TYPES, LogReader, TopicInfo, may_serve, role_accepts
from formats.outputs import json_text
from formats.reference_trajectories import tf_edges
from relpoint.errors import RelpointError
from relpoint.estimators import ESTIMATORS
from relpoint_app.roles import NEED_ROLES
from relpoint_cli.errors import handle_errors
from relpoint_cli.options import input_path
from relpoint_cli.topics import topic_options, topics_from

logger = logging.getLogger(__name__)


def capabilities(available: set[str], unusable: frozenset[str] = frozenset()) -> dict[str, Any]:
    """Which estimators can run and which evaluations are possible with the roles ``available``, of
    which those in ``unusable`` are present without a usable item (every cloud empty or invalid)."""
    estimators = {}
    for name in sorted(ESTIMATORS):
        needs, also = ESTIMATORS.inputs(name)  # without importing the estimator
        roles = [role for need in needs for role in NEED_ROLES.get(need, (need,))]
        missing = [role for role in roles if role not in available]
        empty = [role for role in roles if role in available and role in unusable]
        uses = [need for need in sorted(also) if all(r in available for r in NEED_ROLES.get(need, (need,)))]
        estimators[name] = {"can_run": not missing and not empty, "missing": missing, "unusable": empty,
                            "also_uses": uses}  # fmt: skip
    return {
        "estimators": estimators,
        "evaluate_trajectory": "ground_truth_pose" in available,
        "evaluate_landmarks": "ground_truth_landmarks" in available,
    }


def storage_document(storage: Storage, topic_infos: dict[str, TopicInfo]) -> dict[str, Any]:
    """What ``ros2 bag info`` tells about a log: layout, storage id, files, size, time range, counts, compression.

    Start and end are the first and last message times over every topic, in ns since the epoch and as UTC.
    """
    starts = [i.first_ns for i in topic_infos.values() if i.first_ns is not None]
    ends = [i.last_ns for i in topic_infos.values() if i.last_ns is not None]
    start_ns, end_ns = (min(starts), max(ends)) if starts else (None, None)
    return {
        "layout": storage.layout.value,
        "storage_id": storage.storage_id,
        "files": [
            {"name": f.name, "size_bytes": f.size_bytes, "message_count": f.message_count} for f in storage.files
        ],
        "start_ns": start_ns,
        "end_ns": end_ns,
        "start_utc": None if start_ns is None else _utc(start_ns),
        "end_utc": None if end_ns is None else _utc(end_ns),
        "message_count": sum(i.count for i in topic_infos.values()),
        "compression": {"format": storage.compression_format, "mode": storage.compression_mode},
        "ros_distro": storage.ros_distro or None,
    }


def _utc(stamp_ns: int) -> str:
    seconds, nanoseconds = divmod(stamp_ns, 1_000_000_000)
    return datetime.fromtimestamp(seconds, tz=timezone.utc).strftime("%Y-%m-%dT%H:%M:%S") + f".{nanoseconds:09d}Z"


def _duration(document: dict[str, Any]) -> str:
    """End minus start, exact to the nanosecond like the two (the JSON's ``duration_s`` is rounded to us)."""
    if document["start_ns"] is None or document["end_ns"] is None:
        return f"{document['duration_s']:.6f}"
    return _seconds(document["end_ns"] - document["start_ns"])


def _seconds(stamp_ns: int) -> str:
    return f"{stamp_ns // 1_000_000_000}.{stamp_ns % 1_000_000_000:09d}"


def _size(size_bytes: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if size_bytes < 1024 or unit == "GiB":
            return f"{size_bytes:.0f} {unit}" if unit == "B" else f"{size_bytes:.1f} {unit}"
        size_bytes /= 1024
    raise AssertionError("unreachable")  # pragma: no cover


@click.command()
@click.argument("log", type=input_path())
@click.option("--json", "as_json", is_flag=True, help="Print a JSON document instead of a table.")
@topic_options
@handle_errors
def info(log: Path, as_json: bool, **topic_names: str) -> None:
    """Show a log's storage, topics, types, counts, duration and rates, and which estimators can run on it.

    LOG is an MCAP file, a rosbag2 directory (mcap or sqlite3 storage, split or compressed) or a ROS 1 bag.

    \b
    Examples:
      relpoint info sample_logs/figure8.mcap
      relpoint info rosbag2_2026_11_24-10_00_00 --json
      relpoint info robot.mcap --points-topic /lidar/landmarks --json
    """
    reader = LogReader(log, topics_from(topic_names))
    storage = reader.storage()
    available = reader.available_roles()
    role_of = {topic: role for role, topic in reader.topics.roles().items()}
    topics = []
    for topic, item in reader.topic_infos.items():
        role = role_of.get(topic)
        topics.append({
            "topic": topic, "type": item.typename, "count": item.count, "duration_s": round(item.duration_s, 6),
            "serialization_format": item.message_encoding,
            "rate_hz": None if item.rate_hz is None else round(item.rate_hz, 3),
            "role": role if role and role_accepts(role, item.typename) else None,
        })  # fmt: skip
    observations = None
    if "points" in available:
        clouds = [r.value for r in reader.records(["points"])]
        counts = [len(cloud) for cloud in clouds]
        frames = sorted({cloud.frame_id for cloud in clouds})
        observations = {
            "topic": reader.topics.points, "frame_ids": frames,
            # None when no cloud of the topic could be read (each is counted under "skipped")
            "points_mean": round(float(np.mean(counts)), 3) if counts else None,
            "points_min": int(np.min(counts)) if counts else None,
            "points_max": int(np.max(counts)) if counts else None,
            "skipped": dict(sorted(reader.skipped.items())),
        }  # fmt: skip
    reference_topics = [
        topic for topic, item in reader.topic_infos.items() if item.typename in ros2.POSE_TYPES and item.count
    ]
    tf_topics = [topic for topic, item in reader.topic_infos.items() if item.typename == ros2.TF_MESSAGE and item.count]
    # The frames a chain can join (--parent/--child): each TF topic with its static one.
    tf_trees: dict[str, list[dict[str, Any]]] = {}
    for topic in tf_topics:
        if topic.endswith("_static") and topic.removesuffix("_static") in tf_topics:
            continue  # read with its dynamic topic
        try:
            tf_trees[topic] = [dataclasses.asdict(edge) for edge in tf_edges(reader, topic)]
        except RelpointError as error:  # a transform that cannot be decoded: the rest of info still holds
            logger.warning("%s: its TF tree cannot be read (%s)", topic, error)
    document = {
        "path": str(log),
        "size_bytes": storage.size_bytes,
        "duration_s": round(reader.duration_s(), 6),
        **storage_document(storage, reader.topic_infos),
        "topics": topics,
        "observations": observations,
        **capabilities(
            available, frozenset({"points"}) if observations and not observations["points_max"] else frozenset()
        ),
        "reference_topics": reference_topics,
        "tf_topics": tf_topics,
        "tf_edges": tf_trees,
    }
    missing = sorted({role for cap in document["estimators"].values() for role in cap["missing"]})
    named = set(reader.topics.roles().values())
    document["candidate_topics"] = {
        role: [topic for topic, item in reader.topic_infos.items()
               if may_serve(role, topic, item.typename) and item.count and topic not in named]
        for role in missing
    }  # fmt: skip
    if as_json:
        click.echo(json_text(document, indent=2))
        return
    click.echo(f"{log}  {document['size_bytes'] / 1e6:.2f} MB, {document['duration_s']:.3f} s")
    compression = document["compression"]
    rows = [
        ("layout", document["layout"]),
        ("storage id", document["storage_id"]),
        ("files", ", ".join(f["name"] for f in document["files"])),
        ("size", _size(document["size_bytes"])),
        ("duration", f"{_duration(document)} s"),
        ("start", "-" if document["start_ns"] is None else f"{document['start_utc']} ({_seconds(document['start_ns'])})"),
        ("end", "-" if document["end_ns"] is None else f"{document['end_utc']} ({_seconds(document['end_ns'])})"),
        ("messages", str(document["message_count"])),
        ("compression", f"{compression['format']} ({compression['mode']})" if compression["mode"] else "none"),
    ]  # fmt: skip
    for label, value in rows:
        click.echo(f"  {label + ':':<13} {value}")
    width = max([len(t["topic"]) for t in topics] + [5])
    type_width = max([len(t["type"]) for t in topics] + [4])
    click.echo(f"  {'topic':<{width}}  {'type':<{type_width}}  {'format':<6}  {'count':>7}  {'rate Hz':>8}  role")
    for t in topics:
        rate = "-" if t["rate_hz"] is None else f"{t['rate_hz']:.2f}"
        click.echo(f"  {t['topic']:<{width}}  {t['type']:<{type_width}}  {t['serialization_format']:<6}  "
                   f"{t['count']:>7}  {rate:>8}  {t['role'] or ''}")  # fmt: skip
    if observations and observations["points_mean"] is None:
        click.echo(f"observations on {observations['topic']}: no cloud could be read")
    elif observations:
        click.echo(
            f"observations on {observations['topic']} (frame {', '.join(observations['frame_ids'])}): "
            f"{observations['points_mean']:.1f} points per iteration (min {observations['points_min']}, "
            f"max {observations['points_max']})"
        )
        for kind, count in observations["skipped"].items():
            click.echo(f"  unusable: {count} {kind.split(': ', 1)[1]}")
    click.echo("estimators:")
    if not document["estimators"]:
        click.echo("  (none installed)")
    for name, cap in document["estimators"].items():
        reasons = ([f"missing {', '.join(cap['missing'])}"] if cap["missing"] else []) + [
            f"no usable {role}" for role in cap["unusable"]
        ]
        state = "can run" if cap["can_run"] else f"cannot run ({'; '.join(reasons)})"
        extra = f"; uses {', '.join(cap['also_uses'])}" if cap["also_uses"] and cap["can_run"] else ""
        click.echo(f"  {name:<10} {state}{extra}")
    for role, candidates in document["candidate_topics"].items():
        if candidates:
            click.echo(f"  {role.replace('_', ' ')} ({ROLE_TYPES[role]}) may be on {', '.join(candidates)}: "
                       f"name it with {ROLE_OPTIONS[role]}")  # fmt: skip
    trajectory = (
        "yes" if document["evaluate_trajectory"]
        else "with --reference-topic or --parent/--child (below)" if reference_topics or tf_topics
        else "no (no pose topic)"
    )  # fmt: skip
    click.echo(f"evaluation: trajectory {trajectory}, "
               f"landmarks {'yes' if document['evaluate_landmarks'] else 'no (no ground-truth landmarks)'}")  # fmt: skip
    if reference_topics:
        click.echo(
            f"  pose topics that can serve as --reference-topic or --estimate-topic: {', '.join(reference_topics)}"
        )
    if tf_topics:
        click.echo(f"  transforms on {', '.join(tf_topics)}: a reference from a frame chain with --parent/--child, "
                   "an estimate with --estimate-parent/--estimate-child")  # fmt: skip
        for topic, edges in document["tf_edges"].items():
            moving = [f"{e['parent']} -> {e['child']} ({e['count']})" for e in edges if not e["static"]]
            fixed = [f"{e['parent']} -> {e['child']}" for e in edges if e["static"]]
            shown = ", ".join(fixed[:8]) + (f", ... ({len(fixed)} in all; --json lists them)" if len(fixed) > 8 else "")
            click.echo(f"  {topic} frames: {', '.join(moving) or 'no dynamic transform'}"
                       + (f"; static: {shown}" if fixed else ""))  # fmt: skip
