"""Lens distortion taken out of depth and colour images, so that the pinhole model holds on them.

A ``sensor_msgs/CameraInfo`` may declare a distortion (``plumb_bob``, ``rational_polynomial`` or
``equidistant``) with coefficients ``d``; projective ICP and fusion assume an ideal pinhole, so the
images are resampled onto the same camera matrix without distortion (OpenCV's undistortion maps).
Depth is resampled by the nearest pixel, never interpolated: a blend across a depth edge would
invent surfaces between foreground and background.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
import numpy.typing as npt

from relpoint.types import Intrinsics

#: Distortion models that can be taken out (CameraInfo's names).
MODELS = ("plumb_bob", "rational_polynomial", "equidistant")


@dataclass(frozen=True, eq=False)
class Undistortion:
    """Resampling maps from an ideal pinhole image of ``pinhole`` to the distorted one (pixels, float32)."""

    pinhole: Intrinsics
    map_x: npt.NDArray[np.float32]
    map_y: npt.NDArray[np.float32]

    def depth(self, depth: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """(H, W) metres without distortion (nearest pixel; 0 where no source pixel falls)."""
        return cv2.remap(
            depth, self.map_x, self.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )

    def color(self, color: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
        """(H, W, 3) RGB without distortion (bilinear)."""
        return cv2.remap(color, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def undistortion(intrinsics: Intrinsics) -> Undistortion | None:
    """The maps that take ``intrinsics``'s distortion out, keeping its camera matrix; None for an ideal
    pinhole. Raises ValueError for a model not in :data:`MODELS` or coefficients it cannot take."""
    if not intrinsics.distorted:
        return None
    model, d = intrinsics.distortion_model.lower(), np.asarray(intrinsics.distortion, dtype=np.float64)
    K, size = intrinsics.matrix(), (intrinsics.width, intrinsics.height)
    if model in ("plumb_bob", "rational_polynomial") and len(d) in (4, 5, 8, 12, 14):
        map_x, map_y = cv2.initUndistortRectifyMap(K, d, None, K, size, cv2.CV_32FC1)
    elif model == "equidistant" and len(d) == 4:
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(K, d, np.eye(3), K, size, cv2.CV_32FC1)
    else:
        raise ValueError(f"distortion model {intrinsics.distortion_model!r} with {len(d)} coefficients")
    return Undistortion(replace(intrinsics, distortion_model="", distortion=()), map_x, map_y)
