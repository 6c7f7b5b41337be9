"""Every point estimator over a matrix of simulated scenes, against each cell's batch least-squares optimum.

A *cell* is one set of simulator settings (path, scale and noise, movers, odometry, fixes); each runs
for several seeds. Per cell and estimator it prints the mean over the seeds of:

* ``ate``: RMSE of the estimated sensor positions from the true ones over every iteration (m), raw: the
  simulated ``world`` is the first true pose, which every estimator also takes as its world (fixes are
  given in that frame too); ``x opt``: ratio to the optimum's;
* ``lm``: RMSE of the mapped static landmarks from the true ones named by their ``gt_id`` (m), the
  landmarks flagged dynamic left out (:func:`relpoint.evaluation.landmark_metrics`); ``x opt``;
* ``dyn P / R``: precision and recall of the map's dynamic flags (a landmark is truly dynamic when its
  ``gt_id`` moves); ``R 3s``: the recall over the movers issue 17's floor speaks of, those seen to
  move at least 3 sigma within Relative Point's detection window (``dynamic_window``, 40 iterations):
  observed at two iterations at most 40 apart, that far apart (the floor on recall is measured on it);
* ``dup %``: *duplicate landmarks*, map entries beyond the first for each true landmark (by ``gt_id``,
  flagged dynamic or not), in percent of the map: what moving points that start a new landmark each
  time they no longer match leave behind;
* ``ms/it``: mean time per iteration (``Estimator.step``);
* ``ate al``: the ATE after the rigid alignment (Umeyama, no scale) of the estimate onto the truth;
* with fixes, ``x nofix``: the aligned ATE as a ratio to the same run's with the fixes withheld (aligned,
  because a run without fixes knows ``world`` only up to a rigid transform: the simulator's ``world``
  is its start, which gives it the frame for free), and ``x fixes``: the raw ATE as a ratio to the
  fixes alone (the fixes linearly interpolated to every iteration), both in ``world``;
* with movers, ``x static``: the ATE as a ratio to the run on the same cell without movers (same seed;
  the movers are static landmarks there, so that scene also holds more landmarks to localise on), and
  ``x oracle``: the ATE as a ratio to the run on the same log with the movers' points taken out: how far
  the movers drag the pose, without the information the static scene has and this one lacks. On the
  optimum's row, ``x static`` is the optimum's own ratio to the static scene's optimum: what the
  movers' absence costs least squares with perfect association;
* Relative Point, ``x incr``: the worst seed's larger ratio of ATE and landmark RMSE to the same run's
  incremental solution (``final_adjustment=false``): the final adjustment's floor (at most 1.05). On
  the optimum's row, the same ratio for the optimum's ATE: how far the floor is from what least squares
  itself gives (the incremental solution's errors partly cancel on some seeds).

The *optimum* of a cell is the batch least-squares solution of ``benchmarks/compare.py``
(:func:`compare.batch_solve`): every observation of a static landmark, true association, poses and
landmarks free but the first pose, solved from the truth. It uses the points alone, as Relative Point
does; EKF and FastSLAM also have a motion model, odometry and fixes, so they can go below 1.0 of it.

After the tables it prints, per estimator, the median and the worst cell of each ratio and the floors of
issue 17 with the figure measured against each.

Usage::

    python benchmarks/robustness.py                   # the whole matrix, 3 seeds a cell
    python benchmarks/robustness.py --quick           # the CI subset (tests/test_robustness.py)
    python benchmarks/robustness.py --cells spiral-issue --estimators ekf --seeds 0 1 2 3 4
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import numpy as np  # noqa: E402

from relpoint.types import PointObservation  # noqa: E402

ESTIMATORS = ("relpoint", "ekf", "fastslam")
#: Estimator settings of every run: the defaults, but the observation noise set to the cell's (each
#: estimator's default is the outdoor 0.3 m; deriving it from the data is issue 16's).
NOISE_SETTINGS = {"relpoint": (), "ekf": ("observation_sigma",), "fastslam": ("observation_sigma",)}


@dataclass(frozen=True)
class Cell:
    """One scene: simulator settings (without the seed) and the cell it is compared with when static."""

    name: str
    settings: dict[str, Any] = field(default_factory=dict)

    @property
    def movers(self) -> bool:
        return float(self.settings.get("dynamic", 0.0)) > 0.0

    @property
    def fixes(self) -> bool:
        return int(self.settings.get("fix_every", 0)) > 0

    def static_twin(self) -> Cell:
        """The same scene without movers."""
        settings = {k: v for k, v in self.settings.items() if k not in ("dynamic", "mover_motion", "mover_speed")}
        return Cell(self.name + "/static", settings)


OUTDOOR = {"noise": 0.3}
INDOOR = {"noise": 0.03, "scale": 0.1}
#: The scene of issue 17's report: a climbing spiral over its start, 0.2 m noise, 10 % movers,
#: odometry and 1 m fixes at a low rate.
ISSUE = {"scenario": "spiral", "passes": 2, "step": 1.5, "noise": 0.2, "dynamic": 0.1, "mover_motion": "random-walk",
         "mover_speed": 0.1, "odometry_noise": 0.05, "fix_every": 10, "fix_noise": 1.0}  # fmt: skip


def matrix() -> list[Cell]:
    """The full matrix: each cell varies one or two settings from the figure eight or the issue's spiral."""
    return [
        Cell("figure8", {**OUTDOOR}),
        Cell("figure8-indoor", {**INDOOR}),
        Cell("spiral", {"scenario": "spiral", "passes": 2, "step": 1.5, **OUTDOOR}),
        Cell("corridor", {"scenario": "corridor", "step": 2.0, **OUTDOOR}),
        Cell("spiral-issue", dict(ISSUE)),
        Cell("figure8-oscillate-30", {**OUTDOOR, "dynamic": 0.3}),
        Cell("figure8-line-10-slow", {**OUTDOOR, "dynamic": 0.1, "mover_motion": "line", "mover_speed": 0.02}),
        Cell("figure8-line-40-fast", {**OUTDOOR, "dynamic": 0.4, "mover_motion": "line", "mover_speed": 0.5}),
        Cell("figure8-walk-20", {**OUTDOOR, "dynamic": 0.2, "mover_motion": "random-walk", "mover_speed": 0.2}),
        Cell("figure8-stopgo-20", {**OUTDOOR, "dynamic": 0.2, "mover_motion": "stop-and-go", "mover_speed": 0.2}),
        Cell("figure8-late-20", {**OUTDOOR, "dynamic": 0.2, "mover_motion": "static-then-moving", "mover_speed": 0.2}),
        Cell("indoor-line-20", {**INDOOR, "dynamic": 0.2, "mover_motion": "line", "mover_speed": 0.05}),
        Cell("figure8-noise-0.5", {"noise": 0.5}),
        Cell("figure8-odometry", {**OUTDOOR, "odometry_noise": 0.05}),
        Cell("figure8-fix-1m-every", {**OUTDOOR, "odometry_noise": 0.05, "fix_every": 1, "fix_noise": 1.0}),
        Cell("figure8-fix-5m-sparse", {**OUTDOOR, "fix_every": 10, "fix_noise": 5.0}),
        Cell(
            "spiral-fix-0.5m",
            {"scenario": "spiral", "passes": 2, "step": 1.5, **OUTDOOR, "fix_every": 5, "fix_noise": 0.5},
        ),
    ]


#: The CI subset (tests/test_robustness.py): short runs of the cells that exercise each floor.
QUICK_CELLS = ("spiral-issue", "figure8-line-10-slow", "figure8-fix-1m-every")
QUICK_ITERATIONS = 150


def simulation_config(cell: Cell, seed: int, iterations: int | None) -> Any:
    from relpoint.simulation import SimulationConfig

    settings = dict(cell.settings)
    if iterations is not None:
        settings["iterations"] = iterations
    return SimulationConfig(**settings, seed=seed)


def build_estimator(name: str, noise: float, **settings: Any) -> Any:
    """``name`` with its default settings (but ``settings``), the observation noise set to the scene's."""
    from relpoint.estimators import ESTIMATORS as SPECS

    spec = SPECS[name]
    values = {setting: noise for setting in NOISE_SETTINGS[name]}
    return spec.factory(spec.config_class(**values, **settings), np.random.default_rng(0))


def inputs(sim: Any, fixes: bool = True) -> Any:
    """A simulation's inputs in log order: the observation, then odometry and the fix of its stamp."""
    for step in sim.steps():
        yield step.observation
        if step.odometry is not None:
            yield step.odometry
        if fixes and step.fix is not None:
            yield step.fix


def duplicate_landmarks(gt_id: np.ndarray) -> int:
    """Map entries beyond the first for each true landmark (entries with ``gt_id`` -1 are not counted)."""
    known = np.asarray(gt_id)[np.asarray(gt_id) >= 0]
    return int(known.size - np.unique(known).size)


def fixes_alone_ate(sim: Any) -> float:
    """RMSE (m) of the fixes, linearly interpolated to every iteration (held beyond the first and last)."""
    stamps, positions = [], []
    for step in sim.steps():
        if step.fix is not None:
            stamps.append(step.stamp_ns)
            positions.append(step.fix.position)
    if not stamps:
        return float("nan")
    fixes = np.asarray(positions)
    t = (np.asarray(sim.stamps_ns) - stamps[0]) * 1e-9
    tf = (np.asarray(stamps) - stamps[0]) * 1e-9
    interpolated = np.stack([np.interp(t, tf, fixes[:, axis]) for axis in range(3)], axis=1)
    return _rmse(interpolated - sim.ground_truth.positions)


def aligned_ate(estimate: np.ndarray, truth: np.ndarray) -> float:
    """RMSE (m) of positions (N, 3) after the rigid alignment of ``estimate`` onto ``truth``."""
    from relpoint.evaluation import umeyama

    R, t, _ = umeyama(estimate, truth)
    return _rmse(estimate @ R.T + t - truth)


def _rmse(error: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.square(error), axis=1))))


def reference(sim: Any, in_world: bool) -> tuple[np.ndarray, Any]:
    """True positions (N, 3) and landmarks in the frame an estimator reports in.

    With fixes that is ``world``; without, an estimator's world is its first pose, so the truth is
    expressed in the first true pose's frame (the same as ``world`` on the figure eight and spiral,
    which start at the identity; the corridor starts turned).
    """
    from relpoint.types import GroundTruthLandmarks

    if in_world:
        return sim.ground_truth.positions, sim.landmarks
    T0 = sim.ground_truth.matrices()[0]
    R, t = T0[:3, :3], T0[:3, 3]
    landmarks = sim.landmarks
    local = GroundTruthLandmarks((landmarks.positions - t) @ R, landmarks.ids, landmarks.dynamic)
    return (sim.ground_truth.positions - t) @ R, local


def without_movers(items: Any, dynamic: np.ndarray) -> Any:
    """``items`` (:func:`inputs`) with the points of the landmarks flagged in ``dynamic`` (by id) taken out."""
    for item in items:
        if isinstance(item, PointObservation) and item.ids is not None:
            ids = np.asarray(item.ids)
            known = (ids >= 0) & (ids < len(dynamic))
            moving = np.zeros(len(ids), dtype=bool)
            moving[known] = dynamic[ids[known]]
            item = dataclasses.replace(item, points=item.points[~moving], ids=ids[~moving])
        yield item


def run_one(
    cell: Cell, name: str, seed: int, iterations: int | None, fixes: bool = True, movers: bool = True, **settings: Any
) -> dict[str, Any]:
    """One estimator over one cell and seed (default settings but ``settings``): the figures of the module
    docstring; without ``movers``, the movers' points are taken out of the log first."""
    from threadpoolctl import threadpool_limits

    from relpoint import pipeline
    from relpoint.evaluation import landmark_metrics
    from relpoint.simulation import simulate

    with threadpool_limits(limits=1):
        sim = simulate(simulation_config(cell, seed, iterations))
        estimator = build_estimator(name, sim.config.noise, **settings)
        items = inputs(sim, fixes) if movers else without_movers(inputs(sim, fixes), sim.landmarks.dynamic)
        result = pipeline.run(items, estimator)
    truth, landmarks = reference(sim, in_world=fixes and cell.fixes)
    metrics = landmark_metrics(result.landmarks, landmarks).summary
    size = len(result.landmarks)
    return {
        "cell": cell.name,
        "estimator": name,
        "seed": seed,
        "ate": _rmse(result.trajectory.positions - truth),
        "ate_aligned": aligned_ate(result.trajectory.positions, truth),
        "lm": metrics["lm_err_rmse"],
        "dyn_precision": metrics["dyn_precision"],
        "dyn_recall": metrics["dyn_recall"],
        "dyn_recall_3s": detectable_recall(sim, result.landmarks),
        "duplicates": duplicate_landmarks(result.landmarks.gt_id),
        "dup_pct": 100.0 * duplicate_landmarks(result.landmarks.gt_id) / max(size, 1),
        "map": size,
        "ms_per_it": 1e3 * float(np.mean(result.seconds)),
        "summary": result.summary,
    }


def detectable_recall(sim: Any, landmarks: Any, window: int = 40, sigmas: float = 3.0) -> float:
    """Share flagged dynamic of the mapped landmarks whose true landmark, while in view, moves at least
    ``sigmas`` times the noise within ``window`` iterations at some point of the run: seen at two
    iterations at most ``window`` apart that far from each other (NaN when the map has none)."""
    moving = np.flatnonzero(sim.landmarks.dynamic)
    if len(moving) == 0 or landmarks.gt_id is None or landmarks.dynamic is None:
        return float("nan")
    column = np.full(len(sim.landmarks.ids), -1)
    column[moving] = np.arange(len(moving))
    steps = list(sim.steps())
    seen = np.zeros((len(steps), len(moving)), dtype=bool)
    for k, step in enumerate(steps):
        ids = step.observation.ids
        ids = ids[(ids >= 0) & (ids < len(column))]
        seen[k, column[ids][column[ids] >= 0]] = True
    track = np.stack([sim.landmark_positions(int(t))[moving] for t in sim.stamps_ns[: len(steps)]])  # (K, n, 3)
    reach = np.zeros(len(moving))
    for lag in range(1, min(window, len(steps) - 1) + 1):
        both = seen[lag:] & seen[:-lag]
        step = np.where(both, np.linalg.norm(track[lag:] - track[:-lag], axis=2), 0.0).max(axis=0)
        reach = np.maximum(reach, step)
    detectable = set(sim.landmarks.ids[moving[reach >= sigmas * sim.config.noise]].tolist())
    rows = np.array([int(g) in detectable for g in landmarks.gt_id])
    return float(np.mean(landmarks.dynamic[rows])) if rows.any() else float("nan")


def optimum(cell: Cell, seed: int, iterations: int | None) -> dict[str, Any]:
    """The cell's batch least-squares optimum (points only, true association, static landmarks)."""
    from threadpoolctl import threadpool_limits

    from relpoint.simulation import simulate

    here = str(Path(__file__).resolve().parent)
    if here not in sys.path:
        sys.path.insert(0, here)
    from compare import batch_solve

    sim = simulate(simulation_config(cell, seed, iterations))
    poses = sim.ground_truth.matrices()
    static = ~sim.landmarks.dynamic
    pose_idx, lm_ids, z = [], [], []
    for step in sim.steps():
        ids = np.asarray(step.observation.ids)
        keep = ids >= 0
        keep[keep] &= static[ids[keep]]
        pose_idx.append(np.full(int(keep.sum()), step.index))
        lm_ids.append(ids[keep])
        z.append(step.observation.points[keep])
    ids, lm_idx = np.unique(np.concatenate(lm_ids), return_inverse=True)
    truth = sim.landmarks.positions[ids]
    with threadpool_limits(limits=1):
        _, t, m = batch_solve(
            poses[:, :3, :3], poses[:, :3, 3], truth, np.concatenate(pose_idx), lm_idx, np.concatenate(z),
            sim.config.noise,
        )  # fmt: skip
    return {
        "cell": cell.name,
        "seed": seed,
        "ate": _rmse(t - poses[:, :3, 3]),
        "lm": _rmse(m - truth),
        "fixes_ate": fixes_alone_ate(sim),
    }


@dataclass
class Job:
    kind: str  # "run", "nofix", "static", "oracle", "incremental", "optimum", "optimum_static"
    cell: Cell
    estimator: str
    seed: int


def _do(job: Job, iterations: int | None) -> tuple[Job, dict[str, Any]]:
    if job.kind == "optimum":
        return job, optimum(job.cell, job.seed, iterations)
    if job.kind == "optimum_static":
        return job, optimum(job.cell.static_twin(), job.seed, iterations)
    if job.kind == "static":
        return job, run_one(job.cell.static_twin(), job.estimator, job.seed, iterations)
    if job.kind == "oracle":
        return job, run_one(job.cell, job.estimator, job.seed, iterations, movers=False)
    if job.kind == "incremental":
        return job, run_one(job.cell, job.estimator, job.seed, iterations, final_adjustment=False)
    return job, run_one(job.cell, job.estimator, job.seed, iterations, fixes=job.kind != "nofix")


def plan_jobs(cells: list[Cell], estimators: list[str], seeds: list[int]) -> list[Job]:
    """Every run a table needs: the estimators, their runs without fixes and without movers, the optimum."""
    jobs = []
    for cell in cells:
        for seed in seeds:
            jobs.append(Job("optimum", cell, "", seed))
            if cell.movers:
                jobs.append(Job("optimum_static", cell, "", seed))
            for name in estimators:
                jobs.append(Job("run", cell, name, seed))
                if cell.fixes and name != "relpoint":  # Relative Point does not take fixes
                    jobs.append(Job("nofix", cell, name, seed))
                if cell.movers and name != "relpoint":
                    jobs.append(Job("static", cell, name, seed))
                    jobs.append(Job("oracle", cell, name, seed))
                if name == "relpoint":
                    jobs.append(Job("incremental", cell, name, seed))
    return jobs


def run_matrix(
    cells: list[Cell], estimators: list[str], seeds: list[int], iterations: int | None, jobs: int = 1
) -> dict[tuple[str, str, str], list[dict[str, Any]]]:
    """Run every job; results keyed by (kind, cell, estimator), one dict per seed."""
    work = plan_jobs(cells, estimators, seeds)
    out: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            done = list(pool.map(_do, work, [iterations] * len(work)))
    else:
        done = [_do(job, iterations) for job in work]
    for job, row in done:
        out.setdefault((job.kind, job.cell.name, job.estimator), []).append(row)
    return out


def cell_rows(
    cells: list[Cell], estimators: list[str], results: dict[tuple[str, str, str], list[dict[str, Any]]]
) -> list[dict[str, Any]]:
    """One row per (cell, estimator): seed means and the ratios of the module docstring."""
    rows = []
    for cell in cells:
        opt = results[("optimum", cell.name, "")]
        for name in estimators:
            runs = results[("run", cell.name, name)]
            row: dict[str, Any] = {"cell": cell.name, "estimator": name, "seeds": len(runs)}
            for key in ("ate", "ate_aligned", "lm", "dyn_precision", "dyn_recall", "dyn_recall_3s", "dup_pct",
                        "ms_per_it"):
                values = [r[key] for r in runs if np.isfinite(r[key])]  # the dynamic figures are NaN without movers
                row[key] = float(np.mean(values)) if values else float("nan")
            row["ate_x_opt"] = float(np.mean([r["ate"] / o["ate"] for r, o in zip(runs, opt, strict=True)]))
            row["lm_x_opt"] = float(np.mean([r["lm"] / o["lm"] for r, o in zip(runs, opt, strict=True)]))
            # Worst seed of the per-seed ratios (the floors hold in every run, not on average).
            row["ate_x_opt_worst"] = float(max(r["ate"] / o["ate"] for r, o in zip(runs, opt, strict=True)))
            row["lm_x_opt_worst"] = float(max(r["lm"] / o["lm"] for r, o in zip(runs, opt, strict=True)))
            if ("nofix", cell.name, name) in results:
                nofix = results[("nofix", cell.name, name)]
                row["x_nofix"] = float(
                    max(r["ate_aligned"] / n["ate_aligned"] for r, n in zip(runs, nofix, strict=True))
                )
                row["x_nofix_raw"] = float(max(r["ate"] / n["ate"] for r, n in zip(runs, nofix, strict=True)))
                row["x_fixes"] = float(max(r["ate"] / o["fixes_ate"] for r, o in zip(runs, opt, strict=True)))
            if ("incremental", cell.name, name) in results:
                incremental = results[("incremental", cell.name, name)]
                row["x_incr"] = float(
                    max(max(r["ate"] / i["ate"], r["lm"] / i["lm"]) for r, i in zip(runs, incremental, strict=True))
                )
            if ("static", cell.name, name) in results:
                static = results[("static", cell.name, name)]
                row["x_static"] = float(max(r["ate"] / s["ate"] for r, s in zip(runs, static, strict=True)))
            if ("oracle", cell.name, name) in results:
                oracle = results[("oracle", cell.name, name)]
                row["x_oracle"] = float(max(r["ate"] / o["ate"] for r, o in zip(runs, oracle, strict=True)))
            row["dup_pct_worst"] = float(max(r["dup_pct"] for r in runs))
            row["dyn_precision_worst"] = float(np.nanmin([r["dyn_precision"] for r in runs] + [np.inf]))
            row["dyn_recall_worst"] = float(np.nanmin([r["dyn_recall"] for r in runs] + [np.inf]))
            row["dyn_recall_3s_worst"] = float(np.nanmin([r["dyn_recall_3s"] for r in runs] + [np.inf]))
            adjustment = [r["summary"].get("final_adjustment", {}).get("kept") for r in runs]
            if any(a is not None for a in adjustment):
                row["adjustment_kept"] = "/".join(str(a) for a in adjustment)
            rows.append(row)
        row = {"cell": cell.name, "estimator": "optimum", "seeds": len(opt)}
        row["ate"] = float(np.mean([o["ate"] for o in opt]))
        row["lm"] = float(np.mean([o["lm"] for o in opt]))
        if cell.fixes:
            row["fixes_ate"] = float(np.mean([o["fixes_ate"] for o in opt]))
        if ("optimum_static", cell.name, "") in results:
            twin = results[("optimum_static", cell.name, "")]
            row["x_static"] = float(max(o["ate"] / t["ate"] for o, t in zip(opt, twin, strict=True)))
        if ("incremental", cell.name, "relpoint") in results:
            # The final adjustment's floor applied to the optimum itself (ATE only: the optimum maps
            # every static landmark, the incremental solution those it mapped).
            incremental = results[("incremental", cell.name, "relpoint")]
            row["x_incr"] = float(max(o["ate"] / i["ate"] for o, i in zip(opt, incremental, strict=True)))
        rows.append(row)
    return rows


COLUMNS = (
    ("estimator", "{:<9}"), ("ate", "{:7.3f}"), ("ate_x_opt", "{:6.2f}"), ("ate_aligned", "{:7.3f}"), ("lm", "{:7.3f}"), ("lm_x_opt", "{:6.2f}"),
    ("dyn_precision", "{:6.2f}"), ("dyn_recall", "{:6.2f}"), ("dyn_recall_3s", "{:6.2f}"), ("dup_pct", "{:6.1f}"), ("ms_per_it", "{:7.1f}"),
    ("x_nofix", "{:6.2f}"), ("x_nofix_raw", "{:6.2f}"), ("x_fixes", "{:6.2f}"), ("x_static", "{:6.2f}"), ("x_oracle", "{:6.2f}"),
    ("x_incr", "{:6.2f}"),
)  # fmt: skip
HEADERS = ("estimator", "ate m", "x opt", "ate al", "lm m", "x opt", "dyn P", "dyn R", "R 3s", "dup %", "ms/it", "x nofix", "raw", "x fixes",
           "x static", "x oracle", "x incr")  # fmt: skip


def _format(value: Any, spec: str) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "-".rjust(len(spec.format(0.0)) if "f" in spec else 9)
    return spec.format(value)


def format_tables(cells: list[Cell], rows: list[dict[str, Any]]) -> str:
    """A table per cell, as plain text."""
    lines = []
    for cell in cells:
        lines.append(f"\n## {cell.name}: {cell.settings}")
        lines.append("  ".join(f"{h:>7}" for h in HEADERS))
        for row in (r for r in rows if r["cell"] == cell.name):
            lines.append("  ".join(_format(row.get(key), spec).rjust(7) for key, spec in COLUMNS))
    return "\n".join(lines)


#: Floors of issue 17: (estimator, figure, bound, "max" or "min", which cells).
FLOORS = (
    ("relpoint", "ate_x_opt_worst", 1.5, "max", "all"),
    ("relpoint", "lm_x_opt_worst", 1.5, "max", "all"),
    ("relpoint", "dyn_precision_worst", 0.9, "min", "movers"),
    ("relpoint", "dyn_recall_3s_worst", 0.9, "min", "movers"),
    ("relpoint", "x_incr", 1.05, "max", "all"),
    ("ekf", "x_nofix", 1.1, "max", "fixes"),
    ("ekf", "x_fixes", 1.0, "max", "fixes"),
    ("ekf", "dup_pct_worst", 1.0, "max", "movers"),
    ("ekf", "x_static", 1.5, "max", "movers"),
    ("fastslam", "x_nofix", 1.1, "max", "fixes"),
    ("fastslam", "x_fixes", 1.0, "max", "fixes"),
    ("fastslam", "dup_pct_worst", 1.0, "max", "movers"),
    ("fastslam", "x_static", 1.5, "max", "movers"),
)


def floor_report(cells: list[Cell], rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each floor with the worst cell's figure and whether it holds."""
    by_name = {cell.name: cell for cell in cells}
    report = []
    for name, figure, bound, sense, which in FLOORS:
        values = []
        for row in rows:
            cell = by_name[row["cell"]]
            if row["estimator"] != name or figure not in row:
                continue
            if (which == "movers" and not cell.movers) or (which == "fixes" and not cell.fixes):
                continue
            if np.isfinite(row[figure]):
                values.append((row[figure], cell.name))
        if not values:
            continue
        worst = max(values) if sense == "max" else min(values)
        holds = worst[0] <= bound if sense == "max" else worst[0] >= bound
        report.append({"estimator": name, "figure": figure, "bound": bound, "sense": sense, "worst": worst[0],
                       "worst_cell": worst[1], "median": float(np.median([v for v, _ in values])), "holds": holds})  # fmt: skip
    return report


def format_summary(rows: list[dict[str, Any]], report: list[dict[str, Any]]) -> str:
    lines = ["\n## median and worst cell"]
    for name in ESTIMATORS:
        mine = [r for r in rows if r["estimator"] == name]
        if not mine:
            continue
        for key in ("ate_x_opt", "lm_x_opt"):
            values = [(r[key], r["cell"]) for r in mine if np.isfinite(r[key])]
            worst = max(values)
            lines.append(
                f"{name:<9} {key:<10} median {np.median([v for v, _ in values]):6.2f}   worst {worst[0]:6.2f} ({worst[1]})"
            )
    lines.append("\n## floors (issue 17): worst cell against the bound")
    for item in report:
        sign = "<=" if item["sense"] == "max" else ">="
        verdict = "holds" if item["holds"] else "MISSED"
        lines.append(f"{item['estimator']:<9} {item['figure']:<20} {sign} {item['bound']:<4}  worst {item['worst']:7.3f} "
                     f"({item['worst_cell']}), median {item['median']:7.3f}  {verdict}")  # fmt: skip
    for figure in ("x_incr", "x_static"):
        reference = [(r[figure], r["cell"]) for r in rows if r["estimator"] == "optimum" and figure in r]
        if reference:
            worst = max(reference)
            lines.append(f"optimum   {figure + ' (ATE, reference)':<26} worst {worst[0]:7.3f} ({worst[1]}), "
                         f"median {np.median([v for v, _ in reference]):7.3f}")  # fmt: skip
    for name in ESTIMATORS:
        drag = [(r["x_oracle"], r["cell"]) for r in rows if r["estimator"] == name and "x_oracle" in r]
        if drag:
            worst = max(drag)
            lines.append(f"{name:<9} {'x_oracle (reference)':<26} worst {worst[0]:7.3f} ({worst[1]}), "
                         f"median {np.median([v for v, _ in drag]):7.3f}")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help=f"the CI subset: {', '.join(QUICK_CELLS)}, "
                        f"{QUICK_ITERATIONS} iterations")  # fmt: skip
    parser.add_argument("--cells", nargs="+", help="cells to run (default: all; see matrix())")
    parser.add_argument("--estimators", nargs="+", choices=ESTIMATORS, default=list(ESTIMATORS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--iterations", type=int, default=400, help="iterations a run (default 400)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes")
    args = parser.parse_args(argv)
    cells = matrix()
    iterations = args.iterations
    if args.quick:
        cells = [c for c in cells if c.name in QUICK_CELLS]
        iterations = QUICK_ITERATIONS
    if args.cells:
        unknown = set(args.cells) - {c.name for c in cells}
        if unknown:
            parser.error(f"unknown cells {sorted(unknown)}; choose from {[c.name for c in cells]}")
        cells = [c for c in cells if c.name in args.cells]
    start = time.perf_counter()
    results = run_matrix(cells, args.estimators, args.seeds, iterations, args.jobs)
    rows = cell_rows(cells, args.estimators, results)
    print(f"# robustness matrix: {len(cells)} cells, seeds {args.seeds}, {iterations} iterations a run")
    print(format_tables(cells, rows))
    print(format_summary(rows, floor_report(cells, rows)))
    print(f"\nwall time {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
