"""``relpoint evaluate``: trajectory (and landmark) errors of an estimate against a reference (issue 3).

A thin command over :func:`relpoint.evaluation.evaluate_trajectory` and
:func:`relpoint.evaluation.landmark_metrics`; inputs are read by :mod:`formats.reference_trajectories`.
Outputs: a table on stdout, ``--json`` summary, ``--csv`` per-pose errors, ``--save-results`` and
``--save-rpe-results`` evo result zips, ``--plot`` figures (:mod:`relpoint_app.plots`; PNG, PDF or SVG), and ``--fail-above`` gates (exit code 5).
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path
from typing import Any

import click

from formats.atomic import output_set, write_text
from formats.evo_results import write_evo_result
from formats.outputs import check_output_file, resolve_output, shown_path
from relpoint.errors import GateExceeded, InputError, UsageError
from relpoint.evaluation import (
    STATISTICS,
    AlignMode,
    DeltaUnit,
    EvaluationSettings,
    PoseRelation,
)
from relpoint.evaluation.evaluate import APE_RELATIONS
from relpoint.settings import split_item
from relpoint_app.evaluator import (
    check_gates,
    dense_map_clouds,
    dense_map_summary,
    errors_csv_text,
    evaluate_files,
    evaluation_json,
    run_estimator,
    write_errors_csv,
)
from relpoint_app.evo_results import ape_result, rpe_result
from relpoint_app.plots import EVALUATION_PLOTS, PLOT_FORMATS, evaluation_plots
from relpoint_cli.errors import handle_errors
from relpoint_cli.options import (
    FiniteFloatRange,
    check_tf_chain,
    input_path,
    overwrite_option,
    read_paths,
    time_window,
    time_window_options,
)
from relpoint_cli.progress import progress_bar

log = logging.getLogger(__name__)

EXAMPLES = """\b
Examples:
  relpoint evaluate est.txt --reference groundtruth.txt --align se3
  relpoint evaluate out/fig8 --reference sample_logs/figure8.mcap --json eval.json --plot plots/
  relpoint evaluate out/fig8 -r sample_logs/figure8.mcap --save-results ape.zip --plot plots/ --plot-format pdf
  relpoint evaluate bag.mcap --estimate-topic /odom --reference bag.mcap --reference-topic /amcl_pose
  relpoint evaluate bag.mcap --estimate-topic /odom --reference bag.mcap --parent map --child base_footprint
  relpoint evaluate slam.mcap --estimate-parent map --estimate-child base_link -r groundtruth.txt --align se3
  relpoint evaluate out/run --reference run.mcap --fail-above ate_rmse=0.5 --fail-above lm_err_rmse=1
"""

#: Rows of the statistics table: summary prefix -> label.
_STAT_ROWS = {
    "ate": "APE translation (m)",
    "ape_rot_deg": "APE rotation (deg)",
    "rpe_trans": "RPE translation (m)",
    "rpe_rot_deg": "RPE rotation (deg)",
}


def parse_gates(items: tuple[str, ...]) -> dict[str, float]:
    """``KEY=VALUE`` bounds of ``--fail-above``; raises :class:`UsageError` on malformed items."""
    gates: dict[str, float] = {}
    for item in items:
        key, value = split_item(item, "--fail-above")
        try:
            bound = float(value)
        except ValueError:
            raise UsageError(f"--fail-above {item!r}: {value!r} is not a number") from None
        if math.isnan(bound):
            raise UsageError(f"--fail-above {item!r}: the bound is NaN")
        gates[key] = bound
    return gates


def _fmt(value: float) -> str:
    if math.isnan(value):
        return "n/a"
    if float(value).is_integer() and abs(value) < 1e15:
        return str(int(value))
    return f"{value:.6f}"


def format_table(summary: dict[str, float], relation: PoseRelation = PoseRelation.TRANS_PART) -> str:
    """The summary as text: a statistics table for APE/RPE, then the other figures one per line.

    The ``ape_*`` / ``rpe_*`` figures of ``relation`` get their own rows unless they repeat the translation
    or rotation rows (``trans_part``, ``angle_deg``), in which case they are left out of the text.
    """
    lines = []
    stat_rows = dict(_STAT_ROWS)
    shown: set[str] = set()
    if relation in (PoseRelation.TRANS_PART, PoseRelation.ANGLE_DEG):
        shown.update(f"{p}_{name}" for p in ("ape", "rpe") for name in STATISTICS)
    else:
        stat_rows |= {"ape": f"APE {relation.value}", "rpe": f"RPE {relation.value}"}
    rows = [(p, label) for p, label in stat_rows.items() if f"{p}_rmse" in summary]
    if rows:
        width = max(len(label) for _, label in rows)
        lines.append(f"{'':<{width}}  " + "  ".join(f"{name:>10}" for name in STATISTICS))
        for prefix, label in rows:
            keys = [f"{prefix}_{name}" for name in STATISTICS]
            shown.update(keys)
            lines.append(f"{label:<{width}}  " + "  ".join(f"{summary[k]:>10.6f}" for k in keys))
        lines.append("")
    rest = [k for k in summary if k not in shown]
    width = max((len(k) for k in rest), default=0)
    lines.extend(f"{key:<{width}}  {_fmt(summary[key])}" for key in rest)
    return "\n".join(lines)


def _is_stdout(path: Path | None) -> bool:
    return path is not None and str(path) == "-"


def _refuse_shared_outputs(named: list[tuple[str, Path | None]]) -> None:
    """A usage error when two output options name one file (the second would replace the first)."""
    seen: dict[Path, str] = {}
    for option, path in named:
        if path is None or _is_stdout(path):
            continue
        resolved = resolve_output(path)
        if resolved in seen:
            raise UsageError(f"{seen[resolved]} and {option} both name {path}", "give them different files")
        seen[resolved] = option


@click.command(epilog=EXAMPLES)
@click.argument("estimate", type=input_path())
@click.option(
    "-r",
    "--reference",
    type=input_path(),
    required=True,
    help="Reference: relpoint log (/ground_truth/pose), TUM/EuRoC/KITTI file, run directory or any MCAP bag.",
)
@click.option("--reference-topic", help="Pose topic of an MCAP reference (or its TF topic with --parent/--child).")
@click.option("--estimate-topic", help="Pose topic of an MCAP estimate (default /relpoint/pose or /ground_truth/pose).")
@click.option(
    "--landmarks-topic", metavar="TOPIC",
    help="The reference log's ground-truth landmarks topic (default /ground_truth/landmarks).",
)  # fmt: skip
@click.option("--parent", help="Reference from a TF chain: parent frame (e.g. map).")
@click.option("--child", help="Reference from a TF chain: child frame (e.g. base_footprint).")
@click.option("--estimate-parent", help="Estimate from a TF chain of an MCAP ESTIMATE: parent frame (e.g. map).")
@click.option("--estimate-child", help="Estimate from a TF chain: child frame (e.g. base_link); --estimate-topic "
              "names its TF topic.")  # fmt: skip
@click.option("--reference-times", type=input_path(dir_okay=False), help="Times file of KITTI reference poses.")
@click.option("--times", type=input_path(dir_okay=False), help="Times file of KITTI estimate poses.")
@click.option(
    "--align", type=click.Choice([m.value for m in AlignMode]), default="none", show_default=True,
    help="Alignment of the estimate: Umeyama SE(3) (evo -a), Sim(3) (-as), scale only (-s), origin.",
)  # fmt: skip
@click.option(
    "--n-to-align", type=int, default=-1, show_default=True, help="Fit the alignment on the first N poses (-1 all)."
)
@click.option(
    "--t-max-diff", type=float, default=0.01, show_default=True, help="Largest stamp difference of a match, s."
)
@click.option("--t-offset", type=float, default=0.0, show_default=True, help="Added to the estimate's stamps, s.")
@click.option(
    "--interpolate", is_flag=True, help="Interpolate the denser trajectory (linear + slerp) instead of nearest."
)
@click.option(
    "--pose-relation", type=click.Choice([r.value for r in APE_RELATIONS]), default="trans_part", show_default=True,
    help="Relation of the ape_*/rpe_* figures (evo -r; evo's RPE-only point_distance_error_ratio is not offered).",
)  # fmt: skip
@click.option("--delta", type=float, default=1.0, show_default=True, help="RPE pair separation.")
@click.option(
    "--delta-unit", type=click.Choice([u.value for u in DeltaUnit]), default="f", show_default=True,
    help="RPE delta unit: frames, metres, degrees, radians.",
)  # fmt: skip
@click.option(
    "--delta-tol", type=float, default=0.1, show_default=True, help="Relative tolerance of --all-pairs (m|d|r)."
)
@click.option(
    "--min-matched",
    "min_matched_fraction",
    type=float,
    default=0.5,
    show_default=True,
    help="Fewest matched poses, as a fraction of the sparser trajectory's (0: accept any overlap).",
)
@click.option("--all-pairs", is_flag=True, help="Every pose starts an RPE pair.")
@click.option("--pairs-from-reference", is_flag=True, help="Choose RPE pairs on the reference.")
@click.option(
    "--json",
    "json_path",
    type=click.Path(dir_okay=False, allow_dash=True, path_type=Path),
    help="Write the summary as JSON ('-': to stdout, and the table to stderr).",
)
@click.option(
    "--csv",
    "csv_path",
    type=click.Path(dir_okay=False, allow_dash=True, path_type=Path),
    help="Write per-pose errors as CSV ('-': to stdout, and the table to stderr).",
)
@click.option(
    "--plot", "plot_dir", type=click.Path(file_okay=False, path_type=Path),
    help="Write plots here: trajectory_top, trajectory_side (coloured by error, over the reference) and errors.",
)  # fmt: skip
@click.option(
    "--plot-format", type=click.Choice(PLOT_FORMATS), default="png", show_default=True, help="File format of --plot."
)
@click.option(
    "--save-results", type=click.Path(dir_okay=False, path_type=Path), metavar="FILE.zip",
    help="Write the APE (in --pose-relation) as evo's result zip (evo_ape --save_results), for evo_res and compare.",
)  # fmt: skip
@click.option(
    "--save-rpe-results", type=click.Path(dir_okay=False, path_type=Path), metavar="FILE.zip",
    help="Write the RPE (in --pose-relation) as evo's result zip (evo_rpe --save_results).",
)  # fmt: skip
@click.option(
    "--reference-cloud",
    type=input_path(dir_okay=False),
    help="Dense maps: reference point cloud (PLY, reference frame), e.g. the LOG.scene.ply of a simulated room.",
)
@click.option(
    "--dense-threshold",
    type=FiniteFloatRange(min=0, min_open=True),
    default=0.05,
    show_default=True,
    help="Dense maps: distance counted as a hit, m.",
)
@click.option(
    "--fail-above", "fail_above", multiple=True, metavar="KEY=VALUE",
    help="Exit 5 if summary KEY exceeds VALUE or is NaN (repeatable).",
)  # fmt: skip
@time_window_options
@overwrite_option
@click.pass_context
@handle_errors
def evaluate(ctx: click.Context, estimate: Path, reference: Path, reference_topic: str | None,
             estimate_topic: str | None, landmarks_topic: str | None, parent: str | None, child: str | None,
             estimate_parent: str | None, estimate_child: str | None, reference_times: Path | None,
             times: Path | None, json_path: Path | None, csv_path: Path | None, plot_dir: Path | None,
             plot_format: str, save_results: Path | None, save_rpe_results: Path | None,
             reference_cloud: Path | None, dense_threshold: float, fail_above: tuple[str, ...],
             t_start: float | None, t_end: float | None, overwrite: bool, **options: Any) -> None:  # fmt: skip
    """Evaluate the ESTIMATE trajectory against --reference (APE, RPE, KITTI segments, landmarks).

    ESTIMATE is a `relpoint run` output directory, a TUM file, a EuRoC ground-truth CSV, KITTI poses
    (--times; without it pose i is at i s and pairs by index with KITTI poses of equal count) or an MCAP file
    (--estimate-topic, or --estimate-parent/--estimate-child for a TF chain). Text files are recognised by content: 8 values per line TUM, 12 KITTI, a header
    naming p_RS_R_x or ns stamps with 8+ comma-separated values EuRoC, and a header line naming the columns
    (timestamp,x,y,z,qw,qx,qy,qz in any order) sets them. When ESTIMATE is a run directory with map.csv and the reference is a relpoint log
    with /ground_truth/landmarks, the landmark metrics (lm_*, dyn_*) are added to the summary. When
    ESTIMATE is a dense run (map.ply with normals) and --reference-cloud is given, the map's accuracy
    and completeness (dense_*) are added, after the trajectory alignment. --t-start/--t-end crop both
    trajectories to seconds after the reference's first pose.
    """
    check_tf_chain(parent, child)
    check_tf_chain(estimate_parent, estimate_child, ("--estimate-parent", "--estimate-child"))
    window = time_window(t_start, t_end)
    gates = parse_gates(fail_above)
    settings = EvaluationSettings.from_mapping(options)
    read = read_paths(estimate, reference, reference_cloud, times, reference_times)
    plot_files = [plot_dir / f"{stem}.{plot_format}" for stem in EVALUATION_PLOTS] if plot_dir is not None else []
    for option, path in (("--save-results", save_results), ("--save-rpe-results", save_rpe_results)):
        if path is not None and path.suffix.lower() != ".zip":
            raise UsageError(f"{option} {path}: evo's result files are zip files", "name it FILE.zip")
    if _is_stdout(json_path) and _is_stdout(csv_path):
        raise UsageError("--json - and --csv - both name stdout", "write one of them to a file")
    named = [("--json", json_path), ("--csv", csv_path), ("--save-results", save_results),
             ("--save-rpe-results", save_rpe_results), *(("--plot", path) for path in plot_files)]  # fmt: skip
    _refuse_shared_outputs(named)
    for _, path in named:
        if path is not None and not _is_stdout(path):
            check_output_file(path, inputs=read, overwrite=overwrite)
    evaluation = evaluate_files(
        estimate, reference, settings, reference_topic=reference_topic, estimate_topic=estimate_topic,
        parent=parent, child=child, estimate_parent=estimate_parent, estimate_child=estimate_child,
        reference_times=reference_times, times=times, window=window, landmarks_topic=landmarks_topic,
    )  # fmt: skip
    result, summary = evaluation.result, evaluation.summary
    quiet = bool(ctx.find_root().obj.get("quiet"))
    if not quiet:
        for note in result.notes:
            click.echo(f"relpoint: warning: {note}", err=True)
    if save_rpe_results is not None and result.rpe is None:  # before any output is written
        raise InputError(
            f"--save-rpe-results {save_rpe_results}: this evaluation has no RPE"
            + (f" ({result.notes[0]})" if result.notes else ""),
            "choose a smaller --delta (or --delta-unit), or leave --save-rpe-results out",
        )
    if reference_cloud is not None:
        points, reference_points = dense_map_clouds(estimate, reference_cloud, result, settings)
        with progress_bar(len(points) + len(reference_points), "dense map", unit="point") as bar:
            summary |= dense_map_summary(points, reference_points, dense_threshold, bar.update)

    exceeded = check_gates(summary, gates)  # unknown keys are a usage error before anything is written
    # Absolute, and with everything that chose the poses: `relpoint compare` evaluates it again from these.
    inputs = {
        "estimate": shown_path(os.path.abspath(estimate)),
        "reference": shown_path(os.path.abspath(reference)),
        "reference_topic": reference_topic,
        "estimate_topic": estimate_topic,
        "landmarks_topic": landmarks_topic,
        "parent": parent,
        "child": child,
        "estimate_parent": estimate_parent,
        "estimate_child": estimate_child,
        "times": None if times is None else shown_path(os.path.abspath(times)),
        "reference_times": None if reference_times is None else shown_path(os.path.abspath(reference_times)),
        "t_start": t_start,
        "t_end": t_end,
    }
    estimator = run_estimator(estimate)
    names = {
        "reference_name": shown_path(reference.name or "reference"),
        "estimate_name": shown_path(estimate.name or "estimate"),
    }
    if names["reference_name"] == names["estimate_name"]:
        names["estimate_name"] += " (estimate)"
    with output_set():  # every output file appears, or none does (an interrupt while they are written)
        if json_path is not None and not _is_stdout(json_path):
            write_text(json_path, evaluation_json(summary, settings, inputs))
        if csv_path is not None and not _is_stdout(csv_path):
            write_errors_csv(csv_path, result, evaluation.landmark_error_over_time)
        for path, to_evo in ((save_results, ape_result), (save_rpe_results, rpe_result)):
            if path is not None:
                write_evo_result(path, to_evo(result, summary=summary, extra={"estimator": estimator, "inputs": inputs},
                                              **names))  # fmt: skip
        if plot_dir is not None:
            evaluation_plots(
                plot_dir, evaluation.reference, result, run=" ".join(filter(None, (shown_path(estimate), estimate_topic))),
                estimator=estimator,
                landmarks=evaluation.landmarks, truth=evaluation.truth, plot_format=plot_format,
            )  # fmt: skip
    if _is_stdout(json_path):
        click.echo(evaluation_json(summary, settings, inputs), nl=False)
    if _is_stdout(csv_path):
        click.echo(errors_csv_text(result, evaluation.landmark_error_over_time), nl=False)
    to_stderr = _is_stdout(json_path) or _is_stdout(csv_path)
    if not (to_stderr and quiet):  # on stderr the table is a message, which -q silences
        click.echo(format_table(summary, settings.pose_relation), err=to_stderr)
    if exceeded:
        raise GateExceeded(f"evaluation gate exceeded: {'; '.join(exceeded)}")
