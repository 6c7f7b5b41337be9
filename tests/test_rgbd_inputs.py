"""Depth and colour images as other tools write them: colour after depth, other encodings, other sizes."""

from __future__ import annotations

from collections import Counter
from types import SimpleNamespace

import numpy as np
import pytest

from formats.log import Record
from formats.ros2 import UnsupportedEncoding, msg_to_rgb
from relpoint.types import DepthFrame, Intrinsics
from relpoint_app.runner import COLOUR_PAIRING_NS, estimator_inputs

INTRINSICS = Intrinsics(4, 3, 5.0, 5.0, 2.0, 1.5)


def _depth(stamp: int) -> Record:
    return Record("depth", stamp, np.full((3, 4), 1.5, np.float32))


def _colour(stamp: int, value: int, shape: tuple[int, int] = (3, 4)) -> Record:
    return Record("color", stamp, np.full((*shape, 3), value, np.uint8))


def _frames(records: list[Record], skipped: Counter[str] | None = None) -> list[DepthFrame]:
    return [x for x in estimator_inputs(iter([Record("camera_info", 0, INTRINSICS), *records]), skipped)]


def test_colour_is_paired_whether_it_comes_before_or_after_its_depth_image() -> None:
    # The contract asks for equal stamps, not an order: colour written after depth was dropped.
    ms = 1_000_000
    frames = _frames([_colour(10 * ms, 1), _depth(10 * ms), _depth(43 * ms), _colour(43 * ms, 2),
                      _depth(76 * ms), _colour(80 * ms, 3), _depth(200 * ms)])  # fmt: skip
    assert [f.stamp_ns for f in frames] == [10 * ms, 43 * ms, 76 * ms, 200 * ms]
    assert [None if f.color is None else int(f.color[0, 0, 0]) for f in frames] == [1, 2, 3, None]
    assert 20 * ms == COLOUR_PAIRING_NS  # 4 ms apart is paired, 120 ms is not


def test_inputs_keep_their_order_while_a_depth_image_waits_for_its_colour() -> None:
    ms = 1_000_000
    fix = Record("fix", 12 * ms, "a fix")
    out = list(
        estimator_inputs(iter([Record("camera_info", 0, INTRINSICS), _depth(10 * ms), fix, _colour(10 * ms, 7)]))
    )
    assert isinstance(out[0], DepthFrame) and out[0].color is not None and out[1] == "a fix"


def test_colour_of_another_size_is_left_out_and_counted() -> None:
    skipped: Counter[str] = Counter()
    frames = _frames([_depth(0), _colour(0, 5, shape=(6, 8))], skipped)
    assert frames[0].color is None and skipped["color: images of another size than the depth image"] == 1


def test_a_log_whose_colour_images_colour_no_depth_image_says_so_in_run_json() -> None:
    # Every colour image of another size: the map came out black, which looks like black surfaces.
    skipped: Counter[str] = Counter()
    warnings: list[str] = []
    records = [Record("camera_info", 0, INTRINSICS), _depth(0), _colour(0, 5, shape=(6, 8)), _depth(40_000_000)]
    frames = list(estimator_inputs(iter(records), skipped, warnings))
    assert len(frames) == 2 and all(f.color is None for f in frames)
    assert warnings == [
        "none of the log's 1 colour images could colour a depth image (see skipped for why): the map's points are black"
    ]
    warnings.clear()
    list(estimator_inputs(iter([Record("camera_info", 0, INTRINSICS), _depth(0), _colour(0, 5)]), None, warnings))
    assert warnings == []


def test_a_camera_info_logged_just_after_its_depth_image_is_its_camera_info() -> None:
    # Drivers publish an image, then its camera_info of the same stamp: the first frame was dropped.
    ms = 1_000_000
    skipped: Counter[str] = Counter()
    records = [_depth(10 * ms), Record("camera_info", 10 * ms, INTRINSICS), _depth(43 * ms), _depth(76 * ms)]
    frames = list(estimator_inputs(iter(records), skipped))
    assert [f.stamp_ns for f in frames] == [10 * ms, 43 * ms, 76 * ms] and not skipped
    assert all(f.intrinsics == INTRINSICS for f in frames)
    # One that comes later than the pairing window is not its camera_info: that image is skipped, counted.
    late = [_depth(10 * ms), _depth(43 * ms), Record("camera_info", 43 * ms, INTRINSICS), _depth(76 * ms)]
    frames = list(estimator_inputs(iter(late), skipped))
    assert [f.stamp_ns for f in frames] == [43 * ms, 76 * ms]
    assert skipped["depth: images without a matching camera_info"] == 1


def _image(encoding: str, channels: int, padding: int = 0) -> SimpleNamespace:
    rng = np.random.default_rng(0)
    pixels = rng.integers(0, 256, (3, 4, channels), dtype=np.uint8)
    rows = np.concatenate([pixels.reshape(3, -1), np.zeros((3, padding), np.uint8)], axis=1)
    message = SimpleNamespace(height=3, width=4, step=4 * channels + padding, encoding=encoding, data=rows.reshape(-1))
    return message, pixels


@pytest.mark.parametrize(
    ("encoding", "channels", "order"),
    [
        ("rgb8", 3, [0, 1, 2]),
        ("bgr8", 3, [2, 1, 0]),
        ("rgba8", 4, [0, 1, 2]),
        ("bgra8", 4, [2, 1, 0]),
        ("mono8", 1, [0, 0, 0]),
    ],
)
def test_colour_encodings_are_read_as_rgb(encoding: str, channels: int, order: list[int]) -> None:
    message, pixels = _image(encoding, channels, padding=3)
    np.testing.assert_array_equal(msg_to_rgb(message), pixels[..., order])


def test_an_unread_colour_encoding_is_named_as_unsupported() -> None:
    message, _ = _image("yuv422", 2)
    with pytest.raises(UnsupportedEncoding, match="yuv422"):
        msg_to_rgb(message)


def test_a_camera_info_with_non_finite_distortion_is_refused_naming_it() -> None:
    from formats.ros2 import msg_to_intrinsics
    from relpoint.errors import InputError

    with pytest.raises(ValueError, match="distortion coefficients must be finite"):
        Intrinsics(320, 240, 290.0, 290.0, 160.0, 120.0, "plumb_bob", (float("nan"), 0.0, 0.0, 0.0, 0.0))
    message = SimpleNamespace(
        width=320, height=240, k=[290.0, 0.0, 160.0, 0.0, 290.0, 120.0, 0.0, 0.0, 1.0],
        distortion_model="plumb_bob", d=[0.1, float("inf"), 0.0, 0.0, 0.0],
    )  # fmt: skip
    with pytest.raises(InputError, match="unusable camera_info: distortion coefficients must be finite"):
        msg_to_intrinsics(message)
    # all zeros is an ideal pinhole, whatever the model's name
    assert not Intrinsics(320, 240, 290.0, 290.0, 160.0, 120.0, "plumb_bob", (0.0,) * 5).distorted


def _camera_info(binning: int = 0, roi: tuple[int, int, int, int] = (0, 0, 0, 0)) -> SimpleNamespace:
    """A 640x480 CameraInfo (fx 525, centre 319.5, 239.5) with ``binning`` and ``roi`` (x, y, width, height)."""
    return SimpleNamespace(
        width=640, height=480, k=[525.0, 0.0, 319.5, 0.0, 525.0, 239.5, 0.0, 0.0, 1.0],
        distortion_model="plumb_bob", d=[0.0] * 5, binning_x=binning, binning_y=binning,
        roi=SimpleNamespace(x_offset=roi[0], y_offset=roi[1], width=roi[2], height=roi[3]),
    )  # fmt: skip


def test_a_binned_or_cropped_camera_info_describes_the_images_it_comes_with() -> None:
    from formats.ros2 import msg_to_intrinsics

    # binning and roi 0 (unset) or 1, or a region of the full image: the full sensor's intrinsics
    for message in (_camera_info(0), _camera_info(1), _camera_info(1, (0, 0, 640, 480))):
        assert msg_to_intrinsics(message) == Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
    # a driver binning 2 x 2 publishes 320x240 images with the full sensor's k (image_geometry's model)
    assert msg_to_intrinsics(_camera_info(2)) == Intrinsics(320, 240, 262.5, 262.5, 159.75, 119.75)
    # a region of 200x100 px from (100, 50): the principal point moves by the offset
    assert msg_to_intrinsics(_camera_info(0, (100, 50, 200, 100))) == Intrinsics(200, 100, 525.0, 525.0, 219.5, 189.5)


def test_a_distortion_relpoint_cannot_take_out_is_warned_of_in_run_json_too() -> None:
    # The warning went to the terminal only; run.json's warnings (what a CI job reads) did not have it.
    fisheye = Intrinsics(4, 3, 2.0, 2.0, 1.5, 1.0, "fisheye62", (0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    warnings: list[str] = []
    records = [Record("camera_info", 0, fisheye), _depth(10), _depth(20)]
    frames = list(estimator_inputs(iter(records), Counter(), warnings))
    assert len(frames) == 2 and frames[0].intrinsics == fisheye  # used as an ideal pinhole
    assert len(warnings) == 1 and "fisheye62" in warnings[0] and "ideal pinhole" in warnings[0]
