"""Triangulation with explicit gates (docs/derivations/triangulation.md, seed 004 eq. 9–10).

Two views: rays ``p`` (camera 1) and ``p'`` (camera 2) in normalized coordinates (z = 1),
``R = R_cam1_cam2`` and ``t = C2 − C1`` expressed in camera 1.  The point satisfies
``Z p = t + Z' R p'``; crossing with ``R p'`` gives seed 004 eq. 10

    Z  = ((t × R p') · (p × R p')) / ||p × R p'||²,       P = Z p,

and crossing with ``p`` gives the depth in camera 2, ``Z' = ((t × p) · (p × R p')) / ||p × R p'||²``.
Both depths must be positive.  The problem is degenerate when the baseline vanishes (pure
rotation) or the rays are parallel (point at infinity, or on the focus of expansion), so each
case is gated explicitly and reported with a :class:`Reject` code; a rejected point is returned as
zeros and never as NaN or inf.

Multi-view: the midpoint solution over all rays of a track, ``X = (Σ Aᵢ)⁻¹ Σ Aᵢ Cᵢ`` with
``Aᵢ = I − rᵢ rᵢᵀ`` (least squares on perpendicular distances), gated on its longest baseline
and widest parallax.
"""

from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np

from companion.config import require, require_finite
from companion.core import jit
from companion.core.jit import njit
from companion.errors import InputError


class Reject(enum.IntEnum):
    """Why a triangulation was refused (0 = accepted)."""

    OK = 0
    NON_FINITE = 1
    SHORT_BASELINE = 2
    LOW_PARALLAX = 3
    BEHIND_CAMERA = 4
    TOO_FAR = 5
    TOO_UNCERTAIN = 6


@dataclasses.dataclass(frozen=True)
class TriangulationConfig:
    """Gates of the ``[triangulation]`` table."""

    min_baseline_m: float = 0.3  # camera displacement below this: pure rotation, no range
    min_parallax_deg: float = 1.0  # angle between the two rays below this: too close to infinity / FOE
    min_depth_m: float = 0.5  # nearer than this in either camera: treated as behind / invalid
    max_range_m: float = 1000.0  # farther than this: rejected as unmeasurable
    max_rel_sigma: float = 0.3  # predicted range σ / range above this: too uncertain to seed a filter

    def __post_init__(self) -> None:
        require_finite("min_baseline_m", self.min_baseline_m, nonnegative=True)
        require_finite("min_parallax_deg", self.min_parallax_deg, nonnegative=True)
        require(self.min_parallax_deg < 90, f"min_parallax_deg must be < 90, got {self.min_parallax_deg}")
        require_finite("min_depth_m", self.min_depth_m, positive=True)
        require_finite("max_range_m", self.max_range_m, positive=True)
        require(self.max_range_m > self.min_depth_m, "max_range_m must exceed min_depth_m")
        require_finite("max_rel_sigma", self.max_rel_sigma, positive=True)


@dataclasses.dataclass
class TriangulationResult:
    """Per point: position in camera 1 (or world), depth / range, their σ and the gate verdict."""

    p: np.ndarray  # (N, 3) point; zeros where rejected
    depth: np.ndarray  # (N,) Z in camera 1 (two-view) or range from the last camera (multi-view)
    range_sigma: np.ndarray  # (N,) first-order range σ from the pixel noise; 0 where rejected
    parallax_rad: np.ndarray  # (N,) angle between the rays used
    reason: np.ndarray  # (N,) Reject codes

    @property
    def ok(self) -> np.ndarray:
        return self.reason == Reject.OK


def _check(name: str, a, shape_tail: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.shape[a.ndim - len(shape_tail):] != shape_tail:
        raise InputError(f"{name} must have trailing shape {shape_tail}, got {a.shape}")
    return a


def _homogeneous(xy: np.ndarray) -> np.ndarray:
    return np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], -1)


def triangulate_two_view(
    xy1: np.ndarray,
    xy2: np.ndarray,
    R_cam1_cam2: np.ndarray,
    t_cam1: np.ndarray,
    config: TriangulationConfig,
    sigma_xy: float = 0.0,
) -> TriangulationResult:
    """Seed 004 eq. 10 for N points at once.

    ``xy1``, ``xy2``: (N, 2) undistorted normalized coordinates in cameras 1 and 2.
    ``R_cam1_cam2``: (3, 3) or (N, 3, 3); ``t_cam1``: (3,) or (N, 3), C2 − C1 in camera 1.
    ``sigma_xy``: measurement σ in normalized units (pixel σ / f) for the range σ estimate
    ``σ_d ≈ √2 · d · σ_xy / sin(parallax)``; used by the ``max_rel_sigma`` gate when > 0.
    """
    xy1 = _check("xy1", xy1, (2,)).reshape(-1, 2)
    xy2 = _check("xy2", xy2, (2,)).reshape(-1, 2)
    if len(xy1) != len(xy2):
        raise InputError(f"xy1 and xy2 differ in length: {len(xy1)} vs {len(xy2)}")
    R = _check("R_cam1_cam2", R_cam1_cam2, (3, 3))
    t = _check("t_cam1", t_cam1, (3,))
    n = len(xy1)
    R = np.broadcast_to(R, (n, 3, 3))
    t = np.broadcast_to(t, (n, 3))
    reason = np.zeros(n, dtype=np.int8)
    finite = (
        np.all(np.isfinite(xy1), 1) & np.all(np.isfinite(xy2), 1)
        & np.all(np.isfinite(R), (1, 2)) & np.all(np.isfinite(t), 1)
    )
    reason[~finite] = Reject.NON_FINITE
    xy1 = np.where(finite[:, None], xy1, 0.0)
    xy2 = np.where(finite[:, None], xy2, 0.0)
    R = np.where(finite[:, None, None], R, np.eye(3))
    t = np.where(finite[:, None], t, 0.0)

    p = _homogeneous(xy1)
    Rp2 = np.einsum("nij,nj->ni", R, _homogeneous(xy2))
    c = np.cross(p, Rp2)
    c2 = np.einsum("ni,ni->n", c, c)
    cos_par = np.einsum("ni,ni->n", p, Rp2) / (np.linalg.norm(p, axis=1) * np.linalg.norm(Rp2, axis=1))
    parallax = np.arccos(np.clip(cos_par, -1.0, 1.0))
    baseline = np.linalg.norm(t, axis=1)

    def flag(mask, code):
        reason[(reason == Reject.OK) & mask] = code

    flag(baseline < config.min_baseline_m, Reject.SHORT_BASELINE)
    flag(parallax < np.radians(config.min_parallax_deg), Reject.LOW_PARALLAX)
    flag(c2 <= 1e-18, Reject.LOW_PARALLAX)
    safe = np.where(c2 > 1e-18, c2, 1.0)
    Z1 = np.einsum("ni,ni->n", np.cross(t, Rp2), c) / safe
    Z2 = np.einsum("ni,ni->n", np.cross(t, p), c) / safe
    flag((Z1 < config.min_depth_m) | (Z2 < config.min_depth_m), Reject.BEHIND_CAMERA)
    P = Z1[:, None] * p
    rng = np.linalg.norm(P, axis=1)
    flag(rng > config.max_range_m, Reject.TOO_FAR)
    sin_par = np.maximum(np.sin(parallax), 1e-12)
    range_sigma = np.sqrt(2.0) * rng * sigma_xy / sin_par
    if sigma_xy > 0:
        flag(range_sigma > config.max_rel_sigma * rng, Reject.TOO_UNCERTAIN)
    ok = reason == Reject.OK
    return TriangulationResult(
        p=np.where(ok[:, None], P, 0.0),
        depth=np.where(ok, Z1, 0.0),
        range_sigma=np.where(ok, range_sigma, 0.0),
        parallax_rad=parallax,
        reason=reason,
    )


def triangulate_poses(
    xy_a: np.ndarray,
    R_world_cam_a: np.ndarray,
    p_world_cam_a: np.ndarray,
    xy_b: np.ndarray,
    R_world_cam_b: np.ndarray,
    p_world_cam_b: np.ndarray,
    config: TriangulationConfig,
    sigma_xy: float = 0.0,
) -> TriangulationResult:
    """Two-view triangulation from world poses; ``p`` is returned in the world frame.

    Poses may be (3,3)/(3,) shared by all points or (N,3,3)/(N,3) per point.
    ``depth`` stays the depth along camera a's optical axis.
    """
    Ra = np.asarray(R_world_cam_a, float)
    Rb = np.asarray(R_world_cam_b, float)
    R_ab = np.swapaxes(Ra, -1, -2) @ Rb
    t_a = np.einsum("...ji,...j->...i", Ra, np.asarray(p_world_cam_b, float) - np.asarray(p_world_cam_a, float))
    res = triangulate_two_view(xy_a, xy_b, R_ab, t_a, config, sigma_xy)
    ok = res.ok
    p_world = np.einsum("...ij,...j->...i", Ra, res.p) + np.asarray(p_world_cam_a, float)
    res.p = np.where(ok[:, None], p_world, 0.0)
    return res


def triangulate_multiview(
    rays_world: np.ndarray,
    centers_world: np.ndarray,
    mask: np.ndarray,
    config: TriangulationConfig,
    sigma_xy: float = 0.0,
) -> TriangulationResult:
    """Midpoint least squares over whole tracks (N tracks × K views, padded with ``mask``).

    ``rays_world``: (N, K, 3) viewing directions (any length); ``centers_world``: (N, K, 3) camera
    centres; ``mask``: (N, K) which views exist.  Gates use the longest baseline and the widest
    angle between the first and last used rays; ``depth`` is the range from the last used camera.
    """
    rays = _check("rays_world", rays_world, (3,))
    C = _check("centers_world", centers_world, (3,))
    mask = np.asarray(mask, bool)
    if rays.ndim != 3 or rays.shape != C.shape or mask.shape != rays.shape[:2]:
        raise InputError(f"rays {rays.shape}, centers {C.shape} and mask {mask.shape} must be (N,K,3),(N,K,3),(N,K)")
    n, k, _ = rays.shape
    if jit.ENABLED:  # compiled: the same gates track by track (_multiview_kernel)
        out = TriangulationResult(np.zeros((n, 3)), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n, np.int8))
        _multiview_kernel(np.ascontiguousarray(rays), np.ascontiguousarray(C), np.ascontiguousarray(mask),
                          float(config.min_baseline_m), math.radians(config.min_parallax_deg), float(config.min_depth_m),
                          float(config.max_range_m), float(config.max_rel_sigma), float(sigma_xy),
                          out.p, out.depth, out.range_sigma, out.parallax_rad, out.reason)
        return out
    reason = np.zeros(n, dtype=np.int8)
    finite = np.all(np.isfinite(rays) | ~mask[..., None], (1, 2)) & np.all(np.isfinite(C) | ~mask[..., None], (1, 2))
    reason[~finite] = Reject.NON_FINITE
    m = mask & finite[:, None]
    rays = np.where(m[..., None], rays, 0.0)
    C = np.where(m[..., None], C, 0.0)
    norms = np.linalg.norm(rays, axis=2, keepdims=True)
    r = np.where(norms > 0, rays / np.where(norms > 0, norms, 1.0), 0.0)
    counts = m.sum(1)
    first = np.where(counts > 0, np.argmax(m, 1), 0)
    last = np.where(counts > 0, k - 1 - np.argmax(m[:, ::-1], 1), 0)
    rows = np.arange(n)

    def flag(mask_, code):
        reason[(reason == Reject.OK) & mask_] = code

    flag(counts < 2, Reject.SHORT_BASELINE)
    # longest baseline: farthest centre from the first one
    d_first = np.linalg.norm(C - C[rows, first][:, None, :], axis=2) * m
    baseline = d_first.max(1)
    flag(baseline < config.min_baseline_m, Reject.SHORT_BASELINE)
    cos_par = np.einsum("ni,ni->n", r[rows, first], r[rows, last])
    parallax = np.arccos(np.clip(cos_par, -1.0, 1.0))
    flag(parallax < np.radians(config.min_parallax_deg), Reject.LOW_PARALLAX)
    A = np.eye(3) - np.einsum("nki,nkj->nkij", r, r)
    A = A * m[..., None, None]
    S = A.sum(1)
    b = np.einsum("nkij,nkj->ni", A, C)
    det = np.linalg.det(S)
    good = np.abs(det) > 1e-12
    flag(~good, Reject.LOW_PARALLAX)
    S_safe = np.where(good[:, None, None], S, np.eye(3))
    X = np.linalg.solve(S_safe, b[..., None])[..., 0]
    depths = np.einsum("nki,nki->nk", X[:, None, :] - C, r)
    flag(np.any((depths < config.min_depth_m) & m, 1), Reject.BEHIND_CAMERA)
    rng = np.linalg.norm(X - C[rows, last], axis=1)
    flag(rng > config.max_range_m, Reject.TOO_FAR)
    range_sigma = np.sqrt(2.0) * rng * sigma_xy / np.maximum(np.sin(parallax), 1e-12)
    if sigma_xy > 0:
        flag(range_sigma > config.max_rel_sigma * rng, Reject.TOO_UNCERTAIN)
    ok = reason == Reject.OK
    return TriangulationResult(
        p=np.where(ok[:, None], X, 0.0),
        depth=np.where(ok, rng, 0.0),
        range_sigma=np.where(ok, range_sigma, 0.0),
        parallax_rad=parallax,
        reason=reason,
    )


@njit
def _multiview_kernel(rays, C, mask, min_baseline, min_parallax_rad, min_depth, max_range, max_rel_sigma, sigma_xy,
                      p_out, depth_out, sigma_out, parallax_out, reason_out):
    """:func:`triangulate_multiview` one track at a time (docs/derivations/triangulation.md § Multi-view):
    X = (Σ A_k)⁻¹ Σ A_k C_k, A_k = I − r_k r_kᵀ over the used views, then the gates in the same order,
    the first failing one named.  Outputs (zeros where rejected, parallax always) are written in place."""
    n, k = mask.shape
    for t in range(n):
        # views used: masked in, and the whole track finite (else NON_FINITE, no view used)
        finite = True
        for j in range(k):
            if mask[t, j]:
                for i in range(3):
                    finite &= math.isfinite(rays[t, j, i]) and math.isfinite(C[t, j, i])
        reason = Reject.OK if finite else Reject.NON_FINITE
        count, first, last = 0, 0, 0
        for j in range(k):
            if finite and mask[t, j]:
                if count == 0:
                    first = j
                last = j
                count += 1
        # unit rays r_k, and S = Σ A_k, b = Σ A_k C_k
        S = np.zeros((3, 3))
        b = np.zeros(3)
        r = np.zeros((k, 3))
        baseline = 0.0
        for j in range(k):
            if not (finite and mask[t, j]):
                continue
            nr = math.sqrt(rays[t, j, 0] ** 2 + rays[t, j, 1] ** 2 + rays[t, j, 2] ** 2)
            if nr > 0:
                for i in range(3):
                    r[j, i] = rays[t, j, i] / nr
            for i in range(3):
                for l in range(3):
                    A_il = (1.0 if i == l else 0.0) - r[j, i] * r[j, l]
                    S[i, l] += A_il
                    b[i] += A_il * C[t, j, l]
            d = math.sqrt((C[t, j, 0] - C[t, first, 0]) ** 2 + (C[t, j, 1] - C[t, first, 1]) ** 2
                          + (C[t, j, 2] - C[t, first, 2]) ** 2)
            baseline = max(baseline, d)  # longest baseline, from the first centre
        if reason == Reject.OK and (count < 2 or baseline < min_baseline):
            reason = Reject.SHORT_BASELINE
        cos_par = r[first, 0] * r[last, 0] + r[first, 1] * r[last, 1] + r[first, 2] * r[last, 2]
        parallax = math.acos(min(max(cos_par, -1.0), 1.0))  # first–last rays
        if reason == Reject.OK and parallax < min_parallax_rad:
            reason = Reject.LOW_PARALLAX
        # X = S⁻¹ b by the adjugate (S is 3×3); |det S| ≤ 1e-12: all rays parallel
        c00 = S[1, 1] * S[2, 2] - S[1, 2] * S[2, 1]
        c01 = S[1, 2] * S[2, 0] - S[1, 0] * S[2, 2]
        c02 = S[1, 0] * S[2, 1] - S[1, 1] * S[2, 0]
        det = S[0, 0] * c00 + S[0, 1] * c01 + S[0, 2] * c02
        X = np.zeros(3)
        if abs(det) > 1e-12:
            c10 = S[0, 2] * S[2, 1] - S[0, 1] * S[2, 2]
            c11 = S[0, 0] * S[2, 2] - S[0, 2] * S[2, 0]
            c12 = S[0, 1] * S[2, 0] - S[0, 0] * S[2, 1]
            c20 = S[0, 1] * S[1, 2] - S[0, 2] * S[1, 1]
            c21 = S[0, 2] * S[1, 0] - S[0, 0] * S[1, 2]
            c22 = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
            X[0] = (c00 * b[0] + c10 * b[1] + c20 * b[2]) / det
            X[1] = (c01 * b[0] + c11 * b[1] + c21 * b[2]) / det
            X[2] = (c02 * b[0] + c12 * b[1] + c22 * b[2]) / det
        else:
            if reason == Reject.OK:
                reason = Reject.LOW_PARALLAX
            for i in range(3):  # the reference solves with I in place of S
                X[i] = b[i]
        for j in range(k):  # depth along every used ray
            if finite and mask[t, j] and reason == Reject.OK:
                depth = (X[0] - C[t, j, 0]) * r[j, 0] + (X[1] - C[t, j, 1]) * r[j, 1] + (X[2] - C[t, j, 2]) * r[j, 2]
                if depth < min_depth:
                    reason = Reject.BEHIND_CAMERA
        if count > 0:
            rng = math.sqrt((X[0] - C[t, last, 0]) ** 2 + (X[1] - C[t, last, 1]) ** 2 + (X[2] - C[t, last, 2]) ** 2)
        else:
            rng = math.sqrt(X[0] ** 2 + X[1] ** 2 + X[2] ** 2)
        if reason == Reject.OK and rng > max_range:
            reason = Reject.TOO_FAR
        range_sigma = math.sqrt(2.0) * rng * sigma_xy / max(math.sin(parallax), 1e-12)
        if reason == Reject.OK and sigma_xy > 0 and range_sigma > max_rel_sigma * rng:
            reason = Reject.TOO_UNCERTAIN
        parallax_out[t] = parallax
        reason_out[t] = reason
        if reason == Reject.OK:
            for i in range(3):
                p_out[t, i] = X[i]
            depth_out[t] = rng
            sigma_out[t] = range_sigma


@jit.register_warmup
def warm_up() -> None:
    """Compile (or load) :func:`_multiview_kernel` on one two-view track."""
    rays = np.array([[[0.0, 0.0, 1.0], [-0.1, 0.0, 1.0]]])
    C = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    triangulate_multiview(rays, C, np.ones((1, 2), bool), TriangulationConfig(), sigma_xy=0.002)
