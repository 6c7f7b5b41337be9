"""Points that are no landmarks (a lidar scan's fresh samples of surfaces) are told apart and warned of.

The point estimators associate by position: they need points seen again and again. Registered onto the
observation before, a landmark lies far closer to its earlier sighting than to its neighbours; a fresh
sample of a surface lies about as close to the earlier samples as to its neighbours, at any density.
Before this check such a log ran to a map and path a metre off, with exit 0 and no word (a 16-ring
lidar scan of a room, 3,000 points a scan: Relative Point 0.86 m ATE over a 2.5 m path, FastSLAM 1.24
m; the EKF ran for minutes a scan).
"""

from __future__ import annotations

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.estimators._noise import REVISIT_RATIO, ConsecutiveRegistrations, revisit_ratio
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import PointObservation


def _wall_scans(frames: int = 32, per_frame: int = 800) -> list[PointObservation]:
    """Scans of a box room's walls from a sensor moving 5 cm a frame: every scan fresh random samples."""
    rng = np.random.default_rng(0)
    scans = []
    for k in range(frames):
        position = np.array([0.05 * k, 0.0, 0.0])
        direction = rng.normal(size=(per_frame, 3))
        direction[:, 2] *= 0.2
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        with np.errstate(divide="ignore"):
            hits = np.min(
                np.where(direction > 0, (np.array([10.0, 6.0, 2.0]) - position) / direction,
                         (np.array([-10.0, -6.0, -1.0]) - position) / direction), axis=1,
            )  # fmt: skip
        points = direction * hits[:, None] + rng.normal(0.0, 0.02, (per_frame, 3))
        scans.append(PointObservation(k * 100_000_000, points))
    return scans


@pytest.mark.parametrize("per_frame", [100, 3000])
def test_the_revisit_ratio_tells_surface_samples_from_landmarks_at_any_density(per_frame: int) -> None:
    ratio = revisit_ratio(ConsecutiveRegistrations.of(_wall_scans(12, per_frame)))
    assert ratio is not None and ratio > REVISIT_RATIO


def _run(observations: list[PointObservation], name: str = "relpoint") -> pipeline.RunResult:
    spec = ESTIMATORS[name]
    return pipeline.run(iter(observations), spec.factory(spec.config_class(), np.random.default_rng(0)))


def test_a_run_over_surface_samples_warns_that_they_are_no_landmarks() -> None:
    result = _run(_wall_scans())
    assert result.summary["revisit_ratio"] >= REVISIT_RATIO
    assert any("not landmarks seen again and again" in warning for warning in result.warnings)
    # The simulator's landmarks: no such warning.
    observations = [step.observation for step in simulate(SimulationConfig(iterations=40, seed=1)).steps()]
    result = _run(observations)
    assert result.summary["revisit_ratio"] < REVISIT_RATIO / 3
    assert not any("not landmarks" in warning for warning in result.warnings)
