"""What ``relpoint batch`` needs before it reads a plan: the job limit, the worker count, and the
local pool's fork server.

This module imports nothing heavy, so that the command can start the fork server first: the server
then imports and warms up what every job needs (:mod:`relpoint_app.worker_warmup`) on another core
while the command reads the plan, and every worker forked from it starts its first job warm.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.context
import multiprocessing.forkserver
import os
from collections.abc import Sequence

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


def start_fork_server() -> None:
    """Start the fork server now (it warms up in the background; idempotent; a no-op without one)."""
    if pool_context().get_start_method() == "forkserver":
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
    """
    if runs_local_pool(args):
        start_fork_server()
