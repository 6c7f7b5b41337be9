"""Registering points: local matching of untransformed points and global matching (Kraut, II-A and II-D).

Paper name -> Python name
    *OVLQPQuadTree*  the spatial index of point matching. Locally: the latest untransformed *Point*
                     of every recently seen *RltPoint*, sorted along x each iteration and swept within
                     the matching bound by a compiled kernel (:func:`match_nearest`);
                     ``benchmarks/relative_point.py`` times it against k-d trees and brute force at
                     100 and 540 observed points. Globally (backtracking, loop closure):
                     :class:`GlobalIndex`, a hashed grid of global positions whose cell size is the
                     matching bound, updated incrementally as positions change.

Local matching uses no current position. It can predict the previous observations into the current
sensor frame with the inter-iteration motion estimated from the previous iteration's matched
*untransformed* pairs (:class:`MotionModel`; ``predict_motion=False`` gives the paper's plain
untransformed-to-untransformed matching), which keeps the matching bound tight at high point density.
A predicted point is off by the motion's rotation error times its range, so the points a first round
leaves unmatched get a second one (:func:`match_mutual`) with a bound that grows with range. An
iteration runs all of it, the motion refreshed in between, as one compiled call
(:meth:`MotionModel.match`, :func:`~._kernels.match_recent`); :func:`match_nearest` and
:func:`match_mutual` are its two rounds on their own.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from relpoint.estimators.relative_point._kernels import (
    cell_changes,
    cell_keys,
    claim_one_to_one,
    index_refresh,
    mapped_static_cells,
    match_recent,
    mutual_nearest,
    nearest_two,
    transform_by_age,
)
from relpoint.estimators.relative_point.lsf import fit_transform
from relpoint.geometry import FloatArray, body_twist, integrate_twist, rigid_inverse

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

NO_MATCH = -1


def match_nearest(reference: FloatArray, query: FloatArray, bound: float) -> tuple[IntArray, FloatArray]:
    """One-to-one nearest-neighbour matching of ``query`` (N, 3) into ``reference`` (M, 3).

    Each query takes its nearest reference within ``bound`` (m); when several queries claim one
    reference the closest keeps it and the others fall back to their second-nearest reference if
    that one is free. The neighbour search (:func:`~._kernels.nearest_two`) scans the references
    sorted along one axis, which at these sizes beats building a k-d tree every iteration (see the
    benchmark); the claims are settled by :func:`~._kernels.claim_one_to_one`.

    Returns
    -------
    index, distance:
        (N,) row of ``reference`` matched by each query (``NO_MATCH`` if none) and its distance (inf).
    """
    n = len(query)
    if n == 0 or len(reference) == 0:
        return np.full(n, NO_MATCH, np.int64), np.full(n, np.inf)
    reference = np.ascontiguousarray(reference, dtype=np.float64)
    query = np.ascontiguousarray(query, dtype=np.float64)
    j, d = nearest_two(reference, np.argsort(reference[:, 0]), query, float(bound))
    return claim_one_to_one(j, d, len(reference))


def match_mutual(reference: FloatArray, query: FloatArray, bounds: FloatArray) -> IntArray:
    """Pair ``query`` (Q, 3) and ``reference`` (R, 3) points that are each other's nearest, within ``bounds``.

    ``bounds`` (R,) is each reference's matching bound (m). Mutual nearest neighbours only, so a
    wide bound cannot take a point that another reference is closer to. Brute force: it serves the
    few points the first round of local matching left over (:func:`~._kernels.mutual_nearest`).

    Returns
    -------
    (Q,) row of ``reference`` matched by each query, ``NO_MATCH`` if none.
    """
    if len(query) == 0 or len(reference) == 0:
        return np.full(len(query), NO_MATCH, np.int64)
    return mutual_nearest(
        np.ascontiguousarray(reference, dtype=np.float64),
        np.ascontiguousarray(query, dtype=np.float64),
        np.ascontiguousarray(bounds, dtype=np.float64),
    )


class MotionModel:
    """Inter-iteration sensor motion ``T_curr_prev`` estimated from matched untransformed points.

    ``T_curr_prev`` maps a point from the sensor frame of the previous iteration into the current one;
    it is refreshed each iteration from that iteration's matches and used to predict the next.
    ``interval_s`` is the time it spans (s; None until the stamps say): before an iteration whose
    interval differs, :meth:`to_interval` rescales it, so the prediction holds the velocity rather
    than the step. A dropped frame or an irregular rate moves the sensor in proportion to the time;
    stamps that jitter around evenly spaced frames do not: :meth:`match` tries the step as it was as
    well and keeps whichever prediction matches more points.
    """

    def __init__(self) -> None:
        self.T_curr_prev = np.eye(4)
        self.interval_s: float | None = None
        self._unscaled: FloatArray | None = None  # the motion before this iteration's rescaling
        self._starting_twist: FloatArray | None = None  # (v, w) for the first interval (start_from)

    def start_from(self, twist: FloatArray) -> None:
        """Predict the first interval with the body-frame twist ``(v (m/s), w (rad/s))`` (6,) rather than
        no motion: the sensor's motion as the log's first observations show it."""
        self._starting_twist = np.asarray(twist, dtype=np.float64)

    def to_interval(self, seconds: float) -> None:
        """Make ``T_curr_prev`` the motion over ``seconds`` at the same body-frame velocity (the process
        model of :func:`relpoint.geometry.integrate_twist`), the ratio of intervals clamped to
        [1 / :data:`MAX_INTERVAL_RATIO`, :data:`MAX_INTERVAL_RATIO`]; the first interval's from the
        starting twist, when one was given."""
        if not seconds > 0.0:
            return
        self._unscaled = None
        if self.interval_s is None and self._starting_twist is not None:
            twist, self._starting_twist = self._starting_twist, None
            # T_prev_curr is where the sensor goes; T_curr_prev carries the previous frame's points into this one
            self.T_curr_prev = rigid_inverse(integrate_twist(np.eye(4), twist[:3], twist[3:], seconds))
        if self.interval_s is not None:
            ratio = min(max(seconds / self.interval_s, 1.0 / MAX_INTERVAL_RATIO), MAX_INTERVAL_RATIO)
            if abs(ratio - 1.0) > INTERVAL_TOLERANCE:
                self._unscaled = self.T_curr_prev
                self.T_curr_prev = scaled_motion(self.T_curr_prev, ratio)
        self.interval_s = seconds

    def measured_over(self, T_curr_prev: FloatArray) -> None:
        """Predict this iteration with ``T_curr_prev`` (4, 4), measured otherwise over its whole interval
        (a registration after dropped observations), instead of the last motion rescaled."""
        self.T_curr_prev = np.asarray(T_curr_prev, dtype=np.float64)
        self._unscaled = None

    def predict(self, points: FloatArray, age: IntArray) -> FloatArray:
        """Carry points (N, 3) last observed ``age`` (N,) iterations ago (1 or more) into the current frame."""
        return transform_by_age(self.T_curr_prev, points, age)

    def update(self, previous: FloatArray, current: FloatArray, floor: float) -> FloatArray | None:
        """Re-estimate from pairs: ``previous`` (N, 3, previous frame) -> ``current`` (N, 3).

        Pairs come from one-to-one matching within the bound, so a plain fit suffices.
        """
        fit = fit_transform(previous, current, trim=0.0, floor=floor, collinear_tolerance=MOTION_COLLINEAR_TOLERANCE)
        if fit is not None:
            self.T_curr_prev = fit.T
            return fit.T
        return None

    def match(
        self, reference: FloatArray, age: IntArray, points: FloatArray, bound: float, angle: float, predict: bool
    ) -> LocalMatches:
        """Local matching of one iteration's points (N, 3) against recent points, refreshing the motion.

        ``reference`` (R, 3) are the recent points' latest observations (each in the sensor frame of
        its iteration), ``age`` (R,) iterations since each was observed. A first round matches
        :func:`match_nearest` within ``bound`` (m), against the references carried into the current
        frame by the motion when ``predict``; its pairs with references seen one iteration ago refresh
        the motion, and when that moves the prediction by more than half the bound (a turn began) the
        round is repeated from the refreshed motion. With ``predict`` and ``angle`` > 0, the points
        and references left over are paired by :func:`match_mutual` within ``bound + angle * range``
        (the predicted range, m; the motion's rotation error grows with it), and new pairs refresh
        the motion again. One compiled call (:func:`~._kernels.match_recent`).
        """
        reference = np.ascontiguousarray(reference, dtype=np.float64)
        age = np.ascontiguousarray(age, dtype=np.int64)
        points = np.ascontiguousarray(points, dtype=np.float64)
        args = (float(bound), float(angle), bool(predict), MOTION_COLLINEAR_TOLERANCE)
        row, T_curr_prev, measured, far = match_recent(reference, age, points, self.T_curr_prev, *args)
        if self._unscaled is not None and predict:  # the interval changed: the step as it was, too
            other = match_recent(reference, age, points, self._unscaled, *args)
            if np.count_nonzero(other[0] != NO_MATCH) > np.count_nonzero(row != NO_MATCH):
                row, T_curr_prev, measured, far = other
        self._unscaled = None
        self.T_curr_prev = T_curr_prev
        return LocalMatches(row, bool(measured), int(far))


def scaled_motion(T: FloatArray, ratio: float) -> FloatArray:
    """The rigid motion ``T`` (4, 4) held ``ratio`` times as long at the same body-frame velocity:
    rotation ``exp(ratio log R)``, translation ``ratio t`` (the first-order model of
    :func:`relpoint.geometry.integrate_twist`, in a few microseconds rather than scipy's 150)."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, 3] = ratio * t
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # 2 sin(angle) axis
    sine, cosine = 0.5 * float(np.linalg.norm(w)), 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    angle = math.atan2(sine, cosine)
    if angle > 3.0:  # near a half turn the axis from the antisymmetric part is ill-conditioned
        linear, angular = body_twist(np.eye(4), T, 1.0)
        return integrate_twist(np.eye(4), linear * ratio, angular * ratio, 1.0)
    rotvec = 0.5 * w * (angle / sine if sine > 1e-12 else 1.0)
    scaled = ratio * rotvec
    theta = float(np.linalg.norm(scaled))
    K = np.array([[0.0, -scaled[2], scaled[1]], [scaled[2], 0.0, -scaled[0]], [-scaled[1], scaled[0], 0.0]])
    if theta > 1e-12:
        out[:3, :3] = np.eye(3) + (math.sin(theta) / theta) * K + ((1.0 - math.cos(theta)) / theta**2) * (K @ K)
    else:
        out[:3, :3] = np.eye(3) + K
    return out


class LocalMatches(NamedTuple):
    """What :meth:`MotionModel.match` found: ``row`` (N,), the reference each point matched
    (``NO_MATCH`` if none); whether the motion was measured from this iteration's pairs; and how
    many pairs the second, range-dependent round added."""

    row: IntArray
    motion_measured: bool
    far_matches: int


MOTION_COLLINEAR_TOLERANCE = 0.05
"""RMS distance (m) off their best line below which matched points give no motion (collinear)."""
#: Most the motion is stretched (or shrunk) for an interval longer (shorter) than the one it was
#: measured over: beyond it, constant velocity is a guess rather than a prediction.
MAX_INTERVAL_RATIO = 10.0
#: Relative change of the interval below which the motion is not rescaled (a steady driver's jitter).
INTERVAL_TOLERANCE = 0.05


_KEY_SCALE = 1 << 21
"""Cell coordinates per axis a packed cell key keeps apart (see :class:`GlobalIndex`)."""
_KEY_LIMIT = _KEY_SCALE // 2 - 1
"""Largest cell coordinate (in magnitude) with a key of its own."""


class GlobalIndex:
    """Hashed grid over global positions (``world``, m): the paper's global overlapping quadtree.

    Cells are ``cell`` metres on a side; a query looks in the 27 cells around the query point, so any
    point within ``cell`` metres is found. Positions are updated incrementally: cell keys are
    compared in one vectorised step and only points that change cell touch the hash table.

    The cell with integer coordinates ``(x, y, z)`` has the key ``(x * S + y) * S + z``, ``S = 2**21``:
    one integer, linear in the coordinates (a neighbour's key is the key plus a constant) and distinct
    for every cell within ``2**20`` cells of the origin (thousands of kilometres). Coordinates are
    clipped to that range, so cells farther out share the keys of the border cells, which only adds
    candidates (callers compare distances anyway).
    """

    def __init__(self, cell: float) -> None:
        self.cell = float(cell)
        self._cells: dict[int, set[int]] = {}
        self._key = np.zeros(0, np.int64)
        self._indexed = np.zeros(0, bool)
        self._size = 0
        self._offsets = [
            (a * _KEY_SCALE + b) * _KEY_SCALE + c for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
        ]

    def __len__(self) -> int:
        return self._size

    def keys(self, positions: FloatArray) -> IntArray:
        """Cell keys (N,) of positions (N, 3) m."""
        return cell_keys(np.ascontiguousarray(positions, dtype=np.float64), self.cell, _KEY_LIMIT, _KEY_SCALE)

    def _reserve(self, largest_id: int) -> None:
        if largest_id < len(self._indexed):
            return
        capacity = max(2 * len(self._indexed), largest_id + 1, 64)
        self._key = np.concatenate([self._key, np.zeros(capacity - len(self._key), np.int64)])
        self._indexed = np.concatenate([self._indexed, np.zeros(capacity - len(self._indexed), bool)])

    def update(self, ids: IntArray, positions: FloatArray) -> None:
        """Insert or move points ``ids`` (N,) to ``positions`` (N, 3)."""
        if len(ids) == 0:
            return
        self._reserve(int(ids.max()))
        ids, keys, relocated = cell_changes(
            np.ascontiguousarray(positions, dtype=np.float64), self.cell, _KEY_LIMIT, _KEY_SCALE,
            np.ascontiguousarray(ids, dtype=np.int64), self._key, self._indexed,
        )  # fmt: skip
        self._leave(relocated)
        self._enter(ids, keys)

    def refresh(
        self, changed: IntArray, alive: BoolArray, pos_sum: FloatArray, pos_weight: FloatArray, dynamic: BoolArray
    ) -> None:
        """Bring the index up to date for the points ``changed`` (ids, repeats allowed) of a point store.

        ``alive``, ``pos_sum``, ``pos_weight`` and ``dynamic`` are the store's per-point arrays
        (:class:`~relpoint.estimators.relative_point.points.PointStore`): a live point with a global
        position (``pos_sum / pos_weight``) that is not flagged is indexed there, any other live
        point leaves the index. One compiled pass (:func:`~._kernels.index_refresh`) finds the points
        whose cell changes; only those touch the hash table.
        """
        if len(changed) == 0:
            return
        self._reserve(len(alive) - 1)
        relocated, ids, keys, leaving = index_refresh(
            changed, alive, pos_sum, pos_weight, dynamic, self.cell, _KEY_LIMIT, _KEY_SCALE, self._key, self._indexed
        )
        self._leave(relocated)
        self._enter(ids, keys)
        self._leave(leaving)

    def indexable_cells(
        self, ids: IntArray, alive: BoolArray, pos_sum: FloatArray, pos_weight: FloatArray, dynamic: BoolArray
    ) -> tuple[IntArray, IntArray]:
        """The distinct points among ``ids`` (repeats allowed) that belong in the index, ascending, and their cells' keys.

        The store's arrays as in :meth:`refresh`: live points with a global position, not flagged.
        """
        return mapped_static_cells(ids, alive, pos_sum, pos_weight, dynamic, self.cell, _KEY_LIMIT, _KEY_SCALE)

    def remove(self, ids: npt.ArrayLike) -> None:
        """Drop points from the index (unknown ids are ignored)."""
        ids = np.atleast_1d(np.asarray(ids, dtype=np.int64))
        if len(ids) == 0:
            return
        ids = ids[ids < len(self._indexed)]
        self._leave(ids[self._indexed[ids]])

    def _enter(self, ids: IntArray, keys: IntArray) -> None:
        """Put points ``ids`` (N,), not indexed now, into the cells with keys ``keys`` (N,)."""
        if len(ids) == 0:
            return
        cells = self._cells
        for i, key in zip(ids.tolist(), keys.tolist(), strict=True):
            members = cells.get(key)
            if members is None:
                cells[key] = {i}
            else:
                members.add(i)
        self._key[ids] = keys
        self._indexed[ids] = True
        self._size += len(ids)

    def _leave(self, ids: IntArray) -> None:
        """Take indexed points ``ids`` (N,) out of their cells."""
        if len(ids) == 0:
            return
        cells = self._cells
        for i, key in zip(ids.tolist(), self._key[ids].tolist(), strict=True):
            members = cells[key]
            members.discard(i)
            if not members:
                del cells[key]
        self._indexed[ids] = False
        self._size -= len(ids)

    def candidates(self, position: FloatArray) -> list[int]:
        """Ids in the 27 cells around one position (3,)."""
        x, y, z = (min(max(math.floor(v / self.cell), -_KEY_LIMIT), _KEY_LIMIT) for v in position.tolist())
        return self.candidates_at((x * _KEY_SCALE + y) * _KEY_SCALE + z)

    def candidates_at(self, key: int) -> list[int]:
        """Ids in the 27 cells around the cell with key ``key`` (from :meth:`keys`)."""
        found: list[int] = []
        cells = self._cells
        for offset in self._offsets:
            members = cells.get(key + offset)
            if members:
                found.extend(members)
        return found
