"""Groups: basis frames, relative maps and their least-squares combination (Kraut, section II-B).

Paper name -> Python name
    *RltGroup*     :class:`RelativeGroup`: the member *RltPoints*, three basis members, the running sum
                   of each member's relative position and the group's fit to the global map.
    *RltGroupRef*  :meth:`GroupMap.refs_of`: per point, the ids of the groups it is in (a row of a table).
    *RltLSF*       :func:`relpoint.estimators.relative_point.lsf.fit_transform`.

Basis frame (:func:`basis_rotation`): the first basis point is the origin, the second lies on the
negative x axis and the third in the xz plane (positive z). Relative coordinates of an iteration's
untransformed points are therefore invariant to the sensor's pose, and their average over the
iterations in which every member is observed is the group's *relative map*.

Placement: the first (root) group is fitted to the first observations of its members (the world
frame is the sensor frame of the first iteration); every later group is fitted to the global
positions its previously mapped members already have *from other groups*, and the fit gives the
global positions of its new members. A point in several groups gets the least-squares combination of
the positions its groups give it, weighted by the number of iterations each group averaged:
``pos_sum / pos_weight`` in :class:`~relpoint.estimators.relative_point.points.PointStore`.
Anchors are weighted by the inverse variance of their global position (iterations averaged over
the squared disagreement between their groups) and gross outliers are trimmed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from relpoint.estimators.relative_point._kernels import (
    OPEN_GROUP_AVERAGED,
    OPEN_GROUP_CLOSES,
    append_group,
    basis_coordinates,
    drop_group,
    extend_open_group,
    group_anchors,
    replace_contribution,
    spread_basis,
)
from relpoint.estimators.relative_point.lsf import fit_transform
from relpoint.estimators.relative_point.points import PointStore
from relpoint.geometry import FloatArray, apply_transform

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

ROOT = "root"
"""A group anchored to observations mapped by a known pose (the first group: the first observations)."""
FIRST = "first"
"""A point's first grouping, created a few iterations after the point is first seen."""
LATER = "later"
"""A regrouping over a longer calculation interval (the paper's second grouping)."""


_ROLL1 = np.array([1, 2, 0])
_ROLL2 = np.array([2, 0, 1])


def basis_rotation(b0: FloatArray, b1: FloatArray, b2: FloatArray, min_spread: float) -> tuple[FloatArray, BoolArray]:
    """Rotation ``R_sensor_basis`` (..., 3, 3) of the basis frame of three points (..., 3).

    Columns are the basis axes in the sensor frame: x points from ``b1`` to ``b0`` (so ``b1`` sits on
    the negative x axis), z is the part of ``b2 - b0`` orthogonal to x (so ``b2`` lies in the xz
    plane) and y = z x x. ``valid`` (...) is False where ``b0 b1`` is shorter than ``min_spread`` or
    ``b2`` lies within ``min_spread`` of that line (collinear basis: no unique rotation).
    """
    x = b0 - b1
    x_norm = np.sqrt(np.einsum("...i,...i->...", x, x))[..., None]
    x = x / np.maximum(x_norm, 1e-12)
    v = b2 - b0
    z = v - np.einsum("...i,...i->...", v, x)[..., None] * x
    z_norm = np.sqrt(np.einsum("...i,...i->...", z, z))[..., None]
    z = z / np.maximum(z_norm, 1e-12)
    # y = z x x, written out (np.cross costs several times more at these sizes).
    y = z[..., _ROLL1] * x[..., _ROLL2] - z[..., _ROLL2] * x[..., _ROLL1]
    valid = (x_norm[..., 0] >= min_spread) & (z_norm[..., 0] >= min_spread)
    return np.stack([x, y, z], axis=-1), valid


def relative_coordinates(
    observations: FloatArray, basis: tuple[int, int, int], min_spread: float
) -> tuple[FloatArray, BoolArray]:
    """Members' coordinates in the basis frame of each iteration.

    Parameters
    ----------
    observations:
        (M, L, 3) untransformed observations of M members over L iterations (sensor frame of each).
    basis:
        Rows of the three basis members.

    Returns
    -------
    relative, valid:
        (M, L, 3) coordinates in the basis frame (m) and (L,) whether the basis was usable.
    """
    i0, i1, i2 = basis
    return basis_coordinates(np.ascontiguousarray(observations, dtype=np.float64), i0, i1, i2, float(min_spread))


def choose_basis(points: FloatArray, min_spread: float) -> tuple[int, int, int] | None:
    """Three well-spread, non-collinear rows of ``points`` (M, 3) for a basis, or ``None``.

    The first is the point farthest from the centroid, the second the point farthest from the first,
    the third the point farthest from the line through both.
    """
    i0, i1, i2 = spread_basis(np.ascontiguousarray(points, dtype=np.float64), float(min_spread))
    return None if i0 < 0 else (i0, i1, i2)


@dataclass(eq=False)
class RelativeGroup:
    """One *RltGroup*: members, basis and relative map.

    Attributes
    ----------
    gid: group id.
    kind: :data:`ROOT`, :data:`FIRST` or :data:`LATER`.
    members: (M,) point ids.
    basis: rows of ``members`` used as basis points.
    rel_sum: (M, 3) sum of relative positions over ``count`` iterations (basis frame, m).
    count: iterations averaged.
    last_iteration: last iteration averaged.
    is_open: still averaging (every member was observed in every iteration since creation).
    anchor_targets: (M, 3) world positions a root group is fitted to, else ``None``.
    T_world_group: (4, 4) fit of the relative map into ``world``.
    placed: (M, 3) world positions this group gives its members (its contribution).
    weight: weight of the contribution (``count`` when placed, 0 before).
    """

    gid: int
    kind: str
    members: IntArray
    basis: tuple[int, int, int]
    rel_sum: FloatArray
    count: int
    last_iteration: int
    is_open: bool
    anchor_targets: FloatArray | None = None
    T_world_group: FloatArray = field(default_factory=lambda: np.eye(4))
    placed: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    weight: float = 0.0

    @property
    def relative_map(self) -> FloatArray:
        """Average relative position (M, 3) of each member in the basis frame, metres."""
        return self.rel_sum / max(self.count, 1)

    def __len__(self) -> int:
        return len(self.members)


class GroupMap:
    """Every group, the per-point group references, and the combination of their placements.

    Parameters
    ----------
    store:
        The points; its ``pos_sum``/``pos_weight`` accumulators hold the combination.
    trim, floor, collinear_tolerance, rounds:
        Passed to the least-squares fits (see :func:`fit_transform`).
    min_basis_spread:
        Smallest basis spread (m) for an iteration to be averaged.
    weighted:
        Weight anchors by the iterations averaged into their global positions over the squared
        spread of those positions between groups (floored at ``spread_floor``, m).
    unverified_weight:
        Factor on the weight of anchors not (yet) verified static by dynamic detection.
    consensus:
        Consensus bound of the fits (m; 0 disables; see :func:`fit_transform`).
    """

    def __init__(
        self,
        store: PointStore,
        *,
        trim: float,
        floor: float,
        collinear_tolerance: float,
        min_basis_spread: float,
        weighted: bool = True,
        unverified_weight: float = 0.5,
        spread_floor: float = 0.2,
        rounds: int = 1,
        consensus: float = 0.0,
    ) -> None:
        self.store = store
        self.trim = trim
        self.floor = floor
        self.collinear_tolerance = collinear_tolerance
        self.min_basis_spread = min_basis_spread
        self.weighted = weighted
        self.unverified_weight = unverified_weight
        self.rounds = rounds
        self.consensus = consensus
        self.spread_floor = spread_floor
        self.groups: dict[int, RelativeGroup] = {}
        # The paper's RltGroupRef lists: point i is in the groups refs_table[i, :refs_count[i]], oldest first.
        self._refs_table = np.zeros((0, 8), np.int64)
        self._refs_count = np.zeros(0, np.int64)
        self.open: list[int] = []
        self._next_gid = 0
        self._changed: list[IntArray] = []
        self.created = 0
        self.removed = 0
        self.failed_fits = 0

    def __len__(self) -> int:
        return len(self.groups)

    def new_gid(self) -> int:
        gid = self._next_gid
        self._next_gid += 1
        return gid

    def refs_of(self, point: int) -> list[int]:
        """Ids of the groups point ``point`` is in, in the order they were created or taken over
        (the paper's *RltGroupRef* list)."""
        if point >= len(self._refs_count):
            return []
        return self._refs_table[point, : self._refs_count[point]].tolist()

    def _reserve_refs(self) -> None:
        """Give every row of the point store a group list."""
        extra = self.store.capacity - len(self._refs_count)
        if extra > 0:
            self._refs_table = np.concatenate(
                [self._refs_table, np.zeros((extra, self._refs_table.shape[1]), np.int64)]
            )
            self._refs_count = np.concatenate([self._refs_count, np.zeros(extra, np.int64)])

    def _widen_refs(self) -> None:
        """Double the room of every point's group list."""
        self._refs_table = np.concatenate([self._refs_table, np.zeros_like(self._refs_table)], axis=1)

    # -- placement -------------------------------------------------------------------------------

    def place(self, group: RelativeGroup) -> bool:
        """Fit the group's relative map into ``world`` and update its members' combined positions.

        Returns False (leaving the group as it was) when the fit is degenerate: fewer than three
        non-collinear anchors, i.e. previously mapped members for a later group.
        """
        store = self.store
        members = group.members
        relative = group.relative_map
        if group.anchor_targets is not None:
            static = ~store.dynamic[members]
            source, target, weights = relative[static], group.anchor_targets[static], None
        else:
            source, target, weights = group_anchors(
                store.pos_sum, store.pos_weight, store.pos_sq, store.dynamic, store.verified, members, relative,
                group.placed, float(group.weight), self.weighted, float(self.spread_floor) ** 2, float(self.unverified_weight),
            )  # fmt: skip
        fit = fit_transform(
            source,
            target,
            trim=self.trim,
            floor=self.floor,
            collinear_tolerance=self.collinear_tolerance,
            weights=weights,
            rounds=self.rounds,
            consensus=self.consensus,
        )
        if fit is None:
            self.failed_fits += 1
            return False
        group.T_world_group = fit.T
        self._contribute(group, apply_transform(fit.T, relative), float(group.count))
        return True

    def move(self, group: RelativeGroup, T_world_group: FloatArray) -> None:
        """Give a placed group the pose ``T_world_group`` (4, 4) (the final adjustment), with its contribution."""
        group.T_world_group = T_world_group
        self._contribute(group, apply_transform(T_world_group, group.relative_map), group.weight)

    def shift(self, group: RelativeGroup, offset: FloatArray) -> None:
        """Translate a placed group by ``offset`` (3,) m in ``world`` (loop closure), with its contribution."""
        group.T_world_group = group.T_world_group.copy()
        group.T_world_group[:3, 3] += offset
        if group.anchor_targets is not None:
            group.anchor_targets = group.anchor_targets + offset
        self._contribute(group, group.placed + offset, group.weight)

    def _contribute(self, group: RelativeGroup, placed: FloatArray, weight: float) -> None:
        """Replace the group's contribution to its members' positions by ``placed`` (M, 3) x ``weight``."""
        store = self.store
        replace_contribution(
            store.pos_sum, store.pos_weight, store.pos_sq, group.members, group.placed, group.weight, placed, weight
        )
        group.placed = placed
        group.weight = weight
        self._changed.append(group.members)

    # -- life cycle ------------------------------------------------------------------------------

    def add(self, group: RelativeGroup) -> bool:
        """Place a new group and register it with its members; False if it cannot be placed."""
        if not self.place(group):
            return False
        gid = group.gid
        self.groups[gid] = group
        self._reserve_refs()
        while not append_group(self._refs_table, self._refs_count, group.members, gid):
            self._widen_refs()
        self.store.n_groups[group.members] += 1
        if group.kind == LATER:
            self.store.n_later_groups[group.members] += 1
        if group.is_open:
            self.open.append(group.gid)
        self.created += 1
        return True

    def remove(self, gid: int) -> None:
        """Delete a group and withdraw its contribution from its members' positions."""
        group = self.groups.pop(gid)
        self._contribute(group, group.placed, 0.0)
        drop_group(self._refs_table, self._refs_count, group.members, gid)
        self.store.n_groups[group.members] -= 1
        if group.kind == LATER:
            self.store.n_later_groups[group.members] -= 1
        if gid in self.open:
            self.open.remove(gid)
        self.removed += 1

    def update_open(self, iteration: int) -> int:
        """Average this iteration into every open group whose members were all observed; close the rest.

        This is the paper's notification: a group recomputes only when every member has a new
        observation in the iteration. Returns the number of groups recomputed.
        """
        store = self.store
        still_open: list[int] = []
        updated = 0
        for gid in self.open:
            group = self.groups[gid]
            outcome = extend_open_group(
                store.obs, store.last_iter, store.dynamic, group.members, *group.basis, iteration,
                float(self.min_basis_spread), group.rel_sum,
            )  # fmt: skip
            if outcome == OPEN_GROUP_CLOSES:
                group.is_open = False
                continue
            if outcome == OPEN_GROUP_AVERAGED:
                group.count += 1
                group.last_iteration = iteration
                self.place(group)
                updated += 1
            still_open.append(gid)
        self.open = still_open
        return updated

    def transfer(self, newer: int, older: int) -> None:
        """Make ``older`` take ``newer``'s place in every group of ``newer`` (point merging)."""
        store = self.store
        taken_over = self.refs_of(newer)
        for gid in taken_over:
            group = self.groups[gid]
            group.members = np.where(group.members == newer, older, group.members)
        self._reserve_refs()
        while self._refs_count[older] + len(taken_over) > self._refs_table.shape[1]:
            self._widen_refs()
        start = self._refs_count[older]
        self._refs_table[older, start : start + len(taken_over)] = taken_over
        self._refs_count[older] += len(taken_over)
        self._refs_count[newer] = 0
        store.pos_sum[older] += store.pos_sum[newer]
        store.pos_weight[older] += store.pos_weight[newer]
        store.pos_sq[older] += store.pos_sq[newer]
        store.n_groups[older] += store.n_groups[newer]
        store.n_later_groups[older] += store.n_later_groups[newer]
        store.pos_sum[newer] = 0.0
        store.pos_weight[newer] = 0.0
        store.pos_sq[newer] = 0.0
        store.n_groups[newer] = 0
        store.n_later_groups[newer] = 0
        self._changed.append(np.array([older], np.int64))

    def take_changed(self) -> IntArray:
        """Ids whose combined position changed since the last call (repeats possible, in no order)."""
        if not self._changed:
            return np.zeros(0, np.int64)
        changed = np.concatenate(self._changed)
        self._changed = []
        return changed
