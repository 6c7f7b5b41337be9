"""Covariance-weighted fusion of two independent position estimates.

Implements Zhang, Milios and Gu, *General Concept of 3D SLAM*, section 5.2 (eq. 31-32): the local
estimate ``X_c`` (camera, here any relpoint estimator) and the synchronised fix ``X_b`` (buoys, GNSS),
both Gaussian with covariances ``P_c`` and ``P_b``, combine as

    X_v = P_b (P_b + P_c)^-1 X_c + P_c (P_b + P_c)^-1 X_b,    P_v = P_b (P_b + P_c)^-1 P_c,

the matrix form of the printed scalar ratios (they coincide for isotropic covariances). ``P_v`` is
below both inputs in the Loewner order, so every fused variance is below both input variances.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from relpoint.geometry import FloatArray


def fuse_estimates(
    x_c: npt.ArrayLike, P_c: npt.ArrayLike, x_b: npt.ArrayLike, P_b: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Fuse estimates ``(x_c, P_c)`` and ``(x_b, P_b)`` of the same position (eq. 31-32).

    Parameters
    ----------
    x_c, x_b:
        (3,) or (N, 3) positions, metres, in the same frame.
    P_c, P_b:
        (3, 3) or (N, 3, 3) covariances, m²; their sum must be invertible.

    Returns
    -------
    x_v, P_v:
        The fused positions (N, 3) or (3,) and covariances (N, 3, 3) or (3, 3), symmetric.
    """
    x_c = np.asarray(x_c, dtype=np.float64)
    x_b = np.asarray(x_b, dtype=np.float64)
    P_c = np.asarray(P_c, dtype=np.float64)
    P_b = np.asarray(P_b, dtype=np.float64)
    single = x_c.ndim == 1
    x_c, x_b = np.atleast_2d(x_c), np.atleast_2d(x_b)
    P_c = np.broadcast_to(P_c, (len(x_c), 3, 3))
    P_b = np.broadcast_to(P_b, (len(x_c), 3, 3))
    total = P_b + P_c
    # Gain K = P_c (P_b + P_c)^-1: x_v = x_c + K (x_b - x_c) equals eq. 31, P_v = P_c - K P_c equals eq. 32.
    gain = np.linalg.solve(total, P_c.transpose(0, 2, 1)).transpose(0, 2, 1)
    x_v = x_c + np.einsum("nab,nb->na", gain, x_b - x_c)
    P_v = P_c - gain @ P_c
    P_v = 0.5 * (P_v + P_v.transpose(0, 2, 1))
    return (x_v[0], P_v[0]) if single else (x_v, P_v)
