"""Regression test on real data: EKF-SLAM, FastSLAM and Relative Point on UTIAS Starry Night (issue 5).

The log (``../shared/data/starry-night/starry_night.mcap``, see its README) holds stereo-triangulated
landmarks in the left camera's optical frame, /odom twists of that frame and Vicon ground truth. Each
estimator runs over the first :data:`PREFIX` observations (the full 1900 take over a minute for the three
on two cores; docs/results.md reports the full-log figures) and its trajectory (ATE after an SE(3)
alignment) and landmark map (error after the same alignment, mapped fraction) must stay within bounds set
at about 1.5x the values measured when the test was written (listed beside each bound), so a regression
in an estimator, the log reader or the evaluation shows up here.

Settings are scaled to the data: triangulation error of a few centimetres (RMSE 4.6 cm, heavy tail),
landmarks 0.26 m apart at the closest, a camera 0.1 to 1.9 m above them. Relative Point uses no odometry
and cannot place a step with fewer than three points in view (a third of this log, including its first
60 steps), so its bounds are loose: they document where it stands, and catch a crash or a gross drift.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from formats.log import LogReader
from relpoint import pipeline
from relpoint.estimators.ekf import EkfConfig, EkfSlam
from relpoint.estimators.fastslam import FastSlam, FastSlamConfig
from relpoint.estimators.relative_point.estimator import RelativePointConfig, RelativePointEstimator
from relpoint.evaluation import EvaluationSettings, evaluate_trajectory, landmark_metrics
from relpoint.types import GroundTruthLandmarks, OdometryMeasurement, PointObservation, Trajectory
from tests.conftest import shared_data

#: Observations (time steps) of the log the test runs over.
PREFIX = 400


@dataclass(frozen=True)
class StarryNight:
    """The decoded log: estimator inputs in time order, ground-truth trajectory and landmarks."""

    inputs: list[PointObservation | OdometryMeasurement]
    reference: Trajectory
    landmarks: GroundTruthLandmarks


def load(prefix: int | None = PREFIX) -> StarryNight:
    """Read the log; keep the inputs up to (and excluding) observation ``prefix`` (None: all)."""
    reader = LogReader(shared_data("starry-night", "starry_night.mcap"))
    inputs: list[PointObservation | OdometryMeasurement] = []
    poses = []
    landmarks = None
    observations = 0
    for record in reader.records(["points", "odometry", "ground_truth_pose", "ground_truth_landmarks"]):
        if record.role == "ground_truth_pose":
            poses.append(record.value)
        elif record.role == "ground_truth_landmarks":
            landmarks = record.value
        elif prefix is None or observations < prefix:
            inputs.append(record.value)
            observations += record.role == "points"
    assert landmarks is not None
    return StarryNight(inputs, Trajectory.from_poses(poses), landmarks)


def build(name: str, seed: int = 0) -> Any:
    """The estimator ``name`` with the settings this test (and docs/results.md) uses on Starry Night;
    ``seed`` draws FastSLAM's particles."""
    if name == "ekf":
        return EkfSlam(EkfConfig(observation_sigma=0.05))
    if name == "fastslam":
        return FastSlam(
            FastSlamConfig(observation_sigma=0.05, search_radius=0.5, particles=20), np.random.default_rng(seed)
        )
    if name == "relpoint":
        return RelativePointEstimator(
            RelativePointConfig(
                match_bound=0.1, global_match_bound=0.15, min_basis_spread=0.1, merge_bound=0.1,
                trim_floor=0.05, spread_floor=0.02, collinear_tolerance=0.01, creation_delay=2, loop_search=0.75,
            )
        )  # fmt: skip
    raise ValueError(name)


def evaluate(name: str, data: StarryNight, seed: int = 0) -> dict[str, float]:
    """Run estimator ``name`` over ``data``; ATE (SE(3)-aligned) and landmark figures."""
    result = pipeline.run(data.inputs, build(name, seed))
    evaluation = evaluate_trajectory(
        data.reference, result.trajectory, EvaluationSettings(align="se3", rpe=False, kitti=False)
    )
    landmarks = landmark_metrics(result.landmarks, data.landmarks, alignment=evaluation.alignment).summary
    return {
        "poses": float(len(result.trajectory)),
        "ate_rmse": evaluation.summary["ate_rmse"],
        "rot_rmse_deg": evaluation.summary["ape_rot_deg_rmse"],
        "lm_rmse": landmarks["lm_err_aligned_rmse"],
        "lm_mapped_fraction": landmarks["lm_mapped_fraction"],
        "lm_count": landmarks["lm_count"],
        "seconds": float(result.seconds.sum()),
    }


@pytest.fixture(scope="module")
def starry_night() -> StarryNight:
    return load()


# name: (ATE RMSE m, rotation RMSE deg, landmark RMSE m, smallest mapped fraction), about 1.5x the figures
# measured over the first 400 observations (ATE, rotation, landmark RMSE, mapped fraction):
#   ekf       0.117 m,  9.5 deg, 0.280 m, 0.95  (later code: 0.167 m, 8.9 deg, 0.222 m; with the trajectory
#             smoothed on the final map 0.134 m, 9.0 deg, 0.211 m, and 17 deg before wrong fits were left out)
#   fastslam  0.155 m, 16.5 deg, 0.544 m, 1.00  (before its discard band: 0.192 m, 42.8 deg, 0.341 m);
#             it is bounded by the median over particle seeds 0-4, since one seed is a coin toss: over
#             seeds 0-5 the rotation RMSE ran 16.5-28.5 deg with the association in numpy and 11.2-28.4
#             deg compiled (medians over seeds 0-2: 0.096 m, 19.4 deg, 0.365 m and 0.091 m, 13.9 deg,
#             0.450 m); following moving landmarks (issue 17) 13.6-32.5 deg, two seeds of six above
#             25 deg (medians over seeds 0-4: 0.116 m, 15.8 deg, 0.414 m; 0.103 m, 14.9 deg, 0.412 m
#             without)
#   relpoint  0.545 m, 40.5 deg, 0.536 m, 0.90  (before the final adjustment: 0.557 m, 40.9 deg, 0.554 m;
#             before the range-scaled second round of local matching:
#             0.622 m, 45.5 deg, 0.555 m, 0.95; before coasting on raw-point motion: 0.642 m, 52.1 deg, 0.884 m)
BOUNDS = {
    "ekf": (0.18, 14.0, 0.42, 0.9),
    "fastslam": (0.24, 25.0, 0.82, 0.9),
    "relpoint": (0.85, 62.0, 0.85, 0.85),
}


@pytest.mark.parametrize("name", sorted(BOUNDS))
def test_errors_stay_within_bounds(name: str, starry_night: StarryNight) -> None:
    if name == "fastslam":
        runs = [evaluate(name, starry_night, seed) for seed in range(5)]
        figures = {key: float(np.median([run[key] for run in runs])) for key in runs[0]}
    else:
        figures = evaluate(name, starry_night)
    ate_bound, rotation_bound, lm_bound, fraction_bound = BOUNDS[name]
    assert figures["poses"] == PREFIX
    assert figures["ate_rmse"] < ate_bound, figures
    assert figures["rot_rmse_deg"] < rotation_bound, figures
    assert figures["lm_rmse"] < lm_bound, figures
    assert figures["lm_mapped_fraction"] >= fraction_bound, figures
