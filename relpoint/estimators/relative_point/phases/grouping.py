"""New points and the groups over them: first groups, regrouping over intervals of co-visibility, and each group built on three basis points."""

from __future__ import annotations

import logging

import numpy as np
import numpy.typing as npt

from relpoint.estimators.relative_point._kernels import (
    SELECTION_MADE,
    SELECTION_NO_CREATION,
    SELECTION_NONE,
    creation_triage,
    group_relative_map,
    group_selection,
    members_above,
    regroup_due,
    unmapped_members,
)
from relpoint.estimators.relative_point.groups import (
    FIRST,
    LATER,
    ROOT,
    RelativeGroup,
)
from relpoint.estimators.relative_point.points import IntArray
from relpoint.estimators.relative_point.registration import NO_MATCH
from relpoint.estimators.relative_point.state import EstimatorState
from relpoint.geometry import FloatArray, apply_transform

logger = logging.getLogger(__name__)


class Grouping(EstimatorState):
    """New points and the groups over them: first groups, regrouping over intervals of co-visibility, and
    each group built on three basis points.

    A phase of :class:`~relpoint.estimators.relative_point.estimator.RelativePointEstimator` over
    the state it shares with the other phases (:class:`~relpoint.estimators.relative_point.state.EstimatorState`).
    """

    def _add_points(self, points: FloatArray, ids: IntArray, k: int, gt_ids: IntArray | None) -> IntArray:
        """Create points for unmatched observations, then append every observation to its ring."""
        new = (ids == NO_MATCH).nonzero()[0]
        if len(new):
            ids[new] = self.store.new_points(len(new))
            self.ungrouped.add(ids[new])
            self.counts["new_points"] += len(new)
        self.store.add_observations(ids, points, k)
        duplicate = self.charting.chart(k, ids)
        if duplicate.any():  # registration is one-to-one, so this is a bug, not a data problem
            raise AssertionError("point charted twice in one iteration")
        if gt_ids is not None:
            self.tally.add(self.store.uid[ids], gt_ids)
        return ids

    def _create_first_groups(self, k: int) -> None:
        """First groupings (paper II-C): creation points a few iterations after they are first seen."""
        config, store = self.config, self.store
        if k % config.creation_every:
            return
        listed = self.ungrouped.ids()
        if len(listed) == 0:
            return
        stale, unlisted, due = creation_triage(
            listed, store.alive, store.pos_weight, store.dynamic, store.last_iter, store.run_start, k,
            int(config.stale_after), int(config.creation_delay),
        )  # fmt: skip
        if len(stale):
            self._drop_points(stale)
        if len(unlisted):
            self.ungrouped.discard(unlisted)
        attempts = 0
        for creation in due.tolist():
            if attempts >= config.max_creations_per_iteration:
                break
            if store.pos_weight[creation] > 0 or self._next_creation_try.get(creation, -1) > k:
                continue
            attempts += 1
            first = max(int(store.run_start[creation]), k - config.ring_size + 1)
            if not self._create_group(k, creation, first, k, FIRST):
                self._next_creation_try[creation] = k + max(config.creation_delay, 1)
                self.counts["failed_groupings"] += 1

    def _regroup(self, k: int) -> None:
        """Regrouping (paper II-C): recompute points over longer intervals from stored observations."""
        config, store = self.config, self.store
        if config.max_regroups_per_iteration == 0:
            return
        previous = self.charting.seen(k - 1)
        if len(previous):
            due = regroup_due(
                previous, self.charting.seen(k), store.alive, store.last_iter, store.run_start, store.n_later_groups,
                store.pos_weight, store.dynamic, store.regroup_attempt, k, int(config.regroup_min_iterations),
                int(config.regroup_after),
            )  # fmt: skip
            store.regroup_attempt[due] = k
            self._regroup_queue.extend(due.tolist())
        done = 0
        while self._regroup_queue and done < config.max_regroups_per_iteration:
            point = self._regroup_queue.popleft()
            if not store.alive[point] or store.dynamic[point] or store.n_later_groups[point] > 0:
                continue
            first = int(store.run_start[point])
            last = int(store.last_iter[point])
            if k - first >= config.ring_size:
                first = k - config.ring_size + 1
            if last - first + 1 < config.regroup_min_iterations:
                continue
            done += 1
            if not self._create_group(k, point, first, last, LATER):
                self.counts["failed_groupings"] += 1

    def _create_group(self, k: int, creation: int, first: int, last: int, kind: str) -> bool:
        """Build, check and place one group with ``creation`` as creation point over ``[first, last]``."""
        config, store = self.config, self.store
        candidates = self.charting.enumerate(first, last)
        members, interval, outcome = self._select_members(candidates, creation, first, last, everyone_grouped=False)
        if outcome == SELECTION_NO_CREATION:
            return False
        root = False
        if outcome == SELECTION_NONE and kind == FIRST and self._no_anchor_in_view(candidates):
            # Nothing mapped in view (the start, or the map was lost): anchor to observations + pose.
            members, interval, outcome = self._select_members(candidates, creation, first, last, everyone_grouped=True)
            root = True
        if outcome != SELECTION_MADE:
            return False
        iterations = first + interval.nonzero()[0]
        moving, beyond, verified = self._detect_dynamic(k, members, iterations)
        if len(moving):
            members = members[~np.isin(members, moving)]
        if len(members) < config.seed_points + 1:
            return False
        i0, i1, i2, rel_sum, count, first_valid = group_relative_map(
            store.obs, store.obs_iter, members, iterations, store.verified, float(config.min_basis_spread)
        )
        if i0 < 0 or count == 0:
            return False  # no basis, or no iteration with a usable one
        basis = (int(i0), int(i1), int(i2))
        anchor_targets = None
        if root:
            t0 = int(iterations[first_valid])
            T0 = self._poses[t0 % config.ring_size] if t0 < k else self._T_world_sensor
            observations, _ = store.observations(members, iterations)
            anchor_targets = apply_transform(T0, observations[:, first_valid])
        group = RelativeGroup(
            gid=self.groups.new_gid(),
            kind=ROOT if root else kind,
            members=members,
            basis=basis,
            rel_sum=rel_sum,
            count=int(count),
            last_iteration=int(iterations[-1]),
            is_open=bool(iterations[-1] == k),
            anchor_targets=anchor_targets,
        )
        newly_mapped = unmapped_members(store.pos_weight, members)
        if not self.groups.add(group):
            return False
        self._flag_dynamic(moving, "grouping", beyond)
        if len(verified):
            store.verified[verified] = k
        self._newly_mapped.append(newly_mapped)
        if group.kind == FIRST:
            self._first_groups.append(group.gid)
        if group.kind == ROOT and self.counts["root_groups"]:
            self._map_restarts.append(k)
        self.counts[{ROOT: "root_groups", FIRST: "first_groups", LATER: "regroups"}[group.kind]] += 1
        crowded = members_above(store.n_groups, members, int(config.max_groups_per_point))
        self._over_grouped.update(crowded.tolist())
        return True

    def _select_members(
        self, candidates: IntArray, creation: int, first: int, last: int, *, everyone_grouped: bool
    ) -> tuple[IntArray, npt.NDArray[np.bool_], int]:
        """Members (ids) of a group over ``[first, last]`` among ``candidates`` (the points charted in it),
        its interval mask and the outcome (:func:`~._kernels.group_selection`; the heuristic of
        :func:`~relpoint.estimators.relative_point.grouping.select_members` over the live static candidates)."""
        store = self.store
        return group_selection(
            store.obs_iter, store.alive, store.dynamic, store.pos_weight, candidates, int(creation), int(first),
            int(last), int(self.config.seed_points), everyone_grouped,
        )  # fmt: skip

    def _no_anchor_in_view(self, candidates: IntArray) -> bool:
        return int(np.count_nonzero(self.store.mapped(candidates) & ~self.store.dynamic[candidates])) < 3
