"""``relpoint fuse``: place a run's local SLAM segments in the fixes' frame (Algorithm 3 post-step).

The options, the summary line and the exit codes; the work is :func:`relpoint_app.fuser.fuse_run`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click

from relpoint.fusion import FusionConfig
from relpoint_app.fuser import fuse_run
from relpoint_cli.errors import handle_errors
from relpoint_cli.options import input_path, overwrite_option
from relpoint_cli.topics import topic_options, topics_from

EXAMPLES = """\b
Examples:
  relpoint simulate -o gaps.mcap --scenario figure8-gaps --fix-every 10 --seed 1
  relpoint run gaps.mcap --estimator relpoint --no-fixes -o out/local
  relpoint fuse out/local --log gaps.mcap --restart -o out/global   # fresh local map per segment
  relpoint fuse out/local --log gaps.mcap -o out/global             # split the finished run
  relpoint fuse out/local --log gaps.mcap --param min_matches=8 --param min_spread=2 -o out/global
  relpoint evaluate out/global -r gaps.mcap --align none
"""


def fusion_config(params: tuple[str, ...]) -> FusionConfig:
    """:class:`FusionConfig` from ``--param KEY=VALUE`` items."""
    return FusionConfig.from_strings(params)


@click.command(epilog=EXAMPLES)
@click.argument("run_dir", type=input_path(file_okay=False))
@click.option("--log", "log_path", type=input_path(), required=True,
              help="The log the run was made from (its position fixes are read).")  # fmt: skip
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output directory (replaced atomically).")  # fmt: skip
@click.option("--param", "params", multiple=True, metavar="KEY=VALUE",
              help="Fusion setting (repeatable): " + ", ".join(f.name for f in dataclasses.fields(FusionConfig)) + ".")  # fmt: skip
@click.option("--restart", is_flag=True,
              help="Re-run the run's estimator (name, parameters and seed from run.json) over LOG, starting a "
              "fresh local map at every break (Algorithm 3), instead of splitting the finished run.")  # fmt: skip
@click.option("--other-log", is_flag=True,
              help="Accept a LOG that is not byte for byte the run's (run.json's hash), e.g. the same recording "
              "in another bag layout.")  # fmt: skip
@topic_options
@overwrite_option
@click.pass_context
@handle_errors
def fuse_command(ctx: click.Context, run_dir: Path, log_path: Path, output: Path, params: tuple[str, ...],
                 restart: bool, other_log: bool, overwrite: bool, **topic_names: str) -> None:  # fmt: skip
    """Fuse RUN_DIR (a `relpoint run` output) with the fixes of LOG into a global path and map.

    By default the finished run is split into local maps where matched features fail (matched =
    observed points that did not start a landmark, from timing.csv); with --restart the estimator is
    run again and restarted at each break, so every local map stays rigid (see docs/fusion.md). Each
    local map is fitted to the fixes and mapped into their frame.
    """
    config = fusion_config(params)
    result = fuse_run(run_dir, log_path, output, config, restart=restart, topics=topics_from(topic_names),
                      overwrite=overwrite, other_log=other_log)  # fmt: skip
    if not ctx.find_root().obj.get("quiet"):
        summary = result.summary
        click.echo(
            f"fuse: {summary['segments_placed']} of {summary['segments']} segments placed, "
            f"{summary['iterations_fused']} iterations fused, {summary['iterations_fixes_only']} from fixes alone, "
            f"{summary['landmarks_placed']} landmarks -> {output}",
            err=True,
        )
