"""Algorithm 3 as a post-step: local SLAM segments and low-rate fixes into one global map and path.

Implements Zhang, Milios and Gu, *General Concept of 3D SLAM*, sections 5-6 and Algorithm 3 over the
output of any relpoint estimator (its trajectory, map and per-iteration matched-feature counts, or the
segments of :func:`.segmented.run_segmented`, which restarts the local SLAM at every break) and the
log's position fixes:

1. segment the run where matches fail or the estimated error grows (:mod:`.segmentation`);
2. per segment, a cubic B-spline of the local path over time (:mod:`.bspline`, eq. 33-37);
3. per segment, the rigid transform to the fixes' frame by least squares between the spline at the fix
   times and the fixes (:mod:`.global_map`); segments without three non-collinear pairs are left out.
   A local map whose rigid fit is inconsistent with the fixes' covariance (a continuous run that bent
   inside it) is split into pieces placed each by its own rigid fit, and a piece that no split makes
   rigid is left out (:mod:`.piecewise`, an extension of section 6.3);
4. the segment's landmarks and path mapped into ``world`` (eq. 38) and integrated;
5. at every iteration of a placed segment, the mapped local position fused with the fix interpolated
   to that time (eq. 26-32, :mod:`relpoint.lagrange`, :mod:`.covariance_fusion`); elsewhere (gaps, left-out
   segments) the interpolated fix alone gives the position.

A post-step has no estimator covariance, so two models stand in for it. For the segmentation
threshold, the local error grows as ``local_sigma + drift_fraction * s`` with ``s`` the path length since
the segment started. For the spline (eq. 37) and the fusion (eq. 31-32) each local position has
``P_vv(i) = local_sigma^2 I``: the drift accumulated along a segment is not an error of the mapped path
but of its shape, which the rigid fit absorbs and shows in its residuals; those inflate the
transform's covariance (:class:`.global_map.SegmentTransform`), which is added to ``R P_vv R^T``.
Orientations are the estimator's, turned by the segment's rotation (the nearest placed segment's for
iterations outside one); fixes carry no orientation.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from relpoint.errors import EstimatorError, UsageError
from relpoint.fusion.bspline import PathSpline
from relpoint.fusion.covariance_fusion import fuse_estimates
from relpoint.fusion.global_map import SegmentTransform, fit_segment
from relpoint.fusion.piecewise import Piece, split_segment
from relpoint.fusion.segmentation import NO_SEGMENT, segment_run, segment_slices
from relpoint.geometry import FloatArray
from relpoint.lagrange import interpolate_fixes
from relpoint.settings import Settings, setting
from relpoint.types import IntArray, LandmarkMap, PositionFix, Trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FusionConfig(Settings):
    """Settings of the fusion post-step. Metres."""

    settings_name: ClassVar[str] = "fusion"

    min_matches: int = setting(5, low=1)
    """``m_l`` of Algorithm 3: a pair of iterations with fewer matched features breaks the local map."""
    max_position_error: float = setting(math.inf, above=0, high=math.inf)
    """A local map also ends when its estimated position error exceeds this (m; inf = never)."""
    local_sigma: float = setting(0.1, low=0)
    """Position standard deviation of a local estimate relative to its neighbours (m, per axis)."""
    drift_fraction: float = setting(0.01, low=0)
    """Growth of the estimated local position error per metre travelled within a segment (for
    ``max_position_error``)."""
    min_segment_length: int = setting(4, low=4)
    """Segments with fewer iterations are dropped (a cubic B-spline needs four positions)."""
    min_pairs: int = setting(3, low=3)
    """Fewest (spline position, fix) pairs that place a segment (at least 3)."""
    min_spread: float = setting(1.0, low=0)
    """Smallest RMS distance of a segment's pair positions from a straight line (m); below it the
    rotation is undetermined and the segment is left out."""
    split_significance: float = setting(0.001, low=0, below=1)
    """A segment whose rigid fit to the fixes fails a chi-square test at this significance is split
    into pieces placed each by its own rigid fit (:mod:`.piecewise`); 0 = never split."""

    def check(self) -> None:
        """The local estimate has a covariance: ``local_sigma`` and ``drift_fraction`` are not both 0."""
        if self.local_sigma == 0 and self.drift_fraction == 0:
            raise UsageError(
                "fusion settings local_sigma and drift_fraction cannot both be 0 (the local estimate needs a covariance)"
            )


@dataclass(frozen=True, eq=False)
class SegmentResult:
    """One local map (segment) and what became of it.

    Attributes
    ----------
    index: segment number (0, 1, ... in time order).
    iterations: (K,) iteration indices of the segment.
    local_trajectory: the estimator's poses over the segment (its local frame).
    landmark_rows: (L,) rows of the input map assigned to the segment.
    local_landmarks: those landmarks in the local frame.
    transform: ``T_world_local`` fitted to the fixes, or None when the segment was left out.
    refused: why the segment was left out (None when placed).
    global_trajectory, global_landmarks: the segment mapped into ``world`` by eq. 38 (None when left out).
    local_map: the local map (Algorithm 3 segment) the segment belongs to; a local map whose rigid fit
        fails the chi-square test of :mod:`.piecewise` is split into several segments.
    """

    index: int
    iterations: IntArray
    local_trajectory: Trajectory
    landmark_rows: IntArray
    local_landmarks: LandmarkMap
    transform: SegmentTransform | None
    refused: str | None = None
    global_trajectory: Trajectory | None = None
    global_landmarks: LandmarkMap | None = None
    local_map: int = 0


@dataclass(frozen=True, eq=False)
class FusionResult:
    """The globally consistent path and map, and the parts they came from.

    Attributes
    ----------
    trajectory: global ``T_world_sensor`` at every input iteration.
    covariances: (N, 3, 3) position covariance of each global pose, m².
    fused: (N,) True where a placed segment was fused with the fix (eq. 31-32), False where the
        interpolated fix alone gives the position.
    labels: (N,) segment (index into ``segments``) of each iteration, -1 for none.
    landmarks: the integrated global map (placed segments' landmarks, eq. 38).
    segments: every segment, placed or left out.
    fix_positions, fix_covariances: (N, 3) and (N, 3, 3): the fixes interpolated to every iteration
        (eq. 26-30), i.e. the fixes-alone path.
    """

    trajectory: Trajectory
    covariances: FloatArray
    fused: npt.NDArray[np.bool_]
    labels: IntArray
    landmarks: LandmarkMap
    segments: list[SegmentResult]
    fix_positions: FloatArray
    fix_covariances: FloatArray
    summary: dict[str, Any] = field(default_factory=dict)


def _landmark_iterations(
    landmarks: LandmarkMap, positions: FloatArray, map_size: npt.ArrayLike | None
) -> tuple[IntArray, str]:
    """The iteration each landmark belongs to and how that was found (see :func:`fuse`)."""
    m = len(landmarks)
    first = landmarks.first_iteration
    known = (first >= 0) & (first < len(positions)) if first is not None else np.zeros(m, dtype=bool)
    if m and known.all():
        # The estimator says when each landmark was started: right even where the map also lost
        # landmarks (vanished, or left out as unreliable), which the map's growth cannot tell.
        return first.astype(np.int64), "first iteration"
    if m and known.any():  # e.g. the EKF's followed movers, kept outside its map: the nearest position
        _, nearest = cKDTree(positions).query(landmarks.positions[~known])
        owner = first.astype(np.int64).copy()
        owner[~known] = nearest
        return owner, "first iteration (nearest position where unknown)"
    if map_size is not None:
        sizes = np.asarray(map_size, dtype=np.int64).reshape(-1)
        if len(sizes) == len(positions) and np.all(np.diff(sizes) >= 0) and len(sizes) and sizes[-1] == m:
            # Rows are appended in creation order: row j was created at the first iteration mapping > j.
            return np.searchsorted(sizes, np.arange(m), side="right").astype(np.int64), "creation"
    if m == 0:
        return np.zeros(0, dtype=np.int64), "nearest"
    _, nearest = cKDTree(positions).query(landmarks.positions)
    return np.asarray(nearest, dtype=np.int64), "nearest"


def _subset(landmarks: LandmarkMap, rows: IntArray, positions: FloatArray | None = None) -> LandmarkMap:
    return LandmarkMap(
        landmarks.positions[rows] if positions is None else positions,
        landmarks.observations[rows],
        landmarks.dynamic[rows],
        landmarks.gt_id[rows],
        first_iteration=None if landmarks.first_iteration is None else landmarks.first_iteration[rows],
    )


def _local_covariances(count: int, config: FusionConfig) -> FloatArray:
    """``P_vv(i) = local_sigma^2 I`` for ``count`` local positions (module docstring)."""
    return np.repeat((config.local_sigma**2 * np.eye(3))[None], count, axis=0)


def fuse(
    trajectory: Trajectory,
    landmarks: LandmarkMap,
    matched: npt.ArrayLike | None,
    fixes: Sequence[PositionFix],
    config: FusionConfig | None = None,
    *,
    map_size: npt.ArrayLike | None = None,
    landmark_iterations: npt.ArrayLike | None = None,
    position_sigma: npt.ArrayLike | None = None,
    labels: npt.ArrayLike | None = None,
    landmark_labels: npt.ArrayLike | None = None,
) -> FusionResult:
    """Fuse a local SLAM run with position fixes into a global path and map (Algorithm 3).

    Parameters
    ----------
    trajectory:
        The estimator's ``T_world_sensor`` per iteration (N poses), in its own (local) frame.
    landmarks:
        The estimator's final map (M landmarks), same frame.
    matched:
        (N,) features matched between iteration ``k-1`` and ``k`` (see :mod:`.segmentation` for how to
        derive them when an estimator does not report them); None when ``labels`` is given.
    fixes:
        Position fixes in ``world`` (any rate; time order).
    config:
        Thresholds and the local error model (:class:`FusionConfig`).
    map_size:
        (N,) landmarks mapped after each iteration; when it never shrinks and ends at M, landmark row
        ``j`` belongs to the iteration that created it. Otherwise each landmark belongs to the
        iteration whose position is nearest to it. Both yield to ``landmarks.first_iteration`` when
        the estimator recorded it for every landmark.
    landmark_iterations:
        (M,) the iteration each landmark belongs to, overriding both rules above.
    position_sigma:
        (N,) an estimator's own position standard deviation for the segmentation's error threshold.
    labels, landmark_labels:
        (N,) and (M,) segments already made (e.g. by :func:`.segmented.run_segmented`, which restarts
        the estimator per segment), -1 for none; they replace the segmentation and the landmark
        assignment above.

    Raises
    ------
    EstimatorError
        No fixes, or a matched-count array that does not match the trajectory.
    """
    config = config or FusionConfig()
    n = len(trajectory)
    fixes = sorted(fixes, key=lambda f: f.stamp_ns)
    if not fixes:
        raise EstimatorError("no position fix to fuse with", "the log needs /fix messages (or pass --fix-topic)")
    fix_stamps = np.array([f.stamp_ns for f in fixes], dtype=np.int64)
    fix_positions = np.array([f.position for f in fixes], dtype=np.float64).reshape(-1, 3)
    fix_covariances = np.array([f.covariance for f in fixes], dtype=np.float64).reshape(-1, 3, 3)

    positions = np.asarray(trajectory.positions)
    if labels is not None:
        labels = np.asarray(labels, dtype=np.int64).reshape(-1)
        if len(labels) != n:
            raise EstimatorError(f"{len(labels)} segment labels for {n} iterations")
    elif matched is None:
        raise EstimatorError("fuse needs the matched-feature counts or the segment labels")
    else:
        matched = np.asarray(matched, dtype=np.int64).reshape(-1)
        if len(matched) != n:
            raise EstimatorError(f"{len(matched)} matched counts for {n} iterations")
        labels = segment_run(
            matched,
            min_matches=config.min_matches,
            positions=positions,
            position_sigma=position_sigma,
            local_sigma=config.local_sigma,
            drift_fraction=config.drift_fraction,
            max_position_error=config.max_position_error,
            min_length=config.min_segment_length,
        )
    owner: IntArray | None = None
    if landmark_labels is not None:
        landmark_labels = np.asarray(landmark_labels, dtype=np.int64).reshape(-1)
        if len(landmark_labels) != len(landmarks):
            raise EstimatorError(f"{len(landmark_labels)} landmark labels for {len(landmarks)} landmarks")
        owner_rule = "given"
    elif landmark_iterations is not None:
        owner = np.asarray(landmark_iterations, dtype=np.int64).reshape(-1)
        if len(owner) != len(landmarks) or np.any((owner < 0) | (owner >= n)):
            raise EstimatorError(f"landmark_iterations must hold {len(landmarks)} iteration indices in [0, {n})")
        owner_rule = "given"
        landmark_labels = labels[owner] if len(owner) else np.zeros(0, dtype=np.int64)
    else:
        owner, owner_rule = _landmark_iterations(landmarks, positions, map_size)
    if landmark_labels is None:
        assert owner is not None
        landmark_labels = labels[owner] if len(owner) else np.zeros(0, dtype=np.int64)

    # Eq. 26-30: the fixes at every iteration's time.
    x_b, P_b = interpolate_fixes(fix_stamps, fix_positions, fix_covariances, trajectory.stamps_ns)

    rotations = Rotation.from_quat(trajectory.quats_xyzw).as_matrix()
    global_positions = x_b.copy()
    global_covariances = P_b.copy()
    global_rotations = rotations.copy()
    placed_by = np.full(n, NO_SEGMENT, dtype=np.int64)
    fused = np.zeros(n, dtype=bool)
    segments: list[SegmentResult] = []
    global_maps: list[LandmarkMap] = []

    piece_labels = np.full(n, NO_SEGMENT, dtype=np.int64)
    local_maps = segment_slices(labels)
    split = 0
    for local_index, segment_iterations in enumerate(local_maps):
        if len(segment_iterations) == 0:
            continue
        segment_rows = np.flatnonzero(landmark_labels == local_index).astype(np.int64)
        pieces = split_segment(
            trajectory.stamps_ns[segment_iterations], positions[segment_iterations],
            _local_covariances(len(segment_iterations), config), fix_stamps, fix_positions, fix_covariances,
            significance=config.split_significance, min_pairs=config.min_pairs, min_spread=config.min_spread,
            min_length=config.min_segment_length,
        )  # fmt: skip
        if len(pieces) > 1:
            split += 1
            log.info(
                "local map %d (iterations %d-%d) is not rigid against the fixes: placed in %d pieces",
                local_index, segment_iterations[0], segment_iterations[-1], len(pieces),
            )  # fmt: skip
        piece_of_row = _landmark_pieces(segment_rows, landmarks, positions, segment_iterations, pieces)
        for piece, part in enumerate(pieces):
            index = len(segments)
            iterations = segment_iterations[part.start : part.stop]
            rows = segment_rows[piece_of_row == piece]
            piece_labels[iterations] = index
            segment = _place_segment(
                index, local_index, iterations, rows, trajectory, landmarks, config,
                fix_stamps, fix_positions, fix_covariances, part,
            )  # fmt: skip
            segments.append(segment)
            transform = segment.transform
            if transform is None:
                continue
            # Eq. 38 for the path, then eq. 31-32 with the fix at each iteration.
            local_cov = _local_covariances(len(iterations), config)
            x_c = transform.apply(positions[iterations])
            R = transform.rotation
            P_c = R @ local_cov @ R.T + transform.point_covariance(positions[iterations])
            x_v, P_v = fuse_estimates(x_c, P_c, x_b[iterations], P_b[iterations])
            global_positions[iterations] = x_v
            global_covariances[iterations] = P_v
            global_rotations[iterations] = R @ rotations[iterations]
            placed_by[iterations] = index
            fused[iterations] = True
            assert segment.global_landmarks is not None
            global_maps.append(segment.global_landmarks)

    _orient_unplaced(global_rotations, rotations, placed_by, segments)
    quats = Rotation.from_matrix(global_rotations).as_quat()
    global_traj = Trajectory(trajectory.stamps_ns, global_positions, quats)
    global_map = LandmarkMap.concatenate(global_maps)
    placed = [s for s in segments if s.transform is not None]
    summary: dict[str, Any] = {
        "local_maps": len(local_maps),
        "local_maps_split": split,
        "segments": len(segments),
        "segments_placed": len(placed),
        "segments_left_out": len(segments) - len(placed),
        "iterations_fused": int(fused.sum()),
        "iterations_fixes_only": int(n - fused.sum()),
        "fixes": len(fixes),
        "landmarks_placed": len(global_map),
        "landmarks_left_out": len(landmarks) - len(global_map),
        "landmark_assignment": owner_rule,
    }
    if not placed:
        log.warning("no segment could be placed: the global path is the interpolated fixes alone and the map is empty")
    return FusionResult(global_traj, global_covariances, fused, piece_labels, global_map, segments, x_b, P_b, summary)


def _landmark_pieces(
    rows: IntArray, landmarks: LandmarkMap, positions: FloatArray, iterations: IntArray, pieces: list[Piece]
) -> IntArray:
    """Piece (index into ``pieces``) of each landmark row of one local map: that of the nearest path position.

    Not the piece of the iteration that created the landmark: a local map split into pieces is one
    that re-associated or bent, and its final landmark estimates follow the part of the path that
    last corrected them (on ``figure8-gaps`` seed 1 the continuous EKF's map has 8.2 m RMS error placed
    by the nearest rule, 10.7 m by the creation rule).
    """
    if len(pieces) == 1 or len(rows) == 0:
        return np.zeros(len(rows), dtype=np.int64)
    starts = np.array([piece.start for piece in pieces], dtype=np.int64)
    _, within = cKDTree(positions[iterations]).query(landmarks.positions[rows])
    return (np.searchsorted(starts, np.asarray(within, dtype=np.int64), side="right") - 1).clip(0, len(pieces) - 1)


def _place_segment(
    index: int,
    local_index: int,
    iterations: IntArray,
    rows: IntArray,
    trajectory: Trajectory,
    landmarks: LandmarkMap,
    config: FusionConfig,
    fix_stamps: IntArray,
    fix_positions: FloatArray,
    fix_covariances: FloatArray,
    piece: Piece,
) -> SegmentResult:
    """B-spline (eq. 33-37) and rigid fit (6.2-6.3) of one segment, its path and map by eq. 38."""
    positions = trajectory.positions[iterations]
    local_traj = Trajectory(trajectory.stamps_ns[iterations], positions, trajectory.quats_xyzw[iterations])
    local_map = _subset(landmarks, rows)
    name = f"segment {index} (iterations {iterations[0]}-{iterations[-1]})"
    try:
        if not piece.rigid:
            raise EstimatorError(
                f"{name} is not rigid against the fixes: its rigid fit leaves chi-square {piece.statistic:.1f} "
                f"over {piece.dof} degrees of freedom (above {piece.threshold:.1f}, significance "
                f"{config.split_significance:g}) and no split into pieces of at least {config.min_pairs} fixes makes it rigid",
                "it is left out of the global map (split_significance=0 places it anyway)",
            )
        spline = PathSpline.fit(local_traj.stamps_ns, positions, _local_covariances(len(iterations), config))
        transform = fit_segment(
            spline, fix_stamps, fix_positions, fix_covariances,
            name=name, min_pairs=config.min_pairs, min_spread=config.min_spread,
        )  # fmt: skip
    except EstimatorError as error:
        log.warning("%s", error)
        return SegmentResult(index, iterations, local_traj, rows, local_map, None, str(error), local_map=local_index)
    segment_global = Trajectory.from_matrices(local_traj.stamps_ns, transform.matrix @ local_traj.matrices())
    segment_map = _subset(landmarks, rows, transform.apply(landmarks.positions[rows]))
    return SegmentResult(
        index, iterations, local_traj, rows, local_map, transform, None, segment_global, segment_map, local_index
    )


def _orient_unplaced(
    global_rotations: FloatArray, rotations: FloatArray, placed_by: IntArray, segments: list[SegmentResult]
) -> None:
    """Turn the orientations outside placed segments by the nearest placed segment's rotation (in place)."""
    placed_iterations = np.flatnonzero(placed_by >= 0)
    if len(placed_iterations) == 0:
        return
    transforms = {s.index: s.transform for s in segments if s.transform is not None}
    for k in np.flatnonzero(placed_by < 0):
        nearest = placed_iterations[np.argmin(np.abs(placed_iterations - k))]
        transform = transforms[int(placed_by[nearest])]
        assert transform is not None
        global_rotations[k] = transform.rotation @ rotations[k]
