"""Settings of the EKF-SLAM estimator (:mod:`relpoint.estimators.ekf`).

A module of their own, importable without scipy: ``relpoint batch`` checks a plan's parameters
against them before any worker has started, and ``relpoint config`` lists them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

from relpoint.errors import UsageError
from relpoint.estimators._fix_frame import FixFusionSettings
from relpoint.estimators._landmark_motion import MovingLandmarkSettings
from relpoint.estimators._noise import MotionNoiseSettings
from relpoint.settings import setting

MOTION_MODELS = ("constant_velocity", "constant_position")
ASSOCIATIONS = ("nn", "jcbb", "known")
FIX_ALIGNMENTS = ("rigid", "none")


#: Pairs an iteration needs for the rigid consensus (``EkfConfig.rigid_consensus``) to judge them.
CONSENSUS_MIN_PAIRS = 6


@dataclass(frozen=True)
class EkfConfig(MotionNoiseSettings, MovingLandmarkSettings, FixFusionSettings):
    """Settings of the EKF-SLAM estimator. Metres, radians, seconds."""

    settings_name: ClassVar[str] = "ekf"
    #: What ``relpoint config`` says about the settings that matter.
    key_settings: ClassVar[dict[str, str]] = {
        "observation_sigma": "per-axis point noise (m); sets the measurement covariance and so both gates. "
        "Unset, it is estimated from the first observations (0.3 m on the simulator, about 1 cm for a depth "
        "camera at 2 m); set it when the estimate is off (relpoint run prints it in run.json).",
        "gate_probability, new_landmark_probability": "chi-square gates, relative to the covariance: they "
        "hold at any scale once observation_sigma is right.",
        "motion, linear_acceleration_noise, angular_acceleration_noise": "how far the pose may move between "
        "observations without odometry (m/s^2, rad/s^2): the defaults suit a vehicle; a hand-held camera "
        "wants less linear and more angular acceleration.",
    }
    settings_hint: ClassVar[str] = "see `relpoint config --estimator ekf` for the parameters"

    association: str = setting("nn", choices=ASSOCIATIONS)
    """Data association: ``nn`` (nearest neighbour in Mahalanobis distance), ``jcbb`` (joint
    compatibility branch and bound) or ``known`` (the log's ``id`` field; diagnosis only)."""
    motion: str = setting("constant_velocity", choices=MOTION_MODELS)
    """Process model between observations when no odometry is held: ``constant_velocity`` (twist in
    the state, driven by white acceleration noise) or ``constant_position`` (MRPT's default)."""
    observation_sigma: float | None = setting(None, low=1e-6, high=1e3)
    """Standard deviation of a point measurement, per axis (m). Unset (the default): ``relpoint run``
    estimates it from the first observations of the log (:mod:`relpoint.estimators._noise`), so the
    same defaults hold for a depth camera at 2 m (about 0.01 m) and the simulator at 70 m (0.3 m); an
    ``EkfSlam`` built directly, without ``SPEC.factory``, takes the simulator's 0.3 m. It sets the
    measurement covariance and, through it, the size of both gates below: the setting that matters."""
    gate_probability: float = setting(0.99, above=0, below=1)
    """Chi-square probability of the Mahalanobis validation gate (eq. 14-16)."""
    new_landmark_probability: float = setting(0.9999, above=0, below=1)
    """A point starts a landmark only if it lies outside every landmark's gate of this probability;
    points between the two gates are discarded (a true landmark's point falls outside the 0.99 gate
    one time in a hundred, and would otherwise start a duplicate)."""
    min_observations: int = setting(2, low=1, high=1_000_000)
    """The map (``map.ply``, ``map.csv``, the result's landmarks) holds the landmarks seen at least this
    many times; the filter keeps the others in its state. A landmark seen once has told the filter
    nothing, and a front-end's wild points are seen once: on a log with 5 % of its points 5 m off,
    2,329 of the 2,732 landmarks were such points (landmark RMSE 8.2 m against 0.020 m for the rest).
    1: every landmark."""
    rigid_consensus: bool = True
    """After association, the pairs that the rigid motion shared by most of them does not explain
    (RANSAC, :func:`relpoint.geometry.rigid_consensus`; the tolerance is the validation gate's radius
    over the observation noise and the landmark's own uncertainty) are left out of the update: a real
    keypoint that slid along an edge or whose depth drifted still passes its own gate, which widens
    with the pose uncertainty that all pairs share, and pulls the pose and map. Needs
    ``CONSENSUS_MIN_PAIRS`` pairs: with fewer, a pair that disagrees cannot be told from a
    consensus that is wrong."""
    mover_radius_sigmas: float = setting(0.0, low=0, high=1e6)
    """A point that matches no landmark within this many ``observation_sigma`` of a landmark seen
    lately and not matched now is that landmark moving: it leaves the map and is followed as a
    dynamic point instead of starting duplicates (``relpoint.estimators._movers``). 0 (the default)
    turns this off: 10 removes nearly every duplicate of fast movers and improves Starry Night, but
    costs the oscillating-mover figure eight 20 % of position accuracy (docs/robustness.md)."""
    position_noise: float = setting(0.10, low=0, high=1e3)
    """Constant-position model: position noise per iteration, per axis (m; MRPT default 0.10)."""
    quaternion_noise: float = setting(0.05, low=0, high=1)
    """Constant-position model: noise per quaternion component per iteration (MRPT default 0.05;
    applied as 2 x this in radians per axis, since a small rotation d has quaternion part d/2)."""
    collapse_noise_scale: float = setting(16.0, low=1, high=1e3)
    """When an iteration's association collapses (fewer than half the landmarks the last observation
    saw pair, and more points would start landmarks than pair: the motion changed faster than the
    process noise allows, as when a turn starts at once), its prediction is taken again with 2, 4,
    ... up to this many times the standard deviation of the process noise (motion model or
    odometry), and the first association that pairs half of them is kept, before any landmark
    starts. ``association_widened`` in ``run.json`` counts those iterations, and
    ``association_collapsed`` (with a warning) those that collapse all the same. 1: no retry."""
    initial_speed_sigma: float = setting(10.0, low=0, high=1e4)
    """Constant-velocity model: prior standard deviation of the initial linear velocity (m/s). Where the first interval
    moves the points by more than half their spacing (a low rate, a fast platform), ``relpoint run``
    starts instead from the twist the first two observations register into (``initial_twist`` in
    ``run.json``; :func:`relpoint.estimators._noise.starting_twist`)."""
    initial_turn_rate_sigma: float = setting(0.3, low=0, high=1e2)
    """Constant-velocity model: prior standard deviation of the initial angular velocity (rad/s); as ``initial_speed_sigma``."""
    initial_orientation_sigma: float = setting(0.0, low=0, high=10)
    """``fix_alignment="none"`` only: prior standard deviation of the initial orientation (rad per
    axis) when a position fix places the start: 0 assumes the sensor starts with its axes along the
    fix frame's."""
    fix_alignment: str = setting("rigid", choices=FIX_ALIGNMENTS)
    """How position fixes (``/fix``) enter: ``rigid`` runs in the local frame until at least three
    non-collinear fixes pin it, fits the rigid transform local -> fix frame to the local positions
    and the Lagrange-interpolated fixes, moves the state (and the fit's uncertainty) into the fixes'
    frame, then fuses every later fix as a position measurement; ``none`` fuses every fix at once
    in one frame (the first fix places the start, the orientation prior is
    ``initial_orientation_sigma``)."""
    fix_drift: float = setting(0.0, low=0, high=10)
    """``rigid``: before each fix, the pose and the landmarks seen within ``fix_window`` iterations
    may have drifted together in ``world`` by this much per metre travelled since the previous fix
    (m/m, per axis): a common translation added to their covariance, which the fix then corrects
    as one (the filter's own covariance does not show the drift of a map turned in a stretch
    without landmarks). 0 adds none (the default: on figure8-gaps 0.1 lowers the ATE from 2.7 to
    2.2 m but raises the landmark RMSE from 2.1 to 9.5 m)."""
    fix_window: int = setting(100, low=0, high=1_000_000)
    """``rigid``: landmarks seen within this many iterations move with the pose under ``fix_drift``."""
    jcbb_max_nodes: int = setting(5000, low=1, high=10_000_000)
    """JCBB search budget per iteration, in nodes; the best hypothesis so far is used when it runs out."""
    jcbb_max_seconds: float = setting(1.0, low=0, high=1e6)
    """JCBB search budget per iteration, in wall-clock seconds (0: nodes only). When either budget
    runs out the best hypothesis so far is used, a warning says so and ``jcbb_gave_up`` in
    ``run.json`` counts the iterations; a run stopped by the clock depends on the machine's speed."""
    smooth_trajectory: bool = setting(True)
    """When the log ends, place every past position again on the final map, from the pairs the
    filter made at that iteration, and smooth the corrections over time
    (:mod:`relpoint.estimators._trajectory_smoothing`): what the filter learnt later (a closed loop,
    the fixes) then corrects the positions it had already returned, not only its map; rotations
    stay the filter's. ``smoothing`` in ``run.json`` reports it. Off: the trajectory is the filter's
    own, pose by pose."""

    def at_noise(self, sigma: float) -> EkfConfig:
        """These settings with ``observation_sigma = sigma`` (m)."""
        return dataclasses.replace(self, observation_sigma=sigma)

    def check(self) -> None:
        """A point between the validation gate and the new-landmark gate is discarded: the new-landmark
        gate is the wider one."""
        if self.new_landmark_probability < self.gate_probability:
            raise UsageError(
                f"ekf setting new_landmark_probability must be at least gate_probability ({self.gate_probability}), "
                f"got {self.new_landmark_probability}"
            )
