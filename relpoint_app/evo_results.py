"""relpoint's evaluation results as evo result files (:mod:`formats.evo_results`), and evo's results as
:class:`~relpoint.evaluation.comparison.ComparedRun` rows for ``relpoint compare``.

The APE and RPE are saved as ``evo_ape`` / ``evo_rpe ... --save_results`` save them: evo's title, labels
and arrays, plus a ``relpoint`` object in ``info.json`` with the whole summary, the settings, the
estimator and relpoint's version, so that ``relpoint compare`` reads every figure back.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

import relpoint
from formats.evo_results import EvoResult, tum_text
from relpoint.evaluation import STATISTICS, AlignMode, EvaluationResult, PoseRelation, error_statistics
from relpoint.evaluation.association import stamps_to_seconds
from relpoint.evaluation.comparison import ComparedRun, ErrorSeries
from relpoint.evaluation.evaluate import with_counts
from relpoint.evaluation.rpe import DeltaUnit, accumulated_distances


def _tum_text(stamps_ns: np.ndarray, positions: np.ndarray, rotations: np.ndarray) -> str:
    """TUM lines of poses given as stamps (ns), positions (N, 3) and rotation matrices (N, 3, 3)."""
    from scipy.spatial.transform import Rotation

    quats_xyzw = Rotation.from_matrix(rotations).as_quat() if len(rotations) else np.zeros((0, 4))
    return tum_text(stamps_to_seconds(stamps_ns), positions, quats_xyzw)


#: relpoint's pose relations as evo names them (``evo.core.metrics.PoseRelation`` values) and their units.
EVO_RELATIONS: dict[PoseRelation, tuple[str, str]] = {
    PoseRelation.FULL: ("full transformation", "unit-less"),
    PoseRelation.TRANS_PART: ("translation part", "m"),
    PoseRelation.ROT_PART: ("rotation part", "unit-less"),
    PoseRelation.ANGLE_DEG: ("rotation angle in degrees", "deg"),
    PoseRelation.ANGLE_RAD: ("rotation angle in radians", "rad"),
    PoseRelation.POINT_DISTANCE: ("point distance", "m"),
    PoseRelation.POINT_DISTANCE_ERROR_RATIO: ("point distance error ratio", "%"),  # RPE only
}

#: relpoint's RPE delta units as evo names them (``evo.core.metrics.Unit`` values).
_EVO_DELTA_UNITS = {DeltaUnit.FRAMES: "frames", DeltaUnit.METERS: "m", DeltaUnit.DEGREES: "deg",
                    DeltaUnit.RADIANS: "rad"}  # fmt: skip

#: evo's title line of each alignment (``evo.main_ape.ape``).
_ALIGN_TITLES = {
    AlignMode.NONE: "(not aligned)",
    AlignMode.SE3: "(with SE(3) Umeyama alignment)",
    AlignMode.SIM3: "(with Sim(3) Umeyama alignment)",
    AlignMode.SCALE: "(scale corrected)",
    AlignMode.ORIGIN: "(with origin alignment)",
}


def ape_result(
    result: EvaluationResult,
    *,
    reference_name: str = "reference",
    estimate_name: str = "estimate",
    summary: Mapping[str, float] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> EvoResult:
    """The APE of ``result`` in its settings' pose relation, as ``evo_ape ... --save_results`` saves it.

    ``summary`` (default: the result's own) and ``extra`` (e.g. the estimator's name) go into
    ``info["relpoint"]``, so that ``relpoint compare`` reads back every figure, landmarks included.
    """
    settings = result.settings
    relation, unit = EVO_RELATIONS[settings.pose_relation]
    title = f"APE w.r.t. {relation} ({unit})\n{_align_title(result)}"
    matched = result.matched
    stamps_s = stamps_to_seconds(result.stamps_ns)  # the floats evo parses from the same stamps
    arrays = {
        "error_array": np.asarray(result.ape, dtype=np.float64),
        "seconds_from_start": stamps_s - stamps_s[0],
        "timestamps": stamps_s,
        "distances_from_start": accumulated_distances(matched.reference_positions),
        "distances": accumulated_distances(matched.estimate_positions),
    }
    if settings.align is not AlignMode.NONE:
        arrays["alignment_transformation_sim3"] = result.alignment.as_matrix()
    relpoint_info = _relpoint_info(result, "ape", summary, extra)
    info = {"title": title, "ref_name": reference_name, "est_name": estimate_name, "label": f"APE ({unit})",
            "relpoint": relpoint_info}  # fmt: skip
    trajectories = {
        reference_name: _tum_text(
            matched.reference_stamps_ns, matched.reference_positions, matched.reference_rotations
        ),
        estimate_name: _tum_text(matched.estimate_stamps_ns, matched.estimate_positions, matched.estimate_rotations),
    }
    return EvoResult(info=info, stats=error_statistics(result.ape), arrays=arrays, trajectories=trajectories)


def _align_title(result: EvaluationResult) -> str:
    settings = result.settings
    title = _ALIGN_TITLES[settings.align]
    if settings.align in (AlignMode.SE3, AlignMode.SIM3, AlignMode.SCALE) and settings.n_to_align != -1:
        title += f" (aligned poses: {settings.n_to_align})"
    return title


def rpe_result(
    result: EvaluationResult,
    *,
    reference_name: str = "reference",
    estimate_name: str = "estimate",
    summary: Mapping[str, float] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> EvoResult:
    """The RPE of ``result`` in its settings' pose relation, as ``evo_rpe ... --save_results`` saves it.

    As in evo, the arrays and trajectories hold the pairs' second poses (with the first matched pose
    prepended to the trajectories and the travelled distances measured along them). Raises
    ``ValueError`` when the result has no RPE.
    """
    rpe = result.rpe
    if rpe is None:
        raise ValueError("the evaluation computed no RPE")
    settings = result.settings
    relation, unit = EVO_RELATIONS[settings.pose_relation]
    delta = int(settings.delta) if settings.delta_unit is DeltaUnit.FRAMES else settings.delta
    title = (f"RPE w.r.t. {relation} ({unit})\nfor delta = {delta} ({_EVO_DELTA_UNITS[settings.delta_unit]})"
             f" using {'all' if settings.all_pairs else 'consecutive'} pairs\n{_align_title(result)}")  # fmt: skip
    matched = result.matched
    ids = np.concatenate(([0], rpe.second))
    stamps_s = stamps_to_seconds(result.stamps_ns[ids])
    arrays = {
        "error_array": np.asarray(rpe.errors, dtype=np.float64),
        "seconds_from_start": (stamps_s - stamps_s[0])[1:],
        "timestamps": stamps_s[1:],
        "distances_from_start": accumulated_distances(matched.reference_positions[ids])[1:],
        "distances": accumulated_distances(matched.estimate_positions[ids])[1:],
    }
    if settings.align is not AlignMode.NONE:
        arrays["alignment_transformation_sim3"] = result.alignment.as_matrix()
    info = {"title": title, "ref_name": reference_name, "est_name": estimate_name, "label": f"RPE ({unit})",
            "relpoint": _relpoint_info(result, "rpe", summary, extra)}  # fmt: skip
    trajectories = {
        reference_name: _tum_text(matched.reference_stamps_ns[ids], matched.reference_positions[ids],
                                  matched.reference_rotations[ids]),
        estimate_name: _tum_text(matched.estimate_stamps_ns[ids], matched.estimate_positions[ids],
                                 matched.estimate_rotations[ids]),
    }  # fmt: skip
    return EvoResult(info=info, stats=error_statistics(rpe.errors), arrays=arrays, trajectories=trajectories)


def _relpoint_info(
    result: EvaluationResult, metric: str, summary: Mapping[str, float] | None, extra: Mapping[str, Any] | None
) -> dict[str, Any]:
    """What relpoint adds to ``info.json``: its version, the metric, settings, the whole summary (counts as
    integers), ``extra``."""
    settings = result.settings
    counted = with_counts(summary or result.summary)
    return {
        "version": relpoint.__version__,
        "metric": metric,
        "pose_relation": settings.pose_relation.value,
        "settings": settings.to_dict(),
        "summary": {k: (None if not math.isfinite(v) else v) for k, v in counted.items()},
        **(extra or {}),
    }


def _metric_of(info: Mapping[str, Any]) -> tuple[str, str]:
    """``(metric, relation)`` of an evo result from its title, e.g. ``("ape", "translation part")``."""
    title = str(info.get("title", ""))
    metric = "rpe" if title.startswith("RPE") else "ape"
    relation = title.partition("w.r.t. ")[2].split(" (")[0].split("\n")[0].strip()
    return metric, relation


def _summary_prefix(metric: str, relation: str) -> tuple[str, str | None]:
    """The summary prefix of an evo metric (``ate``, ``rpe_rot_deg``, ...) and its series key, if any."""
    if relation in ("translation part", "point distance") and metric == "ape":
        return "ate", "ape_trans"
    if relation == "translation part":
        return "rpe_trans", "rpe_trans"
    if relation == "rotation angle in degrees":
        return f"{metric}_rot_deg", f"{metric}_rot"
    return metric, None


def _align_of(title: str) -> str:
    for mode, line in _ALIGN_TITLES.items():
        if line in title:
            return mode.value
    return ""


def compared_from_evo(label: str, evo_result: EvoResult, source: str = "") -> ComparedRun:
    """A :class:`ComparedRun` of an evo result.

    A zip relpoint wrote carries the whole summary (landmarks included). A zip evo wrote gives the
    statistics of its one metric under relpoint's key names (``ate_*`` for APE translation part,
    ``rpe_rot_deg_*`` for RPE rotation angle in degrees, ``ape_*`` / ``rpe_*`` for other relations);
    its ``error_array`` over ``seconds_from_start`` becomes the matching series.
    """
    info = evo_result.info
    ours = info.get("relpoint") if isinstance(info.get("relpoint"), dict) else {}
    metric, relation = _metric_of(info)
    prefix, series_key = _summary_prefix(metric, relation)
    summary: dict[str, float] = {f"{prefix}_{name}": float(evo_result.stats[name]) for name in STATISTICS
                                 if name in evo_result.stats}  # fmt: skip
    errors = evo_result.arrays.get("error_array")
    if errors is not None and errors.ndim == 1:
        summary.setdefault("matched_poses" if metric == "ape" else "rpe_pairs", float(len(errors)))
    if isinstance(ours.get("summary"), dict):
        summary |= {str(k): (math.nan if v is None else float(v)) for k, v in ours["summary"].items()}
    series = {}
    seconds = evo_result.arrays.get("seconds_from_start")
    if series_key is not None and errors is not None and errors.ndim == 1:
        if seconds is None or seconds.shape != errors.shape:
            seconds = np.arange(len(errors), dtype=np.float64)  # evo's own fallback: the index
        series[series_key] = ErrorSeries(seconds, errors)
    settings = ours.get("settings") if isinstance(ours.get("settings"), dict) else {}
    return ComparedRun(
        label=label,
        estimator=str(ours.get("estimator") or ""),
        align=str(settings.get("align") or _align_of(str(info.get("title", "")))),
        summary=summary,
        series=series,
        source=source,
    )
