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
chance agreement does not close false loops.

:func:`drift_share` then spreads the correction over the loop: drift builds up along the path, so a
group or pose from iteration ``t`` moves by the share ``(t - t0) / (k - t0)`` of the offset, where
``t0`` is when the old points were last seen and ``k`` is now. This is the linear distribution of a
loop's error used by early pose-graph relaxation, applied to the translation only: a rotation fitted
to the few points of one neighbourhood is too uncertain to be carried over the whole map.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from relpoint.geometry import FloatArray


def vote_offset(
    young: FloatArray, old: FloatArray, *, radius: float, tolerance: float, support: int
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

    Returns
    -------
    The mean of the agreeing proposals around the offset with the most distinct young points behind
    it (ties: the smallest offset), or ``None`` if fewer than :func:`required_support` agree.
    """
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
