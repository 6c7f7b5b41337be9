"""``relpoint fuse``'s work: place a run's local SLAM segments in the fixes' frame (Algorithm 3 post-step).

Reads a run's output directory (``trajectory.tum``, ``map.csv``, ``timing.csv``, ``run.json``) and the
log's position fixes, calls :func:`relpoint.fusion.fuse`, and writes a new output directory like every
run (the global path and map) plus ``segments/`` with each segment's path and map. With ``restart``
the run's estimator runs again through the one drive loop (:func:`relpoint_app.runner.drive`) inside
a :class:`~relpoint.fusion.segmented.RestartingEstimator`.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

import relpoint
from formats.atomic import atomic_directory
from formats.log import LogReader
from formats.outputs import check_output_directory, shown_path, unreadable_input
from formats.ply import read_ply
from formats.run_output import write_run_directory
from formats.tables import read_map_csv, write_map_csv
from formats.trajectory_files import read_tum, write_tum
from relpoint.errors import InputError, UsageError
from relpoint.estimators import ESTIMATORS, SIMULATOR_SIGMA
from relpoint.fusion import FusionConfig, FusionResult, fuse, matched_counts_from_map_growth
from relpoint.fusion.segmented import RestartingEstimator, RestartRule
from relpoint.screening import InputScreen
from relpoint.types import LandmarkMap, RunResult
from relpoint_app.roles import NEED_ROLES
from relpoint_app.run_inputs import check_same_log, log_record
from relpoint_app.runner import drive


def read_timing(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``observed``, ``map_size`` and ``seconds`` columns of a run's ``timing.csv``."""
    try:
        with path.open(newline="", encoding="utf-8") as stream:
            rows = list(csv.DictReader(stream))
    except OSError as error:
        raise unreadable_input(path, error) from None
    try:
        observed = np.array([int(r["observed"]) for r in rows], dtype=np.int64)
        map_size = np.array([int(r["map_size"]) for r in rows], dtype=np.int64)
        seconds = np.array([float(r["seconds"]) for r in rows], dtype=np.float64)
    except (KeyError, ValueError, TypeError) as error:
        raise InputError(f"{path}: not a relpoint timing.csv ({error})") from None
    return observed, map_size, seconds


def fuse_run(
    run_dir: Path,
    log_path: Path,
    output: Path,
    config: FusionConfig,
    *,
    restart: bool,
    topics: Any,
    overwrite: bool,
    other_log: bool = False,
) -> FusionResult:
    """What ``relpoint fuse`` does after parsing its options: fuse ``run_dir`` (or, with ``restart``,
    a re-run of its estimator) with the fixes of ``log_path`` and write ``output``; the fusion result.

    Without ``restart``, ``log_path`` must be the log the run was made from (its run.json's hash), unless
    ``other_log`` (the same recording in another bag layout hashes differently)."""
    output = check_output_directory(output, command="fuse", inputs=[run_dir, log_path], overwrite=overwrite)
    previous = _read_run(run_dir, need_outputs=not restart)
    reader = LogReader(log_path, topics)
    if not restart and not other_log:  # the run's outputs are fused with this log's fixes: one log
        recorded = previous.get("input") if isinstance(previous.get("input"), dict) else {}
        check_same_log(log_path, recorded, run_dir, "give --log the log the run was made from "
                       "(--other-log if LOG is that recording in another layout), or --restart to run over LOG")  # fmt: skip
    start = time.perf_counter()
    if restart:
        result, observed, map_size, seconds, roles = _restarted(previous, reader, config)
    else:
        trajectory = read_tum(run_dir / "trajectory.tum")
        landmarks = _with_first_iterations(read_map_csv(run_dir / "map.csv"), run_dir / "map.ply")
        observed, map_size, seconds = read_timing(run_dir / "timing.csv")
        if len(observed) != len(trajectory):
            raise InputError(f"{run_dir}: timing.csv has {len(observed)} rows for {len(trajectory)} poses")
        screen = InputScreen()  # as a run's fixes are: unusable ones dropped, unfilled axes unmeasured
        fixes = [fix for fix in (screen.fix(record.value) for record in reader.records(["fix"])) if fix is not None]
        if not fixes and screen.skipped:
            reasons = "; ".join(f"{count} {kind.split(': ', 1)[-1]}" for kind, count in sorted(screen.skipped.items()))
            raise InputError(f"{log_path}: no usable position fix ({reasons})",
                             "fixes need a finite position and a position covariance (not all zero)")  # fmt: skip
        matched = matched_counts_from_map_growth(observed, map_size)
        result = fuse(trajectory, landmarks, matched, fixes, config, map_size=map_size)
        roles = ["fix"]
    elapsed = time.perf_counter() - start

    segments = [
        {
            "segment": s.index,
            "local_map": s.local_map,
            "first_iteration": int(s.iterations[0]),
            "last_iteration": int(s.iterations[-1]),
            "iterations": len(s.iterations),
            "landmarks": len(s.landmark_rows),
            "placed": s.transform is not None,
            **(
                {"fix_pairs": s.transform.pairs, "fit_rms_m": s.transform.rms,
                 "T_world_local": s.transform.matrix.tolist()}
                if s.transform is not None else {"refused": s.refused}
            ),
        }
        for s in result.segments
    ]  # fmt: skip
    run_result = RunResult(
        trajectory=result.trajectory,
        landmarks=result.landmarks,
        observed=observed,
        map_size=map_size,
        seconds=seconds,
        summary={**result.summary, "fusion_seconds": elapsed, "restart": restart},
    )
    fusion_settings = {k: (v if np.isfinite(v) else str(v)) if isinstance(v, float) else v
                       for k, v in config.to_dict().items()}  # fmt: skip
    run_info = {
        "estimator": f"fuse({previous.get('estimator', 'unknown')})",
        "fusion": fusion_settings,
        "segments": segments,
        "source_run": {"path": shown_path(os.path.abspath(run_dir)), "estimator": previous.get("estimator"),
                       "parameters": previous.get("parameters"), "seed": previous.get("seed")},
        "relpoint_version": relpoint.__version__,
        "input": {**log_record(log_path), "roles": sorted(roles),
                  "topics": {role: reader.topics.roles()[role] for role in sorted(roles)}},
    }  # fmt: skip
    with atomic_directory(output, command="fuse") as tmp:
        write_run_directory(tmp, run_result, run_info)
        folder = tmp / "segments"
        folder.mkdir()
        for s in result.segments:
            if s.global_trajectory is not None and s.global_landmarks is not None:
                write_tum(folder / f"segment-{s.index}.tum", s.global_trajectory)
                write_map_csv(folder / f"segment-{s.index}-map.csv", s.global_landmarks)
            else:  # left out: kept in its local frame, named so
                write_tum(folder / f"segment-{s.index}-local.tum", s.local_trajectory)
                write_map_csv(folder / f"segment-{s.index}-local-map.csv", s.local_landmarks)
    return result


def _read_run(run_dir: Path, *, need_outputs: bool) -> dict[str, Any]:
    """The run's run.json (empty if absent and not needed); checks the files the post-step reads."""
    names = ("trajectory.tum", "map.csv", "timing.csv") if need_outputs else ("run.json",)
    for name in names:
        if not (run_dir / name).is_file():
            raise InputError(f"{run_dir}: no {name}", "give the output directory of `relpoint run`")
    if not (run_dir / "run.json").is_file():
        return {}
    try:
        document = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise InputError(f"{run_dir / 'run.json'}: not readable JSON ({error})") from None
    return document if isinstance(document, dict) else {}


def _with_first_iterations(landmarks: LandmarkMap, ply: Path) -> LandmarkMap:
    """``landmarks`` with the iteration each was first observed, from the run's ``map.ply`` when it
    holds them for the same landmarks (``fuse`` gives each landmark to its local map by them); as it
    is otherwise (a run of an older relpoint, another tool's files)."""
    if landmarks.first_iteration is not None or len(landmarks) == 0 or not ply.is_file():
        return landmarks
    try:
        vertices = read_ply(ply)
    except InputError:
        return landmarks
    names = vertices.dtype.names or ()
    if "first_iteration" not in names or len(vertices) != len(landmarks):
        return landmarks
    return dataclasses.replace(landmarks, first_iteration=np.asarray(vertices["first_iteration"], dtype=np.int64))


def _with_noise_of(previous: dict[str, Any], parameters: dict[str, Any], config_class: type) -> dict[str, Any]:
    """``parameters`` with the observation noise the previous run used, when it estimated it.

    Every restarted local SLAM must use one noise, known from its first step: one that estimates it
    would hold its first observations back and break the segmentation. A run.json from before the
    noise was estimated used the simulator's 0.3 m.
    """
    if "observation_sigma" not in {f.name for f in dataclasses.fields(config_class)}:
        return parameters
    if parameters.get("observation_sigma") is not None:
        return parameters
    sigma = (previous.get("summary") or {}).get("observation_sigma")
    valid = isinstance(sigma, int | float) and not isinstance(sigma, bool) and 0 < sigma < math.inf
    return {**parameters, "observation_sigma": float(sigma) if valid else SIMULATOR_SIGMA}


def _restarted(
    previous: dict[str, Any], reader: LogReader, config: FusionConfig
) -> tuple[FusionResult, np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Re-run the estimator of ``previous`` (run.json) restarting per segment, then fuse."""
    name = previous.get("estimator")
    if name not in ESTIMATORS:
        raise InputError(f"run.json names estimator {name!r}, which --restart cannot re-run",
                         f"known estimators: {', '.join(sorted(ESTIMATORS))}")  # fmt: skip
    spec = ESTIMATORS[name]
    if "points" not in spec.needs:
        raise InputError(f"--restart re-runs point estimators; run.json names {name}, which reads depth frames",
                         "fuse the finished run without --restart")  # fmt: skip
    parameters = previous.get("parameters") or {}
    parameters = _with_noise_of(previous, parameters if isinstance(parameters, dict) else {}, spec.config_class)
    try:
        estimator_config = spec.build_config(parameters)
    except UsageError as error:
        raise InputError(f"run.json parameters do not fit {name}: {error}") from None
    seed = int(previous.get("seed", 0))
    needed = [role for need in sorted(spec.needs) for role in NEED_ROLES.get(need, (need,))]
    reader.require(*needed)
    used = set((previous.get("input") or {}).get("roles") or [])
    optional = [role for role in ("odometry",) if role in used and reader.role_present(role)]
    roles = [*needed, *optional, "fix"]
    rule = RestartRule(
        min_matches=config.min_matches,
        min_length=config.min_segment_length,
        max_position_error=config.max_position_error,
        local_sigma=config.local_sigma,
        drift_fraction=config.drift_fraction,
    )
    restarting = RestartingEstimator(lambda: spec.factory(estimator_config, np.random.default_rng(seed)), rule)
    run = restarting.segmented(drive(reader, restarting, roles))
    if not run.fixes and reader.role_present("fix"):
        raise InputError(f"{reader.path}: no usable position fix (every one skipped; see the warnings above)",
                         "fixes need a finite position and a position covariance (not all zero)")  # fmt: skip
    result = fuse(
        run.trajectory, run.landmarks, None, run.fixes, config, labels=run.labels, landmark_labels=run.landmark_labels
    )
    return result, run.observed, run.map_size, run.seconds, roles
