"""image_transport's compressed images, as real bags store them: ``compressedDepth`` depth and JPEG or PNG
colour (``sensor_msgs/msg/CompressedImage``) read as the raw images they encode."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import cv2
import numpy as np
from click.testing import CliRunner

from formats import ros2
from formats.log import LogReader, LogWriter
from formats.topics import Topics
from relpoint.types import Intrinsics
from relpoint_cli.main import cli

K = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
DEPTH_TOPIC = "/camera/depth/image_rect_raw/compressedDepth"
COLOUR_TOPIC = "/camera/color/image_raw/compressed"


def _compressed(stamp_ns: int, fmt: str, data: bytes) -> object:
    types = ros2.typestore().types
    return types[ros2.COMPRESSED_IMAGE](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
            frame_id="camera",
        ),
        format=fmt,
        data=np.frombuffer(data, np.uint8),
    )


def _depth_mm(i: int) -> np.ndarray:
    """A tilted wall 1.5-2.1 m away, a little nearer each frame, with a hole (0 = no measurement)."""
    u = np.arange(64)[None, :].repeat(48, axis=0)
    v = np.arange(48)[:, None].repeat(64, axis=1)
    depth = (1500 + 10 * u + 3 * v - 2 * i).astype(np.uint16)
    depth[10:14, 20:30] = 0
    return depth


def _colour(i: int) -> np.ndarray:
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[..., 0] = 200
    rgb[..., 1] = np.arange(64)[None, :] * 3 + i
    rgb[..., 2] = 40
    return rgb


def _write(path: Path, frames: int = 4, float_depth: bool = False) -> Path:
    with LogWriter(path) as writer:
        for i in range(frames):
            stamp = 10**18 + i * 33_333_333
            writer.write("/camera/depth/camera_info", ros2.CAMERA_INFO, ros2.camera_info_to_msg(stamp, K), stamp)
            if float_depth:  # inverse depth quantised to 16 bits, as compressed_depth_image_transport does
                a, b = 100.0, 100.0 / 10.0
                metres = _depth_mm(i) / 1000.0
                with np.errstate(divide="ignore"):
                    q = np.where(metres > 0, np.rint(a / metres + b), 0).astype(np.uint16)
                header, fmt, png = struct.pack("<iff", 1, a, b), "32FC1; compressedDepth png", q
            else:
                header, fmt, png = struct.pack("<iff", 0, 0.0, 0.0), "16UC1; compressedDepth png", _depth_mm(i)
            data = header + cv2.imencode(".png", png)[1].tobytes()
            writer.write(DEPTH_TOPIC, ros2.COMPRESSED_IMAGE, _compressed(stamp, fmt, data), stamp)
            bgr = np.ascontiguousarray(_colour(i)[..., ::-1])
            jpeg = cv2.imencode(".png" if i % 2 else ".jpg", bgr)[1].tobytes()
            colour_format = "rgb8; png compressed bgr8" if i % 2 else "rgb8; jpeg compressed bgr8"
            writer.write(COLOUR_TOPIC, ros2.COMPRESSED_IMAGE, _compressed(stamp, colour_format, jpeg), stamp)
    return path


def test_compressed_depth_and_colour_read_as_the_images_they_encode(tmp_path: Path) -> None:
    reader = LogReader(_write(tmp_path / "c.mcap"), Topics(depth=DEPTH_TOPIC, color=COLOUR_TOPIC))
    records = list(reader.records(["depth", "color"]))
    depths = [r.value for r in records if r.role == "depth"]
    colours = [r.value for r in records if r.role == "color"]
    assert len(depths) == len(colours) == 4 and not reader.skipped
    for i, depth in enumerate(depths):
        np.testing.assert_array_equal(depth, _depth_mm(i).astype(np.float32) * np.float32(0.001))
    np.testing.assert_array_equal(colours[1], _colour(1))  # PNG: exact
    assert np.abs(colours[0].astype(int) - _colour(0)).max() <= 8  # JPEG: within its loss, and in RGB order


def test_a_32fc1_compressed_depth_is_taken_back_from_its_inverse_depth_quantisation(tmp_path: Path) -> None:
    reader = LogReader(_write(tmp_path / "f.mcap", float_depth=True), Topics(depth=DEPTH_TOPIC))
    depth = next(r.value for r in reader.records(["depth"]))
    truth = _depth_mm(0) / 1000.0
    assert np.all(depth[truth == 0] == 0)
    # q = 100 / z + 10 rounded: z moves by at most 100 / (100 / z - 0.5) - z = 0.5 z^2 / (100 - 0.5 z)
    z = truth[truth > 0]
    assert np.all(np.abs(depth[truth > 0] - z) <= 0.5 * z**2 / (100 - 0.5 * z) + 1e-5)


def test_a_bag_with_compressed_images_runs_dense_with_colour(tmp_path: Path) -> None:
    log = _write(tmp_path / "run.mcap", frames=6)
    out = tmp_path / "out"
    result = CliRunner().invoke(
        cli, ["-q", "run", str(log), "-e", "dense", "-o", str(out), "--depth-topic", DEPTH_TOPIC,
              "--color-topic", COLOUR_TOPIC, "--param", "min_correspondences=50"],
    )  # fmt: skip
    assert result.exit_code == 0, result.stderr
    run = json.loads((out / "run.json").read_text())
    assert run["summary"]["frames"] == 6 and run["summary"]["lost_frames"] == 0
    assert not run["skipped"] and not any("colour" in w for w in run["warnings"])
    assert "depth" in run["input"]["roles"] and "color" in run["input"]["roles"]


def test_a_png_that_claims_a_huge_image_is_skipped_before_it_is_decompressed(tmp_path: Path) -> None:
    png = bytearray(cv2.imencode(".png", _depth_mm(0))[1].tobytes())
    png[16:24] = struct.pack(">II", 100_000, 100_000)  # IHDR: 10^10 pixels
    path = tmp_path / "bomb.mcap"
    with LogWriter(path) as writer:
        data = struct.pack("<iff", 0, 0.0, 0.0) + bytes(png)
        writer.write(DEPTH_TOPIC, ros2.COMPRESSED_IMAGE, _compressed(0, "16UC1; compressedDepth png", data), 0)
    reader = LogReader(path, Topics(depth=DEPTH_TOPIC))
    assert list(reader.records(["depth"])) == []
    assert reader.skipped == {f"{DEPTH_TOPIC}: oversized messages": 1}
