"""Trajectories to evaluate, from any of the inputs ``relpoint evaluate`` accepts (issue 3).

:func:`load_trajectory` reads a :class:`relpoint.types.Trajectory` from

* a trajectory file of :mod:`formats.trajectory_files`: TUM (8 values per line), EuRoC ground truth
  CSV (integer nanoseconds, position, quaternion w first, further columns ignored) or KITTI poses
  (12 values per line, stamps from a times file, else pose ``i`` at ``i`` s), told apart by
  :func:`formats.trajectory_files.detect_format`;
* a ``relpoint run`` output directory (its ``trajectory.tum``);
* a log in any layout of :mod:`formats.layouts` (MCAP file, rosbag2 directory, ROS 1 bag): a relpoint
  log's ``/ground_truth/pose``, or any topic of any bag carrying
  ``geometry_msgs/msg/PoseStamped``, ``geometry_msgs/msg/PoseWithCovarianceStamped``,
  ``nav_msgs/msg/Odometry``, ``geometry_msgs/msg/TransformStamped`` (a motion-capture bridge's) or
  ``geometry_msgs/msg/PointStamped`` (a position only: identity rotation, with a warning), as evo reads
  them (stamps from ``header.stamp``), or a TF chain ``parent -> ... -> child``
  composed from ``/tf`` and ``/tf_static`` (:func:`tf_chain_trajectory`).

Bag messages are sorted by stamp and, of messages with the same stamp, the first is kept (rosbag2
recordings repeat messages now and then); a warning gives the count. Every problem is an :class:`InputError` naming the file.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from formats import ros2
from formats.layouts import detect_layout, is_rosbag2_part
from formats.log import LogReader
from formats.ply import read_ply
from formats.signatures import MCAP_MAGIC, is_log
from formats.tables import read_map_csv
from formats.topics import Topics
from formats.trajectory_files import (
    TrajectoryFormat,
    describe_unknown,
    detect_format,
    header_layout,
    identity_where_never_set,
    read_euroc_csv,
    read_kitti,
    read_named_columns,
    read_relpoint_csv,
    read_tum,
)
from relpoint.errors import InputError, UsageError
from relpoint.geometry import FloatArray, invert_pose
from relpoint.types import GroundTruthLandmarks, LandmarkMap, Trajectory

log = logging.getLogger(__name__)

POSE_TYPES = ros2.POSE_TYPES
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
#: Topics tried, in order, when an MCAP input is given without a topic.
DEFAULT_POSE_TOPICS = ("/ground_truth/pose", "/relpoint/pose")


def is_mcap(path: Path) -> bool:
    """Whether ``path`` is a file starting with the MCAP magic bytes."""
    try:
        with path.open("rb") as stream:
            return stream.read(8) == MCAP_MAGIC
    except OSError:
        return False


def _from_poses(stamps: list[int], positions: list[FloatArray], quats: list[FloatArray], source: str) -> Trajectory:
    """A trajectory from possibly unordered poses: sorted by stamp, the first pose of each stamp kept."""
    if not stamps:
        raise InputError(f"{source}: no poses")
    stamps_arr = np.asarray(stamps, dtype=np.int64)
    order = np.argsort(stamps_arr, kind="stable")
    stamps_arr = stamps_arr[order]
    keep = np.ones(len(stamps_arr), dtype=bool)
    keep[1:] = np.diff(stamps_arr) > 0
    dropped = int((~keep).sum())
    if dropped:
        log.warning("%s: %d messages repeat the stamp of an earlier one; kept the first of each stamp", source, dropped)
    index = order[keep]
    stamps_arr = stamps_arr[keep]
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)[index]
    quat = np.asarray(quats, dtype=np.float64).reshape(-1, 4)[index]
    quat = identity_where_never_set(quat, source)
    finite = np.isfinite(pos).all(axis=1) & np.isfinite(quat).all(axis=1) & (np.linalg.norm(quat, axis=1) > 1e-9)
    if not finite.all():
        log.warning("%s: dropped %d poses with non-finite values or zero quaternions", source, int((~finite).sum()))
    if not finite.any():
        raise InputError(f"{source}: no valid poses")
    return Trajectory(stamps_arr[finite], pos[finite], quat[finite])


def pose_topic_trajectory(reader: LogReader, topic: str) -> Trajectory:
    """The trajectory of a topic of :data:`POSE_TYPES` (PoseStamped, PoseWithCovarianceStamped, Odometry,
    TransformStamped, PointStamped) at its ``header.stamp``s; at the recording times (``log_time``), with a
    warning, when every ``header.stamp`` is zero (never set by the publisher)."""
    info = reader.topic_infos.get(topic)
    source = f"{reader.path} {topic}"
    if info is None or info.count == 0:
        raise InputError(f"{reader.path}: no messages on {topic}", _topics_hint(reader))
    if info.typename == ros2.TF_MESSAGE:
        raise InputError(f"{source} is a TF topic", "give the frames with --parent and --child")
    if info.typename not in POSE_TYPES:
        raise InputError(f"{source} carries {info.typename}, not a pose type", _topics_hint(reader))
    stamps: list[int] = []
    positions: list[FloatArray] = []
    quats: list[FloatArray] = []
    if info.typename in ros2.POSITION_ONLY_TYPES:
        log.warning("%s: %s has no orientation: read with the identity rotation, as evo does; only the APE "
                    "translation (and RPE --pose-relation point_distance) means anything", source, info.typename)  # fmt: skip
    log_times: list[int] = []
    frames: Counter[str] = Counter()
    moving = False  # an Odometry message's twist is not zero
    for _, _, log_time, message in reader.messages([topic]):
        pose = ros2.msg_to_pose(message)
        stamps.append(pose.stamp_ns)
        log_times.append(log_time)
        positions.append(np.asarray(pose.position))
        quats.append(np.asarray(pose.quat_xyzw))
        frames[_frame(message.header.frame_id)] += 1
        if info.typename == ros2.ODOMETRY and not moving:
            twist = message.twist.twist
            moving = any(float(getattr(v, a)) != 0.0 for v in (twist.linear, twist.angular) for a in "xyz")
    if (
        moving
        and len(positions) > 1
        and all(np.array_equal(p, positions[0]) for p in positions)
        and all(np.array_equal(q, quats[0]) for q in quats)
    ):
        raise InputError(
            f"{source}: every message holds the same pose while its twist moves: odometry with velocities only",
            "its pose fields are unset (as in a relpoint log's /odom), so it is no trajectory; name a pose topic",
        )
    if len(frames) > 1:
        log.warning("%s: the poses are in %d frames (%s); they are read as one trajectory, as evo reads them",
                    source, len(frames), ", ".join(f"{name or repr(name)}: {count}" for name, count in frames.most_common()))  # fmt: skip
    if len(stamps) > 1 and not any(stamps) and len(set(log_times)) > 1:
        # A publisher that never set header.stamp: one pose per stamp would keep one pose of the topic.
        log.warning("%s: header.stamp is 0 (unset) in every message; the poses are timed by when they were "
                    "recorded (log_time) instead", source)  # fmt: skip
        stamps = log_times
    return _from_poses(stamps, positions, quats, source)


def _topics_hint(reader: LogReader) -> str:
    poses = [t for t, i in reader.topic_infos.items() if i.typename in POSE_TYPES and i.count]
    tf = [t for t, i in reader.topic_infos.items() if i.typename == ros2.TF_MESSAGE and i.count]
    hints = []
    if poses:
        hints.append(f"pose topics here: {', '.join(sorted(poses))}")
    if tf:
        hints.append(f"TF topics here: {', '.join(sorted(tf))} (use --parent/--child)")
    return "; ".join(hints) or "the file has no pose or TF topic"


# --- TF chains -------------------------------------------------------------------------------------


def _frame(name: str) -> str:
    return name.strip().lstrip("/")


@dataclass
class _Edge:
    """All transforms ``T_parent_child`` seen for one child frame."""

    parent: str
    static: bool
    stamps: list[int] = field(default_factory=list)
    positions: list[tuple[float, float, float]] = field(default_factory=list)
    quats: list[tuple[float, float, float, float]] = field(default_factory=list)

    def arrays(self) -> tuple[np.ndarray, FloatArray]:
        """(stamps sorted, (n, 4, 4) matrices in that order)."""
        from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

        stamps = np.asarray(self.stamps, dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        T = np.tile(np.eye(4), (len(stamps), 1, 1))
        T[:, :3, :3] = Rotation.from_quat(np.asarray(self.quats)[order]).as_matrix()
        T[:, :3, 3] = np.asarray(self.positions)[order]
        return stamps[order], T


def _collect_tf(reader: LogReader, topics: Iterable[str], static_topic: str = TF_STATIC_TOPIC) -> dict[str, _Edge]:
    """Every edge of the TF tree on ``topics``, those of ``static_topic`` marked static."""
    edges: dict[str, _Edge] = {}
    conflicts = 0
    for topic, typename, _, message in reader.messages(topics):
        if typename != ros2.TF_MESSAGE:
            raise InputError(f"{reader.path} {topic} carries {typename}, not {ros2.TF_MESSAGE}")
        static = topic == static_topic
        for transform in message.transforms:
            parent, child = _frame(transform.header.frame_id), _frame(transform.child_frame_id)
            edge = edges.get(child)
            if edge is None:
                edge = edges[child] = _Edge(parent, static)
            elif edge.parent != parent:
                conflicts += 1
                continue
            t, q = transform.transform.translation, transform.transform.rotation
            quat = (float(q.x), float(q.y), float(q.z), float(q.w))
            if not np.isfinite(quat).all() or np.linalg.norm(quat) < 1e-9:
                continue
            edge.stamps.append(ros2.stamp_ns_of(transform))
            edge.positions.append((float(t.x), float(t.y), float(t.z)))
            edge.quats.append(quat)
    if conflicts:
        log.warning("%s: ignored %d transforms giving a frame a second parent", reader.path, conflicts)
    return edges


def _tf_tree(reader: LogReader, tf_topic: str) -> dict[str, _Edge]:
    """The edges of ``tf_topic`` and of its static topic (``/robot1/tf_static`` for ``/robot1/tf`` when the
    log has it, else ``/tf_static``), by child frame."""
    static_topic = f"{tf_topic}_static" if f"{tf_topic}_static" in reader.topic_infos else TF_STATIC_TOPIC
    topics = [tf_topic] + ([static_topic] if static_topic in reader.topic_infos and static_topic != tf_topic else [])
    return _collect_tf(reader, topics, static_topic)


@dataclass(frozen=True)
class TfEdge:
    """One edge of a log's TF tree: ``T_parent_child``, from the static topic or not, with its transform count."""

    parent: str
    child: str
    static: bool
    count: int


def tf_edges(reader: LogReader, tf_topic: str = TF_TOPIC) -> list[TfEdge]:
    """The edges of the TF tree on ``tf_topic`` and its static topic (as a chain reads them), dynamic ones
    first, each group by parent and child."""
    edges = _tf_tree(reader, tf_topic)
    found = [TfEdge(edge.parent, child, edge.static, len(edge.stamps)) for child, edge in edges.items()]
    return sorted(found, key=lambda e: (e.static, e.parent, e.child))


def _ancestors(frame: str, edges: dict[str, _Edge]) -> list[str]:
    """``frame``, its parent, grandparent, ... up to the root of its TF tree."""
    chain = [frame]
    while chain[-1] in edges:
        parent = edges[chain[-1]].parent
        if parent in chain:
            break  # a cycle in a malformed tree
        chain.append(parent)
    return chain


def tf_chain_trajectory(reader: LogReader, parent: str, child: str, tf_topic: str = TF_TOPIC) -> Trajectory:
    """Poses ``T_parent_child`` composed from the TF tree of ``tf_topic`` and ``/tf_static``.

    The chain may pass through any number of frames, up and down the tree (``parent`` need not be an
    ancestor of ``child``). The dynamic edge of the chain with the most transforms drives the output:
    one pose per transform of it, at its ``header.stamp``, composed with every other dynamic edge
    interpolated at that stamp as tf2 does (:func:`_edge_at`; poses before every edge has one are
    dropped) and
    with the last value of every static edge (``/tf_static``, or for a namespaced ``tf_topic`` such as
    ``/robot1/tf`` its own ``/robot1/tf_static`` when the log has it).

    Raises
    ------
    InputError
        Unknown frames, frames in different trees, a chain of static transforms only, or no poses.
    """
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

    parent, child = _frame(parent), _frame(child)
    if tf_topic not in reader.topic_infos:
        raise InputError(f"{reader.path}: no {tf_topic} topic", _topics_hint(reader))
    edges = _tf_tree(reader, tf_topic)
    frames = set(edges) | {e.parent for e in edges.values()}
    for name, option in ((parent, "--parent"), (child, "--child")):
        if name not in frames:
            raise InputError(
                f"{reader.path}: frame {name!r} ({option}) is not in the TF tree",
                f"frames here: {', '.join(sorted(frames)) or 'none'}",
            )
    up_child, up_parent = _ancestors(child, edges), _ancestors(parent, edges)
    common = next((f for f in up_child if f in up_parent), None)
    if common is None:
        raise InputError(f"{reader.path}: frames {parent!r} and {child!r} are not connected in the TF tree")
    down = up_child[: up_child.index(common)]  # child, ..., below common: T_common_child = prod over reversed
    up = up_parent[: up_parent.index(common)]
    chain = down + up
    if not chain:
        raise InputError(f"{reader.path}: --parent and --child name the same frame {parent!r}")
    arrays = {frame: edges[frame].arrays() for frame in chain}
    dynamic = [f for f in chain if not edges[f].static]
    if not dynamic:
        raise InputError(f"{reader.path}: the chain {parent} -> {child} has only static transforms")
    driver = max(dynamic, key=lambda f: len(arrays[f][0]))
    stamps = arrays[driver][0]
    valid = np.ones(len(stamps), dtype=bool)
    selected: dict[str, FloatArray] = {}
    for frame in chain:
        edge_stamps, T = arrays[frame]
        if frame == driver:
            selected[frame] = T
        elif edges[frame].static:
            selected[frame] = np.broadcast_to(T[-1], (len(stamps), 4, 4))
        else:
            valid &= stamps >= edge_stamps[0]
            selected[frame] = _edge_at(edge_stamps, T, stamps)
    T_common_child = np.tile(np.eye(4), (len(stamps), 1, 1))
    for frame in down:  # child first: T_common_child = T_common_a @ ... @ T_b_child
        T_common_child = selected[frame] @ T_common_child
    T_common_parent = np.tile(np.eye(4), (len(stamps), 1, 1))
    for frame in up:
        T_common_parent = selected[frame] @ T_common_parent
    T = np.einsum("nij,njk->nik", np.asarray([invert_pose(m) for m in T_common_parent]), T_common_child)
    T = T[valid]
    source = f"{reader.path} TF {parent} -> {child}"
    if len(T) == 0:
        raise InputError(f"{source}: no time at which every transform of the chain is known")
    quats = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    log.debug("%s: %d poses driven by the %s edge", source, len(T), driver)
    return _from_poses(list(stamps[valid]), list(T[:, :3, 3]), list(quats), source)


def _edge_at(edge_stamps: np.ndarray, T: FloatArray, stamps: np.ndarray) -> FloatArray:
    """One TF edge's transforms (n, 4, 4) at its sorted ``edge_stamps`` (ns), looked up at ``stamps`` (ns)
    as tf2 does: between two of its transforms, translation linear and rotation by slerp; of several at
    one stamp, the last. After its last transform the last is held (tf2 would refuse to extrapolate);
    before its first, the first (the caller drops those stamps)."""
    from scipy.spatial.transform import Rotation, Slerp  # here, not at import: scipy costs start-up time

    last_of_stamp = np.append(edge_stamps[1:] != edge_stamps[:-1], True)
    edge_stamps, T = edge_stamps[last_of_stamp], T[last_of_stamp]
    if len(edge_stamps) == 1:
        return np.broadcast_to(T[0], (len(stamps), 4, 4))
    # Relative to the first stamp: int64 nanoseconds of epoch stamps lose precision as float64 seconds.
    times = (edge_stamps - edge_stamps[0]).astype(np.float64)
    query = np.clip(stamps - edge_stamps[0], 0, edge_stamps[-1] - edge_stamps[0]).astype(np.float64)
    out = np.tile(np.eye(4), (len(stamps), 1, 1))
    out[:, :3, :3] = Slerp(times, Rotation.from_matrix(T[:, :3, :3]))(query).as_matrix()
    for axis in range(3):
        out[:, axis, 3] = np.interp(query, times, T[:, axis, 3])
    return out


# --- any input ----------------------------------------------------------------------------------------


def mcap_trajectory(
    path: Path, topic: str | None = None, parent: str | None = None, child: str | None = None
) -> Trajectory:
    """A trajectory from an MCAP file: a pose topic, a TF chain, or the first of :data:`DEFAULT_POSE_TOPICS`."""
    with LogReader(path) as reader:
        return log_trajectory(reader, topic, parent, child)


def log_trajectory(
    reader: LogReader, topic: str | None = None, parent: str | None = None, child: str | None = None
) -> Trajectory:
    """:func:`mcap_trajectory` from a log already open."""
    if parent is not None or child is not None:
        if parent is None or child is None:
            raise UsageError("a TF chain needs both --parent and --child")
        return tf_chain_trajectory(reader, parent, child, topic or TF_TOPIC)
    if topic is None:
        topic = next(
            (t for t in DEFAULT_POSE_TOPICS if reader.topic_infos.get(t) and reader.topic_infos[t].count), None
        )
        if topic is None:
            raise InputError(
                f"{reader.path}: no /ground_truth/pose or /relpoint/pose; name a topic", _topics_hint(reader)
            )
    return pose_topic_trajectory(reader, topic)


def load_trajectory(
    path: str | os.PathLike[str],
    *,
    topic: str | None = None,
    parent: str | None = None,
    child: str | None = None,
    times: str | os.PathLike[str] | None = None,
) -> Trajectory:
    """Read a trajectory from a run directory, TUM or KITTI file, or MCAP file (see the module docstring).

    Parameters
    ----------
    path:
        The input. Directories must hold ``trajectory.tum``; MCAP files are known by their magic bytes;
        text files by :func:`formats.trajectory_files.detect_format` (TUM, EuRoC CSV, KITTI).
    topic:
        MCAP only: the pose topic, or the TF topic of a chain (default ``/tf``).
    parent, child:
        MCAP only: frames of a TF chain; the result is ``T_parent_child`` over time.
    times:
        KITTI only: the times file (seconds per line); without it pose ``i`` is stamped ``i`` s.

    Raises
    ------
    InputError
        Missing files, unknown formats, missing topics or frames, no poses.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    if times is not None and (path.is_dir() or is_log(path)):
        raise InputError(f"{path} is not a KITTI pose file; a times file applies only to KITTI poses")
    if path.is_dir() and not is_log(path):
        tum = path / "trajectory.tum"
        if not tum.is_file():
            raise InputError(f"{path}: a directory without trajectory.tum", "give a relpoint run output directory")
        return read_tum(tum)
    if is_log(path):
        return mcap_trajectory(path, topic, parent, child)
    if is_rosbag2_part(path):
        detect_layout(path)  # raises: give the bag directory that holds this file
    if topic is not None or parent is not None or child is not None:
        raise InputError(f"{path} is not an MCAP file; topics and TF frames apply only to MCAP inputs")
    fmt = detect_format(path)
    if times is not None and fmt is not TrajectoryFormat.KITTI:
        raise InputError(f"{path} is not a KITTI pose file; a times file applies only to KITTI poses")
    if fmt is TrajectoryFormat.TUM:
        return read_tum(path)
    if fmt is TrajectoryFormat.EUROC:
        return read_euroc_csv(path)
    if fmt is TrajectoryFormat.RELPOINT_CSV:
        return read_relpoint_csv(path)
    if fmt is TrajectoryFormat.KITTI:
        return read_kitti(path, times)
    if fmt is TrajectoryFormat.NAMED_COLUMNS:
        return read_named_columns(path)
    raise InputError(
        f"{path}: unknown trajectory format ({describe_unknown(path)})",
        "give a TUM file (8 values per line), a EuRoC ground-truth CSV, KITTI poses (12 values per line), "
        "relpoint's trajectory.csv, a relpoint run directory or an MCAP file",
    )


def assumed_quaternion_order(path: str | os.PathLike[str]) -> str | None:
    """The quaternion order a text trajectory file is read in by its format alone, where no header names
    its columns: ``"xyzw"`` (TUM) or ``"wxyz"`` (EuRoC CSV); None for anything else (a run directory, a
    log, KITTI matrices, relpoint's CSV, a header naming the columns)."""
    path = Path(path)
    if not path.is_file() or is_log(path):
        return None
    fmt = detect_format(path)
    if fmt is TrajectoryFormat.TUM:
        layout = header_layout(path)
        return None if layout is not None and layout.is_tum else "xyzw"
    if fmt is TrajectoryFormat.EUROC and header_layout(path) is None:
        return "wxyz"
    return None


def with_quaternion_order(trajectory: Trajectory, read_as: str) -> Trajectory:
    """``trajectory`` as it would have been read with its file's quaternion columns in the other order
    (``read_as`` is the order it was read in: ``"xyzw"`` or ``"wxyz"``)."""
    shift = -1 if read_as == "xyzw" else 1
    return Trajectory(trajectory.stamps_ns, trajectory.positions, np.roll(trajectory.quats_xyzw, shift, axis=1))


def is_index_stamped(path: str | os.PathLike[str], times: str | os.PathLike[str] | None) -> bool:
    """Whether ``path`` is read as KITTI poses without a times file (pose ``i`` stamped ``i`` s)."""
    path = Path(path)
    return times is None and path.is_file() and not is_mcap(path) and detect_format(path) is TrajectoryFormat.KITTI


def check_index_pairing(reference: tuple[Path, Trajectory, bool], estimate: tuple[Path, Trajectory, bool]) -> None:
    """Refuse pairings that KITTI poses without times cannot make: ``(path, trajectory, index_stamped)`` each.

    Index-stamped poses pair by index, as evo's ``kitti`` mode: only with other index-stamped poses
    (stamps in seconds of a sequence would match them by accident or not at all) and only with the
    same number of poses (evo refuses other counts; a dropped frame would shift every pair after it).

    Raises
    ------
    InputError
        One side index-stamped and the other not, or both with different pose counts.
    """
    (ref_path, ref, ref_index), (est_path, est, est_index) = reference, estimate
    if ref_index != est_index:
        bare, other = (ref_path, est_path) if ref_index else (est_path, ref_path)
        raise InputError(
            f"{bare} holds KITTI poses without times, which pair by index only with other such poses, not with {other}",
            "give its times file (--times for the estimate, --reference-times for the reference)",
        )
    if ref_index and len(ref) != len(est):
        raise InputError(
            f"KITTI poses without times pair by index, but {ref_path} has {len(ref)} poses and {est_path} {len(est)}",
            "give both times files (--times, --reference-times), or poses of the same frames",
        )


def load_landmark_map(path: str | os.PathLike[str]) -> LandmarkMap | None:
    """The ``map.csv`` of a run directory, or None when ``path`` is not a directory holding one."""
    map_csv = Path(path) / "map.csv"
    if not Path(path).is_dir() or not map_csv.exists():
        return None
    if not map_csv.is_file():
        raise InputError(f"{map_csv}: not a file", "a run directory's map.csv is the landmark table")
    landmarks = read_map_csv(map_csv)
    map_ply = Path(path) / "map.ply"
    if map_ply.is_file():  # the PLY carries the per-landmark association purity when the estimator knows it
        vertices = read_ply(map_ply)
        if "purity" in (vertices.dtype.names or ()) and len(vertices) == len(landmarks):
            landmarks = dataclasses.replace(landmarks, purity=vertices["purity"].astype(np.float64))
    return landmarks


def load_ground_truth_landmarks(path: str | os.PathLike[str], topic: str | None = None) -> GroundTruthLandmarks | None:
    """The last ground-truth landmarks message (``topic``, default ``/ground_truth/landmarks``) of a
    relpoint log, or None for other inputs.

    A ``topic`` named by the user must be there: :class:`InputError` when ``path`` is not a log, or the
    log has no PointCloud2 messages on it (the default topic may be missing: not every log has landmarks).
    """
    path = Path(path)
    if not is_log(path):
        if topic is not None:
            raise InputError(f"{path} is not an MCAP file; --landmarks-topic applies only to a log reference")
        return None
    topics = Topics(ground_truth_landmarks=topic) if topic is not None else Topics()
    with LogReader(path, topics) as reader:
        if topic is not None and not reader.role_present("ground_truth_landmarks"):
            info = reader.topic_infos.get(topic)
            clouds = sorted(t for t, i in reader.topic_infos.items() if i.typename == ros2.POINT_CLOUD2 and i.count)
            hint = f"PointCloud2 topics here: {', '.join(clouds)}" if clouds else "the log has no PointCloud2 topic"
            if info is None or info.count == 0:
                raise InputError(f"{path}: no messages on {topic}", hint)
            raise InputError(f"{path} {topic} carries {info.typename}, not {ros2.POINT_CLOUD2}", hint)
        return ground_truth_landmarks(reader)


def ground_truth_landmarks(reader: LogReader) -> GroundTruthLandmarks | None:
    """The last ground-truth landmarks message of an open log, or None when it has none."""
    if not reader.role_present("ground_truth_landmarks"):
        return None
    last = None
    for record in reader.records(["ground_truth_landmarks"]):
        last = record.value
    return last
