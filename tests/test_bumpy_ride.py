"""A ground vehicle on bumps: the body pitches and rolls a few degrees at 0.5-2 Hz while it drives, and
the motion models' angular acceleration noise must cover it (relpoint.estimators._noise).

The held-back path's angular acceleration smoothed over half a second averages the bumps out (0.78
rad/s^2 where the white noise explaining each interval's change is 1.75); taken as the floor, the
EKF's prediction left the points outside their gates again and again and started a landmark for
each (an independent simulator's circle: 3,782 landmarks mapped for 300, ATE 0.0147 m against
0.0071 m on the level; at the white noise 298 landmarks, 0.0084 m).
"""

from __future__ import annotations

import numpy as np

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.types import PointObservation

RADIUS_M, SPEED_M_S, RATE_HZ, RANGE_M, SIGMA_M = 15.0, 2.0, 10.0, 15.0, 0.05


def _rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return Rz @ Ry @ Rx


def _bumpy_circle(frames: int, seed: int = 0) -> tuple[list[PointObservation], int]:
    """Observations of 200 landmarks around a circle driven at 2 m/s, the body pitching and rolling with
    the road (s: metres driven): roll 0.06 sin(2.3 s) + 0.03 sin(5.1 s + 1), pitch 0.08 sin(1.7 s + 0.5)
    + 0.04 sin(6.3 s) rad, height 0.1 sin(1.1 s) m; and how many landmarks were seen."""
    rng = np.random.default_rng(seed)
    driven = SPEED_M_S * np.arange(frames) / RATE_HZ
    centre = np.column_stack([RADIUS_M * np.sin(driven / RADIUS_M), RADIUS_M * (1 - np.cos(driven / RADIUS_M))])
    landmarks = np.column_stack([centre[rng.integers(0, frames, 200)], np.zeros(200)])
    landmarks += rng.uniform([-12, -12, -2], [12, 12, 4], (200, 3))
    observations, seen = [], np.zeros(len(landmarks), dtype=bool)
    for k, s in enumerate(driven):
        roll = 0.06 * np.sin(2.3 * s) + 0.03 * np.sin(5.1 * s + 1)
        pitch = 0.08 * np.sin(1.7 * s + 0.5) + 0.04 * np.sin(6.3 * s)
        R = _rotation(roll, pitch, s / RADIUS_M)
        p = np.array([*centre[k], 0.1 * np.sin(1.1 * s)])
        local = (landmarks - p) @ R
        in_view = np.linalg.norm(local, axis=1) < RANGE_M
        seen |= in_view
        points = local[in_view] + rng.normal(0.0, SIGMA_M, (int(in_view.sum()), 3))
        observations.append(PointObservation(1_000_000_000 + k * 100_000_000, points, np.flatnonzero(in_view)))
    return observations, int(seen.sum())


def test_the_ekf_maps_each_landmark_once_on_a_bumpy_ride() -> None:
    observations, seen = _bumpy_circle(150)
    spec = ESTIMATORS["ekf"]
    result = pipeline.run(observations, spec.factory(spec.config_class(), np.random.default_rng(0)))
    assert len(result.landmarks.positions) <= 1.05 * seen
