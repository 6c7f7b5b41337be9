"""Relative Point says when its map had to begin again: a view with nothing seen before in it (after a
gap or a jump) starts a part of the map that nothing ties to the one before; and when most of its
iterations could not be located at all."""

from __future__ import annotations

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.types import PointObservation


def _observations(jump: bool) -> list[PointObservation]:
    """80 iterations at 10 Hz of a sensor creeping along x past 60 landmarks; with ``jump`` it leaves
    them after 40 iterations for 60 others 500 m away, never seen together."""
    rng = np.random.default_rng(2)
    near = rng.uniform(-10.0, 10.0, (60, 3))
    away = np.array([500.0, 0.0, 0.0])
    far = rng.uniform(-10.0, 10.0, (60, 3)) + away
    observations = []
    for k in range(80):
        position = np.array([0.05 * k, 0.0, 0.0])
        landmarks, ids = (far, np.arange(100, 160)) if jump and k >= 40 else (near, np.arange(60))
        if jump and k >= 40:
            position = position + away
        points = landmarks - position + rng.normal(0.0, 0.02, landmarks.shape)
        observations.append(PointObservation(k * 100_000_000, points, ids))
    return observations


@pytest.mark.parametrize("jump", [False, True])
def test_a_map_begun_again_is_counted_and_warned(jump: bool) -> None:
    spec = ESTIMATORS["relpoint"]
    result = pipeline.run(_observations(jump), spec.factory(spec.config_class(), np.random.default_rng(0)))
    assert result.summary["map_restarts"] == int(jump)
    begun_again = [warning for warning in result.warnings if "begun again" in warning]
    assert len(begun_again) == int(jump)
    if jump:
        assert "iterations 4" in begun_again[0]  # the first iteration of the far view, or just after


def test_a_run_mostly_not_located_is_warned() -> None:
    # Three to six points a frame, each seen in two frames only: rarely three mapped points in view,
    # so the poses coast. The run used to end with exit 0, frozen poses and no word of it.
    rng = np.random.default_rng(3)
    observations, next_id = [], 0
    for k in range(60):
        n = int(rng.integers(3, 7))
        landmarks = rng.uniform(-10.0, 10.0, (n, 3))
        for copy in range(2):
            position = np.array([0.5 * (k + copy), 0.0, 0.0])
            observations.append((k + copy, landmarks - position, np.arange(next_id, next_id + n)))
        next_id += n
    frames = {}
    for k, points, ids in observations:
        frames.setdefault(k, []).append((points, ids))
    sparse = [
        PointObservation(k * 100_000_000, np.vstack([p for p, _ in parts]), np.concatenate([i for _, i in parts]))
        for k, parts in sorted(frames.items())
    ]
    spec = ESTIMATORS["relpoint"]
    result = pipeline.run(sparse, spec.factory(spec.config_class(), np.random.default_rng(0)))
    degenerate = result.summary["degenerate_iterations"]
    assert degenerate > 0.5 * len(sparse)
    not_located = [warning for warning in result.warnings if "could not be located" in warning]
    assert len(not_located) == 1 and f"{degenerate} of {len(sparse)}" in not_located[0]
    assert "ekf or fastslam" in not_located[0]
    located = pipeline.run(_observations(False), spec.factory(spec.config_class(), np.random.default_rng(0)))
    assert not any("could not be located" in warning for warning in located.warnings)


@pytest.mark.parametrize(("tail", "warned"), [(15, True), (5, False)])
def test_a_log_that_ends_with_nothing_located_is_warned(tail: int, warned: bool) -> None:
    # A drive out of the landmark field: the last iterations see nothing, their poses hold the last one
    # (a probe's log: 25 such iterations of 600, ATE 0.75 m against 0.02 m before them; exit 0, no word).
    observations = _observations(False)
    for k in range(len(observations) - tail, len(observations)):
        observations[k] = PointObservation(observations[k].stamp_ns, np.zeros((0, 3)), np.zeros(0, np.int64))
    spec = ESTIMATORS["relpoint"]
    result = pipeline.run(observations, spec.factory(spec.config_class(), np.random.default_rng(0)))
    at_end = [warning for warning in result.warnings if f"the last {tail} iterations could not be located" in warning]
    assert len(at_end) == int(warned)
    assert not any("of 80 iterations could not be located" in warning for warning in result.warnings)
