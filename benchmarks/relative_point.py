"""Speed of the Relative Point estimator against the paper's figures (Kraut, section III, Figs. 4-7).

Prints, all in-process on ``relpoint.simulation`` data (no files):

1. the matching structure: build + query time of candidate spatial indexes at about 100 and 540
   points (the paper's OVLQPQuadTree / octree / k-d tree comparison; "sweep" is the estimator's
   one-to-one matching, sorted along x, which also settles conflicting claims);
2. median time per iteration with about 100 observed points (paper: 2 ms) and about 540 (paper:
   18 ms), wall clock and process CPU time;
3. flatness (paper Fig. 4): median time of the last 10 % of iterations over the first 10 % across
   10 or more passes of the figure eight (target <= 1.2);
4. dynamic detection time and comparisons against the share of uncorrelated points (paper Figs. 6-7),
   normalised by n log2 n;
5. with ``--accuracy``: landmark and trajectory RMSE on the figure eight at density 25, noise 0.3,
   900 iterations, with and without 30 % dynamic points, and dynamic precision / recall; beside them
   an oracle run with the moving points removed (the best the static points allow).

Usage: python benchmarks/relative_point.py [--quick] [--accuracy | --accuracy-only] [--passes 10] [--repeat 3]
       [--seed 0] [--seeds 0 1 2 3 4]
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections.abc import Callable
from dataclasses import replace

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    # As `relpoint run` does: multithreaded BLAS on 3x3 and 100x3 arrays only adds overhead.
    os.environ.setdefault(_name, "1")

import numpy as np  # noqa: E402
from scipy.spatial import KDTree, cKDTree  # noqa: E402

from relpoint.estimators.relative_point import RelativePointConfig, RelativePointEstimator  # noqa: E402
from relpoint.estimators.relative_point.dynamics import detect_dynamic  # noqa: E402
from relpoint.estimators.relative_point.registration import match_nearest  # noqa: E402
from relpoint.simulation import SimulationConfig, simulate  # noqa: E402
from relpoint.types import GroundTruthLandmarks, Trajectory  # noqa: E402

#: Figure-eight densities that give about 100 and about 540 observed points per iteration.
DENSITY_100 = 130.0
DENSITY_540 = 695.0


def _timed(function: Callable[[], object], repeat: int) -> float:
    """Median wall time of ``function`` in milliseconds."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def matching_structures(seed: int) -> None:
    print("== 1. matching structure: build + query of n points against n points (ms, median)")
    rng = np.random.default_rng(seed)
    print(f"{'n':>6} {'sweep':>9} {'cKDTree':>9} {'KDTree':>9} {'brute':>9}")
    match_nearest(np.zeros((3, 3)), np.zeros((3, 3)), 2.0)  # compile (or load) the kernel first
    for n in (100, 540):
        reference = rng.uniform(-70, 70, (n, 3))
        query = reference + rng.normal(0, 0.5, (n, 3))

        def brute(reference: np.ndarray = reference, query: np.ndarray = query) -> object:
            d2 = np.sum((query[:, None, :] - reference[None, :, :]) ** 2, axis=2)
            return d2.argmin(axis=1)

        times = [
            _timed(lambda r=reference, q=query: match_nearest(r, q, 2.0), 200),
            _timed(lambda r=reference, q=query: cKDTree(r).query(q, k=1, distance_upper_bound=2.0), 200),
            _timed(lambda r=reference, q=query: KDTree(r).query(q, k=1, distance_upper_bound=2.0), 200),
            _timed(brute, 50),
        ]
        print(f"{n:>6} " + " ".join(f"{t:>9.3f}" for t in times))


def run_iterations(config: SimulationConfig) -> tuple[np.ndarray, np.ndarray, float, str]:
    """Step the estimator over a simulation: wall ms (N,), CPU ms (N,), mean observed points, and a
    line on the final adjustment (its time, outside the per-iteration figures, and its size)."""
    simulation = simulate(config)
    observations = [step.observation for step in simulation.steps()]
    estimator = RelativePointEstimator(RelativePointConfig())
    wall = np.empty(len(observations))
    cpu = np.empty(len(observations))
    poses = []
    for i, observation in enumerate(observations):
        w0, c0 = time.perf_counter(), time.process_time()
        poses.append(estimator.step(observation))
        wall[i] = time.perf_counter() - w0
        cpu[i] = time.process_time() - c0
    trajectory = Trajectory(
        np.array([pose.stamp_ns for pose in poses]),
        np.array([pose.position for pose in poses]),
        np.array([pose.quat_xyzw for pose in poses]),
    )
    start = time.perf_counter()
    estimator.finish(trajectory)
    report = estimator.summary().get("final_adjustment", {})
    final = (
        f"final adjustment and re-location: {time.perf_counter() - start:.2f} s "
        f"({report.get('groups', 0)} groups, {report.get('points', 0)} points, "
        f"{report.get('memberships', 0)} memberships, {report.get('iterations', 0)} LM iterations)"
    )
    return 1e3 * wall, 1e3 * cpu, float(np.mean([len(o) for o in observations])), final


def speed(quick: bool, seed: int, repeat: int) -> None:
    print("== 2. time per iteration, figure eight, noise 0.3 (paper: 2 ms at ~100 points, 18 ms at ~540)")
    print(f"   (median over iterations; best of {repeat} runs, since other processes share this machine)")
    iterations = 300 if quick else None
    for density, paper in ((DENSITY_100, 2.0), (DENSITY_540, 18.0)):
        config = SimulationConfig(scenario="figure8", density=density, noise=0.3, iterations=iterations, seed=seed)
        runs = [run_iterations(config) for _ in range(repeat)]
        wall, cpu, observed, final = min(runs, key=lambda r: float(np.median(r[0])))
        print(
            f"density {density:>5.0f}: {observed:6.1f} observed points/iteration, {len(wall)} iterations: "
            f"median {np.median(wall):6.2f} ms wall, {np.median(cpu):6.2f} ms CPU "
            f"(mean {np.mean(wall):.2f}, p90 {np.percentile(wall, 90):.2f}; paper {paper:g} ms; "
            f"runs: {', '.join(f'{np.median(r[0]):.2f}' for r in runs)})"
        )
        print(f"   once when the log ends: {final}")


def flatness(passes: int, seed: int) -> None:
    print(f"== 3. flatness over {passes} passes of the figure eight at ~100 observed points (paper Fig. 4)")
    config = SimulationConfig(scenario="figure8", density=DENSITY_100, noise=0.3, passes=passes, seed=seed)
    wall, cpu, observed, final = run_iterations(config)
    tenth = max(1, len(wall) // 10)
    ratio_wall = float(np.median(wall[-tenth:]) / np.median(wall[:tenth]))
    ratio_cpu = float(np.median(cpu[-tenth:]) / np.median(cpu[:tenth]))
    slope = np.polyfit(np.arange(len(wall)), wall, 1)[0] * 1000.0
    print(
        f"{len(wall)} iterations, {observed:.1f} observed points: median first 10 % {np.median(wall[:tenth]):.2f} ms, "
        f"last 10 % {np.median(wall[-tenth:]):.2f} ms; last/first = {ratio_wall:.3f} wall, {ratio_cpu:.3f} CPU "
        f"(target <= 1.2); regression slope {slope:+.3f} ms per 1000 iterations"
    )
    print(f"   once when the log ends: {final}")


def _window_tracks(share: float, density: float, window: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Tracks (n, window, 3) of the points seen throughout a window, a ``share`` of them uncorrelated.

    The static tracks are the simulation's untransformed observations of one window of the figure
    eight; the uncorrelated ones replace randomly chosen tracks by a random walk (0.5 m per axis and
    iteration) from the same start, in the sensor frame, so they share nothing with the sensor's
    rigid motion nor with each other (the paper's uncorrelated points).
    """
    config = SimulationConfig(scenario="figure8", density=density, noise=0.3, iterations=100 + window, seed=seed)
    steps = list(simulate(config).steps())[100 : 100 + window]
    common = set(steps[0].observation.ids.tolist())
    for step in steps[1:]:
        common &= set(step.observation.ids.tolist())
    ids = np.array(sorted(common), dtype=np.int64)
    tracks = np.empty((len(ids), window, 3))
    for t, step in enumerate(steps):
        row = {int(i): r for r, i in enumerate(step.observation.ids)}
        tracks[:, t] = step.observation.points[[row[int(i)] for i in ids]]
    rng = np.random.default_rng(seed)
    moving = np.zeros(len(ids), bool)
    moving[rng.choice(len(ids), size=int(round(share * len(ids))), replace=False)] = True
    walk = np.cumsum(rng.normal(0.0, 0.5, (int(moving.sum()), window, 3)), axis=1)
    tracks[moving] = tracks[moving, :1] + walk
    return tracks, moving


def dynamic_detection(quick: bool, seed: int) -> None:
    print("== 4. dynamic detection vs share of uncorrelated points (paper Figs. 6-7; 20-iteration window)")
    print("   (static tracks: simulated observations; uncorrelated: random walks replacing a share of them)")
    shares = (0.0, 0.2, 0.4, 0.47) if quick else (0.0, 0.1, 0.2, 0.3, 0.4, 0.45, 0.47, 0.5)
    densities = (150.0, 600.0) if quick else (75.0, 150.0, 300.0, 600.0, 1200.0, 2400.0)
    print(f"{'share':>6} {'n':>6} {'ms':>9} {'compares':>9} {'cmp/nlog2n':>11} {'recall':>7} {'precision':>9}")
    for share in shares:
        for density in densities:
            tracks, moving = _window_tracks(share, density, 20, seed)
            n = len(tracks)
            result = detect_dynamic(tracks)
            elapsed = _timed(lambda tracks=tracks: detect_dynamic(tracks), 3)
            flagged = ~result.static
            recall = np.count_nonzero(flagged & moving) / max(np.count_nonzero(moving), 1)
            precision = np.count_nonzero(flagged & moving) / max(np.count_nonzero(flagged), 1)
            normalised = result.comparisons / (n * math.log2(n)) if n > 1 else float("nan")
            print(
                f"{share:>6.2f} {n:>6} {elapsed:>9.2f} {result.comparisons:>9} {normalised:>11.3f} "
                f"{recall:>7.2f} {precision:>9.2f}"
            )


def _map_errors(
    estimator: RelativePointEstimator, truth: GroundTruthLandmarks, *, flagged_too: bool = False
) -> tuple[float, float, int]:
    """Static-landmark RMSE and median (m) and the number of static landmarks compared.

    Landmarks flagged dynamic are left out, unless ``flagged_too``: then static landmarks flagged by
    mistake count too, at the position the map gives them (their mean observed position), so that
    false flags cannot flatter the figure.
    """
    landmarks = estimator.landmark_map()
    known = landmarks.gt_id >= 0
    truly_dynamic = known & truth.dynamic[np.where(known, landmarks.gt_id, 0)]
    static = known & ~truly_dynamic & (flagged_too | ~landmarks.dynamic)
    errors = np.linalg.norm(landmarks.positions[static] - truth.positions[landmarks.gt_id[static]], axis=1)
    if not len(errors):
        return float("nan"), float("nan"), 0
    return float(np.sqrt(np.mean(errors**2))), float(np.median(errors)), len(errors)


def accuracy_run(
    seed: int, dynamic: float, config: RelativePointConfig | None = None, *, oracle: bool = False
) -> dict[str, float]:
    """One accuracy run (figure eight, density 25, noise 0.3, 900 iterations): RMSEs and dynamic flags.

    The simulated first pose is the identity, so estimates (in the first sensor frame) compare with
    ground truth directly: nothing is fitted or transformed. ``oracle`` removes the observations of
    the moving landmarks before the estimator sees them (perfect dynamic detection): the best the
    static points alone allow. The ``incremental_*`` figures are taken before the final adjustment
    (the paper's incremental solution), the others after it (what ``relpoint run`` writes).
    """
    sim_config = SimulationConfig(scenario="figure8", density=25, noise=0.3, iterations=900, dynamic=dynamic, seed=seed)
    simulation = simulate(sim_config)
    truth = simulation.landmarks
    estimator = RelativePointEstimator(config or RelativePointConfig())
    poses = []
    for step in simulation.steps():
        observation = step.observation
        if oracle and observation.ids is not None:
            keep = (observation.ids < 0) | ~truth.dynamic[np.maximum(observation.ids, 0)]
            observation = replace(observation, points=observation.points[keep], ids=observation.ids[keep])
        poses.append(estimator.step(observation))
    trajectory = Trajectory(
        np.array([pose.stamp_ns for pose in poses]),
        np.array([pose.position for pose in poses]),
        np.array([pose.quat_xyzw for pose in poses]),
    )

    def trajectory_rmse(trajectory: Trajectory) -> float:
        squared = np.sum((trajectory.positions - simulation.ground_truth.positions) ** 2, axis=1)
        return float(np.sqrt(np.mean(squared)))

    incremental_rmse, _, _ = _map_errors(estimator, truth)
    incremental_trajectory = trajectory_rmse(trajectory)
    trajectory = estimator.finish(trajectory)
    landmark_rmse, landmark_median, n_static = _map_errors(estimator, truth)
    all_static_rmse, _, _ = _map_errors(estimator, truth, flagged_too=True)
    landmarks = estimator.landmark_map()
    known = landmarks.gt_id >= 0
    truly_dynamic = known & truth.dynamic[np.where(known, landmarks.gt_id, 0)]
    flagged = landmarks.dynamic
    hits = np.count_nonzero(flagged & truly_dynamic)
    return {
        "landmark_rmse": landmark_rmse,
        "landmark_median": landmark_median,
        "static_landmarks": n_static,
        "trajectory_rmse": trajectory_rmse(trajectory),
        "all_static_rmse": all_static_rmse,
        "incremental_landmark_rmse": incremental_rmse,
        "incremental_trajectory_rmse": incremental_trajectory,
        "flagged": int(np.count_nonzero(flagged)),
        "dynamic_landmarks": int(np.count_nonzero(truly_dynamic)),
        "unflagged_dynamic": int(np.count_nonzero(truly_dynamic & ~flagged)),
        "precision": hits / max(np.count_nonzero(flagged), 1),
        "recall": hits / max(np.count_nonzero(truly_dynamic), 1),
    }


def accuracy(seeds: list[int]) -> None:
    print("== 5. accuracy, figure eight, density 25, noise 0.3, 900 iterations (estimates vs ground truth as is)")
    print("   'oracle': the moving landmarks' observations removed before the estimator (perfect detection)")
    print("   'incr': before the final adjustment (the paper's incremental solution)")
    print(
        f"{'seed':>4} {'run':>8} {'lm RMSE':>8} {'lm med':>7} {'static':>6} {'traj RMSE':>9} "
        f"{'incr lm':>7} {'incr tr':>7} {'flagged':>7} {'dyn lm':>6} {'missed':>6} {'prec':>5} {'recall':>6}"
    )
    runs = {"static": (0.0, False), "dyn 30%": (0.3, False), "oracle": (0.3, True)}
    table: dict[str, list[dict[str, float]]] = {name: [] for name in runs}
    for seed in seeds:
        for name, (dynamic, oracle) in runs.items():
            r = accuracy_run(seed, dynamic, oracle=oracle)
            table[name].append(r)
            print(
                f"{seed:>4} {name:>8} {r['landmark_rmse']:>8.3f} {r['landmark_median']:>7.3f} "
                f"{r['static_landmarks']:>6} {r['trajectory_rmse']:>9.3f} "
                f"{r['incremental_landmark_rmse']:>7.3f} {r['incremental_trajectory_rmse']:>7.3f} {r['flagged']:>7} "
                f"{r['dynamic_landmarks']:>6} {r['unflagged_dynamic']:>6} {r['precision']:>5.2f} {r['recall']:>6.2f}",
                flush=True,
            )
    if len(seeds) > 1:
        print(
            f"over {len(seeds)} seeds: landmark RMSE mean / median (m), trajectory RMSE mean (m), precision, recall;"
            " then the same RMSEs before the final adjustment; then the landmark RMSE over every static landmark,"
            " those flagged dynamic by mistake included"
        )
        for name, rows in table.items():
            lm = np.array([r["landmark_rmse"] for r in rows])
            trajectory = np.array([r["trajectory_rmse"] for r in rows])
            incremental = np.array([r["incremental_landmark_rmse"] for r in rows])
            incremental_trajectory = np.array([r["incremental_trajectory_rmse"] for r in rows])
            all_static = np.array([r["all_static_rmse"] for r in rows])
            precision = np.mean([r["precision"] for r in rows])
            recall = np.mean([r["recall"] for r in rows])
            print(
                f"{name:>12}: {lm.mean():.2f} / {np.median(lm):.2f}, {trajectory.mean():.2f}, "
                f"{precision:.2f}, {recall:.2f}   incremental {incremental.mean():.2f} / {np.median(incremental):.2f}, "
                f"{incremental_trajectory.mean():.2f}   all static (flagged too) {all_static.mean():.2f} / "
                f"{np.median(all_static):.2f}"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer iterations, passes and sizes (about a minute)")
    parser.add_argument("--accuracy", action="store_true", help="also print the accuracy figures")
    parser.add_argument("--accuracy-only", action="store_true", help="print only the accuracy figures")
    parser.add_argument("--passes", type=int, default=10, help="figure-eight passes of the flatness test")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="accuracy seeds (default: --seed)")
    parser.add_argument("--repeat", type=int, default=None, help="speed runs to take the best of (default 3, quick 1)")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    if args.accuracy_only:
        accuracy(args.seeds if args.seeds is not None else [args.seed])
        return
    matching_structures(args.seed)
    speed(args.quick, args.seed, args.repeat or (1 if args.quick else 3))
    flatness(2 if args.quick else max(args.passes, 10), args.seed)
    dynamic_detection(args.quick, args.seed)
    if args.accuracy:
        accuracy(args.seeds if args.seeds is not None else [args.seed])


if __name__ == "__main__":
    main()
