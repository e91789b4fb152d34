"""χ² quantiles for the NEES band of the reported σ (:func:`nees_band`), the effective sample size
of a correlated series (:func:`effective_sample_size`, :func:`pooled_n_eff`) and the coverage of
``estimate ± kσ`` (:func:`coverage`), all without SciPy at run time.
Definitions (``NEES of the reported σ``): :mod:`flightsim.score`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np


# ---------------------------------------------------------------------- χ² ---------------------
def _gamma_p(a: float, x: float) -> float:
    """Regularized lower incomplete gamma P(a, x): series below a + 1, Lentz continued fraction above."""
    if x <= 0:
        return 0.0
    log_pre = -x + a * math.log(x) - math.lgamma(a)
    if x < a + 1:
        term = total = 1.0 / a
        ap = a
        for _ in range(10000):
            ap += 1
            term *= x / ap
            total += term
            if abs(term) < abs(total) * 1e-15:
                break
        return min(1.0, total * math.exp(log_pre))
    tiny = 1e-300
    b_ = x + 1 - a
    c = 1 / tiny
    d = 1 / b_
    h = d
    for i in range(1, 10000):
        an = -i * (i - a)
        b_ += 2
        d = an * d + b_
        d = tiny if abs(d) < tiny else d
        c = b_ + an / c
        c = tiny if abs(c) < tiny else c
        d = 1 / d
        delta = d * c
        h *= delta
        if abs(delta - 1) < 1e-15:
            break
    return max(0.0, 1.0 - math.exp(log_pre) * h)


def chi2_quantile(p: float, dof: float) -> float:
    """χ² quantile: the χ² CDF P(dof/2, x/2) inverted by bisection (no SciPy at run time)."""
    if dof <= 0 or not 0 < p < 1:
        return math.nan
    lo, hi = 0.0, dof + 20.0 * math.sqrt(2.0 * dof) + 100.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _gamma_p(dof / 2.0, mid / 2.0) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-13 * hi:  # relative: the lower quantiles of few degrees of freedom are tiny
            break
    return 0.5 * (lo + hi)


def nees_band(n: float, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band for the mean of ``n`` independent χ²₁ samples: ``[χ²(n, α/2), χ²(n, 1 − α/2)] / n``.

    ``n`` need not be an integer: with an effective sample size ``n_eff`` (:func:`effective_sample_size`)
    in its place the band is that of a χ² with ``n_eff`` degrees of freedom scaled by ``1/n_eff`` — the
    distribution with the mean (1) and variance (2/n_eff) of the mean of the correlated samples.
    """
    if not n > 0 or not math.isfinite(n):
        return (math.nan, math.nan)
    lo = (1 - confidence) / 2
    return chi2_quantile(lo, n) / n, chi2_quantile(1 - lo, n) / n


# ---------------------------------------------------------------------- effective sample size ---
def stretch_labels(t: np.ndarray, gap_s: float) -> np.ndarray:
    """Contiguous stretches of a time series: a new stretch starts where a sample comes more than
    ``gap_s`` after the previous one (or before it: a time that goes back).  (n,) int labels 0, 1, …"""
    t = np.asarray(t, float)
    if t.size == 0:
        return np.zeros(0, np.int64)
    dt = np.diff(t)
    brk = ~((dt >= 0) & (dt <= gap_s))  # NaN times break too
    return np.concatenate([[0], np.cumsum(brk)]).astype(np.int64)


def _runs(labels: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of equal consecutive labels."""
    if labels.size == 0:
        return []
    cut = np.flatnonzero(np.diff(labels) != 0) + 1
    starts = np.concatenate([[0], cut])
    stops = np.concatenate([cut, [labels.size]])
    return list(zip(starts.tolist(), stops.tolist()))


def autocorrelation(x: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
    """Autocorrelation ρ_k, k = 0 … (longest stretch − 1), of ``x`` pooled over its stretches.

    Every stretch (a run of equal ``labels``; one stretch when None) contributes the products
    ``(x_i − x̄)(x_{i+k} − x̄)`` of its own pairs only — no pair straddles a gap — about the mean
    ``x̄`` of the whole series; the autocovariance at lag ``k`` is their mean over all such pairs
    (divided by the number of pairs, not by ``n``: with many short stretches the usual ``1/n``
    would shrink every lag by the share of samples without a partner), and ρ_k = c_k / c_0.
    The long lags, with few pairs, are noisy; :func:`effective_sample_size` stops before them.
    A constant series has ρ = [1, 0, …].
    """
    x = np.asarray(x, float)
    n = x.size
    if n == 0:
        return np.zeros(0)
    lab = np.zeros(n, np.int64) if labels is None else np.asarray(labels)
    d = x - x.mean()
    runs = _runs(lab)
    longest = max(b - a for a, b in runs)
    acov = np.zeros(longest)
    pairs = np.zeros(longest)
    for a, b in runs:
        m = b - a
        size = 1 << int(2 * m - 1).bit_length()  # zero-padded: no wrap-around
        f = np.fft.rfft(d[a:b], size)
        acov[:m] += np.fft.irfft(f * np.conj(f), size)[:m]
        pairs[:m] += np.arange(m, 0, -1)
    acov /= pairs
    c0 = acov[0]
    if not c0 > 1e-24 * float(np.mean(x * x)):  # no variance (to rounding): nothing to correlate
        out = np.zeros(longest)
        out[0] = 1.0
        return out
    return acov / c0


@dataclasses.dataclass(frozen=True)
class EffectiveSize:
    """:func:`effective_sample_size` of one series."""

    n: int  # samples
    n_eff: float  # effective number of independent samples for the mean (1 ≤ n_eff ≤ n when n ≥ 1)
    tau: float  # integrated autocorrelation time 1 + 2 Σ ρ_k (samples) over the lags kept
    lags: int  # the last lag kept by the initial monotone sequence
    stretches: int  # contiguous stretches (gaps break the series)


def _geyer_rho(rho: np.ndarray) -> np.ndarray:
    """ρ_0 … ρ_K kept by Geyer's initial monotone sequence estimator (Geyer 1992, *Practical
    Markov chain Monte Carlo*): the sums of adjacent pairs Γ_m = ρ_2m + ρ_2m+1 are taken while they
    are positive, each made no larger than the one before; both lags of a pair are scaled to its
    (possibly lowered) Γ_m.  The pairs make the rule work for series whose odd lags are negative."""
    kept = [1.0] if rho.size < 2 else []
    prev = math.inf
    for m in range(rho.size // 2):
        a, b = float(rho[2 * m]), float(rho[2 * m + 1])
        g = a + b
        if not g > 0:
            break
        if g > prev:  # monotone: a later pair may not add more than the one before
            a, b = a * prev / g, b * prev / g
            g = prev
        kept += [a, b]
        prev = g
    return np.asarray(kept if kept else [1.0])


def effective_sample_size(x: np.ndarray, t: np.ndarray | None = None, gap_s: float = math.inf) -> EffectiveSize:
    """Effective number of independent samples behind the mean of the series ``x`` (stamped ``t``).

    The series is cut into stretches where ``t`` jumps by more than ``gap_s``
    (:func:`stretch_labels`); the autocorrelation ρ_k is estimated over all stretches together
    (:func:`autocorrelation`) and truncated by Geyer's initial monotone sequence (:func:`_geyer_rho`,
    the sum stops before the first lag pair whose ρ sum is not positive).  A stretch of ``m``
    samples then has the variance of its sum ``m·v·(1 + 2 Σ_{k<m} (1 − k/m) ρ_k)`` (``v`` the
    variance of one sample), i.e. ``n_eff,s = m / (1 + 2 Σ_{k<m} (1 − k/m) ρ_k)`` — for a long
    stretch ``m / τ`` with ``τ = 1 + 2 Σ ρ_k`` — held within ``[1, m]`` (never more information than
    independent samples).  Stretches are independent, so the mean of all ``n`` samples has the
    variance of the mean of :func:`pooled_n_eff` independent samples.
    """
    x = np.asarray(x, float)
    n = int(x.size)
    if n == 0:
        return EffectiveSize(0, 0.0, math.nan, 0, 0)
    lab = np.zeros(n, np.int64) if t is None else stretch_labels(t, gap_s)
    rho = _geyer_rho(autocorrelation(x, lab))
    sizes, n_effs = [], []
    for a, b in _runs(lab):
        m = b - a
        k = np.arange(1, min(rho.size, m))
        tau_m = 1.0 + 2.0 * float(np.sum((1.0 - k / m) * rho[k]))
        sizes.append(m)
        n_effs.append(min(float(m), max(1.0, m / tau_m)) if tau_m > 0 else float(m))
    return EffectiveSize(n, pooled_n_eff(sizes, n_effs), 1.0 + 2.0 * float(np.sum(rho[1:])), int(rho.size - 1), len(sizes))


def pooled_n_eff(sizes: Sequence[float], n_effs: Sequence[float]) -> float:
    """Effective size of the mean of independent groups pooled sample by sample: the group of ``m``
    samples (``n_eff`` effective) adds ``m² / n_eff`` to ``n² · var(mean) / v``, so
    ``n_eff = n² / Σ (m² / n_eff)``.  This is the sum of the groups' ``n_eff`` when they share one
    correlation time (``m / n_eff`` alike) and less otherwise (a long, strongly correlated group
    dominates the pooled mean)."""
    pairs = [(float(m), float(e)) for m, e in zip(sizes, n_effs) if m and m > 0 and e and e > 0]
    if not pairs:
        return 0.0
    n = sum(m for m, _ in pairs)
    return n * n / sum(m * m / e for m, e in pairs)


def coverage(error: np.ndarray, sigma: np.ndarray, k: float) -> float | None:
    """Share of the samples with ``|error| ≤ k·σ`` (None when there are none)."""
    e, s = np.asarray(error, float), np.asarray(sigma, float)
    return None if e.size == 0 else float(np.mean(np.abs(e) <= k * s))


def normal_coverage(k: float) -> float:
    """``P(|z| ≤ k)`` of a standard normal ``z``: what ``estimate ± kσ`` covers when σ is right."""
    return math.erf(k / math.sqrt(2.0))
