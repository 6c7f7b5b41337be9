"""Hostile inputs, interrupts, determinism and read-only inputs (the reliability contract)."""

from __future__ import annotations

import contextlib
import hashlib
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from formats import ros2
from formats.log import LogReader, LogWriter
from relpoint import pipeline
from relpoint.errors import RelpointError
from relpoint.estimators import ESTIMATORS
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import PointObservation
from relpoint_app.simulation import write_simulation
from relpoint_cli.main import cli
from tests.conftest import default_interrupts

MAGIC = b"\x89MCAP0\r\n"


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def tiny_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("tiny") / "tiny.mcap"
    config = SimulationConfig(iterations=12, density=25, odometry_noise=0.05, fix_every=4, seed=8)
    write_simulation(simulate(config), path, compression="none")
    return path


def record_boundaries(data: bytes) -> list[int]:
    """Offsets where each top-level MCAP record starts (and the end of the last one)."""
    offsets, position = [], len(MAGIC)
    while position + 9 <= len(data) - len(MAGIC):
        offsets.append(position)
        (length,) = struct.unpack_from("<Q", data, position + 1)
        position += 9 + length
    offsets.append(position)
    return offsets


def consume(path: Path) -> None:
    """Every reader entry point and every point estimator over the log; only RelpointErrors may escape."""
    reader = LogReader(path)
    reader.topic_infos  # noqa: B018 - the summary is part of what must not crash
    roles = sorted(reader.available_roles())
    records = list(reader.records(roles))
    inputs = [r.value for r in records if r.role in ("points", "odometry", "fix")]
    for name in ("relpoint", "ekf", "fastslam"):
        spec = ESTIMATORS[name]
        estimator = spec.factory(spec.config_class(), np.random.default_rng(0))
        pipeline.run(iter(inputs), estimator)


def test_truncation_at_every_record_boundary(tiny_log: Path, tmp_path: Path) -> None:
    data = tiny_log.read_bytes()
    boundaries = record_boundaries(data)
    assert len(boundaries) > 20
    for cut in [*boundaries[:-1], *(b + 5 for b in boundaries[:-1])]:
        damaged = tmp_path / "cut.mcap"
        damaged.write_bytes(data[:cut])
        with pytest.raises(RelpointError):
            consume(damaged)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_random_damage_never_escapes_as_a_traceback(tiny_log: Path, tmp_path: Path, data: st.DataObject) -> None:
    original = bytearray(tiny_log.read_bytes())
    kind = data.draw(st.sampled_from(["flip", "truncate", "overwrite"]))
    if kind == "truncate":
        damaged = original[: data.draw(st.integers(0, len(original) - 1))]
    else:
        damaged = bytearray(original)
        for _ in range(data.draw(st.integers(1, 8))):
            offset = data.draw(st.integers(len(MAGIC), len(damaged) - 1))
            damaged[offset] = damaged[offset] ^ 0xFF if kind == "flip" else data.draw(st.integers(0, 255))
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(damaged))
    start = time.perf_counter()
    with contextlib.suppress(RelpointError):
        consume(path)
    assert time.perf_counter() - start < 30.0


def write_cloud(writer: LogWriter, stamp: int, **overrides: object) -> None:
    message = ros2.observation_to_msg(PointObservation(stamp, np.random.default_rng(stamp).normal(size=(8, 3)) * 5))
    for key, value in overrides.items():
        setattr(message, key, value)
    writer.write("/points", ros2.POINT_CLOUD2, message, stamp)


def test_lying_cloud_headers_are_skipped_and_counted(tmp_path: Path) -> None:
    path = tmp_path / "lying.mcap"
    with LogWriter(path) as writer:
        for k in range(1, 9):
            overrides = {}
            if k == 3:
                overrides = {"width": 200_000_000, "row_step": 3_200_000_000}  # far more than the data
            elif k == 5:
                overrides = {"point_step": 4}  # fields no longer fit
            write_cloud(writer, k * 1000, **overrides)
    reader = LogReader(path)
    observations = [r.value for r in reader.records(["points"])]
    assert len(observations) == 6
    assert reader.skipped["/points: malformed messages"] == 2


def test_wrong_schema_content_is_skipped_not_a_crash(tmp_path: Path) -> None:
    """A channel that claims PointCloud2 but carries PoseStamped bytes."""
    path = tmp_path / "liar.mcap"
    with LogWriter(path) as writer:
        for k in range(1, 5):
            pose = ros2.pose_to_msg(__import__("relpoint.types").types.Pose(k, (0, 0, 0), (0, 0, 0, 1)))
            writer._writer.add_message(
                channel_id=writer._channel("/points", ros2.POINT_CLOUD2), log_time=k, publish_time=k,
                data=ros2.serialize(pose, ros2.POSE_STAMPED),
            )  # fmt: skip
    result = CliRunner().invoke(cli, ["run", str(path), "--estimator", "ekf", "-o", str(tmp_path / "out")])
    assert result.exit_code == 3, result.stderr
    assert "no usable message" in result.stderr and len(result.stderr.strip().splitlines()) <= 2
    assert not (tmp_path / "out").exists()


POINT_ESTIMATORS = sorted(name for name, spec in ESTIMATORS.items() if "points" in spec.needs)


@pytest.mark.parametrize("name", POINT_ESTIMATORS)
def test_same_log_and_settings_give_identical_outputs(name: str, tmp_path: Path, tiny_log: Path) -> None:
    outputs = []
    for k in range(2):
        out = tmp_path / f"out{k}"
        result = CliRunner().invoke(
            cli, ["-q", "run", str(tiny_log), "--estimator", name, "--seed", "4", "-o", str(out)]
        )
        assert result.exit_code == 0, result.stderr
        outputs.append(out)
    for file in ("trajectory.tum", "trajectory.csv", "map.ply", "map.csv", "result.mcap"):
        assert (outputs[0] / file).read_bytes() == (outputs[1] / file).read_bytes(), file
    import json

    documents = [json.loads((o / "run.json").read_text()) for o in outputs]
    for document in documents:
        document.pop("timing")
    assert documents[0] == documents[1]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_interrupted_run_leaves_nothing_and_exits_130(signum: int, tmp_path: Path) -> None:
    log = tmp_path / "long.mcap"
    write_simulation(simulate(SimulationConfig(iterations=2500, density=40, seed=1)), log)
    before = sha256(log)
    out = tmp_path / "out"
    process = subprocess.Popen(
        [sys.executable, "-m", "relpoint_cli.main", "run", str(log), "--estimator", "ekf", "-o", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=default_interrupts,
    )  # fmt: skip
    time.sleep(4.0)
    assert process.poll() is None, "the run ended before it could be interrupted"
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130
    assert stderr.strip().splitlines()[-1] == "relpoint: error: interrupted; no output was written"
    assert "Traceback" not in stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["long.mcap"]  # no output, no temporary
    assert sha256(log) == before


def test_input_log_is_never_modified(tmp_path: Path, tiny_log: Path) -> None:
    before, mtime = sha256(tiny_log), os.stat(tiny_log).st_mtime_ns
    for command in (["info", str(tiny_log)], ["run", str(tiny_log), "-e", "ekf", "-o", str(tmp_path / "o")]):
        assert CliRunner().invoke(cli, ["-q", *command]).exit_code == 0
    assert sha256(tiny_log) == before and os.stat(tiny_log).st_mtime_ns == mtime


CORPUS = Path(__file__).resolve().parent / "corpus"


@pytest.mark.parametrize("path", sorted(CORPUS.glob("*.mcap")), ids=lambda p: p.name)
def test_corpus_of_damaged_logs(path: Path) -> None:
    """Damaged files that once broke a reader: each ends in a RelpointError or in skipped data."""
    try:
        reader = LogReader(path)
        list(reader.records(sorted(reader.available_roles())))
    except RelpointError:
        return
    assert sum(reader.skipped.values()) > 0


@pytest.fixture(scope="module")
def tiny_rgbd_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from relpoint.simulation.rgbd import RgbdConfig, simulate_rgbd
    from relpoint_app.simulation import write_rgbd_simulation

    path = tmp_path_factory.mktemp("rgbd") / "room.mcap"
    write_rgbd_simulation(simulate_rgbd(RgbdConfig(frames=3, reference_points=1000, seed=3)), path, compression="none")
    return path


def consume_depth(path: Path) -> None:
    """The depth readers and the dense estimator over a log; only RelpointErrors may escape."""
    from relpoint_app.runner import estimator_inputs

    reader = LogReader(path)
    spec = ESTIMATORS["dense"]
    estimator = spec.factory(spec.config_class(), np.random.default_rng(0))
    pipeline.run(estimator_inputs(reader.records(sorted(reader.available_roles()))), estimator)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_random_damage_to_depth_logs(tiny_rgbd_log: Path, tmp_path: Path, data: st.DataObject) -> None:
    original = bytearray(tiny_rgbd_log.read_bytes())
    damaged = bytearray(original)
    if data.draw(st.booleans()):
        damaged = damaged[: data.draw(st.integers(0, len(damaged) - 1))]
    else:
        for _ in range(data.draw(st.integers(1, 6))):
            offset = data.draw(st.integers(len(MAGIC), len(damaged) - 1))
            damaged[offset] ^= 0xFF
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(damaged))
    with contextlib.suppress(RelpointError):
        consume_depth(path)
