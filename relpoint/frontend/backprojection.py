"""Depth lookup at tracked pixels and back-projection into the camera's optical frame.

A corner lies on an intensity edge, which is often a depth edge too; where the colour image is not
registered to depth (7-Scenes) it may also sit a few pixels off its true depth pixel. A pixel's depth
is therefore only trusted when the whole window around it is measured and flat: the spread of the
window's depths must stay below a fraction of the depth itself (a depth discontinuity fails it).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from relpoint.geometry import FloatArray
from relpoint.types import Intrinsics


def depth_at_pixels(
    depth_m: npt.NDArray[np.floating],
    pixels: FloatArray,
    *,
    radius: int = 2,
    max_relative_jump: float = 0.03,
    min_depth: float = 0.0,
    max_depth: float = np.inf,
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Depth (m) at each pixel and whether it can be trusted.

    Parameters
    ----------
    depth_m: (H, W) depth image in metres, 0 or non-finite = no measurement.
    pixels: (N, 2) sub-pixel image coordinates ``(u, v)`` (column, row), pixel centres at integers.
    radius: half-width of the square window checked around the nearest pixel.
    max_relative_jump: largest ``(max - min) / centre`` depth within the window; above it the pixel
        sits on a depth discontinuity and is rejected.
    min_depth, max_depth: the sensor's trusted range, m.

    Returns
    -------
    depth: (N,) the depth of the nearest pixel, m (0 where invalid).
    valid: (N,) True where the window lies inside the image, is fully measured, flat and in range.
    """
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    height, width = depth_m.shape
    columns = np.rint(pixels[:, 0]).astype(np.int64)
    rows = np.rint(pixels[:, 1]).astype(np.int64)
    inside = (columns >= radius) & (columns < width - radius) & (rows >= radius) & (rows < height - radius)
    depth = np.zeros(len(pixels))
    valid = np.zeros(len(pixels), dtype=bool)
    if not inside.any():
        return depth, valid
    offsets = np.arange(-radius, radius + 1)
    window_rows = rows[inside, None, None] + offsets[None, :, None]
    window_columns = columns[inside, None, None] + offsets[None, None, :]
    window = np.asarray(depth_m, dtype=np.float64)[window_rows, window_columns].reshape(int(inside.sum()), -1)
    window = np.where(np.isfinite(window), window, 0.0)
    centre = window[:, window.shape[1] // 2]
    measured = (window > 0).all(axis=1)
    spread = window.max(axis=1) - window.min(axis=1)
    flat = spread <= max_relative_jump * centre
    in_range = (centre >= min_depth) & (centre <= max_depth)
    depth[inside] = np.where(measured, centre, 0.0)
    valid[inside] = measured & flat & in_range
    return depth, valid


def back_project(pixels: FloatArray, depth_m: FloatArray, intrinsics: Intrinsics) -> FloatArray:
    """(N, 3) points in the camera optical frame (x right, y down, z forward; m) of pixels ``(u, v)`` at depths (m)."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(depth_m, dtype=np.float64).reshape(-1)
    x = (pixels[:, 0] - intrinsics.cx) * z / intrinsics.fx
    y = (pixels[:, 1] - intrinsics.cy) * z / intrinsics.fy
    return np.column_stack([x, y, z])
