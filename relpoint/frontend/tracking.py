"""Corner tracking from frame to frame: Shi-Tomasi corners and pyramidal Lucas-Kanade optical flow.

Each frame, the corners of the previous frame are tracked into the new one (Bouguet's pyramidal
Lucas-Kanade, ``cv2.calcOpticalFlowPyrLK``) and tracked back again; a track survives only when the
backward track lands within ``forward_backward_px`` of where it started (Kalal et al. 2010), which
drops tracks that slid along an edge or jumped to a look-alike. Lost tracks are replaced by new
Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) detected away from the surviving ones, so the count
stays near ``max_corners``. Every track keeps one ``id`` for its whole life; ids are never reused.
Both OpenCV calls are deterministic, so the same frames give the same tracks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
import numpy.typing as npt

from relpoint.errors import UsageError
from relpoint.geometry import FloatArray
from relpoint.settings import Settings, setting
from relpoint.types import IntArray


@dataclass(frozen=True)
class KeypointSettings(Settings):
    """How corners are detected, tracked and lifted to 3D (pixels unless stated)."""

    settings_name: ClassVar[str] = "keypoint"
    #: Corners kept per frame (tracked plus new).
    max_corners: int = setting(300, low=1, high=100_000)
    #: Shi-Tomasi quality: a corner's smaller eigenvalue relative to the frame's strongest corner.
    quality_level: float = setting(0.01, low=1e-6, high=1)
    #: Smallest distance between two corners (new corners keep it from tracked ones too).
    min_distance: int = setting(12, low=1, high=1000)
    #: Side of the Lucas-Kanade search window.
    window: int = setting(21, low=3, high=255)
    #: Pyramid levels above the full image (0 = no pyramid).
    pyramid_levels: int = setting(3, low=0, high=8)
    #: Largest forward-backward tracking error for a track to survive.
    forward_backward_px: float = setting(1.0, low=0.01, high=100)
    #: Half-width of the depth window that must be measured and flat around a corner.
    depth_radius: int = setting(2, low=0, high=20)
    #: Largest depth spread in that window relative to the corner's depth (a discontinuity above it).
    depth_jump: float = setting(0.03, low=0, high=10)
    #: Trusted depth range of the sensor, m.
    min_depth: float = setting(0.3, low=0, high=1000)
    max_depth: float = setting(5.0, above=0, high=1e6)
    #: Tracks whose 3D point does not follow the rigid motion shared by the tracks seen in both this
    #: frame and the previous one, by more than ``rigid_tolerance`` times its depth plus ``rigid_floor``
    #: (m), are ended: a corner sliding along an edge or across an occlusion. 0 disables the check.
    rigid_tolerance: float = setting(0.01, low=0, high=1)
    rigid_floor: float = setting(0.005, low=0, high=10)
    #: Tracks whose 3D point strays from the mean of the track's earlier points (carried into this
    #: frame by the chained frame-to-frame motions of that check) by more than ``track_tolerance``
    #: times its depth plus ``rigid_floor`` (m) are ended: a corner that slides slowly, or whose depth
    #: drifts with the viewpoint, passes every frame-to-frame check. 0 disables it (needs the check).
    track_tolerance: float = setting(0.02, low=0, high=1)
    #: RANSAC draws (three-point samples) of that check; they come from ``seed``.
    rigid_samples: int = setting(100, low=1, high=100_000)
    seed: int = setting(0, low=0)

    def check(self) -> None:
        """The trusted depth range holds depths."""
        if self.min_depth >= self.max_depth:
            raise UsageError(
                f"keypoint setting min_depth must be below max_depth ({self.max_depth}), got {self.min_depth}"
            )


def to_gray(rgb: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """(H, W) uint8 intensity of an (H, W, 3) RGB image (or the image itself when it has one channel)."""
    image = np.ascontiguousarray(rgb, dtype=np.uint8)
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


class KeypointTracker:
    """Tracks corners through a sequence of intensity images; call :meth:`track` once per frame, in order."""

    def __init__(self, settings: KeypointSettings | None = None) -> None:
        self.settings = settings or KeypointSettings()
        self._previous: npt.NDArray[np.uint8] | None = None
        self._pixels: FloatArray = np.empty((0, 2))
        self._ids: IntArray = np.empty(0, dtype=np.int64)
        self._next_id = 0

    def track(self, gray: npt.NDArray[np.uint8]) -> tuple[IntArray, FloatArray]:
        """Track the live corners into ``gray`` (H, W uint8), replenish lost ones; ``(ids (N,), pixels (N, 2))``.

        ``pixels`` are ``(u, v)`` = (column, row) in ``gray``. The returned arrays are the tracker's
        live set; ``drop`` removes tracks that later stages reject.
        """
        gray = np.ascontiguousarray(gray, dtype=np.uint8)
        if self._previous is not None and self._previous.shape != gray.shape:
            raise ValueError(f"image size changed from {self._previous.shape} to {gray.shape}")
        if self._previous is not None and len(self._pixels):
            keep, moved = self._flow(self._previous, gray, self._pixels)
            self._pixels, self._ids = moved[keep], self._ids[keep]
        self._replenish(gray)
        self._previous = gray
        return self._ids.copy(), self._pixels.copy()

    def drop(self, ids: IntArray) -> None:
        """End the tracks ``ids`` (their corners are re-detected later under new ids if still good)."""
        keep = ~np.isin(self._ids, ids)
        self._pixels, self._ids = self._pixels[keep], self._ids[keep]

    def _flow(self, previous: np.ndarray, current: np.ndarray, pixels: FloatArray) -> tuple[np.ndarray, FloatArray]:
        s = self.settings
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        lk = {"winSize": (s.window, s.window), "maxLevel": s.pyramid_levels, "criteria": criteria}
        start = pixels.astype(np.float32).reshape(-1, 1, 2)
        forward, status, _ = cv2.calcOpticalFlowPyrLK(previous, current, start, None, **lk)
        backward, status_back, _ = cv2.calcOpticalFlowPyrLK(current, previous, forward, None, **lk)
        error = np.linalg.norm((backward - start).reshape(-1, 2), axis=1)
        moved = forward.reshape(-1, 2).astype(np.float64)
        height, width = current.shape
        inside = (moved[:, 0] >= 0) & (moved[:, 0] <= width - 1) & (moved[:, 1] >= 0) & (moved[:, 1] <= height - 1)
        keep = (status.ravel() == 1) & (status_back.ravel() == 1) & (error <= s.forward_backward_px) & inside
        return keep, moved

    def _replenish(self, gray: np.ndarray) -> None:
        s = self.settings
        wanted = s.max_corners - len(self._pixels)
        if wanted <= 0:
            return
        mask = np.full(gray.shape, 255, dtype=np.uint8)
        for u, v in np.rint(self._pixels).astype(int):
            cv2.circle(mask, (int(u), int(v)), s.min_distance, 0, -1)
        corners = cv2.goodFeaturesToTrack(
            gray, maxCorners=wanted, qualityLevel=s.quality_level, minDistance=s.min_distance, mask=mask
        )
        if corners is None or len(corners) == 0:
            return
        new = corners.reshape(-1, 2).astype(np.float64)
        self._pixels = np.vstack([self._pixels, new])
        self._ids = np.concatenate([self._ids, np.arange(self._next_id, self._next_id + len(new), dtype=np.int64)])
        self._next_id += len(new)
