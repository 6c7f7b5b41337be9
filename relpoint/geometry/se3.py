"""SE(3): poses as 4x4 matrices, their inverses, point transforms and body twists.

Conventions (see ``docs/log-format.md``): a pose ``T_a_b`` is a 4x4 homogeneous matrix that maps
coordinates in frame ``b`` to frame ``a`` (``p_a = T_a_b @ p_b``); quaternions are ``(x, y, z, w)``;
metres and radians throughout.

The checked functions (:func:`transform_points`, :func:`invert_pose`) take any array-like; the fast
variants skip the checks for the per-iteration loops: :func:`apply_transform` (float64 points (N, 3)),
:func:`rigid_inverse` (one 4x4), :func:`transform_soa32` (float32 points stored column-wise).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from relpoint.geometry.so3 import FloatArray, skew, so3_exp, so3_right_jacobian

F32 = npt.NDArray[np.float32]


def check_points(points: npt.ArrayLike, name: str = "points") -> FloatArray:
    """Return ``points`` as a float64 array of shape (N, 3), or raise ``ValueError`` naming the shape."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {array.shape}")
    return array


def pose_matrix(position: npt.ArrayLike, quat_xyzw: npt.ArrayLike) -> FloatArray:
    """4x4 pose from a position (3,) and a quaternion (x, y, z, w); also batched: (N,3),(N,4) -> (N,4,4)."""
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time
    position = np.asarray(position, dtype=np.float64)
    quat = np.asarray(quat_xyzw, dtype=np.float64)
    batch_shape = position.shape[:-1]
    matrices = np.zeros((*batch_shape, 4, 4))
    matrices[..., :3, :3] = Rotation.from_quat(quat.reshape(-1, 4)).as_matrix().reshape(*batch_shape, 3, 3)
    matrices[..., :3, 3] = position
    matrices[..., 3, 3] = 1.0
    return matrices


def homogeneous(rotations: npt.ArrayLike, positions: npt.ArrayLike) -> FloatArray:
    """Poses (N, 4, 4) from rotation matrices (N, 3, 3) and positions (N, 3)."""
    positions = np.asarray(positions, dtype=np.float64)
    T = np.zeros((len(positions), 4, 4))
    T[:, :3, :3] = rotations
    T[:, :3, 3] = positions
    T[:, 3, 3] = 1.0
    return T


def matrix_to_position_quat(T: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Split a pose (4,4) or poses (N,4,4) into positions (…,3) and quaternions (…,4), ``w >= 0``."""
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time
    T = np.asarray(T, dtype=np.float64)
    batch_shape = T.shape[:-2]
    quat = Rotation.from_matrix(T[..., :3, :3].reshape(-1, 3, 3)).as_quat(canonical=True)
    return T[..., :3, 3].copy(), quat.reshape(*batch_shape, 4)


def invert_pose(T_a_b: npt.ArrayLike) -> FloatArray:
    """Inverse of a rigid transform (4,4) or a batch (N,4,4): returns ``T_b_a``."""
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    R_T = np.swapaxes(T_a_b[..., :3, :3], -1, -2)
    T_b_a = np.zeros_like(T_a_b)
    T_b_a[..., :3, :3] = R_T
    T_b_a[..., :3, 3] = -np.einsum("...ij,...j->...i", R_T, T_a_b[..., :3, 3])
    T_b_a[..., 3, 3] = 1.0
    return T_b_a


def rigid_inverse(T: FloatArray) -> FloatArray:
    """Inverse of one rigid 4x4 transform (the fast variant of :func:`invert_pose` for a single pose)."""
    inverse = np.empty((4, 4))
    inverse[:3, :3] = T[:3, :3].T
    inverse[:3, 3] = -(T[:3, :3].T @ T[:3, 3])
    inverse[3] = (0.0, 0.0, 0.0, 1.0)
    return inverse


def transform_points(T_a_b: npt.ArrayLike, points_b: npt.ArrayLike) -> FloatArray:
    """Map points (N,3) given in frame ``b`` into frame ``a`` with the pose ``T_a_b`` (4,4)."""
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    points_b = check_points(points_b, "points_b")
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def apply_transform(T: npt.ArrayLike, points: FloatArray) -> FloatArray:
    """Map float64 points (N, 3) with a 4x4 transform (the unchecked variant of :func:`transform_points`)."""
    T = np.asarray(T)
    return points @ T[:3, :3].T + T[:3, 3]


def transform_soa32(T: FloatArray, points: F32) -> F32:
    """Apply a 4x4 transform to float32 points stored column-wise (3, N); returns (3, N) float32
    (the dense estimator's fast variant)."""
    R = T[:3, :3].astype(np.float32)
    t = T[:3, 3].astype(np.float32)[:, None]
    if points.shape[1] > 50_000:  # float32 GEMM with an inner dimension of 3 is slow on large inputs
        return np.einsum("ij,jn->in", R, points) + t
    return R @ points + t


def body_twist(T_world_a: npt.ArrayLike, T_world_b: npt.ArrayLike, dt: float) -> tuple[FloatArray, FloatArray]:
    """Constant body-frame velocities that carry pose ``a`` to pose ``b`` in ``dt`` seconds.

    The model is the one :func:`integrate_twist` inverts: ``p_b = p_a + R_a v dt`` and
    ``R_b = R_a exp([w] dt)``, with ``v`` (m/s) and ``w`` (rad/s) expressed in frame ``a``.
    Also batched: poses (N, 4, 4) give velocities (N, 3).
    """
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time
    T_world_a = np.asarray(T_world_a, dtype=np.float64)
    T_world_b = np.asarray(T_world_b, dtype=np.float64)
    R_a_T = np.swapaxes(T_world_a[..., :3, :3], -1, -2)
    linear = np.einsum("...ij,...j->...i", R_a_T, T_world_b[..., :3, 3] - T_world_a[..., :3, 3]) / dt
    relative = R_a_T @ T_world_b[..., :3, :3]
    angular = Rotation.from_matrix(relative.reshape(-1, 3, 3)).as_rotvec().reshape(linear.shape) / dt
    return linear, angular


def integrate_twist(T_world_a: npt.ArrayLike, linear: npt.ArrayLike, angular: npt.ArrayLike, dt: float) -> FloatArray:
    """Pose after applying body-frame velocities ``linear`` (m/s) and ``angular`` (rad/s) for ``dt`` s."""
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time
    T_world_a = np.asarray(T_world_a, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = T_world_a[:3, :3] @ Rotation.from_rotvec(np.asarray(angular) * dt).as_matrix()
    T[:3, 3] = T_world_a[:3, 3] + T_world_a[:3, :3] @ np.asarray(linear) * dt
    return T


def twist_step(
    positions: FloatArray, rotations: FloatArray, linear: FloatArray, angular: FloatArray, dt: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Hold a body-frame twist for ``dt`` seconds (the process model, *3D SLAM* eq. 5-7), batched.

    ``p' = p + R v dt`` and ``R' = R Exp(w dt)``, as :func:`relpoint.geometry.integrate_twist`.

    Parameters
    ----------
    positions: (..., 3) sensor positions in ``world``, metres.
    rotations: (..., 3, 3) ``R_world_sensor``.
    linear, angular: (..., 3) body-frame velocities, m/s and rad/s.
    dt: seconds.

    Returns
    -------
    positions', rotations':
        The propagated pose.
    F_pose: (..., 6, 6)
        Jacobian of the new pose error ``(dp, dtheta)`` with respect to the old one.
    G_twist: (..., 6, 6)
        Jacobian of the new pose error with respect to an error in the twist ``(dv, dw)``.
    """
    step_v = linear * dt
    step_w = angular * dt
    new_positions = positions + np.einsum("...ij,...j->...i", rotations, step_v)
    increment = so3_exp(step_w)
    new_rotations = rotations @ increment
    batch = positions.shape[:-1]
    F_pose = np.zeros((*batch, 6, 6))
    F_pose[..., :3, :3] = np.eye(3)
    F_pose[..., :3, 3:] = -rotations @ skew(step_v)
    F_pose[..., 3:, 3:] = np.swapaxes(increment, -1, -2)
    G_twist = np.zeros((*batch, 6, 6))
    G_twist[..., :3, :3] = rotations * dt
    G_twist[..., 3:, 3:] = so3_right_jacobian(step_w) * dt
    return new_positions, new_rotations, F_pose, G_twist
