"""Warm-up of a batch worker process, run on import.

The local pool's fork server imports this module once (:mod:`relpoint_app.batch_start`), so every
worker forked from it has the job modules imported and the estimators' compiled kernels loaded
before its first job; a Dask worker gets the same with ``dask worker --preload
relpoint_app.worker_warmup`` (or ``LocalCluster(preload=[...])``), and imports the estimator modules
as well (:func:`dask_setup`). Without it each worker pays about 0.3 s of imports and kernel loading
in its first jobs.

The fork server leaves each estimator's own modules to the first job that runs it (10-45 ms in each
worker): the server's warm-up is on the way to every batch's first job, and most plans run only some
of the estimators.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import importlib
import logging
import os
import sys
from typing import Any

log = logging.getLogger(__name__)

#: glibc ``mallopt`` parameters (``malloc.h``).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: Heap sizes a worker keeps for its arrays when the environment has fixed glibc's thresholds: the
#: ceiling glibc's own dynamic mmap threshold would reach on a 64-bit machine (32 MiB), and twice
#: that as free heap kept before trimming.
ARRAY_HEAP_BYTES = 32 << 20

#: Libraries every point estimator's job imports (the filters' linear algebra and chi-square gates,
#: every run's pose conversions): imported once here rather than in each worker's first job.
SHARED_LIBRARIES = ("scipy.linalg", "scipy.special", "scipy.spatial.transform")


def warm_up(estimators: bool = False) -> None:
    """Import the job modules and load every built-in estimator's compiled kernels into this process;
    with ``estimators``, import every estimator's modules too."""
    from relpoint.estimators import BUILTIN, ESTIMATORS
    from relpoint_app.batch_jobs import JOB_MODULES

    for module in (*JOB_MODULES, *SHARED_LIBRARIES):
        importlib.import_module(module)

    for name, builtin in BUILTIN.items():
        try:
            if builtin.kernels is not None:
                importlib.import_module(builtin.kernels).prepare()
            if estimators:
                ESTIMATORS[name].estimator_class.compile()
        except Exception as error:  # a kernel that cannot load here compiles in the job, which reports it
            log.debug("warm-up: %s's kernels not loaded (%s)", name, error)
    # What the imports made lives as long as the process: frozen, the garbage collector never walks it
    # again, so collections in the workers forked from here do not write to (and copy) the pages they
    # share with the fork server, and the server's exit does not spend 40 ms walking it.
    gc.freeze()


def keep_array_heap() -> bool:
    """Let glibc keep freed arrays' memory for the next ones, when ``MALLOC_TRIM_THRESHOLD_`` has fixed
    its thresholds (Dask's nanny starts every worker with 64 KiB); returns whether it did.

    Set at all, that variable turns off glibc's dynamic mmap threshold: every array above 128 KiB
    is then mapped from the kernel when made and unmapped when freed, and its pages fault in anew.
    An estimator's iteration makes and frees many such arrays: the 8 jobs of ``benchmarks/batch.py``
    took 5.5 s in one process and 6.35 s with the variable set, 5.6 s with the thresholds raised
    to :data:`ARRAY_HEAP_BYTES` (mmap) and twice that (trim). A worker then holds up to 64 MiB of
    freed heap it would have returned. Nothing is done without glibc or without the variable.
    """
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    done = mallopt(_M_MMAP_THRESHOLD, ARRAY_HEAP_BYTES) == 1 and mallopt(_M_TRIM_THRESHOLD, 2 * ARRAY_HEAP_BYTES) == 1
    log.debug("worker heap: mmap threshold %d B, trim threshold %d B: %s", ARRAY_HEAP_BYTES, 2 * ARRAY_HEAP_BYTES, done)
    return done


def dask_setup(worker: Any) -> None:
    """Dask's hook for a preloaded module: a cluster worker outlives many batches, so it imports the
    estimators now rather than in its first jobs, and makes what a job's first use would make: the
    message codecs of relpoint's outputs and numpy's masked arrays (``numpy.median`` imports them).
    It also lets glibc keep freed arrays' memory (:func:`keep_array_heap`)."""
    keep_array_heap()
    warm_up(estimators=True)
    import numpy.ma  # noqa: F401

    from formats import ros2

    for typename in ros2.OWN_TYPES:
        ros2.own_typestore().get_msgdef(typename)


warm_up()
