"""Progress bars that show only on an interactive terminal and never with ``--quiet``."""

from __future__ import annotations

import sys
from typing import Any

import click
from tqdm import tqdm


def progress_enabled() -> bool:
    ctx = click.get_current_context(silent=True)
    quiet = bool(ctx and ctx.find_root().obj and ctx.find_root().obj.get("quiet"))
    return not quiet and sys.stderr.isatty()


def progress_bar(total: int | None, description: str, unit: str = "it") -> Any:
    """A tqdm bar on stderr, disabled when quiet or not a TTY."""
    return tqdm(
        total=total, desc=description, unit=unit, disable=not progress_enabled(), leave=False, dynamic_ncols=True
    )
