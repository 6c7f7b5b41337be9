"""Typed containers for what flows between the log readers, the estimators and the writers.

They validate shapes on construction and freeze their arrays (``writeable = False``), so no caller's
data changes behind its back. Times are integer nanoseconds (``stamp_ns``); positions are metres;
quaternions are ``(x, y, z, w)``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from relpoint.geometry import FloatArray, matrix_to_position_quat, pose_matrix

IntArray = npt.NDArray[np.int64]


def _frozen(array: npt.ArrayLike, dtype: npt.DTypeLike, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    out = np.array(array, dtype=dtype, copy=True)
    if out.ndim != 1 + len(shape_tail) or out.shape[1:] != shape_tail:
        expected = ", ".join(["N", *map(str, shape_tail)])
        raise ValueError(f"{name} must have shape ({expected}), got {out.shape}")
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class PointObservation:
    """The untransformed 3D points seen in one iteration.

    Attributes
    ----------
    stamp_ns:
        Time of the observation, integer nanoseconds.
    points:
        (N, 3) float64, metres, in the sensor frame ``frame_id`` (finite values only).
    ids:
        (N,) int64 ground-truth landmark ids (-1 = clutter), or ``None`` when the log has none.
        Estimators must not use them except in an explicit known-association mode.
    frame_id:
        Frame of ``points`` (``sensor`` or ``camera``).
    """

    stamp_ns: int
    points: FloatArray
    ids: IntArray | None = None
    frame_id: str = "sensor"

    def __post_init__(self) -> None:
        object.__setattr__(self, "points", _frozen(self.points, np.float64, (3,), "points"))
        if self.ids is not None:
            ids = _frozen(self.ids, np.int64, (), "ids")
            if len(ids) != len(self.points):
                raise ValueError(f"ids has {len(ids)} entries for {len(self.points)} points")
            object.__setattr__(self, "ids", ids)

    def __len__(self) -> int:
        return len(self.points)


@dataclass(frozen=True)
class Pose:
    """A timestamped pose ``T_world_frame``: position (3,) metres and quaternion (x, y, z, w)."""

    stamp_ns: int
    position: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]

    @classmethod
    def from_matrix(cls, stamp_ns: int, T_world_frame: npt.ArrayLike) -> Pose:
        position, quat = matrix_to_position_quat(T_world_frame)
        return cls(int(stamp_ns), tuple(position.tolist()), tuple(quat.tolist()))  # type: ignore[arg-type]

    def as_matrix(self) -> FloatArray:
        """The pose as a 4x4 homogeneous matrix ``T_world_frame``."""
        return pose_matrix(self.position, self.quat_xyzw)


@dataclass(frozen=True)
class TimeWindow:
    """A stretch of a log or trajectory: ``start_s`` to ``end_s`` seconds after its first stamp.

    ``None`` leaves that side open; both ``None`` is the whole of it.
    """

    start_s: float | None = None
    end_s: float | None = None

    def __post_init__(self) -> None:
        for name in ("start_s", "end_s"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and 0.0 <= value <= 1e9):
                raise ValueError(f"{name} must be between 0 and 1e9 s, got {value}")
        if self.start_s is not None and self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError(f"the window ends ({self.end_s} s) before it starts ({self.start_s} s)")

    @property
    def is_open(self) -> bool:
        """Whether the window takes everything."""
        return self.start_s is None and self.end_s is None

    def bounds_ns(self, first_ns: int) -> tuple[int, int]:
        """The window's first and last stamp (inclusive), nanoseconds, counted from ``first_ns``."""
        low = first_ns + round(self.start_s * 1e9) if self.start_s is not None else -(2**63)
        high = first_ns + round(self.end_s * 1e9) if self.end_s is not None else 2**63 - 1
        return low, high


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A sequence of poses ``T_world_frame`` with strictly increasing stamps.

    Attributes
    ----------
    stamps_ns: (N,) int64 nanoseconds.
    positions: (N, 3) float64 metres, in ``world``.
    quats_xyzw: (N, 4) float64 unit quaternions, orientation of the frame in ``world``.
    """

    stamps_ns: IntArray
    positions: FloatArray
    quats_xyzw: FloatArray

    def __post_init__(self) -> None:
        stamps = _frozen(self.stamps_ns, np.int64, (), "stamps_ns")
        positions = _frozen(self.positions, np.float64, (3,), "positions")
        quats = np.array(self.quats_xyzw, dtype=np.float64)
        if quats.ndim != 2 or quats.shape[1] != 4:
            raise ValueError(f"quats_xyzw must have shape (N, 4), got {quats.shape}")
        if not (len(stamps) == len(positions) == len(quats)):
            raise ValueError(
                f"stamps ({len(stamps)}), positions ({len(positions)}) and quaternions ({len(quats)}) differ in length"
            )
        if len(stamps) > 1 and np.any(np.diff(stamps) <= 0):
            raise ValueError("trajectory stamps must strictly increase")
        norms = np.linalg.norm(quats, axis=1)
        if np.any(~np.isfinite(norms)) or np.any(norms < 1e-9):
            raise ValueError("trajectory quaternions must be finite and non-zero")
        quats = _frozen(quats / norms[:, None], np.float64, (4,), "quats_xyzw")
        object.__setattr__(self, "stamps_ns", stamps)
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "quats_xyzw", quats)

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def timestamps(self) -> FloatArray:
        """Stamps in seconds (float64)."""
        return self.stamps_ns.astype(np.float64) * 1e-9

    def matrices(self) -> FloatArray:
        """All poses as (N, 4, 4) homogeneous matrices."""
        return pose_matrix(self.positions, self.quats_xyzw)

    @classmethod
    def from_poses(cls, poses: Iterable[Pose]) -> Trajectory:
        poses = list(poses)
        return cls(
            np.array([p.stamp_ns for p in poses], dtype=np.int64),
            np.array([p.position for p in poses], dtype=np.float64).reshape(-1, 3),
            np.array([p.quat_xyzw for p in poses], dtype=np.float64).reshape(-1, 4),
        )

    def cropped(self, window: TimeWindow, first_ns: int | None = None) -> Trajectory:
        """The poses inside ``window``, counted from ``first_ns`` (default: this trajectory's first stamp)."""
        if window.is_open or len(self) == 0:
            return self
        low, high = window.bounds_ns(int(self.stamps_ns[0]) if first_ns is None else first_ns)
        keep = (self.stamps_ns >= low) & (self.stamps_ns <= high)
        return Trajectory(self.stamps_ns[keep], self.positions[keep], self.quats_xyzw[keep])

    @classmethod
    def from_matrices(cls, stamps_ns: npt.ArrayLike, T_world_frame: npt.ArrayLike) -> Trajectory:
        positions, quats = matrix_to_position_quat(np.asarray(T_world_frame).reshape(-1, 4, 4))
        return cls(np.asarray(stamps_ns, dtype=np.int64), positions, quats)


@dataclass(frozen=True, eq=False)
class LandmarkMap:
    """Estimated point landmarks in ``world``.

    Attributes
    ----------
    positions: (M, 3) float64 metres.
    observations: (M,) int64, how many observations were fused into each landmark.
    dynamic: (M,) bool, landmark judged to move (kept out of the static map).
    gt_id: (M,) int64, majority ground-truth id of the fused observations, -1 if unknown.
    purity: (M,) float64 share of the fused observations that carry ``gt_id`` (association purity),
        or ``None`` when the estimator or the log cannot tell.
    first_iteration: (M,) int64, the iteration each landmark was first observed or started (-1 if
        unknown), or ``None``: what tells a continuous run's landmarks apart by the local map they
        were made in when the map also loses landmarks (``relpoint fuse``).
    """

    positions: FloatArray
    observations: IntArray
    dynamic: npt.NDArray[np.bool_]
    gt_id: IntArray
    purity: FloatArray | None = None
    first_iteration: IntArray | None = None

    def __post_init__(self) -> None:
        positions = _frozen(self.positions, np.float64, (3,), "positions")
        n = len(positions)
        for name, dtype in (("observations", np.int64), ("dynamic", np.bool_), ("gt_id", np.int64)):
            array = _frozen(getattr(self, name), dtype, (), name)
            if len(array) != n:
                raise ValueError(f"{name} has {len(array)} entries for {n} landmarks")
            object.__setattr__(self, name, array)
        object.__setattr__(self, "positions", positions)
        if self.purity is not None:
            purity = _frozen(self.purity, np.float64, (), "purity")
            if len(purity) != n or np.any((purity < 0) | (purity > 1)):
                raise ValueError(f"purity must hold {n} shares in [0, 1]")
            object.__setattr__(self, "purity", purity)
        if self.first_iteration is not None:
            first = _frozen(self.first_iteration, np.int64, (), "first_iteration")
            if len(first) != n:
                raise ValueError(f"first_iteration has {len(first)} entries for {n} landmarks")
            object.__setattr__(self, "first_iteration", first)

    def __len__(self) -> int:
        return len(self.positions)

    @classmethod
    def empty(cls) -> LandmarkMap:
        return cls(np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0, np.int64))

    @classmethod
    def concatenate(cls, maps: Sequence[LandmarkMap]) -> LandmarkMap:
        """One map holding every landmark of ``maps`` in order (purity kept only if every map has it)."""
        if not maps:
            return cls.empty()
        purities = [m.purity for m in maps]
        return cls(
            np.concatenate([m.positions for m in maps]),
            np.concatenate([m.observations for m in maps]),
            np.concatenate([m.dynamic for m in maps]),
            np.concatenate([m.gt_id for m in maps]),
            None if any(p is None for p in purities) else np.concatenate(purities),
        )  # first iterations are each map's own


@dataclass(frozen=True, eq=False)
class GroundTruthLandmarks:
    """True landmarks at the first stamp: positions (M,3) in ``world``, ids (M,), dynamic flags (M,)."""

    positions: FloatArray
    ids: IntArray
    dynamic: npt.NDArray[np.bool_]

    def __post_init__(self) -> None:
        positions = _frozen(self.positions, np.float64, (3,), "positions")
        ids = _frozen(self.ids, np.int64, (), "ids")
        dynamic = _frozen(self.dynamic, np.bool_, (), "dynamic")
        if not (len(positions) == len(ids) == len(dynamic)):
            raise ValueError("ground-truth landmark positions, ids and dynamic flags differ in length")
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "dynamic", dynamic)


#: A twist variance ((m/s)^2 or (rad/s)^2) from which an odometry axis counts as not measured: a standard
#: deviation of 10 m/s or 10 rad/s says nothing a motion model does not, and taken as a measurement
#: it lets the pose wander (a 1e6 roll-rate variance left an EKF 50 m off on the figure eight).
UNMEASURED_TWIST_VARIANCE = 100.0


@dataclass(frozen=True, eq=False)
class OdometryMeasurement:
    """Body-frame velocities of the sensor, held from ``stamp_ns`` until the next measurement.

    linear: (3,) m/s and angular: (3,) rad/s, in the sensor frame; covariance: (6,6) of
    (vx, vy, vz, wx, wy, wz), row-major as in ``nav_msgs/Odometry.twist.covariance``.
    """

    stamp_ns: int
    linear: FloatArray
    angular: FloatArray
    covariance: FloatArray = field(default_factory=lambda: np.zeros((6, 6)))

    def __post_init__(self) -> None:
        for name, shape in (("linear", (3,)), ("angular", (3,)), ("covariance", (6, 6))):
            array = np.array(getattr(self, name), dtype=np.float64)
            if array.shape != shape:
                raise ValueError(f"odometry {name} must have shape {shape}, got {array.shape}")
            array.flags.writeable = False
            object.__setattr__(self, name, array)

    @property
    def unset_axes(self) -> npt.NDArray[np.bool_]:
        """(6,) the twist axes whose variance the message leaves unset: zero (REP 145's "unknown"),
        negative (drivers' -1), or :data:`UNMEASURED_TWIST_VARIANCE` and above (the 1e3-1e6 that
        wheel-odometry drivers such as ros2_control's diff_drive_controller give the axes they do not
        measure)."""
        variances = np.diag(self.covariance)
        return ~((variances > 0) & (variances < UNMEASURED_TWIST_VARIANCE))

    def twist_covariance(self, fallback_variances: FloatArray) -> FloatArray:
        """The (6, 6) twist covariance, with each unset axis (:attr:`unset_axes`) given its variance in
        ``fallback_variances`` (6,) ((m/s)^2, (rad/s)^2) and no correlation with the others; taken
        as exact, an unset axis would hold the filter to the odometry's every error."""
        unset = self.unset_axes
        if not unset.any():
            return self.covariance
        covariance = np.array(self.covariance, dtype=np.float64)
        covariance[unset, :] = 0.0
        covariance[:, unset] = 0.0
        covariance[unset, unset] = np.asarray(fallback_variances, dtype=np.float64)[unset]
        return covariance


@dataclass(frozen=True, eq=False)
class PositionFix:
    """An absolute position of the sensor in ``world`` (buoys, GNSS): position (3,) m, covariance (3,3) m²."""

    stamp_ns: int
    position: FloatArray
    covariance: FloatArray

    def __post_init__(self) -> None:
        for name, shape in (("position", (3,)), ("covariance", (3, 3))):
            array = np.array(getattr(self, name), dtype=np.float64)
            if array.shape != shape:
                raise ValueError(f"fix {name} must have shape {shape}, got {array.shape}")
            array.flags.writeable = False
            object.__setattr__(self, name, array)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth camera: image size in pixels, focal lengths and principal point in pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: str = ""
    """``sensor_msgs/CameraInfo.distortion_model`` (``plumb_bob``, ``rational_polynomial``, ``equidistant``);
    empty for an ideal pinhole."""
    distortion: tuple[float, ...] = ()
    """The model's coefficients (CameraInfo's ``d``); empty for an ideal pinhole (all zero is stored empty)."""

    @property
    def distorted(self) -> bool:
        """Whether the images carry lens distortion (a non-zero coefficient)."""
        return any(c != 0.0 for c in self.distortion)

    def __post_init__(self) -> None:
        distortion = tuple(float(c) for c in self.distortion)
        if not np.isfinite(distortion).all():  # NaN != 0 would take it for a distortion, and blank every image
            raise ValueError(f"distortion coefficients must be finite, got {list(distortion)}; zeros mean none")
        if not any(c != 0.0 for c in distortion):  # all zero is an ideal pinhole, whatever the model's name
            distortion = ()
            object.__setattr__(self, "distortion_model", "")
        object.__setattr__(self, "distortion", distortion)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not (np.isfinite([self.fx, self.fy, self.cx, self.cy]).all() and self.fx > 0 and self.fy > 0):
            raise ValueError("focal lengths must be finite and positive")

    def matrix(self) -> FloatArray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class DepthFrame:
    """One depth image in the camera optical frame: depth (H, W) float32 metres, 0 = no measurement.

    ``color`` is an optional (H, W, 3) uint8 RGB image registered to the depth image.
    """

    stamp_ns: int
    depth: npt.NDArray[np.float32]
    intrinsics: Intrinsics
    color: npt.NDArray[np.uint8] | None = None

    def __post_init__(self) -> None:
        depth = np.array(self.depth, dtype=np.float32)
        if depth.shape != (self.intrinsics.height, self.intrinsics.width):
            raise ValueError(
                f"depth image is {depth.shape[::-1]} but the intrinsics say {self.intrinsics.width}x{self.intrinsics.height}"
            )
        depth[~np.isfinite(depth)] = 0.0
        depth.flags.writeable = False
        object.__setattr__(self, "depth", depth)
        if self.color is not None:
            color = np.array(self.color, dtype=np.uint8)
            if color.shape != (*depth.shape, 3):
                raise ValueError(f"colour image shape {color.shape} does not match depth {depth.shape}")
            color.flags.writeable = False
            object.__setattr__(self, "color", color)


@dataclass(frozen=True, eq=False)
class MapSnapshot:
    """The map after one iteration: ``positions`` (M, 3) float32 metres in ``world``, ``dynamic`` (M,) bool."""

    stamp_ns: int
    positions: np.ndarray
    dynamic: np.ndarray


@dataclass(frozen=True, eq=False)
class RunResult:
    """Everything ``relpoint run`` writes, in memory.

    Attributes
    ----------
    trajectory: estimated ``T_world_sensor`` per iteration.
    landmarks: the final map.
    observed: (N,) points observed per iteration.
    map_size: (N,) landmarks mapped after each iteration.
    seconds: (N,) wall time of each ``step`` call.
    summary: estimator summary figures (JSON-serialisable).
    seconds_finish: wall time of the estimator's work once the log ended (a final adjustment).
    seconds_prepare: wall time of compiling or loading compiled code before the first iteration.
    """

    trajectory: Trajectory
    landmarks: LandmarkMap
    observed: np.ndarray
    map_size: np.ndarray
    seconds: np.ndarray
    summary: dict[str, Any] = field(default_factory=dict)
    map_history: tuple[tuple[int, int, LandmarkMap], ...] = ()
    """Snapshots ``(iteration, stamp_ns, map)`` taken every ``map_every`` iterations and at the end."""
    dense_map: tuple[np.ndarray, ...] | None = None
    """For dense estimators: (positions (M,3) m, normals (M,3), colours (M,3) uint8, weights (M,)) in ``world``."""
    seconds_finish: float = 0.0
    seconds_prepare: float = 0.0
    skipped: dict[str, int] = field(default_factory=dict)
    """Inputs dropped before the estimator saw them, and iterations it could not compute, by kind."""
    warnings: tuple[str, ...] = ()
    """What a user should know about the result (no landmarks, mostly failed iterations)."""
    map_timeline: tuple[MapSnapshot, ...] = ()
    """The map as it grew: at most ``relpoint.pipeline.MAX_TIMELINE`` snapshots at evenly spaced iterations."""

    def timing_summary(self) -> dict[str, float]:
        """Mean, median and total wall time per iteration, and the times before the first and after the last, in s."""
        if len(self.seconds) == 0:
            return {"iterations": 0, "seconds_total": 0.0, "seconds_mean": 0.0, "seconds_median": 0.0,
                    "seconds_finish": self.seconds_finish, "seconds_prepare": self.seconds_prepare}  # fmt: skip
        return {
            "iterations": len(self.seconds),
            "seconds_total": float(self.seconds.sum()),
            "seconds_mean": float(self.seconds.mean()),
            "seconds_median": float(np.median(self.seconds)),
            "seconds_finish": self.seconds_finish,
            "seconds_prepare": self.seconds_prepare,
        }


@dataclass(frozen=True, eq=False)
class SimulatedStep:
    """One iteration of a simulated run.

    ``T_world_sensor`` is the true sensor pose (4, 4); ``odometry`` holds the body-frame velocities
    that carry this pose to the next one (``None`` when odometry is off); ``fix`` is an absolute
    position at this stamp (``None`` on iterations without one).
    """

    index: int
    stamp_ns: int
    T_world_sensor: FloatArray
    observation: PointObservation
    odometry: OdometryMeasurement | None
    fix: PositionFix | None
