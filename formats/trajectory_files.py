"""TUM and KITTI trajectory files to and from :class:`relpoint.types.Trajectory`.

* TUM (Sturm et al. 2012): one pose per line, ``timestamp tx ty tz qx qy qz qw``, seconds, metres,
  quaternion (x, y, z, w) of ``T_world_frame``; lines starting with ``#`` and blank lines are ignored;
  any run of spaces or tabs separates values (commas too, as some tools write them).
* KITTI odometry poses: one pose per line, the first three rows of ``T_world_frame`` row-major
  (12 values). Stamps come from a separate times file (one value in seconds per line, KITTI's
  ``times.txt``); without one, pose ``i`` gets stamp ``i`` seconds.

Stamps are parsed from their decimal text into exact integer nanoseconds and written back exactly, and
floats are written with ``repr`` (shortest round-tripping form), so a read-write-read cycle is lossless.
Writes are atomic: a temporary file in the target's directory is renamed over it.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable, Iterator
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

import relpoint
from formats.atomic import write_text
from relpoint.errors import InputError
from relpoint.geometry import matrix_to_position_quat
from relpoint.types import Trajectory

logger = logging.getLogger(__name__)

_SEPARATORS = re.compile(r"[\s,]+")
_NS_PER_S = 1_000_000_000


def _data_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of the non-comment, non-blank lines of ``path``."""
    for number, stripped in _text_lines(path):
        if not stripped or stripped.startswith("#"):
            continue
        yield number, [f for f in _SEPARATORS.split(stripped) if f]


def _text_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, stripped text) of every line of ``path``; InputError if it cannot be read as text."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, expected a trajectory file") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    return [(number, line.strip()) for number, line in enumerate(text.splitlines(), start=1)]


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


def _floats(fields: list[str], path: Path, number: int) -> list[float]:
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise InputError(f"{path}:{number}: non-numeric value in {' '.join(fields)!r}") from None
    if not all(np.isfinite(values)):
        raise InputError(f"{path}:{number}: non-finite value in {' '.join(fields)!r}")
    return values


def _build(
    path: Path, stamps: list[int], positions: list[list[float]], quats: np.ndarray, lines: list[int]
) -> Trajectory:
    if not stamps:
        raise InputError(f"{path}: no poses in file")
    stamps_arr = np.array(stamps, dtype=np.int64)
    bad = np.nonzero(np.diff(stamps_arr) <= 0)[0]
    if bad.size:
        k = int(bad[0]) + 1
        raise InputError(f"{path}:{lines[k]}: timestamp does not increase (previous pose at line {lines[k - 1]})")
    norms = np.linalg.norm(quats, axis=1)
    if np.any(norms < 1e-9):
        raise InputError(f"{path}:{lines[int(np.argmax(norms < 1e-9))]}: zero quaternion")
    return Trajectory(stamps_arr, np.array(positions, dtype=np.float64).reshape(-1, 3), quats)


def _read_tum_fast(path: Path) -> Trajectory | None:
    """Whole-file parse of a well-formed TUM file; ``None`` sends the caller to the line-by-line reader.

    The line-by-line reader names the file and line of any problem; this path only handles files
    with exactly 8 finite values on every data line and plain decimal stamps, which is nearly all.
    """
    lines = [(number, line) for number, line in _text_lines(path) if line and not line.startswith("#")]
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


def read_tum(path: str | os.PathLike[str]) -> Trajectory:
    """Read a TUM trajectory file (see the module docstring).

    Raises
    ------
    InputError
        Missing or unreadable file, no poses, a row without 8 values or with a non-numeric or non-finite
        value, a zero quaternion, or stamps that do not increase - naming the file and line.
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
    try:
        values = np.array(rows, dtype=np.float64).reshape(-1, 7)
        finite = bool(np.isfinite(values).all())
    except ValueError:
        finite = False
    if not finite:  # find the offending line for the message
        for number, fields in zip(lines, rows, strict=True):
            _floats(fields, path, number)
    logger.debug("read %d poses from %s", len(stamps), path)
    return _build(path, stamps, values[:, :3].tolist(), values[:, 3:], lines)


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


def _atomic_write(path: Path, lines: Iterable[str]) -> None:
    """Write ``lines`` to ``path`` atomically (temporary file beside it, then rename)."""
    write_text(path, "".join(lines))


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
    _atomic_write(path, (" ".join(map(repr, row)) + "\n" for row in T[:, :3, :].reshape(-1, 12).tolist()))
    if times_path is not None:
        _atomic_write(Path(times_path), (format_stamp(s) + "\n" for s in trajectory.stamps_ns.tolist()))
