"""Shared fixtures: small simulated logs made once per session, and a CLI runner."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner
from threadpoolctl import threadpool_limits

from relpoint.simulation import SimulationConfig, simulate
from relpoint_app.simulation import write_simulation

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session", autouse=True)
def single_blas_thread() -> object:
    """One BLAS thread: the small matrices here gain nothing from more, and spinning workers steal the CPU."""
    with threadpool_limits(limits=1):
        yield


@pytest.fixture(scope="session")
def small_config() -> SimulationConfig:
    return SimulationConfig(iterations=120, density=25, noise=0.3, odometry_noise=0.05, fix_every=10, seed=3)


@pytest.fixture(scope="session")
def small_log(tmp_path_factory: pytest.TempPathFactory, small_config: SimulationConfig) -> Path:
    path = tmp_path_factory.mktemp("logs") / "small.mcap"
    write_simulation(simulate(small_config), path)
    return path


@pytest.fixture()
def runner() -> CliRunner:
    return CliRunner()


def shared_data(*parts: str) -> Path:
    """A path under ../shared/data; skips the test when the shared data is not beside the checkout."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data {path.name} is not available")
    return path


def run_accuracy(errors: list[float], landmarks: object, truth_positions: object) -> dict[str, float]:
    """Position and landmark error figures of a short simulated run (landmarks matched by ``gt_id``)."""
    import numpy as np

    known = landmarks.gt_id >= 0
    residual = landmarks.positions[known] - truth_positions[landmarks.gt_id[known]]
    return {
        "position_rmse": float(np.sqrt(np.mean(np.square(errors)))),
        "final_error": float(errors[-1]),
        "landmark_rmse": float(np.sqrt(np.mean(np.sum(residual**2, axis=1)))),
        "landmarks": len(landmarks),
        "distinct": len(set(landmarks.gt_id.tolist())),
    }


def default_interrupts() -> None:
    """``preexec_fn`` of a child that a test interrupts: SIGINT at its default, whatever the test runner
    inherited (a shell starts background jobs with SIGINT ignored, and children keep ignored signals)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def sharp_turn(estimator: object, *, speed: float, turn_rate: float, steps: int, far_x: float, landmarks: int) -> float:
    """Drive ``estimator`` along a straight leg at ``speed`` (m/s), then a turn at ``turn_rate`` (rad/s)
    from one observation to the next (after step 30; 10 Hz, 0.1 m noise, 15 m range, ``landmarks``
    uniform in x -20..``far_x``, y -25..25, z -3..3 m); returns its final position error (m)."""
    import numpy as np

    from relpoint.geometry import twist_step
    from relpoint.types import PointObservation

    rng = np.random.default_rng(0)
    scene = rng.uniform([-20.0, -25.0, -3.0], [far_x, 25.0, 3.0], size=(landmarks, 3))
    position, rotation = np.zeros(3), np.eye(3)
    for i in range(steps):
        if i:
            turn = np.array([0.0, 0.0, turn_rate if i > 30 else 0.0])
            position, rotation, _, _ = twist_step(position, rotation, np.array([speed, 0.0, 0.0]), turn, 0.1)
        local = (scene - position) @ rotation
        seen = local[np.linalg.norm(local, axis=1) < 15.0]
        estimator.step(PointObservation(i * 100_000_000, seen + rng.normal(0.0, 0.1, seen.shape)))  # type: ignore[attr-defined]
    return float(np.linalg.norm(np.array(estimator.pose().position) - position))  # type: ignore[attr-defined]
