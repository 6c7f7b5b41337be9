"""The library call under ``relpoint run``: drive an estimator over a log's decoded records.

The loop is the same for every estimator: odometry and fixes are handed over as they arrive, each
observation is one iteration (``Estimator.step``), and the pose, the number of observed points, the
map size and the step's wall time are recorded per iteration. No file I/O happens here; the
records come from any iterable (``formats.log.LogReader.records`` in the CLI, a simulation in tests).
"""

from __future__ import annotations

import logging
import time
from array import array
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from relpoint.errors import EstimatorError
from relpoint.estimators.base import Estimator
from relpoint.types import DepthFrame, LandmarkMap, OdometryMeasurement, PointObservation, Pose, PositionFix, Trajectory

log = logging.getLogger(__name__)

#: What the pipeline accepts from a record stream.
Input = PointObservation | DepthFrame | OdometryMeasurement | PositionFix


@dataclass(frozen=True, eq=False)
class RunResult:
    """Everything ``relpoint run`` writes, in memory.

    Attributes
    ----------
    trajectory: estimated ``T_world_sensor`` per iteration.
    landmarks: the final map.
    observed: (N,) points observed per iteration.
    map_size: (N,) landmarks mapped after each iteration.
    seconds: (N,) wall time of each ``step`` call.
    summary: estimator summary figures (JSON-serialisable).
    seconds_finish: wall time of the estimator's work once the log ended (a final adjustment).
    """

    trajectory: Trajectory
    landmarks: LandmarkMap
    observed: np.ndarray
    map_size: np.ndarray
    seconds: np.ndarray
    summary: dict[str, Any] = field(default_factory=dict)
    map_history: tuple[tuple[int, int, LandmarkMap], ...] = ()
    """Snapshots ``(iteration, stamp_ns, map)`` taken every ``map_every`` iterations and at the end."""
    dense_map: tuple[np.ndarray, ...] | None = None
    """For dense estimators: (positions (M,3) m, normals (M,3), colours (M,3) uint8, weights (M,)) in ``world``."""
    seconds_finish: float = 0.0

    def timing_summary(self) -> dict[str, float]:
        """Mean, median and total wall time per iteration, and the time after the last one, in seconds."""
        if len(self.seconds) == 0:
            return {"iterations": 0, "seconds_total": 0.0, "seconds_mean": 0.0, "seconds_median": 0.0,
                    "seconds_finish": self.seconds_finish}  # fmt: skip
        return {
            "iterations": len(self.seconds),
            "seconds_total": float(self.seconds.sum()),
            "seconds_mean": float(self.seconds.mean()),
            "seconds_median": float(np.median(self.seconds)),
            "seconds_finish": self.seconds_finish,
        }


def run(
    inputs: Iterable[Input],
    estimator: Estimator,
    *,
    on_iteration: Callable[[int, Pose], None] | None = None,
    map_every: int = 0,
) -> RunResult:
    """Run ``estimator`` over ``inputs`` (time-ordered) and collect its results.

    With ``map_every`` > 0 the landmark map is also recorded every that many iterations and after the
    last one (for landmark error over time, the paper's Fig. 8).

    Raises :class:`EstimatorError` if the stream holds no observation at all.
    """
    # Compact per-iteration buffers (8 bytes a number): a 40-pass run keeps about 3 MB of trajectory.
    stamps = array("q")
    positions = array("d")
    quats = array("d")
    observed = array("q")
    map_size = array("q")
    seconds = array("d")
    snapshots: list[tuple[int, int, LandmarkMap]] = []
    for item in inputs:
        if isinstance(item, OdometryMeasurement):
            estimator.add_odometry(item)
        elif isinstance(item, PositionFix):
            estimator.add_fix(item)
        elif isinstance(item, PointObservation | DepthFrame):
            start = time.perf_counter()
            pose = estimator.step(item)
            seconds.append(time.perf_counter() - start)
            if stamps and pose.stamp_ns <= stamps[-1]:
                raise EstimatorError(f"{estimator.name} returned a pose out of time order at {pose.stamp_ns} ns")
            stamps.append(pose.stamp_ns)
            positions.extend(pose.position)
            quats.extend(pose.quat_xyzw)
            observed.append(len(item.points) if isinstance(item, PointObservation) else int((item.depth > 0).sum()))
            map_size.append(estimator.map_size)
            if map_every > 0 and len(stamps) % map_every == 0:
                snapshots.append((len(stamps) - 1, pose.stamp_ns, estimator.landmark_map()))
            if on_iteration is not None:
                on_iteration(len(stamps) - 1, pose)
    if not stamps:
        raise EstimatorError("the log holds no observation to run on")
    start = time.perf_counter()
    trajectory = estimator.finish(
        Trajectory(
            np.frombuffer(stamps, dtype=np.int64),
            np.frombuffer(positions, dtype=np.float64).reshape(-1, 3),
            np.frombuffer(quats, dtype=np.float64).reshape(-1, 4),
        )
    )
    seconds_finish = time.perf_counter() - start
    landmarks = estimator.landmark_map()
    if map_every > 0:
        # The last snapshot is the final map (after any final adjustment).
        if snapshots and snapshots[-1][0] == len(stamps) - 1:
            snapshots.pop()
        snapshots.append((len(stamps) - 1, stamps[-1], landmarks))
    return RunResult(
        trajectory=trajectory,
        landmarks=landmarks,
        observed=np.asarray(observed, dtype=np.int64),
        map_size=np.asarray(map_size, dtype=np.int64),
        seconds=np.asarray(seconds, dtype=np.float64),
        summary=estimator.summary(),
        map_history=tuple(snapshots),
        dense_map=estimator.dense_map() if hasattr(estimator, "dense_map") else None,
        seconds_finish=seconds_finish,
    )
