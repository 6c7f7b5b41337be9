"""Fixes that reach the log after later clouds (a receiver's latency): carried forward along the filter's
own motion since their stamp instead of compared with where it is now."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators._recent_path import RecentPath
from relpoint.estimators.ekf import EkfConfig, EkfSlam
from relpoint.estimators.fastslam import FastSlam, FastSlamConfig
from relpoint.simulation import SimulationConfig, simulate


def test_the_displacement_since_a_stamp_is_interpolated_and_ignores_corrections() -> None:
    path = RecentPath(length=4)
    for k in range(6):
        path.add(k * 100, np.array([2.0 * k, 0.0, 0.0]))
    now = np.array([10.0, 0.0, 0.0])  # iteration 5's position
    np.testing.assert_allclose(path.displacement(450, 500, now), [1.0, 0.0, 0.0])
    np.testing.assert_allclose(path.displacement(500, 500, now), np.zeros(3))  # not late
    path.shift(np.array([0.0, 3.0, 0.0]))  # a fix moved the filter: its motion since 450 is unchanged
    np.testing.assert_allclose(path.displacement(450, 500, now + np.array([0.0, 3.0, 0.0])), [1.0, 0.0, 0.0])
    # the state predicted past the last iteration (odometry): the motion up to it counts too
    np.testing.assert_allclose(path.displacement(450, 550, np.array([11.0, 3.0, 0.0])), [2.0, 0.0, 0.0])
    assert path.displacement(150, 500, now) is None and path.too_old == 1  # older than the 4 kept


@pytest.mark.parametrize("name", ["ekf", "fastslam"])
def test_a_fix_stamped_before_the_latest_cloud_is_carried_to_it(name: str) -> None:
    # 12 m/s, a fix every iteration with 50 ms of latency: compared with the current position each
    # fix was 0.6 m off along the path, and the EKF's ATE went from 0.14 to 0.39 m.
    sim = simulate(SimulationConfig(iterations=200, density=25, seed=0, odometry_noise=0.05, fix_every=1,
                                    fix_noise=1.0))  # fmt: skip
    truth = sim.ground_truth
    lag_ns = 50_000_000

    def inputs(lag: int):  # type: ignore[no-untyped-def]
        for step in sim.steps():
            yield step.observation
            if step.odometry is not None:
                yield step.odometry
            if step.fix is not None:
                then = step.stamp_ns - lag
                true_then = np.array([np.interp(then, truth.stamps_ns, truth.positions[:, a]) for a in range(3)])
                error = step.fix.position - step.T_world_sensor[:3, 3]
                yield dataclasses.replace(step.fix, stamp_ns=then, position=true_then + error)

    def ate(lag: int) -> float:
        if name == "ekf":
            estimator = EkfSlam(EkfConfig(observation_sigma=0.3))
        else:
            estimator = FastSlam(FastSlamConfig(particles=10, observation_sigma=0.3), np.random.default_rng(0))
        result = pipeline.run(inputs(lag), estimator)
        assert result.summary["fixes"] > 50
        return float(np.sqrt(np.mean(np.sum((result.trajectory.positions - truth.positions) ** 2, axis=1))))

    assert ate(lag_ns) < 1.2 * ate(0) + 0.02
