"""Dense map evaluation time: a 300,000-point map against a 1,000,000-point reference cloud.

Prints the time of ``dense_metrics`` (bounded search, the default) for a map in the reference's frame
and for one 129 degrees and a metre off (a run evaluated without alignment, the worst case for an
unbounded search), beside the unbounded search in the same process on the aligned map.

    python benchmarks/dense_evaluation.py [--points 300000] [--reference 1000000]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from relpoint.evaluation.dense import dense_metrics


def room_surface(rng: np.random.Generator, n: int, size: tuple[float, float, float] = (5.0, 4.0, 3.0)) -> np.ndarray:
    """``n`` points on the walls, floor and ceiling of a box room (m), with 5 mm of scan noise."""
    extent = np.asarray(size)
    points = rng.uniform(0.0, 1.0, (n, 3)) * extent
    axis = rng.integers(0, 3, n)
    points[np.arange(n), axis] = extent[axis] * rng.integers(0, 2, n)
    return points + rng.normal(scale=0.005, size=points.shape)


def timed(label: str, points: np.ndarray, reference: np.ndarray, **options: object) -> float:
    start, cpu = time.perf_counter(), time.process_time()
    metrics = dense_metrics(points, reference, threshold=0.05, workers=-1, **options)  # type: ignore[arg-type]
    wall, cpu_s = time.perf_counter() - start, time.process_time() - cpu
    print(f"| {label} | {wall:.2f} | {cpu_s:.2f} | {metrics.accuracy_within:.3f} | {metrics.completeness_within:.3f} |")
    return wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=300_000)
    parser.add_argument("--reference", type=int, default=1_000_000)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    reference = room_surface(rng, args.reference)
    points = room_surface(rng, args.points)
    rotation = Rotation.from_euler("z", 129, degrees=True).as_matrix()
    misplaced = points @ rotation.T + np.array([1.0, 0.5, 0.2])
    print(f"{args.points} map points against {args.reference} reference points; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")  # fmt: skip
    print("| case | wall s | CPU s | accuracy within 5 cm | completeness within 5 cm |")
    print("|---|---|---|---|---|")
    bounded = timed("aligned, bounded search (default)", points, reference)
    timed("misplaced, bounded search (default)", misplaced, reference)
    unbounded = timed("aligned, unbounded search", points, reference, max_distance=np.inf)
    print(f"bounded / unbounded wall time, aligned: {bounded / unbounded:.2f}")


if __name__ == "__main__":
    main()
