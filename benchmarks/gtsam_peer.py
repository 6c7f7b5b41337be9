"""GTSAM peers for ``benchmarks/compare.py``: iSAM2 as the modern online estimator, Levenberg-Marquardt batch.

Issue 5 asks for GTSAM's iSAM2 (Kaess et al., *iSAM2: Incremental smoothing and mapping using the Bayes
tree*, IJRR 2012) as the online peer of Relative Point, EKF-SLAM and FastSLAM on the same simulated
logs, and for GTSAM's Levenberg-Marquardt batch solution as the accuracy limit (here a cross-check of
``compare.py``'s own scipy Gauss-Newton limit). gtsam is an optional benchmark dependency
(``pip install gtsam``; measured with gtsam 4.3.0): :func:`available` tells whether it imports.

Factor graph, per simulated step ``k`` (true association from the observation's ``ids``):

* pose ``x_k`` = ``T_world_sensor`` (gtsam ``Pose3``); ``x_0`` has a tight prior at the identity (the
  simulated world is the first true sensor pose, so errors are raw, without alignment);
* ``x_{k-1} -> x_k``: a weak constant-position ``BetweenFactorPose3`` (identity, sigma 10 m per axis
  and 1 rad per axis by default; the true motion is ~1.2 m and a few degrees per step, so this is a
  regulariser for steps with few points, not a motion model);
* each observed point ``z`` (sensor frame, metres) of landmark ``l_id``: one of two pose-to-point
  factors (gtsam's Python API has no Cartesian pose-to-point factor):

  - ``bearing_range`` (default; native C++, so timings are gtsam's own): ``BearingRangeFactor3D`` with
    the measured ``Unit3`` bearing and range of ``z``. The simulated noise is isotropic Cartesian,
    ``sigma`` per axis; to first order its component along the ray is the range error (``sigma``) and
    its two components across the ray are bearing errors of ``sigma / |z|`` radians in the ``Unit3``
    tangent plane, so the noise model is diagonal ``(sigma/|z|, sigma/|z|, sigma)`` (exact to first
    order in ``sigma / |z|``; |z| is 7-70 m here);
  - ``cartesian``: a ``CustomFactor`` with the residual ``x_k^-1 * l - z`` and isotropic ``sigma``,
    exactly the simulated model and the scipy batch's cost, but each linearisation calls Python, so its
    timings measure the binding, not gtsam.

* Initial values: the new pose from a rigid fit (Umeyama, :func:`relpoint.geometry.fit_rigid`) of the
  step's points onto the current estimates of their already-mapped landmarks (three or more), else the
  previous pose; a new landmark at the new pose times its point. This front end is timed with the update.

iSAM2 settings: gtsam's defaults (Gauss-Newton, ``relinearizeThreshold`` 0.1, ``relinearizeSkip`` 10).
On the figure eight they reach the bearing-range batch optimum (landmark RMSE 0.4527 m, like LM's) at a
median 1.2 ms per update; relinearising every update above 0.01 gives the same errors at ~13 ms CPU. Times recorded per step: the whole step
(front end, ``update``, the new pose's estimate; what ``Estimator.step`` is timed on) and ``update`` alone,
both wall and CPU (``time.process_time``).

Usage (standalone; ``compare.py`` runs it as the ``isam2`` column)::

    python benchmarks/gtsam_peer.py [--scenario figure8] [--iterations 900] [--factor bearing_range]
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import numpy as np

try:  # optional benchmark dependency
    import gtsam
except ImportError as error:  # pragma: no cover - depends on the environment
    gtsam = None
    _IMPORT_ERROR = f"{type(error).__name__}: {error}"
else:
    _IMPORT_ERROR = ""

FACTORS = ("bearing_range", "cartesian")


def available() -> tuple[bool, str]:
    """Whether gtsam imports, and a one-line message saying so (with its version or the import error)."""
    if gtsam is None:
        return False, f"gtsam is not importable ({_IMPORT_ERROR}); install it with `pip install gtsam` (>=4.2)"
    return True, f"gtsam {version()}"


def version() -> str:
    """The installed gtsam's version (from the package metadata), or ``"absent"``."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as package_version

    try:
        return package_version("gtsam")
    except PackageNotFoundError:
        return "absent"


def _x(k: int) -> int:
    return gtsam.symbol("x", k)


def _l(i: int) -> int:
    return gtsam.symbol("l", i)


def cartesian_factor(pose_key: int, point_key: int, z: np.ndarray, model: Any) -> Any:
    """A ``CustomFactor`` with residual ``T_world_sensor^-1 * l - z`` (3,), metres, whitened by ``model``."""

    def error(this: Any, values: Any, jacobians: list[np.ndarray] | None) -> np.ndarray:
        pose = values.atPose3(this.keys()[0])
        point = values.atPoint3(this.keys()[1])
        if jacobians is None:
            return pose.transformTo(point) - z
        H_pose = np.zeros((3, 6), order="F")
        H_point = np.zeros((3, 3), order="F")
        predicted = pose.transformTo(point, H_pose, H_point)
        jacobians[0] = H_pose
        jacobians[1] = H_point
        return predicted - z

    return gtsam.CustomFactor(model, [pose_key, point_key], error)


def observation_factors(
    pose_key: int, ids: np.ndarray, points: np.ndarray, sigma: float, kind: str, huber: float = 0.0
) -> list[Any]:
    """Pose-to-point factors of one step's observations (see the module docstring for the two kinds).

    Parameters
    ----------
    pose_key: gtsam key of the sensor pose ``T_world_sensor``.
    ids: (N,) true landmark ids.
    points: (N, 3) observed points in the sensor frame (metres).
    sigma: observation noise per Cartesian axis (metres).
    kind: ``"bearing_range"`` or ``"cartesian"``.
    huber: if > 0, wrap the noise model in a Huber kernel with this threshold (whitened units).
    """

    def robust(model: Any) -> Any:
        if huber <= 0:
            return model
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber), model)

    factors = []
    if kind == "cartesian":
        model = robust(gtsam.noiseModel.Isotropic.Sigma(3, sigma))
        for i, z in zip(ids, points, strict=True):
            factors.append(cartesian_factor(pose_key, _l(int(i)), np.asarray(z, dtype=np.float64), model))
        return factors
    if kind != "bearing_range":
        raise ValueError(f"unknown factor kind {kind!r}; choose from {FACTORS}")
    ranges = np.linalg.norm(points, axis=1)
    for i, z, r in zip(ids, points, ranges, strict=True):
        model = robust(gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma / r, sigma / r, sigma])))
        factors.append(gtsam.BearingRangeFactor3D(pose_key, _l(int(i)), gtsam.Unit3(z / r), float(r), model))
    return factors


def _usable(observation: Any, static: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The ids and points of one observation with a true id (and, if ``static`` is given, a static one)."""
    if observation.ids is None:
        raise ValueError("the iSAM2 peer needs the observations' ids (true association)")
    ids = np.asarray(observation.ids, dtype=np.int64)
    keep = ids >= 0
    if static is not None:
        keep[keep] &= static[ids[keep]]
    return ids[keep], np.asarray(observation.points, dtype=np.float64)[keep]


def run_isam2(
    sim: Any,
    sigma: float,
    *,
    every: int = 10,
    kind: str = "bearing_range",
    prior_sigmas: tuple[float, float] = (1.0, 10.0),
    static_only: bool = False,
    huber: float = 0.0,
    relinearize_threshold: float = 0.1,
    relinearize_skip: int = 10,
) -> dict[str, Any]:
    """Run iSAM2 over a simulation, one update per step, with true association.

    Parameters
    ----------
    sim: a :class:`relpoint.simulation.Simulation` (observations with ``ids``).
    sigma: observation noise per Cartesian axis (metres), the simulation's ``noise``.
    every: record the landmark error every that many steps (and after the last).
    kind: pose-to-point factor, ``"bearing_range"`` or ``"cartesian"``.
    prior_sigmas: (rotation rad, translation m) per axis of the constant-position between-pose factor.
    static_only: drop observations of moving landmarks (an oracle the other estimators lack); by default
        they enter the graph as if static, like every observation with a true id.
    huber: if > 0, a Huber kernel of this threshold (whitened units) on the observation factors.
    relinearize_threshold, relinearize_skip: iSAM2's (gtsam's defaults are 0.1 and 10).

    Returns
    -------
    A dict shaped like ``compare.run_estimator``'s: ``error`` (n, 3) online position error (estimate of
    ``x_k`` right after update ``k`` minus truth), ``lm_rmse``/``lm_matched`` (n,) every ``every`` steps,
    ``seconds`` (n,) whole-step wall time, ``update_seconds``/``update_cpu`` (n,) ``ISAM2.update`` wall
    and CPU time, ``map_size``/``observed`` (n,), and ``smoothed_error`` (n, 3) of the final estimate.
    """
    from relpoint.evaluation import landmark_metrics
    from relpoint.geometry import fit_rigid
    from relpoint.types import LandmarkMap

    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(relinearize_threshold)
    params.relinearizeSkip = relinearize_skip
    isam = gtsam.ISAM2(params)
    between_model = gtsam.noiseModel.Diagonal.Sigmas(np.array([prior_sigmas[0]] * 3 + [prior_sigmas[1]] * 3))
    first_model = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    static = ~np.asarray(sim.landmarks.dynamic) if static_only else None

    truth = sim.ground_truth.positions
    n = len(sim)
    positions = np.full((n, 3), np.nan)
    lm_rmse = np.full(n, np.nan)
    lm_matched = np.zeros(n, dtype=np.int64)
    seconds = np.zeros(n)
    cpu = np.zeros(n)
    update_seconds = np.zeros(n)
    update_cpu = np.zeros(n)
    map_size = np.zeros(n, dtype=np.int64)
    observed = np.zeros(n, dtype=np.int64)
    landmarks: dict[int, np.ndarray] = {}  # current estimates of the mapped landmarks (world, metres)
    counts: dict[int, int] = {}
    previous = gtsam.Pose3()
    for step in sim.steps():
        k = step.index
        ids, points = _usable(step.observation, static)
        start, start_cpu = time.perf_counter(), time.process_time()
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        known = np.array([int(i) in landmarks for i in ids], dtype=bool)
        if k == 0:
            pose = gtsam.Pose3()
            graph.add(gtsam.PriorFactorPose3(_x(0), pose, first_model))
        else:
            pose = previous
            if known.sum() >= 3:
                fit = fit_rigid(points[known], np.array([landmarks[int(i)] for i in ids[known]]))
                pose = gtsam.Pose3(gtsam.Rot3(fit.rotation), fit.translation)
            graph.add(gtsam.BetweenFactorPose3(_x(k - 1), _x(k), gtsam.Pose3(), between_model))
        values.insert(_x(k), pose)
        for i, z in zip(ids[~known], points[~known], strict=True):
            values.insert(_l(int(i)), pose.transformFrom(z))
        for factor in observation_factors(_x(k), ids, points, sigma, kind, huber):
            graph.add(factor)
        u_start, u_cpu = time.perf_counter(), time.process_time()
        isam.update(graph, values)
        update_seconds[k], update_cpu[k] = time.perf_counter() - u_start, time.process_time() - u_cpu
        estimate = isam.calculateEstimatePose3(_x(k))
        seconds[k], cpu[k] = time.perf_counter() - start, time.process_time() - start_cpu
        previous = estimate
        positions[k] = estimate.translation()
        for i in ids:
            counts[int(i)] = counts.get(int(i), 0) + 1
        # Bookkeeping for the front end's next fit (untimed): the full current estimate of the landmarks
        # only at the error checkpoints, else the new ones plus those seen now, which iSAM2 just moved.
        if (k + 1) % every == 0 or k == n - 1:
            current = isam.calculateEstimate()
            for i in landmarks.keys() | {int(i) for i in ids}:
                landmarks[i] = current.atPoint3(_l(i))
            order = np.array(sorted(landmarks), dtype=np.int64)
            estimated = LandmarkMap(
                positions=np.array([landmarks[int(i)] for i in order]).reshape(-1, 3),
                observations=np.array([counts[int(i)] for i in order], dtype=np.int64),
                dynamic=np.zeros(len(order), dtype=bool),
                gt_id=order,
            )
            summary = landmark_metrics(estimated, sim.landmarks).summary
            lm_rmse[k], lm_matched[k] = summary["lm_err_rmse"], int(summary["lm_matched"])
        else:
            for i in ids:
                landmarks[int(i)] = isam.calculateEstimatePoint3(_l(int(i)))
        map_size[k] = len(landmarks)
        observed[k] = len(step.observation.points)

    final = isam.calculateEstimate()
    smoothed = np.array([final.atPose3(_x(k)).translation() for k in range(n)])
    return {
        "error": positions - truth,
        "smoothed_error": smoothed - truth,
        "lm_rmse": lm_rmse,
        "lm_matched": lm_matched,
        "seconds": seconds,
        "cpu_seconds": cpu,
        "update_seconds": update_seconds,
        "update_cpu": update_cpu,
        "map_size": map_size,
        "observed": observed,
        "summary": {"gtsam": version(), "factor": kind, "static_only": static_only, "huber": huber},
    }


def batch_lm(
    poses: np.ndarray,
    landmarks: np.ndarray,
    pose_idx: np.ndarray,
    lm_idx: np.ndarray,
    z: np.ndarray,
    sigma: float,
    kind: str = "cartesian",
) -> tuple[np.ndarray, np.ndarray]:
    """GTSAM Levenberg-Marquardt over poses (first fixed) and landmarks, true association, from the truth.

    Parameters
    ----------
    poses: (K, 4, 4) initial ``T_world_sensor`` (pose 0 is held at its value by a tight prior).
    landmarks: (L, 3) initial landmark positions in ``world``.
    pose_idx, lm_idx: (M,) pose and landmark index of each observation.
    z: (M, 3) observed points in the sensor frame (metres).
    sigma: observation noise per axis (metres).
    kind: ``"cartesian"`` (the scipy batch's exact cost) or ``"bearing_range"``.

    Returns
    -------
    t, m: (K, 3) solved sensor positions and (L, 3) landmark positions in ``world``.
    """
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, T in enumerate(poses):
        values.insert(_x(k), gtsam.Pose3(T))
    for i, p in enumerate(landmarks):
        values.insert(_l(i), np.asarray(p, dtype=np.float64))
    graph.add(gtsam.PriorFactorPose3(_x(0), gtsam.Pose3(poses[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    order = np.argsort(pose_idx, kind="stable")
    bounds = np.searchsorted(pose_idx[order], np.arange(len(poses) + 1))
    for k in range(len(poses)):
        rows = order[bounds[k] : bounds[k + 1]]
        for factor in observation_factors(_x(k), lm_idx[rows], z[rows], sigma, kind):
            graph.add(factor)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-10)
    params.setMaxIterations(50)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    t = np.array([result.atPose3(_x(k)).translation() for k in range(len(poses))])
    m = np.array([result.atPoint3(_l(i)) for i in range(len(landmarks))]).reshape(-1, 3)
    return t, m


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", choices=("figure8", "stationary", "dynamic"), default="figure8")
    parser.add_argument("--iterations", type=int, default=900)
    parser.add_argument("--density", type=float, default=25.0)
    parser.add_argument("--noise", type=float, default=0.3)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--factor", choices=FACTORS, default="bearing_range")
    parser.add_argument("--static-only", action="store_true", help="drop moving landmarks' observations (oracle)")
    parser.add_argument("--relinearize-threshold", type=float, default=0.1)
    parser.add_argument("--relinearize-skip", type=int, default=10)
    parser.add_argument("--huber", type=float, default=0.0, help="Huber kernel threshold (whitened); 0: Gaussian")
    args = parser.parse_args(argv)
    ok, message = available()
    if not ok:
        print(message, file=sys.stderr)
        return 1
    from relpoint.simulation import SimulationConfig, simulate

    extra: dict[str, Any] = {"scenario": "stationary"} if args.scenario == "stationary" else {}
    if args.scenario == "dynamic":
        extra["dynamic"] = 0.3
    sim = simulate(
        SimulationConfig(iterations=args.iterations, density=args.density, noise=args.noise, seed=args.seed, **extra)
    )
    start = time.perf_counter()
    run = run_isam2(sim, args.noise, kind=args.factor, static_only=args.static_only, huber=args.huber,
                    relinearize_threshold=args.relinearize_threshold, relinearize_skip=args.relinearize_skip)  # fmt: skip
    wall = time.perf_counter() - start
    e = np.linalg.norm(run["error"], axis=1)
    s = np.linalg.norm(run["smoothed_error"], axis=1)
    lm = run["lm_rmse"][np.isfinite(run["lm_rmse"])]
    u = run["update_seconds"]
    options = (
        f"{args.factor}, relinearize {args.relinearize_threshold:g} every {args.relinearize_skip}"
        + (", static only" if args.static_only else "")
        + (f", Huber {args.huber:g}" if args.huber else "")
    )
    print(f"{message}; iSAM2 ({options}) on {args.scenario}, {len(e)} steps, {wall:.1f} s wall")
    print(f"  position RMSE online {np.sqrt(np.mean(e**2)):.4f} m, smoothed {np.sqrt(np.mean(s**2)):.4f} m")
    print(f"  final landmark RMSE {lm[-1]:.4f} m ({run['map_size'][-1]} landmarks)")
    print(f"  update ms: median {1e3 * np.median(u):.2f}, mean {1e3 * u.mean():.2f}, max {1e3 * u.max():.1f}; "
          f"step ms median {1e3 * np.median(run['seconds']):.2f}; update CPU median {1e3 * np.median(run['update_cpu']):.2f}")  # fmt: skip
    for a in range(0, len(u), 100):
        b = min(len(u), a + 100)
        print(f"  steps {a + 1}-{b}: update ms median {1e3 * np.median(u[a:b]):.2f}, map {run['map_size'][b - 1]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
