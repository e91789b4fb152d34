"""Per-landmark inverse-depth EKF driven by the measured camera motion (docs/derivations/ekf_landmark.md, seed 000).

Model
-----
Each landmark is its own 3-state filter.  In the current camera frame (OpenCV: x right, y down,
z forward) a landmark at P = (X, Y, Z) is described by

    x = (x̄, ȳ, ξ),    x̄ = X/Z,  ȳ = Y/Z  (normalized image coordinates),  ξ = 1/Z  (inverse depth).

The inputs are q = (V, ω): the camera's linear velocity and angular rate in its own frame, taken
from telemetry.  A static point then obeys dP/dt = −V − ω × P (seed 000 eq. 5/7).  With
P = (x̄, ȳ, 1)/ξ the quotient rule gives dx̄/dt = ξ (Ẋ − x̄ Ż), dȳ/dt = ξ (Ẏ − ȳ Ż), dξ/dt = −ξ² Ż,
and substituting Ẋ, Ẏ, Ż:

    f₁ = dx̄/dt = ξ(−Vx + x̄ Vz) + x̄ ȳ ωx − (1 + x̄²) ωy + ȳ ωz
    f₂ = dȳ/dt = ξ(−Vy + ȳ Vz) + (1 + ȳ²) ωx − x̄ ȳ ωy − x̄ ωz
    f₃ = dξ/dt = ξ² Vz + ξ (ȳ ωx − x̄ ωy)

With only Vz and ωy non-zero and pixel coordinates x = f x̄ + cx, y = f ȳ + cy this is seed 000
eq. 13 (the test suite checks it term by term).

Analytic Jacobians of the continuous model
------------------------------------------
Differentiating f term by term, F = ∂f/∂x (3×3):

    ∂f₁/∂x̄ = ξ Vz + ȳ ωx − 2 x̄ ωy     ∂f₁/∂ȳ = x̄ ωx + ωz              ∂f₁/∂ξ = −Vx + x̄ Vz
    ∂f₂/∂x̄ = −ȳ ωy − ωz               ∂f₂/∂ȳ = ξ Vz + 2 ȳ ωx − x̄ ωy   ∂f₂/∂ξ = −Vy + ȳ Vz
    ∂f₃/∂x̄ = −ξ ωy                    ∂f₃/∂ȳ = ξ ωx                    ∂f₃/∂ξ = 2 ξ Vz + ȳ ωx − x̄ ωy

and B = ∂f/∂q (3×6), columns (Vx, Vy, Vz, ωx, ωy, ωz):

    ∂f₁/∂q = (−ξ,  0,  x̄ ξ,  x̄ ȳ,      −(1 + x̄²),  ȳ)
    ∂f₂/∂q = ( 0, −ξ,  ȳ ξ,  1 + ȳ²,    −x̄ ȳ,      −x̄)
    ∂f₃/∂q = ( 0,  0,  ξ²,   ξ ȳ,       −ξ x̄,       0)

Discretization (RK4, seed 000 eq. 21–22) and its Jacobians
----------------------------------------------------------
With step h and q held constant over the step:

    k₁ = f(x),  k₂ = f(x + h/2 k₁),  k₃ = f(x + h/2 k₂),  k₄ = f(x + h k₃)
    Ψ(x, q) = x + h/6 (k₁ + 2k₂ + 2k₃ + k₄)

Write u = (x, q) (9 variables), E = [I₃ 0] = ∂x/∂u, the stage points xᵢ (x₁ = x, x₂ = x + h/2 k₁,
x₃ = x + h/2 k₂, x₄ = x + h k₃) and Dᵢ = ∂kᵢ/∂u (3×9).  By the chain rule, since kᵢ = f(xᵢ, q)
and ∂xᵢ/∂u = E + cᵢ h Dᵢ₋₁ (c₂ = c₃ = ½, c₄ = 1):

    Dᵢ = F(xᵢ) (E + cᵢ h Dᵢ₋₁) + [0  B(xᵢ)] = [F(xᵢ)  B(xᵢ)] + cᵢ h F(xᵢ) Dᵢ₋₁,   D₁ = [F(x)  B(x)]

and ∂Ψ/∂u = E + h/6 (D₁ + 2D₂ + 2D₃ + D₄) = [A  G]:  A = ∂Ψ/∂x (3×3), G = ∂Ψ/∂q (3×6).  These are
the exact derivatives of the discrete map (not the Euler approximation I + F h of seed 000's
appendix, which they reduce to at first order in h).  A step longer than ``max_step`` is split into
n equal RK4 sub-steps with the same q; then A = Aₙ⋯A₁ and G = Σₖ (Aₙ⋯Aₖ₊₁) Gₖ.

Process noise and its units
---------------------------
The measured input is q̃ = q + Δq with Δq white, power spectral density
Q = diag(σ_v², σ_v², σ_v², σ_ω², σ_ω², σ_ω²) (σ_v in m/s/√Hz, σ_ω in rad/s/√Hz).  The filter uses one
q per step, i.e. the input averaged over the step; the average of white noise of PSD σ² over Δt has
variance σ²/Δt, so the discrete input covariance is Q/Δt and (seed 000 eq. 24)

    P⁻ = A P Aᵀ + G (Q/Δt) Gᵀ.

Units: σ_v² [(m/s)²·s] / Δt [s] = (m/s)², the variance of the step-mean velocity; G's velocity
columns are [state/(m/s)] (≈ −ξ Δt for x̄), so G (Q/Δt) Gᵀ is in state² units.  For small Δt,
G ≈ B Δt and G (Q/Δt) Gᵀ ≈ B Q Bᵀ Δt: the covariance grows linearly in time at the continuous-time
rate, independent of the frame rate.  (The sign of Δq does not matter: it cancels in G Q Gᵀ.)

Update
------
z = (x̄, ȳ) measured (undistorted normalized coordinates), H = [I₂ 0],
R = diag((σ_px/fx)², (σ_px/fy)²), S = H P Hᵀ + R, K = P Hᵀ S⁻¹, Joseph form
P⁺ = (I − K H) P (I − K H)ᵀ + K R Kᵀ.  The 2-dof innovation is gated with NIS = yᵀ S⁻¹ y ≤ −2 ln(1 − p)
(the χ²₂ quantile in closed form: its CDF is 1 − e^(−x/2)).  A rejected measurement leaves x and P
unchanged and counts a consecutive reject; ``max_consecutive_rejects`` of them flag the landmark
*diverged* (sticky; it keeps filtering, but is reported invalid until the caller removes it).

Validity
--------
A landmark is flagged *invalid* (sticky, and then frozen: no more prediction or update, the caller
should remove it) when its state leaves the model's domain instead of being clipped:
ξ < −k σ_ξ (``negative_inv_depth_sigmas`` = k, "negative depth beyond doubt"), ξ > ``inv_depth_max``
(closer than 1/inv_depth_max: the point is passing the camera), |x̄| or |ȳ| > ``max_normalized_coord``
(the ray is almost in the image plane: the point is passing beside/behind the camera), or a
non-finite prediction (the previous finite state is kept).  Far points with 0 ≤ ξ < inv_depth_min
(or slightly negative, within kσ) keep filtering but are reported with ``valid = False`` and a
finite placeholder range, since no finite range can be stated for them.

A ``predict`` step longer than ``max_dt`` is refused (InputError): over a telemetry gap the
constant-input model does not hold and the landmarks should be re-initialised.

Consistency (measured, see tests/test_ekf_landmark.py)
------------------------------------------------------
Flying at 10 m/s past points at 40–120 m with the default input noise, 1 px at f = 500 and a 30 %
prior on ξ, the average NEES is ≈ 2.3–3.5 (χ²₃ mean 3) and the median range error 1.5–2 % after
2.5 s.  The EKF becomes over-confident (NEES ≈ 5 after 2 s, ξ biased low by ≈ 0.8σ) when the
per-frame velocity noise is large relative to the speed (e.g. 4 m/s with σ_v = 0.1 m/s/√Hz at
30 Hz, i.e. 0.55 m/s per frame) *and* the prior on ξ is wide (≥ 10 %): the cause is the
linearization of A at the wrong ξ̂ (evaluating A at the true state restores NEES ≈ 3; a
second-order mean correction does not help).  Tighter priors (longer-baseline triangulation) or
better velocity inputs avoid it.

Everything is batched over landmarks ((N, 3), (N, 3, 3) arrays, einsum/batched matmul and
closed-form 2×2 inverses); there is no Python loop per landmark.
"""

from __future__ import annotations

import math

import numpy as np

from companion.config import require_finite
from companion.core.idbank import lookup, rows_or_raise
from companion.errors import InputError

from companion.core.ekf_landmark_model import (  # noqa: F401  (re-exported: the public names of this module)
    OK,
    FAR,
    DIVERGED,
    INVALID,
    ACCEPTED,
    GATED,
    FROZEN,
    LandmarkEKFConfig,
    UpdateResult,
    LandmarkEstimates,
    _model,
    _rk4,
    _rk4_multi,
    _array,
    _states,
    _inputs,
    _step,
    _ids,
    continuous_dynamics,
    jacobian_x,
    jacobian_q,
    rk4_step,
    state_from_points,
    points_from_state,
)


# -- the bank -----------------------------------------------------------------------------------
class LandmarkEKFBank:
    """N independent 3-state filters (docs/derivations/ekf_landmark.md), addressed by int64 landmark id (kept sorted).

    Arrays: ``ids`` (N,), ``x`` (N,3), ``P`` (N,3,3), ``n_updates`` (accepted), ``n_rejects``
    (consecutive gated), ``diverged`` and ``invalid`` (sticky flags).
    """

    def __init__(self, config: LandmarkEKFConfig, fx: float, fy: float):
        require_finite("fx", fx, positive=True)
        require_finite("fy", fy, positive=True)
        self.config = config
        #: measurement noise R = diag(r) in normalized coordinates
        self.r = np.array([(config.sigma_px / fx) ** 2, (config.sigma_px / fy) ** 2])
        #: input PSD Q = diag(σ_v² ×3, σ_ω² ×3)
        self.Q_psd = np.concatenate([np.broadcast_to(np.asarray(config.sigma_v, float), (3,)),
                                     np.broadcast_to(np.asarray(config.sigma_w, float), (3,))]) ** 2
        self.ids = np.zeros(0, np.int64)
        self.x = np.zeros((0, 3))
        self.P = np.zeros((0, 3, 3))
        self.n_updates = np.zeros(0, np.int64)
        self.n_rejects = np.zeros(0, np.int64)
        self.diverged = np.zeros(0, bool)
        self.invalid = np.zeros(0, bool)
        self.nis_avg = np.zeros(0)  # mean NIS over the last ~nis_window measurements (consistency with a static point)
        self.nis_count = np.zeros(0, np.int64)  # measurements in nis_avg

    _ARRAYS = ("ids", "x", "P", "n_updates", "n_rejects", "diverged", "invalid", "nis_avg", "nis_count")

    def __len__(self) -> int:
        return len(self.ids)

    def contains(self, ids) -> np.ndarray:
        """(M,) bool: which ids are in the bank."""
        return lookup(self.ids, ids)[0]

    def index_of(self, ids) -> np.ndarray:
        """Row of each id in the bank's arrays; InputError naming the ids that are not in the bank."""
        return self._rows(_ids("index_of: ids", ids), "index_of")

    def _rows(self, ids: np.ndarray, what: str) -> np.ndarray:
        return rows_or_raise(self.ids, ids, what)

    # -- bookkeeping ----------------------------------------------------------------------------
    def add(self, ids, xy, inv_depth, inv_depth_sigma) -> None:
        """Start filters at measured normalized coordinates ``xy`` (M,2) with a prior on ξ.

        Initial P = diag((σ_px/fx)², (σ_px/fy)², inv_depth_sigma²).  ``inv_depth`` (M,) must lie in
        [0, inv_depth_max] (e.g. from a coarse triangulation, seed 000 / docs/derivations/ekf_landmark.md); ids new, unique.
        """
        ids = _ids("add: ids", ids)
        m = len(ids)
        xy = _array("add: xy", xy, (m, 2))
        rho = _array("add: inv_depth", inv_depth, (m,))
        srho = _array("add: inv_depth_sigma", inv_depth_sigma, (m,))
        if m == 0:
            return
        if np.any(self.contains(ids)):
            raise InputError(f"add: ids already in the bank: {ids[self.contains(ids)][:10].tolist()}")
        if np.any(srho <= 0):
            raise InputError("add: inv_depth_sigma must be > 0")
        cfg = self.config
        if np.any((rho < 0) | (rho > cfg.inv_depth_max)):
            raise InputError(f"add: inv_depth must be in [0, inv_depth_max={cfg.inv_depth_max}]")
        if np.any(np.abs(xy) > cfg.max_normalized_coord):
            raise InputError(f"add: |xy| must be <= max_normalized_coord={cfg.max_normalized_coord}")
        P0 = np.zeros((m, 3, 3))
        P0[:, 0, 0] = self.r[0]
        P0[:, 1, 1] = self.r[1]
        P0[:, 2, 2] = srho**2
        new = {
            "ids": ids,
            "x": np.column_stack([xy, rho]),
            "P": P0,
            "n_updates": np.zeros(m, np.int64),
            "n_rejects": np.zeros(m, np.int64),
            "diverged": np.zeros(m, bool),
            "invalid": np.zeros(m, bool),
            "nis_avg": np.zeros(m),
            "nis_count": np.zeros(m, np.int64),
        }
        order = np.argsort(np.concatenate([self.ids, ids]), kind="stable")
        for name in self._ARRAYS:
            setattr(self, name, np.concatenate([getattr(self, name), new[name]])[order])

    def remove(self, ids) -> None:
        """Drop the listed landmarks (InputError on unknown ids)."""
        ids = _ids("remove: ids", ids)
        keep = np.ones(len(self.ids), bool)
        keep[self._rows(ids, "remove")] = False
        for name in self._ARRAYS:
            setattr(self, name, getattr(self, name)[keep])

    # -- filter ---------------------------------------------------------------------------------
    def predict(self, v_cam, w_cam, dt) -> None:
        """Propagate every non-frozen landmark over ``dt`` with measured camera V (3,) and ω (3,).

        x⁻ = Ψ(x, q̃), P⁻ = A P Aᵀ + G (Q/Δt) Gᵀ (module docstring).  Landmarks whose prediction
        leaves the model's domain are flagged invalid and frozen.
        """
        v = _array("v_cam", v_cam, (3,))
        w = _array("w_cam", w_cam, (3,))
        dt = _step(dt)
        if dt > self.config.max_dt:
            raise InputError(f"dt = {dt} s exceeds max_dt = {self.config.max_dt} s: re-initialise the landmarks after a gap")
        if len(self.ids) == 0:
            return
        active = ~self.invalid
        all_active = bool(np.all(active))
        rows = None if all_active else np.flatnonzero(active)
        x = self.x if all_active else self.x[rows]
        P = self.P if all_active else self.P[rows]
        if len(x) == 0:
            return
        q = (v[0], v[1], v[2], w[0], w[1], w[2])
        n_sub = max(1, math.ceil(dt / self.config.max_step - 1e-9))
        with np.errstate(over="ignore", invalid="ignore"):
            x_new, T = _rk4_multi(x, q, dt, n_sub)
            A, G = T[:, :, :3], T[:, :, 3:]
            GQ = G * (self.Q_psd / dt)
            P_new = A @ P @ np.swapaxes(A, 1, 2) + GQ @ np.swapaxes(G, 1, 2)
        P_new = 0.5 * (P_new + np.swapaxes(P_new, 1, 2))
        finite = np.all(np.isfinite(x_new), 1) & np.all(np.isfinite(P_new), (1, 2))
        if not np.all(finite):
            x_new[~finite] = x[~finite]
            P_new[~finite] = P[~finite]
        bad = ~finite | self._out_of_domain(x_new, P_new)
        if all_active:
            self.x, self.P = x_new, P_new
            self.invalid = bad
        else:
            self.x[rows] = x_new
            self.P[rows] = P_new
            self.invalid[rows] = bad

    def _out_of_domain(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        cfg = self.config
        xi = x[:, 2]
        s_xi = np.sqrt(np.maximum(P[:, 2, 2], 0.0))
        return (
            (xi < -cfg.negative_inv_depth_sigmas * s_xi)
            | (xi > cfg.inv_depth_max)
            | (np.abs(x[:, 0]) > cfg.max_normalized_coord)
            | (np.abs(x[:, 1]) > cfg.max_normalized_coord)
            | ~(P[:, 0, 0] > 0) | ~(P[:, 1, 1] > 0) | ~(P[:, 2, 2] > 0)
        )

    def update(self, ids, xy) -> UpdateResult:
        """Fuse one measured normalized position ``xy`` (M,2) per listed landmark ``ids`` (M,).

        H = [I₂ 0], Joseph form, χ² gate per landmark; rejected measurements leave x and P unchanged.
        """
        ids = _ids("update: ids", ids)
        m = len(ids)
        z = _array("update: xy", xy, (m, 2))
        if m == 0:
            e = np.zeros(0)
            return UpdateResult(ids, e.astype(bool), e, e.astype(np.int8))
        rows = self._rows(ids, "update")
        x = self.x[rows]
        P = self.P[rows]
        with np.errstate(over="ignore", invalid="ignore"):  # non-finite rows are rejected below
            r0, r1 = self.r
            # S = P[:2,:2] + R and its closed-form inverse
            a = P[:, 0, 0] + r0
            b = P[:, 0, 1]
            d = P[:, 1, 1] + r1
            det = a * d - b * b
            ok_det = det > 0
            inv_det = 1.0 / np.where(ok_det, det, 1.0)
            y0 = z[:, 0] - x[:, 0]
            y1 = z[:, 1] - x[:, 1]
            nis = (d * y0 * y0 - 2.0 * b * y0 * y1 + a * y1 * y1) * inv_det
            nis = np.where(ok_det & np.isfinite(nis), nis, np.finfo(float).max)
            # K = P Hᵀ S⁻¹ (N,3,2), written out
            Pc0, Pc1 = P[:, :, 0], P[:, :, 1]
            K = np.empty((m, 3, 2))
            K[:, :, 0] = (Pc0 * d[:, None] - Pc1 * b[:, None]) * inv_det[:, None]
            K[:, :, 1] = (Pc1 * a[:, None] - Pc0 * b[:, None]) * inv_det[:, None]
            x_new = x + K[:, :, 0] * y0[:, None] + K[:, :, 1] * y1[:, None]
            L = np.zeros((m, 3, 3))  # I − K H
            L[:, :, :2] = -K
            L[:, 0, 0] += 1.0
            L[:, 1, 1] += 1.0
            L[:, 2, 2] = 1.0
            P_new = L @ P @ np.swapaxes(L, 1, 2) + (K * self.r) @ np.swapaxes(K, 1, 2)
            P_new = 0.5 * (P_new + np.swapaxes(P_new, 1, 2))

        frozen = self.invalid[rows]
        reason = np.where(frozen, FROZEN, np.where(nis <= self.config.gate_threshold, ACCEPTED, GATED)).astype(np.int8)
        finite = np.all(np.isfinite(x_new), 1) & np.all(np.isfinite(P_new), (1, 2)) & ok_det
        reason[(reason == ACCEPTED) & ~finite] = GATED
        acc = reason == ACCEPTED
        ra = rows[acc]
        self.x[ra] = x_new[acc]
        self.P[ra] = P_new[acc]
        self.n_updates[ra] += 1
        gated = rows[reason == GATED]
        self.n_rejects[ra] = 0
        self.n_rejects[gated] += 1
        self.diverged[gated] |= self.n_rejects[gated] >= self.config.max_consecutive_rejects
        self.invalid[ra] |= self._out_of_domain(self.x[ra], self.P[ra])
        live = ~frozen
        rl = rows[live]
        cap = 2.0 * self.config.gate_threshold
        self.nis_count[rl] += 1
        alpha = 1.0 / np.minimum(self.nis_count[rl], self.config.nis_window)  # running mean, then exponential
        self.nis_avg[rl] += alpha * (np.minimum(nis[live], cap) - self.nis_avg[rl])
        if self.config.max_mean_nis > 0:
            full = self.nis_count[rl] >= self.config.nis_window
            self.diverged[rl] |= full & (self.nis_avg[rl] > self.config.max_mean_nis)
        return UpdateResult(ids, acc, nis, reason)

    # -- output ---------------------------------------------------------------------------------
    def estimates(self) -> LandmarkEstimates:
        """Point, range and σ of every landmark in the current camera frame (all finite).

        range = Z sqrt(1 + x̄² + ȳ²) = s/ξ with s = sqrt(1 + x̄² + ȳ²); its gradient is
        ∂range/∂(x̄, ȳ, ξ) = (x̄/(s ξ), ȳ/(s ξ), −s/ξ²) and range_sigma = sqrt(J P Jᵀ).
        """
        cfg = self.config
        x, P = self.x, self.P
        xi = x[:, 2]
        far = xi < cfg.inv_depth_min
        status = np.full(len(x), OK, np.int8)
        status[far] = FAR
        status[self.diverged] = DIVERGED
        status[self.invalid] = INVALID
        valid = status == OK
        c = cfg.max_normalized_coord
        xb = np.clip(x[:, 0], -c, c)
        yb = np.clip(x[:, 1], -c, c)
        s = np.sqrt(1.0 + xb * xb + yb * yb)
        xi_eff = np.where(valid, xi, s * cfg.inv_depth_min)  # placeholder: distance max_range_m along the ray
        rng = s / xi_eff
        J = np.stack([xb / (s * xi_eff), yb / (s * xi_eff), -s / xi_eff**2], 1)
        with np.errstate(over="ignore", invalid="ignore"):
            var = np.einsum("ni,nij,nj->n", J, P, J)
        rsig = np.sqrt(np.clip(np.where(valid & np.isfinite(var), var, 0.0), 0.0, np.finfo(float).max))
        rsig = np.where(valid & np.isfinite(var), rsig, cfg.max_range_m)
        p_cam = np.stack([xb, yb, np.ones(len(x))], 1) / xi_eff[:, None]
        s_xi = np.sqrt(np.maximum(P[:, 2, 2], 0.0))
        converged = valid & (self.n_updates >= cfg.min_updates) & (rsig < cfg.converged_rel_sigma * rng)
        return LandmarkEstimates(self.ids.copy(), p_cam, rng, rsig, xi.copy(), s_xi, converged, valid, status)
