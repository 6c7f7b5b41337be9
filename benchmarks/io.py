"""Log I/O and simulation speed: the figures behind the choice of MCAP/CDR library.

Prints, on a simulated 10,000-iteration figure-eight log (density 100, odometry, fixes):
- read throughput (messages/s, MB/s) of ways to read it into numpy point arrays: the ``mcap``
  package's reader with ``mcap-ros2-support``'s decoder, rosbags' ``AnyReader`` with its CDR codec
  (the library relpoint reads with), and relpoint's ``LogReader`` on top of it, which also checks
  the whole file first and converts every message to validated core types;
- write throughput of ``relpoint simulate``'s writer;
- simulation + write time for 900 iterations at density 25 and at density 550.

Usage: python benchmarks/io.py [--iterations 10000] [--density 100]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def read_relpoint(path: Path) -> int:
    from formats.log import LogReader

    reader = LogReader(path)
    count = 0
    for record in reader.records(["points", "ground_truth_pose", "odometry", "fix"]):
        count += 1
        if record.role == "points":
            assert record.value.points.dtype == np.float64
    return count


def read_mcap_ros2(path: Path) -> int:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    topics = ["/points", "/ground_truth/pose", "/odom", "/fix"]
    count = 0
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, channel, _, message in reader.iter_decoded_messages(topics=topics):
            count += 1
            if channel.topic == "/points":
                raw = np.frombuffer(bytes(message.data), dtype=np.uint8)
                np.frombuffer(raw, dtype=np.dtype({"names": ["x", "y", "z"], "formats": ["<f4"] * 3,
                                                   "offsets": [0, 4, 8], "itemsize": message.point_step}))  # fmt: skip
    return count


def read_rosbags_anyreader(path: Path) -> int:
    from rosbags.highlevel import AnyReader

    count = 0
    with AnyReader([path]) as reader:
        connections = [c for c in reader.connections if c.topic in ("/points", "/ground_truth/pose", "/odom", "/fix")]
        for connection, _, raw in reader.messages(connections=connections):
            message = reader.deserialize(raw, connection.msgtype)
            count += 1
            if connection.topic == "/points":
                np.frombuffer(message.data, dtype=np.dtype({"names": ["x", "y", "z"], "formats": ["<f4"] * 3,
                                                            "offsets": [0, 4, 8], "itemsize": message.point_step}))  # fmt: skip
    return count


def timed(function, *args):  # type: ignore[no-untyped-def]
    start = time.perf_counter()
    value = function(*args)
    return value, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=10_000)
    parser.add_argument("--density", type=float, default=100.0)
    parser.add_argument("--repeats", type=int, default=2, help="best of N for each reader")
    args = parser.parse_args()

    from relpoint.simulation import SimulationConfig, simulate
    from relpoint_app.simulation import write_simulation

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.mcap"
        config = SimulationConfig(
            iterations=args.iterations, passes=max(1, args.iterations // 990 + 1), density=args.density,
            odometry_noise=0.05, fix_every=10, seed=1,
        )  # fmt: skip
        counts, seconds = timed(write_simulation, simulate(config), path)
        size_mb = path.stat().st_size / 1e6
        messages = sum(counts.values())
        print(f"log: {args.iterations} iterations, density {args.density:g}, {messages} messages, {size_mb:.1f} MB")
        print(f"simulate+write: {seconds:.2f} s ({messages / seconds:,.0f} messages/s)")
        warm = Path(tmp) / "warm.mcap"
        write_simulation(simulate(SimulationConfig(iterations=50, odometry_noise=0.05, fix_every=10)), warm)
        print(f"{'reader':<34} {'seconds':>8} {'messages/s':>12} {'MB/s':>8} {'vs relpoint':>11}")
        results = {}
        for name, reader in (
            ("relpoint LogReader -> core types", read_relpoint),
            ("mcap-ros2-support decoder", read_mcap_ros2),
            ("rosbags AnyReader", read_rosbags_anyreader),
        ):
            reader(warm)  # imports and codec generation stay out of the timing
            best = min(timed(reader, path)[1] for _ in range(args.repeats))
            n = reader(path) if name not in results else 0
            results[name] = best
            base = results["relpoint LogReader -> core types"]
            print(f"{name:<34} {best:>8.2f} {n / best:>12,.0f} {size_mb / best:>8.1f} {best / base:>10.2f}x")

        for density in (25, 550):
            config = SimulationConfig(iterations=900, density=density, seed=1)
            out = Path(tmp) / f"d{density}.mcap"
            _, seconds = timed(write_simulation, simulate(config), out)
            print(f"simulate 900 iterations at density {density}: {seconds:.2f} s, {out.stat().st_size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
