"""Telemetry pixel prediction (DESIGN.md §3.2): epipolar window, pure rotation, known depth, behind."""

import math

import numpy as np
import pytest

from companion.core.camera import CameraConfig, CameraModel
from companion.core.frames import so3_exp
from companion.core.prediction import (
    PRED_BEHIND,
    PRED_OK,
    PRED_PARTLY_BEHIND,
    PredictionConfig,
    bearing_parallax,
    make_track_predictor,
    predict_pixels,
    predict_pixels_detailed,
)
from companion.errors import ConfigError, InputError


@pytest.fixture(params=[False, True], ids=["pinhole", "distorted"])
def cam(request):
    dist = (-0.25, 0.08, 0.001, -0.0015, -0.01) if request.param else (0.0,) * 5
    return CameraModel(CameraConfig(width=640, height=480, fx=520.0, fy=515.0, cx=322.0, cy=236.0, distortion=dist))


def poses():
    R_prev = so3_exp(np.array([0.05, -0.02, 0.3]))
    p_prev = np.array([10.0, -4.0, -30.0])
    R_cur = R_prev @ so3_exp(np.array([0.015, -0.02, 0.01]))  # ~1.5° of rotation between frames
    p_cur = p_prev + R_prev @ np.array([0.4, -0.2, 1.5])  # mostly along the optical axis
    return R_prev, p_prev, R_cur, p_cur


def scene_points(cam, n, z_lo, z_hi, seed=0):
    rng = np.random.default_rng(seed)
    uv = np.stack([rng.uniform(20, 620, n), rng.uniform(20, 460, n)], 1)
    z = rng.uniform(z_lo, z_hi, n)
    rays = np.concatenate([cam.pixels_to_normalized(uv), np.ones((n, 1))], 1)
    return uv, z, rays * z[:, None]


def test_true_pixel_lies_inside_the_predicted_window(cam):
    R_prev, p_prev, R_cur, p_cur = poses()
    uv, z, p_cam = scene_points(cam, 300, 4.0, 500.0)
    p_world = p_cam @ R_prev.T + p_prev
    truth = cam.project(cam.world_to_camera(p_world, R_cur, p_cur))
    uv_pred, radius = predict_pixels(cam, uv, R_prev, p_prev, R_cur, p_cur, 3.0, math.inf, 2.0, max_radius_px=1e4)
    d = np.linalg.norm(truth - uv_pred, axis=1)
    assert np.all(d <= radius)
    assert np.all(radius >= 2.0)
    # the window is not absurdly large: the segment from 3 m to infinity
    assert np.median(radius) < 200


def test_infinite_depth_is_the_pure_rotation_mapping(cam):
    R_prev, p_prev, R_cur, p_cur = poses()
    uv, _, _ = scene_points(cam, 100, 1.0, 2.0, seed=1)
    det = predict_pixels_detailed(cam, uv, R_prev, p_prev, R_cur, p_cur, 3.0, math.inf, 2.0)
    m = np.concatenate([cam.pixels_to_normalized(uv), np.ones((100, 1))], 1) @ (R_cur.T @ R_prev).T
    rot = cam.normalized_to_pixels(m[:, :2] / m[:, 2:])
    assert np.allclose(det.uv_far, rot, atol=1e-9)
    # without translation every depth maps to the rotation image: window = base radius
    uv_pred, radius = predict_pixels(cam, uv, R_prev, p_prev, R_cur, p_prev, 3.0, math.inf, 2.0)
    assert np.allclose(uv_pred, rot, atol=1e-9) and np.allclose(radius, 2.0)
    # and the same holds for the K R K⁻¹ homography of an ideal pinhole
    if not cam.config.has_distortion:
        K = cam.K
        Hm = K @ R_cur.T @ R_prev @ np.linalg.inv(K)
        q = np.concatenate([uv, np.ones((100, 1))], 1) @ Hm.T
        assert np.allclose(det.uv_far, q[:, :2] / q[:, 2:], atol=1e-9)


def test_known_depth_centres_exactly_with_the_base_radius(cam):
    R_prev, p_prev, R_cur, p_cur = poses()
    uv, z, p_cam = scene_points(cam, 50, 5.0, 80.0, seed=2)
    truth = cam.project(cam.world_to_camera(p_cam @ R_prev.T + p_prev, R_cur, p_cur))
    uv_pred, radius = predict_pixels(cam, uv, R_prev, p_prev, R_cur, p_cur, 3.0, math.inf, 1.5, depth=z)
    assert np.abs(uv_pred - truth).max() < 1e-6 and np.allclose(radius, 1.5)
    _, wide = predict_pixels(cam, uv, R_prev, p_prev, R_cur, p_cur, 3.0, math.inf, 1.5)
    _, mid = predict_pixels(cam, uv, R_prev, p_prev, R_cur, p_cur, 3.0, math.inf, 1.5, depth=z, depth_sigma=0.2 * z)
    assert np.all(mid >= radius) and np.all(mid <= wide + 1e-9)
    # unknown entries (depth <= 0) fall back to the depth range
    mixed = np.where(np.arange(50) % 2 == 0, z, 0.0)
    _, r_mixed = predict_pixels(cam, uv, R_prev, p_prev, R_cur, p_cur, 3.0, math.inf, 1.5, depth=mixed)
    assert np.allclose(r_mixed[::2], 1.5) and np.allclose(r_mixed[1::2], np.minimum(wide[1::2], 32.0))


def test_points_behind_the_new_camera_are_flagged_never_nan():
    cam = CameraModel(CameraConfig())
    R = np.eye(3)
    uv = np.array([[320.0, 240.0], [100.0, 50.0], [600.0, 400.0]])
    # the camera flies 50 m forward: everything between 2 m and 20 m is now behind it
    det = predict_pixels_detailed(cam, uv, R, np.zeros(3), R, np.array([0.0, 0.0, 50.0]), 2.0, 20.0, 2.0, max_radius_px=40.0)
    assert np.all(det.status == PRED_BEHIND)
    assert np.allclose(det.uv, uv) and np.allclose(det.radius, 40.0)
    # with an infinite far end, the far part is still ahead: partly behind, finite, max radius
    det = predict_pixels_detailed(cam, uv, R, np.zeros(3), R, np.array([0.0, 0.0, 50.0]), 2.0, math.inf, 2.0, max_radius_px=40.0)
    assert np.all(det.status == PRED_PARTLY_BEHIND)
    assert np.all(np.isfinite(det.uv)) and np.allclose(det.radius, 40.0)
    ok = predict_pixels_detailed(cam, uv, R, np.zeros(3), R, np.array([0.0, 0.0, 0.5]), 2.0, math.inf, 2.0, max_radius_px=1e4)
    assert np.all(ok.status == PRED_OK)


def test_track_predictor_adapter(cam):
    R_prev, p_prev, R_cur, p_cur = poses()
    cfg = PredictionConfig(depth_min_m=3.0, base_radius_px=2.0, max_radius_px=1e4)
    predict = make_track_predictor(cam, cfg, (R_prev, p_prev), (R_cur, p_cur), with_parallax=True)
    uv, z, p_cam = scene_points(cam, 40, 5.0, 60.0, seed=3)
    uv_pred, radius, parallax = predict(uv, np.arange(40))
    assert uv_pred.shape == (40, 2) and radius.shape == (40,)
    np.testing.assert_allclose(parallax, bearing_parallax(cam, uv, R_prev, p_prev, R_cur, p_cur))
    truth = cam.project(cam.world_to_camera(p_cam @ R_prev.T + p_prev, R_cur, p_cur))
    assert np.all(np.linalg.norm(truth - uv_pred, axis=1) <= radius)
    with_depth = make_track_predictor(cam, cfg, (R_prev, p_prev), (R_cur, p_cur), depth_of=lambda ids: (z[ids], None))
    uv_k, r_k = with_depth(uv, np.arange(40))  # without with_parallax: no third element
    assert np.abs(uv_k - truth).max() < 1e-6 and np.allclose(r_k, 2.0)


def test_bearing_parallax_is_the_image_motion_per_inverse_depth():
    """|∂uv/∂ρ| at ρ = 0 against a finite difference of the projection; zero at the focus of expansion."""
    cam = CameraModel(CameraConfig(width=320, height=240, fx=277.0, fy=290.0, cx=159.5, cy=119.5))
    R_prev, p_prev, R_cur, p_cur = poses()
    uv, _, _ = scene_points(cam, 30, 5.0, 60.0, seed=5)
    got = bearing_parallax(cam, uv, R_prev, p_prev, R_cur, p_cur)
    m = np.column_stack([cam.pixels_to_normalized(uv), np.ones(len(uv))])
    rays_world = m @ R_prev.T  # direction of each ray in the world
    h = 1e-6  # inverse depth step (1/m): the point at depth 1/h along the ray
    far = cam.project(cam.world_to_camera(p_prev + rays_world / h, R_cur, p_cur))
    nearer = cam.project(cam.world_to_camera(p_prev + rays_world / (2 * h), R_cur, p_cur))  # ρ = 2h
    np.testing.assert_allclose(got, np.linalg.norm(far - nearer, axis=1) / h, rtol=1e-3)
    # straight ahead along the optical axis: the focus of expansion is the principal point
    R = np.eye(3)
    foe = bearing_parallax(cam, np.array([[159.5, 119.5], [200.0, 119.5], [300.0, 119.5]]), R, np.zeros(3), R, np.array([0.0, 0.0, 1.0]))
    assert foe[0] == pytest.approx(0.0, abs=1e-12) and 0 < foe[1] < foe[2]
    assert bearing_parallax(cam, np.zeros((0, 2)), R, np.zeros(3), R, np.zeros(3)).shape == (0,)
    with pytest.raises(InputError, match="R_world_cam_cur"):
        bearing_parallax(cam, uv, R_prev, p_prev, np.full((3, 3), np.nan), p_cur)


def test_bad_input_names_the_problem():
    cam = CameraModel(CameraConfig())
    R, p = np.eye(3), np.zeros(3)
    uv = np.array([[100.0, 100.0]])
    with pytest.raises(InputError, match="uv_prev"):
        predict_pixels(cam, np.array([[np.nan, 1.0]]), R, p, R, p, 1.0, 10.0, 2.0)
    with pytest.raises(InputError, match="uv_prev"):
        predict_pixels(cam, np.zeros((2, 3)), R, p, R, p, 1.0, 10.0, 2.0)
    with pytest.raises(InputError, match="R_world_cam_cur"):
        predict_pixels(cam, uv, R, p, R * 2, p, 1.0, 10.0, 2.0)
    with pytest.raises(InputError, match="R_world_cam_prev"):
        predict_pixels(cam, uv, np.full((3, 3), np.nan), p, R, p, 1.0, 10.0, 2.0)
    with pytest.raises(InputError, match="p_world_cam_cur"):
        predict_pixels(cam, uv, R, p, R, np.array([0.0, np.inf, 0.0]), 1.0, 10.0, 2.0)
    with pytest.raises(InputError, match="depth_min"):
        predict_pixels(cam, uv, R, p, R, p, 0.0, 10.0, 2.0)
    with pytest.raises(InputError, match="depth_max"):
        predict_pixels(cam, uv, R, p, R, p, 5.0, 2.0, 2.0)
    with pytest.raises(InputError, match="depth"):
        predict_pixels(cam, uv, R, p, R, p, 1.0, 10.0, 2.0, depth=np.array([np.nan]))
    with pytest.raises(InputError, match="depth"):
        predict_pixels(cam, uv, R, p, R, p, 1.0, 10.0, 2.0, depth=np.ones(3))
    with pytest.raises(ConfigError, match="depth_max_m"):
        PredictionConfig(depth_min_m=5.0, depth_max_m=1.0)


def test_a_capped_window_covers_the_far_end_of_the_segment(cam):
    """Fast forward flight: from 1 m to infinity the segment is longer than the cap; far points
    (the common case) must still fall inside the window, and the near end is given up first."""
    R_prev, p_prev, R_cur, p_cur = poses()
    uv, z, p_cam = scene_points(cam, 300, 150.0, 400.0, seed=3)
    p_world = p_cam @ R_prev.T + p_prev
    truth = cam.project(cam.world_to_camera(p_world, R_cur, p_cur))
    det = predict_pixels_detailed(cam, uv, R_prev, p_prev, R_cur, p_cur, 1.0, math.inf, 3.0, max_radius_px=24.0)
    capped = det.status != PRED_OK
    assert capped.sum() > 50, "the scenario must exercise the cap"
    d = np.linalg.norm(truth - det.uv, axis=1)
    assert np.all(d[capped] <= det.radius[capped])
    far = np.linalg.norm(det.uv_far - det.uv, axis=1)
    assert np.all(far[capped] <= det.radius[capped] - 3.0 + 1e-9)  # the ρ = 0 image with its base margin
    # the window no longer sits on the middle of the segment (which would lose the far points)
    mid = np.linalg.norm(0.5 * (det.uv_far + det.uv_near) - det.uv, axis=1)
    seg = np.linalg.norm(det.uv_near - det.uv_far, axis=1)
    long_seg = capped & (seg > 2 * 24.0)
    assert long_seg.sum() > 20
    assert np.all(mid[long_seg] > 0.5 * seg[long_seg] - 24.0 - 1e-9)
