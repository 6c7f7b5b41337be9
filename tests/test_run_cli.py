"""``relpoint run``: the output directory, parameters, topic errors and skipped data."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from formats.log import LogReader, LogWriter
from formats.outputs import MARKER, RUN_FILES
from formats.ply import read_ply
from formats.trajectory_files import read_tum
from relpoint.estimators import ESTIMATORS
from relpoint.types import PointObservation
from relpoint_cli.main import cli

ESTIMATOR = "ekf"


def invoke(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(cli, list(args))
    return result.exit_code, result.stderr


def test_run_writes_every_output_file(tmp_path: Path, small_log: Path) -> None:
    out = tmp_path / "out"
    code, err = invoke("-q", "run", str(small_log), "--estimator", ESTIMATOR, "-o", str(out))
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == sorted([*RUN_FILES, MARKER])
    trajectory = read_tum(out / "trajectory.tum")
    truth = [r.value for r in LogReader(small_log).records(["ground_truth_pose"])]
    assert len(trajectory) == len(truth) == 120
    np.testing.assert_array_equal(trajectory.stamps_ns, [p.stamp_ns for p in truth])
    # The estimate follows the truth: the first pose is the identity and the simulated start is too.
    error = np.linalg.norm(trajectory.positions - np.array([p.position for p in truth]), axis=1)
    assert error.max() < 5.0
    with (out / "map.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    vertices = read_ply(out / "map.ply")
    assert len(rows) == len(vertices) > 20
    assert {"observations", "dynamic", "gt_id"} <= set(vertices.dtype.names)
    document = json.loads((out / "run.json").read_text())
    assert document["estimator"] == ESTIMATOR and len(document["input"]["sha256"]) == 64
    assert document["summary"]["iterations"] == 120 and document["timing"]["iterations"] == 120
    result = LogReader(out / "result.mcap")
    assert result.topic_infos["/relpoint/pose"].count == 120 and result.topic_infos["/tf"].count == 120
    assert result.topic_infos["/relpoint/map"].count > 10  # the map as it grew, then the final map
    assert result.topic_infos["/relpoint/path"].count >= 2 and result.topic_infos["/relpoint/observations"].count == 120


def test_unknown_estimator_and_parameters_are_usage_errors(tmp_path: Path, small_log: Path) -> None:
    code, err = invoke("run", str(small_log), "--estimator", "magic", "-o", str(tmp_path / "o"))
    assert code == 2 and "unknown estimator 'magic'" in err
    code, err = invoke(
        "run", str(small_log), "--estimator", ESTIMATOR, "--param", "no_such=1", "-o", str(tmp_path / "o")
    )
    assert code == 2 and "unknown ekf setting(s): no_such; see `relpoint config --estimator ekf`" in err
    assert not (tmp_path / "o").exists()


def test_a_config_file_with_only_another_estimators_table_says_so(tmp_path: Path, small_log: Path) -> None:
    config = tmp_path / "params.toml"
    config.write_text("[relpoint]\nmax_iterations = 5\n")
    code, err = invoke("run", str(small_log), "-e", ESTIMATOR, "--config", str(config), "-o", str(tmp_path / "o"))
    assert code == 2 and "[relpoint] is for another estimator or command, and the file has no [ekf] table" in err
    assert "put ekf's settings under [ekf] (the other tables are then ignored)" in err
    assert not (tmp_path / "o").exists()


def test_a_negative_seed_is_a_usage_error(tmp_path: Path, small_log: Path) -> None:
    code, err = invoke("run", str(small_log), "--estimator", ESTIMATOR, "--seed", "-1", "-o", str(tmp_path / "o"))
    assert code == 2 and "Invalid value for '--seed': -1 is not in the range x>=0" in err
    assert not (tmp_path / "o").exists()


def test_missing_points_topic_is_an_input_error(tmp_path: Path, small_log: Path) -> None:
    code, err = invoke(
        "run", str(small_log), "--estimator", ESTIMATOR, "--points-topic", "/lidar", "-o", str(tmp_path / "o")
    )
    assert code == 3 and "no messages on /lidar" in err and "--points-topic" in err
    code, err = invoke("run", str(small_log), "--estimator", ESTIMATOR, "--points-topic", "/ground_truth/pose",
                       "-o", str(tmp_path / "o"))  # fmt: skip
    assert code == 3 and "not sensor_msgs/msg/PointCloud2" in err
    assert not (tmp_path / "o").exists()


def test_nan_and_empty_clouds_are_skipped_counted_and_the_run_goes_on(tmp_path: Path, small_log: Path) -> None:
    holes = tmp_path / "holes.mcap"
    with LogWriter(holes) as writer:
        for k, record in enumerate(LogReader(small_log).records(["points"])):
            points = np.array(record.value.points)
            if k == 30:
                points = np.zeros((0, 3))
            elif k % 10 == 5:
                points[:3] = np.nan
            writer.write_observation(PointObservation(record.stamp_ns, points, None))
    out = tmp_path / "out"
    code, err = invoke("run", str(holes), "--estimator", ESTIMATOR, "-o", str(out))
    assert code == 0, err
    assert "skipping" in err
    skipped = json.loads((out / "run.json").read_text())["skipped"]
    assert skipped == {"/points: empty clouds": 1, "/points: non-finite points": 36}


def test_config_command_lists_parameters() -> None:
    result = CliRunner().invoke(cli, ["config", "--estimator", ESTIMATOR])
    assert result.exit_code == 0 and result.stdout.startswith(f"[{ESTIMATOR}]")


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
def test_info_reports_each_estimator(name: str, small_log: Path) -> None:
    result = CliRunner().invoke(cli, ["info", str(small_log), "--json"])
    capability = json.loads(result.stdout)["estimators"][name]
    # The small log carries points, odometry and fixes but no depth images.
    assert capability["can_run"] is ("points" in ESTIMATORS[name].needs)
    if not capability["can_run"]:
        assert "depth" in capability["missing"]


def test_stamps_going_backwards_stop_the_run_without_output(tmp_path: Path, small_log: Path) -> None:
    from formats import ros2

    backwards = tmp_path / "backwards.mcap"
    records = list(LogReader(small_log).records(["points"]))
    with LogWriter(backwards) as writer:
        for k, record in enumerate(records[:40]):
            stamp = record.stamp_ns if k != 30 else records[10].stamp_ns  # header stamp jumps back at 30
            message = ros2.observation_to_msg(PointObservation(stamp, record.value.points))
            writer.write("/points", ros2.POINT_CLOUD2, message, record.stamp_ns)
    out = tmp_path / "out"
    code, err = invoke("run", str(backwards), "--estimator", ESTIMATOR, "-o", str(out))
    assert code == 3
    assert len(err.strip().splitlines()) == 1 and "is not after the previous" in err
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["backwards.mcap"]


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
def test_config_output_is_valid_toml_that_rebuilds_the_defaults(name: str, tmp_path: Path) -> None:
    import tomllib

    from relpoint_app.runner import build_config

    result = CliRunner().invoke(cli, ["config", "--estimator", name])
    assert result.exit_code == 0
    path = tmp_path / "params.toml"
    path.write_text(result.stdout)
    assert name in tomllib.loads(result.stdout)
    spec = ESTIMATORS[name]
    assert build_config(spec, path, ()) == spec.config_class()


def test_landmark_error_over_time(tmp_path: Path, small_log: Path) -> None:
    """`run --map-every` records the map; `evaluate --csv` turns it into landmark error over time (Fig. 8)."""
    out = tmp_path / "out"
    # The noise is given: estimating it holds back the first 30 iterations, which then have no map to record.
    code, err = invoke("-q", "run", str(small_log), "--estimator", "relpoint", "--map-every", "20",
                       "--param", "observation_sigma=0.3", "-o", str(out))  # fmt: skip
    assert code == 0, err
    with (out / "map_history.csv").open() as stream:
        iterations = sorted({int(row["iteration"]) for row in csv.DictReader(stream)})
    assert iterations == [19, 39, 59, 79, 99, 119]
    code, err = invoke("evaluate", str(out), "--reference", str(small_log), "--csv", str(tmp_path / "e.csv"))
    assert code == 0, err
    with (tmp_path / "e.csv").open() as stream:
        rows = [row for row in csv.DictReader(stream) if row["landmark_rmse_m"]]
    assert len(rows) == 6
    errors = [float(row["landmark_rmse_m"]) for row in rows]
    assert all(0.0 < e < 3.0 for e in errors)  # noise 0.3 m: mapped landmarks stay within metres


def test_association_purity_reaches_the_evaluation(tmp_path: Path, small_log: Path) -> None:
    out = tmp_path / "out"
    assert invoke("-q", "run", str(small_log), "--estimator", "relpoint", "-o", str(out))[0] == 0
    purity = read_ply(out / "map.ply")["purity"]
    assert len(purity) > 20 and np.all((purity > 0) & (purity <= 1))
    code, err = invoke("evaluate", str(out), "--reference", str(small_log), "--json", str(tmp_path / "e.json"))
    assert code == 0, err
    summary = json.loads((tmp_path / "e.json").read_text())["summary"]
    assert summary["lm_purity_mean"] == pytest.approx(float(np.mean(purity)), abs=1e-6)


BLAS_THREADS_IN_A_RUN = """
import sys
from threadpoolctl import threadpool_info
import relpoint
from relpoint.estimators.relative_point import adjustment
seen = []
solve = adjustment._solve_positive_definite
def spy(*args):
    seen.extend(pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas")
    return solve(*args)
adjustment._solve_positive_definite = spy
relpoint.run(sys.argv[1], estimator="relpoint")
print(len(seen), max(seen))
"""


def test_every_blas_pool_is_single_threaded_while_an_estimator_runs(small_log: Path) -> None:
    # scipy's own OpenBLAS, loaded with scipy.linalg inside the run, kept its threads: on two busy cores
    # the figure eight's final adjustment took 7.6 s (13 s under load) in place of 1.4 s.
    import os
    import subprocess
    import sys

    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2"}  # a pool of two whatever the machine's cores
    completed = subprocess.run([sys.executable, "-c", BLAS_THREADS_IN_A_RUN, str(small_log)], env=env,
                               capture_output=True, text=True, check=False, timeout=300)  # fmt: skip
    assert completed.returncode == 0, completed.stderr
    solves, threads = map(int, completed.stdout.split())
    assert solves > 0 and threads == 1
