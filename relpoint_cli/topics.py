"""The ``--points-topic``-style options every log-reading command takes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from formats.log import ROLE_OPTIONS, ROLE_TYPES, Topics
from relpoint.errors import UsageError


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
    """Build :class:`Topics` from the ``topic_*`` parameters of :func:`topic_options`.

    Raises :class:`UsageError` when two roles of one message type are given one topic: its messages can
    serve only one of them (depth and colour images share a type, so such a log read as colour failed on
    the depth). Roles of other types on one topic are told apart by the type check of the log reader.
    """
    topics = Topics(**{key.removeprefix("topic_"): value for key, value in params.items() if key.startswith("topic_")})
    roles_of: dict[tuple[str, str], list[str]] = {}
    for role, topic in topics.roles().items():
        roles_of.setdefault((topic, ROLE_TYPES[role]), []).append(role)
    for (topic, _), roles in roles_of.items():
        if len(roles) > 1:
            options = " and ".join(ROLE_OPTIONS[role] for role in roles)
            raise UsageError(
                f"{options} both name {topic}: each role needs a topic of its own", "name the right topics"
            )
    return topics
