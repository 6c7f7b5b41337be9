"""``--t-start``/``--t-end``: run, evaluate and export crop to the same stretch of time."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from formats.trajectory_files import read_tum
from relpoint.types import TimeWindow, Trajectory
from relpoint_cli.main import cli


def invoke(*args: str | Path) -> tuple[int, str, str]:
    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result.exit_code, result.stdout, result.stderr


def test_a_window_counts_from_the_first_stamp_and_keeps_its_ends() -> None:
    trajectory = Trajectory(np.arange(5, 15) * 1_000_000_000, np.zeros((10, 3)), np.tile([0, 0, 0, 1.0], (10, 1)))
    assert trajectory.cropped(TimeWindow(2.0, 4.0)).stamps_ns.tolist() == [7e9, 8e9, 9e9]
    assert trajectory.cropped(TimeWindow(end_s=1.0), first_ns=0).stamps_ns.tolist() == []
    assert trajectory.cropped(TimeWindow(start_s=8.0)).stamps_ns.tolist() == [13e9, 14e9]
    assert trajectory.cropped(TimeWindow()) is trajectory
    with pytest.raises(ValueError, match="ends"):
        TimeWindow(3.0, 2.0)
    with pytest.raises(ValueError, match="between"):
        TimeWindow(float("nan"))


def test_run_evaluate_and_export_crop_the_same_stretch(tmp_path: Path, small_log: Path) -> None:
    out = tmp_path / "run"
    code, _, err = invoke("run", small_log, "-e", "ekf", "-o", out, "--t-start", "2", "--t-end", "5")
    assert code == 0, err
    estimate = read_tum(out / "trajectory.tum")
    first = estimate.stamps_ns[0]
    assert len(estimate) > 10 and (estimate.stamps_ns[-1] - first) <= 3e9
    assert json.loads((out / "run.json").read_text())["time_window"] == {"start_s": 2.0, "end_s": 5.0}

    code, _, err = invoke("evaluate", out, "-r", small_log, "--json", tmp_path / "e.json", "--t-start", "3",
                          "--t-end", "4", "--align", "se3")  # fmt: skip
    assert code == 0, err
    summary = json.loads((tmp_path / "e.json").read_text())["summary"]
    assert summary["matched_poses"] == summary["reference_poses"] == summary["estimate_poses"]
    assert 0.9 <= summary["duration_s"] <= 1.0

    code, _, err = invoke("export", out / "trajectory.tum", "-o", tmp_path / "part.tum", "--t-start", "1")
    assert code == 0, err
    part = read_tum(tmp_path / "part.tum")
    assert part.stamps_ns[0] >= first + 1e9 and part.stamps_ns[-1] == estimate.stamps_ns[-1]


def test_an_empty_window_is_a_usage_error() -> None:
    code, _, err = invoke("export", "x.tum", "-o", "y.tum", "--t-start", "5", "--t-end", "1")
    assert code == 2 and err.count("\n") == 1 and "--t-start/--t-end" in err


def test_a_window_past_the_end_of_the_log_is_an_input_error_naming_its_span(tmp_path: Path, small_log: Path) -> None:
    code, _, err = invoke("run", small_log, "-e", "ekf", "-o", tmp_path / "late", "--t-start", "1000")
    assert code == 3
    assert err.startswith(f"relpoint: error: {small_log}: --t-start 1000 leaves no observation; the log spans ")
    assert err.count("\n") == 1 and "seconds from the log's first message" in err
    assert not (tmp_path / "late").exists()
