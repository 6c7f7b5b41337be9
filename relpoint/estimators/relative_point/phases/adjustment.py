"""The final adjustment when the log ends: the whole network solved jointly, every iteration located again on it, the observations themselves solved jointly (bundle adjustment), and kept only where it does not place the observations worse."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from relpoint.estimators._noise import SIMULATOR_SIGMA
from relpoint.estimators.relative_point._kernels import support_observations
from relpoint.estimators.relative_point.adjustment import (
    Adjustment,
    adjust_network,
    carry_corrections,
    inconsistent_relocations,
    residual_drift,
    residual_trend,
    smooth_corrections,
)
from relpoint.estimators.relative_point.dynamics import tail_bound
from relpoint.estimators.relative_point.groups import ROOT
from relpoint.estimators.relative_point.lsf import _median
from relpoint.estimators.relative_point.points import IntArray
from relpoint.estimators.relative_point.state import EstimatorState
from relpoint.geometry import FloatArray, apply_transform, rigid_inverse
from relpoint.types import Trajectory

logger = logging.getLogger(__name__)


#: The final adjustment is kept unless it places the log's observations (each iteration's kept ones,
#: by its pose, against their points) this much farther from their points than the incremental map.
ADJUSTMENT_TOLERANCE = 0.05


#: Iterations on either side whose relocations set an iteration's correction after the final adjustment.
RELOCATION_WINDOW = 10

#: Cauchy scale of the bundle adjustment, in observation noises (per axis, measured as the median
#: residual before it over ``CHI3_MEDIAN``): a static point's residual is about 1.5 noises, so it keeps
#: about 80 % of its weight, while a mismatched or moving point the detection missed pulls with bounded
#: force.
BUNDLE_ROBUST_SIGMAS = 3.0

#: Median length of a 3-D residual with unit noise per axis (the chi distribution with 3 degrees of freedom).
CHI3_MEDIAN = 1.5382

#: Most observations the bundle adjustment keeps until the log ends and solves (memory: about 20 bytes
#: each). Every iteration is a keyframe until then; a longer log keeps every ``2^j``-th iteration's,
#: between half and all of this many, and the others take the nearest keyframe's correction. Every
#: iteration counts while few: keeping one in two on the figure eight (900 iterations, 17,000
#: observations) left its ATE at 1.04-1.16x the optimum's, against 0.94-1.03x with all. The solve's
#: time grows with them: on the 40-pass figure eight (39,837 iterations) the final adjustment takes
#: 8.1 s with 47,000 (landmark RMSE 0.33 m), 11.5 s with 94,000 (0.35 m), 16.8 s with 189,000 (0.41 m).
BUNDLE_MAX_OBSERVATIONS = 50_000

#: A point whose bundle-adjustment residuals drift over time (:func:`.adjustment.residual_drift`) is a
#: mover kept as a static point: judged over blocks of this many observations, flagged when a static
#: point would drift so much with this probability or less and some block mean lies this many of its
#: noises from its mean (0 probability: not judged). The probability is the smaller of the blocks'
#: and of a trend over the whole track (:func:`.adjustment.residual_trend`), doubled: over the
#: robustness matrix, seeds 0-3, the trend raised the worst recall of seeds 0-1 from 0.70 to 0.80
#: (spiral-issue seed 1, random walkers), mean recall 0.914 -> 0.917, precision 0.986 -> 0.987. A
#: point flagged dynamic is static again when its drift is more likely than
#: ``BUNDLE_RELEASE_PROBABILITY``: no sign of motion at all.
BUNDLE_DRIFT_BLOCK = 8
BUNDLE_DRIFT_PROBABILITY = 1e-3
BUNDLE_DRIFT_MOTION = 1.0
BUNDLE_RELEASE_PROBABILITY = 0.05

#: A flagged point judged in the solve that takes every candidate in is judged again alone (in a solve
#: with the static points and itself, ``BUNDLE_ALONE_STEPS`` Levenberg-Marquardt steps from the solution
#: without it) when it is not released there and its block means move less than this many of its
#: noises: a clear mover is not. At most ``BUNDLE_JUDGED_ALONE`` of them, the most observed first (one
#: solve each). Measured over the robustness matrix, seeds 0-3: the worst run's ATE 2.12x -> 1.67x the
#: optimum's (figure8-line-40-fast seed 1: 2.12x -> 1.01x, its two static points seen from the first
#: iterations released), dynamic precision 0.97 -> 1.00 and 0.90 -> 1.00 in two runs, recall unchanged.
BUNDLE_CLEAR_MOTION = 3.0
BUNDLE_JUDGED_ALONE = 16
BUNDLE_ALONE_STEPS = 3

#: The bundle adjustment is for sparse views: with more static observations a keyframe than this on
#: average it is not run and the network adjustment stands. Dense views tie the relative maps together
#: well already, and the solve grows with the square of the points in view (7-Scenes kitchen, 400
#: frames, ~49 a keyframe: 2.97 cm without it, 2.93 cm with it in 16 s more; solved on a subset of
#: each view's points it was worse than without it, 3.4-4.1 cm).
BUNDLE_DENSE_VIEW = 32

#: Most observations a keyframe keeps until the log ends (memory: about 20 bytes each); a view with more
#: is dense (``BUNDLE_DENSE_VIEW``) and only needs enough of them to tell.
BUNDLE_KEPT_PER_KEYFRAME = 4 * BUNDLE_DENSE_VIEW

#: Observations an iteration needs in the bundle adjustment (fewer leave its pose undetermined; it then
#: takes the correction of its neighbours).
BUNDLE_MIN_OBSERVATIONS = 3

#: After the Cauchy-robust bundle adjustment, the observations within this many noises of their
#: points (3-D residual, the noise measured as the median residual over ``CHI3_MEDIAN``) are solved
#: again by plain least squares (0: the robust solution stands). A static point's residual exceeds
#: 4.03 noises with probability 1e-3. Over the robustness matrix (seeds 0-3), before the candidates
#: were judged alone, the final ATE was 1.04x the optimum's (geometric mean; 1.12x at 3 noises, 1.03x
#: at 6) and its worst run 2.1x (2.5x at 6: a looser gate lets the fast movers the detection missed
#: back in).
BUNDLE_INLIER_SIGMAS = 4.03

#: Iterations a point the map never placed must be seen at to take part in the bundle adjustment
#: (two already tie their poses together).
BUNDLE_MIN_SIGHTINGS = 2


class _Bundle(NamedTuple):
    """One bundle adjustment: its solution, the iterations and point rows it solved, and each of its
    observations' index into them with the observation itself (sensor frame, m)."""

    result: Adjustment
    poses: IntArray
    points: IntArray
    pose_row: IntArray
    point_row: IntArray
    observed: FloatArray


def _lookup(row_of: dict[int, int], uids: IntArray) -> IntArray:
    """The rows (N,) of ``uids`` in ``row_of`` (uid -> row), -1 where absent."""
    known = np.fromiter(row_of.keys(), np.int64, len(row_of))
    rows = np.fromiter(row_of.values(), np.int64, len(row_of))
    order = np.argsort(known)
    known, rows = known[order], rows[order]
    slot = np.clip(np.searchsorted(known, uids), 0, max(len(known) - 1, 0))
    found = known[slot] == uids if len(known) else np.zeros(len(uids), bool)
    return np.where(found, rows[slot] if len(rows) else -1, -1)


def _in_solvable_iterations(iteration: IntArray, chosen: npt.NDArray[np.bool_]) -> npt.NDArray[np.bool_]:
    """``chosen`` observations (at ``iteration``) left only in iterations with at least
    ``BUNDLE_MIN_OBSERVATIONS`` of them: fewer leave a pose undetermined."""
    counts = np.bincount(iteration[chosen], minlength=int(iteration.max(initial=0)) + 1)
    return chosen & (counts[iteration] >= BUNDLE_MIN_OBSERVATIONS)


def _all_positions(pos_sum: FloatArray, pos_weight: FloatArray) -> FloatArray:
    """Every store row's global position (rows, 3), ``world``, m (meaningless where unmapped)."""
    return pos_sum / np.maximum(pos_weight, 1e-300)[:, None]


def _solution(T_base: FloatArray, positions: FloatArray, bundle: _Bundle) -> tuple[FloatArray, FloatArray]:
    """Poses (K, 4, 4) and positions (rows, 3) after ``bundle``: its solved keyframes and points; the
    other iterations moved by the nearest keyframe's correction of ``T_base``, the other points as in
    ``positions``."""
    solved = T_base.copy()
    solved[bundle.poses, :3, :3] = bundle.result.R_world_group
    solved[bundle.poses, :3, 3] = bundle.result.t_world_group
    fitted = np.zeros(len(T_base), bool)
    fitted[bundle.poses] = True
    moved = positions.copy()
    moved[bundle.points] = bundle.result.positions
    return carry_corrections(T_base, solved, fitted), moved


class FinalAdjustment(EstimatorState):
    """The final adjustment when the log ends: the whole network solved jointly, every iteration located
    again on it, and kept only where it does not place the observations worse.

    A phase of :class:`~relpoint.estimators.relative_point.estimator.RelativePointEstimator` over
    the state it shares with the other phases (:class:`~relpoint.estimators.relative_point.state.EstimatorState`).
    """

    def finish(self, trajectory: Trajectory) -> Trajectory:
        """The final adjustment (:meth:`_adjusted`), then the iterations that observed no point placed
        between their neighbours (:meth:`_unobserved_interpolated`)."""
        return self._unobserved_interpolated(self._adjusted(trajectory))

    def _unobserved_interpolated(self, trajectory: Trajectory) -> Trajectory:
        """``trajectory`` with the poses of iterations that observed no point (which held the pose
        before them) interpolated in time between the nearest observed iterations around them:
        positions linearly, rotations by slerp; before the first and after the last observed
        iteration, that iteration's pose. ``unobserved_interpolated`` in :meth:`summary` counts them.
        """
        unobserved = np.asarray(self._unobserved, dtype=np.int64)
        if len(unobserved) == 0 or len(trajectory) != self._iteration:
            return trajectory
        observed = np.setdiff1d(np.arange(len(trajectory)), unobserved)
        if len(observed) < 2:
            return trajectory
        from scipy.spatial.transform import Rotation, Slerp  # here, not at import: scipy costs start-up time

        stamps = trajectory.stamps_ns.astype(np.float64)
        at = np.clip(stamps[unobserved], stamps[observed[0]], stamps[observed[-1]])
        positions = trajectory.positions.copy()
        quats = trajectory.quats_xyzw.copy()
        for axis in range(3):
            positions[unobserved, axis] = np.interp(at, stamps[observed], trajectory.positions[observed, axis])
        slerp = Slerp(stamps[observed], Rotation.from_quat(trajectory.quats_xyzw[observed]))
        quats[unobserved] = slerp(at).as_quat(canonical=True)
        self.counts["unobserved_interpolated"] = len(unobserved)
        return Trajectory(trajectory.stamps_ns, positions, quats)

    def _adjusted(self, trajectory: Trajectory) -> Trajectory:
        """Adjust the whole map by least squares and locate every iteration again on it.

        With ``final_adjustment`` (the default) every group pose and point position is solved jointly
        (:meth:`adjust`); points whose groups still disagree are flagged dynamic and the solve is
        repeated without them (:meth:`_flag_disagreeing`). Then each iteration's pose is fitted
        again, as :meth:`_locate` fitted it, from
        the observations it kept (``relocate_points``) to the adjusted global positions. An iteration
        that cannot be fitted again (too few of its points still mapped), or whose fit moves it unlike
        its neighbours (:func:`.adjustment.inconsistent_relocations`), keeps the correction of the
        nearest iteration before it; then every iteration takes the median correction of the fitted
        iterations within ``RELOCATION_WINDOW`` (:func:`.adjustment.smooth_corrections`).
        ``trajectory`` holds the poses :meth:`step` returned.

        The result is checked against the incremental solution on the log's own observations
        (:meth:`_support_residual`): if the adjusted map and poses place them more than
        ``ADJUSTMENT_TOLERANCE`` farther from their points, the incremental map and trajectory are
        kept; ``final_adjustment`` in :meth:`summary` says which was kept and why.
        """
        if not self.config.final_adjustment or len(trajectory) != self._iteration:
            return trajectory
        T_incremental = trajectory.matrices()
        residual_before = self._support_residual(T_incremental)
        incremental_poses = [(group, group.T_world_group.copy()) for group in self.groups.groups.values()]
        if not self.adjust():
            return trajectory
        flagged = self._flag_disagreeing()
        if len(flagged):
            self.adjust()
        assert self.adjustment_report is not None
        self.adjustment_report["dynamic_flagged"] = len(flagged)
        store = self.store
        live = store.live_ids()
        row_of = dict(zip(store.uid[live].tolist(), live.tolist(), strict=True))
        for newer, older in self._merged_uid.items():
            while older not in row_of and older in self._merged_uid:
                older = self._merged_uid[older]
            if older in row_of:
                row_of.setdefault(newer, row_of[older])
        T_before = trajectory.matrices()
        T_fit = T_before.copy()
        fitted = np.zeros(len(T_before), bool)
        seen = np.zeros((len(T_before), 3))
        for k, observed, rows in self._supported_points(row_of):
            fit = self._fit_pose(observed.astype(np.float64), rows)
            if fit is not None:
                T_fit[k], fitted[k] = fit, True
                seen[k] = observed.mean(axis=0)
        # A fit on few or misplaced points moves its iteration unlike its neighbours: such an
        # iteration takes its neighbours' correction instead.
        outliers = inconsistent_relocations(
            T_before, T_fit, fitted, seen, floor=3.0 * (self.config.observation_sigma or SIMULATOR_SIGMA)
        )
        fitted &= ~outliers
        T_after = T_before.copy()
        correction = np.eye(4)
        for k in range(len(T_before)):
            if fitted[k]:
                T_after[k] = T_fit[k]
                correction = T_fit[k] @ rigid_inverse(T_before[k])
            else:
                T_after[k] = correction @ T_before[k]
        # Drift builds up slowly, and so does its correction; a fit on the few observations an
        # iteration kept is noisy. Every iteration takes the median correction of the fitted
        # iterations around it, keeping the incremental path's local shape.
        T_after = smooth_corrections(T_before, T_after, fitted, RELOCATION_WINDOW)
        T_after[0] = T_before[0]  # the first iteration defines ``world``
        self.adjustment_report["relocated_iterations"] = int(np.count_nonzero(fitted))
        self.adjustment_report["relocations_rejected"] = int(np.count_nonzero(outliers))
        network_positions = self.store.pos_sum.copy()
        if self.config.bundle_adjustment:
            T_after = self._bundle_adjust(T_after, row_of)
        residual_after = self._support_residual(T_after)
        report = self.adjustment_report
        report["support_residual_before"] = round(residual_before, 4)
        report["support_residual_after"] = round(residual_after, 4)
        if residual_after > (1.0 + ADJUSTMENT_TOLERANCE) * residual_before:
            # The adjusted map explains the log's own observations worse than the incremental one:
            # keep the incremental map and trajectory (the points flagged dynamic stay flagged).
            self.store.pos_sum[:] = network_positions  # the groups' contributions, before the bundle's
            for group, T_world_group in incremental_poses:
                self.groups.move(group, T_world_group)
            self._refresh_index()
            report["kept"] = "incremental"
            report["reason"] = (
                f"adjusted observations {residual_after:.3f} m from their points against "
                f"{residual_before:.3f} m before (median RMS over iterations)"
            )
            return trajectory
        report["kept"] = "adjusted"
        from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

        orientation = Rotation.from_matrix(T_after[:, :3, :3]).as_quat(canonical=True)
        return Trajectory(trajectory.stamps_ns, T_after[:, :3, 3], orientation)

    def _bundle_adjust(self, T_world_sensor: FloatArray, row_of: dict[int, int]) -> FloatArray:
        """Solve every iteration's pose and every static point's position jointly from the log's observations.

        The network adjustment solves the relative maps, each an average over its interval, and the
        relocation fits each iteration's pose to that map alone; neither is the least-squares
        solution of the observations themselves. This is: over every observation ``z`` (sensor
        frame, m) of a static mapped point ``X`` (``world``, m) by an iteration's pose
        ``T_world_sensor = (R, t)``, it minimises the Cauchy-robust sum of ``|R z + t - X|^2`` with
        :func:`.adjustment.adjust_network` (each iteration a "group" whose relative map is its own
        observations, weight one each), starting from ``T_world_sensor`` (K, 4, 4) and the adjusted
        map; the points the map never placed take part too (``BUNDLE_MIN_SIGHTINGS``). Then the
        flagged points are judged (released when they do not drift, :meth:`_judged_alone`), the
        static ones whose residuals drift are flagged, and the inliers of the robust solution are
        solved again by plain least squares (``BUNDLE_INLIER_SIGMAS``). The first iteration stays
        where it is: it defines ``world``. Only the keyframes are solved (every iteration up to
        ``BUNDLE_MAX_OBSERVATIONS``); the other iterations, and those with fewer than
        ``BUNDLE_MIN_OBSERVATIONS`` usable observations, take the correction of the nearest solved one
        (:func:`carry_corrections`). The mapped points take their solved positions in the store.
        Returns the poses (K, 4, 4).
        """
        store = self.store
        entries = sorted(self._observations.items())
        if not entries:
            return T_world_sensor
        iteration = np.concatenate([np.full(len(uids), k) for k, (uids, _) in entries])
        uids = np.concatenate([uids for _, (uids, _) in entries])
        observed = np.concatenate([points for _, (_, points) in entries]).astype(np.float64)
        row = _lookup(row_of, uids)
        positioned = row >= 0
        positioned[positioned] = store.pos_weight[row[positioned]] > 0
        flagged = row >= 0
        flagged[flagged] = store.dynamic[row[flagged]]
        usable = _in_solvable_iterations(iteration, positioned & ~flagged)
        if not usable.any():
            return T_world_sensor
        per_keyframe = np.count_nonzero(usable) / len(np.unique(iteration[usable]))
        assert self.adjustment_report is not None
        if per_keyframe > BUNDLE_DENSE_VIEW:
            self.adjustment_report["bundle"] = {
                "skipped": f"dense views: {per_keyframe:.0f} static observations a keyframe on average, "
                f"above {BUNDLE_DENSE_VIEW}; the network adjustment stands"
            }
            return T_world_sensor
        # The noise from the data: a 3-D Gaussian residual's median length is 1.54 per-axis noises.
        placed = (
            np.einsum("nij,nj->ni", T_world_sensor[iteration[usable], :3, :3], observed[usable])
            + T_world_sensor[iteration[usable], :3, 3]
        )
        sigma = float(np.median(np.linalg.norm(placed - store.positions(row[usable]), axis=1))) / CHI3_MEDIAN
        positions = _all_positions(store.pos_sum, store.pos_weight)
        n_rows = len(positions)
        # Points the map never placed (seen too briefly to be grouped, or forgotten since) still tie
        # together the poses that saw them: each seen at BUNDLE_MIN_SIGHTINGS iterations or more is
        # solved too, from the mean of its observations placed by the poses, and not kept after. Near
        # the first iteration, which defines ``world``, they are much of what holds the path there.
        unplaced = ~positioned & ~flagged
        if unplaced.any():
            extra_uid, extra_row, sightings = np.unique(uids[unplaced], return_inverse=True, return_counts=True)
            row = row.copy()
            row[unplaced] = n_rows + extra_row
            often = np.zeros(len(row), bool)
            often[unplaced] = sightings[extra_row] >= BUNDLE_MIN_SIGHTINGS
            usable = _in_solvable_iterations(iteration, (positioned & ~flagged) | often)
            T_seen = T_world_sensor[iteration[unplaced]]
            world = np.einsum("nij,nj->ni", T_seen[:, :3, :3], observed[unplaced]) + T_seen[:, :3, 3]
            extra = np.zeros((len(extra_uid), 3))
            np.add.at(extra, extra_row, world)
            positions = np.concatenate([positions, extra / sightings[:, None]])
        bundle = self._bundle_solve(T_world_sensor, positions, iteration, row, observed, usable, sigma)
        # The later solves (with the flagged points judged, without the drifting ones) go on from it.
        T_start, X_start = _solution(T_world_sensor, positions, bundle)
        drifting = released = np.zeros(0, np.int64)
        judged_alone = released_alone = 0
        if BUNDLE_DRIFT_PROBABILITY > 0:
            # Points flagged dynamic with enough observations are judged in a solve that takes them
            # in: a static point flagged while movers outnumbered the static points around it, or
            # displaced by drift when seen again after a loop, is released if its residuals do not
            # drift (an unconverged solve leaves larger residuals: it releases fewer).
            flagged = (row >= 0) & (row < n_rows)
            flagged[flagged] = (store.pos_weight[row[flagged]] > 0) & store.dynamic[row[flagged]]
            candidates = np.flatnonzero(np.bincount(row[flagged], minlength=1) >= 2 * BUNDLE_DRIFT_BLOCK)
            if len(candidates):
                trial = _in_solvable_iterations(iteration, usable | np.isin(row, candidates))
                judged = self._bundle_solve(T_start, X_start, iteration, row, observed, trial, sigma)
                probability, motion = self._drift(judged)
                in_trial = np.isin(judged.points, candidates)
                released = judged.points[(probability > BUNDLE_RELEASE_PROBABILITY) & in_trial]
                # The movers among the candidates bend that solve, and a static point seen while they
                # did seems to drift too. Those that do not clearly move are judged again one at a
                # time, each in a solve with the static points alone.
                doubtful = in_trial & (probability <= BUNDLE_RELEASE_PROBABILITY) & (motion < BUNDLE_CLEAR_MOTION)
                seen = np.bincount(row[trial], minlength=int(row.max()) + 1)[judged.points[doubtful]]
                doubtful_rows = judged.points[doubtful][np.argsort(-seen, kind="stable")[:BUNDLE_JUDGED_ALONE]]
                static = usable | np.isin(row, released)
                alone = self._judged_alone(doubtful_rows, T_start, X_start, iteration, row, observed, static, sigma)
                judged_alone, released_alone = len(doubtful_rows), len(alone)
                released = np.concatenate([released, alone])
                if len(released):
                    store.dynamic[released] = False
                    store.moving[released] = False
                    self.counts["dynamic_released"] += len(released)
                    usable |= np.isin(row, released) & trial
            if bundle.result.converged:
                # An unconverged solution's residuals still carry its error: static points are
                # flagged only from a converged one.
                probability, motion = self._drift(bundle)
                # Blocks cut a wandering mover's track into short steps; over the whole track it
                # trends. Either test may flag, each at half the probability (Bonferroni).
                trend = residual_trend(bundle.point_row, self._residuals(bundle), len(bundle.points))
                probability = 2.0 * np.minimum(probability, trend)
                drifting = bundle.points[(probability < BUNDLE_DRIFT_PROBABILITY) & (motion >= BUNDLE_DRIFT_MOTION)]
            if len(drifting):
                self._flag_dynamic(drifting[drifting < n_rows], "bundle")
                usable &= ~np.isin(row, drifting)
            if len(drifting) or len(released):
                usable = _in_solvable_iterations(iteration, usable)
                bundle = self._bundle_solve(T_start, X_start, iteration, row, observed, usable, sigma)
        if BUNDLE_INLIER_SIGMAS > 0 and bundle.result.converged:
            # The Cauchy loss bounds what a mismatch or a missed mover can do, but it also weighs the
            # static points' own larger residuals down: its minimum is not the least-squares one, and
            # along the directions the observations hold loosely (the path's slow bends) that costs
            # more than the noise. The observations it leaves within the gate are solved again by
            # plain least squares.
            residual = np.linalg.norm(self._residuals(bundle), axis=1)
            gate = BUNDLE_INLIER_SIGMAS * float(np.median(residual)) / CHI3_MEDIAN
            inliers = usable.copy()
            inliers[np.flatnonzero(usable)[residual > gate]] = False
            inliers = _in_solvable_iterations(iteration, inliers)
            T_start, X_start = _solution(T_world_sensor, X_start, bundle)
            refit = self._bundle_solve(T_start, X_start, iteration, row, observed, inliers, 0.0)
            if refit.result.converged:
                bundle = refit
        result, points = bundle.result, bundle.points
        mapped = points < n_rows
        store.pos_sum[points[mapped]] = result.positions[mapped] * store.pos_weight[points[mapped], None]
        self.adjustment_report["bundle"] = {
            "iterations_solved": len(bundle.poses),
            "points": int(np.count_nonzero(mapped)),
            "unmapped_points": int(np.count_nonzero(~mapped)),
            "observations": len(bundle.pose_row),
            "dynamic_flagged": len(drifting),
            "dynamic_released": len(released),
            "judged_alone": judged_alone,
            "released_alone": released_alone,
            "steps": result.iterations,
            "cost_before": round(result.cost_before, 3),
            "cost_after": round(result.cost_after, 3),
        }
        return _solution(T_world_sensor, X_start, bundle)[0]

    def _bundle_solve(
        self,
        T_world_sensor: FloatArray,
        positions: FloatArray,
        iteration: IntArray,
        row: IntArray,
        observed: FloatArray,
        usable: npt.NDArray[np.bool_],
        sigma: float,
        iterations: int | None = None,
    ) -> _Bundle:
        """One bundle adjustment over the ``usable`` observations (``observed`` (N, 3), sensor frame, m,
        of point ``row`` at ``iteration``), starting from ``T_world_sensor`` (K, 4, 4) and ``positions``
        (one per point row, ``world``, m): Cauchy-robust at ``BUNDLE_ROBUST_SIGMAS`` times ``sigma`` (m;
        0: plain least squares), at most ``iterations`` steps (default ``adjustment_iterations``)."""
        poses, pose_row = np.unique(iteration[usable], return_inverse=True)
        points, point_row = np.unique(row[usable], return_inverse=True)
        # The first iteration fixes the gauge; without it a light pull towards the start does.
        anchored = bool(len(poses)) and poses[0] == 0
        result = adjust_network(
            pose_row,
            point_row,
            observed[usable],
            np.ones(len(pose_row)),
            T_world_sensor[poses, :3, :3],
            T_world_sensor[poses, :3, 3],
            positions[points],
            poses == 0,
            prior=0.0 if anchored else self.config.adjustment_prior,
            robust=BUNDLE_ROBUST_SIGMAS * sigma,
            iterations=iterations or self.config.adjustment_iterations,
        )
        return _Bundle(result, poses, points, pose_row, point_row, observed[usable])

    def _judged_alone(
        self,
        candidates: IntArray,
        T_world_sensor: FloatArray,
        positions: FloatArray,
        iteration: IntArray,
        row: IntArray,
        observed: FloatArray,
        static: npt.NDArray[np.bool_],
        sigma: float,
    ) -> IntArray:
        """The ``candidates`` (point rows) whose residuals show no drift, each judged in its own solve.

        Each solve takes the ``static`` observations and the candidate's, ``BUNDLE_ALONE_STEPS``
        steps from ``T_world_sensor`` (K, 4, 4) and ``positions`` (``world``, m), the solution without
        it: a point is released when its drift is more likely than ``BUNDLE_RELEASE_PROBABILITY``.
        """
        released = []
        for candidate in candidates:
            one = _in_solvable_iterations(iteration, static | (row == candidate))
            solved = self._bundle_solve(
                T_world_sensor, positions, iteration, row, observed, one, sigma, iterations=BUNDLE_ALONE_STEPS
            )
            probability, _ = self._drift(solved)
            where = np.searchsorted(solved.points, candidate)
            found = where < len(solved.points) and solved.points[where] == candidate
            if found and probability[where] > BUNDLE_RELEASE_PROBABILITY:
                released.append(candidate)
        return np.asarray(released, np.int64)

    @staticmethod
    def _residuals(bundle: _Bundle) -> FloatArray:
        """Each solved observation placed by its pose minus its point's position (N, 3), ``world``, m."""
        result, pose_row = bundle.result, bundle.pose_row
        return (
            np.einsum("nij,nj->ni", result.R_world_group[pose_row], bundle.observed)
            + result.t_world_group[pose_row]
            - result.positions[bundle.point_row]
        )

    @classmethod
    def _drift(cls, bundle: _Bundle) -> tuple[FloatArray, FloatArray]:
        """:func:`.adjustment.residual_drift` of the solved points (in ``bundle.points`` order)."""
        return residual_drift(bundle.point_row, cls._residuals(bundle), len(bundle.points), block=BUNDLE_DRIFT_BLOCK)

    def _supported_points(self, row_of: dict[int, int]) -> Iterator[tuple[int, npt.NDArray[np.float32], IntArray]]:
        """Per iteration that kept observations: ``(k, observed, rows)``, its kept sensor-frame
        observations (M, 3) of static mapped points and their rows in the point store (``row_of``:
        uid -> row)."""
        store = self.store
        for k, support in enumerate(self._support):
            if support is None:
                continue
            uids, observed = support
            rows = np.array([row_of.get(uid, -1) for uid in uids.tolist()], np.int64)
            usable = rows >= 0
            usable[usable] = (store.pos_weight[rows[usable]] > 0) & ~store.dynamic[rows[usable]]
            yield k, observed[usable], rows[usable]

    def _support_residual(self, T_world_sensor: FloatArray) -> float:
        """Median over iterations of the RMS distance (m) of each one's kept observations, placed by its
        pose (K, 4, 4), from their points' current global positions (static mapped points only)."""
        store = self.store
        live = store.live_ids()
        row_of = dict(zip(store.uid[live].tolist(), live.tolist(), strict=True))
        per_iteration = []
        for k, observed, rows in self._supported_points(row_of):
            if len(rows) < 3:
                continue
            placed = apply_transform(T_world_sensor[k], observed.astype(np.float64))
            per_iteration.append(np.sqrt(np.mean(np.sum((placed - store.positions(rows)) ** 2, axis=1))))
        return float(np.median(per_iteration)) if per_iteration else float("nan")

    def _flag_disagreeing(self) -> IntArray:
        """Flag the points whose groups still disagree about their position after the adjustment.

        Once every group is where the whole network puts it, a static point's groups agree on it to
        within the noise, while a moving point the detection missed is placed where it stood during
        each group's interval. A point in at least three groups whose disagreement (RMS, m) exceeds
        ``adjustment_dynamic_factor`` times the median of such points is flagged dynamic. Returns
        the ids flagged.
        """
        factor = self.config.adjustment_dynamic_factor
        store = self.store
        live = store.live_ids()
        judged = live[(store.pos_weight[live] > 0) & ~store.dynamic[live] & (store.n_groups[live] >= 3)]
        if factor <= 0 or len(judged) == 0:
            return np.zeros(0, np.int64)
        spread = store.spread(judged)
        bound = factor * _median(spread)
        outside = spread > bound
        flagged = judged[outside]
        moving = spread[outside] > max(bound, tail_bound(spread, self.config.dynamic_tail_sigmas))
        self._flag_dynamic(flagged, "adjustment", moving)
        return flagged

    def _keep_support(self, k: int, points: FloatArray, ids: IntArray, mapped: npt.NDArray[np.bool_] | None) -> None:
        """Keep up to ``relocate_points`` of this iteration's observations of ``mapped`` points (None: not
        located), and, on a keyframe of the bundle adjustment, up to ``BUNDLE_KEPT_PER_KEYFRAME``."""
        store = self.store
        every_uid = every_point = None  # every point's uid and observation (float32), when a keyframe keeps them all
        if self.config.final_adjustment and self.config.bundle_adjustment and k % self._keyframe_stride == 0:
            if len(ids) > BUNDLE_KEPT_PER_KEYFRAME:
                # A dense view keeps its mapped points seen most so far, as the solve will prefer them.
                seen = store.n_obs[ids] + (0 if mapped is None else mapped * (self._iteration + 1))
                kept = np.sort(np.argsort(-seen, kind="stable")[:BUNDLE_KEPT_PER_KEYFRAME])
                self._observations[k] = (store.uid[ids[kept]], points[kept].astype(np.float32))
                self._kept_observations += len(kept)
            else:
                every_uid, every_point = store.uid[ids], points.astype(np.float32)
                self._observations[k] = (every_uid, every_point)
                self._kept_observations += len(ids)
            while self._kept_observations > BUNDLE_MAX_OBSERVATIONS:
                # Memory and the solve follow the keyframes, not the log: every other one goes.
                self._keyframe_stride *= 2
                self._observations = {
                    i: kept for i, kept in self._observations.items() if i % self._keyframe_stride == 0
                }
                self._kept_observations = sum(len(uids) for uids, _ in self._observations.values())
        if not self.config.final_adjustment or mapped is None or k == 0:
            # The first iteration defines ``world``; a coasted one had no usable fit.
            self._support.append(None)
            return
        use, uids, kept = support_observations(mapped, int(self.config.relocate_points), ids, store.uid, points)
        if every_uid is None:
            self._support.append((uids, kept))
        else:  # the same values as above, from the keyframe's arrays
            self._support.append((every_uid[use], every_point[use]))

    def adjust(self) -> bool:
        """Joint least-squares adjustment of every placed group and mapped point (:mod:`.adjustment`).

        Flagged dynamic points take no part; groups with fewer than three such members keep their
        pose. The root group stays where it is: it carries ``world``. Returns whether anything was
        adjusted; the figures go to :meth:`summary` under ``final_adjustment``.
        """
        config, store = self.config, self.store
        groups, members, relative, weights = [], [], [], []
        cap = config.adjustment_members
        for group in self.groups.groups.values():
            usable = np.flatnonzero(store.alive[group.members] & ~store.dynamic[group.members])
            if group.weight <= 0 or len(usable) < 3:
                continue
            if len(usable) > cap:
                # Points in the most groups tie the network together; the same points win in every
                # group, so the groups stay coupled through them.
                usable = usable[np.argsort(-store.n_groups[group.members[usable]], kind="stable")[:cap]]
            groups.append(group)
            members.append(group.members[usable])
            relative.append(group.relative_map[usable])
            weights.append(np.full(len(usable), float(group.count)))
        if not groups:
            return False
        group_rows = np.repeat(np.arange(len(groups)), [len(m) for m in members])
        points, point_rows = np.unique(np.concatenate(members), return_inverse=True)
        T_before = np.array([group.T_world_group for group in groups])
        result = adjust_network(
            group_rows,
            point_rows,
            np.concatenate(relative),
            np.concatenate(weights),
            T_before[:, :3, :3],
            T_before[:, :3, 3],
            store.positions(points),
            np.array([group.kind == ROOT for group in groups]),
            prior=config.adjustment_prior,
            robust=config.adjustment_robust,
            iterations=config.adjustment_iterations,
        )
        T_after = np.repeat(np.eye(4)[None], len(groups), axis=0)
        T_after[:, :3, :3] = result.R_world_group
        T_after[:, :3, 3] = result.t_world_group
        for group, T_world_group in zip(groups, T_after, strict=True):
            self.groups.move(group, T_world_group)
        self._refresh_index()
        self.adjustment_report = {
            "groups": len(groups),
            "points": len(points),
            "memberships": len(group_rows),
            "iterations": result.iterations,
            "cost_before": round(result.cost_before, 3),
            "cost_after": round(result.cost_after, 3),
        }
        return True
