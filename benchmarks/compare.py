"""Relative Point vs EKF-SLAM vs FastSLAM on the paper's simulation, with a batch accuracy limit.

Reproduces Kraut, *A Relative Point Algorithm*, sections IV-V (Figs. 8-12) on relpoint's simulator
(figure eight, density 25 landmarks per 100 m, white Gaussian noise 0.3 m per axis, seed 1):

* ``figure8``     900 iterations: landmark error over iterations (Fig. 8), position error (Fig. 9) and
                  time per iteration as the map grows;
* ``stationary``  900 iterations from a fixed viewpoint: landmark error (Fig. 10);
* ``dynamic``     the figure eight with 30 % of the landmarks moving;
* ``long``        40 passes of the figure eight for Relative Point (Figs. 11-12); EKF and FastSLAM run
                  fewer passes (``--long-passes-filters``, default 2: at ~0.1-0.3 s per iteration 40
                  passes of 1000 iterations would take hours).

The landmark error at an iteration is the RMSE, over the static landmarks mapped so far, of the
distance to the true landmark named by the map's ``gt_id`` (majority ground-truth id of the fused
observations), computed from ``estimator.landmark_map()`` every ``--every`` iterations, and at the
last iteration from the map the run writes (for Relative Point, after its final adjustment). The
simulated world frame is the first true sensor pose (the identity), which every estimator also takes
as its world, so errors are raw, without alignment.

Accuracy limit: a batch least-squares solution over all observations up to an iteration, with true
association (unknowns: every pose but the first, which is fixed at the identity, and every static
landmark observed; Gauss-Newton on the sparse Jacobian with a sparse LU solve, started from the truth,
then confirmed by ``scipy.optimize.least_squares`` (trf, sparse Jacobian), which stops at once on the
gradient test; trf alone with its iterative LSMR steps needed 800+ evaluations at 300 poses). Its landmark RMSE at checkpoints
and its (smoothed) position RMSE are the best achievable from the same data; the tables give every
estimator's error as a ratio to it.

GTSAM peers (``benchmarks/gtsam_peer.py``; gtsam is an optional dependency, ``pip install gtsam``,
measured with 4.3.0; without it they are skipped with a printed message):

* ``isam2``: iSAM2 as the modern online peer, one update per step with the step's points as
  ``BearingRangeFactor3D`` factors (Cartesian 0.3 m noise converted to bearing ``0.3/range`` rad and range
  0.3 m), true association from the ``ids``, a weak constant-position between-pose factor; its own column
  in every table and plot (``seconds`` = the whole step; ``update_ms_*`` = ``ISAM2.update`` alone);
* the batch limit's cross-check: GTSAM Levenberg-Marquardt on the same data, with the bearing-range
  factors at every checkpoint (``gtsam_br_*`` columns of ``batch_<scenario>.csv``: the limit of iSAM2's own
  model) and, with ``--gtsam-lm-cartesian``, with a Cartesian ``CustomFactor`` (the scipy batch's exact
  cost; Python callbacks, ~80 s at 900 iterations) at the last checkpoint (``gtsam_lm_*`` columns).

Writes CSV files and PNG plots (matplotlib, Agg) into ``--out`` (default ``docs/results``).

Usage::

    python benchmarks/compare.py [--quick] [--out docs/results] [--jobs 2] [--only figure8 dynamic ...]

Each (scenario, estimator) pair runs in its own worker process with BLAS pinned to one thread.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import numpy as np  # noqa: E402
from scipy import sparse  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402
from scipy.sparse.linalg import splu  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

ESTIMATOR_NAMES = ("relpoint", "ekf", "fastslam", "isam2")
GTSAM_PEERS = ("isam2",)  # run by benchmarks/gtsam_peer.py, only when gtsam imports
SCENARIOS = ("figure8", "stationary", "dynamic", "long")
COLOURS = {"relpoint": "tab:blue", "ekf": "tab:red", "fastslam": "tab:green", "isam2": "tab:purple", "batch": "black"}
LABELS = {
    "relpoint": "Relative Point",
    "ekf": "EKF-SLAM",
    "fastslam": "FastSLAM 2.0",
    "isam2": "iSAM2 (GTSAM, true association)",
    "batch": "batch LSQ (limit)",
}


@dataclass(frozen=True)
class Plan:
    """Sizes of every run (full or ``--quick``)."""

    iterations: int = 900
    stationary_iterations: int = 900
    long_passes: int = 40
    long_passes_filters: int = 2
    every: int = 10
    long_every: int = 100
    checkpoints: int = 6
    noise: float = 0.3
    density: float = 25.0
    seed: int = 1
    gtsam_lm_cartesian: bool = False  # also GTSAM LM with the Cartesian CustomFactor at the last checkpoint


def simulation_config(plan: Plan, scenario: str, estimator: str = "relpoint") -> Any:
    """The :class:`SimulationConfig` of a scenario (``long`` depends on the estimator's pass count)."""
    from relpoint.simulation import SimulationConfig

    common = {"density": plan.density, "noise": plan.noise, "seed": plan.seed}
    if scenario == "figure8":
        return SimulationConfig(iterations=plan.iterations, **common)
    if scenario == "stationary":
        return SimulationConfig(scenario="stationary", iterations=plan.stationary_iterations, **common)
    if scenario == "dynamic":
        return SimulationConfig(iterations=plan.iterations, dynamic=0.3, **common)
    if scenario == "long":
        passes = plan.long_passes if estimator == "relpoint" else plan.long_passes_filters
        return SimulationConfig(passes=passes, **common)
    raise ValueError(scenario)


def build_estimator(name: str) -> Any:
    """A fresh estimator with its default settings (they match the simulation's 0.3 m noise)."""
    from relpoint.estimators import ESTIMATORS

    if name == "relpoint" and "relpoint" not in ESTIMATORS:
        from relpoint.estimators.relative_point.estimator import SPEC
    else:
        SPEC = ESTIMATORS[name]
    return SPEC.factory(SPEC.config_class(), np.random.default_rng(0))


def _pin_threads() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)


def _gtsam_peer() -> Any:
    """The ``benchmarks/gtsam_peer.py`` module (importable whether or not gtsam is)."""
    here = str(Path(__file__).resolve().parent)
    if here not in sys.path:
        sys.path.insert(0, here)
    import gtsam_peer

    return gtsam_peer


# --------------------------------------------------------------------------------- estimator runs


def run_estimator(plan: Plan, scenario: str, name: str) -> dict[str, Any]:
    """Run one estimator over one scenario; per-iteration errors, timing and map size."""
    _pin_threads()
    from relpoint import pipeline
    from relpoint.evaluation import landmark_metrics
    from relpoint.simulation import simulate

    sim = simulate(simulation_config(plan, scenario, name))
    truth = sim.ground_truth.positions
    every = plan.long_every if scenario == "long" else plan.every
    if name == "isam2":
        start = time.perf_counter()
        peer = _gtsam_peer().run_isam2(sim, plan.noise, every=every)
        peer["smoothed_pos_err"] = np.linalg.norm(peer.pop("smoothed_error"), axis=1)
        return {"scenario": scenario, "estimator": name, "wall_s": time.perf_counter() - start,
                "passes": sim.config.passes, **peer}  # fmt: skip
    estimator = build_estimator(name)
    n = len(sim)
    lm_rmse = np.full(n, np.nan)
    lm_matched = np.zeros(n, dtype=np.int64)

    def on_iteration(k: int, _pose: Any) -> None:
        if (k + 1) % every == 0 or k == n - 1:
            summary = landmark_metrics(estimator.landmark_map(), sim.landmarks).summary
            lm_rmse[k] = summary["lm_err_rmse"]
            lm_matched[k] = int(summary["lm_matched"])

    start = time.perf_counter()
    result = pipeline.run((step.observation for step in sim.steps()), estimator, on_iteration=on_iteration)
    wall = time.perf_counter() - start
    # The last point is the map the run writes: after Relative Point's final adjustment, which the
    # pipeline applies once the log ends (the trajectory below is the final one too).
    final = landmark_metrics(result.landmarks, sim.landmarks).summary
    lm_rmse[n - 1] = final["lm_err_rmse"]
    lm_matched[n - 1] = int(final["lm_matched"])
    error = result.trajectory.positions - truth
    return {
        "scenario": scenario,
        "estimator": name,
        "wall_s": wall,
        "passes": sim.config.passes,
        "error": error,
        "lm_rmse": lm_rmse,
        "lm_matched": lm_matched,
        "seconds": result.seconds,
        "map_size": result.map_size,
        "observed": result.observed,
        "summary": result.summary,
    }


# ------------------------------------------------------------------------------ batch least squares


def _skew_rows(q: np.ndarray) -> np.ndarray:
    """Skew matrices [q]x (N, 3, 3) of vectors q (N, 3)."""
    z = np.zeros(len(q))
    return np.stack(
        [np.stack([z, -q[:, 2], q[:, 1]], 1), np.stack([q[:, 2], z, -q[:, 0]], 1), np.stack([-q[:, 1], q[:, 0], z], 1)],
        axis=1,
    )


def batch_solve(
    R0: np.ndarray,
    t0: np.ndarray,
    m0: np.ndarray,
    pose_idx: np.ndarray,
    lm_idx: np.ndarray,
    z: np.ndarray,
    sigma: float,
    rounds: int = 10,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares over poses ``T_world_sensor`` (first fixed) and landmarks, true association.

    Parameters
    ----------
    R0, t0: (K, 3, 3), (K, 3) initial poses (pose 0 is held fixed).
    m0: (L, 3) initial landmark positions in ``world``.
    pose_idx, lm_idx: (M,) pose and landmark of each observation.
    z: (M, 3) observed points in the sensor frame (metres).
    sigma: observation noise per axis (metres).
    rounds: most Gauss-Newton steps; each solves for small rotation increments about the current
        rotations (``R = R_cur Exp(d)``) and folds them in.

    Returns
    -------
    R, t, m: the solution (K, 3, 3), (K, 3), (L, 3).
    """
    K, L, M = len(R0), len(m0), len(z)
    R, t, m = R0.copy(), t0.copy(), m0.copy()
    nv = 6 * (K - 1) + 3 * L
    rows = np.repeat(np.arange(3 * M).reshape(M, 3), 3, axis=1).reshape(M, 3, 3)  # rows[i, a, b] = 3i + a
    free = pose_idx > 0
    col_rot = np.broadcast_to(6 * (pose_idx - 1)[:, None, None] + np.arange(3)[None, None, :], (M, 3, 3))
    col_tr = col_rot + 3
    col_lm = np.broadcast_to(6 * (K - 1) + 3 * lm_idx[:, None, None] + np.arange(3)[None, None, :], (M, 3, 3))
    pattern_rows = np.concatenate([rows[free].ravel(), rows[free].ravel(), rows.ravel()])
    pattern_cols = np.concatenate([col_rot[free].ravel(), col_tr[free].ravel(), col_lm.ravel()])

    def unpack(x: np.ndarray, R_cur: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        poses = x[: 6 * (K - 1)].reshape(K - 1, 6)
        R_new = R_cur.copy()
        R_new[1:] = R_cur[1:] @ Rotation.from_rotvec(poses[:, :3]).as_matrix()
        t_new = t.copy()
        t_new[1:] = poses[:, 3:]
        return R_new, t_new, x[6 * (K - 1) :].reshape(L, 3)

    def problem(R_cur: np.ndarray) -> tuple[Any, Any]:
        def residuals(x: np.ndarray) -> np.ndarray:
            Rx, tx, mx = unpack(x, R_cur)
            pred = np.einsum("nji,nj->ni", Rx[pose_idx], mx[lm_idx] - tx[pose_idx])
            return ((pred - z) / sigma).ravel()

        def jacobian(x: np.ndarray) -> sparse.csr_matrix:
            Rx, tx, mx = unpack(x, R_cur)
            Rt = np.transpose(Rx[pose_idx], (0, 2, 1))
            pred = np.einsum("nij,nj->ni", Rt, mx[lm_idx] - tx[pose_idx])
            d_rot = _skew_rows(pred)  # y = Exp(d)^T q: dy/dd = [y]x at d = 0 (first order in d)
            values = np.concatenate([d_rot[free].ravel(), -Rt[free].ravel(), Rt.ravel()]) / sigma
            return sparse.csr_matrix((values, (pattern_rows, pattern_cols)), shape=(3 * M, nv))

        return residuals, jacobian

    def start(t: np.ndarray, m: np.ndarray) -> np.ndarray:
        return np.concatenate([np.concatenate([np.zeros((K - 1, 3)), t[1:]], axis=1).ravel(), m.ravel()])

    # Gauss-Newton, relinearised about the current rotations each step, normal equations solved by sparse LU.
    for _ in range(rounds):
        residuals, jacobian = problem(R)
        x0 = start(t, m)
        J, r = jacobian(x0), residuals(x0)
        dx = splu((J.T @ J).tocsc()).solve(-(J.T @ r))
        R, t, m = unpack(x0 + dx, R)
        if np.max(np.abs(dx)) < 1e-9:
            break
    # Confirm with scipy's trust-region solver from the Gauss-Newton solution (it stops at once there).
    residuals, jacobian = problem(R)
    x0 = start(t, m)
    solution = least_squares(residuals, x0, jac=jacobian, method="trf", x_scale="jac", max_nfev=20)
    if solution.cost < 0.5 * float(residuals(x0) @ residuals(x0)):
        R, t, m = unpack(solution.x, R)
    return R, t, m


def run_batch(plan: Plan, scenario: str) -> dict[str, Any]:
    """Batch accuracy limit of a scenario at checkpoints (prefixes of the run)."""
    _pin_threads()
    from relpoint.simulation import simulate

    sim = simulate(simulation_config(plan, scenario))
    poses = sim.ground_truth.matrices()
    static = ~sim.landmarks.dynamic
    pose_list, lm_list, z_list = [], [], []
    for step in sim.steps():
        ids = np.asarray(step.observation.ids)
        keep = ids >= 0
        keep[keep] &= static[ids[keep]]
        pose_list.append(np.full(int(keep.sum()), step.index))
        lm_list.append(ids[keep])
        z_list.append(step.observation.points[keep])
    pose_idx, lm_all, z = np.concatenate(pose_list), np.concatenate(lm_list), np.concatenate(z_list)
    n = len(sim)
    checkpoints = np.unique(np.linspace(0, n, plan.checkpoints + 1)[1:].round().astype(int))
    out_rows = []
    start = time.perf_counter()
    position_error = np.full((n, 3), np.nan)
    peer = _gtsam_peer()
    with_gtsam = peer.available()[0]

    def errors(t: np.ndarray, m: np.ndarray, truth_lm: np.ndarray, c: int) -> tuple[float, float]:
        lm_err = np.linalg.norm(m - truth_lm, axis=1)
        return float(np.sqrt(np.mean(lm_err**2))), _rmse(t - poses[:c, :3, 3])

    for c in checkpoints:
        use = pose_idx < c
        ids, lm_idx = np.unique(lm_all[use], return_inverse=True)
        truth_lm = sim.landmarks.positions[ids]
        _, t, m = batch_solve(poses[:c, :3, :3], poses[:c, :3, 3], truth_lm, pose_idx[use], lm_idx, z[use], plan.noise)
        pos_err = t - poses[:c, :3, 3]
        lm_rmse, pos_rmse = errors(t, m, truth_lm, c)
        row = {"iteration": int(c), "landmarks": len(ids), "observations": int(use.sum()), "lm_rmse": lm_rmse,
               "pos_rmse": pos_rmse}  # fmt: skip
        if with_gtsam:  # GTSAM Levenberg-Marquardt on the same data, from the truth
            args = (poses[:c], truth_lm, pose_idx[use], lm_idx, z[use], plan.noise)
            row["gtsam_br_lm_rmse"], row["gtsam_br_pos_rmse"] = errors(
                *peer.batch_lm(*args, "bearing_range"), truth_lm, c
            )
            if plan.gtsam_lm_cartesian and c == n:
                row["gtsam_lm_rmse"], row["gtsam_pos_rmse"] = errors(*peer.batch_lm(*args, "cartesian"), truth_lm, c)
        out_rows.append(row)
        if c == n:
            position_error = pos_err
    return {
        "scenario": scenario,
        "rows": out_rows,
        "position_error": position_error,
        "wall_s": time.perf_counter() - start,
    }


# ------------------------------------------------------------------------------------------ output


def _rmse(e: np.ndarray) -> float:
    e = e[np.all(np.isfinite(e), axis=1)] if e.ndim == 2 else e[np.isfinite(e)]
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) if e.ndim == 2 else float(np.sqrt(np.mean(e**2)))


# Per-iteration extras of the iSAM2 peer: step CPU time, ISAM2.update wall and CPU time, smoothed position error.
EXTRA_COLUMNS = ("cpu_seconds", "update_seconds", "update_cpu", "smoothed_pos_err")


def write_iterations(out: Path, run: dict[str, Any]) -> None:
    path = out / f"{run['scenario']}_{run['estimator']}.csv"
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "iteration",
                "pos_err",
                "err_x",
                "err_y",
                "err_z",
                "lm_rmse",
                "lm_matched",
                "seconds",
                "map_size",
                "observed",
                *(key for key in EXTRA_COLUMNS if key in run),
            ]
        )
        extra = [run[key] for key in EXTRA_COLUMNS if key in run]
        e = run["error"]
        norm = np.linalg.norm(e, axis=1)
        for k in range(len(e)):
            lm = "" if np.isnan(run["lm_rmse"][k]) else f"{run['lm_rmse'][k]:.5f}"
            lmn = "" if np.isnan(run["lm_rmse"][k]) else str(run["lm_matched"][k])
            w.writerow([k, f"{norm[k]:.5f}", *(f"{v:.5f}" for v in e[k]), lm, lmn, f"{run['seconds'][k]:.6f}",
                        run["map_size"][k], run["observed"][k], *(f"{x[k]:.6f}" for x in extra)])  # fmt: skip


def read_iterations(out: Path, plan: Plan, scenario: str, name: str) -> dict[str, Any]:
    """A run back from the CSV :func:`write_iterations` wrote (``wall_s`` becomes the sum of step times)."""
    with (out / f"{scenario}_{name}.csv").open() as f:
        rows = list(csv.DictReader(f))
    column = lambda key, kind=float: np.array([kind(r[key]) if r[key] != "" else np.nan for r in rows])  # noqa: E731
    seconds = column("seconds")
    extra = {key: column(key) for key in EXTRA_COLUMNS if rows and key in rows[0]}
    return {
        **extra,
        "scenario": scenario,
        "estimator": name,
        "wall_s": float(seconds.sum()),
        "passes": _passes_in(rows, plan, scenario, name),
        "error": np.stack([column("err_x"), column("err_y"), column("err_z")], axis=1),
        "lm_rmse": column("lm_rmse"),
        "lm_matched": np.nan_to_num(column("lm_matched")).astype(np.int64),
        "seconds": seconds,
        "map_size": column("map_size").astype(np.int64),
        "observed": column("observed").astype(np.int64),
        "summary": {},
    }


def _passes_in(rows: list[dict[str, str]], plan: Plan, scenario: str, name: str) -> int:
    """Passes a reused CSV holds (a long run may come from another ``--long-passes*`` setting)."""
    from dataclasses import replace

    from relpoint.simulation import simulate

    config = simulation_config(plan, scenario, name)
    if scenario != "long":
        return config.passes
    per_pass = len(simulate(replace(config, passes=1)))
    return max(1, round(len(rows) / per_pass))


def summarise(run: dict[str, Any], batch: dict[str, Any] | None) -> dict[str, Any]:
    e, s = run["error"], run["seconds"]
    lm = run["lm_rmse"]
    last = np.flatnonzero(np.isfinite(lm))
    final_lm = float(lm[last[-1]]) if len(last) else float("nan")
    n = len(e)
    row: dict[str, Any] = {
        "scenario": run["scenario"],
        "estimator": run["estimator"],
        "passes": run["passes"],
        "iterations": n,
        "pos_rmse": _rmse(e),
        "pos_final": float(np.linalg.norm(e[-1])),
        "lm_rmse_final": final_lm,
        "lm_matched_final": int(run["lm_matched"][last[-1]]) if len(last) else 0,
        "map_size_final": int(run["map_size"][-1]),
        "ms_mean": 1e3 * float(s.mean()),
        "ms_median": 1e3 * float(np.median(s)),
        "ms_first100": 1e3 * float(s[:100].mean()),
        "ms_last100": 1e3 * float(s[-100:].mean()),
        "ms_max": 1e3 * float(s.max()),
        "wall_s": run["wall_s"],
    }
    if "update_seconds" in run:  # the iSAM2 peer: ISAM2.update alone, wall and CPU
        u, c = run["update_seconds"], run["update_cpu"]
        row.update({"update_ms_median": 1e3 * float(np.median(u)), "update_ms_first100": 1e3 * float(np.median(u[:100])),
                    "update_ms_last100": 1e3 * float(np.median(u[-100:])), "update_cpu_ms_median": 1e3 * float(np.median(c)),
                    "pos_rmse_smoothed": _rmse(run["smoothed_pos_err"])})  # fmt: skip
    if batch is not None and batch["rows"][-1]["iteration"] == n:
        limit = batch["rows"][-1]
        row["lm_ratio_to_batch"] = final_lm / limit["lm_rmse"]
        row["pos_ratio_to_batch"] = row["pos_rmse"] / limit["pos_rmse"]
    return row


def write_table(path: Path, rows: list[dict[str, Any]]) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.5g}" if isinstance(v, float) else v) for k, v in r.items()})


def plot_all(out: Path, runs: dict[tuple[str, str], dict[str, Any]], batches: dict[str, dict[str, Any]]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []

    def save(fig: Any, ax: Any, title: str, filename: str) -> None:
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / filename, dpi=110)
        plt.close(fig)
        written.append(filename)

    def landmark_plot(scenario: str, filename: str, title: str) -> None:
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for name in ESTIMATOR_NAMES:
            run = runs.get((scenario, name))
            if run is None:
                continue
            k = np.flatnonzero(np.isfinite(run["lm_rmse"]))
            label = LABELS[name] + (f" ({run['passes']} passes)" if scenario == "long" else "")
            ax.plot(k + 1, run["lm_rmse"][k], color=COLOURS[name], label=label, lw=1.2)
        if scenario in batches:
            b = batches[scenario]["rows"]
            ax.plot([r["iteration"] for r in b], [r["lm_rmse"] for r in b], "o--", color="black", label=LABELS["batch"])
        ax.set_xlabel("iteration")
        ax.set_ylabel("landmark RMSE (m)")
        save(fig, ax, title, filename)

    def position_plot(scenario: str, filename: str, title: str, axis: int | None = None) -> None:
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for name in ESTIMATOR_NAMES:
            run = runs.get((scenario, name))
            if run is None:
                continue
            e = run["error"]
            y = np.linalg.norm(e, axis=1) if axis is None else e[:, axis]
            label = LABELS[name] + (f" ({run['passes']} passes)" if scenario == "long" else "")
            ax.plot(np.arange(1, len(y) + 1), y, color=COLOURS[name], label=label, lw=0.8)
        if scenario in batches and axis is None:
            pe = batches[scenario]["position_error"]
            ax.plot(np.arange(1, len(pe) + 1), np.linalg.norm(pe, axis=1), color="black", lw=0.8, label=LABELS["batch"])
        ax.set_xlabel("iteration")
        ax.set_ylabel("position error (m)" if axis is None else f"position error in {'xyz'[axis]} (m)")
        save(fig, ax, title, filename)

    if any(s == "figure8" for s, _ in runs):
        landmark_plot("figure8", "fig8_landmark_error.png", "Figure eight, density 25, noise 0.3: landmark error")
        position_plot("figure8", "fig9_position_error.png", "Figure eight: position error")
        fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
        for name in ESTIMATOR_NAMES:
            run = runs.get(("figure8", name))
            if run is None:
                continue
            s = run["seconds"]
            w = min(25, len(s))
            smooth = np.convolve(s, np.ones(w) / w, mode="valid")
            ax1.semilogy(np.arange(w, len(s) + 1), smooth, color=COLOURS[name], label=LABELS[name])
            if "update_cpu" in run:  # the iSAM2 peer: CPU time of ISAM2.update alone (wall time is load-sensitive)
                cpu = np.convolve(run["update_cpu"], np.ones(w) / w, mode="valid")
                ax1.semilogy(
                    np.arange(w, len(s) + 1), cpu, color=COLOURS[name], ls="--", label="iSAM2 update, CPU time"
                )
            ax2.plot(np.arange(1, len(s) + 1), run["map_size"], color=COLOURS[name], label=LABELS[name])
        ax1.set_ylabel("seconds per iteration (25-iteration mean)")
        ax1.axhline(0.1, color="grey", ls=":", label="0.1 s target")
        ax1.grid(alpha=0.3, which="both")
        ax1.legend()
        ax2.set_ylabel("landmarks mapped")
        ax2.set_xlabel("iteration")
        ax2.grid(alpha=0.3)
        ax1.set_title("Figure eight: time per iteration as the map grows")
        fig.tight_layout()
        fig.savefig(out / "timing.png", dpi=110)
        plt.close(fig)
        written.append("timing.png")
    if any(s == "stationary" for s, _ in runs):
        landmark_plot("stationary", "fig10_stationary.png", "Stationary viewpoint: landmark error")
    if any(s == "dynamic" for s, _ in runs):
        landmark_plot("dynamic", "dynamic_landmark_error.png", "Figure eight, 30 % dynamic: static landmark error")
        position_plot("dynamic", "dynamic_position_error.png", "Figure eight, 30 % dynamic: position error")
    if any(s == "long" for s, _ in runs):
        landmark_plot("long", "fig11_long_landmark_error.png", "Repeated figure-eight passes: landmark error")
        position_plot("long", "fig12_long_position_y.png", "Repeated figure-eight passes: position error in y", axis=1)
    return written


def _starry_night_one(prefix: int | None, name: str) -> dict[str, Any]:
    _pin_threads()
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests.test_starry_night import evaluate, load

    start = time.perf_counter()
    figures = evaluate(name, load(prefix))
    return {"estimator": name, **figures, "wall_s": time.perf_counter() - start}


def starry_night(out: Path, prefix: int | None, names: list[str], jobs: int) -> int:
    """Run the estimators on the Starry Night log with the settings of ``tests/test_starry_night.py``.

    Rows of estimators not run this time are kept from an existing table, so one estimator can be
    rerun alone. The GTSAM peers have no Starry Night settings and are skipped.
    """
    names = [n for n in names if n not in GTSAM_PEERS]
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        rows = list(pool.map(_starry_night_one, [prefix] * len(names), names))
    name = "starry_night.csv" if prefix is None else f"starry_night_prefix{prefix}.csv"
    if (out / name).exists():
        with (out / name).open(newline="") as f:
            rows += [r for r in csv.DictReader(f) if r["estimator"] not in names]
    write_table(out / name, rows)
    print(f"Starry Night, {'all' if prefix is None else f'first {prefix}'} observations (SE(3)-aligned)")
    print(
        f"{'estimator':9s} {'poses':>5} {'ATE m':>7} {'rot deg':>7} {'lm m':>6} {'mapped':>6} {'lms':>4} {'ms/step':>7}"
    )
    for r in rows[: len(names)]:
        print(
            f"{r['estimator']:9s} {r['poses']:5.0f} {r['ate_rmse']:7.3f} {r['rot_rmse_deg']:7.1f} {r['lm_rmse']:6.3f} "
            f"{r['lm_mapped_fraction']:6.2f} {r['lm_count']:4.0f} {1e3 * r['seconds'] / r['poses']:7.1f}"
        )
    print(f"wrote {out / name}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/results"))
    parser.add_argument("--quick", action="store_true", help="small runs for a smoke test (150 iterations, 2 passes)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes")
    parser.add_argument("--only", nargs="+", choices=SCENARIOS, default=list(SCENARIOS))
    parser.add_argument("--estimators", nargs="+", choices=ESTIMATOR_NAMES, default=list(ESTIMATOR_NAMES))
    parser.add_argument("--long-passes", type=int, default=None, help="passes of the long run for Relative Point")
    parser.add_argument("--long-passes-filters", type=int, default=None, help="passes of the long run for EKF/FastSLAM")
    parser.add_argument("--no-batch", action="store_true", help="skip the batch least-squares limit")
    parser.add_argument(
        "--gtsam-lm-cartesian",
        action="store_true",
        help="also cross-check the batch limit at its last checkpoint with GTSAM LM on a Cartesian CustomFactor (slow)",
    )
    parser.add_argument(
        "--reuse",
        action="store_true",
        help="read estimator runs whose CSV already exists in --out instead of rerunning",
    )
    parser.add_argument(
        "--starry-night",
        action="store_true",
        help="instead: run the three on the Starry Night log (../shared/data) with the regression test's settings",
    )
    parser.add_argument("--prefix", type=int, default=None, help="--starry-night: first N observations only")
    args = parser.parse_args(argv)
    if args.starry_night:
        args.out.mkdir(parents=True, exist_ok=True)
        return starry_night(args.out, args.prefix, args.estimators, args.jobs)

    plan = (
        Plan(
            iterations=150,
            stationary_iterations=150,
            long_passes=2,
            long_passes_filters=1,
            checkpoints=3,
            long_every=50,
        )
        if args.quick
        else Plan()
    )
    if args.long_passes is not None or args.long_passes_filters is not None:
        plan = Plan(**{**plan.__dict__, "long_passes": args.long_passes or plan.long_passes,
                       "long_passes_filters": args.long_passes_filters or plan.long_passes_filters})  # fmt: skip
    if args.gtsam_lm_cartesian:
        plan = Plan(**{**plan.__dict__, "gtsam_lm_cartesian": True})
    gtsam_ok, gtsam_message = _gtsam_peer().available()
    print(
        f"GTSAM peers: {gtsam_message}"
        + ("" if gtsam_ok else "; running without the iSAM2 column and the LM cross-check")
    )
    out: Path = args.out
    if not gtsam_ok:
        # A peer that cannot run here still counts where its runs are reused from ``--out``.
        args.estimators = [
            e for e in args.estimators
            if e not in GTSAM_PEERS or (args.reuse and all((out / f"{s}_{e}.csv").exists() for s in args.only))
        ]  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)

    runs: dict[tuple[str, str], dict[str, Any]] = {}
    for s in args.only:
        for e in args.estimators:
            if args.reuse and (out / f"{s}_{e}.csv").exists():
                runs[(s, e)] = read_iterations(out, plan, s, e)
    tasks = [(run_estimator, (plan, s, e)) for s in args.only for e in args.estimators if (s, e) not in runs]
    if not args.no_batch:
        tasks += [(run_batch, (plan, s)) for s in args.only if s != "long"]
    # Longest first so the pool stays busy to the end.
    weight = {"long": 0, "figure8": 1, "dynamic": 1, "stationary": 2}
    tasks.sort(key=lambda t: (weight[t[1][1]], t[0] is run_batch, t[1][-1] in ("relpoint", "isam2")))
    batches: dict[str, dict[str, Any]] = {}
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = [pool.submit(fn, *fargs) for fn, fargs in tasks]
        for future in futures:
            result = future.result()
            if "estimator" in result:
                runs[(result["scenario"], result["estimator"])] = result
                write_iterations(out, result)
                print(f"[{time.perf_counter() - start:7.1f} s] {result['scenario']:10s} {result['estimator']:9s} "
                      f"{len(result['error'])} iterations in {result['wall_s']:.1f} s", flush=True)  # fmt: skip
            else:
                batches[result["scenario"]] = result
                write_table(out / f"batch_{result['scenario']}.csv", result["rows"])
                print(f"[{time.perf_counter() - start:7.1f} s] {result['scenario']:10s} batch     "
                      f"{len(result['rows'])} checkpoints in {result['wall_s']:.1f} s", flush=True)  # fmt: skip

    rows = [summarise(run, batches.get(scenario)) for (scenario, _), run in runs.items()]
    rows.sort(key=lambda r: (SCENARIOS.index(r["scenario"]), ESTIMATOR_NAMES.index(r["estimator"])))
    write_table(out / "summary.csv", rows)
    plots = plot_all(out, runs, batches)

    print(
        f"\nsummary ({'quick' if args.quick else 'full'}; seed {plan.seed}, density {plan.density:g}, noise {plan.noise:g})"
    )
    header = f"{'scenario':10s} {'estimator':9s} {'passes':>6} {'iters':>6} {'pos RMSE':>9} {'lm RMSE':>8} {'x batch':>8} {'x batch':>8} {'map':>5} {'ms mean':>8} {'ms median':>9} {'ms last100':>10}"
    print(header + "\n" + " " * 44 + "(pos)    (lm)")
    for r in rows:
        print(f"{r['scenario']:10s} {r['estimator']:9s} {r['passes']:>6} {r['iterations']:>6} {r['pos_rmse']:9.3f} "
              f"{r['lm_rmse_final']:8.3f} {r.get('pos_ratio_to_batch', float('nan')):8.2f} "
              f"{r.get('lm_ratio_to_batch', float('nan')):8.2f} {r['map_size_final']:>5} {r['ms_mean']:8.1f} "
              f"{r['ms_median']:9.1f} {r['ms_last100']:10.1f}")  # fmt: skip
        if "update_ms_median" in r:
            print(f"{'':17s} iSAM2 update alone: median {r['update_ms_median']:.1f} ms wall "
                  f"({r['update_cpu_ms_median']:.1f} ms CPU), first/last 100 {r['update_ms_first100']:.1f} / "
                  f"{r['update_ms_last100']:.1f} ms; smoothed position RMSE {r['pos_rmse_smoothed']:.3f} m")  # fmt: skip
    for scenario, b in batches.items():
        last = b["rows"][-1]
        print(f"batch {scenario}: landmark RMSE {last['lm_rmse']:.4f} m, position RMSE {last['pos_rmse']:.4f} m "
              f"({last['landmarks']} landmarks, {last['observations']} observations)")  # fmt: skip
        if "gtsam_br_lm_rmse" in last:
            print(f"  GTSAM LM, bearing-range factors: landmark RMSE {last['gtsam_br_lm_rmse']:.4f} m, "
                  f"position RMSE {last['gtsam_br_pos_rmse']:.4f} m")  # fmt: skip
        if "gtsam_lm_rmse" in last:
            print(f"  GTSAM LM, Cartesian CustomFactor: landmark RMSE {last['gtsam_lm_rmse']:.4f} m, "
                  f"position RMSE {last['gtsam_pos_rmse']:.4f} m")  # fmt: skip
    print(f"wrote {out}/summary.csv, per-run CSVs and {', '.join(plots)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
