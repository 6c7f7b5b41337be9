"""``relpoint run``: run an estimator over a log and write its output directory."""

from __future__ import annotations

import dataclasses
import json
import logging
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import click
import numpy as np
from threadpoolctl import threadpool_limits

import relpoint
from formats.config_files import load_settings
from formats.layouts import log_sha256
from formats.log import LogReader, Record
from formats.outputs import check_output_directory
from formats.run_output import write_run_directory
from relpoint import pipeline
from relpoint.errors import UsageError
from relpoint.estimators import ESTIMATORS, EstimatorSpec
from relpoint.types import DepthFrame, Intrinsics, TimeWindow, Trajectory
from relpoint_cli.errors import handle_errors
from relpoint_cli.info import NEED_ROLES
from relpoint_cli.options import overwrite_option, time_window, time_window_options
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


def build_config(spec: EstimatorSpec, config_file: Path | None, params: tuple[str, ...]) -> Any:
    """The estimator's config dataclass from defaults, a settings file and ``--param KEY=VALUE``."""
    values: dict[str, Any] = {}
    if config_file is not None:
        values.update(load_settings(config_file, section=spec.name))
    return spec.build_config(values, params)


def estimator_inputs(records: Iterator[Record], skipped: Counter[str] | None = None) -> Iterator[Any]:
    """Core-type inputs for the pipeline from decoded log records.

    Depth images become :class:`DepthFrame` objects with the latest camera_info's intrinsics and the
    colour image of the same stamp (colour is written before depth at a stamp); depth images that
    arrive before any camera_info, or that do not match its size, are skipped, counted in ``skipped``
    and reported once.
    """
    skipped = Counter() if skipped is None else skipped
    intrinsics: Intrinsics | None = None
    color: tuple[int, np.ndarray] | None = None
    for record in records:
        if record.role in ("points", "odometry", "fix"):
            yield record.value
        elif record.role == "camera_info":
            intrinsics = record.value
        elif record.role == "color":
            color = (record.stamp_ns, record.value)
        elif record.role == "depth":
            if intrinsics is None or record.value.shape != (intrinsics.height, intrinsics.width):
                kind = "depth: images without a matching camera_info"
                if kind not in skipped:
                    log.warning("skipping a depth image at %d ns: no matching camera_info before it; further "
                                "ones are counted in run.json", record.stamp_ns)  # fmt: skip
                skipped[kind] += 1
                continue
            rgb = color[1] if color is not None and color[0] == record.stamp_ns else None
            if rgb is not None and rgb.shape[:2] != record.value.shape:
                rgb = None
            yield DepthFrame(record.stamp_ns, record.value, intrinsics, rgb)


def input_roles(
    reader: LogReader, spec: EstimatorSpec, *, use_odometry: bool = True, use_fixes: bool = True
) -> list[str]:
    """The log roles an estimator reads: the ones it needs (checked present) and the optional ones the log has."""
    needed = [role for need in sorted(spec.needs) for role in NEED_ROLES.get(need, (need,))]
    reader.require(*needed)
    wanted = [
        need for need in sorted(spec.uses) if (need != "odometry" or use_odometry) and (need != "fix" or use_fixes)
    ]
    return needed + [role for need in wanted for role in NEED_ROLES.get(need, (need,)) if reader.role_present(role)]


#: Roles a time window crops; the others (camera_info) describe the sensor and are always read.
CROPPED_ROLES = frozenset({"points", "odometry", "fix", "depth", "color", "ground_truth_pose"})

#: How far (ns) past the window's end a stamp may lie before the rest of the log is left unread:
#: topics are interleaved by log time, and header stamps may trail it.
CROP_READ_AHEAD_NS = 10_000_000_000


def cropped_records(records: Iterator[Record], window: TimeWindow) -> Iterator[Record]:
    """The records inside ``window``, counted from the first record's stamp (camera_info always)."""
    if window.is_open:
        yield from records
        return
    bounds: tuple[int, int] | None = None
    for record in records:
        if record.role not in CROPPED_ROLES:
            yield record
            continue
        if bounds is None:
            bounds = window.bounds_ns(record.stamp_ns)
        if record.stamp_ns > bounds[1] + CROP_READ_AHEAD_NS:
            return
        if bounds[0] <= record.stamp_ns <= bounds[1]:
            yield record


def execute_run(
    reader: LogReader,
    spec: EstimatorSpec,
    config: Any,
    output: Path,
    *,
    seed: int = 0,
    use_odometry: bool = True,
    use_fixes: bool = True,
    extra_info: dict[str, Any] | None = None,
    on_iteration: Callable[[int, Any], None] | None = None,
    map_every: int = 0,
    window: TimeWindow | None = None,
) -> pipeline.RunResult:
    """What ``relpoint run`` does after parsing its options: run ``spec`` over the log, write ``output``.

    ``window`` crops the log's observations, odometry and fixes (seconds from the first one read).

    BLAS runs single-threaded: the estimators' matrices are small, and on a busy machine OpenBLAS's
    spinning worker threads made the EKF about 20 times slower.
    """
    roles = input_roles(reader, spec, use_odometry=use_odometry, use_fixes=use_fixes)
    estimator = spec.factory(config, np.random.default_rng(seed))
    with threadpool_limits(limits=1, user_api="blas"):
        result = pipeline.run(
            estimator_inputs(cropped_records(reader.records(roles), window or TimeWindow()), reader.skipped),
            estimator, on_iteration=on_iteration, map_every=map_every, skipped_before=reader.skipped,
        )  # fmt: skip
    run_info = {
        "estimator": spec.name,
        "parameters": dataclasses.asdict(config),
        "seed": seed,
        "relpoint_version": relpoint.__version__,
        "input": {"path": str(reader.path), "sha256": log_sha256(reader.path), "roles": sorted(roles),
                  "topics": {role: reader.topics.roles()[role] for role in sorted(roles)}},
        "skipped": dict(sorted((reader.skipped + Counter(result.skipped)).items())),
        "warnings": list(result.warnings),
        **({"time_window": dataclasses.asdict(window)} if window is not None and not window.is_open else {}),
        **(extra_info or {}),
    }  # fmt: skip
    observations = (
        (record.value for record in cropped_records(reader.records(["points"]), window or TimeWindow()))
        if "points" in roles else ()
    )  # fmt: skip
    write_run_directory(output, result, run_info, observations=observations, reference=reference_path(reader))
    return result


def reference_path(reader: LogReader) -> Trajectory | None:
    """The log's ground-truth path, if it has one (for result.mcap)."""
    if reader.topics.ground_truth_pose not in reader.topic_infos:
        return None
    poses = [record.value for record in reader.records(["ground_truth_pose"])]
    return Trajectory.from_poses(poses) if poses else None


@click.command(epilog=EXAMPLES)
@click.argument("log", type=click.Path(path_type=Path))
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
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the estimator's random draws.")
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
    if estimator_name not in ESTIMATORS:
        known = ", ".join(sorted(ESTIMATORS)) or "none installed"
        raise UsageError(f"unknown estimator {estimator_name!r}", f"choose one of: {known}")
    spec = ESTIMATORS[estimator_name]
    config = build_config(spec, config_file, params)
    output = check_output_directory(output, command="run", inputs=[log, config_file], overwrite=overwrite)
    reader = LogReader(log, topics_from(topic_names))
    total = reader.topic_infos.get(reader.topics.depth if "depth" in spec.needs else reader.topics.points)
    with progress_bar(total.count if total else None, estimator_name, unit="iter") as bar:
        result = execute_run(
            reader, spec, config, output, seed=seed, use_odometry=not no_odometry, use_fixes=not no_fixes,
            on_iteration=lambda *_: bar.update(1), map_every=map_every, window=window,
        )  # fmt: skip
    if not ctx.find_root().obj.get("quiet"):
        timing = result.timing_summary()
        skipped = sum(reader.skipped.values()) + sum(result.skipped.values())
        click.echo(
            f"{spec.name}: {timing['iterations']} iterations, {len(result.landmarks)} landmarks, "
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
    if estimator_name not in ESTIMATORS:
        raise UsageError(f"unknown estimator {estimator_name!r}", f"choose one of: {', '.join(sorted(ESTIMATORS))}")
    spec = ESTIMATORS[estimator_name]
    click.echo(f"[{spec.name}]  # {spec.description}")
    key_settings = getattr(spec.config_class, "key_settings", {})
    if key_settings:
        click.echo("# The settings that matter (the others rarely need changing):")
        for name, why in key_settings.items():
            click.echo(f"#   {name}: {why}")
    for f in dataclasses.fields(spec.config_class):
        default = f.default if f.default is not dataclasses.MISSING else None
        help_text = f.metadata.get("help", "") or (
            spec.config_class.field_help(f.name) if hasattr(spec.config_class, "field_help") else ""
        )
        limits = spec.config_class.field_limits(f.name) if hasattr(spec.config_class, "field_limits") else None
        if limits is not None:
            help_text = f"{help_text} [{limits[0]:g} .. {limits[1]:g}]".strip()
        comment = f"  # {help_text}" if help_text else ""
        if default is None:
            click.echo(f"# {f.name} =  (unset){comment}")
        else:  # JSON scalars and arrays are valid TOML values
            value = json.dumps(list(default) if isinstance(default, tuple) else default)
            click.echo(f"{f.name} = {value}{comment}")
