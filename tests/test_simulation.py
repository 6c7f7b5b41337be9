"""The simulated scenarios: geometry of the figure eight, observation model, odometry, fixes."""

from __future__ import annotations

import json
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from formats.log import LogReader
from relpoint.errors import UsageError
from relpoint.geometry import integrate_twist, transform_points
from relpoint.simulation import SimulationConfig, paths, simulate
from relpoint_cli.main import cli


def test_observations_land_on_their_landmarks_with_the_configured_noise() -> None:
    config = SimulationConfig(iterations=300, density=40, noise=0.3, seed=11)
    sim = simulate(config)
    residuals = []
    for step in sim.steps():
        obs = step.observation
        world = transform_points(step.T_world_sensor, obs.points)
        truth = sim.landmark_positions(step.stamp_ns)[obs.ids]
        residuals.append(world - truth)
    residuals = np.concatenate(residuals)
    assert len(residuals) > 5000
    # Per-axis: zero mean, standard deviation equal to --noise (4 % tolerance at n > 5000).
    np.testing.assert_allclose(residuals.mean(axis=0), 0.0, atol=0.02)
    np.testing.assert_allclose(residuals.std(axis=0), 0.3, rtol=0.04)


def test_observations_are_inside_the_frustum() -> None:
    config = SimulationConfig(iterations=50, density=100, noise=0.0, range=40.0, fov_horizontal=90.0, seed=2)
    for step in simulate(config).steps():
        p = step.observation.points
        assert np.all(np.linalg.norm(p, axis=1) <= 40.0 + 1e-9)
        assert np.all(np.abs(np.degrees(np.arctan2(p[:, 1], p[:, 0]))) <= 45.0 + 1e-9)


def test_figure_eight_geometry() -> None:
    radius, climb = 95.0, 25.0
    phase = np.linspace(0.0, 1.0, 4001)
    positions, tangents = paths.figure8(phase, radius, climb)
    np.testing.assert_allclose(positions[0], 0.0, atol=1e-9)  # starts in the middle
    np.testing.assert_allclose(positions[-1], positions[0], atol=1e-9)  # closes on itself
    middle = positions[2000]
    np.testing.assert_allclose(middle[:2], 0.0, atol=1e-9)
    assert middle[2] == pytest.approx(climb)  # well above the start at the middle
    right, left = positions[1:2000], positions[2001:-1]
    assert np.all(right[:, 1] > 0) and np.all(left[:, 1] < 0)  # two loops, right (+y) first

    def signed_area(xy: np.ndarray) -> float:
        return 0.5 * float(np.sum(xy[:-1, 0] * xy[1:, 1] - xy[1:, 0] * xy[:-1, 1]))

    assert signed_area(positions[:2001, :2]) > 0  # right loop counter-clockwise
    assert signed_area(positions[2000:, :2]) < 0  # left loop clockwise
    assert np.all(np.diff(positions[:2001, 2]) >= 0) and np.all(np.diff(positions[2000:, 2]) <= 0)
    slope = np.degrees(np.arctan2(tangents[:, 2], np.linalg.norm(tangents[:, :2], axis=1)))
    assert 1.0 < np.abs(slope).max() < 6.0  # a slight incline and decline
    assert paths.figure8_length(radius, climb) == pytest.approx(1200.0, rel=0.01)


def test_sensor_looks_along_the_path_with_pitch() -> None:
    sim = simulate(SimulationConfig(passes=1, step=2.0))
    poses = sim.ground_truth.matrices()
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)  # starts at the identity, like the estimators
    forward = poses[:, :3, 0]
    motion = np.diff(poses[:, :3, 3], axis=0)
    motion /= np.linalg.norm(motion, axis=1, keepdims=True)
    cos_angle = np.sum(forward[:-1] * motion, axis=1)
    assert np.all(cos_angle > np.cos(np.radians(2.0)))
    pitch = np.degrees(np.arcsin(forward[:, 2]))
    assert pitch.max() > 1.0 and pitch.min() < -1.0
    np.testing.assert_allclose(poses[:, :3, 1][:, 2], 0.0, atol=1e-12)  # no roll: left axis stays level


def test_passes_repeat_the_path_and_density_sets_visible_points() -> None:
    one = simulate(SimulationConfig(passes=1))
    three = simulate(SimulationConfig(passes=3))
    assert len(three) == pytest.approx(3 * len(one), abs=2)
    np.testing.assert_allclose(three.ground_truth.positions[len(one) * 2], 0.0, atol=2.0)
    for density in (25, 100):
        sim = simulate(SimulationConfig(density=density, iterations=400))
        visible = np.mean([len(s.observation) for s in sim.steps()])
        assert 0.6 * density <= visible <= 1.2 * density


def test_dynamic_landmarks_move_and_clutter_is_marked() -> None:
    config = SimulationConfig(iterations=200, dynamic=0.3, clutter=3.0, seed=5)
    sim = simulate(config)
    assert sim.landmarks.dynamic.mean() == pytest.approx(0.3, abs=0.01)
    start = sim.landmark_positions(sim.stamps_ns[0])
    later = sim.landmark_positions(sim.stamps_ns[-1])
    moved = np.linalg.norm(later - start, axis=1) > 1e-9
    np.testing.assert_array_equal(moved, sim.landmarks.dynamic)
    clutter = [int((s.observation.ids == -1).sum()) for s in sim.steps()]
    assert np.mean(clutter) == pytest.approx(3.0, rel=0.2)


def test_odometry_integrates_to_the_next_pose() -> None:
    sim = simulate(SimulationConfig(iterations=100, odometry_noise=0.0, odometry_angular_noise=0.0))
    steps = list(sim.steps())
    poses = sim.ground_truth.matrices()
    for k in range(len(steps) - 1):
        odo = steps[k].odometry
        predicted = integrate_twist(poses[k], odo.linear, odo.angular, 0.1)
        np.testing.assert_allclose(predicted, poses[k + 1], atol=1e-9)


def test_noisy_odometry_and_fixes_follow_their_settings() -> None:
    config = SimulationConfig(iterations=600, odometry_noise=0.1, fix_every=5, fix_noise=2.0, seed=9)
    sim = simulate(config)
    steps = list(sim.steps())
    clean = simulate(SimulationConfig(iterations=600, odometry_noise=0.0, odometry_angular_noise=0.0, seed=9))
    clean_linear = np.array([s.odometry.linear for s in clean.steps()])
    linear = np.array([s.odometry.linear for s in steps])
    assert np.std(linear - clean_linear) == pytest.approx(0.1, rel=0.1)
    fixes = [s for s in steps if s.fix is not None]
    assert [s.index for s in fixes] == list(range(0, 600, 5))
    errors = np.array([s.fix.position - s.T_world_sensor[:3, 3] for s in fixes])
    assert errors.std() == pytest.approx(2.0, rel=0.15)
    np.testing.assert_allclose(fixes[0].fix.covariance, np.eye(3) * 4.0)


def test_enabling_odometry_leaves_observations_unchanged() -> None:
    plain = simulate(SimulationConfig(iterations=30, seed=4))
    extra = simulate(SimulationConfig(iterations=30, seed=4, odometry_noise=0.2, fix_every=3, clutter=0.0))
    for a, b in zip(plain.steps(), extra.steps(), strict=True):
        np.testing.assert_array_equal(a.observation.points, b.observation.points)


def test_stationary_and_corridor() -> None:
    still = simulate(SimulationConfig(scenario="stationary", density=50))
    assert len(still) == 900
    np.testing.assert_array_equal(still.ground_truth.positions, 0.0)
    counts = [len(s.observation) for s in still.steps()]
    assert min(counts) == 50  # every landmark is in view at every iteration
    corridor = simulate(SimulationConfig(scenario="corridor", length=600, density=100))
    positions = corridor.ground_truth.positions
    assert positions[-1, 0] == pytest.approx(600, abs=2)
    yaw = Rotation.from_quat(corridor.ground_truth.quats_xyzw).as_euler("ZYX")[:, 0]
    assert np.ptp(yaw) > 0.2


@pytest.mark.parametrize(
    "bad", [{"noise": -1}, {"density": 0}, {"dynamic": 1.5}, {"scenario": "helix"}, {"min_range": 80}]
)
def test_invalid_settings_are_usage_errors(bad: dict) -> None:
    with pytest.raises(UsageError):
        SimulationConfig(**bad)
    with pytest.raises(UsageError, match="unknown simulation setting"):
        SimulationConfig.from_mapping({"nosie": 0.1})


def test_the_last_stamp_must_fit_a_ros_stamp() -> None:
    last_second = 2**31 - 1
    fits = simulate(SimulationConfig(iterations=20, rate=10.0, start_time=last_second - 1.9))
    assert fits.stamps_ns[-1] // 1_000_000_000 == last_second
    for start_time in (last_second, last_second - 0.8):  # the last stamp 1.9 s later
        with pytest.raises(UsageError, match="beyond the 2147483647 s a ROS stamp holds"):
            simulate(SimulationConfig(iterations=20, rate=10.0, start_time=start_time))
    with pytest.raises(UsageError, match="start_time"):
        SimulationConfig(start_time=3e9)


def test_simulate_refuses_a_start_time_past_ros_stamps(tmp_path: Path) -> None:
    out = tmp_path / "late.mcap"
    result = CliRunner().invoke(
        cli, ["-q", "simulate", "-o", str(out), "--iterations", "20", "--start-time", "2147483647"]
    )
    assert result.exit_code == 2 and "a ROS stamp holds" in result.stderr and not out.exists()


@pytest.mark.parametrize("start_time", ["1700000000.000001", "1700000000.654321", "2147480000.000123", "0.1"])
def test_the_first_stamp_is_the_start_time_as_written(tmp_path: Path, start_time: str) -> None:
    # to the nanosecond for the digits a setting holds (a float product was off by up to a few hundred ns)
    out = tmp_path / "start.mcap"
    result = CliRunner().invoke(
        cli, ["-q", "simulate", "-o", str(out), "--iterations", "3", "--start-time", start_time]
    )
    assert result.exit_code == 0, result.stderr
    reader = LogReader(out)
    stamps = [record.value.stamp_ns for record in reader.records(["ground_truth_pose"])]
    exact = int(Decimal(start_time) * 1_000_000_000)
    assert stamps == [exact, exact + 100_000_000, exact + 200_000_000]
    recorded = json.loads(reader.metadata()["relpoint.simulation"]["start_time"], parse_float=Decimal)
    assert recorded * 1_000_000_000 == exact  # the metadata's start time gives the first stamp
