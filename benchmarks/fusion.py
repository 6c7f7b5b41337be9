"""Fusion of local SLAM segments with low-rate fixes: global error of the fused result versus its parts.

The ``figure8-gaps`` scenario (General Concept of 3D SLAM, Fig. 10 setting): a figure eight whose
feature-poor stretches break local SLAM into segments, fixes every 10 iterations (1 Hz) with 1 m noise
per axis, and a survey frame (``world``) in which the run starts at an unknown pose. Every figure is
without alignment, since the fixes define ``world``:

- *fused*: ``relpoint.fusion.fuse`` (Algorithm 3: segments placed by B-spline + rigid LSF, eq. 31-32);
- *segments alone*: the local SLAM's own path and map, in its own frame;
- *fixes alone*: the fixes interpolated to every iteration (eq. 26-30); its map places each landmark
  from its creation pose, taking the position from the fixes and the heading from the fixes' course
  (a fix carries no orientation).

Local SLAM sources: ``synthetic`` (a restarting local SLAM with a random-walk drift, from
``relpoint.fusion.synthetic``; seconds), ``relpoint`` (the Relative Point estimator; seconds) and
``ekf`` (the EKF-SLAM estimator without fixes; minutes), the last two once restarted per segment
(Algorithm 3, ``relpoint fuse --restart``) and once as one continuous run split afterwards
(``relpoint fuse``), that with the piecewise-rigid fit (the default) and with one rigid fit per local
map (``split_significance=0``). With ``--in-loop`` the EKF fusing the fixes inside its filter
(``add_fix``) is printed too. Wall and CPU times are printed for the estimator runs (the machine may be
shared).

Usage::

    .venv/bin/python benchmarks/fusion.py                    # synthetic, seeds 1-5
    .venv/bin/python benchmarks/fusion.py --source relpoint --seeds 1
    .venv/bin/python benchmarks/fusion.py --source ekf --seeds 1 --in-loop
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from relpoint import pipeline
from relpoint.estimators import ESTIMATORS, Estimator
from relpoint.evaluation import EvaluationSettings, evaluate_trajectory
from relpoint.fusion import FusionConfig, FusionResult, fuse, matched_counts_from_map_growth
from relpoint.fusion.segmented import SegmentedRun, run_segmented
from relpoint.fusion.synthetic import synthetic_local_slam
from relpoint.simulation import Simulation, SimulationConfig, paths, simulate
from relpoint.types import LandmarkMap, Trajectory

SETTINGS = EvaluationSettings(align="none", rpe=False, kitti=False)


def ate(reference: Trajectory, estimate: Trajectory, rows: np.ndarray | None = None) -> float:
    if rows is not None:
        reference = Trajectory(reference.stamps_ns[rows], reference.positions[rows], reference.quats_xyzw[rows])
        estimate = Trajectory(estimate.stamps_ns[rows], estimate.positions[rows], estimate.quats_xyzw[rows])
    return evaluate_trajectory(reference, estimate, SETTINGS).summary["ate_rmse"]


def landmark_rmse(landmarks: LandmarkMap, simulation: Simulation) -> float:
    known = landmarks.gt_id >= 0
    truth = simulation.landmarks.positions[landmarks.gt_id[known]]
    return float(np.sqrt(np.mean(np.sum((landmarks.positions[known] - truth) ** 2, axis=1))))


def fixes_alone_map(local: Trajectory, landmarks: LandmarkMap, owners: np.ndarray, result: FusionResult) -> LandmarkMap:
    """Each landmark from its creation pose: position from the fixes, heading from the fixes' course."""
    course = np.gradient(result.fix_positions, axis=0)
    course[np.linalg.norm(course, axis=1) < 1e-9] = [1.0, 0.0, 0.0]
    R_world_fix = paths.orientations_from_tangents(course)
    T_local = local.matrices()
    offsets = np.einsum("nba,nb->na", T_local[owners, :3, :3], landmarks.positions - T_local[owners, :3, 3])
    positions = result.fix_positions[owners] + np.einsum("nab,nb->na", R_world_fix[owners], offsets)
    return LandmarkMap(positions, landmarks.observations, landmarks.dynamic, landmarks.gt_id)


def report(name: str, simulation: Simulation, local: Trajectory, landmarks: LandmarkMap, owners: np.ndarray,
           result: FusionResult, seconds: float) -> dict[str, float]:  # fmt: skip
    truth = simulation.ground_truth
    fixes = Trajectory(truth.stamps_ns, result.fix_positions, local.quats_xyzw)
    figures = {
        "ate_fused": ate(truth, result.trajectory),
        "ate_segments": ate(truth, local),
        "ate_fixes": ate(truth, fixes),
        "lm_fused": landmark_rmse(result.landmarks, simulation),
        "lm_segments": landmark_rmse(landmarks, simulation),
        "lm_fixes": landmark_rmse(fixes_alone_map(local, landmarks, owners, result), simulation),
    }
    s = result.summary
    print(f"\n{name}: {s['segments_placed']}/{s['segments']} segments placed, {s['iterations_fused']} iterations "
          f"fused, {s['iterations_fixes_only']} from fixes alone, {s['landmarks_placed']} landmarks; "
          f"fuse() {seconds * 1e3:.0f} ms")  # fmt: skip
    print(f"  {'part':<24}{'iterations':>11}{'fused ATE':>11}{'segment ATE':>13}{'fixes ATE':>11}  (m, no alignment)")
    for seg in result.segments:
        rows = seg.iterations
        fused = ate(truth, result.trajectory, rows)  # a left-out segment: the fixes alone
        print(f"  segment {seg.index} ({rows[0]}-{rows[-1]}){'':<{max(0, 11 - len(str(rows[0])) - len(str(rows[-1])))}}"
              f"{len(rows):>11}{fused:>11.3f}{ate(truth, local, rows):>13.3f}{ate(truth, fixes, rows):>11.3f}"
              + ("" if seg.transform is not None else f"  left out: {seg.refused}"))  # fmt: skip
    print(f"  {'whole run':<24}{len(truth):>11}{figures['ate_fused']:>11.3f}{figures['ate_segments']:>13.3f}"
          f"{figures['ate_fixes']:>11.3f}")  # fmt: skip
    print(f"  landmark RMSE (m): fused {figures['lm_fused']:.3f}, segments alone {figures['lm_segments']:.3f}, "
          f"fixes alone {figures['lm_fixes']:.3f}")  # fmt: skip
    return figures


def run_synthetic(config: SimulationConfig) -> dict[str, float]:
    simulation = simulate(config)
    local = synthetic_local_slam(simulation, np.random.default_rng(config.seed))
    start = time.perf_counter()
    result = fuse(local.trajectory, local.landmarks, local.matched, local.fixes,
                  landmark_iterations=local.landmark_iterations)  # fmt: skip
    seconds = time.perf_counter() - start
    return report(f"synthetic local SLAM, seed {config.seed}", simulation, local.trajectory, local.landmarks,
                  local.landmark_iterations, result, seconds)  # fmt: skip


def run_estimator(name: str, config: SimulationConfig, in_loop: bool) -> dict[str, float]:
    """A real estimator as local SLAM: restarted per segment, and one continuous run split afterwards."""
    simulation = simulate(config)
    steps = list(simulation.steps())
    spec = ESTIMATORS[name]
    fixes = [s.fix for s in steps if s.fix is not None]
    label = {"ekf": "EKF", "relpoint": "Relative Point"}.get(name, name)

    def make() -> Estimator:
        # One noise for every restarted local map, known from its first step, as ``relpoint fuse
        # --restart`` does: an estimator that estimates it holds its first observations back, and
        # each fresh local map would end before it had matched anything.
        return spec.factory(spec.config_class(observation_sigma=config.noise), np.random.default_rng(0))

    def inputs():  # type: ignore[no-untyped-def]
        for s in steps:
            if s.fix is not None:
                yield s.fix
            yield s.observation

    # Algorithm 3 proper: a fresh local SLAM (local map) at every break, then fuse (``relpoint fuse --restart``).
    start, cpu = time.perf_counter(), time.process_time()
    segmented = run_segmented(inputs(), make)
    print(f"\n{label} restarted per segment: {len(segmented.trajectory)} iterations in "
          f"{time.perf_counter() - start:.1f} s wall, {time.process_time() - cpu:.1f} s CPU")  # fmt: skip
    start = time.perf_counter()
    result = fuse(segmented.trajectory, segmented.landmarks, None, segmented.fixes,
                  labels=segmented.labels, landmark_labels=segmented.landmark_labels)  # fmt: skip
    seconds = time.perf_counter() - start
    owners = _owners(segmented)
    figures = report(f"{label} local SLAM restarted per segment, seed {config.seed}", simulation,
                     segmented.trajectory, segmented.landmarks, owners, result, seconds)  # fmt: skip

    # The default post-step: one continuous run, split afterwards (``relpoint fuse``), with the piecewise-rigid
    # fit (default) and with one rigid fit per local map (``split_significance=0``, the post-step before it).
    start, cpu = time.perf_counter(), time.process_time()
    run = pipeline.run((s.observation for s in steps), make())
    print(f"\n{label} continuous: {len(run.trajectory)} iterations in {time.perf_counter() - start:.1f} s wall, "
          f"{time.process_time() - cpu:.1f} s CPU")  # fmt: skip
    matched = matched_counts_from_map_growth(run.observed, run.map_size)
    # Creation iteration of each landmark; a landmark the run's end added (its final adjustment) takes the last.
    owners = np.minimum(
        np.searchsorted(run.map_size, np.arange(len(run.landmarks)), side="right"), len(run.map_size) - 1
    )
    for suffix, fusion_config in (
        ("continuous", FusionConfig()),
        ("continuous_rigid", FusionConfig(split_significance=0.0)),
    ):
        start = time.perf_counter()
        continuous = fuse(run.trajectory, run.landmarks, matched, fixes, fusion_config, map_size=run.map_size)
        seconds = time.perf_counter() - start
        how = "piecewise-rigid" if fusion_config.split_significance else "one rigid fit per local map"
        post = report(f"{label} continuous run split afterwards ({how}), seed {config.seed}", simulation,
                      run.trajectory, run.landmarks, owners, continuous, seconds)  # fmt: skip
        figures |= {f"{k}_{suffix}": v for k, v in post.items() if k.endswith("fused")}

    if in_loop and name == "ekf":
        # The EKF fusing the fixes inside its filter; the start heading is unknown to it (a 1 rad prior).
        start = time.perf_counter()
        config_in_loop = spec.config_class(initial_orientation_sigma=1.0)
        fused_in_loop = pipeline.run(inputs(), spec.factory(config_in_loop, np.random.default_rng(0)))
        figures["ate_ekf_in_loop"] = ate(simulation.ground_truth, fused_in_loop.trajectory)
        figures["lm_ekf_in_loop"] = landmark_rmse(fused_in_loop.landmarks, simulation)
        print(f"\nEKF with the fixes fused in its loop (initial_orientation_sigma=1 rad, "
              f"{time.perf_counter() - start:.0f} s): ATE {figures['ate_ekf_in_loop']:.3f} m, "
              f"landmark RMSE {figures['lm_ekf_in_loop']:.3f} m")  # fmt: skip
    return figures


def _owners(segmented: SegmentedRun) -> np.ndarray:
    """Creation iteration of each landmark of a restarted run (rows appended per local map)."""
    owners = []
    for label in range(int(segmented.labels.max(initial=-1)) + 1):
        iterations = np.flatnonzero(segmented.labels == label)
        count = int(np.count_nonzero(segmented.landmark_labels == label))
        sizes = segmented.map_size[iterations]
        owners.append(iterations[np.minimum(np.searchsorted(sizes, np.arange(count), side="right"), len(sizes) - 1)])
    return np.concatenate(owners) if owners else np.zeros(0, dtype=np.int64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", choices=("synthetic", "ekf", "relpoint"), default="synthetic")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--density", type=float, default=25.0)
    parser.add_argument("--fix-every", type=int, default=10)
    parser.add_argument("--fix-noise", type=float, default=1.0)
    parser.add_argument("--in-loop", action="store_true", help="ekf: also run the EKF fusing the fixes itself")
    args = parser.parse_args()
    rows = []
    for seed in args.seeds:
        config = SimulationConfig(scenario="figure8-gaps", density=args.density, fix_every=args.fix_every,
                                  fix_noise=args.fix_noise, seed=seed)  # fmt: skip
        rows.append(
            run_synthetic(config) if args.source == "synthetic" else run_estimator(args.source, config, args.in_loop)
        )
    if len(rows) > 1:
        print("\nmean over seeds:", ", ".join(f"{k} {np.mean([r[k] for r in rows]):.3f}" for k in rows[0]))


if __name__ == "__main__":
    main()
