"""Estimators behind ``relpoint run``, one module each, registered in :data:`ESTIMATORS`."""

from __future__ import annotations

from relpoint.estimators._noise import SIMULATOR_SIGMA
from relpoint.estimators.base import DEPTH, FIX, ODOMETRY, POINTS, Estimator, EstimatorSpec

#: Every estimator ``relpoint run --estimator NAME`` can build, by name.
ESTIMATORS: dict[str, EstimatorSpec] = {}


def register(spec: EstimatorSpec) -> EstimatorSpec:
    """Add ``spec`` to :data:`ESTIMATORS` (called once per estimator module below)."""
    ESTIMATORS[spec.name] = spec
    return spec


__all__ = [
    "DEPTH", "ESTIMATORS", "FIX", "ODOMETRY", "POINTS", "SIMULATOR_SIGMA", "Estimator", "EstimatorSpec", "register",
]  # fmt: skip


def _register_builtin() -> None:
    from relpoint.estimators import dense, ekf, fastslam
    from relpoint.estimators.relative_point import estimator as relative_point

    for spec in (relative_point.SPEC, ekf.SPEC, fastslam.SPEC, dense.SPEC):
        register(spec)


_register_builtin()
