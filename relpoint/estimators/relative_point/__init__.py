"""The Relative Point estimator (Kraut, *A Relative Point Algorithm*, section II), one module per component.

See :mod:`.estimator` for the map from the paper's classes to these modules.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from relpoint.estimators.relative_point.estimator import SPEC, RelativePointConfig, RelativePointEstimator

__all__ = ["SPEC", "RelativePointConfig", "RelativePointEstimator"]


def __getattr__(name: str) -> Any:
    """The estimator's names, imported on first use: a batch worker loads the compiled kernels
    (:mod:`._kernels`) before its first job without importing the estimator."""
    if name in __all__:
        from relpoint.estimators.relative_point import estimator

        return getattr(estimator, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
