"""FastSLAM 1.0 and 2.0 over 3D point landmarks, vectorised across particles.

Implements the Rao-Blackwellised particle filter of Zhang, Milios and Gu, *General Concept of 3D
SLAM*, section 4.2 (Alg. 2, eq. 24-25): each particle carries a sensor pose and, conditioned on it,
one independent 3x3 EKF per landmark. The motion models are those of the EKF (section 2.1, eq. 3-7:
odometry held between records, or a constant-velocity model), the measurement is a landmark's
position in the sensor frame (eq. 11-13), and each particle associates each point by maximum
likelihood, starting a new landmark when no landmark explains the point better than a fixed
new-landmark likelihood (Montemerlo et al., FastSLAM 2.0, 2003). A point that no landmark explains but
that lies inside a wider gate of one is discarded rather than mapped (as the EKF's two gates do): at a
loop closure the first points of old landmarks arrive offset by the drift, and a duplicate started
from them would win every later association and keep the loop open.

Moving points: a landmark whose smoothed innovation, beside the particle's other landmarks', leaves
its gate is taken to be moving (``follow_movers``, :mod:`relpoint.estimators._landmark_motion`): it
follows its points without pulling the pose instead of leaving a trail of duplicate landmarks, and
the map flags it dynamic.

Position fixes (``/fix``; *General Concept of 3D SLAM*, sections 5-6) are fused in the loop once
they pin the local frame (``relpoint.estimators._fix_frame``): each particle is weighted by a fix's
likelihood and moved towards it by eq. 31-32 together with the landmarks it saw lately.

Variants
    ``1.0`` samples the pose from the motion model and weights by the landmarks' measurement
    likelihood. ``2.0`` folds each associated point into a Gaussian proposal over the pose and twist
    (an EKF update with the landmark's uncertainty as measurement noise), samples from it, and
    weights by the sequential marginal likelihood of the points, which keeps far fewer particles
    alive when the points are much more precise than the motion model.

Layout
    Particle ``p`` holds position ``positions[p]`` (world, m), ``rotations[p]`` (``R_world_sensor``),
    body twist ``twists[p]`` (v m/s, w rad/s) and landmarks ``means[p, :counts[p]]`` (world, m) with
    covariances ``covs[p, :counts[p]]``. Every array has the particle index first, so each step of the
    algorithm is one numpy expression over all particles; points are taken one at a time, each against
    only the landmark slots near it in some particle.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree
from scipy.special import logsumexp

from relpoint.estimators import _fastslam_kernels
from relpoint.estimators._association import COLLAPSE_FRACTION, widening_scales
from relpoint.estimators._drift_rate import DRIFT_PRIOR, DriftRate
from relpoint.estimators._dropouts import DropoutRegistration, rotation_errors
from relpoint.estimators._fix_frame import (
    FixFrame,
    FrameFit,
    drawn_frame_transform,
    frame_summary,
    moved_to_final_frame,
    placed_in_one_frame,
)
from relpoint.estimators._fix_gate import FixGate
from relpoint.estimators._fix_smoothing import smoothed_on_fixes
from relpoint.estimators._landmark_motion import (
    MotionTest,
    candidate_slots,
    hand_over,
    shared_motion_removed,
)
from relpoint.estimators._loop_closure import (
    LOOP_TOLERANCE_SIGMAS,
    MIN_SUPPORT,
    OLD_ITERATIONS,
    YOUNG_ITERATIONS,
    register_loop,
)
from relpoint.estimators._noise import SIMULATOR_SIGMA
from relpoint.estimators._odometry_hold import OdometryHold
from relpoint.estimators._recent_path import RecentPath
from relpoint.estimators._time_gaps import GapBridge
from relpoint.estimators._trajectory_smoothing import summed_fix_jumps
from relpoint.estimators._vanished import (
    MIN_MISSES,
    MIN_PAIRED,
    SUCCESSION_WINDOW,
    SensorView,
    run_log_probability,
)
from relpoint.estimators.base import FIX, ODOMETRY, POINTS, Estimator
from relpoint.estimators.fastslam_config import SEARCH_RADIUS_SIGMAS, FastSlamConfig
from relpoint.estimators.spec import EstimatorSpec
from relpoint.geometry import FloatArray, apply_transform, so3_exp, twist_step
from relpoint.statistics import chi2_gate
from relpoint.types import LandmarkMap, OdometryMeasurement, PointObservation, Pose, PositionFix, Trajectory

logger = logging.getLogger(__name__)

_LOG_2PI = math.log(2.0 * math.pi)
_SLOT_ARRAYS = {
    "means": 0.0,
    "covs": 0.0,
    "_seen": 0,
    "_last": 0,
    "_vote_id": -1,
    "_vote_n": 0,
    "_drift": 0.0,
    "_moving": False,
    "_suspect": -1,
    "_suspect_misses": 0,
    "_born": -1,
}
"""Attributes indexed by particle and landmark slot, with the value of an empty slot: capacity grows
and a dropped landmark's gap closes in each of them."""
#: Attributes indexed by particle; resampling copies each of them.
_PARTICLE_ARRAYS = ("positions", "rotations", "twists", "_Sigma", "counts", "_fix_cov", "_frame_draws",
                    *_SLOT_ARRAYS)  # fmt: skip


def low_variance_resample(weights: npt.ArrayLike, rng: np.random.Generator) -> npt.NDArray[np.int64]:
    """Low-variance (systematic) resampling: N indices drawn with one uniform number.

    Parameters
    ----------
    weights: (N,) non-negative weights summing to 1.
    rng: the only source of randomness.

    Returns
    -------
    (N,) indices into the particles, sorted; particle ``i`` appears about ``N * weights[i]`` times.
    """
    w = np.asarray(weights, dtype=np.float64)
    n = len(w)
    pointers = (rng.uniform(0.0, 1.0 / n) + np.arange(n) / n).clip(max=1.0)
    cumulative = np.cumsum(w)
    cumulative[-1] = 1.0
    return np.minimum(np.searchsorted(cumulative, pointers, side="left"), n - 1).astype(np.int64)


#: :func:`near_slots` keeps the slots within this many search radii of the points' box in ``world``:
#: a margin for rounding only (the compiled search measures in the sensor frame).
_PRESELECT_MARGIN = 1.001


def near_slots(
    points: FloatArray, positions: FloatArray, rotations: FloatArray, means: FloatArray,
    counts: npt.NDArray[np.int64], radius: float,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:  # fmt: skip
    """Per point, the landmark slots within ``radius`` of it in at least one particle: CSR ``(offsets,
    slots)``, the same as :func:`relpoint.estimators._fastslam_kernels.near_slots` over every slot.

    The compiled search takes every particle's every landmark into the sensor frame, which at 2,500
    landmarks cost as much as the whole association (13 ms an iteration), while only the landmarks
    around the sensor can be near a point. It is handed only the slots whose box over the particles
    (``world``) meets the box of every particle's points grown by the radius: a slot outside it is
    farther than ``radius`` from every point in every particle. The kept slots stay in order, so each
    particle's live ones (``j < counts[p]``) are still a prefix of them.

    ``points`` (N, 3) sensor frame, C-contiguous; ``positions`` (P, 3), ``rotations`` (P, 3, 3)
    ``R_world_sensor``; ``means`` (P, M, 3) world; ``counts`` (P,) slots in use; ``radius`` (m).
    """
    width = int(counts.max(initial=0))
    if len(points) == 0 or width == 0:
        return _fastslam_kernels.near_slots(points, positions, rotations, means, counts, radius)
    world = (positions[:, None, :] + points @ np.swapaxes(rotations, 1, 2)).reshape(-1, 3)
    margin = _PRESELECT_MARGIN * radius
    # fmin/fmax skip NaN: a non-finite point or landmark is near nothing, in the compiled search too.
    low, high = np.fmin.reduce(world, axis=0) - margin, np.fmax.reduce(world, axis=0) + margin
    live = means[:, :width]
    slot_low, slot_high = np.fmin.reduce(live, axis=0), np.fmax.reduce(live, axis=0)  # (width, 3)
    kept = np.flatnonzero(np.all((slot_high >= low) & (slot_low <= high), axis=1))
    kept_counts = np.searchsorted(kept, counts).astype(np.int64)  # the kept slots below each particle's count
    offsets, slots = _fastslam_kernels.near_slots(
        points, positions, rotations, np.ascontiguousarray(live[:, kept]), kept_counts, radius
    )
    return offsets, kept[slots]


def _fix_update(
    P: FloatArray, H: FloatArray, nu: FloatArray, P_fix: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Kalman update of each particle's errors by a position fix (eq. 31-32 on the joint state).

    Parameters
    ----------
    P: (n, m, m) covariance of each particle's errors.
    H: (n, 3, m) each particle's position error as a function of them.
    nu: (n, 3) the fix minus each particle's position (m).
    P_fix: (3, 3) the fix's covariance (m^2).

    Returns
    -------
    The correction of the errors (n, m), their covariance after the fix (n, m, m) and the
    innovation's covariance (n, 3, 3). The covariance is updated in Joseph form and symmetrised, so it
    stays positive semi-definite whatever the gain's rounding.
    """
    H_t = np.swapaxes(H, 1, 2)
    S = H @ P @ H_t + P_fix + np.eye(3) * 1e-12  # the floor keeps a zero-covariance fix invertible
    K = P @ H_t @ np.linalg.inv(S)  # (n, m, 3)
    correction = np.einsum("pij,pj->pi", K, nu)
    A = np.eye(P.shape[-1]) - K @ H
    fused = A @ P @ np.swapaxes(A, 1, 2) + K @ P_fix @ np.swapaxes(K, 1, 2)
    return correction, 0.5 * (fused + np.swapaxes(fused, 1, 2)), S


class FastSlam(Estimator[PointObservation]):
    """FastSLAM 1.0 / 2.0 with per-particle maximum-likelihood association.

    Parameters
    ----------
    config: settings.
    rng: source of every random draw (proposal samples and resampling).
    """

    name: ClassVar[str] = "fastslam"
    finishing: ClassVar[str] = "smoothing trajectory"

    def __init__(self, config: FastSlamConfig | None, rng: np.random.Generator) -> None:
        self.config = cfg = config or FastSlamConfig()
        self._rng = rng
        self._gaps = GapBridge()
        self._dropouts = DropoutRegistration()
        self._last_poses: tuple[FloatArray, FloatArray] | None = None  # each particle's (N, 3), (N, 3, 3)
        n = cfg.particles
        sigma = cfg.observation_sigma if cfg.observation_sigma is not None else SIMULATOR_SIGMA
        self._search_radius = cfg.search_radius if cfg.search_radius is not None else SEARCH_RADIUS_SIGMAS * sigma
        self._Q = np.eye(3) * sigma**2
        # New-landmark likelihood: density of a fresh landmark's innovation (covariance 2Q) at the quantile.
        gate = chi2_gate(cfg.new_landmark_probability, 3)
        log_norm = 0.5 * (3 * _LOG_2PI + math.log(np.linalg.det(2.0 * self._Q)))
        self._log_new = -0.5 * gate - log_norm
        self._log_start = -0.5 * chi2_gate(cfg.start_landmark_probability, 3) - log_norm
        self.positions = np.zeros((n, 3))
        self.rotations = np.tile(np.eye(3), (n, 1, 1))
        self.twists = np.zeros((n, 6))
        self.log_weights = np.full(n, -math.log(n))
        self.counts = np.zeros(n, dtype=np.int64)
        self._capacity = 64
        self.means = np.zeros((n, self._capacity, 3))
        self.covs = np.zeros((n, self._capacity, 3, 3))
        self._seen = np.zeros((n, self._capacity), dtype=np.int64)
        self._last = np.zeros((n, self._capacity), dtype=np.int64)  # iteration each landmark was last seen
        # Each particle's draw (dt (m), dphi (rad)) from the frame fit's uncertainty at the pinning
        # (zeros before it): resampled with the particle, so the fixes' selection among the draws shows.
        self._frame_draws = np.zeros((n, 6))
        # From the pinning on, the joint covariance of each particle's errors (e, f): e (3, m) the part
        # of its position's error in ``world`` that its frame does not explain (the drawn poses'
        # spread, the drift between fixes), f = (dt (m), dphi (rad)) its frame's error about the fit's
        # centre. Its position's error is e + J(p) f (J: FrameFit.perturbation_jacobian): far from
        # the centre the frame's rotation is metres of it. A fix corrects both, the frame's share by
        # turning the particle's pose and whole map (_fix_update).
        self._fix_cov = np.zeros((n, 9, 9))
        # The rate the particles' place in world drifts at between fixes (m/m): fix_drift, or measured
        # on the fused fixes' innovations when it is unset (relpoint.estimators._drift_rate).
        self._drift_rate = DriftRate(DRIFT_PRIOR) if cfg.fix_drift is None else None
        self._vote_id = np.full((n, self._capacity), -1, dtype=np.int64)
        self._vote_n = np.zeros((n, self._capacity), dtype=np.int64)
        self._drift = np.zeros((n, self._capacity, 3))  # smoothed innovation of each landmark (world, m)
        self._moving = np.zeros((n, self._capacity), dtype=bool)
        # Vanished landmarks (relpoint.estimators._vanished): a landmark a new one may have replaced
        # is a suspect from that iteration on, and its misses in view are counted until it is paired
        # again or dropped.
        self._suspect = np.full((n, self._capacity), -1, dtype=np.int64)
        self._suspect_misses = np.zeros((n, self._capacity), dtype=np.int64)
        self._born = np.full((n, self._capacity), -1, dtype=np.int64)  # iteration each landmark was started
        # One spare array per shape, type and empty value of the slot arrays, that resampling gathers
        # into (its old array becomes the next spare): about two thirds more memory than they take.
        self._spare_slot_arrays: dict[tuple[tuple[int, ...], str, float], np.ndarray] = {}
        self._slots_used = 0  # the most landmarks any particle has held so far: slots beyond are empty
        self._view = SensorView() if cfg.drop_vanished else None
        self._log_vanished = math.log(cfg.vanished_probability)
        self._mover_test = MotionTest(cfg.mover_gate_probability, self._search_radius) if cfg.follow_movers else None
        self._stamp_ns: int | None = None
        self._moved = False
        self._predicted = False  # predicted since the last observation (pose_noise is added once per iteration)
        self._twist_unknown = False
        # The first prediction's twist spread: the configured prior, or the measured start's (start_moving).
        self._initial_twist_sigma = np.repeat([cfg.initial_speed_sigma, cfg.initial_turn_rate_sigma], 3)
        self._step_stamp_ns: int | None = None
        self._Sigma = np.zeros((n, 12, 12))
        self._hold = OdometryHold()
        self._stats = Counter[str]()
        self._stats["association_widened"] = 0  # iterations proposed again under a wider prior (run.json)
        self._stats["association_collapsed"] = 0  # ... and those whose association collapsed all the same
        if cfg.close_loops:
            self._stats["loop_closures"] = 0  # loops closed by registering young landmarks onto old ones (run.json)
            self._stats["loop_landmarks_merged"] = 0  # the best particle's young landmarks merged into old ones
        if cfg.drop_vanished:
            self._stats["vanished"] = 0  # landmarks the best particle dropped as vanished (run.json)
        # Fix frame (``rigid``): None once the particles are in the fixes' frame (or with ``ignore``).
        self._frame: FixFrame | None = FixFrame(min_spread=cfg.fix_min_spread) if cfg.fix_alignment == "rigid" else None
        self._frame_fit: FrameFit | None = None
        self._fix_gate = FixGate(self.config.fix_gate_probability, self.config.fix_gate_patience)
        # Trajectory smoothing on the fixes (``smooth_trajectory``): each fix taken (stamp (ns),
        # position (m), per-axis variance (m^2)) and each fused fix's jump of the mean position.
        self._fixes_taken: list[tuple[int, FloatArray, FloatArray]] = []
        self._fix_jumps: list[tuple[int, FloatArray]] = []  # (iteration, position shift (m))
        self._jumps = np.zeros(3)  # the fused fixes' jumps of the mean position so far (m)
        # The mean positions of the latest iterations, to carry a fix stamped before the particles'
        # time to it (relpoint.estimators._recent_path).
        self._recent = RecentPath()
        # (stamp ns, mean pose (local, 4 x 4)) of each iteration before the pinning: placed again by one
        # transform at the end (placed_in_one_frame)
        self._local_poses: list[tuple[int, FloatArray]] = []
        # (stamp ns, the particles' mean frame draw (6,)) of each iteration after a pinning that drew:
        # the frame its pose was output in, moved to the final one at the end (moved_to_final_frame)
        self._draw_means: list[tuple[int, FloatArray]] = []
        self._frame_refined: dict[str, float] = {}  # the final mean draw's size (run.json)
        self._smoothing: dict[str, Any] | None = None

    # ------------------------------------------------------------------------------------ interface

    @classmethod
    def compile(cls) -> None:
        """Compile or load the association's compiled loops (:mod:`relpoint.estimators._fastslam_kernels`);
        nothing to do when they were built ahead of time at install."""
        _fastslam_kernels.prepare()

    @property
    def weights(self) -> FloatArray:
        """Normalised particle weights (N,)."""
        return np.exp(self.log_weights)

    def start_moving(self, twist: FloatArray, twist_sigma: FloatArray) -> bool:
        if self._stamp_ns is not None:
            return False
        self.twists[:] = twist
        self._initial_twist_sigma = np.array(twist_sigma, dtype=np.float64)
        return True

    def step(self, observation: PointObservation) -> Pose:
        """Propose poses, associate and weight, update landmarks, resample; return the mean pose."""
        if self._stamp_ns is None:
            self._stamp_ns = observation.stamp_ns
        self._predict_to(observation.stamp_ns)
        self._hold.observed(self._stamp_ns)
        Sigma, self._Sigma = self._Sigma, np.zeros_like(self._Sigma)
        if self._predicted:  # once per iteration, however many records split the prediction
            Sigma[:, :6, :6] += np.eye(6) * self.config.pose_noise**2
            self._predicted = False
        points = np.asarray(observation.points)
        if len(points):
            Sigma = self._measure_dropout(observation.stamp_ns, points, Sigma)
        # 1.0 samples the motion model, except while the initial twist is unknown: a blind draw from
        # its wide prior (initial_speed_sigma) leaves most particles metres off after one step.
        proposal = self.config.variant == "2.0" or self._twist_unknown
        wide_prior, self._twist_unknown = self._twist_unknown, False
        prior = Sigma
        if not proposal:
            self._apply_sample(Sigma)
            Sigma = np.zeros_like(Sigma)
        points = np.asarray(observation.points)
        if self._mover_test is not None:
            self._mover_test.widen(self.covs, self._moving)
        assoc, log_likelihood, Sigma, near = self._associate_or_widen(points, Sigma, proposal, wide_prior)
        if proposal:
            self._apply_sample(Sigma)
        if self._frame_fit is not None:
            # The pose drawn each iteration carries the proposal's spread into the particle's place in
            # ``world``: its frame covariance grows by it (most in stretches without landmarks).
            drawn = (Sigma if proposal else prior)[:, :3, :3]
            self._fix_cov[:, :3, :3] += drawn
            # A turned map drifts in proportion to the distance travelled, which the collapsed
            # particles' spread does not show: a random walk of the drift rate per metre stands for it.
            if self._step_stamp_ns is not None:
                dt = (observation.stamp_ns - self._step_stamp_ns) * 1e-9
                distance = np.linalg.norm(self.twists[:, :3], axis=1) * dt
                self._fix_cov[:, :3, :3] += (self._fix_drift * distance)[:, None, None] ** 2 * np.eye(3)
                if self._drift_rate is not None:
                    w = self.weights
                    self._drift_rate.travel(float(w @ distance), float(w @ np.trace(drawn, axis1=1, axis2=2)) / 3.0)
        self._step_stamp_ns = observation.stamp_ns
        self.log_weights = self.log_weights + log_likelihood
        self.log_weights -= logsumexp(self.log_weights)
        if self._mover_test is not None:
            self._classify_motion(points, assoc)
        self._update_landmarks(points, assoc, observation.ids)
        if self._mover_test is not None and self.config.hand_over_movers:
            self._hand_over(points, assoc, near, observation.ids)
        started = self._add_landmarks(points, assoc, observation.ids)
        if self._view is not None:
            self._drop_vanished(points, assoc, near, *started)
        self._resample_if_degenerate()
        if self.config.close_loops:
            self._close_loop()
        self._stats["iterations"] += 1
        if self._frame is not None:
            w = self.weights
            mean = w @ self.positions
            spread = np.einsum("p,pa,pb->ab", w, self.positions - mean, self.positions - mean)
            fit = self._frame.update(observation.stamp_ns, mean, spread)
            if fit is not None:
                self._pin_frame(fit)
            else:  # the local pose, placed again by one transform at the end
                self._local_poses.append((observation.stamp_ns, self._mean_pose()))
        if self._frame_fit is not None and self._frame_fit.covariance.any():  # draws only from an uncertain fit
            self._draw_means.append((observation.stamp_ns, self.mean_frame_draw))
        self._recent.add(observation.stamp_ns, self.weights @ self.positions)
        self._dropouts.remember(observation.stamp_ns, points)
        if len(points) >= 3:
            self._last_poses = (self.positions.copy(), self.rotations.copy())
        return self.pose()

    def _measure_dropout(self, stamp_ns: int, points: FloatArray, Sigma: FloatArray) -> FloatArray:
        """After dropped observations, fuse the motion the points register into since the last one
        (:mod:`relpoint.estimators._dropouts`) into each particle's prior ``Sigma`` (N, 12, 12) as a
        measurement of its pose: its pose at the last observation composed with the motion. Moves the
        particles' nominal state; returns the prior given that measurement."""
        if self._last_poses is None or not self._dropouts.pending(stamp_ns):
            return Sigma
        p0, R0 = self._last_poses
        best = int(np.argmax(self.weights))  # its predicted motion is one of the registration's starts
        predicted = (R0[best].T @ self.rotations[best], R0[best].T @ (self.positions[best] - p0[best]))
        motion = self._dropouts.motion_since_last(stamp_ns, points, predicted, float(np.sqrt(self._Q[0, 0])))
        if motion is None:
            return Sigma
        R, t, C = motion
        innovation = np.concatenate(
            [p0 + R0 @ t - self.positions, rotation_errors(self.rotations, R0 @ R)], axis=1
        )  # (N, 6)
        C_world = np.broadcast_to(C, (len(p0), 6, 6)).copy()
        C_world[:, :3, :3] = R0 @ C[:3, :3] @ np.swapaxes(R0, 1, 2)
        S = Sigma[:, :6, :6] + C_world
        gain = np.swapaxes(np.linalg.solve(S, Sigma[:, :6, :]), 1, 2)  # (N, 12, 6): Sigma H^T S^-1
        self._inject(np.einsum("pij,pj->pi", gain, innovation))
        Sigma = Sigma - gain @ Sigma[:, :6, :]
        return 0.5 * (Sigma + np.swapaxes(Sigma, 1, 2))

    def add_fix(self, fix: PositionFix) -> None:
        """Fuse an absolute position fix (``fix_alignment="rigid"``; ignored with ``ignore``).

        Before the fixes pin the frame they only collect pairs for the fit. Afterwards each particle
        keeps a covariance ``C`` of its position in ``world`` (the fit's uncertainty at the pinning,
        grown by every drawn pose's spread); a fix weighs the particle by its likelihood
        ``N(fix; p, C + P_fix)`` and fuses with it by eq. 31-32, moving the particle's pose and the
        landmarks it saw within ``fix_window`` iterations together (a particle's map cannot
        follow its pose otherwise: conditioned on the path, the points never pull the map towards the
        fixes). A fix that no particle can explain is held back by the fix gate
        (``fix_gate_probability``, :class:`~relpoint.estimators._fix_gate.FixGate`); once the gate
        says the particles have drifted, their covariance ``C`` is scaled until the fix lies on the
        gate's edge for the nearest particle, and the fix is fused with its own covariance.
        """
        if self.config.fix_alignment == "ignore":
            return
        fix_variances = np.diag(np.asarray(fix.covariance, dtype=np.float64)).copy()
        if self._frame is not None:
            self._frame.add_fix(fix)
            if self.config.smooth_trajectory:
                self._fixes_taken.append((fix.stamp_ns, np.asarray(fix.position, dtype=np.float64), fix_variances))
            return
        if self._stamp_ns is not None:
            self._predict_to(fix.stamp_ns)
        # A fix stamped before the particles' time (a receiver's latency) is carried forward along the
        # filter's own motion since its stamp.
        now = self._stamp_ns if self._stamp_ns is not None else fix.stamp_ns
        moved = self._recent.displacement(fix.stamp_ns, now, self.weights @ self.positions)
        if moved is None:  # counted by the path (fixes_too_old)
            return
        fix_position = np.asarray(fix.position, dtype=np.float64) + moved
        P_fix = np.asarray(fix.covariance, dtype=np.float64)
        P = self._fix_cov  # (n, 9, 9): each particle's (e, f)
        H = self._position_jacobian()  # (n, 3, 9): the position's error is H (e, f)
        C = H @ P @ np.swapaxes(H, 1, 2)  # (n, 3, 3): covariance of each particle's position in world
        S = C + P_fix + np.eye(3) * 1e-12  # the floor keeps a zero-covariance fix invertible
        S_inv = np.linalg.inv(S)
        nu = fix_position - self.positions  # (n, 3)
        # Gated as a whole: held back only if no particle can explain it (relpoint.estimators._fix_gate).
        inflation = self._fix_gate.inflation(float(np.min(np.einsum("pa,pab,pb->p", nu, S_inv, nu))))
        if inflation is None:
            return
        if inflation != 1.0:
            # Fixes have kept disagreeing with every particle: the particles' frame has drifted
            # further than their covariance says (a stretch without landmarks), so it is the
            # particles' covariance that grows, until the fix lies on the gate's edge, and the fix
            # pulls them by the gain that follows. Inflating the fix's covariance instead left the
            # drifted particles where they were (figure8-gaps: 9-28 m against 1.6-2.2 m).
            # The growth is drift, not the frame's own uncertainty: it goes to e, and the frame's
            # share of the correction below stays what the frame's covariance makes it.
            a = self._filter_inflation(nu, C, P_fix)
            P = P.copy()
            P[:, :3, :3] += (a - 1.0) * C
        mean_before, draw_before = self.weights @ self.positions, self.weights @ self._frame_draws
        if self._drift_rate is not None:
            # The correction the fix measures of the path without its jumps holds the frame's error
            # beside the drift: its share of the position's variance here is noise to the drift rate,
            # not a walk (counted as drift, a frame turned by 2 deg measured a rate of 0.2-0.4 m/m on a
            # map that drifted by centimetres, and the fixes' noise was fused into it).
            J = H[:, :, 3:]
            frame_share = self.weights @ np.diagonal(J @ P[:, 3:, 3:] @ np.swapaxes(J, 1, 2), axis1=1, axis2=2)
            self._drift_rate.fix(fix_position - (mean_before - self._jumps), fix_variances + frame_share)
        correction, self._fix_cov, S = _fix_update(P, H, nu, P_fix)
        S_inv = np.linalg.inv(S)
        _, logdet = np.linalg.slogdet(S)
        self.log_weights = self.log_weights - 0.5 * (np.einsum("pa,pab,pb->p", nu, S_inv, nu) + logdet + 3 * _LOG_2PI)
        self.log_weights -= logsumexp(self.log_weights)
        # The frame's share of the correction (a turn about the fit's centre, which a position alone
        # cannot correct) moves the particle rigidly, pose, heading and whole map: shifted alone, the
        # positions followed the fixes while the heading kept the fit's error, and every landmark
        # seen since was placed along it (2-3 deg on a 60 m pass, 1.5 m at 30 m range). The rest
        # (eq. 31-32 on e) shifts the pose and the landmarks it saw lately together, as one local frame.
        self._turn_frames(correction[:, 3:])
        shift = correction[:, :3]
        self.positions = self.positions + shift
        recent = self._last >= self._stats["iterations"] - self.config.fix_window
        self.means += np.where(recent[:, :, None], shift[:, None, :], 0.0)
        self._stats["fixes"] += 1
        # The jump of the mean position (weights and positions both moved), but for the change of the
        # particles' mean frame draw, which finish() takes out for every pose alike.
        centre = self._frame_fit.centre
        reframed = drawn_frame_transform(centre, self.mean_frame_draw) @ np.linalg.inv(
            drawn_frame_transform(centre, draw_before)
        )
        jump = self.weights @ self.positions - apply_transform(reframed, mean_before[None])[0]
        self._jumps = self._jumps + jump
        self._recent.shift(self.weights @ self.positions - mean_before)
        if self.config.smooth_trajectory:
            self._fix_jumps.append((self._stats["iterations"], jump))
            self._fixes_taken.append((fix.stamp_ns, np.asarray(fix.position, dtype=np.float64), fix_variances))

    def _position_jacobian(self, positions: FloatArray | None = None) -> FloatArray:
        """``H`` (n, 3, 9) with each particle's position error ``H (e, f) = e + J(p) f`` (``_fix_cov``), at
        ``positions`` (n, 3) (the particles' own when None)."""
        assert self._frame_fit is not None
        n = self.config.particles
        H = np.zeros((n, 3, 9))
        H[:, :, :3] = np.eye(3)
        H[:, :, 3:] = self._frame_fit.perturbation_jacobian(self.positions if positions is None else positions)
        return H

    def position_covariance(self, positions: FloatArray | None = None) -> FloatArray:
        """Covariance (n, 3, 3) m^2 of each particle's position in ``world``, its frame's share included,
        at ``positions`` (n, 3) (the particles' own when None; zeros before the fixes pin the frame)."""
        if self._frame_fit is None:
            return np.zeros((self.config.particles, 3, 3))
        H = self._position_jacobian(positions)
        return H @ self._fix_cov @ np.swapaxes(H, 1, 2)

    def _turn_frames(self, correction: FloatArray) -> None:
        """Move each particle ``p`` rigidly by ``correction[p] = (dt, dphi)`` about the fit's centre ``c``
        (``x -> c + Exp(dphi) (x - c) + dt``): its pose and every landmark; its frame draw composes."""
        from scipy.spatial.transform import Rotation  # here, not at import: only fused fixes need it

        assert self._frame_fit is not None
        c = self._frame_fit.centre
        turn = so3_exp(correction[:, 3:])  # (n, 3, 3)
        self.positions = c + np.einsum("pij,pj->pi", turn, self.positions - c) + correction[:, :3]
        self.rotations = turn @ self.rotations
        self.means = c + np.einsum("pij,pmj->pmi", turn, self.means - c) + correction[:, None, :3]
        self.covs = turn[:, None] @ self.covs @ np.swapaxes(turn, 1, 2)[:, None]
        draws = self._frame_draws
        composed = turn @ so3_exp(draws[:, 3:])
        self._frame_draws = np.concatenate(
            [
                np.einsum("pij,pj->pi", turn, draws[:, :3]) + correction[:, :3],
                Rotation.from_matrix(composed).as_rotvec(),
            ],
            axis=1,
        )

    @property
    def _fix_drift(self) -> float:
        """The drift rate in use (m of position per axis per m travelled)."""
        return self._drift_rate.rate if self._drift_rate is not None else float(self.config.fix_drift)

    def _filter_inflation(self, nu: FloatArray, C: FloatArray, P_fix: FloatArray) -> float:
        """The factor ``a`` of the particles' position covariances ``C`` (n, 3, 3) that puts the fix
        on the gate's edge for the particle nearest to it: ``min_p nu_p^T (a C_p + P_fix)^-1 nu_p``
        equals the gate (Brent's method on log ``a``, 1 to 1e12; called past the gate, so at ``a = 1``
        the fix is outside it)."""
        from scipy.optimize import brentq  # here, not at import: only a drifted filter needs it

        threshold = self._fix_gate.threshold
        eye = np.eye(3) * 1e-12

        def excess(log_a: float) -> float:
            S_inv = np.linalg.inv(10.0**log_a * C + P_fix + eye)
            return float(np.min(np.einsum("pa,pab,pb->p", nu, S_inv, nu))) - threshold

        if excess(0.0) <= 0.0:
            return 1.0
        if excess(12.0) > 0.0:
            return 1e12
        return 10.0 ** brentq(excess, 0.0, 12.0, xtol=1e-9)

    @property
    def frame_fit(self) -> FrameFit | None:
        """The fit that moved the particles into the fixes' frame (``rigid``), or None before (or without) it."""
        return self._frame_fit

    @property
    def mean_frame_draw(self) -> FloatArray:
        """The particles' weighted mean draw ``(dt (m), dphi (rad))`` (6,) from the frame fit's uncertainty
        (zeros before the pinning): at the end, the frame every pose is placed in
        (:func:`~relpoint.estimators._fix_frame.moved_to_final_frame`)."""
        return self.weights @ self._frame_draws

    def _pin_frame(self, fit: FrameFit) -> None:
        """Move every particle into the fixes' frame by ``fit``, each by a transform drawn from its uncertainty.

        Particle ``p`` maps a local point ``x`` to ``c + Exp(dphi_p) (T x - c) + dt_p`` with
        ``(dt_p, dphi_p) ~ N(0, Sigma_fit)``: the fit's uncertainty becomes spread between the
        particles, which the later fixes' likelihoods then select from. Landmark covariances turn
        with each particle's rotation; twists are in the sensor frame and stay.
        """
        n = self.config.particles
        values, vectors = np.linalg.eigh(fit.covariance)
        draws = self._rng.standard_normal((n, 6)) @ (vectors * np.sqrt(np.clip(values, 0.0, None))).T
        R_T, t = fit.T_world_local[:3, :3], fit.T_world_local[:3, 3]
        self._frame_draws = draws
        self._recent.transform(fit.T_world_local)
        turn = so3_exp(draws[:, 3:])  # (n, 3, 3)
        R = turn @ R_T  # (n, 3, 3): each particle's rotation local -> world
        offset = fit.centre + draws[:, :3] - np.einsum("pij,j->pi", turn, fit.centre)  # (n, 3)
        shift = np.einsum("pij,j->pi", turn, t) + offset
        self.positions = np.einsum("pij,pj->pi", R, self.positions) + shift
        self.rotations = R @ self.rotations
        self.means = np.einsum("pij,pmj->pmi", R, self.means) + shift[:, None, :]
        self.covs = R[:, None] @ self.covs @ np.swapaxes(R, 1, 2)[:, None]
        self._fix_cov = np.zeros((n, 9, 9))
        self._fix_cov[:, 3:, 3:] = fit.covariance
        self._frame = None
        self._frame_fit = fit
        if self._drift_rate is not None:
            C = self.position_covariance()
            self._drift_rate.start(float(self.weights @ np.trace(C, axis1=1, axis2=2)) / 3.0)
        self._Sigma[:, :3, :] = np.einsum("pij,pjk->pik", R, self._Sigma[:, :3, :])
        self._Sigma[:, :, :3] = np.einsum("pki,pji->pkj", self._Sigma[:, :, :3], R)
        self._stats["frame_pinned_at"] = self._stats["iterations"]

    def add_odometry(self, odometry: OdometryMeasurement) -> None:
        """Hold a body-frame twist as the proposal's input from its stamp until the next one; the
        interval up to its stamp is predicted with the twist held before it."""
        if self._stamp_ns is not None:
            self._predict_to(odometry.stamp_ns)
        self._hold.hold(odometry)

    def landmark_map(self) -> LandmarkMap:
        """The map of the particle with the largest weight (before the fixes pin the frame: provisionally
        placed): its landmarks seen at least ``min_observations`` times."""
        best = int(np.argmax(self.log_weights))
        n = int(self.counts[best])
        shown = self._seen[best, :n] >= self.config.min_observations
        positions = self.means[best, :n][shown]
        if self._frame is not None:
            T = self._frame.provisional
            positions = apply_transform(T, positions)
        return LandmarkMap(
            positions,
            self._seen[best, :n][shown],
            self._moving[best, :n][shown],
            self._vote_id[best, :n][shown],
            first_iteration=self._born[best, :n][shown],
        )

    @property
    def map_size(self) -> int:
        """Landmarks in :meth:`landmark_map` (the best particle's, seen ``min_observations`` times)."""
        return int(self.counts[int(np.argmax(self.log_weights))]) - self._not_mapped()

    def _not_mapped(self) -> int:
        """The best particle's landmarks seen fewer than ``min_observations`` times (left out of the map)."""
        best = int(np.argmax(self.log_weights))
        return int(np.count_nonzero(self._seen[best, : int(self.counts[best])] < self.config.min_observations))

    def _moving_landmarks(self) -> int:
        """The best particle's landmarks flagged moving (its slots past ``counts`` are stale copies)."""
        best = int(np.argmax(self.log_weights))
        return int(np.count_nonzero(self._moving[best, : int(self.counts[best])]))

    def summary(self) -> dict[str, Any]:
        w = self.weights
        return {
            "variant": self.config.variant,
            "particles": self.config.particles,
            "linear_acceleration_noise": self.config.acceleration_noise,
            "angular_acceleration_noise": self.config.angular_noise,
            "landmarks": self.map_size,
            "landmarks_not_mapped": self._not_mapped(),
            "moving_landmarks": self._moving_landmarks(),
            "effective_sample_size": float(1.0 / np.sum(w**2)),
            "time_gaps_bridged": self._gaps.bridged,
            "dropouts_registered": self._dropouts.registered,
            "dropouts_unregistered": self._dropouts.unregistered,
            "dropouts_predicted": self._dropouts.predicted,
            "odometry_stale": self._hold.stale,
            **{k: int(v) for k, v in sorted(self._stats.items())},
            **frame_summary(self.config.fix_alignment == "rigid", self._frame_fit),
            **self._fix_gate.summary(),
            **self._recent.summary(),
            **(self._drift_rate.summary() if self._drift_rate is not None and self._frame_fit is not None else {}),
            **self._frame_refined,
            **({"smoothing": self._smoothing} if self._smoothing is not None else {}),
        }

    def finish(self, trajectory: Trajectory) -> Trajectory:
        """The trajectory in one frame, with the fused fixes' jumps taken out and its correction
        smoothed on the fixes (``smooth_trajectory``; :mod:`relpoint.estimators._fix_smoothing`).

        ``trajectory`` holds the poses :meth:`step` returned, one per iteration (``world``). Those
        returned before the fixes pinned the frame were the local pose under the provisional
        transform of their iteration, which changes as fixes arrive: they are placed again by the
        pinning's transform, or by the last provisional one when the fixes never pinned the frame
        (:func:`~relpoint.estimators._fix_frame.placed_in_one_frame`). Without fused fixes, or when
        the run skipped iterations, there is no smoothing (``smoothing`` in :meth:`summary` says so).
        """
        trajectory = placed_in_one_frame(trajectory, self._local_poses, self._frame_fit, self._frame)
        if self._draw_means:
            stamps = np.array([stamp for stamp, _ in self._draw_means], dtype=np.int64)
            draws = np.stack([draw for _, draw in self._draw_means])
            final = self.mean_frame_draw
            trajectory = moved_to_final_frame(trajectory, stamps, draws, final, self._frame_fit.centre)
            self._frame_refined = {"frame_refined_m": round(float(np.linalg.norm(final[:3])), 4),
                                   "frame_refined_deg": round(float(np.degrees(np.linalg.norm(final[3:]))), 3)}  # fmt: skip
        if not self.config.smooth_trajectory or not self._fix_jumps:
            return trajectory
        iterations = self._stats["iterations"]
        if len(trajectory) != iterations:
            self._smoothing = {"applied": False, "reason": "the run skipped iterations"}
            return trajectory
        stamps = np.array([stamp for stamp, _, _ in self._fixes_taken], dtype=np.int64)
        positions = np.array([position for _, position, _ in self._fixes_taken])
        variances = np.array([variance for _, _, variance in self._fixes_taken])
        smoothed, self._smoothing = smoothed_on_fixes(
            trajectory, summed_fix_jumps(self._fix_jumps, iterations), stamps, positions, variances
        )
        self._smoothing["poses_placed_in_pinned_frame"] = len(self._local_poses)  # fixes were fused: it was pinned
        return smoothed

    def pose(self) -> Pose:
        """Weighted mean pose: mean position and the chordal mean of the rotations (before the fixes
        pin the frame: the local pose mapped by the provisional transform)."""
        T = self._mean_pose()
        if self._frame is not None:
            T = self._frame.provisional @ T
        return Pose.from_matrix(self._stamp_ns or 0, T)

    def _mean_pose(self) -> FloatArray:
        """The particles' weighted mean pose ``T`` (4, 4) in their own frame (local until the pinning)."""
        w = self.weights
        U, _, Vt = np.linalg.svd(np.einsum("p,pij->ij", w, self.rotations))
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        T = np.eye(4)
        T[:3, :3] = U @ D @ Vt
        T[:3, 3] = w @ self.positions
        return T

    # ------------------------------------------------------------------------------------ proposal

    def _predict_to(self, stamp_ns: int) -> None:
        """Move every particle's nominal state to ``stamp_ns`` and grow the pending prior covariance:
        with the held odometry until it goes stale, then with the constant-velocity model.

        The prior (N, 12, 12) is over the error ``(dp, dtheta, dv, dw)`` with ``R_true = R Exp(dtheta)``;
        it is sampled (1.0) or refined by the points and then sampled (2.0) at the next observation,
        so odometry records between observations only accumulate it.
        """
        assert self._stamp_ns is not None
        for end_ns in self._hold.prediction_ends(self._stamp_ns, stamp_ns):
            self._predict_span(end_ns)

    def _predict_span(self, stamp_ns: int) -> None:
        assert self._stamp_ns is not None
        dt = (stamp_ns - self._stamp_ns) * 1e-9
        if dt > 0.0:
            dt = self._gaps.interval(dt)
        if dt <= 0.0:
            return
        cfg = self.config
        n = cfg.particles
        F = np.zeros((n, 12, 12))
        acceleration = np.repeat([cfg.acceleration_noise, cfg.angular_noise], 3)
        if self._hold.held is not None:
            twist = np.broadcast_to(self._hold.twist(), (n, 6))
            # the noise of holding the twist over this interval (relpoint.estimators._odometry_hold)
            Q_twist, Q_span = self._hold.noise(self._stamp_ns, self._stamp_ns + round(dt * 1e9), acceleration)
        else:
            twist = self.twists
            q = (acceleration * dt) ** 2
            if not self._moved:
                q += self._initial_twist_sigma**2
                self._twist_unknown = True
            Q_twist = np.diag(q)
            F[:, 6:, 6:] = np.eye(6)  # the twist persists; with odometry the input replaces it
        positions, rotations, F_pose, G = twist_step(self.positions, self.rotations, twist[:, :3], twist[:, 3:], dt)
        F[:, :6, :6] = F_pose
        if self._hold.held is None:
            F[:, :6, 6:] = G
        self.positions, self.rotations, self.twists = positions, rotations, np.array(twist)
        self._moved = self._predicted = True
        self._stamp_ns = stamp_ns
        # The twist noise acts over the interval: it moves the pose through G and becomes the new twist error.
        G_full = np.concatenate([G, np.broadcast_to(np.eye(6), (n, 6, 6))], axis=1)  # (n, 12, 6)
        Sigma = F @ self._Sigma @ np.swapaxes(F, 1, 2) + G_full @ Q_twist @ np.swapaxes(G_full, 1, 2)
        if self._hold.held is not None:
            Sigma[:, :6, :6] += G @ Q_span @ np.swapaxes(G, 1, 2)
        self._Sigma = Sigma

    def _apply_sample(self, Sigma: FloatArray) -> None:
        """Draw one error per particle from N(0, Sigma) (N, 12, 12) and move the nominal state by it."""
        values, vectors = np.linalg.eigh(0.5 * (Sigma + np.swapaxes(Sigma, 1, 2)))
        scale = np.sqrt(np.clip(values, 0.0, None))
        draw = self._rng.standard_normal((self.config.particles, 12))
        self._inject(np.einsum("pij,pj->pi", vectors, scale * draw))

    def _inject(self, delta: FloatArray, mask: npt.NDArray[np.bool_] | None = None) -> None:
        """Move particles' nominal pose and twist by errors ``delta`` (N, 12) (only ``mask`` if given)."""
        if mask is not None:
            delta = np.where(mask[:, None], delta, 0.0)
        self.positions = self.positions + delta[:, :3]
        self.rotations = self.rotations @ so3_exp(delta[:, 3:6])
        self.twists = self.twists + delta[:, 6:]

    # --------------------------------------------------------------------------------- association

    def _associate_or_widen(
        self, points: FloatArray, Sigma: FloatArray, proposal: bool, wide_prior: bool
    ) -> tuple[np.ndarray, FloatArray, FloatArray, tuple[np.ndarray, np.ndarray]]:
        """:meth:`_associate`, proposed again under a wider prior when the association collapses.

        Collapsed: on average over the particles (weighted), fewer than ``COLLAPSE_FRACTION`` of the
        landmarks each saw in the last iteration pair, and more points would start landmarks than
        pair. The constant-velocity prior cannot follow a motion that changes at once (a turn rate
        stepping from 0 to 1.5 rad/s): its points miss their landmarks and every particle starts
        duplicates, and never learns the new turn rate. The prior ``Sigma`` is scaled by 2^2, 4^2, ...
        up to ``collapse_noise_scale``^2, with the pairing score of a wide prior, and the first
        association that pairs enough is kept; otherwise the first one, counted and warned about.
        """
        scale_limit = self.config.collapse_noise_scale
        start = (self.positions.copy(), self.rotations.copy(), self.twists.copy())  # the association moves them
        first = self._associate(points, Sigma, proposal, wide_prior)
        if not proposal or not self._collapsed(first[0], math.inf):  # most iterations: no landmark count needed
            return self._counted(first)
        expected = self._expected_pairs()
        if expected < MIN_PAIRED or not self._collapsed(first[0], expected):
            return self._counted(first)
        after_first = (self.positions, self.rotations, self.twists)
        for scale in widening_scales(scale_limit):
            self.positions, self.rotations, self.twists = (a.copy() for a in start)
            retry = self._associate(points, Sigma * scale**2, proposal, True, reach=scale)
            if not self._collapsed(retry[0], expected):
                self._stats["association_widened"] += 1
                return self._counted(retry)
        self.positions, self.rotations, self.twists = after_first
        if not self._stats["association_collapsed"]:
            logger.warning(
                "association collapsed at iteration %d: the particles paired few of the landmarks seen just before%s; "
                "the map may hold duplicates from here (association_collapsed in run.json counts such iterations): "
                "raise linear_acceleration_noise / angular_acceleration_noise, or give odometry",
                self._stats["iterations"],
                f", also under {scale_limit:g} x the proposal's prior" if scale_limit > 1.0
                else " (collapse_noise_scale 1: no retry)",
            )  # fmt: skip
        self._stats["association_collapsed"] += 1
        return self._counted(first)

    def _expected_pairs(self) -> float:
        """Landmarks the particles saw in the last iteration (weighted mean over the particles)."""
        iteration = self._stats["iterations"]
        if iteration == 0:
            return 0.0
        live = np.arange(self._last.shape[1])[None, :] < self.counts[:, None]
        seen = np.count_nonzero((self._last == iteration - 1) & live, axis=1)
        return float(self.weights @ seen)

    def _collapsed(self, assoc: np.ndarray, expected: float) -> bool:
        """Whether the particles pair, on average, under ``COLLAPSE_FRACTION`` of ``expected`` landmarks and
        would start more landmarks than they pair."""
        w = self.weights
        paired = float(w @ np.count_nonzero(assoc >= 0, axis=1))
        started = float(w @ np.count_nonzero(assoc == -1, axis=1))
        return paired < COLLAPSE_FRACTION * expected and started > paired

    def _counted(
        self, result: tuple[np.ndarray, FloatArray, FloatArray, tuple[np.ndarray, np.ndarray]]
    ) -> tuple[np.ndarray, FloatArray, FloatArray, tuple[np.ndarray, np.ndarray]]:
        """``result`` of the association kept, its pairs and discarded points counted (``run.json``)."""
        assoc = result[0]
        self._stats["paired"] += int(np.count_nonzero(assoc >= 0))
        self._stats["discarded"] += int(np.count_nonzero(assoc == -2))
        return result

    def _associate(
        self, points: FloatArray, Sigma: FloatArray, proposal: bool, wide_prior: bool = False, reach: float = 1.0
    ) -> tuple[np.ndarray, FloatArray, FloatArray, tuple[np.ndarray, np.ndarray]]:
        """Maximum-likelihood association of each point in each particle, one point at a time.

        The candidates of a point are the landmark slots within ``search_radius`` of it in at least one
        particle (taken before the points move the proposal). Returns the association (N, k) (landmark
        slot, -1 for a new landmark, -2 for a discarded point), each particle's log-likelihood of the
        points (N,), the proposal covariance after the points (when ``proposal``, i.e. 2.0: each
        paired point refines the pose prior ``Sigma`` and moves the particle's pose) and the
        candidates (CSR ``offsets, slots`` per point). ``wide_prior`` (the first step, speed unknown):
        the prior's spread does not count against a pairing; ``reach`` multiplies the search radius
        (a prior widened by that factor). Compiled loops:
        :func:`relpoint.estimators._fastslam_kernels.associate`.
        """
        points = np.array(points, dtype=np.float64)  # a writeable copy: one compiled variant per kernel
        counts = self.counts.astype(np.int64)
        positions = np.ascontiguousarray(self.positions, dtype=np.float64)
        rotations = np.ascontiguousarray(self.rotations, dtype=np.float64)
        twists = np.ascontiguousarray(self.twists, dtype=np.float64)
        offsets, slots = near_slots(
            points, positions, rotations, self.means, counts, float(self._search_radius * reach)
        )
        Sigma = np.ascontiguousarray(Sigma, dtype=np.float64).copy()
        assoc, log_likelihood, _, _ = _fastslam_kernels.associate(
            points, offsets, slots, positions, rotations, twists, self.means, self.covs, counts, self._Q, Sigma,
            proposal, float(self._log_new), float(self._log_start), wide_prior,
        )  # fmt: skip
        self.positions, self.rotations, self.twists = positions, rotations, twists
        return assoc, log_likelihood, Sigma, (offsets, slots)

    # ---------------------------------------------------------------------------------- landmarks

    def _update_landmarks(self, points: FloatArray, assoc: np.ndarray, ids: np.ndarray | None) -> None:
        """3x3 EKF update of every associated landmark with the particle's (sampled) pose
        (:func:`relpoint.estimators._fastslam_kernels.update_landmarks`)."""
        if not (assoc >= 0).any():
            return
        _fastslam_kernels.update_landmarks(
            np.array(points, dtype=np.float64), assoc, self.positions, self.rotations, self.means,
            self.covs, self._Q, self._seen, self._last, self._stats["iterations"],
        )  # fmt: skip
        if ids is not None:
            p, i = np.nonzero(assoc >= 0)
            self._vote(p, assoc[p, i], np.asarray(ids)[i])

    def _classify_motion(self, points: FloatArray, assoc: np.ndarray) -> None:
        """Smooth the innovation of every paired landmark and flag the moving ones
        (:mod:`relpoint.estimators._landmark_motion`), before the pairs update the landmarks."""
        assert self._mover_test is not None
        p, i = np.nonzero(assoc >= 0)
        if len(p) == 0:
            return
        j = assoc[p, i]
        R = self.rotations[p]
        offsets = np.einsum("pij,pj->pi", R, points[i])
        innovations = self.positions[p] + offsets - self.means[p, j]
        innovations = shared_motion_removed(p, innovations, offsets, self.config.particles)  # the pose's error
        # Q is isotropic (observation_sigma per axis), so R Q R^T is Q.
        self._drift[p, j], self._moving[p, j] = self._mover_test.classify(
            p, self.config.particles, innovations, np.broadcast_to(self._Q, (len(p), 3, 3)), self.covs[p, j],
            self._drift[p, j], self._moving[p, j], self._seen[p, j],
        )  # fmt: skip

    def _hand_over(
        self, points: FloatArray, assoc: np.ndarray, near: tuple[np.ndarray, np.ndarray], ids: np.ndarray | None
    ) -> None:
        """Pair a point that would start a landmark with a landmark of the same particle that moved out
        of its gate (:func:`relpoint.estimators._landmark_motion.hand_over`); the landmark is moving."""
        assert self._mover_test is not None
        iteration = self._stats["iterations"]
        p, i, j = hand_over(
            assoc, near, self.counts, self._last, iteration, self.positions, self.rotations, points, self.means,
            self._search_radius,
        )  # fmt: skip
        if len(p) == 0:
            return
        R = self.rotations[p]
        world = self.positions[p] + np.einsum("pij,pj->pi", R, points[i])
        self._drift[p, j] = world - self.means[p, j]
        self.means[p, j] = world
        self.covs[p, j] = R @ self._Q @ np.swapaxes(R, 1, 2)
        self._moving[p, j] = True
        self._seen[p, j] += 1
        self._last[p, j] = iteration
        assoc[p, i] = j
        if ids is not None:
            self._vote(p, j, np.asarray(ids)[i])
        self._stats["handed_over"] += len(p)

    def _vote(self, p: np.ndarray, j: np.ndarray, ids: np.ndarray) -> None:
        """Boyer-Moore majority vote of the ground-truth ids fused into each landmark (diagnosis only)."""
        same = self._vote_id[p, j] == ids
        empty = self._vote_n[p, j] == 0
        self._vote_n[p, j] += np.where(same | empty, 1, -1)
        self._vote_id[p, j] = np.where(empty, ids, self._vote_id[p, j])

    def _add_landmarks(
        self, points: FloatArray, assoc: np.ndarray, ids: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Start a landmark ``m = p + R z`` with covariance ``R Q R^T`` for every unexplained point;
        return the particle, slot and point of each (sorted by particle)."""
        p, i = np.nonzero(assoc == -1)
        if len(p) == 0:
            return p, p, i
        # Slot of each new landmark: the particle's count plus its rank among the particle's new points.
        rank = np.arange(len(p)) - np.searchsorted(p, p, side="left")
        slots = self.counts[p] + rank
        self._ensure_capacity(int(slots.max()) + 1)
        R = self.rotations[p]
        self.means[p, slots] = self.positions[p] + np.einsum("pij,pj->pi", R, points[i])
        self.covs[p, slots] = R @ self._Q @ np.swapaxes(R, 1, 2)
        self._drift[p, slots] = 0.0
        self._moving[p, slots] = False
        self._seen[p, slots] = 1
        self._last[p, slots] = self._stats["iterations"]
        self._vote_id[p, slots] = -1 if ids is None else np.asarray(ids)[i]
        self._vote_n[p, slots] = 0 if ids is None else 1
        self._suspect[p, slots] = -1
        self._suspect_misses[p, slots] = 0
        self._born[p, slots] = self._stats["iterations"]
        self.counts += np.bincount(p, minlength=self.config.particles)
        self._slots_used = max(self._slots_used, int(self.counts.max()))
        self._stats["started"] += len(p)
        return p, slots, i

    def _drop_vanished(
        self, points: FloatArray, assoc: np.ndarray, near: tuple[np.ndarray, np.ndarray], new_p: np.ndarray,
        new_slots: np.ndarray, new_points: np.ndarray,
    ) -> None:  # fmt: skip
        """Drop, in each particle, the landmarks that have vanished (:mod:`relpoint.estimators._vanished`).

        A landmark the particle last paired at most ``SUCCESSION_WINDOW`` iterations ago and not now,
        nearest to where one of the particle's new landmarks started (within the search radius: among
        the association's candidates ``near`` of the point that started it), is a suspect; a suspect paired again is cleared. A suspect in view of ``points`` (sensor frame)
        and not paired counts a miss (in iterations where its particle pairs at least ``MIN_PAIRED``
        points); after ``MIN_MISSES`` misses with a chance below ``vanished_probability`` under its
        detection rate (seen as many times as it was paired) it is dropped from its particle's map.
        """
        assert self._view is not None
        iteration = self._stats["iterations"]
        self._view.add(points)
        if len(new_p):
            pp, pj = self._replaced(near, new_p, new_slots, new_points, iteration)
            fresh = self._suspect[pp, pj] < 0
            self._suspect[pp[fresh], pj[fresh]] = iteration
            self._suspect_misses[pp[fresh], pj[fresh]] = 0
        sp, sj = np.nonzero(self._suspect >= 0)  # slots beyond a particle's count are always -1
        if len(sp) == 0:
            return
        again = self._last[sp, sj] == iteration
        self._suspect[sp[again], sj[again]] = -1
        counted = ~again & (np.count_nonzero(assoc >= 0, axis=1)[sp] >= MIN_PAIRED)
        sp, sj = sp[counted], sj[counted]
        local = np.einsum("kji,kj->ki", self.rotations[sp], self.means[sp, sj] - self.positions[sp])
        view = self._view.in_sight(local, points)
        mp, mj = sp[view], sj[view]
        self._suspect_misses[mp, mj] += 1
        misses = self._suspect_misses[mp, mj]
        long_runs = misses >= MIN_MISSES
        mp, mj, misses = mp[long_runs], mj[long_runs], misses[long_runs]
        chance = run_log_probability(self._seen[mp, mj], np.zeros(len(mp)), misses)
        gone = chance < self._log_vanished
        if gone.any():
            self._stats["vanished"] += int(np.count_nonzero(mp[gone] == int(np.argmax(self.log_weights))))
            self._drop(mp[gone], mj[gone])

    def _replaced(
        self, near: tuple[np.ndarray, np.ndarray], new_p: np.ndarray, new_slots: np.ndarray, new_points: np.ndarray,
        iteration: int,
    ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """Particle and slot of the landmark each new landmark may have replaced: the nearest one of its
        particle within the search radius, last paired in the last ``SUCCESSION_WINDOW`` iterations and
        not in this one (one per new landmark at most; none for some)."""
        owner, j = candidate_slots(near, new_points)
        p = new_p[owner]
        last = self._last[p, j]
        ok = (j < self.counts[p]) & (last < iteration) & (last >= iteration - SUCCESSION_WINDOW)
        owner, p, j = owner[ok], p[ok], j[ok]
        d2 = np.sum((self.means[p, j] - self.means[p, new_slots[owner]]) ** 2, axis=1)
        close = d2 <= self._search_radius**2
        owner, p, j, d2 = owner[close], p[close], j[close], d2[close]
        order = np.lexsort((d2, owner))
        first = order[np.unique(owner[order], return_index=True)[1]]
        return p[first], j[first]

    def _loop_maps(self, particle: int, iteration: int) -> tuple[np.ndarray, np.ndarray]:
        """Slots of ``particle``'s static young landmarks (started within ``YOUNG_ITERATIONS``) and old
        ones (seen at least twice, not within ``OLD_ITERATIONS``) at ``iteration``."""
        n = int(self.counts[particle])
        static = ~self._moving[particle, :n]
        young = np.flatnonzero(static & (self._born[particle, :n] >= iteration - YOUNG_ITERATIONS))
        old = np.flatnonzero(
            static & (self._last[particle, :n] < iteration - OLD_ITERATIONS) & (self._seen[particle, :n] >= 2)
        )
        return young, old

    def _close_loop(self) -> None:
        """Register the best particle's young landmarks onto its old ones
        (:func:`relpoint.estimators._loop_closure.register_loop`, within twice the search radius, at
        two points' noise); on a loop, move every particle's pose and the landmarks it saw within
        ``OLD_ITERATIONS`` by the offset, and merge each particle's young landmarks that then lie on
        an old one into it (the old landmark counts as seen now)."""
        iteration = self._stats["iterations"]
        if iteration <= OLD_ITERATIONS:
            return
        best = int(np.argmax(self.log_weights))
        young, old = self._loop_maps(best, iteration)
        if len(young) < MIN_SUPPORT or len(old) < MIN_SUPPORT:
            return
        tolerance = LOOP_TOLERANCE_SIGMAS * math.sqrt(2.0 * self._Q[0, 0])
        loop = register_loop(self.means[best, young], self.means[best, old], tolerance, 2.0 * self._search_radius)
        if loop is None:
            return
        slot = np.arange(self._capacity)[None, :]
        lately = (self._last >= iteration - OLD_ITERATIONS) & (slot < self.counts[:, None])
        self.positions = self.positions + loop.shift
        self._recent.shift(loop.shift)
        self.means += np.where(lately[:, :, None], loop.shift, 0.0)
        particles, slots = [], []
        for p in range(self.config.particles):
            young, old = self._loop_maps(p, iteration)
            if not len(young) or not len(old):
                continue
            distance, nearest = cKDTree(self.means[p, old]).query(self.means[p, young], distance_upper_bound=tolerance)
            on_old = np.isfinite(distance)
            self._last[p, old[nearest[on_old]]] = iteration
            particles.append(np.full(int(on_old.sum()), p))
            slots.append(young[on_old])
            if p == best:
                self._stats["loop_landmarks_merged"] += int(on_old.sum())
        if particles:
            self._drop(np.concatenate(particles), np.concatenate(slots))
        self._stats["loop_closures"] += 1
        logger.info(
            "loop closed at iteration %d: moved %.2f m (%d of %d young landmarks agree, %.1f by chance)",
            iteration, float(np.linalg.norm(loop.shift)), loop.support, loop.candidates, loop.expected,
        )  # fmt: skip

    def _drop(self, particles: np.ndarray, slots: np.ndarray) -> None:
        """Remove landmark ``slots[k]`` from particle ``particles[k]``'s map; the later slots move down."""
        for p in np.unique(particles).tolist():
            count = int(self.counts[p])
            keep = np.ones(count, dtype=bool)
            keep[slots[particles == p]] = False
            for attr in _SLOT_ARRAYS:
                array = getattr(self, attr)
                array[p, : int(keep.sum())] = array[p, :count][keep]
            self.counts[p] = int(keep.sum())
            self._suspect[p, self.counts[p] : count] = _SLOT_ARRAYS["_suspect"]  # the freed slots' stale copies

    def _ensure_capacity(self, size: int) -> None:
        if size <= self._capacity:
            return
        capacity = max(size, 2 * self._capacity)
        extra = capacity - self._capacity
        for attr, empty in _SLOT_ARRAYS.items():
            array = getattr(self, attr)
            grown = np.full((array.shape[0], extra, *array.shape[2:]), empty, dtype=array.dtype)
            setattr(self, attr, np.concatenate([array, grown], axis=1))
        self._capacity = capacity
        self._spare_slot_arrays.clear()  # of the old capacity

    # ---------------------------------------------------------------------------------- resampling

    def _resample_if_degenerate(self) -> None:
        w = self.weights
        n = self.config.particles
        if 1.0 / np.sum(w**2) >= self.config.resample_threshold * n:
            return
        index = low_variance_resample(w, self._rng)
        for attr in _PARTICLE_ARRAYS:
            array = getattr(self, attr)
            if attr not in _SLOT_ARRAYS:
                setattr(self, attr, array[index])
                continue
            # The landmark arrays (tens of MB at thousands of landmarks) are gathered into a spare array
            # of their shape, and the old one kept as the next spare: gathered into fresh memory, their
            # first-touch page faults cost more than the copy (14 -> 5 ms an iteration at 2,500 landmarks).
            # Only the slots some particle has used are copied: beyond them every slot array holds its
            # empty value in every particle, and so does a spare, which only arrays of the same empty
            # value share (means and covariances, turned and shifted with their particle by fixes,
            # are never read there).
            empty = _SLOT_ARRAYS[attr]
            key = (array.shape, array.dtype.str, empty)
            spare = self._spare_slot_arrays.pop(key, None)
            if spare is None:
                spare = np.full_like(array, empty)
            used = self._slots_used
            for row, source in enumerate(index.tolist()):  # rows: a gather into part of each is buffered
                spare[row, :used] = array[source, :used]
            setattr(self, attr, spare)
            self._spare_slot_arrays[key] = array
        self.log_weights = np.full(n, -math.log(n))
        self._stats["resamples"] += 1


SPEC = EstimatorSpec(
    name="fastslam",
    description="FastSLAM 1.0/2.0: particles over the sensor pose with per-particle 3x3 landmark EKFs",
    config_class=FastSlamConfig,
    estimator_class=FastSlam,
    input_kind=POINTS,
    uses=frozenset({ODOMETRY, FIX}),
    noise_adaptive=True,
)
