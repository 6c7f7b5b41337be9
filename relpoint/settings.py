"""Shared behaviour of the settings dataclasses (simulation, estimators, fusion, evaluation).

Every settings class is a frozen dataclass that mixes in :class:`Settings` and declares what each
field takes where the field is defined, with :func:`setting` (a range, the allowed choices). The
mixin checks every field against its declaration whenever an instance is made, from a mapping or
directly; a class's own rules that relate several fields go in its :meth:`Settings.check` hook. It
also builds instances from a plain mapping (a TOML/YAML table) or ``--param KEY=VALUE`` items, where
unknown keys are a :class:`~relpoint.errors.UsageError`, and dumps them back to a dict.
"""

from __future__ import annotations

import ast
import dataclasses
import enum
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


#: Bounds of a numeric setting whose declaration leaves one open: far outside any sensible value,
#: and inside what the arithmetic on it can take without overflowing.
DEFAULT_INT_LIMITS = (-1_000_000, 1_000_000)
DEFAULT_FLOAT_LIMITS = (-1e9, 1e9)
#: Longest text a text setting takes, in characters.
MAX_TEXT = 1000

_TRUE = ("true", "yes", "on", "1")
_FALSE = ("false", "no", "off", "0")


def short_repr(value: Any, width: int = 60) -> str:
    """A bounded ``repr`` for messages: a huge value (a YAML alias bomb, say) is never rendered whole."""
    if isinstance(value, enum.Enum):
        value = value.value
    bounded = reprlib.Repr()
    bounded.maxlevel, bounded.maxlist, bounded.maxdict, bounded.maxstring, bounded.maxother = 2, 4, 4, width, width
    text = bounded.repr(value)
    return text if len(text) <= width else text[: width - 3] + "..."


def split_item(item: str, option: str = "--param") -> tuple[str, str]:
    """``(key, text)`` of one ``KEY=VALUE`` command-line item, the key stripped; a :class:`UsageError`
    naming ``option`` when the item has no ``=`` or no key."""
    key, sep, text = item.partition("=")
    if not sep or not key.strip():
        raise UsageError(f"{option} {short_repr(item)} is not KEY=VALUE")
    return key.strip(), text


@dataclasses.dataclass(frozen=True)
class Rule:
    """What a setting takes, as :func:`setting` declares it.

    ``low``/``high`` are inclusive bounds, ``above``/``below`` exclusive ones (at most one of each
    pair); an open side of a numeric setting is :data:`DEFAULT_INT_LIMITS` or
    :data:`DEFAULT_FLOAT_LIMITS`. An infinite bound takes every finite value on its side, and the
    infinity itself only when it is inclusive (``high=math.inf``). ``also`` are values taken besides
    the range (``-1`` for "all", say); ``choices`` the only values taken, when given. A tuple setting
    applies the rule to each item.
    """

    low: float | None = None
    high: float | None = None
    above: float | None = None
    below: float | None = None
    choices: tuple[Any, ...] | None = None
    also: tuple[Any, ...] = ()

    @property
    def declared(self) -> bool:
        """Whether the rule says anything (a bound or the choices)."""
        return self.choices is not None or any(
            bound is not None for bound in (self.low, self.high, self.above, self.below)
        )

    def bounds(self, kind: str) -> tuple[float, float, bool, bool]:
        """``(lower, upper, lower_included, upper_included)`` of a numeric setting of ``kind`` (int/float)."""
        low, high = DEFAULT_INT_LIMITS if kind == "int" else DEFAULT_FLOAT_LIMITS
        lower, lower_in = (self.above, False) if self.above is not None else (self.low, True)
        upper, upper_in = (self.below, False) if self.below is not None else (self.high, True)
        return (low if lower is None else lower, high if upper is None else upper, lower_in, upper_in)

    def admits(self, value: float, kind: str) -> bool:
        """Whether the number ``value`` (not NaN) lies in the range of a setting of ``kind`` or in :attr:`also`."""
        if value in self.also:
            return True
        lower, upper, lower_in, upper_in = self.bounds(kind)
        return (lower <= value if lower_in else lower < value) and (value <= upper if upper_in else value < upper)

    def describe(self, kind: str) -> str:
        """What the rule takes, in words (``between 0 and 1``, ``one of nn, jcbb``) for a setting of ``kind``."""
        if self.choices is not None:
            return "one of " + ", ".join(_show(choice) for choice in self.choices)
        lower, upper, lower_in, upper_in = self.bounds(kind)
        if math.isinf(upper):
            text = f"at least {lower:g}" if lower_in else f"above {lower:g}"
        elif lower_in and upper_in:
            text = f"between {lower:g} and {upper:g}"
        elif not (lower_in or upper_in):
            text = f"strictly between {lower:g} and {upper:g}"
        else:
            text = (
                f"between {lower:g}{'' if lower_in else ' (excluded)'} and {upper:g}{'' if upper_in else ' (excluded)'}"
            )
        return " or ".join([*(_show(value) for value in self.also), text])


def _show(value: Any) -> str:
    """A choice as a message lists it: an enum member by its value, text bare."""
    value = value.value if isinstance(value, enum.Enum) else value
    return value if isinstance(value, str) else f"{value:g}" if isinstance(value, float) else str(value)


def setting(
    default: Any = dataclasses.MISSING,
    *,
    low: float | None = None,
    high: float | None = None,
    above: float | None = None,
    below: float | None = None,
    choices: Iterable[Any] | None = None,
    also: Iterable[Any] = (),
    help: str = "",
) -> Any:
    """A settings field with its :class:`Rule`: ``low``/``high`` inclusive bounds, ``above``/``below``
    exclusive ones (``above=0``: positive), ``choices`` the values taken, ``also`` values taken
    besides the range; ``help`` the field's help text where a command builds options from it (the
    other classes keep their help in the attribute docstring below the field)."""
    if (low is not None and above is not None) or (high is not None and below is not None):
        raise TypeError("give one lower bound (low or above) and one upper bound (high or below)")
    rule = Rule(low, high, above, below, None if choices is None else tuple(choices), tuple(also))
    metadata = {"rule": rule, **({"help": help} if help else {})}
    return dataclasses.field(default=default, metadata=metadata)


def _kind(annotation: Any) -> tuple[str, bool]:
    """(``int``/``float``/``bool``/``str``/``tuple``/``other``, whether None is allowed) of a field annotation."""
    text = str(annotation).replace("typing.", "")
    optional = "None" in text
    base = text.replace(" | None", "").replace("None | ", "").replace("Optional[", "").rstrip("]").strip()
    if base.startswith(("tuple[", "Tuple[")):
        return "tuple", optional
    return (base if base in ("int", "float", "bool", "str") else "other"), optional


def _item_kind(annotation: Any) -> str:
    """The kind of the items of a ``tuple[int, ...]`` / ``tuple[float, ...]`` annotation (``other`` else)."""
    found = re.search(r"tuple\[\s*(\w+)", str(annotation), re.IGNORECASE)
    return found.group(1) if found and found.group(1) in ("int", "float") else "other"


@dataclasses.dataclass(frozen=True)
class _Field:
    """A settings field as the checks see it."""

    name: str
    kind: str
    optional: bool
    item_kind: str
    rule: Rule


@functools.cache
def _fields(klass: type) -> dict[str, _Field]:
    return {
        f.name: _Field(f.name, *_kind(f.type), _item_kind(f.type), f.metadata.get("rule", Rule()))
        for f in dataclasses.fields(klass)
    }


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


def is_number(value: Any) -> bool:
    """Whether ``value`` is an int or a float (a bool is not a number here)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


class Settings:
    """Mixin for frozen settings dataclasses; subclasses set :attr:`settings_name` (used in messages).

    Making an instance checks it: :meth:`normalise` first, then every field against its kind and the
    :class:`Rule` its :func:`setting` declares (a numeric field that declares none has
    :data:`DEFAULT_INT_LIMITS` or :data:`DEFAULT_FLOAT_LIMITS`), then :meth:`check`. Any failure is a
    one-line :class:`UsageError` naming the setting, what it takes and what it got. Values from
    outside (a config file, ``--param``, a batch plan) come in through :meth:`from_mapping` or
    :meth:`from_strings`, which also reject unknown keys.
    """

    settings_name: ClassVar[str] = "setting"
    #: Where to look for the settings, said after an unknown key; empty: the known settings are listed.
    settings_hint: ClassVar[str] = ""

    def __post_init__(self) -> None:
        """Check the new instance: :meth:`normalise`, each field against its rule, then :meth:`check`."""
        self.normalise()
        for spec in _fields(type(self)).values():
            value = getattr(self, spec.name)
            if spec.kind == "tuple" and isinstance(value, list):
                value = tuple(value)
                object.__setattr__(self, spec.name, value)
            self._check_field(spec, value)
        self.check()

    def normalise(self) -> None:
        """Bring given values to the form the fields hold (text to an enum member, say) before the
        checks; a hook for subclasses (set fields with ``object.__setattr__``)."""

    def check(self) -> None:
        """Rules that relate several settings, run once every field has passed its own check; a hook
        for subclasses (raise :class:`UsageError`)."""

    @classmethod
    def _check_field(cls, spec: _Field, value: Any) -> None:
        label = f"{cls.settings_name} setting {spec.name}"
        if value is None:
            if not spec.optional:
                raise UsageError(f"{label} needs a value")
            return
        if spec.kind == "tuple":
            if not isinstance(value, tuple):
                raise UsageError(f"{label} must be a list, got {short_repr(value)}")
            for index, item in enumerate(value):
                cls._check_value(f"{label}[{index}]", spec.item_kind, spec.rule, item)
            return
        cls._check_value(label, spec.kind, spec.rule, value)

    @staticmethod
    def _check_value(label: str, kind: str, rule: Rule, value: Any) -> None:
        """Raise :class:`UsageError` unless ``value`` is of ``kind`` and meets ``rule``."""
        if kind == "bool":
            if not isinstance(value, bool):
                raise UsageError(f"{label} must be true or false, got {short_repr(value)}")
            return
        if kind == "str":
            if not isinstance(value, str):
                raise UsageError(f"{label} must be text, got {short_repr(value)}")
            if len(value) > MAX_TEXT:
                raise UsageError(f"{label} must be at most {MAX_TEXT} characters, got {short_repr(value)}")
        elif kind in ("int", "float"):
            if kind == "int" and not (isinstance(value, int) and not isinstance(value, bool)):
                raise UsageError(f"{label} must be an integer, got {short_repr(value)}")
            if not is_number(value):
                raise UsageError(f"{label} must be a number, got {short_repr(value)}")
            if math.isnan(value):
                raise UsageError(f"{label} must be a finite number {rule.describe(kind)}, got {value!r}")
            if rule.choices is None and not rule.admits(value, kind):
                finite = "a finite number " if math.isinf(value) else ""
                raise UsageError(f"{label} must be {finite}{rule.describe(kind)}, got {short_repr(value)}")
        if rule.choices is not None and value not in rule.choices:
            raise UsageError(f"{label} must be {rule.describe(kind)}, got {short_repr(value)}")

    @classmethod
    def field_rule(cls, name: str) -> Rule:
        """The :class:`Rule` field ``name`` declares (an empty one when it declares none)."""
        return _fields(cls)[name].rule

    @classmethod
    def field_limits(cls, name: str) -> tuple[float, float] | None:
        """The ``(low, high)`` range of a numeric setting (or of each item of a numeric tuple), or None
        for other kinds and for settings with choices."""
        spec = _fields(cls)[name]
        kind = spec.item_kind if spec.kind == "tuple" else spec.kind
        if kind not in ("int", "float") or spec.rule.choices is not None:
            return None
        low, high, _, _ = spec.rule.bounds(kind)
        return low, high

    @classmethod
    def field_range(cls, name: str) -> str | None:
        """What a setting takes, as ``relpoint config`` shows it: ``[low .. high]`` (a parenthesis at an
        excluded bound, each item of a tuple setting), ``{a, b}`` for choices; None for other settings."""
        spec = _fields(cls)[name]
        if spec.rule.choices is not None:
            return "{" + ", ".join(_show(choice) for choice in spec.rule.choices) + "}"
        kind = spec.item_kind if spec.kind == "tuple" else spec.kind
        if kind not in ("int", "float"):
            return None
        low, high, low_in, high_in = spec.rule.bounds(kind)
        interval = f"{'[' if low_in else '('}{low:g} .. {high:g}{']' if high_in else ')'}"
        return " or ".join([*(_show(value) for value in spec.rule.also), interval])

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
    def _check_keys(cls, keys: Iterable[str]) -> None:
        """Raise :class:`UsageError` naming the keys that are no field, with :attr:`settings_hint`."""
        known = _fields(cls)
        unknown = sorted(set(keys) - set(known))
        if unknown:
            raise UsageError(
                f"unknown {cls.settings_name} setting(s): {', '.join(str(k)[:40] for k in unknown[:10])}",
                cls.settings_hint or f"known settings are {', '.join(sorted(known))}",
            )

    @classmethod
    def coerce_value(cls, name: str, value: Any) -> Any:
        """``value`` from outside as field ``name`` holds it where that loses nothing: an integral float
        as an int, an int as a float, a number as the text of a text setting, a list as a tuple.
        Anything else is returned unchanged for the checks to judge."""
        spec = _fields(cls)[name]
        kind = spec.item_kind if spec.kind == "tuple" else spec.kind
        if spec.kind == "tuple" and isinstance(value, list | tuple):
            return tuple(cls._coerce(kind, item) for item in value)
        if spec.kind == "str" and is_number(value):
            return str(value)
        return cls._coerce(kind, value)

    @staticmethod
    def _coerce(kind: str, value: Any) -> Any:
        if kind == "int" and isinstance(value, float) and value.is_integer():
            return int(value)
        if kind == "float" and is_number(value) and not isinstance(value, float):
            try:
                return float(value)
            except OverflowError:  # beyond any float: the range check says so
                return value
        return value

    @classmethod
    def parse_text(cls, name: str, text: str) -> Any:
        """A command-line value (``--param name=text``) read as field ``name``'s kind; a list setting
        takes comma-separated numbers (``4,5,10``, brackets optional)."""
        cls._check_keys([name])
        spec = _fields(cls)[name]
        stripped = text.strip()
        label = f"{cls.settings_name} setting {name}"
        if spec.optional and stripped.lower() in ("none", "null", ""):
            return None
        if spec.kind == "bool":
            if stripped.lower() in _TRUE:
                return True
            if stripped.lower() in _FALSE:
                return False
            raise UsageError(f"{label} must be true or false, got {short_repr(text)}")
        if spec.kind in ("int", "float"):
            number = _parse_number(spec.kind, stripped)
            if number is None:
                raise UsageError(f"{label} must be a number, got {short_repr(text)}")
            return number
        if spec.kind == "tuple":
            items = [item.strip() for item in stripped.strip("()[]").split(",") if item.strip()]
            numbers = [_parse_number(spec.item_kind, item) for item in items]
            if any(number is None for number in numbers):
                raise UsageError(f"{label} must be comma-separated numbers, got {short_repr(text)}")
            return tuple(numbers)
        number = _parse_number("other", stripped) if spec.kind == "other" else None
        return text if number is None else number  # another kind: the most specific number, else the text

    @classmethod
    def from_strings(cls: type[S], items: Iterable[str], base: Mapping[str, Any] | None = None) -> S:
        """Build from ``KEY=VALUE`` items (``--param``) over ``base`` values; each value read as its
        field's kind. Every unknown key, of ``base`` and the items, is named at once."""
        values = {str(key).replace("-", "_"): value for key, value in (base or {}).items()}
        pairs = [split_item(item) for item in items]
        parsed = [(key.replace("-", "_"), text) for key, text in pairs]
        cls._check_keys([*values, *(key for key, _ in parsed)])
        values.update((key, cls.parse_text(key, text)) for key, text in parsed)
        return cls.from_mapping(values)

    @classmethod
    def from_mapping(cls: type[S], values: Mapping[str, Any]) -> S:
        """Build from a mapping; keys may use dashes or underscores. Unknown keys, values of the wrong
        kind and values out of range are a :class:`UsageError`."""
        normalised = {str(key).replace("-", "_"): value for key, value in values.items()}
        cls._check_keys(normalised)
        coerced = {name: cls.coerce_value(name, value) for name, value in normalised.items()}
        try:
            return cls(**coerced)
        except (TypeError, ValueError, OverflowError) as error:  # a value the checks did not foresee
            raise UsageError(f"bad {cls.settings_name} setting: {short_repr(str(error), 200)}") from None

    def to_dict(self) -> dict[str, Any]:
        """The settings as a plain dict (JSON-serialisable for the built-in settings)."""
        return dataclasses.asdict(self)  # type: ignore[call-overload]


def _parse_number(kind: str, text: str) -> int | float | None:
    """``text`` as a number of ``kind`` (an int where the text is one, else a float), None when it is none.

    Python's ``int``/``float`` read ``1_0`` as 10: a digit separator there is more likely a typo than
    meant, so it is no number.
    """
    if "_" in text:
        return None
    if kind != "float" and text.lstrip("+-").isdigit():
        return int(text)
    try:
        return float(text)
    except ValueError:
        return None
