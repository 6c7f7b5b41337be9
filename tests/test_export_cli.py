"""``relpoint export``: round trips from logs, run directories, PLY maps and ROS 2 bags; bad combinations."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from plyfile import PlyData
from scipy.spatial.transform import Rotation

from formats.log import LogReader
from formats.ply import ply_comment, read_ply, write_ply
from formats.reference_trajectories import load_ground_truth_landmarks
from formats.tables import read_map_csv, write_map_csv
from formats.trajectory_files import read_kitti, read_tum
from relpoint._open3d import open3d
from relpoint.types import LandmarkMap
from relpoint_cli.main import cli
from tests.conftest import shared_data


def invoke(*args: str | Path) -> tuple[int, str, str]:
    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result.exit_code, result.stdout, result.stderr


def export_ok(*args: str | Path) -> str:
    code, out, err = invoke("export", *args)
    assert code == 0, err
    return out


def assert_one_error_line(err: str, fragment: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("relpoint: error: ") and fragment in lines[0], err


@pytest.fixture(scope="module")
def run_dir(small_log: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("export") / "ekf"
    code, _, err = invoke("run", small_log, "--estimator", "ekf", "-o", out)
    assert code == 0, err
    return out


def read_csv_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    with path.open(newline="") as stream:
        rows = list(csv.reader(stream))
    return rows[0], rows[1:]


# --- trajectories ------------------------------------------------------------------------------------------


def test_log_ground_truth_to_tum_equals_the_logs_poses(small_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "gt.tum"
    assert "120 poses" in export_ok(small_log, "-o", out)
    poses = [record.value for record in LogReader(small_log).records(["ground_truth_pose"])]
    exported = read_tum(out)
    assert len(poses) == len(exported) == 120
    np.testing.assert_array_equal(exported.stamps_ns, [p.stamp_ns for p in poses])
    np.testing.assert_array_equal(exported.positions, [p.position for p in poses])  # repr floats: exact
    # Trajectory renormalises quaternions, which may move their last bit
    np.testing.assert_allclose(exported.quats_xyzw, [p.quat_xyzw for p in poses], rtol=0, atol=1e-15)


def test_run_directory_to_kitti_with_times(run_dir: Path, tmp_path: Path) -> None:
    out, times = tmp_path / "est.kitti", tmp_path / "times.txt"
    export_ok(run_dir, "-o", out, "--out-times", times)
    estimate = read_tum(run_dir / "trajectory.tum")
    exported = read_kitti(out, times)
    np.testing.assert_array_equal(exported.stamps_ns, estimate.stamps_ns)
    np.testing.assert_array_equal(exported.positions, estimate.positions)
    np.testing.assert_allclose(exported.matrices(), estimate.matrices(), atol=1e-12)
    # without --out-times the poses are stamped 0, 1, 2 ... s, and the KITTI file reads back the same poses
    export_ok(run_dir, "-o", tmp_path / "plain.kitti")
    plain = read_kitti(tmp_path / "plain.kitti")
    np.testing.assert_array_equal(plain.stamps_ns, np.arange(len(estimate)) * 1_000_000_000)
    np.testing.assert_allclose(plain.matrices(), estimate.matrices(), atol=1e-12)


def test_run_directory_to_csv(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "est.csv"
    export_ok(run_dir, "-o", out)
    header, rows = read_csv_rows(out)
    assert header == ["iteration", "timestamp", "x", "y", "z", "qx", "qy", "qz", "qw"]
    estimate = read_tum(run_dir / "trajectory.tum")
    values = np.array([[float(v) for v in row] for row in rows])
    assert len(values) == len(estimate)
    np.testing.assert_array_equal(values[:, 0], np.arange(len(estimate)))
    np.testing.assert_allclose(values[:, 1], estimate.stamps_ns * 1e-9, rtol=0, atol=1e-9)
    np.testing.assert_allclose(values[:, 2:5], estimate.positions, rtol=0, atol=1e-9)
    np.testing.assert_allclose(values[:, 5:], estimate.quats_xyzw, rtol=0, atol=1e-9)


def test_relpoints_own_trajectory_csv_reads_back(run_dir: Path, tmp_path: Path) -> None:
    from formats.reference_trajectories import load_trajectory

    exported = tmp_path / "est.csv"
    export_ok(run_dir, "-o", exported)
    estimate = read_tum(run_dir / "trajectory.tum")
    for path in (exported, run_dir / "trajectory.csv"):
        again = load_trajectory(path)
        np.testing.assert_array_equal(again.stamps_ns, estimate.stamps_ns)
        np.testing.assert_allclose(again.positions, estimate.positions, rtol=0, atol=1e-9)
        np.testing.assert_allclose(again.quats_xyzw, estimate.quats_xyzw, rtol=0, atol=1e-9)
    export_ok(exported, "-o", tmp_path / "again.tum")
    assert len(read_tum(tmp_path / "again.tum")) == len(estimate)


def test_tum_file_to_kitti_and_back_through_times(run_dir: Path, tmp_path: Path) -> None:
    kitti, times = tmp_path / "a.kitti", tmp_path / "a_times.txt"
    export_ok(run_dir / "trajectory.tum", "-o", kitti, "--out-times", times)
    export_ok(kitti, "--times", times, "-o", tmp_path / "b.tum")
    before, after = read_tum(run_dir / "trajectory.tum"), read_tum(tmp_path / "b.tum")
    np.testing.assert_array_equal(after.stamps_ns, before.stamps_ns)
    np.testing.assert_array_equal(after.positions, before.positions)
    np.testing.assert_allclose(after.matrices(), before.matrices(), atol=1e-12)


def test_nav2_bag_odom_to_tum(tmp_path: Path) -> None:
    bag = shared_data("ros2-bags", "nav2_turtlebot.mcap")
    out = tmp_path / "odom.txt"
    assert "2639 poses" in export_ok(bag, "--topic", "/odom", "-o", out)
    odom = read_tum(out)
    assert len(odom) == 2639
    assert np.all(np.diff(odom.stamps_ns) > 0)
    np.testing.assert_allclose(np.linalg.norm(odom.quats_xyzw, axis=1), 1.0, atol=1e-6)
    # a turtlebot on the floor: planar odometry, rotation about z only
    assert np.abs(odom.positions[:, 2]).max() < 1e-6
    np.testing.assert_allclose(Rotation.from_quat(odom.quats_xyzw).as_rotvec()[:, :2], 0.0, atol=1e-6)
    # the first message, decoded independently of the export path
    _, _, _, first = next(LogReader(bag).messages(["/odom"]))
    stamp = first.header.stamp.sec * 1_000_000_000 + first.header.stamp.nanosec
    p = first.pose.pose.position
    assert odom.stamps_ns[0] == stamp
    np.testing.assert_array_equal(odom.positions[0], [p.x, p.y, p.z])


def test_trajectories_export_as_ply_points_with_their_stamps_and_rotations(tmp_path: Path) -> None:
    """A bag topic, a TF chain and a trajectory file as PLY, a point per pose: `export --topic /odom -o
    odom.ply` was a usage error ("select a trajectory, not landmarks"), and a TUM file to PLY an input
    error ("landmarks come from a relpoint log")."""
    bag = shared_data("ros2-bags", "nav2_turtlebot.mcap")
    export_ok(bag, "--topic", "/odom", "-o", tmp_path / "odom.tum")
    odom = read_tum(tmp_path / "odom.tum")
    sources = {"topic": [bag, "--topic", "/odom"], "file": [tmp_path / "odom.tum"]}
    for name, source in sources.items():
        out = tmp_path / f"{name}.ply"
        assert "2639 poses" in export_ok(*source, "-o", out)
        cloud = open3d().io.read_point_cloud(str(out))
        np.testing.assert_array_equal(np.asarray(cloud.points), odom.positions)
        vertices = read_ply(out)
        assert vertices.dtype.names == ("x", "y", "z", "timestamp", "qx", "qy", "qz", "qw")
        np.testing.assert_array_equal(vertices["timestamp"], odom.stamps_ns * 1e-9)
        quats = np.column_stack([vertices[a] for a in ("qx", "qy", "qz", "qw")])
        np.testing.assert_allclose(quats, odom.quats_xyzw, rtol=0, atol=1e-15)  # renormalised once more on reading
    assert "2611 poses" in export_ok(bag, "--parent", "map", "--child", "base_footprint", "-o", tmp_path / "tf.ply")
    assert len(read_ply(tmp_path / "tf.ply")) == 2611


# --- landmarks and maps ------------------------------------------------------------------------------------


def test_log_ground_truth_landmarks_to_ply(small_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "truth.ply"
    export_ok(small_log, "-o", out)  # PLY from a log: its ground-truth landmarks
    truth = load_ground_truth_landmarks(small_log)
    assert truth is not None
    assert out.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    cloud = open3d().io.read_point_cloud(str(out))
    assert len(cloud.points) == len(truth.ids) > 0
    np.testing.assert_allclose(np.asarray(cloud.points), truth.positions, rtol=0, atol=1e-12)
    vertices = read_ply(out)
    np.testing.assert_array_equal(vertices["gt_id"], truth.ids)
    np.testing.assert_array_equal(vertices["dynamic"].astype(bool), truth.dynamic)


def test_run_directory_landmarks_to_ply_and_csv(run_dir: Path, tmp_path: Path) -> None:
    landmarks = read_map_csv(run_dir / "map.csv")
    assert len(landmarks) > 0
    export_ok(run_dir, "--what", "landmarks", "-o", tmp_path / "lm.ply")
    cloud = open3d().io.read_point_cloud(str(tmp_path / "lm.ply"))
    assert len(cloud.points) == len(landmarks)
    np.testing.assert_allclose(np.asarray(cloud.points), landmarks.positions, rtol=0, atol=1e-4)  # float32
    vertices = read_ply(tmp_path / "lm.ply")
    np.testing.assert_array_equal(vertices["gt_id"], landmarks.gt_id)
    np.testing.assert_array_equal(vertices["observations"], landmarks.observations)
    export_ok(run_dir, "--what", "landmarks", "-o", tmp_path / "lm.csv")  # a map.csv again
    again = read_map_csv(tmp_path / "lm.csv")
    np.testing.assert_array_equal(again.positions, landmarks.positions)
    np.testing.assert_array_equal(again.gt_id, landmarks.gt_id)


def test_a_source_named_in_other_characters_or_lines_is_exported_with_an_ascii_comment(
    small_log: Path, run_dir: Path, tmp_path: Path
) -> None:
    # PLY comments are one line of ASCII, and the source's name goes into one
    log = tmp_path / "jos\u00e9" / "caf\u00e9\n2.mcap"
    log.parent.mkdir()
    shutil.copyfile(small_log, log)
    run = tmp_path / "jos\u00e9" / "run_\u00e9\u2013\n"
    shutil.copytree(run_dir, run)
    export_ok(log, "-o", tmp_path / "lm.ply")
    export_ok(run, "-o", tmp_path / "map.ply")
    export_ok(run, "--what", "landmarks", "-o", tmp_path / "run_lm.ply")
    assert "ground-truth landmarks of caf\\xe9\\n2.mcap, frame world" in PlyData.read(tmp_path / "lm.ply").comments
    assert "relpoint map from run_\\xe9\\u2013\\n/map.ply" in PlyData.read(tmp_path / "map.ply").comments
    assert len(read_ply(tmp_path / "run_lm.ply")) == len(read_map_csv(run_dir / "map.csv"))
    assert ply_comment("a\\b\tc\r\x01\U0001f600") == "a\\b\\tc\\r\\x01\\U0001f600"


def dense_cloud(n: int, rng: np.random.Generator) -> np.ndarray:
    vertices = np.empty(
        n,
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
               ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("weight", "<f4")],
    )  # fmt: skip
    points = rng.uniform(-5.0, 5.0, size=(n, 3))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colours = rng.integers(0, 256, size=(n, 3))
    for names, values in (
        (("x", "y", "z"), points),
        (("nx", "ny", "nz"), normals),
        (("red", "green", "blue"), colours),
    ):
        for k, name in enumerate(names):
            vertices[name] = values[:, k]
    vertices["weight"] = rng.uniform(0.0, 30.0, size=n)
    return vertices


def test_dense_map_to_ply_and_csv_keeps_every_property(tmp_path: Path) -> None:
    run = tmp_path / "dense_run"
    run.mkdir()
    cloud = dense_cloud(500, np.random.default_rng(7))
    write_ply(run / "map.ply", cloud, comments=["dense map"])
    export_ok(run, "-o", tmp_path / "cloud.ply")  # PLY from a run directory: its map.ply
    back = read_ply(tmp_path / "cloud.ply")
    assert back.dtype.names == cloud.dtype.names
    for name in cloud.dtype.names:
        np.testing.assert_array_equal(back[name], cloud[name])
    o3d_cloud = open3d().io.read_point_cloud(str(tmp_path / "cloud.ply"))
    assert o3d_cloud.has_normals() and o3d_cloud.has_colors() and len(o3d_cloud.points) == 500
    np.testing.assert_allclose(np.asarray(o3d_cloud.colors)[:, 0], cloud["red"] / 255.0, atol=1e-9)

    export_ok(run, "--what", "map", "-o", tmp_path / "cloud.csv")
    header, rows = read_csv_rows(tmp_path / "cloud.csv")
    assert tuple(header) == cloud.dtype.names and len(rows) == 500
    values = np.array(rows, dtype=np.float64)
    for k, name in enumerate(header):  # float32 written with 9 significant digits: exact after the cast back
        np.testing.assert_array_equal(values[:, k].astype(cloud.dtype[name]), cloud[name])


# --- bad input -----------------------------------------------------------------------------------------------


@pytest.fixture()
def empty_run(tmp_path: Path) -> Path:
    run = tmp_path / "empty_run"
    run.mkdir()
    write_map_csv(run / "map.csv", LandmarkMap.empty())
    return run


@pytest.mark.parametrize(
    ("source", "args", "code", "fragment"),
    [
        ("run", ["-o", "x.dat"], 2, "cannot tell the output format"),
        ("run", ["-o", "x.ply", "--what", "trajectory", "--out-times", "t.txt"], 2, "only to KITTI"),
        ("run", ["-o", "x.tum", "--what", "landmarks"], 2, "landmarks cannot be written as tum"),
        ("run", ["-o", "x.txt", "--format", "bogus"], 2, "bogus"),
        ("log", ["-o", "x.ply", "--what", "landmarks", "--topic", "/odom"], 2, "select a trajectory"),
        ("run", ["-o", "x.csv", "--out-times", "t.txt"], 2, "only to KITTI"),
        ("run", ["-o", "DIR"], 2, "is a directory"),
        ("missing", ["-o", "x.tum"], 3, "no such file or directory"),
        ("log", ["-o", "x.ply", "--what", "map"], 3, "a log holds no map"),
        ("log", ["-o", "x.tum", "--topic", "/points"], 3, "not a pose type"),
        ("tum", ["-o", "x.ply", "--what", "landmarks"], 3, "landmarks come from a relpoint log or a run directory"),
        ("empty", ["-o", "x.ply", "--what", "landmarks"], 3, "no landmarks to export"),
        ("empty", ["-o", "x.csv", "--what", "landmarks"], 3, "no landmarks to export"),
    ],
)  # fmt: skip
def test_bad_requests_are_one_line_errors(
    small_log: Path, run_dir: Path, empty_run: Path, tmp_path: Path,
    source: str, args: list[str], code: int, fragment: str,
) -> None:  # fmt: skip
    sources = {
        "run": run_dir,
        "log": small_log,
        "missing": tmp_path / "nope.mcap",
        "tum": run_dir / "trajectory.tum",
        "empty": empty_run,
    }
    args = [str(tmp_path / a) if a.endswith((".dat", ".ply", ".tum", ".txt", ".csv")) else a for a in args]
    args = [str(tmp_path) if a == "DIR" else a for a in args]
    exit_code, _, err = invoke("export", sources[source], *args)
    assert exit_code == code, err
    assert_one_error_line(err, fragment)
    assert not [p for p in tmp_path.iterdir() if p.is_file()]  # nothing written, no temporaries left


def test_map_csv_keeps_the_contracts_columns_and_map_ply_carries_the_first_iterations(tmp_path: Path) -> None:
    from formats.ply import landmark_vertices, read_ply, write_ply

    landmarks = LandmarkMap(
        np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]), np.array([3, 1]), np.array([False, True]), np.array([7, -1]),
        first_iteration=np.array([0, 12]),
    )  # fmt: skip
    write_map_csv(tmp_path / "map.csv", landmarks)
    assert (tmp_path / "map.csv").read_text().splitlines()[0] == "landmark,x,y,z,observations,dynamic,gt_id"
    assert read_map_csv(tmp_path / "map.csv").first_iteration is None
    write_ply(tmp_path / "map.ply", landmark_vertices(landmarks))
    assert read_ply(tmp_path / "map.ply")["first_iteration"].tolist() == [0, 12]
    # Another tool's map.csv with the column is read with it.
    text = (tmp_path / "map.csv").read_text().splitlines()
    lines = [text[0] + ",first_iteration", text[1] + ",0", text[2] + ",12"]
    (tmp_path / "other.csv").write_text("\n".join(lines) + "\n")
    assert read_map_csv(tmp_path / "other.csv").first_iteration.tolist() == [0, 12]


def test_an_unusable_map_csv_is_an_input_error_naming_the_line(run_dir: Path, tmp_path: Path, small_log: Path) -> None:
    import shutil

    broken = tmp_path / "run"
    shutil.copytree(run_dir, broken)
    lines = (broken / "map.csv").read_text().splitlines()
    (broken / "map.csv").write_text("\n".join([*lines[:5], lines[5][:8]]) + "\n")
    code, _, err = invoke("evaluate", broken, "-r", small_log)
    assert code == 3 and "map.csv:6: malformed row" in err, err
    (broken / "map.csv").unlink()
    (broken / "map.csv").mkdir()
    code, _, err = invoke("evaluate", broken, "-r", small_log)
    assert code == 3 and "map.csv: not a file" in err, err
