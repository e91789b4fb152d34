"""Single-level Lucas–Kanade, a compiled copy of ``cv2.calcOpticalFlowPyrLK`` with ``maxLevel=0``.

``cv2.calcOpticalFlowPyrLK(prev, cur, pts, guess, winSize=(2h+1, 2h+1), maxLevel=0,
criteria=(COUNT|EPS, iterations, eps), flags=OPTFLOW_USE_INITIAL_FLOW)`` pads both frames and
takes the Scharr derivatives of the *whole* previous frame (~0.13 ms for 640×480 on one core)
before its per-point loop (~1 µs a point), while the tracker needs a few hundred 11×11 windows.
:func:`lk_track` computes the derivatives only in each point's window (plus the rims the
bilinear interpolation and the Scharr kernel read) and returns the same floats as OpenCV's x86
build, bit for bit (tests/test_lk_kernel.py compares on random textures).  What it copies from
``LKTrackerInvoker::operator()`` and ``calcScharrDeriv`` (opencv modules/video/src/lkpyramid.cpp):

* both frames are read as if padded by the window size with ``BORDER_REFLECT_101``
  (``buildOpticalFlowPyramid``); the Scharr derivatives (int16) are those of the unpadded
  previous frame with reflect-101 at its edges, and zero outside it (``BORDER_CONSTANT``);
* a point is dropped (status 0) when the top-left corner of its window, ⌊p − h⌋, lies left of /
  above −(2h+1) or at / beyond the image width / height — for the start point, every iterate,
  and the final point (the Python binding always asks for the error, whose computation repeats
  the test);
* bilinear weights in 14-bit fixed point (``cvRound`` of the float32 products); the patch I and
  the interpolated J kept ×32 (descaled by 9 bits), the derivatives descaled by 14 bits;
* the structure tensor summed in float32, scaled by 2⁻²⁰; a point is dropped when its smaller
  eigenvalue / (2·(2h+1)²) is below 1e-4 (the default ``minEigThreshold``) or the determinant is
  below FLT_EPSILON;
* the Gauss–Newton step in float32, stopping when |δ|² <= eps² (in double) or when two
  successive steps cancel (|δₖ + δₖ₋₁| < 0.01 on both axes), then moving back by δₖ/2;
* the float32 summation order of OpenCV's SSE2 loops: per window row, pixels 0–7 (8–15, …) in
  four float lanes, the rest of the row in one scalar, lanes reduced as (l0 + l2) + (l1 + l3).

That order is x86's.  OpenCV's ARM build (NEON) sums in 4-pixel blocks, reduces the lanes left
to right and may fuse multiply-adds in its scalar float code, so on a Raspberry Pi or a Jetson
the two agree to float32 rounding (~1e-6 px), not bit for bit, and a point sitting exactly on
one of the thresholds above could come out differently.

The kernel: per point, the neighbourhood is copied into flat buffers of row stride 2h + 4 and
each integer stage is one loop over them that the compiler vectorizes; the ordered float sums
are LLVM intrinsics (four lanes in one vector register — numba would keep them as four scalars);
nothing in the kernel allocates, so it runs without numba's reference counting.  When compiled
kernels are off (:data:`companion.core.jit.ENABLED` false), :func:`lk_track` calls
``cv2.calcOpticalFlowPyrLK`` itself (:func:`lk_track_cv2`).
"""

from __future__ import annotations

import numpy as np

from companion.core import jit
from companion.core.jit import njit

__all__ = ["lk_track", "lk_track_cv2"]

_W_BITS = 14
_MIN_EIG_THRESHOLD = np.float32(1e-4)  # cv2.calcOpticalFlowPyrLK's default, as OpenCV passes it: (float)1e-4
_FLT_EPSILON = np.float32(np.finfo(np.float32).eps)


@njit(inline="always", _nrt=False)
def _reflect101(i, n):
    """``cv::borderInterpolate(i, n, BORDER_REFLECT_101)``."""
    if n == 1:
        return 0
    while i < 0 or i >= n:
        if i < 0:
            i = -i
        else:
            i = 2 * n - 2 - i
    return i


@njit(inline="always", _nrt=False)
def _weights(fx, fy):
    """OpenCV's 14-bit bilinear weights of the float32 fractions (fx, fy): cvRound (to nearest,
    ties to even) of the float32 products, here by adding and removing 1.5·2^23 in float32 (exact
    for the products' range 0 .. 2^14)."""
    one = np.float32(1.0)
    s = np.float32(1 << _W_BITS)
    magic = np.float32(12582912.0)
    w00 = np.int32(((one - fx) * (one - fy) * s + magic) - magic)
    w01 = np.int32((fx * (one - fy) * s + magic) - magic)
    w10 = np.int32(((one - fx) * fy * s + magic) - magic)
    w11 = np.int32((1 << _W_BITS) - w00 - w01 - w10)
    return w00, w01, w10, w11


@njit(inline="always", _nrt=False)
def _round32(n):
    return (n + 31) // 32 * 32


@njit(inline="always", _nrt=False)
def _sizes(h):
    """Flat buffer lengths for window half-size h: the Scharr loop (rows win+1), the window loops
    (rows win), each a multiple of 32, and the patch buffers (the longest loop plus the farthest
    neighbour it reads, plus slack for the 16-byte row copies)."""
    win = 2 * h + 1
    S = win + 3
    nd = _round32((win + 1) * S)
    return nd, _round32(win * S), nd + 2 * S + 64


def _workspace(h):
    """The kernel's scratch buffers (uint8, int16, int32) for window half-size h."""
    nd, nw, nb = _sizes(h)
    return np.zeros(2 * nb, np.uint8), np.zeros(4 * nb, np.int16), np.zeros(5 * nw, np.int32)


def _ordered_sum(rows, win, S, n_simd):
    """OpenCV's float32 sum of one window: ``rows(o)`` gives the (lane, term) pairs and the scalar
    terms of the row starting at flat index o (integer terms, converted to float32 one by one)."""
    f = np.float32
    lanes = [f(0.0)] * 4
    tail = f(0.0)
    for y in range(win):
        lane_terms, tail_terms = rows(y * S)
        for lane, t in lane_terms:
            lanes[lane] = f(lanes[lane] + f(t))
        for t in tail_terms:
            tail = f(tail + f(t))
    return f(tail + f(f(lanes[0] + lanes[2]) + f(lanes[1] + lanes[3])))


def _sums_a_ref(U, V, win, S, n_simd):
    """Plain-Python :func:`_sums_a`: (Σ U², Σ U·V, Σ V²) summed in OpenCV's order."""

    def products(W1, W2):
        def rows(o):
            return ([(x % 4, int(W1[o + x]) * int(W2[o + x])) for x in range(n_simd)],
                    [int(W1[o + x]) * int(W2[o + x]) for x in range(n_simd, win)])

        return rows

    return tuple(_ordered_sum(products(a, b), win, S, n_simd) for a, b in ((U, U), (U, V), (V, V)))


def _sums_b_ref(V1, V2, win, S, n_simd):
    """Plain-Python :func:`_sums_b`: (Σ V1, Σ V2) summed in OpenCV's order."""

    def pairs(W):
        def rows(o):
            return ([(lane, int(W[o + x0 + lane]) + int(W[o + x0 + lane + 4]))
                     for x0 in range(0, n_simd, 8) for lane in range(4)],
                    [int(W[o + x]) for x in range(n_simd, win)])

        return rows

    return tuple(_ordered_sum(pairs(W), win, S, n_simd) for W in (V1, V2))


# --- OpenCV's float32 sums ---------------------------------------------------------------------
# OpenCV (x86, SSE2) sums each window row's first 8·k pixels in four float32 SIMD lanes and the
# rest in one scalar float, then adds scalar + ((l0 + l2) + (l1 + l3)).  Float addition is not
# associative, so to get OpenCV's floats the sums are done in that order.  Written in Python the
# compiler keeps four lanes as four scalars, so these intrinsics emit the loops themselves with
# the lanes in one vector register: a load of four int32, their conversion, a lane-wise IEEE
# float32 add (no reassociation, no fused multiply-add) — exactly OpenCV's SSE steps.
if jit.ENABLED:
    from llvmlite import ir as _ir
    from numba.core import cgutils, types
    from numba.core.extending import intrinsic as _intrinsic

    def _flat(t, dtype):
        return isinstance(t, types.Array) and t.ndim == 1 and t.layout == "C" and t.dtype == dtype

    _F1 = _ir.FloatType()
    _F4 = _ir.VectorType(_F1, 4)
    _I4 = _ir.VectorType(_ir.IntType(32), 4)

    def _load4(builder, data, idx):
        return builder.load(builder.bitcast(builder.gep(data, [idx]), _I4.as_pointer()), align=4)

    def _add4(builder, acc, ints):
        builder.store(builder.fadd(builder.load(acc), builder.sitofp(ints, _F4)), acc)

    def _add1(builder, acc, data, idx, other=None):
        v = builder.load(builder.gep(data, [idx]))
        if other is not None:
            v = builder.mul(v, builder.load(builder.gep(other, [idx])))
        builder.store(builder.fadd(builder.load(acc), builder.sitofp(v, _F1)), acc)

    def _finish(builder, acc, tail):
        v = builder.load(acc)
        lane = [builder.extract_element(v, _ir.Constant(_ir.IntType(32), i)) for i in range(4)]
        return builder.fadd(builder.load(tail), builder.fadd(builder.fadd(lane[0], lane[2]), builder.fadd(lane[1], lane[3])))

    def _setup(context, builder, arrtys, arrs, nacc):
        datas = [context.make_array(t)(context, builder, a).data for t, a in zip(arrtys, arrs)]
        accs = [cgutils.alloca_once_value(builder, _ir.Constant(_F4, [0.0] * 4)) for _ in range(nacc)]
        tails = [cgutils.alloca_once_value(builder, _ir.Constant(_F1, 0.0)) for _ in range(nacc)]
        return datas, accs, tails

    def _rows(builder, win, S, n_simd, block, scalar):
        """for y < win: block(x0) for each 8-pixel block x0 < n_simd, then scalar(x) for x in
        n_simd .. win−1 (x0, x: flat indices, row stride S)."""
        eight = _ir.Constant(win.type, 8)
        with cgutils.for_range(builder, win) as ly:
            o = builder.mul(ly.index, S)
            with cgutils.for_range(builder, builder.sdiv(n_simd, eight)) as lb:
                block(builder.add(o, builder.mul(lb.index, eight)))
            with cgutils.for_range_slice(builder, builder.add(o, n_simd), builder.add(o, win), _ir.Constant(win.type, 1)) as (x, _):
                scalar(x)

    @_intrinsic
    def _sums_a(typingctx, U, V, win, S, n_simd):
        """(Σ U², Σ U·V, Σ V²) over the window (rows of stride S) in float32 as OpenCV's
        structure-tensor loop sums them (int32 products, below 2^24 so exact as OpenCV's float
        products): per row, pixels 0–3 then 4–7 of each 8-pixel block below n_simd go to the four
        lanes, pixels n_simd .. win−1 to the scalar."""
        if not (_flat(U, types.int32) and _flat(V, types.int32)):
            return None
        sig = types.UniTuple(types.float32, 3)(U, V, win, S, n_simd)

        def codegen(context, builder, sig, args):
            (du, dv), accs, tails = _setup(context, builder, sig.args[:2], args[:2], 3)
            win, S, n_simd = args[2:]

            def block(x0):
                for half in (0, 4):
                    x = builder.add(x0, _ir.Constant(win.type, half))
                    u = _load4(builder, du, x)
                    v = _load4(builder, dv, x)
                    _add4(builder, accs[0], builder.mul(u, u))
                    _add4(builder, accs[1], builder.mul(u, v))
                    _add4(builder, accs[2], builder.mul(v, v))

            def scalar(x):
                _add1(builder, tails[0], du, x, du)
                _add1(builder, tails[1], du, x, dv)
                _add1(builder, tails[2], dv, x, dv)

            _rows(builder, win, S, n_simd, block, scalar)
            return context.make_tuple(builder, sig.return_type, [_finish(builder, a, t) for a, t in zip(accs, tails)])

        return sig, codegen

    @_intrinsic
    def _sums_b(typingctx, V1, V2, win, S, n_simd):
        """(Σ V1, Σ V2) over the window in float32 as OpenCV's Gauss–Newton loop sums them: lane l
        of a row's 8-pixel block gets the integer pair of pixels l and l + 4, pixels n_simd ..
        win−1 go to the scalar (OpenCV keeps the two sums in alternate lanes of two registers and
        adds the registers before the lanes, which comes to the same)."""
        if not (_flat(V1, types.int32) and _flat(V2, types.int32)):
            return None
        sig = types.UniTuple(types.float32, 2)(V1, V2, win, S, n_simd)

        def codegen(context, builder, sig, args):
            (d1, d2), accs, tails = _setup(context, builder, sig.args[:2], args[:2], 2)
            win, S, n_simd = args[2:]

            def block(x0):
                x4 = builder.add(x0, _ir.Constant(win.type, 4))
                _add4(builder, accs[0], builder.add(_load4(builder, d1, x0), _load4(builder, d1, x4)))
                _add4(builder, accs[1], builder.add(_load4(builder, d2, x0), _load4(builder, d2, x4)))

            def scalar(x):
                _add1(builder, tails[0], d1, x)
                _add1(builder, tails[1], d2, x)

            _rows(builder, win, S, n_simd, block, scalar)
            return context.make_tuple(builder, sig.return_type, [_finish(builder, a, t) for a, t in zip(accs, tails)])

        return sig, codegen

    @_intrinsic
    def _copy16(typingctx, src, so, dst, do):
        """dst[do : do + 16] = src[so : so + 16] (uint8 arrays) as one 16-byte move."""
        if not (_flat(src, types.uint8) and _flat(dst, types.uint8)):
            return None

        def codegen(context, builder, sig, args):
            v16 = _ir.VectorType(_ir.IntType(8), 16).as_pointer()
            sdata = context.make_array(sig.args[0])(context, builder, args[0]).data
            ddata = context.make_array(sig.args[2])(context, builder, args[2]).data
            v = builder.load(builder.bitcast(builder.gep(sdata, [args[1]]), v16), align=1)
            builder.store(v, builder.bitcast(builder.gep(ddata, [args[3]]), v16), align=1)
            return context.get_dummy_value()

        return types.none(src, so, dst, do), codegen

else:  # without numba lk_track calls OpenCV; these keep the module importable and readable
    _sums_a = _sums_a_ref
    _sums_b = _sums_b_ref

    def _copy16(src, so, dst, do):
        dst[do : do + 16] = src[so : so + 16]


@njit(inline="always", _nrt=False)
def _load_patch(img, flat, r0, c0, nr, S, out):
    """out[r·S + c] = img[r0 + r, c0 + c] for r < nr, c < S, the image extended by reflect-101.

    Inside the image the rows are copied 16 bytes at a time, in order (a row's overhang lands on
    the next row, which then overwrites it; ``out`` has slack for the last one), which reads up
    to 15 columns past c0 + S − 1: such patches count as inside only if those columns exist.
    """
    rows, cols = img.shape
    cw = 16 * ((S + 15) // 16)
    if r0 >= 0 and c0 >= 0 and r0 + nr <= rows and c0 + cw <= cols:
        for r in range(nr):
            for c in range(0, cw, 16):
                _copy16(flat, (r0 + r) * cols + c0 + c, out, r * S + c)
        return
    for r in range(nr):
        rr = _reflect101(r0 + r, rows)
        for c in range(S):
            out[r * S + c] = img[rr, _reflect101(c0 + c, cols)]


# --- vectorizable stages --------------------------------------------------------------------------
# Each is one loop over a flat buffer (window rows of stride S) in int32 arithmetic (every value is
# an exact integer, as in OpenCV's fixed-point code), wrapped in int32() so that the compiler keeps
# 32-bit lanes.  Neighbours are read at unsigned offsets from the loop index (numba then omits its
# negative-index wraparound, so the loads stay contiguous and the loop vectorizes), and each stage
# is a function of its own so that each loop is compiled, and vectorized, on its own.

@njit(_nrt=False)
def _stage_scharr(nd, S, P, T0, T1, DX, DY):
    """Scharr derivatives of the patch P: vertical pass [3 10 3] / [-1 0 1] into T0 / T1, then
    horizontal [-1 0 1] / [3 10 3] into DX / DY (int16, as OpenCV's derivative image)."""
    i16 = np.int16
    i32 = np.int32
    u = np.uint64
    s, s2, one, two = u(S), u(2 * S), u(1), u(2)
    for j in range(u(nd)):
        a = i32(P[j])
        c = i32(P[j + s2])
        T0[j] = i16(i32(a + c) * i32(3) + i32(P[j + s]) * i32(10))
        T1[j] = i16(c - a)
    for j in range(u(nd)):
        DX[j] = i16(i32(T0[j + two]) - i32(T0[j]))
        DY[j] = i16(i32(i32(T1[j + two]) + i32(T1[j])) * i32(3) + i32(T1[j + one]) * i32(10))


@njit(_nrt=False)
def _stage_window(nw, S, P, DX, DY, IW, IX, IY, w00, w01, w10, w11):
    """The patch at the point: I (×32, descaled by 9 bits) from P one row and column in, and the
    derivatives (descaled by 14 bits), bilinear in 14-bit fixed point.  The weights are below 2^15,
    which the masks tell the compiler (it then multiplies 16-bit pairs)."""
    i32 = np.int32
    u = np.uint64
    m15 = i32(0x7FFF)
    w00 = i32(w00 & m15)
    w01 = i32(w01 & m15)
    w10 = i32(w10 & m15)
    w11 = i32(w11 & m15)
    r8 = i32(1 << 8)
    r13 = i32(1 << 13)
    one, s, s1, s2, s21, s22 = u(1), u(S), u(S + 1), u(S + 2), u(2 * S + 1), u(2 * S + 2)
    for j in range(u(nw)):
        v = i32(i32(i32(P[j + s1]) * w00 + i32(P[j + s2]) * w01) + i32(i32(P[j + s21]) * w10 + i32(P[j + s22]) * w11))
        IW[j] = i32(i32(v + r8) >> 9)
    for j in range(u(nw)):
        g = i32(i32(i32(DX[j]) * w00 + i32(DX[j + one]) * w01) + i32(i32(DX[j + s]) * w10 + i32(DX[j + s1]) * w11))
        IX[j] = i32(i32(g + r13) >> 14)
    for j in range(u(nw)):
        g = i32(i32(i32(DY[j]) * w00 + i32(DY[j + one]) * w01) + i32(i32(DY[j + s]) * w10 + i32(DY[j + s1]) * w11))
        IY[j] = i32(i32(g + r13) >> 14)


@njit(_nrt=False)
def _stage_mismatch(nw, S, Q, IW, IX, IY, BX, BY, v00, v01, v10, v11):
    """BX = (J − I)·Ix, BY = (J − I)·Iy: J bilinear (×32) from the patch Q of the current frame,
    |J − I| <= 8160 (int32 products, as OpenCV's)."""
    i32 = np.int32
    u = np.uint64
    m15 = i32(0x7FFF)
    w00 = i32(v00 & m15)
    w01 = i32(v01 & m15)
    w10 = i32(v10 & m15)
    w11 = i32(v11 & m15)
    r8 = i32(1 << 8)
    one, s, s1 = u(1), u(S), u(S + 1)
    for j in range(u(nw)):
        v = i32(i32(i32(Q[j]) * w00 + i32(Q[j + one]) * w01) + i32(i32(Q[j + s]) * w10 + i32(Q[j + s1]) * w11))
        d = i32(i32(i32(v + r8) >> 9) - IW[j])
        BX[j] = i32(d * IX[j])
        BY[j] = i32(d * IY[j])


@njit(_nrt=False)
def _lk_kernel(img_prev, img_cur, pf, cf, prev, guess, h, max_iter, eps2, min_eig, out, status, w8, w16, w32):
    """The per-point loop of ``LKTrackerInvoker::operator()`` (level 0 of 0); writes ``out`` (N, 2) float32 and ``status``.

    Each point's neighbourhood is copied into flat buffers with one row stride S = win + 3, so
    that every integer stage is one vectorized loop over the rows (the columns past the window
    hold garbage that is never summed, the loops run to a multiple of 32 elements); the float32
    sums follow OpenCV's SSE order (:func:`_sums_a`, :func:`_sums_b`).  ``w8``, ``w16``, ``w32``:
    the scratch buffers of :func:`_workspace` (allocated by the caller, so that the kernel runs
    without numba's reference counting).
    """
    rows, cols = img_prev.shape
    win = 2 * h + 1
    S = win + 3  # the Scharr pass needs the window, its bilinear rim and one more column each side
    n = prev.shape[0]
    hw = np.float32(h)  # halfWin = (winSize - 1) * 0.5f
    one = np.float32(1.0)
    zero = np.float32(0.0)
    flt_scale = np.float32(1.0 / (1 << 20))
    n_simd = (win // 8) * 8  # pixels of a row in OpenCV's 8-wide SIMD loop; the rest of the row is scalar
    area2 = np.float32(2 * win * win)
    half = np.float32(0.5)
    four = np.float32(4.0)
    # P: previous frame, rows iy-1 .. iy+win+1, cols ix-1 ..; T0/T1 the vertical Scharr pass;
    # DX/DY the derivatives at rows iy .. iy+win, cols ix ..; IW/IX/IY the interpolated window;
    # Q: current frame, rows jy .. jy+win, cols jx ..; BX, BY the Gauss–Newton terms to sum.  The
    # stage loops run over a multiple of 32 elements (the vector loop does 4 × 8 at a time; a
    # remainder would run scalar), so the buffers are padded.
    nd, nw, nb = _sizes(h)
    P, Q = w8[:nb], w8[nb : 2 * nb]
    T0, T1, DX, DY = w16[:nb], w16[nb : 2 * nb], w16[2 * nb : 3 * nb], w16[3 * nb : 4 * nb]
    IW, IX, IY = w32[:nw], w32[nw : 2 * nw], w32[2 * nw : 3 * nw]
    BX, BY = w32[3 * nw : 4 * nw], w32[4 * nw : 5 * nw]
    for k in range(n):
        px = prev[k, 0]
        py = prev[k, 1]
        nx = guess[k, 0]
        ny = guess[k, 1]
        out[k, 0] = nx
        out[k, 1] = ny
        status[k] = True
        qx = px - hw
        qy = py - hw
        if not (np.isfinite(qx) and np.isfinite(qy)):
            status[k] = False
            continue
        fx0 = np.floor(qx)
        fy0 = np.floor(qy)
        if fx0 < -win or fx0 >= cols or fy0 < -win or fy0 >= rows:
            status[k] = False
            continue
        ix = int(fx0)
        iy = int(fy0)
        w00, w01, w10, w11 = _weights(qx - np.float32(ix), qy - np.float32(iy))

        _load_patch(img_prev, pf, iy - 1, ix - 1, win + 3, S, P)
        _stage_scharr(nd, S, P, T0, T1, DX, DY)
        if not (iy >= 0 and ix >= 0 and iy + win < rows and ix + win < cols):  # zero outside the image
            for r in range(win + 1):
                inside_r = 0 <= iy + r < rows
                for c in range(win + 1):
                    if not (inside_r and 0 <= ix + c < cols):
                        DX[r * S + c] = 0
                        DY[r * S + c] = 0
        _stage_window(nw, S, P, DX, DY, IW, IX, IY, w00, w01, w10, w11)
        a11, a12, a22 = _sums_a(IX, IY, win, S, n_simd)
        a11 = a11 * flt_scale
        a12 = a12 * flt_scale
        a22 = a22 * flt_scale
        det = a11 * a22 - a12 * a12
        d = a11 - a22
        min_eig_k = (a22 + a11 - np.sqrt(d * d + four * a12 * a12)) / area2
        if min_eig_k < min_eig or det < _FLT_EPSILON:
            status[k] = False
            continue
        det = one / det

        nx = nx - hw
        ny = ny - hw
        pdx = zero
        pdy = zero
        for j in range(max_iter):
            fnx = np.floor(nx)
            fny = np.floor(ny)
            if not (fnx >= -win and fnx < cols and fny >= -win and fny < rows):
                status[k] = False
                break
            jx = int(fnx)
            jy = int(fny)
            v00, v01, v10, v11 = _weights(nx - np.float32(jx), ny - np.float32(jy))
            _load_patch(img_cur, cf, jy, jx, win + 1, S, Q)
            _stage_mismatch(nw, S, Q, IW, IX, IY, BX, BY, v00, v01, v10, v11)
            b1, b2 = _sums_b(BX, BY, win, S, n_simd)
            b1 = b1 * flt_scale
            b2 = b2 * flt_scale
            dx = (a12 * b2 - a22 * b1) * det
            dy = (a12 * b1 - a11 * b2) * det
            nx = nx + dx
            ny = ny + dy
            out[k, 0] = nx + hw
            out[k, 1] = ny + hw
            if np.float64(dx) * np.float64(dx) + np.float64(dy) * np.float64(dy) <= eps2:
                break
            if j > 0 and np.float64(abs(dx + pdx)) < 0.01 and np.float64(abs(dy + pdy)) < 0.01:
                out[k, 0] = out[k, 0] - dx * half
                out[k, 1] = out[k, 1] - dy * half
                break
            pdx = dx
            pdy = dy
        if status[k]:  # the error computation's test on the final point (the binding always asks for err)
            ex = np.floor(out[k, 0] - hw)
            ey = np.floor(out[k, 1] - hw)
            if not (ex >= -win and ex < cols and ey >= -win and ey < rows):
                status[k] = False


def lk_track_cv2(img_prev, img_cur, pts_prev, guess, h, iterations, eps=0.01):
    """The reference: ``cv2.calcOpticalFlowPyrLK`` with the arguments :func:`lk_track` copies."""
    import cv2

    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(iterations), float(eps))
    p0 = np.ascontiguousarray(np.asarray(pts_prev, np.float32).reshape(-1, 1, 2))
    p1 = np.ascontiguousarray(np.asarray(guess, np.float32).reshape(-1, 1, 2))
    if len(p0) == 0:
        return np.empty((0, 2)), np.empty(0, bool)
    nxt, status, _ = cv2.calcOpticalFlowPyrLK(
        img_prev, img_cur, p0, p1, winSize=(2 * h + 1, 2 * h + 1), maxLevel=0, criteria=crit,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    return nxt.reshape(-1, 2).astype(np.float64), status.reshape(-1) == 1


def lk_track(img_prev, img_cur, pts_prev, guess, h, iterations, eps=0.01):
    """Track ``pts_prev`` (N, 2) of ``img_prev`` into ``img_cur`` from ``guess`` (N, 2): one-level LK.

    Same result as ``cv2.calcOpticalFlowPyrLK(img_prev, img_cur, pts_prev, guess,
    winSize=(2h+1, 2h+1), maxLevel=0, criteria=(COUNT|EPS, iterations, eps),
    flags=OPTFLOW_USE_INITIAL_FLOW)`` (see the module docstring).  Images uint8 (H, W); points
    are rounded to float32 as OpenCV takes them.  Returns the tracked points (N, 2) float64 and
    the status (N,) bool; where the status is False the point is what OpenCV leaves there (the
    guess, or the last iterate).
    """
    img_prev = np.asarray(img_prev)
    img_cur = np.asarray(img_cur)
    if img_prev.dtype != np.uint8 or img_cur.dtype != np.uint8:
        raise TypeError(f"images must be uint8, got {img_prev.dtype} and {img_cur.dtype}")
    img_prev = np.ascontiguousarray(img_prev)
    img_cur = np.ascontiguousarray(img_cur)
    if img_prev.ndim != 2 or img_prev.shape != img_cur.shape:
        raise ValueError(f"images must be two grey frames of one shape, got {img_prev.shape} and {img_cur.shape}")
    p0 = np.ascontiguousarray(np.asarray(pts_prev).reshape(-1, 2), np.float32)
    p1 = np.ascontiguousarray(np.asarray(guess).reshape(-1, 2), np.float32)
    if p0.shape != p1.shape:
        raise ValueError(f"pts_prev and guess must have one shape, got {p0.shape} and {p1.shape}")
    h = int(h)
    if h < 1:
        raise ValueError(f"h must be >= 1 (window 2h+1 >= 3), got {h}")
    if not jit.ENABLED:
        return lk_track_cv2(img_prev, img_cur, p0, p1, h, iterations, eps)
    max_iter = min(max(int(iterations), 0), 100)  # OpenCV's clamps
    e = min(max(float(eps), 0.0), 10.0)
    out = np.empty(p0.shape, np.float32)
    status = np.empty(len(p0), np.bool_)
    w8, w16, w32 = _workspace(h)
    _lk_kernel(img_prev, img_cur, img_prev.reshape(-1), img_cur.reshape(-1), p0, p1, h, max_iter, e * e,
               _MIN_EIG_THRESHOLD, out, status, w8, w16, w32)
    return out.astype(np.float64), status


@jit.register_warmup
def _warm_up() -> None:
    img = (np.arange(24 * 24, dtype=np.int64).reshape(24, 24) * 37 % 251).astype(np.uint8)
    pts = np.array([[11.5, 11.25], [0.5, 23.0]])
    lk_track(img, img, pts, pts + 0.3, 2, 3)
