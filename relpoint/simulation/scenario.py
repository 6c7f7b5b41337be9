"""Simulated point-landmark runs: ground truth, noisy observations, odometry and position fixes.

Implements the simulation of Kraut, *A Relative Point Algorithm* (section III): landmarks scattered
around a figure-eight path, the untransformed points inside a viewing frustum observed each iteration
with white Gaussian noise, optionally moving ("dynamic") landmarks and clutter; plus odometry and
low-rate absolute fixes ("buoys", Zhang, Milios and Gu, *General Concept of 3D SLAM*, section 5).

Every random draw comes from child streams of one :class:`numpy.random.SeedSequence`, one stream per
concern, so enabling odometry or fixes does not change the observations of the same seed.
"""

from __future__ import annotations

from collections.abc import Iterator
from decimal import Decimal

import numpy as np

from relpoint.errors import UsageError
from relpoint.geometry import FloatArray, body_twist
from relpoint.simulation import movers, paths
from relpoint.simulation.config import MAX_STAMP_S, SceneView, SimulationConfig
from relpoint.types import (
    GroundTruthLandmarks,
    OdometryMeasurement,
    PointObservation,
    PositionFix,
    SimulatedStep,
    Trajectory,
)

STATIONARY_ITERATIONS = 900
#: ``figure8-gaps``: stretches of the pass (phase intervals, cycles) with no landmarks, where a local
#: SLAM loses its features and breaks into segments (General Concept of 3D SLAM, section 6, Fig. 10).
#: Each is 10 % of a pass (120 m by default); with the default 70 m range about 50 m of it has no
#: landmark in view. They lie on the far ends of the two loops, away from the middle crossing.
GAP_PHASES = ((0.20, 0.30), (0.70, 0.80))
#: ``figure8-gaps``: pose of the run's start in the survey frame (``world``) that the fixes define:
#: a local SLAM starting at the identity is offset and turned from it, as a robot launched at an
#: unknown place is (position in metres, heading in degrees about z).
GAPS_START_POSITION = (60.0, -40.0, -15.0)
GAPS_START_HEADING = 35.0
#: Random streams, one per concern; new ones go at the end so the older streams (and logs) stay the same.
_STREAMS = ("landmarks", "dynamics", "noise", "clutter", "odometry", "fixes", "movers")


class Simulation:
    """A simulated run, produced lazily step by step (see :meth:`steps`).

    Attributes
    ----------
    config: the settings.
    ground_truth: true sensor trajectory ``T_world_sensor``, one pose per iteration.
    landmarks: true landmarks at the first stamp (moving ones at their first position).
    """

    def __init__(self, config: SimulationConfig) -> None:
        self.config = config
        scene = config.scene()  # the lengths at the configured scale
        self._scene = scene
        rngs = _random_streams(config.seed)
        self._poses = _sensor_poses(scene)
        self.stamps_ns = _stamps_ns(config, len(self._poses))
        self.ground_truth = Trajectory.from_matrices(self.stamps_ns, self._poses)
        self._centres = _scatter_landmarks(scene, rngs["landmarks"])
        n = len(self._centres)
        dyn_rng = rngs["dynamics"]
        self._dynamic = np.zeros(n, dtype=bool)
        n_dynamic = int(round(config.dynamic * n))
        if n_dynamic:
            self._dynamic[dyn_rng.choice(n, size=n_dynamic, replace=False)] = True
        # Oscillation is drawn for every landmark (the draws of the original simulator, whatever the motion).
        self._oscillation = movers.OscillatingMovers(
            dyn_rng.uniform(-scene.dynamic_amplitude, scene.dynamic_amplitude, (n, 3))[self._dynamic],
            dyn_rng.uniform(20.0, 60.0, (n, 3))[self._dynamic],
            dyn_rng.uniform(0.0, 2.0 * np.pi, (n, 3))[self._dynamic],
        )
        self._travel = None
        if config.mover_motion != "oscillate":
            self._travel = movers.draw_travelling_movers(
                rngs["movers"], config.mover_motion, n_dynamic, config.mover_speed, len(self._poses)
            )
        self.landmarks = GroundTruthLandmarks(
            self.landmark_positions(self.stamps_ns[0]), np.arange(n, dtype=np.int64), self._dynamic
        )

    def __len__(self) -> int:
        return len(self._poses)

    def landmark_positions(self, stamp_ns: int) -> FloatArray:
        """True positions (M, 3) of every landmark at ``stamp_ns``, in ``world``.

        Oscillating movers move with time; travelling ones by iteration (the stamp's, counted from the
        first stamp at the configured rate).
        """
        positions = self._centres.copy()
        d = self._dynamic
        if self._travel is None:
            positions[d] += self._oscillation.excursion(stamp_ns * 1e-9)
        else:
            period_ns = int(round(1e9 / self.config.rate))
            k = max(0, int(round((int(stamp_ns) - int(self.stamps_ns[0])) / period_ns)))
            # A travelling mover starts where an oscillating one would have been at the first stamp.
            positions[d] += self._oscillation.excursion(self.stamps_ns[0] * 1e-9) + self._travel.displacement(k)
        return positions

    def steps(self) -> Iterator[SimulatedStep]:
        """Yield every iteration in order; the draws are the same on every call."""
        config = self._scene
        rngs = _random_streams(config.seed)
        half_h = np.deg2rad(config.fov_horizontal) / 2.0
        half_v = np.deg2rad(config.fov_vertical) / 2.0
        dt = 1.0 / config.rate
        angular_sigma = (
            config.odometry_angular_noise
            if config.odometry_angular_noise is not None
            else (config.odometry_noise or 0.0) / 10.0
        )
        if config.odometry_noise is not None:
            following = np.concatenate([self._poses[1:], self._next_pose()[None]])
            true_linear, true_angular = body_twist(self._poses, following, dt)
        for k, (stamp_ns, T_world_sensor) in enumerate(zip(self.stamps_ns, self._poses, strict=True)):
            landmarks_world = self.landmark_positions(int(stamp_ns))
            R = T_world_sensor[:3, :3]
            in_sensor = (landmarks_world - T_world_sensor[:3, 3]) @ R
            visible = _in_frustum(in_sensor, config.min_range, config.range, half_h, half_v)
            ids = np.flatnonzero(visible)
            points = in_sensor[ids] + rngs["noise"].normal(0.0, config.noise, (len(ids), 3))
            n_clutter = int(rngs["clutter"].poisson(config.clutter)) if config.clutter > 0 else 0
            if n_clutter:
                clutter = _sample_frustum(rngs["clutter"], n_clutter, config.min_range, config.range, half_h, half_v)
                points = np.vstack([points, clutter])
                ids = np.concatenate([ids, np.full(n_clutter, -1)])
            observation = PointObservation(int(stamp_ns), points, ids, "sensor")

            odometry = None
            if config.odometry_noise is not None:
                linear = true_linear[k] + rngs["odometry"].normal(0.0, config.odometry_noise, 3)
                angular = true_angular[k] + rngs["odometry"].normal(0.0, angular_sigma, 3)
                covariance = np.diag([config.odometry_noise**2] * 3 + [angular_sigma**2] * 3)
                odometry = OdometryMeasurement(int(stamp_ns), linear, angular, covariance)

            fix = None
            if config.fix_every and k % config.fix_every == 0:
                position = T_world_sensor[:3, 3] + rngs["fixes"].normal(0.0, config.fix_noise, 3)
                fix = PositionFix(int(stamp_ns), position, np.eye(3) * config.fix_noise**2)
            yield SimulatedStep(k, int(stamp_ns), T_world_sensor, observation, odometry, fix)

    def _next_pose(self) -> FloatArray:
        """The pose one step past the end of the run (so the last odometry has a target)."""
        return _sensor_poses(self._scene, extra=1)[-1]


def _random_streams(seed: int) -> dict[str, np.random.Generator]:
    """One independent generator per concern, all children of ``seed``."""
    children = np.random.SeedSequence(seed).spawn(len(_STREAMS))
    return {name: np.random.default_rng(child) for name, child in zip(_STREAMS, children, strict=True)}


def _stamps_ns(config: SimulationConfig, n: int) -> np.ndarray:
    """The ``n`` stamps (ns) from ``start_time`` at ``rate``. The start is the decimal the setting shows
    (its shortest repr, as the log's metadata records it) in ns: ``start_time * 1e9`` in floats is off by up
    to a few hundred ns at today's epoch seconds (1700000000.000001 gave ...000001024)."""
    start_ns = int((Decimal(repr(config.start_time)) * 1_000_000_000).to_integral_value())
    period_ns = int(round(1e9 / config.rate))
    last_s = (start_ns + period_ns * (n - 1)) // 1_000_000_000
    if last_s > MAX_STAMP_S:
        latest = MAX_STAMP_S - period_ns * (n - 1) // 1_000_000_000
        raise UsageError(
            f"simulation setting start_time {config.start_time!r} puts the last of {n} iterations at {last_s} s, "
            f"beyond the {MAX_STAMP_S} s a ROS stamp holds",
            f"give a start_time of at most {max(latest, 0)}",
        )
    return start_ns + period_ns * np.arange(n, dtype=np.int64)


def _iteration_count(config: SceneView) -> int:
    if config.iterations is not None:
        return config.iterations
    if config.scenario in ("figure8", "figure8-gaps"):
        per_pass = paths.figure8_length(config.radius, config.climb) / config.step
        return max(1, int(round(per_pass * config.passes)))
    if config.scenario == "corridor":
        return max(1, int(round(config.length / config.step)))
    if config.scenario == "spiral":
        return max(1, int(round(paths.spiral_length(config.radius, config.climb) * config.passes / config.step)))
    return STATIONARY_ITERATIONS


def _sensor_poses(config: SceneView, extra: int = 0) -> FloatArray:
    """True poses ``T_world_sensor`` (N, 4, 4) of every iteration (plus ``extra`` beyond the end)."""
    n = _iteration_count(config) + extra
    if config.scenario == "stationary":
        return np.repeat(np.eye(4)[None], n, axis=0)
    if config.scenario in ("figure8", "figure8-gaps"):
        pass_length = paths.figure8_length(config.radius, config.climb)
        positions, tangents = paths.figure8(np.arange(n) * config.step / pass_length, config.radius, config.climb)
    elif config.scenario == "spiral":
        positions, tangents = paths.spiral(np.arange(n) * config.step, config.radius, config.climb)
    else:
        positions, tangents = paths.corridor(np.arange(n) * config.step)
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :3] = paths.orientations_from_tangents(tangents)
    poses[:, :3, 3] = positions
    poses[:, 3, 3] = 1.0
    if config.scenario == "figure8-gaps":
        poses = _T_survey_start() @ poses
    return poses


def _T_survey_start() -> FloatArray:
    """``figure8-gaps``: the start pose in the survey frame (4, 4), see :data:`GAPS_START_POSITION`."""
    heading = np.deg2rad(GAPS_START_HEADING)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]]
    T[:3, 3] = GAPS_START_POSITION
    return T


def _scatter_landmarks(config: SceneView, rng: np.random.Generator) -> FloatArray:
    """Landmark centres (M, 3) in ``world``: ``density`` per 100 m of path, scattered around it."""
    if config.scenario == "stationary":
        # The fixed viewpoint looks along +x: put about `density` points inside its frustum.
        count = max(3, int(round(config.density)))
        half_h = np.deg2rad(config.fov_horizontal) / 2.0
        half_v = np.deg2rad(config.fov_vertical) / 2.0
        return _sample_frustum(rng, count, max(config.min_range, 0.1 * config.range), config.range, half_h, half_v)
    if config.scenario in ("figure8", "figure8-gaps"):
        pass_length = paths.figure8_length(config.radius, config.climb)
        count = max(3, int(round(config.density * pass_length / 100.0)))
        phase = rng.uniform(0.0, 1.0, count)
        base, tangents = paths.figure8(phase, config.radius, config.climb)
    elif config.scenario == "spiral":
        length = paths.spiral_length(config.radius, config.climb) * config.passes
        count = max(3, int(round(config.density * length / 100.0)))
        base, tangents = paths.spiral(rng.uniform(0.0, length, count), config.radius, config.climb)
    else:
        length = config.length + config.range  # landmarks ahead of the end stay in view to the last step
        count = max(3, int(round(config.density * length / 100.0)))
        base, tangents = paths.corridor(rng.uniform(-0.1 * config.range, length, count))
    frames = paths.orientations_from_tangents(tangents)
    lateral = rng.uniform(-config.spread_lateral, config.spread_lateral, count)
    vertical = rng.uniform(-config.spread_vertical, config.spread_vertical, count)
    centres = base + frames[:, :, 1] * lateral[:, None] + frames[:, :, 2] * vertical[:, None]
    if config.scenario == "figure8-gaps":
        # Same draws as the figure eight, then the gap stretches emptied (at least three landmarks kept).
        in_gap = np.zeros(count, dtype=bool)
        for start, end in GAP_PHASES:
            in_gap |= (phase >= start) & (phase < end)
        keep = ~in_gap if np.count_nonzero(~in_gap) >= 3 else np.ones(count, dtype=bool)
        centres = centres[keep] @ _T_survey_start()[:3, :3].T + _T_survey_start()[:3, 3]
    return centres


def _in_frustum(points: FloatArray, near: float, far: float, half_h: float, half_v: float) -> np.ndarray:
    """Mask of sensor-frame points (x forward) inside the viewing frustum."""
    distance = np.linalg.norm(points, axis=1)
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    elevation = np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))
    return (distance >= near) & (distance <= far) & (np.abs(azimuth) <= half_h) & (np.abs(elevation) <= half_v)


def _sample_frustum(
    rng: np.random.Generator, count: int, near: float, far: float, half_h: float, half_v: float
) -> FloatArray:
    """``count`` points uniform in volume inside the frustum, sensor frame (x forward)."""
    radius = np.cbrt(rng.uniform(near**3, far**3, count))
    azimuth = rng.uniform(-half_h, half_h, count)
    # Uniform in solid angle over the elevation band.
    elevation = np.arcsin(rng.uniform(np.sin(-half_v), np.sin(half_v), count))
    return np.stack(
        [
            radius * np.cos(elevation) * np.cos(azimuth),
            radius * np.cos(elevation) * np.sin(azimuth),
            radius * np.sin(elevation),
        ],
        axis=1,
    )


def simulate(config: SimulationConfig) -> Simulation:
    """Set up a simulated run from ``config`` (see :class:`Simulation`)."""
    return Simulation(config)
