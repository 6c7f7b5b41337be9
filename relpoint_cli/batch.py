"""``relpoint batch``: run a plan of simulate/run/evaluate jobs on a process pool or a Dask cluster.

The plan is parsed by :mod:`relpoint_app.batch_plan`; the jobs and executors are in
:mod:`relpoint_app.batch_jobs`. This command picks the executor, shows a progress bar over jobs, writes
``results.csv`` and ``results.json`` and prints a summary table (``docs/batch.md``).
"""

from __future__ import annotations

import contextlib
import gc
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from relpoint.errors import Interrupted, UsageError
from relpoint_app.batch_start import MAX_JOBS, default_workers, start_fork_server
from relpoint_cli.errors import handle_errors
from relpoint_cli.progress import progress_bar

if TYPE_CHECKING:
    from collections.abc import Iterator

    from relpoint_app.batch_jobs import BatchOutcome
    from relpoint_app.batch_plan import BatchPlan

EXAMPLES = """\b
Examples:
  relpoint batch plan.toml                          # local process pool, one worker per core
  relpoint batch plan.toml --jobs 2 --results out/  # two workers, results root out/
  relpoint batch plan.yaml --scheduler tcp://127.0.0.1:8786  # a Dask cluster on this machine
  relpoint batch plan.yaml --scheduler tls://10.0.0.5:8786 --tls-ca-file ca.pem \\
      --tls-cert client.pem --tls-key client.key          # a remote cluster, over TLS
  relpoint batch plan.toml --fail-fast              # CI: stop at the first failed job (exit 4)

\b
A job whose complete output exists is skipped, so rerunning a plan resumes it
(also after Ctrl-C, which cancels running jobs and leaves no partial job directory).
Only connect to schedulers you trust: a Dask scheduler can run code in this process.
Exit codes: 0 every job ok, 2 a bad plan or options, 3 no scheduler, 4 a job failed, 130 interrupted.
See docs/batch.md for the plan format.
"""


def _number(value: Any, scale: float = 1.0, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value * scale:.{digits}f}"


def format_summary(plan: BatchPlan, outcome: BatchOutcome) -> str:
    """The summary table: one line per job, then counts and the failures' errors."""
    header = ("job", "status", "ATE rmse m", "LM rmse m", "ms/iter")
    lines = [
        (row["job"], row["status"], _number(row["ate_rmse"]), _number(row["landmark_rmse"]),
         _number(row["seconds_per_iteration"], 1e3, 2))
        for row in outcome.rows
    ]  # fmt: skip
    widths = [max(len(header[c]), *(len(line[c]) for line in lines)) for c in range(len(header))]

    def render(cells: tuple[str, ...]) -> str:
        return "  ".join(
            cell.ljust(width) if c < 2 else cell.rjust(width)
            for c, (cell, width) in enumerate(zip(cells, widths, strict=True))
        )

    text = [render(header), *(render(line) for line in lines)]
    counts = f"{len(outcome.rows)} jobs: {outcome.count('ok')} ok ({outcome.resumed} resumed), {outcome.count('failed')} failed"
    if outcome.count("cancelled"):
        counts += f", {outcome.count('cancelled')} cancelled"
    text += ["", counts]
    text += [f"failed {row['job']}: {row['error']}" for row in outcome.rows if row["status"] == "failed"]
    return "\n".join(text)


def _failure_hint(results: Path, outcome: BatchOutcome, csv_path: Path) -> str:
    """Where to read why jobs failed: a failed job's job.log, or results.csv for jobs that wrote none
    (refused before running, or their directory refused as not relpoint's)."""
    failed = [row["job"] for row in outcome.rows if row["status"] == "failed"]
    logs = [results / job / "job.log" for job in failed if (results / job / "job.log").is_file()]
    if not logs:
        return f"no failed job wrote a job.log: the error column of {csv_path} says why each failed"
    hint = f"see {logs[0]}" + (f" (and {len(logs) - 1} more job.log under {results})" if len(logs) > 1 else "")
    if len(logs) < len(failed):
        hint += f"; {len(failed) - len(logs)} wrote none: the error column of {csv_path} says why"
    return hint


@contextlib.contextmanager
def _start_up_objects() -> Iterator[None]:
    """No garbage collection while the command starts up; what it made is frozen at the end.

    The start-up imports (with Dask's client, 0.2 s of them) and the executor only make objects that
    live until the exit: collections during them walk every object made so far again and again, 30-40
    ms on the way to the first job. Frozen, none of it is walked again, by later collections nor by
    the exit's (30 ms less between the last job and the end of the command).
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


@click.command(epilog=EXAMPLES)
@click.argument("plan_file", metavar="PLAN", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "-j", "--jobs", type=click.IntRange(min=1), default=None,
    help="Worker processes of the local pool [default: the usable cores].",
)  # fmt: skip
@click.option(
    "--scheduler",
    metavar="tcp://HOST:PORT",
    help="Run on this Dask distributed scheduler instead (tls://HOST:PORT with the --tls-* files).",
)
@click.option(
    "--tls-ca-file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="PEM CA certificate that signed a tls:// scheduler's certificate (required with tls://).",
)
@click.option(
    "--tls-cert",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="PEM client certificate for a tls:// scheduler (required with tls://).",
)
@click.option(
    "--tls-key",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="PEM key of --tls-cert (if not inside it).",
)
@click.option(
    "--max-jobs",
    type=click.IntRange(min=1),
    default=MAX_JOBS,
    show_default=True,
    help="Refuse a plan of more jobs than this (counted before the grids are expanded).",
)
@click.option(
    "--resume/--no-resume",
    default=True,
    show_default=True,
    help="Skip jobs whose complete output exists for the same spec; --no-resume runs them all again.",
)
@click.option("--fail-fast", is_flag=True, help="Stop at the first failed job (what has not started is cancelled).")
@click.option(
    "--results", "results_dir", type=click.Path(file_okay=False, path_type=Path),
    help="Results root (overrides the plan's `results`).",
)  # fmt: skip
@click.pass_context
@handle_errors
def batch(ctx: click.Context, plan_file: Path, jobs: int | None, scheduler: str | None, tls_ca_file: Path | None,
          tls_cert: Path | None, tls_key: Path | None, max_jobs: int, resume: bool, fail_fast: bool,
          results_dir: Path | None) -> None:  # fmt: skip
    """Run every job of PLAN (logs x estimators x parameter grid), evaluate each, and tabulate the results.

    Writes one directory per job (run files, evaluation.json, job.log) and results.csv / results.json
    under the results root, then prints a summary table. A failed job is recorded and the others go on.
    """
    if scheduler is not None and jobs is not None:
        raise UsageError("--jobs sets the local pool's size; the Dask cluster's workers decide with --scheduler")
    if scheduler is None:
        start_fork_server()  # first: the workers' warm-up runs while this process reads the plan
    with _start_up_objects():  # until the executor is up
        from relpoint_app.batch_jobs import (
            DaskExecutor,
            Executor,
            JobFailed,
            LocalPool,
            TlsFiles,
            parse_scheduler,
            remove_plan_temporaries,
            run_plan,
            scheduler_security,
        )
        from relpoint_app.batch_plan import check_outputs, load_plan, write_results

        tls = TlsFiles(tls_ca_file, tls_cert, tls_key) if (tls_ca_file or tls_cert or tls_key) else None
        if scheduler is None:
            if tls is not None:
                raise UsageError("--tls-ca-file, --tls-cert and --tls-key go with --scheduler tls://HOST:PORT")
            address = security = None
        else:
            address = parse_scheduler(scheduler)
            security = scheduler_security(address, tls)
        plan = load_plan(plan_file, results=results_dir, max_jobs=max_jobs)
        check_outputs(plan)
        quiet = bool(ctx.find_root().obj and ctx.find_root().obj.get("quiet"))
        executor: Executor = (
            DaskExecutor(address, security) if address is not None else LocalPool(jobs or default_workers())
        )
    finished = 0
    try:
        with (
            executor,
            progress_bar(len(plan.simulations), "simulate", unit="log") as sim_bar,
            progress_bar(len(plan.jobs), "batch", unit="job") as bar,
        ):

            def on_simulated(row: dict[str, Any]) -> None:
                sim_bar.update(1)
                if row["status"] != "ok" and not quiet:
                    sim_bar.write(
                        f"relpoint: warning: simulating {row['name']} failed: {row['error']}", file=sys.stderr
                    )

            def on_job(row: dict[str, Any], resumed: bool) -> None:
                nonlocal finished
                finished += 1
                bar.update(1)
                if row["status"] == "failed" and not quiet:
                    bar.write(f"relpoint: warning: job {row['job']} failed: {row['error']}", file=sys.stderr)

            outcome = run_plan(
                plan, executor, fail_fast=fail_fast, resume=resume, on_simulated=on_simulated, on_job=on_job
            )
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the executor has cancelled the running jobs
        if isinstance(executor, LocalPool):  # a Dask task unwinds on its own
            remove_plan_temporaries(plan)
        raise Interrupted(
            f"interrupted: {finished} of {len(plan.jobs)} job(s) done and kept, the others cancelled "
            "without leaving a job directory",
            "run the same command again to resume",
        ) from None
    csv_path, _ = write_results(plan, outcome.rows)
    click.echo(format_summary(plan, outcome))
    if not quiet:
        click.echo(f"results: {csv_path} and {csv_path.with_suffix('.json')}", err=True)
    failed = outcome.count("failed")
    if failed:
        stopped = " (--fail-fast stopped the batch)" if outcome.stopped_early else ""
        raise JobFailed(
            f"{failed} of {len(plan.jobs)} job(s) failed{stopped}", _failure_hint(plan.results, outcome, csv_path)
        )
