"""A front-end's wild points (seen once, where no landmark is) stay out of the EKF's and FastSLAM's maps.

The figure eight with four points a frame added far off in the sensor's view, each seen once (id -1,
clutter). Started as landmarks, they are kept by the filter (it cannot tell them yet), but the map
holds only the landmarks seen at least ``min_observations`` times (default 2); the trajectory is the
same either way. (Before ``min_observations``, the map held every one of them.)
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators.ekf import EkfConfig, EkfSlam
from relpoint.estimators.fastslam import FastSlam, FastSlamConfig
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import PointObservation

WILD_PER_FRAME = 4


def _with_wild_points(seed: int) -> list[PointObservation]:
    """The figure eight's observations, each with ``WILD_PER_FRAME`` points 5-40 m off any landmark's
    path: uniform in the sensor's forward half-space, 20-60 m away (clutter, id -1)."""
    sim = simulate(SimulationConfig(density=25, noise=0.3, iterations=60, seed=seed))
    rng = np.random.default_rng(seed + 100)
    observations = []
    for step in sim.steps():
        o = step.observation
        direction = rng.normal(size=(WILD_PER_FRAME, 3))
        direction[:, 0] = np.abs(direction[:, 0])
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        wild = direction * rng.uniform(20.0, 60.0, (WILD_PER_FRAME, 1))
        points = np.vstack([np.asarray(o.points), wild])
        ids = np.concatenate([np.asarray(o.ids), np.full(WILD_PER_FRAME, -1)])
        observations.append(PointObservation(o.stamp_ns, points, ids))
    return observations


def _build(name: str, min_observations: int) -> Any:
    if name == "ekf":
        return EkfSlam(EkfConfig(observation_sigma=0.3, min_observations=min_observations))
    config = dataclasses.replace(FastSlamConfig(particles=10, observation_sigma=0.3), min_observations=min_observations)
    return FastSlam(config, np.random.default_rng(0))


@pytest.mark.parametrize("name", ["ekf", "fastslam"])
def test_points_seen_once_stay_out_of_the_map(name: str) -> None:
    inputs = _with_wild_points(seed=3)
    shown = pipeline.run(inputs, _build(name, 2))
    every = pipeline.run(inputs, _build(name, 1))

    wild_every = int(np.count_nonzero(every.landmarks.gt_id == -1))
    wild_shown = int(np.count_nonzero(shown.landmarks.gt_id == -1))
    assert wild_every > 0.5 * WILD_PER_FRAME * len(inputs)  # the filter started most of them ...
    # ... and the map leaves them out. A few pair with each other while the pose's gates are still wide
    # (the EKF's first iterations), and are seen more than once.
    assert wild_shown <= 0.05 * wild_every
    assert (shown.landmarks.observations >= 2).all()
    assert (every.landmarks.observations == 1).any()
    # The map leaves out only landmarks seen once; the filter's estimate is the same.
    assert len(shown.landmarks) == np.count_nonzero(every.landmarks.observations >= 2)
    np.testing.assert_array_equal(shown.trajectory.positions, every.trajectory.positions)
    # run.json counts what the map holds, and what it leaves out
    assert shown.summary["landmarks"] == len(shown.landmarks)
    assert shown.summary["landmarks_not_mapped"] == len(every.landmarks) - len(shown.landmarks)
    assert every.summary["landmarks_not_mapped"] == 0
