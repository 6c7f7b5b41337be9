"""Fusing local SLAM with low-rate absolute fixes into a globally consistent map and path.

Zhang, Milios and Gu, *General Concept of 3D SLAM*, sections 5-6 and Algorithm 3, as a post-step over
any estimator's output: Lagrange synchronisation of the fixes (:mod:`relpoint.lagrange`, shared with the filters), covariance-weighted
fusion (:mod:`.covariance_fusion`), segmentation into local maps (:mod:`.segmentation`), B-spline path
parameterisation (:mod:`.bspline`) and the rigid local-to-global fit with map integration
(:mod:`.global_map`; piecewise where a local map is not rigid, :mod:`.piecewise`), driven by :func:`fuse`; :func:`run_segmented` runs a local SLAM that restarts
at every break, as Algorithm 3 does. Pure numpy/scipy; no file I/O.
"""

from __future__ import annotations

from relpoint.fusion.bspline import PathSpline
from relpoint.fusion.covariance_fusion import fuse_estimates
from relpoint.fusion.fuse import FusionConfig, FusionResult, SegmentResult, fuse
from relpoint.fusion.global_map import SegmentTransform, fit_segment
from relpoint.fusion.piecewise import Piece, split_segment
from relpoint.fusion.segmentation import (
    NO_SEGMENT,
    matched_counts_from_ids,
    matched_counts_from_map_growth,
    segment_run,
    segment_slices,
)
from relpoint.fusion.segmented import SegmentedRun, run_segmented
from relpoint.lagrange import interpolate_fixes, lagrange_weights

__all__ = [
    "NO_SEGMENT",
    "FusionConfig",
    "FusionResult",
    "PathSpline",
    "Piece",
    "SegmentResult",
    "SegmentTransform",
    "SegmentedRun",
    "fit_segment",
    "fuse",
    "fuse_estimates",
    "interpolate_fixes",
    "lagrange_weights",
    "matched_counts_from_ids",
    "matched_counts_from_map_growth",
    "run_segmented",
    "segment_run",
    "segment_slices",
    "split_segment",
]
