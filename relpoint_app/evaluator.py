"""Evaluating an estimate against a reference: the trajectory and, where both sides have them, the landmarks.

``relpoint evaluate`` and ``relpoint compare`` call :func:`evaluate_files`; scripts call
:func:`evaluate` (also ``relpoint.evaluate``) on a :class:`relpoint.pipeline.RunResult` or a path.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import relpoint
from formats.atomic import write_text
from formats.outputs import json_text, register_csv_header
from formats.ply import read_ply
from formats.reference_trajectories import (
    assumed_quaternion_order,
    check_index_pairing,
    is_index_stamped,
    load_ground_truth_landmarks,
    load_landmark_map,
    load_trajectory,
    with_quaternion_order,
)
from formats.tables import read_map_history_csv
from relpoint.errors import InputError, UsageError
from relpoint.evaluation import AlignMode, EvaluationResult, EvaluationSettings, evaluate_trajectory, landmark_metrics
from relpoint.evaluation.dense import dense_metrics
from relpoint.evaluation.evaluate import frame_mismatch, with_counts
from relpoint.evaluation.landmarks import ground_truth_ids_unique, has_ground_truth_ids
from relpoint.geometry import FloatArray
from relpoint.pipeline import RunResult
from relpoint.types import GroundTruthLandmarks, LandmarkMap, TimeWindow, Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FileEvaluation:
    """What ``relpoint evaluate`` computes from its input files (before writing anything).

    Attributes
    ----------
    reference: the reference trajectory as read (its own frame).
    result: the trajectory evaluation.
    summary: the result's summary plus the landmark figures (``lm_*``, ``dyn_*``) when both sides have them.
    landmarks, truth: the run's map (estimate frame) and the log's true landmarks, when present.
    landmark_error_over_time: stamp (ns) -> landmark RMSE (m) of each ``map_history.csv`` snapshot.
    """

    reference: Trajectory
    result: EvaluationResult
    summary: dict[str, float]
    landmarks: LandmarkMap | None = None
    truth: GroundTruthLandmarks | None = None
    landmark_error_over_time: dict[int, float] = field(default_factory=dict)


def evaluate_files(
    estimate: Path,
    reference: Path,
    settings: EvaluationSettings,
    *,
    reference_topic: str | None = None,
    estimate_topic: str | None = None,
    parent: str | None = None,
    child: str | None = None,
    estimate_parent: str | None = None,
    estimate_child: str | None = None,
    reference_times: Path | None = None,
    times: Path | None = None,
    window: TimeWindow | None = None,
    landmarks_topic: str | None = None,
) -> FileEvaluation:
    """Read ESTIMATE and the reference as ``relpoint evaluate`` does and evaluate them (trajectory, and
    landmarks when ESTIMATE is a run directory with map.csv and the reference a log with true landmarks,
    on ``landmarks_topic`` if given). ``parent``/``child`` read the reference, ``estimate_parent``/
    ``estimate_child`` the estimate, from a TF chain of a bag (its TF topic: ``reference_topic``,
    ``estimate_topic``)."""
    ref = load_trajectory(reference, topic=reference_topic, parent=parent, child=child, times=reference_times)
    est = load_trajectory(estimate, topic=estimate_topic, parent=estimate_parent, child=estimate_child, times=times)
    check_index_pairing(
        (reference, ref, is_index_stamped(reference, reference_times)),
        (estimate, est, is_index_stamped(estimate, times)),
    )
    if window is not None and not window.is_open:  # both cropped to the same stretch of the reference's time
        first_ns = int(ref.stamps_ns[0])
        ref, est = ref.cropped(window), est.cropped(window, first_ns)
        if len(ref) == 0 or len(est) == 0:
            raise InputError(
                f"--t-start/--t-end leave {len(ref)} reference and {len(est)} estimated poses",
                "the window counts seconds from the reference's first pose",
            )
    landmarks = load_landmark_map(estimate)
    # A topic the user named is checked even when the estimate has no map to compare with it.
    wanted = landmarks is not None or landmarks_topic is not None
    truth = load_ground_truth_landmarks(reference, landmarks_topic) if wanted else None
    history = estimate / "map_history.csv"
    snapshots = read_map_history_csv(history) if landmarks is not None and history.is_file() else []
    evaluation = measure(ref, est, settings, landmarks=landmarks, truth=truth, snapshots=snapshots)
    _check_quaternion_order(evaluation, ref, est, reference, estimate, settings)
    return evaluation


#: An aligned rotation error (RMSE, degrees) above this from a file whose quaternion order its format
#: assumed is tried with the other order (:func:`_check_quaternion_order`).
ORDER_CHECK_DEG = 60.0


def _check_quaternion_order(
    evaluation: FileEvaluation, ref: Trajectory, est: Trajectory, reference: Path, estimate: Path,
    settings: EvaluationSettings,
) -> None:  # fmt: skip
    """Warn when a text file read in its format's quaternion order (TUM x y z w, EuRoC w x y z; no header
    names the columns) leaves a rotation error above ``ORDER_CHECK_DEG`` that the other order would cut
    to a third or less: the values alone cannot tell the two orders apart, and files with the
    other order are common. The figures are left as read."""
    rotation = evaluation.summary.get("ape_rot_deg_rmse", math.nan)
    if not rotation > ORDER_CHECK_DEG:
        return
    for path, is_estimate in ((estimate, True), (reference, False)):
        read_as = assumed_quaternion_order(path)
        if read_as is None:
            continue
        other = "wxyz" if read_as == "xyzw" else "xyzw"
        pair = (ref, with_quaternion_order(est, read_as)) if is_estimate else (with_quaternion_order(ref, read_as), est)
        try:
            result = evaluate_trajectory(*pair, settings)
        except InputError:
            continue
        other_rotation = result.summary.get("ape_rot_deg_rmse", math.nan)
        if other_rotation <= rotation / 3.0:
            header = "#timestamp tx ty tz qw qx qy qz" if other == "wxyz" else "#timestamp tx ty tz qx qy qz qw"
            log.warning(
                "%s: read with its quaternions in the order %s (as its format has them), the rotation error is "
                "%.1f deg; with %s it would be %.1f deg. If the file holds %s, name its columns in a header line "
                "(%s); the figures here are as read",
                path, " ".join(read_as), rotation, " ".join(other), other_rotation, " ".join(other), header,
            )  # fmt: skip


def measure(
    reference: Trajectory,
    estimate: Trajectory,
    settings: EvaluationSettings,
    *,
    landmarks: LandmarkMap | None = None,
    truth: GroundTruthLandmarks | None = None,
    snapshots: Iterable[tuple[int, int, LandmarkMap]] = (),
) -> FileEvaluation:
    """Evaluate ``estimate`` against ``reference`` and, when both are given, ``landmarks`` against ``truth``.

    ``snapshots`` are ``(iteration, stamp_ns, map)`` of the map over the run (``map_history.csv``): each
    one's landmark RMSE goes into ``landmark_error_over_time``. A warning is logged when the two
    trajectories start in different frames (:func:`relpoint.evaluation.evaluate.frame_mismatch`).
    """
    result = evaluate_trajectory(reference, estimate, settings)
    if (mismatch := frame_mismatch(result)) is not None:
        log.warning("%s", mismatch)
    summary = dict(result.summary)
    over_time: dict[int, float] = {}
    if landmarks is not None and truth is not None:
        alignment = result.alignment if settings.align is not AlignMode.NONE else None
        summary |= landmark_metrics(landmarks, truth, alignment=alignment, purity=landmarks.purity).summary
        key = "lm_err_aligned_rmse" if alignment is not None else "lm_err_rmse"
        if not ground_truth_ids_unique(truth):
            repeated = len(truth.ids) - len(np.unique(truth.ids))
            log.warning("the ground truth's landmarks repeat ids (%d of %d ids name a landmark already named): "
                        "the id-based landmark figures are undefined; lm_nn_* give each landmark's distance to the "
                        "nearest true one", repeated, len(truth.ids))  # fmt: skip
            key = key.replace("lm_err", "lm_nn")
        elif len(landmarks) and not has_ground_truth_ids(landmarks):
            log.warning("the map's landmarks name no ground-truth id (the log's clouds carry no `id` field): the "
                        "id-based landmark figures are undefined; lm_nn_* give each landmark's distance to the "
                        "nearest true one")  # fmt: skip
            key = key.replace("lm_err", "lm_nn")
        for _, stamp_ns, snapshot in snapshots:
            if len(snapshot):
                over_time[stamp_ns] = landmark_metrics(snapshot, truth, alignment=alignment).summary.get(key, math.nan)
    return FileEvaluation(reference, result, summary, landmarks, truth, over_time)


def evaluate(
    estimate: RunResult | str | os.PathLike[str],
    reference: str | os.PathLike[str],
    *,
    align: str = "se3",
    reference_topic: str | None = None,
    **settings: Any,
) -> FileEvaluation:
    """Evaluate a run against a reference as ``relpoint evaluate`` does; the Python API.

    Parameters
    ----------
    estimate:
        A :class:`relpoint.pipeline.RunResult` (``relpoint.run``'s), or what ``relpoint evaluate``
        reads: a run directory, a TUM or KITTI file, or a log with a pose topic.
    reference:
        A log with ground truth (its true landmarks are used too), a TUM, EuRoC or KITTI file.
    align:
        none | se3 | sim3 | scale | origin.
    reference_topic:
        The reference's pose topic in a log (default: its ground truth).
    settings:
        Further :class:`relpoint.evaluation.EvaluationSettings` fields (``t_max_diff``, ``delta``, ...).

    Returns
    -------
    FileEvaluation
        ``summary`` holds ``ate_*``, ``ape_*``, ``rpe_*`` and, with landmarks on both sides,
        ``lm_*`` and ``dyn_*``; ``result`` the per-pose errors.
    """
    evaluation_settings = EvaluationSettings.from_mapping({"align": align, **settings})
    if not isinstance(estimate, RunResult):
        return evaluate_files(Path(estimate), Path(reference), evaluation_settings, reference_topic=reference_topic)
    ref = load_trajectory(reference, topic=reference_topic)
    truth = load_ground_truth_landmarks(reference) if len(estimate.landmarks) else None
    return measure(ref, estimate.trajectory, evaluation_settings, landmarks=estimate.landmarks, truth=truth)


def evaluation_json(summary: dict[str, float], settings: EvaluationSettings, inputs: dict[str, Any]) -> str:
    """The text of ``evaluation.json`` (``relpoint evaluate --json``): the summary (counts as integers,
    NaN and inf as null), the settings, the inputs and the relpoint version."""
    document = {"summary": with_counts(summary), "settings": settings.to_dict(), "inputs": inputs,
                "relpoint_version": relpoint.__version__}  # fmt: skip
    return json_text(document, indent=2, sort_keys=True) + "\n"


def run_estimator(path: Path) -> str:
    """The estimator named in a run directory's run.json ("" for other inputs or an unreadable run.json)."""
    run_json = path / "run.json"
    if not run_json.is_file():
        return ""
    try:
        document = json.loads(run_json.read_text(encoding="utf-8")[:10_000_000])
    except (OSError, ValueError):
        return ""
    return str(document.get("estimator", "")) if isinstance(document, dict) else ""


#: Families of summary keys that only some evaluations have (landmarks, dense maps, KITTI segments of
#: a long enough path, an RPE with pose pairs): a gate on one that this evaluation did not measure fails
#: like a NaN, so that one CI gate serves short and long runs alike, instead of being a usage error.
MEASURED_SOMETIMES = ("rpe_", "kitti_", "lm_", "dyn_", "dense_")


def _apart(value: float, bound: float) -> tuple[str, str]:
    """``value`` and ``bound`` with 6 significant digits, or as many more as it takes to tell them apart."""
    for digits in range(6, 18):
        shown = f"{value:.{digits}g}", f"{bound:.{digits}g}"
        if shown[0] != shown[1]:
            return shown
    return repr(value), repr(bound)


def check_gates(summary: dict[str, float], gates: dict[str, float]) -> list[str]:
    """Descriptions of the exceeded bounds (NaN values, and keys of :data:`MEASURED_SOMETIMES` this
    evaluation did not measure, fail); raises :class:`UsageError` for unknown keys."""
    unknown = sorted(k for k in gates if k not in summary and not k.startswith(MEASURED_SOMETIMES))
    if unknown:
        raise UsageError(
            f"--fail-above: unknown summary key(s) {', '.join(unknown)}",
            f"known keys: {', '.join(sorted(summary))}",
        )
    return [
        "{}={} > {}".format(key, *_apart(summary[key], bound))
        if key in summary
        else f"{key} not measured (bound {bound:g})"
        for key, bound in gates.items()
        if key not in summary or math.isnan(summary[key]) or summary[key] > bound
    ]


def dense_map_clouds(
    estimate: Path, reference_cloud: Path, result: EvaluationResult, settings: EvaluationSettings
) -> tuple[FloatArray, FloatArray]:
    """A dense run's map points (N, 3), aligned as the trajectory was, and the reference cloud's (M, 3), m."""
    map_path = estimate / "map.ply"
    if not map_path.is_file():
        raise UsageError(f"--reference-cloud needs a run directory with a map.ply as ESTIMATE, not {estimate}")
    vertices = read_ply(map_path)
    reference = read_ply(reference_cloud)
    points = np.stack([vertices[a] for a in "xyz"], axis=1).astype(np.float64)
    if settings.align is not AlignMode.NONE:
        points = result.alignment.apply_positions(points)
    reference_points = np.stack([reference[a] for a in "xyz"], axis=1).astype(np.float64)
    return points, reference_points


def dense_map_summary(
    points: FloatArray, reference_points: FloatArray, threshold: float, on_progress: Callable[[int], None] | None = None
) -> dict[str, float]:
    """Accuracy and completeness (dense_* keys) of map points against a reference cloud (both (N, 3), m);
    ``on_progress(n)`` counts the points done, of both clouds together."""
    metrics = dense_metrics(points, reference_points, threshold=threshold, workers=-1, on_progress=on_progress)
    return metrics.summary()


ERRORS_CSV_HEADER = "stamp_s,ape_translation_m,ape_rotation_deg,ape,rpe_translation_m,rpe_rotation_deg,landmark_rmse_m"
register_csv_header(ERRORS_CSV_HEADER)


def write_errors_csv(path: Path, result: EvaluationResult, landmark_rmse: dict[int, float] | None = None) -> None:
    """:func:`errors_csv_text`, atomically to ``path``."""
    write_text(path, errors_csv_text(result, landmark_rmse))


def errors_csv_text(result: EvaluationResult, landmark_rmse: dict[int, float] | None = None) -> str:
    """Per matched pose: stamp, APE translation/rotation/relation, the RPE of the pair ending there, and
    the landmark RMSE at poses where the run recorded its map (``--map-every``).

    RPE columns are empty for poses that end no pair (with ``--all-pairs`` or deltas in metres or degrees
    several pairs can share a last pose; the last such pair is written).
    """
    n = len(result.stamps_ns)
    rpe_t = np.full(n, np.nan)
    rpe_r = np.full(n, np.nan)
    if result.rpe_translation is not None and result.rpe_rotation_deg is not None:
        rpe_t[result.rpe_translation.second] = result.rpe_translation.errors
        rpe_r[result.rpe_rotation_deg.second] = result.rpe_rotation_deg.errors
    landmark_rmse = landmark_rmse or {}
    header = ERRORS_CSV_HEADER + "\n"
    body = []
    for i, stamp in enumerate(result.stamps_ns.tolist()):
        seconds, nanos = divmod(int(stamp), 1_000_000_000)
        values = (result.ape_translation[i], result.ape_rotation_deg[i], result.ape[i], rpe_t[i], rpe_r[i],
                  landmark_rmse.get(int(stamp), math.nan))  # fmt: skip
        body.append(f"{seconds}.{nanos:09d}," + ",".join("" if math.isnan(v) else repr(float(v)) for v in values))
    return header + "\n".join(body) + ("\n" if body else "")
