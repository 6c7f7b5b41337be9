"""Summary statistics of an error array, computed exactly as evo's ``PE.get_all_statistics``."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

#: The statistics evo reports, in evo's order.
STATISTICS: tuple[str, ...] = ("rmse", "mean", "median", "std", "min", "max", "sse")


def error_statistics(errors: npt.ArrayLike) -> dict[str, float]:
    """rmse, mean, median, std (population, ddof=0), min, max and sse of ``errors`` (N,), N >= 1.

    The formulas and operation order are evo's (``evo.core.metrics.PE.get_statistic``), so the figures
    agree with evo to the last bit for the same error array.

    Raises
    ------
    ValueError
        If ``errors`` is empty.
    """
    error = np.asarray(errors, dtype=np.float64).reshape(-1)
    if error.size == 0:
        raise ValueError("cannot compute statistics of an empty error array")
    squared = np.power(error, 2)
    return {
        "rmse": math.sqrt(float(np.mean(squared))),
        "mean": float(np.mean(error)),
        "median": float(np.median(error)),
        "std": float(np.std(error)),
        "min": float(np.min(error)),
        "max": float(np.max(error)),
        "sse": float(np.sum(squared)),
    }
