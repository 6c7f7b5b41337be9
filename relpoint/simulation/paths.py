"""Sensor paths of the simulated scenarios (Kraut, *A Relative Point Algorithm*, section III).

Each path function takes arc-length-like parameters and returns positions (N, 3) in metres, in
``world`` (z up), and unit tangents (N, 3). :func:`orientations_from_tangents` turns tangents into
sensor orientations: x forward along the path (heading and pitch), y left, z up, no roll.
"""

from __future__ import annotations

import numpy as np

from relpoint.geometry import FloatArray


def figure8(phase: FloatArray, radius: float, climb: float) -> tuple[FloatArray, FloatArray]:
    """The paper's figure eight at pass phase ``phase`` (cycles; 0..1 is one pass, repeats after).

    Starts at the origin (the middle) heading along +x, so the first true pose is the identity;
    travels the right loop (centre ``(0, radius)``) counter-clockwise while climbing, reaches the
    middle ``climb`` metres above the start at phase 0.5, then travels the left loop (centre
    ``(0, -radius)``) clockwise while descending back to the start. Height ``z = climb/2 (1 - cos 2π phase)`` is smooth, so pitch has no jumps.

    Returns
    -------
    positions, tangents:
        (N, 3) arrays; tangents are d(position)/d(phase), not normalised.
    """
    u = np.mod(np.asarray(phase, dtype=np.float64), 1.0)
    right = u < 0.5
    positions = np.empty((len(u), 3))
    tangents = np.empty((len(u), 3))
    # Right loop, counter-clockwise around (radius, 0): angle pi -> 3 pi over u in [0, 0.5).
    angle = np.pi + 4.0 * np.pi * u[right]
    positions[right, 0] = radius + radius * np.cos(angle)
    positions[right, 1] = radius * np.sin(angle)
    tangents[right, 0] = -4.0 * np.pi * radius * np.sin(angle)
    tangents[right, 1] = 4.0 * np.pi * radius * np.cos(angle)
    # Left loop, clockwise around (-radius, 0): angle 0 -> -2 pi over u in [0.5, 1).
    angle = -4.0 * np.pi * (u[~right] - 0.5)
    positions[~right, 0] = -radius + radius * np.cos(angle)
    positions[~right, 1] = radius * np.sin(angle)
    tangents[~right, 0] = 4.0 * np.pi * radius * np.sin(angle)
    tangents[~right, 1] = -4.0 * np.pi * radius * np.cos(angle)
    positions[:, 2] = 0.5 * climb * (1.0 - np.cos(2.0 * np.pi * u))
    tangents[:, 2] = np.pi * climb * np.sin(2.0 * np.pi * u)
    # Turn the figure a quarter turn about z so the sensor starts at the identity pose (heading +x):
    # the first loop then lies on the +y side, which is the right-hand loop of a top view drawn with
    # the start heading pointing down the page, as in the paper's Fig. 1.
    for array in (positions, tangents):
        array[:, :2] = np.stack([-array[:, 1], array[:, 0]], axis=1)
    return positions, tangents


def figure8_length(radius: float, climb: float, samples: int = 20_000) -> float:
    """Length of one pass of :func:`figure8` in metres (numerical quadrature)."""
    phase = (np.arange(samples) + 0.5) / samples
    _, tangents = figure8(phase, radius, climb)
    return float(np.linalg.norm(tangents, axis=1).mean())


def corridor(distance: FloatArray, sway: float = 5.0, wavelength: float = 200.0) -> tuple[FloatArray, FloatArray]:
    """A long, gently swaying straight run along +x: ``distance`` metres along x (N,).

    The lateral sway (``sway`` metres, period ``wavelength``) and a quarter-amplitude vertical
    undulation keep yaw and pitch changing so rotations are exercised.
    """
    s = np.asarray(distance, dtype=np.float64)
    k = 2.0 * np.pi / wavelength
    positions = np.stack([s, sway * np.sin(k * s), 0.25 * sway * np.sin(0.5 * k * s)], axis=1)
    tangents = np.stack([np.ones_like(s), sway * k * np.cos(k * s), 0.125 * sway * k * np.cos(0.5 * k * s)], axis=1)
    return positions, tangents


def spiral(distance: FloatArray, radius: float, climb: float) -> tuple[FloatArray, FloatArray]:
    """A spiral climbing ``climb`` metres per turn of ``radius``, about ``distance`` metres along it (N,).

    Starts at the origin heading along +x (level, so the first true pose is the identity) and turns
    counter-clockwise about ``(0, radius)``; after each turn it passes over its start again, level and
    ``climb`` metres higher, so it sees the first turn's landmarks from another height. The height
    ``z = rise (a - sin a)`` at turn angle ``a`` (``rise = climb / 2 pi``) climbs smoothly, steepest
    half way round. The angle advances by ``distance`` over the mean speed of a turn, which the
    climb changes by less than ``(climb / radius)**2 / 2`` (0.03 % at the defaults). Tangents are unit.
    """
    s = np.asarray(distance, dtype=np.float64)
    rise = climb / (2.0 * np.pi)  # mean metres of climb per radian of turn
    angle = s * 2.0 * np.pi / spiral_length(radius, climb)
    positions = np.stack(
        [radius * np.sin(angle), radius * (1.0 - np.cos(angle)), rise * (angle - np.sin(angle))], axis=1
    )
    tangents = np.stack([radius * np.cos(angle), radius * np.sin(angle), rise * (1.0 - np.cos(angle))], axis=1)
    return positions, tangents / np.linalg.norm(tangents, axis=1, keepdims=True)


def spiral_length(radius: float, climb: float, samples: int = 20_000) -> float:
    """Length of one turn of :func:`spiral` in metres (numerical quadrature)."""
    angle = (np.arange(samples) + 0.5) / samples * 2.0 * np.pi
    rise = climb / (2.0 * np.pi)
    return float(np.mean(np.hypot(radius, rise * (1.0 - np.cos(angle)))) * 2.0 * np.pi)


def orientations_from_tangents(tangents: FloatArray) -> FloatArray:
    """Rotation matrices (N, 3, 3) ``R_world_sensor`` with x along the tangent, no roll.

    Columns are the sensor axes in ``world``: forward (tangent), left (horizontal, perpendicular
    to forward) and up (forward x left).
    """
    forward = tangents / np.linalg.norm(tangents, axis=1, keepdims=True)
    left = np.cross(np.array([0.0, 0.0, 1.0]), forward)
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    up = np.cross(forward, left)
    return np.stack([forward, left, up], axis=2)
