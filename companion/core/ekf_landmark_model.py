"""The plain inverse-depth EKF's configuration, status and reason codes, result types and its motion
model: continuous dynamics, Jacobians and the RK4 step (docs/derivations/ekf_landmark.md).

:mod:`companion.core.ekf_landmark` holds the filter bank that uses them and re-exports every name here.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion.config import require, require_finite
from companion.errors import InputError

# -- status codes of estimates() ----------------------------------------------------------------
OK = 0  # valid range
FAR = 1  # ξ below inv_depth_min (beyond the largest stated range, or slightly negative): no range
DIVERGED = 2  # max_consecutive_rejects gated measurements in a row
INVALID = 3  # state left the model's domain (see module docstring); frozen

# -- reason codes of update() -------------------------------------------------------------------
ACCEPTED = 0
GATED = 1  # NIS above the χ² gate
FROZEN = 2  # landmark flagged invalid, measurement not used


@dataclasses.dataclass(frozen=True)
class LandmarkEKFConfig:
    """The ``[ekf_landmark]`` table (docs/derivations/ekf_landmark.md)."""

    sigma_px: float = 1.0  # pixel measurement noise σ (px)
    sigma_v: float | tuple[float, float, float] = 0.1  # linear-velocity input noise PSD^½ (m/s/√Hz), one or per camera axis
    sigma_w: float | tuple[float, float, float] = 0.002  # angular-rate input noise PSD^½ (rad/s/√Hz), one or per camera axis
    gate_probability: float = 0.999  # χ² gate on the 2-dof innovation
    max_consecutive_rejects: int = 5  # then the landmark is flagged diverged
    converged_rel_sigma: float = 0.1  # converged when range σ / range is below this ...
    min_updates: int = 3  # ... and at least this many accepted updates
    inv_depth_min: float = 1e-4  # 1/m: ξ below this has no finite range (reported valid = False)
    inv_depth_max: float = 10.0  # 1/m: ξ above this (closer than 0.1 m) flags the landmark invalid
    negative_inv_depth_sigmas: float = 3.0  # ξ < −k σ_ξ flags the landmark invalid
    max_normalized_coord: float = 20.0  # |x̄| or |ȳ| above this (ray > 87° off axis) flags invalid
    max_step: float = 0.05  # s: longer prediction steps are split into RK4 sub-steps
    max_dt: float = 1.0  # s: a longer predict() step is refused (constant-input model no longer holds)
    nis_window: float = 10.0  # updates averaged (exponentially) in each landmark's mean NIS
    max_mean_nis: float = 0.0  # mean NIS above this flags the landmark diverged (not a static point); 0 = off

    def __post_init__(self) -> None:
        require_finite("sigma_px", self.sigma_px, positive=True)
        for name in ("sigma_v", "sigma_w"):
            value = getattr(self, name)
            values = value if isinstance(value, tuple) else (value,)
            require(len(values) in (1, 3), f"{name} must be one number or three (x, y, z camera axes)")
            for i, v in enumerate(values):
                require_finite(f"{name}[{i}]" if isinstance(value, tuple) else name, v, nonnegative=True)
        require_finite("gate_probability", self.gate_probability)
        require(0.5 <= self.gate_probability < 1.0, f"gate_probability must be in [0.5, 1), got {self.gate_probability}")
        require(
            isinstance(self.max_consecutive_rejects, int) and not isinstance(self.max_consecutive_rejects, bool)
            and self.max_consecutive_rejects >= 1,
            f"max_consecutive_rejects must be an integer >= 1, got {self.max_consecutive_rejects!r}",
        )
        require_finite("converged_rel_sigma", self.converged_rel_sigma, positive=True)
        require(
            isinstance(self.min_updates, int) and not isinstance(self.min_updates, bool) and self.min_updates >= 0,
            f"min_updates must be an integer >= 0, got {self.min_updates!r}",
        )
        require_finite("inv_depth_min", self.inv_depth_min, positive=True)
        require_finite("inv_depth_max", self.inv_depth_max, positive=True)
        require(self.inv_depth_min < self.inv_depth_max, f"inv_depth_min ({self.inv_depth_min}) must be < inv_depth_max ({self.inv_depth_max})")
        require_finite("negative_inv_depth_sigmas", self.negative_inv_depth_sigmas, positive=True)
        require_finite("max_normalized_coord", self.max_normalized_coord, positive=True)
        require_finite("max_step", self.max_step, positive=True)
        require_finite("max_dt", self.max_dt, positive=True)
        require_finite("nis_window", self.nis_window)
        require(self.nis_window >= 1.0, f"nis_window must be >= 1, got {self.nis_window}")
        require_finite("max_mean_nis", self.max_mean_nis, nonnegative=True)
        require(self.max_dt >= self.max_step, f"max_dt ({self.max_dt}) must be >= max_step ({self.max_step})")

    @property
    def gate_threshold(self) -> float:
        """χ²₂ quantile of ``gate_probability``: −2 ln(1 − p) (closed form for 2 dof)."""
        return -2.0 * math.log(1.0 - self.gate_probability)

    @property
    def max_range_m(self) -> float:
        """Largest range the bank states, 1/inv_depth_min (also the placeholder of invalid rows)."""
        return 1.0 / self.inv_depth_min


@dataclasses.dataclass
class UpdateResult:
    """Outcome of :meth:`LandmarkEKFBank.update`, one entry per measurement (in call order)."""

    ids: np.ndarray  # (M,) int64
    accepted: np.ndarray  # (M,) bool
    nis: np.ndarray  # (M,) normalized innovation squared yᵀ S⁻¹ y (before the update), finite
    reason: np.ndarray  # (M,) int8: ACCEPTED / GATED / FROZEN


@dataclasses.dataclass
class LandmarkEstimates:
    """Per landmark, in the current camera frame; every array is finite.

    Where ``valid`` is False, ``p_cam``, ``range`` and ``range_sigma`` are placeholders that
    callers must ignore: the point at distance ``max_range_m`` along the (clamped) ray, so
    ``range = range_sigma = max_range_m``.  ``status`` says why (OK / FAR / DIVERGED / INVALID).
    """

    ids: np.ndarray  # (N,) int64, sorted
    p_cam: np.ndarray  # (N, 3) m, camera frame
    range: np.ndarray  # (N,) m, distance from the camera centre, Z·sqrt(1 + x̄² + ȳ²)
    range_sigma: np.ndarray  # (N,) m, first-order σ of range
    inv_depth: np.ndarray  # (N,) ξ (1/m), the raw state (finite)
    inv_depth_sigma: np.ndarray  # (N,) σ_ξ
    converged: np.ndarray  # (N,) bool: valid, ≥ min_updates, range σ / range < converged_rel_sigma
    valid: np.ndarray  # (N,) bool
    status: np.ndarray  # (N,) int8


# -- model --------------------------------------------------------------------------------------
def _model(x: np.ndarray, q, jac: bool):
    """f (N,3) and, if ``jac``, J = [∂f/∂x  ∂f/∂q] (N,3,9).  ``q`` is six scalars or six (N,) arrays."""
    vx, vy, vz, wx, wy, wz = q
    xb, yb, xi = x[:, 0], x[:, 1], x[:, 2]
    xx, yy, xy = xb * xb, yb * yb, xb * yb
    rot = yb * wx - xb * wy  # shared term of f₃ and the diagonal of F
    f = np.empty_like(x)
    f[:, 0] = xi * (xb * vz - vx) + xy * wx - (1.0 + xx) * wy + yb * wz
    f[:, 1] = xi * (yb * vz - vy) + (1.0 + yy) * wx - xy * wy - xb * wz
    f[:, 2] = xi * (xi * vz + rot)
    if not jac:
        return f, None
    J = np.empty((len(x), 3, 9))  # np.empty + explicit zeros: np.zeros (calloc) page-faults on big batches
    J[:, 0, 4] = 0.0
    J[:, 1, 3] = 0.0
    J[:, 2, 3:5] = 0.0
    J[:, 2, 8] = 0.0
    xivz = xi * vz
    J[:, 0, 0] = xivz + yb * wx - 2.0 * xb * wy
    J[:, 0, 1] = xb * wx + wz
    J[:, 0, 2] = xb * vz - vx
    J[:, 1, 0] = -(yb * wy + wz)
    J[:, 1, 1] = xivz + 2.0 * yb * wx - xb * wy
    J[:, 1, 2] = yb * vz - vy
    J[:, 2, 0] = -xi * wy
    J[:, 2, 1] = xi * wx
    J[:, 2, 2] = 2.0 * xivz + rot
    # ∂f/∂q, columns 3..8 = (Vx, Vy, Vz, ωx, ωy, ωz)
    J[:, 0, 3] = -xi
    J[:, 0, 5] = xb * xi
    J[:, 0, 6] = xy
    J[:, 0, 7] = -(1.0 + xx)
    J[:, 0, 8] = yb
    J[:, 1, 4] = -xi
    J[:, 1, 5] = yb * xi
    J[:, 1, 6] = 1.0 + yy
    J[:, 1, 7] = -xy
    J[:, 1, 8] = -xb
    J[:, 2, 5] = xi * xi
    J[:, 2, 6] = xi * yb
    J[:, 2, 7] = -xi * xb
    return f, J


def _rk4(x: np.ndarray, q, h: float):
    """One RK4 step: Ψ (N,3) and ∂Ψ/∂(x, q) (N,3,9), chain rule through the stages (docstring)."""
    k1, D1 = _model(x, q, True)
    k2, J2 = _model(x + (0.5 * h) * k1, q, True)
    D2 = J2 + (0.5 * h) * (J2[:, :, :3] @ D1)
    k3, J3 = _model(x + (0.5 * h) * k2, q, True)
    D3 = J3 + (0.5 * h) * (J3[:, :, :3] @ D2)
    k4, J4 = _model(x + h * k3, q, True)
    D4 = J4 + h * (J4[:, :, :3] @ D3)
    x_next = x + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
    T = (h / 6.0) * (D1 + 2.0 * (D2 + D3) + D4)
    T[:, 0, 0] += 1.0
    T[:, 1, 1] += 1.0
    T[:, 2, 2] += 1.0
    return x_next, T


def _rk4_multi(x: np.ndarray, q, dt: float, n: int):
    """``n`` equal RK4 sub-steps over ``dt`` with the same q; composed ∂Ψ/∂(x, q) (N,3,9)."""
    h = dt / n
    x, T = _rk4(x, q, h)
    for _ in range(n - 1):  # loop over sub-steps (not landmarks)
        x, Tk = _rk4(x, q, h)
        Ak = Tk[:, :, :3]
        T = np.concatenate([Ak @ T[:, :, :3], Ak @ T[:, :, 3:] + Tk[:, :, 3:]], axis=2)
    return x, T


# -- input checks -------------------------------------------------------------------------------
def _array(name: str, a, shape: tuple) -> np.ndarray:
    """Float array of exactly ``shape`` (None = any length), finite; InputError naming ``name``."""
    try:
        a = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric array") from None
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise InputError(f"{name} must have shape {want}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} contains NaN or inf")
    return a


def _states(x) -> np.ndarray:
    return _array("x", x, (None, 3))


def _inputs(q, n: int):
    """q (6,) or (N,6) → six scalars or six (N,) arrays."""
    try:
        q = np.asarray(q, dtype=float)
    except (TypeError, ValueError):
        raise InputError("q must be a numeric array") from None
    if q.shape == (6,):
        if not np.all(np.isfinite(q)):
            raise InputError("q contains NaN or inf")
        return tuple(float(v) for v in q)
    if q.shape != (n, 6):
        raise InputError(f"q must have shape (6,) or (N, 6) = {(n, 6)}, got {q.shape}")
    q = _array("q", q, (n, 6))
    return tuple(q[:, i] for i in range(6))


def _step(dt) -> float:
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.integer, np.floating)) or np.ndim(dt) != 0:
        raise InputError(f"dt must be a scalar number of seconds, got {dt!r}")
    dt = float(dt)
    if not math.isfinite(dt) or dt <= 0.0:
        raise InputError(f"dt must be finite and > 0, got {dt}")
    return dt


def _ids(name: str, ids) -> np.ndarray:
    a = np.asarray(ids)
    if a.ndim != 1:
        raise InputError(f"{name} must be a 1-D array of integer ids, got shape {a.shape}")
    if a.size and a.dtype.kind not in "iu":
        raise InputError(f"{name} must be integers, got dtype {a.dtype}")
    a = a.astype(np.int64)
    if len(np.unique(a)) != len(a):
        raise InputError(f"{name} contains duplicate ids")
    return a


# -- public model functions ---------------------------------------------------------------------
def continuous_dynamics(x, q) -> np.ndarray:
    """f(x, q) = dx/dt (N,3) for states x (N,3) and inputs q = (V, ω), (6,) or (N,6)."""
    x = _states(x)
    return _model(x, _inputs(q, len(x)), False)[0]


def jacobian_x(x, q) -> np.ndarray:
    """F = ∂f/∂x (N,3,3) (formulas in the module docstring)."""
    x = _states(x)
    return np.ascontiguousarray(_model(x, _inputs(q, len(x)), True)[1][:, :, :3])


def jacobian_q(x, q) -> np.ndarray:
    """B = ∂f/∂q (N,3,6), columns (Vx, Vy, Vz, ωx, ωy, ωz)."""
    x = _states(x)
    return np.ascontiguousarray(_model(x, _inputs(q, len(x)), True)[1][:, :, 3:])


def rk4_step(x, q, dt):
    """One RK4 step of length ``dt`` with constant q: ``(x_next (N,3), A (N,3,3), G (N,3,6))``.

    A = ∂Ψ/∂x and G = ∂Ψ/∂q are the exact derivatives of the discrete map (chain rule through the
    four stages, see the module docstring).
    """
    x = _states(x)
    q = _inputs(q, len(x))
    h = _step(dt)
    with np.errstate(over="ignore", invalid="ignore"):
        x_next, T = _rk4(x, q, h)
    if not (np.all(np.isfinite(x_next)) and np.all(np.isfinite(T))):
        raise InputError("rk4_step: the step overflowed (state far outside the model's domain or dt too long)")
    return x_next, np.ascontiguousarray(T[:, :, :3]), np.ascontiguousarray(T[:, :, 3:])


def state_from_points(p_cam) -> np.ndarray:
    """x = (X/Z, Y/Z, 1/Z) of camera-frame points (N,3); every Z must be > 0."""
    p = _array("p_cam", p_cam, (None, 3))
    if np.any(p[:, 2] <= 0):
        raise InputError("p_cam: points must be in front of the camera (Z > 0)")
    return np.stack([p[:, 0] / p[:, 2], p[:, 1] / p[:, 2], 1.0 / p[:, 2]], 1)


def points_from_state(x) -> np.ndarray:
    """P = (x̄, ȳ, 1)/ξ (N,3); every ξ must be > 0."""
    x = _states(x)
    if np.any(x[:, 2] <= 0):
        raise InputError("x: inverse depth must be > 0 to give a point")
    return np.stack([x[:, 0], x[:, 1], np.ones(len(x))], 1) / x[:, 2:3]
