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
adjustment), and the poses it returns replace them. The fixes in the input are collected for
:func:`.fuse.fuse`, not given to the estimators (the local SLAM is the camera's alone, as in the
chapter). Odometry goes to the current estimator, and the last one held is handed to each new
estimator.

The loop is an estimator itself, :class:`RestartingEstimator`, so the one drive loop
(:func:`relpoint.pipeline.run`) runs it as it runs any other: input screening, timing, the final
:meth:`~RestartingEstimator.finish` that finishes the last local map. No file I/O; the application
layer (``relpoint fuse --restart``) and the benchmarks drive it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from relpoint import pipeline
from relpoint.errors import UsageError
from relpoint.estimators.base import Estimator
from relpoint.fusion.segmentation import NO_SEGMENT
from relpoint.types import (
    IntArray,
    LandmarkMap,
    OdometryMeasurement,
    PointObservation,
    Pose,
    PositionFix,
    RunResult,
    Trajectory,
)

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


@dataclass(frozen=True)
class RestartRule:
    """When a local map ends (see the module): fewer than ``min_matches`` matched features, or a
    modelled position error ``local_sigma + drift_fraction * travelled`` (m) above
    ``max_position_error``. Local maps shorter than ``min_length`` iterations are dropped."""

    min_matches: int = 5
    min_length: int = 4
    max_position_error: float = math.inf
    local_sigma: float = 0.1
    drift_fraction: float = 0.01


class RestartingEstimator(Estimator[PointObservation]):
    """A local SLAM that starts a fresh estimator (a new local map) at every break; see the module.

    ``make_estimator()`` returns a fresh point estimator. After the run (:meth:`finish`),
    :meth:`landmark_map` holds every kept local map's final map in its own local frame, concatenated
    in time order, and :meth:`segmented` gives the labels. Local maps shorter than ``min_length``
    iterations are dropped (their iterations labelled -1).
    """

    name = "restarting"

    def __init__(self, make_estimator: Callable[[], Estimator], rule: RestartRule | None = None) -> None:
        self._make = make_estimator
        self.rule = rule or RestartRule()
        self._estimator: Estimator | None = None
        self._odometry: OdometryMeasurement | None = None
        self._poses: list[Pose] = []
        self._labels: list[int] = []
        self._matched: list[int] = []
        self._maps: list[LandmarkMap] = []
        self._fixes: list[PositionFix] = []
        self._segment = -1  # provisional label of the current local map
        self._first = 0  # index in ``_poses`` of the current local map's first iteration
        self._length = 0
        self._travelled = 0.0
        self._final: LandmarkMap | None = None

    @property
    def estimator_name(self) -> str:
        """The name of the estimator restarted (known once the first one is made)."""
        return self._estimator.name if self._estimator is not None else self.name

    def prepare(self) -> None:
        self._make().prepare()  # compiled code is shared: a throwaway instance warms it

    def add_odometry(self, odometry: OdometryMeasurement) -> None:
        self._odometry = odometry
        if self._estimator is not None:
            self._estimator.add_odometry(odometry)

    def add_fix(self, fix: PositionFix) -> None:
        self._fixes.append(fix)

    def step(self, observation: PointObservation) -> Pose:
        if not isinstance(observation, PointObservation):
            raise UsageError("a restarting local SLAM runs point estimators only, not depth frames")
        estimator = self._estimator
        restart = estimator is None
        size_before = 0
        pairs = 0
        pose: Pose | None = None
        if estimator is not None:
            size_before = estimator.map_size
            started_before = estimator.features_started
            pose = estimator.step(observation)
            started_after = estimator.features_started
            if started_before is not None and started_after is not None:
                pairs = len(observation) - max(started_after - started_before, 0)
            else:
                pairs = len(observation) - max(estimator.map_size - size_before, 0)
            self._travelled += float(np.linalg.norm(np.subtract(pose.position, self._poses[-1].position)))
            error = self.rule.local_sigma + self.rule.drift_fraction * self._travelled
            restart = pairs < self.rule.min_matches or error > self.rule.max_position_error
        if restart:
            # the breaking observation's new landmarks belong to the next map
            self._close(size_before, pose)
            estimator = self._estimator = self._make()
            if self._odometry is not None:
                estimator.add_odometry(self._odometry)
            pose = estimator.step(observation)
            pairs = 0
            self._segment += 1
            self._first = len(self._poses)
            self._length = 0
            self._travelled = 0.0
        assert pose is not None
        self._poses.append(pose)
        self._labels.append(self._segment)
        self._length += 1
        self._matched.append(pairs)
        return pose

    def _close(self, rows: int | None = None, breaking: Pose | None = None) -> None:
        """End the current local map: finish its estimator over its poses (and ``breaking``, the pose it
        gave the observation that broke it, which the next map takes); ``rows``: keep only its first
        rows (those before the breaking step)."""
        estimator = self._estimator
        if estimator is None:
            return
        if self._length < self.rule.min_length:
            self._maps.append(LandmarkMap.empty())
            return
        own = self._poses[self._first :] + ([breaking] if breaking is not None else [])
        finished = estimator.finish(Trajectory.from_poses(own))
        length = self._length
        self._poses[self._first :] = [
            Pose(int(stamp), tuple(position), tuple(quat))  # type: ignore[arg-type]
            for stamp, position, quat in zip(
                finished.stamps_ns[:length].tolist(), finished.positions[:length].tolist(),
                finished.quats_xyzw[:length].tolist(), strict=True,
            )
        ]  # fmt: skip
        final = estimator.landmark_map()
        keep = np.arange(len(final) if rows is None else min(rows, len(final)))
        self._maps.append(
            LandmarkMap(final.positions[keep], final.observations[keep], final.dynamic[keep], final.gt_id[keep])
        )

    def finish(self, trajectory: Trajectory) -> Trajectory:
        """Finish the last local map; the poses with every kept local map's finished ones in place."""
        if len(trajectory) != len(self._poses):
            raise ValueError(f"finish() got {len(trajectory)} poses for {len(self._poses)} iterations")
        self._close()
        kept = [self._maps[i] for i in self._kept_segments()]
        self._final = LandmarkMap.concatenate(kept)
        log.info("local SLAM restarted %d times; %d local maps kept", len(self._maps) - 1, len(kept))
        return Trajectory.from_poses(self._poses)

    def _kept_segments(self) -> IntArray:
        counts = np.bincount(np.asarray(self._labels, dtype=np.int64), minlength=len(self._maps))
        return np.flatnonzero(counts >= self.rule.min_length)

    def landmark_map(self) -> LandmarkMap:
        """Before :meth:`finish`, the current local map; after it, every kept one (local frames)."""
        if self._final is not None:
            return self._final
        return self._estimator.landmark_map() if self._estimator is not None else LandmarkMap.empty()

    @property
    def map_size(self) -> int:
        """Landmarks in the current local map."""
        return self._estimator.map_size if self._estimator is not None else 0

    def summary(self) -> dict[str, int]:
        return {"local_maps": len(self._maps), "local_maps_kept": len(self._kept_segments())}

    def segmented(self, result: RunResult) -> SegmentedRun:
        """The run :func:`relpoint.pipeline.run` made with this estimator, with its segments."""
        raw = np.asarray(self._labels, dtype=np.int64)
        keep = self._kept_segments()
        renumber = np.full(len(self._maps), NO_SEGMENT, dtype=np.int64)
        renumber[keep] = np.arange(len(keep))
        sizes = [len(self._maps[i]) for i in keep]
        landmark_labels = np.repeat(np.arange(len(keep), dtype=np.int64), sizes)
        return SegmentedRun(
            trajectory=result.trajectory,
            landmarks=result.landmarks,
            labels=renumber[raw],
            landmark_labels=landmark_labels,
            matched=np.asarray(self._matched, dtype=np.int64),
            observed=result.observed,
            map_size=result.map_size,
            seconds=result.seconds,
            fixes=list(self._fixes),
        )


def run_segmented(
    inputs: Iterable[object], make_estimator: Callable[[], Estimator], **rule: Any
) -> SegmentedRun:
    """Run a local SLAM over time-ordered ``inputs``, starting a new one at every break (see the module),
    through the one drive loop, :func:`relpoint.pipeline.run`; ``rule`` holds :class:`RestartRule`'s
    fields.

    Raises
    ------
    EstimatorError
        The input holds no observation.
    """
    restarting = RestartingEstimator(make_estimator, RestartRule(**rule))
    result = pipeline.run(inputs, restarting)  # type: ignore[arg-type]
    return restarting.segmented(result)
