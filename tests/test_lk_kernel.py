"""companion/core/lk_kernel.py against cv2.calcOpticalFlowPyrLK (maxLevel=0, USE_INITIAL_FLOW).

Random band-limited textures (blurred noise), the second frame a sub-pixel shift / small scale and
rotation of the first (cv2.warpAffine) plus noise; guesses within ±1 px of the truth; points deep
inside, near and across the borders, on flat patches; windows 3×3 … 23×23, 1–5 iterations.  On
x86 the kernel follows OpenCV's SSE summation order, so the points must be the same floats and
the status the same; elsewhere (OpenCV's NEON build sums in another order) within 1e-3 px.

``python tests/test_lk_kernel.py`` prints the timing of both for 300 points on a 640×480 frame.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from companion.core import jit
from companion.core import lk_kernel as lk

pytestmark = pytest.mark.skipif(not jit.ENABLED, reason="compiled kernels off: lk_track is cv2 itself")

X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")
H, W = 480, 640


def texture(rng, h=H, w=W, blur=1.5, contrast=40.0):
    """Gaussian-blurred white noise, std ``contrast`` grey levels around 128."""
    img = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), blur)
    return np.clip(128 + contrast * img / img.std(), 0, 255).astype(np.uint8)


def warped(rng, img, shift=3.0, scale=0.03, angle_deg=1.0, noise=2.0):
    """``img`` moved by a random sub-pixel shift, scale and rotation, plus noise; returns it and the 2×3 map."""
    h, w = img.shape
    m = cv2.getRotationMatrix2D((w / 2, h / 2), rng.uniform(-angle_deg, angle_deg), 1 + rng.uniform(-scale, scale))
    m[:, 2] += rng.uniform(-shift, shift, 2)
    out = cv2.warpAffine(img, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    return np.clip(out + rng.normal(0, noise, out.shape), 0, 255).astype(np.uint8), m


def moved(m, pts):
    return pts @ m[:, :2].T + m[:, 2]


def check(img0, img1, pts, guess, h, iterations, eps=0.01):
    """Run both; assert the same status and the same points (x86) or within 1e-3 px; return the status."""
    ours, ok = lk.lk_track(img0, img1, pts, guess, h, iterations, eps)
    ref, ok_ref = lk.lk_track_cv2(img0, img1, pts, guess, h, iterations, eps)
    assert ours.shape == ref.shape == (len(pts), 2) and ours.dtype == np.float64
    assert ok.shape == ok_ref.shape == (len(pts),) and ok.dtype == bool
    if X86:
        assert np.array_equal(ok, ok_ref), f"status differs at {np.flatnonzero(ok != ok_ref)}"
        assert np.array_equal(ours, ref, equal_nan=True), f"max |Δ| {np.nanmax(np.abs(ours - ref)):.3g} px"
    else:  # OpenCV's ARM build sums in another order: float32 rounding apart, a rare threshold flip
        assert (ok != ok_ref).mean() <= 0.005
        both = ok & ok_ref
        assert np.abs(ours[both] - ref[both]).max(initial=0) <= 1e-3
    return ok


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("iterations", [1, 2, 3, 4, 5])
def test_same_as_opencv_on_random_textures(seed, iterations):
    rng = np.random.default_rng(100 * seed + iterations)
    blur, contrast = [(0.8, 60), (1.5, 40), (1.5, 100), (3.0, 30), (1.0, 20), (2.0, 80)][seed]
    img0 = texture(rng, blur=blur, contrast=contrast)
    img1, m = warped(rng, img0)
    pts = np.column_stack([rng.uniform(8, W - 8, 300), rng.uniform(8, H - 8, 300)])
    guess = moved(m, pts) + rng.uniform(-1, 1, pts.shape)
    ok = check(img0, img1, pts, guess, 5, iterations)
    assert ok.mean() > 0.9


@pytest.mark.parametrize("h", [1, 2, 3, 4, 6, 7, 8, 11])
def test_same_as_opencv_for_other_windows(h):
    # windows narrower than OpenCV's 8-pixel SIMD block, one block, two blocks; row copies of 16 and 32 bytes
    rng = np.random.default_rng(h)
    img0 = texture(rng, 240, 320, blur=1.2, contrast=50)
    img1, m = warped(rng, img0, shift=2.0)
    pts = np.column_stack([rng.uniform(-2 * h, 320 + 2 * h, 200), rng.uniform(-2 * h, 240 + 2 * h, 200)])
    check(img0, img1, pts, moved(m, pts) + rng.uniform(-1, 1, pts.shape), h, 3)


def test_points_at_and_across_the_borders():
    rng = np.random.default_rng(7)
    img0 = texture(rng, blur=1.3, contrast=50)
    img1, m = warped(rng, img0, shift=4.0)
    n = 1500
    edge = rng.integers(0, 4, n)
    along = np.where(edge < 2, rng.uniform(0, W, n), rng.uniform(0, H, n))
    across = rng.uniform(-14, 14, n)  # window corner from inside to beyond -(2h+1) / the far edge
    x = np.select([edge == 0, edge == 1, edge == 2, edge == 3], [along, along, across, W - 1 - across])
    y = np.select([edge == 0, edge == 1, edge == 2, edge == 3], [across, H - 1 - across, along, along])
    pts = np.column_stack([x, y])
    for iterations in (1, 3):
        guess = moved(m, pts) + rng.uniform(-1, 1, pts.shape)
        ok = check(img0, img1, pts, guess, 5, iterations)
        assert 0.2 < ok.mean() < 0.95  # both kinds occur
    # the final-point test (after the last iterate, outside the loop) is exercised: with one
    # iteration the loop tests the guess only, so a dropped point whose guess passed was dropped there
    corner = lambda p: np.floor(p.astype(np.float32) - np.float32(5))  # noqa: E731
    inside = lambda c: (c[:, 0] >= -11) & (c[:, 0] < W) & (c[:, 1] >= -11) & (c[:, 1] < H)  # noqa: E731
    guess = moved(m, pts) + rng.uniform(-1, 1, pts.shape)
    nxt, ok = lk.lk_track(img0, img1, pts, guess, 5, 1)
    _, ok_ref = lk.lk_track_cv2(img0, img1, pts, guess, 5, 1)
    late = ~ok & inside(corner(pts)) & inside(corner(guess)) & ~inside(corner(nxt))
    assert late.any() and np.array_equal(ok, ok_ref)


def test_flat_patches_fail_the_eigenvalue_test():
    rng = np.random.default_rng(3)
    img0 = texture(rng, blur=1.5, contrast=40)
    img0[100:200, 100:300] = 90  # flat
    img0[300:400, 100:300] = np.tile(np.arange(200, dtype=np.uint8) // 2 + 40, (100, 1))  # a ramp: rank-1 tensor
    img1, m = warped(rng, img0, shift=1.0)
    pts = np.vstack([np.column_stack([rng.uniform(110, 290, 200), rng.uniform(110, 190, 200)]),
                     np.column_stack([rng.uniform(110, 290, 200), rng.uniform(310, 390, 200)]),
                     np.column_stack([rng.uniform(20, 620, 200), rng.uniform(20, 80, 200)])])
    ok = check(img0, img1, pts, moved(m, pts) + rng.uniform(-1, 1, pts.shape), 5, 3)
    assert not ok[:200].any()  # flat: zero tensor
    assert ok[400:].mean() > 0.9


def test_odd_inputs():
    rng = np.random.default_rng(5)
    img0 = texture(rng, 17, 23, blur=1.0, contrast=50)  # smaller than the padding: reflections all round
    img1, m = warped(rng, img0, shift=1.0)
    pts = np.column_stack([rng.uniform(-8, 30, 100), rng.uniform(-8, 24, 100)])
    check(img0, img1, pts, moved(m, pts) + rng.uniform(-1, 1, pts.shape), 3, 4)
    big0 = texture(rng, 120, 160)
    big1, m = warped(rng, big0)
    pts = np.array([[50.0, 60.0], [np.nan, 3.0], [1e9, 5.0], [-1e9, 5.0], [70.25, 40.5], [80.0, 80.0]])
    guess = moved(m, np.nan_to_num(pts))
    guess[4] = [np.nan, 40.0]
    guess[5] = [1e7, 80.0]
    for iterations, eps in [(0, 0.01), (1, 0.0), (5, 0.5), (150, 0.01), (3, 20.0)]:
        ok = check(big0, big1, pts, guess, 5, iterations, eps)
        assert not ok[1:6].any()
    ours, ok = lk.lk_track(big0, big1, np.empty((0, 2)), np.empty((0, 2)), 5, 3)
    assert ours.shape == (0, 2) and ok.shape == (0,)


def test_bad_inputs():
    img = np.zeros((20, 20), np.uint8)
    pts = np.zeros((3, 2))
    with pytest.raises(TypeError):
        lk.lk_track(img.astype(np.float32), img, pts, pts, 5, 3)
    with pytest.raises(ValueError):
        lk.lk_track(img, img[:10], pts, pts, 5, 3)
    with pytest.raises(ValueError):
        lk.lk_track(img, img, pts, pts[:2], 5, 3)
    with pytest.raises(ValueError):
        lk.lk_track(img, img, pts, pts, 0, 3)


def test_weights_round_like_cvround():
    rng = np.random.default_rng(0)
    f = rng.random((20000, 2)).astype(np.float32)
    f[:5] = [[0, 0], [0.5, 0.5], [0.25, 0.75], [np.float32(1) - np.float32(2**-24), 0.5], [0.5, 0.0]]
    one, s = np.float32(1), np.float32(1 << 14)
    want = np.rint(np.stack([(one - f[:, 0]) * (one - f[:, 1]) * s, f[:, 0] * (one - f[:, 1]) * s,
                             (one - f[:, 0]) * f[:, 1] * s], 1)).astype(np.int64)
    got = np.array([lk._weights(a, b)[:3] for a, b in f], np.int64)
    assert np.array_equal(got, want)


def test_ordered_sums_match_the_plain_python_order():
    # terms up to 2^25 so that float32 rounding happens and the order matters
    import numba

    sums_a = numba.njit(lambda U, V, win, S, n: lk._sums_a(U, V, win, S, n))
    sums_b = numba.njit(lambda U, V, win, S, n: lk._sums_b(U, V, win, S, n))
    rng = np.random.default_rng(1)
    differs = 0
    for h in (1, 3, 5, 8, 9):
        win = 2 * h + 1
        S = win + 3
        n_simd = win // 8 * 8
        U, V = (rng.integers(-4080, 4081, win * S + 8).astype(np.int32) for _ in range(2))
        B1, B2 = (rng.integers(-2**25, 2**25, win * S + 8).astype(np.int32) for _ in range(2))
        assert sums_a(U, V, win, S, n_simd) == lk._sums_a_ref(U, V, win, S, n_simd)
        assert sums_b(B1, B2, win, S, n_simd) == lk._sums_b_ref(B1, B2, win, S, n_simd)
        naive = np.float32(0)
        for t in B1[: win * S].reshape(win, S)[:, :win].ravel():
            naive = np.float32(naive + np.float32(t))
        differs += sums_b(B1, B2, win, S, n_simd)[0] != naive
    assert differs  # the data is such that the order does matter


def test_without_numba_it_is_opencv():
    code = ("import numpy as np, cv2; from companion.core import jit, lk_kernel as lk; assert not jit.ENABLED;"
            "r = np.random.default_rng(0); a = cv2.GaussianBlur(r.integers(0, 255, (60, 80)).astype(np.uint8), (5, 5), 1);"
            "b = np.roll(a, 1, 1); p = r.uniform(10, 50, (20, 2)); q = p + [1.2, 0.1];"
            "x, s = lk.lk_track(a, b, p, q, 5, 3); y, t = lk.lk_track_cv2(a, b, p, q, 5, 3);"
            "assert np.array_equal(x, y) and np.array_equal(s, t)")
    env = dict(os.environ, COMPANION_KERNELS="numpy")
    subprocess.run([sys.executable, "-c", code], check=True, env=env, cwd=os.path.dirname(os.path.dirname(__file__)))


def timing(n=300, repeats=500):
    """Median and best time of one call for n points on a 640×480 frame, cv2 (one thread) and the kernel."""
    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    img0 = texture(rng, blur=1.5, contrast=40)
    img1, m = warped(rng, img0, shift=1.0)
    pts = np.column_stack([rng.uniform(20, W - 20, n), rng.uniform(20, H - 20, n)])
    guess = moved(m, pts) + rng.uniform(-0.5, 0.5, pts.shape)
    calls = {"cv2.calcOpticalFlowPyrLK": lambda: lk.lk_track_cv2(img0, img1, pts, guess, 5, 3),
             "lk_kernel.lk_track": lambda: lk.lk_track(img0, img1, pts, guess, 5, 3)}
    times = {k: [] for k in calls}
    for f in calls.values():
        f()
    for _ in range(repeats):
        for k, f in calls.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    return {k: (float(np.median(v)), float(np.min(v))) for k, v in times.items()}


if __name__ == "__main__":
    for name, (med, best) in timing().items():
        print(f"{name:26s} median {1e3 * med:.3f} ms  best {1e3 * best:.3f} ms  (300 points, 640×480, h=5, 3 iterations)")
