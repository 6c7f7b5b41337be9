"""``relpoint batch`` under hostile plans, interrupts and scheduler addresses (issue 15).

Grids are counted before they are expanded and capped by ``--max-jobs``; clashing log names are named;
globs never read outputs; Ctrl-C and SIGTERM cancel running jobs and leave no partial job directory; a
scheduler address is checked, ``tls://`` takes certificates, and plain tcp to another host is warned of.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import ClassVar

import pytest
from click.testing import CliRunner, Result

from formats.atomic import atomic_directory
from formats.outputs import MARKER
from relpoint.errors import UsageError
from relpoint.simulation import SimulationConfig, simulate
from relpoint_app import batch_jobs, batch_plan
from relpoint_app.batch_jobs import SchedulerAddress, parse_scheduler
from relpoint_app.batch_plan import MAX_JOBS, load_plan, read_results
from relpoint_app.simulation import write_simulation
from relpoint_cli.main import cli
from tests.conftest import default_interrupts

REPO = Path(__file__).resolve().parents[1]

#: One relpoint grid of 6 axes x 10 values: 10^6 grid points.
MILLION_GRID = "\n".join(
    [
        "[estimators.relpoint.grid]",
        *(f"{name} = [{', '.join(str(start + k) for k in range(10))}]"
          for name, start in (("match_window", 1), ("loop_support", 3), ("seed", 0), ("ring_size", 128),
                              ("adjustment_iterations", 1), ("seed_points", 1))),
    ]
)  # fmt: skip


def invoke(*args: str) -> Result:
    return CliRunner().invoke(cli, ["batch", *args])


def stderr_lines(result: Result) -> list[str]:
    return [line for line in result.stderr.splitlines() if line.strip()]


def write_plan(folder: Path, text: str, name: str = "plan.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def touch(*paths: Path) -> None:
    for path in paths:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")


# --- job limit ---------------------------------------------------------------------------------------


def test_million_job_grid_is_refused_before_expanding(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    touch(tmp_path / "log.mcap")
    plan = write_plan(tmp_path, 'logs = ["log.mcap"]\n' + MILLION_GRID + "\n")

    def never(*args: object, **kwargs: object) -> None:
        raise AssertionError("the grid was expanded")

    monkeypatch.setattr(batch_plan, "expand_grid", never)
    with pytest.raises(UsageError) as caught:
        load_plan(plan)
    assert "1,000,000 jobs" in str(caught.value) and "--max-jobs 10,000" in str(caught.value)
    outcome = invoke(str(plan))
    assert outcome.exit_code == 2
    assert stderr_lines(outcome) == [f"relpoint: error: {caught.value}"]


def test_max_jobs_counts_logs_simulations_and_grid_points(tmp_path: Path) -> None:
    touch(*(tmp_path / "logs" / f"log{k}.mcap" for k in range(3)))
    plan = write_plan(
        tmp_path,
        'logs = ["logs/*.mcap"]\n[[simulate]]\nname = "sim"\niterations = 20\n[simulate.grid]\nseed = [1, 2]\n'
        "[estimators.ekf.grid]\nobservation_sigma = [0.2, 0.3]\n[estimators.fastslam]\nparticles = 5\n",
    )
    # (3 globbed + 2 simulated logs) x (2 ekf + 1 fastslam points) = 15 jobs
    with pytest.raises(UsageError, match=r"makes 15 jobs \(5 log\(s\) x 3 grid point\(s\)\), more than --max-jobs 14"):
        load_plan(plan, max_jobs=14)
    jobs = load_plan(plan, max_jobs=15).jobs
    assert len(jobs) == 15 and len({job.job_id for job in jobs}) == 15
    assert MAX_JOBS == 10_000


def test_plans_are_size_capped_before_parsing(tmp_path: Path) -> None:
    big = write_plan(tmp_path, 'estimators = ["ekf"]\n' + "# padding\n" * 200_000)
    bomb = write_plan(
        tmp_path,
        "estimators: [ekf]\nx0: &x0 [a, a, a, a, a, a, a, a, a, a]\n"
        + "".join(f"x{k + 1}: &x{k + 1} [{', '.join([f'*x{k}'] * 10)}]\n" for k in range(8)),
        "bomb.yaml",
    )
    for plan, message in ((big, "is larger than 1 MB"), (bomb, "expands to more than 100000 values")):
        outcome = invoke(str(plan))
        lines = stderr_lines(outcome)
        assert outcome.exit_code == 2 and len(lines) == 1 and message in lines[0], outcome.output


def test_large_glob_loads_every_log_once_in_order(tmp_path: Path) -> None:
    names = [f"log{k:05d}" for k in range(3000)]
    touch(*(tmp_path / "logs" / f"d{k % 7}" / f"{name}.mcap" for k, name in enumerate(names)))
    plan = write_plan(tmp_path, 'logs = ["logs/**/*.mcap"]\nestimators = ["ekf"]\n')
    with pytest.raises(UsageError, match="makes 3,000 jobs"):
        load_plan(plan, max_jobs=2999)
    jobs = load_plan(plan, max_jobs=3000).jobs
    expected = sorted(tmp_path.joinpath("logs", f"d{k % 7}", f"{name}.mcap") for k, name in enumerate(names))
    assert [job.log for job in jobs] == expected
    assert [job.job_id for job in jobs] == [f"{path.stem}/ekf/default" for path in expected]


# --- job directory names -----------------------------------------------------------------------------


def test_log_names_that_clash_after_sanitising_are_named(tmp_path: Path) -> None:
    touch(tmp_path / "logs" / "a b.mcap", tmp_path / "logs" / "a-b.mcap")
    plan = write_plan(tmp_path, 'logs = ["logs/*.mcap"]\nestimators = ["ekf"]\n')
    with pytest.raises(UsageError) as caught:
        load_plan(plan)
    message = str(caught.value)
    assert str(tmp_path / "logs" / "a b.mcap") in message and str(tmp_path / "logs" / "a-b.mcap") in message
    assert "job directory name a-b" in message and "grid" not in message
    outcome = invoke(str(plan))
    assert outcome.exit_code == 2 and stderr_lines(outcome) == [f"relpoint: error: {message}"]


def test_same_stems_in_different_folders_get_a_path_hash(tmp_path: Path) -> None:
    touch(tmp_path / "x" / "run.mcap", tmp_path / "y" / "run.mcap")
    plan = write_plan(tmp_path, 'logs = ["*/run.mcap"]\nestimators = ["ekf"]\n')
    ids = [job.job_id for job in load_plan(plan).jobs]
    assert len(set(ids)) == 2 and all(i.startswith("run-") and i.endswith("/ekf/default") for i in ids)


def test_grid_values_that_clash_are_blamed_on_the_grid(tmp_path: Path) -> None:
    touch(tmp_path / "log.mcap")
    plan = write_plan(tmp_path, 'logs = ["log.mcap"]\n[estimators.ekf.grid]\nseed = [1, 1]\n')
    with pytest.raises(UsageError, match=r"grid values of estimators.ekf give the job directory ekf/seed=1 twice"):
        load_plan(plan)


# --- globs never match outputs -----------------------------------------------------------------------


def test_globs_leave_out_the_results_root_and_relpoint_outputs(tmp_path: Path) -> None:
    touch(tmp_path / "data" / "drive.mcap", tmp_path / "data" / "deep" / "walk.mcap")
    # a finished job of this batch, and a `relpoint run -o` directory elsewhere, each holding result.mcap
    for output in (tmp_path / "results" / "drive" / "ekf" / "default", tmp_path / "data" / "old-run"):
        with atomic_directory(output) as tmp:
            (tmp / "result.mcap").write_bytes(b"")
            (tmp / "nested").mkdir()
            (tmp / "nested" / "copy.mcap").write_bytes(b"")
    touch(tmp_path / "results" / "logs" / "sim.mcap")  # a simulated log of this batch
    assert (tmp_path / "data" / "old-run" / MARKER).is_file()
    plan = write_plan(tmp_path, 'logs = ["**/*.mcap"]\nestimators = ["ekf"]\n')
    logs = sorted({job.log for job in load_plan(plan).jobs})
    assert logs == [tmp_path / "data" / "deep" / "walk.mcap", tmp_path / "data" / "drive.mcap"]
    # another results root (--results) makes the old one an input tree again, but never its job outputs
    logs = sorted({job.log for job in load_plan(plan, results=tmp_path / "elsewhere").jobs})
    assert tmp_path / "results" / "logs" / "sim.mcap" in logs
    assert not any("result.mcap" in str(log) or "copy.mcap" in str(log) for log in logs)
    # a plain path is taken as given
    literal = write_plan(tmp_path, 'logs = ["data/old-run/result.mcap"]\nestimators = ["ekf"]\n', "literal.toml")
    assert [job.log for job in load_plan(literal).jobs] == [tmp_path / "data" / "old-run" / "result.mcap"]


def test_a_glob_that_matches_only_outputs_says_so(tmp_path: Path) -> None:
    with atomic_directory(tmp_path / "runs" / "a") as tmp:
        (tmp / "result.mcap").write_bytes(b"")
    plan = write_plan(tmp_path, 'logs = ["runs/**/*.mcap"]\nestimators = ["ekf"]\n')
    with pytest.raises(UsageError, match=r"matches no file \(1 inside relpoint outputs left out\)"):
        load_plan(plan)


# --- outputs -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "content"),
    [("results.csv", "name,score\nalice,3\n"), ("results.json", '{"mine": true}\n'), ("logs/sim.mcap", "recorded")],
)
def test_files_relpoint_did_not_write_are_never_replaced(tmp_path: Path, name: str, content: str) -> None:
    touch(tmp_path / "log.mcap")
    plan = write_plan(tmp_path, '[[simulate]]\nname = "sim"\niterations = 20\n[estimators.ekf]\n')
    (tmp_path / "results" / name).parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / "results" / name).write_text(content)
    outcome = invoke(str(plan), "--jobs", "1")
    lines = stderr_lines(outcome)
    assert outcome.exit_code == 2 and len(lines) == 1, outcome.output
    assert "relpoint did not write it" in lines[0] and "--results DIR" in lines[0]
    assert (tmp_path / "results" / name).read_text() == content
    assert not (tmp_path / "results" / "sim").exists()


def test_a_link_to_a_foreign_file_is_not_written_through(tmp_path: Path) -> None:
    touch(tmp_path / "log.mcap")
    (tmp_path / "precious.csv").write_text("keep me\n")
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "results.csv").symlink_to(tmp_path / "precious.csv")
    outcome = invoke(str(write_plan(tmp_path, 'logs = ["log.mcap"]\nestimators = ["ekf"]\n')), "--jobs", "1")
    assert outcome.exit_code == 2 and (tmp_path / "precious.csv").read_text() == "keep me\n"


# --- interrupts --------------------------------------------------------------------------------------


def _descendants(pid: int) -> dict[int, int]:
    """Every descendant process of ``pid``: pid -> depth (1 = child)."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
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
    except OSError:
        return False
    return state not in ("Z", "X")


@pytest.fixture(scope="module")
def long_logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("long-logs")
    for seed in (1, 2):
        write_simulation(
            simulate(SimulationConfig(iterations=250, density=25, seed=seed)), folder / f"fig8-{seed}.mcap"
        )
    return folder


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc to find the workers")
@pytest.mark.parametrize("how", ["Ctrl-C to the process group", "SIGTERM to relpoint"])
def test_interrupt_cancels_running_jobs_and_a_rerun_completes_them(long_logs: Path, tmp_path: Path, how: str) -> None:
    plan = write_plan(
        tmp_path, f'logs = ["{long_logs}/*.mcap"]\n[estimators.ekf.grid]\nobservation_sigma = [0.3, 0.5]\n'
    )
    results = tmp_path / "results"
    command = [sys.executable, "-m", "relpoint_cli.main", "batch", str(plan), "--jobs", "2", "--results", str(results)]
    process = subprocess.Popen(command, cwd=REPO, stderr=subprocess.PIPE, text=True, start_new_session=True,
                               preexec_fn=default_interrupts)  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not any(results.rglob(".*.partial")) and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert process.poll() is None, "the batch ended before a job was under way"
        time.sleep(0.3)
        workers = [pid for pid, depth in _descendants(process.pid).items() if depth == 2]  # the fork server's children
        assert workers, "no pool worker found"
        done_before = {path.parent for path in results.glob("*/*/*/job.json")}
        sent = time.monotonic()
        if how.startswith("Ctrl-C"):
            os.killpg(process.pid, signal.SIGINT)  # what a terminal does
        else:
            process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=30)
        seconds = time.monotonic() - sent
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    print(f"{how}: exit {process.returncode} {seconds:.2f} s after the signal")
    assert process.returncode == 130
    lines = stderr.strip().splitlines()
    assert lines[-1].startswith("relpoint: error: interrupted: ") and "run the same command again" in lines[-1]
    assert not any("Traceback" in line for line in lines)
    assert not any(_alive(pid) for pid in workers), "a worker outlived the batch"
    time.sleep(0.5)
    # the jobs that were running left nothing: no temporary, no directory without its files
    assert not list(results.rglob(".*.partial"))
    job_dirs = {path.parent for path in results.rglob(MARKER)}
    assert all((folder / "job.json").is_file() for folder in job_dirs)
    assert done_before <= job_dirs and len(job_dirs) < 4
    assert not (results / "results.json").exists()

    rerun = subprocess.run(command, cwd=REPO, capture_output=True, text=True, check=False, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert f"4 jobs: 4 ok ({len(job_dirs)} resumed), 0 failed" in rerun.stdout
    assert [row["status"] for row in read_results(results / "results.json")] == ["ok"] * 4


def test_interrupt_cancels_running_dask_jobs(long_logs: Path, tmp_path: Path) -> None:
    from distributed import LocalCluster

    plan = write_plan(
        tmp_path, f'logs = ["{long_logs}/*.mcap"]\n[estimators.ekf.grid]\nobservation_sigma = [0.3, 0.5]\n'
    )
    results = tmp_path / "results"
    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
    ) as cluster:
        command = [sys.executable, "-m", "relpoint_cli.main", "batch", str(plan), "--scheduler",
                   cluster.scheduler_address, "--results", str(results)]  # fmt: skip
        process = subprocess.Popen(command, cwd=REPO, stderr=subprocess.PIPE, text=True, preexec_fn=default_interrupts)
        try:
            deadline = time.monotonic() + 120
            while not any(results.rglob(".*.partial")) and process.poll() is None and time.monotonic() < deadline:
                time.sleep(0.02)
            assert process.poll() is None, "the batch ended before a job was under way"
            process.send_signal(signal.SIGTERM)
            _, stderr = process.communicate(timeout=30)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
        done_at_exit = {folder.parent for folder in results.rglob(MARKER)}
        assert process.returncode == 130
        assert stderr.strip().splitlines()[-1].startswith("relpoint: error: interrupted: ")
        # the cluster's running jobs stop at their next iteration and leave nothing
        deadline = time.monotonic() + 10
        while any(results.rglob(".*.partial")) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not list(results.rglob(".*.partial"))
        time.sleep(1.0)
        assert {folder.parent for folder in results.rglob(MARKER)} == done_at_exit, "a cancelled job completed"
        assert all((folder / "job.json").is_file() for folder in done_at_exit)


def test_no_resume_runs_every_job_again(long_logs: Path, tmp_path: Path) -> None:
    short = tmp_path / "short.mcap"
    write_simulation(simulate(SimulationConfig(iterations=30, density=10, seed=4)), short)
    plan = write_plan(tmp_path, f'logs = ["{short}"]\nestimators = ["ekf"]\n[evaluation]\nkitti = false\n')
    assert invoke(str(plan), "--jobs", "1").exit_code == 0
    job_json = tmp_path / "results" / "short" / "ekf" / "default" / "job.json"
    first = job_json.stat().st_mtime_ns
    resumed = invoke(str(plan), "--jobs", "1", "--resume")
    assert resumed.exit_code == 0 and "1 ok (1 resumed)" in resumed.stdout and job_json.stat().st_mtime_ns == first
    again = invoke(str(plan), "--jobs", "1", "--no-resume")
    assert again.exit_code == 0 and "1 ok (0 resumed)" in again.stdout and job_json.stat().st_mtime_ns != first


# --- the scheduler -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "address",
    ["tcp://", "tcp://host:port", "tcp://[::1", "udp://127.0.0.1:8786", "tcp://127.0.0.1:99999", "tcp://a b:1",
     "tcp://[not-ipv6]:8786", "127.0.0.1", "x" * 5000],
)  # fmt: skip
def test_malformed_scheduler_address_is_a_usage_error(tmp_path: Path, address: str) -> None:
    touch(tmp_path / "log.mcap")
    plan = write_plan(tmp_path, 'logs = ["log.mcap"]\nestimators = ["ekf"]\n')
    outcome = invoke(str(plan), "--scheduler", address)
    assert outcome.exit_code == 2, outcome.output
    lines = stderr_lines(outcome)
    assert len(lines) == 1 and lines[0].startswith("relpoint: error: --scheduler ") and len(lines[0]) < 300
    assert "tcp://HOST:PORT or tls://HOST:PORT" in lines[0]


def test_scheduler_addresses_parse_and_know_local_hosts() -> None:
    assert parse_scheduler("tcp://127.0.0.1:8786") == SchedulerAddress("tcp", "127.0.0.1", 8786)
    assert parse_scheduler("10.0.0.5:8786") == SchedulerAddress("tcp", "10.0.0.5", 8786)
    assert str(parse_scheduler("tls://[::1]:8786")) == "tls://[::1]:8786"
    assert parse_scheduler("TLS://Sched.example.org:1") == SchedulerAddress("tls", "Sched.example.org", 1)
    local = ["tcp://127.0.0.1:1", "tcp://127.8.9.1:1", "tcp://localhost:1", "tcp://[::1]:1"]
    remote = ["tcp://10.0.0.5:1", "tcp://sched.example.org:1", "tcp://[2001:db8::1]:1"]
    assert all(parse_scheduler(a).is_local for a in local)
    assert not any(parse_scheduler(a).is_local for a in remote)


class _Unreachable:
    """Stands in for ``distributed.Client``: records how it was called and fails to connect."""

    calls: ClassVar[list[tuple[str, object]]] = []

    def __init__(self, address: str, timeout: float, security: object = None) -> None:
        _Unreachable.calls.append((address, security))
        raise OSError("connection refused")


@pytest.fixture()
def unreachable(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, object]]:
    import distributed

    _Unreachable.calls = []
    monkeypatch.setattr(distributed, "Client", _Unreachable)
    return _Unreachable.calls


def test_plain_tcp_to_another_host_is_warned_of(tmp_path: Path, unreachable: list[tuple[str, object]]) -> None:
    touch(tmp_path / "log.mcap")
    plan = write_plan(tmp_path, 'logs = ["log.mcap"]\nestimators = ["ekf"]\n')
    remote = invoke(str(plan), "--scheduler", "tcp://10.0.0.5:8786")
    assert remote.exit_code == 3
    lines = stderr_lines(remote)
    assert lines[0].startswith("relpoint: warning: the scheduler tcp://10.0.0.5:8786 is reached over plain tcp")
    assert lines[-1].startswith("relpoint: error: cannot connect to the Dask scheduler at tcp://10.0.0.5:8786")
    local = invoke(str(plan), "--scheduler", "tcp://127.0.0.1:8786")
    assert local.exit_code == 3 and "warning" not in local.stderr
    assert unreachable == [("tcp://10.0.0.5:8786", None), ("tcp://127.0.0.1:8786", None)]


@pytest.fixture(scope="module")
def certificate(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A self-signed certificate (its own CA) and its key, made by openssl."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    folder = tmp_path_factory.mktemp("tls")
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out", str(cert),
         "-days", "2", "-subj", "/CN=relpoint-test"],
        check=True, capture_output=True,
    )  # fmt: skip
    return cert, key


def test_tls_options_are_checked_before_connecting(
    tmp_path: Path, certificate: tuple[Path, Path], unreachable: list[tuple[str, object]]
) -> None:
    cert, key = certificate
    touch(tmp_path / "log.mcap")
    (tmp_path / "junk.pem").write_text("not a certificate\n")
    plan = str(write_plan(tmp_path, 'logs = ["log.mcap"]\nestimators = ["ekf"]\n'))
    cases = {
        ("--scheduler", "tls://127.0.0.1:8786"): "needs --tls-ca-file and --tls-cert",
        ("--scheduler", "tcp://127.0.0.1:8786", "--tls-ca-file", str(cert)): "need a tls:// scheduler address",
        ("--tls-ca-file", str(cert)): "go with --scheduler tls://HOST:PORT",
        ("--scheduler", "tls://127.0.0.1:8786", "--tls-cert", str(cert)): "needs --tls-ca-file and --tls-cert",
        ("--scheduler", "tls://127.0.0.1:8786", "--tls-ca-file", str(cert)): "needs --tls-ca-file and --tls-cert",
        ("--scheduler", "tls://127.0.0.1:8786", "--tls-ca-file", str(tmp_path / "junk.pem"), "--tls-cert", str(cert),
         "--tls-key", str(key)): "cannot use the TLS files",
        ("--scheduler", "tls://127.0.0.1:8786", "--tls-ca-file", str(cert), "--tls-cert", str(cert)):
            "cannot use the TLS files",  # the key is not inside the certificate
    }  # fmt: skip
    for options, message in cases.items():
        outcome = invoke(plan, *options)
        lines = stderr_lines(outcome)
        assert outcome.exit_code == 2 and len(lines) == 1 and message in lines[0], (options, outcome.output)
    assert unreachable == []
    outcome = invoke(plan, "--scheduler", "tls://10.0.0.5:8786", "--tls-ca-file", str(cert), "--tls-cert", str(cert),
                     "--tls-key", str(key))  # fmt: skip
    assert outcome.exit_code == 3 and "warning" not in outcome.stderr
    [(address, security)] = unreachable
    assert address == "tls://10.0.0.5:8786"
    assert security.require_encryption and security.tls_ca_file == str(cert) and security.tls_client_key == str(key)


def test_tls_scheduler_runs_the_batch(tmp_path: Path, certificate: tuple[Path, Path]) -> None:
    from distributed import LocalCluster
    from distributed.security import Security

    cert, key = certificate
    log = tmp_path / "short.mcap"
    write_simulation(simulate(SimulationConfig(iterations=30, density=10, seed=5)), log)
    plan = write_plan(tmp_path, f'logs = ["{log}"]\nestimators = ["ekf"]\n[evaluation]\nkitti = false\n')
    security = Security(
        tls_ca_file=str(cert), tls_scheduler_cert=str(cert), tls_scheduler_key=str(key), tls_worker_cert=str(cert),
        tls_worker_key=str(key), tls_client_cert=str(cert), tls_client_key=str(key), require_encryption=True,
    )  # fmt: skip
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, protocol="tls", host="127.0.0.1", security=security,
        dashboard_address=None,
    ) as cluster:  # fmt: skip
        assert cluster.scheduler_address.startswith("tls://")
        plain = invoke(str(plan), "--scheduler", cluster.scheduler_address.replace("tls://", "tcp://"))
        outcome = invoke(str(plan), "--scheduler", cluster.scheduler_address, "--tls-ca-file", str(cert),
                         "--tls-cert", str(cert), "--tls-key", str(key))  # fmt: skip
    assert plain.exit_code == 3, plain.output  # a TLS scheduler does not speak plain tcp
    assert outcome.exit_code == 0, outcome.output
    rows = json.loads((tmp_path / "results" / "results.json").read_text())["jobs"]
    assert [(row["job"], row["status"]) for row in rows] == [("short/ekf/default", "ok")]


def test_executor_stop_ignores_a_second_interrupt(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[object] = []

    class Recording(batch_jobs.Executor):
        def map_unordered(self, function, items):  # type: ignore[no-untyped-def]
            return iter(())

        def cancel_pending(self) -> None:
            pass

        def stop(self) -> None:
            seen.append(signal.getsignal(signal.SIGINT))

        def close(self) -> None:
            seen.append("close")

    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # whatever the test runner inherited
    try:
        with pytest.raises(KeyboardInterrupt), Recording():
            raise KeyboardInterrupt
        with Recording():
            pass
        assert seen == [signal.SIG_IGN, "close"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored after the clean-up
    finally:
        signal.signal(signal.SIGINT, before)
