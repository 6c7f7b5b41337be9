"""Dynamic point detection before a group is final (Kraut, section II-C).

Two points that are both static keep their distance in every untransformed observation, whatever
the sensor does, so the standard deviation of their distance over the group's interval is at the
noise level; a moving point breaks that with every other point. The paper's binning makes the
search O(n log n):

* each point starts in its own bin; each round, every bin is compared with one bin it has not been
  compared with, through one representative point per bin; a standard deviation below the
  threshold merges the two bins, otherwise each remembers the other (the paper's per-bin hash
  table) so the pair is never compared again;
* the threshold comes from the first round: its deviations are sorted and enumerated until the next
  one is much larger (by ``gap_ratio``) than the previous, the gap rule;
* bins merged in the previous round are paired first (positive comparisons are prioritised);
* once one bin holds a majority of the points, one last round compares it with every bin it has not
  been compared with and merges the positive ones; everything outside it is dynamic.

Each round compares at most n/2 pairs of L-iteration tracks in one vectorised step.

Between detections the majority bin persists as the points verified static;
:func:`deviation_to_references` judges further points against several of its members, as the last
round judges a bin against the majority bin (used by the estimator's periodic sweep).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.estimators.relative_point._kernels import block_mean_scatter, reference_deviations
from relpoint.geometry import FloatArray

BoolArray = npt.NDArray[np.bool_]

_PAIRING_SCAN = 8


@dataclass(frozen=True)
class DynamicResult:
    """Outcome of :func:`detect_dynamic`.

    static: (M,) True for members of the majority bin (all True when undecided).
    decided: a bin reached a majority (or the largest bin was accepted at the end).
    threshold: standard deviation threshold from the gap rule (m).
    comparisons: pairwise track comparisons made.
    rounds: comparison rounds run.
    """

    static: BoolArray
    decided: bool
    threshold: float
    comparisons: int
    rounds: int


def distance_deviation(observations: FloatArray, a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Standard deviation (P,) over iterations of the distance between tracks ``a`` and ``b`` (P,).

    ``observations`` is (M, L, 3): untransformed points of M tracks over L iterations.
    """
    difference = observations[np.asarray(a)] - observations[np.asarray(b)]
    distance = np.sqrt(np.einsum("plk,plk->pl", difference, difference))
    return distance.std(axis=1, ddof=1)


def gap_threshold(deviations: FloatArray, gap_ratio: float, noise_factor: float = 1.6) -> float:
    """The paper's gap rule over the first round's deviations (P,).

    Sorted ascending, the threshold sits between the first consecutive pair whose ratio exceeds
    ``1 + gap_ratio`` (geometric mean of the two); with no such gap every deviation is below it.
    Moving points rarely leave a clean gap (their deviations spread from the noise level upwards), so
    the threshold is also capped at ``noise_factor`` times the lower quartile, which is a static
    pair's deviation while fewer than half of the points move (0.5^2 of the pairs are static-static).
    """
    s = np.sort(np.maximum(deviations[np.isfinite(deviations)], 1e-6))
    if len(s) == 0:
        return np.inf
    ratio = s[1:] / s[:-1]
    gaps = np.flatnonzero(ratio > 1.0 + gap_ratio)
    threshold = float(s[-1] * (1.0 + gap_ratio)) if len(gaps) == 0 else float(np.sqrt(s[gaps[0]] * s[gaps[0] + 1]))
    if noise_factor > 0 and len(s) >= 8:
        threshold = min(threshold, noise_factor * float(s[len(s) // 4]))
    return threshold


def detect_dynamic(
    observations: FloatArray,
    *,
    gap_ratio: float = 0.5,
    noise_factor: float = 1.6,
    min_static: int = 3,
    floor: float = 0.0,
) -> DynamicResult:
    """Find the points that do not move rigidly with the majority.

    Parameters
    ----------
    observations:
        (M, L, 3) untransformed observations of the M candidate members over the group's L
        iterations (each iteration in its own sensor frame), metres; L >= 2.
    gap_ratio:
        Relative jump in sorted first-round deviations that sets the threshold.
    noise_factor:
        Cap of the threshold as a multiple of the first round's lower-quartile deviation (0: none).
    min_static:
        Smallest bin accepted as the static set when no bin reaches a majority.
    floor:
        Smallest threshold (m): what the observation noise alone gives a static pair.

    Returns
    -------
    DynamicResult
    """
    m = len(observations)
    if m < 4 or observations.shape[1] < 2:
        return DynamicResult(np.ones(m, bool), False, np.inf, 0, 0)
    bins: dict[int, list[int]] = {i: [i] for i in range(m)}  # bin id = its representative's row
    compared: dict[int, set[int]] = {i: set() for i in range(m)}
    comparisons = 0
    rounds = 0

    def was_compared(a: int, b: int) -> bool:
        return b in compared[a] or a in compared[b]

    def merge(a: int, b: int) -> None:
        bins[a].extend(bins.pop(b))
        compared[a] |= compared.pop(b)

    # First round: neighbours in row order; its deviations set the threshold (gap rule).
    first_a = np.arange(0, m - 1, 2)
    first_b = first_a + 1
    deviation = distance_deviation(observations, first_a, first_b)
    comparisons += len(first_a)
    rounds += 1
    threshold = max(gap_threshold(deviation, gap_ratio, noise_factor), floor)

    def settle(pairs_a: list[int], pairs_b: list[int], deviation: FloatArray) -> set[int]:
        """Merge the pairs below the threshold, remember the rest; the bins merged into."""
        merged: set[int] = set()
        for a, b, dev in zip(pairs_a, pairs_b, deviation.tolist(), strict=True):
            if dev < threshold:
                merge(a, b)
                merged.add(a)
            else:
                compared[a].add(b)
                compared[b].add(a)
        return merged

    positive = settle(first_a.tolist(), first_b.tolist(), deviation)

    majority = None
    while True:
        largest = max(bins, key=lambda k: len(bins[k]))
        if 2 * len(bins[largest]) > m:
            majority = largest
            break
        # Pair bins: those with a positive comparison last round first, then larger bins first.
        order = sorted(bins, key=lambda k: (k not in positive, -len(bins[k]), k))
        waiting: list[int] = []  # bins still looking for a partner this round, in priority order
        pairs_a: list[int] = []
        pairs_b: list[int] = []
        for b in order:
            # Looking at only the first few waiting bins keeps a round O(n) when many bins have
            # already met each other; a missed pairing is found in a later round.
            for index, a in enumerate(waiting[:_PAIRING_SCAN]):
                if not was_compared(a, b):
                    del waiting[index]
                    pairs_a.append(a)
                    pairs_b.append(b)
                    break
            else:
                waiting.append(b)
        if not pairs_a:
            break
        deviation = distance_deviation(observations, pairs_a, pairs_b)
        comparisons += len(pairs_a)
        rounds += 1
        positive = settle(pairs_a, pairs_b, deviation)

    if majority is not None:
        # Last round: the majority bin against every bin it has not met; positives join it.
        others = [k for k in bins if k != majority and not was_compared(majority, k)]
        if others:
            deviation = distance_deviation(observations, [majority] * len(others), others)
            comparisons += len(others)
            rounds += 1
            for k, dev in zip(others, deviation.tolist(), strict=True):
                if dev < threshold:
                    merge(majority, k)
        static_bin = majority
    else:
        static_bin = max(bins, key=lambda k: len(bins[k]))
        if len(bins[static_bin]) < min_static:
            return DynamicResult(np.ones(m, bool), False, threshold, comparisons, rounds)
    static = np.zeros(m, bool)
    static[bins[static_bin]] = True
    return DynamicResult(static, True, threshold, comparisons, rounds)


def tail_bound(values: FloatArray, sigmas: float, min_count: int = 8) -> float:
    """Where the bulk of positive ``values`` (N,) ends on a log scale (0 when it cannot be told).

    ``exp(median(log v) + sigmas * 1.4826 * MAD(log v))`` over the finite positive values: a
    deviation or ratio above it stands out from the points judged beside it whatever the shape of
    their noise. On a simulator's white noise the bulk is narrow and the bound sits near twice the
    median; a real sensor's heavy-tailed, range-dependent error widens it (on 7-Scenes keypoints to
    about 3.6 times the median), so a factor on the median alone would flag its tail as moving. The
    median absolute deviation resists movers but not entirely: far outliers among the values widen
    the bound by about 15 % at a tenth of them, 40 % at a fifth and twofold at 30 % (the cost on the
    simulator's crowded scenes is a little recall; the factors still bind where the bulk is narrow).
    Fewer than ``min_count`` usable values, or ``sigmas <= 0``: 0 (no bound).
    """
    usable = values[np.isfinite(values) & (values > 0)]
    if sigmas <= 0 or len(usable) < min_count:
        return 0.0
    logs = np.log(usable)
    centre = float(np.median(logs))
    return float(np.exp(centre + sigmas * 1.4826 * float(np.median(np.abs(logs - centre)))))


def row_nanmedian(values: FloatArray) -> FloatArray:
    """Median of each row (N, K) over its finite entries (NaN where none): ``np.nanmedian(axis=1)``, one sort."""
    ordered = np.sort(values, axis=1)  # NaN sort last
    count = np.count_nonzero(np.isfinite(ordered), axis=1)
    rows = np.arange(len(ordered))
    low = ordered[rows, np.maximum(count - 1, 0) // 2]
    high = ordered[rows, count // 2 - (count == 0)]
    return np.where(count > 0, 0.5 * (low + high), np.nan)


def world_block_deviation(tracks: FloatArray, valid: BoolArray, poses: FloatArray, block: int) -> FloatArray:
    """RMS scatter (N,) of each track's block-mean position in ``world`` (m; NaN under three blocks).

    A witness beside the relative distances: the observations are mapped to ``world`` by the
    poses of their iterations and averaged over blocks of ``block`` iterations; a static point's
    block means scatter by the noise over ``sqrt(block)`` plus pose jitter, a moving point's by its
    motion in every direction (a distance to a reference only sees the motion along it).

    Parameters
    ----------
    tracks:
        (N, L, 3) untransformed observations (sensor frame of each iteration), metres.
    valid:
        (N, L) where each track has an observation.
    poses:
        (L, 4, 4) ``T_world_sensor`` of the L iterations.
    block:
        Iterations per block (blocks count from the latest iteration; blocks with fewer than two
        observations are ignored).
    """
    return block_mean_scatter(
        np.ascontiguousarray(tracks, dtype=np.float64),
        np.ascontiguousarray(valid, dtype=np.bool_),
        np.ascontiguousarray(poses, dtype=np.float64),
        int(block),
    )


def deviation_to_references(
    tracks: FloatArray, valid: BoolArray, references: npt.ArrayLike, min_common: int, block: int = 1
) -> FloatArray:
    """Median distance deviation of every track against a set of static reference tracks.

    The majority bin of earlier detections persists between iterations as the set of points verified
    static; a new point is judged the way the paper's last round judges a bin against the majority
    bin, against several of its members (median, so one unlucky reference does not decide).

    With ``block > 1`` the distance is first averaged over consecutive blocks of ``block``
    iterations and the deviation is taken over the block means: the noise of a static pair shrinks
    by about ``sqrt(block)`` while a point that moves over the window keeps its deviation, so slow
    movers (a few metres over the window, below the single-observation noise per iteration) stand
    out. Blocks with fewer than two common observations are ignored.

    Parameters
    ----------
    tracks:
        (N, L, 3) untransformed observations of N points over the last L iterations.
    valid:
        (N, L) where each track has an observation.
    references:
        Rows of ``tracks`` that are verified static (R,).
    min_common:
        Pairs observed together in fewer iterations are not compared.
    block:
        Iterations averaged per block before the deviation (1: the plain deviation).

    Returns
    -------
    (N,) median over references (excluding the track itself) of the standard deviation of the
    distance (or of its block means) over the iterations both were observed; NaN where no reference
    qualifies.
    """
    references = np.asarray(references, dtype=np.int64)
    if len(references) == 0 or len(tracks) == 0:
        return np.full(len(tracks), np.nan)
    deviation = reference_deviations(
        np.ascontiguousarray(tracks, dtype=np.float64),
        np.ascontiguousarray(valid, dtype=np.bool_),
        references,
        int(min_common),
        int(block),
    )
    out = np.full(len(tracks), np.nan)
    any_usable = np.isfinite(deviation).any(axis=1)
    if any_usable.any():
        out[any_usable] = row_nanmedian(deviation[any_usable])
    return out
