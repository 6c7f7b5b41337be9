"""The output directory of ``relpoint run`` (``docs/log-format.md``), written as one atomic unit.

Everything is first written into a temporary directory beside the target, which replaces the target
only when every file is complete, so an interrupted or failed run leaves no partial output.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from formats import ros2
from formats.atomic import atomic_directory, write_text
from formats.log import LogWriter
from formats.outputs import json_text
from formats.ply import landmark_vertices, stored_coordinates, write_ply
from formats.rgbd_log import dense_map_vertices
from formats.tables import write_map_csv, write_map_history_csv, write_timing_csv, write_trajectory_csv
from formats.trajectory_files import write_tum
from relpoint.geometry import apply_transform
from relpoint.types import PointObservation, Pose, RunResult, Trajectory

#: Most intermediate ``/relpoint/path`` messages, and most poses in each (an even subsample); the
#: last message holds every pose.
PATH_MESSAGES = 50
PATH_POSES = 2000

#: Colours of the map in Foxglove (packed ``rgb`` field): static landmarks, dynamic ones.
STATIC_RGB = (90, 160, 255)
DYNAMIC_RGB = (255, 60, 40)


def _packed_rgb(dynamic: np.ndarray) -> np.ndarray:
    """float32 ``rgb`` values (the PCL packing Foxglove and RViz read) for static and dynamic points."""
    colours = np.where(dynamic[:, None], DYNAMIC_RGB, STATIC_RGB).astype(np.uint32)
    packed = (colours[:, 0] << 16) | (colours[:, 1] << 8) | colours[:, 2]
    return packed.astype(np.uint32).view(np.float32)


def _xyz_columns(positions: np.ndarray) -> dict[str, np.ndarray]:
    """FLOAT32 x, y, z fields, FLOAT64 far from the origin (:func:`formats.ply.stored_coordinates`)."""
    xyz = stored_coordinates(positions)
    return {axis: xyz[:, i] for i, axis in enumerate("xyz")}


def _map_columns(positions: np.ndarray, dynamic: np.ndarray) -> dict[str, np.ndarray]:
    return {
        **_xyz_columns(positions),
        "rgb": _packed_rgb(dynamic),
        "dynamic": dynamic.astype(np.uint8),
    }


def _subsampled(trajectory: Trajectory, end: int, most: int) -> Trajectory:
    """The first ``end`` poses, evenly thinned to at most ``most`` (the last always kept)."""
    index = np.unique(np.append(np.arange(0, end, max(1, -(-end // most))), end - 1))
    return Trajectory(trajectory.stamps_ns[index], trajectory.positions[index], trajectory.quats_xyzw[index])


def write_result_mcap(
    path: Path,
    result: RunResult,
    frame_id: str = "sensor",
    *,
    observations: Iterable[PointObservation] = (),
    reference: Trajectory | None = None,
) -> None:
    """The run for Foxglove and ``ros2 bag``, all in ``world``.

    - ``/relpoint/pose`` (PoseStamped) and ``/tf`` (world -> ``frame_id``) at every iteration;
    - ``/relpoint/path`` (nav_msgs/Path): the path so far, :data:`PATH_MESSAGES` times over the run
      and whole at the end; ``/relpoint/reference_path``: the ``reference`` (ground truth) at the start;
    - ``/relpoint/observations`` (PointCloud2): each iteration's ``observations`` moved into ``world``
      with the estimated pose of its stamp;
    - ``/relpoint/map`` (PointCloud2, ``rgb`` blue static, red dynamic): the map as it grew (the run's
      timeline) and the final map, with ``observations`` and ``gt_id`` fields for landmarks, or the
      dense map's colours.
    """
    trajectory = result.trajectory
    stamps = trajectory.stamps_ns
    rotations = trajectory.matrices()
    path_every = max(1, -(-len(stamps) // PATH_MESSAGES))
    timeline = {snapshot.stamp_ns: snapshot for snapshot in result.map_timeline}
    observation_stream = iter(observations)
    pending = next(observation_stream, None)
    with LogWriter(path) as writer:
        if reference is not None and len(reference):
            first = int(min(stamps[0], reference.stamps_ns[0]))
            writer.write("/relpoint/reference_path", ros2.PATH, ros2.path_to_msg(first, reference), first)
        for k, (stamp, position, quat) in enumerate(
            zip(stamps.tolist(), trajectory.positions, trajectory.quats_xyzw, strict=True)
        ):
            pose = Pose(stamp, tuple(position.tolist()), tuple(quat.tolist()))  # type: ignore[arg-type]
            writer.write("/relpoint/pose", ros2.POSE_STAMPED, ros2.pose_to_msg(pose), stamp)
            writer.write("/tf", ros2.TF_MESSAGE, ros2.tf_to_msg(stamp, "world", frame_id, position, quat), stamp)
            while pending is not None and pending.stamp_ns <= stamp:
                if pending.stamp_ns == stamp and len(pending.points):
                    T = rotations[k]
                    world = apply_transform(T, pending.points)
                    columns = _xyz_columns(world)
                    if pending.ids is not None:
                        columns["id"] = pending.ids.astype(np.int32)
                    writer.write("/relpoint/observations", ros2.POINT_CLOUD2,
                                 ros2.point_cloud2(stamp, "world", columns), stamp)  # fmt: skip
                pending = next(observation_stream, None)
            if (k + 1) % path_every == 0 and k + 1 < len(stamps):
                writer.write("/relpoint/path", ros2.PATH, ros2.path_to_msg(stamp, _subsampled(trajectory, k + 1, PATH_POSES)), stamp)
            snapshot = timeline.get(stamp)
            if snapshot is not None and k + 1 < len(stamps):
                writer.write("/relpoint/map", ros2.POINT_CLOUD2,
                             ros2.point_cloud2(stamp, "world", _map_columns(snapshot.positions, snapshot.dynamic)),
                             stamp)  # fmt: skip
        last = int(stamps[-1])
        writer.write("/relpoint/path", ros2.PATH, ros2.path_to_msg(last, trajectory), last)
        if result.dense_map is not None:
            positions, _, colours = result.dense_map[:3]
            columns = _map_columns(positions, np.zeros(len(positions), dtype=bool))
            rgb = colours.astype(np.uint32)
            columns["rgb"] = ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).astype(np.uint32).view(np.float32)
        else:
            landmarks = result.landmarks
            columns = _map_columns(landmarks.positions, landmarks.dynamic)
            columns["observations"] = landmarks.observations.astype(np.int32)
            columns["gt_id"] = landmarks.gt_id.astype(np.int32)
        writer.write("/relpoint/map", ros2.POINT_CLOUD2, ros2.point_cloud2(last, "world", columns), last)


def write_run_directory(
    out_dir: str | os.PathLike[str],
    result: RunResult,
    run_info: dict[str, Any],
    *,
    observations: Iterable[PointObservation] = (),
    reference: Trajectory | None = None,
) -> Path:
    """Write every file of a run's output directory atomically; returns the directory.

    ``observations`` (time-ordered) and ``reference`` go to result.mcap (:func:`write_result_mcap`).

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
        write_result_mcap(tmp / "result.mcap", result, observations=observations, reference=reference)
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
        write_text(tmp / "run.json", json_text(document, indent=2, sort_keys=True) + "\n")
    return out_dir
