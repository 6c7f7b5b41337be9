"""``relpoint simulate``: write a simulated scenario as a relpoint log."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import click

from formats.config_files import load_settings
from formats.log import COMPRESSIONS
from formats.simulation_log import write_simulation
from relpoint.simulation import SCENARIOS, SimulationConfig
from relpoint.simulation import simulate as make_simulation
from relpoint_cli.errors import handle_errors
from relpoint_cli.options import config_options, explicit_options
from relpoint_cli.progress import progress_bar

EXAMPLES = """\b
Examples:
  relpoint simulate -o fig8.mcap                         # one figure-eight pass, density 25
  relpoint simulate -o fig8.mcap --iterations 900 --noise 0.3 --seed 7
  relpoint simulate -o dyn.mcap --dynamic 0.3 --clutter 2
  relpoint simulate -o odo.mcap --odometry-noise 0.05 --fix-every 20 --fix-noise 1.5
  relpoint simulate -o still.mcap --scenario stationary
  relpoint simulate -o fast.mcap --scenario corridor --density 550
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
@config_options(SimulationConfig, choices={"scenario": SCENARIOS})
@click.pass_context
@handle_errors
def simulate(ctx: click.Context, output: Path, config_file: Path | None, compression: str, **settings: Any) -> None:
    """Write a simulated run (observations, ground truth, odometry, fixes) to an MCAP log."""
    values: dict[str, Any] = {}
    if config_file is not None:
        values.update(load_settings(config_file, section="simulate"))
    names = [f.name for f in dataclasses.fields(SimulationConfig)]
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
