"""Splitting a local SLAM run into segments (local maps) where it loses its features or drifts.

Implements the segmentation of Zhang, Milios and Gu, *General Concept of 3D SLAM*, section 6,
Algorithm 3 (lines 1-15): a local map continues while the features matched between consecutive
iterations are at least ``m_l`` and the estimated position error stays below a threshold; otherwise
the current local map ends and the next good pair of iterations starts a new one.

Here the local SLAM has already run (a post-step), so a segment is a run of iterations rather than a
restarted estimator. A pair of consecutive iterations ``(k-1, k)`` whose matched count reaches
``min_matches`` links both into the same segment; iterations that no good pair links belong to no
segment (label -1). The position error is either given per iteration (an estimator's covariance) or
modelled as ``local_sigma + drift_fraction * (path length since the segment started)``, the usual
drift of odometry-like local SLAM in proportion to distance travelled.

Matched counts
    Algorithm 3 counts SIFT matches between images ``I_{k-1}`` and ``I_k``. An estimator that does not
    report its matches still reports, per iteration, the points it observed and its map size
    (``timing.csv``); :func:`matched_counts_from_map_growth` takes the points that did not start a new
    landmark as matched. That is exact for estimators that either pair a point with a landmark or
    start a landmark from it, and an upper bound for those that also discard ambiguous points (EKF).
    In a simulation, :func:`matched_counts_from_ids` counts ground-truth landmarks seen in both
    iterations, the direct analogue of image-to-image matches.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from relpoint.errors import UsageError
from relpoint.types import IntArray

#: Label of an iteration that belongs to no segment.
NO_SEGMENT = -1


def matched_counts_from_map_growth(observed: npt.ArrayLike, map_size: npt.ArrayLike) -> IntArray:
    """Points per iteration that did not start a landmark: ``observed[k] - (map_size[k] - map_size[k-1])``.

    Parameters
    ----------
    observed, map_size:
        (N,) points observed and landmarks mapped after each iteration (``timing.csv`` columns).

    Returns
    -------
    (N,) int64 matched counts; the first iteration (nothing to match against) counts 0. Map shrinkage
    (pruning, merging) counts as no new landmark.
    """
    observed = np.asarray(observed, dtype=np.int64).reshape(-1)
    map_size = np.asarray(map_size, dtype=np.int64).reshape(-1)
    if observed.shape != map_size.shape:
        raise ValueError(f"observed {observed.shape} and map_size {map_size.shape} differ in shape")
    started = np.maximum(np.diff(map_size, prepend=0), 0)
    matched = np.maximum(observed - started, 0)
    if len(matched):
        matched[0] = 0
    return matched


def matched_counts_from_ids(ids_per_iteration: list[npt.ArrayLike]) -> IntArray:
    """Landmark ids (>= 0) seen in both iteration ``k-1`` and ``k``, per iteration (first: 0)."""
    counts = np.zeros(len(ids_per_iteration), dtype=np.int64)
    previous: npt.NDArray[np.int64] = np.zeros(0, dtype=np.int64)
    for k, ids in enumerate(ids_per_iteration):
        current = np.unique(np.asarray(ids, dtype=np.int64))
        current = current[current >= 0]
        if k:
            counts[k] = np.intersect1d(previous, current, assume_unique=True).size
        previous = current
    return counts


def segment_run(
    matched: npt.ArrayLike,
    *,
    min_matches: int = 5,
    positions: npt.ArrayLike | None = None,
    position_sigma: npt.ArrayLike | None = None,
    local_sigma: float = 0.1,
    drift_fraction: float = 0.01,
    max_position_error: float = float("inf"),
    min_length: int = 4,
) -> IntArray:
    """Segment labels (0, 1, ...; -1 = none) per iteration, Algorithm 3 lines 1-15.

    Parameters
    ----------
    matched:
        (N,) features matched between iteration ``k-1`` and ``k`` (``matched[0]`` is ignored).
    min_matches:
        ``m_l``: a pair with fewer matches breaks the local map.
    positions:
        (N, 3) local positions, metres; needed for the modelled position error.
    position_sigma:
        (N,) an estimator's own position standard deviation, metres; its growth since the current
        segment's first iteration is the error used instead of the model when given.
    local_sigma, drift_fraction:
        The modelled error ``local_sigma + drift_fraction * path length since the segment start``.
    max_position_error:
        A segment ends when the (modelled or given) error exceeds this, metres (inf = never).
    min_length:
        Segments with fewer iterations are dropped (their iterations labelled -1): a cubic B-spline
        needs four positions.

    Raises
    ------
    UsageError
        Bad thresholds or array shapes.
    """
    matched = np.asarray(matched, dtype=np.int64).reshape(-1)
    n = len(matched)
    if min_matches < 1:
        raise UsageError(f"min_matches must be at least 1, got {min_matches}")
    if not max_position_error > 0:
        raise UsageError(f"max_position_error must be positive, got {max_position_error}")
    if local_sigma < 0 or drift_fraction < 0:
        raise UsageError("local_sigma and drift_fraction must be >= 0")
    step_length = np.zeros(n)
    if positions is not None:
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        if len(pos) != n:
            raise UsageError(f"positions has {len(pos)} rows for {n} iterations")
        step_length[1:] = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    sigma_given = None
    if position_sigma is not None:
        sigma_given = np.asarray(position_sigma, dtype=np.float64).reshape(-1)
        if len(sigma_given) != n:
            raise UsageError(f"position_sigma has {len(sigma_given)} entries for {n} iterations")

    labels = np.full(n, NO_SEGMENT, dtype=np.int64)
    current = NO_SEGMENT  # flag = new Map_start while NO_SEGMENT
    next_label = 0
    travelled = 0.0
    start_sigma = 0.0
    for k in range(1, n):
        travelled += step_length[k]
        modelled = local_sigma + drift_fraction * travelled
        error = sigma_given[k] - start_sigma if sigma_given is not None else modelled
        good = matched[k] >= min_matches and (current == NO_SEGMENT or error <= max_position_error)
        if good and current != NO_SEGMENT:
            labels[k] = current
            continue
        if matched[k] >= min_matches:
            # A new local map starts at iteration k-1 (the first of the good pair).
            current = next_label
            next_label += 1
            labels[k - 1] = labels[k] = current
            travelled = step_length[k]
            start_sigma = sigma_given[k - 1] if sigma_given is not None else 0.0
        else:
            current = NO_SEGMENT
            travelled = 0.0
    return _drop_short(labels, min_length)


def _drop_short(labels: IntArray, min_length: int) -> IntArray:
    """Remove segments shorter than ``min_length`` and renumber the rest 0, 1, ... in time order."""
    out = np.full_like(labels, NO_SEGMENT)
    next_label = 0
    for label in np.unique(labels[labels >= 0]):
        members = labels == label
        if np.count_nonzero(members) >= min_length:
            out[members] = next_label
            next_label += 1
    return out


def segment_slices(labels: npt.ArrayLike) -> list[IntArray]:
    """Iteration indices of each segment, in label order."""
    labels = np.asarray(labels, dtype=np.int64)
    return [np.flatnonzero(labels == label) for label in range(int(labels.max(initial=-1)) + 1)]
