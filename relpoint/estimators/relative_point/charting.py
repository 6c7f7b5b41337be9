"""RltPointCharting: which *RltPoints* were seen in which iteration (Kraut, section II-A).

Paper name -> Python name
    *RltPointCharting*  :class:`PointCharting`, a ring over the last ``ring_size`` iterations holding
                        the ids of the points observed in each. It enumerates the points seen in an
                        interval (for registration and group creation) and detects duplicates, i.e. two
                        observations of one iteration charted to the same point, which registration's
                        one-to-one rule must have resolved.

The paper's hash table for duplicate detection is replaced by a sort (``np.unique``) of each
iteration's ids, which gives the same answer for a whole iteration at once.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from relpoint.estimators.relative_point._kernels import distinct_ascending

IntArray = npt.NDArray[np.int64]


class PointCharting:
    """Per-iteration lists of observed point ids, bounded to the last ``ring_size`` iterations."""

    def __init__(self, ring_size: int) -> None:
        self.ring_size = int(ring_size)
        self._ids: list[IntArray] = [np.zeros(0, np.int64)] * self.ring_size
        self._iteration = np.full(self.ring_size, -1, np.int64)

    def chart(self, iteration: int, ids: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Record the points seen in ``iteration``; return a mask (N,) of duplicate entries in ``ids``."""
        ids = np.ascontiguousarray(ids, dtype=np.int64)
        unique = distinct_ascending(ids)  # a new array: ids are row numbers, np.unique in linear time
        if len(unique) == len(ids):  # the usual case: no duplicates
            duplicate = np.zeros(len(ids), bool)
        else:
            unique, first = np.unique(ids, return_index=True)
            duplicate = np.ones(len(ids), bool)
            duplicate[first] = False
        slot = iteration % self.ring_size
        self._ids[slot] = unique
        self._iteration[slot] = iteration
        return duplicate

    def seen(self, iteration: int) -> IntArray:
        """Ids charted in ``iteration`` (empty if outside the ring)."""
        slot = iteration % self.ring_size
        return self._ids[slot] if self._iteration[slot] == iteration else np.zeros(0, np.int64)

    def enumerate(self, first: int, last: int) -> IntArray:
        """Distinct ids charted in any iteration of ``[first, last]`` (clipped to the ring), ascending."""
        first = max(first, last - self.ring_size + 1)
        iterations = np.arange(first, last + 1)
        slots = iterations % self.ring_size
        charted_slots = slots[self._iteration[slots] == iterations].tolist()
        lists = [ids for ids in (self._ids[slot] for slot in charted_slots) if len(ids)]
        if not lists:
            return np.zeros(0, np.int64)
        if len(lists) == 1:
            return lists[0]
        return distinct_ascending(np.concatenate(lists))  # ids are row numbers: np.unique in linear time

    def replace(self, old: int, new: int, first: int, last: int) -> None:
        """Re-chart ``old`` as ``new`` in ``[first, last]`` (after merging ``old`` into ``new``)."""
        for t in range(max(first, last - self.ring_size + 1), last + 1):
            slot = t % self.ring_size
            ids = self._ids[slot]
            if self._iteration[slot] != t or not np.any(ids == old):
                continue
            self._ids[slot] = np.unique(np.where(ids == old, new, ids))
