"""Each landmark's accepted observations, kept for the batch refinement (docs/derivations/ekf_anchored.md,
§ Batch refinement).

Pure bookkeeping, no estimation: :class:`ObservationHistory` holds, per landmark id, the observations
its anchored filter accepted since the anchor, in time order, one *slot* per frame (the first: the
anchor's frame, no measurement): the pose of that frame (``R_world_cam``, ``p_world_cam``, t), the normalized pixel z = (x̄, ȳ) (NaN when the frame gave
no accepted pixel update) and the looming scale change with its variance (NaN when none).  A looming
measurement relates the slot's pose to the previous frame's, which must therefore be the landmark's
previous slot; when it is not (the previous frame's pixel update was refused and held no looming
either), the history cannot reproduce what the filter fused and is marked *incomplete*: it is never
refined again.

Memory is bounded: a history holds at most ``capacity`` slots; a full one stops recording.  Slots
live in a pool of rows that never move (a landmark leaving frees its row for the next), so recording
a frame costs array writes for that frame's landmarks only, never a copy of the histories.
"""

from __future__ import annotations

import numpy as np

from companion.core.idbank import lookup
from companion.errors import InputError


class ObservationHistory:
    """Per-landmark observation histories (module docstring), addressed by landmark id."""

    def __init__(self, capacity: int, first_due: int = 2):
        if not isinstance(capacity, (int, np.integer)) or isinstance(capacity, bool) or capacity < 2:
            raise InputError(f"ObservationHistory: capacity must be an integer >= 2, got {capacity!r}")
        if not isinstance(first_due, (int, np.integer)) or isinstance(first_due, bool) or not 1 <= first_due <= capacity:
            raise InputError(f"ObservationHistory: first_due must be an integer in 1..capacity, got {first_due!r}")
        self.capacity = int(capacity)
        self.first_due = int(first_due)
        # per landmark, sorted by id: its pool row, its slot count, whether it is still complete
        self.ids = np.zeros(0, np.int64)
        self.row = np.zeros(0, np.int64)
        self.count = np.zeros(0, np.int64)
        self.complete = np.zeros(0, bool)
        self.next_due = np.zeros(0, np.int64)  # history size at which the landmark is next due (:meth:`due`)
        self._free = np.zeros(0, np.int64)  # pool rows not held by any landmark (a stack: the last is reused first)
        self._alloc(8)

    def _alloc(self, rows: int) -> None:
        """Grow the pool to ``rows`` rows (existing rows keep their index and content)."""
        old = getattr(self, "t", None)
        k = self.capacity
        new = {
            "t": np.full((rows, k), np.nan),
            "R": np.zeros((rows, k, 3, 3)),
            "C": np.zeros((rows, k, 3)),
            "z": np.full((rows, k, 2), np.nan),
            "s": np.full((rows, k), np.nan),
            "s_var": np.full((rows, k), np.nan),
        }
        n_old = 0 if old is None else len(old)
        for name, a in new.items():
            if n_old:
                a[:n_old] = getattr(self, name)
            setattr(self, name, a)
        self._free = np.concatenate([self._free, np.arange(rows - 1, n_old - 1, -1, dtype=np.int64)])

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def pool_rows(self) -> int:
        """Rows allocated (the memory held: ``pool_rows`` × ``capacity`` slots)."""
        return len(self.t)

    def contains(self, ids) -> np.ndarray:
        return lookup(self.ids, ids)[0]

    # -- membership -----------------------------------------------------------------------------
    def _ensure(self, ids: np.ndarray) -> np.ndarray:
        """Entries of ``ids`` (distinct), created empty where missing; returns their indices."""
        found, idx = lookup(self.ids, ids)
        new = ids[~found]
        if len(new):
            while len(self._free) < len(new):
                self._alloc(2 * self.pool_rows)
            rows = self._free[::-1][: len(new)].copy()
            self._free = self._free[: len(self._free) - len(new)]
            self._clear_rows(rows)
            ids_all = np.concatenate([self.ids, new])
            order = np.argsort(ids_all, kind="stable")
            self.ids = ids_all[order]
            self.row = np.concatenate([self.row, rows])[order]
            self.count = np.concatenate([self.count, np.zeros(len(new), np.int64)])[order]
            self.complete = np.concatenate([self.complete, np.ones(len(new), bool)])[order]
            self.next_due = np.concatenate([self.next_due, np.full(len(new), self.first_due, np.int64)])[order]
            idx = lookup(self.ids, ids)[1]
        return idx

    def _clear_rows(self, rows: np.ndarray) -> None:
        for name in ("t", "z", "s", "s_var"):
            getattr(self, name)[rows] = np.nan

    def drop(self, ids) -> None:
        """Forget landmarks (unknown ids are ignored); their pool rows are reused."""
        found, idx = lookup(self.ids, np.asarray(ids, np.int64).reshape(-1))
        idx = np.unique(idx[found])
        if len(idx) == 0:
            return
        held = self.row[idx]
        self._free = np.concatenate([self._free, held[held >= 0]])
        keep = np.ones(len(self.ids), bool)
        keep[idx] = False
        for name in ("ids", "row", "count", "complete", "next_due"):
            setattr(self, name, getattr(self, name)[keep])

    def seal(self, ids) -> None:
        """Stop recording for these landmarks (e.g. after their last refinement): mark them incomplete
        and free their slots, keeping the entry so that nothing is recorded for them again."""
        found, idx = lookup(self.ids, np.asarray(ids, np.int64).reshape(-1))
        idx = np.unique(idx[found])
        held = self.row[idx]
        self._free = np.concatenate([self._free, held[held >= 0]])
        self.row[idx] = -1
        self.complete[idx] = False
        self.count[idx] = 0

    # -- recording ------------------------------------------------------------------------------
    def _slot_at(self, idx: np.ndarray, t: float, create: bool) -> tuple[np.ndarray, np.ndarray]:
        """(mask (M,), slot (M,)): the slot of frame t for entries ``idx``, the last one when it holds t,
        else (``create``) a new one where there is room; mask False where there is none."""
        cnt = self.count[idx]
        rows = self.row[idx]
        last_t = np.where(cnt > 0, self.t[rows, np.maximum(cnt - 1, 0)], np.nan)
        same = cnt > 0
        same &= last_t == t
        slot = np.where(same, cnt - 1, cnt)
        ok = self.complete[idx] & (same | (create & (cnt < self.capacity)))
        return ok, slot

    def record_anchor(self, ids, t: float, R_world_cam, p_world_cam) -> None:
        """New landmarks anchored at frame t: their first slot holds the anchor's pose and no measurement
        (the anchor pixel is the filter's prior), so that a looming measurement at the next frame finds
        its previous pose."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        self.record_pixels(ids, t, R_world_cam, p_world_cam, np.full((len(ids), 2), np.nan))

    def record_pixels(self, ids, t: float, R_world_cam, p_world_cam, xy) -> None:
        """Accepted pixel updates of frame t (one pose for the frame): ``ids`` (M,) distinct, ``xy`` (M,2)
        normalized.  A landmark whose history is full or incomplete records nothing."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        if len(ids) == 0:
            return
        idx = self._ensure(ids)
        ok, slot = self._slot_at(idx, float(t), create=True)
        idx, slot, xy = idx[ok], slot[ok], np.asarray(xy, float).reshape(-1, 2)[ok]
        rows = self.row[idx]
        self.t[rows, slot] = t
        self.R[rows, slot] = R_world_cam
        self.C[rows, slot] = p_world_cam
        self.z[rows, slot] = xy
        self.count[idx] = np.maximum(self.count[idx], slot + 1)

    def record_looming(self, ids, t: float, R_world_cam, p_world_cam, t_prev: float, scale, var) -> None:
        """Accepted looming updates of frame t against the previous frame t_prev: ``scale`` and its
        variance ``var`` (M,).  Attached to the landmark's slot of frame t (a new one, pixel NaN, if its
        pixel update was refused); the previous slot must be frame t_prev, else the history is marked
        incomplete (module docstring)."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        if len(ids) == 0:
            return
        idx = self._ensure(ids)
        ok, slot = self._slot_at(idx, float(t), create=True)
        rows = self.row[idx]
        prev = slot - 1
        prev_t = np.where(prev >= 0, self.t[rows, np.maximum(prev, 0)], np.nan)
        linked = prev_t == t_prev
        self.complete[idx[ok & ~linked]] = False
        ok &= linked
        idx, slot, rows = idx[ok], slot[ok], rows[ok]
        self.t[rows, slot] = t
        self.R[rows, slot] = R_world_cam
        self.C[rows, slot] = p_world_cam
        self.s[rows, slot] = np.asarray(scale, float).reshape(-1)[ok]
        self.s_var[rows, slot] = np.asarray(var, float).reshape(-1)[ok]
        self.count[idx] = np.maximum(self.count[idx], slot + 1)

    # -- schedule -------------------------------------------------------------------------------
    def due(self, ids) -> np.ndarray:
        """(M,) bool: complete histories that reached their next due size (first ``first_due``, then
        each doubling, the last at ``capacity``)."""
        found, idx = lookup(self.ids, np.asarray(ids, np.int64).reshape(-1))
        return found & self.complete[idx] & (self.count[idx] >= self.next_due[idx])

    def advance(self, ids) -> None:
        """Done with these landmarks' current due size: the next is the first doubling beyond their
        count (or the capacity); a full history is sealed (:meth:`seal`), its memory freed."""
        found, idx = lookup(self.ids, np.asarray(ids, np.int64).reshape(-1))
        idx = np.unique(idx[found])
        cnt, nxt = self.count[idx], self.next_due[idx].copy()
        while True:
            low = nxt <= cnt
            if not low.any():
                break
            nxt[low] *= 2
        self.next_due[idx] = np.minimum(nxt, self.capacity)
        full = cnt >= self.capacity
        if full.any():
            self.seal(self.ids[idx[full]])

    # -- reading --------------------------------------------------------------------------------
    def counts(self, ids) -> tuple[np.ndarray, np.ndarray]:
        """(slots (M,), complete (M,) bool) of ``ids``; 0 and False for unknown ones."""
        found, idx = lookup(self.ids, np.asarray(ids, np.int64).reshape(-1))
        return np.where(found, self.count[idx], 0), found & self.complete[idx]

    def gather(self, ids) -> dict:
        """The histories of ``ids`` (all known, non-empty), flattened in id order then time order:
        ``owner`` (L,) index into ``ids`` of each slot, ``starts`` and ``counts`` (M,) the first slot and the
        number of slots of each, and the slot
        fields ``t``, ``R``, ``C``, ``z``, ``s``, ``s_var``, plus ``prev`` (L,) the index of the slot before
        (−1 for a landmark's first)."""
        found, idx = lookup(self.ids, np.asarray(ids, np.int64).reshape(-1))
        if not np.all(found):
            raise InputError("ObservationHistory.gather: unknown landmark ids")
        cnt = self.count[idx]
        owner = np.repeat(np.arange(len(idx)), cnt)
        starts = np.concatenate([[0], np.cumsum(cnt)[:-1]]).astype(np.int64)
        k = np.arange(len(owner)) - starts[owner]
        rows = self.row[idx][owner]
        out = {"owner": owner, "starts": starts, "counts": cnt, "prev": np.where(k > 0, np.arange(len(owner)) - 1, -1)}
        for name in ("t", "R", "C", "z", "s", "s_var"):
            out[name] = getattr(self, name)[rows, k]
        return out
