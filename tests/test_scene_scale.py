"""The point estimators' defaults hold at any scale: the same scene 100 times smaller gives errors about
100 times smaller (the motion model's acceleration noise is taken from the log, as the noise is)."""

from __future__ import annotations

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.estimators._noise import (
    ACCELERATION_MARGIN,
    VEHICLE_ACCELERATION,
    derived_acceleration_noise,
    estimate_acceleration,
)
from relpoint.evaluation import landmark_metrics
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import PointObservation


def _circling_observations(scale: float, seconds: float = 3.0, rate_hz: float = 10.0) -> list[PointObservation]:
    """A sensor circling at 1 rad/s on a radius of ``scale`` m (centripetal acceleration ``scale`` m/s^2)
    past 60 landmarks within ``3 scale`` m, observed without noise."""
    rng = np.random.default_rng(4)
    landmarks = rng.uniform(-3.0, 3.0, (60, 3)) * scale
    observations = []
    for k in range(int(seconds * rate_hz)):
        t = k / rate_hz
        position = scale * np.array([np.cos(t), np.sin(t), 0.0])
        c, s = np.cos(t), np.sin(t)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        points = (landmarks - position) @ rotation  # R^T (m - p), row-wise
        observations.append(PointObservation(int(t * 1e9), points, np.arange(60)))
    return observations


def test_the_measured_acceleration_is_the_paths_and_scales_with_it() -> None:
    for scale in (0.01, 1.0, 100.0):
        measured = estimate_acceleration(_circling_observations(scale))
        assert measured == pytest.approx(scale, rel=0.1)


def test_the_derived_noise_stays_within_the_vehicle_default_and_the_noise_floor() -> None:
    assert derived_acceleration_noise(None, 0.01) == VEHICLE_ACCELERATION  # the path could not tell
    assert derived_acceleration_noise(10.0, 0.3) == VEHICLE_ACCELERATION
    assert derived_acceleration_noise(0.004, 0.002) == pytest.approx(ACCELERATION_MARGIN * 0.004)
    assert derived_acceleration_noise(0.0, 0.003) == pytest.approx(VEHICLE_ACCELERATION * 0.01)


def _errors(name: str, scale: float) -> tuple[float, float]:
    """ATE and landmark RMSE (m) of ``name`` with its default settings on the figure eight at ``scale``,
    with the noise scaled alike."""
    sim = simulate(SimulationConfig(iterations=200, scale=scale, noise=0.3 * scale, seed=3))
    spec = ESTIMATORS[name]
    result = pipeline.run(
        (step.observation for step in sim.steps()), spec.factory(spec.config_class(), np.random.default_rng(0))
    )
    truth = sim.ground_truth.positions
    ate = float(np.sqrt(np.mean(np.sum((result.trajectory.positions - truth) ** 2, axis=1))))
    return ate, landmark_metrics(result.landmarks, sim.landmarks).summary["lm_err_rmse"]


@pytest.mark.parametrize("name", ["ekf", "fastslam"])
def test_a_scene_a_hundred_times_smaller_gives_errors_a_hundred_times_smaller(name: str) -> None:
    ate, landmarks = _errors(name, 1.0)
    small_ate, small_landmarks = _errors(name, 0.01)
    # with the vehicle's 2 m/s^2 the EKF's landmarks were 20 times worse at 1 cm scale
    assert small_ate / 0.01 < 2.0 * ate
    assert small_landmarks / 0.01 < 2.0 * landmarks
