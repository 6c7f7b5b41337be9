"""RGB-D frames to point observations: track corners, keep those with trustworthy depth, lift them to 3D,
and end the tracks whose 3D point does not move with the rest (a RANSAC rigid fit between consecutive
frames over the tracks they share)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from relpoint.frontend.backprojection import back_project, depth_at_pixels
from relpoint.frontend.tracking import KeypointSettings, KeypointTracker, to_gray
from relpoint.geometry import FloatArray, fit_rigid
from relpoint.types import IntArray, Intrinsics, PointObservation


def rigid_outliers(
    previous: FloatArray, current: FloatArray, tolerance: FloatArray, samples: int, rng: np.random.Generator
) -> npt.NDArray[np.bool_]:
    """Which pairs ``previous[i] <-> current[i]`` (N, 3, m) the best rigid motion misses by more than ``tolerance[i]``.

    RANSAC over three-point samples keeps the motion with the most inliers; it is refitted to them
    before the final test. With fewer than six pairs nothing is called an outlier.
    """
    n = len(previous)
    if n < 6:
        return np.zeros(n, dtype=bool)

    def misses(source: FloatArray, target: FloatArray) -> npt.NDArray[np.bool_]:
        fit = fit_rigid(source, target)
        return np.linalg.norm(current @ fit.rotation.T + fit.translation - previous, axis=1) > tolerance

    best = np.ones(n, dtype=bool)
    for _ in range(samples):
        pick = rng.choice(n, 3, replace=False)
        outliers = misses(current[pick], previous[pick])
        if outliers.sum() < best.sum():
            best = outliers
    inliers = ~best
    return misses(current[inliers], previous[inliers]) if inliers.sum() >= 3 else best


class KeypointFrontEnd:
    """One :class:`PointObservation` per RGB-D frame, in the camera's optical frame (``frame_id`` ``camera``).

    ``ids`` of the observation are persistent track ids (not ground-truth landmarks). A track whose
    corner lands on an unmeasured pixel or a depth discontinuity is skipped in that frame only: it may
    find valid depth again in a later frame under the same id.
    """

    def __init__(self, settings: KeypointSettings | None = None) -> None:
        self.settings = settings or KeypointSettings()
        self.tracker = KeypointTracker(self.settings)
        self._rng = np.random.default_rng(self.settings.seed)
        self._previous: tuple[IntArray, FloatArray] | None = None
        self.ended_tracks = 0
        """Tracks ended by the rigid-motion check so far."""

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
        ids, points = ids[valid], back_project(pixels[valid], depth[valid], intrinsics)
        if s.rigid_tolerance > 0 and self._previous is not None:
            keep = self._moves_with_the_rest(ids, points)
            ids, points = ids[keep], points[keep]
        self._previous = (ids, points)
        return PointObservation(stamp_ns, points, ids, "camera")

    def _moves_with_the_rest(self, ids: IntArray, points: FloatArray) -> npt.NDArray[np.bool_]:
        """False for the points of tracks the rigid-motion check ends (their tracks are dropped)."""
        assert self._previous is not None
        s = self.settings
        previous_ids, previous_points = self._previous
        shared, here, there = np.intersect1d(ids, previous_ids, return_indices=True)
        tolerance = s.rigid_tolerance * points[here, 2] + s.rigid_floor
        outliers = rigid_outliers(previous_points[there], points[here], tolerance, s.rigid_samples, self._rng)
        ended = shared[outliers]
        self.tracker.drop(ended)
        self.ended_tracks += len(ended)
        return ~np.isin(ids, ended)
