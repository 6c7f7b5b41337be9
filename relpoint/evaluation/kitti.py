"""KITTI odometry segment errors, as the KITTI devkit's ``evaluate_odometry.cpp`` computes them.

Geiger, Lenz, Urtasun, *Are we ready for autonomous driving? The KITTI vision benchmark suite* (CVPR
2012): from every ``step``-th frame, for each segment length (100, 200, ..., 800 m of reference path), the
first frame whose travelled reference distance exceeds the start's plus the length closes the segment;
the error pose ``E = (P_first^-1 P_last)^-1 (Q_first^-1 Q_last)`` gives a translation error ``|t_E| / len``
and a rotation error ``acos((trace(R_E) - 1) / 2) / len``. The benchmark reports their means over all
segments as percent and, by common convention, degrees per 100 m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.evaluation.association import MatchedPoses
from relpoint.evaluation.rpe import accumulated_distances
from relpoint.geometry import FloatArray, invert_pose
from relpoint.types import IntArray

#: Segment lengths of the KITTI odometry benchmark, metres.
KITTI_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)


@dataclass(frozen=True, eq=False)
class KittiSegmentErrors:
    """All evaluated segments (S,) and their means.

    Attributes
    ----------
    first, last: (S,) int64 frame indices of each segment's ends.
    length: (S,) segment length, metres.
    t_err: (S,) translation error per metre (multiply by 100 for percent).
    r_err: (S,) rotation error per metre, radians/m.
    """

    first: IntArray
    last: IntArray
    length: FloatArray
    t_err: FloatArray
    r_err: FloatArray

    def __len__(self) -> int:
        return len(self.first)

    @property
    def translation_percent(self) -> float:
        """Mean translation error over all segments, percent (the devkit's headline figure); NaN if none."""
        return float(np.mean(self.t_err) * 100.0) if len(self) else float("nan")

    @property
    def rotation_deg_per_100m(self) -> float:
        """Mean rotation error over all segments, degrees per 100 m; NaN if none."""
        return float(np.rad2deg(np.mean(self.r_err)) * 100.0) if len(self) else float("nan")

    def by_length(self) -> dict[float, tuple[float, float, int]]:
        """Per segment length: (translation %, rotation deg/100 m, number of segments)."""
        out: dict[float, tuple[float, float, int]] = {}
        for length in np.unique(self.length).tolist():
            sel = self.length == length
            out[length] = (
                float(np.mean(self.t_err[sel]) * 100.0),
                float(np.rad2deg(np.mean(self.r_err[sel])) * 100.0),
                int(np.count_nonzero(sel)),
            )
        return out


def kitti_segment_errors_from_poses(
    T_reference: npt.ArrayLike,
    T_estimate: npt.ArrayLike,
    lengths: tuple[float, ...] = KITTI_LENGTHS,
    step: int = 10,
) -> KittiSegmentErrors:
    """KITTI segment errors of frame-aligned poses (N, 4, 4) ``T_world_frame`` (reference and estimate).

    Parameters
    ----------
    T_reference, T_estimate:
        Poses of the same frames; no alignment is applied (KITTI poses start at the identity).
    lengths:
        Segment lengths, metres of reference path.
    step:
        Frames between segment starts (the devkit's ``step_size`` = 10, one second at 10 Hz).
    """
    gt = np.asarray(T_reference, dtype=np.float64)
    est = np.asarray(T_estimate, dtype=np.float64)
    if gt.shape != est.shape or gt.ndim != 3 or gt.shape[1:] != (4, 4):
        raise ValueError(f"poses must be two (N, 4, 4) arrays of equal shape, got {gt.shape} and {est.shape}")
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    n = len(gt)
    dist = accumulated_distances(gt[:, :3, 3]) if n else np.zeros(0)
    firsts_all = np.arange(0, n, step)
    firsts: list[IntArray] = []
    lasts: list[IntArray] = []
    seg_lengths: list[FloatArray] = []
    for length in lengths:
        # The devkit's lastFrameFromSegmentLength: the first i >= first with dist[i] > dist[first] + len.
        last = np.searchsorted(dist, dist[firsts_all] + length, side="right")
        ok = last < n
        firsts.append(firsts_all[ok])
        lasts.append(last[ok])
        seg_lengths.append(np.full(np.count_nonzero(ok), float(length)))
    # Order segments as the devkit does: by start frame, then by length.
    first = np.concatenate(firsts) if firsts else np.zeros(0, np.int64)
    last = np.concatenate(lasts) if lasts else np.zeros(0, np.int64)
    length_arr = np.concatenate(seg_lengths) if seg_lengths else np.zeros(0)
    order = np.lexsort((np.searchsorted(np.asarray(lengths), length_arr), first))
    first, last, length_arr = first[order].astype(np.int64), last[order].astype(np.int64), length_arr[order]
    # Rigid inverses (R^T, -R^T t) equal the devkit's general matrix inverse for SE(3) poses.
    delta_gt = invert_pose(gt[first]) @ gt[last]
    delta_est = invert_pose(est[first]) @ est[last]
    error = invert_pose(delta_est) @ delta_gt
    d = 0.5 * (error[:, 0, 0] + error[:, 1, 1] + error[:, 2, 2] - 1.0)
    r_err = np.arccos(np.clip(d, -1.0, 1.0))
    t_err = np.linalg.norm(error[:, :3, 3], axis=1)
    return KittiSegmentErrors(first, last, length_arr, t_err / length_arr, r_err / length_arr)


def kitti_segment_errors(
    matched: MatchedPoses, lengths: tuple[float, ...] = KITTI_LENGTHS, step: int = 10
) -> KittiSegmentErrors:
    """KITTI segment errors over matched pose pairs, taking the matching order as the frame order."""
    return kitti_segment_errors_from_poses(matched.reference_matrices(), matched.estimate_matrices(), lengths, step)
