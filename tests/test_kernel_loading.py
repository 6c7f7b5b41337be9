"""How the compiled kernels (Relative Point's, FastSLAM's and the dense estimator's) are loaded, and compile time kept out of the iterations."""

from __future__ import annotations

import importlib.util
import inspect
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from relpoint import pipeline
from relpoint._aot_kernels import KernelSet
from relpoint.estimators import _fastslam_kernels
from relpoint.estimators.base import Estimator
from relpoint.estimators.dense import _kernels as _dense_kernels
from relpoint.estimators.relative_point import _kernels
from relpoint.geometry import so3_exp
from relpoint.types import LandmarkMap, PointObservation, Pose, Trajectory

KERNEL_MODULES = {"relative_point": _kernels, "fastslam": _fastslam_kernels, "dense": _dense_kernels}
"""Every kernel source, by a short name: each one's kernels are prebuilt into its own extension module."""


def _jit_copy(monkeypatch: pytest.MonkeyPatch, cache: Path, source: str | Path, name: str) -> ModuleType:
    """A second copy of the kernel source ``source`` whose kernels are numba dispatchers when
    ``RELPOINT_KERNELS=jit`` is set or the copy's digest is not the prebuilt module's.

    Its machine code is cached in ``cache``: cached code names the module it was compiled in, and
    the package's own cache must not receive this copy's.
    """
    from numba.core import config

    monkeypatch.setattr(config, "CACHE_DIR", str(cache))
    spec = importlib.util.spec_from_file_location(name, source)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)
    spec.loader.exec_module(module)
    return module


def _jit_kernels(monkeypatch: pytest.MonkeyPatch, cache: Path) -> ModuleType:
    """A copy of Relative Point's ``_kernels`` loaded with ``RELPOINT_KERNELS=jit``."""
    monkeypatch.setenv("RELPOINT_KERNELS", "jit")
    return _jit_copy(monkeypatch, cache, _kernels.__file__, "relpoint_kernels_jit_copy")


@pytest.mark.parametrize(("name", "count"), [("relative_point", 58), ("fastslam", 7), ("dense", 14)])
def test_every_kernel_declares_its_argument_types(name: str, count: int) -> None:
    module = KERNEL_MODULES[name]
    source = inspect.getsource(module)
    declared = set(module.SIGNATURES)
    defined = {line.split("(")[0].removeprefix("def ") for line in source.splitlines() if line.startswith("def ")}
    assert declared == defined
    assert len(declared) == count
    assert module.kernels.prebuilt_name == module.__name__ + "_aot"  # the extension setup.py builds for it


@pytest.mark.parametrize("name", sorted(KERNEL_MODULES))
def test_the_prebuilt_module_is_refused_when_unwanted_or_built_from_another_source(
    monkeypatch: pytest.MonkeyPatch, name: str
) -> None:
    kernels: KernelSet = KERNEL_MODULES[name].kernels
    monkeypatch.setenv("RELPOINT_KERNELS", "jit")
    assert kernels.load_prebuilt() is None
    monkeypatch.setenv("RELPOINT_KERNELS", "auto")
    monkeypatch.setattr(kernels, "source_digest", lambda: -1)  # as if the file had been edited since the build
    assert kernels.load_prebuilt() is None
    assert KernelSet(kernels.source, kernels.prebuilt_name + "_missing").load_prebuilt() is None


@pytest.mark.parametrize("name", sorted(KERNEL_MODULES))
def test_the_prebuilt_module_is_taken_when_built_from_this_source(monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    module = KERNEL_MODULES[name]
    if importlib.util.find_spec(module.__name__ + "_aot") is None:
        pytest.skip("the kernels were not compiled ahead of time at install")
    extension = importlib.import_module(module.__name__ + "_aot")
    monkeypatch.setenv("RELPOINT_KERNELS", "auto")
    assert (module.kernels.load_prebuilt() is extension) == (extension.source_digest() == module.source_digest())
    if module.COMPILED_AHEAD:  # each kernel is the prebuilt function behind its argument check
        assert all(getattr(module, kernel).__wrapped__.__name__ == kernel for kernel in module.SIGNATURES)
        assert not any(hasattr(getattr(module, kernel), "signatures") for kernel in module.SIGNATURES)
        module.prepare()  # nothing to compile


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
    # A dtype equal to the declared one but a separate object (as the kernels return) is taken too.
    tagged = np.dtype(np.float64, metadata={"unit": "m"})
    assert tagged is not sums.dtype
    np.testing.assert_array_equal(_kernels.gather_positions(sums.astype(tagged), weights, ids), sums[ids])
    for bad in (
        (np.asfortranarray(sums), weights, ids),
        (sums[::2], weights[::2], ids[:2]),
        (sums.astype(np.float32), weights, ids),
        (sums.astype(">f8"), weights, ids),
        (sums, weights, ids.astype(np.int32)),
        (sums, weights, [0, 4, 9]),
        (sums, weights.reshape(10, 1), ids),
        (sums.ravel(), weights, ids),
        (np.ma.masked_array(sums), weights, ids),
    ):
        with pytest.raises(TypeError, match="gather_positions: argument"):
            _kernels.gather_positions(*bad)


def _fastslam_case(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Random particles, landmarks and points in the shapes FastSLAM's kernels take."""
    n, m, k, sigma = 6, 30, 20, 0.3
    truth = rng.uniform(-10, 10, (m, 3))
    A = rng.normal(0, sigma, (n, m, 3, 3))
    B = rng.normal(0, 0.05, (n, 12, 12))
    seen = truth[rng.choice(m, k - 4, replace=False)]
    return {
        "points": np.concatenate([seen + rng.normal(0, sigma, seen.shape), rng.uniform(-10, 10, (4, 3))]),
        "positions": rng.normal(0, 0.3, (n, 3)),
        "rotations": so3_exp(rng.normal(0, 0.05, (n, 3))),
        "twists": rng.normal(0, 0.1, (n, 6)),
        "means": truth[None] + rng.normal(0, sigma, (n, m, 3)),
        "covs": A @ np.swapaxes(A, 2, 3) + 0.01 * np.eye(3),
        "counts": rng.integers(m // 2, m + 1, n).astype(np.int64),
        "Sigma": B @ np.swapaxes(B, 1, 2) + 1e-4 * np.eye(12),
        "Q": np.eye(3) * sigma**2,
    }


def _run_fastslam_kernels(kernels: ModuleType, case: dict[str, np.ndarray], proposal: bool) -> list[np.ndarray]:
    """Every output of one candidate search, association and landmark update, and the arrays they update."""
    c = {name: value.copy() for name, value in case.items()}
    offsets, slots = kernels.near_slots(c["points"], c["positions"], c["rotations"], c["means"], c["counts"], 2.0)
    assoc, log_likelihood, paired, discarded = kernels.associate(
        c["points"], offsets, slots, c["positions"], c["rotations"], c["twists"], c["means"], c["covs"], c["counts"],
        c["Q"], c["Sigma"], proposal, -8.0, -14.0, proposal,
    )  # fmt: skip
    seen, last = np.zeros(c["means"].shape[:2], dtype=np.int64), np.zeros(c["means"].shape[:2], dtype=np.int64)
    kernels.update_landmarks(c["points"], assoc, c["positions"], c["rotations"], c["means"], c["covs"], c["Q"], seen,
                             last, 3)  # fmt: skip
    assert (assoc >= 0).any()
    return [offsets, slots, assoc, log_likelihood, np.array([paired, discarded]), seen, last, *c.values()]


def test_an_edited_fastslam_source_falls_back_to_jit_kernels_equal_to_the_prebuilt_bit_for_bit(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    source = tmp_path / "edited_fastslam_kernels.py"
    source.write_text(Path(_fastslam_kernels.__file__).read_text() + "\n# edited after the build\n")
    monkeypatch.delenv("RELPOINT_KERNELS", raising=False)
    jit = _jit_copy(monkeypatch, tmp_path / "cache", source, "relpoint_edited_fastslam_kernels")
    assert not jit.COMPILED_AHEAD and jit.kernels.prebuilt_name == _fastslam_kernels.kernels.prebuilt_name
    jit.prepare()  # each public kernel for its declared types (and the helpers they call)
    assert [len(getattr(jit, name).signatures) for name in ("near_slots", "associate", "update_landmarks")] == [1, 1, 1]
    rng = np.random.default_rng(4)
    for _ in range(4):
        case = _fastslam_case(rng)
        for proposal in (True, False):
            prebuilt = _run_fastslam_kernels(_fastslam_kernels, case, proposal)
            compiled = _run_fastslam_kernels(jit, case, proposal)
            for k, (a, b) in enumerate(zip(prebuilt, compiled, strict=True)):
                assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), k


@pytest.mark.skipif(not _fastslam_kernels.COMPILED_AHEAD, reason="FastSLAM's kernels were not compiled ahead of time")
def test_prebuilt_fastslam_kernels_refuse_arrays_they_would_misread() -> None:
    c = _fastslam_case(np.random.default_rng(1))
    arguments = [c["points"], c["positions"], c["rotations"], c["means"], c["counts"], 2.0]
    offsets, slots = _fastslam_kernels.near_slots(*arguments)
    assert offsets.dtype == slots.dtype == np.int64 and offsets[-1] == len(slots) > 0
    for position, bad in (
        (0, c["points"].astype(np.float32)),
        (0, c["points"][::2]),
        (0, c["points"].tolist()),
        (2, np.asfortranarray(c["rotations"])),
        (3, c["means"][:, ::2]),
        (4, c["counts"].astype(np.int32)),
    ):
        with pytest.raises(TypeError, match=f"near_slots: argument {position} "):
            _fastslam_kernels.near_slots(*arguments[:position], bad, *arguments[position + 1 :])
    Q = np.eye(6)[::2, ::2]  # a strided 3x3 view
    with pytest.raises(TypeError, match="update_landmarks: argument 6 "):
        _fastslam_kernels.update_landmarks(c["points"], np.zeros((6, 20), dtype=np.int64), c["positions"],
                                           c["rotations"], c["means"], c["covs"], Q, np.zeros((6, 30), dtype=np.int64),
                                           np.zeros((6, 30), dtype=np.int64), 0)  # fmt: skip


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
        return LandmarkMap(
            np.zeros((1, 3)), np.ones(1, dtype=np.int64), np.zeros(1, dtype=bool), np.zeros(1, dtype=np.int64)
        )

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
