"""SO(3): rotations as matrices, quaternions and rotation vectors; the filters' right-perturbation
calculus (``R_true = R Exp(dtheta)``, ``dtheta`` in the sensor frame).

Conventions (see ``docs/log-format.md``): a pose ``T_a_b`` is a 4x4 homogeneous matrix that maps
coordinates in frame ``b`` to frame ``a`` (``p_a = T_a_b @ p_b``); quaternions are ``(x, y, z, w)``;
metres and radians throughout. Batched conversions go through :class:`scipy.spatial.transform.Rotation`;
:func:`quaternion_xyzw` is the fast variant for one matrix in a per-iteration loop.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def skew(vectors: npt.ArrayLike) -> FloatArray:
    """Cross-product matrices ``[v]x`` of vectors (..., 3) -> (..., 3, 3), so ``[v]x @ u = v x u``."""
    v = np.asarray(vectors, dtype=np.float64)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def so3_exp(rotvecs: npt.ArrayLike) -> FloatArray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) in radians."""
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

    v = np.asarray(rotvecs, dtype=np.float64)
    return Rotation.from_rotvec(v.reshape(-1, 3)).as_matrix().reshape(*v.shape[:-1], 3, 3)


def so3_right_jacobian(rotvecs: npt.ArrayLike) -> FloatArray:
    """Right Jacobians (..., 3, 3) of SO(3): ``Exp(phi + d) ~= Exp(phi) Exp(Jr(phi) d)`` for small ``d``."""
    phi = np.asarray(rotvecs, dtype=np.float64)
    theta = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe**2)
    b = np.where(small, 1.0 / 6.0, (safe - np.sin(safe)) / safe**3)
    return np.eye(3) - a * K + b * (K @ K)


def quat_to_matrix(quats_xyzw: npt.ArrayLike) -> FloatArray:
    """Rotation matrices (N, 3, 3) of unit quaternions (N, 4) ``(x, y, z, w)``; (0, 3, 3) for none."""
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

    quats = np.asarray(quats_xyzw, dtype=np.float64)
    if len(quats) == 0:
        return np.zeros((0, 3, 3))
    return Rotation.from_quat(quats).as_matrix()


def quaternion_xyzw(R: FloatArray) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)``, ``w >= 0``, of one rotation matrix (3, 3) (Shepperd's method).

    The fast variant of ``Rotation.from_matrix(R).as_quat(canonical=True)``, which costs about 0.1 ms
    per call (5 % of Relative Point's per-iteration budget at 100 points); the tests check the two agree.
    """
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = R.tolist()
    trace = m00 + m11 + m22
    if trace > 0.0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = ((m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s)
    elif m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        q = (0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s)
    elif m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        q = ((m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
        q = ((m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s)
    qx, qy, qz, qw = q
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    sign = -1.0 if qw < 0.0 else 1.0
    return sign * qx / norm, sign * qy / norm, sign * qz / norm, sign * qw / norm


def smallest_rotation(u: FloatArray, v: FloatArray) -> FloatArray:
    """The rotation (3, 3) of least angle taking direction ``u`` onto direction ``v``."""
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

    u = u / np.linalg.norm(u)
    v = v / np.linalg.norm(v)
    axis = np.cross(u, v)
    sin, cos = np.linalg.norm(axis), float(u @ v)
    if sin < 1e-12:
        if cos > 0:
            return np.eye(3)
        # Opposite: half a turn about any axis perpendicular to u.
        other = np.eye(3)[int(np.argmin(np.abs(u)))]
        axis = np.cross(u, other)
        return Rotation.from_rotvec(np.pi * axis / np.linalg.norm(axis)).as_matrix()
    return Rotation.from_rotvec(axis / sin * np.arctan2(sin, cos)).as_matrix()
