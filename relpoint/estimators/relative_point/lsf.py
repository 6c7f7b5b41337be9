"""RltLSF: least-squares rigid fitting between two point clouds (Kraut, section II-B, after Arun et al.).

Paper name -> Python name
    *RltLSF*  :func:`fit_transform`: Arun / Umeyama least-squares rigid fitting with the reflection
              case handled (the rotation is always proper; same mathematics as
              :func:`relpoint.geometry.fit_rigid`, lean enough to run several times per iteration),
              plus the checks the algorithm needs: at least three pairs, a non-collinear source, and
              trimming of gross outliers (mismatched or moving points) before the final fit.

The fit and the trimming rounds run as one compiled call (:func:`~._kernels.robust_fit`, over
:func:`~._kernels.rigid_fit` and :func:`~._kernels.trimmed_fit`; their docstrings give the numpy
they equal); only the consensus re-seeding, when called for, runs in numpy. The kernel finds the
Arun / Umeyama rotation (the best proper rotation, reflections excluded) by Horn's quaternion method,
which reaches the same optimum without a LAPACK call; the tests compare it with the SVD solution.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from relpoint.estimators.relative_point._kernels import (
    FIT_DEGENERATE,
    FIT_WANTS_CONSENSUS,
    off_line_rms,
    pair_residuals,
    rigid_fit,
    robust_fit,
    trimmed_fit,
)
from relpoint.geometry import FloatArray


class Fit(NamedTuple):
    """A rigid fit ``target ≈ T[:3,:3] @ source + T[:3,3]``.

    ``T`` is (4, 4); ``inliers`` (N,) marks the pairs kept by trimming.
    """

    T: FloatArray
    inliers: npt.NDArray[np.bool_]


def is_collinear(points: FloatArray, tolerance: float) -> bool:
    """Whether points (N, 3) fail to span a plane: fewer than 3, or RMS off their best line <= ``tolerance`` m."""
    if len(points) < 3:
        return True
    centred = points - points.mean(axis=0)
    return _off_line_rms(centred.T @ centred / len(points)) <= tolerance


def _off_line_rms(covariance: FloatArray) -> float:
    # The two smallest eigenvalues of the scatter are the mean squared distance off the best line.
    (a, d, e), (_, b, f), (_, _, c) = np.asarray(covariance, dtype=np.float64).tolist()
    return off_line_rms(a, b, c, d, e, f)


def _median(values: FloatArray) -> float:
    """Median of a 1-D array (``np.median`` without its overhead: one partition)."""
    n = len(values)
    half = n // 2
    if n % 2:
        return float(np.partition(values, half)[half])
    low, high = np.partition(values, (half - 1, half))[half - 1 : half + 1].tolist()
    return 0.5 * (low + high)


def fit_transform(
    source: FloatArray,
    target: FloatArray,
    *,
    trim: float = 3.0,
    floor: float = 0.5,
    collinear_tolerance: float = 0.05,
    weights: FloatArray | None = None,
    rounds: int = 1,
    consensus: float = 0.0,
) -> Fit | None:
    """Rigid transform taking ``source`` (N, 3) onto ``target`` (N, 3), or ``None`` if degenerate.

    Parameters
    ----------
    source, target:
        Corresponding points in their two frames, metres (finite).
    trim:
        After a fit, pairs whose residual exceeds ``max(trim * median residual, floor)`` are dropped
        and the fit is repeated, up to ``rounds`` times or until the inliers settle (0 disables
        trimming). The median over all pairs is robust while fewer than half are outliers.
    floor:
        Smallest residual (m) that trimming may call an outlier.
    collinear_tolerance:
        Sources whose RMS distance from their best line is at most this (m) give no unique rotation.
    weights:
        Optional non-negative per-pair weights (N,).
    rounds:
        Trimming rounds at most.
    consensus:
        Consensus bound (m; 0 disables). When 5 % of the pairs (at least two) have residuals above
        it after the first fit, the fit is re-seeded from the minimal three-pair fit
        (:func:`_consensus`) that the most weight agrees with within the bound, and pairs outside
        the bound are dropped before trimming: moving points cannot pull the fit while they are a
        minority of the weight, whereas the median rule of ``trim`` only sees them once most pairs
        fit well.

    Returns
    -------
    Fit or None
        ``None`` when fewer than three pairs or a collinear source; if trimming would leave a
        degenerate set, the untrimmed fit is kept.
    """
    if len(source) < 3:
        return None
    source = np.ascontiguousarray(source, dtype=np.float64)
    target = np.ascontiguousarray(target, dtype=np.float64)
    weights = np.ones(len(source)) if weights is None else np.ascontiguousarray(weights, dtype=np.float64)
    T, inliers, outcome = robust_fit(
        source, target, weights, float(trim), float(floor), float(collinear_tolerance), int(rounds), float(consensus),
        _CONSENSUS_SHARE,
    )  # fmt: skip
    if outcome == FIT_DEGENERATE:
        return None
    if outcome == FIT_WANTS_CONSENSUS:
        T, inliers = _reseeded_fit(source, target, weights, T, trim, floor, collinear_tolerance, rounds, consensus)
    return Fit(T, inliers)


def _reseeded_fit(
    source: FloatArray,
    target: FloatArray,
    weights: FloatArray,
    T: FloatArray,
    trim: float,
    floor: float,
    collinear_tolerance: float,
    rounds: int,
    consensus: float,
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """The rest of :func:`fit_transform` once the first fit ``T`` left a group of pairs beyond ``consensus``.

    The fit restarts from the pairs that agree with the best minimal fit (:func:`_consensus`), if
    that one gathers more weight and is not collinear, and is then trimmed among those pairs.
    """
    inliers = np.ones(len(source), bool)
    agree = _consensus(source, target, weights, consensus, pair_residuals(source, target, T))
    if agree is not None:
        T_agree, spread = rigid_fit(source, target, weights, agree)
        if spread > collinear_tolerance:
            T, inliers = T_agree, agree
    if trim > 0:
        # Trimming only removes pairs the consensus kept (all without it).
        T, inliers = trimmed_fit(source, target, weights, T, inliers, trim, floor, rounds, collinear_tolerance)
    return T, inliers


_CONSENSUS_SHARE = 0.05
"""The consensus runs when at least this share of the pairs (and two) lie beyond its bound."""
_CONSENSUS_ANCHORS = 8
"""Minimal fits are drawn from the heaviest this many pairs (all their triples: 56 at most)."""
_TRIPLES = {
    m: np.array(list(itertools.combinations(range(m), 3)), dtype=np.int64) for m in range(3, _CONSENSUS_ANCHORS + 1)
}


def _consensus(
    source: FloatArray, target: FloatArray, w: FloatArray, bound: float, residual: FloatArray
) -> npt.NDArray[np.bool_] | None:
    """Pairs agreeing within ``bound`` with the best minimal (three-pair) fit, or ``None``.

    Deterministic RANSAC: every triple of the heaviest pairs is fitted at once (batched SVD); the
    fit whose agreeing pairs carry the most weight wins (ties: smaller summed residual). ``None``
    unless it gathers more weight than the full fit's own agreeing pairs (``residual``, (N,)).
    """
    n = len(source)
    m = min(n, _CONSENSUS_ANCHORS)
    heaviest = np.argsort(-w, kind="stable")[:m] if m < n else np.arange(n)
    triples = heaviest[_TRIPLES[m]]  # (K, 3)
    src, dst = source[triples], target[triples]  # (K, 3, 3)
    src_mean, dst_mean = src.mean(axis=1), dst.mean(axis=1)
    H = np.einsum("kia,kib->kab", src - src_mean[:, None], dst - dst_mean[:, None])
    U, _, Vt = np.linalg.svd(H)
    flip = np.linalg.det(np.einsum("kab,kbc->kac", U, Vt)) < 0
    Vt[flip, 2] *= -1.0
    R = np.einsum("kba,kcb->kac", Vt, U)  # (V U^T) per triple
    t = dst_mean - np.einsum("kab,kb->ka", R, src_mean)
    difference = target[None] - np.einsum("kab,nb->kna", R, source) - t[:, None]
    residuals = np.sqrt(np.einsum("kna,kna->kn", difference, difference))  # (K, N)
    agree = residuals <= bound
    support = agree.astype(np.float64) @ w
    best = int(np.lexsort((np.where(agree, residuals, bound).sum(axis=1), -support))[0])
    chosen = agree[best]
    if np.count_nonzero(chosen) < 3 or support[best] <= float(w[residual <= bound].sum()):
        return None
    return chosen
