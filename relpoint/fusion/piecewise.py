"""Piecewise-rigid placement: split a segment whose rigid fit to the fixes is inconsistent with them.

An extension of Zhang, Milios and Gu, *General Concept of 3D SLAM*, section 6.3, for the post-step
over a finished run. Section 6.3 places each local map by one rigid transform, which assumes the local
map is rigid. A continuous local SLAM that keeps its map through a gap re-associates old landmarks
after it (a loop closure across the break) and bends its path inside what Algorithm 3 would call one
segment; a segment that drifted far is bent too. One rigid transform cannot undo a bend, and the fit
then leaves residuals far beyond what the fixes' covariance allows.

The test: with ``n`` (spline position, fix) pairs, residuals ``r_i = x_b(i) - (R x'_v(i) + T)`` and
their covariances ``S_i = P_b(i) + R P_vv(i) R^T``, the statistic ``sum_i r_i^T S_i^-1 r_i`` is
chi-square with ``3n - 6`` degrees of freedom when the segment is rigid and the covariances are
right. When it exceeds the ``1 - significance`` quantile, the segment is split in two at the fix
that minimises the two pieces' statistics together (each piece a rigid fit of its own), and each
piece is tested again. Both pieces keep at least ``min_pairs`` fixes and ``min_length`` iterations,
and each is either placeable (its local positions at least ``min_spread`` RMS off a straight line,
section 6.3's condition) or fails the test itself: a local SLAM that held its pose after a gap is cut
out that way. Pieces that still fail the test are returned with ``rigid`` False (neighbouring ones
merged) for the caller to leave out. A rigid segment (the restarted local SLAM of Algorithm 3) passes
the test and stays whole, so this changes nothing where the chapter's assumptions hold.

The iteration boundary between two pieces is the longest step of the local path between the last fix
of one and the first fix of the other (a re-association or a held pose let go shows as a jump), or
halfway between the two fixes when all those steps are equal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.errors import EstimatorError
from relpoint.fusion.bspline import PathSpline
from relpoint.geometry import FloatArray, fit_rigid_on_axes, fitted_parameters, measured_basis
from relpoint.statistics import chi2_gate


@dataclass(frozen=True)
class Piece:
    """Iterations ``[start, stop)`` of a segment placed by one rigid fit, and its chi-square test.

    ``statistic`` and ``threshold`` are NaN when the piece was not tested (too few fixes, splitting off).
    """

    start: int
    stop: int
    statistic: float = math.nan
    threshold: float = math.nan
    dof: int = 0

    @property
    def rigid(self) -> bool:
        """False when the piece's rigid fit failed the test (it could not be split further)."""
        return not self.statistic > self.threshold


def _off_line(points: FloatArray) -> float:
    """RMS distance of points (n, 3) from their best-fitting straight line, metres."""
    singular = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return float(np.sqrt(np.sum(singular[1:] ** 2) / len(points)))


def rigid_fit_statistic(local: FloatArray, targets: FloatArray, target_cov: FloatArray, local_cov: FloatArray) -> float:
    """``sum_i r_i^T S_i^-1 r_i`` of the weighted rigid fit of ``local`` (n, 3) onto ``targets`` (n, 3).

    ``target_cov`` and ``local_cov`` are (n, 3, 3) m²; the weights are those of
    :func:`.global_map.fit_segment` (inverse mean variance per pair).
    """
    basis = measured_basis(target_cov)
    total_cov = np.einsum("ai,nab,bj->nij", basis, target_cov + local_cov, basis)
    weights = 1.0 / np.maximum(np.trace(total_cov, axis1=1, axis2=2) / basis.shape[1], 1e-12)
    fit = fit_rigid_on_axes(local, targets, weights, basis)
    residuals = (targets - fit.apply(local)) @ basis  # on the measured axes
    S = target_cov + np.einsum("ab,nbc,dc->nad", fit.rotation, local_cov, fit.rotation)
    S = np.einsum("ai,nab,bj->nij", basis, S, basis)
    return float(np.einsum("na,na->", residuals, np.linalg.solve(S, residuals[..., None])[..., 0]))


def split_segment(
    stamps_ns: npt.ArrayLike,
    positions: npt.ArrayLike,
    covariances: npt.ArrayLike,
    fix_stamps_ns: npt.ArrayLike,
    fix_positions: npt.ArrayLike,
    fix_covariances: npt.ArrayLike,
    *,
    significance: float = 0.001,
    min_pairs: int = 3,
    min_spread: float = 1.0,
    min_length: int = 4,
) -> list[Piece]:
    """Pieces ``[start, stop)`` (iteration indices into the segment) each rigid enough for one transform.

    Parameters
    ----------
    stamps_ns, positions, covariances:
        (K,), (K, 3) metres and (K, 3, 3) m²: the segment's local path and ``P_vv``.
    fix_stamps_ns, fix_positions, fix_covariances:
        (M,), (M, 3) metres and (M, 3, 3) m²: every fix (those in the segment's span are used).
    significance:
        Probability that a rigid segment fails the chi-square test (a needless split); 0 never splits.
    min_pairs, min_spread, min_length:
        What each piece must keep (see the module docstring).

    Returns
    -------
    The pieces in time order; one piece ``[0, K)`` when the segment is consistent with one rigid transform,
    cannot be split, or cannot be fitted at all (the caller's fit then reports why).
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    k = len(stamps)
    if significance <= 0:
        return [Piece(0, k)]
    points = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    try:
        spline = PathSpline.fit(stamps, points, covariances)
    except EstimatorError:
        return [Piece(0, k)]
    all_fix_stamps = np.asarray(fix_stamps_ns, dtype=np.int64).reshape(-1)
    inside = spline.contains(all_fix_stamps)
    fix_stamps = all_fix_stamps[inside]
    n = len(fix_stamps)
    pairs_needed = max(3, min_pairs)
    if n < 2 * pairs_needed:
        return [Piece(0, k)]
    local = spline(fix_stamps)
    local_cov = spline.covariance(fix_stamps)
    targets = np.asarray(fix_positions, dtype=np.float64).reshape(-1, 3)[inside]
    target_cov = np.asarray(fix_covariances, dtype=np.float64).reshape(-1, 3, 3)[inside]
    basis = measured_basis(target_cov)  # the axes the fixes measure, and the parameters fitted on them
    measured, parameters = basis.shape[1], fitted_parameters(basis).shape[1]

    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)

    def boundary(j: int) -> int:
        """First iteration of the piece whose first fix is ``j`` (0 < j < n): after the longest step between
        fixes ``j - 1`` and ``j`` (a re-association shows as a jump), halfway between them on a tie."""
        if j <= 0:
            return 0
        if j >= n:
            return k
        first = int(np.searchsorted(stamps, fix_stamps[j - 1], side="right"))  # first iteration after fix j-1
        last = int(np.searchsorted(stamps, fix_stamps[j], side="left"))  # last iteration at or before fix j
        last = min(max(last, first), k - 1)
        candidates = steps[first - 1 : last]  # step i leads from iteration i to i + 1
        if len(candidates) == 0 or np.ptp(candidates) <= 1e-9 * max(float(candidates.max()), 1.0):
            middle = (int(fix_stamps[j - 1]) + int(fix_stamps[j])) // 2
            return int(np.searchsorted(stamps, middle, side="right"))
        return first + int(np.argmax(candidates))

    cache: dict[tuple[int, int], tuple[float, float, int]] = {}

    def test(a: int, b: int) -> tuple[float, float, int]:
        """Statistic, threshold and degrees of freedom of the rigid fit of fixes ``[a, b)``."""
        if (a, b) not in cache:
            dof = measured * (b - a) - parameters
            if dof <= 0:
                cache[a, b] = (math.nan, math.nan, 0)
            else:
                value = rigid_fit_statistic(local[a:b], targets[a:b], target_cov[a:b], local_cov[a:b])
                cache[a, b] = (value, chi2_gate(1.0 - significance, dof), dof)
        return cache[a, b]

    def failing(a: int, b: int) -> bool:
        value, threshold, _ = test(a, b)
        return value > threshold

    def valid(a: int, b: int) -> bool:
        """A piece may be cut: enough fixes and iterations, and placeable (off a line) or itself not rigid."""
        if b - a < pairs_needed or boundary(b) - boundary(a) < min_length:
            return False
        return _off_line(local[a:b]) >= min_spread or failing(a, b)

    def pieces(a: int, b: int) -> list[tuple[int, int]]:
        if not failing(a, b):
            return [(a, b)]
        best: tuple[float, int] | None = None
        for j in range(a + pairs_needed, b - pairs_needed + 1):
            if valid(a, j) and valid(j, b):
                total = test(a, j)[0] + test(j, b)[0]
                if best is None or total < best[0]:
                    best = (total, j)
        if best is None:
            return [(a, b)]
        return pieces(a, best[1]) + pieces(best[1], b)

    # Neighbouring pieces that are still not rigid are left out together: one piece.
    merged: list[tuple[int, int]] = []
    for a, b in pieces(0, n):
        if merged and failing(*merged[-1]) and failing(a, b):
            merged[-1] = (merged[-1][0], b)
        else:
            merged.append((a, b))
    return [Piece(boundary(a), boundary(b), *test(a, b)) for a, b in merged]
