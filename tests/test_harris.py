"""Harris detector (DESIGN.md §3.1): checkerboard corners, bucketing, exclusion, bad input."""

import numpy as np
import pytest

from companion.core.harris import HarrisConfig, as_gray_u8, detect_harris, refine_corners
from companion.errors import ConfigError, InputError


def checkerboard(width, height, square, offset, angle_rad, supersample=8, dark=40, light=210):
    """Anti-aliased checkerboard rendered analytically (area average of supersample² points per pixel).

    Pixel (i, j) covers [j − ½, j + ½] × [i − ½, i + ½] (OpenCV pixel-centre convention).  Corners
    of the board lie at ``offset + square · R(angle) · (a, b)`` for integers a, b.
    """
    ss = supersample
    ys, xs = np.mgrid[0 : height * ss, 0 : width * ss]
    x = (xs + 0.5) / ss - 0.5 - offset[0]
    y = (ys + 0.5) / ss - 0.5 - offset[1]
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    a = (c * x + s * y) / square
    b = (-s * x + c * y) / square
    v = ((np.floor(a) + np.floor(b)) % 2).reshape(height, ss, width, ss).mean(axis=(1, 3))
    img = (dark + (light - dark) * v).round().astype(np.uint8)
    ij = np.mgrid[-40:40, -40:40].reshape(2, -1).T
    corners = np.stack(
        [offset[0] + square * (c * ij[:, 0] - s * ij[:, 1]), offset[1] + square * (s * ij[:, 0] + c * ij[:, 1])], 1
    )
    return img, corners


def _match(found, truth):
    d = np.linalg.norm(found[:, None, :] - truth[None, :, :], axis=2)
    return d.min(axis=1), d.min(axis=0)


@pytest.mark.parametrize("angle_deg, offset", [(0.0, (10.37, 7.61)), (8.0, (12.21, 9.83)), (-23.0, (5.5, 3.25))])
def test_checkerboard_inner_corners_within_half_pixel(angle_deg, offset):
    w, h = 320, 240
    img, corners = checkerboard(w, h, 24.0, offset, np.radians(angle_deg))
    cfg = HarrisConfig()
    pts, resp = detect_harris(img, cfg)
    assert pts.dtype == np.float64 and pts.shape[1] == 2 and resp.shape == (len(pts),)
    b = cfg.border + 2  # corners this far inside the detection border must all be found
    inner = corners[(corners[:, 0] > b) & (corners[:, 0] < w - 1 - b) & (corners[:, 1] > b) & (corners[:, 1] < h - 1 - b)]
    assert len(inner) > 60
    d_found, _ = _match(pts, corners)
    _, d_truth = _match(pts, inner)
    assert np.all(d_found < 0.5), f"spurious or inaccurate corners: worst {d_found.max():.3f} px"
    assert np.all(d_truth < 0.5), f"missed inner corners: worst {d_truth.max():.3f} px"
    assert np.median(d_found) < 0.1
    # one detection per corner
    assert len(pts) == len(np.unique(np.rint(pts / 4.0), axis=0))


def test_sub_pixel_refinement_beats_integer_maxima():
    img, corners = checkerboard(200, 160, 20.0, (9.3, 7.7), np.radians(5.0))
    raw, _ = detect_harris(img, HarrisConfig(subpix_window=0))
    ref, _ = detect_harris(img, HarrisConfig())
    assert np.mean(_match(ref, corners)[0]) < 0.5 * np.mean(_match(raw, corners)[0])
    # refine_corners on its own: from the integer maxima to the truth
    again = refine_corners(img, np.rint(raw), 3)
    ok = np.all(np.isfinite(again), 1)
    assert np.all(_match(again[ok], corners)[0] < 0.5)


def _texture(width, height, seed, contrast):
    rng = np.random.default_rng(seed)
    import cv2

    big = cv2.GaussianBlur(rng.standard_normal((height * 4, width * 4)).astype(np.float32), (0, 0), 5.0)
    img = cv2.resize(big, (width, height), interpolation=cv2.INTER_AREA)
    img = (img - img.mean()) / img.std()
    return np.clip(128 + contrast * img, 0, 255).astype(np.uint8)


def test_grid_bucketing_spreads_corners_over_weak_texture():
    img = _texture(320, 240, 1, 50.0)
    img[:, 160:] = _texture(320, 240, 2, 4.0)[:, 160:]  # right half: 12× weaker gradients
    cfg = HarrisConfig(max_corners=120, grid_rows=4, grid_cols=4)
    pts, _ = detect_harris(img, cfg)
    assert len(pts) == 120
    right = pts[:, 0] > 170
    assert right.sum() >= 30, "bucketing should give the weakly textured half its share of corners"
    cols = np.floor(pts[:, 0] * 4 / 320).astype(int)
    rows = np.floor(pts[:, 1] * 4 / 240).astype(int)
    assert len(set(zip(rows.tolist(), cols.tolist()))) == 16  # every cell has corners
    # without bucketing (one cell) the strong half takes nearly everything
    one, _ = detect_harris(img, HarrisConfig(max_corners=120, grid_rows=1, grid_cols=1, cell_cap=0))
    assert (one[:, 0] > 170).sum() < right.sum()


def test_max_corners_cell_cap_mask_and_exclusion():
    img = _texture(320, 240, 3, 50.0)
    cfg = HarrisConfig(min_distance=5)
    pts, resp = detect_harris(img, cfg, max_corners=50)
    assert len(pts) == 50 and np.all(resp > 0)
    capped, _ = detect_harris(img, HarrisConfig(grid_rows=2, grid_cols=2, cell_cap=3, max_corners=100))
    assert len(capped) <= 12
    mask = np.zeros(img.shape, np.uint8)
    mask[:, :100] = 1
    left, _ = detect_harris(img, cfg, mask=mask)
    assert len(left) > 0 and np.all(left[:, 0] < 100 + cfg.subpix_window)
    existing = pts[:20]
    new, _ = detect_harris(img, cfg, exclude_pts=existing, exclude_radius=12.0)
    d = np.linalg.norm(new[:, None] - existing[None], axis=2)
    assert np.all(d > 12.0 - cfg.subpix_window - 0.5)
    assert len(new) > 0
    # minimum distance between corners (NMS radius), up to the sub-pixel shift
    d_all = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 1e9
    assert d_all.min() > cfg.min_distance - 2 * cfg.subpix_window


def test_flat_and_tiny_images_give_no_corners():
    pts, resp = detect_harris(np.full((120, 160), 77, np.uint8), HarrisConfig())
    assert pts.shape == (0, 2) and resp.shape == (0,)
    pts, _ = detect_harris(np.zeros((10, 10), np.uint8), HarrisConfig())
    assert pts.shape == (0, 2)


@pytest.mark.parametrize(
    "image, words",
    [
        (np.zeros((0, 10), np.uint8), "empty"),
        (np.zeros((20, 20), np.float32), "uint8"),
        (np.zeros((20, 20, 3), np.uint8), "colour"),
        (np.zeros(20, np.uint8), "2-D"),
        ([[1, 2], [3, 4]], "numpy array"),
    ],
)
def test_bad_images_raise_naming_the_problem(image, words):
    with pytest.raises(InputError, match=words):
        detect_harris(image, HarrisConfig())


def test_single_channel_3d_is_accepted():
    img = _texture(160, 120, 4, 50.0)
    assert as_gray_u8(img[:, :, None]).shape == (120, 160)


def test_bad_arguments_and_config():
    img = _texture(160, 120, 5, 50.0)
    with pytest.raises(InputError, match="exclude_pts"):
        detect_harris(img, HarrisConfig(), exclude_pts=np.array([[np.nan, 3.0]]))
    with pytest.raises(InputError, match="exclude_pts"):
        detect_harris(img, HarrisConfig(), exclude_pts=np.zeros((3, 3)))
    with pytest.raises(InputError, match="mask"):
        detect_harris(img, HarrisConfig(), mask=np.ones((5, 5)))
    with pytest.raises(InputError, match="max_corners"):
        detect_harris(img, HarrisConfig(), max_corners=-1)
    with pytest.raises(ConfigError, match="k"):
        HarrisConfig(k=-0.04)
    with pytest.raises(ConfigError, match="aperture"):
        HarrisConfig(aperture=4)
    with pytest.raises(ConfigError, match="border"):
        HarrisConfig(border=2, subpix_window=3)
