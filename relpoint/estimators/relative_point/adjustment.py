"""Joint least-squares adjustment of the relative maps (an addition to Kraut, section II-B).

The paper joins relative maps one at a time: each group is fitted to the global positions its
members already have, once, when it is created (and while it is still averaging), and a point in
several groups gets the weighted mean of the positions its groups give it. Each fit is a least-squares
fit, but the sequence is not the least-squares solution of the whole network: a group placed early is
never moved by what later groups learn about its members, and a group fitted while a moving point
was still among its anchors keeps that error after the point is flagged.

:func:`adjust_network` solves for every group pose and every point position at once::

    minimise   sum_(g, m)  w_gm rho(|| R_g p_gm + t_g - X_m ||)  +  mu sum_m || X_m - X0_m ||^2

over the memberships ``(g, m)`` of point ``m`` in group ``g``: ``p_gm`` is the member's averaged
relative position in the group's basis frame, ``(R_g, t_g)`` the group's pose ``T_world_group`` and
``X_m`` the point's global position, all in metres. ``w_gm`` is the number of iterations the group
averaged (a relative map's noise variance falls with it), and ``rho`` the Cauchy loss with scale
``robust``, so that a moving point the detection missed, or a mismatched one, pulls with bounded
force. The second term ties each point weakly to its position before the adjustment, ``X0``: the
network of relative maps leaves some directions almost free (two groups sharing only two points
hinge about the line through them; a stretch where few points are shared bends at no cost), and
``mu``, a small fraction of one iteration's weight, settles those where the incremental solution had
them instead of letting round-off choose. Groups marked ``fixed`` (the root group, which defines the
world frame) do not move.

The solver is Levenberg-Marquardt over the poses' tangent space (``R <- exp([dtheta]x) R``) with
the points eliminated by the Schur complement: a point's block of the normal equations is a multiple
of the identity, so the reduced system over the 6 G pose unknowns is formed exactly, and it is as
sparse as the groups' sharing of points. Groups share points mostly with groups of nearby time,
so in reverse Cuthill-McKee order the system is banded and is solved by a banded Cholesky
factorisation (:func:`scipy.linalg.solveh_banded`); a wide band falls back to sparse LU. When the
points have fewer unknowns than the free poses (a bundle adjustment over many keyframes of a sparse
map), the poses are eliminated instead (their 6 x 6 blocks inverted) and the reduced system is over
the points. The Cauchy loss enters by iteratively reweighted least squares.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from relpoint.geometry import FloatArray, invert_pose, skew

if TYPE_CHECKING:
    from scipy import sparse

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class Adjustment:
    """The result of :func:`adjust_network`.

    Attributes
    ----------
    R_world_group: (G, 3, 3) adjusted group rotations.
    t_world_group: (G, 3) adjusted group translations, metres.
    positions: (P, 3) adjusted point positions in ``world``, metres.
    cost_before, cost_after: the objective at the start and at the end.
    iterations: Levenberg-Marquardt iterations run (accepted or not).
    converged: whether it stopped because the objective no longer fell, not at ``iterations``.
    """

    R_world_group: FloatArray
    t_world_group: FloatArray
    positions: FloatArray
    cost_before: float
    cost_after: float
    iterations: int
    converged: bool = False


def _objective(residual: FloatArray, weight: FloatArray, robust: float, prior: float, shift: FloatArray) -> float:
    squared = np.einsum("ni,ni->n", residual, residual)
    if robust > 0:
        fit = float(np.sum(weight * robust**2 * np.log1p(squared / robust**2)))
    else:
        fit = float(np.sum(weight * squared))
    return fit + prior * float(np.sum(shift * shift))


_SIX = np.arange(6)
_THREE = np.arange(3)


def _block_diagonal(blocks: FloatArray) -> sparse.csr_matrix:
    """Sparse matrix with the (G, 6, 6) ``blocks`` along its diagonal."""
    from scipy import sparse  # here, not at import: scipy costs start-up time

    n = 6 * len(blocks)
    rows = np.repeat(np.arange(n), 6)
    cols = (rows // 6 * 6).reshape(-1, 6) + _SIX
    return sparse.csr_matrix((blocks.ravel(), (rows, cols.ravel())), shape=(n, n))


#: Largest reduced system solved densely when its band is wide (about 0.3 s to factorise at this size).
DENSE_SOLVE_LIMIT = 6000


def _solve_positive_definite(S: sparse.csr_matrix, rhs: FloatArray, order: IntArray) -> FloatArray:
    """Solve the symmetric positive definite ``S x = rhs``.

    Groups couple mostly to groups of nearby time, so in reverse Cuthill-McKee ``order`` the
    reduced system is banded: a banded Cholesky factorisation (LAPACK) costs n b^2 for bandwidth b,
    several times less than a general sparse LU here. A wide band (long loops) is factorised densely
    up to ``DENSE_SOLVE_LIMIT`` unknowns, and beyond that by SuperLU.
    """
    from scipy.linalg import cho_factor, cho_solve, solveh_banded  # here, not at import: scipy costs start-up time
    from scipy.sparse.linalg import spsolve

    n = S.shape[0]
    permuted = S[order][:, order].tocoo()
    upper = permuted.row <= permuted.col
    bandwidth = int(np.max(permuted.col[upper] - permuted.row[upper], initial=0))
    if bandwidth < n // 3:
        banded = np.zeros((bandwidth + 1, n))
        banded[bandwidth + permuted.row[upper] - permuted.col[upper], permuted.col[upper]] = permuted.data[upper]
        try:
            solution = np.empty(n)
            solution[order] = solveh_banded(banded, rhs[order], check_finite=False)
            return solution
        except np.linalg.LinAlgError:
            pass
    elif n <= DENSE_SOLVE_LIMIT:
        # A wide band (a bundle adjustment's points seen from every keyframe, long loops): a dense
        # Cholesky factorisation, n^3 / 3, is far cheaper than sparse LU's fill-in at this size.
        try:
            return cho_solve(cho_factor(S.toarray(), check_finite=False), rhs, check_finite=False)
        except np.linalg.LinAlgError:
            pass
    return np.asarray(spsolve(S.tocsc(), rhs))


def adjust_network(
    group: IntArray,
    point: IntArray,
    relative: FloatArray,
    weight: FloatArray,
    R_world_group: FloatArray,
    t_world_group: FloatArray,
    positions: FloatArray,
    fixed: BoolArray,
    *,
    prior: float,
    robust: float,
    iterations: int,
) -> Adjustment:
    """Least-squares poses of all groups and positions of all points (see the module docstring).

    Parameters
    ----------
    group, point:
        (N,) group row and point row of each membership.
    relative:
        (N, 3) the member's averaged position in its group's basis frame, metres.
    weight:
        (N,) weight of each membership (iterations averaged), > 0.
    R_world_group, t_world_group:
        (G, 3, 3) and (G, 3): the groups' poses before the adjustment (the starting point).
    positions:
        (P, 3) the points' positions before the adjustment (starting point and prior), metres.
    fixed:
        (G,) groups whose pose stays as it is.
    prior:
        ``mu``, weight of a point's pull towards its position before the adjustment (>= 0; > 0 is
        needed when no group is fixed).
    robust:
        Cauchy scale (m); 0 for plain least squares.
    iterations:
        Largest number of Levenberg-Marquardt iterations.
    """
    from scipy import sparse  # here, not at import: scipy costs start-up time
    from scipy.sparse.csgraph import reverse_cuthill_mckee
    from scipy.spatial.transform import Rotation

    n_groups, n_points = len(R_world_group), len(positions)
    R = np.array(R_world_group, dtype=np.float64)
    t = np.array(t_world_group, dtype=np.float64)
    X = np.array(positions, dtype=np.float64)
    X0 = X.copy()
    free = ~np.asarray(fixed, bool)

    def residuals(R: FloatArray, t: FloatArray, X: FloatArray) -> tuple[FloatArray, FloatArray]:
        rotated = np.einsum("nij,nj->ni", R[group], relative)
        return rotated, rotated + t[group] - X[point]

    keep = np.repeat(free, 6)
    # The reduced system is over the poses (points eliminated) unless the points are fewer.
    eliminate_poses = 3 * n_points < 6 * int(np.count_nonzero(free))
    order: IntArray | None = None  # a bandwidth-reducing order of the reduced system (same every iteration)
    rotated, residual = residuals(R, t, X)
    cost = cost_before = _objective(residual, weight, robust, prior, X - X0)
    damping = 1e-4
    done = 0
    converged = False
    for done in range(1, iterations + 1):  # noqa: B007 - the count is reported
        # Cauchy loss by reweighting: rho'(e) / e = 1 / (1 + e^2 / c^2).
        omega = weight / (1.0 + np.einsum("ni,ni->n", residual, residual) / robust**2) if robust > 0 else weight
        # Jacobian of a residual: d/d(dtheta, dt) = [-[q]x, I] with q = R p; d/dX = -I.
        J_pose = np.concatenate([-skew(rotated), np.broadcast_to(np.eye(3), (len(group), 3, 3))], axis=2)
        A_blocks = np.einsum("n,nki,nkj->nij", omega, J_pose, J_pose)
        B = -omega[:, None, None] * np.transpose(J_pose, (0, 2, 1))  # (N, 6, 3): pose-point coupling
        g_pose = np.zeros((n_groups, 6))
        np.add.at(g_pose, group, -np.einsum("n,nki,nk->ni", omega, J_pose, residual))
        C = np.bincount(point, omega, minlength=n_points) + prior
        g_point = np.zeros((n_points, 3))
        np.add.at(g_point, point, omega[:, None] * residual)
        g_point -= prior * (X - X0)

        A_diag = np.zeros((n_groups, 6, 6))
        np.add.at(A_diag, group, A_blocks)
        A_diag += damping * np.einsum("gii->gi", A_diag)[:, :, None] * np.eye(6)[None]
        C_damped = C * (1.0 + damping)
        # Schur complement S = A - B C^-1 B^T, with B as a sparse (6 G, 3 P) matrix of 6 x 3 blocks.
        B_sparse = sparse.csr_matrix(
            (
                B.ravel(),
                (
                    np.repeat(6 * group[:, None] + _SIX, 3, axis=1).ravel(),
                    (3 * point[:, None, None] + _THREE).repeat(6, axis=1).ravel(),
                ),
            ),
            shape=(6 * n_groups, 3 * n_points),
        )
        step_pose = np.zeros((n_groups, 6))
        if eliminate_poses:
            # Fewer point unknowns than pose unknowns (a bundle adjustment over many keyframes): the
            # poses go instead, T = C - B^T A^-1 B over the points (A's blocks are 6 x 6, one a pose).
            # A pose seen only along a line cannot turn about it: a ridge far below any observed
            # curvature keeps its block invertible and that turn at zero.
            A_free = A_diag[free]
            ridge = 1e-9 * np.einsum("gii->g", A_free) / 6.0 + 1e-12
            A_inverse = np.linalg.inv(A_free + ridge[:, None, None] * np.eye(6))
            B_free = B_sparse[keep]
            T = sparse.diags(np.repeat(C_damped, 3)) - B_free.T @ _block_diagonal(A_inverse) @ B_free
            A_inverse_g = np.einsum("gij,gj->gi", A_inverse, g_pose[free])
            rhs = g_point.ravel() - B_free.T @ A_inverse_g.ravel()
            T = T.tocsr()
            if order is None:
                order = reverse_cuthill_mckee(T, symmetric_mode=True)
            step_point = _solve_positive_definite(T, rhs, order).reshape(n_points, 3)
            coupled = (B_free @ step_point.ravel()).reshape(-1, 6)
            step_pose[free] = np.einsum("gij,gj->gi", A_inverse, g_pose[free] - coupled)
        else:
            S = _block_diagonal(A_diag) - B_sparse @ sparse.diags(np.repeat(1.0 / C_damped, 3)) @ B_sparse.T
            BCg = np.zeros((n_groups, 6))
            np.add.at(BCg, group, np.einsum("nij,nj->ni", B, g_point[point] / C_damped[point, None]))
            rhs = (g_pose - BCg).ravel()
            if keep.any():
                reduced = S.tocsr()[keep][:, keep]
                if order is None:
                    order = reverse_cuthill_mckee(reduced, symmetric_mode=True)
                step_pose[free] = _solve_positive_definite(reduced, rhs[keep], order).reshape(-1, 6)
            BT_step = np.zeros((n_points, 3))
            np.add.at(BT_step, point, np.einsum("nji,nj->ni", B, step_pose[group]))
            step_point = (g_point - BT_step) / C_damped[:, None]

        R_new = np.einsum("gij,gjk->gik", Rotation.from_rotvec(step_pose[:, :3]).as_matrix(), R)
        t_new = t + step_pose[:, 3:]
        X_new = X + step_point
        rotated_new, residual_new = residuals(R_new, t_new, X_new)
        cost_new = _objective(residual_new, weight, robust, prior, X_new - X0)
        if np.isfinite(cost_new) and cost_new < cost:
            converged = cost - cost_new < 1e-6 * cost
            R, t, X, rotated, residual, cost = R_new, t_new, X_new, rotated_new, residual_new, cost_new
            damping = max(damping / 10.0, 1e-8)
            if converged:
                break
        else:
            damping *= 10.0
            if damping > 1e4:
                converged = True  # no step lowers the objective: a minimum to numerical precision
                break
    return Adjustment(R, t, X, cost_before, cost, done, converged)


def inconsistent_relocations(
    before: FloatArray,
    after: FloatArray,
    fitted: npt.NDArray[np.bool_],
    seen: FloatArray,
    *,
    floor: float,
    window: int = 5,
    factor: float = 4.0,
) -> npt.NDArray[np.bool_]:
    """Iterations whose relocation disagrees with their neighbours' (K,) bool.

    The adjustment moves the map smoothly along the path (it corrects drift, which builds up
    slowly), so the correction an iteration's new fit applies is close to the corrections of the
    iterations around it. A fit on few or badly placed points breaks that: it moves what the sensor
    saw by much more than its neighbours' fits do. For each fitted iteration, what its correction
    does to the sensor position and to the centroid of what it saw (``seen``, (K, 3) sensor frame,
    m) is compared with the median of the same over the fitted iterations within ``window``; an
    iteration beyond ``factor`` times the robust spread of these differences over the log (at
    least ``floor``, m) is inconsistent.

    ``before`` and ``after`` are the poses ``T_world_sensor`` (K, 4, 4) before and after the
    adjustment; only iterations with ``fitted`` are judged.
    """
    judged = np.flatnonzero(fitted)
    inconsistent = np.zeros(len(fitted), bool)
    if len(judged) < 2 * window + 1:
        return inconsistent
    anchors = np.stack([np.zeros((len(judged), 3)), seen[judged]], axis=1)  # (J, 2, 3) sensor frame
    shift_after = np.einsum("jxy,jay->jax", after[judged, :3, :3], anchors) + after[judged, None, :3, 3]
    shift_before = np.einsum("jxy,jay->jax", before[judged, :3, :3], anchors) + before[judged, None, :3, 3]
    shift = (shift_after - shift_before).reshape(len(judged), 6)  # (J, 6): the two anchors' displacement
    neighbours = np.lib.stride_tricks.sliding_window_view(
        np.pad(shift, ((window, window), (0, 0)), mode="edge"), 2 * window + 1, axis=0
    )  # (J, 6, 2w + 1)
    local = np.median(neighbours, axis=2)
    difference = np.linalg.norm((shift - local).reshape(len(judged), 2, 3), axis=2).max(axis=1)
    spread = 1.4826 * float(np.median(difference))
    inconsistent[judged] = difference > max(factor * spread, floor)
    return inconsistent


def smooth_corrections(before: FloatArray, after: FloatArray, fitted: npt.NDArray[np.bool_], window: int) -> FloatArray:
    """Poses (K, 4, 4) whose corrections are the median of the fitted iterations' within ``window``.

    The correction of iteration ``k`` is a rotation ``R_after R_before^T`` about the sensor and a
    displacement of the sensor ``p_after - p_before`` (world frame). Each iteration with a fitted
    iteration within ``window`` on either side takes the component-wise median of their rotation
    vectors and displacements, applied to its pose in ``before``; the others keep their pose in
    ``after``. ``before`` and ``after`` are ``T_world_sensor``.
    """
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

    fitted_rows = np.flatnonzero(fitted)
    smoothed = after.copy()
    if len(fitted_rows) == 0:
        return smoothed
    rotation = Rotation.from_matrix(
        after[fitted_rows, :3, :3] @ np.transpose(before[fitted_rows, :3, :3], (0, 2, 1))
    ).as_rotvec()
    displacement = after[fitted_rows, :3, 3] - before[fitted_rows, :3, 3]
    k = np.arange(len(before))
    low = np.searchsorted(fitted_rows, k - window)
    high = np.searchsorted(fitted_rows, k + window, side="right")
    for row in np.flatnonzero(high > low):
        lo, hi = low[row], high[row]
        turn = Rotation.from_rotvec(np.median(rotation[lo:hi], axis=0)).as_matrix()
        smoothed[row, :3, :3] = turn @ before[row, :3, :3]
        smoothed[row, :3, 3] = before[row, :3, 3] + np.median(displacement[lo:hi], axis=0)
    return smoothed


def carry_corrections(before: FloatArray, after: FloatArray, fitted: npt.NDArray[np.bool_]) -> FloatArray:
    """Poses (K, 4, 4): ``after`` where ``fitted``, elsewhere ``before`` moved by the correction
    ``after @ inv(before)`` of the nearest fitted iteration before it (after it, for those before the
    first). ``before`` and ``after`` are ``T_world_sensor``; all poses of ``after`` unchanged if none is fitted."""
    fitted_rows = np.flatnonzero(fitted)
    if len(fitted_rows) == 0:
        return after.copy()
    k = np.arange(len(before))
    nearest = fitted_rows[np.clip(np.searchsorted(fitted_rows, k, side="right") - 1, 0, None)]
    correction = after[nearest] @ invert_pose(before[nearest])
    carried = correction @ before
    carried[fitted_rows] = after[fitted_rows]
    return carried


def residual_trend(point: IntArray, residual: FloatArray, n_points: int) -> FloatArray:
    """How unlikely each point's residuals are to trend over its observations if it is static (n_points,).

    ``point`` and ``residual`` as in :func:`residual_drift` (each point's residuals in time order).
    Each axis's residuals are regressed on the observation's rank; for a static point with white
    noise the regression's mean square over the residual one follows F(3, 3 (n - 2)) for ``n``
    observations, whatever its noise level. The F distribution's upper-tail probability is returned
    (small: it trends); 1 for a point seen fewer than six times. A mover that wanders one way (a
    random walk, a slow drift) trends over its whole track, where blocks cut it into short steps.
    """
    from scipy.special import fdtrc  # here, not at import: scipy costs start-up time

    order = np.argsort(point, kind="stable")
    rows, r = point[order], residual[order]
    count = np.bincount(rows, minlength=n_points).astype(np.float64)
    start = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
    rank = np.arange(len(rows)) - start[rows]
    centred_rank = rank - (count[rows] - 1.0) / 2.0
    mean = np.zeros((n_points, 3))
    np.add.at(mean, rows, r)
    mean /= np.maximum(count, 1.0)[:, None]
    deviation = r - mean[rows]
    spread = count * (count**2 - 1.0) / 12.0  # sum of the centred ranks' squares
    moment = np.zeros((n_points, 3))
    np.add.at(moment, rows, centred_rank[:, None] * deviation)
    explained = np.sum(moment**2, axis=1) / np.maximum(spread, 1e-300)
    total = np.bincount(rows, np.sum(deviation**2, axis=1), minlength=n_points)
    d_residual = np.maximum(3.0 * (count - 2.0), 1.0)
    ratio = (explained / 3.0) / np.maximum((total - explained) / d_residual, 1e-300)
    return np.where(count >= 6, fdtrc(3.0, d_residual, ratio), 1.0)


def residual_drift(
    point: IntArray, residual: FloatArray, n_points: int, *, block: int
) -> tuple[FloatArray, FloatArray]:
    """How far each point's residuals drift over its observations, and how unlikely that is if it is static.

    Parameters
    ----------
    point:
        (N,) point row of each residual, the residuals of each point in time order.
    residual:
        (N, 3) each observation placed by its pose minus its point's position (``world``, metres).
    n_points:
        Number of points (rows ``0 .. n_points - 1``).
    block:
        Observations per block; a point seen less than twice that many times is cut into two blocks.

    Each point's residuals are cut into consecutive blocks (the last one takes the remainder) and
    judged by a one-way analysis of variance: for a static point with white noise the
    between-block mean square over the within-block mean square follows F(3 (b - 1), 3 (n - b)) for
    ``n`` observations in ``b`` blocks, whatever its noise level, so points of every range and sensor
    are judged alike.

    Returns
    -------
    probability:
        (n_points,) the F distribution's upper-tail probability of the point's ratio (small: it
        drifts); 1 for a point seen fewer than six times (not judged).
    motion:
        (n_points,) the largest distance of a block mean from the point's mean, in the point's own
        noises (per axis, within blocks).
    """
    from scipy.special import fdtrc  # here, not at import: scipy costs start-up time (scipy.stats far more)

    order = np.argsort(point, kind="stable")
    rows, r = point[order], residual[order]
    count = np.bincount(rows, minlength=n_points)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    size = np.clip(count // 2, 1, block)
    blocks = np.maximum(count // size, 1)
    rank = np.arange(len(rows)) - start[rows]
    label = start[rows] + np.minimum(rank // size[rows], blocks[rows] - 1)  # unique per (point, block)
    labels, member, members = np.unique(label, return_inverse=True, return_counts=True)
    block_mean = np.zeros((len(labels), 3))
    np.add.at(block_mean, member, r)
    block_mean /= members[:, None]
    block_point = np.empty(len(labels), np.int64)
    block_point[member] = rows
    point_mean = np.zeros((n_points, 3))
    np.add.at(point_mean, rows, r)
    point_mean /= np.maximum(count, 1)[:, None]
    within = np.bincount(rows, np.sum((r - block_mean[member]) ** 2, axis=1), minlength=n_points)
    offset = np.linalg.norm(block_mean - point_mean[block_point], axis=1)
    between = np.bincount(block_point, members * offset**2, minlength=n_points)
    farthest = np.zeros(n_points)
    np.maximum.at(farthest, block_point, offset)
    d_between = np.maximum(3 * (blocks - 1), 1)
    d_within = np.maximum(3 * (count - blocks), 1)
    noise = np.sqrt(np.maximum(within / d_within, 1e-300))  # per axis, within blocks, m
    probability = fdtrc(d_between, d_within, (between / d_between) / noise**2)
    return np.where(count >= 6, probability, 1.0), farthest / noise
