"""Timestamp association of a reference and an estimated trajectory, as evo's ``sync`` module does it.

Two modes, both evo 1.38's (``evo.core.sync.associate_trajectories``):

* nearest (default, ``evo --sync_method nearest_time``): the trajectory with fewer poses is walked and
  each of its stamps is matched to the nearest stamp of the other within ``max_diff`` seconds after
  adding ``offset`` to the estimate's stamps. Ties between an earlier and a later candidate go to the
  earlier one; the longer trajectory's poses may be used more than once. On equal lengths the
  *estimate* is walked (evo treats the second trajectory as the short one then).
* interpolation (``--sync_method interpolation``): the same matches decide which stamps survive, but the
  longer trajectory is resampled exactly at the matched stamps of the shorter one (linear position,
  slerp orientation, clamped at its ends) instead of snapping to its nearest pose.

Stamps are compared as float64 seconds, as evo does, converted from integer nanoseconds with correct
rounding so they equal the floats evo parses from the same TUM file; ties and tolerance edges therefore
fall the same way as in evo.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.errors import UsageError
from relpoint.evaluation import EvaluationError
from relpoint.geometry import FloatArray, homogeneous, quat_to_matrix
from relpoint.types import IntArray, Trajectory

logger = logging.getLogger(__name__)

#: evo's (transformations.py) threshold for degenerate slerp cases.
_SLERP_EPS = float(np.finfo(float).eps) * 4.0


def stamps_to_seconds(stamps_ns: npt.ArrayLike) -> FloatArray:
    """Integer nanoseconds (N,) to float64 seconds, correctly rounded.

    Python's ``int / int`` rounds correctly, so a stamp read from the decimal text ``1305031102.175304``
    gives the same float as parsing that text directly (what evo does); ``ns * 1e-9`` would not always.
    """
    return np.array([s / 1_000_000_000 for s in np.asarray(stamps_ns, dtype=np.int64).tolist()], dtype=np.float64)


def matching_time_indices(
    stamps_1: npt.ArrayLike, stamps_2: npt.ArrayLike, max_diff: float = 0.01, offset_2: float = 0.0
) -> tuple[IntArray, IntArray]:
    """Indices of the best matches of ``stamps_1`` in ``stamps_2 + offset_2`` within ``max_diff``.

    A vectorised, bit-for-bit equivalent of ``evo.core.sync.matching_time_indices`` (sorted branch;
    unsorted ``stamps_2`` fall back to evo's linear search).

    Parameters
    ----------
    stamps_1, stamps_2:
        Stamps in seconds, shapes (N,) and (M,), M >= 1.
    max_diff:
        Largest accepted absolute difference, seconds.
    offset_2:
        Added to ``stamps_2`` before matching, seconds.

    Returns
    -------
    indices_1, indices_2:
        (K,) int64 each; ``indices_1`` increases strictly, ``indices_2`` may repeat.
    """
    s1 = np.asarray(stamps_1, dtype=np.float64).reshape(-1)
    s2 = np.asarray(stamps_2, dtype=np.float64).reshape(-1) + offset_2
    if s1.size == 0 or s2.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if not np.all(np.diff(s2) >= 0):
        logger.warning("Timestamps aren't sorted, using slower linear matching.")
        diffs = np.abs(s2[None, :] - s1[:, None])
        best = np.argmin(diffs, axis=1)
        ok = diffs[np.arange(s1.size), best] <= max_diff
        return np.nonzero(ok)[0].astype(np.int64), best[ok].astype(np.int64)
    in_range = ~((s1 < s2[0] - max_diff) | (s1 > s2[-1] + max_diff))
    upper = np.minimum(np.searchsorted(s2, s1, side="right"), s2.size - 1)
    diff_ub = s2[upper] - s1
    diff_lb = np.where(upper > 0, s1 - s2[np.maximum(upper - 1, 0)], np.inf)
    take_upper = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lower = ~take_upper & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    ok = in_range & (take_upper | take_lower)
    best = np.where(take_upper, upper, upper - 1)
    return np.nonzero(ok)[0].astype(np.int64), best[ok].astype(np.int64)


@dataclass(frozen=True, eq=False)
class MatchedPoses:
    """Pose pairs of a reference and an estimate at (approximately) equal times, in matching order.

    Attributes
    ----------
    reference_stamps_ns, estimate_stamps_ns:
        (K,) int64 stamps of each side (an interpolated side carries the other side's stamp shifted by
        the time offset).
    reference_positions, estimate_positions:
        (K, 3) float64 metres, each in its own world frame.
    reference_rotations, estimate_rotations:
        (K, 3, 3) float64 rotation matrices ``R_world_frame``.
    reference_index, estimate_index:
        (K,) int64 index of the nearest matched pose in the input trajectories.
    interpolated:
        Whether the longer trajectory was resampled instead of snapped to its nearest poses.
    """

    reference_stamps_ns: IntArray
    estimate_stamps_ns: IntArray
    reference_positions: FloatArray
    reference_rotations: FloatArray
    estimate_positions: FloatArray
    estimate_rotations: FloatArray
    reference_index: IntArray
    estimate_index: IntArray
    interpolated: bool = False

    def __len__(self) -> int:
        return len(self.reference_positions)

    def reference_matrices(self) -> FloatArray:
        """Reference poses as (K, 4, 4) matrices ``T_world_frame``."""
        return homogeneous(self.reference_rotations, self.reference_positions)

    def estimate_matrices(self) -> FloatArray:
        """Estimated poses as (K, 4, 4) matrices ``T_world_frame``."""
        return homogeneous(self.estimate_rotations, self.estimate_positions)


def slerp_quaternions(q0: npt.ArrayLike, q1: npt.ArrayLike, fraction: npt.ArrayLike) -> FloatArray:
    """Shortest-path slerp between quaternion rows (K, 4) at fractions (K,), as evo/transformations does.

    Degenerate cases follow ``transformations.quaternion_slerp``: fraction 0 gives ``q0``, fraction 1
    gives ``q1``, (anti)parallel quaternions give ``q0``. Component order is irrelevant (any order).
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    frac = np.asarray(fraction, dtype=np.float64)
    q0 = q0 / np.linalg.norm(q0, axis=1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=1, keepdims=True)
    d = np.sum(q0 * q1, axis=1)
    parallel = np.abs(np.abs(d) - 1.0) < _SLERP_EPS
    flip = d < 0.0
    d_pos = np.where(flip, -d, d)
    q1_near = np.where(flip[:, None], -q1, q1)
    angle = np.arccos(np.clip(d_pos, -1.0, 1.0))
    general = (frac != 0.0) & (frac != 1.0) & ~parallel & ~(np.abs(angle) < _SLERP_EPS)
    safe_angle = np.where(general, angle, 1.0)
    isin = 1.0 / np.sin(safe_angle)
    blended = (
        q0 * (np.sin((1.0 - frac) * safe_angle) * isin)[:, None] + q1_near * (np.sin(frac * safe_angle) * isin)[:, None]
    )
    out = np.where(general[:, None], blended, q0)
    return np.where((frac == 1.0)[:, None], q1, out)


def _interpolate(trajectory: Trajectory, stamps_s: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Positions (K,3) and rotations (K,3,3) of ``trajectory`` at ``stamps_s``, clamped at its ends (evo)."""
    t = stamps_to_seconds(trajectory.stamps_ns)
    n = len(t)
    idx = np.clip(np.searchsorted(t, stamps_s, side="left"), 1, n - 1)
    t_prev = t[idx - 1]
    dt = t[idx] - t_prev
    frac = (stamps_s - t_prev) / np.where(dt > 0.0, dt, 1.0)
    frac = np.clip(np.where(dt > 0.0, frac, 0.0), 0.0, 1.0)
    p = trajectory.positions
    positions = p[idx - 1] + frac[:, None] * (p[idx] - p[idx - 1])
    q = trajectory.quats_xyzw
    quats = slerp_quaternions(q[idx - 1], q[idx], frac)
    return positions, quat_to_matrix(quats)


def _no_match_advice(reference: Trajectory, estimate: Trajectory, offset: float) -> str:
    """What to change when no stamps matched: the offset that starts both together when their spans (the
    estimate's moved by ``offset``, s) do not overlap, else a wider tolerance or interpolation."""
    ref_t, est_t = stamps_to_seconds(reference.stamps_ns), stamps_to_seconds(estimate.stamps_ns) + offset
    if est_t[-1] < ref_t[0] or est_t[0] > ref_t[-1]:
        start_together = offset + float(ref_t[0] - est_t[0])
        return (
            f"they do not overlap: if both start together (an estimate stamped from its own start, or on "
            f"another clock), --t-offset {start_together:.6f} moves the estimate's first stamp onto the "
            "reference's"
        )
    return "their stamps interleave without a pair close enough: a larger --t-max-diff, or --interpolate"


def associate(
    reference: Trajectory,
    estimate: Trajectory,
    *,
    max_diff: float = 0.01,
    offset: float = 0.0,
    interpolate: bool = False,
) -> MatchedPoses:
    """Pair the poses of ``reference`` and ``estimate`` by time, as ``evo.core.sync.associate_trajectories``.

    Parameters
    ----------
    reference, estimate:
        The trajectories; neither is modified.
    max_diff:
        Largest accepted stamp difference, seconds (evo ``--t_max_diff``, default 0.01).
    offset:
        Added to the estimate's stamps before matching, seconds (evo ``--t_offset``).
    interpolate:
        Resample the longer trajectory at the matched stamps of the shorter one (evo
        ``--sync_method interpolation``) instead of taking its nearest poses.

    Raises
    ------
    EvaluationError
        If no stamps match, or interpolation is asked of a trajectory with fewer than two poses.
    UsageError
        If ``max_diff`` is negative or not finite, or ``offset`` is not finite.
    """
    if not (np.isfinite(max_diff) and max_diff >= 0.0):
        raise UsageError(f"maximum time difference must be a finite number >= 0 s, got {max_diff}")
    if not np.isfinite(offset):
        raise UsageError(f"time offset must be finite, got {offset}")
    if len(reference) == 0 or len(estimate) == 0:
        raise EvaluationError("cannot associate an empty trajectory")
    second_longer = len(estimate) > len(reference)
    short, long_ = (reference, estimate) if second_longer else (estimate, reference)
    short_offset = offset if second_longer else -offset
    short_t = stamps_to_seconds(short.stamps_ns)
    long_t = stamps_to_seconds(long_.stamps_ns)
    idx_short, idx_long = matching_time_indices(short_t, long_t, max_diff, short_offset)
    if idx_short.size == 0:
        raise EvaluationError(
            f"found no matching timestamps between reference and estimate with max. time diff {max_diff} s "
            f"and time offset {offset} s",
            hint=f"reference spans {time_span(reference)}, estimate spans {time_span(estimate)}; "
            + _no_match_advice(reference, estimate, offset),
        )
    short_p = short.positions[idx_short]
    short_R = quat_to_matrix(short.quats_xyzw[idx_short])
    short_ns = short.stamps_ns[idx_short]
    if interpolate:
        if len(long_) < 2:
            raise EvaluationError("cannot interpolate a trajectory with fewer than two poses")
        long_p, long_R = _interpolate(long_, short_t[idx_short] - short_offset)
        long_ns = short_ns - round(short_offset * 1e9)
    else:
        long_p = long_.positions[idx_long]
        long_R = quat_to_matrix(long_.quats_xyzw[idx_long])
        long_ns = long_.stamps_ns[idx_long]
    logger.debug(
        "matched %d of max. %d poses (max diff %g s, offset %g s)", idx_short.size, len(short), max_diff, offset
    )
    if second_longer:
        return MatchedPoses(short_ns, long_ns, short_p, short_R, long_p, long_R, idx_short, idx_long, interpolate)
    return MatchedPoses(long_ns, short_ns, long_p, long_R, short_p, short_R, idx_long, idx_short, interpolate)


def time_span(trajectory: Trajectory) -> str:
    """``first..last s (N poses)`` of a trajectory, for messages."""
    t = trajectory.stamps_ns
    return f"{t[0] / 1e9:.6f}..{t[-1] / 1e9:.6f} s ({len(t)} poses)"
