"""Time per iteration of the EKF-SLAM estimator as its map grows (paper: Kraut, section IV).

The paper's MRPT 6D EKF reached about 1 s per iteration by iteration 900 on the figure eight at
density 25; the target for relpoint's EKF is 0.15 s or less at 1,000 landmarks and 100
observations per iteration, with nearest-neighbour association: by default the figure eight at
density 150, keeping the first 100 points of each observation. Prints, per window of iterations,
the map size, state size and mean/max wall time of ``EkfSlam.step``, then the accuracy of the run.

Then, in the same process, the comparison with a reference implementation: the EKF module of
``--reference`` (a git revision; default: the one before the batched symmetric update) is loaded
from ``git show`` into a temporary module, handed a copy of the filter's state at the first
iteration whose map holds ``--landmarks`` landmarks, and both filters step through the next
``--compare`` observations in turn (so the machine's load falls on both alike). Prints both mean
times, their ratio, how far the two poses drift apart, and the load average before and after.

Usage::

    python benchmarks/ekf_speed.py [--iterations 600] [--density 150] [--max-points 100]
        [--association nn|jcbb|known] [--threads 1] [--landmarks 1000] [--compare 20] [--reference REV] [--profile]

BLAS is pinned to ``--threads`` (default 1) before numpy loads: on a shared machine OpenBLAS's
worker threads for these mid-sized products mostly wait for each other.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import os
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

from _reference import carry_state, load_module, reference_config

REPO = Path(__file__).resolve().parents[1]
#: The EKF before the batched, symmetric update and the preallocated covariance.
REFERENCE = "4db1a8e"


def load_reference(revision: str) -> ModuleType:
    """The EKF module as it was at git ``revision`` (:func:`_reference.load_module`)."""
    return load_module(revision, "relpoint.estimators.ekf")


def reference_copy(ekf: Any, reference_module: ModuleType) -> Any:
    """A filter of the reference revision, built by its own constructor from ``ekf``'s settings, holding a
    copy of ``ekf``'s state (:func:`_reference.carry_state`; the covariance as a plain array); prints what
    it keeps of its own."""
    other = reference_module.EkfSlam(reference_config(ekf.config, reference_module.EkfConfig))
    kept = carry_state(other, ekf)
    other._P = ekf.covariance
    kept = [name for name in kept if name != "_P"]
    if kept:
        print("reference keeps its own " + ", ".join(kept))
    return other


def load_average() -> str:
    return "load average " + " ".join(f"{value:.2f}" for value in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--density", type=float, default=150.0, help="landmarks per 100 m of path")
    parser.add_argument(
        "--max-points", type=int, default=100, help="keep the first N points of each observation (0: all)"
    )
    parser.add_argument("--radius", type=float, default=95.0, help="figure-eight loop radius (m)")
    parser.add_argument("--noise", type=float, default=0.3)
    parser.add_argument("--association", default="nn", choices=("nn", "jcbb", "known"))
    parser.add_argument("--window", type=int, default=100, help="iterations per printed row")
    parser.add_argument("--threads", type=int, default=1, help="BLAS threads (set before numpy loads)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--landmarks", type=int, default=1000, help="map size at which to compare (0: no comparison)")
    parser.add_argument("--compare", type=int, default=20, help="iterations timed for the comparison")
    parser.add_argument("--reference", default=REFERENCE, help="git revision of the reference EKF")
    parser.add_argument(
        "--profile",
        action="store_true",
        help="also profile the current filter over the compared iterations (pyinstrument)",
    )
    args = parser.parse_args(argv)
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = str(args.threads)

    import numpy as np

    from relpoint.estimators.ekf import EkfConfig, EkfSlam
    from relpoint.geometry import invert_pose, transform_points
    from relpoint.simulation import SimulationConfig, simulate

    sim = simulate(
        SimulationConfig(
            density=args.density, radius=args.radius, noise=args.noise, iterations=args.iterations, seed=args.seed
        )
    )
    config = EkfConfig(association=args.association)
    ekf = EkfSlam(config)
    T_first_world = invert_pose(sim.ground_truth.matrices()[0])
    times: list[float] = []
    errors: list[float] = []
    snapshot: tuple[EkfSlam, int] | None = None
    observations = []
    print(
        f"EKF-SLAM, figure eight (radius {args.radius:g} m), density {args.density:g}, noise {args.noise:g}, "
        f"at most {args.max_points or 'all'} points per observation, "
        f"association {args.association}, BLAS threads {args.threads}; {load_average()}"
    )
    print(f"{'iterations':>12} {'landmarks':>9} {'state':>6} {'mean s/it':>10} {'max s/it':>9}")
    for step in sim.steps():
        observation = step.observation
        if args.max_points and len(observation.points) > args.max_points:
            ids = None if observation.ids is None else observation.ids[: args.max_points]
            observation = dataclasses.replace(observation, points=observation.points[: args.max_points], ids=ids)
        observations.append(observation)
        start = time.perf_counter()
        pose = ekf.step(observation)
        times.append(time.perf_counter() - start)
        if snapshot is None and args.landmarks and ekf.map_size >= args.landmarks:
            snapshot = (copy.deepcopy(ekf), len(times))
        truth = (T_first_world @ step.T_world_sensor)[:3, 3]
        errors.append(float(np.linalg.norm(np.array(pose.position) - truth)))
        if len(times) % args.window == 0 or len(times) == args.iterations:
            window = times[-args.window :]
            first = len(times) - len(window) + 1
            print(
                f"{first:>5}-{len(times):<6} {ekf.map_size:>9} {ekf.summary()['state_size']:>6} "
                f"{np.mean(window):>10.4f} {np.max(window):>9.4f}"
            )
    landmarks = ekf.landmark_map()
    truth_landmarks = transform_points(T_first_world, sim.landmarks.positions)
    known = landmarks.gt_id >= 0
    residual = landmarks.positions[known] - truth_landmarks[landmarks.gt_id[known]]
    print(f"total {sum(times):.2f} s, mean {np.mean(times):.4f} s/iteration")
    print(
        f"position RMSE {np.sqrt(np.mean(np.square(errors))):.3f} m, final {errors[-1]:.3f} m; "
        f"landmark RMSE {np.sqrt(np.mean(np.sum(residual**2, axis=1))):.3f} m over {known.sum()} landmarks "
        f"({len(set(landmarks.gt_id[known].tolist()))} distinct ids)"
    )
    if not args.landmarks:
        return 0
    if snapshot is None:
        print(f"no comparison: the map never held {args.landmarks} landmarks (raise --iterations or --density)")
        return 0
    current, done = snapshot
    reference = reference_copy(current, load_reference(args.reference))
    profiled = copy.deepcopy(current) if args.profile else None
    batch = observations[done : done + args.compare]
    timed = {"current": [], "reference": []}
    drift = 0.0
    print(
        f"comparison from iteration {done + 1}: {current.map_size} landmarks, "
        f"{np.mean([len(o.points) for o in batch]):.0f} observations per iteration, {len(batch)} iterations; "
        f"{load_average()}"
    )
    for observation in batch:
        poses = {}
        for name, filter_ in (("reference", reference), ("current", current)):
            start = time.perf_counter()
            poses[name] = filter_.step(observation)
            timed[name].append(time.perf_counter() - start)
        drift = max(drift, float(np.linalg.norm(np.subtract(poses["current"].position, poses["reference"].position))))
    mean = {name: float(np.mean(values)) for name, values in timed.items()}
    print(
        f"reference ({args.reference}) {mean['reference']:.4f} s/it, current {mean['current']:.4f} s/it "
        f"(max {np.max(timed['current']):.4f}), speed-up {mean['reference'] / mean['current']:.2f}x; "
        f"poses differ by at most {drift:.2e} m; {load_average()}"
    )
    if profiled is not None:
        profile(profiled, batch)
    return 0


def profile(ekf: Any, observations: list[Any]) -> None:
    """Profile ``ekf`` stepping through ``observations``; print the call tree and the covariance update's share."""
    from pyinstrument import Profiler

    profiler = Profiler(interval=0.001)
    profiler.start()
    for observation in observations:
        ekf.step(observation)
    session = profiler.stop()
    print(profiler.output_text(color=False, unicode=False))
    root = session.root_frame()
    assert root is not None

    def time_in(frame: Any, function: str) -> float:
        if frame.function == function:
            return float(frame.time)
        return sum(time_in(child, function) for child in frame.children)

    steps = time_in(root, "step")
    for function, what in (
        ("_reduce_covariance", "the rank update P -= W^T W (syrk)"),
        ("_apply_update", "the whole covariance update (Cholesky of S, W = L^-1 H P, rank update)"),
    ):
        spent = time_in(root, function)
        print(f"{what}, EkfSlam.{function}: {spent:.3f} s of {steps:.3f} s in step, {100 * spent / steps:.1f} %")


if __name__ == "__main__":
    sys.exit(main())
