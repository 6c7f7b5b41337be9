"""Long runs: peak memory against the number of figure-eight passes (the paper's 40-pass test).

Each row runs in a fresh process so its peak RSS (``ru_maxrss``) is its own: simulate N passes
(density 25, noise 0.3) in memory, run the estimator over them, print iterations, map size, wall
time and peak RSS. Memory should follow the map, which stops growing after the first pass, not the
number of iterations.

Usage: python benchmarks/long_run.py [--estimator relpoint] [--passes 1 2 5 10 20 40]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys


def child(estimator_name: str, passes: int) -> None:
    import resource
    import time

    import numpy as np

    from relpoint import pipeline
    from relpoint.estimators import ESTIMATORS
    from relpoint.simulation import SimulationConfig, simulate

    baseline = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    simulation = simulate(SimulationConfig(passes=passes, density=25, noise=0.3, seed=1))
    spec = ESTIMATORS[estimator_name]
    estimator = spec.factory(spec.config_class(), np.random.default_rng(0))
    start = time.perf_counter()
    result = pipeline.run((step.observation for step in simulation.steps()), estimator)
    seconds = time.perf_counter() - start
    truth = simulation.ground_truth.positions
    error = np.linalg.norm(result.trajectory.positions - truth, axis=1)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({
        "passes": passes, "iterations": len(result.trajectory), "landmarks": len(result.landmarks),
        "seconds": seconds, "peak_rss_mb": peak / 1024, "import_rss_mb": baseline / 1024,
        "position_rmse_last_pass": float(np.sqrt(np.mean(error[-len(error) // passes:] ** 2))),
    }))  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--estimator", default="relpoint")
    parser.add_argument("--passes", type=int, nargs="+", default=[1, 2, 5, 10, 20, 40])
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        child(args.estimator, args.child)
        return
    print(f"{args.estimator}: peak RSS against figure-eight passes (density 25, noise 0.3)")
    print(
        f"{'passes':>6} {'iterations':>10} {'landmarks':>9} {'seconds':>8} {'peak RSS MB':>11} {'RMSE last pass m':>16}"
    )
    for passes in args.passes:
        output = subprocess.run(
            [sys.executable, __file__, "--estimator", args.estimator, "--child", str(passes)],
            capture_output=True, text=True, check=True,
        ).stdout  # fmt: skip
        row = json.loads(output.strip().splitlines()[-1])
        print(f"{row['passes']:>6} {row['iterations']:>10} {row['landmarks']:>9} {row['seconds']:>8.1f} "
              f"{row['peak_rss_mb']:>11.1f} {row['position_rmse_last_pass']:>16.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
