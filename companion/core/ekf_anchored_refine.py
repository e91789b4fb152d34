"""Batch refinement of anchored inverse-depth landmarks (docs/derivations/ekf_anchored.md, § Batch refinement).

The iterated EKF linearizes each measurement once, at the estimate of its moment, and folds it into
x and P for good.  Early on that estimate can be far off (a range three times too near, a ρ seeded by a
noisy triangulation), and those linearizations stay in the landmark's P and mean (the seed-004 4 px
NEES excess, docs/BENCHMARKS.md "Where the excess at 4 px sits").  :func:`refine` recomputes a
landmark from its whole accepted history (:class:`companion.core.obs_history.ObservationHistory`) as the
maximum a posteriori estimate of the static state x = (θ, φ, ρ, [b]):

    J(x) = (x − x_p)ᵀ P_p⁻¹ (x − x_p) + Σ_k r_kᵀ W_k r_k

with the prior (x_p, P_p) = the anchor pixel's (θ, φ), the wide inverse-depth prior that includes
ρ = 0 (not the triangulated seed: its pixels are in the history, and counting them twice is what the
EKF's ×3 inflation only approximates) and the gyro bias prior; r_k the pixel residuals z_k − h(x)
(W_k = R⁻¹ of the EKF's measurement model, evaluated once at the filter's estimate: R depends on ρ
through the white position term) and the looming residuals s_k − h_s(x) (W = 1/σ_s²).
Gauss–Newton from the filter's own estimate, every step scored by J, the best kept; the result replaces
x and P = (P_p⁻¹ + Σ H_kᵀ W_k H_k)⁻¹ at the optimum only where it lowered J and every residual's point
lies in front of its camera.  All landmarks of a call are solved together: arrays over the flattened
slots (landmark, frame), sums per landmark, no loop per landmark.

Static states only: the position-error states δ have a process (they are a different random variable at
each frame), so a bank that carries them is not refined (:attr:`AnchoredEKFConfig.refine`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from companion.core import ekf_anchored_kernels as _kernels
from companion.core import jit
from companion.core.ekf_anchored_model import _looming_args, _looming_predict, _predict, _ray_map


@dataclasses.dataclass
class RefineResult:
    """Per landmark (M,): refined state x (M,n) and P (M,n,n) (the input's where not ``improved``),
    ``improved`` (the refinement replaced them), the cost J at the filter's estimate and at the result."""

    x: np.ndarray
    P: np.ndarray
    improved: np.ndarray
    cost_before: np.ndarray
    cost_after: np.ndarray


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _sum_by(owner: np.ndarray, values: np.ndarray, m: int) -> np.ndarray:
    """Sum of ``values`` (L, ...) per owner index (L,) into (m, ...)."""
    out = np.zeros((m,) + values.shape[1:])
    np.add.at(out, owner, values)
    return out


def _evaluate_kernel(x, xp, Ip, RA, pA, tA, h, W, drift: bool, i_pos: int):
    """:func:`_evaluate` by the compiled kernel (:func:`ekf_anchored_kernels.refine_evaluate`), one loop over
    landmarks and their slots."""
    m, n = x.shape
    cost, info, grad, front = np.zeros(m), np.zeros((m, n, n)), np.zeros((m, n)), np.zeros(m, bool)
    c = np.ascontiguousarray
    _kernels.refine_evaluate(c(x, float), c(xp, float), c(Ip, float), c(RA, float), c(pA, float), c(tA, float),
                             c(h["starts"], np.int64), c(h["counts"], np.int64), c(h["t"], float), c(h["R"], float), c(h["C"], float),
                             c(h["z"], float), c(W, float), c(h["s"], float), c(h["s_var"], float), c(h["prev"], np.int64),
                             bool(drift), int(i_pos), cost, info, grad, front)
    return cost, info, grad, front


def _fixed_parts(RA, pA, tA, h, drift: bool) -> dict:
    """What :func:`_evaluate` needs that does not depend on x, computed once per refinement: the slots with a
    pixel and their ray maps, C_A − C, R_cᵀ and drift integrals; the slots with a scale and the looming model's
    fixed arguments (:func:`_looming_args`)."""
    owner = h["owner"]
    pix = np.flatnonzero(np.isfinite(h["z"][:, 0]))
    o = owner[pix]
    D = (0.5 * (h["t"][pix] - tA[o]))[:, None, None] * (RA[o] + h["R"][pix]) if drift else None
    out = {"pix": pix, "pix_owner": o, "pix_args": (_ray_map(RA[o]), pA[o] - h["C"][pix], np.swapaxes(h["R"][pix], 1, 2), D)}
    loom = np.flatnonzero(np.isfinite(h["s"]) & (h["prev"] >= 0))
    o, q = owner[loom], h["prev"][loom]
    out.update(loom=loom, loom_owner=o, loom_args=_looming_args(RA[o], pA[o], tA[o], h["R"][q], h["C"][q], h["t"][q],
                                                                h["R"][loom], h["C"][loom], h["t"][loom], drift))
    return out


def _evaluate(x, xp, Ip, RA, pA, tA, h, W, drift: bool, i_pos: int, fixed: dict | None = None):
    """At states x (M,n): cost J (M,), information I (M,n,n), gradient g = −½∇J (M,n) and whether every
    used slot's point is in front of its camera (M,).  ``W`` (L,2): the pixel weights (NaN in slots without a
    pixel), held fixed over the iterations (R depends on ρ through the white position term: weights that
    moved with x would make J a different function at every step).  ``fixed``: :func:`_fixed_parts` of these
    landmarks (computed here when None)."""
    fixed = _fixed_parts(RA, pA, tA, h, drift) if fixed is None else fixed
    m, n = x.shape
    dx = x - xp
    dx[:, 0] = _wrap(dx[:, 0])
    Ipdx = np.einsum("mij,mj->mi", Ip, dx)
    cost = np.einsum("mi,mi->m", dx, Ipdx)
    info = Ip.copy()
    grad = -Ipdx
    front = np.ones(m, bool)
    pix, o = fixed["pix"], fixed["pix_owner"]
    if len(pix):
        hc, zhat, H = _predict(x[o], *fixed["pix_args"], i_pos)
        W_pix = W[pix]  # (L,2): R is diagonal
        r = h["z"][pix] - zhat
        info += _sum_by(o, np.einsum("lki,lk,lkj->lij", H, W_pix, H), m)
        grad += _sum_by(o, np.einsum("lki,lk,lk->li", H, W_pix, r), m)
        cost += _sum_by(o, np.einsum("lk,lk,lk->l", r, W_pix, r), m)
        front &= _sum_by(o, (hc[:, 2] <= 1e-9).astype(float), m) == 0
    loom, o = fixed["loom"], fixed["loom_owner"]
    if len(loom):
        hzp, hzn, hs, Hs = _looming_predict(x[o], *fixed["loom_args"], i_pos)
        w = 1.0 / h["s_var"][loom]
        r = h["s"][loom] - hs
        info += _sum_by(o, w[:, None, None] * Hs[:, :, None] * Hs[:, None, :], m)
        grad += _sum_by(o, (w * r)[:, None] * Hs, m)
        cost += _sum_by(o, w * r * r, m)
        front &= _sum_by(o, ((hzp <= 1e-9) | (hzn <= 1e-9)).astype(float), m) == 0
    return cost, info, grad, front


def _solve_or_nan(A: np.ndarray, b: np.ndarray | None) -> np.ndarray:
    """A⁻¹ b (M,n) for stacked A (M,n,n), or A⁻¹ when ``b`` is None; NaN for a landmark whose A is singular
    (A = P_p⁻¹ + Σ HᵀWH is positive definite by construction, but input NaN must not raise in flight)."""
    with np.errstate(all="ignore"):
        try:
            return np.linalg.inv(A) if b is None else np.linalg.solve(A, b[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            out = np.full(A.shape if b is None else b.shape, np.nan)
            for i in range(len(A)):  # rare: find the singular ones one by one
                try:
                    out[i] = np.linalg.inv(A[i]) if b is None else np.linalg.solve(A[i], b[i])
                except np.linalg.LinAlgError:
                    pass
            return out


def refine(x0, P0, xp, Pp, RA, pA, tA, history: dict, pixel_variance, drift: bool, i_pos: int,
           iterations: int) -> RefineResult:
    """Batch MAP of M landmarks (module docstring).

    ``x0`` (M,n), ``P0`` (M,n,n): the filters' estimates (the Gauss–Newton start, and the answer where
    the refinement does not improve); ``xp``, ``Pp``: the priors; ``RA`` (M,3,3), ``pA`` (M,3), ``tA`` (M,):
    the anchors; ``history``: :meth:`ObservationHistory.gather` of the same landmarks in the same order;
    ``pixel_variance``: states (L,n) → the pixel measurement variance (L,2) of the filter
    (:meth:`AnchoredInverseDepthEKF.measurement_variance`); ``iterations`` Gauss–Newton steps."""
    x0 = np.asarray(x0, float)
    m = len(x0)
    Ip = np.linalg.inv(Pp)
    x = x0.copy()
    best_x, best_cost = x0.copy(), np.full(m, np.inf)
    best_info = np.zeros_like(P0)
    cost_before = None
    pix = np.isfinite(history["z"][:, 0])
    W = np.full(history["z"].shape, np.nan)
    W[pix] = 1.0 / pixel_variance(x0[history["owner"][pix]])  # R at the filter's estimate, as the EKF weighs
    if jit.ENABLED:
        evaluate = _evaluate_kernel
    else:  # the numpy reference: its x-independent parts once, not at every step
        fixed = _fixed_parts(RA, pA, tA, history, drift)

        def evaluate(*args):
            return _evaluate(*args, fixed=fixed)
    for it in range(iterations + 1):
        cost, info, grad, front = evaluate(x, xp, Ip, RA, pA, tA, history, W, drift, i_pos)
        if cost_before is None:
            cost_before = np.where(front, cost, np.inf)
        better = front & np.isfinite(cost) & (cost < best_cost)
        best_x[better], best_cost[better], best_info[better] = x[better], cost[better], info[better]
        if it == iterations:
            break
        step = _solve_or_nan(info, grad)
        x = np.where(np.isfinite(step).all(1)[:, None], x + step, x)
    # improved: a step lowered J (the filter's own estimate, if best, keeps its x and P)
    improved = np.isfinite(best_cost) & (best_cost < cost_before) & np.isfinite(best_x).all(1)
    P = P0.copy()
    x_out = x0.copy()
    if improved.any():
        Pi = _solve_or_nan(best_info[improved], None)
        Pi = 0.5 * (Pi + np.swapaxes(Pi, 1, 2))
        ok = np.isfinite(Pi).all((1, 2)) & (np.linalg.eigvalsh(Pi)[:, 0] > 0)
        sel = np.flatnonzero(improved)
        improved[sel[~ok]] = False
        sel = sel[ok]
        x_out[sel], P[sel] = best_x[sel], Pi[ok]
    return RefineResult(x_out, P, improved, cost_before, np.where(improved, best_cost, cost_before))
