"""Statistics the estimators and the fusion share: chi-square gates and a stable log-sum-exp.

Written with :mod:`math` and numpy rather than ``scipy.special``: an EKF or FastSLAM run needs nothing
else from scipy, and importing it costs a fifth of a second of start-up in every batch worker. The
tests check both functions against ``scipy.special``.
"""

from __future__ import annotations

import decimal
import functools
import math

import numpy as np
import numpy.typing as npt

#: Relative change of a Newton step below which the quantile is taken as converged.
_TOLERANCE = 4e-16
#: Digits of the final Newton step, which makes the quantile the float nearest the exact one.
_DIGITS = 50
_PI = decimal.Decimal("3.14159265358979323846264338327950288419716939937510582097494459")


def _chi2_tails(dof: int, x: float) -> tuple[float, float]:
    """Both tails ``(P, Q)`` of the chi-square distribution of ``dof`` degrees of freedom at ``x >= 0``.

    The regularised incomplete gamma functions at ``a = dof / 2``, ``y = x / 2``: below ``y = a + 1``
    the series of ``P`` (all terms positive), above it the closed form of ``Q`` for a half-integer
    ``a`` (a finite sum, plus ``erfc`` for odd ``dof``). The other tail is one minus the accurate one.
    """
    a, y = 0.5 * dof, 0.5 * x
    if y <= 0.0:
        return 0.0, 1.0
    if y < a + 1.0:
        term = total = 1.0
        n = 0
        while term > total * 1e-17:
            n += 1
            term *= y / (a + n)
            total += term
        p = total * math.exp(a * math.log(y) - y - math.lgamma(a + 1.0))
        return p, 1.0 - p
    # Q(a, y) = e^-y sum_{i < a} y^i / i!  (integer a), or erfc(sqrt y) + e^-y sum y^(i+1/2) / Gamma(i+3/2).
    if dof % 2 == 0:
        term, total, start = 1.0, 0.0, 0.0
    else:
        term, total, start = math.sqrt(y) / math.gamma(1.5), 0.0, 0.5
    order = start
    while order < a:
        total += term
        order += 1.0
        term *= y / order
    q = math.exp(-y) * total
    if dof % 2:
        q += math.erfc(math.sqrt(y))
    return 1.0 - q, q


def _chi2_density(dof: int, x: float) -> float:
    a, y = 0.5 * dof, 0.5 * x
    return 0.5 * math.exp((a - 1.0) * math.log(y) - y - math.lgamma(a))


def _chi2_lower_tail_exact(dof: int, x: float) -> decimal.Decimal:
    """``P(dof / 2, x / 2)`` to :data:`_DIGITS` digits: the series of :func:`_chi2_tails` in decimal arithmetic."""
    with decimal.localcontext() as context:
        context.prec = _DIGITS + 10
        a = decimal.Decimal(dof) / 2
        y = decimal.Decimal(x) / 2
        if dof % 2 == 0:  # Gamma(a + 1) = a!
            gamma = decimal.Decimal(math.factorial(dof // 2))
        else:  # Gamma(k + 1/2) = (2k)! sqrt(pi) / (4^k k!), k = a + 1/2
            k = (dof + 1) // 2
            gamma = decimal.Decimal(math.factorial(2 * k)) * _PI.sqrt() / (4**k * math.factorial(k))
        term = total = decimal.Decimal(1)
        n = 0
        limit = decimal.Decimal(10) ** -(_DIGITS + 5)
        while term > total * limit:
            n += 1
            term = term * y / (a + n)
            total += term
        return total * (a * y.ln() - y).exp() / gamma


def chi2_quantile(probability: float, dof: int) -> float:
    """Chi-square quantile: the ``x`` at which the CDF of ``dof`` degrees of freedom reaches ``probability``.

    What ``scipy.stats.chi2.ppf`` gives, by a Newton iteration on the closed-form CDF kept inside a
    shrinking bracket (bisection when a step leaves it). It works on the smaller tail, so it keeps
    its relative accuracy for probabilities near 0 and near 1 (``1 - probability`` is exact in
    floating point there). A last Newton step with the CDF in 50-digit decimal arithmetic rounds the
    result to the double nearest the exact quantile (scipy's is within a few ulps of it).
    """
    if not 0.0 <= probability <= 1.0 or dof < 1:
        raise ValueError(f"chi2_quantile needs 0 <= probability <= 1 and dof >= 1, got {probability}, {dof}")
    if probability == 0.0:
        return 0.0
    if probability == 1.0:
        return math.inf
    upper = probability > 0.5
    target = 1.0 - probability if upper else probability

    def residual(x: float) -> float:  # increases with x; zero at the quantile
        p, q = _chi2_tails(dof, x)
        return target - q if upper else p - target

    low, high = 0.0, 2.0 * dof
    while residual(high) < 0.0:
        low, high = high, 2.0 * high
    x = 0.5 * (low + high)
    for _ in range(200):
        r = residual(x)
        if r == 0.0:
            break
        if r > 0.0:
            high = x
        else:
            low = x
        candidate = x - r / _chi2_density(dof, x)
        if not low < candidate < high:
            candidate = 0.5 * (low + high)
        if abs(candidate - x) <= _TOLERANCE * x or high - low <= _TOLERANCE * x:
            x = candidate
            break
        x = candidate
    return _polish(dof, x, probability)


def _polish(dof: int, x: float, probability: float) -> float:
    """One Newton step from ``x`` with the CDF in decimal arithmetic: the double nearest the exact quantile."""
    if x <= 0.0:
        return x
    with decimal.localcontext() as context:
        context.prec = _DIGITS
        residual = _chi2_lower_tail_exact(dof, x) - decimal.Decimal(probability)
        return float(decimal.Decimal(x) - residual / decimal.Decimal(_chi2_density(dof, x)))


@functools.lru_cache(maxsize=4096)
def chi2_gate(probability: float, dof: int) -> float:
    """Chi-square quantile: squared Mahalanobis distance inside which ``probability`` of innovations fall."""
    return chi2_quantile(probability, dof)


def log_sum_exp(values: npt.ArrayLike) -> float:
    """``log(sum(exp(values)))`` of a vector, without overflow or underflow.

    ``scipy.special.logsumexp``'s own steps for a 1-d real input (the largest terms are taken out of
    the sum and added back through ``log1p``), so the two give the same bits.
    """
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return -math.inf
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        largest = a.max()
        at_max = a == largest
        count = float(np.count_nonzero(at_max))
        rest = np.sum(np.exp(np.where(at_max, -np.inf, a) - largest))
        if rest != 0.0:
            rest = rest / count
        out = float(np.log1p(rest) + np.log(count) + largest)
        if not math.isfinite(out):  # every term -inf, an inf or a NaN: the direct formula handles them
            out = float(np.log(np.sum(np.exp(a))))
    return out
