"""In-loop fusion of position fixes (issue 7) in EKF-SLAM and FastSLAM: the rigid fit that pins the local
frame, the covariance-weighted fusion of a pose with a fix (eq. 31-32), and short runs on figure8-gaps."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from relpoint.errors import UsageError
from relpoint.estimators._fix_frame import FixFrame, FrameFit, line_spread
from relpoint.estimators.ekf import EkfConfig, EkfSlam
from relpoint.estimators.fastslam import FastSlam, FastSlamConfig
from relpoint.fusion.covariance_fusion import fuse_estimates
from relpoint.simulation import SimulationConfig, simulate
from relpoint.simulation.scenario import GAPS_START_HEADING, GAPS_START_POSITION
from relpoint.types import PositionFix

DT_NS = 100_000_000


def _known_transform() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [35.0, 4.0, -3.0], degrees=True).as_matrix()
    T[:3, 3] = [60.0, -40.0, -15.0]
    return T


def _arc(n: int) -> np.ndarray:
    """Local positions (n, 3) along a climbing arc of radius 95 m, 1.2 m apart."""
    angle = np.arange(n) * 1.2 / 95.0
    return np.stack([95.0 * np.sin(angle), 95.0 * (1.0 - np.cos(angle)), 0.1 * np.arange(n)], axis=1)


def test_fit_reproduces_a_known_transform() -> None:
    T = _known_transform()
    local = _arc(101)
    frame = FixFrame(min_spread=3.0)
    for k, x in enumerate(local):
        if k % 10 == 0:
            frame.add_fix(PositionFix(k * DT_NS, T[:3, :3] @ x + T[:3, 3], np.eye(3) * 1e-6))
        frame.add_local(k * DT_NS, x, np.zeros((3, 3)))
    fit = frame.fit()
    assert fit is not None and fit.fixes == 11
    # The interpolated fixes between two fixes are off the arc by the quadratic's error, millimetres.
    np.testing.assert_allclose(fit.T_world_local, T, atol=2e-3)
    assert np.all(np.linalg.eigvalsh(fit.covariance) > 0)
    # The rotation about the nearly straight arc is the least determined direction.
    assert fit.covariance[3:, 3:].max() < 1e-6


def test_fit_waits_for_fixes_off_a_line() -> None:
    frame = FixFrame(min_spread=3.0)
    T = _known_transform()
    for k in range(60):
        x = np.array([1.2 * k, 0.0, 0.0])
        if k % 10 == 0:
            frame.add_fix(PositionFix(k * DT_NS, T[:3, :3] @ x + T[:3, 3], np.eye(3)))
        frame.add_local(k * DT_NS, x, np.zeros((3, 3)))
    assert frame.fix_count == 6 and line_spread(np.array([T[:3, 3], T[:3, 3] + 1.0, T[:3, 3] + 2.0])) < 1e-9
    assert frame.fit() is None  # collinear: the rotation about the line is free
    # The provisional transform still carries the direction of travel onto the fixes'.
    x = np.array([10.0, 0.0, 0.0])
    np.testing.assert_allclose(frame.provisional[:3, :3] @ x, T[:3, :3] @ x, atol=1e-9)


@pytest.mark.parametrize("options", [{"fix_alignment": "gps"}, {"fix_min_spread": 0.0}, {"fix_window": -1}])
def test_configs_reject_bad_fix_settings(options: dict[str, object]) -> None:
    with pytest.raises(UsageError):
        EkfConfig(**options)  # type: ignore[arg-type]
    with pytest.raises(UsageError):
        FastSlamConfig(**options)  # type: ignore[arg-type]


def _gaps(iterations: int, fix_noise: float = 1.0) -> list:  # type: ignore[type-arg]
    sim = simulate(
        SimulationConfig(scenario="figure8-gaps", fix_every=10, fix_noise=fix_noise, iterations=iterations, seed=1)
    )
    return list(sim.steps())


def _drive(estimator: EkfSlam | FastSlam, steps: list, with_fixes: bool = True) -> np.ndarray:  # type: ignore[type-arg]
    errors = []
    for step in steps:
        if with_fixes and step.fix is not None:
            estimator.add_fix(step.fix)
        pose = estimator.step(step.observation)
        errors.append(np.linalg.norm(np.array(pose.position) - step.T_world_sensor[:3, 3]))
    return np.array(errors)


def test_ekf_moves_its_state_into_the_fixes_frame() -> None:
    ekf = EkfSlam(EkfConfig())
    _drive(ekf, _gaps(130, fix_noise=0.05))
    fit = ekf.frame_fit
    assert fit is not None and ekf.summary()["fix_frame"] == "fixes"
    heading = np.rad2deg(Rotation.from_matrix(fit.T_world_local[:3, :3]).as_euler("zyx")[0])
    assert heading == pytest.approx(GAPS_START_HEADING, abs=0.5)
    np.testing.assert_allclose(fit.T_world_local[:3, 3], GAPS_START_POSITION, atol=0.5)
    P = ekf.covariance
    assert np.abs(P - P.T).max() <= 1e-12 * np.abs(P).max() and np.linalg.eigvalsh(P).min() > -1e-9 * np.abs(P).max()


def test_ekf_fused_position_variance_is_below_both_inputs() -> None:
    ekf = EkfSlam(EkfConfig(fix_drift=0.0, fix_min_spread=3.0))
    steps = _gaps(90)
    _drive(ekf, steps)
    assert ekf.frame_fit is not None
    prior_position, prior = np.array(ekf.pose().position), ekf.covariance[:3, :3]
    fix = PositionFix(steps[-1].stamp_ns, prior_position + np.array([1.0, -0.5, 0.3]), np.diag([1.0, 0.8, 1.2]))
    ekf.add_fix(fix)  # at the state's stamp: no prediction in between
    posterior = ekf.covariance[:3, :3]
    # Eq. 31-32: the Kalman update on the position is the covariance-weighted fusion.
    expected_position, expected = fuse_estimates(prior_position, prior, fix.position, fix.covariance)
    np.testing.assert_allclose(ekf.pose().position, expected_position, atol=1e-9)
    np.testing.assert_allclose(posterior, expected, atol=1e-12)
    for other in (prior, fix.covariance):
        assert np.linalg.eigvalsh(other - posterior).min() > 0
        assert np.all(np.diag(posterior) < np.diag(other))


def test_fastslam_fused_particle_variance_is_below_both_inputs() -> None:
    slam = FastSlam(FastSlamConfig(particles=10, fix_min_spread=3.0), np.random.default_rng(0))
    steps = _gaps(90)
    _drive(slam, steps)
    assert slam.frame_fit is not None
    before_positions, before = slam.positions.copy(), slam.position_covariance()
    before_rotations = slam.rotations.copy()
    fix = PositionFix(steps[-1].stamp_ns, before_positions.mean(axis=0) + np.array([2.0, 0.0, -1.0]), np.eye(3) * 0.5)
    slam.add_fix(fix)
    expected_positions, expected = fuse_estimates(
        before_positions, before, np.tile(fix.position, (10, 1)), fix.covariance
    )
    # The frame's share of the correction is a turn about the fit's centre (pose, heading and map
    # together), the rest a shift: to first order the position is eq. 31-32's; the turn's second
    # order is millimetres here (measured up to 7 mm, 100 m from the centre).
    np.testing.assert_allclose(slam.positions, expected_positions, atol=0.02)
    after = slam.position_covariance(before_positions)  # where the fix's gain was computed
    np.testing.assert_allclose(after, expected, atol=1e-12)
    turned = np.degrees(
        np.linalg.norm(Rotation.from_matrix(slam.rotations @ np.swapaxes(before_rotations, 1, 2)).as_rotvec(), axis=1)
    )
    assert (turned > 1e-3).all() and (turned < 5.0).all()
    for p in range(10):
        for other in (before[p], fix.covariance):
            assert np.linalg.eigvalsh(other - after[p]).min() > 0
    assert slam.weights.sum() == pytest.approx(1.0, abs=1e-12)


def test_ekf_short_run_with_fixes_ends_closer_to_truth() -> None:
    steps = _gaps(160)
    with_fixes = _drive(EkfSlam(EkfConfig()), steps)
    without = _drive(EkfSlam(EkfConfig()), steps, with_fixes=False)
    # Measured: final error 1.0 m with fixes, 77 m without (the local frame starts at the identity).
    assert with_fixes[-1] < 2.0
    assert with_fixes[-1] < 0.1 * without[-1]
    assert np.sqrt(np.mean(with_fixes[-40:] ** 2)) < 2.0


@pytest.mark.parametrize(("variant", "bound", "ratio"), [("2.0", 3.0, 0.1), ("1.0", 16.0, 0.5)])
def test_fastslam_short_run_with_fixes_ends_closer_to_truth(variant: str, bound: float, ratio: float) -> None:
    # 10 particles with fixes, 5 without, pinned at iteration 121, one fix after it. 2.0 ends 1.2-3.7 m
    # from the truth with fixes over seeds 1-20 (median 2.31 m, mean 2.25 m; 2.12 and 2.11 m before a
    # fix turned the particles' frame, which keeps the heading with the fixes on longer runs), 27-28 m without;
    # 1.0 ends 7.0-15.1 m off (45-58 m without): its motion-model proposal turns the map in a way the
    # fixes correct only slowly. One seed alone is a coin toss for both, and so is a median of three
    # (seeds 1-3 of 2.0 end 1.7-3.7 m off), so both bounds are on the median over five seeds.
    steps = _gaps(140)
    finals, ratios = [], []
    for seed in (1, 2, 3, 4, 5):
        with_fixes = _drive(FastSlam(FastSlamConfig(variant=variant, particles=10), np.random.default_rng(seed)), steps)
        without = _drive(
            FastSlam(FastSlamConfig(variant=variant, particles=5), np.random.default_rng(seed)), steps, with_fixes=False
        )
        finals.append(with_fixes[-1])
        ratios.append(with_fixes[-1] / without[-1])
    assert np.median(finals) < bound, finals
    assert np.median(ratios) < ratio, ratios


def test_fastslam_ignores_fixes_when_told() -> None:
    steps = _gaps(40)
    slam = FastSlam(FastSlamConfig(particles=5, fix_alignment="ignore"), np.random.default_rng(0))
    errors = _drive(slam, steps)
    assert slam.frame_fit is None and "fix_frame" not in slam.summary()
    assert errors[0] == pytest.approx(np.linalg.norm(GAPS_START_POSITION), abs=1e-9)


def test_frame_is_pinned_when_fixes_spread_after_a_full_window_of_collinear_ones() -> None:
    # More collinear fixes than the frame keeps: the fix count stays bounded, but every new fix
    # must still trigger a fit, so the first fix off the line pins the frame.
    frame = FixFrame(min_fixes=3, min_spread=8.0, max_fixes=5)
    covariance = np.eye(3)
    for k in range(8):
        stamp = k * 10**9
        frame.add_fix(PositionFix(stamp, np.array([10.0 * k, 0.0, 0.0]), covariance))
        assert frame.update(stamp, np.array([10.0 * k, 0.0, 0.0]), 0.01 * covariance) is None
    assert 3 <= frame.fix_count <= 5
    turn = [(8, (70.0, 30.0, 0.0)), (9, (70.0, 60.0, 0.0)), (10, (70.0, 90.0, 0.0))]
    fits = []
    for k, position in turn:
        frame.add_fix(PositionFix(k * 10**9, np.array(position), covariance))
        fits.append(frame.update(k * 10**9, np.array(position), 0.01 * covariance))
    fit = next(f for f in fits if f is not None)
    np.testing.assert_allclose(fit.T_world_local, np.eye(4), atol=1e-6)


def test_fastslam_follows_fixes_after_drifting_through_a_stretch_without_landmarks() -> None:
    """figure8-gaps' landmark-free stretches leave the particles metres off with a small covariance;
    the fixes keep failing the gate. After the gate's patience the particles' covariance grows until
    the fix lies on the gate's edge, and the fixes pull them back. Seed 2, 500 iterations, 10
    particles (9 fixes inflated): the filter's own poses 13.8 m RMS, the run's trajectory 1.6 m (fixes
    alone 1.8 m). Seed 1 was 8.9 m RMS against 125 m when the fix's covariance was inflated instead;
    since the particles' covariance carries the frame's rotation uncertainty far from the fit's
    centre, no fix of seed 1 falls outside the gate for long (2.8 m RMS, 1.4 m)."""
    from relpoint import pipeline

    steps = _gaps(500)
    online = FastSlam(FastSlamConfig(particles=10), np.random.default_rng(2))
    errors = _drive(online, steps)
    assert online.summary()["fixes_inflated"] > 0
    assert np.sqrt(np.mean(errors**2)) < 20.0

    def inputs():  # type: ignore[no-untyped-def]
        for step in steps:
            if step.fix is not None:
                yield step.fix
            yield step.observation

    result = pipeline.run(inputs(), FastSlam(FastSlamConfig(particles=10), np.random.default_rng(2)))
    truth = np.array([step.T_world_sensor[:3, 3] for step in steps])
    fixes = np.array([s.fix.position - s.T_world_sensor[:3, 3] for s in steps if s.fix is not None])
    ate = np.sqrt(np.mean(np.sum((result.trajectory.positions - truth) ** 2, axis=1)))
    assert ate < 2.0 * np.sqrt(np.mean(np.sum(fixes**2, axis=1)))


def test_ekf_is_not_lost_after_a_stretch_without_landmarks() -> None:
    """figure8-gaps seed 3: past the fix gate's patience the EKF fuses each fix as it is. With the fix's
    covariance inflated onto the gate's edge instead, the filter never came back: 84.6 m, 3,940 map
    entries (4.3 m and 362 now; fixes alone 1.7 m)."""
    from relpoint import pipeline

    sim = simulate(SimulationConfig(scenario="figure8-gaps", fix_every=10, seed=3))
    steps = list(sim.steps())

    def inputs():  # type: ignore[no-untyped-def]
        for step in steps:
            if step.fix is not None:
                yield step.fix
            yield step.observation

    estimator = EkfSlam(EkfConfig())
    result = pipeline.run(inputs(), estimator)
    truth = np.array([step.T_world_sensor[:3, 3] for step in steps])
    ate = np.sqrt(np.mean(np.sum((result.trajectory.positions - truth) ** 2, axis=1)))
    assert estimator.summary()["fixes_inflated"] > 0  # the gate saw the drift
    assert ate < 10.0 and len(result.landmarks) < 1000


def _moved_fix_inputs(sim: object, T: np.ndarray) -> list[object]:
    """The simulation's observations and its fixes, the fixes given in a frame ``T`` away from its start."""
    items: list[object] = []
    for step in sim.steps():  # type: ignore[attr-defined]
        items.append(step.observation)
        if step.fix is not None:
            R = T[:3, :3]
            items.append(
                PositionFix(step.fix.stamp_ns, R @ step.fix.position + T[:3, 3], R @ step.fix.covariance @ R.T)
            )
    return items


@pytest.mark.parametrize("name", ["ekf", "fastslam"])
@pytest.mark.parametrize("pinned", [False, True])
def test_output_before_the_frame_is_pinned_is_placed_by_one_transform(name: str, pinned: bool) -> None:
    # The fixes' frame is turned 90 degrees and 40 m away from the sensor's start. Before the fixes pin
    # the frame (or when they never do) each pose was output under the provisional transform of its
    # iteration; at the end every pose is in one frame: no jump between consecutive poses.
    from relpoint import pipeline
    from relpoint.evaluation import umeyama

    T = _known_transform()
    sim = simulate(SimulationConfig(iterations=120, density=25, seed=2, fix_every=10, fix_noise=0.2))
    spread = 3.0 if pinned else 1e5
    if name == "ekf":
        estimator = EkfSlam(EkfConfig(observation_sigma=0.3, fix_min_spread=spread))
    else:
        estimator = FastSlam(FastSlamConfig(particles=10, observation_sigma=0.3, fix_min_spread=spread),
                             np.random.default_rng(0))  # fmt: skip
    result = pipeline.run(_moved_fix_inputs(sim, T), estimator)
    assert (estimator.frame_fit is not None) == pinned
    matrices = result.trajectory.matrices()
    truth = sim.ground_truth.matrices()
    steps = np.einsum("kji,kjl->kil", matrices[:-1, :3, :3], matrices[1:, :3, :3])  # R_k^T R_k+1
    true_steps = np.einsum("kji,kjl->kil", truth[:-1, :3, :3], truth[1:, :3, :3])
    turn = np.degrees(np.arccos(np.clip((np.trace(steps, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    true_turn = np.degrees(np.arccos(np.clip((np.trace(true_steps, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert np.max(np.abs(turn - true_turn)) < 3.0
    jumps = np.linalg.norm(np.diff(matrices[:, :3, 3], axis=0), axis=1)
    true_jumps = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)
    assert np.max(np.abs(jumps - true_jumps)) < 1.0
    positions = matrices[:, :3, 3]
    R, t, _ = umeyama(positions, truth[:, :3, 3])
    assert np.sqrt(np.mean(np.sum((positions @ R.T + t - truth[:, :3, 3]) ** 2, axis=1))) < 1.0
    if name == "fastslam":  # pinned: the drift rate measured on the fixes, the poses in the final draw's frame
        summary = estimator.summary()
        assert ("drift_rate" in summary and "frame_refined_deg" in summary) == pinned


@pytest.mark.parametrize("sigma", [0.2, 1.0, 5.0])
def test_the_spread_a_fit_needs_scales_with_the_fixes_noise(sigma: float) -> None:
    # The rotation about the fixes' best line is known to about noise / spread: the default asks the
    # same 8 noises at any noise (8 m for 1 m fixes, as the fixed default did).
    T = _known_transform()
    local = _arc(400)
    frame = FixFrame()
    pinned_at = None
    for k, x in enumerate(local):
        if k % 10 == 0:
            frame.add_fix(PositionFix(k * DT_NS, T[:3, :3] @ x + T[:3, 3], np.eye(3) * sigma**2))
        if frame.update(k * DT_NS, x, np.zeros((3, 3))) is not None:
            pinned_at = k
            break
    assert frame.required_spread() == pytest.approx(8.0 * sigma)
    assert pinned_at is not None
    fixes = np.array([T[:3, :3] @ x + T[:3, 3] for x in local[: pinned_at + 1 : 10]])
    assert 8.0 * sigma <= line_spread(fixes) < 8.0 * sigma + 2.0
    assert FixFrame(min_spread=3.0).required_spread() == 3.0


def _pinned_far_from_the_fit_centre(distance: float, seed: int = 0) -> FastSlam:
    """FastSLAM pinned by a fit with a few degrees of rotation uncertainty about its centre (the
    origin, where the particles were), whose particles have since travelled ``distance`` m along x,
    where the frame's rotation uncertainty alone puts metres of uncertainty on their position."""
    slam = FastSlam(FastSlamConfig(particles=20), np.random.default_rng(seed))
    covariance = np.diag([0.2, 0.2, 0.2, 0.006, 0.002, 0.001])
    slam._pin_frame(FrameFit(np.eye(4), covariance, np.zeros(3), pairs=30, fixes=4, rms=0.7, spread=8.0))
    # Each particle travelled in its own drawn frame: x -> Exp(dphi) x + dt about the centre.
    turn = Rotation.from_rotvec(slam._frame_draws[:, 3:]).as_matrix()
    slam.positions = np.einsum("pij,j->pi", turn, [distance, 0.0, 0.0]) + slam._frame_draws[:, :3]
    return slam


@pytest.mark.parametrize("distance", [10.0, 50.0, 200.0])
def test_fastslam_fixes_far_from_the_fit_centre_keep_the_frame_bounded(distance: float) -> None:
    """The frame fit's rotation uncertainty is metres of position uncertainty far from its centre.
    When a particle's position covariance left that lever arm out, the frame's share of each fix's
    correction exceeded the fix's own and the frame's covariance lost its positive definiteness; the
    fixes then turned the frame further each time (a foreign log: 1e78 m after 8 fixes)."""
    slam = _pinned_far_from_the_fit_centre(distance)
    rng = np.random.default_rng(1)
    truth = np.array([distance, 0.0, 0.0])
    rotations = slam.rotations.copy()
    for k in range(12):
        slam.add_fix(PositionFix(k * DT_NS, truth + rng.normal(0.0, 1.0, 3), np.eye(3)))
        assert np.linalg.norm(slam.weights @ slam.positions - truth) < 3.0, k
    turned = np.degrees(
        np.linalg.norm(Rotation.from_matrix(slam.rotations @ np.swapaxes(rotations, 1, 2)).as_rotvec(), axis=1)
    )
    assert turned.max() < 15.0


def test_fastslam_drift_rate_leaves_the_frames_error_out() -> None:
    """Fixes in a frame turned and moved from the sensor's start (1 m fixes every 20 iterations) pin a
    frame whose fit is off by a fraction of a degree; far from the fit's centre that is metres, which
    the drift rate counted as drift (0.024 m/m on this map, 0.1-0.4 on another tool's loop, where the
    fixes' noise was then fused into a centimetre-accurate map: 1.0 m against 0.03 m without fixes)."""
    from relpoint import pipeline

    sim = simulate(SimulationConfig(iterations=300, fix_every=20, fix_noise=1.0, seed=0))
    estimator = FastSlam(FastSlamConfig(particles=20), np.random.default_rng(0))
    pipeline.run(_moved_fix_inputs(sim, _known_transform()), estimator)
    assert estimator.frame_fit is not None and estimator.frame_fit.covariance.any()
    assert estimator.summary()["drift_rate"] < 1e-3
