"""EKF-SLAM: covariance properties, a hand-derived update, gating, JCBB vs nearest neighbour, fix
fusion, and short simulated runs with error bounds a regression would break."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from relpoint.errors import EstimatorError, UsageError
from relpoint.estimators._association import (
    chi2_gate,
    jcbb_search,
    mahalanobis_squared,
    nearest_neighbour,
)
from relpoint.estimators._noise import NoiseAdaptive
from relpoint.estimators.base import Estimator
from relpoint.estimators.ekf import INITIAL_CAPACITY, SPEC, EkfConfig, EkfSlam
from relpoint.geometry import invert_pose, so3_exp, transform_points, twist_step
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import PointObservation, PositionFix
from tests.conftest import run_accuracy, sharp_turn

DT_NS = 100_000_000


def _observe(stamp_ns: int, *points: tuple[float, float, float], ids: list[int] | None = None) -> PointObservation:
    return PointObservation(stamp_ns, np.array(points, dtype=np.float64), None if ids is None else np.array(ids))


def _run(config: EkfConfig, iterations: int, **sim_options: object) -> dict[str, float]:
    """Run the EKF on the figure eight; errors in the frame of the first true pose (where the EKF starts)."""
    sim = simulate(SimulationConfig(density=25, noise=0.3, iterations=iterations, seed=0, **sim_options))  # type: ignore[arg-type]
    ekf = EkfSlam(config)
    T_first_world = invert_pose(sim.ground_truth.matrices()[0])
    errors = []
    for step in sim.steps():
        if step.odometry is not None:
            ekf.add_odometry(step.odometry)
        pose = ekf.step(step.observation)
        truth = (T_first_world @ step.T_world_sensor)[:3, 3]
        errors.append(np.linalg.norm(np.array(pose.position) - truth))
    return run_accuracy(errors, ekf.landmark_map(), transform_points(T_first_world, sim.landmarks.positions))


# ----------------------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    "options",
    [
        {"association": "greedy"},
        {"motion": "teleport"},
        {"observation_sigma": 0.0},
        {"gate_probability": 1.0},
        {"gate_probability": 0.999, "new_landmark_probability": 0.99},
        {"linear_acceleration_noise": -1.0},
        {"jcbb_max_nodes": 0},
        {"jcbb_max_seconds": -1.0},
        {"fix_alignment": "umeyama"},
        {"fix_drift": -0.1},
    ],
)
def test_config_rejects_bad_values(options: dict[str, object]) -> None:
    with pytest.raises(UsageError):
        EkfConfig(**options)  # type: ignore[arg-type]


def test_config_from_mapping_rejects_unknown_keys_and_round_trips() -> None:
    config = EkfConfig.from_mapping({"association": "jcbb", "observation-sigma": 0.5})
    assert config == EkfConfig(association="jcbb", observation_sigma=0.5)
    assert EkfConfig.from_mapping(config.to_dict()) == config
    with pytest.raises(UsageError, match="gate"):
        EkfConfig.from_mapping({"gate": 0.9})


def test_spec_builds_an_ekf() -> None:
    given = EkfConfig(
        observation_sigma=0.3, linear_acceleration_noise=2.0, angular_acceleration_noise=0.5, odometry_check=False
    )
    assert isinstance(SPEC.factory(given, np.random.default_rng(0)), EkfSlam)
    # the odometry is checked against the first observations, which are held back for it
    checked = SPEC.factory(dataclasses.replace(given, odometry_check=True), np.random.default_rng(0))
    assert isinstance(checked, NoiseAdaptive)
    # an unset acceleration noise is taken from the first observations, the noise given is kept
    measured = SPEC.factory(EkfConfig(observation_sigma=0.3), np.random.default_rng(0))
    assert isinstance(measured, NoiseAdaptive) and measured.name == "ekf"
    estimated = SPEC.factory(EkfConfig(), np.random.default_rng(0))  # builds its EKF once it knows the noise
    assert isinstance(estimated, Estimator) and estimated.name == "ekf"
    assert SPEC.name == "ekf" and SPEC.needs == frozenset({"points"}) and SPEC.uses == frozenset({"odometry", "fix"})


# ----------------------------------------------------------------------------------- covariance


def test_covariance_stays_symmetric_positive_semidefinite() -> None:
    sim = simulate(SimulationConfig(density=25, noise=0.3, iterations=60, clutter=0.5, seed=3))
    ekf = EkfSlam(EkfConfig())
    for step in sim.steps():
        ekf.step(step.observation)
        P = ekf.covariance
        scale = np.abs(P).max()
        assert np.abs(P - P.T).max() <= 1e-12 * scale
        if step.index % 10 == 9:
            assert np.linalg.eigvalsh(P).min() >= -1e-9 * scale
    assert ekf.map_size > 20


# ---------------------------------------------------------------------------------- motion model


def test_motion_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(0)
    p, R = rng.normal(size=3), Rotation.random(random_state=1).as_matrix()
    v, w, dt = np.array([12.0, 0.3, -0.2]), np.array([0.1, -0.2, 0.5]), 0.1
    p1, R1, F_pose, G = twist_step(p, R, v, w, dt)
    analytic = np.hstack([F_pose, G])  # d(dp', dtheta') / d(dp, dtheta, dv, dw)
    numeric = np.zeros((6, 12))
    eps = 1e-6
    for k in range(12):
        e = np.zeros(12)
        e[k] = eps
        p2, R2, _, _ = twist_step(p + e[:3], R @ so3_exp(e[3:6]), v + e[6:9], w + e[9:], dt)
        numeric[:3, k] = (p2 - p1) / eps
        numeric[3:, k] = Rotation.from_matrix(R1.T @ R2).as_rotvec() / eps
    np.testing.assert_allclose(analytic, numeric, atol=1e-5)


# ------------------------------------------------------------------------------ hand-derived update


def test_single_landmark_update_matches_hand_derivation() -> None:
    sigma, sigma_p, sigma_theta = 0.3, 0.5, 0.02
    ekf = EkfSlam(
        EkfConfig(
            motion="constant_position",
            observation_sigma=sigma,
            position_noise=sigma_p,
            quaternion_noise=sigma_theta / 2,
            min_observations=1,  # the map shows the landmark seen once
        )
    )
    ekf.step(_observe(0, (10.0, 0.0, 0.0)))
    # The first pose anchors the world: the landmark is the point, with covariance sigma^2 I.
    np.testing.assert_allclose(ekf.landmark_map().positions, [[10.0, 0.0, 0.0]])
    np.testing.assert_allclose(ekf.covariance[6:9, 6:9], sigma**2 * np.eye(3))

    pose = ekf.step(_observe(DT_NS, (10.2, 0.1, 0.0)))
    # Prior: pose error diag(sp^2 I, st^2 I), landmark sigma^2 I, no cross terms. With R = I and
    # z_hat = (10, 0, 0): H = [-I, [z_hat]x, I], so S = diag(sp^2 + 2s^2, sp^2 + 100 st^2 + 2s^2, same).
    S = np.diag([sigma_p**2 + 2 * sigma**2] + [sigma_p**2 + 100 * sigma_theta**2 + 2 * sigma**2] * 2)
    nu = np.array([0.2, 0.1, 0.0])
    S_inv_nu = np.linalg.solve(S, nu)
    expected_position = -(sigma_p**2) * S_inv_nu  # dp = P_pp (-I) S^-1 nu
    expected_yaw = sigma_theta**2 * -10.0 * S_inv_nu[1]  # dtheta = P_tt [z]x^T S^-1 nu: z-component
    expected_landmark = np.array([10.0, 0.0, 0.0]) + sigma**2 * S_inv_nu
    np.testing.assert_allclose(pose.position, expected_position, atol=1e-12)
    yaw = 2.0 * np.arctan2(pose.quat_xyzw[2], pose.quat_xyzw[3])
    assert yaw == pytest.approx(expected_yaw, rel=1e-6)
    assert yaw < 0  # the landmark appeared further left: the sensor turned right
    np.testing.assert_allclose(ekf.landmark_map().positions[0], expected_landmark, atol=1e-12)
    expected_landmark_cov = sigma**2 * np.eye(3) - sigma**4 * np.linalg.inv(S)
    np.testing.assert_allclose(ekf.covariance[6:9, 6:9], expected_landmark_cov, atol=1e-12)
    assert ekf.landmark_map().observations.tolist() == [2]


def _dense_update(ekf: EkfSlam, points: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The textbook update on the full state: dense H, gain, Joseph form, then the rotation-error reset.

    Returns the error-state estimate dx (N,) and the covariance (N, N) after the reset.
    """
    P = ekf.covariance
    N, m = len(P), len(indices)
    R, p = ekf.pose().as_matrix()[:3, :3], ekf.pose().as_matrix()[:3, 3]
    nv = N - 3 * ekf.map_size
    landmarks = ekf.landmark_map().positions[indices]
    z_hat = (landmarks - p) @ R
    H = np.zeros((3 * m, N))
    for row, (j, z) in enumerate(zip(indices, z_hat, strict=True)):
        H[3 * row : 3 * row + 3, :3] = -R.T
        H[3 * row : 3 * row + 3, 3:6] = np.cross(np.eye(3), z)  # [z]x
        H[3 * row : 3 * row + 3, nv + 3 * j : nv + 3 * j + 3] = R.T
    R_meas = ekf.config.observation_sigma**2 * np.eye(3 * m)
    S = H @ P @ H.T + R_meas
    K = P @ H.T @ np.linalg.inv(S)
    dx = K @ (points - z_hat).ravel()
    I_KH = np.eye(N) - K @ H
    P_new = I_KH @ P @ I_KH.T + K @ R_meas @ K.T
    reset = np.eye(N)
    reset[3:6, 3:6] = np.eye(3) - 0.5 * np.cross(np.eye(3), dx[3:6])
    return dx, reset @ P_new @ reset.T


def test_batched_update_matches_dense_update_after_the_covariance_block_grew() -> None:
    rng = np.random.default_rng(7)
    world = rng.uniform([8.0, -20.0, -5.0], [40.0, 20.0, 5.0], size=(120, 3))
    ekf = EkfSlam(EkfConfig(motion="constant_position", observation_sigma=0.3))
    ekf.step(PointObservation(0, world))
    ekf.step(PointObservation(DT_NS, world + rng.normal(0.0, 0.3, world.shape)))  # correlates pose and map
    assert ekf.covariance.shape[0] > INITIAL_CAPACITY  # 6 + 360 states: the block has grown
    assert ekf.summary()["paired"] == 120
    ekf._predict_to(2 * DT_NS)
    indices = rng.permutation(120)[:90]
    position, R = ekf.pose().as_matrix()[:3, 3], ekf.pose().as_matrix()[:3, :3]
    before = ekf.landmark_map().positions
    points = (before[indices] - position) @ R + rng.normal(0.0, 0.3, (90, 3))
    dx, expected_P = _dense_update(ekf, points, indices)

    ekf._update_landmarks(points, indices)
    np.testing.assert_allclose(ekf.pose().position, position + dx[:3], atol=1e-10)
    np.testing.assert_allclose(ekf.landmark_map().positions, before + dx[6:].reshape(-1, 3), atol=1e-10)
    np.testing.assert_allclose(ekf.covariance, expected_P, atol=1e-10)
    assert np.array_equal(ekf.covariance, ekf.covariance.T)  # the symmetric rank update keeps P exactly symmetric


def test_removing_landmarks_keeps_the_covariance_of_the_rest() -> None:
    rng = np.random.default_rng(8)
    world = rng.uniform([8.0, -20.0, -5.0], [40.0, 20.0, 5.0], size=(100, 3))
    ekf = EkfSlam(EkfConfig(motion="constant_position", observation_sigma=0.3))
    ekf.step(PointObservation(0, world))
    ekf.step(PointObservation(DT_NS, world + rng.normal(0.0, 0.3, world.shape)))
    before = ekf.covariance
    ekf._remove_landmarks(np.arange(0, 100, 2))
    keep = np.concatenate([np.arange(6), (6 + 3 * np.arange(1, 100, 2)[:, None] + np.arange(3)).ravel()])
    np.testing.assert_array_equal(ekf.covariance, before[np.ix_(keep, keep)])
    assert ekf.summary()["state_size"] == 6 + 150


# ---------------------------------------------------------------------------------------- gating


@pytest.mark.parametrize(
    ("offset", "paired", "started", "discarded"),
    [
        (0.5, 1, 0, 0),  # inside the 0.99 gate: updates the landmark
        (1.7, 0, 0, 1),  # between the 0.99 and 0.9999 gates: too doubtful for either
        (5.0, 0, 1, 0),  # an outlier: rejected by the gate, starts its own landmark
    ],
)
def test_gate_accepts_inlier_and_rejects_outlier(offset: float, paired: int, started: int, discarded: int) -> None:
    ekf = EkfSlam(EkfConfig(motion="constant_position", min_observations=1))  # map_size counts landmarks seen once
    ekf.step(_observe(0, (10.0, 0.0, 0.0)))
    # S_xx = 0.10^2 (position noise) + 2 * 0.3^2 = 0.19: the 0.99 gate is |dx| < 1.47 m, the 0.9999 one 2.0 m.
    assert np.sqrt(chi2_gate(0.99, 3) * 0.19) == pytest.approx(1.468, abs=1e-3)
    ekf.step(_observe(DT_NS, (10.0 + offset, 0.0, 0.0)))
    summary = ekf.summary()
    assert (summary["paired"], summary["started"] - 1, summary.get("discarded", 0)) == (paired, started, discarded)
    assert ekf.map_size == 1 + started


# ------------------------------------------------------------------------------------ JCBB vs NN


def _shifted_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two landmarks 2 m apart seen through a shared 1 m pose uncertainty, both shifted 1.1 m along y."""
    predicted = np.array([[10.0, 0.0, 0.0], [10.0, 2.0, 0.0]])
    points = predicted + np.array([0.0, 1.1, 0.0])
    covariance = np.kron(np.ones((2, 2)), np.eye(3))  # perfectly correlated translation, landmarks exact
    observation_cov = 0.01 * np.eye(3)
    innovations = points[:, None, :] - predicted[None, :, :]
    S = np.stack([covariance[:3, :3], covariance[3:, 3:]]) + observation_cov
    d2 = mahalanobis_squared(innovations, np.linalg.inv(S))
    return d2, innovations, covariance, observation_cov


def test_jcbb_resolves_ambiguous_pair_that_nearest_neighbour_gets_wrong() -> None:
    d2, innovations, covariance, observation_cov = _shifted_pair()
    gate = chi2_gate(0.99, 3)
    assert (d2 < gate).all()  # every pairing is individually compatible: a genuine ambiguity
    nn, gated = nearest_neighbour(d2, gate)
    assert gated.all()
    assert nn.tolist() == [1, 0]  # the first point is nearest to the second landmark: both pairings wrong
    assert jcbb_search(d2, innovations, covariance, observation_cov)[0].tolist() == [0, 1]


def test_jcbb_drops_a_pairing_that_breaks_joint_compatibility() -> None:
    d2, innovations, covariance, observation_cov = _shifted_pair()
    # Move the second point against the common shift: each point still gates on its own, together they cannot.
    innovations = innovations.copy()
    innovations[1] -= [0.0, 2.0, 0.0]
    S_inv = np.linalg.inv(np.stack([covariance[:3, :3], covariance[3:, 3:]]) + observation_cov)
    d2 = mahalanobis_squared(innovations, S_inv)
    assignment = jcbb_search(d2, innovations, covariance, observation_cov)[0]
    assert (assignment >= 0).sum() == 1


def test_jcbb_says_when_its_time_budget_runs_out() -> None:
    d2, innovations, covariance, observation_cov = _shifted_pair()
    assignment, gave_up = jcbb_search(d2, innovations, covariance, observation_cov, max_seconds=60.0)
    assert not gave_up
    assert assignment.tolist() == [0, 1]
    assignment, gave_up = jcbb_search(d2, innovations, covariance, observation_cov, max_seconds=1e-12)
    assert gave_up
    assert assignment.tolist() == [-1, -1]  # stopped before its first node: nothing paired
    assignment, gave_up = jcbb_search(d2, innovations, covariance, observation_cov, max_nodes=1)
    assert gave_up


def test_ekf_counts_and_warns_when_jcbb_gives_up(caplog: pytest.LogCaptureFixture) -> None:
    config = EkfConfig(association="jcbb", motion="constant_position", observation_sigma=0.1, jcbb_max_seconds=1e-12)
    ekf = EkfSlam(config)
    assert ekf.summary()["jcbb_gave_up"] == 0
    ekf.step(_observe(0, (10.0, 0.0, 0.0), (10.0, 2.0, 0.0)))
    with caplog.at_level("WARNING", logger="relpoint.estimators.ekf"):
        for i in range(1, 4):
            ekf.step(_observe(i * DT_NS, (10.0, 0.01 * i, 0.0), (10.0, 2.0, 0.0)))
    assert ekf.summary()["jcbb_gave_up"] == 3
    assert ekf.summary()["paired"] == 0
    assert len([r for r in caplog.records if "JCBB ran out of its budget" in r.getMessage()]) == 1


@pytest.mark.parametrize(("association", "expected_y"), [("jcbb", -1.1), ("nn", None)])
def test_ekf_association_on_ambiguous_pair(association: str, expected_y: float | None) -> None:
    ekf = EkfSlam(
        EkfConfig(
            association=association,
            motion="constant_position",
            observation_sigma=0.1,
            position_noise=1.0,
            quaternion_noise=1e-5,
        )
    )
    ekf.step(_observe(0, (10.0, 0.0, 0.0), (10.0, 2.0, 0.0), ids=[0, 1]))
    pose = ekf.step(_observe(DT_NS, (10.0, 1.1, 0.0), (10.0, 3.1, 0.0), ids=[0, 1]))
    landmarks = ekf.landmark_map()
    if expected_y is not None:
        # Right pairing: the shared shift is the sensor's motion; the landmarks stay where they were.
        assert pose.position[1] == pytest.approx(expected_y, abs=0.05)
        np.testing.assert_allclose(landmarks.positions, [[10.0, 0.0, 0.0], [10.0, 2.0, 0.0]], atol=0.05)
        assert landmarks.gt_id.tolist() == [0, 1]
    else:
        # Crossed pairing: the mean shift still moves the sensor, but the landmarks are dragged about
        # 0.4 m towards each other's points.
        assert np.abs(landmarks.positions - [[10.0, 0.0, 0.0], [10.0, 2.0, 0.0]]).max() > 0.3


def test_known_association_needs_ids() -> None:
    ekf = EkfSlam(EkfConfig(association="known"))
    with pytest.raises(EstimatorError):
        ekf.step(_observe(0, (10.0, 0.0, 0.0)))


# ----------------------------------------------------------------------------------------- fixes


def test_fix_is_fused_weighted_by_covariances() -> None:
    # fix_alignment="none": every fix is fused at once, in one frame (the default waits for the fixes
    # to pin the frame; tests/test_fix_fusion_in_loop.py covers it); ungated, as the fix is 4.5 sigma out.
    ekf = EkfSlam(
        EkfConfig(motion="constant_position", position_noise=0.2, fix_alignment="none", fix_gate_probability=1.0)
    )
    ekf.step(_observe(0, (10.0, 0.0, 0.0)))
    # Predicting to the fix's stamp gives the position variance 0.2^2; the fix has variance 0.1^2.
    ekf.add_fix(PositionFix(DT_NS, np.array([1.0, 0.0, 0.0]), np.eye(3) * 0.1**2))
    gain = 0.2**2 / (0.2**2 + 0.1**2)
    assert ekf.pose().position[0] == pytest.approx(gain * 1.0, rel=1e-9)
    assert ekf.covariance[0, 0] == pytest.approx(0.2**2 * (1 - gain), rel=1e-9)
    assert ekf.summary()["fixes"] == 1


def test_fix_before_first_observation_places_the_start() -> None:
    ekf = EkfSlam(EkfConfig())
    ekf.add_fix(PositionFix(0, np.array([5.0, -2.0, 1.0]), np.eye(3)))
    pose = ekf.step(_observe(0, (10.0, 0.0, 0.0)))
    np.testing.assert_allclose(pose.position, [5.0, -2.0, 1.0])


# ------------------------------------------------------------------------------- simulated runs


@pytest.mark.parametrize(
    ("association", "iterations", "bound"),
    [
        ("nn", 300, 0.8),  # measured: 0.51 m position and 0.56 m landmark RMSE, final error 1.08 m
        ("jcbb", 200, 0.45),  # measured: 0.29 m and 0.33 m, final error 0.36 m (the same as nn)
    ],
)
def test_figure_eight_run_stays_accurate(association: str, iterations: int, bound: float) -> None:
    result = _run(EkfConfig(association=association), iterations)
    assert result["position_rmse"] < bound
    assert result["landmark_rmse"] < bound
    assert result["final_error"] < 2 * bound
    assert result["landmarks"] == result["distinct"]  # no duplicate landmark


def test_figure_eight_run_with_odometry() -> None:
    result = _run(EkfConfig(), 150, odometry_noise=0.5)
    # Measured: 0.27 m position and 0.30 m landmark RMSE.
    assert result["position_rmse"] < 0.45
    assert result["landmark_rmse"] < 0.45
    assert result["landmarks"] == result["distinct"]


@pytest.mark.parametrize("association", ["known", "nn"])
def test_run_with_clutter(association: str) -> None:
    result = _run(EkfConfig(association=association), 100, clutter=2.0)
    # Measured: 0.18 m position and 0.19-0.20 m landmark RMSE. Known association ignores clutter
    # (id -1); nearest neighbour maps each clutter point as a landmark of its own.
    assert result["position_rmse"] < 0.3
    assert result["landmark_rmse"] < 0.3
    if association == "known":
        assert result["landmarks"] == result["distinct"] == 66


def test_fix_before_first_observation_places_the_start_without_alignment() -> None:
    ekf = EkfSlam(EkfConfig(fix_alignment="none"))
    ekf.add_fix(PositionFix(0, np.array([5.0, -2.0, 1.0]), np.eye(3)))
    pose = ekf.step(_observe(0, (10.0, 0.0, 0.0)))
    np.testing.assert_allclose(pose.position, [5.0, -2.0, 1.0])
    np.testing.assert_allclose(ekf.covariance[:3, :3], np.eye(3))


def test_rigid_consensus_finds_the_pairs_one_motion_does_not_explain() -> None:
    from scipy.spatial.transform import Rotation

    from relpoint.geometry import rigid_consensus

    rng = np.random.default_rng(11)
    source = rng.uniform(-2, 2, (60, 3))
    R = Rotation.from_rotvec([0.4, -0.3, 1.2]).as_matrix()
    target = source @ R.T + [3.0, -1.0, 0.5] + rng.normal(0, 0.005, source.shape)
    target[[2, 17, 40, 41]] += [0.0, 0.06, 0.0]  # four points slid 6 cm
    keep = rigid_consensus(source, target, 0.03)
    assert np.flatnonzero(~keep).tolist() == [2, 17, 40, 41]
    # Per-pair tolerances: a wide one keeps its pair; too few pairs to outvote keeps them all.
    wide = np.full(60, 0.03)
    wide[17] = 0.1
    assert np.flatnonzero(~rigid_consensus(source, target, wide)).tolist() == [2, 40, 41]
    assert rigid_consensus(source[:5], target[:5] + np.array([0.0, 1.0, 0.0]), 0.03).all()
    # The same draws give the same answer.
    assert np.array_equal(rigid_consensus(source, target, 0.03, seed=4), rigid_consensus(source, target, 0.03, seed=4))


def test_rigid_consensus_keeps_a_slid_keypoint_out_of_the_update() -> None:
    # Known association (every pair passes, however far): a keypoint that jumped 40 sigma would drag the
    # pose; the consensus leaves it out and the pose stays where the other 29 put it.
    rng = np.random.default_rng(5)
    world = rng.uniform([1.0, -1.0, -1.0], [3.0, 1.0, 1.0], size=(30, 3))
    ids = np.arange(30)
    poses = {}
    for consensus in (True, False):
        ekf = EkfSlam(EkfConfig(association="known", observation_sigma=0.01, rigid_consensus=consensus))
        ekf.step(PointObservation(0, world, ids))
        moved = world + rng.normal(0.0, 0.01, world.shape)
        moved[7] += [0.0, 0.4, 0.0]
        ekf.step(PointObservation(DT_NS, moved, ids))
        poses[consensus] = ekf.pose().position
        if consensus:
            assert ekf.summary()["consensus_rejected"] == 1
    assert np.linalg.norm(poses[True]) < 0.01 < np.linalg.norm(poses[False])


def _turn_run(config: EkfConfig) -> tuple[EkfSlam, float]:
    """A straight leg at 4 m/s, then a turn at 1 rad/s from one observation to the next; returns the
    filter and its final position error (m)."""
    ekf = EkfSlam(config)
    return ekf, sharp_turn(ekf, speed=4.0, turn_rate=1.0, steps=60, far_x=40.0, landmarks=300)


def test_a_turn_that_starts_at_once_is_followed_by_widening_the_prediction(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level("WARNING", logger="relpoint.estimators.ekf"):
        ekf, error = _turn_run(EkfConfig(observation_sigma=0.1))
    summary = ekf.summary()
    assert summary["association_widened"] >= 1
    assert summary["association_collapsed"] == 0
    assert error < 0.1
    assert not caplog.records
    # Without the retry the points of the turn's first iterations start duplicates, and a warning says so.
    with caplog.at_level("WARNING", logger="relpoint.estimators.ekf"):
        stiff, stiff_error = _turn_run(EkfConfig(observation_sigma=0.1, collapse_noise_scale=1.0))
    assert stiff.summary()["association_collapsed"] >= 1
    assert stiff.summary()["landmarks"] > summary["landmarks"] + 20
    assert stiff_error > 2 * error
    assert len([r for r in caplog.records if "association collapsed" in r.getMessage()]) == 1


def test_a_large_map_is_warned_of_once_and_its_block_grows_by_half(caplog: pytest.LogCaptureFixture) -> None:
    # A 20,000-iteration log grew the EKF to 3,100 landmarks and 1.8 GB without a word (the doubled
    # block stood half empty); it ran on for over 20 minutes.
    import logging

    from relpoint.estimators.ekf import LARGE_MAP_LANDMARKS

    ekf = EkfSlam(EkfConfig(observation_sigma=0.1))
    rng = np.random.default_rng(0)
    with caplog.at_level(logging.WARNING):
        for _ in range(LARGE_MAP_LANDMARKS // 100 + 5):
            ekf._add_landmarks(rng.normal(scale=50.0, size=(100, 3)))
            assert ekf._P_block.shape[0] <= max(INITIAL_CAPACITY, 1.5 * ekf._size)  # grown by half, not doubled
    warnings = [r.getMessage() for r in caplog.records if "map reached" in r.getMessage()]
    assert len(warnings) == 1 and f"reached {LARGE_MAP_LANDMARKS} landmarks" in warnings[0]
    np.testing.assert_array_equal(ekf._P, ekf._P.T)
