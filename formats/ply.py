"""Binary PLY point clouds (maps) read and written through ``plyfile``.

A cloud is a numpy structured array whose fields become vertex properties (``x, y, z`` float, plus
any of ``nx, ny, nz``, ``red, green, blue`` uint8, ``weight``, ``observations``, ``dynamic``,
``gt_id``...). Open3D, MeshLab and CloudCompare read the files written here.
"""

from __future__ import annotations

import os

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from formats.atomic import atomic_path
from relpoint.errors import InputError
from relpoint.types import LandmarkMap

#: Largest error (m) that storing coordinates as float32 may make before they are stored as float64:
#: float32 keeps a millimetre up to 8 km from the origin, but a map in UTM coordinates (5e6 m north)
#: would be rounded to 0.5 m.
COORDINATE_TOLERANCE = 1e-4


def stored_coordinates(positions: np.ndarray) -> np.ndarray:
    """``positions`` (N, 3) m as float32 when that holds them within :data:`COORDINATE_TOLERANCE`, else
    as float64 (non-finite values, which no storage rounds, are not counted)."""
    values = np.asarray(positions, dtype=np.float64)
    single = values.astype(np.float32)
    with np.errstate(invalid="ignore"):
        error = np.abs(values - single)
    if not np.any(error > COORDINATE_TOLERANCE):  # NaN compares False
        return single
    return values


def write_ply(path: str | os.PathLike[str], vertices: np.ndarray, *, comments: list[str] | None = None) -> None:
    """Write a structured array as the ``vertex`` element of a binary little-endian PLY, atomically."""
    if vertices.dtype.names is None:
        raise ValueError("vertices must be a structured array (one field per PLY property)")
    # plyfile wants native scalar fields; bool becomes uint8.
    fields = [(name, np.uint8 if vertices.dtype[name] == np.bool_ else vertices.dtype[name].newbyteorder("<"))
              for name in vertices.dtype.names]  # fmt: skip
    packed = np.empty(len(vertices), dtype=fields)
    for name in vertices.dtype.names:
        packed[name] = vertices[name]
    data = PlyData([PlyElement.describe(packed, "vertex")], text=False, byte_order="<", comments=_marked(comments))
    with atomic_path(path) as tmp, tmp.open("wb") as stream:
        data.write(stream)


def _marked(comments: list[str] | None) -> list[str]:
    """The comments as :func:`ply_comment` lines, with one naming relpoint (what lets a later run recognise
    and replace the file)."""
    comments = [ply_comment(c) for c in comments or []]
    return comments if any("relpoint" in c for c in comments) else ["written by relpoint", *comments]


#: Escapes of the control characters that have a short one (the others are written ``\xNN``).
_SHORT_ESCAPES = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}


def ply_comment(text: str) -> str:
    """``text`` as one line of printable ASCII, which a PLY header's comment must be (a file name such as
    ``café.mcap`` goes into one): other characters are escaped as Python's ``backslashreplace`` does
    (``\\xe9``, ``\\u2013``), newlines, returns and tabs as ``\\n``, ``\\r``, ``\\t``."""
    return "".join(char if " " <= char <= "~" else _SHORT_ESCAPES.get(char) or _escaped(char) for char in text)


def _escaped(char: str) -> str:
    """One character as its ``\\xNN``, ``\\uNNNN`` or ``\\UNNNNNNNN`` escape."""
    code = ord(char)
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}" if code < 0x10000 else f"\\U{code:08x}"


def read_ply(path: str | os.PathLike[str]) -> np.ndarray:
    """The ``vertex`` element of a PLY file (ASCII or binary) as a structured array."""
    try:
        data = PlyData.read(str(path))
        return np.asarray(data["vertex"].data)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except (PlyParseError, KeyError, ValueError, EOFError) as error:
        raise InputError(f"{path} is not a readable PLY point cloud ({error})") from None


def landmark_vertices(landmarks: LandmarkMap) -> np.ndarray:
    """A landmark map as PLY vertices: x, y, z float32 (float64 far from the origin:
    :func:`stored_coordinates`) and observations, dynamic, gt_id (and purity and first_iteration where known)."""
    xyz = stored_coordinates(landmarks.positions)
    fields = [(axis, xyz.dtype) for axis in "xyz"] + [("observations", "<i4"), ("dynamic", "u1"), ("gt_id", "<i4")]
    if landmarks.purity is not None:
        fields.append(("purity", "<f4"))
    if landmarks.first_iteration is not None:
        fields.append(("first_iteration", "<i4"))
    vertices = np.empty(len(landmarks), dtype=fields)
    if landmarks.purity is not None:
        vertices["purity"] = landmarks.purity
    if landmarks.first_iteration is not None:
        vertices["first_iteration"] = landmarks.first_iteration
    vertices["x"], vertices["y"], vertices["z"] = xyz.T
    vertices["observations"] = landmarks.observations
    vertices["dynamic"] = landmarks.dynamic
    vertices["gt_id"] = landmarks.gt_id
    return vertices
