"""Bridging gaps in a log's stamps that a motion model cannot span.

A filter's prediction grows its uncertainty with the interval it predicts over (white acceleration
noise: position variance ~ dt^3). Over a gap of years (a recording paused, a clock reset) that variance
reaches 1e25 m^2 and the next update fails numerically. Such a gap says nothing about the motion, so
the prediction spans at most :data:`GAP_FACTOR` times the typical interval of the log so far (and at
least :data:`MIN_BRIDGE_S`); the filter then relocates on the map as after any large uncertain move.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

logger = logging.getLogger(__name__)

#: A prediction spans at most this many typical intervals.
GAP_FACTOR = 100.0

#: ... and never less than this (s), so slow logs and the first intervals are not cut.
MIN_BRIDGE_S = 10.0

#: Intervals remembered for the typical one.
_HISTORY = 64


class GapBridge:
    """The interval a prediction may span, given the log's own intervals; counts the gaps it bridged."""

    def __init__(self) -> None:
        self._intervals: deque[float] = deque(maxlen=_HISTORY)
        self.bridged = 0

    def interval(self, dt: float) -> float:
        """``dt`` (s), or the longest interval the motion model may span when ``dt`` is beyond it."""
        limit = max(MIN_BRIDGE_S, GAP_FACTOR * float(np.median(self._intervals))) if self._intervals else MIN_BRIDGE_S
        if dt <= limit:
            self._intervals.append(dt)
            return dt
        if self.bridged == 0:
            logger.warning("a %.3g s gap in the stamps is bridged as %.3g s (the motion model cannot span it); "
                           "the count is in run.json", dt, limit)  # fmt: skip
        self.bridged += 1
        return limit
