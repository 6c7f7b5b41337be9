"""The library call under ``relpoint run``: drive an estimator over a log's decoded records.

The loop is the same for every estimator: odometry and fixes are handed over as they arrive, each
observation is one iteration (``Estimator.step``), and the pose, the number of observed points, the
map size and the step's wall time are recorded per iteration. No file I/O happens here; the
records come from any iterable (``formats.log.LogReader.records`` in the CLI, a simulation in tests).
"""

from __future__ import annotations

import logging
import math
import time
from array import array
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from relpoint.errors import EstimatorError, InputError
from relpoint.estimators.base import Estimator
from relpoint.screening import InputScreen
from relpoint.types import (
    DepthFrame,
    LandmarkMap,
    MapSnapshot,
    OdometryMeasurement,
    PointObservation,
    Pose,
    PositionFix,
    RunResult,
    Trajectory,
)

log = logging.getLogger(__name__)

#: What the pipeline accepts from a record stream.
Input = PointObservation | DepthFrame | OdometryMeasurement | PositionFix

#: Points a 6-DoF pose needs from one observation (three, not on one line).
MIN_POSE_POINTS = 3
#: From this share of iterations with fewer points, and nothing else to carry the pose (no odometry, no
#: fix), a run warns that its path is the motion model's guess. Measured: the simulator's figure eight
#: with 1.6 and 2.5 points an iteration (87 % and 55 % of them under three) gave the EKF 72 and 6.9 m
#: ATE, FastSLAM 121 and 195 m, without a word; Starry Night has 36 % under three, and odometry.
UNDERDETERMINED_SHARE = 0.25


#: Most map snapshots a run keeps for its timeline (``result.mcap``); the spacing doubles to stay below.
MAX_TIMELINE = 64

#: Most points a dense map snapshot keeps (an even subsample); the final map is always whole.
MAX_SNAPSHOT_POINTS = 100_000

#: How many times the scene's extent (:class:`SceneExtent`) a pose may lie from the origin. A path
#: covers a million times its sensor's range only after, say, 35,000 km with a 35 m lidar; a filter
#: whose numerics have come apart places its pose at 1e9 to 1e78 m, finite but absurd.
ABSURD_EXTENTS = 1e6


class SceneExtent:
    """The scene's size so far (m): the farthest observed point from its sensor and the farthest fix from
    the origin (a fix in an Earth-centred frame places the whole run millions of metres out), at least 1 m."""

    def __init__(self) -> None:
        self.metres = 1.0

    def observe(self, item: PointObservation | DepthFrame) -> None:
        if isinstance(item, PointObservation):
            points = item.points
            reach = math.sqrt(float(np.einsum("ij,ij->i", points, points).max())) if len(points) else 0.0
        else:  # the farthest depth along the image's widest ray
            k = item.intrinsics
            reach = float(item.depth.max(initial=0.0)) * math.hypot(1.0, k.width / k.fx, k.height / k.fy)
        self.metres = max(self.metres, reach)

    def fix(self, fix: PositionFix) -> None:
        self.metres = max(self.metres, float(np.linalg.norm(fix.position)))

    def holds(self, position: Sequence[float]) -> bool:
        """Whether one position (m) lies within :data:`ABSURD_EXTENTS` times the extent (the loop's
        cheap test; :meth:`check` says what went wrong)."""
        x, y, z = position
        return bool(math.sqrt(x * x + y * y + z * z) <= ABSURD_EXTENTS * self.metres)

    def check(self, name: str, positions: np.ndarray, stamps_ns: np.ndarray, when: str) -> None:
        """Raise :class:`EstimatorError` if any of ``positions`` (K, 3) lies more than
        :data:`ABSURD_EXTENTS` times the extent from the origin; ``when`` says at what stage."""
        distances = np.linalg.norm(positions, axis=1)
        beyond = np.flatnonzero(~(distances <= ABSURD_EXTENTS * self.metres))
        if not len(beyond):
            return
        k = int(beyond[0])
        raise EstimatorError(
            f"{name} broke down numerically: {when} it placed the pose at {stamps_ns[k]} ns {distances[k]:.3g} m "
            f"from the origin, {distances[k] / self.metres:.1g} times the scene's extent ({self.metres:.3g} m: the "
            "farthest observed point and fix)",
            "no result is written; try another estimator, or run without the fixes or odometry to find the input "
            "that breaks it",
        )


def _snapshot(estimator: Estimator, stamp_ns: int) -> MapSnapshot:
    dense = estimator.dense_map()
    if dense is not None:
        positions = dense[0][:: max(1, -(-len(dense[0]) // MAX_SNAPSHOT_POINTS))]
        return MapSnapshot(stamp_ns, positions.astype(np.float32), np.zeros(len(positions), dtype=bool))
    landmarks = estimator.landmark_map()
    return MapSnapshot(stamp_ns, landmarks.positions.astype(np.float32), landmarks.dynamic.copy())


def run(
    inputs: Iterable[Input],
    estimator: Estimator,
    *,
    on_iteration: Callable[[int, Pose], None] | None = None,
    on_finish: Callable[[str], None] | None = None,
    map_every: int = 0,
    skipped_before: Mapping[str, int] | None = None,
) -> RunResult:
    """Run ``estimator`` over ``inputs`` (time-ordered) and collect its results.

    ``on_finish`` is called once after the last iteration, before the estimator's
    :meth:`~relpoint.estimators.base.Estimator.finish` (which may take a while), with what it does
    (:attr:`~relpoint.estimators.base.Estimator.finishing`).

    With ``map_every`` > 0 the landmark map is also recorded every that many iterations and after the
    last one (for landmark error over time, the paper's Fig. 8).

    ``skipped_before`` counts what was dropped before ``inputs`` (a reader's unusable messages, read
    when the stream is exhausted): when nothing usable is left, the run is an :class:`InputError`
    naming every count, not an estimator failure.

    Raises :class:`InputError` if every observation was unusable, :class:`EstimatorError` if the
    stream holds no observation at all.
    """
    # Compact per-iteration buffers (8 bytes a number): a 40-pass run keeps about 3 MB of trajectory.
    stamps = array("q")
    positions = array("d")
    quats = array("d")
    observed = array("q")
    map_size = array("q")
    seconds = array("d")
    snapshots: list[tuple[int, int, LandmarkMap]] = []
    timeline: list[MapSnapshot] = []
    timeline_every = 4
    screen = InputScreen()
    extent = SceneExtent()
    failed = 0
    start = time.perf_counter()
    estimator.prepare()
    seconds_prepare = time.perf_counter() - start
    if seconds_prepare > 1.0:
        log.warning("%s: %.1f s compiling or loading its compiled code before the first iteration "
                    "(not in the per-iteration times)", estimator.name, seconds_prepare)  # fmt: skip
    aided = False  # odometry or a fix reached the estimator
    few_points = 0  # point observations of fewer than MIN_POSE_POINTS points (all of them: warned otherwise)
    for item in inputs:
        if isinstance(item, OdometryMeasurement):
            if (odometry := screen.odometry(item)) is not None:
                aided = True
                estimator.add_odometry(odometry)
        elif isinstance(item, PositionFix):
            if (fix := screen.fix(item)) is not None:
                aided = True
                extent.fix(fix)
                estimator.add_fix(fix)
        elif isinstance(item, PointObservation | DepthFrame):
            if isinstance(item, PointObservation):
                item = screen.points(item)
                few_points += len(item.points) < MIN_POSE_POINTS
            elif (item := screen.depth(item)) is None:
                continue
            extent.observe(item)
            start = time.perf_counter()
            try:
                pose = estimator.step(item)
            except (np.linalg.LinAlgError, FloatingPointError) as error:
                # A singular system at this iteration: skip it, keep the estimator's state, go on.
                failed += 1
                if failed == 1:
                    log.warning("%s: iteration at %d ns skipped, its numerics failed (%s); further ones are "
                                "counted in run.json", estimator.name, item.stamp_ns, error)  # fmt: skip
                continue
            seconds.append(time.perf_counter() - start)
            if not (all(math.isfinite(v) for v in pose.position) and all(math.isfinite(v) for v in pose.quat_xyzw)):
                raise EstimatorError(
                    f"{estimator.name} lost its pose at {pose.stamp_ns} ns (not finite) after {len(stamps)} iterations",
                    "check the log's stamps and values, or try another estimator",
                )
            if not extent.holds(pose.position):
                extent.check(estimator.name, np.array([pose.position]), np.array([pose.stamp_ns]), "in the loop")
            if stamps and pose.stamp_ns <= stamps[-1]:
                raise EstimatorError(f"{estimator.name} returned a pose out of time order at {pose.stamp_ns} ns")
            stamps.append(pose.stamp_ns)
            positions.extend(pose.position)
            quats.extend(pose.quat_xyzw)
            observed.append(len(item.points) if isinstance(item, PointObservation) else int((item.depth > 0).sum()))
            map_size.append(estimator.map_size)
            if map_every > 0 and len(stamps) % map_every == 0:
                snapshots.append((len(stamps) - 1, pose.stamp_ns, estimator.landmark_map()))
            if len(stamps) % timeline_every == 0:
                timeline.append(_snapshot(estimator, pose.stamp_ns))
                if len(timeline) > MAX_TIMELINE:  # keep every other one and take them half as often
                    timeline, timeline_every = timeline[1::2], 2 * timeline_every
            if on_iteration is not None:
                on_iteration(len(stamps) - 1, pose)
    replayed = int(getattr(estimator, "replayed_steps", 0) or 0)
    if 1 < replayed <= len(seconds) and not failed:
        # An estimator that held its first iterations back (to learn the noise) did their work at the last
        # of them: each is given its share, so that the median per iteration is not that of idle calls.
        seconds[:replayed] = array("d", [sum(seconds[:replayed]) / replayed] * replayed)
    skipped = dict(screen.skipped)
    if failed:
        skipped["iterations: numerics failed (skipped)"] = failed
    if not stamps:
        if failed:
            raise EstimatorError(f"{estimator.name} could not compute any of the log's {failed} iterations",
                                 "check the log's stamps and values, or try another estimator")  # fmt: skip
        dropped = Counter(skipped_before or {}) + screen.skipped
        if dropped:
            counts = ", ".join(f"{n} {kind}" for kind, n in sorted(dropped.items()))
            raise InputError(f"the log holds no usable message ({counts})",
                             "check the topics' message types and the log format's limits")  # fmt: skip
        raise EstimatorError("the log holds no observation to run on")
    # Every iteration ran on nothing: no usable point in the whole log. A depth estimator says so itself
    # when it finishes, naming the depths it saw (EstimatorError, exit 4).
    if not any(observed) and not isinstance(item, DepthFrame):
        dropped = Counter(skipped_before or {}) + screen.skipped
        counts = ", ".join(f"{n} {kind}" for kind, n in sorted(dropped.items())) or "every observation is empty"
        raise InputError(f"the log holds no usable point in its {len(stamps)} observations ({counts})",
                         "check the points topic's fields and values, and the log format's limits")  # fmt: skip
    if on_finish is not None:
        on_finish(estimator.finishing)
    start = time.perf_counter()
    trajectory = estimator.finish(
        Trajectory(
            np.frombuffer(stamps, dtype=np.int64),
            np.frombuffer(positions, dtype=np.float64).reshape(-1, 3),
            np.frombuffer(quats, dtype=np.float64).reshape(-1, 4),
        )
    )
    seconds_finish = time.perf_counter() - start
    if not np.all(np.isfinite(trajectory.positions)):
        raise EstimatorError(f"{estimator.name} lost its trajectory when finishing it (not finite)",
                             "check the log's stamps and values, or try another estimator")  # fmt: skip
    extent.check(estimator.name, trajectory.positions, trajectory.stamps_ns, "finishing its trajectory,")
    landmarks = estimator.landmark_map()
    if map_every > 0:
        # The last snapshot is the final map (after any final adjustment).
        if snapshots and snapshots[-1][0] == len(stamps) - 1:
            snapshots.pop()
        snapshots.append((len(stamps) - 1, stamps[-1], landmarks))
    dense_map = estimator.dense_map()
    summary = estimator.summary()
    warnings = _result_warnings(estimator.name, len(stamps), failed, len(landmarks), dense_map, observed)
    if summary.get("lost_frames"):
        warnings.append(f"{estimator.name} lost tracking in {summary['lost_frames']} of {len(stamps)} frames "
                        "(each held at the last pose and not fused)")  # fmt: skip
    warnings.extend(estimator.run_warnings())
    if (
        not aided and stamps and UNDERDETERMINED_SHARE * len(stamps) <= few_points < len(stamps)
        and not getattr(estimator, "reports_unlocated", False)
    ):  # fmt: skip
        warnings.append(
            f"{estimator.name}: {few_points} of {len(stamps)} iterations saw fewer than {MIN_POSE_POINTS} points and the "
            "log has no odometry or fix: a pose cannot be fixed from so few, so the path there is the motion "
            "model's guess and may be far off; odometry, fixes or more points per frame would help"
        )
    if summary.get("association_collapsed"):
        warnings.append(f"{estimator.name}: the association collapsed in {summary['association_collapsed']} of "
                        f"{len(stamps)} iterations (the map may hold duplicates from there)")  # fmt: skip
    for warning in warnings:
        log.warning("%s", warning)
    return RunResult(
        trajectory=trajectory,
        landmarks=landmarks,
        observed=np.asarray(observed, dtype=np.int64),
        map_size=np.asarray(map_size, dtype=np.int64),
        seconds=np.asarray(seconds, dtype=np.float64),
        summary=summary,
        map_history=tuple(snapshots),
        dense_map=dense_map,
        seconds_finish=seconds_finish,
        seconds_prepare=seconds_prepare,
        skipped=skipped,
        warnings=tuple(warnings),
        map_timeline=tuple(timeline),
    )


def _result_warnings(
    name: str, iterations: int, failed: int, landmarks: int, dense_map: tuple[np.ndarray, ...] | None, observed: Any
) -> list[str]:
    """What makes a finished run doubtful: no map at all, or most iterations failed or unobserved."""
    warnings = []
    if dense_map is None and landmarks == 0:
        warnings.append(
            f"{name} mapped no landmark in {iterations} iterations; the trajectory is not anchored to a map"
        )
    if dense_map is not None and len(dense_map[0]) == 0:
        warnings.append(f"{name} fused no map point in {iterations} frames")
    if failed and failed >= iterations:
        warnings.append(f"{name}: {failed} of {iterations + failed} iterations failed numerically")
    empty = sum(1 for n in observed if n < 3)
    if iterations and empty >= iterations:
        warnings.append(
            f"every one of the {iterations} iterations observed fewer than 3 points: nothing to locate with"
        )
    return warnings
