"""RltLSF: least-squares rigid fitting between two point clouds (Kraut, section II-B, after Arun et al.).

Paper name -> Python name
    *RltLSF*  :func:`fit_transform`: Arun / Umeyama least-squares rigid fitting with the reflection
              case handled (the rotation is always proper; same mathematics as
              :func:`relpoint.geometry.fit_rigid`, lean enough to run several times per iteration),
              plus the checks the algorithm needs: at least three pairs, a non-collinear source, and
              trimming of gross outliers (mismatched or moving points) before the final fit.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

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
    eigenvalues = np.linalg.eigvalsh(covariance)
    return float(np.sqrt(max(eigenvalues[0] + eigenvalues[1], 0.0)))


def _det3(M: FloatArray) -> float:
    (a, b, c), (d, e, f), (g, h, i) = M.tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def _kabsch(source: FloatArray, target: FloatArray, weights: FloatArray | None) -> tuple[FloatArray, float]:
    """Arun / Umeyama rigid fit (4x4 ``T`` with ``target ≈ R source + t``) and the source's off-line RMS.

    Same mathematics as :func:`relpoint.geometry.fit_rigid` (reflection case handled by flipping
    the weakest singular direction), without its input checking: it runs several times per iteration.
    """
    if weights is None:
        w_src = source
        total = float(len(source))
    else:
        w_src = source * weights[:, None]
        total = float(weights.sum())
    mean_source = w_src.sum(axis=0) / total
    mean_target = (target.T @ weights if weights is not None else target.sum(axis=0)) / total
    centred = source - mean_source
    weighted = centred if weights is None else centred * weights[:, None]
    scatter = weighted.T @ centred / total
    U, _, Vt = np.linalg.svd(weighted.T @ (target - mean_target))
    R = Vt.T @ U.T
    if _det3(R) < 0:
        Vt[2] = -Vt[2]
        R = Vt.T @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mean_target - R @ mean_source
    return T, _off_line_rms(scatter)


def fit_transform(
    source: FloatArray,
    target: FloatArray,
    *,
    trim: float = 3.0,
    floor: float = 0.5,
    collinear_tolerance: float = 0.05,
    weights: FloatArray | None = None,
    rounds: int = 1,
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

    Returns
    -------
    Fit or None
        ``None`` when fewer than three pairs or a collinear source; if trimming would leave a
        degenerate set, the untrimmed fit is kept.
    """
    n = len(source)
    if n < 3:
        return None
    T, spread = _kabsch(source, target, weights)
    if spread <= collinear_tolerance:
        return None
    inliers = np.ones(n, bool)
    if trim > 0 and n > 4:
        for _ in range(rounds):
            difference = target - source @ T[:3, :3].T - T[:3, 3]
            residual = np.sqrt(np.einsum("ij,ij->i", difference, difference))
            keep = residual <= max(trim * float(np.median(residual)), floor)
            if keep.all() or np.array_equal(keep, inliers) or np.count_nonzero(keep) < 3:
                break
            T_kept, spread = _kabsch(source[keep], target[keep], None if weights is None else weights[keep])
            if spread <= collinear_tolerance:
                break
            T, inliers = T_kept, keep
    return Fit(T, inliers)


def apply(T: npt.ArrayLike, points: FloatArray) -> FloatArray:
    """Map points (N, 3) with a 4x4 transform."""
    T = np.asarray(T)
    return points @ T[:3, :3].T + T[:3, 3]
