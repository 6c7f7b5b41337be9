"""``relpoint info``: what a log holds and what can run on it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click
import numpy as np

from formats.log import ROLE_TYPES, LogReader
from relpoint.estimators import ESTIMATORS
from relpoint_cli.errors import handle_errors
from relpoint_cli.topics import topic_options, topics_from

#: Log roles behind each input an estimator may need.
NEED_ROLES = {"points": ("points",), "depth": ("depth", "camera_info"), "odometry": ("odometry",), "fix": ("fix",)}


def capabilities(available: set[str]) -> dict[str, Any]:
    """Which estimators can run and which evaluations are possible with the roles ``available``."""
    estimators = {}
    for name, spec in sorted(ESTIMATORS.items()):
        missing = [role for need in spec.needs for role in NEED_ROLES.get(need, (need,)) if role not in available]
        uses = [need for need in sorted(spec.uses) if all(r in available for r in NEED_ROLES.get(need, (need,)))]
        estimators[name] = {"can_run": not missing, "missing": missing, "also_uses": uses}
    return {
        "estimators": estimators,
        "evaluate_trajectory": "ground_truth_pose" in available,
        "evaluate_landmarks": "ground_truth_landmarks" in available,
    }


@click.command()
@click.argument("log", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print a JSON document instead of a table.")
@topic_options
@handle_errors
def info(log: Path, as_json: bool, **topic_names: str) -> None:
    """Show a log's topics, types, counts, duration and rates, and which estimators can run on it.

    \b
    Examples:
      relpoint info sample_logs/figure8.mcap
      relpoint info robot.mcap --points-topic /lidar/landmarks --json
    """
    reader = LogReader(log, topics_from(topic_names))
    available = reader.available_roles()
    role_of = {topic: role for role, topic in reader.topics.roles().items()}
    topics = []
    for topic, item in reader.topic_infos.items():
        role = role_of.get(topic)
        topics.append({
            "topic": topic, "type": item.typename, "count": item.count, "duration_s": round(item.duration_s, 6),
            "rate_hz": None if item.rate_hz is None else round(item.rate_hz, 3),
            "role": role if role and item.typename == ROLE_TYPES[role] else None,
        })  # fmt: skip
    observations = None
    if "points" in available:
        clouds = [r.value for r in reader.records(["points"])]
        counts = [len(cloud) for cloud in clouds]
        frames = sorted({cloud.frame_id for cloud in clouds})
        observations = {
            "topic": reader.topics.points, "frame_ids": frames, "points_mean": round(float(np.mean(counts)), 3),
            "points_min": int(np.min(counts)), "points_max": int(np.max(counts)),
            "skipped": dict(sorted(reader.skipped.items())),
        }  # fmt: skip
    document = {
        "path": str(log),
        "size_bytes": log.stat().st_size,
        "duration_s": round(reader.duration_s(), 6),
        "topics": topics,
        "observations": observations,
        **capabilities(available),
    }
    if as_json:
        click.echo(json.dumps(document, indent=2))
        return
    click.echo(f"{log}  {document['size_bytes'] / 1e6:.2f} MB, {document['duration_s']:.3f} s")
    width = max([len(t["topic"]) for t in topics] + [5])
    type_width = max([len(t["type"]) for t in topics] + [4])
    click.echo(f"  {'topic':<{width}}  {'type':<{type_width}}  {'count':>7}  {'rate Hz':>8}  role")
    for t in topics:
        rate = "-" if t["rate_hz"] is None else f"{t['rate_hz']:.2f}"
        click.echo(f"  {t['topic']:<{width}}  {t['type']:<{type_width}}  {t['count']:>7}  {rate:>8}  {t['role'] or ''}")
    if observations:
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
        state = "can run" if cap["can_run"] else f"cannot run (missing {', '.join(cap['missing'])})"
        extra = f"; uses {', '.join(cap['also_uses'])}" if cap["also_uses"] and cap["can_run"] else ""
        click.echo(f"  {name:<10} {state}{extra}")
    click.echo(f"evaluation: trajectory {'yes' if document['evaluate_trajectory'] else 'no (no ground-truth pose)'}, "
               f"landmarks {'yes' if document['evaluate_landmarks'] else 'no (no ground-truth landmarks)'}")  # fmt: skip
