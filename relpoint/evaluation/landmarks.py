"""Landmark-map metrics against ground-truth landmarks (issue 3; the paper's landmark error, Figs. 8, 10, 11).

Kraut, *A Relative Point Algorithm*, Sec. "Results": the landmark error is the distance of each mapped
static landmark from the true landmark it stands for. Here the correspondence is the map's ``gt_id`` (the
majority ground-truth id of the observations fused into a landmark), never a nearest-neighbour guess, so a
wrong association shows up as error and impurity rather than being hidden.

Definitions (all over the map's landmarks):

* *matched*: not flagged dynamic and ``gt_id`` names a static ground-truth landmark;
* *error*: ``|p_est - p_gt|`` of matched landmarks, raw (the estimate's world frame) and, when an
  :class:`~relpoint.evaluation.alignment.Alignment` is given, after mapping ``p_est`` with it;
* *mapped fraction*: distinct static ground-truth ids matched / static ground-truth landmarks
  (or / ``observed_ids`` that are static, when given);
* *duplicates*: matched landmarks beyond the first for each ``gt_id``;
* *false landmarks*: not flagged dynamic, with ``gt_id`` -1 (clutter or unknown) or not in the ground truth;
* *purity*: per-landmark share of fused observations that carry the majority id (supplied by the
  estimator), mean and observation-weighted mean;
* *dynamic precision / recall*: a landmark is truly dynamic when its ``gt_id`` names a dynamic ground-truth
  landmark (clutter counts as not dynamic); predicted dynamic is the map's ``dynamic`` flag.

Undefined ratios (nothing to divide by) are NaN.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from relpoint.evaluation.alignment import Alignment
from relpoint.geometry import FloatArray
from relpoint.types import GroundTruthLandmarks, IntArray, LandmarkMap

NAN = float("nan")


def precision_recall(predicted: npt.ArrayLike, truth: npt.ArrayLike) -> tuple[float, float]:
    """Precision and recall of boolean predictions (N,) against boolean truth (N,); NaN when undefined."""
    p = np.asarray(predicted, dtype=bool).reshape(-1)
    t = np.asarray(truth, dtype=bool).reshape(-1)
    if p.shape != t.shape:
        raise ValueError(f"predicted {p.shape} and truth {t.shape} differ in shape")
    tp = int(np.count_nonzero(p & t))
    n_pred = int(np.count_nonzero(p))
    n_true = int(np.count_nonzero(t))
    return (tp / n_pred if n_pred else NAN), (tp / n_true if n_true else NAN)


def _lookup(ground_truth: GroundTruthLandmarks, ids: IntArray) -> tuple[npt.NDArray[np.bool_], IntArray]:
    """For each id (N,): whether the ground truth has it, and its row there (0 where it has not)."""
    if len(ground_truth.ids) == 0:
        return np.zeros(len(ids), bool), np.zeros(len(ids), np.int64)
    order = np.argsort(ground_truth.ids, kind="stable")
    sorted_ids = ground_truth.ids[order]
    pos = np.clip(np.searchsorted(sorted_ids, ids), 0, len(sorted_ids) - 1)
    known = (sorted_ids[pos] == ids) & (ids >= 0)
    return known, np.where(known, order[pos], 0).astype(np.int64)


def dynamic_point_precision_recall(
    flagged_dynamic: npt.ArrayLike, point_ids: npt.ArrayLike, ground_truth: GroundTruthLandmarks
) -> tuple[float, float]:
    """Point-level dynamic detection: points (N,) flagged dynamic vs. their ground-truth landmark's flag.

    ``point_ids`` are the observations' ground-truth ids (-1 = clutter, counted as not dynamic).
    """
    ids = np.asarray(point_ids, dtype=np.int64).reshape(-1)
    known, row = _lookup(ground_truth, ids)
    truth = known & ground_truth.dynamic[row] if len(ground_truth.ids) else np.zeros(len(ids), bool)
    return precision_recall(flagged_dynamic, truth)


def _stats(errors: FloatArray) -> tuple[float, float, float]:
    if errors.size == 0:
        return NAN, NAN, NAN
    return float(np.sqrt(np.mean(errors**2))), float(np.mean(errors)), float(np.max(errors))


@dataclass(frozen=True, eq=False)
class LandmarkEvaluation:
    """Landmark metrics: a flat ``summary`` and per-matched-landmark arrays.

    Attributes
    ----------
    summary: flat name -> value (keys listed in ``docs/evaluation.md``).
    index: (K,) rows of the matched landmarks in the map.
    gt_id: (K,) their ground-truth ids.
    error: (K,) raw error, metres.
    error_aligned: (K,) error after the alignment, metres (empty when no alignment was given).
    """

    summary: dict[str, float]
    index: IntArray
    gt_id: IntArray
    error: FloatArray
    error_aligned: FloatArray = field(default_factory=lambda: np.zeros(0))


def landmark_metrics(
    landmarks: LandmarkMap,
    ground_truth: GroundTruthLandmarks,
    *,
    alignment: Alignment | None = None,
    purity: npt.ArrayLike | None = None,
    observed_ids: npt.ArrayLike | None = None,
) -> LandmarkEvaluation:
    """Evaluate an estimated landmark map against the ground truth (see the module docstring).

    Parameters
    ----------
    landmarks:
        The estimated map, positions in the estimate's ``world``.
    ground_truth:
        True landmarks in the reference ``world``.
    alignment:
        The trajectory alignment (estimate -> reference) to also report the error after it.
    purity:
        Optional per-landmark association purity (M,), each in [0, 1].
    observed_ids:
        Optional ids of the ground-truth landmarks that were ever observed; the mapped fraction is then
        taken over those instead of all static ones.

    A ground truth whose ids repeat (:func:`ground_truth_ids_unique`) is evaluated as a map without
    ids: the id-based figures are NaN and ``lm_nn_*`` stand in.
    """
    m = len(landmarks)
    if not ground_truth_ids_unique(ground_truth):
        # One id names several true landmarks: no landmark can be told which one it stands for.
        landmarks = dataclasses.replace(landmarks, gt_id=np.full(m, -1, dtype=np.int64))
    known, row = _lookup(ground_truth, landmarks.gt_id)
    gt_dynamic = ground_truth.dynamic[row] & known if len(ground_truth.ids) else np.zeros(m, bool)
    static_est = ~landmarks.dynamic
    matched = static_est & known & ~gt_dynamic
    index = np.nonzero(matched)[0].astype(np.int64)
    gt_rows = row[index]
    est_positions = landmarks.positions[index]
    gt_positions = ground_truth.positions[gt_rows]
    error = np.linalg.norm(est_positions - gt_positions, axis=1)

    summary: dict[str, float] = {"lm_count": float(m), "lm_matched": float(index.size)}
    summary["lm_err_rmse"], summary["lm_err_mean"], summary["lm_err_max"] = _stats(error)
    error_aligned = np.zeros(0)
    if alignment is not None:
        error_aligned = np.linalg.norm(alignment.apply_positions(est_positions) - gt_positions, axis=1)
        rmse, mean, maximum = _stats(error_aligned)
        summary.update(lm_err_aligned_rmse=rmse, lm_err_aligned_mean=mean, lm_err_aligned_max=maximum)

    static_gt_ids = ground_truth.ids[~ground_truth.dynamic]
    if observed_ids is not None:
        static_gt_ids = np.intersect1d(static_gt_ids, np.asarray(observed_ids, dtype=np.int64))
    mapped_ids = np.unique(landmarks.gt_id[index])
    summary["lm_mapped_fraction"] = (
        float(np.intersect1d(mapped_ids, static_gt_ids).size / static_gt_ids.size) if static_gt_ids.size else NAN
    )
    summary["lm_duplicates"] = float(index.size - mapped_ids.size)
    summary["lm_false"] = float(np.count_nonzero(static_est & ~known))

    if purity is not None:
        purity_arr = np.asarray(purity, dtype=np.float64).reshape(-1)
        if purity_arr.shape != (m,):
            raise ValueError(f"purity must have one value per landmark ({m}), got shape {purity_arr.shape}")
        weights = landmarks.observations.astype(np.float64)
        summary["lm_purity_mean"] = float(np.mean(purity_arr)) if m else NAN
        summary["lm_purity_weighted"] = float(np.sum(purity_arr * weights) / np.sum(weights)) if weights.sum() else NAN

    # Without movers in the ground truth there is nothing to detect: the figures do not apply.
    precision, recall = precision_recall(landmarks.dynamic, gt_dynamic) if ground_truth.dynamic.any() else (NAN, NAN)
    summary["dyn_precision"], summary["dyn_recall"] = precision, recall
    if m and not np.any(landmarks.gt_id >= 0):
        summary |= _without_ids(landmarks, ground_truth, alignment)
    return LandmarkEvaluation(summary, index, landmarks.gt_id[index], error, error_aligned)


def ground_truth_ids_unique(ground_truth: GroundTruthLandmarks) -> bool:
    """Whether every true landmark has an id of its own (a log may reuse an id for another landmark once
    the first left view; then the ids say nothing of which true landmark an estimate stands for)."""
    return len(np.unique(ground_truth.ids)) == len(ground_truth.ids)


def has_ground_truth_ids(landmarks: LandmarkMap) -> bool:
    """Whether any landmark names a ground-truth id (a log whose clouds carry no ``id`` field gives none)."""
    return bool(np.any(landmarks.gt_id >= 0))


def _without_ids(
    landmarks: LandmarkMap, ground_truth: GroundTruthLandmarks, alignment: Alignment | None
) -> dict[str, float]:
    """A map without ground-truth ids: the id-based figures are undefined (NaN, not "every landmark
    false"), and each static landmark's distance to the nearest static true landmark stands in
    (``lm_nn_*``, raw and after the alignment; a nearest-neighbour figure, which hides a wrong
    association that lands near another landmark)."""
    from scipy.spatial import cKDTree  # here, not at import: only maps without ids need it

    summary = {key: NAN for key in ("lm_mapped_fraction", "lm_duplicates", "lm_false", "dyn_precision", "dyn_recall")}
    static = ~landmarks.dynamic
    truth = ground_truth.positions[~ground_truth.dynamic]
    if not static.any() or len(truth) == 0:
        return summary
    tree = cKDTree(truth)
    positions = landmarks.positions[static]
    summary["lm_nn_rmse"], summary["lm_nn_mean"], summary["lm_nn_max"] = _stats(tree.query(positions)[0])
    if alignment is not None:
        aligned = tree.query(alignment.apply_positions(positions))[0]
        summary["lm_nn_aligned_rmse"], summary["lm_nn_aligned_mean"], summary["lm_nn_aligned_max"] = _stats(aligned)
    return summary
