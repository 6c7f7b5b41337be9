"""Does an estimator close the figure eight's loop? Seed by seed, over the simulator's figure eight.

The figure eight crosses its start about half-way (iteration ~470 of 900). An estimator that closes
the loop there re-associates the landmarks it mapped on the way out; one that does not maps them a
second time. Per seed it prints the duplicate map entries (entries beyond the first for each true
landmark, in percent of the true landmarks mapped), the raw ATE and whether the loop is closed:
duplicates at most ``--max-duplicates`` percent (issue 17: FastSLAM on at least 9 of 10 seeds).

Usage::

    python benchmarks/loop_closure.py [--estimator fastslam] [--seeds 0 1 ... 9] [--iterations 900]
        [--max-duplicates 5] [--param KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    from relpoint.estimators import ESTIMATORS
    from relpoint.pipeline import run
    from relpoint.simulation import SimulationConfig, simulate

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--estimator", default="fastslam", choices=sorted(ESTIMATORS))
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    parser.add_argument("--iterations", type=int, default=900)
    parser.add_argument("--max-duplicates", type=float, default=5.0, help="percent of the true landmarks mapped")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args(argv)
    spec = ESTIMATORS[args.estimator]
    closed = 0
    for seed in args.seeds:
        sim = simulate(SimulationConfig(density=25, noise=0.3, seed=seed, iterations=args.iterations))
        estimator = spec.factory(spec.build_config({}, args.param), np.random.default_rng(seed))
        started = time.process_time()
        result = run([step.observation for step in sim.steps()], estimator)
        cpu = time.process_time() - started
        gt = result.landmarks.gt_id
        known = gt[gt >= 0]
        true_mapped = np.unique(known).size
        duplicates = 100.0 * (known.size - true_mapped) / max(true_mapped, 1)
        T0 = sim.ground_truth.matrices()[0]
        estimated = result.trajectory.positions @ T0[:3, :3].T + T0[:3, 3]
        ate = float(np.sqrt(np.mean(np.sum((estimated - sim.ground_truth.positions) ** 2, axis=1))))
        ok = duplicates <= args.max_duplicates
        closed += ok
        print(f"seed {seed}: duplicates {duplicates:5.1f} % of {true_mapped} landmarks, ATE {ate:.3f} m, "
              f"{'closed' if ok else 'NOT closed'} ({cpu:.0f} s CPU)", flush=True)  # fmt: skip
    print(f"{args.estimator}: loop closed on {closed} of {len(args.seeds)} seeds")
    return 0


if __name__ == "__main__":
    sys.exit(main())
