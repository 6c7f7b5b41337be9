"""The drift rate FastSLAM measures on its fixes, and the move of its poses to the final frame draw."""

from __future__ import annotations

import numpy as np
import pytest

from relpoint.estimators._drift_rate import MIN_FIXES, RATES, DriftRate
from relpoint.estimators._fix_frame import drawn_frame_transform, moved_to_final_frame
from relpoint.types import Trajectory


def _measured(rate: float, fix_sigma: float, step: float, steps_per_fix: int, fixes: int, seed: int) -> DriftRate:
    """A path whose place in world walks ``rate`` m per m travelled, and fixes of ``fix_sigma`` (m): the
    corrections the fixes measure of it, fed to a DriftRate that starts at the prior 0.1."""
    rng = np.random.default_rng(seed)
    measured = DriftRate(prior=0.1)
    error = np.zeros(3)
    for _ in range(fixes):
        for _ in range(steps_per_fix):
            error += rng.normal(0.0, rate * step, 3)
            measured.travel(step)
        fix_error = rng.normal(0.0, fix_sigma, 3)
        measured.fix(fix_error - error, np.full(3, fix_sigma**2))  # fix minus path, both against the truth
    return measured


@pytest.mark.parametrize("rate", [0.003, 0.03, 0.3])
@pytest.mark.parametrize("fix_sigma", [0.2, 1.0])
def test_the_measured_rate_finds_the_walk_of_the_filter(rate: float, fix_sigma: float) -> None:
    # 60 fixes, one per 15 m: a rate whose walk stays below the fixes' noise between two fixes cannot
    # be told from a slower one, so it is only bounded; a faster one is found within a factor of 2.
    found = [_measured(rate, fix_sigma, 1.5, 10, 60, seed).rate for seed in range(5)]
    walk = rate * 1.5 * np.sqrt(10)  # m per axis between two fixes
    if walk < 0.5 * fix_sigma:
        assert np.median(found) <= 2.0 * max(rate, 0.5 * fix_sigma / (1.5 * np.sqrt(10)))
    else:
        assert rate / 2.0 <= np.median(found) <= 2.0 * rate


def test_the_prior_holds_until_enough_fixes() -> None:
    measured = DriftRate(prior=0.1)
    for _ in range(MIN_FIXES - 1):
        measured.travel(10.0)
        measured.fix(np.zeros(3), np.ones(3))
        assert measured.rate == 0.1
    measured.travel(10.0)
    measured.fix(np.zeros(3), np.ones(3))
    assert measured.rate == RATES[0]  # fixes that agree exactly: the slowest walk
    assert measured.summary() == {"drift_rate": round(float(RATES[0]), 6), "drift_rate_fixes": MIN_FIXES}


def test_poses_output_under_each_draw_are_moved_to_the_final_one() -> None:
    rng = np.random.default_rng(3)
    centre = np.array([5.0, -2.0, 1.0])
    K = 30
    truth = np.tile(np.eye(4), (K, 1, 1))
    truth[:, :3, 3] = rng.normal(0.0, 10.0, (K, 3))
    draws = np.vstack([np.zeros((10, 6)), rng.normal(0.0, [0.3, 0.3, 0.3, 0.05, 0.05, 0.05], (K - 10, 6))])
    output = np.stack([drawn_frame_transform(centre, draw) @ pose for draw, pose in zip(draws, truth, strict=True)])
    stamps = np.arange(K, dtype=np.int64) * 100_000_000
    final = rng.normal(0.0, [0.3, 0.3, 0.3, 0.05, 0.05, 0.05])
    moved = moved_to_final_frame(Trajectory.from_matrices(stamps, output), stamps, draws, final, centre)
    expected = drawn_frame_transform(centre, final) @ truth
    assert np.allclose(moved.matrices(), expected, atol=1e-9)
    # a draw maps the centre by its translation alone
    assert np.allclose(drawn_frame_transform(centre, final)[:3] @ np.append(centre, 1.0), centre + final[:3])
