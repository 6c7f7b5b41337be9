"""Batch plans (``relpoint batch PLAN``) and the combined results files they produce.

A plan is a TOML or YAML file (``docs/batch.md``) naming logs (globs), optional simulated logs,
estimators with fixed parameters and parameter grids, evaluation settings and a results root. It is
parsed and validated here, up front, into frozen job descriptions: a bad plan is a usage error before
any job runs. Everything the jobs need travels in those descriptions (absolute paths, validated
values), so a job can run in another process or on another machine of a Dask cluster that shares the
file system.

The results root holds ``logs/`` (simulated logs), one directory per job (``LOG/ESTIMATOR/GRID``) and
the combined ``results.csv`` / ``results.json`` written by :func:`write_results`.
"""

from __future__ import annotations

import csv
import dataclasses
import glob
import hashlib
import io
import itertools
import json
import math
import os
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from formats.atomic import write_text
from formats.config_files import read_document
from formats.layouts import is_log
from formats.log import Topics
from relpoint.errors import UsageError
from relpoint.estimators import ESTIMATORS
from relpoint.evaluation import EvaluationSettings
from relpoint.simulation import SimulationConfig

if sys.version_info >= (3, 11):
    pass
else:  # pragma: no cover
    pass

#: Keys of an estimator table that set how the job runs rather than the estimator's config.
RUN_KEYS = ("seed", "use_odometry", "use_fixes")
#: Top-level keys of a plan.
PLAN_KEYS = ("results", "logs", "simulate", "estimators", "evaluation", "topics")
#: Columns of ``results.csv`` (and keys of each ``results.json`` row), in order.
RESULT_COLUMNS = (
    "job",
    "log",
    "estimator",
    "parameters",
    "seed",
    "status",
    "ate_rmse",
    "landmark_rmse",
    "seconds_per_iteration",
    "iterations",
    "landmarks",
    "wall_seconds",
    "cpu_seconds",
    "error",
)
#: Columns that measure time and so differ from run to run.
TIMING_COLUMNS = ("seconds_per_iteration", "wall_seconds", "cpu_seconds")
#: Job outcomes.
STATUSES = ("ok", "failed", "cancelled")

_UNSAFE = re.compile(r"[^A-Za-z0-9._=+-]+")
_MAX_NAME = 80


Items = tuple[tuple[str, Any], ...]


@dataclass(frozen=True)
class SimulationStep:
    """One simulated log the plan asks for.

    Attributes
    ----------
    name: the log's name (``RESULTS/logs/NAME.mcap``).
    output: absolute path of the log.
    config: the validated simulation settings.
    """

    name: str
    output: Path
    config: SimulationConfig


@dataclass(frozen=True)
class Job:
    """One estimator run over one log with one parameter set, and its evaluation.

    Attributes
    ----------
    job_id: ``LOG/ESTIMATOR/GRID``, the job's directory relative to the results root.
    log: absolute path of the input log.
    estimator: name in :data:`relpoint.estimators.ESTIMATORS`.
    parameters: estimator config overrides (fixed and grid values), sorted by name.
    seed: seed of the estimator's random draws.
    use_odometry, use_fixes: hand ``/odom`` and ``/fix`` to estimators that use them (when present).
    topics: topic renames by role (``formats.log.Topics`` fields).
    evaluation: settings of the trajectory evaluation against the log's ground truth.
    output: absolute path of the job's output directory.
    """

    job_id: str
    log: Path
    estimator: str
    parameters: Items
    seed: int
    use_odometry: bool
    use_fixes: bool
    topics: Items
    evaluation: EvaluationSettings
    output: Path

    def describe(self) -> dict[str, Any]:
        """Plain JSON-able description (what ``job.json`` records and :meth:`spec_hash` covers)."""
        return {
            "job": self.job_id,
            "log": str(self.log),
            "estimator": self.estimator,
            "parameters": dict(self.parameters),
            "seed": self.seed,
            "use_odometry": self.use_odometry,
            "use_fixes": self.use_fixes,
            "topics": dict(self.topics),
            "evaluation": self.evaluation.to_dict(),
        }

    def spec_hash(self) -> str:
        """SHA-256 of :meth:`describe`: a stored output is reused only when this matches."""
        text = json.dumps(self.describe(), sort_keys=True, default=str)
        return hashlib.sha256(text.encode("utf-8")).hexdigest()

    def row_parameters(self) -> dict[str, Any]:
        """The ``parameters`` cell of the results: config overrides plus run switches that are off."""
        values = dict(self.parameters)
        if not self.use_odometry:
            values["use_odometry"] = False
        if not self.use_fixes:
            values["use_fixes"] = False
        return values


@dataclass(frozen=True)
class BatchPlan:
    """A parsed plan: simulated logs to make first, then the jobs, in plan order."""

    source: Path
    results: Path
    simulations: tuple[SimulationStep, ...]
    jobs: tuple[Job, ...]


# --- reading -----------------------------------------------------------------------------------------


def _read_document(path: Path) -> dict[str, Any]:
    data = read_document(path, what="plan")
    unknown = sorted(set(data) - set(PLAN_KEYS))
    if unknown:
        raise UsageError(f"plan {path}: unknown key(s) {', '.join(unknown)}", f"known keys: {', '.join(PLAN_KEYS)}")
    return data


def _table(value: Any, where: str) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise UsageError(f"{where} must be a table, not {type(value).__name__}")
    return {str(k).replace("-", "_"): v for k, v in value.items()}


def expand_grid(fixed: Mapping[str, Any], grid: Mapping[str, Any], where: str) -> list[tuple[dict[str, Any], Items]]:
    """Every combination of ``grid`` (name -> non-empty list) merged over ``fixed``, in row-major order.

    Returns (all values, grid values) per combination; an empty grid gives one combination.
    """
    for name, values in grid.items():
        if not isinstance(values, list) or not values:
            raise UsageError(f"{where}.grid.{name} must be a non-empty list of values")
        if name in fixed:
            raise UsageError(f"{where}: {name} is both fixed and in the grid")
    names = list(grid)
    combinations = []
    for values in itertools.product(*(grid[name] for name in names)):
        swept = tuple(zip(names, values, strict=True))
        combinations.append(({**fixed, **dict(swept)}, swept))
    return combinations


def _slug(swept: Items) -> str:
    """Directory name of a grid point: ``name=value_name=value`` or ``default``; hashed when long."""
    if not swept:
        return "default"
    text = "_".join(f"{name}={_format_value(value)}" for name, value in swept)
    text = _UNSAFE.sub("-", text).strip(".-") or "grid"
    if len(text) > _MAX_NAME:
        digest = hashlib.sha1(text.encode("utf-8")).hexdigest()[:10]
        text = f"{text[: _MAX_NAME - 11]}-{digest}"
    return text


def _format_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _resolve(base: Path, text: str) -> Path:
    path = Path(os.path.expanduser(text))
    return path if path.is_absolute() else base / path


def _glob_logs(base: Path, patterns: Any) -> list[Path]:
    if patterns is None:
        return []
    if isinstance(patterns, str):
        patterns = [patterns]
    if not isinstance(patterns, list) or not all(isinstance(p, str) for p in patterns):
        raise UsageError("plan: logs must be a glob or a list of globs")
    logs: list[Path] = []
    for pattern in patterns:
        matches = sorted(Path(m) for m in glob.glob(str(_resolve(base, pattern)), recursive=True))
        files = [m.resolve() for m in matches if m.is_file() or is_log(m)]  # a rosbag2 bag is a directory
        if not files:
            raise UsageError(f"plan: logs pattern {pattern!r} matches no file", f"patterns are relative to {base}")
        logs.extend(files)
    return logs


def _simulations(entries: Any, results: Path) -> list[SimulationStep]:
    if entries is None:
        return []
    if isinstance(entries, dict):
        entries = [entries]
    if not isinstance(entries, list):
        raise UsageError("plan: simulate must be a list of tables ([[simulate]])")
    steps: list[SimulationStep] = []
    for index, entry in enumerate(entries):
        where = f"simulate[{index}]"
        values = _table(entry, where)
        name = str(values.pop("name", f"sim{index}"))
        if not name or _UNSAFE.search(name) or name.startswith("."):
            raise UsageError(f"{where}: name {name!r} must be a plain file name (letters, digits, . _ = + -)")
        grid = _table(values.pop("grid", None), f"{where}.grid")
        for settings, swept in expand_grid(values, grid, where):
            log_name = name if not swept else f"{name}-{_slug(swept)}"
            try:
                config = SimulationConfig.from_mapping(settings)
            except UsageError as error:
                raise UsageError(f"{where}: {error.message}", error.hint) from None
            steps.append(SimulationStep(log_name, results / "logs" / f"{log_name}.mcap", config))
    names = [step.name for step in steps]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise UsageError(f"plan: simulated log name(s) used twice: {', '.join(duplicates)}")
    return steps


def _estimator_tables(value: Any) -> dict[str, dict[str, Any]]:
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return {name: {} for name in value}
    if isinstance(value, dict):
        return {str(name): _table(table, f"estimators.{name}") for name, table in value.items()}
    raise UsageError("plan: estimators must be a list of names or a table of estimator tables")


def _run_options(values: dict[str, Any], where: str) -> tuple[int, bool, bool]:
    seed = values.pop("seed", 0)
    use_odometry = values.pop("use_odometry", True)
    use_fixes = values.pop("use_fixes", True)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise UsageError(f"{where}: seed must be a non-negative integer, got {seed!r}")
    for name, flag in (("use_odometry", use_odometry), ("use_fixes", use_fixes)):
        if not isinstance(flag, bool):
            raise UsageError(f"{where}: {name} must be true or false, got {flag!r}")
    return seed, use_odometry, use_fixes


def _estimator_config(name: str, values: dict[str, Any], where: str) -> None:
    """Validate ``values`` by building the estimator's config (raises UsageError like ``relpoint run``)."""
    try:
        ESTIMATORS[name].build_config(values)
    except UsageError as error:
        raise UsageError(f"{where}: {error.message}", error.hint) from None


def _log_labels(logs: Sequence[Path]) -> dict[Path, str]:
    """A directory name per log: its stem, with a path hash where stems clash."""
    stems = [log.stem for log in logs]
    labels = {}
    for log, stem in zip(logs, stems, strict=True):
        label = _UNSAFE.sub("-", stem).strip(".") or "log"
        if label == "logs":  # RESULTS/logs holds the simulated logs
            label = "logs-run"
        if stems.count(stem) > 1:
            label += "-" + hashlib.sha1(str(log).encode("utf-8")).hexdigest()[:8]
        labels[log] = label
    return labels


def load_plan(path: str | os.PathLike[str], results: str | os.PathLike[str] | None = None) -> BatchPlan:
    """Parse and validate a plan file into a :class:`BatchPlan`.

    Paths in the plan (``results``, ``logs`` globs) are relative to the plan's directory; ``results``
    (``--results``) overrides the plan's results root and is relative to the working directory. Globs
    are expanded now, so logs that appear later are not picked up by this plan.

    Raises
    ------
    UsageError
        Unreadable or malformed plan, unknown keys, estimators or parameters, invalid values, globs that
        match nothing, or a plan without logs or estimators.
    """
    source = Path(path).resolve()
    data = _read_document(source)
    base = source.parent
    if results is not None:
        root = Path(results).resolve()
    else:
        if not isinstance(data.get("results", "results"), str):
            raise UsageError("plan: results must be a directory path")
        root = _resolve(base, data.get("results", "results")).resolve()

    simulations = _simulations(data.get("simulate"), root)
    logs = _glob_logs(base, data.get("logs"))
    logs = list(dict.fromkeys([*logs, *(step.output for step in simulations)]))
    if not logs:
        raise UsageError(f"plan {source} names no logs", 'add logs = ["GLOB", ...] or [[simulate]] steps')

    topics_table = _table(data.get("topics"), "topics")
    try:
        Topics(**topics_table)
    except TypeError:
        known = ", ".join(f.name for f in dataclasses.fields(Topics))
        raise UsageError(f"plan: unknown topic role(s) in topics; known roles: {known}") from None
    topics = tuple(sorted((str(k), str(v)) for k, v in topics_table.items()))

    evaluation_table = _table(data.get("evaluation"), "evaluation")
    known_settings = {f.name for f in dataclasses.fields(EvaluationSettings)}
    unknown = sorted(set(evaluation_table) - known_settings)
    if unknown:
        raise UsageError(f"plan: unknown evaluation setting(s) {', '.join(unknown)}")
    try:
        evaluation = EvaluationSettings(**evaluation_table)
    except (TypeError, ValueError) as error:
        raise UsageError(f"plan: bad evaluation setting: {error}") from None

    tables = _estimator_tables(data.get("estimators"))
    if not tables:
        raise UsageError(f"plan {source} names no estimators")
    points: list[tuple[str, dict[str, Any], Items]] = []
    for name, table in tables.items():
        where = f"estimators.{name}"
        if name not in ESTIMATORS:
            raise UsageError(f"{where}: unknown estimator {name!r}", f"choose from {', '.join(sorted(ESTIMATORS))}")
        grid = _table(table.pop("grid", None), f"{where}.grid")
        for values, swept in expand_grid(table, grid, where):
            points.append((name, values, swept))

    labels = _log_labels(logs)
    jobs: list[Job] = []
    for log in logs:
        for name, values, swept in points:
            where = f"estimators.{name}"
            config_values = dict(values)
            seed, use_odometry, use_fixes = _run_options(config_values, where)
            _estimator_config(name, config_values, where)
            job_id = f"{labels[log]}/{name}/{_slug(swept)}"
            jobs.append(
                Job(
                    job_id=job_id, log=log, estimator=name, parameters=tuple(sorted(config_values.items())),
                    seed=seed, use_odometry=use_odometry, use_fixes=use_fixes, topics=topics,
                    evaluation=evaluation, output=root / job_id,
                )
            )  # fmt: skip
    ids = [job.job_id for job in jobs]
    clashes = sorted({i for i in ids if ids.count(i) > 1})
    if clashes:
        raise UsageError(f"plan: grid values give the same job directory twice: {', '.join(clashes[:3])}")
    return BatchPlan(source=source, results=root, simulations=tuple(simulations), jobs=tuple(jobs))


# --- results -----------------------------------------------------------------------------------------


def _finite_or_none(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def results_document(rows: Iterable[Mapping[str, Any]], plan: BatchPlan) -> dict[str, Any]:
    """The ``results.json`` document: plan, results root, counts by status and one row per job."""
    rows = [{key: _finite_or_none(row.get(key)) for key in RESULT_COLUMNS} for row in rows]
    counts = {status: sum(row["status"] == status for row in rows) for status in STATUSES}
    return {"plan": str(plan.source), "results": str(plan.results), "counts": counts, "jobs": rows}


def results_csv(rows: Iterable[Mapping[str, Any]]) -> str:
    """``results.csv`` text: :data:`RESULT_COLUMNS`, parameters as compact JSON, missing numbers empty."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(RESULT_COLUMNS)
    for row in rows:
        cells = []
        for key in RESULT_COLUMNS:
            value = _finite_or_none(row.get(key))
            if key == "parameters":
                cells.append(json.dumps(value or {}, sort_keys=True, separators=(",", ":")))
            elif value is None:
                cells.append("")
            elif isinstance(value, float):
                cells.append(repr(value))
            else:
                cells.append(str(value))
        writer.writerow(cells)
    return buffer.getvalue()


def write_results(plan: BatchPlan, rows: Sequence[Mapping[str, Any]]) -> tuple[Path, Path]:
    """Write ``results.csv`` and ``results.json`` under the results root, each atomically."""
    csv_path = plan.results / "results.csv"
    json_path = plan.results / "results.json"
    write_text(csv_path, results_csv(rows))
    document = results_document(rows, plan)
    write_text(json_path, json.dumps(document, indent=2, sort_keys=True, allow_nan=False) + "\n")
    return csv_path, json_path


def read_results(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Rows of a ``results.json`` (for comparing batches and in tests)."""
    document = json.loads(Path(path).read_text(encoding="utf-8"))
    return list(document["jobs"])
