"""``relpoint simulate``: write a simulated scenario as a relpoint log."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import click

from formats.config_files import load_settings
from formats.log import COMPRESSIONS
from formats.outputs import check_output_file
from relpoint.errors import UsageError
from relpoint.simulation import MOVER_MOTIONS, SCENARIOS, SimulationConfig
from relpoint.simulation import simulate as make_simulation
from relpoint_app.simulation import write_simulation
from relpoint_cli.errors import handle_errors
from relpoint_cli.options import config_options, explicit_options, overwrite_option
from relpoint_cli.progress import progress_bar

EXAMPLES = """\b
Examples:
  relpoint simulate -o fig8.mcap                         # one figure-eight pass, density 25
  relpoint simulate -o fig8.mcap --iterations 900 --noise 0.3 --seed 7
  relpoint simulate -o dyn.mcap --dynamic 0.3 --clutter 2
  relpoint simulate -o odo.mcap --odometry-noise 0.05 --fix-every 20 --fix-noise 1.5
  relpoint simulate -o still.mcap --scenario stationary
  relpoint simulate -o fast.mcap --scenario corridor --density 550
  relpoint simulate -o room.mcap --scenario room --resolution 640x480 --iterations 300
  relpoint simulate -o run.mcap --config sim.toml        # settings from TOML/YAML; options override

A config file holds the same settings by name (dashes or underscores), e.g. in TOML:

\b
  scenario = "figure8"
  density = 100
  noise = 0.3
"""


@click.command(epilog=EXAMPLES)
@click.option(
    "-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True, help="The .mcap file to write."
)
@click.option(
    "--config", "config_file", type=click.Path(dir_okay=False, path_type=Path), help="TOML or YAML file of settings."
)
@click.option(
    "--compression",
    type=click.Choice(sorted(COMPRESSIONS)),
    default="zstd",
    show_default=True,
    help="MCAP chunk compression.",
)
@click.option("--resolution", type=click.Choice(["320x240", "640x480"]), help="Image size (scenario room only).")
@config_options(SimulationConfig, choices={"scenario": (*SCENARIOS, "room"), "mover_motion": MOVER_MOTIONS})
@overwrite_option
@click.pass_context
@handle_errors
def simulate(
    ctx: click.Context,
    output: Path,
    config_file: Path | None,
    compression: str,
    resolution: str | None,
    overwrite: bool,
    **settings: Any,
) -> None:
    """Write a simulated run (observations, ground truth, odometry, fixes) to an MCAP log.

    The scenario room renders depth and colour images of a furnished room instead (for the dense
    estimator) and writes the room's surface samples beside the log as LOG.scene.ply.
    """
    check_output_file(output, inputs=[config_file], overwrite=overwrite)
    values: dict[str, Any] = {}
    if config_file is not None:
        values.update(load_settings(config_file, section="simulate"))
    names = [f.name for f in dataclasses.fields(SimulationConfig)]
    if explicit_options(ctx, ["scenario"]).get("scenario", values.get("scenario")) == "room":
        simulate_room(ctx, output, compression, resolution, values, explicit_options(ctx, names))
        return
    if resolution is not None:
        raise UsageError("--resolution applies to the room scenario only")
    defaults = {name: settings[name] for name in names}
    merged = {**defaults, **values, **explicit_options(ctx, names)}
    config = SimulationConfig.from_mapping(merged)
    simulation = make_simulation(config)
    with progress_bar(len(simulation), "simulate", unit="iter") as bar:
        counts = write_simulation(simulation, output, compression=compression, on_step=lambda _: bar.update(1))
    size = output.stat().st_size
    click.echo(
        f"wrote {output}: {counts['points']} iterations, {len(simulation.landmarks.ids)} landmarks "
        f"({int(simulation.landmarks.dynamic.sum())} dynamic), {size / 1e6:.2f} MB",
        err=True,
    ) if not ctx.find_root().obj.get("quiet") else None


def explicit_overwrite(ctx: click.Context) -> bool:
    """Whether ``--overwrite`` was given."""
    return bool(ctx.params.get("overwrite"))


#: Point-scenario options that carry over to the room scenario, under the room's own names.
_ROOM_OPTIONS = {"iterations": "frames", "rate": "rate", "seed": "seed"}


def simulate_room(
    ctx: click.Context, output: Path, compression: str, resolution: str | None,
    file_values: dict[str, Any], explicit: dict[str, Any],
) -> None:  # fmt: skip
    """``relpoint simulate --scenario room``: an RGB-D log of a rendered room and its reference cloud."""
    from relpoint.simulation.rgbd import RgbdConfig, simulate_rgbd
    from relpoint_app.simulation import write_rgbd_simulation, write_scene_cloud

    unused = sorted(set(explicit) - set(_ROOM_OPTIONS) - {"scenario"})
    if unused:
        raise UsageError(
            f"option(s) {', '.join('--' + n.replace('_', '-') for n in unused)} do not apply to the room scenario",
            "room settings go in a --config file (see docs/dense.md)",
        )
    values = {key: value for key, value in file_values.items() if key != "scenario"}
    values.update({_ROOM_OPTIONS[name]: value for name, value in explicit.items() if name in _ROOM_OPTIONS})
    if resolution is not None:
        values["resolution"] = resolution
    config = RgbdConfig.from_mapping(values)
    check_output_file(output.with_suffix(".scene.ply"), inputs=[output], overwrite=explicit_overwrite(ctx))
    simulation = simulate_rgbd(config)
    with progress_bar(len(simulation), "render", unit="frame") as bar:
        counts = write_rgbd_simulation(simulation, output, compression=compression, on_frame=lambda _: bar.update(1))
    scene = output.with_suffix(".scene.ply")
    samples = write_scene_cloud(simulation, scene)
    if not ctx.find_root().obj.get("quiet"):
        click.echo(
            f"wrote {output}: {counts['depth']} depth frames at {config.resolution}, "
            f"{output.stat().st_size / 1e6:.2f} MB; scene reference cloud {scene} ({samples} points)",
            err=True,
        )
