"""The Relative Point estimator end to end on short simulated runs (Kraut, section II)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from relpoint.errors import UsageError
from relpoint.estimators.base import POINTS, Estimator
from relpoint.estimators.relative_point import SPEC, RelativePointConfig, RelativePointEstimator
from relpoint.simulation import Simulation, SimulationConfig, simulate
from relpoint.types import PointObservation, Pose, Trajectory

NOISE = 0.3


def run(
    config: SimulationConfig,
    estimator_config: RelativePointConfig | None = None,
    *,
    hide: tuple[int, int, int] | None = None,
    drop_ids: bool = False,
) -> tuple[Simulation, RelativePointEstimator, list[Pose]]:
    """Run the estimator over a simulation; ``hide=(landmark, first, stop)`` removes one landmark."""
    simulation = simulate(config)
    estimator = RelativePointEstimator(estimator_config)
    poses = []
    for step in simulation.steps():
        observation = step.observation
        assert observation.ids is not None
        if hide is not None and hide[1] <= step.index < hide[2]:
            keep = observation.ids != hide[0]
            observation = PointObservation(observation.stamp_ns, observation.points[keep], observation.ids[keep])
        if drop_ids:
            observation = PointObservation(observation.stamp_ns, observation.points, None)
        poses.append(estimator.step(observation))
    return simulation, estimator, poses


def in_world(simulation: Simulation, positions: np.ndarray) -> np.ndarray:
    """Estimates live in the first sensor frame: map them to world through the true first pose."""
    T0 = simulation.ground_truth.matrices()[0]
    return positions @ T0[:3, :3].T + T0[:3, 3]


def static_landmark_errors(simulation: Simulation, estimator: RelativePointEstimator) -> np.ndarray:
    landmarks = estimator.landmark_map()
    known = landmarks.gt_id >= 0
    static = known & ~landmarks.dynamic & ~simulation.landmarks.dynamic[np.where(known, landmarks.gt_id, 0)]
    estimated = in_world(simulation, landmarks.positions[static])
    return np.linalg.norm(estimated - simulation.landmarks.positions[landmarks.gt_id[static]], axis=1)


def trajectory_errors(simulation: Simulation, poses: list[Pose]) -> np.ndarray:
    estimated = in_world(simulation, np.array([p.position for p in poses]))
    return np.linalg.norm(estimated - simulation.ground_truth.positions, axis=1)


@pytest.fixture(scope="module")
def figure8_run() -> tuple[Simulation, RelativePointEstimator, list[Pose]]:
    return run(SimulationConfig(scenario="figure8", density=25, noise=NOISE, iterations=150, seed=4))


def test_spec_and_interface() -> None:
    assert SPEC.name == "relpoint" and SPEC.needs == frozenset({POINTS})
    assert SPEC.config_class is RelativePointConfig
    estimator = SPEC.factory(RelativePointConfig(), np.random.default_rng(0))
    assert isinstance(estimator, Estimator) and estimator.name == "relpoint"
    assert len(estimator.landmark_map()) == 0 and estimator.map_size == 0


def test_first_pose_is_identity_and_stamps_pass_through(figure8_run) -> None:
    simulation, _, poses = figure8_run
    assert poses[0].position == (0.0, 0.0, 0.0)
    assert np.allclose(poses[0].quat_xyzw, (0.0, 0.0, 0.0, 1.0))
    assert [p.stamp_ns for p in poses] == simulation.stamps_ns.tolist()


def test_short_run_error_is_bounded_by_the_noise(figure8_run) -> None:
    simulation, estimator, poses = figure8_run
    errors = static_landmark_errors(simulation, estimator)
    # A single observation is off by NOISE * sqrt(3) ~ 0.52 m; the relative maps average at least
    # five of them (creation delay) and groups add up along 180 m of path, each fit adding
    # ~NOISE / sqrt(anchors): the map must stay within 4 NOISE (measured ~0.5 m).
    assert len(errors) >= 60
    assert np.sqrt(np.mean(errors**2)) < 4 * NOISE
    assert np.sqrt(np.mean(trajectory_errors(simulation, poses) ** 2)) < 4 * NOISE
    summary = estimator.summary()
    assert summary["degenerate_iterations"] == 0 and summary["iterations"] == 150


def test_stationary_map_converges_below_the_noise() -> None:
    simulation, estimator, poses = run(SimulationConfig(scenario="stationary", density=25, noise=NOISE, iterations=200))
    errors = static_landmark_errors(simulation, estimator)
    # The relative map averages ~200 observations; what remains is the world frame, fixed by the
    # first observations of ~25 points (NOISE * sqrt(3) / 5 ~ 0.1 m, more at 70 m lever arms).
    assert len(errors) == 25
    assert np.sqrt(np.mean(errors**2)) < NOISE
    assert np.max(trajectory_errors(simulation, poses)) < 2 * NOISE


def test_gt_id_is_the_majority_id_and_ids_are_not_used_for_association(figure8_run) -> None:
    simulation, estimator, poses = figure8_run
    landmarks = estimator.landmark_map()
    assert len(np.unique(landmarks.gt_id)) >= 0.95 * len(landmarks)  # few duplicates
    purity = estimator.landmark_purity()
    assert purity.shape == (len(landmarks),) and np.mean(purity) > 0.98
    assert landmarks.observations.sum() <= sum(len(s.observation) for s in simulation.steps())
    _, blind, blind_poses = run(
        SimulationConfig(scenario="figure8", density=25, noise=NOISE, iterations=150, seed=4), drop_ids=True
    )
    assert [p.position for p in blind_poses] == [p.position for p in poses]
    assert np.all(blind.landmark_map().gt_id == -1)
    assert np.allclose(blind.landmark_map().positions, landmarks.positions)


def test_dynamic_points_are_flagged_and_kept_out_of_the_static_map() -> None:
    simulation, estimator, _ = run(
        SimulationConfig(scenario="stationary", density=60, noise=NOISE, iterations=200, dynamic=0.3)
    )
    landmarks = estimator.landmark_map()
    known = landmarks.gt_id >= 0
    truly = known & simulation.landmarks.dynamic[np.where(known, landmarks.gt_id, 0)]
    flagged = landmarks.dynamic
    assert np.count_nonzero(flagged & truly) / np.count_nonzero(flagged) >= 0.8  # precision
    assert np.count_nonzero(flagged & truly) / np.count_nonzero(truly) >= 0.7  # recall
    assert np.sqrt(np.mean(static_landmark_errors(simulation, estimator) ** 2)) < NOISE
    summary = estimator.summary()
    assert summary["landmarks_dynamic"] == np.count_nonzero(flagged)
    # Every flag is counted under the test that raised it.
    witnesses = [key for key in summary if key.startswith("dynamic_by_")]
    assert len(witnesses) == 7 and sum(summary[key] for key in witnesses) == summary["dynamic_flagged"] > 0


def test_points_flagged_within_the_bulk_are_left_out_not_reported_moving() -> None:
    # Static points whose noise differs from point to point (log-normal scale, as a real tracker's
    # corners differ): the factors flag many of them; only those that stand out of the bulk of the
    # points judged with them are reported dynamic, the rest are left out. What is left out of the
    # estimate is the same either way, so the static map and the poses do not change.
    simulation = simulate(SimulationConfig(scenario="stationary", density=60, noise=0.0, iterations=200, seed=2))
    rng = np.random.default_rng(2)
    scale = NOISE * np.exp(rng.normal(0.0, 0.6, len(simulation.landmarks.ids)))
    observations = []
    for step in simulation.steps():
        o = step.observation
        assert o.ids is not None
        noisy = o.points + rng.standard_normal(o.points.shape) * scale[o.ids][:, None]
        observations.append(PointObservation(o.stamp_ns, noisy, o.ids))
    maps, poses, summaries = [], [], []
    for tail in (0.0, 3.0):
        estimator = RelativePointEstimator(RelativePointConfig(dynamic_tail_sigmas=tail).at_noise(NOISE))
        poses.append([estimator.step(o).position for o in observations])
        maps.append(estimator.landmark_map())
        summaries.append(estimator.summary())
    every, bulk = maps
    assert np.mean(every.dynamic) > 0.3 and summaries[0]["landmarks_unreliable"] == 0  # measured: 0.69
    assert np.mean(bulk.dynamic) < 0.5 * np.mean(every.dynamic)  # measured: 0.15
    assert summaries[1]["landmarks_unreliable"] == summaries[0]["landmarks_dynamic"] - summaries[1]["landmarks_dynamic"]
    assert np.array_equal(poses[0], poses[1])
    assert np.array_equal(every.gt_id[~every.dynamic], bulk.gt_id[~bulk.dynamic])
    assert np.array_equal(every.positions[~every.dynamic], bulk.positions[~bulk.dynamic])


def test_duplicated_point_is_merged_back() -> None:
    # Landmark 5 vanishes for 20 iterations; without global matching it comes back as a new point,
    # which must merge into the old one once grouped at the same global position.
    config = SimulationConfig(scenario="stationary", density=25, noise=NOISE, iterations=120, seed=1)
    _, estimator, _ = run(config, RelativePointConfig(global_matching=False), hide=(5, 30, 50))
    landmarks = estimator.landmark_map()
    assert estimator.summary()["merges"] >= 1
    assert np.count_nonzero(landmarks.gt_id == 5) == 1
    assert landmarks.observations[landmarks.gt_id == 5].item() == 100


def test_false_alarm_is_reabsorbed_when_the_point_returns() -> None:
    # Landmark 5 is wrongly flagged as moving, then leaves view. A flagged point is out of the
    # global index, so on its return it registers as a new point; once that one is mapped as
    # static, the old record takes it over: one map entry, static, with every observation.
    config = SimulationConfig(scenario="stationary", density=25, noise=NOISE, iterations=120, seed=1)
    simulation = simulate(config)
    estimator = RelativePointEstimator()
    for step in simulation.steps():
        observation = step.observation
        if 30 <= step.index < 50:
            keep = observation.ids != 5
            observation = PointObservation(observation.stamp_ns, observation.points[keep], observation.ids[keep])
        estimator.step(observation)
        if step.index == 29:
            store = estimator.store
            live = store.live_ids()
            keep = live[store.pos_weight[live] > 0]
            (row,) = keep[estimator.landmark_map().gt_id == 5]
            estimator._flag_dynamic(np.array([row]), "references")
            assert estimator.landmark_map().dynamic[estimator.landmark_map().gt_id == 5].tolist() == [True]
    landmarks = estimator.landmark_map()
    assert estimator.summary()["reabsorbed"] == 1
    assert landmarks.dynamic[landmarks.gt_id == 5].tolist() == [False]
    assert landmarks.observations[landmarks.gt_id == 5].tolist() == [100]
    assert not landmarks.dynamic.any()


def test_map_does_not_grow_over_passes() -> None:
    # Revisits re-associate (global matching) and false alarms are reabsorbed, so a fourth pass of
    # the figure eight adds next to nothing to the map of the first.
    simulation = simulate(SimulationConfig(scenario="figure8", density=25, noise=NOISE, passes=4, seed=1))
    estimator = RelativePointEstimator()
    per_pass = len(simulation) // 4
    sizes = []
    for step in simulation.steps():
        estimator.step(step.observation)
        if (step.index + 1) % per_pass == 0:
            sizes.append(estimator.map_size)
    assert sizes[-1] <= sizes[0] + 3, sizes
    landmarks = estimator.landmark_map()
    static_ids = landmarks.gt_id[(landmarks.gt_id >= 0) & ~landmarks.dynamic]
    assert len(np.unique(static_ids)) >= len(static_ids) - 2  # no duplicated landmarks


def test_returning_point_is_matched_globally() -> None:
    config = SimulationConfig(scenario="stationary", density=25, noise=NOISE, iterations=120, seed=1)
    _, estimator, _ = run(config, hide=(5, 30, 50))
    landmarks = estimator.landmark_map()
    assert estimator.summary()["global_matches"] >= 1 and estimator.summary()["merges"] == 0
    assert landmarks.observations[landmarks.gt_id == 5].tolist() == [100]


def test_degenerate_input_holds_the_pose_and_is_counted() -> None:
    simulation = simulate(SimulationConfig(scenario="stationary", density=25, noise=NOISE, iterations=40))
    observations = [step.observation for step in simulation.steps()]
    estimator = RelativePointEstimator()
    poses = [estimator.step(o) for o in observations[:20]]
    stamp = observations[19].stamp_ns
    line = np.outer(np.linspace(5.0, 50.0, 10), [1.0, 0.2, 0.1])
    nan_cloud = np.full((6, 3), np.nan)
    bad = [
        PointObservation(stamp + 1, np.zeros((0, 3))),
        PointObservation(stamp + 2, nan_cloud),
        PointObservation(stamp + 3, observations[19].points[:2]),
        PointObservation(stamp + 4, line),
        PointObservation(stamp + 5, np.zeros((5, 3))),
    ]
    held = [estimator.step(o) for o in bad]
    assert all(p.position == poses[-1].position and p.quat_xyzw == poses[-1].quat_xyzw for p in held)
    summary = estimator.summary()
    assert summary["degenerate_iterations"] == len(bad)
    assert summary["empty_iterations"] == 2 and summary["nonfinite_points"] == 6
    # Normal input afterwards recovers the stationary pose.
    for o in observations[25:]:
        recovered = estimator.step(PointObservation(o.stamp_ns + 10**9, o.points, o.ids))
    assert np.linalg.norm(recovered.position) < 2 * NOISE
    # A world whose points are all collinear gives no basis and no rotation: held, never placed.
    collinear = RelativePointEstimator()
    for t in range(15):
        held_line = collinear.step(PointObservation(t, line + np.random.default_rng(t).normal(0, 0.01, line.shape)))
    assert held_line.position == (0.0, 0.0, 0.0) and len(collinear.landmark_map()) == 0
    assert collinear.summary()["degenerate_iterations"] == 14
    # A log that starts empty or tiny does not crash either.
    fresh = RelativePointEstimator()
    first = fresh.step(PointObservation(0, np.zeros((0, 3))))
    assert first.position == (0.0, 0.0, 0.0)
    fresh.step(PointObservation(1, np.ones((1, 3))))
    assert fresh.summary()["degenerate_iterations"] == 2


def test_sparse_stretch_coasts_on_the_raw_point_motion() -> None:
    # Around iteration 170 of this sparse figure eight only three or four points are in view, all
    # new: no fit to mapped points exists for 16 iterations. Holding the pose leaves it behind the
    # moving sensor (~1.3 m per iteration); moving it by the raw points' own motion keeps up.
    simulation = simulate(SimulationConfig(scenario="figure8", density=17.5, noise=NOISE, iterations=240, seed=7))
    final_error = {}
    for coast in (True, False):
        estimator = RelativePointEstimator(RelativePointConfig(coast=coast))
        poses = [estimator.step(step.observation) for step in simulation.steps()]
        assert estimator.summary()["degenerate_iterations"] >= 10
        final_error[coast] = trajectory_errors(simulation, poses)[-1]
    assert final_error[True] < 8.0 < final_error[False]


def test_far_points_are_matched_with_a_bound_that_grows_with_range() -> None:
    # Four near points (10-20 m) and two far ones (65-70 m) seen twice by a still sensor. The
    # near points' noise looks like a 2 degree turn, and the motion from before predicted the same
    # turn: the far points are predicted 2.3-2.5 m off, beyond the 2 m bound of the first round.
    near = np.array([[10.0, 3, 1], [12, -4, 0], [15, 6, -2], [20, -2, 3]])
    far = np.array([[65.0, 5, 2], [70, -8, -1]])
    turn = Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    first = PointObservation(0, np.concatenate([near, far]))
    second = PointObservation(1, np.concatenate([near @ turn.T, far]))
    new_points = {}
    for angle in (0.03, 0.0):
        estimator = RelativePointEstimator(RelativePointConfig(match_angle=angle))
        estimator.step(first)
        estimator.motion.T_curr_prev[:3, :3] = turn
        estimator.step(second)
        new_points[angle] = estimator.summary()["new_points"]
        if angle:
            assert estimator.summary()["far_matches"] == 2
    assert new_points == {0.03: 6, 0.0: 8}


def test_loop_is_closed_beyond_the_global_matching_bound() -> None:
    # With 30 % of the landmarks moving, this figure eight has drifted about 4.5 m when it crosses
    # its start (iteration ~470), beyond the 3 m global matching bound. The young points in view
    # agree on the offset onto the old map; the drift is taken out along the loop.
    config = SimulationConfig(scenario="figure8", density=25, noise=NOISE, iterations=900, dynamic=0.3, seed=3)
    rmse = {}
    for search in (15.0, 0.0):
        simulation, estimator, _ = run(config, RelativePointConfig(loop_search=search))
        rmse[search] = float(np.sqrt(np.mean(static_landmark_errors(simulation, estimator) ** 2)))
        assert (estimator.summary()["loop_closures"] >= 1) == (search > 0)
    assert rmse[15.0] < 0.6 * rmse[0.0], rmse


def test_a_dense_map_closes_no_false_loop() -> None:
    # At ~230 points per iteration each young point has dozens of old neighbours within the search
    # radius. Counting only the agreeing points (at least four), this run closed 8 false loops and
    # ended 13 m off; the vote must see that chance explains such agreement.
    simulation, estimator, poses = run(SimulationConfig(scenario="figure8", density=300, noise=NOISE, iterations=600))
    assert estimator.summary()["loop_closures"] == 0
    assert trajectory_errors(simulation, poses).max() < 1.0


def test_final_adjustment_lowers_map_and_trajectory_error() -> None:
    # Seed 0 with 30 % moving points: groups placed early, some against moving points flagged
    # later, leave the incremental map 1.07 m off; solved jointly it is 0.59 m off, and the poses
    # located again on it follow (1.40 m to 0.69 m). (Over seeds 0-3 the map goes from 1.97 to
    # 1.19 m on average and the trajectory from 2.15 to 1.27 m; seed 2 gains least, 1.05 to 1.04 m.)
    config = SimulationConfig(scenario="figure8", density=25, noise=NOISE, iterations=900, dynamic=0.3, seed=0)
    simulation, estimator, poses = run(config)
    trajectory = Trajectory.from_poses(poses)
    rmse_before = np.sqrt(np.mean(static_landmark_errors(simulation, estimator) ** 2))
    unreliable_before = estimator.summary()["landmarks_unreliable"]
    before = estimator.landmark_map()
    flagged_before = set(before.gt_id[before.dynamic].tolist())
    adjusted = estimator.finish(trajectory)
    rmse_after = np.sqrt(np.mean(static_landmark_errors(simulation, estimator) ** 2))
    assert rmse_after < 0.75 * rmse_before, (rmse_before, rmse_after)
    truth = simulation.ground_truth.positions
    assert np.sqrt(np.mean(np.sum((adjusted.positions - truth) ** 2, axis=1))) < 0.85 * np.sqrt(
        np.mean(np.sum((trajectory.positions - truth) ** 2, axis=1))
    )
    assert np.array_equal(adjusted.stamps_ns, trajectory.stamps_ns)
    assert np.allclose(adjusted.positions[0], 0.0) and np.allclose(adjusted.quats_xyzw[0], (0, 0, 0, 1))
    report = estimator.summary()["final_adjustment"]
    assert report["cost_after"] < report["cost_before"]
    # Moving points the detection missed stand out once the groups sit where the whole network puts
    # them: flagged here, reported dynamic where they stand out of the bulk and left out otherwise,
    # and the ones reported are moving (measured: 12 flagged, 5 of them reported, all moving).
    # The bundle adjustment after it may flag more (drifting residuals) and release some (none).
    landmarks = estimator.landmark_map()
    newly = landmarks.dynamic & ~np.isin(landmarks.gt_id, list(flagged_before))
    after = estimator.summary()
    bundle = report["bundle"]
    assert report["dynamic_flagged"] >= 8
    assert (after["landmarks_dynamic"] + after["landmarks_unreliable"]) - (
        np.count_nonzero(before.dynamic) + unreliable_before
    ) == report["dynamic_flagged"] + bundle["dynamic_flagged"] - bundle["dynamic_released"]
    assert np.count_nonzero(newly) >= 3
    assert np.mean(simulation.landmarks.dynamic[landmarks.gt_id[newly]]) >= 0.9
    assert report["relocated_iterations"] >= 0.97 * len(poses)
    # Off, the paper's incremental solution is returned as it is.
    _, plain, plain_poses = run(
        SimulationConfig(scenario="figure8", density=25, noise=NOISE, iterations=60),
        RelativePointConfig(final_adjustment=False),
    )
    plain_trajectory = Trajectory.from_poses(plain_poses)
    assert plain.finish(plain_trajectory) is plain_trajectory and "final_adjustment" not in plain.summary()


def test_bundle_adjustment_solves_the_observations_and_flags_the_movers_whose_residuals_drift() -> None:
    # Random-walk movers (20 %, 0.2 m an iteration) on the figure eight, seed 0: the bundle adjustment
    # solves every iteration from its own observations, finds the movers kept as static points by
    # their drifting residuals (measured: 3, all moving), and the trajectory follows (ATE 0.750 m
    # without it, 0.543 m with it).
    config = SimulationConfig(iterations=200, noise=NOISE, dynamic=0.2, mover_motion="random-walk", mover_speed=0.2)
    results = {}
    for bundle in (False, True):
        simulation, estimator, poses = run(config, RelativePointConfig(bundle_adjustment=bundle))
        trajectory = Trajectory.from_poses(poses)
        final = estimator.finish(trajectory)
        error = np.sqrt(np.mean(np.sum((final.positions - simulation.ground_truth.positions) ** 2, axis=1)))
        landmarks = estimator.landmark_map()
        results[bundle] = (error, set(landmarks.gt_id[landmarks.dynamic].tolist()), estimator.summary())
    (error_without, flagged_without, _), (error_with, flagged_with, summary) = results[False], results[True]
    report = summary["final_adjustment"]
    assert report["kept"] == "adjusted" and "bundle" not in results[False][2]["final_adjustment"]
    assert report["bundle"]["iterations_solved"] == config.iterations
    assert report["bundle"]["cost_after"] < report["bundle"]["cost_before"]
    newly = flagged_with - flagged_without
    assert len(newly) == report["bundle"]["dynamic_flagged"] == summary["dynamic_by_bundle"] >= 2
    assert simulation.landmarks.dynamic[list(newly)].all()
    assert error_with < 0.85 * error_without, (error_without, error_with)


def test_bundle_adjustment_leaves_dense_views_to_the_network_adjustment() -> None:
    # About 540 points in view: far above 32 static observations a keyframe, so the bundle adjustment is
    # not run and says why; the network adjustment's trajectory is what comes back.
    config = SimulationConfig(iterations=40, noise=NOISE, density=695.0)
    results = {}
    for bundle in (True, False):
        _, estimator, poses = run(config, RelativePointConfig(bundle_adjustment=bundle))
        trajectory = Trajectory.from_poses(poses)
        results[bundle] = (estimator.finish(trajectory), estimator.summary()["final_adjustment"], estimator)
    (with_bundle, report, estimator), (without_bundle, _, _) = results[True], results[False]
    assert report["bundle"]["skipped"].startswith("dense views:")
    kept = [len(uids) for uids, _ in estimator._observations.values()]
    assert len(kept) == config.iterations and max(kept) == 128  # every keyframe, at most 128 observations each
    np.testing.assert_array_equal(with_bundle.positions, without_bundle.positions)


def test_memory_is_bounded_by_the_map_not_the_iterations() -> None:
    simulation = simulate(SimulationConfig(scenario="stationary", density=25, noise=NOISE, iterations=400, clutter=2.0))
    estimator = RelativePointEstimator(RelativePointConfig(ring_size=32, regroup_after=32, dynamic_window=32))
    sizes = []
    for step in simulation.steps():
        estimator.step(step.observation)
        if step.index in (149, 399):
            sizes.append((estimator.store.capacity, len(estimator.groups), estimator.store.count))
    (capacity_a, groups_a, points_a), (capacity_b, groups_b, points_b) = sizes
    assert estimator.store.obs.shape[1] == 32
    assert capacity_b == capacity_a  # clutter points are dropped and their rows reused
    assert groups_b <= groups_a + 5 and points_b <= points_a + 10


def test_config_is_validated() -> None:
    with pytest.raises(UsageError):
        RelativePointConfig(match_bound=-1.0)
    with pytest.raises(UsageError):
        RelativePointConfig(seed_points=2)
    with pytest.raises(UsageError):
        RelativePointConfig(regroup_after=500)
    for bad in (
        {"relocate_points": 2},
        {"adjustment_members": 1},
        {"final_adjustment": "yes"},
        {"adjustment_prior": -1.0},
    ):
        with pytest.raises(UsageError):
            RelativePointConfig(**bad)
    with pytest.raises(UsageError):
        RelativePointConfig.from_mapping({"match-bound": 2.0, "no_such_setting": 1})
    config = RelativePointConfig.from_mapping({"match-bound": 2.5})
    assert config.match_bound == 2.5 and RelativePointConfig(**config.to_dict()) == config


def test_residual_trend_is_calibrated_on_static_points_and_finds_wandering_ones() -> None:
    from relpoint.estimators.relative_point.adjustment import residual_trend

    rng = np.random.default_rng(0)
    points, seen = 400, 40
    point = np.repeat(np.arange(points), seen)
    static = rng.normal(0.0, 0.3, (points * seen, 3))
    probability = residual_trend(point, static, points)
    # White noise of any level: the F distribution holds (measured 4.0 % below 0.05, none below 1e-3).
    assert 0.02 < np.mean(probability < 0.05) < 0.08 and np.mean(probability < 1e-3) < 0.005
    # A random walk of a third of the noise per observation trends over its 40 observations.
    walk = np.cumsum(rng.normal(0.0, 0.1, (points, seen, 3)), axis=1).reshape(-1, 3) + static
    assert np.mean(residual_trend(point, walk, points) < 1e-3) > 0.5
    # Fewer than six observations are not judged.
    assert residual_trend(np.zeros(5, np.int64), rng.normal(size=(5, 3)), 1)[0] == 1.0


def test_dropped_frames_and_jittered_stamps_are_followed() -> None:
    # The motion between iterations is rescaled to each iteration's interval: a dropped frame (the
    # sensor moved twice as far) is predicted from the velocity, and stamps that jitter around evenly
    # spaced frames fall back to the step as it was. Measured: with 30 % of the frames dropped at
    # random, 1.21 m against 0.92 m with all of them (39.8 m, 51 degenerate iterations, when the
    # motion was a step per iteration).
    simulation = simulate(SimulationConfig(scenario="figure8", density=25, noise=NOISE, iterations=300, seed=3))
    rng = np.random.default_rng(0)

    def rms(keep: float, jitter_s: float) -> tuple[float, int]:
        estimator = RelativePointEstimator()
        errors = []
        for step in simulation.steps():
            if step.index and rng.random() > keep:
                continue
            observation = step.observation
            if step.index:
                shift = int(rng.uniform(-jitter_s, jitter_s) * 1e9)
                observation = PointObservation(observation.stamp_ns + shift, observation.points, observation.ids)
            position = in_world(simulation, np.array([estimator.step(observation).position]))[0]
            errors.append(np.linalg.norm(position - simulation.ground_truth.positions[step.index]))
        return float(np.sqrt(np.mean(np.square(errors)))), estimator.counts["degenerate_iterations"]

    every, _ = rms(1.0, 0.0)
    dropped, degenerate = rms(0.7, 0.0)
    jittered, _ = rms(1.0, 0.045)
    assert dropped < 1.5 * every and degenerate == 0
    assert jittered < 1.1 * every


def test_iterations_without_points_are_placed_between_their_neighbours() -> None:
    # An empty cloud holds the pose during the run; at the end it is interpolated in time.
    from relpoint import pipeline

    simulation = simulate(SimulationConfig(scenario="figure8", density=25, noise=NOISE, iterations=120, seed=2))
    empty = {k for k in range(5, 120, 9)}
    observations = [
        PointObservation(s.observation.stamp_ns, s.observation.points[:0], s.observation.ids[:0])
        if s.index in empty else s.observation
        for s in simulation.steps()
    ]  # fmt: skip
    result = pipeline.run(iter(observations), RelativePointEstimator())
    estimated = in_world(simulation, result.trajectory.positions)
    errors = np.linalg.norm(estimated - simulation.ground_truth.positions, axis=1)
    rows = sorted(empty)
    assert result.summary["unobserved_interpolated"] == len(rows)
    neighbours = np.concatenate([errors[[k - 1 for k in rows]], errors[[k + 1 for k in rows]]])
    assert errors[rows].max() < 2.0 * neighbours.max() + NOISE
