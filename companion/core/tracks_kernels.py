"""Compiled kernel of the tracks' reference-patch check (docs/derivations/tracking.md, docs/derivations/compute.md).

:func:`reference_ncc_k` does per track, in one pass over the (2h+1)² grid and without allocating,
what :meth:`companion.core.tracks.TrackManager._warped_patches` and :func:`companion.core.tracks.zncc_patches`
do with numpy: sample the frame bilinearly (border replicated) at ``uv + A·d`` for the reference
offsets d, and correlate the samples with the reference patch (zero-mean NCC).  The in-image test
uses the grid's four corners with the reference's arithmetic, so it is the same bit for bit; the
correlation agrees with the reference to float rounding (one-pass sums in float64 against
cv2.remap in float32 and two-pass sums; tests/test_tracks.py bounds the difference).
"""

from __future__ import annotations

import math

import numpy as np

from companion.core import jit as _jit


@_jit.njit
def reference_ncc_k(gray, ref, uv, A, ncc, inside):
    """Fill ``ncc`` (n,) and ``inside`` (n,) bool for the n tracks: ``gray`` (H, W) uint8 frame,
    ``ref`` (n, m, m) float32 reference patches (m = 2h+1), ``uv`` (n, 2) current pixels, ``A``
    (n, 2, 2) the warp of a reference offset (S·J).  NaN where the patch does not fit or either
    side is flat (variance product ≤ 1e-12 in grey levels⁴, as the reference's 1e-6 on its root)."""
    n, m = ref.shape[0], ref.shape[1]
    h = (m - 1) // 2
    H, W = gray.shape
    N = m * m
    for i in range(n):
        a00, a01, a10, a11 = A[i, 0, 0], A[i, 0, 1], A[i, 1, 0], A[i, 1, 1]
        u, v = uv[i, 0], uv[i, 1]
        ok = True
        for k in range(4):
            cx = -h if k % 2 == 0 else h
            cy = -h if k < 2 else h
            X = u + a00 * cx + a01 * cy
            Y = v + a10 * cx + a11 * cy
            if not (X >= 0 and X <= W - 1 and Y >= 0 and Y <= H - 1):
                ok = False
        inside[i] = ok
        if not ok:
            ncc[i] = np.nan
            continue
        sa = 0.0
        sb = 0.0
        saa = 0.0
        sbb = 0.0
        sab = 0.0
        for r in range(m):
            dy = r - h
            for c in range(m):
                dx = c - h
                X = u + a00 * dx + a01 * dy
                Y = v + a10 * dx + a11 * dy
                x0 = int(math.floor(X))
                y0 = int(math.floor(Y))
                fx = X - x0
                fy = Y - y0
                x1 = min(x0 + 1, W - 1)
                y1 = min(y0 + 1, H - 1)
                top = (1.0 - fx) * gray[y0, x0] + fx * gray[y0, x1]
                bot = (1.0 - fx) * gray[y1, x0] + fx * gray[y1, x1]
                b = (1.0 - fy) * top + fy * bot
                a = np.float64(ref[i, r, c])
                sa += a
                sb += b
                saa += a * a
                sbb += b * b
                sab += a * b
        va = saa - sa * sa / N
        vb = sbb - sb * sb / N
        den2 = va * vb
        if den2 > 1e-12:
            ncc[i] = (sab - sa * sb / N) / math.sqrt(den2)
        else:
            ncc[i] = np.nan


@_jit.register_warmup
def _warm_up() -> None:
    """Compile :func:`reference_ncc_k` on a tiny frame."""
    gray = np.zeros((20, 20), np.uint8)
    gray[::2] = 200
    ref = np.ones((1, 5, 5), np.float32)
    reference_ncc_k(gray, ref, np.array([[10.0, 10.0]]), np.eye(2)[None], np.zeros(1), np.zeros(1, np.bool_))
