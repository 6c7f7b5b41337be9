"""Odometry at another rate than the observations: the noise of a held twist does not depend on how
many messages cover an interval, a twist held over several observations grows uncertain, and a
stream that stops hands over to the motion model (relpoint.estimators._odometry_hold)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from relpoint.estimators.ekf import EkfConfig, EkfSlam
from relpoint.estimators.fastslam import FastSlam, FastSlamConfig
from relpoint.types import OdometryMeasurement, PointObservation

OBSERVATION_NS = 100_000_000  # 10 Hz
SIGMA_V, SIGMA_W = 0.05, 0.005
TWIST_COVARIANCE = np.diag([SIGMA_V**2] * 3 + [SIGMA_W**2] * 3)


def _empty(stamp_ns: int) -> PointObservation:
    return PointObservation(stamp_ns, np.zeros((0, 3)), None)


def _pose_covariance_after_one_interval(rate_hz: int) -> np.ndarray:
    """The EKF's pose covariance (6, 6) after one observation interval of odometry at ``rate_hz``."""
    ekf = EkfSlam(EkfConfig(observation_sigma=0.1, linear_acceleration_noise=2.0))
    ekf.step(_empty(0))
    for stamp in np.arange(0, OBSERVATION_NS, 1_000_000_000 // rate_hz):
        ekf.add_odometry(OdometryMeasurement(int(stamp), [5.0, 0.0, 0.0], [0.0, 0.0, 0.2], TWIST_COVARIANCE))
    ekf.step(_empty(OBSERVATION_NS))
    return ekf.covariance[:6, :6]


def test_ekf_odometry_noise_over_an_interval_does_not_shrink_with_the_message_rate() -> None:
    # The same driver's covariance at ten times the rate is not ten times the information: its errors
    # outlast its period. Taken as independent, 100 Hz cut the pose variance tenfold and the filter
    # followed the odometry's slowly varying errors instead of the points (0.50 m ATE against 0.02 m
    # at 10 Hz on a foreign log).
    at_10, at_100 = _pose_covariance_after_one_interval(10), _pose_covariance_after_one_interval(100)
    np.testing.assert_allclose(np.diag(at_100), np.diag(at_10), rtol=0.05)
    assert np.diag(at_10)[0] == pytest.approx((0.1 * SIGMA_V) ** 2, rel=0.05)


def _lemniscate(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n, 3) and yaws (n,) along a figure eight of 40 x 25 m run in 40 s (up to 5 m/s^2)."""
    s = 2 * np.pi * t / 40.0
    positions = np.stack([40 * np.sin(s), 50 * np.sin(s) * np.cos(s), np.zeros_like(s)], axis=1)
    velocity = np.stack([40 * np.cos(s), 50 * np.cos(2 * s), np.zeros_like(s)], axis=1)
    return positions, np.unwrap(np.arctan2(velocity[:, 1], velocity[:, 0]))


def _drive(estimator: EkfSlam, odometry_hz: float, seconds: float = 12.0) -> float:
    """Drive the figure eight with points at 10 Hz (0.1 m noise) and odometry at ``odometry_hz``
    carrying the velocity at its stamp (ROS); return the RMS position error (m) from the first pose."""
    rng = np.random.default_rng(0)
    landmarks = rng.uniform([-60.0, -40.0, -3.0], [60.0, 40.0, 8.0], size=(300, 3))
    t_obs = np.arange(0.0, seconds, OBSERVATION_NS * 1e-9)
    t_odo = np.arange(0.0, seconds, 1.0 / odometry_hz)
    eps = 1e-4
    items: list[tuple[float, int, object]] = []
    for t in t_odo:
        (p0, p1), (y0, y1) = _lemniscate(np.array([t, t + eps]))
        R0 = Rotation.from_euler("z", y0)
        linear = R0.inv().apply(p1 - p0) / eps + rng.normal(0, SIGMA_V, 3)
        angular = np.array([0.0, 0.0, (y1 - y0) / eps]) + rng.normal(0, SIGMA_W, 3)
        items.append((t, 0, OdometryMeasurement(round(t * 1e9), linear, angular, TWIST_COVARIANCE)))
    positions, yaws = _lemniscate(t_obs)
    for t, p, yaw in zip(t_obs, positions, yaws, strict=True):
        body = Rotation.from_euler("z", yaw).inv().apply(landmarks - p)
        seen = np.linalg.norm(body, axis=1) < 35.0
        points = body[seen] + rng.normal(0, 0.1, (int(seen.sum()), 3))
        items.append((t, 1, PointObservation(round(t * 1e9), points, np.flatnonzero(seen))))
    T_first = Rotation.from_euler("z", yaws[0])
    errors = []
    for _, _, item in sorted(items, key=lambda entry: (entry[0], entry[1])):
        if isinstance(item, OdometryMeasurement):
            estimator.add_odometry(item)
            continue
        assert isinstance(item, PointObservation)
        pose = estimator.step(item)
        truth = T_first.inv().apply(positions[len(errors)] - positions[0])
        errors.append(np.linalg.norm(np.array(pose.position) - truth))
    return float(np.sqrt(np.mean(np.square(errors))))


def test_odometry_slower_than_the_points_is_not_trusted_beyond_what_it_can_tell() -> None:
    # At 2 Hz a twist is held over five observations while the vehicle turns: held as exact, its
    # error (about 0.5 m after half a second) overrode the points (0.51 m RMSE here, 0.03 m at 10 Hz).
    ekf = EkfSlam(EkfConfig(observation_sigma=0.1, linear_acceleration_noise=2.0))
    assert _drive(ekf, 2.0) < 0.06
    assert ekf.summary()["odometry_stale"] == 0


def test_a_stopped_odometry_stream_hands_over_to_the_motion_model() -> None:
    ekf = EkfSlam(EkfConfig(observation_sigma=0.1, linear_acceleration_noise=2.0))
    ekf.step(_empty(0))
    for k in range(5):  # 100 Hz for 40 ms, then silence
        ekf.add_odometry(OdometryMeasurement(k * 10_000_000, [5.0, 0.0, 0.0], [0.0, 0.0, 0.0], TWIST_COVARIANCE))
    for k in range(1, 11):
        ekf.step(_empty(k * OBSERVATION_NS))
    assert ekf.summary()["odometry_stale"] == 1
    # about a second on the constant-velocity model, not the 5 cm of the odometry held as exact
    assert np.sqrt(ekf.covariance[1, 1]) > 0.25
    assert ekf.pose().position[0] == pytest.approx(5.0, abs=1e-6)  # the last twist carries on


def _fastslam_spread_after_one_interval(rate_hz: int) -> np.ndarray:
    """The variance (3,) of 200 FastSLAM particles' positions after one interval of odometry at ``rate_hz``."""
    slam = FastSlam(
        FastSlamConfig(observation_sigma=0.1, linear_acceleration_noise=2.0, particles=200), np.random.default_rng(0)
    )
    slam.step(_empty(0))
    for stamp in np.arange(0, OBSERVATION_NS, 1_000_000_000 // rate_hz):
        slam.add_odometry(OdometryMeasurement(int(stamp), [5.0, 0.0, 0.0], [0.0, 0.0, 0.2], TWIST_COVARIANCE))
    slam.step(_empty(OBSERVATION_NS))
    return np.var(slam.positions, axis=0)


def test_fastslam_proposal_does_not_grow_with_the_odometry_rate() -> None:
    # pose_noise was added at every record, ten times per interval at 100 Hz (eight times the spread)
    ratio = _fastslam_spread_after_one_interval(100).sum() / _fastslam_spread_after_one_interval(10).sum()
    assert 0.6 < ratio < 1.6  # the same prior, drawn by 200 particles
