"""Screening a log's inputs before an estimator sees them: implausible values are dropped and counted.

A log can be valid and still carry values no sensor measured: a point a billion kilometres away, a
fix at infinity, an odometry twist of light speed. One such point in every cloud is enough to ruin
a map without any error (the estimators fit to it), so the pipeline drops them here and the run
reports how many it dropped.

A point is implausible when its range (distance from the sensor, metres) is

- beyond :data:`MAX_POINT_RANGE` whatever the log, or
- beyond :data:`RANGE_FACTOR` times the median range the data itself shows: the larger of the
  median over a window of recent points and this cloud's own median (so a robot leaving a room for
  the open keeps its new far points). A median holds while fewer than half the points are bad, and
  no real sensor's far points lie fifty times beyond its median point. When most of a cloud lies
  beyond the limit the scene has changed, and only the absolute bound applies.

A depth frame smaller than :data:`MIN_DEPTH_SIDE` pixels a side holds too little image to track (the
image pyramid and the normal estimate need a neighbourhood), so it is dropped and counted too.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from relpoint.types import UNMEASURED_TWIST_VARIANCE, DepthFrame, OdometryMeasurement, PointObservation, PositionFix

log = logging.getLogger(__name__)

#: No 3D sensor measures points farther than this (m).
MAX_POINT_RANGE = 1e5

#: A point beyond this many times the running median range is dropped.
RANGE_FACTOR = 50.0

#: A cloud of at least this many points speaks for its own scene's range (a robot leaving a room).
MIN_CLOUD_FOR_MEDIAN = 5

#: Ranges of recent points kept for the running median.
RANGE_WINDOW = 4096

#: Smallest depth image the dense estimator can track, pixels per side.
MIN_DEPTH_SIDE = 16

#: Largest plausible fix coordinate (m): beyond the Earth-centred frame's reach.
MAX_FIX_COORDINATE = 1e8

#: Variance (m^2) given to a fix axis whose variance is zero while another's is not: unmeasured
#: (:func:`relpoint.geometry.measured_basis` leaves it out), as a horizontal fix's altitude.
UNMEASURED_VARIANCE = 1e12

#: Largest plausible odometry speed (m/s) and turn rate (rad/s).
MAX_SPEED = 1e4
MAX_TURN_RATE = 1e3
#: Names of the twist's axes, in ``nav_msgs/Odometry.twist.covariance`` order.
TWIST_AXES = ("vx", "vy", "vz", "wx", "wy", "wz")


@dataclass
class InputScreen:
    """Drops implausible points, fixes and odometry; counts what it dropped in :attr:`skipped`.

    The first drop of each kind is logged as a warning; later ones are only counted.
    """

    skipped: Counter[str] = field(default_factory=Counter)
    _ranges: np.ndarray = field(default_factory=lambda: np.zeros(RANGE_WINDOW))
    _filled: int = 0
    _next: int = 0
    unmeasured_axes: int = 0  # fixes with an axis of zero variance taken as unmeasured
    unset_odometry_axes: int = 0  # odometry messages with a twist variance of zero or below

    def points(self, observation: PointObservation) -> PointObservation:
        """``observation`` without its implausible points (the same object when none is dropped)."""
        if len(observation) == 0:
            return observation
        ranges = np.linalg.norm(observation.points, axis=1)
        plausible = ranges[ranges <= MAX_POINT_RANGE]
        medians = [float(np.median(self._ranges[: self._filled]))] if self._filled else []
        if len(plausible) >= MIN_CLOUD_FOR_MEDIAN or not medians:
            medians.append(float(np.median(plausible)) if len(plausible) else 0.0)
        median = max(medians)
        limit = min(MAX_POINT_RANGE, RANGE_FACTOR * median) if median > 0 else MAX_POINT_RANGE
        keep = ranges <= limit
        if keep.sum() * 2 < len(keep):  # most of the cloud is far: the scene changed, not its outliers
            keep = ranges <= MAX_POINT_RANGE
        self._remember(ranges[keep])
        dropped = int(len(keep) - keep.sum())
        if dropped:
            self._count("points: implausible range (far beyond the data's own)", dropped,
                        f"beyond {limit:.4g} m, {RANGE_FACTOR:g} times the median range {median:.4g} m")  # fmt: skip
        repeated = _repeated_points(observation.points, keep)
        if repeated.any():
            self._count("points: repeated within their cloud (the same coordinates twice)", int(repeated.sum()),
                        "a sensor measures a point once; a second copy would start a second landmark")  # fmt: skip
            keep &= ~repeated
            dropped += int(repeated.sum())
        if dropped == 0:
            return observation
        ids = observation.ids[keep] if observation.ids is not None else None
        return PointObservation(observation.stamp_ns, observation.points[keep], ids, observation.frame_id)

    def depth(self, frame: DepthFrame) -> DepthFrame | None:
        """``frame``, or None (counted) when it is too small to track."""
        height, width = frame.depth.shape
        if min(height, width) < MIN_DEPTH_SIDE:
            self._count("depth frames: too small to track", 1,
                        f"{width}x{height} pixels, at least {MIN_DEPTH_SIDE} a side needed")  # fmt: skip
            return None
        return frame

    def _count(self, kind: str, count: int, detail: str) -> None:
        if kind not in self.skipped:
            log.warning("skipping %s (%s); further ones are counted in run.json", kind, detail)
        self.skipped[kind] += count

    def _remember(self, ranges: np.ndarray) -> None:
        ranges = ranges[-RANGE_WINDOW:]
        n = len(ranges)
        if n == 0:
            return
        end = self._next + n
        if end <= RANGE_WINDOW:
            self._ranges[self._next : end] = ranges
        else:
            first = RANGE_WINDOW - self._next
            self._ranges[self._next :] = ranges[:first]
            self._ranges[: n - first] = ranges[first:]
        self._next = end % RANGE_WINDOW
        self._filled = min(RANGE_WINDOW, self._filled + n)

    def fix(self, fix: PositionFix) -> PositionFix | None:
        """``fix``, or None (counted) when its position or covariance is not finite or implausible, or its
        covariance is all zero (unknown); an axis of zero variance beside positive ones is given
        :data:`UNMEASURED_VARIANCE` (warned once)."""
        if (
            not np.all(np.isfinite(fix.position))
            or np.any(np.abs(fix.position) > MAX_FIX_COORDINATE)
            or not np.all(np.isfinite(fix.covariance))
            or np.any(np.diag(fix.covariance) < 0)
        ):
            self._count("fixes: non-finite or implausible", 1, f"position {fix.position.tolist()}")
            return None
        if not is_positive_semidefinite(fix.covariance):
            self._count("fixes: covariance not positive semi-definite", 1,
                        f"the position covariance has a negative eigenvalue; variances "
                        f"{np.round(np.diag(fix.covariance), 6).tolist()}")  # fmt: skip
            return None
        if not np.any(np.diag(fix.covariance) > 0):
            # All zero is how ROS messages say "unknown" (REP 145); taken as exact, one such fix would
            # override the filter, and the next make its covariance singular.
            self._count("fixes: no covariance", 1, "all position variances are zero: its noise is unknown")
            return None
        variances = np.diag(fix.covariance)
        if np.any(variances == 0):
            # Zero beside positive variances: an axis the message does not fill (a horizontal GNSS fix's
            # altitude, often a placeholder 0), not one measured exactly, which would pin the filter to
            # the placeholder. It is given a variance that leaves it unmeasured.
            zero = variances == 0
            covariance = np.array(fix.covariance, dtype=np.float64)
            covariance[zero, :] = 0.0
            covariance[:, zero] = 0.0
            covariance[zero, zero] = UNMEASURED_VARIANCE
            self.unmeasured_axes += 1
            if self.unmeasured_axes == 1:
                log.warning("a position fix has zero variance on axis %s beside positive ones: that axis is "
                            "taken as not measured", ", ".join("xyz"[i] for i in np.flatnonzero(zero)))  # fmt: skip
            return PositionFix(fix.stamp_ns, fix.position, covariance)
        return fix

    def odometry(self, odometry: OdometryMeasurement) -> OdometryMeasurement | None:
        """``odometry``, or None (counted) when its twist is not finite or implausibly fast."""
        linear, angular = odometry.linear, odometry.angular
        if (
            not (np.all(np.isfinite(linear)) and np.all(np.isfinite(angular)))
            or np.linalg.norm(linear) > MAX_SPEED
            or np.linalg.norm(angular) > MAX_TURN_RATE
            or not np.all(np.isfinite(odometry.covariance))
        ):
            self._count("odometry: non-finite or implausible", 1, f"twist {linear.tolist()} {angular.tolist()}")
            return None
        unset = odometry.unset_axes
        if not is_positive_semidefinite(odometry.covariance[np.ix_(~unset, ~unset)]):
            self._count("odometry: covariance not positive semi-definite", 1,
                        f"the twist covariance of the measured axes has a negative eigenvalue; "
                        f"variances {np.round(np.diag(odometry.covariance), 6).tolist()}")  # fmt: skip
            return None
        if unset.any():
            # Zero is REP 145's "unknown", -1 some drivers', 1e3-1e6 others' for an axis they do not
            # measure; the filters give those axes their motion model's noise
            # (OdometryMeasurement.twist_covariance) rather than take them as exact or let them wander.
            self.unset_odometry_axes += 1
            if self.unset_odometry_axes == 1:
                log.warning("odometry leaves the variance of %s unset (zero, negative, or %g and above: not measured): "
                            "the motion model's noise is used for them", ", ".join(np.array(TWIST_AXES)[unset]),
                            UNMEASURED_TWIST_VARIANCE)  # fmt: skip
        return odometry


def _repeated_points(points: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """(N,) True for each of ``points`` (N, 3) among ``kept`` that repeats the coordinates of an earlier
    kept one, bit for bit (a front-end that published one point twice, a buffer written twice)."""
    repeated = np.zeros(len(points), dtype=bool)
    index = np.flatnonzero(kept)
    if len(index) < 2:
        return repeated
    x = np.sort(points[index, 0])
    if not np.any(x[1:] == x[:-1]):  # no two points share even their x: the common case, at a tenth of the cost
        return repeated
    _, first = np.unique(points[index], axis=0, return_index=True)
    if len(first) < len(index):
        repeated[index] = True
        repeated[index[first]] = False
    return repeated


def is_positive_semidefinite(covariance: np.ndarray) -> bool:
    """Whether a symmetric matrix has no eigenvalue below minus a rounding tolerance (an empty one has
    none); a covariance that breaks this gives negative variances along some direction."""
    if covariance.size == 0:
        return True
    if not np.any(covariance - np.diag(np.diag(covariance))):  # diagonal, as nearly every message's
        return bool(np.all(np.diag(covariance) >= 0))
    symmetric = 0.5 * (covariance + covariance.T)
    scale = float(np.max(np.abs(np.diag(symmetric)))) or 1.0
    return bool(np.linalg.eigvalsh(symmetric).min() >= -1e-9 * scale)
