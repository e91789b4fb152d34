"""Anchored inverse-depth EKF, one 3-state filter per landmark (docs/derivations/ekf_anchored.md).

Parametrization (Civera et al., ref. [4] of seed 004), with the anchor pose taken from telemetry
instead of being estimated:

    x = (θ, φ, ρ),   m(θ, φ) = (cos φ sin θ, −sin φ, cos φ cos θ)   (in the anchor camera frame)
    p_world = p_world_camA + R_world_camA · m(θ, φ) / ρ

θ is the azimuth (to the right), φ the elevation (up) of the ray seen from the anchor camera and
ρ = 1/d the inverse distance along it.  The landmark is static, so the prediction is the identity
(F = I, Q = 0) and all the work is in the update.

Measurement (undistorted normalized coordinates in the current camera, pose R_world_cam, C):

    h_c = ρ · R_cam_world (p_world_camA − C) + R_cam_camA · m(θ, φ) = ρ · t + R_ca · m
    z   = (h_c,x / h_c,z,  h_c,y / h_c,z)

h_c is the camera-frame point scaled by ρ, so the model stays finite at infinity (ρ = 0).  The
analytic Jacobian is H = ∂z/∂h_c · [R_ca ∂m/∂θ, R_ca ∂m/∂φ, t] with
∂z/∂h = [[1/h_z, 0, −h_x/h_z²], [0, 1/h_z, −h_y/h_z²]],
∂m/∂θ = (cos φ cos θ, 0, −cos φ sin θ), ∂m/∂φ = (−sin φ sin θ, −cos φ, −sin φ cos θ).

Attitude drift (seed 004 gyro model; docs/derivations/ekf_anchored.md).  Telemetry attitude drifts (gyro bias), and that error is
correlated in time, so inflating R cannot keep the filter honest.  When ``attitude_drift_deg_s`` > 0
each filter carries three more states: the gyro bias b (camera axes, rad/s, prior σ =
attitude_drift_deg_s).  A body-fixed bias makes the reported attitude drift in the world frame at
the rate R_world_cam(τ)·b, so between anchor and now the true rotation is the reported one
followed by Exp(w), w = D·b with D = ∫ R_world_cam dτ ≈ Δt·(R_world_camA + R_world_cam)/2
(trapezoid over the landmark's life, Δt = t − t_anchor):

    h_c = R_cam_world · Exp(w) · g,    g = ρ (p_world_camA − C) + R_world_camA · m(θ, φ),

with ∂h_c/∂b = −R_cam_world [Exp(w) g]× J_l(w) D (J_l the left Jacobian of SO(3)).
Each landmark estimates its own copy of b from its own pixels only, so every filter remains a
proper posterior of its own measurements (the bank does not pool b across landmarks).  Without
drift (n = 3 states) the same equations hold with b = 0.

Update: iterated EKF (Gauss–Newton on the prior + measurement cost, ``iterations`` relinearizations;
1 = the plain EKF), χ² innovation gate on the first linearization; covariance in the standard form
P = (I − K H) P₀ at the last linearization, symmetrized (the looming update below uses the Joseph form).
Measurement noise R = (σ_px/f)² + σ_att² (white attitude noise of each telemetry sample)
+ 2 (ρ σ_p)² (the telemetry's position error at the anchor and now, seen from the landmark at
inverse depth ρ; treated as white, an approximation for GPS-like correlated error).

The numpy code here is the *reference*: every operation is batched over landmarks, arrays of shape
(N, 3), (N, 3, 3), no loop per landmark.  When compiled kernels are on (:mod:`companion.core.jit`)
the pixel and looming updates (with their bookkeeping) and :meth:`~AnchoredInverseDepthEKF.estimates`
run instead as one loop over landmarks in :mod:`companion.core.ekf_anchored_kernels`, the same
equations to float rounding (tests/test_ekf_anchored_kernels.py compares the two).

Looming (docs/derivations/looming.md).  A small surface patch facing the camera images
with a size ∝ 1/Z, Z its depth along the optical axis, so the patch scale change between the
previous frame (pose R_world_cam', C', time t') and the current one (R_world_cam, C, t) measured
by the matcher, s = size now / size before, is the depth ratio s = Z'/Z — also on the optical axis,
where the bearings (and so the pixel measurement above) carry no range.  With the same h_c as the
pixel model evaluated at each pose (ρ scales both depths and cancels in the ratio, the camera
positions and attitudes come from telemetry):

    Z = h_z / ρ,   h_z = e₃ᵀ R_cam_world Exp(w) (ρ (p_world_camA − C) + R_world_camA m(θ, φ))
    z_s = h_s(x) = h_z' / h_z                     (h_z' the same at the previous pose, w' = D' b)

a scalar measurement of x.  With ∂h_z/∂x the third row of [∂h_c/∂(θ, φ, ρ) | ∂h_c/∂b] above
(evaluated at each pose), the quotient rule gives the analytic Jacobian

    H_s = (∂h_z'/∂x − h_s ∂h_z/∂x) / h_z          (1 × n)

(for a point on the axis, h_s = (1 − ρ ζ')/(1 − ρ ζ) with ζ the distance travelled towards it
since the anchor: ∂h_s/∂ρ ≈ ζ − ζ' = the distance travelled between the two frames, so a scale
σ of 0.005 over a 0.13 m step gives σ_ρ ≈ 0.04 per frame, then accumulates).  The model is exact
for a patch parallel to the image plane; a tilted patch or the camera's rotation between two
frames changes the scale by O(angle²) more, which the noise floor covers.  Noise
R_s = σ_s² + σ_floor² (σ_s from the matcher's Gauss–Newton covariance, ``looming_sigma_floor``);
χ² (1 dof) gate ``looming_gate_probability``; update (iterated ``looming_iterations`` times: one
step suffices for a measurement this weak per frame) in Joseph form
P = (I − K H) P (I − K H)ᵀ + K R Kᵀ, batched over landmarks.  Input that cannot be a scale is
not an error in flight: NaN (the matcher could not measure it) is skipped and counted
(``LOOM_NAN``), a non-positive or non-finite scale or σ is refused (``LOOM_NONPOSITIVE``).
"""

from __future__ import annotations

import dataclasses
import math
import statistics

import numpy as np

from companion.config import require, require_finite
from companion.core import jit
from companion.core.frames import SKEW_MAP
from companion.core.idbank import lookup, rows_or_raise
from companion.errors import InputError


@dataclasses.dataclass(frozen=True)
class AnchoredEKFConfig:
    """The ``[ekf_anchored]`` table."""

    sigma_px: float = 1.0  # pixel measurement noise σ
    gate_probability: float = 0.999  # χ² (2 dof) innovation gate
    iterations: int = 3  # iterated-EKF relinearizations per update (1 = plain EKF)
    attitude_sigma_deg: float = 0.0  # white attitude error of each telemetry pose
    attitude_drift_deg_s: float = 0.03  # σ of the gyro bias per axis (°/s); > 0 adds 3 bias states
    position_sigma_m: float = 0.1  # σ of the telemetry's camera position error per axis (m), seen as ρ·σ at the landmark
    converged_rel_sigma: float = 0.1  # converged when range σ / range is below this
    min_updates: int = 3  # ... and at least this many accepted updates
    max_consecutive_rejects: int = 5  # then the landmark is flagged diverged
    max_range_m: float = 10000.0  # ranges beyond this are reported as this value
    nis_window: float = 10.0  # updates averaged (exponentially) in each landmark's mean NIS
    max_mean_nis: float = 4.0  # mean NIS above this flags the landmark diverged (not a static point); 0 = off
    looming: bool = True  # fuse the matcher's patch scale change (looming, docs/derivations/looming.md) when given
    looming_sigma_floor: float = 0.003  # floor added (in quadrature) to the matcher's scale σ
    looming_gate_probability: float = 0.999  # χ² (1 dof) gate of the looming innovation
    looming_iterations: int = 1  # iterated-EKF relinearizations of the looming update (1 = plain EKF)

    def __post_init__(self) -> None:
        require_finite("sigma_px", self.sigma_px, positive=True)
        require_finite("gate_probability", self.gate_probability)
        require(0.5 < self.gate_probability < 1.0, f"gate_probability must be in (0.5, 1), got {self.gate_probability}")
        require(isinstance(self.iterations, int) and 1 <= self.iterations <= 20, "iterations must be an integer in 1..20")
        require_finite("attitude_sigma_deg", self.attitude_sigma_deg, nonnegative=True)
        require_finite("attitude_drift_deg_s", self.attitude_drift_deg_s, nonnegative=True)
        require_finite("converged_rel_sigma", self.converged_rel_sigma, positive=True)
        require(isinstance(self.min_updates, int) and self.min_updates >= 0, "min_updates must be an integer >= 0")
        require(isinstance(self.max_consecutive_rejects, int) and self.max_consecutive_rejects >= 1, "max_consecutive_rejects must be >= 1")
        require_finite("max_range_m", self.max_range_m, positive=True)
        require_finite("position_sigma_m", self.position_sigma_m, nonnegative=True)
        require_finite("nis_window", self.nis_window)
        require(self.nis_window >= 1.0, f"nis_window must be >= 1, got {self.nis_window}")
        require_finite("max_mean_nis", self.max_mean_nis, nonnegative=True)
        require(isinstance(self.looming, bool), f"looming must be true or false, got {self.looming!r}")
        require_finite("looming_sigma_floor", self.looming_sigma_floor, positive=True)
        require_finite("looming_gate_probability", self.looming_gate_probability)
        require(isinstance(self.looming_iterations, int) and 1 <= self.looming_iterations <= 20,
                "looming_iterations must be an integer in 1..20")
        require(
            0.5 < self.looming_gate_probability < 1.0,
            f"looming_gate_probability must be in (0.5, 1), got {self.looming_gate_probability}",
        )

    @property
    def gate_threshold(self) -> float:
        """χ²₂ quantile: for 2 dof the CDF is 1 − exp(−x/2), so the quantile is −2 ln(1 − p)."""
        return -2.0 * math.log(1.0 - self.gate_probability)

    @property
    def looming_gate_threshold(self) -> float:
        """χ²₁ quantile: (Φ⁻¹((1 + p)/2))²."""
        return statistics.NormalDist().inv_cdf(0.5 * (1.0 + self.looming_gate_probability)) ** 2


# -- reasons an update was not applied --------------------------------------------------------
UPDATED = 0
GATED = 1  # innovation failed the χ² gate
BEHIND = 2  # the predicted point is behind the current camera


LOOM_NAN = 3  # looming: the scale is NaN (not measured): skipped
LOOM_NONPOSITIVE = 4  # looming: scale ≤ 0, ±inf, or its σ not finite and > 0: refused

UPDATE_REASON_NAMES = {UPDATED: "updated", GATED: "gated", BEHIND: "behind", LOOM_NAN: "nan_scale", LOOM_NONPOSITIVE: "nonpositive_scale"}


@dataclasses.dataclass
class UpdateResult:
    ids: np.ndarray
    accepted: np.ndarray  # (M,) bool
    nis: np.ndarray  # (M,) normalized innovation squared (first linearization)
    reason: np.ndarray  # (M,) UPDATED / GATED / BEHIND (looming also LOOM_NAN / LOOM_NONPOSITIVE)


def _no_update(ids: np.ndarray) -> UpdateResult:
    """The result of an update with no landmarks."""
    return UpdateResult(ids, np.zeros(0, bool), np.zeros(0), np.zeros(0, np.int8))


@dataclasses.dataclass
class LandmarkEstimates:
    """Per landmark, relative to a given camera: everything a consumer needs, always finite."""

    ids: np.ndarray
    p_world: np.ndarray  # (N, 3); for ρ ≤ 1/max_range the point is placed at max_range along the ray
    range: np.ndarray  # (N,) distance from the camera centre, ≤ max_range_m
    range_sigma: np.ndarray  # (N,) first-order σ of range, ≤ max_range_m
    inv_depth: np.ndarray  # (N,) ρ
    inv_depth_sigma: np.ndarray  # (N,)
    converged: np.ndarray  # (N,) bool
    valid: np.ndarray  # (N,) bool: not diverged, ρ not significantly negative


def ray(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """m(θ, φ) of docs/derivations/ekf_anchored.md, (N, 3)."""
    return _ray_columns(theta, phi)[:, :, 0]


def ray_jacobian(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """[∂m/∂θ, ∂m/∂φ] as (N, 3, 2)."""
    return _ray_columns(theta, phi)[:, :, 1:]


def angles_of(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(θ, φ) of direction vectors v (N, 3) in a camera frame: inverse of :func:`ray`."""
    theta = np.arctan2(v[..., 0], v[..., 2])
    phi = np.arctan2(-v[..., 1], np.hypot(v[..., 0], v[..., 2]))
    return theta, phi


def inverse_depth_state(p_world: np.ndarray, R_world_camA: np.ndarray, p_world_camA: np.ndarray) -> np.ndarray:
    """True state (θ, φ, ρ) of world points relative to anchors (for NEES and tests), (N, 3)."""
    v = np.einsum("...ji,...j->...i", R_world_camA, np.asarray(p_world, float) - p_world_camA)
    th, ph = angles_of(v)
    return np.stack([th, ph, 1.0 / np.linalg.norm(v, axis=-1)], -1)


def _ray_products(angles: np.ndarray) -> np.ndarray:
    """(N, 6) products (cos φ cos θ, cos φ sin θ, cos φ, sin φ cos θ, sin φ sin θ, sin φ) of angles
    (θ, φ) (N, 2): every entry of m(θ, φ), ∂m/∂θ and ∂m/∂φ is one of them up to sign."""
    f = np.empty((len(angles), 2, 3))  # rows θ, φ; columns cos, sin, 1
    np.cos(angles, out=f[:, :, 0])
    np.sin(angles, out=f[:, :, 1])
    f[:, :, 2] = 1.0
    return (f[:, 1, :2, None] * f[:, 0, None, :]).reshape(-1, 6)


def _ray_basis() -> np.ndarray:
    """(6, 3, 4): [m, ∂m/∂θ, ∂m/∂φ, 0] (columns, docs/derivations/ekf_anchored.md) as a linear map of :func:`_ray_products`."""
    M = np.zeros((6, 3, 4))
    cc, cs, c, sc, ss, s = range(6)  # cos φ cos θ, cos φ sin θ, cos φ, sin φ cos θ, sin φ sin θ, sin φ
    M[cs, 0, 0], M[s, 1, 0], M[cc, 2, 0] = 1, -1, 1  # m = (cos φ sin θ, −sin φ, cos φ cos θ)
    M[cc, 0, 1], M[cs, 2, 1] = 1, -1  # ∂m/∂θ = (cos φ cos θ, 0, −cos φ sin θ)
    M[ss, 0, 2], M[c, 1, 2], M[sc, 2, 2] = -1, -1, -1  # ∂m/∂φ = (−sin φ sin θ, −cos φ, −sin φ cos θ)
    return M


_RAY_FROM_PRODUCTS = _ray_basis()
_RAY_FROM_PRODUCTS_L = np.ascontiguousarray(_RAY_FROM_PRODUCTS.transpose(1, 0, 2)).reshape(3, 24)  # [l, (k, c)]
_RAY_COLUMNS = np.ascontiguousarray(_RAY_FROM_PRODUCTS[:, :, :3]).reshape(6, 9)
_I3 = np.eye(3)


def _ray_columns(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """[m, ∂m/∂θ, ∂m/∂φ] (N, 3, 3), columns, at angles (N,): :func:`_ray_basis` applied to the products."""
    P = _ray_products(np.stack([np.ravel(theta), np.ravel(phi)], -1))
    return (P @ _RAY_COLUMNS).reshape(-1, 3, 3)


def _exp_and_left_jacobian(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exp(φ) and the left Jacobian of SO(3) (N, 3, 3) each:

    Exp(φ) = I + sin θ/θ K + (1 − cos θ)/θ² K²,   J_l(φ) = I + (1 − cos θ)/θ² K + (θ − sin θ)/θ³ K²,

    K = [φ]×, K² = φ φᵀ − θ² I, θ = |φ|, with the Taylor series of the three coefficients below θ = 1e-6.
    """
    n = len(phi)
    th2 = np.einsum("ni,ni->n", phi, phi)
    th = np.sqrt(th2)
    small = th < 1e-6
    n_small = np.count_nonzero(small)
    if n_small == n:  # every angle small (e.g. all biases still at their zero prior)
        a, b, d = 1.0 - th2 / 6, 0.5 - th2 / 24, 1.0 / 6 - th2 / 120
    else:
        ths = np.where(small, 1.0, th) if n_small else th
        s, c = np.sin(ths), np.cos(ths)
        ths2 = ths * ths
        a, b, d = s / ths, (1 - c) / ths2, (ths - s) / (ths2 * ths)
        if n_small:
            a = np.where(small, 1.0 - th2 / 6, a)
            b = np.where(small, 0.5 - th2 / 24, b)
            d = np.where(small, 1.0 / 6 - th2 / 120, d)
    K = (phi @ SKEW_MAP).reshape(n, 3, 3)
    K2 = phi[:, :, None] * phi[:, None, :] - th2[:, None, None] * _I3
    a, b, d = a[:, None, None], b[:, None, None], d[:, None, None]
    return a * K + b * K2 + _I3, b * K + d * K2 + _I3


def _ray_map(R_world_camA: np.ndarray) -> np.ndarray:
    """(N, 6, 12): products of :func:`_ray_products` → R_world_camA [m, ∂m/∂θ, ∂m/∂φ, 0] (flattened)."""
    n = len(R_world_camA)
    RM = (R_world_camA @ _RAY_FROM_PRODUCTS_L).reshape(n, 3, 6, 4)  # [n, i, k, c] = Σ_l R[n, i, l] M[k, l, c]
    return np.ascontiguousarray(RM.transpose(0, 2, 1, 3)).reshape(n, 6, 12)


def _predict(x, ray_map, a, R_cam_world, D):
    """h_c (N,3), z (N,2) and H (N,2,n) of the module docstring at states x (N,n).

    ``ray_map`` = :func:`_ray_map` of the anchor rotations, ``a`` = p_world_camA − C (N,3),
    ``R_cam_world`` (3,3) or (N,3,3) and the drift integral ``D`` (N,3,3; None without drift
    states): the parts that stay fixed over the iterated-EKF relinearizations, computed once per
    update by the caller.
    """
    V = _hc_jacobian(x, ray_map, a, R_cam_world, D)
    h = V[:, :, 0]
    hz = h[:, 2]
    inv_hz = 1.0 / np.where(np.abs(hz) > 1e-12, hz, 1e-12)
    z = h[:, :2] * inv_hz[:, None]
    # ∂z/∂h = (1/h_z) [I₂ | −z], applied row-wise without forming it
    H = (V[:, :2, 1:] - z[:, :, None] * V[:, 2:3, 1:]) * inv_hz[:, None, None]
    return h, z, H


def _hc_jacobian(x, ray_map, a, R_cam_world, D):
    """[h_c | ∂h_c/∂x] (N, 3, 1+n) at states x (N,n); arguments as in :func:`_predict`."""
    n = len(x)
    # W = [g | ∂g/∂(θ, φ, ρ)] with g = ρ a + R_world_camA m, ∂g/∂θ = R ∂m/∂θ, ∂g/∂φ = R ∂m/∂φ, ∂g/∂ρ = a
    W = (_ray_products(x[:, :2])[:, None, :] @ ray_map).reshape(n, 3, 4)
    W[:, :, 3] = a
    W[:, :, 0] += x[:, 2:3] * a
    if D is not None:  # [Exp(w) g | Exp(w) ∂g/∂(θ, φ, ρ) | −[Exp(w) g]× J_l(w) D]
        E, J_l = _exp_and_left_jacobian((D @ x[:, 3:, None])[:, :, 0])
        W7 = np.empty((n, 3, 7))
        np.matmul(E, W, out=W7[:, :, :4])
        np.matmul((W7[:, :, 0] @ -SKEW_MAP).reshape(n, 3, 3), J_l @ D, out=W7[:, :, 4:])
        W = W7
    if R_cam_world.ndim == 2:  # one pose for all: a single (3,3)·(3, N·k) product
        k = W.shape[2]
        V = (R_cam_world @ W.transpose(1, 0, 2).reshape(3, n * k)).reshape(3, n, k).transpose(1, 0, 2)
    else:
        V = R_cam_world @ W  # [h | ∂h/∂x]
    return V


def _looming_args(RA, pA, tA, Rp, Cp, t_prev, Rc, C, t, drift: bool):
    """The fixed parts of :func:`_looming_predict` for N landmarks, both poses stacked (2N rows):
    ray map, p_world_camA − C, R_cam_world and the drift integral D (None without drift)."""
    n = len(RA)
    ray_map = _ray_map(RA)
    R2 = np.concatenate([np.broadcast_to(np.swapaxes(Rp, -1, -2), (n, 3, 3)), np.broadcast_to(np.swapaxes(Rc, -1, -2), (n, 3, 3))])
    a2 = np.concatenate([np.broadcast_to(pA - Cp, (n, 3)), np.broadcast_to(pA - C, (n, 3))])
    D2 = None
    if drift:
        D2 = np.concatenate([(0.5 * (t_prev - tA))[:, None, None] * (RA + Rp), (0.5 * (t - tA))[:, None, None] * (RA + Rc)])
    return np.concatenate([ray_map, ray_map]), a2, R2, D2


def _looming_predict(x, ray_map2, a2, R2, D2):
    """h_z' (N,), h_z (N,), h_s = h_z'/h_z (N,) and H_s (N,n) of the looming model (module docstring)
    at states x (N,n); the other arguments from :func:`_looming_args` (one evaluation for both poses)."""
    n = len(x)
    V = _hc_jacobian(np.concatenate([x, x]), ray_map2, a2, R2, D2)[:, 2, :]
    Vp, Vn = V[:n], V[n:]
    hz_prev, hz_now = Vp[:, 0], Vn[:, 0]
    inv = 1.0 / np.where(np.abs(hz_now) > 1e-12, hz_now, 1e-12)
    hs = hz_prev * inv
    Hs = (Vp[:, 1:] - hs[:, None] * Vn[:, 1:]) * inv[:, None]
    return hz_prev, hz_now, hs, Hs


def _inv2(S: np.ndarray) -> np.ndarray:
    """Inverse of 2×2 matrices (N, 2, 2): adjugate [[d, −b], [−c, a]] over the determinant."""
    det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
    return np.swapaxes(S[:, ::-1, ::-1], 1, 2) * _ADJ_SIGN / det[:, None, None]


_ADJ_SIGN = np.array([[1.0, -1.0], [-1.0, 1.0]])


def _require_distinct(ids: np.ndarray, what: str) -> None:
    """One observation per landmark and call: InputError naming repeated ids."""
    if len(ids) > 1:
        s = np.sort(ids)
        dup = s[1:][s[1:] == s[:-1]]
        if len(dup):
            raise InputError(f"{what}: landmark ids listed more than once {np.unique(dup)[:10].tolist()}")


def _as_batch(name: str, a, n: int, tail: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.shape == tail:
        a = np.broadcast_to(a, (n,) + tail)
    if a.shape != (n,) + tail:
        raise InputError(f"{name} must have shape {tail} or {(n,) + tail}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} contains NaN or inf")
    return a


def _shared_or_batch(name: str, a, n: int, tail: tuple[int, ...]) -> np.ndarray:
    """Like :func:`_as_batch` but keeps a shared pose unbroadcast (cheaper batched products)."""
    a = np.asarray(a, dtype=float)
    if a.shape == tail:
        if not np.all(np.isfinite(a)):
            raise InputError(f"{name} contains NaN or inf")
        return a
    return _as_batch(name, a, n, tail)


class AnchoredInverseDepthEKF:
    """A bank of independent anchored inverse-depth filters, addressed by landmark id."""

    def __init__(self, config: AnchoredEKFConfig, fx: float, fy: float):
        require_finite("fx", fx, positive=True)
        require_finite("fy", fy, positive=True)
        self.config = config
        self.sigma_xy = np.array([config.sigma_px / fx, config.sigma_px / fy])
        self.ids = np.zeros(0, dtype=np.int64)
        #: state size: (θ, φ, ρ), plus the drift rate β when attitude drift is modelled
        self.n = 6 if config.attitude_drift_deg_s > 0 else 3
        self.x = np.zeros((0, self.n))
        self.P = np.zeros((0, self.n, self.n))
        self.R_world_camA = np.zeros((0, 3, 3))
        self.p_world_camA = np.zeros((0, 3))
        self.t_anchor = np.zeros(0)
        self.n_updates = np.zeros(0, dtype=np.int64)
        self.n_rejects = np.zeros(0, dtype=np.int64)  # consecutive
        self.diverged = np.zeros(0, dtype=bool)
        self.nis_avg = np.zeros(0)  # mean NIS over the last ~nis_window measurements (consistency with a static point)
        self.nis_count = np.zeros(0, dtype=np.int64)  # measurements in nis_avg
        self.n_looming = np.zeros(0, dtype=np.int64)  # accepted looming (scale) updates
        #: the pixel kernels' constants: (σ_px/f)² + σ_att² (2,), σ_p, χ²₂ gate, iterations, reject limit,
        #: NIS window, mean-NIS limit (§ Measurement noise, § Update, § Bookkeeping)
        self._kernel_constants = (
            self.sigma_xy**2 + np.radians(config.attitude_sigma_deg) ** 2, float(config.position_sigma_m), config.gate_threshold,
            config.iterations, config.max_consecutive_rejects, float(config.nis_window), float(config.max_mean_nis))

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def invalid(self) -> np.ndarray:
        """(N,) bool: inverse depth significantly negative (a track inconsistent with a static point)."""
        return self.x[:, 2] < -3.0 * np.sqrt(np.maximum(self.P[:, 2, 2], 0.0))

    # -- bookkeeping ----------------------------------------------------------------------------
    def index_of(self, ids) -> np.ndarray:
        """Row of each id; InputError naming the ids that are not in the bank."""
        return rows_or_raise(self.ids, ids, "anchored EKF")

    def contains(self, ids) -> np.ndarray:
        return lookup(self.ids, ids)[0]

    def add(self, ids, xy_anchor, R_world_cam, p_world_cam, t_anchor, inv_depth, inv_depth_sigma) -> None:
        """Start filters anchored at the given camera pose(s) and first observation(s).

        ``xy_anchor``: (M, 2) undistorted normalized coordinates of the landmark in the anchor image.
        ``inv_depth`` / ``inv_depth_sigma``: (M,) or scalar prior on ρ (from triangulation, or the
        estimator's wide prior that includes ρ = 0).
        """
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        m = len(ids)
        if m == 0:
            return
        if len(np.unique(ids)) != m or np.any(self.contains(ids)):
            raise InputError("add: landmark ids must be new and unique")
        xy = _as_batch("xy_anchor", xy_anchor, m, (2,))
        R = _as_batch("R_world_cam", R_world_cam, m, (3, 3))
        p = _as_batch("p_world_cam", p_world_cam, m, (3,))
        t = _as_batch("t_anchor", np.asarray(t_anchor, float).reshape(-1) if np.ndim(t_anchor) else t_anchor, m, ())
        cfg = self.config
        rho = _as_batch("inv_depth", inv_depth, m, ())
        srho = _as_batch("inv_depth_sigma", inv_depth_sigma, m, ())
        if np.any(srho <= 0):
            raise InputError("inv_depth_sigma must be > 0")
        x_, y_ = xy[:, 0], xy[:, 1]
        theta, phi = angles_of(np.stack([x_, y_, np.ones(m)], 1))
        # Jacobian of (θ, φ) w.r.t. (x, y): θ = atan(x), φ = atan2(−y, √(1+x²))
        r2 = 1 + x_**2
        J = np.zeros((m, 2, 2))
        J[:, 0, 0] = 1.0 / r2
        J[:, 1, 0] = y_ * x_ / (np.sqrt(r2) * (r2 + y_**2))
        J[:, 1, 1] = -np.sqrt(r2) / (r2 + y_**2)
        Rxy = np.diag(self.sigma_xy**2)
        P0 = np.zeros((m, self.n, self.n))
        P0[:, :2, :2] = J @ Rxy @ np.swapaxes(J, 1, 2)
        P0[:, 2, 2] = srho**2
        x0 = np.stack([theta, phi, rho], 1)
        if self.n == 6:
            sb = np.radians(cfg.attitude_drift_deg_s)
            P0[:, 3:, 3:] = sb**2 * np.eye(3)
            x0 = np.concatenate([x0, np.zeros((m, 3))], 1)
        zi = np.zeros(m, np.int64)
        self._insert(dict(ids=ids, x=x0, P=P0, R_world_camA=R, p_world_camA=p, t_anchor=t, n_updates=zi,
                          n_rejects=zi, diverged=np.zeros(m, bool), nis_avg=np.zeros(m), nis_count=zi, n_looming=zi))

    #: per-landmark arrays, all aligned with ``ids`` (kept sorted ascending)
    _FIELDS = ("ids", "x", "P", "R_world_camA", "p_world_camA", "t_anchor", "n_updates", "n_rejects", "diverged", "nis_avg",
               "nis_count", "n_looming")

    def _insert(self, rows: dict) -> None:
        """Merge new landmarks (every field of :data:`_FIELDS`, ids not yet present) keeping ids sorted."""
        order = np.argsort(np.concatenate([self.ids, rows["ids"]]), kind="stable")
        for name in self._FIELDS:
            setattr(self, name, np.concatenate([getattr(self, name), rows[name]])[order])

    def remove(self, ids) -> None:
        keep = np.ones(len(self.ids), bool)
        keep[self.index_of(ids)] = False
        for name in self._FIELDS:
            setattr(self, name, getattr(self, name)[keep])

    def move_to(self, other: "AnchoredInverseDepthEKF", ids) -> None:
        """Hand landmarks over, state and history unchanged, to another bank of the same configuration."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        if len(ids) == 0:
            return
        if other.n != self.n or np.any(other.contains(ids)):
            raise InputError("move_to: the other bank must have the same state size and none of the ids")
        rows = self.index_of(ids)
        other._insert({name: getattr(self, name)[rows] for name in self._FIELDS})
        self.remove(ids)

    # -- model ----------------------------------------------------------------------------------
    @staticmethod
    def measure(x, R_world_camA, p_world_camA, R_world_cam, p_world_cam, dt=None):
        """h_c (N,3), predicted z (N,2) and H (N,2,n) for states x (N,n) seen from (R_world_cam, C).

        The current pose may be shared, (3,3) and (3,), or per landmark, (N,3,3) and (N,3).
        With n = 6 the last three states are the gyro bias b and ``dt`` (N,) is t − t_anchor.
        """
        R_cam_world = np.swapaxes(R_world_cam, -1, -2)
        D = (0.5 * dt)[:, None, None] * (R_world_camA + R_world_cam) if x.shape[1] == 6 else None
        return _predict(x, _ray_map(R_world_camA), p_world_camA - p_world_cam, R_cam_world, D)

    def measurement_variance(self, x: np.ndarray) -> np.ndarray:
        """Diagonal of R (M,2) at states x (M,n): pixel noise, white attitude noise of the telemetry
        and 2 (ρ σ_p)² for the anchor and current position errors ⟂ to the ray (normalized units)."""
        att = np.radians(self.config.attitude_sigma_deg) ** 2
        var = self.sigma_xy**2 + att
        if self.config.position_sigma_m > 0:
            pos = 2.0 * (np.maximum(x[:, 2], 0.0) * self.config.position_sigma_m) ** 2
            return var + pos[:, None]
        return np.broadcast_to(var, (len(x), 2))

    # -- update ---------------------------------------------------------------------------------
    def update(self, ids, xy, R_world_cam, p_world_cam, t) -> UpdateResult:
        """Fuse one observation per listed landmark; poses shared (3,3)/(3,) or per landmark."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        m = len(ids)
        if m == 0:
            return _no_update(ids)
        rows = self.index_of(ids)
        _require_distinct(ids, "update")
        z = _as_batch("xy", xy, m, (2,))
        Rc = _shared_or_batch("R_world_cam", R_world_cam, m, (3, 3))
        C = _shared_or_batch("p_world_cam", p_world_cam, m, (3,))
        t = _as_batch("t", np.asarray(t, float).reshape(-1) if np.ndim(t) else t, m, ())
        return UpdateResult(ids, *self._update_rows(rows, z, Rc, C, t))

    def update_sequence(self, ids, xy, R_world_cam, p_world_cam, t, count) -> np.ndarray:
        """Fuse a buffer of observations per landmark, in order (e.g. a track replayed after :meth:`add`).

        ``xy`` (M,K,2), ``R_world_cam`` (M,K,3,3), ``p_world_cam`` (M,K,3), ``t`` (M,K); landmark i
        uses its first ``count[i]`` ≤ K entries.  The same as calling :meth:`update` once per slot
        with the landmarks that have it; returns the number of accepted updates per landmark (M,).
        """
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        m = len(ids)
        count = np.asarray(count).reshape(-1)
        if len(count) != m or (m and not np.issubdtype(count.dtype, np.integer)):
            raise InputError(f"count must be {m} integers, got shape {count.shape} dtype {count.dtype}")
        xy, R, p, t = (np.asarray(a, float) for a in (xy, R_world_cam, p_world_cam, t))
        k = xy.shape[1] if xy.ndim == 3 else -1
        if xy.shape != (m, k, 2) or R.shape != (m, k, 3, 3) or p.shape != (m, k, 3) or t.shape != (m, k):
            raise InputError(
                f"update_sequence: xy, R_world_cam, p_world_cam, t must be (M,K,2), (M,K,3,3), (M,K,3), (M,K) "
                f"with M = {m}, got {xy.shape}, {R.shape}, {p.shape}, {t.shape}"
            )
        if np.any(count < 0) or np.any(count > k):
            raise InputError(f"count must lie in 0..{k}")
        accepted = np.zeros(m, np.int64)
        if m == 0:
            return accepted
        rows = self.index_of(ids)
        _require_distinct(ids, "update_sequence")
        used = np.arange(k)[None, :] < count[:, None]
        for name, a in (("xy", xy), ("R_world_cam", R), ("p_world_cam", p), ("t", t)):
            if not np.all(np.isfinite(a[used])):
                raise InputError(f"{name} contains NaN or inf")
        if jit.ENABLED:  # compiled: each landmark's buffer in order, in one loop (ekf_anchored_kernels)
            return self._kernel_sequences(rows, xy, R, p, t, count.astype(np.int64))[0].sum(1)
        for j in range(int(count.max())):
            sel = np.flatnonzero(count > j)
            good = self._update_rows(rows[sel], xy[sel, j], R[sel, j], p[sel, j], t[sel, j])[0]
            accepted[sel] += good
        return accepted

    @staticmethod
    def update_banks(parts, R_world_cam, p_world_cam, t) -> list[UpdateResult]:
        """Fuse one frame's observations of landmarks held in several banks, in one batch.

        ``parts``: a list of (bank, ids, xy); the banks share configuration and camera, the pose
        ``R_world_cam`` (3,3), ``p_world_cam`` (3,) and time ``t`` are the frame's.  The same as
        :meth:`update` on each bank in turn, with one set of array operations for all of them.
        """
        parts = [(bank, np.asarray(ids, dtype=np.int64).reshape(-1), xy) for bank, ids, xy in parts]
        if not parts:
            return []
        first = parts[0][0]
        if any(b.config != first.config or not np.array_equal(b.sigma_xy, first.sigma_xy) for b, _, _ in parts):
            raise InputError("update_banks: the banks must share their configuration and camera")
        Rc = _shared_or_batch("R_world_cam", R_world_cam, 1, (3, 3))
        C = _shared_or_batch("p_world_cam", p_world_cam, 1, (3,))
        if Rc.shape != (3, 3) or C.shape != (3,) or np.ndim(t) != 0 or not np.isfinite(t):
            raise InputError("update_banks: one frame's pose (3,3), (3,) and a finite time t")
        for _, ids, _ in parts:
            _require_distinct(ids, "update_banks")
        return AnchoredInverseDepthEKF._update_banks_rows(
            [(bank, ids, bank.index_of(ids), _as_batch("xy", xy, len(ids), (2,))) for bank, ids, xy in parts], Rc, C, float(t))

    @staticmethod
    def _update_banks_rows(parts, Rc, C, t: float) -> list[UpdateResult]:
        """:meth:`update_banks` on validated input: ``parts`` a list of (bank, ids, rows, z (M,2)),
        distinct ids per bank; one pose Rc (3,3), C (3,) at t."""
        if jit.ENABLED:  # compiled: bank by bank (the same as one batch: landmarks are independent)
            return [UpdateResult(ids, *bank._kernel_rows(r, z, Rc, C, t)) for bank, ids, r, z in parts]
        ends = np.cumsum([len(r) for _, _, r, _ in parts])
        if ends[-1] == 0:
            return [_no_update(ids) for _, ids, _, _ in parts]
        gather = [np.concatenate([getattr(b, name)[r] for b, _, r, _ in parts])
                  for name in ("x", "P", "R_world_camA", "p_world_camA", "t_anchor")]
        x, P, good, nis, reason = parts[0][0]._solve(*gather, np.concatenate([z for *_, z in parts]), Rc, C, t)
        out = []
        for (bank, ids, r, _), lo, hi in zip(parts, np.concatenate([[0], ends[:-1]]), ends):
            bank._commit(r, x[lo:hi], P[lo:hi], good[lo:hi], nis[lo:hi])
            out.append(UpdateResult(ids, good[lo:hi], nis[lo:hi], reason[lo:hi]))
        return out

    def _update_rows(self, rows, z, Rc, C, t):
        """The iterated EKF update of bank rows ``rows`` (validated inputs): (accepted, nis, reason)."""
        if jit.ENABLED:
            return self._kernel_rows(rows, z, Rc, C, t)
        x, P, good, nis, reason = self._solve(
            self.x[rows], self.P[rows], self.R_world_camA[rows], self.p_world_camA[rows], self.t_anchor[rows], z, Rc, C, t
        )
        self._commit(rows, x, P, good, nis)
        return good, nis, reason

    def _kernel_rows(self, rows, z, Rc, C, t):
        """:meth:`_update_rows` by the compiled kernels: one observation z (M,2) per row, from one pose
        ((3,3), (3,), scalar t) or one per row; (accepted, nis, reason)."""
        m = len(rows)
        if m == 0:
            return np.zeros(0, bool), np.zeros(0), np.zeros(0, np.int8)
        if np.ndim(Rc) == 3 or np.ndim(C) == 2 or np.ndim(t) == 1:  # a pose per landmark: a sequence of one each
            good, nis, reason = self._kernel_sequences(
                rows, np.reshape(z, (m, 1, 2)), np.broadcast_to(Rc, (m, 3, 3))[:, None],
                np.broadcast_to(C, (m, 3))[:, None], np.broadcast_to(t, (m,))[:, None], np.ones(m, np.int64))
            return good[:, 0], nis[:, 0], reason[:, 0]
        accepted, nis, reason = np.zeros(m, bool), np.empty(m), np.empty(m, np.int8)
        _kernels.update_pixel_rows(*self._kernel_bank(), np.ascontiguousarray(rows, np.int64), np.ascontiguousarray(z, float),
                                   np.ascontiguousarray(Rc, float), np.ascontiguousarray(C, float), float(t),
                                   *self._kernel_constants, accepted, nis, reason)
        return accepted, nis, reason

    def _kernel_bank(self) -> tuple:
        """The bank arrays the pixel kernels read and update in place."""
        return (self.x, self.P, self.R_world_camA, self.p_world_camA, self.t_anchor, self.n_updates, self.n_rejects,
                self.diverged, self.nis_avg, self.nis_count)

    def _kernel_sequences(self, rows, z, Rc, C, t, count):
        """Run :func:`ekf_anchored_kernels.update_pixel_sequences` on bank rows ``rows`` with observations
        z (M,K,2) from poses Rc (M,K,3,3), C (M,K,3) at t (M,K), the first ``count`` (M,) of each:
        the bank is updated in place (with :meth:`_commit`'s bookkeeping); (accepted, nis, reason), each (M,K)."""
        m, k = z.shape[:2]
        accepted, nis, reason = np.zeros((m, k), bool), np.full((m, k), np.nan), np.zeros((m, k), np.int8)
        c = np.ascontiguousarray
        _kernels.update_pixel_sequences(*self._kernel_bank(), c(rows, np.int64), c(z, float), c(Rc, float), c(C, float),
                                        c(t, float), c(count, np.int64), *self._kernel_constants, accepted, nis, reason)
        return accepted, nis, reason

    def _solve(self, x0, P0, RA, pA, tA, z, Rc, C, t):
        """Iterated EKF update of states x0 (M,n), P0 (M,n,n) anchored at (RA, pA, tA) with measurements
        z (M,2) from pose (Rc, C) at t: (x, P, accepted, nis, reason), x and P unchanged where not accepted."""
        cfg = self.config
        ray_map = _ray_map(RA)
        var = self.measurement_variance(x0)
        R_cam_world = np.swapaxes(Rc, -1, -2)
        a = pA - C
        D = (0.5 * (t - tA))[:, None, None] * (RA + Rc) if self.n == 6 else None

        def gain(H):
            """P0 Hᵀ (M,n,2) and S⁻¹ (M,2,2), S = H P0 Hᵀ + R."""
            PHt = P0 @ np.swapaxes(H, 1, 2)
            S = H @ PHt
            S[:, 0, 0] += var[:, 0]
            S[:, 1, 1] += var[:, 1]
            return PHt, _inv2(S)

        h, zhat, H = _predict(x0, ray_map, a, R_cam_world, D)
        behind = h[:, 2] <= 1e-9
        y = z - zhat
        PHt, Si = gain(H)
        nis = np.einsum("ni,nij,nj->n", y, Si, y)
        nis[behind] = np.inf
        reason = np.where(nis <= cfg.gate_threshold, UPDATED, GATED).astype(np.int8)
        reason[behind] = BEHIND
        ok = reason == UPDATED

        # iterated EKF: x_{i+1} = x0 + K_i (z − h(x_i) − H_i (x0 − x_i)), K_i = P0 H_iᵀ S_i⁻¹
        xi = x0
        K = PHt @ Si
        innov = y  # at x_0 the H_0 (x0 − x_0) term vanishes
        for it in range(cfg.iterations):
            if it > 0:
                h, zhat, H = _predict(xi, ray_map, a, R_cam_world, D)
                PHt, Si = gain(H)
                K = PHt @ Si
                ok &= h[:, 2] > 1e-9
                innov = z - zhat - (H @ (x0 - xi)[:, :, None])[:, :, 0]
            x_new = x0 + (K @ innov[:, :, None])[:, :, 0]
            xi = np.where(ok[:, None], x_new, xi)
        # P = (I − K H) P0 = P0 − K (P0 Hᵀ)ᵀ at the last linearization, symmetrized
        P_new = P0 - K @ np.swapaxes(PHt, 1, 2)
        P_new = 0.5 * (P_new + np.swapaxes(P_new, 1, 2))
        good = ok & np.isfinite(xi).all(1) & np.isfinite(P_new).all((1, 2))
        reason[ok & ~good] = GATED
        return np.where(good[:, None], xi, x0), np.where(good[:, None, None], P_new, P0), good, nis, reason

    def _commit(self, rows, x, P, good, nis) -> None:
        """Store the updated rows and their accept / reject / NIS history."""
        cfg = self.config
        self.x[rows] = x
        self.P[rows] = P
        self.n_updates[rows] += good
        n_rejects = np.where(good, 0, self.n_rejects[rows] + 1)
        self.n_rejects[rows] = n_rejects
        self.diverged[rows] |= n_rejects >= cfg.max_consecutive_rejects
        cap = 2.0 * cfg.gate_threshold
        nis_c = np.where(np.isfinite(nis), np.minimum(nis, cap), cap)
        nis_count = self.nis_count[rows] + 1
        self.nis_count[rows] = nis_count
        alpha = 1.0 / np.minimum(nis_count, cfg.nis_window)  # running mean, then exponential
        nis_avg = self.nis_avg[rows]
        nis_avg += alpha * (nis_c - nis_avg)
        self.nis_avg[rows] = nis_avg
        if cfg.max_mean_nis > 0:
            full = nis_count >= cfg.nis_window
            self.diverged[rows] |= full & (nis_avg > cfg.max_mean_nis)

    # -- looming (module docstring, docs/derivations/looming.md) ------------------------------
    @staticmethod
    def measure_looming(x, R_world_camA, p_world_camA, R_world_cam_prev, p_world_cam_prev, R_world_cam, p_world_cam,
                        dt_prev=None, dt=None):
        """Predicted scale change h_s (N,) and H_s (N,n) of states x (N,n) between the previous pose
        (R_world_cam_prev, p_world_cam_prev) and the current one; poses (3,3)/(3,) or per landmark.
        With n = 6, ``dt_prev`` and ``dt`` (N,) are t' − t_anchor and t − t_anchor."""
        n = len(x)
        RA = np.broadcast_to(np.asarray(R_world_camA, float), (n, 3, 3))
        drift = x.shape[1] == 6
        zero = np.zeros(n)
        args = _looming_args(RA, np.asarray(p_world_camA, float), zero, np.asarray(R_world_cam_prev, float),
                             np.asarray(p_world_cam_prev, float), dt_prev if drift else zero,
                             np.asarray(R_world_cam, float), np.asarray(p_world_cam, float), dt if drift else zero, drift)
        _, _, hs, Hs = _looming_predict(x, *args)
        return hs, Hs

    def update_looming(self, ids, scale, scale_sigma, R_world_cam_prev, p_world_cam_prev, t_prev,
                       R_world_cam, p_world_cam, t) -> UpdateResult:
        """Fuse one looming measurement per listed landmark: ``scale`` (M,) = image size now / in the
        previous frame (pose R_world_cam_prev, p_world_cam_prev at t_prev) with σ ``scale_sigma``
        (M,) or None (the floor only).  NaN scales are skipped (``LOOM_NAN``), non-positive or
        infinite ones refused (``LOOM_NONPOSITIVE``); neither raises."""
        return self.update_looming_banks([(self, ids, scale, scale_sigma)], R_world_cam_prev, p_world_cam_prev, t_prev,
                                         R_world_cam, p_world_cam, t)[0]

    @staticmethod
    def update_looming_banks(parts, R_world_cam_prev, p_world_cam_prev, t_prev, R_world_cam, p_world_cam, t) -> list[UpdateResult]:
        """:meth:`update_looming` over several banks of one configuration in one batch.

        ``parts``: a list of (bank, ids, scale, scale_sigma); the two poses are shared (3,3)/(3,).
        """
        parts = [(b, np.asarray(ids, dtype=np.int64).reshape(-1), sc, sg) for b, ids, sc, sg in parts]
        if not parts:
            return []
        first = parts[0][0]
        if any(b.config != first.config for b, *_ in parts):
            raise InputError("update_looming_banks: the banks must share their configuration")
        Rp = _shared_or_batch("R_world_cam_prev", R_world_cam_prev, 1, (3, 3))
        Cp = _shared_or_batch("p_world_cam_prev", p_world_cam_prev, 1, (3,))
        Rc = _shared_or_batch("R_world_cam", R_world_cam, 1, (3, 3))
        C = _shared_or_batch("p_world_cam", p_world_cam, 1, (3,))
        if Rp.shape != (3, 3) or Cp.shape != (3,) or Rc.shape != (3, 3) or C.shape != (3,):
            raise InputError("update_looming_banks: one previous and one current pose, (3,3) and (3,) each")
        if np.ndim(t) or np.ndim(t_prev) or not (np.isfinite(t) and np.isfinite(t_prev)) or not t > t_prev:
            raise InputError(f"update_looming_banks: times must be finite scalars with t > t_prev, got {t_prev!r}, {t!r}")
        checked = []
        for bank, ids, sc, sg in parts:
            m = len(ids)
            _require_distinct(ids, "update_looming")
            sc = np.asarray(sc, float).reshape(-1) if sc is not None else np.full(m, np.nan)
            sg = np.zeros(m) if sg is None else np.asarray(sg, float).reshape(-1)
            if sc.shape != (m,) or sg.shape != (m,):
                raise InputError(f"scale and scale_sigma must have shape ({m},), got {sc.shape} and {sg.shape}")
            checked.append((bank, ids, bank.index_of(ids), sc, sg))
        return AnchoredInverseDepthEKF._looming_banks_rows(checked, Rp, Cp, float(t_prev), Rc, C, float(t))

    @staticmethod
    def _looming_banks_rows(parts, Rp, Cp, t_prev: float, Rc, C, t: float) -> list[UpdateResult]:
        """:meth:`update_looming_banks` on validated input: ``parts`` a list of (bank, ids, rows,
        scale (M,), scale_sigma (M,)), distinct ids per bank; poses (3,3)/(3,), t > t_prev."""
        if not parts:
            return []
        first = parts[0][0]
        if jit.ENABLED:  # compiled: bank by bank (landmarks are independent)
            return [bank._kernel_looming(ids, r, sc, sg, Rp, Cp, t_prev, Rc, C, t) for bank, ids, r, sc, sg in parts]
        rows = [r for _, _, r, _, _ in parts]
        z = np.concatenate([sc for *_, sc, _ in parts])
        sig = np.concatenate([sg for *_, sg in parts])
        reason = np.full(len(z), UPDATED, np.int8)
        reason[np.isnan(z)] = LOOM_NAN
        bad = ~np.isnan(z) & (~np.isfinite(z) | (z <= 0) | ~np.isfinite(sig) | (sig < 0))
        reason[bad] = LOOM_NONPOSITIVE
        nis = np.full(len(z), np.nan)
        good = np.zeros(len(z), bool)
        use = np.flatnonzero(reason == UPDATED)
        ends = np.cumsum([len(r) for r in rows])
        starts = np.concatenate([[0], ends[:-1]])
        if len(use):
            bank_of = np.searchsorted(ends, use, side="right")
            gather = {name: np.concatenate([getattr(b, name)[r] for (b, *_), r in zip(parts, rows)])[use]
                      for name in ("x", "P", "R_world_camA", "p_world_camA", "t_anchor")}
            var = sig[use] ** 2 + first.config.looming_sigma_floor**2
            x, P, g, nis_u, reason_u = first._solve_looming(
                gather["x"], gather["P"], gather["R_world_camA"], gather["p_world_camA"], gather["t_anchor"],
                z[use], var, Rp, Cp, t_prev, Rc, C, t)
            good[use], nis[use], reason[use] = g, nis_u, reason_u
            for k, ((bank, *_), r) in enumerate(zip(parts, rows)):
                sel = bank_of == k
                if np.any(sel):
                    rr = r[use[sel] - starts[k]]
                    bank.x[rr] = x[sel]
                    bank.P[rr] = P[sel]
                    bank.n_looming[rr] += g[sel]
        return [UpdateResult(ids, good[lo:hi], nis[lo:hi], reason[lo:hi])
                for (_, ids, *_), lo, hi in zip(parts, starts, ends)]

    def _kernel_looming(self, ids, rows, sc, sg, Rp, Cp, t_prev, Rc, C, t) -> UpdateResult:
        """One bank's part of :meth:`_looming_banks_rows` by :func:`ekf_anchored_kernels.update_looming_rows`."""
        m = len(ids)
        accepted, nis, reason = np.zeros(m, bool), np.empty(m), np.empty(m, np.int8)
        if m == 0:
            return UpdateResult(ids, accepted, nis, reason)
        cfg = self.config
        c = np.ascontiguousarray
        _kernels.update_looming_rows(
            self.x, self.P, self.R_world_camA, self.p_world_camA, self.t_anchor, self.n_looming, rows, c(sc), c(sg),
            c(Rp), c(Cp), t_prev, c(Rc), c(C), t, float(cfg.looming_sigma_floor), cfg.looming_gate_threshold,
            cfg.looming_iterations, accepted, nis, reason)
        return UpdateResult(ids, accepted, nis, reason)

    def _solve_looming(self, x0, P0, RA, pA, tA, z, var, Rp, Cp, t_prev, Rc, C, t):
        """Iterated scalar EKF update (Joseph form) of states x0 (M,n), P0 (M,n,n) with scale
        measurements z (M,) of variance var (M,): (x, P, accepted, nis, reason)."""
        cfg = self.config
        args = _looming_args(RA, pA, tA, Rp, Cp, t_prev, Rc, C, t, self.n == 6)
        hzp, hzn, hs, Hs = _looming_predict(x0, *args)
        behind = (hzp <= 1e-9) | (hzn <= 1e-9)
        PHt = (P0 @ Hs[:, :, None])[:, :, 0]  # (M,n)
        S = np.einsum("ni,ni->n", Hs, PHt) + var
        y = z - hs
        nis = y * y / S
        nis[behind] = np.inf
        reason = np.where(nis <= cfg.looming_gate_threshold, UPDATED, GATED).astype(np.int8)
        reason[behind] = BEHIND
        ok = reason == UPDATED
        xi = x0
        K = PHt / S[:, None]
        innov = y
        H = Hs
        for it in range(cfg.looming_iterations):
            if it > 0:
                hzp, hzn, hs, H = _looming_predict(xi, *args)
                ok &= (hzp > 1e-9) & (hzn > 1e-9)
                PHt = (P0 @ H[:, :, None])[:, :, 0]
                S = np.einsum("ni,ni->n", H, PHt) + var
                K = PHt / S[:, None]
                innov = z - hs - np.einsum("ni,ni->n", H, x0 - xi)
            xi = np.where(ok[:, None], x0 + K * innov[:, None], xi)
        # Joseph form: (I − K H) P0 (I − K H)ᵀ + K R Kᵀ
        A = np.eye(self.n) - K[:, :, None] * H[:, None, :]
        P_new = A @ P0 @ np.swapaxes(A, 1, 2) + var[:, None, None] * (K[:, :, None] * K[:, None, :])
        P_new = 0.5 * (P_new + np.swapaxes(P_new, 1, 2))
        good = ok & np.isfinite(xi).all(1) & np.isfinite(P_new).all((1, 2))
        reason[ok & ~good] = GATED
        return np.where(good[:, None], xi, x0), np.where(good[:, None, None], P_new, P0), good, nis, reason

    # -- output ---------------------------------------------------------------------------------
    def estimates(self, p_world_cam) -> LandmarkEstimates:
        """Point, range and σ of every landmark as seen from camera centre ``p_world_cam`` (3,)."""
        C = np.asarray(p_world_cam, float).reshape(3)
        if not np.all(np.isfinite(C)):
            raise InputError("p_world_cam contains NaN or inf")
        cfg = self.config
        x = self.x
        if jit.ENABLED:  # compiled: the same formulas landmark by landmark
            n = len(x)
            p_world, rng, rsig, srho = np.zeros((n, 3)), np.zeros(n), np.zeros(n), np.zeros(n)
            valid, converged = np.zeros(n, bool), np.zeros(n, bool)
            _kernels.estimates(x, self.P, self.R_world_camA, self.p_world_camA, self.diverged, self.n_updates, C,
                               float(cfg.max_range_m), float(cfg.converged_rel_sigma), cfg.min_updates,
                               p_world, rng, rsig, srho, valid, converged)
            return LandmarkEstimates(self.ids.copy(), p_world, rng, rsig, x[:, 2].copy(), srho, converged, valid)
        rho = x[:, 2]
        srho = np.sqrt(np.maximum(self.P[:, 2, 2], 0.0))
        rho_floor = 1.0 / cfg.max_range_m
        rho_eff = np.maximum(rho, rho_floor)
        Rm = np.einsum("nij,njk->nik", self.R_world_camA, _ray_columns(x[:, 0], x[:, 1]))  # R [m, ∂m/∂θ, ∂m/∂φ]
        mw = Rm[:, :, 0]
        a = self.p_world_camA - C
        g = rho_eff[:, None] * a + mw  # ρ · (p − C)
        ng = np.linalg.norm(g, axis=1)
        rng = np.minimum(ng / rho_eff, cfg.max_range_m)
        J = np.zeros((len(x), 3))
        J[:, :2] = np.einsum("ni,nik->nk", g, Rm[:, :, 1:]) / (ng * rho_eff)[:, None]
        J[:, 2] = np.einsum("ni,ni->n", g, a) / (ng * rho_eff) - ng / rho_eff**2
        rsig = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", J, self.P[:, :3, :3], J), 0.0))
        rsig = np.minimum(rsig, cfg.max_range_m)
        p_world = self.p_world_camA + mw / rho_eff[:, None]
        valid = ~self.diverged & (rho > -3.0 * srho)
        converged = valid & (rho > rho_floor) & (rsig < cfg.converged_rel_sigma * rng) & (self.n_updates >= cfg.min_updates)
        return LandmarkEstimates(self.ids.copy(), p_world, rng, rsig, rho.copy(), srho, converged, valid)


# The compiled kernels import this module's reason codes, so they are imported last.
from companion.core import ekf_anchored_kernels as _kernels  # noqa: E402
