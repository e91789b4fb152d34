"""Anchored inverse-depth EKF (DESIGN §3.4): Jacobians, convergence, consistency, gating, bad input."""

import numpy as np
import pytest
from scipy.stats import chi2

from companion.core.ekf_anchored import (
    GATED, AnchoredEKFConfig, AnchoredInverseDepthEKF, inverse_depth_state, ray, ray_jacobian,
)
from companion.core import jit
from companion.core.frames import SKEW_MAP, skew, so3_exp
from companion.errors import ConfigError, InputError
from conftest import ekf_for_exact_telemetry

rng = np.random.default_rng(7)


@pytest.fixture(params=[False, True], ids=["reference", "kernels"])
def kernels(request, monkeypatch):
    """Run the test on the numpy reference and on the compiled kernels (companion.core.jit)."""
    monkeypatch.setattr(jit, "ENABLED", request.param)
    return request.param


def numeric_H(x, RA, pA, Rc, C, dt, eps=1e-7):
    n = x.shape[1]
    H = np.zeros((len(x), 2, n))
    for j in range(n):
        d = np.zeros(n)
        d[j] = eps
        zp = AnchoredInverseDepthEKF.measure(x + d, RA, pA, Rc, C, dt)[1]
        zm = AnchoredInverseDepthEKF.measure(x - d, RA, pA, Rc, C, dt)[1]
        H[:, :, j] = (zp - zm) / (2 * eps)
    return H


@pytest.mark.parametrize("n", [3, 6])
def test_analytic_jacobian_matches_numeric(n):
    N = 40
    x = np.stack([rng.uniform(-0.5, 0.5, N), rng.uniform(-0.4, 0.4, N), rng.uniform(0.01, 0.2, N)], 1)
    if n == 6:
        x = np.concatenate([x, rng.normal(scale=0.01, size=(N, 3))], 1)
    RA = so3_exp(rng.normal(scale=0.1, size=(N, 3)))
    pA = rng.normal(size=(N, 3))
    Rc = RA @ so3_exp(rng.normal(scale=0.05, size=(N, 3)))
    C = pA + np.einsum("nij,j->ni", RA, [0.3, -0.2, 2.0])
    dt = rng.uniform(0.1, 3.0, N)
    _, _, H = AnchoredInverseDepthEKF.measure(x, RA, pA, Rc, C, dt)
    np.testing.assert_allclose(H, numeric_H(x, RA, pA, Rc, C, dt), rtol=1e-5, atol=1e-7)


def test_ray_and_skew_maps_match_their_formulas():
    """m, ∂m/∂θ, ∂m/∂φ from the product basis and [v]× from SKEW_MAP equal the closed forms exactly."""
    th, ph = rng.uniform(-3, 3, 50), rng.uniform(-1.5, 1.5, 50)
    cp, sp, ct, st = np.cos(ph), np.sin(ph), np.cos(th), np.sin(th)
    np.testing.assert_array_equal(ray(th, ph), np.stack([cp * st, -sp, cp * ct], -1))
    dth = np.stack([cp * ct, np.zeros_like(cp), -cp * st], -1)
    dph = np.stack([-sp * st, -cp, -sp * ct], -1)
    np.testing.assert_array_equal(ray_jacobian(th, ph), np.stack([dth, dph], -1))
    v = rng.normal(size=(20, 3))
    np.testing.assert_array_equal((v @ SKEW_MAP).reshape(-1, 3, 3), skew(v))


def test_state_round_trip():
    RA = so3_exp([0.1, -0.2, 0.3])
    pA = np.array([1.0, 2.0, 3.0])
    p = np.array([[10.0, -4.0, 30.0], [-2.0, 1.0, 8.0]])
    x = inverse_depth_state(p, RA, pA)
    back = pA + (RA @ ray(x[:, 0], x[:, 1]).T).T / x[:, 2:3]
    np.testing.assert_allclose(back, p, atol=1e-10)


def simulate(ekf_cfg, runs=20, n=30, sigma_px=1.0, f=500.0, drift=None):
    """Forward flight with sway and rotation; returns final errors, NEES and |range error| ratios."""
    K, dt = 60, 0.05
    t = np.arange(K) * dt
    C = np.stack([8.0 * t, 1.5 * np.sin(2 * t), 0.5 * np.sin(3 * t)], 1)
    R = so3_exp(np.stack([0.05 * np.sin(t), 0.08 * np.sin(1.3 * t), 0.1 * t], 1))
    nees, rel = [], []
    for r in range(runs):
        g = np.random.default_rng(100 + r)
        p = np.stack([g.uniform(-15, 15, n), g.uniform(-8, 8, n), g.uniform(30, 80, n)], 1)
        if drift is None:
            R_tel = R
        else:  # a body-fixed gyro bias integrates into a world-frame error w(t) = ∫ R(τ) b dτ
            b = g.normal(scale=drift, size=3)
            w = np.cumsum(np.einsum("kij,j->ki", R, b) * dt, axis=0) - np.einsum("ij,j->i", R[0], b) * dt
            R_tel = so3_exp(w) @ R
        ekf = AnchoredInverseDepthEKF(ekf_cfg, f, f)
        ids = np.arange(n)
        for k in range(K):
            pc = (p - C[k]) @ R[k]  # truth sees the true attitude
            xy = pc[:, :2] / pc[:, 2:3] + sigma_px / f * g.standard_normal((n, 2))
            if k == 0:
                ekf.add(ids, xy, R_tel[0], C[0], t[0], 0.01, 0.02)
            else:
                ekf.update(ids, xy, R_tel[k], C[k], t[k])
        x_true = inverse_depth_state(p, R_tel[0] if drift is None else R[0], C[0])
        d = ekf.x[:, :3] - x_true
        nees.append(np.einsum("ni,nij,nj->n", d, np.linalg.inv(ekf.P[:, :3, :3]), d))
        est = ekf.estimates(C[-1])
        true_range = np.linalg.norm(p - C[-1], axis=1)
        rel.append(np.abs(est.range - true_range) / true_range)
        assert np.all(np.isfinite(est.range)) and np.all(np.isfinite(est.range_sigma))
    return np.concatenate(nees), np.concatenate(rel)


def band(nees, dof=3, p=0.99):
    lo, hi = chi2.ppf([(1 - p) / 2, (1 + p) / 2], dof * len(nees))
    return lo / len(nees), hi / len(nees)


def test_converges_and_is_consistent(kernels):
    nees, rel = simulate(ekf_for_exact_telemetry(sigma_px=1.0))  # simulate's telemetry is exact
    assert np.median(rel) < 0.03
    lo, hi = band(nees)
    assert lo <= nees.mean() <= hi, (nees.mean(), lo, hi)


def test_drift_states_keep_filter_honest():
    drift = np.radians(0.3)  # rad/s per axis: a bad gyro bias
    nees_naive, _ = simulate(ekf_for_exact_telemetry(sigma_px=1.0), runs=10, drift=drift)
    nees, rel = simulate(ekf_for_exact_telemetry(sigma_px=1.0, attitude_drift_deg_s=0.3), runs=10, drift=drift)
    lo, hi = band(nees)
    assert nees_naive.mean() > hi  # ignoring the drift is overconfident ...
    assert nees.mean() <= hi  # ... modelling it is not
    assert np.median(rel) < 0.05


@pytest.mark.parametrize("tau", [0.0, 30.0], ids=["white", "position-states"])
def test_gate_rejects_outlier_and_keeps_state(kernels, tau):
    """A gated update leaves x and P as they were; with the position-error states P still takes their
    process noise over the 0.1 s that passed."""
    f = 500.0
    ekf = AnchoredInverseDepthEKF(AnchoredEKFConfig(sigma_px=1.0, position_tau_s=tau), f, f)
    p = np.array([[1.0, 0.5, 20.0]])
    ekf.add([5], p[:, :2] / p[:, 2:], np.eye(3), np.zeros(3), 0.0, 0.01, 0.02)
    for k in range(1, 10):
        C = np.array([0.3 * k, 0.0, 1.0 * k])
        pc = p - C
        ekf.update([5], pc[:, :2] / pc[:, 2:], np.eye(3), C, 0.1 * k)
    x, P = ekf.x.copy(), ekf.P.copy()
    C = np.array([3.0, 0.0, 10.0])
    pc = p - C
    res = ekf.update([5], pc[:, :2] / pc[:, 2:] + 30.0 / f, np.eye(3), C, 1.0)
    assert not res.accepted[0] and res.reason[0] == GATED and res.nis[0] > 100
    np.testing.assert_array_equal(ekf.x, x)
    if tau == 0:
        np.testing.assert_array_equal(ekf.P, P)
        return
    assert ekf.i_pos == 6
    i = ekf.i_pos + np.arange(3)
    P[0, i, i] += ekf.config.delta_variance(1.0) - ekf.config.delta_variance(0.9)
    np.testing.assert_allclose(ekf.P, P, rtol=1e-9, atol=1e-15)


def test_point_at_infinity_stays_finite(kernels):
    f = 500.0
    ekf = AnchoredInverseDepthEKF(AnchoredEKFConfig(), f, f)
    ekf.add([1], [[0.1, -0.05]], np.eye(3), np.zeros(3), 0.0, 0.01, 0.02)
    for k in range(1, 30):  # a star: same direction whatever the translation
        ekf.update([1], [[0.1, -0.05]], np.eye(3), np.array([0.0, 0.0, 2.0 * k]), 0.1 * k)
    e = ekf.estimates(np.zeros(3))
    assert abs(e.inv_depth[0]) < 3 * e.inv_depth_sigma[0]
    assert np.isfinite(e.range[0]) and e.range[0] <= ekf.config.max_range_m
    assert not e.converged[0]


def test_bad_input():
    ekf = AnchoredInverseDepthEKF(AnchoredEKFConfig(), 500.0, 500.0)
    ekf.add([1, 2], np.zeros((2, 2)), np.eye(3), np.zeros(3), 0.0, 0.01, 0.02)
    with pytest.raises(InputError, match="NaN"):
        ekf.update([1], [[np.nan, 0.0]], np.eye(3), np.ones(3), 1.0)
    with pytest.raises(InputError, match="unknown landmark ids \\[9\\]"):
        ekf.update([9], [[0.0, 0.0]], np.eye(3), np.ones(3), 1.0)
    with pytest.raises(InputError, match="xy must have shape"):
        ekf.update([1], np.zeros((2, 2)), np.eye(3), np.ones(3), 1.0)
    with pytest.raises(InputError, match="new and unique"):
        ekf.add([1], np.zeros((1, 2)), np.eye(3), np.zeros(3), 0.0, 0.01, 0.02)
    with pytest.raises(ConfigError, match="gate_probability"):
        AnchoredEKFConfig(gate_probability=1.5)


def _bank_with_track(ids, drift=0.03):
    """A bank of landmarks at 10–40 m and the pixels of a forward flight past them (one row per frame)."""
    f = 400.0
    ekf = AnchoredInverseDepthEKF(AnchoredEKFConfig(attitude_drift_deg_s=drift, position_sigma_m=0.1), f, f)
    g = np.random.default_rng(3)
    p = np.stack([g.uniform(-5, 5, len(ids)), g.uniform(-3, 3, len(ids)), g.uniform(10, 40, len(ids))], 1)
    C = np.stack([0.05 * np.arange(8), np.zeros(8), 0.4 * np.arange(8)], 1)
    R = so3_exp(np.stack([np.zeros(8), 0.01 * np.arange(8), np.zeros(8)], 1))
    xy = np.stack([(np.einsum("ji,nj->ni", R[k], p - C[k])) for k in range(8)])
    xy = xy[:, :, :2] / xy[:, :, 2:] + g.normal(scale=1.0 / f, size=(8, len(ids), 2))
    ekf.add(ids, xy[0], R[0], C[0], 0.0, 0.02, 0.03)
    return ekf, xy, R, C, 0.1 * np.arange(8)


def test_update_sequence_and_update_banks_match_update(kernels):
    """Replaying buffers (update_sequence) and one batch over two banks (update_banks) give what
    update() gives landmark by landmark, frame by frame."""
    ids = np.arange(6)
    ref, xy, R, C, t = _bank_with_track(ids)
    count = np.array([8, 3, 5, 8, 1, 6])  # observations per landmark, the anchor included
    for k in range(1, 8):
        sel = count > k
        ref.update(ids[sel], xy[k, sel], R[k], C[k], t[k])
    seq, *_ = _bank_with_track(ids)
    seq.update_sequence(ids, np.swapaxes(xy[1:], 0, 1), np.broadcast_to(R[1:], (6, 7, 3, 3)),
                        np.broadcast_to(C[1:], (6, 7, 3)), np.broadcast_to(t[1:], (6, 7)), count - 1)
    np.testing.assert_allclose(seq.x, ref.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(seq.P, ref.P, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(seq.n_updates, ref.n_updates)

    a, *_ = _bank_with_track(ids[:4])
    b, *_ = _bank_with_track(ids[:4])
    b.move_to(a, [])  # nothing to move
    alone, *_ = _bank_with_track(ids[:4])
    other, *_ = _bank_with_track(ids[:4])
    for k in range(1, 8):
        res = AnchoredInverseDepthEKF.update_banks([(a, ids[:3], xy[k, :3]), (b, ids[1:4], xy[k, 1:4])], R[k], C[k], t[k])
        alone.update(ids[:3], xy[k, :3], R[k], C[k], t[k])
        other.update(ids[1:4], xy[k, 1:4], R[k], C[k], t[k])
        assert [len(r.ids) for r in res] == [3, 3]
    np.testing.assert_allclose(a.x, alone.x, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(b.P, other.P, rtol=1e-12, atol=1e-18)
    fields = AnchoredInverseDepthEKF._FIELDS
    before = {name: getattr(b, name)[b.index_of([1, 3])].copy() for name in fields}
    a.remove([1, 3])
    b.move_to(a, [3, 1])  # state and history unchanged, ids kept sorted
    np.testing.assert_array_equal(a.ids, [0, 1, 2, 3])
    np.testing.assert_array_equal(b.ids, [0, 2])
    for name in fields:
        np.testing.assert_array_equal(getattr(a, name)[[1, 3]], before[name])
    with pytest.raises(InputError, match="move_to"):
        a.move_to(b, [2])  # b already holds id 2
    with pytest.raises(InputError, match="count"):
        seq.update_sequence(ids, np.swapaxes(xy[1:], 0, 1), np.broadcast_to(R[1:], (6, 7, 3, 3)),
                            np.broadcast_to(C[1:], (6, 7, 3)), np.broadcast_to(t[1:], (6, 7)), count + 1)


def test_far_convergence_limit(kernels):
    """§ Outputs and convergence: with converged_far_rel_sigma a range also needs σ_r < max(floor, k_far·r).
    Points straight ahead of the anchor (σ_r = σ_ρ/ρ² there): at 30 m a σ of 2.4 m (8 %) is converged by the
    relative test alone and not with k_far = 0.06 (limit 1.8 m); at 5 m a σ of 0.45 m (9 %) stays converged
    (the floor, 0.6 m, is the larger limit there); at 40 m a σ of 2.0 m (5 %) passes both."""
    r = np.array([30.0, 5.0, 40.0])
    s_r = np.array([2.4, 0.45, 2.0])
    rho, s_rho = 1.0 / r, s_r / r**2

    def converged(**kw):
        ekf = AnchoredInverseDepthEKF(AnchoredEKFConfig(min_updates=0, **kw), 500.0, 500.0)
        ekf.add([1, 2, 3], np.zeros((3, 2)), np.eye(3), np.zeros(3), 0.0, rho, s_rho)
        est = ekf.estimates(np.zeros(3))
        np.testing.assert_allclose(est.range, r, rtol=1e-9)
        np.testing.assert_allclose(est.range_sigma, s_r, rtol=1e-6)
        return est.converged.tolist()

    assert converged() == [True, True, True]  # off by default
    assert converged(converged_far_rel_sigma=0.06, converged_sigma_floor_m=0.6) == [False, True, True]
    assert converged(converged_far_rel_sigma=0.06, converged_sigma_floor_m=0.4) == [False, False, True]
    with pytest.raises(ConfigError, match="converged_far_rel_sigma"):
        AnchoredEKFConfig(converged_far_rel_sigma=-0.1)
    with pytest.raises(ConfigError, match="converged_sigma_floor_m"):
        AnchoredEKFConfig(converged_sigma_floor_m=float("nan"))


def test_near_convergence_limit(kernels):
    """§ Outputs and convergence: with converged_near_sigma_m a range σ below it counts as converged whatever σ_r/r.
    At 2.5 m a σ of 0.3 m (12 %) fails the relative test; with σ_near 0.4 m it is converged, with 0.25 m not; at 30 m
    a σ of 4 m (13 %) stays unconverged; min_updates and validity still apply."""
    r = np.array([2.5, 30.0, 2.5])
    s_r = np.array([0.3, 4.0, 0.3])
    rho, s_rho = 1.0 / r, s_r / r**2

    def converged(min_updates=0, **kw):
        ekf = AnchoredInverseDepthEKF(AnchoredEKFConfig(min_updates=min_updates, **kw), 500.0, 500.0)
        ekf.add([1, 2, 3], np.zeros((3, 2)), np.eye(3), np.zeros(3), 0.0, rho, s_rho)
        ekf.diverged[2] = True  # the third is not valid
        est = ekf.estimates(np.zeros(3))
        np.testing.assert_allclose(est.range_sigma, s_r, rtol=1e-6)
        return est.converged.tolist()

    assert converged() == [False, False, False]  # off by default: the relative test alone
    assert converged(converged_near_sigma_m=0.4) == [True, False, False]
    assert converged(converged_near_sigma_m=0.25) == [False, False, False]
    assert converged(min_updates=3, converged_near_sigma_m=0.4) == [False, False, False]  # no update accepted yet
    with pytest.raises(ConfigError, match="converged_near_sigma_m"):
        AnchoredEKFConfig(converged_near_sigma_m=-0.1)


def test_mean_nis_counts_only_with_baseline(kernels):
    """§ Bookkeeping: with nis_min_baseline_deg a NIS enters the mean only once the camera has moved that far, seen from
    the landmark.  A point 5 m ahead ranged on the way in, then watched from a hover with a slowly swinging pixel
    error (what the telemetry's correlated position error leaves in a hover): each update passes the gate, but
    their mean passes max_mean_nis and retires the point; counted only with baseline, the hover adds nothing to the
    mean and the point stays.  Moving again, the NIS counts: 0.1 m sideways is 1.1° at 5 m."""
    f = 500.0
    p = np.array([[0.2, 0.1, 5.0]])

    def run(baseline_deg):
        cfg = AnchoredEKFConfig(sigma_px=1.0, max_mean_nis=4.0, nis_window=10.0, nis_min_baseline_deg=baseline_deg,
                                position_sigma_m=0.0, attitude_drift_deg_s=0.0)
        ekf = AnchoredInverseDepthEKF(cfg, f, f)
        ekf.add([7], p[:, :2] / p[:, 2:], np.eye(3), np.zeros(3), 0.0, 0.2, 0.05)
        k = 0
        for k in range(1, 11):  # the approach: 0.3 m a frame, exact pixels
            C = np.array([0.02 * k, 0.0, 0.3 * k])
            pc = p - C
            ekf.update([7], pc[:, :2] / pc[:, 2:], np.eye(3), C, 0.1 * k)
        counted = int(ekf.nis_count[0])
        C = np.array([0.2, 0.0, 3.0])
        pc = p - C
        for j in range(1, 41):  # a 4 s hover, the pixel error swinging ±2.2 px in x and y with a period of 0.8 s
            k += 1
            e = 2.2 * np.sin(2 * np.pi * j * 0.1 / 0.8) / f
            ekf.update([7], pc[:, :2] / pc[:, 2:] + e, np.eye(3), C, 0.1 * k)
        return ekf, counted

    ekf, _ = run(0.0)
    assert ekf.diverged[0]  # every hover update counted: the mean crosses 4
    ekf, counted = run(1.0)
    assert not ekf.diverged[0] and ekf.nis_count[0] == counted  # the hover added nothing to the mean
    assert 3 <= counted <= 10  # on the way in, with 0.3 m a frame, each update counted
    n = int(ekf.nis_count[0])
    C = ekf.nis_C[0] + np.array([0.1, 0.0, 0.0])
    pc = p - C
    ekf.update([7], pc[:, :2] / pc[:, 2:], np.eye(3), C, 10.0)
    assert ekf.nis_count[0] == n + 1 and np.allclose(ekf.nis_C[0], C)
    with pytest.raises(ConfigError, match="nis_min_baseline_deg"):
        AnchoredEKFConfig(nis_min_baseline_deg=-1.0)
