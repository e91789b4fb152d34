"""Compiled kernels of the anchored inverse-depth EKF: one loop over landmarks (docs/derivations/ekf_anchored.md, looming.md).

The pure-numpy reference in :mod:`companion.core.ekf_anchored` evaluates each step of the update
for all landmarks at once, ~60 small array operations per relinearization.  The kernels here do
the same arithmetic one landmark at a time, in scalars, 9-tuples (3×3 matrices) and n×n scratch
arrays allocated once per call (:mod:`companion.core.jit`).  They are used when ``jit.ENABLED``;
the reference runs otherwise, and tests/test_ekf_anchored_kernels.py compares the two.

Plain IEEE arithmetic (no fastmath).  ``error_model="numpy"``: a division by zero gives inf or NaN
as in the numpy reference, where numba's default would raise; such a result is then refused by the
same tests as in the reference (the gate, or step 4 of § Update).

Every equation is named after the section of docs/derivations/ekf_anchored.md (§ Measurement
model, § Jacobian, § Measurement noise, § Update, § Bookkeeping, § Outputs) or looming.md
(§ Inverse-depth form, § Jacobian, § Noise, gate and update) that derives it.

State x = (θ, φ, ρ, [b], [δ]) (n = 3, 6 or 9: the gyro bias b when ``drift``, the position-error
states δ at index ``i_pos`` ≥ 0, § Position error states), covariance P (n×n), anchor pose (R_A, C_A, t_A);
the bank's arrays are updated in place at the given rows (the rows of one call must be distinct).
"""

from __future__ import annotations

import math

import numpy as np

from companion.core import jit
from companion.core.ekf_anchored_model import BEHIND, GATED, LOOM_NAN, LOOM_NONPOSITIVE, UPDATED
from companion.core.jit import njit

#: h_z at or below this: the point is behind the camera (BEHIND), as in the reference
_HZ_MIN = 1e-9
#: |h_z| below this is replaced by it in 1/h_z (keeps the projection finite; the BEHIND test decides)
_HZ_GUARD = 1e-12


# 3×3 matrices travel as 9-tuples in row-major order (m00, m01, m02, m10, …): they stay in
# registers, where scratch arrays would be stored and reloaded between every product.
@njit(error_model="numpy")
def mat3(A):
    """A (3×3 array) as a row-major 9-tuple."""
    return (A[0, 0], A[0, 1], A[0, 2], A[1, 0], A[1, 1], A[1, 2], A[2, 0], A[2, 1], A[2, 2])


@njit(error_model="numpy")
def mat3_transposed(A):
    """Aᵀ (of a 3×3 array) as a row-major 9-tuple."""
    return (A[0, 0], A[1, 0], A[2, 0], A[0, 1], A[1, 1], A[2, 1], A[0, 2], A[1, 2], A[2, 2])


@njit(error_model="numpy")
def matvec3(M, v0, v1, v2):
    """M v for a 9-tuple M: a 3-tuple."""
    return (M[0] * v0 + M[1] * v1 + M[2] * v2, M[3] * v0 + M[4] * v1 + M[5] * v2, M[6] * v0 + M[7] * v1 + M[8] * v2)


@njit(error_model="numpy")
def matmul3(A, B):
    """A B for 9-tuples: a 9-tuple."""
    c0 = matvec3(A, B[0], B[3], B[6])
    c1 = matvec3(A, B[1], B[4], B[7])
    c2 = matvec3(A, B[2], B[5], B[8])
    return (c0[0], c1[0], c2[0], c0[1], c1[1], c2[1], c0[2], c1[2], c2[2])


@njit(error_model="numpy")
def exp_and_left_jacobian(w0, w1, w2):
    """(Exp(w), J_l(w)) as 9-tuples, § Jacobian:

    E = I + (sin ϑ/ϑ) K + ((1 − cos ϑ)/ϑ²) K²,   J_l = I + ((1 − cos ϑ)/ϑ²) K + ((ϑ − sin ϑ)/ϑ³) K²,
    K = [w]×, K² = w wᵀ − ϑ² I, ϑ = |w|, Taylor series of the coefficients below ϑ = 1e-6.
    """
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    th = math.sqrt(th2)
    if th < 1e-6:
        a = 1.0 - th2 / 6
        b = 0.5 - th2 / 24
        d = 1.0 / 6 - th2 / 120
    else:
        s, c = math.sin(th), math.cos(th)
        ths2 = th * th
        a = s / th
        b = (1 - c) / ths2
        d = (th - s) / (ths2 * th)
    # K² = w wᵀ − ϑ² I: diagonal and (symmetric) off-diagonal entries
    q00, q11, q22 = w0 * w0 - th2, w1 * w1 - th2, w2 * w2 - th2
    q01, q02, q12 = w0 * w1, w0 * w2, w1 * w2
    # K = [w]× = [[0, −w₂, w₁], [w₂, 0, −w₀], [−w₁, w₀, 0]]
    E = (1.0 + b * q00, -a * w2 + b * q01, a * w1 + b * q02,
         a * w2 + b * q01, 1.0 + b * q11, -a * w0 + b * q12,
         -a * w1 + b * q02, a * w0 + b * q12, 1.0 + b * q22)
    J_l = (1.0 + d * q00, -b * w2 + d * q01, b * w1 + d * q02,
           b * w2 + d * q01, 1.0 + d * q11, -b * w0 + d * q12,
           -b * w1 + d * q02, b * w0 + d * q12, 1.0 + d * q22)
    return E, J_l


@njit(error_model="numpy")
def drift_integral(RA, Rc, dt):
    """D = ∫ R_world_cam dτ ≈ Δt/2 (R_A + R_c) (§ Attitude drift; trapezoid over the landmark's life), 9-tuple."""
    h = 0.5 * dt
    return (h * (RA[0] + Rc[0]), h * (RA[1] + Rc[1]), h * (RA[2] + Rc[2]), h * (RA[3] + Rc[3]), h * (RA[4] + Rc[4]),
            h * (RA[5] + Rc[5]), h * (RA[6] + Rc[6]), h * (RA[7] + Rc[7]), h * (RA[8] + Rc[8]))


@njit(error_model="numpy", inline="always")
def hc_jacobian(x, RA, a, R_cam_world, D, V, first_row, drift, i_pos):
    """[h_c | ∂h_c/∂x] (3 × (1+n)) into V at state x, § Measurement model and § Jacobian; rows
    ``first_row``…2 only (0: all; 2: h_z and its gradient, for looming).

    ``RA`` = R_world_camA, ``R_cam_world`` = R_cᵀ and the drift integral ``D`` (read when ``drift``)
    are 9-tuples, ``a`` = C_A − C (reported) a 3-tuple; ``i_pos`` the index of δ in x (−1: none).

        m = (cos φ sin θ, −sin φ, cos φ cos θ), ∂m/∂θ = (cos φ cos θ, 0, −cos φ sin θ),
        ∂m/∂φ = (−sin φ sin θ, −cos φ, −sin φ cos θ)
        with δ: a ← a + δ (§ Position error states)
        g = ρ a + R_A m;  [g | ∂g/∂(θ, φ, ρ)] = [g | R_A ∂m/∂θ | R_A ∂m/∂φ | a]
        no drift:  V = R_cᵀ [g | ∂g/∂(θ, φ, ρ)]
        drift:     w = D b, E = Exp(w);  V = [R_cᵀ E [g | ∂g/∂(θ, φ, ρ)] | −R_cᵀ [E g]× J_l D]
        with δ, its columns: ∂h_c/∂δ = ρ R_cᵀ E (E = I without drift)
    """
    if i_pos >= 0:
        a = (a[0] + x[i_pos], a[1] + x[i_pos + 1], a[2] + x[i_pos + 2])
    ct, st = math.cos(x[0]), math.sin(x[0])
    cp, sp = math.cos(x[1]), math.sin(x[1])
    rho = x[2]
    Rm = matvec3(RA, cp * st, -sp, cp * ct)  # R_A m
    g = (Rm[0] + rho * a[0], Rm[1] + rho * a[1], Rm[2] + rho * a[2])
    g_th = matvec3(RA, cp * ct, 0.0, -cp * st)  # ∂g/∂θ = R_A ∂m/∂θ
    g_ph = matvec3(RA, -sp * st, -cp, -sp * ct)  # ∂g/∂φ = R_A ∂m/∂φ
    M = R_cam_world
    if drift:  # attitude drift
        w = matvec3(D, x[3], x[4], x[5])
        E, J_l = exp_and_left_jacobian(w[0], w[1], w[2])
        Eg = matvec3(E, g[0], g[1], g[2])
        for c in range(3):  # column c of −[E g]× J_l D = (J_l D)[:, c] × E g, then R_cᵀ of it
            u = matvec3(J_l, D[c], D[3 + c], D[6 + c])
            col = matvec3(M, u[1] * Eg[2] - u[2] * Eg[1], u[2] * Eg[0] - u[0] * Eg[2], u[0] * Eg[1] - u[1] * Eg[0])
            for i in range(first_row, 3):
                V[i, 4 + c] = col[i]
        M = matmul3(M, E)  # R_cᵀ E
    for i in range(first_row, 3):
        m0, m1, m2 = M[3 * i], M[3 * i + 1], M[3 * i + 2]
        V[i, 0] = m0 * g[0] + m1 * g[1] + m2 * g[2]
        V[i, 1] = m0 * g_th[0] + m1 * g_th[1] + m2 * g_th[2]
        V[i, 2] = m0 * g_ph[0] + m1 * g_ph[1] + m2 * g_ph[2]
        V[i, 3] = m0 * a[0] + m1 * a[1] + m2 * a[2]
        if i_pos >= 0:
            V[i, 1 + i_pos] = rho * m0
            V[i, 2 + i_pos] = rho * m1
            V[i, 3 + i_pos] = rho * m2


@njit(error_model="numpy", inline="always")
def predict_pixel(x, RA, a, R_cam_world, D, zhat, H, V, drift, i_pos):
    """Predicted z̄ = (h_x/h_z, h_y/h_z) into ``zhat`` and H = ∂z/∂x (2×n) into ``H`` at x; returns h_z.

    § Jacobian: ∂z/∂h_c = (1/h_z) [I₂ | −z], applied to the rows of ∂h_c/∂x (:func:`hc_jacobian`).
    """
    n = x.shape[0]
    hc_jacobian(x, RA, a, R_cam_world, D, V, 0, drift, i_pos)
    hz = V[2, 0]
    inv_hz = 1.0 / (hz if abs(hz) > _HZ_GUARD else _HZ_GUARD)
    zhat[0] = V[0, 0] * inv_hz
    zhat[1] = V[1, 0] * inv_hz
    for j in range(n):
        H[0, j] = (V[0, 1 + j] - zhat[0] * V[2, 1 + j]) * inv_hz
        H[1, j] = (V[1, 1 + j] - zhat[1] * V[2, 1 + j]) * inv_hz
    return hz


@njit(error_model="numpy", inline="always")
def pixel_gain(P0, H, var0, var1, PHt, K):
    """§ Update, steps 1–2: P₀Hᵀ (n×2) into PHt, S = H P₀ Hᵀ + R, K = P₀ Hᵀ S⁻¹ (n×2) into K;
    returns S⁻¹ as (s00, s01, s10, s11) (closed-form 2×2 inverse: adjugate over the determinant)."""
    n = P0.shape[0]
    for i in range(n):
        p0 = 0.0
        p1 = 0.0
        for k in range(n):
            p0 += P0[i, k] * H[0, k]
            p1 += P0[i, k] * H[1, k]
        PHt[i, 0] = p0
        PHt[i, 1] = p1
    S00, S01, S10, S11 = var0, 0.0, 0.0, var1
    for k in range(n):
        S00 += H[0, k] * PHt[k, 0]
        S01 += H[0, k] * PHt[k, 1]
        S10 += H[1, k] * PHt[k, 0]
        S11 += H[1, k] * PHt[k, 1]
    det = S00 * S11 - S01 * S10
    i00, i01, i10, i11 = S11 / det, -S01 / det, -S10 / det, S00 / det
    for i in range(n):
        K[i, 0] = PHt[i, 0] * i00 + PHt[i, 1] * i10
        K[i, 1] = PHt[i, 0] * i01 + PHt[i, 1] * i11
    return i00, i01, i10, i11


@njit(error_model="numpy")
def pixel_workspace(n):
    """Scratch of :func:`update_pixel`, allocated once per kernel call: x₀, x_i (n), P_new (n×n),
    H (2×n), P₀Hᵀ, K (n×2), V = [h_c | ∂h_c/∂x] (3×(1+n)), z̄ (2)."""
    return (np.empty(n), np.empty(n), np.empty((n, n)), np.empty((2, n)), np.empty((n, 2)), np.empty((n, 2)),
            np.zeros((3, 1 + n)), np.empty(2))


@njit(error_model="numpy")
def layout_drift(n, i_pos):
    """Whether x carries the gyro bias b (x[3:6]): n = 6 without δ, n = 9 with it (the rule of
    ekf_anchored_model.layout_of, compiled)."""
    return n - (3 if i_pos >= 0 else 0) == 6


@njit(error_model="numpy")
def propagate(P, t_last, tA, r, t, i_pos, pos_var, pos_tau):
    """§ Position error states, process, for bank row r advanced from t_last[r] to t > t_last[r]: Var δ per
    axis grows by V(t − t_A) − V(t_last − t_A), V(Δ) = 2σ_p² (1 − exp(−Δ/τ)) (``pos_var`` = 2σ_p², ``pos_tau`` = τ;
    AnchoredEKFConfig.delta_variance), then t_last[r] = t.  Nothing without δ (i_pos < 0) or when t ≤ t_last[r]."""
    if i_pos < 0:
        return
    if t > t_last[r]:
        grow = pos_var * (math.exp(-(t_last[r] - tA[r]) / pos_tau) - math.exp(-(t - tA[r]) / pos_tau))  # V(t) − V(t_last)
        for k in range(3):
            P[r, i_pos + k, i_pos + k] += grow
        t_last[r] = t


@njit(error_model="numpy")
def update_pixel(x, P, RA, pA, tA, z, Rc, C, t, var_px, position_sigma, gate, iterations, ws, i_pos, consider):
    """One landmark's iterated EKF pixel update (§ Update); x (n,) and P (n×n) are overwritten only
    when accepted.  Returns (accepted, NIS at the first linearization, reason code).

    Anchor R_A (3×3), C_A (3,), t_A; measurement z (2,) from the pose R_c (3×3), C (3,) at t.
    ``var_px`` (2,) = (σ_px/f)² + σ_att² per axis and ``position_sigma`` = σ_p (§ Measurement noise);
    ``gate`` = χ²₂(p); ``iterations`` relinearizations (1 = plain EKF); ``ws`` = :func:`pixel_workspace`;
    ``i_pos`` the index of δ in x (−1: none; δ's covariance already propagated to t by :func:`propagate`);
    ``consider``: δ are consider states (§ Position error states, consider form): their gain rows are 0, so their mean
    and covariance stay as they are and only their cross-covariances with the estimated states change.
    """
    x0, xi, P_new, H, PHt, K, V, zhat = ws
    n = x.shape[0]
    drift = layout_drift(n, i_pos)
    for i in range(n):
        x0[i] = x[i]
    # § Measurement noise: R = diag((σ_px/f)² + σ_att² + 2 (max(ρ₀, 0) σ_p)²), evaluated at the prior x₀
    var0, var1 = var_px[0], var_px[1]
    if position_sigma > 0:
        pos = 2.0 * (max(x0[2], 0.0) * position_sigma) ** 2
        var0 += pos
        var1 += pos
    # what stays fixed over the relinearizations: R_A, C_A − C, R_cᵀ, the drift integral D
    RA_ = mat3(RA)
    Rc_ = mat3(Rc)
    a = (pA[0] - C[0], pA[1] - C[1], pA[2] - C[2])
    D = drift_integral(RA_, Rc_, t - tA)
    R_cam_world = mat3_transposed(Rc)
    # § Update step 1, predict and gate at x₀: y = z − h(x₀), S = H P₀ Hᵀ + R, NIS = yᵀ S⁻¹ y
    hz = predict_pixel(x0, RA_, a, R_cam_world, D, zhat, H, V, drift, i_pos)
    y0 = z[0] - zhat[0]
    y1 = z[1] - zhat[1]
    i00, i01, i10, i11 = pixel_gain(P, H, var0, var1, PHt, K)
    if consider:
        _zero_rows(K, i_pos)
    nis = y0 * (i00 * y0 + i01 * y1) + y1 * (i10 * y0 + i11 * y1)
    if hz <= _HZ_MIN:
        return False, np.inf, BEHIND
    if not nis <= gate:  # (a NaN NIS fails the gate too)
        return False, nis, GATED
    # § Update step 2, iterated EKF: x_{i+1} = x₀ + K_i (z − h(x_i) − H_i (x₀ − x_i)), K_i = P₀ H_iᵀ S_i⁻¹
    for i in range(n):  # first step: at x_0 = x₀ the H_0 (x₀ − x_0) term vanishes, the innovation is y
        xi[i] = x0[i] + (K[i, 0] * y0 + K[i, 1] * y1)
    for _ in range(1, iterations):
        hz = predict_pixel(xi, RA_, a, R_cam_world, D, zhat, H, V, drift, i_pos)
        if not hz > _HZ_MIN:  # an iterate behind the camera: update dropped; reason stays UPDATED, as in the reference
            return False, nis, UPDATED
        pixel_gain(P, H, var0, var1, PHt, K)
        if consider:
            _zero_rows(K, i_pos)
        e0 = z[0] - zhat[0]
        e1 = z[1] - zhat[1]
        for k in range(n):
            e0 -= H[0, k] * (x0[k] - xi[k])
            e1 -= H[1, k] * (x0[k] - xi[k])
        for i in range(n):
            xi[i] = x0[i] + (K[i, 0] * e0 + K[i, 1] * e1)
    # § Update step 3: P = P₀ − K (P₀ Hᵀ)ᵀ = (I − K H) P₀ at the last linearization, symmetrized
    for i in range(n):
        for j in range(n):
            P_new[i, j] = P[i, j] - (K[i, 0] * PHt[j, 0] + K[i, 1] * PHt[j, 1])
    if consider:  # consider form: the δ rows are the transposed δ columns, the δ block is P₀'s (§ Position error states)
        for i in range(i_pos, i_pos + 3):
            for j in range(n):
                P_new[i, j] = P_new[j, i] if j < i_pos else P[i, j]
    return _accept_if_finite(x, P, xi, P_new, nis)  # § Update step 4: non-finite → GATED, state unchanged


@njit(error_model="numpy", inline="always")
def _zero_rows(K, i_pos):
    """The consider form's pixel gain: K's (n×2) rows of δ (x[i_pos:i_pos+3]) set to 0."""
    for i in range(i_pos, i_pos + 3):
        K[i, 0] = 0.0
        K[i, 1] = 0.0


@njit(error_model="numpy", inline="always")
def _zero_entries(K, i_pos):
    """The consider form's looming gain: K's (n) entries of δ set to 0."""
    for i in range(i_pos, i_pos + 3):
        K[i] = 0.0


@njit(error_model="numpy")
def _symmetrize_finite(x, P):
    """P ← (P + Pᵀ)/2 in place; True when x and P are finite."""
    n = x.shape[0]
    finite = True
    for i in range(n):
        finite &= math.isfinite(x[i])
        for j in range(i + 1):
            s = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = s
            P[j, i] = s
            finite &= math.isfinite(s)
    return finite


@njit(error_model="numpy", inline="always")
def _accept_if_finite(x, P, xi, P_new, nis):
    """Symmetrize P_new; if xi and P_new are finite copy them into x and P (UPDATED), else leave the
    state as it was (GATED).  Returns (accepted, nis, reason) as the update kernels do."""
    if not _symmetrize_finite(xi, P_new):
        return False, nis, GATED
    n = x.shape[0]
    for i in range(n):
        x[i] = xi[i]
        for j in range(n):
            P[i, j] = P_new[i, j]
    return True, nis, UPDATED


@njit(error_model="numpy")
def commit(r, accepted, nis, n_updates, n_rejects, diverged, nis_avg, nis_count, nis_C, rho, C, gate, max_rejects, nis_window,
           max_mean_nis, nis_baseline):
    """§ Bookkeeping after each update of bank row r: accepted and consecutive-reject counts, the sticky
    diverged flag, the mean NIS (capped at 2 χ²₂(p), inf → cap; running mean, then exponential).  With
    ``nis_baseline`` (tan of the least angle) > 0 the NIS enters the mean only when the camera centre C has moved
    from ``nis_C[r]`` (where the last one did) by at least that angle seen from the landmark at inverse depth ρ."""
    if accepted:
        n_updates[r] += 1
        n_rejects[r] = 0
    else:
        n_rejects[r] += 1
    if n_rejects[r] >= max_rejects:
        diverged[r] = True
    if nis_baseline > 0:
        d2 = (C[0] - nis_C[r, 0]) ** 2 + (C[1] - nis_C[r, 1]) ** 2 + (C[2] - nis_C[r, 2]) ** 2
        if not math.sqrt(d2) * max(rho, 0.0) >= nis_baseline:
            return
        nis_C[r, 0], nis_C[r, 1], nis_C[r, 2] = C[0], C[1], C[2]
    cap = 2.0 * gate
    nis_c = min(nis, cap) if math.isfinite(nis) else cap
    nis_count[r] += 1
    alpha = 1.0 / min(float(nis_count[r]), nis_window)
    nis_avg[r] += alpha * (nis_c - nis_avg[r])
    if max_mean_nis > 0 and nis_count[r] >= nis_window and nis_avg[r] > max_mean_nis:
        diverged[r] = True


@njit(error_model="numpy")
def update_pixel_sequences(x, P, RA, pA, tA, n_updates, n_rejects, diverged, nis_avg, nis_count, nis_C, t_last,
                           rows, z, Rc, C, t, count, var_px, position_sigma, gate, iterations, max_rejects, nis_window,
                           max_mean_nis, i_pos, pos_var, pos_tau, consider, nis_baseline, accepted, nis, reason):
    """Fuse, for each listed landmark i (bank row ``rows[i]``), its observations j < ``count[i]`` in
    order (z (M,K,2) from poses Rc (M,K,3,3), C (M,K,3) at times t (M,K)), each followed by :func:`commit`.

    The bank arrays (x … t_last) are updated in place (δ's covariance propagated before each update); ``accepted`` (M,K) bool, ``nis`` (M,K) and
    ``reason`` (M,K) int8 are written per observation.  One frame of ``update_banks`` is K = 1; a
    buffered replay (``update_sequence``) is K slots: landmarks are independent, so landmark by
    landmark equals the reference's slot-by-slot batches.
    """
    ws = pixel_workspace(x.shape[1])
    for i in range(rows.shape[0]):
        r = rows[i]
        for j in range(count[i]):
            propagate(P, t_last, tA, r, t[i, j], i_pos, pos_var, pos_tau)
            ok, nis_ij, reason_ij = update_pixel(x[r], P[r], RA[r], pA[r], tA[r], z[i, j], Rc[i, j], C[i, j], t[i, j],
                                                 var_px, position_sigma, gate, iterations, ws, i_pos, consider)
            accepted[i, j] = ok
            nis[i, j] = nis_ij
            reason[i, j] = reason_ij
            commit(r, ok, nis_ij, n_updates, n_rejects, diverged, nis_avg, nis_count, nis_C, x[r, 2], C[i, j], gate,
                   max_rejects, nis_window, max_mean_nis, nis_baseline)


@njit(error_model="numpy")
def update_pixel_rows(x, P, RA, pA, tA, n_updates, n_rejects, diverged, nis_avg, nis_count, nis_C, t_last,
                      rows, z, Rc, C, t, var_px, position_sigma, gate, iterations, max_rejects, nis_window, max_mean_nis,
                      i_pos, pos_var, pos_tau, consider, nis_baseline, accepted, nis, reason):
    """One frame: fuse z[i] (M,2) into bank row ``rows[i]``, all seen from the pose Rc (3,3), C (3,)
    at t, each followed by :func:`commit`; ``accepted``, ``nis``, ``reason`` (M,) written per landmark.
    The same as :func:`update_pixel_sequences` with K = 1 and that pose in every slot."""
    ws = pixel_workspace(x.shape[1])
    for i in range(rows.shape[0]):
        r = rows[i]
        propagate(P, t_last, tA, r, t, i_pos, pos_var, pos_tau)
        ok, nis_i, reason_i = update_pixel(x[r], P[r], RA[r], pA[r], tA[r], z[i], Rc, C, t, var_px, position_sigma,
                                           gate, iterations, ws, i_pos, consider)
        accepted[i] = ok
        nis[i] = nis_i
        reason[i] = reason_i
        commit(r, ok, nis_i, n_updates, n_rejects, diverged, nis_avg, nis_count, nis_C, x[r, 2], C, gate, max_rejects,
               nis_window, max_mean_nis, nis_baseline)


# -- looming (docs/derivations/looming.md) ----------------------------------------------------------
@njit(error_model="numpy")
def looming_workspace(n):
    """Scratch of :func:`update_looming`: x₀, x_i, H_s, P₀H_sᵀ, K (n), A = I − K H_s, A P₀, P_new (n×n),
    the third rows of [h_c | ∂h_c/∂x] at the previous and the current pose (3×(1+n) each, row 2 used)."""
    return (np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty((n, n)), np.empty((n, n)),
            np.empty((n, n)), np.zeros((3, 1 + n)), np.zeros((3, 1 + n)))


@njit(error_model="numpy", inline="always")
def predict_looming(x, RA, a_prev, R_cam_world_prev, D_prev, a, R_cam_world, D, Hs, Vp, Vn, drift, i_pos):
    """looming.md § Inverse-depth form and § Jacobian at x: returns (h_z', h_z, h_s = h_z'/h_z) and
    H_s = (∂h_z'/∂x − h_s ∂h_z/∂x)/h_z into ``Hs`` (n); h_z', h_z and their gradients are the third
    row of [h_c | ∂h_c/∂x] (:func:`hc_jacobian`) at the previous and the current pose (the same δ at both)."""
    n = x.shape[0]
    hc_jacobian(x, RA, a_prev, R_cam_world_prev, D_prev, Vp, 2, drift, i_pos)
    hc_jacobian(x, RA, a, R_cam_world, D, Vn, 2, drift, i_pos)
    hz_prev, hz_now = Vp[2, 0], Vn[2, 0]
    inv = 1.0 / (hz_now if abs(hz_now) > _HZ_GUARD else _HZ_GUARD)
    hs = hz_prev * inv
    for j in range(n):
        Hs[j] = (Vp[2, 1 + j] - hs * Vn[2, 1 + j]) * inv
    return hz_prev, hz_now, hs


@njit(error_model="numpy")
def update_looming(x, P, RA, pA, tA, z, var, Rp, Cp, t_prev, Rc, C, t, gate, iterations, ws, i_pos, consider):
    """One landmark's looming update (looming.md § Noise, gate and update): scalar z = scale, R_s = ``var``,
    χ²₁ ``gate``, iterated ``iterations`` times, Joseph form; x, P overwritten only when accepted.
    Previous pose (Rp, Cp, t_prev), current (Rc, C, t); ``consider``: δ's gain is 0 (:func:`update_pixel`; the Joseph form
    holds for any gain).  Returns (accepted, NIS at the first linearization, reason code)."""
    x0, xi, H, PHt, K, A, AP, P_new, Vp, Vn = ws
    n = x.shape[0]
    drift = layout_drift(n, i_pos)
    for i in range(n):
        x0[i] = x[i]
    RA_ = mat3(RA)
    a_prev = (pA[0] - Cp[0], pA[1] - Cp[1], pA[2] - Cp[2])
    a = (pA[0] - C[0], pA[1] - C[1], pA[2] - C[2])
    D_prev = drift_integral(RA_, mat3(Rp), t_prev - tA)
    D = drift_integral(RA_, mat3(Rc), t - tA)
    Rcw_prev, Rcw = mat3_transposed(Rp), mat3_transposed(Rc)
    hzp, hzn, hs = predict_looming(x0, RA_, a_prev, Rcw_prev, D_prev, a, Rcw, D, H, Vp, Vn, drift, i_pos)
    S = _looming_gain(P, H, var, PHt, K)  # P₀ H_sᵀ, S = H_s P₀ H_sᵀ + R_s, K = P₀ H_sᵀ / S
    if consider:
        _zero_entries(K, i_pos)
    y = z - hs
    nis = y * y / S
    if hzp <= _HZ_MIN or hzn <= _HZ_MIN:
        return False, np.inf, BEHIND
    if not nis <= gate:
        return False, nis, GATED
    for i in range(n):
        xi[i] = x0[i] + K[i] * y
    for _ in range(1, iterations):  # iterated EKF, as the pixel update
        hzp, hzn, hs = predict_looming(xi, RA_, a_prev, Rcw_prev, D_prev, a, Rcw, D, H, Vp, Vn, drift, i_pos)
        if not (hzp > _HZ_MIN and hzn > _HZ_MIN):
            return False, nis, UPDATED
        _looming_gain(P, H, var, PHt, K)
        if consider:
            _zero_entries(K, i_pos)
        e = z - hs
        for k in range(n):
            e -= H[k] * (x0[k] - xi[k])
        for i in range(n):
            xi[i] = x0[i] + K[i] * e
    # Joseph form: P = (I − K H) P₀ (I − K H)ᵀ + K R_s Kᵀ, symmetrized
    for i in range(n):
        for j in range(n):
            A[i, j] = (1.0 if i == j else 0.0) - K[i] * H[j]
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += A[i, k] * P[k, j]
            AP[i, j] = s
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(n):
                s += AP[i, k] * A[j, k]
            P_new[i, j] = s + var * (K[i] * K[j])
    return _accept_if_finite(x, P, xi, P_new, nis)


@njit(error_model="numpy", inline="always")
def _looming_gain(P0, H, var, PHt, K):
    """P₀ H_sᵀ (n) into PHt, K = P₀ H_sᵀ / S into K; returns S = H_s P₀ H_sᵀ + R_s."""
    n = P0.shape[0]
    S = 0.0
    for i in range(n):
        s = 0.0
        for k in range(n):
            s += P0[i, k] * H[k]
        PHt[i] = s
    for k in range(n):
        S += H[k] * PHt[k]
    S += var
    for i in range(n):
        K[i] = PHt[i] / S
    return S


@njit(error_model="numpy")
def update_looming_rows(x, P, RA, pA, tA, n_looming, t_last, rows, z, sigma, Rp, Cp, t_prev, Rc, C, t, sigma_floor, gate,
                        iterations, i_pos, pos_var, pos_tau, consider, accepted, nis, reason):
    """Looming updates of bank rows ``rows`` with scales z (M,) of σ ``sigma`` (M,) between the shared
    previous (Rp, Cp, t_prev) and current (Rc, C, t) poses; bank arrays updated in place, ``n_looming``
    counts accepted ones.  A NaN scale is skipped (LOOM_NAN), a non-positive or non-finite scale or σ
    refused (LOOM_NONPOSITIVE), both with NIS NaN; R_s = σ² + σ_floor².  Every listed row's δ covariance
    is first propagated to t (:func:`propagate`)."""
    ws = looming_workspace(x.shape[1])
    for i in range(rows.shape[0]):
        r = rows[i]
        propagate(P, t_last, tA, r, t, i_pos, pos_var, pos_tau)
        zi, si = z[i], sigma[i]
        accepted[i] = False
        nis[i] = np.nan
        if math.isnan(zi):
            reason[i] = LOOM_NAN
            continue
        if not (math.isfinite(zi) and zi > 0 and math.isfinite(si) and si >= 0):
            reason[i] = LOOM_NONPOSITIVE
            continue
        var = si * si + sigma_floor * sigma_floor
        ok, nis_i, reason_i = update_looming(x[r], P[r], RA[r], pA[r], tA[r], zi, var, Rp, Cp, t_prev, Rc, C, t, gate,
                                             iterations, ws, i_pos, consider)
        accepted[i] = ok
        nis[i] = nis_i
        reason[i] = reason_i
        if ok:
            n_looming[r] += 1


# -- outputs ------------------------------------------------------------------------------------------
@njit(error_model="numpy")
def estimates(x, P, RA, pA, diverged, n_updates, C, max_range, converged_rel_sigma, min_updates, i_pos,
              p_world, rng, rsig, srho, valid, converged):
    """§ Outputs and convergence, per landmark, relative to the camera centre C (3,), into the (N,…) outputs:

        a = C_A − C (+ δ when i_pos ≥ 0), ρ_eff = max(ρ, 1/max_range), g = ρ_eff a + R_A m,
        r = min(|g|/ρ_eff, max_range),
        ∂r/∂(θ, φ) = gᵀ R_A ∂m/∂(θ, φ) / (|g| ρ_eff), ∂r/∂ρ = gᵀ a/(|g| ρ_eff) − |g|/ρ_eff², ∂r/∂δ = g/|g|,
        σ_r = min(√(J P_[θφρ(δ)] Jᵀ), max_range), p_world = C_A (+ δ) + R_A m / ρ_eff,
        valid = not diverged and ρ > −3 σ_ρ, converged = valid, ρ > 1/max_range, σ_r < k r, n_updates ≥ min.
    """
    rho_floor = 1.0 / max_range
    J = np.zeros(6)
    idx = np.array([0, 1, 2, max(i_pos, 0), max(i_pos, 0) + 1, max(i_pos, 0) + 2])
    nj = 6 if i_pos >= 0 else 3
    for l in range(x.shape[0]):
        th, ph, rho = x[l, 0], x[l, 1], x[l, 2]
        ct, st, cp, sp = math.cos(th), math.sin(th), math.cos(ph), math.sin(ph)
        s_rho = math.sqrt(max(P[l, 2, 2], 0.0))
        rho_eff = max(rho, rho_floor)
        R = RA[l]
        ng2 = 0.0  # |g|²
        gm_t = 0.0  # gᵀ R_A ∂m/∂θ
        gm_p = 0.0  # gᵀ R_A ∂m/∂φ
        ga = 0.0  # gᵀ (C_A − C)
        for i in range(3):
            mw = R[i, 0] * (cp * st) - R[i, 1] * sp + R[i, 2] * (cp * ct)  # R_A m
            a_i = pA[l, i] - C[i]
            p_world[l, i] = pA[l, i] + mw / rho_eff
            if i_pos >= 0:
                a_i = a_i + x[l, i_pos + i]
                p_world[l, i] = p_world[l, i] + x[l, i_pos + i]
            g_i = rho_eff * a_i + mw
            J[3 + i] = g_i  # ∂r/∂δ_i = g_i/|g|, normalized below
            ng2 += g_i * g_i
            gm_t += g_i * (R[i, 0] * (cp * ct) - R[i, 2] * (cp * st))
            gm_p += g_i * (-R[i, 0] * (sp * st) - R[i, 1] * cp - R[i, 2] * (sp * ct))
            ga += g_i * a_i
        ng = math.sqrt(ng2)
        r = min(ng / rho_eff, max_range)
        J0 = gm_t / (ng * rho_eff)
        J1 = gm_p / (ng * rho_eff)
        J2 = ga / (ng * rho_eff) - ng / rho_eff**2
        if nj == 3:
            var = (J0 * (P[l, 0, 0] * J0 + P[l, 0, 1] * J1 + P[l, 0, 2] * J2)
                   + J1 * (P[l, 1, 0] * J0 + P[l, 1, 1] * J1 + P[l, 1, 2] * J2)
                   + J2 * (P[l, 2, 0] * J0 + P[l, 2, 1] * J1 + P[l, 2, 2] * J2))
        else:  # J P Jᵀ over (θ, φ, ρ, δ)
            J[0], J[1], J[2] = J0, J1, J2
            for k in range(3, 6):
                J[k] = J[k] / ng
            var = 0.0
            for i in range(6):
                s = 0.0
                for k in range(6):
                    s += P[l, idx[i], idx[k]] * J[k]
                var += J[i] * s
        sr = min(math.sqrt(max(var, 0.0)), max_range)
        rng[l] = r
        rsig[l] = sr
        srho[l] = s_rho
        valid[l] = not diverged[l] and rho > -3.0 * s_rho
        converged[l] = valid[l] and rho > rho_floor and sr < converged_rel_sigma * r and n_updates[l] >= min_updates


@njit(error_model="numpy")
def refine_evaluate(x, xp, Ip, RA, pA, tA, starts, counts, t, R, C, z, W, s, s_var, prev, drift, i_pos,
                    cost, info, grad, front):
    """The batch refinement's cost, information and gradient at states x (M,n) (ekf_anchored.md § Batch
    refinement; :func:`companion.core.ekf_anchored_refine._evaluate` is the numpy reference): per landmark m,
    its slots ``starts[m]`` … + ``counts[m]`` of the flattened history (t, R, C, z, s, s_var, prev), fixed pixel
    weights ``W`` (L,2; NaN where no pixel); writes cost (M,), info (M,n,n), grad (M,n) = −½∇J, front (M,)."""
    M, n = x.shape
    zhat = np.empty(2)
    H = np.empty((2, n))
    V = np.zeros((3, 1 + n))
    Hs = np.empty(n)
    Vp = np.zeros((3, 1 + n))
    Vn = np.zeros((3, 1 + n))
    dx = np.empty(n)
    D = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for m in range(M):
        xm = x[m]
        for i in range(n):
            dx[i] = xm[i] - xp[m, i]
        dx[0] = (dx[0] + math.pi) % (2.0 * math.pi) - math.pi
        c = 0.0
        for i in range(n):
            g = 0.0
            for j in range(n):
                g += Ip[m, i, j] * dx[j]
                info[m, i, j] = Ip[m, i, j]
            c += dx[i] * g
            grad[m, i] = -g
        ok = True
        RAm = mat3(RA[m])
        for l in range(starts[m], starts[m] + counts[m]):
            Rc = mat3(R[l])
            Rcw = mat3_transposed(R[l])
            a = (pA[m, 0] - C[l, 0], pA[m, 1] - C[l, 1], pA[m, 2] - C[l, 2])
            if drift:
                D = drift_integral(RAm, Rc, t[l] - tA[m])
            if z[l, 0] == z[l, 0]:  # a pixel in this slot
                hz = predict_pixel(xm, RAm, a, Rcw, D, zhat, H, V, drift, i_pos)
                if not hz > _HZ_MIN:
                    ok = False
                for k in range(2):
                    r = z[l, k] - zhat[k]
                    w = W[l, k]
                    c += w * r * r
                    for i in range(n):
                        wh = w * H[k, i]
                        grad[m, i] += wh * r
                        for j in range(n):
                            info[m, i, j] += wh * H[k, j]
            q = prev[l]
            if s[l] == s[l] and q >= 0:  # a looming measurement against the previous slot's pose
                a_p = (pA[m, 0] - C[q, 0], pA[m, 1] - C[q, 1], pA[m, 2] - C[q, 2])
                Rcw_p = mat3_transposed(R[q])
                D_p = D
                if drift:
                    D_p = drift_integral(RAm, mat3(R[q]), t[q] - tA[m])
                hzp, hzn, hs = predict_looming(xm, RAm, a_p, Rcw_p, D_p, a, Rcw, D, Hs, Vp, Vn, drift, i_pos)
                if not (hzp > _HZ_MIN and hzn > _HZ_MIN):
                    ok = False
                w = 1.0 / s_var[l]
                r = s[l] - hs
                c += w * r * r
                for i in range(n):
                    wh = w * Hs[i]
                    grad[m, i] += wh * r
                    for j in range(n):
                        info[m, i, j] += wh * Hs[j]
        cost[m] = c
        front[m] = ok


@jit.register_warmup
def warm_up() -> None:
    """Compile (or load) every kernel on one landmark with 3, 6 and 9 states (with and without δ), in the array
    layouts the filter passes (one signature serves them all: the layout is a run-time argument)."""
    for n, i_pos in ((3, -1), (6, -1), (6, 3), (9, 6)):
        consider = i_pos >= 0  # a run-time flag: one signature for both forms
        x = np.zeros((1, n))
        x[0, 2] = 0.1
        P = np.eye(n)[None] * 1e-4
        RA, pA, tA = np.eye(3)[None].copy(), np.zeros((1, 3)), np.zeros(1)
        i64, b = np.zeros(1, np.int64), np.zeros(1, bool)
        rows, one = np.zeros(1, np.int64), np.ones(1, np.int64)
        Rc, C = np.eye(3), np.array([0.0, 0.0, -1.0])
        update_pixel_sequences(x, P, RA, pA, tA, i64.copy(), i64.copy(), b.copy(), np.zeros(1), i64.copy(), np.zeros((1, 3)),
                               np.zeros(1), rows, np.zeros((1, 1, 2)), Rc[None, None].copy(), C[None, None].copy(),
                               np.ones((1, 1)), one, np.full(2, 1e-6), 0.1, 13.8, 2, 5, 10.0, 4.0, i_pos, 0.02, 30.0, consider,
                               0.01, np.zeros((1, 1), bool), np.zeros((1, 1)), np.zeros((1, 1), np.int8))
        update_pixel_rows(x, P, RA, pA, tA, i64.copy(), i64.copy(), b.copy(), np.zeros(1), i64.copy(), np.zeros((1, 3)),
                          np.zeros(1), rows, np.zeros((1, 2)), Rc, C, 1.0, np.full(2, 1e-6), 0.1, 13.8, 2, 5, 10.0, 4.0, i_pos,
                          0.02, 30.0, consider, 0.01, np.zeros(1, bool), np.zeros(1), np.zeros(1, np.int8))
        update_looming_rows(x, P, RA, pA, tA, i64.copy(), np.zeros(1), rows, np.ones(1), np.zeros(1), Rc, np.zeros(3), 0.0,
                            Rc, C, 1.0, 0.003, 10.8, 1, i_pos, 0.02, 30.0, consider, np.zeros(1, bool), np.zeros(1), np.zeros(1, np.int8))
        estimates(x, P, RA, pA, b, i64, np.zeros(3), 1e4, 0.1, 3, i_pos, np.zeros((1, 3)), np.zeros(1), np.zeros(1),
                  np.zeros(1), np.zeros(1, bool), np.zeros(1, bool))
        if i_pos < 0:  # the batch refinement (static states only)
            refine_evaluate(x, x.copy(), P.copy(), RA, pA, tA, np.zeros(1, np.int64), np.full(1, 2, np.int64), np.array([0.0, 1.0]),
                            np.stack([np.eye(3), np.eye(3)]), np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
                            np.array([[np.nan, np.nan], [0.0, 0.0]]), np.ones((2, 2)), np.array([np.nan, 1.0]), np.ones(2),
                            np.array([-1, 0], np.int64), n == 6, i_pos, np.zeros(1), np.zeros((1, n, n)), np.zeros((1, n)),
                            np.zeros(1, bool))
