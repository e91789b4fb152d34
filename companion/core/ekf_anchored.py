"""Anchored inverse-depth EKF, one 3-state filter per landmark (docs/derivations/ekf_anchored.md).

:class:`AnchoredInverseDepthEKF` is a bank of independent filters addressed by landmark id.  Its
state x = (θ, φ, ρ) (plus the gyro bias b when attitude drift is modelled), the pixel measurement
model h_c, z = (h_c,x / h_c,z, h_c,y / h_c,z) with its Jacobian H and the looming model h_s, H_s are
stated in :mod:`companion.core.ekf_anchored_model`, with :class:`AnchoredEKFConfig`, the reason
codes and the result types (all importable from here).

Update: iterated EKF (Gauss–Newton on the prior + measurement cost, ``iterations`` relinearizations;
1 = the plain EKF), χ² innovation gate on the first linearization; covariance in the standard form
P = (I − K H) P₀ at the last linearization, symmetrized (the looming update below uses the Joseph form).
Measurement noise R = (σ_px/f)² + σ_att² (white attitude noise of each telemetry sample)
+ 2 (ρ σ_p)² (the telemetry's position error at the anchor and now, seen from the landmark at
inverse depth ρ; treated as white, an approximation for GPS-like correlated error).  With
``position_tau_s`` > 0 that last term is replaced by the position-error states δ, whose covariance
grows between updates (:meth:`AnchoredInverseDepthEKF._propagate`, before every pixel or looming
update of a landmark, accepted or not).

Batch refinement (docs/derivations/ekf_anchored.md § Batch refinement): :meth:`~AnchoredInverseDepthEKF.refine`
replaces a landmark's x and P by the Gauss–Newton MAP over its whole accepted history
(:mod:`companion.core.ekf_anchored_refine`; the estimator keeps the histories and calls it on a doubling
schedule), which undoes the early linearizations the EKF folded in for good.

The numpy code here is the *reference*: every operation is batched over landmarks, arrays of shape
(N, 3), (N, 3, 3), no loop per landmark.  When compiled kernels are on (:mod:`companion.core.jit`)
the pixel and looming updates (with their bookkeeping) and :meth:`~AnchoredInverseDepthEKF.estimates`
run instead as one loop over landmarks in :mod:`companion.core.ekf_anchored_kernels`, the same
equations to float rounding (tests/test_ekf_anchored_kernels.py compares the two).

Looming (docs/derivations/looming.md): the scale change z_s = h_s(x) of the model, fused as a scalar
measurement.  Noise R_s = σ_s² + σ_floor² (σ_s from the matcher's Gauss–Newton covariance,
``looming_sigma_floor``); χ² (1 dof) gate ``looming_gate_probability``; update (iterated
``looming_iterations`` times: one step suffices for a measurement this weak per frame) in Joseph
form P = (I − K H) P (I − K H)ᵀ + K R Kᵀ, batched over landmarks.  Input that cannot be a scale is
not an error in flight: NaN (the matcher could not measure it) is skipped and counted
(``LOOM_NAN``), a non-positive or non-finite scale or σ is refused (``LOOM_NONPOSITIVE``).
"""

from __future__ import annotations

import math

import numpy as np

from companion.config import require_finite
from companion.core import ekf_anchored_kernels as _kernels
from companion.core import jit
from companion.core.idbank import lookup, rows_or_raise
# the filter's configuration, reason codes, results and measurement models, re-exported: every public
# name stays importable from here
from companion.core.ekf_anchored_model import (  # noqa: F401
    BEHIND,
    GATED,
    LOOM_NAN,
    LOOM_NONPOSITIVE,
    LOOM_OFF_AXIS,
    UPDATE_REASON_NAMES,
    UPDATED,
    AnchoredEKFConfig,
    LandmarkEstimates,
    UpdateResult,
    _looming_args,
    _looming_predict,
    _no_update,
    _predict,
    _ray_columns,
    _ray_map,
    angles_of,
    layout_of,
    inverse_depth_state,
    ray,
    ray_jacobian,
)
from companion.errors import InputError


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
        #: state size n, whether the gyro bias b is x[3:6], and the index of the position-error states δ (−1: none):
        #: x = (θ, φ, ρ, [b], [δ]) (:meth:`AnchoredEKFConfig.layout`)
        self.n, self.drift, self.i_pos = config.layout()
        #: δ are consider (Schmidt–Kalman) states: zero gain, mean kept at 0 (§ Position error states, consider form)
        self.consider = bool(config.position_consider and self.i_pos >= 0)
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
        self.nis_C = np.zeros((0, 3))  # camera centre of the last measurement that entered nis_avg (the anchor's at first)
        self.n_looming = np.zeros(0, dtype=np.int64)  # accepted looming (scale) updates
        self.t_last = np.zeros(0)  # time δ's covariance was last propagated to (§ Position error states)
        self.rho_c = np.zeros(0)  # ρ̂ when the landmark was first converged, NaN before (§ Drift test)
        self.P_rho_c = np.zeros(0)  # its variance then
        self.xy_anchor = np.zeros((0, 2))  # the anchor pixel (normalized): the batch refinement's prior (:meth:`_prior`)
        #: the pixel kernels' constants: (σ_px/f)² + σ_att² (2,), the white σ_p (0 with the δ states), χ²₂ gate,
        #: iterations, reject limit, NIS window, mean-NIS limit, the index of δ (−1: none), 2σ_p² and τ of its
        #: process, whether δ are consider states (§ Measurement noise, § Update, § Bookkeeping, § Position error states)
        self._kernel_constants = (
            self.sigma_xy**2 + np.radians(config.attitude_sigma_deg) ** 2, self._white_position_sigma, config.gate_threshold,
            config.iterations, config.max_consecutive_rejects, float(config.nis_window), float(config.max_mean_nis),
            self.i_pos, float(config.position_variance_limit), float(config.position_tau_s), self.consider,
            self._nis_baseline)

    @property
    def _nis_baseline(self) -> float:
        """tan of ``nis_min_baseline_deg``: the least baseline per unit range for a NIS to enter the mean (0: every one)."""
        return math.tan(math.radians(self.config.nis_min_baseline_deg))

    @property
    def _white_position_sigma(self) -> float:
        """σ_p of the white position term of R: 0 when the error is carried by the δ states instead."""
        return 0.0 if self.config.position_states else float(self.config.position_sigma_m)

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
        x0, P0 = self._prior(xy, rho, srho)
        zi = np.zeros(m, np.int64)
        self._insert(dict(ids=ids, x=x0, P=P0, R_world_camA=R, p_world_camA=p, t_anchor=t, n_updates=zi,
                          n_rejects=zi, diverged=np.zeros(m, bool), nis_avg=np.zeros(m), nis_count=zi, nis_C=p.copy(), n_looming=zi,
                          t_last=np.array(t, float), rho_c=np.full(m, np.nan), P_rho_c=np.full(m, np.nan),
                          xy_anchor=xy.copy()))

    def _prior(self, xy: np.ndarray, rho, srho) -> tuple[np.ndarray, np.ndarray]:
        """§ Initialization: x₀ (M,n) and P₀ (M,n,n) of landmarks first seen at normalized ``xy`` (M,2) with
        ρ ~ N(``rho``, ``srho``²): (θ, φ) of the pixel with its σ mapped through their Jacobian, the gyro-bias
        prior, δ = 0 exactly (the anchor is where δ is defined).  The batch refinement reuses it as its prior."""
        m = len(xy)
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
        x0 = np.zeros((m, self.n))
        x0[:, 0], x0[:, 1], x0[:, 2] = theta, phi, rho
        if self.drift:
            sb = np.radians(self.config.attitude_drift_deg_s)
            P0[:, 3:6, 3:6] = sb**2 * np.eye(3)
        # δ = e(t) − e(t_anchor) is exactly 0 at the anchor: zero mean, zero variance (§ Position error states)
        return x0, P0

    #: per-landmark arrays, all aligned with ``ids`` (kept sorted ascending)
    _FIELDS = ("ids", "x", "P", "R_world_camA", "p_world_camA", "t_anchor", "n_updates", "n_rejects", "diverged", "nis_avg",
               "nis_count", "nis_C", "n_looming", "t_last", "rho_c", "P_rho_c", "xy_anchor")

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
        if other.config.layout() != self.config.layout() or np.any(other.contains(ids)):
            raise InputError("move_to: the other bank must have the same state size and none of the ids")
        rows = self.index_of(ids)
        other._insert({name: getattr(self, name)[rows] for name in self._FIELDS})
        self.remove(ids)

    # -- model ----------------------------------------------------------------------------------
    @staticmethod
    def measure(x, R_world_camA, p_world_camA, R_world_cam, p_world_cam, dt=None, position_states=False):
        """h_c (N,3), predicted z (N,2) and H (N,2,n) for states x (N,n) seen from (R_world_cam, C).

        The current pose may be shared, (3,3) and (3,), or per landmark, (N,3,3) and (N,3).
        x = (θ, φ, ρ, [b], [δ]): with ``position_states`` the last three states are δ; the gyro bias
        b is present when the remaining size is 6, and then ``dt`` (N,) is t − t_anchor.
        """
        R_cam_world = np.swapaxes(R_world_cam, -1, -2)
        drift, i_pos = layout_of(x.shape[1], position_states)
        D = (0.5 * dt)[:, None, None] * (R_world_camA + R_world_cam) if drift else None
        return _predict(x, _ray_map(R_world_camA), p_world_camA - p_world_cam, R_cam_world, D, i_pos)

    def measurement_variance(self, x: np.ndarray) -> np.ndarray:
        """Diagonal of R (M,2) at states x (M,n): pixel noise, white attitude noise of the telemetry
        and 2 (ρ σ_p)² for the anchor and current position errors ⟂ to the ray (normalized units)."""
        att = np.radians(self.config.attitude_sigma_deg) ** 2
        var = self.sigma_xy**2 + att
        if self._white_position_sigma > 0:  # not with the δ states (§ Position error states)
            pos = 2.0 * (np.maximum(x[:, 2], 0.0) * self._white_position_sigma) ** 2
            return var + pos[:, None]
        return np.broadcast_to(var, (len(x), 2))

    def _propagate(self, rows, t) -> None:
        """§ Position error states, process: for bank rows ``rows`` (distinct) advanced from their last
        propagation t_last to ``t`` (scalar or per row; nothing where t ≤ t_last), Var δ per axis grows by
        V(t − t_A) − V(t_last − t_A), V = :meth:`AnchoredEKFConfig.delta_variance`, so that it equals the
        Gauss–Markov difference's 2σ_p² (1 − exp(−(t − t_A)/τ)) at every update when no measurement has informed it."""
        if self.i_pos < 0 or len(rows) == 0:
            return
        t = np.broadcast_to(np.asarray(t, float), (len(rows),))
        t_last, tA = self.t_last[rows], self.t_anchor[rows]
        later = t > t_last
        V = self.config.delta_variance
        grow = np.where(later, V(t - tA) - V(t_last - tA), 0.0)
        i = self.i_pos + np.arange(3)
        self.P[rows[:, None], i, i] += grow[:, None]
        self.t_last[rows] = np.where(later, t, t_last)

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
        for bank, _, r, _ in parts:
            bank._propagate(r, t)
        gather = [np.concatenate([getattr(b, name)[r] for b, _, r, _ in parts])
                  for name in ("x", "P", "R_world_camA", "p_world_camA", "t_anchor")]
        x, P, good, nis, reason = parts[0][0]._solve(*gather, np.concatenate([z for *_, z in parts]), Rc, C, t)
        out = []
        for (bank, ids, r, _), lo, hi in zip(parts, np.concatenate([[0], ends[:-1]]), ends):
            bank._commit(r, x[lo:hi], P[lo:hi], good[lo:hi], nis[lo:hi], C)
            out.append(UpdateResult(ids, good[lo:hi], nis[lo:hi], reason[lo:hi]))
        return out

    def _update_rows(self, rows, z, Rc, C, t):
        """The iterated EKF update of bank rows ``rows`` (validated inputs): (accepted, nis, reason)."""
        if jit.ENABLED:
            return self._kernel_rows(rows, z, Rc, C, t)
        self._propagate(rows, t)
        x, P, good, nis, reason = self._solve(
            self.x[rows], self.P[rows], self.R_world_camA[rows], self.p_world_camA[rows], self.t_anchor[rows], z, Rc, C, t
        )
        self._commit(rows, x, P, good, nis, C)
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
                self.diverged, self.nis_avg, self.nis_count, self.nis_C, self.t_last)

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
        D = (0.5 * (t - tA))[:, None, None] * (RA + Rc) if self.drift else None
        i_pos = self.i_pos

        def gain(H):
            """P0 Hᵀ (M,n,2) and S⁻¹ (M,2,2), S = H P0 Hᵀ + R."""
            PHt = P0 @ np.swapaxes(H, 1, 2)
            S = H @ PHt
            S[:, 0, 0] += var[:, 0]
            S[:, 1, 1] += var[:, 1]
            return PHt, _inv2(S)

        h, zhat, H = _predict(x0, ray_map, a, R_cam_world, D, i_pos)
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
        K = self._consider_gain(PHt @ Si)
        innov = y  # at x_0 the H_0 (x0 − x_0) term vanishes
        for it in range(cfg.iterations):
            if it > 0:
                h, zhat, H = _predict(xi, ray_map, a, R_cam_world, D, i_pos)
                PHt, Si = gain(H)
                K = self._consider_gain(PHt @ Si)
                ok &= h[:, 2] > 1e-9
                innov = z - zhat - (H @ (x0 - xi)[:, :, None])[:, :, 0]
            x_new = x0 + (K @ innov[:, :, None])[:, :, 0]
            xi = np.where(ok[:, None], x_new, xi)
        # P = (I − K H) P0 = P0 − K (P0 Hᵀ)ᵀ at the last linearization, symmetrized
        P_new = P0 - K @ np.swapaxes(PHt, 1, 2)
        if self.consider:  # (I − K H) P₀ (I − K H)ᵀ + K R Kᵀ with K's δ rows 0: the δ rows mirror the δ columns, P_δδ stays
            d = slice(i_pos, i_pos + 3)
            P_new[:, d, :] = np.swapaxes(P_new[:, :, d], 1, 2)
            P_new[:, d, d] = P0[:, d, d]
        P_new = 0.5 * (P_new + np.swapaxes(P_new, 1, 2))
        good = ok & np.isfinite(xi).all(1) & np.isfinite(P_new).all((1, 2))
        reason[ok & ~good] = GATED
        return np.where(good[:, None], xi, x0), np.where(good[:, None, None], P_new, P0), good, nis, reason

    def _consider_gain(self, K: np.ndarray) -> np.ndarray:
        """K (M,n[,k]) with the δ rows set to 0 when δ are consider states (§ Position error states, consider form):
        an update then leaves δ's mean (0) and covariance alone and moves only what it correlates with."""
        if self.consider:
            K = K.copy()
            K[:, self.i_pos : self.i_pos + 3] = 0.0
        return K

    def _commit(self, rows, x, P, good, nis, C) -> None:
        """Store the updated rows and their accept / reject / NIS history (C (3,): the camera centre of the update;
        § Bookkeeping: with ``nis_min_baseline_deg`` a NIS enters the mean only once the camera has moved that far)."""
        cfg = self.config
        self.x[rows] = x
        self.P[rows] = P
        self.n_updates[rows] += good
        n_rejects = np.where(good, 0, self.n_rejects[rows] + 1)
        self.n_rejects[rows] = n_rejects
        self.diverged[rows] |= n_rejects >= cfg.max_consecutive_rejects
        cap = 2.0 * cfg.gate_threshold
        nis_c = np.where(np.isfinite(nis), np.minimum(nis, cap), cap)
        rows = np.asarray(rows)
        if self._nis_baseline > 0:
            C = np.broadcast_to(np.asarray(C, float), (len(rows), 3))  # one pose (3,) or one per landmark (M, 3)
            moved = np.linalg.norm(C - self.nis_C[rows], axis=1) * np.maximum(x[:, 2], 0.0) >= self._nis_baseline
            rows, nis_c = rows[moved], nis_c[moved]
            self.nis_C[rows] = C[moved]
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
                        dt_prev=None, dt=None, position_states=False):
        """Predicted scale change h_s (N,) and H_s (N,n) of states x (N,n) between the previous pose
        (R_world_cam_prev, p_world_cam_prev) and the current one; poses (3,3)/(3,) or per landmark.
        Layout as in :meth:`measure`; with the drift states ``dt_prev`` and ``dt`` (N,) are t' − t_anchor
        and t − t_anchor."""
        n = len(x)
        RA = np.broadcast_to(np.asarray(R_world_camA, float), (n, 3, 3))
        drift, i_pos = layout_of(x.shape[1], position_states)
        zero = np.zeros(n)
        args = _looming_args(RA, np.asarray(p_world_camA, float), zero, np.asarray(R_world_cam_prev, float),
                             np.asarray(p_world_cam_prev, float), dt_prev if drift else zero,
                             np.asarray(R_world_cam, float), np.asarray(p_world_cam, float), dt if drift else zero, drift)
        _, _, hs, Hs = _looming_predict(x, *args, i_pos)
        return hs, Hs

    def update_looming(self, ids, scale, scale_sigma, R_world_cam_prev, p_world_cam_prev, t_prev,
                       R_world_cam, p_world_cam, t) -> UpdateResult:
        """Fuse one looming measurement per listed landmark: ``scale`` (M,) = image size now / in the
        previous frame (pose R_world_cam_prev, p_world_cam_prev at t_prev) with σ ``scale_sigma``
        (M,) or None (the floor only).  NaN scales are skipped (``LOOM_NAN``), non-positive or
        infinite ones refused (``LOOM_NONPOSITIVE``); neither raises.  With the position-error states
        every listed landmark's δ covariance is first propagated to t, skipped or not (time has passed)."""
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
        for (bank, *_), r in zip(parts, rows):
            bank._propagate(r, t)
        if len(use):
            bank_of = np.searchsorted(ends, use, side="right")
            gather = {name: np.concatenate([getattr(b, name)[r] for (b, *_), r in zip(parts, rows)])[use]
                      for name in ("x", "P", "R_world_camA", "p_world_camA", "t_anchor")}
            var = first.config.looming_variance(sig[use])
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
            self.x, self.P, self.R_world_camA, self.p_world_camA, self.t_anchor, self.n_looming, self.t_last, rows, c(sc),
            c(sg), c(Rp), c(Cp), t_prev, c(Rc), c(C), t, float(cfg.looming_sigma_floor), cfg.looming_gate_threshold,
            cfg.looming_iterations, self.i_pos, float(cfg.position_variance_limit), float(cfg.position_tau_s), self.consider,
            accepted, nis, reason)
        return UpdateResult(ids, accepted, nis, reason)

    def _solve_looming(self, x0, P0, RA, pA, tA, z, var, Rp, Cp, t_prev, Rc, C, t):
        """Iterated scalar EKF update (Joseph form) of states x0 (M,n), P0 (M,n,n) with scale
        measurements z (M,) of variance var (M,): (x, P, accepted, nis, reason)."""
        cfg = self.config
        args = _looming_args(RA, pA, tA, Rp, Cp, t_prev, Rc, C, t, self.drift)
        hzp, hzn, hs, Hs = _looming_predict(x0, *args, self.i_pos)
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
        K = self._consider_gain(PHt / S[:, None])
        innov = y
        H = Hs
        for it in range(cfg.looming_iterations):
            if it > 0:
                hzp, hzn, hs, H = _looming_predict(xi, *args, self.i_pos)
                ok &= (hzp > 1e-9) & (hzn > 1e-9)
                PHt = (P0 @ H[:, :, None])[:, :, 0]
                S = np.einsum("ni,ni->n", H, PHt) + var
                K = self._consider_gain(PHt / S[:, None])
                innov = z - hs - np.einsum("ni,ni->n", H, x0 - xi)
            xi = np.where(ok[:, None], x0 + K * innov[:, None], xi)
        # Joseph form: (I − K H) P0 (I − K H)ᵀ + K R Kᵀ
        A = np.eye(self.n) - K[:, :, None] * H[:, None, :]
        P_new = A @ P0 @ np.swapaxes(A, 1, 2) + var[:, None, None] * (K[:, :, None] * K[:, None, :])
        P_new = 0.5 * (P_new + np.swapaxes(P_new, 1, 2))
        good = ok & np.isfinite(xi).all(1) & np.isfinite(P_new).all((1, 2))
        reason[ok & ~good] = GATED
        return np.where(good[:, None], xi, x0), np.where(good[:, None, None], P_new, P0), good, nis, reason

    # -- batch refinement (docs/derivations/ekf_anchored.md § Batch refinement) --------------
    def refine(self, ids, history: dict, rho_prior: float, rho_prior_sigma: float) -> np.ndarray:
        """Replace the listed landmarks' x and P by the batch MAP over ``history`` (their
        :meth:`ObservationHistory.gather`, same order) where it lowers the cost: the prior is the anchor
        pixel's (θ, φ), ρ ~ N(``rho_prior``, ``rho_prior_sigma``²) (the wide prior, not a triangulated
        seed) and the gyro-bias prior; returns the (M,) bool of landmarks replaced.  A bank with the
        position-error states is not refined (InputError)."""
        from companion.core.ekf_anchored_refine import refine as _refine

        if self.i_pos >= 0:
            raise InputError("refine: a bank with position-error states cannot be refined in batch")
        rows = self.index_of(ids)
        m = len(rows)
        if m == 0:
            return np.zeros(0, bool)
        if not (np.isfinite(rho_prior) and np.isfinite(rho_prior_sigma) and rho_prior_sigma > 0):
            raise InputError("refine: the inverse-depth prior must be finite with σ > 0")
        xp, Pp = self._prior(self.xy_anchor[rows], rho_prior, rho_prior_sigma)
        res = _refine(self.x[rows], self.P[rows], xp, Pp, self.R_world_camA[rows], self.p_world_camA[rows],
                      self.t_anchor[rows], history, self.measurement_variance, self.drift, self.i_pos,
                      self.config.refine_iterations)
        self.x[rows], self.P[rows] = res.x, res.P
        return res.improved

    # -- output ---------------------------------------------------------------------------------
    #: the drift test's denominator never falls below this fraction of P_c (a filter that has learnt nothing
    #: since convergence must not have moved; the floor keeps rounding from dividing by zero)
    DRIFT_FLOOR = 0.01

    def drift_test(self, converged) -> np.ndarray:
        """(N,) χ²₁ of each landmark's inverse range against its value at first convergence
        (docs/derivations/ekf_anchored.md § Drift test): ρ is a static state, so its estimate ρ̂ is a
        martingale and ρ̂ − ρ̂_c has variance P_c − P.  ``converged`` (N,) bool: the landmarks converged
        now; those without a reference take it now (statistic 0).  NaN where none is held.  With
        ``max_drift_chi2`` > 0 a statistic above it flags the landmark diverged (retired with its track)."""
        conv = np.asarray(converged, bool).reshape(-1)
        if conv.shape != self.ids.shape:
            raise InputError(f"drift_test: converged must have {len(self.ids)} entries, got {conv.shape}")
        rho, P = self.x[:, 2], self.P[:, 2, 2]
        new = conv & np.isnan(self.rho_c)
        self.rho_c[new], self.P_rho_c[new] = rho[new], P[new]
        den = np.maximum(self.P_rho_c - P, self.DRIFT_FLOOR * self.P_rho_c)
        with np.errstate(invalid="ignore", divide="ignore"):
            stat = (rho - self.rho_c) ** 2 / den
        limit = self.config.max_drift_chi2
        if limit > 0:
            self.diverged |= stat > limit  # NaN (no reference) compares False
        return stat

    def _apply_limits(self, converged: np.ndarray, valid: np.ndarray, rng: np.ndarray, rsig: np.ndarray) -> None:
        """§ Outputs and convergence, in place: with σ_near = ``converged_near_sigma_m`` > 0 a valid landmark with
        enough updates and ρ > 1/max_range is converged when σ_r < σ_near whatever σ_r / r; then ``converged``
        also needs σ_r < max(σ_floor, k_far · r) when k_far > 0."""
        cfg = self.config
        if cfg.converged_near_sigma_m > 0:
            converged |= (valid & (self.x[:, 2] > 1.0 / cfg.max_range_m) & (self.n_updates >= cfg.min_updates)
                          & (rsig < cfg.converged_near_sigma_m))
        if cfg.converged_far_rel_sigma > 0:
            converged &= rsig < np.maximum(cfg.converged_sigma_floor_m, cfg.converged_far_rel_sigma * rng)

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
                               float(cfg.max_range_m), float(cfg.converged_rel_sigma), cfg.min_updates, self.i_pos,
                               p_world, rng, rsig, srho, valid, converged)
            self._apply_limits(converged, valid, rng, rsig)
            return LandmarkEstimates(self.ids.copy(), p_world, rng, rsig, x[:, 2].copy(), srho, converged, valid)
        rho = x[:, 2]
        srho = np.sqrt(np.maximum(self.P[:, 2, 2], 0.0))
        rho_floor = 1.0 / cfg.max_range_m
        rho_eff = np.maximum(rho, rho_floor)
        Rm = np.einsum("nij,njk->nik", self.R_world_camA, _ray_columns(x[:, 0], x[:, 1]))  # R [m, ∂m/∂θ, ∂m/∂φ]
        mw = Rm[:, :, 0]
        a = self.p_world_camA - C
        # the range's states: (θ, φ, ρ), and δ when carried (the true C_A − C is a + δ)
        idx = [0, 1, 2] if self.i_pos < 0 else [0, 1, 2, self.i_pos, self.i_pos + 1, self.i_pos + 2]
        if self.i_pos >= 0:
            a = a + x[:, self.i_pos : self.i_pos + 3]
        g = rho_eff[:, None] * a + mw  # ρ · (p − C)
        ng = np.linalg.norm(g, axis=1)
        rng = np.minimum(ng / rho_eff, cfg.max_range_m)
        J = np.zeros((len(x), len(idx)))
        J[:, :2] = np.einsum("ni,nik->nk", g, Rm[:, :, 1:]) / (ng * rho_eff)[:, None]
        J[:, 2] = np.einsum("ni,ni->n", g, a) / (ng * rho_eff) - ng / rho_eff**2
        if self.i_pos >= 0:
            J[:, 3:] = g / ng[:, None]  # ∂|a + δ + R m/ρ|/∂δ: the unit vector to the point
        P_r = self.P[:, idx][:, :, idx]
        rsig = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", J, P_r, J), 0.0))
        rsig = np.minimum(rsig, cfg.max_range_m)
        p_world = self.p_world_camA + mw / rho_eff[:, None]
        if self.i_pos >= 0:  # in the telemetry's world frame as of now: C + (C_A − C + δ) + R m/ρ
            p_world = p_world + x[:, self.i_pos : self.i_pos + 3]
        valid = ~self.diverged & (rho > -3.0 * srho)
        converged = valid & (rho > rho_floor) & (rsig < cfg.converged_rel_sigma * rng) & (self.n_updates >= cfg.min_updates)
        self._apply_limits(converged, valid, rng, rsig)
        return LandmarkEstimates(self.ids.copy(), p_world, rng, rsig, rho.copy(), srho, converged, valid)
