"""Odometry checked against the motion the first observations register into.

A filter takes an odometry message's twist covariance as the size of its error, and that error as
white: independent from one message to the next. A wheel driver's yaw rate is often biased (a wheel
radius, a gyro's offset) by several times the deviation it states, and a bias is the opposite of
white: the filter, told that each message is good to its stated deviation, follows the bias and
turns its map with it. On a circle with a 0.02 rad/s yaw bias and 0.002 rad/s stated, the EKF's
path was 0.35 m off where the same log without odometry gave 0.04 m.

The observations held back to estimate the noise (:mod:`relpoint.estimators._noise`) are registered
onto each other anyway. Each registration is a measured motion over one interval, whose constant
twist (:func:`relpoint.geometry.body_twist`) the odometry held over the interval should match. Per
twist axis, the median difference over the intervals is the odometry's bias as far as the window
shows it: the registrations' own errors average out of it, as the spread of the differences says.
Where that bias is significant (:data:`SIGNIFICANCE` standard errors of the median) and larger than
the deviation the messages state for the axis, the axis's variance is raised by the bias squared for
the rest of the log: the filter then weighs the odometry as what it is, and the observations correct
it. Axes a message leaves unset already take the motion model's noise and are not changed; nor is
an odometry whose twist is in another frame than the sensor's told apart from a biased one (both
differ from the registered motion, and both are better trusted less).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from relpoint.geometry import FloatArray, body_twist, homogeneous
from relpoint.types import OdometryMeasurement, PointObservation

#: Twist axes, in the order of ``nav_msgs/Odometry.twist.covariance``.
AXES = ("vx", "vy", "vz", "wx", "wy", "wz")
#: Fewest registered intervals covered by odometry for a check.
MIN_INTERVALS = 8
#: A bias counts when it is this many standard errors of the median from zero ...
SIGNIFICANCE = 3.0
#: ... and larger than the axis's stated deviation.
#: (The median of n values has about 1.2533 / sqrt(n) times their deviation as its standard error.)
_MEDIAN_EFFICIENCY = 1.2533
#: Deviation of a Gaussian from its median absolute deviation.
_MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class OdometryCheck:
    """What the odometry showed against the registered motion, per twist axis (m/s, rad/s).

    ``bias``: the median difference of the registered twist from the odometry's; ``spread``: the
    deviation of those differences (odometry and registration errors together); ``stated``: the
    deviation the messages state (NaN where they leave the axis unset); ``added_variance``: what is
    added to each message's variance on the axis for the rest of the log (0 where nothing is).
    """

    intervals: int
    bias: FloatArray
    spread: FloatArray
    stated: FloatArray
    added_variance: FloatArray

    @property
    def raised(self) -> list[str]:
        """The axes whose variance is raised."""
        return [axis for axis, added in zip(AXES, self.added_variance, strict=True) if added > 0]

    def adjusted(self, odometry: OdometryMeasurement) -> OdometryMeasurement:
        """``odometry`` with the added variance on the axes it states (unset axes are left unset)."""
        added = np.where(odometry.unset_axes, 0.0, self.added_variance)
        if not added.any():
            return odometry
        return dataclasses.replace(odometry, covariance=odometry.covariance + np.diag(added))

    def summary(self) -> dict[str, Any]:
        def axes(values: FloatArray) -> dict[str, float | None]:
            return {
                axis: (None if not math.isfinite(v) else round(float(v), 6))
                for axis, v in zip(AXES, values, strict=True)
            }

        return {
            "intervals": self.intervals,
            "bias": axes(self.bias),
            "spread": axes(self.spread),
            "stated_sigma": axes(self.stated),
            "raised_axes": self.raised,
        }

    def warnings(self) -> list[str]:
        if not self.raised:
            return []
        parts = []
        for axis, bias, stated in zip(AXES, self.bias, self.stated, strict=True):
            if axis in self.raised:
                unit = "m/s" if axis.startswith("v") else "rad/s"
                parts.append(f"{axis} by {bias:+.3g} {unit} ({abs(bias) / stated:.0f}x the {stated:.2g} it states)")
        return [
            f"odometry: over the first {self.intervals} intervals its twist differs from the motion the observations "
            f"register, {', '.join(parts)}; its variance on {'that axis' if len(parts) == 1 else 'those axes'} is "
            "raised by the difference squared, so the observations correct it (run.json: odometry_check; "
            "--param odometry_check=false keeps the stated covariance)"
        ]


def held_twists(
    start_ns: int, end_ns: int, messages: Sequence[OdometryMeasurement]
) -> tuple[FloatArray, FloatArray] | None:
    """The time-weighted mean twist (6,) and variance diagonal (6,) of the messages held over
    ``[start_ns, end_ns]`` (each from its stamp until the next; ``messages`` in stamp order), or None
    when no message is held at ``start_ns``."""
    stamps = np.array([m.stamp_ns for m in messages], dtype=np.int64)
    first = int(np.searchsorted(stamps, start_ns, side="right")) - 1
    if first < 0 or end_ns <= start_ns:
        return None
    last = int(np.searchsorted(stamps, end_ns, side="left"))  # messages [first, last) are held inside
    bounds = np.concatenate([[start_ns], stamps[first + 1 : last], [end_ns]]).astype(np.float64)
    weights = np.diff(bounds) / (end_ns - start_ns)
    held = messages[first:last]
    twist = sum(w * np.concatenate([m.linear, m.angular]) for w, m in zip(weights, held, strict=True))
    variance = sum(w * np.diag(m.covariance) for w, m in zip(weights, held, strict=True))
    return np.asarray(twist), np.asarray(variance)


def check_odometry(
    observations: Sequence[PointObservation],
    steps: Sequence[tuple[FloatArray, FloatArray, FloatArray] | None],
    odometry: Sequence[OdometryMeasurement],
) -> OdometryCheck | None:
    """The odometry's bias against the consecutive registrations ``steps`` of ``observations`` (the
    registration of each onto the one before: ``(R, t, residuals)``, None where it failed), or None
    when fewer than :data:`MIN_INTERVALS` registered intervals are covered by odometry."""
    messages = sorted(odometry, key=lambda m: m.stamp_ns)
    if not messages:
        return None
    rotations, translations, spans, held_twist, held_variance = [], [], [], [], []
    for (a, b), step in zip(itertools.pairwise(observations), steps, strict=True):
        dt = (b.stamp_ns - a.stamp_ns) * 1e-9
        held = held_twists(a.stamp_ns, b.stamp_ns, messages)
        if step is None or held is None or not dt > 0:
            continue
        rotations.append(step[0])
        translations.append(step[1])
        spans.append(dt)
        held_twist.append(held[0])
        held_variance.append(held[1])
    n = len(spans)
    if n < MIN_INTERVALS:
        return None
    motions = homogeneous(np.array(rotations), np.array(translations))  # T_k<-k+1, the sensor's motion
    linear, angular = body_twist(np.broadcast_to(np.eye(4), motions.shape), motions, 1.0)
    difference = np.hstack([linear, angular]) / np.array(spans)[:, None] - np.array(held_twist)
    bias = np.median(difference, axis=0)
    spread = _MAD_TO_SIGMA * np.median(np.abs(difference - bias), axis=0)
    stated_variance = np.median(np.array(held_variance), axis=0)
    stated = np.where(stated_variance > 0, np.sqrt(np.maximum(stated_variance, 0.0)), np.nan)
    significant = np.abs(bias) > SIGNIFICANCE * _MEDIAN_EFFICIENCY * spread / math.sqrt(n)
    raise_axis = significant & (np.abs(bias) > np.nan_to_num(stated, nan=np.inf))
    return OdometryCheck(n, bias, spread, stated, np.where(raise_axis, bias**2, 0.0))
