"""Group creation: choosing the members and calculation interval of a new group (Kraut, section II-C).

Paper name -> Python name
    *RltInterval*       a boolean presence row per point over the creation interval (from the rings,
                        :meth:`PointStore.presence`); a group's interval is the AND of its members'
                        rows (the iterations in which *all* members are observed), and
                        :func:`select_members` combines rows that way.
    *RltUngroupedList*  :class:`UngroupedList`.
    *RltMapper*         :class:`~relpoint.estimators.relative_point.estimator.RelativePointEstimator`,
                        which applies the heuristic of :func:`select_members` for first groupings and
                        regroupings, in one compiled call with the candidates' presence rows
                        (:func:`~._kernels.group_selection`).

The heuristic (:func:`select_members`): the lists of grouped and ungrouped points present in the
creation point's interval are sorted by how many iterations of it they cover; the creation point and
the three best previously grouped points seed the group; then points are taken in order of coverage
while the calculation interval length times the member count grows, stopping at the first that does
not improve it.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from relpoint.estimators.relative_point._kernels import interval_members

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


def select_members(
    presence: BoolArray, grouped: BoolArray, creation: int, seeds: int = 3
) -> tuple[IntArray, BoolArray] | None:
    """Pick a group's members among candidates by the paper's interval x count heuristic.

    Parameters
    ----------
    presence:
        (N, L) whether each candidate is observed in each iteration of the creation interval.
    grouped:
        (N,) candidates that already have a global position (the "previous" points).
    creation:
        Row of the creation point.
    seeds:
        Previously grouped points that seed the group with the creation point (paper: three).

    Returns
    -------
    rows, interval:
        Chosen candidate rows (creation point first) and the (L,) mask of iterations in which all
        of them are observed; ``None`` if fewer than ``seeds`` grouped candidates share an iteration
        with the creation point.
    """
    presence = np.ascontiguousarray(presence, dtype=bool)
    # Ties keep candidate order (ascending id = older first): stable sort by descending coverage.
    order = np.argsort(-presence.sum(axis=1), kind="stable")
    rows, interval = interval_members(
        presence, np.ascontiguousarray(grouped, dtype=bool), order, int(creation), int(seeds)
    )
    return (rows, interval) if len(rows) else None


class UngroupedList:
    """*RltUngroupedList*: points not grouped yet, in order of creation (hence of first iteration).

    Lets the mapper find creation points without enumerating every point.
    """

    def __init__(self) -> None:
        self._ids: dict[int, None] = {}

    def __len__(self) -> int:
        return len(self._ids)

    def add(self, ids: npt.ArrayLike) -> None:
        for i in np.atleast_1d(ids).tolist():
            self._ids[int(i)] = None

    def discard(self, ids: npt.ArrayLike) -> None:
        for i in np.atleast_1d(ids).tolist():
            self._ids.pop(int(i), None)

    def ids(self) -> IntArray:
        """The listed ids, oldest first."""
        return np.fromiter(self._ids, np.int64, len(self._ids))
