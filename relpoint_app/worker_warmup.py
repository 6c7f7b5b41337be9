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

import gc
import importlib
import logging
from typing import Any

log = logging.getLogger(__name__)

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


def dask_setup(worker: Any) -> None:
    """Dask's hook for a preloaded module: a cluster worker outlives many batches, so it imports the
    estimators now rather than in its first jobs, and makes what a job's first use would make: the
    message codecs of relpoint's outputs and numpy's masked arrays (``numpy.median`` imports them)."""
    warm_up(estimators=True)
    import numpy.ma  # noqa: F401

    from formats import ros2

    for typename in ros2.OWN_TYPES:
        ros2.own_typestore().get_msgdef(typename)


warm_up()
