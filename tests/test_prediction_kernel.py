"""The compiled telemetry-prediction kernel against the pure-numpy reference (seed 004 §3.2;
companion/core/prediction.py module docstring).

The status of every point (ok, capped, partly or wholly behind) must be identical; the window
centre, radius and segment ends agree within rtol = atol = 1e-9 px.  Why 1e-9: the kernel evaluates
the reference's expressions per point in the same order, except R·m (a fixed order of summation
here, BLAS there: ≤ 1 ulp) — the pixel error is that ulp magnified by the projection, at most
~1e-16 · |q|/z · f ≈ 1e-11 px for samples just in front of the camera (z ≥ 1e-3 |q|) at the
10·(W + H) px clip; 1e-9 px leaves a margin and still catches any real difference (a window moved
by the smallest change of the rules moves by far more).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.core import jit
from companion.core import prediction as PR
from companion.core.camera import CameraConfig, CameraModel
from companion.core.frames import so3_exp
from companion.core.prediction import PRED_BEHIND, PRED_CAPPED, PRED_OK, PRED_PARTLY_BEHIND, predict_pixels_detailed
from companion.errors import InputError

TOL = 1e-9
N_CASES = 400 if jit.ENABLED else 40
CAMERAS = {
    "pinhole": CameraConfig(width=640, height=480, fx=554.3, fy=554.3, cx=319.5, cy=239.5),
    "distorted": CameraConfig(width=640, height=480, fx=520.0, fy=515.0, cx=322.0, cy=236.0,
                              distortion=(-0.25, 0.08, 0.001, -0.0015, -0.01)),
    "rational": CameraConfig(width=320, height=240, fx=260.0, fy=262.0, cx=161.0, cy=118.0,
                             distortion=(0.1, -0.05, 0.0005, 0.0002, 0.01, 0.05, -0.02, 0.003)),
}


def both(monkeypatch, *args, **kwargs):
    """predict_pixels_detailed with kernels on, then off (the reference)."""
    out = []
    for enabled in (True, False):
        monkeypatch.setattr(jit, "ENABLED", enabled)
        out.append(predict_pixels_detailed(*args, **kwargs))
    monkeypatch.setattr(jit, "ENABLED", True)
    return out


def assert_same_prediction(k: PR.PixelPrediction, r: PR.PixelPrediction, what: str) -> None:
    assert k.status.dtype == r.status.dtype and np.array_equal(k.status, r.status), f"{what}: status"
    for f in ("uv", "radius", "uv_far", "uv_near"):
        a, b = getattr(k, f), getattr(r, f)
        assert a.shape == b.shape, f"{what}: {f} shape"
        np.testing.assert_allclose(a, b, rtol=TOL, atol=TOL, err_msg=f"{what}: {f}")


def random_case(rng: np.random.Generator, cam: CameraModel):
    """Seeded poses (small steps and violent ones, forward, sideways and backward), pixels anywhere in
    the image, known depths of every kind (unknown ≤ 0, near, far, infinite, with and without σ)."""
    c = cam.config
    n = int(rng.integers(0, 300))
    uv = np.stack([rng.uniform(0, c.width - 1, n), rng.uniform(0, c.height - 1, n)], 1)
    R_prev = so3_exp(rng.normal(0, 1.0, 3))
    p_prev = rng.normal(0, 50, 3)
    scale = rng.choice([0.01, 0.2, 2.0])
    R_cur = R_prev @ so3_exp(rng.normal(0, scale * 0.1, 3))
    p_cur = p_prev + R_prev @ (rng.normal(0, scale, 3) + [0, 0, rng.choice([-1.0, 0.0, 1.0]) * scale])
    kw = dict(max_radius_px=float(rng.choice([8.0, 32.0, 200.0])), samples=int(rng.integers(2, 10)))
    if rng.random() < 0.7:
        d = rng.choice([-1.0, 0.0, 0.5, 3.0, 40.0, 800.0, math.inf], n) * rng.uniform(0.8, 1.2, n)
        kw["depth_sigma"] = None if rng.random() < 0.3 else rng.uniform(0, 5, n) * (rng.random(n) < 0.8)
        kw["depth_sigma_k"] = float(rng.choice([0.0, 2.0, 3.0]))
        depth = d
    else:
        depth = None
    depth_min = float(rng.choice([0.5, 2.0, 5.0]))
    depth_max = float(rng.choice([math.inf, 60.0, 1e4]))
    base = float(rng.choice([0.0, 3.0]))
    return (cam, uv, R_prev, p_prev, R_cur, p_cur, depth_min, depth_max, base, depth), kw


@pytest.mark.parametrize("camera", list(CAMERAS))
def test_kernel_equals_reference_on_seeded_cases(monkeypatch, camera):
    cam = CameraModel(CAMERAS[camera])
    rng = np.random.default_rng(len(camera))
    seen = np.zeros(4, int)
    for i in range(N_CASES):
        args, kw = random_case(rng, cam)
        k, r = both(monkeypatch, *args, **kw)
        assert_same_prediction(k, r, f"{camera} case {i}")
        seen += np.bincount(r.status, minlength=4)
    assert np.all(seen > 0), seen  # every status occurs: the comparison is not vacuous


@pytest.mark.parametrize("case", ["empty", "one point", "all behind", "pure rotation", "standing still", "corners",
                                  "radius at the cap"])
def test_kernel_edge_cases(monkeypatch, case):
    cam = CameraModel(CAMERAS["distorted"])
    R = so3_exp(np.array([0.1, -0.2, 0.3]))
    p = np.array([1.0, 2.0, 3.0])
    uv = {"empty": np.zeros((0, 2)), "one point": np.array([[100.0, 50.0]]),
          "corners": np.array([[0.0, 0.0], [639.0, 0.0], [0.0, 479.0], [639.0, 479.0], [322.0, 236.0]])}.get(
        case, np.array([[100.0, 50.0], [320.0, 240.0], [600.0, 400.0]]))
    R_cur, p_cur = R, p + R @ np.array([0.2, 0.0, 1.0])
    if case == "all behind":
        p_cur = p + R @ np.array([0.0, 0.0, 50.0])  # flew 50 m past every point nearer than that
    elif case == "pure rotation":
        R_cur, p_cur = R @ so3_exp(np.array([0.0, 0.05, 0.0])), p
    elif case in ("standing still", "radius at the cap"):
        R_cur, p_cur = R, p
    base = 32.0 if case == "radius at the cap" else 3.0  # a point's window: radius = 0 + base = the cap exactly: not capped
    k, r = both(monkeypatch, cam, uv, R, p, R_cur, p_cur, 2.0, 40.0 if case == "all behind" else math.inf, base, max_radius_px=32.0)
    assert_same_prediction(k, r, case)
    if case == "all behind":
        assert np.all(r.status == PRED_BEHIND)
    if case in ("pure rotation", "standing still", "radius at the cap"):
        assert np.all(r.status == PRED_OK)


def test_kernel_raises_what_the_reference_raises(monkeypatch):
    cam = CameraModel(CAMERAS["pinhole"])
    R, p = np.eye(3), np.zeros(3)
    uv = np.array([[10.0, 10.0], [20.0, 20.0]])
    bad = [dict(uv_prev=np.array([[np.nan, 1.0]])), dict(depth=np.array([1.0, np.nan])),
           dict(depth=np.array([1.0, 2.0]), depth_sigma=np.array([-1.0, 0.0])), dict(R_world_cam_cur=2 * np.eye(3)),
           dict(depth_min=0.0), dict(depth_max=1.0), dict(samples=1)]
    for b in bad:
        a = dict(camera=cam, uv_prev=uv, R_world_cam_prev=R, p_world_cam_prev=p, R_world_cam_cur=R, p_world_cam_cur=p,
                 depth_min=2.0, depth_max=math.inf, base_radius_px=3.0) | b
        for enabled in (True, False):
            monkeypatch.setattr(jit, "ENABLED", enabled)
            with pytest.raises(InputError):
                predict_pixels_detailed(**a)


def test_reference_directly_pure_rotation():
    """The reference itself: with the camera only turning, the far end of the segment (ρ = 0) is
    the pure-rotation image of the previous pixel, K R K⁻¹ uv."""
    cam = CameraModel(CAMERAS["pinhole"])
    R_prev = np.eye(3)
    R_cur = so3_exp(np.array([0.0, 0.02, 0.0]))
    uv = np.array([[100.0, 200.0], [320.0, 240.0]])
    m = np.concatenate([cam.pixels_to_normalized(uv), np.ones((2, 1))], 1)
    q = m @ (R_cur.T @ R_prev).T
    expected = cam.normalized_to_pixels(q[:, :2] / q[:, 2:])
    r = PR._predict_reference(cam, uv, R_prev, np.zeros(3), R_cur, np.zeros(3), 2.0, math.inf, 3.0, None, None, 2.0, 32.0, 5)
    np.testing.assert_allclose(r.uv_far, expected, atol=1e-9)
    np.testing.assert_allclose(r.uv_near, expected, atol=1e-9)  # no translation: the segment is a point
    assert np.all(r.status == PRED_OK) and np.allclose(r.radius, 3.0)


def test_statuses_are_the_module_codes():
    assert (PRED_OK, PRED_CAPPED, PRED_PARTLY_BEHIND, PRED_BEHIND) == (0, 1, 2, 3)  # hard-coded in the kernel


@pytest.mark.skipif(not jit.ENABLED, reason="whole flight: compiled kernels only")
def test_kernel_equals_reference_on_a_flight(monkeypatch):
    """The tracker's predictions on a short turning, rocking flight (filtered depths included)."""
    import companion.core.prediction as P
    from flight_inputs import fly

    orig = P.predict_pixels_detailed
    calls = []

    def both_paths(*a, **kw):
        monkeypatch.setattr(jit, "ENABLED", False)
        r = orig(*a, **kw)
        monkeypatch.setattr(jit, "ENABLED", True)
        k = orig(*a, **kw)
        assert_same_prediction(k, r, f"frame {len(calls)}")
        calls.append(int(np.sum(r.status != PRED_OK)))
        return k

    monkeypatch.setattr(P, "predict_pixels_detailed", both_paths)
    fly(frames=45)
    assert len(calls) >= 40


def test_warm_up_is_registered():
    assert PR._warm_up in jit._WARMUPS
    PR._warm_up()
