"""``relpoint export``: trajectories, landmarks and maps out of logs, runs and bags into common files.

The options and the summary line; what can be exported from which source, as which format, and the
work itself are :mod:`relpoint_app.exporter`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import click

from formats.outputs import check_output_file, resolve_output
from relpoint.errors import InputError, UsageError
from relpoint_app.exporter import Format, What, default_what, export_file, output_format
from relpoint_cli.errors import handle_errors
from relpoint_cli.options import (
    check_tf_chain,
    input_path,
    overwrite_option,
    read_paths,
    time_window,
    time_window_options,
)

log = logging.getLogger(__name__)

EXAMPLES = """\b
Examples:
  relpoint export run.mcap -o groundtruth.tum                  # ground-truth trajectory of a log
  relpoint export out/run -o estimate.kitti --out-times times.txt
  relpoint export out/run -o estimate.csv
  relpoint export run.mcap -o truth_landmarks.ply              # ground-truth landmarks of a log
  relpoint export out/run -o landmarks.ply --what landmarks    # map.csv as PLY
  relpoint export out/dense -o cloud.csv --what map            # map.ply with all its properties
  relpoint export bag.mcap --topic /odom -o odom.tum
  relpoint export bag.mcap --parent map --child base_footprint -o amcl_tf.tum
"""


@click.command(epilog=EXAMPLES)
@click.argument("source", type=input_path())
@click.option("-o", "--output", "out", type=click.Path(path_type=Path), required=True, help="Output file.")
@click.option(
    "--what", type=click.Choice([w.value for w in What]),
    help="What to export [default: map for PLY output from a run directory or PLY file, landmarks for PLY "
    "output from a log, else trajectory].",
)  # fmt: skip
@click.option(
    "--format", "fmt", type=click.Choice([f.value for f in Format]),
    help="Output format [default: from the suffix: .tum/.txt tum, .kitti kitti, .csv csv, .ply ply].",
)  # fmt: skip
@click.option(
    "--topic",
    help="MCAP pose topic (PoseStamped, PoseWithCovarianceStamped, Odometry, TransformStamped, PointStamped), "
    "or the TF topic.",
)
@click.option("--parent", help="Trajectory from a TF chain: parent frame (e.g. map).")
@click.option("--child", help="Trajectory from a TF chain: child frame (e.g. base_footprint).")
@click.option("--times", type=input_path(dir_okay=False), help="Times file of KITTI SOURCE poses.")
@click.option(
    "--out-times", type=click.Path(dir_okay=False, path_type=Path), help="KITTI output: also write its times file."
)
@time_window_options
@overwrite_option
@click.pass_context
@handle_errors
def export(ctx: click.Context, source: Path, out: Path, what: str | None, fmt: str | None, topic: str | None,
           parent: str | None, child: str | None, times: Path | None, out_times: Path | None,
           t_start: float | None, t_end: float | None, overwrite: bool) -> None:  # fmt: skip
    """Export a trajectory, landmarks or a map from SOURCE to OUT (TUM, KITTI, CSV or binary PLY).

    SOURCE is a relpoint log (ground-truth trajectory and landmarks), a `relpoint run` output directory
    (estimated trajectory, map.csv landmarks, map.ply), a TUM, EuRoC CSV or KITTI file, a PLY file, or any ROS 2 bag
    (--topic, or --parent/--child for a TF chain). Trajectory files are recognised by content, as by
    `relpoint evaluate`.
    """
    check_tf_chain(parent, child)
    window = time_window(t_start, t_end)
    if not source.exists():
        raise InputError(f"{source}: no such file or directory")
    if out.is_dir():
        raise UsageError(f"{out} is a directory; give an output file name")
    read = read_paths(source, times)
    for path in (out, out_times):
        if path is not None:
            check_output_file(path, inputs=read, overwrite=overwrite)
    if out_times is not None and resolve_output(out_times) == resolve_output(out):
        raise UsageError(f"--out-times {out_times} is the output file itself", "give the times file another name")
    out_format = output_format(out, fmt)
    selects_trajectory = topic is not None or parent is not None
    kind = What(what) if what is not None else default_what(source, out_format, selects_trajectory=selects_trajectory)
    description = export_file(
        source,
        out,
        kind,
        out_format,
        topic=topic,
        parent=parent,
        child=child,
        times=times,
        out_times=out_times,
        window=window,
    )
    if not (ctx.find_root().obj or {}).get("quiet"):
        click.echo(f"wrote {description} to {out} ({out_format.value})")
