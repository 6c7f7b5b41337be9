"""The Relative Point estimator: Kraut, *A Relative Point Algorithm*, section II, behind :class:`Estimator`.

Paper name -> Python name
    *RltMapper*         :class:`RelativePointEstimator` (entry point; group creation and regrouping)
    *Point*, *RltPoint*, *RltInterval*   :mod:`.points` (:class:`PointStore`)
    *RltPointCharting*  :mod:`.charting` (:class:`PointCharting`)
    *OVLQPQuadTree*     :mod:`.registration` (sorted sweep locally, :class:`GlobalIndex` globally)
    loop closure        :mod:`.loops` (global matching beyond its bound, an addition to section II-D)
    *RltLSF*            :mod:`.lsf` (:func:`fit_transform`)
    compiled inner loops   :mod:`._kernels` (numba; each with its numpy meaning)
    *RltGroup*, *RltGroupRef*   :mod:`.groups` (:class:`RelativeGroup`, :class:`GroupMap`)
    *RltUngroupedList*  :mod:`.grouping` (:class:`UngroupedList`; member heuristic :func:`select_members`)
    dynamic detection   :mod:`.dynamics` (:func:`detect_dynamic`)
    final adjustment    :mod:`.adjustment` (:func:`adjust_network`)
    settings            :mod:`.config` (:class:`RelativePointConfig`)

One iteration (:meth:`RelativePointEstimator.step`) reads like section II:

1. *register* the untransformed points against the latest observations of recently seen points;
2. *match globally* the rest through the current position (backtracking, loop closure); the rest
   become new points;
3. *detect dynamics* among the points in view (every few iterations);
4. *compute groups*: every open group whose members were all observed averages the iteration;
5. *create groups* a few iterations after points are first seen, and *regroup* points over longer
   intervals later, with *dynamic detection* before a group is final;
6. *merge* new points whose global position converges onto an older point;
7. *locate*: the current position is the least-squares fit of the observations to their global
   positions.

Choices the paper leaves open, and where this implementation adds to it:

* Local matching may predict the previous observations into the current frame with the motion
  between the last two iterations' raw observations (``predict_motion``; never current position).
* A group stays open only while every member is observed in every iteration; longer intervals come
  from regrouping over stored observations. The root group is never removed: it carries the world
  frame. First groupings are attempted every ``creation_every`` iterations.
* Dynamic detection runs the paper's binning over a group's interval when it is long enough
  (regroupings). First groupings are too short to tell motion from noise, so the majority bin is
  kept between detections as the set of points *verified* static, and every ``dynamic_every``
  iterations each point in view is compared against several of them over its recent history (the
  paper's last round against the majority bin), with a second witness: how much the groups that
  placed the point disagree about its global position. Verified points are preferred as basis
  points and weigh more as anchors and for the current position.
* The sweep compares distances averaged over blocks of ``dynamic_block`` iterations (noise down by
  about its square root, slow movers kept), and has a third witness: the scatter of the point's
  block-mean positions in ``world`` through the poses of their iterations, which sees motion in
  every direction (``dynamic_world_factor``).
* A flagged point leaves the static map and every fit, but it is reported as a dynamic landmark only
  where the value that flagged it stands out of the bulk of the values judged with it
  (``dynamic_tail_sigmas``); the others are left out of the map as unreliable: a real sensor's
  heavy-tailed error makes static points cross the factors now and then.
* Group fits and the current position re-seed from the best three-point fit among the heaviest
  pairs (a deterministic RANSAC) when several pairs lie beyond ``consensus_bound``.
* Least-squares fits weight each anchor by the iterations averaged into its global position over
  the squared disagreement of its groups (inverse variance), and trim gross outliers.
* A point in more than ``max_groups_per_point`` groups loses its lightest redundant closed group,
  so memory follows the map, not the number of passes (but for the few observations each iteration
  keeps for the final adjustment, below: about 0.4 kB an iteration at 20 points in view).
* Local matching gives the points a first round leaves over a second round whose bound grows with
  range (``match_angle``): at low density the motion's rotation error otherwise keeps far points
  entering view from matching, and they are registered as new points iteration after iteration.
* Loop closure also works beyond the global matching bound (:mod:`.loops`): an offset of the young
  points in view onto old mapped points that several of them agree on is taken out of the groups
  and poses along the loop, and the young points are matched or merged to the old ones.
* When the log ends (:meth:`RelativePointEstimator.finish`, ``final_adjustment``), every group pose and
  point position is solved jointly by least squares (:mod:`.adjustment`) instead of group by group,
  and every iteration's pose is fitted again to the adjusted map from observations it kept for that
  (``relocate_points``). ``step`` returns the online poses; the pipeline writes the final ones.
* Observation ids are never used for association; they only label the output map (``gt_id``).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from relpoint.estimators._noise import SIMULATOR_SIGMA
from relpoint.estimators.base import POINTS, Estimator
from relpoint.estimators.relative_point import _kernels
from relpoint.estimators.relative_point.adjustment import adjust_network, inconsistent_relocations, smooth_corrections
from relpoint.estimators.relative_point.charting import PointCharting
from relpoint.estimators.relative_point.config import RelativePointConfig
from relpoint.estimators.relative_point.dynamics import (
    detect_dynamic,
    deviation_to_references,
    distance_deviation,
    tail_bound,
    world_block_deviation,
)
from relpoint.estimators.relative_point.grouping import UngroupedList, select_members
from relpoint.estimators.relative_point.groups import (
    FIRST,
    LATER,
    ROOT,
    GroupMap,
    RelativeGroup,
    choose_basis,
    relative_coordinates,
)
from relpoint.estimators.relative_point.loops import drift_profile, vote_offset
from relpoint.estimators.relative_point.lsf import _median, fit_transform
from relpoint.estimators.relative_point.points import IntArray, PointStore
from relpoint.estimators.relative_point.registration import (
    NO_MATCH,
    GlobalIndex,
    MotionModel,
    match_mutual,
    match_nearest,
)
from relpoint.estimators.relative_point.tally import IdTally
from relpoint.estimators.spec import EstimatorSpec
from relpoint.geometry import FloatArray, apply_transform, quaternion_xyzw, rigid_inverse
from relpoint.types import LandmarkMap, PointObservation, Pose, Trajectory

logger = logging.getLogger(__name__)


#: The final adjustment is kept unless it places the log's observations (each iteration's kept ones,
#: by its pose, against their points) this much farther from their points than the incremental map.
ADJUSTMENT_TOLERANCE = 0.05

#: Iterations on either side whose relocations set an iteration's correction after the final adjustment.
RELOCATION_WINDOW = 10

class RelativePointEstimator(Estimator[PointObservation]):
    """The Relative Point algorithm (the paper's *RltMapper*); see the module docstring.

    :meth:`step` takes one iteration's untransformed points and returns ``T_world_sensor``; the
    world frame is the sensor frame of the first iteration, so the first pose is the identity.
    Observation ids are never used for association; they only label the output map (``gt_id``).
    """

    name: ClassVar[str] = "relpoint"

    def __init__(self, config: RelativePointConfig | None = None, rng: np.random.Generator | None = None) -> None:
        del rng  # the algorithm draws no random numbers
        self.config = config = config or RelativePointConfig()
        self.store = PointStore(config.ring_size)
        self.charting = PointCharting(config.ring_size)
        self.groups = GroupMap(
            self.store,
            trim=config.trim,
            floor=config.trim_floor,
            collinear_tolerance=config.collinear_tolerance,
            min_basis_spread=config.min_basis_spread,
            spread_floor=config.spread_floor,
            unverified_weight=config.unverified_weight,
            rounds=config.trim_rounds,
            consensus=config.consensus_bound,
        )
        self.motion = MotionModel()
        self.index = GlobalIndex(max(config.global_match_bound, config.merge_bound, 1e-3))
        self.ungrouped = UngroupedList()
        self.tally = IdTally()
        self._poses = np.repeat(np.eye(4)[None], config.ring_size, axis=0)
        self._T_world_sensor = np.eye(4)
        self._path = np.zeros((256, 3))  # position of every iteration (world, m): loop corrections follow it
        self._motion_measured = False
        self._iteration = 0
        self._regroup_queue: deque[int] = deque()
        self._first_groups: deque[int] = deque()
        self._over_grouped: set[int] = set()
        self._newly_mapped: list[IntArray] = []
        self._next_creation_try: dict[int, int] = {}
        self.adjustment_report: dict[str, Any] | None = None
        # Per iteration: uids and sensor-frame observations of mapped points, to locate it again
        # after the final adjustment; and where merged points' uids went.
        self._support: list[tuple[IntArray, npt.NDArray[np.float32]] | None] = []
        self._merged_uid: dict[int, int] = {}
        self.counts: dict[str, int] = dict.fromkeys(
            (
                "degenerate_iterations", "empty_iterations", "nonfinite_points", "new_points", "local_matches",
                "global_matches", "first_groups", "root_groups", "regroups", "failed_groupings",
                "first_groups_retired", "groups_pruned", "merges", "dynamic_flagged", "dynamic_comparisons",
                "dropped_points", "reabsorbed", "far_matches", "loop_closures", "dynamic_by_grouping",
                "dynamic_by_binning", "dynamic_by_references", "dynamic_by_spread", "dynamic_by_world",
                "dynamic_by_adjustment",
            ),
            0,
        )  # fmt: skip

    # -- Estimator interface ---------------------------------------------------------------------

    @classmethod
    def compile(cls) -> None:
        """Compile or load the compiled inner loops (:mod:`._kernels`)."""
        _kernels.prepare()

    def step(self, observation: PointObservation) -> Pose:
        """Process one iteration's untransformed points (sensor frame); return ``T_world_sensor``."""
        k = self._iteration
        self._iteration += 1
        points = np.asarray(observation.points, dtype=np.float64)
        finite = np.all(np.isfinite(points), axis=1)
        self.counts["nonfinite_points"] += int(np.count_nonzero(~finite))
        points = points[finite]
        gt_ids = None if observation.ids is None else np.asarray(observation.ids)[finite]
        if len(points) == 0:
            self.counts["empty_iterations"] += 1
            self.counts["degenerate_iterations"] += 1
            self.charting.chart(k, np.zeros(0, np.int64))
            self._support.append(None)
            return self._finish(k, observation.stamp_ns, self._T_world_sensor)

        self._motion_measured = False
        ids = self._register(points, k)
        if self.config.global_matching:
            self._match_globally(points, ids, k)
            if self.config.loop_search > 0 and k % self.config.loop_every == 0:
                self._close_loop(points, ids, k)
        ids = self._add_points(points, ids, k, gt_ids)
        self._dynamic_sweep(k)

        self.groups.update_open(k)
        self._create_first_groups(k)
        self._regroup(k)
        ids = self._merge_duplicates(ids, k)

        mapped = self._mapped_static(ids)
        T_world_sensor = np.eye(4) if k == 0 else self._locate(points, ids, mapped)
        self._keep_support(k, points, ids, mapped if T_world_sensor is not None else None)
        if T_world_sensor is None:
            logger.debug("iteration %d: fewer than three usable non-collinear mapped points, pose coasted", k)
            self.counts["degenerate_iterations"] += 1
            T_world_sensor = self._coast()
        self.store.world_sum[ids] += apply_transform(T_world_sensor, points)
        self._housekeeping(k)
        self._refresh_index()
        return self._finish(k, observation.stamp_ns, T_world_sensor)

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
        for k, support in enumerate(self._support):
            if support is None:
                continue
            uids, observed = support
            rows = np.array([row_of.get(uid, -1) for uid in uids.tolist()], np.int64)
            usable = rows >= 0
            usable[usable] = (store.pos_weight[rows[usable]] > 0) & ~store.dynamic[rows[usable]]
            fit = self._fit_pose(observed[usable].astype(np.float64), rows[usable])
            if fit is not None:
                T_fit[k], fitted[k] = fit, True
                seen[k] = observed[usable].mean(axis=0)
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
        orientation = Rotation.from_matrix(T_after[:, :3, :3]).as_quat(canonical=True)
        return Trajectory(trajectory.stamps_ns, T_after[:, :3, 3], orientation)

    def _support_residual(self, T_world_sensor: FloatArray) -> float:
        """Median over iterations of the RMS distance (m) of each one's kept observations, placed by its
        pose (K, 4, 4), from their points' current global positions (static mapped points only)."""
        store = self.store
        live = store.live_ids()
        row_of = dict(zip(store.uid[live].tolist(), live.tolist(), strict=True))
        per_iteration = []
        for k, support in enumerate(self._support):
            if support is None:
                continue
            uids, observed = support
            rows = np.array([row_of.get(uid, -1) for uid in uids.tolist()], np.int64)
            usable = rows >= 0
            usable[usable] = (store.pos_weight[rows[usable]] > 0) & ~store.dynamic[rows[usable]]
            if np.count_nonzero(usable) < 3:
                continue
            T = T_world_sensor[k]
            placed = apply_transform(T, observed[usable].astype(np.float64))
            per_iteration.append(np.sqrt(np.mean(np.sum((placed - store.positions(rows[usable])) ** 2, axis=1))))
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

    def landmark_map(self) -> LandmarkMap:
        """Mapped points (static: least-squares global position) and points reported moving (mean position);
        points flagged but not reported moving are left out (``landmarks_unreliable``)."""
        store = self.store
        live = store.live_ids()
        keep = live[self._reported(live)]
        if len(keep) == 0:
            return LandmarkMap.empty()
        positions = store.positions(keep)
        dynamic = store.dynamic[keep]
        n_obs = store.n_obs[keep]
        positions[dynamic] = store.world_sum[keep[dynamic]] / np.maximum(n_obs[dynamic], 1)[:, None]
        gt_id, purity = self.tally.majority(store.uid[keep])
        known = bool(np.any(gt_id >= 0))
        return LandmarkMap(positions, n_obs, dynamic, gt_id, np.clip(purity, 0.0, 1.0) if known else None)

    def _reported(self, ids: IntArray) -> npt.NDArray[np.bool_]:
        """Which points the map reports: static mapped points and points flagged as moving."""
        store = self.store
        return np.where(store.dynamic[ids], store.moving[ids], store.pos_weight[ids] > 0)

    def landmark_purity(self) -> FloatArray:
        """Share of each landmark's observations carrying its ``gt_id`` (M,), in :meth:`landmark_map` order."""
        store = self.store
        live = store.live_ids()
        keep = live[self._reported(live)]
        return self.tally.majority(store.uid[keep])[1]

    @property
    def map_size(self) -> int:
        store = self.store
        n = store.high_water
        return int(np.count_nonzero(store.alive[:n] & self._reported(np.arange(n))))

    @property
    def features_started(self) -> int:
        """Points started so far (``new_points``): a point enters the map only when a group places it,
        a few iterations after it was first seen, so the map's growth would not count them."""
        return self.counts["new_points"]

    def summary(self) -> dict[str, Any]:
        store = self.store
        n = store.high_water
        alive = store.alive[:n]
        return {
            "iterations": self._iteration,
            **self.counts,
            "points": int(np.count_nonzero(alive)),
            "landmarks_static": int(np.count_nonzero(alive & (store.pos_weight[:n] > 0) & ~store.dynamic[:n])),
            "landmarks_dynamic": int(np.count_nonzero(alive & store.dynamic[:n] & store.moving[:n])),
            "landmarks_unreliable": int(np.count_nonzero(alive & store.dynamic[:n] & ~store.moving[:n])),
            "groups": len(self.groups),
            "groups_created": self.groups.created,
            "groups_removed": self.groups.removed,
            "group_fit_failures": self.groups.failed_fits,
            **({"final_adjustment": self.adjustment_report} if self.adjustment_report else {}),
        }

    # -- the phases of one iteration -------------------------------------------------------------

    def _register(self, points: FloatArray, k: int) -> IntArray:
        """Local matching (paper II-A): ids (N,) of the recent points matched, ``NO_MATCH`` elsewhere."""
        config, store = self.config, self.store
        ids = np.full(len(points), NO_MATCH, np.int64)
        # Each recently seen point, once: from the charting of the iteration it was last seen in.
        recent = []
        for t in range(k - config.match_window, k):
            seen = self.charting.seen(t)
            recent.append(seen[store.last_iter[seen] == t])
        refs = np.concatenate(recent)
        if len(refs) == 0:
            return ids
        reference = store.latest(refs)
        age = k - store.last_iter[refs]
        predicted = self.motion.predict(reference, age) if config.predict_motion else reference
        row, _ = match_nearest(predicted, points, config.match_bound)
        pairs = np.flatnonzero((row != NO_MATCH) & (age[row] == 1))
        before = self.motion.T_curr_prev
        T_new = self.motion.update(reference[row[pairs]], points[pairs], config.trim_floor)
        self._motion_measured = T_new is not None
        if config.predict_motion and T_new is not None:
            # Largest change of prediction over the references: translation plus angle x range.
            (c00, _, _, x), (_, c11, _, y), (_, _, c22, z), _ = (T_new @ rigid_inverse(before)).tolist()
            angle = math.acos(min(1.0, max(-1.0, (c00 + c11 + c22 - 1.0) / 2.0)))
            reach = math.sqrt(float(np.max(np.einsum("ij,ij->i", reference, reference))))
            shift = math.sqrt(x * x + y * y + z * z) + angle * reach
            if shift > 0.5 * config.match_bound:
                # The prediction was off (a turn began): match again from the refreshed motion.
                predicted = self.motion.predict(reference, age)
                row, _ = match_nearest(predicted, points, config.match_bound)
        if config.predict_motion and config.match_angle > 0:
            self._match_far(reference, predicted, age, points, row)
        matched = row != NO_MATCH
        ids[matched] = refs[row[matched]]
        self.counts["local_matches"] += int(np.count_nonzero(matched))
        return ids

    def _match_far(
        self, reference: FloatArray, predicted: FloatArray, age: IntArray, points: FloatArray, row: IntArray
    ) -> None:
        """Second round of local matching, in place on ``row``: bounds grow with the predicted range.

        ``reference`` (R, 3) are the recent points' latest observations, ``predicted`` (R, 3) the same
        carried into the current sensor frame, ``age`` (R,) iterations since each was observed.

        The leftover observations and the recent points nobody matched are paired as mutual nearest
        neighbours within ``match_bound + match_angle * range``; new pairs refresh the motion.
        """
        free_points = np.flatnonzero(row == NO_MATCH)
        if len(free_points) == 0:
            return
        taken = np.zeros(len(reference), bool)
        taken[row[row != NO_MATCH]] = True
        free_refs = np.flatnonzero(~taken)
        if len(free_refs) == 0:
            return
        predicted = predicted[free_refs]
        bounds = self.config.match_bound + self.config.match_angle * np.sqrt(
            np.einsum("ij,ij->i", predicted, predicted)
        )
        found = match_mutual(predicted, points[free_points], bounds)
        matched = found != NO_MATCH
        if not matched.any():
            return
        row[free_points[matched]] = free_refs[found[matched]]
        self.counts["far_matches"] += int(np.count_nonzero(matched))
        pairs = np.flatnonzero((row != NO_MATCH) & (age[np.maximum(row, 0)] == 1))
        if self.motion.update(reference[row[pairs]], points[pairs], self.config.trim_floor) is not None:
            self._motion_measured = True

    def _match_globally(self, points: FloatArray, ids: IntArray, k: int) -> None:
        """Global matching (paper II-D) of unmatched points through the provisional current position."""
        unmatched = np.flatnonzero(ids == NO_MATCH)
        if len(unmatched) == 0 or len(self.index) == 0:
            return
        store = self.store
        world = apply_transform(self._provisional_pose(), points[unmatched])
        recent = k - self.config.match_window
        bound2 = self.config.global_match_bound**2
        claims: list[tuple[float, int, int]] = []
        keys = self.index.keys(world).tolist()
        for q, position, key in zip(unmatched.tolist(), world, keys, strict=True):
            candidates = np.asarray(self.index.candidates_at(key), np.int64)
            if len(candidates) == 0:
                continue
            candidates = candidates[store.last_iter[candidates] < recent]
            if len(candidates) == 0:
                continue
            d2 = np.sum((store.positions(candidates) - position) ** 2, axis=1)
            best = int(np.argmin(d2))
            if d2[best] <= bound2:
                claims.append((float(d2[best]), q, int(candidates[best])))
        taken: set[int] = set()
        for _, q, point in sorted(claims):
            if point not in taken:
                taken.add(point)
                ids[q] = point
        self.counts["global_matches"] += len(taken)

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
            young, old_positions, radius=config.loop_search, tolerance=tolerance, support=config.loop_support,
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

    def _add_points(self, points: FloatArray, ids: IntArray, k: int, gt_ids: IntArray | None) -> IntArray:
        """Create points for unmatched observations, then append every observation to its ring."""
        new = np.flatnonzero(ids == NO_MATCH)
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
        alive = store.alive[listed]
        done = ~alive | store.mapped(listed) | store.dynamic[listed]
        stale = alive & ~done & (k - store.last_iter[listed] > config.stale_after)
        if stale.any():
            self._drop_points(listed[stale])
        if (done | stale).any():
            self.ungrouped.discard(listed[done | stale])
        due = ~done & ~stale & (store.last_iter[listed] == k) & (k - store.run_start[listed] >= config.creation_delay)
        attempts = 0
        for creation in listed[due].tolist():
            if attempts >= config.max_creations_per_iteration:
                break
            if store.mapped(np.array([creation]))[0] or self._next_creation_try.get(creation, -1) > k:
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
            previous = previous[store.alive[previous]]
            left = previous[store.last_iter[previous] == k - 1]
            left = left[(k - store.run_start[left] >= config.regroup_min_iterations)]
            current = self.charting.seen(k)
            long_run = current[k - store.run_start[current] + 1 >= config.regroup_after]
            due = np.concatenate([left, long_run])
            due = due[
                (store.n_later_groups[due] == 0)
                & (store.pos_weight[due] > 0)
                & ~store.dynamic[due]
                & (k - store.regroup_attempt[due] >= config.regroup_after)
            ]
            for point in due.tolist():
                store.regroup_attempt[point] = k
                self._regroup_queue.append(point)
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
        candidates = candidates[store.alive[candidates] & ~store.dynamic[candidates]]
        where = np.flatnonzero(candidates == creation)
        if len(where) == 0:
            return False
        presence = store.presence(candidates, first, last)
        selection = select_members(presence, store.mapped(candidates), int(where[0]), config.seed_points)
        root = False
        if selection is None and kind == FIRST and self._no_anchor_in_view(candidates):
            # Nothing mapped in view (the start, or the map was lost): anchor to observations + pose.
            selection = select_members(presence, np.ones(len(candidates), bool), int(where[0]), config.seed_points)
            root = True
        if selection is None:
            return False
        rows, interval = selection
        members = candidates[rows]
        iterations = first + np.flatnonzero(interval)
        observations, _ = store.observations(members, iterations)
        moving, beyond, verified = self._detect_dynamic(k, members, observations, len(iterations))
        if len(moving):
            keep = ~np.isin(members, moving)
            members, observations = members[keep], observations[keep]
        if len(members) < config.seed_points + 1:
            return False
        basis = self._choose_basis(members, observations[:, 0])
        if basis is None:
            return False
        relative, valid = relative_coordinates(observations, basis, config.min_basis_spread)
        if not valid.any():
            return False
        anchor_targets = None
        if root:
            t0 = int(iterations[valid][0])
            T0 = self._poses[t0 % config.ring_size] if t0 < k else self._T_world_sensor
            anchor_targets = apply_transform(T0, observations[:, int(np.flatnonzero(valid)[0])])
        group = RelativeGroup(
            gid=self.groups.new_gid(),
            kind=ROOT if root else kind,
            members=members,
            basis=basis,
            rel_sum=relative[:, valid].sum(axis=1),
            count=int(valid.sum()),
            last_iteration=int(iterations[-1]),
            is_open=bool(iterations[-1] == k),
            anchor_targets=anchor_targets,
        )
        newly_mapped = members[~store.mapped(members)]
        if not self.groups.add(group):
            return False
        self._flag_dynamic(moving, "grouping", beyond)
        store.verified[verified] = k
        self._newly_mapped.append(newly_mapped)
        if group.kind == FIRST:
            self._first_groups.append(group.gid)
        self.counts[{ROOT: "root_groups", FIRST: "first_groups", LATER: "regroups"}[group.kind]] += 1
        crowded = members[store.n_groups[members] > config.max_groups_per_point]
        self._over_grouped.update(crowded.tolist())
        return True

    def _detect_dynamic(
        self, k: int, members: IntArray, observations: FloatArray, interval: int
    ) -> tuple[IntArray, npt.NDArray[np.bool_], IntArray]:
        """Dynamic detection before a group is final (paper II-C).

        Returns the ids found moving, whether each stands out of the bulk (:meth:`_beyond_bulk`)
        and the ids verified static. Runs over the group's interval when it is at least
        ``dynamic_min_iterations`` long (first groupings are shorter; their points are judged by
        :meth:`_dynamic_sweep` before they serve as basis or anchors).
        """
        config = self.config
        none = np.zeros(0, np.int64)
        if not config.dynamic_detection or interval < config.dynamic_min_iterations:
            return none, np.zeros(0, bool), none
        result = detect_dynamic(observations, gap_ratio=config.dynamic_gap_ratio, floor=self._pair_noise(1))
        self.counts["dynamic_comparisons"] += result.comparisons
        if not result.decided:
            return none, np.zeros(0, bool), none
        beyond = self._beyond_bulk(observations, result.static, result.threshold)
        return members[~result.static], beyond, members[result.static]

    def _beyond_bulk(self, observations: FloatArray, static: npt.NDArray[np.bool_], threshold: float) -> npt.NDArray[np.bool_]:
        """Which points outside the binning's static majority stand out of the bulk (one per such point).

        Every point's distance deviation (m) against up to ``dynamic_references`` members of the
        majority (median) is compared with :func:`.tail_bound` of all of them: a point beyond both
        it and the binning's ``threshold`` is reported moving; the rest of those the binning put
        outside are only left out (see ``dynamic_tail_sigmas``). ``observations`` is (M, L, 3).
        """
        outside = np.flatnonzero(~static)
        if len(outside) == 0 or self.config.dynamic_tail_sigmas <= 0:
            return np.ones(len(outside), bool)
        references = np.flatnonzero(static)[: self.config.dynamic_references]
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
            result = detect_dynamic(tracks, gap_ratio=config.dynamic_gap_ratio, noise_factor=margin,
                                    floor=self._pair_noise(1))
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

    def _choose_basis(self, members: IntArray, points: FloatArray) -> tuple[int, int, int] | None:
        """Basis rows of ``members``: among points verified static when they allow one, else among all."""
        spread = self.config.min_basis_spread
        trusted = np.flatnonzero(self.store.verified[members] >= 0)
        if len(trusted) >= 3:
            basis = choose_basis(points[trusted], spread)
            if basis is not None:
                return int(trusted[basis[0]]), int(trusted[basis[1]]), int(trusted[basis[2]])
        return choose_basis(points, spread)

    def _no_anchor_in_view(self, candidates: IntArray) -> bool:
        return int(np.count_nonzero(self.store.mapped(candidates) & ~self.store.dynamic[candidates])) < 3

    def _flag_dynamic(self, ids: IntArray, witness: str, moving: npt.NDArray[np.bool_] | None = None) -> None:
        """Flag points: they leave the static map, the global index and future fits.

        ``witness`` names the test that flagged them (counted as ``dynamic_by_<witness>``);
        ``moving`` (one per id, default all) says which are reported as dynamic landmarks, the
        others being left out of the map as unreliable (see ``dynamic_tail_sigmas``).
        """
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
        newly = np.unique(np.concatenate(self._newly_mapped))
        self._newly_mapped = []
        self._refresh_index()
        newly = newly[store.alive[newly] & (store.pos_weight[newly] > 0) & ~store.dynamic[newly]]
        bound2 = self.config.merge_bound**2
        for newer in newly.tolist():
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

    def _reabsorb_flagged(self, newly: IntArray, ids: IntArray, k: int) -> None:
        """Merge newly mapped static points onto older points flagged dynamic at the same place.

        A static point wrongly flagged leaves the global index, so when the sensor returns it is
        registered again as a new point. Once that new point is mapped as static, the old record
        (reported at its mean world position) takes it over and follows its judgement, so the map
        does not gain an entry for every false alarm across passes. A truly moving point is rarely
        mapped static at its old mean position, and if it is, it would otherwise sit in the map twice.
        """
        store = self.store
        newly = newly[store.alive[newly] & (store.pos_weight[newly] > 0) & ~store.dynamic[newly]]
        if len(newly) == 0:
            return
        n = store.high_water
        flagged = np.flatnonzero(store.alive[:n] & store.dynamic[:n])
        if len(flagged) == 0:
            return
        flagged_at = store.world_sum[flagged] / np.maximum(store.n_obs[flagged], 1)[:, None]
        positions = store.positions(newly)
        d2 = np.sum((positions[:, None, :] - flagged_at[None, :, :]) ** 2, axis=2)
        older_than = store.uid[flagged][None, :] < store.uid[newly][:, None]
        d2 = np.where(older_than, d2, np.inf)
        bound2 = self.config.merge_bound**2
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
        store = self.store
        safe = np.where(ids != NO_MATCH, ids, 0)
        return (ids != NO_MATCH) & (store.pos_weight[safe] > 0) & ~store.dynamic[safe]

    def _fit_pose(self, points: FloatArray, ids: IntArray) -> FloatArray | None:
        """``T_world_sensor`` fitting observations (N, 3) (sensor frame) to their points' global positions.

        Points whose groups disagree about their position (slow movers) and points not yet verified
        static count for less; gross outliers are trimmed. ``None`` if the fit is degenerate.
        """
        store, config = self.store, self.config
        weights = 1.0 / (store.spread(ids) ** 2 + config.spread_floor**2)
        weights *= np.where(store.verified[ids] >= 0, 1.0, config.unverified_weight)
        return self._fit_sensor(points, store.positions(ids), weights)

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
        changed = self.groups.take_changed()
        if len(changed) == 0:
            return
        store = self.store
        alive = changed[store.alive[changed]]
        indexable = (store.pos_weight[alive] > 0) & ~store.dynamic[alive]
        self.index.update(alive[indexable], store.positions(alive[indexable]))
        self.index.remove(alive[~indexable])

    def _housekeeping(self, k: int) -> None:
        """Bounded upkeep: retire redundant first groups and thin points in too many groups."""
        store, groups = self.store, self.groups
        for _ in range(min(4, len(self._first_groups))):
            gid = self._first_groups.popleft()
            group = groups.groups.get(gid)
            if group is None:
                continue
            if not group.is_open and store.n_later_groups[group.members].min() >= 1:
                groups.remove(gid)
                self.counts["first_groups_retired"] += 1
            else:
                self._first_groups.append(gid)
        for _ in range(min(4, len(self._over_grouped))):
            point = self._over_grouped.pop()
            refs = groups.refs_of(point)
            if not store.alive[point] or len(refs) <= self.config.max_groups_per_point:
                continue
            closed = [groups.groups[g] for g in refs if not groups.groups[g].is_open and groups.groups[g].kind != ROOT]
            for group in sorted(closed, key=lambda g: g.weight):
                if store.n_groups[group.members].min() >= 2:
                    groups.remove(group.gid)
                    self.counts["groups_pruned"] += 1
                    break

    def _drop_points(self, ids: IntArray) -> None:
        """Delete never-grouped points that are gone (clutter, one-off observations)."""
        self.tally.drop(self.store.uid[ids])
        for i in ids.tolist():
            self._next_creation_try.pop(i, None)
        self.store.delete(ids)
        self.counts["dropped_points"] += len(ids)

    def _finish(self, k: int, stamp_ns: int, T_world_sensor: FloatArray) -> Pose:
        self._T_world_sensor = T_world_sensor
        self._poses[k % self.config.ring_size] = T_world_sensor
        if k >= len(self._path):
            self._path = np.concatenate([self._path, np.zeros((max(len(self._path), 256), 3))])
        self._path[k] = T_world_sensor[:3, 3]
        x, y, z = T_world_sensor[:3, 3].tolist()
        return Pose(int(stamp_ns), (x, y, z), quaternion_xyzw(T_world_sensor[:3, :3]))


_LOOP_YOUNG_MAX = 64
"""Young points that vote on a loop's offset at most (an even sample of them in a dense view)."""


def _finite_median(values: FloatArray) -> float:
    """Median of the finite entries of a 1-D array (NaN if none)."""
    finite = values[np.isfinite(values)]
    return _median(finite) if len(finite) else float("nan")


SPEC = EstimatorSpec(
    name="relpoint",
    description="Relative Point: relative maps of co-observed point groups joined by least squares (Kraut)",
    config_class=RelativePointConfig,
    estimator_class=RelativePointEstimator,
    input_kind=POINTS,
    noise_adaptive=True,
)
