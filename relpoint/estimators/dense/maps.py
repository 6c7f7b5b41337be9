"""Vertex and normal maps from a depth image, with a downsampling pyramid (section 2 of the dense-SLAM paper).

A *vertex map* holds, per pixel, the 3D point ``v = d K^-1 [u, v, 1]`` in the camera optical frame (x right,
y down, z forward, metres); a *normal map* the unit surface normal there, from the cross product of the
central differences of the vertex map, oriented towards the camera. Pixels without a usable measurement
are marked by ``valid`` (their vertex/normal entries are zero). Everything is numpy-vectorised.
"""

from __future__ import annotations

import dataclasses
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
    vertices: (H, W, 3) float32 metres, camera optical frame.
    normals: (H, W, 3) float32 unit normals, camera frame, facing the camera (0 where invalid).
    valid: (H, W) bool, pixel has both a vertex and a normal.
    planes: (7, H*W) float32 rows x, y, z, nx, ny, nz of every pixel and 1/0 validity (fast gathers).
    """

    intrinsics: Intrinsics
    depth: F32
    vertices: F32
    normals: F32
    valid: BoolArray
    planes: F32 = dataclasses.field(init=False, repr=False)

    def __post_init__(self) -> None:
        planes = np.empty((7, self.depth.size), dtype=np.float32)
        planes[:3] = self.vertices.reshape(-1, 3).T
        planes[3:6] = self.normals.reshape(-1, 3).T
        planes[6] = self.valid.reshape(-1)
        object.__setattr__(self, "planes", planes)


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
    corners = [depth[r:h:2, c:w:2] for r in (0, 1) for c in (0, 1)]
    total = corners[0] + corners[1] + corners[2] + corners[3]
    count = sum(((c > 0).astype(np.float32) for c in corners), np.zeros_like(total))
    big = np.float32(np.inf)
    nearest = np.minimum(
        np.minimum(np.where(corners[0] > 0, corners[0], big), np.where(corners[1] > 0, corners[1], big)),
        np.minimum(np.where(corners[2] > 0, corners[2], big), np.where(corners[3] > 0, corners[3], big)),
    )
    farthest = np.maximum(np.maximum(corners[0], corners[1]), np.maximum(corners[2], corners[3]))
    mean = total / np.maximum(count, np.float32(1.0))
    jump = (count > 0) & (farthest - nearest > np.float32(max_jump) * nearest)
    return np.where(jump, nearest, mean).astype(np.float32)


def smooth_depth(depth: F32, max_jump: float = 0.03) -> F32:
    """Edge-preserving 3x3 mean of a depth image (a box-kernel bilateral filter, as KinectFusion smooths depth).

    Each valid pixel becomes the mean of the valid pixels of its 3x3 neighbourhood whose depth lies within
    ``max_jump`` (relative) of its own; invalid pixels stay 0. Averaging nine samples reduces the noise
    and the quantisation steps that would otherwise tilt the normals.
    """
    h, w = depth.shape
    padded = np.zeros((h + 2, w + 2), dtype=np.float32)
    padded[1:-1, 1:-1] = depth
    limit = np.float32(max_jump) * depth
    total = np.zeros_like(depth)
    count = np.zeros_like(depth)
    for dr in (0, 1, 2):
        for dc in (0, 1, 2):
            nb = padded[dr : dr + h, dc : dc + w]
            near = (nb > 0) & (np.abs(nb - depth) < limit)
            total += np.where(near, nb, np.float32(0.0))
            count += near
    return np.where(depth > 0, total / np.maximum(count, np.float32(1.0)), np.float32(0.0)).astype(np.float32)


def vertex_map(depth: F32, intrinsics: Intrinsics) -> F32:
    """Back-project a depth image (H, W) metres to an (H, W, 3) vertex map in the camera frame."""
    h, w = depth.shape
    x = (np.arange(w, dtype=np.float32) - np.float32(intrinsics.cx)) / np.float32(intrinsics.fx)
    y = (np.arange(h, dtype=np.float32) - np.float32(intrinsics.cy)) / np.float32(intrinsics.fy)
    out = np.empty((h, w, 3), dtype=np.float32)
    out[..., 0] = depth * x[None, :]
    out[..., 1] = depth * y[:, None]
    out[..., 2] = depth
    return out


def normal_map(vertices: F32, depth: F32, max_jump: float = 0.05) -> tuple[F32, BoolArray]:
    """Unit normals (H, W, 3) from central differences of a vertex map, and their validity (H, W).

    A normal is valid where the pixel and its four neighbours have depth and no neighbour lies further
    than ``max_jump`` (relative) from the pixel's depth. Normals face the camera (``n . v < 0``).
    """
    h, w = depth.shape
    normals = np.zeros((h, w, 3), dtype=np.float32)
    valid = np.zeros((h, w), dtype=bool)
    if h < 3 or w < 3:
        return normals, valid
    d = depth
    centre = d[1:-1, 1:-1]
    ok = centre > 0
    limit = np.float32(max_jump) * centre
    for nb in (d[1:-1, 2:], d[1:-1, :-2], d[2:, 1:-1], d[:-2, 1:-1]):
        ok &= (nb > 0) & (np.abs(nb - centre) < limit)
    x, y, z = vertices[..., 0], vertices[..., 1], vertices[..., 2]
    ax, ay, az = (c[1:-1, 2:] - c[1:-1, :-2] for c in (x, y, z))
    bx, by, bz = (c[2:, 1:-1] - c[:-2, 1:-1] for c in (x, y, z))
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    ok &= norm > 0
    # Orient towards the camera: the vertex is the ray from the camera, so n . v must be negative.
    facing = nx * x[1:-1, 1:-1] + ny * y[1:-1, 1:-1] + nz * z[1:-1, 1:-1]
    scale = np.where(ok, np.where(facing > 0, -1.0, 1.0) / np.where(ok, norm, 1.0), 0.0).astype(np.float32)
    inner = normals[1:-1, 1:-1]
    inner[..., 0] = nx * scale
    inner[..., 1] = ny * scale
    inner[..., 2] = nz * scale
    valid[1:-1, 1:-1] = ok
    return normals, valid


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
    depth = np.where((depth >= min_depth) & (depth <= max_depth), depth, np.float32(0.0)).astype(np.float32)
    out: list[Level] = []
    current = depth
    for _ in range(skip):
        current = downsample_depth(current)
    if smooth:
        current = smooth_depth(current)
    for level in range(skip, skip + levels):
        k = scaled_intrinsics(intrinsics, 2**level) if level else intrinsics
        if level > skip:
            current = downsample_depth(current)
        vertices = vertex_map(current, k)
        normals, valid = normal_map(vertices, current)
        out.append(Level(k, current, vertices, normals, valid))
    return out
