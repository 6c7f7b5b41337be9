"""The point map and point-based fusion (section 3 of the dense-SLAM paper; Keller et al. 2013).

The map is an unordered set of points in ``world``, each with a position, a unit normal, a colour, a
weight (the number of measurements averaged into it) and the frame indices where it was created and last
updated. It is stored column-wise (3, M) in float32 and grows by amortised doubling.

Per frame (section 3): the map is *rendered* into the camera by projection with a z-buffer (the
nearest map point per pixel wins) giving an index map; each frame pixel with a valid vertex and
normal is *filtered* against the map point rendered at that pixel (distance and normal-angle gates);
matched pairs are *merged* by the weighted averages

    p <- (w p + T q) / (w + 1),   n <- normalise((w n + R n_q) / (w + 1)),   c <- (w c + c_q) / (w + 1),
    w <- w + 1,

with ``T = (R, t) = T_world_camera``. Normals are only rotated: the paper's formula also adds ``t`` to
the normal, which is wrong for a direction. Unmatched pixels are *added* as new points with weight 1.
Optionally, points that stay below a weight after some frames are removed as unstable (outliers that
were never seen again).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.estimators.dense import _kernels
from relpoint.estimators.dense.maps import Level
from relpoint.geometry import FloatArray, transform_soa32

F32 = npt.NDArray[np.float32]
I64 = npt.NDArray[np.int64]

_NO_COLOUR = np.zeros((0, 3), dtype=np.uint8)
_NO_CONFIDENCE = np.zeros(0, dtype=np.float32)


@dataclass(frozen=True)
class FusionStats:
    """Counts of one fusion step: frame points merged into map points, and points added."""

    merged: int
    added: int


class PointMap:
    """A growing map of fused points in ``world`` (positions, normals, colours, weights)."""

    def __init__(self, capacity: int = 1 << 16) -> None:
        capacity = max(int(capacity), 16)
        self._positions = np.zeros((3, capacity), dtype=np.float32)
        self._normals = np.zeros((3, capacity), dtype=np.float32)
        self._colors = np.zeros((3, capacity), dtype=np.float32)
        self._weights = np.zeros(capacity, dtype=np.float32)
        # Colour has its own weight: a frame without colour adds to the point's weight but not to its colour.
        self._color_weights = np.zeros(capacity, dtype=np.float32)
        self._created = np.zeros(capacity, dtype=np.int32)
        self.size = 0

    def __len__(self) -> int:
        return self.size

    @property
    def positions(self) -> F32:
        """(3, M) float32 positions in ``world``, metres (a view)."""
        return self._positions[:, : self.size]

    @property
    def normals(self) -> F32:
        """(3, M) float32 unit normals in ``world`` (a view)."""
        return self._normals[:, : self.size]

    @property
    def colors(self) -> F32:
        """(3, M) float32 RGB colours in 0-255 (a view)."""
        return self._colors[:, : self.size]

    @property
    def color_weights(self) -> F32:
        """(M,) float32 weights of the colours: the coloured measurements fused into each point, 0 for
        a point no frame with colour has seen (a view)."""
        return self._color_weights[: self.size]

    @property
    def weights(self) -> F32:
        """(M,) float32 weights: the number of measurements fused into each point (a view)."""
        return self._weights[: self.size]

    @property
    def created(self) -> npt.NDArray[np.int32]:
        """(M,) frame index at which each point was added (a view)."""
        return self._created[: self.size]

    def _reserve(self, extra: int) -> None:
        need = self.size + extra
        capacity = self._weights.shape[0]
        if need <= capacity:
            return
        while capacity < need:
            capacity *= 2
        for name in ("_positions", "_normals", "_colors"):
            grown = np.zeros((3, capacity), dtype=np.float32)
            grown[:, : self.size] = getattr(self, name)[:, : self.size]
            setattr(self, name, grown)
        for name in ("_weights", "_color_weights", "_created"):
            old = getattr(self, name)
            grown1 = np.zeros(capacity, dtype=old.dtype)
            grown1[: self.size] = old[: self.size]
            setattr(self, name, grown1)

    def append(self, positions: F32, normals: F32, colors: F32, frame_index: int) -> I64:
        """Add points ((3, n) world positions, normals, colours) with weight 1; returns their ids (n,)."""
        n = positions.shape[1]
        self._reserve(n)
        s = slice(self.size, self.size + n)
        self._positions[:, s] = positions
        self._normals[:, s] = normals
        self._colors[:, s] = colors
        self._weights[s] = 1.0
        self._color_weights[s] = 0.0
        self._created[s] = frame_index
        ids = np.arange(self.size, self.size + n, dtype=np.int64)
        self.size += n
        return ids

    def render(self, T_camera_world: FloatArray, level: Level) -> I64:
        """Index map (H, W) int64 of the nearest map point projecting into each pixel of ``level``, -1 for none.

        A z-buffer over all map points: each point is projected to its nearest pixel and the smallest depth
        per pixel wins; ties go to the highest id (one compiled pass: :func:`_kernels.render`).
        """
        k = level.intrinsics
        if self.size == 0:
            return np.full((k.height, k.width), -1, dtype=np.int64)
        p_cam = transform_soa32(T_camera_world, self.positions)
        index = _kernels.render(
            np.ascontiguousarray(p_cam), float(k.fx), float(k.fy), k.cx + 0.5, k.cy + 0.5, int(k.width), int(k.height)
        )
        return index.reshape(k.height, k.width)

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
        """Merge a frame into the map (filter, merge, add) given the map's index map at the frame's pose.

        Parameters
        ----------
        T_world_camera: (4, 4) pose of the frame.
        level: the frame level to fuse (vertices/normals in the camera frame).
        colors: (H, W, 3) uint8 RGB registered to ``level``, or None (colour 0).
        index_map: (H, W) map ids rendered at ``T_world_camera`` (:meth:`render`), -1 for none.
        distance_threshold: largest distance between a frame point and its map point to merge, metres,
            plus ``distance_quadratic`` times the squared depth (Kinect-like noise grows with depth squared).
        normal_cos_threshold: smallest cosine between their normals to merge.
        frame_index: index of the frame (recorded as the creation time of added points).
        max_weight: weights stop growing here (the newest measurements keep some influence).
        confidence: optional (H*W,) weight of each pixel's measurement (Keller et al.'s radial confidence);
            a merge then adds ``alpha`` instead of 1: ``p <- (w p + alpha q) / (w + alpha)``, ``w <- w + alpha``,
            and new points start at weight ``alpha``. None means 1 everywhere (the paper's rule).

        Returns
        -------
        The index map after fusion ((H, W), merged and added points at their pixels) and the counts.

        A valid pixel without a rendered point (the index map holds one point per pixel, so a surface seen
        from a new pose shows pinholes) is compared with the first map point rendered in its 3x3
        neighbourhood, and a pixel failing the gates with every point rendered there; when one passes the
        pixel is *covered* (neither merged nor added).
        """
        R = T_world_camera[:3, :3].astype(np.float32)
        t = T_world_camera[:3, 3].astype(np.float32)[:, None]
        planes = level.planes
        h, w_img = index_map.shape
        ids = np.ascontiguousarray(index_map.reshape(-1))
        filled = _fill_from_neighbours(index_map).reshape(-1)

        # Filter and merge: the map point rendered at (or, for pinholes, next to) each valid pixel, within
        # the gates; weighted averages into the points rendered at their own pixels (compiled: one pass).
        pixels = np.flatnonzero(planes[6] > 0)
        frame = np.take(planes[:6], pixels, axis=1)
        q = R @ frame[:3] + t
        n_q = R @ frame[3:6]
        depth = np.ascontiguousarray(frame[2])
        rgb = _NO_COLOUR if colors is None else np.ascontiguousarray(colors, dtype=np.uint8).reshape(-1, 3)
        pixel_confidence = _NO_CONFIDENCE if confidence is None else np.ascontiguousarray(confidence, dtype=np.float32)
        ok, merged = _kernels.fuse_gates_and_merge(
            pixels, q, n_q, depth, filled, ids, self._positions, self._normals, self._colors, self._weights,
            self._color_weights, rgb, pixel_confidence, float(distance_threshold), float(distance_quadratic),
            float(np.float32(normal_cos_threshold)), float(max_weight),
        )  # fmt: skip

        # Add: valid pixels neither merged nor covered by a point rendered next to them.
        failed = np.flatnonzero(~ok)
        covered = _kernels.covered(
            failed, pixels, q, n_q, depth, np.ascontiguousarray(index_map, dtype=np.int64), self._positions,
            self._normals, float(distance_threshold), float(distance_quadratic),
            float(np.float32(normal_cos_threshold)),
        )  # fmt: skip
        keep = failed[~covered]
        added_pixels = pixels[keep]
        rgb_new = (
            np.take(rgb, added_pixels, axis=0).T.astype(np.float32)
            if colors is not None
            else np.zeros((3, len(added_pixels)), np.float32)
        )
        new_ids = self.append(np.take(q, keep, axis=1), np.take(n_q, keep, axis=1), rgb_new, frame_index)
        if confidence is not None:
            self._weights[new_ids] = confidence[added_pixels]
        if colors is not None:
            self._color_weights[new_ids] = self._weights[new_ids]
        after = ids.copy()
        after[added_pixels] = new_ids
        return after.reshape(h, w_img), FusionStats(int(merged), int(len(new_ids)))

    def remove(self, drop: npt.NDArray[np.bool_]) -> I64:
        """Delete the points flagged in ``drop`` (M,); returns the old-id -> new-id map (-1 for deleted)."""
        keep = ~drop
        remap = np.full(self.size, -1, dtype=np.int64)
        n = int(keep.sum())
        remap[keep] = np.arange(n)
        for name in ("_positions", "_normals", "_colors"):
            array = getattr(self, name)
            array[:, :n] = array[:, : self.size][:, keep]
        for name in ("_weights", "_color_weights", "_created"):
            array = getattr(self, name)
            array[:n] = array[: self.size][keep]
        self.size = n
        return remap

    def unstable(self, frame_index: int, min_weight: float, age: int) -> npt.NDArray[np.bool_]:
        """Points created at least ``age`` frames ago whose weight is still below ``min_weight`` (M,) bool."""
        return (self.weights < min_weight) & (frame_index - self.created >= age)


def _fill_from_neighbours(index_map: I64) -> I64:
    """The index map with each empty pixel (-1) given the id of the first non-empty of its 8 neighbours."""
    h, w = index_map.shape
    padded = np.full((h + 2, w + 2), -1, dtype=index_map.dtype)
    padded[1:-1, 1:-1] = index_map
    filled = index_map.copy()
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1)):
        empty = filled < 0
        np.copyto(filled, padded[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w], where=empty)
    return filled


def colors_filled(
    positions: FloatArray, colors: npt.NDArray[np.uint8], colored: npt.NDArray[np.bool_]
) -> npt.NDArray[np.uint8]:
    """``colors`` (M, 3) uint8 with each point not ``colored`` (M,) given the colour of the nearest
    coloured point (positions (M, 3), metres). A log whose colour stream is sparser than its depth
    (colour at half rate, dropped colour frames) leaves points that only uncoloured frames saw; written
    black, they speckled the map (7.8 % of it with colour at half rate). Unchanged when no point, or
    every point, is coloured."""
    missing = np.flatnonzero(~colored)
    if len(missing) == 0 or len(missing) == len(colored):
        return colors
    from scipy.spatial import cKDTree  # here, not at import: scipy costs start-up time

    source = np.flatnonzero(colored)
    nearest = cKDTree(positions[source]).query(positions[missing])[1]
    filled = colors.copy()
    filled[missing] = colors[source[nearest]]
    return filled
