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


def test_a_folder_calibration_file_gives_the_intrinsics(tmp_path: Path) -> None:
    # ETH3D's SLAM datasets (TUM lists, 5000 per metre, 739x458 images) keep their camera in calibration.txt
    # as "fx fy cx cy": it was ignored and Freiburg 1's intrinsics were scaled to the images (fx 597 for 726),
    # with a warning only that the folder's name did not say which Freiburg camera it was.
    folder = tmp_path / "sofa_1"
    _tum_folder(folder, [1341847980.722988], [(1341847980.72, 0, 0, 0, 0, 0, 0, 1)])
    (folder / "calibration.txt").write_text("726.21081542969 726.21081542969 359.2048034668 202.47247314453\n")
    result = CliRunner().invoke(cli, ["import", "tum", str(folder), "-o", str(tmp_path / "eth3d.mcap")])
    assert result.exit_code == 0, result.output
    assert "calibration.txt" in result.output and "warning" not in result.output
    (info,) = [r.value for r in LogReader(tmp_path / "eth3d.mcap").records(["camera_info"])]
    assert (info.width, info.height) == (64, 48)  # the images' size; the file's numbers are theirs, not scaled
    assert (info.fx, info.fy, info.cx, info.cy) == pytest.approx((726.21081542969, 726.21081542969, 359.2048034668,
                                                                 202.47247314453))  # fmt: skip

    given = ["--intrinsics", "600,600,32,24"]
    result = CliRunner().invoke(cli, ["import", "tum", str(folder), "-o", str(tmp_path / "given.mcap"), *given])
    assert result.exit_code == 0, result.output
    (info,) = [r.value for r in LogReader(tmp_path / "given.mcap").records(["camera_info"])]
    assert (info.fx, info.cx) == (600.0, 32.0)

    (folder / "calibration.txt").write_text("726.2 726.2 359.2\n")
    result = CliRunner().invoke(cli, ["import", "tum", str(folder), "-o", str(tmp_path / "bad.mcap")])
    assert result.exit_code == 3 and "Traceback" not in result.output
    assert "calibration.txt: not one line of the four numbers fx fy cx cy" in result.output


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


def _lists(folder: Path, depth_lines: str, rgb_lines: str = "", *, size: tuple[int, int] = (64, 48),
           raw_depth: int = 7500) -> None:  # fmt: skip
    """A TUM folder whose lists hold the given lines; every file they name is written."""
    folder.mkdir(parents=True, exist_ok=True)
    for line in (depth_lines + rgb_lines).splitlines():
        if line and not line.startswith("#"):
            name = line.split()[1].replace("\\", "/")
            (folder / name).parent.mkdir(exist_ok=True)
            if name.startswith("depth"):
                Image.fromarray(np.full(size[::-1], raw_depth, dtype=np.uint16)).save(folder / name)
            else:
                Image.fromarray(np.full((*size[::-1], 3), 90, dtype=np.uint8)).save(folder / name)
    (folder / "depth.txt").write_text(depth_lines)
    if rgb_lines:
        (folder / "rgb.txt").write_text(rgb_lines)


def _depth_stamps(path: Path) -> list[int]:
    return [r.stamp_ns for r in LogReader(path).records(["depth"])]


@pytest.mark.parametrize("factor", [1_000, 1_000_000_000])
def test_stamps_in_milliseconds_or_nanoseconds_are_named_not_a_crash(tmp_path: Path, factor: int) -> None:
    folder = tmp_path / "scan"
    _lists(folder, "".join(f"{(1305031102 + k) * factor} depth/{k}.png\n" for k in range(2)))
    result = CliRunner().invoke(cli, ["import", "tum", str(folder), "-o", str(tmp_path / "x.mcap")])
    assert result.exit_code == 3, result.output
    assert "depth.txt:1: timestamp" in result.output and "milliseconds or nanoseconds" in result.output
    assert "Traceback" not in result.output and not (tmp_path / "x.mcap").exists()


def test_stamps_keep_every_nanosecond_of_their_text(tmp_path: Path) -> None:
    # Through float64 seconds, 1305031102.175852 became ...175852032 ns.
    folder = tmp_path / "scan"
    _lists(folder, "1305031102.175852 depth/a.png\n1305031102.209102345 depth/b.png\n")
    import_tum(folder, tmp_path / "x.mcap")
    assert _depth_stamps(tmp_path / "x.mcap") == [1305031102_175852000, 1305031102_209102345]


def test_a_depth_list_out_of_time_order_is_read_in_time_order(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    # Each image not after the one before was dropped: a shuffled list lost most of its frames, silently.
    stamps = [100.0 + 0.033 * k for k in range(8)]
    shuffled = [stamps[k] for k in (3, 0, 6, 1, 7, 2, 5, 4)]
    folder = tmp_path / "scan"
    _lists(folder, "".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in shuffled) + f"{stamps[2]:.6f} depth/again.png\n")
    counts = import_tum(folder, tmp_path / "x.mcap")
    assert counts.depth == 8 and counts.skipped_depth == 1  # the repeated stamp
    assert _depth_stamps(tmp_path / "x.mcap") == [round(t * 1e9) for t in stamps]
    assert "not in time order" in caplog.text and "repeats the stamp" in caplog.text


def test_a_tolerance_pairing_nothing_is_warned_of(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    folder = tmp_path / "rgbd_dataset_freiburg1_xyz"
    depth = [100.0 + 0.033 * k for k in range(6)]
    _lists(folder, "".join(f"{t:.6f} depth/{k}.png\n" for k, t in enumerate(depth)),
           "".join(f"{t + 0.004:.6f} rgb/{k}.png\n" for k, t in enumerate(depth)))  # fmt: skip
    (folder / "groundtruth.txt").write_text("".join(f"{t + 0.006:.4f} 0 0 0 0 0 0 1\n" for t in depth))
    counts = import_tum(folder, tmp_path / "paired.mcap")
    assert (counts.color, counts.ground_truth_pose) == (6, 6) and "have no" not in caplog.text
    counts = import_tum(folder, tmp_path / "x.mcap", tolerance=0.001)
    assert (counts.color, counts.ground_truth_pose) == (0, 0)
    assert "6 of 6 depth frames have no colour image within 0.001 s in rgb.txt" in caplog.text
    assert "6 of 6 depth frames have no ground-truth pose within 0.001 s in groundtruth.txt" in caplog.text


def test_an_output_inside_the_dataset_folder_is_replaced_by_a_second_import(tmp_path: Path) -> None:
    folder = tmp_path / "rgbd_dataset_freiburg1_xyz"
    _lists(folder, "100.0 depth/a.png\n100.033 depth/b.png\n")
    for _ in range(2):
        result = CliRunner().invoke(cli, ["import", "tum", str(folder), "-o", str(folder / "fr1.mcap")])
        assert result.exit_code == 0, result.output
    assert len(_depth_stamps(folder / "fr1.mcap")) == 2
    result = CliRunner().invoke(cli, ["import", "tum", str(folder), "-o", str(folder / "depth.txt"), "--overwrite"])
    assert result.exit_code == 2 and "100.033 depth/b.png" in (folder / "depth.txt").read_text()


def test_the_freiburg_name_is_read_through_dot_dot(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    folder = tmp_path / "rgbd_dataset_freiburg2_desk"
    (folder / "depth").mkdir(parents=True)
    monkeypatch.chdir(folder / "depth")
    assert tum_camera_number("..") == 2
    monkeypatch.chdir(folder)
    assert tum_camera_number(".") == 2
    (tmp_path / "data").symlink_to(folder)
    assert tum_camera_number(tmp_path / "data") == 2


def test_associations_alone_backslashes_and_a_byte_order_mark_are_read(tmp_path: Path) -> None:
    folder = tmp_path / "scan"
    _lists(folder, "100.000000 depth\\a.png\n100.033000 depth\\b.png\n",
           "100.001000 rgb\\a.png\n100.034000 rgb\\b.png\n")  # fmt: skip
    (folder / "depth.txt").write_text("\ufeff# depth\n100.000000 depth\\a.png\n100.033000 depth\\b.png\n")
    counts = import_tum(folder, tmp_path / "x.mcap")
    assert (counts.depth, counts.color, counts.skipped_depth) == (2, 2, 0)

    (folder / "associations.txt").write_text("100.001000 rgb/a.png 100.000000 depth/a.png\n"
                                             "100.034000 rgb/b.png 100.033000 depth/b.png\n")  # fmt: skip
    (folder / "depth.txt").unlink()
    (folder / "rgb.txt").unlink()
    counts = import_tum(folder, tmp_path / "y.mcap")
    assert (counts.depth, counts.color) == (2, 2)
    assert _depth_stamps(tmp_path / "y.mcap") == [100_000_000_000, 100_033_000_000]


def test_depth_images_of_another_size_are_skipped_and_counted(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    folder = tmp_path / "scan"
    _lists(folder, "100.0 depth/a.png\n100.1 depth/b.png\n100.2 depth/c.png\n")
    Image.fromarray(np.full((24, 32), 7500, dtype=np.uint16)).save(folder / "depth" / "b.png")
    counts = import_tum(folder, tmp_path / "x.mcap")
    assert (counts.depth, counts.skipped_depth) == (2, 1)
    assert "depth/b.png is 32x24, the first one 64x48" in caplog.text


def test_millimetre_depth_is_warned_of_and_read_with_depth_scale(tmp_path: Path) -> None:
    folder = tmp_path / "scan"
    _lists(folder, "100.0 depth/a.png\n", raw_depth=1500)  # 1.5 m in millimetres
    result = CliRunner().invoke(cli, ["import", "tum", str(folder), "-o", str(tmp_path / "x.mcap")])
    assert result.exit_code == 0 and "median depth of 0.30 m" in result.output and "--depth-scale 1000" in result.output
    result = CliRunner().invoke(cli, ["import", "tum", str(folder), "-o", str(tmp_path / "y.mcap"),
                                      "--depth-scale", "1000"])  # fmt: skip
    assert result.exit_code == 0 and "median depth" not in result.output
    (depth,) = [r.value for r in LogReader(tmp_path / "y.mcap").records(["depth"])]
    assert float(np.median(depth)) == pytest.approx(1.5)
    result = CliRunner().invoke(cli, ["import", "7scenes", str(folder), "-o", str(tmp_path / "z.mcap"),
                                      "--depth-scale", "1000"])  # fmt: skip
    assert result.exit_code == 2 and "--depth-scale does not apply to the 7scenes layout" in result.output
