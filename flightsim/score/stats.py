"""χ² quantiles for the NEES band of the reported σ (:func:`nees_band`), without SciPy at run time.
Definitions (``NEES of the reported σ``): :mod:`flightsim.score`.
"""

from __future__ import annotations

import math


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
        if hi - lo <= 1e-12 * max(1.0, hi):
            break
    return 0.5 * (lo + hi)


def nees_band(n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band for the mean of ``n`` χ²₁ samples."""
    if n <= 0:
        return (math.nan, math.nan)
    lo = (1 - confidence) / 2
    return chi2_quantile(lo, n) / n, chi2_quantile(1 - lo, n) / n
