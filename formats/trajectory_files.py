"""Trajectory files, as evo reads them, to and from :class:`relpoint.types.Trajectory`.

* TUM (Sturm et al. 2012): one pose per line, ``timestamp tx ty tz qx qy qz qw``, seconds, metres,
  quaternion (x, y, z, w) of ``T_world_frame``; lines starting with ``#`` and blank lines are ignored;
  any run of spaces or tabs separates values (commas too, as some tools write them).
* EuRoC MAV ground truth (``mav0/state_groundtruth_estimate0/data.csv``): comma-separated,
  ``timestamp [ns], p_RS_R_x, p_RS_R_y, p_RS_R_z [m], q_RS_w, q_RS_x, q_RS_y, q_RS_z`` (quaternion
  w first), then any number of further columns (velocity, biases), which are ignored; the header line
  starts with ``#``.
* KITTI odometry poses: one pose per line, the first three rows of ``T_world_frame`` row-major
  (12 values). Stamps come from a separate times file (one value in seconds per line, KITTI's
  ``times.txt``); without one, pose ``i`` gets stamp ``i`` seconds, so two KITTI files without times
  pair frame by frame, as evo pairs them by index.
* Any of these, or a CSV another tool wrote, with a header line naming its columns
  (``#timestamp,x,y,z,qw,qx,qy,qz``, ``time tx ty tz qx qy qz qw``, ``rostopic echo -p``'s
  ``%time,field.pose.position.x,...``; commented out with ``#`` or not): the columns are taken by
  their names (:func:`header_layout`), the stamp's unit from the header (``[ns]``, ``_ns``) or, for
  integer stamps of 17 digits or more, nanoseconds. A header states the quaternion order, which the
  values alone cannot.

:func:`detect_format` tells them apart by content (and a ``.csv`` suffix where content alone is
ambiguous). Each has a reader and a writer (``read_tum``/``write_tum``, ``read_euroc_csv``/
``write_euroc_csv``, ``read_kitti``/``write_kitti``).

Stamps are parsed from their decimal text into exact integer nanoseconds and written back exactly, and
floats are written with ``repr`` (shortest round-tripping form), so a read-write-read cycle is lossless.
Writes are atomic: a temporary file in the target's directory is renamed over it.

Repeated stamps (motion-capture files have them now and then) are kept as evo keeps them, both poses in
file order: :func:`separate_repeated_stamps` moves each earlier copy 1 ns back so that stamps increase,
and the reader says so once (a warning with the count). evo compares stamps as float64 seconds, in which
1 ns vanishes for epoch stamps, so evo's nearest-stamp association picks the same poses: the first copy
for a stamp just before the repeat, the last copy for the repeated stamp itself and after it, every copy
when the file is the shorter of the two. Stamps that go back in time are an error.
"""

from __future__ import annotations

import codecs
import csv
import logging
import os
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from enum import Enum
from pathlib import Path

import numpy as np
import numpy.typing as npt

import relpoint
from formats.atomic import write_text
from formats.outputs import unreadable_input
from relpoint.errors import InputError
from relpoint.geometry import matrix_to_position_quat
from relpoint.types import FloatArray, IntArray, Trajectory

logger = logging.getLogger(__name__)

_SEPARATORS = re.compile(r"[\s,]+")
_NS_PER_S = 1_000_000_000
_INT64_MIN, _INT64_MAX = int(np.iinfo(np.int64).min), int(np.iinfo(np.int64).max)


def _data_lines(path: Path, *, comma_separated: bool = False) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of the non-comment, non-blank lines of ``path``.

    Fields are separated by any run of blanks and commas; with ``comma_separated``, a line holding commas
    is read as CSV: each comma separates a value (an empty one between two commas included), quotes
    keep commas inside a value (``"(0.0, 0.0)"``), blanks around values are stripped.
    """
    for number, stripped in text_lines(path):
        if not stripped or stripped.startswith("#"):
            continue
        if comma_separated and "," in stripped:
            yield number, [f.strip() for f in next(csv.reader([stripped]))]
        else:
            yield number, [f for f in _SEPARATORS.split(stripped) if f]


def text_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, stripped text) of every line of ``path``; InputError if it cannot be read as text."""
    try:
        text = _decode(path.read_bytes(), final=True)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, expected a trajectory file") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file") from None
    except OSError as exc:
        raise unreadable_input(path, exc) from None
    return [(number, line.strip()) for number, line in enumerate(text.splitlines(), start=1)]


def _decode(data: bytes, *, final: bool) -> str:
    """The text of a file's bytes ``data``: UTF-8 (a BOM dropped), or UTF-16 after its BOM (what Windows
    PowerShell's ``>`` writes). With ``final`` False, ``data`` is the file's beginning only, and a
    character that its end cuts in two is left out.

    Raises ``UnicodeDecodeError`` for bytes that are neither, and for UTF-16 that is not mostly ASCII:
    numbers and column names are, and binary data behind those two bytes is not.
    """
    if data[:2] not in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE):
        return codecs.getincrementaldecoder("utf-8-sig")().decode(data, final=final)
    text = codecs.getincrementaldecoder("utf-16")().decode(data, final=final)
    if sum(map(str.isascii, text)) < 0.9 * len(text):
        raise UnicodeDecodeError("utf-16", data, 0, len(data), "not mostly ASCII text")
    return text


def identity_where_never_set(quats: FloatArray, source: object) -> FloatArray:
    """``quats`` (n, 4), or the identity for each when every one is zero: a trajectory without orientation
    (a total station, GNSS, a pose whose orientation was never set), read as evo reads it, with a warning
    naming ``source``."""
    if len(quats) == 0 or np.any(quats):
        return quats
    logger.warning("%s: every quaternion is zero, a trajectory without orientation: read with the identity "
                   "rotation, as evo does; only the APE translation (and RPE --pose-relation point_distance) "
                   "means anything", source)  # fmt: skip
    return np.tile([0.0, 0.0, 0.0, 1.0], (len(quats), 1))


def parse_stamp_ns(text: str) -> int:
    """Exact integer nanoseconds of a decimal seconds string (``1305031102.175304``, ``1.0e-01``).

    Raises ``ValueError`` for text that is not a finite number.
    """
    whole, dot, fraction = text.partition(".")
    if whole.isdigit() and (not dot or fraction.isdigit()) and len(fraction) <= 9:
        # The common case, plain decimal seconds: exact integer arithmetic without Decimal.
        return int(whole) * _NS_PER_S + int(fraction.ljust(9, "0") or 0)
    try:
        value = Decimal(text)
    except InvalidOperation:
        raise ValueError(f"not a number: {text!r}") from None
    if not value.is_finite():
        raise ValueError(f"not a finite stamp: {text!r}")
    return int((value * _NS_PER_S).to_integral_value())


def format_stamp(stamp_ns: int) -> str:
    """Decimal seconds text of integer nanoseconds, exact (9 decimals)."""
    sign = "-" if stamp_ns < 0 else ""
    seconds, nanos = divmod(abs(int(stamp_ns)), _NS_PER_S)
    return f"{sign}{seconds}.{nanos:09d}"


def _numbers(fields: list[str], path: Path, number: int) -> list[float]:
    """``fields`` as floats (NaN and infinity included); InputError naming the line if one is not a number."""
    try:
        return [float(f) for f in fields]
    except ValueError:
        raise InputError(f"{path}:{number}: non-numeric value in {' '.join(fields)!r}") from None


def _floats(fields: list[str], path: Path, number: int) -> list[float]:
    values = _numbers(fields, path, number)
    if not all(np.isfinite(values)):
        raise InputError(f"{path}:{number}: non-finite value in {' '.join(fields)!r}")
    return values


def separate_repeated_stamps(stamps_ns: npt.ArrayLike) -> IntArray:
    """Non-decreasing stamps (N,) int64 ns made strictly increasing by moving repeated ones back.

    Each stamp becomes ``min(stamp, next stamp - 1 ns)``, from the last one back, so of ``k`` copies of
    a stamp the last keeps it and the earlier ones sit 1 ns apart just before it. Stamps already
    increasing are returned unchanged (a copy).
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    offsets = np.arange(stamps.size, dtype=np.int64)
    # out[i] = min over j >= i of (stamps[j] - (j - i)): a running minimum from the end.
    return np.minimum.accumulate((stamps - offsets)[::-1])[::-1] + offsets


#: Stamps are nanoseconds from this value up (in seconds, year 3e9): integers under a header that names no
#: unit, and any stamp of a file whose every stamp is this large.
_NANOSECOND_STAMP = 10**17
#: A median step between poses above this (a day, in ns) says the stamps are nanoseconds read as seconds.
NANOSECOND_LIKE_STEP_NS = 86_400 * 10**9


def _increasing_stamps(path: Path, stamps: list[int], lines: list[int]) -> IntArray:
    """``stamps`` as strictly increasing int64 ns: repeats separated (one warning), going back refused.

    Stamps of seconds that are all :data:`_NANOSECOND_STAMP` or more (beyond year 3e9) are nanoseconds
    written where seconds belong (ORB-SLAM3 writes EuRoC's into TUM files): read as such, with a warning.
    """
    if stamps and min(stamps) >= _NANOSECOND_STAMP * _NS_PER_S:
        logger.warning("%s: its stamps are %.4g s, beyond year 3e9: read as nanoseconds, which they are",
                       path, stamps[0] / _NS_PER_S)  # fmt: skip
        stamps = [(stamp + _NS_PER_S // 2) // _NS_PER_S for stamp in stamps]  # to the nearest nanosecond
    out_of_range = [k for k, stamp in enumerate(stamps) if not _INT64_MIN <= stamp <= _INT64_MAX]
    if out_of_range:
        raise InputError(f"{path}:{lines[out_of_range[0]]}: timestamp out of range (beyond year 2262)",
                         "stamps that large are nanoseconds: this format holds seconds (divide them by 1e9)")  # fmt: skip
    stamps_arr = np.array(stamps, dtype=np.int64)
    steps = np.diff(stamps_arr)
    if steps.size and np.median(steps) > NANOSECOND_LIKE_STEP_NS:
        logger.warning("%s: its poses are %.3g s apart (median): are the stamps nanoseconds? This format holds seconds",
                    path, float(np.median(steps)) * 1e-9)  # fmt: skip
    back = np.nonzero(steps < 0)[0]
    if back.size:
        k = int(back[0]) + 1
        raise InputError(
            f"{path}:{lines[k]}: timestamp goes back in time (previous pose at line {lines[k - 1]})",
            "sort the file by time",
        )
    repeats = np.nonzero(steps == 0)[0]
    if repeats.size:
        separated = separate_repeated_stamps(stamps_arr)
        k = int(repeats[0]) + 1
        moved = int(np.count_nonzero(separated != stamps_arr))
        logger.warning(
            "%s: %d repeated timestamp%s (the first: line %d repeats the stamp of line %d); kept every pose as "
            "evo does, each earlier copy moved 1 ns back so that stamps increase",
            path, moved, "s" if moved > 1 else "",
            lines[k], lines[k - 1],
        )  # fmt: skip
        stamps_arr = separated
    return stamps_arr


def _build(
    path: Path, stamps: list[int], positions: list[list[float]], quats: np.ndarray, lines: list[int]
) -> Trajectory:
    if not stamps:
        raise InputError(f"{path}: no poses in file")
    stamps_arr = _increasing_stamps(path, stamps, lines)
    quats = identity_where_never_set(np.asarray(quats, dtype=np.float64).reshape(-1, 4), path)
    zero = np.linalg.norm(quats, axis=1) < 1e-9
    if zero.any():
        raise InputError(
            f"{path}:{lines[int(np.argmax(zero))]}: zero quaternion",
            "give the pose its orientation or leave the line out (a file without any orientation has zeros in "
            "every line)",
        )
    return Trajectory(stamps_arr, np.array(positions, dtype=np.float64).reshape(-1, 3), quats)


def _read_tum_fast(path: Path) -> Trajectory | None:
    """Whole-file parse of a well-formed TUM file; ``None`` sends the caller to the line-by-line reader.

    The line-by-line reader names the file and line of any problem; this path only handles files
    with exactly 8 finite values on every data line and plain decimal stamps, which is nearly all.
    """
    lines = [(number, line) for number, line in text_lines(path) if line and not line.startswith("#")]
    if not lines:
        return None
    fields = " ".join(line for _, line in lines).replace(",", " ").split()
    if len(fields) != 8 * len(lines):
        return None
    table = np.array(fields, dtype=object).reshape(-1, 8)
    try:
        stamps = [parse_stamp_ns(text) for text in table[:, 0]]
        values = table[:, 1:].astype(np.float64)
    except ValueError:
        return None
    if not np.isfinite(values).all():
        return None
    return _build(path, stamps, values[:, :3].tolist(), values[:, 3:], [number for number, _ in lines])


def _pose_rows(path: Path, stamps: list[int], rows: list[list[str]], lines: list[int]) -> Trajectory:
    """The trajectory of text ``rows`` (x y z qx qy qz qw each) at ``stamps``, read from ``lines`` of ``path``:
    InputError naming the line of a non-numeric value; rows with a NaN or infinite value left out."""
    try:
        values = np.array(rows, dtype=np.float64).reshape(-1, 7)
    except ValueError:  # find the offending line for the message
        for number, fields in zip(lines, rows, strict=True):
            _numbers(fields, path, number)
        raise
    stamps, lines, values = _finite_rows(path, stamps, lines, values)
    logger.debug("read %d poses from %s", len(stamps), path)
    return _build(path, stamps, values[:, :3].tolist(), values[:, 3:], lines)


def _finite_rows(
    path: Path, stamps: list[int], lines: list[int], values: np.ndarray
) -> tuple[list[int], list[int], np.ndarray]:
    """The rows of ``values`` (N, 7) without a NaN or infinite value, with their stamps and line numbers.

    A pose with a NaN or infinite value (a motion-capture dropout) says nothing: left out, as evo's
    alignment would be poisoned by it, with one warning; InputError when no row is left.
    """
    finite = np.isfinite(values).all(axis=1)
    if finite.all():
        return stamps, lines, values
    dropped = np.nonzero(~finite)[0]
    if dropped.size == len(stamps):
        raise InputError(f"{path}: every pose holds a NaN or infinite value", "check how the file was written")
    logger.warning("%s: %d pose%s holding a NaN or infinite value left out (the first: line %d)",
                   path, dropped.size, "s" if dropped.size > 1 else "", lines[int(dropped[0])])  # fmt: skip
    keep = np.nonzero(finite)[0]
    return [stamps[k] for k in keep], [lines[k] for k in keep], values[keep]


def read_tum(path: str | os.PathLike[str]) -> Trajectory:
    """Read a TUM trajectory file (see the module docstring).

    Raises
    ------
    InputError
        Missing or unreadable file, no poses, a row without 8 values or with a non-numeric value, a zero
        quaternion, or stamps that do not increase - naming the file and line. Rows holding a NaN or an
        infinite value are left out with a warning (an error only when no row is left).
    """
    path = Path(path)
    fast = _read_tum_fast(path)
    if fast is not None:
        return fast
    stamps: list[int] = []
    rows: list[list[str]] = []
    lines: list[int] = []
    for number, fields in _data_lines(path):
        if len(fields) != 8:
            raise InputError(f"{path}:{number}: expected 8 values (timestamp tx ty tz qx qy qz qw), got {len(fields)}")
        try:
            stamps.append(parse_stamp_ns(fields[0]))
        except ValueError:
            raise InputError(f"{path}:{number}: bad timestamp {fields[0]!r}") from None
        rows.append(fields[1:])
        lines.append(number)
    return _pose_rows(path, stamps, rows, lines)


def read_kitti(path: str | os.PathLike[str], times_path: str | os.PathLike[str] | None = None) -> Trajectory:
    """Read KITTI poses (12 values per line) with an optional times file (one stamp in seconds per line).

    Without ``times_path`` pose ``i`` is stamped ``i`` seconds, so two KITTI files of the same sequence
    match frame by frame under the default 0.01 s tolerance.

    Raises
    ------
    InputError
        Unreadable files, a row without 12 values, non-numeric values, a rotation block that is not a
        rotation, a times file whose line count differs from the poses', or non-increasing times.
    """
    path = Path(path)
    rows: list[list[float]] = []
    lines: list[int] = []
    for number, fields in _data_lines(path):
        if len(fields) != 12:
            raise InputError(f"{path}:{number}: expected 12 values (3x4 pose, row-major), got {len(fields)}")
        rows.append(_floats(fields, path, number))
        lines.append(number)
    if not rows:
        raise InputError(f"{path}: no poses in file")
    T = np.zeros((len(rows), 4, 4))
    T[:, :3, :] = np.array(rows).reshape(-1, 3, 4)
    T[:, 3, 3] = 1.0
    R = T[:, :3, :3]
    orth_err = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.nonzero((orth_err > 1e-4) | (det <= 0))[0]
    if bad.size:
        raise InputError(f"{path}:{lines[int(bad[0])]}: the 3x3 block is not a rotation matrix")
    if times_path is None:
        stamps = [i * _NS_PER_S for i in range(len(rows))]
        stamp_lines = lines
    else:
        times_path = Path(times_path)
        stamps, stamp_lines = [], []
        for number, fields in _data_lines(times_path):
            if len(fields) != 1:
                raise InputError(f"{times_path}:{number}: expected one time in seconds, got {len(fields)} values")
            try:
                stamps.append(parse_stamp_ns(fields[0]))
            except ValueError:
                raise InputError(f"{times_path}:{number}: bad time {fields[0]!r}") from None
            stamp_lines.append(number)
        if len(stamps) != len(rows):
            raise InputError(f"{times_path}: {len(stamps)} times for {len(rows)} poses in {path}")
        path = times_path  # stamp errors below refer to the times file
    positions, quats = matrix_to_position_quat(T)
    return _build(path, stamps, positions.tolist(), quats, stamp_lines)


def read_relpoint_csv(path: str | os.PathLike[str]) -> Trajectory:
    """Read relpoint's own ``trajectory.csv`` (``iteration,timestamp,x,y,z,qx,qy,qz,qw``, seconds).

    Raises
    ------
    InputError
        As :func:`read_tum`: no poses, a row without 9 values, a non-numeric or non-finite value, a zero
        quaternion, or stamps that do not increase - naming the file and line.
    """
    path = Path(path)
    stamps: list[int] = []
    positions: list[list[float]] = []
    quats: list[list[float]] = []
    lines: list[int] = []
    for number, fields in _data_lines(path):
        if fields == RELPOINT_CSV_HEADER:
            continue
        if len(fields) != len(RELPOINT_CSV_HEADER):
            raise InputError(f"{path}:{number}: expected 9 values ({','.join(RELPOINT_CSV_HEADER)}), got {len(fields)}")
        try:
            stamps.append(parse_stamp_ns(fields[1]))
        except ValueError:
            raise InputError(f"{path}:{number}: bad timestamp {fields[1]!r}") from None
        values = _floats(fields[2:], path, number)
        positions.append(values[:3])
        quats.append(values[3:])
        lines.append(number)
    return _build(path, stamps, positions, np.array(quats, dtype=np.float64).reshape(-1, 4), lines)


def read_euroc_csv(path: str | os.PathLike[str]) -> Trajectory:
    """Read EuRoC ground truth (``state_groundtruth_estimate0/data.csv``; see the module docstring).

    The stamp column is integer nanoseconds and is kept exact (evo divides its float by 1e9, which can
    differ from the exact value by one float64 step, about 0.2 us, with no effect on the association).

    Raises
    ------
    InputError
        Missing or unreadable file, no poses, a row with fewer than 8 values, a stamp that is not an
        integer, a non-numeric or non-finite value, a zero quaternion, or stamps going back in time -
        naming the file and line.
    """
    path = Path(path)
    stamps: list[int] = []
    rows: list[list[float]] = []
    lines: list[int] = []
    for number, fields in _data_lines(path):
        if len(fields) < 8:
            raise InputError(
                f"{path}:{number}: expected at least 8 values (timestamp [ns], p_RS_R xyz, q_RS wxyz), got {len(fields)}"
            )
        if not (fields[0].isascii() and fields[0].isdigit()):
            raise InputError(f"{path}:{number}: bad timestamp {fields[0]!r}, expected integer nanoseconds")
        stamps.append(int(fields[0]))
        rows.append(_floats(fields[1:8], path, number))
        lines.append(number)
    values = np.array(rows, dtype=np.float64).reshape(-1, 7)
    quats_xyzw = values[:, [4, 5, 6, 3]]  # q_RS is w first
    logger.debug("read %d poses from %s", len(stamps), path)
    return _build(path, stamps, values[:, :3].tolist(), quats_xyzw, lines)


class TrajectoryFormat(Enum):
    """Text trajectory formats :func:`detect_format` recognises."""

    TUM = "tum"
    KITTI = "kitti"
    EUROC = "euroc"
    RELPOINT_CSV = "relpoint-csv"
    #: A header line names the columns (:func:`header_layout`, :func:`read_named_columns`).
    NAMED_COLUMNS = "named-columns"


#: The header of relpoint's own ``trajectory.csv`` (:func:`formats.tables.write_trajectory_csv`).
RELPOINT_CSV_HEADER = ["iteration", "timestamp", "x", "y", "z", "qx", "qy", "qz", "qw"]


#: Column names of EuRoC's ground-truth header; any of them in a ``#`` line marks the file as EuRoC.
_EUROC_HEADER_MARKS = ("p_RS_R_x", "q_RS_w")


def _head(path: Path) -> tuple[list[tuple[int, str]], tuple[int, str]] | None:
    """(``#`` lines before the first data line, that line), each as (line number, stripped text), from the
    first 64 KiB of ``path``.

    None for a binary file or one without a data line there; InputError if it cannot be opened.
    """
    try:
        with path.open("rb") as stream:
            head = stream.read(1 << 16)
    except OSError as error:
        raise unreadable_input(path, error) from None
    try:
        text = _decode(head, final=len(head) < 1 << 16)
    except UnicodeDecodeError:
        return None
    comments = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped.startswith("#"):
            comments.append((number, stripped))
        elif stripped:
            return comments, (number, stripped)
    return None


def _first_lines(path: Path) -> tuple[list[str], list[str]] | None:
    """(``#`` lines before the first data line, fields of that line, with a trailing ``","`` when the line
    is comma-separated) from the first 64 KiB of ``path``; None as :func:`_head`."""
    head = _head(path)
    return None if head is None else _split_head(head)


def _split_head(head: tuple[list[tuple[int, str]], tuple[int, str]]) -> tuple[list[str], list[str]]:
    """:func:`_first_lines` of a file whose :func:`_head` is ``head``."""
    comments, (_, line) = head
    return [text for _, text in comments], [f for f in _SEPARATORS.split(line) if f] + ([","] if "," in line else [])


#: Words naming a stamp column; a name of these and units alone (``timestamp [ns]``, ``time_s``,
#: ``field.header.stamp``) is the stamp.
_STAMP_WORDS = frozenset({"timestamp", "time", "stamp", "t", "times", "field", "header", "sec", "secs", "seconds"})
#: Stamp units, in nanoseconds.
_STAMP_UNITS = {"s": _NS_PER_S, "sec": _NS_PER_S, "secs": _NS_PER_S, "seconds": _NS_PER_S, "ms": 1_000_000,
                "us": 1_000, "ns": 1}  # fmt: skip
#: Words that make an axis a position or a quaternion component (the last such word of a name counts:
#: ``field.pose.orientation.x`` is a quaternion's, ``p_RS_R_x`` a position's).
_POSITION_WORDS = frozenset({"p", "t", "pos", "position", "translation", "trans"})
_QUATERNION_WORDS = frozenset({"q", "quat", "quaternion", "orientation", "rotation", "rot"})
_UNIT = re.compile(r"[\[(]([^\])]*)[\])]")
#: A name's words: runs of letters and digits.
_WORD = re.compile(r"[A-Za-z0-9]+")


def _column_role(name: str) -> tuple[str, str] | None:
    """What a header's column ``name`` holds: ``("t", unit)`` (unit ``""`` when not named), ``("p", axis)``
    or ``("q", axis)``; None for any other column (velocities, biases, covariances)."""
    unit_match = _UNIT.search(name)
    unit = unit_match.group(1).strip().lower() if unit_match else ""
    words = [w.lower() for w in _WORD.findall(_UNIT.sub(" ", name))]
    if not words:
        return None
    stamp_words = [w for w in words if w not in _STAMP_UNITS]
    if stamp_words and set(stamp_words) <= _STAMP_WORDS and set(stamp_words) != {"field"}:
        units = [w for w in words if w in _STAMP_UNITS]
        unit = unit or (units[-1] if units else "")
        return ("t", unit) if unit in _STAMP_UNITS or not unit else None
    last, kinds = words[-1], words[:-1]
    if last not in ("x", "y", "z", "w"):
        if len(last) == 2 and last[1] in "xyzw" and last[0] in "qtp":  # qx, tx, px
            last, kinds = last[1], [*kinds, last[0]]
        else:
            return None
    kind = next((w for w in reversed(kinds) if w in _POSITION_WORDS or w in _QUATERNION_WORDS), None)
    if kind is None:
        if kinds:  # v_RS_R_x, b_w_RS_S_x, twist.linear.x: another quantity's axis
            return None
        return ("q", "w") if last == "w" else ("p", last)
    if kind in _QUATERNION_WORDS:
        return "q", last
    return ("p", last) if last != "w" else None


@dataclass(frozen=True)
class ColumnLayout:
    """Where a trajectory file's values are, from the header line naming its columns.

    line: the header's line number (1-based). commented: the header starts with ``#``. names: its column
    names. stamp: the stamp's column; position: x, y, z's; quaternion: x, y, z, w's (0-based).
    stamp_unit_ns: nanoseconds per stamp unit as the header names it, None when it names none.
    comma_separated: the header separates its names with commas, so the rows' values are one per comma.
    stamp_nanoseconds: the column of the stamp's nanoseconds when the stamp is split in two
    (``header.stamp.secs``, ``header.stamp.nsecs``), whole seconds then in ``stamp``; None otherwise.
    """

    line: int
    commented: bool
    names: tuple[str, ...]
    stamp: int
    position: tuple[int, int, int]
    quaternion: tuple[int, int, int, int]
    stamp_unit_ns: int | None
    comma_separated: bool = False
    stamp_nanoseconds: int | None = None

    @property
    def is_tum(self) -> bool:
        """The columns are TUM's, in TUM's order, in seconds (or no unit named)."""
        return (
            len(self.names) == 8
            and (self.stamp, self.position, self.quaternion) == (0, (1, 2, 3), (4, 5, 6, 7))
            and self.stamp_unit_ns in (None, _NS_PER_S)
        )


def _header_names(text: str) -> list[str]:
    """The column names of a header line (commas separate names when there are any, else blanks; a
    blank-separated unit such as ``[m]`` belongs to the name before it)."""
    text = text.lstrip("#").strip()
    if "," in text:
        return [name.strip() for name in text.split(",")]
    names: list[str] = []
    for word in text.split():
        if names and _UNIT.fullmatch(word):
            names[-1] += " " + word
        else:
            names.append(word)
    return names


#: Last words of the column holding a split stamp's nanoseconds (ROS 1 ``nsecs``, ROS 2 ``nanosec``).
_NANOSECOND_WORDS = frozenset({"nsec", "nsecs", "nanosec", "nanosecs"})


def _nanoseconds_column(names: list[str], stamp: int) -> int | None:
    """The column holding the nanoseconds of the stamp in column ``stamp`` when that one holds its whole
    seconds (``header.stamp.secs`` beside ``header.stamp.nsecs``, ``header.stamp.sec`` beside
    ``header.stamp.nanosec``), else None."""
    words = [w.lower() for w in _WORD.findall(names[stamp])]
    if not words or words[-1] not in ("sec", "secs"):
        return None
    for column, name in enumerate(names):
        other = [w.lower() for w in _WORD.findall(name)]
        if other[:-1] == words[:-1] and other[-1:] and other[-1] in _NANOSECOND_WORDS:
            return column
    return None


def _is_header_stamp(name: str) -> bool:
    """Whether a stamp column ``name`` is a message's own ``header.stamp`` (``field.header.stamp``), not
    the time it was recorded at (``rostopic echo -p``'s ``%time``)."""
    return "header" in (w.lower() for w in _WORD.findall(name))


def _layout_of(names: list[str], line: int, commented: bool, comma_separated: bool = False) -> ColumnLayout | None:
    """The layout that ``names`` give, or None unless they name one stamp, one x, y, z and one quaternion.

    Of two stamp columns, the message's ``header.stamp`` is taken over the other (``rostopic echo -p``
    writes ``%time``, the receive time, and ``field.header.stamp``), as bag topics are read by their
    ``header.stamp``; any other pair of columns for one value leaves the layout undecided.
    """
    roles: dict[tuple[str, str], int] = {}
    stamp_unit = ""
    for column, name in enumerate(names):
        role = _column_role(name)
        if role is None:
            continue
        if role[0] == "t":
            if ("t", "") in roles:
                first_is_header = _is_header_stamp(names[roles[("t", "")]])
                if first_is_header == _is_header_stamp(name):
                    return None  # two stamps, neither the message's own: the names do not say which
                if first_is_header:
                    continue
                del roles[("t", "")]
            role, stamp_unit = ("t", ""), role[1]
        if role in roles:
            return None  # two columns for one value: the names do not say which to take
        roles[role] = column
    wanted = [("t", ""), *(("p", a) for a in "xyz"), *(("q", a) for a in "xyzw")]
    if any(role not in roles for role in wanted):
        return None
    return ColumnLayout(
        line=line,
        commented=commented,
        names=tuple(names),
        stamp=roles[("t", "")],
        position=(roles[("p", "x")], roles[("p", "y")], roles[("p", "z")]),
        quaternion=(roles[("q", "x")], roles[("q", "y")], roles[("q", "z")], roles[("q", "w")]),
        stamp_unit_ns=_STAMP_UNITS.get(stamp_unit),
        comma_separated=comma_separated,
        stamp_nanoseconds=_nanoseconds_column(names, roles[("t", "")]),
    )


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def header_layout(path: str | os.PathLike[str]) -> ColumnLayout | None:
    """The column layout a header line of ``path`` names, or None when it has none that names them all.

    The header is the first non-blank line when its first value is not a number (a header left
    uncommented), else the last ``#`` line before the first data line. It must name the stamp, the
    position's x, y, z and the quaternion's x, y, z, w, each once (``timestamp``, ``time``, ``%time``,
    ``field.header.stamp``; ``x``, ``tx``, ``p_x``, ``pos_x``, ``field.pose.position.x``,
    ``p_RS_R_x``; ``qx``, ``q_x``, ``q_RS_x``, ``field.pose.orientation.x``, ``w``); other columns are
    ignored. Units in brackets (``timestamp [ns]``) or as a last word (``time_ns``) set the stamp's.

    Raises
    ------
    InputError
        If the file cannot be opened, or its first line is an uncommented header whose names do not
        give the layout.
    """
    path = Path(path)
    return _layout_in(path, _head(path))


def _layout_in(path: Path, head: tuple[list[tuple[int, str]], tuple[int, str]] | None) -> ColumnLayout | None:
    """:func:`header_layout` of a file whose :func:`_head` is ``head``."""
    if head is None:
        return None
    comments, (number, line) = head
    first = [f for f in _SEPARATORS.split(line) if f]
    if first and not _is_number(first[0]):
        names = _header_names(line)
        layout = _layout_of(names, number, commented=False, comma_separated="," in line)
        if layout is None:
            raise InputError(
                f"{path}:{number}: a header line whose names do not say where the stamp, position and "
                f"quaternion are ({', '.join(names[:10])})",
                "name the columns as timestamp,x,y,z,qx,qy,qz,qw (any order; `[ns]` after timestamp for "
                "nanoseconds), or comment the line out with # to read the file as TUM",
            )
        return layout
    if comments:
        number, text = comments[-1]
        return _layout_of(_header_names(text), number, commented=True, comma_separated="," in text)
    return None


def read_named_columns(path: str | os.PathLike[str], layout: ColumnLayout | None = None) -> Trajectory:
    """Read a trajectory file by the column names of its header (:func:`header_layout`).

    Stamps are seconds unless the header names another unit; integer stamps of 17 digits or more under
    a header naming none are nanoseconds. Rows holding a NaN or an infinite value are left out with a
    warning, as :func:`read_tum` does.

    Raises
    ------
    InputError
        No header naming the columns, no poses, a row with another number of values than the header
        names, a bad stamp or value, a zero quaternion, or stamps going back in time - naming the file
        and line.
    """
    path = Path(path)
    layout = layout or header_layout(path)
    if layout is None:
        raise InputError(f"{path}: no header line naming the columns (timestamp, x, y, z, qx, qy, qz, qw)")
    width = len(layout.names)
    stamps_text: list[str] = []
    nanoseconds_text: list[str] = []
    rows: list[list[str]] = []
    lines: list[int] = []
    for number, fields in _data_lines(path, comma_separated=layout.comma_separated):
        if number == layout.line:
            continue
        if layout.comma_separated and len(fields) == width + 1 and not fields[-1]:
            fields.pop()  # a comma ending every row (VINS-Mono's CSV)
        if len(fields) != width:
            raise InputError(f"{path}:{number}: expected {width} values, as the header on line {layout.line} names, "
                             f"got {len(fields)}")  # fmt: skip
        stamps_text.append(fields[layout.stamp])
        if layout.stamp_nanoseconds is not None:
            nanoseconds_text.append(fields[layout.stamp_nanoseconds])
        rows.append([fields[k] for k in (*layout.position, *layout.quaternion)])
        lines.append(number)
    if layout.stamp_nanoseconds is not None:  # whole seconds and nanoseconds in two columns
        stamps_text = [_joined_stamp(sec, nsec, path, number)
                       for sec, nsec, number in zip(stamps_text, nanoseconds_text, lines, strict=True)]  # fmt: skip
    unit = layout.stamp_unit_ns if layout.stamp_nanoseconds is None else _NS_PER_S
    if unit is None and stamps_text and all(t.isascii() and t.isdigit() for t in stamps_text):
        unit = 1 if int(stamps_text[0]) >= _NANOSECOND_STAMP else None
    stamps: list[int] = []
    for text, number in zip(stamps_text, lines, strict=True):
        try:
            if unit in (None, _NS_PER_S):
                stamps.append(parse_stamp_ns(text))
            else:
                stamps.append(int((Decimal(text) * unit).to_integral_value()))
        except (ValueError, InvalidOperation):
            raise InputError(f"{path}:{number}: bad timestamp {text!r}") from None
    return _pose_rows(path, stamps, rows, lines)


def _joined_stamp(seconds: str, nanoseconds: str, path: Path, number: int) -> str:
    """Decimal seconds text of a stamp split into whole ``seconds`` and ``nanoseconds`` (both integers)."""
    if not (seconds.isascii() and seconds.isdigit() and nanoseconds.isascii() and nanoseconds.isdigit()):
        raise InputError(
            f"{path}:{number}: bad timestamp {seconds!r}, {nanoseconds!r}, expected whole seconds and nanoseconds"
        )
    return format_stamp(int(seconds) * _NS_PER_S + int(nanoseconds))


def detect_format(path: str | os.PathLike[str]) -> TrajectoryFormat | None:
    """The format of a text trajectory file from its first 64 KiB, or None if it is none of them.

    * a ``#`` line naming EuRoC's columns (``p_RS_R_x``, ``q_RS_w``): EuRoC;
    * a first line ``iteration,timestamp,x,y,z,qx,qy,qz,qw``: relpoint's own ``trajectory.csv``;
    * a header line naming the columns (:func:`header_layout`), other than a ``#`` line naming TUM's in
      TUM's order over values read as TUM: named columns (:func:`read_named_columns`);
    * else by the first data line: 12 values KITTI; 8 values TUM, unless the file is named ``*.csv``,
      the values are comma-separated and the first is an integer (nanoseconds), which is EuRoC; more
      than 8 comma-separated values with an integer first one (EuRoC's velocity and bias columns): EuRoC.

    Raises
    ------
    InputError
        If the file cannot be opened, or its first line is a header that does not name the columns.
    """
    path = Path(path)
    head = _head(path)
    if head is None:
        return None
    comments, fields = _split_head(head)
    if any(mark in line for line in comments for mark in _EUROC_HEADER_MARKS):
        return TrajectoryFormat.EUROC
    if fields[: len(RELPOINT_CSV_HEADER)] == RELPOINT_CSV_HEADER:
        return TrajectoryFormat.RELPOINT_CSV
    by_values = _format_by_values(path, fields)
    layout = _layout_in(path, head)
    if layout is not None and not (layout.commented and layout.is_tum and by_values is TrajectoryFormat.TUM):
        return TrajectoryFormat.NAMED_COLUMNS
    return by_values


def _format_by_values(path: Path, fields: list[str]) -> TrajectoryFormat | None:
    """The format the first data line's ``fields`` (as :func:`_first_lines` gives them) and the file's
    suffix say, whatever a header says."""
    commas = fields[-1:] == [","]
    values = fields[:-1] if commas else fields
    integer_stamp_csv = commas and values[0].isascii() and values[0].isdigit()
    if len(values) == 12:
        return TrajectoryFormat.KITTI
    if len(values) == 8 and not (integer_stamp_csv and path.suffix.lower() == ".csv"):
        return TrajectoryFormat.TUM
    if len(values) >= 8 and integer_stamp_csv:
        return TrajectoryFormat.EUROC
    return None


def describe_unknown(path: str | os.PathLike[str]) -> str:
    """Why :func:`detect_format` found no format in ``path``, for an error message."""
    head = _first_lines(Path(path))
    if head is None:
        return "not a text file with poses"
    fields = head[1]
    return f"{len(fields) - (fields[-1:] == [','])} values per line"


def _atomic_write(path: Path, lines: Iterable[str], *, mark: bool = False) -> None:
    """Write ``lines`` to ``path`` atomically (temporary file beside it, then rename)."""
    write_text(path, "".join(lines), mark=mark)


def write_tum(path: str | os.PathLike[str], trajectory: Trajectory, header: str | None = None) -> None:
    """Write ``trajectory`` as a TUM file (exact stamps, round-tripping floats), atomically.

    ``header`` lines are written as ``#`` comments before the column legend.
    """
    path = Path(path)
    header = header or f"relpoint {relpoint.__version__}"  # the mark that lets a later run replace the file
    out = [f"# {line}\n" for line in header.splitlines()]
    out.append("# timestamp tx ty tz qx qy qz qw\n")
    for stamp, p, q in zip(
        trajectory.stamps_ns.tolist(), trajectory.positions.tolist(), trajectory.quats_xyzw.tolist(), strict=True
    ):
        out.append(" ".join([format_stamp(stamp), *map(repr, p), *map(repr, q)]) + "\n")
    _atomic_write(path, out)


def write_kitti(
    path: str | os.PathLike[str], trajectory: Trajectory, times_path: str | os.PathLike[str] | None = None
) -> None:
    """Write ``trajectory`` as KITTI poses (3x4 row-major per line) and, if given, its times file, atomically."""
    path = Path(path)
    T = trajectory.matrices()
    # Neither file has room for a header: both are marked as relpoint's outside their content.
    rows = T[:, :3, :].reshape(-1, 12).tolist()
    _atomic_write(path, (" ".join(map(repr, row)) + "\n" for row in rows), mark=True)
    if times_path is not None:
        _atomic_write(Path(times_path), (format_stamp(s) + "\n" for s in trajectory.stamps_ns.tolist()), mark=True)


#: EuRoC's ground-truth header, the columns :func:`write_euroc_csv` writes.
EUROC_HEADER = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"


def write_euroc_csv(path: str | os.PathLike[str], trajectory: Trajectory) -> None:
    """Write ``trajectory`` as EuRoC ground truth (integer ns, position, quaternion w first), atomically."""
    out = [EUROC_HEADER + "\n"]
    for stamp, p, q in zip(
        trajectory.stamps_ns.tolist(), trajectory.positions.tolist(), trajectory.quats_xyzw.tolist(), strict=True
    ):
        out.append(",".join([str(stamp), *map(repr, p), *map(repr, [q[3], q[0], q[1], q[2]])]) + "\n")
    _atomic_write(Path(path), out)
