"""The odometry is checked against the motion the first observations register into: a twist biased by
more than the deviation its messages state gets that axis's variance raised, so the filters are not
dragged along by it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.estimators._noise import ConsecutiveRegistrations
from relpoint.estimators._odometry_check import MIN_INTERVALS, check_odometry, held_twists
from relpoint.geometry import so3_exp
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import OdometryMeasurement, PointObservation

RATE_HZ = 10.0
YAW_RATE = 0.3  # rad/s
SPEED = 1.0  # m/s, along the sensor's x


def _observations(frames: int = 30, noise: float = 0.01) -> list[PointObservation]:
    """A sensor driving a circle (1 m/s forward, 0.3 rad/s yaw) past 80 landmarks, observed at 10 Hz."""
    rng = np.random.default_rng(2)
    landmarks = rng.uniform(-8.0, 8.0, (80, 3)) + np.array([2.0, 2.0, 0.0])
    observations = []
    for k in range(frames):
        t = k / RATE_HZ
        yaw = YAW_RATE * t
        position = SPEED / YAW_RATE * np.array([np.sin(yaw), 1.0 - np.cos(yaw), 0.0])
        points = (landmarks - position) @ so3_exp([0.0, 0.0, yaw]) + rng.normal(0.0, noise, landmarks.shape)
        observations.append(PointObservation(int(round(t * 1e9)), points, np.arange(80)))
    return observations


def _odometry(frames: int, yaw_bias: float, sigmas: tuple[float, float] = (0.02, 0.002)) -> list[OdometryMeasurement]:
    """The circle's true twist at every observation, ``yaw_bias`` (rad/s) added to its yaw rate, stating
    ``sigmas`` (m/s, rad/s) as its deviations (0: unset)."""
    covariance = np.diag([sigmas[0] ** 2] * 3 + [sigmas[1] ** 2] * 3)
    return [
        OdometryMeasurement(
            int(round(k / RATE_HZ * 1e9)), [SPEED, 0.0, 0.0], [0.0, 0.0, YAW_RATE + yaw_bias], covariance
        )
        for k in range(frames)
    ]


def _check(yaw_bias: float, frames: int = 30, sigmas: tuple[float, float] = (0.02, 0.002)):
    observations = _observations(frames)
    registrations = ConsecutiveRegistrations.of(observations)
    return check_odometry(registrations.observations, registrations.steps, _odometry(frames, yaw_bias, sigmas))


def test_a_yaw_rate_biased_beyond_its_stated_deviation_is_found_and_its_variance_raised() -> None:
    check = _check(yaw_bias=0.02)
    assert check is not None and check.intervals == 29
    assert check.raised == ["wz"]
    assert check.bias[5] == pytest.approx(-0.02, abs=0.003)  # registered minus odometry
    assert np.abs(check.bias[[0, 2, 3, 4]]).max() < 0.005
    # the filters' model moves straight along the interval's first heading: on the circle the chord
    # turns half the interval's yaw away from it, which shows as a sideways rate (well within 0.02 m/s)
    assert check.bias[1] == pytest.approx(SPEED * np.sin(0.5 * YAW_RATE / RATE_HZ), abs=0.003)
    assert check.added_variance[5] == pytest.approx(check.bias[5] ** 2)
    message = _odometry(1, 0.02)[0]
    adjusted = check.adjusted(message)
    assert adjusted.covariance[5, 5] == pytest.approx(0.002**2 + check.bias[5] ** 2)
    assert np.array_equal(adjusted.covariance[:5, :5], message.covariance[:5, :5])
    assert np.array_equal(adjusted.angular, message.angular)  # the twist itself is kept
    assert "wz" in check.warnings()[0] and "odometry_check=false" in check.warnings()[0]


def test_odometry_that_agrees_with_the_registered_motion_is_kept_as_it_is() -> None:
    check = _check(yaw_bias=0.0)
    assert check is not None and check.raised == [] and not check.warnings()
    message = _odometry(1, 0.0)[0]
    assert check.adjusted(message) is message


def test_a_bias_within_the_stated_deviation_is_left_alone() -> None:
    check = _check(yaw_bias=0.02, sigmas=(0.02, 0.05))
    assert check is not None and check.raised == []


def test_axes_the_messages_leave_unset_are_not_touched() -> None:
    check = _check(yaw_bias=0.02, sigmas=(0.02, 0.0))
    assert check is not None and check.raised == []
    assert np.isnan(check.stated[5])
    unset = _odometry(1, 0.02, (0.02, 0.0))[0]
    assert check.adjusted(unset).covariance[5, 5] == 0.0


def test_too_few_intervals_or_no_odometry_tell_nothing() -> None:
    assert _check(yaw_bias=0.02, frames=MIN_INTERVALS) is None
    observations = _observations(30)
    registrations = ConsecutiveRegistrations.of(observations)
    assert check_odometry(registrations.observations, registrations.steps, []) is None


def test_the_held_twist_is_weighted_by_the_time_each_message_holds() -> None:
    slow = OdometryMeasurement(0, [1.0, 0.0, 0.0], [0.0, 0.0, 0.0], np.eye(6))
    fast = OdometryMeasurement(75_000_000, [3.0, 0.0, 0.0], [0.0, 0.0, 0.0], 3 * np.eye(6))
    twist, variance = held_twists(50_000_000, 150_000_000, [slow, fast])
    assert twist[0] == pytest.approx(0.25 * 1.0 + 0.75 * 3.0)
    assert variance[0] == pytest.approx(0.25 * 1.0 + 0.75 * 3.0)
    assert held_twists(0, 100, [fast]) is None  # nothing held yet


def _biased_figure_eight(yaw_bias: float):
    sim = simulate(SimulationConfig(iterations=200, odometry_noise=0.05, seed=3))

    def items():
        for step in sim.steps():
            yield step.observation
            if step.odometry is not None:
                odometry = step.odometry
                yield dataclasses.replace(odometry, angular=odometry.angular + np.array([0.0, 0.0, yaw_bias]))

    return sim, items


def _ekf_ate(items, truth: np.ndarray, **settings) -> tuple[float, dict]:
    spec = ESTIMATORS["ekf"]
    result = pipeline.run(items(), spec.factory(spec.config_class(**settings), np.random.default_rng(0)))
    error = result.trajectory.positions - truth
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1)))), result.summary


def test_the_ekf_is_not_dragged_along_by_a_biased_yaw_rate() -> None:
    sim, items = _biased_figure_eight(0.05)  # 10 times the 0.005 rad/s the simulator's odometry states
    truth = sim.ground_truth.positions
    checked, summary = _ekf_ate(items, truth)
    unchecked, _ = _ekf_ate(items, truth, odometry_check=False)
    assert summary["odometry_check"]["raised_axes"] == ["wz"]
    assert checked < 0.05 * unchecked  # taken at its word, the biased odometry lost the path (tens of m)
    _, unbiased = _biased_figure_eight(0.0)
    reference, reference_summary = _ekf_ate(unbiased, truth)
    assert reference_summary["odometry_check"]["raised_axes"] == []
    assert checked < 3.0 * reference
