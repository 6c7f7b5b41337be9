"""ROS 2 message definitions, CDR (de)serialisation and conversion to relpoint's core types.

Message classes and their ``ros2msg`` definition texts come from rosbags' bundled typestore of the
standard ROS 2 Humble messages (identical to Jazzy for every type used here), so nothing is typed by
hand. Serialisation and deserialisation use the same typestore's CDR codec: it returns ``uint8[]``
fields as numpy arrays, so point clouds and images decode without copies.

The types relpoint writes and reads by name (:data:`OWN_TYPES` and the types they contain) come from
:mod:`formats._ros2_types`, rosbags' own code for just those types, generated from the bundled store
by :func:`own_types_module` (a test checks it is current): the bundled store defines 170 message
classes over five distributions, a tenth of a second at the first message of every process.
"""

from __future__ import annotations

import functools
import os
import struct
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from formats.pointcloud2 import Field, decode_cloud, encode_cloud, xyz_from_cloud
from relpoint.errors import InputError
from relpoint.types import (
    GroundTruthLandmarks,
    IntArray,
    Intrinsics,
    OdometryMeasurement,
    PointObservation,
    Pose,
    PositionFix,
    Trajectory,
)

POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
#: A motion-capture bridge's pose (vicon_bridge): ``transform`` is ``T_header.frame_id_child_frame_id``.
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
#: A position without orientation (a total station's prism, EuRoC's ``/leica/position``).
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
#: Message types that carry a pose a trajectory can be read from (a reference or an estimate): the
#: types evo 1.38 reads from bags.
POSE_TYPES = (POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, ODOMETRY, TRANSFORM_STAMPED, POINT_STAMPED)
#: Of :data:`POSE_TYPES`, those without an orientation (read with the identity rotation, as evo does).
POSITION_ONLY_TYPES = (POINT_STAMPED,)
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
PATH = "nav_msgs/msg/Path"

#: Rotation variance written for an unknown orientation (the log format's convention for /fix).
UNKNOWN_ROTATION_VARIANCE = 1e9


#: The message types relpoint writes and reads by name.
OWN_TYPES = (POINT_CLOUD2, POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, ODOMETRY, IMAGE, CAMERA_INFO, TF_MESSAGE, PATH)


@functools.cache
def typestore() -> Any:
    """The standard ROS 2 typestore (cached)."""
    return get_typestore(Stores.ROS2_HUMBLE)


@functools.cache
def own_typestore() -> Any:
    """A typestore of :data:`OWN_TYPES` and the types they contain, as the standard one defines them (cached)."""
    from rosbags.typesys.store import Typestore

    from formats import _ros2_types

    return Typestore(_ros2_types)


def typestore_of(typename: str) -> Any:
    """The cheapest typestore that defines ``typename``: :func:`own_typestore`, else the standard one."""
    own = own_typestore()
    return own if typename in own.fielddefs else typestore()


def own_types_module() -> str:
    """The text of :mod:`formats._ros2_types`: rosbags' generated code of :data:`OWN_TYPES` and the types
    they contain, from the standard typestore.

    Regenerate with ``python -c "from formats import ros2; print(ros2.own_types_module(), end='')"
    > formats/_ros2_types.py``.
    """
    from rosbags.interfaces import Nodetype
    from rosbags.typesys.codegen import generate_python_code

    standard = typestore()
    needed: dict[str, Any] = {}

    def add(typename: str) -> None:
        if typename not in needed:
            needed[typename] = standard.fielddefs[typename]
            for _, description in standard.fielddefs[typename][1]:
                while description[0] in (Nodetype.ARRAY, Nodetype.SEQUENCE):
                    description = description[1][0]
                if description[0] == Nodetype.NAME:
                    add(description[1])

    for typename in OWN_TYPES:
        add(typename)
    return generate_python_code(dict(sorted(needed.items())))


@functools.cache
def message_definition(typename: str) -> str:
    """The rosbag2-style ``ros2msg`` definition text of ``typename`` (with its dependencies)."""
    return typestore_of(typename).generate_msgdef(typename, ros_version=2)[0]


def normalise_typename(name: str) -> str:
    """``pkg/Type`` -> ``pkg/msg/Type``; other names unchanged."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def serialize(message: Any, typename: str) -> bytes:
    """CDR (little-endian) bytes of ``message``."""
    return bytes(typestore_of(typename).serialize_cdr(message, typename))


def deserialize(raw: bytes | memoryview, typename: str) -> Any:
    """Decode CDR bytes of ``typename``; raises :class:`InputError` on malformed data."""
    try:
        return typestore_of(typename).deserialize_cdr(raw, typename)
    except Exception as error:  # rosbags raises assorted errors on malformed CDR
        raise InputError(f"a {typename} message cannot be decoded ({type(error).__name__}: {error})") from None


# --- building messages -------------------------------------------------------------------------


def _types() -> Any:
    return own_typestore().types


def _stamp(stamp_ns: int) -> Any:
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return _types()["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _header(stamp_ns: int, frame_id: str) -> Any:
    return _types()["std_msgs/msg/Header"](stamp=_stamp(stamp_ns), frame_id=frame_id)


def stamp_ns_of(message: Any) -> int:
    """``header.stamp`` of a message in integer nanoseconds."""
    stamp = message.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


#: The message types whose first field is a ``std_msgs/Header`` (every type a log role carries).
HEADER_FIRST_TYPES = frozenset({POINT_CLOUD2, POSE_STAMPED, POSE_WITH_COVARIANCE_STAMPED, ODOMETRY, IMAGE, CAMERA_INFO})


def raw_stamp_ns(raw: bytes | memoryview, ros1: bool = False) -> int | None:
    """``header.stamp`` in ns of a serialised message whose first field is its header, without decoding it.

    ``raw`` is CDR (a 4-byte encapsulation header, then ``int32 sec, uint32 nanosec``) or, with ``ros1``,
    ROS 1 serialised (``uint32 seq, uint32 secs, uint32 nsecs``); ``None`` when it is too short or in a
    CDR variant other than plain CDR.
    """
    if len(raw) < 12:
        return None
    if ros1:
        sec, nanosec = struct.unpack_from("<II", raw, 4)
    elif raw[0] == 0 and raw[1] in (0, 1):  # CDR_BE, CDR_LE
        sec, nanosec = struct.unpack_from("<iI" if raw[1] else ">iI", raw, 4)
    else:
        return None
    return sec * 1_000_000_000 + nanosec


def _pose_msg(position: Any, quat_xyzw: Any) -> Any:
    types = _types()
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(position[0]), y=float(position[1]), z=float(position[2])),
        orientation=types["geometry_msgs/msg/Quaternion"](
            x=float(quat_xyzw[0]), y=float(quat_xyzw[1]), z=float(quat_xyzw[2]), w=float(quat_xyzw[3])
        ),
    )


def point_cloud2(stamp_ns: int, frame_id: str, columns: dict[str, np.ndarray]) -> Any:
    """A PointCloud2 (height 1, little-endian, dense) carrying the given columns as fields."""
    fields, point_step, data = encode_cloud(columns)
    n = len(next(iter(columns.values()))) if columns else 0
    point_field = _types()["sensor_msgs/msg/PointField"]
    return _types()[POINT_CLOUD2](
        header=_header(stamp_ns, frame_id),
        height=1,
        width=n,
        fields=[point_field(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in fields],
        is_bigendian=False,
        point_step=point_step,
        row_step=point_step * n,
        data=np.frombuffer(data, dtype=np.uint8),
        is_dense=True,
    )


def observation_to_msg(observation: PointObservation) -> Any:
    """``/points`` message: x, y, z FLOAT32 and, when known, id INT32."""
    columns: dict[str, np.ndarray] = {
        "x": observation.points[:, 0].astype(np.float32),
        "y": observation.points[:, 1].astype(np.float32),
        "z": observation.points[:, 2].astype(np.float32),
    }
    if observation.ids is not None:
        columns["id"] = observation.ids.astype(np.int32)
    return point_cloud2(observation.stamp_ns, observation.frame_id, columns)


def landmarks_to_msg(stamp_ns: int, landmarks: GroundTruthLandmarks, frame_id: str = "world") -> Any:
    """``/ground_truth/landmarks`` message: x, y, z FLOAT32, id INT32, dynamic UINT8."""
    return point_cloud2(
        stamp_ns,
        frame_id,
        {
            "x": landmarks.positions[:, 0].astype(np.float32),
            "y": landmarks.positions[:, 1].astype(np.float32),
            "z": landmarks.positions[:, 2].astype(np.float32),
            "id": landmarks.ids.astype(np.int32),
            "dynamic": landmarks.dynamic.astype(np.uint8),
        },
    )


def pose_to_msg(pose: Pose, frame_id: str = "world") -> Any:
    """A PoseStamped of ``pose`` in ``frame_id``."""
    return _types()[POSE_STAMPED](
        header=_header(pose.stamp_ns, frame_id), pose=_pose_msg(pose.position, pose.quat_xyzw)
    )


def path_to_msg(stamp_ns: int, trajectory: Trajectory, frame_id: str = "world") -> Any:
    """A nav_msgs/Path of every pose of ``trajectory`` (stamped at ``stamp_ns``) in ``frame_id``."""
    types = _types()
    poses = [
        types[POSE_STAMPED](header=_header(stamp, frame_id), pose=_pose_msg(position, quat))
        for stamp, position, quat in zip(
            trajectory.stamps_ns.tolist(), trajectory.positions.tolist(), trajectory.quats_xyzw.tolist(), strict=True
        )
    ]
    return types[PATH](header=_header(stamp_ns, frame_id), poses=poses)


def odometry_to_msg(odometry: OdometryMeasurement, frame_id: str = "world", child_frame_id: str = "sensor") -> Any:
    """A nav_msgs/Odometry with the body-frame twist and its covariance; pose fields zero."""
    types = _types()
    vector3 = types["geometry_msgs/msg/Vector3"]
    twist = types["geometry_msgs/msg/Twist"](
        linear=vector3(x=float(odometry.linear[0]), y=float(odometry.linear[1]), z=float(odometry.linear[2])),
        angular=vector3(x=float(odometry.angular[0]), y=float(odometry.angular[1]), z=float(odometry.angular[2])),
    )
    return types[ODOMETRY](
        header=_header(odometry.stamp_ns, frame_id),
        child_frame_id=child_frame_id,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose_msg((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)), covariance=np.zeros(36)
        ),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=twist, covariance=np.asarray(odometry.covariance, dtype=np.float64).reshape(36).copy()
        ),
    )


def fix_to_msg(fix: PositionFix, frame_id: str = "world") -> Any:
    """A PoseWithCovarianceStamped: position and its covariance; orientation unknown (1e9 variances)."""
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = fix.covariance
    covariance[3:, 3:] = np.eye(3) * UNKNOWN_ROTATION_VARIANCE
    types = _types()
    return types[POSE_WITH_COVARIANCE_STAMPED](
        header=_header(fix.stamp_ns, frame_id),
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose_msg(fix.position, (0.0, 0.0, 0.0, 1.0)), covariance=covariance.reshape(36)
        ),
    )


def depth_image_to_msg(stamp_ns: int, depth_m: np.ndarray, frame_id: str = "camera", encoding: str = "16UC1") -> Any:
    """A depth Image: ``16UC1`` millimetres (REP 118, 0 = none) or ``32FC1`` metres."""
    depth_m = np.asarray(depth_m, dtype=np.float32)
    height, width = depth_m.shape
    if encoding == "16UC1":
        valid = np.isfinite(depth_m) & (depth_m > 0)
        pixels = np.where(valid, np.clip(np.round(depth_m * 1000.0), 0, 65535), 0).astype("<u2")
    elif encoding == "32FC1":
        pixels = np.where(np.isfinite(depth_m), depth_m, np.nan).astype("<f4")
    else:
        raise ValueError(f"unsupported depth encoding {encoding!r}")
    return _types()[IMAGE](
        header=_header(stamp_ns, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * pixels.itemsize,
        data=np.frombuffer(pixels.tobytes(), dtype=np.uint8),
    )


def color_image_to_msg(stamp_ns: int, rgb: np.ndarray, frame_id: str = "camera") -> Any:
    """An ``rgb8`` Image from an (H, W, 3) uint8 array."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    height, width, _ = rgb.shape
    return _types()[IMAGE](
        header=_header(stamp_ns, frame_id), height=height, width=width, encoding="rgb8", is_bigendian=0,
        step=width * 3, data=np.frombuffer(rgb.tobytes(), dtype=np.uint8),
    )  # fmt: skip


def camera_info_to_msg(stamp_ns: int, intrinsics: Intrinsics, frame_id: str = "camera") -> Any:
    """A CameraInfo with pinhole ``k``, identity ``r``, ``p = [K | 0]`` and no distortion."""
    types = _types()
    k = intrinsics.matrix()
    p = np.zeros((3, 4))
    p[:, :3] = k
    return types[CAMERA_INFO](
        header=_header(stamp_ns, frame_id), height=intrinsics.height, width=intrinsics.width,
        distortion_model="plumb_bob", d=np.zeros(5), k=k.reshape(9), r=np.eye(3).reshape(9), p=p.reshape(12),
        binning_x=0, binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )  # fmt: skip


def tf_to_msg(stamp_ns: int, parent: str, child: str, position: Any, quat_xyzw: Any) -> Any:
    """A TFMessage with one transform ``parent -> child`` (the child's pose in the parent)."""
    types = _types()
    vector3 = types["geometry_msgs/msg/Vector3"]
    transform = types["geometry_msgs/msg/Transform"](
        translation=vector3(x=float(position[0]), y=float(position[1]), z=float(position[2])),
        rotation=types["geometry_msgs/msg/Quaternion"](
            x=float(quat_xyzw[0]), y=float(quat_xyzw[1]), z=float(quat_xyzw[2]), w=float(quat_xyzw[3])
        ),
    )
    stamped = types["geometry_msgs/msg/TransformStamped"](
        header=_header(stamp_ns, parent), child_frame_id=child, transform=transform
    )
    return types[TF_MESSAGE](transforms=[stamped])


# --- reading messages into core types ------------------------------------------------------------


def cloud_of(message: Any) -> np.ndarray:
    """The structured array of a decoded PointCloud2 (see :func:`formats.pointcloud2.decode_cloud`)."""
    width, height = int(message.width), int(message.height)
    point_step, row_step = int(message.point_step), int(message.row_step)
    if width * height > MAX_CLOUD_POINTS:
        if width * point_step > row_step or row_step * height > len(message.data):
            raise InputError(
                f"PointCloud2 header ({width}x{height} points, point_step {point_step}, row_step {row_step}) "
                f"does not match its {len(message.data)} bytes"
            )
        raise OversizedMessage(f"cloud of {width * height} points exceeds the limit of {MAX_CLOUD_POINTS} points")
    fields = [Field(f.name, int(f.offset), int(f.datatype), int(f.count)) for f in message.fields]
    return decode_cloud(
        message.data,
        fields,
        width=int(message.width),
        height=int(message.height),
        point_step=int(message.point_step),
        row_step=int(message.row_step),
        big_endian=bool(message.is_bigendian),
    )


#: Largest PointCloud2 read, points: a landmark or keypoint cloud holds hundreds to thousands; a larger
#: one is skipped (and counted) before any array is made of it.
MAX_CLOUD_POINTS = 1_000_000

#: Largest image read, pixels (4096 x 4096); larger ones are skipped before their pixels are copied.
MAX_IMAGE_PIXELS = 4096 * 4096

#: Largest serialised message decoded, bytes: the largest image allowed (4 bytes a pixel) or cloud
#: (64 bytes a point) fits; anything larger is skipped before it is decoded.
MAX_MESSAGE_BYTES = max(4 * MAX_IMAGE_PIXELS, 64 * MAX_CLOUD_POINTS) + (1 << 20)


class OversizedMessage(InputError):
    """A message within the format but beyond relpoint's documented size limits (skipped and counted)."""

    kind = "oversized messages"


class UnsupportedEncoding(InputError):
    """An image in a valid encoding that relpoint does not read (skipped and counted)."""

    kind = "unsupported encodings"


def _check_image_size(what: str, width: int, height: int) -> None:
    if width * height > MAX_IMAGE_PIXELS:
        raise OversizedMessage(f"{what} of {width}x{height} pixels exceeds the limit of {MAX_IMAGE_PIXELS} pixels")


def landmark_ids(column: np.ndarray) -> IntArray:
    """An ``id`` field's values as int64. The format's ``id`` is INT32 with -1 for clutter; an unsigned
    field of the same width (a writer that declared UINT32 and stored -1) is read as the signed value its
    bits hold, so its 4294967295 is -1 again, not a landmark of its own."""
    if column.dtype.kind == "u" and column.dtype.itemsize in (4, 8):
        column = column.view(column.dtype.str.replace("u", "i"))
    return column.astype(np.int64)


def msg_to_observation(message: Any) -> tuple[PointObservation, int]:
    """A PointObservation of the finite points of a PointCloud2, and the number of invalid points dropped."""
    cloud = cloud_of(message)
    xyz, finite = xyz_from_cloud(cloud)
    ids = None
    if cloud.dtype.names and "id" in cloud.dtype.names and cloud["id"].ndim == 1:
        ids = landmark_ids(cloud["id"][finite])
    observation = PointObservation(stamp_ns_of(message), xyz, ids, str(message.header.frame_id) or "sensor")
    return observation, int(len(cloud) - len(xyz))


def msg_to_landmarks(message: Any) -> GroundTruthLandmarks:
    """Ground-truth landmarks from a PointCloud2 with x, y, z, id and optional dynamic fields."""
    cloud = cloud_of(message)
    xyz, finite = xyz_from_cloud(cloud)
    names = cloud.dtype.names or ()
    if "id" not in names:
        raise InputError("the ground-truth landmark cloud has no 'id' field")
    ids = landmark_ids(cloud["id"][finite])
    dynamic = cloud["dynamic"][finite].astype(bool) if "dynamic" in names else np.zeros(len(ids), dtype=bool)
    return GroundTruthLandmarks(xyz, ids, dynamic)


def msg_to_pose(message: Any) -> Pose:
    """A Pose from a message of :data:`POSE_TYPES`: a PoseStamped's, PoseWithCovarianceStamped's or Odometry's
    pose, a TransformStamped's transform, a PointStamped's point with the identity rotation."""
    if hasattr(message, "transform"):
        p, q = message.transform.translation, message.transform.rotation
    elif hasattr(message, "point"):
        p = message.point
        return Pose(stamp_ns_of(message), (float(p.x), float(p.y), float(p.z)), (0.0, 0.0, 0.0, 1.0))
    else:
        pose = message.pose.pose if hasattr(message.pose, "pose") else message.pose
        p, q = pose.position, pose.orientation
    return Pose(
        stamp_ns_of(message), (float(p.x), float(p.y), float(p.z)), (float(q.x), float(q.y), float(q.z), float(q.w))
    )


def msg_to_odometry(message: Any) -> OdometryMeasurement:
    """Body-frame velocities and their covariance from a nav_msgs/Odometry."""
    twist = message.twist.twist
    return OdometryMeasurement(
        stamp_ns_of(message),
        np.array([twist.linear.x, twist.linear.y, twist.linear.z], dtype=np.float64),
        np.array([twist.angular.x, twist.angular.y, twist.angular.z], dtype=np.float64),
        np.asarray(message.twist.covariance, dtype=np.float64).reshape(6, 6),
    )


def msg_to_fix(message: Any) -> PositionFix:
    """Position and its 3x3 covariance from a PoseWithCovarianceStamped."""
    p = message.pose.pose.position
    covariance = np.asarray(message.pose.covariance, dtype=np.float64).reshape(6, 6)[:3, :3]
    return PositionFix(stamp_ns_of(message), np.array([p.x, p.y, p.z], dtype=np.float64), covariance)


def msg_to_intrinsics(message: Any) -> Intrinsics:
    """Pinhole intrinsics of the images a CameraInfo describes: its ``k``, with its distortion model and
    coefficients ``d``.

    ``k``, ``width`` and ``height`` are the full sensor's; a driver that bins pixels (``binning_x``,
    ``binning_y`` above 1) or crops a region (``roi``) publishes smaller images, whose intrinsics are
    taken as ``image_geometry``'s ``PinholeCameraModel`` takes them: the principal point less the
    region's offset, then both focal lengths and the principal point divided by the binning.
    """
    k = np.asarray(message.k, dtype=np.float64).reshape(3, 3)
    width, height = int(message.width), int(message.height)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    roi = getattr(message, "roi", None)
    region = (int(roi.width), int(roi.height)) if roi is not None else (0, 0)
    if region[0] > 0 and region[1] > 0 and region != (width, height):  # 0 x 0: the full image
        width, height = region
        cx, cy = cx - int(roi.x_offset), cy - int(roi.y_offset)
    binning = (max(int(getattr(message, "binning_x", 0)), 1), max(int(getattr(message, "binning_y", 0)), 1))
    if binning != (1, 1):
        width, height = width // binning[0], height // binning[1]
        fx, cx, fy, cy = fx / binning[0], cx / binning[0], fy / binning[1], cy / binning[1]
    _check_image_size("camera_info", width, height)
    try:
        return Intrinsics(width, height, fx, fy, cx, cy,
                          str(message.distortion_model), tuple(np.asarray(message.d, dtype=np.float64).tolist()))  # fmt: skip
    except ValueError as error:
        raise InputError(f"unusable camera_info: {error}") from None


def _decoded_image(data: np.ndarray, what: str, flags: int) -> np.ndarray:
    """The pixels of a PNG or JPEG byte string (OpenCV's ``imdecode`` with ``flags``)."""
    if data.size == 0:
        raise InputError(f"{what} holds no data")
    if data[:8].tobytes() == _PNG_SIGNATURE and data.size >= 24:  # the size, before a byte is decompressed
        width, height = struct.unpack(">II", data[16:24].tobytes())
        _check_image_size(what, width, height)
    # OpenCV refuses larger images itself (a small JPEG can claim a huge size), if it reads this first
    os.environ.setdefault("CV_IO_MAX_IMAGE_PIXELS", str(MAX_IMAGE_PIXELS))
    import cv2  # here, not at import: OpenCV costs start-up time

    pixels = cv2.imdecode(data, flags)
    if pixels is None:
        raise InputError(f"{what} is neither PNG nor JPEG data OpenCV can decode")
    _check_image_size(what, pixels.shape[1], pixels.shape[0])
    return pixels


#: image_transport's ``compressedDepth`` messages start with this header before the PNG: the source
#: format (int32) and, for 32FC1, the two parameters of its inverse-depth quantisation (float32).
_COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def compressed_to_depth(message: Any) -> np.ndarray:
    """Depth in metres (H, W) float32 from a CompressedImage: image_transport's ``compressedDepth``
    (``"16UC1; compressedDepth png"``: millimetres; ``"32FC1; compressedDepth png"``: inverse depth
    quantised to 16 bits, ``depth = a / (q - b)``) or a plain 16-bit PNG; 0 where there is no measurement."""
    import cv2

    data = np.asarray(message.data, dtype=np.uint8).reshape(-1)
    fmt = str(message.format)
    source = fmt.split(";", 1)[0].strip().upper()
    header = None
    if data[:8].tobytes() != _PNG_SIGNATURE and data[12:20].tobytes() == _PNG_SIGNATURE:
        header, data = _COMPRESSED_DEPTH_HEADER.unpack(data[:12].tobytes()), data[12:]
    if "PNG" not in fmt.upper() and data[:8].tobytes() != _PNG_SIGNATURE:
        raise UnsupportedEncoding(f"compressed depth format {fmt!r} is not PNG (compressedDepth)")
    pixels = _decoded_image(data, "compressed depth image", cv2.IMREAD_UNCHANGED)
    if pixels.ndim != 2 or pixels.dtype != np.uint16:
        raise UnsupportedEncoding(f"compressed depth image ({fmt!r}) does not decode to one 16-bit channel")
    if source == "32FC1":
        if header is None:
            raise InputError(f"compressed depth format {fmt!r} lacks the quantisation header of 32FC1 data")
        _, a, b = header
        q = pixels.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(q > 0, np.float32(a) / (q - np.float32(b)), np.float32(0.0)).astype(np.float32)
    elif source in ("16UC1", "MONO16", ""):
        depth = pixels.astype(np.float32) * np.float32(0.001)
    else:
        raise UnsupportedEncoding(f"compressed depth of {source} data is not 16UC1 or 32FC1")
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


def msg_to_depth(message: Any) -> np.ndarray:
    """Depth in metres (H, W) float32 from a ``32FC1`` or ``16UC1`` Image (or a compressed one,
    :func:`compressed_to_depth`); 0 where there is no measurement."""
    if hasattr(message, "format"):
        return compressed_to_depth(message)
    height, width, step = int(message.height), int(message.width), int(message.step)
    encoding = str(message.encoding).upper()
    dtypes = {"32FC1": np.dtype(np.float32), "16UC1": np.dtype(np.uint16), "MONO16": np.dtype(np.uint16)}
    if encoding not in dtypes:
        raise InputError(f"depth image encoding {message.encoding!r} is not 32FC1 or 16UC1")
    dtype = dtypes[encoding].newbyteorder(">" if message.is_bigendian else "<")
    if height <= 0 or width <= 0:
        raise InputError(f"depth image has size {width}x{height}")
    data = np.asarray(message.data, dtype=np.uint8).reshape(-1)
    if step < width * dtype.itemsize or step * height > data.size:
        raise InputError(f"depth image header ({width}x{height}, step {step}) does not match its {data.size} bytes")
    _check_image_size("depth image", width, height)
    rows = np.lib.stride_tricks.as_strided(
        data[: step * height].view(np.uint8), shape=(height, width * dtype.itemsize), strides=(step, 1)
    )
    pixels = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
    depth = pixels.astype(np.float32) * (np.float32(0.001) if dtype.kind == "u" else np.float32(1.0))
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth


#: Colour encodings read (REP 104 names): channels per pixel and where R, G, B are among them.
COLOUR_ENCODINGS = {
    "rgb8": (3, (0, 1, 2)), "bgr8": (3, (2, 1, 0)), "rgba8": (4, (0, 1, 2)), "bgra8": (4, (2, 1, 0)),
    "mono8": (1, (0, 0, 0)),
}  # fmt: skip


def msg_to_rgb(message: Any) -> np.ndarray:
    """An (H, W, 3) uint8 RGB array from an ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8`` (alpha dropped) or
    ``mono8`` (grey repeated) Image, or from a JPEG or PNG CompressedImage (image_transport's
    ``compressed``)."""
    if hasattr(message, "format"):
        import cv2

        data = np.asarray(message.data, dtype=np.uint8).reshape(-1)
        bgr = _decoded_image(data, "compressed colour image", cv2.IMREAD_COLOR)
        if bgr.dtype != np.uint8:
            raise UnsupportedEncoding(f"compressed colour image ({message.format!r}) is not 8 bits a channel")
        return np.ascontiguousarray(bgr[..., ::-1])
    height, width, step = int(message.height), int(message.width), int(message.step)
    encoding = str(message.encoding).lower()
    if encoding not in COLOUR_ENCODINGS:
        raise UnsupportedEncoding(
            f"colour image encoding {message.encoding!r} is not one of {', '.join(COLOUR_ENCODINGS)}"
        )
    channels, order = COLOUR_ENCODINGS[encoding]
    data = np.asarray(message.data, dtype=np.uint8).reshape(-1)
    if step < width * channels or step * height > data.size:
        raise InputError(f"colour image header ({width}x{height}, step {step}) does not match its {data.size} bytes")
    _check_image_size("colour image", width, height)
    rows = np.lib.stride_tricks.as_strided(data, shape=(height, width * channels), strides=(step, 1))
    pixels = np.ascontiguousarray(rows).reshape(height, width, channels)
    return pixels if order == (0, 1, 2) and channels == 3 else np.ascontiguousarray(pixels[..., list(order)])
