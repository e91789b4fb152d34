"""The sector's nearest surface (docs/derivations/sectors.md, "Nearest surface"): a sector's live points
consistent with its nearest one are fused, so the published value is a lower bound of the stated
confidence instead of the nearest of many noisy points (an order statistic, biased near)."""

import dataclasses
import math

import numpy as np
import pytest

from companion.core.sectors import SectorConfig, SectorState, compute_sectors, compute_sectors_reference
from companion.errors import ConfigError

HFOV = math.radians(60.0)
CFG = SectorConfig(sigma_k_taper_to_m=0.0)  # as shipped (fusion on), the margin's taper off: values d̄ − 2σ̄ at any range
OFF = dataclasses.replace(CFG, fuse_gate_k=0.0)


def points_at(ranges, bearings_deg, height=0.0):
    b = np.radians(np.asarray(bearings_deg, float))
    r = np.asarray(ranges, float)
    return np.stack([r * np.cos(b), r * np.sin(b), np.full(b.shape, height)], 1)


def sectors(p, sig, config=CFG, reference=False, **kw):
    n = len(p)
    f = compute_sectors_reference if reference else compute_sectors
    return f(p, np.asarray(sig, float), np.ones(n, bool), np.ones(n, bool), HFOV, 0.0, config, **kw)


def fused_expected(d, s, rho, k, gate):
    """The fused conservative value by hand: members agree with the anchor (smallest d − kσ) within
    gate·hypot(σ_i, σ_a); inverse-variance mean; variance of a mean of equicorrelated errors."""
    d, s = np.asarray(d, float), np.asarray(s, float)
    a = np.argmin(d - k * s)
    m = np.abs(d - d[a]) <= gate * np.hypot(s, s[a])
    w = 1 / s[m] ** 2
    d_bar = np.sum(w * d[m]) / np.sum(w)
    var = ((1 - rho) * np.sum(w) + rho * np.sum(1 / s[m]) ** 2) / np.sum(w) ** 2
    return d_bar - k * math.sqrt(var), math.sqrt(var), d_bar, m


@pytest.mark.parametrize("reference", [False, True])
def test_fused_value_is_the_formula(reference):
    """Five points of one sector with unequal σ, one of them beyond the gate: the published value,
    σ and estimate are those of the inverse-variance mean of the four consistent ones."""
    d = np.array([10.2, 10.0, 10.5, 9.9, 14.0])
    s = np.array([0.4, 0.3, 0.6, 0.5, 0.3])
    out = sectors(points_at(d, [0.0, 0.5, -0.5, 1.0, -1.0]), s, reference=reference)
    value, sig_bar, d_bar, m = fused_expected(d, s, CFG.fuse_correlation, CFG.sigma_k, CFG.fuse_gate_k)
    assert m.tolist() == [True, True, True, True, False]
    assert out.state[0] == SectorState.OBSTACLE
    assert out.distances_cm[0] == round(value * 100)
    assert out.range_m[0] == pytest.approx(value, abs=1e-12)
    assert out.sigma_m[0] == pytest.approx(sig_bar, abs=1e-12)
    assert out.forward.sigma_m == pytest.approx(sig_bar, abs=1e-12)
    assert out.forward.estimate_m == pytest.approx(d_bar, abs=1e-12)
    # without fusion: the nearest conservative point, 9.9 − 2·0.5
    assert sectors(points_at(d, [0.0, 0.5, -0.5, 1.0, -1.0]), s, OFF, reference=reference).distances_cm[0] == 890


def test_correlation_bounds_the_fused_sigma():
    """m equal points: σ̄ = σ √(ρ + (1 − ρ)/m); ρ = 1 (errors all shared) leaves σ unchanged."""
    d, s = np.full(12, 20.0), np.full(12, 1.0)
    p = points_at(d, np.linspace(-2.0, 2.0, 12))
    for rho in (0.0, 0.3, 1.0):
        out = sectors(p, s, dataclasses.replace(CFG, fuse_correlation=rho))
        assert out.sigma_m[0] == pytest.approx(math.sqrt(rho + (1 - rho) / 12), rel=1e-9)


def test_fusion_removes_the_order_statistic_bias():
    """Seeded Monte Carlo: a wall at 20 m, 15 points in the forward sector, σ = 1 m, errors with a
    shared part (correlation ρ as configured) and an independent part.  The nearest point − 2σ lies
    ~3.5 m short of the wall on average (beyond the scorer's 20 % tolerance in a quarter of the
    trials); the fused value lies 2σ̄ short, and below the truth in about 97.7 % of trials (one-sided
    2σ), as it states."""
    rng = np.random.default_rng(1504)
    rho, n, trials, truth = CFG.fuse_correlation, 15, 2000, 20.0
    bearings = np.linspace(-2.0, 2.0, n)
    pub_on, pub_off = np.empty(trials), np.empty(trials)
    for t in range(trials):
        e = math.sqrt(rho) * rng.normal() + math.sqrt(1 - rho) * rng.normal(size=n)
        p = points_at(truth / np.cos(np.radians(bearings)) + e, bearings)  # ranges along each ray
        pub_on[t] = sectors(p, np.ones(n)).range_m[0]
        pub_off[t] = sectors(p, np.ones(n), OFF).range_m[0]
    short_on, short_off = truth - pub_on.mean(), truth - pub_off.mean()
    assert 1.0 < short_on < 1.4  # 2σ̄ = 2·√(0.3 + 0.7/15) ≈ 1.18 m
    assert short_off > 3.0  # 2σ plus the expected minimum of 15 normals (≈ 1.7σ·√0.7)
    below = np.mean(pub_on <= truth)
    assert 0.96 <= below <= 0.99
    assert np.mean(pub_off < 0.8 * truth) > 0.15 and np.mean(pub_on < 0.8 * truth) < 0.001


def test_a_pole_in_front_of_a_wall_is_not_averaged_away():
    """A pole's two points at 8 m and a wall's ten at 20 m in one sector: the gate keeps them apart;
    the sector reports the pole (fused with itself only), never something between."""
    p = np.vstack([points_at([8.0, 8.1], [0.2, -0.2]), points_at(np.full(10, 20.0), np.linspace(-2, 2, 10))])
    s = np.r_[0.3, 0.3, np.full(10, 1.0)]
    out = sectors(p, s)
    value, *_ = fused_expected([8.0, 8.1], [0.3, 0.3], CFG.fuse_correlation, CFG.sigma_k, CFG.fuse_gate_k)
    assert out.range_m[0] == pytest.approx(value, abs=1e-9)
    assert out.range_m[0] < 8.0
    # one pole point alone: exactly its own conservative value, as without fusion
    one = np.vstack([p[:1], p[2:]])
    s1 = np.r_[0.3, np.full(10, 1.0)]
    assert sectors(one, s1).distances_cm[0] == sectors(one, s1, OFF).distances_cm[0] == 740


def test_remembered_points_are_not_fused():
    """Remembered points share the drift since they were last seen (and spread copies are one point):
    they keep their own conservative values; a sector of them only publishes their nearest."""
    mem = points_at([12.0, 12.2, 12.1], [90.0, 91.0, 89.0])  # beside the vehicle, out of view
    args = (np.zeros((0, 3)), [])
    kw = dict(remembered_p_body=mem, remembered_sigma=np.full(3, 0.5), remembered_tangential_sigma=np.zeros(3))
    on, off = sectors(*args, **kw), sectors(*args, OFF, **kw)
    assert on.state[18] == SectorState.OBSTACLE
    assert np.array_equal(on.distances_cm, off.distances_cm)
    assert on.distances_cm[18] == 1100


def test_fusion_never_turns_an_obstacle_into_clear():
    """Far, uncertain points within max_distance conservatively: fused, the sector stays an obstacle
    (at most max_distance), never "clear"."""
    p = points_at(np.full(6, 41.0), np.linspace(-2, 2, 6))
    out = sectors(p, np.full(6, 2.0))  # each 41 − 4 = 37 m (near); fused ≈ 41 − 2.3 > 38 m
    assert out.state[0] == SectorState.OBSTACLE
    assert out.range_m[0] <= CFG.max_distance_m


@pytest.mark.parametrize("changes", [dict(fuse_gate_k=-1.0), dict(fuse_gate_k=math.nan), dict(fuse_correlation=1.5),
                                     dict(fuse_correlation=-0.1)])
def test_bad_fusion_settings_are_rejected(changes):
    with pytest.raises(ConfigError):
        dataclasses.replace(CFG, **changes)
