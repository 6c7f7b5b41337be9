"""Time per iteration of the EKF-SLAM estimator as its map grows (paper: Kraut, section IV).

The paper's MRPT 6D EKF reached about 1 s per iteration by iteration 900 on the figure eight at
density 25; the target for relpoint's EKF is 0.1 s or less there. Prints, per window of iterations,
the map size, state size and mean/max wall time of ``EkfSlam.step``, then the accuracy of the run.

Usage::

    python benchmarks/ekf_speed.py [--iterations 900] [--association nn|jcbb|known] [--threads 1]

BLAS is pinned to ``--threads`` (default 1) before numpy loads: on a shared machine OpenBLAS's
worker threads for these mid-sized products mostly wait for each other.
"""

from __future__ import annotations

import argparse
import os
import sys
import time


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=900)
    parser.add_argument("--density", type=float, default=25.0)
    parser.add_argument("--noise", type=float, default=0.3)
    parser.add_argument("--association", default="nn", choices=("nn", "jcbb", "known"))
    parser.add_argument("--window", type=int, default=100, help="iterations per printed row")
    parser.add_argument("--threads", type=int, default=1, help="BLAS threads (set before numpy loads)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = str(args.threads)

    import numpy as np

    from relpoint.estimators.ekf import EkfConfig, EkfSlam
    from relpoint.geometry import invert_pose, transform_points
    from relpoint.simulation import SimulationConfig, simulate

    sim = simulate(SimulationConfig(density=args.density, noise=args.noise, iterations=args.iterations, seed=args.seed))
    ekf = EkfSlam(EkfConfig(association=args.association))
    T_first_world = invert_pose(sim.ground_truth.matrices()[0])
    times: list[float] = []
    errors: list[float] = []
    print(f"EKF-SLAM, figure eight, density {args.density:g}, noise {args.noise:g}, association {args.association}, "
          f"BLAS threads {args.threads}")  # fmt: skip
    print(f"{'iterations':>12} {'landmarks':>9} {'state':>6} {'mean s/it':>10} {'max s/it':>9}")
    for step in sim.steps():
        start = time.perf_counter()
        pose = ekf.step(step.observation)
        times.append(time.perf_counter() - start)
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
