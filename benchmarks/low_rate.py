"""The point estimators on a sensor that moves far between observations: ATE divided by the scene's scale.

A sensor circles through 500 scattered landmarks about 9 m apart (times the scale), one observation a
second, turning ``step`` degrees about the circle's centre between two (``relpoint.simulation.circle``:
15 degrees is 7.9 m on the circle of 30 m, about the landmarks' spacing). Every step, at two scales and
two noise levels (a thirtieth and a tenth of the spacing), over seeds (the scene's draws and the
estimator's). The worst seed is printed beside the median; nothing is gated.

    python benchmarks/low_rate.py
    python benchmarks/low_rate.py --estimators fastslam --steps 15 --seeds 0 1 2 3 4 5
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.simulation.circle import fast_circle, first_frame

#: Scales of the scene: a vehicle's (1: the circle 30 m across) and a room's (0.02: 0.6 m).
SCALES = (1.0, 0.02)
#: Noise per axis at scale 1 (m): a thirtieth and a tenth of the landmarks' spacing.
NOISES = (0.3, 0.9)


def scaled_ate(name: str, step: float, scale: float, noise: float, seed: int, frames: int) -> float:
    """ATE (m, in the first pose's frame) of ``name`` with its defaults, divided by the scale."""
    observations, truth = fast_circle(noise * scale, frames=frames, scale=scale, seed=seed, step_degrees=step)
    spec = ESTIMATORS[name]
    result = pipeline.run(observations, spec.factory(spec.config_class(), np.random.default_rng(seed)))
    error = result.trajectory.positions - first_frame(truth)
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1)))) / scale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--estimators", nargs="+", choices=["relpoint", "ekf", "fastslam"],
                        default=["relpoint", "ekf", "fastslam"])  # fmt: skip
    parser.add_argument("--steps", nargs="+", type=float, default=[5.0, 15.0, 25.0], help="degrees a second")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--frames", type=int, default=40)
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)  # the estimators' run warnings: the table says how each run went
    start = time.perf_counter()
    print(f"# ATE / scale (m) over seeds {args.seeds}, {args.frames} observations a second; noise at scale 1")
    print(f"{'estimator':<10} {'step':>5} {'scale':>6} {'noise':>6} {'median':>8} {'worst':>8}   per seed")
    cells: dict[str, list[float]] = {name: [] for name in args.estimators}
    for name in args.estimators:
        for step in args.steps:
            for scale in SCALES:
                for noise in NOISES:
                    ates = [scaled_ate(name, step, scale, noise, seed, args.frames) for seed in args.seeds]
                    cells[name].append(float(np.median(ates)))
                    per_seed = " ".join(f"{a:.3f}" for a in ates)
                    print(f"{name:<10} {step:>5.1f} {scale:>6.2f} {noise:>6.2f} {np.median(ates):>8.3f} "
                          f"{max(ates):>8.3f}   {per_seed}", flush=True)  # fmt: skip
    print()
    for name, medians in cells.items():
        print(f"{name:<10} median cell {np.median(medians):.3f}, worst cell {max(medians):.3f}")
    print(f"\nwall time {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
