"""Settings of the FastSLAM estimator (:mod:`relpoint.estimators.fastslam`).

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
from relpoint.estimators._noise import SIMULATOR_SIGMA, MotionNoiseSettings
from relpoint.settings import setting

VARIANTS = ("2.0", "1.0")
FIX_ALIGNMENTS = ("rigid", "ignore")


#: The default search radius in units of the observation noise (5 m at the simulator's 0.3 m).
SEARCH_RADIUS_SIGMAS = 5.0 / SIMULATOR_SIGMA


@dataclass(frozen=True)
class FastSlamConfig(MotionNoiseSettings, MovingLandmarkSettings, FixFusionSettings):
    """Settings of the FastSLAM estimator. Metres, radians, seconds."""

    settings_name: ClassVar[str] = "fastslam"
    #: What ``relpoint config`` says about the settings that matter.
    key_settings: ClassVar[dict[str, str]] = {
        "observation_sigma": "per-axis point noise (m); sets the landmark filters and the new-landmark "
        "likelihood. Unset, it is estimated from the first observations.",
        "search_radius": "landmarks considered for a point (m); unset, 16.7 x observation_sigma (5 m at 0.3 m). "
        "Cost grows with the landmarks inside it.",
        "particles": "accuracy against time: the cost is linear in the particles.",
        "linear_acceleration_noise, angular_acceleration_noise": "the proposal's motion spread between "
        "observations (m/s^2, rad/s^2).",
    }
    settings_hint: ClassVar[str] = "see `relpoint config --estimator fastslam` for the parameters"

    variant: str = setting("2.0", choices=VARIANTS)
    """``2.0`` (proposal includes the points) or ``1.0`` (proposal is the motion model)."""
    particles: int = setting(50, low=1, high=10_000)
    """Number of particles."""
    observation_sigma: float | None = setting(None, low=1e-6, high=1e3)
    """Standard deviation of a point measurement, per axis (m). Unset (the default): ``relpoint run``
    estimates it from the first observations of the log (:mod:`relpoint.estimators._noise`); a
    ``FastSlam`` built directly, without ``SPEC.factory``, takes the simulator's 0.3 m. It sets the
    measurement covariance, the new-landmark likelihood and (unset) ``search_radius``."""
    new_landmark_probability: float = setting(0.9999, above=0, below=1)
    """Sets the new-landmark likelihood: the density of a point at this chi-square quantile of a
    fresh landmark's innovation. A point starts a landmark in a particle when no landmark there
    explains it with a higher likelihood."""
    start_landmark_probability: float = setting(0.9999999, above=0, below=1)
    """A point that no landmark explains starts a landmark only if it also lies outside this wider
    quantile of every candidate landmark; points in between are discarded. Without the band a point
    of a drifted landmark (a loop closure) starts a duplicate that then wins every later association."""
    collapse_noise_scale: float = setting(16.0, low=1, high=1e3)
    """2.0 (and the first step of 1.0): when an iteration's association collapses in the particles
    (on average fewer than half the landmarks the last observation saw pair, and more points would
    start landmarks than pair: the motion changed faster than the proposal's prior allows, as when
    a turn starts at once), it is proposed again from 2, 4, ... up to this many times the prior's
    standard deviation, and the first association that pairs half of them is kept, before any
    landmark starts. ``association_widened`` in ``run.json`` counts those iterations, and
    ``association_collapsed`` (with a warning) those that collapse all the same. 1: no retry."""
    initial_speed_sigma: float = setting(10.0, low=0, high=1e4)
    """Prior standard deviation of the initial linear velocity (m/s). Where the first interval
    moves the points by more than half their spacing (a low rate, a fast platform), ``relpoint run``
    starts instead from the twist the first two observations register into (``initial_twist`` in
    ``run.json``; :func:`relpoint.estimators._noise.starting_twist`)."""
    initial_turn_rate_sigma: float = setting(0.3, low=0, high=1e2)
    """Prior standard deviation of the initial angular velocity (rad/s); as ``initial_speed_sigma``."""
    pose_noise: float = setting(0.01, low=0, high=1e2)
    """Extra position noise per iteration, per axis (m), and the same in radians for orientation;
    keeps the proposal full rank when odometry is perfect. Not derived from the noise: scaled down with
    it, it mended a tabletop seed whose association collapsed (2 mm noise) and cost Starry Night's real
    stereo points their worst of ten seeds (0.12 -> 0.75 m): the proposal needs the spread on real data,
    where the error repeats from frame to frame."""
    resample_threshold: float = setting(0.5, low=0, high=1)
    """Resample when the effective sample size falls below this fraction of the particles."""
    min_observations: int = setting(2, low=1, high=1_000_000)
    """The map (``map.ply``, ``map.csv``, the result's landmarks) holds the best particle's landmarks
    seen at least this many times; the particles keep the others. A front-end's wild points are seen
    once: on a log with 5 % of its points 5 m off, 2,391 of the best particle's 2,810 landmarks were
    such points (landmark RMSE 8.2 m against 0.045 m for the rest). 1: every landmark."""
    search_radius: float | None = setting(None, low=1e-6, high=1e6)
    """Landmarks farther than this from a point (in every particle) are not considered for it (m).
    Unset (the default): ``SEARCH_RADIUS_SIGMAS`` (16.7) times ``observation_sigma``, which is 5 m at
    the simulator's 0.3 m and 0.25 m for a depth camera's 1.5 cm."""
    fix_alignment: str = setting("rigid", choices=FIX_ALIGNMENTS)
    """How position fixes (``/fix``) enter: ``rigid`` runs in the local frame until at least three
    non-collinear fixes pin it, fits the rigid transform local -> fix frame to the mean local
    positions and the Lagrange-interpolated fixes, moves every particle into the fixes' frame (each
    by a transform drawn from the fit's uncertainty), then fuses every later fix in each particle's
    proposal and weights the particles by its likelihood; ``ignore`` leaves the fixes out."""
    fix_drift: float | None = setting(None, low=0, high=10)
    """``rigid``: growth of each particle's position uncertainty in ``world`` per metre travelled
    (m/m, per axis), the drift of the local map that the fixes correct. Unset (the default): measured
    on the fused fixes' innovations, 0.1 until three are in (``relpoint.estimators._drift_rate``;
    ``drift_rate`` in ``run.json``)."""
    close_loops: bool = setting(True)
    """Close loops the particles' drift keeps open (:mod:`relpoint.estimators._loop_closure`): when the
    best particle's landmarks started in the last 50 iterations sit at one offset from landmarks not
    seen for 100, beyond chance, every particle's pose and the landmarks it saw lately move by that
    offset, and each young landmark that then lies on an old one is merged into it. ``loop_closures``
    in ``run.json`` counts them."""
    smooth_trajectory: bool = setting(True)
    """When the log ends, take the fused fixes' jumps out of the trajectory and smooth the
    correction on the fixes (:mod:`relpoint.estimators._fix_smoothing`): each fix moves the filter at
    once, partly by its own noise. The poses returned before the fixes pinned the frame (local, under
    a provisional transform) are placed by the pinning's transform first. ``smoothing`` in
    ``run.json`` reports it. Off, or without fused fixes: the trajectory is the filter's poses as it
    made them. After the pinning, rotations stay the filter's."""
    fix_window: int = setting(100, low=0, high=1_000_000)
    """``rigid``: a fix moves each particle's pose, and the landmarks it saw within this many
    iterations, by the covariance-weighted correction (eq. 31-32)."""

    def at_noise(self, sigma: float) -> FastSlamConfig:
        """These settings with ``observation_sigma = sigma`` (m)."""
        return dataclasses.replace(self, observation_sigma=sigma)

    def check(self) -> None:
        """A point between the new-landmark quantile and the start quantile is discarded: the start
        quantile is the wider one."""
        if self.start_landmark_probability < self.new_landmark_probability:
            raise UsageError(
                "fastslam setting start_landmark_probability must be at least new_landmark_probability "
                f"({self.new_landmark_probability}), got {self.start_landmark_probability}"
            )
