"""Fixes that leave an axis unmeasured (a GNSS receiver's altitude at a variance of 1e6-1e9 m^2): the
frame is pinned on the axes they measure, and the EKF and FastSLAM use them (they were ignored)."""

from __future__ import annotations

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators._fix_frame import FixFrame
from relpoint.estimators._fix_smoothing import smoothed_on_fixes
from relpoint.estimators.ekf import EkfConfig, EkfSlam
from relpoint.estimators.fastslam import FastSlam, FastSlamConfig
from relpoint.geometry import fit_rigid, fit_rigid_on_axes, fitted_parameters, measured_basis, so3_exp
from relpoint.screening import UNMEASURED_VARIANCE, InputScreen
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import PositionFix, Trajectory

DT_NS = 100_000_000
UNKNOWN = 1e9  # ROS's variance for what a message does not measure


def _horizontal_fix(stamp_ns: int, position: np.ndarray, sigma: float, z_variance: float = UNKNOWN) -> PositionFix:
    """A fix measuring x and y (``sigma`` m), its altitude a placeholder 0 of unknown variance (ROS's 1e9,
    or a 0 the writer left unfilled)."""
    covariance = np.diag([sigma**2, sigma**2, z_variance])
    return PositionFix(stamp_ns, np.array([position[0], position[1], 0.0]), covariance)


def test_measured_basis_leaves_out_axes_of_unknown_variance() -> None:
    assert measured_basis([np.eye(3)]).shape == (3, 3)
    assert measured_basis([np.diag([1.0, 1.0, 9.0])]).shape == (3, 3)  # worse, but measured
    plane = measured_basis([np.diag([1.0, 1.0, 1e6])] * 3)
    assert plane.shape == (3, 2)
    np.testing.assert_allclose(plane @ plane.T, np.diag([1.0, 1.0, 0.0]), atol=1e-9)
    line = measured_basis([np.diag([0.04, UNKNOWN, UNKNOWN])])
    assert line.shape == (3, 1) and abs(line[0, 0]) == pytest.approx(1.0)


def test_a_frame_turned_about_z_is_fitted_from_horizontal_fixes() -> None:
    # A climbing arc, its fixes in a frame turned 120 deg about z and moved 50 m; the fixes' altitude
    # is unknown. The fit turns about z and moves in the plane; altitude, roll and pitch stay exact.
    yaw = np.radians(120.0)
    R = so3_exp(np.array([0.0, 0.0, yaw]))
    t = np.array([50.0, -20.0, 0.0])
    angle = np.arange(151) * 1.2 / 40.0
    local = np.stack([40.0 * np.sin(angle), 40.0 * (1.0 - np.cos(angle)), 0.1 * np.arange(151)], axis=1)
    frame = FixFrame()
    for k, x in enumerate(local):
        if k % 10 == 0:
            frame.add_fix(_horizontal_fix(k * DT_NS, R @ x + t, 0.01))
        frame.add_local(k * DT_NS, x, np.zeros((3, 3)))
    assert frame.required_spread() == pytest.approx(8 * 0.01)  # from the measured axes' noise
    fit = frame.fit()
    assert fit is not None
    np.testing.assert_allclose(fit.T_world_local[:3, :3], R, atol=2e-3)
    np.testing.assert_allclose(fit.T_world_local[:3, 3], t, atol=0.05)
    unmeasured = [2, 3, 4]  # z offset, rotations about x and y
    assert np.all(fit.covariance[unmeasured] == 0.0) and np.all(fit.covariance[:, unmeasured] == 0.0)
    assert fit.covariance[5, 5] > 0.0


def test_smoothing_on_horizontal_fixes_leaves_the_altitude() -> None:
    stamps = np.arange(50, dtype=np.int64) * DT_NS
    positions = np.stack([np.arange(50.0), np.zeros(50), np.full(50, 5.0)], axis=1)
    path = Trajectory(stamps, positions, np.tile([0.0, 0.0, 0.0, 1.0], (50, 1)))
    fixes = positions[::5] + np.array([0.3, -0.2, 0.0])
    fixes[:, 2] = 0.0
    smoothed, report = smoothed_on_fixes(
        path, np.zeros((50, 3)), stamps[::5], fixes, np.tile([0.01, 0.01, UNKNOWN], (10, 1))
    )
    assert report["applied"]
    np.testing.assert_allclose(smoothed.positions[:, 2], 5.0)  # not pulled to the placeholder 0
    np.testing.assert_allclose(smoothed.positions[:, :2] - positions[:, :2], [[0.3, -0.2]] * 50, atol=0.05)


@pytest.mark.parametrize("z_variance", [UNKNOWN, 0.0])
@pytest.mark.parametrize("name", ["ekf", "fastslam"])
def test_filters_use_horizontal_fixes_in_a_turned_frame(name: str, z_variance: float) -> None:
    yaw = np.radians(90.0)
    R = so3_exp(np.array([0.0, 0.0, yaw]))
    t = np.array([40.0, -10.0, 0.0])
    sim = simulate(SimulationConfig(iterations=200, density=25, seed=1, fix_every=2, fix_noise=0.5))

    def inputs():  # type: ignore[no-untyped-def]
        for step in sim.steps():
            yield step.observation
            if step.fix is not None:
                yield _horizontal_fix(step.fix.stamp_ns, R @ step.fix.position + t, 0.5, z_variance)

    if name == "ekf":
        estimator = EkfSlam(EkfConfig(observation_sigma=0.3))
    else:
        estimator = FastSlam(FastSlamConfig(particles=10, observation_sigma=0.3), np.random.default_rng(0))
    result = pipeline.run(inputs(), estimator)
    assert result.summary["fix_frame"] == "fixes" and result.summary["fixes"] > 20
    truth = sim.ground_truth.positions @ R.T + t
    horizontal = result.trajectory.positions[:, :2] - truth[:, :2]
    assert np.sqrt(np.mean(np.sum(horizontal**2, axis=1))) < 0.5  # in the fixes' frame (160 m off unpinned)
    # the altitude is the filter's own: the start's, not the fixes' placeholder
    assert abs(result.trajectory.positions[0, 2] - truth[0, 2]) < 0.5


def test_the_fit_on_measured_axes_ignores_the_placeholder_axis() -> None:
    rng = np.random.default_rng(4)
    source = rng.normal(0.0, 10.0, (30, 3))
    R = so3_exp(np.array([0.0, 0.0, np.radians(-70.0)]))
    target = source @ R.T + np.array([3.0, -4.0, 0.0])
    target[:, 2] = rng.normal(0.0, 50.0, 30)  # what a horizontal fix reports as altitude
    plane = measured_basis([np.diag([1.0, 1.0, UNKNOWN])])
    fit = fit_rigid_on_axes(source, target, np.ones(30), plane)
    np.testing.assert_allclose(fit.rotation, R, atol=1e-9)
    np.testing.assert_allclose(fit.translation, [3.0, -4.0, 0.0], atol=1e-9)
    assert fit.rms < 1e-9
    assert fit_rigid(source, target).rms > 10.0  # the 3-D fit follows the placeholder
    line = measured_basis([np.diag([UNKNOWN, 1.0, UNKNOWN])])
    along = fit_rigid_on_axes(source, source + np.array([5.0, 2.0, -7.0]), np.ones(30), line)
    np.testing.assert_allclose(along.rotation, np.eye(3))
    np.testing.assert_allclose(along.translation, [0.0, 2.0, 0.0], atol=1e-9)
    assert fitted_parameters(plane).shape == (6, 3) and fitted_parameters(line).shape == (6, 1)
    np.testing.assert_allclose(np.abs(fitted_parameters(plane)[5, 2]), 1.0)  # the rotation about z
    np.testing.assert_array_equal(fitted_parameters(np.eye(3)), np.eye(6))


def test_fixes_at_ten_per_iteration_keep_their_whole_span_and_pin_the_frame() -> None:
    # GNSS at 10 Hz beside clouds at 1 Hz: the kept fixes must still span the whole path (halving them
    # at every pass kept only the last few seconds and the first fix: the frame never pinned).
    angle = np.arange(250) * 1.5 / 30.0
    local = np.stack([30.0 * np.sin(angle), 30.0 * (1.0 - np.cos(angle)), np.zeros(250)], axis=1)
    rng = np.random.default_rng(2)
    pinned = {}
    for per_iteration in (1, 10):
        frame = FixFrame()
        for k, x in enumerate(local):
            fit = frame.update(k * DT_NS, x, np.zeros((3, 3)))
            if fit is not None:
                pinned[per_iteration] = k
                break
            if k + 1 < len(local):
                for j in range(per_iteration):
                    f = j / per_iteration
                    position = (1 - f) * x + f * local[k + 1] + rng.normal(0.0, 1.0, 3)
                    frame.add_fix(PositionFix(k * DT_NS + int(f * DT_NS) + 1, position, np.eye(3)))
        stamps = frame.fix_stamps
        assert len(stamps) <= frame.max_fixes and np.max(np.diff(stamps)) < 0.1 * (stamps[-1] - stamps[0])
    assert set(pinned) == {1, 10}
    assert pinned[10] <= pinned[1] + 5  # ten times the fixes pin it no later


def test_an_unfilled_axis_of_zero_variance_is_taken_as_unmeasured() -> None:
    screen = InputScreen()
    fix = screen.fix(_horizontal_fix(0, np.array([1.0, 2.0, 3.0]), 0.2, z_variance=0.0))
    assert fix is not None and fix.covariance[2, 2] == UNMEASURED_VARIANCE
    np.testing.assert_allclose(fix.covariance[:2, :2], np.diag([0.04, 0.04]))
    assert measured_basis([fix.covariance]).shape == (3, 2)
    assert screen.unmeasured_axes == 1 and not screen.skipped
    assert screen.fix(PositionFix(1, np.zeros(3), np.zeros((3, 3)))) is None  # all zero: unknown, dropped
