"""RGB-D sequences to point logs: tracked corners as ``/points`` (``relpoint import ... --points``).

The frames come from a TUM RGB-D folder, a 7-Scenes folder (:mod:`formats.rgbd_import`) or an RGB-D
relpoint log (:func:`log_frames`); :class:`relpoint.frontend.KeypointFrontEnd` turns each into a
``sensor_msgs/PointCloud2`` in the camera's optical frame (``frame_id`` ``camera``) whose ``id`` field is
the persistent track id. The ground-truth poses are copied (``T_world_camera``, the frame the points
are in), so ``relpoint evaluate`` scores any point estimator on the result. Nothing else is written:
the log holds no images.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from formats.log import LogReader, LogWriter, Topics, metadata_json
from formats.rgbd_import import RgbdFrame
from relpoint.errors import InputError
from relpoint.frontend import KeypointFrontEnd, KeypointSettings
from relpoint.types import Intrinsics, Pose

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KeypointCounts:
    """What a keypoint import read and wrote."""

    frames: int
    observations: int
    points: int
    tracks: int
    ground_truth_pose: int
    frames_without_colour: int = 0
    frames_without_points: int = 0


def log_frames(path: str | os.PathLike[str], topics: Topics | None = None) -> Iterator[RgbdFrame | Pose]:
    """The RGB-D frames of a relpoint log, and its ground-truth poses as they come.

    Depth and colour images are paired by equal stamps (the log format writes them so); a frame is
    yielded once both halves are in, or without colour when a later depth image arrives first.
    Ground-truth poses are yielded unchanged, in log order.
    """
    reader = LogReader(path, topics)
    reader.require("depth", "camera_info")
    if not reader.role_present("color"):
        raise InputError(
            f"{path}: the log has no colour images ({reader.topics.color})",
            "keypoints are tracked in colour; give --color-topic if they are on another topic",
        )
    intrinsics: Intrinsics | None = None
    depths: dict[int, np.ndarray] = {}
    colours: dict[int, np.ndarray] = {}

    def flush_before(stamp: int) -> Iterator[RgbdFrame]:
        for old in sorted(s for s in depths if s < stamp):
            assert intrinsics is not None
            yield RgbdFrame(old, depths.pop(old), intrinsics, colours.pop(old, None))
        for old in [s for s in colours if s < stamp]:
            del colours[old]

    for record in reader.records(["camera_info", "depth", "color", "ground_truth_pose"]):
        if record.role == "ground_truth_pose":
            yield record.value
            continue
        if record.role == "camera_info":
            intrinsics = record.value
            continue
        yield from flush_before(record.stamp_ns)
        if record.role == "depth":
            if intrinsics is None:
                log.warning("depth image at %.6f s comes before any camera info; skipped", record.stamp_ns * 1e-9)
                continue
            depths[record.stamp_ns] = record.value
        else:
            colours[record.stamp_ns] = record.value
        if record.stamp_ns in depths and record.stamp_ns in colours:
            assert intrinsics is not None
            yield RgbdFrame(record.stamp_ns, depths.pop(record.stamp_ns), intrinsics, colours.pop(record.stamp_ns))
    yield from flush_before(np.iinfo(np.int64).max)


def write_keypoint_log(
    frames: Iterable[RgbdFrame | Pose],
    output: str | os.PathLike[str],
    *,
    settings: KeypointSettings | None = None,
    source: dict[str, object] | None = None,
    compression: str = "zstd",
    topics: Topics | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> KeypointCounts:
    """Track corners through ``frames`` and write them as a point log.

    ``frames`` holds RGB-D frames (with their ground-truth pose, if any) and, from a log, loose
    ground-truth poses to copy. A frame without colour cannot be tracked and is skipped, as is the
    observation of a frame where no corner has valid depth; both are counted and warned about once.
    """
    settings = settings or KeypointSettings()
    topics = topics or Topics()
    front_end = KeypointFrontEnd(settings)
    metadata = {
        "relpoint.import": metadata_json({**(source or {}), "kind": "keypoints"}),
        "relpoint.keypoints": metadata_json(settings.to_dict()),
    }
    frames_seen = observations = points = poses = no_colour = no_points = 0
    track_ids: set[int] = set()
    with LogWriter(output, compression=compression, metadata=metadata) as writer:
        for item in frames:
            if isinstance(item, Pose):
                writer.write_ground_truth_pose(item, topics.ground_truth_pose)
                poses += 1
                continue
            frames_seen += 1
            if item.pose is not None:
                writer.write_ground_truth_pose(item.pose, topics.ground_truth_pose)
                poses += 1
            if item.color is None:
                if no_colour == 0:
                    log.warning("frame at %.6f s has no colour image; frames without colour are skipped",
                                item.stamp_ns * 1e-9)  # fmt: skip
                no_colour += 1
                continue
            observation = front_end.observe(item.stamp_ns, item.color, item.depth, item.intrinsics)
            if len(observation) == 0:
                if no_points == 0:
                    log.warning("no corner with valid depth at %.6f s; such frames get no observation",
                                item.stamp_ns * 1e-9)  # fmt: skip
                no_points += 1
            else:
                writer.write_observation(observation, topics.points)
                observations += 1
                points += len(observation)
                assert observation.ids is not None
                track_ids.update(observation.ids.tolist())
            if on_frame is not None:
                on_frame(frames_seen - 1)
    return KeypointCounts(frames_seen, observations, points, len(track_ids), poses, no_colour, no_points)
