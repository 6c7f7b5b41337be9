"""Time per iteration of FastSLAM at real-data sizes: 50 particles, 250 observations per iteration,
2,500 landmarks (issue 20's target: at most 50 ms per iteration, at unchanged accuracy).

A dense figure eight (``--density``, the first ``--max-points`` points of each observation) is run
until the best particle's map holds ``--landmarks`` landmarks; printed per window: map size and the
mean/max wall time and mean CPU time of ``FastSlam.step`` (the process's: on a shared machine it
shows less of the others' load). Then, in the same process, the comparison with a reference
implementation: FastSLAM as it was at git ``--reference`` (default: the last revision with the
association in numpy), on its own revision's core package (``benchmarks/_reference.py``), is handed a
copy of the filter's state and both step through the next ``--compare`` observations in turn, so the
machine's load falls on both alike. Prints both mean times (wall and CPU), their ratio, the last
pose of each and the load average.

Usage::

    python benchmarks/fastslam_speed.py [--particles 50] [--max-points 250] [--landmarks 2500]
        [--density 400] [--compare 10] [--reference REV] [--seed 0]

Accuracy on real data: ``python benchmarks/keypoints.py --estimators fastslam --fastslam-frames 400``.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import os
import time
from types import ModuleType
from typing import Any

from _reference import carry_state, load_module, reference_config

#: The last revision whose FastSLAM associated points in numpy.
REFERENCE = "913402b"


def load_average() -> str:
    return "load average " + " ".join(f"{value:.2f}" for value in os.getloadavg())


def reference_copy(slam: Any, reference_module: ModuleType) -> Any:
    """A filter of the reference revision, built by its own constructor from ``slam``'s settings, holding a
    deep copy of ``slam``'s state (:func:`_reference.carry_state`); prints what it keeps of its own."""
    config = reference_config(slam.config, reference_module.FastSlamConfig)
    other = reference_module.FastSlam(config, copy.deepcopy(slam._rng))
    if hasattr(reference_module.FastSlam, "compile"):  # its compiled loops, not timed (JIT: no prebuilt module)
        reference_module.FastSlam.compile()
    kept = carry_state(other, slam)
    if kept:
        print("reference keeps its own " + ", ".join(kept))
    return other


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=50)
    parser.add_argument("--max-points", type=int, default=250, help="keep the first N points of each observation")
    parser.add_argument("--landmarks", type=int, default=2500, help="map size at which to compare")
    parser.add_argument("--density", type=float, default=400.0, help="landmarks per 100 m of path")
    parser.add_argument("--window", type=int, default=50, help="iterations per printed row")
    parser.add_argument("--compare", type=int, default=10, help="iterations timed for the comparison")
    parser.add_argument("--reference", default=REFERENCE, help="git revision of the reference FastSLAM")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `relpoint run` does

    import numpy as np

    from relpoint.estimators.fastslam import FastSlam, FastSlamConfig
    from relpoint.simulation import SimulationConfig, simulate

    sim = simulate(SimulationConfig(density=args.density, noise=0.3, seed=args.seed))
    config = FastSlamConfig(particles=args.particles, observation_sigma=0.3)
    slam = FastSlam(config, np.random.default_rng(args.seed))
    FastSlam.compile()
    print(
        f"FastSLAM {config.variant}, {args.particles} particles, figure eight at density {args.density:g}, "
        f"at most {args.max_points} points per observation; {load_average()}"
    )
    print(f"{'iterations':>12} {'landmarks':>9} {'points':>6} {'mean s/it':>10} {'max s/it':>9} {'CPU s/it':>9}")
    times: list[float] = []
    cpu_times: list[float] = []  # CPU time of the process: on a shared machine, less of the others' load
    points: list[int] = []
    steps = iter(sim.steps())
    observations = []
    for step in steps:
        observation = step.observation
        if len(observation.points) > args.max_points:
            ids = None if observation.ids is None else observation.ids[: args.max_points]
            observation = dataclasses.replace(observation, points=observation.points[: args.max_points], ids=ids)
        start, cpu_start = time.perf_counter(), time.process_time()
        slam.step(observation)
        times.append(time.perf_counter() - start)
        cpu_times.append(time.process_time() - cpu_start)
        points.append(len(observation.points))
        full = slam.map_size >= args.landmarks
        if len(times) % args.window == 0 or full:  # the last, partial window ends at the target map size
            size = (len(times) - 1) % args.window + 1
            window = times[-size:]
            print(
                f"{len(times) - len(window) + 1:>5}-{len(times):<6} {slam.map_size:>9} "
                f"{np.mean(points[-size:]):>6.0f} {np.mean(window):>10.4f} {np.max(window):>9.4f} "
                f"{np.mean(cpu_times[-size:]):>9.4f}"
            )
        if full:
            break
    for step in steps:  # the observations both filters are timed on
        observation = step.observation
        if len(observation.points) > args.max_points:
            ids = None if observation.ids is None else observation.ids[: args.max_points]
            observation = dataclasses.replace(observation, points=observation.points[: args.max_points], ids=ids)
        observations.append(observation)
        if len(observations) == args.compare:
            break
    if slam.map_size < args.landmarks:
        print(f"the map never held {args.landmarks} landmarks (raise --density)")
        return 0
    # The current filter alone on a copy first: stepped in turn with the reference below, each evicts the
    # other's data from the caches, which inflates both.
    alone = copy.deepcopy(slam)
    alone_cpu = []
    for observation in observations:
        cpu_start = time.process_time()
        alone.step(observation)
        alone_cpu.append(time.process_time() - cpu_start)
    print(
        f"current alone from iteration {len(times) + 1} ({slam.map_size} landmarks, {len(observations)} iterations): "
        f"CPU {np.mean(alone_cpu):.4f} s/it (max {np.max(alone_cpu):.4f}); {load_average()}"
    )
    del alone
    reference = reference_copy(slam, load_module(args.reference, "relpoint.estimators.fastslam"))
    timed: dict[str, list[float]] = {"current": [], "reference": []}
    cpu: dict[str, list[float]] = {"current": [], "reference": []}
    print(
        f"comparison from iteration {len(times) + 1}: {slam.map_size} landmarks, "
        f"{np.mean([len(o.points) for o in observations]):.0f} observations per iteration, "
        f"{len(observations)} iterations; {load_average()}"
    )
    poses = {}
    for observation in observations:
        for name, filter_ in (("reference", reference), ("current", slam)):
            start, cpu_start = time.perf_counter(), time.process_time()
            poses[name] = filter_.step(observation)
            timed[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - cpu_start)
    mean = {name: float(np.mean(values)) for name, values in timed.items()}
    print(
        f"reference ({args.reference}) {mean['reference']:.4f} s/it, current {mean['current']:.4f} s/it "
        f"(max {np.max(timed['current']):.4f}), speed-up {mean['reference'] / mean['current']:.1f}x; "
        f"CPU {np.mean(cpu['reference']):.4f} and {np.mean(cpu['current']):.4f} s/it; {load_average()}"
    )
    # The default reference is an older algorithm, whose pose is not expected to match; both are printed
    # in full: the current one stays the same across changes meant to leave results unchanged, and
    # equals the reference's when that is a revision of the same algorithm.
    print(
        "last pose: current "
        + " ".join(repr(float(value)) for value in poses["current"].position)
        + ", reference "
        + " ".join(repr(float(value)) for value in poses["reference"].position)
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
