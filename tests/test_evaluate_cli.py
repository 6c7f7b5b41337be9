"""``relpoint evaluate``: evo parity through the CLI, ROS 2 bag and TF inputs, landmarks, outputs, gates, bad input."""

from __future__ import annotations

import copy
import csv
import json
import math
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from formats.log import LogReader
from formats.reference_trajectories import load_trajectory
from formats.tables import write_map_csv
from formats.trajectory_files import write_tum
from relpoint.types import LandmarkMap, Trajectory
from relpoint_app.evaluator import check_gates
from relpoint_cli.main import cli
from tests.conftest import shared_data

FR1 = ("evo-fr1xyz",)
BAG = ("ros2-bags", "nav2_turtlebot.mcap")


def invoke(*args: str | Path) -> tuple[int, str, str]:
    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result.exit_code, result.stdout, result.stderr


def summary_of(tmp_path: Path, *args: str | Path) -> dict[str, float]:
    out = tmp_path / "summary.json"
    code, _, err = invoke("evaluate", *args, "--json", out)
    assert code == 0, err
    return json.loads(out.read_text())["summary"]


def assert_one_error_line(err: str, fragment: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("relpoint: error: ") and fragment in lines[0], err


# --- evo parity (../shared/data/evo-fr1xyz/REFERENCE.md, evo 1.38.1) ------------------------------------


@pytest.mark.parametrize(
    ("estimate", "args", "expected"),
    [
        ("rgbdslam", ["--align", "se3"], {"ate_rmse": 0.013470, "ate_mean": 0.012024, "ate_median": 0.011183,
                                          "ate_max": 0.034760, "ate_std": 0.006071}),
        ("rgbdslam", [], {"ate_rmse": 0.020079, "ate_mean": 0.018063, "ate_max": 0.043289,
                          "rpe_trans_rmse": 0.005764, "rpe_trans_mean": 0.004816, "rpe_trans_max": 0.020866,
                          "rpe_rot_deg_rmse": 0.353613, "rpe_rot_deg_mean": 0.300307}),
        ("ORB_kf_mono", ["--align", "sim3"], {"ate_rmse": 0.009755, "ate_mean": 0.008219, "ate_max": 0.027924}),
    ],
)  # fmt: skip
def test_tum_pair_matches_reference_md(
    tmp_path: Path, estimate: str, args: list[str], expected: dict[str, float]
) -> None:
    data = shared_data(*FR1)
    summary = summary_of(
        tmp_path, data / f"freiburg1_xyz-{estimate}.txt", "--reference", data / "freiburg1_xyz-groundtruth.txt", *args
    )
    for key, value in expected.items():
        assert summary[key] == pytest.approx(value, abs=1e-6), key


def test_table_on_stdout(tmp_path: Path) -> None:
    data = shared_data(*FR1)
    code, out, err = invoke(
        "evaluate", data / "freiburg1_xyz-rgbdslam.txt", "-r", data / "freiburg1_xyz-groundtruth.txt", "--align", "se3"
    )
    assert code == 0, err
    ate_row = next(line for line in out.splitlines() if line.startswith("APE translation (m)"))
    assert ate_row.split()[3:5] == ["0.013470", "0.012024"]  # rmse, mean
    assert "matched_poses    785" in out


def test_json_dash_writes_the_summary_to_stdout_and_the_table_to_stderr(tmp_path: Path, monkeypatch) -> None:
    data = shared_data(*FR1)
    monkeypatch.chdir(tmp_path)
    code, out, err = invoke("evaluate", data / "freiburg1_xyz-rgbdslam.txt", "-r", data / "freiburg1_xyz-groundtruth.txt",
                            "--align", "se3", "--json", "-")  # fmt: skip
    assert code == 0, err
    assert json.loads(out)["summary"]["ate_rmse"] == pytest.approx(0.013470, abs=1e-6)
    assert "APE translation (m)" in err
    assert list(tmp_path.iterdir()) == []  # no file named "-"


def test_csv_dash_writes_the_errors_to_stdout_and_the_table_to_stderr(tmp_path: Path, monkeypatch) -> None:
    data = shared_data(*FR1)
    monkeypatch.chdir(tmp_path)
    args = ("evaluate", data / "freiburg1_xyz-rgbdslam.txt", "-r", data / "freiburg1_xyz-groundtruth.txt")
    code, out, err = invoke(*args, "--csv", "-")
    assert code == 0, err
    rows = list(csv.DictReader(out.splitlines()))
    assert len(rows) > 700 and float(rows[0]["ape_translation_m"]) >= 0
    assert "APE translation (m)" in err
    assert list(tmp_path.iterdir()) == []  # no file named "-"
    code, out, err = invoke(*args, "--csv", "-", "--json", "-")
    assert code == 2 and out == ""
    assert_one_error_line(err, "--json - and --csv - both name stdout")


def test_quiet_silences_the_table_on_stderr() -> None:
    data = shared_data(*FR1)
    args = ("evaluate", data / "freiburg1_xyz-rgbdslam.txt", "-r", data / "freiburg1_xyz-groundtruth.txt")
    for output in ("--json", "--csv"):
        result = CliRunner().invoke(cli, ["-q", *map(str, args), output, "-"])
        assert result.exit_code == 0 and result.stdout and result.stderr == ""


def test_a_small_overlap_is_an_error_naming_both_time_ranges(tmp_path: Path) -> None:
    data = shared_data(*FR1)
    args = ["evaluate", data / "freiburg1_xyz-rgbdslam.txt", "-r", data / "freiburg1_xyz-groundtruth.txt",
            "--t-offset", "20", "--t-max-diff", "0.02"]  # fmt: skip
    code, _, err = invoke(*args)
    assert code == 3
    assert_one_error_line(err, "poses matched")
    assert "reference 1305031098" in err and "estimate 1305031102" in err and "--min-matched 0" in err
    code, _, err = invoke(*args, "--min-matched", "0")
    assert code == 0, err


# --- ROS 2 bag written by rosbag2 -------------------------------------------------------------------------


def test_bag_odom_against_amcl_pose(tmp_path: Path) -> None:
    bag = shared_data(*BAG)
    summary = summary_of(
        tmp_path, bag, "--estimate-topic", "/odom", "--reference", bag, "--reference-topic", "/amcl_pose",
        "--align", "se3",
    )  # fmt: skip
    assert summary["reference_poses"] == 135 and summary["estimate_poses"] == 2639
    assert summary["matched_poses"] == 83
    assert all(np.isfinite(v) for k, v in summary.items() if not k.startswith("kitti_"))
    # Odometry drifts against AMCL by decimetres over the 34 m run, not metres.
    assert 0.1 < summary["ate_rmse"] < 1.0 and summary["path_length_m"] == pytest.approx(34.1, abs=0.5)
    # evo 1.38.1: `evo_ape bag2 nav2_turtlebot.mcap /amcl_pose /odom -a` prints rmse 0.512301, max 0.852349.
    assert summary["ate_rmse"] == pytest.approx(0.512301, abs=1e-6)
    assert summary["ate_max"] == pytest.approx(0.852349, abs=1e-6)


def _motion_capture_bag(path: Path) -> Trajectory:
    """A rosbag2 MCAP bag written by rosbags, as motion-capture and survey bridges record ground truth:
    ``/vicon/robot/robot`` (TransformStamped), ``/leica/position`` (PointStamped, every other stamp) and an
    estimate ``/pose`` (PoseStamped, centimetres off). Returns the true trajectory."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    from scipy.spatial.transform import Rotation

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = store.types
    n = 200
    stamps = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 20_000_000
    angle = np.linspace(0.0, 2.0 * np.pi, n)
    positions = np.column_stack([3.0 * np.cos(angle), 2.0 * np.sin(2.0 * angle), 0.3 * np.sin(angle)])
    quats = Rotation.from_euler("zyx", np.column_stack([angle, 0.1 * np.sin(angle), 0.05 * angle]).tolist()).as_quat()
    point, quaternion, vector = (types[f"geometry_msgs/msg/{t}"] for t in ("Point", "Quaternion", "Vector3"))

    def header(stamp: int, frame: str) -> object:
        time = types["builtin_interfaces/msg/Time"](sec=int(stamp) // 10**9, nanosec=int(stamp) % 10**9)
        return types["std_msgs/msg/Header"](stamp=time, frame_id=frame)

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        topics = {"/vicon/robot/robot": "TransformStamped", "/leica/position": "PointStamped", "/pose": "PoseStamped"}
        connections = {
            t: writer.add_connection(t, f"geometry_msgs/msg/{kind}", typestore=store) for t, kind in topics.items()
        }
        for k, (stamp, p, q) in enumerate(zip(stamps.tolist(), positions, quats, strict=True)):
            rotation = quaternion(x=q[0], y=q[1], z=q[2], w=q[3])
            transform = types["geometry_msgs/msg/Transform"](
                translation=vector(x=p[0], y=p[1], z=p[2]), rotation=rotation
            )
            messages = {
                "/vicon/robot/robot": types["geometry_msgs/msg/TransformStamped"](
                    header=header(stamp, "world"), child_frame_id="robot", transform=transform
                ),
                "/pose": types["geometry_msgs/msg/PoseStamped"](
                    header=header(stamp, "world"),
                    pose=types["geometry_msgs/msg/Pose"](
                        position=point(x=p[0] + 0.01 * np.sin(k), y=p[1], z=p[2]), orientation=rotation
                    ),
                ),
            }
            if k % 2 == 0:
                messages["/leica/position"] = types["geometry_msgs/msg/PointStamped"](
                    header=header(stamp, "leica"), point=point(x=p[0], y=p[1], z=p[2])
                )
            for topic, message in messages.items():
                writer.write(connections[topic], stamp, store.serialize_cdr(message, message.__msgtype__))
    return Trajectory(stamps, positions, quats)


def test_motion_capture_topics_are_read_as_evo_reads_them(tmp_path: Path) -> None:
    """TransformStamped (vicon_bridge) and PointStamped (a total station) topics were refused as "not a
    pose type"; evo 1.38 reads both (PointStamped with the identity rotation) and gives these figures."""
    from evo.core import sync
    from evo.core.metrics import PoseRelation
    from evo.core.trajectory import PoseTrajectory3D
    from evo.main_ape import ape
    from evo.tools import file_interface
    from rosbags.rosbag2 import Reader

    bag = tmp_path / "mocap"
    truth = _motion_capture_bag(bag)
    vicon = load_trajectory(bag, topic="/vicon/robot/robot")
    np.testing.assert_array_equal(vicon.stamps_ns, truth.stamps_ns)
    np.testing.assert_array_equal(vicon.positions, truth.positions)
    np.testing.assert_array_equal(vicon.quats_xyzw, truth.quats_xyzw)
    with Reader(bag) as reader:
        evo_trajectories = {t: file_interface.read_bag_trajectory(reader, t) for t in ("/vicon/robot/robot",
                                                                                      "/leica/position", "/pose")}  # fmt: skip
    for reference in ("/vicon/robot/robot", "/leica/position"):
        code, _, err = invoke("evaluate", bag, "--estimate-topic", "/pose", "-r", bag, "--reference-topic", reference,
                              "--align", "se3", "--json", tmp_path / "summary.json", "--overwrite")  # fmt: skip
        assert code == 0, err
        assert ("has no orientation" in err) == (reference == "/leica/position"), err
        summary = json.loads((tmp_path / "summary.json").read_text())["summary"]
        ref, est = sync.associate_trajectories(evo_trajectories[reference], copy.deepcopy(evo_trajectories["/pose"]))
        assert isinstance(ref, PoseTrajectory3D)
        expected = ape(ref, est, PoseRelation.translation_part, align=True).stats
        assert summary["matched_poses"] == len(ref.timestamps)
        for key in ("rmse", "mean", "median", "max"):
            assert summary[f"ate_{key}"] == pytest.approx(expected[key], rel=1e-9, abs=1e-12)
    code, _, err = invoke("export", bag, "--topic", "/leica/position", "-o", tmp_path / "leica.tum")
    assert code == 0 and "has no orientation" in err, err
    leica = load_trajectory(tmp_path / "leica.tum")
    np.testing.assert_array_equal(leica.positions, truth.positions[::2])
    np.testing.assert_array_equal(leica.quats_xyzw, np.tile([0.0, 0.0, 0.0, 1.0], (len(leica), 1)))


def test_a_pose_topic_without_header_stamps_is_timed_by_its_log_times(tmp_path: Path) -> None:
    """A publisher that never sets header.stamp: every message at stamp 0 made one pose of 600 (exported
    with exit 0, and no match against the truth); the recording times time them instead, with a warning."""
    from mcap_ros2.writer import Writer

    from formats import ros2

    full = load_trajectory(shared_data(*FR1) / "freiburg1_xyz-groundtruth.txt")
    truth = Trajectory(full.stamps_ns[:600], full.positions[:600], full.quats_xyzw[:600])
    bag = tmp_path / "unstamped.mcap"
    with bag.open("wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef(ros2.POSE_STAMPED, ros2.message_definition(ros2.POSE_STAMPED))
        for stamp, p, q in zip(truth.stamps_ns.tolist(), truth.positions, truth.quats_xyzw, strict=True):
            pose = {"position": dict(zip("xyz", p.tolist(), strict=True)),
                    "orientation": dict(zip("xyzw", q.tolist(), strict=True))}  # fmt: skip
            message = {"header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": "map"}, "pose": pose}
            writer.write_message("/pose", schema, message, log_time=stamp)
        writer.finish()
    code, _, err = invoke("export", bag, "--topic", "/pose", "-o", tmp_path / "pose.tum")
    assert code == 0 and "header.stamp is 0 (unset) in every message" in err, err
    exported = load_trajectory(tmp_path / "pose.tum")
    np.testing.assert_array_equal(exported.stamps_ns, truth.stamps_ns)
    np.testing.assert_array_equal(exported.positions, truth.positions)
    summary = summary_of(
        tmp_path, bag, "--estimate-topic", "/pose", "-r", shared_data(*FR1) / "freiburg1_xyz-groundtruth.txt"
    )
    assert summary["matched_poses"] == 600 and summary["ate_max"] == 0.0


def _line_of_poses(path: Path, topic: str, frames: list[str], w: float = 1.0) -> Path:
    """A bag of PoseStamped on ``topic``: one pose per entry of ``frames`` (its header's frame_id), 10 Hz
    from 1 s, 0.1 m apart along x, orientation ``(0, 0, 0, w)`` (0: never set)."""
    from mcap_ros2.writer import Writer

    from formats import ros2

    with path.open("wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef(ros2.POSE_STAMPED, ros2.message_definition(ros2.POSE_STAMPED))
        for k, frame in enumerate(frames):
            stamp = 1_000_000_000 + k * 100_000_000
            pose = {
                "position": {"x": 0.1 * k, "y": 0.0, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": w},
            }
            header = {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": frame}
            writer.write_message(topic, schema, {"header": header, "pose": pose}, log_time=stamp)
        writer.finish()
    return path


def test_a_pose_topic_in_several_frames_is_pointed_out(tmp_path: Path) -> None:
    """Poses of one topic in different frames (a localiser that restarted in odom) are not one trajectory;
    they were read as one without a word. The figures stay evo's (it reads them as one too)."""
    bag = _line_of_poses(tmp_path / "frames.mcap", "/pose", ["map"] * 20 + ["odom"] * 10)
    code, _, err = invoke("export", bag, "--topic", "/pose", "-o", tmp_path / "pose.tum")
    assert code == 0, err
    assert f"{bag} /pose: the poses are in 2 frames (map: 20, odom: 10)" in err, err
    assert len(load_trajectory(tmp_path / "pose.tum")) == 30


def test_an_estimate_from_a_tf_chain(tmp_path: Path) -> None:
    """A SLAM node that publishes its pose only as TF (map -> base_link) could be a reference but not an
    estimate (--parent/--child name the reference's chain). --estimate-parent/--estimate-child read it,
    and `compare` re-evaluates the saved evaluation from its inputs."""
    bag = shared_data(*BAG)
    # odom -> base_footprint is /odom's pose, published beside it: every pose matched, no error.
    summary = summary_of(tmp_path, bag, "--estimate-parent", "odom", "--estimate-child", "base_footprint",
                         "-r", bag, "--reference-topic", "/odom")  # fmt: skip
    assert summary["matched_poses"] == 2639 and summary["ate_max"] == 0.0
    # map -> base_footprint against AMCL gives what its export to a file gives.
    code, _, err = invoke("export", bag, "--parent", "map", "--child", "base_footprint", "-o", tmp_path / "tf.tum")
    assert code == 0, err
    against_amcl = ["-r", bag, "--reference-topic", "/amcl_pose", "--align", "se3"]
    from_file = summary_of(tmp_path, tmp_path / "tf.tum", *against_amcl)
    out = tmp_path / "tf.json"
    code, _, err = invoke("evaluate", bag, "--estimate-parent", "map", "--estimate-child", "base_footprint",
                          *against_amcl, "--json", out)  # fmt: skip
    assert code == 0, err
    document = json.loads(out.read_text())
    assert document["summary"]["ate_rmse"] == from_file["ate_rmse"] and from_file["matched_poses"] == 83
    assert (document["inputs"]["estimate_parent"], document["inputs"]["estimate_child"]) == ("map", "base_footprint")
    code, stdout, err = invoke("compare", out, "--format", "json")
    assert code == 0 and "cannot re-evaluate" not in err, err
    (run,) = json.loads(stdout)["runs"]
    assert "re-evaluated" in run["source"] and run["summary"]["ate_rmse"] == from_file["ate_rmse"]
    code, _, err = invoke("evaluate", bag, "--estimate-parent", "map", "-r", bag, "--reference-topic", "/amcl_pose")
    assert code == 2 and "--estimate-parent without --estimate-child" in err, err


def test_a_pose_topic_without_orientations_is_read_with_the_identity(tmp_path: Path) -> None:
    """PoseStamped messages whose orientation was never set (0 0 0 0) were all dropped: 'no valid poses'."""
    bag = _line_of_poses(tmp_path / "positions.mcap", "/gnss", ["map"] * 30, w=0.0)
    code, _, err = invoke("export", bag, "--topic", "/gnss", "-o", tmp_path / "gnss.tum")
    assert code == 0 and "every quaternion is zero" in err, err
    gnss = load_trajectory(tmp_path / "gnss.tum")
    np.testing.assert_array_equal(gnss.positions[:, 0], 0.1 * np.arange(30))
    np.testing.assert_array_equal(gnss.quats_xyzw, np.tile([0.0, 0.0, 0.0, 1.0], (30, 1)))


def test_a_file_of_a_rosbag2_bag_is_named_for_its_bag_directory(tmp_path: Path) -> None:
    """The .db3 or metadata.yaml of a rosbag2 bag given instead of its directory: evaluate said "is not an
    MCAP file; topics and TF frames apply only to MCAP inputs" (or, without a topic, "unknown trajectory
    format"), where `info` names the directory to give."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = store.types
    bag = tmp_path / "recording"
    with Writer(bag, version=9) as writer:  # the sqlite3 storage, rosbag2's former default
        connection = writer.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=store)
        for k in range(5):
            header = types["std_msgs/msg/Header"](
                stamp=types["builtin_interfaces/msg/Time"](sec=k, nanosec=0), frame_id="map"
            )
            pose = types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](x=float(k), y=0.0, z=0.0),
                orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            )
            message = types["geometry_msgs/msg/PoseStamped"](header=header, pose=pose)
            writer.write(connection, k * 10**9, store.serialize_cdr(message, message.__msgtype__))
    (storage,) = bag.glob("*.db3")
    for part, kind in ((storage, "sqlite3 storage file"), (bag / "metadata.yaml", "metadata file")):
        for args in (["evaluate", part, "--estimate-topic", "/pose", "-r", bag, "--reference-topic", "/pose"],
                     ["evaluate", bag, "--estimate-topic", "/pose", "-r", part],
                     ["export", part, "-o", tmp_path / "pose.tum"]):  # fmt: skip
            code, _, err = invoke(*args)
            assert code == 3, err
            assert_one_error_line(
                err, f"{part} is a rosbag2 {kind}, not a log on its own; give the bag directory {bag}"
            )
    assert (
        summary_of(tmp_path, bag, "--estimate-topic", "/pose", "-r", bag, "--reference-topic", "/pose")["ate_max"] == 0
    )


def test_a_namespaced_tf_topic_takes_its_own_static_transforms(tmp_path: Path) -> None:
    """A robot under a namespace records /robot1/tf and /robot1/tf_static (Nav2's multi-robot remapping);
    the chain read /tf_static only, so a frame on the robot's static tree was 'not in the TF tree'."""
    from mcap_ros2.writer import Writer

    from formats import ros2

    def transform(stamp: int, parent: str, child: str, x: float) -> dict:
        return {"header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": parent},
                "child_frame_id": child,
                "transform": {"translation": {"x": x, "y": 0.0, "z": 0.0},
                              "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}  # fmt: skip

    bag = tmp_path / "robots.mcap"
    with bag.open("wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef(ros2.TF_MESSAGE, ros2.message_definition(ros2.TF_MESSAGE))
        start = 1_000_000_000
        writer.write_message("/robot1/tf_static", schema, {"transforms": [transform(start, "base_link", "laser", 0.25)]},
                             log_time=start)  # fmt: skip
        for k in range(20):
            stamp = start + k * 100_000_000
            writer.write_message("/robot1/tf", schema, {"transforms": [transform(stamp, "odom", "base_link", 0.1 * k)]},
                                 log_time=stamp)  # fmt: skip
        writer.finish()
    trajectory = load_trajectory(bag, topic="/robot1/tf", parent="odom", child="laser")
    np.testing.assert_allclose(trajectory.positions[:, 0], 0.1 * np.arange(20) + 0.25, rtol=0, atol=1e-12)


def test_a_tf_chain_interpolates_its_slower_edges_as_tf2_does(tmp_path: Path) -> None:
    """map -> odom at 2 Hz (a localiser's correction, turning and moving) under odom -> base_link at 20 Hz:
    each pose takes map -> odom interpolated at its stamp (tf2's lookup), not the latest one before it,
    which lagged the chain by up to one correction (here up to 0.45 m and 2.6 degrees)."""
    from mcap_ros2.writer import Writer
    from scipy.spatial.transform import Rotation

    from formats import ros2

    def transform(stamp: int, parent: str, child: str, xyz: tuple, yaw: float) -> dict:
        x, y, z, w = Rotation.from_euler("z", yaw).as_quat()
        return {"header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": parent},
                "child_frame_id": child,
                "transform": {"translation": dict(zip("xyz", xyz, strict=True)), "rotation": {"x": x, "y": y, "z": z, "w": w}}}  # fmt: skip

    def correction(t: float) -> tuple[tuple, float]:  # map -> odom: 1 m/s along x, 0.1 rad/s
        return (1.0 * t, 0.0, 0.0), 0.1 * t

    bag = tmp_path / "localised.mcap"
    start = 1_700_000_000_000_000_000
    with bag.open("wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef(ros2.TF_MESSAGE, ros2.message_definition(ros2.TF_MESSAGE))
        for k in range(101):  # 5 s at 20 Hz, map -> odom every 10th
            stamp = start + k * 50_000_000
            transforms = [transform(stamp, "odom", "base_link", (0.0, 0.2 * k * 0.05, 0.0), 0.0)]
            if k % 10 == 0:
                transforms.append(transform(stamp, "map", "odom", *correction(k * 0.05)))
            writer.write_message("/tf", schema, {"transforms": transforms}, log_time=stamp)
        writer.finish()
    trajectory = load_trajectory(bag, parent="map", child="base_link")
    t = (trajectory.stamps_ns - start) / 1e9
    assert len(t) == 101
    shift, yaw = np.array([correction(s)[0] for s in t]), 0.1 * t
    rotation = Rotation.from_euler("z", yaw[:, None])
    expected = shift + rotation.apply(np.column_stack([np.zeros_like(t), 0.2 * t, np.zeros_like(t)]))
    np.testing.assert_allclose(trajectory.positions, expected, rtol=0, atol=1e-9)
    angle = (Rotation.from_quat(trajectory.quats_xyzw) * rotation.inv()).magnitude()
    assert angle.max() < 1e-9


def test_odometry_with_velocities_only_is_no_trajectory(tmp_path: Path) -> None:
    """A relpoint log's /odom carries velocities, its pose fields the identity: exported as 50 poses at the
    origin and evaluated as a robot standing still, without a word."""
    log = tmp_path / "odometry.mcap"
    code, _, err = invoke("simulate", "-o", log, "--iterations", "50", "--odometry-noise", "0.05", "--seed", "2")
    assert code == 0, err
    code, _, err = invoke("export", log, "--topic", "/odom", "-o", tmp_path / "odom.tum")
    assert code == 3
    assert_one_error_line(err, f"{log} /odom: every message holds the same pose while its twist moves")
    code, _, err = invoke("evaluate", log, "--estimate-topic", "/odom", "-r", log)
    assert code == 3 and "odometry with velocities only" in err, err
    assert not (tmp_path / "odom.tum").exists()


def test_trajectories_in_different_frames_are_pointed_out() -> None:
    bag = shared_data(*BAG)
    args = ["evaluate", bag, "--estimate-topic", "/odom", "--reference", bag, "--reference-topic", "/amcl_pose"]
    code, _, err = invoke(*args)
    assert code == 0 and "look to be in different frames" in err and "--align se3" in err
    code, _, err = invoke(*args, "--align", "se3")
    assert code == 0 and "different frames" not in err
    fr1 = shared_data(*FR1)
    code, _, err = invoke("evaluate", fr1 / "freiburg1_xyz-rgbdslam.txt", "-r", fr1 / "freiburg1_xyz-groundtruth.txt")
    assert code == 0 and "different frames" not in err


def test_tf_chain_reference(tmp_path: Path) -> None:
    bag = shared_data(*BAG)
    # odom -> base_footprint is the transform the odometry node publishes beside /odom: identical poses.
    odom_tf = load_trajectory(bag, parent="odom", child="base_footprint")
    odom = load_trajectory(bag, topic="/odom")
    np.testing.assert_array_equal(odom_tf.stamps_ns, odom.stamps_ns)
    np.testing.assert_allclose(odom_tf.positions, odom.positions, atol=1e-9)
    # map -> odom -> base_footprint: AMCL's localisation, so /amcl_pose agrees within centimetres unaligned.
    summary = summary_of(
        tmp_path, bag, "--estimate-topic", "/amcl_pose", "--reference", bag, "--parent", "map", "--child",
        "base_footprint",
    )  # fmt: skip
    assert summary["matched_poses"] == 83 and summary["reference_poses"] > 2500
    assert summary["ate_rmse"] < 0.1 and summary["ape_rot_deg_rmse"] < 2.0
    code, _, err = invoke("evaluate", bag, "--estimate-topic", "/odom", "-r", bag, "--parent", "map", "--child", "nope")
    assert code == 3
    assert_one_error_line(err, "frame 'nope' (--child) is not in the TF tree")


# --- run directory against a relpoint log: landmarks, CSV, plots, gates ----------------------------------


@pytest.fixture()
def run_dir(tmp_path: Path, small_log: Path) -> Path:
    """A fake run output: the true trajectory shifted by 0.1 m in x, and the true landmarks with noise."""
    reader = LogReader(small_log)
    poses = [r.value for r in reader.records(["ground_truth_pose"])]
    truth = [r.value for r in reader.records(["ground_truth_landmarks"])][-1]
    rng = np.random.default_rng(7)
    out = tmp_path / "run"
    out.mkdir()
    positions = np.array([p.position for p in poses]) + np.array([0.1, 0.0, 0.0])
    write_tum(
        out / "trajectory.tum",
        Trajectory(np.array([p.stamp_ns for p in poses]), positions, np.array([p.quat_xyzw for p in poses])),
    )
    n = len(truth.ids)
    write_map_csv(
        out / "map.csv",
        LandmarkMap(truth.positions + rng.normal(0, 0.05, (n, 3)), np.full(n, 3), truth.dynamic.copy(), truth.ids),
    )
    return out


def test_run_directory_with_landmarks_csv_and_plots(tmp_path: Path, small_log: Path, run_dir: Path) -> None:
    csv_path, plots = tmp_path / "errors.csv", tmp_path / "plots"
    summary = summary_of(tmp_path, run_dir, "--reference", small_log, "--csv", csv_path, "--plot", plots)
    assert summary["matched_poses"] == 120
    assert summary["ate_rmse"] == pytest.approx(0.1, abs=1e-6)
    assert summary["lm_matched"] > 20 and summary["lm_duplicates"] == 0 and summary["lm_false"] == 0
    assert 0.03 < summary["lm_err_rmse"] < 0.15  # 3-D noise of 0.05 m per axis: rmse ~0.087 m
    with csv_path.open() as stream:
        rows = list(csv.DictReader(stream))
    assert len(rows) == 120 and float(rows[5]["ape_translation_m"]) == pytest.approx(0.1, abs=1e-6)
    assert rows[0]["rpe_translation_m"] == "" and float(rows[1]["rpe_translation_m"]) < 1e-6
    assert sorted(p.name for p in plots.iterdir()) == ["errors.png", "trajectory_side.png", "trajectory_top.png"]
    assert all((plots / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for name in ("errors.png",))


def test_an_interrupt_while_the_outputs_are_written_leaves_none_of_them(
    tmp_path: Path, small_log: Path, run_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt  # Ctrl-C after the JSON, CSV and zip were written, before the plots

    monkeypatch.setattr("relpoint_cli.evaluate.evaluation_plots", interrupted)
    out = tmp_path / "s"
    out.mkdir()
    code, _, err = invoke("evaluate", run_dir, "-r", small_log, "--json", out / "e.json", "--csv", out / "e.csv",
                          "--save-results", out / "e.zip", "--plot", out / "plots")  # fmt: skip
    assert code == 130
    assert_one_error_line(err, "interrupted; no output was written")
    assert list(out.iterdir()) == []  # no output, no temporary, no plot directory


def test_the_ground_truth_landmarks_topic_can_be_named(tmp_path: Path, small_log: Path, run_dir: Path) -> None:
    named = summary_of(tmp_path, run_dir, "--reference", small_log, "--landmarks-topic", "/ground_truth/landmarks")
    assert named["lm_matched"] > 20
    for topic, fragment in (("/mocap/landmarks", "no messages on /mocap/landmarks"),
                            ("/ground_truth/pose", "carries geometry_msgs/msg/PoseStamped")):  # fmt: skip
        code, _, err = invoke("evaluate", run_dir, "--reference", small_log, "--landmarks-topic", topic)
        assert code == 3
        assert_one_error_line(err, fragment)
    data = shared_data(*FR1)
    code, _, err = invoke("evaluate", data / "freiburg1_xyz-rgbdslam.txt", "-r", data / "freiburg1_xyz-groundtruth.txt",
                          "--landmarks-topic", "/ground_truth/landmarks")  # fmt: skip
    assert code == 3
    assert_one_error_line(err, "--landmarks-topic applies only to a log reference")


def test_a_times_file_for_a_run_directory_or_a_log_is_refused(tmp_path: Path, small_log: Path, run_dir: Path) -> None:
    missing = tmp_path / "no-such-times.txt"
    for args in (("--times", missing), ("--reference-times", missing)):
        code, _, err = invoke("evaluate", run_dir, "--reference", small_log, *args)
        assert code == 3
        assert_one_error_line(err, "a times file applies only to KITTI poses")
    code, _, err = invoke("export", run_dir, "-o", tmp_path / "e.tum", "--times", missing)
    assert code == 3
    assert_one_error_line(err, "a times file applies only to KITTI poses")
    assert not (tmp_path / "e.tum").exists()


def test_fail_above_gates(tmp_path: Path, small_log: Path, run_dir: Path) -> None:
    json_path = tmp_path / "gate.json"
    base = ("evaluate", run_dir, "-r", small_log, "--json", json_path)
    code, out, err = invoke(*base, "--fail-above", "ate_rmse=0.05", "--fail-above", "lm_err_rmse=1")
    assert code == 5
    assert_one_error_line(err, "ate_rmse=0.1 > 0.05")
    assert "APE translation" in out and json_path.exists()  # outputs are still written
    code, _, err = invoke(*base, "--fail-above", "ate_rmse=0.5", "--fail-above", "lm_err_rmse=1")
    assert code == 0, err
    # Undefined ratios are NaN and count as failing (no dynamic landmarks here: precision is undefined).
    assert json.loads(json_path.read_text())["summary"]["dyn_precision"] is None
    code, _, err = invoke(*base, "--fail-above", "dyn_precision=1")
    assert code == 5 and "dyn_precision=nan" in err
    code, _, err = invoke(*base, "--fail-above", "no_such_key=1")
    assert code == 2
    assert_one_error_line(err, "unknown summary key(s) no_such_key")
    code, _, err = invoke(*base, "--fail-above", "ate_rmse")
    assert code == 2


# --- bad input: one line, exit code 3 --------------------------------------------------------------------


def _tum(path: Path, stamps: list[float]) -> Path:
    path.write_text("".join(f"{t} {t} {0.5 * t} 0 0 0 0 1\n" for t in stamps))
    return path


def test_no_matching_stamps_says_what_would_match_them(tmp_path: Path) -> None:
    """An estimate stamped from its own start against an epoch reference, and stamps that interleave
    beyond the tolerance: the error gave the two spans and no way out."""
    ref = _tum(tmp_path / "ref.txt", [1000.0 + 0.1 * k for k in range(50)])
    relative = _tum(tmp_path / "relative.txt", [0.1 * k for k in range(50)])
    code, _, err = invoke("evaluate", relative, "-r", ref)
    assert code == 3
    assert_one_error_line(err, "they do not overlap: if both start together")
    offset = err.split("--t-offset ")[1].split()[0]
    assert float(offset) == pytest.approx(1000.0)
    assert summary_of(tmp_path, relative, "-r", ref, "--t-offset", offset)["matched_poses"] == 50
    between = _tum(tmp_path / "between.txt", [1000.05 + 0.1 * k for k in range(49)])
    code, _, err = invoke("evaluate", between, "-r", ref)
    assert code == 3
    assert_one_error_line(err, "their stamps interleave without a pair close enough: a larger --t-max-diff")


def test_bad_inputs_exit_3_with_one_line(tmp_path: Path) -> None:
    ref = _tum(tmp_path / "ref.txt", [0.0, 1.0, 2.0, 3.0, 4.0])
    unknown = tmp_path / "poses.txt"
    unknown.write_text("1 2 3 4 5\n")
    code, _, err = invoke("evaluate", unknown, "-r", ref)
    assert code == 3
    assert_one_error_line(err, "unknown trajectory format (5 values per line)")

    late = _tum(tmp_path / "late.txt", [100.0, 101.0, 102.0])
    code, _, err = invoke("evaluate", late, "-r", ref)
    assert code == 3
    assert_one_error_line(err, "no matching timestamps")

    two = _tum(tmp_path / "two.txt", [0.0, 1.0])
    code, _, err = invoke("evaluate", two, "-r", ref, "--align", "se3")
    assert code == 3
    assert_one_error_line(err, "at least 3 matched poses, got 2")

    code, _, err = invoke("evaluate", tmp_path / "missing.txt", "-r", ref)
    assert code == 3
    assert_one_error_line(err, "no such file")

    bag = shared_data(*BAG)
    code, _, err = invoke("evaluate", bag, "--estimate-topic", "/nothing", "-r", ref)
    assert code == 3
    assert_one_error_line(err, "no messages on /nothing")


@pytest.mark.parametrize("threshold", ["0", "-0.1", "nan", "inf"])
def test_a_dense_threshold_out_of_range_is_refused_before_any_work(tmp_path: Path, threshold: str) -> None:
    missing = tmp_path / "missing"  # not even read: the option is checked first
    code, _, err = invoke("evaluate", missing, "-r", missing, "--reference-cloud", missing,
                          "--dense-threshold", threshold)  # fmt: skip
    assert code == 2
    assert_one_error_line(err, "Invalid value for '--dense-threshold'")


def test_info_names_the_pose_topics_a_bag_can_be_evaluated_against() -> None:
    bag = shared_data(*BAG)
    code, out, _ = invoke("info", bag, "--json")
    assert code == 0
    document = json.loads(out)
    assert document["reference_topics"] == ["/odom", "/amcl_pose"] and document["tf_topics"] == ["/tf", "/tf_static"]
    code, out, _ = invoke("info", bag)
    assert "trajectory with --reference-topic" in out and "/amcl_pose" in out


def test_info_names_the_tf_frames_a_chain_can_join() -> None:
    """`info` said a bag has transforms but not which frames, the one thing --parent/--child need (the
    nav2 bag's robot is base_link under odom, base_footprint hangs below it statically)."""
    bag = shared_data(*BAG)
    code, out, _ = invoke("info", bag, "--json")
    assert code == 0
    edges = {(e["parent"], e["child"]): e for e in json.loads(out)["tf_edges"]["/tf"]}
    assert edges[("map", "odom")]["count"] == 921 and not edges[("map", "odom")]["static"]
    assert edges[("odom", "base_link")]["count"] == 2639
    assert edges[("base_link", "base_footprint")]["static"]
    assert len(edges) == 33  # every frame but the root, map, is a child once
    code, out, _ = invoke("info", bag)
    line = next(line for line in out.splitlines() if line.startswith("  /tf frames:"))
    assert "map -> odom (921), odom -> base_link (2639); static: base_link -> base_footprint" in line


def test_info_on_a_bag_with_an_undecodable_transform_still_describes_it(tmp_path: Path) -> None:
    from mcap.writer import Writer

    from formats import ros2

    bag = tmp_path / "broken_tf.mcap"
    with bag.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(ros2.TF_MESSAGE, "ros2msg", ros2.message_definition(ros2.TF_MESSAGE).encode())
        channel = writer.register_channel("/tf", "cdr", schema)
        writer.add_message(channel, log_time=1, data=b"\x00\x01\x00\x00\xff\xff\xff\x7f", publish_time=1)
        writer.finish()
    code, out, err = invoke("info", bag)
    assert code == 0, err
    assert "/tf: its TF tree cannot be read" in err and "tf2_msgs/msg/TFMessage" in out


def test_an_estimate_too_short_for_the_rpe_still_gets_its_ape(tmp_path: Path, small_log: Path) -> None:
    from formats.reference_trajectories import load_trajectory
    from formats.trajectory_files import write_tum

    reference = load_trajectory(small_log)
    one = tmp_path / "one.tum"
    write_tum(one, Trajectory(reference.stamps_ns[5:6], reference.positions[5:6], reference.quats_xyzw[5:6]))
    code, _, err = invoke("evaluate", one, "-r", small_log, "--json", tmp_path / "s.json")
    assert code == 0 and "no pose pairs" in err, err
    summary = json.loads((tmp_path / "s.json").read_text())["summary"]
    assert summary["matched_poses"] == 1 and summary["rpe_pairs"] == 0 and "rpe_trans_rmse" not in summary
    code, _, err = invoke("evaluate", one, "-r", small_log, "--save-rpe-results", tmp_path / "r.zip")
    assert code == 3 and "has no RPE" in err and not (tmp_path / "r.zip").exists()
    # a gate on a figure this evaluation could not measure fails (exit 5); a misspelt key is a usage error
    code, _, err = invoke("evaluate", one, "-r", small_log, "--fail-above", "rpe_trans_rmse=1")
    assert code == 5 and "rpe_trans_rmse not measured" in err, err
    code, _, err = invoke("evaluate", one, "-r", small_log, "--fail-above", "ate_rmsee=1")
    assert code == 2, err


def test_one_path_for_two_outputs_is_a_usage_error(tmp_path: Path) -> None:
    data = shared_data(*FR1)
    args = ("evaluate", data / "freiburg1_xyz-rgbdslam.txt", "-r", data / "freiburg1_xyz-groundtruth.txt")
    plots = tmp_path / "plots"
    for outputs in (
        ("--json", tmp_path / "same.json", "--csv", tmp_path / "same.json"),
        ("--save-results", tmp_path / "s.zip", "--save-rpe-results", tmp_path / "s.zip"),
        ("--json", plots / "errors.png", "--plot", plots),
    ):
        code, _, err = invoke(*args, *outputs)
        assert code == 2
        assert_one_error_line(err, "both name")
    assert list(tmp_path.iterdir()) == []


def test_a_file_name_that_is_not_utf8_is_written_as_escapes(tmp_path: Path) -> None:
    data = shared_data(*FR1)
    estimate = tmp_path / os.fsdecode(b"est\xff.txt")
    estimate.write_bytes((data / "freiburg1_xyz-rgbdslam.txt").read_bytes())
    reference = data / "freiburg1_xyz-groundtruth.txt"
    exported = tmp_path / "e.tum"
    code, _, err = invoke("export", estimate, "-o", exported)
    assert code == 0, err
    assert exported.read_text(encoding="utf-8").startswith("# relpoint export of " + str(tmp_path) + "/est\\xff.txt\n")
    out = tmp_path / "out"
    code, _, err = invoke("evaluate", estimate, "-r", reference, "--json", out / "e.json",
                          "--save-results", out / "e.zip", "--plot", out / "plots")  # fmt: skip
    assert code == 0, err
    assert json.loads((out / "e.json").read_bytes())["inputs"]["estimate"].endswith("/est\\xff.txt")
    with zipfile.ZipFile(out / "e.zip") as archive:
        assert json.loads(archive.read("info.json"))["est_name"] == "est\\xff.txt"
    assert len(list((out / "plots").iterdir())) == 3


def test_a_gate_message_shows_the_value_and_bound_apart() -> None:
    bound = 0.01347008884973369
    for value in (math.nextafter(bound, 1.0), bound * (1 + 1e-9), 0.1):
        (message,) = check_gates({"ate_rmse": value}, {"ate_rmse": bound})
        shown_value, shown_bound = message.removeprefix("ate_rmse=").split(" > ")
        assert float(shown_value) > float(shown_bound), message
    assert check_gates({"ate_rmse": 0.1}, {"ate_rmse": 0.05}) == ["ate_rmse=0.1 > 0.05"]


def test_half_a_tf_chain_is_a_usage_error(tmp_path: Path) -> None:
    bag = shared_data(*BAG)
    for frames in (("--parent", "map"), ("--child", "base_footprint")):
        for args in (("evaluate", bag, "-r", bag), ("export", bag, "-o", tmp_path / "t.tum"),
                     ("compare", tmp_path, "--reference", bag)):  # fmt: skip
            code, _, err = invoke(*args, *frames)
            assert code == 2, args
            assert_one_error_line(err, "a TF chain needs both")
    assert list(tmp_path.iterdir()) == []
