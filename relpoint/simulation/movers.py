"""How the simulated moving landmarks move: displacement from their start, per iteration.

Kraut's simulation (*A Relative Point Algorithm*, section III) moves its dynamic points by
oscillation; real scenes also hold things that travel on (people, vehicles), wander, stop and go,
or stand still for a while before they leave. Each motion here is a displacement ``(n, 3)`` in
metres, in ``world``, of the ``n`` movers from where they are at the first iteration, as a function of
the iteration index ``k`` (the speed is in metres per iteration) or, for ``oscillate``, of the time
``t`` in seconds since the epoch of the stamps (as before, so older logs stay the same).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from relpoint.geometry import FloatArray

#: Largest climb angle of a mover's straight line (radians): movers travel mostly level.
MAX_ELEVATION = np.deg2rad(15.0)
#: ``stop-and-go``: length of one stop-and-go cycle, iterations (uniform); the mover moves half of it.
STOP_AND_GO_CYCLE = (20.0, 60.0)
#: ``static-then-moving``: the iteration at which a mover starts, as a fraction of the run (uniform).
START_FRACTION = (0.2, 0.6)


@dataclass(frozen=True, eq=False)
class OscillatingMovers:
    """Movers oscillating about their centres: ``amplitude sin(2 pi t / period + phase)`` per axis.

    ``amplitude`` (m), ``period`` (s) and ``phase`` (rad) are (n, 3).
    """

    amplitude: FloatArray
    period: FloatArray
    phase: FloatArray

    def excursion(self, t: float) -> FloatArray:
        """Offset (n, 3) from the centre at time ``t`` (seconds)."""
        return self.amplitude * np.sin(2.0 * np.pi * t / self.period + self.phase)


@dataclass(frozen=True, eq=False)
class TravellingMovers:
    """Movers that travel: straight lines (``line``, ``stop-and-go``, ``static-then-moving``) or a random walk.

    Attributes
    ----------
    motion: one of ``line``, ``random-walk``, ``stop-and-go``, ``static-then-moving``.
    speed: metres per iteration.
    direction: (n, 3) unit directions of travel (straight-line motions).
    cycle: (n,) stop-and-go cycle length, iterations.
    cycle_offset: (n,) where in its cycle each stop-and-go mover starts, iterations.
    start: (n,) iteration at which a ``static-then-moving`` mover starts.
    walk: (K, n, 3) cumulative random-walk displacement at every iteration (``random-walk`` only).
    """

    motion: str
    speed: float
    direction: FloatArray
    cycle: FloatArray
    cycle_offset: FloatArray
    start: FloatArray
    walk: FloatArray | None

    def displacement(self, k: int) -> FloatArray:
        """Displacement (n, 3) of every mover at iteration ``k`` from its position at iteration 0 (metres)."""
        if self.motion == "random-walk":
            assert self.walk is not None
            return self.walk[min(k, len(self.walk) - 1)].copy()
        if self.motion == "line":
            travelled = np.full(len(self.direction), self.speed * k)
        elif self.motion == "stop-and-go":
            travelled = self.speed * (
                _moving_time(k + self.cycle_offset, self.cycle) - _moving_time(self.cycle_offset, self.cycle)
            )
        else:  # static-then-moving
            travelled = self.speed * np.maximum(0.0, k - self.start)
        return self.direction * travelled[:, None]


def _moving_time(u: FloatArray, cycle: FloatArray) -> FloatArray:
    """Iterations spent moving up to ``u`` when each cycle moves for its first half, then stops."""
    whole = np.floor(u / cycle)
    return whole * cycle / 2.0 + np.minimum(u - whole * cycle, cycle / 2.0)


def draw_travelling_movers(
    rng: np.random.Generator, motion: str, count: int, speed: float, iterations: int
) -> TravellingMovers:
    """Draw the parameters of ``count`` travelling movers for a run of ``iterations`` iterations.

    A random walk takes one Gaussian step per iteration with ``speed / sqrt(3)`` per axis, so its mean
    squared step is ``speed**2``.
    """
    heading = rng.uniform(-np.pi, np.pi, count)
    elevation = rng.uniform(-MAX_ELEVATION, MAX_ELEVATION, count)
    direction = np.stack(
        [np.cos(elevation) * np.cos(heading), np.cos(elevation) * np.sin(heading), np.sin(elevation)], axis=1
    )
    cycle = rng.uniform(*STOP_AND_GO_CYCLE, count)
    cycle_offset = rng.uniform(0.0, 1.0, count) * cycle
    start = np.floor(rng.uniform(*START_FRACTION, count) * iterations)
    walk = None
    if motion == "random-walk":
        steps = rng.normal(0.0, speed / np.sqrt(3.0), (max(iterations, 1), count, 3))
        steps[0] = 0.0
        walk = np.cumsum(steps, axis=0)
    return TravellingMovers(motion, speed, direction, cycle, cycle_offset, start, walk)
