"""Id → row lookup shared by the per-landmark filter banks (ids kept sorted ascending)."""

from __future__ import annotations

import numpy as np

from companion.errors import InputError


def lookup(sorted_ids: np.ndarray, ids) -> tuple[np.ndarray, np.ndarray]:
    """(found (M,) bool, rows (M,) int) of ``ids`` in the ascending array ``sorted_ids``."""
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    if len(sorted_ids) == 0:
        return np.zeros(len(ids), bool), np.zeros(len(ids), np.int64)
    rows = np.minimum(np.searchsorted(sorted_ids, ids), len(sorted_ids) - 1)
    return sorted_ids[rows] == ids, rows


def rows_or_raise(sorted_ids: np.ndarray, ids, what: str) -> np.ndarray:
    """Rows of ``ids``; InputError naming (up to ten of) the ids that are not present."""
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    found, rows = lookup(sorted_ids, ids)
    if not np.all(found):
        raise InputError(f"{what}: unknown landmark ids {ids[~found][:10].tolist()}")
    return rows
