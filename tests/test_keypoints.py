"""The keypoint front-end (corner tracking, depth lookup, back-projection) and ``relpoint import --points``."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from formats.log import LogReader
from formats.rgbd_import import RgbdFrame
from relpoint.frontend import KeypointFrontEnd, KeypointSettings, KeypointTracker, back_project, depth_at_pixels
from relpoint.types import Intrinsics, Pose
from relpoint_app.keypoint_import import write_keypoint_log
from relpoint_cli.main import cli
from tests.conftest import shared_data

INTRINSICS = Intrinsics(160, 120, 150.0, 150.0, 79.5, 59.5)


def textured_image(rng: np.random.Generator, height: int = 120, width: int = 160) -> np.ndarray:
    """A smooth random texture (uint8) with plenty of corners, larger than the view so it can be shifted."""
    noise = rng.uniform(0, 255, size=(height // 6, width // 6)).astype(np.float32)
    return cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC).clip(0, 255).astype(np.uint8)


def shifted(image: np.ndarray, du: float, dv: float) -> np.ndarray:
    """``image`` moved by (du, dv) pixels (content at u appears at u + du)."""
    M = np.array([[1.0, 0.0, du], [0.0, 1.0, dv]])
    return cv2.warpAffine(image, M, image.shape[::-1], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


# --- depth lookup and back-projection -------------------------------------------------------------


def test_back_projection_inverts_the_pinhole_projection() -> None:
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-0.7, 0.7, 50), rng.uniform(0.5, 4, 50)])
    pixels = np.column_stack([
        INTRINSICS.fx * points[:, 0] / points[:, 2] + INTRINSICS.cx,
        INTRINSICS.fy * points[:, 1] / points[:, 2] + INTRINSICS.cy,
    ])  # fmt: skip
    np.testing.assert_allclose(back_project(pixels, points[:, 2], INTRINSICS), points, atol=1e-12)


def test_depth_lookup_rejects_holes_discontinuities_borders_and_range() -> None:
    depth = np.full((120, 160), 2.0, dtype=np.float32)
    depth[:, 100:] = 3.0  # a step: pixels within the window of column 100 span it
    depth[30, 30] = 0.0  # one unmeasured pixel
    depth[90, 40] = np.nan
    depth[60:70, 10:20] = 9.0  # beyond max_depth
    pixels = np.array([[50.2, 50.4], [99.0, 50.0], [97.0, 50.0], [31.0, 31.0], [40.0, 89.0], [1.0, 50.0],
                       [15.0, 65.0], [120.0, 50.0]])  # fmt: skip
    depth_m, valid = depth_at_pixels(depth, pixels, radius=2, max_relative_jump=0.03, max_depth=5.0)
    assert valid.tolist() == [True, False, True, False, False, False, False, True]
    assert depth_m[0] == pytest.approx(2.0) and depth_m[7] == pytest.approx(3.0)


# --- tracking -------------------------------------------------------------------------------------


def test_tracks_follow_a_known_image_motion_under_persistent_ids() -> None:
    rng = np.random.default_rng(1)
    scene = textured_image(rng)
    tracker = KeypointTracker(KeypointSettings(max_corners=80, min_distance=8))
    ids0, pixels0 = tracker.track(scene)
    assert len(ids0) > 30 and len(np.unique(ids0)) == len(ids0)
    ids1, pixels1 = tracker.track(shifted(scene, 2.5, -1.5))
    common, at0, at1 = np.intersect1d(ids0, ids1, return_indices=True)
    assert len(common) > 0.8 * len(ids0)
    motion = pixels1[at1] - pixels0[at0]
    np.testing.assert_allclose(np.median(motion, axis=0), [2.5, -1.5], atol=0.05)
    assert np.percentile(np.linalg.norm(motion - [2.5, -1.5], axis=1), 90) < 0.2
    # New corners (replenishing the ones lost at the border) get fresh ids, never a reused one.
    assert np.all(np.setdiff1d(ids1, ids0) > ids0.max())


def test_forward_backward_check_drops_tracks_that_cannot_be_followed() -> None:
    scene, unrelated = textured_image(np.random.default_rng(2)), textured_image(np.random.default_rng(99))

    def survivors(forward_backward_px: float) -> int:
        tracker = KeypointTracker(KeypointSettings(max_corners=80, min_distance=8, forward_backward_px=forward_backward_px))
        ids0, _ = tracker.track(scene)
        ids1, _ = tracker.track(unrelated)
        assert len(ids1) > 30  # replenished from the new image
        return len(np.intersect1d(ids0, ids1))

    checked, unchecked = survivors(1.0), survivors(100.0)
    assert checked < 0.25 * 80 and checked < 0.5 * unchecked


def test_front_end_is_deterministic_and_drops_tracks_without_valid_depth() -> None:
    rng = np.random.default_rng(3)
    scene = textured_image(rng)
    depth = np.full(scene.shape, 1.5, dtype=np.float32)
    depth[:, :60] = 0.0  # the left part has no depth measurement
    rgb = np.repeat(scene[:, :, None], 3, axis=2)

    def observe_twice() -> list:
        front_end = KeypointFrontEnd(KeypointSettings(max_corners=60, min_distance=8))
        first = front_end.observe(0, rgb, depth, INTRINSICS)
        second = front_end.observe(1, np.repeat(shifted(scene, 1.0, 0.0)[:, :, None], 3, axis=2), depth, INTRINSICS)
        return [first, second]

    a, b = observe_twice(), observe_twice()
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.points, y.points)
        np.testing.assert_array_equal(x.ids, y.ids)
    first = a[0]
    assert first.frame_id == "camera" and len(first) > 10
    u = INTRINSICS.fx * first.points[:, 0] / first.points[:, 2] + INTRINSICS.cx
    assert np.all(u >= 60 + 2 - 0.5)  # every point's depth window is fully measured
    np.testing.assert_allclose(first.points[:, 2], 1.5)


# --- import --------------------------------------------------------------------------------------


def _synthetic_frames(count: int) -> list[RgbdFrame]:
    """A camera sliding sideways in front of a textured wall 2 m away, with exact poses."""
    rng = np.random.default_rng(4)
    wall = textured_image(rng, 240, 320)
    frames = []
    for k in range(count):
        du = 2.0 * k  # pixels; the camera moves +x, so the wall moves -u
        view = shifted(wall, -du, 0.0)[60:180, 80:240]
        x = du * 2.0 / INTRINSICS.fx
        pose = Pose(k * 10**8, (x, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
        depth = np.full(view.shape, 2.0, dtype=np.float32)
        frames.append(RgbdFrame(k * 10**8, depth, INTRINSICS, np.repeat(view[:, :, None], 3, axis=2), pose))
    return frames


def test_keypoint_log_holds_tracked_points_that_stay_put_in_the_world(tmp_path: Path) -> None:
    frames = _synthetic_frames(6)
    frames[3] = RgbdFrame(frames[3].stamp_ns, frames[3].depth, INTRINSICS, None, frames[3].pose)  # no colour
    path = tmp_path / "points.mcap"
    counts = write_keypoint_log(frames, path, settings=KeypointSettings(max_corners=60, min_distance=8))
    assert (counts.frames, counts.observations, counts.ground_truth_pose, counts.frames_without_colour) == (6, 5, 6, 1)
    records = list(LogReader(path).records(["points", "ground_truth_pose"]))
    poses = {r.stamp_ns: r.value for r in records if r.role == "ground_truth_pose"}
    world: dict[int, list[np.ndarray]] = {}
    for record in (r for r in records if r.role == "points"):
        observation = record.value
        assert observation.frame_id == "camera"
        T = poses[record.stamp_ns].as_matrix()
        for track, point in zip(observation.ids, observation.points @ T[:3, :3].T + T[:3, 3], strict=True):
            world.setdefault(int(track), []).append(point)
    long_tracks = [np.array(p) for p in world.values() if len(p) >= 4]
    assert len(long_tracks) > 10
    spread = max(float(np.abs(p - p.mean(axis=0)).max()) for p in long_tracks)
    assert spread < 0.01  # m: a static point keeps its world position along its track
    assert counts.tracks == len(world)


def test_import_log_needs_points_and_colour(tmp_path: Path, runner: CliRunner) -> None:
    result = runner.invoke(cli, ["import", "log", str(tmp_path / "any.mcap"), "-o", str(tmp_path / "out.mcap")])
    assert result.exit_code == 2 and "--points" in result.output
    result = runner.invoke(
        cli, ["import", "7scenes", str(tmp_path), "-o", str(tmp_path / "o.mcap"), "--param", "max_corners=5"]
    )
    assert result.exit_code == 2 and "needs --points" in result.output


def test_real_7scenes_points_agree_with_the_reference_poses(tmp_path: Path, runner: CliRunner) -> None:
    folder = shared_data("7scenes-redkitchen-0000-0399")
    rgbd, points, from_log = tmp_path / "rgbd.mcap", tmp_path / "points.mcap", tmp_path / "from_log.mcap"
    base = ["import", "7scenes", str(folder), "--count", "30"]
    assert runner.invoke(cli, [*base, "-o", str(points), "--points"]).exit_code == 0
    assert runner.invoke(cli, [*base, "-o", str(rgbd)]).exit_code == 0
    result = runner.invoke(cli, ["import", "log", str(rgbd), "-o", str(from_log), "--points"])
    assert result.exit_code == 0, result.output
    # The same frames give the same points whether read from the folder or from an RGB-D log.
    a = [r.value for r in LogReader(points).records(["points"])]
    b = [r.value for r in LogReader(from_log).records(["points"])]
    assert len(a) == len(b) == 30
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x.points, y.points, atol=1e-6)
        np.testing.assert_array_equal(x.ids, y.ids)

    records = list(LogReader(points).records(["points", "ground_truth_pose"]))
    poses = {r.stamp_ns: r.value.as_matrix() for r in records if r.role == "ground_truth_pose"}
    world: dict[int, list[np.ndarray]] = {}
    counts = []
    for record in (r for r in records if r.role == "points"):
        T = poses[record.stamp_ns]
        counts.append(len(record.value))
        assert np.all((record.value.points[:, 2] > 0.3) & (record.value.points[:, 2] < 5.0))
        for track, point in zip(record.value.ids, record.value.points @ T[:3, :3].T + T[:3, 3], strict=True):
            world.setdefault(int(track), []).append(point)
    assert min(counts) > 100
    residuals = np.concatenate([
        np.linalg.norm(np.array(p) - np.median(p, axis=0), axis=1) for p in world.values() if len(p) >= 10
    ])  # fmt: skip
    assert np.median(residuals) < 0.04  # m: real Kinect depth at about 2 m, reference poses from KinectFusion


# --- observation noise from the data ------------------------------------------------------------


def _scene_observations(rng: np.random.Generator, sigma: float, scale: float = 1.0, frames: int = 8,
                        repeat_noise: bool = False, walk: bool = False) -> list:  # fmt: skip
    """Static points seen by a moving sensor with per-axis noise ``sigma``; ``repeat_noise``: every frame
    has the same noise (a fully correlated error that registration cannot see); ``walk``: the noise
    drifts by a random walk, ``sigma`` over the whole sequence (little from one frame to the next)."""
    from scipy.spatial.transform import Rotation

    from relpoint.types import PointObservation

    world = rng.uniform(-1, 1, (150, 3)) * scale + [0, 0, 2 * scale]
    fixed = rng.normal(0, sigma, world.shape)
    observations = []
    for k in range(frames):
        R = Rotation.from_rotvec([0.0, 0.01 * k, 0.0]).as_matrix()
        t = np.array([0.01 * k, 0.0, 0.0]) * scale
        if walk:
            fixed = fixed + rng.normal(0, sigma / np.sqrt(frames), world.shape)
        noise = fixed if repeat_noise or walk else rng.normal(0, sigma, world.shape)
        observations.append(PointObservation(k * 10**8, (world - t) @ R + noise, np.arange(len(world))))
    return observations


def test_registration_residuals_recover_independent_noise_at_any_scale() -> None:
    from relpoint.estimators._noise import estimate_observation_noise, registration_noise

    for scale, sigma in ((1.0, 0.02), (30.0, 0.6)):
        observations = _scene_observations(np.random.default_rng(5), sigma, scale)
        assert registration_noise(observations) == pytest.approx(sigma, rel=0.15)
        assert estimate_observation_noise(observations) == pytest.approx(sigma, rel=0.15)


def test_noise_that_repeats_from_frame_to_frame_is_floored_relative_to_range() -> None:
    from relpoint.estimators._noise import RANGE_FRACTION, estimate_observation_noise, registration_noise

    observations = _scene_observations(np.random.default_rng(6), 0.02, repeat_noise=True)
    assert registration_noise(observations) < 0.002
    ranges = np.concatenate([np.linalg.norm(o.points, axis=1) for o in observations])
    assert estimate_observation_noise(observations) == pytest.approx(RANGE_FRACTION * np.median(ranges))


def test_noise_that_drifts_slowly_shows_over_the_wider_baseline() -> None:
    from relpoint.estimators._noise import registration_noise

    observations = _scene_observations(np.random.default_rng(8), 0.04, frames=16, walk=True)
    consecutive, wide = registration_noise(observations, baseline=1), registration_noise(observations)
    # A random walk of 16 steps of 0.01 m per axis: two observations k steps apart differ by 0.01 sqrt(k)
    # per axis, which the estimator reads as two independent errors of 0.01 sqrt(k / 2).
    assert consecutive == pytest.approx(0.01 / np.sqrt(2), rel=0.2)
    assert wide == pytest.approx(0.01 * np.sqrt(8 / 2), rel=0.2)


@pytest.mark.parametrize("name", ["relpoint", "ekf"])
def test_estimated_noise_run_equals_a_run_given_that_noise(name: str, small_log: Path) -> None:
    import dataclasses

    from relpoint.estimators import ESTIMATORS
    from relpoint.pipeline import run

    inputs = [r.value for r in LogReader(small_log).records(["points"])][:60]
    spec = ESTIMATORS[name]
    auto = run(inputs, spec.factory(spec.config_class(), np.random.default_rng(0)))
    sigma = auto.summary["observation_sigma"]
    assert auto.summary["observation_sigma_estimated"] and 0.2 < sigma < 0.4  # the simulator's 0.3 m
    given = run(inputs, spec.factory(dataclasses.replace(spec.config_class(), observation_sigma=sigma),
                                     np.random.default_rng(0)))  # fmt: skip
    # The same run, to the last bits that BLAS may round differently with the arrays' memory alignment.
    np.testing.assert_allclose(auto.trajectory.positions, given.trajectory.positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(auto.trajectory.quats_xyzw, given.trajectory.quats_xyzw, rtol=0, atol=1e-12)
    assert len(auto.landmarks) == len(given.landmarks)


def test_rigid_motion_check_finds_the_points_that_do_not_move_with_the_rest() -> None:
    from scipy.spatial.transform import Rotation

    from relpoint.frontend.keypoints import rigid_outliers

    rng = np.random.default_rng(7)
    previous = rng.uniform(-1, 1, (40, 3)) + np.array([0.0, 0.0, 2.0])
    R = Rotation.from_rotvec([0.02, -0.03, 0.01]).as_matrix()
    current = (previous - [0.05, 0.0, 0.02]) @ R + rng.normal(0, 0.002, previous.shape)  # the camera moved
    current[[3, 17, 30]] += [0.0, 0.08, 0.0]  # three corners slid 8 cm
    tolerance = 0.01 * current[:, 2] + 0.005
    outliers = rigid_outliers(previous, current, tolerance, 100, np.random.default_rng(0))
    assert np.flatnonzero(outliers).tolist() == [3, 17, 30]
    assert not rigid_outliers(previous[:5], current[:5], tolerance[:5], 100, np.random.default_rng(0)).any()


def test_a_track_that_strays_slowly_is_ended_though_each_frame_passes() -> None:
    # The camera moves; corner 5's point slides 1.2 cm a frame (0.6 % of its 2 m depth, under the
    # 1 % + 5 mm each frame-to-frame check allows) and is ended once it has strayed over 2 % + 5 mm
    # from its track's mean; every other track, with 2 mm noise, lives on under its id.
    from scipy.spatial.transform import Rotation

    from relpoint.frontend.keypoints import KeypointFrontEnd
    from relpoint.frontend.tracking import KeypointSettings

    rng = np.random.default_rng(3)
    world = rng.uniform(-1, 1, (40, 3)) + np.array([0.0, 0.0, 2.0])
    front = KeypointFrontEnd(KeypointSettings())
    ids = np.arange(40)
    alive = []
    for frame in range(12):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec([0.0, 0.01 * frame, 0.0]).as_matrix()
        T[:3, 3] = [0.02 * frame, 0.0, 0.0]
        seen = world.copy()
        seen[5] += [0.012 * frame, 0.0, 0.0]
        points = ((seen - T[:3, 3]) @ T[:3, :3] + rng.normal(0, 0.002, seen.shape))[ids]  # camera frame
        keep = front._moves_with_the_rest(ids, points) if front._previous is not None else np.ones(len(ids), bool)
        front._previous = (ids[keep], points[keep])
        ids = ids[keep]
        alive.append(set(ids.tolist()))
    assert 5 not in alive[-1] and 5 in alive[2]
    assert alive[-1] == set(range(40)) - {5}
    assert front.strayed_tracks == 1 and front.ended_tracks == 0
