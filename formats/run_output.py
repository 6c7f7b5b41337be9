"""The output directory of ``relpoint run`` (``docs/log-format.md``), written as one atomic unit.

Everything is first written into a temporary directory beside the target, which replaces the target
only when every file is complete, so an interrupted or failed run leaves no partial output.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from formats import ros2
from formats.atomic import atomic_directory, write_text
from formats.log import LogWriter
from formats.ply import landmark_vertices, write_ply
from formats.rgbd_log import dense_map_vertices
from formats.tables import write_map_csv, write_map_history_csv, write_timing_csv, write_trajectory_csv
from formats.trajectory_files import write_tum
from relpoint.pipeline import RunResult
from relpoint.types import Pose

RUN_FILES = ("trajectory.tum", "trajectory.csv", "map.ply", "map.csv", "timing.csv", "run.json", "result.mcap")


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_result_mcap(path: Path, result: RunResult, frame_id: str = "sensor") -> None:
    """``/relpoint/pose`` and ``/tf`` (world -> sensor) per iteration, ``/relpoint/map`` at the end."""
    trajectory = result.trajectory
    with LogWriter(path) as writer:
        for stamp, position, quat in zip(
            trajectory.stamps_ns.tolist(), trajectory.positions, trajectory.quats_xyzw, strict=True
        ):
            pose = Pose(stamp, tuple(position.tolist()), tuple(quat.tolist()))  # type: ignore[arg-type]
            writer.write("/relpoint/pose", ros2.POSE_STAMPED, ros2.pose_to_msg(pose), stamp)
            writer.write("/tf", ros2.TF_MESSAGE, ros2.tf_to_msg(stamp, "world", frame_id, position, quat), stamp)
        landmarks = result.landmarks
        columns = {
            "x": landmarks.positions[:, 0].astype(np.float32),
            "y": landmarks.positions[:, 1].astype(np.float32),
            "z": landmarks.positions[:, 2].astype(np.float32),
            "observations": landmarks.observations.astype(np.int32),
            "dynamic": landmarks.dynamic.astype(np.uint8),
            "gt_id": landmarks.gt_id.astype(np.int32),
        }
        last = int(trajectory.stamps_ns[-1])
        writer.write("/relpoint/map", ros2.POINT_CLOUD2, ros2.point_cloud2(last, "world", columns), last)


def write_run_directory(out_dir: str | os.PathLike[str], result: RunResult, run_info: dict[str, Any]) -> Path:
    """Write every file of a run's output directory atomically; returns the directory.

    ``run_info`` holds what run.json records besides the summary (estimator, parameters, input log,
    version); the timing figures go under its ``timing`` key so that comparisons can drop them.
    """
    out_dir = Path(out_dir)
    with atomic_directory(out_dir) as tmp:
        write_tum(tmp / "trajectory.tum", result.trajectory)
        write_trajectory_csv(tmp / "trajectory.csv", result.trajectory)
        if result.dense_map is not None:
            vertices = dense_map_vertices(*result.dense_map)
            write_ply(
                tmp / "map.ply", vertices, comments=["relpoint dense map: points, normals, colours, weights; world"]
            )
        else:
            write_ply(
                tmp / "map.ply", landmark_vertices(result.landmarks), comments=["relpoint landmark map, frame world"]
            )
        write_map_csv(tmp / "map.csv", result.landmarks)
        write_timing_csv(tmp / "timing.csv", result.observed, result.map_size, result.seconds)
        if result.map_history:
            write_map_history_csv(tmp / "map_history.csv", result.map_history)
        write_result_mcap(tmp / "result.mcap", result)
        document = {
            **run_info,
            "summary": {
                "iterations": len(result.trajectory),
                "landmarks": len(result.landmarks),
                "dynamic_landmarks": int(result.landmarks.dynamic.sum()),
                "observed_mean": float(result.observed.mean()) if len(result.observed) else 0.0,
                **({"map_points": len(result.dense_map[0])} if result.dense_map is not None else {}),
                **result.summary,
            },
            "timing": result.timing_summary(),
        }
        write_text(tmp / "run.json", json.dumps(document, indent=2, sort_keys=True) + "\n")
    return out_dir
