"""A point log of too few points a frame, with nothing else to carry the pose, is said to be unreliable.

With fewer than three points an observation cannot fix a 6-DoF pose; without odometry or fixes the
EKF's and FastSLAM's paths are then their motion models' guesses. On the figure eight with 1.6 points an
iteration they ran to 72 and 121 m ATE with exit 0 and no word (Relative Point warns of the iterations
it could not locate itself).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.simulation import SimulationConfig, simulate


def _inputs(sim: Any) -> Any:
    for step in sim.steps():
        yield step.observation
        if step.odometry is not None:
            yield step.odometry


def _warnings(name: str, **settings: Any) -> list[str]:
    sim = simulate(SimulationConfig(density=3, iterations=60, seed=3, **settings))
    spec = ESTIMATORS[name]
    estimator = spec.factory(spec.config_class(), np.random.default_rng(0))
    return list(pipeline.run(_inputs(sim), estimator).warnings)


@pytest.mark.parametrize("name", ["ekf", "fastslam"])
def test_too_few_points_without_odometry_are_warned_of(name: str) -> None:
    assert any("saw fewer than 3 points and the log has no odometry or fix" in w for w in _warnings(name))
    # With odometry the path has something to rest on: no such warning.
    assert not any("no odometry or fix" in w for w in _warnings(name, odometry_noise=0.05))
