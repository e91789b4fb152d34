"""Where a tracked point should appear in the next frame, from telemetry (seed 004, NCC search window).

Seed 004 notes that the known camera motion shrinks the NCC search area through the epipolar
constraint E = [t]× R: a pixel of the previous frame can only reappear on the image of its
viewing ray in the current camera.  With the previous camera's normalized ray m = (x, y, 1)
(undistorted with ``CameraModel.pixels_to_normalized``), the relative rotation
``R = R_cam_cur_cam_prev = R_world_cam_curᵀ R_world_cam_prev`` and the previous camera centre seen
from the current camera ``t = R_world_cam_curᵀ (p_world_cam_prev − p_world_cam_cur)``, the point
at depth Z (along the previous optical axis) is, in the current camera,

    P(Z) = Z·R m + t   ∝   R m + ρ t,        ρ = 1/Z,

so the inverse depth ρ ∈ [1/depth_max, 1/depth_min] sweeps the epipolar segment: ρ = 0 (infinite
depth) is the pure-rotation image of the ray, ρ = 1/depth_min the closest expected point.  The
segment is sampled at a few ρ (uniform in ρ, each projected with the camera's distortion, so a
distorted curve is covered as well as a straight one); the search window is centred on the
middle of the samples' bounding box and its radius is the farthest sample plus
``base_radius_px`` (attitude / timing / pixel errors), capped at ``max_radius_px``.  When the
cap cuts the segment, the window covers its far end (ρ = 0 side: a static point far away, the common
case; a near point that matters has a filtered depth and a short segment).  A known
depth (from a filter) collapses the segment to a point (± ``depth_sigma``), giving a smaller
window.  Parts of the ray at or behind the current camera are never projected: such points get
a status flag and the largest radius, never NaN.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

from companion.config import require, require_finite
from companion.core import jit as _jit
from companion.core.camera import CameraModel
from companion.core.frames import is_orthonormal
from companion.errors import InputError

#: :attr:`PixelPrediction.status` codes.
PRED_OK = 0
PRED_CAPPED = 1  # the epipolar segment is longer than the cap allows: radius = max_radius_px
PRED_PARTLY_BEHIND = 2  # near part of the depth range is at/behind the current camera: radius = max
PRED_BEHIND = 3  # the whole depth range is behind the current camera: centre = previous pixel, radius = max

_MIN_COS = 1e-3  # a sample needs Z > 1e-3·|P| (within ~89.9° of the optical axis) to be projected


@dataclasses.dataclass(frozen=True)
class PredictionConfig:
    """The ``[prediction]`` table: the depth range expected in the scene and the window sizes."""

    depth_min_m: float = 2.0  # closest expected obstacle (along the optical axis)
    depth_max_m: float = math.inf  # farthest; inf includes the pure-rotation image (ρ = 0)
    base_radius_px: float = 3.0  # added to the epipolar half-length (attitude, timing, pixel noise)
    max_radius_px: float = 32.0  # cap of the search radius
    samples: int = 5  # ρ samples along the segment (>= 2)
    depth_sigma_k: float = 2.0  # a known depth covers depth ± k·σ

    def __post_init__(self) -> None:
        require_finite("depth_min_m", self.depth_min_m, positive=True)
        require(
            isinstance(self.depth_max_m, (int, float)) and not math.isnan(self.depth_max_m) and self.depth_max_m > self.depth_min_m,
            f"depth_max_m must exceed depth_min_m (inf allowed), got {self.depth_max_m!r}",
        )
        require_finite("base_radius_px", self.base_radius_px, nonnegative=True)
        require_finite("max_radius_px", self.max_radius_px, positive=True)
        require(self.max_radius_px >= self.base_radius_px, "max_radius_px must be >= base_radius_px")
        require(isinstance(self.samples, int) and self.samples >= 2, f"samples must be an integer >= 2, got {self.samples!r}")
        require_finite("depth_sigma_k", self.depth_sigma_k, nonnegative=True)


@dataclasses.dataclass
class PixelPrediction:
    """Per point: window centre and radius, the two ends of the epipolar segment and a status."""

    uv: np.ndarray  # (N, 2) centre of the search window
    radius: np.ndarray  # (N,) px
    uv_far: np.ndarray  # (N, 2) image of the far end (ρ_min; the pure-rotation image if depth_max = inf)
    uv_near: np.ndarray  # (N, 2) image of the near end (ρ_max); = uv_far where not projectable
    status: np.ndarray  # (N,) int8, PRED_* codes


def _rotation(name: str, R) -> np.ndarray:
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        raise InputError(f"{name} must have shape (3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise InputError(f"{name} contains NaN or inf")
    if not is_orthonormal(R):
        raise InputError(f"{name} is not a rotation matrix (Rᵀ R ≠ I)")
    return R


def _position(name: str, p) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    if p.shape != (3,):
        raise InputError(f"{name} must have shape (3,), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise InputError(f"{name} contains NaN or inf")
    return p


def _per_point(name: str, a, n: int) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape != (n,):
        raise InputError(f"{name} must be a scalar or have shape ({n},), got {a.shape}")
    if np.any(np.isnan(a)):
        raise InputError(f"{name} contains NaN")
    return a


def predict_pixels_detailed(
    camera: CameraModel,
    uv_prev: np.ndarray,
    R_world_cam_prev: np.ndarray,
    p_world_cam_prev: np.ndarray,
    R_world_cam_cur: np.ndarray,
    p_world_cam_cur: np.ndarray,
    depth_min: float,
    depth_max: float,
    base_radius_px: float,
    depth: np.ndarray | None = None,
    *,
    depth_sigma: np.ndarray | None = None,
    depth_sigma_k: float = 2.0,
    max_radius_px: float = 32.0,
    samples: int = 5,
) -> PixelPrediction:
    """Epipolar prediction of pixels ``uv_prev`` (N, 2) of the previous frame in the current one.

    ``depth_min`` > 0 and ``depth_max`` > ``depth_min`` (may be ``inf``) bound the depth along the
    previous optical axis.  ``depth`` (N,) optional known depths: entries > 0 are used (± k·σ with
    ``depth_sigma``), entries ≤ 0 mean unknown (NaN is refused).  See the module docstring.
    """
    if _jit.ENABLED:  # inputs checked in one kernel; anything it does not pass takes the reference's checks (which raise)
        got = _checked_inputs(uv_prev, R_world_cam_prev, p_world_cam_prev, R_world_cam_cur, p_world_cam_cur, depth_min, depth_max,
                              base_radius_px, depth, depth_sigma, max_radius_px, samples)
        if got is not None:
            uv, Rp, pp, Rc, pc, d, sig = got
            return _predict_kernel(camera, uv, Rp, pp, Rc, pc, float(depth_min), float(depth_max), float(base_radius_px), d, sig,
                                   float(depth_sigma_k), float(max_radius_px), samples)
    uv = np.asarray(uv_prev, dtype=float)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InputError(f"uv_prev must have shape (N, 2), got {uv.shape}")
    bad = ~np.all(np.isfinite(uv), 1)
    if np.any(bad):
        raise InputError(f"uv_prev contains NaN or inf (rows {np.flatnonzero(bad)[:5].tolist()})")
    Rp = _rotation("R_world_cam_prev", R_world_cam_prev)
    Rc = _rotation("R_world_cam_cur", R_world_cam_cur)
    pp = _position("p_world_cam_prev", p_world_cam_prev)
    pc = _position("p_world_cam_cur", p_world_cam_cur)
    for name, v in (("depth_min", depth_min), ("base_radius_px", base_radius_px), ("max_radius_px", max_radius_px)):
        if not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v) or v < 0:
            raise InputError(f"{name} must be a finite number >= 0, got {v!r}")
    if depth_min <= 0:
        raise InputError(f"depth_min must be > 0, got {depth_min!r}")
    if not isinstance(depth_max, (int, float, np.floating, np.integer)) or math.isnan(depth_max) or depth_max <= depth_min:
        raise InputError(f"depth_max must exceed depth_min (inf allowed), got {depth_max!r}")
    if not isinstance(samples, int) or samples < 2:
        raise InputError(f"samples must be an integer >= 2, got {samples!r}")
    n = len(uv)
    d = sig = None
    if depth is not None:
        d = _per_point("depth", depth, n)
        sig = np.zeros(n) if depth_sigma is None else _per_point("depth_sigma", depth_sigma, n)
        if np.any(sig < 0) or not np.all(np.isfinite(sig)):
            raise InputError("depth_sigma must be finite and >= 0")
    if _jit.ENABLED:
        return _predict_kernel(camera, uv, Rp, pp, Rc, pc, float(depth_min), float(depth_max), float(base_radius_px), d, sig,
                               float(depth_sigma_k), float(max_radius_px), samples)
    return _predict_reference(camera, uv, Rp, pp, Rc, pc, depth_min, depth_max, base_radius_px, d, sig, depth_sigma_k,
                              max_radius_px, samples)


def _predict_reference(camera, uv, Rp, pp, Rc, pc, depth_min, depth_max, base_radius_px, d, sig, depth_sigma_k, max_radius_px,
                       samples) -> PixelPrediction:
    """The pure-numpy reference of :func:`predict_pixels_detailed` on checked inputs (``d``, ``sig``:
    the known depths and their σ, or None)."""
    n = len(uv)
    # Inverse-depth interval of every point.
    rho_lo = np.full(n, 0.0 if math.isinf(depth_max) else 1.0 / depth_max)
    rho_hi = np.full(n, 1.0 / depth_min)
    if d is not None:
        known = d > 0
        far = d + depth_sigma_k * sig
        near = np.maximum(d - depth_sigma_k * sig, depth_min * 1e-3)
        with np.errstate(divide="ignore"):
            rho_lo = np.where(known, np.where(np.isinf(far), 0.0, 1.0 / np.where(known, far, 1.0)), rho_lo)
            rho_hi = np.where(known, np.where(np.isinf(near), 0.0, 1.0 / np.where(known, near, 1.0)), rho_hi)

    m = np.concatenate([camera.pixels_to_normalized(uv), np.ones((n, 1))], 1)  # (N, 3), Z = 1
    R_rel = Rc.T @ Rp
    t_rel = Rc.T @ (pp - pc)
    s = np.linspace(0.0, 1.0, samples)
    rho = rho_lo[:, None] + (rho_hi - rho_lo)[:, None] * s[None, :]  # (N, K), far -> near
    q = (m @ R_rel.T)[:, None, :] + rho[:, :, None] * t_rel[None, None, :]  # (N, K, 3)
    z = q[..., 2]
    front = z > _MIN_COS * np.linalg.norm(q, axis=2)
    zs = np.where(front, z, 1.0)
    xy = q[..., :2] / zs[..., None]
    c = camera.config
    lim = 10.0 * (c.width + c.height)
    px = camera.normalized_to_pixels(xy.reshape(-1, 2)).reshape(n, samples, 2)
    px = np.clip(np.where(front[..., None], px, 0.0), -lim, lim)

    any_front = np.any(front, 1)
    all_front = np.all(front, 1)
    hi = np.max(np.where(front[..., None], px, -lim), 1)
    lo = np.min(np.where(front[..., None], px, lim), 1)
    centre = np.where(any_front[:, None], 0.5 * (hi + lo), uv)
    dist = np.linalg.norm(px - centre[:, None, :], axis=2)
    half = np.max(np.where(front, dist, 0.0), 1)
    radius = half + base_radius_px

    status = np.zeros(n, np.int8)
    status[radius > max_radius_px] = PRED_CAPPED
    status[any_front & ~all_front] = PRED_PARTLY_BEHIND
    status[~any_front] = PRED_BEHIND
    radius = np.where(status >= PRED_PARTLY_BEHIND, max_radius_px, np.minimum(radius, max_radius_px))

    first = np.argmax(front, 1)  # farthest projectable sample
    last = samples - 1 - np.argmax(front[:, ::-1], 1)  # nearest projectable sample
    rows = np.arange(n)
    uv_far = np.where(any_front[:, None], px[rows, first], uv)
    uv_near = np.where(any_front[:, None], px[rows, last], uv)
    # A segment longer than the window: cover its far end (static points far away are the common
    # case; a near point that matters was tracked while it approached and has a filtered depth).
    long_seg = any_front & (status != PRED_OK)
    if np.any(long_seg):
        # the point of the curve ~2·(cap − base) px from the far end (image motion ∝ ρ to first
        # order), projected with the distortion; the window is centred between it and the far end
        # length on the undistorted image plane (distortion can fold far off-axis projections)
        norm = c.fx * np.linalg.norm(xy[rows, last] - xy[rows, first], axis=1)
        frac = np.minimum(1.0, 2.0 * (max_radius_px - base_radius_px) / np.where(norm > 0, norm, 1.0))
        rho_far = rho[rows, first]
        rho_s = rho_far + (rho[rows, last] - rho_far) * frac
        q_s = m @ R_rel.T + rho_s[:, None] * t_rel[None, :]
        ok_s = q_s[:, 2] > _MIN_COS * np.linalg.norm(q_s, axis=1)
        px_s = camera.normalized_to_pixels(q_s[:, :2] / np.where(ok_s, q_s[:, 2], 1.0)[:, None])
        px_s = np.clip(px_s, -lim, lim)
        use = long_seg & ok_s
        centre = np.where(use[:, None], 0.5 * (uv_far + px_s), centre)
    return PixelPrediction(uv=centre, radius=radius, uv_far=uv_far, uv_near=uv_near, status=status)


_NUMBER = (int, float, np.floating, np.integer)


def _checked_inputs(uv_prev, R_prev, p_prev, R_cur, p_cur, depth_min, depth_max, base_radius_px, depth, depth_sigma, max_radius_px,
                    samples):
    """The inputs of :func:`predict_pixels_detailed` as arrays when they pass every check the
    reference makes (shapes here, values in :func:`_inputs_ok_k`), else None."""
    uv = np.asarray(uv_prev, dtype=float)
    Rp, Rc = np.asarray(R_prev, dtype=float), np.asarray(R_cur, dtype=float)
    pp, pc = np.asarray(p_prev, dtype=float), np.asarray(p_cur, dtype=float)
    if uv.ndim != 2 or uv.shape[1] != 2 or Rp.shape != (3, 3) or Rc.shape != (3, 3) or pp.shape != (3,) or pc.shape != (3,):
        return None
    for v in (depth_min, base_radius_px, max_radius_px):
        if not isinstance(v, _NUMBER) or not math.isfinite(v) or v < 0:
            return None
    if (depth_min <= 0 or not isinstance(depth_max, _NUMBER) or math.isnan(depth_max) or depth_max <= depth_min
            or not isinstance(samples, int) or samples < 2):
        return None
    n = len(uv)
    d = sig = None
    if depth is not None:
        d = np.asarray(depth, dtype=float)
        d = np.full(n, float(d)) if d.ndim == 0 else d
        sig = np.zeros(n) if depth_sigma is None else np.asarray(depth_sigma, dtype=float)
        sig = np.full(n, float(sig)) if sig.ndim == 0 else sig
        if d.shape != (n,) or sig.shape != (n,):
            return None
    if not _inputs_ok_k(uv, Rp, Rc, pp, pc, _EMPTY if d is None else d, _EMPTY if sig is None else sig):
        return None
    return uv, Rp, pp, Rc, pc, d, sig


@_jit.njit
def _inputs_ok_k(uv, Rp, Rc, pp, pc, d, sig):
    """The reference's value checks at once: finite pixels, poses finite with rotations orthonormal
    (|RᵀR − I| ≤ 1e-6 + 1e-5 δ, :func:`companion.core.frames.is_orthonormal`), depths not NaN, their σ finite ≥ 0."""
    for i in range(uv.shape[0]):
        if not (math.isfinite(uv[i, 0]) and math.isfinite(uv[i, 1])):
            return False
    for R in (Rp, Rc):
        for a in range(3):
            for b in range(3):
                if not math.isfinite(R[a, b]):
                    return False
        for a in range(3):
            for b in range(3):
                rtr = R[0, a] * R[0, b] + R[1, a] * R[1, b] + R[2, a] * R[2, b]
                if not abs(rtr - (1.0 if a == b else 0.0)) <= 1e-6 + (1e-5 if a == b else 0.0):
                    return False
    for a in range(3):
        if not (math.isfinite(pp[a]) and math.isfinite(pc[a])):
            return False
    for i in range(d.size):
        if math.isnan(d[i]) or not (math.isfinite(sig[i]) and sig[i] >= 0):
            return False
    return True


def _predict_kernel(camera, uv, Rp, pp, Rc, pc, depth_min, depth_max, base_radius_px, d, sig, depth_sigma_k, max_radius_px,
                    samples) -> PixelPrediction:
    """:func:`predict_pixels_detailed` through the compiled kernel :func:`_predict_core` (same
    window, segment ends and status as :func:`_predict_reference`, to rounding)."""
    c = camera.config
    n = len(uv)
    distorted, k, s = _constants(c, samples)
    # the undistorted rays of the previous pixels: the camera's own (cv2) with distortion, K⁻¹ uv inline without
    xy = camera.pixels_to_normalized(uv) if distorted and n else _EMPTY2
    known = d is not None
    center, radius, uv_far, uv_near, status = _predict_core(
        uv, xy, distorted, k, float(c.fx), float(c.fy), float(c.cx), float(c.cy), 10.0 * (c.width + c.height), Rc.T @ Rp,
        Rc.T @ (pp - pc), depth_min, depth_max, base_radius_px, d if known else _EMPTY, sig if known else _EMPTY, known,
        depth_sigma_k, max_radius_px, s)
    return PixelPrediction(uv=center, radius=radius, uv_far=uv_far, uv_near=uv_near, status=status)


_EMPTY = np.zeros(0)
_EMPTY2 = np.zeros((0, 2))
_CONSTANTS: dict = {}


def _constants(config, samples: int):
    """Per camera and sample count, computed once: has distortion, the 8 OpenCV coefficients, the ρ fractions."""
    key = (config, samples)
    got = _CONSTANTS.get(key)
    if got is None:
        k = np.zeros(8)
        k[: len(config.distortion)] = config.distortion
        got = _CONSTANTS[key] = (bool(config.has_distortion), k, np.linspace(0.0, 1.0, samples))
        if len(_CONSTANTS) > 16:  # bounded (one camera per process; tests use a few)
            _CONSTANTS.pop(next(iter(_CONSTANTS)))
    return got


@_jit.njit
def _to_pixels(x, y, distorted, k, fx, fy, cx, cy):
    """:meth:`CameraModel.normalized_to_pixels` of one point (OpenCV distortion, then K)."""
    if distorted:
        r2 = x * x + y * y
        radial = (1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))) / (1 + r2 * (k[5] + r2 * (k[6] + r2 * k[7])))
        xd = x * radial + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
        yd = y * radial + k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y
        x, y = xd, yd
    return fx * x + cx, fy * y + cy


@_jit.njit
def _project_samples(a0, a1, a2, rho_lo, rho_hi, s_j, t_rel, distorted, k, fx, fy, cx, cy, lim, rho, front, xs, ys, pu, pv):
    """One ρ sample of every point: ρ, q = R m + ρ t, projectable (q_z > 1e-3 |q|), q_xy / q_z (q_z := 1
    when not) and its pixel, clipped to ± ``lim`` (0 when not projectable).  Written as one loop over the
    points without calls or branches but selects, so that it runs in SIMD lanes."""
    n = a0.size
    t0, t1, t2 = t_rel[0], t_rel[1], t_rel[2]
    for i in range(n):
        r = rho_lo[i] + (rho_hi[i] - rho_lo[i]) * s_j
        q0, q1, q2 = a0[i] + r * t0, a1[i] + r * t1, a2[i] + r * t2
        f = q2 > 1e-3 * math.sqrt(q0 * q0 + q1 * q1 + q2 * q2)
        zs = q2 if f else 1.0
        x, y = q0 / zs, q1 / zs
        rho[i], front[i], xs[i], ys[i] = r, f, x, y
        if distorted:
            r2 = x * x + y * y
            radial = (1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))) / (1 + r2 * (k[5] + r2 * (k[6] + r2 * k[7])))
            xd = x * radial + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
            yd = y * radial + k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y
            x, y = xd, yd
        u, v = fx * x + cx, fy * y + cy
        pu[i] = min(max(u, -lim), lim) if f else 0.0
        pv[i] = min(max(v, -lim), lim) if f else 0.0


@_jit.njit
def _predict_core(uv, xy_in, distorted, k, fx, fy, cx, cy, lim, R_rel, t_rel, depth_min, depth_max, base, d, sig, known_depth,
                  depth_sigma_k, max_r, s):
    """:func:`_predict_reference` per point (module docstring): the inverse-depth interval, the
    segment P(ρ) ∝ R m + ρ t sampled at ``s``, its projectable samples' bounding box, the window
    (centre, radius, capped), the segment ends, and the far-end window of a capped segment."""
    n, K = uv.shape[0], s.size
    center = np.empty((n, 2))
    radius = np.empty(n)
    uv_far = np.empty((n, 2))
    uv_near = np.empty((n, 2))
    status = np.zeros(n, np.int8)
    a0, a1, a2 = np.empty(n), np.empty(n), np.empty(n)
    rho_lo, rho_hi = np.empty(n), np.empty(n)
    rho_lo0 = 0.0 if math.isinf(depth_max) else 1.0 / depth_max
    rho_hi0 = 1.0 / depth_min
    for i in range(n):
        if distorted:
            mx, my = xy_in[i, 0], xy_in[i, 1]
        else:  # CameraModel.pixels_to_normalized without distortion
            mx, my = (uv[i, 0] - cx) / fx, (uv[i, 1] - cy) / fy
        rho_lo[i], rho_hi[i] = rho_lo0, rho_hi0
        if known_depth and d[i] > 0:
            far = d[i] + depth_sigma_k * sig[i]
            near = max(d[i] - depth_sigma_k * sig[i], depth_min * 1e-3)
            rho_lo[i] = 0.0 if math.isinf(far) else 1.0 / far
            rho_hi[i] = 0.0 if math.isinf(near) else 1.0 / near
        # R m (m = (x, y, 1)); each sample adds ρ t
        a0[i] = mx * R_rel[0, 0] + my * R_rel[0, 1] + R_rel[0, 2]
        a1[i] = mx * R_rel[1, 0] + my * R_rel[1, 1] + R_rel[1, 2]
        a2[i] = mx * R_rel[2, 0] + my * R_rel[2, 1] + R_rel[2, 2]
    rho, front = np.empty((K, n)), np.empty((K, n), np.bool_)
    xs, ys, pu, pv = np.empty((K, n)), np.empty((K, n)), np.empty((K, n)), np.empty((K, n))
    for j in range(K):
        _project_samples(a0, a1, a2, rho_lo, rho_hi, s[j], t_rel, distorted, k, fx, fy, cx, cy, lim, rho[j], front[j], xs[j], ys[j],
                         pu[j], pv[j])
    for i in range(n):
        u0, v0 = uv[i, 0], uv[i, 1]
        any_front, all_front = False, True
        hi_u, hi_v, lo_u, lo_v = -lim, -lim, lim, lim
        first, last = -1, -1
        for j in range(K):
            if front[j, i]:
                hi_u, hi_v = max(hi_u, pu[j, i]), max(hi_v, pv[j, i])
                lo_u, lo_v = min(lo_u, pu[j, i]), min(lo_v, pv[j, i])
                any_front = True
                if first < 0:
                    first = j
                last = j
            else:
                all_front = False
        if any_front:
            c_u, c_v = 0.5 * (hi_u + lo_u), 0.5 * (hi_v + lo_v)
        else:
            c_u, c_v = u0, v0
        half2 = 0.0  # the largest squared distance: √ of the max = max of the √ (√ is monotonic, correctly rounded)
        for j in range(K):
            if front[j, i]:
                du, dv = pu[j, i] - c_u, pv[j, i] - c_v
                half2 = max(half2, du * du + dv * dv)
        r = math.sqrt(half2) + base
        st = 0
        if r > max_r:
            st = 1  # PRED_CAPPED
        if any_front and not all_front:
            st = 2  # PRED_PARTLY_BEHIND
        if not any_front:
            st = 3  # PRED_BEHIND
        radius[i] = max_r if st >= 2 else min(r, max_r)
        status[i] = st
        if any_front:
            uv_far[i, 0], uv_far[i, 1] = pu[first, i], pv[first, i]
            uv_near[i, 0], uv_near[i, 1] = pu[last, i], pv[last, i]
        else:
            uv_far[i, 0], uv_far[i, 1] = u0, v0
            uv_near[i, 0], uv_near[i, 1] = u0, v0
        if any_front and st != 0:
            # a segment longer than the window: centre it between the far end and the point ~2·(cap − base) px from it
            dx, dy = xs[last, i] - xs[first, i], ys[last, i] - ys[first, i]
            norm = fx * math.sqrt(dx * dx + dy * dy)
            frac = min(1.0, 2.0 * (max_r - base) / (norm if norm > 0 else 1.0))
            rho_s = rho[first, i] + (rho[last, i] - rho[first, i]) * frac
            q0, q1, q2 = a0[i] + rho_s * t_rel[0], a1[i] + rho_s * t_rel[1], a2[i] + rho_s * t_rel[2]
            if q2 > 1e-3 * math.sqrt(q0 * q0 + q1 * q1 + q2 * q2):
                x_px, y_px = _to_pixels(q0 / q2, q1 / q2, distorted, k, fx, fy, cx, cy)
                c_u = 0.5 * (uv_far[i, 0] + min(max(x_px, -lim), lim))
                c_v = 0.5 * (uv_far[i, 1] + min(max(y_px, -lim), lim))
        center[i, 0], center[i, 1] = c_u, c_v
    return center, radius, uv_far, uv_near, status


def predict_pixels(
    camera: CameraModel,
    uv_prev: np.ndarray,
    R_world_cam_prev: np.ndarray,
    p_world_cam_prev: np.ndarray,
    R_world_cam_cur: np.ndarray,
    p_world_cam_cur: np.ndarray,
    depth_min: float,
    depth_max: float,
    base_radius_px: float,
    depth: np.ndarray | None = None,
    *,
    depth_sigma: np.ndarray | None = None,
    max_radius_px: float = 32.0,
    samples: int = 5,
) -> tuple[np.ndarray, np.ndarray]:
    """Search-window centres (N, 2) and radii (N,) for ``uv_prev`` in the current frame.

    The short form of :func:`predict_pixels_detailed` (which also reports the segment ends and
    a status per point): points behind the current camera get the previous pixel and
    ``max_radius_px``; nothing is ever NaN.
    """
    p = predict_pixels_detailed(
        camera, uv_prev, R_world_cam_prev, p_world_cam_prev, R_world_cam_cur, p_world_cam_cur,
        depth_min, depth_max, base_radius_px, depth,
        depth_sigma=depth_sigma, max_radius_px=max_radius_px, samples=samples,
    )
    return p.uv, p.radius


def bearing_parallax(
    camera: CameraModel,
    uv_prev: np.ndarray,
    R_world_cam_prev: np.ndarray,
    p_world_cam_prev: np.ndarray,
    R_world_cam_cur: np.ndarray,
    p_world_cam_cur: np.ndarray,
) -> np.ndarray:
    """How far each point's image moves per unit inverse depth: |∂uv/∂ρ| at ρ = 0, px·m (N,).

    With the module docstring's ``P ∝ R m + ρ t`` and ``q = R m``, the normalized image
    ``x = (q₀ + ρ t₀)/(q₂ + ρ t₂)`` has ``∂x/∂ρ = (t₀ q₂ − q₀ t₂)/q₂²`` at ρ = 0 (the same with
    index 1 for y); scaled by the focal lengths it is the bearing parallax a point there can give
    between the two frames, per m⁻¹ of inverse depth (lens distortion ignored: it only rescales).
    It vanishes at the focus of expansion, where bearings alone cannot range a point and the
    patch's scale change (looming, DESIGN §7) must: the tracker spends its scale-fit budget on the
    smallest values first (``[ncc] scale_order = "parallax"``).  Rays at or behind the current
    camera get +inf (last).
    """
    uv = np.asarray(uv_prev, float).reshape(-1, 2)
    n = len(uv)
    if n == 0:
        return np.zeros(0)
    Rp, Rc = _rotation("R_world_cam_prev", R_world_cam_prev), _rotation("R_world_cam_cur", R_world_cam_cur)
    pp, pc = _position("p_world_cam_prev", p_world_cam_prev), _position("p_world_cam_cur", p_world_cam_cur)
    m = np.column_stack([camera.pixels_to_normalized(uv), np.ones(n)])
    q = m @ (Rc.T @ Rp).T
    t = Rc.T @ (pp - pc)
    out = np.full(n, np.inf)
    front = q[:, 2] > _MIN_COS * np.linalg.norm(q, axis=1)
    qz = q[front, 2]
    dx = (t[0] * qz - q[front, 0] * t[2]) / qz**2
    dy = (t[1] * qz - q[front, 1] * t[2]) / qz**2
    c = camera.config
    out[front] = np.hypot(c.fx * dx, c.fy * dy)
    return out


def make_track_predictor(
    camera: CameraModel,
    config: PredictionConfig,
    pose_prev: tuple[np.ndarray, np.ndarray],
    pose_cur: tuple[np.ndarray, np.ndarray],
    depth_of: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None]] | None = None,
    with_parallax: bool = False,
) -> Callable[[np.ndarray, np.ndarray], tuple]:
    """A ``predict`` callable for :meth:`companion.core.tracks.TrackManager.step`.

    ``pose_prev`` / ``pose_cur`` are ``(R_world_cam, p_world_cam)`` of the previous and current
    frames; ``depth_of(ids)`` optionally returns ``(depth, depth_sigma)`` per track id from a
    filter (depth ≤ 0 where unknown).  The callable returns ``(uv_pred, radius)``, and with
    ``with_parallax`` also :func:`bearing_parallax` as a third element (the tracker's order of scale fits,
    ``[ncc] scale_order = "parallax"``; not computed otherwise).
    """

    def predict(uv_prev: np.ndarray, ids: np.ndarray) -> tuple:
        depth = sigma = None
        if depth_of is not None:
            depth, sigma = depth_of(ids)
        p = predict_pixels_detailed(
            camera, uv_prev, pose_prev[0], pose_prev[1], pose_cur[0], pose_cur[1],
            config.depth_min_m, config.depth_max_m, config.base_radius_px, depth,
            depth_sigma=sigma, depth_sigma_k=config.depth_sigma_k,
            max_radius_px=config.max_radius_px, samples=config.samples,
        )
        if not with_parallax:
            return p.uv, p.radius
        return p.uv, p.radius, bearing_parallax(camera, uv_prev, pose_prev[0], pose_prev[1], pose_cur[0], pose_cur[1])

    return predict


@_jit.register_warmup
def _warm_up() -> None:
    """Compile the prediction kernel (pinhole and distorted cameras, with and without known depths)."""
    from companion.core.camera import CameraConfig

    R = np.eye(3)
    uv = np.array([[100.0, 80.0], [10.0, 10.0]])
    for dist in ((0.0,) * 5, (-0.2, 0.05, 0.001, 0.001, 0.0)):
        cam = CameraModel(CameraConfig(width=320, height=240, fx=277.0, fy=277.0, cx=159.5, cy=119.5, distortion=dist))
        predict_pixels_detailed(cam, uv, R, np.zeros(3), R, np.array([0.0, 0.1, 1.0]), 2.0, math.inf, 3.0)
        predict_pixels_detailed(cam, uv, R, np.zeros(3), R, np.array([0.0, 0.1, 1.0]), 2.0, 50.0, 3.0, np.array([5.0, -1.0]),
                                depth_sigma=np.array([0.5, 0.0]))
