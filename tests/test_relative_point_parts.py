"""Properties of the Relative Point components: least-squares fitting, basis frames, matching, binning."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from relpoint.estimators.relative_point.charting import PointCharting
from relpoint.estimators.relative_point.dynamics import (
    detect_dynamic,
    deviation_to_references,
    gap_threshold,
    row_nanmedian,
    world_block_deviation,
)
from relpoint.estimators.relative_point.estimator import quaternion_xyzw
from relpoint.estimators.relative_point.grouping import select_members
from relpoint.estimators.relative_point.groups import basis_rotation, choose_basis, relative_coordinates
from relpoint.estimators.relative_point.loops import drift_share, vote_offset
from relpoint.estimators.relative_point.lsf import apply, fit_transform, is_collinear
from relpoint.estimators.relative_point.points import PointStore
from relpoint.estimators.relative_point.registration import (
    NO_MATCH,
    GlobalIndex,
    MotionModel,
    match_mutual,
    match_nearest,
)
from relpoint.estimators.relative_point.tally import IdTally
from relpoint.geometry import fit_rigid

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
    target = apply(T, source) + rng.normal(0.0, noise, (n, 3))
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
    target = apply(random_pose(rng), source @ mirror)
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
    fit = fit_transform(source, apply(T, source) + rng.normal(0, noise, (25, 3)), trim=0.0)
    assert fit is not None
    assert np.linalg.det(fit.T[:3, :3]) == pytest.approx(1.0, abs=1e-9)
    assert np.allclose(fit.T[:3, :3], T[:3, :3], atol=1e-9 + 0.02 * (noise > 0))


def test_fit_trims_gross_outliers_and_weights_pull() -> None:
    rng = np.random.default_rng(0)
    T = random_pose(rng)
    source = rng.uniform(-30, 30, (40, 3))
    target = apply(T, source) + rng.normal(0, 0.1, (40, 3))
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
    moved = np.stack([points, apply(random_pose(rng, 100.0), points), apply(random_pose(rng, 100.0), points)], axis=1)
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
        tracks[:, t] = apply(random_pose(rng, 10.0), world) + rng.normal(0, noise, (m, 3))
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
    target = apply(T, source) + rng.normal(0, 0.2, (14, 3))
    target[:5] += rng.normal(0, 3.0, (5, 3))
    trimmed = fit_transform(source, target, trim=3.0, floor=0.5)
    robust = fit_transform(source, target, trim=3.0, floor=0.5, consensus=1.0)
    assert trimmed is not None and robust is not None
    assert trimmed.inliers[:5].any()
    assert not robust.inliers[:5].any() and robust.inliers[5:].all()
    assert np.linalg.norm(robust.T[:3, 3] - T[:3, 3]) < 0.3 < np.linalg.norm(trimmed.T[:3, 3] - T[:3, 3])
    # Without outliers beyond the bound the consensus changes nothing.
    clean = apply(T, source) + rng.normal(0, 0.2, (14, 3))
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
        tracks[:, t] = apply(random_pose(rng, 10.0), world) + rng.normal(0, 0.3, (m, 3))
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
