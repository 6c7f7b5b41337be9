"""Landmarks that move, told apart from static ones by their smoothed innovations (FastSLAM).

A filter that pairs points with landmarks by their predicted position takes a moving point for a
landmark until the point leaves the landmark's gate, and then starts a new landmark, again and
again: every mover leaves a trail of duplicates, and each of them pulls the pose while it is paired.

The test here needs no sensor model. A paired point's *innovation* is the point, placed in
``world`` by the particle's pose, minus its landmark's mean (m). For a static landmark it is noise
of covariance ``S = R Q R^T + C`` (the point's noise in ``world`` plus the landmark's covariance)
once the error that every pair of the iteration shares, the pose's, is taken out: the per-axis
median innovation of the particle's pairs (the static landmarks are the bulk). A landmark that
moves shows up ahead of its mean, in the direction it moves, iteration after iteration; so the
exponentially smoothed innovation ``d <- (1 - a) d + a v`` of a static landmark has covariance
``S a / (2 - a)`` and a moving one's leaves the gate ``d^T (S a / (2 - a))^-1 d > chi2(p, 3)``.

A landmark seen at least :data:`MIN_SEEN` times whose ``d`` leaves the gate, and is longer than
:data:`MIN_MOTION_SIGMAS` point noises (a real keypoint slides by a noise or two as the viewpoint
changes), is *moving*. Its position
says nothing about the pose: before each association its covariance is widened by a variance as wide
as the search (:meth:`MotionTest.widen`), so it takes the point nearest to it without pulling the
pose, and the landmark update then places it on that point. It follows its mover instead of leaving
duplicates, and the map reports it as dynamic. It is static again when its smoothed motion, against
``2 R Q R^T`` (the noise of two successive points), falls back inside the 25 % gate: a mover that
stopped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.geometry import FloatArray, skew
from relpoint.settings import Settings, setting
from relpoint.statistics import chi2_gate

#: Weight of the newest innovation in the smoothed one.
SMOOTHING = 0.3
#: Pairings a landmark needs before it can be taken for a mover (a new landmark's first innovations
#: are mostly its own initial error).
MIN_SEEN = 3
#: A landmark is taken for a mover only once its smoothed innovation is this many point noises long
#: (per axis, scaled like the gate): real keypoints slide by a noise or two as the viewpoint changes.
MIN_MOTION_SIGMAS = 3.0
#: Median of the chi-square distribution with 3 degrees of freedom: ``chi2_gate(0.5, 3)``, written out
#: so that the settings below import without scipy (``tests/test_landmark_motion.py`` checks it).
CHI2_MEDIAN_3 = 2.3659738843753377
#: Chi-square probability of the gate under which a moving landmark is static again. A static
#: landmark flagged by mistake falls inside it a quarter of the time (released in about 4
#: iterations); a slow mover, whose smoothed motion is one or two noises, dips under the median (the
#: 50 % gate) by chance and was released there, then left the association's reach and came back as
#: a duplicate (figure8-line-40-fast). Measured: with 0.25 instead of 0.5 the EKF's duplicates there
#: fall from 1.9 % to 1.0 % of the map on seeds 0-1 (4.3-10.2 % to 2.7-7.5 % on seeds 2-5), the 30 %-dynamic figure eight's EKF ATE over seeds 0-4 from
#: 6.2 to 4.7 m, FastSLAM's on the 7-Scenes kitchen from 5.7 to 4.8 cm; the EKF on the kitchen and
#: on Starry Night stays within 3 % (3.62 -> 3.63 cm, 0.115 -> 0.119 m). With 0.1 the kitchen's
#: EKF lost 0.9 mm.
RELEASE_PROBABILITY = 0.25
#: How far a moving landmark may get from its next point, in observation sigmas (5 m at the
#: simulator's 0.3 m): the EKF's hand-over radius, and twice the widening of a moving landmark
#: (FastSLAM uses its search radius, whose default is the same).
REACH_SIGMAS = 5.0 / 0.3
#: Iterations a landmark that is no longer paired stays a candidate for a hand-over (a mover's points
#: may fall between the association gate and the new-landmark gate for a few iterations first).
HAND_OVER_MEMORY = 3
#: A particle hands landmarks over only while it pairs at least this many points in the iteration,
#: and more than the landmarks it saw the iteration before and does not pair now (else its pose has
#: drifted, every landmark seems to move, and new landmarks are what lets it recover).
MIN_PAIRED = 8
#: The EKF's :data:`MIN_PAIRED`: a single hypothesis has no other particles to outvote a wrong flag,
#: and with 8 pairs Starry Night's EKF (about 5 landmarks in view, 8 or more in a few frames) flagged
#: static landmarks (landmark RMSE 0.50 m against 0.26 m with 10).
EKF_MIN_PAIRED = 10


@dataclass(frozen=True)
class MovingLandmarkSettings(Settings):
    """The moving-landmark settings the filters share (EKF-SLAM and FastSLAM inherit them)."""

    follow_movers: bool = setting(True)
    """Tell moving landmarks apart by their smoothed innovations and let them follow their points
    without pulling the pose (:mod:`relpoint.estimators._landmark_motion`); the map flags them dynamic.
    Off: a mover pulls the pose and leaves a trail of duplicate landmarks."""
    mover_gate_probability: float = setting(0.999, above=0, below=1)
    """Chi-square probability of the gate a static landmark's smoothed innovation stays inside."""
    hand_over_movers: bool = setting(True)
    """With ``follow_movers``: a point that would start a landmark, near a landmark paired lately and
    missed now, is that landmark having moved (:func:`relpoint.estimators._landmark_motion.hand_over`)."""
    drop_vanished: bool = setting(True)
    """Drop a landmark that was paired regularly and is then missed, again and again, while points
    all around its position are seen (:mod:`relpoint.estimators._vanished`): the place a mover left.
    Without it, every stop-and-go mover leaves a duplicate landmark behind each time it moves on."""
    vanished_probability: float = setting(1e-3, above=0, below=1)
    """With ``drop_vanished``: a landmark vanishes once its current run of misses in view would have
    less than this probability under its own detection rate (and is at least 5 long)."""


def median_by_group(group: npt.NDArray[np.int64], values: FloatArray, groups: int) -> FloatArray:
    """Per row of ``values`` (k, d): the per-axis median over the rows of the same ``group`` (ids in
    ``[0, groups)``, sorted ascending, as ``np.nonzero`` returns them).

    Each group's values are laid out in a row of a table (padded with NaN, which sorts last, as it
    does among a group's own values) and the rows sorted stably: the same order a ``lexsort`` by
    group and value gives, at a fraction of its cost for thousands of rows.
    """
    medians = np.empty_like(values)
    if len(group) == 0:
        return medians
    counts = np.bincount(group, minlength=groups)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(len(group)) - starts[group]  # each row's place in its group
    middle_low, middle_high = ((counts - 1) // 2)[group], (counts // 2)[group]
    table = np.empty((groups, int(counts.max())), dtype=values.dtype)
    for axis in range(values.shape[1]):
        table.fill(np.nan)
        table[group, rank] = values[:, axis]
        table.sort(axis=1, kind="stable")
        medians[:, axis] = 0.5 * (table[group, middle_low] + table[group, middle_high])
    return medians


def candidate_slots(
    near: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]], points: npt.NDArray[np.int64]
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Every (entry, candidate slot) pair of the association's candidates ``near`` (CSR ``offsets,
    slots`` per point) for the points ``points`` (k,): the entry's index into ``points`` and the slot."""
    offsets, slots = near
    per_point = offsets[points + 1] - offsets[points]
    owner = np.repeat(np.arange(len(points)), per_point)
    first = np.repeat(offsets[points] - np.cumsum(per_point) + per_point, per_point)
    return owner, slots[first + np.arange(len(owner))]


def hand_over(
    assoc: npt.NDArray[np.int64],
    near: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]],
    counts: npt.NDArray[np.int64],
    last_seen: npt.NDArray[np.int64],
    iteration: int,
    positions: FloatArray,
    rotations: FloatArray,
    points: FloatArray,
    means: FloatArray,
    radius: float,
    min_pairs: int = MIN_PAIRED,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The landmarks that moved out of their gate, and the points they moved to: ``(p, i, j)``.

    A point ``i`` that particle ``p`` would start a landmark from (``assoc[p, i] == -1``), within ``radius`` (m, ``world``) of a landmark ``j`` of the
    particle that was paired in the last :data:`HAND_OVER_MEMORY` iterations but not in this one
    (``last_seen[p, j]``, with this iteration's pairs already marked ``iteration``), is that landmark
    having moved: a static landmark is paired whenever it is seen. Points discarded between the
    gates (-2) are not handed over: on real data with its noise underestimated a static landmark's
    points land there often, several in a row (Starry Night: 7 % of the points), and the landmark
    would be taken for a mover. Each landmark and each point is
    handed over once (nearest pairs first; a point or landmark whose nearest pair conflicts is left
    alone), and only in particles that pair at least ``min_pairs`` points and more than they
    miss of the landmarks seen lately.

    ``near`` is the association's candidates (CSR ``offsets, slots`` per point); ``positions`` (P, 3),
    ``rotations`` (P, 3, 3) ``R_world_sensor``; ``points`` (N, 3) sensor frame; ``means`` (P, M, 3).
    """
    empty = np.zeros(0, dtype=np.int64)
    paired = (assoc >= 0).sum(axis=1)
    lately = (last_seen >= iteration - HAND_OVER_MEMORY) & (last_seen < iteration)
    steady = (paired >= min_pairs) & (paired > lately.sum(axis=1))
    p, i = np.nonzero((assoc == -1) & steady[:, None])
    owner, j = candidate_slots(near, i)
    if len(j) == 0:
        return empty, empty, empty
    p, i = p[owner], i[owner]
    live = j < counts[p]
    p, i, j = p[live], i[live], j[live]
    recent = lately[p, j]
    p, i, j = p[recent], i[recent], j[recent]
    world = positions[p] + np.einsum("kab,kb->ka", rotations[p], points[i])
    distance = np.linalg.norm(world - means[p, j], axis=1)
    close = distance < radius
    p, i, j, distance = p[close], i[close], j[close], distance[close]
    order = np.argsort(distance, kind="stable")
    p, i, j = p[order], i[order], j[order]
    # Nearest pairs first: keep a pair only if neither its point nor its landmark was taken before.
    _, first_point = np.unique(p * (points.shape[0] + 1) + i, return_index=True)
    _, first_landmark = np.unique(p * (means.shape[1] + 1) + j, return_index=True)
    keep = np.intersect1d(first_point, first_landmark)
    return p[keep], i[keep], j[keep]


def shared_motion_removed(
    group: npt.NDArray[np.int64], innovations: FloatArray, offsets: FloatArray, groups: int
) -> FloatArray:
    """``innovations`` (k, 3) less the small rigid motion each group's pairs share (its pose error).

    A pose error ``(t, w)`` (translation, small rotation) moves a landmark at ``offsets`` (k, 3, m, the
    landmark less the sensor position, ``world``) by ``t + w x offset``: fitted per group by least
    squares, first from every pair, then again without the pairs whose residual is over three times
    the group's median residual (the movers, mostly). ``group`` ids are in ``[0, groups)``, ascending.
    Groups of fewer than 3 (weighted) pairs keep their innovations.
    """
    weights = np.ones(len(group))
    residual = innovations
    for _ in range(2):
        shared = _fit_small_motion(group, innovations, offsets, weights, groups)
        residual = innovations - shared[group, :3] - cross(shared[group, 3:], offsets)
        size = np.linalg.norm(residual, axis=1)
        weights = (size <= 3.0 * median_by_group(group, size[:, None], groups)[:, 0]).astype(np.float64)
    return residual


def _fit_small_motion(
    group: npt.NDArray[np.int64], innovations: FloatArray, offsets: FloatArray, weights: FloatArray, groups: int
) -> FloatArray:
    """Per group, the weighted least-squares ``(t, w)`` (groups, 6) of ``innovation ~ t + w x offset``.

    The normal equations of the rows ``A = [I, -[r]x]`` are summed in closed form,
    ``A^T A = [[I, -[r]x], [[r]x, |r|^2 I - r r^T]]`` and ``A^T v = [v, r x v]``, with one weighted
    ``bincount`` per entry; a group with less than 3 of weight gets zero motion.
    """

    def total(values: FloatArray) -> FloatArray:
        return np.bincount(group, weights=weights * values, minlength=groups)

    r, v = offsets, innovations
    count = total(np.ones(len(group)))
    r_sum = np.stack([total(r[:, a]) for a in range(3)], axis=1)
    products = {(a, b): total(r[:, a] * r[:, b]) for a in range(3) for b in range(a, 3)}  # r_a r_b is r_b r_a
    rr = np.stack([np.stack([products[min(a, b), max(a, b)] for b in range(3)], axis=1) for a in range(3)], axis=1)
    normal = np.zeros((groups, 6, 6))
    normal[:, :3, :3] = count[:, None, None] * np.eye(3)
    normal[:, :3, 3:] = -skew(r_sum)
    normal[:, 3:, :3] = skew(r_sum)
    normal[:, 3:, 3:] = np.trace(rr, axis1=1, axis2=2)[:, None, None] * np.eye(3) - rr
    rxv = cross(r, v)
    right = np.stack([total(v[:, a]) for a in range(3)] + [total(rxv[:, a]) for a in range(3)], axis=1)
    enough = count >= 3
    normal[~enough] = np.eye(6)
    right[~enough] = 0.0
    return np.linalg.solve(normal + 1e-9 * np.eye(6), right[:, :, None])[:, :, 0]


def cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross products ``a x b`` of (k, 3) arrays: ``np.cross``'s arithmetic (each component one
    product less another), without its axis handling, which costs several times more at these sizes."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def inverse_3x3(matrices: FloatArray) -> FloatArray:
    """Inverses of invertible 3x3 matrices (k, 3, 3) by their adjugates (several times faster than
    ``np.linalg.inv`` on many small matrices)."""
    m = matrices
    adjugate = np.empty_like(m)
    adjugate[:, 0, 0] = m[:, 1, 1] * m[:, 2, 2] - m[:, 1, 2] * m[:, 2, 1]
    adjugate[:, 0, 1] = m[:, 0, 2] * m[:, 2, 1] - m[:, 0, 1] * m[:, 2, 2]
    adjugate[:, 0, 2] = m[:, 0, 1] * m[:, 1, 2] - m[:, 0, 2] * m[:, 1, 1]
    adjugate[:, 1, 0] = m[:, 1, 2] * m[:, 2, 0] - m[:, 1, 0] * m[:, 2, 2]
    adjugate[:, 1, 1] = m[:, 0, 0] * m[:, 2, 2] - m[:, 0, 2] * m[:, 2, 0]
    adjugate[:, 1, 2] = m[:, 0, 2] * m[:, 1, 0] - m[:, 0, 0] * m[:, 1, 2]
    adjugate[:, 2, 0] = m[:, 1, 0] * m[:, 2, 1] - m[:, 1, 1] * m[:, 2, 0]
    adjugate[:, 2, 1] = m[:, 0, 1] * m[:, 2, 0] - m[:, 0, 0] * m[:, 2, 1]
    adjugate[:, 2, 2] = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    determinant = m[:, 0, 0] * adjugate[:, 0, 0] + m[:, 0, 1] * adjugate[:, 1, 0] + m[:, 0, 2] * adjugate[:, 2, 0]
    return adjugate / determinant[:, None, None]


class MotionTest:
    """The moving-landmark test and what follows from it, over arrays of paired landmarks.

    Parameters
    ----------
    gate_probability: chi-square probability of the gate on the smoothed innovation (3 dof).
    reach: how far (m) a moving landmark may be from its next point (the association's search
        radius); its covariance is widened by ``(reach / 2)^2`` per axis before each association.
    min_pairs: pairs an iteration (particle) needs before it may start a flag or hand a landmark over.
    """

    def __init__(self, gate_probability: float, reach: float, min_pairs: int = MIN_PAIRED) -> None:
        self.gate = chi2_gate(gate_probability, 3)
        self.release = chi2_gate(RELEASE_PROBABILITY, 3)
        self.reach = reach
        self.min_pairs = min_pairs
        self.widening = (reach / 2.0) ** 2

    def classify(
        self,
        group: npt.NDArray[np.int64],
        groups: int,
        innovations: FloatArray,
        point_covariances: FloatArray,
        landmark_covariances: FloatArray,
        drift: FloatArray,
        moving: npt.NDArray[np.bool_],
        seen: npt.NDArray[np.int64],
    ) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
        """The new smoothed innovations (k, 3) and moving flags (k,) of k paired landmarks.

        ``group`` (k,) the particle of each pair (ids in ``[0, groups)``, ascending; all 0 for an EKF);
        ``innovations`` (k, 3, m, ``world``) with the pose's shared error already taken out;
        ``point_covariances`` ``R Q R^T`` (k, 3, 3) and ``landmark_covariances`` (k, 3, 3);
        ``drift``, ``moving`` and ``seen`` the landmarks' smoothed innovations, flags and pairing
        counts so far.

        Two things come from the data rather than the noise model. Only groups that pair at least
        ``min_pairs`` points (:data:`MIN_PAIRED` by default) start a flag (with fewer, one landmark's motion cannot be told from
        the pose's). And the gates scale with the group's own innovations: by the median of their
        normalised squares over its chi-square median, when that is above 1 (real sensors' noise
        grows with range and is often larger than the ``observation_sigma`` the filter is given;
        without this a static real scene has a fifth of its landmarks flagged).
        """
        a = SMOOTHING
        drift = (1.0 - a) * drift + a * innovations
        # A moving landmark sits on its last point: its innovation is the motion plus two points' noise.
        S = np.where(moving[:, None, None], 2.0 * point_covariances, point_covariances + landmark_covariances)
        S_inv = inverse_3x3(S)
        squared = np.einsum("ki,kij,kj->k", innovations, S_inv, innovations)
        scale = np.maximum(median_by_group(group, squared[:, None], groups)[:, 0] / CHI2_MEDIAN_3, 1.0)
        nis = np.einsum("ki,kij,kj->k", drift, S_inv, drift) * ((2.0 - a) / a) / scale
        decidable = (np.bincount(group, minlength=groups) >= self.min_pairs)[group]
        # A steady offset smaller than a few points' noise is what a real keypoint's position does as the
        # viewpoint changes (it slides along an edge, its depth drifts with range): not motion.
        noise = scale * np.trace(point_covariances, axis1=1, axis2=2) / 3.0
        far = np.einsum("ki,ki->k", drift, drift) > MIN_MOTION_SIGMAS**2 * noise
        started = decidable & (seen >= MIN_SEEN) & (nis > self.gate) & far
        return drift, np.where(moving, nis > self.release, started)

    def widen(self, covariances: FloatArray, moving: npt.NDArray[np.bool_]) -> None:
        """Widen the covariances of the moving landmarks (``covariances[moving]``, in place)."""
        where = np.nonzero(moving)  # one pass over the flags, not three (any, read, write)
        if len(where[0]):
            covariances[where] += self.widening * np.eye(3)
