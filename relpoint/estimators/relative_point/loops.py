"""Closing loops after drift beyond the global matching bound (an addition to Kraut, section II-D).

The paper closes a loop by global matching: a point that local matching leaves over is carried into
``world`` with the current position and matched to a mapped point within the matching bound. After a
long stretch the drift of the current position and of the recent map exceeds that bound, and the
returning sensor maps old points a second time, a few metres off.

:func:`vote_offset` finds that drift. The *young* points in view (first seen a few iterations ago,
plus this iteration's unmatched ones) are carried into ``world`` with the provisional current
position; every pairing with an *old* mapped point (unseen for many iterations) within a search
radius proposes an offset, old minus young. Drift moves a whole neighbourhood alike, so the true
offset is proposed by many distinct young points, while chance pairings scatter. The offset that the
most distinct young points agree on, within a tolerance, wins when enough of them agree: at least
``support``, and more than chance explains. Chance is measured on the vote itself: the proposals
outside the winning cluster agree with ``lambda`` others on average (at least what ``P`` proposals
spread evenly over the search ball would give, ``(P - 1) (tolerance / radius)^3``), and the winner
must be beyond what the largest of ``P`` Poisson(``lambda``) counts reaches with probability 1 %.
At low density that is the plain ``support``; in a dense map, where each young point has dozens of
old neighbours and landmarks lie along the path, so that chance offsets crowd, it rises so that
chance agreement does not close false loops. Chance is not the only rival: where the scene repeats
(cabinet doors, tiles, shelves, the parallel edges of a counter), whole neighbourhoods fit onto old
points at several offsets, each with about the same support. A drift is one offset far ahead of every
other, so the best offset more than two tolerances away from the winner may gather at most
``ambiguity`` (0.4) of its support (the ratio test of feature matching applied to votes): on real
keypoints in a kitchen the false winners led their rivals by 5-100 %, where the simulator's true
loops lead by 2-4 times. A false loop moves the whole map; a true one missed at one check is found
at the next.

:func:`drift_share` then spreads the correction over the loop: drift builds up along the path, so a
group or pose from iteration ``t`` moves by the share ``(t - t0) / (k - t0)`` of the offset, where
``t0`` is when the old points were last seen and ``k`` is now: the linear distribution of a loop's
error of early pose-graph relaxation. :func:`drift_profile` refines it with the path's shape: drift is
mostly heading drift, which moves the path by a rotation that grows along it, so the error can peak
far from the loop's ends. Only the offset is measured (a rotation fitted to the few points of one
neighbourhood is too uncertain to carry over the whole map), so the profile assumes the heading
error grows at a constant rate (the mean course of a random walk known to start at zero and
end at some value is a straight line).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from relpoint.geometry import FloatArray


def vote_offset(
    young: FloatArray, old: FloatArray, *, radius: float, tolerance: float, support: int, ambiguity: float = 0.4
) -> FloatArray | None:
    """World offset (3,) taking the young points onto old ones, or ``None`` without enough agreement.

    Parameters
    ----------
    young:
        (Y, 3) young points in ``world`` through the provisional current position, metres.
    old:
        (O, 3) global positions of old mapped points, metres.
    radius:
        Largest drift looked for (m): only pairings within it propose an offset.
    tolerance:
        Proposals within this distance of each other agree (m).
    support:
        Distinct young points that must agree on the offset.
    ambiguity:
        Largest ratio of the support of a rival offset (more than ``2 tolerance`` from the winner)
        to the winner's: a scene that repeats offers several offsets with similar support.

    Returns
    -------
    The mean of the agreeing proposals around the offset with the most distinct young points behind
    it (ties: the smallest offset), or ``None`` if fewer than :func:`required_support` agree or a
    rival offset comes within ``ambiguity`` of its support.
    """
    from scipy.spatial import cKDTree  # here, not at import: scipy costs start-up time

    if len(young) < support or len(old) == 0:
        return None
    candidates = cKDTree(old).query_ball_point(young, radius)
    counts = np.fromiter((len(c) for c in candidates), np.int64, len(candidates))
    if counts.sum() < support:
        return None
    proposer = np.repeat(np.arange(len(young)), counts)
    offsets = old[np.concatenate([np.asarray(c, np.int64) for c in candidates if c])] - young[proposer]
    # Pairs of agreeing proposals, both ways, plus each proposal with itself.
    pairs = cKDTree(offsets).query_pairs(tolerance, output_type="ndarray")
    first = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(len(offsets))])
    second = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(len(offsets))])
    # Distinct young points behind each proposal's agreeing set.
    distinct = np.unique(first * len(young) + proposer[second])
    agreeing = np.bincount(distinct // len(young), minlength=len(offsets))
    best = int(np.lexsort((np.einsum("ij,ij->i", offsets, offsets), -agreeing))[0])
    members = np.unique(second[first == best])  # includes ``best`` itself
    background = np.ones(len(offsets), bool)
    background[members] = False
    chance = (len(offsets) - 1) * (tolerance / radius) ** 3
    if background.any():
        chance = max(chance, float(np.mean(agreeing[background] - 1)))
    if agreeing[best] < required_support(len(offsets), chance, support):
        return None
    rivals = np.einsum("ij,ij->i", offsets - offsets[best], offsets - offsets[best]) > (2 * tolerance) ** 2
    if rivals.any() and agreeing[rivals].max() > ambiguity * agreeing[best]:
        return None
    return offsets[members].mean(axis=0)


def required_support(proposals: int, chance: float, support: int, false_rate: float = 0.01) -> int:
    """Agreeing young points needed for the best of ``proposals`` offsets.

    The smallest ``s >= support`` with ``proposals * P(X >= s - 1) <= false_rate`` for
    ``X ~ Poisson(chance)``, ``chance`` being the mean number of other proposals that agree with one
    by chance: the best proposal gathers ``s - 1`` others by chance alone with probability at most
    ``false_rate`` over all proposals (a union bound).
    """
    term = math.exp(-chance)  # P(X = 0)
    tail = 1.0  # P(X >= 0)
    for count in range(support - 1):  # tail of P(X >= support - 1)
        tail -= term
        term *= chance / (count + 1)
    needed = support
    while proposals * tail > false_rate:
        tail -= term
        term *= chance / needed
        needed += 1
    return needed


def drift_share(iterations: npt.ArrayLike, t0: int, k: int) -> FloatArray:
    """Share of a loop's drift accumulated by ``iterations``: 0 up to ``t0``, rising linearly to 1 at ``k``."""
    span = max(k - t0, 1)
    return np.clip((np.asarray(iterations, dtype=np.float64) - t0) / span, 0.0, 1.0)


def drift_profile(path: FloatArray, offset: FloatArray, max_angle: float) -> FloatArray:
    """Correction (N, 3) m for each iteration of a loop whose path is ``path`` (N, 3), ending in ``offset``.

    Heading drift builds up along a path: with a rotation error growing at a constant rate ``w``
    (rad per iteration, 3-vector) from the loop's start, the position error at iteration ``t`` is
    ``w x W(t)``, ``W(t) = sum over tau < t of (tau - t0) * v(tau)``, ``v`` the displacement per
    iteration. The part of ``offset`` across ``W`` at the end is explained that way (minimum-norm
    ``w``); the part along it, and all of it when the implied rotation exceeds ``max_angle``, is
    spread linearly in time. Row 0 is 0, the last row ``offset``.
    """
    n = len(path)
    linear = drift_share(np.arange(n), 0, n - 1)[:, None] * offset
    if n < 3:
        return linear
    steps = np.diff(path, axis=0)
    W = np.concatenate([np.zeros((1, 3)), np.cumsum(np.arange(n - 1)[:, None] * steps, axis=0)])
    end = W[-1]
    norm2 = float(end @ end)
    if norm2 <= 1e-12:
        return linear
    across = offset - (offset @ end) / norm2 * end
    w = np.cross(end, across) / norm2
    if np.linalg.norm(w) * (n - 1) > max_angle:
        return linear
    along = offset - across
    return np.cross(w, W) + drift_share(np.arange(n), 0, n - 1)[:, None] * along
