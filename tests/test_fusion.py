"""Fusion of local SLAM with position fixes (General Concept of 3D SLAM, sections 5-6, Algorithm 3)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from click.testing import CliRunner

from formats.run_output import write_run_directory
from formats.tables import read_map_csv
from formats.trajectory_files import read_tum
from relpoint.errors import EstimatorError, UsageError
from relpoint.estimators.base import Estimator
from relpoint.evaluation import EvaluationSettings, evaluate_trajectory
from relpoint.fusion import (
    FusionConfig,
    PathSpline,
    fit_segment,
    fuse,
    fuse_estimates,
    interpolate_fixes,
    lagrange_weights,
    matched_counts_from_map_growth,
    segment_run,
)
from relpoint.fusion.segmented import run_segmented
from relpoint.fusion.synthetic import SyntheticRun, synthetic_local_slam
from relpoint.pipeline import RunResult
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import LandmarkMap, PointObservation, Pose, PositionFix, Trajectory
from relpoint_app.simulation import write_simulation
from relpoint_cli.main import cli

# ----------------------------------------------------------------------------------- eq. 26-30


def test_lagrange_reproduces_a_quadratic_exactly() -> None:
    rng = np.random.default_rng(0)
    fix_stamps = np.cumsum(rng.integers(300_000_000, 1_500_000_000, 12))  # uneven fix intervals
    coefficients = rng.normal(size=(3, 3))  # per axis: a + b t + c t^2

    def quadratic(stamps_ns: np.ndarray) -> np.ndarray:
        t = stamps_ns * 1e-9
        return coefficients[0] + np.outer(t, coefficients[1]) + np.outer(t**2, coefficients[2])

    queries = np.sort(rng.integers(fix_stamps[0], fix_stamps[-1], 200))
    queries = np.concatenate([queries, fix_stamps])
    covariances = np.repeat(np.eye(3)[None], len(fix_stamps), axis=0)
    positions, _ = interpolate_fixes(fix_stamps, quadratic(fix_stamps), covariances, queries)
    np.testing.assert_allclose(positions, quadratic(queries), atol=1e-9)


def test_lagrange_weights_are_the_corrected_basis() -> None:
    nodes = np.array([0.0, 1.0, 3.0])
    t = 2.0
    xi = lagrange_weights(t, nodes)
    # eq. 27, 28 and eq. 29 with the correct denominator (t_k - t_{k-2})(t_k - t_{k-1}).
    expected = [
        (t - 1.0) * (t - 3.0) / ((0.0 - 1.0) * (0.0 - 3.0)),
        (t - 0.0) * (t - 3.0) / ((1.0 - 0.0) * (1.0 - 3.0)),
        (t - 0.0) * (t - 1.0) / ((3.0 - 0.0) * (3.0 - 1.0)),
    ]
    np.testing.assert_allclose(xi, expected)
    assert xi.sum() == pytest.approx(1.0)


def test_two_fixes_interpolate_linearly_and_covariance_follows_eq_30() -> None:
    stamps = np.array([0, 2_000_000_000])
    positions = np.array([[0.0, 0.0, 0.0], [2.0, 4.0, -2.0]])
    covariances = np.stack([np.eye(3) * 1.0, np.eye(3) * 4.0])
    x, P = interpolate_fixes(stamps, positions, covariances, [500_000_000])
    np.testing.assert_allclose(x[0], [0.5, 1.0, -0.5])
    np.testing.assert_allclose(P[0], np.eye(3) * (0.75**2 * 1.0 + 0.25**2 * 4.0))
    with pytest.raises(EstimatorError, match="no position fix"):
        interpolate_fixes(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)), [0])


# ----------------------------------------------------------------------------------- eq. 31-32


def test_fused_variance_is_below_both_inputs() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        A, B = rng.normal(size=(2, 3, 3))
        P_c = A @ A.T + 0.05 * np.eye(3)
        P_b = B @ B.T + 0.05 * np.eye(3)
        x_v, P_v = fuse_estimates(rng.normal(size=3), P_c, rng.normal(size=3), P_b)
        np.testing.assert_allclose(P_v, P_v.T, atol=1e-12)
        # Loewner order: P_c - P_v and P_b - P_v are positive semi-definite.
        assert np.linalg.eigvalsh(P_c - P_v).min() > -1e-10
        assert np.linalg.eigvalsh(P_b - P_v).min() > -1e-10
        assert np.all(np.diag(P_v) < np.minimum(np.diag(P_c), np.diag(P_b)))
    # The scalar form as printed (eq. 31-32).
    x_v, P_v = fuse_estimates([1.0, 0, 0], np.eye(3) * 4.0, [3.0, 0, 0], np.eye(3) * 1.0)
    assert x_v[0] == pytest.approx(1.0 / 5.0 * 1.0 + 4.0 / 5.0 * 3.0)
    assert P_v[0, 0] == pytest.approx(4.0 * 1.0 / 5.0)


# ----------------------------------------------------------------------------------- eq. 33-37


def _helix(stamps_ns: np.ndarray) -> np.ndarray:
    t = stamps_ns * 1e-9
    return np.stack([10 * np.cos(0.3 * t), 10 * np.sin(0.3 * t), 0.5 * t], axis=1)


def test_bspline_passes_the_endpoints_and_is_c2() -> None:
    rng = np.random.default_rng(2)
    stamps = np.cumsum(rng.integers(80_000_000, 120_000_000, 40))
    positions = _helix(stamps) + rng.normal(0.0, 0.05, (40, 3))
    spline = PathSpline.fit(stamps, positions, np.repeat(np.eye(3)[None] * 0.01, 40, axis=0))
    np.testing.assert_allclose(spline(stamps[[0, -1]]), positions[[0, -1]], atol=1e-9)
    np.testing.assert_allclose(spline(stamps), positions, atol=1e-9)  # an interpolating spline
    knots = np.unique(spline.spline.t)[1:-1]
    eps = 1e-9
    for order in (0, 1, 2):
        derivative = spline.spline.derivative(order) if order else spline.spline
        left, right = derivative(knots - eps), derivative(knots + eps)
        scale = np.abs(derivative(np.linspace(0, 1, 200))).max()
        np.testing.assert_allclose(left, right, atol=1e-5 * scale)
    # The third derivative jumps: the curve is C2, not smoother (a real cubic spline).
    third = spline.spline.derivative(3)
    assert np.abs(third(knots - eps) - third(knots + eps)).max() > 1e-3


def test_bspline_covariance_is_the_intended_eq_37() -> None:
    stamps = np.arange(12) * 100_000_000
    covariances = np.array([np.eye(3) * (0.1 + 0.05 * i) for i in range(12)])
    spline = PathSpline.fit(stamps, _helix(stamps), covariances)
    # At a position's own time only that position contributes (weights are the cardinal functions).
    np.testing.assert_allclose(spline.covariance(stamps), covariances, atol=1e-9)
    # Between them: sum_i L_i(u)^2 P_vv(i) with weights summing to one; inside the path, where the
    # not-a-knot ends do not reach, that averages below the larger neighbouring variance.
    mid = stamps[:-1] + 50_000_000
    weights = spline.cardinal_weights(mid)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(spline.covariance(mid), np.einsum("ni,iab->nab", weights**2, covariances))
    inner = slice(3, -3)
    bound = np.maximum(covariances[:-1, 0, 0], covariances[1:, 0, 0])[inner]
    assert np.all(spline.covariance(mid)[inner, 0, 0] < bound)
    with pytest.raises(EstimatorError, match="at least 4 positions"):
        PathSpline.fit(stamps[:3], _helix(stamps[:3]))


# ----------------------------------------------------------------------------------- sections 6.2-6.4


def _fixes_for(stamps: np.ndarray, world_positions: np.ndarray, sigma: float, rng: np.random.Generator) -> list:
    return [
        PositionFix(int(s), p + rng.normal(0.0, sigma, 3), np.eye(3) * sigma**2)
        for s, p in zip(stamps, world_positions, strict=True)
    ]


def test_a_segment_with_collinear_fixes_is_refused_with_a_clear_error() -> None:
    rng = np.random.default_rng(3)
    stamps = np.arange(50) * 100_000_000
    line = np.stack([np.arange(50) * 1.2, np.zeros(50), np.zeros(50)], axis=1)  # a straight run
    spline = PathSpline.fit(stamps, line)
    fixes = _fixes_for(stamps[::10], line[::10] + np.array([5.0, 2.0, 0.0]), 0.5, rng)
    args = ([f.stamp_ns for f in fixes], [f.position for f in fixes], [f.covariance for f in fixes])
    with pytest.raises(EstimatorError, match=r"segment 7: its 5 fix pairs lie within .* of a straight line"):
        fit_segment(spline, *args, name="segment 7")
    with pytest.raises(EstimatorError, match="has 2 position fix"):
        fit_segment(spline, *(a[:2] for a in args), name="segment 7")

    # Through fuse(): a straight segment and a curved one; the straight one is left out, the other placed.
    curve_stamps = stamps[-1] + 100_000_000 + np.arange(80) * 100_000_000
    curve = _helix(curve_stamps)
    trajectory = Trajectory(
        np.concatenate([stamps, curve_stamps]),
        np.concatenate([line, curve]),
        np.tile([0.0, 0.0, 0.0, 1.0], (130, 1)),
    )
    matched = np.full(130, 20)
    matched[50] = 0  # the break between the two local maps
    all_fixes = fixes + _fixes_for(curve_stamps[::8], curve[::8], 0.5, rng)
    result = fuse(trajectory, LandmarkMap.empty(), matched, all_fixes)
    assert [s.transform is None for s in result.segments] == [True, False]
    assert "straight line" in (result.segments[0].refused or "")
    assert result.summary["segments_left_out"] == 1
    assert not result.fused[:50].any() and result.fused[51:].all()


def test_segmentation_follows_matches_and_drift() -> None:
    matched = np.array([0, 9, 9, 9, 9, 2, 0, 0, 7, 8, 8, 8, 8, 1, 9])
    labels = segment_run(matched, min_matches=5, min_length=4)
    np.testing.assert_array_equal(labels, [0, 0, 0, 0, 0, -1, -1, 1, 1, 1, 1, 1, 1, -1, -1])
    # The modelled error (0.1 m + 1 % of 1.2 m steps) passes 0.2 m after about nine steps: new local maps.
    positions = np.stack([np.arange(40) * 1.2, np.zeros(40), np.zeros(40)], axis=1)
    labels = segment_run(np.full(40, 20), positions=positions, max_position_error=0.2)
    assert labels.max() >= 3 and np.all(np.bincount(labels[labels >= 0]) <= 10)
    # Counts from timing.csv columns: points that did not start a landmark.
    np.testing.assert_array_equal(
        matched_counts_from_map_growth([10, 12, 8, 0, 5], [10, 14, 14, 14, 19]), [0, 8, 8, 0, 0]
    )
    with pytest.raises(UsageError):
        FusionConfig(min_pairs=2)


# ----------------------------------------------------------------------------------- a simulated run


@pytest.fixture(scope="module")
def gaps_run() -> tuple[object, SyntheticRun]:
    config = SimulationConfig(scenario="figure8-gaps", density=20, fix_every=10, fix_noise=1.0, seed=5)
    simulation = simulate(config)
    return simulation, synthetic_local_slam(simulation, np.random.default_rng(5))


def _ate(reference: Trajectory, estimate: Trajectory) -> float:
    settings = EvaluationSettings(align="none", rpe=False, kitti=False)
    return evaluate_trajectory(reference, estimate, settings).summary["ate_rmse"]


def _part(trajectory: Trajectory, rows: np.ndarray) -> Trajectory:
    return Trajectory(trajectory.stamps_ns[rows], trajectory.positions[rows], trajectory.quats_xyzw[rows])


def test_simulated_run_fused_global_error_beats_each_part(gaps_run) -> None:  # type: ignore[no-untyped-def]
    simulation, run = gaps_run
    truth = simulation.ground_truth
    result = fuse(run.trajectory, run.landmarks, run.matched, run.fixes, landmark_iterations=run.landmark_iterations)
    assert result.summary["segments"] >= 3 and result.summary["segments_left_out"] == 0
    fixes_alone = Trajectory(truth.stamps_ns, result.fix_positions, truth.quats_xyzw)

    fused_ate = _ate(truth, result.trajectory)
    fixes_ate = _ate(truth, fixes_alone)
    assert fused_ate < 0.75 * fixes_ate
    for segment in result.segments:
        rows = segment.iterations
        fused_part = _ate(_part(truth, rows), _part(result.trajectory, rows))
        assert fused_part < _ate(_part(truth, rows), segment.local_trajectory)  # the segment alone
        assert fused_part < _ate(_part(truth, rows), _part(fixes_alone, rows))  # the fixes alone
        assert fused_part < 1.2  # the fixes are 1 m per axis (1.7 m in 3D)

    # Landmarks: the integrated global map against the truth, versus the local maps as they were.
    gt_positions = simulation.landmarks.positions
    global_error = np.linalg.norm(result.landmarks.positions - gt_positions[result.landmarks.gt_id], axis=1)
    local_error = np.linalg.norm(run.landmarks.positions - gt_positions[run.landmarks.gt_id], axis=1)
    assert len(result.landmarks) == len(run.landmarks)
    assert np.sqrt(np.mean(global_error**2)) < 1.5 < np.sqrt(np.mean(local_error**2))


def test_fuse_command_writes_a_run_directory_with_segments(gaps_run, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    simulation, run = gaps_run
    log = tmp_path / "gaps.mcap"
    write_simulation(simulation, log)
    # A run directory as `relpoint run` writes it; timing.csv carries observed and map_size.
    owners = run.landmark_iterations
    map_size = np.searchsorted(owners, np.arange(len(run.trajectory)), side="right")
    observed = run.matched + np.diff(map_size, prepend=0)
    n = len(run.trajectory)
    write_run_directory(
        tmp_path / "local",
        RunResult(run.trajectory, run.landmarks, observed, map_size, np.zeros(n)),
        {"estimator": "x"},
    )
    result = CliRunner().invoke(
        cli, ["-q", "fuse", str(tmp_path / "local"), "--log", str(log), "-o", str(tmp_path / "g")]
    )
    assert result.exit_code == 0, result.output
    out = tmp_path / "g"
    for name in ("trajectory.tum", "trajectory.csv", "map.ply", "map.csv", "timing.csv", "run.json", "result.mcap"):
        assert (out / name).is_file(), name
    info = json.loads((out / "run.json").read_text())
    placed = [s for s in info["segments"] if s["placed"]]
    assert len(placed) == info["summary"]["segments_placed"] >= 3
    for s in placed:
        segment_path = read_tum(out / "segments" / f"segment-{s['segment']}.tum")
        assert len(segment_path) == s["iterations"]
        assert len(read_map_csv(out / "segments" / f"segment-{s['segment']}-map.csv")) == s["landmarks"]
    global_path = read_tum(out / "trajectory.tum")
    assert _ate(simulation.ground_truth, global_path) < 1.2

    # A run directory without its files is an input error (exit 3) in one line.
    (tmp_path / "empty").mkdir()
    bad = CliRunner().invoke(cli, ["fuse", str(tmp_path / "empty"), "--log", str(log), "-o", str(tmp_path / "x")])
    assert bad.exit_code == 3 and "no trajectory.tum" in bad.output


class _IdMapper(Estimator):
    """A stub local SLAM: its map is the set of ids seen, its path a fixed 1 m step along x per iteration."""

    name = "id-mapper"

    def __init__(self) -> None:
        self.ids: set[int] = set()
        self.steps = 0

    def step(self, observation: PointObservation) -> Pose:
        assert observation.ids is not None
        self.ids.update(observation.ids.tolist())
        self.steps += 1
        return Pose(observation.stamp_ns, (float(self.steps - 1), 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))

    def landmark_map(self) -> LandmarkMap:
        ids = np.array(sorted(self.ids), dtype=np.int64)
        return LandmarkMap(np.zeros((len(ids), 3)), np.ones(len(ids), np.int64), np.zeros(len(ids), bool), ids)


def _break_ids(k: int) -> np.ndarray:
    """Ids seen at iteration ``k``: 0-5 see landmarks 0-9, 6-7 nothing, 8-15 see 100-109, 16 sees 200-209."""
    if k < 6:
        return np.arange(10)
    if k < 8:
        return np.zeros(0, np.int64)
    return np.arange(100, 110) if k < 16 else np.arange(200, 210)


def _apart(ids: np.ndarray) -> np.ndarray:
    """Points (n, 3) for the stub estimators, one a metre apart per id: a cloud holding one point twice
    is screened down to one copy before any estimator sees it."""
    return np.column_stack([np.asarray(ids, dtype=np.float64), np.zeros(len(ids)), np.ones(len(ids))])


def test_run_segmented_starts_a_fresh_local_map_at_every_break() -> None:
    # Iteration 16 is a one-off: its landmarks are seen nowhere else.
    ids = _break_ids

    inputs: list[object] = []
    for k in range(17):
        if k % 4 == 0:
            inputs.append(PositionFix(k * 100_000_000, np.full(3, float(k)), np.eye(3)))
        inputs.append(PointObservation(k * 100_000_000, _apart(ids(k)), ids(k)))
    run = run_segmented(inputs, _IdMapper, min_matches=5, min_length=4)
    np.testing.assert_array_equal(run.labels, [0] * 6 + [-1] * 2 + [1] * 8 + [-1])
    # Each local map starts at the identity of its own frame.
    np.testing.assert_allclose(run.trajectory.positions[[0, 8]], 0.0)
    np.testing.assert_allclose(run.trajectory.positions[15], [7.0, 0.0, 0.0])
    np.testing.assert_array_equal(run.landmarks.gt_id, [*range(10), *range(100, 110)])
    np.testing.assert_array_equal(run.landmark_labels, [0] * 10 + [1] * 10)
    assert len(run.fixes) == 5 and run.matched[0] == 0 and run.matched[1] == 10


class _FinishingMapper(_IdMapper):
    """A stub whose ``finish`` moves every pose 0.5 m up and records how many poses it was given."""

    finished: ClassVar[list[int]] = []

    def finish(self, trajectory: Trajectory) -> Trajectory:
        assert len(trajectory) == self.steps  # every iteration it stepped, the breaking one included
        _FinishingMapper.finished.append(len(trajectory))
        return Trajectory(trajectory.stamps_ns, np.add(trajectory.positions, (0.0, 0.0, 0.5)), trajectory.quats_xyzw)


def test_run_segmented_finishes_every_local_map_it_keeps() -> None:
    # Maps of 6 and 8 iterations are kept, the 2-iteration gap and the one-off are not (:func:`_break_ids`).
    _FinishingMapper.finished = []
    inputs = [PointObservation(k * 100_000_000, _apart(_break_ids(k)), _break_ids(k)) for k in range(17)]
    run = run_segmented(inputs, _FinishingMapper, min_matches=5, min_length=4)
    np.testing.assert_array_equal(run.labels, [0] * 6 + [-1] * 2 + [1] * 8 + [-1])
    assert _FinishingMapper.finished == [7, 9]  # each map's poses and the pose of the step that broke it
    kept = run.labels >= 0
    np.testing.assert_allclose(run.trajectory.positions[kept, 2], 0.5)
    np.testing.assert_allclose(run.trajectory.positions[~kept, 2], 0.0)
    np.testing.assert_allclose(run.trajectory.positions[15], [7.0, 0.0, 0.5])


class _GroupingMapper(_IdMapper):
    """A stub like the Relative Point estimator: a feature enters the map only on its fourth sighting (in a
    burst), while it counts the features started (``features_started``) when ``counts`` is set."""

    def __init__(self, counts: bool) -> None:
        super().__init__()
        self.counts = counts
        self.sightings: dict[int, int] = {}

    def step(self, observation: PointObservation) -> Pose:
        assert observation.ids is not None
        for i in observation.ids.tolist():
            self.sightings[i] = self.sightings.get(i, 0) + 1
        return super().step(observation)

    def landmark_map(self) -> LandmarkMap:
        ids = np.array(sorted(i for i, n in self.sightings.items() if n >= 4), dtype=np.int64)
        return LandmarkMap(np.zeros((len(ids), 3)), np.ones(len(ids), np.int64), np.zeros(len(ids), bool), ids)

    @property
    def features_started(self) -> int | None:
        return len(self.sightings) if self.counts else None


def test_run_segmented_counts_matches_from_started_features_when_reported() -> None:
    # 30 iterations seeing the same 10 landmarks (5 more from iteration 10): one local map. Read from
    # map growth, the burst when features are first mapped (iteration 3: 10 of 10 points) is a break.
    def inputs() -> list[object]:
        ids = [np.arange(10) if k < 10 else np.arange(15) for k in range(30)]
        return [PointObservation(k * 100_000_000, _apart(i), i) for k, i in enumerate(ids)]

    run = run_segmented(inputs(), lambda: _GroupingMapper(counts=True), min_matches=5, min_length=4)
    np.testing.assert_array_equal(run.labels, np.zeros(30))
    assert run.matched[1] == 10 and run.matched[10] == 10  # 5 new of 15 observed at iteration 10
    np.testing.assert_array_equal(np.sort(run.landmarks.gt_id), np.arange(15))
    shattered = run_segmented(inputs(), lambda: _GroupingMapper(counts=False), min_matches=5, min_length=4)
    # Why the started-feature count is read when an estimator has it: each fresh map's burst (10 of 10
    # points) restarts it three iterations later, too short to keep, until 15 points are seen and a burst
    # of 10 leaves 5 matched (the map started at iteration 9).
    np.testing.assert_array_equal(shattered.labels, [-1] * 9 + [0] * 21)


# ----------------------------------------------------------------------------------- piecewise-rigid fit


def _arc(count: int) -> tuple[np.ndarray, np.ndarray]:
    stamps = np.arange(count) * 100_000_000
    t = stamps * 1e-9
    return stamps, np.stack([60 * np.cos(0.04 * t), 60 * np.sin(0.04 * t), 0.3 * t], axis=1)


def _bend(positions: np.ndarray, at: int, degrees: float, jump: np.ndarray) -> np.ndarray:
    """The path after iteration ``at`` turned about the position there and shifted: a re-association."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    bent = positions.copy()
    bent[at:] = (positions[at:] - positions[at]) @ R.T + positions[at] + jump
    return bent


def test_a_bent_local_map_is_placed_piecewise_and_a_rigid_one_whole() -> None:
    rng = np.random.default_rng(11)
    stamps, world = _arc(600)
    T_local_world = np.eye(4)
    angle = np.radians(35.0)
    T_local_world[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    T_local_world[:3, 3] = [-60.0, 40.0, 15.0]
    local = world @ T_local_world[:3, :3].T + T_local_world[:3, 3]
    fixes = _fixes_for(stamps[::10], world[::10], 0.7, rng)
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (600, 1))
    matched = np.full(600, 20)
    truth = Trajectory(stamps, world, quats)
    args = ([f.stamp_ns for f in fixes], [f.position for f in fixes], [f.covariance for f in fixes])
    fixes_ate = _ate(truth, Trajectory(stamps, interpolate_fixes(*args, stamps)[0], quats))

    rigid = fuse(Trajectory(stamps, local, quats), LandmarkMap.empty(), matched, fixes)
    assert rigid.summary["local_maps_split"] == 0 and len(rigid.segments) == 1

    bent_local = _bend(local, 287, 6.0, np.array([4.0, -3.0, 0.0]))
    bent = fuse(Trajectory(stamps, bent_local, quats), LandmarkMap.empty(), matched, fixes)
    whole = fuse(Trajectory(stamps, bent_local, quats), LandmarkMap.empty(), matched, fixes,
                 FusionConfig(split_significance=0.0))  # fmt: skip
    assert bent.summary["local_maps_split"] == 1 and bent.summary["segments_placed"] == 2
    assert [s.local_map for s in bent.segments] == [0, 0]
    assert bent.segments[1].iterations[0] == 287  # at the jump (286 -> 287), not halfway between fixes
    assert _ate(truth, bent.trajectory) < 0.6 * fixes_ate < _ate(truth, whole.trajectory)
    assert _ate(truth, bent.trajectory) < _ate(truth, rigid.trajectory) + 0.2  # measured 0.25 m and 0.22 m


def test_a_local_map_that_cannot_be_made_rigid_is_left_out() -> None:
    rng = np.random.default_rng(12)
    stamps, world = _arc(120)
    held = world.copy()
    held[40:] = world[40]  # the local SLAM lost its position after iteration 40 and held it
    fixes = _fixes_for(stamps[::10], world[::10], 0.7, rng)
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (120, 1))
    result = fuse(Trajectory(stamps, held, quats), LandmarkMap.empty(), np.full(120, 20), fixes)
    assert [s.transform is None for s in result.segments] == [True]  # 4 fixes before the hold: too few to cut
    assert "is not rigid against the fixes" in (result.segments[0].refused or "")
    assert not result.fused.any()
    with pytest.raises(UsageError, match="split_significance"):
        FusionConfig(split_significance=1.0)


def test_landmarks_go_to_the_iteration_the_estimator_says_they_were_first_seen() -> None:
    """A map that shrank (landmarks dropped) defeats the map-growth rule; the estimator's own first
    iterations place every landmark; without them the nearest path position is the fallback."""
    from relpoint.fusion.fuse import _landmark_iterations

    path = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])
    positions = np.array([[8.0, 5.0, 0.0], [1.0, 5.0, 0.0], [4.0, 5.0, 0.0]])
    shrank = np.array([0, 1, 2, 3, 4, 4, 3, 3, 3, 3])  # ends at 3, but not by growth alone
    first = np.array([2, 7, 5])
    with_first = LandmarkMap(positions, np.ones(3, np.int64), np.zeros(3, bool), np.full(3, -1), first_iteration=first)
    owner, rule = _landmark_iterations(with_first, path, shrank)
    assert rule == "first iteration" and owner.tolist() == [2, 7, 5]
    without = LandmarkMap(positions, np.ones(3, np.int64), np.zeros(3, bool), np.full(3, -1))
    owner, rule = _landmark_iterations(without, path, shrank)
    assert rule == "nearest" and owner.tolist() == [8, 1, 4]
    unknown = LandmarkMap(
        positions, np.ones(3, np.int64), np.zeros(3, bool), np.full(3, -1), first_iteration=[2, -1, 5]
    )
    owner, rule = _landmark_iterations(unknown, path, shrank)
    assert rule == "first iteration (nearest position where unknown)" and owner.tolist() == [2, 1, 5]


def test_horizontal_fixes_place_segments_by_yaw_and_leave_their_altitude(gaps_run) -> None:  # type: ignore[no-untyped-def]
    # The same run with fixes that measure x and y only, their altitude a placeholder 0 of ROS's
    # "unknown" variance: each segment is turned about z and moved in the plane, not tilted to z = 0.
    simulation, run = gaps_run
    truth = simulation.ground_truth
    horizontal = [
        PositionFix(f.stamp_ns, np.array([f.position[0], f.position[1], 0.0]), np.diag([1.0, 1.0, 1e9]))
        for f in run.fixes
    ]
    result = fuse(run.trajectory, run.landmarks, run.matched, horizontal, landmark_iterations=run.landmark_iterations)
    assert result.summary["segments"] >= 3 and result.summary["segments_left_out"] == 0
    for segment in result.segments:
        rows = segment.iterations
        error = result.trajectory.positions[rows, :2] - truth.positions[rows, :2]
        assert np.sqrt(np.mean(np.sum(error**2, axis=1))) < 1.2  # the fixes are 1 m per axis
        np.testing.assert_allclose(result.trajectory.positions[rows, 2], segment.local_trajectory.positions[:, 2])
