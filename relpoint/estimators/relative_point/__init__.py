"""The Relative Point estimator (Kraut, *A Relative Point Algorithm*, section II), one module per component.

See :mod:`.estimator` for the map from the paper's classes to these modules.
"""

from relpoint.estimators.relative_point.estimator import SPEC, RelativePointConfig, RelativePointEstimator

__all__ = ["SPEC", "RelativePointConfig", "RelativePointEstimator"]
