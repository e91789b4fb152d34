"""The one entry point from pixel tracks and camera poses to ranges (docs/derivations/triangulation.md, ekf_anchored.md, ekf_landmark.md).

``RangeEstimator.process`` takes one frame at a time, in time order: the camera pose from
telemetry (``R_world_cam``, ``p_world_cam``; optionally the camera velocity and angular rate), and
the tracked pixels of that frame with their track ids.  It returns the current estimate of every
landmark.  The benchmarks drive it now; the live process and the replay tool drive it later.

Life of a landmark (the "combined method" of seeds 000 and 004):

1. *pending*: its first observation is the anchor; the next observations are buffered
   (at most ``init_max_frames``).
2. *initialization*: as soon as the multi-view triangulation of the buffered views (gated on
   their longest baseline) passes every gate, the filter starts from it, with the
   triangulated σ inflated by ``tri_sigma_scale`` because the replay below reuses those pixels;
   if the gates still fail after ``init_max_frames`` frames, the filter starts from the wide
   inverse-depth prior that includes infinity.
3. *filtering*: the anchored EKF (§3.4) is anchored at the first observation and replays the
   buffered observations, so no measurement is lost; the seed-000 EKF (§3.5) starts in the
   current frame and is then propagated with the camera twist between frames.  The replay from
   the wide prior needs nothing learnt at initialization, so it runs as the observations arrive
   (one batch per frame in a second bank of pending filters) and a landmark that times out moves
   over unchanged; a triangulated start replays its buffer from the triangulated prior.
4. a landmark unseen for ``max_unseen_s``, or flagged diverged or invalid, is dropped.

Looming (docs/derivations/looming.md): with the anchored filter, ``process`` optionally takes each track's patch
scale change since the previous frame (``scale``, ``scale_sigma``, keyed like the pixels, NaN where
the matcher could not measure it: see :class:`companion.core.tracks.TrackFrame`).  After the pixel
update, the running filters *and* the pending landmarks' wide-prior filters get the looming
update (``[ekf_anchored] looming``), so a landmark on the direction of travel, which never
triangulates, starts from the wide prior and converges by looming.  The scale is relative to the
previous frame given to ``process``; a triangulated start replays its buffered pixels only.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion.config import require, require_finite
from companion.core import ekf_anchored_kernels, jit
from companion.core.camera import CameraConfig, CameraModel
from companion.core.ekf_anchored import LOOM_OFF_AXIS, UPDATE_REASON_NAMES, AnchoredEKFConfig, AnchoredInverseDepthEKF
from companion.core.ekf_landmark import LandmarkEKFBank, LandmarkEKFConfig
from companion.core.frames import is_orthonormal, se3_twist
from companion.core.idbank import lookup
from companion.core.obs_history import ObservationHistory
from companion.core.triangulation import Reject, TriangulationConfig, triangulate_multiview
from companion.core.triangulation import warm_up as warm_up_triangulation
from companion.errors import InputError

FILTERS = ("anchored", "landmark")


@dataclasses.dataclass(frozen=True)
class EstimatorConfig:
    """The ``[estimator]`` table."""

    filter: str = "anchored"  # "anchored" (§3.4) or "landmark" (seed 000, §3.5)
    init_max_frames: int = 10  # frames to wait for a triangulation before the wide prior
    prior_inv_depth: float = 0.01  # wide prior on inverse range ρ0 (1/m), used without triangulation
    prior_inv_depth_sigma: float = 0.02  # its σ: ρ = 0 (a point at infinity) lies within 1σ
    tri_sigma_scale: float = 3.0  # inflation of the triangulated σ used to seed a filter
    max_unseen_s: float = 0.5  # drop a landmark not observed for this long
    max_landmarks: int = 1000  # hard bound on pending + filtered landmarks

    def __post_init__(self) -> None:
        require(self.filter in FILTERS, f"filter must be one of {FILTERS}, got {self.filter!r}")
        require(isinstance(self.init_max_frames, int) and 1 <= self.init_max_frames <= 1000, "init_max_frames must be an integer in 1..1000")
        require_finite("prior_inv_depth", self.prior_inv_depth, nonnegative=True)
        require_finite("prior_inv_depth_sigma", self.prior_inv_depth_sigma, positive=True)
        require_finite("tri_sigma_scale", self.tri_sigma_scale, positive=True)
        require(self.tri_sigma_scale >= 1.0, f"tri_sigma_scale must be >= 1, got {self.tri_sigma_scale}")
        require_finite("max_unseen_s", self.max_unseen_s, positive=True)
        require(isinstance(self.max_landmarks, int) and self.max_landmarks > 0, "max_landmarks must be a positive integer")


@dataclasses.dataclass
class RangeOutput:
    """Estimates after one frame, relative to that frame's camera; every array is finite."""

    t: float
    ids: np.ndarray  # (N,) landmark (track) ids with a running filter
    p_world: np.ndarray  # (N, 3)
    range: np.ndarray  # (N,) m from the camera centre
    range_sigma: np.ndarray  # (N,)
    converged: np.ndarray  # (N,) bool
    valid: np.ndarray  # (N,) bool
    n_pending: int  # landmarks waiting for initialization
    n_initialized_tri: int  # started from triangulation in this frame
    n_initialized_prior: int  # started from the wide prior in this frame
    n_rejected: int  # measurements refused by the χ² gate in this frame
    tri_reasons: dict  # Reject name -> count among pending landmarks tried this frame
    retired_ids: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))  # diverged this frame: end their tracks
    n_looming: int = 0  # looming (scale) updates accepted in this frame (running + pending filters)
    looming_reasons: dict = dataclasses.field(default_factory=dict)  # reason name -> count of looming measurements not applied
    mean_nis: np.ndarray | None = None  # (N,) each filter's running mean NIS (consistency with a static point), None = not computed
    n_refined: int = 0  # landmarks replaced by their batch refinement in this frame


def _det3(R: np.ndarray) -> float:
    """Determinant of one 3×3 matrix (cofactor expansion; cheaper than np.linalg.det for one)."""
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def _world_rays(xy: np.ndarray, R_world_cam: np.ndarray) -> np.ndarray:
    """Rays R_world_cam (x̄, ȳ, 1) (M, 3) of normalized points xy (M, 2) seen from one camera."""
    return xy @ R_world_cam[:, :2].T + R_world_cam[:, 2]


class _Pending:
    """Vectorized store of landmarks awaiting initialization (anchor + buffered observations)."""

    def __init__(self, window: int):
        self.W = window
        self.ids = np.zeros(0, np.int64)
        self.count = np.zeros(0, np.int64)  # observations stored (≥ 1, anchor included)
        self.t = np.zeros((0, window + 1))
        self.xy = np.zeros((0, window + 1, 2))
        self.R = np.zeros((0, window + 1, 3, 3))
        self.p = np.zeros((0, window + 1, 3))
        self.ray = np.zeros((0, window + 1, 3))  # R (x̄, ȳ, 1): each view's ray in the world frame (triangulation)
        self.t_last = np.zeros(0)

    _fields = ("ids", "count", "t", "xy", "R", "p", "ray", "t_last")

    def __len__(self) -> int:
        return len(self.ids)

    def rows_of(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mask of ids present, their rows)."""
        if len(self.ids) == 0:
            return np.zeros(len(ids), bool), np.zeros(len(ids), np.int64)
        order = np.argsort(self.ids)
        pos = np.minimum(np.searchsorted(self.ids[order], ids), len(self.ids) - 1)
        rows = order[pos]
        return self.ids[rows] == ids, rows

    def add(self, ids, t, xy, R, p) -> None:
        m = len(ids)
        if m == 0:
            return
        W1 = self.W + 1
        new = {
            "ids": ids, "count": np.ones(m, np.int64), "t": np.zeros((m, W1)), "xy": np.zeros((m, W1, 2)),
            "R": np.broadcast_to(np.eye(3), (m, W1, 3, 3)).copy(), "p": np.zeros((m, W1, 3)), "ray": np.zeros((m, W1, 3)),
            "t_last": np.full(m, t),
        }
        new["t"][:, 0] = t
        new["xy"][:, 0] = xy
        new["R"][:, 0] = R
        new["p"][:, 0] = p
        new["ray"][:, 0] = _world_rays(xy, R)
        for f in self._fields:
            setattr(self, f, np.concatenate([getattr(self, f), new[f]]))

    def append(self, rows, t, xy, R, p) -> None:
        c = self.count[rows]
        self.t[rows, c] = t
        self.xy[rows, c] = xy
        self.R[rows, c] = R
        self.p[rows, c] = p
        self.ray[rows, c] = _world_rays(xy, R)
        self.count[rows] = c + 1
        self.t_last[rows] = t

    def keep(self, mask) -> None:
        for f in self._fields:
            setattr(self, f, getattr(self, f)[mask])


class RangeEstimator:
    """Tracks + poses in, landmark ranges out; see the module docstring for the life cycle."""

    def __init__(
        self,
        camera: CameraConfig,
        config: EstimatorConfig | None = None,
        triangulation: TriangulationConfig | None = None,
        ekf_anchored: AnchoredEKFConfig | None = None,
        ekf_landmark: LandmarkEKFConfig | None = None,
    ):
        self.camera = CameraModel(camera)
        self.config = config or EstimatorConfig()
        self.tri_config = triangulation or TriangulationConfig()
        fx, fy = camera.fx, camera.fy
        if self.config.filter == "anchored":
            self.ekf = AnchoredInverseDepthEKF(ekf_anchored or AnchoredEKFConfig(), fx, fy)
        else:
            self.ekf = LandmarkEKFBank(ekf_landmark or LandmarkEKFConfig(), fx, fy)
        # measurement σ in normalized units, used by the triangulation's uncertainty gate
        self.sigma_xy = self.ekf.config.sigma_px / min(fx, fy)
        self.pending = _Pending(self.config.init_max_frames)
        #: anchored filters of the pending landmarks from the wide prior, fed as observations arrive
        self.prior_bank = (
            AnchoredInverseDepthEKF(self.ekf.config, fx, fy) if isinstance(self.ekf, AnchoredInverseDepthEKF) else None
        )
        #: each landmark's accepted observations, for the batch refinement (anchored filter, ``refine_max_obs`` > 0)
        acfg = self.ekf.config if isinstance(self.ekf, AnchoredInverseDepthEKF) else None
        self.history = ObservationHistory(acfg.refine_max_obs, acfg.refine_min_obs) if acfg is not None and acfg.refine else None
        self.t_seen = np.zeros(0)  # last observation time of each filtered landmark, aligned with ekf.ids
        self._seen_ids = np.zeros(0, np.int64)
        self.t_prev: float | None = None
        self.pose_prev: tuple[np.ndarray, np.ndarray] | None = None
        #: ids of tracks whose filters diverged (inconsistent with a static point): never restarted
        self.retired = np.zeros(0, np.int64)
        self._retired_now = np.zeros(0, np.int64)
        if jit.ENABLED:  # load (or compile) the kernels now: ~1 s from numba's cache, which must not fall on a frame
            ekf_anchored_kernels.warm_up()
            warm_up_triangulation()

    # -- validation -----------------------------------------------------------------------------
    @staticmethod
    def _validate(t, R_world_cam, p_world_cam, ids, uv):
        if not np.isfinite(t):
            raise InputError(f"frame time is not finite: {t!r}")
        R = np.asarray(R_world_cam, float)
        p = np.asarray(p_world_cam, float)
        if R.shape != (3, 3) or p.shape != (3,):
            raise InputError(f"camera pose must be R (3,3) and p (3,), got {R.shape} and {p.shape}")
        if not (np.isfinite(R).all() and np.isfinite(p).all()):
            raise InputError("camera pose contains NaN or inf")
        if not is_orthonormal(R) or _det3(R) < 0:
            raise InputError("R_world_cam is not a rotation matrix")
        ids = np.asarray(ids)
        if ids.ndim != 1 or (len(ids) and not np.issubdtype(ids.dtype, np.integer)):
            raise InputError(f"ids must be a 1-D integer array, got shape {ids.shape} dtype {ids.dtype}")
        uv = np.asarray(uv, float)
        if uv.shape != (len(ids), 2):
            raise InputError(f"uv must have shape ({len(ids)}, 2) to match ids, got {uv.shape}")
        if not np.isfinite(uv).all():
            bad = ids[~np.all(np.isfinite(uv), 1)]
            raise InputError(f"uv contains NaN or inf for track ids {bad[:10].tolist()}")
        ids = ids.astype(np.int64)
        if len(ids) > 1:
            s = np.sort(ids)
            if (s[1:] == s[:-1]).any():
                raise InputError("ids contain duplicates")
        return R, p, ids, uv

    # -- main step ------------------------------------------------------------------------------
    def process(self, t, R_world_cam, p_world_cam, ids, uv, v_cam=None, w_cam=None, scale=None, scale_sigma=None) -> RangeOutput:
        """Fuse one frame.  ``uv``: raw (distorted) pixels (M, 2) of tracks ``ids`` (M,).

        ``scale`` / ``scale_sigma`` (M,), optional: each track's patch scale change since the
        previous frame and its σ (NaN = not measured), fused as looming (module docstring)."""
        R, p, ids, uv = self._validate(t, R_world_cam, p_world_cam, ids, uv)
        scale, scale_sigma = self._validate_scale(scale, scale_sigma, len(ids))
        t = float(t)
        self._retired_now = np.zeros(0, np.int64)
        if len(self.retired):
            fresh = ~lookup(self.retired, ids)[0]  # (retired is sorted)
            ids, uv = ids[fresh], uv[fresh]
            if scale is not None:
                scale, scale_sigma = scale[fresh], scale_sigma[fresh]
        if self.t_prev is not None and not t > self.t_prev:
            raise InputError(f"frame times must increase: {t} after {self.t_prev}")
        xy = self.camera.pixels_to_normalized(uv)

        if isinstance(self.ekf, LandmarkEKFBank) and self.t_prev is not None and len(self.ekf):
            dt = t - self.t_prev
            if v_cam is None or w_cam is None:
                v_cam, w_cam = se3_twist(*self.pose_prev, R, p, dt)
            self.ekf.predict(np.asarray(v_cam, float), np.asarray(w_cam, float), dt)

        # 1. landmarks with a running filter (positions sel_e in this frame, rows_e in the bank);
        #    pending ones (sel_p) are buffered, and fed to their wide-prior filters in the same batch
        in_ekf, rows = lookup(self.ekf.ids, ids)
        sel_e = np.flatnonzero(in_ekf)
        rows_e = rows[sel_e]
        sel_rest = np.flatnonzero(~in_ekf)
        in_pend, prow = self.pending.rows_of(ids[sel_rest])
        sel_p = sel_rest[in_pend]
        self.pending.append(prow[in_pend], t, xy[sel_p], R, p)
        accepted, rows_p, accepted_p = self._update(ids, xy, sel_e, rows_e, sel_p, R, p, t)
        n_rej = len(accepted) - int(np.count_nonzero(accepted))
        if self.history is not None:  # what each filter accepted, for its batch refinement
            use = np.concatenate([sel_e[accepted], sel_p[accepted_p]])
            self.history.record_pixels(ids[use], t, R, p, xy[use])
        self.t_seen[rows_e] = t
        n_loom, loom_reasons = 0, {}
        if scale is not None and self.prior_bank is not None and self.ekf.config.looming and self.t_prev is not None:
            off = self._off_axis(xy, R, p)
            if off is not None:
                off &= ~np.isnan(scale)  # a measured scale skipped for its bearing (an unmeasured one stays nan_scale)
                scale = np.where(off, np.nan, scale)
            parts = [(self.ekf, ids[sel_e], rows_e, scale[sel_e], scale_sigma[sel_e]),
                     (self.prior_bank, ids[sel_p], rows_p, scale[sel_p], scale_sigma[sel_p])]
            res = AnchoredInverseDepthEKF._looming_banks_rows(parts, *self.pose_prev, self.t_prev, R, p, t)
            if off is not None:
                for r, sel in zip(res, (sel_e, sel_p)):
                    r.reason[off[sel]] = LOOM_OFF_AXIS
            n_loom = int(sum(np.count_nonzero(r.accepted) for r in res))
            if self.history is not None and n_loom:
                use = np.concatenate([sel[r.accepted] for r, sel in zip(res, (sel_e, sel_p))])
                self.history.record_looming(ids[use], t, R, p, self.t_prev, scale[use],
                                            self.ekf.config.looming_variance(scale_sigma[use]))  # the filter's R_s
            counts = sum(np.bincount(r.reason[~r.accepted], minlength=len(UPDATE_REASON_NAMES)) for r in res)
            loom_reasons = {UPDATE_REASON_NAMES[c]: int(counts[c]) for c in np.flatnonzero(counts)}

        # 2. new landmarks, then try to initialize the pending ones
        room = self.config.max_landmarks - len(self.ekf) - len(self.pending)
        sel_new = sel_rest[~in_pend][: max(room, 0)]
        new_ids, new_xy = ids[sel_new], xy[sel_new]
        self.pending.add(new_ids, t, new_xy, R, p)
        if self.prior_bank is not None:
            self.prior_bank.add(new_ids, new_xy, R, p, t, self.config.prior_inv_depth, self.config.prior_inv_depth_sigma)
            if self.history is not None:
                self.history.record_anchor(new_ids, t, R, p)
        n_tri, n_prior, reasons = self._initialize(t, R, p)
        n_refined = self._refine()

        # 3. forget what is no longer seen
        self._expire(t)
        self.t_prev = t
        self.pose_prev = (R, p)
        out = self._output(t, R, p, n_tri, n_prior, n_rej, reasons)
        out.n_looming, out.looming_reasons, out.n_refined = n_loom, loom_reasons, n_refined
        return out

    def _off_axis(self, xy: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray | None:
        """(M,) True where a track's ray lies farther than ``looming_max_angle_deg`` from the camera's
        translation since the previous frame (docs/derivations/looming.md, § Off the axis of travel);
        None when the limit is off or the camera did not move (then nothing is excluded)."""
        max_deg = self.ekf.config.looming_max_angle_deg
        if max_deg >= 180.0 or len(xy) == 0:  # off (as shipped): no work per frame
            return None
        d = p - self.pose_prev[1]
        n = float(np.linalg.norm(d))
        if not n > 1e-9:
            return None
        ray_world = np.column_stack([xy, np.ones(len(xy))]) @ R.T  # R (x̄, ȳ, 1) per track
        cos = ray_world @ d / (np.linalg.norm(ray_world, axis=1) * n)
        return cos < math.cos(math.radians(max_deg))

    @staticmethod
    def _validate_scale(scale, scale_sigma, m):
        """(M,) float arrays or (None, None).  NaN or bad values are not errors here: the looming
        update skips NaN and refuses non-positive scales with a named reason."""
        if scale is None:
            if scale_sigma is not None:
                raise InputError("scale_sigma given without scale")
            return None, None
        scale = np.asarray(scale, float).reshape(-1) if np.ndim(scale) else np.full(m, float(scale))
        if scale.shape != (m,):
            raise InputError(f"scale must have shape ({m},) to match ids, got {scale.shape}")
        if scale_sigma is None:
            scale_sigma = np.zeros(m)
        scale_sigma = np.asarray(scale_sigma, float).reshape(-1) if np.ndim(scale_sigma) else np.full(m, float(scale_sigma))
        if scale_sigma.shape != (m,):
            raise InputError(f"scale_sigma must have shape ({m},) to match ids, got {scale_sigma.shape}")
        return scale, scale_sigma

    def drop(self, ids) -> None:
        """Forget landmarks whose tracks ended (e.g. the track manager's dropped ids)."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        if len(ids) == 0:
            return
        if len(self.ekf):
            hit, rows = lookup(self.ekf.ids, ids)
            if hit.any():
                keep = np.ones(len(self.ekf), bool)
                keep[rows[hit]] = False
                self.ekf.remove(ids[hit])
                self.t_seen = self.t_seen[keep]
                self._seen_ids = self.ekf.ids.copy()
        present, rows = self.pending.rows_of(ids)
        if present.any():
            keep = np.ones(len(self.pending), bool)
            keep[rows[present]] = False
            self._keep_pending(keep)
        if self.history is not None:
            self.history.drop(ids)

    def _keep_pending(self, keep: np.ndarray) -> None:
        """Keep the pending landmarks of mask ``keep``; the others also leave the prior bank (if still there)."""
        if keep.all():
            return
        if self.prior_bank is not None:
            gone = self.pending.ids[~keep]
            self.prior_bank.remove(gone[self.prior_bank.contains(gone)])
        self.pending.keep(keep)

    def _update(self, ids, xy, sel_e, rows_e, sel_p, R, p, t) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Fuse this frame's observations ``sel_e`` (bank rows ``rows_e``) into the running filters
        and, with the anchored filter, the pending ones ``sel_p`` into their wide-prior filters, in
        one batch: (accepted flags of the running filters, prior-bank rows of ``sel_p`` or None,
        accepted flags of the wide-prior filters)."""
        if isinstance(self.ekf, AnchoredInverseDepthEKF):
            pend_ids = ids[sel_p]
            rows_p = self.prior_bank.index_of(pend_ids)  # the prior bank holds exactly the pending landmarks
            parts = [(self.ekf, ids[sel_e], rows_e, xy[sel_e]), (self.prior_bank, pend_ids, rows_p, xy[sel_p])]
            res_e, res_p = AnchoredInverseDepthEKF._update_banks_rows(parts, R, p, t)
            return res_e.accepted, rows_p, res_p.accepted
        none = np.zeros(0, bool)
        if len(sel_e) == 0:
            return none, None, none
        return self.ekf.update(ids[sel_e], xy[sel_e]).accepted, None, none

    def _initialize(self, t, R, p):
        pend = self.pending
        fresh = pend.t_last == t
        reasons: dict = {}
        if len(pend) == 0 or not fresh.any():
            return 0, 0, reasons
        rows = np.flatnonzero(fresh & (pend.count >= 2))
        if len(rows) == 0:
            return 0, 0, reasons
        # multi-view triangulation over every buffered view; gates on its longest baseline
        mask = np.arange(pend.xy.shape[1])[None, :] < pend.count[rows][:, None]
        tri = triangulate_multiview(pend.ray[rows], pend.p[rows], mask, self.tri_config, sigma_xy=self.sigma_xy)
        counts = np.bincount(tri.reason, minlength=len(Reject))
        reasons = {Reject(code).name: int(counts[code]) for code in np.flatnonzero(counts)}
        ok = tri.ok
        timeout = pend.count[rows] >= self.config.init_max_frames
        start_tri = rows[ok]
        start_prior = rows[~ok & timeout]
        # range along the anchor ray → inverse depth and its σ (inflated: the replay reuses these pixels)
        d_anchor = np.linalg.norm(tri.p[ok] - pend.p[start_tri, 0], axis=1)
        rho_tri = 1.0 / d_anchor
        srho_tri = self.config.tri_sigma_scale * tri.range_sigma[ok] / d_anchor**2
        self._start(start_tri, rho_tri, srho_tri, tri.p[ok], R, p)
        if self.prior_bank is not None and len(start_prior):  # already replayed from the wide prior, one frame at a time
            self.prior_bank.move_to(self.ekf, pend.ids[start_prior])
            self._set_seen(pend.ids[start_prior], pend.t_last[start_prior])
        elif self.prior_bank is None:
            self._start(start_prior, None, None, None, R, p)
        if len(start_tri) or len(start_prior):
            done = np.zeros(len(pend), bool)
            done[start_tri] = True
            done[start_prior] = True
            self._keep_pending(~done)
        return len(start_tri), len(start_prior), reasons

    def _start(self, rows, rho, srho, p_world_tri, R, p) -> None:
        if len(rows) == 0:
            return
        pend = self.pending
        ids = pend.ids[rows]
        cfg = self.config
        if rho is None:  # the wide prior, identical for every landmark
            rho = np.full(len(rows), cfg.prior_inv_depth)
            srho = np.full(len(rows), cfg.prior_inv_depth_sigma)
        if isinstance(self.ekf, AnchoredInverseDepthEKF):  # anchor at the first view, replay the others
            self.ekf.add(ids, pend.xy[rows, 0], pend.R[rows, 0], pend.p[rows, 0], pend.t[rows, 0], rho, srho)
            self.ekf.update_sequence(
                ids, pend.xy[rows, 1:], pend.R[rows, 1:], pend.p[rows, 1:], pend.t[rows, 1:], pend.count[rows] - 1
            )
        else:
            last = pend.count[rows] - 1
            xy_now = pend.xy[rows, last]
            if p_world_tri is None:  # inverse range ρ → inverse depth ξ = ρ·√(1 + x̄² + ȳ²)
                stretch = np.sqrt(1.0 + np.sum(xy_now**2, axis=1))
                xi, srho_xi = rho * stretch, srho * stretch
            else:
                Z = (p_world_tri - p) @ R[:, 2]  # depth in the current camera
                Z = np.maximum(Z, self.tri_config.min_depth_m)
                xi = 1.0 / Z
                srho_xi = srho * (np.linalg.norm(p_world_tri - pend.p[rows, 0], axis=1) / Z) ** 2
            self.ekf.add(ids, xy_now, xi, srho_xi)
        self._set_seen(ids, pend.t_last[rows])

    def _refine(self) -> int:
        """§ Batch refinement (docs/derivations/ekf_anchored.md): the running landmarks whose history
        reached its next due size are re-solved from it (``AnchoredInverseDepthEKF.refine``, with the
        wide inverse-depth prior); returns how many were replaced."""
        if self.history is None or len(self.ekf) == 0:
            return 0
        due = self.history.due(self.ekf.ids) & ~self.ekf.diverged
        if not due.any():
            return 0
        ids = self.ekf.ids[due]
        size = self.history.counts(ids)[0]
        if size.sum() > self.ekf.config.refine_max_slots:  # a frame's budget: the smallest histories first, the rest wait
            order = np.argsort(size, kind="stable")
            take = np.cumsum(size[order]) <= self.ekf.config.refine_max_slots
            take[0] = True  # at least one landmark a frame
            ids = np.sort(ids[order[take]])
        improved = self.ekf.refine(ids, self.history.gather(ids), self.config.prior_inv_depth, self.config.prior_inv_depth_sigma)
        self.history.advance(ids)
        return int(np.count_nonzero(improved))

    def _set_seen(self, new_ids, new_t) -> None:
        """Keep ``t_seen`` aligned with the bank's (sorted) ids after landmarks were added."""
        old_ids, old_t = self._seen_ids, self.t_seen
        t_seen = np.zeros(len(self.ekf))
        if len(old_ids):
            t_seen[self.ekf.index_of(old_ids)] = old_t
        t_seen[self.ekf.index_of(new_ids)] = new_t
        self.t_seen = t_seen
        self._seen_ids = self.ekf.ids.copy()

    def _expire(self, t) -> None:
        """Drop filtered landmarks unseen for ``max_unseen_s``, diverged or invalid, and stale pending ones."""
        cfg = self.config
        if len(self.ekf):
            bad = self.ekf.diverged | self.ekf.invalid
            gone = ((t - self.t_seen) > cfg.max_unseen_s) | bad
            if bad.any():  # a track that is not a static point stays out (bounded memory: newest ids)
                self._retired_now = self.ekf.ids[bad].copy()
                self.retired = np.union1d(self.retired, self._retired_now)[-cfg.max_landmarks:]
            if gone.any():
                self.drop(self.ekf.ids[gone])
        if len(self.pending):
            stale = (t - self.pending.t_last) > cfg.max_unseen_s
            if self.history is not None and stale.any():
                self.history.drop(self.pending.ids[stale])
            self._keep_pending(~stale)

    def _output(self, t, R, p, n_tri, n_prior, n_rej, reasons) -> RangeOutput:
        if isinstance(self.ekf, AnchoredInverseDepthEKF):
            e = self.ekf.estimates(p)
            ids, p_world, rng, rsig, conv, valid = e.ids, e.p_world, e.range, e.range_sigma, e.converged, e.valid
            if self.ekf.config.max_drift_chi2 > 0:  # moved since convergence more than its σ allows: not a static point
                self.ekf.drift_test(conv)  # flags them diverged (the bank holds no other: _expire dropped those)
                conv, valid = conv & ~self.ekf.diverged, valid & ~self.ekf.diverged  # retired at the next frame
        else:
            e = self.ekf.estimates()
            ids = e.ids
            p_world = e.p_cam @ R.T + p
            rng, rsig, conv, valid = e.range, e.range_sigma, e.converged, e.valid
        mean_nis = np.where(self.ekf.nis_count > 0, self.ekf.nis_avg, np.nan)  # both banks' estimates are in bank order
        return RangeOutput(
            t=t, ids=ids, p_world=p_world, range=rng, range_sigma=rsig, converged=conv, valid=valid, mean_nis=mean_nis,
            n_pending=len(self.pending), n_initialized_tri=n_tri, n_initialized_prior=n_prior,
            n_rejected=n_rej, tri_reasons=reasons, retired_ids=self._retired_now,
        )
