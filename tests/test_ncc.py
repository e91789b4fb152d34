"""NCC matcher (DESIGN.md §3.2, eq. 13–14): known shifts, rejections, search window, bad input."""

import cv2
import numpy as np
import pytest

from companion.core import ncc
from companion.core.harris import HarrisConfig, detect_harris
from companion.core.ncc import NCCConfig, extract_templates, match_ncc, match_templates
from companion.errors import ConfigError, InputError

SS = 4  # supersampling: shifts are exact in steps of 1/SS px


class Scene:
    """Band-limited noise, 4× supersampled: render(shift) is the same texture moved by ``shift`` px."""

    def __init__(self, width=320, height=240, seed=0, margin=32, blur=1.2):
        rng = np.random.default_rng(seed)
        big = rng.standard_normal(((height + 2 * margin) * SS, (width + 2 * margin) * SS)).astype(np.float32)
        self.big = cv2.GaussianBlur(big, (0, 0), blur * SS)
        self.big /= self.big.std()
        self.w, self.h, self.m = width, height, margin

    def render(self, shift=(0.0, 0.0)):
        sx, sy = int(round(shift[0] * SS)), int(round(shift[1] * SS))
        y0, x0 = self.m * SS - sy, self.m * SS - sx
        crop = self.big[y0 : y0 + self.h * SS, x0 : x0 + self.w * SS]
        img = cv2.resize(crop, (self.w, self.h), interpolation=cv2.INTER_AREA)
        return np.clip(128 + 45 * img, 0, 255).round().astype(np.uint8)


@pytest.fixture(scope="module")
def scene():
    return Scene()


@pytest.fixture(scope="module")
def corners(scene):
    pts, _ = detect_harris(scene.render(), HarrisConfig(max_corners=80))
    return pts


@pytest.mark.parametrize("shift", [(0.0, 0.0), (1.0, 0.0), (-2.0, 3.0), (0.5, 0.75), (2.25, -1.5), (-3.75, 2.0)])
def test_recovers_known_shift(scene, corners, shift):
    a, b = scene.render(), scene.render(shift)
    inner = (corners[:, 0] > 16) & (corners[:, 0] < 304) & (corners[:, 1] > 16) & (corners[:, 1] < 224)
    corners = corners[inner]
    res = match_ncc(a, b, corners, corners, NCCConfig())
    assert res.ok.all(), np.bincount(res.reason)
    err = np.abs(res.pts - (corners + shift))
    assert err.max() < 0.1
    assert np.sqrt(np.mean(err**2)) < 0.04
    assert np.all(res.score > 0.85) and np.all(res.score <= 1.0 + 1e-6)
    if float(shift[0]).is_integer() and float(shift[1]).is_integer():
        assert err.max() < 0.01  # the sub-pixel step is exact for whole-pixel motion


def test_parabola_subpixel_is_close_but_biased(scene, corners):
    a, b = scene.render(), scene.render((1.25, 0.5))
    res = match_ncc(a, b, corners, corners, NCCConfig(subpixel_method="parabola"))
    assert res.ok.all()
    assert np.abs(res.pts - (corners + (1.25, 0.5))).max() < 0.5
    whole = match_ncc(a, b, corners, corners, NCCConfig(subpixel=False))
    frac = corners - np.rint(corners)
    assert np.allclose(whole.pts - frac, np.rint(whole.pts - frac))  # integer peaks + carried fraction


def test_window_is_centred_on_the_prediction(scene, corners):
    shift = (14.0, -9.0)  # beyond the default search half-size of 8 px
    a, b = scene.render(), scene.render(shift)
    pts = corners[(corners[:, 0] > 30) & (corners[:, 0] < 280) & (corners[:, 1] > 30) & (corners[:, 1] < 210)]
    blind = match_ncc(a, b, pts, pts, NCCConfig())
    assert not blind.ok.any()
    pred = pts + shift + np.array([1.4, -0.8])  # telemetry prediction with an error
    res = match_ncc(a, b, pts, pred, NCCConfig(), search_radius=3.0)
    assert res.ok.all()
    assert np.abs(res.pts - (pts + shift)).max() < 0.1
    # per-point radii: too small a window for half of them -> not accepted there
    radius = np.where(np.arange(len(pts)) % 2 == 0, 3.0, 1.0)
    res2 = match_ncc(a, b, pts, pts + shift + np.array([2.0, 0.0]), NCCConfig(), search_radius=radius)
    assert res2.ok[::2].all() and not res2.ok[1::2].any()
    assert np.all(np.isin(res2.reason[1::2], (ncc.PEAK_AT_EDGE, ncc.LOW_SCORE)))
    assert np.mean(res2.reason[1::2] == ncc.PEAK_AT_EDGE) > 0.5


@pytest.mark.parametrize("radius", [1.0, 2.0, 4.0, 5.0, 7.0])
def test_batch_scoring_equals_opencv(scene, corners, radius):
    a, b = scene.render(), scene.render((0.75, -0.5))
    pred = corners + np.array([0.75, -0.5])
    fast = match_ncc(a, b, corners, pred, NCCConfig(), search_radius=radius)
    slow = match_ncc(a, b, corners, pred, NCCConfig(batch_search_half=0), search_radius=radius)
    assert np.array_equal(fast.reason, slow.reason)
    assert np.allclose(fast.score, slow.score, atol=1e-3)
    assert np.allclose(fast.pts[fast.ok], slow.pts[slow.ok], atol=1e-3)


def test_low_correlation_is_rejected(scene, corners):
    other = Scene(seed=7).render()
    res = match_ncc(scene.render(), other, corners, corners, NCCConfig())
    # a smooth 11×11 texture searched over 17×17 places can meet k_min by chance, rarely
    assert np.mean(res.reason == ncc.LOW_SCORE) > 0.9
    assert np.mean(res.ok) < 0.05
    assert np.all(res.score[res.reason == ncc.LOW_SCORE] < 0.8)
    assert np.all(np.isfinite(res.pts))
    # k_min is the acceptance threshold: a low one accepts the same scores
    lax = match_ncc(scene.render(), other, corners, corners, NCCConfig(k_min=-1.0, ambiguity_margin=0.0))
    assert lax.ok.sum() > res.ok.sum()


def test_repeated_pattern_is_ambiguous():
    yy, xx = np.mgrid[0:160, 0:200]
    img = (128 + 60 * np.sin(2 * np.pi * xx / 6.0) * np.sin(2 * np.pi * yy / 7.0)).astype(np.uint8)
    pts = np.array([[60.0, 60.0], [100.2, 80.7], [140.0, 100.0]])
    res = match_ncc(img, img, pts, pts + 1.0, NCCConfig())
    assert np.all(res.reason == ncc.AMBIGUOUS)
    assert np.all(res.score > 0.99)  # the best peak itself is perfect; its twin makes it unusable
    # one isolated blob on a flat background is not ambiguous
    blob = np.full((160, 200), 100, np.uint8)
    cv2.circle(blob, (100, 80), 4, 200, -1)
    cv2.rectangle(blob, (103, 70), (110, 78), 30, -1)
    ok = match_ncc(blob, blob, np.array([[101.0, 78.0]]), np.array([[102.0, 79.0]]), NCCConfig())
    assert ok.ok.all()


def test_flat_and_out_of_image(scene):
    img = scene.render()
    flat = np.full_like(img, 90)
    res = match_ncc(flat, img, np.array([[100.0, 100.0]]), np.array([[100.0, 100.0]]), NCCConfig())
    assert res.reason[0] == ncc.FLAT_TEMPLATE
    pts = np.array([[2.0, 100.0], [100.0, 100.0], [100.0, 100.0], [160.0, 120.0]])
    pred = np.array([[2.0, 100.0], [-40.0, 100.0], [1e12, -1e12], [160.0, 120.0]])
    res = match_ncc(img, img, pts, pred, NCCConfig())
    assert list(res.reason[:3]) == [ncc.OUT_OF_IMAGE] * 3 and res.ok[3]
    assert np.all(np.isfinite(res.pts))


def test_point_leaving_the_image_is_out_of_image(scene):
    a, b = scene.render(), scene.render((-6.0, 0.0))
    pts = np.array([[9.0, 60.0], [8.4, 120.0], [10.0, 180.0]])  # true positions 3 px from the edge
    res = match_ncc(a, b, pts, pts, NCCConfig())
    assert not res.ok.any()
    assert np.all(np.isin(res.reason, (ncc.OUT_OF_IMAGE, ncc.LOW_SCORE)))
    assert np.sum(res.reason == ncc.OUT_OF_IMAGE) >= 2


def test_stored_templates_match_like_frames(scene, corners):
    a, b = scene.render(), scene.render((1.5, -0.25))
    tpl, frac, inside = extract_templates(a, corners, NCCConfig().template_half)
    assert tpl.shape == (len(corners), 13, 13) and inside.all()
    r1 = match_templates(tpl, frac, b, corners, NCCConfig(), valid=inside)
    r2 = match_ncc(a, b, corners, corners, NCCConfig())
    assert np.array_equal(r1.ok, r2.ok)
    assert np.abs(r1.pts - r2.pts).max() < 0.1
    assert np.abs(r1.pts - (corners + (1.5, -0.25))).max() < 0.1


def test_empty_input_gives_empty_result(scene):
    img = scene.render()
    res = match_ncc(img, img, np.zeros((0, 2)), np.zeros((0, 2)), NCCConfig())
    assert res.pts.shape == (0, 2) and res.ok.shape == (0,) and res.reason.dtype == np.int8


def test_bad_input_names_the_problem(scene):
    img = scene.render()
    p = np.array([[50.0, 50.0]])
    with pytest.raises(InputError, match="pts_prev"):
        match_ncc(img, img, np.array([[np.nan, 3.0]]), p, NCCConfig())
    with pytest.raises(InputError, match="pts_pred"):
        match_ncc(img, img, p, np.array([[np.inf, 3.0]]), NCCConfig())
    with pytest.raises(InputError, match="pts_pred"):
        match_ncc(img, img, p, np.zeros((2, 2)), NCCConfig())
    with pytest.raises(InputError, match=r"pts_prev must have shape \(N, 2\)"):
        match_ncc(img, img, np.zeros((3, 3)), np.zeros((3, 3)), NCCConfig())
    with pytest.raises(InputError, match="differ in shape"):
        match_ncc(img, img[:100], p, p, NCCConfig())
    with pytest.raises(InputError, match="img_cur is empty"):
        match_ncc(img, img[:0], p, p, NCCConfig())
    with pytest.raises(InputError, match="img_prev must have dtype uint8"):
        match_ncc(img.astype(float), img, p, p, NCCConfig())
    with pytest.raises(InputError, match="search_radius"):
        match_ncc(img, img, p, p, NCCConfig(), search_radius=-1.0)
    with pytest.raises(InputError, match="search_radius"):
        match_ncc(img, img, p, p, NCCConfig(), search_radius=np.ones(3))
    with pytest.raises(ConfigError, match="k_min"):
        NCCConfig(k_min=1.5)
    with pytest.raises(ConfigError, match="subpixel_method"):
        NCCConfig(subpixel_method="gauss")


def test_structure_tensor_ratio_of_known_patches():
    """λmin/λmax: 1 for a rotationally balanced bowl, 0 for straight edges at any angle."""
    T = 2 * NCCConfig().template_half + 3  # matched patch plus its rim
    v, u = np.mgrid[0:T, 0:T].astype(float)
    c = (T - 1) / 2
    bowl = 50 + (u - c) ** 2 + (v - c) ** 2  # ∂I/∂u odd in u, ∂I/∂v odd in v: M = a·I
    step = np.where(u > c, 180.0, 60.0)  # vertical edge
    diagonal = np.where(u + v > 2 * c, 180.0, 60.0)  # I(u + v): gradients all along (1, 1)
    ramp = 40 + 7 * u + 3 * v  # one constant gradient: rank 1
    flat = np.full((T, T), 90.0)
    tpl = np.stack([bowl, step, diagonal, ramp, flat]).round().astype(np.uint8)
    ratio = ncc.template_eigen_ratio(tpl)
    assert ratio[0] == pytest.approx(1.0, abs=1e-12)
    assert np.all(ratio[1:] == 0.0)


def test_a_template_on_a_straight_edge_is_refused():
    """On an edge the NCC peak is a ridge: the match would slide along it (aperture problem)."""
    rng = np.random.default_rng(3)
    img = np.full((120, 160), 70.0)
    img[60:, :] = 170.0  # a long horizontal edge
    img = np.clip(img + rng.normal(0, 1.0, img.shape), 0, 255).round().astype(np.uint8)
    pts = np.array([[50.0, 60.0], [90.0, 59.5]])
    res = match_ncc(img, img, pts, pts + [2.0, 0.0], NCCConfig())
    assert np.all(res.reason == ncc.EDGE_TEMPLATE) and not res.ok.any()
    # the verdict comes from the template alone, before any scoring: off, it is never given
    loose = match_ncc(img, img, pts, pts + [2.0, 0.0], NCCConfig(min_eigen_ratio=0.0))
    assert not np.any(loose.reason == ncc.EDGE_TEMPLATE)
    # a corner of the same contrast passes
    img2 = np.full((120, 160), 70, np.uint8)
    img2[60:, 80:] = 170
    ok = match_ncc(img2, img2, np.array([[80.0, 60.0]]), np.array([[81.0, 61.0]]), NCCConfig())
    assert ok.ok.all()
    with pytest.raises(ConfigError, match="min_eigen_ratio"):
        NCCConfig(min_eigen_ratio=1.0)


def _ncc_batch_box_filter(img, tpl, centres, sb, h):
    """The former _ncc_batch (window sums by cv2.boxFilter / sqrBoxFilter): the reference for
    the integral-image version, which must give bit-identical scores."""
    t = 2 * h + 1
    size = t + 2 * sb
    rb = 2 * sb + 1
    nb = len(centres)
    win = np.lib.stride_tricks.sliding_window_view(img, (size, size))[centres[:, 1] - sb - h, centres[:, 0] - sb - h]
    win = win.astype(np.float32)
    f = tpl.reshape(nb, t * t).astype(np.float32)
    f = f - f.mean(axis=1, keepdims=True)
    f = f / np.sqrt(np.einsum("nk,nk->n", f, f))[:, None]
    num = np.empty((nb, rb, rb), np.float32)
    for j in range(rb):
        cols = np.ascontiguousarray(win[:, :, j : j + t])
        blocks = np.lib.stride_tricks.sliding_window_view(cols, (t, t), axis=(1, 2))[:, :, 0].reshape(nb, rb, t * t)
        num[:, :, j] = np.einsum("nik,nk->ni", np.ascontiguousarray(blocks), f)
    wide = np.ascontiguousarray(win.transpose(1, 0, 2)).reshape(size, nb * size)
    s1 = cv2.boxFilter(wide, -1, (t, t), normalize=False, borderType=cv2.BORDER_REPLICATE)
    s2 = cv2.sqrBoxFilter(wide, -1, (t, t), normalize=False, borderType=cv2.BORDER_REPLICATE)

    def valid(a):
        return a.reshape(size, nb, size).transpose(1, 0, 2)[:, h : h + rb, h : h + rb].astype(np.float64)

    m1 = valid(s1)
    var = valid(s2) - m1 * m1 / (t * t)
    den = np.sqrt(np.maximum(var, 0.0))
    ok = den > 1e-3
    return np.where(ok, num / np.where(ok, den, 1.0), 0.0).astype(np.float32)


@pytest.mark.parametrize("sb", [1, 3, 5])
def test_ncc_batch_is_bit_identical_to_the_box_filter_version(sb):
    rng = np.random.default_rng(sb)
    h = 5
    img = rng.integers(0, 256, (120, 160), dtype=np.uint8)
    img[:40, :60] = 77  # flat windows: score 0
    img[60:, 80:] = (img[60:, 80:] // 64) * 64  # few grey levels: ties and exact sums
    m = 40
    lo = sb + h
    centres = np.stack([rng.integers(lo, 160 - lo, m), rng.integers(lo, 120 - lo, m)], 1)
    centres[0] = (lo + 5, lo + 5)  # inside the flat block
    tpl = np.stack([img[y - h : y + h + 1, x - h : x + h + 1] for x, y in rng.integers(h + 41, 110, (m, 2))])  # textured
    got = ncc._ncc_batch(img, tpl, centres, sb, h)
    want = _ncc_batch_box_filter(img, tpl, centres, sb, h)
    assert got.dtype == want.dtype and got.shape == want.shape
    assert np.array_equal(got, want)
    assert np.all(got[0] == 0.0)


def test_ncc_batch_cell_scores_do_not_depend_on_the_batch_radius():
    # _score_group scores each radius in its own batch: a cell's score must be bit-identical to
    # the centre cells of a batch with a larger radius (and to a batch of different points)
    rng = np.random.default_rng(7)
    h = 5
    img = rng.integers(0, 256, (100, 140), dtype=np.uint8)
    m = 30
    centres = np.stack([rng.integers(12, 128, m), rng.integers(12, 88, m)], 1)
    tpl = np.stack([img[y - h : y + h + 1, x - h : x + h + 1] for x, y in rng.integers(h + 1, 90, (m, 2))])
    big = ncc._ncc_batch(img, tpl, centres, 6, h)
    for sb in range(1, 6):
        small = ncc._ncc_batch(img, tpl[::2], centres[::2], sb, h)
        assert np.array_equal(small, big[::2, 6 - sb : 7 + sb, 6 - sb : 7 + sb])
