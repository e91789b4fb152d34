"""Tests of the per-landmark inverse-depth EKF (DESIGN.md §3.5, seed 000)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from companion.config import from_mapping
from companion.core import ekf_landmark as ekf
from companion.core.ekf_landmark import (
    LandmarkEKFBank,
    LandmarkEKFConfig,
    continuous_dynamics,
    jacobian_q,
    jacobian_x,
    points_from_state,
    rk4_step,
    state_from_points,
)
from companion.core.frames import se3_twist, skew, so3_exp
from companion.errors import ConfigError, InputError

F_PX = 500.0


def random_states(rng, n):
    return np.column_stack([rng.uniform(-0.8, 0.8, (n, 2)), rng.uniform(0.02, 0.5, n)])


def random_inputs(rng, n=None):
    shape = (6,) if n is None else (n, 6)
    q = rng.normal(0.0, 1.0, shape)
    q[..., :3] *= 3.0  # m/s
    q[..., 3:] *= 0.5  # rad/s
    return q


def numeric_jacobian(fun, x0, eps):
    """Central differences of fun: (N,k) -> (N,3) with respect to the k columns of x0: (N,3,k)."""
    n, k = x0.shape
    J = np.empty((n, 3, k))
    for j in range(k):
        d = np.zeros_like(x0)
        d[:, j] = eps
        J[:, :, j] = (fun(x0 + d) - fun(x0 - d)) / (2 * eps)
    return J


def left_jacobian(phi):
    """J_l(φ) = Σ [φ]×^k/(k+1)! = ∫₀¹ exp(s[φ]×) ds in closed form."""
    th = np.linalg.norm(phi)
    K = skew(phi)
    if th < 1e-8:
        return np.eye(3) + 0.5 * K
    return np.eye(3) + (1 - math.cos(th)) / th**2 * K + (th - math.sin(th)) / th**3 * (K @ K)


def rigid_motion(P0, v, w, t):
    """Exact camera-frame point after moving the camera with constant twist (v, w) for t seconds.

    The camera pose relative to its start is R = exp([w]× t), C = J_l(w t) v t (the SE(3)
    exponential); the point is P(t) = Rᵀ (P0 − C), the solution of dP/dt = −v − w × P.
    """
    R = so3_exp(w * t)
    C = left_jacobian(w * t) @ v * t
    return (P0 - C) @ R  # rows: Rᵀ (P0 − C)


# -- analytic Jacobians ---------------------------------------------------------------------------
def test_continuous_jacobians_match_central_differences():
    rng = np.random.default_rng(1)
    x = random_states(rng, 40)
    q = random_inputs(rng)
    Fx = jacobian_x(x, q)
    Fq = jacobian_q(x, q)
    assert Fx.shape == (40, 3, 3) and Fq.shape == (40, 3, 6)
    Fx_num = numeric_jacobian(lambda xx: continuous_dynamics(xx, q), x, 1e-6)
    qs = np.tile(q, (40, 1))
    Fq_num = numeric_jacobian(lambda qq: continuous_dynamics(x, qq), qs, 1e-6)
    np.testing.assert_allclose(Fx, Fx_num, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(Fq, Fq_num, rtol=1e-6, atol=1e-8)


def test_rk4_jacobians_match_central_differences():
    rng = np.random.default_rng(2)
    n = 40
    x = random_states(rng, n)
    q = random_inputs(rng, n)  # per-landmark inputs exercise the (N, 6) path
    dt = 0.05
    x1, A, G = rk4_step(x, q, dt)
    assert x1.shape == (n, 3) and A.shape == (n, 3, 3) and G.shape == (n, 3, 6)
    A_num = numeric_jacobian(lambda xx: rk4_step(xx, q, dt)[0], x, 1e-6)
    G_num = numeric_jacobian(lambda qq: rk4_step(x, qq, dt)[0], q, 1e-6)
    np.testing.assert_allclose(A, A_num, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(G, G_num, rtol=1e-6, atol=1e-9)
    # the shared (6,) input gives the same as the same input repeated per landmark
    xa, Aa, Ga = rk4_step(x, q[0], dt)
    xb, Ab, Gb = rk4_step(x, np.tile(q[0], (n, 1)), dt)
    np.testing.assert_array_equal(xa, xb)
    np.testing.assert_array_equal(Aa, Ab)
    np.testing.assert_array_equal(Ga, Gb)


def test_predict_substeps_compose_A_and_G():
    """dt > max_step splits into RK4 sub-steps; P⁻ must use the composed A and G."""
    rng = np.random.default_rng(3)
    cfg = LandmarkEKFConfig(max_step=0.05)
    n, dt = 6, 0.17  # 4 sub-steps of 0.0425 s
    x0 = random_states(rng, n) * np.array([0.5, 0.5, 1.0])
    v, w = np.array([0.7, -0.3, 4.0]), np.array([0.05, -0.2, 0.1])
    bank = LandmarkEKFBank(cfg, F_PX, F_PX)
    bank.add(np.arange(n), x0[:, :2], x0[:, 2], np.full(n, 0.01))
    P0 = bank.P.copy()
    bank.predict(v, w, dt)

    def flow(xx, qq):
        for _ in range(4):
            xx = rk4_step(xx, qq, dt / 4)[0]
        return xx

    q = np.concatenate([v, w])
    np.testing.assert_allclose(bank.x, flow(x0, q), rtol=1e-12, atol=1e-14)
    A = numeric_jacobian(lambda xx: flow(xx, q), x0, 1e-6)
    G = numeric_jacobian(lambda qq: flow(x0, qq), np.tile(q, (n, 1)), 1e-6)
    Qd = np.diag(bank.Q_psd / dt)
    P_expected = A @ P0 @ np.swapaxes(A, 1, 2) + G @ Qd @ np.swapaxes(G, 1, 2)
    np.testing.assert_allclose(bank.P, P_expected, rtol=1e-6, atol=1e-14)


# -- seed 000 eq. 13 ------------------------------------------------------------------------------
def test_planar_case_equals_seed000_eq13():
    """With only Vz and ωy non-zero the 6-DOF model is seed 000 eq. 13 (pixel form).

    Seed 000 eq. 13, state (x, y, ξ) in pixels with focal length f and principal point (cx, cy):
        ẋ = −(f + (x − cx)²/f) ωy + Vz ξ (x − cx)
        ẏ = Vz ξ (y − cy) − ωy (x − cx)(y − cy)/f
        ξ̇ = Vz ξ² − ωy ξ (x − cx)/f
    Sign conventions reconciled: the seed's eq. 5/7 is dP/dt = −V − [Ω]× P with V and Ω the
    camera's own velocity and rate in its frame, exactly our q = (V, ω), and x = f x̄ + cx,
    y = f ȳ + cy, so no sign flips are needed for f.  The seed's appendix differentiates with
    respect to the *measurement error* Δ (true = measured − Δ, its eq. 14), so its G columns
    (ωy, Vz) are −∂f/∂(ωy, Vz) in pixel units; it also has two typos fixed here: (x + cx)² for
    (x − cx)² in G and Vz ξ Δt/f for Vz ξ Δt in A₁₁.  Its A is the Euler form I + F Δt, which the
    exact RK4 Jacobian matches to first order in Δt.
    """
    rng = np.random.default_rng(4)
    f, cx, cy = 420.0, 317.0, 243.0
    n = 25
    xpix = np.column_stack([rng.uniform(0, 640, n), rng.uniform(0, 480, n)])
    xi = rng.uniform(0.02, 0.5, n)
    Vz, wy = 1.7, -0.23
    q = np.array([0.0, 0.0, Vz, 0.0, wy, 0.0])
    dx, dy = xpix[:, 0] - cx, xpix[:, 1] - cy
    state = np.column_stack([dx / f, dy / f, xi])  # normalized coordinates of the same points

    # eq. 13 written out
    xdot = -(f + dx**2 / f) * wy + Vz * xi * dx
    ydot = Vz * xi * dy - wy * dx * dy / f
    xidot = Vz * xi**2 - wy * xi * dx / f
    fn = continuous_dynamics(state, q)
    np.testing.assert_allclose(f * fn[:, 0], xdot, rtol=1e-12)
    np.testing.assert_allclose(f * fn[:, 1], ydot, rtol=1e-12)
    np.testing.assert_allclose(fn[:, 2], xidot, rtol=1e-12)

    # appendix G (columns ωy-noise, Vz-noise), typo (x + cx)² corrected, = −∂f/∂(ωy, Vz) in pixels
    G_seed = np.stack(
        [
            np.column_stack([f + dx**2 / f, -xi * dx]),
            np.column_stack([dx * dy / f, -xi * dy]),
            np.column_stack([xi * dx / f, -(xi**2)]),
        ],
        1,
    )
    B = jacobian_q(state, q)
    T = np.diag([f, f, 1.0])  # normalized -> pixel state
    B_pix = T @ B[:, :, [4, 2]]
    np.testing.assert_allclose(-B_pix, G_seed, rtol=1e-12, atol=1e-12)

    # appendix A (Euler form, typo in A₁₁ corrected) vs our exact RK4 A, to first order in Δt
    dt = 1e-5
    A_seed = np.zeros((n, 3, 3))
    A_seed[:, 0, 0] = 1 - 2 * dx * wy * dt / f + Vz * xi * dt
    A_seed[:, 0, 2] = Vz * dx * dt
    A_seed[:, 1, 0] = -wy * dy * dt / f
    A_seed[:, 1, 1] = 1 + Vz * xi * dt - dx * wy * dt / f
    A_seed[:, 1, 2] = Vz * dy * dt
    A_seed[:, 2, 0] = -wy * xi * dt / f
    A_seed[:, 2, 2] = 1 + 2 * Vz * xi * dt - dx * wy * dt / f
    _, A, _ = rk4_step(state, q, dt)
    A_pix = T @ A @ np.linalg.inv(T)
    # compare the first-order parts (A − I)/Δt: they agree up to O(Δt)
    np.testing.assert_allclose((A_pix - np.eye(3)) / dt, (A_seed - np.eye(3)) / dt, rtol=1e-3, atol=1e-6)


# -- exact rigid motion -------------------------------------------------------------------------
def test_rk4_reproduces_exact_rigid_motion():
    rng = np.random.default_rng(5)
    n = 30
    P0 = np.column_stack([rng.uniform(-4, 4, (n, 2)), rng.uniform(12, 30, n)])
    v = np.array([0.8, -0.4, 3.0])
    w = np.array([0.06, -0.15, 0.1])
    dt, steps = 0.05, 40
    # the closed-form pose agrees with the package's twist convention (frames.se3_twist)
    t_end = dt * steps
    v_back, w_back = se3_twist(np.eye(3), np.zeros(3), so3_exp(w * t_end), left_jacobian(w * t_end) @ v * t_end, t_end)
    np.testing.assert_allclose(v_back, v, atol=1e-12)
    np.testing.assert_allclose(w_back, w, atol=1e-12)

    x = state_from_points(P0)
    q = np.concatenate([v, w])
    for k in range(1, steps + 1):
        x = rk4_step(x, q, dt)[0]
        if k % 10 == 0:
            x_true = state_from_points(rigid_motion(P0, v, w, k * dt))
            # 1e-8 in normalized coordinates is 5e-6 px at f = 500
            np.testing.assert_allclose(x, x_true, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(points_from_state(x), rigid_motion(P0, v, w, t_end), rtol=1e-7)


# -- synthetic flight ---------------------------------------------------------------------------
def simulate(seed, n_landmarks=50, n_frames=75, dt=1.0 / 30.0, cfg=None):
    """Camera flying forward at 10 m/s with lateral/vertical motion and rotation past known points.

    50 points at 40–120 m inside a ±0.6 (normalized) field of view; 2.5 s at 30 fps (25 m flown).
    Truth is propagated exactly (constant twist per frame); the filter gets inputs with white
    noise of the configured PSD averaged over the frame (variance σ²/Δt: 0.55 m/s and 0.011 rad/s
    per frame with the defaults) and 1 px pixel noise at f = 500.  The prior on ξ is Gaussian with
    σ = 30 % of ξ (a coarse triangulation), draws clipped at 2.5σ so ξ stays positive.  Every point
    is measured every frame (this tests the filter, not a tracker's field of view).
    Returns the final bank, the true final states and ranges, and the overall acceptance rate.
    """
    cfg = cfg or LandmarkEKFConfig()
    rng = np.random.default_rng(seed)
    ids = np.arange(100, 100 + n_landmarks)
    Z = rng.uniform(40.0, 120.0, n_landmarks)
    xy0 = rng.uniform(-0.6, 0.6, (n_landmarks, 2))
    P = np.column_stack([xy0 * Z[:, None], Z])
    sig_px = cfg.sigma_px / F_PX

    x_true = state_from_points(P)
    s0 = 0.3 * x_true[:, 2]
    xi0 = x_true[:, 2] + s0 * np.clip(rng.standard_normal(n_landmarks), -2.5, 2.5)
    bank = LandmarkEKFBank(cfg, F_PX, F_PX)
    bank.add(ids, x_true[:, :2] + rng.normal(0, sig_px, (n_landmarks, 2)), xi0, s0)
    accepted = 0
    for k in range(1, n_frames):
        t = k * dt
        v = np.array([2.5 * math.sin(0.9 * t), 1.0 * math.cos(1.3 * t), 10.0])
        w = np.array([0.05 * math.sin(1.1 * t), 0.08 * math.cos(0.7 * t), 0.04 * math.sin(0.5 * t)])
        P = rigid_motion(P, v, w, dt)
        v_meas = v + rng.normal(0, cfg.sigma_v / math.sqrt(dt), 3)
        w_meas = w + rng.normal(0, cfg.sigma_w / math.sqrt(dt), 3)
        bank.predict(v_meas, w_meas, dt)
        z = P[:, :2] / P[:, 2:3] + rng.normal(0, sig_px, (n_landmarks, 2))
        accepted += int(bank.update(ids, z).accepted.sum())
    return bank, state_from_points(P), np.linalg.norm(P, axis=1), accepted / ((n_frames - 1) * n_landmarks)


def nees(bank, x_true):
    e = bank.x - x_true
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(bank.P), e)


def test_synthetic_flight_converges_and_is_consistent():
    runs = 8
    mean_nees, rel_err, conv, acc = [], [], [], []
    for seed in range(runs):
        bank, x_true, rng_true, accepted = simulate(seed)
        est = bank.estimates()
        assert np.all(est.valid)
        assert np.all(np.isfinite(est.range)) and np.all(np.isfinite(est.range_sigma))
        rel_err.append(np.abs(est.range - rng_true) / rng_true)
        mean_nees.append(nees(bank, x_true).mean())
        conv.append(est.converged.mean())
        acc.append(accepted)
    rel_err = np.concatenate(rel_err)
    # the range converged: median < 3 % after 75 frames (the prior had 30 % σ on ξ)
    assert np.median(rel_err) < 0.03, np.median(rel_err)
    assert np.mean(conv) > 0.9
    # the 0.999 gate rejects few of the (all genuine) measurements
    assert np.mean(acc) > 0.99
    # consistency: average 3-state NEES over landmarks and runs.  Landmarks of one run share the
    # input noise, so the band is computed as if each run gave one independent sample (generous):
    # mean of `runs` χ²₃ variables, 99 % two-sided.
    avg = float(np.mean(mean_nees))
    lo, hi = chi2.ppf(0.005, 3 * runs) / runs, chi2.ppf(0.995, 3 * runs) / runs
    assert lo < avg < hi, (avg, lo, hi)


# -- gate, flags and placeholders -----------------------------------------------------------------
def make_bank(n=5, cfg=None):
    cfg = cfg or LandmarkEKFConfig()
    bank = LandmarkEKFBank(cfg, F_PX, F_PX)
    rng = np.random.default_rng(7)
    bank.add(np.arange(n), rng.uniform(-0.3, 0.3, (n, 2)), np.full(n, 0.05), np.full(n, 0.02))
    return bank


def test_gate_rejects_30px_outlier_and_leaves_state_unchanged():
    bank = make_bank(5, LandmarkEKFConfig(max_consecutive_rejects=3))
    ids = bank.ids.copy()
    for _ in range(5):
        bank.predict([0.2, 0.0, 3.0], [0.0, 0.01, 0.0], 1 / 30)
        bank.update(ids, bank.x[:, :2])
    x_before, P_before = bank.x.copy(), bank.P.copy()
    z = bank.x[:, :2].copy()
    z[2, 0] += 30.0 / F_PX  # 30 px off
    res = bank.update(ids, z)
    assert res.accepted.tolist() == [True, True, False, True, True]
    assert res.reason[2] == ekf.GATED
    assert res.nis[2] > bank.config.gate_threshold > 0
    np.testing.assert_array_equal(bank.x[2], x_before[2])
    np.testing.assert_array_equal(bank.P[2], P_before[2])
    assert bank.n_rejects[2] == 1 and bank.n_rejects[0] == 0
    assert abs(bank.config.gate_threshold - chi2.ppf(0.999, 2)) < 1e-9
    # two more in a row reach max_consecutive_rejects = 3: flagged diverged, reported invalid
    for _ in range(2):
        bank.update(ids[2:3], z[2:3])
    est = bank.estimates()
    assert bank.diverged[2] and not est.valid[2] and est.status[2] == ekf.DIVERGED
    assert est.valid[[0, 1, 3, 4]].all()


def test_range_sigma_is_first_order_propagation():
    bank = make_bank(4)
    bank.P = bank.P + 1e-5 * np.array([[0, 1, 2], [1, 0, 3], [2, 3, 0]])[None]  # some correlation
    est = bank.estimates()

    def rng_of(x):
        return np.sqrt(1 + x[:, 0] ** 2 + x[:, 1] ** 2) / x[:, 2]

    J = np.stack([(rng_of(bank.x + d) - rng_of(bank.x - d)) / 2e-7 for d in 1e-7 * np.eye(3)[:, None, :]], 1)
    np.testing.assert_allclose(est.range, rng_of(bank.x))
    np.testing.assert_allclose(est.range_sigma, np.sqrt(np.einsum("ni,nij,nj->n", J, bank.P, J)), rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(est.p_cam, axis=1), est.range)


def test_far_and_invalid_landmarks_give_finite_placeholders():
    cfg = LandmarkEKFConfig()
    bank = LandmarkEKFBank(cfg, F_PX, F_PX)
    # id 1: ξ = 0 (at infinity); id 2: 1 m ahead; id 3: normal
    bank.add([1, 2, 3], [[0.1, 0.0], [0.0, 0.0], [0.2, -0.1]], [0.0, 1.0, 0.05], [0.01, 0.01, 0.01])
    est = bank.estimates()
    assert est.status.tolist() == [ekf.FAR, ekf.OK, ekf.OK]
    assert est.range[0] == pytest.approx(cfg.max_range_m) and est.range_sigma[0] == cfg.max_range_m
    # flying 0.95 m towards id 2 puts it 5 cm ahead (ξ = 20 > inv_depth_max): flagged invalid, frozen
    bank.predict([0.0, 0.0, 9.5], [0.0, 0.0, 0.0], 0.1)
    assert bank.invalid.tolist() == [False, True, False]
    x_frozen = bank.x[1].copy()
    bank.predict([0.0, 0.0, 9.5], [0.0, 0.0, 0.0], 0.1)
    np.testing.assert_array_equal(bank.x[1], x_frozen)
    res = bank.update([2, 3], [[0.0, 0.0], bank.x[2, :2]])
    assert res.reason.tolist() == [ekf.FROZEN, ekf.ACCEPTED]
    # significantly negative inverse depth is flagged, not clipped
    bank.x[2, 2] = -5.0 * math.sqrt(bank.P[2, 2, 2])
    bank.predict([0.0, 0.0, 0.1], [0.0, 0.0, 0.0], 0.01)
    assert bank.invalid[2]
    est = bank.estimates()
    assert est.status.tolist() == [ekf.FAR, ekf.INVALID, ekf.INVALID]
    assert not est.valid.any() and not est.converged.any()
    for a in (est.p_cam, est.range, est.range_sigma, est.inv_depth, est.inv_depth_sigma):
        assert np.all(np.isfinite(a))
    np.testing.assert_allclose(est.range[1:], cfg.max_range_m)


def test_extreme_prediction_never_emits_nan():
    bank = make_bank(5, LandmarkEKFConfig(max_dt=1.0))
    bank.predict([0.0, 0.0, -1e6], [50.0, -80.0, 30.0], 1.0)
    assert np.all(np.isfinite(bank.x)) and np.all(np.isfinite(bank.P))
    est = bank.estimates()
    for a in (est.p_cam, est.range, est.range_sigma):
        assert np.all(np.isfinite(a))


def test_add_remove_keep_ids_sorted_and_rows_aligned():
    bank = LandmarkEKFBank(LandmarkEKFConfig(), F_PX, F_PX)
    bank.add([5, 1], [[0.5, 0.0], [0.1, 0.0]], [0.05, 0.01], [0.01, 0.01])
    bank.add([3], [[0.3, 0.0]], [0.03], [0.01])
    assert bank.ids.tolist() == [1, 3, 5]
    np.testing.assert_allclose(bank.x[:, 0], [0.1, 0.3, 0.5])
    bank.remove([3])
    assert bank.ids.tolist() == [1, 5] and len(bank) == 2
    res = bank.update([5, 1], [[0.5, 0.0], [0.1, 0.0]])
    assert res.ids.tolist() == [5, 1] and res.accepted.all()
    assert bank.contains([1, 3, 5]).tolist() == [True, False, True]
    assert bank.index_of([5, 1]).tolist() == [1, 0]
    with pytest.raises(InputError, match=r"unknown landmark ids \[3\]"):
        bank.index_of([1, 3])


# -- bad input ----------------------------------------------------------------------------------
def test_bad_input_raises_input_error_naming_the_problem():
    bank = make_bank(3)
    ids = bank.ids
    with pytest.raises(InputError, match="xy contains NaN"):
        bank.update(ids, [[0.0, 0.0], [np.nan, 0.0], [0.0, 0.0]])
    with pytest.raises(InputError, match=r"xy must have shape \(3, 2\)"):
        bank.update(ids, np.zeros((3, 3)))
    with pytest.raises(InputError, match=r"xy must have shape \(3, 2\)"):
        bank.update(ids, np.zeros((2, 2)))
    with pytest.raises(InputError, match="unknown landmark ids \\[42\\]"):
        bank.update([0, 42], np.zeros((2, 2)))
    with pytest.raises(InputError, match="unknown landmark ids"):
        bank.remove([7])
    with pytest.raises(InputError, match="duplicate"):
        bank.update([0, 0], np.zeros((2, 2)))
    with pytest.raises(InputError, match="integers"):
        bank.update([0.5], np.zeros((1, 2)))
    with pytest.raises(InputError, match="1-D"):
        bank.update([[0]], np.zeros((1, 2)))
    for dt in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(InputError, match="dt must be finite and > 0"):
            bank.predict([0, 0, 1], [0, 0, 0], dt)
    with pytest.raises(InputError, match="exceeds max_dt"):
        bank.predict([0, 0, 1], [0, 0, 0], 5.0)
    with pytest.raises(InputError, match=r"v_cam must have shape \(3,\)"):
        bank.predict([0, 0], [0, 0, 0], 0.1)
    with pytest.raises(InputError, match="w_cam contains NaN"):
        bank.predict([0, 0, 1], [0, np.nan, 0], 0.1)
    with pytest.raises(InputError, match="already in the bank"):
        bank.add([0], [[0.0, 0.0]], [0.1], [0.1])
    with pytest.raises(InputError, match="inv_depth_sigma must be > 0"):
        bank.add([9], [[0.0, 0.0]], [0.1], [0.0])
    with pytest.raises(InputError, match="inv_depth must be in"):
        bank.add([9], [[0.0, 0.0]], [-0.1], [0.1])
    with pytest.raises(InputError, match=r"inv_depth must have shape \(1,\)"):
        bank.add([9], [[0.0, 0.0]], [0.1, 0.2], [0.1])
    with pytest.raises(InputError, match="add: xy contains NaN"):
        bank.add([9], [[np.nan, 0.0]], [0.1], [0.1])
    # the model functions
    x = np.array([[0.1, 0.2, 0.1]])
    with pytest.raises(InputError, match=r"x must have shape \(N, 3\)"):
        continuous_dynamics(np.zeros((2, 2)), np.zeros(6))
    with pytest.raises(InputError, match=r"q must have shape \(6,\) or \(N, 6\)"):
        jacobian_x(x, np.zeros(5))
    with pytest.raises(InputError, match="q contains NaN"):
        jacobian_q(x, np.full(6, np.nan))
    with pytest.raises(InputError, match="dt must be finite and > 0"):
        rk4_step(x, np.zeros(6), 0.0)
    with pytest.raises(InputError, match="x contains NaN"):
        rk4_step(np.array([[np.nan, 0, 1]]), np.zeros(6), 0.1)
    # nothing above changed the bank
    assert bank.ids.tolist() == [0, 1, 2]


def test_config_validation():
    with pytest.raises(ConfigError, match="sigma_px"):
        LandmarkEKFConfig(sigma_px=0.0)
    with pytest.raises(ConfigError, match="sigma_v"):
        LandmarkEKFConfig(sigma_v=float("nan"))
    with pytest.raises(ConfigError, match="gate_probability"):
        LandmarkEKFConfig(gate_probability=1.0)
    with pytest.raises(ConfigError, match="max_consecutive_rejects"):
        LandmarkEKFConfig(max_consecutive_rejects=0)
    with pytest.raises(ConfigError, match="inv_depth_min"):
        LandmarkEKFConfig(inv_depth_min=20.0)
    with pytest.raises(ConfigError, match="fx"):
        LandmarkEKFBank(LandmarkEKFConfig(), 0.0, 500.0)
    # it loads from a TOML table like every other module's config
    cfg = from_mapping(LandmarkEKFConfig, {"sigma_px": 2, "gate_probability": 0.99}, "ekf_landmark")
    assert cfg.sigma_px == 2.0 and cfg.gate_threshold == pytest.approx(chi2.ppf(0.99, 2))
    with pytest.raises(ConfigError, match="unknown key"):
        from_mapping(LandmarkEKFConfig, {"sigma_pix": 2}, "ekf_landmark")


def test_per_axis_input_noise():
    """A planar platform (odometer + one gyro axis) states noise per camera axis."""
    from companion.errors import ConfigError as _ConfigError

    cfg = LandmarkEKFConfig(sigma_v=(0.0, 0.0, 0.01), sigma_w=(0.0, 0.001, 0.0))
    bank = LandmarkEKFBank(cfg, 500.0, 500.0)
    np.testing.assert_allclose(bank.Q_psd, [0, 0, 1e-4, 0, 1e-6, 0])
    # on the optical axis ȳ is moved only by V_y and ω_x (both noise-free here), so it gains no
    # variance from the inputs (compare with a bank without input noise); ω_y noise moves x̄ and
    # V_z noise reaches ξ
    quiet = LandmarkEKFBank(LandmarkEKFConfig(sigma_v=0.0, sigma_w=0.0), 500.0, 500.0)
    for b in (bank, quiet):
        b.add([1], [[0.0, 0.0]], [0.1], [0.01])
        b.predict(np.array([0.0, 0.0, 0.5]), np.zeros(3), 0.1)
    assert bank.P[0, 1, 1] == pytest.approx(quiet.P[0, 1, 1], rel=1e-12)
    assert bank.P[0, 0, 0] > quiet.P[0, 0, 0]
    assert bank.P[0, 2, 2] > quiet.P[0, 2, 2]
    with pytest.raises(_ConfigError, match="sigma_v"):
        LandmarkEKFConfig(sigma_v=(0.1, 0.2))
