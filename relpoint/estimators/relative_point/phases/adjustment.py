"""The final adjustment when the log ends: the whole network solved jointly, every iteration located again on it, and kept only where it does not place the observations worse."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import numpy as np
import numpy.typing as npt

from relpoint.estimators._noise import SIMULATOR_SIGMA
from relpoint.estimators.relative_point.adjustment import adjust_network, inconsistent_relocations, smooth_corrections
from relpoint.estimators.relative_point.dynamics import tail_bound
from relpoint.estimators.relative_point.groups import ROOT
from relpoint.estimators.relative_point.lsf import _median
from relpoint.estimators.relative_point.points import IntArray
from relpoint.estimators.relative_point.state import EstimatorState
from relpoint.geometry import FloatArray, apply_transform, rigid_inverse
from relpoint.types import Trajectory

logger = logging.getLogger(__name__)


#: The final adjustment is kept unless it places the log's observations (each iteration's kept ones,
#: by its pose, against their points) this much farther from their points than the incremental map.
ADJUSTMENT_TOLERANCE = 0.05


#: Iterations on either side whose relocations set an iteration's correction after the final adjustment.
RELOCATION_WINDOW = 10


class FinalAdjustment(EstimatorState):
    """The final adjustment when the log ends: the whole network solved jointly, every iteration located
    again on it, and kept only where it does not place the observations worse.

    A phase of :class:`~relpoint.estimators.relative_point.estimator.RelativePointEstimator` over
    the state it shares with the other phases (:class:`~relpoint.estimators.relative_point.state.EstimatorState`).
    """

    def finish(self, trajectory: Trajectory) -> Trajectory:
        """Adjust the whole map by least squares and locate every iteration again on it.

        With ``final_adjustment`` (the default) every group pose and point position is solved jointly
        (:meth:`adjust`); points whose groups still disagree are flagged dynamic and the solve is
        repeated without them (:meth:`_flag_disagreeing`). Then each iteration's pose is fitted
        again, as :meth:`_locate` fitted it, from
        the observations it kept (``relocate_points``) to the adjusted global positions. An iteration
        that cannot be fitted again (too few of its points still mapped), or whose fit moves it unlike
        its neighbours (:func:`.adjustment.inconsistent_relocations`), keeps the correction of the
        nearest iteration before it; then every iteration takes the median correction of the fitted
        iterations within ``RELOCATION_WINDOW`` (:func:`.adjustment.smooth_corrections`).
        ``trajectory`` holds the poses :meth:`step` returned.

        The result is checked against the incremental solution on the log's own observations
        (:meth:`_support_residual`): if the adjusted map and poses place them more than
        ``ADJUSTMENT_TOLERANCE`` farther from their points, the incremental map and trajectory are
        kept; ``final_adjustment`` in :meth:`summary` says which was kept and why.
        """
        if not self.config.final_adjustment or len(trajectory) != self._iteration:
            return trajectory
        T_incremental = trajectory.matrices()
        residual_before = self._support_residual(T_incremental)
        incremental_poses = [(group, group.T_world_group.copy()) for group in self.groups.groups.values()]
        if not self.adjust():
            return trajectory
        flagged = self._flag_disagreeing()
        if len(flagged):
            self.adjust()
        assert self.adjustment_report is not None
        self.adjustment_report["dynamic_flagged"] = len(flagged)
        store = self.store
        live = store.live_ids()
        row_of = dict(zip(store.uid[live].tolist(), live.tolist(), strict=True))
        for newer, older in self._merged_uid.items():
            while older not in row_of and older in self._merged_uid:
                older = self._merged_uid[older]
            if older in row_of:
                row_of.setdefault(newer, row_of[older])
        T_before = trajectory.matrices()
        T_fit = T_before.copy()
        fitted = np.zeros(len(T_before), bool)
        seen = np.zeros((len(T_before), 3))
        for k, observed, rows in self._supported_points(row_of):
            fit = self._fit_pose(observed.astype(np.float64), rows)
            if fit is not None:
                T_fit[k], fitted[k] = fit, True
                seen[k] = observed.mean(axis=0)
        # A fit on few or misplaced points moves its iteration unlike its neighbours: such an
        # iteration takes its neighbours' correction instead.
        outliers = inconsistent_relocations(
            T_before, T_fit, fitted, seen, floor=3.0 * (self.config.observation_sigma or SIMULATOR_SIGMA)
        )
        fitted &= ~outliers
        T_after = T_before.copy()
        correction = np.eye(4)
        for k in range(len(T_before)):
            if fitted[k]:
                T_after[k] = T_fit[k]
                correction = T_fit[k] @ rigid_inverse(T_before[k])
            else:
                T_after[k] = correction @ T_before[k]
        # Drift builds up slowly, and so does its correction; a fit on the few observations an
        # iteration kept is noisy. Every iteration takes the median correction of the fitted
        # iterations around it, keeping the incremental path's local shape.
        T_after = smooth_corrections(T_before, T_after, fitted, RELOCATION_WINDOW)
        T_after[0] = T_before[0]  # the first iteration defines ``world``
        self.adjustment_report["relocated_iterations"] = int(np.count_nonzero(fitted))
        self.adjustment_report["relocations_rejected"] = int(np.count_nonzero(outliers))
        residual_after = self._support_residual(T_after)
        report = self.adjustment_report
        report["support_residual_before"] = round(residual_before, 4)
        report["support_residual_after"] = round(residual_after, 4)
        if residual_after > (1.0 + ADJUSTMENT_TOLERANCE) * residual_before:
            # The adjusted map explains the log's own observations worse than the incremental one:
            # keep the incremental map and trajectory (the points flagged dynamic stay flagged).
            for group, T_world_group in incremental_poses:
                self.groups.move(group, T_world_group)
            self._refresh_index()
            report["kept"] = "incremental"
            report["reason"] = (
                f"adjusted observations {residual_after:.3f} m from their points against "
                f"{residual_before:.3f} m before (median RMS over iterations)"
            )
            return trajectory
        report["kept"] = "adjusted"
        from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

        orientation = Rotation.from_matrix(T_after[:, :3, :3]).as_quat(canonical=True)
        return Trajectory(trajectory.stamps_ns, T_after[:, :3, 3], orientation)

    def _supported_points(
        self, row_of: dict[int, int]
    ) -> Iterator[tuple[int, npt.NDArray[np.float32], IntArray]]:
        """Per iteration that kept observations: ``(k, observed, rows)``, its kept sensor-frame
        observations (M, 3) of static mapped points and their rows in the point store (``row_of``:
        uid -> row)."""
        store = self.store
        for k, support in enumerate(self._support):
            if support is None:
                continue
            uids, observed = support
            rows = np.array([row_of.get(uid, -1) for uid in uids.tolist()], np.int64)
            usable = rows >= 0
            usable[usable] = (store.pos_weight[rows[usable]] > 0) & ~store.dynamic[rows[usable]]
            yield k, observed[usable], rows[usable]

    def _support_residual(self, T_world_sensor: FloatArray) -> float:
        """Median over iterations of the RMS distance (m) of each one's kept observations, placed by its
        pose (K, 4, 4), from their points' current global positions (static mapped points only)."""
        store = self.store
        live = store.live_ids()
        row_of = dict(zip(store.uid[live].tolist(), live.tolist(), strict=True))
        per_iteration = []
        for k, observed, rows in self._supported_points(row_of):
            if len(rows) < 3:
                continue
            placed = apply_transform(T_world_sensor[k], observed.astype(np.float64))
            per_iteration.append(np.sqrt(np.mean(np.sum((placed - store.positions(rows)) ** 2, axis=1))))
        return float(np.median(per_iteration)) if per_iteration else float("nan")

    def _flag_disagreeing(self) -> IntArray:
        """Flag the points whose groups still disagree about their position after the adjustment.

        Once every group is where the whole network puts it, a static point's groups agree on it to
        within the noise, while a moving point the detection missed is placed where it stood during
        each group's interval. A point in at least three groups whose disagreement (RMS, m) exceeds
        ``adjustment_dynamic_factor`` times the median of such points is flagged dynamic. Returns
        the ids flagged.
        """
        factor = self.config.adjustment_dynamic_factor
        store = self.store
        live = store.live_ids()
        judged = live[(store.pos_weight[live] > 0) & ~store.dynamic[live] & (store.n_groups[live] >= 3)]
        if factor <= 0 or len(judged) == 0:
            return np.zeros(0, np.int64)
        spread = store.spread(judged)
        bound = factor * _median(spread)
        outside = spread > bound
        flagged = judged[outside]
        moving = spread[outside] > max(bound, tail_bound(spread, self.config.dynamic_tail_sigmas))
        self._flag_dynamic(flagged, "adjustment", moving)
        return flagged

    def _keep_support(self, k: int, points: FloatArray, ids: IntArray, mapped: npt.NDArray[np.bool_] | None) -> None:
        """Keep up to ``relocate_points`` of this iteration's observations of ``mapped`` points (None: not located)."""
        if not self.config.final_adjustment or mapped is None or k == 0:
            # The first iteration defines ``world``; a coasted one had no usable fit.
            self._support.append(None)
            return
        use = np.flatnonzero(mapped)
        keep = self.config.relocate_points
        if len(use) > keep:
            use = use[np.arange(keep) * (len(use) - 1) // (keep - 1)]  # evenly spread
        self._support.append((self.store.uid[ids[use]], points[use].astype(np.float32)))

    def adjust(self) -> bool:
        """Joint least-squares adjustment of every placed group and mapped point (:mod:`.adjustment`).

        Flagged dynamic points take no part; groups with fewer than three such members keep their
        pose. The root group stays where it is: it carries ``world``. Returns whether anything was
        adjusted; the figures go to :meth:`summary` under ``final_adjustment``.
        """
        config, store = self.config, self.store
        groups, members, relative, weights = [], [], [], []
        cap = config.adjustment_members
        for group in self.groups.groups.values():
            usable = np.flatnonzero(store.alive[group.members] & ~store.dynamic[group.members])
            if group.weight <= 0 or len(usable) < 3:
                continue
            if len(usable) > cap:
                # Points in the most groups tie the network together; the same points win in every
                # group, so the groups stay coupled through them.
                usable = usable[np.argsort(-store.n_groups[group.members[usable]], kind="stable")[:cap]]
            groups.append(group)
            members.append(group.members[usable])
            relative.append(group.relative_map[usable])
            weights.append(np.full(len(usable), float(group.count)))
        if not groups:
            return False
        group_rows = np.repeat(np.arange(len(groups)), [len(m) for m in members])
        points, point_rows = np.unique(np.concatenate(members), return_inverse=True)
        T_before = np.array([group.T_world_group for group in groups])
        result = adjust_network(
            group_rows,
            point_rows,
            np.concatenate(relative),
            np.concatenate(weights),
            T_before[:, :3, :3],
            T_before[:, :3, 3],
            store.positions(points),
            np.array([group.kind == ROOT for group in groups]),
            prior=config.adjustment_prior,
            robust=config.adjustment_robust,
            iterations=config.adjustment_iterations,
        )
        T_after = np.repeat(np.eye(4)[None], len(groups), axis=0)
        T_after[:, :3, :3] = result.R_world_group
        T_after[:, :3, 3] = result.t_world_group
        for group, T_world_group in zip(groups, T_after, strict=True):
            self.groups.move(group, T_world_group)
        self._refresh_index()
        self.adjustment_report = {
            "groups": len(groups),
            "points": len(points),
            "memberships": len(group_rows),
            "iterations": result.iterations,
            "cost_before": round(result.cost_before, 3),
            "cost_after": round(result.cost_after, 3),
        }
        return True
