"""Synchronising low-rate position fixes to observation times by Lagrange interpolation.

Implements Zhang, Milios and Gu, *General Concept of 3D SLAM*, section 5.1 (eq. 26-30): the fix
position at an observation time ``t`` is a three-point Lagrange interpolation of the fixes around it,
and its covariance is the same combination with squared weights (the fixes are independent). Eq. 29
as printed has ``(t_{b,k-2} - t_{b,k-2})`` in its denominator, which is zero; the Lagrange basis it
stands for is ``xi_3 = (t - t_{k-2})(t - t_{k-1}) / ((t_k - t_{k-2})(t_k - t_{k-1}))``, used here. With
only two fixes the interpolation is linear, as the section says; with one fix it is constant.

The three nodes for a time inside the fixes' span are the two fixes bracketing it plus the nearer of
their outer neighbours; outside the span the two nearest fixes extrapolate linearly (a quadratic
would swing far off within one fix interval).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from relpoint.errors import EstimatorError
from relpoint.geometry import FloatArray


def lagrange_weights(t: float, nodes: npt.ArrayLike) -> FloatArray:
    """Lagrange basis values ``xi_j(t)`` of distinct ``nodes`` (K,), so ``f(t) ~ sum_j xi_j f(nodes[j])``.

    For three nodes these are eq. 27, 28 and the corrected eq. 29; the weights sum to one.
    """
    nodes = np.asarray(nodes, dtype=np.float64)
    weights = np.ones(len(nodes))
    for j in range(len(nodes)):
        for m in range(len(nodes)):
            if m != j:
                weights[j] *= (t - nodes[m]) / (nodes[j] - nodes[m])
    return weights


def _nodes(index: int, t: float, times: FloatArray) -> list[int]:
    """Indices of the fixes used for time ``t``; ``index`` = first fix at or after ``t``."""
    n = len(times)
    if n == 1:
        return [0]
    if n == 2 or t <= times[0] or t >= times[-1]:
        # Linear: the bracketing pair, or the two nearest fixes outside the span.
        lo = int(np.clip(index - 1, 0, n - 2))
        return [lo, lo + 1]
    lo, hi = index - 1, index  # times[lo] < t <= times[hi]
    if lo == 0:
        return [lo, hi, hi + 1]
    if hi == n - 1:
        return [lo - 1, lo, hi]
    # The nearer outer neighbour keeps the interpolation local.
    return [lo - 1, lo, hi] if t - times[lo - 1] <= times[hi + 1] - t else [lo, hi, hi + 1]


def interpolate_fixes(
    fix_stamps_ns: npt.ArrayLike,
    fix_positions: npt.ArrayLike,
    fix_covariances: npt.ArrayLike,
    stamps_ns: npt.ArrayLike,
) -> tuple[FloatArray, FloatArray]:
    """Fix position and covariance at each of ``stamps_ns`` (eq. 26 and 30).

    Parameters
    ----------
    fix_stamps_ns:
        (M,) strictly increasing fix times, integer nanoseconds.
    fix_positions:
        (M, 3) fix positions in ``world``, metres.
    fix_covariances:
        (M, 3, 3) fix position covariances, m².
    stamps_ns:
        (N,) times to interpolate at, integer nanoseconds.

    Returns
    -------
    positions, covariances:
        (N, 3) metres and (N, 3, 3) m², in ``world``.

    Raises
    ------
    EstimatorError
        No fix at all, or fix stamps that do not strictly increase.
    """
    fix_stamps = np.asarray(fix_stamps_ns, dtype=np.int64).reshape(-1)
    positions = np.asarray(fix_positions, dtype=np.float64).reshape(-1, 3)
    covariances = np.asarray(fix_covariances, dtype=np.float64).reshape(-1, 3, 3)
    if len(fix_stamps) == 0:
        raise EstimatorError("no position fix to interpolate", "the log needs /fix messages (or pass --fix-topic)")
    if not (len(fix_stamps) == len(positions) == len(covariances)):
        raise ValueError("fix stamps, positions and covariances differ in length")
    if np.any(np.diff(fix_stamps) <= 0):
        raise EstimatorError("position fix stamps must strictly increase")
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    # Seconds relative to the first fix keep the basis well conditioned.
    times = (fix_stamps - fix_stamps[0]).astype(np.float64) * 1e-9
    queries = (stamps - fix_stamps[0]).astype(np.float64) * 1e-9
    after = np.searchsorted(times, queries, side="left")
    out_positions = np.empty((len(stamps), 3))
    out_covariances = np.empty((len(stamps), 3, 3))
    for i, (t, index) in enumerate(zip(queries, after, strict=True)):
        nodes = _nodes(int(index), float(t), times)
        xi = lagrange_weights(float(t), times[nodes])
        out_positions[i] = xi @ positions[nodes]
        out_covariances[i] = np.einsum("j,jab->ab", xi**2, covariances[nodes])
    return out_positions, out_covariances
