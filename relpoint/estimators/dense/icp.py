"""Projective data association and linearised point-to-plane ICP (sections 2.1-2.3 of the dense-SLAM paper).

The map is the *source* and the frame the *target* (section 4): map points ``p`` (world) are moved into
the camera by the current estimate ``T_camera_world`` (``p' = T p``), projected into the frame's depth
image, and paired with the frame vertex ``q`` and normal ``n_q`` found at that pixel when the pair passes
the validity conditions of section 2.1: ``0 <= u < W``, ``0 <= v < H``, ``d > 0``, ``|p' - q| < d_thr``,
and (as in KinectFusion) an angle between the normals below a threshold.

Each pair gives one linearised point-to-plane residual (section 2.2)

    r_i = n_q . (dR p' + dt - q) ~= A_i x - b_i,
    A_i = [ (p' x n_q)^T, n_q^T ],  b_i = n_q . (q - p'),  x = (alpha, beta, gamma, t_x, t_y, t_z),

using the small-angle rotation ``dR ~= I + [x_{0:3}]_x``. Section 2.3 solves the 6x6 normal equations
``A^T A x = A^T b``; the increment is re-orthonormalised to a rotation (SVD projection onto SO(3)) and
left-composed with the estimate. Iterations stop when the increment is below the convergence
thresholds, and run coarse-to-fine over the frame's pyramid. Optionally (beyond the paper) the normal
equations are weighted, ``A^T W A x = A^T W b``, by a Huber weight of each residual and by the inverse
variance of depth noise at the pair's depth (:func:`depth_sigma`), and the plane normal may be the map's.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.estimators.dense.maps import Level
from relpoint.geometry import FloatArray, transform_soa32

logger = logging.getLogger(__name__)

F32 = npt.NDArray[np.float32]


@dataclass(frozen=True)
class Correspondences:
    """Pairs found by projective association (arrays of the valid pairs only).

    Attributes
    ----------
    source: (N, 3) float32 map points moved into the camera frame (``p'``), metres.
    target: (N, 3) float32 frame vertices ``q``, camera frame, metres.
    normals: (N, 3) float32 frame normals ``n_q``, camera frame.
    index: (N,) int64 indices of the paired source points in the input arrays.
    pixels: (N,) int64 row-major pixel index of each pair in the target level.
    map_normals: (N, 3) float32 map normals rotated into the camera frame.
    """

    source: F32
    target: F32
    normals: F32
    index: npt.NDArray[np.int64]
    pixels: npt.NDArray[np.int64]
    map_normals: F32

    def __len__(self) -> int:
        return len(self.index)


def project(points_cam: F32, level: Level) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
    """Nearest pixel (row-major index) of camera-frame points (3, N) in ``level``, and whether it is inside.

    Points at or behind the camera (z <= 0) are outside; the pixel of a point outside is 0.
    """
    k = level.intrinsics
    x, y, z = points_cam
    inv = np.float32(1.0) / np.where(z > 1e-6, z, np.float32(-1.0))  # negative: fails the u >= 0 test below
    u = x * inv
    u *= np.float32(k.fx)
    u += np.float32(k.cx + 0.5)
    v = y * inv
    v *= np.float32(k.fy)
    v += np.float32(k.cy + 0.5)
    inside = (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height) & (z > 1e-6)
    # floor(c + 0.5) is the nearest pixel; u, v are non-negative inside, so truncation is floor.
    pixel = v.astype(np.int64)
    pixel *= k.width
    pixel += u.astype(np.int64)
    pixel[~inside] = 0
    return pixel, inside


def associate(
    T_camera_world: FloatArray,
    points: F32,
    normals: F32,
    level: Level,
    distance_threshold: float,
    normal_cos_threshold: float,
) -> Correspondences:
    """Projective data association of map points with a frame level (section 2.1).

    Parameters
    ----------
    T_camera_world: (4, 4) current estimate of the camera pose's inverse.
    points: (3, N) float32 map points in ``world``.
    normals: (3, N) float32 map normals in ``world``.
    level: the frame's pyramid level (target).
    distance_threshold: largest ``|p' - q|`` of a pair, metres.
    normal_cos_threshold: smallest cosine of the angle between the map normal (rotated into the camera)
        and the frame normal; -1 disables the check.
    """
    p_cam = transform_soa32(T_camera_world, points)
    pixel, inside = project(p_cam, level)
    # Pixels outside the image point at pixel 0; the validity plane rejects them below.
    gathered = np.take(level.planes, pixel, axis=1)
    ok = inside & (gathered[6] > 0)
    q = gathered[:3]
    n_q = gathered[3:6]
    diff = p_cam - q
    ok &= (diff * diff).sum(axis=0) < np.float32(distance_threshold**2)
    n_p = T_camera_world[:3, :3].astype(np.float32) @ normals
    if normal_cos_threshold > -1.0:
        ok &= (n_p * n_q).sum(axis=0) > np.float32(normal_cos_threshold)
    idx = np.flatnonzero(ok)
    return Correspondences(
        np.take(p_cam, idx, axis=1).T,
        np.take(q, idx, axis=1).T,
        np.take(n_q, idx, axis=1).T,
        idx,
        pixel[idx],
        np.take(n_p, idx, axis=1).T,
    )


def linear_system(source: F32, target: F32, normals: F32) -> tuple[F32, F32]:
    """The stacked linearised residuals of section 2.2-2.3: ``A`` (N, 6) and ``b`` (N,), float32.

    ``A_i = [p'_i x n_i, n_i]`` and ``b_i = n_i . (q_i - p'_i)``, so ``A x = b`` in the least-squares
    sense gives the increment ``x = (alpha, beta, gamma, t_x, t_y, t_z)`` that moves ``p'`` onto the
    tangent planes of ``q``. ``A`` is returned as a transposed view of a (6, N) array.
    """
    px, py, pz = source.T
    nx, ny, nz = normals.T
    At = np.empty((6, len(source)), dtype=np.float32)
    At[0] = py * nz - pz * ny
    At[1] = pz * nx - px * nz
    At[2] = px * ny - py * nx
    At[3], At[4], At[5] = nx, ny, nz
    d = target.T - source.T
    b = nx * d[0] + ny * d[1] + nz * d[2]
    return At.T, b


def normal_equations(A: F32, b: F32, weights: F32 | None = None) -> tuple[FloatArray, FloatArray]:
    """``A^T W A`` (6, 6) and ``A^T W b`` (6,), float64 (``W`` = diag(weights), identity if None)."""
    At = A.T
    Aw = At if weights is None else At * weights
    return (Aw @ A).astype(np.float64), (Aw @ b).astype(np.float64)


DEGENERATE_SHARE = 2e-3
"""A direction of motion is unobserved when its information, with rotations measured at the scene's
distance, is below this share of the best-observed direction's. Measured on the 7-Scenes kitchen (640x480
and 320x240, every ICP iteration of 150 frames) the weakest direction holds at least 4.2e-3 of the
strongest; a view of one plane (1 mm noise) leaves three directions (the in-plane translations, the
rotation about the normal) at 1e-5 to 1.1e-3, filled only by the noise of the normals."""


@dataclass(frozen=True)
class Increment:
    """A solution of the normal equations: the increment ``x`` (6,) and how many of the six directions of
    motion the pairs left unobserved (their component of ``x`` is 0: the estimate keeps its start there)."""

    x: FloatArray
    unobserved: int


def solve_increment(AtA: FloatArray, Atb: FloatArray, degenerate_share: float = DEGENERATE_SHARE) -> Increment | None:
    """Solve the 6x6 normal equations along their well-observed directions only (degeneracy-aware ICP,
    Zhang, Kaess and Singh, ICRA 2016); ``None`` when no direction is observed.

    The rotation unknowns are radians and the translations metres, so eigenvalues of ``A^T A`` compare
    rotations with translations only once a rotation is measured as the displacement it causes at the
    scene's distance: the rotation rows and columns are scaled by ``1 / L`` with ``L^2`` the ratio of
    the traces of the rotation and translation blocks (the mean squared lever arm ``|p' x n|^2`` of
    the pairs). Eigen-directions with less than ``degenerate_share`` of the largest eigenvalue (a single
    plane: the translations within it and the rotation about its normal) get no increment, so the pose
    there stays at ICP's start (the prediction) instead of following the noise.
    """
    rotation, translation = float(np.trace(AtA[:3, :3])), float(np.trace(AtA[3:, 3:]))
    if not (rotation > 0 and translation > 0 and np.isfinite(rotation + translation)):
        return None
    scale = np.r_[np.full(3, math.sqrt(translation / rotation)), np.ones(3)]
    eigenvalues, vectors = np.linalg.eigh(AtA * np.outer(scale, scale))
    observed = eigenvalues > degenerate_share * eigenvalues[-1]
    if eigenvalues[-1] <= 0 or not observed.any():
        return None
    kept = vectors[:, observed]
    y = kept @ ((kept.T @ (Atb * scale)) / eigenvalues[observed])
    return Increment(y * scale, int((~observed).sum()))


def orthonormalise(M: FloatArray) -> FloatArray:
    """The rotation nearest to a 3x3 matrix (SVD projection onto SO(3))."""
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def increment_matrix(x: FloatArray) -> FloatArray:
    """The 4x4 transform of an increment ``x = (alpha, beta, gamma, t)``: small-angle ``I + [w]_x``, re-orthonormalised."""
    a, b, c = x[:3]
    T = np.eye(4)
    T[:3, :3] = orthonormalise(np.array([[1.0, -c, b], [c, 1.0, -a], [-b, a, 1.0]]))
    T[:3, 3] = x[3:]
    return T


@dataclass(frozen=True)
class IcpSettings:
    """Settings of :func:`track` (see :class:`relpoint.estimators.dense.DenseConfig` for their meaning)."""

    iterations: tuple[int, ...]
    distance_threshold: float
    normal_cos_threshold: float
    convergence_rotation: float
    convergence_translation: float
    min_correspondences: int
    huber_delta: float
    depth_weighting: bool = False
    map_normals: bool = False


@dataclass(frozen=True)
class TrackResult:
    """Outcome of :func:`track`: the estimate, whether it is trusted, and diagnostics."""

    T_camera_world: FloatArray
    ok: bool
    iterations: int
    correspondences: int
    rmse: float
    unobserved: int = 0
    """Directions of motion the finest level's pairs left unobserved (degenerate geometry, e.g. one plane)."""


def depth_sigma(z: F32) -> F32:
    """Axial depth noise of a Kinect-like sensor at depth ``z`` (metres): ``0.0012 + 0.0019 (z - 0.4)^2``.

    The noise model of Nguyen, Izadi and Lovell (3DIMPVT 2012), used to weight residuals by their inverse
    variance (relative to a point at 1 m).
    """
    d = z - np.float32(0.4)
    return np.float32(0.0012) + np.float32(0.0019) * d * d


SIGMA_1M = float(0.0012 + 0.0019 * 0.6**2)


def _huber_weights(residuals: F32, delta: float) -> F32 | None:
    if delta <= 0:
        return None
    a = np.abs(residuals)
    return np.minimum(np.float32(1.0), np.float32(delta) / np.maximum(a, np.float32(1e-12)))


def alignment_cost(
    T_camera_world: FloatArray, points: F32, normals: F32, level: Level, settings: IcpSettings
) -> tuple[int, float]:
    """How well a pose explains a frame level: the number of associated pairs and their mean squared
    point-to-plane residual (m^2; ``inf`` with fewer than ``settings.min_correspondences`` pairs)."""
    pairs = associate(
        T_camera_world, points, normals, level, settings.distance_threshold, settings.normal_cos_threshold
    )
    n = len(pairs)
    if n < settings.min_correspondences:
        return n, float("inf")
    _, b = linear_system(pairs.source, pairs.target, pairs.normals)
    return n, float(np.mean(np.square(b, dtype=np.float64)))


def track(
    source_levels: list[tuple[F32, F32]],
    pyramid: list[Level],
    T_init: FloatArray,
    settings: IcpSettings,
) -> TrackResult:
    """Coarse-to-fine point-to-plane ICP of map points (source) against a frame pyramid (target).

    Parameters
    ----------
    source_levels: per pyramid level, (3, N_l) world points and (3, N_l) world normals, float32.
    pyramid: the frame's levels, level 0 finest.
    T_init: (4, 4) initial ``T_camera_world``.
    settings: iteration counts per level (finest first), gates and convergence thresholds.
    """
    T = np.array(T_init, dtype=np.float64)
    total = 0
    last_n = 0
    last_rmse = float("nan")
    unobserved = 0
    ok = True
    for level_index in reversed(range(len(pyramid))):
        points, normals = source_levels[level_index]
        for _ in range(settings.iterations[level_index]):
            pairs = associate(
                T, points, normals, pyramid[level_index], settings.distance_threshold, settings.normal_cos_threshold
            )
            total += 1
            last_n = len(pairs)
            if last_n < settings.min_correspondences:
                logger.debug("level %d: only %d correspondences", level_index, last_n)
                ok = False
                break
            plane_normals = pairs.map_normals if settings.map_normals else pairs.normals
            A, b = linear_system(pairs.source, pairs.target, plane_normals)
            weights = _huber_weights(b, settings.huber_delta)
            if settings.depth_weighting:
                inverse_variance = (np.float32(SIGMA_1M) / depth_sigma(pairs.target[:, 2])) ** 2
                weights = inverse_variance if weights is None else weights * inverse_variance
            last_rmse = float(np.sqrt(np.mean(np.square(b, dtype=np.float64))))
            increment = solve_increment(*normal_equations(A, b, weights))
            if increment is None:
                logger.debug("level %d: singular normal equations", level_index)
                ok = False
                break
            x = increment.x
            unobserved = increment.unobserved
            T = increment_matrix(x) @ T
            if np.linalg.norm(x[:3]) < settings.convergence_rotation and (
                np.linalg.norm(x[3:]) < settings.convergence_translation
            ):
                break
        else:
            continue
        if not ok and level_index > 0:
            ok = True  # a coarse level may lack pairs; finer levels get another chance
    return TrackResult(T, ok, total, last_n, last_rmse, unobserved)
