"""Reading settings files (TOML or YAML) for ``--config``."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import yaml

from relpoint.errors import UsageError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def read_document(path: str | os.PathLike[str], what: str = "config file") -> dict[str, Any]:
    """A TOML (``.toml``) or YAML (``.yaml``/``.yml``/``.json``) file as a mapping.

    Raises :class:`UsageError` naming ``what``, the file and the problem when it cannot be read, has
    another suffix, does not parse, or does not hold a table.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise UsageError(f"cannot read {what} {path}: {error.strerror or error}") from None
    suffix = path.suffix.lower()
    try:
        if suffix == ".toml":
            data: Any = tomllib.loads(text)
        elif suffix in (".yaml", ".yml", ".json"):
            data = yaml.safe_load(text)
        else:
            raise UsageError(f"{what} {path} must end in .toml, .yaml or .yml")
    except (tomllib.TOMLDecodeError, yaml.YAMLError) as error:
        raise UsageError(f"{what} {path} is not valid {suffix[1:].upper()}: {error}".splitlines()[0]) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise UsageError(f"{what} {path} must hold a table of settings, not a {type(data).__name__}")
    return data


def load_settings(path: str | os.PathLike[str], section: str | None = None) -> dict[str, Any]:
    """Settings from a ``.toml``, ``.yaml``/``.yml`` (or ``.json``) file as a flat mapping.

    With ``section``, a table of that name is used if the file has one (so one file can hold the
    settings of several commands, e.g. ``[simulate]``). Raises :class:`UsageError` naming the file and
    the problem when it cannot be read or parsed.
    """
    data = read_document(path)
    if section and isinstance(data.get(section), dict):
        data = data[section]
    nested = [key for key, value in data.items() if isinstance(value, dict)]
    if nested:
        raise UsageError(f"config file {path}: unexpected table(s) {', '.join(nested)}")
    return data
