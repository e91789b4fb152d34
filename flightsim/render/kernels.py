"""Compiled per-pixel loops of the renderer: the same float32 arithmetic as the numpy they replace, bit for bit.

Each function here has two bodies: the numpy *reference* (the form the renderer's docstrings
describe, several whole-array passes) and a loop *kernel* compiled by numba
(:mod:`companion.core.jit`) that does, per pixel and in one pass, the same IEEE float32 operations
in the same order — no fused multiply-add (numba contracts nothing without ``fastmath``), no
reassociation, minimum and clamp with numpy's NaN propagation — so the two give the same bits
(tests/test_flightsim_render.py compares them on random and real inputs; the simulator's frames
are byte-identical with or without ``COMPANION_KERNELS=numpy``).  Which body runs is
:data:`companion.core.jit.ENABLED`, decided once per process.

The kernels are compiled for C-contiguous arrays (row slices are indexed inside the kernels) when
this module is imported (cached on disk by numba after the first time), not in the middle of the
first frame.
"""

from __future__ import annotations

import numpy as np

from companion.core import jit as _jit

_F32 = np.float32


# ---------------------------------------------------------------------- ground: one mip level
def _ground_level_ref(acc: np.ndarray, lam: np.ndarray, tex: np.ndarray | None, L: int, grey) -> None:
    w = lam - _F32(L)  # w = max(1 − |λ − L|, 0), in place
    np.abs(w, out=w)
    np.subtract(_F32(1.0), w, out=w)
    np.maximum(w, _F32(0.0), out=w)
    w *= grey if tex is None else tex
    acc += w


@_jit.njit(signature_or_function="void(float32[:, ::1], float32[:, ::1], uint8[:, ::1], float32, int64, int64, int64, int64)")
def _ground_level_k(acc, lam, tex, Lf, r0, r1, c0, c1):  # pragma: no cover - compiled
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for y in range(r0, r1):  # row slices indexed from 0: the inner loop vectorizes
        a = acc[y, c0:c1]
        lm = lam[y, c0:c1]
        t = tex[y - r0]
        for x in range(c1 - c0):
            wt = one - abs(lm[x] - Lf)
            if wt < zero:  # np.maximum(wt, 0) (a NaN stays NaN)
                wt = zero
            a[x] += wt * np.float32(t[x])


@_jit.njit(signature_or_function="void(float32[:, ::1], float32[:, ::1], float32, float32, int64, int64, int64, int64)")
def _ground_flat_k(acc, lam, Lf, grey, r0, r1, c0, c1):  # pragma: no cover - compiled
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for y in range(r0, r1):
        a = acc[y, c0:c1]
        lm = lam[y, c0:c1]
        for x in range(c1 - c0):
            wt = one - abs(lm[x] - Lf)
            if wt < zero:
                wt = zero
            a[x] += wt * grey


def ground_level(acc: np.ndarray, lam: np.ndarray, band: tuple[int, int, int, int], tex: np.ndarray | None, L: int,
                 grey=None) -> None:
    """``acc += max(1 − |λ − L|, 0) · texture`` (float32, in place) on the rows ``r0:r1`` and columns
    ``c0:c1`` of ``band``: the trilinear weight of mip level ``L`` at each pixel times the level's
    warped texture ``tex`` (uint8, the band's shape), or times the float32 ``grey`` when ``tex`` is
    None (a level flat at its mean).  ``lam`` (float32, the shape of ``acc``) is the per-pixel
    level of detail; ``acc`` ≥ 0 (a sum of such terms).  ``acc`` and ``lam`` are C-contiguous."""
    r0, r1, c0, c1 = band
    if not _jit.ENABLED:
        _ground_level_ref(acc[r0:r1, c0:c1], lam[r0:r1, c0:c1], tex, L, grey)
    elif tex is None:
        _ground_flat_k(acc, lam, _F32(L), _F32(grey), r0, r1, c0, c1)
    else:
        _ground_level_k(acc, lam, np.ascontiguousarray(tex), _F32(L), r0, r1, c0, c1)


# ---------------------------------------------------------------------- solids: hull coverage
def _coverage_ref(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    w, h = rows.shape[1], cols.shape[1]
    if w * h * len(rows) <= 60000:
        m = np.min(rows[:, None, :] + cols[:, :, None], axis=0)
    else:
        m = rows[0][None, :] + cols[0][:, None]
        for i in range(1, len(rows)):
            np.minimum(m, rows[i][None, :] + cols[i][:, None], out=m)
    m += _F32(0.5)
    np.minimum(m, _F32(1.0), out=m)
    return np.maximum(m, _F32(0.0), out=m)


@_jit.njit(signature_or_function="void(float32[:, ::1], float32[:, ::1], float32[:, ::1])")
def _coverage_k(rows, cols, out):  # pragma: no cover - compiled
    n, w = rows.shape
    h = cols.shape[1]
    half = np.float32(0.5)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for y in range(h):  # edge by edge along each row: the inner loops run over contiguous memory and vectorize
        o = out[y]
        r = rows[0]
        c = cols[0, y]
        for x in range(w):
            o[x] = r[x] + c
        for i in range(1, n):
            r = rows[i]
            c = cols[i, y]
            for x in range(w):
                v = r[x] + c
                if v < o[x] or v != v:  # np.minimum: the smaller, NaN if either is NaN
                    o[x] = v
        for x in range(w):
            m = o[x] + half
            if m > one:  # np.minimum(m, 1) and np.maximum(m, 0), NaN kept
                m = one
            if m < zero:
                m = zero
            o[x] = m


def coverage(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """α = clamp(0.5 + minᵢ (rows[i][x] + cols[i][y]), 0, 1) as a new (h, w) float32 array:
    ``rows`` (n, w) and ``cols`` (n, h) float32 are the signed distances to the n edges of a
    convex polygon split into their column and row parts (:meth:`Solids._coverage`)."""
    if not _jit.ENABLED:
        return _coverage_ref(rows, cols)
    out = np.empty((cols.shape[1], rows.shape[1]), _F32)
    _coverage_k(np.ascontiguousarray(rows), np.ascontiguousarray(cols), out)
    return out
