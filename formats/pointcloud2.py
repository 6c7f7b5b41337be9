"""``sensor_msgs/PointCloud2`` to and from numpy without per-point Python loops.

Decoding builds a structured dtype from the message's ``fields`` (offsets, datatypes, counts and
``point_step`` as the item size) and views the ``data`` buffer through it with ``np.frombuffer``,
so padding and extra fields cost nothing. Header values are checked against the buffer before any
view is made, so a lying header cannot make us read past the data or allocate from its claims.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from relpoint.errors import InputError

#: PointField datatype codes (sensor_msgs/msg/PointField) and their numpy scalar types.
DATATYPES: dict[int, np.dtype] = {
    1: np.dtype(np.int8),
    2: np.dtype(np.uint8),
    3: np.dtype(np.int16),
    4: np.dtype(np.uint16),
    5: np.dtype(np.int32),
    6: np.dtype(np.uint32),
    7: np.dtype(np.float32),
    8: np.dtype(np.float64),
}
_CODES = {dtype: code for code, dtype in DATATYPES.items()}


#: The fields relpoint reads from a cloud: the coordinates, the ground-truth landmark id, and the
#: ground-truth landmarks' dynamic flag (LOG_FORMAT.md). Every other field is tolerated unread.
READ_FIELDS = frozenset({"x", "y", "z", "id", "dynamic"})


@dataclass(frozen=True)
class Field:
    """One PointField: ``name``, byte ``offset`` in the point, ``datatype`` code, element ``count``."""

    name: str
    offset: int
    datatype: int
    count: int = 1


def cloud_dtype(fields: Sequence[Field], point_step: int, big_endian: bool = False) -> np.dtype:
    """Structured dtype for one point (cached: a log's clouds nearly always share one layout)."""
    return _cloud_dtype(tuple(fields), point_step, big_endian)


@functools.lru_cache(maxsize=64)
def _cloud_dtype(fields: tuple[Field, ...], point_step: int, big_endian: bool) -> np.dtype:
    """Structured dtype for one point of a cloud with these fields and ``point_step`` bytes per point.

    A field relpoint reads (:data:`READ_FIELDS`) must be unique, of a known datatype and inside
    ``point_step``, else :class:`InputError`. Any other field that is not (padding fields that share a
    name, as some drivers write, or a vendor's datatype) is left out of the dtype: nothing reads it.
    """
    names, formats, offsets = [], [], []
    for field in fields:
        read = field.name in READ_FIELDS
        if field.datatype not in DATATYPES:
            if not read:
                continue
            raise InputError(f"PointCloud2 field {field.name!r} has unknown datatype {field.datatype}")
        if field.name in names or (read and sum(f.name == field.name for f in fields) > 1):
            if not read:
                continue
            raise InputError(f"PointCloud2 has two fields named {field.name!r}")
        base = DATATYPES[field.datatype].newbyteorder(">" if big_endian else "<")
        count = max(1, int(field.count))
        end = field.offset + base.itemsize * count
        if field.offset < 0 or end > point_step:
            if not read:
                continue
            raise InputError(
                f"PointCloud2 field {field.name!r} (offset {field.offset}, {count} x {base.itemsize} bytes) "
                f"does not fit in point_step {point_step}"
            )
        names.append(field.name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(field.offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


def decode_cloud(
    data: npt.ArrayLike | bytes | memoryview,
    fields: Sequence[Field],
    *,
    width: int,
    height: int,
    point_step: int,
    row_step: int,
    big_endian: bool = False,
) -> np.ndarray:
    """View a PointCloud2 buffer as a structured array of ``width * height`` points (no copy).

    Rows are ``row_step`` bytes apart; a cloud whose rows are padded is gathered row by row.
    Raises :class:`InputError` when the header's sizes disagree with the buffer.
    """
    buffer = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8)
    buffer = buffer.reshape(-1)
    if width < 0 or height < 0 or (point_step <= 0 and width * height > 0):
        raise InputError(f"PointCloud2 has impossible sizes: width {width}, height {height}, point_step {point_step}")
    n_points = width * height
    dtype = cloud_dtype(fields, max(point_step, 1), big_endian)
    if n_points == 0:
        return np.zeros(0, dtype=dtype)
    if row_step < width * point_step:
        raise InputError(f"PointCloud2 row_step {row_step} is less than width x point_step = {width * point_step}")
    needed = row_step * (height - 1) + width * point_step
    if needed > buffer.size:
        raise InputError(
            f"PointCloud2 header claims {n_points} points ({needed} bytes) but the data holds {buffer.size} bytes"
        )
    if height == 1 or row_step == width * point_step:
        return np.frombuffer(buffer, dtype=dtype, count=n_points)
    rows = [np.frombuffer(buffer, dtype=dtype, count=width, offset=r * row_step) for r in range(height)]
    return np.concatenate(rows)


def xyz_from_cloud(cloud: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Finite xyz coordinates (N, 3) float64 from a decoded cloud, and the mask of kept points.

    Raises :class:`InputError` if the cloud lacks an ``x``, ``y`` or ``z`` field.
    """
    names = cloud.dtype.names or ()
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise InputError(f"PointCloud2 lacks the required field(s) {', '.join(missing)}")
    if any(cloud.dtype[axis].shape != () for axis in "xyz"):
        raise InputError("PointCloud2 fields x, y and z must have count 1")
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64, copy=False)
    finite = np.isfinite(xyz).all(axis=1)
    return (xyz if finite.all() else xyz[finite]), finite


def encode_cloud(columns: dict[str, npt.ArrayLike]) -> tuple[list[Field], int, bytes]:
    """Pack equal-length 1-D columns into a little-endian PointCloud2 payload.

    Each column keeps its dtype (must be one of :data:`DATATYPES`); fields are laid out in the order
    given, with no padding. Returns ``(fields, point_step, data)``.
    """
    arrays = {name: np.asarray(values) for name, values in columns.items()}
    lengths = {len(a) for a in arrays.values()}
    if len(lengths) > 1:
        raise ValueError(f"columns differ in length: { {k: len(v) for k, v in arrays.items()} }")
    fields, offset = [], 0
    for name, array in arrays.items():
        dtype = array.dtype.newbyteorder("=")
        if dtype not in _CODES:
            raise ValueError(f"column {name!r} has dtype {array.dtype}, not a PointField datatype")
        fields.append(Field(name, offset, _CODES[dtype], 1))
        offset += dtype.itemsize
    packed = np.zeros(lengths.pop() if lengths else 0, dtype=cloud_dtype(fields, offset))
    for name, array in arrays.items():
        packed[name] = array
    return fields, offset, packed.tobytes()
