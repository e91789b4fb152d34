"""Position-error states of the anchored EKF (docs/derivations/ekf_anchored.md § Position error states).

The telemetry's position carries a first-order Gauss–Markov error e(t) (σ_p, τ); with
``position_tau_s`` > 0 each filter estimates δ = e(t) − e(t_anchor).  Checked here: the layout, the
analytic Jacobians of both measurement models against numeric ones for every layout, the process
model (Var δ grows by q Δt, also across rejected updates), the compiled kernels against the numpy
reference, and a seeded Monte Carlo with a Gauss–Markov position error in which the range σ is
honest with the states and over-confident without them.  The consider form (``position_consider``: δ's
gain is zero, its mean stays 0, its covariance and cross-covariances are carried) is checked against the
Joseph form with that gain, against the reference, and on a hover, where estimating δ drifts the range.
"""

import numpy as np
import pytest

from companion.core import jit
from companion.core.ekf_anchored import AnchoredEKFConfig, AnchoredInverseDepthEKF
from companion.core.frames import so3_exp
from companion.errors import ConfigError

from test_ekf_anchored_kernels import flight_bank, same_banks, same_results

BARE = dict(attitude_drift_deg_s=0.0, max_mean_nis=0.0)
#: (attitude_drift_deg_s, position_tau_s) → (n, drift, i_pos)
LAYOUTS = {(0.0, 0.0): (3, False, -1), (0.03, 0.0): (6, True, -1), (0.0, 30.0): (6, False, 3), (0.03, 30.0): (9, True, 6)}


@pytest.fixture
def path(monkeypatch):
    return lambda kernels: monkeypatch.setattr(jit, "ENABLED", kernels)


@pytest.mark.parametrize("drift,tau", list(LAYOUTS))
def test_layout(drift, tau):
    cfg = AnchoredEKFConfig(attitude_drift_deg_s=drift, position_tau_s=tau, position_sigma_m=0.2)
    assert cfg.layout() == LAYOUTS[(drift, tau)]
    bank = AnchoredInverseDepthEKF(cfg, 400.0, 400.0)
    assert (bank.n, bank.drift, bank.i_pos) == LAYOUTS[(drift, tau)]
    assert cfg.position_variance_limit == pytest.approx(2 * 0.2**2 if tau else 0.0)
    if tau:  # the Gauss–Markov difference: ≈ (2σ²/τ) Δt early, 2σ² late
        np.testing.assert_allclose(cfg.delta_variance([0.0, 0.01, 1e4]), [0.0, 2 * 0.2**2 * 0.01 / tau, 2 * 0.2**2], rtol=1e-3)


def test_no_states_without_a_position_error_and_bad_tau_refused():
    assert AnchoredEKFConfig(position_sigma_m=0.0, position_tau_s=30.0).layout()[2] == -1
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="position_tau_s"):
            AnchoredEKFConfig(position_tau_s=bad)


def _states(N, g, drift, pos):
    x = np.stack([g.uniform(-0.5, 0.5, N), g.uniform(-0.4, 0.4, N), g.uniform(0.01, 0.2, N)], 1)
    if drift:
        x = np.concatenate([x, g.normal(scale=0.01, size=(N, 3))], 1)
    if pos:
        x = np.concatenate([x, g.normal(scale=0.3, size=(N, 3))], 1)
    return x


def _geometry(N, g):
    RA = so3_exp(g.normal(scale=0.1, size=(N, 3)))
    pA = g.normal(size=(N, 3))
    Rp = RA @ so3_exp(g.normal(scale=0.05, size=(N, 3)))
    Cp = pA + np.einsum("nij,j->ni", RA, [0.3, -0.2, 1.8])
    Rc = Rp @ so3_exp(g.normal(scale=0.01, size=(N, 3)))
    C = Cp + np.einsum("nij,j->ni", Rp, [0.02, 0.01, 0.2])
    return RA, pA, Rp, Cp, Rc, C


def _numeric_jacobian(f, x, eps=1e-7):
    """Central differences of f (states (N,n) → (N,…)) in each state: (N,…,n)."""
    cols = []
    for j in range(x.shape[1]):
        d = np.zeros(x.shape[1])
        d[j] = eps
        cols.append((f(x + d) - f(x - d)) / (2 * eps))
    return np.stack(cols, -1)


@pytest.mark.parametrize("drift", [False, True])
def test_pixel_jacobian_with_position_states_matches_numeric(drift):
    g = np.random.default_rng(11)
    N = 40
    x = _states(N, g, drift, True)
    RA, pA, _, _, Rc, C = _geometry(N, g)
    dt = g.uniform(0.1, 3.0, N)

    def z(xx):
        return AnchoredInverseDepthEKF.measure(xx, RA, pA, Rc, C, dt, position_states=True)[1]

    _, _, H = AnchoredInverseDepthEKF.measure(x, RA, pA, Rc, C, dt, position_states=True)
    assert H.shape == (N, 2, x.shape[1])
    np.testing.assert_allclose(H, _numeric_jacobian(z, x), rtol=1e-5, atol=1e-7)
    # δ enters as a shift of the camera: the same pixel as the camera moved by −δ without the states
    n0 = x.shape[1] - 3
    z_states = AnchoredInverseDepthEKF.measure(x, RA, pA, Rc, C, dt, position_states=True)[1]
    z_moved = AnchoredInverseDepthEKF.measure(x[:, :n0], RA, pA, Rc, C - x[:, n0:], dt)[1]
    np.testing.assert_allclose(z_states, z_moved, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("drift", [False, True])
def test_looming_jacobian_with_position_states_matches_numeric(drift):
    g = np.random.default_rng(12)
    N = 40
    x = _states(N, g, drift, True)
    RA, pA, Rp, Cp, Rc, C = _geometry(N, g)
    dtp = g.uniform(0.1, 3.0, N)
    dt = dtp + 0.05

    def hs(xx):
        return AnchoredInverseDepthEKF.measure_looming(xx, RA, pA, Rp, Cp, Rc, C, dtp, dt, position_states=True)

    _, Hs = hs(x)
    np.testing.assert_allclose(Hs, _numeric_jacobian(lambda xx: hs(xx)[0], x), rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("kernels", [False, True])
def test_process_grows_the_delta_variance_also_when_rejected(path, kernels):
    """Var δ follows the Gauss–Markov difference 2σ²(1 − exp(−(t − t_A)/τ)) from 0 at the anchor while
    no update informs it (gated updates still advance it, in steps that add up to the same); time going
    backwards changes nothing."""
    path(kernels)
    cfg = AnchoredEKFConfig(**BARE, position_sigma_m=0.5, position_tau_s=25.0)
    bank = AnchoredInverseDepthEKF(cfg, 400.0, 400.0)
    bank.add([1], [[0.01, -0.02]], np.eye(3), np.zeros(3), 10.0, 0.05, 0.02)
    np.testing.assert_array_equal(bank.P[0, 3:, 3:], 0.0)
    assert bank.t_last[0] == 10.0
    outlier = [[0.6, 0.5]]  # far outside the gate: every update below is rejected
    for t in (10.4, 13.0, 40.0):
        res = bank.update([1], outlier, np.eye(3), np.array([0.0, 0.0, 1.0]), t)
        assert not res.accepted[0]
        np.testing.assert_allclose(np.diag(bank.P[0, 3:, 3:]), cfg.delta_variance(t - 10.0), rtol=1e-12)
        assert bank.t_last[0] == t
    bank.update([1], outlier, np.eye(3), np.array([0.0, 0.0, 1.0]), 20.0)
    np.testing.assert_allclose(np.diag(bank.P[0, 3:, 3:]), cfg.delta_variance(30.0), rtol=1e-12)
    assert bank.P[0, 3, 3] < 2 * 0.5**2


def _bank(drift, seed=0, consider=False):
    """test_ekf_anchored_kernels' flight bank with the position-error states (and the gyro bias when ``drift``)."""
    return flight_bank(seed=seed, attitude_drift_deg_s=drift, position_sigma_m=0.3, position_tau_s=20.0, iterations=3,
                       position_consider=consider)


@pytest.mark.parametrize("drift,consider", [(0.0, False), (0.03, False), (0.0, True), (0.03, True)])
def test_kernels_match_the_reference_with_position_states(path, drift, consider):
    """Frame updates, replayed sequences, looming and the outputs: the compiled kernels equal the numpy
    reference to float rounding, with δ in x (n = 6 and 9), estimated or considered."""
    runs = []
    for kernels in (False, True):
        path(kernels)
        bank, ids, xy, R, C, t = _bank(drift, consider=consider)
        seq, *_ = _bank(drift, seed=1, consider=consider)
        results = []
        for k in range(1, len(t)):
            sel = ids[(np.arange(len(ids)) + k) % 5 != 0]
            results.append(bank.update(sel, xy[k, sel - 100], R[k], C[k], t[k]))
            s = 1.0 + 0.03 * (C[k, 2] - C[k - 1, 2]) * np.ones(len(ids))
            s[k % len(ids)] = np.nan
            results += AnchoredInverseDepthEKF.update_looming_banks([(bank, ids, s, np.full(len(ids), 0.004))],
                                                                    R[k - 1], C[k - 1], t[k - 1], R[k], C[k], t[k])
        count = np.arange(len(ids)) % len(t)
        acc = seq.update_sequence(ids, np.swapaxes(xy[1:], 0, 1), np.broadcast_to(R[1:], (len(ids),) + R[1:].shape),
                                  np.broadcast_to(C[1:], (len(ids),) + C[1:].shape),
                                  np.broadcast_to(t[1:], (len(ids), len(t) - 1)), count)
        runs.append((bank, seq, results, acc, bank.estimates(C[-1])))
    (b0, s0, r0, a0, e0), (b1, s1, r1, a1, e1) = runs
    same_banks(b0, b1)
    same_banks(s0, s1)
    np.testing.assert_allclose(b0.t_last, b1.t_last, rtol=0)
    np.testing.assert_array_equal(a0, a1)
    for x, y in zip(r0, r1):
        same_results(x, y)  # (NaN NIS, where a scale was not measured, compare equal)
    for name in ("p_world", "range", "range_sigma", "inv_depth_sigma"):
        np.testing.assert_allclose(getattr(e1, name), getattr(e0, name), rtol=1e-8, err_msg=name)
    np.testing.assert_array_equal(e0.converged, e1.converged)
    assert np.any(b0.P[:, b0.i_pos, b0.i_pos] > 0) and e0.converged.any()
    d = slice(b0.i_pos, b0.i_pos + 3)
    assert np.all(b0.x[:, d] == 0) == consider  # considered: δ's mean never moves


@pytest.mark.parametrize("kernels", [False, True])
@pytest.mark.parametrize("looming", [False, True])
def test_consider_update_is_the_joseph_form_with_zero_delta_gain(path, kernels, looming):
    """One plain-EKF update (pixel or looming) of a landmark with correlated δ: with ``position_consider`` the
    state and covariance equal x + K y and (I − K H) P (I − K H)ᵀ + K R Kᵀ with K = P Hᵀ S⁻¹ and K's δ rows
    zeroed, computed here from the analytic Jacobian: δ's mean and covariance do not move, the rest does."""
    path(kernels)
    cfg = AnchoredEKFConfig(**BARE, position_sigma_m=0.2, position_tau_s=30.0, position_consider=True, iterations=1,
                            looming_iterations=1, looming_sigma_floor=0.003)
    bank = AnchoredInverseDepthEKF(cfg, 400.0, 400.0)
    g = np.random.default_rng(7)
    bank.add([1], [[0.05, -0.02]], np.eye(3), np.zeros(3), 0.0, 0.12, 0.03)
    A = g.normal(size=(6, 6)) * 0.02
    bank.P[0] = bank.P[0] + A @ A.T  # correlated δ (and everything else)
    bank.x[0, 3:] = [0.05, -0.03, 0.02]
    bank.t_last[0] = 2.0  # δ already propagated: the update adds no process noise
    x0, P0 = bank.x[0].copy(), bank.P[0].copy()
    Rp, Cp = so3_exp(np.array([0.01, -0.02, 0.005])), np.array([0.2, 0.1, 2.0])
    Rc, C = so3_exp(np.array([0.012, -0.018, 0.004])), np.array([0.22, 0.1, 2.15])
    if looming:
        z = np.array([1.02])
        res = AnchoredInverseDepthEKF.update_looming_banks([(bank, np.array([1]), z, np.array([0.004]))], Rp, Cp, 1.9,
                                                           Rc, C, 2.0)[0]
        zhat, H = AnchoredInverseDepthEKF.measure_looming(x0[None], np.eye(3), np.zeros(3), Rp, Cp, Rc, C,
                                                          position_states=True)
        y, H, Rm = (z - zhat[0])[:, None], H[0][None, :], np.array([[0.004**2 + 0.003**2]])
    else:
        _, zhat, H = AnchoredInverseDepthEKF.measure(x0[None], np.eye(3)[None], np.zeros((1, 3)), Rc, C,
                                                     position_states=True)
        zhat, H = zhat[0], H[0]
        z = zhat + np.array([0.004, -0.003])
        res = bank.update([1], z[None], Rc, C, 2.0)
        y, Rm = (z - zhat)[:, None], np.diag(bank.measurement_variance(x0[None])[0])
    assert res.accepted[0]
    S = H @ P0 @ H.T + Rm
    K = P0 @ H.T @ np.linalg.inv(S)
    K[3:] = 0.0
    I_KH = np.eye(6) - K @ H
    np.testing.assert_allclose(bank.x[0], x0 + (K @ y)[:, 0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(bank.P[0], I_KH @ P0 @ I_KH.T + K @ Rm @ K.T, rtol=1e-7, atol=1e-12)
    np.testing.assert_array_equal(bank.x[0, 3:], x0[3:])
    np.testing.assert_allclose(bank.P[0, 3:, 3:], P0[3:, 3:], rtol=1e-12)
    assert abs(bank.x[0, 2] - x0[2]) > 1e-6 and not np.allclose(bank.P[0, :3, 3:], P0[:3, 3:])  # ρ and the cross terms move


def test_range_sigma_includes_delta():
    """The range's σ grows with Var δ along the line of sight, and the point moves with δ."""
    cfg = AnchoredEKFConfig(**BARE, position_sigma_m=0.5, position_tau_s=30.0)
    bank = AnchoredInverseDepthEKF(cfg, 400.0, 400.0)
    bank.add([1], [[0.0, 0.0]], np.eye(3), np.zeros(3), 0.0, 0.05, 1e-6)  # 20 m ahead, ρ nearly exact
    base = bank.estimates(np.zeros(3))
    bank.P[0, 5, 5] = 0.25  # Var δ_z = (0.5 m)² along the ray (camera z)
    bank.x[0, 5] = 0.3
    e = bank.estimates(np.zeros(3))
    assert base.range_sigma[0] < 0.01
    np.testing.assert_allclose(e.range_sigma[0], np.hypot(base.range_sigma[0], 0.5), rtol=1e-6)
    np.testing.assert_allclose(e.range[0], 20.3, rtol=1e-9)
    np.testing.assert_allclose(e.p_world[0], [0.0, 0.0, 20.3], atol=1e-9)


def _gauss_markov_flight(cfg, runs, **kw):
    """bench.position_states' seeded flights: (range NEES, within ±2σ) of the landmarks in view at the end."""
    from bench.position_states import gauss_markov_flight

    e, s, _ = gauss_markov_flight(cfg, runs, **kw)
    return e**2 / s**2, np.abs(e) <= 2 * s


@pytest.mark.parametrize("kind", ["fixed-wing", "quad"])
def test_gauss_markov_position_error_honest_with_states(path, kind):
    """Landmarks followed for 5–6 s under a Gauss–Markov position error: with the states the range NEES
    is ≈ 1 and ±2σ covers ≈ 95 % (≥ 90 % asserted); the same flights with the error treated as white noise are
    over-confident (NEES ≈ 3.5–4.3, ±2σ ≈ 70 % at 100 runs): a correlated error does not average out."""
    path(True)
    from bench.position_states import CASES

    kw = CASES[kind]
    runs = 40
    states = AnchoredEKFConfig(**BARE, position_sigma_m=kw["sigma"], position_tau_s=30.0)
    white = AnchoredEKFConfig(**BARE, position_sigma_m=kw["sigma"], position_tau_s=0.0)
    nees_s, cov_s = _gauss_markov_flight(states, runs, **kw)
    nees_w, cov_w = _gauss_markov_flight(white, runs, **kw)
    # ~130–160 NEES samples but only 40 position-error paths (the landmarks of one run share theirs): the
    # band of 40 independent χ²₁ samples, two-sided 99 %, [0.50, 1.71], is the honest one
    assert 0.5 <= nees_s.mean() <= 1.71, nees_s.mean()
    assert cov_s.mean() >= 0.9, cov_s.mean()  # 95.4 % expected; ~40 independent paths
    assert nees_w.mean() > 2.0 and cov_w.mean() < 0.85, (nees_w.mean(), cov_w.mean())


@pytest.mark.parametrize("position_sigma", [0.0, 0.1])
def test_hover_drifts_the_range_when_delta_is_estimated_not_when_considered(path, position_sigma):
    """bench.position_states' hover: 3 s of approach at 1 m/s, then 6 s of hover before landmarks 2–6 m away, 40
    seeded runs, the filter told σ_p = 0.1 m.  In a hover the pixels cannot tell ρ from δ along the line of sight;
    an EKF that estimates δ gains information there at each relinearization and drifts.  With exact telemetry
    (``position_sigma`` 0) the estimated δ pull the ranges short by ~18σ (NEES ~630); considered, they stay put
    (|mean error| < 0.5σ).  With the simulator's 0.1 m Gauss–Markov error: NEES ~33 estimated, ~1.4 considered,
    ~12 with the white term."""
    path(True)
    from bench.position_states import CASES

    kw = dict(CASES["hover"], sigma=position_sigma)

    def z_of(tau, consider):
        cfg = AnchoredEKFConfig(**BARE, max_drift_chi2=0.0, position_sigma_m=0.1, position_tau_s=tau, position_consider=consider)
        e, s, _ = gauss_markov_flight(cfg, 40, **kw)
        return e / s

    from bench.position_states import gauss_markov_flight

    z_est, z_con = z_of(30.0, False), z_of(30.0, True)
    assert len(z_con) > 250
    if position_sigma == 0.0:
        assert z_est.mean() < -5.0 and np.mean(z_est**2) > 100.0
        assert abs(z_con.mean()) < 0.5 and np.mean(z_con**2) < 1.0
    else:
        z_white = z_of(0.0, False)
        assert np.mean(z_est**2) > 10.0 and np.mean(z_white**2) > 5.0
        assert 0.5 < np.mean(z_con**2) < 2.0 and np.mean(np.abs(z_con) <= 2) > 0.85


def test_bench_command_prints_every_case(capsys):
    """python -m bench.position_states: a table row (and a JSON entry) per case and model."""
    from bench import position_states

    assert position_states.main(["--runs", "3", "--json"]) == 0
    import json

    res = json.loads(capsys.readouterr().out)
    assert set(res) == {f"{c}/{m}" for c in ("quad", "fixed-wing", "hover") for m in ("white", "states", "consider")}
    assert all(r["runs"] == 3 and r["landmarks"] > 0 and np.isfinite(r["nees_mean"]) for r in res.values())
    assert position_states.main(["--runs", "2"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ")]
    assert len(rows) == 1 + 9  # header + a row per case and model
    with pytest.raises(SystemExit):
        position_states.main(["--runs", "1"])
