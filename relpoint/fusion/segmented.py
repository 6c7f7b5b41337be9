"""Algorithm 3's local SLAM loop: a fresh estimator (a new local map) whenever the current one breaks.

Implements Zhang, Milios and Gu, *General Concept of 3D SLAM*, Algorithm 3, lines 1-15, around any
relpoint estimator: each observation is stepped through the current local SLAM; when the features it
matched fall below ``min_matches``, or the modelled position error since the map started passes
``max_position_error``, the local map ends before that iteration and a new estimator starts from it,
at the identity of a new local frame. Every local map thus stays rigid in its own frame: a continuous
run would instead re-associate old landmarks after a gap (a loop closure across the break) and bend
the path inside a "segment", which no rigid transform to the fixes can undo.

Matched features are the observed points that did not start a new feature. An estimator that counts
the features it started (:attr:`~relpoint.estimators.base.Estimator.features_started`, the Relative
Point estimator's ``new_points``) is read from that count; for the others a new feature is a new landmark, i.e. the
map's growth (:func:`.segmentation.matched_counts_from_map_growth`). Map growth would not do for the
Relative Point estimator: a point enters its map only when a group places it, a few iterations
after it was first seen and matched, so the first grouping of a fresh local map (about 20 points at
once) would read as a break and restart the local SLAM every few iterations.

The observation that breaks a local map has already been stepped through it; the landmarks it
started there are cut off (estimators append new landmarks at the end of their map), the updates it
made to existing ones (fewer than ``min_matches`` pairs) stay. When a local map of at least
``min_length`` iterations ends, its estimator's :meth:`~relpoint.estimators.base.Estimator.finish`
runs over its poses, as at the end of ``relpoint run`` (the Relative Point estimator's final
adjustment), and the poses it returns replace them; its wall time is counted in the map's last
iteration. The fixes in the input are collected
for :func:`.fuse.fuse`, not given to the estimators (the local SLAM is the camera's alone, as in the
chapter). Odometry goes to the current estimator, and the last
one held is handed to each new estimator. No file I/O; the CLI (``relpoint fuse --restart``) and the
benchmarks drive it.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from relpoint.errors import EstimatorError
from relpoint.estimators.base import Estimator
from relpoint.fusion.segmentation import NO_SEGMENT
from relpoint.types import IntArray, LandmarkMap, OdometryMeasurement, PointObservation, Pose, PositionFix, Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class SegmentedRun:
    """A local SLAM restarted per segment.

    Attributes
    ----------
    trajectory: pose per iteration, each segment in its own local frame (iterations outside a segment
        hold the pose of the short-lived estimator that saw them).
    landmarks: every kept segment's final map, concatenated in segment order (local frames).
    labels: (N,) segment per iteration, -1 for none.
    landmark_labels: (M,) segment of each landmark.
    matched: (N,) matched features per iteration (0 on a local map's first iteration).
    observed: (N,) points observed per iteration.
    map_size: (N,) landmarks in the current local map after each iteration.
    seconds: (N,) wall time of each step.
    fixes: the position fixes found in the input.
    """

    trajectory: Trajectory
    landmarks: LandmarkMap
    labels: IntArray
    landmark_labels: IntArray
    matched: IntArray
    observed: IntArray
    map_size: IntArray
    seconds: np.ndarray
    fixes: list[PositionFix]


def run_segmented(
    inputs: Iterable[object],
    make_estimator: Callable[[], Estimator],
    *,
    min_matches: int = 5,
    min_length: int = 4,
    max_position_error: float = math.inf,
    local_sigma: float = 0.1,
    drift_fraction: float = 0.01,
) -> SegmentedRun:
    """Run a local SLAM over time-ordered ``inputs``, starting a new one at every break (see the module).

    ``make_estimator()`` returns a fresh estimator. Local maps shorter than ``min_length`` iterations
    are dropped (their iterations labelled -1).

    Raises
    ------
    EstimatorError
        The input holds no observation.
    """
    poses: list[Pose] = []
    labels: list[int] = []
    matched: list[int] = []
    observed: list[int] = []
    map_size: list[int] = []
    seconds: list[float] = []
    fixes: list[PositionFix] = []
    maps: list[LandmarkMap] = []
    estimator: Estimator | None = None
    odometry: OdometryMeasurement | None = None
    segment = -1  # provisional label of the current local map
    first = 0  # index in ``poses`` of the current local map's first iteration
    length = 0
    travelled = 0.0

    def close(rows: int | None = None, breaking: Pose | None = None) -> None:
        """End the current local map: finish its estimator over its poses (and ``breaking``, the pose it
        gave the observation that broke it, which the next map takes); ``rows``: keep only its first
        rows (those before the breaking step)."""
        if estimator is None:
            return
        if length < min_length:
            maps.append(LandmarkMap.empty())
            return
        start = time.perf_counter()
        own = poses[first:] + ([breaking] if breaking is not None else [])
        finished = estimator.finish(Trajectory.from_poses(own))
        poses[first:] = [
            Pose(int(stamp), tuple(position), tuple(quat))  # type: ignore[arg-type]
            for stamp, position, quat in zip(
                finished.stamps_ns[:length].tolist(), finished.positions[:length].tolist(),
                finished.quats_xyzw[:length].tolist(), strict=True,
            )
        ]  # fmt: skip
        seconds[-1] += time.perf_counter() - start
        final = estimator.landmark_map()
        keep = np.arange(len(final) if rows is None else min(rows, len(final)))
        maps.append(
            LandmarkMap(final.positions[keep], final.observations[keep], final.dynamic[keep], final.gt_id[keep])
        )

    for item in inputs:
        if isinstance(item, PositionFix):
            fixes.append(item)
            continue
        if isinstance(item, OdometryMeasurement):
            odometry = item
            if estimator is not None:
                estimator.add_odometry(item)
            continue
        if not isinstance(item, PointObservation):
            continue
        start = time.perf_counter()
        restart = estimator is None
        size_before = 0
        if estimator is not None:
            size_before = estimator.map_size
            started_before = estimator.features_started
            pose = estimator.step(item)
            started_after = estimator.features_started
            if started_before is not None and started_after is not None:
                pairs = len(item) - max(started_after - started_before, 0)
            else:
                pairs = len(item) - max(estimator.map_size - size_before, 0)
            travelled += float(np.linalg.norm(np.subtract(pose.position, poses[-1].position)))
            error = local_sigma + drift_fraction * travelled
            restart = pairs < min_matches or error > max_position_error
        if restart:
            # the breaking observation's new landmarks belong to the next map
            close(size_before, pose if estimator is not None else None)
            estimator = make_estimator()
            if odometry is not None:
                estimator.add_odometry(odometry)
            pose = estimator.step(item)
            pairs = 0
            segment += 1
            first = len(poses)
            length = 0
            travelled = 0.0
        assert estimator is not None
        seconds.append(time.perf_counter() - start)
        if poses and pose.stamp_ns <= poses[-1].stamp_ns:
            raise EstimatorError(f"{estimator.name} returned a pose out of time order at {pose.stamp_ns} ns")
        poses.append(pose)
        labels.append(segment)
        length += 1
        matched.append(pairs)
        observed.append(len(item))
        map_size.append(estimator.map_size)
    if not poses:
        raise EstimatorError("the log holds no observation to run on")
    close()

    # Keep local maps of at least min_length iterations, renumbered 0, 1, ... in time order.
    raw = np.asarray(labels, dtype=np.int64)
    counts = np.bincount(raw, minlength=len(maps))
    keep = np.flatnonzero(counts >= min_length)
    renumber = np.full(len(maps), NO_SEGMENT, dtype=np.int64)
    renumber[keep] = np.arange(len(keep))
    kept = [maps[i] for i in keep]
    landmarks = LandmarkMap.concatenate(kept)
    landmark_labels = np.concatenate([np.full(len(m), i, dtype=np.int64) for i, m in enumerate(kept)] or [[]])
    log.info("local SLAM restarted %d times; %d local maps kept", len(maps) - 1, len(kept))
    return SegmentedRun(
        trajectory=Trajectory.from_poses(poses),
        landmarks=landmarks,
        labels=renumber[raw],
        landmark_labels=landmark_labels.astype(np.int64),
        matched=np.asarray(matched, dtype=np.int64),
        observed=np.asarray(observed, dtype=np.int64),
        map_size=np.asarray(map_size, dtype=np.int64),
        seconds=np.asarray(seconds, dtype=np.float64),
        fixes=fixes,
    )
