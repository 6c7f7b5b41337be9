"""One library call for ``relpoint evaluate``: associate, align, then APE, RPE and KITTI segment errors.

The pipeline is evo's (``evo_ape`` / ``evo_rpe``: sync, Umeyama alignment, metric), run once for both
metrics, with one settings object whose fields are the CLI options (``docs/evaluation.md`` maps each to
its evo flag). The result holds a flat summary (``ate_rmse``, ``rpe_trans_rmse``, ...) and the per-pose
error arrays for CSV output and plots.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from relpoint.errors import UsageError
from relpoint.evaluation import EvaluationError
from relpoint.evaluation.alignment import Alignment, AlignMode, apply_alignment, estimate_alignment
from relpoint.evaluation.ape import PoseRelation, ape_errors
from relpoint.evaluation.association import MatchedPoses, associate, time_span
from relpoint.evaluation.kitti import KITTI_LENGTHS, KittiSegmentErrors, kitti_segment_errors
from relpoint.evaluation.rpe import DeltaUnit, RelativeErrors, accumulated_distances, rpe_errors
from relpoint.evaluation.statistics import STATISTICS, error_statistics
from relpoint.geometry import FloatArray
from relpoint.settings import Settings, is_number, setting
from relpoint.types import IntArray, Trajectory

#: The pose relations of the APE (and so of the ``ape_*`` and ``rpe_*`` figures together):
#: ``point_distance_error_ratio`` is defined for the RPE only.
APE_RELATIONS = tuple(relation for relation in PoseRelation if relation is not PoseRelation.POINT_DISTANCE_ERROR_RATIO)

#: Summary keys (trajectory and landmark figures) that count poses, pairs, segments or landmarks.
COUNT_KEYS = frozenset({
    "matched_poses", "reference_poses", "estimate_poses", "rpe_pairs", "kitti_segments",
    "lm_count", "lm_matched", "lm_duplicates", "lm_false",
})  # fmt: skip


def with_counts(summary: Mapping[str, float]) -> dict[str, float | int]:
    """``summary`` with its counts (:data:`COUNT_KEYS`) as ints, as every file relpoint writes holds them
    (``200``, not ``200.0``); a count that is NaN (undefined) stays NaN."""
    return {key: int(value) if key in COUNT_KEYS and float(value).is_integer() else value
            for key, value in summary.items()}  # fmt: skip


@dataclass(frozen=True)
class EvaluationSettings(Settings):
    """Options of a trajectory evaluation (CLI option and evo flag in brackets).

    Attributes
    ----------
    align: none | se3 | sim3 | scale | origin (``--align``; evo ``-a``, ``-as``, ``-s``, ``--align_origin``).
    n_to_align: fit the alignment on the first n matched poses, -1 = all (``--n-to-align``; evo ``--n_to_align``).
    t_max_diff: largest stamp difference for a match, seconds (``--t-max-diff``; evo ``--t_max_diff``).
    t_offset: added to the estimate's stamps, seconds (``--t-offset``; evo ``--t_offset``).
    interpolate: resample the denser trajectory at the other's stamps (``--interpolate``; evo
        ``--sync_method interpolation``).
    pose_relation: relation of the ``ape_*`` and ``rpe_*`` figures (``--pose-relation``; evo ``-r``).
    delta, delta_unit, delta_tol, all_pairs, pairs_from_reference: RPE pairs (``--delta``, ``--delta-unit``
        f|m|d|r, ``--delta-tol``, ``--all-pairs``, ``--pairs-from-reference``; evo ``-d``, ``-u``, ``-t``,
        ``--all_pairs``, ``--pairs_from_reference``).
    rpe: compute the RPE figures.
    kitti, kitti_lengths, kitti_step: KITTI segment errors (reported when any segment fits).
    min_matched_fraction: the matched pairs must number at least this fraction of the sparser
        trajectory's poses (``--min-matched``; 0 accepts any overlap). A smaller overlap usually means
        the two trajectories come from different runs or time bases.
    """

    settings_name: ClassVar[str] = "evaluation"

    align: AlignMode = setting(AlignMode.NONE, choices=AlignMode)
    n_to_align: int = setting(-1, low=1, high=1e9, also=(-1,))
    t_max_diff: float = setting(0.01, low=0, high=1e10)
    t_offset: float = setting(0.0, low=-1e10, high=1e10)
    interpolate: bool = False
    pose_relation: PoseRelation = setting(PoseRelation.TRANS_PART, choices=APE_RELATIONS)
    delta: float = setting(1.0, above=0, high=1e9)
    delta_unit: DeltaUnit = setting(DeltaUnit.FRAMES, choices=DeltaUnit)
    delta_tol: float = setting(0.1, low=0, below=math.inf)
    all_pairs: bool = False
    pairs_from_reference: bool = False
    rpe: bool = True
    kitti: bool = True
    kitti_lengths: tuple[float, ...] = setting(KITTI_LENGTHS, above=0, below=math.inf)
    kitti_step: int = setting(10, low=1, high=1e9)
    min_matched_fraction: float = setting(0.5, low=0, high=1)

    def normalise(self) -> None:
        """Text to the enum members (``se3`` to ``AlignMode.SE3``, ...; text that names none is left for
        the choices check to report), the KITTI lengths to floats."""
        for name, parse in (("align", AlignMode.parse), ("pose_relation", PoseRelation.parse),
                            ("delta_unit", DeltaUnit.parse)):  # fmt: skip
            if isinstance(getattr(self, name), str):
                with contextlib.suppress(UsageError):
                    object.__setattr__(self, name, parse(getattr(self, name)))
        if isinstance(self.kitti_lengths, list | tuple):
            lengths = tuple(float(x) if is_number(x) else x for x in self.kitti_lengths)
            object.__setattr__(self, "kitti_lengths", lengths)

    def check(self) -> None:
        """A delta in frames is a whole number of frames."""
        if self.delta_unit is DeltaUnit.FRAMES and not float(self.delta).is_integer():
            raise UsageError(
                f"evaluation setting delta must be a whole number for delta unit f (frames), got {self.delta}"
            )

    def to_dict(self) -> dict[str, Any]:
        """Plain values (strings for the enums) for dumping beside the results."""
        out = dataclasses.asdict(self)
        for key, value in out.items():
            if isinstance(value, AlignMode | PoseRelation | DeltaUnit):
                out[key] = value.value
        out["kitti_lengths"] = list(self.kitti_lengths)
        return out


@dataclass(frozen=True, eq=False)
class EvaluationResult:
    """Everything ``evaluate_trajectory`` found.

    Attributes
    ----------
    summary: flat name -> float (see ``docs/evaluation.md`` for the keys).
    matched: the associated pose pairs, estimate already aligned into the reference frame.
    alignment: the transform applied to the estimate.
    stamps_ns: (K,) estimate stamps of the matched pairs.
    ape_translation: (K,) position error after alignment, metres.
    ape_rotation_deg: (K,) rotation angle of the error pose, degrees.
    ape: (K,) APE in ``settings.pose_relation``.
    rpe_translation, rpe_rotation_deg, rpe: relative errors (None without RPE); their ``second`` indices
        index ``stamps_ns``.
    kitti: KITTI segment errors (None when disabled).
    notes: what was left out and why (an RPE without a pose pair at its delta: ``rpe_pairs`` is 0).
    """

    summary: dict[str, float]
    settings: EvaluationSettings
    matched: MatchedPoses
    alignment: Alignment
    stamps_ns: IntArray
    ape_translation: FloatArray
    ape_rotation_deg: FloatArray
    ape: FloatArray
    rpe_translation: RelativeErrors | None = None
    rpe_rotation_deg: RelativeErrors | None = None
    rpe: RelativeErrors | None = None
    kitti: KittiSegmentErrors | None = field(default=None)
    notes: tuple[str, ...] = ()


def _prefixed(prefix: str, errors: FloatArray) -> dict[str, float]:
    stats = error_statistics(errors)
    return {f"{prefix}_{name}": stats[name] for name in STATISTICS}


def evaluate_trajectory(
    reference: Trajectory, estimate: Trajectory, settings: EvaluationSettings | None = None
) -> EvaluationResult:
    """Associate, align and measure ``estimate`` against ``reference`` (evo_ape + evo_rpe in one pass).

    Summary keys: ``matched_poses``, ``reference_poses``, ``estimate_poses``, ``duration_s``,
    ``path_length_m`` (reference, over matched poses), ``alignment_scale``; ``ate_*`` (translation, m),
    ``ape_rot_deg_*`` (rotation angle, deg), ``ape_*`` (``settings.pose_relation``); with RPE
    ``rpe_trans_*`` (m), ``rpe_rot_deg_*`` (deg), ``rpe_*`` (``settings.pose_relation``), ``rpe_pairs``; with
    KITTI segments ``kitti_segments`` and, if any, ``kitti_t_err_pct``, ``kitti_r_err_deg_per_100m``.
    Each ``*`` is one of rmse, mean, median, std, min, max, sse.

    Raises
    ------
    EvaluationError
        No matching stamps, fewer than three matched poses or collinear positions for an alignment, or
        an RPE delta that yields no pairs.
    """
    settings = settings or EvaluationSettings()
    matched = associate(
        reference, estimate, max_diff=settings.t_max_diff, offset=settings.t_offset, interpolate=settings.interpolate
    )
    sparser = min(len(reference), len(estimate))
    if len(matched) < settings.min_matched_fraction * sparser:
        raise EvaluationError(
            f"only {len(matched)} of {sparser} poses matched ({100 * len(matched) / sparser:.0f} %): reference "
            f"{time_span(reference)}, estimate {time_span(estimate)}",
            "check that both come from the same run and clock (--t-offset, --t-max-diff), or accept a partial "
            "overlap with --min-matched 0",
        )
    alignment = estimate_alignment(matched, settings.align, settings.n_to_align)
    aligned = apply_alignment(matched, alignment)

    stamps = aligned.estimate_stamps_ns
    summary: dict[str, float] = {
        "matched_poses": float(len(aligned)),
        "reference_poses": float(len(reference)),
        "estimate_poses": float(len(estimate)),
        "duration_s": float((stamps[-1] - stamps[0]) / 1e9),
        "path_length_m": float(accumulated_distances(aligned.reference_positions)[-1]),
        "alignment_scale": float(alignment.scale),
    }
    ape_translation = ape_errors(aligned, PoseRelation.TRANS_PART)
    ape_rotation = ape_errors(aligned, PoseRelation.ANGLE_DEG)
    reuse = {PoseRelation.TRANS_PART: ape_translation, PoseRelation.ANGLE_DEG: ape_rotation}
    ape_selected = reuse.get(settings.pose_relation)
    if ape_selected is None:
        ape_selected = ape_errors(aligned, settings.pose_relation)
    summary |= _prefixed("ate", ape_translation) | _prefixed("ape_rot_deg", ape_rotation)
    summary |= _prefixed("ape", ape_selected)

    rpe_kwargs = {
        "delta": settings.delta,
        "delta_unit": settings.delta_unit,
        "rel_tol": settings.delta_tol,
        "all_pairs": settings.all_pairs,
        "pairs_from_reference": settings.pairs_from_reference,
    }
    rpe_t = rpe_r = rpe_sel = None
    notes: list[str] = []
    if settings.rpe:
        try:
            rpe_t = rpe_errors(aligned, PoseRelation.TRANS_PART, **rpe_kwargs)
        except EvaluationError as error:  # too few or too close poses for the delta: the APE still stands
            notes.append(f"{error.message}: no RPE figures")
            summary["rpe_pairs"] = 0.0
    if rpe_t is not None:
        rpe_r = rpe_errors(aligned, PoseRelation.ANGLE_DEG, **rpe_kwargs)
        rpe_sel = {PoseRelation.TRANS_PART: rpe_t, PoseRelation.ANGLE_DEG: rpe_r}.get(settings.pose_relation)
        if rpe_sel is None:
            rpe_sel = rpe_errors(aligned, settings.pose_relation, **rpe_kwargs)
        summary["rpe_pairs"] = float(len(rpe_t))
        summary |= _prefixed("rpe_trans", rpe_t.errors) | _prefixed("rpe_rot_deg", rpe_r.errors)
        summary |= _prefixed("rpe", rpe_sel.errors)

    kitti = None
    if settings.kitti:
        kitti = kitti_segment_errors(aligned, settings.kitti_lengths, settings.kitti_step)
        summary["kitti_segments"] = float(len(kitti))
        if len(kitti):
            summary["kitti_t_err_pct"] = kitti.translation_percent
            summary["kitti_r_err_deg_per_100m"] = kitti.rotation_deg_per_100m

    return EvaluationResult(
        summary=summary,
        settings=settings,
        matched=aligned,
        alignment=alignment,
        stamps_ns=np.asarray(stamps),
        ape_translation=ape_translation,
        ape_rotation_deg=ape_rotation,
        ape=ape_selected,
        rpe_translation=rpe_t,
        rpe_rotation_deg=rpe_r,
        rpe=rpe_sel,
        kitti=kitti,
        notes=tuple(notes),
    )


#: The first poses' offset must exceed this many times the SE(3)-aligned error to suggest an alignment.
FRAME_MISMATCH_FACTOR = 3.0


def frame_mismatch(result: EvaluationResult) -> str | None:
    """Why the estimate looks to be in another frame than the reference, or None.

    Only for an unaligned evaluation: when the first matched poses differ (in position or heading) by
    far more than the error left after an SE(3) alignment (the noise of the estimate), and by more than
    5 cm and 1 % of the path (or 10 degrees), the two
    trajectories start in different frames (``/odom`` against ``/amcl_pose``, a dense run started at
    the identity) and the unaligned figures measure that offset, not the estimate.
    """
    if result.settings.align is not AlignMode.NONE or len(result.matched) < 3:
        return None
    matched = result.matched
    try:
        aligned = apply_alignment(matched, estimate_alignment(matched, AlignMode.SE3))
    except EvaluationError:  # degenerate (collinear or stationary) trajectories: nothing to compare
        return None
    noise_m = float(np.sqrt(np.mean(ape_errors(aligned, PoseRelation.TRANS_PART) ** 2)))
    noise_deg = float(np.sqrt(np.mean(ape_errors(aligned, PoseRelation.ANGLE_DEG) ** 2)))
    offset_m = float(np.linalg.norm(matched.estimate_positions[0] - matched.reference_positions[0]))
    relative = matched.reference_rotations[0].T @ matched.estimate_rotations[0]
    offset_deg = float(np.degrees(np.arccos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0))))
    # An offset under 5 cm or 1 % of the path does not change the figures' meaning, whatever the noise.
    floor_m = max(0.05, 0.01 * float(accumulated_distances(matched.reference_positions)[-1]))
    if offset_m > max(FRAME_MISMATCH_FACTOR * noise_m, floor_m) or offset_deg > max(
        FRAME_MISMATCH_FACTOR * noise_deg, 10.0
    ):
        return (
            f"the estimate's first pose is {offset_m:.3g} m and {offset_deg:.3g} deg from the reference's, far "
            f"beyond the {noise_m:.3g} m left after an SE(3) alignment: they look to be in different frames; "
            "evaluate with --align se3 (sim3 for a monocular scale)"
        )
    return None
