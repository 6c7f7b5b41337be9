"""The point estimators' defaults at scales they were not tuned on: ATE divided by the scene's scale.

Two scenes, each at several scales with the noise scaled alike, over five seeds (the scene's draws and
the estimator's): a slow tabletop arc past 400 landmarks (at scale 0.0375 a sensor moving 4 cm/s over a
1 m table with 2 mm noise; ``relpoint.simulation.tabletop``) and the simulator's figure eight (200
iterations, noise 0.3 m times the scale). Scale-invariant defaults give the same figures at every
scale; the worst seed is printed beside the median. Nothing is gated: the figures are printed.

    python benchmarks/scene_scale.py                    # EKF and FastSLAM
    python benchmarks/scene_scale.py --estimators fastslam --seeds 0 1 2 3 4 5 6 7
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable

import numpy as np

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS
from relpoint.simulation import SimulationConfig, simulate
from relpoint.simulation.tabletop import tabletop_arc
from relpoint.types import PointObservation

Scene = Callable[[float, int], tuple[list[PointObservation], np.ndarray]]


def figure_eight(scale: float, seed: int) -> tuple[list[PointObservation], np.ndarray]:
    """Observations and true positions of 200 iterations of the figure eight at ``scale``."""
    sim = simulate(SimulationConfig(iterations=200, scale=scale, noise=0.3 * scale, seed=seed))
    return [step.observation for step in sim.steps()], sim.ground_truth.positions


SCENES: dict[str, tuple[Scene, tuple[float, ...]]] = {
    "tabletop": (tabletop_arc, (0.0375, 37.5)),
    "figure8": (figure_eight, (0.01, 1.0, 10.0)),
}


def scaled_ate(name: str, scene: Scene, scale: float, seed: int) -> float:
    """ATE (m) of ``name`` with its defaults on ``scene`` at ``scale``, divided by the scale."""
    observations, truth = scene(scale, seed)
    spec = ESTIMATORS[name]
    result = pipeline.run(observations, spec.factory(spec.config_class(), np.random.default_rng(seed)))
    return float(np.sqrt(np.mean(np.sum((result.trajectory.positions - truth) ** 2, axis=1)))) / scale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--estimators", nargs="+", choices=["ekf", "fastslam"], default=["ekf", "fastslam"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)  # the estimators' run warnings: the table says how each run went
    start = time.perf_counter()
    print(f"# ATE / scale over seeds {args.seeds}")
    print(f"{'estimator':<10} {'scene':<9} {'scale':>7} {'median':>8} {'worst':>8}   per seed")
    for name in args.estimators:
        for label, (scene, scales) in SCENES.items():
            for scale in scales:
                values = [scaled_ate(name, scene, scale, seed) for seed in args.seeds]
                print(f"{name:<10} {label:<9} {scale:>7g} {np.median(values):8.4f} {max(values):8.4f}   "
                      + " ".join(f"{v:.4f}" for v in values), flush=True)  # fmt: skip
    print(f"\nwall time {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
