"""Reading settings files (TOML or YAML) for ``--config``."""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from relpoint.errors import UsageError

if TYPE_CHECKING:
    import yaml

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


#: Largest settings file or plan read, bytes: far above any real one, and bounded before parsing.
MAX_DOCUMENT_BYTES = 1_000_000

#: Most YAML nodes a document may expand to once aliases are followed (an alias bomb is refused).
MAX_YAML_NODES = 100_000

_SUFFIXES = (".toml", ".yaml", ".yml", ".json")


def _read_text(path: Path, what: str) -> str:
    """The file's text, read only up to :data:`MAX_DOCUMENT_BYTES` (so ``/dev/zero`` is safe)."""
    try:
        with path.open("rb") as stream:
            data = stream.read(MAX_DOCUMENT_BYTES + 1)
    except IsADirectoryError:
        raise UsageError(f"{what} {path} is a directory", "give a .toml or .yaml file") from None
    except OSError as error:
        raise UsageError(f"cannot read {what} {path}: {error.strerror or error}") from None
    if len(data) > MAX_DOCUMENT_BYTES:
        raise UsageError(f"{what} {path} is larger than {MAX_DOCUMENT_BYTES // 1_000_000} MB", "is it the right file?")
    if b"\x00" in data:
        raise UsageError(f"{what} {path} is a binary file, not TOML or YAML text", "is it the right file?")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise UsageError(f"{what} {path} is not UTF-8 text (byte {error.start})", "save it as UTF-8") from None


@functools.cache
def _bounded_loader() -> type[yaml.SafeLoader]:
    """A safe YAML loader that refuses documents whose aliases expand beyond :data:`MAX_YAML_NODES`
    (made when first needed: PyYAML is imported for YAML files only)."""
    import yaml

    class BoundedLoader(yaml.SafeLoader):
        def compose_document(self) -> yaml.Node:
            node = super().compose_document()
            _check_expanded_size(node)
            return node

    return BoundedLoader


def _check_expanded_size(root: yaml.Node) -> None:
    """Count the nodes a document expands to (an alias counts every time it is used), up to the bound."""
    import yaml

    count = 0
    stack: list[yaml.Node] = [root]
    while stack:
        node = stack.pop()
        count += 1
        if count > MAX_YAML_NODES:
            raise UsageError(f"document expands to more than {MAX_YAML_NODES} values (YAML aliases)",
                             "write the settings out without nested aliases")  # fmt: skip
        if isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)
        elif isinstance(node, yaml.MappingNode):
            for key, value in node.value:
                stack.append(key)
                stack.append(value)


def read_document(path: str | os.PathLike[str], what: str = "config file") -> dict[str, Any]:
    """A TOML (``.toml``) or YAML (``.yaml``/``.yml``/``.json``) file as a mapping.

    The suffix is checked before anything is read, at most :data:`MAX_DOCUMENT_BYTES` are read, and
    YAML aliases may not expand past :data:`MAX_YAML_NODES` values. Raises :class:`UsageError` naming
    ``what``, the file and the problem when it cannot be read, is binary, has another suffix, does
    not parse, or does not hold a table.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _SUFFIXES:
        raise UsageError(f"{what} {path} must end in .toml, .yaml or .yml")
    text = _read_text(path, what)
    if suffix == ".toml":
        unparsable: tuple[type[BaseException], ...] = (tomllib.TOMLDecodeError, RecursionError)
    else:
        import yaml  # here, not at import: a TOML file does not need PyYAML

        unparsable = (yaml.YAMLError, RecursionError)
    try:
        if suffix == ".toml":
            data: Any = tomllib.loads(text)
        else:
            data = yaml.load(text, Loader=_bounded_loader())
    except UsageError as error:
        raise UsageError(f"{what} {path}: {error.message}", error.hint) from None
    except unparsable as error:
        first = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise UsageError(f"{what} {path} is not valid {suffix[1:].upper()}: {first[:200]}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise UsageError(f"{what} {path} must hold a table of settings, not a {type(data).__name__}")
    return data


def load_settings(path: str | os.PathLike[str], section: str | None = None) -> dict[str, Any]:
    """Settings from a ``.toml``, ``.yaml``/``.yml`` (or ``.json``) file as a flat mapping.

    With ``section``, a table of that name is used if the file has one (so one file can hold the
    settings of several commands, e.g. ``[simulate]``), and the file's other tables are ignored;
    without one, a table in the file is an error. Raises :class:`UsageError` naming the file and
    the problem when it cannot be read or parsed.
    """
    data = read_document(path)
    if section and isinstance(data.get(section), dict):
        data = data[section]
    nested = [key for key, value in data.items() if isinstance(value, dict)]
    if nested and section:
        # Other tables are ignored beside a [section] table: one file may hold several estimators' settings.
        tables = ", ".join(f"[{key}]" for key in nested)
        raise UsageError(
            f"config file {path}: {tables} {'is' if len(nested) == 1 else 'are'} for another estimator or command, "
            f"and the file has no [{section}] table",
            f"put {section}'s settings under [{section}] (the other tables are then ignored), or run what {tables} "
            f"{'is' if len(nested) == 1 else 'are'} for",
        )
    if nested:
        raise UsageError(f"config file {path}: unexpected table(s) {', '.join(nested)}")
    return data
