"""Offline smoothing of a filter's trajectory on its final map: relocation fits, the random-walk
smoother, and the poses it returns."""

from __future__ import annotations

import numpy as np

from relpoint.estimators._trajectory_smoothing import (
    MAX_PAIRS_PER_ITERATION,
    MIN_PAIRS,
    PairHistory,
    Relocation,
    relocate,
    smooth_corrections,
    smoothed_poses,
)
from relpoint.geometry import so3_exp


def _scene(iterations: int, seed: int = 0, noise: float = 0.0, points: int = 12):
    """True poses T_world_sensor (K, 4, 4), a map of landmarks, and each iteration's pairs."""
    rng = np.random.default_rng(seed)
    landmarks = rng.uniform(-10, 10, size=(200, 3))
    ids = np.arange(200) * 7 + 3  # ids need not be positions in the map
    poses = np.tile(np.eye(4), (iterations, 1, 1))
    poses[:, :3, :3] = so3_exp(rng.normal(scale=0.5, size=(iterations, 3)))
    poses[:, :3, 3] = rng.uniform(-3, 3, size=(iterations, 3))
    history = PairHistory()
    for k in range(iterations):
        chosen = rng.choice(200, size=points, replace=False)
        R, p = poses[k, :3, :3], poses[k, :3, 3]
        sensor = (
            (landmarks[chosen] - p) @ R + rng.normal(scale=noise, size=(points, 3))
            if noise
            else (landmarks[chosen] - p) @ R
        )
        history.add(k, sensor, ids[chosen])
    return poses, ids, landmarks, history


def test_relocation_recovers_every_pose_from_noise_free_pairs() -> None:
    poses, ids, landmarks, history = _scene(20)
    relocation = relocate(*history.arrays(), 20, ids, landmarks)
    assert relocation.fitted.all()
    np.testing.assert_allclose(relocation.rotations, poses[:, :3, :3], atol=1e-6)  # points are stored as float32
    np.testing.assert_allclose(relocation.positions, poses[:, :3, 3], atol=1e-6)  # points are stored as float32
    assert relocation.noise < 1e-6


def test_relocation_leaves_out_a_wrong_pair_and_measures_the_noise() -> None:
    poses, ids, landmarks, history = _scene(50, noise=0.05)
    iteration, points, landmark_ids = history.arrays()
    first = np.flatnonzero(iteration == 0)
    landmark_ids = landmark_ids.copy()
    landmark_ids[first[0]] = landmark_ids[first[1]]  # one point paired with another's landmark
    relocation = relocate(iteration, points, landmark_ids, 50, ids, landmarks)
    assert relocation.pairs[0] == len(first) - 1
    assert np.linalg.norm(relocation.positions[0] - poses[0, :3, 3]) < 0.15
    assert 0.035 < relocation.noise < 0.07  # 0.05 m per axis, measured from the residuals
    # The variances follow the geometry: positions about noise^2 / n at least.
    assert np.all(relocation.variances[:, 3:] >= relocation.noise**2 / 12 * 0.99)


def test_noise_floor_and_iterations_too_sparse_to_fit() -> None:
    _, ids, landmarks, history = _scene(5, points=MIN_PAIRS)
    iteration, points, landmark_ids = history.arrays()
    keep = ~((iteration == 2) & (np.arange(len(iteration)) % MIN_PAIRS == 0))  # iteration 2: one pair short
    relocation = relocate(iteration[keep], points[keep], landmark_ids[keep], 5, ids, landmarks, min_noise=0.2)
    assert relocation.fitted.tolist() == [True, True, False, True, True]
    assert np.isinf(relocation.variances[2]).all()
    assert relocation.noise == 0.2
    # Pairs whose landmark left the map (removed, or flagged moving) do not count.
    relocation = relocate(iteration, points, landmark_ids, 5, ids[:0], landmarks[:0])
    assert not relocation.fitted.any()


def test_history_keeps_a_bounded_evenly_spread_sample_per_iteration() -> None:
    history = PairHistory()
    history.add(0, np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    history.add(1, np.arange(600, dtype=float).reshape(200, 3), np.arange(200))
    iteration, points, ids = history.arrays()
    assert len(history) == MAX_PAIRS_PER_ITERATION == len(ids)
    assert ids[0] == 0 and ids[-1] == 199 and np.all(np.diff(ids) > 0)
    assert np.all(iteration == 1) and points.dtype == np.float64


def test_smoother_averages_a_steady_offset_and_follows_a_drifting_one() -> None:
    rng = np.random.default_rng(1)
    K = 400
    variance = np.full((K, 3), 0.1**2)
    steady = np.array([0.3, -0.2, 0.1])
    measured = steady + rng.normal(scale=0.1, size=(K, 3))
    smoothing = smooth_corrections(measured, variance)
    assert np.abs(smoothing.corrections - steady).max() < 0.05  # each measurement is 0.1 m off
    assert smoothing.position_step < 1e-3
    drift = np.cumsum(rng.normal(scale=0.03, size=(K, 3)), axis=0)
    smoothing = smooth_corrections(drift + rng.normal(scale=0.1, size=(K, 3)), variance)
    raw_error = 0.1 * np.sqrt(3)
    assert np.sqrt(np.mean(np.sum((smoothing.corrections - drift) ** 2, axis=1))) < 0.6 * raw_error
    assert 0.01 < smoothing.position_step < 0.1  # the walk's own 0.03 m per step, measured


def test_iterations_without_a_fit_take_their_neighbours_correction() -> None:
    K = 30
    measured = np.tile([1.0, 2.0, 3.0], (K, 1))
    variance = np.full((K, 3), 0.01)
    variance[:5] = np.inf
    variance[12:18] = np.inf
    measured[np.isinf(variance)] = 0.0
    smoothing = smooth_corrections(measured, variance)
    np.testing.assert_allclose(smoothing.corrections, np.tile([1.0, 2.0, 3.0], (K, 1)), atol=1e-6)
    assert np.all(smooth_corrections(measured, np.full((K, 3), np.inf)).corrections == 0.0)


def test_smoothed_poses_move_positions_onto_the_map_and_keep_rotations() -> None:
    poses, ids, landmarks, history = _scene(60, noise=0.02)
    filtered = poses.copy()
    filtered[:, :3, 3] += np.array([0.5, 0.0, -0.3])  # a filter's drift the final map no longer has
    relocation = relocate(*history.arrays(), 60, ids, landmarks)
    smoothed, smoothing = smoothed_poses(filtered, relocation)
    assert np.abs(smoothed[:, :3, 3] - poses[:, :3, 3]).max() < 0.02
    np.testing.assert_array_equal(smoothed[:, :3, :3], filtered[:, :3, :3])
    np.testing.assert_array_equal(smoothed[:, 3], filtered[:, 3])
    assert smoothing.corrections.shape == (60, 3)
    empty = Relocation(np.tile(np.eye(3), (60, 1, 1)), np.zeros((60, 3)), np.zeros(60, bool), np.full((60, 6), np.inf),
                       np.zeros(60, np.int64), float("nan"))  # fmt: skip
    np.testing.assert_array_equal(smoothed_poses(filtered, empty)[0], filtered)


def test_a_wrong_fit_is_left_out_of_the_smoothed_path() -> None:
    poses, ids, landmarks, history = _scene(60, noise=0.02)
    relocation = relocate(*history.arrays(), 60, ids, landmarks)
    positions = relocation.positions.copy()
    positions[30] += np.array([0.0, 2.5, 0.0])  # five points in a line, paired with the wrong landmarks
    wrong = Relocation(relocation.rotations, positions, relocation.fitted, relocation.variances, relocation.pairs,
                       relocation.noise)  # fmt: skip
    smoothed, smoothing = smoothed_poses(poses, wrong)
    assert smoothing.rejected == 1
    assert np.abs(smoothed[:, :3, 3] - poses[:, :3, 3]).max() < 0.02


def test_the_ekf_keeps_its_own_trajectory_when_the_run_skipped_iterations() -> None:
    from relpoint.estimators.ekf import EkfConfig, EkfSlam
    from relpoint.simulation import SimulationConfig, simulate
    from relpoint.types import Trajectory

    sim = simulate(SimulationConfig(density=25, noise=0.3, iterations=40, seed=0))
    ekf = EkfSlam(EkfConfig(observation_sigma=0.3))
    poses = [ekf.step(step.observation) for step in sim.steps()]
    shorter = Trajectory.from_poses(poses[:-1])  # one iteration's pose missing: not one per iteration
    assert ekf.finish(shorter) is shorter
    assert ekf.summary()["smoothing"] == {"applied": False, "reason": "the run skipped iterations"}
    whole = Trajectory.from_poses(poses)
    smoothed = ekf.finish(whole)
    assert ekf.summary()["smoothing"]["applied"] and ekf.summary()["smoothing"]["iterations_placed"] >= 35
    np.testing.assert_allclose(smoothed.matrices()[:, :3, :3], whole.matrices()[:, :3, :3], atol=1e-12)
    assert not np.array_equal(smoothed.positions, whole.positions)
    off = EkfSlam(EkfConfig(observation_sigma=0.3, smooth_trajectory=False))
    for step in sim.steps():
        off.step(step.observation)
    assert off.finish(whole) is whole and "smoothing" not in off.summary()


def test_the_fixes_jumps_are_taken_out_when_the_fits_say_they_were_noise() -> None:
    # A filter that fuses a noisy fix every iteration jumps by part of each fix's noise; relocated on
    # the final map, its positions are 7 cm fits. Taken as a plain walk the correction must follow
    # every jump; with the jumps taken out it is a constant, which the fits pin far better.
    rng = np.random.default_rng(3)
    K = 300
    truth = np.cumsum(rng.normal(scale=1.0, size=(K, 3)), axis=0)
    jumps = np.cumsum(rng.normal(scale=0.05, size=(K, 3)), axis=0)  # each fix's pull, summed
    poses = np.tile(np.eye(4), (K, 1, 1))
    poses[:, :3, 3] = truth + jumps
    variances = np.full((K, 6), 0.07**2)
    fits = Relocation(np.tile(np.eye(3), (K, 1, 1)), truth + rng.normal(scale=0.07, size=(K, 3)), np.ones(K, bool),
                      variances, np.full(K, 20), 0.3)  # fmt: skip
    walk, plain = smoothed_poses(poses, fits)
    jumped, removed = smoothed_poses(poses, fits, fix_jumps=jumps)
    assert not plain.fix_jumps_removed and removed.fix_jumps_removed
    assert removed.log_likelihood > plain.log_likelihood
    error_walk = np.sqrt(np.mean(np.sum((walk[:, :3, 3] - truth) ** 2, axis=1)))
    error_jumps = np.sqrt(np.mean(np.sum((jumped[:, :3, 3] - truth) ** 2, axis=1)))
    assert error_jumps < 0.5 * error_walk
    # Jumps that were real corrections (each pulled back drift, and the filter is right) stay in.
    poses[:, :3, 3] = truth + rng.normal(scale=0.005, size=(K, 3))
    _, kept = smoothed_poses(poses, fits, fix_jumps=jumps)
    assert not kept.fix_jumps_removed
