"""Ground-truth id tally: the majority ``id`` of the observations fused into each landmark.

Not part of the algorithm (Kraut, section II never sees ids) and never read for association: it only
labels the output map (``map.csv``'s ``gt_id``) and its association purity for evaluation. Pairs
``(point uid, id)`` are buffered per iteration and folded into sorted count arrays in batches, so the
per-iteration cost is one array append; point uids are never reused, merges re-label the newer uid.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

IntArray = npt.NDArray[np.int64]

_SHIFT = np.int64(1) << np.int64(32)


class IdTally:
    """Counts of ``(point uid, ground-truth id)`` pairs, with majority look-up.

    Parameters
    ----------
    fold_every:
        Fold the buffered pairs into the counts after this many buffered pairs.
    """

    def __init__(self, fold_every: int = 200_000) -> None:
        self._fold_every = fold_every
        self._pending: list[IntArray] = []
        self._pending_size = 0
        self._keys = np.zeros(0, np.int64)
        self._counts = np.zeros(0, np.int64)
        self._alias: dict[int, int] = {}
        self._dropped: set[int] = set()

    @staticmethod
    def _encode(uids: IntArray, ids: IntArray) -> IntArray:
        return uids.astype(np.int64) * _SHIFT + (ids.astype(np.int64) + 1)

    def add(self, uids: IntArray, ids: IntArray) -> None:
        """Record one observation with ground-truth ``ids`` (N,) for each point uid (N,)."""
        keys = self._encode(uids, ids)
        self._pending.append(keys)
        self._pending_size += len(keys)
        if self._pending_size >= self._fold_every:
            self._fold()

    def relabel(self, newer_uid: int, older_uid: int) -> None:
        """Count everything of ``newer_uid`` (past and buffered) as ``older_uid`` (point merging)."""
        self._alias[int(newer_uid)] = int(older_uid)
        self._fold()

    def drop(self, uids: IntArray) -> None:
        """Forget deleted points (applied at the next fold)."""
        self._dropped.update(int(u) for u in uids)

    def _fold(self) -> None:
        keys = np.concatenate([self._keys, *self._pending]) if self._pending else self._keys
        counts = np.concatenate([self._counts, *[np.ones(len(p), np.int64) for p in self._pending]])
        self._pending, self._pending_size = [], 0
        uid = keys // _SHIFT
        if self._alias:
            source = np.fromiter(self._alias.keys(), np.int64)
            target = np.fromiter(self._alias.values(), np.int64)
            hit = np.isin(uid, source)
            if hit.any():
                lookup = dict(zip(source.tolist(), target.tolist(), strict=True))
                new_uid = np.array([lookup[int(u)] for u in uid[hit]], np.int64)
                keys = keys.copy()
                keys[hit] = new_uid * _SHIFT + keys[hit] % _SHIFT
                uid = keys // _SHIFT
            self._alias.clear()
        if self._dropped:
            keep = ~np.isin(uid, np.fromiter(self._dropped, np.int64))
            keys, counts = keys[keep], counts[keep]
            self._dropped.clear()
        unique, inverse = np.unique(keys, return_inverse=True)
        self._keys = unique
        self._counts = np.bincount(inverse.reshape(-1), weights=counts, minlength=len(unique)).astype(np.int64)

    def majority(self, uids: IntArray) -> tuple[IntArray, npt.NDArray[np.float64]]:
        """Majority ground-truth id (N,) of each uid (-1 if none) and its share of the uid's observations."""
        self._fold()
        uids = np.asarray(uids, np.int64)
        result = np.full(len(uids), -1, np.int64)
        purity = np.zeros(len(uids))
        if len(self._keys) == 0 or len(uids) == 0:
            return result, purity
        key_uid = self._keys // _SHIFT
        # Keys are sorted by uid then id: order each uid's run by count, the last of a run is its majority.
        order = np.lexsort((self._counts, key_uid))
        sorted_uid = key_uid[order]
        last = np.r_[sorted_uid[1:] != sorted_uid[:-1], True]
        best_uid = sorted_uid[last]
        best_id = self._keys[order][last] % _SHIFT - 1
        totals = np.bincount(np.searchsorted(best_uid, key_uid), weights=self._counts, minlength=len(best_uid))
        best_share = self._counts[order][last] / np.maximum(totals, 1)
        pos = np.clip(np.searchsorted(best_uid, uids), 0, len(best_uid) - 1)
        found = best_uid[pos] == uids
        result[found] = best_id[pos[found]]
        purity[found] = best_share[pos[found]]
        return result, purity
