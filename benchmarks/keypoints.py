"""The point estimators on real keypoints (issue 16): 7-Scenes redkitchen frames 0-399, and Starry Night.

Real keypoints: the frames in ``../shared/data/7scenes-redkitchen-0000-0399`` are imported as
``relpoint import 7scenes ... --points`` does (corners tracked with Lucas-Kanade, back-projected with
their depth; read from there, never copied into the repository). Printed:

- points per frame, track lengths;
- the observation noise measured against the dataset's poses: each track's world positions (points
  mapped by the reference pose of their frame) scatter about their median; the per-axis sigma is the
  robust (1.4826 MAD) spread of that scatter, overall and by depth;
- the noise each estimator estimates from the log itself (``observation_sigma``, first iterations);
- SE(3)-aligned ATE (RMSE, m) and median time per frame of relpoint, ekf and fastslam with their default
  settings and with the settings passed as ``--best-*`` (the best found by hand, see docs/keypoints.md),
  beside a **reference**: a plain frame-to-map rigid fit that is given the true track ids (RANSAC over
  three-point samples, then Kabsch on the inliers, against the mean world position of each id so far);
- the share of the static kitchen that Relative Point flags dynamic, and how many points each of its
  tests flagged.

Starry Night (``../shared/data/starry-night``, with its odometry as ``relpoint run`` uses it): ATE of
the three point estimators with the default settings; ``--scale-free off`` runs them with the noise fixed at the simulator's 0.3 m (the settings
before the scale-free defaults) for the before/after comparison.

Usage::

    python benchmarks/keypoints.py [--frames 400] [--estimators relpoint,ekf,fastslam] [--ekf-frames 100]
        [--fastslam-frames 100] [--stride 1]
        [--best-relpoint K=V,...] [--best-ekf K=V,...] [--best-fastslam K=V,...] [--starry] [--scale-free on|off]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
KITCHEN = DATA / "7scenes-redkitchen-0000-0399"
STARRY = DATA / "starry-night"


def keypoint_log(frames: int, directory: Path) -> Path:
    """Import the kitchen frames as point observations (as ``relpoint import 7scenes --points``)."""
    import hashlib

    from formats.rgbd_import import seven_scenes_frames
    from relpoint.frontend.tracking import KeypointSettings
    from relpoint_app.keypoint_import import write_keypoint_log

    settings = hashlib.sha256(repr(KeypointSettings()).encode()).hexdigest()[:8]  # a new front-end, a new log
    path = directory / f"kitchen_points_{frames}_{settings}.mcap"
    if not path.exists():
        started = time.perf_counter()
        counts = write_keypoint_log(seven_scenes_frames(KITCHEN, count=frames), path, source={"layout": "7scenes"})
        elapsed = time.perf_counter() - started
        print(f"import: {counts.frames} frames in {elapsed:.1f} s ({1000 * elapsed / counts.frames:.1f} ms/frame)")
    return path


def read_log(path: Path, odometry: bool = False) -> tuple[list, object]:
    """The log's observations (with its odometry, in order, if asked) and its ground-truth trajectory."""
    from formats.log import LogReader
    from relpoint.types import Trajectory

    records = list(LogReader(path).records(["points", "ground_truth_pose", *(["odometry"] if odometry else [])]))
    observations = [r.value for r in records if r.role in ("points", "odometry")]
    truth = Trajectory.from_poses([r.value for r in records if r.role == "ground_truth_pose"])
    return observations, truth


def track_statistics(observations: list, truth: object) -> dict[str, float]:
    """Points per frame, track lengths and the per-axis noise of the points against the reference poses."""
    import numpy as np

    T_world = dict(zip(truth.stamps_ns.tolist(), truth.matrices(), strict=True))
    world: dict[int, list] = {}
    depth: dict[int, list] = {}
    for observation in observations:
        T = T_world[observation.stamp_ns]
        mapped = observation.points @ T[:3, :3].T + T[:3, 3]
        for track, point, z in zip(observation.ids.tolist(), mapped, observation.points[:, 2], strict=True):
            world.setdefault(track, []).append(point)
            depth.setdefault(track, []).append(z)
    lengths = np.array([len(v) for v in world.values()])
    residuals, depths = [], []
    for track, points in world.items():
        if len(points) >= 5:
            points = np.array(points)
            residuals.append(points - np.median(points, axis=0))
            depths.append(np.array(depth[track]))
    residual, z = np.concatenate(residuals), np.concatenate(depths)

    def sigma(r: np.ndarray) -> float:
        return float(1.4826 * np.median(np.abs(r - np.median(r, axis=0))))

    per_frame = np.array([len(o) for o in observations])
    figures = {
        "points_per_frame_mean": float(per_frame.mean()), "points_per_frame_min": float(per_frame.min()),
        "points_per_frame_max": float(per_frame.max()), "tracks": float(len(lengths)),
        "track_length_mean": float(lengths.mean()), "track_length_median": float(np.median(lengths)),
        "track_length_p90": float(np.percentile(lengths, 90)), "track_length_max": float(lengths.max()),
        "noise_sigma_per_axis": sigma(residual),
        "residual_p90_m": float(np.percentile(np.linalg.norm(residual, axis=1), 90)),
    }  # fmt: skip
    for low, high in ((0.5, 1.0), (1.0, 2.0), (2.0, 3.0), (3.0, 4.0)):
        band = (z >= low) & (z < high)
        if band.sum() > 50:
            figures[f"noise_sigma_{low:g}_{high:g}m"] = sigma(residual[band])
    return figures


def track_scatter(observations: list, truth: object) -> dict[int, float]:
    """RMS distance (m) of each track's world points (mapped by the reference poses) from their median:
    how far the front-end's point for one corner wanders (tracks seen at least 5 times)."""
    import numpy as np

    T_world = dict(zip(truth.stamps_ns.tolist(), truth.matrices(), strict=True))
    world: dict[int, list] = {}
    for observation in observations:
        T = T_world[observation.stamp_ns]
        for track, point in zip(observation.ids.tolist(), observation.points @ T[:3, :3].T + T[:3, 3], strict=True):
            world.setdefault(track, []).append(point)
    return {
        track: float(np.sqrt(np.mean(np.sum((np.array(p) - np.median(p, axis=0)) ** 2, axis=1))))
        for track, p in world.items()
        if len(p) >= 5
    }


def kabsch(source, target):  # type: ignore[no-untyped-def]
    """The rigid transform (4x4) that best maps ``source`` (N, 3) onto ``target`` (least squares)."""
    import numpy as np

    cs, ct = source.mean(axis=0), target.mean(axis=0)
    U, _, Vt = np.linalg.svd((source - cs).T @ (target - ct))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, ct - R @ cs
    return T


def reference_fit(observations: list, inlier_m: float = 0.05, samples: int = 200, seed: int = 0) -> object:
    """Frame-to-map rigid fit given the true track ids: each frame is fitted (RANSAC + Kabsch) against the
    mean world position of each id seen so far; the first frame is the identity."""
    import numpy as np

    from relpoint.types import Trajectory

    rng = np.random.default_rng(seed)
    sums: dict[int, np.ndarray] = {}
    counts: dict[int, int] = {}
    T = np.eye(4)
    poses = []
    for observation in observations:
        ids = observation.ids.tolist()
        known = [k for k, i in enumerate(ids) if i in sums]
        if len(known) >= 3:
            source = observation.points[known]
            target = np.array([sums[ids[k]] / counts[ids[k]] for k in known])
            best = np.zeros(len(known), dtype=bool)
            for _ in range(samples):
                pick = rng.choice(len(known), 3, replace=False)
                candidate = kabsch(source[pick], target[pick])
                inliers = np.linalg.norm(source @ candidate[:3, :3].T + candidate[:3, 3] - target, axis=1) < inlier_m
                if inliers.sum() > best.sum():
                    best = inliers
            if best.sum() >= 3:
                T = kabsch(source[best], target[best])
        poses.append(T.copy())
        mapped = observation.points @ T[:3, :3].T + T[:3, 3]
        for i, point in zip(ids, mapped, strict=True):
            sums[i] = sums.get(i, 0.0) + point
            counts[i] = counts.get(i, 0) + 1
    return Trajectory.from_matrices([o.stamp_ns for o in observations], np.array(poses))


def run_estimator(name: str, observations: list, params: dict[str, object], seed: int = 0) -> tuple[object, object]:
    """(RunResult, config) of estimator ``name`` over ``observations``."""
    import numpy as np

    from relpoint.estimators import ESTIMATORS
    from relpoint.pipeline import run

    spec = ESTIMATORS[name]
    config = spec.build_config(params)
    estimator = spec.factory(config, np.random.default_rng(seed))
    return run(observations, estimator), config


def ate(truth: object, trajectory: object) -> float:
    from relpoint.evaluation import EvaluationSettings, evaluate_trajectory

    result = evaluate_trajectory(truth, trajectory, EvaluationSettings(align="se3", rpe=False, kitti=False))
    return float(result.summary["ate_rmse"])


def parse_params(name: str, text: str) -> dict[str, object]:
    """The ``K=V,...`` settings of estimator ``name``, each value read as its setting's kind."""
    from relpoint.estimators import ESTIMATORS
    from relpoint.settings import split_item

    config_class = ESTIMATORS[name].config_class
    pairs = [split_item(item, "--best-" + name) for item in text.split(",") if item]
    return {key: config_class.parse_text(key, value) for key, value in pairs}


def report_runs(
    label: str, observations: list, truth: object, runs: list[tuple[str, str, dict]],
    scatter: dict[int, float] | None = None,
) -> None:
    """ATE, time per frame, noise used and the share of landmarks flagged dynamic of each run; with
    ``scatter`` (:func:`track_scatter`), also that share among the landmarks of well-tracked corners
    (scatter at most 2 cm, 1.7 times the per-axis noise in 3D) and of badly tracked ones (over 5 cm)."""
    import numpy as np

    print(f"\n{label}")
    print(f"{'estimator':10} {'settings':10} {'ATE m':>8} {'ms/frame':>9} {'noise m':>8} {'dynamic':>8}  parameters")
    for name, kind, params in runs:
        result, _ = run_estimator(name, observations, params)
        summary = result.summary
        landmarks = result.landmarks
        flagged = float(np.mean(landmarks.dynamic)) if len(landmarks) and landmarks.dynamic is not None else 0.0
        noise = summary.get("observation_sigma") or params.get("observation_sigma") or float("nan")
        print(f"{name:10} {kind:10} {ate(truth, result.trajectory):8.4f} {1000 * np.median(result.seconds):9.2f} "
              f"{noise:8.4f} {flagged:8.1%}  {params or ''}", flush=True)  # fmt: skip
        witnesses = {key[len("dynamic_by_"):]: value for key, value in summary.items() if key.startswith("dynamic_by_")}
        if witnesses:
            print(f"{'':21} points flagged by test: {witnesses}", flush=True)
        if scatter and len(landmarks) and landmarks.dynamic is not None and landmarks.gt_id is not None:
            spread = np.array([scatter.get(int(i), np.nan) for i in landmarks.gt_id])
            good, bad = spread <= 0.02, spread > 0.05
            print(f"{'':21} flagged dynamic: {np.mean(landmarks.dynamic[good]):.1%} of {good.sum()} landmarks of "
                  f"well-tracked corners (scatter <= 2 cm), {np.mean(landmarks.dynamic[bad]):.1%} of {bad.sum()} "
                  f"of badly tracked ones (> 5 cm)", flush=True)  # fmt: skip
            static_ids = set(landmarks.gt_id[~landmarks.dynamic].tolist())
            dynamic_ids = set(landmarks.gt_id[landmarks.dynamic].tolist()) - static_ids
            for label, tracks in (("well-tracked", [t for t, v in scatter.items() if v <= 0.02]),
                                  ("badly tracked", [t for t, v in scatter.items() if v > 0.05])):  # fmt: skip
                mapped_static = np.mean([t in static_ids for t in tracks])
                mapped_dynamic = np.mean([t in dynamic_ids for t in tracks])
                print(f"{'':21} of the {len(tracks)} {label} corners seen 5 times or more: {mapped_static:.1%} mapped "
                      f"static, {mapped_dynamic:.1%} dynamic, {1 - mapped_static - mapped_dynamic:.1%} not in the map",
                      flush=True)  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--estimators", default="relpoint,ekf,fastslam")
    parser.add_argument("--fastslam-frames", type=int, default=100, help="FastSLAM is slow on thousands of landmarks")
    parser.add_argument("--ekf-frames", type=int, default=100,
                        help="the EKF's joint covariance grows with the square of the landmarks (about 500 by "
                        "frame 100, thousands by frame 400)")
    parser.add_argument("--best-relpoint", default="", metavar="K=V,...")
    parser.add_argument("--best-ekf", default="", metavar="K=V,...")
    parser.add_argument("--best-fastslam", default="", metavar="K=V,...")
    parser.add_argument("--starry", action="store_true", help="also run Starry Night")
    parser.add_argument("--no-kitchen", action="store_true")
    parser.add_argument("--scale-free", default="on", choices=("on", "off"),
                        help="off: fix the observation noise at the simulator's 0.3 m (the settings before)")
    parser.add_argument("--stride", type=int, default=1, help="keep every N-th frame (faster motion per frame)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()), help="where the imported log is kept")
    args = parser.parse_args(argv)
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = str(args.threads)
    sys.path.insert(0, str(REPO))
    names = [n for n in args.estimators.split(",") if n]
    fixed = {"observation_sigma": 0.3} if args.scale_free == "off" else {}
    best = {"relpoint": parse_params("relpoint", args.best_relpoint), "ekf": parse_params("ekf", args.best_ekf),
            "fastslam": parse_params("fastslam", args.best_fastslam)}  # fmt: skip

    if not args.no_kitchen:
        if not KITCHEN.is_dir():
            print(f"{KITCHEN.name} is not in the shared data; skipped")
        else:
            observations, truth = read_log(keypoint_log(args.frames, args.cache))
            observations = observations[:: args.stride]
            stats = track_statistics(observations, truth)
            print(f"7-Scenes redkitchen, {len(observations)} frames")
            for key, value in stats.items():
                print(f"  {key:28} {value:10.4f}")
            started = time.perf_counter()
            reference = reference_fit(observations)
            elapsed = time.perf_counter() - started
            print(f"\nreference frame-to-map fit (true ids, RANSAC + Kabsch): ATE {ate(truth, reference):.4f} m, "
                  f"{1000 * elapsed / len(observations):.2f} ms/frame")  # fmt: skip
            runs = []
            for name in names:
                cap = {"fastslam": args.fastslam_frames, "ekf": args.ekf_frames}.get(name, len(observations))
                frames = min(cap, len(observations))
                subset = observations[:frames]
                if frames < len(observations):
                    print(f"{name}: first {frames} frames only; the reference fit scores "
                          f"{ate(truth, reference_fit(subset)):.4f} m there")  # fmt: skip
                runs = [(name, "default", dict(fixed))]
                if best[name]:
                    runs.append((name, "best", best[name]))
                report_runs(f"{name} on {frames} frames", subset, truth, runs, track_scatter(subset, truth))
    if args.starry:
        if not STARRY.is_dir():
            print(f"{STARRY.name} is not in the shared data; skipped")
        else:
            logs = sorted(STARRY.glob("*.mcap"))
            observations, truth = read_log(logs[0], odometry=True)
            runs = [(name, "default" if not fixed else "noise 0.3", dict(fixed)) for name in names]
            report_runs(f"Starry Night {logs[0].name}, {len(observations)} inputs", observations, truth, runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
