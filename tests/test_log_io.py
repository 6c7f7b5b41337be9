"""Log round trips for every message kind, interoperability with other ROS 2 MCAP tools, bad files."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer

from formats import ros2
from formats.log import LogReader, LogWriter, Topics
from relpoint.errors import InputError
from relpoint.types import GroundTruthLandmarks, Intrinsics, OdometryMeasurement, PointObservation, Pose, PositionFix

ALL_ROLES = [
    "points",
    "ground_truth_pose",
    "ground_truth_landmarks",
    "odometry",
    "fix",
    "depth",
    "camera_info",
    "color",
]


def write_every_kind(path: Path, compression: str = "zstd") -> dict[str, object]:
    rng = np.random.default_rng(7)
    stamp = 1_700_000_000_123_456_789
    observation = PointObservation(stamp, rng.normal(size=(50, 3)) * 10, rng.integers(-1, 99, 50), "sensor")
    pose = Pose(stamp, (1.0, -2.0, 3.5), tuple(np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm([0.1, 0.2, 0.3, 0.9])))
    landmarks = GroundTruthLandmarks(rng.normal(size=(30, 3)), np.arange(30), np.arange(30) % 3 == 0)
    covariance = np.diag(rng.uniform(0.01, 0.1, 6))
    odometry = OdometryMeasurement(stamp, [1.0, 0.1, -0.2], [0.01, -0.02, 0.3], covariance)
    fix = PositionFix(stamp, [10.0, 20.0, -1.0], np.diag([1.0, 2.0, 3.0]))
    intrinsics = Intrinsics(64, 48, 52.5, 52.0, 31.5, 23.5)
    depth = rng.uniform(0.3, 5.0, (48, 64)).astype(np.float32)
    depth[::7, ::5] = 0.0
    color = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    with LogWriter(path, compression=compression) as writer:
        writer.write_ground_truth_landmarks(stamp, landmarks)
        writer.write_ground_truth_pose(pose)
        writer.write_observation(observation)
        writer.write_odometry(odometry)
        writer.write_fix(fix)
        writer.write_camera_info(stamp, intrinsics)
        writer.write_depth(stamp, depth)
        writer.write_color(stamp, color)
        writer.write_depth(stamp + 1, depth, topic="/depth32", encoding="32FC1")
    return {"observation": observation, "pose": pose, "landmarks": landmarks, "odometry": odometry, "fix": fix,
            "intrinsics": intrinsics, "depth": depth, "color": color}  # fmt: skip


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_every_message_kind_round_trips(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "all.mcap"
    written = write_every_kind(path, compression)
    reader = LogReader(path)
    assert reader.available_roles() == set(ALL_ROLES)
    records = {r.role: r.value for r in reader.records(ALL_ROLES)}
    obs = records["points"]
    np.testing.assert_allclose(obs.points, written["observation"].points.astype(np.float32), rtol=0, atol=0)
    np.testing.assert_array_equal(obs.ids, written["observation"].ids)
    assert obs.stamp_ns == written["observation"].stamp_ns and obs.frame_id == "sensor"
    assert records["ground_truth_pose"] == written["pose"]
    gt = records["ground_truth_landmarks"]
    np.testing.assert_allclose(gt.positions, written["landmarks"].positions.astype(np.float32))
    np.testing.assert_array_equal(gt.ids, written["landmarks"].ids)
    np.testing.assert_array_equal(gt.dynamic, written["landmarks"].dynamic)
    odo = records["odometry"]
    np.testing.assert_array_equal(odo.linear, written["odometry"].linear)
    np.testing.assert_array_equal(odo.angular, written["odometry"].angular)
    np.testing.assert_array_equal(odo.covariance, written["odometry"].covariance)
    fix = records["fix"]
    np.testing.assert_array_equal(fix.position, written["fix"].position)
    np.testing.assert_array_equal(fix.covariance, written["fix"].covariance)
    assert records["camera_info"] == written["intrinsics"]
    # 16UC1 keeps millimetres.
    np.testing.assert_allclose(records["depth"], np.round(written["depth"] * 1000) / 1000, atol=1e-6)
    assert (records["depth"] == 0).sum() == (written["depth"] == 0).sum()
    np.testing.assert_array_equal(records["color"], written["color"])
    float_depth = LogReader(path, Topics(depth="/depth32"))
    depth32 = next(r.value for r in float_depth.records(["depth"]))
    np.testing.assert_array_equal(depth32, written["depth"])


def test_our_logs_decode_with_mcap_ros2_support(tmp_path: Path) -> None:
    path = tmp_path / "all.mcap"
    written = write_every_kind(path)
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        decoded = {channel.topic: (schema.name, msg) for schema, channel, _, msg in reader.iter_decoded_messages()}
        assert reader.get_header().profile == "ros2"
    name, cloud = decoded["/points"]
    assert name == "sensor_msgs/msg/PointCloud2"
    assert cloud.width == 50 and [f.name for f in cloud.fields] == ["x", "y", "z", "id"]
    name, odom = decoded["/odom"]
    assert odom.twist.twist.angular.z == pytest.approx(written["odometry"].angular[2])
    assert decoded["/fix"][1].pose.covariance[35] == pytest.approx(1e9)


def test_reads_a_log_written_by_another_tool(tmp_path: Path) -> None:
    """mcap-ros2-support's writer, other topic names, padded points with extra fields."""
    path = tmp_path / "other.mcap"
    rng = np.random.default_rng(3)
    n = 40
    dtype = np.dtype({"names": ["x", "y", "z", "intensity", "id"], "formats": ["<f4", "<f4", "<f4", "<f4", "<i4"],
                      "offsets": [0, 4, 8, 16, 20], "itemsize": 32})  # fmt: skip
    fields = [{"name": n_, "offset": o, "datatype": d, "count": 1}
              for n_, o, d in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("id", 20, 5))]  # fmt: skip
    with path.open("wb") as stream:
        writer = Ros2Writer(stream)
        schema = writer.register_msgdef(ros2.POINT_CLOUD2, ros2.message_definition(ros2.POINT_CLOUD2))
        clouds = []
        for k in range(5):
            points = np.zeros(n, dtype=dtype)
            points["x"], points["y"], points["z"] = rng.normal(size=(3, n))
            points["id"] = np.arange(n)
            points["x"][0] = np.nan
            clouds.append(points)
            stamp = 5_000_000_000 + k * 100_000_000
            writer.write_message(
                topic="/robot/landmarks", schema=schema, log_time=stamp, publish_time=stamp,
                message={"header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "base"},
                         "height": 1, "width": n, "fields": fields, "is_bigendian": False, "point_step": 32,
                         "row_step": 32 * n, "data": points.tobytes(), "is_dense": False},
            )  # fmt: skip
        writer.finish()
    reader = LogReader(path, Topics(points="/robot/landmarks"))
    reader.require("points")
    observations = [r.value for r in reader.records(["points"])]
    assert len(observations) == 5
    for obs, points in zip(observations, clouds, strict=True):
        assert obs.frame_id == "base" and len(obs) == n - 1
        np.testing.assert_allclose(obs.points[:, 1], points["y"][1:])
        np.testing.assert_array_equal(obs.ids, np.arange(1, n))
    assert reader.skipped["/robot/landmarks: non-finite points"] == 5
    with pytest.raises(InputError, match="no messages on /points"):
        LogReader(path).require("points")


def test_writer_is_atomic(tmp_path: Path) -> None:
    path = tmp_path / "broken.mcap"
    with pytest.raises(RuntimeError), LogWriter(path) as writer:
        writer.write_fix(PositionFix(1, [0, 0, 0], np.eye(3)))
        raise RuntimeError("simulated crash")
    assert list(tmp_path.iterdir()) == []


def test_bad_files_are_input_errors(tmp_path: Path, small_log: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        LogReader(tmp_path / "missing.mcap")
    (tmp_path / "text.mcap").write_text("hello, not a log\n")
    with pytest.raises(InputError, match="not an MCAP file"):
        LogReader(tmp_path / "text.mcap")
    data = small_log.read_bytes()
    for cut in (9, 100, len(data) // 3, len(data) // 2, len(data) - 40, len(data) - 1):
        truncated = tmp_path / f"cut{cut}.mcap"
        truncated.write_bytes(data[:cut])
        with pytest.raises(InputError, match="truncated or corrupt"):
            reader = LogReader(truncated)
            list(reader.records(["points"]))


def test_flipped_bytes_in_a_chunk_are_detected(tmp_path: Path, small_log: Path) -> None:
    data = bytearray(small_log.read_bytes())
    data[len(data) // 2] ^= 0xFF
    damaged = tmp_path / "flipped.mcap"
    damaged.write_bytes(bytes(data))
    with pytest.raises(InputError, match="truncated or corrupt"):
        list(LogReader(damaged).records(["points", "ground_truth_pose"]))


def test_wrong_type_and_backwards_stamps(tmp_path: Path) -> None:
    path = tmp_path / "bad.mcap"
    with LogWriter(path) as writer:
        writer.write_ground_truth_pose(Pose(10, (0, 0, 0), (0, 0, 0, 1)), topic="/points")
    with pytest.raises(InputError, match="carries geometry_msgs/msg/PoseStamped, not sensor_msgs/msg/PointCloud2"):
        LogReader(path).require("points")
    path = tmp_path / "backwards.mcap"
    with LogWriter(path) as writer:
        for log_time, stamp in ((1000, 100), (1001, 200), (1002, 150)):
            # log_time increases in file order while header.stamp goes backwards at the third message
            msg = ros2.observation_to_msg(PointObservation(stamp, np.ones((3, 3))))
            writer.write("/points", ros2.POINT_CLOUD2, msg, log_time)
    with pytest.raises(InputError, match="is not after the previous"):
        list(LogReader(path).records(["points"]))


def test_empty_and_nan_clouds_are_skipped_and_counted(tmp_path: Path) -> None:
    path = tmp_path / "holes.mcap"
    with LogWriter(path) as writer:
        writer.write_observation(PointObservation(1, np.ones((4, 3))))
        writer.write_observation(PointObservation(2, np.zeros((0, 3))))
        writer.write_observation(PointObservation(3, np.array([[np.nan, 0, 0], [1, 2, 3], [np.inf, 1, 1]])))
    reader = LogReader(path)
    observations = [r.value for r in reader.records(["points"])]
    assert [len(o) for o in observations] == [4, 0, 1]
    assert reader.skipped["/points: empty clouds"] == 1
    assert reader.skipped["/points: non-finite points"] == 2


def test_reads_a_real_rosbag2_recording() -> None:
    from tests.conftest import shared_data

    path = shared_data("ros2-bags", "nav2_turtlebot.mcap")
    reader = LogReader(path, Topics(odometry="/odom"))
    infos = reader.topic_infos
    assert infos["/odom"].count == 2639 and infos["/tf"].count == 5422 and infos["/amcl_pose"].count == 135
    assert infos["/amcl_pose"].typename == "geometry_msgs/msg/PoseWithCovarianceStamped"
    odometry = [r.value for r in reader.records(["odometry"])]
    assert len(odometry) == 2639
    assert all(np.isfinite(o.linear).all() for o in odometry)
    assert max(abs(o.linear[0]) for o in odometry) > 0.05  # the robot drives


def _count_opens(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """Patch the log reader's opener to record every path it opens."""
    import formats.log as log_module

    opened: list[Path] = []
    real = log_module.open_reader

    def counting(path: Path):  # type: ignore[no-untyped-def]
        opened.append(path)
        return real(path)

    monkeypatch.setattr(log_module, "open_reader", counting)
    return opened


def test_passes_one_after_another_share_one_open_reader(small_log: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    opened = _count_opens(monkeypatch)
    with LogReader(small_log) as reader:
        points = [r.stamp_ns for r in reader.records(["points"])]
        poses = [r.stamp_ns for r in reader.records(["ground_truth_pose"])]
        first = next(iter(reader.records(["points"])))  # stopped early: the reader is kept, not spoiled
        again = [r.stamp_ns for r in reader.records(["points"])]
        raw = [stamp for _, _, stamp, _ in reader.messages(["/points"])]
    assert len(opened) == 1
    assert points and poses and len(raw) == len(points)
    assert first.stamp_ns == points[0] and again == points


def test_passes_at_the_same_time_read_independently(small_log: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    opened = _count_opens(monkeypatch)
    with LogReader(small_log) as reader:
        alone = [r.stamp_ns for r in reader.records(["points"])]
        together = [
            (a.stamp_ns, b.stamp_ns)
            for a, b in zip(reader.records(["points"]), reader.records(["points"]), strict=True)
        ]
    assert [a for a, _ in together] == alone and [b for _, b in together] == alone
    assert len(opened) == 2  # the second pass, started while the first ran, had a reader of its own


def test_own_message_types_are_the_standard_ones() -> None:
    """``formats/_ros2_types.py`` is rosbags' code for relpoint's types as the bundled Humble store defines
    them (regenerate it as :func:`formats.ros2.own_types_module` says when rosbags changes)."""
    generated = Path(ros2.__file__).with_name("_ros2_types.py").read_text()
    assert generated == ros2.own_types_module()
    own, standard = ros2.own_typestore(), ros2.typestore()
    assert set(ros2.OWN_TYPES) <= set(own.fielddefs)
    for typename in own.fielddefs:
        assert own.fielddefs[typename] == standard.fielddefs[typename]
        assert own.generate_msgdef(typename, ros_version=2) == standard.generate_msgdef(typename, ros_version=2)
    message = ros2.odometry_to_msg(OdometryMeasurement(123_456_789, [1.0, 0.1, -0.2], [0.01, -0.02, 0.3], np.eye(6)))
    assert ros2.serialize(message, ros2.ODOMETRY) == bytes(standard.serialize_cdr(message, ros2.ODOMETRY))
    assert ros2.typestore_of("sensor_msgs/msg/Imu") is standard


def test_an_unindexed_mcap_file_out_of_log_time_order_says_so_and_how_to_index_it(tmp_path: Path) -> None:
    from mcap.writer import IndexType, Writer

    path = tmp_path / "unindexed.mcap"
    with path.open("wb") as stream:  # valid MCAP: messages may come in any log-time order
        writer = Writer(stream, index_types=IndexType.NONE, use_summary_offsets=False, use_statistics=False,
                        repeat_channels=False, repeat_schemas=False, chunk_size=200)  # fmt: skip
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(
            ros2.POSE_STAMPED, "ros2msg", ros2.message_definition(ros2.POSE_STAMPED).encode()
        )
        channel = writer.register_channel("/ground_truth/pose", "cdr", schema)
        for k in (3, 1, 0, 2, 5, 4):
            message = ros2.serialize(ros2.pose_to_msg(Pose(k * 10**8, (k, 0, 0), (0, 0, 0, 1))), ros2.POSE_STAMPED)
            writer.add_message(channel, k * 10**8, message, k * 10**8)
        writer.finish()
    with pytest.raises(InputError) as caught:
        LogReader(path)
    assert "unindexed (no chunk indexes or summary) and its messages are not in log-time order" in caught.value.message
    assert "truncated" not in caught.value.message and "mcap recover" in caught.value.hint


class _Extra(NamedTuple):
    """A channel added to a rewritten log (registered before the log's own), a message of it after every cloud."""

    topic: str
    type_name: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    payload: bytes


def _rewrite(source: Path, target: Path, schema_text: Any = None, extra: _Extra | None = None) -> None:
    """``source`` written again by the raw mcap writer: each ros2msg schema's text through ``schema_text``
    (None: unchanged), and with ``extra`` a channel beside the log's."""
    from mcap.writer import Writer

    with source.open("rb") as stream, target.open("wb") as out:
        writer = Writer(out)
        writer.start(profile="ros2", library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        added = None
        if extra is not None:
            added_schema = writer.register_schema(extra.type_name, extra.schema_encoding, extra.schema_data)
            added = writer.register_channel(extra.topic, extra.message_encoding, added_schema)
        for schema, channel, message in make_reader(stream).iter_messages(log_time_order=True):
            if schema.id not in schemas:
                text = schema.data.decode()
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, (schema_text(text) if schema_text else text).encode()
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding, schemas[schema.id])
            writer.add_message(channels[channel.id], log_time=message.log_time, publish_time=message.publish_time,
                               data=message.data, sequence=message.sequence)  # fmt: skip
            if added is not None and extra is not None and channel.topic == "/points":
                writer.add_message(added, log_time=message.log_time, publish_time=message.log_time,
                                   data=extra.payload, sequence=0)  # fmt: skip
        writer.finish()


@pytest.mark.parametrize(
    ("variant", "schema_text", "extra"),
    [
        ("a JSON channel (Foxglove)", None,
         _Extra("/vendor/status", "vendor.Status", "jsonschema", b'{"type": "object"}', "json", b'{"level": 3}')),
        ("a protobuf channel", None,
         _Extra("/vendor/status", "vendor.Status", "protobuf", b'{"type": "object"}', "protobuf", b"\x08\x03")),
        ("separators of 40 =", lambda t: t.replace("=" * 80, "=" * 40), None),
        ("separators of 120 = and a trailing blank", lambda t: t.replace("=" * 80, "=" * 120 + " "), None),
        ("CRLF line ends", lambda t: t.replace("\n", "\r\n"), None),
        ("empty schemas (schemaless channels)", lambda t: "", None),
    ],
)  # fmt: skip
def test_logs_other_writers_make_read_as_relpoint_s_own(
    tmp_path: Path, small_log: Path, variant: str, schema_text: Any, extra: _Extra | None
) -> None:
    """What another writer puts in an MCAP file beside the log format's topics, or how it spells a schema,
    must not matter: each was refused as a truncated or corrupt file."""
    path = tmp_path / "other.mcap"
    _rewrite(small_log, path, schema_text, extra)
    ours, theirs = LogReader(small_log), LogReader(path)
    expected = [r.value for r in ours.records(["points", "odometry", "fix", "ground_truth_pose"])]
    read = [r.value for r in theirs.records(["points", "odometry", "fix", "ground_truth_pose"])]
    assert len(read) == len(expected) > 0, variant
    for a, b in zip(read, expected, strict=True):
        assert type(a) is type(b) and a.stamp_ns == b.stamp_ns
        if isinstance(a, PointObservation):
            np.testing.assert_array_equal(a.points, b.points)
    assert not theirs.skipped, theirs.skipped
    if extra is not None:
        assert theirs.topic_infos["/vendor/status"].typename == "vendor.Status"


def test_a_stamp_before_1970_is_logged_at_zero_and_kept_in_its_header(tmp_path: Path) -> None:
    # A ROS time may be negative (int32 seconds); MCAP's log_time cannot. Writing a run's result.mcap
    # for such a log failed with an internal error after the whole estimation had run.
    path = tmp_path / "early.mcap"
    with LogWriter(path) as writer:
        writer.write_ground_truth_pose(Pose(-1_000_000_000_000, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0)))
        writer.write_ground_truth_pose(Pose(5, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0)))
    with path.open("rb") as stream:
        read = list(make_reader(stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert [message.log_time for _, _, message, _ in read] == [0, 5]
    assert read[0][3].header.stamp.sec == -1000 and read[1][3].header.stamp.nanosec == 5


def test_a_topic_carrying_two_types_is_read_as_its_role_s(tmp_path: Path, small_log: Path) -> None:
    # A second publisher of another type on /points, registered first: the log was refused ("carries
    # std_msgs/msg/String") although every cloud was there; registered after the clouds it was read.
    path = tmp_path / "two-types.mcap"
    string = _Extra("/points", "std_msgs/msg/String", "ros2msg", b"string data", "cdr",
                    b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00")  # fmt: skip
    _rewrite(small_log, path, extra=string)
    reader = LogReader(path)
    reader.require("points")
    assert reader.topic_infos["/points"].typename == ros2.POINT_CLOUD2
    clouds = [r.value for r in reader.records(["points"])]
    assert [c.stamp_ns for c in clouds] == [r.value.stamp_ns for r in LogReader(small_log).records(["points"])]
    assert any("/points carries more than one message type" in w and "std_msgs/msg/String" in w
               for w in reader.warnings)  # fmt: skip


def test_image_topics_named_for_the_other_kind_are_no_candidates() -> None:
    # `relpoint info` offered a camera driver's /camera/color/image_raw as the depth topic to name.
    from formats.log import may_serve

    image = ros2.IMAGE
    assert may_serve("depth", "/camera/aligned_depth_to_color/image_raw", image)  # RealSense: depth, named both
    assert may_serve("depth", "/kinect/image", image)  # a name that says nothing
    assert not may_serve("depth", "/camera/color/image_raw", image)
    assert may_serve("color", "/camera/rgb/image_color", image)
    assert not may_serve("color", "/camera/depth/image_rect_raw", image)
    assert not may_serve("color", "/camera/color/camera_info", ros2.CAMERA_INFO)
    assert may_serve("odometry", "/odometry/filtered", ros2.ODOMETRY)
