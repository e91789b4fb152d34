"""Triangulation (DESIGN §3.3): exact on noise-free data, explicit rejections, never NaN."""

import numpy as np
import pytest

from companion.core.frames import so3_exp
from companion.core.triangulation import Reject, TriangulationConfig, triangulate_multiview, triangulate_poses
from companion.errors import InputError

CFG = TriangulationConfig()
rng = np.random.default_rng(3)


def observe(p_world, R_world_cam, p_world_cam):
    pc = (p_world - p_world_cam) @ R_world_cam
    return pc[:, :2] / pc[:, 2:3]


def two_poses():
    Ra, pa = so3_exp([0.02, -0.01, 0.03]), np.array([0.0, 0.0, 0.0])
    Rb, pb = so3_exp([-0.01, 0.04, 0.0]), np.array([1.5, 0.4, 2.0])
    return Ra, pa, Rb, pb


def test_exact_on_noise_free_data():
    Ra, pa, Rb, pb = two_poses()
    p = np.stack([rng.uniform(-10, 10, 100), rng.uniform(-5, 5, 100), rng.uniform(15, 60, 100)], 1)
    res = triangulate_poses(observe(p, Ra, pa), Ra, pa, observe(p, Rb, pb), Rb, pb, CFG)
    assert np.all(res.ok)
    np.testing.assert_allclose(res.p, p, rtol=1e-9, atol=1e-9)
    # depth is Z in camera a
    np.testing.assert_allclose(res.depth, ((p - pa) @ Ra)[:, 2], rtol=1e-9)


def test_multiview_exact_and_uses_all_views():
    p = np.array([[3.0, -2.0, 40.0], [-5.0, 1.0, 25.0]])
    K = 8
    Rs = so3_exp(rng.normal(scale=0.02, size=(K, 3)))
    Cs = np.stack([np.linspace(0, 3, K), np.linspace(0, 0.5, K), np.linspace(0, 8, K)], 1)
    # viewing ray of each point in each camera, rotated into the world frame
    rays = np.stack([
        np.stack([Rs[k] @ np.append(observe(p[i:i + 1], Rs[k], Cs[k])[0], 1.0) for k in range(K)])
        for i in range(len(p))
    ])
    centers = np.broadcast_to(Cs, (2, K, 3))
    mask = np.ones((2, K), bool)
    mask[1, 3:5] = False  # a gap in the second track
    res = triangulate_multiview(rays, centers, mask, CFG)
    assert np.all(res.ok)
    np.testing.assert_allclose(res.p, p, atol=1e-8)
    np.testing.assert_allclose(res.depth, np.linalg.norm(p - Cs[-1], axis=1), rtol=1e-9)


def test_zero_baseline_rejected():
    Ra, pa, _, _ = two_poses()
    Rb = Ra @ so3_exp([0.0, 0.05, 0.0])  # pure rotation
    p = np.array([[2.0, 1.0, 30.0]])
    res = triangulate_poses(observe(p, Ra, pa), Ra, pa, observe(p, Rb, pa), Rb, pa, CFG)
    assert res.reason[0] == Reject.SHORT_BASELINE
    assert np.all(np.isfinite(res.p)) and np.all(res.p == 0)


def test_focus_of_expansion_and_far_point_rejected():
    R = np.eye(3)
    pa, pb = np.zeros(3), np.array([0.0, 0.0, 3.0])  # moving along the optical axis
    p = np.array([[0.0, 0.0, 50.0], [0.05, 0.0, 50.0], [20.0, 0.0, 1e6]])
    res = triangulate_poses(observe(p, R, pa), R, pa, observe(p, R, pb), R, pb, CFG)
    assert res.reason[0] == Reject.LOW_PARALLAX  # exactly on the FOE: parallel rays
    assert res.reason[1] == Reject.LOW_PARALLAX  # near the FOE: below the parallax gate
    assert res.reason[2] == Reject.LOW_PARALLAX  # effectively at infinity
    assert np.all(np.isfinite(res.p)) and np.all(np.isfinite(res.range_sigma))


def test_point_behind_camera_rejected():
    R = np.eye(3)
    pa, pb = np.zeros(3), np.array([2.0, 0.0, 0.0])
    # rays that intersect behind both cameras (diverging forwards)
    xy_a = np.array([[-0.1, 0.0]])
    xy_b = np.array([[0.1, 0.0]])
    res = triangulate_poses(xy_a, R, pa, xy_b, R, pb, CFG)
    assert res.reason[0] == Reject.BEHIND_CAMERA


def test_uncertainty_gate_and_sigma():
    R = np.eye(3)
    pa, pb = np.zeros(3), np.array([1.0, 0.0, 0.0])
    p = np.array([[0.5, 0.0, 20.0]])
    ok = triangulate_poses(observe(p, R, pa), R, pa, observe(p, R, pb), R, pb, CFG, sigma_xy=1e-4)
    assert ok.ok[0]
    assert ok.range_sigma[0] == pytest.approx(np.sqrt(2) * np.linalg.norm(p) * 1e-4 / np.sin(ok.parallax_rad[0]))
    bad = triangulate_poses(observe(p, R, pa), R, pa, observe(p, R, pb), R, pb, CFG, sigma_xy=3e-2)
    assert bad.reason[0] == Reject.TOO_UNCERTAIN


def test_nan_is_reported_not_propagated():
    Ra, pa, Rb, pb = two_poses()
    xy = np.array([[0.1, 0.0], [np.nan, 0.0]])
    res = triangulate_poses(xy, Ra, pa, xy, Rb, pb, CFG)
    assert res.reason[1] == Reject.NON_FINITE
    assert np.all(np.isfinite(res.p))


def test_shape_errors():
    with pytest.raises(InputError, match="differ in length"):
        triangulate_poses(np.zeros((2, 2)), np.eye(3), np.zeros(3), np.zeros((3, 2)), np.eye(3), np.ones(3), CFG)
    with pytest.raises(InputError, match="trailing shape"):
        triangulate_poses(np.zeros((2, 3)), np.eye(3), np.zeros(3), np.zeros((2, 3)), np.eye(3), np.ones(3), CFG)
