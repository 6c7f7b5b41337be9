"""RGB-D frames to point observations: track corners, keep those with trustworthy depth, lift them to 3D,
and end the tracks whose 3D point does not move with the rest (a RANSAC rigid fit between consecutive
frames over the tracks they share) or strays from where the track's earlier points put it."""

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
        return np.linalg.norm(fit.apply(current) - previous, axis=1) > tolerance

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
        self._track_sum: dict[int, FloatArray] = {}  # per track: sum of its points, in the previous frame
        self._track_count: dict[int, int] = {}
        self.ended_tracks = 0
        """Tracks ended by the rigid-motion check so far."""
        self.strayed_tracks = 0
        """Tracks ended because their point strayed from the mean of their earlier points."""

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
        self.ended_tracks += len(ended)
        if s.track_tolerance > 0:
            strayed = self._strayed(ids, points, here[~outliers], there[~outliers])
            self.strayed_tracks += len(strayed)
            ended = np.concatenate([ended, strayed])
        self.tracker.drop(ended)
        for track in ended.tolist():
            self._track_sum.pop(track, None)
            self._track_count.pop(track, None)
        return ~np.isin(ids, ended)

    def _strayed(self, ids: IntArray, points: FloatArray, here: IntArray, there: IntArray) -> IntArray:
        """Tracks whose point strays from the mean of their earlier points (:attr:`KeypointSettings.track_tolerance`).

        The frame-to-frame motion is fitted to the pairs that passed the rigid check (``here`` rows of
        this frame, ``there`` of the previous one); each track's sum of earlier points is carried into
        this frame with it and compared with its point here; this frame's points then join the sums.
        """
        assert self._previous is not None
        s = self.settings
        previous_points = self._previous[1]
        carried_sum: dict[int, FloatArray] = {}
        if len(here) >= 3:
            fit = fit_rigid(previous_points[there], points[here])  # previous frame -> this frame
            R, t = fit.rotation, fit.translation
            for track, total in self._track_sum.items():
                carried_sum[track] = R @ total + self._track_count[track] * t
        counts = np.array([self._track_count.get(track, 0) for track in ids.tolist()])
        known = np.flatnonzero(counts > 0)
        strayed = np.zeros(len(ids), dtype=bool)
        if len(known) and carried_sum:
            mean = np.array([carried_sum[int(ids[i])] for i in known]) / counts[known, None]
            distance = np.linalg.norm(points[known] - mean, axis=1)
            strayed[known] = distance > s.track_tolerance * points[known, 2] + s.rigid_floor
        elif not carried_sum:
            self._track_sum.clear()  # no motion to carry the sums with: the tracks start over
            self._track_count.clear()
            counts[:] = 0
        self._track_sum = {
            int(track): (carried_sum.get(int(track), 0.0) if counts[i] else 0.0) + points[i]
            for i, track in enumerate(ids.tolist())
            if not strayed[i]
        }
        self._track_count = {int(track): int(counts[i]) + 1 for i, track in enumerate(ids.tolist()) if not strayed[i]}
        return ids[strayed]
