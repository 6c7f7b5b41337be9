"""FastSLAM: low-variance resampling, normalised weights, determinism by seed, association and new
landmarks, and short simulated runs of both variants with error bounds a regression would break."""

from __future__ import annotations

import numpy as np
import pytest

from relpoint.errors import UsageError
from relpoint.estimators.fastslam import SPEC, FastSlam, FastSlamConfig, low_variance_resample
from relpoint.geometry import invert_pose, transform_points
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import PointObservation
from tests.conftest import run_accuracy

DT_NS = 100_000_000


def _run(config: FastSlamConfig, seed: int, iterations: int, **sim_options: object) -> dict[str, float]:
    """Run FastSLAM on the figure eight; errors in the frame of the first true pose (where it starts)."""
    sim = simulate(SimulationConfig(density=25, noise=0.3, iterations=iterations, seed=0, **sim_options))  # type: ignore[arg-type]
    slam = FastSlam(config, np.random.default_rng(seed))
    T_first_world = invert_pose(sim.ground_truth.matrices()[0])
    errors = []
    for step in sim.steps():
        if step.odometry is not None:
            slam.add_odometry(step.odometry)
        pose = slam.step(step.observation)
        assert slam.weights.sum() == pytest.approx(1.0, abs=1e-12)
        truth = (T_first_world @ step.T_world_sensor)[:3, 3]
        errors.append(np.linalg.norm(np.array(pose.position) - truth))
    return run_accuracy(errors, slam.landmark_map(), transform_points(T_first_world, sim.landmarks.positions))


# ----------------------------------------------------------------------------------------- config


@pytest.mark.parametrize(
    "options",
    [
        {"variant": "3.0"},
        {"particles": 0},
        {"observation_sigma": -0.1},
        {"new_landmark_probability": 1.0},
        {"resample_threshold": 1.5},
        {"search_radius": 0.0},
        {"start_landmark_probability": 0.999},  # below new_landmark_probability
        {"fix_alignment": "none"},
    ],
)
def test_config_rejects_bad_values(options: dict[str, object]) -> None:
    with pytest.raises(UsageError):
        FastSlamConfig(**options)  # type: ignore[arg-type]


def test_config_round_trips_and_spec_builds() -> None:
    config = FastSlamConfig.from_mapping({"variant": "1.0", "particles": 7, "observation_sigma": 0.3})
    assert FastSlamConfig.from_mapping(config.to_dict()) == config
    with pytest.raises(UsageError):
        FastSlamConfig.from_mapping({"particle_count": 7})
    slam = SPEC.factory(config, np.random.default_rng(0))
    assert isinstance(slam, FastSlam) and len(slam.weights) == 7
    assert SPEC.name == "fastslam" and SPEC.needs == frozenset({"points"})


# ------------------------------------------------------------------------------------ resampling


def test_low_variance_resampling_is_proportional_and_seeded() -> None:
    weights = np.array([0.5, 0.25, 0.25, 0.0])
    for seed in range(20):
        index = low_variance_resample(weights, np.random.default_rng(seed))
        # Systematic resampling copies particle i either floor(N w_i) or ceil(N w_i) times.
        assert np.bincount(index, minlength=4).tolist() == [2, 1, 1, 0]
    weights = np.random.default_rng(1).dirichlet(np.ones(100))
    first = low_variance_resample(weights, np.random.default_rng(5))
    again = low_variance_resample(weights, np.random.default_rng(5))
    other = low_variance_resample(weights, np.random.default_rng(6))
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    counts = np.bincount(first, minlength=100)
    assert np.all(np.abs(counts - 100 * weights) < 1.0)


def test_weights_stay_normalised_and_resampling_resets_them() -> None:
    sim = simulate(SimulationConfig(density=25, noise=0.3, iterations=40, seed=2))
    slam = FastSlam(FastSlamConfig(particles=20), np.random.default_rng(0))
    resamples = 0
    for step in sim.steps():
        slam.step(step.observation)
        w = slam.weights
        assert w.sum() == pytest.approx(1.0, abs=1e-12)
        assert np.all(w >= 0)
        if slam.summary().get("resamples", 0) > resamples:
            resamples = slam.summary()["resamples"]
            np.testing.assert_allclose(w, 1.0 / 20)
    assert resamples > 0


def test_runs_are_deterministic_by_seed() -> None:
    sim = simulate(SimulationConfig(density=25, noise=0.3, iterations=30, seed=4))

    def run(seed: int) -> tuple[np.ndarray, np.ndarray]:
        slam = FastSlam(FastSlamConfig(particles=15), np.random.default_rng(seed))
        positions = np.array([slam.step(step.observation).position for step in sim.steps()])
        return positions, slam.landmark_map().positions

    first, again, other = run(11), run(11), run(12)
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])
    assert not np.array_equal(first[0], other[0])


# ----------------------------------------------------------------------------------- association


@pytest.mark.parametrize("variant", ["1.0", "2.0"])
def test_points_pair_with_their_landmark_or_start_new_ones(variant: str) -> None:
    slam = FastSlam(FastSlamConfig(variant=variant, particles=5, pose_noise=0.0), np.random.default_rng(0))
    slam.step(PointObservation(0, [[10.0, 0.0, 0.0], [0.0, 10.0, 0.0]], [0, 1]))
    assert slam.counts.tolist() == [2] * 5
    # Same stamp (no motion): one point near landmark 0, one far from everything.
    slam.step(PointObservation(0, [[10.1, 0.0, 0.0], [0.0, 20.0, 0.0]], [0, 2]))
    assert slam.counts.tolist() == [3] * 5
    landmarks = slam.landmark_map()
    assert landmarks.observations.tolist() == [2, 1, 1]
    assert landmarks.gt_id.tolist() == [0, 1, 2]
    # The landmark EKF averages the two sightings with equal covariances.
    np.testing.assert_allclose(landmarks.positions[0], [10.05, 0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize("variant", ["1.0", "2.0"])
def test_point_between_the_gates_is_discarded(variant: str) -> None:
    slam = FastSlam(FastSlamConfig(variant=variant, particles=4, pose_noise=0.0), np.random.default_rng(0))
    slam.step(PointObservation(0, [[10.0, 0.0, 0.0]], [0]))
    # A once-seen landmark's innovation covariance is 2 Q = 0.18 m^2 per axis, the same as the
    # new-landmark density's: the 0.9999 match gate (d2 < 21.1) ends at 1.95 m, the 1 - 1e-7 start
    # gate (d2 < 35.4) at 2.52 m.
    slam.step(PointObservation(0, [[12.2, 0.0, 0.0]], [0]))
    assert slam.counts.tolist() == [1] * 4 and slam.summary()["discarded"] == 4
    slam.step(PointObservation(0, [[12.8, 0.0, 0.0]], [1]))
    assert slam.counts.tolist() == [2] * 4


# ------------------------------------------------------------------------------- simulated runs


def test_fastslam2_figure_eight_run_stays_accurate() -> None:
    result = _run(FastSlamConfig(particles=30), seed=0, iterations=300)
    # Measured: 0.53 m position and 0.42 m landmark RMSE (0.5-1.1 m over rng seeds 0-3).
    assert result["position_rmse"] < 1.0
    assert result["landmark_rmse"] < 1.0
    assert result["final_error"] < 1.5
    assert result["landmarks"] <= result["distinct"] + 3


def test_fastslam1_with_odometry_stays_accurate() -> None:
    result = _run(FastSlamConfig(variant="1.0", particles=30), seed=0, iterations=200, odometry_noise=0.5)
    # Measured: 0.61 m position and 1.01 m landmark RMSE.
    assert result["position_rmse"] < 1.0
    assert result["landmark_rmse"] < 1.5
    assert result["final_error"] < 2.5
