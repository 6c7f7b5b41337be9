"""Trajectory, landmark and dense-map evaluation (issue 3): evo-exact APE/RPE, KITTI segments and beyond.

The package is pure computation over :mod:`relpoint.types` containers and numpy arrays: no file I/O,
no printing. The CLI (``relpoint evaluate``) reads files with :mod:`formats` and calls
:func:`evaluate_trajectory`, :func:`landmark_metrics` and :func:`dense_metrics`.

Where relpoint and evo overlap the numbers are evo 1.38's, computed the same way (see
``docs/evaluation.md`` for the option correspondence).
"""

from __future__ import annotations

from relpoint.errors import RelpointError


class EvaluationError(RelpointError):
    """The evaluation cannot be computed from the given data.

    Raised for no overlapping timestamps, fewer than three matched poses for an alignment, degenerate
    (collinear or stationary) trajectories for Umeyama alignment, or an RPE delta that yields no pairs.
    """

    exit_code = 3


# Submodules import EvaluationError from here, so they are imported after its definition.
from relpoint.evaluation.alignment import (  # noqa: E402
    Alignment,
    AlignMode,
    align_positions,
    apply_alignment,
    estimate_alignment,
    umeyama,
)
from relpoint.evaluation.ape import PoseRelation, ape_errors  # noqa: E402
from relpoint.evaluation.association import MatchedPoses, associate, matching_time_indices  # noqa: E402
from relpoint.evaluation.dense import DenseMetrics, dense_metrics, dense_metrics_to_mesh  # noqa: E402
from relpoint.evaluation.evaluate import EvaluationResult, EvaluationSettings, evaluate_trajectory  # noqa: E402
from relpoint.evaluation.kitti import KittiSegmentErrors, kitti_segment_errors  # noqa: E402
from relpoint.evaluation.landmarks import (  # noqa: E402
    LandmarkEvaluation,
    dynamic_point_precision_recall,
    landmark_metrics,
    precision_recall,
)
from relpoint.evaluation.rpe import DeltaUnit, RelativeErrors, rpe_errors, rpe_pairs  # noqa: E402
from relpoint.evaluation.statistics import STATISTICS, error_statistics  # noqa: E402

__all__ = [
    "STATISTICS",
    "AlignMode",
    "Alignment",
    "DeltaUnit",
    "DenseMetrics",
    "EvaluationError",
    "EvaluationResult",
    "EvaluationSettings",
    "KittiSegmentErrors",
    "LandmarkEvaluation",
    "MatchedPoses",
    "PoseRelation",
    "RelativeErrors",
    "align_positions",
    "ape_errors",
    "apply_alignment",
    "associate",
    "dense_metrics",
    "dense_metrics_to_mesh",
    "dynamic_point_precision_recall",
    "error_statistics",
    "estimate_alignment",
    "evaluate_trajectory",
    "kitti_segment_errors",
    "landmark_metrics",
    "matching_time_indices",
    "precision_recall",
    "rpe_errors",
    "rpe_pairs",
    "umeyama",
]
