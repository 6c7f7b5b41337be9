"""EKF-SLAM over 3D point landmarks: the paper's 6D EKF baseline.

Implements the filter of Zhang, Milios and Gu, *General Concept of 3D SLAM*: the robot process model
(section 2.1, eq. 3-7) driven by odometry, or a constant-position / constant-velocity model without
it; static point landmarks (section 2.2, eq. 8-10); the measurement of a landmark's position in the
sensor frame (section 2.3, eq. 11-13); innovation gating with a chi-square threshold (section 3.2,
eq. 14-16) feeding nearest-neighbour or JCBB association; and the joint EKF over pose and map
(section 4, eq. 17-18). It stands in for the MRPT 6D EKF that Kraut's *A Relative Point Algorithm*
(section IV) compares against. Position fixes (``/fix``, sections 5-6) are fused in the filter once
they pin its local frame (``fix_alignment="rigid"``, ``relpoint.estimators._fix_frame``): eq. 31-32
is the Kalman update on the position.

State and parameterisation
    The nominal sensor pose is a position ``p`` (world, metres) and a rotation ``R = R_world_sensor``;
    the covariance is over an error state ``(dp, dtheta)`` with ``R_true = R Exp(dtheta)`` (dtheta in
    the sensor frame), so orientation never leaves SO(3) and needs no normalisation. With
    ``motion="constant_velocity"`` the body-frame twist ``(v, w)`` follows (12 vehicle states).
    Landmarks ``m_j`` (world, metres) follow, three states each.

Cost
    Association computes every landmark's 3x3 innovation covariance from its 9x9 block (O(n)). The
    update of m paired points is one batched measurement: ``H P`` is built from the pose's and the
    observed landmarks' rows of ``P`` (``H`` is non-zero only in their columns, and its landmark
    blocks are all ``R^T``) in O(N m), and the covariance falls by one symmetric rank-3m product
    ``P -= W^T W`` with ``W = L^-1 H P`` (``S = L L^T``): a BLAS ``syrk``, O(N^2 m), half the
    products of the general form, and the algorithm's own cost: about 80 % of the time at a
    thousand landmarks and 100 points per iteration (``benchmarks/ekf_speed.py --profile``).
    ``P`` lives in one preallocated block that grows by half when full; the filter works on a view of its
    used corner, so a new landmark costs O(N), not a copy of ``P``.
"""

from __future__ import annotations

import logging
from collections import Counter
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt
from scipy import linalg
from scipy.linalg import blas

from relpoint.errors import EstimatorError
from relpoint.estimators._association import (
    COLLAPSE_FRACTION,
    jcbb_search,
    mahalanobis_squared,
    nearest_neighbour,
    widening_scales,
)
from relpoint.estimators._dropouts import DropoutRegistration, rotation_errors
from relpoint.estimators._fix_frame import FixFrame, FrameFit, frame_summary, placed_in_one_frame
from relpoint.estimators._fix_gate import FixGate
from relpoint.estimators._landmark_motion import (
    EKF_MIN_PAIRED,
    HAND_OVER_MEMORY,
    REACH_SIGMAS,
    MotionTest,
    hand_over,
    shared_motion_removed,
)
from relpoint.estimators._movers import MoverTracks, moved_landmarks
from relpoint.estimators._noise import SIMULATOR_SIGMA
from relpoint.estimators._odometry_hold import OdometryHold
from relpoint.estimators._recent_path import RecentPath
from relpoint.estimators._time_gaps import GapBridge
from relpoint.estimators._trajectory_smoothing import PairHistory, smoothed_trajectory, summed_fix_jumps
from relpoint.estimators._vanished import VanishedLandmarks
from relpoint.estimators.base import FIX, ODOMETRY, POINTS, Estimator
from relpoint.estimators.ekf_config import CONSENSUS_MIN_PAIRS, EkfConfig
from relpoint.estimators.spec import EstimatorSpec
from relpoint.geometry import FloatArray, apply_transform, rigid_consensus, skew, so3_exp, twist_step
from relpoint.statistics import chi2_gate
from relpoint.types import LandmarkMap, OdometryMeasurement, PointObservation, Pose, PositionFix, Trajectory

logger = logging.getLogger(__name__)

#: Rows and columns the covariance block holds before it first grows (by half when full).
INITIAL_CAPACITY = 256

#: A map of this many landmarks is warned of once (covariance about 290 MB; each update O(n^2) in it).
LARGE_MAP_LANDMARKS = 2000

#: A landmark seen within this many iterations that a point near it does not match may have moved
#: (a moving point can fall between the two gates for an iteration or two before it starts one).
MOVER_RECENT = 3
#: Landmarks are only taken for movers while at least this many landmarks match, and more of the
#: recently seen ones match than not (otherwise the filter's pose is off, and every landmark seems to move).
MOVER_MIN_MATCHED = 8


class EkfSlam(Estimator[PointObservation]):
    """Joint EKF over the sensor pose (error state) and every 3D point landmark.

    Each :meth:`step` predicts to the observation's stamp, associates the points with the map,
    updates the joint state with the paired points, and starts a landmark from every point outside
    every landmark's (wider) new-landmark gate; unpaired points in between are discarded. The first
    pose is the identity with zero covariance (it anchors ``world``) unless a position fix arrives
    before the first observation; it then places the start, with ``initial_orientation_sigma`` as
    the prior on the unknown initial orientation.
    """

    name: ClassVar[str] = "ekf"
    finishing: ClassVar[str] = "smoothing trajectory"

    def __init__(self, config: EkfConfig | None = None, rng: np.random.Generator | None = None) -> None:
        del rng  # the EKF draws no random numbers
        self.config = config or EkfConfig()
        self._gaps = GapBridge()
        self._dropouts = DropoutRegistration()
        self._last_pose: tuple[FloatArray, FloatArray, FloatArray] | None = None  # p, R, their covariance (6, 6)
        cv = self.config.motion == "constant_velocity"
        self._nv = 12 if cv else 6
        sigma = self.config.observation_sigma if self.config.observation_sigma is not None else SIMULATOR_SIGMA
        self._R_obs = np.eye(3) * sigma**2
        self._gate = chi2_gate(self.config.gate_probability, 3)
        self._new_gate = chi2_gate(self.config.new_landmark_probability, 3)
        self._position = np.zeros(3)
        self._rotation = np.eye(3)
        self._twist = np.zeros(6)
        self._landmarks = np.zeros((0, 3))
        # The joint covariance: the used corner (self._size x self._size) of one preallocated block.
        self._P_block = np.zeros((INITIAL_CAPACITY, INITIAL_CAPACITY))
        self._size = self._nv
        if cv:
            self._P[6:9, 6:9] = np.eye(3) * self.config.initial_speed_sigma**2
            self._P[9:12, 9:12] = np.eye(3) * self.config.initial_turn_rate_sigma**2
        self._stamp_ns: int | None = None
        # The process noise (nv, nv) the predictions since the last observation added, carried to its stamp.
        self._step_noise = np.zeros((self._nv, self._nv))
        self._seen_last = 0  # landmarks the last observation with points paired or started
        # The positions of the latest iterations, to carry a fix stamped before the state's time to it.
        self._recent = RecentPath()
        self._hold = OdometryHold()
        self._observations: list[int] = []
        self._id_votes: list[Counter[int]] = []
        self._known: dict[int, int] = {}
        self._stats = Counter[str]()
        self._stats["association_widened"] = 0  # iterations re-associated under wider process noise (run.json)
        self._stats["association_collapsed"] = 0  # ... and those whose association collapsed all the same
        if self.config.rigid_consensus:
            self._stats["consensus_rejected"] = 0  # pairs the rigid consensus left out (run.json)
        if self.config.association == "jcbb":
            self._stats["jcbb_gave_up"] = 0  # iterations whose search ran out of budget (run.json)
        # Fix frame (``rigid``): None once the state is in the fixes' frame (or with ``none``).
        self._frame: FixFrame | None = None
        if self.config.fix_alignment == "rigid":
            self._frame = FixFrame(min_spread=self.config.fix_min_spread)
        self._frame_fit: FrameFit | None = None
        self._fix_gate = FixGate(self.config.fix_gate_probability, self.config.fix_gate_patience)
        radius = self.config.mover_radius_sigmas * sigma
        self._movers = MoverTracks(radius) if radius > 0 else None
        self._last_seen = np.zeros(0, dtype=np.int64)  # iteration each landmark was last observed
        self._first_seen = np.zeros(0, dtype=np.int64)  # iteration each landmark was started
        self._mover_test = (
            MotionTest(self.config.mover_gate_probability, REACH_SIGMAS * sigma, EKF_MIN_PAIRED)
            if self.config.follow_movers
            else None
        )
        self._drift = np.zeros((0, 3))  # smoothed innovation of each landmark (world, m)
        self._uid = np.zeros(0, dtype=np.int64)  # a stable id for each landmark (removals keep the others')
        self._next_uid = 0
        self._pairs = PairHistory() if self.config.smooth_trajectory else None
        self._smoothing: dict[str, Any] | None = None
        self._fix_jumps: list[tuple[int, FloatArray]] = []  # (iteration, position shift (m)) per fused fix
        # (stamp ns, local pose (4, 4)) of each iteration before the fixes pin the frame: placed again by
        # one transform at the end (placed_in_one_frame)
        self._local_poses: list[tuple[int, FloatArray]] = []
        self._moving = np.zeros(0, dtype=bool)
        self._position_at_fix: FloatArray | None = None
        self._vanished = (
            VanishedLandmarks(self.config.vanished_probability, REACH_SIGMAS * sigma)
            if self.config.drop_vanished
            else None
        )
        if self._vanished is not None:
            self._stats["vanished"] = 0  # landmarks dropped as vanished (run.json)

    # ------------------------------------------------------------------------------------ interface

    def start_moving(self, twist: FloatArray, twist_sigma: FloatArray) -> bool:
        if self._nv != 12 or self._stamp_ns is not None:
            return False
        self._twist = np.array(twist, dtype=np.float64)
        self._P[6:12, 6:12] = np.diag(np.square(twist_sigma))
        return True

    def step(self, observation: PointObservation) -> Pose:
        """Predict to the observation's stamp, associate, update, add new landmarks; return the pose."""
        if self._stamp_ns is None:
            self._stamp_ns = observation.stamp_ns
        self._predict_to(observation.stamp_ns)
        self._hold.observed(self._stamp_ns)
        points = np.asarray(observation.points)
        pairs: tuple[FloatArray, npt.NDArray[np.int64]] | None = None
        if len(points):
            self._measure_dropout(observation.stamp_ns, points)
            if self._mover_test is not None:
                self._widen(np.flatnonzero(self._moving))
            assignment, may_start = self._associate_or_widen(observation)
            to_moving = np.zeros(len(points), dtype=bool)
            to_moving[assignment >= 0] = self._moving[assignment[assignment >= 0]]
            if self._mover_test is not None:
                self._classify_motion(points, assignment)
            if self.config.rigid_consensus:  # over the static landmarks' pairs: a moving one says nothing of the pose
                kept = self._keep_consensus(points, np.where(to_moving, -1, assignment))
                kept = np.where(to_moving, assignment, kept)
                if self._movers is not None:  # a pair the consensus leaves out may be a landmark that moved
                    may_start |= (assignment >= 0) & (kept < 0)
                assignment = kept
            if self._mover_test is not None and self.config.hand_over_movers:
                self._hand_over(points, assignment, may_start)
            paired = np.flatnonzero(assignment >= 0)
            if self._pairs is not None:  # the pairs of static landmarks: what places the pose
                steady = paired[~self._moving[assignment[paired]]]
                pairs = (points[steady], self._uid[assignment[steady]])  # kept once the step succeeds
            if len(paired):
                self._update_landmarks(points[paired], assignment[paired])
            fresh = np.flatnonzero(may_start)
            moved_points, moved = np.zeros(0, np.int64), np.zeros(0, np.int64)
            if len(fresh) and self._movers is not None:
                fresh, moved_points, moved = self._follow_movers(points, fresh, assignment, observation.ids)
            if len(fresh):
                self._add_landmarks(points[fresh])
            self._record(observation.ids, paired, assignment[paired], fresh)
            if len(moved):
                self._start_tracks(points[moved_points], moved, observation.ids, moved_points)
            if self._vanished is not None:
                self._drop_vanished(points, len(fresh))
            self._seen_last = len(paired) + len(fresh)
            self._step_noise[:] = 0.0
            self._stats["paired"] += len(paired)
            self._stats["started"] += len(fresh)
            self._stats["discarded"] += len(points) - len(paired) - len(fresh)
        if pairs is not None and self._pairs is not None:
            self._pairs.add(self._stats["iterations"], *pairs)
        self._stats["iterations"] += 1
        if self._frame is not None:
            fit = self._frame.update(observation.stamp_ns, self._position, self._P[:3, :3])
            if fit is not None:
                self._pin_frame(fit)
            else:
                self._local_poses.append((observation.stamp_ns, self._local_pose()))
        self._recent.add(observation.stamp_ns, self._position)
        self._dropouts.remember(observation.stamp_ns, points)
        if len(points) >= 3:
            self._last_pose = (self._position.copy(), self._rotation.copy(), self._P[:6, :6].copy())
        return self.pose()

    def _measure_dropout(self, stamp_ns: int, points: FloatArray) -> None:
        """After dropped observations, fuse the motion the points register into since the last one
        (:mod:`relpoint.estimators._dropouts`) as a measurement of the pose: the last pose composed with
        it, its covariance the last pose's plus the registration's."""
        if self._last_pose is None or not self._dropouts.pending(stamp_ns):
            return
        p0, R0, P0 = self._last_pose
        predicted = (R0.T @ self._rotation, R0.T @ (self._position - p0))
        motion = self._dropouts.motion_since_last(stamp_ns, points, predicted, float(np.sqrt(self._R_obs[0, 0])))
        if motion is None:
            return
        R, t, C = motion
        innovation = np.r_[p0 + R0 @ t - self._position, rotation_errors(self._rotation, R0 @ R)]
        C_world = C.copy()
        C_world[:3, :3] = R0 @ C[:3, :3] @ R0.T
        self._kalman_update(np.arange(6), np.eye(6), innovation, P0 + C_world)

    def add_odometry(self, odometry: OdometryMeasurement) -> None:
        """Hold a body-frame twist from its stamp until the next one (process model eq. 3-7); the
        interval up to its stamp is predicted with the twist held before it."""
        if self._stamp_ns is not None:
            self._predict_to(odometry.stamp_ns)
        self._hold.hold(odometry)

    def add_fix(self, fix: PositionFix) -> None:
        """Fuse an absolute position as a direct, covariance-weighted measurement of ``p`` (eq. 31-32).

        With ``fix_alignment="rigid"`` the fixes before the frame is pinned only collect pairs for
        the fit (see :meth:`step`); the later ones are fused if they pass the fix gate
        (``fix_gate_probability``, :class:`~relpoint.estimators._fix_gate.FixGate`).
        """
        if self._frame is not None:
            self._frame.add_fix(fix)
            return
        if self._stamp_ns is None:
            # Before the first observation a fix places the start instead of the identity.
            self._stamp_ns = fix.stamp_ns
            self._position = np.array(fix.position, dtype=np.float64)
            self._P[:3, :3] = np.asarray(fix.covariance)
            self._P[3:6, 3:6] = np.eye(3) * self.config.initial_orientation_sigma**2
            return
        self._predict_to(fix.stamp_ns)
        # A fix stamped before the state's time (a receiver's latency) is carried forward along the
        # filter's own motion since its stamp (relpoint.estimators._recent_path).
        moved = self._recent.displacement(fix.stamp_ns, self._stamp_ns, self._position)
        if moved is None:  # counted by the path (fixes_too_old)
            return
        if self._frame_fit is not None:
            self._add_drift()
        innovation = np.asarray(fix.position) + moved - self._position
        R_fix = np.asarray(fix.covariance, dtype=np.float64)
        d2 = float(innovation @ np.linalg.solve(self._P[:3, :3] + R_fix, innovation))
        inflation = self._fix_gate.inflation(d2)
        if inflation is None:
            return  # held back: it contradicts the filter's position (see relpoint.estimators._fix_gate)
        before = self._position.copy()
        # Past the gate's patience the fix is fused as it is: the filter, not the fix, has drifted,
        # and its small covariance already limits the step. Inflating the fix as well left the
        # filter lost on figure8-gaps seed 3 (84.6 m, 3,940 landmarks; 4.3 m fused as given).
        self._kalman_update(np.arange(3), np.eye(3), innovation, R_fix)
        self._recent.shift(self._position - before)
        if self._pairs is not None:  # the jump the fix made, from the next pose on (trajectory smoothing)
            self._fix_jumps.append((self._stats["iterations"], self._position - before))
        self._stats["fixes"] += 1

    def landmark_map(self) -> LandmarkMap:
        """The landmarks seen at least ``min_observations`` times, then the moving points followed outside
        the map (flagged dynamic, last position)."""
        n = len(self._landmarks)
        votes = self._id_votes + (self._movers.votes if self._movers is not None else [])
        observations = self._observations + (self._movers.observations if self._movers is not None else [])
        gt_id = np.array([v.most_common(1)[0][0] if v else -1 for v in votes], dtype=np.int64)
        positions = self._landmarks.copy()
        if self._movers is not None:
            positions = np.vstack([positions, self._movers.positions])
        if self._frame is not None:
            T = self._frame.provisional
            positions = apply_transform(T, positions)
        dynamic = np.concatenate([self._moving, np.ones(len(positions) - n, dtype=bool)])
        first = np.concatenate([self._first_seen, np.full(len(positions) - n, -1, dtype=np.int64)])
        observations = np.array(observations, dtype=np.int64)
        shown = np.ones(len(positions), dtype=bool)
        shown[:n] = observations[:n] >= self.config.min_observations
        return LandmarkMap(
            positions[shown], observations[shown], dynamic[shown], gt_id[shown], first_iteration=first[shown]
        )

    @property
    def map_size(self) -> int:
        """Landmarks in :meth:`landmark_map` (seen ``min_observations`` times, and followed movers)."""
        mapped = len(self._landmarks) - self._not_mapped()
        return mapped + (len(self._movers) if self._movers is not None else 0)

    def _not_mapped(self) -> int:
        """Landmarks in the state seen fewer than ``min_observations`` times (left out of the map)."""
        if self.config.min_observations <= 1:
            return 0
        return int(np.count_nonzero(np.array(self._observations, dtype=np.int64) < self.config.min_observations))

    def summary(self) -> dict[str, Any]:
        return {
            "landmarks": self.map_size,
            "landmarks_not_mapped": self._not_mapped(),
            "moving_landmarks": int(self._moving.sum()),
            "association": self.config.association,
            "motion": self.config.motion,
            "linear_acceleration_noise": self.config.acceleration_noise,
            "angular_acceleration_noise": self.config.angular_noise,
            "state_size": int(self._P.shape[0]),
            "time_gaps_bridged": self._gaps.bridged,
            "dropouts_registered": self._dropouts.registered,
            "dropouts_unregistered": self._dropouts.unregistered,
            "dropouts_predicted": self._dropouts.predicted,
            "odometry_stale": self._hold.stale,
            **{k: int(v) for k, v in sorted(self._stats.items())},
            **frame_summary(self.config.fix_alignment == "rigid", self._frame_fit),
            **self._fix_gate.summary(),
            **self._recent.summary(),
            **({"smoothing": self._smoothing} if self._smoothing is not None else {}),
        }

    def finish(self, trajectory: Trajectory) -> Trajectory:
        """The trajectory in one frame, smoothed on the final map (``smooth_trajectory``; see
        :mod:`relpoint.estimators._trajectory_smoothing`).

        ``trajectory`` holds the poses :meth:`step` returned, one per iteration (``world``). Those
        returned before the fixes pinned the frame were placed by the provisional transform of their
        iteration: they are placed again by the pinning's transform, or by the last provisional one
        when the fixes never pinned it (:func:`~relpoint.estimators._fix_frame.placed_in_one_frame`).
        A run that skipped iterations, or whose pairs place no iteration on the final map, is not
        smoothed, and ``smoothing`` in :meth:`summary` says why.
        """
        trajectory = placed_in_one_frame(trajectory, self._local_poses, self._frame_fit, self._frame)
        if self._pairs is None:
            return trajectory
        static = ~self._moving
        positions = (
            self._landmarks if self._frame is None else apply_transform(self._frame.provisional, self._landmarks)
        )
        iterations = self._stats["iterations"]
        smoothed, self._smoothing = smoothed_trajectory(
            trajectory, iterations, self._pairs, self._uid[static], positions[static],
            min_noise=float(np.sqrt(self._R_obs[0, 0])),
            fix_jumps=summed_fix_jumps(self._fix_jumps, iterations) if self._fix_jumps else None,
        )  # fmt: skip
        return smoothed

    # ------------------------------------------------------------------------------------- accessors

    def pose(self) -> Pose:
        """The current sensor pose ``T_world_sensor`` at the last processed stamp.

        Before the fixes pin the frame (``rigid``), the local pose mapped by the provisional transform.
        """
        T = self._local_pose()
        if self._frame is not None:
            T = self._frame.provisional @ T
        return Pose.from_matrix(self._stamp_ns or 0, T)

    def _local_pose(self) -> FloatArray:
        """``T`` (4, 4) of the filter's pose in its own frame (``world`` once the frame is pinned)."""
        T = np.eye(4)
        T[:3, :3] = self._rotation
        T[:3, 3] = self._position
        return T

    @property
    def frame_fit(self) -> FrameFit | None:
        """The fit that moved the state into the fixes' frame (``rigid``), or None before (or without) it."""
        return self._frame_fit

    def _add_drift(self) -> None:
        """Let the pose and the recently seen landmarks move together by ``fix_drift`` per metre since the last fix."""
        previous, self._position_at_fix = self._position_at_fix, self._position.copy()
        if previous is None or self.config.fix_drift <= 0.0:
            return
        q = (self.config.fix_drift * float(np.linalg.norm(self._position - previous))) ** 2
        recent = np.flatnonzero(self._last_seen >= self._stats["iterations"] - self.config.fix_window)
        rows = np.concatenate([np.arange(3), self._landmark_columns(recent)])
        J = np.tile(np.eye(3), (len(rows) // 3, 1))
        self._P[np.ix_(rows, rows)] += q * (J @ J.T)

    def _pin_frame(self, fit: FrameFit) -> None:
        """Move the state into the fixes' frame by ``fit`` and add the fit's uncertainty to ``P``.

        The pose and the landmarks map by ``T_world_local``; their covariance blocks turn with its
        rotation (the orientation and twist errors are in the sensor frame and do not). The fit's
        error ``(dt, dphi)`` moves every position by ``dt - [y - c]x dphi`` and the orientation by
        ``R^T dphi``: ``P += J Sigma_fit J^T``.
        """
        nv = self._nv
        R_T, t = fit.T_world_local[:3, :3], fit.T_world_local[:3, 3]
        first = 0
        self._position = R_T @ self._position + t
        self._recent.transform(fit.T_world_local)
        self._rotation = R_T @ self._rotation
        self._landmarks[first:] = self._landmarks[first:] @ R_T.T + t
        P = self._P
        N = P.shape[0]
        spatial = np.concatenate([np.arange(3), np.arange(nv + 3 * first, N)]).reshape(-1, 3)
        rows = P[spatial.ravel()].reshape(-1, 3, N)
        P[spatial.ravel()] = np.einsum("ij,gjn->gin", R_T, rows).reshape(-1, N)
        cols = P[:, spatial.ravel()].reshape(N, -1, 3)
        P[:, spatial.ravel()] = np.einsum("ngj,ij->ngi", cols, R_T).reshape(N, -1)
        J = np.zeros((N, 6))
        J[spatial.ravel()] = fit.perturbation_jacobian(np.vstack([self._position, self._landmarks[first:]])).reshape(
            -1, 6
        )
        J[3:6, 3:] = self._rotation.T
        JS = J @ fit.covariance
        P += JS @ J.T
        P += P.T
        P *= 0.5
        self._frame = None
        self._frame_fit = fit
        self._position_at_fix = self._position.copy()
        self._stats["frame_pinned_at"] = self._stats["iterations"]

    @property
    def covariance(self) -> FloatArray:
        """A copy of the joint covariance (N, N): pose error (6), twist (6, constant velocity), landmarks (3 each)."""
        return self._P.copy()

    @property
    def _P(self) -> FloatArray:
        """The joint covariance (N, N): a view of the used corner of the preallocated block."""
        return self._P_block[: self._size, : self._size]

    def _resize(self, size: int) -> FloatArray:
        """Let the covariance hold ``size`` states, growing the block by half when it is full; return the new view.

        The entries of the first ``min(size, N)`` states keep their values; those of new states are
        unset (the caller fills them).
        """
        capacity = self._P_block.shape[0]
        if size > capacity:
            # 1.5 times, not twice: at 3,000 landmarks a doubled block took 2 GB of which half stood empty.
            block = np.zeros((max(size, capacity + capacity // 2),) * 2)
            block[: self._size, : self._size] = self._P
            self._P_block = block
        if self._size < self._nv + 3 * LARGE_MAP_LANDMARKS <= size:
            landmarks = (size - self._nv) // 3
            logger.warning(
                "the EKF's map reached %d landmarks at iteration %d: its covariance takes %.0f MB and every "
                "iteration's update grows with the square of the map; on a long log with many landmarks "
                "Relative Point (--estimator relpoint) or FastSLAM keep far larger maps",
                landmarks, self._stats["iterations"], self._P_block.nbytes / 1e6,
            )  # fmt: skip
        self._size = size
        return self._P

    # ------------------------------------------------------------------------------------ prediction

    def _predict_to(self, stamp_ns: int) -> None:
        """Predict to ``stamp_ns``: with the held odometry until it goes stale, then with the motion model."""
        assert self._stamp_ns is not None
        for end_ns in self._hold.prediction_ends(self._stamp_ns, stamp_ns):
            self._predict_span(end_ns)

    def _predict_span(self, stamp_ns: int) -> None:
        assert self._stamp_ns is not None
        dt = (stamp_ns - self._stamp_ns) * 1e-9
        if dt > 0.0:
            dt = self._gaps.interval(dt)
        if dt <= 0.0:
            if dt < 0.0:
                logger.debug(
                    "record at %d ns is older than the state (%d ns); not predicting", stamp_ns, self._stamp_ns
                )
            return
        F, Q = self._motion(dt)
        self._step_noise = F @ self._step_noise @ F.T + Q
        nv = self._nv
        P = self._P
        P_vv = F @ P[:nv, :nv] @ F.T + Q
        P[:nv, :nv] = 0.5 * (P_vv + P_vv.T)
        P[:nv, nv:] = F @ P[:nv, nv:]
        P[nv:, :nv] = P[:nv, nv:].T
        self._stamp_ns = stamp_ns

    def _motion(self, dt: float) -> tuple[FloatArray, FloatArray]:
        """Propagate the nominal vehicle state by ``dt`` s from the state's stamp; return its Jacobian F
        and process noise Q."""
        cfg = self.config
        nv = self._nv
        F = np.eye(nv)
        Q = np.zeros((nv, nv))
        acceleration = np.repeat([cfg.acceleration_noise, cfg.angular_noise], 3)
        if self._hold.held is not None:
            assert self._stamp_ns is not None
            # Eq. 7: X(k+1) = F(X(k), U(k) + noise); the held odometry twist is the input U, its noise
            # that of holding it over this interval (relpoint.estimators._odometry_hold).
            u = self._hold.twist()
            Q_u, Q_span = self._hold.noise(self._stamp_ns, self._stamp_ns + round(dt * 1e9), acceleration)
            p, R, F_pose, G = twist_step(self._position, self._rotation, u[:3], u[3:], dt)
            F[:6, :6] = F_pose
            Q[:6, :6] = G @ Q_span @ G.T
            if nv == 12:
                # The new twist is the input itself: it forgets the old twist and shares the input noise.
                F[6:, 6:] = 0.0
                G = np.vstack([G, np.eye(6)])
                self._twist = u.copy()
            Q[: len(G), : len(G)] += G @ Q_u @ G.T
        elif nv == 12:
            p, R, F_pose, G = twist_step(self._position, self._rotation, self._twist[:3], self._twist[3:], dt)
            F[:6, :6] = F_pose
            F[:6, 6:] = G
            q = (acceleration * dt) ** 2
            # Acceleration acts over the interval: it moves the twist and, through it, the pose.
            G_full = np.vstack([G, np.eye(6)])
            Q = G_full @ np.diag(q) @ G_full.T
        else:
            p, R = self._position, self._rotation
            angle_sigma = 2.0 * cfg.quaternion_noise
            Q = np.diag(np.r_[np.full(3, cfg.position_noise**2), np.full(3, angle_sigma**2)])
        self._position, self._rotation = p, R
        return F, Q

    # ----------------------------------------------------------------------------------- measurement

    def _predict_measurements(self, landmarks: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Predicted sensor-frame positions (n, 3) of landmarks (eq. 11) and their pose Jacobians (n, 3, 6).

        ``z = R^T (m - p)``: ``dz/dp = -R^T``, ``dz/dtheta = [z]x``, ``dz/dm = R^T``.
        """
        z = (landmarks - self._position) @ self._rotation
        H_pose = np.empty((len(z), 3, 6))
        H_pose[:, :, :3] = -self._rotation.T
        H_pose[:, :, 3:] = skew(z)
        return z, H_pose

    def _landmark_columns(self, indices: np.ndarray) -> np.ndarray:
        return (self._nv + 3 * np.asarray(indices, dtype=np.int64)[:, None] + np.arange(3)).ravel()

    def _innovation_covariances(self, H_pose: FloatArray) -> FloatArray:
        """Innovation covariance S_j (n, 3, 3) of every landmark's measurement (eq. 16), O(n)."""
        n = len(H_pose)
        nv = self._nv
        P = self._P
        Rt = self._rotation.T
        P_pp = P[:6, :6]
        P_pm = P[:6, nv:].reshape(6, n, 3).transpose(1, 0, 2)  # (n, 6, 3)
        cols = self._landmark_columns(np.arange(n)).reshape(n, 3)
        P_mm = P[cols[:, :, None], cols[:, None, :]]  # (n, 3, 3)
        H_t = np.swapaxes(H_pose, 1, 2)
        HPH = (H_pose.reshape(3 * n, 6) @ P_pp).reshape(n, 3, 6) @ H_t
        cross = (H_pose @ P_pm) @ Rt.T
        S = HPH + cross + np.swapaxes(cross, 1, 2) + Rt @ P_mm @ Rt.T + self._R_obs
        return 0.5 * (S + np.swapaxes(S, 1, 2))

    def _associate(self, observation: PointObservation) -> tuple[np.ndarray, np.ndarray]:
        """Pair points with landmarks; return (assignment (k,), may-start-a-landmark mask (k,))."""
        points = np.asarray(observation.points)
        k = len(points)
        n = len(self._landmarks)
        if self.config.association == "known":
            if observation.ids is None:
                raise EstimatorError("association 'known' needs the log's point ids", "use --association nn or jcbb")
            ids = np.asarray(observation.ids)
            assignment = np.array([self._known.get(int(i), -1) for i in ids], dtype=np.int64)
            may_start = (assignment < 0) & (ids >= 0)
            # Two points claiming one id in a frame: keep only the first.
            _, first = np.unique(ids, return_index=True)
            duplicate = np.ones(k, dtype=bool)
            duplicate[first] = False
            assignment[duplicate] = -1
            may_start &= ~duplicate
            return assignment, may_start
        if n == 0:
            return np.full(k, -1, dtype=np.int64), np.ones(k, dtype=bool)
        z_hat, H_pose = self._predict_measurements(self._landmarks)
        S = self._innovation_covariances(H_pose)
        innovations = points[:, None, :] - z_hat[None, :, :]
        d2 = mahalanobis_squared(innovations, np.linalg.inv(S))
        # Static landmarks first: a moving one's gate is wide, and it takes only a point they leave.
        moving_d2, d2 = d2, np.where(self._moving[None, :], np.inf, d2)
        assignment, _ = nearest_neighbour(d2, self._gate)
        may_start = ~(d2 < self._new_gate).any(axis=1)
        if self.config.association == "jcbb":
            candidates = np.flatnonzero((d2 < self._gate).any(axis=0))
            if len(candidates):
                joint = self._joint_measurement_covariance(candidates, H_pose[candidates])
                local, gave_up = jcbb_search(
                    d2[:, candidates],
                    innovations[:, candidates],
                    joint,
                    self._R_obs,
                    self.config.gate_probability,
                    self.config.jcbb_max_nodes,
                    self.config.jcbb_max_seconds,
                )
                if gave_up:
                    self._jcbb_gave_up()
                assignment = np.where(local >= 0, candidates[np.maximum(local, 0)], -1)
        if self._moving.any():
            moving_d2 = np.where(self._moving[None, :] & (assignment < 0)[:, None], moving_d2, np.inf)
            followed, _ = nearest_neighbour(moving_d2, self._gate)
            assignment = np.where(followed >= 0, followed, assignment)
        return assignment, may_start & (assignment < 0)

    def _associate_or_widen(self, observation: PointObservation) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_associate`, again under wider process noise when the association collapses.

        The motion model holds the twist between observations; a turn that starts or stops at once
        (a turn-rate step of 1 rad/s against 0.5 rad/s^2 of acceleration noise) puts the true pose
        outside the predicted covariance, the points fall outside every gate and start duplicates
        of the landmarks they are, and the filter never learns the new twist. Collapsed: fewer than
        ``COLLAPSE_FRACTION`` of the landmarks the last observation saw pair, and more points would
        start landmarks than pair. The predictions since the last association are then taken again
        with 2, 4, ... up to ``collapse_noise_scale`` times the standard deviation of their process
        noise (the same Jacobians, so ``P``'s vehicle block gains ``(scale^2 - 1) Q``), and the
        first association that pairs ``COLLAPSE_FRACTION`` of them is kept, with its covariance;
        when none does, the prediction is restored, and the iteration is counted and warned about.
        Iterations that do not collapse are untouched: the noise is widened only when the data
        contradict the motion model as a whole, never pair by pair.
        """
        assignment, may_start = self._associate(observation)
        scale = self.config.collapse_noise_scale
        expected = min(self._seen_last, len(observation.points))
        if self.config.association == "known" or not self._collapsed(assignment, may_start, expected):
            return assignment, may_start
        nv = self._nv
        predicted = self._P[:nv, :nv].copy()
        for tried in widening_scales(scale):
            self._P[:nv, :nv] = predicted + (tried**2 - 1.0) * self._step_noise
            widened, widened_start = self._associate(observation)
            if np.count_nonzero(widened >= 0) >= COLLAPSE_FRACTION * expected:
                self._stats["association_widened"] += 1
                return widened, widened_start
        self._P[:nv, :nv] = predicted
        self._association_collapsed(assignment, may_start, expected)
        return assignment, may_start

    def _association_collapsed(self, assignment: np.ndarray, may_start: np.ndarray, expected: int) -> None:
        """Count an iteration whose association collapsed even under the widest process noise; warn the first time."""
        if not self._stats["association_collapsed"]:
            scale = self.config.collapse_noise_scale
            logger.warning(
                "association collapsed at iteration %d: %d of the %d landmarks seen just before paired and %d points "
                "start landmarks%s; the map may hold duplicates from here (association_collapsed in run.json counts "
                "such iterations): raise linear_acceleration_noise / angular_acceleration_noise, or give odometry",
                self._stats["iterations"], np.count_nonzero(assignment >= 0), expected, np.count_nonzero(may_start),
                f", also under {scale:g} x the process noise" if scale > 1.0 else " (collapse_noise_scale 1: no retry)",
            )  # fmt: skip
        self._stats["association_collapsed"] += 1

    @staticmethod
    def _collapsed(assignment: np.ndarray, may_start: np.ndarray, expected: int) -> bool:
        """Whether an association pairs too few of the ``expected`` landmarks and starts more than it pairs."""
        paired = np.count_nonzero(assignment >= 0)
        return (
            expected >= CONSENSUS_MIN_PAIRS
            and paired < COLLAPSE_FRACTION * expected
            and np.count_nonzero(may_start) > paired
        )

    def _widen(self, landmarks: np.ndarray) -> None:
        """Widen the covariance blocks of moving ``landmarks`` (:meth:`MotionTest.widen`): process noise
        of a landmark that moves, so that its pair updates it and not the pose."""
        assert self._mover_test is not None
        if len(landmarks):
            cols = self._landmark_columns(landmarks).reshape(-1, 3)
            self._P[cols[:, :, None], cols[:, None, :]] += self._mover_test.widening * np.eye(3)

    def _classify_motion(self, points: FloatArray, assignment: np.ndarray) -> None:
        """Smooth the innovation of every paired landmark and flag the moving ones
        (:mod:`relpoint.estimators._landmark_motion`)."""
        assert self._mover_test is not None
        rows = np.flatnonzero(assignment >= 0)
        if len(rows) == 0:
            return
        landmarks = assignment[rows]
        R = self._rotation
        offsets = points[rows] @ R.T
        innovations = self._position + offsets - self._landmarks[landmarks]
        innovations = shared_motion_removed(np.zeros(len(rows), dtype=np.int64), innovations, offsets, 1)
        cols = self._landmark_columns(landmarks).reshape(-1, 3)
        landmark_covariances = self._P[cols[:, :, None], cols[:, None, :]]
        point_covariance = np.broadcast_to(R @ self._R_obs @ R.T, landmark_covariances.shape)
        seen = np.array(self._observations, dtype=np.int64)[landmarks]
        self._drift[landmarks], self._moving[landmarks] = self._mover_test.classify(
            np.zeros(len(rows), dtype=np.int64), 1, innovations, point_covariance, landmark_covariances,
            self._drift[landmarks], self._moving[landmarks], seen,
        )  # fmt: skip

    def _hand_over(self, points: FloatArray, assignment: np.ndarray, may_start: np.ndarray) -> None:
        """Pair points that would start landmarks with the landmarks that moved out of their gates
        (:func:`relpoint.estimators._landmark_motion.hand_over`); those landmarks are moving, widened
        before the update. Updates ``assignment`` and ``may_start`` in place."""
        assert self._mover_test is not None
        unpaired = np.flatnonzero(may_start)
        iteration = self._stats["iterations"]
        last_seen = self._last_seen.copy()
        last_seen[assignment[assignment >= 0]] = iteration
        candidates = np.flatnonzero((last_seen >= iteration - HAND_OVER_MEMORY) & (last_seen < iteration))
        if len(unpaired) == 0 or len(candidates) == 0:
            return
        per_point = np.zeros(len(points), dtype=np.int64)
        per_point[unpaired] = len(candidates)
        near = (np.concatenate([[0], np.cumsum(per_point)]), np.tile(candidates, len(unpaired)))
        claims = np.where(assignment >= 0, assignment, np.where(may_start, -1, -2))[None]
        _, rows, landmarks = hand_over(
            claims, near, np.array([len(self._landmarks)]), last_seen[None], iteration, self._position[None],
            self._rotation[None], points, self._landmarks[None], self._mover_test.reach, self._mover_test.min_pairs,
        )  # fmt: skip
        if len(rows) == 0:
            return
        self._drift[landmarks] = self._position + points[rows] @ self._rotation.T - self._landmarks[landmarks]
        self._moving[landmarks] = True
        self._widen(landmarks)
        assignment[rows] = landmarks
        may_start[rows] = False
        self._stats["handed_over"] += len(rows)

    def _keep_consensus(self, points: FloatArray, assignment: np.ndarray) -> np.ndarray:
        """``assignment`` without the pairs the rigid motion most pairs share leaves unexplained.

        Each pair's tolerance is the validation gate's radius (``gate_probability``, 3 degrees of
        freedom) over the observation noise and the landmark's own uncertainty (RMS over its axes);
        the shared pose error is what the rigid motion absorbs. Draws are seeded by the iteration.
        """
        paired = np.flatnonzero(assignment >= 0)
        if len(paired) < CONSENSUS_MIN_PAIRS:
            return assignment
        landmarks = assignment[paired]
        cols = self._landmark_columns(landmarks).reshape(-1, 3)
        P = self._P
        landmark_variance = (P[cols[:, 0], cols[:, 0]] + P[cols[:, 1], cols[:, 1]] + P[cols[:, 2], cols[:, 2]]) / 3.0
        tolerance = np.sqrt(self._gate * (self._R_obs[0, 0] + landmark_variance))
        keep = rigid_consensus(points[paired], self._landmarks[landmarks], tolerance, seed=self._stats["iterations"])
        self._stats["consensus_rejected"] += int(np.count_nonzero(~keep))
        out = assignment.copy()
        out[paired[~keep]] = -1
        return out

    def _jcbb_gave_up(self) -> None:
        """Count an iteration whose JCBB search ran out of budget; warn the first time."""
        if not self._stats["jcbb_gave_up"]:
            logger.warning(
                "JCBB ran out of its budget (%d nodes or %g s) at iteration %d and used its best pairing so far; "
                "raise jcbb_max_nodes / jcbb_max_seconds, or use association nn (jcbb_gave_up in run.json counts them)",
                self.config.jcbb_max_nodes, self.config.jcbb_max_seconds, self._stats["iterations"],
            )  # fmt: skip
        self._stats["jcbb_gave_up"] += 1

    def _measurement_jacobian(self, indices: np.ndarray, H_pose: FloatArray) -> tuple[np.ndarray, FloatArray]:
        """The stacked Jacobian of landmarks ``indices`` (c,) restricted to its non-zero columns.

        Returns the state columns (6 + 3c,) (pose error, then each landmark) and H (3c, 6 + 3c).
        """
        c = len(indices)
        cols = np.concatenate([np.arange(6), self._landmark_columns(indices)])
        H = np.zeros((3 * c, 6 + 3 * c))
        H[:, :6] = H_pose.reshape(3 * c, 6)
        landmark_blocks = H[:, 6:].reshape(c, 3, c, 3)
        landmark_blocks[np.arange(c), :, np.arange(c), :] = self._rotation.T
        return cols, H

    def _joint_measurement_covariance(self, indices: np.ndarray, H_pose: FloatArray) -> FloatArray:
        """``H P H^T`` (3c, 3c) of the predicted measurements of landmarks ``indices`` (no noise)."""
        cols, H = self._measurement_jacobian(indices, H_pose)
        return H @ self._P[np.ix_(cols, cols)] @ H.T

    # ---------------------------------------------------------------------------------------- update

    def _update_landmarks(self, points: FloatArray, indices: np.ndarray) -> None:
        """EKF update with points (m, 3) paired to landmarks ``indices`` (m,), as one batched measurement.

        ``H`` is non-zero only in the pose-error columns (``H_pose``, 3m x 6) and in landmark j's own
        block (``R^T``), so, ``P`` being symmetric, ``H P = H_pose P[:6] + R^T P[m_j]`` per landmark
        from whole rows of ``P``: O(N m).
        """
        m = len(indices)
        N = self._size
        P = self._P
        Rt = self._rotation.T
        z_hat, H_pose = self._predict_measurements(self._landmarks[indices])
        H_pose = H_pose.reshape(3 * m, 6)
        rows = self._landmark_columns(indices)
        HP = np.matmul(Rt, P[rows].reshape(m, 3, N)).reshape(3 * m, N)
        HP += H_pose @ P[:6]
        # S = (H P) H^T: the pose columns, then R (= (R^T)^T) on each landmark's own three columns.
        S = HP[:, :6] @ H_pose.T
        S += (HP[:, rows].reshape(3 * m * m, 3) @ Rt.T).reshape(3 * m, 3 * m)
        blocks = S.reshape(m, 3, m, 3)
        blocks[np.arange(m), :, np.arange(m), :] += self._R_obs
        self._apply_update(HP, S, (points - z_hat).ravel())

    def _kalman_update(self, cols: np.ndarray, H: FloatArray, innovation: FloatArray, R_meas: FloatArray) -> None:
        """Update with a measurement whose Jacobian ``H`` (q, len(cols)) is non-zero only in columns ``cols``."""
        HP = H @ self._P[cols]  # (q, N); P is symmetric
        self._apply_update(HP, HP[:, cols] @ H.T + R_meas, innovation)

    def _apply_update(self, HP: FloatArray, S: FloatArray, innovation: FloatArray) -> None:
        """Kalman update from ``H P`` (q, N), the innovation covariance ``S`` (q, q) and the innovation (q,).

        With ``S = L L^T`` and ``W = L^-1 H P`` (q, N): ``dx = W^T L^-1 nu`` and ``P' = P - W^T W``,
        a symmetric rank-q update (BLAS ``syrk``: half the products of the general form, and ``P'``
        stays exactly symmetric).
        """
        S = 0.5 * (S + S.T)
        try:
            L = linalg.cholesky(S, lower=True, check_finite=False)
        except linalg.LinAlgError as error:
            raise np.linalg.LinAlgError("EKF innovation covariance is not positive definite") from error
        # W^T = (H P)^T L^-T, solved from the right in place on the (N, q) Fortran view of H P.
        Wt = blas.dtrsm(1.0, L, HP.T, side=1, lower=1, trans_a=1, overwrite_b=1)
        dx = Wt @ linalg.solve_triangular(L, innovation, lower=True, check_finite=False)
        self._reduce_covariance(Wt)
        self._inject(dx)

    def _reduce_covariance(self, Wt: FloatArray) -> None:
        """``P -= W^T W`` for ``W^T`` (N, q): the O(N^2 q) heart of the update, one BLAS ``syrk``.

        numpy hands the product of an array with its own transpose to ``syrk`` and mirrors the
        triangle, so the result is exactly symmetric.
        """
        P = self._P
        P -= Wt @ Wt.T

    def _inject(self, dx: FloatArray) -> None:
        """Move the nominal state by the error estimate ``dx`` and reset the rotation error to zero."""
        nv = self._nv
        self._position += dx[:3]
        self._rotation = self._rotation @ so3_exp(dx[3:6])
        if nv == 12:
            self._twist += dx[6:12]
        self._landmarks += dx[nv:].reshape(-1, 3)
        # Re-centring dtheta: the error after the reset is G dtheta with G ~ I - [dtheta/2]x.
        G = np.eye(3) - 0.5 * skew(dx[3:6])
        P = self._P
        P[3:6, :] = G @ P[3:6, :]
        P[:, 3:6] = P[:, 3:6] @ G.T
        P[3:6, :] = P[:, 3:6].T  # the same values up to rounding: keep P exactly symmetric
        block = P[3:6, 3:6]
        P[3:6, 3:6] = 0.5 * (block + block.T)  # G B G^T computed as (G B) G^T: symmetric up to rounding

    # ------------------------------------------------------------------------------------- landmarks

    def _add_landmarks(self, points: FloatArray) -> None:
        """Augment the state with ``m = p + R z`` for each point (k, 3) and its joint covariance."""
        k = len(points)
        R = self._rotation
        J = np.zeros((3 * k, 6))
        J[:, :3] = np.tile(np.eye(3), (k, 1))
        J[:, 3:] = (-R @ skew(points)).reshape(3 * k, 3)  # dm/dtheta = -R [z]x
        N = self._size
        P_new_all = J @ self._P[:6, :]  # (3k, N)
        P_nn = P_new_all[:, :6] @ J.T + np.kron(np.eye(k), R @ self._R_obs @ R.T)
        grown = self._resize(N + 3 * k)
        grown[N:, :N] = P_new_all
        grown[:N, N:] = P_new_all.T
        grown[N:, N:] = 0.5 * (P_nn + P_nn.T)
        self._landmarks = np.vstack([self._landmarks, self._position + points @ R.T])
        self._uid = np.concatenate([self._uid, self._next_uid + np.arange(k, dtype=np.int64)])
        self._next_uid += k
        self._drift = np.vstack([self._drift, np.zeros((k, 3))])
        self._moving = np.concatenate([self._moving, np.zeros(k, dtype=bool)])

    def _follow_movers(
        self, points: FloatArray, fresh: np.ndarray, assignment: np.ndarray, ids: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Split the points that would start landmarks (``fresh``) into new landmarks and moving points.

        Points near a live track move it; points near a landmark seen within ``MOVER_RECENT``
        iterations and not matched now are that landmark moving, while most recently seen landmarks
        still match (see :mod:`relpoint.estimators._movers`). Returns the
        points still to start landmarks, and the (point, landmark) pairs of landmarks that moved.
        """
        assert self._movers is not None
        iteration = self._stats["iterations"]
        world = self._position + points[fresh] @ self._rotation.T
        claimed = self._movers.claim(world, None if ids is None else np.asarray(ids)[fresh], iteration)
        fresh, world = fresh[~claimed], world[~claimed]
        matched = np.zeros(len(self._landmarks), dtype=bool)
        matched[assignment[assignment >= 0]] = True
        recent = self._last_seen >= iteration - MOVER_RECENT
        candidates = np.flatnonzero(recent & ~matched)
        if np.count_nonzero(matched) < MOVER_MIN_MATCHED or len(candidates) > np.count_nonzero(recent & matched):
            # Most of what was just seen no longer matches: the pose has drifted, not the landmarks.
            candidates = candidates[:0]
        rows, moved = moved_landmarks(world, self._landmarks, candidates, self._movers.radius)
        self._stats["claimed_by_movers"] += int(np.count_nonzero(claimed))
        return np.delete(fresh, rows), fresh[rows], moved

    def _start_tracks(
        self, points: FloatArray, landmarks: np.ndarray, ids: np.ndarray | None, rows: np.ndarray
    ) -> None:
        """Take ``landmarks`` (c,) out of the state (marginalised) and follow them from ``points`` (c, 3)."""
        assert self._movers is not None
        iteration = self._stats["iterations"]
        world = self._position + points @ self._rotation.T
        for j, position, row in zip(landmarks.tolist(), world, rows.tolist(), strict=True):
            votes = Counter(self._id_votes[j])
            if ids is not None:
                votes[int(ids[row])] += 1
            self._movers.start(position, self._observations[j] + 1, votes, iteration)
        self._remove_landmarks(landmarks)
        self._stats["movers"] += len(landmarks)

    def _drop_vanished(self, points: FloatArray, started: int) -> None:
        """Remove the landmarks that have vanished from the view of this iteration's ``points`` (q, 3,
        sensor frame), after the update; the last ``started`` landmarks were started from them."""
        assert self._vanished is not None
        n = len(self._landmarks)
        new = np.arange(n) >= n - started
        paired = (self._last_seen == self._stats["iterations"]) & ~new
        gone = self._vanished.update(
            self._landmarks, points, self._rotation, self._position, paired, self._moving | new
        )
        if len(gone):
            self._remove_landmarks(gone)
            self._stats["vanished"] += len(gone)

    def _remove_landmarks(self, indices: np.ndarray) -> None:
        """Drop landmarks from the state: their rows and columns of ``P`` (marginalisation) and their records."""
        keep = np.ones(len(self._landmarks), dtype=bool)
        keep[indices] = False
        cols = np.concatenate([np.arange(self._nv), self._landmark_columns(np.flatnonzero(keep))])
        kept = self._P[np.ix_(cols, cols)]
        self._resize(len(cols))[:] = kept
        self._landmarks = self._landmarks[keep]
        self._last_seen = self._last_seen[keep]
        self._first_seen = self._first_seen[keep]
        self._drift = self._drift[keep]
        self._moving = self._moving[keep]
        self._uid = self._uid[keep]
        if self._vanished is not None:
            self._vanished.keep(keep)
        self._observations = [o for o, k in zip(self._observations, keep.tolist(), strict=True) if k]
        self._id_votes = [v for v, k in zip(self._id_votes, keep.tolist(), strict=True) if k]
        if self._known:
            new_index = np.cumsum(keep) - 1
            self._known = {i: int(new_index[j]) for i, j in self._known.items() if keep[j]}

    def _record(self, ids: np.ndarray | None, paired: np.ndarray, indices: np.ndarray, fresh: np.ndarray) -> None:
        """Count observations per landmark and their ground-truth ids (for gt_id; never used to estimate)."""
        first_new = len(self._observations)
        self._last_seen = np.concatenate([self._last_seen, np.full(len(fresh), self._stats["iterations"])])
        self._first_seen = np.concatenate([self._first_seen, np.full(len(fresh), self._stats["iterations"])])
        self._last_seen[indices] = self._stats["iterations"]
        self._observations.extend([1] * len(fresh))
        if self._vanished is not None:
            self._vanished.add(self._landmarks[first_new:])
        self._id_votes.extend(Counter[int]() for _ in range(len(fresh)))
        for j in indices.tolist():
            self._observations[j] += 1
        if ids is None:
            return
        for i, j in zip(paired.tolist(), indices.tolist(), strict=True):
            self._id_votes[j][int(ids[i])] += 1
        for offset, i in enumerate(fresh.tolist()):
            self._id_votes[first_new + offset][int(ids[i])] += 1
            if self.config.association == "known":
                self._known[int(ids[i])] = first_new + offset


SPEC = EstimatorSpec(
    name="ekf",
    description="EKF-SLAM: joint EKF over the 6D sensor pose and 3D point landmarks (NN or JCBB association)",
    config_class=EkfConfig,
    estimator_class=EkfSlam,
    input_kind=POINTS,
    uses=frozenset({ODOMETRY, FIX}),
    noise_adaptive=True,
)
