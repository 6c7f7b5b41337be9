"""The topic of every role in a log (:class:`Topics`), in a module of its own so that reading a batch
plan does not import the log reader (rosbags, mcap)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True)
class Topics:
    """Topic name of every role in a log; the defaults are the log format's."""

    points: str = "/points"
    ground_truth_pose: str = "/ground_truth/pose"
    ground_truth_landmarks: str = "/ground_truth/landmarks"
    odometry: str = "/odom"
    fix: str = "/fix"
    depth: str = "/camera/depth/image"
    camera_info: str = "/camera/depth/camera_info"
    color: str = "/camera/color/image"

    def roles(self) -> dict[str, str]:
        """Role name -> topic."""
        return dataclasses.asdict(self)
