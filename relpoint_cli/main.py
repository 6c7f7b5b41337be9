"""The ``relpoint`` command group."""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import signal
import sys
from typing import Any

from relpoint_app.batch_start import start_fork_server_early

if __name__ == "__main__" or os.path.basename(sys.argv[0]) == "relpoint":  # the command line, not an import
    start_fork_server_early(sys.argv[1:])  # first: ``relpoint batch`` warms its workers up from here on

import click

from relpoint_cli.errors import EXIT_INTERRUPTED, EXIT_USAGE, quiet_broken_pipe

EPILOG = """\b
Examples:
  relpoint simulate -o run.mcap --scenario figure8 --density 25 --seed 1
  relpoint simulate -o long.mcap --passes 40 --dynamic 0.3 --odometry-noise 0.05
  relpoint info run.mcap
  relpoint simulate --config sim.toml -o run.mcap

\b
Exit codes: 0 ok, 1 internal error, 2 usage error, 3 input error,
            4 estimator failure, 5 evaluation gate exceeded, 130 interrupted.
"""


def _raise_keyboard_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


class RelpointGroup(click.Group):
    """A click group whose usage errors are one line on stderr (exit 2), like every other error.

    Subcommands are listed in :data:`COMMANDS` and imported on first use.
    """

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The command list from :data:`SUMMARIES`: ``relpoint --help`` imports no command module."""
        with formatter.section("Commands"):
            formatter.write_dl([(name, SUMMARIES.get(name, "")) for name in COMMANDS])

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module_name, attribute = COMMANDS[name].split(":")
        command = getattr(importlib.import_module(module_name), attribute)
        command.name = name
        _accept_verbosity_options(command)
        return command

    def main(self, *args: Any, **kwargs: Any) -> Any:  # type: ignore[override]
        kwargs["standalone_mode"] = False
        # SIGTERM ends a run like Ctrl-C from the first instant, before any command module is imported.
        with contextlib.suppress(ValueError):  # not the main thread: leave signals alone
            signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)
        try:
            return super().main(*args, **kwargs)
        except KeyboardInterrupt:
            click.echo("relpoint: error: interrupted; no output was written", err=True)
            sys.exit(EXIT_INTERRUPTED)
        except click.UsageError as error:
            where = f"'{error.ctx.command_path} --help'" if error.ctx else "'relpoint --help'"
            click.echo(f"relpoint: error: {error.format_message()} (see {where})", err=True)
            sys.exit(EXIT_USAGE)
        except click.ClickException as error:
            click.echo(f"relpoint: error: {error.format_message()}", err=True)
            sys.exit(error.exit_code)
        except click.Abort:
            click.echo("relpoint: error: interrupted; no output was written", err=True)
            sys.exit(EXIT_INTERRUPTED)
        except click.exceptions.Exit as exit_:
            sys.exit(exit_.exit_code)
        except BrokenPipeError:
            quiet_broken_pipe()


def _set_verbosity(ctx: click.Context, *, quiet: bool = False, verbose: bool = False) -> None:
    """Record ``--quiet`` for progress bars and summaries, and set the log level to match."""
    root_ctx = ctx.find_root()
    root_ctx.ensure_object(dict)
    if quiet:
        root_ctx.obj["quiet"] = True
    quiet = bool(root_ctx.obj.get("quiet"))
    verbose = verbose or bool(root_ctx.obj.get("verbose"))
    root_ctx.obj["verbose"] = verbose
    logging.getLogger().setLevel(logging.ERROR if quiet else logging.DEBUG if verbose else logging.WARNING)
    # Third-party chatter stays out of the user's terminal unless debugging.
    for name in ("matplotlib", "PIL", "numba"):
        logging.getLogger(name).setLevel(logging.WARNING if verbose else logging.ERROR)


def _accept_verbosity_options(command: click.Command) -> None:
    """Let ``-q/--quiet`` and ``-v/--verbose`` follow the subcommand too (``relpoint run LOG ... -q``)."""
    if any(param.name == "quiet_after" for param in command.params):
        return

    def quiet(ctx: click.Context, _: click.Parameter, value: bool) -> None:
        if value:
            _set_verbosity(ctx, quiet=True)

    def verbose(ctx: click.Context, _: click.Parameter, value: bool) -> None:
        if value:
            _set_verbosity(ctx, verbose=True)

    command.params += [
        click.Option(["-q", "--quiet", "quiet_after"], is_flag=True, expose_value=False, callback=quiet,
                     help="Only errors on stderr (also accepted before the command)."),
        click.Option(["-v", "--verbose", "verbose_after"], is_flag=True, expose_value=False, callback=verbose,
                     help="Debug logging (also accepted before the command)."),
    ]  # fmt: skip


class _Formatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return f"relpoint: {record.levelname.lower()}: {record.getMessage()}"


@click.group(
    cls=RelpointGroup, epilog=EPILOG, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100}
)
@click.version_option(package_name="relpoint", prog_name="relpoint")
@click.option("-q", "--quiet", is_flag=True, help="Only errors on stderr; no progress bars or warnings.")
@click.option("-v", "--verbose", is_flag=True, help="Debug logging (and tracebacks of internal errors).")
@click.pass_context
def cli(ctx: click.Context, quiet: bool, verbose: bool) -> None:
    """relpoint: offline 3D SLAM over recorded ROS 2 (MCAP) logs.

    Simulate observation logs, run estimators over them, and evaluate the results.
    """
    ctx.ensure_object(dict)
    ctx.obj["quiet"] = quiet
    ctx.obj["verbose"] = verbose
    handler = logging.StreamHandler()
    handler.setFormatter(_Formatter())
    logging.getLogger().handlers[:] = [handler]
    _set_verbosity(ctx)


#: Every subcommand, imported only when used so that each command starts quickly.
COMMANDS: dict[str, str] = {
    "simulate": "relpoint_cli.simulate:simulate",
    "info": "relpoint_cli.info:info",
    "run": "relpoint_cli.run:run",
    "config": "relpoint_cli.run:config_command",
    "evaluate": "relpoint_cli.evaluate:evaluate",
    "compare": "relpoint_cli.compare:compare",
    "export": "relpoint_cli.export:export",
    "fuse": "relpoint_cli.fuse:fuse_command",
    "batch": "relpoint_cli.batch:batch",
    "import": "relpoint_cli.import_data:import_command",
}

#: One line a command for ``relpoint --help`` (kept here so that help starts without importing them).
SUMMARIES: dict[str, str] = {
    "simulate": "Write a simulated run (observations, ground truth, odometry, fixes, depth) to a log.",
    "info": "Show a log's topics, types, counts, duration and rates, and which estimators it suits.",
    "run": "Run an estimator over a log; write trajectory, map, timing and run.json.",
    "config": "Print an estimator's settings with their defaults and ranges, as TOML for --config.",
    "evaluate": "Evaluate a trajectory against a reference (APE, RPE, KITTI segments, landmarks).",
    "compare": "Compare several runs or evaluations: one table and one figure.",
    "export": "Export a trajectory, landmarks or a map (TUM, KITTI, CSV, PLY).",
    "fuse": "Fuse a run with the log's absolute fixes into a globally consistent path and map.",
    "batch": "Run a plan of logs x estimators x settings, evaluate each job, tabulate.",
    "import": "Convert a dataset (TUM RGB-D, 7-Scenes) to a relpoint log.",
}


def main() -> None:
    """Console entry point.

    An interrupt that lands outside a command's own handling (while click unwinds, say) still ends
    with the one-line message and exit code 130, not with Python's default SIGINT exit.
    """
    try:
        cli(prog_name="relpoint")
    except BrokenPipeError:
        quiet_broken_pipe()
    except KeyboardInterrupt:
        click.echo("relpoint: error: interrupted; no output was written", err=True)
        sys.exit(EXIT_INTERRUPTED)


if __name__ == "__main__":  # pragma: no cover
    main()
