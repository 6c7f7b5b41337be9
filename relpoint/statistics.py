"""Statistics the estimators and the fusion share: chi-square gates."""

from __future__ import annotations

import functools


@functools.lru_cache(maxsize=4096)
def chi2_gate(probability: float, dof: int) -> float:
    """Chi-square quantile: squared Mahalanobis distance inside which ``probability`` of innovations fall.

    ``scipy.stats.chi2.ppf``'s own formula, ``2 P^-1(dof / 2, probability)`` (the inverse regularised
    lower incomplete gamma function), without importing ``scipy.stats`` (a third of a second); scipy
    itself is imported on the first call, so that the estimators' settings import without it."""
    from scipy import special

    return float(2.0 * special.gammaincinv(dof / 2, probability))
