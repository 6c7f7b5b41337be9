"""The CSV files of a run's output directory (``trajectory.csv``, ``map.csv``, ``timing.csv``).

All are plain comma-separated text with one header line, written atomically. Floats are written
with 9 significant digits past the point for coordinates, so they round-trip at sub-micrometre level.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import numpy as np

from formats.atomic import write_text
from formats.outputs import register_csv_header, unreadable_input
from relpoint.errors import InputError
from relpoint.types import LandmarkMap, Trajectory

TRAJECTORY_HEADER = ["iteration", "timestamp", "x", "y", "z", "qx", "qy", "qz", "qw"]
MAP_HEADER = ["landmark", "x", "y", "z", "observations", "dynamic", "gt_id"]
#: An optional column of a ``map.csv`` that relpoint reads but does not write (``map.ply`` carries it):
#: the iteration each landmark was first observed or started.
FIRST_ITERATION = "first_iteration"
TIMING_HEADER = ["iteration", "observed", "map_size", "seconds"]


def _rows_to_text(header: list[str], rows: list[list[str]]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


def write_trajectory_csv(path: str | os.PathLike[str], trajectory: Trajectory) -> None:
    """``iteration,timestamp,x,y,z,qx,qy,qz,qw``; timestamp in seconds."""
    rows = [
        [str(i), f"{stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d}",
         *(f"{v:.9f}" for v in position), *(f"{v:.9f}" for v in quat)]
        for i, (stamp, position, quat) in enumerate(
            zip(trajectory.stamps_ns.tolist(), trajectory.positions, trajectory.quats_xyzw, strict=True)
        )
    ]  # fmt: skip
    write_text(path, _rows_to_text(TRAJECTORY_HEADER, rows))


def write_map_csv(path: str | os.PathLike[str], landmarks: LandmarkMap) -> None:
    """``landmark,x,y,z,observations,dynamic,gt_id``; dynamic is 0 or 1 (the log-format contract's
    columns; a landmark's first iteration goes to ``map.ply``)."""
    rows = [
        [str(i), f"{p[0]:.9f}", f"{p[1]:.9f}", f"{p[2]:.9f}", str(int(n)), str(int(d)), str(int(g))]
        for i, (p, n, d, g) in enumerate(
            zip(landmarks.positions, landmarks.observations, landmarks.dynamic, landmarks.gt_id, strict=True)
        )
    ]
    write_text(path, _rows_to_text(MAP_HEADER, rows))


def read_map_csv(path: str | os.PathLike[str]) -> LandmarkMap:
    """Read a ``map.csv`` back into a :class:`LandmarkMap` (``first_iteration`` when the file has it)."""
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8") as stream:
            reader = csv.DictReader(stream)
            missing = [c for c in MAP_HEADER[1:] if c not in (reader.fieldnames or [])]
            if missing:
                raise InputError(f"{path}: not a relpoint map.csv (missing column(s) {', '.join(missing)})")
            has_first = FIRST_ITERATION in (reader.fieldnames or [])
            rows = list(reader)
    except OSError as error:
        raise unreadable_input(path, error) from None
    try:
        positions = np.array([[float(r["x"]), float(r["y"]), float(r["z"])] for r in rows]).reshape(-1, 3)
        return LandmarkMap(
            positions,
            np.array([int(r["observations"]) for r in rows], dtype=np.int64),
            np.array([int(r["dynamic"]) != 0 for r in rows], dtype=bool),
            np.array([int(r["gt_id"]) for r in rows], dtype=np.int64),
            first_iteration=np.array([int(r[FIRST_ITERATION]) for r in rows], dtype=np.int64) if has_first else None,
        )
    except (ValueError, TypeError):
        for number, row in enumerate(rows, start=2):  # the header is line 1
            try:
                for column in ("x", "y", "z"):
                    float(row[column])
                for column in ("observations", "dynamic", "gt_id"):
                    int(row[column])
            except (ValueError, TypeError) as error:
                raise InputError(f"{path}:{number}: malformed row ({error})") from None
        raise InputError(f"{path}: malformed rows") from None


def write_timing_csv(
    path: str | os.PathLike[str], observed: np.ndarray, map_size: np.ndarray, seconds: np.ndarray
) -> None:
    """``iteration,observed,map_size,seconds`` per iteration."""
    rows = [
        [str(i), str(int(o)), str(int(m)), f"{s:.9f}"]
        for i, (o, m, s) in enumerate(zip(observed, map_size, seconds, strict=True))
    ]
    write_text(path, _rows_to_text(TIMING_HEADER, rows))


MAP_HISTORY_HEADER = ["iteration", "timestamp", "landmark", "x", "y", "z", "dynamic", "gt_id"]
for _header in (TRAJECTORY_HEADER, MAP_HEADER, TIMING_HEADER, MAP_HISTORY_HEADER):
    register_csv_header(_header)


def write_map_history_csv(path: str | os.PathLike[str], history: tuple[tuple[int, int, LandmarkMap], ...]) -> None:
    """``iteration,timestamp,landmark,x,y,z,dynamic,gt_id``: the map at each snapshot iteration."""
    rows = [
        [str(iteration), f"{stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d}", str(i),
         f"{p[0]:.9f}", f"{p[1]:.9f}", f"{p[2]:.9f}", str(int(d)), str(int(g))]
        for iteration, stamp, landmarks in history
        for i, (p, d, g) in enumerate(zip(landmarks.positions, landmarks.dynamic, landmarks.gt_id, strict=True))
    ]  # fmt: skip
    write_text(path, _rows_to_text(MAP_HISTORY_HEADER, rows))


def read_map_history_csv(path: str | os.PathLike[str]) -> list[tuple[int, int, LandmarkMap]]:
    """Read ``map_history.csv`` back as ``(iteration, stamp_ns, map)`` snapshots (observations unknown: 0)."""
    path = Path(path)
    try:
        table = np.genfromtxt(path, delimiter=",", skip_header=1, dtype=np.float64, ndmin=2)
        stamps_text = [line.split(",")[1] for line in path.read_text(encoding="utf-8").splitlines()[1:] if line]
    except (OSError, ValueError) as error:
        raise InputError(f"{path}: not a readable map_history.csv ({error})") from None
    if table.size == 0:
        return []
    if table.shape[1] != len(MAP_HISTORY_HEADER):
        raise InputError(f"{path}: expected {len(MAP_HISTORY_HEADER)} columns, got {table.shape[1]}")
    snapshots = []
    iterations = table[:, 0].astype(np.int64)
    for iteration in np.unique(iterations):
        rows = np.flatnonzero(iterations == iteration)
        whole, _, fraction = stamps_text[rows[0]].partition(".")
        stamp_ns = int(whole) * 1_000_000_000 + int(fraction.ljust(9, "0")[:9] or 0)
        block = table[rows]
        snapshots.append(
            (
                int(iteration),
                stamp_ns,
                LandmarkMap(
                    block[:, 3:6], np.zeros(len(rows), np.int64), block[:, 6] != 0, block[:, 7].astype(np.int64)
                ),
            )
        )
    return snapshots
