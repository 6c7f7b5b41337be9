"""The state the phases of the Relative Point estimator share (:class:`EstimatorState`).

:class:`~.estimator.RelativePointEstimator` composes its phases, one module each: localisation
(:mod:`.localisation`), loop closure (:mod:`.loops`), grouping (:mod:`.grouping`), the dynamic
sweep (:mod:`.dynamics`) and the final adjustment (:mod:`.adjustment`). Each phase is a class over
this state; the estimator builds the state once (``__init__``) and :meth:`~.estimator.RelativePointEstimator.step`
calls the phases in the paper's order. The stateful parts (points, groups, index, motion, charting,
tally) are collaborators in their own modules.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
import numpy.typing as npt

from relpoint.estimators.relative_point.charting import PointCharting
from relpoint.estimators.relative_point.config import RelativePointConfig
from relpoint.estimators.relative_point.grouping import UngroupedList
from relpoint.estimators.relative_point.groups import GroupMap
from relpoint.estimators.relative_point.points import IntArray, PointStore
from relpoint.estimators.relative_point.registration import GlobalIndex, MotionModel
from relpoint.estimators.relative_point.tally import IdTally
from relpoint.geometry import FloatArray


class EstimatorState:
    """What every phase reads and writes. Distances in metres, poses ``T_world_sensor`` (4, 4).

    Attributes
    ----------
    config: the settings.
    store: every point: its ring of untransformed observations and world position sums (:mod:`.points`).
    charting: which points each recent iteration observed (:mod:`.charting`).
    groups: the relative maps over three basis points and their world poses (:mod:`.groups`).
    motion: the last inter-iteration motion, for predicting recent observations.
    index: the spatial index of mapped points' world positions, for global matching and merging.
    ungrouped: points not yet in a group.
    tally: ground-truth ids per point (output labels only, never used for association).
    counts: event counters for ``summary()``.
    """

    config: RelativePointConfig
    store: PointStore
    charting: PointCharting
    groups: GroupMap
    motion: MotionModel
    index: GlobalIndex
    ungrouped: UngroupedList
    tally: IdTally
    counts: dict[str, int]
    adjustment_report: dict[str, Any] | None
    _poses: FloatArray
    _T_world_sensor: FloatArray
    _path: FloatArray
    _motion_measured: bool
    _iteration: int
    _regroup_queue: deque[int]
    _first_groups: deque[int]
    _over_grouped: set[int]
    _map_restarts: list[int]
    _newly_mapped: list[IntArray]
    _next_creation_try: dict[int, int]
    _support: list[tuple[IntArray, npt.NDArray[np.float32]] | None]
    _observations: dict[int, tuple[IntArray, npt.NDArray[np.float32]]]
    _keyframe_stride: int
    _kept_observations: int
    _merged_uid: dict[int, int]
