"""``relpoint run``: run an estimator over a log and write its output directory."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from pathlib import Path
from typing import Any

import click

from formats.log import LogReader
from formats.outputs import check_output_directory
from relpoint.estimators import ESTIMATORS
from relpoint_app.runner import build_config, estimator_spec, execute_run
from relpoint_cli.errors import handle_errors
from relpoint_cli.options import input_path, overwrite_option, time_window, time_window_options
from relpoint_cli.progress import progress_bar
from relpoint_cli.topics import topic_options, topics_from

log = logging.getLogger(__name__)

#: ``[relpoint|ekf|...]``: the estimators, shown in ``--help``.
ESTIMATOR_METAVAR = "[" + "|".join(ESTIMATORS) + "]"


def complete_estimator(ctx: click.Context, param: click.Parameter, incomplete: str) -> list[Any]:
    """Shell completion of ``--estimator``: the registered estimators' names."""
    from click.shell_completion import CompletionItem

    return [CompletionItem(name) for name in ESTIMATORS if name.startswith(incomplete)]


EXAMPLES = """\b
Examples:
  relpoint run sample_logs/figure8.mcap --estimator relpoint -o out/fig8
  relpoint run run.mcap --estimator ekf --param association=jcbb -o out/ekf
  relpoint run robot.mcap --estimator fastslam --points-topic /landmarks --seed 3 -o out/fs
  relpoint run run.mcap --estimator ekf --config params.toml -o out/ekf   # [ekf] table or flat keys
  relpoint config --estimator ekf                                          # list parameters
"""


@click.command(epilog=EXAMPLES)
@click.argument("log", type=input_path())
@click.option("-e", "--estimator", "estimator_name", required=True, metavar=ESTIMATOR_METAVAR,
              shell_complete=complete_estimator, help="Estimator to run (see `relpoint info LOG`).")  # fmt: skip
@click.option(
    "-o",
    "--output",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Output directory (written atomically; an earlier `relpoint run` output there is replaced, nothing else is).",
)
@click.option("--param", "params", multiple=True, metavar="KEY=VALUE", help="Estimator parameter (repeatable).")
@click.option(
    "--config",
    "config_file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="TOML/YAML file of estimator parameters.",
)
@click.option(
    "--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seed of the estimator's random draws."
)
@click.option(
    "--map-every",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Also write map_history.csv with the map every N iterations (landmark error over time); 0 = off.",
)
@click.option("--no-odometry", is_flag=True, help="Ignore /odom even if the log has it.")
@click.option("--no-fixes", is_flag=True, help="Ignore /fix even if the log has it.")
@topic_options
@time_window_options
@overwrite_option
@click.pass_context
@handle_errors
def run(ctx: click.Context, log: Path, estimator_name: str, output: Path, params: tuple[str, ...],
        config_file: Path | None, seed: int, map_every: int, no_odometry: bool, no_fixes: bool,
        t_start: float | None, t_end: float | None, overwrite: bool, **topic_names: str) -> None:  # fmt: skip
    """Run an estimator over LOG and write trajectory, map, timing and run.json to OUTPUT.

    --t-start/--t-end crop the log: seconds after its first observation, odometry or fix.
    """
    window = time_window(t_start, t_end)
    spec = estimator_spec(estimator_name)
    config = build_config(spec, config_file, params)
    output = check_output_directory(output, command="run", inputs=[log, config_file], overwrite=overwrite)
    reader = LogReader(log, topics_from(topic_names))
    # A cropped run's iterations are not counted ahead: its bar shows no total rather than the whole log's.
    total = reader.topic_infos.get(reader.topics.depth if "depth" in spec.needs else reader.topics.points)
    with progress_bar(total.count if total and window.is_open else None, estimator_name, unit="iter") as bar:
        result = execute_run(
            reader, spec, config, output, seed=seed, use_odometry=not no_odometry, use_fixes=not no_fixes,
            on_iteration=lambda *_: bar.update(1), on_finish=lambda doing: bar.set_description(f"{estimator_name}: {doing}"),
            map_every=map_every, window=window,
        )  # fmt: skip
    if not ctx.find_root().obj.get("quiet"):
        timing = result.timing_summary()
        skipped = sum(reader.skipped.values()) + sum(result.skipped.values())
        mapped = (f"{len(result.dense_map[0])} map points" if result.dense_map is not None
                  else f"{len(result.landmarks)} landmarks")  # fmt: skip
        click.echo(
            f"{spec.name}: {timing['iterations']} iterations, {mapped}, "
            f"{timing['seconds_median'] * 1e3:.2f} ms median per iteration"
            + (f", {timing['seconds_finish']:.2f} s final adjustment" if timing["seconds_finish"] >= 0.01 else "")
            + (f", {skipped} unusable items skipped" if skipped else "")
            + f" -> {output}",
            err=True,
        )


@click.command("config")
@click.option("-e", "--estimator", "estimator_name", required=True, metavar=ESTIMATOR_METAVAR,
              shell_complete=complete_estimator, help="Estimator whose parameters to show.")  # fmt: skip
@handle_errors
def config_command(estimator_name: str) -> None:
    """Print an estimator's parameters with their defaults, as TOML for --config."""
    spec = estimator_spec(estimator_name)
    click.echo(f"[{spec.name}]  # {spec.description}")
    key_settings = getattr(spec.config_class, "key_settings", {})
    if key_settings:
        click.echo("# The settings that matter (the others rarely need changing):")
        for name, why in key_settings.items():
            click.echo(f"#   {name}: {why}")
    for f in dataclasses.fields(spec.config_class):
        default = f.default if f.default is not dataclasses.MISSING else None
        help_text = f.metadata.get("help", "") or spec.config_class.field_help(f.name)
        takes = spec.config_class.field_range(f.name)
        if takes is not None:
            help_text = f"{help_text} {takes}".strip()
        comment = f"  # {help_text}" if help_text else ""
        if default is None:
            click.echo(f"# {f.name} =  (unset){comment}")
        else:
            click.echo(f"{f.name} = {_toml_value(default)}{comment}")


def _toml_value(value: object) -> str:
    """A default as a TOML value: JSON's scalars and arrays are TOML's, except the infinities (and NaN), which
    JSON writes as ``Infinity`` and TOML as ``inf``."""
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    return json.dumps(value)
