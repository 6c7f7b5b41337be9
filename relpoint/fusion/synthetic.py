"""A stand-in local SLAM for tests and benchmarks of the fusion post-step.

It turns a :class:`relpoint.simulation.Simulation` into what a local SLAM that restarts at every
segment (Algorithm 3) would report, without running an estimator: segments from the features matched
between consecutive iterations (shared ground-truth ids), each segment's path in its own local frame
(starting at the identity) with a random-walk drift, gap iterations dead-reckoned from the previous
segment with a larger drift, and each landmark seen in a segment placed from its first observation
there, with the drift of that moment. All draws come from the ``rng`` passed in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from relpoint.fusion.segmentation import matched_counts_from_ids, segment_run, segment_slices
from relpoint.geometry import FloatArray, invert_pose, transform_points
from relpoint.simulation import Simulation
from relpoint.types import IntArray, LandmarkMap, PositionFix, Trajectory


@dataclass(frozen=True, eq=False)
class SyntheticRun:
    """A synthetic local SLAM run: what :func:`relpoint.fusion.fuse` takes, plus the truth it came from.

    Attributes
    ----------
    trajectory: local ``T_world_sensor`` per iteration (segments in their own frames).
    landmarks: local map; ``gt_id`` holds the true ids.
    landmark_iterations: (M,) iteration at which each landmark was placed.
    matched: (N,) ids shared by iterations ``k-1`` and ``k``.
    fixes: the simulation's fixes.
    """

    trajectory: Trajectory
    landmarks: LandmarkMap
    landmark_iterations: IntArray
    matched: IntArray
    fixes: list[PositionFix]


def synthetic_local_slam(
    simulation: Simulation,
    rng: np.random.Generator,
    *,
    min_matches: int = 5,
    step_sigma: float = 0.02,
    yaw_sigma_deg: float = 0.02,
    gap_step_sigma: float = 0.3,
    landmark_sigma: float = 0.1,
) -> SyntheticRun:
    """Simulate a restarting local SLAM over ``simulation`` (see the module docstring).

    ``step_sigma`` (m) and ``yaw_sigma_deg`` (deg) are the per-iteration random-walk drift inside a
    segment, ``gap_step_sigma`` (m) per iteration in gaps, ``landmark_sigma`` (m) the landmark noise.
    """
    steps = list(simulation.steps())
    truth = np.array([s.T_world_sensor for s in steps])
    ids = [s.observation.ids if s.observation.ids is not None else np.zeros(0, np.int64) for s in steps]
    matched = matched_counts_from_ids(ids)
    labels = segment_run(matched, min_matches=min_matches)
    n = len(steps)
    # Drift: T_true_est at each iteration, a random walk in position and yaw, reset at segment starts.
    estimated = np.empty_like(truth)
    starts = {int(s[0]) for s in segment_slices(labels)}
    T_local_world = invert_pose(truth[0])
    drift = np.eye(4)
    for k in range(n):
        if k in starts:
            T_local_world = invert_pose(truth[k])  # a new local map: its frame is this pose
            drift = np.eye(4)
        elif k:
            sigma = step_sigma if labels[k] >= 0 else gap_step_sigma
            step = np.eye(4)
            step[:3, :3] = Rotation.from_euler("z", rng.normal(0.0, yaw_sigma_deg), degrees=True).as_matrix()
            step[:3, 3] = rng.normal(0.0, sigma, 3)
            drift = drift @ step
        estimated[k] = T_local_world @ truth[k] @ drift
    trajectory = Trajectory.from_matrices([s.stamp_ns for s in steps], estimated)

    positions: list[FloatArray] = []
    gt_ids: list[int] = []
    owners: list[int] = []
    seen: set[tuple[int, int]] = set()
    for k, step in enumerate(steps):
        if labels[k] < 0 or step.observation.ids is None:
            continue
        for point, gt in zip(step.observation.points, step.observation.ids.tolist(), strict=True):
            if gt < 0 or (int(labels[k]), gt) in seen:
                continue
            seen.add((int(labels[k]), gt))
            local = transform_points(estimated[k], point[None])[0] + rng.normal(0.0, landmark_sigma, 3)
            positions.append(local)
            gt_ids.append(gt)
            owners.append(k)
    m = len(positions)
    landmarks = LandmarkMap(
        np.array(positions).reshape(-1, 3), np.ones(m, np.int64), np.zeros(m, bool), np.array(gt_ids, np.int64)
    )
    fixes = [s.fix for s in steps if s.fix is not None]
    return SyntheticRun(trajectory, landmarks, np.array(owners, dtype=np.int64), matched, fixes)
