"""Warm-up of a batch worker process, run on import.

The local pool's fork server imports this module once (:mod:`relpoint_app.batch_start`), so every
worker forked from it has the job modules imported and the estimators' compiled kernels loaded
before its first job; a Dask worker gets the same with ``dask worker --preload
relpoint_app.worker_warmup`` (or ``LocalCluster(preload=[...])``). Without it each worker pays
about 0.6 s of imports and kernel loading in its first jobs.
"""

from __future__ import annotations

import gc
import logging

log = logging.getLogger(__name__)


def warm_up() -> None:
    """Import the job modules and load every estimator's compiled kernels into this process."""
    import relpoint_app.batch_jobs  # noqa: F401  (the imports every job makes)
    from relpoint.estimators import ESTIMATORS

    for name in ESTIMATORS:
        try:
            ESTIMATORS[name].estimator_class.compile()
        except Exception as error:  # a kernel that cannot load here compiles in the job, which reports it
            log.debug("warm-up: %s's kernels not loaded (%s)", name, error)
    # What the imports made lives as long as the process: frozen, the garbage collector never walks it
    # again, so collections in the workers forked from here do not write to (and copy) the pages they
    # share with the fork server, and the server's exit does not spend 40 ms walking it.
    gc.freeze()


warm_up()
