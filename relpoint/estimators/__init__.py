"""Estimators behind ``relpoint run``, one module each, registered in :data:`ESTIMATORS`.

A built-in estimator's module is imported the first time its spec is asked for: what each one reads
(:meth:`EstimatorRegistry.inputs`) and its name are known without importing it, so that ``relpoint
info`` and ``--help`` start without scipy and numba; its settings class
(:meth:`EstimatorRegistry.config_class`) lives in a module of its own that imports neither, so that
``relpoint batch`` checks a plan without them.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

from relpoint.estimators._noise import SIMULATOR_SIGMA
from relpoint.estimators.base import DEPTH, FIX, ODOMETRY, POINTS, Estimator
from relpoint.estimators.spec import EstimatorSpec
from relpoint.settings import Settings


@dataclass(frozen=True)
class BuiltinEstimator:
    """Where a built-in estimator's spec lives (``module.SPEC``) and its settings class
    (``config``, as ``module:Class``), the input roles it declares there, and the module of its
    compiled kernels, if any (whose ``prepare()`` loads or compiles them)."""

    module: str
    config: str
    needs: frozenset[str]
    uses: frozenset[str] = frozenset()
    kernels: str | None = None


#: The built-in estimators; ``tests/test_estimators_registry.py`` checks these against each ``SPEC``.
BUILTIN = {
    "relpoint": BuiltinEstimator(
        "relpoint.estimators.relative_point.estimator",
        "relpoint.estimators.relative_point.config:RelativePointConfig",
        frozenset({POINTS}),
        kernels="relpoint.estimators.relative_point._kernels",
    ),
    "ekf": BuiltinEstimator(
        "relpoint.estimators.ekf",
        "relpoint.estimators.ekf_config:EkfConfig",
        frozenset({POINTS}),
        frozenset({ODOMETRY, FIX}),
    ),
    "fastslam": BuiltinEstimator(
        "relpoint.estimators.fastslam",
        "relpoint.estimators.fastslam_config:FastSlamConfig",
        frozenset({POINTS}),
        frozenset({ODOMETRY, FIX}),
        kernels="relpoint.estimators._fastslam_kernels",
    ),
    "dense": BuiltinEstimator(
        "relpoint.estimators.dense.estimator",
        "relpoint.estimators.dense.estimator:DenseConfig",
        frozenset({DEPTH}),
        frozenset({"color"}),
        kernels="relpoint.estimators.dense._kernels",
    ),
}


class EstimatorRegistry(Mapping[str, EstimatorSpec]):
    """Estimator specs by name; a built-in one is imported when first asked for."""

    def __init__(self) -> None:
        self._specs: dict[str, EstimatorSpec] = {}

    def __getitem__(self, name: str) -> EstimatorSpec:
        if name not in self._specs:
            if name not in BUILTIN:
                raise KeyError(name)
            self._specs[name] = importlib.import_module(BUILTIN[name].module).SPEC
        return self._specs[name]

    def __iter__(self) -> Iterator[str]:
        yield from BUILTIN
        yield from (name for name in self._specs if name not in BUILTIN)

    def __len__(self) -> int:
        return len(BUILTIN) + sum(1 for name in self._specs if name not in BUILTIN)

    def __contains__(self, name: object) -> bool:
        return name in BUILTIN or name in self._specs

    def register(self, spec: EstimatorSpec) -> EstimatorSpec:
        """Add (or replace) an estimator under ``spec.name``."""
        self._specs[spec.name] = spec
        return spec

    def config_class(self, name: str) -> type[Settings]:
        """The settings class of ``name``, without importing a built-in estimator's own module."""
        if name in self._specs:
            return self._specs[name].config_class
        if name not in BUILTIN:
            raise KeyError(name)
        module, attribute = BUILTIN[name].config.split(":")
        config_class: type[Settings] = getattr(importlib.import_module(module), attribute)
        return config_class

    def inputs(self, name: str) -> tuple[frozenset[str], frozenset[str]]:
        """(input roles ``name`` needs, roles it also uses), without importing a built-in estimator."""
        if name in self._specs:
            return self._specs[name].needs, self._specs[name].uses
        if name not in BUILTIN:
            raise KeyError(name)
        return BUILTIN[name].needs, BUILTIN[name].uses


#: Every estimator ``relpoint run --estimator NAME`` can build, by name.
ESTIMATORS = EstimatorRegistry()


def register(spec: EstimatorSpec) -> EstimatorSpec:
    """Add ``spec`` to :data:`ESTIMATORS`."""
    return ESTIMATORS.register(spec)


__all__ = [
    "BUILTIN", "DEPTH", "ESTIMATORS", "FIX", "ODOMETRY", "POINTS", "SIMULATOR_SIGMA", "Estimator",
    "EstimatorRegistry", "EstimatorSpec", "register",
]  # fmt: skip
