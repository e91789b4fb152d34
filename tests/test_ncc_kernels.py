"""The NCC matcher's compiled kernels against its numpy/OpenCV reference (docs/derivations/compute.md).

Same inputs through both paths (``jit.ENABLED`` switched for the call); they must agree to float
rounding: verdicts identical, scores within 1e-4 (float32 dot products summed in another order than
OpenCV's matchTemplate / the einsum batch: ~1e-6 seen), matched pixels identical (the same integer
peak, then the same OpenCV Lucas–Kanade step), scale within 1e-4 (the reference resamples with
cv2.remap, the kernel with its own bilinear: ~2e-6 seen).  Skipped without numba.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from companion.core import jit
from companion.core import ncc as N
from companion.core import ncc_kernels as K

pytestmark = pytest.mark.skipif(not jit.ENABLED, reason="numba not installed (or COMPANION_KERNELS=numpy): no kernels to compare")


def _scene(seed: int, size=(240, 320), blur=1.5, flat_box=True):
    rng = np.random.default_rng(seed)
    h, w = size
    img = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), blur)
    img = np.clip(128 + 40 * img / img.std(), 0, 255).astype(np.uint8)
    if flat_box:
        img[20:60, 20:60] = 100  # flat: FLAT_TEMPLATE / flat windows
        img[100:140, 200:260] = np.where(np.arange(60) < 30, 60, 190)[None, :]  # a vertical edge: EDGE_TEMPLATE
        img[:, 290:] = np.tile(img[:, 250:260], (1, 3))  # repeated texture: AMBIGUOUS
    return img


def _shifted(img: np.ndarray, dx: float, dy: float, scale: float = 1.0, noise: float = 1.0, seed: int = 0) -> np.ndarray:
    h, w = img.shape
    c = ((w - 1) / 2, (h - 1) / 2)
    M = np.array([[scale, 0, dx + c[0] * (1 - scale)], [0, scale, dy + c[1] * (1 - scale)]])
    out = cv2.warpAffine(img.astype(np.float32), M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    out += np.random.default_rng(seed).normal(0, noise, out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _both(fn, *args, **kwargs):
    old = jit.ENABLED
    try:
        jit.ENABLED = False
        ref = fn(*args, **kwargs)
        jit.ENABLED = True
        ker = fn(*args, **kwargs)
    finally:
        jit.ENABLED = old
    return ref, ker


@pytest.mark.parametrize("seed", range(6))
def test_match_ncc_kernel_equals_reference(seed):
    rng = np.random.default_rng(100 + seed)
    prev = _scene(seed)
    scale = 1.0 + rng.uniform(-0.04, 0.06)
    cur = _shifted(prev, rng.uniform(-2, 2), rng.uniform(-2, 2), scale, seed=seed)
    n = 300
    pts = np.stack([rng.uniform(-5, 325, n), rng.uniform(-5, 245, n)], 1)  # some outside: OUT_OF_IMAGE
    pred = pts + rng.normal(0, 1.5, (n, 2))
    radius = rng.choice([0.5, 2.2, 3.0, 4.7, 6.0, 9.5, 14.0, 21.0, 40.0], n)  # batch sizes, wide windows, the cap
    cfg = N.NCCConfig(max_scale_points=60)
    ref, ker = _both(N.match_ncc, prev, cur, pts, pred, cfg, radius, scale_pred=np.full(n, scale), rescale_threshold=0.05)
    np.testing.assert_array_equal(ker.reason, ref.reason)
    assert len(set(ref.reason.tolist())) >= 4  # the scene exercises several verdicts
    np.testing.assert_allclose(ker.score, ref.score, atol=1e-4)
    np.testing.assert_allclose(ker.pts, ref.pts, atol=1e-6)
    np.testing.assert_array_equal(np.isfinite(ker.scale), np.isfinite(ref.scale))
    fin = np.isfinite(ref.scale)
    assert np.count_nonzero(fin) >= 20
    np.testing.assert_allclose(ker.scale[fin], ref.scale[fin], atol=1e-4)
    np.testing.assert_allclose(ker.scale_sigma[fin], ref.scale_sigma[fin], rtol=1e-3, atol=1e-6)


def test_match_templates_kernel_equals_reference_for_stored_templates():
    """Tracks that missed a frame: stored templates, the vectorized Lucas–Kanade step (no img_prev)."""
    rng = np.random.default_rng(7)
    prev = _scene(3, flat_box=False)
    cur = _shifted(prev, 1.3, -0.6, seed=1)
    pts = np.stack([rng.uniform(15, 300, 120), rng.uniform(15, 220, 120)], 1)
    tpl, frac, inside = N.extract_templates(prev, pts, 5)
    cfg = N.NCCConfig()
    ref, ker = _both(N.match_templates, tpl, frac, cur, pts + [1.3, -0.6], cfg, 5.0, valid=inside)
    np.testing.assert_array_equal(ker.reason, ref.reason)
    np.testing.assert_allclose(ker.score, ref.score, atol=1e-4)
    np.testing.assert_allclose(ker.pts, ref.pts, atol=1e-5)
    assert np.count_nonzero(ref.ok) > 100


def test_score_peaks_scores_equal_opencv_on_every_cell():
    """Each cell of a window: eq. 13 as cv2.matchTemplate(TM_CCOEFF_NORMED) computes it."""
    img = _scene(11, flat_box=False)
    rng = np.random.default_rng(3)
    h = 5
    for _ in range(20):
        u, v = int(rng.integers(30, 290)), int(rng.integers(30, 210))
        s = int(rng.integers(1, 12))
        tpl = np.ascontiguousarray(img[v - h - 1 : v + h + 2, u - h - 1 : u + h + 2][None])  # with its rim
        cu, cv_ = u + int(rng.integers(-3, 4)), v + int(rng.integers(-3, 4))
        c = np.array([[cu, cv_]], np.int64)
        lo = np.maximum(c - s, h)
        hi = np.minimum(c + s, [img.shape[1] - 1 - h, img.shape[0] - 1 - h])
        bi, bj, best, nbrs, amb = K.score_peaks(img, tpl, c, np.array([s], np.int64), lo, hi, 0.03, 3.0)
        win = img[lo[0, 1] - h : hi[0, 1] + h + 1, lo[0, 0] - h : hi[0, 0] + h + 1]
        ref = cv2.matchTemplate(win, tpl[0, 1:-1, 1:-1], cv2.TM_CCOEFF_NORMED)
        i, j = np.unravel_index(np.argmax(ref), ref.shape)
        assert (bi[0] - (lo[0, 1] - c[0, 1] + s), bj[0] - (lo[0, 0] - c[0, 0] + s)) == (i, j)
        assert best[0] == pytest.approx(ref.max(), abs=1e-4)


def test_template_stats_equal_reference():
    rng = np.random.default_rng(5)
    tpl = rng.integers(0, 256, (50, 13, 13)).astype(np.uint8)
    tpl[0] = 77  # flat
    tpl[1] = np.where(np.arange(13) < 6, 10, 200)[None, :].astype(np.uint8)  # an edge
    var, ratio = K.template_stats(tpl)
    inner = tpl[:, 1:-1, 1:-1].reshape(50, -1).astype(np.float64)
    np.testing.assert_allclose(var, inner.var(axis=1), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ratio, N.template_eigen_ratio(tpl), rtol=1e-9, atol=1e-12)
    assert var[0] == 0 and ratio[0] == 0 and ratio[1] == pytest.approx(0.0, abs=1e-12)


def test_kernels_handle_empty_input():
    img = _scene(1)
    cfg = N.NCCConfig()
    ref, ker = _both(N.match_ncc, img, img, np.zeros((0, 2)), np.zeros((0, 2)), cfg)
    assert len(ker.pts) == len(ref.pts) == 0
    s, sig = K.scale_fit(img, img, np.zeros((0, 2)), np.zeros((0, 2)),
                         np.zeros(0), np.zeros(0, np.bool_), 7, 2, 1.3, 1.5, 0.06)
    assert s.shape == sig.shape == (0,)
