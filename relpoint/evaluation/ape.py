"""Absolute pose error (APE/ATE) over matched pose pairs, exactly as evo's ``metrics.APE``.

Kümmerle et al., *On measuring the accuracy of SLAM algorithms* (2009): the error pose of a pair is
``E = T_est^-1 T_ref``; the pose relation picks what is measured of it. The translation part is the
distance between the (aligned) positions, ``|p_est - p_ref|`` - the ATE of Sturm et al. (2012).
"""

from __future__ import annotations

import enum

import numpy as np

from relpoint.errors import UsageError
from relpoint.evaluation.association import MatchedPoses
from relpoint.geometry import FloatArray


class PoseRelation(str, enum.Enum):
    """What an error pose is reduced to; values are evo's ``-r/--pose_relation`` choices."""

    FULL = "full"  # |E - I_4| (Frobenius), dimensionless
    TRANS_PART = "trans_part"  # metres
    ROT_PART = "rot_part"  # |R_E - I_3| (Frobenius), dimensionless
    ANGLE_DEG = "angle_deg"  # rotation angle of E, degrees
    ANGLE_RAD = "angle_rad"  # rotation angle of E, radians
    POINT_DISTANCE = "point_distance"  # metres; APE: as trans_part, RPE: difference of pair distances
    POINT_DISTANCE_ERROR_RATIO = "point_distance_error_ratio"  # RPE only, percent

    @classmethod
    def parse(cls, value: str | PoseRelation) -> PoseRelation:
        """The member named ``value``, or raise ``UsageError`` listing the choices."""
        try:
            return cls(value)
        except ValueError:
            choices = "|".join(m.value for m in cls)
            raise UsageError(f"unknown pose relation {value!r}, expected {choices}") from None

    @property
    def unit(self) -> str:
        """Unit of the error values (evo's ``Unit`` value)."""
        return {
            PoseRelation.TRANS_PART: "m",
            PoseRelation.POINT_DISTANCE: "m",
            PoseRelation.ANGLE_DEG: "deg",
            PoseRelation.ANGLE_RAD: "rad",
            PoseRelation.POINT_DISTANCE_ERROR_RATIO: "%",
        }.get(self, "")


def rotation_angles(rotations: FloatArray) -> FloatArray:
    """Rotation angles in radians (N,) of rotation matrices (N, 3, 3), as evo's ``so3_log_angle``."""
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

    if len(rotations) == 0:
        return np.zeros(0)
    return np.linalg.norm(Rotation.from_matrix(rotations).as_rotvec(), axis=1)


def relation_errors(error_rotations: FloatArray, error_translations: FloatArray, relation: PoseRelation) -> FloatArray:
    """Reduce error poses (N, 3, 3) + (N, 3) to scalars (N,) by ``relation`` (pose-based relations only)."""
    if relation is PoseRelation.TRANS_PART:
        return np.linalg.norm(error_translations, axis=1)
    if relation is PoseRelation.ROT_PART:
        return np.linalg.norm(error_rotations - np.eye(3), axis=(1, 2))
    if relation is PoseRelation.FULL:
        E = np.zeros((len(error_rotations), 4, 4))
        E[:, :3, :3] = error_rotations
        E[:, :3, 3] = error_translations
        E[:, 3, 3] = 1.0
        return np.linalg.norm(E - np.eye(4), axis=(1, 2))
    if relation is PoseRelation.ANGLE_RAD:
        return np.abs(rotation_angles(error_rotations))
    if relation is PoseRelation.ANGLE_DEG:
        return np.abs(np.rad2deg(rotation_angles(error_rotations)))
    raise UsageError(f"pose relation {relation.value} is not defined on error poses")


def ape_errors(matched: MatchedPoses, relation: PoseRelation | str = PoseRelation.TRANS_PART) -> FloatArray:
    """Absolute error of each matched pair (K,), in the unit of ``relation``.

    ``matched`` should already be aligned (:func:`~relpoint.evaluation.alignment.apply_alignment`).

    Raises
    ------
    UsageError
        For ``point_distance_error_ratio``, which evo defines for the RPE only.
    """
    relation = PoseRelation.parse(relation)
    if relation in (PoseRelation.TRANS_PART, PoseRelation.POINT_DISTANCE):
        # The translation part of E_i equals the position difference in norm; evo takes this shortcut.
        return np.linalg.norm(matched.estimate_positions - matched.reference_positions, axis=1)
    if relation is PoseRelation.POINT_DISTANCE_ERROR_RATIO:
        raise UsageError("pose relation point_distance_error_ratio is defined for the RPE only")
    R_est_T = np.swapaxes(matched.estimate_rotations, 1, 2)
    error_rotations = R_est_T @ matched.reference_rotations
    error_translations = np.einsum("nij,nj->ni", R_est_T, matched.reference_positions - matched.estimate_positions)
    return relation_errors(error_rotations, error_translations, relation)
