"""The ``--points-topic``-style options every log-reading command takes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from formats.log import ROLE_OPTIONS, Topics


def topic_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """Add one option per log role that renames its topic (defaults: the log format's names)."""
    defaults = Topics().roles()
    for role in reversed(list(ROLE_OPTIONS)):
        command = click.option(
            ROLE_OPTIONS[role], f"topic_{role}", default=defaults[role], show_default=True,
            help=f"Topic of the {role.replace('_', ' ')} messages.",
        )(command)  # fmt: skip
    return command


def topics_from(params: dict[str, Any]) -> Topics:
    """Build :class:`Topics` from the ``topic_*`` parameters of :func:`topic_options`."""
    return Topics(**{key.removeprefix("topic_"): value for key, value in params.items() if key.startswith("topic_")})
