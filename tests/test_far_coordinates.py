"""Fixes in coordinates far from the origin (UTM: 5e6 m north): the run stays accurate and its outputs
keep the coordinates to the millimetre (float32 would round them to 0.5 m)."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
from click.testing import CliRunner
from mcap_ros2.reader import read_ros2_messages

from formats.ply import read_ply, stored_coordinates
from formats.pointcloud2 import Field, decode_cloud
from formats.trajectory_files import read_tum
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import GroundTruthLandmarks, PositionFix, Trajectory
from relpoint_app.simulation import write_simulation
from relpoint_cli.main import cli

UTM = np.array([500_000.0, 5_000_000.0, 100.0])


def test_coordinates_are_float32_unless_that_rounds_them() -> None:
    assert stored_coordinates(np.array([[12.5, -3.25, 1.0], [4000.1, 2.0, 0.0]])).dtype == np.dtype("<f4")
    assert stored_coordinates(UTM[None] + np.array([[0.123, 0.456, 0.789]])).dtype == np.dtype("<f8")
    assert stored_coordinates(np.zeros((0, 3))).dtype == np.dtype("<f4")


def _utm_log(path: Path) -> None:
    """A figure eight whose fixes, ground truth and landmarks are all given UTM-sized coordinates."""
    sim = simulate(SimulationConfig(iterations=120, density=25, seed=3, fix_every=5, fix_noise=0.5))
    steps = sim.steps

    def shifted():  # type: ignore[no-untyped-def]
        for step in steps():
            if step.fix is not None:
                step = dataclasses.replace(
                    step, fix=PositionFix(step.fix.stamp_ns, step.fix.position + UTM, step.fix.covariance)
                )
            T = step.T_world_sensor.copy()
            T[:3, 3] += UTM
            yield dataclasses.replace(step, T_world_sensor=T)

    sim.steps = shifted  # type: ignore[method-assign]
    truth = sim.ground_truth
    sim.ground_truth = Trajectory(truth.stamps_ns, truth.positions + UTM, truth.quats_xyzw)
    sim.landmarks = GroundTruthLandmarks(sim.landmarks.positions + UTM, sim.landmarks.ids, sim.landmarks.dynamic)
    write_simulation(sim, path)


def test_a_run_in_utm_coordinates_keeps_them_in_every_output(tmp_path: Path) -> None:
    log, out = tmp_path / "utm.mcap", tmp_path / "run"
    _utm_log(log)
    result = CliRunner().invoke(cli, ["run", str(log), "-e", "ekf", "-o", str(out)])
    assert result.exit_code == 0, result.stderr
    estimate = read_tum(out / "trajectory.tum")
    assert np.linalg.norm(estimate.positions[-1] - UTM) < 200.0  # in the fixes' frame
    evaluation = CliRunner().invoke(cli, ["evaluate", str(out), "--reference", str(log), "--align", "none",
                                          "--fail-above", "ate_rmse=1.0"])  # fmt: skip
    assert evaluation.exit_code == 0, evaluation.output
    with (out / "map.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    mapped = np.array([[float(row[axis]) for axis in "xyz"] for row in rows])
    vertices = read_ply(out / "map.ply")
    ply = np.stack([vertices[axis] for axis in "xyz"], axis=1)
    assert vertices["x"].dtype == np.float64
    np.testing.assert_allclose(ply, mapped, atol=1e-6)
    maps = [
        item.ros_msg for item in read_ros2_messages(str(out / "result.mcap")) if item.channel.topic == "/relpoint/map"
    ]
    last = maps[-1]
    fields = [Field(f.name, f.offset, f.datatype, f.count) for f in last.fields]
    cloud = decode_cloud(bytes(last.data), fields, width=last.width, height=last.height,
                         point_step=last.point_step, row_step=last.row_step)  # fmt: skip
    np.testing.assert_allclose(np.stack([cloud[axis] for axis in "xyz"], axis=1), mapped, atol=1e-6)
