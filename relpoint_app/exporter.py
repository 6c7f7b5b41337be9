"""``relpoint export``'s work: trajectories, landmarks and maps out of logs, runs and bags into common files.

What can be exported, from which SOURCE, as which format:

============ ============================================================ ====================
``--what``   SOURCE                                                       formats
============ ============================================================ ====================
trajectory   relpoint log (``/ground_truth/pose``), run directory         tum, kitti, csv, ply
             (``trajectory.tum``), TUM/EuRoC/KITTI file, any MCAP bag topic
             (PoseStamped, PoseWithCovarianceStamped, Odometry,
             TransformStamped, PointStamped) or TF chain
             (``--parent/--child``)
landmarks    relpoint log (``/ground_truth/landmarks``), run directory    ply, csv
             (``map.csv``)
map          run directory (``map.ply``: landmarks or a dense cloud with  ply, csv
             normals, colours, weights...), any PLY file; every vertex
             property is kept
============ ============================================================ ====================

Inputs are read by :mod:`formats.reference_trajectories` and :mod:`formats.ply`, outputs written by
:mod:`formats.trajectory_files`, :mod:`formats.tables` and :mod:`formats.ply`; every output is atomic.
PLY is binary little-endian (Open3D, MeshLab and CloudCompare read it).
"""

from __future__ import annotations

import enum
import io
import logging
from pathlib import Path

import numpy as np

from formats.atomic import write_text
from formats.outputs import shown_path
from formats.ply import landmark_vertices, read_ply, write_ply
from formats.reference_trajectories import load_ground_truth_landmarks, load_landmark_map, load_trajectory
from formats.signatures import is_log
from formats.tables import write_map_csv, write_trajectory_csv
from formats.trajectory_files import write_kitti, write_tum
from relpoint.errors import InputError, UsageError
from relpoint.types import GroundTruthLandmarks, TimeWindow, Trajectory

log = logging.getLogger(__name__)


class What(enum.Enum):
    """What to export."""

    TRAJECTORY = "trajectory"
    LANDMARKS = "landmarks"
    MAP = "map"


class Format(enum.Enum):
    """Output file formats."""

    TUM = "tum"
    KITTI = "kitti"
    CSV = "csv"
    PLY = "ply"


#: Output suffix -> format, when ``--format`` is not given.
SUFFIX_FORMATS = {
    ".tum": Format.TUM,
    ".txt": Format.TUM,
    ".kitti": Format.KITTI,
    ".csv": Format.CSV,
    ".ply": Format.PLY,
}
#: Formats each kind of data can be written as.
ALLOWED = {
    What.TRAJECTORY: (Format.TUM, Format.KITTI, Format.CSV, Format.PLY),
    What.LANDMARKS: (Format.PLY, Format.CSV),
    What.MAP: (Format.PLY, Format.CSV),
}
PLY_MAGIC = b"ply"


def output_format(out: Path, given: str | None) -> Format:
    """``--format`` if given, else the format of ``out``'s suffix; :class:`UsageError` if neither says."""
    if given is not None:
        return Format(given)
    fmt = SUFFIX_FORMATS.get(out.suffix.lower())
    if fmt is None:
        raise UsageError(
            f"cannot tell the output format from {out.name!r}",
            f"give --format {'|'.join(f.value for f in Format)} or a suffix {', '.join(SUFFIX_FORMATS)}",
        )
    return fmt


def _is_ply(path: Path) -> bool:
    try:
        with path.open("rb") as stream:
            return stream.read(4).rstrip(b"\r\n") == PLY_MAGIC
    except OSError:
        return False


def _is_run_directory(path: Path) -> bool:
    """A directory that is not a rosbag2 bag: a run's output directory (or nothing relpoint reads)."""
    return path.is_dir() and not is_log(path)


def default_what(source: Path, fmt: Format, *, selects_trajectory: bool = False) -> What:
    """``map`` for a PLY source or PLY output from a run directory, ``landmarks`` for PLY output from a log
    without a trajectory selected (``selects_trajectory``: ``--topic``, ``--parent``/``--child``), else
    ``trajectory`` (a trajectory file or a bag topic as PLY too)."""
    if _is_ply(source) or (_is_run_directory(source) and fmt is Format.PLY):
        return What.MAP
    if fmt is Format.PLY and is_log(source) and not selects_trajectory:
        return What.LANDMARKS
    return What.TRAJECTORY


def check_combination(what: What, fmt: Format) -> None:
    """:class:`UsageError` for data that the format cannot hold (landmarks or a map as TUM or KITTI)."""
    if fmt not in ALLOWED[what]:
        raise UsageError(
            f"{what.value} cannot be written as {fmt.value}",
            f"{what.value} export as {' or '.join(f.value for f in ALLOWED[what])}",
        )


# --- reading the source --------------------------------------------------------------------------------


def ground_truth_vertices(truth: GroundTruthLandmarks) -> np.ndarray:
    """True landmarks as PLY vertices: x, y, z float64, dynamic uint8, gt_id int32 (the landmark id)."""
    vertices = np.empty(
        len(truth.ids), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("dynamic", "u1"), ("gt_id", "<i4")]
    )
    vertices["x"], vertices["y"], vertices["z"] = truth.positions.T
    vertices["dynamic"] = truth.dynamic
    vertices["gt_id"] = truth.ids
    return vertices


def landmark_source(source: Path) -> tuple[np.ndarray, str]:
    """Landmarks of ``source`` as PLY vertices and a description, from a run's map.csv or a log's ground truth."""
    if _is_run_directory(source):
        landmarks = load_landmark_map(source)
        if landmarks is None:
            raise InputError(f"{source}: a directory without map.csv", "give a relpoint run output directory")
        return landmark_vertices(landmarks), f"relpoint landmark map from {source.name}/map.csv, frame world"
    if is_log(source):
        truth = load_ground_truth_landmarks(source)
        if truth is None:
            raise InputError(
                f"{source}: no /ground_truth/landmarks messages",
                "landmarks come from relpoint logs; a pose topic exports as PLY points with --topic",
            )
        return ground_truth_vertices(truth), f"ground-truth landmarks of {source.name}, frame world"
    raise InputError(f"{source}: landmarks come from a relpoint log or a run directory, not this file")


def map_source(source: Path) -> tuple[np.ndarray, str]:
    """Every vertex property of a run directory's map.ply, or of a PLY file."""
    if _is_run_directory(source):
        ply = source / "map.ply"
        if not ply.is_file():
            raise InputError(f"{source}: a directory without map.ply", "give a relpoint run output directory")
        return read_ply(ply), f"relpoint map from {source.name}/map.ply"
    if source.is_file() and _is_ply(source):
        return read_ply(source), f"relpoint map from {source.name}"
    if is_log(source):
        raise InputError(f"{source}: a log holds no map", "--what landmarks exports its ground-truth landmarks")
    raise InputError(f"{source}: maps come from a run directory (map.ply) or a PLY file")


# --- writing -------------------------------------------------------------------------------------------


def vertices_csv_text(vertices: np.ndarray) -> str:
    """CSV text of a structured array: one column per field, in order; floats round-trip their dtype."""
    names = vertices.dtype.names or ()
    formats = []
    for name in names:
        kind = vertices.dtype[name]
        if kind.kind == "f":
            formats.append("%.9g" if kind.itemsize <= 4 else "%.17g")
        elif kind.kind in "iub":
            formats.append("%d")
        else:
            raise InputError(f"vertex property {name!r} of type {kind} cannot be written as CSV")
    columns = np.empty((len(vertices), len(names)), dtype=object)
    for j, name in enumerate(names):
        column = vertices[name]
        columns[:, j] = column.astype(np.int64) if column.dtype.kind in "ub" else column
    buffer = io.StringIO()
    buffer.write(",".join(names) + "\n")
    if len(vertices):
        np.savetxt(buffer, columns, fmt=formats, delimiter=",")
    return buffer.getvalue()


def trajectory_vertices(trajectory: Trajectory) -> np.ndarray:
    """A trajectory as PLY vertices, one per pose: x, y, z (m), timestamp (s) and the quaternion qx, qy, qz,
    qw of ``T_world_frame``, all float64 (PLY has no 64-bit integer for the nanoseconds)."""
    fields = [(name, "<f8") for name in ("x", "y", "z", "timestamp", "qx", "qy", "qz", "qw")]
    vertices = np.empty(len(trajectory), dtype=fields)
    vertices["x"], vertices["y"], vertices["z"] = trajectory.positions.T
    vertices["timestamp"] = trajectory.timestamps
    vertices["qx"], vertices["qy"], vertices["qz"], vertices["qw"] = trajectory.quats_xyzw.T
    return vertices


def write_trajectory(out: Path, trajectory: Trajectory, fmt: Format, out_times: Path | None, header: str) -> None:
    """``trajectory`` as TUM, KITTI (with ``out_times`` if given), relpoint's trajectory CSV or PLY (a point
    per pose, :func:`trajectory_vertices`)."""
    if fmt is Format.TUM:
        write_tum(out, trajectory, header=header)
    elif fmt is Format.KITTI:
        write_kitti(out, trajectory, out_times)
    elif fmt is Format.PLY:
        write_ply(out, trajectory_vertices(trajectory), comments=[header])
    else:
        write_trajectory_csv(out, trajectory)


def export_file(
    source: Path,
    out: Path,
    what: What,
    fmt: Format,
    *,
    topic: str | None = None,
    parent: str | None = None,
    child: str | None = None,
    times: Path | None = None,
    out_times: Path | None = None,
    window: TimeWindow | None = None,
) -> str:
    """Read ``what`` from ``source`` and write it to ``out`` as ``fmt``; returns a one-line description.

    Raises
    ------
    UsageError
        Options that do not apply to ``what`` or ``fmt``.
    InputError
        Unreadable or unsuitable sources, and empty landmark sets or maps.
    """
    check_combination(what, fmt)
    if what is not What.TRAJECTORY and (topic or parent or child or times or (window and not window.is_open)):
        raise UsageError(
            f"--topic, --parent, --child, --times and --t-start/--t-end select a trajectory, not {what.value}"
        )
    if out_times is not None and fmt is not Format.KITTI:
        raise UsageError("--out-times applies only to KITTI output")
    if what is What.TRAJECTORY:
        trajectory = load_trajectory(source, topic=topic, parent=parent, child=child, times=times)
        if window is not None and not window.is_open:
            trajectory = trajectory.cropped(window)
            if len(trajectory) == 0:
                raise InputError(
                    f"{source}: --t-start/--t-end leave no pose", "the window counts seconds from its first pose"
                )
        origin = shown_path(source) + (f" {topic}" if topic else "") + (f" TF {parent} -> {child}" if parent else "")
        for path in (out, out_times):
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
        write_trajectory(out, trajectory, fmt, out_times, header=f"relpoint export of {origin}")
        return f"{len(trajectory)} poses"
    if what is What.LANDMARKS and _is_run_directory(source) and fmt is Format.CSV:
        landmarks = load_landmark_map(source)
        if landmarks is None:
            raise InputError(f"{source}: a directory without map.csv", "give a relpoint run output directory")
        if len(landmarks) == 0:
            raise InputError(f"{source}/map.csv: no landmarks to export")
        write_map_csv(out, landmarks)
        return f"{len(landmarks)} landmarks"
    vertices, comment = landmark_source(source) if what is What.LANDMARKS else map_source(source)
    noun = "landmarks" if what is What.LANDMARKS else "points"
    if len(vertices) == 0:
        raise InputError(f"{source}: no {noun} to export")
    if fmt is Format.PLY:
        write_ply(out, vertices, comments=[comment])
    else:
        write_text(out, vertices_csv_text(vertices))
    return f"{len(vertices)} {noun} ({', '.join(vertices.dtype.names or ())})"
