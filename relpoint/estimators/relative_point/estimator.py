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
    shared state        :mod:`.state` (:class:`~.state.EstimatorState`)

:meth:`RelativePointEstimator.step` composes the phases, one module each under :mod:`.phases`, over
the state they share: :class:`~.phases.localisation.Localisation` (steps 1, 2 and 7),
:class:`~.phases.loops.LoopClosing`, :class:`~.phases.grouping.Grouping` (steps 4-5),
:class:`~.phases.dynamics.DynamicSweep` (steps 3 and 6) and, when the log ends,
:class:`~.phases.adjustment.FinalAdjustment` (``finish``).

One iteration reads like section II:

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
  (``relocate_points``). Then every keyframe's pose and every static point are solved jointly from
  the run's own observations (``bundle_adjustment``), whose residuals flag the moving points kept as
  static and release the static points flagged as moving. ``step`` returns the online poses; the
  pipeline writes the final ones.
* Observation ids are never used for association; they only label the output map (``gt_id``).
"""

from __future__ import annotations

import logging
from collections import deque
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from relpoint.estimators._dropouts import DropoutRegistration
from relpoint.estimators._noise import SIMULATOR_SIGMA
from relpoint.estimators.base import POINTS, Estimator
from relpoint.estimators.relative_point import _kernels
from relpoint.estimators.relative_point._kernels import least_at
from relpoint.estimators.relative_point.charting import PointCharting
from relpoint.estimators.relative_point.config import RelativePointConfig
from relpoint.estimators.relative_point.grouping import UngroupedList
from relpoint.estimators.relative_point.groups import (
    ROOT,
    GroupMap,
)
from relpoint.estimators.relative_point.phases.adjustment import FinalAdjustment
from relpoint.estimators.relative_point.phases.dynamics import DynamicSweep
from relpoint.estimators.relative_point.phases.grouping import Grouping
from relpoint.estimators.relative_point.phases.localisation import Localisation
from relpoint.estimators.relative_point.phases.loops import LoopClosing
from relpoint.estimators.relative_point.points import IntArray, PointStore
from relpoint.estimators.relative_point.registration import (
    GlobalIndex,
    MotionModel,
)
from relpoint.estimators.relative_point.tally import IdTally
from relpoint.estimators.spec import EstimatorSpec
from relpoint.geometry import FloatArray, apply_transform, quaternion_xyzw, rigid_inverse
from relpoint.types import LandmarkMap, PointObservation, Pose

logger = logging.getLogger(__name__)

#: A run warns when more than this share of its iterations could not be located (pose coasted).
DEGENERATE_WARNING_SHARE = 0.2
#: ... or when at least this many iterations at its end could not be located: a log that ends after the
#: sensor left the landmarks it had mapped (a probe's drive out of a landmark field: the last 25 of 600
#: iterations held their pose while the sensor went on 6.8 m, ATE 0.75 m against 0.02 m before them).
UNLOCATED_TAIL_WARNING = 10


class RelativePointEstimator(
    Localisation, LoopClosing, Grouping, DynamicSweep, FinalAdjustment, Estimator[PointObservation]
):
    """The Relative Point algorithm (the paper's *RltMapper*); see the module docstring.

    :meth:`step` takes one iteration's untransformed points and returns ``T_world_sensor``; the
    world frame is the sensor frame of the first iteration, so the first pose is the identity.
    Observation ids are never used for association; they only label the output map (``gt_id``).
    """

    name: ClassVar[str] = "relpoint"
    finishing: ClassVar[str] = "final adjustment"
    reports_unlocated: ClassVar[bool] = True

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
        self._dropouts = DropoutRegistration()
        self.index = GlobalIndex(max(config.global_match_bound, config.merge_bound, 1e-3))
        self.ungrouped = UngroupedList()
        self.tally = IdTally()
        self._poses = np.repeat(np.eye(4)[None], config.ring_size, axis=0)
        self._T_world_sensor = np.eye(4)
        self._path = np.zeros((256, 3))  # position of every iteration (world, m): loop corrections follow it
        self._motion_measured = False
        self._iteration = 0
        self._previous_stamp_ns: int | None = None  # the last iteration's stamp (ns)
        self._unlocated_tail = 0  # iterations since the last located one (empty or not located)
        self._unobserved: list[int] = []  # iterations without a point: their pose is interpolated at the end
        self._regroup_queue: deque[int] = deque()
        self._first_groups: deque[int] = deque()
        self._over_grouped: set[int] = set()
        # Iterations whose view held nothing mapped after the map had begun: a new root was anchored there.
        self._map_restarts: list[int] = []
        self._newly_mapped: list[IntArray] = []
        self._next_creation_try: dict[int, int] = {}
        self.adjustment_report: dict[str, Any] | None = None
        # Per iteration: uids and sensor-frame observations of mapped points, to locate it again
        # after the final adjustment; every observation of the bundle adjustment's keyframes (every
        # ``_keyframe_stride``-th iteration); and where merged points' uids went.
        self._support: list[tuple[IntArray, npt.NDArray[np.float32]] | None] = []
        self._observations: dict[int, tuple[IntArray, npt.NDArray[np.float32]]] = {}
        self._keyframe_stride = 1
        self._kept_observations = 0
        self._merged_uid: dict[int, int] = {}
        self.counts: dict[str, int] = dict.fromkeys(
            (
                "degenerate_iterations", "empty_iterations", "unobserved_interpolated", "nonfinite_points", "new_points", "local_matches",
                "global_matches", "first_groups", "root_groups", "regroups", "failed_groupings",
                "first_groups_retired", "groups_pruned", "merges", "dynamic_flagged", "dynamic_comparisons",
                "dropped_points", "reabsorbed", "far_matches", "loop_closures", "dynamic_by_grouping",
                "dynamic_by_binning", "dynamic_by_references", "dynamic_by_spread", "dynamic_by_world",
                "dynamic_by_adjustment", "dynamic_by_bundle", "dynamic_released",
            ),
            0,
        )  # fmt: skip

    # -- Estimator interface ---------------------------------------------------------------------

    @classmethod
    def compile(cls) -> None:
        """Compile or load the compiled inner loops (:mod:`._kernels`)."""
        _kernels.prepare()

    def start_moving(self, twist: FloatArray, twist_sigma: FloatArray) -> bool:
        """The local matching's motion prediction starts from ``twist`` (``twist_sigma`` is not used)."""
        if self._iteration:
            return False
        self.motion.start_from(twist)
        return True

    def step(self, observation: PointObservation) -> Pose:
        """Process one iteration's untransformed points (sensor frame); return ``T_world_sensor``."""
        k = self._iteration
        self._iteration += 1
        # The motion predicts one iteration (older points: one per iteration of age): rescaled to this
        # iteration's interval, whatever the previous one's was.
        if self._previous_stamp_ns is not None:
            self.motion.to_interval((observation.stamp_ns - self._previous_stamp_ns) * 1e-9)
        self._previous_stamp_ns = observation.stamp_ns
        points = np.asarray(observation.points, dtype=np.float64)
        finite = np.isfinite(points)
        if finite.all():  # the usual case: every point kept (a copy, as the masking below gives)
            points = points.copy()
            gt_ids = None if observation.ids is None else np.array(observation.ids)
        else:
            finite = finite.all(axis=1)
            self.counts["nonfinite_points"] += int(np.count_nonzero(~finite))
            points = points[finite]
            gt_ids = None if observation.ids is None else np.asarray(observation.ids)[finite]
        if len(points) == 0:
            self.counts["empty_iterations"] += 1
            self.counts["degenerate_iterations"] += 1
            self._unobserved.append(k)
            self._unlocated_tail += 1
            self.charting.chart(k, np.zeros(0, np.int64))
            self._support.append(None)
            return self._finish(k, observation.stamp_ns, self._T_world_sensor)

        self._motion_measured = False
        self._measure_dropout(observation.stamp_ns, points)
        self._dropouts.remember(observation.stamp_ns, points)
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
            self._unlocated_tail += 1
            T_world_sensor = self._coast()
        else:
            self._unlocated_tail = 0
        self.store.world_sum[ids] += apply_transform(T_world_sensor, points)
        self._housekeeping(k)
        self._refresh_index()
        return self._finish(k, observation.stamp_ns, T_world_sensor)

    def _measure_dropout(self, stamp_ns: int, points: FloatArray) -> None:
        """After dropped observations, the local matching predicts the motion the points register into
        since the last observation (:mod:`relpoint.estimators._dropouts`) rather than the last motion
        stretched over the interval (at most ``MAX_INTERVAL_RATIO`` times)."""
        if not self._dropouts.pending(stamp_ns):
            return
        T_prev_curr = rigid_inverse(self.motion.T_curr_prev)
        sigma = self.config.observation_sigma if self.config.observation_sigma is not None else SIMULATOR_SIGMA
        motion = self._dropouts.motion_since_last(stamp_ns, points, (T_prev_curr[:3, :3], T_prev_curr[:3, 3]), sigma)
        if motion is not None:
            T_prev_curr = np.eye(4)
            T_prev_curr[:3, :3], T_prev_curr[:3, 3] = motion[0], motion[1]
            self.motion.measured_over(rigid_inverse(T_prev_curr))

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
        return LandmarkMap(
            positions, n_obs, dynamic, gt_id, np.clip(purity, 0.0, 1.0) if known else None, store.first_iter[keep]
        )

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
            "map_restarts": len(self._map_restarts),
            "dropouts_registered": self._dropouts.registered,
            "dropouts_unregistered": self._dropouts.unregistered,
            "dropouts_predicted": self._dropouts.predicted,
            **({"final_adjustment": self.adjustment_report} if self.adjustment_report else {}),
        }

    def run_warnings(self) -> list[str]:
        """What makes the run doubtful: many iterations not located, or many at the end, or the map begun again.

        Not located (``degenerate_iterations``): fewer than three usable non-collinear mapped points
        in view, so the pose coasted on the predicted motion. Past ``DEGENERATE_WARNING_SHARE`` of the
        iterations the path is mostly that prediction (on a sparse log, frozen poses) and the map is
        placed by it. A map begun again: fewer than three mapped points not flagged as moving were in view
        where new points were grouped (after a gap in the observations, a jump, a view of new ground, or
        points there taken for movers), so a new part was anchored to the pose predicted then, and little
        ties it to the map before it. The path and map after it may be off by the move."""
        warnings = []
        degenerate = self.counts["degenerate_iterations"]
        if self._iteration and degenerate > DEGENERATE_WARNING_SHARE * self._iteration:
            warnings.append(
                f"relpoint: {degenerate} of {self._iteration} iterations could not be located (fewer than three "
                "usable non-collinear mapped points in view), so their poses only carry the predicted motion on; "
                "more points per frame would help, or, with odometry, ekf or fastslam"
            )
        elif self._unlocated_tail >= UNLOCATED_TAIL_WARNING:
            warnings.append(
                f"relpoint: the last {self._unlocated_tail} iterations could not be located (no point, or fewer "
                "than three usable mapped points, in view: the sensor left what it had mapped?), so their poses "
                "hold or carry on the last located motion and may be far off; with odometry, ekf or fastslam "
                "carry the pose on"
            )
        if not self._map_restarts:
            return warnings
        where = ", ".join(str(k) for k in self._map_restarts[:5]) + (", ..." if len(self._map_restarts) > 5 else "")
        warnings.append(
            f"relpoint: the map was begun again {len(self._map_restarts)} time(s) (iterations {where}): fewer than "
            "three mapped points not flagged as moving were in view where new points were grouped (after a gap or "
            "a jump, a view of new ground, or when the points there were taken for movers), so each new part is "
            "placed only by the pose predicted then; the path and map after it may be off by that move. With "
            "odometry, ekf or fastslam carry the pose across such a break"
        )
        return warnings

    # -- the phases of one iteration -------------------------------------------------------------

    def _housekeeping(self, k: int) -> None:
        """Bounded upkeep: retire redundant first groups and thin points in too many groups."""
        store, groups = self.store, self.groups
        for _ in range(min(4, len(self._first_groups))):
            gid = self._first_groups.popleft()
            group = groups.groups.get(gid)
            if group is None:
                continue
            if not group.is_open and least_at(store.n_later_groups, group.members) >= 1:
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
                if least_at(store.n_groups, group.members) >= 2:
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


SPEC = EstimatorSpec(
    name="relpoint",
    description="Relative Point: relative maps of co-observed point groups joined by least squares (Kraut)",
    config_class=RelativePointConfig,
    estimator_class=RelativePointEstimator,
    input_kind=POINTS,
    noise_adaptive=True,
)
