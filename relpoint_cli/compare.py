"""``relpoint compare``: the evaluations of several runs in one table and one figure (issue 19, evo_res).

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
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import click

from formats.atomic import write_text
from formats.compare_table import SUFFIX_FORMATS, TABLE_FORMATS, render_table
from formats.evo_results import compared_from_evo, read_evo_result
from formats.outputs import check_output_file
from formats.plots import PLOT_FORMATS, comparison_plot
from relpoint.errors import InputError, RelpointError, UsageError
from relpoint.evaluation import AlignMode, EvaluationSettings
from relpoint.evaluation.comparison import ComparedRun, compared_from_evaluation, table_keys, unique_labels
from relpoint_app.evaluator import evaluate_files
from relpoint_cli.errors import handle_errors
from relpoint_cli.evaluate import run_estimator
from relpoint_cli.options import overwrite_option, read_paths

log = logging.getLogger(__name__)

EXAMPLES = """\b
Examples:
  relpoint compare out/relpoint out/ekf out/fastslam
  relpoint compare out/relpoint out/ekf --reference run.mcap --align se3 -o table.md --plot compare.pdf
  relpoint compare results/*/ --format csv -o table.csv --keys ate_rmse,rpe_trans_rmse,lm_err_rmse
  relpoint compare ape_orb.zip ape_vins.zip eval.json --plot compare.png --plot-kind violin
"""

_MAX_JSON_BYTES = 50_000_000


def _read_json(path: Path) -> dict[str, Any]:
    try:
        if path.stat().st_size > _MAX_JSON_BYTES:
            raise InputError(f"{path}: larger than {_MAX_JSON_BYTES >> 20} MB, not an evaluation summary")
        document = json.loads(path.read_text(encoding="utf-8"))
    except OSError as error:
        raise InputError(f"{path}: cannot read ({error.strerror or error})") from None
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
        log.warning("%s: its estimate or reference (%s) is not readable here; only its summary is compared",
                    path, inputs.get("reference"))  # fmt: skip
    else:
        try:
            evaluation = evaluate_files(
                estimate, reference, settings, reference_topic=inputs.get("reference_topic"),
                estimate_topic=inputs.get("estimate_topic"), parent=inputs.get("parent"), child=inputs.get("child"),
            )  # fmt: skip
        except RelpointError as error:
            log.warning("%s: cannot re-evaluate it (%s); only its summary is compared", path, error)
        else:
            return compared_from_evaluation(label, evaluation.result, summary | evaluation.summary,
                                            estimator=estimator, source=f"{path} (re-evaluated)")  # fmt: skip
    return ComparedRun(label=label, estimator=estimator, align=settings.align.value, summary=summary,
                       source=f"{path} (summary)")  # fmt: skip


def _run_log(directory: Path) -> str | None:
    """The input log a run directory's run.json names (as it was given to `relpoint run`), if any."""
    try:
        document = json.loads((directory / "run.json").read_text(encoding="utf-8")[:10_000_000])
    except (OSError, ValueError):
        return None
    recorded = document.get("input", {}) if isinstance(document, dict) else {}
    path = recorded.get("path") if isinstance(recorded, dict) else None
    return path if isinstance(path, str) and path else None


def load_compared(label: str, path: Path, reference: Path | None, settings: EvaluationSettings) -> ComparedRun:
    """One RESULT of ``relpoint compare`` (see the module docstring); InputError when it is none of them."""
    if path.is_dir():
        if not (path / "trajectory.tum").is_file():
            raise InputError(f"{path}: not a relpoint run directory (no trajectory.tum)",
                             "give run directories, evaluate --json summaries or evo result zips")  # fmt: skip
        if reference is None and (path / "evaluation.json").is_file():
            return _from_saved_evaluation(label, path / "evaluation.json", path, _read_json(path / "evaluation.json"))
        if reference is None:
            recorded = _run_log(path)
            reference = _existing(recorded)
            if reference is None:
                where = f"the log its run.json names ({recorded}) is not here" if recorded else "no run.json names its log"
                raise InputError(f"{path}: no evaluation.json, and {where}", "pass --reference LOG")
        evaluation = evaluate_files(path, reference, settings)
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


def _parse_keys(text: str | None) -> list[str] | None:
    if text is None:
        return None
    keys = [key.strip() for key in text.split(",") if key.strip()]
    if not keys:
        raise UsageError("--keys is empty", "give comma-separated summary keys, e.g. ate_rmse,rpe_trans_rmse")
    return keys


def _check_keys(runs: Sequence[ComparedRun], keys: Sequence[str]) -> None:
    known = {key for run in runs for key in run.summary}
    unknown = [key for key in keys if key not in known]
    if unknown:
        raise UsageError(f"--keys: no run has {', '.join(unknown)}", f"known keys: {', '.join(sorted(known))}")


def _table_format(table_format: str | None, output: Path | None) -> str:
    if table_format is not None:
        return table_format
    return SUFFIX_FORMATS.get(output.suffix.lower(), "text") if output is not None else "text"


def _plot_format(plot_format: str | None, plot: Path) -> str:
    suffix = plot.suffix.lower().lstrip(".")
    if plot_format is not None and suffix in PLOT_FORMATS and suffix != plot_format:
        raise UsageError(f"--plot {plot} is named .{suffix} but --plot-format is {plot_format}",
                         f"name it .{plot_format} or drop --plot-format")  # fmt: skip
    return plot_format or (suffix if suffix in PLOT_FORMATS else "png")


@click.command(epilog=EXAMPLES)
@click.argument("results", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "-r", "--reference", type=click.Path(path_type=Path),
    help="Evaluate every run directory against this reference (as `relpoint evaluate --reference`).",
)  # fmt: skip
@click.option(
    "--align", type=click.Choice([m.value for m in AlignMode]), default="none", show_default=True,
    help="Alignment of the run directories compare evaluates itself (saved evaluations keep theirs).",
)  # fmt: skip
@click.option("--label", "labels", multiple=True, help="Name of each RESULT in order (default: its path).")
@click.option("--keys", help="Comma-separated summary keys to tabulate (default: APE, RPE and landmark figures).")
@click.option(
    "--format", "table_format", type=click.Choice(TABLE_FORMATS), help="Table format (default: text, or -o's suffix)."
)
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), help="Write the table to this file.")
@click.option(
    "--plot", type=click.Path(dir_okay=False, path_type=Path), help="Write the comparison figure to this file."
)
@click.option("--plot-kind", type=click.Choice(("box", "violin")), default="box", show_default=True,
              help="Distribution plot of the per-pose errors.")  # fmt: skip
@click.option(
    "--plot-format", type=click.Choice(PLOT_FORMATS), help="Figure format (default: --plot's suffix, else png)."
)
@overwrite_option
@handle_errors
def compare(results: tuple[Path, ...], reference: Path | None, align: str, labels: tuple[str, ...],
            keys: str | None, table_format: str | None, output: Path | None, plot: Path | None, plot_kind: str,
            plot_format: str | None, overwrite: bool) -> None:  # fmt: skip
    """Compare the evaluations of RESULTS: run directories, `evaluate --json` summaries, evo result zips.

    Prints a table of APE/RPE/landmark figures (text unless --format says otherwise) and writes it with
    -o (in --format, else as its suffix says: .md, .csv, .json, else text). With --plot, draws every
    run's error distributions and APE over time in one figure.
    """
    if labels and len(labels) != len(results):
        raise UsageError(f"{len(labels)} --label for {len(results)} results", "give one --label per RESULT, or none")
    wanted = _parse_keys(keys)
    file_format = _table_format(table_format, output)
    read = read_paths(*results, reference)
    for path in (output, plot):
        if path is not None:
            check_output_file(path, inputs=read, overwrite=overwrite)
    if output is not None and plot is not None and output.resolve() == plot.resolve():
        raise UsageError(f"-o and --plot both name {output}", "give them different files")
    figure_format = _plot_format(plot_format, plot) if plot is not None else None
    settings = EvaluationSettings(align=align)
    names = list(labels) or [str(path).rstrip("/") or str(path) for path in results]
    runs = [
        load_compared(label, path, reference, settings)
        for label, path in zip(unique_labels(names), results, strict=True)
    ]
    if wanted is not None:
        _check_keys(runs, wanted)
    columns = table_keys(runs, wanted)
    if plot is not None and not any(run.series for run in runs):
        raise InputError("no RESULT holds per-pose errors to plot",
                         "give run directories with their reference, or evo result zips")  # fmt: skip
    aligns = {run.align for run in runs if run.align}
    if len(aligns) > 1:
        log.warning("the runs were evaluated with different alignments (%s)", ", ".join(sorted(aligns)))
    if output is not None:
        write_text(output, render_table(runs, columns, file_format))
    if plot is not None and figure_format is not None:
        comparison_plot(plot, runs, kind=plot_kind, plot_format=figure_format)
    click.echo(render_table(runs, columns, table_format or "text"), nl=False)
