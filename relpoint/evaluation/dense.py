"""Accuracy and completeness of a dense point map against a reference cloud or mesh.

The usual pair of reconstruction measures (e.g. Knapitsch et al., *Tanks and Temples*, 2017; Schöps et al.,
ETH3D, 2017): *accuracy* is the distance from each mapped point to the reference, *completeness* the
distance from each reference point to the map. Each is reported as a mean distance and as the share of
points within a threshold (precision and recall at that threshold), and their harmonic mean (F-score).
Both clouds must be in the same frame: align the trajectory first and map the cloud with the alignment.

The nearest-neighbour search is bounded at ``max_distance`` (by default :data:`SEARCH_THRESHOLDS`
thresholds): a point farther from the other cloud counts as that far. The shares within the threshold
are exact; the mean and median distances are those of the capped distances. Without the bound a
misaligned map (a run evaluated in the wrong frame) costs minutes of search for figures that only
say "far".
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.evaluation import EvaluationError
from relpoint.geometry import FloatArray, check_points

#: Default search bound, in thresholds (1 m at the default 5 cm threshold).
SEARCH_THRESHOLDS = 20.0

#: Query points per chunk of the nearest-neighbour search (progress is reported per chunk).
QUERY_CHUNK = 1 << 16


@dataclass(frozen=True)
class DenseMetrics:
    """Accuracy (map -> reference) and completeness (reference -> map) at ``threshold`` metres."""

    threshold: float
    accuracy_mean: float  # metres
    accuracy_median: float  # metres
    accuracy_within: float  # share of map points within threshold of the reference (precision)
    completeness_mean: float  # metres
    completeness_median: float  # metres
    completeness_within: float  # share of reference points within threshold of the map (recall)
    n_points: int
    n_reference: int
    max_distance: float = math.inf  # metres: the search bound; farther distances count as this

    @property
    def f_score(self) -> float:
        """Harmonic mean of the two shares (0 when both are 0)."""
        p, r = self.accuracy_within, self.completeness_within
        return 2 * p * r / (p + r) if p + r > 0 else 0.0

    def summary(self, prefix: str = "dense_") -> dict[str, float]:
        """Flat name -> value dict for the evaluation summary."""
        return {
            f"{prefix}accuracy_mean": self.accuracy_mean,
            f"{prefix}accuracy_median": self.accuracy_median,
            f"{prefix}accuracy_within": self.accuracy_within,
            f"{prefix}completeness_mean": self.completeness_mean,
            f"{prefix}completeness_median": self.completeness_median,
            f"{prefix}completeness_within": self.completeness_within,
            f"{prefix}f_score": self.f_score,
            f"{prefix}threshold": self.threshold,
            f"{prefix}max_distance": self.max_distance,
        }


def _check_threshold(threshold: float) -> None:
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive distance in metres, got {threshold}")


def _metrics(to_ref: FloatArray, to_map: FloatArray, threshold: float, max_distance: float = math.inf) -> DenseMetrics:
    return DenseMetrics(
        threshold=float(threshold),
        accuracy_mean=float(np.mean(to_ref)),
        accuracy_median=float(np.median(to_ref)),
        accuracy_within=float(np.mean(to_ref <= threshold)),
        completeness_mean=float(np.mean(to_map)),
        completeness_median=float(np.median(to_map)),
        completeness_within=float(np.mean(to_map <= threshold)),
        n_points=len(to_ref),
        n_reference=len(to_map),
        max_distance=float(max_distance),
    )


def nearest_distances(
    query: npt.ArrayLike,
    cloud: npt.ArrayLike,
    workers: int = 1,
    max_distance: float = math.inf,
    on_progress: Callable[[int], None] | None = None,
) -> FloatArray:
    """Distance (N,) from each query point (N, 3) to its nearest point of ``cloud`` (M, 3), metres.

    Distances beyond ``max_distance`` are returned as ``max_distance`` (the search stops there).
    ``on_progress(n)`` is called after each chunk of ``n`` query points.
    """
    query = check_points(query, "query")
    # An unbalanced tree builds several times faster and queries as fast on scan-like clouds.
    from scipy.spatial import cKDTree  # here, not at import: scipy costs start-up time

    tree = cKDTree(check_points(cloud, "cloud"), balanced_tree=False, compact_nodes=False)
    distances = np.empty(len(query))
    for start in range(0, len(query), QUERY_CHUNK):
        chunk = query[start : start + QUERY_CHUNK]
        found = tree.query(chunk, k=1, distance_upper_bound=max_distance, workers=workers)[0]
        distances[start : start + len(chunk)] = np.minimum(found, max_distance)
        if on_progress is not None:
            on_progress(len(chunk))
    return distances


def dense_metrics(
    points: npt.ArrayLike,
    reference: npt.ArrayLike,
    threshold: float = 0.05,
    workers: int = 1,
    max_distance: float | None = None,
    on_progress: Callable[[int], None] | None = None,
) -> DenseMetrics:
    """Accuracy and completeness of ``points`` (N, 3) against a reference cloud (M, 3), same frame, metres.

    ``max_distance`` bounds the search (default :data:`SEARCH_THRESHOLDS` x ``threshold``);
    ``on_progress(n)`` is told of every ``n`` points searched (N + M in all).

    Raises
    ------
    EvaluationError
        If either cloud is empty.
    """
    _check_threshold(threshold)
    points = check_points(points, "points")
    reference = check_points(reference, "reference")
    if len(points) == 0 or len(reference) == 0:
        raise EvaluationError(
            f"dense evaluation needs points in both clouds (map {len(points)}, reference {len(reference)})"
        )
    bound = SEARCH_THRESHOLDS * threshold if max_distance is None else float(max_distance)
    to_ref = nearest_distances(points, reference, workers, bound, on_progress)
    to_map = nearest_distances(reference, points, workers, bound, on_progress)
    return _metrics(to_ref, to_map, threshold, bound)


def dense_metrics_to_mesh(
    points: npt.ArrayLike,
    vertices: npt.ArrayLike,
    triangles: npt.ArrayLike,
    rng: np.random.Generator,
    threshold: float = 0.05,
    samples: int = 100_000,
) -> DenseMetrics:
    """Accuracy and completeness of ``points`` (N, 3) against a triangle mesh, same frame, metres.

    Accuracy is the exact point-to-surface distance (open3d ``RaycastingScene.compute_distance``);
    completeness is taken from ``samples`` points drawn uniformly over the mesh area with ``rng``.

    Parameters
    ----------
    vertices: (V, 3) mesh vertices, metres.
    triangles: (F, 3) vertex indices.
    rng: source of the surface samples.
    """
    from relpoint._open3d import open3d

    _check_threshold(threshold)
    points = check_points(points, "points")
    vertices = check_points(vertices, "vertices")
    faces = np.asarray(triangles, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise EvaluationError(f"reference mesh needs triangles of shape (F, 3), got {faces.shape}")
    if len(points) == 0:
        raise EvaluationError("dense evaluation needs at least one map point")
    o3d = open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    to_ref = scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)
    # Area-weighted uniform samples: pick a face by area, then uniform barycentric coordinates.
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if areas.sum() <= 0:
        raise EvaluationError("reference mesh has zero surface area")
    face = rng.choice(len(faces), size=samples, p=areas / areas.sum())
    u, v = rng.random(samples), rng.random(samples)
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    surface = a[face] + u[:, None] * (b[face] - a[face]) + v[:, None] * (c[face] - a[face])
    to_map = nearest_distances(surface, points)
    return _metrics(to_ref, to_map, threshold)
