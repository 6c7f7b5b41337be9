"""Every bag layout reads as the single MCAP file does: the same messages, the same outputs, the same errors.

Each layout is written with rosbags' own writers from the messages of one simulated log (rosbag2 with
mcap and sqlite3 storage, split over several files, zstd per file and per message; ROS 1 bags plain and
with compressed chunks), then read back through every entry point.
"""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from formats.layout_writers import LayoutSpec, raw_messages, write_layout
from formats.layouts import Layout, detect_layout, log_sha256
from formats.log import LogReader
from formats.ply import read_ply
from formats.signatures import is_log
from relpoint.errors import InputError, RelpointError
from relpoint.simulation import SimulationConfig, simulate
from relpoint_app.simulation import write_simulation
from relpoint_cli.main import cli
from tests.conftest import shared_data

SPECS = {
    "rosbag2-mcap": LayoutSpec(Layout.ROSBAG2, "mcap"),
    "rosbag2-sqlite3": LayoutSpec(Layout.ROSBAG2, "sqlite3"),
    "rosbag2-mcap-split": LayoutSpec(Layout.ROSBAG2, "mcap", files=3),
    "rosbag2-sqlite3-split": LayoutSpec(Layout.ROSBAG2, "sqlite3", files=3),
    "rosbag2-mcap-zstd-file": LayoutSpec(Layout.ROSBAG2, "mcap", "file", files=2),
    "rosbag2-mcap-zstd-message": LayoutSpec(Layout.ROSBAG2, "mcap", "message"),
    "rosbag2-sqlite3-zstd-message": LayoutSpec(Layout.ROSBAG2, "sqlite3", "message", files=2),
    "rosbag1.bag": LayoutSpec(Layout.ROS1),
    "rosbag1-bz2.bag": LayoutSpec(Layout.ROS1, compression="bz2"),
    "rosbag1-lz4.bag": LayoutSpec(Layout.ROS1, compression="lz4"),
}


def invoke(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(cli, ["-q", *args])
    return result.exit_code, result.stdout, result.stderr


@pytest.fixture(scope="module")
def points_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("layouts") / "points.mcap"
    config = SimulationConfig(iterations=40, density=25, noise=0.3, odometry_noise=0.05, fix_every=5, seed=5)
    write_simulation(simulate(config), path)
    return path


@pytest.fixture(scope="module")
def room_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Depth, colour, camera info and poses: the image and CameraInfo types (``K`` in ROS 1, ``k`` in ROS 2)."""
    path = tmp_path_factory.mktemp("room") / "room.mcap"
    code, _, err = invoke("simulate", "-o", str(path), "--scenario", "room", "--iterations", "4", "--seed", "2")
    assert code == 0, err
    return path


def layouts_of(log: Path) -> dict[str, Path]:
    """The log's messages in every layout of :data:`SPECS`, beside it (written once)."""
    messages = list(raw_messages(log))
    paths = {}
    for name, spec in SPECS.items():
        path = log.parent / f"{log.stem}-{name}"
        if not path.exists():
            write_layout(messages, path, spec)
        paths[name] = path
    return paths


@pytest.fixture(scope="module")
def points_layouts(points_log: Path) -> dict[str, Path]:
    return layouts_of(points_log)


def records_of(path: Path) -> list[tuple[str, int, object]]:
    reader = LogReader(path)
    return [(r.role, r.stamp_ns, r.value) for r in reader.records(sorted(reader.available_roles()))]


def assert_same_records(expected: list, actual: list) -> None:
    assert len(actual) == len(expected)
    for (role_a, stamp_a, value_a), (role_b, stamp_b, value_b) in zip(expected, actual, strict=True):
        assert (role_a, stamp_a) == (role_b, stamp_b)
        if isinstance(value_a, np.ndarray):
            np.testing.assert_array_equal(value_a, value_b)
        else:  # the core types are dataclasses of arrays and scalars
            for name in value_a.__dataclass_fields__:
                np.testing.assert_array_equal(
                    getattr(value_a, name), getattr(value_b, name), err_msg=f"{role_a}.{name}"
                )


def test_layouts_are_told_apart_by_content(points_layouts: dict[str, Path], points_log: Path, tmp_path: Path) -> None:
    assert detect_layout(points_log) is Layout.MCAP
    for name, path in points_layouts.items():
        assert detect_layout(path) is SPECS[name].layout, name
    (tmp_path / "plain").mkdir()
    (tmp_path / "text.mcap").write_text("1 2 3\n")
    sqlite_file = next(points_layouts["rosbag2-sqlite3"].glob("*.db3"))
    for path, message in [
        (tmp_path / "plain", "directory without metadata.yaml"),
        (tmp_path / "text.mcap", "not an MCAP file"),
        (sqlite_file, "sqlite3 storage file, not a log on its own"),
        (next(points_layouts["rosbag2-mcap-zstd-file"].glob("*.zstd")), "zstd-compressed storage file"),
        (points_layouts["rosbag2-mcap"] / "metadata.yaml", "metadata file, not a log"),
        (tmp_path / "absent", "no such file"),
    ]:
        assert not is_log(path)
        with pytest.raises(InputError, match=message):
            LogReader(path)
    misnamed = tmp_path / "recording.log"
    shutil.copy(points_layouts["rosbag1.bag"], misnamed)
    assert is_log(misnamed)
    with pytest.raises(InputError, match=r"not named \*\.bag; rename it"):
        LogReader(misnamed)
    code, _, err = invoke("evaluate", str(misnamed), "--reference", str(points_log))
    assert code == 3 and "rename it to end in .bag" in err


@pytest.mark.parametrize("name", sorted(SPECS))
def test_every_layout_yields_the_same_records(points_log: Path, points_layouts: dict[str, Path], name: str) -> None:
    assert_same_records(records_of(points_log), records_of(points_layouts[name]))


def test_images_and_camera_info_survive_every_layout(room_log: Path) -> None:
    expected = records_of(room_log)
    assert {role for role, _, _ in expected} >= {"depth", "color", "camera_info", "ground_truth_pose"}
    for name, path in layouts_of(room_log).items():
        actual = records_of(path)
        assert len(actual) == len(expected), name
        assert_same_records(expected, actual)


def run_outputs(log: Path, out: Path, estimator: str) -> dict[str, str]:
    code, _, err = invoke("run", str(log), "-e", estimator, "-o", str(out), "--seed", "4")
    assert code == 0, err
    outputs = {name: (out / name).read_text() for name in ("trajectory.tum", "trajectory.csv", "map.csv")}
    timing = [line.split(",") for line in (out / "timing.csv").read_text().splitlines()]
    outputs["timing.csv without seconds"] = "\n".join(",".join(row[:-1]) for row in timing)
    outputs["map.ply"] = (out / "map.ply").read_bytes().hex()
    return outputs


def test_runs_give_byte_identical_outputs_in_every_layout(
    points_log: Path, points_layouts: dict[str, Path], tmp_path: Path
) -> None:
    expected = run_outputs(points_log, tmp_path / "mcap", "ekf")
    for name, path in points_layouts.items():
        actual = run_outputs(path, tmp_path / name, "ekf")
        for output, text in expected.items():
            assert actual[output] == text, f"{name}: {output} differs"
        run_json = json.loads((tmp_path / name / "run.json").read_text())
        assert run_json["input"]["sha256"] == log_sha256(path)


def test_dense_runs_give_byte_identical_outputs_from_a_ros1_bag_and_a_sqlite3_bag(
    room_log: Path, tmp_path: Path
) -> None:
    layouts = layouts_of(room_log)
    expected = run_outputs(room_log, tmp_path / "mcap", "dense")
    for name in ("rosbag1-lz4.bag", "rosbag2-sqlite3-zstd-message"):
        assert run_outputs(layouts[name], tmp_path / name, "dense") == expected, name


def test_evaluate_export_and_fuse_read_bag_directories(
    points_log: Path, points_layouts: dict[str, Path], tmp_path: Path
) -> None:
    bag = points_layouts["rosbag2-sqlite3-split"]
    code, _, err = invoke("run", str(bag), "-e", "relpoint", "-o", str(tmp_path / "run"))
    assert code == 0, err
    for log in (points_log, bag):  # the run's bag, and its recording as one .mcap (accepted with --other-log)
        other = ["--other-log"] if log == points_log else []
        code, _, err = invoke("fuse", str(tmp_path / "run"), "--log", str(log), "-o", str(tmp_path / f"fused-{log.name}"),
                              *other)  # fmt: skip
        assert code == 0, err
    fused = [(tmp_path / f"fused-{log.name}" / "trajectory.tum").read_text() for log in (points_log, bag)]
    assert fused[0] == fused[1] and fused[0]
    figures = {}
    for reference in (points_log, bag, points_layouts["rosbag1.bag"]):
        report = tmp_path / f"{reference.name}.json"
        code, _, err = invoke("evaluate", str(tmp_path / "run"), "--reference", str(reference), "--json", str(report))
        assert code == 0, err
        figures[reference.name] = json.loads(report.read_text())["summary"]
    assert len({json.dumps(f, sort_keys=True) for f in figures.values()}) == 1
    for source in (points_log, bag):
        code, _, err = invoke("export", str(source), "--what", "landmarks", "-o", str(tmp_path / f"{source.name}.ply"))
        assert code == 0, err
    from_bag, from_file = (read_ply(tmp_path / f"{source.name}.ply") for source in (bag, points_log))
    assert from_bag.tobytes() == from_file.tobytes() and len(from_bag) > 0


def test_a_real_rosbag2_recording_exports_the_same_in_every_layout(tmp_path: Path) -> None:
    """nav2's turtlebot bag (odometry, TF, AMCL) as recorded, and its messages in other layouts."""
    bag = shared_data("ros2-bags", "nav2_turtlebot.mcap")
    messages = list(raw_messages(bag))
    copies = {name: write_layout(messages, tmp_path / name, SPECS[name])
              for name in ("rosbag2-sqlite3-zstd-message", "rosbag2-mcap-split", "rosbag1-lz4.bag")}  # fmt: skip
    selections = {"odom": ["--topic", "/odom"], "amcl": ["--topic", "/amcl_pose"],
                  "tf": ["--parent", "map", "--child", "base_footprint"]}  # fmt: skip
    for what, options in selections.items():
        outputs = {}
        for name, path in {"recorded": bag, **copies}.items():
            out = tmp_path / f"{what}-{name}.tum"
            code, _, err = invoke("export", str(path), *options, "-o", str(out))
            assert code == 0, err
            outputs[name] = [line for line in out.read_text().splitlines() if not line.startswith("#")]
        assert len(outputs["recorded"]) > 100, what
        for name, lines in outputs.items():
            assert lines == outputs["recorded"], f"{what} from {name}"


def test_output_inside_a_bag_directory_is_refused(points_layouts: dict[str, Path]) -> None:
    bag = points_layouts["rosbag2-mcap"]
    before = sorted(p.name for p in bag.iterdir())
    code, _, err = invoke("run", str(bag), "-e", "ekf", "-o", str(bag / "out"))
    assert code == 2 and "inside the input" in err
    assert sorted(p.name for p in bag.iterdir()) == before


def info_json(path: Path) -> dict:
    code, out, err = invoke("info", str(path), "--json")
    assert code == 0, err
    return json.loads(out)


def test_info_tells_what_ros2_bag_info_tells(points_log: Path, points_layouts: dict[str, Path]) -> None:
    expected = info_json(points_log)
    assert {t.pop("serialization_format") for t in expected["topics"]} == {"cdr"}
    assert expected["layout"] == "mcap" and expected["compression"] == {"format": "zstd", "mode": "chunk"}
    total = sum(t["count"] for t in expected["topics"])
    assert expected["message_count"] == total and expected["files"][0]["message_count"] == total
    assert expected["start_ns"] == 0 and expected["end_ns"] == 39 * 100_000_000
    for name, path in points_layouts.items():
        spec = SPECS[name]
        document = info_json(path)
        encoding = "ros1" if spec.layout is Layout.ROS1 else "cdr"
        assert {t.pop("serialization_format") for t in document["topics"]} == {encoding}
        for key in ("topics", "duration_s", "start_ns", "end_ns", "start_utc", "message_count", "observations"):
            assert document[key] == expected[key], f"{name}: {key}"
        assert document["layout"] == spec.layout.value
        assert document["storage_id"] == (spec.storage if spec.layout is Layout.ROSBAG2 else "rosbag1")
        assert len(document["files"]) == spec.files
        assert sum(f["size_bytes"] for f in document["files"]) == document["size_bytes"]
        if spec.layout is Layout.ROSBAG2:
            assert sum(f["message_count"] for f in document["files"]) == total
            mode = "" if spec.compression == "none" else spec.compression
            assert document["compression"] == {"format": "zstd" if mode else "", "mode": mode}
        else:
            codec = "" if spec.compression == "none" else spec.compression
            assert document["compression"] == {"format": codec, "mode": "chunk" if codec else ""}
    code, out, _ = invoke("info", str(points_layouts["rosbag2-sqlite3-zstd-message"]))
    assert code == 0
    assert "storage id:   sqlite3" in out and "compression:  zstd (message)" in out and "_1.db3" in out


def test_topic_options_apply_in_every_layout(points_log: Path, tmp_path: Path) -> None:
    renamed = [(topic.replace("/points", "/robot/landmarks"), *rest) for topic, *rest in raw_messages(points_log)]
    expected = info_json(points_log)["observations"]
    for name in ("rosbag2-sqlite3-split", "rosbag1-lz4.bag"):
        path = write_layout(renamed, tmp_path / name, SPECS[name])
        assert info_json(path)["observations"] is None
        code, out, err = invoke("info", str(path), "--points-topic", "/robot/landmarks", "--json")
        assert code == 0, err
        assert json.loads(out)["observations"] == {**expected, "topic": "/robot/landmarks"}


def test_batch_plans_take_bag_directories(points_layouts: dict[str, Path], points_log: Path, tmp_path: Path) -> None:
    bags = tmp_path / "bags"
    bags.mkdir()
    for name in ("rosbag2-mcap-split", "rosbag1.bag"):
        shutil.copytree(points_layouts[name], bags / name) if points_layouts[name].is_dir() else shutil.copy(
            points_layouts[name], bags / name
        )
    plan = tmp_path / "plan.toml"
    plan.write_text('logs = "bags/*"\nestimators = ["ekf"]\n')
    code, _, err = invoke("batch", str(plan), "--results", str(tmp_path / "results"))
    assert code == 0, err
    assert len(list((tmp_path / "results").rglob("trajectory.tum"))) == 2
    # A glob reaching into a bag takes the bag through its directory, never its storage files alone.
    shutil.copy(points_log, bags / "single.mcap")
    plan.write_text('logs = "bags/**/*.mcap"\nestimators = ["ekf"]\n')
    code, _, err = invoke("batch", str(plan), "--results", str(tmp_path / "results2"))
    assert code == 0, err
    assert len(list((tmp_path / "results2").rglob("trajectory.tum"))) == 1
    assert "single.mcap" in (tmp_path / "results2" / "results.csv").read_text()


# --- damaged input -----------------------------------------------------------------------------------


def storage_files(path: Path) -> list[Path]:
    return sorted(f for f in path.iterdir() if f.name != "metadata.yaml") if path.is_dir() else [path]


def damaged_copy(source: Path, target: Path) -> Path:
    if source.is_dir():
        shutil.copytree(source, target)
    else:
        shutil.copy(source, target)
    return target


def consume(path: Path) -> None:
    """Every reader entry point; only RelpointErrors may escape."""
    reader = LogReader(path)
    reader.storage()
    list(reader.records(sorted(reader.available_roles())))


@pytest.mark.parametrize("name", sorted(SPECS))
def test_truncated_storage_is_one_line_and_exit_3_in_every_layout(
    points_layouts: dict[str, Path], tmp_path: Path, name: str
) -> None:
    for fraction in (0.0, 0.25, 0.5, 0.9, 0.999):
        path = damaged_copy(points_layouts[name], tmp_path / f"{fraction}-{points_layouts[name].name}")
        victim = storage_files(path)[-1]
        data = victim.read_bytes()
        victim.write_bytes(data[: int(len(data) * fraction)])
        with pytest.raises(InputError, match=r"truncated or corrupt|not an MCAP file|seems to be empty"):
            consume(path)
        code, _, err = invoke("info", str(path))
        assert code == 3 and len(err.strip().splitlines()) == 1 and err.startswith("relpoint: error: ")


@pytest.mark.parametrize("name", ["rosbag2-mcap-split", "rosbag2-sqlite3-split"])
def test_a_missing_or_foreign_split_file_is_caught(points_layouts: dict[str, Path], tmp_path: Path, name: str) -> None:
    path = damaged_copy(points_layouts[name], tmp_path / "missing")
    storage_files(path)[1].unlink()
    with pytest.raises(InputError, match="missing"):
        consume(path)
    path = damaged_copy(points_layouts[name], tmp_path / "swapped")
    first, second = storage_files(path)[:2]
    shutil.copy(first, second)  # the second part replaced by a copy of the first
    with pytest.raises(InputError, match="truncated or corrupt"):
        consume(path)


def test_damaged_metadata_yaml_is_an_input_error(points_layouts: dict[str, Path], tmp_path: Path) -> None:
    for text in ("{[", "rosbag2_bagfile_information: 3\n", "other: 1\n"):
        path = damaged_copy(points_layouts["rosbag2-mcap"], tmp_path / f"meta{len(text)}")
        (path / "metadata.yaml").write_text(text)
        with pytest.raises(InputError):
            consume(path)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_random_damage_in_any_layout_never_escapes_as_a_traceback(
    points_layouts: dict[str, Path], tmp_path_factory: pytest.TempPathFactory, data: st.DataObject
) -> None:
    name = data.draw(st.sampled_from(sorted(SPECS)))
    path = damaged_copy(points_layouts[name], tmp_path_factory.mktemp("fuzz") / points_layouts[name].name)
    victim = data.draw(st.sampled_from(storage_files(path) + ([path / "metadata.yaml"] if path.is_dir() else [])))
    damaged = bytearray(victim.read_bytes())
    kind = data.draw(st.sampled_from(["flip", "truncate", "overwrite"]))
    if kind == "truncate":
        damaged = damaged[: data.draw(st.integers(0, len(damaged) - 1))]
    else:
        for _ in range(data.draw(st.integers(1, 8))):
            offset = data.draw(st.integers(0, len(damaged) - 1))
            damaged[offset] = damaged[offset] ^ 0xFF if kind == "flip" else data.draw(st.integers(0, 255))
    victim.write_bytes(bytes(damaged))
    with contextlib.suppress(RelpointError):
        consume(path)


def test_a_logs_hash_is_read_once_and_again_when_the_file_changes(tmp_path: Path) -> None:
    import hashlib
    import os

    from formats.signatures import MCAP_MAGIC

    log = tmp_path / "a.mcap"
    log.write_bytes(MCAP_MAGIC + b"x" * 100)
    reads = []
    opened = Path.open

    def counting_open(self: Path, *args, **kwargs):  # type: ignore[no-untyped-def]
        if self == log:
            reads.append(1)
        return opened(self, *args, **kwargs)

    first = log_sha256(log, Layout.MCAP)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Path, "open", counting_open)
        assert log_sha256(log, Layout.MCAP) == first
        assert reads == []  # remembered
        log.write_bytes(log.read_bytes() + b"y")
        os.utime(log, ns=(1, 1))
        changed = log_sha256(log, Layout.MCAP)
    assert changed == hashlib.sha256(log.read_bytes()).hexdigest() != first


def test_a_malformed_metadata_file_is_one_line(tmp_path: Path) -> None:
    from relpoint_cli.main import cli

    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    (bag / "bag_0.db3").write_bytes(b"")
    result = CliRunner().invoke(cli, ["info", str(bag)])
    assert result.exit_code == 3
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "not a rosbag2 metadata file (YAML" in lines[0] and "line 2" in lines[0], lines


@pytest.mark.parametrize(
    ("compression", "chunked", "summary", "expected"),
    [("zstd", True, True, "zstd"), ("zstd", True, False, "zstd"), ("lz4", True, False, "lz4"),
     ("", True, False, ""), ("", False, False, "")],
)  # fmt: skip
def test_the_compression_of_an_mcap_file_without_chunk_indexes_is_told_by_its_first_chunk(
    tmp_path: Path, compression: str, chunked: bool, summary: bool, expected: str
) -> None:
    from mcap.writer import CompressionType, IndexType, Writer

    from formats import ros2
    from formats.layouts import describe_storage
    from relpoint.types import Pose

    path = tmp_path / "noindex.mcap"
    codec = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "": CompressionType.NONE}[compression]
    with path.open("wb") as stream:
        writer = Writer(stream, compression=codec, use_chunking=chunked, index_types=IndexType.NONE,
                        use_summary_offsets=summary, use_statistics=summary, repeat_channels=summary,
                        repeat_schemas=summary)  # fmt: skip
        writer.start(profile="ros2", library="test")
        schema = writer.register_schema(
            ros2.POSE_STAMPED, "ros2msg", ros2.message_definition(ros2.POSE_STAMPED).encode()
        )
        channel = writer.register_channel("/ground_truth/pose", "cdr", schema)
        writer.add_metadata("recorder", {"tool": "test"})
        for k in range(20):
            message = ros2.serialize(ros2.pose_to_msg(Pose(k * 10**8, (k, 0, 0), (0, 0, 0, 1))), ros2.POSE_STAMPED)
            writer.add_message(channel, k * 10**8, message, k * 10**8)
        writer.finish()
    storage = describe_storage(path)
    assert (storage.compression_format, storage.compression_mode) == (expected, "chunk" if expected else "")
