"""Closing a loop by registering a particle's young landmarks onto its old ones (FastSLAM).

A particle filter closes a loop only if some particle has drifted little enough for the old
landmarks to fall inside its association gates. Each particle's pose and the landmarks it mapped
lately drift together, so when the path comes back (the figure eight's crossing, 1.5-5.5 m of drift
after 470 iterations) the points of the old landmarks pair with nothing, start new landmarks, and
the map keeps two copies of every landmark of the overlap: the loop stays open.

What shows the loop is the map itself: landmarks started lately (*young*, the last
:data:`YOUNG_ITERATIONS`) sit at one common offset from landmarks not seen for
:data:`OLD_ITERATIONS` (*old*), the offset being the drift. :func:`register_loop` finds that offset
by a vote: every young landmark proposes the offsets to the old landmarks within ``reach`` of it,
the offsets are binned at the ``tolerance`` (two points' noise), and the best-supported offset is
refined as the mean over the young landmarks that agree with it, one old landmark each.

A loop is taken only when the agreement is far beyond chance. Were the young landmarks placed at
random among the old ones, a young landmark with ``c`` old ones within ``reach`` would agree with a
given offset with probability about ``c (tolerance / reach)^2`` (landmarks lie on surfaces, so
areas rather than volumes: the larger and more cautious of the two). The number that agree by chance
is then Poisson with the sum of those as its mean, and a loop needs a support whose Poisson tail is
below :data:`FALSE_LOOP_PROBABILITY`. On the 7-Scenes kitchen keypoints, where the camera comes back
to the same corners every few seconds, the strongest offset had a tail of 5e-5; at the figure eight's
crossing the true offset's is below 1e-30.

Positions in ``world`` (m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import pdtrc

from relpoint.geometry import FloatArray

#: Landmarks started within this many iterations are the young map that may duplicate an old one.
YOUNG_ITERATIONS = 50
#: Landmarks not seen for this many iterations are the old map a loop comes back to.
OLD_ITERATIONS = 100
#: The vote's tolerance in point noises per axis, times sqrt(2) (a young and an old landmark's
#: position, each about one point's noise off): the offset bins and what agreeing means.
LOOP_TOLERANCE_SIGMAS = 2.0
#: Young landmarks that must agree on the offset, at the least.
MIN_SUPPORT = 5
#: Tail probability of the agreement under chance below which the offset is taken for a loop.
FALSE_LOOP_PROBABILITY = 1e-9
#: Most offset bins whose exact support is counted.
TOP_BINS = 8
#: Most young-old pairs a vote holds (memory and time stay bounded in dense maps): beyond it, an
#: evenly strided share of the young landmarks votes.
MAX_PAIRS = 200_000


@dataclass(frozen=True)
class LoopClosure:
    """A loop found by :func:`register_loop`."""

    shift: FloatArray  # (3,): offset young -> old (m, world): what the pose and young map are moved by
    support: int  # young landmarks that agree on it
    candidates: int  # young landmarks with an old landmark within reach
    expected: float  # young landmarks expected to agree by chance
    log10_tail: float  # log10 of the chance of that support or more


def register_loop(young: FloatArray, old: FloatArray, tolerance: float, reach: float) -> LoopClosure | None:
    """The common offset from the ``young`` landmarks (Y, 3) to the ``old`` ones (O, 3), if it is a
    loop (module docstring); None otherwise, and when the offset is within ``tolerance`` (m) (the
    association pairs them without help). ``reach`` (m) bounds the offset.
    """
    if len(young) < MIN_SUPPORT or len(old) < MIN_SUPPORT or tolerance <= 0 or reach <= tolerance:
        return None
    tree = cKDTree(old)
    counts = np.asarray(tree.query_ball_point(young, r=reach, return_length=True), dtype=np.int64)
    if counts.sum() > MAX_PAIRS:
        young = young[:: int(np.ceil(counts.sum() / MAX_PAIRS))]
    lists = tree.query_ball_point(young, r=reach)
    counts = np.fromiter((len(near) for near in lists), dtype=np.int64, count=len(young))
    candidates = int(np.count_nonzero(counts))
    if candidates < MIN_SUPPORT:
        return None
    young_of_pair = np.repeat(np.arange(len(young)), counts)
    old_of_pair = np.fromiter((j for near in lists for j in near), dtype=np.int64, count=int(counts.sum()))
    offsets = old[old_of_pair] - young[young_of_pair]  # (P, 3)
    # Vote: distinct young landmarks per offset bin, the best bins counted exactly.
    bins = np.floor(offsets / tolerance).astype(np.int64)
    _, bin_of_pair = np.unique(bins, axis=0, return_inverse=True)
    bin_of_pair = bin_of_pair.reshape(-1)
    votes = np.unique(np.column_stack([bin_of_pair, young_of_pair]), axis=0)[:, 0]
    tally = np.bincount(votes)
    best_shift, best_support = np.zeros(3), 0
    for b in np.argsort(tally)[::-1][:TOP_BINS]:
        if tally[b] < MIN_SUPPORT:
            break
        centre = offsets[bin_of_pair == b].mean(axis=0)
        agree, shift = _agreement(offsets, young_of_pair, centre, tolerance)
        if len(agree) > best_support:
            best_shift, best_support = shift, len(agree)
    if best_support < MIN_SUPPORT or np.linalg.norm(best_shift) <= tolerance:
        return None
    expected = float(counts.sum() * (tolerance / reach) ** 2)
    tail = float(pdtrc(best_support - 1, expected))
    if tail > FALSE_LOOP_PROBABILITY:
        return None
    return LoopClosure(best_shift, best_support, candidates, expected, float(np.log10(max(tail, 1e-300))))


def _agreement(
    offsets: FloatArray, young_of_pair: np.ndarray, centre: FloatArray, tolerance: float
) -> tuple[np.ndarray, FloatArray]:
    """The young landmarks with a pair within ``tolerance`` of ``centre`` (each by its nearest such
    pair), and the mean offset of those pairs, refined once."""
    for _ in range(2):
        distance = np.linalg.norm(offsets - centre, axis=1)
        inside = np.flatnonzero(distance < tolerance)
        if not len(inside):
            return np.zeros(0, dtype=np.int64), centre
        order = inside[np.argsort(distance[inside], kind="stable")]
        _, first = np.unique(young_of_pair[order], return_index=True)
        chosen = order[first]
        centre = offsets[chosen].mean(axis=0)
    return young_of_pair[chosen], centre
