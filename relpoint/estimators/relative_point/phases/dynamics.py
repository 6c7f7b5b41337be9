"""The dynamic sweep: which points move (against their group, over time, against references and in the world), which are reported, and duplicates merged back."""

from __future__ import annotations

import itertools
import logging
import math

import numpy as np
import numpy.typing as npt

from relpoint.estimators._noise import SIMULATOR_SIGMA
from relpoint.estimators.relative_point._kernels import flagged_within, older_within
from relpoint.estimators.relative_point.dynamics import (
    detect_dynamic,
    deviation_to_references,
    distance_deviation,
    tail_bound,
    world_block_deviation,
)
from relpoint.estimators.relative_point.lsf import _median
from relpoint.estimators.relative_point.points import IntArray
from relpoint.estimators.relative_point.state import EstimatorState
from relpoint.geometry import FloatArray

logger = logging.getLogger(__name__)


def _finite_median(values: FloatArray) -> float:
    """Median of the finite entries of a 1-D array (NaN if none)."""
    finite = values[np.isfinite(values)]
    return _median(finite) if len(finite) else float("nan")


class DynamicSweep(EstimatorState):
    """The dynamic sweep: which points move (against their group, over time, against references and in the
    world), which are reported, and duplicates merged back.

    A phase of :class:`~relpoint.estimators.relative_point.estimator.RelativePointEstimator` over
    the state it shares with the other phases (:class:`~relpoint.estimators.relative_point.state.EstimatorState`).
    """

    def _detect_dynamic(
        self, k: int, members: IntArray, iterations: IntArray
    ) -> tuple[IntArray, npt.NDArray[np.bool_], IntArray]:
        """Dynamic detection before a group is final (paper II-C), over the group's ``iterations`` (L,).

        Returns the ids found moving, whether each stands out of the bulk (:meth:`_beyond_bulk`)
        and the ids verified static. Runs over the group's interval when it is at least
        ``dynamic_min_iterations`` long (first groupings are shorter; their points are judged by
        :meth:`_dynamic_sweep` before they serve as basis or anchors).
        """
        config = self.config
        none = np.zeros(0, np.int64)
        if not config.dynamic_detection or len(iterations) < config.dynamic_min_iterations:
            return none, np.zeros(0, bool), none
        observations, _ = self.store.observations(members, iterations)
        result = detect_dynamic(observations, gap_ratio=config.dynamic_gap_ratio, floor=self._pair_noise(1))
        self.counts["dynamic_comparisons"] += result.comparisons
        if not result.decided:
            return none, np.zeros(0, bool), none
        beyond = self._beyond_bulk(observations, result.static, result.threshold)
        return members[~result.static], beyond, members[result.static]

    def _beyond_bulk(
        self, observations: FloatArray, static: npt.NDArray[np.bool_], threshold: float
    ) -> npt.NDArray[np.bool_]:
        """Which points outside the binning's static majority stand out of the bulk (one per such point).

        Every point's distance deviation (m) against up to ``dynamic_references`` members of the
        majority (median) is compared with :func:`.tail_bound` of all of them: a point beyond both
        it and the binning's ``threshold`` is reported moving; the rest of those the binning put
        outside are only left out (see ``dynamic_tail_sigmas``). ``observations`` is (M, L, 3).
        """
        outside = (~static).nonzero()[0]
        if len(outside) == 0 or self.config.dynamic_tail_sigmas <= 0:
            return np.ones(len(outside), bool)
        references = static.nonzero()[0][: self.config.dynamic_references]
        everyone = np.arange(len(observations))
        deviation = np.median(
            [distance_deviation(observations, np.full(len(everyone), r), everyone) for r in references], axis=0
        )
        self.counts["dynamic_comparisons"] += len(everyone) * len(references)
        return deviation[outside] > max(threshold, tail_bound(deviation, self.config.dynamic_tail_sigmas))

    def _pair_noise(self, block: int) -> float:
        """Smallest noise level (m) the dynamic tests assume for the distance between two static points.

        A distance between two points with per-axis noise ``observation_sigma`` varies by about
        ``sqrt(2) sigma`` from one observation to the next, ``sqrt(2) sigma / sqrt(block)`` between
        means of ``block`` observations; ``dynamic_noise_floor`` times that is the floor.
        """
        sigma = self.config.observation_sigma or SIMULATOR_SIGMA
        return self.config.dynamic_noise_floor * math.sqrt(2.0) * sigma / math.sqrt(block)

    def _dynamic_sweep(self, k: int) -> None:
        """Judge the points in view against the points already verified static (paper II-C).

        The majority bin of earlier detections persists as the verified-static set; every
        ``dynamic_every`` iterations each point in view with enough history is compared with up to
        ``dynamic_references`` of its members over the last ``dynamic_window`` iterations (the
        paper's last round against the majority bin). Their own mutual deviation is the noise level
        the factors scale. A second witness is the spread of the point's global position between
        the groups that placed it, against the typical spread in view. Verification is current: a
        point that stops passing loses it. Until three verified points are in view, the paper's
        binning seeds the set over the longest window that six points in view span without a break:
        a full window verifies its majority bin, a shorter one (with a noise margin widened by the
        square root of the shortfall) only flags the movers it shows.
        """
        config, store = self.config, self.store
        if not config.dynamic_detection or k % config.dynamic_every:
            return
        seen = self.charting.seen(k)
        seen = seen[~store.dynamic[seen]]
        tested = seen[k - store.run_start[seen] + 1 >= config.dynamic_min_iterations]
        if len(tested) < 4:
            return
        window = min(config.dynamic_window, config.ring_size)
        start = k - window + 1
        verified = tested[store.verified[tested] >= 0]
        if len(verified) < 3:
            # Seed the verified set by the paper's binning over the longest window that at least
            # six points in view span without a break (not shorter than dynamic_min_iterations).
            run_length = np.minimum(k - store.run_start[tested] + 1, window)
            if len(tested) < 6:
                return
            length = int(np.sort(run_length)[-6])
            full = tested[run_length >= length]
            tracks, _ = store.observations(full, np.arange(k - length + 1, k + 1))
            # A short window estimates each deviation from few iterations: a wider noise margin.
            margin = 1.6 if length == window else 1.6 * math.sqrt(window / length)
            result = detect_dynamic(
                tracks, gap_ratio=config.dynamic_gap_ratio, noise_factor=margin, floor=self._pair_noise(1)
            )
            self.counts["dynamic_comparisons"] += result.comparisons
            if result.decided:
                # A short window shows fast movers, but it is too short to vouch for the rest.
                if length == window:
                    store.verified[full[result.static]] = k
                self._flag_dynamic(
                    full[~result.static], "binning", self._beyond_bulk(tracks, result.static, result.threshold)
                )
            return
        references = verified[np.argsort(store.run_start[verified], kind="stable")[: config.dynamic_references]]
        tracks, valid = store.observations(tested, np.arange(start, k + 1))
        rows = np.searchsorted(tested, references)
        deviation = deviation_to_references(
            tracks, valid, rows, config.dynamic_min_iterations, block=config.dynamic_block
        )
        self.counts["dynamic_comparisons"] += len(tested) * len(rows)
        noise = _finite_median(deviation[rows])
        if not np.isfinite(noise) or noise <= 0:
            return
        noise = max(noise, self._pair_noise(config.dynamic_block))
        # Second witness: how much the point's groups disagree about its global position, against
        # the typical disagreement of the points in view (a moving point is placed differently by
        # every group that sees it).
        # Only meaningful for points placed by several groups (two placements always disagree), and
        # only within one unbroken run of observations: after a loop closure the groups of two
        # passes also disagree by the drift between them.
        mapped = (
            (store.pos_weight[tested] > 0)
            & (store.n_groups[tested] >= 4)
            & (store.first_iter[tested] == store.run_start[tested])
        )
        spread = np.where(mapped, store.spread(tested), np.nan)
        typical = _finite_median(spread)
        spread_ratio = spread / typical if np.isfinite(typical) and typical > 0 else np.full(len(tested), np.nan)
        judged = np.isfinite(deviation)
        by_references = judged & (deviation > config.dynamic_moving_factor * noise)
        by_spread = np.isfinite(spread_ratio) & (spread_ratio > config.dynamic_spread_factor)
        by_world = np.zeros(len(tested), bool)
        world_ratio = np.full(len(tested), np.nan)
        if config.dynamic_world_factor > 0:
            # Third witness: scatter of the point's block-mean world positions within its current
            # run (the pose of this iteration is not known yet), against the typical scatter.
            iterations = np.arange(start, k)
            current = valid[:, :-1] & (iterations[None, :] >= store.run_start[tested, None])
            poses = self._poses[iterations % config.ring_size]
            scatter = world_block_deviation(tracks[:, :-1], current, poses, config.dynamic_block)
            typical_scatter = _finite_median(scatter)
            if np.isfinite(typical_scatter) and typical_scatter > 0:
                world_ratio = scatter / typical_scatter
                by_world = np.isfinite(world_ratio) & (world_ratio > config.dynamic_world_factor)
                static_ok = ~(world_ratio > config.dynamic_verify_factor)  # NaN: no objection
            else:
                static_ok = np.ones(len(tested), bool)
        else:
            static_ok = np.ones(len(tested), bool)
        moving = by_references | by_spread | by_world
        beyond = np.zeros(len(tested), bool)
        if moving.any():  # reported moving (not only left out) where a value also stands out of the bulk
            tail = config.dynamic_tail_sigmas
            beyond = (
                (deviation > tail_bound(deviation, tail))
                | (spread_ratio > tail_bound(spread_ratio, tail))
                | (world_ratio > tail_bound(world_ratio, tail))
            )  # NaN compares False
        by_spread &= ~by_references
        by_world &= ~by_references & ~by_spread
        static = judged & ~moving & static_ok & (deviation <= config.dynamic_verify_factor * noise)
        static &= ~(spread_ratio > config.dynamic_spread_verify * config.dynamic_spread_factor)  # NaN: False
        # Verification is current: a point that no longer passes loses it until it passes again.
        store.verified[tested[judged & ~static]] = -1
        store.verified[tested[static]] = k
        self._flag_dynamic(tested[by_references], "references", beyond[by_references])
        self._flag_dynamic(tested[by_spread], "spread", beyond[by_spread])
        self._flag_dynamic(tested[by_world], "world", beyond[by_world])

    def _flag_dynamic(self, ids: IntArray, witness: str, moving: npt.NDArray[np.bool_] | None = None) -> None:
        """Flag points: they leave the static map, the global index and future fits.

        ``witness`` names the test that flagged them (counted as ``dynamic_by_<witness>``);
        ``moving`` (one per id, default all) says which are reported as dynamic landmarks, the
        others being left out of the map as unreliable (see ``dynamic_tail_sigmas``).
        """
        if len(ids) == 0:
            return
        fresh_mask = ~self.store.dynamic[ids]
        fresh = ids[fresh_mask]
        self.store.dynamic[fresh] = True
        self.store.moving[fresh] = True if moving is None else np.asarray(moving, bool)[fresh_mask]
        self.index.remove(fresh)
        self.counts["dynamic_flagged"] += len(fresh)
        self.counts[f"dynamic_by_{witness}"] += len(fresh)

    def _merge_duplicates(self, ids: IntArray, k: int) -> IntArray:
        """Merge newly mapped points onto older ones at the same global position (paper II-D)."""
        if not self._newly_mapped or self.config.merge_bound <= 0:
            self._newly_mapped = []
            return ids
        store = self.store
        newly_mapped = np.concatenate(self._newly_mapped)
        self._newly_mapped = []
        self._refresh_index()
        newly, keys = self.index.indexable_cells(
            newly_mapped, store.alive, store.pos_sum, store.pos_weight, store.dynamic
        )
        bound2 = self.config.merge_bound**2
        merging = newly if self._older_point_within(newly, keys, bound2) else newly[:0]  # usually none
        for newer in merging.tolist():
            if not store.alive[newer]:
                continue
            position = store.positions(np.array([newer]))[0]
            candidates = np.asarray(self.index.candidates(position), np.int64)
            candidates = candidates[(candidates != newer) & (store.uid[candidates] < store.uid[newer])]
            if len(candidates) == 0:
                continue
            d2 = np.sum((store.positions(candidates) - position) ** 2, axis=1)
            for j in np.argsort(d2).tolist():
                if d2[j] > bound2:
                    break
                older = int(candidates[j])
                if not store.co_observed(older, newer):
                    self._merge(older, newer, k)
                    ids[ids == newer] = older
                    break
        self._reabsorb_flagged(newly, ids, k)
        return ids

    def _older_point_within(self, newly: IntArray, keys: IntArray, bound2: float) -> bool:
        """Whether any of the mapped points ``newly`` (in the index cells ``keys``) has an older indexed
        point within ``sqrt(bound2)`` m.

        One pass over every point's index neighbours (:func:`~._kernels.older_within`); when it finds
        none, the merging loop of :meth:`_merge_duplicates` would merge nothing.
        """
        if len(newly) == 0:
            return False
        store = self.store
        neighbours = [self.index.candidates_at(key) for key in keys.tolist()]
        offsets = np.array([0, *itertools.accumulate(len(found) for found in neighbours)], np.int64)
        candidates = np.fromiter(itertools.chain.from_iterable(neighbours), np.int64, int(offsets[-1]))
        return bool(older_within(store.pos_sum, store.pos_weight, store.uid, newly, candidates, offsets, float(bound2)))

    def _reabsorb_flagged(self, newly: IntArray, ids: IntArray, k: int) -> None:
        """Merge newly mapped static points onto older points flagged dynamic at the same place.

        A static point wrongly flagged leaves the global index, so when the sensor returns it is
        registered again as a new point. Once that new point is mapped as static, the old record
        (reported at its mean world position) takes it over and follows its judgement, so the map
        does not gain an entry for every false alarm across passes. A truly moving point is rarely
        mapped static at its old mean position, and if it is, it would otherwise sit in the map twice.
        """
        store = self.store
        bound2 = self.config.merge_bound**2
        n = store.high_water
        if not flagged_within(
            store.world_sum, store.n_obs, store.alive, store.dynamic, store.uid, n, store.pos_sum, store.pos_weight,
            newly, float(bound2),
        ):  # fmt: skip
            return  # the usual case, found in one pass: nothing to take over
        newly = newly[store.alive[newly] & (store.pos_weight[newly] > 0) & ~store.dynamic[newly]]
        positions = store.positions(newly)
        flagged = np.flatnonzero(store.alive[:n] & store.dynamic[:n])
        flagged_at = store.world_sum[flagged] / np.maximum(store.n_obs[flagged], 1)[:, None]
        d2 = np.sum((positions[:, None, :] - flagged_at[None, :, :]) ** 2, axis=2)
        older_than = store.uid[flagged][None, :] < store.uid[newly][:, None]
        d2 = np.where(older_than, d2, np.inf)
        taken: set[int] = set()
        nearest = d2.min(axis=1)
        for row in np.argsort(nearest).tolist():
            if nearest[row] > bound2:
                break  # this and every later row have nothing within the bound
            for column in np.argsort(d2[row]).tolist():
                if d2[row, column] > bound2:
                    break
                older, newer = int(flagged[column]), int(newly[row])
                if older in taken or store.co_observed(older, newer):
                    continue
                taken.add(older)
                self._merge(older, newer, k)
                store.dynamic[older] = False
                store.moving[older] = False
                ids[ids == newer] = older
                self.counts["reabsorbed"] += 1
                break

    def _merge(self, older: int, newer: int, k: int) -> None:
        store = self.store
        first, last = int(store.first_iter[newer]), int(store.last_iter[newer])
        store.merge_into(older, newer)
        self.groups.transfer(newer, older)
        self.charting.replace(newer, older, first, min(last, k))
        self.tally.relabel(int(store.uid[newer]), int(store.uid[older]))
        self._merged_uid[int(store.uid[newer])] = int(store.uid[older])
        self.index.remove(newer)
        self.ungrouped.discard(newer)
        self._over_grouped.discard(newer)
        store.delete(newer)
        self.counts["merges"] += 1
