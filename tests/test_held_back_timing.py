"""The iterations an estimator holds back to learn the noise get their share of the time of their replay."""

from __future__ import annotations

import numpy as np

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.estimators._noise import NOISE_FRAMES
from relpoint.simulation import SimulationConfig, simulate


def test_held_back_iterations_share_the_time_of_their_replay() -> None:
    # 30 iterations held back cost nothing each and the 30th all of them: on a 50-iteration log the
    # median per iteration read 0.00 ms.
    spec = ESTIMATORS["relpoint"]
    estimator = spec.factory(spec.config_class(), np.random.default_rng(0))
    observations = [step.observation for step in simulate(SimulationConfig(iterations=50, seed=2)).steps()]
    result = pipeline.run(iter(observations), estimator)
    held = result.seconds[:NOISE_FRAMES]
    assert estimator.replayed_steps == NOISE_FRAMES
    np.testing.assert_array_equal(held, np.full(NOISE_FRAMES, held[0]))
    later = float(np.median(result.seconds[NOISE_FRAMES:]))
    assert held[0] > 0.1 * later and np.median(result.seconds) > 0.1 * later
