"""Depth noise measured from the frames (dense estimator): the fit, and the thresholds it widens."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from relpoint.estimators.dense import DenseConfig, DenseFusion
from relpoint.estimators.dense.noise import fit_noise, second_differences
from relpoint.evaluation import EvaluationSettings, evaluate_trajectory
from relpoint.simulation.rgbd import RgbdConfig, RgbdSimulation, simulate_rgbd
from relpoint.types import Trajectory


def _slanted_depth(width: int = 320, height: int = 240) -> np.ndarray:
    """Depth (H, W) metres of a smooth surface from 0.7 m (top row) to 4 m (bottom row)."""
    rows = np.linspace(0.7, 4.0, height, dtype=np.float32)[:, None]
    cols = np.linspace(-0.1, 0.1, width, dtype=np.float32)[None, :]
    return rows + cols * rows


@pytest.mark.parametrize(("constant", "quadratic"), [(0.002, 0.006), (0.0, 0.0085), (0.004, 0.0)])
def test_the_noise_fit_recovers_a_known_sigma_of_depth(constant: float, quadratic: float) -> None:
    rng = np.random.default_rng(3)
    clean = _slanted_depth()
    sigma = constant + quadratic * clean**2
    noisy = (clean + rng.standard_normal(clean.shape).astype(np.float32) * sigma).astype(np.float32)
    noisy[rng.random(noisy.shape) < 0.1] = 0  # missing pixels are left out, not taken for depth 0
    model = fit_noise(*second_differences(noisy))
    assert model is not None
    assert model.near < 1.0 and model.far > 3.5
    for z in (1.0, 2.0, 3.5):
        true = constant + quadratic * z * z
        assert model.sigma(z) == pytest.approx(true, rel=0.1), z
    # The noise-free surface measures (next to) nothing: the figures above are the noise's.
    clean_model = fit_noise(*second_differences(clean))
    assert clean_model is not None and clean_model.sigma(2.0) < 1e-4


def test_too_few_samples_give_no_model() -> None:
    depth = np.zeros((40, 40), dtype=np.float32)
    depth[10:14, 10:14] = 1.0
    assert fit_noise(*second_differences(depth)) is None


def _noisy(sim: RgbdSimulation, quadratic: float, seed: int) -> list:
    """The simulation's noise-free frames with independent noise ``quadratic z^2`` metres added (a stereo
    camera's, growing with depth squared)."""
    rng = np.random.default_rng(seed)
    frames = []
    for frame in sim.frames():
        depth = frame.depth
        noise = rng.standard_normal(depth.shape).astype(np.float32) * np.float32(quadratic) * depth * depth
        frames.append(dataclasses.replace(frame, depth=np.where(depth > 0, depth + noise, 0).astype(np.float32)))
    return frames


def _ate(sim: RgbdSimulation, estimator: DenseFusion, frames: list) -> float:
    poses = [estimator.step(frame) for frame in frames]
    result = evaluate_trajectory(
        sim.ground_truth, Trajectory.from_poses(poses), EvaluationSettings(align="se3", rpe=False, kitti=False)
    )
    return float(result.summary["ate_rmse"])


def test_noisy_depth_widens_the_thresholds_is_tracked_better_and_warned_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # Stereo-like noise, 3.4 cm at 2 m: the 3 % edge threshold rejected most neighbours (the depth stayed
    # unsmoothed) and the fusion gate most matches, silently (12 frames: ATE 0.71 cm with the fixed
    # thresholds, 0.23 cm widened to the noise measured).
    sim = simulate_rgbd(RgbdConfig(frames=12, noise=False, seed=2))
    frames = _noisy(sim, 0.0085, seed=1)
    fixed = DenseFusion(DenseConfig(noise_model=False))
    ate_fixed = _ate(sim, fixed, frames)
    assert not fixed.run_warnings() and fixed.summary()["depth_noise"]["pixel"] is None
    caplog.clear()
    measured = DenseFusion(DenseConfig())
    with caplog.at_level("WARNING"):
        ate_measured = _ate(sim, measured, frames)
    assert ate_measured < 0.7 * ate_fixed
    noise = measured.summary()["depth_noise"]
    assert noise["pixel"]["sigma_at_2m_m"] == pytest.approx(0.0085 * 4, rel=0.15)
    assert noise["residual"] is not None and noise["widened"]
    warned = [r.getMessage() for r in caplog.records if "depth noise measured" in r.getMessage()]
    assert len(warned) == 1 and f"{noise['pixel']['sigma_at_2m_m'] * 100:.2g} cm from pixel to pixel" in warned[0]
    assert any("depth noise measured" in warning for warning in measured.run_warnings())


def test_kinect_like_noise_changes_nothing() -> None:
    # The simulator's Kinect v1 noise (axial noise, disparity steps, missing pixels): the settings made for
    # it stay, and the path is the same to the bit as without the measurement.
    sim = simulate_rgbd(RgbdConfig(frames=12, seed=2))
    frames = list(sim.frames())
    measured = DenseFusion(DenseConfig())
    poses = [measured.step(frame).as_matrix() for frame in frames]
    fixed = DenseFusion(DenseConfig(noise_model=False))
    assert np.array_equal(poses, [fixed.step(frame).as_matrix() for frame in frames])
    noise = measured.summary()["depth_noise"]
    assert noise["pixel"] is not None and noise["residual"] is not None
    assert noise["widened"] == [] and not measured.run_warnings()
