"""Writing a simulated RGB-D sequence as a relpoint log, from core types, with its scene beside it.

Per frame, at its stamp and in this order: ``/camera/depth/camera_info`` (first frame only),
``/ground_truth/pose`` (``T_world_camera``) and the same as ``/tf`` (world -> camera), ``/camera/color/image`` (rgb8, registered to the depth) and
``/camera/depth/image`` (16UC1 millimetres, 0 = none). The settings go into a ``relpoint.simulation`` metadata record. The
scene's reference cloud (points and normals sampled over the meshes, in ``world``) can be written as a
PLY file for map-accuracy evaluation.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np

from formats import ros2
from formats.log import LogWriter, Topics, metadata_json
from formats.ply import stored_coordinates, write_ply
from relpoint.geometry import FloatArray
from relpoint.types import DepthFrame, Pose


def write_rgbd_simulation_log(
    frames: Iterable[DepthFrame],
    path: str | os.PathLike[str],
    *,
    poses: FloatArray,
    settings: Mapping[str, Any],
    compression: str = "zstd",
    topics: Topics | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> dict[str, int]:
    """Write every frame to the log ``path`` (atomically) and return message counts.

    ``poses`` (N, 4, 4) are the true camera poses ``T_world_camera``, one per frame; ``settings`` the
    simulation's settings as plain values (stored with ``scenario: room``).

    ``on_frame(k)`` is called after frame ``k`` (for progress bars).
    """
    topics = topics or Topics()
    counts = {"camera_info": 0, "depth": 0, "color": 0, "ground_truth_pose": 0, "tf": 0}
    metadata = {"relpoint.simulation": metadata_json({"scenario": "room", **settings})}
    with LogWriter(path, compression=compression, metadata=metadata) as writer:
        for index, frame in enumerate(frames):
            stamp = frame.stamp_ns
            if index == 0:
                writer.write_camera_info(stamp, frame.intrinsics, topics.camera_info)
                counts["camera_info"] += 1
            pose = Pose.from_matrix(stamp, poses[index])
            writer.write_ground_truth_pose(pose, topics.ground_truth_pose)
            counts["ground_truth_pose"] += 1
            writer.write("/tf", ros2.TF_MESSAGE, ros2.tf_to_msg(stamp, "world", "camera", pose.position, pose.quat_xyzw), stamp)
            counts["tf"] += 1
            if frame.color is not None:  # colour first: a reader can attach it to the depth that follows
                writer.write_color(stamp, frame.color, topics.color)
                counts["color"] += 1
            writer.write_depth(stamp, frame.depth, topics.depth, encoding="16UC1")
            counts["depth"] += 1
            if on_frame is not None:
                on_frame(index)
    return counts


def write_reference_cloud(points: FloatArray, normals: FloatArray, path: str | os.PathLike[str]) -> int:
    """Write a scene's reference cloud (points and unit normals (N, 3) in ``world``, metres; stored as
    x, y, z, nx, ny, nz float32) as a binary PLY; returns its size."""
    vertices = np.empty(len(points), dtype=[(n, "<f4") for n in ("x", "y", "z", "nx", "ny", "nz")])
    for k, name in enumerate(("x", "y", "z")):
        vertices[name] = points[:, k]
        vertices["n" + name] = normals[:, k]
    write_ply(path, vertices, comments=["relpoint simulated room: surface samples of the scene meshes"])
    return len(points)


def dense_map_vertices(
    positions: np.ndarray, normals: np.ndarray, colors: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """A dense map (``DenseFusion.dense_map()``) as PLY vertices for :func:`formats.ply.write_ply`.

    Fields: x, y, z float32 (float64 far from the origin: :func:`formats.ply.stored_coordinates`), nx,
    ny, nz float32, red, green, blue uint8 and weight float32.
    """
    xyz = stored_coordinates(positions)
    fields = [(n, xyz.dtype) for n in ("x", "y", "z")] + [(n, "<f4") for n in ("nx", "ny", "nz")]
    fields += [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("weight", "<f4")]
    vertices = np.empty(len(positions), dtype=fields)
    for k, name in enumerate(("x", "y", "z")):
        vertices[name] = xyz[:, k]
        vertices["n" + name] = normals[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        vertices[name] = colors[:, k]
    vertices["weight"] = weights
    return vertices
