"""From local segments to the global frame: rigid least-squares fit to the fixes, then eq. 38.

Implements Zhang, Milios and Gu, *General Concept of 3D SLAM*, sections 6.2-6.5: each segment's
B-spline gives its local position ``X'_v(k)`` at every fix time ``t_b,k`` inside the segment (6.2); a
rigid transform ``(R_k, T_k)`` from the local frame to the fixes' frame is fitted by least squares over
those pairs (6.3), weighted by the inverse of each pair's total variance; the segment's landmarks and
path are then mapped by ``L^g = R_k L^l + T_k`` (eq. 38) and integrated into one map and path (6.4, 6.5).

Section 6.3 asks for more than three pairs not on a line. Fewer than three pairs, or pairs whose local
positions lie within ``min_spread`` metres (RMS) of a line, leave the rotation about that line
undetermined: the segment is refused with an :class:`EstimatorError` naming it, and the caller leaves
it out.

The transform's own uncertainty, first order: with ``n`` pairs of mean fix covariance ``P_b`` and local
offsets ``r_i`` from their centroid, a point ``x`` mapped by the fit has covariance about
``P_b (1/n + |x - centroid|^2 / sum |r_i|^2)`` (the centroid's error plus the rotation's lever arm); ``P_b``
is inflated to the fit's residual variance when the residuals are larger than the fixes claim.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.errors import EstimatorError
from relpoint.fusion.bspline import PathSpline
from relpoint.geometry import FloatArray, apply_transform, fit_rigid_on_axes, fitted_parameters, measured_basis


@dataclass(frozen=True, eq=False)
class SegmentTransform:
    """``T_world_local`` of one segment and what its uncertainty model needs.

    Attributes
    ----------
    rotation: (3, 3) ``R_k``.
    translation: (3,) ``T_k``, metres.
    rms: weighted RMS residual of the fit, metres.
    pairs: number of (spline position, fix) pairs used.
    centroid: (3,) centroid of the local pair positions, metres (local frame).
    spread: ``sum |r_i|^2`` of the local pair positions about their centroid, m².
    pair_covariance: (3, 3) per-pair covariance of the fit (mean fix covariance, inflated to the
        residuals), m².
    """

    rotation: FloatArray
    translation: FloatArray
    rms: float
    pairs: int
    centroid: FloatArray
    spread: float
    pair_covariance: FloatArray

    @property
    def matrix(self) -> FloatArray:
        """``T_world_local`` (4, 4)."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.translation
        return T

    def apply(self, points_local: npt.ArrayLike) -> FloatArray:
        """Eq. 38: ``R_k L + T_k`` for points (N, 3) in the local frame -> (N, 3) in ``world``."""
        return apply_transform(self.matrix, np.asarray(points_local, dtype=np.float64).reshape(-1, 3))

    def point_covariance(self, points_local: npt.ArrayLike) -> FloatArray:
        """Covariance (N, 3, 3) of mapped points due to the transform's uncertainty, m² (module docstring)."""
        points = np.asarray(points_local, dtype=np.float64).reshape(-1, 3)
        lever = np.sum((points - self.centroid) ** 2, axis=1) / self.spread
        return (1.0 / self.pairs + lever)[:, None, None] * self.pair_covariance


def fit_segment(
    spline: PathSpline,
    fix_stamps_ns: npt.ArrayLike,
    fix_positions: npt.ArrayLike,
    fix_covariances: npt.ArrayLike,
    *,
    name: str = "segment",
    min_pairs: int = 3,
    min_spread: float = 1.0,
) -> SegmentTransform:
    """Fit ``T_world_local`` of one segment to the fixes inside its time span (sections 6.2-6.3).

    Parameters
    ----------
    spline:
        The segment's local path (:class:`PathSpline`).
    fix_stamps_ns, fix_positions, fix_covariances:
        (M,), (M, 3) metres and (M, 3, 3) m²: every fix; those within the spline's span are used.
    name:
        How the segment is named in errors.
    min_pairs:
        Fewest pairs accepted (at least 3).
    min_spread:
        Smallest RMS distance of the local pair positions from their best-fitting line, metres.

    Raises
    ------
    EstimatorError
        Too few pairs, or pairs (nearly) on a line: the rotation is undetermined.
    """
    stamps = np.asarray(fix_stamps_ns, dtype=np.int64).reshape(-1)
    inside = spline.contains(stamps)
    n = int(np.count_nonzero(inside))
    if n < max(3, min_pairs):
        raise EstimatorError(
            f"{name} has {n} position fix(es) in its time span, fewer than {max(3, min_pairs)}",
            "it is left out of the global map; fixes at a higher rate or longer segments would place it",
        )
    targets = np.asarray(fix_positions, dtype=np.float64).reshape(-1, 3)[inside]
    target_cov = np.asarray(fix_covariances, dtype=np.float64).reshape(-1, 3, 3)[inside]
    local = spline(stamps[inside])
    local_cov = spline.covariance(stamps[inside])
    centroid = local.mean(axis=0)
    singular = np.linalg.svd(local - centroid, compute_uv=False)
    off_line = float(np.sqrt(np.sum(singular[1:] ** 2) / n))
    if off_line < min_spread:
        raise EstimatorError(
            f"{name}: its {n} fix pairs lie within {off_line:.3g} m (RMS) of a straight line, "
            f"below the {min_spread:g} m needed to fix the rotation to the global frame",
            "it is left out of the global map (collinear fixes leave the rotation about the line undetermined)",
        )
    # The axes the fixes measure (a horizontal fix's altitude is a placeholder: relpoint.geometry.measured_basis)
    basis = measured_basis(target_cov)
    measured = basis.shape[1]
    variances = np.trace(np.einsum("ai,nab,bj->nij", basis, target_cov + local_cov, basis), axis1=1, axis2=2) / measured
    weights = 1.0 / np.maximum(variances, 1e-12)
    fit = fit_rigid_on_axes(local, targets, weights, basis)
    projector = basis @ basis.T
    mean_cov = projector @ (target_cov.mean(axis=0) + local_cov.mean(axis=0)) @ projector
    # Residual variance per measured axis, with the fitted parameters' degrees of freedom taken out.
    dof = max(measured * n - fitted_parameters(basis).shape[1], 1)
    residual_var = fit.rms**2 * n / dof
    scale = max(1.0, residual_var / max(np.trace(mean_cov) / measured, 1e-12))
    return SegmentTransform(
        rotation=fit.rotation,
        translation=fit.translation,
        rms=fit.rms,
        pairs=n,
        centroid=centroid,
        spread=float(np.sum((local - centroid) ** 2)),
        pair_covariance=mean_cov * scale,
    )
