"""Data association and rotation helpers shared by the EKF-SLAM and FastSLAM estimators.

Implements the innovation gating of Zhang, Milios and Gu, *General Concept of 3D SLAM*, section 3.2
(eq. 14-16: innovation, its normalisation by the innovation covariance, and a chi-square validation
region), the nearest-neighbour choice among gated pairs, and Joint Compatibility Branch and Bound
(Neira and Tardós, 2001), which tests a whole set of pairings against one joint chi-square gate so
that pairings made wrong by a shared pose error are rejected together.

The SO(3) helpers of the filters' motion models live in :mod:`relpoint.geometry`.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import numpy.typing as npt
from scipy import linalg

from relpoint.geometry import FloatArray
from relpoint.statistics import chi2_gate

logger = logging.getLogger(__name__)

IntArray = npt.NDArray[np.int64]

#: An association that pairs fewer than this share of the landmarks the last observation saw has
#: collapsed (when more points would also start landmarks than pair): the filters then associate
#: again under a wider prior (``collapse_noise_scale``).
COLLAPSE_FRACTION = 0.5


def widening_scales(limit: float) -> FloatArray:
    """The factors 2, 4, 8, ... up to ``limit`` >= 1 (the last one ``limit`` itself) that a collapsed
    association's prior standard deviation is widened by, in turn; none for ``limit`` 1."""
    return np.minimum(2.0 ** np.arange(1, np.ceil(np.log2(limit)) + 1), limit)


# ------------------------------------------------------------------------------------------- gating


def mahalanobis_squared(innovations: FloatArray, S_inv: FloatArray) -> FloatArray:
    """Normalised innovations ``nu^T S^-1 nu`` (eq. 15) of (k, n, 3) innovations with (n, 3, 3) ``S^-1``.

    ``nu^T S^-1`` is one batched matrix product per landmark (a quarter of the time of a
    three-operand einsum at a thousand landmarks), then a row-wise dot product.
    """
    weighted = np.matmul(innovations.transpose(1, 0, 2), S_inv)  # (n, k, 3)
    return np.einsum("nkb,knb->kn", weighted, innovations)


def nearest_neighbour(d2: FloatArray, gate: float) -> tuple[IntArray, npt.NDArray[np.bool_]]:
    """One-to-one nearest-neighbour pairing of k observations with n landmarks.

    Gated pairs (``d2 < gate``) are taken in increasing Mahalanobis distance; an observation or
    landmark already paired is skipped, so each landmark explains at most one observation.

    Parameters
    ----------
    d2: (k, n) squared Mahalanobis distances.
    gate: chi-square threshold.

    Returns
    -------
    assignment: (k,) landmark index per observation, -1 when unpaired.
    gated: (k,) True where the observation fell inside at least one landmark's gate (an unpaired
        gated observation is ambiguous and should not start a new landmark).
    """
    k = d2.shape[0]
    assignment = np.full(k, -1, dtype=np.int64)
    inside = d2 < gate
    gated = inside.any(axis=1) if d2.size else np.zeros(k, dtype=bool)
    obs, lms = np.nonzero(inside)
    order = np.argsort(d2[obs, lms], kind="stable")
    taken: set[int] = set()
    for i, j in zip(obs[order].tolist(), lms[order].tolist(), strict=True):
        if assignment[i] < 0 and j not in taken:
            assignment[i] = j
            taken.add(j)
    return assignment, gated


def jcbb_search(
    d2: FloatArray,
    innovations: FloatArray,
    covariance: FloatArray,
    observation_cov: FloatArray,
    probability: float = 0.99,
    max_nodes: int = 10_000,
    max_seconds: float = 0.0,
) -> tuple[IntArray, bool]:
    """Joint Compatibility Branch and Bound (Neira and Tardós, 2001).

    Searches for the largest set of one-to-one pairings whose stacked innovation passes a
    chi-square test with its joint covariance; among sets of equal size, the one with the smallest
    joint Mahalanobis distance wins. Only individually compatible pairs (``d2`` inside the 3-DOF
    gate) are considered. The joint distance is extended pair by pair through a growing Cholesky
    factor, so each node costs O(pairs^2).

    Parameters
    ----------
    d2: (k, n) individual squared Mahalanobis distances.
    innovations: (k, n, 3) ``z_i - h_j``.
    covariance: (3n, 3n) ``H P H^T`` over the n landmarks' predicted measurements (no noise).
    observation_cov: (3, 3) measurement noise added to each paired observation.
    probability: chi-square gate probability, individual and joint.
    max_nodes: search budget in nodes; when exceeded, the best hypothesis found so far is returned.
    max_seconds: search budget in wall-clock seconds (0: none), checked at every node; the same.

    Returns
    -------
    assignment: (k,) landmark index per observation, -1 when unpaired.
    gave_up: True when a budget ran out before the search was complete.
    """
    k = d2.shape[0]
    assignment = np.full(k, -1, dtype=np.int64)
    if d2.size == 0:
        return assignment, False
    deadline = time.perf_counter() + max_seconds if max_seconds > 0 else np.inf
    compatible = d2 < chi2_gate(probability, 3)
    order = [int(i) for i in np.argsort(d2.min(axis=1), kind="stable") if compatible[i].any()]
    candidates = [np.flatnonzero(compatible[i])[np.argsort(d2[i, compatible[i]], kind="stable")] for i in order]
    levels = len(order)
    best_count, best_d2, best_assignment = 0, np.inf, assignment.copy()
    current = assignment.copy()
    used = np.zeros(d2.shape[1], dtype=bool)
    nodes = 0
    out_of_budget = False

    def cross_covariance(rows: list[int], col: int) -> FloatArray:
        r = (3 * np.asarray(rows, dtype=np.int64)[:, None] + np.arange(3)).ravel()
        return covariance[r, 3 * col : 3 * col + 3]

    def search(level: int, L: FloatArray, w: FloatArray, joint: float, paired: list[int]) -> None:
        """Extend the hypothesis ``paired`` (Cholesky factor L of its S, ``w = L^-1 nu``) at ``level``."""
        nonlocal nodes, best_count, best_d2, best_assignment, out_of_budget
        count = len(paired)
        if level == levels:
            if count > best_count or (count == best_count and joint < best_d2):
                best_count, best_d2, best_assignment = count, joint, current.copy()
            return
        nodes += 1
        if nodes > max_nodes or time.perf_counter() > deadline:
            out_of_budget = True
            return
        remaining = levels - level
        i = order[level]
        if count + remaining >= best_count:
            joint_gate = chi2_gate(probability, 3 * (count + 1))
            for j in candidates[level].tolist():
                if used[j]:
                    continue
                # x = L^-1 (cross-covariance of the paired measurements with landmark j's).
                x = linalg.solve_triangular(L, cross_covariance(paired, j), lower=True) if paired else np.zeros((0, 3))
                s = covariance[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] + observation_cov - x.T @ x
                try:
                    L22 = np.linalg.cholesky(s)
                except np.linalg.LinAlgError:
                    continue
                w2 = linalg.solve_triangular(L22, innovations[i, j] - x.T @ w, lower=True)
                extended = joint + float(w2 @ w2)
                # The joint distance only grows as pairs are added: a tie in count must already win on it.
                if extended >= joint_gate or (count + remaining == best_count and extended >= best_d2):
                    continue
                n = 3 * count
                L_new = np.zeros((n + 3, n + 3))
                L_new[:n, :n] = L
                L_new[n:, :n] = x.T
                L_new[n:, n:] = L22
                used[j] = True
                current[i] = j
                search(level + 1, L_new, np.concatenate([w, w2]), extended, [*paired, j])
                used[j] = False
                current[i] = -1
                if out_of_budget:
                    return
        # Leave observation i unpaired.
        if count + remaining - 1 > best_count or (count + remaining - 1 == best_count and joint < best_d2):
            search(level + 1, L, w, joint, paired)

    search(0, np.zeros((0, 0)), np.zeros(0), 0.0, [])
    if out_of_budget:
        logger.debug("JCBB stopped after %d nodes; returning the best of %d pairings", nodes, best_count)
    return best_assignment, out_of_budget
