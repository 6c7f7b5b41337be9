"""The command line: simulate, info, config files, determinism and one-line errors."""

from __future__ import annotations

import hashlib
import io
import json
import math
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from formats.evo_results import EvoResult, write_evo_result
from formats.log import LogReader, TopicInfo
from formats.run_output import write_run_directory
from relpoint.evaluation import EvaluationSettings
from relpoint.types import LandmarkMap, RunResult, Trajectory
from relpoint_app.batch_jobs import _finish
from relpoint_app.batch_plan import Job
from relpoint_cli.main import cli


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def invoke(runner: CliRunner, *args: str) -> tuple[int, str, str]:
    result = runner.invoke(cli, list(args), catch_exceptions=False)
    return result.exit_code, result.stdout, result.stderr


def test_help_and_version(runner: CliRunner) -> None:
    code, out, _ = invoke(runner, "--help")
    assert code == 0 and "Examples:" in out and "simulate" in out and "Exit codes" in out
    code, out, _ = invoke(runner, "simulate", "--help")
    assert code == 0 and "--density" in out and "--odometry-noise" in out and "--fix-every" in out
    code, out, _ = invoke(runner, "--version")
    assert code == 0 and "relpoint, version" in out


def test_same_seed_gives_byte_identical_logs(runner: CliRunner, tmp_path: Path) -> None:
    args = ["--iterations", "150", "--dynamic", "0.2", "--clutter", "1", "--odometry-noise", "0.05", "--fix-every", "7"]
    paths = [tmp_path / "a.mcap", tmp_path / "b.mcap", tmp_path / "c.mcap"]
    for path, seed in zip(paths, ("4", "4", "5"), strict=True):
        code, _, err = invoke(runner, "simulate", "-o", str(path), "--seed", seed, *args)
        assert code == 0, err
    assert sha256(paths[0]) == sha256(paths[1])
    assert sha256(paths[0]) != sha256(paths[2])


def test_config_files_and_option_precedence(runner: CliRunner, tmp_path: Path) -> None:
    toml = tmp_path / "sim.toml"
    toml.write_text('[simulate]\nscenario = "corridor"\niterations = 40\ndensity = 60\nfix-every = 4\nseed = 2\n')
    yaml = tmp_path / "sim.yaml"
    yaml.write_text("scenario: corridor\niterations: 40\ndensity: 60\nfix_every: 4\nseed: 2\n")
    for config, out in ((toml, "t.mcap"), (yaml, "y.mcap")):
        code, _, err = invoke(runner, "simulate", "-o", str(tmp_path / out), "--config", str(config))
        assert code == 0, err
    assert sha256(tmp_path / "t.mcap") == sha256(tmp_path / "y.mcap")
    reader = LogReader(tmp_path / "t.mcap")
    assert reader.topic_infos["/points"].count == 40 and reader.topic_infos["/fix"].count == 10
    settings = json.loads(reader.metadata()["relpoint.simulation"]["density"])
    assert settings == 60
    # An option on the command line beats the file.
    code, _, _ = invoke(runner, "simulate", "-o", str(tmp_path / "o.mcap"), "--config", str(toml), "--iterations", "12")
    assert code == 0 and LogReader(tmp_path / "o.mcap").topic_infos["/points"].count == 12
    bad = tmp_path / "bad.toml"
    bad.write_text("densty = 3\n")
    code, _, err = invoke(runner, "simulate", "-o", str(tmp_path / "x.mcap"), "--config", str(bad))
    assert code == 2 and "unknown simulation setting(s): densty" in err
    assert not (tmp_path / "x.mcap").exists()


def test_info_lists_topics_rates_and_capabilities(runner: CliRunner, small_log: Path) -> None:
    code, out, _ = invoke(runner, "info", str(small_log), "--json")
    assert code == 0
    document = json.loads(out)
    topics = {t["topic"]: t for t in document["topics"]}
    assert topics["/points"]["count"] == 120 and topics["/points"]["rate_hz"] == pytest.approx(10.0)
    assert topics["/fix"]["count"] == 12 and topics["/fix"]["rate_hz"] == pytest.approx(1.0)
    assert topics["/odom"]["type"] == "nav_msgs/msg/Odometry" and topics["/odom"]["role"] == "odometry"
    assert document["duration_s"] == pytest.approx(11.9)
    assert document["evaluate_trajectory"] and document["evaluate_landmarks"]
    code, out, _ = invoke(runner, "info", str(small_log))
    assert code == 0 and "/ground_truth/pose" in out and "10.00" in out


def strict_json(text: str) -> object:
    """``text`` parsed as strict JSON: NaN and Infinity, which Python writes by default, are refused."""

    def refuse(constant: str) -> None:
        raise AssertionError(f"{constant} in JSON")

    return json.loads(text, parse_constant=refuse)


def test_every_json_relpoint_writes_is_strict(
    runner: CliRunner, small_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # non-finite figures are null in run.json, job.json, an evo zip's stats.json and info --json
    n = 3
    trajectory = Trajectory(np.arange(n) * 100_000_000, np.zeros((n, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)))
    landmarks = LandmarkMap(np.eye(3), np.full(3, 2), np.zeros(3, dtype=bool), np.arange(3))
    result = RunResult(trajectory, landmarks, np.full(n, 3), np.full(n, 3), np.full(n, 0.01),
                       summary={"acceleration_measured": math.nan, "nested": {"ratio": math.inf}})  # fmt: skip
    write_run_directory(tmp_path / "run", result, {"estimator": "ekf"})
    summary = strict_json((tmp_path / "run" / "run.json").read_text())["summary"]
    assert summary["acceleration_measured"] is None and summary["nested"] == {"ratio": None}

    write_evo_result(tmp_path / "e.zip", EvoResult({"title": "APE w.r.t. translation part (m)"},
                                                   {"rmse": 0.5, "std": math.nan}))  # fmt: skip
    with zipfile.ZipFile(tmp_path / "e.zip") as archive:
        assert strict_json(archive.read("stats.json").decode()) == {"rmse": 0.5, "std": None}

    job = Job("small/ekf/default", small_log, "ekf", (), 0, True, True, (), EvaluationSettings(), tmp_path / "job")
    (tmp_path / "job").mkdir()
    _finish(tmp_path / "job", job, {"ate_rmse": math.nan, "wall_seconds": 1.5}, "", io.StringIO())
    assert strict_json((tmp_path / "job" / "job.json").read_text())["row"] == {"ate_rmse": None, "wall_seconds": 1.5}

    monkeypatch.setattr(TopicInfo, "rate_hz", property(lambda self: math.inf))
    code, out, _ = invoke(runner, "info", str(small_log), "--json")
    assert code == 0 and all(topic["rate_hz"] is None for topic in strict_json(out)["topics"])


def test_info_names_the_topics_that_could_serve_a_missing_role(runner: CliRunner, small_log: Path) -> None:
    # A driver's topic names: info said "cannot run (missing points)" and left the user to guess the option.
    code, out, _ = invoke(runner, "info", str(small_log), "--points-topic", "/lidar", "--json")
    assert code == 0
    document = json.loads(out)
    assert document["candidate_topics"]["points"] == ["/points"]
    assert "ground_truth_pose" not in document["candidate_topics"]  # nothing missing there
    code, out, _ = invoke(runner, "info", str(small_log), "--points-topic", "/lidar")
    assert "points (sensor_msgs/msg/PointCloud2) may be on /points: name it with --points-topic" in out


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "relpoint_cli.main", *args], capture_output=True, text=True, cwd=cwd, timeout=120
    )


@pytest.mark.parametrize("case", ["missing", "text", "truncated", "directory"])
def test_unusable_files_give_one_line_and_exit_3(tmp_path: Path, small_log: Path, case: str) -> None:
    path = tmp_path / "log.mcap"
    if case == "text":
        path.write_text("not a log")
    elif case == "truncated":
        path.write_bytes(small_log.read_bytes()[: small_log.stat().st_size // 2])
    elif case == "directory":
        path.mkdir()
    result = run_cli("info", str(path))
    assert result.returncode == 3
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("relpoint: error: ") and "Traceback" not in result.stderr


def test_unknown_options_give_one_line_and_exit_2(tmp_path: Path) -> None:
    result = run_cli("simulate", "-o", str(tmp_path / "x.mcap"), "--xyzzy")
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "relpoint: error: No such option '--xyzzy'. (see 'relpoint simulate --help')"
    ]
    result = run_cli("simulate", "-o", str(tmp_path / "x.mcap"), "--noise", "-2")
    assert result.returncode == 2 and "noise must be between 0 and 1000" in result.stderr
    assert not (tmp_path / "x.mcap").exists()


@pytest.mark.parametrize("where", ["before", "after"])
def test_quiet_is_accepted_before_or_after_the_command(runner: CliRunner, tmp_path: Path, where: str) -> None:
    log = tmp_path / "q.mcap"
    args = ["simulate", "-o", str(log), "--iterations", "10"]
    code, _, err = invoke(runner, *(["-q", *args] if where == "before" else [*args, "-q"]))
    assert code == 0 and err == ""
    code, _, err = invoke(runner, *args)
    assert code == 0 and err.startswith("wrote ")


def test_every_commands_help_renders_without_markup(runner: CliRunner) -> None:
    for command in cli.list_commands(None):  # type: ignore[arg-type]
        code, out, _ = invoke(runner, command, "--help")
        assert code == 0 and "\\b" not in out and "\b" not in out, command


def test_top_level_help_lists_every_command_without_importing_them() -> None:
    from relpoint_cli.main import COMMANDS, SUMMARIES

    assert set(SUMMARIES) == set(COMMANDS)
    code = ("import sys; from relpoint_cli.main import main; sys.argv = ['relpoint', '--help']\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.startswith(('numpy', 'relpoint_cli.', 'scipy'))))")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert all(name in out for name in COMMANDS)
    assert out.strip().splitlines()[-1] == "['relpoint_cli.errors', 'relpoint_cli.main']"


def test_estimator_names_complete_in_the_shell(tmp_path: Path) -> None:
    import os

    env = {
        **os.environ,
        "COMP_WORDS": "relpoint run x.mcap -e fa",
        "COMP_CWORD": "4",
        "_RELPOINT_COMPLETE": "bash_complete",
    }
    out = subprocess.run([sys.executable, "-m", "relpoint_cli.main"], env=env, capture_output=True, text=True)
    assert out.stdout.split() == ["plain,fastslam"]


def test_config_describes_each_setting(runner: CliRunner) -> None:
    code, out, _ = invoke(runner, "config", "--estimator", "ekf")
    assert code == 0
    line = next(text for text in out.splitlines() if text.lstrip("# ").startswith("observation_sigma ="))
    assert "Standard deviation of a point measurement, per axis (m)." in line and "[1e-06 .. 1000]" in line
    settings = [text for text in out.splitlines()[1:] if " = " in text]
    assert sum("  # " in text for text in settings) == len(settings)


def test_info_prints_the_duration_as_exactly_as_start_and_end(runner: CliRunner, tmp_path: Path) -> None:
    log = tmp_path / "thirds.mcap"  # 3 Hz: stamps 333333333 ns apart, off the microsecond grid
    code, _, err = invoke(runner, "simulate", "-o", str(log), "--iterations", "4", "--rate", "3")
    assert code == 0, err
    code, out, _ = invoke(runner, "info", str(log))
    assert code == 0
    rows = {line.split(":", 1)[0].strip(): line.split(":", 1)[1].strip() for line in out.splitlines()[1:9]}
    start, end = (int(rows[key].rsplit("(", 1)[1].rstrip(")").replace(".", "")) for key in ("start", "end"))
    assert end - start == 999_999_999
    assert rows["duration"] == "0.999999999 s"
