"""A segment's local path as a cubic B-spline over time, with its covariance.

Implements Zhang, Milios and Gu, *General Concept of 3D SLAM*, section 6.1 (eq. 33-37): the local path
``p_v(i)`` (``i = 0..n``, at times ``t_i``) becomes a clamped cubic B-spline ``S(u) = sum_i c_i N_{i,3}(u)``
with ``u = (t - t_0) / (t_n - t_0)`` (eq. 34) and the basis of eq. 35-36 (scipy's ``BSpline``, 0/0 = 0).
The section asks for a curve that "smoothly passes all the discrete position points" (B-spline
interpolation, Piegl and Tiller): the control points ``c`` are solved so that ``S(u_i) = p_v(i)``, with
scipy's not-a-knot knots (simple interior knots, so the curve is C2). Taking the positions themselves
as control points, as eq. 33 is printed, would lag the path by up to a third of a step near the ends.

Covariance: eq. 37 as printed sums the positions ``p_v(i)`` where it means the covariances ``P_vv(i)``.
Since ``S(u)`` is linear in the positions, ``S(u) = sum_i L_i(u) p_v(i)`` with the cardinal functions
``L(u) = N(u) A^-1`` (``A`` the collocation matrix ``N_{j,3}(u_i)``), and for independent positions the
intended sum is ``P_vv(u) = sum_i L_i(u)^2 P_vv(i)``: eq. 37 with the interpolating basis in place of
``N_{i,3}`` (the two coincide when the control points are the positions).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.interpolate import BSpline, make_interp_spline
from scipy.sparse.linalg import splu

from relpoint.errors import EstimatorError
from relpoint.geometry import FloatArray

DEGREE = 3


@dataclass(frozen=True, eq=False)
class PathSpline:
    """Cubic B-spline of a local path over time (eq. 33-34) and its covariance (eq. 37, intended form).

    Attributes
    ----------
    t0_ns, tn_ns:
        First and last stamps of the path, integer nanoseconds.
    spline:
        scipy ``BSpline`` over ``u`` in [0, 1] interpolating the positions (n+1, 3), metres.
    parameters:
        (n+1,) ``u_i`` of the positions.
    position_covariances:
        (n+1, 3, 3) covariances ``P_vv(i)`` of the positions, m².
    """

    t0_ns: int
    tn_ns: int
    spline: BSpline
    parameters: FloatArray
    position_covariances: FloatArray

    @classmethod
    def fit(
        cls, stamps_ns: npt.ArrayLike, positions: npt.ArrayLike, covariances: npt.ArrayLike | None = None
    ) -> PathSpline:
        """Build the spline of positions (n+1, 3) at strictly increasing ``stamps_ns`` (n+1,), n+1 >= 4.

        ``covariances`` (n+1, 3, 3) default to zero.

        Raises
        ------
        EstimatorError
            Fewer than four positions, or stamps that do not strictly increase.
        """
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        points = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        if len(points) != len(stamps):
            raise ValueError(f"{len(stamps)} stamps for {len(points)} positions")
        if len(points) < DEGREE + 1:
            raise EstimatorError(f"a cubic B-spline needs at least {DEGREE + 1} positions, got {len(points)}")
        if np.any(np.diff(stamps) <= 0):
            raise EstimatorError("path stamps must strictly increase")
        if covariances is None:
            cov = np.zeros((len(points), 3, 3))
        else:
            cov = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
            if len(cov) != len(points):
                raise ValueError(f"{len(cov)} covariances for {len(points)} positions")
        t0, tn = int(stamps[0]), int(stamps[-1])
        u = (stamps - t0).astype(np.float64) / float(tn - t0)
        spline = make_interp_spline(u, points, k=DEGREE)
        return cls(t0, tn, spline, u, cov)

    def parameter(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        """Eq. 34: ``u = (t - t_0) / (t_n - t_0)`` for stamps (N,), clipped to [0, 1]."""
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        u = (stamps - self.t0_ns).astype(np.float64) / float(self.tn_ns - self.t0_ns)
        return np.clip(u, 0.0, 1.0)

    def contains(self, stamps_ns: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Mask of the stamps inside ``[t_0, t_n]``."""
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        return (stamps >= self.t0_ns) & (stamps <= self.tn_ns)

    def __call__(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        """Eq. 33: positions (N, 3) on the path at ``stamps_ns`` (N,), metres (clamped to the path's span)."""
        return np.asarray(self.spline(self.parameter(stamps_ns)), dtype=np.float64).reshape(-1, 3)

    def basis(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        """B-spline basis values ``N_{i,3}(u)`` (N, n+1) at ``stamps_ns`` (eq. 35-36)."""
        return np.asarray(BSpline.design_matrix(self.parameter(stamps_ns), self.spline.t, DEGREE).toarray())

    def cardinal_weights(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        """Weights ``L_i(u)`` (N, n+1) with ``S(u) = sum_i L_i(u) p_v(i)``: ``N(u) A^-1``."""
        collocation = BSpline.design_matrix(self.parameters, self.spline.t, DEGREE).tocsc()
        # L = N A^-1  <=>  A^T L^T = N^T; A is banded and sparse, so one LU serves every query.
        return np.asarray(splu(collocation.T.tocsc()).solve(self.basis(stamps_ns).T).T)

    def covariance(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        """Eq. 37 (intended): ``P_vv(u) = sum_i L_i(u)^2 P_vv(i)``, (N, 3, 3) m²."""
        weights = self.cardinal_weights(stamps_ns) ** 2
        return np.einsum("ni,iab->nab", weights, self.position_covariances)
