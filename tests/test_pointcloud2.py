"""PointCloud2 decoding honours point_step, offsets, extra fields, row padding and byte order."""

from __future__ import annotations

import numpy as np
import pytest

from formats.pointcloud2 import Field, decode_cloud, encode_cloud, xyz_from_cloud
from relpoint.errors import InputError

FLOAT32, INT32, UINT16, UINT8, FLOAT64 = 7, 5, 4, 2, 8


def padded_cloud(n: int, rng: np.random.Generator, big_endian: bool = False) -> tuple[np.ndarray, bytes, list[Field]]:
    """A 40-byte point: x,y,z f32, 4 pad bytes, intensity f64, id i32, ring u16, 2 pad, rgb 3 x u8, pad."""
    order = ">" if big_endian else "<"
    dtype = np.dtype(
        {
            "names": ["x", "y", "z", "intensity", "id", "ring", "rgb"],
            "formats": [
                f"{order}f4",
                f"{order}f4",
                f"{order}f4",
                f"{order}f8",
                f"{order}i4",
                f"{order}u2",
                ("u1", (3,)),
            ],
            "offsets": [0, 4, 8, 16, 24, 28, 32],
            "itemsize": 40,
        }
    )
    points = np.zeros(n, dtype=dtype)
    points["x"], points["y"], points["z"] = rng.normal(size=(3, n)).astype(np.float32)
    points["intensity"] = rng.uniform(size=n)
    points["id"] = rng.integers(-1, 1000, n)
    points["ring"] = rng.integers(0, 64, n)
    points["rgb"] = rng.integers(0, 255, (n, 3))
    fields = [
        Field("x", 0, FLOAT32), Field("y", 4, FLOAT32), Field("z", 8, FLOAT32), Field("intensity", 16, FLOAT64),
        Field("id", 24, INT32), Field("ring", 28, UINT16), Field("rgb", 32, UINT8, 3),
    ]  # fmt: skip
    return points, points.tobytes(), fields


@pytest.mark.parametrize("big_endian", [False, True])
def test_padding_and_extra_fields_decode(big_endian: bool) -> None:
    rng = np.random.default_rng(0)
    points, data, fields = padded_cloud(257, rng, big_endian)
    cloud = decode_cloud(data, fields, width=257, height=1, point_step=40, row_step=40 * 257, big_endian=big_endian)
    for name in ("x", "y", "z", "intensity", "id", "ring"):
        np.testing.assert_array_equal(cloud[name], points[name])
    np.testing.assert_array_equal(cloud["rgb"], points["rgb"])
    xyz, kept = xyz_from_cloud(cloud)
    assert kept.all()
    np.testing.assert_allclose(xyz, np.stack([points["x"], points["y"], points["z"]], axis=1))


def test_padded_rows_are_gathered() -> None:
    rng = np.random.default_rng(1)
    points, _, fields = padded_cloud(12, rng)
    rows = points.reshape(3, 4)
    row_step = 4 * 40 + 24  # 24 bytes of padding after every row
    data = b"".join(row.tobytes() + b"\xab" * 24 for row in rows)
    cloud = decode_cloud(data, fields, width=4, height=3, point_step=40, row_step=row_step)
    np.testing.assert_array_equal(cloud["id"], points["id"])


def test_non_finite_points_are_dropped() -> None:
    fields, step, data = encode_cloud(
        {"x": np.array([1, np.nan, 3, 4], np.float32), "y": np.array([0, 0, np.inf, 0], np.float32),
         "z": np.zeros(4, np.float32)}
    )  # fmt: skip
    cloud = decode_cloud(data, fields, width=4, height=1, point_step=step, row_step=4 * step)
    xyz, kept = xyz_from_cloud(cloud)
    assert kept.tolist() == [True, False, False, True]
    assert xyz[:, 0].tolist() == [1.0, 4.0]


@pytest.mark.parametrize(
    ("width", "point_step", "row_step", "data_len", "message"),
    [
        (1_000_000_000, 16, 16_000_000_000, 160, "claims"),  # a lying header must not allocate
        (10, 16, 100, 160, "row_step"),
        (10, 8, 80, 80, "does not fit"),  # z at offset 8 overflows an 8-byte point
    ],
)
def test_lying_headers_raise(width: int, point_step: int, row_step: int, data_len: int, message: str) -> None:
    fields = [Field("x", 0, FLOAT32), Field("y", 4, FLOAT32), Field("z", 8, FLOAT32)]
    with pytest.raises(InputError, match=message):
        decode_cloud(b"\0" * data_len, fields, width=width, height=1, point_step=point_step, row_step=row_step)


def test_missing_xyz_field_and_unknown_datatype() -> None:
    with pytest.raises(InputError, match="lacks"):
        xyz_from_cloud(decode_cloud(b"\0" * 8, [Field("x", 0, FLOAT32), Field("y", 4, FLOAT32)],
                                    width=1, height=1, point_step=8, row_step=8))  # fmt: skip
    with pytest.raises(InputError, match="unknown datatype"):
        decode_cloud(b"\0" * 4, [Field("x", 0, 42)], width=1, height=1, point_step=4, row_step=4)


def test_encode_round_trip_keeps_dtypes() -> None:
    columns = {"x": np.arange(5, dtype=np.float32), "id": np.arange(5, dtype=np.int32), "flag": np.ones(5, np.uint8)}
    fields, step, data = encode_cloud(columns)
    assert step == 9
    cloud = decode_cloud(data, fields, width=5, height=1, point_step=step, row_step=5 * step)
    for name, values in columns.items():
        np.testing.assert_array_equal(cloud[name], values)
        assert cloud[name].dtype == values.dtype


def test_fields_relpoint_does_not_read_may_repeat_overflow_or_have_unknown_types() -> None:
    # Drivers pad points with fields that share a name ("_"); vendors add their own datatypes. Only the
    # coordinates and ids are read, so those fields are left out rather than refusing the cloud.
    fields = [Field("x", 0, FLOAT32), Field("_", 4, 7), Field("y", 8, FLOAT32), Field("_", 12, 7),
              Field("z", 16, FLOAT32), Field("vendor", 20, 99), Field("long", 20, 7, count=8)]  # fmt: skip
    points = np.arange(12, dtype=np.float32).reshape(4, 3)
    data = np.zeros((4, 24), dtype=np.uint8)
    for k, offset in enumerate((0, 8, 16)):
        data[:, offset : offset + 4] = points[:, k : k + 1].view(np.uint8)
    cloud = decode_cloud(data.tobytes(), fields, width=4, height=1, point_step=24, row_step=96)
    assert cloud.dtype.names == ("x", "_", "y", "z")
    xyz, _ = xyz_from_cloud(cloud)
    np.testing.assert_array_equal(xyz, points)
    # ... but a field relpoint reads must be unambiguous.
    with pytest.raises(InputError, match="two fields named 'x'"):
        decode_cloud(data.tobytes(), [*fields, Field("x", 4, FLOAT32)], width=4, height=1, point_step=24, row_step=96)


def test_an_unsigned_id_field_reads_minus_one_as_clutter() -> None:
    # A writer that declared `id` UINT32 and stored -1 (the format's clutter) gave 4294967295: each
    # clutter point counted as a landmark of its own, lowering the map's purity without a word.
    from formats.ros2 import landmark_ids

    stored = np.array([3, -1, 7], dtype=np.int32)
    np.testing.assert_array_equal(landmark_ids(stored.view(np.uint32)), [3, -1, 7])
    np.testing.assert_array_equal(landmark_ids(stored.astype(np.int64).view(np.uint64)), [3, -1, 7])
    np.testing.assert_array_equal(landmark_ids(np.array([3, 255], dtype=np.uint8)), [3, 255])
    np.testing.assert_array_equal(landmark_ids(np.array([3.0, -1.0], dtype=np.float32)), [3, -1])
