"""Shared behaviour of the settings dataclasses (simulation, estimators, fusion).

Every settings class is a frozen dataclass that validates itself in ``__post_init__``; this mixin
adds building from a plain mapping (a TOML/YAML table or ``--param`` pairs), where unknown keys are a
:class:`~relpoint.errors.UsageError` naming the known ones, and dumping back to a dict.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any, ClassVar, TypeVar

from relpoint.errors import UsageError

S = TypeVar("S", bound="Settings")


class Settings:
    """Mixin for frozen settings dataclasses; subclasses set :attr:`settings_name` (used in messages)."""

    settings_name: ClassVar[str] = "setting"

    @classmethod
    def from_mapping(cls: type[S], values: Mapping[str, Any]) -> S:
        """Build from a mapping; keys may use dashes or underscores; unknown keys are a UsageError."""
        known = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        normalised = {str(key).replace("-", "_"): value for key, value in values.items()}
        unknown = sorted(set(normalised) - known)
        if unknown:
            raise UsageError(
                f"unknown {cls.settings_name} setting(s): {', '.join(unknown)}",
                f"known settings are {', '.join(sorted(known))}",
            )
        try:
            return cls(**normalised)
        except TypeError as error:  # a value of the wrong kind that validation did not catch
            raise UsageError(f"bad {cls.settings_name} setting: {error}") from None

    def to_dict(self) -> dict[str, Any]:
        """The settings as a plain dict (JSON-serialisable for the built-in settings)."""
        return dataclasses.asdict(self)  # type: ignore[call-overload]


def require_positive(values: Mapping[str, Any]) -> None:
    """Raise :class:`UsageError` naming the first value that is not a finite number > 0."""
    for name, value in values.items():
        if not (isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value > 0):
            raise UsageError(f"{name} must be a positive number, got {value!r}")


def require_non_negative(values: Mapping[str, Any]) -> None:
    """Raise :class:`UsageError` naming the first value that is not a finite number >= 0."""
    for name, value in values.items():
        if not (isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value >= 0):
            raise UsageError(f"{name} must be a number >= 0, got {value!r}")
