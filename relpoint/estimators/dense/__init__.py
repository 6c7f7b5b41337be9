"""Dense RGB-D SLAM with point-based fusion (``relpoint run --estimator dense``).

Modules: :mod:`.maps` (vertex/normal pyramids), :mod:`.icp` (projective association, point-to-plane ICP),
:mod:`.fusion` (the point map and its fusion), :mod:`.estimator` (the estimator and its config).
"""

from relpoint.estimators.dense.estimator import SPEC, DenseConfig, DenseFusion

__all__ = ["SPEC", "DenseConfig", "DenseFusion"]
