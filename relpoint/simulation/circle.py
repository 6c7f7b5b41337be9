"""A sensor circling through scattered landmarks with a large step between observations: the scene the
low-rate tests and ``benchmarks/low_rate.py`` run the point estimators on.

The sensor turns ``step_degrees`` about the circle's centre between two observations, one a second (at
15 degrees, 7.9 m on a circle of 30 m: a vehicle seen at 1 Hz, about its landmarks' spacing); every
length (circle, landmarks, range) is proportional to ``scale``.
"""

from __future__ import annotations

import numpy as np

from relpoint.geometry import FloatArray, so3_exp
from relpoint.types import PointObservation

#: Landmarks of the scene, drawn in a box of 120 x 120 x 25 m (times the scale): about 9 m apart.
CIRCLE_LANDMARKS = 500


def fast_circle(
    sigma: float, frames: int = 30, scale: float = 1.0, seed: int = 0, step_degrees: float = 15.0
) -> tuple[list[PointObservation], FloatArray]:
    """Observations (sensor frame, m) of a sensor circling on a radius of ``30 scale`` m, ``step_degrees``
    a second, whose height wavers by ``3 scale`` m, seeing the landmarks within ``40 scale`` m with noise
    ``sigma`` (m) per axis; and its true positions (``frames``, 3) in ``world``, the sensor's x axis
    along the circle. ``seed`` draws the landmarks and the noise."""
    rng = np.random.default_rng(seed)
    landmarks = np.column_stack([rng.uniform(-60, 60, (CIRCLE_LANDMARKS, 2)), rng.uniform(-10, 15, CIRCLE_LANDMARKS)])
    landmarks *= scale
    observations, positions = [], []
    for k in range(frames):
        angle = np.radians(step_degrees) * k
        position = 30.0 * scale * np.array([np.cos(angle), np.sin(angle), 0.1 * np.sin(2 * angle)])
        rotation = so3_exp([0.0, 0.0, angle + np.pi / 2])
        local = (landmarks - position) @ rotation  # R^T (m - p), row-wise
        seen = np.linalg.norm(local, axis=1) < 40.0 * scale
        points = local[seen] + rng.normal(0.0, sigma, (int(seen.sum()), 3))
        observations.append(PointObservation(k * 1_000_000_000, points, np.flatnonzero(seen)))
        positions.append(position)
    return observations, np.array(positions)


def first_frame(positions: FloatArray) -> FloatArray:
    """:func:`fast_circle`'s true positions (N, 3) in its first pose's frame, where estimators start."""
    return (positions - positions[0]) @ so3_exp([0.0, 0.0, np.pi / 2])
