"""Speed and accuracy of the dense estimator (issue 6) beside open3d's peers, on real and simulated frames.

Real frames: the 7-Scenes redkitchen frames 0-399 in ``../shared/data`` (read from there, never copied
into the repository). For each method: SE(3)-aligned ATE (RMSE, metres) against the dataset's poses and
the median wall and CPU time per frame (``time.process_time``: all threads of the process, so a
multi-threaded peer's CPU time can exceed its wall time; a loaded machine inflates wall time more).
Ours is fed the 640x480 frames as ``relpoint run`` does (``downsample=2`` at 320x240, so its own 2x2
downsampling is timed); the peers get the already downsampled images (their downsampling is not timed).
Peers, run in the same process on the same depth:

- open3d tensor frame-to-frame ``t.pipelines.odometry.rgbd_odometry_multi_scale`` (point-to-plane);
- open3d dense ``t.pipelines.slam.Model`` (TSDF, frame-to-model, CPU), voxel 0.02 m at 320x240 and
  0.01 m at 640x480.

Simulated room (``relpoint.simulation.rgbd``): ATE and the map's accuracy/completeness against the scene.

Usage::

    python benchmarks/dense.py [--frames 400] [--resolution 320x240|640x480] [--no-peers]
                               [--sim-frames 150] [--threads 1]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "7scenes-redkitchen-0000-0399"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--resolution", default="320x240", choices=("320x240", "640x480"))
    parser.add_argument("--no-peers", action="store_true", help="skip open3d's odometry and SLAM")
    parser.add_argument("--sim-frames", type=int, default=150, help="simulated room frames (0 = skip)")
    parser.add_argument("--threads", type=int, default=1, help="BLAS threads (set before numpy loads)")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="DenseConfig setting")
    args = parser.parse_args(argv)
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = str(args.threads)

    import numpy as np
    from PIL import Image

    from relpoint.estimators.dense import DenseConfig, DenseFusion
    from relpoint.estimators.dense.maps import downsample_depth
    from relpoint.evaluation import EvaluationSettings, dense_metrics_to_mesh, evaluate_trajectory
    from relpoint.types import DepthFrame, Intrinsics, Trajectory

    factor = 2 if args.resolution == "320x240" else 1
    settings = EvaluationSettings(align="se3", rpe=False, kitti=False)

    def ate(reference: Trajectory, poses: list) -> float:
        estimate = Trajectory.from_matrices(reference.stamps_ns, np.array(poses))
        return evaluate_trajectory(reference, estimate, settings).summary["ate_rmse"]

    rows: list[tuple[str, float, float, str]] = []
    if DATA.exists():
        K = np.loadtxt(DATA / "camera-intrinsics.txt")
        full = Intrinsics(640, 480, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        depths_mm, colors, full_colors, truth = [], [], [], []
        for i in range(args.frames):
            with Image.open(DATA / f"frame-{i:06d}.depth.png") as image:
                raw = np.asarray(image).astype(np.float32)
            raw[raw >= 65535] = 0
            depths_mm.append(raw)
            with Image.open(DATA / f"frame-{i:06d}.color.jpg") as image:
                full_colors.append(np.asarray(image.convert("RGB")))
            colors.append(np.asarray(Image.fromarray(full_colors[-1]).resize((640 // factor, 480 // factor))))
            truth.append(np.loadtxt(DATA / f"frame-{i:06d}.pose.txt"))
        stamps = np.arange(args.frames, dtype=np.int64) * round(1e9 / 30)
        reference = Trajectory.from_matrices(stamps, np.array(truth))
        # The same downsampled depth for every method (2x2 block mean of valid pixels).
        depths = [downsample_depth(d * 1e-3) if factor == 2 else d * 1e-3 for d in depths_mm]
        k = Intrinsics(
            640 // factor, 480 // factor, full.fx / factor, full.fy / factor,
            (full.cx + 0.5) / factor - 0.5, (full.cy + 0.5) / factor - 0.5,
        )  # fmt: skip
        print(
            f"7-Scenes redkitchen frames 0-{args.frames - 1} at {k.width}x{k.height}; "
            f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores",
            flush=True,
        )

        estimator = DenseFusion(DenseConfig.from_strings(args.param, base={"downsample": factor}))
        wall, cpu, poses = [], [], []
        for i, raw in enumerate(depths_mm):
            frame = DepthFrame(int(stamps[i]), raw * np.float32(1e-3), full, full_colors[i])
            t0, c0 = time.perf_counter(), time.process_time()
            poses.append(estimator.step(frame).as_matrix())
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        summary = estimator.summary()
        ours_ms = np.median(wall) * 1e3
        ours_cpu_ms = np.median(cpu) * 1e3
        rows.append(
            (
                "relpoint dense (ours)", ate(reference, poses), ours_ms,
                f"cpu {np.median(cpu) * 1e3:.0f} ms, {1e3 / ours_ms:.1f} fps wall, {1 / np.median(cpu):.1f} fps cpu, "
                f"{summary['map_points']} points, compression {summary['compression_ratio']:.4f}, "
                f"lost {summary['lost_frames']}, {summary['icp_iterations_per_frame']:.1f} ICP iterations/frame",
            )
        )  # fmt: skip
        print(rows[-1], flush=True)

        if not args.no_peers:
            from relpoint._open3d import open3d

            o3d = open3d()
            o3c = o3d.core
            intr = o3c.Tensor(k.matrix(), o3c.Dtype.Float64)
            images = [o3d.t.geometry.Image(np.ascontiguousarray(np.rint(d * 1000).astype(np.uint16))) for d in depths]
            color_images = [o3d.t.geometry.Image(np.ascontiguousarray(c)) for c in colors]

            # Frame-to-frame multi-scale point-to-plane odometry.
            criteria = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(n) for n in (20, 10, 5)]
            T = np.eye(4)
            poses, wall, cpu = [T.copy()], [], []
            previous = o3d.t.geometry.RGBDImage(color_images[0], images[0])
            for i in range(1, len(images)):
                current = o3d.t.geometry.RGBDImage(color_images[i], images[i])
                t0, c0 = time.perf_counter(), time.process_time()
                result = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
                    current, previous, intr, o3c.Tensor(np.eye(4)), 1000.0, 3.0, criteria,
                    o3d.t.pipelines.odometry.Method.PointToPlane,
                )  # fmt: skip
                wall.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
                T = T @ result.transformation.numpy()
                poses.append(T.copy())
                previous = current
            rows.append(
                (
                    "open3d rgbd_odometry_multi_scale", ate(reference, poses), np.median(wall) * 1e3,
                    f"cpu {np.median(cpu) * 1e3:.0f} ms",
                )
            )  # fmt: skip
            print(rows[-1], flush=True)

            # Dense SLAM (TSDF voxel block grid, frame-to-model tracking), as open3d's dense_slam.py.
            voxel = 0.02 if factor == 2 else 0.01
            device = o3c.Device("CPU:0")
            T_frame_to_model = o3c.Tensor(np.identity(4))
            model = o3d.t.pipelines.slam.Model(voxel, 16, 40000, T_frame_to_model, device)
            input_frame = o3d.t.pipelines.slam.Frame(k.height, k.width, intr, device)
            raycast_frame = o3d.t.pipelines.slam.Frame(k.height, k.width, intr, device)
            poses, wall, cpu = [], [], []
            for i in range(len(images)):
                t0, c0 = time.perf_counter(), time.process_time()
                input_frame.set_data_from_image("depth", images[i])
                input_frame.set_data_from_image("color", color_images[i])
                if i > 0:
                    result = model.track_frame_to_model(input_frame, raycast_frame, 1000.0, 3.0, 0.07)
                    T_frame_to_model = T_frame_to_model @ result.transformation
                poses.append(T_frame_to_model.cpu().numpy())
                model.update_frame_pose(i, T_frame_to_model)
                model.integrate(input_frame, 1000.0, 3.0, 8.0)
                model.synthesize_model_frame(raycast_frame, 1000.0, 0.1, 3.0, 8.0, False)
                wall.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            slam_ms = np.median(wall) * 1e3
            slam_cpu_ms = np.median(cpu) * 1e3
            rows.append(
                (
                    f"open3d t.pipelines.slam.Model (voxel {voxel} m)", ate(reference, poses), slam_ms,
                    f"cpu {slam_cpu_ms:.0f} ms, {1e3 / slam_ms:.1f} fps wall",
                )
            )  # fmt: skip
            print(rows[-1], flush=True)
            rows.append(
                (
                    "ratio ours / open3d SLAM time per frame", float("nan"), ours_ms / slam_ms,
                    f"(wall); cpu ratio {ours_cpu_ms / slam_cpu_ms:.2f}",
                )
            )  # fmt: skip
    else:
        print(f"{DATA} is absent: real-frame figures skipped", file=sys.stderr)

    if args.sim_frames:
        from relpoint.simulation.rgbd import RgbdConfig, simulate_rgbd

        sim = simulate_rgbd(RgbdConfig(frames=args.sim_frames, resolution=args.resolution, seed=0))
        frames = list(sim.frames())
        estimator = DenseFusion(DenseConfig.from_strings(args.param))
        wall, cpu, poses = [], [], []
        for frame in frames:
            t0, c0 = time.perf_counter(), time.process_time()
            poses.append(estimator.step(frame))
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        result = evaluate_trajectory(sim.ground_truth, Trajectory.from_poses(poses), settings)
        positions, _, _, _ = estimator.dense_map()
        a = result.alignment
        aligned = a.scale * positions @ a.rotation.T + a.translation
        metrics = dense_metrics_to_mesh(
            aligned, sim.scene.vertices, sim.scene.triangles, np.random.default_rng(0), threshold=0.02
        )
        rows.append(
            (
                f"simulated room ({args.sim_frames} frames, Kinect-like noise)", result.summary["ate_rmse"],
                np.median(wall) * 1e3,
                f"cpu {np.median(cpu) * 1e3:.0f} ms; map accuracy median {metrics.accuracy_median * 1e3:.1f} mm, within 2 cm "
                f"{metrics.accuracy_within:.3f}; completeness within 2 cm {metrics.completeness_within:.3f} "
                "(of the whole room, most of which is never seen)",
            )
        )  # fmt: skip
        print(rows[-1], flush=True)

    print()
    print(f"{'method':<48} {'ATE (m)':>9} {'ms/frame':>9}  notes")
    for name, error, ms, notes in rows:
        print(f"{name:<48} {error:>9.4f} {ms:>9.1f}  {notes}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
