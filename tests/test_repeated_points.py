"""Points repeated within one cloud (a front-end that published a point twice, a buffer written twice)
are dropped and counted before the estimators see them (relpoint.screening).

Each copy started a landmark of its own: on an independent simulator's circle (300 landmarks, 10 %
of each cloud's points repeated) Relative Point's map held 543 landmarks for 297 (244 duplicates)
and FastSLAM's 594 (296 duplicates); the EKF 29.
"""

from __future__ import annotations

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.screening import InputScreen
from relpoint.types import PointObservation


def _line_of_sight(seed: int = 0) -> tuple[list[PointObservation], list[PointObservation]]:
    """40 observations of 60 landmarks from a sensor moving 0.2 m along x per 0.1 s, and the same
    observations with a tenth of each cloud's points appended again."""
    rng = np.random.default_rng(seed)
    landmarks = rng.uniform([-10, -10, -2], [18, 10, 4], (60, 3))
    plain, doubled = [], []
    for k in range(40):
        points = landmarks - [0.2 * k, 0.0, 0.0] + rng.normal(0.0, 0.02, landmarks.shape)
        ids = np.arange(len(landmarks))
        again = rng.random(len(points)) < 0.1
        stamp = 1_000_000_000 + k * 100_000_000
        plain.append(PointObservation(stamp, points, ids))
        doubled.append(PointObservation(stamp, np.vstack([points, points[again]]), np.r_[ids, ids[again]]))
    return plain, doubled


def test_a_repeated_point_is_dropped_and_counted_but_a_near_one_is_kept() -> None:
    points = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [1.0, 2.0, 3.0], [1.0, 2.0, 3.0 + 1e-6]])
    screen = InputScreen()
    kept = screen.points(PointObservation(0, points, np.array([7, 8, 7, 9])))
    assert kept.points.tolist() == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [1.0, 2.0, 3.0 + 1e-6]]
    assert kept.ids is not None and kept.ids.tolist() == [7, 8, 9]
    assert sum(screen.skipped.values()) == 1


@pytest.mark.parametrize("name", ["relpoint", "fastslam"])
def test_repeated_points_start_no_second_landmark(name: str) -> None:
    plain, doubled = _line_of_sight()
    spec = ESTIMATORS[name]
    sizes = []
    for observations in (plain, doubled):
        result = pipeline.run(observations, spec.factory(spec.config_class(), np.random.default_rng(0)))
        sizes.append(len(result.landmarks.positions))
    assert sizes[1] == sizes[0]
