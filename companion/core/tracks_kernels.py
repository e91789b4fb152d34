"""Compiled kernels of the tracks' reference patch: the check and the drift correction (docs/derivations/tracking.md,
docs/derivations/compute.md).

:func:`reference_ncc_k` does per track, in one pass over the (2h+1)² grid and without allocating,
what :meth:`companion.core.tracks.TrackManager._warped_patches` and :func:`companion.core.tracks.zncc_patches`
do with numpy: sample the frame bilinearly (border replicated) at ``uv + A·d`` for the reference
offsets d, and correlate the samples with the reference patch (zero-mean NCC).  The in-image test
uses the grid's four corners with the reference's arithmetic, so it is the same bit for bit; the
correlation agrees with the reference to float rounding (one-pass sums in float64 against
cv2.remap in float32 and two-pass sums; tests/test_tracks.py bounds the difference).

:func:`correct_drift_k` does per track what :meth:`companion.core.tracks.TrackManager._correct_drift` does with
numpy before its acceptance test: the Gauss–Newton re-alignment of the match to the warped reference (a shift and a
scale factor), sampling the frame and its gradient images bilinearly with the same in-image test.  It agrees with
the reference to float rounding (tests/test_tracks.py).
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


@_jit.njit
def _bilinear_at(img, X, Y):
    """Bilinear sample of float32 ``img`` at (X, Y) inside it (x0 + 1, y0 + 1 clamped to the border)."""
    H, W = img.shape
    x0 = int(math.floor(X))
    y0 = int(math.floor(Y))
    fx = X - x0
    fy = Y - y0
    x1 = min(x0 + 1, W - 1)
    y1 = min(y0 + 1, H - 1)
    top = (1.0 - fx) * img[y0, x0] + fx * img[y0, x1]
    bot = (1.0 - fx) * img[y1, x0] + fx * img[y1, x1]
    return (1.0 - fy) * top + fy * bot


@_jit.njit
def correct_drift_k(img, gx, gy, ref, uv, A, max_px, max_scale, iterations, par, ok):
    """Fill ``par`` (n, 3) = (Δx, Δy, ε) and ``ok`` (n,) bool for the n tracks: ``img``, ``gx``, ``gy``
    (H, W) float32 frame and its gradient images, ``ref`` (n, m, m) float32 reference patches, ``uv``
    (n, 2) matched pixels, ``A`` (n, 2, 2) the reference warps; ``iterations`` Gauss–Newton steps;
    a track fails (ok False, par 0) on a flat patch, an edge's normal matrix, a sample outside
    [1, W − 2] × [1, H − 2], a shift beyond ``max_px`` or a scale factor beyond ``max_scale``."""
    n, m = ref.shape[0], ref.shape[1]
    h = (m - 1) // 2
    H, W = img.shape
    N = m * m
    T = np.empty(N)
    C = np.empty(N)
    GX = np.empty(N)
    GY = np.empty(N)
    AX = np.empty(N)
    AY = np.empty(N)
    for i in range(n):
        a00, a01, a10, a11 = A[i, 0, 0], A[i, 0, 1], A[i, 1, 0], A[i, 1, 1]
        st = 0.0
        for r in range(m):
            for c in range(m):
                j = r * m + c
                T[j] = np.float64(ref[i, r, c])
                st += T[j]
                AX[j] = a00 * (c - h) + a01 * (r - h)
                AY[j] = a10 * (c - h) + a11 * (r - h)
        mt = st / N
        vt = 0.0
        for j in range(N):
            T[j] -= mt
            vt += T[j] * T[j]
        sT = math.sqrt(vt / N)
        p0 = 0.0
        p1 = 0.0
        p2 = 0.0
        good = sT > 1e-6
        if good:
            for j in range(N):
                T[j] /= sT
        it = 0
        while good and it < iterations:
            it += 1
            sc = 1.0 + p2
            u = uv[i, 0] + p0
            v = uv[i, 1] + p1
            for k in range(4):  # the grid's extremes are its corners
                cx = -h if k % 2 == 0 else h
                cy = -h if k < 2 else h
                X = u + sc * (a00 * cx + a01 * cy)
                Y = v + sc * (a10 * cx + a11 * cy)
                if not (X >= 1 and X <= W - 2 and Y >= 1 and Y <= H - 2):
                    good = False
            if not good:
                break
            sc_ = 0.0
            for j in range(N):
                X = u + sc * AX[j]
                Y = v + sc * AY[j]
                C[j] = _bilinear_at(img, X, Y)
                GX[j] = _bilinear_at(gx, X, Y)
                GY[j] = _bilinear_at(gy, X, Y)
                sc_ += C[j]
            mc = sc_ / N
            vc = 0.0
            for j in range(N):
                C[j] -= mc
                vc += C[j] * C[j]
            sC = math.sqrt(vc / N)
            if not sC > 1e-6:
                good = False
                break
            inv = 1.0 / sC
            n00 = n01 = n02 = n11 = n12 = n22 = 0.0
            e0 = e1 = e2 = 0.0
            for j in range(N):
                rr = C[j] * inv - T[j]
                g0 = GX[j] * inv
                g1 = GY[j] * inv
                g2 = g0 * AX[j] + g1 * AY[j]
                n00 += g0 * g0
                n01 += g0 * g1
                n02 += g0 * g2
                n11 += g1 * g1
                n12 += g1 * g2
                n22 += g2 * g2
                e0 += g0 * rr
                e1 += g1 * rr
                e2 += g2 * rr
            det2 = n00 * n11 - n01 * n01
            half = (n00 + n11) / 2
            disc = math.sqrt(max(half * half - det2, 0.0))
            if not (det2 > 1e-12 and half - disc >= 0.05 * max(half + disc, 1e-12)):
                good = False
                break
            c00 = n11 * n22 - n12 * n12
            c01 = n02 * n12 - n01 * n22
            c02 = n01 * n12 - n02 * n11
            c11 = n00 * n22 - n02 * n02
            c12 = n01 * n02 - n00 * n12
            c22 = n00 * n11 - n01 * n01
            det3 = n00 * c00 + n01 * c01 + n02 * c02
            if not abs(det3) > 1e-12:
                good = False
                break
            p0 -= (c00 * e0 + c01 * e1 + c02 * e2) / det3
            p1 -= (c01 * e0 + c11 * e1 + c12 * e2) / det3
            p2 -= (c02 * e0 + c12 * e1 + c22 * e2) / det3
            if not (math.isfinite(p0) and math.isfinite(p1) and math.isfinite(p2)
                    and math.hypot(p0, p1) <= max_px and abs(p2) <= max_scale):
                good = False
        ok[i] = good
        if good:
            par[i, 0], par[i, 1], par[i, 2] = p0, p1, p2
        else:
            par[i, 0], par[i, 1], par[i, 2] = 0.0, 0.0, 0.0


@_jit.register_warmup
def _warm_up() -> None:
    """Compile :func:`reference_ncc_k` and :func:`correct_drift_k` on a tiny frame."""
    gray = np.zeros((20, 20), np.uint8)
    gray[::2] = 200
    ref = np.ones((1, 5, 5), np.float32)
    reference_ncc_k(gray, ref, np.array([[10.0, 10.0]]), np.eye(2)[None], np.zeros(1), np.zeros(1, np.bool_))
    img = gray.astype(np.float32)
    correct_drift_k(img, img, img, ref, np.array([[10.0, 10.0]]), np.eye(2)[None], 1.0, 0.1, 1, np.zeros((1, 3)),
                    np.zeros(1, np.bool_))
