"""Consistency of the reported σ as the scorer reports it: the effective sample size of a
correlated series (AR(1) with a known answer, white noise, gaps), the NEES band with n_eff, χ²
quantiles for non-integer degrees of freedom, and the ±σ / ±2σ coverage."""

import math

import numpy as np
import pytest

from flightsim.score.stats import (autocorrelation, chi2_quantile, coverage, effective_sample_size, nees_band,
                                   normal_coverage, pooled_n_eff, stretch_labels)
from flightsim.score.summary import nees_stats


def ar1(phi: float, n: int, rng) -> np.ndarray:
    """Stationary AR(1): x_i = φ x_{i−1} + e_i, unit innovations."""
    e = rng.standard_normal(n)
    x = np.empty(n)
    x[0] = e[0] / math.sqrt(1 - phi * phi)
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    return x


@pytest.mark.parametrize("phi", [0.3, 0.6, 0.9])
def test_n_eff_of_an_ar1_series(phi):
    rng = np.random.default_rng(11)
    n = 20000
    expected = n * (1 - phi) / (1 + phi)
    got = [effective_sample_size(ar1(phi, n, rng)).n_eff for _ in range(4)]
    assert np.mean(got) == pytest.approx(expected, rel=0.12)
    # the NEES of a Gaussian AR(1) error is correlated as φ^2k: n_eff = n (1 − φ²) / (1 + φ²)
    got_sq = [effective_sample_size(ar1(phi, n, rng) ** 2).n_eff for _ in range(4)]
    assert np.mean(got_sq) == pytest.approx(n * (1 - phi ** 2) / (1 + phi ** 2), rel=0.15)


def test_n_eff_of_white_noise_is_about_n():
    rng = np.random.default_rng(3)
    for _ in range(5):
        n = 5000
        r = effective_sample_size(rng.standard_normal(n))
        assert 0.9 * n <= r.n_eff <= n and r.stretches == 1
        assert effective_sample_size(rng.chisquare(1, n)).n_eff >= 0.9 * n  # NEES of independent errors
    # anticorrelated: never more than n
    x = ar1(-0.5, 5000, rng)
    assert effective_sample_size(x).n_eff == pytest.approx(5000)


def test_n_eff_degenerate_series():
    assert effective_sample_size(np.zeros(0)).n_eff == 0
    assert effective_sample_size(np.array([3.0])).n_eff == 1
    assert effective_sample_size(np.full(50, 2.0)).n_eff == 50  # no variance: nothing correlated
    assert autocorrelation(np.full(5, 2.0)).tolist() == [1.0, 0.0, 0.0, 0.0, 0.0]


def test_gaps_break_the_series():
    t = np.r_[np.arange(10) * 0.1, 5.0 + np.arange(5) * 0.1, 4.0, 4.05]  # a gap, then time going back
    assert stretch_labels(t, 0.5).tolist() == [0] * 10 + [1] * 5 + [2, 2]
    # a strongly correlated series cut into 40 stretches of 25 samples: no pair straddles a gap,
    # so independent stretches (each its own constant offset) are each worth about one sample
    rng = np.random.default_rng(5)
    x = np.repeat(rng.standard_normal(40), 25) + 0.01 * rng.standard_normal(1000)
    t = np.arange(1000) * 0.1 + np.repeat(np.arange(40) * 10.0, 25)
    r = effective_sample_size(x, t, 0.5)
    assert r.stretches == 40 and r.n_eff == pytest.approx(40, rel=0.25)
    # without the gaps the same numbers look like one long stretch of slowly varying data
    assert effective_sample_size(x).n_eff < r.n_eff
    # the autocorrelation pools only pairs within a stretch: the pair across the step is not one
    x = np.r_[np.ones(4), -np.ones(4)]
    assert autocorrelation(x, np.r_[np.zeros(4), np.ones(4)])[1] == pytest.approx(1.0)
    assert autocorrelation(x)[1] == pytest.approx(5 / 7)


def test_pooled_n_eff():
    assert pooled_n_eff([100, 100], [10, 30]) == pytest.approx(200 ** 2 / (100 ** 2 / 10 + 100 ** 2 / 30))
    assert pooled_n_eff([100, 300], [10, 30]) == pytest.approx(40)  # one correlation time: the sum
    assert pooled_n_eff([1000, 10], [10, 10]) == pytest.approx(1010 ** 2 / (1000 ** 2 / 10 + 10))  # ≈ 10, not 20
    assert pooled_n_eff([], []) == 0.0


def test_band_with_n_eff_widens_as_correlation_grows():
    rng = np.random.default_rng(8)
    n = 4000
    widths, neffs = [], []
    for phi in (0.0, 0.5, 0.8, 0.95):
        z = ar1(phi, n, rng) * math.sqrt(1 - phi * phi)  # unit-variance normalized errors
        ess = effective_sample_size(z ** 2)
        s = nees_stats(z ** 2, 0.95, ess=ess)
        neffs.append(s["n_eff"])
        widths.append(s["band"][1] - s["band"][0])
        assert s["band_independent"] == pytest.approx(list(nees_band(n, 0.95)))
        assert s["band"][0] <= s["band_independent"][0] and s["band"][1] >= s["band_independent"][1]
    assert all(a > b for a, b in zip(neffs, neffs[1:]))
    assert all(a < b for a, b in zip(widths, widths[1:]))


def test_correlated_errors_with_the_right_sigma_are_consistent_with_n_eff():
    """Most seeds of a strongly correlated, correctly scaled error fail the independent band; the
    n_eff band holds them at about its confidence."""
    rng = np.random.default_rng(21)
    phi, n, runs = 0.95, 600, 60
    ok_eff = ok_ind = 0
    for _ in range(runs):
        z = ar1(phi, n, rng) * math.sqrt(1 - phi * phi)
        s = nees_stats(z ** 2, 0.95, ess=effective_sample_size(z ** 2))
        ok_eff += s["consistent"]
        ok_ind += s["consistent_independent"]
    assert ok_ind / runs < 0.6
    assert ok_eff / runs > 0.8


def test_chi2_quantile_non_integer_dof_matches_scipy():
    stats = pytest.importorskip("scipy.stats")
    for dof in (1.0, 1.37, 2.5, 7.3, 14.91, 250.5, 3333.3):
        for p in (0.025, 0.5, 0.975):
            assert chi2_quantile(p, dof) == pytest.approx(stats.chi2.ppf(p, dof), rel=1e-8)
        lo, hi = nees_band(dof, 0.95)
        assert lo == pytest.approx(stats.chi2.ppf(0.025, dof) / dof, rel=1e-8)
        assert hi == pytest.approx(stats.chi2.ppf(0.975, dof) / dof, rel=1e-8)
    assert chi2_quantile(0.025, 0.6) == pytest.approx(stats.chi2.ppf(0.025, 0.6), rel=1e-6)  # tiny lower quantile
    assert all(math.isnan(v) for v in nees_band(0.0))


def test_coverage_of_gaussian_errors():
    rng = np.random.default_rng(4)
    n = 20000
    sigma = rng.uniform(0.1, 3.0, n)
    err = sigma * rng.standard_normal(n)
    assert normal_coverage(2.0) == pytest.approx(0.9545, abs=1e-4) and normal_coverage(1.0) == pytest.approx(0.6827, abs=1e-4)
    assert coverage(err, sigma, 2.0) == pytest.approx(0.9545, abs=0.005)
    assert coverage(err, sigma, 1.0) == pytest.approx(0.6827, abs=0.01)
    assert coverage(err, sigma / 2, 2.0) < 0.75  # σ reported half the truth: ±2σ covers only ±1 true σ (68 %)
    s = nees_stats((err / sigma) ** 2, 0.95, ess=effective_sample_size((err / sigma) ** 2))
    assert s["coverage"]["rate_2sigma"] == pytest.approx(coverage(err, sigma, 2.0))
    assert s["coverage"]["within_1sigma"] == int(np.sum(np.abs(err) <= sigma))
    s_half = nees_stats((2 * err / sigma) ** 2, 0.95, ess=effective_sample_size((2 * err / sigma) ** 2))
    assert s_half["coverage"]["rate_2sigma"] < 0.75 and s_half["consistent"] is False
    assert coverage(np.zeros(0), np.zeros(0), 2.0) is None
