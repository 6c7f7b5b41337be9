"""Moving points in the filters: telling a landmark that moved from a new one, and following it.

A filter that matches points to landmarks by their predicted position (EKF-SLAM, FastSLAM) sees a
moving point as a landmark until the point leaves the landmark's gate, and then as a new landmark,
again and again: every mover leaves a trail of duplicate landmarks, each of which pulls the pose
while it is matched. The test here is the one a moving point cannot avoid: a point that matches no
landmark, close (within ``radius``) to a landmark seen the iteration before that this iteration
does not match, is that landmark having moved. The landmark leaves the map and becomes a *track*;
later points near a track are its new positions and start no landmark. A static landmark is matched
whenever it is seen, so it is never taken for a mover by this test; a new static point next to one
that is matched is a new landmark.

Tracks are kept in ``world`` (the filters' frame) with their last position; one unseen for
``memory`` iterations is dropped (it stays in the map, flagged dynamic, at its last position).
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from relpoint.geometry import FloatArray


class MoverTracks:
    """The moving points a filter follows outside its map.

    Parameters
    ----------
    radius: a point this close (m, in ``world``) to a recently seen, unmatched landmark or a live track
        is that landmark or track having moved.
    memory: iterations a track stays live without being seen.
    """

    def __init__(self, radius: float, memory: int = 10) -> None:
        self.radius = radius
        self.memory = memory
        self.positions = np.zeros((0, 3))
        self.last_seen = np.zeros(0, dtype=np.int64)
        self.observations: list[int] = []
        self.votes: list[Counter[int]] = []

    def __len__(self) -> int:
        return len(self.positions)

    def claim(self, points_world: FloatArray, ids: np.ndarray | None, iteration: int) -> np.ndarray:
        """Move live tracks onto the nearest of ``points_world`` (k, 3) within ``radius``; mask of points claimed."""
        claimed = np.zeros(len(points_world), dtype=bool)
        live = np.flatnonzero(self.last_seen >= iteration - self.memory)
        if len(live) == 0 or len(points_world) == 0:
            return claimed
        distance = np.linalg.norm(points_world[:, None, :] - self.positions[live][None, :, :], axis=2)
        for i in np.argsort(distance.min(axis=1), kind="stable"):
            j = int(np.argmin(distance[i]))
            if distance[i, j] > self.radius:
                break
            self.see(live[j], points_world[i], None if ids is None else int(ids[i]), iteration)
            claimed[i] = True
            distance[:, j] = np.inf  # one point a track an iteration
        return claimed

    def start(self, position: FloatArray, observations: int, votes: Counter[int], iteration: int) -> int:
        """Start a track from a landmark that moved: its history and the point's position (3,)."""
        self.positions = np.vstack([self.positions, np.asarray(position, dtype=np.float64)[None]])
        self.last_seen = np.append(self.last_seen, iteration)
        self.observations.append(observations)
        self.votes.append(Counter(votes))
        return len(self.positions) - 1

    def see(self, track: int, position: FloatArray, gt_id: int | None, iteration: int) -> None:
        """Record an observation of ``track`` at ``position`` (3,) in ``world``."""
        self.positions[track] = position
        self.last_seen[track] = iteration
        self.observations[track] += 1
        if gt_id is not None:
            self.votes[track][gt_id] += 1


def moved_landmarks(
    points_world: FloatArray, landmarks: FloatArray, candidates: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pair unmatched points with unmatched, recently seen landmarks within ``radius`` (nearest first).

    ``points_world`` (k, 3) and ``landmarks`` (n, 3) in ``world``; ``candidates`` (c,) the landmark
    indices that may have moved. Returns (point indices, landmark indices), one to one.
    """
    if len(points_world) == 0 or len(candidates) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    distance = np.linalg.norm(points_world[:, None, :] - landmarks[candidates][None, :, :], axis=2)
    points, moved = [], []
    while True:
        i, j = np.unravel_index(int(np.argmin(distance)), distance.shape)
        if not np.isfinite(distance[i, j]) or distance[i, j] > radius:
            break
        points.append(int(i))
        moved.append(int(candidates[j]))
        distance[i, :] = np.inf
        distance[:, j] = np.inf
    return np.asarray(points, np.int64), np.asarray(moved, np.int64)
