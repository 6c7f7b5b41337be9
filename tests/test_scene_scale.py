"""The point estimators' defaults hold at any scale: the same scene 100 times smaller gives errors about
100 times smaller (the motion model's acceleration noise is taken from the log, as the noise is)."""

from __future__ import annotations

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.estimators._noise import (
    ACCELERATION_MARGIN,
    MAX_ACCELERATION_NOISE,
    VEHICLE_ACCELERATION,
    PathAcceleration,
    derived_acceleration_noise,
    estimate_acceleration,
)
from relpoint.evaluation import landmark_metrics
from relpoint.geometry import so3_exp
from relpoint.simulation import SimulationConfig, simulate
from relpoint.simulation.tabletop import tabletop_arc
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
        rotation = so3_exp([0.0, 0.0, t])
        points = (landmarks - position) @ rotation  # R^T (m - p), row-wise
        observations.append(PointObservation(int(t * 1e9), points, np.arange(60)))
    return observations


def test_the_measured_acceleration_is_the_paths_and_scales_with_it() -> None:
    for scale in (0.01, 1.0, 100.0):
        measured = estimate_acceleration(_circling_observations(scale))
        assert measured is not None
        # velocities over 0.5 s (5 intervals): the white noise over one interval is sqrt(5) times that
        assert measured.smoothed == pytest.approx(scale, rel=0.1)  # the centripetal acceleration
        assert measured.white == pytest.approx(scale * np.sqrt(5.0), rel=0.1)


def test_the_derived_noise_keeps_to_the_vehicle_default_and_the_noise_floor_unless_the_path_shows_more() -> None:
    def path(white: float, smoothed: float | None = None) -> PathAcceleration:
        return PathAcceleration(white, white / np.sqrt(5.0) if smoothed is None else smoothed)

    assert derived_acceleration_noise(None, 0.01) == VEHICLE_ACCELERATION  # the path could not tell
    # the simulator's figure eight: 1.5 m/s^2 turns measured as 4.2 of white noise; the margin stops at 2
    assert derived_acceleration_noise(path(4.2, 1.9), 0.3) == VEHICLE_ACCELERATION
    # a path turning harder than a vehicle keeps what it shows (capped, the proposal trailed it)
    assert derived_acceleration_noise(path(52.0, 23.0), 3.0) == 23.0
    assert derived_acceleration_noise(path(1e7, 1e6), 0.3) == MAX_ACCELERATION_NOISE
    assert derived_acceleration_noise(path(0.004), 0.002) == pytest.approx(ACCELERATION_MARGIN * 0.004)
    assert derived_acceleration_noise(path(0.0), 0.003) == pytest.approx(VEHICLE_ACCELERATION * 0.01)


def test_the_ekf_on_a_scene_a_hundred_times_smaller_gives_errors_a_hundred_times_smaller() -> None:
    def errors(scale: float) -> tuple[float, float]:
        """ATE and landmark RMSE (m) of the EKF with its defaults on the figure eight at ``scale``, with
        the noise scaled alike."""
        sim = simulate(SimulationConfig(iterations=200, scale=scale, noise=0.3 * scale, seed=3))
        spec = ESTIMATORS["ekf"]
        estimator = spec.factory(spec.config_class(), np.random.default_rng(0))
        result = pipeline.run((step.observation for step in sim.steps()), estimator)
        error = result.trajectory.positions - sim.ground_truth.positions
        ate = float(np.sqrt(np.mean(np.sum(error**2, axis=1))))
        return ate, landmark_metrics(result.landmarks, sim.landmarks).summary["lm_err_rmse"]

    ate, landmarks = errors(1.0)
    small_ate, small_landmarks = errors(0.01)
    # with the vehicle's 2 m/s^2 the landmarks were 20 times worse at 1 cm scale
    assert small_ate / 0.01 < 2.0 * ate
    assert small_landmarks / 0.01 < 2.0 * landmarks


def _fastslam_ate_on_a_tabletop(scale: float, seed: int = 0) -> float:
    """FastSLAM's ATE (m, in the first pose's frame) with its defaults on the tabletop arc at ``scale``
    (:func:`relpoint.simulation.tabletop.tabletop_arc`). ``seed`` draws the scene and the particles."""
    observations, truth = tabletop_arc(scale, seed)
    spec = ESTIMATORS["fastslam"]
    result = pipeline.run(observations, spec.factory(spec.config_class(), np.random.default_rng(seed)))
    return float(np.sqrt(np.mean(np.sum((result.trajectory.positions - truth) ** 2, axis=1))))


def test_fastslam_on_a_tabletop_is_as_good_as_on_the_same_scene_a_thousand_times_larger() -> None:
    # With the vehicle's 2 m/s^2 the tabletop's ATE was 5.6 times the large scene's, scaled. In the median
    # of five seeds (measured 0.032 against 0.038, scaled): one tabletop seed's association collapses
    # (0.355), as FastSLAM's 0.01 m pose jitter is five times the tabletop's noise; scaling the jitter
    # with the noise mends it there, and costs Starry Night's real stereo points (worst of ten seeds
    # 0.119 -> 0.745 m), so the jitter stays.
    tabletop = [_fastslam_ate_on_a_tabletop(0.0375, seed) / 0.0375 for seed in range(5)]
    large = [_fastslam_ate_on_a_tabletop(37.5, seed) / 37.5 for seed in range(5)]
    assert np.median(tabletop) < 2.0 * np.median(large)


def test_fastslam_on_the_figure_eight_ten_times_larger_stays_near_ten_times_the_error() -> None:
    # The path turns ten times harder: with the acceleration noise capped at a vehicle's 2 m/s^2 the
    # proposal trailed it and the ATE was 45 times the figure eight's, scaled; now 2.7 times. The rest
    # of the gap: settings written for the simulator, such as the proposal's fixed 0.01 m pose jitter.
    def ate(scale: float) -> float:
        sim = simulate(SimulationConfig(iterations=200, scale=scale, noise=0.3 * scale, seed=3))
        spec = ESTIMATORS["fastslam"]
        result = pipeline.run((step.observation for step in sim.steps()),
                              spec.factory(spec.config_class(), np.random.default_rng(0)))  # fmt: skip
        error = result.trajectory.positions - sim.ground_truth.positions
        return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))

    assert ate(10.0) / 10.0 < 4.0 * ate(1.0)
