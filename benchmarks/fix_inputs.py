"""Position fixes as other tools and receivers write them, fed to the EKF and FastSLAM with defaults.

The simulator's fixes measure all three axes, come once an iteration at most, are stamped with the
cloud they follow, and sit near the origin. Receivers and other tools' logs do otherwise. Each
variant below changes one of those on the same figure eight (12 m/s, 10 Hz clouds, odometry, 1 m
fixes), and the fixes' frame is turned 90 deg about z and 40 m away from the start, so that the
fixes must be used to get ``world`` at all:

- ``every``: one fix an iteration, as the simulator writes them (the reference);
- ``horizontal``: the altitude a placeholder 0 with ROS's "unknown" variance 1e9 m^2 (a GNSS fix in
  a local plane);
- ``10 Hz``: ten fixes an iteration, each measured at its own stamp between two clouds;
- ``late 50 ms`` / ``late 200 ms``: each fix measured that long before the cloud it follows in the
  log (a receiver's latency);
- ``utm``: the fixes' frame 5,000 km north and 500 km east (UTM coordinates).

Printed per estimator and seed: the ATE in the fixes' frame, without alignment (m), horizontal only
for ``horizontal`` (it measures no altitude), and whether the fixes pinned the frame; then the same
run without fixes, whose frame is its start (so its error in ``world`` is tens of metres).

Usage::

    .venv/bin/python benchmarks/fix_inputs.py [--seeds 0 1] [--iterations 250] [--variants every utm]
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator

import numpy as np

from relpoint import pipeline
from relpoint.estimators.ekf import EkfConfig, EkfSlam
from relpoint.estimators.fastslam import FastSlam, FastSlamConfig
from relpoint.geometry import so3_exp
from relpoint.simulation import Simulation, SimulationConfig, simulate
from relpoint.types import PositionFix

FIX_SIGMA = 1.0
UNKNOWN = 1e9
VARIANTS = ("every", "horizontal", "10 Hz", "late 50 ms", "late 200 ms", "utm", "none")


def _frame(variant: str) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and offset of the fixes' frame from the simulated ``world``."""
    offset = np.array([500_000.0, 5_000_000.0, 100.0]) if variant == "utm" else np.array([40.0, -10.0, 0.0])
    return so3_exp(np.array([0.0, 0.0, np.pi / 2])), offset


def _true_position(sim: Simulation, stamp_ns: int) -> np.ndarray:
    truth = sim.ground_truth
    return np.array([np.interp(stamp_ns, truth.stamps_ns, truth.positions[:, axis]) for axis in range(3)])


def inputs(sim: Simulation, variant: str, rng: np.random.Generator) -> Iterator[object]:
    """The log's items in log order: each cloud, its odometry, then the fixes logged after it."""
    R, t = _frame(variant)
    stamps = sim.ground_truth.stamps_ns
    for k, step in enumerate(sim.steps()):
        yield step.observation
        if step.odometry is not None:
            yield step.odometry
        if variant == "none" or k + 1 >= len(stamps):
            continue
        if variant == "10 Hz":
            measured = [int(stamps[k] + j * (stamps[k + 1] - stamps[k]) // 10) + 1 for j in range(10)]
        elif variant.startswith("late"):
            measured = [int(stamps[k]) - int(float(variant.split()[1]) * 1e6)]
        else:
            measured = [int(stamps[k])]
        for stamp in measured:
            position = R @ (_true_position(sim, stamp) + rng.normal(0.0, FIX_SIGMA, 3)) + t
            covariance = np.eye(3) * FIX_SIGMA**2
            if variant == "horizontal":
                position[2] = 0.0
                covariance = np.diag([FIX_SIGMA**2, FIX_SIGMA**2, UNKNOWN])
            yield PositionFix(stamp, position, covariance)


def run(name: str, seed: int, variant: str, iterations: int) -> tuple[float, str]:
    sim = simulate(SimulationConfig(iterations=iterations, density=25, seed=seed, odometry_noise=0.05))
    if name == "ekf":
        estimator: EkfSlam | FastSlam = EkfSlam(EkfConfig(observation_sigma=0.3))
    else:
        estimator = FastSlam(FastSlamConfig(observation_sigma=0.3), np.random.default_rng(0))
    result = pipeline.run(inputs(sim, variant, np.random.default_rng(seed + 100)), estimator)
    R, t = _frame(variant)
    truth = sim.ground_truth.positions @ R.T + t
    axes = 2 if variant == "horizontal" else 3
    error = (result.trajectory.positions - truth)[:, :axes]
    pinned = result.summary.get("fix_frame", "-")
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1)))), f"{pinned}, {result.summary.get('fixes', 0)} fused"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--iterations", type=int, default=250)
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    parser.add_argument("--estimators", nargs="+", choices=("ekf", "fastslam"), default=["ekf", "fastslam"])
    args = parser.parse_args(argv)
    start = time.perf_counter()
    print(f"figure eight, {args.iterations} iterations, 1 m fixes, fixes' frame turned 90 deg and moved; ATE m")
    print(f"{'variant':<14}{'estimator':<10}" + "".join(f"{'seed ' + str(s):>34}" for s in args.seeds))
    for variant in args.variants:
        for name in args.estimators:
            cells = []
            for seed in args.seeds:
                ate, note = run(name, seed, variant, args.iterations)
                cells.append(f"{ate:9.3f} ({note})")
            print(f"{variant:<14}{name:<10}" + "".join(f"{cell:>34}" for cell in cells), flush=True)
    print(f"wall time {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
