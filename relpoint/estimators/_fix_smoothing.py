"""A trajectory smoothed on the position fixes it fused: offline smoothing of FastSLAM's fixes.

FastSLAM fuses a fix by moving each particle, and the landmarks it saw lately, part of the way
towards it (``relpoint.estimators.fastslam``). The gain follows the filter's model of how fast its
frame drifts, which must hold for any log and is therefore wide. Each fix then moves the path at
once, and partly by the fix's own noise: the trajectory jumps at every fix, and its shape suffers
(on the spiral of issue 17, 0.53 m SE(3)-aligned against 0.12 m without the fixes). An offline
tool has every fix, so when the log ends:

1. **The jumps are taken out.** The filter records how far each fused fix moved its mean position;
   their running sum, subtracted from the trajectory, leaves the path its map made on its own
   (``world``, m).
2. **The correction is smoothed.** ``fix - path`` at each fix (the path interpolated to the fix's
   stamp, the fix's covariance its variance) observes the correction the path needs: a random
   walk, solved by a Kalman filter and a Rauch-Tung-Striebel pass
   (:func:`relpoint.estimators._trajectory_smoothing.smooth_corrections`), axis by axis.
3. **Its step is measured, with a test.** The walk's step is the maximum-likelihood one, but only
   when its likelihood beats a constant correction by :data:`WALK_MIN_GAIN` nats. A few noisy fixes
   (25 fixes of 5 m) can favour a fast walk by chance, and a walk that follows them bends the path
   by metres; where the fixes are dense and the drift real the gain is tens to hundreds of nats.
4. **A refused walk turns the path first.** The jumps taken out had been mending a turn of the map's
   own path against the fixes' frame as well; an offset alone leaves it (on a spiral, 0.64 m raw
   ATE against the filter's 0.40 m). Where the walk is refused, the path (positions and orientations
   alike) is turned onto the fixes by a rigid fit before the offset, when the fixes fix a rotation.

Otherwise only positions move: a fix holds no rotation. Poses are ``T_world_sensor``, stamps in ns.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from relpoint.estimators._trajectory_smoothing import POSITION_STEPS, smooth_corrections
from relpoint.geometry import FloatArray, kabsch, measured_basis
from relpoint.types import Trajectory

#: Log-likelihood (nats) a random walk of the correction must gain over a constant correction to be
#: taken. The likelihood-ratio statistic for a variance at its bound (zero) is an even mixture of
#: chi-square with 0 and 1 degrees of freedom; its 0.999 quantile is 9.55, that is 4.77 nats. A
#: wrongly taken walk costs far more (it follows the fixes' noise) than a wrongly refused one.
WALK_MIN_GAIN = 4.77
#: Where the walk is refused, the path is turned onto the fixes that measure all three axes when at
#: least this many of them spread at least ``RIGID_MIN_SPREAD_SIGMAS`` times their noise across two
#: directions (along one line, the rotation about it is free).
RIGID_MIN_FIXES = 10
RIGID_MIN_SPREAD_SIGMAS = 5.0


def fix_corrections(
    stamps_ns: npt.NDArray[np.int64], positions: FloatArray, fix_stamps_ns: npt.NDArray[np.int64],
    fix_positions: FloatArray, fix_variances: FloatArray,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """What each fix says of the correction of the path ``positions`` (K, 3) at ``stamps_ns`` (K,).

    Each fix (``fix_positions`` (F, 3), per-axis ``fix_variances`` (F, 3), m and m^2) is compared
    with the path interpolated linearly to its stamp (held at the ends), and counts at the pose
    nearest in time; fixes at the same pose are combined by their inverse variances. Returns the
    measured corrections (K, 3) and their variances (K, 3; ``inf`` where no fix counts).
    """
    K = len(stamps_ns)
    measured = np.zeros((K, 3))
    variances = np.full((K, 3), np.inf)
    if K == 0 or len(fix_stamps_ns) == 0:
        return measured, variances
    t = (stamps_ns - stamps_ns[0]).astype(np.float64)
    tf = (fix_stamps_ns - stamps_ns[0]).astype(np.float64)
    path = np.column_stack([np.interp(tf, t, positions[:, axis]) for axis in range(3)])
    after = np.clip(np.searchsorted(t, tf), 1, max(K - 1, 1)) if K > 1 else np.zeros(len(tf), dtype=np.int64)
    before = np.maximum(after - 1, 0)
    nearest = np.where(np.abs(t[after] - tf) < np.abs(tf - t[before]), after, before)
    information = np.zeros((K, 3))
    weighted = np.zeros((K, 3))
    usable = np.all(np.isfinite(fix_variances) & (fix_variances > 0), axis=1)
    np.add.at(information, nearest[usable], 1.0 / fix_variances[usable])
    np.add.at(weighted, nearest[usable], (fix_positions[usable] - path[usable]) / fix_variances[usable])
    seen = information > 0
    measured[seen] = weighted[seen] / information[seen]
    variances[seen] = 1.0 / information[seen]
    return measured, variances


def smoothed_on_fixes(
    trajectory: Trajectory, fix_jumps: FloatArray, fix_stamps_ns: npt.NDArray[np.int64],
    fix_positions: FloatArray, fix_variances: FloatArray,
) -> tuple[Trajectory, dict[str, Any]]:  # fmt: skip
    """``trajectory`` (one pose per iteration, ``world``) with the fixes' jumps taken out and the
    correction smoothed on the fixes, and the report for ``run.json``.

    ``fix_jumps`` (K, 3, m) is how far the fixes fused up to each iteration had moved the filter's
    position (summed); the fixes are as in :func:`fix_corrections`.
    """
    path = trajectory.positions - fix_jumps
    poses = trajectory.matrices().copy()
    measured, variances = fix_corrections(trajectory.stamps_ns, path, fix_stamps_ns, fix_positions, fix_variances)
    if not np.isfinite(variances).any():
        return trajectory, {"applied": False, "reason": "no fix with a usable covariance"}
    smoothing = smooth_corrections(measured, variances, min_gain=WALK_MIN_GAIN)
    turned = 0.0
    if smoothing.position_step == POSITION_STEPS[0]:
        # The walk was refused: a constant shift would leave the path turned against the fixes' frame
        # by what the jumps had been mending. Turn it onto the fixes first, where they fix a rotation.
        rigid = _rigid_onto_fixes(trajectory.stamps_ns, path, fix_stamps_ns, fix_positions, fix_variances)
        if rigid is not None:
            R, t = rigid
            path = path @ R.T + t
            poses[:, :3, :3] = R @ poses[:, :3, :3]
            turned = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
            measured, variances = fix_corrections(
                trajectory.stamps_ns, path, fix_stamps_ns, fix_positions, fix_variances
            )
            smoothing = smooth_corrections(measured, variances, min_gain=WALK_MIN_GAIN)
    # Only where the fixes measure: an axis they leave unmeasured (a horizontal fix's altitude, with a
    # variance of 1e6 m^2) would otherwise be moved to the fixes' mean there, whatever its variance.
    basis = measured_basis(np.stack([np.diag(v) for v in np.asarray(fix_variances, dtype=np.float64)]))
    poses[:, :3, 3] = path + smoothing.corrections @ (basis @ basis.T)
    shift = np.linalg.norm(poses[:, :3, 3] - trajectory.positions, axis=1)
    report = {
        "applied": True,
        "poses_with_fixes": int(np.isfinite(variances[:, 0]).sum()),
        "fix_jumps_removed": True,
        "walk_position_m": round(smoothing.position_step, 6),
        "turned_onto_fixes_deg": round(turned, 4),
        "mean_shift_m": round(float(shift.mean()), 6),
        "max_shift_m": round(float(shift.max()), 6),
    }
    return Trajectory.from_matrices(trajectory.stamps_ns, poses), report


def _rigid_onto_fixes(
    stamps_ns: npt.NDArray[np.int64], positions: FloatArray, fix_stamps_ns: npt.NDArray[np.int64],
    fix_positions: FloatArray, fix_variances: FloatArray,
) -> tuple[FloatArray, FloatArray] | None:  # fmt: skip
    """The rigid motion ``(R, t)`` that best moves the path onto the fixes measuring all three axes,
    or None when they are too few or spread along too little to fix a rotation."""
    variances = np.asarray(fix_variances, dtype=np.float64)
    full = np.all(np.isfinite(variances) & (variances > 0) & (variances < 1e4), axis=1)
    if full.sum() < RIGID_MIN_FIXES or len(stamps_ns) < 2:
        return None
    fixes = np.asarray(fix_positions, dtype=np.float64)[full]
    sigma = float(np.sqrt(np.median(variances[full])))
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(fixes.T)), 0.0))
    if spread[1] < RIGID_MIN_SPREAD_SIGMAS * sigma:  # along a line: the rotation about it is free
        return None
    t = (stamps_ns - stamps_ns[0]).astype(np.float64)
    tf = (np.asarray(fix_stamps_ns)[full] - stamps_ns[0]).astype(np.float64)
    path = np.column_stack([np.interp(tf, t, positions[:, axis]) for axis in range(3)])
    return kabsch(path, fixes)
