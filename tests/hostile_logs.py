"""Logs that are valid MCAP but hostile to an estimator, written with mcap-ros2-support (not relpoint).

Used by the reliability suite and by ``benchmarks/hostile.py`` (peak memory per case). Each builder
takes a simulation from relpoint's simulator as the honest content and spoils it in one way.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap_ros2.writer import Writer as Ros2Writer

from formats import ros2
from relpoint.geometry import matrix_to_position_quat
from relpoint.simulation import SimulationConfig, simulate


def _header(stamp: int, frame: str) -> dict:
    return {"stamp": {"sec": stamp // 1_000_000_000, "nanosec": stamp % 1_000_000_000}, "frame_id": frame}


def _cloud(stamp: int, points: np.ndarray, ids: np.ndarray) -> dict:
    dtype = np.dtype({"names": ["x", "y", "z", "id"], "formats": ["<f4", "<f4", "<f4", "<i4"]})
    data = np.zeros(len(points), dtype=dtype)
    data["x"], data["y"], data["z"] = np.asarray(points, dtype=np.float64).T
    data["id"] = ids
    fields = [{"name": n, "offset": o, "datatype": d, "count": 1}
              for n, o, d in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("id", 12, 5))]  # fmt: skip
    return {"header": _header(stamp, "sensor"), "height": 1, "width": len(points), "fields": fields,
            "is_bigendian": False, "point_step": 16, "row_step": 16 * len(points), "data": data.tobytes(),
            "is_dense": True}  # fmt: skip


def _pose(stamp: int, position: np.ndarray, quat: np.ndarray) -> dict:
    return {"header": _header(stamp, "world"),
            "pose": {"position": dict(zip("xyz", map(float, position), strict=True)),
                     "orientation": dict(zip("xyzw", map(float, quat), strict=True))}}  # fmt: skip


def _odometry(stamp: int, linear: np.ndarray, angular: np.ndarray, covariance: np.ndarray | None = None) -> dict:
    if covariance is None:
        covariance = np.diag([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4])
    covariance = np.asarray(covariance, dtype=np.float64).reshape(-1).tolist()
    twist = {"linear": dict(zip("xyz", map(float, linear), strict=True)),
             "angular": dict(zip("xyz", map(float, angular), strict=True))}  # fmt: skip
    return {"header": _header(stamp, "odom"), "child_frame_id": "sensor",
            "pose": {"pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                              "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}, "covariance": [0.0] * 36},
            "twist": {"twist": twist, "covariance": covariance}}  # fmt: skip


def _fix(stamp: int, position: np.ndarray, sigma: float) -> dict:
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = np.eye(3) * sigma**2
    covariance[3:, 3:] = np.eye(3) * 1e9
    return {"header": _header(stamp, "world"),
            "pose": {"pose": {"position": dict(zip("xyz", map(float, position), strict=True)),
                              "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                     "covariance": covariance.reshape(-1).tolist()}}  # fmt: skip


Spoil = Callable[[int, int, np.ndarray, np.ndarray], tuple[int, np.ndarray, np.ndarray]]


def write_log(
    path: Path,
    config: SimulationConfig,
    spoil: Spoil | None = None,
    *,
    odometry: bool = False,
    odometry_covariance: np.ndarray | None = None,
    fixes_every: int = 0,
) -> Path:
    """Write ``config``'s simulation with mcap-ros2-support; ``spoil(k, stamp, points, ids)`` may change
    each iteration's stamp, points and ids first; ``odometry_covariance`` (6, 6) replaces the twist
    covariance of every odometry message."""
    simulation = simulate(config)
    with path.open("wb") as stream:
        writer = Ros2Writer(stream)
        schemas = {name: writer.register_msgdef(name, ros2.message_definition(name))
                   for name in (ros2.POINT_CLOUD2, ros2.POSE_STAMPED, ros2.ODOMETRY, ros2.POSE_WITH_COVARIANCE_STAMPED)}  # fmt: skip
        for step in simulation.steps():
            k, observation = step.index, step.observation
            position, quat = matrix_to_position_quat(step.T_world_sensor)
            stamp, points, ids = observation.stamp_ns, observation.points, observation.ids
            if spoil is not None:
                stamp, points, ids = spoil(k, stamp, points, ids)

            def write(topic: str, schema: str, message: dict, stamp: int = stamp) -> None:
                writer.write_message(topic=topic, schema=schemas[schema], message=message, log_time=stamp,
                                     publish_time=stamp)  # fmt: skip

            write("/ground_truth/pose", ros2.POSE_STAMPED, _pose(stamp, position, quat))
            if odometry and step.odometry is not None:
                write("/odom", ros2.ODOMETRY,
                      _odometry(stamp, step.odometry.linear, step.odometry.angular, odometry_covariance))  # fmt: skip
            if fixes_every and k % fixes_every == 0:
                write("/fix", ros2.POSE_WITH_COVARIANCE_STAMPED, _fix(stamp, position, 1.0))
            write("/points", ros2.POINT_CLOUD2, _cloud(stamp, points, ids))
        writer.finish()
    return path


def far_point(distance: float = 1e30) -> Spoil:
    """One point at ``distance`` metres added to every cloud."""

    def spoil(k: int, stamp: int, points: np.ndarray, ids: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
        return stamp, np.vstack([points, [[distance, 0.0, 0.0]]]), np.append(ids, -1)

    return spoil


def time_gap(at: int, seconds: float) -> Spoil:
    """Every stamp from iteration ``at`` on shifted ``seconds`` later."""

    def spoil(k: int, stamp: int, points: np.ndarray, ids: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
        return (stamp + int(seconds * 1e9) if k >= at else stamp), points, ids

    return spoil


def one_point(k: int, stamp: int, points: np.ndarray, ids: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """Only the first point of every cloud."""
    return stamp, points[:1], ids[:1]
