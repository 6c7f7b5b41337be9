"""``relpoint compare``: the evaluations of several runs in one table and one figure (evo_res).

The options, the table and the figure; each RESULT is read by :func:`relpoint_app.comparer.load_compared`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import click

from formats.atomic import output_set, write_text
from formats.outputs import check_output_file, shown_path
from relpoint.errors import InputError, UsageError
from relpoint.evaluation import AlignMode, EvaluationSettings
from relpoint.evaluation.comparison import ComparedRun, table_keys, unique_labels
from relpoint_app.compare_table import SUFFIX_FORMATS, TABLE_FORMATS, render_table
from relpoint_app.comparer import load_compared
from relpoint_app.plots import PLOT_FORMATS, comparison_plot
from relpoint_cli.errors import handle_errors
from relpoint_cli.options import check_tf_chain, input_path, overwrite_option, read_paths

log = logging.getLogger(__name__)

EXAMPLES = """\b
Examples:
  relpoint compare out/relpoint out/ekf out/fastslam
  relpoint compare out/relpoint out/ekf --reference run.mcap --align se3 -o table.md --plot compare.pdf
  relpoint compare results/*/ --format csv -o table.csv --keys ate_rmse,rpe_trans_rmse,lm_err_rmse
  relpoint compare ape_orb.zip ape_vins.zip eval.json --plot compare.png --plot-kind violin
"""


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
@click.argument("results", nargs=-1, required=True, type=input_path())
@click.option(
    "-r", "--reference", type=input_path(),
    help="Evaluate every run directory against this reference (as `relpoint evaluate --reference`).",
)  # fmt: skip
@click.option("--reference-topic", help="Pose topic of an MCAP reference (or its TF topic with --parent/--child).")
@click.option("--parent", help="Reference from a TF chain of the MCAP reference: parent frame (e.g. map).")
@click.option("--child", help="... and child frame (e.g. base_link).")
@click.option("--reference-times", type=input_path(dir_okay=False), help="Times file of KITTI reference poses.")
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
def compare(results: tuple[Path, ...], reference: Path | None, reference_topic: str | None, parent: str | None,
            child: str | None, reference_times: Path | None, align: str, labels: tuple[str, ...],
            keys: str | None, table_format: str | None, output: Path | None, plot: Path | None, plot_kind: str,
            plot_format: str | None, overwrite: bool) -> None:  # fmt: skip
    """Compare the evaluations of RESULTS: run directories, `evaluate --json` summaries, evo result zips.

    Prints a table of APE/RPE/landmark figures (text unless --format says otherwise) and writes it with
    -o (in --format, else as its suffix says: .md, .csv, .json, else text). With --plot, draws every
    run's error distributions and APE over time in one figure.
    """
    if labels and len(labels) != len(results):
        raise UsageError(f"{len(labels)} --label for {len(results)} results", "give one --label per RESULT, or none")
    check_tf_chain(parent, child)
    wanted = _parse_keys(keys)
    file_format = _table_format(table_format, output)
    read = read_paths(*results, reference, reference_times)
    chosen = {"reference_topic": reference_topic, "parent": parent, "child": child, "reference_times": reference_times}
    if reference is None and any(value is not None for value in chosen.values()):
        given = ", ".join(f"--{key.replace('_', '-')}" for key, value in chosen.items() if value is not None)
        raise UsageError(f"{given} choose poses of --reference, which is not given", "add --reference REF")
    for path in (output, plot):
        if path is not None:
            check_output_file(path, inputs=read, overwrite=overwrite)
    if output is not None and plot is not None and output.resolve() == plot.resolve():
        raise UsageError(f"-o and --plot both name {output}", "give them different files")
    figure_format = _plot_format(plot_format, plot) if plot is not None else None
    settings = EvaluationSettings(align=align)
    names = list(labels) or [shown_path(path).rstrip("/") or shown_path(path) for path in results]
    runs = [
        load_compared(label, path, reference, settings, reference_options=chosen)
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
    with output_set():  # the table and the figure appear together, or neither does
        if output is not None:
            write_text(output, render_table(runs, columns, file_format))
        if plot is not None and figure_format is not None:
            comparison_plot(plot, runs, kind=plot_kind, plot_format=figure_format)
    click.echo(render_table(runs, columns, table_format or "text"), nl=False)
