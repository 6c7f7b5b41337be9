"""The estimator registry: built-in specs load on demand, their declared inputs match, and the
commands that only look at a log start without the estimators' heavy dependencies."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from relpoint.estimators import BUILTIN, ESTIMATORS, EstimatorRegistry, EstimatorSpec

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_builtin_declarations_match_each_spec(name: str) -> None:
    spec = ESTIMATORS[name]
    assert isinstance(spec, EstimatorSpec) and spec.name == name
    assert ESTIMATORS.inputs(name) == (spec.needs, spec.uses)
    assert ESTIMATORS.config_class(name) is spec.config_class


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_every_estimator_is_built_as_config_and_rng_and_declares_its_input_kind(name: str) -> None:
    import numpy as np

    from relpoint.estimators._noise import NoiseAdaptive
    from relpoint.estimators.base import Estimator

    spec = ESTIMATORS[name]
    assert spec.needs == {spec.input_kind} and spec.input_kind in ("points", "depth")
    config = spec.config_class()
    direct = spec.estimator_class(config, np.random.default_rng(0))
    assert isinstance(direct, Estimator) and direct.name == name
    assert direct.dense_map() is None or spec.input_kind == "depth"
    built = spec.factory(config, np.random.default_rng(0))
    # an estimator whose noise is unset waits for it; one given the noise is built at once
    assert isinstance(built, NoiseAdaptive) == (spec.noise_adaptive and config.observation_sigma is None)
    if spec.noise_adaptive:
        given = config.at_noise(0.05)
        if getattr(given, "derives_acceleration", False):  # a motion model's, measured alike
            given = dataclasses.replace(given, linear_acceleration_noise=1.0, angular_acceleration_noise=0.5)
        if getattr(given, "odometry_check", False):  # the odometry's check holds the first observations back
            assert isinstance(spec.factory(given, np.random.default_rng(0)), NoiseAdaptive)
            given = dataclasses.replace(given, odometry_check=False)
        fitted = spec.factory(given, np.random.default_rng(0))
        assert isinstance(fitted, spec.estimator_class) and fitted.config.observation_sigma == 0.05


@pytest.mark.parametrize("name", sorted(BUILTIN))
def test_builtin_declares_the_kernels_its_estimator_uses(name: str) -> None:
    """The batch warm-up loads the declared kernel modules in place of the estimators' own."""
    import importlib
    import types

    from relpoint._aot_kernels import KernelSet

    module = importlib.import_module(BUILTIN[name].module)
    used = {
        value.__name__ for value in vars(module).values()
        if isinstance(value, types.ModuleType) and isinstance(getattr(value, "kernels", None), KernelSet)
    }  # fmt: skip
    assert used == ({BUILTIN[name].kernels} if BUILTIN[name].kernels else set())


def test_registry_lists_builtins_and_registered_specs_and_refuses_unknown_names() -> None:
    registry = EstimatorRegistry()
    assert list(registry) == list(BUILTIN) and len(registry) == len(BUILTIN)
    extra = EstimatorSpec("extra", "a test estimator", dict, lambda config, rng: None)
    registry.register(extra)
    assert "extra" in registry and registry["extra"] is extra and list(registry)[-1] == "extra"
    assert registry.inputs("extra") == (frozenset({"points"}), frozenset())
    assert registry.config_class("extra") is dict
    with pytest.raises(KeyError):
        registry["nope"]
    with pytest.raises(KeyError):
        registry.inputs("nope")
    with pytest.raises(KeyError):
        registry.config_class("nope")
    assert "nope" not in registry


def in_a_fresh_interpreter(code: str) -> None:
    """Run ``code`` in a new Python process from the repository (its imports are its own); it must pass."""
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]


def test_info_imports_no_estimator_scipy_or_numba() -> None:
    # What `relpoint info` imports to describe a log: the registry answers from its declarations.
    code = (
        "import sys; sys.argv = ['relpoint', 'info', 'sample_logs/figure8.mcap', '--json']\n"
        "from relpoint_cli.main import main\n"
        "try:\n    main()\nexcept SystemExit as stop:\n    assert not stop.code, stop.code\n"
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('scipy', 'numba', 'open3d', 'cv2')"
        " or m.startswith('relpoint.estimators.') and m.split('.')[2] not in ('base', '_noise', 'spec'))\n"
        "assert not heavy, heavy\n"
    )
    in_a_fresh_interpreter(code)


def test_batch_checks_a_plan_without_scipy_or_the_estimators(tmp_path: Path) -> None:
    # `relpoint batch` reads and checks its plan while the workers warm up: the point estimators'
    # settings come from their own modules, which import no scipy.
    plan = tmp_path / "plan.toml"
    plan.write_text(
        f'logs = ["{REPO / "sample_logs" / "figure8.mcap"}"]\n'
        "[estimators.relpoint]\n[estimators.ekf.grid]\nobservation_sigma = [0.3, 0.5]\n"
        "[estimators.fastslam]\nparticles = 7\n"
    )
    code = (
        "import sys\nfrom pathlib import Path\nfrom relpoint_app.batch_plan import check_outputs, load_plan\n"
        f"plan = load_plan(Path({str(plan)!r}), results=Path({str(tmp_path / 'results')!r}))\n"
        "check_outputs(plan)\nassert len(plan.jobs) == 4, plan.jobs\n"
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('scipy', 'numba', 'open3d', 'cv2')"
        " or m in ('relpoint.estimators.ekf', 'relpoint.estimators.fastslam',"
        " 'relpoint.estimators.relative_point.estimator'))\n"
        "assert not heavy, heavy\n"
    )
    in_a_fresh_interpreter(code)
