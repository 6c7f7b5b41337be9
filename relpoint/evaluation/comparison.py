"""Evaluation results of several runs side by side: the data ``relpoint compare`` tabulates and plots.

A :class:`ComparedRun` is what is known of one run's evaluation: a label, the estimator and the
alignment when known, the flat summary of :func:`relpoint.evaluation.evaluate_trajectory` (plus the
landmark figures), and per-pose error series for distribution and over-time plots. It is built from a
fresh :class:`~relpoint.evaluation.EvaluationResult` (:func:`compared_from_evaluation`) or by the readers
in :mod:`formats` from saved results (relpoint's JSON summary, evo result zips), which may carry a
summary without series, or a single series.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from relpoint.evaluation.evaluate import EvaluationResult
from relpoint.geometry import FloatArray

#: Error series a comparison knows: key -> (axis label, summary prefix of its statistics).
SERIES: dict[str, tuple[str, str]] = {
    "ape_trans": ("APE translation (m)", "ate"),
    "ape_rot": ("APE rotation (deg)", "ape_rot_deg"),
    "rpe_trans": ("RPE translation (m)", "rpe_trans"),
    "rpe_rot": ("RPE rotation (deg)", "rpe_rot_deg"),
}

#: Summary keys of the default comparison table, in column order (absent ones are left out).
DEFAULT_KEYS: tuple[str, ...] = (
    "matched_poses",
    "ate_rmse",
    "ate_mean",
    "ate_median",
    "ate_std",
    "ate_max",
    "ape_rot_deg_rmse",
    "rpe_trans_rmse",
    "rpe_rot_deg_rmse",
    "lm_count",
    "lm_err_rmse",
    "lm_err_aligned_rmse",
    "lm_mapped_fraction",
    "dyn_precision",
    "dyn_recall",
)


@dataclass(frozen=True)
class ErrorSeries:
    """One error per pose (APE) or per pose pair (RPE, at the pair's second pose).

    Attributes
    ----------
    seconds: (N,) float64 time since the first matched pose, s.
    errors: (N,) float64 errors in the unit of the series (:data:`SERIES`).
    """

    seconds: FloatArray
    errors: FloatArray

    def __post_init__(self) -> None:
        seconds = np.asarray(self.seconds, dtype=np.float64).reshape(-1)
        errors = np.asarray(self.errors, dtype=np.float64).reshape(-1)
        if len(seconds) != len(errors):
            raise ValueError(f"{len(seconds)} times for {len(errors)} errors")
        object.__setattr__(self, "seconds", seconds)
        object.__setattr__(self, "errors", errors)

    def __len__(self) -> int:
        return len(self.errors)


@dataclass(frozen=True)
class ComparedRun:
    """One row of a comparison.

    Attributes
    ----------
    label: how the run is named in tables and legends (unique within a comparison).
    estimator: the estimator's name, "" when the source does not say.
    align: the alignment of the figures (``none``, ``se3``, ...), "" when unknown.
    summary: flat summary key -> value (``docs/evaluation.md``); NaN for undefined values.
    series: :data:`SERIES` key -> per-pose errors, for the runs whose source holds them.
    source: where the figures came from (a path and its kind), for the JSON table.
    """

    label: str
    estimator: str = ""
    align: str = ""
    summary: Mapping[str, float] = field(default_factory=dict)
    series: Mapping[str, ErrorSeries] = field(default_factory=dict)
    source: str = ""


def compared_from_evaluation(
    label: str,
    result: EvaluationResult,
    summary: Mapping[str, float] | None = None,
    *,
    estimator: str = "",
    source: str = "",
) -> ComparedRun:
    """A :class:`ComparedRun` of a fresh evaluation: its summary (or ``summary``, e.g. with landmark
    figures added) and the APE and RPE translation and rotation series."""
    seconds = (result.stamps_ns - result.stamps_ns[0]) * 1e-9 if len(result.stamps_ns) else np.zeros(0)
    series = {
        "ape_trans": ErrorSeries(seconds, result.ape_translation),
        "ape_rot": ErrorSeries(seconds, result.ape_rotation_deg),
    }
    if result.rpe_translation is not None:
        series["rpe_trans"] = ErrorSeries(seconds[result.rpe_translation.second], result.rpe_translation.errors)
    if result.rpe_rotation_deg is not None:
        series["rpe_rot"] = ErrorSeries(seconds[result.rpe_rotation_deg.second], result.rpe_rotation_deg.errors)
    return ComparedRun(
        label=label,
        estimator=estimator,
        align=result.settings.align.value,
        summary=dict(result.summary if summary is None else summary),
        series=series,
        source=source,
    )


def table_keys(runs: Sequence[ComparedRun], keys: Sequence[str] | None = None) -> list[str]:
    """The summary keys to tabulate: ``keys`` as given, or the :data:`DEFAULT_KEYS` that any run has."""
    if keys is not None:
        return list(keys)
    present = {key for run in runs for key in run.summary}
    return [key for key in DEFAULT_KEYS if key in present]


def table_rows(runs: Sequence[ComparedRun], keys: Sequence[str]) -> list[dict[str, Any]]:
    """One mapping per run: ``run``, ``estimator``, ``align``, then each key's value (None where the
    run lacks it; NaN stays NaN)."""
    rows = []
    for run in runs:
        row: dict[str, Any] = {"run": run.label, "estimator": run.estimator, "align": run.align}
        for key in keys:
            value = run.summary.get(key)
            row[key] = None if value is None else float(value)
        rows.append(row)
    return rows


def unique_labels(names: Sequence[str]) -> list[str]:
    """``names`` with repeats told apart by a ``#2``, ``#3``... suffix, in order."""
    seen: dict[str, int] = {}
    labels = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        labels.append(name if seen[name] == 1 else f"{name}#{seen[name]}")
    return labels

