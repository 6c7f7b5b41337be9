"""Points and RltPoints: bounded rings of untransformed observations (Kraut, section II-A).

Paper name -> Python name
    *Point*     one ring slot: an untransformed ``(x, y, z)`` in the sensor frame of the iteration it was
                observed in, with that iteration (``PointStore.obs[i, slot]``, ``PointStore.obs_iter[i, slot]``).
    *RltPoint*  one row ``i`` of :class:`PointStore`: the circular array of its *Points* plus its interval
                bookkeeping (first, last and current-run iterations), its observation count and the
                least-squares accumulators of its global position (filled by the groups).
    *RltInterval*  the iterations a *RltPoint* was observed in, read straight from its ring
                (:meth:`PointStore.presence`); merging two *RltPoints* takes the union of their rings.

Every *RltPoint* lives in pooled numpy arrays so that registration, grouping and dynamic detection read
many points at once. The ring is indexed by iteration: the observation of iteration ``t`` sits in slot
``t % ring_size`` and is valid when ``obs_iter[i, t % ring_size] == t``. A point observed every
iteration therefore keeps exactly its last ``ring_size`` observations, and memory is
``capacity x ring_size`` whatever the number of iterations. Rows of deleted points are reused.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from relpoint.estimators.relative_point._kernels import (
    gather_positions,
    gather_spread,
    record_observations,
    ring_observations,
    ring_presence,
)
from relpoint.geometry import FloatArray

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

_UNSEEN = -1


class PointStore:
    """Pooled storage of every *RltPoint* (see the module docstring for the paper's names).

    Parameters
    ----------
    ring_size:
        Number of iterations of untransformed observations each point keeps.
    capacity:
        Initial number of rows; the pool doubles when full.

    Attributes (per row ``i``; arrays grow with the pool)
    ----------
    obs: (C, R, 3) float64, untransformed observations in the sensor frame of their iteration, metres.
    obs_iter: (C, R) int64, iteration of each slot (-1 empty).
    first_iter, last_iter, run_start: (C,) int64, first / last iteration observed and the start of
        the current unbroken run of observations.
    n_obs: (C,) int64, observations fused (survives the ring).
    alive: (C,) bool, the row holds a point.
    dynamic: (C,) bool, flagged by dynamic detection (paper II-C): left out of the static map, the
        global index and every fit.
    moving: (C,) bool, flagged with evidence beyond the bulk of the points judged with it: reported
        as a dynamic landmark (a point ``dynamic`` but not ``moving`` is left out of the map as
        unreliable).
    pos_sum, pos_weight: (C, 3), (C,), weighted sum of the global positions the point's groups give it
        and the sum of weights: the least-squares combination of several groups is ``pos_sum / pos_weight``.
    pos_sq: (C,), weighted sum of the squared norms of those positions, for their spread.
    world_sum: (C, 3), sum of the observations mapped to ``world`` by the pose of their iteration
        (the reported position of dynamic points: where they were on average).
    n_groups, n_later_groups: (C,) int64, groups the point is in, and how many of them are not its
        first grouping (the paper's "second grouping").
    uid: (C,) int64, identity that is never reused (for the id tally across row reuse).
    regroup_attempt: (C,) int64, last iteration a regrouping was tried with the point as creation point.
    verified: (C,) int64, last iteration dynamic detection found the point moving with the static
        majority (-1 never): only verified points serve as basis and anchors when there are enough.
    """

    def __init__(self, ring_size: int, capacity: int = 256) -> None:
        self.ring_size = int(ring_size)
        self.capacity = 0
        self.high_water = 0
        self._free: list[int] = []
        self._next_uid = 0
        self.obs = np.zeros((0, self.ring_size, 3))
        self.obs_iter = np.zeros((0, self.ring_size), np.int64)
        self.first_iter = np.zeros(0, np.int64)
        self.last_iter = np.zeros(0, np.int64)
        self.run_start = np.zeros(0, np.int64)
        self.n_obs = np.zeros(0, np.int64)
        self.alive = np.zeros(0, bool)
        self.dynamic = np.zeros(0, bool)
        self.moving = np.zeros(0, bool)
        self.pos_sum = np.zeros((0, 3))
        self.pos_weight = np.zeros(0)
        self.pos_sq = np.zeros(0)
        self.world_sum = np.zeros((0, 3))
        self.n_groups = np.zeros(0, np.int64)
        self.n_later_groups = np.zeros(0, np.int64)
        self.uid = np.zeros(0, np.int64)
        self.regroup_attempt = np.zeros(0, np.int64)
        self.verified = np.zeros(0, np.int64)
        self._grow(max(16, int(capacity)))

    # -- pool management -------------------------------------------------------------------------

    def _grow(self, capacity: int) -> None:
        extra = capacity - self.capacity
        if extra <= 0:
            return

        def pad(array: np.ndarray, fill: float | int | bool) -> np.ndarray:
            tail = np.full((extra, *array.shape[1:]), fill, dtype=array.dtype)
            return np.concatenate([array, tail])

        self.obs = pad(self.obs, 0.0)
        self.obs_iter = pad(self.obs_iter, _UNSEEN)
        self.first_iter = pad(self.first_iter, _UNSEEN)
        self.last_iter = pad(self.last_iter, _UNSEEN)
        self.run_start = pad(self.run_start, _UNSEEN)
        self.n_obs = pad(self.n_obs, 0)
        self.alive = pad(self.alive, False)
        self.dynamic = pad(self.dynamic, False)
        self.moving = pad(self.moving, False)
        self.pos_sum = pad(self.pos_sum, 0.0)
        self.pos_weight = pad(self.pos_weight, 0.0)
        self.pos_sq = pad(self.pos_sq, 0.0)
        self.world_sum = pad(self.world_sum, 0.0)
        self.n_groups = pad(self.n_groups, 0)
        self.n_later_groups = pad(self.n_later_groups, 0)
        self.uid = pad(self.uid, -1)
        self.regroup_attempt = pad(self.regroup_attempt, _UNSEEN)
        self.verified = pad(self.verified, _UNSEEN)
        self.capacity = capacity

    def new_points(self, count: int) -> IntArray:
        """Allocate ``count`` fresh rows (reusing deleted ones first) and return their ids."""
        reused = [self._free.pop() for _ in range(min(count, len(self._free)))]
        fresh = count - len(reused)
        if self.high_water + fresh > self.capacity:
            self._grow(max(2 * self.capacity, self.high_water + fresh))
        ids = np.array(reused + list(range(self.high_water, self.high_water + fresh)), dtype=np.int64)
        self.high_water += fresh
        self.alive[ids] = True
        self.uid[ids] = np.arange(self._next_uid, self._next_uid + count)
        self._next_uid += count
        return ids

    def delete(self, ids: npt.ArrayLike) -> None:
        """Free rows (their observations become invalid at once, so stale references see nothing)."""
        ids = np.atleast_1d(np.asarray(ids, dtype=np.int64))
        if len(ids) == 0:
            return
        self.alive[ids] = False
        self.obs_iter[ids] = _UNSEEN
        for name in ("first_iter", "last_iter", "run_start", "uid", "regroup_attempt", "verified"):
            getattr(self, name)[ids] = _UNSEEN
        for name in ("n_obs", "n_groups", "n_later_groups", "pos_weight", "pos_sq"):
            getattr(self, name)[ids] = 0
        self.dynamic[ids] = False
        self.moving[ids] = False
        self.pos_sum[ids] = 0.0
        self.world_sum[ids] = 0.0
        self._free.extend(int(i) for i in ids)

    @property
    def count(self) -> int:
        """Number of live points."""
        return int(np.count_nonzero(self.alive[: self.high_water]))

    def live_ids(self) -> IntArray:
        """Ids of every live point, ascending."""
        return np.flatnonzero(self.alive[: self.high_water]).astype(np.int64)

    # -- observations ----------------------------------------------------------------------------

    def add_observations(self, ids: IntArray, points: FloatArray, iteration: int) -> None:
        """Append one iteration's untransformed points (N, 3) to the rings of ``ids`` (N,), distinct."""
        record_observations(
            self.obs, self.obs_iter, self.first_iter, self.last_iter, self.run_start, self.n_obs,
            np.ascontiguousarray(ids, dtype=np.int64), np.ascontiguousarray(points, dtype=np.float64), int(iteration),
        )  # fmt: skip

    def latest(self, ids: IntArray) -> FloatArray:
        """Most recent untransformed observation (N, 3) of each point."""
        return self.obs[ids, self.last_iter[ids] % self.ring_size]

    def observations(self, ids: IntArray, iterations: IntArray) -> tuple[FloatArray, BoolArray]:
        """Observations (N, L, 3) of points ``ids`` (N,) at ``iterations`` (L,), and their validity (N, L)."""
        return ring_observations(self.obs, self.obs_iter, ids, np.asarray(iterations, dtype=np.int64))

    def presence(self, ids: IntArray, first: int, last: int) -> BoolArray:
        """*RltInterval* of each point restricted to ``[first, last]``: observed or not, (N, last-first+1)."""
        return ring_presence(self.obs_iter, ids, int(first), int(last))

    def co_observed(self, a: int, b: int) -> bool:
        """Whether points ``a`` and ``b`` were ever seen in the same iteration (within the ring)."""
        rows = self.obs_iter[[a, b]]
        return bool(np.any((rows[0] == rows[1]) & (rows[0] >= 0)))

    # -- global positions ------------------------------------------------------------------------

    def mapped(self, ids: IntArray) -> BoolArray:
        """Points that have a global position from at least one group."""
        return self.pos_weight[ids] > 0.0

    def positions(self, ids: IntArray) -> FloatArray:
        """Least-squares global positions (N, 3) of mapped points (``world``, metres; NaN if unmapped)."""
        return gather_positions(self.pos_sum, self.pos_weight, ids)

    def spread(self, ids: IntArray) -> FloatArray:
        """RMS disagreement (N,) between the global positions a point's groups give it (m).

        Small for a static point (noise averaged per group); large when the point moved between
        groups, so it also serves as the inverse weight of the point as an anchor.
        """
        return gather_spread(self.pos_sum, self.pos_weight, self.pos_sq, ids)

    # -- merging ---------------------------------------------------------------------------------

    def merge_into(self, older: int, newer: int) -> None:
        """Copy the untransformed observations of ``newer`` into ``older`` (paper II-D merging).

        Ring slots where ``newer`` holds a later iteration than ``older`` are overwritten; intervals
        and counts combine. The global-position accumulators are moved by the group map, and the
        caller deletes ``newer`` afterwards.
        """
        take = self.obs_iter[newer] > self.obs_iter[older]
        self.obs[older, take] = self.obs[newer, take]
        self.obs_iter[older, take] = self.obs_iter[newer, take]
        if self.last_iter[newer] > self.last_iter[older]:
            # The newer point carries the current run: continue it under the older identity.
            gap_free = self.run_start[newer] == self.last_iter[older] + 1
            self.run_start[older] = self.run_start[older] if gap_free else self.run_start[newer]
            self.last_iter[older] = self.last_iter[newer]
        self.first_iter[older] = min(self.first_iter[older], self.first_iter[newer])
        self.n_obs[older] += self.n_obs[newer]
        self.world_sum[older] += self.world_sum[newer]
        self.dynamic[older] |= self.dynamic[newer]
        self.moving[older] |= self.moving[newer]
        self.verified[older] = max(self.verified[older], self.verified[newer])
