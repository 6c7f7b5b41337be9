"""TUM RGB-D folders as the benchmark ships them: the camera named by the folder, ground truth at its own rate."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from formats.log import LogReader
from formats.rgbd_import import TUM_CAMERAS, import_tum, tum_camera_number
from relpoint.types import Intrinsics
from relpoint_cli.main import cli


@pytest.mark.parametrize(
    ("name", "number"),
    [
        ("rgbd_dataset_freiburg3_long_office_household", 3),
        ("rgbd_dataset_freiburg2_pioneer_360", 2),
        ("fr1_desk", 1),
        ("evo-fr1xyz", 1),
        ("TUM_FR2-xyz", 2),
        ("Freiburg_3_walking", 3),
        ("my_scan", None),
        ("frame1", None),
        ("freiburg4_x", None),
        ("fr12", None),
    ],
)
def test_the_freiburg_camera_is_read_from_the_folder_name(name: str, number: int | None) -> None:
    assert tum_camera_number(Path("/data") / name) == number


def _tum_folder(folder: Path, depth_stamps: list[float], groundtruth: list[tuple[float, ...]]) -> None:
    folder.mkdir(parents=True)
    (folder / "depth").mkdir()
    for k, _ in enumerate(depth_stamps):
        Image.fromarray(np.full((48, 64), 7500, dtype=np.uint16)).save(folder / "depth" / f"{k}.png")
    (folder / "depth.txt").write_text(
        "# depth maps\n# file: 'x.bag'\n# timestamp filename\n"
        + "".join(f"{t:.6f} depth/{k}.png\n" for k, t in enumerate(depth_stamps))
    )
    (folder / "groundtruth.txt").write_text(
        "# ground truth trajectory\n# file: 'x.bag'\n# timestamp tx ty tz qx qy qz qw\n"
        + "".join(" ".join(f"{v:.6f}" for v in row) + "\n" for row in groundtruth)
    )


def test_a_freiburg3_folder_is_imported_with_the_freiburg3_camera_and_says_so(tmp_path: Path) -> None:
    # Imported with Freiburg 1's intrinsics, as before, a Freiburg 3 sequence's points were bent by 3.5 % in x and
    # 4.4 % in y, and the import only warned that fr3 "differs".
    folder = tmp_path / "rgbd_dataset_freiburg3_long_office_household"
    _tum_folder(folder, [1341847980.722988], [(1341847980.72, 0, 0, 0, 0, 0, 0, 1)])
    result = CliRunner().invoke(cli, ["import", "tum", str(folder), "-o", str(tmp_path / "fr3.mcap")])
    assert result.exit_code == 0, result.output
    assert "Freiburg 3" in result.output and "535.4,539.2,320.1,247.6" in result.output
    (info,) = [r.value for r in LogReader(tmp_path / "fr3.mcap").records(["camera_info"])]
    fr3 = TUM_CAMERAS[3]
    scale = 64 / 640  # the test's images are a tenth of the camera's size
    assert isinstance(info, Intrinsics)
    assert (info.fx, info.fy, info.cx, info.cy) == pytest.approx((fr3.fx * scale, fr3.fy * scale, fr3.cx * scale,
                                                                 fr3.cy * scale))  # fmt: skip

    unnamed = tmp_path / "office"
    _tum_folder(unnamed, [1341847980.722988], [(1341847980.72, 0, 0, 0, 0, 0, 0, 1)])
    result = CliRunner().invoke(cli, ["import", "tum", str(unnamed), "-o", str(tmp_path / "office.mcap")])
    assert result.exit_code == 0 and "warning" in result.output and "Freiburg 1" in result.output
    (info,) = [r.value for r in LogReader(tmp_path / "office.mcap").records(["camera_info"])]
    assert info.fx == pytest.approx(TUM_CAMERAS[1].fx * scale)

    given = ["--intrinsics", "600,600,320,240"]
    result = CliRunner().invoke(cli, ["import", "tum", str(folder), "-o", str(tmp_path / "given.mcap"), *given])
    assert result.exit_code == 0 and "Freiburg" not in result.output
    (info,) = [r.value for r in LogReader(tmp_path / "given.mcap").records(["camera_info"])]
    assert (info.fx, info.cx) == (600.0, 320.0)


def test_ground_truth_is_interpolated_to_each_depth_stamp(tmp_path: Path) -> None:
    # The mocap's 100 Hz samples fall between the camera's frames: each frame took the nearest sample's pose at
    # its own stamp, up to 5 ms of motion off (2 mm at 0.4 m/s).
    t0 = 1305031102.0
    turn = [math.radians(10.0) * k for k in range(4)]  # about z, 10 degrees a sample
    groundtruth = [(t0 + 0.01 * k, 0.4 * k, -0.1 * k, 1.0, 0.0, 0.0, math.sin(a / 2), math.cos(a / 2))
                   for k, a in enumerate(turn)]  # fmt: skip
    folder = tmp_path / "rgbd_dataset_freiburg1_xyz"
    _tum_folder(folder, [t0 + 0.0025, t0 + 0.017, t0 + 0.03, t0 + 0.0445], groundtruth)
    counts = import_tum(folder, tmp_path / "t.mcap")
    assert counts.ground_truth_pose == 4
    poses = [r.value for r in LogReader(tmp_path / "t.mcap").records(["ground_truth_pose"])]
    expected_fractions = [0.25, 1.7, 3.0, 3.0]  # the last frame is 4.5 ms after the last sample: that sample
    for pose, fraction in zip(poses, expected_fractions, strict=True):
        assert pose.position == pytest.approx((0.4 * fraction, -0.1 * fraction, 1.0), abs=1e-4)  # stamps: 0.2 us
        yaw = 2 * math.atan2(pose.quat_xyzw[2], pose.quat_xyzw[3])
        assert math.degrees(yaw) == pytest.approx(10.0 * fraction, abs=1e-3)
