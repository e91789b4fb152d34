"""bench/looming_truth.py: the statistics it reports, on synthetic scale errors of known structure,
and one short rendered flight whose scales it checks against the truth."""

import numpy as np
import pytest

from bench import looming_truth as lt


def synthetic(n_tracks=400, length=40, sigma=0.004, bias_sd=0.0, ar=0.0, sigma_used=None, seed=0):
    """Scale errors of ``n_tracks`` tracks of ``length`` frames: a per-track constant (σ ``bias_sd``)
    plus AR(1) noise of marginal σ ``sigma`` and lag-1 correlation ``ar``."""
    g = np.random.default_rng(seed)
    rows = {k: [] for k in ("t", "track", "k", "s", "sigma", "s_true", "depth", "ground")}
    for i in range(n_tracks):
        w = np.empty(length)
        w[0] = g.normal(0, sigma)
        for k in range(1, length):
            w[k] = ar * w[k - 1] + np.sqrt(1 - ar**2) * g.normal(0, sigma)
        e = w + g.normal(0, bias_sd)
        k0 = int(g.integers(0, 100))
        s_true = 1.0 + g.uniform(0.001, 0.01, length)
        rows["t"].append((k0 + np.arange(length)) / 30.0)
        rows["track"].append(np.full(length, i))
        rows["k"].append(k0 + np.arange(length))
        rows["s"].append(s_true + e)
        rows["sigma"].append(np.full(length, sigma if sigma_used is None else sigma_used))
        rows["s_true"].append(s_true)
        rows["depth"].append(np.full(length, 15.0))
        rows["ground"].append(np.zeros(length, bool))
    return {k: np.concatenate(v) for k, v in rows.items()} | {"floor": 0.0}


def test_independent_errors_with_an_honest_sigma_read_as_such():
    s = lt.summarize(synthetic())["obstacles"]
    assert s["sd_z"] == pytest.approx(1.0, abs=0.03)
    assert all(abs(c) < 0.05 for c in s["corr"].values())
    assert s["sd_track_means"] == pytest.approx(s["sd_track_means_if_white"], rel=0.12)


def test_an_understated_sigma_a_per_track_bias_and_correlation_are_found():
    s = lt.summarize(synthetic(sigma_used=0.002))["obstacles"]
    assert s["sd_z"] == pytest.approx(2.0, abs=0.06)  # the σ used is half the real one
    s = lt.summarize(synthetic(bias_sd=0.004))["obstacles"]
    # a constant per track: every lag correlates by bias² / (bias² + σ²) = 0.5, and the track means spread by ~bias
    for c in s["corr"].values():
        assert c == pytest.approx(0.5, abs=0.08)
    assert s["sd_track_means"] == pytest.approx(np.hypot(0.004, 0.004 / np.sqrt(40)), rel=0.1)
    assert s["sd_track_means"] > 3 * s["sd_track_means_if_white"]
    s = lt.summarize(synthetic(ar=0.6))["obstacles"]
    assert s["corr"]["1"] == pytest.approx(0.6, abs=0.05) and s["corr"]["3"] == pytest.approx(0.6**3, abs=0.05)


def test_a_short_rendered_flight_measures_scales_against_the_truth():
    """The quad flying at the wall: scales were measured, their truth found by ray casting (the
    true change is a growth: the vehicle approaches), and the error's spread is of the matcher's order."""
    d = lt.fly_and_track(lt.ROOT / "configs" / "scenarios" / "quad_approach.toml", seed=1, max_frames=45)
    assert d["s"].size > 200 and np.all(np.isfinite(d["s_true"])) and np.all(d["depth"] > 0)
    s = lt.summarize(d)
    assert s["obstacles"]["n"] > 100
    assert 0.0 < s["obstacles"]["true_s_minus_1"] < 0.02  # approaching at ~4 m/s, 30 frames/s, tens of metres out
    assert 0.5 < s["obstacles"]["sd_z"] < 4.0
    table = lt.markdown({"scenarios": [{"scenario": "quad_approach", "seed": 1, **s}]})
    assert "| quad_approach (seed 1) | obstacles |" in table
