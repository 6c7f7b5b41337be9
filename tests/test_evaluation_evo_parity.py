"""relpoint.evaluation against evo 1.38: the REFERENCE.md figures, evo as an oracle, and synthetic truths."""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from formats.trajectory_files import read_tum
from relpoint.errors import EstimatorError, InputError, RelpointError, UsageError
from relpoint.evaluation import (
    AlignMode,
    EvaluationError,
    EvaluationSettings,
    PoseRelation,
    ape_errors,
    associate,
    dense_metrics,
    dense_metrics_to_mesh,
    dynamic_point_precision_recall,
    estimate_alignment,
    evaluate_trajectory,
    landmark_metrics,
    matching_time_indices,
    precision_recall,
    rpe_errors,
    umeyama,
)
from relpoint.evaluation.alignment import apply_alignment
from relpoint.evaluation.association import slerp_quaternions, stamps_to_seconds
from relpoint.evaluation.kitti import kitti_segment_errors_from_poses
from relpoint.types import GroundTruthLandmarks, LandmarkMap, Trajectory

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "evo-fr1xyz"
GT = "freiburg1_xyz-groundtruth.txt"
RGBD = "freiburg1_xyz-rgbdslam.txt"
DRIFT = "freiburg1_xyz-rgbdslam_drift.txt"
ORB = "freiburg1_xyz-ORB_kf_mono.txt"

evo_sync = pytest.importorskip("evo.core.sync")
from evo.core import metrics as evo_metrics  # noqa: E402
from evo.core.sync_method import SyncMethod  # noqa: E402
from evo.core.units import Unit  # noqa: E402
from evo.main_ape import ape as evo_ape  # noqa: E402
from evo.main_rpe import rpe as evo_rpe  # noqa: E402
from evo.tools import file_interface  # noqa: E402

logging.getLogger("evo").setLevel(logging.ERROR)

EVO_RELATION = {
    "full": evo_metrics.PoseRelation.full_transformation,
    "trans_part": evo_metrics.PoseRelation.translation_part,
    "rot_part": evo_metrics.PoseRelation.rotation_part,
    "angle_deg": evo_metrics.PoseRelation.rotation_angle_deg,
    "angle_rad": evo_metrics.PoseRelation.rotation_angle_rad,
    "point_distance": evo_metrics.PoseRelation.point_distance,
    "point_distance_error_ratio": evo_metrics.PoseRelation.point_distance_error_ratio,
}
EVO_UNIT = {"f": Unit.frames, "m": Unit.meters, "d": Unit.degrees, "r": Unit.radians}
EVO_ALIGN = {"none": (False, False), "se3": (True, False), "sim3": (True, True), "scale": (False, True)}


def _need_data() -> None:
    if not DATA.is_dir():
        pytest.skip("../shared/data/evo-fr1xyz is absent")


_ours_cache: dict[str, Trajectory] = {}
_evo_cache: dict[str, object] = {}


def ours(name: str) -> Trajectory:
    _need_data()
    if name not in _ours_cache:
        _ours_cache[name] = read_tum(DATA / name)
    return _ours_cache[name]


def evo_traj(name: str):
    _need_data()
    if name not in _evo_cache:
        _evo_cache[name] = file_interface.read_tum_trajectory_file(str(DATA / name))
    return copy.deepcopy(_evo_cache[name])


def evo_synced(ref: str, est: str, max_diff: float = 0.01, offset: float = 0.0, interpolate: bool = False):
    method = SyncMethod.interpolation if interpolate else SyncMethod.nearest_time
    return evo_sync.associate_trajectories(
        evo_traj(ref), evo_traj(est), max_diff=max_diff, offset_2=offset, sync_method=method
    )


# --- REFERENCE.md: every figure, to 1e-6, with relpoint's own code -------------------------------------


@pytest.mark.parametrize(
    ("est", "align", "expected"),
    [
        (RGBD, "se3", {"rmse": 0.013470, "mean": 0.012024, "median": 0.011183, "max": 0.034760, "std": 0.006071}),
        (RGBD, "none", {"rmse": 0.020079, "mean": 0.018063, "max": 0.043289}),
        (ORB, "sim3", {"rmse": 0.009755, "mean": 0.008219, "max": 0.027924}),
    ],
)
def test_reference_md_ape_figures(est: str, align: str, expected: dict[str, float]) -> None:
    summary = evaluate_trajectory(ours(GT), ours(est), EvaluationSettings(align=align)).summary
    for stat, value in expected.items():
        assert summary[f"ate_{stat}"] == pytest.approx(value, abs=1e-6), stat


def test_reference_md_rpe_figures() -> None:
    summary = evaluate_trajectory(ours(GT), ours(RGBD), EvaluationSettings(delta=1, delta_unit="f")).summary
    assert summary["rpe_trans_rmse"] == pytest.approx(0.005764, abs=1e-6)
    assert summary["rpe_trans_mean"] == pytest.approx(0.004816, abs=1e-6)
    assert summary["rpe_trans_max"] == pytest.approx(0.020866, abs=1e-6)
    assert summary["rpe_rot_deg_rmse"] == pytest.approx(0.353613, abs=1e-6)
    assert summary["rpe_rot_deg_mean"] == pytest.approx(0.300307, abs=1e-6)
    angle = evaluate_trajectory(ours(GT), ours(RGBD), EvaluationSettings(pose_relation="angle_deg")).summary
    assert angle["rpe_rmse"] == pytest.approx(0.353613, abs=1e-6)


# --- evo as an oracle over the option space -------------------------------------------------------------


@pytest.mark.parametrize(("max_diff", "offset"), [(0.01, 0.0), (0.02, 0.0), (0.005, 0.003), (0.01, -0.02), (0.1, 1.5)])
@pytest.mark.parametrize("pair", [(GT, RGBD), (RGBD, GT), (GT, ORB), (RGBD, DRIFT)])
def test_association_indices_equal_evo(pair: tuple[str, str], max_diff: float, offset: float) -> None:
    ref, est = pair
    try:
        evo_ref, evo_est = evo_synced(ref, est, max_diff, offset)
    except evo_sync.SyncException:
        with pytest.raises(EvaluationError):
            associate(ours(ref), ours(est), max_diff=max_diff, offset=offset)
        return
    matched = associate(ours(ref), ours(est), max_diff=max_diff, offset=offset)
    np.testing.assert_array_equal(stamps_to_seconds(matched.reference_stamps_ns), evo_ref.timestamps)
    np.testing.assert_array_equal(stamps_to_seconds(matched.estimate_stamps_ns), evo_est.timestamps)
    np.testing.assert_allclose(matched.estimate_positions, evo_est.positions_xyz, rtol=0, atol=1e-15)


def test_matching_ties_go_to_the_earlier_stamp_like_evo() -> None:
    stamps_2 = np.array([0.0, 1.0, 2.0, 3.0])
    stamps_1 = np.array([0.5, 1.5, 2.9, 3.2, 10.0])
    ours_1, ours_2 = matching_time_indices(stamps_1, stamps_2, max_diff=0.5)
    evo_1, evo_2 = evo_sync.matching_time_indices(stamps_1, stamps_2, max_diff=0.5)
    assert ours_1.tolist() == evo_1 == [0, 1, 2, 3]
    assert ours_2.tolist() == evo_2 == [0, 1, 3, 3]


@pytest.mark.parametrize("offset", [0.0, 0.004])
@pytest.mark.parametrize("pair", [(GT, RGBD), (ORB, GT)])
def test_interpolation_equals_evo_sync_method_interpolation(pair: tuple[str, str], offset: float) -> None:
    ref, est = pair
    evo_ref, evo_est = evo_synced(ref, est, 0.02, offset, interpolate=True)
    matched = associate(ours(ref), ours(est), max_diff=0.02, offset=offset, interpolate=True)
    assert matched.interpolated
    np.testing.assert_allclose(matched.reference_positions, evo_ref.positions_xyz, rtol=0, atol=1e-12)
    np.testing.assert_allclose(matched.estimate_positions, evo_est.positions_xyz, rtol=0, atol=1e-12)
    evo_R_ref = np.array([p[:3, :3] for p in evo_ref.poses_se3])
    evo_R_est = np.array([p[:3, :3] for p in evo_est.poses_se3])
    np.testing.assert_allclose(matched.reference_rotations, evo_R_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(matched.estimate_rotations, evo_R_est, rtol=0, atol=1e-12)


@pytest.mark.parametrize("relation", ["trans_part", "full", "rot_part", "angle_deg", "angle_rad", "point_distance"])
@pytest.mark.parametrize("align", ["none", "se3", "sim3", "scale"])
def test_ape_equals_evo(align: str, relation: str) -> None:
    for est, n_to_align in ((RGBD, -1), (DRIFT, 100), (ORB, -1)):
        settings = EvaluationSettings(align=align, n_to_align=n_to_align, pose_relation=relation, rpe=False)
        result = evaluate_trajectory(ours(GT), ours(est), settings)
        evo_ref, evo_est = evo_synced(GT, est)
        do_align, scale = EVO_ALIGN[align]
        expected = evo_ape(
            evo_ref, evo_est, EVO_RELATION[relation], align=do_align, correct_scale=scale, n_to_align=n_to_align
        )
        np.testing.assert_allclose(result.ape, expected.np_arrays["error_array"], rtol=1e-9, atol=1e-12)
        for stat, value in expected.stats.items():
            assert result.summary[f"ape_{stat}"] == pytest.approx(value, rel=1e-9, abs=1e-12), (est, stat)


def test_origin_alignment_equals_evo() -> None:
    result = evaluate_trajectory(ours(GT), ours(DRIFT), EvaluationSettings(align="origin", pose_relation="full"))
    evo_ref, evo_est = evo_synced(GT, DRIFT)
    expected = evo_ape(evo_ref, evo_est, EVO_RELATION["full"], align_origin=True)
    np.testing.assert_allclose(result.ape, expected.np_arrays["error_array"], rtol=1e-9, atol=1e-12)


RPE_CASES = [
    (1, "f", False, False),
    (5, "f", True, False),
    (7, "f", False, True),
    (0.1, "m", False, False),
    (0.1, "m", True, False),
    (0.25, "m", True, True),
    (5.0, "d", False, False),
    (0.05, "r", False, True),
]


@pytest.mark.parametrize(("delta", "unit", "all_pairs", "from_ref"), RPE_CASES)
@pytest.mark.parametrize(
    "relation",
    ["trans_part", "angle_deg", "angle_rad", "full", "rot_part", "point_distance", "point_distance_error_ratio"],
)
def test_rpe_equals_evo(delta: float, unit: str, all_pairs: bool, from_ref: bool, relation: str) -> None:
    align = "sim3" if unit == "m" else "none"
    matched = apply_alignment(m := associate(ours(GT), ours(RGBD)), estimate_alignment(m, align))
    got = rpe_errors(
        matched, relation, delta=delta, delta_unit=unit, all_pairs=all_pairs, pairs_from_reference=from_ref
    )
    evo_ref, evo_est = evo_synced(GT, RGBD)
    expected = evo_rpe(
        evo_ref,
        evo_est,
        EVO_RELATION[relation],
        delta=delta,
        delta_unit=EVO_UNIT[unit],
        all_pairs=all_pairs,
        pairs_from_reference=from_ref,
        align=align == "sim3",
        correct_scale=align == "sim3",
    )
    assert len(got.errors) == len(expected.np_arrays["error_array"])
    np.testing.assert_allclose(got.errors, expected.np_arrays["error_array"], rtol=1e-8, atol=1e-10)


def test_rpe_all_pairs_by_angle_equals_evo() -> None:
    relation = "trans_part"
    got = rpe_errors(associate(ours(GT), ours(RGBD)), relation, delta=3.0, delta_unit="d", all_pairs=True)
    evo_ref, evo_est = evo_synced(GT, RGBD)
    expected = evo_rpe(evo_ref, evo_est, EVO_RELATION[relation], delta=3.0, delta_unit=Unit.degrees, all_pairs=True)
    assert len(got.errors) == len(expected.np_arrays["error_array"]) > 1000
    np.testing.assert_allclose(got.errors, expected.np_arrays["error_array"], rtol=1e-8, atol=1e-10)


def test_rpe_pairs_equal_evo_on_drift_trajectory_all_pairs_metres() -> None:
    from evo.core.filters import filter_pairs_by_path

    matched = associate(ours(GT), ours(DRIFT))
    got = rpe_errors(matched, "trans_part", delta=0.05, delta_unit="m", all_pairs=True, rel_tol=0.02)
    _, evo_est = evo_synced(GT, DRIFT)
    pairs = filter_pairs_by_path(evo_est.poses_se3, 0.05, 0.05 * 0.02, all_pairs=True)
    assert list(zip(got.first.tolist(), got.second.tolist(), strict=True)) == pairs


# --- properties with known answers ----------------------------------------------------------------------


def _random_trajectory(rng: np.random.Generator, n: int = 200, dt_ns: int = 50_000_000) -> Trajectory:
    t = np.arange(n)
    positions = np.column_stack([np.sin(t * 0.05) * 3, np.cos(t * 0.031) * 2, 0.3 * np.sin(t * 0.07)])
    positions += rng.normal(scale=0.01, size=positions.shape)
    quats = Rotation.from_rotvec(np.column_stack([0.1 * np.sin(t * 0.02), 0.05 * t / n, t * 0.01])).as_quat()
    return Trajectory(1_000_000_000 + t * dt_ns, positions, quats)


def _transformed(traj: Trajectory, rotation: Rotation, translation: np.ndarray, scale: float) -> Trajectory:
    positions = scale * rotation.apply(np.array(traj.positions)) + translation
    quats = (rotation * Rotation.from_quat(traj.quats_xyzw)).as_quat()
    return Trajectory(traj.stamps_ns, positions, quats)


def test_sim3_alignment_recovers_known_similarity() -> None:
    rng = np.random.default_rng(0)
    reference = _random_trajectory(rng)
    rotation = Rotation.from_rotvec([0.3, -1.1, 0.7])
    translation = np.array([4.0, -2.0, 0.5])
    scale = 0.37
    # estimate = inverse similarity of the reference: aligning it back must recover (R, t, s).
    inv_rot = rotation.inv()
    estimate = _transformed(reference, inv_rot, -inv_rot.apply(translation) / scale, 1.0 / scale)
    matched = associate(reference, estimate)
    alignment = estimate_alignment(matched, "sim3")
    np.testing.assert_allclose(alignment.rotation, rotation.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(alignment.translation, translation, atol=1e-10)
    assert alignment.scale == pytest.approx(scale, rel=1e-10)
    result = evaluate_trajectory(reference, estimate, EvaluationSettings(align="sim3"))
    assert result.summary["ate_max"] < 1e-10
    assert result.summary["ape_rot_deg_max"] < 1e-6
    se3 = evaluate_trajectory(reference, estimate, EvaluationSettings(align="se3"))
    assert se3.summary["ate_rmse"] > 0.1  # the scale is not corrected


def test_se3_alignment_on_first_n_poses_only() -> None:
    rng = np.random.default_rng(1)
    reference = _random_trajectory(rng)
    rotation = Rotation.from_rotvec([0.0, 0.0, 0.8])
    moved = _transformed(reference, rotation, np.array([1.0, 2.0, 3.0]), 1.0)
    # Corrupt the second half: an alignment on the first 100 poses must be unaffected by it.
    positions = moved.positions.copy()
    positions[100:] += 5.0
    estimate = Trajectory(moved.stamps_ns, positions, moved.quats_xyzw)
    result = evaluate_trajectory(reference, estimate, EvaluationSettings(align="se3", n_to_align=100))
    assert np.max(result.ape_translation[:100]) < 1e-9
    assert np.min(result.ape_translation[100:]) > 1.0
    assert result.alignment.n_used == 100


def test_umeyama_matches_evo_geometry() -> None:
    from evo.core.geometry import umeyama_alignment

    rng = np.random.default_rng(2)
    x = rng.normal(size=(50, 3))
    y = 2.0 * x @ Rotation.from_rotvec([1.0, 0.2, -0.3]).as_matrix().T + 1.0 + rng.normal(scale=0.01, size=x.shape)
    for with_scale in (False, True):
        ours_r, ours_t, ours_s = umeyama(x, y, with_scale)
        evo_r, evo_t, evo_s = umeyama_alignment(x.T, y.T, with_scale)
        np.testing.assert_allclose(ours_r, evo_r, atol=1e-12)
        np.testing.assert_allclose(ours_t, evo_t, atol=1e-12)
        assert ours_s == pytest.approx(evo_s, rel=1e-12)


def test_interpolation_is_linear_in_position_and_slerp_in_rotation() -> None:
    # A dense reference (11 poses, 0.1 s apart) moving linearly and yawing at a constant rate; the
    # sparse estimate's stamps fall between its poses, so the reference is resampled there.
    ref_t = np.arange(11) * 100_000_000
    fractions_ref = ref_t / 1e9
    reference = Trajectory(
        ref_t,
        fractions_ref[:, None] * [2.0, 4.0, -6.0],
        Rotation.from_rotvec(np.outer(fractions_ref, [0.0, 0.0, 1.2])).as_quat(),
    )
    stamps = np.array([130_000_000, 250_000_000, 500_000_000, 960_000_000])
    estimate = Trajectory(stamps, np.zeros((4, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (4, 1)))
    matched = associate(reference, estimate, max_diff=0.05, interpolate=True)
    fractions = stamps / 1e9
    np.testing.assert_allclose(matched.reference_positions, fractions[:, None] * [2.0, 4.0, -6.0], atol=1e-12)
    yaw = Rotation.from_matrix(matched.reference_rotations).as_rotvec()[:, 2]
    np.testing.assert_allclose(yaw, 1.2 * fractions, atol=1e-12)
    np.testing.assert_array_equal(matched.reference_stamps_ns, stamps)
    # Without interpolation the nearest poses are taken instead (0.25 s is a tie: the earlier one wins).
    nearest = associate(reference, estimate, max_diff=0.05)
    np.testing.assert_array_equal(nearest.reference_index, [1, 2, 5, 10])


def test_slerp_takes_the_short_way_and_keeps_endpoints() -> None:
    q0 = Rotation.from_rotvec([0.0, 0.0, 0.2]).as_quat()
    q1 = -Rotation.from_rotvec([0.0, 0.0, 0.6]).as_quat()  # same rotation, opposite hemisphere
    out = slerp_quaternions(np.tile(q0, (3, 1)), np.tile(q1, (3, 1)), np.array([0.0, 0.5, 1.0]))
    angles = Rotation.from_quat(out).as_rotvec()[:, 2]
    np.testing.assert_allclose(angles, [0.2, 0.4, 0.6], atol=1e-12)


def test_kitti_segments_on_synthetic_trajectory() -> None:
    # A straight 1 m-per-frame reference along x; the estimate travels 1 % too far per frame and yaws
    # 0.001 rad per frame. Every 100..800 m segment then has translation error 1 % and rotation error
    # from the accumulated yaw, known in closed form.
    n = 1000
    x = np.arange(n, dtype=float)
    ref_T = np.tile(np.eye(4), (n, 1, 1))
    ref_T[:, 0, 3] = x
    est_T = np.tile(np.eye(4), (n, 1, 1))
    est_T[:, 0, 3] = 1.01 * x
    errors = kitti_segment_errors_from_poses(ref_T, ref_T)
    assert len(errors) > 0 and np.all(errors.t_err == 0) and np.all(errors.r_err == 0)
    errors = kitti_segment_errors_from_poses(ref_T, est_T)
    # segment (first, last): last is the first frame with dist > first + len, i.e. first + len + 1.
    assert np.all(errors.last - errors.first == errors.length + 1)
    np.testing.assert_allclose(errors.t_err * errors.length, 0.01 * (errors.length + 1), rtol=1e-9)
    assert errors.translation_percent == pytest.approx(np.mean(1.0 * (errors.length + 1) / errors.length), rel=1e-9)
    # segment counts: starts every 10 frames whose start + len + 1 < n
    for length, (_, _, count) in errors.by_length().items():
        assert count == len(range(0, n - int(length) - 1, 10))
    yaw = Rotation.from_rotvec(np.column_stack([np.zeros(n), np.zeros(n), 0.001 * x])).as_matrix()
    rot_T = ref_T.copy()
    rot_T[:, :3, :3] = yaw
    rot_errors = kitti_segment_errors_from_poses(ref_T, rot_T)
    np.testing.assert_allclose(
        rot_errors.r_err, 0.001 * (rot_errors.last - rot_errors.first) / rot_errors.length, rtol=1e-6
    )
    assert rot_errors.rotation_deg_per_100m == pytest.approx(np.rad2deg(np.mean(rot_errors.r_err)) * 100, rel=1e-12)


def test_kitti_via_evaluate_trajectory_and_short_paths() -> None:
    rng = np.random.default_rng(3)
    short = _random_trajectory(rng)
    summary = evaluate_trajectory(short, short).summary
    assert summary["kitti_segments"] == 0 and "kitti_t_err_pct" not in summary
    n = 1200
    stamps = np.arange(n) * 100_000_000
    positions = np.column_stack([np.arange(n) * 1.0, np.zeros(n), np.zeros(n)])
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    reference = Trajectory(stamps, positions, quats)
    estimate = Trajectory(stamps, positions * 1.02, quats)
    summary = evaluate_trajectory(reference, estimate).summary
    assert summary["kitti_segments"] > 0
    assert summary["kitti_t_err_pct"] == pytest.approx(2.0, rel=0.02)
    assert summary["kitti_r_err_deg_per_100m"] == pytest.approx(0.0, abs=1e-9)


# --- landmarks and dense maps ---------------------------------------------------------------------------


def _landmark_case() -> tuple[LandmarkMap, GroundTruthLandmarks]:
    truth = GroundTruthLandmarks(
        positions=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]], dtype=float),
        ids=np.array([10, 11, 12, 13, 14]),
        dynamic=np.array([False, False, False, False, True]),
    )
    estimated = LandmarkMap(
        positions=np.array(
            [
                [0.1, 0, 0],  # id 10, error 0.1
                [1, 0.2, 0],  # id 11, error 0.2
                [1, 0, 0.4],  # id 11 again: a duplicate, error 0.4
                [9, 9, 9],  # clutter: a false landmark
                [5, 5, 5.5],  # id 14 flagged dynamic: true positive
                [0, 1, 0],  # id 12 flagged dynamic: false positive (static truth)
            ]
        ),
        observations=np.array([10, 10, 2, 3, 5, 4]),
        dynamic=np.array([False, False, False, False, True, True]),
        gt_id=np.array([10, 11, 11, -1, 14, 12]),
    )
    return estimated, truth


def test_a_map_without_ids_gets_nearest_neighbour_figures_not_false_landmarks() -> None:
    # A log whose clouds carry no `id` field: every landmark was counted false and the mapped fraction 0.
    estimated, truth = _landmark_case()
    estimated = dataclasses.replace(estimated, gt_id=np.full(len(estimated), -1))
    s = landmark_metrics(estimated, truth).summary
    assert s["lm_matched"] == 0 and all(math.isnan(s[k]) for k in ("lm_false", "lm_mapped_fraction", "lm_err_rmse"))
    # static landmarks (the first four) to the nearest static truth: 0.1, 0.2, 0.4 and |(9, 9, 9) - (0, 0, 1)|
    nearest = np.array([0.1, 0.2, 0.4, np.linalg.norm([9.0, 9.0, 8.0])])
    assert s["lm_nn_rmse"] == pytest.approx(np.sqrt(np.mean(nearest**2)))
    assert s["lm_nn_max"] == pytest.approx(nearest.max())


def test_a_ground_truth_that_repeats_ids_is_evaluated_as_one_without_ids() -> None:
    # A log that gives a landmark's id to another once the first left view: matching by id would pair
    # landmarks with whichever true landmark comes first, and report a correct map metres off.
    estimated, truth = _landmark_case()
    repeated = GroundTruthLandmarks(truth.positions, np.where(truth.ids == 13, 10, truth.ids), truth.dynamic)
    s = landmark_metrics(estimated, repeated).summary
    assert s["lm_matched"] == 0 and all(math.isnan(s[k]) for k in ("lm_err_rmse", "lm_false", "dyn_precision"))
    assert (
        s["lm_nn_rmse"]
        == landmark_metrics(dataclasses.replace(estimated, gt_id=np.full(6, -1)), truth).summary["lm_nn_rmse"]
    )


def test_landmark_metrics_on_crafted_case() -> None:
    estimated, truth = _landmark_case()
    purity = np.array([1.0, 0.9, 0.5, 0.0, 1.0, 1.0])
    result = landmark_metrics(estimated, truth, purity=purity)
    s = result.summary
    assert result.gt_id.tolist() == [10, 11, 11]
    np.testing.assert_allclose(result.error, [0.1, 0.2, 0.4], atol=1e-12)
    assert s["lm_err_rmse"] == pytest.approx(np.sqrt((0.01 + 0.04 + 0.16) / 3))
    assert s["lm_err_mean"] == pytest.approx(0.7 / 3)
    assert s["lm_err_max"] == pytest.approx(0.4)
    assert s["lm_mapped_fraction"] == pytest.approx(2 / 4)  # ids 10, 11 of static 10..13
    assert s["lm_duplicates"] == 1
    assert s["lm_false"] == 1
    assert s["lm_purity_mean"] == pytest.approx(purity.mean())
    assert s["lm_purity_weighted"] == pytest.approx((10 + 9 + 1 + 0 + 5 + 4) / 34)
    assert s["dyn_precision"] == pytest.approx(0.5)
    assert s["dyn_recall"] == pytest.approx(1.0)
    observed = landmark_metrics(estimated, truth, observed_ids=[10, 11, 14])
    assert observed.summary["lm_mapped_fraction"] == pytest.approx(1.0)
    assert "lm_purity_mean" not in observed.summary


def test_dynamic_figures_do_not_apply_to_a_log_without_movers() -> None:
    estimated, truth = _landmark_case()
    still = GroundTruthLandmarks(truth.positions, truth.ids, np.zeros(len(truth.ids), dtype=bool))
    summary = landmark_metrics(estimated, still).summary
    assert np.isnan(summary["dyn_precision"]) and np.isnan(summary["dyn_recall"])
    assert summary["lm_err_rmse"] == landmark_metrics(estimated, truth).summary["lm_err_rmse"]


def test_landmark_error_with_trajectory_alignment() -> None:
    estimated, truth = _landmark_case()
    rotation = Rotation.from_rotvec([0.0, 0.0, np.pi / 2])
    moved = LandmarkMap(
        rotation.inv().apply(estimated.positions - [1.0, 2.0, 3.0]),
        estimated.observations,
        estimated.dynamic,
        estimated.gt_id,
    )
    from relpoint.evaluation import Alignment

    alignment = Alignment(rotation.as_matrix(), np.array([1.0, 2.0, 3.0]), 1.0, AlignMode.SE3, 10)
    result = landmark_metrics(moved, truth, alignment=alignment)
    np.testing.assert_allclose(result.error_aligned, [0.1, 0.2, 0.4], atol=1e-12)
    assert result.summary["lm_err_aligned_max"] == pytest.approx(0.4)
    assert result.summary["lm_err_max"] > 1.0


def test_precision_recall_helpers() -> None:
    assert precision_recall([True, True, False, False], [True, False, True, False]) == (0.5, 0.5)
    p, r = precision_recall([False, False], [False, False])
    assert np.isnan(p) and np.isnan(r)
    _, truth = _landmark_case()
    p, r = dynamic_point_precision_recall([True, True, False, True], [14, 10, 14, -1], truth)
    assert p == pytest.approx(1 / 3) and r == pytest.approx(0.5)


def test_dense_accuracy_and_completeness() -> None:
    rng = np.random.default_rng(4)
    reference = rng.uniform(-1, 1, size=(2000, 3))
    shifted = reference[:1000] + np.array([0.0, 0.0, 0.01])  # half the scene, 1 cm off
    metrics = dense_metrics(shifted, reference, threshold=0.02)
    assert metrics.accuracy_mean <= 0.01 + 1e-12
    assert metrics.accuracy_within == 1.0
    assert 0.4 < metrics.completeness_within < 0.75
    assert metrics.completeness_mean > metrics.accuracy_mean
    assert metrics.summary()["dense_f_score"] == pytest.approx(metrics.f_score)
    with pytest.raises(EvaluationError):
        dense_metrics(np.zeros((0, 3)), reference)


def test_dense_search_is_bounded_and_exact_within_the_bound() -> None:
    rng = np.random.default_rng(5)
    reference = rng.uniform(-1, 1, size=(3000, 3))
    near = reference[:600] + rng.normal(scale=0.01, size=(600, 3))
    far = reference[600:1000] + np.array([50.0, 0.0, 0.0])  # a misplaced part: 50 m off
    searched: list[int] = []
    bounded = dense_metrics(np.vstack([near, far]), reference, threshold=0.05, on_progress=searched.append)
    exact = dense_metrics(np.vstack([near, far]), reference, threshold=0.05, max_distance=np.inf)
    assert sum(searched) == 1000 + 3000
    assert bounded.max_distance == pytest.approx(1.0)  # 20 thresholds
    assert bounded.accuracy_within == exact.accuracy_within == pytest.approx(0.6, abs=0.02)
    assert bounded.completeness_within == exact.completeness_within
    assert bounded.accuracy_median == pytest.approx(exact.accuracy_median)  # the median lies within the bound
    assert exact.accuracy_mean > 15 and bounded.accuracy_mean < 1.0  # far points count as 1 m


def test_dense_against_a_mesh() -> None:
    # The unit square z = 0 as two triangles; map points 1 cm above its left half.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    rng = np.random.default_rng(9)
    grid = np.stack(np.meshgrid(np.linspace(0, 0.5, 26), np.linspace(0, 1, 51)), axis=-1).reshape(-1, 2)
    points = np.column_stack([grid, np.full(len(grid), 0.01)])
    metrics = dense_metrics_to_mesh(points, vertices, triangles, rng, threshold=0.05, samples=4000)
    assert metrics.accuracy_mean == pytest.approx(0.01, abs=1e-6)
    assert metrics.accuracy_within == 1.0
    assert metrics.completeness_within == pytest.approx(0.55, abs=0.05)  # x <= 0.5 + 0.05 within reach


# --- error cases ----------------------------------------------------------------------------------------


def test_error_class_is_a_relpoint_error_with_exit_code_3() -> None:
    assert issubclass(EvaluationError, RelpointError)
    assert not issubclass(EvaluationError, (InputError, EstimatorError, UsageError))
    assert EvaluationError.exit_code == 3


def test_no_overlapping_timestamps() -> None:
    rng = np.random.default_rng(5)
    reference = _random_trajectory(rng)
    later = Trajectory(reference.stamps_ns + 10**12, reference.positions, reference.quats_xyzw)
    with pytest.raises(EvaluationError, match="no matching timestamps"):
        evaluate_trajectory(reference, later)
    # ...but a time offset that undoes the shift makes them match (evo --t_offset).
    result = evaluate_trajectory(reference, later, EvaluationSettings(t_offset=-1000.0))
    assert result.summary["matched_poses"] == len(reference)
    assert result.summary["ate_max"] == 0.0


def test_too_few_matched_poses_for_alignment() -> None:
    rng = np.random.default_rng(6)
    reference = _random_trajectory(rng)
    two = Trajectory(reference.stamps_ns[:2], reference.positions[:2], reference.quats_xyzw[:2])
    with pytest.raises(EvaluationError, match="at least 3 matched poses"):
        evaluate_trajectory(reference, two, EvaluationSettings(align="se3"))
    with pytest.raises(EvaluationError, match="at least 3 matched poses"):
        evaluate_trajectory(reference, reference, EvaluationSettings(align="sim3", n_to_align=2))
    assert evaluate_trajectory(reference, two).summary["matched_poses"] == 2  # fine without alignment


def test_collinear_trajectory_is_degenerate_for_alignment() -> None:
    n = 50
    stamps = np.arange(n) * 100_000_000
    line = np.column_stack([np.linspace(0, 5, n), 2 * np.linspace(0, 5, n), np.zeros(n)])
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    reference = Trajectory(stamps, line, quats)
    estimate = Trajectory(stamps, line + 0.5, quats)
    for align in ("se3", "sim3"):
        with pytest.raises(EvaluationError, match="collinear"):
            evaluate_trajectory(reference, estimate, EvaluationSettings(align=align))
    stationary = Trajectory(stamps, np.ones((n, 3)), quats)
    with pytest.raises(EvaluationError, match="collinear or coincident"):
        evaluate_trajectory(reference, stationary, EvaluationSettings(align="se3"))
    assert evaluate_trajectory(reference, estimate).summary["ate_rmse"] == pytest.approx(np.sqrt(3 * 0.25))


@pytest.mark.parametrize(
    "kwargs",
    [
        {"align": "affine"},
        {"pose_relation": "yaw"},
        {"delta_unit": "s"},
        {"delta": 1.5, "delta_unit": "f"},
        {"delta": 0},
        {"n_to_align": 0},
        {"t_max_diff": -0.1},
        {"t_offset": float("nan")},
        {"pose_relation": "point_distance_error_ratio"},
    ],
)
def test_bad_settings_raise_usage_error(kwargs: dict) -> None:
    with pytest.raises(UsageError):
        EvaluationSettings(**kwargs)


def test_rpe_delta_without_pairs_and_bad_angle() -> None:
    rng = np.random.default_rng(7)
    reference = _random_trajectory(rng)
    # evo_rpe refuses a delta that makes no pair; the evaluation keeps its APE and says why it has no RPE
    result = evaluate_trajectory(reference, reference, EvaluationSettings(delta=1000.0, delta_unit="m"))
    assert result.rpe is None and result.summary["rpe_pairs"] == 0 and "ate_rmse" in result.summary
    assert len(result.notes) == 1 and "no pose pairs" in result.notes[0]
    matched = associate(reference, reference)
    with pytest.raises(EvaluationError, match="no pose pairs"):
        rpe_errors(matched, delta=1000.0, delta_unit="m")
    with pytest.raises(UsageError):
        rpe_errors(matched, delta=200.0, delta_unit="d")


def test_ape_rejects_rpe_only_relation_and_settings_round_trip() -> None:
    rng = np.random.default_rng(8)
    reference = _random_trajectory(rng)
    with pytest.raises(UsageError):
        ape_errors(associate(reference, reference), PoseRelation.POINT_DISTANCE_ERROR_RATIO)
    settings = EvaluationSettings(align="sim3", delta_unit="m", delta=0.5, interpolate=True)
    assert EvaluationSettings(**settings.to_dict()) == settings
    assert settings.to_dict()["align"] == "sim3"


def test_result_arrays_line_up_with_stamps() -> None:
    result = evaluate_trajectory(ours(GT), ours(RGBD), EvaluationSettings(align="se3"))
    k = int(result.summary["matched_poses"])
    assert result.stamps_ns.shape == result.ape_translation.shape == result.ape_rotation_deg.shape == (k,)
    assert result.rpe_translation is not None
    assert result.rpe_translation.second.max() < k
    assert np.all(np.diff(result.stamps_ns) > 0)
