"""Closing a loop by registering young landmarks onto old ones (FastSLAM): the vote and its test,
and the figure eight's crossing."""

from __future__ import annotations

import numpy as np
import pytest

from relpoint.estimators._loop_closure import MIN_SUPPORT, register_loop
from relpoint.estimators.fastslam import FastSlam, FastSlamConfig
from relpoint.pipeline import run
from relpoint.simulation import SimulationConfig, simulate

SIGMA = 0.3
TOLERANCE = 2.0 * np.sqrt(2.0) * SIGMA
REACH = 10.0


def _surface(rng: np.random.Generator, n: int) -> np.ndarray:
    """Landmarks on a gently curved 60 m x 60 m surface (m)."""
    xy = rng.uniform(-30.0, 30.0, size=(n, 2))
    return np.column_stack([xy, 0.02 * xy[:, 0] ** 2 / 30.0 + rng.normal(scale=0.5, size=n)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_offset_of_a_revisited_place_is_found(seed: int) -> None:
    rng = np.random.default_rng(seed)
    old = _surface(rng, 400)
    drift = np.array([1.8, -2.5, 0.6])
    revisited = rng.choice(400, size=60, replace=False)
    young = old[revisited] + drift + rng.normal(scale=SIGMA, size=(60, 3))
    young = np.vstack([young, _surface(rng, 10)])  # and landmarks of new places
    loop = register_loop(young, old, TOLERANCE, REACH)  # young -> old: the offset that undoes the drift
    assert loop is not None
    np.testing.assert_allclose(loop.shift, -drift, atol=0.25)
    assert loop.support >= 50 and loop.log10_tail < -9


@pytest.mark.parametrize("seed", range(6))
def test_young_landmarks_at_random_places_make_no_loop(seed: int) -> None:
    """Dense old and young landmarks with no common offset: whatever the vote finds is chance."""
    rng = np.random.default_rng(seed)
    old = _surface(rng, 3000)
    young = _surface(rng, 300)
    assert register_loop(young, old, TOLERANCE, REACH) is None


def test_an_offset_within_the_tolerance_is_left_to_the_association() -> None:
    rng = np.random.default_rng(4)
    old = _surface(rng, 200)
    young = old[:40] + np.array([0.2, 0.1, 0.0])
    assert register_loop(young, old, TOLERANCE, REACH) is None
    assert register_loop(young[: MIN_SUPPORT - 1] + 3.0, old, TOLERANCE, REACH) is None


def _duplicates_percent(result) -> float:  # type: ignore[no-untyped-def]
    known = result.landmarks.gt_id[result.landmarks.gt_id >= 0]
    mapped = np.unique(known).size
    return 100.0 * (known.size - mapped) / mapped


def test_fastslam_closes_the_figure_eights_loop() -> None:
    """Seed 0 reaches the crossing (about iteration 470) 2.7 m off: without the registration every
    landmark of the overlap is mapped twice (19 % over 900 iterations)."""
    sim = simulate(SimulationConfig(density=25, noise=0.3, seed=0, iterations=600))
    observations = [step.observation for step in sim.steps()]
    closed = run(observations, FastSlam(FastSlamConfig(), np.random.default_rng(0)))
    open_ = run(observations, FastSlam(FastSlamConfig(close_loops=False), np.random.default_rng(0)))
    assert closed.summary["loop_closures"] >= 1 and closed.summary["loop_landmarks_merged"] >= 10
    assert "loop_closures" not in open_.summary
    assert _duplicates_percent(open_) > 10.0
    assert _duplicates_percent(closed) < 3.0
    truth = sim.ground_truth.positions
    T0 = sim.ground_truth.matrices()[0]

    def ate(result) -> float:  # type: ignore[no-untyped-def]
        estimate = result.trajectory.positions @ T0[:3, :3].T + T0[:3, 3]
        return float(np.sqrt(np.mean(np.sum((estimate - truth) ** 2, axis=1))))

    assert ate(closed) < 0.8 * ate(open_)


def test_a_vote_with_more_pairs_than_its_bound_thins_the_young_and_still_finds_the_loop(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from relpoint.estimators import _loop_closure

    monkeypatch.setattr(_loop_closure, "MAX_PAIRS", 1_500)
    rng = np.random.default_rng(5)
    old = _surface(rng, 300)
    young = old[:150] + np.array([2.0, 1.0, 0.0]) + rng.normal(scale=SIGMA, size=(150, 3))
    loop = register_loop(young, old, TOLERANCE, REACH)
    assert loop is not None and loop.candidates <= 75  # a third of the young landmarks voted
    np.testing.assert_allclose(loop.shift, [-2.0, -1.0, 0.0], atol=0.25)
