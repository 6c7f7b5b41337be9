"""Compiled per-pixel loops of the dense estimator (numba): depth downsampling and smoothing, normals,
colour downsampling, the z-buffer, projective association, and the fusion's gates, merge and cover test.

In numpy each of these is a dozen or more passes over whole images, each writing a temporary of the
image's size; here every pixel is read once and its result written once. Each kernel computes the
same float32 operations in the same order as the numpy expression its docstring gives, so the results
are bit-identical: ``tests/test_dense_kernels.py`` keeps the numpy code each kernel replaced
(``reference_*``) and compares them byte for byte. The 3x3 rotations of whole point sets stay numpy
matrix products outside the kernels (their rounding is BLAS's).

An install builds the kernels ahead of time into the extension module ``_kernels_aot`` (numba's
``pycc``, from the argument types each kernel names; see ``setup.py`` and :mod:`relpoint._aot_kernels`),
so no run pays for compilation and numba is not imported. Without that module each kernel is compiled
on its first call instead (``cache=True`` keeps the machine code for later processes); :func:`prepare`
compiles them ahead of a run.
"""

from __future__ import annotations

import numpy as np

from relpoint._aot_kernels import KernelSet

kernels = KernelSet(__file__, "relpoint.estimators.dense._kernels_aot")
"""This file's kernels: prebuilt at install into ``_kernels_aot`` or compiled on first call."""
kernel = kernels.kernel
SIGNATURES: dict[str, str] = kernels.signatures
"""Argument types of every kernel in numba's notation, by name: what the ahead-of-time build compiles."""
COMPILED_AHEAD = kernels.compiled_ahead
"""Whether the kernels below are the prebuilt machine code (True) or compiled on first call (False)."""
source_digest = kernels.source_digest
prepare = kernels.prepare
"""Compile every public kernel for its declared argument types, or load it from numba's cache
(nothing to do when :data:`COMPILED_AHEAD`); :meth:`DenseFusion.compile` calls this before a run."""


@kernel("f4, f4")
def _maximum(x: float, y: float) -> float:
    """``np.maximum`` of two float32 scalars: NaN if either is NaN."""
    if x >= y or x != x:
        return x
    return y


@kernel("f4[:, ::1], f8, b1, f8, f8")
def downsample_depth(depth: np.ndarray, max_jump: float, noisy: bool, constant: float, quadratic: float) -> np.ndarray:
    """Half-size depth (H//2, W//2) float32 from 2x2 blocks of ``depth`` (H, W) metres: the mean of a
    block's valid (positive) depths, or their nearest where they spread more than ``max_jump`` times it
    (with ``noisy``, more than ``max(max_jump z, constant + quadratic z^2)`` at the nearest depth ``z``,
    0 for a block without depth).

    numpy (``reference_downsample_depth``), with ``a, b, c, d`` the block's
    four depths in row order: ``total = a + b + c + d``; ``count`` the positive ones; ``nearest`` the
    least positive one (inf for none); ``farthest = maximum(maximum(a, b), maximum(c, d))``;
    ``where(farthest - nearest > f32(max_jump) * nearest, nearest, total / maximum(count, 1))``; with
    ``noisy`` the limit is ``maximum(f32(max_jump) * z, f32(constant) + f32(quadratic) * z * z)``.
    """
    h, w = depth.shape[0] // 2, depth.shape[1] // 2
    out = np.empty((h, w), dtype=np.float32)
    ratio = np.float32(max_jump)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    inf = np.float32(np.inf)
    for i in range(h):
        for j in range(w):
            a = depth[2 * i, 2 * j]
            b = depth[2 * i, 2 * j + 1]
            c = depth[2 * i + 1, 2 * j]
            d = depth[2 * i + 1, 2 * j + 1]
            total = a + b
            total += c
            total += d
            count = zero
            nearest = inf
            for value in (a, b, c, d):
                if value > 0:
                    count += one
                    nearest = min(nearest, value)
            farthest = _maximum(_maximum(a, b), _maximum(c, d))
            if noisy:
                z = nearest if count > 0 else zero
                limit = _maximum(ratio * z, np.float32(constant) + np.float32(quadratic) * z * z)
            else:
                limit = ratio * nearest
            if farthest - nearest > limit:
                out[i, j] = nearest
            else:
                out[i, j] = total / max(count, one)
    return out


@kernel("f4[:, ::1], f8, b1, f8, f8")
def smooth_depth(depth: np.ndarray, max_jump: float, noisy: bool, constant: float, quadratic: float) -> np.ndarray:
    """Edge-preserving 3x3 mean (H, W) float32 of ``depth`` (H, W) metres: of the neighbours within
    ``max_jump`` times the pixel's depth ``z`` (with ``noisy``, within ``max(max_jump z, constant +
    quadratic z^2)``; nothing is near a pixel without depth).

    numpy (``reference_smooth_depth``): with the image padded by zeros and
    ``limit = f32(max_jump) * depth``, over the nine neighbours ``nb`` in row order
    ``near = abs(nb - depth) < limit``, ``total += nb * near``, ``count += near``; then
    ``where(count > 0, total / maximum(count, 1), 0)``; with ``noisy`` the limit is
    ``maximum(limit, f32(constant) + f32(quadratic) * depth * depth)``, 0 where ``depth <= 0``.
    """
    h, w = depth.shape
    out = np.empty((h, w), dtype=np.float32)
    ratio = np.float32(max_jump)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for i in range(h):
        for j in range(w):
            own = depth[i, j]
            limit = ratio * own
            if noisy:
                limit = _maximum(limit, np.float32(constant) + np.float32(quadratic) * own * own)
                if own <= 0:
                    limit = zero
            total = zero
            count = zero
            for r in range(i - 1, i + 2):
                for c in range(j - 1, j + 2):
                    nb = depth[r, c] if 0 <= r < h and 0 <= c < w else zero
                    near = one if abs(nb - own) < limit else zero
                    total += nb * near
                    count += near
            out[i, j] = total / max(count, one) if count > 0 else zero
    return out


@kernel("f4[:, :, ::1], f4[:, ::1], i8, i8, i8, i8, f4[::1]")
def _side(v: np.ndarray, depth: np.ndarray, i: int, j: int, di: int, dj: int, jumps: np.ndarray) -> int:
    """How many pixels along ``(di, dj)`` from ``(i, j)`` lies the nearest usable neighbour of a (3, H, W)
    vertex map, 0 for none: the first ``k`` (up to ``len(jumps)``) inside the image whose depth ``nb``
    has ``abs(nb - d) < jumps[k - 1] * d``. (Outside the image depth is 0, never usable: ``jumps < 1``.)"""
    h, w = depth.shape
    own = depth[i, j]
    for k in range(1, len(jumps) + 1):
        r = i + k * di
        c = j + k * dj
        if r < 0 or r >= h or c < 0 or c >= w:
            return 0
        if abs(depth[r, c] - own) < jumps[k - 1] * own:
            return k
    return 0


@kernel("f4[:, :, ::1], f4[:, ::1], f4[::1]")
def normals(v: np.ndarray, depth: np.ndarray, jumps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (3, H, W) float32 of a (3, H, W) vertex map and their validity (H, W).

    Along each image axis the tangent joins the nearest usable neighbour on either side (:func:`_side`;
    the pixel itself stands in for a side without one): ``a`` along columns, ``b`` along rows; the
    normal ``n = b x a`` is kept where both tangents exist, the depth is positive, ``|n| > 0`` and
    ``n . v < 0``, and is zero elsewhere. ``jumps[k - 1]`` is the relative depth step a neighbour ``k``
    pixels away may make (float32 ``max_jump * k``, all below 1).

    numpy: ``reference_normals``.
    """
    h, w = depth.shape
    out = np.zeros((3, h, w), dtype=np.float32)
    valid = np.zeros((h, w), dtype=np.bool_)
    one = np.float32(1.0)
    for i in range(h):
        for j in range(w):
            if depth[i, j] == 0:  # no vertex, no tangent: the normal is 0
                continue
            right = _side(v, depth, i, j, 0, 1, jumps)
            left = _side(v, depth, i, j, 0, -1, jumps)
            down = _side(v, depth, i, j, 1, 0, jumps)
            up = _side(v, depth, i, j, -1, 0, jumps)
            a0 = v[0, i, j + right] - v[0, i, j - left]
            a1 = v[1, i, j + right] - v[1, i, j - left]
            a2 = v[2, i, j + right] - v[2, i, j - left]
            b0 = v[0, i + down, j] - v[0, i - up, j]
            b1 = v[1, i + down, j] - v[1, i - up, j]
            b2 = v[2, i + down, j] - v[2, i - up, j]
            nx = b1 * a2 - b2 * a1
            ny = b2 * a0 - b0 * a2
            nz = b0 * a1 - b1 * a0
            norm2 = nx * nx + ny * ny + nz * nz
            facing = nx * v[0, i, j] + ny * v[1, i, j] + nz * v[2, i, j]
            ok = (right > 0 or left > 0) and (down > 0 or up > 0) and depth[i, j] > 0 and norm2 > 0 and facing < 0
            if ok:
                scale = one / np.sqrt(norm2)
                out[0, i, j] = nx * scale
                out[1, i, j] = ny * scale
                out[2, i, j] = nz * scale
                valid[i, j] = True
            else:  # as numpy's n * 0: NaN stays NaN
                out[0, i, j] = nx * np.float32(0.0)
                out[1, i, j] = ny * np.float32(0.0)
                out[2, i, j] = nz * np.float32(0.0)
    return out, valid


@kernel("u1[:, :, ::1], i8")
def downsample_color(color: np.ndarray, factor: int) -> np.ndarray:
    """Mean of each ``factor x factor`` block of an (H, W, 3) uint8 image, rounded half up:
    (H // factor, W // factor, 3) uint8.

    numpy (``reference_downsample_color``): uint16 block sums ``total``,
    then ``(total + n // 2) // n`` with ``n = factor ** 2``."""
    h, w = color.shape[0] // factor, color.shape[1] // factor
    out = np.empty((h, w, 3), dtype=np.uint8)
    total = np.empty((w, 3), dtype=np.int64)
    n = factor * factor
    for i in range(h):
        total[:] = n // 2
        for r in range(i * factor, i * factor + factor):
            row = color[r]
            for j in range(w):
                for c in range(j * factor, j * factor + factor):
                    total[j, 0] += row[c, 0]
                    total[j, 1] += row[c, 1]
                    total[j, 2] += row[c, 2]
        for j in range(w):
            out[i, j, 0] = total[j, 0] // n
            out[i, j, 1] = total[j, 1] // n
            out[i, j, 2] = total[j, 2] // n
    return out


# -- point-based fusion (relpoint.estimators.dense.fusion.PointMap.fuse) ------------------------------


@kernel("f4, f8, f8")
def _squared_gate(depth: float, threshold: float, quadratic: float) -> float:
    """The squared merge distance (m^2, float32) at camera depth ``depth`` (m):
    ``(f32(threshold) + f32(quadratic) * depth * depth) ** 2``."""
    limit = np.float32(threshold) + np.float32(quadratic) * depth * depth
    return limit * limit


@kernel("f4[:, ::1], f4[:, ::1], i8, f4[:, ::1], f4[:, ::1], i8, f4, f4")
def _passes(
    q: np.ndarray, n_q: np.ndarray, k: int, positions: np.ndarray, normals: np.ndarray, j: int, limit: float, cos: float
) -> bool:
    """Whether map point ``j`` lies within ``sqrt(limit)`` of frame point ``k`` (columns of (3, n) ``q``,
    ``n_q``) and their normals' cosine exceeds ``cos`` (float32, sums in axis order)."""
    d0 = q[0, k] - positions[0, j]
    d1 = q[1, k] - positions[1, j]
    d2 = q[2, k] - positions[2, j]
    if not d0 * d0 + d1 * d1 + d2 * d2 < limit:
        return False
    return n_q[0, k] * normals[0, j] + n_q[1, k] * normals[1, j] + n_q[2, k] * normals[2, j] > cos


@kernel(
    "i8[::1], f4[:, ::1], f4[:, ::1], f4[::1], i8[::1], i8[::1], "
    "f4[:, ::1], f4[:, ::1], f4[:, ::1], f4[::1], f4[::1], u1[:, ::1], f4[::1], f8, f8, f8, f8"
)
def fuse_gates_and_merge(
    pixels: np.ndarray,
    q: np.ndarray,
    n_q: np.ndarray,
    depth: np.ndarray,
    filled: np.ndarray,
    ids: np.ndarray,
    positions: np.ndarray,
    normals: np.ndarray,
    colors: np.ndarray,
    weights: np.ndarray,
    color_weights: np.ndarray,
    rgb: np.ndarray,
    confidence: np.ndarray,
    distance_threshold: float,
    distance_quadratic: float,
    normal_cos: float,
    max_weight: float,
) -> tuple[np.ndarray, int]:
    """The filter and merge of point-based fusion, the map updated in place: which frame points passed
    the gates (n,) bool, and how many were merged.

    ``pixels`` (n,) are the frame's valid pixels; ``q``, ``n_q`` (3, n) their vertices and normals in
    ``world`` and ``depth`` (n,) their camera depths (m); ``filled`` and ``ids`` (H*W,) the map point
    rendered next to (for pinholes) or at each pixel, -1 for none. A point passes where its ``filled``
    map point is within the gate (:func:`_squared_gate`) and faces alike (:func:`_passes`), judged on the
    map as it was before this frame. A passing point whose map point is rendered at its own pixel is
    merged into it, with ``a = confidence[pixel]`` (1 if ``confidence`` is empty):
    ``p <- (w p + a q) / (w + a)``; ``n`` likewise, renormalised; the colour likewise with its own
    weight, from ``rgb`` (H*W, 3) uint8 unless it is empty; ``w <- min(w + a, max_weight)``.

    numpy: the filter and merge of ``ReferencePointMap.fuse``.
    """
    n = len(pixels)
    cos = np.float32(normal_cos)
    passed = np.zeros(n, dtype=np.bool_)
    for k in range(n):
        j = filled[pixels[k]]
        if j >= 0:
            passed[k] = _passes(
                q, n_q, k, positions, normals, j, _squared_gate(depth[k], distance_threshold, distance_quadratic), cos
            )
    one = np.float32(1.0)
    cap = np.float32(max_weight)
    tiny = np.float32(1e-12)
    merged = 0
    for k in range(n):
        pixel = pixels[k]
        j = ids[pixel]
        if not passed[k] or j < 0:
            continue
        merged += 1
        w = weights[j]
        alpha = confidence[pixel] if len(confidence) else one
        w1 = w + alpha
        inverse = one / w1
        a = alpha * inverse
        b = w * inverse
        for axis in range(3):
            positions[axis, j] = positions[axis, j] * b + q[axis, k] * a
        m0 = normals[0, j] * b + n_q[0, k] * a
        m1 = normals[1, j] * b + n_q[1, k] * a
        m2 = normals[2, j] * b + n_q[2, k] * a
        norm = max(np.sqrt(m0 * m0 + m1 * m1 + m2 * m2), tiny)
        normals[0, j] = m0 / norm
        normals[1, j] = m1 / norm
        normals[2, j] = m2 / norm
        if len(rgb):
            cw = color_weights[j]
            cw1 = cw + alpha
            for channel in range(3):
                colors[channel, j] = (colors[channel, j] * cw + np.float32(rgb[pixel, channel]) * alpha) / cw1
            color_weights[j] = min(cw1, cap)
        weights[j] = min(w1, cap)
    return passed, merged


@kernel("i8[::1], i8[::1], f4[:, ::1], f4[:, ::1], f4[::1], i8[:, ::1], f4[:, ::1], f4[:, ::1], f8, f8, f8")
def covered(
    failed: np.ndarray,
    pixels: np.ndarray,
    q: np.ndarray,
    n_q: np.ndarray,
    depth: np.ndarray,
    index_map: np.ndarray,
    positions: np.ndarray,
    normals: np.ndarray,
    distance_threshold: float,
    distance_quadratic: float,
    normal_cos: float,
) -> np.ndarray:
    """For each frame point ``failed[i]`` (an index into ``pixels``, ``q``, ``n_q``, ``depth`` as in
    :func:`fuse_gates_and_merge`), whether a map point rendered (``index_map`` (H, W), -1 for none) at
    one of its pixel's 8 neighbours passes the same gates, on the map as merged: (len(failed),) bool.

    numpy: ``ReferencePointMap._covered`` (neighbours in its order)."""
    h, w = index_map.shape
    cos = np.float32(normal_cos)
    out = np.zeros(len(failed), dtype=np.bool_)
    rows = (0, 0, 1, -1, 1, 1, -1, -1)
    cols = (1, -1, 0, 0, 1, -1, 1, -1)
    for i in range(len(failed)):
        k = failed[i]
        row, col = divmod(pixels[k], w)
        limit = _squared_gate(depth[k], distance_threshold, distance_quadratic)
        for neighbour in range(8):
            r = row + rows[neighbour]
            c = col + cols[neighbour]
            if r < 0 or r >= h or c < 0 or c >= w:
                continue
            j = index_map[r, c]
            if j >= 0 and _passes(q, n_q, k, positions, normals, j, limit, cos):
                out[i] = True
                break
    return out


# -- projection: the z-buffer and projective association (fusion.PointMap.render, icp.associate) -----


@kernel("f4, f4")
def _minimum(x: float, y: float) -> float:
    """``np.minimum`` of two float32 scalars: NaN if either is NaN."""
    if x <= y or x != x:
        return x
    return y


@kernel("f4, f4, f4, f8, f8, f8, f8, i8, i8")
def _pixel(x: float, y: float, z: float, fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> int:
    """Row-major index of the pixel nearest to a camera-frame point (float32 metres), -1 when it falls
    outside the ``width`` x ``height`` image or lies at or behind the camera (``z <= 1e-6``).

    ``cx``, ``cy`` are the principal point plus 0.5 (pixel centres), so truncation finds the nearest
    pixel. numpy: ``reference_project`` (float32 throughout)."""
    if not z > np.float32(1e-6):
        return -1
    inverse = np.float32(1.0) / z
    u = x * inverse
    u *= np.float32(fx)
    u += np.float32(cx)
    v = y * inverse
    v *= np.float32(fy)
    v += np.float32(cy)
    if not (u >= 0 and u < np.float32(width) and v >= 0 and v < np.float32(height)):
        return -1
    return np.int64(v) * width + np.int64(u)


@kernel("f4[:, ::1], f8, f8, f8, f8, i8, i8")
def render(p_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> np.ndarray:
    """Index (H*W,) of the nearest of the points ``p_cam`` (3, N) (camera frame, float32 metres) projecting
    into each pixel (:func:`_pixel`), -1 for none; among points at the same depth the last wins.

    numpy: ``reference_render`` (``np.minimum.at`` over the depths, then each point whose depth is at
    most its pixel's, in order)."""
    n = p_cam.shape[1]
    pixels = np.empty(n, dtype=np.int64)
    zbuffer = np.full(width * height, np.inf, dtype=np.float32)
    for i in range(n):
        pixel = _pixel(p_cam[0, i], p_cam[1, i], p_cam[2, i], fx, fy, cx, cy, width, height)
        pixels[i] = pixel
        if pixel >= 0:
            zbuffer[pixel] = _minimum(zbuffer[pixel], p_cam[2, i])
    index = np.full(width * height, -1, dtype=np.int64)
    for i in range(n):
        pixel = pixels[i]
        if pixel >= 0 and p_cam[2, i] <= zbuffer[pixel]:
            index[pixel] = i
    return index


@kernel("f4[:, ::1], f4[:, ::1], f4[:, ::1], f8, f8, f8, f8, i8, i8, f8, b1, f8")
def associate(
    p_cam: np.ndarray,
    n_p: np.ndarray,
    planes: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    max_distance_squared: float,
    check_normals: bool,
    normal_cos: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Projective association of map points ``p_cam`` (3, N) with normals ``n_p`` (3, N) (camera frame,
    float32) with a frame level's ``planes`` (7, H*W): each point is paired with the vertex of the
    pixel it projects to (:func:`_pixel`) where that pixel is valid, the squared distance is below
    ``f32(max_distance_squared)`` and, if ``check_normals``, the normals' cosine exceeds ``f32(normal_cos)``.

    Returns the paired points' indices (M,) and pixels (M,), and (3, M) float32 columns of their
    ``p_cam``, the pixels' vertices and normals, and their ``n_p``. numpy: ``reference_associate``
    after its transforms."""
    n = p_cam.shape[1]
    limit = np.float32(max_distance_squared)
    cos = np.float32(normal_cos)
    pixels = np.empty(n, dtype=np.int64)
    count = 0
    for i in range(n):
        pixel = _pixel(p_cam[0, i], p_cam[1, i], p_cam[2, i], fx, fy, cx, cy, width, height)
        pixels[i] = -1
        if pixel < 0 or not planes[6, pixel] > 0:
            continue
        d0 = p_cam[0, i] - planes[0, pixel]
        d1 = p_cam[1, i] - planes[1, pixel]
        d2 = p_cam[2, i] - planes[2, pixel]
        if not d0 * d0 + d1 * d1 + d2 * d2 < limit:
            continue
        if (
            check_normals
            and not n_p[0, i] * planes[3, pixel] + n_p[1, i] * planes[4, pixel] + n_p[2, i] * planes[5, pixel] > cos
        ):
            continue
        pixels[i] = pixel
        count += 1
    index = np.empty(count, dtype=np.int64)
    paired = np.empty(count, dtype=np.int64)
    source = np.empty((3, count), dtype=np.float32)
    target = np.empty((3, count), dtype=np.float32)
    normals = np.empty((3, count), dtype=np.float32)
    map_normals = np.empty((3, count), dtype=np.float32)
    m = 0
    for i in range(n):
        pixel = pixels[i]
        if pixel < 0:
            continue
        index[m] = i
        paired[m] = pixel
        for axis in range(3):
            source[axis, m] = p_cam[axis, i]
            target[axis, m] = planes[axis, pixel]
            normals[axis, m] = planes[3 + axis, pixel]
            map_normals[axis, m] = n_p[axis, i]
        m += 1
    return index, paired, source, target, normals, map_normals
