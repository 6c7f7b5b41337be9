"""The dense estimator's compiled per-pixel loops equal their numpy expressions bit for bit.

Each reference below is the numpy code the kernel replaced; the kernels are run on random depth
images with holes, depth steps and far values, and on a real 7-Scenes frame when the data is present.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from relpoint.estimators.dense.estimator import _downsample_color
from relpoint.estimators.dense.fusion import FusionStats, PointMap, _fill_from_neighbours
from relpoint.estimators.dense.icp import Correspondences, associate
from relpoint.estimators.dense.maps import (
    NORMAL_REACH,
    Level,
    _normals,
    _vertices,
    build_pyramid,
    downsample_depth,
    smooth_depth,
)
from relpoint.geometry import FloatArray, transform_soa32
from relpoint.types import Intrinsics

F32 = npt.NDArray[np.float32]
I64 = npt.NDArray[np.int64]


def assert_bitwise_equal(actual: np.ndarray, expected: np.ndarray) -> None:
    """Equal shapes, dtypes and bytes (so -0.0 differs from 0.0 and NaN payloads must match)."""
    assert actual.shape == expected.shape and actual.dtype == expected.dtype
    assert actual.tobytes() == expected.tobytes()


KITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes-redkitchen-0000-0399"


def _reference_edge_limit(depth: np.ndarray, max_jump: float, noise: tuple[float, float] | None) -> np.ndarray:
    limit = np.float32(max_jump) * depth
    if noise is not None:
        constant, quadratic = noise
        np.maximum(limit, np.float32(constant) + np.float32(quadratic) * depth * depth, out=limit)
    return limit


def reference_downsample_depth(
    depth: np.ndarray, max_jump: float = 0.03, noise: tuple[float, float] | None = None
) -> np.ndarray:
    h, w = depth.shape[0] // 2 * 2, depth.shape[1] // 2 * 2
    depth = np.asarray(depth, dtype=np.float32)
    a, b, c, d = (depth[r:h:2, s:w:2] for r in (0, 1) for s in (0, 1))
    total = a + b
    total += c
    total += d
    count = (a > 0).astype(np.float32)
    count += b > 0
    count += c > 0
    count += d > 0
    inf = np.float32(np.inf)
    nearest = np.minimum(np.where(a > 0, a, inf), np.where(b > 0, b, inf))
    np.minimum(nearest, np.where(c > 0, c, inf), out=nearest)
    np.minimum(nearest, np.where(d > 0, d, inf), out=nearest)
    farthest = np.maximum(np.maximum(a, b), np.maximum(c, d))
    mean = total / np.maximum(count, np.float32(1.0))
    if noise is None:
        jump = farthest - nearest > np.float32(max_jump) * nearest
    else:
        jump = farthest - nearest > _reference_edge_limit(
            np.where(count > 0, nearest, np.float32(0.0)), max_jump, noise
        )
    return np.where(jump, nearest, mean).astype(np.float32, copy=False)


def reference_smooth_depth(
    depth: np.ndarray, max_jump: float = 0.03, noise: tuple[float, float] | None = None
) -> np.ndarray:
    h, w = depth.shape
    padded = np.zeros((h + 2, w + 2), dtype=np.float32)
    padded[1:-1, 1:-1] = depth
    limit = _reference_edge_limit(depth, max_jump, noise)
    if noise is not None:
        limit[depth <= 0] = 0
    total = np.zeros_like(depth)
    count = np.zeros_like(depth)
    near = np.empty(depth.shape, dtype=bool)
    diff = np.empty_like(depth)
    for dr in (0, 1, 2):
        for dc in (0, 1, 2):
            nb = padded[dr : dr + h, dc : dc + w]
            np.subtract(nb, depth, out=diff)
            np.abs(diff, out=diff)
            np.less(diff, limit, out=near)
            total += nb * near
            count += near
    return np.where(count > 0, total / np.maximum(count, np.float32(1.0)), np.float32(0.0)).astype(np.float32)


def _reference_tangent(v, depth, padded_v, padded_d, dr, dc, max_jump):
    h, w = depth.shape
    r = NORMAL_REACH
    sides = []
    for sign in (1, -1):
        found = np.zeros((h, w), dtype=bool)
        point = np.zeros((3, h, w), dtype=np.float32)
        for k in range(1, r + 1):
            row, col = r + sign * k * dr, r + sign * k * dc
            nb = padded_d[row : row + h, col : col + w]
            near = np.abs(nb - depth) < np.float32(max_jump * k) * depth
            near &= ~found
            np.copyto(point, padded_v[:, row : row + h, col : col + w], where=near)
            found |= near
        sides.append((point, found))
    (after, has_after), (before, has_before) = sides
    np.copyto(after, v, where=~has_after)
    np.copyto(before, v, where=~has_before)
    return after - before, has_after | has_before


def reference_normals(v: np.ndarray, depth: np.ndarray, max_jump: float) -> tuple[np.ndarray, np.ndarray]:
    h, w = depth.shape
    r = NORMAL_REACH
    padded_d = np.zeros((h + 2 * r, w + 2 * r), dtype=np.float32)
    padded_d[r:-r, r:-r] = depth
    padded_v = np.zeros((3, h + 2 * r, w + 2 * r), dtype=np.float32)
    padded_v[:, r:-r, r:-r] = v
    a, ok = _reference_tangent(v, depth, padded_v, padded_d, 0, 1, max_jump)
    b, ok_b = _reference_tangent(v, depth, padded_v, padded_d, 1, 0, max_jump)
    ok &= ok_b
    ok &= depth > 0
    nx = b[1] * a[2] - b[2] * a[1]
    ny = b[2] * a[0] - b[0] * a[2]
    nz = b[0] * a[1] - b[1] * a[0]
    norm2 = nx * nx + ny * ny + nz * nz
    ok &= norm2 > 0
    facing = nx * v[0] + ny * v[1] + nz * v[2]
    ok &= facing < 0
    scale = np.zeros_like(norm2)
    np.divide(np.float32(1.0), np.sqrt(norm2, where=ok, out=np.ones_like(norm2)), out=scale, where=ok)
    normals = np.empty((3, h, w), dtype=np.float32)
    np.multiply(nx, scale, out=normals[0])
    np.multiply(ny, scale, out=normals[1])
    np.multiply(nz, scale, out=normals[2])
    return normals, ok


def reference_downsample_color(color: np.ndarray, factor: int) -> np.ndarray:
    h, w = color.shape[0] // factor * factor, color.shape[1] // factor * factor
    total = np.zeros((h // factor, w // factor, 3), dtype=np.uint16)
    for r in range(factor):
        for c in range(factor):
            total += color[r:h:factor, c:w:factor]
    n = factor * factor
    return ((total + n // 2) // n).astype(np.uint8)


class ReferencePointMap(PointMap):
    """:class:`PointMap` with the numpy fusion the kernels replaced."""

    def fuse(
        self,
        T_world_camera: FloatArray,
        level: Level,
        colors: npt.NDArray[np.uint8] | None,
        index_map: I64,
        distance_threshold: float,
        normal_cos_threshold: float,
        frame_index: int,
        max_weight: float = np.inf,
        distance_quadratic: float = 0.0,
        confidence: F32 | None = None,
    ) -> tuple[I64, FusionStats]:
        """The numpy filter, merge and add that the compiled kernels replaced."""
        R = T_world_camera[:3, :3].astype(np.float32)
        t = T_world_camera[:3, 3].astype(np.float32)[:, None]
        cos = np.float32(normal_cos_threshold)
        planes = level.planes
        h, w_img = index_map.shape
        ids = index_map.reshape(-1)
        filled = _fill_from_neighbours(index_map).reshape(-1)

        # Filter: the map point rendered at (or, for pinholes, next to) each valid pixel, within the gates.
        pixels = np.flatnonzero(planes[6] > 0)
        frame = np.take(planes[:6], pixels, axis=1)
        q = R @ frame[:3] + t
        n_q = R @ frame[3:6]
        j = filled[pixels]
        has = j >= 0
        jj = np.where(has, j, 0)
        p = np.take(self._positions, jj, axis=1)
        n_p = np.take(self._normals, jj, axis=1)
        diff = q - p
        depth = frame[2]
        limit = np.float32(distance_threshold) + np.float32(distance_quadratic) * depth * depth
        limit *= limit
        diff *= diff
        ok = diff.sum(axis=0) < limit
        ok &= (n_q * n_p).sum(axis=0) > cos
        ok &= has
        direct = ids[pixels] >= 0
        sel = np.flatnonzero(ok & direct)
        j = j[sel]
        merged_pixels = pixels[sel]

        # Merge: weighted averages; normals rotated only, then renormalised.
        w = self._weights[j]
        alpha = np.float32(1.0) if confidence is None else confidence[merged_pixels]
        w1 = w + alpha
        inv = np.float32(1.0) / w1
        a = alpha * inv
        b = w * inv
        self._positions[:, j] = np.take(p, sel, axis=1) * b + np.take(q, sel, axis=1) * a
        n = np.take(n_p, sel, axis=1) * b + np.take(n_q, sel, axis=1) * a
        n /= np.maximum(np.sqrt((n * n).sum(axis=0)), np.float32(1e-12))
        self._normals[:, j] = n
        rgb = None if colors is None else colors.reshape(-1, 3).T.astype(np.float32)  # (3, H*W)
        if rgb is not None:
            cw = self._color_weights[j]
            cw1 = cw + alpha
            self._colors[:, j] = (
                np.take(self._colors, j, axis=1) * cw + np.take(rgb, merged_pixels, axis=1) * alpha
            ) / cw1
            self._color_weights[j] = np.minimum(cw1, np.float32(max_weight))
        self._weights[j] = np.minimum(w1, np.float32(max_weight))

        # Add: valid pixels neither merged nor covered by a point rendered next to them.
        failed = np.flatnonzero(~ok)
        covered = self._covered(
            pixels[failed], index_map, np.take(q, failed, axis=1), np.take(n_q, failed, axis=1),
            depth[failed], distance_threshold, distance_quadratic, cos,
        )  # fmt: skip
        keep = failed[~covered]
        added_pixels = pixels[keep]
        rgb_new = (
            np.take(rgb, added_pixels, axis=1) if rgb is not None else np.zeros((3, len(added_pixels)), np.float32)
        )
        new_ids = self.append(np.take(q, keep, axis=1), np.take(n_q, keep, axis=1), rgb_new, frame_index)
        if confidence is not None:
            self._weights[new_ids] = confidence[added_pixels]
        if rgb is not None:
            self._color_weights[new_ids] = self._weights[new_ids]
        after = ids.copy()
        after[added_pixels] = new_ids
        return after.reshape(h, w_img), FusionStats(int(len(j)), int(len(new_ids)))

    def _covered(
        self,
        pixels: I64,
        index_map: I64,
        q: F32,
        n_q: F32,
        depth: F32,
        distance_threshold: float,
        distance_quadratic: float,
        cos: np.float32,
    ) -> npt.NDArray[np.bool_]:
        """Whether a map point rendered in the 3x3 neighbourhood of each pixel passes the fusion gates."""
        h, w = index_map.shape
        covered = np.zeros(len(pixels), dtype=bool)
        if len(pixels) == 0:
            return covered
        padded = np.full((h + 2, w + 2), -1, dtype=np.int64)
        padded[1:-1, 1:-1] = index_map
        flat = padded.reshape(-1)
        row, col = np.divmod(pixels, w)
        base = (row + 1) * (w + 2) + col + 1
        limit = (np.float32(distance_threshold) + np.float32(distance_quadratic) * depth * depth) ** 2
        for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1)):
            open_ = np.flatnonzero(~covered)
            j = flat[base[open_] + dr * (w + 2) + dc]
            has = j >= 0
            test = open_[has]
            j = j[has]
            diff = np.take(q, test, axis=1) - np.take(self._positions, j, axis=1)
            ok = ((diff * diff).sum(axis=0) < limit[test]) & (
                (np.take(n_q, test, axis=1) * np.take(self._normals, j, axis=1)).sum(axis=0) > cos
            )
            covered[test[ok]] = True
        return covered


def reference_project(points_cam: F32, level: Level) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
    """Nearest pixel (row-major index) of camera-frame points (3, N) in ``level``, and whether it is inside.

    Points at or behind the camera (z <= 0) are outside; the pixel of a point outside is 0.
    """
    k = level.intrinsics
    x, y, z = points_cam
    inv = np.float32(1.0) / np.where(z > 1e-6, z, np.float32(-1.0))  # negative: fails the u >= 0 test below
    u = x * inv
    u *= np.float32(k.fx)
    u += np.float32(k.cx + 0.5)
    v = y * inv
    v *= np.float32(k.fy)
    v += np.float32(k.cy + 0.5)
    inside = (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height) & (z > 1e-6)
    # floor(c + 0.5) is the nearest pixel; u, v are non-negative inside, so truncation is floor.
    pixel = v.astype(np.int64)
    pixel *= k.width
    pixel += u.astype(np.int64)
    pixel[~inside] = 0
    return pixel, inside


def reference_associate(
    T_camera_world: FloatArray,
    points: F32,
    normals: F32,
    level: Level,
    distance_threshold: float,
    normal_cos_threshold: float,
) -> Correspondences:
    """Projective data association of map points with a frame level (section 2.1).

    Parameters
    ----------
    T_camera_world: (4, 4) current estimate of the camera pose's inverse.
    points: (3, N) float32 map points in ``world``.
    normals: (3, N) float32 map normals in ``world``.
    level: the frame's pyramid level (target).
    distance_threshold: largest ``|p' - q|`` of a pair, metres.
    normal_cos_threshold: smallest cosine of the angle between the map normal (rotated into the camera)
        and the frame normal; -1 disables the check.
    """
    p_cam = transform_soa32(T_camera_world, points)
    pixel, inside = reference_project(p_cam, level)
    # Pixels outside the image point at pixel 0; the validity plane rejects them below.
    gathered = np.take(level.planes, pixel, axis=1)
    ok = inside & (gathered[6] > 0)
    q = gathered[:3]
    n_q = gathered[3:6]
    diff = p_cam - q
    ok &= (diff * diff).sum(axis=0) < np.float32(distance_threshold**2)
    n_p = T_camera_world[:3, :3].astype(np.float32) @ normals
    if normal_cos_threshold > -1.0:
        ok &= (n_p * n_q).sum(axis=0) > np.float32(normal_cos_threshold)
    idx = np.flatnonzero(ok)
    return Correspondences(
        np.take(p_cam, idx, axis=1).T,
        np.take(q, idx, axis=1).T,
        np.take(n_q, idx, axis=1).T,
        idx,
        pixel[idx],
        np.take(n_p, idx, axis=1).T,
    )


def reference_render(point_map: PointMap, T_camera_world: FloatArray, level: Level) -> I64:
    k = level.intrinsics
    index = np.full(k.height * k.width, -1, dtype=np.int64)
    if point_map.size == 0:
        return index.reshape(k.height, k.width)
    p_cam = transform_soa32(T_camera_world, point_map.positions)
    pixel, inside = reference_project(p_cam, level)
    ids = np.flatnonzero(inside)
    pixel = pixel[ids]
    z = p_cam[2, ids]
    zbuffer = np.full(k.height * k.width, np.inf, dtype=np.float32)
    np.minimum.at(zbuffer, pixel, z)
    nearest = np.flatnonzero(z <= zbuffer[pixel])
    index[pixel[nearest]] = ids[nearest]
    return index.reshape(k.height, k.width)


def _random_depth(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A depth image (metres) of smooth surfaces with steps, holes, and a few far and tiny depths."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    depth = (1.5 + 0.01 * rows + 0.004 * cols + rng.normal(0.0, 0.004, (h, w))).astype(np.float32)
    depth[:, w // 3 :] += np.float32(0.4)  # a depth step
    depth[h // 2 :, : w // 4] *= np.float32(1.02)  # a step inside the jump threshold
    depth[rng.random((h, w)) < 0.15] = 0.0  # holes
    depth[rng.random((h, w)) < 0.01] = np.float32(60.0)  # far outliers
    depth[rng.random((h, w)) < 0.01] = np.float32(1e-3)
    return depth


def _kitchen_depth() -> np.ndarray:
    from PIL import Image

    with Image.open(KITCHEN / "frame-000000.depth.png") as image:
        raw = np.asarray(image).astype(np.float32)
    raw[raw >= 65535] = 0
    return raw * np.float32(1e-3)


def _depths() -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    depths = [_random_depth(rng, 48, 64), _random_depth(rng, 37, 51)]  # odd sizes too
    if KITCHEN.exists():
        depths.append(_kitchen_depth())
    return depths


@pytest.mark.parametrize("noise", [None, (0.004, 0.008), (0.02, 0.02), (0.0, 0.0)])
@pytest.mark.parametrize("max_jump", [0.03, 0.2])
def test_depth_downsampling_and_smoothing_equal_numpy_bit_for_bit(
    max_jump: float, noise: tuple[float, float] | None
) -> None:
    for depth in _depths():
        expected = reference_downsample_depth(depth, max_jump, noise)
        assert_bitwise_equal(downsample_depth(depth, max_jump, noise), expected)
        assert_bitwise_equal(smooth_depth(depth, max_jump, noise), reference_smooth_depth(depth, max_jump, noise))


@pytest.mark.parametrize("max_jump", [0.05, 0.3])
def test_normals_equal_numpy_bit_for_bit(max_jump: float) -> None:
    for depth in _depths():
        h, w = depth.shape
        intrinsics = Intrinsics(w, h, 0.9 * w, 0.9 * w, (w - 1) / 2, (h - 1) / 2)
        vertices = _vertices(depth, intrinsics)
        normals, valid = _normals(vertices, depth, max_jump)
        expected, expected_valid = reference_normals(vertices, depth, max_jump)
        assert_bitwise_equal(valid, expected_valid)
        assert_bitwise_equal(normals, expected)
        assert 0.3 < valid.mean() < 1.0  # the images exercise both outcomes


@pytest.mark.parametrize("factor", [1, 2, 4])
def test_colour_downsampling_equals_numpy(factor: int) -> None:
    color = np.random.default_rng(3).integers(0, 256, (30, 42, 3), dtype=np.uint8)
    assert_bitwise_equal(_downsample_color(color, factor), reference_downsample_color(color, factor))


@pytest.mark.parametrize("with_colour_and_confidence", [False, True])
def test_fusion_equals_numpy_bit_for_bit(with_colour_and_confidence: bool) -> None:
    """Frames of a turning camera over random depth fused into the compiled and the numpy map: every
    point's position, normal, colour, weight and creation frame, and the index maps, equal exactly."""
    rng = np.random.default_rng(11)
    h, w = 60, 80
    intrinsics = Intrinsics(w, h, 70.0, 70.0, (w - 1) / 2, (h - 1) / 2)
    maps = PointMap(capacity=64), ReferencePointMap(capacity=64)
    for frame_index in range(6):
        level = build_pyramid(_random_depth(rng, h, w), intrinsics, 1, smooth=True)[0]
        angle = 0.01 * frame_index
        T = np.eye(4)
        T[:3, :3] = [[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]]
        T[:3, 3] = [0.005 * frame_index, 0.0, 0.0]
        colors = rng.integers(0, 256, (h, w, 3), dtype=np.uint8) if with_colour_and_confidence else None
        confidence = rng.uniform(0.2, 1.0, h * w).astype(np.float32) if with_colour_and_confidence else None
        results = []
        for point_map in maps:
            index_map = point_map.render(np.linalg.inv(T), level)
            results.append(
                point_map.fuse(
                    T,
                    level,
                    colors,
                    index_map,
                    0.02,
                    0.9,
                    frame_index,
                    max_weight=4.0,
                    distance_quadratic=0.003,
                    confidence=confidence,
                )
            )
        (index, stats), (expected_index, expected_stats) = results
        assert_bitwise_equal(index, expected_index)
        assert stats == expected_stats
        if frame_index:
            assert stats.merged > 0 and stats.added > 0  # both paths run
    ours, reference = maps
    assert len(ours) == len(reference)
    for name in ("positions", "normals", "colors", "weights", "color_weights", "created"):
        assert_bitwise_equal(getattr(ours, name), getattr(reference, name))


@pytest.mark.parametrize("normal_cos", [-1.0, 0.8])
def test_rendering_and_association_equal_numpy_bit_for_bit(normal_cos: float) -> None:
    """A map fused from one frame, rendered and associated from nearby poses (some points behind the
    camera or outside the image): index maps and every pair equal the numpy code's exactly."""
    rng = np.random.default_rng(5)
    h, w = 60, 80
    intrinsics = Intrinsics(w, h, 70.0, 70.0, 41.3, 28.9)
    level = build_pyramid(_random_depth(rng, h, w), intrinsics, 1, smooth=True)[0]
    point_map = PointMap(capacity=64)
    point_map.fuse(np.eye(4), level, None, point_map.render(np.eye(4), level), 0.02, 0.9, 0)
    assert len(point_map) > 1000
    for angle, shift in ((0.0, 0.0), (0.05, 0.02), (0.4, -0.3), (1.6, 0.0), (3.1, 0.1)):
        T = np.eye(4)
        T[:3, :3] = [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = [shift, 0.0, shift]
        T_camera_world = np.linalg.inv(T)
        assert_bitwise_equal(
            point_map.render(T_camera_world, level), reference_render(point_map, T_camera_world, level)
        )
        ours = associate(T_camera_world, point_map.positions, point_map.normals, level, 0.05, normal_cos)
        expected = reference_associate(T_camera_world, point_map.positions, point_map.normals, level, 0.05, normal_cos)
        for name in ("source", "target", "normals", "index", "pixels", "map_normals"):
            assert_bitwise_equal(
                np.ascontiguousarray(getattr(ours, name)), np.ascontiguousarray(getattr(expected, name))
            )
        if angle == 0.0:
            assert len(ours) > 1000  # pairs are found, so the comparison is not vacuous
