"""Cramér–Rao bound on range for static points seen from known camera poses (the floor in the seed 000 and seed 004 benchmarks).

With pixel noise σ (independent, isotropic) the Fisher information of a point p after frames
0..k is  F_k = Σ_{j ≤ k, visible} J_jᵀ J_j / σ²,  where J_j = ∂(u, v)/∂p_world of the pinhole
projection:  J_j = (1/Z) [[fx, 0, −fx·x], [0, fy, −fy·y]] · R_cam_world,j  with (x, y) the
normalized coordinates and Z the depth in camera j.  The bound on the range d_k = ||p − C_k|| from
the current camera is  σ_d² ≥ gᵀ F_k⁻¹ g,  g = (p − C_k)/d_k.  Where F_k is singular (fewer than
two views, no translation) the bound is infinite.
"""

from __future__ import annotations

import numpy as np

from companion.errors import InputError


def range_crlb(
    p_world: np.ndarray,
    R_world_cam: np.ndarray,
    p_world_cam: np.ndarray,
    visible: np.ndarray,
    sigma_px: float,
    fx: float,
    fy: float,
) -> np.ndarray:
    """Range σ bound for N points at every frame k of K: returns (K, N), ``inf`` where unobservable.

    ``p_world`` (N, 3); ``R_world_cam`` (K, 3, 3); ``p_world_cam`` (K, 3); ``visible`` (K, N) bool.
    """
    p = np.asarray(p_world, float)
    R = np.asarray(R_world_cam, float)
    C = np.asarray(p_world_cam, float)
    vis = np.asarray(visible, bool)
    if p.ndim != 2 or p.shape[1] != 3 or R.ndim != 3 or R.shape[1:] != (3, 3) or C.shape != (len(R), 3):
        raise InputError(f"range_crlb: shapes p {p.shape}, R {R.shape}, C {C.shape} must be (N,3), (K,3,3), (K,3)")
    if vis.shape != (len(R), len(p)):
        raise InputError(f"range_crlb: visible must be (K, N) = {(len(R), len(p))}, got {vis.shape}")
    if not sigma_px > 0:
        raise InputError("range_crlb: sigma_px must be > 0")
    pc = np.einsum("kji,knj->kni", R, p[None, :, :] - C[:, None, :])  # (K, N, 3) camera frame
    Z = pc[..., 2]
    vis = vis & (Z > 1e-9)
    Zs = np.where(vis, Z, 1.0)
    x, y = pc[..., 0] / Zs, pc[..., 1] / Zs
    Jc = np.zeros(pc.shape[:2] + (2, 3))
    Jc[..., 0, 0] = fx / Zs
    Jc[..., 0, 2] = -fx * x / Zs
    Jc[..., 1, 1] = fy / Zs
    Jc[..., 1, 2] = -fy * y / Zs
    J = np.einsum("knab,kcb->knac", Jc, R)  # ∂uv/∂p_world = Jc · R_cam_world
    info = np.einsum("knai,knaj->knij", J, J) * vis[..., None, None] / sigma_px**2
    F = np.cumsum(info, axis=0)
    d = p[None, :, :] - C[:, None, :]
    dn = np.linalg.norm(d, axis=2)
    g = d / dn[..., None]
    out = np.full(F.shape[:2], np.inf)
    scale = np.trace(F, axis1=2, axis2=3)
    ok = scale > 0
    # relative conditioning test before inverting: singular when fewer than two distinct views
    cond = np.full(F.shape[:2], np.inf)
    cond[ok] = np.linalg.cond(F[ok])
    ok &= cond < 1e12
    if np.any(ok):
        Finv = np.linalg.inv(F[ok])
        out[ok] = np.sqrt(np.einsum("mi,mij,mj->m", g[ok], Finv, g[ok]))
    return out
