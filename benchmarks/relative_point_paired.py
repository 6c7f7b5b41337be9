"""Paired timing of two versions of the Relative Point estimator, in one process.

This machine's speed drifts by up to 1.5x within minutes, so times from separate runs compare poorly.
Here both versions are imported from their source trees into one process and stepped alternately on
the same observations (figure eight at ~100 observed points); the order alternates between
repetitions. The ratio of their median times per iteration is what to quote; the absolute times are
inflated by the interleaving (each version evicts the other's data from the caches).

Usage: python benchmarks/relative_point_paired.py OLD_TREE NEW_TREE [--repeat 4] [--density 130]

A tree is a directory holding a ``relpoint`` package, e.g. an export of an older commit:
``mkdir /tmp/old && git archive <commit> relpoint | tar -x -C /tmp/old``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `relpoint run` does

import numpy as np


def load_estimator(tree: Path) -> tuple[Any, Any, Any]:
    """(estimator class, its config class, the tree's simulate + SimulationConfig) imported from ``tree``."""
    for name in [m for m in sys.modules if m == "relpoint" or m.startswith("relpoint.")]:
        del sys.modules[name]
    sys.path.insert(0, str(tree))
    try:
        import relpoint
        from relpoint.estimators.relative_point import RelativePointConfig, RelativePointEstimator
        from relpoint.simulation import SimulationConfig, simulate

        if not Path(relpoint.__file__).resolve().is_relative_to(tree.resolve()):
            raise SystemExit(f"relpoint_paired: {tree} holds no relpoint package (imported {relpoint.__file__})")
    finally:
        sys.path.remove(str(tree))
    return RelativePointEstimator, RelativePointConfig, (simulate, SimulationConfig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--repeat", type=int, default=4)
    parser.add_argument("--density", type=float, default=130.0, help="130: about 100 observed points")
    args = parser.parse_args()
    versions = [load_estimator(args.old), load_estimator(args.new)]
    simulate, SimulationConfig = versions[1][2]
    observations = [
        s.observation for s in simulate(SimulationConfig(scenario="figure8", density=args.density, seed=0)).steps()
    ]
    for Estimator, Config, _ in versions:  # compile or load compiled code before timing
        warm = Estimator(Config())
        for observation in observations[:100]:
            warm.step(observation)
    ratios = []
    print(f"{len(observations)} iterations, {np.mean([len(o) for o in observations]):.1f} observed points")
    for rep in range(args.repeat):
        estimators = [Estimator(Config()) for Estimator, Config, _ in versions]
        times = np.zeros((2, len(observations)))
        order = (0, 1) if rep % 2 == 0 else (1, 0)
        for i, observation in enumerate(observations):
            for j in order:
                start = time.perf_counter()
                estimators[j].step(observation)
                times[j, i] = time.perf_counter() - start
        median = 1e3 * np.median(times, axis=1)
        ratios.append(median[1] / median[0])
        print(f"repetition {rep}: median ms old {median[0]:.3f}, new {median[1]:.3f}; new/old {ratios[-1]:.3f}")
    print(f"new/old, median over repetitions: {np.median(ratios):.3f}")


if __name__ == "__main__":
    main()
