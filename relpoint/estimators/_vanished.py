"""Landmarks that vanish: seen regularly, then missed again and again while their place is in view.

A mover that stood still long enough to be mapped leaves its landmark behind when it goes on (a
stop-and-go mover, a parked car that drives off, a landmark that moved before the motion test could
tell): its points fall outside that landmark's gate, a new landmark starts from them, and the old
one stays in the map, a duplicate at a place where nothing is. The filter never pairs it again, so
nothing in the update removes it. What shows it is *negative information*: the sensor keeps looking
at that place and does not see it.

No sensor model is needed to say that a place is in view. A landmark is *in view* at an iteration
when at least :data:`MIN_NEIGHBOURS` of the iteration's points, placed in ``world`` by the updated
pose, lie within ``NEIGHBOUR_SPACINGS`` typical point spacings of it, the spacing being the median
distance from each of the iteration's points to its nearest neighbour: where the sensor sees points
all around a position, it would have seen a landmark there. A landmark in view that is not paired
is *missed*.

Each landmark's detection rate ``p`` is learned from its own history before its current run of
misses (a keypoint detector finds a real corner in some views and not in others; a simulated point
is seen whenever it is in range): a landmark whose current run of ``L`` misses in a row has, under
the posterior of ``p`` (:func:`run_log_probability`), a chance below ``vanished_probability``, after
at least :data:`MIN_MISSES` of them, has vanished: the filter drops it (an EKF marginalises it out of its
state). A landmark seen 20 times in 20 vanishes after 5 misses in a row, one seen 10 times in 20 after
14, one seen once after 44: an occluded, rarely detected or young static landmark stays.

Misses alone are not enough: a real landmark can be occluded, and a keypoint detector stops finding a
corner once the viewpoint has changed, with its neighbours still in view. A landmark vanishes only
when it has also been *replaced*: a landmark started, within :data:`SUCCESSION_WINDOW` iterations
of its last pairing, nearer to it than to any other unpaired landmark and within the filter's reach
of it: where the mover went. On the 7-Scenes kitchen keypoints that keeps the map's coverage (30.8 %
of the well-tracked corners mapped, against 34.2 % without dropping, and 26.1 % with misses alone),
and on Starry Night nothing vanishes.

Misses only count in iterations that pair at least :data:`MIN_PAIRED` points and more than half of
the landmarks in view: when most of what should be seen is not paired, the pose is off, not the
landmarks.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import betaln

from relpoint.geometry import FloatArray

#: Points of the iteration that must lie near a landmark's position for it to be in view.
MIN_NEIGHBOURS = 2
#: Radius of "near", in median nearest-neighbour spacings of the iteration's points.
NEIGHBOUR_SPACINGS = 2.0
#: Misses in a row before a landmark can vanish, whatever its detection rate.
MIN_MISSES = 5
#: Misses only count in iterations that pair at least this many points.
MIN_PAIRED = 8
#: The spacing is estimated from at most this many of the iteration's points (evenly strided).
SPACING_SAMPLE = 256


def point_spacing(points: FloatArray) -> float:
    """Median distance (m) from each point (n, 3) to its nearest other point; 0 for fewer than 2."""
    if len(points) < 2:
        return 0.0
    sample = points[:: max(1, -(-len(points) // SPACING_SAMPLE))]
    # The squared distances summed axis by axis, as np.sum over the (n, n, 3) differences adds them,
    # without that array.
    d2 = np.zeros((len(sample), len(sample)))
    for axis in range(3):
        difference = sample[:, None, axis] - sample[None, :, axis]
        d2 += difference * difference
    np.fill_diagonal(d2, np.inf)
    return float(np.sqrt(np.median(d2.min(axis=1))))


def in_view(
    landmarks: FloatArray, points: FloatArray, radius: float, min_neighbours: int = MIN_NEIGHBOURS
) -> np.ndarray:
    """Which ``landmarks`` (n, 3) have at least ``min_neighbours`` of ``points`` (p, 3) within ``radius`` (m).

    Both in the same frame. Landmarks outside the points' bounding box grown by ``radius`` are out
    of view without a distance computed.
    """
    result = np.zeros(len(landmarks), dtype=bool)
    if len(points) < min_neighbours or radius <= 0 or not len(landmarks):
        return result
    low, high = points.min(axis=0) - radius, points.max(axis=0) + radius
    near = np.flatnonzero(np.all((landmarks >= low) & (landmarks <= high), axis=1))
    r2 = radius * radius
    for start in range(0, len(near), 512):  # bounded memory: 512 x p distances at a time
        rows = near[start : start + 512]
        d2 = np.sum((landmarks[rows, None, :] - points[None, :, :]) ** 2, axis=2)
        result[rows] = np.count_nonzero(d2 <= r2, axis=1) >= min_neighbours
    return result


#: Width (degrees) of the azimuth and elevation histograms of the learned field of view.
BIN_DEGREES = 1.0
#: Share of the observed directions left outside the learned field of view at each edge.
EDGE_SHARE = 0.01
#: The learned field of view is shrunk by this share of its width at each edge.
EDGE_MARGIN = 0.05
#: A landmark started this many iterations at most after an unpaired one was last paired, near
#: it, may be where it went (:meth:`VanishedLandmarks._adopt`).
SUCCESSION_WINDOW = 10
#: Points counted before the view's axes are set from their mean direction.
FRAME_POINTS = 200
#: Length of the points' mean unit direction below which they look all around (no forward axis).
FORWARD_MIN = 0.3
#: Range bins of the learned field of view: log-spaced from 1 mm to 10 km.
RANGE_BINS = np.geomspace(1e-3, 1e4, 129)
#: A landmark is in view only up to this share of the range the sensor reaches (its 95th percentile).
RANGE_SHARE = 0.9


def _quantile_span(histogram: np.ndarray, share: float) -> tuple[float, float]:
    """First and last bin edges (in bins) between which all but ``share`` at each end of the counts lie."""
    cumulative = np.cumsum(histogram)
    total = cumulative[-1]
    low = int(np.searchsorted(cumulative, share * total, side="right"))
    high = int(np.searchsorted(cumulative, (1.0 - share) * total, side="left")) + 1
    return float(low), float(high)


def run_log_probability(seen: np.ndarray, missed: np.ndarray, run: np.ndarray) -> np.ndarray:
    """Log-probability of ``run`` misses in a row for landmarks seen ``seen`` times and missed
    ``missed`` times in view before (arrays of the same shape).

    The detection rate ``p`` is unknown; with a uniform prior its posterior is Beta(seen + 1, missed
    + 1), and the chance of the run is the posterior mean of ``(1 - p) ** run``:
    ``B(seen + 1, missed + 1 + run) / B(seen + 1, missed + 1)``. A landmark seen once is not
    believed to be seen every time: after 7 misses the chance is 1/36, where the plug-in rate 2/3
    would give 1/2187.
    """
    a, b = np.asarray(seen) + 1.0, np.asarray(missed) + 1.0
    return betaln(a, b + run) - betaln(a, b)


class SensorView:
    """The directions and ranges at which the sensor sees points, learned from its observations.

    Its axes are set from the first :data:`FRAME_POINTS` points: ``x`` along their mean direction
    (the way a camera looks, whichever of its axes that is), or the sensor's own axes when the points
    lie all around it (a lidar). Each observed point's direction in those axes is counted on azimuth
    (about ``z``, from its circular mean) and elevation histograms of :data:`BIN_DEGREES` bins, and its range on a log-spaced histogram. The
    view is the azimuth-elevation box that holds all but :data:`EDGE_SHARE` of the directions at each
    edge, shrunk by :data:`EDGE_MARGIN` of its width, up to :data:`RANGE_SHARE` of the 95th
    percentile of the ranges: a camera's frustum, a lidar's band, the simulator's 150 x 90 degrees.
    Nothing is assumed about which axis looks forward.
    """

    def __init__(self) -> None:
        self.frame: FloatArray | None = None  # rows: the view's x (forward), y, z axes in the sensor frame
        self.pending: list[FloatArray] = []  # points seen before the frame is set
        self.azimuth = np.zeros(int(round(360.0 / BIN_DEGREES)), dtype=np.int64)
        self.elevation = np.zeros(int(round(180.0 / BIN_DEGREES)), dtype=np.int64)
        self.ranges = np.zeros(len(RANGE_BINS) - 1, dtype=np.int64)

    def _set_frame(self, points: FloatArray) -> None:
        """The view's axes: ``x`` along the points' mean direction, when they have one (a camera);
        the sensor's own axes when they look all around (a lidar)."""
        directions = points / np.linalg.norm(points, axis=1, keepdims=True)
        mean = directions.mean(axis=0)
        if np.linalg.norm(mean) < FORWARD_MIN:
            self.frame = np.eye(3)
            return
        forward = mean / np.linalg.norm(mean)
        helper = np.eye(3)[int(np.argmin(np.abs(forward)))]
        side = np.cross(helper, forward)
        side /= np.linalg.norm(side)
        self.frame = np.stack([forward, side, np.cross(forward, side)])

    def _angles(self, points: FloatArray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Azimuth in [0, 360), elevation in [0, 180] (from the view's -z), both degrees, and range (m)."""
        assert self.frame is not None
        points = points @ self.frame.T
        r = np.linalg.norm(points, axis=1)
        elevation = np.degrees(np.arccos(np.clip(-points[:, 2] / np.maximum(r, 1e-12), -1.0, 1.0)))
        azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360.0
        return azimuth, elevation, r

    def add(self, points: FloatArray) -> None:
        """Count the points (p, 3) of one observation, in the sensor frame (m)."""
        points = points[np.any(points != 0.0, axis=1)]
        if self.frame is None:
            self.pending.append(points)
            if sum(len(p) for p in self.pending) < FRAME_POINTS:
                return
            points = np.concatenate(self.pending)
            self.pending = []
            self._set_frame(points)
        azimuth, elevation, r = self._angles(points)
        self.azimuth += np.bincount((azimuth / BIN_DEGREES).astype(np.int64) % len(self.azimuth),
                                    minlength=len(self.azimuth))  # fmt: skip
        self.elevation += np.bincount(np.minimum((elevation / BIN_DEGREES).astype(np.int64), len(self.elevation) - 1),
                                      minlength=len(self.elevation))  # fmt: skip
        self.ranges += np.histogram(r, RANGE_BINS)[0]

    def inside(self, positions: FloatArray) -> np.ndarray:
        """Which positions (n, 3), in the sensor frame (m), lie inside the learned view."""
        if not len(positions) or self.frame is None or not self.ranges.any():
            return np.zeros(len(positions), dtype=bool)
        bins = len(self.azimuth)
        centres = (np.arange(bins) + 0.5) * np.radians(BIN_DEGREES)
        mean = np.arctan2(self.azimuth @ np.sin(centres), self.azimuth @ np.cos(centres))
        shift = int(round(np.degrees(mean) / BIN_DEGREES)) - bins // 2  # the mean direction to the middle
        az_low, az_high = _quantile_span(np.roll(self.azimuth, -shift), EDGE_SHARE)
        el_low, el_high = _quantile_span(self.elevation, EDGE_SHARE)
        az_margin, el_margin = EDGE_MARGIN * (az_high - az_low), EDGE_MARGIN * (el_high - el_low)
        cumulative = np.cumsum(self.ranges)
        reach = RANGE_BINS[1 + int(np.searchsorted(cumulative, 0.95 * cumulative[-1]))]
        azimuth, elevation, r = self._angles(positions)
        a = (azimuth / BIN_DEGREES - shift) % bins
        e = elevation / BIN_DEGREES
        return ((a >= az_low + az_margin) & (a <= az_high - az_margin) & (e >= el_low + el_margin)
                & (e <= el_high - el_margin) & (r < RANGE_SHARE * reach))  # fmt: skip

    def in_sight(self, positions: FloatArray, points: FloatArray) -> np.ndarray:
        """Which positions (n, 3) are in view of this observation's ``points`` (p, 3), both in the
        sensor frame (m): inside the learned view, with at least :data:`MIN_NEIGHBOURS` of the points
        within :data:`NEIGHBOUR_SPACINGS` of their median spacing."""
        view = self.inside(positions)
        view[view] = in_view(positions[view], points, NEIGHBOUR_SPACINGS * point_spacing(points))
        return view


class VanishedLandmarks:
    """Per-landmark counts of iterations seen, missed in view, and missed in a row; in map order.

    The filter keeps it in step with its map: :meth:`add` for new landmarks, :meth:`keep` when it
    removes some, :meth:`update` once per iteration after its update.
    """

    def __init__(self, vanished_probability: float, reach: float) -> None:
        self.log_threshold = math.log(vanished_probability)
        self.reach = reach
        self.iteration = 0
        self.born = np.zeros(0, dtype=np.int64)  # iteration each landmark started
        self.last_paired = np.zeros(0, dtype=np.int64)  # iteration each landmark was last paired
        self.origin = np.zeros((0, 3))  # where each landmark started (world, m)
        self.parent = np.zeros(0, dtype=np.int64)  # the landmark each one may have replaced, or -1
        self.seen = np.zeros(0, dtype=np.int64)
        self.missed = np.zeros(0, dtype=np.int64)
        self.streak = np.zeros(0, dtype=np.int64)
        self.view = SensorView()

    def add(self, positions: FloatArray) -> None:
        """Append new landmarks started at ``positions`` (k, 3; world, m), each seen once."""
        count = len(positions)
        self.origin = np.concatenate([self.origin, positions])
        self.parent = np.concatenate([self.parent, np.full(count, -1, dtype=np.int64)])
        now = self.iteration + 1  # the iteration being counted (update closes it)
        self.born = np.concatenate([self.born, np.full(count, now, dtype=np.int64)])
        self.last_paired = np.concatenate([self.last_paired, np.full(count, now, dtype=np.int64)])
        self.seen = np.concatenate([self.seen, np.ones(count, dtype=np.int64)])
        self.missed = np.concatenate([self.missed, np.zeros(count, dtype=np.int64)])
        self.streak = np.concatenate([self.streak, np.zeros(count, dtype=np.int64)])

    def keep(self, mask: np.ndarray) -> None:
        """Keep only the landmarks where ``mask`` (n,) is true."""
        self.seen, self.missed, self.streak = self.seen[mask], self.missed[mask], self.streak[mask]
        self.born, self.last_paired, self.origin = self.born[mask], self.last_paired[mask], self.origin[mask]
        index = np.cumsum(mask) - 1
        parent = self.parent[mask]
        alive = parent >= 0
        alive[alive] = mask[parent[alive]]
        self.parent = np.where(alive, index[np.maximum(parent, 0)], -1)

    def update(
        self, landmarks: FloatArray, points: FloatArray, rotation: FloatArray, position: FloatArray,
        paired: np.ndarray, exempt: np.ndarray,
    ) -> np.ndarray:  # fmt: skip
        """Count this iteration and return the indices of the landmarks that have vanished.

        ``landmarks`` (n, 3) are in ``world``, ``points`` (p, 3) in the sensor frame of this
        iteration, whose updated pose is ``rotation`` (3, 3) and ``position`` (3,) in ``world``;
        ``paired`` (n,) marks the landmarks paired in this iteration, ``exempt`` (n,) those whose
        misses do not count (moving landmarks the filter follows, landmarks started in this iteration).
        """
        self.view.add(points)
        in_sensor = (landmarks - position) @ rotation
        self.iteration += 1
        n = len(landmarks)
        self.seen[paired] += 1
        self.streak[paired] = 0
        self.last_paired[paired] = self.iteration
        self._adopt(landmarks, paired)
        if n == 0 or np.count_nonzero(paired) < MIN_PAIRED:
            return np.zeros(0, dtype=np.int64)
        view = self.view.in_sight(in_sensor, points)
        missed = view & ~paired & ~exempt
        if np.count_nonzero(missed) >= np.count_nonzero(view & paired):
            return np.zeros(0, dtype=np.int64)  # most of the view unpaired: the pose is off
        self.missed[missed] += 1
        self.streak[missed] += 1
        long_runs = np.flatnonzero(self.streak >= MIN_MISSES)
        chance = run_log_probability(self.seen[long_runs], self.missed[long_runs] - self.streak[long_runs],
                                     self.streak[long_runs])  # fmt: skip
        unlikely = long_runs[chance < self.log_threshold]
        return unlikely[np.isin(unlikely, self.parent)]  # replaced: the parent of a landmark (_adopt)

    def _adopt(self, landmarks: FloatArray, paired: np.ndarray) -> None:
        """Give each landmark started in this iteration its parent: the nearest older landmark within
        :attr:`reach` of where it started that this iteration did not pair (one it paired is where it
        was), last paired at most :data:`SUCCESSION_WINDOW` iterations ago."""
        new = np.flatnonzero(self.born == self.iteration)
        older = np.flatnonzero(
            (self.born < self.iteration) & ~paired & (self.last_paired >= self.iteration - SUCCESSION_WINDOW)
        )
        if not len(new) or not len(older):
            return
        d2 = np.sum((self.origin[new, None, :] - landmarks[None, older, :]) ** 2, axis=2)
        nearest = np.argmin(d2, axis=1)
        close = d2[np.arange(len(new)), nearest] <= self.reach**2
        self.parent[new[close]] = older[nearest[close]]
