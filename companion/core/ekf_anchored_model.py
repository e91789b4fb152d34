"""The anchored inverse-depth filter's model (docs/derivations/ekf_anchored.md, looming.md): its
configuration, the outcomes of an update and the batched measurement models with their analytic
Jacobians, which :class:`companion.core.ekf_anchored.AnchoredInverseDepthEKF` runs (that module
re-exports every public name defined here).

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

Position error states (docs/derivations/ekf_anchored.md § Position error states).  The telemetry's
position is C_reported = C_true + e(t), with e a first-order Gauss–Markov error (σ_p, τ), correlated
over a landmark's life.  When ``position_tau_s`` > 0 each filter carries three more states, last in x:
δ = e(t) − e(t_anchor) (world frame, m).  The true C_A − C is then the reported one plus δ:

    g = ρ (p_world_camA − C + δ) + R_world_camA · m(θ, φ),   ∂h_c/∂δ = ρ R_cam_world Exp(w)

and between updates Var δ grows per axis as the Gauss–Markov difference does, to
2σ_p² (1 − exp(−(t − t_anchor)/τ)) (``AnchoredEKFConfig.delta_variance``); δ starts at 0 with zero variance at the anchor.  The white
2 (ρ σ_p)² of R is then dropped: the error is in the state instead.

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
frames changes the scale by O(angle²) more, which the noise floor covers.

The functions here are the numpy *reference*: every operation is batched over landmarks, arrays of
shape (N, 3), (N, 3, 3), no loop per landmark.  :mod:`companion.core.ekf_anchored_kernels` evaluates
the same equations one landmark at a time, and takes the reason codes (``UPDATED`` …) from here.
"""

from __future__ import annotations

import dataclasses
import math
import statistics

import numpy as np

from companion.config import require, require_finite
from companion.core.frames import SKEW_MAP


@dataclasses.dataclass(frozen=True)
class AnchoredEKFConfig:
    """The ``[ekf_anchored]`` table."""

    sigma_px: float = 1.0  # pixel measurement noise σ
    gate_probability: float = 0.999  # χ² (2 dof) innovation gate
    iterations: int = 3  # iterated-EKF relinearizations per update (1 = plain EKF)
    attitude_sigma_deg: float = 0.0  # white attitude error of each telemetry pose
    attitude_drift_deg_s: float = 0.03  # σ of the gyro bias per axis (°/s); > 0 adds 3 bias states
    position_sigma_m: float = 0.1  # σ of the telemetry's camera position error per axis (m), seen as ρ·σ at the landmark
    position_tau_s: float = 0.0  # correlation time of that error (s); > 0 adds 3 states δ = e(t) − e(t_anchor) per landmark
    position_consider: bool = False  # with the δ states: carry them as consider states (their covariance only, mean 0; § Position error states)
    converged_rel_sigma: float = 0.1  # converged when range σ / range is below this ...
    converged_sigma_floor_m: float = 0.6  # ... and σ below max(this, converged_far_rel_sigma · range), m
    converged_far_rel_sigma: float = 0.0  # ... (far ranges need a tighter relative σ than near ones: § Outputs and convergence); 0 = off
    converged_near_sigma_m: float = 0.0  # > 0: a range σ below this (m) is converged whatever σ / range (close in, where an honest σ holds the position error); 0 = off
    min_updates: int = 3  # ... and at least this many accepted updates
    max_consecutive_rejects: int = 5  # then the landmark is flagged diverged
    max_range_m: float = 10000.0  # ranges beyond this are reported as this value
    nis_window: float = 10.0  # updates averaged (exponentially) in each landmark's mean NIS
    max_mean_nis: float = 4.0  # mean NIS above this flags the landmark diverged (not a static point); 0 = off
    nis_min_baseline_deg: float = 0.0  # a NIS enters the mean only after the camera moved this far, seen from the landmark, since the last one that did (degrees); 0 = every update
    max_drift_chi2: float = 9.0  # (ρ̂ − ρ̂_c)² / (P_c − P) above this since convergence flags it diverged (§ Drift test); 0 = off
    looming: bool = True  # fuse the matcher's patch scale change (looming, docs/derivations/looming.md) when given
    looming_sigma_floor: float = 0.003  # floor added (in quadrature) to the matcher's scale σ
    looming_gate_probability: float = 0.999  # χ² (1 dof) gate of the looming innovation
    looming_iterations: int = 1  # iterated-EKF relinearizations of the looming update (1 = plain EKF)
    refine_min_obs: int = 8  # batch refinement (§ Batch refinement): first at this many frames in a landmark's history ...
    refine_max_obs: int = 0  # ... then each time the count doubles, the last at this many (the history's bound); 0 = off (the seed-004 benchmark: 128)
    refine_iterations: int = 3  # Gauss–Newton steps of each refinement
    refine_max_slots: int = 2048  # history slots refined per frame at most (the smallest histories first; the rest wait a frame): bounds a frame's cost when many landmarks fall due together
    looming_max_angle_deg: float = 180.0  # looming only for points within this angle of the direction of travel: off the axis a tilted patch biases the scale at first order while parallax ranges the point (docs/derivations/looming.md, § Off the axis of travel); 180 = everywhere

    def __post_init__(self) -> None:
        require_finite("sigma_px", self.sigma_px, positive=True)
        require_finite("gate_probability", self.gate_probability)
        require(0.5 < self.gate_probability < 1.0, f"gate_probability must be in (0.5, 1), got {self.gate_probability}")
        require(isinstance(self.iterations, int) and 1 <= self.iterations <= 20, "iterations must be an integer in 1..20")
        require_finite("attitude_sigma_deg", self.attitude_sigma_deg, nonnegative=True)
        require_finite("attitude_drift_deg_s", self.attitude_drift_deg_s, nonnegative=True)
        require_finite("converged_rel_sigma", self.converged_rel_sigma, positive=True)
        require_finite("converged_sigma_floor_m", self.converged_sigma_floor_m, nonnegative=True)
        require_finite("converged_far_rel_sigma", self.converged_far_rel_sigma, nonnegative=True)
        require_finite("converged_near_sigma_m", self.converged_near_sigma_m, nonnegative=True)
        require(isinstance(self.min_updates, int) and self.min_updates >= 0, "min_updates must be an integer >= 0")
        require(isinstance(self.max_consecutive_rejects, int) and self.max_consecutive_rejects >= 1, "max_consecutive_rejects must be >= 1")
        require_finite("max_range_m", self.max_range_m, positive=True)
        require_finite("position_sigma_m", self.position_sigma_m, nonnegative=True)
        require_finite("position_tau_s", self.position_tau_s, nonnegative=True)
        require(isinstance(self.position_consider, bool), f"position_consider must be true or false, got {self.position_consider!r}")
        require_finite("nis_window", self.nis_window)
        require(self.nis_window >= 1.0, f"nis_window must be >= 1, got {self.nis_window}")
        require_finite("max_mean_nis", self.max_mean_nis, nonnegative=True)
        require_finite("nis_min_baseline_deg", self.nis_min_baseline_deg, nonnegative=True)
        require(self.nis_min_baseline_deg < 90.0, f"nis_min_baseline_deg must be < 90, got {self.nis_min_baseline_deg}")
        require_finite("max_drift_chi2", self.max_drift_chi2, nonnegative=True)
        require(isinstance(self.looming, bool), f"looming must be true or false, got {self.looming!r}")
        require_finite("looming_sigma_floor", self.looming_sigma_floor, positive=True)
        require_finite("looming_gate_probability", self.looming_gate_probability)
        require_finite("looming_max_angle_deg", self.looming_max_angle_deg, positive=True)
        require(self.looming_max_angle_deg <= 180.0, f"looming_max_angle_deg must be in (0, 180], got {self.looming_max_angle_deg}")
        require(isinstance(self.refine_max_obs, int) and not isinstance(self.refine_max_obs, bool) and 0 <= self.refine_max_obs <= 4096,
                f"refine_max_obs must be an integer in 0..4096 (0 = off), got {self.refine_max_obs!r}")
        require(isinstance(self.refine_min_obs, int) and not isinstance(self.refine_min_obs, bool) and 2 <= self.refine_min_obs,
                f"refine_min_obs must be an integer >= 2, got {self.refine_min_obs!r}")
        require(self.refine_max_obs == 0 or self.refine_min_obs <= self.refine_max_obs,
                f"refine_min_obs ({self.refine_min_obs}) must not exceed refine_max_obs ({self.refine_max_obs})")
        require(isinstance(self.refine_iterations, int) and not isinstance(self.refine_iterations, bool)
                and 1 <= self.refine_iterations <= 20, f"refine_iterations must be an integer in 1..20, got {self.refine_iterations!r}")
        require(isinstance(self.refine_max_slots, int) and not isinstance(self.refine_max_slots, bool) and self.refine_max_slots >= 1,
                f"refine_max_slots must be an integer >= 1, got {self.refine_max_slots!r}")
        require(isinstance(self.looming_iterations, int) and 1 <= self.looming_iterations <= 20,
                "looming_iterations must be an integer in 1..20")
        require(
            0.5 < self.looming_gate_probability < 1.0,
            f"looming_gate_probability must be in (0.5, 1), got {self.looming_gate_probability}",
        )

    @property
    def position_states(self) -> bool:
        """True when each filter carries the position-error difference δ (§ Position error states)."""
        return self.position_tau_s > 0 and self.position_sigma_m > 0

    def looming_variance(self, scale_sigma):
        """R_s of a looming measurement: the matcher's σ² plus the floor² (looming.md § Noise, gate and update)."""
        return np.asarray(scale_sigma, float) ** 2 + self.looming_sigma_floor**2

    @property
    def refine(self) -> bool:
        """True when landmarks are refined in batch (§ Batch refinement): on, and no position-error states."""
        return self.refine_max_obs > 0 and not self.position_states

    @property
    def position_variance_limit(self) -> float:
        """2σ_p² (m² per axis): Var δ for t − t_anchor ≫ τ, the variance of the difference of two
        independent samples of the Gauss–Markov error (§ Position error states); 0 without the states."""
        return 2.0 * self.position_sigma_m**2 if self.position_states else 0.0

    def delta_variance(self, dt):
        """Var δ per axis a time ``dt`` (≥ 0) after the anchor: 2σ_p² (1 − exp(−dt/τ)) (§ Position error states)."""
        if not self.position_states:
            return 0.0 * np.asarray(dt, float)
        return self.position_variance_limit * -np.expm1(-np.asarray(dt, float) / self.position_tau_s)

    def layout(self) -> tuple[int, bool, int]:
        """(n, drift, i_pos): state size, whether the gyro-bias states b are in x (x[3:6]) and the index
        of δ in x (−1 when absent).  x = (θ, φ, ρ, [b], [δ])."""
        drift = self.attitude_drift_deg_s > 0
        n = 3 + 3 * drift + 3 * self.position_states
        return (n, *layout_of(n, self.position_states))

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
LOOM_OFF_AXIS = 5  # looming: the point lies farther than looming_max_angle_deg from the direction of travel: skipped

UPDATE_REASON_NAMES = {UPDATED: "updated", GATED: "gated", BEHIND: "behind", LOOM_NAN: "nan_scale", LOOM_NONPOSITIVE: "nonpositive_scale", LOOM_OFF_AXIS: "off_axis"}


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


def layout_of(n: int, position_states: bool) -> tuple[bool, int]:
    """(drift, i_pos) of a state vector of size ``n`` = (θ, φ, ρ, [b], [δ]): the gyro bias b is x[3:6]
    when what is left without δ has 6 entries; δ, when carried, is last (i_pos = n − 3, else −1)."""
    return n - 3 * bool(position_states) == 6, (n - 3 if position_states else -1)


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


def _predict(x, ray_map, a, R_cam_world, D, i_pos=-1):
    """h_c (N,3), z (N,2) and H (N,2,n) of the module docstring at states x (N,n).

    ``ray_map`` = :func:`_ray_map` of the anchor rotations, ``a`` = p_world_camA − C (N,3),
    ``R_cam_world`` (3,3) or (N,3,3) and the drift integral ``D`` (N,3,3; None without drift
    states): the parts that stay fixed over the iterated-EKF relinearizations, computed once per
    update by the caller.  ``i_pos``: index of the position-error states δ in x (−1: none).
    """
    V = _hc_jacobian(x, ray_map, a, R_cam_world, D, i_pos)
    h = V[:, :, 0]
    hz = h[:, 2]
    inv_hz = 1.0 / np.where(np.abs(hz) > 1e-12, hz, 1e-12)
    z = h[:, :2] * inv_hz[:, None]
    # ∂z/∂h = (1/h_z) [I₂ | −z], applied row-wise without forming it
    H = (V[:, :2, 1:] - z[:, :, None] * V[:, 2:3, 1:]) * inv_hz[:, None, None]
    return h, z, H


def _hc_jacobian(x, ray_map, a, R_cam_world, D, i_pos=-1):
    """[h_c | ∂h_c/∂x] (N, 3, 1+n) at states x (N,n); arguments as in :func:`_predict`."""
    n = len(x)
    if i_pos >= 0:  # the true C_A − C is the reported one plus δ (§ Position error states)
        a = a + x[:, i_pos : i_pos + 3]
    # W = [g | ∂g/∂(θ, φ, ρ)] with g = ρ a + R_world_camA m, ∂g/∂θ = R ∂m/∂θ, ∂g/∂φ = R ∂m/∂φ, ∂g/∂ρ = a
    W = (_ray_products(x[:, :2])[:, None, :] @ ray_map).reshape(n, 3, 4)
    W[:, :, 3] = a
    W[:, :, 0] += x[:, 2:3] * a
    E = None
    if D is not None:  # [Exp(w) g | Exp(w) ∂g/∂(θ, φ, ρ) | −[Exp(w) g]× J_l(w) D]
        E, J_l = _exp_and_left_jacobian((D @ x[:, 3:6, None])[:, :, 0])
        W7 = np.empty((n, 3, 7))
        np.matmul(E, W, out=W7[:, :, :4])
        np.matmul((W7[:, :, 0] @ -SKEW_MAP).reshape(n, 3, 3), J_l @ D, out=W7[:, :, 4:])
        W = W7
    if i_pos >= 0:  # ∂g/∂δ = ρ I, so ∂(Exp(w) g)/∂δ = ρ Exp(w)
        rho = x[:, 2, None, None]
        W = np.concatenate([W, rho * E if E is not None else rho * _I3], axis=2)
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


def _looming_predict(x, ray_map2, a2, R2, D2, i_pos=-1):
    """h_z' (N,), h_z (N,), h_s = h_z'/h_z (N,) and H_s (N,n) of the looming model (module docstring)
    at states x (N,n); the other arguments from :func:`_looming_args` (one evaluation for both poses;
    the same δ at both, ``i_pos`` its index or −1)."""
    n = len(x)
    V = _hc_jacobian(np.concatenate([x, x]), ray_map2, a2, R2, D2, i_pos)[:, 2, :]
    Vp, Vn = V[:n], V[n:]
    hz_prev, hz_now = Vp[:, 0], Vn[:, 0]
    inv = 1.0 / np.where(np.abs(hz_now) > 1e-12, hz_now, 1e-12)
    hs = hz_prev * inv
    Hs = (Vp[:, 1:] - hs[:, None] * Vn[:, 1:]) * inv[:, None]
    return hz_prev, hz_now, hs, Hs
