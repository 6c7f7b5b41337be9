"""Placing a filter's local frame in the frame of the position fixes, inside the estimator loop.

Implements the in-loop part of Zhang, Milios and Gu, *General Concept of 3D SLAM*, sections 5-6 for
the estimators that carry a pose covariance (EKF-SLAM, FastSLAM): the fixes (``/fix``: buoys, GNSS)
are synchronised to the observation times by three-point Lagrange interpolation (section 5.1,
eq. 26-30, :func:`relpoint.lagrange.interpolate_fixes`); once at least three fixes that are
not collinear are in, the rigid transform ``T_world_local`` is fitted by least squares to the pairs
of local positions and interpolated fixes (section 6.3, :func:`relpoint.geometry.fit_rigid`); the
filter then moves its state into ``world`` and fuses every later fix as a position measurement
(section 5.2, eq. 31-32 in information form, which is the Kalman update on the position).

Until then the filter runs in its local frame (the first pose at the identity) and its output is
mapped by a provisional transform: the fixes' offset with one fix, plus the smallest rotation taking
the local direction of travel onto the fixes' once the fixes span a distance (a line of fixes
leaves the rotation about itself free).

Both the fit and the provisional transform first test the null hypothesis that the fixes' frame is
the local frame itself (a chi-square test of the pairs' residuals against their covariances): when
the fixes cannot reject it, the transform is the identity, without uncertainty (the frames are one),
because a transform fitted to metres of fix noise would move a centimetre-accurate filter by that
noise; the later fixes are then plain measurements of its position, held back by the fix gate
(:mod:`relpoint.estimators._fix_gate`) if the hypothesis turns out wrong.

The transform's uncertainty is a 6-vector ``(dt, dphi)`` in ``world`` about the pairs' weighted
centroid ``c``: a point ``y`` placed by the fit is truly at ``c + Exp(dphi) (y - c) + dt``, so
``dy = dt - [y - c]x dphi``, and an orientation ``R_world_sensor`` has the right-perturbation error
``R^T dphi``. Its covariance is the inverse of the fit's information, counted once per fix (the
interpolated pairs between two fixes share their noise), and inflated to the residuals when the
residuals exceed what the fixes and the local positions claim.

Fixes need not measure every axis: a GNSS receiver in a local frame often reports its altitude with a
variance of 1e6 m^2 or more (ROS's "unknown" is 1e9), and an acoustic fix may measure depth badly.
An axis whose standard deviation is over 100 times the best one's is left out of the frame's
noise, spread and fit (:func:`relpoint.geometry.measured_basis`): with one axis unmeasured only the
rotation about it is fitted (a yaw for fixes in the horizontal plane) and the offset in the plane;
with two, only the offset along the measured axis. The transform leaves the rest at the identity,
without uncertainty, as the frames that agree.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from relpoint.geometry import (
    FloatArray,
    apply_transform,
    fit_rigid_on_axes,
    fitted_parameters,
    information_basis,
    skew,
    smallest_rotation,
    so3_exp,
    summed_information,
)
from relpoint.lagrange import interpolate_fixes
from relpoint.settings import Settings, setting
from relpoint.statistics import chi2_gate
from relpoint.types import PositionFix, Trajectory

logger = logging.getLogger(__name__)

#: Chi-square probability up to which the fixes are taken to agree with the local frame itself.
AGREEMENT_PROBABILITY = 0.999


@dataclass(frozen=True)
class FrameFit:
    """A fitted ``T_world_local`` and its uncertainty.

    Attributes
    ----------
    T_world_local: (4, 4) rigid transform taking local coordinates into ``world``.
    covariance: (6, 6) covariance of the error ``(dt, dphi)`` (m, rad) in ``world`` about ``centre``.
    centre: (3,) weighted centroid of the pairs' fix positions in ``world`` (m).
    pairs: number of (local position, interpolated fix) pairs fitted.
    fixes: number of fixes they span.
    rms: weighted RMS residual of the fit (m).
    spread: RMS distance of the fixes from their best-fitting line (m).
    """

    T_world_local: FloatArray
    covariance: FloatArray
    centre: FloatArray
    pairs: int
    fixes: int
    rms: float
    spread: float

    def perturbation_jacobian(self, positions: npt.ArrayLike) -> FloatArray:
        """``d y / d(dt, dphi)`` (n, 3, 6) of world points ``positions`` (n, 3): ``[I, -[y - c]x]``."""
        y = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        J = np.zeros((len(y), 3, 6))
        J[:, :, :3] = np.eye(3)
        J[:, :, 3:] = -skew(y - self.centre)
        return J


@dataclass(frozen=True)
class FixFusionSettings(Settings):
    """The settings of fusing position fixes that the EKF and FastSLAM share: the fix gate
    (:mod:`relpoint.estimators._fix_gate`) and the spread that pins the frame (:class:`FixFrame`)."""

    fix_gate_probability: float = setting(0.999, low=0, high=1)
    """Chi-square probability of the gate a fix must pass before it is fused (its innovation against
    the predicted position and both covariances; ``relpoint.estimators._fix_gate``); 1 fuses every fix."""
    fix_gate_patience: int = setting(3, low=0, high=1_000_000)
    """Fixes in a row outside the gate that are held back; the ones after are fused with their
    covariance inflated onto the gate's edge (the filter, not the fixes, has drifted)."""
    fix_min_spread: float | None = setting(None, low=1e-3, high=1e6)
    """``rigid``: RMS distance of the fixes from their best line (m) needed to pin the frame. Unset
    (the default): 8 times the fixes' noise (the RMS of their per-axis standard deviations): 8 m for
    1 m fixes, 1.6 m for 0.2 m ones (``relpoint.estimators._fix_frame.FixFrame.required_spread``)."""


def line_spread(points: npt.ArrayLike, weights: npt.ArrayLike | None = None) -> float:
    """RMS distance (m) of points (n, 3) from their least-squares line, weighted by ``weights`` (n,)
    when given; 0 for fewer than three."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 3:
        return 0.0
    w = np.full(len(p), 1.0 / len(p)) if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
    centred = (p - w @ p) * np.sqrt(w)[:, None]
    singular = np.linalg.svd(centred, compute_uv=False)
    return float(np.sqrt(np.sum(singular[1:] ** 2)))


def time_weights(stamps_ns: npt.ArrayLike) -> FloatArray:
    """The stretch of time (ns) each of ``stamps_ns`` (n,) stands for: half the gaps to its neighbours
    (the whole gap to its one neighbour at either end, so that evenly spaced stamps weigh alike).

    Kept fixes thin out unevenly (:meth:`FixFrame._thin` halves the older ones, the newest stay
    dense), so counted alike they would favour the latest stretch of the path."""
    t = np.asarray(stamps_ns, dtype=np.float64)
    if len(t) < 2:
        return np.ones(len(t))
    gaps = np.diff(t)
    weights = np.zeros(len(t))
    weights[:-1] += gaps / 2.0
    weights[1:] += gaps / 2.0
    weights[0] += gaps[0] / 2.0
    weights[-1] += gaps[-1] / 2.0
    return np.maximum(weights, 1e-9 * max(float(gaps.max()), 1.0))


#: The fixes' spread (RMS distance from their best line) a frame fit needs, in units of the fixes'
#: per-axis noise: the rotation about that line is then known to about 1 / 8 rad over one fix.
SPREAD_SIGMAS = 8.0
#: Floor (m) of the noise behind the required spread, for fixes and local positions that claim none.
MIN_SPREAD_NOISE = 1e-3


class FixFrame:
    """Collects fixes and a filter's local positions until the fixes pin ``T_world_local``.

    Parameters
    ----------
    min_fixes: fixes needed before a fit is tried (at least 3).
    min_spread: the fixes' RMS distance from their best line (m) needed for a fit; below it the
        rotation about the line is not determined. None (the default): :data:`SPREAD_SIGMAS` times
        the fixes' noise (:meth:`required_spread`).
    max_fixes: at most this many fixes are kept: beyond it every other one is dropped (see
        :meth:`_thin`), so the kept ones thin out but still span every fix so far.
    """

    def __init__(self, min_fixes: int = 3, min_spread: float | None = None, max_fixes: int = 100) -> None:
        if not 3 <= min_fixes <= max_fixes:
            raise ValueError(f"need 3 <= min_fixes <= max_fixes, got {min_fixes} and {max_fixes}")
        self.min_fixes = min_fixes
        self.min_spread = min_spread
        self.max_fixes = max_fixes
        self._fix_stamps: list[int] = []
        self._fix_positions: list[FloatArray] = []
        self._fix_covariances: list[FloatArray] = []
        self._fix_information = np.zeros((3, 3))  # summed over the kept fixes (measured_basis)
        self._stamps: list[int] = []
        self._positions: list[FloatArray] = []
        self._covariances: list[FloatArray] = []
        self._provisional = np.eye(4)
        # The pairs changed since the provisional transform was fitted: fitted again when next asked
        # for (once an iteration at most, however many fixes arrived in it).
        self._provisional_stale = False
        self._fixes_received = 0
        self._fixes_tried = 0

    @property
    def fix_count(self) -> int:
        return len(self._fix_stamps)

    @property
    def fix_stamps(self) -> npt.NDArray[np.int64]:
        """Stamps (ns) of the fixes kept for the fit, in time order."""
        return np.asarray(self._fix_stamps, dtype=np.int64)

    @property
    def measured_basis(self) -> FloatArray:
        """The directions (3, k) the fixes kept so far measure (:func:`~relpoint.geometry.measured_basis`)."""
        return information_basis(self._fix_information)

    def add_fix(self, fix: PositionFix) -> None:
        """Keep a fix (one not after the last kept fix is dropped: the interpolation needs increasing stamps)."""
        if self._fix_stamps and fix.stamp_ns <= self._fix_stamps[-1]:
            logger.debug("fix at %d ns is not after the previous one; not used for the frame", fix.stamp_ns)
            return
        self._fixes_received += 1
        self._fix_stamps.append(int(fix.stamp_ns))
        self._fix_positions.append(np.array(fix.position, dtype=np.float64))
        self._fix_covariances.append(np.array(fix.covariance, dtype=np.float64))
        self._fix_information += summed_information(self._fix_covariances[-1])
        self._provisional_stale = True

    def _thin(self) -> None:
        """Keep about half the fixes, evenly spread in time over all of them (the first and the last
        always), and the local positions up to the last fix only where they are nearest a kept one.

        This bounds the cost when the fixes never spread (a straight run) but keeps their whole span:
        a window of the latest fixes at a high rate covers too short a stretch of a curving path to
        ever reach ``min_spread``. Even in time, not every other one: halving the kept fixes each
        time left the oldest ones thinned again at every pass, so with fixes at 10 per iteration the
        kept ones were the last few seconds and the first fix. The pairs before the last fix then
        sit on the kept fixes, where the interpolation is exact, instead of between fixes that are
        now far apart.
        """
        fix_stamps = np.asarray(self._fix_stamps, dtype=np.int64)
        grid = np.linspace(float(fix_stamps[0]), float(fix_stamps[-1]), max(self.max_fixes // 2, self.min_fixes))
        chosen = np.abs(fix_stamps[None, :].astype(np.float64) - grid[:, None]).argmin(axis=1)
        chosen = np.unique(np.concatenate([[0, len(fix_stamps) - 1], chosen])).tolist()
        for kept in (self._fix_stamps, self._fix_positions, self._fix_covariances):
            kept[:] = [kept[i] for i in chosen]
        self._fix_information = summed_information(self._fix_covariances)
        if not self._stamps:
            return
        stamps = np.asarray(self._stamps, dtype=np.int64)
        nearest = np.abs(stamps[:, None] - np.asarray(self._fix_stamps, dtype=np.int64)[None, :]).argmin(axis=0)
        keep = stamps > self._fix_stamps[-1]
        keep[nearest] = True
        for local in (self._stamps, self._positions, self._covariances):
            local[:] = [value for value, kept in zip(local, keep.tolist(), strict=True) if kept]

    def add_local(self, stamp_ns: int, position: npt.ArrayLike, covariance: npt.ArrayLike) -> None:
        """Keep the filter's local position (3,) m and its covariance (3, 3) m² at an observation time."""
        if self._stamps and stamp_ns <= self._stamps[-1]:
            self._positions[-1] = np.array(position, dtype=np.float64)
            self._covariances[-1] = np.array(covariance, dtype=np.float64)
        else:
            self._stamps.append(int(stamp_ns))
            self._positions.append(np.array(position, dtype=np.float64))
            self._covariances.append(np.array(covariance, dtype=np.float64))
        if len(self._fix_stamps) > self.max_fixes:
            self._thin()  # here, not in add_fix: the local position at the newest fix is now in
        if len(self._fix_stamps) == 1 or (self._fix_stamps and self._stamps[-1] <= self._fix_stamps[-1]):
            self._provisional_stale = True  # otherwise the pairs, and so the transform, have not changed

    def update(self, stamp_ns: int, position: npt.ArrayLike, covariance: npt.ArrayLike) -> FrameFit | None:
        """:meth:`add_local`, then :meth:`fit` if a fix arrived since the last attempt (else ``None``)."""
        self.add_local(stamp_ns, position, covariance)
        if self._fixes_received == self._fixes_tried:
            return None
        self._fixes_tried = self._fixes_received
        return self.fit()

    @property
    def provisional(self) -> FloatArray:
        """Best ``T_world_local`` (4, 4) so far, for the output before the frame is pinned (identity without fixes)."""
        if self._provisional_stale:
            self._update_provisional()
            self._provisional_stale = False
        return self._provisional.copy()

    def _pairs(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None:
        """Local positions and covariances at the observation times within the fixes' span, and the fixes there."""
        if not self._fix_stamps or not self._stamps:
            return None
        stamps = np.asarray(self._stamps, dtype=np.int64)
        inside = (stamps >= self._fix_stamps[0]) & (stamps <= self._fix_stamps[-1])
        if len(self._fix_stamps) == 1 or not inside.any():
            # One fix (or none inside the span): pair it with the nearest local position.
            inside = np.zeros(len(stamps), dtype=bool)
            inside[int(np.argmin(np.abs(stamps - self._fix_stamps[-1])))] = True
            if len(self._fix_stamps) == 1:
                world = np.array([self._fix_positions[0]])
                world_cov = np.array([self._fix_covariances[0]])
                return (np.asarray(self._positions)[inside], np.asarray(self._covariances)[inside], world, world_cov)
        world, world_cov = interpolate_fixes(
            self._fix_stamps, np.asarray(self._fix_positions), np.asarray(self._fix_covariances), stamps[inside]
        )
        return np.asarray(self._positions)[inside], np.asarray(self._covariances)[inside], world, world_cov

    def _agree_with_local(
        self, local: FloatArray, local_cov: FloatArray, world: FloatArray, world_cov: FloatArray
    ) -> bool:
        """Whether the fixes are consistent with ``world`` being the local frame itself.

        The null hypothesis of the frame fit: the pairs' residuals ``world - local`` tested against
        their covariances (chi-square at ``AGREEMENT_PROBABILITY``, the pairs between two fixes
        counted once per fix, as in :meth:`fit`). When the fixes cannot tell their frame from the
        filter's, moving the filter by a transform fitted to their noise only adds that noise.
        """
        residual = world - local
        try:
            W = np.linalg.inv(world_cov + local_cov)
        except np.linalg.LinAlgError:
            return False
        fixes = max(1, int(np.count_nonzero(np.asarray(self._fix_stamps) <= self._stamps[-1])))
        chi2 = float(np.einsum("na,nab,nb->", residual, W, residual)) * min(1.0, fixes / len(local))
        return chi2 <= chi2_gate(AGREEMENT_PROBABILITY, 3 * min(fixes, len(local)))

    def _update_provisional(self) -> None:
        pairs = self._pairs()
        if pairs is None:
            return
        local, local_cov, world, world_cov = pairs
        if self._agree_with_local(local, local_cov, world, world_cov):
            self._provisional = np.eye(4)
            return
        basis = self.measured_basis
        measured = basis.shape[1]
        rotation = np.eye(3)
        travel_local, travel_world = local[-1] - local[0], world[-1] - world[0]
        if measured == 3:
            if len(local) >= 2 and np.linalg.norm(travel_world) > 3.0 * np.sqrt(np.trace(self._fix_covariances[-1])):
                rotation = smallest_rotation(travel_local, travel_world)
            offset = world.mean(axis=0) - rotation @ local.mean(axis=0)
        else:  # turned about the unmeasured axis only (with one), moved only where the fixes measure
            noise = np.sqrt(np.trace(basis.T @ self._fix_covariances[-1] @ basis))
            if measured == 2 and len(local) >= 2 and np.linalg.norm(basis.T @ travel_world) > 3.0 * noise:
                rotation = fit_rigid_on_axes(local[[0, -1]], world[[0, -1]], np.ones(2), basis).rotation
            offset = basis @ basis.T @ (world.mean(axis=0) - rotation @ local.mean(axis=0))
        T = np.eye(4)
        T[:3, :3] = rotation
        T[:3, 3] = offset
        self._provisional = T

    def required_spread(self) -> float:
        """The fixes' spread (m) a fit needs: ``min_spread``, or :data:`SPREAD_SIGMAS` times the fixes'
        noise (the RMS of their standard deviations along the axes they measure,
        :func:`~relpoint.geometry.measured_basis`; the local positions' when the fixes claim none), so that the rotation is pinned as well at any noise and scale: 8 m for 1 m fixes
        (the fixed default before), 1.6 m for 0.2 m fixes, 40 m for 5 m ones."""
        if self.min_spread is not None:
            return self.min_spread
        basis = self.measured_basis
        sigma = (
            float(np.sqrt(np.mean(np.einsum("ai,nab,bi->n", basis, np.asarray(self._fix_covariances), basis))
                          / basis.shape[1]))
            if self._fix_covariances
            else 0.0
        )  # fmt: skip
        if sigma <= 0.0 and self._covariances:
            sigma = float(np.sqrt(max(np.mean([np.trace(c) / 3.0 for c in self._covariances]), 0.0)))
        return SPREAD_SIGMAS * max(sigma, MIN_SPREAD_NOISE)

    def fit(self) -> FrameFit | None:
        """Fit ``T_world_local`` if at least ``min_fixes`` fixes with the required spread are paired
        (:meth:`required_spread`); else None."""
        if len(self._fix_stamps) < self.min_fixes:
            return None
        basis = self.measured_basis
        measured = basis.shape[1]
        projector = basis @ basis.T  # onto the directions the fixes measure
        spread = line_spread(np.asarray(self._fix_positions) @ projector, time_weights(self._fix_stamps))
        required = self.required_spread()
        if spread < required:
            return None
        pairs = self._pairs()
        if pairs is None or len(pairs[0]) < 3:
            return None
        local, local_cov, world, world_cov = pairs
        if line_spread(local @ projector) < 0.5 * required:
            return None  # the local path has not spread (yet) as the fixes have: no rotation to fit
        noise_measured = np.einsum("ai,nab,bj->nij", basis, world_cov + local_cov, basis)
        weights = 1.0 / np.maximum(np.trace(noise_measured, axis1=1, axis2=2), 1e-12)
        w = weights / weights.sum()
        result = fit_rigid_on_axes(local, world, weights, basis)
        fitted, fit_rms = result.as_matrix(), result.rms
        agree = self._agree_with_local(local, local_cov, world, world_cov)
        T = np.eye(4) if agree else fitted
        placed = apply_transform(T, local)
        # Information of (dt, dphi) about the weighted centroid, from every pair, counted once per fix.
        noise = world_cov + T[:3, :3] @ local_cov @ T[:3, :3].T
        try:
            W = np.linalg.inv(noise)
        except np.linalg.LinAlgError:
            return None
        # the centroid of the fixes where they measure, of the placed path where they do not
        centre = projector @ (w @ world) + (np.eye(3) - projector) @ (w @ placed)
        J = np.zeros((len(local), 3, 6))
        J[:, :, :3] = np.eye(3)
        J[:, :, 3:] = -skew(placed - centre)
        fixes_spanned = int(np.count_nonzero(np.asarray(self._fix_stamps) <= self._stamps[-1]))
        information = np.einsum("nai,nab,nbj->ij", J, W, J) * min(1.0, max(fixes_spanned, 3) / len(local))
        residual = world - placed
        chi2 = 1.0 if agree else float(np.mean(np.einsum("na,nab,nb->n", residual, W, residual))) / measured
        parameters = fitted_parameters(basis)  # the rest stay exact: no uncertainty
        try:
            reduced = np.linalg.inv(parameters.T @ information @ parameters)
        except np.linalg.LinAlgError:
            return None
        covariance = parameters @ reduced @ parameters.T * max(1.0, chi2)
        # Frames that agree are one frame: no transform, so no transform error for the filter to carry.
        covariance = np.zeros((6, 6)) if agree else 0.5 * (covariance + covariance.T)
        logger.debug(
            "frame pinned by %d fixes (%d pairs, spread %.1f m, rms %.2f m)",
            fixes_spanned,
            len(local),
            spread,
            fit_rms,
        )
        rms = (
            float(np.sqrt(np.sum(weights * np.sum((residual @ projector) ** 2, axis=1)) / np.sum(weights)))
            if agree
            else fit_rms
        )
        return FrameFit(T, covariance, centre, len(local), fixes_spanned, rms, spread)


def frame_summary(rigid: bool, fit: FrameFit | None) -> dict[str, Any]:
    """run.json figures of the fix frame: whether it is pinned, by how many fixes, and the fit's residual."""
    if not rigid:
        return {}
    if fit is None:
        return {"fix_frame": "local"}
    return {"fix_frame": "fixes", "fix_frame_fixes": fit.fixes, "fix_frame_rms": round(fit.rms, 4)}


def placed_in_one_frame(
    trajectory: Trajectory, local_poses: list[tuple[int, FloatArray]], fit: FrameFit | None, frame: FixFrame | None
) -> Trajectory:
    """``trajectory`` with each pose output before the frame was pinned placed again by one transform.

    Before the pinning a filter outputs its local pose under the provisional transform of that
    iteration, which changes as fixes arrive: the early poses are then in as many frames as there
    were transforms. At the end, the poses at the stamps of ``local_poses`` ((stamp ns, the filter's
    local pose (4, 4)) per iteration before the pinning) are replaced by ``T_world_local @ pose``:
    ``T_world_local`` is the pinning's (``fit``), or the last provisional one of ``frame`` when the
    fixes never pinned it. The other poses (after the pinning, already in ``world``) are kept; so is
    the whole trajectory when no fix arrived.
    """
    if fit is not None:
        T_world_local = fit.T_world_local
    elif frame is not None and frame.fix_count:
        T_world_local = frame.provisional
    else:
        return trajectory
    if not local_poses:
        return trajectory
    stamps = np.array([stamp for stamp, _ in local_poses], dtype=np.int64)
    poses = np.stack([pose for _, pose in local_poses])
    matrices = trajectory.matrices().copy()
    rows = np.minimum(np.searchsorted(trajectory.stamps_ns, stamps), len(trajectory.stamps_ns) - 1)
    found = trajectory.stamps_ns[rows] == stamps
    matrices[rows[found]] = T_world_local @ poses[found]
    return Trajectory.from_matrices(trajectory.stamps_ns, matrices)


def drawn_frame_transform(centre: FloatArray, draw: FloatArray) -> FloatArray:
    """The rigid transform (4, 4) in ``world`` of a draw ``(dt, dphi)`` (6,) from a frame fit's uncertainty:
    ``x -> c + Exp(dphi) (x - c) + dt``, with ``c`` the fit's ``centre`` (m; ``dt`` in m, ``dphi`` in rad)."""
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.asarray(draw[3:], dtype=np.float64))
    T[:3, 3] = centre - T[:3, :3] @ centre + draw[:3]
    return T


def moved_to_final_frame(
    trajectory: Trajectory, stamps_ns: npt.NDArray[np.int64], draws: FloatArray, final_draw: FloatArray,
    centre: FloatArray,
) -> Trajectory:  # fmt: skip
    """``trajectory`` with each pose at ``stamps_ns`` moved from the frame it was output in to the final one.

    A particle filter pinned to the fixes' frame gives each particle its own draw from the fit's
    uncertainty (:meth:`relpoint.estimators.fastslam.FastSlam._pin_frame`); the later fixes select
    among them, so the particles' mean draw at an iteration (``draws`` (K, 6) at ``stamps_ns``) is
    the frame its mean pose was output in, and the mean draw when the log ends (``final_draw``) is
    the frame every fix has informed. The frame is one constant of the whole run, so its estimate at
    the end holds for every pose: each is moved by ``F(final) F(draw_k)^-1``
    (:func:`drawn_frame_transform`). A pose at another stamp (before the pinning: placed by the
    pinning's own transform) was output under no draw and is moved by ``F(final)``.
    """
    final = drawn_frame_transform(centre, final_draw)
    moves = np.broadcast_to(final, (len(trajectory), 4, 4)).copy()
    if len(stamps_ns):
        rows = np.minimum(np.searchsorted(trajectory.stamps_ns, stamps_ns), len(trajectory.stamps_ns) - 1)
        found = trajectory.stamps_ns[rows] == stamps_ns
        for row, draw in zip(rows[found], np.asarray(draws)[found], strict=True):
            moves[row] = final @ np.linalg.inv(drawn_frame_transform(centre, draw))
    return Trajectory.from_matrices(trajectory.stamps_ns, moves @ trajectory.matrices())
