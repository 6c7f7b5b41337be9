"""The Python API (``relpoint.run``, ``relpoint.evaluate``) gives what the command line gives."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import relpoint
from relpoint.errors import UsageError
from relpoint_cli.main import cli

SAMPLE = Path(__file__).resolve().parents[1] / "sample_logs" / "figure8.mcap"


def test_run_and_evaluate_match_the_command_line(tmp_path: Path) -> None:
    result = relpoint.run(SAMPLE, estimator="relpoint", final_adjustment=False, output=tmp_path / "api")
    assert len(result.trajectory) == 900 and len(result.landmarks) > 0
    evaluation = relpoint.evaluate(result, reference=SAMPLE, align="se3")
    assert 0 < evaluation.summary["ate_rmse"] < 5.0 and "lm_err_rmse" in evaluation.summary

    runner = CliRunner()
    ran = runner.invoke(cli, ["-q", "run", str(SAMPLE), "-e", "relpoint", "--param", "final_adjustment=false",
                              "-o", str(tmp_path / "cli")])  # fmt: skip
    assert ran.exit_code == 0, ran.output
    for name in ("trajectory.tum", "map.csv"):
        assert (tmp_path / "api" / name).read_bytes() == (tmp_path / "cli" / name).read_bytes()
    evaluated = runner.invoke(cli, ["-q", "evaluate", str(tmp_path / "cli"), "-r", str(SAMPLE), "--align", "se3",
                                    "--json", str(tmp_path / "eval.json")])  # fmt: skip
    assert evaluated.exit_code == 0, evaluated.output
    on_file = json.loads((tmp_path / "eval.json").read_text())
    summary = on_file.get("summary", on_file)
    assert summary["ate_rmse"] == pytest.approx(evaluation.summary["ate_rmse"], abs=1e-6)
    # The run directory evaluates as the result does.
    from_directory = relpoint.evaluate(tmp_path / "api", reference=SAMPLE, align="se3")
    assert from_directory.summary["ate_rmse"] == pytest.approx(evaluation.summary["ate_rmse"], abs=1e-6)


def test_run_without_output_writes_nothing_and_follows_the_seed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    first = relpoint.run(SAMPLE, estimator="fastslam", particles=5, seed=3, use_fixes=False)
    again = relpoint.run(SAMPLE, estimator="fastslam", particles=5, seed=3, use_fixes=False)
    assert np.array_equal(first.trajectory.positions, again.trajectory.positions)
    assert list(tmp_path.iterdir()) == []


def test_bad_names_are_usage_errors() -> None:
    with pytest.raises(UsageError, match="unknown estimator"):
        relpoint.run(SAMPLE, estimator="orb")
    with pytest.raises(UsageError):
        relpoint.run(SAMPLE, estimator="relpoint", no_such_setting=1)
    with pytest.raises(UsageError, match="unknown evaluation setting"):
        relpoint.evaluate(SAMPLE, reference=SAMPLE, bogus=True)
