"""Least-squares rigid fitting of point pairs: the weighted Umeyama/Kabsch fit, plain Kabsch, the fit
on the axes a set of targets measures, and a RANSAC consensus of the pairs one rigid motion explains.

Conventions (see ``docs/log-format.md``): a pose ``T_a_b`` is a 4x4 homogeneous matrix that maps
coordinates in frame ``b`` to frame ``a`` (``p_a = T_a_b @ p_b``); quaternions are ``(x, y, z, w)``;
metres and radians throughout.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from relpoint.geometry.se3 import check_points
from relpoint.geometry.so3 import FloatArray, so3_exp


class RigidFit(NamedTuple):
    """Result of :func:`fit_rigid`: ``target ≈ scale * rotation @ source + translation``."""

    rotation: FloatArray
    translation: FloatArray
    scale: float
    rms: float

    def apply(self, points: FloatArray) -> FloatArray:
        """Map points (N, 3) of the source frame into the target's: ``scale * R p + t``."""
        return (self.scale * points) @ self.rotation.T + self.translation

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


#: Ratio of an axis's standard deviation to the best-measured one's beyond which a set of targets is
#: taken not to measure it (the altitude of a horizontal GNSS fix: variance 1e6-1e9 m^2 against 1 m^2).
UNMEASURED_RATIO = 100.0


def measured_basis(covariances: npt.ArrayLike) -> FloatArray:
    """Orthonormal basis (3, k) of the directions that targets of ``covariances`` (n, 3, 3) m^2 measure.

    Their mean information (inverse covariance) is split into its principal directions; those whose
    information is at least ``1 / UNMEASURED_RATIO^2`` of the largest are measured: k = 3 for
    targets whose per-axis standard deviations are within a factor of 100 of each other, 2 for a
    horizontal fix whose altitude is a placeholder of unknown variance.
    """
    return information_basis(summed_information(covariances))


def summed_information(covariances: npt.ArrayLike) -> FloatArray:
    """The summed information (3, 3) m^-2 of targets of ``covariances`` (n, 3, 3) m^2 (pseudo-inverses,
    with a 1e-12 m^2 floor, so that an exact target counts as very well measured, not as a singularity)."""
    covs = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
    return np.sum(np.linalg.pinv(covs + 1e-12 * np.eye(3), hermitian=True), axis=0)


def information_basis(information: FloatArray) -> FloatArray:
    """The basis (3, k) of :func:`measured_basis` from summed (or mean) ``information`` (3, 3)."""
    values, vectors = np.linalg.eigh(0.5 * (information + information.T))
    if values.max() <= 0.0:  # no target yet
        return np.eye(3)
    measured = values >= values.max() / UNMEASURED_RATIO**2
    return np.eye(3) if measured.all() else vectors[:, measured]  # every axis: the axes themselves


def fit_rigid_on_axes(source: FloatArray, target: FloatArray, weights: FloatArray, basis: FloatArray) -> RigidFit:
    """The rigid fit of ``source`` onto ``target`` (n, 3) on the directions ``basis`` (3, k) measures.

    k = 3 is :func:`fit_rigid`. With k = 2 (one axis unmeasured) the rotation is about that axis
    only, a weighted 2-D Procrustes fit in the measured plane; with k = 1 there is no rotation. The
    translation moves only along the measured directions, and ``rms`` is the weighted residual on
    them: what the targets say of the unmeasured axis (a placeholder value) is not used.
    """
    k = basis.shape[1]
    if k == 3:
        return fit_rigid(source, target, weights=weights)
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    rotation = np.eye(3)
    if k == 2:
        axis = np.cross(basis[:, 0], basis[:, 1])  # (basis, axis) is right-handed
        a = source @ basis
        b = target @ basis
        H = ((a - w @ a) * w[:, None]).T @ (b - w @ b)
        rotation = so3_exp(float(np.arctan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1])) * axis)
    projector = basis @ basis.T
    translation = projector @ (w @ target - rotation @ (w @ source))
    residual = (target - source @ rotation.T - translation) @ projector
    return RigidFit(rotation, translation, 1.0, float(np.sqrt(w @ np.sum(residual**2, axis=1))))


def fitted_parameters(basis: FloatArray) -> FloatArray:
    """The directions (6, m) of an error ``(dt, dphi)`` (m, rad) that :func:`fit_rigid_on_axes` fits:
    all six with three measured axes; else the translation along the measured ones and, with two,
    the rotation about the third. The others are not fitted, so they carry no uncertainty."""
    k = basis.shape[1]
    if k == 3:
        return np.eye(6)
    directions = np.vstack([basis, np.zeros((3, k))])
    if k == 2:
        axis = np.cross(basis[:, 0], basis[:, 1])
        directions = np.hstack([directions, np.concatenate([np.zeros(3), axis])[:, None]])
    return directions


def kabsch(source: FloatArray, target: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(R, t)`` minimising ``|R source + t - target|`` over (N, 3) point pairs, unweighted."""
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    U, _, Vt = np.linalg.svd((source - cs).T @ (target - ct))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, ct - R @ cs


def kabsch_batch(source: FloatArray, target: FloatArray) -> tuple[FloatArray, FloatArray]:
    """:func:`kabsch` of each of H sets of point pairs at once: ``source``, ``target`` (H, n, 3) ->
    ``(R (H, 3, 3), t (H, 3))`` with ``R[h] source[h] + t[h]`` nearest ``target[h]`` (one batched SVD)."""
    ca, cb = source.mean(axis=1, keepdims=True), target.mean(axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(np.einsum("sni,snj->sij", source - ca, target - cb))
    flip = np.linalg.det(np.einsum("sji,skj->sik", Vt, U)) < 0  # det(V U^T)
    Vt[flip, 2] *= -1.0
    R = np.einsum("sji,skj->sik", Vt, U)  # V U^T: takes source onto target
    return R, cb[:, 0] - np.einsum("sij,sj->si", R, ca[:, 0])


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
    R, t = kabsch_batch(source[picks], target[picks])  # (S, 3, 3) pairs a draw
    residual = np.linalg.norm(np.einsum("sij,nj->sni", R, source) + t[:, None] - target[None], axis=2)
    best = int(np.argmax((residual <= tolerance).sum(axis=1)))
    inliers = residual[best] <= tolerance
    if inliers.sum() < 3:
        return np.ones(n, dtype=bool)
    fit = fit_rigid(source[inliers], target[inliers])
    return np.linalg.norm(fit.apply(source) - target, axis=1) <= tolerance
