"""A filter's past poses re-placed on its final map: offline smoothing of EKF-SLAM's trajectory.

A filter's pose at iteration ``k`` uses what it knew at ``k``. What it learns later, from a loop it
closes or from the position fixes it fuses, moves its map (through the joint covariance) but not the
poses it has already returned: the trajectory keeps every drift it had, and where fixes pull the
filter back the path bends. An offline tool has the whole log, so when it ends each past pose is
placed again on the final map, from the very pairs the filter made at that iteration:

1. **Relocation** (:func:`relocate`): per iteration, the rigid fit (Kabsch) of its paired points
   (sensor frame) onto their landmarks' final positions (``world``), robust to the odd pair (refitted
   twice, each time without the pairs over three times the iteration's median residual). Its uncertainty
   follows from the fit's geometry and the point noise (measured from all residuals, their median
   over the chi-square median with 3 degrees of freedom, and no less than the filter's): per axis,
   the rotation's from the inverse of the landmarks' inertia about their centroid, the position's
   from the point count and the rotation's lever arm. Fewer than :data:`MIN_PAIRS` pairs give no fit.
2. **Smoothing** (:func:`smooth_corrections`): a single fit has one iteration's noise, while the
   filter's own error changes slowly. Wrong fits (a few pairs that were not what they seemed) are
   left out first by Hampel's filter: a fit far from the median of its neighbours, in robust
   standard deviations of all fits and in its own. The position correction ``fit - filtered`` (``world``) is
   taken as a random walk observed with each fit's variance, and solved by a Rauch-Tung-Striebel
   smoother, axis by axis. The walk's step variance is the maximum-likelihood one over a
   log-spaced grid: how fast the filter's error changes is measured from the log, not set.

Only positions move (:func:`smoothed_poses` says why). Poses are ``T_world_sensor``; positions in
metres, rotations in radians.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from relpoint.estimators._landmark_motion import median_by_group
from relpoint.geometry import FloatArray, skew
from relpoint.statistics import chi2_gate
from relpoint.types import Trajectory

IntArray = npt.NDArray[np.int64]

#: Pairs an iteration needs for its relocation (a rigid fit needs 3; one more to see its noise).
MIN_PAIRS = 4
#: Most pairs an iteration keeps for the relocation (evenly chosen): memory follows the log's
#: length, not its density.
MAX_PAIRS_PER_ITERATION = 64
#: A pair whose residual is over this many times its iteration's median residual is left out of
#: the second fit (a mover the filter still paired, a wrong pair).
OUTLIER_FACTOR = 3.0
#: Hampel's filter on the fits (a wrong one is left out): half window (fits) and bound (robust
#: standard deviations).
HAMPEL_HALF_WINDOW = 5
HAMPEL_SIGMAS = 5.0
#: Candidate step standard deviations of the position correction's random walk (m per
#: iteration), log-spaced.
POSITION_STEPS = np.geomspace(1e-5, 1.0, 41)


class PairHistory:
    """Every iteration's pairs: the points (sensor frame, m) and the ids of their landmarks.

    Landmark ids are stable over the run (a filter that removes landmarks keeps the others' ids).
    At most :data:`MAX_PAIRS_PER_ITERATION` pairs an iteration are kept, evenly spread over them,
    in buffers that double as they fill: float32 points and int32 ids and iterations, 20 bytes a
    pair (at most 1,280 bytes an iteration, 128 MB over 100,000 iterations).
    """

    def __init__(self) -> None:
        self._size = 0
        self._iterations = np.zeros(0, dtype=np.int32)
        self._points = np.zeros((0, 3), dtype=np.float32)
        self._ids = np.zeros(0, dtype=np.int32)

    def add(self, iteration: int, points: FloatArray, landmark_ids: IntArray) -> None:
        """Record the ``points`` (k, 3) paired with landmarks ``landmark_ids`` (k,) at ``iteration``."""
        k = len(points)
        if k == 0:
            return
        if k > MAX_PAIRS_PER_ITERATION:
            keep = np.linspace(0, k - 1, MAX_PAIRS_PER_ITERATION).round().astype(np.int64)
            points, landmark_ids = points[keep], landmark_ids[keep]
            k = MAX_PAIRS_PER_ITERATION
        end = self._size + k
        if end > len(self._ids):
            capacity = max(end, 2 * len(self._ids), 1024)
            self._iterations = np.resize(self._iterations, capacity)
            self._points = np.resize(self._points, (capacity, 3))
            self._ids = np.resize(self._ids, capacity)
        self._iterations[self._size : end] = iteration
        self._points[self._size : end] = points
        self._ids[self._size : end] = landmark_ids
        self._size = end

    def __len__(self) -> int:
        return self._size

    def arrays(self) -> tuple[IntArray, FloatArray, IntArray]:
        """``(iteration (N,), points (N, 3) float64, landmark ids (N,))`` in recording order."""
        n = self._size
        return (
            self._iterations[:n].astype(np.int64),
            self._points[:n].astype(np.float64),
            self._ids[:n].astype(np.int64),
        )


@dataclass(frozen=True)
class Relocation:
    """Per-iteration rigid fits onto the final map (:func:`relocate`).

    Attributes
    ----------
    rotations: (K, 3, 3) fitted ``R_world_sensor`` (identity where not ``fitted``).
    positions: (K, 3) fitted sensor positions (m).
    fitted: (K,) whether the iteration had a fit.
    variances: (K, 6) variance of the fit per axis: rotation about ``world``'s axes (rad^2), then
        position (m^2); ``inf`` where not fitted.
    pairs: (K,) pairs the second fit used.
    noise: the point noise measured from the residuals (m, per axis).
    """

    rotations: FloatArray
    positions: FloatArray
    fitted: npt.NDArray[np.bool_]
    variances: FloatArray
    pairs: IntArray
    noise: float


def _batched_kabsch(
    group: IntArray, source: FloatArray, target: FloatArray, weights: FloatArray, groups: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per group the weighted rigid fit ``target ~ R source + t``: rotations (G, 3, 3), translations
    (G, 3), weight sums (G,), source and target centroids (G, 3)."""
    count = np.bincount(group, weights=weights, minlength=groups)
    safe = np.maximum(count, 1e-12)
    source_mean = np.stack([np.bincount(group, weights=weights * source[:, a], minlength=groups) for a in range(3)], 1)
    target_mean = np.stack([np.bincount(group, weights=weights * target[:, a], minlength=groups) for a in range(3)], 1)
    source_mean /= safe[:, None]
    target_mean /= safe[:, None]
    ds = source - source_mean[group]
    dt = target - target_mean[group]
    H = np.zeros((groups, 3, 3))
    for a in range(3):
        for b in range(3):
            H[:, a, b] = np.bincount(group, weights=weights * ds[:, a] * dt[:, b], minlength=groups)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros((groups, 3, 3))
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2)
    t = target_mean - np.einsum("gab,gb->ga", R, source_mean)
    return R, t, count, source_mean, target_mean


def relocate(
    iteration: IntArray, points: FloatArray, landmark_ids: IntArray, iterations: int,
    map_ids: IntArray, map_positions: FloatArray, min_noise: float = 0.0,
) -> Relocation:  # fmt: skip
    """Fit every iteration's pairs onto the final map.

    ``iteration`` (N,), ``points`` (N, 3, sensor frame, m) and ``landmark_ids`` (N,) are the pairs
    (:meth:`PairHistory.arrays`); ``iterations`` the log's iteration count; ``map_ids`` (M,) and
    ``map_positions`` (M, 3, ``world``) the final map's static landmarks. Pairs whose landmark is not
    in it (removed, or flagged dynamic) are left out. ``min_noise`` (m, per axis) floors the noise
    measured from the residuals: a landmark is placed by the very points it is fitted to, so its
    residuals understate the noise where landmarks are seen a few times or their errors are
    correlated over time (a filter passes the noise its model assumes).
    """
    K = iterations
    empty = Relocation(
        np.broadcast_to(np.eye(3), (K, 3, 3)).copy(), np.zeros((K, 3)), np.zeros(K, dtype=bool),
        np.full((K, 6), np.inf), np.zeros(K, dtype=np.int64), float("nan"),
    )  # fmt: skip
    if len(map_ids) == 0:
        return empty
    order = np.argsort(map_ids, kind="stable")
    sorted_ids = map_ids[order]
    where = np.clip(np.searchsorted(sorted_ids, landmark_ids), 0, len(sorted_ids) - 1)
    known = (sorted_ids[where] == landmark_ids) & (iteration >= 0) & (iteration < K)
    by_iteration = np.flatnonzero(known)[np.argsort(iteration[known], kind="stable")]  # median_by_group's order
    group, source = iteration[by_iteration], points[by_iteration]
    target = map_positions[order[where[by_iteration]]]
    weights = np.ones(len(group))
    if len(group) == 0:
        return empty
    for _ in range(2):  # each refit leaves out the pairs far from the fit before it
        R, t, count, _, target_mean = _batched_kabsch(group, source, target, weights, K)
        residual = np.linalg.norm(np.einsum("nab,nb->na", R[group], source) + t[group] - target, axis=1)
        median = median_by_group(group, residual[:, None], K)[:, 0]
        weights = (residual <= OUTLIER_FACTOR * median).astype(np.float64)
    R, t, count, _, target_mean = _batched_kabsch(group, source, target, weights, K)
    fitted = count >= MIN_PAIRS
    residual = np.einsum("nab,nb->na", R[group], source) + t[group] - target
    used = (weights > 0) & fitted[group]
    if not used.any():
        return empty
    noise = float(np.sqrt(np.median(np.sum(residual[used] ** 2, axis=1)) / chi2_gate(0.5, 3)))
    noise = max(noise, min_noise)
    # Rotation information about world axes: sum over the pairs of |d|^2 I - d d^T, d the landmark
    # less its group's centroid; its inverse times the noise variance is the rotation's covariance.
    d = target - target_mean[group]
    inertia = np.zeros((K, 3, 3))
    for a in range(3):
        for b in range(3):
            value = weights * ((np.sum(d * d, axis=1) if a == b else 0.0) - d[:, a] * d[:, b])
            inertia[:, a, b] = np.bincount(group, weights=value, minlength=K)
    variances = np.full((K, 6), np.inf)
    rows = np.flatnonzero(fitted)
    info = inertia[rows] + 1e-12 * np.eye(3)
    rotation_cov = noise**2 * np.linalg.pinv(info, hermitian=True)
    # The position is the centroid less R times the source centroid: the rotation's error moves it
    # by the lever arm from the sensor to the centroid.
    lever = skew(target_mean[rows] - t[rows])
    position_cov = noise**2 / count[rows, None, None] * np.eye(3) + lever @ rotation_cov @ np.swapaxes(lever, 1, 2)
    variances[rows, :3] = np.diagonal(rotation_cov, axis1=1, axis2=2)
    variances[rows, 3:] = np.diagonal(position_cov, axis1=1, axis2=2)
    rotations = np.where(fitted[:, None, None], R, np.eye(3))
    positions = np.where(fitted[:, None], t, 0.0)
    return Relocation(rotations, positions, fitted, variances, np.round(count).astype(np.int64), noise)


def _random_walk_filter(
    measured: FloatArray, variance: FloatArray, step_variance: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Kalman filter of scalar random walks, vectorised over the trailing axes.

    ``measured`` and ``variance`` (K, ...) (``inf`` variance: no measurement), ``step_variance``
    broadcastable to ``measured[0]``. Returns the filtered means and variances, the predicted
    variances (K, ...), and the log-likelihood of the measurements (...).
    """
    K = len(measured)
    shape = np.broadcast_shapes(measured.shape[1:], np.shape(step_variance))
    mean = np.zeros(shape)
    var = np.full(shape, np.inf)
    means = np.empty((K, *shape))
    variances = np.empty((K, *shape))
    predicted = np.empty((K, *shape))
    log_likelihood = np.zeros(shape)
    for k in range(K):
        if k > 0:
            var = var + step_variance
        predicted[k] = var
        r = variance[k]
        seen = np.isfinite(r)
        if seen.any():
            fresh = seen & ~np.isfinite(var)
            S = np.where(seen & ~fresh, var + r, 1.0)
            innovation = measured[k] - mean
            gain = np.where(fresh, 1.0, np.where(seen, var / S, 0.0))
            log_likelihood = log_likelihood - np.where(
                seen & ~fresh, 0.5 * (np.log(2 * np.pi * S) + innovation**2 / S), 0.0
            )
            mean = np.where(seen, mean + gain * innovation, mean)
            var = np.where(fresh, r, np.where(seen, (1.0 - gain) * var, var))
        means[k] = mean
        variances[k] = var
    return means, variances, predicted, log_likelihood


def _rts(means: FloatArray, variances: FloatArray, predicted: FloatArray) -> FloatArray:
    """Rauch-Tung-Striebel pass of :func:`_random_walk_filter`'s output: the smoothed means."""
    smoothed = means.copy()
    for k in range(len(means) - 2, -1, -1):
        nxt = predicted[k + 1]
        gain = np.where(np.isfinite(nxt) & (nxt > 0), variances[k] / np.where(nxt > 0, nxt, 1.0), 0.0)
        gain = np.where(np.isfinite(variances[k]), gain, 1.0)
        smoothed[k] = means[k] + gain * (smoothed[k + 1] - means[k])
    return smoothed


@dataclass(frozen=True)
class Smoothing:
    """The smoothed position corrections (:func:`smooth_corrections`) and the walk's measured step."""

    corrections: FloatArray  # (K, 3): position correction in world (m)
    position_step: float  # the random walk's step standard deviation (m per iteration, per axis)
    rejected: int = 0  # fits left out as wrong (:func:`smoothed_poses`)
    log_likelihood: float = float("nan")  # of the fits under the walk, at its measured step
    fix_jumps_removed: bool = False  # the walk is of the correction with the fixes' jumps taken out


def smooth_corrections(measured: FloatArray, variances: FloatArray, min_gain: float = 0.0) -> Smoothing:
    """RTS-smoothed random-walk corrections (K, 3) from per-iteration measurements and variances.

    The step variance (one for the three axes) is the maximum-likelihood one over
    :data:`POSITION_STEPS`, unless its log-likelihood beats the smallest step's (a constant
    correction) by less than ``min_gain`` (nats): then the smallest. Iterations before an axis's
    first measurement take its first smoothed value; with no measurement at all the corrections are
    zero.
    """
    K = len(measured)
    if K == 0 or not np.isfinite(variances).any():
        return Smoothing(np.zeros((K, 3)), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        _, _, _, log_likelihood = _random_walk_filter(
            measured[:, None, :], variances[:, None, :], (POSITION_STEPS**2)[:, None]
        )
        total = log_likelihood.sum(axis=1)
        best = int(np.argmax(total))
        if total[best] - total[0] < min_gain:
            best = 0
        step = float(POSITION_STEPS[best])
        means, filtered_var, predicted, _ = _random_walk_filter(measured, variances, np.full(3, step**2))
        smoothed = _rts(means, filtered_var, predicted)
    for axis in range(3):
        seen = np.flatnonzero(np.isfinite(variances[:, axis]))
        if len(seen):
            smoothed[: seen[0], axis] = smoothed[seen[0], axis]
        else:
            smoothed[:, axis] = 0.0
    return Smoothing(smoothed, step, log_likelihood=float(total[best]))


def summed_fix_jumps(jumps: list[tuple[int, FloatArray]], iterations: int) -> FloatArray:
    """How far the fixes fused up to each of ``iterations`` iterations moved a filter's position
    (``world``, m; (K, 3)), from the ``(iteration, shift)`` of each fused fix: a fix fused before
    iteration ``k`` moves the poses from ``k`` on."""
    summed = np.zeros((iterations, 3))
    for iteration, shift in jumps:
        if iteration < iterations:
            summed[iteration] += shift
    return np.cumsum(summed, axis=0)


def _hampel_outliers(measured: FloatArray, variances: FloatArray) -> npt.NDArray[np.bool_]:
    """The fits (F, 3) that stand out of their neighbours: Hampel's filter on each axis.

    A fit is an outlier where, on some axis, it is further from the median of the
    ``2 * HAMPEL_HALF_WINDOW + 1`` fits around it than ``HAMPEL_SIGMAS`` robust standard deviations
    of all fits' such distances (1.4826 times their median) and than that many of its own standard
    deviations: the filter's error changes slowly, a wrong fit jumps.
    """
    F = len(measured)
    if F < 3:
        return np.zeros(F, dtype=bool)
    half = min(HAMPEL_HALF_WINDOW, (F - 1) // 2)
    padded = np.pad(measured, ((half, half), (0, 0)), mode="reflect")
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1, axis=0)  # (F, 3, W)
    distance = np.abs(measured - np.median(windows, axis=2))
    scale = 1.4826 * np.median(distance, axis=0)
    bound = HAMPEL_SIGMAS * np.maximum(scale, np.sqrt(variances))
    return np.any(distance > bound, axis=1)


def smoothed_poses(
    poses: FloatArray, relocation: Relocation, fix_jumps: FloatArray | None = None
) -> tuple[FloatArray, Smoothing]:
    """The filter's poses ``T_world_sensor`` (K, 4, 4) with their positions moved by the smoothed
    corrections toward the relocation (``p <- p + dp``); rotations are the filter's.

    ``fix_jumps`` (K, 3, m), when given, is how far the fixes fused up to each iteration moved the
    filter's position (their Kalman updates, summed): each fix moves the filter at once, partly by
    the fix's own noise, so its error is a walk with jumps. The correction is smoothed twice, as a
    walk and as a walk once the jumps are taken out (``fit - (filtered - jumps)``), and the model
    whose fits are the likelier is kept.

    Iterations before the first fit take its correction. Not even where the first pose defines
    ``world`` (no fixes) is the correction held at zero there: the final map has moved against that
    pose as much as against any other (held at zero, Starry Night's ATE was 0.13 m against 0.12 m).

    Only positions move: a fit's rotation, from a few points near the sensor, is noisier than a
    filter's that fuses odometry, and on real stereo landmarks (UTIAS Starry Night) smoothing it
    made the rotation error worse, while positions improved on every log tried.
    """
    p_f = poses[:, :3, 3]
    measured = np.zeros((len(poses), 3))
    rows = np.flatnonzero(relocation.fitted)
    measured[rows] = relocation.positions[rows] - p_f[rows]
    variances = relocation.variances[:, 3:].copy()
    # A wrong fit (pairs that were not what they seemed, a few points in a line) is left out.
    outlying = rows[_hampel_outliers(measured[rows], variances[rows])]
    variances[outlying] = np.inf
    smoothing = smooth_corrections(measured, variances)
    if fix_jumps is not None and np.any(fix_jumps):
        without_jumps = smooth_corrections(measured + fix_jumps, variances)
        if without_jumps.log_likelihood > smoothing.log_likelihood:
            smoothing = Smoothing(
                without_jumps.corrections - fix_jumps, without_jumps.position_step,
                log_likelihood=without_jumps.log_likelihood, fix_jumps_removed=True,
            )  # fmt: skip
    smoothing = Smoothing(
        smoothing.corrections, smoothing.position_step, len(outlying), smoothing.log_likelihood,
        smoothing.fix_jumps_removed,
    )  # fmt: skip
    out = poses.copy()
    out[:, :3, 3] = p_f + smoothing.corrections
    return out, smoothing


def smoothed_trajectory(
    trajectory: Trajectory, iterations: int, pairs: PairHistory, map_ids: IntArray, map_positions: FloatArray,
    min_noise: float, fix_jumps: FloatArray | None = None,
) -> tuple[Trajectory, dict[str, Any]]:  # fmt: skip
    """A filter's trajectory smoothed on its final map, and the report for ``run.json``.

    ``trajectory`` holds the poses the filter returned, one per iteration (``world``); ``pairs`` the
    pairs it made; ``map_ids`` (M,) and ``map_positions`` (M, 3, ``world``, m) the final map's static
    landmarks; ``min_noise`` the filter's point noise (m, per axis); ``fix_jumps`` as in
    :func:`smoothed_poses`. A run that skipped iterations,
    or whose pairs place no iteration on the final map, keeps its trajectory, and the report says why.
    """
    if len(trajectory) != iterations:
        return trajectory, {"applied": False, "reason": "the run skipped iterations"}
    relocation = relocate(*pairs.arrays(), iterations, map_ids, map_positions, min_noise=min_noise)
    fitted = int(relocation.fitted.sum())
    if fitted == 0:
        return trajectory, {"applied": False, "reason": "no iteration has enough pairs on the final map"}
    poses, smoothing = smoothed_poses(trajectory.matrices(), relocation, fix_jumps)
    shift = np.linalg.norm(poses[:, :3, 3] - trajectory.positions, axis=1)
    report = {
        "applied": True,
        "iterations_placed": fitted,
        "noise_m": round(relocation.noise, 6),
        "walk_position_m": round(smoothing.position_step, 6),
        "fits_rejected": smoothing.rejected,
        "fix_jumps_removed": smoothing.fix_jumps_removed,
        "mean_shift_m": round(float(shift.mean()), 6),
        "max_shift_m": round(float(shift.max()), 6),
    }
    return Trajectory.from_matrices(trajectory.stamps_ns, poses), report
