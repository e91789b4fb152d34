"""Batch refinement of anchored landmarks (docs/derivations/ekf_anchored.md § Batch refinement): the Gauss–Newton
MAP against exact geometry, against a general least-squares solver on the same cost, its covariance against the
numeric information, the looming rows, the gyro-bias states, and what it refuses."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from companion.core.ekf_anchored import AnchoredEKFConfig, AnchoredInverseDepthEKF, inverse_depth_state
from companion.core.obs_history import ObservationHistory
from companion.errors import InputError

F = 400.0
RHO_PRIOR, RHO_SIGMA = 0.01, 0.02


def _poses(k, forward=1.0, lateral=0.3):
    """k camera poses (R_world_cam = I: camera axes = world axes, z forward) moving forward and sideways."""
    t = np.arange(k) / 30.0
    C = np.stack([lateral * np.arange(k) / 30.0, np.zeros(k), forward * np.arange(k) / 30.0], 1)
    return np.repeat(np.eye(3)[None], k, 0), C, t


def _project(P_world, R, C):
    q = (P_world - C) @ R  # R_world_cam: world → camera is Rᵀ (row vector times R)
    return q[:, :2] / q[:, 2:3]


def _bank(sigma_px=1.0, drift=0.0, **kw):
    """Gauss–Newton run to convergence (20 steps: these starts are far from the optimum; the estimator's start
    is the filter's own estimate, where the shipped 3 suffice)."""
    cfg = AnchoredEKFConfig(sigma_px=sigma_px, attitude_drift_deg_s=drift, position_sigma_m=0.0, refine_iterations=20, **kw)
    return AnchoredInverseDepthEKF(cfg, F, F)


def _setup(point, k=40, noise_px=0.0, seed=0, rho_start_factor=3.0, drift=0.0):
    """A bank holding one landmark anchored at frame 0 with a wrong ρ, and the history of frames 1..k−1."""
    rng = np.random.default_rng(seed)
    R, C, t = _poses(k)
    xy = np.array([_project(point[None], R[i], C[i])[0] for i in range(k)]) + noise_px / F * rng.standard_normal((k, 2))
    bank = _bank(drift=drift)
    x_true = inverse_depth_state(point[None], R[:1], C[:1])[0]
    bank.add([7], xy[:1], R[0], C[0], t[0], rho_start_factor * x_true[2], RHO_SIGMA)
    hist = ObservationHistory(64)
    hist.record_anchor([7], t[0], R[0], C[0])
    for i in range(1, k):
        hist.record_pixels([7], t[i], R[i], C[i], xy[i:i + 1])
    return bank, hist, x_true, (R, C, t, xy)


def _info_numeric(bank, x, R, C, xp_P):
    """Prior information + Σ Hᵀ W H with H by central differences of ``measure``."""
    n = bank.n
    info = np.linalg.inv(xp_P)
    var = bank.measurement_variance(x[None])[0]
    for Ri, Ci in zip(R, C):
        H = np.zeros((2, n))
        for j in range(n):
            d = np.zeros(n)
            d[j] = 1e-7 * max(1.0, abs(x[j]))
            zp = bank.measure((x + d)[None], bank.R_world_camA, bank.p_world_camA, Ri, Ci)[1][0]
            zm = bank.measure((x - d)[None], bank.R_world_camA, bank.p_world_camA, Ri, Ci)[1][0]
            H[:, j] = (zp - zm) / (2 * d[j])
        info += H.T @ (H / var[:, None])
    return info


def test_refinement_lands_on_the_true_point_from_a_wrong_start():
    point = np.array([2.0, 1.0, 20.0])
    bank, hist, x_true, _ = _setup(point)
    assert abs(bank.x[0, 2] / x_true[2] - 3.0) < 1e-9  # starts three times too near
    # exact pixels and a prior on ρ too wide to pull (σ 10 m⁻¹): the MAP is the true point
    improved = bank.refine([7], hist.gather([7]), RHO_PRIOR, 10.0)
    assert improved.tolist() == [True]
    assert np.allclose(bank.x[0], x_true, rtol=1e-6, atol=1e-10)
    # with the wide prior of the estimator (σ 0.02) over this short baseline the prior pulls ρ (0.05) towards 0.01:
    # the MAP trades pixel residual for prior cost, and lies below the truth's cost
    bank.x[0, 2] = 3.0 * x_true[2]
    res = bank.refine([7], hist.gather([7]), RHO_PRIOR, RHO_SIGMA)
    assert res[0] and RHO_PRIOR < bank.x[0, 2] < x_true[2]


def test_refinement_is_the_map_of_a_general_least_squares_solver_and_its_information():
    point = np.array([-3.0, 0.5, 35.0])
    bank, hist, x_true, (R, C, t, xy) = _setup(point, k=50, noise_px=2.0, seed=3)
    xp, Pp = (a[0] for a in bank._prior(bank.xy_anchor[:1], RHO_PRIOR, RHO_SIGMA))
    assert np.allclose(xp[:2], bank.x[0, :2]) and Pp[2, 2] == RHO_SIGMA**2  # the anchor pixel's angles, as add set them
    U = np.linalg.cholesky(np.linalg.inv(Pp)).T  # prior information = Uᵀ U
    sig = bank.sigma_xy

    def residual(x):
        z = bank.measure(np.repeat(x[None], len(R) - 1, 0), np.repeat(bank.R_world_camA, len(R) - 1, 0),
                         np.repeat(bank.p_world_camA, len(R) - 1, 0), R[1:], C[1:])[1]
        return np.concatenate([U @ (x - xp), ((xy[1:] - z) / sig).ravel()])

    ref = least_squares(residual, bank.x[0].copy(), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    improved = bank.refine([7], hist.gather([7]), RHO_PRIOR, RHO_SIGMA)
    assert improved[0]
    assert np.allclose(bank.x[0], ref.x, rtol=1e-6, atol=1e-10)
    # P is the inverse information at the optimum (numeric Jacobians of the measurement model)
    info = _info_numeric(bank, bank.x[0], R[1:], C[1:], Pp)
    assert np.allclose(np.linalg.inv(bank.P[0]), info, rtol=1e-4)


def test_refinement_with_gyro_bias_states_matches_least_squares():
    point = np.array([1.0, -1.0, 25.0])
    bank, hist, x_true, (R, C, t, xy) = _setup(point, k=45, noise_px=1.0, seed=5, drift=0.05)
    assert bank.n == 6
    xp, Pp = (a[0] for a in bank._prior(bank.xy_anchor[:1], RHO_PRIOR, RHO_SIGMA))
    assert np.allclose(Pp[3:, 3:], np.radians(0.05) ** 2 * np.eye(3)) and not xp[3:].any()
    U = np.linalg.cholesky(np.linalg.inv(Pp)).T
    sig = bank.sigma_xy
    k = len(R) - 1

    def residual(x):
        z = bank.measure(np.repeat(x[None], k, 0), np.repeat(bank.R_world_camA, k, 0), np.repeat(bank.p_world_camA, k, 0),
                         R[1:], C[1:], dt=t[1:] - t[0])[1]
        return np.concatenate([U @ (x - xp), ((xy[1:] - z) / sig).ravel()])

    ref = least_squares(residual, bank.x[0].copy(), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert bank.refine([7], hist.gather([7]), RHO_PRIOR, RHO_SIGMA)[0]
    assert np.allclose(bank.x[0], ref.x, rtol=1e-5, atol=1e-9)


def test_looming_rows_range_a_point_at_the_focus_of_expansion():
    """Head-on at the focus of expansion the pixels carry no range; the looming rows of the history do."""
    point = np.array([0.0, 0.0, 30.0])
    k = 40
    R, C, t = _poses(k, forward=5.0, lateral=0.0)
    bank = _bank(sigma_px=0.5)
    x_true = inverse_depth_state(point[None], R[:1], C[:1])[0]
    bank.add([1], np.zeros((1, 2)), R[0], C[0], t[0], RHO_PRIOR, RHO_SIGMA)
    hist = ObservationHistory(64)
    hist.record_anchor([1], t[0], R[0], C[0])
    depth = point[2] - C[:, 2]
    for i in range(1, k):
        hist.record_pixels([1], t[i], R[i], C[i], np.zeros((1, 2)))
        hist.record_looming([1], t[i], R[i], C[i], t[i - 1], [depth[i - 1] / depth[i]], [1e-6])
    pixels_only = ObservationHistory(64)
    for i in range(1, k):
        pixels_only.record_pixels([1], t[i], R[i], C[i], np.zeros((1, 2)))
    g = pixels_only.gather([1])
    assert not np.isfinite(g["s"]).any()
    x0 = bank.x.copy()
    bank.refine([1], g, RHO_PRIOR, RHO_SIGMA)
    assert abs(bank.x[0, 2] - RHO_PRIOR) < 1e-6  # bearings alone: ρ stays at its prior
    bank.x[:] = x0
    assert bank.refine([1], hist.gather([1]), RHO_PRIOR, RHO_SIGMA)[0]
    assert abs(bank.x[0, 2] / x_true[2] - 1.0) < 1e-3
    assert np.sqrt(bank.P[0, 2, 2]) < 0.05 * x_true[2]


def test_refinement_keeps_the_filter_where_it_cannot_improve_and_refuses_position_states():
    point = np.array([2.0, 1.0, 20.0])
    bank, hist, x_true, _ = _setup(point)
    g = hist.gather([7])
    bank.refine([7], g, RHO_PRIOR, RHO_SIGMA)
    x1, P1 = bank.x.copy(), bank.P.copy()
    # from the optimum a second refinement finds nothing lower: x stays (P is already the batch one)
    bank.refine([7], g, RHO_PRIOR, RHO_SIGMA)
    assert np.allclose(bank.x, x1, rtol=1e-9) and np.allclose(bank.P, P1, rtol=1e-6)
    with pytest.raises(InputError, match="prior"):
        bank.refine([7], g, RHO_PRIOR, 0.0)
    with pytest.raises(InputError, match="unknown"):
        bank.refine([8], g, RHO_PRIOR, RHO_SIGMA)
    pos = AnchoredInverseDepthEKF(AnchoredEKFConfig(position_tau_s=30.0, position_sigma_m=0.1, refine_max_obs=128), F, F)
    assert not pos.config.refine
    with pytest.raises(InputError, match="position-error"):
        pos.refine([1], g, RHO_PRIOR, RHO_SIGMA)


def test_config_validates_the_refinement_keys():
    assert not AnchoredEKFConfig().refine and AnchoredEKFConfig(refine_max_obs=128).refine  # off by default
    for bad in ({"refine_max_obs": -1}, {"refine_max_obs": 4}, {"refine_min_obs": 1}, {"refine_iterations": 0},
                {"refine_max_obs": True}, {"refine_min_obs": 2.0}, {"refine_max_slots": 0}):
        with pytest.raises(Exception, match="refine_"):
            AnchoredEKFConfig(**bad)


def test_compiled_and_reference_cost_information_and_gradient_agree():
    """The batch cost's kernel (ekf_anchored_kernels.refine_evaluate) against the numpy reference, three landmarks
    with the gyro-bias states, pixels and looming, a refused pixel (its slot holds only a scale)."""
    from companion.core import ekf_anchored_refine as ER
    from companion.core import jit

    if not jit.ENABLED:
        pytest.skip("compiled kernels are off (COMPANION_KERNELS=numpy or no numba)")
    rng = np.random.default_rng(11)
    k = 30
    R, C, t = _poses(k, forward=3.0, lateral=0.5)
    bank = _bank(drift=0.05)
    pts = np.array([[1.0, 0.5, 20.0], [-2.0, -1.0, 30.0], [0.2, 0.1, 15.0]])
    xy = np.stack([_project(pts, R[i], C[i]) for i in range(k)], 1) + 1e-3 * rng.standard_normal((3, k, 2))
    bank.add([1, 2, 3], xy[:, 0], R[0], C[0], t[0], 0.04, RHO_SIGMA)
    hist = ObservationHistory(64)
    hist.record_anchor([1, 2, 3], t[0], R[0], C[0])
    depth = pts[:, 2][:, None] - C[:, 2][None]
    for i in range(1, k):
        keep = [0, 1] if i == 12 else [0, 1, 2]  # landmark 3's pixel refused at frame 12
        hist.record_pixels(np.array([1, 2, 3])[keep], t[i], R[i], C[i], xy[keep, i])
        hist.record_looming([1, 2, 3], t[i], R[i], C[i], t[i - 1], depth[:, i - 1] / depth[:, i] + 1e-4 * rng.standard_normal(3),
                            np.full(3, 1e-6))
    h = hist.gather([1, 2, 3])
    assert np.isnan(h["z"][h["starts"][2] + 12, 0]) and np.isfinite(h["s"][h["starts"][2] + 12])
    x = bank.x + 1e-3 * rng.standard_normal(bank.x.shape)
    xp = x + 1e-3
    Ip = np.repeat(np.diag([1e6, 1e6, 2500.0, 1e7, 1e7, 1e7])[None], 3, 0)
    W = np.where(np.isfinite(h["z"]), 1.0 / bank.sigma_xy**2, np.nan)
    args = (x, xp, Ip, bank.R_world_camA, bank.p_world_camA, bank.t_anchor, h, W, True, -1)
    ref = ER._evaluate(*args)
    ker = ER._evaluate_kernel(*args)
    for a, b in zip(ref[:3], ker[:3]):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)
    assert ref[3].all() and ker[3].all()


def test_a_singular_system_leaves_that_landmark_alone_and_raises_nothing():
    from companion.core.ekf_anchored_refine import _solve_or_nan

    A = np.stack([np.eye(3), np.zeros((3, 3)), 2.0 * np.eye(3)])
    b = np.ones((3, 3))
    x = _solve_or_nan(A, b)
    assert np.allclose(x[0], 1.0) and np.isnan(x[1]).all() and np.allclose(x[2], 0.5)
    inv = _solve_or_nan(A, None)
    assert np.allclose(inv[2], 0.5 * np.eye(3)) and np.isnan(inv[1]).all()
