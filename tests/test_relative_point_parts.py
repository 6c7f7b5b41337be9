"""Properties of the Relative Point components: least-squares fitting, basis frames, matching, binning."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from relpoint.estimators.relative_point import _kernels
from relpoint.estimators.relative_point.adjustment import (
    adjust_network,
    carry_corrections,
    inconsistent_relocations,
    residual_drift,
    smooth_corrections,
)
from relpoint.estimators.relative_point.charting import PointCharting
from relpoint.estimators.relative_point.dynamics import (
    detect_dynamic,
    deviation_to_references,
    gap_threshold,
    row_nanmedian,
    tail_bound,
    world_block_deviation,
)
from relpoint.estimators.relative_point.grouping import select_members
from relpoint.estimators.relative_point.groups import basis_rotation, choose_basis, relative_coordinates
from relpoint.estimators.relative_point.loops import drift_profile, drift_share, required_support, vote_offset
from relpoint.estimators.relative_point.lsf import fit_transform, is_collinear
from relpoint.estimators.relative_point.points import PointStore
from relpoint.estimators.relative_point.registration import (
    NO_MATCH,
    GlobalIndex,
    MotionModel,
    match_mutual,
    match_nearest,
)
from relpoint.estimators.relative_point.tally import IdTally
from relpoint.geometry import apply_transform, fit_rigid, quaternion_xyzw

SEEDS = st.integers(min_value=0, max_value=2**32 - 1)
PROPERTY = settings(max_examples=60, deadline=None, derandomize=True)


def random_pose(rng: np.random.Generator, spread: float = 20.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-spread, spread, 3)
    return T


# -- RltLSF -------------------------------------------------------------------------------------


@PROPERTY
@given(seed=SEEDS, n=st.integers(min_value=3, max_value=60), noise=st.sampled_from([0.0, 0.01, 0.3]))
def test_fit_recovers_known_rigid_transform(seed: int, n: int, noise: float) -> None:
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    source = rng.uniform(-30.0, 30.0, (n, 3))
    target = apply_transform(T, source) + rng.normal(0.0, noise, (n, 3))
    fit = fit_transform(source, target, trim=0.0)
    assert fit is not None
    R = fit.T[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)
    # Pose error of a least-squares fit shrinks like noise / sqrt(n); points span ~35 m (rms).
    angle = np.linalg.norm(Rotation.from_matrix(R @ T[:3, :3].T).as_rotvec())
    assert angle <= 1e-9 + 10.0 * noise / (35.0 * np.sqrt(n)) * np.sqrt(3.0) * 3.0
    assert np.linalg.norm(fit.T[:3, 3] - T[:3, 3]) <= 1e-7 + 10.0 * noise * 3.0
    # Same answer as the library fit (which it reimplements for speed).
    reference = fit_rigid(source, target)
    assert np.allclose(R, reference.rotation, atol=1e-8)
    assert np.allclose(fit.T[:3, 3], reference.translation, atol=1e-6)


@PROPERTY
@given(seed=SEEDS, n=st.integers(min_value=4, max_value=40))
def test_fit_is_a_proper_rotation_even_for_a_mirrored_target(seed: int, n: int) -> None:
    # A mirror image cannot be reached by a rotation: Arun's SVD would return a reflection
    # (det -1) unless the weakest singular direction is flipped.
    rng = np.random.default_rng(seed)
    source = rng.normal(0.0, 10.0, (n, 3))
    mirror = np.diag([1.0, 1.0, -1.0])
    target = apply_transform(random_pose(rng), source @ mirror)
    fit = fit_transform(source, target, trim=0.0)
    assert fit is not None
    assert np.linalg.det(fit.T[:3, :3]) == pytest.approx(1.0, abs=1e-9)


@PROPERTY
@given(seed=SEEDS, noise=st.sampled_from([0.0, 0.05]))
def test_fit_recovers_transform_of_coplanar_points(seed: int, noise: float) -> None:
    # Planar sources are where the reflection case bites: the plane's mirror image fits as well.
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    source = np.c_[rng.uniform(-20, 20, (25, 2)), np.zeros(25)]
    fit = fit_transform(source, apply_transform(T, source) + rng.normal(0, noise, (25, 3)), trim=0.0)
    assert fit is not None
    assert np.linalg.det(fit.T[:3, :3]) == pytest.approx(1.0, abs=1e-9)
    assert np.allclose(fit.T[:3, :3], T[:3, :3], atol=1e-9 + 0.02 * (noise > 0))


def test_fit_trims_gross_outliers_and_weights_pull() -> None:
    rng = np.random.default_rng(0)
    T = random_pose(rng)
    source = rng.uniform(-30, 30, (40, 3))
    target = apply_transform(T, source) + rng.normal(0, 0.1, (40, 3))
    target[:5] += rng.normal(0, 20.0, (5, 3))  # five mismatched pairs
    fit = fit_transform(source, target, trim=3.0, floor=0.5)
    assert fit is not None
    assert not fit.inliers[:5].any() and fit.inliers[5:].all()
    assert np.linalg.norm(fit.T[:3, 3] - T[:3, 3]) < 0.2


def test_fit_rejects_degenerate_input() -> None:
    line = np.outer(np.linspace(0, 10, 8), [1.0, 2.0, 0.5])
    assert fit_transform(line, line + 1.0) is None
    assert fit_transform(np.zeros((2, 3)), np.zeros((2, 3))) is None
    assert fit_transform(np.ones((5, 3)), np.ones((5, 3))) is None
    assert is_collinear(line, 0.05) and not is_collinear(np.eye(3) * 5.0, 0.05)


def test_quaternion_matches_scipy() -> None:
    rng = np.random.default_rng(1)
    matrices = [*Rotation.random(500, random_state=rng).as_matrix(), np.eye(3), np.diag([1.0, -1.0, -1.0])]
    for R in matrices:
        ours = np.array(quaternion_xyzw(R))
        theirs = Rotation.from_matrix(R).as_quat(canonical=True)
        assert ours[3] >= 0.0
        assert np.allclose(ours, theirs, atol=1e-9) or np.allclose(ours, -theirs, atol=1e-9)


# -- basis frames ---------------------------------------------------------------------------------


@PROPERTY
@given(seed=SEEDS, m=st.integers(min_value=3, max_value=30))
def test_basis_frame_is_invariant_under_rigid_motion(seed: int, m: int) -> None:
    rng = np.random.default_rng(seed)
    points = rng.uniform(-40, 40, (m, 3))
    basis = choose_basis(points, 1.0)
    assert basis is not None
    moved = np.stack(
        [points, apply_transform(random_pose(rng, 100.0), points), apply_transform(random_pose(rng, 100.0), points)],
        axis=1,
    )
    relative, valid = relative_coordinates(moved, basis, 1.0)
    assert valid.all()
    assert np.allclose(relative[:, 1:], relative[:, :1], atol=1e-8)
    # The paper's frame: first basis point at the origin, second on -x, third in the xz plane.
    b0, b1, b2 = (relative[i, 0] for i in basis)
    assert np.allclose(b0, 0.0, atol=1e-9)
    assert b1[0] < 0 and np.allclose(b1[1:], 0.0, atol=1e-9)
    assert abs(b2[1]) < 1e-9 and b2[2] > 0
    # Distances are preserved: the relative map is the point set itself up to a rigid motion.
    assert np.allclose(
        np.linalg.norm(relative[:, 0, None] - relative[None, :, 0], axis=2),
        np.linalg.norm(points[:, None] - points[None], axis=2),
        atol=1e-8,
    )


def test_collinear_basis_is_refused() -> None:
    line = np.outer(np.arange(6.0), [3.0, 0.0, 0.0])
    assert choose_basis(line, 1.0) is None
    _, valid = basis_rotation(line[0], line[3], line[5], 1.0)
    assert not valid


# -- registration, charting, interval heuristic ---------------------------------------------------------


def test_matching_is_one_to_one_with_closest_winning() -> None:
    reference = np.array([[0.0, 0, 0], [5.0, 0, 0], [10.0, 0, 0]])
    query = np.array([[0.3, 0, 0], [0.1, 0, 0], [5.5, 0, 0], [30.0, 0, 0]])
    index, distance = match_nearest(reference, query, 2.0)
    assert index[1] == 0  # the closer claim keeps reference 0
    assert index[0] == NO_MATCH  # its second-nearest (reference 1) is 4.7 m away: beyond the bound
    assert index[2] == 1 and index[3] == NO_MATCH
    assert distance[1] == pytest.approx(0.1)


def test_mutual_matching_keeps_only_mutual_nearest_pairs_within_each_bound() -> None:
    reference = np.array([[0.0, 0, 0], [10.0, 0, 0], [20.0, 0, 0], [60.0, 0, 0]])
    bounds = np.array([1.0, 1.0, 1.0, 4.0])  # the far reference gets a wider bound
    query = np.array([[0.5, 0, 0], [0.9, 0, 0], [12.0, 0, 0], [63.0, 0, 0], [30.0, 0, 0]])
    index = match_mutual(reference, query, bounds)
    # 0.5 is reference 0's nearest; 0.9 is not (and not mutual); 12 is 2 m off a 1 m bound;
    # 63 is within the far bound; 30 is nobody's nearest within a bound.
    assert index.tolist() == [0, NO_MATCH, NO_MATCH, 3, NO_MATCH]
    assert match_mutual(reference[:0], query, bounds[:0]).tolist() == [NO_MATCH] * 5


def test_loop_vote_finds_the_shared_drift_and_ignores_chance_pairings() -> None:
    rng = np.random.default_rng(3)
    old = rng.uniform(-60, 60, (300, 3))
    drift = np.array([-4.0, 2.5, 6.0])
    returning = old[:8] - drift + rng.normal(0, 0.2, (8, 3))  # old points mapped again, off by the drift
    clutter = rng.uniform(-60, 60, (12, 3))  # young points with no old counterpart
    young = np.concatenate([returning, clutter])
    offset = vote_offset(young, old, radius=15.0, tolerance=1.5, support=4)
    assert offset is not None and np.linalg.norm(offset - drift) < 0.3
    # Three agreeing young points are not enough, and unrelated points never agree.
    assert vote_offset(np.concatenate([returning[:3], clutter]), old, radius=15.0, tolerance=1.5, support=4) is None
    assert vote_offset(clutter, old, radius=15.0, tolerance=1.5, support=4) is None
    # Beyond the search radius nothing is proposed.
    assert vote_offset(young, old, radius=5.0, tolerance=1.5, support=4) is None


def test_loop_vote_is_not_fooled_by_a_dense_map() -> None:
    # Landmarks crowd along a path (a tube): new landmarks have dozens of old neighbours within the
    # search radius, and chance offsets agree by the handful. Only a real drift is found.
    # (7.5 landmarks per metre of path; without the chance test this vote closes a loop 8 m off.)
    rng = np.random.default_rng(5)

    def tube(n: int, start: float, end: float) -> np.ndarray:
        return np.column_stack([rng.uniform(start, end, n), rng.uniform(-20, 20, n), rng.uniform(-5, 5, n)])

    old = tube(3000, 0, 400)
    assert vote_offset(tube(60, 180, 220), old, radius=15.0, tolerance=1.5, support=4) is None
    drift = np.array([5.0, -2.0, 1.0])
    returning = old[(old[:, 0] > 180) & (old[:, 0] < 220)][:60] - drift + rng.normal(0, 0.2, (60, 3))
    offset = vote_offset(returning, old, radius=15.0, tolerance=1.5, support=4)
    assert offset is not None and np.linalg.norm(offset - drift) < 0.3


def test_loop_vote_rejects_an_offset_a_repeating_scene_explains_as_well() -> None:
    # Cabinet doors along a wall: the same pattern of corners every 0.4 m. Young points seen on one
    # door fit the old points of the doors on either side (offsets 0.13 m and -0.27 m) alike; no drift
    # is singled out.
    rng = np.random.default_rng(2)
    door = rng.uniform(0, 0.3, (12, 3))
    old = np.concatenate([door + np.array([0.4 * i, 0, 0]) for i in range(8)])
    young = door + np.array([1.47, 0.0, 0.0]) + rng.normal(0, 0.003, door.shape)
    assert vote_offset(young, old, radius=0.6, tolerance=0.05, support=4, ambiguity=1.0) is not None
    assert vote_offset(young, old, radius=0.6, tolerance=0.05, support=4) is None
    # A single returning neighbourhood (no repetition) is still found.
    unique = rng.uniform(0, 3.2, (48, 3))
    drift = np.array([0.3, -0.1, 0.05])
    offset = vote_offset(unique[:10] - drift, unique, radius=0.6, tolerance=0.05, support=4)
    assert offset is not None and np.linalg.norm(offset - drift) < 0.01


def test_a_relocation_unlike_its_neighbours_is_inconsistent() -> None:
    # The adjustment shifts the path smoothly (a drift growing to 0.2 m); iteration 30's fit moves
    # it by 0.15 m more than its neighbours': that one, and only that one, is inconsistent.
    k = 60
    before = np.repeat(np.eye(4)[None], k, axis=0)
    before[:, 0, 3] = np.linspace(0, 6, k)
    after = before.copy()
    after[:, 1, 3] += np.linspace(0, 0.2, k)
    after[30, 2, 3] += 0.15
    seen = np.tile([0.0, 0.0, 2.0], (k, 1))
    fitted = np.ones(k, bool)
    flagged = inconsistent_relocations(before, after, fitted, seen, floor=0.03)
    assert flagged.tolist() == [i == 30 for i in range(k)]
    # A turn of the sensor moves what it saw even when its position barely moves.
    turned = after.copy()
    turned[30, 2, 3] -= 0.15
    turned[45, :3, :3] = Rotation.from_rotvec([0.05, 0, 0]).as_matrix()
    assert np.flatnonzero(inconsistent_relocations(before, turned, fitted, seen, floor=0.03)).tolist() == [45]
    # Unfitted iterations are not judged, and the floor keeps noise-sized differences.
    fitted[30] = False
    assert not inconsistent_relocations(before, after, fitted, seen, floor=0.03).any()
    assert not inconsistent_relocations(before, after, np.ones(k, bool), seen, floor=0.2).any()


def test_corrections_are_smoothed_over_the_fitted_neighbours() -> None:
    # A slow drift correction (0 to 0.2 m, 0 to 0.02 rad) with fit noise on every fitted iteration:
    # the smoothed poses follow the drift, the noise averaged out; unfitted iterations in reach
    # of fitted ones take their correction, those beyond keep their pose.
    rng = np.random.default_rng(8)
    k = 80
    before = np.repeat(np.eye(4)[None], k, axis=0)
    before[:, 0, 3] = np.linspace(0, 8, k)
    drift = np.linspace(0, 0.2, k)
    turn = Rotation.from_rotvec(np.outer(np.linspace(0, 0.02, k), [0, 0, 1]))
    truth = before.copy()
    truth[:, :3, :3] = turn.as_matrix()
    truth[:, 1, 3] += drift
    noisy = truth.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.01, (k, 3))
    fitted = np.ones(k, bool)
    fitted[40:44] = False
    fitted[70:] = False
    after = noisy.copy()
    after[~fitted] = before[~fitted] + 5.0  # what the caller carried: must be replaced within reach
    smoothed = smooth_corrections(before, after, fitted, window=10)
    inside = np.arange(k) < 70 + 10
    error = np.linalg.norm(smoothed[inside, :3, 3] - truth[inside, :3, 3], axis=1)
    assert error[:60].max() < 0.02 and np.sqrt(np.mean(error[:60] ** 2)) < 0.6 * 0.01 * np.sqrt(3)
    assert np.allclose(smoothed[~inside], after[~inside])
    angle = Rotation.from_matrix(smoothed[:70, :3, :3] @ np.transpose(truth[:70, :3, :3], (0, 2, 1))).magnitude()
    assert angle.max() < 0.002


def test_carried_corrections_come_from_the_nearest_solved_iteration_before() -> None:
    # Iterations 0, 3 and 7 solved (each moved by its own correction); the others take the correction
    # of the nearest solved one before them, so a path keeps its local shape between keyframes.
    k = 10
    before = np.repeat(np.eye(4)[None], k, axis=0)
    before[:, 0, 3] = np.arange(k, dtype=float)
    solved = np.zeros(k, bool)
    solved[[0, 3, 7]] = True
    after = before.copy()
    turn = Rotation.from_rotvec([0, 0, 0.1]).as_matrix()
    after[3, :3, :3] = turn
    after[3, :3, 3] += (0.0, 0.5, 0.0)
    after[7, :3, 3] += (0.0, 0.0, 1.0)
    carried = carry_corrections(before, after, solved)
    np.testing.assert_allclose(carried[solved], after[solved])
    np.testing.assert_allclose(carried[1:3], before[1:3])
    correction = after[3] @ np.linalg.inv(before[3])
    np.testing.assert_allclose(carried[4:7], correction @ before[4:7])
    np.testing.assert_allclose(carried[8:, :3, 3], before[8:, :3, 3] + (0.0, 0.0, 1.0))


@pytest.mark.parametrize("noise", [0.01, 0.3])
def test_drifting_residuals_are_told_from_static_noise_at_any_noise_level(noise: float) -> None:
    # 300 static points with white noise at their own level (noise to 3 noise), 60 observations each,
    # and 10 points drifting 4 of their noises along a line over their observations; 6 that slide by
    # half a noise, like a keypoint whose corner shifts with the viewpoint, are not movers.
    rng = np.random.default_rng(11)
    n_static, n_moving, n_sliding, n_obs = 300, 10, 6, 60
    n_points = n_static + n_moving + n_sliding
    point = np.repeat(np.arange(n_points), n_obs)
    level = noise * rng.uniform(1.0, 3.0, n_points)
    residual = rng.normal(0.0, 1.0, (len(point), 3)) * level[point, None]
    ramp = np.tile(np.linspace(-0.5, 0.5, n_obs), n_points)
    direction = rng.normal(size=(n_points, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    span = np.zeros(n_points)
    span[n_static : n_static + n_moving] = 4.0
    span[n_static + n_moving :] = 0.5
    residual += (span * level)[point, None] * ramp[:, None] * direction[point]
    by_time = np.argsort(np.tile(np.arange(n_obs), n_points), kind="stable")  # interleaved, as iterations deliver them
    probability, motion = residual_drift(point[by_time], residual[by_time], n_points, block=8)
    drifting = (probability < 1e-3) & (motion >= 1.0)
    assert drifting[n_static : n_static + n_moving].all()
    assert np.count_nonzero(drifting[:n_static]) <= 2  # 0.3 expected at 1e-3
    assert not drifting[n_static + n_moving :].any()
    # A static point's probability is uniform: about 5 % of them fall below 0.05.
    assert 0.02 < np.mean(probability[:n_static] < 0.05) < 0.09
    # Seen fewer than six times: not judged. Six times, moving 8 noises between its halves: drifting.
    few = np.repeat(np.arange(2), [5, 6])
    jump = rng.normal(size=(11, 3))
    jump[8:] += 8.0
    probability, motion = residual_drift(few, jump, 2, block=8)
    assert probability[0] == 1.0 and probability[1] < 1e-3 and motion[1] > 1.0


def test_dynamic_threshold_never_falls_below_the_noise_floor() -> None:
    # Static points whose noise differs threefold from point to point (near and far points of a depth
    # camera): the lower quartile of the first round sets too low a threshold and the noisiest are
    # flagged; a floor at what the largest noise explains keeps them all.
    rng = np.random.default_rng(4)
    sigma = np.repeat([0.005, 0.01, 0.015], 8)
    tracks = rng.uniform(-1, 1, (24, 1, 3)) + rng.normal(0, 1, (24, 40, 3)) * sigma[:, None, None]
    assert not detect_dynamic(tracks).static.all()
    result = detect_dynamic(tracks, floor=3 * np.sqrt(2) * 0.015)
    assert result.decided and result.static.all()
    # The floor does not hide a point that moves well beyond it.
    tracks[0] += np.linspace(0, 0.5, 40)[:, None] * [1, 0, 0]
    assert detect_dynamic(tracks, floor=3 * np.sqrt(2) * 0.015).static.tolist() == [False] + [True] * 23


def test_tail_bound_widens_with_heavy_tails_and_holds_against_a_minority_of_movers() -> None:
    rng = np.random.default_rng(7)
    # Deviations of static points under white noise: chi-like, narrow on a log scale.
    white = np.sqrt(rng.chisquare(7, 400) / 7)
    # The same with a heavy tail (Student t with 2 degrees of freedom, as tracker slips give).
    heavy = np.abs(rng.standard_t(2, 400)) + 0.2
    assert 1.5 < tail_bound(white, 3.0) / np.median(white) < 2.5
    assert tail_bound(heavy, 3.0) / np.median(heavy) > 1.5 * tail_bound(white, 3.0) / np.median(white)
    # A tenth of movers far above the bulk widens it a little, and stays far above it.
    movers = np.concatenate([white, np.full(40, 20.0)])
    assert tail_bound(movers, 3.0) < 1.25 * tail_bound(white, 3.0) < 20.0 / 4
    # Too few values, no finite ones, or no sigmas: no bound.
    assert tail_bound(white[:5], 3.0) == 0.0
    assert tail_bound(np.full(20, np.nan), 3.0) == 0.0
    assert tail_bound(white, 0.0) == 0.0


def test_required_support_grows_with_chance_agreement() -> None:
    from scipy.stats import poisson

    assert required_support(30, 0.03, 4) == 4
    for proposals, chance in ((300, 1.0), (3000, 3.0)):
        needed = required_support(proposals, chance, 4)
        assert proposals * poisson.sf(needed - 2, chance) <= 0.01 < proposals * poisson.sf(needed - 3, chance)


def test_drift_profile_follows_heading_drift_along_the_path() -> None:
    # A circular loop mapped with a heading error growing at a constant rate: the position error
    # peaks half way round and is smaller at the end. Knowing only the end offset, the profile
    # recovers the error along the path; the linear share cannot.
    n = 400
    angle = np.linspace(0.0, 2 * np.pi, n)
    true_path = 50.0 * np.column_stack([np.sin(angle), 1.0 - np.cos(angle), np.zeros(n)])
    heading_error = np.linspace(0.0, np.radians(3.0), n)
    steps = np.diff(true_path, axis=0)
    drifted_steps = np.column_stack(
        [
            np.cos(heading_error[:-1]) * steps[:, 0] - np.sin(heading_error[:-1]) * steps[:, 1],
            np.sin(heading_error[:-1]) * steps[:, 0] + np.cos(heading_error[:-1]) * steps[:, 1],
            steps[:, 2],
        ]
    )
    drifted = np.concatenate([true_path[:1], true_path[0] + np.cumsum(drifted_steps, axis=0)])
    error = true_path - drifted  # the correction each iteration needs
    profile = drift_profile(drifted, error[-1], max_angle=0.2)
    assert np.allclose(profile[[0, -1]], error[[0, -1]])
    linear = drift_share(np.arange(n), 0, n - 1)[:, None] * error[-1]
    assert np.abs(profile - error).max() < 0.1 * np.abs(error).max()
    assert np.abs(linear - error).max() > 0.5 * np.abs(error).max()
    # An offset a rotation within the limit cannot explain is spread linearly.
    assert np.allclose(drift_profile(drifted, 100 * error[-1], max_angle=0.2), 100 * linear)


def _chain_network(rng: np.random.Generator, n_groups: int = 12, per_group: int = 12, step: int = 6):
    """Groups along a corridor of points, each sharing half its members with the next.

    Returns true group poses (G, 4, 4), true points (P, 3) and the memberships (group, point,
    relative position in the group's frame), noise-free.
    """
    n_points = step * (n_groups - 1) + per_group
    points = np.column_stack(
        [np.linspace(0.0, 150.0, n_points), rng.uniform(-10, 10, n_points), rng.uniform(-3, 3, n_points)]
    )
    poses = np.array([random_pose(rng, 100.0) for _ in range(n_groups)])
    group = np.repeat(np.arange(n_groups), per_group)
    point = np.concatenate([np.arange(g * step, g * step + per_group) for g in range(n_groups)])
    # relative = T_world_group^-1 applied to the point
    relative = np.einsum("nji,nj->ni", poses[group, :3, :3], points[point] - poses[group, :3, 3])
    return poses, points, group, point, relative


def _perturbed(rng: np.random.Generator, poses: np.ndarray, points: np.ndarray):
    turns = Rotation.from_rotvec(rng.normal(0.0, 0.03, (len(poses), 3))).as_matrix()
    R = np.einsum("gij,gjk->gik", turns, poses[:, :3, :3])
    t = poses[:, :3, 3] + rng.normal(0.0, 1.0, (len(poses), 3))
    R[0], t[0] = poses[0, :3, :3], poses[0, :3, 3]  # the fixed group starts (and stays) right
    return R, t, points + rng.normal(0.0, 1.0, points.shape)


@pytest.mark.parametrize(
    "shape",
    [
        (12, 12, 6),  # 72 pose unknowns, 234 point unknowns: the points are eliminated
        (40, 12, 1),  # 240 pose unknowns, 153 point unknowns (a bundle adjustment's keyframes): the poses are
    ],
)
def test_adjustment_recovers_a_perturbed_network_of_relative_maps(shape: tuple[int, int, int]) -> None:
    rng = np.random.default_rng(5)
    poses, points, group, point, relative = _chain_network(rng, *shape)
    R, t, X = _perturbed(rng, poses, points)
    fixed = np.zeros(len(poses), bool)
    fixed[0] = True
    result = adjust_network(
        group, point, relative, np.full(len(group), 10.0), R, t, X, fixed, prior=0.0, robust=0.0, iterations=20
    )
    assert result.cost_before > 1e3 and result.cost_after < 1e-12
    assert np.abs(result.positions - points).max() < 1e-6
    assert np.abs(result.R_world_group - poses[:, :3, :3]).max() < 1e-8
    assert np.abs(result.t_world_group - poses[:, :3, 3]).max() < 1e-6
    # A weak pull towards the start (1 m off here) holds back only the chain's softest bending.
    held = adjust_network(
        group, point, relative, np.full(len(group), 10.0), R, t, X, fixed, prior=0.005, robust=0.0, iterations=20
    )
    start_error = np.linalg.norm(X - points, axis=1).max()
    assert np.linalg.norm(held.positions - points, axis=1).max() < 0.15 * start_error


def test_adjustment_with_the_poses_eliminated_survives_a_pose_seen_along_a_line() -> None:
    # 30 poses and 12 points (the poses are eliminated); pose 5 sees only three points on one line
    # through it, so it cannot turn about that line: the solve must stay finite and still lower the cost.
    rng = np.random.default_rng(0)
    points = np.column_stack([np.linspace(1, 12, 12), rng.uniform(-3, 3, 12), rng.uniform(-1, 1, 12)])
    points[:3] = [[1, 0, 0], [2, 0, 0], [3, 0, 0]]
    members = [[0, 1, 2] if g == 5 else list(range(12)) for g in range(30)]
    group = np.repeat(np.arange(30), [len(m) for m in members])
    point = np.concatenate(members)
    t = np.zeros((30, 3))
    t[:, 1] = np.linspace(0, 1, 30)
    t[5] = 0.0
    relative = points[point] - t[group]
    noise = rng.normal(0, 0.01, relative.shape)
    noise[group == 5] = 0.0
    fixed = np.zeros(30, bool)
    fixed[0] = True
    start = t + np.where(np.arange(30)[:, None] == 5, 0.0, 0.05)
    result = adjust_network(
        group, point, relative + noise, np.ones(len(group)), np.repeat(np.eye(3)[None], 30, axis=0), start,
        points + 0.05, fixed, prior=0.005, robust=0.03, iterations=10,
    )  # fmt: skip
    assert np.isfinite(result.positions).all() and np.isfinite(result.R_world_group).all()
    assert result.cost_after < result.cost_before


def test_adjustment_bounds_the_pull_of_a_wrong_relative_position() -> None:
    rng = np.random.default_rng(6)
    poses, points, group, point, relative = _chain_network(rng)
    noisy = relative + rng.normal(0.0, 0.05, relative.shape)
    wrong = 40  # a mismatched or moving member, 5 m off in its group's map
    R, t, X = _perturbed(rng, poses, points)
    fixed = np.zeros(len(poses), bool)
    fixed[0] = True
    weight = np.full(len(group), 10.0)
    others = np.ones(len(points), bool)
    others[point[wrong]] = False

    def worst_error(relative: np.ndarray, robust: float) -> float:
        result = adjust_network(
            group, point, relative, weight, R, t, X, fixed, prior=0.005, robust=robust, iterations=30
        )
        return float(np.linalg.norm(result.positions[others] - points[others], axis=1).max())

    clean = worst_error(noisy, 0.5)  # 5 cm noise over a 150 m chain: ~0.7 m at its far end
    noisy[wrong] += (3.0, 4.0, 0.0)
    assert worst_error(noisy, 0.5) < 1.1 * clean
    assert worst_error(noisy, 0.0) > 2.0 * clean


def test_drift_share_ramps_from_the_last_visit_to_now() -> None:
    assert drift_share([0, 100, 150, 200, 250], 100, 200).tolist() == [0.0, 0.0, 0.5, 1.0, 1.0]


def test_motion_model_predicts_by_age() -> None:
    model = MotionModel()
    step = np.eye(4)
    step[:3, 3] = [-1.2, 0.0, 0.0]  # sensor moved 1.2 m forward
    model.T_curr_prev = step
    points = np.array([[10.0, 0, 0], [10.0, 0, 0]])
    predicted = model.predict(points, np.array([1, 3]))
    assert np.allclose(predicted, [[8.8, 0, 0], [6.4, 0, 0]])


def test_global_index_finds_neighbours_and_tracks_moves() -> None:
    index = GlobalIndex(3.0)
    index.update(np.array([0, 1, 2]), np.array([[0.0, 0, 0], [2.5, 0, 0], [50.0, 0, 0]]))
    assert sorted(index.candidates(np.array([1.0, 0, 0]))) == [0, 1]
    index.update(np.array([1]), np.array([[60.0, 0, 0]]))
    assert sorted(index.candidates(np.array([1.0, 0, 0]))) == [0]
    index.remove([0])
    assert index.candidates(np.array([1.0, 0, 0])) == [] and len(index) == 2


def test_global_index_keys_find_every_point_within_a_cell() -> None:
    # Packed cell keys: neighbours across every axis and sign, and far out (clipped keys) no misses.
    rng = np.random.default_rng(19)
    for scale in (10.0, 1e8):
        positions = rng.uniform(-scale, scale, (300, 3))
        index = GlobalIndex(3.0)
        index.update(np.arange(300), positions)
        for query in positions[:40] + rng.uniform(-3.0, 3.0, (40, 3)):
            found = set(index.candidates(query))
            near = np.flatnonzero(np.linalg.norm(positions - query, axis=1) <= 3.0)
            assert set(near.tolist()) <= found
            assert found == set(index.candidates_at(int(index.keys(query[None])[0])))


def test_charting_detects_duplicates_and_enumerates_intervals() -> None:
    charting = PointCharting(4)
    assert not charting.chart(0, [3, 1, 2]).any()
    assert charting.chart(1, [1, 5, 1]).tolist() == [False, False, True]
    charting.chart(2, [7])
    assert charting.enumerate(0, 2).tolist() == [1, 2, 3, 5, 7]
    charting.chart(6, [9])  # overwrites iteration 2's slot; the ring forgets beyond 4 iterations
    assert charting.seen(2).size == 0 and charting.enumerate(3, 6).tolist() == [9]


def test_rings_are_bounded_and_merging_copies_observations() -> None:
    store = PointStore(ring_size=4, capacity=4)
    a, b = store.new_points(2)
    for t in range(10):
        store.add_observations(np.array([a]), np.array([[t, 0.0, 0.0]]), t)
    assert store.obs.shape == (store.capacity, 4, 3)
    xyz, valid = store.observations(np.array([a]), np.arange(5, 10))
    assert valid.tolist() == [[False, True, True, True, True]] and xyz[0, -1, 0] == 9.0
    for t in (12, 13):
        store.add_observations(np.array([b]), np.array([[100.0 + t, 0, 0]]), t)
    assert not store.co_observed(a, b)
    store.merge_into(a, b)
    assert store.last_iter[a] == 13 and store.n_obs[a] == 12
    # Iterations 12 and 13 took the slots of 8 and 9 (ring of 4); 6 and 7 survive.
    assert store.presence(np.array([a]), 6, 13).tolist() == [[True, True, False, False, False, False, True, True]]


def test_member_heuristic_trades_interval_for_members() -> None:
    # Creation point 0 seen in all 10 iterations; grouped 1-3 too; 4 loses 1 iteration; 5 and 6 half.
    presence = np.ones((7, 10), bool)
    presence[4, 0] = False
    presence[5, :5] = False
    presence[6, 5:] = False
    grouped = np.array([False, True, True, True, False, False, False])
    chosen = select_members(presence, grouped, creation=0)
    assert chosen is not None
    rows, interval = chosen
    # 5 members x 9 iterations = 45 beats 4 x 10; a sixth would give 6 x 5 = 30 < 45: stop there.
    assert sorted(rows.tolist()) == [0, 1, 2, 3, 4] and interval.sum() == 9
    assert select_members(presence, np.zeros(7, bool), creation=0) is None  # no previous points


def test_id_tally_majority_and_merge() -> None:
    tally = IdTally(fold_every=3)
    tally.add(np.array([10, 11]), np.array([5, 7]))
    tally.add(np.array([10, 11]), np.array([5, 8]))
    tally.add(np.array([10, 11]), np.array([6, 8]))
    tally.add(np.array([12]), np.array([9]))
    ids, purity = tally.majority(np.array([10, 11, 12, 13]))
    assert ids.tolist() == [5, 8, 9, -1]
    assert purity[:3] == pytest.approx([2 / 3, 2 / 3, 1.0])
    tally.relabel(12, 10)
    ids, _ = tally.majority(np.array([10, 12]))
    assert ids.tolist() == [5, -1]


# -- dynamic detection --------------------------------------------------------------------------------


def rigid_tracks(rng: np.random.Generator, m: int, length: int, moving: int, noise: float = 0.3) -> np.ndarray:
    """Tracks (m, length, 3) seen from a moving sensor; the first ``moving`` wander independently."""
    points = rng.uniform(-40, 40, (m, 3))
    drift = np.cumsum(rng.normal(0.0, 0.6, (moving, length, 3)), axis=1)
    tracks = np.empty((m, length, 3))
    for t in range(length):
        world = points.copy()
        world[:moving] += drift[:, t]
        tracks[:, t] = apply_transform(random_pose(rng, 10.0), world) + rng.normal(0, noise, (m, 3))
    return tracks


@pytest.mark.parametrize("share", [0.0, 0.2, 0.4])
def test_uncorrelated_points_are_binned_out(share: float) -> None:
    rng = np.random.default_rng(7)
    m = 120
    moving = int(share * m)
    result = detect_dynamic(rigid_tracks(rng, m, 30, moving))
    assert result.decided
    assert not result.static[:moving].any()
    assert result.static[moving:].mean() >= 0.97
    # n log n: a handful of comparisons per point, far from the n^2 / 2 of all pairs.
    assert result.comparisons <= 3 * m * np.log2(m)


def test_gap_rule_splits_at_the_first_large_jump() -> None:
    deviations = np.array([0.40, 0.42, 0.41, 0.45, 0.43, 0.39, 0.44, 0.42, 2.5, 3.0, 4.1])
    threshold = gap_threshold(deviations, 0.5)
    assert 0.45 < threshold < 2.5
    assert gap_threshold(np.array([0.4, 0.41, 0.43]), 0.5) > 0.43  # no gap: all alike


def test_consensus_rejects_a_moving_minority_that_trimming_keeps() -> None:
    # Five of fourteen anchors displaced by ~3 m: the median rule keeps some of them, the
    # three-point consensus drops them all and recovers the transform to the noise level.
    rng = np.random.default_rng(1)
    T = random_pose(rng)
    source = rng.uniform(-30, 30, (14, 3))
    target = apply_transform(T, source) + rng.normal(0, 0.2, (14, 3))
    target[:5] += rng.normal(0, 3.0, (5, 3))
    trimmed = fit_transform(source, target, trim=3.0, floor=0.5)
    robust = fit_transform(source, target, trim=3.0, floor=0.5, consensus=1.0)
    assert trimmed is not None and robust is not None
    assert trimmed.inliers[:5].any()
    assert not robust.inliers[:5].any() and robust.inliers[5:].all()
    assert np.linalg.norm(robust.T[:3, 3] - T[:3, 3]) < 0.3 < np.linalg.norm(trimmed.T[:3, 3] - T[:3, 3])
    # Without outliers beyond the bound the consensus changes nothing.
    clean = apply_transform(T, source) + rng.normal(0, 0.2, (14, 3))
    plain, guarded = fit_transform(source, clean), fit_transform(source, clean, consensus=1.0)
    assert plain is not None and guarded is not None and np.array_equal(plain.T, guarded.T)


def test_off_line_rms_and_row_median_match_numpy() -> None:
    rng = np.random.default_rng(3)
    for points in (rng.normal(0, 5, (30, 3)), np.outer(rng.normal(0, 5, 30), [1.0, 2.0, 3.0]), np.eye(3)):
        centred = points - points.mean(axis=0)
        assert is_collinear(points, 0.05) == (
            np.sqrt(max(np.linalg.eigvalsh(centred.T @ centred / 30)[:2].sum(), 0)) <= 0.05
        )
    values = rng.normal(size=(40, 7))
    values[rng.random((40, 7)) < 0.4] = np.nan
    values[0] = np.nan
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
        expected = np.nanmedian(values, axis=1)
    assert np.allclose(row_nanmedian(values), expected, equal_nan=True)


def test_block_deviation_separates_a_slow_mover() -> None:
    # A point drifting 3 m over 40 iterations (0.075 m per iteration, a quarter of the noise)
    # hides in single-observation deviations but stands out of block means.
    rng = np.random.default_rng(5)
    m, length = 12, 40
    points = rng.uniform(-30, 30, (m, 3))
    tracks = np.empty((m, length, 3))
    for t in range(length):
        world = points.copy()
        world[0] += np.array([3.0, 0.0, 0.0]) * t / length
        tracks[:, t] = apply_transform(random_pose(rng, 10.0), world) + rng.normal(0, 0.3, (m, 3))
    valid = np.ones((m, length), bool)
    references = np.arange(1, 7)
    plain = deviation_to_references(tracks, valid, references, 15)
    blocked = deviation_to_references(tracks, valid, references, 15, block=5)
    ratio_plain = plain[0] / np.median(plain[1:])
    ratio_blocked = blocked[0] / np.median(blocked[1:])
    assert ratio_blocked > 2.0 and ratio_blocked > 1.5 * ratio_plain


def test_world_scatter_flags_motion_across_the_line_of_sight() -> None:
    # Known poses map observations to world: a static point's block means scatter by the noise
    # over sqrt(block), a point moving 3 m over the window by its motion, in any direction.
    rng = np.random.default_rng(6)
    length = 40
    poses = np.stack([random_pose(rng, 10.0) for _ in range(length)])
    world = np.repeat(rng.uniform(-30, 30, (6, 1, 3)), length, axis=1)
    world[0] += np.outer(np.linspace(0.0, 3.0, length), [0.0, 0.0, 1.0])
    inverse = np.linalg.inv(poses)
    tracks = np.einsum("lab,nlb->nla", inverse[:, :3, :3], world) + inverse[None, :, :3, 3]
    tracks += rng.normal(0, 0.3, tracks.shape)
    valid = np.ones((6, length), bool)
    scatter = world_block_deviation(tracks, valid, poses, 5)
    assert scatter[0] > 3.0 * np.max(scatter[1:])
    assert np.all(scatter[1:] < 0.35)
    valid[1, :30] = False  # two blocks only: not judged
    assert np.isnan(world_block_deviation(tracks, valid, poses, 5)[1])


# -- compiled kernels against their numpy meaning ----------------------------------------------------
# Each reference below is the numpy expression a kernel's docstring gives (several are the numpy
# implementations the kernels replaced).


def numpy_rigid_fit(source, target, weights):  # type: ignore[no-untyped-def]
    mean_source, mean_target = weights @ source / weights.sum(), weights @ target / weights.sum()
    centred = (source - mean_source) * weights[:, None]
    U, _, Vt = np.linalg.svd(centred.T @ target)
    if np.linalg.det(Vt.T @ U.T) < 0:
        Vt[2] = -Vt[2]
    R = Vt.T @ U.T
    scatter = centred.T @ source / weights.sum()
    spread = np.sqrt(max(np.linalg.eigvalsh(scatter)[:2].sum(), 0.0))
    return R, mean_target - R @ mean_source, spread


@pytest.mark.parametrize("case", ["plain", "mirrored", "coplanar", "noisy"])
def test_rigid_fit_kernel_equals_numpy_svd_fit(case: str) -> None:
    rng = np.random.default_rng(["plain", "mirrored", "coplanar", "noisy"].index(case))
    for _ in range(200):
        n = int(rng.integers(3, 60))
        source = rng.normal(0, 1, (n, 3)) * rng.uniform(0.5, 30, 3)
        if case == "coplanar":
            source[:, 2] = 0.0
        R_true = Rotation.random(random_state=rng).as_matrix()
        if case == "mirrored":  # the best orthogonal map is a reflection: the fit must stay proper
            R_true = R_true @ np.diag([1.0, 1.0, -1.0])
        target = source @ R_true.T + rng.uniform(-20, 20, 3)
        target += rng.normal(0, {"plain": 0.0, "noisy": 2.0}.get(case, 0.1), (n, 3))
        weights = rng.uniform(0.1, 3.0, n)
        use = rng.random(n) < 0.8
        use[:3] = True
        T, spread = _kernels.rigid_fit(source, target, weights, use)
        R, t, spread_ref = numpy_rigid_fit(source[use], target[use], weights[use])
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
        assert np.allclose(T[:3, :3], R, atol=1e-8) and np.allclose(T[:3, 3], t, atol=1e-6)
        assert np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
        assert spread == pytest.approx(spread_ref, rel=1e-6, abs=1e-9)
        # Horn's quaternion rotation alone, on the raw cross-covariance.
        H = rng.normal(size=(3, 3))
        U, _, Vt = np.linalg.svd(H)
        R_svd = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
        T = np.eye(4)
        _kernels.best_rotation_into(T, H)
        assert np.allclose(T[:3, :3], R_svd, atol=1e-9)


def test_trimming_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(11)
    for _ in range(300):
        n = int(rng.integers(5, 80))
        values = np.round(rng.exponential(1.0, n), int(rng.integers(0, 3)))  # with ties
        use = rng.random(n) < 0.7
        use[0] = True
        assert _kernels._masked_median(values, use) == np.median(values[use])
        source = rng.uniform(-30, 30, (n, 3))
        T = random_pose(rng)
        target = apply_transform(T, source) + rng.normal(0, 0.3, (n, 3))
        target[: n // 5] += rng.normal(0, 5.0, (n // 5, 3))
        weights = rng.uniform(0.5, 2.0, n)
        residual = np.linalg.norm(target - source @ T[:3, :3].T - T[:3, 3], axis=1)
        assert np.allclose(_kernels.pair_residuals(source, target, T), residual, rtol=1e-12, atol=1e-12)
        # Trimming rounds, as numpy.
        allowed = rng.random(n) < 0.9
        allowed[:5] = True
        T_ref, inliers_ref = np.eye(4), allowed
        for _ in range(2):
            residual = np.linalg.norm(target - source @ T_ref[:3, :3].T - T_ref[:3, 3], axis=1)
            keep = allowed & (residual <= max(3.0 * np.median(residual[allowed]), 0.5))
            if np.array_equal(keep, inliers_ref) or keep.sum() < 3:
                break
            R, t, spread = numpy_rigid_fit(source[keep], target[keep], weights[keep])
            if spread <= 0.05:
                break
            T_ref, inliers_ref = np.eye(4), keep
            T_ref[:3, :3], T_ref[:3, 3] = R, t
        T_fit, inliers = _kernels.trimmed_fit(source, target, weights, np.eye(4), allowed, 3.0, 0.5, 2, 0.05)
        assert np.array_equal(inliers, inliers_ref) and np.allclose(T_fit, T_ref, atol=1e-7)


def numpy_match_nearest(reference, query, bound):  # type: ignore[no-untyped-def]
    """The k-d tree matching the kernels replaced."""
    index, distance = np.full(len(query), NO_MATCH), np.full(len(query), np.inf)
    k = 2 if len(reference) > 1 else 1
    d, j = cKDTree(reference).query(query, k=k, distance_upper_bound=bound)
    d, j = d.reshape(len(query), k), j.reshape(len(query), k)
    taken = np.zeros(len(reference) + 1, bool)
    taken[-1] = True
    for column in range(k):
        pending = np.flatnonzero(index == NO_MATCH)
        cand = j[pending, column]
        ok = ~taken[cand]
        pending, cand, dist = pending[ok], cand[ok], d[pending[ok], column]
        order = np.lexsort((dist, cand))
        chosen = order[np.r_[True, cand[order][1:] != cand[order][:-1]]] if len(order) else order
        index[pending[chosen]], distance[pending[chosen]] = cand[chosen], dist[chosen]
        taken[cand[chosen]] = True
    return index, distance


def test_matching_kernels_equal_k_d_tree_matching() -> None:
    rng = np.random.default_rng(12)
    for _ in range(300):
        m, n = int(rng.integers(1, 80)), int(rng.integers(1, 80))
        reference = rng.uniform(-8, 8, (m, 3))
        query = rng.uniform(-8, 8, (n, 3))
        bound = float(rng.uniform(0.5, 4.0))
        d, j = cKDTree(reference).query(query, k=2, distance_upper_bound=bound)
        j_kernel, d_kernel = _kernels.nearest_two(reference, np.argsort(reference[:, 0]), query, bound)
        if m > 1:
            assert np.array_equal(j_kernel, j) and np.allclose(d_kernel, d, rtol=1e-12)
        index, distance = match_nearest(reference, query, bound)
        index_ref, distance_ref = numpy_match_nearest(reference, query, bound)
        assert np.array_equal(index, index_ref) and np.allclose(distance, distance_ref, rtol=1e-12)


def test_mutual_nearest_kernel_equals_numpy() -> None:
    rng = np.random.default_rng(18)
    for _ in range(200):
        q_count, r_count = int(rng.integers(1, 30)), int(rng.integers(1, 30))
        query = rng.uniform(-8, 8, (q_count, 3))
        reference = np.round(rng.uniform(-8, 8, (r_count, 3)))  # rounded: some distance ties
        bounds = rng.uniform(0.5, 6.0, r_count)
        difference = query[:, None, :] - reference[None, :, :]
        distance = np.sqrt(np.einsum("qrk,qrk->qr", difference, difference))
        nearest_reference, nearest_query = distance.argmin(axis=1), distance.argmin(axis=0)
        rows = np.arange(q_count)
        mutual = (nearest_query[nearest_reference] == rows) & (
            distance[rows, nearest_reference] <= bounds[nearest_reference]
        )
        expected = np.where(mutual, nearest_reference, -1)
        assert np.array_equal(_kernels.mutual_nearest(reference, query, bounds), expected)


def test_placement_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(13)
    c = 50
    pos_sum, pos_weight, pos_sq = rng.normal(0, 10, (c, 3)), rng.uniform(0, 5, c), rng.uniform(0, 500, c)
    pos_weight[:5] = 0.0
    ids = rng.permutation(c)[:30]
    weight = pos_weight[ids]
    expected = pos_sum[ids] / np.maximum(weight, 1e-300)[:, None]
    expected[weight <= 0] = np.nan
    assert np.allclose(_kernels.gather_positions(pos_sum, pos_weight, ids), expected, equal_nan=True)
    w = np.maximum(weight, 1e-12)
    mean = pos_sum[ids] / w[:, None]
    expected = np.sqrt(np.maximum(pos_sq[ids] / w - np.sum(mean**2, axis=1), 0.0))
    assert np.allclose(_kernels.gather_spread(pos_sum, pos_weight, pos_sq, ids), expected)
    # Swapping a group's contribution.
    old, new = rng.normal(0, 10, (30, 3)), rng.normal(0, 10, (30, 3))
    sums, weights, squares = pos_sum.copy(), pos_weight + 2.0, pos_sq.copy()
    expected_sum = sums.copy()
    expected_sum[ids] += 1.5 * new - 2.0 * old
    expected_weight = weights.copy()
    expected_weight[ids] += 1.5 - 2.0
    expected_sq = squares.copy()
    expected_sq[ids] += 1.5 * np.sum(new**2, axis=1) - 2.0 * np.sum(old**2, axis=1)
    _kernels.replace_contribution(sums, weights, squares, ids, old, 2.0, new, 1.5)
    assert np.allclose(sums, expected_sum) and np.allclose(weights, expected_weight)
    assert np.allclose(squares, expected_sq)
    # Withdrawing the only contribution leaves no ghost weight.
    _kernels.replace_contribution(sums, weights, squares, ids[:1], new[:1], weights[ids[0]], new[:1], 0.0)
    assert weights[ids[0]] == 0.0 and not sums[ids[0]].any() and squares[ids[0]] == 0.0


def test_motion_and_basis_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(14)
    T = random_pose(rng, 2.0)
    points, age = rng.normal(0, 10, (40, 3)), rng.integers(1, 5, 40)
    powers = np.stack([np.linalg.matrix_power(T, a) for a in range(1, 5)])[age - 1]
    expected = np.einsum("nij,nj->ni", powers[:, :3, :3], points) + powers[:, :3, 3]
    assert np.allclose(_kernels.transform_by_age(T, points, age), expected)
    observations = rng.normal(0, 5, (12, 9, 3))
    observations[:, 4] = observations[0, 4]  # one degenerate iteration
    R, valid = basis_rotation(observations[3], observations[7], observations[1], 1.0)
    expected = np.matmul((observations - observations[3][None]).transpose(1, 0, 2), R).transpose(1, 0, 2)
    relative, valid_kernel = _kernels.basis_coordinates(observations, 3, 7, 1, 1.0)
    assert np.array_equal(valid_kernel, valid) and not valid[4]
    assert np.allclose(relative, expected)
    for _ in range(100):
        m = int(rng.integers(3, 30))
        cloud = rng.normal(0, 1, (m, 3)) * rng.uniform(0.1, 10, 3)
        centred = cloud - cloud.mean(axis=0)
        i0 = int(np.argmax(np.sum(centred**2, axis=1)))
        squared = np.sum((cloud - cloud[i0]) ** 2, axis=1)
        i1 = int(np.argmax(squared))
        along = (cloud - cloud[i0]) @ ((cloud[i1] - cloud[i0]) / np.sqrt(squared[i1]))
        i2 = int(np.argmax(squared - along**2))
        ok = squared[i1] >= 1.0 and (squared - along**2)[i2] >= 1.0
        assert choose_basis(cloud, 1.0) == ((i0, i1, i2) if ok else None)


def numpy_select_members(presence, grouped, creation, seeds):  # type: ignore[no-untyped-def]
    """The numpy interval x count heuristic the kernel replaced."""
    order = np.argsort(-presence.sum(axis=1), kind="stable")
    order = order[order != creation]
    previous = order[grouped[order]]
    previous = previous[(presence[previous] & presence[creation]).any(axis=1)]
    if len(previous) < seeds:
        return None
    seed_rows = np.concatenate(([creation], previous[:seeds]))
    interval = np.logical_and.reduce(presence[seed_rows], axis=0)
    if not interval.any():
        return None
    rest = order[~np.isin(order, seed_rows)]
    if len(rest) == 0:
        return seed_rows, interval
    running = np.logical_and.accumulate(presence[rest] & interval[None, :], axis=0)
    scores = running.sum(axis=1) * (len(seed_rows) + 1 + np.arange(len(rest)))
    failed = np.flatnonzero(scores <= np.concatenate(([interval.sum() * len(seed_rows)], scores[:-1])))
    take = int(failed[0]) if len(failed) else len(rest)
    return np.concatenate((seed_rows, rest[:take])), (running[take - 1] if take else interval)


def test_member_selection_kernel_equals_numpy() -> None:
    rng = np.random.default_rng(15)
    for _ in range(500):
        n, length = int(rng.integers(1, 40)), int(rng.integers(1, 30))
        presence = rng.random((n, length)) < rng.uniform(0.3, 1.0)
        grouped = rng.random(n) < rng.uniform(0.0, 1.0)
        creation, seeds = int(rng.integers(0, n)), int(rng.integers(1, 5))
        chosen = select_members(presence, grouped, creation, seeds)
        expected = numpy_select_members(presence, grouped, creation, seeds)
        assert (chosen is None) == (expected is None)
        if chosen is not None:
            assert np.array_equal(chosen[0], expected[0]) and np.array_equal(chosen[1], expected[1])


def test_ring_kernels_equal_numpy_indexing() -> None:
    rng = np.random.default_rng(16)
    obs, obs_iter = rng.normal(size=(20, 8, 3)), rng.integers(-1, 30, (20, 8))
    ids, iterations = rng.permutation(20)[:12], np.arange(-2, 25)
    slots = iterations % 8
    xyz, valid = _kernels.ring_observations(obs, obs_iter, ids, iterations)
    assert np.array_equal(xyz, obs[ids[:, None], slots[None, :]])
    expected = (obs_iter[ids[:, None], slots[None, :]] == iterations[None, :]) & (iterations[None, :] >= 0)
    assert np.array_equal(valid, expected)
    assert np.array_equal(_kernels.ring_presence(obs_iter, ids, -2, 24), valid)
    # An unwritten slot (-1) is not an observation at iteration -1.
    obs_iter[ids[0], -1 % 8] = -1
    assert not _kernels.ring_observations(obs, obs_iter, ids, iterations)[1][0, 1]
    assert not _kernels.ring_presence(obs_iter, ids, -2, 24)[0, 1]


def _numpy_reference_deviations(
    tracks: np.ndarray, valid: np.ndarray, references: np.ndarray, min_common: int, block: int
) -> np.ndarray:
    both = valid[:, None, :] & valid[references][None, :, :]  # (N, R, L)
    difference = tracks[:, None, :, :] - tracks[references][None, :, :, :]
    distance = np.where(both, np.sqrt(np.einsum("nrlk,nrlk->nrl", difference, difference)), 0.0)
    usable = (both.sum(axis=2) >= min_common) & (np.arange(len(tracks))[:, None] != references[None, :])
    if block > 1:
        n, r, length = distance.shape
        blocks = -(-length // block)
        pad = blocks * block - length
        distance = np.concatenate([np.zeros((n, r, pad)), distance], axis=2)
        both = np.concatenate([np.zeros((n, r, pad), bool), both], axis=2)
        sums = distance.reshape(n, r, blocks, block).sum(axis=3)
        counts = both.reshape(n, r, blocks, block).sum(axis=3)
        both = counts >= 2
        distance = np.where(both, sums / np.maximum(counts, 1), 0.0)
        usable &= both.sum(axis=2) >= 3
    count = both.sum(axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = distance.sum(axis=2) / count
        variance = np.where(both, (distance - mean[..., None]) ** 2, 0.0).sum(axis=2) / (count - 1)
    return np.where(usable, np.sqrt(variance), np.nan)


def _numpy_block_mean_scatter(tracks: np.ndarray, valid: np.ndarray, poses: np.ndarray, block: int) -> np.ndarray:
    n, length = valid.shape
    world = np.einsum("lab,nlb->nla", poses[:, :3, :3], tracks) + poses[None, :, :3, 3]
    blocks = length // block
    if blocks == 0:
        return np.full(n, np.nan)
    tail = slice(length - blocks * block, length)
    sums = np.where(valid[:, tail, None], world[:, tail], 0.0).reshape(n, blocks, block, 3).sum(axis=2)
    counts = valid[:, tail].reshape(n, blocks, block).sum(axis=2)
    usable = counts >= 2
    means = sums / np.maximum(counts, 1)[..., None]
    used = usable.sum(axis=1)
    centre = np.where(usable[..., None], means, 0.0).sum(axis=1) / np.maximum(used, 1)[:, None]
    scatter = np.where(usable[..., None], (means - centre[:, None]) ** 2, 0.0).sum(axis=(1, 2))
    return np.where(used >= 3, np.sqrt(scatter / np.maximum(used - 1, 1)), np.nan)


@pytest.mark.parametrize("block", [1, 3, 5])
def test_sweep_kernels_equal_numpy(block: int) -> None:
    rng = np.random.default_rng(17 + block)
    for length in (4, 13, 40):
        tracks = rng.normal(0.0, 10.0, (9, length, 3))
        valid = rng.random((9, length)) < 0.8
        valid[0] = False  # never observed: never compared
        references = np.array([1, 4, 2, 7])
        expected = _numpy_reference_deviations(tracks, valid, references, 3, block)
        kernel = _kernels.reference_deviations(tracks, valid, references, 3, block)
        assert np.allclose(kernel, expected, rtol=1e-12, atol=1e-12, equal_nan=True)
        assert np.isnan(kernel[0]).all() and np.isnan(kernel[4, 1]) and (length < 13 or np.isfinite(kernel).any())
        poses = np.stack([random_pose(rng, 10.0) for _ in range(length)])
        expected = _numpy_block_mean_scatter(tracks, valid, poses, block)
        kernel = _kernels.block_mean_scatter(tracks, valid, poses, block)
        assert np.allclose(kernel, expected, rtol=1e-12, atol=1e-12, equal_nan=True)
        assert np.isnan(kernel[0])


def numpy_match_recent(reference, age, points, T_curr_prev, bound, angle, predict):  # type: ignore[no-untyped-def]
    """Local matching step by step in numpy (the kernel ``match_recent``'s meaning)."""

    def motion(row):  # type: ignore[no-untyped-def]
        pairs = np.flatnonzero((row >= 0) & (age[np.maximum(row, 0)] == 1))
        fit = fit_transform(reference[row[pairs]], points[pairs], trim=0.0, collinear_tolerance=0.05)
        return None if fit is None else fit.T

    predicted = _kernels.transform_by_age(T_curr_prev, reference, age) if predict else reference
    row = match_nearest(predicted, points, bound)[0]
    T = T_curr_prev
    T_new = motion(row)
    measured = T_new is not None
    if measured:
        T = T_new
        D = T_new @ np.linalg.inv(T_curr_prev)
        angle_change = np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))
        shift = np.linalg.norm(D[:3, 3]) + angle_change * np.sqrt(np.max(np.sum(reference**2, axis=1)))
        if predict and shift > bound / 2:
            predicted = _kernels.transform_by_age(T, reference, age)
            row = match_nearest(predicted, points, bound)[0]
    far = 0
    if predict and angle > 0:
        free_points = np.flatnonzero(row == NO_MATCH)
        free_refs = np.setdiff1d(np.arange(len(reference)), row)
        if len(free_points) and len(free_refs):
            bounds = bound + angle * np.linalg.norm(predicted[free_refs], axis=1)
            found = match_mutual(predicted[free_refs], points[free_points], bounds)
            row[free_points[found >= 0]] = free_refs[found[found >= 0]]
            far = int(np.count_nonzero(found >= 0))
            if far:
                T_far = motion(row)
                if T_far is not None:
                    T, measured = T_far, True
    return row, T, measured, far


def test_local_matching_kernel_equals_numpy() -> None:
    rng = np.random.default_rng(21)
    for trial in range(300):
        m = int(rng.integers(1, 60))
        reference = rng.uniform(-20, 20, (m, 3))
        age = rng.integers(1, 4, m)
        T_true = random_pose(rng, 0.8)
        T_true[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix()
        carried = _kernels.transform_by_age(T_true, reference, age)
        keep = rng.random(m) < 0.8
        points = np.concatenate(
            [carried[keep] + rng.normal(0, 0.1, (int(keep.sum()), 3)), rng.uniform(-20, 20, (5, 3))]
        )
        points = points[rng.permutation(len(points))]
        T_guess = np.eye(4) if trial % 3 == 0 else T_true @ random_pose(rng, 0.3) if trial % 3 == 1 else T_true
        bound, angle, predict = float(rng.uniform(0.5, 2.0)), float(rng.choice([0.0, 0.05])), bool(trial % 5)
        row, T, measured, far = _kernels.match_recent(reference, age, points, T_guess, bound, angle, predict, 0.05)
        row_ref, T_ref, measured_ref, far_ref = numpy_match_recent(
            reference, age, points, T_guess, bound, angle, predict
        )
        assert np.array_equal(row, row_ref) and measured == measured_ref and far == far_ref
        assert np.allclose(T, T_ref, atol=1e-12)


def test_stable_argsort_and_prediction_shift_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(22)
    for n in (0, 1, 2, 7, 64, 65, 200):
        values = np.round(rng.normal(0, 3, n))  # rounded: ties
        assert np.array_equal(_kernels._stable_argsort(values), np.argsort(values, kind="stable"))
    for _ in range(50):
        T_new, T_before, reference = random_pose(rng, 2.0), random_pose(rng, 2.0), rng.normal(0, 10, (20, 3))
        D = T_new @ np.linalg.inv(T_before)
        angle = np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))
        expected = np.linalg.norm(D[:3, 3]) + angle * np.sqrt(np.max(np.sum(reference**2, axis=1)))
        assert np.isclose(_kernels._prediction_shift(T_new, T_before, reference), expected, rtol=1e-12)


def random_store_arrays(rng: np.random.Generator, c: int = 80):  # type: ignore[no-untyped-def]
    """Per-point arrays like a PointStore's: positions' accumulators, flags, verification, uids."""
    pos_weight = np.where(rng.random(c) < 0.7, rng.uniform(0.5, 20, c), 0.0)
    pos_sum = rng.normal(0, 10, (c, 3)) * pos_weight[:, None]
    pos_sq = np.sum(pos_sum**2, axis=1) / np.maximum(pos_weight, 1e-12) + rng.uniform(0, 2, c) * pos_weight
    return {
        "pos_sum": pos_sum,
        "pos_weight": pos_weight,
        "pos_sq": pos_sq,
        "alive": rng.random(c) < 0.9,
        "dynamic": rng.random(c) < 0.15,
        "verified": np.where(rng.random(c) < 0.6, rng.integers(0, 50, c), -1),
        "uid": rng.permutation(c).astype(np.int64),
    }


def test_anchor_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(23)
    for trial in range(50):
        s = random_store_arrays(rng)
        members = rng.permutation(80)[:30]
        relative, placed = rng.normal(0, 5, (30, 3)), rng.normal(0, 5, (30, 3))
        own = 0.0 if trial % 3 == 0 else float(rng.uniform(0.1, 3.0))
        source, target, weights = _kernels.group_anchors(
            s["pos_sum"], s["pos_weight"], s["pos_sq"], s["dynamic"], s["verified"], members, relative, placed, own,
            bool(trial % 4), 0.04, 0.5,
        )  # fmt: skip
        other = s["pos_weight"][members] - own
        anchors = ~s["dynamic"][members] & (other > 1e-9)
        own_part = own * placed[anchors] if own > 0 else 0.0
        expected_target = (s["pos_sum"][members[anchors]] - own_part) / other[anchors, None]
        spread = _kernels.gather_spread(s["pos_sum"], s["pos_weight"], s["pos_sq"], members[anchors])
        expected_weights = other[anchors] / (spread**2 + 0.04)
        expected_weights *= np.where(s["verified"][members[anchors]] >= 0, 1.0, 0.5)
        if not trial % 4:
            expected_weights = np.ones(int(anchors.sum()))
        assert source.tobytes() == relative[anchors].tobytes() and target.tobytes() == expected_target.tobytes()
        assert weights.tobytes() == expected_weights.tobytes()
        ids = np.flatnonzero(s["pos_weight"] > 0)
        positions, weights = _kernels.pose_anchors(
            s["pos_sum"], s["pos_weight"], s["pos_sq"], s["verified"], ids, 0.04, 0.5
        )
        expected = 1.0 / (_kernels.gather_spread(s["pos_sum"], s["pos_weight"], s["pos_sq"], ids) ** 2 + 0.04)
        expected *= np.where(s["verified"][ids] >= 0, 1.0, 0.5)
        assert positions.tobytes() == _kernels.gather_positions(s["pos_sum"], s["pos_weight"], ids).tobytes()
        assert weights.tobytes() == expected.tobytes()


def test_robust_fit_kernel_equals_its_steps() -> None:
    rng = np.random.default_rng(24)
    for trial in range(200):
        n = int(rng.integers(2, 40))
        source = rng.normal(0, 5, (n, 3))
        T = random_pose(rng, 5.0)
        target = apply_transform(T, source) + rng.normal(0, 0.05, (n, 3))
        target[rng.random(n) < 0.2] += rng.normal(0, 5, 3)  # a moving group
        if trial % 10 == 0:
            source[:, 1:] = 0.0  # collinear
        weights = rng.uniform(0.5, 2.0, n)
        consensus = float(rng.choice([0.0, 1.0]))
        T_kernel, inliers, outcome = _kernels.robust_fit(source, target, weights, 3.0, 0.3, 0.05, 2, consensus, 0.05)
        if n < 3:
            assert outcome == _kernels.FIT_DEGENERATE
            continue
        T_fit, spread = _kernels.rigid_fit(source, target, weights, np.ones(n, bool))
        if spread <= 0.05:
            assert outcome == _kernels.FIT_DEGENERATE
            continue
        residual = _kernels.pair_residuals(source, target, T_fit)
        if consensus > 0 and n > 4 and np.count_nonzero(residual > consensus) >= max(2, 0.05 * n):
            assert outcome == _kernels.FIT_WANTS_CONSENSUS and T_kernel.tobytes() == T_fit.tobytes()
            continue
        expected = (T_fit, np.ones(n, bool))
        if n > 4:
            expected = _kernels.trimmed_fit(source, target, weights, T_fit, np.ones(n, bool), 3.0, 0.3, 2, 0.05)
        assert outcome == _kernels.FIT_DONE
        assert T_kernel.tobytes() == expected[0].tobytes() and np.array_equal(inliers, expected[1])


def test_index_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(25)
    cell, limit, scale = 2.5, (1 << 20) - 1, 1 << 21
    for _ in range(50):
        s = random_store_arrays(rng)
        positions = rng.normal(0, 30, (40, 3))
        positions[0] = 1e9  # clipped to the border cell
        c = np.clip(np.floor(positions / cell), -limit, limit).astype(np.int64)
        expected_keys = (c[:, 0] * scale + c[:, 1]) * scale + c[:, 2]
        assert np.array_equal(_kernels.cell_keys(positions, cell, limit, scale), expected_keys)
        changed = rng.integers(0, 80, 60)
        assert np.array_equal(_kernels.distinct_ascending(changed), np.unique(changed))
        key = rng.integers(-5, 5, 80)
        indexed = rng.random(80) < 0.5
        ids = np.unique(changed)
        live = ids[s["alive"][ids]]
        keep = (s["pos_weight"][live] > 0) & ~s["dynamic"][live]
        stay, drop = live[keep], live[~keep]
        stay_positions = _kernels.gather_positions(s["pos_sum"], s["pos_weight"], stay)
        keys = _kernels.cell_keys(stay_positions, cell, limit, scale)
        key[stay[::3]] = keys[::3]  # some stay in their cell
        moved = ~indexed[stay] | (keys != key[stay])
        expected = (stay[moved & indexed[stay]], stay[moved], keys[moved], drop[indexed[drop]])
        found = _kernels.index_refresh(
            changed, s["alive"], s["pos_sum"], s["pos_weight"], s["dynamic"], cell, limit, scale, key, indexed
        )
        assert all(np.array_equal(a, b) for a, b in zip(found, expected, strict=True))
        moving, moving_keys, relocated = _kernels.cell_changes(stay_positions, cell, limit, scale, stay, key, indexed)
        assert np.array_equal(moving, stay[moved]) and np.array_equal(moving_keys, keys[moved])
        assert np.array_equal(relocated, stay[moved & indexed[stay]])
        mapped, mapped_keys = _kernels.mapped_static_cells(
            changed, s["alive"], s["pos_sum"], s["pos_weight"], s["dynamic"], cell, limit, scale
        )
        assert np.array_equal(mapped, stay) and np.array_equal(mapped_keys, keys)


def test_global_matching_kernel_equals_numpy() -> None:
    rng = np.random.default_rng(27)
    for trial in range(100):
        s = random_store_arrays(rng, 60)
        if trial % 2:  # all mapped but some: unmapped candidates only in some trials
            s["pos_weight"][s["pos_weight"] <= 0] = 1.0
        s["pos_sum"][1::7], s["pos_weight"][1::7] = s["pos_sum"][0], s["pos_weight"][0]  # ties
        last_iter = rng.integers(0, 20, 60)
        recent = int(rng.integers(0, 21))
        counts = rng.integers(0, 12, 6)
        candidates = rng.integers(0, 60, int(counts.sum()))
        world = rng.normal(0, 10, (6, 3))
        found_d2, found_id = _kernels.nearest_older_candidates(
            candidates, counts, last_iter, recent, s["pos_sum"], s["pos_weight"], world
        )
        starts = np.concatenate([[0], np.cumsum(counts)])
        for q in range(6):
            c = candidates[starts[q] : starts[q + 1]]
            c = c[last_iter[c] < recent]
            if len(c) == 0:
                assert found_id[q] == -1 and found_d2[q] == np.inf
                continue
            d2 = np.sum((_kernels.gather_positions(s["pos_sum"], s["pos_weight"], c) - world[q]) ** 2, axis=1)
            best = np.argmin(d2)
            assert found_id[q] == c[best]
            assert np.array_equal(found_d2[q], d2[best], equal_nan=True)


def test_bookkeeping_mask_and_least_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(28)
    for _ in range(50):
        s = random_store_arrays(rng, 60)
        ids = np.where(rng.random(40) < 0.2, -1, rng.integers(0, 60, 40))
        known = ids != -1
        safe = np.where(known, ids, 0)
        expected = known & (s["pos_weight"][safe] > 0) & ~s["dynamic"][safe]
        assert np.array_equal(_kernels.mapped_static_mask(ids, s["pos_weight"], s["dynamic"]), expected)
        values = rng.integers(-3, 6, 60)
        members = rng.integers(0, 60, int(rng.integers(1, 20)))
        assert _kernels.least_at(values, members) == values[members].min()
    with pytest.raises(ValueError, match="no ids"):
        _kernels.least_at(np.zeros(3, np.int64), np.zeros(0, np.int64))


def test_group_member_and_support_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(29)
    for trial in range(50):
        s = random_store_arrays(rng, 60)
        members = rng.permutation(60)[: int(rng.integers(0, 30))]
        assert np.array_equal(
            _kernels.unmapped_members(s["pos_weight"], members), members[~(s["pos_weight"][members] > 0)]
        )
        counts = rng.integers(0, 8, 60)
        assert np.array_equal(_kernels.members_above(counts, members, 4), members[counts[members] > 4])
        n, keep = int(rng.integers(0, 120)), int(rng.integers(3, 40))
        mapped = rng.random(n) < (0.2 if trial % 2 else 0.9)
        ids = rng.integers(0, 60, n)
        points = rng.normal(0, 30, (n, 3))
        use = mapped.nonzero()[0]
        if len(use) > keep:
            use = use[np.arange(keep) * (len(use) - 1) // (keep - 1)]
        rows, uids, kept = _kernels.support_observations(mapped, keep, ids, s["uid"], points)
        assert np.array_equal(rows, use) and np.array_equal(uids, s["uid"][ids[use]])
        assert kept.dtype == np.float32 and np.array_equal(kept, points[use].astype(np.float32))


def test_merge_check_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(26)
    for _ in range(100):
        s = random_store_arrays(rng, 60)
        world_sum, n_obs = rng.normal(0, 3, (60, 3)) * 4, rng.integers(0, 5, 60)
        ids = rng.permutation(60)[:10]
        bound2 = float(rng.uniform(0.5, 30.0))
        mapped = ids[s["alive"][ids] & (s["pos_weight"][ids] > 0) & ~s["dynamic"][ids]]
        flagged = np.flatnonzero(s["alive"] & s["dynamic"])
        at = world_sum[flagged] / np.maximum(n_obs[flagged], 1)[:, None]
        d2 = np.sum(
            (_kernels.gather_positions(s["pos_sum"], s["pos_weight"], mapped)[:, None, :] - at[None]) ** 2, axis=2
        )
        expected = bool(np.any((d2 <= bound2) & (s["uid"][flagged][None, :] < s["uid"][mapped][:, None])))
        found = _kernels.flagged_within(
            world_sum, n_obs, s["alive"], s["dynamic"], s["uid"], 60, s["pos_sum"], s["pos_weight"], ids, bound2
        )
        assert found == expected
        points = np.flatnonzero(s["pos_weight"] > 0)[:8]
        lists = [rng.permutation(60)[: int(rng.integers(0, 6))] for _ in points]
        offsets = np.concatenate([[0], np.cumsum([len(c) for c in lists])]).astype(np.int64)
        near = []
        for p, c in zip(points, lists, strict=True):
            d2 = np.sum(
                (_kernels.gather_positions(s["pos_sum"], s["pos_weight"], c) - s["pos_sum"][p] / s["pos_weight"][p])
                ** 2,
                axis=1,
            )
            near.append(np.any((c != p) & (s["uid"][c] < s["uid"][p]) & ((d2 <= bound2) | (s["pos_weight"][c] <= 0))))
        candidates = np.concatenate(lists).astype(np.int64)
        assert _kernels.older_within(
            s["pos_sum"], s["pos_weight"], s["uid"], points, candidates, offsets, bound2
        ) == any(near)


def test_group_creation_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(27)
    for trial in range(100):
        s = random_store_arrays(rng, 50)
        obs_iter = np.where(rng.random((50, 16)) < 0.8, np.arange(16)[None, :], -1)
        candidates = np.unique(rng.integers(0, 50, 30))
        creation = int(candidates[int(rng.integers(0, len(candidates)))])
        everyone = bool(trial % 5 == 0)
        members, interval, outcome = _kernels.group_selection(
            obs_iter, s["alive"], s["dynamic"], s["pos_weight"], candidates, creation, 2, 13, 3, everyone
        )
        usable = candidates[s["alive"][candidates] & ~s["dynamic"][candidates]]
        if creation not in usable:
            assert outcome == _kernels.SELECTION_NO_CREATION
            continue
        presence = _kernels.ring_presence(obs_iter, usable, 2, 13)
        grouped = np.ones(len(usable), bool) if everyone else s["pos_weight"][usable] > 0
        selection = select_members(presence, grouped, int(np.flatnonzero(usable == creation)[0]), 3)
        if selection is None:
            assert outcome == _kernels.SELECTION_NONE
            continue
        assert outcome == _kernels.SELECTION_MADE
        assert np.array_equal(members, usable[selection[0]]) and np.array_equal(interval, selection[1])
    for _ in range(100):
        m = int(rng.integers(3, 20))
        points = rng.normal(0, 3, (m, 3))
        members = rng.permutation(50)[:m]
        verified = np.where(rng.random(50) < 0.4, 1, -1)
        trusted = np.flatnonzero(verified[members] >= 0)
        expected = None
        if len(trusted) >= 3 and (basis := choose_basis(points[trusted], 1.0)) is not None:
            expected = tuple(int(trusted[b]) for b in basis)
        expected = expected or choose_basis(points, 1.0) or (-1, -1, -1)
        assert tuple(_kernels.basis_preferring_verified(points, members, verified, 1.0)) == expected
    for length in (1, 5, 40):
        observations = rng.normal(0, 5, (12, length, 3))
        observations[:, 0] = observations[0, 0]  # a degenerate first iteration
        total, count, first = _kernels.relative_map_sum(observations, 3, 7, 1, 0.5)
        relative, valid = _kernels.basis_coordinates(observations, 3, 7, 1, 0.5)
        assert total.tobytes() == relative[:, valid].sum(axis=1).tobytes()
        assert count == valid.sum() and first == (np.flatnonzero(valid)[0] if valid.any() else -1)


def test_bookkeeping_kernels_equal_numpy() -> None:
    rng = np.random.default_rng(28)
    c, ring = 40, 8
    for iteration in range(12):
        obs, obs_iter = rng.normal(size=(c, ring, 3)), rng.integers(-1, iteration + 1, (c, ring))
        first_iter = np.where(rng.random(c) < 0.3, -1, rng.integers(0, iteration + 1, c))
        last_iter = np.where(first_iter < 0, -1, np.maximum(first_iter, rng.integers(0, iteration + 1, c)))
        run_start, n_obs = np.minimum(last_iter, rng.integers(0, iteration + 1, c)), rng.integers(0, 9, c)
        ids, points = rng.permutation(c)[:15], rng.normal(size=(15, 3))
        expected = [a.copy() for a in (obs, obs_iter, first_iter, last_iter, run_start, n_obs)]
        e_obs, e_iter, e_first, e_last, e_run, e_n = expected
        slot = iteration % ring
        e_obs[ids, slot], e_iter[ids, slot] = points, iteration
        first = e_first[ids] < 0
        e_first[ids[first]] = iteration
        e_run[ids[first | (e_last[ids] != iteration - 1)]] = iteration
        e_last[ids] = iteration
        e_n[ids] += 1
        _kernels.record_observations(obs, obs_iter, first_iter, last_iter, run_start, n_obs, ids, points, iteration)
        assert all(
            np.array_equal(a, b)
            for a, b in zip((obs, obs_iter, first_iter, last_iter, run_start, n_obs), expected, strict=True)
        )
        s = random_store_arrays(rng, c)
        listed = rng.permutation(c)[:25]
        done = ~s["alive"][listed] | (s["pos_weight"][listed] > 0) | s["dynamic"][listed]
        stale = s["alive"][listed] & ~done & (iteration - last_iter[listed] > 3)
        due = ~done & ~stale & (last_iter[listed] == iteration) & (iteration - run_start[listed] >= 2)
        found = _kernels.creation_triage(
            listed, s["alive"], s["pos_weight"], s["dynamic"], last_iter, run_start, iteration, 3, 2
        )
        assert all(
            np.array_equal(a, b) for a, b in zip(found, (listed[stale], listed[done | stale], listed[due]), strict=True)
        )
        previous, current = np.unique(rng.integers(0, c, 12)), np.unique(rng.integers(0, c, 12))
        n_later, attempt = rng.integers(0, 2, c), rng.integers(-1, iteration + 1, c)
        live = previous[s["alive"][previous]]
        left = live[(last_iter[live] == iteration - 1) & (iteration - run_start[live] >= 2)]
        due = np.concatenate([left, current[iteration - run_start[current] + 1 >= 3]])
        due = due[
            (n_later[due] == 0) & (s["pos_weight"][due] > 0) & ~s["dynamic"][due] & (iteration - attempt[due] >= 3)
        ]
        found = _kernels.regroup_due(
            previous, current, s["alive"], last_iter, run_start, n_later, s["pos_weight"], s["dynamic"], attempt,
            iteration, 2, 3,
        )  # fmt: skip
        assert np.array_equal(found, due)
        window = [np.unique(rng.integers(0, c, 10)) for _ in range(3)]
        first_t = iteration - 3
        refs = np.concatenate([seen[last_iter[seen] == first_t + t] for t, seen in enumerate(window)])
        offsets = np.concatenate([[0], np.cumsum([len(w) for w in window])]).astype(np.int64)
        found = _kernels.recent_references(np.concatenate(window), offsets, first_t, last_iter, obs)
        expected = (refs, obs[refs, last_iter[refs] % ring], iteration - last_iter[refs])
        assert all(np.array_equal(a, b) for a, b in zip(found, expected, strict=True))


def test_group_list_kernels_equal_list_operations() -> None:
    rng = np.random.default_rng(29)
    table, count = np.zeros((30, 4), np.int64), np.zeros(30, np.int64)
    lists: dict[int, list[int]] = {}
    for gid in range(60):
        members = rng.permutation(30)[: int(rng.integers(1, 10))]
        if rng.random() < 0.3 and lists:
            victim = int(rng.choice(list({g for listed in lists.values() for g in listed} or {gid})))
            holders = np.array([p for p, listed in lists.items() if victim in listed], np.int64)
            _kernels.drop_group(table, count, holders, victim)
            for p in holders.tolist():
                lists[p].remove(victim)
            continue
        while not _kernels.append_group(table, count, members, gid):
            table = np.concatenate([table, np.zeros_like(table)], axis=1)
        for p in members.tolist():
            lists.setdefault(p, []).append(gid)
        for p in range(30):
            assert table[p, : count[p]].tolist() == lists.get(p, [])


def test_group_relative_map_kernel_equals_its_steps() -> None:
    rng = np.random.default_rng(30)
    store = PointStore(ring_size=8, capacity=40)
    ids = store.new_points(30)
    for t in range(10):
        store.add_observations(ids, rng.normal(0, 5, (30, 3)), t)
    verified = np.where(rng.random(store.capacity) < 0.5, 1, -1)
    for _ in range(30):
        members = rng.permutation(ids)[: int(rng.integers(4, 20))]
        iterations = np.sort(rng.permutation(np.arange(3, 10))[: int(rng.integers(1, 7))])
        observations, _ = store.observations(members, iterations)
        basis = _kernels.basis_preferring_verified(np.ascontiguousarray(observations[:, 0]), members, verified, 0.5)
        found = _kernels.group_relative_map(store.obs, store.obs_iter, members, iterations, verified, 0.5)
        assert tuple(found[:3]) == tuple(basis)
        total, count, first = _kernels.relative_map_sum(observations, *basis, 0.5)
        assert found[3].tobytes() == total.tobytes() and (found[4], found[5]) == (count, first)


def test_open_group_kernel_equals_numpy() -> None:
    rng = np.random.default_rng(31)
    store = PointStore(ring_size=8, capacity=40)
    ids = store.new_points(30)
    for t in range(6):
        seen = ids[rng.random(30) < 0.9] if t == 5 else ids
        store.add_observations(seen, rng.normal(0, 5, (len(seen), 3)), t)
    store.dynamic[ids[rng.random(30) < 0.1]] = True
    outcomes = set()
    for _ in range(40):
        members = rng.permutation(ids)[: int(rng.integers(4, 15))]
        basis = tuple(int(b) for b in rng.permutation(len(members))[:3])
        rel_sum = rng.normal(size=(len(members), 3))
        expected = rel_sum.copy()
        if np.any(store.last_iter[members] != 5) or np.any(store.dynamic[members[list(basis)]]):
            outcome = _kernels.OPEN_GROUP_CLOSES
        else:
            relative, valid = _kernels.basis_coordinates(
                np.ascontiguousarray(store.obs[members, 5 % 8][:, None]), *basis, 0.5
            )
            outcome = _kernels.OPEN_GROUP_AVERAGED if valid[0] else _kernels.OPEN_GROUP_SKIPS
            if valid[0]:
                expected += relative[:, 0]
        assert (
            _kernels.extend_open_group(store.obs, store.last_iter, store.dynamic, members, *basis, 5, 0.5, rel_sum)
            == outcome
        )
        assert rel_sum.tobytes() == expected.tobytes()
        outcomes.add(outcome)
    assert _kernels.OPEN_GROUP_CLOSES in outcomes and _kernels.OPEN_GROUP_AVERAGED in outcomes


def test_scaled_motion_holds_the_body_velocity_over_a_longer_or_shorter_interval() -> None:
    from relpoint.estimators.relative_point.registration import scaled_motion
    from relpoint.geometry import body_twist, integrate_twist, so3_exp

    rng = np.random.default_rng(0)
    for angle in (0.0, 1e-8, 0.3, 1.5, 3.1):
        T = np.eye(4)
        T[:3, :3] = so3_exp(rng.normal(size=3) / np.sqrt(3) * angle) if angle else np.eye(3)
        T[:3, 3] = rng.normal(size=3)
        for ratio in (0.1, 0.5, 2.0, 10.0):
            linear, angular = body_twist(np.eye(4), T, 1.0)
            expected = integrate_twist(np.eye(4), linear * ratio, angular * ratio, 1.0)
            np.testing.assert_allclose(scaled_motion(T, ratio), expected, atol=1e-9)
        np.testing.assert_allclose(scaled_motion(T, 1.0), T, atol=1e-9)
