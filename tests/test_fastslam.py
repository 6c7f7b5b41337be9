"""FastSLAM: low-variance resampling, normalised weights, determinism by seed, association and new
landmarks, and short simulated runs of both variants with error bounds a regression would break."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from relpoint.errors import UsageError
from relpoint.estimators.fastslam import SPEC, FastSlam, FastSlamConfig, low_variance_resample
from relpoint.geometry import invert_pose, transform_points
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import PointObservation
from tests.conftest import run_accuracy, sharp_turn

DT_NS = 100_000_000


def _run(config: FastSlamConfig, seed: int, iterations: int, **sim_options: object) -> dict[str, float]:
    """Run FastSLAM on the figure eight; errors in the frame of the first true pose (where it starts)."""
    sim = simulate(SimulationConfig(density=25, noise=0.3, iterations=iterations, seed=0, **sim_options))  # type: ignore[arg-type]
    slam = FastSlam(config, np.random.default_rng(seed))
    T_first_world = invert_pose(sim.ground_truth.matrices()[0])
    errors = []
    for step in sim.steps():
        if step.odometry is not None:
            slam.add_odometry(step.odometry)
        pose = slam.step(step.observation)
        assert slam.weights.sum() == pytest.approx(1.0, abs=1e-12)
        truth = (T_first_world @ step.T_world_sensor)[:3, 3]
        errors.append(np.linalg.norm(np.array(pose.position) - truth))
    return run_accuracy(errors, slam.landmark_map(), transform_points(T_first_world, sim.landmarks.positions))


# ----------------------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    "options",
    [
        {"variant": "3.0"},
        {"particles": 0},
        {"observation_sigma": -0.1},
        {"new_landmark_probability": 1.0},
        {"resample_threshold": 1.5},
        {"search_radius": 0.0},
        {"start_landmark_probability": 0.999},  # below new_landmark_probability
        {"fix_alignment": "none"},
    ],
)
def test_config_rejects_bad_values(options: dict[str, object]) -> None:
    with pytest.raises(UsageError):
        FastSlamConfig(**options)  # type: ignore[arg-type]


def test_config_round_trips_and_spec_builds() -> None:
    config = FastSlamConfig.from_mapping(
        {"variant": "1.0", "particles": 7, "observation_sigma": 0.3, "linear_acceleration_noise": 2.0,
         "angular_acceleration_noise": 0.5, "odometry_check": False}
    )  # fmt: skip
    assert FastSlamConfig.from_mapping(config.to_dict()) == config
    with pytest.raises(UsageError):
        FastSlamConfig.from_mapping({"particle_count": 7})
    slam = SPEC.factory(config, np.random.default_rng(0))
    assert isinstance(slam, FastSlam) and len(slam.weights) == 7
    assert SPEC.name == "fastslam" and SPEC.needs == frozenset({"points"})


# ------------------------------------------------------------------------------------ resampling


def test_low_variance_resampling_is_proportional_and_seeded() -> None:
    weights = np.array([0.5, 0.25, 0.25, 0.0])
    for seed in range(20):
        index = low_variance_resample(weights, np.random.default_rng(seed))
        # Systematic resampling copies particle i either floor(N w_i) or ceil(N w_i) times.
        assert np.bincount(index, minlength=4).tolist() == [2, 1, 1, 0]
    weights = np.random.default_rng(1).dirichlet(np.ones(100))
    first = low_variance_resample(weights, np.random.default_rng(5))
    again = low_variance_resample(weights, np.random.default_rng(5))
    other = low_variance_resample(weights, np.random.default_rng(6))
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    counts = np.bincount(first, minlength=100)
    assert np.all(np.abs(counts - 100 * weights) < 1.0)


def test_resampling_through_spare_arrays_gives_each_particle_its_source_s_state() -> None:
    """Resampling copies the landmark arrays' used slots into spare arrays it keeps and reuses: every
    particle holds its drawn source's state, and every slot beyond those ever used its empty value,
    resampling after resampling and across a growth of the capacity."""
    from relpoint.estimators.fastslam import _PARTICLE_ARRAYS, _SLOT_ARRAYS

    n = 6
    slam = FastSlam(FastSlamConfig(particles=n), np.random.default_rng(0))
    rng = np.random.default_rng(1)
    for round_, used in enumerate((10, 10, 40, 70, 70)):
        if round_ == 2:
            slam._ensure_capacity(slam._capacity + 1)
        slam.counts[:] = used
        slam._slots_used = used
        for attr in _PARTICLE_ARRAYS:  # distinct values in every particle's rows
            array = getattr(slam, attr)
            values = rng.integers(0, 1000, array.shape).astype(array.dtype)
            if attr in _SLOT_ARRAYS:
                assert np.all(array[:, used:] == _SLOT_ARRAYS[attr])  # as the filter keeps them
                array[:, :used] = values[:, :used]
            else:
                array[...] = values
        before = {attr: getattr(slam, attr).copy() for attr in _PARTICLE_ARRAYS}
        slam.log_weights = np.log(np.array([0.5, 0.5, 0, 0, 0, 0]) + 1e-12)
        slam.log_weights -= np.log(np.exp(slam.log_weights).sum())
        index = low_variance_resample(slam.weights, copy.deepcopy(slam._rng))
        slam._resample_if_degenerate()
        assert set(index.tolist()) == {0, 1}
        for attr in _PARTICLE_ARRAYS:
            np.testing.assert_array_equal(getattr(slam, attr), before[attr][index], err_msg=attr)


def test_weights_stay_normalised_and_resampling_resets_them() -> None:
    sim = simulate(SimulationConfig(density=25, noise=0.3, iterations=40, seed=2))
    slam = FastSlam(FastSlamConfig(particles=20), np.random.default_rng(0))
    resamples = 0
    for step in sim.steps():
        slam.step(step.observation)
        w = slam.weights
        assert w.sum() == pytest.approx(1.0, abs=1e-12)
        assert np.all(w >= 0)
        if slam.summary().get("resamples", 0) > resamples:
            resamples = slam.summary()["resamples"]
            np.testing.assert_allclose(w, 1.0 / 20)
    assert resamples > 0


def test_runs_are_deterministic_by_seed() -> None:
    sim = simulate(SimulationConfig(density=25, noise=0.3, iterations=30, seed=4))

    def run(seed: int) -> tuple[np.ndarray, np.ndarray]:
        slam = FastSlam(FastSlamConfig(particles=15), np.random.default_rng(seed))
        positions = np.array([slam.step(step.observation).position for step in sim.steps()])
        return positions, slam.landmark_map().positions

    first, again, other = run(11), run(11), run(12)
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])
    assert not np.array_equal(first[0], other[0])


# ----------------------------------------------------------------------------------- association


@pytest.mark.parametrize("variant", ["1.0", "2.0"])
def test_points_pair_with_their_landmark_or_start_new_ones(variant: str) -> None:
    config = FastSlamConfig(
        variant=variant, particles=5, pose_noise=0.0, min_observations=1
    )  # landmarks seen once shown
    slam = FastSlam(config, np.random.default_rng(0))
    slam.step(PointObservation(0, [[10.0, 0.0, 0.0], [0.0, 10.0, 0.0]], [0, 1]))
    assert slam.counts.tolist() == [2] * 5
    # Same stamp (no motion): one point near landmark 0, one far from everything.
    slam.step(PointObservation(0, [[10.1, 0.0, 0.0], [0.0, 20.0, 0.0]], [0, 2]))
    assert slam.counts.tolist() == [3] * 5
    landmarks = slam.landmark_map()
    assert landmarks.observations.tolist() == [2, 1, 1]
    assert landmarks.gt_id.tolist() == [0, 1, 2]
    # The landmark EKF averages the two sightings with equal covariances.
    np.testing.assert_allclose(landmarks.positions[0], [10.05, 0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize("variant", ["1.0", "2.0"])
def test_point_between_the_gates_is_discarded(variant: str) -> None:
    slam = FastSlam(FastSlamConfig(variant=variant, particles=4, pose_noise=0.0), np.random.default_rng(0))
    slam.step(PointObservation(0, [[10.0, 0.0, 0.0]], [0]))
    # A once-seen landmark's innovation covariance is 2 Q = 0.18 m^2 per axis, the same as the
    # new-landmark density's: the 0.9999 match gate (d2 < 21.1) ends at 1.95 m, the 1 - 1e-7 start
    # gate (d2 < 35.4) at 2.52 m.
    slam.step(PointObservation(0, [[12.2, 0.0, 0.0]], [0]))
    assert slam.counts.tolist() == [1] * 4 and slam.summary()["discarded"] == 4
    slam.step(PointObservation(0, [[12.8, 0.0, 0.0]], [1]))
    assert slam.counts.tolist() == [2] * 4


def test_moving_landmark_count_leaves_out_the_dropped_landmarks() -> None:
    config = FastSlamConfig(particles=3, pose_noise=0.0, min_observations=1)  # every landmark shown
    slam = FastSlam(config, np.random.default_rng(0))
    slam.step(PointObservation(0, [[10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]], [0, 1, 2]))
    slam._moving[:, 1:3] = True  # landmarks 1 and 2 taken for movers
    # Landmark 1 dropped (as a vanished one is): landmark 2 moves down into its slot, and its old slot,
    # past the count now, keeps a stale copy of it.
    slam._drop(np.arange(3), np.ones(3, dtype=np.int64))
    assert slam.counts.tolist() == [2] * 3
    assert slam.summary()["moving_landmarks"] == int(slam.landmark_map().dynamic.sum()) == 1


# ------------------------------------------------------------------------------- simulated runs


def test_fastslam2_figure_eight_run_stays_accurate() -> None:
    # The median over five rng seeds: the particle filter turns a rounding difference of 1e-14 into
    # another run (the compiled association agrees with numpy to 1e-13 step by step, with the same
    # pairings), and one seed's figures scatter by 4x: over seeds 0-11 the position RMSE ran from 0.44
    # to 2.06 m and the final error from 0.77 to 5.4 m, with the association in numpy or compiled.
    # Medians over seeds 0-4 measured: 1.10 / 1.06 / 2.02 m (numpy) and 1.16 / 1.29 / 2.54 m (compiled)
    # position RMSE, landmark RMSE, final error; a diverged filter is off by tens of metres.
    results = [_run(FastSlamConfig(particles=30), seed=seed, iterations=300) for seed in range(5)]
    median = {key: float(np.median([r[key] for r in results])) for key in results[0]}
    assert median["position_rmse"] < 1.5
    assert median["landmark_rmse"] < 1.6
    assert median["final_error"] < 3.5
    assert all(r["landmarks"] <= r["distinct"] + 3 for r in results)


@pytest.mark.parametrize("variant", ["1.0", "2.0"])
def test_first_step_pairs_under_a_wide_speed_prior(variant: str) -> None:
    # A hand-held camera at 10 Hz over points 1-4 m away with 1 cm noise: the speed prior that suits a
    # vehicle (10 m/s, a metre in the first step) spreads every candidate's density below the
    # new-landmark likelihood, so the first step paired nothing and drew the pose blind from that
    # prior (0.17-2 m off on the 7-Scenes kitchen at 15 and 10 Hz; it never came back). Both variants
    # refine the first step by its points; after it, 1.0 samples the motion model (2 cm steps at the
    # default acceleration noise, against 1 cm points), so only 2.0 is held to the whole run.
    rng = np.random.default_rng(4)
    landmarks = rng.uniform([1.0, -1.5, -1.0], [4.0, 1.5, 1.0], (250, 3))
    slam = FastSlam(FastSlamConfig(variant=variant, particles=20, observation_sigma=0.01), rng)
    errors, paired = [], []
    for k in range(20):
        truth = np.array([0.0, 0.02 * k, 0.005 * k])  # 0.2 m/s sideways, a slow climb
        points = landmarks - truth + rng.normal(0.0, 0.01, landmarks.shape)
        pose = slam.step(PointObservation(k * DT_NS, points, None))
        errors.append(np.linalg.norm(np.asarray(pose.position) - truth))
        paired.append(slam.summary()["paired"])
    assert paired[1] > 0.95 * 20 * len(landmarks)  # every particle paired nearly every point at once
    assert errors[1] < 0.01
    if variant == "2.0":  # measured: 6.8 mm at most, 99.99 % paired (before: none at first, 7.6 m off at the end)
        assert paired[-1] > 0.95 * 19 * 20 * len(landmarks)
        assert max(errors) < 0.01


def _turn_run(config: FastSlamConfig) -> tuple[FastSlam, float]:
    """A straight leg at 6 m/s, then a turn at 1.5 rad/s from one observation to the next (a lawnmower's
    end); returns the filter and its final position error (m)."""
    slam = FastSlam(config, np.random.default_rng(1))
    return slam, sharp_turn(slam, speed=6.0, turn_rate=1.5, steps=50, far_x=60.0, landmarks=400)


def test_a_turn_that_starts_at_once_is_proposed_again_under_a_wider_prior(caplog: pytest.LogCaptureFixture) -> None:
    # Measured: 0.078 m and 143 landmarks, the turn's first iterations proposed again twice; without the
    # retry 0.334 m and 188 landmarks (duplicates), one warning. Another tool's lawnmower log at 6 m/s:
    # ATE 18.9 -> 0.032 m, 1017 -> 205 landmarks.
    with caplog.at_level("WARNING", logger="relpoint.estimators.fastslam"):
        slam, error = _turn_run(FastSlamConfig(particles=20, observation_sigma=0.1))
    summary = slam.summary()
    assert summary["association_widened"] >= 1 and summary["association_collapsed"] == 0
    assert error < 0.15 and not caplog.records
    with caplog.at_level("WARNING", logger="relpoint.estimators.fastslam"):
        stiff, stiff_error = _turn_run(FastSlamConfig(particles=20, observation_sigma=0.1, collapse_noise_scale=1.0))
    assert stiff.summary()["association_collapsed"] >= 1
    assert stiff.summary()["landmarks"] > summary["landmarks"] + 20 and stiff_error > 2 * error
    assert len([r for r in caplog.records if "association collapsed" in r.getMessage()]) == 1


def test_fastslam1_with_odometry_stays_accurate() -> None:
    result = _run(FastSlamConfig(variant="1.0", particles=30), seed=0, iterations=200, odometry_noise=0.5)
    # Measured: 0.61 m position and 1.01 m landmark RMSE.
    assert result["position_rmse"] < 1.0
    assert result["landmark_rmse"] < 1.5
    assert result["final_error"] < 2.5


# ----------------------------------------------------------------- compiled association against numpy


def _associate_numpy(points, radius, positions, rotations, twists, means, covs, counts, Q, Sigma, proposal,
                     log_new, log_start, wide_prior):  # fmt: skip
    """The association in numpy, one point at a time, as FastSLAM ran it before its loops were compiled."""
    from relpoint.geometry import skew, so3_exp

    n, k = len(positions), len(points)
    cap = int(counts.max())
    predicted = np.einsum("pji,pmj->pmi", rotations, means[:, :cap] - positions[:, None, :])
    valid = np.arange(cap)[None, :] < counts[:, None]
    candidates_of = [
        np.flatnonzero(((np.sum((predicted - z) ** 2, axis=2) < radius**2) & valid).any(axis=0)) for z in points
    ]
    assoc = np.full((n, k), -1, dtype=np.int64)
    log_likelihood = np.zeros(n)
    used = np.zeros((n, cap), dtype=bool)
    rows = np.arange(n)
    for i, candidates in enumerate(candidates_of):
        c = len(candidates)
        if c == 0:
            log_likelihood += log_new
            continue
        Rt = np.swapaxes(rotations, 1, 2)
        z_hat = np.einsum("pij,pcj->pci", Rt, means[:, candidates] - positions[:, None, :])
        S_m = Rt[:, None] @ covs[:, candidates] @ rotations[:, None] + Q
        H = np.zeros((n, c, 3, 12))
        H[:, :, :, :3] = -Rt[:, None]
        H[:, :, :, 3:6] = skew(z_hat)
        L = S_m + H @ Sigma[:, None] @ np.swapaxes(H, 2, 3) if proposal else S_m
        nu = points[i] - z_hat
        L_inv = np.linalg.inv(L)
        _, logdet = np.linalg.slogdet(L)
        quad = np.einsum("pci,pcij,pcj->pc", nu, L_inv, nu)
        logl = -0.5 * (quad + logdet + 3 * np.log(2 * np.pi))
        score = -0.5 * (quad + np.linalg.slogdet(S_m)[1] + 3 * np.log(2 * np.pi)) if proposal and wide_prior else logl
        logl = np.where((candidates[None, :] >= counts[:, None]) | used[:, candidates], -np.inf, logl)
        best = np.argmax(logl, axis=1)
        best_logl = logl[rows, best]
        best_score = np.where(np.isfinite(best_logl), score[rows, best], -np.inf)
        matched = best_score >= log_new
        slot = candidates[best]
        assoc[matched, i] = slot[matched]
        assoc[~matched & (best_score >= log_start), i] = -2
        used[rows[matched], slot[matched]] = True
        log_likelihood += np.where(matched, best_logl, log_new)
        if proposal and matched.any():
            H_b = H[rows, best]
            K = Sigma @ np.swapaxes(H_b, 1, 2) @ L_inv[rows, best]
            delta = np.where(matched[:, None], np.einsum("pij,pj->pi", K, nu[rows, best]), 0.0)
            positions = positions + delta[:, :3]
            rotations = rotations @ so3_exp(delta[:, 3:6])
            twists = twists + delta[:, 6:]
            I_KH = np.eye(12) - K @ H_b
            joseph = I_KH @ Sigma @ np.swapaxes(I_KH, 1, 2) + K @ S_m[rows, best] @ np.swapaxes(K, 1, 2)
            Sigma = np.where(matched[:, None, None], joseph, Sigma)
    return assoc, log_likelihood, Sigma, positions, rotations, twists


@pytest.mark.parametrize(("prior_scale", "wide_prior"), [(1.0, False), (100.0, False), (100.0, True)])
@pytest.mark.parametrize("proposal", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_association_equals_the_numpy_loop(
    proposal: bool, seed: int, prior_scale: float, wide_prior: bool
) -> None:
    from relpoint.estimators import _fastslam_kernels
    from relpoint.geometry import so3_exp

    rng = np.random.default_rng(seed)
    n, m, k, sigma = 7, 40, 25, 0.3
    truth = rng.uniform(-10, 10, (m, 3))
    positions = rng.normal(0, 0.3, (n, 3))
    rotations = so3_exp(rng.normal(0, 0.05, (n, 3)))
    twists = rng.normal(0, 0.1, (n, 6))
    counts = rng.integers(m // 2, m + 1, n).astype(np.int64)
    means = truth[None] + rng.normal(0, sigma, (n, m, 3))
    A = rng.normal(0, sigma, (n, m, 3, 3))
    covs = A @ np.swapaxes(A, 2, 3) + 0.01 * np.eye(3)
    B = rng.normal(0, 0.05, (n, 12, 12))
    Sigma = (B @ np.swapaxes(B, 1, 2) + 1e-4 * np.eye(12)) * prior_scale  # 100: a wide prior
    seen = truth[rng.choice(m, k - 5, replace=False)]  # some points of no landmark (new ones)
    points = np.concatenate([seen + rng.normal(0, sigma, seen.shape), rng.uniform(-10, 10, (5, 3))])
    Q = np.eye(3) * sigma**2
    log_new, log_start = -8.0, -14.0
    expected = _associate_numpy(points, 2.0, positions, rotations, twists, means, covs, counts, Q, Sigma, proposal,
                                log_new, log_start, wide_prior)  # fmt: skip
    offsets, slots = _fastslam_kernels.near_slots(points, positions, rotations, means, counts, 2.0)
    got_positions, got_rotations, got_twists, got_Sigma = (
        positions.copy(),
        rotations.copy(),
        twists.copy(),
        Sigma.copy(),
    )
    assoc, log_likelihood, paired, discarded = _fastslam_kernels.associate(
        points, offsets, slots, got_positions, got_rotations, got_twists, means, covs, counts, Q, got_Sigma, proposal,
        log_new, log_start, wide_prior,
    )  # fmt: skip
    np.testing.assert_array_equal(assoc, expected[0])
    assert paired == int((assoc >= 0).sum()) > 0 and discarded == int((assoc == -2).sum())
    np.testing.assert_allclose(log_likelihood, expected[1], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(got_Sigma, expected[2], rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(got_positions, expected[3], atol=1e-12)
    np.testing.assert_allclose(got_rotations, expected[4], atol=1e-12)
    np.testing.assert_allclose(got_twists, expected[5], atol=1e-12)


def test_compiled_landmark_update_equals_the_numpy_update() -> None:
    from relpoint.estimators import _fastslam_kernels
    from relpoint.geometry import so3_exp

    rng = np.random.default_rng(5)
    n, m, k = 4, 12, 6
    positions = rng.normal(0, 1, (n, 3))
    rotations = so3_exp(rng.normal(0, 0.5, (n, 3)))
    means = rng.normal(0, 5, (n, m, 3))
    A = rng.normal(0, 0.3, (n, m, 3, 3))
    covs = A @ np.swapaxes(A, 2, 3) + 0.01 * np.eye(3)
    Q = np.eye(3) * 0.09
    points = rng.normal(0, 5, (k, 3))
    assoc = np.full((n, k), -1, dtype=np.int64)
    for p in range(n):  # each particle pairs a few points with distinct slots
        chosen = rng.choice(k, 4, replace=False)
        assoc[p, chosen] = rng.choice(m, 4, replace=False)
    # numpy form: every pair at once
    p, i = np.nonzero(assoc >= 0)
    j = assoc[p, i]
    R, cov = rotations[p], covs[p, j]
    Rt = np.swapaxes(R, 1, 2)
    z_hat = np.einsum("pij,pj->pi", Rt, means[p, j] - positions[p])
    K = cov @ R @ np.linalg.inv(Rt @ cov @ R + Q)
    expected_means = means.copy()
    expected_means[p, j] += np.einsum("pij,pj->pi", K, points[i] - z_hat)
    I_KH = np.eye(3) - K @ Rt
    new_cov = I_KH @ cov @ np.swapaxes(I_KH, 1, 2) + K @ Q @ np.swapaxes(K, 1, 2)
    expected_covs = covs.copy()
    expected_covs[p, j] = 0.5 * (new_cov + np.swapaxes(new_cov, 1, 2))
    seen, last = np.zeros((n, m), dtype=np.int64), np.zeros((n, m), dtype=np.int64)
    _fastslam_kernels.update_landmarks(points, assoc, positions, rotations, means, covs, Q, seen, last, 7)
    np.testing.assert_allclose(means, expected_means, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(covs, expected_covs, rtol=1e-10, atol=1e-14)
    assert seen.sum() == len(p) and set(last[p, j].tolist()) == {7} and last.sum() == 7 * len(p)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_candidate_search_over_the_landmarks_near_the_points_equals_the_full_search(seed: int) -> None:
    """fastslam.near_slots hands the compiled search only the slots near the points' box: the same
    candidates as the search over every slot, for particles of unequal map sizes, landmarks far from
    the points, a landmark slot beyond a particle's count and a non-finite point."""
    from relpoint.estimators import _fastslam_kernels
    from relpoint.estimators.fastslam import near_slots
    from relpoint.geometry import so3_exp

    rng = np.random.default_rng(seed)
    n, m, radius = 6, 400, 2.0
    truth = rng.uniform(-60, 60, (m, 3))  # most of the map far from the sensor
    positions = rng.normal(0, 0.2, (n, 3))
    rotations = so3_exp(rng.normal(0, 0.01, (n, 3)))
    counts = rng.integers(m // 2, m + 1, n).astype(np.int64)
    means = truth[None] + rng.normal(0, 0.3, (n, m, 3))
    means[0, counts[0] :] = 0.0  # stale slots beyond a count (at the sensor) are no candidates
    seen = truth[np.linalg.norm(truth, axis=1) < 30.0]  # what the sensor sees
    points = np.concatenate([seen + rng.normal(0, 0.3, seen.shape), rng.uniform(-5, 5, (10, 3))])
    points[3] = np.nan
    points = np.ascontiguousarray(points)
    offsets, slots = near_slots(points, positions, rotations, means, counts, radius)
    expected_offsets, expected_slots = _fastslam_kernels.near_slots(points, positions, rotations, means, counts, radius)
    assert len(expected_slots) > 10  # the case is not empty
    np.testing.assert_array_equal(offsets, expected_offsets)
    np.testing.assert_array_equal(slots, expected_slots)
