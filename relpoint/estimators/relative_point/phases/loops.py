"""Loop closure beyond the global matching bound: the young points in view vote on an offset onto old mapped points, and the drift it shows is taken out of the groups and poses along the loop."""

from __future__ import annotations

import logging

import numpy as np

from relpoint.estimators.relative_point.loops import drift_profile, vote_offset
from relpoint.estimators.relative_point.points import IntArray
from relpoint.estimators.relative_point.registration import NO_MATCH, match_nearest
from relpoint.estimators.relative_point.state import EstimatorState
from relpoint.geometry import FloatArray, apply_transform

logger = logging.getLogger(__name__)


_LOOP_YOUNG_MAX = 64
"""Young points that vote on a loop's offset at most (an even sample of them in a dense view)."""


class LoopClosing(EstimatorState):
    """Loop closure beyond the global matching bound: the young points in view vote on an offset onto old
    mapped points, and the drift it shows is taken out of the groups and poses along the loop.

    A phase of :class:`~relpoint.estimators.relative_point.estimator.RelativePointEstimator` over
    the state it shares with the other phases (:class:`~relpoint.estimators.relative_point.state.EstimatorState`).
    """

    def _close_loop(self, points: FloatArray, ids: IntArray, k: int) -> None:
        """Loop closure beyond the global matching bound (see :mod:`.loops`), in place on ``ids``.

        When the young points in view agree on an offset onto old mapped points, the drift is taken
        out of the groups and poses since the old points were last seen (:meth:`_take_out_drift`),
        and the young points are matched to the old ones: unmatched observations take them, young
        points are merged into them (the paper's merging, observations copied to the older point).
        """
        config, store = self.config, self.store
        known = ids != NO_MATCH
        young_rows = np.flatnonzero(~known | (store.first_iter[np.where(known, ids, 0)] >= k - config.loop_young))
        if len(young_rows) < config.loop_support:
            return
        if len(young_rows) > _LOOP_YOUNG_MAX:  # a dense view: an even sample votes as well, for less
            young_rows = young_rows[np.linspace(0, len(young_rows) - 1, _LOOP_YOUNG_MAX).astype(np.int64)]
        n = store.high_water
        old = np.flatnonzero(
            store.alive[:n]
            & (store.pos_weight[:n] > 0)
            & ~store.dynamic[:n]
            & (store.last_iter[:n] < k - config.loop_gap)
        )
        if len(old) < config.loop_support:
            return
        young = apply_transform(self._provisional_pose(), points[young_rows])
        old_positions = store.positions(old)
        near = np.all(
            (old_positions >= young.min(axis=0) - config.loop_search)
            & (old_positions <= young.max(axis=0) + config.loop_search),
            axis=1,
        )
        old, old_positions = old[near], old_positions[near]
        tolerance = 0.5 * config.global_match_bound
        offset = vote_offset(
            young,
            old_positions,
            radius=config.loop_search,
            tolerance=tolerance,
            support=config.loop_support,
            ambiguity=config.loop_ambiguity,
        )
        if offset is None or float(np.linalg.norm(offset)) <= tolerance:  # within reach of global matching
            return
        row, _ = match_nearest(old_positions, young + offset, tolerance)
        paired = np.flatnonzero(row != NO_MATCH)
        if len(paired) < config.loop_support:
            return
        self._take_out_drift(offset, int(np.median(store.last_iter[old[row[paired]]])), k)
        self.counts["loop_closures"] += 1
        in_view = set(ids[known].tolist())
        for i in paired.tolist():
            older, r = int(old[row[i]]), int(young_rows[i])
            if older in in_view:
                continue
            newer = int(ids[r])
            if newer == NO_MATCH:
                ids[r] = older
            elif not store.co_observed(older, newer):
                self._merge(older, newer, k)
                ids[r] = older
            else:
                continue
            in_view.add(older)

    def _take_out_drift(self, offset: FloatArray, t0: int, k: int) -> None:
        """Shift groups and poses by their part of a loop's drift ``offset`` (3,) m (:func:`.loops.drift_profile`).

        The correction of iteration ``t`` follows the path from ``t0`` (when the old points were last
        seen, no correction) to now (``offset``); a group takes that of its last iteration.
        """
        path = np.concatenate([self._path[t0:k], self._T_world_sensor[None, :3, 3]])
        correction = drift_profile(path, offset, self.config.loop_max_rotation)
        for group in list(self.groups.groups.values()):
            if group.last_iteration > t0:
                self.groups.shift(group, correction[min(group.last_iteration, k) - t0])
        ring = self.config.ring_size
        iterations = np.arange(max(t0 + 1, k - ring + 1), k)
        self._poses[iterations % ring, :3, 3] += correction[iterations - t0]
        self._path[t0 + 1 : k] += correction[1 : k - t0]
        self._T_world_sensor = self._T_world_sensor.copy()
        self._T_world_sensor[:3, 3] += offset
