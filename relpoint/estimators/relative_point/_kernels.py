"""Compiled inner loops of the Relative Point estimator (numba), each with a plain numpy meaning.

At about 100 observed points an iteration runs several rigid fits and matchings over arrays of a
few dozen rows, where the cost is numpy's per-call overhead rather than arithmetic. These kernels
do the same arithmetic in compiled loops. Each docstring gives the numpy expression the kernel
equals (up to floating-point rounding); ``tests/test_relative_point_parts.py`` checks every kernel
against that expression on random inputs.

An install builds all kernels ahead of time into the extension module ``_kernels_aot`` (numba's
``pycc``, from the argument types each :func:`kernel` names; see ``setup.py`` and
:mod:`relpoint._aot_kernels`, the mechanism FastSLAM's kernels share), so no run pays for
compilation and numba itself is not even imported. Without that module (no C compiler at install,
a source checkout, or ``RELPOINT_KERNELS=jit``), or when it was built from another version of this
file, each kernel is compiled on its first call instead (``cache=True`` keeps the machine code in
``__pycache__`` or ``NUMBA_CACHE_DIR``: about ten seconds of CPU once, under half a second to load
later). Both are the same LLVM code of the same loops and give bit-identical results. The kernels
are plain loops over scalars: numpy's sorting, linear algebra and broadcasting inside a kernel cost
seconds of compilation each, so the callers sort and the 3x3 rotation is solved by hand.
"""

from __future__ import annotations

import math

import numpy as np

from relpoint._aot_kernels import KernelSet

kernels = KernelSet(__file__, "relpoint.estimators.relative_point._kernels_aot")
"""This file's kernels: prebuilt at install into ``_kernels_aot`` or compiled on first call."""
kernel = kernels.kernel
SIGNATURES: dict[str, str] = kernels.signatures
"""Argument types of every kernel in numba's notation, by name: what the ahead-of-time build compiles."""
COMPILED_AHEAD = kernels.compiled_ahead
"""Whether the kernels below are the prebuilt machine code (True) or compiled on first call (False)."""
source_digest = kernels.source_digest
prepare = kernels.prepare
"""Compile every public kernel for its declared argument types, or load it from numba's cache
(nothing to do when :data:`COMPILED_AHEAD`); a run calls this before its first iteration."""

# -- RltLSF (section II-B): least-squares rigid fitting ------------------------------------------


@kernel("f8, f8, f8, f8, f8, f8")
def off_line_rms(a: float, b: float, c: float, d: float, e: float, f: float) -> float:
    """RMS distance off the best line of a scatter ``[[a, d, e], [d, b, f], [e, f, c]]`` (m^2 entries).

    numpy: ``sqrt(max(eigvalsh(S)[:2].sum(), 0))``, the square root of the sum of the two smallest
    eigenvalues (trace minus the largest), found in closed form (trigonometric solution of the
    symmetric 3x3 eigenproblem).
    """
    trace = a + b + c
    p1 = d * d + e * e + f * f
    q = trace / 3.0
    p2 = (a - q) ** 2 + (b - q) ** 2 + (c - q) ** 2 + 2.0 * p1
    if p2 <= 1e-300:
        return math.sqrt(max(trace - q, 0.0))  # isotropic: all three eigenvalues equal q
    p = math.sqrt(p2 / 6.0)
    ba, bb, bc, bd, be, bf = (a - q) / p, (b - q) / p, (c - q) / p, d / p, e / p, f / p
    r = 0.5 * (ba * (bb * bc - bf * bf) - bd * (bd * bc - bf * be) + be * (bd * bf - bb * be))
    largest = q + 2.0 * p * math.cos(math.acos(min(1.0, max(-1.0, r))) / 3.0)
    return math.sqrt(max(trace - largest, 0.0))


@kernel("f8[:, ::1]")
def _largest_eigenvector4(N: np.ndarray) -> tuple[float, float, float, float]:
    """Unit eigenvector (4,) of the largest eigenvalue of a symmetric 4x4 matrix (cyclic Jacobi rotations).

    numpy: ``eigh(N)[1][:, -1]`` (up to sign).
    """
    A = np.empty((4, 4))
    V = np.zeros((4, 4))
    for p in range(4):
        V[p, p] = 1.0
        for q in range(4):
            A[p, q] = N[p, q]
    for _ in range(50):
        off = 0.0
        diagonal = 0.0
        for p in range(4):
            diagonal += A[p, p] * A[p, p]
            for q in range(p + 1, 4):
                off += A[p, q] * A[p, q]
        if off <= 1e-34 * diagonal or off == 0.0:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                apq = A[p, q]
                if apq == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for r in range(4):  # A <- A J (columns p, q)
                    arp, arq = A[r, p], A[r, q]
                    A[r, p] = c * arp - s * arq
                    A[r, q] = s * arp + c * arq
                for r in range(4):  # A <- J^T A (rows p, q)
                    apr, aqr = A[p, r], A[q, r]
                    A[p, r] = c * apr - s * aqr
                    A[q, r] = s * apr + c * aqr
                for r in range(4):
                    vrp, vrq = V[r, p], V[r, q]
                    V[r, p] = c * vrp - s * vrq
                    V[r, q] = s * vrp + c * vrq
    best = 0
    for p in range(1, 4):
        if A[p, p] > A[best, best]:
            best = p
    return V[0, best], V[1, best], V[2, best], V[3, best]


@kernel("f8[:, ::1], f8[:, ::1]")
def best_rotation_into(T: np.ndarray, H: np.ndarray) -> None:
    """``T[:3, :3] = R``, the proper rotation maximising ``trace(R H)`` for a cross-covariance ``H`` (3, 3).

    ``H = sum_i s_i d_i^T`` (centred source x target), so ``R`` is the least-squares rotation with
    ``d ≈ R s``. numpy (Arun / Umeyama, reflection case handled)::

        U, _, Vt = svd(H);  R = Vt.T @ diag(1, 1, sign(det(Vt.T @ U.T))) @ U.T

    found here by Horn's method, as the unit quaternion of the largest eigenvalue of a symmetric 4x4
    built from ``H``: a few Jacobi sweeps over registers, where a LAPACK SVD of a 3x3 matrix costs
    several times more once its code has left the cache between calls.
    """
    sxx, sxy, sxz = H[0, 0], H[0, 1], H[0, 2]
    syx, syy, syz = H[1, 0], H[1, 1], H[1, 2]
    szx, szy, szz = H[2, 0], H[2, 1], H[2, 2]
    N = np.empty((4, 4))
    N[0, 0] = sxx + syy + szz
    N[0, 1] = N[1, 0] = syz - szy
    N[0, 2] = N[2, 0] = szx - sxz
    N[0, 3] = N[3, 0] = sxy - syx
    N[1, 1] = sxx - syy - szz
    N[1, 2] = N[2, 1] = sxy + syx
    N[1, 3] = N[3, 1] = szx + sxz
    N[2, 2] = -sxx + syy - szz
    N[2, 3] = N[3, 2] = syz + szy
    N[3, 3] = -sxx - syy + szz
    w, x, y, z = _largest_eigenvector4(N)
    norm2 = w * w + x * x + y * y + z * z
    w, x, y, z = w / math.sqrt(norm2), x / math.sqrt(norm2), y / math.sqrt(norm2), z / math.sqrt(norm2)
    T[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    T[0, 1] = 2.0 * (x * y - w * z)
    T[0, 2] = 2.0 * (x * z + w * y)
    T[1, 0] = 2.0 * (x * y + w * z)
    T[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    T[1, 2] = 2.0 * (y * z - w * x)
    T[2, 0] = 2.0 * (x * z - w * y)
    T[2, 1] = 2.0 * (y * z + w * x)
    T[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@kernel("f8[:, ::1], f8[:, ::1], f8[::1], b1[::1]")
def rigid_fit(source: np.ndarray, target: np.ndarray, weights: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, float]:
    """Arun / Umeyama fit of the pairs ``use`` (N,) bool: 4x4 ``T`` with ``target ≈ R source + t``, and spread.

    numpy, with ``s, d, w = source[use], target[use], weights[use]``::

        ms, md = w @ s / w.sum(), w @ d / w.sum()
        U, _, Vt = svd(((s - ms) * w[:, None]).T @ d)          # cross-covariance H
        R = Vt.T @ diag(1, 1, det(Vt.T @ U.T)) @ U.T             # reflection: flip the weakest direction
        t = md - R @ ms
        spread = off_line_rms(weighted scatter of s about ms)     # m, 0 for a collinear source

    The weighted-centred source sums to zero, so the target needs no centring. ``R`` comes from
    :func:`best_rotation_into`.
    """
    n = source.shape[0]
    total = 0.0
    mean_s = np.zeros(3)
    mean_t = np.zeros(3)
    for i in range(n):
        if use[i]:
            w = weights[i]
            total += w
            for a in range(3):
                mean_s[a] += w * source[i, a]
                mean_t[a] += w * target[i, a]
    mean_s /= total
    mean_t /= total
    H = np.zeros((3, 3))  # cross-covariance (centred source x target)
    S = np.zeros((3, 3))  # scatter of the source (upper triangle)
    for i in range(n):
        if use[i]:
            w = weights[i]
            c0 = w * (source[i, 0] - mean_s[0])
            c1 = w * (source[i, 1] - mean_s[1])
            c2 = w * (source[i, 2] - mean_s[2])
            for b in range(3):
                H[0, b] += c0 * target[i, b]
                H[1, b] += c1 * target[i, b]
                H[2, b] += c2 * target[i, b]
            S[0, 0] += c0 * source[i, 0]
            S[1, 1] += c1 * source[i, 1]
            S[2, 2] += c2 * source[i, 2]
            S[0, 1] += c0 * source[i, 1]
            S[0, 2] += c0 * source[i, 2]
            S[1, 2] += c1 * source[i, 2]
    T = np.eye(4)
    best_rotation_into(T, H)
    for a in range(3):
        T[a, 3] = mean_t[a] - (T[a, 0] * mean_s[0] + T[a, 1] * mean_s[1] + T[a, 2] * mean_s[2])
    spread = off_line_rms(
        S[0, 0] / total, S[1, 1] / total, S[2, 2] / total, S[0, 1] / total, S[0, 2] / total, S[1, 2] / total
    )
    return T, spread


@kernel("f8[:, ::1], f8[:, ::1], f8[:, ::1]")
def pair_residuals(source: np.ndarray, target: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Distance (N,) between each target and its mapped source, m.

    numpy: ``norm(target - source @ T[:3, :3].T - T[:3, 3], axis=1)``.
    """
    n = source.shape[0]
    out = np.empty(n)
    for i in range(n):
        s0, s1, s2 = source[i, 0], source[i, 1], source[i, 2]
        total = 0.0
        for a in range(3):
            r = target[i, a] - (T[a, 0] * s0 + T[a, 1] * s1 + T[a, 2] * s2) - T[a, 3]
            total += r * r
        out[i] = math.sqrt(total)
    return out


@kernel("f8[::1], i8")
def _kth_smallest(values: np.ndarray, k: int) -> float:
    """The ``k``-th smallest entry (0-based) of ``values`` (reordered in place; quickselect).

    numpy: ``np.partition(values, k)[k]``.
    """
    low, high = 0, values.shape[0] - 1
    while low < high:
        pivot = values[(low + high) // 2]
        i, j = low, high
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i += 1
                j -= 1
        if k <= j:
            high = j
        elif k >= i:
            low = i
        else:
            break
    return values[k]


@kernel("f8[::1], b1[::1]")
def _masked_median(values: np.ndarray, use: np.ndarray) -> float:
    """numpy: ``np.median(values[use])`` (finite values, at least one used)."""
    selected = np.empty(values.shape[0])
    n = 0
    for i in range(values.shape[0]):
        if use[i]:
            selected[n] = values[i]
            n += 1
    selected = selected[:n]
    half = n // 2
    upper = _kth_smallest(selected, half)
    if n % 2:
        return upper
    lower = selected[0]  # after selection every entry below position half is <= upper
    for i in range(1, half):
        lower = max(lower, selected[i])
    return 0.5 * (lower + upper)


@kernel("f8[:, ::1], f8[:, ::1], f8[::1], f8[:, ::1], b1[::1], f8, f8, i8, f8")
def trimmed_fit(
    source: np.ndarray,
    target: np.ndarray,
    weights: np.ndarray,
    T: np.ndarray,
    allowed: np.ndarray,
    trim: float,
    floor: float,
    rounds: int,
    collinear_tolerance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Trimming rounds of :func:`~relpoint.estimators.relative_point.lsf.fit_transform` from fit ``T``.

    Each round keeps the pairs of ``allowed`` (N,) whose residual is at most
    ``max(trim * median(residual[allowed]), floor)`` and refits them with :func:`rigid_fit`; it stops
    when the kept set no longer changes, would leave fewer than three pairs, or a collinear source.
    Returns the final ``T`` and the kept pairs (``allowed`` itself when no round changed anything).
    """
    inliers = allowed
    for _ in range(rounds):
        residual = pair_residuals(source, target, T)
        bound = max(trim * _masked_median(residual, allowed), floor)
        keep = np.empty(residual.shape[0], np.bool_)
        kept = 0
        same = True
        for i in range(keep.shape[0]):
            keep[i] = allowed[i] and residual[i] <= bound
            kept += keep[i]
            same = same and keep[i] == inliers[i]
        if same or kept < 3:
            break
        T_kept, spread = rigid_fit(source, target, weights, keep)
        if spread <= collinear_tolerance:
            break
        T, inliers = T_kept, keep
    return T, inliers


# -- OVLQPQuadTree (section II-A): local point matching -------------------------------------------


@kernel("f8[:, ::1], i8[::1], f8[:, ::1], f8")
def nearest_two(
    reference: np.ndarray, order: np.ndarray, query: np.ndarray, bound: float
) -> tuple[np.ndarray, np.ndarray]:
    """The two nearest rows of ``reference`` (M, 3) within ``bound`` (m) of each row of ``query`` (N, 3).

    numpy: ``cKDTree(reference).query(query, k=2, distance_upper_bound=bound)``: rows ``j`` (N, 2)
    nearest first, ``M`` where there is none, and distances ``d`` (N, 2), ``inf`` there. ``order``
    is ``argsort(reference[:, 0])``: each query scans only the references within ``bound`` along x.
    """
    m, n = reference.shape[0], query.shape[0]
    xs = np.empty(m)
    for p in range(m):
        xs[p] = reference[order[p], 0]
    bound2 = bound * bound
    j = np.full((n, 2), m, np.int64)
    d = np.full((n, 2), np.inf)
    for i in range(n):
        qx, qy, qz = query[i, 0], query[i, 1], query[i, 2]
        low, high = 0, m  # first sorted reference with x >= qx - bound (binary search)
        while low < high:
            middle = (low + high) // 2
            if xs[middle] < qx - bound:
                low = middle + 1
            else:
                high = middle
        best1, best2 = np.inf, np.inf
        j1, j2 = m, m
        for p in range(low, m):
            if xs[p] > qx + bound:
                break
            r = order[p]
            dx, dy, dz = reference[r, 0] - qx, reference[r, 1] - qy, reference[r, 2] - qz
            d2 = dx * dx + dy * dy + dz * dz
            if d2 >= bound2:
                continue
            if d2 < best1 or (d2 == best1 and r < j1):
                best2, j2 = best1, j1
                best1, j1 = d2, r
            elif d2 < best2 or (d2 == best2 and r < j2):
                best2, j2 = d2, r
        if j1 < m:
            j[i, 0], d[i, 0] = j1, math.sqrt(best1)
        if j2 < m:
            j[i, 1], d[i, 1] = j2, math.sqrt(best2)
    return j, d


@kernel("i8[:, ::1], f8[:, ::1], i8")
def claim_one_to_one(j: np.ndarray, d: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one assignment of queries to their nearest (then second-nearest) free reference.

    ``j``, ``d`` (N, K) are each query's K nearest references and distances (``m``: none). Column by
    column, every still unmatched query claims its reference in that column unless an earlier
    column took it; of several claims on one reference the closest wins (ties: the lower query row).
    numpy, per column: ``order = lexsort((dist, cand))`` over the pending claims, the first of
    each ``cand`` wins. Returns the matched reference row per query (-1 if none) and its distance.
    """
    n, k = j.shape
    index = np.full(n, -1, np.int64)
    distance = np.full(n, np.inf)
    taken = np.zeros(m, np.bool_)
    winner = np.full(m, -1, np.int64)
    for column in range(k):
        for i in range(n):
            c = j[i, column]
            if index[i] >= 0 or c >= m or taken[c]:
                continue
            w = winner[c]
            if w < 0 or d[i, column] < d[w, column]:
                winner[c] = i
        for i in range(n):
            c = j[i, column]
            if c < m and winner[c] == i:
                index[i] = c
                distance[i] = d[i, column]
                taken[c] = True
                winner[c] = -1
    return index, distance


@kernel("f8[:, ::1], f8[:, ::1], f8[::1]")
def mutual_nearest(reference: np.ndarray, query: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Row of ``reference`` (R, 3) each query (Q, 3) matches as mutual nearest neighbours within ``bounds`` (R,).

    numpy, with ``distance = norm(query[:, None] - reference[None], axis=2)`` (Q, R)::

        nearest_reference, nearest_query = distance.argmin(1), distance.argmin(0)
        mutual = (nearest_query[nearest_reference] == arange(Q))
                 & (distance[arange(Q), nearest_reference] <= bounds[nearest_reference])
        where(mutual, nearest_reference, -1)

    (ties go to the lower row, as ``argmin``).
    """
    q_count, r_count = query.shape[0], reference.shape[0]
    distance = np.empty((q_count, r_count))
    for q in range(q_count):
        for r in range(r_count):
            dx = query[q, 0] - reference[r, 0]
            dy = query[q, 1] - reference[r, 1]
            dz = query[q, 2] - reference[r, 2]
            distance[q, r] = math.sqrt(dx * dx + dy * dy + dz * dz)
    nearest_query = np.empty(r_count, np.int64)
    for r in range(r_count):
        nearest_query[r] = 0
        for q in range(1, q_count):
            if distance[q, r] < distance[nearest_query[r], r]:
                nearest_query[r] = q
    index = np.empty(q_count, np.int64)
    for q in range(q_count):
        index[q] = -1
        best = 0
        for r in range(1, r_count):
            if distance[q, r] < distance[q, best]:
                best = r
        if nearest_query[best] == q and distance[q, best] <= bounds[best]:
            index[q] = best
    return index


@kernel("f8[:, ::1], f8[:, ::1], i8[::1]")
def transform_by_age(T_curr_prev: np.ndarray, points: np.ndarray, age: np.ndarray) -> np.ndarray:
    """Points (N, 3) carried ``age`` (N,) steps (1 or more) of the motion ``T_curr_prev`` (4, 4).

    numpy: ``P = stack([T^1, T^2, ...])[age - 1]; einsum("nij,nj->ni", P[:, :3, :3], points) + P[:, :3, 3]``.
    """
    n = points.shape[0]
    steps = 1
    for i in range(n):
        steps = max(steps, age[i])
    powers = np.empty((steps, 4, 4))
    for a in range(4):
        for b in range(4):
            powers[0, a, b] = T_curr_prev[a, b]
    for s in range(1, steps):  # T^(s+1) = T @ T^s
        for a in range(4):
            for b in range(4):
                total = 0.0
                for c in range(4):
                    total += T_curr_prev[a, c] * powers[s - 1, c, b]
                powers[s, a, b] = total
    out = np.empty((n, 3))
    for i in range(n):
        s = age[i] - 1
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        for a in range(3):
            out[i, a] = powers[s, a, 0] * x + powers[s, a, 1] * y + powers[s, a, 2] * z + powers[s, a, 3]
    return out


# -- RltGroup (section II-B): combination of the groups' placements --------------------------------


@kernel("f8[:, ::1], f8[::1], i8[::1]")
def gather_positions(pos_sum: np.ndarray, pos_weight: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Least-squares global positions (N, 3) of points ``ids`` (N,); NaN rows where unmapped.

    numpy: ``pos_sum[ids] / maximum(pos_weight[ids], 1e-300)[:, None]``, NaN where ``pos_weight[ids] <= 0``.
    """
    n = ids.shape[0]
    out = np.empty((n, 3))
    for r in range(n):
        i = ids[r]
        w = pos_weight[i]
        if w <= 0.0:
            out[r] = np.nan
        else:
            w = max(w, 1e-300)
            for a in range(3):
                out[r, a] = pos_sum[i, a] / w
    return out


@kernel("f8[:, ::1], f8[::1], f8[::1], i8[::1]")
def gather_spread(pos_sum: np.ndarray, pos_weight: np.ndarray, pos_sq: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """RMS disagreement (N,) between the global positions the groups of points ``ids`` give them (m).

    numpy, with ``w = maximum(pos_weight[ids], 1e-12)`` and ``m = pos_sum[ids] / w[:, None]``:
    ``sqrt(maximum(pos_sq[ids] / w - sum(m**2, axis=1), 0))``.
    """
    n = ids.shape[0]
    out = np.empty(n)
    for r in range(n):
        i = ids[r]
        w = max(pos_weight[i], 1e-12)
        m0, m1, m2 = pos_sum[i, 0] / w, pos_sum[i, 1] / w, pos_sum[i, 2] / w
        variance = pos_sq[i] / w - (m0 * m0 + m1 * m1 + m2 * m2)
        out[r] = math.sqrt(max(variance, 0.0))
    return out


@kernel("f8[:, ::1], f8[::1], f8[::1], i8[::1], f8[:, ::1], f8, f8[:, ::1], f8")
def replace_contribution(
    pos_sum: np.ndarray,
    pos_weight: np.ndarray,
    pos_sq: np.ndarray,
    members: np.ndarray,
    old_placed: np.ndarray,
    old_weight: float,
    new_placed: np.ndarray,
    new_weight: float,
) -> None:
    """Swap one group's contribution to its members' accumulators, in place.

    numpy, for distinct ``members`` (M,), placements (M, 3) and weights (skipped when 0)::

        pos_sum[members] += new_weight * new_placed - old_weight * old_placed     (each term separately)
        pos_weight[members] += new_weight - old_weight
        pos_sq[members] += new_weight * sum(new_placed**2, 1) - old_weight * sum(old_placed**2, 1)

    then points left with ``pos_weight < 1e-9`` (round-off ghosts) are zeroed.
    """
    for r in range(members.shape[0]):
        i = members[r]
        if old_weight > 0.0:
            p0, p1, p2 = old_placed[r, 0], old_placed[r, 1], old_placed[r, 2]
            pos_sum[i, 0] -= old_weight * p0
            pos_sum[i, 1] -= old_weight * p1
            pos_sum[i, 2] -= old_weight * p2
            pos_weight[i] -= old_weight
            pos_sq[i] -= old_weight * (p0 * p0 + p1 * p1 + p2 * p2)
        if new_weight > 0.0:
            p0, p1, p2 = new_placed[r, 0], new_placed[r, 1], new_placed[r, 2]
            pos_sum[i, 0] += new_weight * p0
            pos_sum[i, 1] += new_weight * p1
            pos_sum[i, 2] += new_weight * p2
            pos_weight[i] += new_weight
            pos_sq[i] += new_weight * (p0 * p0 + p1 * p1 + p2 * p2)
        if pos_weight[i] < 1e-9:
            pos_weight[i] = 0.0
            pos_sum[i] = 0.0
            pos_sq[i] = 0.0


# -- RltGroup (section II-B): basis frames and relative maps ----------------------------------------


@kernel("f8[:, :, ::1], i8, i8, i8, f8")
def basis_coordinates(
    observations: np.ndarray, i0: int, i1: int, i2: int, min_spread: float
) -> tuple[np.ndarray, np.ndarray]:
    """Members' coordinates (M, L, 3) in the basis frame of rows ``i0, i1, i2`` in each of L iterations.

    numpy, with ``b0, b1, b2 = observations[[i0, i1, i2]]`` and
    :func:`~relpoint.estimators.relative_point.groups.basis_rotation`::

        R, valid = basis_rotation(b0, b1, b2, min_spread)                     # (L, 3, 3), (L,)
        relative = matmul((observations - b0).transpose(1, 0, 2), R).transpose(1, 0, 2)
    """
    m, length = observations.shape[0], observations.shape[1]
    relative = np.empty((m, length, 3))
    valid = np.empty(length, np.bool_)
    for t in range(length):
        o0, o1, o2 = observations[i0, t], observations[i1, t], observations[i2, t]
        x0, x1, x2 = o0[0] - o1[0], o0[1] - o1[1], o0[2] - o1[2]
        x_norm = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        scale = max(x_norm, 1e-12)
        x0, x1, x2 = x0 / scale, x1 / scale, x2 / scale
        v0, v1, v2 = o2[0] - o0[0], o2[1] - o0[1], o2[2] - o0[2]
        along = v0 * x0 + v1 * x1 + v2 * x2
        z0, z1, z2 = v0 - along * x0, v1 - along * x1, v2 - along * x2
        z_norm = math.sqrt(z0 * z0 + z1 * z1 + z2 * z2)
        scale = max(z_norm, 1e-12)
        z0, z1, z2 = z0 / scale, z1 / scale, z2 / scale
        y0, y1, y2 = z1 * x2 - z2 * x1, z2 * x0 - z0 * x2, z0 * x1 - z1 * x0  # y = z x x
        valid[t] = x_norm >= min_spread and z_norm >= min_spread
        for r in range(m):
            d0 = observations[r, t, 0] - o0[0]
            d1 = observations[r, t, 1] - o0[1]
            d2 = observations[r, t, 2] - o0[2]
            relative[r, t, 0] = d0 * x0 + d1 * x1 + d2 * x2
            relative[r, t, 1] = d0 * y0 + d1 * y1 + d2 * y2
            relative[r, t, 2] = d0 * z0 + d1 * z1 + d2 * z2
    return relative, valid


@kernel("f8[:, ::1], i8")
def _row_mean(points: np.ndarray, m: int) -> tuple[float, float, float]:
    """Mean of the first ``m`` rows of ``points`` (N, 3). numpy: ``points[:m].mean(axis=0)``."""
    c0 = c1 = c2 = 0.0
    for r in range(m):
        c0 += points[r, 0]
        c1 += points[r, 1]
        c2 += points[r, 2]
    return c0 / m, c1 / m, c2 / m


@kernel("f8[:, ::1], f8")
def spread_basis(points: np.ndarray, min_spread: float) -> tuple[int, int, int]:
    """Rows of three well-spread, non-collinear points of ``points`` (M, 3); ``(-1, -1, -1)`` if none.

    numpy: ``i0 = argmax(|p - centroid|)``, ``i1 = argmax(|p - p[i0]|)``, ``i2 = argmax`` of the
    distance off the line through both (squared); none when ``|p[i1] - p[i0]|`` or that distance
    is below ``min_spread``. Ties go to the first row, as ``argmax``.
    """
    m = points.shape[0]
    if m < 3:
        return -1, -1, -1
    c0, c1, c2 = _row_mean(points, m)
    i0, best = 0, -1.0
    for r in range(m):
        d0, d1, d2 = points[r, 0] - c0, points[r, 1] - c1, points[r, 2] - c2
        d = d0 * d0 + d1 * d1 + d2 * d2
        if d > best:
            i0, best = r, d
    squared = np.empty(m)
    i1, best = 0, -1.0
    for r in range(m):
        d0, d1, d2 = points[r, 0] - points[i0, 0], points[r, 1] - points[i0, 1], points[r, 2] - points[i0, 2]
        squared[r] = d0 * d0 + d1 * d1 + d2 * d2
        if squared[r] > best:
            i1, best = r, squared[r]
    length = math.sqrt(best)
    if length < min_spread:
        return -1, -1, -1
    u0 = (points[i1, 0] - points[i0, 0]) / length
    u1 = (points[i1, 1] - points[i0, 1]) / length
    u2 = (points[i1, 2] - points[i0, 2]) / length
    i2, best = 0, -np.inf
    for r in range(m):
        along = (points[r, 0] - points[i0, 0]) * u0 + (points[r, 1] - points[i0, 1]) * u1
        along += (points[r, 2] - points[i0, 2]) * u2
        off_line = squared[r] - along * along
        if off_line > best:
            i2, best = r, off_line
    if best < min_spread * min_spread:
        return -1, -1, -1
    return i0, i1, i2


# -- RltMapper (section II-C): member selection of a new group ------------------------------------


@kernel("b1[:, ::1], b1[::1], i8[::1], i8, i8")
def interval_members(
    presence: np.ndarray, grouped: np.ndarray, order: np.ndarray, creation: int, seeds: int
) -> tuple[np.ndarray, np.ndarray]:
    """The interval x count heuristic of :func:`~relpoint.estimators.relative_point.grouping.select_members`.

    ``presence`` (N, L) bool, ``grouped`` (N,) bool, ``order`` the candidates by coverage
    (``argsort(-presence.sum(1), kind="stable")``). The creation row and the first ``seeds`` grouped
    candidates sharing an iteration with it seed the group; the other candidates are added in that
    order while ``interval length x member count`` grows (numpy: ``logical_and.accumulate`` over
    their rows, stopping at the first score not above the previous one). Returns the chosen rows
    (creation first) and the interval mask (L,); no rows when fewer than ``seeds`` grouped
    candidates overlap the creation row or the seeds share no iteration.
    """
    n, length = presence.shape
    rows = np.empty(n, np.int64)
    rows[0] = creation
    chosen = 1
    for r in order:
        if chosen > seeds:
            break
        if r == creation or not grouped[r]:
            continue
        for t in range(length):
            if presence[r, t] and presence[creation, t]:
                rows[chosen] = r
                chosen += 1
                break
    interval = np.empty(length, np.bool_)
    covered = 0
    for t in range(length):
        interval[t] = True
        for s in range(chosen):
            interval[t] = interval[t] and presence[rows[s], t]
        covered += interval[t]
    if chosen <= seeds or covered == 0:
        return rows[:0].copy(), interval
    is_seed = np.zeros(n, np.bool_)
    for s in range(chosen):
        is_seed[rows[s]] = True
    score = covered * chosen
    for r in order:
        if is_seed[r]:
            continue
        covered = 0
        for t in range(length):
            covered += interval[t] and presence[r, t]
        if covered * (chosen + 1) <= score:
            break
        for t in range(length):
            interval[t] = interval[t] and presence[r, t]
        rows[chosen] = r
        chosen += 1
        score = covered * chosen
    return rows[:chosen].copy(), interval


# -- RltPoint / RltInterval (section II-A): reading the observation rings --------------------------


@kernel("f8[:, :, ::1], i8[:, ::1], i8[::1], i8[::1]")
def ring_observations(
    obs: np.ndarray, obs_iter: np.ndarray, ids: np.ndarray, iterations: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Observations (N, L, 3) of points ``ids`` (N,) at ``iterations`` (L,) and their validity (N, L).

    numpy, with ``slots = iterations % R`` for rings of R slots::

        obs[ids[:, None], slots[None, :]],
        (obs_iter[ids[:, None], slots[None, :]] == iterations[None, :]) & (iterations[None, :] >= 0)

    (An unwritten slot holds -1, so an iteration before the first is never observed.)
    """
    ring = obs_iter.shape[1]
    n, length = ids.shape[0], iterations.shape[0]
    xyz = np.empty((n, length, 3))
    valid = np.empty((n, length), np.bool_)
    for r in range(n):
        i = ids[r]
        for t in range(length):
            slot = iterations[t] % ring
            xyz[r, t, 0] = obs[i, slot, 0]
            xyz[r, t, 1] = obs[i, slot, 1]
            xyz[r, t, 2] = obs[i, slot, 2]
            valid[r, t] = iterations[t] >= 0 and obs_iter[i, slot] == iterations[t]
    return xyz, valid


@kernel("i8[:, ::1], i8[::1], i8, i8")
def ring_presence(obs_iter: np.ndarray, ids: np.ndarray, first: int, last: int) -> np.ndarray:
    """Whether points ``ids`` (N,) were observed in each iteration of ``[first, last]`` (N, last - first + 1).

    numpy: ``(obs_iter[ids[:, None], slots[None, :]] == iterations[None, :]) & (iterations[None, :] >= 0)``
    with ``iterations = arange(first, last + 1)`` and ``slots = iterations % R``.
    """
    ring = obs_iter.shape[1]
    n, length = ids.shape[0], last - first + 1
    present = np.empty((n, length), np.bool_)
    for r in range(n):
        i = ids[r]
        for t in range(length):
            present[r, t] = first + t >= 0 and obs_iter[i, (first + t) % ring] == first + t
    return present


# -- dynamic detection (section II-C): the periodic sweep against verified points -----------------


@kernel("f8[:, :, ::1], b1[:, ::1], i8[::1], i8, i8")
def reference_deviations(
    tracks: np.ndarray, valid: np.ndarray, references: np.ndarray, min_common: int, block: int
) -> np.ndarray:
    """Deviation (N, R) of the distance of every track (N, L, 3) to each reference track, NaN if not compared.

    numpy, with ``both = valid[:, None] & valid[references][None]`` (N, R, L) and
    ``distance = where(both, norm(tracks[:, None] - tracks[references][None], axis=3), 0)``::

        usable = (both.sum(2) >= min_common) & (arange(N)[:, None] != references[None, :])
        # block > 1: distances averaged over blocks of ``block`` iterations counted from the
        # latest (zero-padded at the start); blocks with under two common observations dropped:
        #   sums, counts = block sums of distance and both;  both = counts >= 2
        #   distance = where(both, sums / counts, 0);  usable &= both.sum(2) >= 3
        count = both.sum(2);  mean = distance.sum(2) / count
        variance = where(both, (distance - mean[..., None]) ** 2, 0).sum(2) / (count - 1)
        where(usable, sqrt(variance), nan)
    """
    n, length = valid.shape
    n_refs = references.shape[0]
    blocks = (length + block - 1) // block
    pad = blocks * block - length
    deviation = np.empty((n, n_refs))
    values = np.empty(blocks)
    for i in range(n):
        for j in range(n_refs):
            deviation[i, j] = np.nan
            ref = references[j]
            if ref == i:
                continue
            common = 0
            used = 0
            for b in range(blocks):
                total = 0.0
                count = 0
                for t in range(max(b * block - pad, 0), (b + 1) * block - pad):
                    if valid[i, t] and valid[ref, t]:
                        dx = tracks[i, t, 0] - tracks[ref, t, 0]
                        dy = tracks[i, t, 1] - tracks[ref, t, 1]
                        dz = tracks[i, t, 2] - tracks[ref, t, 2]
                        total += math.sqrt(dx * dx + dy * dy + dz * dz)
                        count += 1
                common += count
                if count >= (2 if block > 1 else 1):
                    values[used] = total / count
                    used += 1
            if common < min_common or (block > 1 and used < 3) or used < 2:
                continue
            mean = 0.0
            for u in range(used):
                mean += values[u]
            mean /= used
            squares = 0.0
            for u in range(used):
                squares += (values[u] - mean) ** 2
            deviation[i, j] = math.sqrt(squares / (used - 1))
    return deviation


@kernel("f8[:, :, ::1], b1[:, ::1], f8[:, :, ::1], i8")
def block_mean_scatter(tracks: np.ndarray, valid: np.ndarray, poses: np.ndarray, block: int) -> np.ndarray:
    """RMS scatter (N,) of each track's block-mean world position (NaN under three usable blocks).

    numpy, with ``world = einsum("lab,nlb->nla", poses[:, :3, :3], tracks) + poses[None, :, :3, 3]``
    and blocks of ``block`` iterations counted from the latest (iterations before the first full
    block ignored)::

        sums, counts = block sums of where(valid[..., None], world, 0) and of valid   # (N, B, 3), (N, B)
        usable = counts >= 2;  means = sums / counts[..., None];  used = usable.sum(1)
        centre = where(usable[..., None], means, 0).sum(1) / used[:, None]
        scatter = where(usable[..., None], (means - centre[:, None]) ** 2, 0).sum((1, 2))
        where(used >= 3, sqrt(scatter / (used - 1)), nan)
    """
    n, length = valid.shape
    blocks = length // block
    start = length - blocks * block
    scatter = np.empty(n)
    means = np.empty((blocks, 3))
    for i in range(n):
        scatter[i] = np.nan
        used = 0
        for b in range(blocks):
            sx = sy = sz = 0.0
            count = 0
            for t in range(start + b * block, start + (b + 1) * block):
                if valid[i, t]:
                    x, y, z = tracks[i, t, 0], tracks[i, t, 1], tracks[i, t, 2]
                    sx += poses[t, 0, 0] * x + poses[t, 0, 1] * y + poses[t, 0, 2] * z + poses[t, 0, 3]
                    sy += poses[t, 1, 0] * x + poses[t, 1, 1] * y + poses[t, 1, 2] * z + poses[t, 1, 3]
                    sz += poses[t, 2, 0] * x + poses[t, 2, 1] * y + poses[t, 2, 2] * z + poses[t, 2, 3]
                    count += 1
            if count >= 2:
                means[used, 0], means[used, 1], means[used, 2] = sx / count, sy / count, sz / count
                used += 1
        if used < 3:
            continue
        cx, cy, cz = _row_mean(means, used)
        total = 0.0
        for u in range(used):
            total += (means[u, 0] - cx) ** 2 + (means[u, 1] - cy) ** 2 + (means[u, 2] - cz) ** 2
        scatter[i] = math.sqrt(total / (used - 1))
    return scatter


# -- Local matching of one iteration, whole (section II-A) ------------------------------------------


@kernel("f8[::1]")
def _stable_argsort(values: np.ndarray) -> np.ndarray:
    """numpy: ``argsort(values, kind="stable")`` (bottom-up merge sort; NaN-free input)."""
    n = values.shape[0]
    order = np.arange(n)
    spare = np.empty(n, np.int64)
    width = 1
    while width < n:
        for low in range(0, n, 2 * width):
            middle, high = min(low + width, n), min(low + 2 * width, n)
            i, j = low, middle
            for out in range(low, high):
                if i < middle and (j >= high or values[order[i]] <= values[order[j]]):
                    spare[out] = order[i]
                    i += 1
                else:
                    spare[out] = order[j]
                    j += 1
        order, spare = spare, order
        width *= 2
    return order


@kernel("f8[:, ::1], f8[:, ::1], f8")
def _nearest_one_to_one(reference: np.ndarray, query: np.ndarray, bound: float) -> np.ndarray:
    """Row of ``reference`` (M, 3) each query (N, 3) takes one-to-one within ``bound`` (m), -1 if none.

    numpy: ``claim_one_to_one(*nearest_two(reference, argsort(reference[:, 0]), query, bound), M)[0]``
    (:func:`~relpoint.estimators.relative_point.registration.match_nearest`; ``nearest_two`` breaks
    distance ties by row, so the order among equal x does not matter).
    """
    m = reference.shape[0]
    xs = np.empty(m)
    for r in range(m):
        xs[r] = reference[r, 0]
    j, d = nearest_two(reference, _stable_argsort(xs), query, bound)
    return claim_one_to_one(j, d, m)[0]


@kernel("f8[:, ::1], f8[:, ::1], i8[::1], i8[::1], f8")
def _motion_from_pairs(
    previous: np.ndarray, current: np.ndarray, row: np.ndarray, age: np.ndarray, collinear_tolerance: float
) -> tuple[np.ndarray, bool]:
    """Inter-iteration motion ``T_curr_prev`` (4, 4) from the pairs matched to points seen one iteration ago.

    ``previous`` (R, 3) are the references' latest observations, ``current`` (N, 3) this
    iteration's points, ``row`` (N,) the reference each point matched (-1 none), ``age`` (R,)
    iterations since each reference was seen. numpy, with ``pairs = flatnonzero((row >= 0) & (age[row] == 1))``::

        fit_transform(previous[row[pairs]], current[pairs], trim=0, collinear_tolerance=collinear_tolerance)

    (:meth:`~relpoint.estimators.relative_point.registration.MotionModel.update`): the plain fit, and
    False where there are fewer than three pairs or their sources are collinear.
    """
    count = 0
    for q in range(row.shape[0]):
        if row[q] >= 0 and age[row[q]] == 1:
            count += 1
    T = np.eye(4)
    if count < 3:
        return T, False
    source = np.empty((count, 3))
    target = np.empty((count, 3))
    p = 0
    for q in range(row.shape[0]):
        if row[q] >= 0 and age[row[q]] == 1:
            for a in range(3):
                source[p, a] = previous[row[q], a]
                target[p, a] = current[q, a]
            p += 1
    T, spread = rigid_fit(source, target, np.ones(count), np.ones(count, np.bool_))
    return T, spread > collinear_tolerance


@kernel("f8[:, ::1], f8[:, ::1], f8[:, ::1]")
def _prediction_shift(T_new: np.ndarray, T_before: np.ndarray, reference: np.ndarray) -> float:
    """Largest change (m) of the predicted references (R, 3) when the motion goes from ``T_before`` to ``T_new``.

    numpy: with ``D = T_new @ rigid_inverse(T_before)``,
    ``norm(D[:3, 3]) + arccos(clip((trace(D[:3, :3]) - 1) / 2, -1, 1)) * sqrt(max(sum(reference**2, 1)))``:
    translation plus angle times range.
    """
    inverse_t = np.empty(3)
    for a in range(3):
        inverse_t[a] = -(
            T_before[0, a] * T_before[0, 3] + T_before[1, a] * T_before[1, 3] + T_before[2, a] * T_before[2, 3]
        )
    trace = 0.0
    squared = 0.0
    for a in range(3):
        trace += T_new[a, 0] * T_before[a, 0] + T_new[a, 1] * T_before[a, 1] + T_new[a, 2] * T_before[a, 2]
        moved = T_new[a, 0] * inverse_t[0] + T_new[a, 1] * inverse_t[1] + T_new[a, 2] * inverse_t[2] + T_new[a, 3]
        squared += moved * moved
    angle = math.acos(min(1.0, max(-1.0, (trace - 1.0) / 2.0)))
    reach2 = 0.0
    for r in range(reference.shape[0]):
        x, y, z = reference[r, 0], reference[r, 1], reference[r, 2]
        reach2 = max(reach2, x * x + y * y + z * z)
    return math.sqrt(squared) + angle * math.sqrt(reach2)


@kernel("f8[:, ::1], f8[:, ::1], i8[::1], f8, f8")
def _match_far(
    predicted: np.ndarray, points: np.ndarray, row: np.ndarray, match_bound: float, match_angle: float
) -> int:
    """Second round of local matching, in place on ``row`` (N,): returns the number of new pairs.

    The points nobody matched (``row == -1``) and the references (R, 3, predicted into the current
    frame) no point took are paired as mutual nearest neighbours within
    ``match_bound + match_angle * norm(predicted)`` (:func:`mutual_nearest`). numpy::

        free_points = flatnonzero(row == -1);  free_refs = setdiff1d(arange(R), row)
        bounds = match_bound + match_angle * sqrt(einsum("ij,ij->i", predicted[free_refs], predicted[free_refs]))
        found = mutual_nearest(predicted[free_refs], points[free_points], bounds)
        row[free_points[found >= 0]] = free_refs[found[found >= 0]]
    """
    n_points, n_refs = row.shape[0], predicted.shape[0]
    taken = np.zeros(n_refs, np.bool_)
    free_count, taken_count = 0, 0
    for q in range(n_points):
        if row[q] < 0:
            free_count += 1
        elif not taken[row[q]]:
            taken[row[q]] = True
            taken_count += 1
    free_points = np.empty(free_count, np.int64)
    f = 0
    for q in range(n_points):
        if row[q] < 0:
            free_points[f] = q
            f += 1
    free_refs = np.empty(n_refs - taken_count, np.int64)
    f = 0
    for r in range(n_refs):
        if not taken[r]:
            free_refs[f] = r
            f += 1
    if free_points.shape[0] == 0 or free_refs.shape[0] == 0:
        return 0
    references = np.empty((free_refs.shape[0], 3))
    bounds = np.empty(free_refs.shape[0])
    for f in range(free_refs.shape[0]):
        x, y, z = predicted[free_refs[f], 0], predicted[free_refs[f], 1], predicted[free_refs[f], 2]
        references[f, 0], references[f, 1], references[f, 2] = x, y, z
        bounds[f] = match_bound + match_angle * math.sqrt(x * x + y * y + z * z)
    queries = np.empty((free_points.shape[0], 3))
    for f in range(free_points.shape[0]):
        for a in range(3):
            queries[f, a] = points[free_points[f], a]
    found = mutual_nearest(references, queries, bounds)
    matched = 0
    for f in range(found.shape[0]):
        if found[f] >= 0:
            row[free_points[f]] = free_refs[found[f]]
            matched += 1
    return matched


@kernel("f8[:, ::1], i8[::1], f8[:, ::1], f8[:, ::1], f8, f8, b1, f8")
def match_recent(
    reference: np.ndarray,
    age: np.ndarray,
    points: np.ndarray,
    T_curr_prev: np.ndarray,
    match_bound: float,
    match_angle: float,
    predict_motion: bool,
    collinear_tolerance: float,
) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """Local matching of one iteration's points (N, 3) against the recent points' latest observations.

    ``reference`` (R, 3) are those observations (each in the sensor frame of its iteration), ``age``
    (R,) iterations since each, ``T_curr_prev`` (4, 4) the motion between the last two iterations.
    Returns ``row`` (N,), the reference each point matched (-1 none), the refreshed motion (4, 4),
    whether this iteration's pairs measured it, and the number of pairs the second round added.
    numpy, as :meth:`~relpoint.estimators.relative_point.phases.localisation.Localisation._register`
    did it step by step::

        predicted = transform_by_age(T_curr_prev, reference, age) if predict_motion else reference
        row = match_nearest(predicted, points, match_bound)[0]
        T, measured = _motion_from_pairs(reference, points, row, age)      # T_curr_prev if not measured
        if predict_motion and measured and _prediction_shift(T, T_curr_prev, reference) > match_bound / 2:
            predicted = transform_by_age(T, reference, age)                    # a turn began: match again
            row = match_nearest(predicted, points, match_bound)[0]
        if predict_motion and match_angle > 0 and (far := _match_far(predicted, points, row, ...)):
            T, measured = _motion_from_pairs(...) if measured again else (T, measured)
    """
    predicted = transform_by_age(T_curr_prev, reference, age) if predict_motion else reference
    row = _nearest_one_to_one(predicted, points, match_bound)
    T, measured = _motion_from_pairs(reference, points, row, age, collinear_tolerance)
    if not measured:
        T = T_curr_prev.copy()
    if predict_motion and measured and _prediction_shift(T, T_curr_prev, reference) > 0.5 * match_bound:
        predicted = transform_by_age(T, reference, age)
        row = _nearest_one_to_one(predicted, points, match_bound)
    far = 0
    if predict_motion and match_angle > 0:
        far = _match_far(predicted, points, row, match_bound, match_angle)
        if far > 0:
            T_far, measured_far = _motion_from_pairs(reference, points, row, age, collinear_tolerance)
            if measured_far:
                T, measured = T_far, True
    return row, T, measured, far


# -- RltGroup (section II-B): a group's anchors for its fit into the world ---------------------------


@kernel("f8[:, ::1], f8[::1], f8[::1], i8")
def _point_spread(pos_sum: np.ndarray, pos_weight: np.ndarray, pos_sq: np.ndarray, i: int) -> float:
    """RMS disagreement (m) between the global positions point ``i``'s groups give it: :func:`gather_spread` of one point."""
    w = max(pos_weight[i], 1e-12)
    m0, m1, m2 = pos_sum[i, 0] / w, pos_sum[i, 1] / w, pos_sum[i, 2] / w
    return math.sqrt(max(pos_sq[i] / w - (m0 * m0 + m1 * m1 + m2 * m2), 0.0))


@kernel("f8[:, ::1], f8[::1], f8[::1], b1[::1], i8[::1], i8[::1], f8[:, ::1], f8[:, ::1], f8, b1, f8, f8")
def group_anchors(
    pos_sum: np.ndarray,
    pos_weight: np.ndarray,
    pos_sq: np.ndarray,
    dynamic: np.ndarray,
    verified: np.ndarray,
    members: np.ndarray,
    relative: np.ndarray,
    placed: np.ndarray,
    own_weight: float,
    weighted: bool,
    spread_floor_squared: float,
    unverified_weight: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs a group's fit into ``world`` uses: its static members that other groups placed.

    ``members`` (M,) are the group's points, ``relative`` (M, 3) their relative map (basis frame,
    m), ``placed`` (M, 3) the group's own contribution with weight ``own_weight`` (0: none yet, and
    ``placed`` is not read). Returns the anchors' relative positions (A, 3), their global positions
    without the group's own contribution (A, 3, ``world``) and their weights (A,). numpy::

        other = pos_weight[members] - own_weight
        anchors = ~dynamic[members] & (other > 1e-9)
        own = own_weight * placed[anchors] if own_weight > 0 else 0.0
        target = (pos_sum[members[anchors]] - own) / other[anchors, None]
        weights = other[anchors] / (gather_spread(..., members[anchors]) ** 2 + spread_floor_squared)
        weights *= where(verified[members[anchors]] >= 0, 1.0, unverified_weight)   # if weighted, else ones

    Inverse-variance weights: an anchor's global position is as good as the iterations averaged
    into it and as bad as its groups disagree about it.
    """
    m = members.shape[0]
    count = 0
    for r in range(m):
        i = members[r]
        if not dynamic[i] and pos_weight[i] - own_weight > 1e-9:
            count += 1
    source = np.empty((count, 3))
    target = np.empty((count, 3))
    weights = np.ones(count)
    a = 0
    for r in range(m):
        i = members[r]
        other = pos_weight[i] - own_weight
        if dynamic[i] or not other > 1e-9:
            continue
        for c in range(3):
            source[a, c] = relative[r, c]
            own = own_weight * placed[r, c] if own_weight > 0.0 else 0.0
            target[a, c] = (pos_sum[i, c] - own) / other
        if weighted:
            spread = _point_spread(pos_sum, pos_weight, pos_sq, i)
            weights[a] = other / (spread * spread + spread_floor_squared)
            weights[a] *= 1.0 if verified[i] >= 0 else unverified_weight
        a += 1
    return source, target, weights


@kernel("f8[:, ::1], f8[::1], f8[::1], i8[::1], i8[::1], f8, f8")
def pose_anchors(
    pos_sum: np.ndarray,
    pos_weight: np.ndarray,
    pos_sq: np.ndarray,
    verified: np.ndarray,
    ids: np.ndarray,
    spread_floor_squared: float,
    unverified_weight: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Global positions (N, 3, ``world``, m) of mapped points ``ids`` (N,) and their weights (N,) in the pose fit.

    numpy::

        positions = gather_positions(pos_sum, pos_weight, ids)
        weights = 1.0 / (gather_spread(pos_sum, pos_weight, pos_sq, ids) ** 2 + spread_floor_squared)
        weights *= where(verified[ids] >= 0, 1.0, unverified_weight)

    Points whose groups disagree about their position (slow movers) and points not yet verified
    static count for less.
    """
    n = ids.shape[0]
    positions = gather_positions(pos_sum, pos_weight, ids)
    weights = np.empty(n)
    for r in range(n):
        i = ids[r]
        spread = _point_spread(pos_sum, pos_weight, pos_sq, i)
        weights[r] = 1.0 / (spread * spread + spread_floor_squared)
        weights[r] *= 1.0 if verified[i] >= 0 else unverified_weight
    return positions, weights


# -- RltLSF (section II-B): the whole fit but the consensus ----------------------------------------

FIT_DEGENERATE = 0
"""Outcome of :func:`robust_fit`: fewer than three pairs or a collinear source, no fit."""
FIT_DONE = 1
"""Outcome of :func:`robust_fit`: the fit, trimmed."""
FIT_WANTS_CONSENSUS = 2
"""Outcome of :func:`robust_fit`: enough pairs lie beyond the consensus bound that the caller re-seeds the fit."""


@kernel("f8[:, ::1], f8[:, ::1], f8[::1], f8, f8, f8, i8, f8, f8")
def robust_fit(
    source: np.ndarray,
    target: np.ndarray,
    weights: np.ndarray,
    trim: float,
    floor: float,
    collinear_tolerance: float,
    rounds: int,
    consensus: float,
    consensus_share: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`~relpoint.estimators.relative_point.lsf.fit_transform` up to its consensus step: ``T`` (4, 4), inliers (N,), outcome.

    numpy, for N pairs ``source`` -> ``target`` (N, 3) with ``weights`` (N,)::

        if N < 3: FIT_DEGENERATE
        T, spread = rigid_fit(source, target, weights, ones(N, bool))
        if spread <= collinear_tolerance: FIT_DEGENERATE
        if consensus > 0 and N > 4 and count_nonzero(pair_residuals(source, target, T) > consensus)
                >= max(2, consensus_share * N): FIT_WANTS_CONSENSUS, with T and all pairs
        if trim > 0 and N > 4: T, inliers = trimmed_fit(source, target, weights, T, ones(N, bool), ...)
        FIT_DONE
    """
    n = source.shape[0]
    inliers = np.ones(n, np.bool_)
    if n < 3:
        return np.eye(4), inliers, FIT_DEGENERATE
    T, spread = rigid_fit(source, target, weights, inliers)
    if spread <= collinear_tolerance:
        return T, inliers, FIT_DEGENERATE
    if consensus > 0 and n > 4:
        residual = pair_residuals(source, target, T)
        beyond = 0
        for i in range(n):
            if residual[i] > consensus:
                beyond += 1
        if beyond >= max(2.0, consensus_share * n):
            return T, inliers, FIT_WANTS_CONSENSUS
    if trim > 0 and n > 4:
        T, inliers = trimmed_fit(source, target, weights, T, inliers, trim, floor, rounds, collinear_tolerance)
    return T, inliers, FIT_DONE


# -- The global index (section II-D): cells and the points whose cell may have changed -----------------


@kernel("f8, f8, f8, f8, i8, i8")
def _cell_key(x: float, y: float, z: float, cell: float, limit: int, scale: int) -> int:
    """Packed key of the grid cell (``cell`` m on a side) holding the point ``(x, y, z)`` m: :func:`cell_keys` of one point."""
    cx = int(min(max(math.floor(x / cell), -limit), limit))
    cy = int(min(max(math.floor(y / cell), -limit), limit))
    cz = int(min(max(math.floor(z / cell), -limit), limit))
    return (cx * scale + cy) * scale + cz


@kernel("f8[:, ::1], f8, i8, i8")
def cell_keys(positions: np.ndarray, cell: float, limit: int, scale: int) -> np.ndarray:
    """Packed keys (N,) of the grid cells (``cell`` m on a side) holding positions (N, 3) m.

    numpy: ``c = clip(floor(positions / cell), -limit, limit).astype(int64); (c[:, 0] * scale + c[:, 1]) * scale + c[:, 2]``
    (:meth:`~relpoint.estimators.relative_point.registration.GlobalIndex.keys`; finite positions).
    """
    n = positions.shape[0]
    keys = np.empty(n, np.int64)
    for r in range(n):
        keys[r] = _cell_key(positions[r, 0], positions[r, 1], positions[r, 2], cell, limit, scale)
    return keys


@kernel("i8[::1]")
def distinct_ascending(ids: np.ndarray) -> np.ndarray:
    """numpy: ``unique(ids)`` for non-negative ids (marked in a table as long as the largest, then collected)."""
    largest = -1
    for r in range(ids.shape[0]):
        largest = max(largest, ids[r])
    marked = np.zeros(largest + 1, np.bool_)
    count = 0
    for r in range(ids.shape[0]):
        if not marked[ids[r]]:
            marked[ids[r]] = True
            count += 1
    out = np.empty(count, np.int64)
    c = 0
    for i in range(largest + 1):
        if marked[i]:
            out[c] = i
            c += 1
    return out


# -- Merging (section II-D): flagged points a newly mapped point may take over ---------------------------


@kernel("f8[:, ::1], i8[::1], b1[::1], b1[::1], i8[::1], i8, f8[:, ::1], f8[::1], i8[::1], f8")
def flagged_within(
    world_sum: np.ndarray,
    n_obs: np.ndarray,
    alive: np.ndarray,
    dynamic: np.ndarray,
    uid: np.ndarray,
    high_water: int,
    pos_sum: np.ndarray,
    pos_weight: np.ndarray,
    ids: np.ndarray,
    bound_squared: float,
) -> bool:
    """Whether a live flagged point lies within the bound of a younger live, mapped, static point of ``ids``.

    A flagged point sits at its mean observed position ``world_sum / n_obs``, a mapped point at its
    global position (:func:`gather_positions`, ``world``, m); only flagged points older (smaller
    ``uid``) than the mapped point count. numpy::

        mapped = ids[alive[ids] & (pos_weight[ids] > 0) & ~dynamic[ids]]
        flagged = flatnonzero(alive[:high_water] & dynamic[:high_water])
        at = world_sum[flagged] / maximum(n_obs[flagged], 1)[:, None]
        d2 = sum((gather_positions(pos_sum, pos_weight, mapped)[:, None, :] - at[None, :, :]) ** 2, axis=2)
        any((d2 <= bound_squared) & (uid[flagged][None, :] < uid[mapped][:, None]))
    """
    n = ids.shape[0]
    positions = np.empty((n, 3))
    mapped = np.empty(n, np.int64)
    m = 0
    for r in range(n):
        p = ids[r]
        if alive[p] and pos_weight[p] > 0 and not dynamic[p]:
            w = max(pos_weight[p], 1e-300)
            for a in range(3):
                positions[m, a] = pos_sum[p, a] / w
            mapped[m] = p
            m += 1
    if m == 0:
        return False
    for i in range(high_water):
        if not (alive[i] and dynamic[i]):
            continue
        count = float(max(n_obs[i], 1))
        x, y, z = world_sum[i, 0] / count, world_sum[i, 1] / count, world_sum[i, 2] / count
        for r in range(m):
            if uid[i] >= uid[mapped[r]]:
                continue
            dx, dy, dz = positions[r, 0] - x, positions[r, 1] - y, positions[r, 2] - z
            if dx * dx + dy * dy + dz * dz <= bound_squared:
                return True
    return False


# -- RltMapper (section II-C): a new group's members, from the points charted in its interval --------

SELECTION_NO_CREATION = 0
"""Outcome of :func:`group_selection`: the creation point is not among the usable candidates."""
SELECTION_NONE = 1
"""Outcome of :func:`group_selection`: too few grouped candidates overlap the creation point."""
SELECTION_MADE = 2
"""Outcome of :func:`group_selection`: members and interval chosen."""


@kernel("i8[:, ::1], b1[::1], b1[::1], f8[::1], i8[::1], i8, i8, i8, i8, b1")
def group_selection(
    obs_iter: np.ndarray,
    alive: np.ndarray,
    dynamic: np.ndarray,
    pos_weight: np.ndarray,
    candidates: np.ndarray,
    creation: int,
    first: int,
    last: int,
    seeds: int,
    everyone_grouped: bool,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Members (point ids, creation point first) and interval mask (L,) of a new group over ``[first, last]``.

    ``candidates`` (N,) are the points charted in the interval, ``creation`` the creation point's
    id. Dead and flagged candidates are left out; the rest are ranked by how many iterations of the
    interval they were observed in, and :func:`interval_members` picks among them, with the mapped
    ones (``pos_weight > 0``; every one when ``everyone_grouped``) as the grouped candidates. numpy::

        usable = candidates[alive[candidates] & ~dynamic[candidates]]
        presence = ring_presence(obs_iter, usable, first, last)
        grouped = ones(len(usable), bool) if everyone_grouped else pos_weight[usable] > 0
        order = argsort(-presence.sum(axis=1), kind="stable")
        rows, interval = interval_members(presence, grouped, order, flatnonzero(usable == creation)[0], seeds)
        usable[rows], interval

    The outcome says whether the creation point was usable and a selection was made.
    """
    count = 0
    creation_row = -1
    for r in range(candidates.shape[0]):
        i = candidates[r]
        if alive[i] and not dynamic[i]:
            if i == creation:
                creation_row = count
            count += 1
    if creation_row < 0:
        return candidates[:0].copy(), np.zeros(0, np.bool_), SELECTION_NO_CREATION
    usable = np.empty(count, np.int64)
    grouped = np.empty(count, np.bool_)
    u = 0
    for r in range(candidates.shape[0]):
        i = candidates[r]
        if alive[i] and not dynamic[i]:
            usable[u] = i
            grouped[u] = everyone_grouped or pos_weight[i] > 0
            u += 1
    presence = ring_presence(obs_iter, usable, first, last)
    fewer_observed = np.empty(count)
    for u in range(count):
        observed = 0
        for t in range(presence.shape[1]):
            observed += presence[u, t]
        fewer_observed[u] = -observed
    rows, interval = interval_members(presence, grouped, _stable_argsort(fewer_observed), creation_row, seeds)
    if rows.shape[0] == 0:
        return candidates[:0].copy(), interval, SELECTION_NONE
    members = np.empty(rows.shape[0], np.int64)
    for r in range(rows.shape[0]):
        members[r] = usable[rows[r]]
    return members, interval, SELECTION_MADE


@kernel("f8[:, ::1], i8[::1], i8[::1], f8")
def basis_preferring_verified(
    points: np.ndarray, members: np.ndarray, verified: np.ndarray, min_spread: float
) -> tuple[int, int, int]:
    """Basis rows of ``points`` (M, 3) by :func:`spread_basis`, among the members verified static when they allow one.

    ``members`` (M,) are the points' ids, ``verified`` the store's last verification per point (-1
    never). numpy, with ``trusted = flatnonzero(verified[members] >= 0)``: ``trusted[spread_basis(points[trusted])]``
    when there are three or more trusted points and they give a basis, else ``spread_basis(points)``
    (-1s when neither does).
    """
    m = members.shape[0]
    trusted_count = 0
    for r in range(m):
        if verified[members[r]] >= 0:
            trusted_count += 1
    if trusted_count >= 3:
        trusted = np.empty(trusted_count, np.int64)
        trusted_points = np.empty((trusted_count, 3))
        t = 0
        for r in range(m):
            if verified[members[r]] >= 0:
                trusted[t] = r
                for a in range(3):
                    trusted_points[t, a] = points[r, a]
                t += 1
        i0, i1, i2 = spread_basis(trusted_points, min_spread)
        if i0 >= 0:
            return trusted[i0], trusted[i1], trusted[i2]
    return spread_basis(points, min_spread)


@kernel("f8[:, :, ::1], i8, i8, i8, f8")
def relative_map_sum(
    observations: np.ndarray, i0: int, i1: int, i2: int, min_spread: float
) -> tuple[np.ndarray, int, int]:
    """A new group's relative map: members' basis-frame coordinates summed over the iterations with a usable basis.

    ``observations`` (M, L, 3) are the members' untransformed observations (sensor frame of each
    iteration), rows ``i0, i1, i2`` the basis. Returns the sum (M, 3, basis frame, m), the number of
    iterations summed and the first of them (-1 if none). numpy::

        relative, valid = basis_coordinates(observations, i0, i1, i2, min_spread)
        relative[:, valid].sum(axis=1), count_nonzero(valid), (flatnonzero(valid)[:1] or [-1])[0]

    (numpy adds the iterations one after another from zero, as here).
    """
    relative, valid = basis_coordinates(observations, i0, i1, i2, min_spread)
    m, length = relative.shape[0], relative.shape[1]
    count, first_valid = 0, -1
    for t in range(length):
        if valid[t]:
            count += 1
            if first_valid < 0:
                first_valid = t
    total = np.zeros((m, 3))
    for r in range(m):
        for t in range(length):
            if valid[t]:
                for a in range(3):
                    total[r, a] += relative[r, t, a]
    return total, count, first_valid


# -- RltPoint (section II-A): one iteration's observations into the rings -----------------------------


@kernel("f8[:, :, ::1], i8[:, ::1], i8[::1], i8[::1], i8[::1], i8[::1], i8[::1], f8[:, ::1], i8")
def record_observations(
    obs: np.ndarray,
    obs_iter: np.ndarray,
    first_iter: np.ndarray,
    last_iter: np.ndarray,
    run_start: np.ndarray,
    n_obs: np.ndarray,
    ids: np.ndarray,
    points: np.ndarray,
    iteration: int,
) -> None:
    """Append one iteration's untransformed points (N, 3) to the rings of the distinct points ``ids`` (N,), in place.

    numpy, with ``slot = iteration % R`` for rings of R slots::

        obs[ids, slot] = points;  obs_iter[ids, slot] = iteration
        first = first_iter[ids] < 0;  first_iter[ids[first]] = iteration
        run_start[ids[first | (last_iter[ids] != iteration - 1)]] = iteration   # a new unbroken run
        last_iter[ids] = iteration;  n_obs[ids] += 1
    """
    slot = iteration % obs_iter.shape[1]
    for r in range(ids.shape[0]):
        i = ids[r]
        for a in range(3):
            obs[i, slot, a] = points[r, a]
        obs_iter[i, slot] = iteration
        first = first_iter[i] < 0
        if first:
            first_iter[i] = iteration
        if first or last_iter[i] != iteration - 1:
            run_start[i] = iteration
        last_iter[i] = iteration
        n_obs[i] += 1


# -- RltUngroupedList (section II-C): which listed points are due for a first grouping ----------------


@kernel("i8[::1], b1[::1], f8[::1], b1[::1], i8[::1], i8[::1], i8, i8, i8")
def creation_triage(
    listed: np.ndarray,
    alive: np.ndarray,
    pos_weight: np.ndarray,
    dynamic: np.ndarray,
    last_iter: np.ndarray,
    run_start: np.ndarray,
    iteration: int,
    stale_after: int,
    creation_delay: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sort the ungrouped list ``listed`` (N,) at ``iteration``: stale points, points to unlist, points due.

    numpy::

        done = ~alive[listed] | (pos_weight[listed] > 0) | dynamic[listed]          # gone, grouped or flagged
        stale = alive[listed] & ~done & (iteration - last_iter[listed] > stale_after)   # not seen for long
        due = ~done & ~stale & (last_iter[listed] == iteration)
              & (iteration - run_start[listed] >= creation_delay)                      # seen long enough
        listed[stale], listed[done | stale], listed[due]
    """
    n = listed.shape[0]
    stale = np.empty(n, np.int64)
    unlisted = np.empty(n, np.int64)
    due = np.empty(n, np.int64)
    n_stale, n_unlisted, n_due = 0, 0, 0
    for r in range(n):
        i = listed[r]
        if not alive[i] or pos_weight[i] > 0 or dynamic[i]:
            unlisted[n_unlisted] = i
            n_unlisted += 1
        elif iteration - last_iter[i] > stale_after:
            stale[n_stale] = i
            n_stale += 1
            unlisted[n_unlisted] = i
            n_unlisted += 1
        elif last_iter[i] == iteration and iteration - run_start[i] >= creation_delay:
            due[n_due] = i
            n_due += 1
    return stale[:n_stale].copy(), unlisted[:n_unlisted].copy(), due[:n_due].copy()


@kernel("f8[:, ::1], f8, i8, i8, i8[::1], i8[::1], b1[::1]")
def cell_changes(
    positions: np.ndarray, cell: float, limit: int, scale: int, ids: np.ndarray, key: np.ndarray, indexed: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points ``ids`` (N,) at ``positions`` (N, 3, m) that enter the global index or change cell.

    ``key`` and ``indexed`` are the index's cell key and membership per point id. Returns those
    points' ids, their new keys (:func:`cell_keys`) and, among them, the ones indexed before (to
    take out of their old cells). numpy::

        keys = cell_keys(positions, cell, limit, scale)
        moved = ~indexed[ids] | (keys != key[ids])
        ids[moved], keys[moved], ids[moved & indexed[ids]]
    """
    keys = cell_keys(positions, cell, limit, scale)
    n = ids.shape[0]
    moved_ids = np.empty(n, np.int64)
    moved_keys = np.empty(n, np.int64)
    relocated = np.empty(n, np.int64)
    n_moved, n_relocated = 0, 0
    for r in range(n):
        i = ids[r]
        if indexed[i] and keys[r] == key[i]:
            continue
        moved_ids[n_moved] = i
        moved_keys[n_moved] = keys[r]
        n_moved += 1
        if indexed[i]:
            relocated[n_relocated] = i
            n_relocated += 1
    return moved_ids[:n_moved].copy(), moved_keys[:n_moved].copy(), relocated[:n_relocated].copy()


@kernel("f8[:, ::1], f8[::1], i8[::1], i8[::1], i8[::1], i8[::1], f8")
def older_within(
    pos_sum: np.ndarray,
    pos_weight: np.ndarray,
    uid: np.ndarray,
    points: np.ndarray,
    candidates: np.ndarray,
    offsets: np.ndarray,
    bound_squared: float,
) -> bool:
    """Whether any of the mapped ``points`` (N,) has an older mapped candidate within the bound (``world``).

    The candidates of ``points[r]`` are ``candidates[offsets[r]:offsets[r + 1]]`` (ids; the point
    itself may be among them); positions are :func:`gather_positions`', and a candidate without one
    counts as within. numpy::

        def near(p, c):  # c: the candidates of point p
            d2 = sum((gather_positions(pos_sum, pos_weight, c) - gather_positions(pos_sum, pos_weight, [p])) ** 2, axis=1)
            return any((c != p) & (uid[c] < uid[p]) & ((d2 <= bound_squared) | (pos_weight[c] <= 0)))
        any(near(p, c) for p, c in zip(points, split(candidates, offsets[1:-1])))
    """
    for r in range(points.shape[0]):
        p = points[r]
        w = max(pos_weight[p], 1e-300)
        x, y, z = pos_sum[p, 0] / w, pos_sum[p, 1] / w, pos_sum[p, 2] / w
        for c in candidates[offsets[r] : offsets[r + 1]]:
            if c == p or uid[c] >= uid[p]:
                continue
            if pos_weight[c] <= 0.0:
                return True  # no position (not in an index refreshed since): the caller looks closer
            v = max(pos_weight[c], 1e-300)
            dx, dy, dz = pos_sum[c, 0] / v - x, pos_sum[c, 1] / v - y, pos_sum[c, 2] / v - z
            if dx * dx + dy * dy + dz * dz <= bound_squared:
                return True
    return False


# -- RltMapper (section II-C): points due for regrouping ------------------------------------------------


@kernel("i8[::1], i8[::1], b1[::1], i8[::1], i8[::1], i8[::1], f8[::1], b1[::1], i8[::1], i8, i8, i8")
def regroup_due(
    previous: np.ndarray,
    current: np.ndarray,
    alive: np.ndarray,
    last_iter: np.ndarray,
    run_start: np.ndarray,
    n_later_groups: np.ndarray,
    pos_weight: np.ndarray,
    dynamic: np.ndarray,
    regroup_attempt: np.ndarray,
    iteration: int,
    min_iterations: int,
    every: int,
) -> np.ndarray:
    """Points due for a regrouping at ``iteration``: runs that just ended, then runs that grew long.

    ``previous`` and ``current`` are the points charted in the last and this iteration. A point
    whose run of at least ``min_iterations`` ended last iteration, or whose current run reached
    ``every`` iterations, is due when it is mapped, static, has no later grouping yet and was not
    tried in the last ``every`` iterations. numpy::

        live = previous[alive[previous]]
        left = live[(last_iter[live] == iteration - 1) & (iteration - run_start[live] >= min_iterations)]
        long_run = current[iteration - run_start[current] + 1 >= every]
        due = concatenate([left, long_run])
        due[(n_later_groups[due] == 0) & (pos_weight[due] > 0) & ~dynamic[due]
            & (iteration - regroup_attempt[due] >= every)]
    """
    due = np.empty(previous.shape[0] + current.shape[0], np.int64)
    n = 0
    for r in range(previous.shape[0] + current.shape[0]):
        if r < previous.shape[0]:
            i = previous[r]
            if not (alive[i] and last_iter[i] == iteration - 1 and iteration - run_start[i] >= min_iterations):
                continue
        else:
            i = current[r - previous.shape[0]]
            if iteration - run_start[i] + 1 < every:
                continue
        if n_later_groups[i] == 0 and pos_weight[i] > 0 and not dynamic[i] and iteration - regroup_attempt[i] >= every:
            due[n] = i
            n += 1
    return due[:n].copy()


@kernel("i8[::1], i8[::1], i8, i8[::1], f8[:, :, ::1]")
def recent_references(
    seen: np.ndarray, offsets: np.ndarray, first_iteration: int, last_iter: np.ndarray, obs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each recently seen point once, with its latest untransformed observation and its age.

    ``seen[offsets[s]:offsets[s + 1]]`` are the points charted in iteration ``first_iteration + s``
    (W iterations, up to the current one, ``first_iteration + W``, excluded). A point is taken from
    the iteration it was last seen in. Returns the ids (R,), their latest observations (R, 3, sensor
    frame of that iteration) and their ages (R,, iterations). numpy::

        refs = concatenate([seen_t[last_iter[seen_t] == t] for each iteration t and its seen_t])
        refs, obs[refs, last_iter[refs] % obs.shape[1]], first_iteration + W - last_iter[refs]
    """
    window = offsets.shape[0] - 1
    ring = obs.shape[1]
    refs = np.empty(seen.shape[0], np.int64)
    n = 0
    for s in range(window):
        for r in range(offsets[s], offsets[s + 1]):
            if last_iter[seen[r]] == first_iteration + s:
                refs[n] = seen[r]
                n += 1
    reference = np.empty((n, 3))
    age = np.empty(n, np.int64)
    for r in range(n):
        i = refs[r]
        slot = last_iter[i] % ring
        for a in range(3):
            reference[r, a] = obs[i, slot, a]
        age[r] = first_iteration + window - last_iter[i]
    return refs[:n].copy(), reference, age


@kernel("i8[::1], b1[::1], f8[:, ::1], f8[::1], b1[::1], f8, i8, i8, i8[::1], b1[::1]")
def index_refresh(
    changed: np.ndarray,
    alive: np.ndarray,
    pos_sum: np.ndarray,
    pos_weight: np.ndarray,
    dynamic: np.ndarray,
    cell: float,
    limit: int,
    scale: int,
    key: np.ndarray,
    indexed: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the global index must change for the points ``changed`` (ids, repeats allowed) of a point store.

    A live point with a global position (``pos_sum / pos_weight``, ``world``, m) that is not
    flagged ``dynamic`` belongs in the cell :func:`cell_keys` gives it; any other live point does
    not belong in the index. ``key`` and ``indexed`` are the index's cell and membership per id.
    Returns, in ascending id order: the indexed points that change cell, every point that enters
    a cell (those and the new ones) with that cell's key, and the indexed points that leave. numpy::

        ids = unique(changed);  live = ids[alive[ids]]
        keep = (pos_weight[live] > 0) & ~dynamic[live];  stay, drop = live[keep], live[~keep]
        moving_ids, keys, relocated = cell_changes(gather_positions(pos_sum, pos_weight, stay), cell, limit, scale,
                                                   stay, key, indexed)
        relocated, moving_ids, keys, drop[indexed[drop]]
    """
    ids = distinct_ascending(changed)
    n = ids.shape[0]
    relocated = np.empty(n, np.int64)
    moving = np.empty(n, np.int64)
    keys = np.empty(n, np.int64)
    leaving = np.empty(n, np.int64)
    n_relocated, n_moving, n_leaving = 0, 0, 0
    for r in range(n):
        i = ids[r]
        if not alive[i]:
            continue
        if pos_weight[i] > 0 and not dynamic[i]:
            w = max(pos_weight[i], 1e-300)
            k = _cell_key(pos_sum[i, 0] / w, pos_sum[i, 1] / w, pos_sum[i, 2] / w, cell, limit, scale)
            if indexed[i] and k == key[i]:
                continue
            moving[n_moving] = i
            keys[n_moving] = k
            n_moving += 1
            if indexed[i]:
                relocated[n_relocated] = i
                n_relocated += 1
        elif indexed[i]:
            leaving[n_leaving] = i
            n_leaving += 1
    return (
        relocated[:n_relocated].copy(),
        moving[:n_moving].copy(),
        keys[:n_moving].copy(),
        leaving[:n_leaving].copy(),
    )


@kernel("i8[::1], b1[::1], f8[:, ::1], f8[::1], b1[::1], f8, i8, i8")
def mapped_static_cells(
    ids: np.ndarray,
    alive: np.ndarray,
    pos_sum: np.ndarray,
    pos_weight: np.ndarray,
    dynamic: np.ndarray,
    cell: float,
    limit: int,
    scale: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The distinct live, mapped, static points among ``ids`` (repeats allowed), ascending, and their cell keys.

    numpy: ``u = unique(ids); u = u[alive[u] & (pos_weight[u] > 0) & ~dynamic[u]]`` and
    ``u, cell_keys(gather_positions(pos_sum, pos_weight, u), cell, limit, scale)``.
    """
    distinct = distinct_ascending(ids)
    kept = np.empty(distinct.shape[0], np.int64)
    keys = np.empty(distinct.shape[0], np.int64)
    n = 0
    for r in range(distinct.shape[0]):
        i = distinct[r]
        if alive[i] and pos_weight[i] > 0 and not dynamic[i]:
            w = max(pos_weight[i], 1e-300)
            kept[n] = i
            keys[n] = _cell_key(pos_sum[i, 0] / w, pos_sum[i, 1] / w, pos_sum[i, 2] / w, cell, limit, scale)
            n += 1
    return kept[:n].copy(), keys[:n].copy()


# -- RltGroupRef (section II-B): per point, the groups it is in -----------------------------------------


@kernel("i8[:, ::1], i8[::1], i8[::1], i8")
def append_group(table: np.ndarray, count: np.ndarray, members: np.ndarray, gid: int) -> bool:
    """Append group ``gid`` to the group lists of its distinct ``members`` (M,), in place; False if a list is full.

    Point ``i``'s list is ``table[i, :count[i]]`` in the order the groups were added. numpy::

        if any(count[members] >= table.shape[1]): False (nothing changed)
        table[members, count[members]] = gid;  count[members] += 1;  True
    """
    width = table.shape[1]
    for r in range(members.shape[0]):
        if count[members[r]] >= width:
            return False
    for r in range(members.shape[0]):
        i = members[r]
        table[i, count[i]] = gid
        count[i] += 1
    return True


@kernel("i8[:, ::1], i8[::1], i8[::1], i8")
def drop_group(table: np.ndarray, count: np.ndarray, members: np.ndarray, gid: int) -> None:
    """Take group ``gid`` out of the group lists of ``members`` (M,), in place, keeping the others' order.

    numpy, per member ``i`` with ``listed = table[i, :count[i]]`` holding ``gid``:
    ``j = flatnonzero(listed == gid)[0]; table[i, j:count[i] - 1] = listed[j + 1:]; count[i] -= 1``
    (the first occurrence, as ``list.remove``; members whose list lacks it are left alone).
    """
    for r in range(members.shape[0]):
        i = members[r]
        n = count[i]
        for j in range(n):
            if table[i, j] == gid:
                for s in range(j, n - 1):
                    table[i, s] = table[i, s + 1]
                count[i] = n - 1
                break


@kernel("f8[:, :, ::1], i8[:, ::1], i8[::1], i8[::1], i8[::1], f8")
def group_relative_map(
    obs: np.ndarray,
    obs_iter: np.ndarray,
    members: np.ndarray,
    iterations: np.ndarray,
    verified: np.ndarray,
    min_spread: float,
) -> tuple[int, int, int, np.ndarray, int, int]:
    """A new group's basis and relative map, from its members' rings over the iterations of its interval.

    ``members`` (M,) are point ids, ``iterations`` (L,) the interval's iterations (every member
    observed in each). Returns the basis rows ``i0, i1, i2`` (-1s when none), then as
    :func:`relative_map_sum` the summed relative map (M, 3, basis frame, m), the iterations summed
    and the first of them. numpy::

        observations = ring_observations(obs, obs_iter, members, iterations)[0]
        i0, i1, i2 = basis_preferring_verified(observations[:, 0], members, verified, min_spread)
        (i0, i1, i2, *relative_map_sum(observations, i0, i1, i2, min_spread)) if i0 >= 0 else (-1, -1, -1, ...)
    """
    observations = ring_observations(obs, obs_iter, members, iterations)[0]
    m = members.shape[0]
    first = np.empty((m, 3))
    for r in range(m):
        for a in range(3):
            first[r, a] = observations[r, 0, a]
    i0, i1, i2 = basis_preferring_verified(first, members, verified, min_spread)
    if i0 < 0:
        return -1, -1, -1, np.zeros((0, 3)), 0, -1
    total, count, first_valid = relative_map_sum(observations, i0, i1, i2, min_spread)
    return i0, i1, i2, total, count, first_valid


OPEN_GROUP_CLOSES = 0
"""Outcome of :func:`extend_open_group`: a member went unobserved or a basis member was flagged."""
OPEN_GROUP_SKIPS = 1
"""Outcome of :func:`extend_open_group`: the group stays open, but this iteration's basis is unusable."""
OPEN_GROUP_AVERAGED = 2
"""Outcome of :func:`extend_open_group`: this iteration was added to the group's relative map."""


@kernel("f8[:, :, ::1], i8[::1], b1[::1], i8[::1], i8, i8, i8, i8, f8, f8[:, ::1]")
def extend_open_group(
    obs: np.ndarray,
    last_iter: np.ndarray,
    dynamic: np.ndarray,
    members: np.ndarray,
    i0: int,
    i1: int,
    i2: int,
    iteration: int,
    min_spread: float,
    rel_sum: np.ndarray,
) -> int:
    """Average ``iteration`` into an open group's relative map ``rel_sum`` (M, 3, basis frame, m), in place.

    ``members`` (M,) are the group's points, rows ``i0, i1, i2`` its basis. numpy, with
    ``slot = iteration % obs.shape[1]``::

        if any(last_iter[members] != iteration) or any(dynamic[members[[i0, i1, i2]]]): OPEN_GROUP_CLOSES
        relative, valid = basis_coordinates(obs[members, slot][:, None], i0, i1, i2, min_spread)
        if not valid[0]: OPEN_GROUP_SKIPS
        rel_sum += relative[:, 0];  OPEN_GROUP_AVERAGED
    """
    m = members.shape[0]
    for r in range(m):
        if last_iter[members[r]] != iteration:
            return OPEN_GROUP_CLOSES
    if dynamic[members[i0]] or dynamic[members[i1]] or dynamic[members[i2]]:
        return OPEN_GROUP_CLOSES
    slot = iteration % obs.shape[1]
    current = np.empty((m, 1, 3))
    for r in range(m):
        for a in range(3):
            current[r, 0, a] = obs[members[r], slot, a]
    relative, valid = basis_coordinates(current, i0, i1, i2, min_spread)
    if not valid[0]:
        return OPEN_GROUP_SKIPS
    for r in range(m):
        for a in range(3):
            rel_sum[r, a] += relative[r, 0, a]
    return OPEN_GROUP_AVERAGED


# -- global matching (section II-D) ---------------------------------------------------------------


@kernel("i8[::1], i8[::1], i8[::1], i8, f8[:, ::1], f8[::1], f8[:, ::1]")
def nearest_older_candidates(
    candidates: np.ndarray,
    counts: np.ndarray,
    last_iter: np.ndarray,
    recent: int,
    pos_sum: np.ndarray,
    pos_weight: np.ndarray,
    world: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Each query position's nearest candidate point not seen since iteration ``recent``.

    ``world`` (Q, 3) are the query positions (``world``, m); ``candidates`` holds each query's
    candidate point ids in turn, ``counts`` (Q,) how many are each query's. Returns the squared
    distance (Q,) m^2 and the id (Q,) of each query's nearest candidate with ``last_iter >= recent``
    left out (-1 and infinity where none is left; the first of equal ones; NaN and the first
    unmapped one where a candidate has no global position, as ``argmin`` picks NaN). numpy, per
    query ``q`` with candidates ``c``::

        c = c[last_iter[c] < recent]
        d2 = sum((gather_positions(pos_sum, pos_weight, c) - world[q]) ** 2, axis=1)
        best = argmin(d2);  d2[best], c[best]
    """
    q_count = counts.shape[0]
    best_d2 = np.full(q_count, np.inf)
    best_id = np.full(q_count, -1, np.int64)
    start = 0
    for q in range(q_count):
        end = start + counts[q]
        x, y, z = world[q, 0], world[q, 1], world[q, 2]
        for r in range(start, end):
            i = candidates[r]
            if last_iter[i] >= recent:
                continue
            w = pos_weight[i]
            if w <= 0.0:
                d2 = np.nan
            else:
                w = max(w, 1e-300)
                dx = pos_sum[i, 0] / w - x
                dy = pos_sum[i, 1] / w - y
                dz = pos_sum[i, 2] / w - z
                d2 = dx * dx
                d2 += dy * dy
                d2 += dz * dz
            if best_id[q] < 0 or d2 < best_d2[q] or (d2 != d2 and best_d2[q] == best_d2[q]):
                best_d2[q] = d2
                best_id[q] = i
            if d2 != d2:
                break  # argmin stops at the first NaN
        start = end
    return best_d2, best_id


# -- per-iteration bookkeeping ---------------------------------------------------------------------


@kernel("i8[::1], f8[::1], b1[::1]")
def mapped_static_mask(ids: np.ndarray, pos_weight: np.ndarray, dynamic: np.ndarray) -> np.ndarray:
    """Which of the point ids (N,) (-1 for none) have a global position and are not flagged ``dynamic``.

    numpy: ``known = ids != -1;  safe = where(known, ids, 0);  known & (pos_weight[safe] > 0) & ~dynamic[safe]``.
    """
    n = ids.shape[0]
    out = np.zeros(n, np.bool_)
    for r in range(n):
        i = ids[r]
        if i != -1 and pos_weight[i] > 0 and not dynamic[i]:
            out[r] = True
    return out


@kernel("i8[::1], i8[::1]")
def least_at(values: np.ndarray, ids: np.ndarray) -> int:
    """The least of ``values`` at ``ids`` (N,), N > 0. numpy: ``values[ids].min()``."""
    if ids.shape[0] == 0:
        raise ValueError("least_at: no ids")
    least = values[ids[0]]
    for r in range(1, ids.shape[0]):
        if values[ids[r]] < least:
            least = values[ids[r]]
    return least


@kernel("f8[::1], i8[::1]")
def unmapped_members(pos_weight: np.ndarray, members: np.ndarray) -> np.ndarray:
    """The points among ``members`` (N,) without a global position, in order. numpy: ``members[~(pos_weight[members] > 0)]``."""
    out = np.empty(members.shape[0], np.int64)
    n = 0
    for r in range(members.shape[0]):
        if not pos_weight[members[r]] > 0.0:
            out[n] = members[r]
            n += 1
    return out[:n].copy()


@kernel("i8[::1], i8[::1], i8")
def members_above(values: np.ndarray, members: np.ndarray, bound: int) -> np.ndarray:
    """The points among ``members`` (N,) whose ``values`` exceed ``bound``, in order. numpy: ``members[values[members] > bound]``."""
    out = np.empty(members.shape[0], np.int64)
    n = 0
    for r in range(members.shape[0]):
        if values[members[r]] > bound:
            out[n] = members[r]
            n += 1
    return out[:n].copy()


@kernel("b1[::1], i8, i8[::1], i8[::1], f8[:, ::1]")
def support_observations(
    mapped: np.ndarray, keep: int, ids: np.ndarray, uid: np.ndarray, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Up to ``keep`` (>= 2) of an iteration's observations of ``mapped`` points, evenly spread.

    ``mapped`` (N,) marks the usable observations, ``ids`` (N,) their points, ``uid`` the store's
    uids by point and ``points`` (N, 3) the observations. Returns the rows kept, their points'
    uids and their observations as float32. numpy::

        use = mapped.nonzero()[0]
        if len(use) > keep: use = use[arange(keep) * (len(use) - 1) // (keep - 1)]
        use, uid[ids[use]], points[use].astype(float32)
    """
    n = 0
    for r in range(mapped.shape[0]):
        if mapped[r]:
            n += 1
    rows = np.empty(n, np.int64)
    n = 0
    for r in range(mapped.shape[0]):
        if mapped[r]:
            rows[n] = r
            n += 1
    if n > keep:
        spread = np.empty(keep, np.int64)
        for j in range(keep):
            spread[j] = rows[j * (n - 1) // (keep - 1)]
        rows = spread
    m = rows.shape[0]
    uids = np.empty(m, np.int64)
    kept = np.empty((m, 3), np.float32)
    for j in range(m):
        uids[j] = uid[ids[rows[j]]]
        for a in range(3):
            kept[j, a] = np.float32(points[rows[j], a])
    return rows, uids, kept
