"""The speed benchmarks' reference filters (benchmarks/_reference.py): an older revision's filter is built
by its own constructor and handed the state the current filter shares with it."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from _reference import carry_state, reference_config


class Gaps:
    def __init__(self) -> None:
        self.bridged = 0
        self.longest = 0.0


class Hold:
    """A helper the current filter has and the reference has not (as OdometryHold replaced ``_odometry``)."""

    def __init__(self) -> None:
        self.held = None


@dataclass(frozen=True)
class OldConfig:
    particles: int = 10
    acceleration: float = 1.0  # the reference needs a value; the current one derives it when unset


@dataclass(frozen=True)
class NewConfig:
    particles: int = 10
    acceleration: float | None = None
    follow_movers: bool = True


class OldFilter:
    def __init__(self, config: OldConfig) -> None:
        self.config = config
        self.positions = np.zeros((config.particles, 3))
        self._gaps = Gaps()
        self._odometry = None  # read by the old step, absent from the current filter

    def step(self) -> float:
        assert self._odometry is None
        return float(self.positions.sum()) + self._gaps.longest


class NewFilter:
    def __init__(self, config: NewConfig) -> None:
        self.config = config
        self.positions = np.zeros((config.particles, 3))
        self._gaps = Gaps()
        self._hold = Hold()
        self._moving = np.zeros((config.particles, 4), dtype=bool)


for cls in (Gaps, Hold, OldConfig, NewConfig, OldFilter, NewFilter):  # classes of the core package, to the helper
    cls.__module__ = "relpoint.estimators.stand_in"


def test_the_reference_keeps_what_only_it_has_and_takes_the_shared_state() -> None:
    current = NewFilter(NewConfig(particles=4))
    current.positions += 1.5
    current._gaps.bridged, current._gaps.longest = 3, 0.25
    reference = OldFilter(reference_config(current.config, OldConfig))
    assert reference.config == OldConfig(particles=4, acceleration=1.0)  # the unset value left to the reference
    kept = carry_state(reference, current)
    assert kept == ["_odometry"]
    assert reference.step() == 4 * 3 * 1.5 + 0.25  # the old step finds every attribute it reads
    assert isinstance(reference._gaps, Gaps) and reference._gaps.bridged == 3
    assert not hasattr(reference, "_hold") and not hasattr(reference, "_moving")
    current.positions += 1.0  # a copy, not the current filter's arrays
    assert reference.positions[0, 0] == 1.5
