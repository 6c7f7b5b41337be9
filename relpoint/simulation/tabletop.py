"""A slow arc past scattered landmarks at any scale: the scene the scale tests and
``benchmarks/scene_scale.py`` run the point estimators on.

At ``scale`` 0.0375 it is a sensor moving 4 cm/s over a 1 m table with 2 mm noise; every length (path,
landmarks, range, noise) is proportional to ``scale``, so estimators whose defaults are derived from
the data give errors proportional to it too.
"""

from __future__ import annotations

import numpy as np

from relpoint.geometry import FloatArray, so3_exp
from relpoint.types import PointObservation

#: Iterations of the arc, 10 Hz.
TABLETOP_ITERATIONS = 200


def _rotation(yaw: float, pitch: float, roll: float) -> FloatArray:
    """R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return so3_exp([0.0, 0.0, yaw]) @ so3_exp([0.0, pitch, 0.0]) @ so3_exp([roll, 0.0, 0.0])


def tabletop_arc(scale: float, seed: int = 0) -> tuple[list[PointObservation], FloatArray]:
    """Observations (sensor frame, m) of 400 landmarks seen within ``8 scale`` m with ``0.053 scale`` m
    noise per axis along a slow arc, and the true positions (N, 3) in the first pose's frame.
    ``seed`` draws the landmarks and the noise."""
    rng = np.random.default_rng(seed)
    times = np.arange(TABLETOP_ITERATIONS) * 0.1
    angle = times / 10.0
    positions = scale * np.column_stack([10 * np.sin(angle), 10 * (1 - np.cos(angle)), np.sin(0.5 * angle)])
    rotations = [_rotation(a, 0.15 * np.sin(1.3 * a), 0.2 * np.sin(0.7 * a)) for a in angle]
    landmarks = rng.uniform([-15, -15, -3], [15, 15, 3], (400, 3)) * scale + positions.mean(axis=0)
    observations = []
    for k, (rotation, position) in enumerate(zip(rotations, positions, strict=True)):
        local = (landmarks - position) @ rotation  # R^T (m - p), row-wise
        seen = np.linalg.norm(local, axis=1) <= 8 * scale
        noisy = local[seen] + rng.normal(0.0, 0.002 / 0.0375 * scale, (int(seen.sum()), 3))
        observations.append(PointObservation(int(times[k] * 1e9), noisy, np.nonzero(seen)[0]))
    return observations, (positions - positions[0]) @ rotations[0]
