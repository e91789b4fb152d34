"""Looming (DESIGN §7): the scale-change measurement of the anchored EKF, its Jacobian, its bad-input
reasons, and range at the focus of expansion where bearings alone give nothing."""

import numpy as np
import pytest

from companion.core.camera import CameraConfig, CameraModel
from companion.core.ekf_anchored import (
    GATED, LOOM_NAN, LOOM_NONPOSITIVE, UPDATED, AnchoredEKFConfig, AnchoredInverseDepthEKF, inverse_depth_state,
)
from companion.core.estimator import EstimatorConfig, RangeEstimator
from companion.core.frames import so3_exp
from companion.errors import ConfigError

rng = np.random.default_rng(11)


def numeric_Hs(x, RA, pA, Rp, Cp, Rc, C, dtp, dt, eps=1e-7):
    n = x.shape[1]
    H = np.zeros((len(x), n))
    for j in range(n):
        d = np.zeros(n)
        d[j] = eps
        hp = AnchoredInverseDepthEKF.measure_looming(x + d, RA, pA, Rp, Cp, Rc, C, dtp, dt)[0]
        hm = AnchoredInverseDepthEKF.measure_looming(x - d, RA, pA, Rp, Cp, Rc, C, dtp, dt)[0]
        H[:, j] = (hp - hm) / (2 * eps)
    return H


@pytest.mark.parametrize("n", [3, 6])
def test_looming_jacobian_matches_numeric(n):
    N = 50
    x = np.stack([rng.uniform(-0.5, 0.5, N), rng.uniform(-0.4, 0.4, N), rng.uniform(0.01, 0.3, N)], 1)
    if n == 6:
        x = np.concatenate([x, rng.normal(scale=0.01, size=(N, 3))], 1)
    RA = so3_exp(rng.normal(scale=0.1, size=(N, 3)))
    pA = rng.normal(size=(N, 3))
    Rp = RA @ so3_exp(rng.normal(scale=0.05, size=(N, 3)))
    Rc = Rp @ so3_exp(rng.normal(scale=0.02, size=(N, 3)))
    Cp = pA + np.einsum("nij,j->ni", RA, [0.3, -0.2, 1.5])
    C = Cp + np.einsum("nij,j->ni", Rp, [0.05, 0.02, 0.4])
    dtp = rng.uniform(0.1, 3.0, N)
    dt = dtp + 0.05
    hs, Hs = AnchoredInverseDepthEKF.measure_looming(x, RA, pA, Rp, Cp, Rc, C, dtp, dt)
    assert np.median(hs) > 1.0  # approaching: the patch grows (mostly; the rotation tilts a few)
    np.testing.assert_allclose(Hs, numeric_Hs(x, RA, pA, Rp, Cp, Rc, C, dtp, dt), rtol=1e-5, atol=1e-8)


def test_looming_model_is_the_depth_ratio():
    """h_s at the true state is Z_prev / Z_now of the point, for any pose."""
    N = 20
    p = rng.uniform([-5, -5, 10], [5, 5, 40], (N, 3))
    RA, pA = so3_exp([0.02, -0.03, 0.01]), np.zeros(3)
    Rp, Cp = so3_exp([0.01, 0.02, -0.01]), np.array([0.2, 0.1, 2.0])
    Rc, C = so3_exp([0.0, 0.03, 0.0]), np.array([0.3, 0.1, 2.5])
    x = inverse_depth_state(p, RA, pA)
    hs, _ = AnchoredInverseDepthEKF.measure_looming(x, np.broadcast_to(RA, (N, 3, 3)), pA, Rp, Cp, Rc, C)
    Zp = (p - Cp) @ Rp[:, 2]
    Zn = (p - C) @ Rc[:, 2]
    np.testing.assert_allclose(hs, Zp / Zn, rtol=1e-12)


def _bank(**kw):
    bank = AnchoredInverseDepthEKF(AnchoredEKFConfig(**kw), 400.0, 400.0)
    bank.add(np.arange(5), np.zeros((5, 2)), np.eye(3), np.zeros(3), 0.0, 0.01, 0.02)
    return bank


def test_nan_and_nonpositive_scales_have_named_reasons():
    bank = _bank()
    x0, P0 = bank.x.copy(), bank.P.copy()
    scale = np.array([np.nan, 0.0, -1.0, np.inf, 1.01])
    sigma = np.array([0.01, 0.01, 0.01, 0.01, np.nan])  # a NaN σ with a finite scale is refused too
    r = bank.update_looming(np.arange(5), scale, sigma, np.eye(3), np.zeros(3), 0.0, np.eye(3), [0, 0, 0.2], 0.05)
    assert r.reason.tolist() == [LOOM_NAN, LOOM_NONPOSITIVE, LOOM_NONPOSITIVE, LOOM_NONPOSITIVE, LOOM_NONPOSITIVE]
    assert not r.accepted.any()
    np.testing.assert_array_equal(bank.x, x0)
    np.testing.assert_array_equal(bank.P, P0)
    r = bank.update_looming(np.arange(5), np.full(5, 1.003), np.full(5, 0.004), np.eye(3), np.zeros(3), 0.0, np.eye(3), [0, 0, 0.2], 0.05)
    assert np.all(r.reason == UPDATED) and np.all(bank.n_looming == 1)
    assert np.all(bank.P[:, 2, 2] < P0[:, 2, 2])
    r = bank.update_looming(np.arange(5), np.full(5, 1.5), np.full(5, 0.004), np.eye(3), [0, 0, 0.2], 0.05, np.eye(3), [0, 0, 0.4], 0.1)
    assert np.all(r.reason == GATED)  # a 50 % jump in one 0.2 m step at ~100 m


def test_looming_config_is_validated():
    with pytest.raises(ConfigError, match="looming_sigma_floor"):
        AnchoredEKFConfig(looming_sigma_floor=0.0)
    with pytest.raises(ConfigError, match="looming_gate_probability"):
        AnchoredEKFConfig(looming_gate_probability=1.0)
    with pytest.raises(ConfigError, match="looming must be"):
        AnchoredEKFConfig(looming=1)
    assert abs(AnchoredEKFConfig(looming_gate_probability=0.95).looming_gate_threshold - 3.841) < 1e-3


CAM = CameraConfig()


def head_on(K=120, fps=30.0, speed=4.0, d0=30.0, sigma_px=0.3, sigma_s=0.004, seed=0, offsets_deg=(0.0,)):
    """A camera flying along its optical axis towards points at ``offsets_deg`` from it: frames
    (t, R, p, ids, uv, scale, scale_sigma), with scale = exact Z_prev/Z_now plus noise."""
    r = np.random.default_rng(seed)
    cam = CameraModel(CAM)
    R = np.eye(3)  # camera axes = world axes, flying along +z
    a = np.radians(np.asarray(offsets_deg, float))
    pts = np.stack([d0 * np.sin(a), np.zeros_like(a), d0 * np.cos(a)], 1)
    frames = []
    Z_prev = None
    for k in range(K):
        t = k / fps
        p = np.array([0.0, 0.0, speed * t])
        pc = pts - p
        uv = cam.project(pc) + sigma_px * r.standard_normal((len(pts), 2))
        Z = pc[:, 2]
        s = np.full(len(pts), np.nan) if Z_prev is None else Z_prev / Z + sigma_s * r.standard_normal(len(pts))
        Z_prev = Z
        frames.append((t, R, p, np.arange(len(pts)), uv, s, np.full(len(pts), sigma_s)))
    return pts, frames


def _run(frames, looming, scales=True):
    est = RangeEstimator(CAM, EstimatorConfig(), ekf_anchored=AnchoredEKFConfig(sigma_px=0.3, looming=looming))
    for t, R, p, ids, uv, s, ss in frames:
        out = est.process(t, R, p, ids, uv, scale=s if scales else None, scale_sigma=ss if scales else None)
    return out


def test_range_at_the_focus_of_expansion_needs_looming():
    pts, frames = head_on()
    p_end = frames[-1][2]
    truth = np.linalg.norm(pts[0] - p_end)
    off = _run(frames, looming=False)
    on = _run(frames, looming=True)
    assert len(off.ids) == 1 and len(on.ids) == 1
    # bearing only: nothing learnt, σ stays at the order of the range itself (or beyond)
    assert off.range_sigma[0] > 0.5 * truth and not off.converged[0]
    # with looming: converged, within 3σ of the truth, σ a few % of the range
    assert on.converged[0]
    assert abs(on.range[0] - truth) < 3 * on.range_sigma[0]
    assert on.range_sigma[0] < 0.15 * truth
    assert abs(on.range[0] - truth) < 0.1 * truth


def test_looming_off_or_absent_leaves_outputs_unchanged():
    pts, frames = head_on(K=40, offsets_deg=(0.0, 2.0, 5.0, 10.0))
    a = _run(frames, looming=False)
    b = _run(frames, looming=True, scales=False)
    c = _run(frames, looming=False, scales=True)
    for o in (b, c):
        np.testing.assert_array_equal(a.ids, o.ids)
        np.testing.assert_array_equal(a.range, o.range)
        np.testing.assert_array_equal(a.range_sigma, o.range_sigma)


def test_estimator_counts_nan_scales_and_does_not_raise():
    pts, frames = head_on(K=5, offsets_deg=(0.0, 1.0))
    est = RangeEstimator(CAM, EstimatorConfig(), ekf_anchored=AnchoredEKFConfig(sigma_px=0.3))
    for t, R, p, ids, uv, s, ss in frames:
        out = est.process(t, R, p, ids, uv, scale=np.array([np.nan, -1.0]), scale_sigma=ss)
    assert out.looming_reasons == {"nan_scale": 1, "nonpositive_scale": 1} and out.n_looming == 0
