"""Vertex and normal maps from a depth image, with a downsampling pyramid (section 2 of the dense-SLAM paper).

A *vertex map* holds, per pixel, the 3D point ``v = d K^-1 [u, v, 1]`` in the camera optical frame (x right,
y down, z forward, metres); a *normal map* the unit surface normal there, from the cross product of the
central differences of the vertex map, facing the camera. Pixels without a usable measurement are marked
by ``valid`` (their vertex/normal entries are zero). Everything is numpy-vectorised and kept channel-first
(``(3, H, W)``) internally so that every arithmetic operation runs over contiguous memory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.types import Intrinsics

F32 = npt.NDArray[np.float32]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class Level:
    """One pyramid level of a frame.

    Attributes
    ----------
    intrinsics: pinhole intrinsics of this level (pixels of this level).
    depth: (H, W) float32 metres, 0 = no measurement.
    planes: (7, H*W) float32 rows x, y, z, nx, ny, nz of every pixel (camera frame, metres; unit normals
        facing the camera, 0 where invalid) and 1/0 validity (row-major pixels; fast gathers).
    valid: (H, W) bool, pixel has both a vertex and a normal.
    """

    intrinsics: Intrinsics
    depth: F32
    planes: F32
    valid: BoolArray

    @property
    def vertices(self) -> F32:
        """(H, W, 3) float32 vertex map, camera frame, metres (a view of :attr:`planes`)."""
        h, w = self.depth.shape
        return np.moveaxis(self.planes[:3].reshape(3, h, w), 0, -1)

    @property
    def normals(self) -> F32:
        """(H, W, 3) float32 unit normals facing the camera, 0 where invalid (a view of :attr:`planes`)."""
        h, w = self.depth.shape
        return np.moveaxis(self.planes[3:6].reshape(3, h, w), 0, -1)


def scaled_intrinsics(intrinsics: Intrinsics, factor: int) -> Intrinsics:
    """Intrinsics of an image downsampled by averaging ``factor x factor`` blocks.

    The centre of block ``(i, j)`` is the full-resolution pixel ``factor * i + (factor - 1) / 2``, so the
    principal point maps as ``(c + 0.5) / factor - 0.5``.
    """
    return Intrinsics(
        intrinsics.width // factor,
        intrinsics.height // factor,
        intrinsics.fx / factor,
        intrinsics.fy / factor,
        (intrinsics.cx + 0.5) / factor - 0.5,
        (intrinsics.cy + 0.5) / factor - 0.5,
    )


def downsample_depth(depth: F32, max_jump: float = 0.03) -> F32:
    """Halve a depth image (H, W) -> (H//2, W//2) by averaging the valid depths of each 2x2 block.

    A block whose valid depths spread more than ``max_jump`` times their minimum (relative; a depth
    discontinuity) takes the nearest depth instead of a mean that would float between two surfaces.
    Blocks without any valid depth are 0.
    """
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
    jump = farthest - nearest > np.float32(max_jump) * nearest  # False where no depth (inf on the right)
    return np.where(jump, nearest, mean).astype(np.float32, copy=False)


def smooth_depth(depth: F32, max_jump: float = 0.03) -> F32:
    """Edge-preserving 3x3 mean of a depth image (a box-kernel bilateral filter, as KinectFusion smooths depth).

    Each valid pixel becomes the mean of the valid pixels of its 3x3 neighbourhood whose depth lies within
    ``max_jump`` (relative) of its own; invalid pixels stay 0. Averaging nine samples reduces the noise
    and the quantisation steps that would otherwise tilt the normals.
    """
    h, w = depth.shape
    padded = np.zeros((h + 2, w + 2), dtype=np.float32)
    padded[1:-1, 1:-1] = depth
    limit = np.float32(max_jump) * depth  # 0 where there is no depth: nothing is "near" then
    total = np.zeros_like(depth)
    count = np.zeros_like(depth)
    near = np.empty(depth.shape, dtype=bool)
    diff = np.empty_like(depth)
    for dr in (0, 1, 2):
        for dc in (0, 1, 2):
            nb = padded[dr : dr + h, dc : dc + w]
            np.subtract(nb, depth, out=diff)
            np.abs(diff, out=diff)
            # A missing neighbour (0) is |0 - d| = d away: never within max_jump * d (max_jump < 1).
            np.less(diff, limit, out=near)
            total += nb * near
            count += near
    return np.where(count > 0, total / np.maximum(count, np.float32(1.0)), np.float32(0.0)).astype(np.float32)


def vertex_map(depth: F32, intrinsics: Intrinsics) -> F32:
    """Back-project a depth image (H, W) metres to an (H, W, 3) vertex map in the camera frame."""
    return np.moveaxis(_vertices(np.asarray(depth, dtype=np.float32), intrinsics), 0, -1)


def _vertices(depth: F32, intrinsics: Intrinsics) -> F32:
    h, w = depth.shape
    x = (np.arange(w, dtype=np.float32) - np.float32(intrinsics.cx)) / np.float32(intrinsics.fx)
    y = (np.arange(h, dtype=np.float32) - np.float32(intrinsics.cy)) / np.float32(intrinsics.fy)
    out = np.empty((3, h, w), dtype=np.float32)
    np.multiply(depth, x[None, :], out=out[0])
    np.multiply(depth, y[:, None], out=out[1])
    out[2] = depth
    return out


def normal_map(vertices: F32, depth: F32, max_jump: float = 0.05) -> tuple[F32, BoolArray]:
    """Unit normals (H, W, 3) from central differences of a vertex map (H, W, 3), and their validity (H, W).

    A normal is valid where the pixel and its four neighbours have depth, no neighbour lies further than
    ``max_jump`` (relative) from the pixel's depth, and the normal faces the camera (``n . v < 0``).
    """
    normals, valid = _normals(np.ascontiguousarray(np.moveaxis(vertices, -1, 0)), depth, max_jump)
    return np.moveaxis(normals, 0, -1), valid


def _normals(v: F32, depth: F32, max_jump: float) -> tuple[F32, BoolArray]:
    """:func:`normal_map` on a channel-first (3, H, W) vertex map; returns (3, H, W) normals and validity."""
    h, w = depth.shape
    normals = np.zeros((3, h, w), dtype=np.float32)
    valid = np.zeros((h, w), dtype=bool)
    if h < 3 or w < 3:
        return normals, valid
    centre = depth[1:-1, 1:-1]
    limit = np.float32(max_jump) * centre
    ok = centre > 0
    for nb in (depth[1:-1, 2:], depth[1:-1, :-2], depth[2:, 1:-1], depth[:-2, 1:-1]):
        ok &= np.abs(nb - centre) < limit  # a missing neighbour (0) fails: max_jump < 1
    a = v[:, 1:-1, 2:] - v[:, 1:-1, :-2]  # along +u (right)
    b = v[:, 2:, 1:-1] - v[:, :-2, 1:-1]  # along +v (down)
    # b x a faces the camera for a surface seen from its front (a x b = x x y = +z points away).
    nx = b[1] * a[2] - b[2] * a[1]
    ny = b[2] * a[0] - b[0] * a[2]
    nz = b[0] * a[1] - b[1] * a[0]
    norm2 = nx * nx + ny * ny + nz * nz
    ok &= norm2 > 0
    facing = nx * v[0, 1:-1, 1:-1] + ny * v[1, 1:-1, 1:-1] + nz * v[2, 1:-1, 1:-1]
    ok &= facing < 0  # folded (noisy, grazing) neighbourhoods give back-facing normals: not trusted
    scale = np.zeros_like(norm2)
    np.divide(np.float32(1.0), np.sqrt(norm2, where=ok, out=np.ones_like(norm2)), out=scale, where=ok)
    np.multiply(nx, scale, out=normals[0, 1:-1, 1:-1])
    np.multiply(ny, scale, out=normals[1, 1:-1, 1:-1])
    np.multiply(nz, scale, out=normals[2, 1:-1, 1:-1])
    valid[1:-1, 1:-1] = ok
    return normals, valid


def make_level(depth: F32, intrinsics: Intrinsics) -> Level:
    """One pyramid level (vertices, normals, validity) of a depth image (H, W) metres."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    h, w = depth.shape
    planes = np.zeros((7, h * w), dtype=np.float32)
    vertices = _vertices(depth, intrinsics)
    normals, valid = _normals(vertices, depth, 0.05)
    flat = valid.reshape(-1)
    planes[:3] = vertices.reshape(3, -1)
    planes[:3] *= flat  # invalid pixels carry zeros
    planes[3:6] = normals.reshape(3, -1)
    planes[6] = flat
    return Level(intrinsics, depth, planes, valid)


def build_pyramid(
    depth: F32,
    intrinsics: Intrinsics,
    levels: int,
    *,
    min_depth: float = 0.0,
    max_depth: float = np.inf,
    skip: int = 0,
    smooth: bool = False,
) -> list[Level]:
    """The frame's pyramid: level ``l`` is the input downsampled ``2**(l + skip)`` times (``levels`` levels).

    Depths outside ``[min_depth, max_depth]`` are treated as missing. With ``smooth`` the first level is
    filtered by :func:`smooth_depth` (coarser levels average it further).
    """
    depth = np.asarray(depth, dtype=np.float32)
    current = np.where((depth >= min_depth) & (depth <= max_depth), depth, np.float32(0.0)).astype(np.float32)
    out: list[Level] = []
    for _ in range(skip):
        current = downsample_depth(current)
    if smooth:
        current = smooth_depth(current)
    for level in range(skip, skip + levels):
        k = scaled_intrinsics(intrinsics, 2**level) if level else intrinsics
        if level > skip:
            current = downsample_depth(current)
        out.append(make_level(current, k))
    return out
