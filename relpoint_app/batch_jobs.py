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
import ipaddress
import json
import logging
import os
import re
import signal
import socket
import threading
import time
import traceback
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from formats.atomic import atomic_directory, remove_temporaries, write_text
from formats.outputs import RUN_FILES, json_text
from formats.topics import Topics
from relpoint.errors import InputError, RelpointError, UsageError
from relpoint.estimators import ESTIMATORS
from relpoint_app.batch_plan import BatchPlan, Job, SimulationStep
from relpoint_app.batch_start import pool_context, start_fork_server

if TYPE_CHECKING:
    from formats.log import LogReader
    from relpoint import pipeline

log = logging.getLogger(__name__)

#: What a job imports (in the worker, when it first runs; the fork server's warm-up imports them
#: beforehand): not at this module's import, which the ``relpoint batch`` command makes too. A
#: plan's simulated logs import the simulator's writer when they are made.
JOB_MODULES = (
    "formats.log", "formats.reference_trajectories", "relpoint.evaluation", "relpoint_app.evaluator",
    "relpoint_app.runner",
)  # fmt: skip

#: Files whose presence (with a matching ``job.json``) marks a job as complete.
JOB_FILES = (*RUN_FILES, "evaluation.json", "job.log", "job.json")
#: Loggers whose records go into ``job.log``.
_CAPTURED = ("relpoint", "relpoint_app", "formats", "relpoint_cli")


class JobFailed(RelpointError):
    """At least one job of a batch failed (exit code 4, like an estimator failure)."""

    exit_code = 4


# --- inside a worker ---------------------------------------------------------------------------------


class JobCancelled(BaseException):
    """Raised in a pool worker by SIGTERM while it runs a job: the job unwinds (its temporaries are removed).

    A ``BaseException``, like ``KeyboardInterrupt``, so that :func:`run_job` does not record it as the
    job's failure.
    """


#: Whether this worker process is inside a job (SIGTERM then unwinds the job before the worker exits).
_in_job = False
#: Whether this worker has been told to stop (it then starts no further item).
_stopping = False


def _on_sigterm(signum: int, frame: Any) -> None:
    global _stopping
    _stopping = True
    if _in_job:
        raise JobCancelled
    os._exit(128 + signum)


def _init_worker() -> None:
    """Signals of a pool worker: the parent decides about Ctrl-C; SIGTERM stops the worker's job.

    The terminal sends Ctrl-C's SIGINT to the whole process group; workers ignore it and leave it to
    the parent, which cancels what is queued and then terminates them (:meth:`LocalPool.stop`).
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_sigterm)


#: Per thread: a function that says whether this thread's job was cancelled (set by the Dask executor,
#: whose worker threads cannot be signalled).
_cancellation = threading.local()


def _stop_if_cancelled(*_: Any) -> None:
    """Called after every estimator iteration of a job: raises :class:`JobCancelled` once it is cancelled."""
    cancelled = getattr(_cancellation, "check", None)
    if cancelled is not None and cancelled():
        raise JobCancelled


def _call_in_dask(function: Callable[[Any], Any], item: Any) -> Any:
    """Run ``function(item)`` as a Dask task that stops at its next iteration once its future is cancelled.

    Dask cannot interrupt a running task; the job polls its own state on the worker (a dictionary
    look-up, no network) and unwinds like a terminated pool worker's job. Returns None when cancelled
    (nobody waits for the result).
    """
    from distributed import get_worker

    worker = get_worker()
    key = worker.get_current_task()

    def cancelled() -> bool:
        task = worker.state.tasks.get(key)
        return task is None or task.state in ("cancelled", "released", "forgotten")

    _cancellation.check = cancelled
    try:
        return function(item)
    except JobCancelled:
        return None
    finally:
        _cancellation.check = None


def _call_in_worker(function: Callable[[Any], Any], item: Any) -> Any:
    """Run ``function(item)`` in a pool worker; a cancelled job ends the worker once it has unwound.

    Exiting (rather than returning to the pool's loop) keeps the worker from taking another item.
    """
    global _in_job
    if _stopping:
        os._exit(128 + signal.SIGTERM)
    _in_job = True
    try:
        return function(item)
    except JobCancelled:
        os._exit(128 + signal.SIGTERM)
    finally:
        _in_job = False


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


def _run(job: Job, reader: LogReader, out_dir: Path) -> pipeline.RunResult:
    """``relpoint run``: the estimator over the log, written to ``out_dir`` (which it replaces)."""
    from relpoint_app.runner import execute_run

    spec = ESTIMATORS[job.estimator]
    config = spec.build_config(dict(job.parameters))
    log.info("running %s over %s", spec.name, job.log)
    result = execute_run(
        reader, spec, config, out_dir, seed=job.seed, use_odometry=job.use_odometry, use_fixes=job.use_fixes,
        extra_info={"batch_job": job.job_id}, on_iteration=_stop_if_cancelled,
    )  # fmt: skip
    timing = result.timing_summary()
    log.info(
        "%d iterations, %d landmarks, %.3f ms median per iteration",
        timing["iterations"], len(result.landmarks), timing["seconds_median"] * 1e3,
    )  # fmt: skip
    return result


def _evaluate(job: Job, reader: LogReader, out_dir: Path) -> dict[str, float]:
    """``relpoint evaluate OUT --reference LOG --json OUT/evaluation.json``; empty without ground truth.

    The reference comes from the job's open log (``reader``), the estimate from what the run wrote.
    """
    from formats.reference_trajectories import (
        ground_truth_landmarks,
        load_landmark_map,
        load_trajectory,
        log_trajectory,
    )
    from relpoint.evaluation import AlignMode, evaluate_trajectory, landmark_metrics
    from relpoint_app.evaluator import evaluation_json

    topics = Topics(**dict(job.topics))
    inputs = {"estimate": str(job.output), "reference": str(job.log), "reference_topic": None,
              "estimate_topic": None, "parent": None, "child": None}  # fmt: skip
    summary: dict[str, float] = {}
    if reader.role_present("ground_truth_pose"):
        inputs["reference_topic"] = topics.ground_truth_pose
        reference = log_trajectory(reader, topic=topics.ground_truth_pose)
        result = evaluate_trajectory(reference, load_trajectory(out_dir), job.evaluation)
        summary = dict(result.summary)
        landmarks = load_landmark_map(out_dir)
        truth = ground_truth_landmarks(reader)
        if landmarks is not None and truth is not None:
            alignment = result.alignment if job.evaluation.align is not AlignMode.NONE else None
            summary |= landmark_metrics(landmarks, truth, alignment=alignment).summary
        log.info("ATE rmse %.6f m, landmark rmse %.6f m", summary["ate_rmse"], summary.get("lm_err_rmse", float("nan")))
    else:
        log.warning("%s has no %s: no trajectory evaluation", job.log, topics.ground_truth_pose)
    write_text(out_dir / "evaluation.json", evaluation_json(summary, job.evaluation, inputs))
    return summary


def _finish(out_dir: Path, job: Job, row: dict[str, Any], header: str, stream: io.StringIO) -> None:
    write_text(out_dir / "job.log", header + stream.getvalue())
    document = {"spec": job.describe(), "spec_hash": job.spec_hash(), "row": row}
    write_text(out_dir / "job.json", json_text(document, indent=2, sort_keys=True, default=str) + "\n")


def run_job(job: Job) -> dict[str, Any]:
    """Run, evaluate and record one job; returns its results row (never raises for a job's failure).

    The row holds ``job, log, estimator, parameters, seed, status`` (ok | failed), ``ate_rmse`` and
    ``landmark_rmse`` (metres, None without ground truth), ``seconds_per_iteration`` (median wall time
    of an estimator step), ``iterations``, ``landmarks``, ``wall_seconds`` and ``cpu_seconds`` (the whole
    job, in its process) and ``error``.
    A failed job's directory holds only ``job.log`` (with the traceback) and ``job.json``.
    """
    from formats.log import LogReader

    start, start_cpu = time.perf_counter(), time.process_time()
    row = _empty_row(job)
    header = (
        f"job {job.job_id}\nlog {job.log}\nestimator {job.estimator}\nparameters {json.dumps(job.row_parameters())}\n"
        f"seed {job.seed}\nhost {socket.gethostname()} pid {os.getpid()}\n"
        f"started {time.strftime('%Y-%m-%dT%H:%M:%S%z')}\n\n"
    )
    with _captured_log() as stream, _single_threaded():
        try:
            # The log is opened once: the run and the evaluation's reference read it through one reader.
            with LogReader(job.log, Topics(**dict(job.topics))) as reader, atomic_directory(job.output) as tmp:
                result = _run(job, reader, tmp)
                summary = _evaluate(job, reader, tmp)
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
    from relpoint.simulation import simulate
    from relpoint_app.simulation import write_simulation

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
    from formats.log import LogReader, metadata_json

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
    def stop(self) -> None:
        """After an interrupt: start nothing more, cancel what runs, and release the workers at once."""

    @abstractmethod
    def close(self) -> None:
        """Release workers or the connection once every item is done."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc is None:
            self.close()
            return
        with _signals_ignored():  # a second Ctrl-C must not cut the clean-up short
            self.stop()


@contextlib.contextmanager
def _signals_ignored() -> Iterator[None]:
    """SIGINT and SIGTERM ignored for the block (in the main thread; elsewhere nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.signal(signum, signal.SIG_IGN) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


class LocalPool(Executor):
    """A ``ProcessPoolExecutor`` of ``workers`` processes (``--jobs N``).

    Workers are forked from a fork server that has imported the job modules and loaded the estimators'
    kernels once (:func:`relpoint_app.batch_start.pool_context`), so none pays for them in its jobs.

    Workers ignore SIGINT; :meth:`stop` cancels the queued items and sends the workers SIGTERM, on
    which a running job unwinds (an atomic job directory removes its temporary) and the worker exits;
    a worker still alive after :attr:`STOP_GRACE_S` is killed.
    """

    #: Seconds a terminated worker has to unwind its job before it is killed.
    STOP_GRACE_S = 1.0

    def __init__(self, workers: int) -> None:
        start_fork_server()  # with its environment (a no-op once ``relpoint batch`` has started it)
        context = pool_context()
        self._new_pool = lambda: concurrent.futures.ProcessPoolExecutor(
            max_workers=workers, mp_context=context, initializer=_init_worker
        )
        self._pool = self._new_pool()
        self._futures: list[concurrent.futures.Future[Any]] = []

    def _submit(self, function: Callable[[Any], Any], item: Any) -> concurrent.futures.Future[Any]:
        try:
            return self._pool.submit(_call_in_worker, function, item)
        except concurrent.futures.process.BrokenProcessPool:
            # a worker died hard (killed, out of memory) in an earlier phase: its items are already
            # recorded as failed; later items get fresh workers
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = self._new_pool()
            return self._pool.submit(_call_in_worker, function, item)

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

    def stop(self) -> None:
        # the pool forgets its processes on shutdown: take them first
        processes = list((getattr(self._pool, "_processes", None) or {}).values())
        self._pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.terminate()
        deadline = time.monotonic() + self.STOP_GRACE_S
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
        for process in processes:
            if process.is_alive():
                process.kill()
                process.join(self.STOP_GRACE_S)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


_ADDRESS = re.compile(
    r"(?:(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*)://)?(?P<host>\[[^\]]*\]|[^:/\[\]]+):(?P<port>[0-9]{1,5})"
)
_HOST_NAME = re.compile(r"[A-Za-z0-9_]([A-Za-z0-9_.-]*[A-Za-z0-9_])?")


@dataclasses.dataclass(frozen=True)
class SchedulerAddress:
    """A checked ``--scheduler`` address: ``scheme://host:port`` with scheme ``tcp`` or ``tls``."""

    scheme: str
    host: str
    port: int

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}"

    @property
    def is_local(self) -> bool:
        """Whether the host is this machine (a loopback address, ``localhost`` or this host's name)."""
        if self.host.lower() in ("localhost", socket.gethostname().lower()):
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False


def parse_scheduler(text: str) -> SchedulerAddress:
    """Check a ``--scheduler`` value (``tcp://HOST:PORT``, ``tls://HOST:PORT``, or ``HOST:PORT`` for tcp).

    Raises :class:`UsageError` (exit 2) naming the value for anything else: another scheme, a missing
    or out-of-range port, a malformed host or IPv6 address.
    """
    shown = text if len(text) <= 80 else text[:77] + "..."
    hint = "give tcp://HOST:PORT or tls://HOST:PORT (IPv6 in brackets: tcp://[::1]:8786)"
    match = _ADDRESS.fullmatch(text.strip())
    if match is None:
        raise UsageError(f"--scheduler {shown!r} is not a scheduler address", hint)
    scheme = (match["scheme"] or "tcp").lower()
    if scheme not in ("tcp", "tls"):
        raise UsageError(f"--scheduler {shown!r}: unsupported scheme {scheme}://", hint)
    host, port = match["host"], int(match["port"])
    if host.startswith("["):
        host = host[1:-1]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise UsageError(f"--scheduler {shown!r}: {host!r} is not an IPv6 address", hint) from None
    elif _HOST_NAME.fullmatch(host) is None:
        raise UsageError(f"--scheduler {shown!r}: {host!r} is not a host name or address", hint)
    if not 1 <= port <= 65535:
        raise UsageError(f"--scheduler {shown!r}: port {port} is not in 1..65535", hint)
    return SchedulerAddress(scheme, host, port)


@dataclasses.dataclass(frozen=True)
class TlsFiles:
    """PEM files of a ``tls://`` connection (``--tls-ca-file``, ``--tls-cert``, ``--tls-key``).

    ``ca_file`` signed the scheduler's certificate; ``cert`` (with ``key``, unless the key is inside
    it) is the client's own: Dask's TLS is mutual, the scheduler checks the client too.
    """

    ca_file: Path | None = None
    cert: Path | None = None
    key: Path | None = None


def scheduler_security(address: SchedulerAddress, tls: TlsFiles | None) -> Any:
    """The ``distributed.security.Security`` of a connection to ``address`` (None for plain tcp).

    ``tls://`` needs the CA file and the client certificate, and encryption is then required; TLS
    files with a ``tcp://`` address are a usage error. The files are loaded now, so a bad one is
    refused (exit 2) before anything runs.
    """
    if address.scheme == "tcp":
        if tls is not None:
            raise UsageError("--tls-ca-file, --tls-cert and --tls-key need a tls:// scheduler address",
                             f"use tls://{str(address).split('://', 1)[1]}")  # fmt: skip
        return None
    if tls is None or tls.ca_file is None or tls.cert is None:
        raise UsageError(f"--scheduler {address} needs --tls-ca-file and --tls-cert",
                         "the CA that signed the scheduler's certificate, and this client's certificate "
                         "(--tls-key if its key is a separate file)")  # fmt: skip
    from distributed.security import Security

    security = Security(
        tls_ca_file=str(tls.ca_file),
        tls_client_cert=str(tls.cert),
        tls_client_key=None if tls.key is None else str(tls.key),
        require_encryption=True,
    )
    try:
        security.get_connection_args("client")  # builds the SSL context from the files
    except (OSError, ValueError) as error:  # ssl.SSLError is an OSError
        raise UsageError(f"cannot use the TLS files {tls.ca_file.name}, {tls.cert.name}: {error}",
                         "give PEM files: the CA certificate, the client certificate and its key") from None  # fmt: skip
    return security


class DaskExecutor(Executor):
    """A ``dask.distributed`` client of the scheduler at ``address`` (``--scheduler tcp://HOST:PORT``).

    Workers must import the same relpoint version and see the plan's paths (a shared file system).
    The scheduler is trusted: Dask moves pickled objects, so a scheduler (or anyone who can speak to
    the client over plain tcp) can run code in this process. Hence ``tls://`` with certificates
    (``security``, see :func:`scheduler_security`), and a warning for plain tcp to another host.
    """

    def __init__(self, address: SchedulerAddress, security: Any = None, timeout_s: float = 10.0) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise UsageError("--scheduler needs dask.distributed", "pip install 'relpoint[cluster]'") from None
        if address.scheme == "tcp" and not address.is_local:
            log.warning(
                "the scheduler %s is reached over plain tcp: anyone on the network between can read the jobs "
                "or run code in this process; use tls:// with --tls-ca-file/--tls-cert/--tls-key", address
            )  # fmt: skip
        try:
            self._client = Client(str(address), timeout=timeout_s, security=security)
        except (OSError, TimeoutError) as error:
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
            future = self._client.submit(
                _call_in_dask, function, item, key=f"relpoint-{name}-{token}-{i}", pure=False, priority=-i
            )
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

    def stop(self) -> None:
        """Cancel every future of this client; a running job notices at its next estimator iteration.

        Dask cannot interrupt a task's thread: a running job polls its task's state after every
        iteration (:func:`_call_in_dask`) and unwinds, leaving no job directory.
        """
        if self._futures:
            self._client.cancel(self._futures, force=True)
        self._client.close(timeout=2)

    def close(self) -> None:
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


def remove_plan_temporaries(plan: BatchPlan) -> None:
    """After an interrupt, once the pool's workers are gone: remove the temporaries that a worker
    killed before its job unwound (after :attr:`LocalPool.STOP_GRACE_S`) left beside the outputs of
    the plan's jobs and simulated logs (:func:`formats.atomic.remove_temporaries`)."""
    for output in [step.output for step in plan.simulations] + [job.output for job in plan.jobs]:
        remove_temporaries(output)


def run_plan(
    plan: BatchPlan,
    executor: Executor,
    *,
    fail_fast: bool = False,
    resume: bool = True,
    on_simulated: Callable[[dict[str, Any]], None] | None = None,
    on_job: Callable[[dict[str, Any], bool], None] | None = None,
) -> BatchOutcome:
    """Make the plan's simulated logs, then run its jobs on ``executor``; skip work already done.

    With ``resume`` (the default) a job whose complete output exists for the same spec is not run
    again (:func:`completed_row`); without it every job runs and replaces its directory.

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
        stored = completed_row(job) if resume else None
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
