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
from scipy.spatial.transform import Rotation

from relpoint.estimators.dense import _kernels
from relpoint.estimators.dense.maps import Level
from relpoint.geometry import FloatArray, invert_pose, transform_soa32

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


def associate(
    T_camera_world: FloatArray,
    points: F32,
    normals: F32,
    level: Level,
    distance_threshold: float,
    normal_cos_threshold: float,
) -> Correspondences:
    """Projective data association of map points with a frame level (section 2.1).

    Each map point, moved into the camera, is paired with the frame vertex at the pixel it projects to
    (the nearest pixel; points at or behind the camera, or outside the image, are not paired) when that
    pixel is valid and the pair passes the distance and normal gates (one compiled pass:
    :func:`_kernels.associate`).

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
    n_p = T_camera_world[:3, :3].astype(np.float32) @ normals
    k = level.intrinsics
    idx, pixels, source, target, target_normals, map_normals = _kernels.associate(
        np.ascontiguousarray(p_cam), np.ascontiguousarray(n_p), level.planes, float(k.fx), float(k.fy),
        k.cx + 0.5, k.cy + 0.5, int(k.width), int(k.height), float(distance_threshold**2),
        bool(normal_cos_threshold > -1.0), float(normal_cos_threshold),
    )  # fmt: skip
    return Correspondences(source.T, target.T, target_normals.T, idx, pixels, map_normals.T)


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
"""A direction of motion is weakly observed when its information, with rotations measured at the scene's
distance, is below this share of the best-observed direction's. A view of one plane (1 mm noise) leaves
three directions (the in-plane translations, the rotation about the normal) there, at 2e-6 to 1.8e-3,
filled only by the noise of the normals; but real directions of real scenes fall there too: under fast
motion (every 12th frame, 2.5 frames a second) the 7-Scenes kitchen's weakest direction holds 1.3e-3
after convergence at 640x480, and 5e-4 at the coarser levels. A weak direction is unobserved only when
the normals' noise could also explain its information (``NOISE_RATIO``). Each ICP iteration solves along
the directions this leaves observed; the pose's final verdict takes the wider ``UNOBSERVED_SHARE``."""

UNOBSERVED_SHARE = 1e-2
"""The share of :data:`DEGENERATE_SHARE` for the verdict once the finest level has converged: far, noisy
depth fills the unobserved directions more than a near plane does. A simulated corridor (walls, floor and
ceiling, its end beyond ``max_depth``, Kinect-like noise) leaves the translation along it at 3e-3 (1.1
times the normals' noise): at 2e-3, 135 of 200 frames followed the noise there, unwarned, and the run
recovered 1.2 of the 5.4 m driven; now 138 frames are counted and warned. The 7-Scenes kitchen frames
(every frame, every 8th and every 12th, 320x240 and 640x480) have none, as before; at 5e-2 the noise test
held two of its every-12th frames at 640x480 along a real direction (ATE 3.4 -> 6.4 cm). Used within the
iterations as well, it slowed convergence along real directions (a simulated room crossed at 1 m/s: 4.5
-> 17 cm RMS)."""

NOISE_RATIO = 1.25
"""A weakly observed direction is unobserved when its information is less than this many times what the
disagreement between the frame's and the map's normals at the pairs gives it: the information that the
noise of the normals alone would put there (``A^T W A`` with the rows of ``A`` the difference of the two
normals' rows). A plane's three directions hold 0.5 to 1.0 of it (rarely up to 3.9, where the frame's and
the map's normals share a bias), the kitchen's weakest at least 1.5. Judged by the share alone, 5 of 33
ordinary kitchen frames at 2.5 frames a second were held along a real direction (6.2 cm ATE instead of
2.7)."""

NUMERICAL_SHARE = 1e-9
"""Below this share of the strongest direction's information a direction carries no information at all
(rounding): the coarser levels, which do not judge degeneracy, solve along every direction above it."""


@dataclass(frozen=True)
class Increment:
    """A solution of the normal equations: the increment ``x`` (6,) and how many of the six directions of
    motion the pairs left unobserved (their component of ``x`` is 0: the estimate keeps its start there)."""

    x: FloatArray
    unobserved: int


@dataclass(frozen=True)
class Directions:
    """The eigen-directions of the normal equations with rotations measured at the scene's distance.

    ``scale`` (6,) multiplies the rotation unknowns into that measure (translations: 1); ``eigenvalues``
    (6,) ascending and ``vectors`` (6, 6) (columns) of the scaled ``A^T A``; ``observed`` (6,) the
    directions with at least the requested share of the largest eigenvalue."""

    scale: FloatArray
    eigenvalues: FloatArray
    vectors: FloatArray
    observed: npt.NDArray[np.bool_]

    def project(self, x: FloatArray) -> FloatArray:
        """The part of a motion ``x = (rotation vector, translation)`` (6,) along the observed directions."""
        kept = self.vectors[:, self.observed]
        return (kept @ (kept.T @ (x / self.scale))) * self.scale


def directions(
    AtA: FloatArray, degenerate_share: float = DEGENERATE_SHARE, noise: FloatArray | None = None
) -> Directions | None:
    """The scaled eigen-directions of ``AtA`` (6, 6) and which are observed; ``None`` when none is.

    The rotation unknowns are radians and the translations metres, so eigenvalues of ``A^T A`` compare
    rotations with translations only once a rotation is measured as the displacement it causes at the
    scene's distance: the rotation rows and columns are scaled by ``1 / L`` with ``L^2`` the ratio of
    the traces of the rotation and translation blocks (the mean squared lever arm ``|p' x n|^2`` of
    the pairs). Eigen-directions with less than ``degenerate_share`` of the largest eigenvalue (a single
    plane: the translations within it and the rotation about its normal) are unobserved, unless
    ``noise`` (6, 6), the information the noise of the normals alone gives each direction, is given and
    explains less than ``1 / NOISE_RATIO`` of theirs.
    """
    rotation, translation = float(np.trace(AtA[:3, :3])), float(np.trace(AtA[3:, 3:]))
    if not (rotation > 0 and translation > 0 and np.isfinite(rotation + translation)):
        return None
    scale = np.r_[np.full(3, math.sqrt(translation / rotation)), np.ones(3)]
    eigenvalues, vectors = np.linalg.eigh(AtA * np.outer(scale, scale))
    observed = eigenvalues > degenerate_share * eigenvalues[-1]
    if noise is not None:
        explained = np.einsum("ij,ik,kj->j", vectors, noise * np.outer(scale, scale), vectors)
        observed |= eigenvalues > NOISE_RATIO * explained
    if eigenvalues[-1] <= 0 or not observed.any():
        return None
    return Directions(scale, eigenvalues, vectors, observed)


def solve_increment(AtA: FloatArray, Atb: FloatArray, degenerate_share: float = DEGENERATE_SHARE) -> Increment | None:
    """Solve the 6x6 normal equations along their well-observed directions only (degeneracy-aware ICP,
    Zhang, Kaess and Singh, ICRA 2016; the directions as :func:`directions` finds them); ``None`` when no
    direction is observed. Unobserved directions (a single plane: the translations within it and the
    rotation about its normal) get no increment, so the pose there stays at ICP's start instead of
    following the noise.
    """
    found = directions(AtA, degenerate_share)
    if found is None:
        return None
    kept = found.vectors[:, found.observed]
    y = kept @ ((kept.T @ (Atb * found.scale)) / found.eigenvalues[found.observed])
    return Increment(y * found.scale, int((~found.observed).sum()))


def solve_within(AtA: FloatArray, Atb: FloatArray, within: Directions) -> FloatArray | None:
    """The least-squares increment (6,) of the normal equations restricted to ``within``'s observed
    directions (fixed, e.g. judged at an earlier iteration); ``None`` when they hold no information."""
    basis = within.vectors[:, within.observed] * within.scale[:, None]  # columns: motions
    reduced = basis.T @ AtA @ basis
    if not np.all(np.isfinite(reduced)) or np.linalg.eigvalsh(reduced)[0] <= 0:
        return None
    return basis @ np.linalg.solve(reduced, basis.T @ Atb)


def motion_vector(T: FloatArray) -> FloatArray:
    """``(rotation vector, translation)`` (6,) of a 4x4 transform, the unknowns' order of :func:`linear_system`."""
    return np.r_[Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]]


def motion_matrix(x: FloatArray) -> FloatArray:
    """The 4x4 transform of ``x = (rotation vector, translation)`` (6,); inverse of :func:`motion_vector`."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    T[:3, 3] = x[3:]
    return T


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
    rotation_iterations: int = 0
    huber_noise: tuple[float, float] | None = None
    """``(constant, quadratic)``: the Huber threshold at a pair's depth ``z`` is at least ``constant + quadratic
    z^2`` metres (from the depth noise measured from the frames; None: ``huber_delta`` alone)."""


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
    rotation_start: bool = False
    """ICP started from the rotation-only alignment (:func:`rotation_start`) rather than from ``T_init``."""
    pair_depths: F32 | None = None
    pair_residuals: F32 | None = None
    """The finest level's last pairs: their depths in the frame and point-to-plane residuals, metres."""


def depth_sigma(z: F32) -> F32:
    """Axial depth noise of a Kinect-like sensor at depth ``z`` (metres): ``0.0012 + 0.0019 (z - 0.4)^2``.

    The noise model of Nguyen, Izadi and Lovell (3DIMPVT 2012), used to weight residuals by their inverse
    variance (relative to a point at 1 m).
    """
    d = z - np.float32(0.4)
    return np.float32(0.0012) + np.float32(0.0019) * d * d


SIGMA_1M = float(0.0012 + 0.0019 * 0.6**2)


def _huber_weights(residuals: F32, settings: IcpSettings, depths: F32) -> F32 | None:
    """Huber weights of point-to-plane residuals (metres) of pairs at ``depths`` (metres): threshold
    ``huber_delta``, or the measured noise's where that is larger (``huber_noise``)."""
    if settings.huber_delta <= 0:
        return None
    a = np.abs(residuals)
    delta: float | F32 = np.float32(settings.huber_delta)
    if settings.huber_noise is not None:
        constant, quadratic = settings.huber_noise
        delta = np.maximum(delta, np.float32(constant) + np.float32(quadratic) * depths * depths)
    return np.minimum(np.float32(1.0), delta / np.maximum(a, np.float32(1e-12)))


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
    T_start = np.array(T_init, dtype=np.float64)
    T = T_start  # stays ICP's start for the verdict below: along unobserved directions the pose goes back to it
    total = 0
    rotated = False
    if settings.rotation_iterations:
        T_rotated, used = rotation_start(source_levels[-1], pyramid[-1], T_start, settings)
        total += used
        if T_rotated is not None:
            T, rotated = T_rotated, True
    fit = _Fit(T, True, 0, 0, float("nan"), None, None)
    for level_index in reversed(range(len(pyramid))):
        fit = _iterate(source_levels[level_index], pyramid[level_index], T, level_index, settings)
        total += fit.iterations
        T = fit.T_camera_world
    unobserved = 0
    if fit.ok and fit.AtA is not None:
        # Degeneracy is judged once the finest level has converged (see UNOBSERVED_SHARE). Along an
        # unobserved direction the levels followed the noise: the pose goes back to the start there, and
        # the finest level refines the observed directions again, held along the others.
        found = directions(fit.AtA, UNOBSERVED_SHARE, fit.noise)
        if found is not None and not found.observed.all():
            unobserved = int((~found.observed).sum())
            T = motion_matrix(found.project(motion_vector(T @ invert_pose(T_start)))) @ T_start
            fit = _iterate(source_levels[0], pyramid[0], T, 0, settings, within=found)
            total += fit.iterations
    return TrackResult(
        fit.T_camera_world, fit.ok, total, fit.correspondences, fit.rmse, unobserved, rotated,
        fit.pair_depths, fit.pair_residuals,
    )  # fmt: skip


def rotation_start(
    source: tuple[F32, F32], level: Level, T_init: FloatArray, settings: IcpSettings
) -> tuple[FloatArray | None, int]:
    """A start for ICP that turns the camera about its centre until the coarsest level's pairs agree, and
    the iterations it took; ``None`` when that start explains the level no better than ``T_init`` does.

    Up to ``settings.rotation_iterations`` Gauss-Newton iterations over the three rotation unknowns only
    (the translation held at ``T_init``'s). A hand-held camera turns faster than it moves: 80 degrees a
    second at 30 frames a second shift a wall 2.7 m away by 13 cm between frames. Solved jointly from the
    last pose, that shift leaks into a translation the view hardly observes (along a blank wall, observed
    only by the noise of its normals), and no later iteration pulls it back: in an empty simulated room
    turned on the spot at that rate, the camera slid 12 cm on the first frame and 0.89 m over 150. With the
    rotation found first the joint iterations start where the pairs already agree (4.4 cm RMS). A start is
    kept only when it pairs at least 90 % as many points as ``T_init`` with no larger mean squared residual
    (:func:`alignment_cost`), so a translation is never explained away as a turn.
    """
    points, normals = source
    T = T_init
    used = 0
    for _ in range(settings.rotation_iterations):
        pairs = associate(T, points, normals, level, settings.distance_threshold, settings.normal_cos_threshold)
        used += 1
        if len(pairs) < settings.min_correspondences:
            return None, used
        A, b = linear_system(pairs.source, pairs.target, pairs.normals)
        weights = _huber_weights(b, settings, pairs.target[:, 2])
        AtA, Atb = normal_equations(A[:, :3], b, weights)
        if not np.all(np.isfinite(AtA)) or np.linalg.eigvalsh(AtA)[0] <= NUMERICAL_SHARE * np.trace(AtA):
            return None, used
        rotation = np.linalg.solve(AtA, Atb)
        T = increment_matrix(np.r_[rotation, 0.0, 0.0, 0.0]) @ T
        if np.linalg.norm(rotation) < settings.convergence_rotation:
            break
    n_init, cost_init = alignment_cost(T_init, points, normals, level, settings)
    n_rotated, cost_rotated = alignment_cost(T, points, normals, level, settings)
    if math.isfinite(cost_rotated) and n_rotated >= 0.9 * n_init and cost_rotated <= cost_init:
        return T, used
    return None, used


@dataclass(frozen=True)
class _Fit:
    """Outcome of the iterations at one pyramid level; ``AtA`` of the last iteration (None without one) and
    ``noise``, the information the disagreement of the frame's and the map's normals gives (finest level)."""

    T_camera_world: FloatArray
    ok: bool
    iterations: int
    correspondences: int
    rmse: float
    AtA: FloatArray | None
    noise: FloatArray | None
    pair_depths: F32 | None = None
    pair_residuals: F32 | None = None


def _iterate(
    source: tuple[F32, F32],
    level: Level,
    T_init: FloatArray,
    level_index: int,
    settings: IcpSettings,
    within: Directions | None = None,
) -> _Fit:
    """ICP iterations at one level from ``T_init``, each increment solved along every direction that holds
    information (``NUMERICAL_SHARE``), or only along ``within``'s observed ones. A level that runs out of
    pairs or of information stops there, not ok; a coarse level's failure leaves the finer levels another
    chance."""
    points, normals = source
    T = T_init
    iterations = n = 0
    rmse = float("nan")
    AtA = noise = None
    b = depths = None
    for _ in range(settings.iterations[level_index]):
        pairs = associate(T, points, normals, level, settings.distance_threshold, settings.normal_cos_threshold)
        iterations += 1
        n = len(pairs)
        if n < settings.min_correspondences:
            logger.debug("level %d: only %d correspondences", level_index, n)
            return _Fit(T, level_index > 0, iterations, n, rmse, None, None)
        plane_normals = pairs.map_normals if settings.map_normals else pairs.normals
        A, b = linear_system(pairs.source, pairs.target, plane_normals)
        depths = pairs.target[:, 2]
        weights = _huber_weights(b, settings, depths)
        if settings.depth_weighting:
            inverse_variance = (np.float32(SIGMA_1M) / depth_sigma(depths)) ** 2
            weights = inverse_variance if weights is None else weights * inverse_variance
        rmse = float(np.sqrt(np.mean(np.square(b, dtype=np.float64))))
        AtA, Atb = normal_equations(A, b, weights)
        other_normals = pairs.normals if settings.map_normals else pairs.map_normals
        A_other, _ = linear_system(pairs.source, pairs.target, other_normals)
        noise, _ = normal_equations(A - A_other, b, weights)
        found = within or directions(AtA, DEGENERATE_SHARE, noise)
        x = None if found is None else solve_within(AtA, Atb, found)
        if x is None:
            logger.debug("level %d: singular normal equations", level_index)
            return _Fit(T, level_index > 0, iterations, n, rmse, None, None)
        T = increment_matrix(x) @ T
        if np.linalg.norm(x[:3]) < settings.convergence_rotation and (
            np.linalg.norm(x[3:]) < settings.convergence_translation
        ):
            break
    return _Fit(T, True, iterations, n, rmse, AtA, noise, depths, b)
