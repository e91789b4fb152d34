"""Compiled kernels of the tracks' reference patch: the check and the drift correction (docs/derivations/tracking.md,
docs/derivations/compute.md).

:func:`reference_ncc_k` does per track, in one pass over the (2h+1)² grid and without allocating,
what :meth:`companion.core.tracks.TrackManager._warped_patches` and :func:`companion.core.tracks.zncc_patches`
do with numpy: sample the frame bilinearly (border replicated) at ``uv + A·d`` for the reference
offsets d, and correlate the samples with the reference patch (zero-mean NCC).  The in-image test
uses the grid's four corners with the reference's arithmetic, so it is the same bit for bit; the
correlation agrees with the reference to float rounding (one-pass sums in float64 against
cv2.remap in float32 and two-pass sums; tests/test_tracks.py bounds the difference).

:func:`correct_drift_k` does per track what :meth:`companion.core.tracks.TrackManager._drift_parameters` does with
numpy: the inverse-compositional Gauss–Newton re-alignment of the match to the warped reference (a shift and a scale
factor; the reference's own gradients, one bilinear sample of the frame per grid point and step, border test as the
check's) and the NCC where its last step started.  What depends on the reference alone (its normalization, gradients
and normal matrix) is computed once per reference by :func:`prepare_reference_k`, not every frame.  It agrees with the
reference to float rounding (tests/test_tracks.py).

:func:`cut_reference_k` and :func:`reference_warp_k` cut a reference patch and compute each reference's warp, what
:meth:`companion.core.tracks.TrackManager._cut_reference` and ``_reference_warp`` do with numpy (``cv2.remap`` on the
whole frame converted to float32, einsums over small arrays), per track and without allocating
(docs/derivations/compute.md bounds the differences).
"""

from __future__ import annotations

import math

import numpy as np

from companion.core import jit as _jit


@_jit.njit
def _bilinear_u8(gray, X, Y):
    """Bilinear sample of the uint8 frame at (X, Y) inside it (the right and lower taps clamped to the border)."""
    H, W = gray.shape
    x0 = int(math.floor(X))
    y0 = int(math.floor(Y))
    fx = X - x0
    fy = Y - y0
    x1 = min(x0 + 1, W - 1)
    y1 = min(y0 + 1, H - 1)
    top = (1.0 - fx) * gray[y0, x0] + fx * gray[y0, x1]
    bot = (1.0 - fx) * gray[y1, x0] + fx * gray[y1, x1]
    return (1.0 - fy) * top + fy * bot


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
                b = _bilinear_u8(gray, u + a00 * dx + a01 * dy, v + a10 * dx + a11 * dy)
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
def _template_gradients(T, m, GX, GY):
    """Central differences of the (m·m,) patch T (row-major), one-sided at its border, into GX and GY."""
    for r in range(m):
        for c in range(m):
            j = r * m + c
            if c == 0:
                GX[j] = T[j + 1] - T[j]
            elif c == m - 1:
                GX[j] = T[j] - T[j - 1]
            else:
                GX[j] = 0.5 * (T[j + 1] - T[j - 1])
            if r == 0:
                GY[j] = T[j + m] - T[j]
            elif r == m - 1:
                GY[j] = T[j] - T[j - m]
            else:
                GY[j] = 0.5 * (T[j + m] - T[j - m])


@_jit.njit
def _sample_normalized(gray, u, v, s, a00, a01, a10, a11, h, m, C):
    """Sample the uint8 frame bilinearly at u + s·A·d over the reference grid into C, normalized to zero mean and unit
    variance; False where a grid corner leaves [0, W − 1] × [0, H − 1] or the samples are flat."""
    H, W = gray.shape
    for k in range(4):  # the grid's extremes are its corners
        cx = -h if k % 2 == 0 else h
        cy = -h if k < 2 else h
        X = u + s * (a00 * cx + a01 * cy)
        Y = v + s * (a10 * cx + a11 * cy)
        if not (X >= 0 and X <= W - 1 and Y >= 0 and Y <= H - 1):
            return False
    for r in range(m):
        dy = r - h
        for c in range(m):
            dx = c - h
            C[r * m + c] = _bilinear_u8(gray, u + s * (a00 * dx + a01 * dy), v + s * (a10 * dx + a11 * dy))
    return _normalize(C)


@_jit.njit
def _normalize(V):
    """V in place to zero mean and unit variance; False (V then zero-mean only) where its σ is 1e-6 or less."""
    N = V.shape[0]
    tot = 0.0
    for j in range(N):
        tot += V[j]
    mean = tot / N
    var = 0.0
    for j in range(N):
        V[j] -= mean
        var += V[j] * V[j]
    sd = math.sqrt(var / N)
    if not sd > 1e-6:
        return False
    for j in range(N):
        V[j] /= sd
    return True


@_jit.njit
def cut_reference_k(gray, uv, slots, h, ref, ok):
    """Cut the (2h+1)² reference patch of each of ``slots`` centred on its sub-pixel ``uv`` (n, 2), in the order of
    ``slots``, into ``ref[slot]`` (float32) and ``ok[slot]``: the frame sampled bilinearly at uv + d for the integer
    offsets d, rounded to grey levels (as :func:`companion.core.ncc_templates.extract_scaled_templates` at scale 1,
    the numpy reference, whose remap quantizes the sub-pixel position to 1/32 px; tests/test_tracks.py bounds the
    difference); ``ok`` False (and the patch zero) unless the patch and a one-pixel rim fit, as there."""
    H, W = gray.shape
    m = 2 * h + 1
    ext = h + 2.0
    for ii in range(slots.shape[0]):
        i = slots[ii]
        u, v = uv[ii, 0], uv[ii, 1]
        if not (u - ext >= 0 and u + ext <= W - 1 and v - ext >= 0 and v + ext <= H - 1):
            ok[i] = False
            for r in range(m):
                for c in range(m):
                    ref[i, r, c] = 0.0
            continue
        ok[i] = True
        for r in range(m):
            for c in range(m):
                b = _bilinear_u8(gray, u + (c - h), v + (r - h))
                ref[i, r, c] = np.float32(min(max(np.rint(b), 0.0), 255.0))


@_jit.njit
def reference_warp_k(R_now, has_R, ref_R, ref_R_ok, ref_uv, ref_scale, slots, fx, fy, cx, cy, A):
    """Fill ``A`` (n, 2, 2), in the order of ``slots``, with each reference's warp S·J
    (:meth:`companion.core.tracks.TrackManager._reference_warp`, its numpy reference, to float rounding): S =
    ``ref_scale[slot]`` and J the Jacobian at ``ref_uv[slot]`` of the infinite homography of the rotation
    R = R_nowᵀ ``ref_R[slot]`` (J = I where either attitude is unknown, ``has_R`` or ``ref_R_ok[slot]`` False, or
    where the point has turned behind the camera; an element of J that is not finite stays the identity's)."""
    rxy = fx / fy
    ryx = fy / fx
    R = np.empty((3, 3))
    for ii in range(slots.shape[0]):
        i = slots[ii]
        j00, j01, j10, j11 = 1.0, 0.0, 0.0, 1.0
        if has_R and ref_R_ok[i]:
            for a in range(3):
                for c in range(3):
                    R[a, c] = R_now[0, a] * ref_R[i, 0, c] + R_now[1, a] * ref_R[i, 1, c] + R_now[2, a] * ref_R[i, 2, c]
            x0 = (ref_uv[i, 0] - cx) / fx
            x1 = (ref_uv[i, 1] - cy) / fy
            q0 = R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2]
            q1 = R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2]
            q2 = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2]
            if q2 > 1e-6:
                d = q2 * q2
                p00 = (R[0, 0] * q2 - q0 * R[2, 0]) / d
                p01 = (R[0, 1] * q2 - q0 * R[2, 1]) / d * rxy
                p10 = (R[1, 0] * q2 - q1 * R[2, 0]) / d * ryx
                p11 = (R[1, 1] * q2 - q1 * R[2, 1]) / d
                if math.isfinite(p00):
                    j00 = p00
                if math.isfinite(p01):
                    j01 = p01
                if math.isfinite(p10):
                    j10 = p10
                if math.isfinite(p11):
                    j11 = p11
        S = ref_scale[i]
        A[ii, 0, 0] = j00 * S
        A[ii, 0, 1] = j01 * S
        A[ii, 1, 0] = j10 * S
        A[ii, 1, 1] = j11 * S


@_jit.njit
def prepare_reference_k(ref, slots, T, G, Nc, fit):
    """What the drift correction needs of a reference patch and what changes only when it is cut: for each of
    ``slots``, ``T[slot]`` (m·m,) the reference ``ref[slot]`` (m, m) float32 at zero mean and unit variance, ``G[slot]``
    (3, m·m) its steepest-descent images (∂T/∂x, ∂T/∂y, and x·∂T/∂x + y·∂T/∂y for the scale; central differences,
    one-sided at the border), ``Nc[slot]`` (7,) the cofactors c00, c01, c02, c11, c12, c22 and the determinant of its
    3 × 3 normal matrix, and ``fit[slot]`` whether it can be aligned (not flat, the 2 × 2 shift block not an edge's:
    λmin/λmax ≥ 0.05, the 3 × 3 matrix not singular)."""
    m = ref.shape[1]
    h = (m - 1) // 2
    N = m * m
    for ii in range(slots.shape[0]):
        i = slots[ii]
        fit[i] = False
        Ti = T[i]
        for r in range(m):
            for c in range(m):
                Ti[r * m + c] = np.float64(ref[i, r, c])
        if not _normalize(Ti):
            continue
        GX = G[i, 0]
        GY = G[i, 1]
        G2 = G[i, 2]
        _template_gradients(Ti, m, GX, GY)
        n00 = n01 = n02 = n11 = n12 = n22 = 0.0
        for r in range(m):
            for c in range(m):
                j = r * m + c
                g2 = GX[j] * (c - h) + GY[j] * (r - h)
                G2[j] = g2
                n00 += GX[j] * GX[j]
                n01 += GX[j] * GY[j]
                n02 += GX[j] * g2
                n11 += GY[j] * GY[j]
                n12 += GY[j] * g2
                n22 += g2 * g2
        det2 = n00 * n11 - n01 * n01
        half = (n00 + n11) / 2
        disc = math.sqrt(max(half * half - det2, 0.0))
        if not (det2 > 1e-12 and half - disc >= 0.05 * max(half + disc, 1e-12)):
            continue
        c00 = n11 * n22 - n12 * n12
        c01 = n02 * n12 - n01 * n22
        c02 = n01 * n12 - n02 * n11
        c11 = n00 * n22 - n02 * n02
        c12 = n01 * n02 - n00 * n12
        c22 = n00 * n11 - n01 * n01
        det3 = n00 * c00 + n01 * c01 + n02 * c02
        if not abs(det3) > 1e-12:
            continue
        Nc[i, 0], Nc[i, 1], Nc[i, 2], Nc[i, 3], Nc[i, 4], Nc[i, 5], Nc[i, 6] = c00, c01, c02, c11, c12, c22, det3
        fit[i] = True


@_jit.njit
def correct_drift_k(gray, T, G, Nc, fit, slots, uv, A, max_px, max_scale, iterations, par, ncc):
    """Fill ``par`` (n, 3) = (Δx, Δy, s) and ``ncc`` (n,) for the n = len(``slots``) tracks (the inverse-compositional
    Gauss–Newton of :meth:`companion.core.tracks.TrackManager._drift_parameters`): ``gray`` (H, W) uint8 frame; ``T``,
    ``G``, ``Nc``, ``fit`` the references as :func:`prepare_reference_k` left them, indexed by slot; ``uv`` (n, 2)
    matched pixels and ``A`` (n, 2, 2) the reference warps, in the order of ``slots``; ``iterations`` steps (one sample
    of the frame each) and the zero-mean NCC of the reference with the frame where the last step started.  A track that
    fails (a reference that does not fit, a flat frame patch, a grid leaving the frame, a shift beyond ``max_px`` or a
    scale beyond 1 ± ``max_scale``) gets (0, 0, 1) and NaN."""
    m = int(round(math.sqrt(T.shape[1])))
    h = (m - 1) // 2
    N = m * m
    C = np.empty(N)
    for ii in range(slots.shape[0]):
        i = slots[ii]
        a00, a01, a10, a11 = A[ii, 0, 0], A[ii, 0, 1], A[ii, 1, 0], A[ii, 1, 1]
        par[ii, 0], par[ii, 1], par[ii, 2] = 0.0, 0.0, 1.0
        ncc[ii] = np.nan
        if not fit[i]:
            continue
        Ti = T[i]
        GX = G[i, 0]
        GY = G[i, 1]
        G2 = G[i, 2]
        c00, c01, c02, c11, c12, c22, det3 = Nc[i, 0], Nc[i, 1], Nc[i, 2], Nc[i, 3], Nc[i, 4], Nc[i, 5], Nc[i, 6]
        dx_, dy_, s = 0.0, 0.0, 1.0
        good = True
        acc = 0.0
        for _ in range(iterations):
            if not _sample_normalized(gray, uv[ii, 0] + dx_, uv[ii, 1] + dy_, s, a00, a01, a10, a11, h, m, C):
                good = False
                break
            e0 = e1 = e2 = 0.0
            acc = 0.0
            for j in range(N):
                e = C[j] - Ti[j]
                acc += C[j] * Ti[j]
                e0 += GX[j] * e
                e1 += GY[j] * e
                e2 += G2[j] * e
            q0 = (c00 * e0 + c01 * e1 + c02 * e2) / det3
            q1 = (c01 * e0 + c11 * e1 + c12 * e2) / det3
            q2 = (c02 * e0 + c12 * e1 + c22 * e2) / det3
            k = s / (1.0 + q2)  # compose with the inverse of the reference's warp d → (1 + q2)·d + q
            dx_ -= k * (a00 * q0 + a01 * q1)
            dy_ -= k * (a10 * q0 + a11 * q1)
            s = k
            if not (math.isfinite(dx_) and math.isfinite(dy_) and math.isfinite(s)
                    and math.hypot(dx_, dy_) <= max_px and abs(s - 1.0) <= max_scale):
                good = False
                break
        if not good:
            continue
        par[ii, 0], par[ii, 1], par[ii, 2] = dx_, dy_, s
        ncc[ii] = acc / N


@_jit.register_warmup
def _warm_up() -> None:
    """Compile every kernel of this module on a tiny frame."""
    gray = np.zeros((20, 20), np.uint8)
    gray[::2] = 200
    ref = np.ones((1, 5, 5), np.float32)
    reference_ncc_k(gray, ref, np.array([[10.0, 10.0]]), np.eye(2)[None], np.zeros(1), np.zeros(1, np.bool_))
    slots = np.zeros(1, np.int64)
    T, G, Nc, fit = np.zeros((1, 25)), np.zeros((1, 3, 25)), np.zeros((1, 7)), np.zeros(1, np.bool_)
    ok = np.zeros(1, np.bool_)
    cut_reference_k(gray, np.array([[10.0, 10.0]]), slots, 2, ref, ok)
    reference_warp_k(np.eye(3), True, np.eye(3)[None], ok, np.array([[10.0, 10.0]]), np.ones(1), slots, 100.0, 100.0,
                     10.0, 10.0, np.zeros((1, 2, 2)))
    prepare_reference_k(ref, slots, T, G, Nc, fit)
    correct_drift_k(gray, T, G, Nc, fit, slots, np.array([[10.0, 10.0]]), np.eye(2)[None], 1.0, 0.1, 1, np.zeros((1, 3)),
                    np.zeros(1))
