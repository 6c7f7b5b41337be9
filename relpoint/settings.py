"""Shared behaviour of the settings dataclasses (simulation, estimators, fusion).

Every settings class is a frozen dataclass that validates itself in ``__post_init__``; this mixin
adds building from a plain mapping (a TOML/YAML table or ``--param`` pairs), where unknown keys are a
:class:`~relpoint.errors.UsageError` naming the known ones, and dumping back to a dict.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import itertools
import math
import re
import reprlib
import textwrap
from collections.abc import Iterable, Mapping
from typing import Any, ClassVar, TypeVar

from relpoint.errors import UsageError

S = TypeVar("S", bound="Settings")


#: Bounds of a numeric setting that declares none in its class's ``limits``: far outside any sensible
#: value, and inside what the arithmetic on it can take without overflowing.
DEFAULT_INT_LIMITS = (-1_000_000, 1_000_000)
DEFAULT_FLOAT_LIMITS = (-1e9, 1e9)

_TRUE = ("true", "yes", "on", "1")
_FALSE = ("false", "no", "off", "0")


def short_repr(value: Any, width: int = 60) -> str:
    """A bounded ``repr`` for messages: a huge value (a YAML alias bomb, say) is never rendered whole."""
    bounded = reprlib.Repr()
    bounded.maxlevel, bounded.maxlist, bounded.maxdict, bounded.maxstring, bounded.maxother = 2, 4, 4, width, width
    text = bounded.repr(value)
    return text if len(text) <= width else text[: width - 3] + "..."


def _kind(annotation: Any) -> tuple[str, bool]:
    """(``int``/``float``/``bool``/``str``/``other``, whether None is allowed) of a field annotation."""
    text = str(annotation).replace("typing.", "")
    optional = "None" in text
    base = text.replace(" | None", "").replace("None | ", "").replace("Optional[", "").rstrip("]").strip()
    return (base if base in ("int", "float", "bool", "str") else "other"), optional


@functools.cache
def _attribute_docs(klass: type) -> dict[str, str]:
    """``{field: docstring}`` of a class's annotated attributes followed by a string literal."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
    except (OSError, TypeError, SyntaxError):  # no source (frozen, built-in): no help
        return {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    docs: dict[str, str] = {}
    for statement, following in itertools.pairwise(body):
        if (
            isinstance(statement, ast.AnnAssign)
            and isinstance(statement.target, ast.Name)
            and isinstance(following, ast.Expr)
            and isinstance(following.value, ast.Constant)
            and isinstance(following.value.value, str)
        ):
            docs[statement.target.id] = following.value.value
    return docs


class Settings:
    """Mixin for frozen settings dataclasses; subclasses set :attr:`settings_name` (used in messages).

    Every value given from outside (a config file, ``--param``, a batch plan) goes through
    :meth:`from_mapping`, which checks it against its field's type and range before the dataclass's
    own ``__post_init__`` checks how the settings fit together. :attr:`limits` holds a class's
    ranges; a numeric field without one has :data:`DEFAULT_INT_LIMITS` or :data:`DEFAULT_FLOAT_LIMITS`.
    """

    settings_name: ClassVar[str] = "setting"
    limits: ClassVar[Mapping[str, tuple[float, float]]] = {}

    @classmethod
    def field_limits(cls, name: str) -> tuple[float, float] | None:
        """The ``(low, high)`` range of a numeric setting, or None for other kinds."""
        if name in cls.limits:
            return cls.limits[name]
        kind, _ = _kind(cls._field(name).type)
        if kind == "int":
            return DEFAULT_INT_LIMITS
        if kind == "float":
            return DEFAULT_FLOAT_LIMITS
        return None

    @classmethod
    def field_help(cls, name: str) -> str:
        """The first sentence of a setting's attribute docstring (the string literal below the field)."""
        for klass in cls.__mro__:
            text = _attribute_docs(klass).get(name)
            if text:
                first = re.split(r"\.\s+(?=[A-Z(])", " ".join(text.split()))[0].rstrip(".")
                return first.replace("``", "`") + "."
        return ""

    @classmethod
    def _field(cls, name: str) -> dataclasses.Field[Any]:
        return {f.name: f for f in dataclasses.fields(cls)}[name]  # type: ignore[arg-type]

    @classmethod
    def _check_keys(cls, keys: Iterable[str]) -> None:
        known = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        unknown = sorted(set(keys) - known)
        if unknown:
            raise UsageError(
                f"unknown {cls.settings_name} setting(s): {', '.join(str(k)[:40] for k in unknown[:10])}",
                f"known settings are {', '.join(sorted(known))}",
            )

    @classmethod
    def check_value(cls, name: str, value: Any) -> Any:
        """``value`` as field ``name`` holds it (an integral float as an int, an int as a float, a
        number as the text of a text setting); a :class:`UsageError` naming the setting, what it
        takes and what it got when it is of the wrong kind or out of range."""
        kind, optional = _kind(cls._field(name).type)
        label = f"{cls.settings_name} setting {name}"
        if value is None:
            if optional:
                return None
            raise UsageError(f"{label} needs a value")
        if kind == "bool":
            if not isinstance(value, bool):
                raise UsageError(f"{label} must be true or false, got {short_repr(value)}")
            return value
        if kind == "str":
            if isinstance(value, int | float) and not isinstance(value, bool):
                return str(value)
            if not isinstance(value, str):
                raise UsageError(f"{label} must be text, got {short_repr(value)}")
            if len(value) > 1000:
                raise UsageError(f"{label} is {len(value)} characters long, got {short_repr(value)}")
            return value
        if kind in ("int", "float"):
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise UsageError(f"{label} must be a number, got {short_repr(value)}")
            if kind == "int":
                if isinstance(value, float):
                    if not (math.isfinite(value) and value.is_integer()):
                        raise UsageError(f"{label} must be an integer, got {short_repr(value)}")
                    value = int(value)
            else:
                value = float(value)
                default = cls._field(name).default
                if math.isnan(value) or (math.isinf(value) and not (isinstance(default, float) and math.isinf(default))):
                    raise UsageError(f"{label} must be a finite number, got {value!r}")
            low, high = cls.field_limits(name) or (-math.inf, math.inf)
            if not (low <= value <= high or (math.isinf(value) and math.isinf(high) and value > 0)):
                raise UsageError(f"{label} must be between {low:g} and {high:g}, got {short_repr(value)}")
        return value

    @classmethod
    def parse_text(cls, name: str, text: str) -> Any:
        """A command-line value (``--param name=text``) read as field ``name``'s kind."""
        cls._check_keys([name])
        kind, optional = _kind(cls._field(name).type)
        stripped = text.strip()
        label = f"{cls.settings_name} setting {name}"
        if optional and stripped.lower() in ("none", "null", ""):
            return None
        if kind == "bool":
            if stripped.lower() in _TRUE:
                return True
            if stripped.lower() in _FALSE:
                return False
            raise UsageError(f"{label} must be true or false, got {short_repr(text)}")
        if kind in ("int", "float"):
            try:
                number = int(stripped) if kind == "int" and stripped.lstrip("+-").isdigit() else float(stripped)
            except ValueError:
                raise UsageError(f"{label} must be a number, got {short_repr(text)}") from None
            return number
        if kind == "str":
            return text
        for cast in (int, float):  # another kind: the most specific number, else the text
            try:
                return cast(stripped)
            except ValueError:
                pass
        return text

    @classmethod
    def from_strings(cls: type[S], items: Iterable[str], base: Mapping[str, Any] | None = None) -> S:
        """Build from ``KEY=VALUE`` items (``--param``) over ``base`` values; each value read as its field's kind."""
        values = {str(key).replace("-", "_"): value for key, value in (base or {}).items()}
        for item in items:
            if "=" not in item:
                raise UsageError(f"--param {short_repr(item)} is not KEY=VALUE")
            key, text = item.split("=", 1)
            key = key.strip().replace("-", "_")
            values[key] = cls.parse_text(key, text)
        return cls.from_mapping(values)

    @classmethod
    def from_mapping(cls: type[S], values: Mapping[str, Any]) -> S:
        """Build from a mapping; keys may use dashes or underscores; unknown keys, values of the wrong
        kind and values out of range are a UsageError."""
        normalised = {str(key).replace("-", "_"): value for key, value in values.items()}
        cls._check_keys(normalised)
        checked = {name: cls.check_value(name, value) for name, value in normalised.items()}
        try:
            return cls(**checked)
        except (TypeError, ValueError, OverflowError) as error:  # a value validation did not catch
            raise UsageError(f"bad {cls.settings_name} setting: {short_repr(str(error), 200)}") from None

    def to_dict(self) -> dict[str, Any]:
        """The settings as a plain dict (JSON-serialisable for the built-in settings)."""
        return dataclasses.asdict(self)  # type: ignore[call-overload]


def require_positive(values: Mapping[str, Any]) -> None:
    """Raise :class:`UsageError` naming the first value that is not a finite number > 0."""
    for name, value in values.items():
        if not (isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value > 0):
            raise UsageError(f"{name} must be a positive number, got {short_repr(value)}")


def require_non_negative(values: Mapping[str, Any]) -> None:
    """Raise :class:`UsageError` naming the first value that is not a finite number >= 0."""
    for name, value in values.items():
        if not (isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value >= 0):
            raise UsageError(f"{name} must be a number >= 0, got {short_repr(value)}")
