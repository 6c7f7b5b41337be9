"""Writing a simulated run as a relpoint log, from core types (:class:`relpoint.types.SimulatedStep`)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from formats import ros2
from formats.log import LogWriter, Topics, metadata_json
from relpoint.types import GroundTruthLandmarks, Pose, SimulatedStep, Trajectory

#: Where simulated logs put the true sensor pose as a transform, as ROS does.
TF_TOPIC = "/tf"


def write_simulation_log(
    steps: Iterable[SimulatedStep],
    path: str | os.PathLike[str],
    *,
    landmarks: GroundTruthLandmarks,
    ground_truth: Trajectory,
    settings: Mapping[str, Any],
    compression: str = "zstd",
    topics: Topics | None = None,
    on_step: Callable[[int], None] | None = None,
) -> dict[str, int]:
    """Write every step of a simulated run to ``path`` (atomically) and return message counts.

    ``landmarks`` are the true landmarks at the first stamp, ``ground_truth`` the true sensor poses
    ``T_world_sensor`` (one per step, indexed by ``step.index``) and ``settings`` the simulation's
    settings as plain values.

    Per iteration, at its stamp: ``/ground_truth/landmarks`` (first iteration only), the true pose on
    ``/ground_truth/pose`` and as ``/tf`` (world -> the observation's frame, so that Foxglove places
    ``/points``), the observation on ``/points``, then ``/odom`` and ``/fix`` when the
    simulation made them. The settings are stored as a ``relpoint.simulation`` metadata record.
    ``on_step(k)`` is called after iteration ``k`` (for progress bars).
    """
    topics = topics or Topics()
    counts = {"points": 0, "ground_truth_pose": 0, "ground_truth_landmarks": 0, "odometry": 0, "fix": 0, "tf": 0}
    metadata = {"relpoint.simulation": metadata_json(dict(settings))}
    truth = ground_truth
    with LogWriter(path, compression=compression, metadata=metadata) as writer:
        for step in steps:
            if step.index == 0:
                writer.write_ground_truth_landmarks(step.stamp_ns, landmarks, topics.ground_truth_landmarks)
                counts["ground_truth_landmarks"] += 1
            position, quat = truth.positions[step.index], truth.quats_xyzw[step.index]
            pose = Pose(step.stamp_ns, tuple(position.tolist()), tuple(quat.tolist()))  # type: ignore[arg-type]
            writer.write_ground_truth_pose(pose, topics.ground_truth_pose)
            writer.write(TF_TOPIC, ros2.TF_MESSAGE,
                         ros2.tf_to_msg(step.stamp_ns, "world", step.observation.frame_id, position, quat), step.stamp_ns)  # fmt: skip
            counts["tf"] += 1
            writer.write_observation(step.observation, topics.points)
            counts["ground_truth_pose"] += 1
            counts["points"] += 1
            if step.odometry is not None:
                writer.write_odometry(step.odometry, topics.odometry)
                counts["odometry"] += 1
            if step.fix is not None:
                writer.write_fix(step.fix, topics.fix)
                counts["fix"] += 1
            if on_step is not None:
                on_step(step.index)
    return counts
