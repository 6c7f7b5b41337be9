"""``relpoint compare``'s inputs: each RESULT read into a comparison row.

Each RESULT is read into a :class:`~relpoint.evaluation.comparison.ComparedRun`:

* a ``relpoint run`` output directory: evaluated against ``--reference`` when given; else against the
  reference its ``evaluation.json`` names (``relpoint batch`` writes one), with that file's settings;
  else against the log its ``run.json`` names (its ``/ground_truth/pose``), with ``--align``. When the
  reference is gone, the ``evaluation.json`` summary alone fills the table;
* an ``evaluate --json`` summary: its figures; re-evaluated with its settings when its estimate and
  reference still exist, for the plots;
* an evo result zip (``evo_ape``/``evo_rpe --save_results``, or ``evaluate --save-results``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from pathlib import Path
from typing import Any

from formats.evo_results import read_evo_result
from formats.outputs import unreadable_input
from relpoint.errors import InputError, RelpointError, UsageError
from relpoint.evaluation import EvaluationSettings
from relpoint.evaluation.comparison import ComparedRun, compared_from_evaluation
from relpoint.types import TimeWindow
from relpoint_app.evaluator import evaluate_files, run_estimator
from relpoint_app.evo_results import compared_from_evo
from relpoint_app.run_inputs import recorded_input, recorded_log

log = logging.getLogger(__name__)

_MAX_JSON_BYTES = 50_000_000


def _read_json(path: Path) -> dict[str, Any]:
    try:
        if path.stat().st_size > _MAX_JSON_BYTES:
            raise InputError(f"{path}: larger than {_MAX_JSON_BYTES >> 20} MB, not an evaluation summary")
        document = json.loads(path.read_text(encoding="utf-8"))
    except OSError as error:
        raise unreadable_input(path, error) from None
    except (ValueError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(document, dict) or not isinstance(document.get("summary"), dict):
        raise InputError(f"{path}: not a relpoint evaluation summary (no summary object)",
                         "give the file written by `relpoint evaluate --json`")  # fmt: skip
    return document


def _summary_of(document: dict[str, Any], path: Path) -> dict[str, float]:
    try:
        return {str(k): (math.nan if v is None else float(v)) for k, v in document["summary"].items()}
    except (TypeError, ValueError):
        raise InputError(f"{path}: malformed summary (values must be numbers or null)") from None


def _saved_settings(document: dict[str, Any], path: Path) -> EvaluationSettings:
    """The settings an evaluation summary was computed with (unknown fields ignored)."""
    saved = document.get("settings")
    known = {f.name for f in dataclasses.fields(EvaluationSettings)}
    try:
        return EvaluationSettings.from_mapping({k: v for k, v in (saved or {}).items() if k in known})
    except UsageError as error:
        raise InputError(f"{path}: malformed settings ({error})") from None


def _saved_window(inputs: dict[str, Any]) -> TimeWindow | None:
    """The ``--t-start``/``--t-end`` window an evaluation was made over (None: the whole of it)."""
    start, end = inputs.get("t_start"), inputs.get("t_end")
    numbers = [value for value in (start, end) if value is not None]
    if not all(isinstance(value, (int, float)) for value in numbers):
        return None
    try:
        return TimeWindow(start, end) if numbers else None
    except ValueError:
        return None


def _existing(text: Any) -> Path | None:
    return Path(text) if isinstance(text, str) and text and Path(text).exists() else None


def _from_saved_evaluation(label: str, path: Path, estimate: Path | None, document: dict[str, Any]) -> ComparedRun:
    """A run from an evaluation summary: its figures, and its per-pose errors re-computed with its settings
    when its inputs still exist (fresh figures overlay the saved ones; saved-only ones, e.g. ``dense_*``,
    stay). When they are gone or cannot be re-read, the saved figures alone, with a warning."""
    inputs = document.get("inputs") if isinstance(document.get("inputs"), dict) else {}
    settings = _saved_settings(document, path)
    summary = _summary_of(document, path)
    estimate = estimate or _existing(inputs.get("estimate"))
    reference = _existing(inputs.get("reference"))
    estimator = run_estimator(estimate) if estimate is not None else ""
    if not summary:
        log.warning("%s holds no evaluation figures (was there a ground truth?)", path)
    elif estimate is None or reference is None:
        missing = inputs.get("estimate") if estimate is None else inputs.get("reference")
        log.warning("%s: its %s (%s) is not readable here; only its summary is compared",
                    path, "estimate" if estimate is None else "reference", missing)  # fmt: skip
    elif any(inputs.get(key) and _existing(inputs.get(key)) is None for key in ("times", "reference_times")):
        log.warning("%s: its times files (%s, %s) are not readable here; only its summary is compared",
                    path, inputs.get("times"), inputs.get("reference_times"))  # fmt: skip
    else:
        try:
            evaluation = evaluate_files(
                estimate, reference, settings, reference_topic=inputs.get("reference_topic"),
                estimate_topic=inputs.get("estimate_topic"), parent=inputs.get("parent"), child=inputs.get("child"),
                estimate_parent=inputs.get("estimate_parent"), estimate_child=inputs.get("estimate_child"),
                times=_existing(inputs.get("times")), reference_times=_existing(inputs.get("reference_times")),
                window=_saved_window(inputs),
            )  # fmt: skip
        except RelpointError as error:
            log.warning("%s: cannot re-evaluate it (%s); only its summary is compared", path, error)
        else:
            return compared_from_evaluation(label, evaluation.result, summary | evaluation.summary,
                                            estimator=estimator, source=f"{path} (re-evaluated)")  # fmt: skip
    return ComparedRun(label=label, estimator=estimator, align=settings.align.value, summary=summary,
                       source=f"{path} (summary)")  # fmt: skip


def load_compared(
    label: str, path: Path, reference: Path | None, settings: EvaluationSettings,
    reference_options: dict[str, Any] | None = None,
) -> ComparedRun:  # fmt: skip
    """One RESULT of ``relpoint compare`` (see the module docstring); InputError when it is none of them.

    ``reference_options`` (``reference_topic``, ``parent``, ``child``, ``reference_times``) choose the
    poses of ``reference`` as ``relpoint evaluate``'s options do.
    """
    if path.is_dir():
        if not (path / "trajectory.tum").is_file():
            raise InputError(f"{path}: not a relpoint run directory (no trajectory.tum)",
                             "give run directories, evaluate --json summaries or evo result zips")  # fmt: skip
        if reference is None and (path / "evaluation.json").is_file():
            return _from_saved_evaluation(label, path / "evaluation.json", path, _read_json(path / "evaluation.json"))
        if reference is None:
            run_input = recorded_input(path)
            recorded = run_input.get("path")
            reference = recorded_log(path, run_input)
            if reference is None:
                where = (
                    f"the log its run.json names ({recorded}) is not here" if recorded else "no run.json names its log"
                )
                raise InputError(f"{path}: no evaluation.json, and {where}", "pass --reference LOG")
        evaluation = evaluate_files(path, reference, settings, **(reference_options or {}))
        return compared_from_evaluation(label, evaluation.result, evaluation.summary,
                                        estimator=run_estimator(path), source=f"{path} against {reference}")  # fmt: skip
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    if path.suffix.lower() == ".zip":
        return compared_from_evo(label, read_evo_result(path), source=f"{path} (evo result)")
    if path.suffix.lower() == ".json":
        return _from_saved_evaluation(label, path, None, _read_json(path))
    raise InputError(f"{path}: not a run directory, an evaluation .json or an evo result .zip",
                     "give run directories, evaluate --json summaries or evo result zips")  # fmt: skip
