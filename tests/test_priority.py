"""New corners where they matter (priority region), and search windows close in."""

import dataclasses
import math

import numpy as np
import pytest

from companion.core.camera import CameraConfig, CameraModel
from companion.core.harris import HarrisConfig, detect_harris
from companion.core.ncc import NCCConfig
from companion.core.prediction import predict_pixels_detailed
from companion.core.priority import detection_priority, live_points_per_sector
from companion.core.sectors import SECTOR_COUNT, SectorConfig
from companion.core.tracks import TrackConfig, TrackManager
from companion.errors import ConfigError, InputError


def corner_image(h=240, w=320):
    """Strong (contrast 200) squares in the top half, weak ones (contrast 30) in the bottom half."""
    img = np.full((h, w), 100, np.uint8)
    for y in range(20, h // 2 - 20, 24):
        for x in range(20, w - 20, 24):
            img[y : y + 10, x : x + 10] = 255 if (x // 24 + y // 24) % 2 else 0
    for y in range(h // 2 + 20, h - 20, 24):
        for x in range(20, w - 20, 24):
            img[y : y + 10, x : x + 10] = 130 if (x // 24 + y // 24) % 2 else 70
    return img


def test_priority_puts_new_corners_inside_the_region_first():
    img = corner_image()
    region = np.zeros(img.shape, bool)
    region[130:, :] = True  # the weak half
    # one grid cell for all, so the weak corners lose the per-cell threshold without priority
    cfg = HarrisConfig(grid_rows=1, grid_cols=1, cell_cap=0)
    pts, _ = detect_harris(img, cfg, max_corners=20)
    assert len(pts) == 20 and np.all(pts[:, 1] < 120)  # the busiest part takes everything
    pts, _ = detect_harris(img, cfg, max_corners=20, priority=region, priority_max=10)
    inside = pts[:, 1] >= 130
    assert len(pts) == 20
    assert np.count_nonzero(inside) == 10  # the share, no more
    assert np.all(inside[:10])  # first in the selection order
    assert np.all(pts[~inside, 1] < 120)  # the rest: the strongest anywhere, as before
    # all of the budget may go to the region
    pts, _ = detect_harris(img, cfg, max_corners=12, priority=region)
    assert len(pts) == 12 and np.all(pts[:, 1] >= 130)


def test_priority_min_distance_gives_denser_corners_in_the_region():
    img = np.full((120, 160), 100, np.uint8)
    for y in range(16, 104, 6):  # a 6 px checker of 3 px squares: corners 3 px apart
        for x in range(16, 144, 6):
            img[y : y + 3, x : x + 3] = 200
    region = np.ones(img.shape, bool)
    cfg = HarrisConfig(min_distance=7, cell_cap=0)
    n_plain = len(detect_harris(img, cfg, max_corners=1000)[0])
    dense = dataclasses.replace(cfg, priority_min_distance=3)
    n_dense = len(detect_harris(img, dense, max_corners=1000, priority=region)[0])
    assert n_dense > 1.5 * n_plain


def test_priority_bad_input():
    img = corner_image()
    with pytest.raises(InputError, match="priority"):
        detect_harris(img, HarrisConfig(), priority=np.ones((10, 10), bool))
    with pytest.raises(InputError, match="priority_max"):
        detect_harris(img, HarrisConfig(), priority=np.ones(img.shape, bool), priority_max=-1)
    with pytest.raises(ConfigError):
        TrackConfig(priority_share=1.5)
    with pytest.raises(ConfigError):
        TrackConfig(priority_min_tracks=-1)
    with pytest.raises(ConfigError):
        HarrisConfig(priority_min_distance=-2)


def _manager(**kw):
    cam = CameraModel(CameraConfig.from_fov(320, 240, 60.0))
    return TrackManager(cam, HarrisConfig(grid_rows=1, grid_cols=1, cell_cap=0), NCCConfig(), TrackConfig(**kw))


def test_track_manager_refill_share_goes_to_the_region():
    img = corner_image()
    region = np.zeros(img.shape, bool)
    region[130:, :] = True
    tm = _manager(max_tracks=20, priority_share=0.5)
    tf = tm.step(img, 0.0, 0, priority_mask=region)
    assert len(tf.new_ids) == 20
    assert np.count_nonzero(tf.uv[:, 1] >= 130) == 10
    # share 0 (off): the strongest corners only, the mask is ignored
    tm = _manager(max_tracks=20, priority_share=0.0)
    tf = tm.step(img, 0.0, 0, priority_mask=region)
    assert np.count_nonzero(tf.uv[:, 1] >= 130) == 0


def test_track_manager_tops_up_a_starving_region():
    img = corner_image()
    region = np.zeros(img.shape, bool)
    region[130:, :] = True
    tm = _manager(max_tracks=40, redetect_fraction=0.5, priority_min_tracks=5)
    tf = tm.step(img, 0.0, 0)  # no region: 40 strong corners, all in the top half
    assert len(tf.ids) == 40 and np.all(tf.uv[:, 1] < 120)
    tm.kill(tf.ids[:4])  # 36 live, above redetect_fraction: no plain refill
    tf = tm.step(img, 1.0, 1)
    assert len(tf.new_ids) == 0
    tm.kill(tf.ids[:4])
    tf = tm.step(img, 2.0, 2, priority_mask=region)  # the region holds none: top up inside it only
    new = np.isin(tf.ids, tf.new_ids)
    assert np.count_nonzero(new) == 8 and np.all(tf.uv[new, 1] >= 130)
    tf = tm.step(img, 3.0, 3, priority_mask=region)  # now it holds 8 >= 5: nothing more
    assert len(tf.new_ids) == 0


# ---- the region's geometry on exact poses ------------------------------------------------------
@pytest.fixture
def cam():
    return CameraModel(CameraConfig.from_fov(320, 240, 60.0))


def test_flight_path_straight_ahead_gives_the_band_around_the_principal_point(cam):
    c = cam.config
    live = np.ones(SECTOR_COUNT, int)  # every sector has live points: only the flight path counts
    m = detection_priority(cam, SectorConfig(), velocity_body=[5.0, 0, 0], live_points=live,
                           band_range_m=8.0, path_half_width_deg=15.0, stride=1)
    assert m.shape == (240, 320)
    rows = np.flatnonzero(m[:, int(round(c.cx))])  # the centre column: tan(elevation) = (v − cy) / fy
    half_rows = c.fy * 1.5 / 8.0  # band_half_height_m / band_range_m
    assert abs(rows.min() - (c.cy - half_rows)) <= 1 and abs(rows.max() - (c.cy + half_rows)) <= 1
    # columns within 15° of the flight path at the horizon row
    half_cols = c.fx * math.tan(math.radians(15))
    r = int(round(c.cy))
    on = np.flatnonzero(m[r])
    assert abs(on.min() - (c.cx - half_cols)) <= 1 and abs(on.max() - (c.cx + half_cols)) <= 1
    assert not m[0].any() and not m[-1].any()
    # the same with the coarse grid (the pipeline's default): within a grid step
    mc = detection_priority(cam, SectorConfig(), velocity_body=[5.0, 0, 0], live_points=live, stride=4)
    assert np.count_nonzero(mc != m) < 0.1 * np.count_nonzero(m)


def test_a_climb_moves_the_band_up(cam):
    c = cam.config
    live = np.ones(SECTOR_COUNT, int)
    v = [5.0, 0.0, -5.0 * math.tan(math.radians(10))]  # climbing at 10° (z down)
    m = detection_priority(cam, SectorConfig(), velocity_body=v, live_points=live, stride=1)
    rows = np.flatnonzero(m.any(1))
    centre = c.cy - c.fy * math.tan(math.radians(10))
    assert abs(0.5 * (rows.min() + rows.max()) - centre) <= 3


def test_a_sector_without_live_points_adds_its_columns(cam):
    c = cam.config
    live = np.ones(SECTOR_COUNT, int)
    live[5] = 0  # 22.5°..27.5° right of forward: in view of a 60° camera
    m = detection_priority(cam, SectorConfig(), velocity_body=[5.0, 0, 0], live_points=live,
                           path_half_width_deg=10.0, stride=1)
    r = int(round(c.cy))
    on = np.flatnonzero(m[r])
    path = on[on < c.cx + c.fx * math.tan(math.radians(12))]
    sector = on[on > c.cx + c.fx * math.tan(math.radians(12))]
    assert abs(path.max() - (c.cx + c.fx * math.tan(math.radians(10)))) <= 1
    assert abs(sector.min() - (c.cx + c.fx * math.tan(math.radians(22.5)))) <= 1
    assert abs(sector.max() - (c.cx + c.fx * math.tan(math.radians(27.5)))) <= 1
    # hovering (no direction of travel): the whole band
    m = detection_priority(cam, SectorConfig(), velocity_body=[0.0, 0, 0], live_points=live, stride=1)
    assert m[r].all()


def test_roll_tilts_the_band(cam):
    c = cam.config
    live = np.ones(SECTOR_COUNT, int)
    m = detection_priority(cam, SectorConfig(), roll_pitch_rad=(math.radians(20), 0.0), velocity_body=None,
                           live_points=live, stride=1)
    # rolled right (right wing down): the horizon, and the band with it, rises to the right of the image
    left = np.flatnonzero(m[:, 20])
    right = np.flatnonzero(m[:, 300])
    assert left.mean() - right.mean() == pytest.approx((300 - 20) * math.tan(math.radians(20)), abs=6)


def test_live_points_per_sector_excludes_remembered():
    class S:
        obstacle_points = np.full(SECTOR_COUNT, 3)
        remembered_points = np.full(SECTOR_COUNT, 3)
        clear_points = np.zeros(SECTOR_COUNT, int)

    S.remembered_points = S.remembered_points.copy()
    S.remembered_points[0] = 1
    lp = live_points_per_sector(S)
    assert lp[0] == 2 and np.all(lp[1:] == 0)
    assert live_points_per_sector(None) is None


# ---- search windows close in (image motion ∝ 1/Z², window from the predicted depth) ---------
@pytest.mark.parametrize("Z", [2.0, 3.0, 6.0])
def test_known_depth_window_grows_as_one_over_depth_squared(Z):
    cam = CameraModel(CameraConfig.from_fov(320, 240, 60.0))
    f = cam.config.fx
    b, sigma, k, base = 0.05, 0.1, 2.0, 3.0  # camera moves 5 cm right; depth σ 10 cm
    uv = np.array([[cam.config.cx, cam.config.cy]])
    I = np.eye(3)
    p = predict_pixels_detailed(cam, uv, I, np.zeros(3), I, np.array([b, 0.0, 0.0]), 0.5, math.inf, base,
                                np.array([Z]), depth_sigma=np.array([sigma]), depth_sigma_k=k, max_radius_px=200.0)
    # the segment between depths Z ± kσ: u = cx − f b / depth; half its length + base
    half = 0.5 * f * b * (1 / (Z - k * sigma) - 1 / (Z + k * sigma))
    assert p.radius[0] == pytest.approx(half + base, rel=1e-9)
    assert half == pytest.approx(f * b * k * sigma / (Z**2 - (k * sigma) ** 2))
    assert p.uv[0, 0] == pytest.approx(cam.config.cx - 0.5 * f * b * (1 / (Z - k * sigma) + 1 / (Z + k * sigma)), abs=1e-9)
    # the true pixel (depth Z) is inside
    assert abs(cam.config.cx - f * b / Z - p.uv[0, 0]) <= p.radius[0]


def test_window_nearer_than_depth_min_uses_the_filtered_depth():
    cam = CameraModel(CameraConfig.from_fov(320, 240, 60.0))
    f, cx = cam.config.fx, cam.config.cx
    uv = np.array([[cx, cam.config.cy]])
    I = np.eye(3)
    Z, b = 1.0, 0.1  # 1 m: nearer than depth_min = 2 m; the point moves f·b/Z = 27.7 px
    p = predict_pixels_detailed(cam, uv, I, np.zeros(3), I, np.array([b, 0.0, 0.0]), 2.0, math.inf, 3.0,
                                np.array([Z]), depth_sigma=np.array([0.05]), max_radius_px=32.0)
    assert abs(cx - f * b / Z - p.uv[0, 0]) <= p.radius[0]
    assert p.radius[0] < 8.0


def test_no_previous_frame_means_the_whole_band(cam):
    m = detection_priority(cam, SectorConfig(), velocity_body=[0.0, 5.0, 0.0], live_points=None, stride=1)
    r = int(round(cam.config.cy))
    assert m[r].all() and not m[0].any()  # flying sideways, out of view: still the band
