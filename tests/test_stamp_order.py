"""Logs whose log times are not their header stamps, as recorders write them (log time = receive time):
the estimators get every role's records in stamp order, and stamps on different clocks are an error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mcap.reader import make_reader
from mcap.writer import Writer

from formats import ros2
from formats.log import LogReader, LogWriter
from relpoint.errors import InputError
from relpoint.types import OdometryMeasurement, PointObservation
from relpoint_app.runner import run
from relpoint_cli.main import cli

MS = 1_000_000
EPOCH_NS = 1_700_000_000 * 1_000_000_000


def relogged(source: Path, target: Path, log_time: dict[str, object]) -> Path:
    """``source`` rewritten with each listed topic's log_time = ``log_time[topic](stamp)``, in log-time order."""
    with source.open("rb") as stream:
        reader = make_reader(stream)
        messages = [(schema, channel, message) for schema, channel, message in reader.iter_messages()]
    rows = []
    for order, (schema, channel, message) in enumerate(messages):
        shift = log_time.get(channel.topic)
        when = message.log_time if shift is None else shift(message.log_time)  # type: ignore[operator]
        rows.append((when, order, schema, channel, message))
    rows.sort(key=lambda row: (row[0], row[1]))
    with target.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2", library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for when, _, schema, channel, message in rows:
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id]
                )
            writer.add_message(channels[channel.id], when, message.data, when)
        writer.finish()
    return target


def two_topic_log(path: Path, stamps: dict[str, int], log_time: dict[str, object]) -> Path:
    """Ten clouds and ten odometry messages 100 ms apart from ``stamps[topic]``, logged at ``log_time``."""
    plain = path.with_name("plain-" + path.name)
    with LogWriter(plain) as writer:
        for k in range(10):
            writer.write_observation(PointObservation(stamps["/points"] + k * 100 * MS, np.ones((3, 3))))
            writer.write_odometry(OdometryMeasurement(stamps["/odom"] + k * 100 * MS, [1, 0, 0], [0, 0, 0]))
    return relogged(plain, path, log_time)


def test_records_of_lagging_topics_come_in_stamp_order(tmp_path: Path) -> None:
    # clouds reach the recorder 250 ms after their stamp, odometry 150 ms (0-40 ms jitter on top)
    jitter = iter(np.random.default_rng(0).integers(0, 40 * MS, 100).tolist())
    path = two_topic_log(tmp_path / "lag.mcap", {"/points": 0, "/odom": 0},
                         {"/points": lambda s: s + 250 * MS + next(jitter), "/odom": lambda s: s + 150 * MS})  # fmt: skip
    with path.open("rb") as stream:
        logged = [message.log_time for _, _, message in make_reader(stream).iter_messages()]
    assert logged == sorted(logged)
    reader = LogReader(path)
    records = list(reader.records(["points", "odometry"]))
    assert [(r.stamp_ns, r.role) for r in records] == [  # ties in ROLE_ORDER, not in their log order
        (k * 100 * MS, role) for k in range(10) for role in ("points", "odometry")
    ]
    assert reader.warnings == []


def test_a_log_in_time_order_reads_in_its_own_order(small_log: Path) -> None:
    reader = LogReader(small_log)
    roles = ["points", "odometry", "fix", "ground_truth_pose"]
    records = [(r.role, r.stamp_ns) for r in reader.records(roles)]
    topics = {reader.topics.roles()[role]: role for role in roles}
    with small_log.open("rb") as stream:
        logged = [(topics[c.topic], m.log_time) for _, c, m in make_reader(stream).iter_messages()
                  if c.topic in topics]  # fmt: skip
    assert records == logged


def test_stamps_on_another_clock_than_log_time_read_with_one_warning(tmp_path: Path) -> None:
    # simulated time from 0 s, logged at wall-clock time
    path = two_topic_log(tmp_path / "sim.mcap", {"/points": 0, "/odom": 0},
                         {"/points": lambda s: s + EPOCH_NS, "/odom": lambda s: s + EPOCH_NS + 20 * MS})  # fmt: skip
    reader = LogReader(path)
    assert [r.stamp_ns for r in reader.records(["points", "odometry"])][:4] == [0, 0, 100 * MS, 100 * MS]
    list(reader.records(["points"]))
    assert len(reader.warnings) == 1 and "log_time - header.stamp reaches 1700000000.020 s" in reader.warnings[0]


def test_topics_stamped_on_different_clocks_are_an_error(tmp_path: Path) -> None:
    # odometry stamped in wall-clock time, clouds in simulated time, both logged in simulated time
    path = two_topic_log(tmp_path / "clocks.mcap", {"/points": 0, "/odom": EPOCH_NS},
                         {"/odom": lambda s: s - EPOCH_NS})  # fmt: skip
    reader = LogReader(path)
    with pytest.raises(InputError, match=r"on /odom but 0\.000 s on /points: their stamps are not on one clock"):
        next(reader.records(["points", "odometry"]))
    assert len(list(reader.records(["points"]))) == 10  # each topic alone reads
    # a topic stamped all at zero (log time 20 s on): the stamps that do not increase are named
    zero = tmp_path / "zero-odom.mcap"
    with LogWriter(zero) as writer:
        for k in range(10):
            writer.write_observation(PointObservation(k * 100 * MS, np.ones((3, 3))))
            message = ros2.odometry_to_msg(OdometryMeasurement(0, [1, 0, 0], [0, 0, 0]))
            writer.write("/odom", ros2.ODOMETRY, message, k * 100 * MS + 20_000 * MS)
    with pytest.raises(InputError, match=r"/odom stamp 0\.000000000 s is not after the previous 0\.000000000 s"):
        list(LogReader(zero).records(["points", "odometry"]))


def test_a_stamp_that_goes_back_is_named_to_the_nanosecond(tmp_path: Path) -> None:
    # In float seconds a stamp of 1.7e9 s keeps 7 digits after the point (666666746 for 666666660): the
    # message named a stamp that is nowhere in the log.
    path = tmp_path / "back.mcap"
    stamps = [EPOCH_NS + 633_333_330, EPOCH_NS + 699_999_993, EPOCH_NS + 666_666_660]
    with LogWriter(path) as writer:
        for k, stamp in enumerate(stamps):  # logged in order, the last stamped before the one before it
            message = ros2.observation_to_msg(PointObservation(stamp, np.ones((3, 3))))
            writer.write("/points", ros2.POINT_CLOUD2, message, EPOCH_NS + k * 100 * MS)
    seconds = EPOCH_NS // 1_000_000_000
    with pytest.raises(
        InputError, match=rf"stamp {seconds}\.666666660 s is not after the previous {seconds}\.699999993 s"
    ):
        list(LogReader(path).records(["points"]))


@pytest.mark.parametrize("name", ["ekf", "fastslam"])
def test_estimators_on_a_log_with_receive_times_match_the_log_in_stamp_order(
    tmp_path: Path, small_log: Path, name: str
) -> None:
    # a recorder's receive times: clouds 250 ms after their stamp, odometry 150 ms, fixes 60 ms; the
    # estimators used to lose the time order (exit 4) or apply each twist an interval late
    lagged = relogged(small_log, tmp_path / "lagged.mcap",
                      {"/points": lambda s: s + 250 * MS, "/odom": lambda s: s + 150 * MS,
                       "/fix": lambda s: s + 60 * MS})  # fmt: skip
    expected = run(small_log, name, seed=1).trajectory
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["run", str(lagged), "-e", name, "-o", str(out), "-q", "--seed", "1"])
    assert result.exit_code == 0, result.stderr
    assert json.loads((out / "run.json").read_text())["warnings"] == []
    got = run(lagged, name, seed=1).trajectory
    np.testing.assert_array_equal(got.stamps_ns, expected.stamps_ns)
    np.testing.assert_allclose(got.positions, expected.positions, atol=1e-6)
    # odometry alone lagging keeps every tie in its log order: the same run exactly
    odom_lag = relogged(small_log, tmp_path / "odom-lag.mcap", {"/odom": lambda s: s + 150 * MS})
    np.testing.assert_array_equal(run(odom_lag, name, seed=1).trajectory.positions, expected.positions)


@pytest.mark.parametrize("every_frame", [False, True])
def test_a_camera_info_stamped_zero_by_a_static_publisher_is_read_with_the_depth(
    tmp_path: Path, every_frame: bool
) -> None:
    """A static publisher stamps its CameraInfo 0 (or repeats one stamp), logged at wall-clock time:
    calibration is not a time series, so it neither breaks the clock check nor has to increase."""
    from relpoint.types import Intrinsics

    intrinsics = Intrinsics(8, 6, 5.0, 5.0, 4.0, 3.0)
    path = tmp_path / "static-info.mcap"
    with LogWriter(path) as writer:
        for k in range(5):
            stamp = EPOCH_NS + k * 100 * MS
            if k == 0 or every_frame:
                writer.write(
                    "/camera/depth/camera_info", ros2.CAMERA_INFO, ros2.camera_info_to_msg(0, intrinsics), stamp
                )
            writer.write_depth(stamp, np.full((6, 8), 1.5, dtype=np.float32))
    reader = LogReader(path)
    records = list(reader.records(["depth", "camera_info"]))
    roles = [r.role for r in records]
    assert roles[0] == "camera_info" and roles.count("depth") == 5
    assert roles.count("camera_info") == (5 if every_frame else 1)
    assert [r.stamp_ns for r in records if r.role == "depth"] == [EPOCH_NS + k * 100 * MS for k in range(5)]
    assert not reader.warnings  # the depth's stamps are its log times: nothing to warn of


@pytest.mark.parametrize("name", ["ekf", "fastslam"])
def test_fixes_logged_before_the_cloud_of_their_instant_give_the_same_run(
    tmp_path: Path, small_log: Path, name: str
) -> None:
    # A recorder logs what it receives first: a fix before the cloud of the same stamp (the cloud's
    # driver is slower). Equal stamps were read in log order, and FastSLAM's ATE moved 16 %.
    early = relogged(small_log, tmp_path / "early.mcap", {"/points": lambda s: s + 1})  # logged after the fix
    reader = LogReader(early)
    roles = [r.role for r in reader.records(["points", "odometry", "fix"])]
    assert roles == [r.role for r in LogReader(small_log).records(["points", "odometry", "fix"])]
    expected = run(small_log, name, seed=1).trajectory
    np.testing.assert_array_equal(run(early, name, seed=1).trajectory.positions, expected.positions)
