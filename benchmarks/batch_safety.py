"""What ``relpoint batch`` does with hostile plans, interrupts and scheduler addresses (issue 15).

Each case runs ``relpoint batch`` in a fresh process and prints one table row: case | exit code | last
stderr line | peak memory (the process's maximum resident set, from ``wait4``) | wall time.

- ``grid-1e6``: one estimator with a 10^6-point grid (6 axes of 10 values): time to refuse.
- ``glob-20k``: a plan whose glob matches 20,000 (empty) logs, loaded by ``relpoint_app.batch_plan.load_plan``
  in a fresh process (``--max-jobs 20000`` where the option exists): time to load.
- ``SIGINT`` (to the process group, as Ctrl-C in a terminal) and ``SIGTERM`` (to relpoint): a 6-job
  plan on 2 workers, signalled once the first job is done and the next are under way; time from the signal
  until the pool's workers are gone and until the command exits, then the job directories left:
  complete ones, temporaries (``.*.partial``), and whether any appeared after the exit (a worker
  still running); then the rerun that resumes the batch.
- ``scheduler``: malformed ``--scheduler`` addresses.

Usage::

    python benchmarks/batch_safety.py [--timeout 120] [--cases grid-1e6,glob-20k,SIGINT,SIGTERM,scheduler]
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

GRID_PLAN = """\
logs = ["log.mcap"]
[estimators.relpoint.grid]
match_bound = [{values}]
match_angle = [{values}]
loop_support = [3, 4, 5, 6, 7, 8, 9, 10, 11, 12]
seed = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]
ring_size = [128, 129, 130, 131, 132, 133, 134, 135, 136, 137]
match_window = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10]
"""

GLOB_PLAN = """\
logs = ["logs/**/*.mcap"]
estimators = ["relpoint"]
"""

SIGNAL_PLAN = """\
logs = ["logs/*.mcap"]
[estimators.ekf.grid]
observation_sigma = [0.3, 0.4, 0.5]
"""

LOAD_SCRIPT = """\
import inspect, sys, time
from relpoint_app.batch_plan import load_plan
start = time.perf_counter()
options = {"max_jobs": 20000} if "max_jobs" in inspect.signature(load_plan).parameters else {}
plan = load_plan(sys.argv[1], **options)
print(f"loaded {len(plan.jobs)} jobs in {time.perf_counter() - start:.2f} s", file=sys.stderr)
"""


def relpoint(*args: str) -> list[str]:
    return [sys.executable, "-m", "relpoint_cli.main", *args]


def measure(command: Sequence[str], timeout_s: float, cwd: Path | None = None) -> tuple[str, str, float, float]:
    """Exit code (or 'killed'), last stderr line, peak resident MB and wall seconds of one process."""
    start = time.perf_counter()
    with tempfile.TemporaryFile() as stderr:
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=stderr, cwd=cwd)
        deadline = start + timeout_s
        status = None
        while status is None:
            pid, wait_status, usage = os.wait4(process.pid, os.WNOHANG)
            if pid:
                status = os.waitstatus_to_exitcode(wait_status)
                break
            if time.perf_counter() > deadline:
                process.kill()
                _, wait_status, usage = os.wait4(process.pid, 0)
                status = f"killed after {timeout_s:.0f} s"
                break
            time.sleep(0.05)
        process.returncode = 0  # reaped above
        seconds = time.perf_counter() - start
        stderr.seek(0)
        lines = stderr.read().decode("utf-8", "replace").strip().splitlines()
    return str(status), (lines[-1] if lines else ""), usage.ru_maxrss / 1024, seconds


def row(case: str, code: str, line: str, peak_mb: float, seconds: float) -> None:
    print(f"| {case} | {code} | {line[:110]} | {peak_mb:.0f} MB | {seconds:.2f} s |", flush=True)


def baseline_case(timeout_s: float) -> None:
    """``relpoint batch --help``: the command's start-up (imports) alone, for comparison."""
    row("batch --help (start-up only)", *measure(relpoint("batch", "--help"), timeout_s))


def grid_case(root: Path, timeout_s: float) -> None:
    (root / "log.mcap").write_bytes(b"")
    values = ", ".join(f"{0.1 * (k + 1):.1f}" for k in range(10))
    (root / "grid.toml").write_text(GRID_PLAN.format(values=values))
    row("grid-1e6 (refuse)", *measure(relpoint("batch", str(root / "grid.toml")), timeout_s))


def glob_case(root: Path, timeout_s: float, count: int = 20_000) -> None:
    for k in range(count):
        folder = root / "logs" / f"d{k // 1000:02d}"
        folder.mkdir(parents=True, exist_ok=True)
        (folder / f"log {k}.mcap" if k % 2 else folder / f"log-{k}.mcap").write_bytes(b"")
    (root / "glob.toml").write_text(GLOB_PLAN)
    command = [sys.executable, "-c", LOAD_SCRIPT, str(root / "glob.toml")]
    row(f"glob-{count // 1000}k (load)", *measure(command, timeout_s, cwd=REPO))


def _job_dirs(results: Path) -> tuple[int, int]:
    """(complete job directories, temporaries) under ``results``."""
    complete = sum(1 for path in results.glob("*/*/*/job.json"))
    partial = sum(1 for path in results.rglob(".*.partial"))
    return complete, partial


def _descendants(pid: int) -> dict[int, int]:
    """Every descendant process of ``pid``: pid -> depth (1 = child)."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    found: dict[int, int] = {}
    frontier = [(pid, 0)]
    while frontier:
        parent, depth = frontier.pop()
        for child, its_parent in parents.items():
            if its_parent == parent and child not in found:
                found[child] = depth + 1
                frontier.append((child, depth + 1))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")


def signal_case(root: Path, signum: signal.Signals, timeout_s: float) -> None:
    from relpoint.simulation import SimulationConfig, simulate
    from relpoint_app.simulation import write_simulation

    root = root / "signals"
    logs = root / "logs"
    if not logs.exists():
        for seed in (1, 2):
            write_simulation(
                simulate(SimulationConfig(iterations=400, density=25, seed=seed)), logs / f"fig8-{seed}.mcap"
            )
        (root / "signal.toml").write_text(SIGNAL_PLAN)
    results = root / f"results-{signum.name}"
    process = subprocess.Popen(
        relpoint("batch", str(root / "signal.toml"), "--jobs", "2", "--results", str(results)),
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
    )  # fmt: skip
    while _job_dirs(results)[0] == 0 and process.poll() is None:
        time.sleep(0.05)
    if process.poll() is not None:
        raise SystemExit(f"the batch ended before a job was done: {process.communicate()[1].decode()}")
    time.sleep(0.5)  # the next jobs are under way
    before = _job_dirs(results)
    workers = [pid for pid, depth in _descendants(process.pid).items() if depth == 2]  # the fork server's children
    sent = time.perf_counter()
    if signum == signal.SIGINT:
        os.killpg(process.pid, signum)  # Ctrl-C: the terminal signals the whole process group
    else:
        process.send_signal(signum)
    workers_gone = exited = None
    while exited is None and time.perf_counter() - sent < timeout_s:
        now = time.perf_counter() - sent
        if workers_gone is None and not any(_alive(pid) for pid in workers):
            workers_gone = now
        if process.poll() is not None:
            exited = now
        time.sleep(0.01)
    if exited is None:
        process.kill()
        code = "killed"
    else:
        code = str(process.returncode)
    stderr = process.communicate()[1]
    seconds = exited if exited is not None else timeout_s
    gone = f"{workers_gone:.2f} s" if workers_gone is not None else "after exit"
    at_exit = _job_dirs(results)
    time.sleep(3.0)
    later = _job_dirs(results)
    lines = stderr.decode("utf-8", "replace").strip().splitlines()
    print(
        f"| {signum.name} | {code} | {(lines[-1] if lines else '')[:110]} | - | {seconds:.2f} s to exit |"
        f" {len(workers)} workers gone {gone} after the signal;"
        f" job dirs complete/partial: {before[0]}/{before[1]} at the signal, {at_exit[0]}/{at_exit[1]} at exit,"
        f" {later[0]}/{later[1]} 3 s later",
        flush=True,
    )
    resume = subprocess.run(
        relpoint("batch", str(root / "signal.toml"), "--jobs", "2", "--results", str(results)),
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    print(
        f"|   rerun after {signum.name} | {resume.returncode} | {resume.stdout.strip().splitlines()[-1][:110]} |",
        flush=True,
    )


def scheduler_case(timeout_s: float) -> None:
    for address in ("tcp://", "tcp://host:port", "tcp://[::1", "udp://127.0.0.1:8786", "tcp://127.0.0.1:99999"):
        with tempfile.TemporaryDirectory() as tmp:
            plan = Path(tmp) / "plan.toml"
            (Path(tmp) / "log.mcap").write_bytes(b"")
            plan.write_text('logs = ["log.mcap"]\nestimators = ["ekf"]\n')
            row(f"--scheduler {address}", *measure(relpoint("batch", str(plan), "--scheduler", address), timeout_s))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds before a case is killed")
    parser.add_argument("--cases", default="grid-1e6,glob-20k,SIGINT,SIGTERM,scheduler")
    args = parser.parse_args(argv)
    cases = args.cases.split(",")
    print("| case | exit code | last stderr line | peak memory | time |\n|---|---|---|---|---|", flush=True)
    with tempfile.TemporaryDirectory(prefix="relpoint-batch-safety-") as tmp:
        root = Path(tmp)
        if "grid-1e6" in cases:
            baseline_case(args.timeout)
            grid_case(root, args.timeout)
        if "glob-20k" in cases:
            glob_case(root, args.timeout)
        for name in ("SIGINT", "SIGTERM"):
            if name in cases:
                signal_case(root, signal.Signals[name], args.timeout)
        if "scheduler" in cases:
            scheduler_case(args.timeout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
