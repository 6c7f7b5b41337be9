"""Compiled inner loops of FastSLAM (numba): the candidate search and the per-point association.

FastSLAM's association takes the points one at a time (a landmark takes at most one point, and in
2.0 each paired point refines the pose proposal the next point is judged with), each against a
handful of landmark slots in every particle. In numpy every point costs some twenty calls over
arrays of a few dozen elements; here the same arithmetic runs as plain loops. Each kernel's docstring
gives the numpy expression it equals up to rounding, and ``tests/test_fastslam.py`` checks the
kernels against the numpy reference on random inputs.

An install builds the kernels ahead of time into the extension module ``_fastslam_kernels_aot``
(numba's ``pycc``, from the argument types each kernel names; see ``setup.py`` and
:mod:`relpoint._aot_kernels`, the mechanism Relative Point's kernels share), so no run pays for
compilation and numba is not imported. Without that module (no C compiler at install, a source
checkout, or ``RELPOINT_KERNELS=jit``), or when it was built from another version of this file, each
kernel is compiled on its first call instead (``cache=True`` keeps the machine code for later
processes); :func:`prepare` compiles them ahead of a run. Both give bit-identical results.
"""

from __future__ import annotations

import math

import numpy as np

from relpoint._aot_kernels import KernelSet

kernels = KernelSet(__file__, "relpoint.estimators._fastslam_kernels_aot")
"""This file's kernels: prebuilt at install into ``_fastslam_kernels_aot`` or compiled on first call."""
kernel = kernels.kernel
SIGNATURES: dict[str, str] = kernels.signatures
"""Argument types of every kernel in numba's notation, by name: what the ahead-of-time build compiles."""
COMPILED_AHEAD = kernels.compiled_ahead
"""Whether the kernels below are the prebuilt machine code (True) or compiled on first call (False)."""
source_digest = kernels.source_digest
prepare = kernels.prepare
"""Compile every public kernel for its declared argument types, or load it from numba's cache
(nothing to do when :data:`COMPILED_AHEAD`); :meth:`FastSlam.compile` calls this before a run."""

_LOG_2PI = math.log(2.0 * math.pi)


@kernel("f8[:, ::1], f8[::1], f8[::1], f8[::1]")
def _in_sensor_frame(R, position, mean, out):  # pragma: no cover - compiled
    """``out = R^T (mean - position)``: a world point (3,) in the sensor frame of pose ``(R, position)``."""
    d0 = mean[0] - position[0]
    d1 = mean[1] - position[1]
    d2 = mean[2] - position[2]
    for a in range(3):
        out[a] = R[0, a] * d0 + R[1, a] * d1 + R[2, a] * d2


@kernel("f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[:, ::1], f8[:, ::1]")
def _measurement_covariance(R, C, Q, CR, S):  # pragma: no cover - compiled
    """``S = R^T C R + Q``: a landmark's covariance ``C`` (world) seen from ``R``, plus the point noise
    ``Q``; ``CR`` (3, 3) is scratch and holds ``C R`` afterwards."""
    for a in range(3):
        for b in range(3):
            CR[a, b] = C[a, 0] * R[0, b] + C[a, 1] * R[1, b] + C[a, 2] * R[2, b]
    for a in range(3):
        for b in range(3):
            S[a, b] = R[0, a] * CR[0, b] + R[1, a] * CR[1, b] + R[2, a] * CR[2, b] + Q[a, b]


@kernel("f8[:, ::1], f8[:, ::1], f8[:, :, ::1], f8[:, :, ::1], i8[::1], f8")
def near_slots(points, positions, rotations, means, counts, radius):  # pragma: no cover - compiled
    """Per point, the landmark slots within ``radius`` of it (sensor frame) in at least one particle.

    ``points`` (N, 3) sensor frame; ``positions`` (P, 3), ``rotations`` (P, 3, 3) ``R_world_sensor``;
    ``means`` (P, M, 3) world; ``counts`` (P,) slots in use. Returns CSR ``(offsets (N + 1,), slots)``,
    slots ascending per point; equal to testing ``|R_p^T (m_pj - x_p) - z_i|^2 < radius^2`` for all
    ``p`` and ``j < counts[p]``.
    """
    n = points.shape[0]
    n_particles = positions.shape[0]
    cap = 0
    for p in range(n_particles):
        cap = max(cap, counts[p])
    # Every particle's landmarks in its sensor frame, once.
    predicted = np.empty((n_particles, cap, 3))
    for p in range(n_particles):
        for j in range(counts[p]):
            _in_sensor_frame(rotations[p], positions[p], means[p, j], predicted[p, j])
    # Each slot's bounding box over the particles that hold it: a point farther than ``radius`` from
    # the box is farther than that from the slot in every particle, so only the others are tested.
    low = np.full((cap, 3), np.inf)
    high = np.full((cap, 3), -np.inf)
    for p in range(n_particles):
        for j in range(counts[p]):
            for a in range(3):
                low[j, a] = min(low[j, a], predicted[p, j, a])
                high[j, a] = max(high[j, a], predicted[p, j, a])
    r2 = radius * radius
    near = np.zeros(cap, dtype=np.bool_)
    offsets = np.zeros(n + 1, dtype=np.int64)
    found = np.empty(16 * max(n, 1), dtype=np.int64)
    size = 0
    for i in range(n):
        near[:] = False
        z0, z1, z2 = points[i, 0], points[i, 1], points[i, 2]
        for j in range(cap):
            g0 = max(low[j, 0] - z0, 0.0, z0 - high[j, 0])
            g1 = max(low[j, 1] - z1, 0.0, z1 - high[j, 1])
            g2 = max(low[j, 2] - z2, 0.0, z2 - high[j, 2])
            if g0 * g0 + g1 * g1 + g2 * g2 >= r2:
                continue
            for p in range(n_particles):
                if j >= counts[p]:
                    continue
                e0 = predicted[p, j, 0] - z0
                e1 = predicted[p, j, 1] - z1
                e2 = predicted[p, j, 2] - z2
                if e0 * e0 + e1 * e1 + e2 * e2 < r2:
                    near[j] = True
                    break
        for j in range(cap):
            if near[j]:
                if size == found.shape[0]:
                    grown = np.empty(2 * size, dtype=np.int64)
                    grown[:size] = found
                    found = grown
                found[size] = j
                size += 1
        offsets[i + 1] = size
    return offsets, found[:size].copy()


@kernel("f8[:, ::1], f8[:, ::1]")
def _inverse_and_logdet3(L, out):  # pragma: no cover - compiled
    """``out = L^-1`` of a 3x3 matrix; returns ``log|det L|`` (NaN when singular)."""
    a, b, c = L[0, 0], L[0, 1], L[0, 2]
    d, e, f = L[1, 0], L[1, 1], L[1, 2]
    g, h, k = L[2, 0], L[2, 1], L[2, 2]
    c00 = e * k - f * h
    c01 = -(d * k - f * g)
    c02 = d * h - e * g
    det = a * c00 + b * c01 + c * c02
    if det == 0.0 or not math.isfinite(det):
        return math.nan
    inv = 1.0 / det
    out[0, 0] = c00 * inv
    out[1, 0] = c01 * inv
    out[2, 0] = c02 * inv
    out[0, 1] = -(b * k - c * h) * inv
    out[1, 1] = (a * k - c * g) * inv
    out[2, 1] = -(a * h - b * g) * inv
    out[0, 2] = (b * f - c * e) * inv
    out[1, 2] = -(a * f - c * d) * inv
    out[2, 2] = (a * e - b * d) * inv
    return math.log(abs(det))


@kernel("f8[:, ::1], f8[::1]")
def _rotate_by(R, w):  # pragma: no cover - compiled
    """``R @ Exp(w)`` in place for a rotation vector ``w`` (rad), Rodrigues' formula."""
    theta = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    E = np.eye(3)
    if theta > 0.0:
        kx, ky, kz = w[0] / theta, w[1] / theta, w[2] / theta
        s, c = math.sin(theta), math.cos(theta)
        v = 1.0 - c
        E[0, 0] = c + kx * kx * v
        E[0, 1] = kx * ky * v - kz * s
        E[0, 2] = kx * kz * v + ky * s
        E[1, 0] = ky * kx * v + kz * s
        E[1, 1] = c + ky * ky * v
        E[1, 2] = ky * kz * v - kx * s
        E[2, 0] = kz * kx * v - ky * s
        E[2, 1] = kz * ky * v + kx * s
        E[2, 2] = c + kz * kz * v
    for a in range(3):
        r0, r1, r2 = R[a, 0], R[a, 1], R[a, 2]
        for b in range(3):
            R[a, b] = r0 * E[0, b] + r1 * E[1, b] + r2 * E[2, b]


@kernel(
    "f8[:, ::1], i8[::1], i8[::1], f8[:, ::1], f8[:, :, ::1], f8[:, ::1], f8[:, :, ::1], f8[:, :, :, ::1], i8[::1], "
    "f8[:, ::1], f8[:, :, ::1], b1, f8, f8, b1"
)
def associate(
    points, offsets, slots, positions, rotations, twists, means, covs, counts, Q, Sigma, proposal, log_new, log_start,
    wide_prior,
):  # pragma: no cover - compiled
    """Maximum-likelihood association of each point in each particle, one point at a time.

    The loop of ``FastSlam._associate`` (``tests/test_fastslam.py`` holds its numpy form): for point
    ``i`` and particle ``p`` every candidate slot ``j`` (``slots[offsets[i]:offsets[i + 1]]``) not yet
    taken in ``p`` gets ``log N(z_i; R^T (m - x), L)`` with ``L = R^T C R + Q``, plus ``H Sigma H^T``
    when ``proposal``, where ``H = [-R^T, [z_hat]x, 0]`` (3, 12). The best one is paired when its
    *pairing score* reaches ``log_new``, the point is discarded (-2) when it reaches ``log_start`` only,
    and otherwise starts a landmark (-1). The score is the log-likelihood, except under a
    ``wide_prior`` (with ``proposal``: the first step, whose speed is unknown): there the determinant
    of ``R^T C R + Q`` replaces ``L``'s, so that the prior's spread ``H Sigma H^T`` widens the search
    through the distance without lowering the score; it is the same for every point, and the first
    pairings narrow it. (Judged by the likelihood, the initial speed's prior over a 1 cm sensor put
    every candidate below ``log_new``: nothing paired and the pose was drawn blind from the prior.)
    With ``proposal`` each pairing moves the particle's pose and
    twist by the EKF correction ``K nu``, ``K = Sigma H^T L^-1``, and updates ``Sigma`` by the Joseph
    form ``(I - K H) Sigma (I - K H)^T + K S K^T``, evaluated left to right as numpy does (``H`` is
    zero beyond its first six columns, so only six of ``Sigma``'s rows and columns enter each product
    with it). ``positions``,
    ``rotations``, ``twists`` and ``Sigma`` are updated in place.

    Returns ``(assoc (P, N), log_likelihood (P,), paired, discarded)``.
    """
    n_particles = positions.shape[0]
    n = points.shape[0]
    assoc = np.full((n_particles, n), -1, dtype=np.int64)
    log_likelihood = np.zeros(n_particles)
    cap = 1
    for p in range(n_particles):
        cap = max(cap, counts[p])
    used = np.zeros((n_particles, cap), dtype=np.bool_)
    A = np.zeros((3, 6))  # H's non-zero columns
    HS = np.zeros((3, 12))  # H Sigma
    CR = np.empty((3, 3))
    S_m = np.empty((3, 3))
    L = np.empty((3, 3))
    L_inv = np.empty((3, 3))
    S_m_inv = np.empty((3, 3))  # scratch of the wide prior's score
    best_S = np.empty((3, 3))
    best_L_inv = np.empty((3, 3))
    best_HS = np.empty((3, 12))
    best_A = np.empty((3, 6))
    SHt = np.empty((12, 3))  # Sigma H^T
    T = np.empty((12, 12))  # (I - K H) Sigma
    THt = np.empty((12, 3))  # T H^T
    best_nu = np.empty(3)
    z_hat = np.empty(3)
    nu = np.empty(3)
    K = np.empty((12, 3))
    KL = np.empty((12, 3))
    delta = np.empty(12)
    for i in range(n):
        first, last = offsets[i], offsets[i + 1]
        if first == last:
            for p in range(n_particles):
                log_likelihood[p] += log_new
            continue
        for p in range(n_particles):
            R = rotations[p]
            Sg = Sigma[p]
            best = -math.inf
            best_score = -math.inf
            best_slot = -1
            for c in range(first, last):
                j = slots[c]
                if j >= counts[p] or used[p, j]:
                    continue
                _in_sensor_frame(R, positions[p], means[p, j], z_hat)
                for a in range(3):
                    nu[a] = points[i, a] - z_hat[a]
                _measurement_covariance(R, covs[p, j], Q, CR, S_m)
                for a in range(3):
                    for b in range(3):
                        L[a, b] = S_m[a, b]
                if proposal:
                    for a in range(3):
                        for b in range(3):
                            A[a, b] = -R[b, a]
                    A[0, 3], A[0, 4], A[0, 5] = 0.0, -z_hat[2], z_hat[1]
                    A[1, 3], A[1, 4], A[1, 5] = z_hat[2], 0.0, -z_hat[0]
                    A[2, 3], A[2, 4], A[2, 5] = -z_hat[1], z_hat[0], 0.0
                    for a in range(3):
                        for b in range(12):
                            total = 0.0
                            for e in range(6):
                                total += A[a, e] * Sg[e, b]
                            HS[a, b] = total
                    for a in range(3):
                        for b in range(3):
                            total = 0.0
                            for e in range(6):
                                total += HS[a, e] * A[b, e]
                            L[a, b] += total
                logdet = _inverse_and_logdet3(L, L_inv)
                quad = 0.0
                for a in range(3):
                    for b in range(3):
                        quad += nu[a] * L_inv[a, b] * nu[b]
                logl = -0.5 * (quad + logdet + 3.0 * _LOG_2PI)
                if logl > best:
                    best = logl
                    if proposal and wide_prior:  # the determinant without the prior's spread
                        best_score = -0.5 * (quad + _inverse_and_logdet3(S_m, S_m_inv) + 3.0 * _LOG_2PI)
                    else:
                        best_score = logl
                    best_slot = j
                    for a in range(3):
                        best_nu[a] = nu[a]
                        for b in range(3):
                            best_S[a, b] = S_m[a, b]
                            best_L_inv[a, b] = L_inv[a, b]
                    if proposal:
                        for a in range(3):
                            for b in range(12):
                                best_HS[a, b] = HS[a, b]
                            for b in range(6):
                                best_A[a, b] = A[a, b]
            if best_slot >= 0 and best_score >= log_new:
                assoc[p, i] = best_slot
                used[p, best_slot] = True
                log_likelihood[p] += best
                if proposal:
                    for a in range(12):  # Sigma H^T (H is zero beyond its first six columns)
                        for b in range(3):
                            total = 0.0
                            for e in range(6):
                                total += Sg[a, e] * best_A[b, e]
                            SHt[a, b] = total
                    for a in range(12):  # K = Sigma H^T L^-1, the correction K nu
                        for b in range(3):
                            K[a, b] = SHt[a, 0] * best_L_inv[0, b] + SHt[a, 1] * best_L_inv[1, b] \
                                + SHt[a, 2] * best_L_inv[2, b]
                        delta[a] = K[a, 0] * best_nu[0] + K[a, 1] * best_nu[1] + K[a, 2] * best_nu[2]
                    for a in range(3):
                        positions[p, a] += delta[a]
                    _rotate_by(rotations[p], delta[3:6])
                    for a in range(6):
                        twists[p, a] += delta[6 + a]
                    # Joseph form, as (I - K H) Sigma (I - K H)^T + K S K^T is evaluated left to right:
                    # T = Sigma - K (H Sigma), then T - (T H^T) K^T, then + K S K^T.
                    for a in range(12):
                        for b in range(12):
                            T[a, b] = Sg[a, b] - (K[a, 0] * best_HS[0, b] + K[a, 1] * best_HS[1, b]
                                                  + K[a, 2] * best_HS[2, b])
                    for a in range(12):
                        for b in range(3):
                            total = 0.0
                            for e in range(6):
                                total += T[a, e] * best_A[b, e]
                            THt[a, b] = total
                    for a in range(12):  # K S
                        for b in range(3):
                            KL[a, b] = K[a, 0] * best_S[0, b] + K[a, 1] * best_S[1, b] + K[a, 2] * best_S[2, b]
                    for a in range(12):
                        for b in range(12):
                            Sg[a, b] = (
                                T[a, b]
                                - (THt[a, 0] * K[b, 0] + THt[a, 1] * K[b, 1] + THt[a, 2] * K[b, 2])
                                + (KL[a, 0] * K[b, 0] + KL[a, 1] * K[b, 1] + KL[a, 2] * K[b, 2])
                            )
            else:
                if best_slot >= 0 and best_score >= log_start:
                    assoc[p, i] = -2
                log_likelihood[p] += log_new
    paired = 0
    discarded = 0
    for p in range(n_particles):
        for i in range(n):
            paired += assoc[p, i] >= 0
            discarded += assoc[p, i] == -2
    return assoc, log_likelihood, paired, discarded


@kernel(
    "f8[:, ::1], i8[:, ::1], f8[:, ::1], f8[:, :, ::1], f8[:, :, ::1], f8[:, :, :, ::1], f8[:, ::1], i8[:, ::1], "
    "i8[:, ::1], i8"
)
def update_landmarks(points, assoc, positions, rotations, means, covs, Q, seen, last, iteration):  # pragma: no cover
    """The 3x3 EKF update of every paired landmark with its particle's (sampled) pose.

    For each ``assoc[p, i] = j >= 0``: ``S = R^T C R + Q``, ``K = C R S^-1`` (``dz/dm = R^T``),
    ``m += K (z_i - R^T (m - x))`` and ``C = sym((I - K R^T) C (I - K R^T)^T + K Q K^T)``; ``seen[p, j]``
    counts the pairing and ``last[p, j]`` takes ``iteration``. ``means``, ``covs``, ``seen`` and
    ``last`` are updated in place (a slot is paired at most once per iteration, so the order is free).
    """
    n_particles, n = assoc.shape
    S = np.empty((3, 3))
    S_inv = np.empty((3, 3))
    CR = np.empty((3, 3))
    K = np.empty((3, 3))
    I_KH = np.empty((3, 3))
    T = np.empty((3, 3))
    new = np.empty((3, 3))
    z_hat = np.empty(3)
    nu = np.empty(3)
    for p in range(n_particles):
        R = rotations[p]
        for i in range(n):
            j = assoc[p, i]
            if j < 0:
                continue
            C = covs[p, j]
            _in_sensor_frame(R, positions[p], means[p, j], z_hat)
            for a in range(3):
                nu[a] = points[i, a] - z_hat[a]
            _measurement_covariance(R, C, Q, CR, S)
            _inverse_and_logdet3(S, S_inv)
            for a in range(3):  # K = C R S^-1
                for b in range(3):
                    K[a, b] = CR[a, 0] * S_inv[0, b] + CR[a, 1] * S_inv[1, b] + CR[a, 2] * S_inv[2, b]
            for a in range(3):
                means[p, j, a] += K[a, 0] * nu[0] + K[a, 1] * nu[1] + K[a, 2] * nu[2]
            for a in range(3):  # I - K R^T
                for b in range(3):
                    I_KH[a, b] = (1.0 if a == b else 0.0) - (K[a, 0] * R[b, 0] + K[a, 1] * R[b, 1] + K[a, 2] * R[b, 2])
            for a in range(3):  # (I - K H) C
                for b in range(3):
                    T[a, b] = I_KH[a, 0] * C[0, b] + I_KH[a, 1] * C[1, b] + I_KH[a, 2] * C[2, b]
            for a in range(3):  # ... (I - K H)^T + K Q K^T
                for b in range(3):
                    total = T[a, 0] * I_KH[b, 0] + T[a, 1] * I_KH[b, 1] + T[a, 2] * I_KH[b, 2]
                    for e in range(3):
                        total += K[a, e] * (Q[e, 0] * K[b, 0] + Q[e, 1] * K[b, 1] + Q[e, 2] * K[b, 2])
                    new[a, b] = total
            for a in range(3):
                for b in range(3):
                    C[a, b] = 0.5 * (new[a, b] + new[b, a])
            seen[p, j] += 1
            last[p, j] = iteration

