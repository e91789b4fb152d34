"""Frames (DESIGN §2) and the camera model: exact round trips and known geometry."""

import math

import numpy as np
import pytest

from companion.core import frames
from companion.core.camera import CameraConfig, CameraModel
from companion.errors import ConfigError, InputError

rng = np.random.default_rng(1)


def random_rotations(n):
    return frames.so3_exp(rng.normal(size=(n, 3)))


def test_euler_zyx_to_R_scalar_is_euler_zyx_to_R_bit_for_bit():
    """The per-frame scalar form (math instead of numpy on 0-d arrays) gives the same matrix exactly
    (the compiled sector and priority paths rely on it to level points as the reference does)."""
    rng = np.random.default_rng(12)
    for _ in range(20000):
        rpy = rng.uniform(-math.pi, math.pi, 3) * rng.choice([1.0, 1e-3, 1e-9, 0.0], 3)
        assert np.array_equal(frames.euler_zyx_to_R_scalar(*rpy), frames.euler_zyx_to_R(*rpy)), rpy


def test_single_attitude_forms_are_the_vectorized_ones_bit_for_bit():
    """The telemetry buffer's per-message forms (Python floats, numpy ufuncs only for the
    transcendental functions) reproduce the vectorized functions exactly, near the gimbal lock,
    at the identity, and for opposite-sign quaternion pairs in the slerp."""
    rng = np.random.default_rng(13)
    for k in range(20000):
        rpy = rng.uniform(-math.pi, math.pi, 3) * rng.choice([1.0, 1e-3, 1e-9, 0.0], 3)
        if k % 7 == 0:
            rpy[1] = rng.choice([math.pi / 2, -math.pi / 2, 1.5707963, 0.0])
        R = frames.euler_zyx_to_R_scalar(*rpy)
        q = frames.R_to_quat(R)
        assert np.array_equal(frames.R_to_quat_scalar(R), q), rpy
        q_scaled = q * rng.uniform(0.5, 2.0)
        assert np.array_equal(frames.quat_to_R_scalar(q_scaled), frames.quat_to_R(q_scaled)), q_scaled
        Rq = frames.quat_to_R(q)
        assert np.array_equal(frames.R_to_euler_zyx_scalar(Rq), frames.R_to_euler_zyx(Rq)), rpy
        q1 = frames.R_to_quat(frames.euler_zyx_to_R(*(rpy + rng.normal(0.0, rng.choice([1e-12, 1e-6, 0.01, 3.0]), 3))))
        q1 = -q1 if k % 5 == 0 else q1
        s = float(rng.choice([0.0, 1.0, rng.uniform()]))
        assert np.array_equal(frames.quat_slerp_scalar(q, q1, s), frames.quat_slerp(q, q1, s)), (q, q1, s)
    for bad in ([math.nan, 0, 0, 1], [0.0, 0.0, 0.0, 0.0]):
        with pytest.raises(InputError):
            frames.quat_to_R_scalar(bad)


def test_euler_round_trip_and_axes():
    rpy = np.stack([rng.uniform(-3, 3, 50), rng.uniform(-1.5, 1.5, 50), rng.uniform(-3, 3, 50)], 1)
    R = frames.euler_zyx_to_R(*rpy.T)
    np.testing.assert_allclose(frames.R_to_euler_zyx(R), rpy, atol=1e-12)
    # yaw 90°: body forward points east in NED
    R = frames.euler_zyx_to_R(0.0, 0.0, math.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # pitch up 90°: body forward points up (−z in NED)
    R = frames.euler_zyx_to_R(0.0, math.pi / 2, 0.0)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    # roll right 90°: body right axis points down
    R = frames.euler_zyx_to_R(math.pi / 2, 0.0, 0.0)
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-12)


def test_quaternion_round_trip_and_slerp():
    R = random_rotations(100)
    q = frames.R_to_quat(R)
    np.testing.assert_allclose(frames.quat_to_R(q), R, atol=1e-12)
    assert np.all(q[:, 0] >= 0)
    q0 = frames.R_to_quat(np.eye(3))
    q1 = frames.R_to_quat(frames.so3_exp([0, 0, 1.0]))
    half = frames.quat_slerp(q0, q1, 0.5)
    np.testing.assert_allclose(frames.quat_to_R(half), frames.so3_exp([0, 0, 0.5]), atol=1e-12)
    with pytest.raises(InputError, match="zero norm"):
        frames.quat_to_R([0, 0, 0, 0])


def test_so3_exp_log_and_twist():
    phi = rng.normal(size=(100, 3))
    phi *= (np.minimum(np.linalg.norm(phi, axis=1), 3.0) / np.linalg.norm(phi, axis=1))[:, None]
    np.testing.assert_allclose(frames.so3_log(frames.so3_exp(phi)), phi, atol=1e-9)
    # constant twist: integrate dP/dt = −v − w×P and compare with the pose change
    v, w, dt = np.array([1.0, -0.5, 3.0]), np.array([0.2, -0.1, 0.3]), 0.7
    R0, p0 = frames.so3_exp([0.1, 0.2, 0.3]), np.array([1.0, 2.0, 3.0])
    # pose after dt with body twist (v, w): R1 = R0 Exp(w dt), p1 = p0 + R0 V(w dt) v dt
    th = w * dt
    K = frames.skew(th)
    a = np.linalg.norm(th)
    V = np.eye(3) + (1 - math.cos(a)) / a**2 * K + (a - math.sin(a)) / a**3 * K @ K
    R1, p1 = R0 @ frames.so3_exp(th), p0 + R0 @ V @ v * dt
    v_est, w_est = frames.se3_twist(R0, p0, R1, p1, dt)
    np.testing.assert_allclose(v_est, v, atol=1e-9)
    np.testing.assert_allclose(w_est, w, atol=1e-9)


def test_forward_camera_axes():
    cam = CameraModel(CameraConfig())
    R_world_cam, p_world_cam = cam.camera_pose(np.eye(3), np.zeros(3))
    # a point 10 m north of a level, north-facing vehicle is on the optical axis
    pc = cam.world_to_camera(np.array([[10.0, 0, 0]]), R_world_cam, p_world_cam)
    np.testing.assert_allclose(pc, [[0, 0, 10]], atol=1e-12)
    # east → image right (+x), down → image down (+y)
    pc = cam.world_to_camera(np.array([[10.0, 1, 2]]), R_world_cam, p_world_cam)
    np.testing.assert_allclose(pc, [[1, 2, 10]], atol=1e-12)


def test_mount_and_lever_arm():
    cfg = CameraConfig(mount_rpy_deg=(0.0, -30.0, 0.0), lever_arm_m=(0.2, 0.0, 0.1))
    cam = CameraModel(cfg)
    R_world_cam, p_world_cam = cam.camera_pose(np.eye(3), np.array([5.0, 0, -10]))
    np.testing.assert_allclose(p_world_cam, [5.2, 0, -9.9])
    # the optical axis is tilted 30° down from forward
    axis_world = R_world_cam @ [0, 0, 1]
    np.testing.assert_allclose(axis_world, [math.cos(math.radians(30)), 0, math.sin(math.radians(30))], atol=1e-12)


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.28, 0.07, 1e-3, -5e-4, 0.01)])
def test_project_unproject_round_trip(dist):
    cam = CameraModel(CameraConfig(distortion=dist))
    p = np.stack([rng.uniform(-3, 3, 200), rng.uniform(-2, 2, 200), rng.uniform(4, 40, 200)], 1)
    uv = cam.project(p)
    rays = cam.unproject(uv)
    np.testing.assert_allclose(rays, p / np.linalg.norm(p, axis=1, keepdims=True), atol=1e-9)
    pin = cam.undistort_to_pinhole(uv)
    np.testing.assert_allclose(pin, np.stack([cam.K[0, 0] * p[:, 0] / p[:, 2] + cam.K[0, 2],
                                              cam.K[1, 1] * p[:, 1] / p[:, 2] + cam.K[1, 2]], 1), atol=1e-6)


def test_distortion_matches_opencv():
    import cv2

    cfg = CameraConfig(distortion=(-0.28, 0.07, 1e-3, -5e-4, 0.01))
    cam = CameraModel(cfg)
    p = np.stack([rng.uniform(-3, 3, 50), rng.uniform(-2, 2, 50), rng.uniform(4, 40, 50)], 1)
    uv_cv, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cfg.K, cfg.dist)
    np.testing.assert_allclose(cam.project(p), uv_cv.reshape(-1, 2), atol=1e-9)


def test_fov_constructor():
    cfg = CameraConfig.from_fov(320, 240, 45.0)
    assert cfg.fx == pytest.approx(386.27, abs=0.01)
    assert math.degrees(cfg.hfov_rad) == pytest.approx(45.0, abs=0.01)


def test_camera_bad_input():
    cam = CameraModel(CameraConfig())
    with pytest.raises(InputError, match="behind"):
        cam.project([[0, 0, -1.0]])
    with pytest.raises(InputError, match="NaN"):
        cam.unproject([[np.nan, 1.0]])
    with pytest.raises(ConfigError, match="fx"):
        CameraConfig(fx=-1.0)
    with pytest.raises(ConfigError, match="distortion"):
        CameraConfig(distortion=(0.1, 0.2))
