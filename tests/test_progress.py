"""Progress bars: on a terminal (sized or not), never with ``--quiet`` or when stderr is not a TTY."""

from __future__ import annotations

import os
import pty
import select
import subprocess
import sys
from pathlib import Path

import pytest


def _stderr_of(args: list[str], tmp_path: Path, *, terminal: bool) -> str:
    """What ``relpoint ARGS`` writes to stderr, on a fresh pseudo-terminal (which reports 0 columns, as
    one nobody sized does) or on a pipe."""
    command = [sys.executable, "-m", "relpoint_cli.main", *args]
    if not terminal:
        completed = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert completed.returncode == 0, completed.stderr
        return completed.stderr
    leader, follower = pty.openpty()
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=follower, cwd=tmp_path)
    os.close(follower)
    chunks = []
    while True:
        ready, _, _ = select.select([leader], [], [], 300)
        if not ready:
            process.kill()
            break
        try:
            chunk = os.read(leader, 65536)
        except OSError:  # the follower side closed: the process is gone
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(leader)
    assert process.wait(timeout=60) == 0
    return b"".join(chunks).decode("utf-8", "replace")


SIMULATE = ["simulate", "-o", "log.mcap", "--iterations", "400", "--density", "5", "--overwrite"]


def test_a_terminal_that_reports_no_width_still_shows_the_bar(tmp_path: Path) -> None:
    assert os.get_terminal_size(pty.openpty()[1]).columns == 0  # what makes this case
    shown = _stderr_of(SIMULATE, tmp_path, terminal=True)
    assert "simulate:" in shown and "iter" in shown


@pytest.mark.parametrize(("args", "terminal"), [(["-q", *SIMULATE], True), (SIMULATE, False)])
def test_no_bar_when_quiet_or_not_a_terminal(tmp_path: Path, args: list[str], terminal: bool) -> None:
    assert "simulate:" not in _stderr_of(args, tmp_path, terminal=terminal)


@pytest.mark.parametrize(("estimator", "doing"), [("relpoint", "final adjustment"), ("ekf", "smoothing trajectory")])
def test_the_run_bar_says_what_the_estimator_does_after_its_last_iteration(
    tmp_path: Path, estimator: str, doing: str
) -> None:
    _stderr_of(["-q", "simulate", "-o", "log.mcap", "--iterations", "60", "--density", "5"], tmp_path, terminal=False)
    run = ["run", "log.mcap", "-e", estimator, "-o", "out"]
    status = f"{estimator}: {doing}"
    assert status in _stderr_of(run, tmp_path, terminal=True)
    assert status not in _stderr_of(["-q", *run, "--overwrite"], tmp_path, terminal=True)
    assert status not in _stderr_of([*run, "--overwrite"], tmp_path, terminal=False)


def test_a_cropped_run_bar_does_not_count_the_whole_log(tmp_path: Path) -> None:
    _stderr_of(["-q", "simulate", "-o", "log.mcap", "--iterations", "60", "--density", "5"], tmp_path, terminal=False)
    shown = _stderr_of(["run", "log.mcap", "-e", "ekf", "-o", "out", "--t-end", "1"], tmp_path, terminal=True)
    assert "ekf:" in shown and "iter" in shown
    assert "/60" not in shown
