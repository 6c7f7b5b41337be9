"""Vertex and normal maps from a depth image, with a downsampling pyramid (section 2 of the dense-SLAM paper).

A *vertex map* holds, per pixel, the 3D point ``v = d K^-1 [u, v, 1]`` in the camera optical frame (x right,
y down, z forward, metres); a *normal map* the unit surface normal there, from the cross product of the
differences of the vertex map along rows and columns (central where both sides have depth, one-sided
otherwise), facing the camera. Pixels without a usable measurement are marked
by ``valid`` (their vertex/normal entries are zero). Arrays are kept channel-first (``(3, H, W)``)
internally so that every operation runs over contiguous memory; the per-pixel filters (downsampling,
smoothing, normals) are compiled loops (:mod:`relpoint.estimators.dense._kernels`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.estimators.dense import _kernels
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


EDGE_JUMP = 0.03
"""Largest relative depth step (of the depth) between neighbouring pixels of one surface that the edge
thresholds of smoothing and downsampling allow (set for a Kinect v1's noise; widened by ``noise``)."""

EdgeNoise = tuple[float, float]
"""``(constant, quadratic)`` of a depth difference ``constant + quadratic z^2`` metres that neighbouring
pixels' noise reaches at depth ``z`` (:mod:`.noise`): an edge threshold never rejects less."""


def downsample_depth(depth: F32, max_jump: float = EDGE_JUMP, noise: EdgeNoise | None = None) -> F32:
    """Halve a depth image (H, W) -> (H//2, W//2) by averaging the valid depths of each 2x2 block.

    A block whose valid depths spread more than ``max_jump`` times their minimum (relative; a depth
    discontinuity), or more than ``noise`` gives where that is larger, takes the nearest depth instead of a
    mean that would float between two surfaces. Blocks without any valid depth are 0. (One compiled
    pass: :func:`_kernels.downsample_depth`.)
    """
    constant, quadratic = noise if noise is not None else (0.0, 0.0)
    return _kernels.downsample_depth(
        np.ascontiguousarray(depth, dtype=np.float32), float(max_jump), noise is not None, float(constant),
        float(quadratic),
    )  # fmt: skip


def smooth_depth(depth: F32, max_jump: float = EDGE_JUMP, noise: EdgeNoise | None = None) -> F32:
    """Edge-preserving 3x3 mean of a depth image (a box-kernel bilateral filter, as KinectFusion smooths depth).

    Each valid pixel becomes the mean of the valid pixels of its 3x3 neighbourhood whose depth lies within
    ``max_jump`` (relative) of its own, or within what ``noise`` gives where that is larger (noisy depth
    would otherwise reject most neighbours and stay unsmoothed); invalid pixels stay 0. Averaging nine
    samples reduces the noise and the quantisation steps that would otherwise tilt the normals. (One
    compiled pass: :func:`_kernels.smooth_depth`.)
    """
    constant, quadratic = noise if noise is not None else (0.0, 0.0)
    return _kernels.smooth_depth(
        np.ascontiguousarray(depth, dtype=np.float32), float(max_jump), noise is not None, float(constant),
        float(quadratic),
    )  # fmt: skip


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
    """Unit normals (H, W, 3) from differences of a vertex map (H, W, 3) along rows and columns, and their
    validity (H, W).

    Along each image axis the tangent joins the nearest usable neighbour on either side (one or
    ``NORMAL_REACH`` pixels away): central differences where both sides have one, one-sided differences
    with the pixel itself where only one side has. A neighbour is usable when it has depth within
    ``max_jump`` (relative, per pixel of distance) of the pixel's. A normal is valid where both axes have
    a tangent and it faces the camera (``n . v < 0``).
    """
    normals, valid = _normals(np.ascontiguousarray(np.moveaxis(vertices, -1, 0)), depth, max_jump)
    return np.moveaxis(normals, 0, -1), valid


NORMAL_REACH = 2
"""Farthest neighbour (pixels) a normal's tangent may use. Scattered missing depth (the speckle holes of
stereo cameras) then costs few normals: with half the pixels missing at random, requiring all four direct
neighbours kept 3 % of the pixels, while a tangent along each axis from either side within two pixels
keeps about 88 % of the valid ones."""


def _normals(v: F32, depth: F32, max_jump: float) -> tuple[F32, BoolArray]:
    """:func:`normal_map` on a channel-first (3, H, W) vertex map; returns (3, H, W) normals and validity
    (one compiled pass: :func:`_kernels.normals`)."""
    jumps = np.array([max_jump * k for k in range(1, NORMAL_REACH + 1)], dtype=np.float32)
    return _kernels.normals(
        np.ascontiguousarray(v, dtype=np.float32), np.ascontiguousarray(depth, dtype=np.float32), jumps
    )


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
    edge_noise: EdgeNoise | None = None,
) -> list[Level]:
    """The frame's pyramid: level ``l`` is the input downsampled ``2**(l + skip)`` times (``levels`` levels).

    Depths outside ``[min_depth, max_depth]`` are treated as missing. With ``smooth`` the first level is
    filtered by :func:`smooth_depth` (coarser levels average it further). ``edge_noise``: the depth
    difference neighbouring pixels' noise reaches at the input resolution (None: the relative thresholds
    alone); each halving averages four pixels and halves it.
    """
    depth = np.asarray(depth, dtype=np.float32)
    current = np.where((depth >= min_depth) & (depth <= max_depth), depth, np.float32(0.0)).astype(np.float32)
    out: list[Level] = []

    def halved(noise: EdgeNoise | None) -> EdgeNoise | None:
        return None if noise is None else (noise[0] / 2, noise[1] / 2)

    for _ in range(skip):
        current = downsample_depth(current, noise=edge_noise)
        edge_noise = halved(edge_noise)
    if smooth:
        current = smooth_depth(current, noise=edge_noise)
    for level in range(skip, skip + levels):
        k = scaled_intrinsics(intrinsics, 2**level) if level else intrinsics
        if level > skip:
            current = downsample_depth(current, noise=edge_noise)
            edge_noise = halved(edge_noise)
        out.append(make_level(current, k))
    return out
