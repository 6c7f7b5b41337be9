"""``relpoint batch``: plans, the local pool against a Dask cluster, resuming, failures and --fail-fast."""

from __future__ import annotations

import gc
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner, Result
from distributed import LocalCluster

from relpoint.errors import UsageError
from relpoint_app.batch_jobs import JOB_FILES, completed_row
from relpoint_app.batch_plan import RESULT_COLUMNS, TIMING_COLUMNS, load_plan, read_results
from relpoint_cli.main import cli

#: 2 simulated logs x (ekf, fastslam) x a 2-value grid = 8 jobs of 60 iterations.
PLAN = """\
results = "results"

[[simulate]]
name = "fig8"
iterations = 60
density = 10
[simulate.grid]
seed = [1, 2]

[estimators.ekf.grid]
observation_sigma = [0.3, 0.5]

[estimators.fastslam]
particles = 5
[estimators.fastslam.grid]
seed = [0, 1]

[evaluation]
align = "se3"
kitti = false
"""

PLAN_YAML = """\
results: results
simulate:
  - name: fig8
    iterations: 60
    density: 10
    grid: {seed: [1, 2]}
estimators:
  ekf:
    grid: {observation_sigma: [0.3, 0.5]}
  fastslam:
    particles: 5
    grid: {seed: [0, 1]}
evaluation: {align: se3, kitti: false}
"""


def invoke(*args: str) -> Result:
    return CliRunner().invoke(cli, ["batch", *args])


def comparable(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows without timing columns, logs by file name (each batch simulates its own)."""
    return [
        {key: (Path(value).name if key == "log" else value) for key, value in row.items() if key not in TIMING_COLUMNS}
        for row in rows
    ]


@pytest.fixture(scope="module")
def plan_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("plan") / "plan.toml"
    path.write_text(PLAN)
    return path


@pytest.fixture(scope="module")
def local_run(plan_file: Path) -> tuple[Path, list[dict[str, Any]]]:
    """The plan run once on a local pool of two processes: (results root, rows)."""
    results = plan_file.parent / "local"
    outcome = invoke(str(plan_file), "--jobs", "2", "--results", str(results))
    assert outcome.exit_code == 0, outcome.output
    return results, read_results(results / "results.json")


@pytest.fixture()
def bad_log(tmp_path: Path) -> Path:
    path = tmp_path / "bad" / "broken.mcap"
    path.parent.mkdir()
    path.write_bytes(b"\x89MCAP0\r\n" + b"not really a log" * 8)
    return path


def test_plan_expands_logs_estimators_and_grids(plan_file: Path, tmp_path: Path) -> None:
    plan = load_plan(plan_file)
    assert [step.name for step in plan.simulations] == ["fig8-seed=1", "fig8-seed=2"]
    assert [step.config.seed for step in plan.simulations] == [1, 2]
    assert [job.job_id for job in plan.jobs] == [
        f"fig8-seed={s}/{e}" for s in (1, 2)
        for e in ("ekf/observation_sigma=0.3", "ekf/observation_sigma=0.5", "fastslam/seed=0", "fastslam/seed=1")
    ]  # fmt: skip
    assert plan.jobs[2].parameters == (("particles", 5),) and plan.jobs[3].seed == 1
    assert plan.results == plan_file.parent / "results"
    yaml_file = plan_file.parent / "plan.yaml"
    yaml_file.write_text(PLAN_YAML)
    assert [job.describe() for job in load_plan(yaml_file).jobs] == [job.describe() for job in plan.jobs]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('logs = "*.mcap"\nestimators = ["ekf"]\n', "matches no file"),
        ('[[simulate]]\nname = "a"\n[estimators.magic]\n', "unknown estimator 'magic'"),
        (
            '[[simulate]]\nname = "a"\n[estimators.ekf]\nno_such = 1\n',
            "unknown ekf setting(s): no_such; see `relpoint config --estimator ekf`",
        ),
        ('[[simulate]]\nname = "a"\n[estimators.ekf.grid]\nobservation_sigma = 0.3\n', "must be a non-empty list"),
        ('estimators = ["ekf"]\n[[simulate]]\nname = "a"\n[evaluation]\nalign = "banana"\n', "align"),
        (
            '[[simulate]]\nname = "a"\ndensity = -1\n[estimators.ekf]\n',
            "simulate[0]: simulation setting density must be between 0.001",
        ),
        ('estimators = ["ekf"]\n', "names no logs"),
        ("jobs = 3\n", "unknown key(s) jobs"),
    ],
)
def test_bad_plans_are_usage_errors(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "plan.toml"
    path.write_text(text)
    with pytest.raises(UsageError) as caught:
        load_plan(path)
    assert message in str(caught.value)
    outcome = invoke(str(path))
    assert outcome.exit_code == 2 and message in outcome.stderr
    assert gc.isenabled()  # the start-up's pause of the garbage collector ends with the command's error too


def test_local_pool_runs_evaluates_and_writes_every_job(local_run: tuple[Path, list[dict[str, Any]]]) -> None:
    results, rows = local_run
    assert len(rows) == 8 and all(row["status"] == "ok" for row in rows)
    assert (results / "results.csv").read_text().splitlines()[0] == ",".join(RESULT_COLUMNS)
    assert len((results / "results.csv").read_text().splitlines()) == 9
    for row in rows:
        job_dir = results / row["job"]
        assert all((job_dir / name).is_file() for name in JOB_FILES), row["job"]
        evaluation = json.loads((job_dir / "evaluation.json").read_text())
        assert evaluation["summary"]["ate_rmse"] == row["ate_rmse"]
        assert evaluation["summary"]["lm_err_rmse"] == row["landmark_rmse"]
        assert row["iterations"] == 60 and row["seconds_per_iteration"] > 0 and row["landmarks"] > 5
        assert math.isfinite(row["ate_rmse"]) and math.isfinite(row["landmark_rmse"])
        assert "job done" in (job_dir / "job.log").read_text()
    # The EKF tracks these short loops to within decimetres; a broken hand-over of settings would not.
    assert max(row["ate_rmse"] for row in rows if row["estimator"] == "ekf") < 1.0
    sigmas = {
        json.loads((results / r["job"] / "run.json").read_text())["parameters"]["observation_sigma"] for r in rows[:2]
    }
    assert sigmas == {0.3, 0.5}
    # The job's evaluation is the one `relpoint evaluate` gives for its directory.
    first = rows[0]
    cli_json = results / "cli_evaluation.json"
    outcome = CliRunner().invoke(
        cli, ["-q", "evaluate", str(results / first["job"]), "--reference", first["log"], "--align", "se3",
              "--json", str(cli_json)],
    )  # fmt: skip
    assert outcome.exit_code == 0, outcome.output
    assert json.loads(cli_json.read_text())["summary"]["ate_rmse"] == first["ate_rmse"]


def test_dask_cluster_gives_the_local_pool_results(
    plan_file: Path, local_run: tuple[Path, list[dict[str, Any]]]
) -> None:
    results = plan_file.parent / "dask"
    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
    ) as cluster:
        outcome = invoke(str(plan_file), "--scheduler", cluster.scheduler_address, "--results", str(results))
    assert outcome.exit_code == 0, outcome.output
    rows = read_results(results / "results.json")
    assert comparable(rows) == comparable(local_run[1])
    assert all((results / "logs" / f"fig8-seed={s}.mcap").is_file() for s in (1, 2))


def test_rerun_skips_completed_jobs_and_redoes_missing_ones(
    plan_file: Path, local_run: tuple[Path, list[dict[str, Any]]]
) -> None:
    results, rows = local_run
    stamps = {row["job"]: (results / row["job"] / "job.json").stat().st_mtime_ns for row in rows}
    outcome = invoke(str(plan_file), "--jobs", "2", "--results", str(results))
    assert outcome.exit_code == 0 and "8 ok (8 resumed)" in outcome.stdout
    assert {job: (results / job / "job.json").stat().st_mtime_ns for job in stamps} == stamps
    (results / rows[5]["job"] / "evaluation.json").unlink()  # an incomplete output is redone
    outcome = invoke(str(plan_file), "--jobs", "1", "--results", str(results))
    assert outcome.exit_code == 0 and "8 ok (7 resumed)" in outcome.stdout
    assert comparable(read_results(results / "results.json")) == comparable(rows)
    # Changed evaluation settings make every stored output stale.
    changed = plan_file.parent / "changed.toml"
    changed.write_text(PLAN.replace('align = "se3"', 'align = "sim3"'))
    assert all(completed_row(job) is None for job in load_plan(changed, results=results).jobs)
    assert all(completed_row(job) is not None for job in load_plan(plan_file, results=results).jobs)


def test_failed_job_is_recorded_and_the_others_complete(
    tmp_path: Path, bad_log: Path, local_run: tuple[Path, list[dict[str, Any]]]
) -> None:
    logs = local_run[0] / "logs"
    plan = tmp_path / "plan.toml"
    plan.write_text(f'logs = ["{bad_log}", "{logs}/*1.mcap"]\nestimators = ["ekf"]\n[evaluation]\nkitti = false\n')
    outcome = invoke(str(plan), "--jobs", "2")
    assert outcome.exit_code == 4, outcome.output
    assert "1 of 2 job(s) failed" in outcome.stderr
    rows = read_results(tmp_path / "results" / "results.json")
    assert [(row["job"], row["status"]) for row in rows] == [
        ("broken/ekf/default", "failed"),
        ("fig8-seed=1/ekf/default", "ok"),
    ]
    assert rows[0]["error"].startswith("InputError") and rows[1]["error"] is None
    job_log = (tmp_path / "results" / "broken" / "ekf" / "default" / "job.log").read_text()
    assert "FAILED: InputError" in job_log and "Traceback" in job_log
    assert "failed broken/ekf/default: InputError" in outcome.stdout
    assert f"see {tmp_path / 'results' / 'broken' / 'ekf' / 'default' / 'job.log'}" in outcome.stderr


def test_a_refused_job_directory_points_to_the_reason_not_to_a_missing_job_log(tmp_path: Path, small_log: Path) -> None:
    plan = tmp_path / "plan.toml"
    plan.write_text(f'logs = ["{small_log}"]\nestimators = ["ekf"]\n[evaluation]\nkitti = false\n')
    mine = tmp_path / "results" / "small" / "ekf" / "default"
    mine.mkdir(parents=True)
    (mine / "notes.txt").write_text("mine\n")
    outcome = invoke(str(plan), "--jobs", "1")
    assert outcome.exit_code == 4, outcome.output
    assert "is not a relpoint output" in outcome.stdout
    assert "job.log" not in outcome.stderr.replace("no failed job wrote a job.log", "")
    assert f"the error column of {tmp_path / 'results' / 'results.csv'} says why" in outcome.stderr
    assert sorted(path.name for path in mine.iterdir()) == ["notes.txt"]


def test_fail_fast_stops_at_the_first_failure(
    tmp_path: Path, bad_log: Path, local_run: tuple[Path, list[dict[str, Any]]]
) -> None:
    logs = local_run[0] / "logs"
    plan = tmp_path / "plan.toml"
    plan.write_text(
        f'logs = ["{bad_log}", "{logs}/*.mcap"]\n[estimators.ekf.grid]\nobservation_sigma = [0.3, 0.4, 0.5]\n'
    )
    outcome = invoke(str(plan), "--jobs", "1", "--fail-fast")
    assert outcome.exit_code == 4, outcome.output
    assert "--fail-fast stopped the batch" in outcome.stderr
    rows = read_results(tmp_path / "results" / "results.json")
    assert len(rows) == 9 and rows[0]["status"] == "failed"
    statuses = [row["status"] for row in rows]
    # One worker holds at most two queued jobs when the first failure arrives; the rest never start.
    assert statuses.count("cancelled") >= 4 and statuses.count("ok") <= 2
    assert all(not (tmp_path / "results" / r["job"]).exists() for r in rows if r["status"] == "cancelled")


def _warm_modules() -> list[str]:
    """In a pool worker: which warm-up modules and kernels the worker had before its first job."""
    import sys

    names = ("relpoint_app.worker_warmup", "relpoint_app.batch_jobs", "relpoint.estimators._fastslam_kernels",
             "relpoint.estimators.relative_point._kernels", "relpoint.estimators.fastslam",
             "relpoint.estimators.relative_point.estimator")  # fmt: skip
    loaded = [name for name in names if name in sys.modules]
    from relpoint.estimators import _fastslam_kernels

    if _fastslam_kernels.COMPILED_AHEAD or _fastslam_kernels.associate.signatures:  # prebuilt, or compiled
        loaded.append("fastslam kernels")
    return loaded


def test_pool_workers_start_warm() -> None:
    """Job modules and compiled kernels loaded; the estimators' own modules are left to their first job."""
    from relpoint_app.batch_jobs import LocalPool

    with LocalPool(1) as pool:
        [(_, loaded)] = list(pool.map_unordered(lambda_free_call, [_warm_modules]))
    assert loaded == ["relpoint_app.worker_warmup", "relpoint_app.batch_jobs", "relpoint.estimators._fastslam_kernels",
                      "relpoint.estimators.relative_point._kernels", "fastslam kernels"]  # fmt: skip


def _blas_threads() -> list[int]:
    """In a pool worker: the native thread pools' sizes, as the worker started (no limit applied)."""
    from threadpoolctl import threadpool_info

    return [pool["num_threads"] for pool in threadpool_info()]


def test_pool_workers_start_with_single_threaded_native_pools_and_leave_this_environment() -> None:
    import os

    from relpoint_app.batch_jobs import LocalPool
    from relpoint_app.batch_start import SINGLE_THREADED

    before = {name: os.environ.get(name) for name in SINGLE_THREADED}
    with LocalPool(1) as pool:
        [(_, threads)] = list(pool.map_unordered(lambda_free_call, [_blas_threads]))
    assert threads and set(threads) == {1}
    assert {name: os.environ.get(name) for name in SINGLE_THREADED} == before


@pytest.mark.parametrize("trim_threshold", [None, "65536"])
def test_a_dask_worker_keeps_its_array_heap_only_when_the_trim_threshold_is_fixed(trim_threshold: str | None) -> None:
    import os
    import subprocess
    import sys

    env = {key: value for key, value in os.environ.items() if key != "MALLOC_TRIM_THRESHOLD_"}
    if trim_threshold is not None:
        env["MALLOC_TRIM_THRESHOLD_"] = trim_threshold
    code = "from relpoint_app.worker_warmup import keep_array_heap\nprint(keep_array_heap())\n"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == str(trim_threshold is not None and sys.platform.startswith("linux"))


def test_filter_jobs_import_no_library_the_warm_up_did_not(tmp_path: Path) -> None:
    """An EKF or FastSLAM job (run, write, evaluate) in a warmed-up worker imports no part of scipy that
    the warm-up did not: each worker would pay for it in its first job (a fifth of a second)."""
    import subprocess
    import sys

    from relpoint.simulation import SimulationConfig, simulate
    from relpoint_app.simulation import write_simulation

    log = tmp_path / "fig8.mcap"
    write_simulation(simulate(SimulationConfig(iterations=60, density=25.0, seed=1)), log)
    code = (
        "import sys\n"
        "import relpoint_app.worker_warmup\n"
        "warm = set(sys.modules)\n"
        "from relpoint_app.batch_plan import load_plan\n"
        "from relpoint_app.batch_jobs import run_job\n"
        f"plan = load_plan({str(tmp_path / 'plan.toml')!r})\n"
        "rows = [run_job(job) for job in plan.jobs]\n"
        "assert [row['status'] for row in rows] == ['ok', 'ok'], rows\n"
        "scipy = sorted(m for m in set(sys.modules) - warm if m.startswith('scipy'))\n"
        "assert not scipy, scipy\n"
    )
    (tmp_path / "plan.toml").write_text(
        f"logs = [{str(log)!r}]\nresults = {str(tmp_path / 'results')!r}\n"
        "[estimators.ekf]\n[estimators.fastslam]\nparticles = 5\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]


@pytest.mark.parametrize(
    ("args", "local"),
    [
        (["batch", "plan.toml"], True),
        (["-q", "batch", "plan.toml", "--jobs", "2"], True),
        (["batch", "plan.toml", "--scheduler", "tcp://127.0.0.1:8786"], False),
        (["batch", "plan.toml", "--scheduler=tcp://127.0.0.1:8786"], False),
        (["batch", "--help"], False),
        (["run", "batch"], False),
        (["-q"], False),
    ],
)
def test_the_fork_server_starts_early_only_for_the_local_pool(args: list[str], local: bool) -> None:
    from relpoint_app.batch_start import runs_local_pool

    assert runs_local_pool(args) is local


def test_the_installed_command_runs_a_plan_on_the_local_pool(tmp_path: Path) -> None:
    """``relpoint batch`` as a user types it: the console script, whose workers run that script again
    as they start (with its arguments) and must not start fork servers of their own."""
    command = Path(sys.executable).with_name("relpoint")
    assert command.exists(), "relpoint is not installed in this environment (pip install -e .)"
    plan = tmp_path / "plan.toml"
    plan.write_text(
        'results = "results"\n[[simulate]]\nname = "fig8"\niterations = 20\ndensity = 5\nseed = 1\n'
        "[estimators.ekf.grid]\nobservation_sigma = [0.3, 0.5]\n"
    )
    completed = subprocess.run(
        [str(command), "-q", "batch", str(plan), "--jobs", "2"], capture_output=True, text=True, timeout=300
    )
    assert completed.returncode == 0, completed.stderr
    assert "Traceback" not in completed.stderr
    rows = read_results(tmp_path / "results" / "results.json")
    assert [row["status"] for row in rows] == ["ok", "ok"]


def lambda_free_call(function: Any) -> Any:
    """Call ``function`` in the worker (the pool pickles both by name)."""
    return function()


def test_a_job_opens_its_log_once(plan_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import formats.log as log_module
    from relpoint_app.batch_jobs import run_job, run_simulation

    plan = load_plan(plan_file, results=tmp_path / "results")
    assert run_simulation(plan.simulations[0])["status"] == "ok"
    opened: list[Path] = []
    real = log_module.open_reader
    monkeypatch.setattr(log_module, "open_reader", lambda path: opened.append(path) or real(path))
    row = run_job(plan.jobs[0])
    assert row["status"] == "ok" and row["ate_rmse"] is not None and row["landmark_rmse"] is not None
    assert opened == [plan.jobs[0].log]
