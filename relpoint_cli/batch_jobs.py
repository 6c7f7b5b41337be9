"""Running a batch plan's jobs: the job functions and the two executors behind ``relpoint batch``.

:func:`run_job` does what ``relpoint run LOG -o DIR`` followed by ``relpoint evaluate DIR --reference
LOG --json DIR/evaluation.json`` does, through the same library calls, and writes its directory (run
files, ``evaluation.json``, ``job.log``, ``job.json``) atomically. It never raises for a failing job:
the error goes into the returned row and the directory, so one bad log does not stop a batch.

The executors only move frozen job descriptions to a worker and rows back: :class:`LocalPool`
(``concurrent.futures.ProcessPoolExecutor``) and :class:`DaskExecutor` (a ``dask.distributed``
client of an existing scheduler) hand the same function the same arguments; :func:`run_plan` drives
either one the same way.
"""

from __future__ import annotations

import concurrent.futures
import concurrent.futures.process
import contextlib
import dataclasses
import io
import json
import logging
import multiprocessing
import os
import socket
import threading
import time
import traceback
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from formats.atomic import atomic_directory, write_text
from formats.batch_plan import BatchPlan, Job, SimulationStep
from formats.log import LogReader, Topics, metadata_json
from formats.reference_trajectories import load_ground_truth_landmarks, load_landmark_map, load_trajectory
from formats.run_output import RUN_FILES
from formats.simulation_log import write_simulation
from relpoint import pipeline
from relpoint.errors import RelpointError
from relpoint.estimators import ESTIMATORS
from relpoint.evaluation import AlignMode, evaluate_trajectory, landmark_metrics
from relpoint.simulation import simulate
from relpoint_cli.evaluate import write_json
from relpoint_cli.run import execute_run

log = logging.getLogger(__name__)

#: Files whose presence (with a matching ``job.json``) marks a job as complete.
JOB_FILES = (*RUN_FILES, "evaluation.json", "job.log", "job.json")
#: Loggers whose records go into ``job.log``.
_CAPTURED = ("relpoint", "formats", "relpoint_cli")


class JobFailed(RelpointError):
    """At least one job of a batch failed (exit code 4, like an estimator failure)."""

    exit_code = 4


# --- inside a worker ---------------------------------------------------------------------------------


@contextlib.contextmanager
def _single_threaded() -> Iterator[None]:
    """One BLAS/OpenMP thread for the job: jobs are the parallelism.

    On a busy 2-core machine, OpenBLAS's spinning threads made the EKF about 20x slower per iteration
    than with one thread; workers of a process pool or a Dask cluster each run one job per core.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl ships with the cluster extra
        log.warning("threadpoolctl is not installed; native thread pools are not limited")
        yield
        return
    with threadpool_limits(limits=1):
        yield


class _ThreadHandler(logging.Handler):
    """Collects the records of one thread (Dask workers may run several jobs at once)."""

    def __init__(self, stream: io.StringIO) -> None:
        super().__init__(logging.INFO)
        self.stream = stream
        self.thread = threading.get_ident()
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread == self.thread:
            self.stream.write(self.format(record) + "\n")


@contextlib.contextmanager
def _captured_log() -> Iterator[io.StringIO]:
    stream = io.StringIO()
    handler = _ThreadHandler(stream)
    loggers = [logging.getLogger(name) for name in _CAPTURED]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.addHandler(handler)
        if logger.getEffectiveLevel() > logging.INFO:
            logger.setLevel(logging.INFO)
    try:
        yield stream
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.removeHandler(handler)
            logger.setLevel(level)


def _describe_error(error: BaseException) -> str:
    if isinstance(error, RelpointError):
        return f"{type(error).__name__}: {error}"
    return f"internal error: {type(error).__name__}: {error}"


def _empty_row(job: Job) -> dict[str, Any]:
    return {
        "job": job.job_id, "log": str(job.log), "estimator": job.estimator, "parameters": job.row_parameters(),
        "seed": job.seed, "status": "failed", "ate_rmse": None, "landmark_rmse": None,
        "seconds_per_iteration": None, "iterations": None, "landmarks": None, "wall_seconds": None,
        "cpu_seconds": None, "error": None,
    }  # fmt: skip


def _run(job: Job, out_dir: Path) -> tuple[pipeline.RunResult, bool]:
    """``relpoint run``: the estimator over the log, written to ``out_dir`` (which it replaces).

    Returns the result and whether the log has ground-truth poses to evaluate against.
    """
    spec = ESTIMATORS[job.estimator]
    config = spec.config_class(**dict(job.parameters))
    reader = LogReader(job.log, Topics(**dict(job.topics)))
    log.info("running %s over %s", spec.name, job.log)
    result = execute_run(
        reader, spec, config, out_dir, seed=job.seed, use_odometry=job.use_odometry, use_fixes=job.use_fixes,
        extra_info={"batch_job": job.job_id},
    )  # fmt: skip
    timing = result.timing_summary()
    log.info(
        "%d iterations, %d landmarks, %.3f ms median per iteration",
        timing["iterations"], len(result.landmarks), timing["seconds_median"] * 1e3,
    )  # fmt: skip
    return result, reader.role_present("ground_truth_pose")


def _evaluate(job: Job, out_dir: Path, has_ground_truth: bool) -> dict[str, float]:
    """``relpoint evaluate OUT --reference LOG --json OUT/evaluation.json``; empty without ground truth."""
    topics = Topics(**dict(job.topics))
    inputs = {"estimate": str(job.output), "reference": str(job.log), "reference_topic": None,
              "estimate_topic": None, "parent": None, "child": None}  # fmt: skip
    summary: dict[str, float] = {}
    if has_ground_truth:
        inputs["reference_topic"] = topics.ground_truth_pose
        reference = load_trajectory(job.log, topic=topics.ground_truth_pose)
        result = evaluate_trajectory(reference, load_trajectory(out_dir), job.evaluation)
        summary = dict(result.summary)
        landmarks = load_landmark_map(out_dir)
        truth = load_ground_truth_landmarks(job.log)
        if landmarks is not None and truth is not None:
            alignment = result.alignment if job.evaluation.align is not AlignMode.NONE else None
            summary |= landmark_metrics(landmarks, truth, alignment=alignment).summary
        log.info("ATE rmse %.6f m, landmark rmse %.6f m", summary["ate_rmse"], summary.get("lm_err_rmse", float("nan")))
    else:
        log.warning("%s has no %s: no trajectory evaluation", job.log, topics.ground_truth_pose)
    write_json(out_dir / "evaluation.json", summary, job.evaluation, inputs)
    return summary


def _finish(out_dir: Path, job: Job, row: dict[str, Any], header: str, stream: io.StringIO) -> None:
    write_text(out_dir / "job.log", header + stream.getvalue())
    document = {"spec": job.describe(), "spec_hash": job.spec_hash(), "row": row}
    write_text(out_dir / "job.json", json.dumps(document, indent=2, sort_keys=True, default=str) + "\n")


def run_job(job: Job) -> dict[str, Any]:
    """Run, evaluate and record one job; returns its results row (never raises for a job's failure).

    The row holds ``job, log, estimator, parameters, seed, status`` (ok | failed), ``ate_rmse`` and
    ``landmark_rmse`` (metres, None without ground truth), ``seconds_per_iteration`` (median wall time
    of an estimator step), ``iterations``, ``landmarks``, ``wall_seconds`` and ``cpu_seconds`` (the whole
    job, in its process) and ``error``.
    A failed job's directory holds only ``job.log`` (with the traceback) and ``job.json``.
    """
    start, start_cpu = time.perf_counter(), time.process_time()
    row = _empty_row(job)
    header = (
        f"job {job.job_id}\nlog {job.log}\nestimator {job.estimator}\nparameters {json.dumps(job.row_parameters())}\n"
        f"seed {job.seed}\nhost {socket.gethostname()} pid {os.getpid()}\n"
        f"started {time.strftime('%Y-%m-%dT%H:%M:%S%z')}\n\n"
    )
    with _captured_log() as stream, _single_threaded():
        try:
            with atomic_directory(job.output) as tmp:
                result, has_ground_truth = _run(job, tmp)
                summary = _evaluate(job, tmp, has_ground_truth)
                timing = result.timing_summary()
                row.update(
                    status="ok",
                    ate_rmse=summary.get("ate_rmse"),
                    landmark_rmse=summary.get("lm_err_rmse"),
                    seconds_per_iteration=timing["seconds_median"],
                    iterations=int(timing["iterations"]),
                    landmarks=len(result.landmarks),
                    wall_seconds=time.perf_counter() - start,
                    cpu_seconds=time.process_time() - start_cpu,
                )
                log.info("job done in %.2f s", row["wall_seconds"])
                _finish(tmp, job, row, header, stream)
            return row
        except Exception as error:
            row.update(
                status="failed",
                error=_describe_error(error),
                wall_seconds=time.perf_counter() - start,
                cpu_seconds=time.process_time() - start_cpu,
            )
            stream.write(f"\nFAILED: {row['error']}\n" + traceback.format_exc())
    with atomic_directory(job.output) as tmp:
        _finish(tmp, job, row, header, stream)
    return row


def completed_row(job: Job) -> dict[str, Any] | None:
    """The stored row of a job whose complete, successful output exists for the same spec, else None."""
    try:
        document = json.loads((job.output / "job.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    row = document.get("row") if isinstance(document, dict) else None
    if document.get("spec_hash") != job.spec_hash() or not isinstance(row, dict) or row.get("status") != "ok":
        return None
    if not all((job.output / name).is_file() for name in JOB_FILES):
        return None
    return row


def run_simulation(step: SimulationStep) -> dict[str, Any]:
    """``relpoint simulate -o LOG``: write a simulated log atomically; returns {name, log, status, error}."""
    start = time.perf_counter()
    try:
        with _single_threaded():
            counts = write_simulation(simulate(step.config), step.output)
        return {"name": step.name, "log": str(step.output), "status": "ok", "error": None,
                "iterations": counts["points"], "wall_seconds": time.perf_counter() - start}  # fmt: skip
    except Exception as error:
        return {"name": step.name, "log": str(step.output), "status": "failed", "error": _describe_error(error),
                "iterations": None, "wall_seconds": time.perf_counter() - start}  # fmt: skip


def simulation_complete(step: SimulationStep) -> bool:
    """Whether ``step.output`` is a log simulated with exactly ``step.config``."""
    if not step.output.is_file():
        return False
    try:
        stored = LogReader(step.output).metadata().get("relpoint.simulation")
    except RelpointError:
        return False
    return stored == metadata_json(step.config.log_settings())


# --- executors ---------------------------------------------------------------------------------------

Outcome = Any  # a row (dict) or the exception that kept the function from returning one


class Executor(ABC):
    """Runs one picklable function over items somewhere else and yields (index, outcome) as they finish."""

    @abstractmethod
    def map_unordered(self, function: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Outcome]]:
        """Submit every item; yield (item index, result or exception) in completion order."""

    @abstractmethod
    def cancel_pending(self) -> None:
        """Cancel what has not started (``--fail-fast``); running items finish."""

    @abstractmethod
    def close(self, wait: bool = True) -> None:
        """Release workers or the connection (``wait=False`` after an interrupt: do not wait for running items)."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self.close(wait=exc is None)


class LocalPool(Executor):
    """A ``ProcessPoolExecutor`` of ``workers`` processes (``--jobs N``).

    Workers come from a fork server that has imported this module once (spawned where there is none),
    never forked from the parent, which may hold threads (progress bar, logging, a test runner): each
    starts as a clean interpreter, as a cluster worker does, without paying the imports again.
    """

    def __init__(self, workers: int) -> None:
        if "forkserver" in multiprocessing.get_all_start_methods():
            context = multiprocessing.get_context("forkserver")
            context.set_forkserver_preload([__name__])
        else:  # pragma: no cover - Windows
            context = multiprocessing.get_context("spawn")
        self._new_pool = lambda: concurrent.futures.ProcessPoolExecutor(max_workers=workers, mp_context=context)
        self._pool = self._new_pool()
        self._futures: list[concurrent.futures.Future[Any]] = []

    def _submit(self, function: Callable[[Any], Any], item: Any) -> concurrent.futures.Future[Any]:
        try:
            return self._pool.submit(function, item)
        except concurrent.futures.process.BrokenProcessPool:
            # a worker died hard (killed, out of memory) in an earlier phase: its items are already
            # recorded as failed; later items get fresh workers
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = self._new_pool()
            return self._pool.submit(function, item)

    def map_unordered(self, function: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Outcome]]:
        index = {}
        for i, item in enumerate(items):
            future = self._submit(function, item)
            index[future] = i
            self._futures.append(future)
        for future in concurrent.futures.as_completed(index):
            if future.cancelled():
                continue
            try:
                yield index[future], future.result()
            except Exception as error:  # a worker died (BrokenProcessPool) or the item did not pickle
                yield index[future], error

    def cancel_pending(self) -> None:
        for future in self._futures:
            future.cancel()

    def close(self, wait: bool = True) -> None:
        self._pool.shutdown(wait=wait, cancel_futures=True)


class DaskExecutor(Executor):
    """A ``dask.distributed`` client of the scheduler at ``address`` (``--scheduler tcp://HOST:PORT``).

    Workers must import the same relpoint version and see the plan's paths (a shared file system).
    """

    def __init__(self, address: str, timeout_s: float = 10.0) -> None:
        try:
            from distributed import Client
        except ImportError:
            from relpoint.errors import UsageError

            raise UsageError("--scheduler needs dask.distributed", "pip install 'relpoint[cluster]'") from None
        try:
            self._client = Client(address, timeout=timeout_s)
        except (OSError, TimeoutError) as error:
            from relpoint.errors import InputError

            raise InputError(f"cannot connect to the Dask scheduler at {address}: {error}") from None
        self._futures: list[Any] = []

    def map_unordered(self, function: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Outcome]]:
        from distributed import as_completed

        token = uuid.uuid4().hex[:8]
        name = getattr(function, "__name__", "task")
        index = {}
        futures = []
        for i, item in enumerate(items):
            # earlier items first, like the pool; keys unique per batch so a rerun is not served from memory
            future = self._client.submit(function, item, key=f"relpoint-{name}-{token}-{i}", pure=False, priority=-i)
            index[future.key] = i
            futures.append(future)
        self._futures.extend(futures)
        for future in as_completed(futures):
            if future.cancelled():
                continue
            try:
                yield index[future.key], future.result()
            except Exception as error:  # KilledWorker, a lost connection, ...
                yield index[future.key], error

    def cancel_pending(self) -> None:
        pending = [f for f in self._futures if not f.done()]
        if pending:
            self._client.cancel(pending)

    def close(self, wait: bool = True) -> None:
        if not wait:
            self.cancel_pending()
        self._client.close()


# --- driving a plan ----------------------------------------------------------------------------------


@dataclasses.dataclass
class BatchOutcome:
    """Rows in plan order and what happened to them."""

    rows: list[dict[str, Any]]
    resumed: int = 0
    ran: int = 0
    stopped_early: bool = False

    def count(self, status: str) -> int:
        return sum(row["status"] == status for row in self.rows)


def _cancelled_row(job: Job, reason: str) -> dict[str, Any]:
    row = _empty_row(job)
    row.update(status="cancelled", error=reason)
    return row


def run_plan(
    plan: BatchPlan,
    executor: Executor,
    *,
    fail_fast: bool = False,
    on_simulated: Callable[[dict[str, Any]], None] | None = None,
    on_job: Callable[[dict[str, Any], bool], None] | None = None,
) -> BatchOutcome:
    """Make the plan's simulated logs, then run its jobs on ``executor``; skip work already done.

    ``on_simulated(row)`` is called per simulated log made, ``on_job(row, resumed)`` once per job
    (resumed jobs first). A job whose log failed to simulate fails without running. With
    ``fail_fast`` the first failure cancels what has not started; those jobs get status ``cancelled``.
    """
    to_simulate = [step for step in plan.simulations if not simulation_complete(step)]
    failed_logs: dict[Path, str] = {}
    stop = False
    if to_simulate:
        for i, outcome in executor.map_unordered(run_simulation, to_simulate):
            step = to_simulate[i]
            if isinstance(outcome, BaseException):
                outcome = {
                    "name": step.name,
                    "log": str(step.output),
                    "status": "failed",
                    "error": _describe_error(outcome),
                }
            if outcome["status"] != "ok":
                failed_logs[step.output] = f"simulating {step.name} failed: {outcome['error']}"
            if on_simulated is not None:
                on_simulated(outcome)
    rows: list[dict[str, Any] | None] = [None] * len(plan.jobs)
    batch = BatchOutcome(rows=[])
    pending: list[int] = []
    for i, job in enumerate(plan.jobs):
        stored = completed_row(job)
        if stored is not None:
            rows[i] = stored
            batch.resumed += 1
            if on_job is not None:
                on_job(stored, True)
        elif job.log in failed_logs:
            row = _empty_row(job)
            row.update(error=failed_logs[job.log])
            rows[i] = row
            if on_job is not None:
                on_job(row, False)
        else:
            pending.append(i)
    if failed_logs and fail_fast:
        stop = True
    if pending and not stop:
        jobs = [plan.jobs[i] for i in pending]
        for k, result in executor.map_unordered(run_job, jobs):
            job = jobs[k]
            row = result
            if isinstance(result, BaseException):
                row = _empty_row(job)
                row.update(error=_describe_error(result))
            rows[pending[k]] = row
            batch.ran += 1
            if on_job is not None:
                on_job(row, False)
            if row["status"] != "ok" and fail_fast and not stop:
                stop = True
                executor.cancel_pending()  # jobs already running still finish and are recorded
    if stop:
        batch.stopped_early = True
    batch.rows = [
        row if row is not None else _cancelled_row(plan.jobs[i], "not run: --fail-fast stopped the batch")
        for i, row in enumerate(rows)
    ]
    return batch
