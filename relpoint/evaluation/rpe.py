"""Relative pose error (RPE) over matched pose pairs, exactly as evo's ``metrics.RPE``.

Sturm et al., *A benchmark for the evaluation of RGB-D SLAM systems* (IROS 2012), eq. 1: for a pair of
indices ``(i, j)`` the error pose is ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` with ``Q`` the reference and
``P`` the estimate. The pairs are chosen by a delta in frames, metres of travelled path or degrees /
radians of rotation, from the estimate (default) or the reference, consecutive or "all pairs" within a
relative tolerance - evo's ``filters.filter_pairs_by_*`` semantics, reproduced bit for bit.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.errors import UsageError
from relpoint.evaluation import EvaluationError
from relpoint.evaluation.ape import PoseRelation, relation_errors, rotation_angles
from relpoint.evaluation.association import MatchedPoses
from relpoint.geometry import FloatArray
from relpoint.types import IntArray

#: Half width of the window searched around the predicted partner in the all-pairs path search.
_PATH_WINDOW = 3
#: Margin of the quaternion-dot preselection in the all-pairs angle search, radians.
_ANGLE_MARGIN = 1e-6


class DeltaUnit(str, enum.Enum):
    """Unit of the RPE delta; values are evo's ``-u/--delta_unit`` choices."""

    FRAMES = "f"
    METERS = "m"
    DEGREES = "d"
    RADIANS = "r"

    @classmethod
    def parse(cls, value: str | DeltaUnit) -> DeltaUnit:
        """The member for ``value`` (``f``, ``m``, ``d``, ``r`` or a member name), else ``UsageError``."""
        if isinstance(value, DeltaUnit):
            return value
        aliases = {"frames": "f", "meters": "m", "metres": "m", "degrees": "d", "deg": "d", "radians": "r", "rad": "r"}
        try:
            return cls(aliases.get(value.lower(), value.lower()))
        except ValueError:
            raise UsageError(f"unknown delta unit {value!r}, expected f|m|d|r") from None


@dataclass(frozen=True, eq=False)
class RelativeErrors:
    """RPE of each pose pair: ``errors`` (P,) in the relation's unit, pair indices ``first``, ``second`` (P,)."""

    errors: FloatArray
    first: IntArray
    second: IntArray
    relation: PoseRelation

    def __len__(self) -> int:
        return len(self.errors)


def accumulated_distances(positions: FloatArray) -> FloatArray:
    """Travelled path length at each pose (N,), metres, starting at 0 (evo ``geometry.accumulated_distances``)."""
    return np.concatenate((np.array([0.0]), np.cumsum(np.linalg.norm(positions[:-1] - positions[1:], axis=1))))


def _pairs_by_index(n: int, delta: int, all_pairs: bool) -> tuple[IntArray, IntArray]:
    if all_pairs:
        first = np.arange(max(n - delta, 0), dtype=np.int64)
        return first, first + delta
    ids = np.arange(0, n, delta, dtype=np.int64)
    return ids[:-1], ids[1:]


def _pairs_by_path(positions: FloatArray, delta: float, tol: float, all_pairs: bool) -> tuple[IntArray, IntArray]:
    n = len(positions)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if not all_pairs:
        steps = np.linalg.norm(positions[1:] - positions[:-1], axis=1).tolist()
        ids = [0]
        current = 0.0
        for i, step in enumerate(steps, start=1):  # sequential: the sum restarts at each chosen pose
            current += step
            if current >= delta:
                ids.append(i)
                current = 0.0
        ids_array = np.array(ids, dtype=np.int64)
        return ids_array[:-1], ids_array[1:]
    distances = accumulated_distances(positions)
    starts = np.arange(n - 1)
    # |(d_j - d_i) - delta| is unimodal in j (d is non-decreasing), so evo's first arg-min over j > i lies
    # next to the predicted crossing; rows where it touches the window edge are redone in full.
    centre = np.searchsorted(distances, distances[starts] + delta)
    cols = centre[:, None] + np.arange(-_PATH_WINDOW, _PATH_WINDOW + 1)[None, :]
    valid = (cols > starts[:, None]) & (cols < n)
    cols_c = np.clip(cols, 0, n - 1)
    gap = np.abs((distances[cols_c] - distances[starts][:, None]) - delta)
    gap = np.where(valid, gap, np.inf)
    pick = np.argmin(gap, axis=1)
    best = cols_c[starts, pick]
    best_gap = gap[starts, pick]
    low_edge = (pick == 0) & (cols[:, 0] > starts + 1)
    high_edge = (pick == cols.shape[1] - 1) & (cols[:, -1] < n - 1)
    for i in np.nonzero(low_edge | high_edge)[0].tolist():
        row = np.abs((distances[i + 1 :] - distances[i]) - delta)
        k = int(np.argmin(row))
        best[i], best_gap[i] = k + i + 1, row[k]
    keep = ~(best_gap > tol)
    return starts[keep].astype(np.int64), best[keep].astype(np.int64)


def _pairs_by_angle(
    rotations: FloatArray, delta: float, tol: float, degrees: bool, all_pairs: bool
) -> tuple[IntArray, IntArray]:
    bounds = (0.0, 180.0) if degrees else (0.0, np.pi)
    if delta < bounds[0] or delta > bounds[1]:
        raise UsageError(f"delta angle must be within [{bounds[0]}, {bounds[1]:.6g}]")
    delta = float(np.deg2rad(delta)) if degrees else delta
    tol = float(np.deg2rad(tol)) if degrees else tol
    n = len(rotations)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if all_pairs:
        from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

        rots = Rotation.from_matrix(rotations)
        quats = rots.as_quat()
        first: list[int] = []
        second: list[int] = []
        for i in range(n - 1):  # O(n^2) like evo: every later pose is a candidate partner
            # A cheap quaternion-dot angle (error < 1e-7 rad) preselects candidates; evo's exact formula
            # then decides, so pairs on the tolerance edge fall as in evo.
            rough = 2.0 * np.arccos(np.clip(np.abs(quats[i + 1 :] @ quats[i]), 0.0, 1.0))
            near = np.nonzero((rough >= delta - tol - _ANGLE_MARGIN) & (rough <= delta + tol + _ANGLE_MARGIN))[0]
            if near.size == 0:
                continue
            angles = np.linalg.norm((rots[i].inv() * rots[near + i + 1]).as_rotvec(), axis=1)
            matches = near[(delta - tol <= angles) & (angles <= delta + tol)] + i + 1
            first.extend([i] * len(matches))
            second.extend(matches.tolist())
        return np.array(first, dtype=np.int64), np.array(second, dtype=np.int64)
    steps = rotation_angles(np.swapaxes(rotations[:-1], 1, 2) @ rotations[1:]).tolist()
    pairs: list[tuple[int, int]] = []
    accumulated = 0.0
    start = 0
    for i, step in enumerate(steps):
        accumulated += step
        if accumulated >= delta:
            pairs.append((start, i + 1))
            accumulated = 0.0
            start = i + 1
    array = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    return array[:, 0], array[:, 1]


def rpe_pairs(
    positions: npt.ArrayLike,
    rotations: npt.ArrayLike,
    delta: float,
    unit: DeltaUnit | str = DeltaUnit.FRAMES,
    rel_tol: float = 0.1,
    all_pairs: bool = False,
) -> tuple[IntArray, IntArray]:
    """Index pairs ``(first, second)`` (P,) each, separated by ``delta`` (evo ``id_pairs_from_delta``).

    Parameters
    ----------
    positions, rotations:
        The poses the pairs are chosen on: (N, 3) metres and (N, 3, 3).
    delta:
        Pair separation in ``unit``: frames (integer > 0), metres of travelled path, or degrees /
        radians of rotation (accumulated along the path; direct angle between the pair if ``all_pairs``).
    rel_tol:
        Relative tolerance ``delta * rel_tol`` for metres and angles in all-pairs mode (evo ``--delta_tol``).
    all_pairs:
        Every pose starts a pair (evo ``--all_pairs``) instead of consecutive, non-overlapping pairs.

    Raises
    ------
    UsageError
        Negative delta, non-integer frame delta, angle outside [0, 180] deg / [0, pi] rad.
    EvaluationError
        No pair has the requested separation.
    """
    unit = DeltaUnit.parse(unit)
    positions = np.asarray(positions, dtype=np.float64)
    rotations = np.asarray(rotations, dtype=np.float64)
    if not np.isfinite(delta) or delta < 0:
        raise UsageError(f"delta must be a finite number >= 0, got {delta}")
    if unit is DeltaUnit.FRAMES:
        if float(delta) != int(delta) or delta < 1:
            raise UsageError(f"delta must be a positive integer for delta unit f (frames), got {delta}")
        first, second = _pairs_by_index(len(positions), int(delta), all_pairs)
    elif unit is DeltaUnit.METERS:
        first, second = _pairs_by_path(positions, float(delta), float(delta) * rel_tol, all_pairs)
    else:
        first, second = _pairs_by_angle(
            rotations, float(delta), float(delta) * rel_tol, unit is DeltaUnit.DEGREES, all_pairs
        )
    if len(first) == 0:
        raise EvaluationError(
            f"RPE delta = {delta} ({unit.value}) produced no pose pairs among {len(positions)} poses",
            hint="try a lower delta or a larger tolerance",
        )
    return first, second


def rpe_errors(
    matched: MatchedPoses,
    relation: PoseRelation | str = PoseRelation.TRANS_PART,
    *,
    delta: float = 1.0,
    delta_unit: DeltaUnit | str = DeltaUnit.FRAMES,
    rel_tol: float = 0.1,
    all_pairs: bool = False,
    pairs_from_reference: bool = False,
) -> RelativeErrors:
    """Relative pose error of matched (and, if wanted, aligned) poses, as ``evo_rpe``.

    The pairs are chosen on the estimate unless ``pairs_from_reference`` (evo
    ``--pairs_from_reference``). ``point_distance_error_ratio`` drops pairs whose reference distance is 0.
    """
    relation = PoseRelation.parse(relation)
    source_p = matched.reference_positions if pairs_from_reference else matched.estimate_positions
    source_R = matched.reference_rotations if pairs_from_reference else matched.estimate_rotations
    i, j = rpe_pairs(source_p, source_R, delta, delta_unit, rel_tol, all_pairs)
    Qp, QR = matched.reference_positions, matched.reference_rotations
    Pp, PR = matched.estimate_positions, matched.estimate_rotations
    if relation in (PoseRelation.POINT_DISTANCE, PoseRelation.POINT_DISTANCE_ERROR_RATIO):
        ref_distances = np.linalg.norm(Qp[i] - Qp[j], axis=1)
        est_distances = np.linalg.norm(Pp[i] - Pp[j], axis=1)
        errors = np.abs(ref_distances - est_distances)
        if relation is PoseRelation.POINT_DISTANCE_ERROR_RATIO:
            nonzero = ref_distances.nonzero()[0]
            errors = np.divide(errors[nonzero], ref_distances[nonzero]) * 100
            i, j = i[nonzero], j[nonzero]
        return RelativeErrors(errors, i, j, relation)
    QR_i_T = np.swapaxes(QR[i], 1, 2)
    PR_i_T = np.swapaxes(PR[i], 1, 2)
    Q_rel_R = QR_i_T @ QR[j]
    Q_rel_t = np.einsum("nij,nj->ni", QR_i_T, Qp[j] - Qp[i])
    P_rel_R = PR_i_T @ PR[j]
    P_rel_t = np.einsum("nij,nj->ni", PR_i_T, Pp[j] - Pp[i])
    Q_rel_R_T = np.swapaxes(Q_rel_R, 1, 2)
    E_R = Q_rel_R_T @ P_rel_R
    E_t = np.einsum("nij,nj->ni", Q_rel_R_T, P_rel_t - Q_rel_t)
    return RelativeErrors(relation_errors(E_R, E_t, relation), i, j, relation)
