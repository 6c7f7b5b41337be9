"""The application layer: read a log, drive an estimator, write and evaluate its outputs.

Between :mod:`formats` (bytes to core types and back) and the core package :mod:`relpoint` (pure
computation): the command line (:mod:`relpoint_cli`) keeps only options, printing and exit codes, and
scripts use the same functions, also reachable as ``relpoint.run`` and ``relpoint.evaluate``::

    import relpoint
    result = relpoint.run("sample_logs/figure8.mcap", estimator="relpoint", final_adjustment=False)
    result.trajectory, result.landmarks, result.timing_summary()
    relpoint.evaluate(result, reference="sample_logs/figure8.mcap", align="se3").summary["ate_rmse"]

Submodules are imported when used, so that importing this package costs nothing.
"""

from __future__ import annotations

from typing import Any

__all__ = ["evaluate", "run"]


def __getattr__(name: str) -> Any:
    if name == "run":
        from relpoint_app.runner import run

        return run
    if name == "evaluate":
        from relpoint_app.evaluator import evaluate

        return evaluate
    raise AttributeError(f"module 'relpoint_app' has no attribute {name!r}")
