"""``relpoint compare`` and ``evaluate --save-results``: evo's result zips both ways, tables, figures, errors."""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from formats.evo_results import read_evo_result
from formats.log import LogReader
from formats.tables import read_map_csv, write_map_csv, write_map_history_csv
from formats.trajectory_files import read_tum, write_tum
from relpoint.evaluation.comparison import ComparedRun
from relpoint.types import LandmarkMap, Trajectory
from relpoint_app.compare_table import render_table
from relpoint_app.plots import plot_title
from relpoint_cli.main import cli
from tests.conftest import shared_data

evo_file_interface = pytest.importorskip("evo.tools.file_interface")
from evo.core import metrics as evo_metrics  # noqa: E402
from evo.core import sync as evo_sync  # noqa: E402
from evo.main_ape import ape as evo_ape  # noqa: E402
from evo.main_rpe import rpe as evo_rpe  # noqa: E402

logging.getLogger("evo").setLevel(logging.ERROR)

FR1 = "evo-fr1xyz"
GT, RGBD = "freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt"


def invoke(*args: str | Path) -> tuple[int, str, str]:
    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result.exit_code, result.stdout, result.stderr


def assert_one_error_line(err: str, fragment: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("relpoint: error: ") and fragment in lines[0], err


def evo_synced(ref: Path, est: Path) -> tuple[object, object]:
    return evo_sync.associate_trajectories(
        evo_file_interface.read_tum_trajectory_file(str(ref)),
        evo_file_interface.read_tum_trajectory_file(str(est)),
        max_diff=0.01,
    )


# --- evaluate --save-results: read by evo's own load_res_file ---------------------------------------------


def test_saved_results_load_in_evo_and_equal_evo_ape(tmp_path: Path) -> None:
    ref, est = shared_data(FR1, GT), shared_data(FR1, RGBD)
    zip_path = tmp_path / "ape.zip"
    code, _, err = invoke("evaluate", est, "-r", ref, "--align", "se3", "--save-results", zip_path)
    assert code == 0, err
    ours = evo_file_interface.load_res_file(str(zip_path), load_trajectories=True)
    traj_ref, traj_est = evo_synced(ref, est)
    theirs = evo_ape(traj_ref, traj_est, evo_metrics.PoseRelation.translation_part, align=True)
    assert ours.info["title"] == theirs.info["title"]  # "APE w.r.t. translation part (m)\n(with SE(3) ...)"
    assert ours.info["label"] == theirs.info["label"]
    assert ours.stats["rmse"] == pytest.approx(0.013470, abs=1e-6)  # REFERENCE.md
    for name, value in theirs.stats.items():
        assert ours.stats[name] == pytest.approx(value, rel=1e-9), name
    assert set(ours.np_arrays) == set(theirs.np_arrays)
    for name, array in theirs.np_arrays.items():
        np.testing.assert_allclose(ours.np_arrays[name], array, rtol=1e-9, atol=1e-9, err_msg=name)
    assert len(ours.trajectories) == 2
    for traj in ours.trajectories.values():  # the matched reference and the aligned estimate, as evo keeps them
        assert traj.num_poses == traj_est.num_poses
    aligned = ours.trajectories[RGBD]
    np.testing.assert_allclose(aligned.positions_xyz, traj_est.positions_xyz, atol=1e-9)
    # relpoint reads its own zip back with every figure of the summary, RPE included.
    assert read_evo_result(zip_path).info["relpoint"]["summary"]["ate_rmse"] == pytest.approx(ours.stats["rmse"])
    code, out, err = invoke("compare", zip_path, "--format", "json")
    assert code == 0, err
    (row,) = json.loads(out)["runs"]
    assert row["align"] == "se3" and row["summary"]["ate_rmse"] == pytest.approx(0.013470, abs=1e-6)
    assert row["summary"]["rpe_trans_rmse"] > 0 and row["summary"]["matched_poses"] == traj_est.num_poses


def test_saved_results_in_another_relation_and_replaced_without_overwrite(tmp_path: Path) -> None:
    ref, est = shared_data(FR1, GT), shared_data(FR1, RGBD)
    zip_path = tmp_path / "ape_deg.zip"
    for _ in range(2):  # the second write replaces relpoint's own zip without --overwrite
        code, _, err = invoke("evaluate", est, "-r", ref, "--pose-relation", "angle_deg", "--save-results", zip_path)
        assert code == 0, err
    ours = evo_file_interface.load_res_file(str(zip_path))
    theirs = evo_ape(*evo_synced(ref, est), evo_metrics.PoseRelation.rotation_angle_deg)
    assert ours.info["title"] == theirs.info["title"]
    assert ours.stats["rmse"] == pytest.approx(theirs.stats["rmse"], rel=1e-9)
    foreign = tmp_path / "foreign.zip"
    foreign.write_bytes(b"PK\x05\x06" + bytes(18))  # an empty zip relpoint did not write
    code, _, err = invoke("evaluate", est, "-r", ref, "--save-results", foreign)
    assert code == 2
    assert_one_error_line(err, "relpoint did not write it")
    code, _, err = invoke("evaluate", est, "-r", ref, "--save-results", tmp_path / "ape.json")
    assert code == 2
    assert_one_error_line(err, "name it FILE.zip")


@pytest.mark.parametrize(
    ("args", "evo_kwargs"),
    [
        ([], {"pose_relation": evo_metrics.PoseRelation.translation_part, "delta": 1,
              "delta_unit": evo_metrics.Unit.frames}),
        (["--pose-relation", "angle_deg", "--delta", "0.2", "--delta-unit", "m", "--all-pairs", "--align", "se3"],
         {"pose_relation": evo_metrics.PoseRelation.rotation_angle_deg, "delta": 0.2,
          "delta_unit": evo_metrics.Unit.meters, "all_pairs": True, "align": True}),
    ],
)  # fmt: skip
def test_saved_rpe_results_equal_evo_rpe(tmp_path: Path, args: list[str], evo_kwargs: dict[str, object]) -> None:
    ref, est = shared_data(FR1, GT), shared_data(FR1, RGBD)
    zip_path = tmp_path / "rpe.zip"
    code, _, err = invoke("evaluate", est, "-r", ref, *args, "--save-rpe-results", zip_path)
    assert code == 0, err
    ours = evo_file_interface.load_res_file(str(zip_path), load_trajectories=True)
    theirs = evo_rpe(*evo_synced(ref, est), **evo_kwargs)
    assert ours.info["title"] == theirs.info["title"]
    for name, value in theirs.stats.items():
        assert ours.stats[name] == pytest.approx(value, rel=1e-9), name
    assert set(ours.np_arrays) == set(theirs.np_arrays)
    for name, array in theirs.np_arrays.items():
        np.testing.assert_allclose(ours.np_arrays[name], array, rtol=1e-9, atol=1e-9, err_msg=name)
    for mine, traj in zip(ours.trajectories.values(), theirs.trajectories.values(), strict=True):  # ref, est
        np.testing.assert_allclose(mine.positions_xyz, traj.positions_xyz, atol=1e-9)
        np.testing.assert_array_equal(mine.timestamps, traj.timestamps)


# --- compare reads zips evo wrote itself ------------------------------------------------------------------


def test_compare_reads_evo_zips(tmp_path: Path) -> None:
    ref, est = shared_data(FR1, GT), shared_data(FR1, RGBD)
    ape = evo_ape(*evo_synced(ref, est), evo_metrics.PoseRelation.translation_part, align=True)
    rpe = evo_rpe(*evo_synced(ref, est), evo_metrics.PoseRelation.rotation_angle_deg, delta=1,
                  delta_unit=evo_metrics.Unit.frames)  # fmt: skip
    evo_file_interface.save_res_file(str(tmp_path / "ape.zip"), ape)
    evo_file_interface.save_res_file(str(tmp_path / "rpe.zip"), rpe)
    table = tmp_path / "table.json"
    code, out, err = invoke("compare", tmp_path / "ape.zip", tmp_path / "rpe.zip", "-o", table,
                            "--plot", tmp_path / "compare.png", "--label", "rgbdslam APE", "--label", "rgbdslam RPE")  # fmt: skip
    assert code == 0, err
    runs = {run["run"]: run for run in json.loads(table.read_text())["runs"]}
    assert runs["rgbdslam APE"]["align"] == "se3"
    assert runs["rgbdslam APE"]["summary"]["ate_rmse"] == pytest.approx(ape.stats["rmse"], rel=1e-12)
    assert runs["rgbdslam APE"]["summary"]["matched_poses"] == len(ape.np_arrays["error_array"])
    assert runs["rgbdslam RPE"]["summary"]["rpe_rot_deg_rmse"] == pytest.approx(rpe.stats["rmse"], rel=1e-12)
    assert runs["rgbdslam RPE"]["summary"]["ate_rmse"] is None  # an RPE zip has no APE figures
    assert "rgbdslam APE" in out.splitlines()[1] and "ate_rmse" in out
    assert (tmp_path / "compare.png").read_bytes()[:4] == b"\x89PNG"


def test_compare_refuses_a_zip_that_is_no_result(tmp_path: Path) -> None:
    import zipfile

    with zipfile.ZipFile(tmp_path / "other.zip", "w") as archive:
        archive.writestr("readme.txt", "hello")
    code, _, err = invoke("compare", tmp_path / "other.zip")
    assert code == 3
    assert_one_error_line(err, "not an evo result file")
    (tmp_path / "broken.zip").write_bytes(b"PK not really")
    code, _, err = invoke("compare", tmp_path / "broken.zip")
    assert code == 3
    assert_one_error_line(err, "cannot read as a zip file")


# --- run directories ---------------------------------------------------------------------------------------


def fake_run(out: Path, log: Path, shift: float, estimator: str | None = None) -> Path:
    """A run output: the true trajectory shifted by ``shift`` m in x, the true landmarks with 5 cm noise;
    with ``estimator``, a run.json naming it and the log (as `relpoint run` writes)."""
    reader = LogReader(log)
    poses = [r.value for r in reader.records(["ground_truth_pose"])]
    truth = [r.value for r in reader.records(["ground_truth_landmarks"])][-1]
    out.mkdir()
    positions = np.array([p.position for p in poses]) + np.array([shift, 0.0, 0.0])
    write_tum(
        out / "trajectory.tum",
        Trajectory(np.array([p.stamp_ns for p in poses]), positions, np.array([p.quat_xyzw for p in poses])),
    )
    n = len(truth.ids)
    noise = np.random.default_rng(7).normal(0, 0.05, (n, 3))
    dynamic = np.arange(n) % 10 == 0  # some flagged dynamic, to be marked in the plots
    write_map_csv(out / "map.csv", LandmarkMap(truth.positions + noise, np.full(n, 3), dynamic, truth.ids))
    if estimator is not None:
        document = {"estimator": estimator, "relpoint_version": "test", "input": {"path": str(log)}}
        (out / "run.json").write_text(json.dumps(document))
    return out


def test_run_directories_against_their_logs(tmp_path: Path, small_log: Path) -> None:
    near = fake_run(tmp_path / "near", small_log, 0.1, estimator="ekf")
    far = fake_run(tmp_path / "far", small_log, 0.3, estimator="fastslam")
    code, out, err = invoke("compare", near, far, "--format", "csv")
    assert code == 0, err
    rows = {row["run"]: row for row in csv.DictReader(io.StringIO(out))}
    assert rows[str(near)]["estimator"] == "ekf" and rows[str(far)]["estimator"] == "fastslam"
    assert float(rows[str(near)]["ate_rmse"]) == pytest.approx(0.1, abs=1e-6)
    assert float(rows[str(far)]["ate_rmse"]) == pytest.approx(0.3, abs=1e-6)
    assert 0.03 < float(rows[str(near)]["lm_err_rmse"]) < 0.15  # 5 cm per axis: ~0.087 m
    assert rows[str(near)]["align"] == "none" and float(rows[str(near)]["matched_poses"]) == 120
    # --align se3 removes the constant shift; --keys chooses the columns.
    code, out, err = invoke("compare", near, far, "--align", "se3", "--format", "json", "--keys", "ate_rmse,lm_count")
    assert code == 0, err
    document = json.loads(out)
    assert document["columns"] == ["ate_rmse", "lm_count"]
    code, out, err = invoke("compare", near, near, "--format", "json")  # one run twice: told apart
    assert code == 0, err
    assert [run["run"] for run in json.loads(out)["runs"]] == [str(near), f"{near}#2"]
    assert all(run["summary"]["ate_rmse"] < 1e-6 and run["align"] == "se3" for run in document["runs"])


def test_a_real_run_is_evaluated_against_the_log_its_run_json_names(tmp_path: Path, small_log: Path) -> None:
    run = tmp_path / "ekf"
    code, _, err = invoke("run", small_log, "--estimator", "ekf", "-o", run)
    assert code == 0, err
    code, _, err = invoke("evaluate", run, "-r", small_log, "--json", tmp_path / "evaluate.json")
    assert code == 0, err
    expected = json.loads((tmp_path / "evaluate.json").read_text())["summary"]
    code, out, err = invoke("compare", run, "--format", "json")
    assert code == 0, err
    (row,) = json.loads(out)["runs"]
    assert row["estimator"] == "ekf" and str(small_log) in row["source"]
    for key in ("ate_rmse", "rpe_trans_rmse", "lm_err_rmse", "lm_count"):
        assert row["summary"][key] == expected[key], key


def test_a_run_finds_its_log_from_any_directory_and_never_another_log_of_that_name(
    tmp_path: Path, small_log: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    here, elsewhere = tmp_path / "here", tmp_path / "elsewhere"
    here.mkdir()
    elsewhere.mkdir()
    shutil.copy(small_log, here / "l.mcap")
    code, _, err = invoke("simulate", "-o", elsewhere / "l.mcap", "--iterations", "40", "--scenario", "spiral")
    assert code == 0, err
    monkeypatch.chdir(here)
    code, _, err = invoke("-q", "run", "l.mcap", "--estimator", "ekf", "-o", tmp_path / "run")  # a relative LOG
    assert code == 0, err
    code, expected, err = invoke("compare", tmp_path / "run", "--keys", "ate_rmse")
    assert code == 0, err
    monkeypatch.chdir(elsewhere)  # another l.mcap here: the run's log is still found where it was
    code, out, err = invoke("compare", tmp_path / "run", "--keys", "ate_rmse")
    assert code == 0, err
    assert out == expected
    # A run.json of an older relpoint, which kept the path as given: the l.mcap here is another log.
    document = json.loads((tmp_path / "run" / "run.json").read_text())
    document["input"] = {key: document["input"][key] for key in ("path", "sha256")} | {"path": "l.mcap"}
    (tmp_path / "run" / "run.json").write_text(json.dumps(document))
    code, out, err = invoke("compare", tmp_path / "run", "--keys", "ate_rmse")
    assert code == 3
    assert_one_error_line(err, f"l.mcap is not the log {tmp_path / 'run'} was run on (sha256 ")
    assert "pass --reference LOG" in err
    monkeypatch.chdir(here)  # there, the relative path names the log it ran on (its hash says so)
    code, out, err = invoke("compare", tmp_path / "run", "--keys", "ate_rmse")
    assert code == 0, err
    assert out == expected


def test_a_log_is_known_by_its_size_and_time_or_else_by_its_hash(tmp_path: Path, small_log: Path) -> None:
    from relpoint.errors import InputError
    from relpoint_app.run_inputs import check_same_log, log_record

    recorded = log_record(small_log)
    assert recorded["path"] == str(small_log.resolve()) and recorded["size"] == small_log.stat().st_size
    copy = tmp_path / "copy.mcap"
    shutil.copy(small_log, copy)  # a new modification time: hashed, and found the same
    os.utime(copy, ns=(0, recorded["mtime_ns"] + 1))
    check_same_log(copy, recorded, tmp_path, "hint")
    data = bytearray(copy.read_bytes())
    data[len(data) // 2] ^= 0xFF  # the same size, another log
    copy.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"copy.mcap is not the log .* \(sha256 .*; hint"):
        check_same_log(copy, recorded, tmp_path, "hint")
    with pytest.raises(InputError, match=r"\(\d+ bytes, run.json records \d+ for"):
        check_same_log(copy, recorded | {"size": 1}, tmp_path, "hint")


def test_tables_figures_and_their_replacement(tmp_path: Path, small_log: Path) -> None:
    runs = [fake_run(tmp_path / name, small_log, shift) for name, shift in (("a", 0.1), ("b", 0.2))]
    for suffix, first in ((".md", "<!-- relpoint compare -->"), (".txt", "# relpoint compare: 2 runs")):
        table = tmp_path / f"table{suffix}"
        for _ in range(2):  # written, then replaced: relpoint recognises its own table
            code, out, err = invoke("compare", *runs, "-r", small_log, "-o", table, "--label", "A", "--label", "B")
            assert code == 0, err
        lines = table.read_text().splitlines()
        assert lines[0] == first
        ate = next(line for line in lines if "ate_rmse" in line)
        assert "0.100000" in ate and "0.200000" in ate
    assert out.splitlines()[0] == "# relpoint compare: 2 runs"  # stdout is text unless --format says otherwise
    for plot, kind in (("compare.svg", "violin"), ("compare.pdf", "box")):
        for _ in range(2):
            code, _, err = invoke("compare", *runs, "-r", small_log, "--plot", tmp_path / plot, "--plot-kind", kind)
            assert code == 0, err
    assert (tmp_path / "compare.pdf").read_bytes()[:5] == b"%PDF-"
    assert b"<svg" in (tmp_path / "compare.svg").read_bytes()[:2000]


def test_an_interrupt_while_the_figure_is_drawn_leaves_no_table(
    tmp_path: Path, small_log: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt  # Ctrl-C after the table was written

    monkeypatch.setattr("relpoint_cli.compare.comparison_plot", interrupted)
    runs = [fake_run(tmp_path / name, small_log, shift) for name, shift in (("a", 0.1), ("b", 0.2))]
    out = tmp_path / "out"
    out.mkdir()
    code, _, err = invoke("compare", *runs, "-r", small_log, "-o", out / "table.md", "--plot", out / "compare.png")
    assert code == 130
    assert_one_error_line(err, "interrupted; no output was written")
    assert list(out.iterdir()) == []


def test_saved_evaluations_keep_their_settings(tmp_path: Path, small_log: Path) -> None:
    run = fake_run(tmp_path / "run", small_log, 0.25, estimator="relpoint")
    code, _, err = invoke("evaluate", run, "-r", small_log, "--align", "se3", "--json", run / "evaluation.json")
    assert code == 0, err
    summary_json = tmp_path / "eval.json"
    code, _, err = invoke("evaluate", run, "-r", small_log, "--json", summary_json)
    assert code == 0, err
    code, out, err = invoke("compare", run, summary_json, "--format", "json", "--label", "batch", "--label", "json")
    assert code == 0, err
    runs = {r["run"]: r for r in json.loads(out)["runs"]}
    assert runs["batch"]["align"] == "se3" and runs["batch"]["summary"]["ate_rmse"] < 1e-6
    assert runs["json"]["align"] == "none" and runs["json"]["summary"]["ate_rmse"] == pytest.approx(0.25, abs=1e-6)
    assert runs["json"]["estimator"] == "relpoint" and "re-evaluated" in runs["json"]["source"]
    # Its reference gone, a summary still fills the table (with a warning), but cannot be plotted.
    moved = tmp_path / "moved.mcap"
    shutil.copy(small_log, moved)
    code, _, err = invoke("evaluate", run, "-r", moved, "--json", summary_json)
    assert code == 0, err
    moved.unlink()
    code, out, err = invoke("compare", summary_json, "--format", "json")
    assert code == 0, err
    assert "only its summary is compared" in err and "moved.mcap" in err
    assert json.loads(out)["runs"][0]["summary"]["ate_rmse"] == pytest.approx(0.25, abs=1e-6)
    # A reference that no longer reads as one: a warning, and the saved figures.
    document = json.loads(summary_json.read_text())
    junk = tmp_path / "junk.txt"
    junk.write_text("not a trajectory\n")
    document["inputs"]["reference"] = str(junk)
    changed = tmp_path / "changed.json"
    changed.write_text(json.dumps(document))
    code, out, err = invoke("compare", changed, "--format", "json")
    assert code == 0, err
    assert "cannot re-evaluate it" in err and json.loads(out)["runs"][0]["source"].endswith("(summary)")
    code, _, err = invoke("compare", summary_json, "--plot", tmp_path / "p.png")
    assert code == 3
    assert_one_error_line(err.strip().splitlines()[-1], "no RESULT holds per-pose errors")  # after the warning
    assert not (tmp_path / "p.png").exists()


def test_a_saved_evaluation_is_evaluated_again_over_the_poses_it_chose(tmp_path: Path, small_log: Path) -> None:
    # --t-start/--t-end and KITTI times files chose the saved evaluation's poses; compare ran it again
    # without them (all poses, or KITTI poses paired by index) and showed those figures, no warning.
    run = fake_run(tmp_path / "run", small_log, 0.25, estimator="relpoint")
    code, out, err = invoke(
        "evaluate", run, "-r", small_log, "--t-start", "2", "--t-end", "5", "--json", tmp_path / "e.json"
    )
    assert code == 0, err
    saved = json.loads((tmp_path / "e.json").read_text())
    assert saved["inputs"]["t_start"] == 2 and Path(saved["inputs"]["estimate"]).is_absolute()
    code, out, err = invoke("compare", tmp_path / "e.json", "--format", "json")
    assert code == 0, err
    (compared,) = json.loads(out)["runs"]
    assert "re-evaluated" in compared["source"]
    assert compared["summary"]["matched_poses"] == saved["summary"]["matched_poses"] < 40


def test_the_reference_poses_are_chosen_as_evaluate_chooses_them(tmp_path: Path, small_log: Path) -> None:
    # compare's errors told to name a topic or a TF chain, with options only evaluate had.
    run = fake_run(tmp_path / "run", small_log, 0.25, estimator="relpoint")
    code, out, err = invoke(
        "compare", run, "-r", small_log, "--reference-topic", "/ground_truth/pose", "--format", "json"
    )
    assert code == 0, err
    assert json.loads(out)["runs"][0]["summary"]["ate_rmse"] == pytest.approx(0.25, abs=1e-6)
    code, out, err = invoke("compare", run, "-r", small_log, "--reference-topic", "/no/such", "--format", "json")
    assert code == 3 and "/no/such" in err
    code, _, err = invoke("compare", run, "--parent", "map", "--child", "base_link")
    assert code == 2 and "--parent, --child choose poses of --reference" in err


def test_errors_are_one_line(tmp_path: Path, small_log: Path) -> None:
    run = fake_run(tmp_path / "run", small_log, 0.1)
    code, _, err = invoke("compare", run)  # no run.json, no evaluation.json, no --reference
    assert code == 3
    assert_one_error_line(err, "pass --reference LOG")
    code, _, err = invoke("compare", tmp_path)
    assert code == 3
    assert_one_error_line(err, "not a relpoint run directory")
    code, _, err = invoke("compare", run, "-r", small_log, "--keys", "ate_rmse,no_such_key")
    assert code == 2
    assert_one_error_line(err, "no run has no_such_key")
    code, _, err = invoke("compare", run, run, "--label", "one")
    assert code == 2
    assert_one_error_line(err, "1 --label for 2 results")
    code, _, err = invoke("compare", run, "-r", small_log, "--plot", tmp_path / "c.png", "--plot-format", "svg")
    assert code == 2
    assert_one_error_line(err, "named .png but --plot-format is svg")
    (tmp_path / "notes.md").write_text("mine\n")
    code, _, err = invoke("compare", run, "-r", small_log, "-o", tmp_path / "notes.md")
    assert code == 2
    assert_one_error_line(err, "relpoint did not write it")
    assert (tmp_path / "notes.md").read_text() == "mine\n"
    (tmp_path / "x.json").write_text("[1, 2]")
    code, _, err = invoke("compare", tmp_path / "x.json")
    assert code == 3
    assert_one_error_line(err, "not a relpoint evaluation summary")


# --- evaluate's figures ------------------------------------------------------------------------------------


def test_evaluate_plot_formats(tmp_path: Path, small_log: Path) -> None:
    run = fake_run(tmp_path / "run", small_log, 0.1, estimator="ekf")
    for plot_format, magic in (("svg", b"<?xml"), ("pdf", b"%PDF-")):
        plots = tmp_path / plot_format
        for _ in range(2):  # replaced without --overwrite: relpoint recognises its own figures
            code, _, err = invoke("evaluate", run, "-r", small_log, "--align", "se3", "--plot", plots,
                                  "--plot-format", plot_format)  # fmt: skip
            assert code == 0, err
        names = sorted(p.name for p in plots.iterdir())
        assert names == [f"{stem}.{plot_format}" for stem in ("errors", "trajectory_side", "trajectory_top")]
        assert all((plots / name).read_bytes()[:5] == magic for name in names)


def test_landmark_error_over_time_is_aligned_with_the_trajectory(tmp_path: Path, small_log: Path) -> None:
    """With --align, the map_history column is the aligned landmark error (it was NaN before)."""
    run = fake_run(tmp_path / "run", small_log, 0.3)
    last_stamp = int(read_tum(run / "trajectory.tum").stamps_ns[-1])
    write_map_history_csv(run / "map_history.csv", ((119, last_stamp, read_map_csv(run / "map.csv")),))
    code, _, err = invoke("evaluate", run, "-r", small_log, "--align", "se3", "--csv", tmp_path / "e.csv",
                          "--json", tmp_path / "e.json")  # fmt: skip
    assert code == 0, err
    with (tmp_path / "e.csv").open() as stream:
        (row,) = [row for row in csv.DictReader(stream) if row["landmark_rmse_m"]]
    summary = json.loads((tmp_path / "e.json").read_text())["summary"]
    assert float(row["landmark_rmse_m"]) == pytest.approx(summary["lm_err_aligned_rmse"], rel=1e-9)
    # The map is unshifted while the path is 0.3 m off: aligning the path moves the map 0.3 m away.
    assert summary["lm_err_rmse"] < 0.15 < float(row["landmark_rmse_m"])


def test_plot_title_names_run_estimator_and_alignment() -> None:
    assert plot_title("out/fig8", "ekf", "se3") == "out/fig8 - ekf - SE(3) Umeyama alignment"
    assert plot_title("est.txt", "", "none") == "est.txt - not aligned"


def _zip_of_zeros(path: Path, n: int) -> Path:
    """An evo-style result zip whose error array is ``n`` zeros: a few KB that inflate to ``8 n`` bytes."""
    import zipfile

    buffer = io.BytesIO()
    np.save(buffer, np.zeros(n))
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("info.json", json.dumps({"title": "APE w.r.t. translation part (m)", "ref_name": "a",
                                                  "est_name": "b", "label": "APE (m)"}))  # fmt: skip
        archive.writestr("stats.json", json.dumps(dict.fromkeys(("rmse", "mean", "median", "std", "min", "max"), 0)))
        archive.writestr("error_array.npy", buffer.getvalue())
        archive.writestr("seconds_from_start.npy", buffer.getvalue())
    return path


def test_a_result_zip_that_inflates_beyond_the_limit_is_refused_before_it_is_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    small = _zip_of_zeros(tmp_path / "small.zip", 1000)
    assert len(read_evo_result(small).arrays["error_array"]) == 1000
    monkeypatch.setattr("formats.evo_results.MAX_RESULT_BYTES", 1 << 20)
    bomb = _zip_of_zeros(tmp_path / "bomb.zip", 100_000)  # 2 x 800 kB inflated, 2 kB on disk
    assert bomb.stat().st_size < 10_000

    def no_load(*args: object, **kwargs: object) -> None:
        raise AssertionError("an array was inflated")

    monkeypatch.setattr("formats.evo_results.np.load", no_load)
    code, out, err = invoke("compare", bomb)
    assert code == 3 and out == ""
    assert "inflate to 2 MiB, more than the 1 MiB" in err and len(err.strip().splitlines()) == 1


def test_undefined_figures_are_empty_in_csv_and_n_a_in_the_tables() -> None:
    # as evaluate --csv and a batch's results.csv write them; a missing figure is empty (CSV) or "-"
    runs = [
        ComparedRun("a", "ekf", "none", {"ate_rmse": 0.5, "dyn_precision": math.nan, "lm_err_rmse": math.inf}),
        ComparedRun("b", "fastslam", "none", {"ate_rmse": 0.25}),
    ]
    keys = ["ate_rmse", "dyn_precision", "lm_err_rmse"]
    rows = list(csv.reader(io.StringIO(render_table(runs, keys, "csv"))))
    assert rows[1:] == [["a", "ekf", "none", "0.5", "", ""], ["b", "fastslam", "none", "0.25", "", ""]]
    for table_format in ("text", "markdown"):
        line = next(line for line in render_table(runs, keys, table_format).splitlines() if "dyn_precision" in line)
        assert "n/a" in line and line.rstrip(" |").endswith("-") and "nan" not in line
    summaries = [run["summary"] for run in json.loads(render_table(runs, keys, "json"))["runs"]]
    assert summaries[0]["dyn_precision"] is None and summaries[1]["dyn_precision"] is None


def test_counts_are_integers_in_every_summary_written(tmp_path: Path, small_log: Path) -> None:
    run = fake_run(tmp_path / "run", small_log, 0.1, estimator="ekf")
    code, _, err = invoke("evaluate", run, "-r", small_log, "--json", tmp_path / "e.json", "--save-results",
                          tmp_path / "e.zip")  # fmt: skip
    assert code == 0, err
    saved = json.loads((tmp_path / "e.json").read_text())["summary"]
    with zipfile.ZipFile(tmp_path / "e.zip") as archive:
        zipped = json.loads(archive.read("info.json"))["relpoint"]["summary"]
    code, out, err = invoke("compare", run, tmp_path / "e.json", tmp_path / "e.zip", "--format", "json")
    assert code == 0, err
    compared = [r["summary"] for r in json.loads(out)["runs"]]
    for summary in (saved, zipped, *compared):
        assert summary["matched_poses"] == 120 and type(summary["matched_poses"]) is int
        assert type(summary["lm_count"]) is int and type(summary["ate_rmse"]) is float
    assert all(type(saved[key]) is int for key in ("reference_poses", "estimate_poses", "rpe_pairs", "lm_matched"))
    code, out, err = invoke("compare", run, tmp_path / "e.zip", "--format", "csv")
    assert code == 0, err
    rows = list(csv.DictReader(io.StringIO(out)))
    assert [row["matched_poses"] for row in rows] == ["120", "120"] and rows[0]["lm_count"] == str(saved["lm_count"])
