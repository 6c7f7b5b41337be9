"""Progress bars that show only on an interactive terminal and never with ``--quiet``."""

from __future__ import annotations

import os
import sys
from typing import Any

import click
from tqdm import tqdm


def progress_enabled() -> bool:
    ctx = click.get_current_context(silent=True)
    quiet = bool(ctx and ctx.find_root().obj and ctx.find_root().obj.get("quiet"))
    return not quiet and sys.stderr.isatty()


#: The terminal size assumed when the terminal reports none (0 x 0: a pseudo-terminal nobody sized,
#: as ``docker run -t`` and some CI runners give); tqdm draws nothing on a screen of no rows.
FALLBACK_COLUMNS, FALLBACK_ROWS = 80, 24


def _terminal_columns() -> int:
    """stderr's width in columns; 0 when the terminal does not say (its rows are then 0 too)."""
    try:
        return os.get_terminal_size(sys.stderr.fileno()).columns
    except (OSError, ValueError):
        return 0


def progress_bar(total: int | None, description: str, unit: str = "it") -> Any:
    """A tqdm bar on stderr, disabled when quiet or not a TTY; as wide as the terminal, or
    :data:`FALLBACK_COLUMNS` wide when the terminal reports no size."""
    enabled = progress_enabled()
    sized = enabled and _terminal_columns() > 0
    return tqdm(
        total=total,
        desc=description,
        unit=unit,
        disable=not enabled,
        leave=False,
        dynamic_ncols=sized,
        ncols=None if sized else FALLBACK_COLUMNS,
        nrows=None if sized else FALLBACK_ROWS,
    )
