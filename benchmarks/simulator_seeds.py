"""One estimator over the simulator's figure eight for several seeds: raw position and landmark RMSE.

The estimator is built as ``relpoint run`` builds it (``SPEC.factory``, so the noise is estimated
unless given); errors are raw, in the first true pose's frame, the landmarks flagged dynamic and the
moving ones left out. Shows how a change moves the figures seed by seed, where one seed can swing.

Usage::

    python benchmarks/simulator_seeds.py [--estimator relpoint] [--dynamic 0.3] [--seeds 1 2 3]
        [--iterations N] [--param KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    from relpoint.estimators import ESTIMATORS
    from relpoint.pipeline import run
    from relpoint.simulation import SimulationConfig, simulate

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--estimator", default="relpoint", choices=sorted(ESTIMATORS))
    parser.add_argument("--dynamic", type=float, default=0.0, help="share of moving landmarks")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--iterations", type=int, default=None, help="default: the whole path (996 on the figure eight)")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args(argv)
    spec = ESTIMATORS[args.estimator]
    positions, maps = [], []
    for seed in args.seeds:
        sim = simulate(SimulationConfig(density=25, noise=0.3, seed=seed, dynamic=args.dynamic, iterations=args.iterations))
        estimator = spec.factory(spec.build_config({}, args.param), np.random.default_rng(seed))
        result = run([step.observation for step in sim.steps()], estimator)
        T0 = sim.ground_truth.matrices()[0]
        estimated = result.trajectory.positions @ T0[:3, :3].T + T0[:3, 3]
        position = float(np.sqrt(np.mean(np.sum((estimated - sim.ground_truth.positions) ** 2, axis=1))))
        landmarks = result.landmarks
        known = landmarks.gt_id >= 0
        static = known & ~landmarks.dynamic & ~sim.landmarks.dynamic[np.where(known, landmarks.gt_id, 0)]
        mapped = landmarks.positions[static] @ T0[:3, :3].T + T0[:3, 3]
        error = mapped - sim.landmarks.positions[landmarks.gt_id[static]]
        landmark = float(np.sqrt(np.mean(np.sum(error**2, axis=1))))
        positions.append(position)
        maps.append(landmark)
        print(f"seed {seed}: position RMSE {position:.3f} m, landmark RMSE {landmark:.3f} m", flush=True)
    print(f"mean: position {np.mean(positions):.3f} m, landmarks {np.mean(maps):.3f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
