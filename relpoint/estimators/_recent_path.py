"""Fixes that arrive late: a filter's recent path, to carry a fix from its stamp to the filter's time.

A GNSS receiver stamps its position when it measured it, and the message reaches the log 50-200 ms
later, often after the point cloud of a later time. A filter that has already moved its state to that
cloud's stamp cannot predict backwards, and compared with the current position a fix is off by
the distance travelled meanwhile (0.6 m for 50 ms at 12 m/s, a bias as large as the fix's noise).
The standard remedy short of re-running the filter from the fix's time: carry the fix forward along
the filter's own motion since then, ``fix + (p_now - p(t_fix))``, with ``p(t_fix)`` interpolated
between the positions the filter had at its recent iterations. The displacement is the filter's
own estimate, whose error over a fraction of a second is far below a fix's.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from relpoint.geometry import FloatArray

logger = logging.getLogger(__name__)

#: Iterations of positions kept: at 10 Hz, 25 s of latency.
HISTORY = 256


class RecentPath:
    """The positions (m, ``world``) a filter had at its latest iterations, by stamp (ns).

    The kept positions move with every correction the filter makes to its own position (a fused
    fix, a closed loop, the frame's pinning: :meth:`shift`, :meth:`transform`), so that the
    displacement between two of them is the filter's motion alone.
    """

    def __init__(self, length: int = HISTORY) -> None:
        self._stamps: deque[int] = deque(maxlen=length)
        self._positions: deque[FloatArray] = deque(maxlen=length)
        self.carried = 0  # fixes carried forward (stamped before the filter's time)
        self.too_old = 0  # fixes older than every kept iteration (skipped by the filter)

    def add(self, stamp_ns: int, position: FloatArray) -> None:
        """The filter's position (3,) at an iteration's stamp (stamps increase)."""
        self._stamps.append(int(stamp_ns))
        self._positions.append(np.array(position, dtype=np.float64))

    def shift(self, offset: FloatArray) -> None:
        """Every kept position moved by ``offset`` (3,) m."""
        for k in range(len(self._positions)):
            self._positions[k] = self._positions[k] + offset

    def transform(self, T: FloatArray) -> None:
        """Every kept position moved by the rigid transform ``T`` (4, 4)."""
        for k in range(len(self._positions)):
            self._positions[k] = T[:3, :3] @ self._positions[k] + T[:3, 3]

    def displacement(self, stamp_ns: int, now_ns: int, now: FloatArray) -> FloatArray | None:
        """``now - p(stamp_ns)`` (3,) m: how far the filter has moved since ``stamp_ns`` to its position
        ``now`` at ``now_ns``, ``p`` interpolated between the kept iterations (and ``now``). Zero for a
        stamp at or after ``now_ns``; None when it is older than every kept iteration."""
        if stamp_ns >= now_ns:
            return np.zeros(3)
        stamps = list(self._stamps)
        positions = list(self._positions)
        if not stamps or now_ns > stamps[-1]:
            stamps.append(int(now_ns))
            positions.append(np.asarray(now, dtype=np.float64))
        if stamp_ns < stamps[0]:
            self.too_old += 1
            if self.too_old == 1:
                logger.warning(
                    "a position fix stamped %.1f s before the filter's time is older than the %d iterations "
                    "kept to carry it forward; such fixes are skipped and counted in run.json (fixes_too_old)",
                    (now_ns - stamp_ns) * 1e-9, len(stamps),
                )  # fmt: skip
            return None
        times = np.asarray(stamps, dtype=np.int64)
        after = min(int(np.searchsorted(times, stamp_ns, side="right")), len(times) - 1)
        before = max(after - 1, 0)
        fraction = (stamp_ns - times[before]) / max(int(times[after] - times[before]), 1)
        then = (1.0 - fraction) * positions[before] + fraction * positions[after]
        self.carried += 1
        return np.asarray(now, dtype=np.float64) - then

    def summary(self) -> dict[str, int]:
        """run.json figures: ``fixes_carried_forward`` and ``fixes_too_old``, each when there were any."""
        counts = {"fixes_carried_forward": self.carried, "fixes_too_old": self.too_old}
        return {key: count for key, count in counts.items() if count}
