"""Compiled kernels of the NCC matcher (docs/derivations/compute.md; seed 004 eq. 13–14).

Loop forms of the numpy reference in :mod:`companion.core.ncc` (and :mod:`~companion.core.ncc_templates`,
:mod:`~companion.core.ncc_scale`), one pass per point instead of a few dozen array operations per
frame.  Each kernel states which reference function it replaces;
the tests compare the two on the same inputs (float rounding only: scores to ~1e-4 — float32
dot products summed in another order than OpenCV's / einsum's —, scale fits to ~1e-5).

* :func:`template_stats` — grey-level variance and structure-tensor λmin/λmax of each template
  (reference: the variance in ``match_templates`` and :func:`~companion.core.ncc_templates.template_eigen_ratio`).
* :func:`score_peaks` — eq. 13 over each point's search window, the best cell (eq. 14), its four
  neighbours and the second-peak test (reference: ``_score_group`` + ``_ambiguous``).
* :func:`scale_fit` — the inverse-compositional Gauss–Newton scale + translation fit of
  :func:`~companion.core.ncc_scale.estimate_scale` (docs/derivations/looming.md).
"""

from __future__ import annotations

import math

import numpy as np

from companion.core.jit import njit, register_warmup

_EMPTY = np.float32(-2.0)  # sentinel of cells not searched, as in companion.core.ncc


@njit
def template_stats(templates):
    """Per template (N, T+2, T+2) uint8 (matched patch plus 1-px rim): variance of the inner T×T patch
    (grey levels², population) and λmin/λmax of its structure tensor from central differences (rim
    included), 0 for a flat patch.  Same quantities as the reference, in float64."""
    n, tr, _ = templates.shape
    t = tr - 2
    var = np.empty(n)
    ratio = np.empty(n)
    npx = t * t
    for k in range(n):
        s1 = 0.0
        s2 = 0.0
        a = 0.0
        b = 0.0
        c = 0.0
        for i in range(1, tr - 1):
            for j in range(1, tr - 1):
                v = float(templates[k, i, j])
                s1 += v
                s2 += v * v
                gx = float(templates[k, i, j + 1]) - float(templates[k, i, j - 1])
                gy = float(templates[k, i + 1, j]) - float(templates[k, i - 1, j])
                a += gx * gx
                b += gx * gy
                c += gy * gy
        mean = s1 / npx
        var[k] = s2 / npx - mean * mean
        half_tr = 0.5 * (a + c)
        disc = math.sqrt(max(0.25 * (a - c) ** 2 + b * b, 0.0))
        lmax = half_tr + disc
        lmin = max(half_tr - disc, 0.0)
        ratio[k] = lmin / lmax if lmax > 0 else 0.0
    return var, ratio


@njit
def score_peaks(img, templates, c, s, lo, hi, margin, min_sep):
    """Eq. 13 for every template centre of each point's window, then the peak and its tests.

    ``img`` (H, W) current frame (uint8; converted to float32 as each window is copied); ``templates`` (N, T+2, T+2) uint8 (the inner T×T patch is
    matched); ``c`` (N, 2) int64 window centres (u, v); ``s`` (N,) search half-sizes; ``lo``/``hi``
    (N, 2) the window clipped to the image (template centres, inclusive).  A point's block is the
    (2s+1)² cells around ``c``; cells outside [lo, hi] are not searched (the sentinel −2).

    Returns per point: ``bi``, ``bj`` (block row / column of the best cell; ties: first in row-major
    order, like ``np.argmax``), ``best`` score, ``nbrs`` (4, N) scores left, right, up, down of the
    best (the sentinel outside the block or not searched) and ``ambiguous`` — a local maximum (3×3,
    ties allowed) scoring ≥ best − ``margin`` at least ``min_sep`` cells from the best (the
    reference's ``_ambiguous``).  Flat windows (σ·T ≤ 1e-3) score 0, like the numpy batch.
    """
    n, tr, _ = templates.shape
    t = tr - 2
    npx = t * t
    bi = np.zeros(n, np.int64)
    bj = np.zeros(n, np.int64)
    best = np.zeros(n)
    nbrs = np.full((4, n), float(_EMPTY))
    ambiguous = np.zeros(n, np.bool_)
    f = np.empty((t, t), np.float32)
    smax = 0
    for k in range(n):
        smax = max(smax, s[k])
    mmax = 2 * smax + 1
    block = np.empty((mmax, mmax), np.float32)
    region = np.empty((mmax + t) * (mmax + t), np.float32)
    acc = np.empty((mmax + t) * (mmax + t), np.float32)
    colsum = np.empty(mmax + t, np.float64)
    colsq = np.empty(mmax + t, np.float64)
    sep2 = min_sep * min_sep
    for k in range(n):
        m = 2 * s[k] + 1
        ox = c[k, 0] - s[k]  # block origin: template centre of cell (0, 0)
        oy = c[k, 1] - s[k]
        block[:m, :m] = _EMPTY
        # zero-mean, unit-norm template f̂ (Σ f̂ = 0 removes ḡ from the numerator of eq. 13)
        mean = 0.0
        for i in range(t):
            for j in range(t):
                mean += float(templates[k, i + 1, j + 1])
        mean /= npx
        nf = 0.0
        for i in range(t):
            for j in range(t):
                v = float(templates[k, i + 1, j + 1]) - mean
                nf += v * v
        nf = math.sqrt(nf)
        if nf <= 0.0:
            nf = 1.0
        for i in range(t):
            for j in range(t):
                f[i, j] = np.float32((float(templates[k, i + 1, j + 1]) - mean) / nf)
        x0, x1 = lo[k, 0], hi[k, 0]
        y0, y1 = lo[k, 1], hi[k, 1]
        nx = x1 - x0 + 1
        h = t // 2
        ny = y1 - y0 + 1
        # numerator of every cell, Σ_ij f̂_ij · g(y + i − h, x + j − h).  For each template column j the
        # window's pixels shifted by j are copied into a row-major buffer of width nx (one entry per
        # cell column), so that for each template row i one contiguous loop over all ny·nx cells
        # accumulates f̂_ij times the buffer from row i on — long and unit-stride, so the compiler
        # vectorizes it (a loop over one window row, 7–20 cells, is too short).  The masks only tell
        # the compiler the indices are not negative (no wraparound test).
        nxm = nx & 0xFFFF
        P = (ny * nxm) & 0xFFFFFF
        for p in range(P):
            acc[p] = 0.0
        for j in range(t):
            for r in range(ny + t - 1):
                src = img[y0 - h + r, x0 - h + j : x0 - h + j + nxm]
                base = (r * nxm) & 0xFFFFFF
                for q in range(nxm):
                    region[base + q] = src[q]
            for i in range(t):
                fij = f[i, j]
                off = (i * nxm) & 0xFFFFFF
                for p in range(P):
                    acc[p] += fij * region[p + off]
        L = nxm
        for y in range(y0, y1 + 1):
            row0 = (y - y0) * L
            # window sums Σ g, Σ g²: column sums over the template's rows (slid down one row at a
            # time: integers in float64, exact), then a running box along the row
            ncol = nx + t - 1
            if y == y0:
                for q in range(ncol):
                    colsum[q] = 0.0
                    colsq[q] = 0.0
                for i in range(t):
                    seg = img[y + i - h, x0 - h : x0 - h + ncol]
                    for q in range(ncol):
                        v = float(seg[q])
                        colsum[q] += v
                        colsq[q] += v * v
            else:
                seg_in = img[y + h, x0 - h : x0 - h + ncol]
                seg_out = img[y - h - 1, x0 - h : x0 - h + ncol]
                for q in range(ncol):
                    a = float(seg_in[q])
                    b = float(seg_out[q])
                    colsum[q] += a - b
                    colsq[q] += a * a - b * b
            s1 = 0.0
            s2 = 0.0
            for q in range(t):
                s1 += colsum[q]
                s2 += colsq[q]
            bi_row = y - oy
            for q in range(nx):
                if q > 0:
                    s1 += colsum[q + t - 1] - colsum[q - 1]
                    s2 += colsq[q + t - 1] - colsq[q - 1]
                var = s2 - s1 * s1 / npx
                den = math.sqrt(var) if var > 0.0 else 0.0
                block[bi_row, x0 + q - ox] = np.float32(acc[row0 + q] / den) if den > 1e-3 else np.float32(0.0)
        # best cell (first in row-major order)
        b = block[0, 0]
        ib = 0
        jb = 0
        for i in range(m):
            for j in range(m):
                if block[i, j] > b:
                    b = block[i, j]
                    ib = i
                    jb = j
        bi[k] = ib
        bj[k] = jb
        best[k] = float(b)
        if jb > 0:
            nbrs[0, k] = float(block[ib, jb - 1])
        if jb < m - 1:
            nbrs[1, k] = float(block[ib, jb + 1])
        if ib > 0:
            nbrs[2, k] = float(block[ib - 1, jb])
        if ib < m - 1:
            nbrs[3, k] = float(block[ib + 1, jb])
        # second peak: a cell ≥ best − margin, far enough, that is a 3×3 local maximum
        thr = np.float32(float(b) - margin)
        amb = False
        for i in range(m):
            if amb:
                break
            for j in range(m):
                v = block[i, j]
                if v < thr or (i - ib) ** 2 + (j - jb) ** 2 < sep2:
                    continue
                is_max = True
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        if di == 0 and dj == 0:
                            continue
                        ni = i + di
                        nj = j + dj
                        if 0 <= ni < m and 0 <= nj < m and block[ni, nj] > v:
                            is_max = False
                if is_max:
                    amb = True
                    break
        ambiguous[k] = amb
    return bi, bj, best, nbrs, ambiguous


@njit
def _grid_weights(c, step, n, size, idx, w):
    """Bilinear taps of the sample coordinates c + step·(k − (n−1)/2), k = 0 … n−1, along one image axis
    of length ``size`` (float32 coordinates as cv2.remap gets them): the lower index (clamped: border
    replicated) and the weight of the upper one.  A grid's samples share their row and column taps."""
    half = (n - 1) // 2
    for k in range(n):
        x = np.float32(c) + np.float32(step) * np.float32(k - half)
        x0 = math.floor(x)
        w[k] = x - x0
        idx[k, 0] = min(max(x0, 0), size - 1)
        idx[k, 1] = min(max(x0 + 1, 0), size - 1)


@njit
def _sample_grid(img, ix, wx, iy, wy, out):
    """``out[i, j]`` = bilinear sample of ``img`` at row taps ``iy[i]`` and column taps ``ix[j]``."""
    for i in range(out.shape[0]):
        ya, yb, ay = iy[i, 0], iy[i, 1], wy[i]
        for j in range(out.shape[1]):
            xa, xb, ax = ix[j, 0], ix[j, 1], wx[j]
            i00, i01 = float(img[ya, xa]), float(img[ya, xb])
            i10, i11 = float(img[yb, xa]), float(img[yb, xb])
            top = i00 + ax * (i01 - i00)
            bot = i10 + ax * (i11 - i10)
            out[i, j] = top + ay * (bot - top)


@njit
def scale_fit(img_prev, img_cur, pts_prev, pts_cur, s0, ok_in, h, iterations, smax, sigma_factor, sigma_slope):
    """Scale change s and its σ per point (NaN where not measurable): the Gauss–Newton fit of
    :func:`companion.core.ncc_scale.estimate_scale`, one point at a time (same steps, same tests).

    ``img_prev``/``img_cur`` uint8 frames; ``pts_prev``/``pts_cur`` (N, 2); ``s0`` (N,) start;
    ``ok_in`` (N,) the points whose windows fit both frames; ``h`` the half-size of the fitted
    patch; ``smax`` = 1 + max_scale_change.
    """
    n = pts_prev.shape[0]
    t = 2 * h + 1
    npx = t * t
    out_s = np.full(n, np.nan)
    out_sig = np.full(n, np.nan)
    T = np.empty((t + 2, t + 2))
    H, W = img_cur.shape
    ix = np.empty((t, 2), np.int64)
    iy = np.empty((t, 2), np.int64)
    wx = np.empty(t)
    wy = np.empty(t)
    ix2 = np.empty((t + 2, 2), np.int64)
    iy2 = np.empty((t + 2, 2), np.int64)
    wx2 = np.empty(t + 2)
    wy2 = np.empty(t + 2)
    f = np.empty(npx)
    J = np.empty((3, npx))
    AJ = np.empty((3, npx))
    r = np.empty(npx)
    G = np.empty((t, t))
    g = G.reshape(npx)  # the same memory, row-major: pixel p = i·t + j
    xx = np.empty(npx)
    yy = np.empty(npx)
    for i in range(t):
        for j in range(t):
            xx[i * t + j] = j - h
            yy[i * t + j] = i - h
    sq = math.sqrt(npx)
    for k in range(n):
        if not ok_in[k]:
            continue
        ok = True
        # template with its rim at the exact sub-pixel point; gradients; normalization
        _grid_weights(pts_prev[k, 0], 1.0, t + 2, W, ix2, wx2)
        _grid_weights(pts_prev[k, 1], 1.0, t + 2, H, iy2, wy2)
        _sample_grid(img_prev, ix2, wx2, iy2, wy2, T)
        mean = 0.0
        for i in range(t):
            for j in range(t):
                mean += T[i + 1, j + 1]
        mean /= npx
        nf = 0.0
        for i in range(t):
            for j in range(t):
                v = T[i + 1, j + 1] - mean
                f[i * t + j] = v
                nf += v * v
        nf = math.sqrt(nf)
        if not nf > 1e-3 * sq:
            continue
        for p in range(npx):
            f[p] /= nf
        for i in range(t):
            for j in range(t):
                p = i * t + j
                gx = 0.5 * (T[i + 1, j + 2] - T[i + 1, j]) / nf
                gy = 0.5 * (T[i + 2, j + 1] - T[i, j + 1]) / nf
                J[0, p] = gx * xx[p] + gy * yy[p]
                J[1, p] = gx
                J[2, p] = gy
        # J projected off the mean and off f̂ (the directions the normalization removes)
        for a in range(3):
            mu = 0.0
            for p in range(npx):
                mu += J[a, p]
            mu /= npx
            dot = 0.0
            for p in range(npx):
                J[a, p] -= mu
                dot += J[a, p] * f[p]
            for p in range(npx):
                J[a, p] -= dot * f[p]
        A = np.zeros((3, 3))
        for a in range(3):
            for b in range(a, 3):
                acc = 0.0
                for p in range(npx):
                    acc += J[a, p] * J[b, p]
                A[a, b] = acc
                A[b, a] = acc
        c00 = A[1, 1] * A[2, 2] - A[1, 2] ** 2
        c01 = A[0, 2] * A[1, 2] - A[0, 1] * A[2, 2]
        c02 = A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]
        c11 = A[0, 0] * A[2, 2] - A[0, 2] ** 2
        c12 = A[0, 2] * A[0, 1] - A[0, 0] * A[1, 2]
        c22 = A[0, 0] * A[1, 1] - A[0, 1] ** 2
        detA = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
        tr = A[0, 0] + A[1, 1] + A[2, 2]
        if not detA > 1e-9 * max(tr, 1e-30) ** 3:
            continue
        Ai = np.empty((3, 3))
        Ai[0, 0] = c00 / detA
        Ai[0, 1] = c01 / detA
        Ai[0, 2] = c02 / detA
        Ai[1, 0] = c01 / detA
        Ai[1, 1] = c11 / detA
        Ai[1, 2] = c12 / detA
        Ai[2, 0] = c02 / detA
        Ai[2, 1] = c12 / detA
        Ai[2, 2] = c22 / detA
        for a in range(3):
            for p in range(npx):
                AJ[a, p] = Ai[a, 0] * J[0, p] + Ai[a, 1] * J[1, p] + Ai[a, 2] * J[2, p]
        s = min(max(s0[k], 1.0 / smax), smax)
        dx = 0.0
        dy = 0.0
        step_s = math.inf
        for it in range(iterations + 2):
            if it >= iterations and not (abs(step_s) >= 0.002 * s):
                break  # settled: the reference's two extra steps run only where not
            cx = pts_cur[k, 0] + dx
            cy = pts_cur[k, 1] + dy
            _grid_weights(cx, s, t, W, ix, wx)
            _grid_weights(cy, s, t, H, iy, wy)
            _sample_grid(img_cur, ix, wx, iy, wy, G)
            gm = 0.0
            for p in range(npx):
                gm += g[p]
            gm /= npx
            ng = 0.0
            for p in range(npx):
                g[p] -= gm
                ng += g[p] * g[p]
            ng = math.sqrt(ng)
            if not ng > 1e-3 * sq:
                ok = False
            if ng <= 0.0:
                ng = 1.0
            d0 = 0.0
            d1 = 0.0
            d2 = 0.0
            for p in range(npx):
                r[p] = g[p] / ng - f[p]
                d0 += AJ[0, p] * r[p]
                d1 += AJ[1, p] * r[p]
                d2 += AJ[2, p] * r[p]
            one = 1.0 + d0
            if not one > 0.5:
                ok = False
                one = 1.0
            step_s = d0
            dx = dx - s * d1 / one
            dy = dy - s * d2 / one
            s = min(max(s / one, 1.0 / smax), smax)
            if not ok:
                break
        if not ok or not abs(step_s) < 0.01 * s:
            continue
        rr = 0.0
        for p in range(npx):
            rr += r[p] * r[p]
        var_r = rr / max(npx - 5, 1)
        sig = math.hypot(sigma_factor * math.sqrt(max(var_r * Ai[0, 0], 0.0)) * s, sigma_slope * abs(s - 1.0))
        out_s[k] = s
        out_sig[k] = sig
    return out_s, out_sig


@register_warmup
def _warm() -> None:
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (40, 40)).astype(np.uint8)
    tpl = np.ascontiguousarray(np.stack([img[5:18, 5:18], img[10:23, 12:25]]))
    template_stats(tpl)
    c = np.array([[20, 20], [21, 19]], np.int64)
    s = np.array([3, 2], np.int64)
    score_peaks(img, tpl, c, s, c - s[:, None], c + s[:, None], 0.03, 3.0)
    p = np.array([[20.3, 20.1], [19.5, 21.0]])
    scale_fit(img, img, p, p, np.ones(2), np.ones(2, np.bool_), 4, 2, 1.3, 1.5, 0.06)
