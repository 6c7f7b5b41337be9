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
import logging
import math
import os
import re
import stat
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from formats.atomic import write_text
from formats.config_files import read_document
from formats.outputs import MARKER, OutputError, check_output_file, json_object, probe_writable, register_csv_header
from formats.signatures import is_log
from formats.topics import Topics
from relpoint.errors import UsageError
from relpoint.estimators import ESTIMATORS
from relpoint.evaluation import EvaluationSettings
from relpoint.settings import Settings, setting
from relpoint.simulation import SimulationConfig
from relpoint_app.batch_start import MAX_JOBS

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


log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunOptions(Settings):
    """How a job runs beside its estimator's config: the run keys of an estimator table (or its grid)."""

    settings_name: ClassVar[str] = "run"

    seed: int = setting(0, low=0, high=math.inf)
    """Seed of the estimator's random draws."""
    use_odometry: bool = True
    """Hand ``/odom`` to estimators that use it (when the log has it); false is ``relpoint run --no-odometry``."""
    use_fixes: bool = True
    """Hand ``/fix`` to estimators that use it (when the log has it); false is ``relpoint run --no-fixes``."""


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


def grid_size(fixed: Mapping[str, Any], grid: Mapping[str, Any], where: str) -> int:
    """Number of combinations of ``grid`` (name -> non-empty list), checked but not expanded.

    Raises :class:`UsageError` for a value that is not a non-empty list, or a name also in ``fixed``.
    """
    for name, values in grid.items():
        if not isinstance(values, list) or not values:
            raise UsageError(f"{where}.grid.{name} must be a non-empty list of values")
        if name in fixed:
            raise UsageError(f"{where}: {name} is both fixed and in the grid")
    return math.prod(len(values) for values in grid.values())


def expand_grid(fixed: Mapping[str, Any], grid: Mapping[str, Any], where: str) -> list[tuple[dict[str, Any], Items]]:
    """Every combination of ``grid`` (name -> non-empty list) merged over ``fixed``, in row-major order.

    Returns (all values, grid values) per combination; an empty grid gives one combination. Callers
    bound :func:`grid_size` first: the list holds every combination.
    """
    grid_size(fixed, grid, where)
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


def _inside_output(folder: str, results: str, verdicts: dict[str, bool]) -> bool:
    """Whether the resolved directory ``folder`` is ``results``, or in it, or in a directory relpoint
    wrote (one holding :data:`~formats.outputs.MARKER`).

    ``verdicts`` caches the answer per directory, so a glob of N files costs O(N) directory checks.
    """
    chain: list[str] = []
    while folder not in verdicts:
        chain.append(folder)
        if folder == results or os.path.isfile(os.path.join(folder, MARKER)):
            verdict = True
            break
        parent = os.path.dirname(folder)
        if parent == folder:
            verdict = False
            break
        folder = parent
    else:
        verdict = verdicts[folder]
    verdicts.update(dict.fromkeys(chain, verdict))
    return verdict


class _Resolver:
    """``os.path.realpath`` of files, resolving each directory once (a glob's files share a few)."""

    def __init__(self) -> None:
        self._folders: dict[str, str] = {}
        self._bags: dict[str, bool] = {}

    def _in_bag(self, folder: str) -> bool:
        if folder not in self._bags:
            self._bags[folder] = is_log(folder)
        return self._bags[folder]

    def file(self, text: str) -> str | None:
        """The real path of ``text`` if it is a regular file (or a link to one) outside a rosbag2 bag, or
        a rosbag2 bag directory; else None (a bag's storage files are read through its directory)."""
        try:
            mode = os.lstat(text).st_mode
        except OSError:
            return None
        if stat.S_ISDIR(mode) or (stat.S_ISLNK(mode) and os.path.isdir(text)):
            return os.path.realpath(text) if is_log(text) else None
        if stat.S_ISLNK(mode):
            real = os.path.realpath(text)
            return real if os.path.isfile(real) and not self._in_bag(os.path.dirname(real)) else None
        if not stat.S_ISREG(mode):
            return None
        if self._in_bag(os.path.dirname(os.path.abspath(text))):
            return None
        folder, name = os.path.split(os.path.abspath(text))
        real_folder = self._folders.get(folder)
        if real_folder is None:
            real_folder = self._folders[folder] = os.path.realpath(folder)
        return os.path.join(real_folder, name)


def _glob_logs(base: Path, patterns: Any, results: Path, limit: int) -> tuple[list[Path], int]:
    """Logs the ``logs`` globs match, in pattern order, each pattern's matches sorted; and their count.

    A glob (a pattern with ``*``, ``?`` or ``[``) leaves out files inside ``results`` and inside any
    relpoint output directory, so a batch never reads its own or another run's outputs as logs; a
    plain path is taken as given. Only the first ``limit`` logs are returned (the count goes on), so
    a glob over a huge tree costs no memory beyond the plan's job limit.
    """
    if patterns is None:
        return [], 0
    if isinstance(patterns, str):
        patterns = [patterns]
    if not isinstance(patterns, list) or not all(isinstance(p, str) for p in patterns):
        raise UsageError("plan: logs must be a glob or a list of globs")
    logs: list[Path] = []
    count = 0
    resolver = _Resolver()
    verdicts: dict[str, bool] = {}
    for pattern in patterns:
        matches: list[tuple[str, str]] = []  # (sort key, real path)
        left_out = 0
        for text in glob.iglob(str(_resolve(base, pattern)), recursive=True):
            real = resolver.file(text)
            if real is None:
                continue
            if glob.has_magic(pattern) and _inside_output(os.path.dirname(real), str(results), verdicts):
                left_out += 1
                continue
            count += 1
            if count <= limit:
                matches.append((text.replace(os.sep, "\0"), real))  # sorts as paths do: by component
        if not matches and count <= limit:
            outputs = f" ({left_out} inside relpoint outputs left out)" if left_out else ""
            raise UsageError(
                f"plan: logs pattern {pattern!r} matches no file{outputs}", f"patterns are relative to {base}"
            )
        if left_out:
            log.info("logs pattern %r: left out %d file(s) inside relpoint outputs", pattern, left_out)
        matches.sort()
        logs.extend(Path(real) for _, real in matches)
    return logs, count


def _simulation_entries(entries: Any) -> list[tuple[str, str, dict[str, Any], dict[str, Any]]]:
    """``(where, name, fixed settings, grid)`` of each ``[[simulate]]`` table, checked but not expanded."""
    if entries is None:
        return []
    if isinstance(entries, dict):
        entries = [entries]
    if not isinstance(entries, list):
        raise UsageError("plan: simulate must be a list of tables ([[simulate]])")
    parsed = []
    for index, entry in enumerate(entries):
        where = f"simulate[{index}]"
        values = _table(entry, where)
        name = str(values.pop("name", f"sim{index}"))
        if not name or _UNSAFE.search(name) or name.startswith("."):
            raise UsageError(f"{where}: name {name!r} must be a plain file name (letters, digits, . _ = + -)")
        grid = _table(values.pop("grid", None), f"{where}.grid")
        grid_size(values, grid, where)
        parsed.append((where, name, values, grid))
    return parsed


def _simulations(entries: list[tuple[str, str, dict[str, Any], dict[str, Any]]], results: Path) -> list[SimulationStep]:
    steps: list[SimulationStep] = []
    for where, name, values, grid in entries:
        for settings, swept in expand_grid(values, grid, where):
            log_name = name if not swept else f"{name}-{_slug(swept)}"
            try:
                config = SimulationConfig.from_mapping(settings)
            except UsageError as error:
                raise UsageError(f"{where}: {error.message}", error.hint) from None
            steps.append(SimulationStep(log_name, results / "logs" / f"{log_name}.mcap", config))
    duplicates = sorted(name for name, uses in Counter(step.name for step in steps).items() if uses > 1)
    if duplicates:
        raise UsageError(f"plan: simulated log name(s) used twice: {', '.join(duplicates)}")
    return steps


def _estimator_tables(value: Any) -> dict[str, tuple[dict[str, Any], dict[str, Any]]]:
    """``name -> (fixed values, grid)`` of the plan's estimators, checked but not expanded."""
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        tables = {name: {} for name in value}
    elif isinstance(value, dict):
        tables = {str(name): _table(table, f"estimators.{name}") for name, table in value.items()}
    else:
        raise UsageError("plan: estimators must be a list of names or a table of estimator tables")
    parsed = {}
    for name, table in tables.items():
        where = f"estimators.{name}"
        if name not in ESTIMATORS:
            raise UsageError(f"{where}: unknown estimator {name!r}", f"choose from {', '.join(sorted(ESTIMATORS))}")
        grid = _table(table.pop("grid", None), f"{where}.grid")
        grid_size(table, grid, where)
        parsed[name] = (table, grid)
    return parsed


def _run_options(values: dict[str, Any], where: str) -> RunOptions:
    """The run keys taken out of an estimator's ``values`` (the rest is its config)."""
    keys = [field.name for field in dataclasses.fields(RunOptions)]
    options = {key: values.pop(key) for key in keys if key in values}
    try:
        return RunOptions.from_mapping(options)
    except UsageError as error:
        raise UsageError(f"{where}: {error.message}", error.hint) from None


def _estimator_config(name: str, values: dict[str, Any], where: str) -> None:
    """Validate ``values`` by building the estimator's config (raises UsageError like ``relpoint run``)."""
    try:
        ESTIMATORS.config_class(name).from_strings((), base=values)
    except UsageError as error:
        raise UsageError(f"{where}: {error.message}", error.hint) from None


@dataclass(frozen=True)
class _GridPoint:
    """One estimator with one parameter set: the part of a job that does not depend on the log."""

    estimator: str
    directory: str
    parameters: Items
    options: RunOptions


def _grid_points(tables: Mapping[str, tuple[dict[str, Any], dict[str, Any]]]) -> list[_GridPoint]:
    """Every estimator's grid points, each config validated once; distinct directories per point."""
    points: list[_GridPoint] = []
    seen: set[str] = set()
    for name, (fixed, grid) in tables.items():
        where = f"estimators.{name}"
        for values, swept in expand_grid(fixed, grid, where):
            config_values = dict(values)
            options = _run_options(config_values, where)
            _estimator_config(name, config_values, where)
            directory = f"{name}/{_slug(swept)}"
            if directory in seen:
                raise UsageError(f"plan: grid values of {where} give the job directory {directory} twice",
                                 "make the values differ in their text")  # fmt: skip
            seen.add(directory)
            points.append(_GridPoint(name, directory, tuple(sorted(config_values.items())), options))
    return points


def _log_labels(logs: Sequence[Path]) -> dict[Path, str]:
    """A directory name per log: its stem, with a path hash where stems clash.

    Raises :class:`UsageError` naming both paths when two different stems reduce to the same name
    (``a b.mcap`` and ``a-b.mcap``: characters outside letters, digits and ``. _ = + -`` become ``-``).
    """
    stems = {log: log.stem for log in logs}
    uses = Counter(stems.values())
    labels: dict[Path, str] = {}
    owners: dict[str, Path] = {}
    for log, stem in stems.items():
        label = _UNSAFE.sub("-", stem).strip(".") or "log"
        if label == "logs":  # RESULTS/logs holds the simulated logs
            label = "logs-run"
        if uses[stem] > 1:
            label += "-" + hashlib.sha1(str(log).encode("utf-8")).hexdigest()[:8]
        other = owners.setdefault(label, log)
        if other != log:
            raise UsageError(f"plan: logs {other} and {log} both give the job directory name {label}",
                             "rename one of them (only letters, digits and . _ = + - are kept)")  # fmt: skip
        labels[log] = label
    return labels


def load_plan(
    path: str | os.PathLike[str], results: str | os.PathLike[str] | None = None, *, max_jobs: int = MAX_JOBS
) -> BatchPlan:
    """Parse and validate a plan file into a :class:`BatchPlan`.

    Paths in the plan (``results``, ``logs`` globs) are relative to the plan's directory; ``results``
    (``--results``) overrides the plan's results root and is relative to the working directory. Globs
    are expanded now, so logs that appear later are not picked up by this plan; they never pick up
    files inside the results root or inside a relpoint output directory.

    The number of jobs (logs x grid points) is counted from the globs and the grids' lengths before
    any grid is expanded; a plan of more than ``max_jobs`` jobs is refused. Loading is linear in the
    number of jobs.

    Raises
    ------
    UsageError
        Unreadable or malformed plan, unknown keys, estimators or parameters, invalid values, globs that
        match nothing, a plan without logs or estimators, more than ``max_jobs`` jobs, or two logs or
        grid points that would share a job directory.
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

    simulation_entries = _simulation_entries(data.get("simulate"))
    tables = _estimator_tables(data.get("estimators"))
    if not tables:
        raise UsageError(f"plan {source} names no estimators")
    simulated = sum(grid_size(values, grid, where) for where, _, values, grid in simulation_entries)
    per_log = sum(grid_size(fixed, grid, f"estimators.{name}") for name, (fixed, grid) in tables.items())
    logs, globbed = _glob_logs(base, data.get("logs"), root, limit=max(0, max_jobs // per_log - simulated))
    jobs_count = (globbed + simulated) * per_log
    if jobs_count > max_jobs:
        raise UsageError(
            f"plan {source} makes {jobs_count:,} jobs ({globbed + simulated:,} log(s) x {per_log:,} grid point(s)), "
            f"more than --max-jobs {max_jobs:,}",
            f"narrow the logs or grids, or pass --max-jobs {jobs_count} to run them all",
        )
    if not logs and not simulated:
        raise UsageError(f"plan {source} names no logs", 'add logs = ["GLOB", ...] or [[simulate]] steps')

    simulations = _simulations(simulation_entries, root)
    logs = list(dict.fromkeys([*logs, *(step.output for step in simulations)]))

    topics_table = _table(data.get("topics"), "topics")
    try:
        Topics(**topics_table)
    except TypeError:
        known = ", ".join(f.name for f in dataclasses.fields(Topics))
        raise UsageError(f"plan: unknown topic role(s) in topics; known roles: {known}") from None
    topics = tuple(sorted((str(k), str(v)) for k, v in topics_table.items()))

    try:
        evaluation = EvaluationSettings.from_mapping(_table(data.get("evaluation"), "evaluation"))
    except UsageError as error:
        raise UsageError(f"plan: {error.message}", error.hint) from None

    points = _grid_points(tables)
    jobs = [
        Job(
            job_id=f"{label}/{point.directory}", log=log, estimator=point.estimator, parameters=point.parameters,
            seed=point.options.seed, use_odometry=point.options.use_odometry, use_fixes=point.options.use_fixes,
            topics=topics, evaluation=evaluation, output=root.joinpath(label, point.directory),
        )
        for log, label in _log_labels(logs).items()  # in the order of ``logs``
        for point in points
    ]  # fmt: skip
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


register_csv_header(RESULT_COLUMNS)


def _results_json_of_a_batch(path: Path) -> bool:
    """Whether ``path`` is a ``results.json`` that :func:`write_results` wrote."""
    document = json_object(path, 200_000_000)
    return document is not None and {"plan", "results", "counts", "jobs"} <= set(document)


def check_outputs(plan: BatchPlan) -> None:
    """Check, before any job runs, that the batch replaces only what relpoint wrote.

    ``results.csv`` and ``results.json`` may replace only earlier batch results, and a simulated log
    only a log relpoint wrote; the results root must be writable. Job directories are checked as they
    are written (:func:`formats.atomic.atomic_directory` replaces only a relpoint output). Raises
    :class:`~formats.outputs.OutputError` (exit 2) naming the file and the way out.
    """
    hint = "move it away or choose another results root (--results DIR)"
    for path in (plan.results / "results.csv", plan.results / "results.json"):
        if not (path.exists() or path.is_symlink()):
            continue
        ours = _results_json_of_a_batch(path) if path.suffix == ".json" else None
        try:
            check_output_file(path, inputs=[plan.source], overwrite=bool(ours))
        except OutputError as error:
            raise OutputError(error.message, hint) from None
    for step in plan.simulations:
        if step.output.exists() or step.output.is_symlink():
            try:
                check_output_file(step.output, inputs=[plan.source])
            except OutputError as error:
                raise OutputError(f"simulated log {step.name}: {error.message}", hint) from None
    probe_writable(plan.results, plan.results)


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
