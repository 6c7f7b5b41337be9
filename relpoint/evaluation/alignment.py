"""Umeyama alignment of an estimated trajectory to a reference: none, SE(3), Sim(3), scale only, origin.

Umeyama, *Least-squares estimation of transformation parameters between two point patterns*, IEEE PAMI
1991, eqs. 34-43, as evo 1.38 applies it (``PosePath3D.align``, ``align_origin``): the transform is fitted
on the matched positions (optionally only the first ``n`` pairs) and applied to the estimate's poses,
``p' = R (s p) + t`` and ``R' = R R_est``. Unlike evo, nothing is modified in place: the aligned poses are
returned as a new :class:`~relpoint.evaluation.association.MatchedPoses`.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from relpoint.errors import UsageError
from relpoint.evaluation import EvaluationError
from relpoint.evaluation.association import MatchedPoses
from relpoint.geometry import FloatArray, check_points

logger = logging.getLogger(__name__)

#: Second singular value of the cross-covariance, relative to the first, below which the positions
#: are taken as collinear: the rotation about that line is then undetermined.
COLLINEAR_TOLERANCE = 1e-12


class AlignMode(str, enum.Enum):
    """How the estimate is aligned before the absolute error is taken (evo flag in brackets)."""

    NONE = "none"  # (no flag)
    SE3 = "se3"  # -a / --align
    SIM3 = "sim3"  # -as / --align --correct_scale
    SCALE = "scale"  # -s / --correct_scale alone: only the Umeyama scale is applied
    ORIGIN = "origin"  # --align_origin: first estimated pose moved onto the first reference pose

    @classmethod
    def parse(cls, value: str | AlignMode) -> AlignMode:
        """The member named ``value`` (case-insensitive), or raise ``UsageError`` listing the choices."""
        try:
            return cls(value.lower() if isinstance(value, str) else value)
        except ValueError:
            choices = "|".join(m.value for m in cls)
            raise UsageError(f"unknown alignment {value!r}, expected {choices}") from None


@dataclass(frozen=True)
class Alignment:
    """The similarity ``p_ref ≈ s R p_est + t`` applied to the estimate (identity for ``none``).

    Attributes
    ----------
    rotation: (3, 3) rotation ``R_ref_est``.
    translation: (3,) metres, in the reference world frame.
    scale: uniform scale ``s`` (1 unless Sim(3) or scale-only).
    mode: the :class:`AlignMode` that produced it.
    n_used: number of pose pairs the fit used (0 for ``none``).
    """

    rotation: FloatArray
    translation: FloatArray
    scale: float
    mode: AlignMode
    n_used: int

    @classmethod
    def identity(cls) -> Alignment:
        return cls(np.eye(3), np.zeros(3), 1.0, AlignMode.NONE, 0)

    def as_matrix(self) -> FloatArray:
        """The 4x4 Sim(3) matrix ``[[s R, t], [0, 1]]`` (evo's ``alignment_transformation_sim3``)."""
        T = np.eye(4)
        T[:3, :3] = self.scale * self.rotation
        T[:3, 3] = self.translation
        return T

    def apply_positions(self, positions: npt.ArrayLike) -> FloatArray:
        """Map estimate-frame points (N, 3) into the reference frame: ``R (s p) + t``."""
        p = check_points(positions, "positions")
        return (self.scale * p) @ self.rotation.T + self.translation

    def apply_rotations(self, rotations: npt.ArrayLike) -> FloatArray:
        """Map estimate orientations (N, 3, 3) into the reference frame: ``R R_est``."""
        return np.einsum("ij,njk->nik", self.rotation, np.asarray(rotations, dtype=np.float64))


def umeyama(
    source: npt.ArrayLike, target: npt.ArrayLike, with_scale: bool = False
) -> tuple[FloatArray, FloatArray, float]:
    """Least-squares ``target ≈ c R source + t`` (Umeyama 1991), as ``evo.core.geometry.umeyama_alignment``.

    Parameters
    ----------
    source, target:
        Corresponding points (N, 3), N >= 3.
    with_scale:
        Estimate the scale ``c`` (Sim(3)); otherwise ``c = 1``.

    Returns
    -------
    rotation (3, 3), translation (3,), scale.

    Raises
    ------
    EvaluationError
        If fewer than three pairs are given, or the points are collinear or coincident (the
        cross-covariance has rank < 2: evo's test, plus a relative one for floating-point lines).
    """
    x = check_points(source, "source")
    y = check_points(target, "target")
    if x.shape != y.shape:
        raise ValueError(f"source {x.shape} and target {y.shape} must have the same shape")
    n = len(x)
    if n < 3:
        raise EvaluationError(f"alignment needs at least 3 matched poses, got {n}")
    mean_x = x.mean(axis=0)
    mean_y = y.mean(axis=0)
    dx = x - mean_x
    dy = y - mean_y
    sigma_x = 1.0 / n * np.linalg.norm(dx) ** 2  # eq. 36
    cov_xy = np.multiply(1.0 / n, dy.T @ dx)  # eq. 38
    u, d, v = np.linalg.svd(cov_xy)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < 2 or d[1] <= COLLINEAR_TOLERANCE * d[0]:
        raise EvaluationError(
            "degenerate trajectory: the matched positions are collinear or coincident, "
            "so the Umeyama alignment is not unique",
            hint="use --align none, or a section of the trajectory that turns",
        )
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(v) < 0.0:
        s[2, 2] = -1.0  # proper rotation (eq. 43)
    rotation = u @ s @ v  # eq. 40
    scale = float(1.0 / sigma_x * np.trace(np.diag(d) @ s)) if with_scale else 1.0  # eq. 42
    translation = mean_y - np.multiply(scale, rotation @ mean_x)  # eq. 41
    return rotation, translation, scale


def align_positions(
    reference_positions: npt.ArrayLike,
    estimate_positions: npt.ArrayLike,
    mode: AlignMode | str,
    n_to_align: int = -1,
) -> Alignment:
    """Fit the alignment of ``mode`` taking estimate positions (N, 3) onto reference positions (N, 3).

    ``n_to_align`` is evo's ``--n_to_align``: -1 uses all pairs, n > 0 the first n. ``origin`` needs
    orientations and is handled by :func:`estimate_alignment`.

    Raises
    ------
    EvaluationError
        Fewer than three pairs to fit, or degenerate (collinear) positions.
    UsageError
        ``n_to_align`` is 0 or below -1.
    """
    mode = AlignMode.parse(mode)
    if n_to_align == 0 or n_to_align < -1:
        raise UsageError(f"n_to_align must be -1 (all poses) or a positive count, got {n_to_align}")
    if mode is AlignMode.NONE:
        return Alignment.identity()
    if mode is AlignMode.ORIGIN:
        raise ValueError("origin alignment needs orientations: use estimate_alignment()")
    ref = check_points(reference_positions, "reference_positions")
    est = check_points(estimate_positions, "estimate_positions")
    if n_to_align != -1:
        ref, est = ref[:n_to_align], est[:n_to_align]
    rotation, translation, scale = umeyama(est, ref, with_scale=mode in (AlignMode.SIM3, AlignMode.SCALE))
    logger.debug("alignment %s on %d poses: scale %.9g", mode.value, len(est), scale)
    if mode is AlignMode.SCALE:
        return Alignment(np.eye(3), np.zeros(3), scale, mode, len(est))
    return Alignment(rotation, translation, scale, mode, len(est))


def estimate_alignment(matched: MatchedPoses, mode: AlignMode | str, n_to_align: int = -1) -> Alignment:
    """The alignment of ``mode`` for matched pose pairs (see :func:`align_positions`).

    ``origin`` maps the first estimated pose onto the first reference pose: ``T = T_ref0 T_est0^-1``.
    """
    mode = AlignMode.parse(mode)
    if mode is AlignMode.ORIGIN:
        if len(matched) == 0:
            raise EvaluationError("origin alignment needs at least one matched pose")
        R_ref0, R_est0 = matched.reference_rotations[0], matched.estimate_rotations[0]
        rotation = R_ref0 @ R_est0.T
        translation = matched.reference_positions[0] - rotation @ matched.estimate_positions[0]
        return Alignment(rotation, translation, 1.0, mode, 1)
    return align_positions(matched.reference_positions, matched.estimate_positions, mode, n_to_align)


def apply_alignment(matched: MatchedPoses, alignment: Alignment) -> MatchedPoses:
    """A copy of ``matched`` with the estimate's poses mapped by ``alignment`` into the reference frame."""
    if alignment.mode is AlignMode.NONE:
        return matched
    return replace(
        matched,
        estimate_positions=alignment.apply_positions(matched.estimate_positions),
        estimate_rotations=alignment.apply_rotations(matched.estimate_rotations),
    )
