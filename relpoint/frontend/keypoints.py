"""RGB-D frames to point observations: track corners, keep those with trustworthy depth, lift them to 3D."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from relpoint.frontend.backprojection import back_project, depth_at_pixels
from relpoint.frontend.tracking import KeypointSettings, KeypointTracker, to_gray
from relpoint.types import Intrinsics, PointObservation


class KeypointFrontEnd:
    """One :class:`PointObservation` per RGB-D frame, in the camera's optical frame (``frame_id`` ``camera``).

    ``ids`` of the observation are persistent track ids (not ground-truth landmarks). A track whose
    corner lands on an unmeasured pixel or a depth discontinuity is skipped in that frame only: it may
    find valid depth again in a later frame under the same id.
    """

    def __init__(self, settings: KeypointSettings | None = None) -> None:
        self.settings = settings or KeypointSettings()
        self.tracker = KeypointTracker(self.settings)

    def observe(
        self, stamp_ns: int, rgb: npt.NDArray[np.uint8], depth_m: npt.NDArray[np.floating], intrinsics: Intrinsics
    ) -> PointObservation:
        """Track into this frame; ``rgb`` (H, W, 3) uint8 and ``depth_m`` (H, W) metres of the same size."""
        if rgb.shape[:2] != depth_m.shape:
            raise ValueError(f"colour image {rgb.shape[:2]} and depth image {depth_m.shape} differ in size")
        s = self.settings
        ids, pixels = self.tracker.track(to_gray(rgb))
        depth, valid = depth_at_pixels(
            depth_m, pixels, radius=s.depth_radius, max_relative_jump=s.depth_jump,
            min_depth=s.min_depth, max_depth=s.max_depth,
        )  # fmt: skip
        points = back_project(pixels[valid], depth[valid], intrinsics)
        return PointObservation(stamp_ns, points, ids[valid], "camera")
