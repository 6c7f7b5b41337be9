"""Trajectory files (TUM, EuRoC, KITTI): round trips, how evo reads them and its figures, malformed input."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from formats.trajectory_files import (
    TrajectoryFormat,
    detect_format,
    format_stamp,
    parse_stamp_ns,
    read_euroc_csv,
    read_kitti,
    read_tum,
    separate_repeated_stamps,
    write_euroc_csv,
    write_kitti,
    write_tum,
)
from relpoint.errors import InputError
from relpoint.types import Trajectory
from tests.conftest import shared_data

FR1 = "evo-fr1xyz"


def _trajectory(rng: np.random.Generator, n: int = 50) -> Trajectory:
    stamps = 1_305_031_102_000_000_000 + np.cumsum(rng.integers(1, 50_000_000, size=n))
    positions = rng.normal(scale=3.0, size=(n, 3))
    quats = Rotation.random(n, random_state=np.random.RandomState(0)).as_quat()
    return Trajectory(stamps, positions, quats)


def _assert_same(a: Trajectory, b: Trajectory, atol: float = 0.0) -> None:
    np.testing.assert_array_equal(a.stamps_ns, b.stamps_ns)
    np.testing.assert_allclose(a.positions, b.positions, rtol=0, atol=atol)
    # q and -q are the same rotation
    dots = np.abs(np.sum(a.quats_xyzw * b.quats_xyzw, axis=1))
    np.testing.assert_allclose(dots, 1.0, rtol=0, atol=1e-12)


def test_tum_round_trip_is_exact(tmp_path: Path) -> None:
    original = _trajectory(np.random.default_rng(0))
    path = tmp_path / "traj.tum"
    write_tum(path, original, header="estimate of run 7")
    again = read_tum(path)
    np.testing.assert_array_equal(again.stamps_ns, original.stamps_ns)
    np.testing.assert_array_equal(again.positions, original.positions)
    # Written exactly; Trajectory re-normalises on construction, which may move the last bit.
    np.testing.assert_allclose(again.quats_xyzw, original.quats_xyzw, rtol=0, atol=1e-15)
    assert path.read_text().startswith("# estimate of run 7\n# timestamp tx ty tz qx qy qz qw\n")
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


def test_tum_written_file_is_read_by_evo_identically(tmp_path: Path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    original = _trajectory(np.random.default_rng(1))
    path = tmp_path / "traj.txt"
    write_tum(path, original)
    evo_traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_array_equal(evo_traj.timestamps, [s / 1_000_000_000 for s in original.stamps_ns.tolist()])
    np.testing.assert_array_equal(evo_traj.positions_xyz, original.positions)


def test_tum_tolerates_whitespace_comments_and_scientific_notation(tmp_path: Path) -> None:
    path = tmp_path / "messy.txt"
    path.write_text(
        "\ufeff# a comment\n"
        "\n"
        "  1.5   1 2 3\t0 0 0 1  \n"
        "   # indented comment\n"
        "1.6e0 1.0e-1 2 3 0 0 0 2\r\n"
        "1.700000001,4,5,6,0,0,1,0\n"
    )
    traj = read_tum(path)
    assert traj.stamps_ns.tolist() == [1_500_000_000, 1_600_000_000, 1_700_000_001]
    np.testing.assert_array_equal(traj.positions[1], [0.1, 2, 3])
    np.testing.assert_array_equal(traj.quats_xyzw[1], [0, 0, 0, 1])  # normalised


def test_reads_the_shared_tum_files_like_evo() -> None:
    data = shared_data(FR1)
    file_interface = pytest.importorskip("evo.tools.file_interface")
    for name in ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", "freiburg1_xyz-ORB_kf_mono.txt"):
        ours = read_tum(data / name)
        theirs = file_interface.read_tum_trajectory_file(str(data / name))
        np.testing.assert_array_equal([s / 1_000_000_000 for s in ours.stamps_ns.tolist()], theirs.timestamps)
        np.testing.assert_array_equal(ours.positions, theirs.positions_xyz)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("1 2 3 4 5 6 7\n", r":1: expected 8 values"),
        ("# ok\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1 9\n", r":3: expected 8 values"),
        ("1 0 0 zero 0 0 0 1\n", r":1: non-numeric value"),
        ("abc 0 0 0 0 0 0 1\n", r":1: bad timestamp"),
        ("1 0 0 nan 0 0 0 1\n", r"every pose holds a NaN"),
        ("inf 0 0 0 0 0 0 1\n", r":1: bad timestamp"),
        ("2 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", r":3: timestamp goes back in time .*line 2"),
        ("1e30 0 0 0 0 0 0 1\n", r":1: timestamp out of range"),
        ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 0\n", r":2: zero quaternion"),  # one pose without its orientation
        ("# only comments\n\n", r"no poses"),
    ],
)
def test_malformed_tum_names_file_and_line(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as info:
        read_tum(path)
    assert str(path) in str(info.value)


def test_tum_rows_holding_nan_are_left_out_with_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "groundtruth.txt"
    path.write_text("# mocap\n1.0 0 0 0 0 0 0 1\n1.1 nan nan nan nan nan nan nan\n1.2 1 0 0 0 0 0 1\n"
                    "1.3 1 inf 0 0 0 0 1\n1.4 2 0 0 0 0 0 1\n")  # fmt: skip
    with caplog.at_level(logging.WARNING):
        trajectory = read_tum(path)
    assert trajectory.stamps_ns.tolist() == [1_000_000_000, 1_200_000_000, 1_400_000_000]
    np.testing.assert_array_equal(trajectory.positions[:, 0], [0.0, 1.0, 2.0])
    assert "2 poses holding a NaN or infinite value left out (the first: line 3)" in caplog.text


def test_unreadable_inputs(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        read_tum(tmp_path / "missing.txt")
    with pytest.raises(InputError, match="is a directory"):
        read_tum(tmp_path)
    binary = tmp_path / "binary.mcap"
    binary.write_bytes(b"\x89MCAP0\r\n\xff\xfe\x00")
    with pytest.raises(InputError, match="not a text file"):
        read_tum(binary)


def test_kitti_round_trip_with_times(tmp_path: Path) -> None:
    original = _trajectory(np.random.default_rng(2))
    poses, times = tmp_path / "poses.txt", tmp_path / "times.txt"
    write_kitti(poses, original, times)
    again = read_kitti(poses, times)
    _assert_same(again, original, atol=1e-12)
    np.testing.assert_allclose(again.matrices(), original.matrices(), rtol=0, atol=1e-15)
    assert len(poses.read_text().splitlines()[0].split()) == 12


def test_kitti_without_times_uses_frame_index_seconds(tmp_path: Path) -> None:
    path = tmp_path / "00.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1.5 0 1 0 0 0 0 1 0\n0 -1 0 2 1 0 0 0 0 0 1 0\n")
    traj = read_kitti(path)
    assert traj.stamps_ns.tolist() == [0, 1_000_000_000, 2_000_000_000]
    np.testing.assert_array_equal(traj.positions[1], [1.5, 0, 0])
    assert Rotation.from_quat(traj.quats_xyzw[2]).as_rotvec()[2] == pytest.approx(np.pi / 2)


def test_kitti_times_in_scientific_notation(tmp_path: Path) -> None:
    poses, times = tmp_path / "poses.txt", tmp_path / "times.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 1 0\n")
    times.write_text("0.000000e+00\n1.036896e-01\n")
    assert read_kitti(poses, times).stamps_ns.tolist() == [0, 103_689_600]


@pytest.mark.parametrize(
    ("poses_text", "times_text", "message"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1\n", None, r"poses.txt:1: expected 12 values"),
        ("1 0 0 0 0 1 0 0 0 0 1 x\n", None, r"poses.txt:1: non-numeric"),
        ("2 0 0 0 0 1 0 0 0 0 1 0\n", None, r"poses.txt:1: .*not a rotation"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n", "0.0\n0.1\n", r"times.txt: 2 times for 1 poses"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2, "0.2\n0.1\n", r"times.txt:2: timestamp goes back in time"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n", "0.1 0.2\n", r"times.txt:1: expected one time"),
    ],
)
def test_malformed_kitti(tmp_path: Path, poses_text: str, times_text: str | None, message: str) -> None:
    poses = tmp_path / "poses.txt"
    poses.write_text(poses_text)
    times = None
    if times_text is not None:
        times = tmp_path / "times.txt"
        times.write_text(times_text)
    with pytest.raises(InputError, match=message):
        read_kitti(poses, times)


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path: Path) -> None:
    path = tmp_path / "keep.txt"
    path.write_text("old\n")

    class Exploding(Trajectory):
        pass

    traj = _trajectory(np.random.default_rng(3), n=3)
    broken = object.__new__(Exploding)
    object.__setattr__(broken, "stamps_ns", traj.stamps_ns)
    object.__setattr__(broken, "positions", traj.positions)
    object.__setattr__(broken, "quats_xyzw", None)  # fails midway through formatting
    with pytest.raises(AttributeError):
        write_tum(path, broken)
    assert path.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]


@pytest.mark.parametrize("text", ["0", "1305031102.175304", "-3.25", "12.000000001", "1e-9"])
def test_stamp_text_round_trips(text: str) -> None:
    ns = parse_stamp_ns(text)
    assert parse_stamp_ns(format_stamp(ns)) == ns
    assert float(format_stamp(ns)) == pytest.approx(float(text), abs=1e-9)


# --- repeated stamps -----------------------------------------------------------------------------------


def test_separate_repeated_stamps_moves_earlier_copies_back() -> None:
    assert separate_repeated_stamps([10, 20, 20, 20, 30]).tolist() == [10, 18, 19, 20, 30]
    assert separate_repeated_stamps([5, 6, 6]).tolist() == [4, 5, 6]  # room is made further back when needed
    increasing = np.array([1, 2, 7])
    assert separate_repeated_stamps(increasing).tolist() == [1, 2, 7]
    assert separate_repeated_stamps([]).tolist() == []


def test_tum_with_repeated_stamps_keeps_every_pose_and_says_so_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "gt.txt"
    path.write_text(
        "# motion capture\n1.0 0 0 0 0 0 0 1\n\n2.0 1 0 0 0 0 0 1\n2.0 2 0 0 0 0 0 1\n3.0 3 0 0 0 0 0 1\n"
        "3.0 4 0 0 0 0 0 1\n3.0 5 0 0 0 0 0 1\n"
    )
    with caplog.at_level("WARNING"):
        traj = read_tum(path)
    assert traj.stamps_ns.tolist() == [10**9, 2 * 10**9 - 1, 2 * 10**9, 3 * 10**9 - 2, 3 * 10**9 - 1, 3 * 10**9]
    assert traj.positions[:, 0].tolist() == [0, 1, 2, 3, 4, 5]  # file order
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1
    assert "3 repeated timestamps (the first: line 5 repeats the stamp of line 4)" in warnings[0]
    assert "kept every pose" in warnings[0] and "1 ns back" in warnings[0]


# --- format detection ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "text", "expected"),
    [
        ("a.txt", "# tum\n1.5 0 0 0 0 0 0 1\n", TrajectoryFormat.TUM),
        ("a.csv", "1.5,0,0,0,0,0,0,1\n", TrajectoryFormat.TUM),
        ("a.txt", "1,0,0,0,0,0,0,1\n", TrajectoryFormat.TUM),
        ("a.csv", "1403636579758555392,0,0,0,1,0,0,0\n", TrajectoryFormat.EUROC),
        ("data.csv", "#timestamp,p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []\n"
         "1403636579758555392,0,0,0,1,0,0,0\n", TrajectoryFormat.EUROC),
        ("gt", "1403636579758555392,0,0,0,1,0,0,0,0.1,0.2,0.3,0,0,0,0,0,0\n", TrajectoryFormat.EUROC),
        ("00.txt", "1 0 0 0 0 1 0 0 0 0 1 0\n", TrajectoryFormat.KITTI),
        ("a.txt", "1 2 3 4 5\n", None),
        ("a.txt", "# nothing\n\n", None),
        ("a.bin", b"\xff\xfe\x00\x01", None),
    ],
)  # fmt: skip
def test_detect_format(tmp_path: Path, name: str, text: str | bytes, expected: TrajectoryFormat | None) -> None:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    assert detect_format(path) is expected


# --- EuRoC ground truth --------------------------------------------------------------------------------


def test_euroc_round_trip_and_extra_columns(tmp_path: Path) -> None:
    original = _trajectory(np.random.default_rng(4))
    path = tmp_path / "data.csv"
    write_euroc_csv(path, original)
    header, first = path.read_text().splitlines()[:2]
    assert header.startswith("#timestamp [ns],p_RS_R_x [m]") and len(first.split(",")) == 8
    again = read_euroc_csv(path)
    np.testing.assert_array_equal(again.stamps_ns, original.stamps_ns)
    np.testing.assert_array_equal(again.positions, original.positions)
    np.testing.assert_allclose(again.quats_xyzw, original.quats_xyzw, rtol=0, atol=1e-15)
    wide = tmp_path / "wide.csv"
    wide.write_text(
        "".join(line + ",0.5,-0.5,0,0.01,0.02,0.03,0.1,0.2,0.3\n" for line in path.read_text().splitlines())
    )
    _assert_same(read_euroc_csv(wide), original)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("1,0,0,0,1,0,0\n", r":1: expected at least 8 values"),
        ("1.5,0,0,0,1,0,0,0\n", r":1: bad timestamp '1.5', expected integer nanoseconds"),
        ("#h\n1,0,0,x,1,0,0,0\n", r":2: non-numeric value"),
        ("1,0,0,0,1,0,0,0\n2,0,0,0,0,0,0,0\n", r":2: zero quaternion"),
        ("2,0,0,0,1,0,0,0\n1,0,0,0,1,0,0,0\n", r":2: timestamp goes back in time"),
        ("\u00b2,0,0,0,1,0,0,0\n", r":1: bad timestamp"),
        ("#h\n99999999999999999999,0,0,0,1,0,0,0\n", r":2: timestamp out of range"),
    ],
)
def test_malformed_euroc_names_file_and_line(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "data.csv"
    path.write_text(content)
    with pytest.raises(InputError, match=message):
        read_euroc_csv(path)


# --- evo's figures on files built from the real fr1/xyz trajectories -------------------------------------
#
# evo 1.38 (evo.core.sync.matching_time_indices) walks the shorter trajectory and, in the longer one,
# takes for a stamp just before a repeated stamp its first copy, for the repeated stamp and after it the
# last copy; every row of the shorter one is kept. relpoint keeps every row too (earlier copies 1 ns
# back), so its figures are evo's. evo's TUM reader refuses blank lines, so evo reads the same rows
# without them.

GT = "freiburg1_xyz-groundtruth.txt"
RGBD = "freiburg1_xyz-rgbdslam.txt"
FIGURE_KEYS = [f"{prefix}_{stat}" for prefix in ("ate", "rpe_trans", "rpe_rot_deg")
               for stat in ("rmse", "mean", "median", "std", "min", "max", "sse")]  # fmt: skip


def _data_rows(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]


def _stamp(row: str) -> float:
    return float(row.split()[0])


def _moved(row: str, dx: float) -> str:
    fields = row.split()
    return " ".join([fields[0], repr(float(fields[1]) + dx), *fields[2:]])


def _relpoint_figures(
    reference: Path, estimate: Path, align: str, interpolate: bool = False, **times: Path
) -> dict[str, float]:
    from formats.reference_trajectories import load_trajectory
    from relpoint.evaluation import AlignMode, EvaluationSettings, evaluate_trajectory

    ref = load_trajectory(reference, times=times.get("reference_times"))
    est = load_trajectory(estimate, times=times.get("times"))
    settings = EvaluationSettings(align=AlignMode(align), interpolate=interpolate)
    summary = evaluate_trajectory(ref, est, settings).summary
    return {key: summary[key] for key in FIGURE_KEYS}


def _evo_figures(
    ref: object, est: object, align: str, synchronise: bool = True, interpolate: bool = False
) -> dict[str, float]:
    """evo_ape -r trans_part and evo_rpe -r trans_part / angle_deg (delta 1 frame), as evo's CLI runs them."""
    import copy

    from evo.core import metrics, sync
    from evo.core.sync_method import SyncMethod
    from evo.main_ape import ape
    from evo.main_rpe import rpe

    if synchronise:
        method = SyncMethod.interpolation if interpolate else SyncMethod.nearest_time
        ref, est = sync.associate_trajectories(ref, est, max_diff=0.01, sync_method=method)
    do_align = align == "se3"
    relation = metrics.PoseRelation
    results = {
        "ate": ape(copy.deepcopy(ref), copy.deepcopy(est), relation.translation_part, align=do_align),
        **{
            name: rpe(copy.deepcopy(ref), copy.deepcopy(est), rel, delta=1, delta_unit=metrics.Unit.frames,
                      align=do_align)
            for name, rel in (("rpe_trans", relation.translation_part), ("rpe_rot_deg", relation.rotation_angle_deg))
        },
    }  # fmt: skip
    return {f"{name}_{stat}": float(value) for name, result in results.items() for stat, value in result.stats.items()}


def _assert_figures_equal(ours: dict[str, float], evo: dict[str, float]) -> None:
    for key in FIGURE_KEYS:
        assert ours[key] == pytest.approx(evo[key], abs=1e-6, rel=1e-9), key


def _repeat_near_estimate(gt_rows: list[str], est_rows: list[str]) -> tuple[list[str], list[int], list[int]]:
    """Ground-truth rows with a moved copy after some rows, and the indices where evo uses either copy.

    A copy 5 cm off is appended after every 40th ground-truth row that an estimate stamp matches: when
    the estimate stamp lies just before the row evo uses the first (true) copy, when at or after it the
    last (moved) one, so both choices change the figures.
    """
    gt_t = np.array([_stamp(r) for r in gt_rows])
    est_t = np.array([_stamp(r) for r in est_rows])
    nearest = np.clip(np.searchsorted(gt_t, est_t), 1, len(gt_t) - 1)
    nearest -= (est_t - gt_t[nearest - 1]) <= (gt_t[nearest] - est_t)
    repeated = sorted(set(nearest[::40].tolist()))
    before = [k for k in repeated if est_t[np.searchsorted(nearest, k)] < gt_t[k]]
    after = [k for k in repeated if k not in before]
    rows = []
    for k, row in enumerate(gt_rows):
        rows.append(row)
        if k in repeated:
            rows.append(_moved(row, 0.05))
    return rows, before, after


@pytest.fixture(scope="module")
def fr1() -> dict[str, list[str]]:
    data = shared_data(FR1)
    pytest.importorskip("evo.core.sync")
    return {"gt": _data_rows(data / GT), "est": _data_rows(data / RGBD)}


@pytest.mark.parametrize(("align", "interpolate"), [("none", False), ("se3", False), ("se3", True)])
def test_repeated_stamps_in_the_longer_file_give_evo_figures(
    tmp_path: Path, fr1: dict[str, list[str]], align: str, interpolate: bool
) -> None:
    from evo.tools import file_interface

    rows, before, after = _repeat_near_estimate(fr1["gt"], fr1["est"])
    assert len(before) >= 3 and len(after) >= 3  # both of evo's choices are exercised
    ours, theirs, estimate = tmp_path / "gt_ours.txt", tmp_path / "gt_evo.txt", tmp_path / "est.txt"
    ours.write_text("# repeated stamps, a blank line and comments\n\n" + "\n# c\n".join(rows) + "\n")
    theirs.write_text("\n".join(rows) + "\n")
    estimate.write_text("\n".join(fr1["est"]) + "\n")
    evo = _evo_figures(
        file_interface.read_tum_trajectory_file(str(theirs)), file_interface.read_tum_trajectory_file(str(estimate)),
        align, interpolate=interpolate,
    )  # fmt: skip
    _assert_figures_equal(_relpoint_figures(ours, estimate, align, interpolate), evo)
    # Keeping only one copy (either) would not give evo's figures: the test can tell.
    for keep in ("first", "last"):
        dropped = tmp_path / f"gt_{keep}.txt"
        kept = [r for i, r in enumerate(rows) if i + 1 == len(rows) or _stamp(rows[i + 1]) != _stamp(r)]
        if keep == "first":
            kept = [r for i, r in enumerate(rows) if i == 0 or _stamp(rows[i - 1]) != _stamp(r)]
        dropped.write_text("\n".join(kept) + "\n")
        assert _relpoint_figures(dropped, estimate, align, interpolate)["ate_rmse"] != pytest.approx(
            evo["ate_rmse"], abs=1e-6
        )


@pytest.mark.parametrize("interpolate", [False, True])
def test_repeated_stamps_in_the_shorter_file_give_evo_figures(
    tmp_path: Path, fr1: dict[str, list[str]], interpolate: bool
) -> None:
    from evo.tools import file_interface

    est_rows = []
    for k, row in enumerate(fr1["est"]):
        est_rows.append(row)
        if k % 50 == 7:
            est_rows.append(_moved(row, -0.03))
    reference, estimate = tmp_path / "gt.txt", tmp_path / "est.txt"
    reference.write_text("\n".join(fr1["gt"]) + "\n")
    estimate.write_text("\n".join(est_rows) + "\n")
    evo = _evo_figures(
        file_interface.read_tum_trajectory_file(str(reference)), file_interface.read_tum_trajectory_file(str(estimate)),
        "se3", interpolate=interpolate,
    )  # fmt: skip
    _assert_figures_equal(_relpoint_figures(reference, estimate, "se3", interpolate), evo)


def test_euroc_ground_truth_gives_evo_figures(tmp_path: Path, fr1: dict[str, list[str]]) -> None:
    from evo.tools import file_interface

    data = shared_data(FR1)
    csv = tmp_path / "state_groundtruth_estimate0" / "data.csv"
    csv.parent.mkdir()
    header = "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
    lines = [header + ", v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1]"]
    for row in fr1["gt"]:
        stamp, x, y, z, qx, qy, qz, qw = row.split()
        lines.append(",".join([str(parse_stamp_ns(stamp)), x, y, z, qw, qx, qy, qz, "0.1", "-0.2", "0.3"]))
    csv.write_text("\n".join(lines) + "\n")
    assert detect_format(csv) is TrajectoryFormat.EUROC
    tum = read_tum(data / GT)
    euroc = read_euroc_csv(csv)
    np.testing.assert_array_equal(euroc.stamps_ns, tum.stamps_ns)
    np.testing.assert_array_equal(euroc.positions, tum.positions)
    np.testing.assert_allclose(euroc.quats_xyzw, tum.quats_xyzw, rtol=0, atol=1e-15)
    evo_ref = file_interface.read_euroc_csv_trajectory(str(csv))
    evo_est = file_interface.read_tum_trajectory_file(str(data / RGBD))
    _assert_figures_equal(_relpoint_figures(csv, data / RGBD, "se3"), _evo_figures(evo_ref, evo_est, "se3"))


def test_kitti_with_times_gives_evo_figures_of_the_tum_files(tmp_path: Path, fr1: dict[str, list[str]]) -> None:
    """evo's ``kitti`` mode ignores times; with them relpoint pairs by time, as ``evo_ape tum`` on the same poses."""
    from evo.tools import file_interface

    data = shared_data(FR1)
    files = {}
    for name in (GT, RGBD):
        poses, times = tmp_path / f"{name}.kitti", tmp_path / f"{name}.times"
        write_kitti(poses, read_tum(data / name), times)
        files[name] = (poses, times)
    ours = _relpoint_figures(files[GT][0], files[RGBD][0], "se3", reference_times=files[GT][1], times=files[RGBD][1])
    evo = _evo_figures(
        file_interface.read_tum_trajectory_file(str(data / GT)), file_interface.read_tum_trajectory_file(str(data / RGBD)),
        "se3",
    )  # fmt: skip
    _assert_figures_equal(ours, evo)


@pytest.mark.parametrize("align", ["none", "se3"])
def test_kitti_without_times_pairs_by_index_as_evo(tmp_path: Path, fr1: dict[str, list[str]], align: str) -> None:
    """KITTI files of the same frames (the evo-associated fr1/xyz pair): ``evo_ape kitti`` / ``evo_rpe kitti``."""
    from evo.core import sync
    from evo.tools import file_interface

    data = shared_data(FR1)
    ref, est = sync.associate_trajectories(
        file_interface.read_tum_trajectory_file(str(data / GT)),
        file_interface.read_tum_trajectory_file(str(data / RGBD)),
    )
    paths = []
    for name, traj in (("ref", ref), ("est", est)):
        path = tmp_path / f"{name}.txt"
        path.write_text("".join(" ".join(map(repr, T[:3, :].ravel().tolist())) + "\n" for T in traj.poses_se3))
        paths.append(path)
    evo = _evo_figures(
        file_interface.read_kitti_poses_file(str(paths[0])), file_interface.read_kitti_poses_file(str(paths[1])),
        align, synchronise=False,
    )  # fmt: skip
    ours = _relpoint_figures(paths[0], paths[1], align)
    _assert_figures_equal(ours, evo)


# --- through the CLI: one warning, format detection, KITTI pairing -------------------------------------


def _invoke(*args: str | Path) -> tuple[int, str, str]:
    from click.testing import CliRunner

    from relpoint_cli.main import cli

    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result.exit_code, result.stdout, result.stderr


def test_evaluate_warns_once_about_repeated_stamps(tmp_path: Path, fr1: dict[str, list[str]]) -> None:
    import json

    rows, _, _ = _repeat_near_estimate(fr1["gt"], fr1["est"])
    reference, estimate, out = tmp_path / "gt.txt", tmp_path / "est.txt", tmp_path / "eval.json"
    reference.write_text("\n".join(rows) + "\n")
    estimate.write_text("\n".join(fr1["est"]) + "\n")
    code, _, err = _invoke("evaluate", estimate, "-r", reference, "--align", "se3", "--json", out)
    assert code == 0, err
    lines = err.strip().splitlines()
    repeats = len(rows) - len(fr1["gt"])
    assert len(lines) == 1 and lines[0].startswith("relpoint: warning: "), err
    assert f"{reference}: {repeats} repeated timestamps" in lines[0] and "kept every pose" in lines[0]
    summary = json.loads(out.read_text())["summary"]
    assert summary["reference_poses"] == len(rows)
    assert summary["ate_rmse"] == pytest.approx(_relpoint_figures(reference, estimate, "se3")["ate_rmse"], abs=0)


def test_export_and_evaluate_detect_euroc_csv(tmp_path: Path) -> None:
    original = _trajectory(np.random.default_rng(5))
    csv, tum = tmp_path / "data.csv", tmp_path / "gt.tum"
    write_euroc_csv(csv, original)
    code, _, err = _invoke("export", csv, "-o", tum)
    assert code == 0 and err == "", err
    _assert_same(read_tum(tum), original)
    code, out, err = _invoke("evaluate", tum, "-r", csv)
    assert code == 0 and err == "", err
    assert "matched_poses" in out


@pytest.mark.parametrize(
    ("make", "fragment"),
    [
        ("one_side", "holds KITTI poses without times, which pair by index only with other such poses"),
        ("counts", "pair by index, but"),
        ("times_on_tum", "is not a KITTI pose file; a times file applies only to KITTI poses"),
    ],
)
def test_kitti_pairing_errors(tmp_path: Path, make: str, fragment: str) -> None:
    traj = _trajectory(np.random.default_rng(6), n=30)
    kitti, short, tum, times = tmp_path / "a.kitti", tmp_path / "b.kitti", tmp_path / "c.tum", tmp_path / "t.txt"
    write_kitti(kitti, traj, times)
    write_kitti(short, Trajectory(traj.stamps_ns[:20], traj.positions[:20], traj.quats_xyzw[:20]))
    write_tum(tum, traj)
    args = {
        "one_side": [kitti, "-r", tum],
        "counts": [kitti, "-r", short],
        "times_on_tum": [tum, "--times", times, "-r", kitti, "--reference-times", times],
    }[make]
    code, _, err = _invoke("evaluate", *args)
    lines = err.strip().splitlines()
    assert code == 3 and len(lines) == 1 and lines[0].startswith("relpoint: error: ") and fragment in lines[0], err


def test_kitti_without_times_evaluates_by_index(tmp_path: Path) -> None:
    import json

    traj = _trajectory(np.random.default_rng(7), n=30)
    a, b, out = tmp_path / "a.kitti", tmp_path / "b.kitti", tmp_path / "eval.json"
    write_kitti(a, traj)
    write_kitti(b, Trajectory(traj.stamps_ns, traj.positions + np.array([0.1, 0.0, 0.0]), traj.quats_xyzw))
    code, _, err = _invoke("evaluate", b, "-r", a, "--json", out)
    assert code == 0 and err == "", err
    summary = json.loads(out.read_text())["summary"]
    assert summary["matched_poses"] == 30
    assert summary["ate_max"] == pytest.approx(0.1, abs=1e-12) and summary["ate_min"] == pytest.approx(0.1, abs=1e-12)


def test_bag_pose_topic_with_repeated_stamps_warns_once(tmp_path: Path) -> None:
    """Bag topics as before: sorted by stamp, the first message of each stamp kept; now said on stderr."""
    from mcap_ros2.writer import Writer

    from formats import ros2

    bag, out = tmp_path / "bag.mcap", tmp_path / "pose.tum"
    with bag.open("wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef(ros2.POSE_STAMPED, ros2.message_definition(ros2.POSE_STAMPED))
        for x, stamp in enumerate([1, 2, 2, 3, 3, 4]):
            header = {"stamp": {"sec": stamp, "nanosec": 0}, "frame_id": "map"}
            pose = {
                "position": {"x": float(x), "y": 0.0, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            }
            writer.write_message("/pose", schema, {"header": header, "pose": pose}, log_time=stamp * 10**9 + x)
        writer.finish()
    code, _, err = _invoke("export", bag, "--topic", "/pose", "-o", out)
    lines = err.strip().splitlines()
    assert code == 0 and len(lines) == 1, err
    assert (
        lines[0]
        == f"relpoint: warning: {bag} /pose: 2 messages repeat the stamp of an earlier one; kept the first of each stamp"
    )
    assert read_tum(out).positions[:, 0].tolist() == [0, 1, 3, 5]


def test_nanosecond_stamps_in_a_seconds_format_are_named(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    # A TUM file written with ns stamps: from zero they read as poses 3e7 s apart, without a word; from
    # a 2011 epoch they overflow, and the error only said "beyond year 2262".
    rows = "".join(f"{k * 33_333_333} {k * 0.1} 0 0 0 0 0 1\n" for k in range(20))
    (tmp_path / "zero.txt").write_text(rows)
    with caplog.at_level("WARNING"):
        read_tum(tmp_path / "zero.txt")
    assert "are the stamps nanoseconds?" in caplog.text
    # From an epoch they cannot be seconds (year 4e10): they are read as nanoseconds (ORB-SLAM3's EuRoC
    # output, "1403636580838555648.000000"), where they were refused ("divide them by 1e9").
    caplog.clear()
    (tmp_path / "epoch.txt").write_text(
        "".join(f"{1305031102175304000 + k * 33_333_333}.000000 {k} 0 0 0 0 0 1\n" for k in range(3))
    )
    with caplog.at_level("WARNING"):
        epoch = read_tum(tmp_path / "epoch.txt")
    assert "read as nanoseconds" in caplog.text
    assert epoch.stamps_ns.tolist() == [1305031102175304000 + k * 33_333_333 for k in range(3)]
    # One stamp in seconds among them: not a file of nanoseconds, and out of range.
    (tmp_path / "mixed.txt").write_text("1305031102.175304 0 0 0 0 0 0 1\n1305031102208637333 1 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r":2: timestamp out of range .*nanoseconds"):
        read_tum(tmp_path / "mixed.txt")


# --- files whose header names the columns --------------------------------------------------------------


def _columns_text(trajectory: Trajectory, header: str, order: str, *, sep: str = ",", stamp: str = "s") -> str:
    """``trajectory`` as a text file under ``header``, columns t x y z then the quaternion in ``order``."""
    lines = [header]
    for t, p, q in zip(trajectory.stamps_ns, trajectory.positions, trajectory.quats_xyzw, strict=True):
        quat = dict(zip("xyzw", q.tolist(), strict=True))
        text = str(int(t)) if stamp == "ns" else format_stamp(int(t))
        lines.append(sep.join([text, *map(repr, p.tolist()), *(repr(quat[a]) for a in order)]))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(
    ("header", "order", "sep", "stamp"),
    [
        ("timestamp,x,y,z,qx,qy,qz,qw", "xyzw", ",", "s"),  # uncommented, TUM order
        ("#timestamp,x,y,z,qw,qx,qy,qz", "wxyz", ",", "s"),  # w first, named
        ("timestamp tx ty tz qw qx qy qz", "wxyz", " ", "s"),  # uncommented, blanks
        ("# timestamp tx ty tz qw qx qy qz", "wxyz", " ", "s"),  # a TUM-looking file, w first
        ("#timestamp [ns],x,y,z,qx,qy,qz,qw", "xyzw", ",", "ns"),  # nanoseconds, x-y-z-w: not EuRoC's order
        ("time_ns,pos_x,pos_y,pos_z,quat_w,quat_x,quat_y,quat_z", "wxyz", ",", "ns"),
        ("#timestamp,x,y,z,qx,qy,qz,qw", "xyzw", ",", "ns"),  # integer stamps of 19 digits: nanoseconds
        ("%time,field.pose.position.x,field.pose.position.y,field.pose.position.z,field.pose.orientation.x,"
         "field.pose.orientation.y,field.pose.orientation.z,field.pose.orientation.w", "xyzw", ",", "ns"),
    ],
)  # fmt: skip
def test_a_header_naming_the_columns_sets_the_order(
    tmp_path: Path, header: str, order: str, sep: str, stamp: str
) -> None:
    from formats.reference_trajectories import load_trajectory

    original = _trajectory(np.random.default_rng(3))
    path = tmp_path / "trajectory.csv"
    path.write_text(_columns_text(original, header, order, sep=sep, stamp=stamp))
    assert detect_format(path) is TrajectoryFormat.NAMED_COLUMNS
    _assert_same(load_trajectory(path), original)


def test_named_columns_ignore_other_quantities_and_keep_units(tmp_path: Path) -> None:
    from formats.trajectory_files import header_layout, read_named_columns

    path = tmp_path / "odometry.csv"
    path.write_text(
        "# header: t in ms\nstamp [ms], v_x, x, y, z, b_w_RS_S_x, w, qx, qy, qz, covariance_x\n"
        "1500, 9, 1, 2, 3, 9, 1, 0, 0, 0, 9\n2500.5, 9, 4, 5, 6, 9, 0, 0, 0, 1, 9\n"
    )
    layout = header_layout(path)
    assert layout is not None and not layout.commented
    assert (layout.stamp, layout.position, layout.quaternion) == (0, (2, 3, 4), (7, 8, 9, 6))
    trajectory = read_named_columns(path)
    assert trajectory.stamps_ns.tolist() == [1_500_000_000, 2_500_500_000]
    np.testing.assert_array_equal(trajectory.positions, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(trajectory.quats_xyzw, [[0, 0, 0, 1], [0, 0, 1, 0]])


def test_commented_tum_and_euroc_headers_keep_their_readers(tmp_path: Path) -> None:
    tum = tmp_path / "a.txt"
    tum.write_text("# timestamp tx ty tz qx qy qz qw\n1.5 0 0 0 0 0 0 1\n")
    assert detect_format(tum) is TrajectoryFormat.TUM
    euroc = tmp_path / "data.csv"
    euroc.write_text("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []\n"
                     "1403636579758555392,0,0,0,1,0,0,0\n")  # fmt: skip
    assert detect_format(euroc) is TrajectoryFormat.EUROC


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("time,a,b,c,d,e,f,g\n1,0,0,0,0,0,0,1\n", r":1: a header line whose names do not say .*comment the line out"),
        ("t,x,y,z,x,qy,qz,qw\n1,0,0,0,0,0,0,1\n", r":1: a header line whose names"),  # x twice
        ("timestamp,x,y,z,qx,qy,qz,qw\n1,0,0,0,0,0,0,1,5\n", r":2: expected 8 values, as the header on line 1"),
        ("timestamp,x,y,z,qx,qy,qz,qw\nnow,0,0,0,0,0,0,1\n", r":2: bad timestamp 'now'"),
    ],
)
def test_bad_headers_and_rows_under_them_name_the_line(tmp_path: Path, text: str, message: str) -> None:
    from formats.reference_trajectories import load_trajectory

    path = tmp_path / "t.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        load_trajectory(path)


@pytest.mark.parametrize("layout", ["tum-w-first", "euroc-x-y-z-w"])
def test_evaluate_says_when_the_other_quaternion_order_fits(
    tmp_path: Path, fr1: dict[str, list[str]], layout: str
) -> None:
    """A TUM file holding w x y z, or nanosecond CSV rows holding x y z w (read as EuRoC's w x y z): the
    values alone cannot tell; a rotation error that the other order cuts from 164 to 2 degrees can."""
    estimate = tmp_path / ("est.txt" if layout == "tum-w-first" else "est.csv")
    rows = []
    for row in fr1["est"]:
        stamp, x, y, z, qx, qy, qz, qw = row.split()
        if layout == "tum-w-first":
            rows.append(" ".join([stamp, x, y, z, qw, qx, qy, qz]))
        else:
            rows.append(",".join([str(parse_stamp_ns(stamp)), x, y, z, qx, qy, qz, qw]))
    estimate.write_text("\n".join(rows) + "\n")
    reference = shared_data(FR1) / GT
    code, stdout, err = _invoke("evaluate", estimate, "-r", reference, "--align", "se3")
    assert code == 0, err
    other = "w x y z" if layout == "tum-w-first" else "x y z w"
    assert f"with {other} it would be 2.1 deg" in err, err
    fixed = tmp_path / "named.csv"
    header = "#timestamp,x,y,z,qw,qx,qy,qz" if layout == "tum-w-first" else "#timestamp [ns],x,y,z,qx,qy,qz,qw"
    fixed.write_text(header + "\n" + "\n".join(row.replace(" ", ",") for row in rows) + "\n")
    code, stdout, err = _invoke("evaluate", fixed, "-r", reference, "--align", "se3")
    assert code == 0 and "would be" not in err, err
    rotation = next(line for line in stdout.splitlines() if line.startswith("APE rotation"))
    assert float(rotation.split()[3]) == pytest.approx(2.0577, abs=1e-4)  # evo's angle_deg rmse


def test_rostopic_echo_csv_of_odometry_is_read_by_its_header_stamp(tmp_path: Path) -> None:
    """``rostopic echo -p`` of a stamped message writes two stamps (``%time``, the receive time, and
    ``field.header.stamp``), string columns that may be empty (``field.header.frame_id``) and the
    covariances: the header stamp and the pose are taken, every value between two commas counted."""
    from formats.reference_trajectories import load_trajectory

    original = _trajectory(np.random.default_rng(5))
    covariance = [f"field.pose.covariance{k}" for k in range(36)]
    twist = [f"field.twist.twist.{kind}.{axis}" for kind in ("linear", "angular") for axis in "xyz"]
    header = ["%time", "field.header.seq", "field.header.stamp", "field.header.frame_id", "field.child_frame_id",
              *(f"field.pose.pose.position.{a}" for a in "xyz"), *(f"field.pose.pose.orientation.{a}" for a in "xyzw"),
              *covariance, *twist]  # fmt: skip
    rows = [",".join(header)]
    for k, (stamp, p, q) in enumerate(zip(original.stamps_ns, original.positions, original.quats_xyzw, strict=True)):
        received = int(stamp) + 40_000_000  # 40 ms after the stamp: the wrong clock by four matching windows
        rows.append(",".join([str(received), str(k), str(int(stamp)), "", "", *map(repr, p.tolist()),
                              *map(repr, q.tolist()), *["0.0"] * 42]))  # fmt: skip
    path = tmp_path / "odom.csv"
    path.write_text("\n".join(rows) + "\n")
    assert detect_format(path) is TrajectoryFormat.NAMED_COLUMNS
    _assert_same(load_trajectory(path), original)


@pytest.mark.parametrize(("seconds", "nanoseconds"), [("header.stamp.secs", "header.stamp.nsecs"),
                                                     ("header.stamp.sec", "header.stamp.nanosec")])  # fmt: skip
def test_a_stamp_split_in_seconds_and_nanoseconds_is_joined(tmp_path: Path, seconds: str, nanoseconds: str) -> None:
    """bagpy's CSV of a ROS 1 bag topic (and such CSVs of ROS 2 topics): a receive ``Time``, the header
    stamp split in whole seconds and nanoseconds, tuples quoted with their commas. The seconds column
    alone was taken for the stamp (every pose of a second at one stamp: 761 of 788 'repeated', ATE
    0.173 m against 0.013 m), and a quoted covariance tuple counted as several values."""
    from formats.reference_trajectories import load_trajectory

    original = _trajectory(np.random.default_rng(8))
    header = ["Time", "header.seq", seconds, nanoseconds, "header.frame_id", "child_frame_id",
              *(f"pose.pose.position.{a}" for a in "xyz"), *(f"pose.pose.orientation.{a}" for a in "xyzw"),
              "pose.covariance", "twist.twist.linear.x"]  # fmt: skip
    rows = [",".join(header)]
    for k, (stamp, p, q) in enumerate(zip(original.stamps_ns, original.positions, original.quats_xyzw, strict=True)):
        received = f"{(int(stamp) + 40_000_000) * 1e-9:.9f}"
        rows.append(",".join([received, str(k), str(int(stamp) // 10**9), str(int(stamp) % 10**9), "odom", "base",
                              *map(repr, p.tolist()), *map(repr, q.tolist()), '"(0.0, 0.0, 0.0)"', "0.1"]))  # fmt: skip
    path = tmp_path / "_odom.csv"
    path.write_text("\n".join(rows) + "\n")
    _assert_same(load_trajectory(path), original)


def test_a_trailing_comma_on_every_named_row_is_no_value(tmp_path: Path) -> None:
    from formats.reference_trajectories import load_trajectory

    original = _trajectory(np.random.default_rng(6))
    for name, header in (
        ("bare.csv", "timestamp,x,y,z,qw,qx,qy,qz,vx"),
        ("ended.csv", "timestamp,x,y,z,qw,qx,qy,qz,vx,"),
    ):
        path = tmp_path / name
        text = _columns_text(original, header, "wxyz").replace("\n", ",0.5,\n")
        path.write_text(text.replace(header + ",0.5,", header, 1))  # every row ends with a comma, the header as named
        _assert_same(load_trajectory(path), original)


@pytest.mark.parametrize("encoding", ["utf-8", "utf-16"])
def test_text_beyond_ascii_in_any_place_and_utf16_files_are_read(tmp_path: Path, encoding: str) -> None:
    """Comments beyond ASCII, one character of which straddles the 64 KiB that format detection reads
    (the detection found "not a text file with poses"), and UTF-16 with its BOM (Windows PowerShell's
    ``>``), which was refused the same way."""
    from formats.reference_trajectories import load_trajectory

    original = _trajectory(np.random.default_rng(7), n=1200)
    body = []
    for k, (stamp, p, q) in enumerate(zip(original.stamps_ns, original.positions, original.quats_xyzw, strict=True)):
        if k % 20 == 0:
            body.append(f"# Schlüsselbild {k}")
        body.append(" ".join([format_stamp(int(stamp)), *map(repr, p.tolist()), *map(repr, q.tolist())]))
    text = "\n".join(body) + "\n"
    if encoding == "utf-8":
        data = text.encode()
        last = data.rfind("ü".encode(), 0, 1 << 16)
        assert last > 0 and len(data) > 1 << 16
        text = "#" + "x" * ((1 << 16) - 3 - last) + "\n" + text  # an "ü" over the 64 KiB boundary
        data = text.encode()
        assert data[(1 << 16) - 1 : (1 << 16) + 1] == "ü".encode()
    else:
        data = text.encode("utf-16")
    path = tmp_path / "estimate.txt"
    path.write_bytes(data)
    assert detect_format(path) is TrajectoryFormat.TUM
    _assert_same(load_trajectory(path), original)


def test_a_trajectory_without_orientation_is_read_with_the_identity_as_evo_does(
    tmp_path: Path, fr1: dict[str, list[str]], caplog: pytest.LogCaptureFixture
) -> None:
    """Positions only, every quaternion 0 0 0 0 (a total station's or GNSS track written as TUM): refused
    as "zero quaternion"; evo reads the zeros as the identity and gives the translation figures."""
    from evo.core import sync
    from evo.core.metrics import PoseRelation
    from evo.main_ape import ape
    from evo.tools import file_interface

    from formats.reference_trajectories import load_trajectory
    from relpoint.evaluation import EvaluationSettings, evaluate_trajectory

    estimate = tmp_path / "positions.txt"
    estimate.write_text("".join(" ".join([*row.split()[:4], "0", "0", "0", "0"]) + "\n" for row in fr1["est"]))
    with caplog.at_level(logging.WARNING):
        trajectory = load_trajectory(estimate)
    assert "every quaternion is zero" in caplog.text
    np.testing.assert_array_equal(trajectory.quats_xyzw, np.tile([0.0, 0.0, 0.0, 1.0], (len(fr1["est"]), 1)))
    reference_path = shared_data(FR1) / GT
    result = evaluate_trajectory(load_trajectory(reference_path), trajectory, EvaluationSettings(align="se3"))
    ref, est = sync.associate_trajectories(
        file_interface.read_tum_trajectory_file(reference_path), file_interface.read_tum_trajectory_file(estimate)
    )
    expected = ape(ref, est, PoseRelation.translation_part, align=True).stats
    assert result.summary["ate_rmse"] == pytest.approx(expected["rmse"], rel=1e-9)
    assert expected["rmse"] == pytest.approx(0.013470, abs=1e-6)  # REFERENCE.md's figure: the rotations do not enter
