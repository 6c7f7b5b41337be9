"""How each iteration is placed: local, far and global matching of the observed points, and the pose fitted to the mapped static points they matched (or coasted when too few)."""

from __future__ import annotations

import logging
from itertools import accumulate, chain

import numpy as np
import numpy.typing as npt

from relpoint.estimators.relative_point._kernels import (
    mapped_static_mask,
    nearest_older_candidates,
    pose_anchors,
    recent_references,
)
from relpoint.estimators.relative_point.lsf import fit_transform
from relpoint.estimators.relative_point.points import IntArray
from relpoint.estimators.relative_point.registration import NO_MATCH
from relpoint.estimators.relative_point.state import EstimatorState
from relpoint.geometry import FloatArray, apply_transform, rigid_inverse

logger = logging.getLogger(__name__)


class Localisation(EstimatorState):
    """How each iteration is placed: local, far and global matching of the observed points, and the pose
    fitted to the mapped static points they matched (or coasted when too few).

    A phase of :class:`~relpoint.estimators.relative_point.estimator.RelativePointEstimator` over
    the state it shares with the other phases (:class:`~relpoint.estimators.relative_point.state.EstimatorState`).
    """

    def _register(self, points: FloatArray, k: int) -> IntArray:
        """Local matching (paper II-A): ids (N,) of the recent points matched, ``NO_MATCH`` elsewhere."""
        config, store = self.config, self.store
        ids = np.empty(len(points), np.int64)
        ids.fill(NO_MATCH)
        # Each recently seen point, once: from the charting of the iteration it was last seen in.
        first = k - config.match_window
        seen = [self.charting.seen(t) for t in range(first, k)]
        offsets = np.array([0, *accumulate(len(ids_t) for ids_t in seen)], np.int64)
        refs, reference, age = recent_references(np.concatenate(seen), offsets, first, store.last_iter, store.obs)
        if len(refs) == 0:
            return ids
        local = self.motion.match(reference, age, points, config.match_bound, config.match_angle, config.predict_motion)
        self._motion_measured = local.motion_measured
        matched = local.row != NO_MATCH
        ids[matched] = refs[local.row[matched]]
        self.counts["local_matches"] += int(np.count_nonzero(matched))
        self.counts["far_matches"] += local.far_matches
        return ids

    def _match_globally(self, points: FloatArray, ids: IntArray, k: int) -> None:
        """Global matching (paper II-D) of unmatched points through the provisional current position."""
        unmatched = (ids == NO_MATCH).nonzero()[0]
        if len(unmatched) == 0 or len(self.index) == 0:
            return
        store = self.store
        world = apply_transform(self._provisional_pose(), points[unmatched])
        recent = k - self.config.match_window
        bound2 = self.config.global_match_bound**2
        # Every unmatched point's index neighbours in one array (each point's in the index's order);
        # each point claims its nearest within bound among those not seen within the matching window.
        found = [self.index.candidates_at(key) for key in self.index.keys(world).tolist()]
        counts = [len(neighbours) for neighbours in found]
        candidates = np.fromiter(chain.from_iterable(found), np.int64, sum(counts))
        nearest_d2, nearest = nearest_older_candidates(
            candidates, np.array(counts, np.int64), store.last_iter, recent, store.pos_sum, store.pos_weight, world
        )
        claims = [
            (d2, q, point)
            for q, d2, point in zip(unmatched.tolist(), nearest_d2.tolist(), nearest.tolist(), strict=True)
            if point >= 0 and d2 <= bound2
        ]
        taken: set[int] = set()
        for _, q, point in sorted(claims):
            if point not in taken:
                taken.add(point)
                ids[q] = point
        self.counts["global_matches"] += len(taken)

    def _locate(self, points: FloatArray, ids: IntArray, mapped: npt.NDArray[np.bool_]) -> FloatArray | None:
        """Current position (paper II-D): LSF of this iteration's observations to their global positions.

        ``mapped`` marks the observations of static points with a global position.
        """
        store = self.store
        if len(self.groups):
            return self._fit_pose(points[mapped], ids[mapped])
        # Before the first group: the first observations are global positions (world = first frame).
        known = ids != NO_MATCH
        use = known & (store.obs_iter[np.where(known, ids, 0), 0] == 0)
        return self._fit_sensor(points[use], store.obs[ids[use], 0], None)

    def _mapped_static(self, ids: IntArray) -> npt.NDArray[np.bool_]:
        """Which of this iteration's point ids (NO_MATCH for none) have a global position and are static."""
        return mapped_static_mask(ids, self.store.pos_weight, self.store.dynamic)  # NO_MATCH is -1

    def _fit_pose(self, points: FloatArray, ids: IntArray) -> FloatArray | None:
        """``T_world_sensor`` fitting observations (N, 3) (sensor frame) to their points' global positions.

        Points whose groups disagree about their position (slow movers) and points not yet verified
        static count for less; gross outliers are trimmed. ``None`` if the fit is degenerate.
        """
        store, config = self.store, self.config
        positions, weights = pose_anchors(
            store.pos_sum, store.pos_weight, store.pos_sq, store.verified, ids, float(config.spread_floor) ** 2,
            float(config.unverified_weight),
        )  # fmt: skip
        return self._fit_sensor(points, positions, weights)

    def _fit_sensor(self, points: FloatArray, targets: FloatArray, weights: FloatArray | None) -> FloatArray | None:
        """``T_world_sensor`` by the trimmed least-squares fit of ``points`` (sensor) onto ``targets`` (world)."""
        config = self.config
        fit = fit_transform(
            points,
            targets,
            trim=config.trim,
            floor=config.trim_floor,
            collinear_tolerance=config.collinear_tolerance,
            weights=weights,
            rounds=config.trim_rounds,
            consensus=config.consensus_bound,
        )
        return None if fit is None else fit.T

    def _coast(self) -> FloatArray:
        """Pose of an iteration without a usable fit to mapped points.

        When this iteration's local matches gave the raw-point motion (three or more non-collinear
        matched points, mapped or not), the last pose moves by it (visual odometry); otherwise the
        pose is held. Constant-velocity coasting was tried and rejected: on hand-held real data
        (Starry Night) it extrapolated erratic motion and doubled the trajectory error. With
        ``coast=False`` the pose is always held.
        """
        if self.config.coast and self._motion_measured:
            return self._provisional_pose()
        return self._T_world_sensor

    def _provisional_pose(self) -> FloatArray:
        """``T_world_sensor`` of this iteration before its fit: the last pose moved by the raw-point motion.

        Good to a fraction of the matching bound, and free; the fit to mapped points comes after grouping.
        """
        return self._T_world_sensor @ rigid_inverse(self.motion.T_curr_prev)

    def _refresh_index(self) -> None:
        """Move changed global positions in the global index."""
        store = self.store
        self.index.refresh(self.groups.take_changed(), store.alive, store.pos_sum, store.pos_weight, store.dynamic)
