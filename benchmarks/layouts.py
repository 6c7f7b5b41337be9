"""Bag layouts against the single MCAP file: ``relpoint info`` and ``relpoint run`` on the same messages.

Simulates one figure-eight log (points, odometry, fixes, ground truth), copies its messages into every
layout with rosbags' writers (:func:`formats.layouts.write_layout`): rosbag2 with mcap and sqlite3
storage, split over several files, zstd per file and per message, and ROS 1 bags plain and with bz2 or
lz4 chunks. Then times, in this process (imports and JIT compilation warmed up first, best of N):

- ``info``: the whole command (one pass over every record, the observation statistics, the storage);
- ``read``: ``LogReader.records`` over every role, decoded into core types;
- ``run``: ``relpoint run`` with the chosen estimator, outputs written;

(the repeats go round the layouts in turn, so passing load on the machine spreads over all of them)

and prints a table with each layout's time over the single file's. With ``--room N`` it adds a second
table for an RGB-D room log of N depth+colour frames (info and read only), where payloads are large.

Usage: python benchmarks/layouts.py [--iterations 2000] [--density 100] [--estimator relpoint]
       [--repeats 3] [--room 0]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from click.testing import CliRunner

from formats.layout_writers import LayoutSpec, raw_messages, write_layout
from formats.layouts import Layout
from formats.log import LogReader
from relpoint_cli.main import cli

SPECS = {
    "single mcap (relpoint)": None,
    "rosbag2 mcap": LayoutSpec(Layout.ROSBAG2, "mcap"),
    "rosbag2 mcap, split x4": LayoutSpec(Layout.ROSBAG2, "mcap", files=4),
    "rosbag2 mcap, zstd file": LayoutSpec(Layout.ROSBAG2, "mcap", "file"),
    "rosbag2 mcap, zstd message": LayoutSpec(Layout.ROSBAG2, "mcap", "message"),
    "rosbag2 sqlite3": LayoutSpec(Layout.ROSBAG2, "sqlite3"),
    "rosbag2 sqlite3, split x4": LayoutSpec(Layout.ROSBAG2, "sqlite3", files=4),
    "rosbag2 sqlite3, zstd message": LayoutSpec(Layout.ROSBAG2, "sqlite3", "message"),
    "ros1 bag": LayoutSpec(Layout.ROS1),
    "ros1 bag, bz2 chunks": LayoutSpec(Layout.ROS1, compression="bz2"),
    "ros1 bag, lz4 chunks": LayoutSpec(Layout.ROS1, compression="lz4"),
}


def invoke(*args: str) -> None:
    result = CliRunner().invoke(cli, ["-q", *args])
    if result.exit_code != 0:
        raise SystemExit(f"relpoint {' '.join(args)} failed: {result.stderr or result.output}")


def best_of(repeats: int, action: Callable[[], object]) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        action()
        times.append(time.perf_counter() - start)
    return min(times)


def read_all(path: Path) -> int:
    reader = LogReader(path)
    return sum(1 for _ in reader.records(sorted(reader.available_roles())))


def size_of(path: Path) -> int:
    return sum(f.stat().st_size for f in path.iterdir()) if path.is_dir() else path.stat().st_size


def layouts(source: Path, root: Path) -> dict[str, Path]:
    messages = list(raw_messages(source))
    paths = {}
    for index, (name, spec) in enumerate(SPECS.items()):
        if spec is None:
            paths[name] = source
            continue
        suffix = ".bag" if spec.layout is Layout.ROS1 else ""
        paths[name] = write_layout(messages, root / f"layout{index}{suffix}", spec)
    return paths


def table(title: str, paths: dict[str, Path], columns: dict[str, Callable[[Path], object]], repeats: int) -> None:
    """Best of ``repeats`` per layout and column; the repeats go round the layouts in turn, so a spell of
    load on the machine falls on every layout alike rather than on a few."""
    best: dict[tuple[str, str], float] = {}
    for _ in range(repeats):
        for name, path in paths.items():
            for column, action in columns.items():
                seconds = best_of(1, lambda action=action, path=path: action(path))
                best[name, column] = min(seconds, best.get((name, column), float("inf")))
    first = next(iter(paths))
    print(f"\n{title}")
    print(f"{'layout':<31} {'MB':>6}" + "".join(f" {column + ' s':>9} {'ratio':>6}" for column in columns))
    for name, path in paths.items():
        row = f"{name:<31} {size_of(path) / 1e6:>6.2f}"
        for column in columns:
            row += f" {best[name, column]:>9.3f} {best[name, column] / best[first, column]:>6.2f}"
        print(row, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=2000)
    parser.add_argument("--density", type=float, default=100.0)
    parser.add_argument("--estimator", default="relpoint")
    parser.add_argument("--repeats", type=int, default=3, help="best of N for each figure")
    parser.add_argument("--room", type=int, default=0, help="also an RGB-D room log of N frames (info and read)")
    args = parser.parse_args()

    from relpoint.simulation import SimulationConfig, simulate
    from relpoint_app.simulation import write_simulation

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        source = root / "points.mcap"
        config = SimulationConfig(
            iterations=args.iterations, passes=max(1, args.iterations // 990 + 1), density=args.density,
            odometry_noise=0.05, fix_every=10, seed=1,
        )  # fmt: skip
        write_simulation(simulate(config), source)
        paths = layouts(source, root)
        out = root / "out"

        def run(path: Path) -> None:
            invoke("run", str(path), "-e", args.estimator, "-o", str(out), "--overwrite")

        run(source)  # JIT compilation and imports stay out of the timings
        print(f"points log: {args.iterations} iterations, density {args.density:g}, {read_all(source)} messages")
        table(
            f"points log, estimator {args.estimator} (best of {args.repeats}; ratio = time / single mcap time)",
            paths,
            {"info": lambda p: invoke("info", str(p)), "read": read_all, "run": run},
            args.repeats,
        )
        if args.room:
            shutil.rmtree(out, ignore_errors=True)
            room = root / "room" / "room.mcap"
            invoke("simulate", "-o", str(room), "--scenario", "room", "--iterations", str(args.room), "--seed", "2")
            depth = next(r.value for r in LogReader(room).records(["depth"]))
            table(
                f"RGB-D room log, {args.room} frames of {depth.shape[1]}x{depth.shape[0]} depth + colour "
                f"(best of {args.repeats})",
                layouts(room, room.parent),
                {"info": lambda p: invoke("info", str(p)), "read": read_all},
                args.repeats,
            )


if __name__ == "__main__":
    main()
