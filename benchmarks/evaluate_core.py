"""In-process timing of relpoint's APE (associate + Sim(3)/SE(3) Umeyama + statistics) against evo's.

A 20,000-pose pair: the paper's figure eight (40 passes) as reference at 100 Hz, and an estimate with
random-walk drift, noise, a rigid offset and a 2 ms stamp jitter, as a long simulated run would give.
Both libraries get the same trajectories in memory (file reading is not timed); the script prints the
best of ``--repeat`` runs of each and checks the figures agree.

    .venv/bin/python benchmarks/evaluate_core.py [--poses 20000] [--repeat 5] [--align se3]
"""

from __future__ import annotations

import argparse
import copy
import logging
import time

import numpy as np
from scipy.spatial.transform import Rotation

from relpoint.evaluation import EvaluationSettings, ape_errors, associate, error_statistics, evaluate_trajectory
from relpoint.evaluation.alignment import apply_alignment, estimate_alignment
from relpoint.simulation import paths
from relpoint.types import Trajectory


def make_pair(n: int, rng: np.random.Generator) -> tuple[Trajectory, Trajectory]:
    stamps = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 10_000_000
    positions, tangents = paths.figure8(np.linspace(0.0, 40.0, n, endpoint=False), radius=20.0, climb=2.0)
    quats = Rotation.from_matrix(paths.orientations_from_tangents(tangents)).as_quat()
    reference = Trajectory(stamps, positions, quats)
    drift = np.cumsum(rng.normal(scale=2e-3, size=(n, 3)), axis=0)
    offset = Rotation.from_rotvec([0.02, -0.01, 0.3])
    est_positions = offset.apply(positions + drift + rng.normal(scale=0.01, size=(n, 3))) + np.array([1.0, -2.0, 0.5])
    est_quats = (
        offset * Rotation.from_quat(quats) * Rotation.from_rotvec(rng.normal(scale=0.005, size=(n, 3)))
    ).as_quat()
    jitter = rng.integers(-2_000_000, 2_000_000, size=n)
    return reference, Trajectory(stamps + jitter, est_positions, est_quats)


def to_evo(trajectory: Trajectory):
    from evo.core.trajectory import PoseTrajectory3D

    stamps = np.array([s / 1_000_000_000 for s in trajectory.stamps_ns.tolist()])
    return PoseTrajectory3D(np.array(trajectory.positions), np.roll(trajectory.quats_xyzw, 1, axis=1), stamps)


def relpoint_ape(reference: Trajectory, estimate: Trajectory, align: str) -> dict[str, float]:
    matched = associate(reference, estimate)
    aligned = apply_alignment(matched, estimate_alignment(matched, align))
    return error_statistics(ape_errors(aligned, "trans_part"))


def evo_ape(evo_ref, evo_est, align: str) -> dict[str, float]:
    from evo.core import metrics, sync
    from evo.main_ape import ape

    ref, est = sync.associate_trajectories(evo_ref, evo_est)
    result = ape(
        ref, est, metrics.PoseRelation.translation_part, align=align in ("se3", "sim3"), correct_scale=align == "sim3"
    )
    return result.stats


def best_time(fn, repeat: int) -> tuple[float, dict[str, float]]:
    best, out = float("inf"), {}
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--poses", type=int, default=20_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--align", choices=["none", "se3", "sim3"], default="se3")
    args = parser.parse_args()
    logging.getLogger("evo").setLevel(logging.ERROR)

    reference, estimate = make_pair(args.poses, np.random.default_rng(0))
    evo_ref, evo_est = to_evo(reference), to_evo(estimate)

    t_ours, ours = best_time(lambda: relpoint_ape(reference, estimate, args.align), args.repeat)
    t_evo, theirs = best_time(lambda: evo_ape(copy.deepcopy(evo_ref), copy.deepcopy(evo_est), args.align), args.repeat)
    t_full, full = best_time(
        lambda: evaluate_trajectory(reference, estimate, EvaluationSettings(align=args.align)).summary, args.repeat
    )

    print(f"{args.poses} poses, align {args.align}, best of {args.repeat}")
    print(f"relpoint APE          {t_ours * 1e3:9.1f} ms")
    print(f"evo APE               {t_evo * 1e3:9.1f} ms   (relpoint {t_evo / t_ours:.1f}x faster)")
    print(f"relpoint evaluate_trajectory (APE trans+rot, RPE trans+rot, KITTI) {t_full * 1e3:.1f} ms")
    print(f"{'statistic':>10} {'relpoint':>14} {'evo':>14} {'|diff|':>10}")
    worst = 0.0
    for name in ("rmse", "mean", "median", "std", "min", "max", "sse"):
        diff = abs(ours[name] - theirs[name])
        worst = max(worst, diff / max(abs(theirs[name]), 1e-300))
        print(f"{name:>10} {ours[name]:14.9f} {theirs[name]:14.9f} {diff:10.2e}")
    assert full["ate_rmse"] == ours["rmse"]
    print(
        f"same numbers: {'yes' if worst < 1e-9 else 'NO'} (max relative difference {worst:.1e}); "
        f"matched poses {int(full['matched_poses'])}"
    )


if __name__ == "__main__":
    main()
