"""The small interface every estimator implements, and the registry the CLI picks them from.

An estimator consumes a log's records in time order through :meth:`Estimator.step` (one call per
observation, i.e. per iteration) and the optional :meth:`Estimator.add_odometry` /
:meth:`Estimator.add_fix`, and reports its map through :meth:`Estimator.landmark_map`. It never
reads files, prints or exits: the pipeline (``relpoint.pipeline``) drives it and the CLI does I/O.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar, Generic, TypeVar

import numpy as np
import numpy.typing as npt

from relpoint.geometry import FloatArray
from relpoint.types import DepthFrame, LandmarkMap, OdometryMeasurement, PointObservation, Pose, PositionFix, Trajectory

#: Input roles a log can provide (named after the default topics of the log format).
POINTS = "points"
DEPTH = "depth"
ODOMETRY = "odometry"
FIX = "fix"


#: What one iteration of an estimator reads: a point cloud or a depth frame.
InputT = TypeVar("InputT", PointObservation, DepthFrame)


class Estimator(abc.ABC, Generic[InputT]):
    """Base class of the estimators: ``Estimator[PointObservation]`` for point-landmark estimators,
    ``Estimator[DepthFrame]`` for dense ones.

    Subclasses set :attr:`name`, are built as ``cls(config, rng)`` (:class:`~.spec.EstimatorSpec`)
    and implement :meth:`step` and :meth:`landmark_map`. Poses are ``T_world_sensor``: the first pose
    is the identity unless an absolute reference is fused.
    """

    name: ClassVar[str]
    #: What :meth:`finish` does, in a few words, for a progress display while it runs.
    finishing: ClassVar[str] = "finishing"
    #: Whether the estimator itself warns of iterations whose points could not fix its pose (else the
    #: pipeline warns of clouds of fewer than three points with no odometry or fix to carry the pose).
    reports_unlocated: ClassVar[bool] = False

    @abc.abstractmethod
    def step(self, observation: InputT) -> Pose:
        """Process one iteration's input (untransformed points or a depth frame, sensor frame);
        return the sensor pose at its stamp."""

    @classmethod
    def compile(cls) -> None:
        """Compile or load the class's compiled code (shared by every instance); nothing by default."""

    def prepare(self) -> None:
        """Compile or load what :meth:`step` runs, once, before the first iteration (timed apart from
        them); by default :meth:`compile`."""
        self.compile()

    def start_moving(self, twist: FloatArray, twist_sigma: FloatArray) -> bool:
        """Before the first :meth:`step`: the sensor's body-frame twist over the first interval
        ``(v (m/s), w (rad/s))`` (6,) as the log's first observations show it, with its standard
        deviation (6,). An estimator with a constant-velocity motion model starts from it instead of
        from rest and returns True; ignored by default (False)."""
        return False

    def add_odometry(self, odometry: OdometryMeasurement) -> None:
        """Take a body-frame velocity measurement (ignored by estimators that do not use odometry)."""

    def add_fix(self, fix: PositionFix) -> None:
        """Take an absolute position fix (ignored by estimators that do not fuse fixes)."""

    @abc.abstractmethod
    def landmark_map(self) -> LandmarkMap:
        """The current map of landmarks in ``world``."""

    def finish(self, trajectory: Trajectory) -> Trajectory:
        """Called once after the last iteration with the poses :meth:`step` returned, in order.

        Returns the final trajectory. An estimator that refines its map when the log ends (a final
        adjustment) corrects the trajectory here too; the default returns it unchanged.
        """
        return trajectory

    def dense_map(self) -> tuple[FloatArray, FloatArray, npt.NDArray[np.uint8], FloatArray] | None:
        """A dense estimator's surface map: points (N, 3) in ``world`` (m), normals (N, 3), colours
        (N, 3) uint8 RGB and weights (N,); None (the default) for landmark estimators."""
        return None

    @property
    def features_started(self) -> int | None:
        """Features started so far for observations that matched nothing, mapped yet or not; None (the
        default) when every new feature is at once a new landmark, so that the map's growth counts them."""
        return None

    @property
    def map_size(self) -> int:
        """Number of landmarks currently mapped (for timing.csv)."""
        return len(self.landmark_map())

    def summary(self) -> dict[str, Any]:
        """Estimator-specific summary figures for run.json (counts, flags); JSON-serialisable."""
        return {}

    def run_warnings(self) -> list[str]:
        """What makes this run's result doubtful, beyond what :meth:`summary` counts generically (one line
        each, for run.json's ``warnings`` and stderr)."""
        return []
