"""Rigid-body geometry over numpy arrays: poses, point transforms and least-squares rigid fitting.

Conventions (see ``docs/log-format.md``): a pose ``T_a_b`` is a 4x4 homogeneous matrix that maps
coordinates in frame ``b`` to frame ``a`` (``p_a = T_a_b @ p_b``); quaternions are ``(x, y, z, w)``;
metres and radians throughout. Rotations go through :class:`scipy.spatial.transform.Rotation`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


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


def transform_points(T_a_b: npt.ArrayLike, points_b: npt.ArrayLike) -> FloatArray:
    """Map points (N,3) given in frame ``b`` into frame ``a`` with the pose ``T_a_b`` (4,4)."""
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    points_b = check_points(points_b, "points_b")
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


class RigidFit(NamedTuple):
    """Result of :func:`fit_rigid`: ``target ≈ scale * rotation @ source + translation``."""

    rotation: FloatArray
    translation: FloatArray
    scale: float
    rms: float

    def as_matrix(self) -> FloatArray:
        """The fit as a 4x4 similarity matrix (scale folded into the upper-left block)."""
        T = np.eye(4)
        T[:3, :3] = self.scale * self.rotation
        T[:3, 3] = self.translation
        return T


def fit_rigid(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    *,
    with_scale: bool = False,
    weights: npt.ArrayLike | None = None,
) -> RigidFit:
    """Least-squares rigid (or similarity) transform taking ``source`` points onto ``target`` points.

    Umeyama (1991) / Arun et al. (1987): SVD of the cross-covariance, with the reflection case
    handled by flipping the sign of the smallest singular direction, so the result is always a proper
    rotation (det = +1).

    Parameters
    ----------
    source, target:
        Corresponding points, shape (N, 3), N >= 3 for a unique rotation.
    with_scale:
        Also estimate a uniform scale (Sim(3)); otherwise the scale is 1 (SE(3)).
    weights:
        Optional non-negative per-pair weights, shape (N,).

    Raises
    ------
    ValueError
        If the shapes differ or fewer than one pair is given.
    """
    source = check_points(source, "source")
    target = check_points(target, "target")
    if source.shape != target.shape or len(source) == 0:
        raise ValueError(f"source {source.shape} and target {target.shape} must be equal, non-empty shapes")
    if weights is None:
        w = np.full(len(source), 1.0 / len(source))
    else:
        w = np.asarray(weights, dtype=np.float64)
        w = w / w.sum()
    mean_source = w @ source
    mean_target = w @ target
    src = source - mean_source
    tgt = target - mean_target
    covariance = (tgt * w[:, None]).T @ src
    U, singular, Vt = np.linalg.svd(covariance)
    reflection = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        reflection[2, 2] = -1.0
    rotation = U @ reflection @ Vt
    if with_scale:
        variance = float(w @ np.sum(src**2, axis=1))
        scale = float(np.sum(singular * np.diag(reflection)) / variance) if variance > 0 else 1.0
    else:
        scale = 1.0
    translation = mean_target - scale * rotation @ mean_source
    residual = target - (scale * source @ rotation.T + translation)
    rms = float(np.sqrt(w @ np.sum(residual**2, axis=1)))
    return RigidFit(rotation, translation, scale, rms)


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


def rigid_consensus(
    source: npt.ArrayLike, target: npt.ArrayLike, tolerance: float | npt.ArrayLike, samples: int = 64, seed: int = 0
) -> npt.NDArray[np.bool_]:
    """Pairs ``source[i] <-> target[i]`` (N, 3) that one rigid motion explains within ``tolerance`` (m).

    RANSAC over three-pair samples (``samples`` draws from ``seed``; all fitted at once with a batched
    SVD) keeps the motion with the most pairs within ``tolerance`` (a scalar or (N,)); it is refitted to
    them and the pairs within ``tolerance`` of the refitted motion are returned. With fewer than six
    pairs every pair is kept: too few to outvote.
    """
    source = check_points(source, "source")
    target = check_points(target, "target")
    n = len(source)
    if n < 6:
        return np.ones(n, dtype=bool)
    tolerance = np.broadcast_to(np.asarray(tolerance, dtype=np.float64), (n,))
    rng = np.random.default_rng(seed)
    picks = np.stack([rng.choice(n, 3, replace=False) for _ in range(samples)])  # (S, 3)
    a, b = source[picks], target[picks]  # (S, 3, 3)
    ca, cb = a.mean(axis=1, keepdims=True), b.mean(axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(np.einsum("sni,snj->sij", a - ca, b - cb))
    flip = np.linalg.det(np.einsum("sji,skj->sik", Vt, U)) < 0  # det(V U^T)
    Vt[flip, 2] *= -1.0
    R = np.einsum("sji,skj->sik", Vt, U)  # V U^T: takes source onto target
    t = cb[:, 0] - np.einsum("sij,sj->si", R, ca[:, 0])
    residual = np.linalg.norm(np.einsum("sij,nj->sni", R, source) + t[:, None] - target[None], axis=2)
    best = int(np.argmax((residual <= tolerance).sum(axis=1)))
    inliers = residual[best] <= tolerance
    if inliers.sum() < 3:
        return np.ones(n, dtype=bool)
    fit = fit_rigid(source[inliers], target[inliers])
    return np.linalg.norm(source @ fit.rotation.T + fit.translation - target, axis=1) <= tolerance


# -- SO(3) of the filters' motion models (right-perturbation error state: ``R_true = R Exp(dtheta)``,
# ``dtheta`` in the sensor frame) -----------------------------------------------------------------

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
