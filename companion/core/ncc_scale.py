"""Scale change of matched patches between two frames (looming, docs/derivations/looming.md).

For each accepted match of two frames, :func:`estimate_scale` refines a scale + translation warp of
the patch: I_cur(p_cur + s·x + d) ≈ a·I_prev(p_prev + x) + b over x in a (2·scale_half+1)² grid, by
inverse-compositional Gauss–Newton on the zero-mean, unit-norm patches (gain/offset invariant like
eq. 13 of seed 004), vectorized over points.  With f̂ the normalized template, J = [∇f̂·x, ∇f̂]
projected off the mean and off f̂ (the directions the normalization removes), the step is
Δ = (JᵀJ)⁻¹ Jᵀ (ĝ − f̂) and the warp is composed with the inverse of the step:
s ← s/(1 + Δs), d ← d − s Δd/(1 + Δs).  σ_s is the scale entry of σ_r² (JᵀJ)⁻¹, σ_r² the residual
variance per pixel (both frames' noise and the model error), inflated by ``scale_sigma_factor`` for
the pixels' correlation (bilinear resampling, blur), plus ``scale_sigma_slope`` · |s − 1| in
quadrature (resampling a patch by s is not exactly the scene seen from closer: on band-limited
texture scaled by a known s the error grows ~0.06 |s − 1| beyond the residual σ).  The scale is NaN
where it cannot be measured: window not inside both frames, flat or edge patch (singular normal
matrix), no convergence, |s − 1| > ``max_scale_change`` or σ_s > ``max_scale_sigma``.

:func:`companion.core.ncc.match_ncc` calls it on its accepted matches (and re-exports it); the
compiled form is ``scale_fit`` in :mod:`companion.core.ncc_kernels`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from companion.core import jit
from companion.core import ncc_kernels as _kernels
from companion.core.harris import as_gray_u8
from companion.core.ncc_templates import _bilinear, _check_pts

if TYPE_CHECKING:  # only an annotation here; the matcher module imports this one
    from companion.core.ncc import NCCConfig


def estimate_scale(img_prev, img_cur, pts_prev, pts_cur, config: NCCConfig, scale0=None) -> tuple[np.ndarray, np.ndarray]:
    """Scale change s (N,) of the patches at ``pts_prev`` (in ``img_prev``) matched at ``pts_cur``
    (in ``img_cur``) and its σ (N,), NaN where not measurable (module docstring).  ``scale0`` (N,):
    starting scale (default 1)."""
    img_prev = as_gray_u8(img_prev, "img_prev")
    img_cur = as_gray_u8(img_cur, "img_cur")
    pts_prev = _check_pts("pts_prev", pts_prev)
    n = len(pts_prev)
    pts_cur = _check_pts("pts_cur", pts_cur, n)
    nan = np.full(n, np.nan)
    if n == 0:
        return nan, nan.copy()
    h = config.scale_half
    smax = 1.0 + config.max_scale_change
    H, W = img_prev.shape
    s = np.ones(n) if scale0 is None else np.clip(np.asarray(scale0, float).reshape(n), 1.0 / smax, smax)
    mp, mc = h + 2.0, h * smax + 2.0  # margins of the template (with its rim) and of the warped window

    def fits(p, m):
        return (p[:, 0] >= m) & (p[:, 0] <= W - 1 - m) & (p[:, 1] >= m) & (p[:, 1] <= H - 1 - m)

    ok = fits(pts_prev, mp) & fits(pts_cur, mc)
    f32 = np.float32
    if jit.ENABLED:
        return _kernels.scale_fit(img_prev, img_cur, pts_prev, pts_cur, s, ok, h,
                                  config.scale_iterations, smax, config.scale_sigma_factor, config.scale_sigma_slope)
    # template with a 1-px rim at the exact sub-pixel point, its gradients, normalization
    off = np.arange(-h - 1, h + 2, dtype=f32)
    Xt = pts_prev[:, 0, None, None].astype(f32) + off[None, None, :]
    Yt = pts_prev[:, 1, None, None].astype(f32) + off[None, :, None]
    T = _bilinear(img_prev.astype(f32), *np.broadcast_arrays(Xt, Yt))
    npx = (2 * h + 1) ** 2
    f = T[:, 1:-1, 1:-1].reshape(n, npx)
    gx = (T[:, 1:-1, 2:] - T[:, 1:-1, :-2]).reshape(n, npx) * f32(0.5)
    gy = (T[:, 2:, 1:-1] - T[:, :-2, 1:-1]).reshape(n, npx) * f32(0.5)
    f = f - f.mean(1, keepdims=True)
    nf = np.sqrt(_rowdot(f, f))
    ok &= nf > 1e-3 * np.sqrt(npx)
    nf = np.where(nf > 0, nf, f32(1.0))[:, None]
    f /= nf
    gx /= nf
    gy /= nf
    grid = off[1:-1]
    xx = np.broadcast_to(grid[None, :], (2 * h + 1, 2 * h + 1)).reshape(-1)
    yy = np.broadcast_to(grid[:, None], (2 * h + 1, 2 * h + 1)).reshape(-1)
    J = np.stack([gx * xx + gy * yy, gx, gy], 1)  # (n, 3, npx): ∂/∂(s, dx, dy)
    J -= J.mean(2, keepdims=True)
    J -= (J @ f[:, :, None]) * f[:, None, :]  # off f̂: the gain is free
    A = (J @ np.swapaxes(J, 1, 2)).astype(np.float64)
    # symmetric 3×3 inverse by cofactors (cheaper than np.linalg for small stacks)
    cof = np.empty_like(A)
    cof[:, 0, 0] = A[:, 1, 1] * A[:, 2, 2] - A[:, 1, 2] ** 2
    cof[:, 0, 1] = A[:, 0, 2] * A[:, 1, 2] - A[:, 0, 1] * A[:, 2, 2]
    cof[:, 0, 2] = A[:, 0, 1] * A[:, 1, 2] - A[:, 0, 2] * A[:, 1, 1]
    cof[:, 1, 1] = A[:, 0, 0] * A[:, 2, 2] - A[:, 0, 2] ** 2
    cof[:, 1, 2] = A[:, 0, 2] * A[:, 0, 1] - A[:, 0, 0] * A[:, 1, 2]
    cof[:, 2, 2] = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] ** 2
    cof[:, 1, 0], cof[:, 2, 0], cof[:, 2, 1] = cof[:, 0, 1], cof[:, 0, 2], cof[:, 1, 2]
    detA = A[:, 0, 0] * cof[:, 0, 0] + A[:, 0, 1] * cof[:, 0, 1] + A[:, 0, 2] * cof[:, 0, 2]
    tr = A[:, 0, 0] + A[:, 1, 1] + A[:, 2, 2]
    ok &= detA > 1e-9 * np.maximum(tr, 1e-30) ** 3
    A_inv = cof / np.where(ok, detA, 1.0)[:, None, None]
    AJ = (A_inv.astype(f32) @ J)  # (n, 3, npx): the Gauss–Newton step is AJ · r
    img_c = img_cur.astype(f32)
    d = np.zeros((n, 2))
    step_s = np.zeros(n)
    r = np.zeros((n, npx), f32)
    step_s = np.full(n, np.inf)

    def gauss_newton(k):
        """One step on rows ``k`` (index array or slice; updates s, d, step_s, r, ok in place)."""
        c = (pts_cur[k] + d[k]).astype(f32)
        sf = s[k].astype(f32)[:, None]
        g = _bilinear(img_c, c[:, 0, None] + sf * xx[None, :], c[:, 1, None] + sf * yy[None, :])
        g -= g.mean(1, keepdims=True)
        ng = np.sqrt(_rowdot(g, g))
        ok[k] &= ng > 1e-3 * np.sqrt(npx)
        r[k] = g / np.where(ng > 0, ng, f32(1.0))[:, None] - f[k]
        delta = (AJ[k] @ r[k][:, :, None])[:, :, 0].astype(np.float64)
        one = 1.0 + delta[:, 0]
        ok[k] &= one > 0.5
        one = np.where(one > 0.5, one, 1.0)
        step_s[k] = delta[:, 0]
        d[k] = d[k] - s[k][:, None] * delta[:, 1:] / one[:, None]
        s[k] = np.clip(s[k] / one, 1.0 / smax, smax)

    for _ in range(config.scale_iterations):
        gauss_newton(slice(None))  # every row (a slice: no copies)
    for _ in range(2):  # a poor start (a track's first fit, a sudden change): two more steps where not settled
        k = np.flatnonzero(ok & (np.abs(step_s) >= 0.002 * s))
        if len(k) == 0:
            break
        gauss_newton(k)
    ok &= np.abs(step_s) < 0.01 * s
    var_r = _rowdot(r, r).astype(np.float64) / max(npx - 5, 1)
    sigma = np.hypot(config.scale_sigma_factor * np.sqrt(np.maximum(var_r * A_inv[:, 0, 0], 0.0)) * s,
                     config.scale_sigma_slope * np.abs(s - 1.0))
    ok &= (np.abs(s - 1.0) <= config.max_scale_change) & (sigma <= config.max_scale_sigma) & np.isfinite(s) & np.isfinite(sigma)
    return np.where(ok, s, np.nan), np.where(ok, sigma, np.nan)


def _rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (N, K) arrays, (N,)."""
    return (a[:, None, :] @ b[:, :, None])[:, 0, 0]
