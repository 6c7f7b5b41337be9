"""In-loop fusion of position fixes in EKF-SLAM and FastSLAM versus the fixes alone and the local SLAM alone.

General Concept of 3D SLAM, sections 5-6 (issue 7), inside the filter: each estimator runs in its
local frame until at least three non-collinear fixes pin it, fits the rigid transform local -> fixes'
frame to its local positions and the Lagrange-interpolated fixes (eq. 26-30, section 6.3), moves its
state into that frame with the fit's uncertainty, then fuses every later fix as a position measurement
(eq. 31-32 as the Kalman update; FastSLAM: in each particle's proposal, and the fix likelihood in its
weight). See ``relpoint/estimators/_fix_frame.py``.

Scenario ``figure8-gaps`` (one pass, 996 iterations at 10 Hz, two landmark-free stretches, fixes every
10 iterations with 1 m noise per axis, start at (60, -40, -15) m and 35 deg heading in the fixes'
frame). Every figure is without alignment (the fixes define ``world``):

- *in-loop*: the estimator given the fixes (``fix_alignment="rigid"``, the default);
- *local alone*: the same estimator without fixes, in its own frame (the first pose at the identity);
- *fixes alone*: the fixes interpolated to every iteration (eq. 26-30).

ATE = RMSE of the position error over iterations; landmark RMSE over the mapped landmarks with a
ground-truth id. Times are per iteration, wall and CPU (``time.process_time``), with the load average.

With ``--figure8`` it measures instead the loop closure of issue 5's comparison: the figure eight
(density 25, noise 0.3 m, 900 iterations, no odometry, no fixes), where the simulated ``world`` is the
first true pose and every estimator starts there, so the errors are raw: position RMSE, final
landmark RMSE (landmarks matched by ``gt_id``), map entries against the distinct landmarks they
name (a duplicate is a failed re-association), and time per iteration.

Usage::

    .venv/bin/python benchmarks/in_loop_fusion.py                         # EKF and FastSLAM 2.0/1.0, seed 1
    .venv/bin/python benchmarks/in_loop_fusion.py --estimators ekf --seeds 1 2 3
    .venv/bin/python benchmarks/in_loop_fusion.py --angular-noise 0.1     # smoother motion prior
    .venv/bin/python benchmarks/in_loop_fusion.py --figure8                # FastSLAM loop closure
"""

from __future__ import annotations

import argparse
import os
import time

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import numpy as np  # noqa: E402

from relpoint import pipeline  # noqa: E402
from relpoint.estimators.ekf import EkfConfig, EkfSlam  # noqa: E402
from relpoint.estimators.fastslam import FastSlam, FastSlamConfig  # noqa: E402
from relpoint.evaluation import EvaluationSettings, evaluate_trajectory  # noqa: E402
from relpoint.lagrange import interpolate_fixes  # noqa: E402
from relpoint.simulation import Simulation, SimulationConfig, simulate  # noqa: E402
from relpoint.types import LandmarkMap, Trajectory  # noqa: E402

SETTINGS = EvaluationSettings(align="none", rpe=False, kitti=False)


def ate(reference: Trajectory, estimate: Trajectory) -> float:
    return float(evaluate_trajectory(reference, estimate, SETTINGS).summary["ate_rmse"])


def landmark_rmse(landmarks: LandmarkMap, simulation: Simulation) -> float:
    known = landmarks.gt_id >= 0
    truth = simulation.landmarks.positions[landmarks.gt_id[known]]
    return float(np.sqrt(np.mean(np.sum((landmarks.positions[known] - truth) ** 2, axis=1))))


#: Settings applied to every estimator (``--angular-noise``).
OVERRIDES: dict[str, float] = {}


def make(name: str, particles: int, seed: int) -> EkfSlam | FastSlam:
    if name == "ekf":
        return EkfSlam(EkfConfig(**OVERRIDES))
    variant = name.removeprefix("fastslam")
    return FastSlam(FastSlamConfig(variant=variant, particles=particles, **OVERRIDES), np.random.default_rng(seed))


def run(name: str, simulation: Simulation, with_fixes: bool, particles: int, seed: int) -> dict[str, float]:
    steps = list(simulation.steps())

    def inputs():  # type: ignore[no-untyped-def]
        for s in steps:
            if with_fixes and s.fix is not None:
                yield s.fix
            yield s.observation

    estimator = make(name, particles, seed)
    wall, cpu = time.perf_counter(), time.process_time()
    result = pipeline.run(inputs(), estimator)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    n = len(result.trajectory)
    summary = estimator.summary()
    return {
        "ate": ate(simulation.ground_truth, result.trajectory),
        "landmark_rmse": landmark_rmse(result.landmarks, simulation),
        "landmarks": len(result.landmarks),
        "ms_wall": 1e3 * wall / n,
        "ms_cpu": 1e3 * cpu / n,
        "pinned_at": summary.get("frame_pinned_at", -1),
    }


def fixes_alone(simulation: Simulation) -> float:
    fixes = [s.fix for s in simulation.steps() if s.fix is not None]
    truth = simulation.ground_truth
    positions, _ = interpolate_fixes(
        [f.stamp_ns for f in fixes], [f.position for f in fixes], [f.covariance for f in fixes], truth.stamps_ns
    )
    return ate(truth, Trajectory(truth.stamps_ns, positions, truth.quats_xyzw))


def figure8(name: str, seed: int, particles: int, rng_seed: int) -> None:
    """One figure-eight run without fixes: raw position and landmark errors, duplicates, time per iteration."""
    simulation = simulate(SimulationConfig(density=25, noise=0.3, iterations=900, seed=seed))
    estimator = make(name, particles, rng_seed)
    errors = []
    wall, cpu = time.perf_counter(), time.process_time()
    for step in simulation.steps():
        pose = estimator.step(step.observation)
        errors.append(np.linalg.norm(np.array(pose.position) - step.T_world_sensor[:3, 3]))
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    landmarks = estimator.landmark_map()
    n = len(errors)
    print(f"  {name:<13}{np.sqrt(np.mean(np.square(errors))):>10.3f}{errors[-1]:>9.3f}"
          f"{landmark_rmse(landmarks, simulation):>9.3f}{len(landmarks):>7d}{len(set(landmarks.gt_id.tolist())):>9d}"
          f"{1e3 * wall / n:>12.1f}{1e3 * cpu / n:>11.1f}", flush=True)  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--estimators", nargs="+", default=["ekf", "fastslam2.0", "fastslam1.0"],
                        choices=["ekf", "fastslam2.0", "fastslam1.0"])  # fmt: skip
    parser.add_argument("--seeds", type=int, nargs="+", default=[1])
    parser.add_argument("--particles", type=int, default=50)
    parser.add_argument("--iterations", type=int, default=None, help="default: one pass (996)")
    parser.add_argument("--no-local", action="store_true", help="skip the runs without fixes")
    parser.add_argument("--figure8", action="store_true", help="loop closure on the figure eight instead")
    parser.add_argument("--rng-seeds", type=int, nargs="+", default=[0], help="FastSLAM generator seeds")
    parser.add_argument("--angular-noise", type=float, default=None,
                        help="angular_acceleration_noise of the constant-velocity model (rad/s^2; default: from the log, 0.5 at 10 Hz)")  # fmt: skip
    args = parser.parse_args()
    if args.angular_noise is not None:
        OVERRIDES["angular_acceleration_noise"] = args.angular_noise
    if args.figure8:
        for seed in args.seeds:
            print(f"\nfigure8 seed {seed}, 900 iterations, no fixes (errors raw, m)")
            print(f"  {'estimator':<13}{'pos RMSE':>10}{'final':>9}{'lm RMSE':>9}{'map':>7}{'distinct':>9}"
                  f"{'ms/it wall':>12}{'ms/it cpu':>11}")  # fmt: skip
            for name in args.estimators:
                for rng_seed in args.rng_seeds if name != "ekf" else [0]:
                    figure8(name, seed, args.particles, rng_seed)
        print(f"\nload average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        return
    for seed in args.seeds:
        config = SimulationConfig(scenario="figure8-gaps", fix_every=10, seed=seed, iterations=args.iterations)
        simulation = simulate(config)
        print(f"\nfigure8-gaps seed {seed}: {len(simulation.ground_truth)} iterations; "
              f"fixes alone ATE {fixes_alone(simulation):.3f} m")  # fmt: skip
        print(f"  {'estimator':<13}{'mode':<13}{'ATE (m)':>9}{'lm RMSE (m)':>13}{'landmarks':>11}"
              f"{'ms/it wall':>12}{'ms/it cpu':>11}{'pinned at':>11}")  # fmt: skip
        for name in args.estimators:
            for with_fixes in (True,) if args.no_local else (True, False):
                figures = run(name, simulation, with_fixes, args.particles, seed)
                print(f"  {name:<13}{'in-loop' if with_fixes else 'local alone':<13}{figures['ate']:>9.3f}"
                      f"{figures['landmark_rmse']:>13.3f}{figures['landmarks']:>11d}{figures['ms_wall']:>12.1f}"
                      f"{figures['ms_cpu']:>11.1f}{figures['pinned_at']:>11d}", flush=True)  # fmt: skip
    print(f"\nload average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
