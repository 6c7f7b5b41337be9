"""What the registry knows of an estimator (:class:`EstimatorSpec`) and how it builds one."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from relpoint.estimators._noise import (
    SIMULATOR_SIGMA,
    MotionNoiseSettings,
    NoiseAdaptive,
    PathAcceleration,
)
from relpoint.estimators.base import DEPTH, POINTS, Estimator
from relpoint.settings import Settings


@dataclass(frozen=True)
class EstimatorSpec:
    """One estimator as ``relpoint run`` knows it: its class, its settings class and its inputs.

    Every estimator class is built as ``estimator_class(config, rng)``; ``rng`` is the only source of
    randomness it may use. ``input_kind`` is what one iteration reads (:data:`POINTS` or
    :data:`DEPTH`), ``uses`` the optional input roles it also takes (odometry, fixes, colour).
    ``noise_adaptive``: the settings hold ``observation_sigma`` and an ``at_noise(sigma)`` that fits
    them to a noise; when the noise is unset, :meth:`factory` builds the estimator once the noise is
    estimated from the first observations (:class:`~relpoint.estimators._noise.NoiseAdaptive`), and so
    is a motion model's unset ``linear_acceleration_noise`` (:class:`~relpoint.estimators._noise.MotionNoiseSettings`).
    """

    name: str
    description: str
    config_class: type[Settings]
    estimator_class: Callable[[Any, np.random.Generator], Estimator]
    input_kind: str = POINTS
    uses: frozenset[str] = frozenset()
    noise_adaptive: bool = False

    def __post_init__(self) -> None:
        if self.input_kind not in (POINTS, DEPTH):
            raise ValueError(f"input_kind must be {POINTS!r} or {DEPTH!r}, got {self.input_kind!r}")

    @property
    def needs(self) -> frozenset[str]:
        """The input roles a log must have: the one of :attr:`input_kind`."""
        return frozenset({self.input_kind})

    def factory(self, config: Any, rng: np.random.Generator) -> Estimator:
        """A fresh estimator for ``config``; noise-adaptive ones wait for the noise when it is unset."""
        if not self.noise_adaptive:
            return self.estimator_class(config, rng)
        # A motion model whose acceleration noise is unset takes it from the held-back path.
        measure_acceleration = isinstance(config, MotionNoiseSettings) and config.derives_acceleration
        check_odometry = isinstance(config, MotionNoiseSettings) and config.odometry_check
        if config.observation_sigma is not None and not (measure_acceleration or check_odometry):
            return self.estimator_class(config.at_noise(config.observation_sigma), rng)

        def build(sigma: float, acceleration: PathAcceleration | None) -> Estimator:
            fitted = config.at_noise(sigma)
            if measure_acceleration:
                fitted = fitted.at_acceleration(acceleration, sigma)
            return self.estimator_class(fitted, rng)

        compile_code = getattr(self.estimator_class, "compile", None)
        return NoiseAdaptive(build, SIMULATOR_SIGMA, self.name, prepare=compile_code, sigma=config.observation_sigma,
                             measure_acceleration=measure_acceleration, check_odometry=check_odometry,
                             finishing=getattr(self.estimator_class, "finishing", Estimator.finishing),
                             reports_unlocated=getattr(self.estimator_class, "reports_unlocated", False))  # fmt: skip

    def build_config(self, values: Mapping[str, Any], params: Iterable[str] = ()) -> Any:
        """The config dataclass from parameter values and ``KEY=VALUE`` items (``--param``) over them:
        :meth:`Settings.from_strings <relpoint.settings.Settings.from_strings>`."""
        return self.config_class.from_strings(params, base=values)
