"""SO(3): rotations as matrices, quaternions and rotation vectors; the filters' right-perturbation
calculus (``R_true = R Exp(dtheta)``, ``dtheta`` in the sensor frame).

Conventions (see ``docs/log-format.md``): a pose ``T_a_b`` is a 4x4 homogeneous matrix that maps
coordinates in frame ``b`` to frame ``a`` (``p_a = T_a_b @ p_b``); quaternions are ``(x, y, z, w)``;
metres and radians throughout. The batched conversions a filter run and its evaluation need
(:func:`so3_exp`, :func:`so3_log`, :func:`matrix_to_quat`, :func:`quat_to_matrix`) follow
:class:`scipy.spatial.transform.Rotation`'s steps bit for bit without importing scipy (a fifth of a
second of start-up in every batch worker; the tests compare them with it); the others use it.
:func:`quaternion_xyzw` is the fast variant for one matrix in a per-iteration loop.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

_ATAN2 = np.frompyfunc(math.atan2, 2, 1)


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
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) in radians.

    ``Rotation.from_rotvec(v).as_matrix()``'s steps, bit for bit (the tests check it): the unit
    quaternion ``(sin(θ/2) v/θ, cos(θ/2))``, with a Taylor series of ``sin(θ/2)/θ`` below 1 mrad,
    then its matrix. Computed here because the filters call it every iteration and scipy costs
    start-up time.
    """
    v = np.asarray(rotvecs, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    small = angle <= 1e-3
    angle2 = angle**2
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(small, 0.5 - angle2 / 48 + angle2**2 / 3840, np.sin(angle / 2) / angle)
    return _quat_matrices(np.concatenate([v * scale, np.cos(angle / 2)], axis=-1))


def _quat_matrices(quats_xyzw: FloatArray) -> FloatArray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4), by ``Rotation.as_matrix``'s formula."""
    x, y, z, w = np.moveaxis(quats_xyzw, -1, 0)
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    elements = [
        x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw),
        2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw),
        2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2,
    ]  # fmt: skip
    return np.stack(elements, axis=-1).reshape(*quats_xyzw.shape[:-1], 3, 3)


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
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) ``(x, y, z, w)``, normalised first; (0, 3, 3) for none.

    ``Rotation.from_quat(q).as_matrix()``'s steps, bit for bit (the tests check it); raises
    ``ValueError`` for a zero quaternion.
    """
    quats = np.asarray(quats_xyzw, dtype=np.float64)
    if quats.shape[-1:] != (4,):
        raise ValueError(f"quaternions must have shape (..., 4), got {quats.shape}")
    norms = np.linalg.norm(quats, axis=-1, keepdims=True)
    if np.any(norms == 0):
        raise ValueError("Found zero norm quaternions in `quat`.")
    return _quat_matrices(quats / norms)


def matrix_to_quat(rotations: npt.ArrayLike) -> FloatArray:
    """Unit quaternions (N, 4) ``(x, y, z, w)``, ``w >= 0``, of rotation matrices (N, 3, 3).

    scipy's ``Rotation.from_matrix`` (``as_quat(canonical=True)``) step by step: a matrix that is not
    orthogonal to 1e-12 is first replaced by the nearest rotation (``U V^T`` of its SVD); then the
    largest of the diagonal and the trace picks the formula (Markley's method), the quaternion is
    normalised and its sign made canonical.
    """
    R = np.array(rotations, dtype=np.float64)
    if len(R) == 0:
        return np.zeros((0, 4))
    if np.any(np.linalg.det(R) <= 0):
        raise ValueError("a rotation matrix has a non-positive determinant")
    gramians = R @ np.swapaxes(R, -1, -2)
    orthogonal = np.all(np.isclose(gramians, np.eye(3), atol=1e-12), axis=(-2, -1))
    if not np.all(orthogonal):
        U, _, Vt = np.linalg.svd(R[~orthogonal], full_matrices=False)
        R[~orthogonal] = U @ Vt
    trace = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    choice = np.argmax(np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], trace], axis=-1), axis=-1)
    quats = np.empty((len(R), 4))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        rows = choice == i
        m = R[rows]
        quats[rows, i] = 1 - trace[rows] + 2 * m[:, i, i]
        quats[rows, j] = m[:, j, i] + m[:, i, j]
        quats[rows, k] = m[:, k, i] + m[:, i, k]
        quats[rows, 3] = m[:, k, j] - m[:, j, k]
    rows = choice == 3
    m = R[rows]
    quats[rows, 0] = m[:, 2, 1] - m[:, 1, 2]
    quats[rows, 1] = m[:, 0, 2] - m[:, 2, 0]
    quats[rows, 2] = m[:, 1, 0] - m[:, 0, 1]
    quats[rows, 3] = 1 + trace[rows]
    quats /= np.linalg.norm(quats, axis=-1, keepdims=True)
    x, y, z, w = quats.T
    flip = (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
    quats[flip] *= -1.0
    return quats


def so3_log(rotations: npt.ArrayLike) -> FloatArray:
    """Rotation vectors (N, 3) in radians of rotation matrices (N, 3, 3).

    ``Rotation.from_matrix(R).as_rotvec()``'s steps, bit for bit (the tests check it): the
    quaternion of :func:`matrix_to_quat`, its angle ``2 atan2(|xyz|, w)`` and its vector part scaled by
    ``angle / sin(angle / 2)`` (a Taylor series below 1 mrad).
    """
    quats = matrix_to_quat(rotations)
    x, y, z, w = quats.T
    # The C library's atan2, as scipy's: numpy's vectorised one can differ in the last bit.
    angle = 2 * _ATAN2(np.sqrt(x * x + y * y + z * z), w).astype(np.float64)[:, None]
    small = angle <= 1e-3
    angle2 = angle**2
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(small, 2 + angle2 / 12 + 7 * angle2**2 / 2880, angle / np.sin(angle / 2.0))
    return scale * quats[:, :3]


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
    norm = math.sqrt(sum(c * c for c in q))
    sign = -1.0 if q[3] < 0.0 else 1.0
    x, y, z, w = (sign * c / norm for c in q)
    return x, y, z, w


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
