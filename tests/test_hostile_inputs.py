"""Hostile inputs (the reliability suite): logs and settings that are valid on their face but would
ruin a run, exhaust memory or crash it. Logs are written with mcap-ros2-support, not relpoint.

Each case ends in the documented exit code with one stderr line, or in a run that goes on with
what it skipped counted in run.json.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from formats import ros2
from formats.trajectory_files import read_tum
from relpoint import pipeline
from relpoint.errors import EstimatorError
from relpoint.estimators.base import Estimator
from relpoint.screening import InputScreen
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import LandmarkMap, OdometryMeasurement, PointObservation, Pose, PositionFix, Trajectory
from relpoint_cli.main import cli
from tests.hostile_logs import far_point, one_point, time_gap, write_log

REPO = Path(__file__).resolve().parents[1]
POINT_ESTIMATORS = ("relpoint", "ekf", "fastslam")
CONFIG = SimulationConfig(iterations=150, density=25, noise=0.3, odometry_noise=0.05, seed=5)


def invoke(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(cli, list(args))
    return result.exit_code, result.stderr


def position_rmse(run_dir: Path) -> float:
    estimate = read_tum(run_dir / "trajectory.tum").positions
    truth = simulate(CONFIG).ground_truth.positions
    return float(np.sqrt(np.mean(np.sum((estimate - truth) ** 2, axis=1))))


@pytest.fixture(scope="module")
def clean_and_far(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("far")
    return write_log(folder / "clean.mcap", CONFIG), write_log(folder / "far.mcap", CONFIG, far_point(1e30))


@pytest.mark.parametrize("name", POINT_ESTIMATORS)
def test_a_far_point_in_every_cloud_is_skipped_and_counted(
    name: str, clean_and_far: tuple[Path, Path], tmp_path: Path
) -> None:
    clean, far = clean_and_far
    code, err = invoke("run", str(clean), "--estimator", name, "-o", str(tmp_path / "clean"))
    assert code == 0, err
    code, err = invoke("run", str(far), "--estimator", name, "-o", str(tmp_path / "far"))
    assert code == 0, err
    assert err.count("implausible range") == 1  # warned once
    document = json.loads((tmp_path / "far" / "run.json").read_text())
    assert document["skipped"]["points: implausible range (far beyond the data's own)"] == CONFIG.iterations
    assert document["summary"]["landmarks"] > 20 and document["warnings"] == []
    assert position_rmse(tmp_path / "far") <= 1.1 * position_rmse(tmp_path / "clean") + 0.05


def test_one_point_clouds_end_with_a_warning(tmp_path: Path) -> None:
    log = write_log(tmp_path / "one.mcap", SimulationConfig(iterations=300, density=25, seed=5), one_point)
    code, err = invoke("run", str(log), "--estimator", "relpoint", "-o", str(tmp_path / "out"))
    assert code == 0, err
    assert "fewer than 3 points" in err and "mapped no landmark" in err
    warnings = json.loads((tmp_path / "out" / "run.json").read_text())["warnings"]
    assert any("no landmark" in w for w in warnings) and any("fewer than 3 points" in w for w in warnings)


@pytest.mark.parametrize("name", ("ekf", "fastslam"))
def test_a_ten_year_stamp_gap_is_bridged(name: str, tmp_path: Path) -> None:
    log = write_log(tmp_path / "gap.mcap", CONFIG, time_gap(75, 10 * 365.25 * 86400), odometry=True)
    code, err = invoke("run", str(log), "--estimator", name, "-o", str(tmp_path / "out"))
    assert code == 0, err
    document = json.loads((tmp_path / "out" / "run.json").read_text())
    assert document["summary"]["iterations"] == CONFIG.iterations
    assert document["summary"]["time_gaps_bridged"] == 1
    assert "gap in the stamps" in err


@pytest.mark.parametrize("name", ("ekf", "fastslam"))
@pytest.mark.parametrize("variance", (-1.0, 0.0))
def test_odometry_without_variances_is_weighed_by_the_motion_model(name: str, variance: float, tmp_path: Path) -> None:
    # -1 (some drivers) or 0 (REP 145's "unknown") on the twist covariance's diagonal: taken as given,
    # -1 made FastSLAM's particles run off by tens of kilometres and the EKF fail numerically, exit 0.
    clean = write_log(tmp_path / "clean.mcap", CONFIG, odometry=True)
    unset = write_log(tmp_path / "unset.mcap", CONFIG, odometry=True, odometry_covariance=np.eye(6) * variance)
    for log in (clean, unset):
        code, err = invoke("run", str(log), "--estimator", name, "-o", str(tmp_path / log.stem))
        assert code == 0, err
    assert err.count("odometry leaves the variance of vx, vy, vz, wx, wy, wz unset") == 1  # warned once
    document = json.loads((tmp_path / "unset" / "run.json").read_text())
    assert document["summary"]["iterations"] == CONFIG.iterations and "failed" not in " ".join(document["warnings"])
    assert position_rmse(tmp_path / "unset") <= 1.5 * position_rmse(tmp_path / "clean") + 0.1


@pytest.mark.parametrize("name", ("ekf", "fastslam"))
def test_odometry_placeholder_variances_are_taken_as_unmeasured(name: str, tmp_path: Path) -> None:
    # ros2_control's diff_drive_controller publishes 1e6 on the axes it does not measure and 1e3 on yaw:
    # taken as measurements the EKF ended 77 m off (exit 0, no word) and FastSLAM broke down (exit 4).
    placeholders = np.diag([0.0025, 0.0025, 1e6, 1e6, 1e6, 1e3])
    clean = write_log(tmp_path / "clean.mcap", CONFIG, odometry=True)
    driver = write_log(tmp_path / "driver.mcap", CONFIG, odometry=True, odometry_covariance=placeholders)
    for log in (clean, driver):
        code, err = invoke("run", str(log), "--estimator", name, "-o", str(tmp_path / log.stem))
        assert code == 0, err
    assert "odometry leaves the variance of vz, wx, wy, wz unset (zero, negative, or 100 and above" in err
    assert position_rmse(tmp_path / "driver") <= 1.5 * position_rmse(tmp_path / "clean") + 0.1


def test_a_covariance_that_is_no_covariance_is_skipped_and_counted(tmp_path: Path) -> None:
    # An off-diagonal term larger than the variances: the EKF took square roots of negative variances
    # (a numpy RuntimeWarning on stderr, 172 iterations skipped, ATE 7 m, exit 0).
    broken = np.eye(6) * 0.0025
    broken[0, 1] = broken[1, 0] = 0.01
    log = write_log(tmp_path / "broken.mcap", CONFIG, odometry=True, odometry_covariance=broken)
    code, err = invoke("run", str(log), "--estimator", "ekf", "-o", str(tmp_path / "out"))
    assert code == 0, err
    assert "RuntimeWarning" not in err and "covariance not positive semi-definite" in err
    document = json.loads((tmp_path / "out" / "run.json").read_text())
    assert document["skipped"]["odometry: covariance not positive semi-definite"] == CONFIG.iterations
    screen = InputScreen()
    covariance = np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    assert screen.fix(PositionFix(0, [1.0, 2.0, 3.0], covariance)) is None
    assert screen.fix(PositionFix(0, [1.0, 2.0, 3.0], np.eye(3))) is not None
    assert screen.skipped == {"fixes: covariance not positive semi-definite": 1}


def test_fuse_says_when_every_fix_of_the_log_is_unusable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # All-zero covariances (ROS's "unknown"): every fix skipped, and fuse said the log had none (exit 4).
    import tests.hostile_logs as hostile

    plain = hostile._fix
    monkeypatch.setattr(hostile, "_fix", lambda stamp, position, sigma: plain(stamp, position, 0.0))
    log = write_log(tmp_path / "zero.mcap", CONFIG, fixes_every=10)
    code, err = invoke("run", str(log), "-e", "relpoint", "-o", str(tmp_path / "run"))
    assert code == 0, err
    code, err = invoke("fuse", str(tmp_path / "run"), "--log", str(log), "-o", str(tmp_path / "fused"))
    assert code == 3 and "no usable position fix (15 no covariance)" in err.strip().splitlines()[-1], err
    assert not (tmp_path / "fused").exists()


@pytest.mark.parametrize("tolerance", ("nan", "-1"))
def test_an_import_tolerance_that_is_no_duration_is_a_usage_error(tolerance: str, tmp_path: Path) -> None:
    # It paired nothing (or everything) and exited 0.
    code, err = invoke("import", "tum", str(tmp_path), "-o", str(tmp_path / "x.mcap"), "--tolerance", tolerance)
    assert code == 2 and "--tolerance" in err and not (tmp_path / "x.mcap").exists()


class _Singular(Estimator):
    """Fails numerically on every third iteration."""

    name = "singular"

    def __init__(self) -> None:
        self.calls = 0

    def step(self, observation: PointObservation) -> Pose:
        self.calls += 1
        if self.calls % 3 == 0:
            raise np.linalg.LinAlgError("singular matrix")
        return Pose(observation.stamp_ns, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))

    def landmark_map(self) -> LandmarkMap:
        return LandmarkMap(
            np.zeros((1, 3)), np.ones(1, dtype=np.int64), np.zeros(1, dtype=bool), np.zeros(1, dtype=np.int64)
        )


def test_a_singular_iteration_is_skipped_counted_and_the_run_goes_on() -> None:
    rng = np.random.default_rng(0)
    inputs = [PointObservation(k * 10**8, rng.normal(size=(10, 3))) for k in range(1, 10)]
    result = pipeline.run(iter(inputs), _Singular())
    assert len(result.trajectory) == 6
    assert result.skipped == {"iterations: numerics failed (skipped)": 3}


class _RunsOff(Estimator):
    """Tracks at the origin, then (from iteration ``at``, or only in :meth:`finish`) places its pose at
    ``distance`` m, finite but absurd: the numerics of a filter that has come apart."""

    name = "runs-off"

    def __init__(self, distance: float, at: int | None) -> None:
        self.distance, self.at, self.calls = distance, at, 0

    def step(self, observation: PointObservation) -> Pose:
        self.calls += 1
        x = self.distance if self.at is not None and self.calls >= self.at else float(self.calls)
        return Pose(observation.stamp_ns, (x, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))

    def finish(self, trajectory: Trajectory) -> Trajectory:
        if self.at is not None:
            return trajectory
        positions = trajectory.positions.copy()
        positions[-1, 0] = self.distance
        return Trajectory(trajectory.stamps_ns, positions, trajectory.quats_xyzw)

    def landmark_map(self) -> LandmarkMap:
        return _Singular().landmark_map()


@pytest.mark.parametrize(("distance", "at"), [(1.3e78, 5), (1e9, 5), (1.3e78, None)])
def test_a_pose_far_beyond_the_scene_is_an_estimator_failure(distance: float, at: int | None) -> None:
    # Finite, so the pipeline's check for a lost pose let 1e78 m through with exit 0.
    rng = np.random.default_rng(0)
    inputs = [PointObservation(k * 10**8, rng.normal(size=(10, 3)) * 20.0) for k in range(1, 10)]
    with pytest.raises(EstimatorError, match="broke down") as error:
        pipeline.run(iter(inputs), _RunsOff(distance, at))
    assert f"{distance:.3g} m" in str(error.value) and "runs-off" in str(error.value)


def test_a_pose_far_out_with_far_fixes_is_no_failure() -> None:
    # Fixes in an Earth-centred frame place the scene millions of metres out: that is its extent.
    rng = np.random.default_rng(0)
    inputs: list[object] = [PositionFix(10**8, [6.4e6, 0.0, 0.0], np.eye(3))]
    inputs += [PointObservation(k * 10**8, rng.normal(size=(10, 3))) for k in range(1, 10)]
    result = pipeline.run(iter(inputs), _RunsOff(6.4e6, 3))  # type: ignore[arg-type]
    assert len(result.trajectory) == 9


def test_the_screen_keeps_real_ranges_and_drops_absurd_ones() -> None:
    rng = np.random.default_rng(1)
    screen = InputScreen()
    for scale in (0.5, 3.0, 70.0, 0.5):  # indoor, room, outdoor and back: nothing real is dropped
        for k in range(20):
            points = rng.normal(size=(40, 3)) * scale
            assert len(screen.points(PointObservation(k, points))) == 40
    screen = InputScreen()
    kept = screen.points(PointObservation(0, np.array([[1.0, 0, 0], [2.0, 0, 0], [1e7, 0, 0], [3.0, 1, 0]])))
    assert len(kept) == 3 and screen.skipped["points: implausible range (far beyond the data's own)"] == 1
    assert screen.fix(PositionFix(0, [np.inf, 0, 0], np.eye(3))) is None
    assert screen.fix(PositionFix(0, [1.0, 2.0, 3.0], np.eye(3))) is not None
    # an all-zero covariance is ROS's "unknown": such a fix cannot be weighed
    assert screen.fix(PositionFix(0, [1.0, 2.0, 3.0], np.zeros((3, 3)))) is None
    assert screen.skipped["fixes: no covariance"] == 1
    assert screen.fix(PositionFix(0, [1.0, 2.0, 3.0], np.diag([0.04, 0.04, 0.0]))) is not None
    assert screen.odometry(OdometryMeasurement(0, [3e8, 0, 0], [0, 0, 0])) is None
    assert screen.odometry(OdometryMeasurement(0, [1.0, 0, 0], [0, 0, 0.1])) is not None


def test_oversized_clouds_and_images_are_refused_before_allocation() -> None:
    # Stride-0 byte buffers: headers that match their data without allocating it.
    cloud_bytes = np.broadcast_to(np.zeros(1, np.uint8), (5_000_000 * 16,))
    huge_cloud = SimpleNamespace(width=5_000_000, height=1, fields=[], data=cloud_bytes, point_step=16,
                                 row_step=5_000_000 * 16, is_bigendian=False, header=None)  # fmt: skip
    with pytest.raises(ros2.OversizedMessage, match="exceeds the limit"):
        ros2.msg_to_observation(huge_cloud)
    image_bytes = np.broadcast_to(np.zeros(1, np.uint8), (10_000 * 20_000,))
    huge_image = SimpleNamespace(width=10_000, height=10_000, step=20_000, encoding="16UC1", is_bigendian=False,
                                 data=image_bytes)  # fmt: skip
    with pytest.raises(ros2.OversizedMessage, match="exceeds the limit"):
        ros2.msg_to_depth(huge_image)


def test_headers_claiming_more_than_their_bytes_are_malformed_not_oversized() -> None:
    lying_cloud = SimpleNamespace(width=5_000_000, height=1, fields=[], data=b"", point_step=16,
                                  row_step=5_000_000 * 16, is_bigendian=False, header=None)  # fmt: skip
    with pytest.raises(ros2.InputError, match="does not match") as caught:
        ros2.msg_to_observation(lying_cloud)
    assert not isinstance(caught.value, ros2.OversizedMessage)


def test_depth_frames_too_small_to_track_are_skipped_and_counted() -> None:
    from relpoint.screening import InputScreen
    from relpoint.types import DepthFrame, Intrinsics

    screen = InputScreen()
    tiny = DepthFrame(0, np.ones((1, 1), np.float32), Intrinsics(1, 1, 1.0, 1.0, 0.5, 0.5))
    usable = DepthFrame(1, np.ones((16, 20), np.float32), Intrinsics(20, 16, 10.0, 10.0, 10.0, 8.0))
    assert screen.depth(tiny) is None
    assert screen.depth(usable) is usable
    assert screen.skipped == {"depth frames: too small to track": 1}


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--param", "match_bound=1e308"), "match_bound must be between"),
        (("--param", "ring_size=1e8"), "ring_size must be between"),
        (("--param", "ring_size=true"), "ring_size must be a number"),
        (("--param", "ring_size=2.5"), "ring_size must be an integer"),
        (("--param", "final_adjustment=7"), "final_adjustment must be true or false"),
    ],
)
def test_settings_out_of_range_are_usage_errors(args: tuple[str, ...], message: str, tmp_path: Path) -> None:
    log = REPO / "sample_logs" / "figure8.mcap"
    code, err = invoke("run", str(log), "--estimator", "relpoint", *args, "-o", str(tmp_path / "o"))
    assert code == 2 and message in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists()


def test_estimator_settings_are_read_as_their_kind(tmp_path: Path) -> None:
    log = REPO / "sample_logs" / "figure8.mcap"
    code, err = invoke("run", str(log), "-e", "fastslam", "--param", "particles=1e7", "-o", str(tmp_path / "o"))
    assert code == 2 and "particles must be between 1 and 10000" in err
    config = ros2_free_fastslam_config(["variant=1.0", "particles=8"])
    assert config.variant == "1.0" and config.particles == 8


def ros2_free_fastslam_config(params: list[str]):
    from relpoint.estimators import ESTIMATORS

    return ESTIMATORS["fastslam"].build_config({}, params)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--rate", "1e-300"), "rate must be between"),
        (("--iterations", "100000000"), "iterations must be between"),
        (("--noise", "nan"), "noise must be a finite number"),
    ],
)
def test_simulation_settings_out_of_range_are_usage_errors(args: tuple[str, ...], message: str, tmp_path: Path) -> None:
    code, err = invoke("simulate", "-o", str(tmp_path / "s.mcap"), *args)
    assert code == 2 and message in err
    assert not (tmp_path / "s.mcap").exists()


ALIAS_BOMB = (
    "a: &a ["
    + ",".join(['"lol"'] * 9)
    + "]\n"
    + "".join(f"{b}: &{b} [" + ",".join([f"*{a}"] * 9) + "]\n" for a, b in zip("abcdefgh", "bcdefghi", strict=True))
)


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("bomb.yaml", ALIAS_BOMB.encode(), "expands to more than"),
        ("binary.toml", bytes(range(256)) * 8, "binary file"),
        ("latin.yaml", "noise: 0.3 # caf\xe9\n".encode("latin-1"), "not UTF-8"),
        ("big.toml", b"# " + b"x" * 2_000_000 + b"\n", "larger than 1 MB"),
        ("settings.ini", b"noise = 1\n", "must end in .toml"),
    ],
)
def test_config_files_are_bounded_before_parsing(name: str, content: bytes, message: str, tmp_path: Path) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    start = time.perf_counter()
    for command in (["simulate", "-o", str(tmp_path / "s.mcap")],
                    ["run", str(REPO / "sample_logs" / "figure8.mcap"), "-e", "ekf", "-o", str(tmp_path / "o")]):  # fmt: skip
        code, err = invoke(*command, "--config", str(path))
        assert code == 2 and message in err and err.count("\n") == 1 and len(err) < 400
    assert time.perf_counter() - start < 20  # parsing is bounded: the bomb expanded would take minutes


def test_dev_zero_as_a_config_file_is_refused_unread(tmp_path: Path) -> None:
    link = tmp_path / "zero.toml"
    link.symlink_to("/dev/zero")
    process = subprocess.run([sys.executable, "-m", "relpoint_cli.main", "simulate", "-o", str(tmp_path / "s.mcap"),
                              "--config", str(link)], capture_output=True, text=True, timeout=120, cwd=REPO)  # fmt: skip
    assert process.returncode == 2 and "larger than 1 MB" in process.stderr


def test_info_on_a_log_whose_every_cloud_is_unreadable_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import tests.hostile_logs as hostile

    plain = hostile._cloud

    def ambiguous(stamp: int, points: np.ndarray, ids: np.ndarray) -> dict:
        message = plain(stamp, points, ids)
        message["fields"] = [*message["fields"], {"name": "x", "offset": 12, "datatype": 7, "count": 1}]
        return message

    monkeypatch.setattr(hostile, "_cloud", ambiguous)
    log = write_log(tmp_path / "ambiguous.mcap", SimulationConfig(iterations=5, density=25, seed=1))
    result = CliRunner().invoke(cli, ["info", str(log)])
    assert result.exit_code == 0, result.output
    assert "no cloud could be read" in result.output and "two fields named 'x'" in result.output
    assert "ekf        cannot run (no usable points)" in result.output  # as run then says (below)
    result = CliRunner().invoke(cli, ["info", str(log), "--json"])
    document = json.loads(result.stdout)
    observations = document["observations"]
    assert observations["points_mean"] is None and sum(observations["skipped"].values()) == 5
    assert not any(cap["can_run"] for name, cap in document["estimators"].items())
    code, err = invoke("run", str(log), "-e", "ekf", "-o", str(tmp_path / "out"))
    assert code == 3 and err.strip().splitlines()[-1].startswith("relpoint: error: the log holds no usable"), err


def test_info_on_a_log_of_empty_clouds_says_nothing_can_run(tmp_path: Path) -> None:
    def empty(k: int, stamp: int, points: np.ndarray, ids: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
        return stamp, points[:0], ids[:0]

    log = write_log(tmp_path / "empty.mcap", SimulationConfig(iterations=5, density=25, seed=1), empty)
    result = CliRunner().invoke(cli, ["info", str(log)])
    assert result.exit_code == 0, result.output
    for name in ("ekf", "fastslam", "relpoint"):
        assert f"{name:<10} cannot run (no usable points)" in result.output
    assert "dense      cannot run (missing depth, camera_info)" in result.output


def test_the_run_line_counts_what_run_json_counts(tmp_path: Path) -> None:
    # result.mcap reads the observations again; what it meets unusable was already counted by the run.
    def empty_every_fifth(
        k: int, stamp: int, points: np.ndarray, ids: np.ndarray
    ) -> tuple[int, np.ndarray, np.ndarray]:
        return (stamp, points[:0], ids[:0]) if k % 5 == 4 else (stamp, points, ids)

    log = write_log(tmp_path / "gaps.mcap", SimulationConfig(iterations=40, density=25, seed=2), empty_every_fifth)
    result = CliRunner().invoke(cli, ["run", str(log), "-e", "ekf", "-o", str(tmp_path / "out")])
    assert result.exit_code == 0, result.stderr
    skipped = json.loads((tmp_path / "out" / "run.json").read_text())["skipped"]
    assert sum(skipped.values()) == 8
    assert ", 8 unusable items skipped" in result.stderr


@pytest.mark.parametrize("name", POINT_ESTIMATORS)
def test_a_log_without_one_usable_point_is_an_input_error(name: str, tmp_path: Path) -> None:
    def nothing(k: int, stamp: int, points: np.ndarray, ids: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
        return stamp, np.full_like(points[:3], np.nan), ids[:3]

    log = write_log(tmp_path / "nothing.mcap", SimulationConfig(iterations=20, density=25, seed=2), nothing)
    code, err = invoke("run", str(log), "-e", name, "-o", str(tmp_path / "out"))
    assert code == 3 and err.strip().splitlines()[-1].startswith("relpoint: error: the log holds no usable point"), err
    assert not (tmp_path / "out").exists()
