"""What ``relpoint batch`` needs before it reads a plan: the job limit, the worker count, and the
local pool's fork server.

This module imports nothing heavy, so that the command can start the fork server first: the server
then imports and warms up what every job needs (:mod:`relpoint_app.worker_warmup`) on another core
while the command reads the plan, and every worker forked from it starts its first job warm.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.context
import multiprocessing.forkserver
import os
from collections.abc import Iterator, Sequence

#: Most jobs a plan may expand to (``relpoint batch --max-jobs``).
MAX_JOBS = 10_000

#: The module the fork server (and a Dask worker, with ``--preload``) imports before the first job.
WARMUP_MODULE = "relpoint_app.worker_warmup"


def default_workers() -> int:
    """Cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def pool_context() -> multiprocessing.context.BaseContext:
    """How local pool workers start: forked from a fork server that has run :data:`WARMUP_MODULE`
    (spawned where there is no fork server, e.g. on Windows).

    Never forked from the command itself, which may hold threads (progress bar, logging, a test
    runner): each worker starts as a clean interpreter, as a cluster worker does.
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():  # pragma: no cover - Windows
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([WARMUP_MODULE])
    return context


#: Set in the fork server's environment, so in every worker it forks: a worker prepares itself by
#: running the command's main script again (multiprocessing does, to find the job function's module),
#: with the command's own ``sys.argv``, and must not start a fork server of its own from there.
IN_FORK_SERVER = "RELPOINT_IN_FORK_SERVER"

#: The native thread pools' sizes, as the fork server (and so every local pool worker) starts with
#: them: one thread each, since the jobs are the parallelism.
SINGLE_THREADED = {
    name: "1"
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
                 "VECLIB_MAXIMUM_THREADS")
}  # fmt: skip


@contextlib.contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
    """``os.environ`` with ``values`` for the duration (what a process started meanwhile inherits)."""
    saved = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def start_fork_server() -> None:
    """Start the fork server now (it warms up in the background; idempotent; a no-op without one).

    The server starts with single-threaded native thread pools (:data:`SINGLE_THREADED`; this
    process's own environment is left as it was). Every job limits them to one thread anyway
    (``threadpoolctl``), but a pool sized at start-up is never made: OpenBLAS starts a thread per
    core when numpy is imported, which slowed the server's warm-up, on the way to every batch's
    first job, by about 0.1 s on 2 cores.
    """
    if pool_context().get_start_method() == "forkserver":
        with _environment({**SINGLE_THREADED, IN_FORK_SERVER: "1"}):
            multiprocessing.forkserver.ensure_running()


def runs_local_pool(args: Sequence[str]) -> bool:
    """Whether the command line ``args`` (after the program name) is ``relpoint batch`` on the local pool:
    ``batch`` after the group's own flags, without ``--scheduler`` or a request for help."""
    for position, arg in enumerate(args):
        if arg not in ("-q", "--quiet", "-v", "--verbose"):
            rest = args[position + 1 :]
            return arg == "batch" and not any(
                option in ("-h", "--help", "--scheduler") or option.startswith("--scheduler=") for option in rest
            )
    return False


def start_fork_server_early(args: Sequence[str]) -> None:
    """Start the fork server before the command line is even parsed when it asks for the local pool.

    The console entry point calls this before importing click and the command modules (70 ms), which
    the fork server's warm-up then overlaps. ``relpoint batch`` starts it again in any case (a no-op).
    Nothing happens in a pool worker, which runs the console script again as it starts (with the
    command's own arguments).
    """
    if runs_local_pool(args) and IN_FORK_SERVER not in os.environ:
        # This process only reads the plan and gathers rows: its own native thread pools, made when
        # the plan's checks import numpy, would only compete with the server's warm-up for the cores.
        os.environ.update(SINGLE_THREADED)
        start_fork_server()
