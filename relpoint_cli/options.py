"""Click options generated from config dataclasses, so ``--help``, config files and defaults agree."""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable
from typing import Any

import click
from click.core import ParameterSource

_TYPES = {"int": int, "float": float, "str": str, "bool": bool}


class FiniteFloatRange(click.FloatRange):
    """A float range that also refuses NaN and infinity (NaN passes every comparison of ``FloatRange``)."""

    name = "float"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return number


def _click_type(annotation: str) -> Any:
    base = annotation.replace(" | None", "").replace("None | ", "").strip()
    return _TYPES.get(base, str)


def _plain(text: str) -> str:
    return re.sub(r"``(.*?)``", r"\1", text)


def config_options(
    config_class: type, *, skip: tuple[str, ...] = (), choices: dict[str, tuple[str, ...]] | None = None
) -> Callable[[Any], Any]:
    """Decorator adding one ``--option`` per field of ``config_class`` (default shown, None = unset)."""
    choices = choices or {}

    def decorate(command: Any) -> Any:
        for f in reversed(dataclasses.fields(config_class)):
            if f.name in skip:
                continue
            option_type = click.Choice(choices[f.name]) if f.name in choices else _click_type(str(f.type))
            default = f.default if f.default is not dataclasses.MISSING else None
            command = click.option(
                f"--{f.name.replace('_', '-')}",
                f.name,
                type=option_type,
                default=default,
                show_default=default is not None,
                help=_plain(f.metadata.get("help", "")),
            )(command)
        return command

    return decorate


def explicit_options(ctx: click.Context, names: list[str]) -> dict[str, Any]:
    """The options among ``names`` the user actually gave on the command line."""
    return {
        name: ctx.params[name]
        for name in names
        if name in ctx.params and ctx.get_parameter_source(name) not in (ParameterSource.DEFAULT, None)
    }


def input_path(*, file_okay: bool = True, dir_okay: bool = True) -> click.Path:
    """The click type of an input file or directory: its permissions are left to the reader, which names the
    file and the way out with exit 3 (click would call an unreadable input a usage error)."""
    from pathlib import Path

    return click.Path(file_okay=file_okay, dir_okay=dir_okay, readable=False, path_type=Path)


def overwrite_option(command: Any) -> Any:
    """``--overwrite``: replace an output that relpoint did not recognisably write (never an input)."""
    return click.option(
        "--overwrite",
        is_flag=True,
        help="Replace an existing output file, or another relpoint command's output directory. "
        "Inputs and directories holding other files are never replaced.",
    )(command)


def read_paths(*paths: Any) -> list[Any]:
    """The files a command reads: each path given, and the files directly inside a directory given."""
    import os

    found: list[Any] = []
    for path in paths:
        if path is None:
            continue
        found.append(path)
        if os.path.isdir(path):
            with os.scandir(path) as entries:
                found.extend(entry.path for entry in entries if entry.is_file())
    return found


def check_tf_chain(parent: str | None, child: str | None, options: tuple[str, str] = ("--parent", "--child")) -> None:
    """``--parent`` and ``--child`` (or the two ``options`` named) come together (exit 2 before any input
    is read)."""
    from relpoint.errors import UsageError

    if (parent is None) != (child is None):
        given, missing = options if child is None else options[::-1]
        raise UsageError(f"{given} without {missing}: a TF chain needs both", f"add {missing} FRAME")


def time_window_options(command: Any) -> Any:
    """``--t-start`` and ``--t-end``: seconds after the first stamp (of the log, or of the reference)."""
    command = click.option("--t-end", type=float, help="Use nothing after this many seconds from the first stamp.")(
        command
    )
    return click.option("--t-start", type=float, help="Use nothing before this many seconds from the first stamp.")(
        command
    )


def time_window(t_start: float | None, t_end: float | None) -> Any:
    """The :class:`~relpoint.types.TimeWindow` of ``--t-start``/``--t-end`` (exit 2 when it is empty)."""
    from relpoint.errors import UsageError
    from relpoint.types import TimeWindow

    try:
        return TimeWindow(t_start, t_end)
    except ValueError as error:
        raise UsageError(f"--t-start/--t-end: {error}") from None
