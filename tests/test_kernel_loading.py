"""How Relative Point's compiled kernels are loaded, and compile time kept out of the iterations."""

from __future__ import annotations

import importlib.util
import inspect
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from relpoint import pipeline
from relpoint.estimators.base import Estimator
from relpoint.estimators.relative_point import _kernels
from relpoint.types import LandmarkMap, PointObservation, Pose, Trajectory


def _jit_kernels(monkeypatch: pytest.MonkeyPatch, cache: Path) -> ModuleType:
    """A second copy of ``_kernels`` whose kernels are numba dispatchers (``RELPOINT_KERNELS=jit``).

    Its machine code is cached in ``cache``: cached code names the module it was compiled in, and
    the package's own cache must not receive this copy's.
    """
    from numba.core import config

    monkeypatch.setattr(config, "CACHE_DIR", str(cache))
    monkeypatch.setenv("RELPOINT_KERNELS", "jit")
    spec = importlib.util.spec_from_file_location("relpoint_kernels_jit_copy", _kernels.__file__)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)
    spec.loader.exec_module(module)
    return module


def test_every_kernel_declares_its_argument_types() -> None:
    source = inspect.getsource(_kernels)
    declared = set(_kernels.SIGNATURES)
    defined = {line.split("(")[0].removeprefix("def ") for line in source.splitlines() if line.startswith("def ")}
    helpers = {"source_digest", "_ahead_of_time", "kernel", "_checked", "prepare"}
    assert declared == defined - helpers
    assert len(declared) == 52


def test_the_prebuilt_module_is_refused_when_unwanted_or_built_from_another_source(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("RELPOINT_KERNELS", "jit")
    assert _kernels._ahead_of_time() is None
    monkeypatch.setenv("RELPOINT_KERNELS", "auto")
    monkeypatch.setattr(_kernels, "source_digest", lambda: -1)  # as if this file had been edited since the build
    assert _kernels._ahead_of_time() is None


@pytest.mark.skipif(not _kernels.COMPILED_AHEAD, reason="the kernels were not compiled ahead of time at install")
def test_prebuilt_kernels_equal_the_jit_ones_bit_for_bit(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    jit = _jit_kernels(monkeypatch, tmp_path)
    assert not jit.COMPILED_AHEAD
    rng = np.random.default_rng(3)
    for _ in range(20):
        n = int(rng.integers(4, 60))
        source = rng.normal(size=(n, 3))
        angle = rng.uniform(-np.pi, np.pi)
        rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        target = source @ rotation.T + rng.normal(size=3) + rng.normal(scale=0.05, size=(n, 3))
        weights = rng.uniform(0.5, 2.0, n)
        use = rng.random(n) < 0.9
        use[:3] = True
        for name, arguments in (
            ("rigid_fit", (source, target, weights, use)),
            ("trimmed_fit", (source, target, weights, np.eye(4), use, 3.0, 0.01, 4, 0.05)),
            ("nearest_two", (target, np.argsort(target[:, 0]), source, 1.5)),
        ):
            prebuilt, compiled = getattr(_kernels, name)(*arguments), getattr(jit, name)(*arguments)
            for a, b in zip(prebuilt, compiled, strict=True):
                assert np.asarray(a).tobytes() == np.asarray(b).tobytes(), name


@pytest.mark.skipif(not _kernels.COMPILED_AHEAD, reason="the kernels were not compiled ahead of time at install")
def test_prebuilt_kernels_refuse_arrays_they_would_misread() -> None:
    sums, weights, ids = np.arange(30.0).reshape(10, 3), np.ones(10), np.array([0, 4, 9])
    np.testing.assert_array_equal(_kernels.gather_positions(sums, weights, ids), sums[ids])
    for bad in (
        (np.asfortranarray(sums), weights, ids),
        (sums[::2], weights[::2], ids[:2]),
        (sums.astype(np.float32), weights, ids),
        (sums, weights, ids.astype(np.int32)),
        (sums, weights, [0, 4, 9]),
    ):
        with pytest.raises(TypeError, match="gather_positions: argument"):
            _kernels.gather_positions(*bad)


class _Recording(Estimator):
    """Records the order of prepare and step calls."""

    name = "recording"

    def __init__(self) -> None:
        self.calls: list[str] = []

    def prepare(self) -> None:
        self.calls.append("prepare")

    def step(self, observation: PointObservation) -> Pose:
        self.calls.append("step")
        return Pose(observation.stamp_ns, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))

    def landmark_map(self) -> LandmarkMap:
        return LandmarkMap(np.zeros((1, 3)), np.ones(1, dtype=np.int64), np.zeros(1, dtype=bool), np.zeros(1, dtype=np.int64))

    def finish(self, trajectory: Trajectory) -> Trajectory:
        return trajectory

    @property
    def map_size(self) -> int:
        return 1

    def summary(self) -> dict[str, int]:
        return {}


def test_the_run_prepares_once_before_the_first_iteration_and_reports_it_apart() -> None:
    rng = np.random.default_rng(0)
    estimator = _Recording()
    result = pipeline.run(iter([PointObservation(k * 10**8, rng.normal(size=(10, 3))) for k in range(1, 6)]), estimator)
    assert estimator.calls == ["prepare"] + ["step"] * 5
    timing = result.timing_summary()
    assert timing["iterations"] == 5 == len(result.seconds)
    assert timing["seconds_prepare"] == result.seconds_prepare >= 0.0


def test_the_default_relative_point_prepares_its_kernels_before_it_knows_the_noise(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from relpoint.estimators import ESTIMATORS
    from relpoint.estimators.relative_point import _kernels as kernels

    calls: list[str] = []
    monkeypatch.setattr(kernels, "prepare", lambda: calls.append("prepare"))
    spec = ESTIMATORS["relpoint"]
    estimator = spec.factory(spec.config_class(), np.random.default_rng(0))  # observation noise: estimated
    estimator.prepare()
    assert calls == ["prepare"]
