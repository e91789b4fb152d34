"""Feature tracks: Harris corners followed frame to frame by NCC (seed 004, Harris corners and NCC matching).

Every frame, each live track is searched for in the new frame with :func:`~companion.core.ncc.match_ncc`
around a predicted pixel (from telemetry through the optional ``predict`` callable, see
:func:`companion.core.prediction.make_track_predictor`; without it, around the previous pixel).
Tracks the matcher rejects are dropped (or, with ``max_failures`` > 1, searched again in the next
frames with the template kept from their last observation); when fewer than
``redetect_fraction`` × ``max_tracks`` tracks remain, new Harris corners are detected away from
the survivors (``min_new_distance_px``) to refill up to ``max_tracks``.  The number of tracks
never exceeds ``max_tracks``.  A refill that finds fewer than ``refill_backoff_yield`` × the corners it
asked for means the image holds no free texture (a small image is full long before ``max_tracks``);
the next ``refill_backoff_frames`` frames then skip the refill (Harris over the whole image, the
tracker's costliest step when it runs every frame for a handful of corners); with
``refill_backoff_priority`` the priority region's own top-up (``priority_min_tracks``) still runs.

Template source: each match uses the template cut from the **previous** frame, at the track's
last matched position — not from the anchor frame.  Over a few frames of flight the appearance of
a patch changes (scale grows as the drone approaches, perspective and lighting change), so a
template from the anchor frame would soon stop correlating; renewing it every frame keeps NCC
scores high and lets a track live as long as the point stays visible.  The price is drift: each
match's sub-pixel error is inherited by the next template.  The sub-pixel step is therefore
unbiased at integer shifts (Lucas–Kanade on the two frames, see :mod:`companion.core.ncc`), and
the anchor observation (frame, time, pixel) is kept for the estimators, which need the longest
baseline rather than the template.

Scale (looming, docs/derivations/looming.md): every match of two consecutive frames also gets the patch's scale
change s = size now / size in the previous frame and its σ from the matcher
(:func:`~companion.core.ncc.estimate_scale`), reported per track in :class:`TrackFrame` (``scale``,
``scale_sigma``, NaN where not measured: new tracks, tracks matched from a stored template, flat or
edge patches, beyond the matcher's cost bound).  Templates that follow scale: the template is
re-cut every frame, so it follows a slow scale change by itself; when the predicted change to
the next frame (the track's last measured scale) departs from 1 by more than
``template_rescale_threshold`` — close in, where a patch grows several % per frame — the template
is resampled at that scale before the search, so NCC still correlates and the track survives.

Reference-patch check (``reference_min_ncc`` > 0; docs/derivations/tracking.md): each track also keeps
the patch it was born with; after every match that patch, warped by the camera's rotation since (the
caller's ``R_world_cam``) and the scale change since, is correlated with the patch at the match, and a
track below the threshold ends with :data:`DROP_REFERENCE` — an occlusion-edge corner or a drifted track.

Storage is a fixed set of ``max_tracks`` slots held in numpy arrays (positions, scores, failure
counts and a ring buffer of the last ``max_history`` observations per slot), so a step costs a
handful of vectorized operations plus the matcher — no Python object per track per frame.
:meth:`TrackManager.track` (or ``manager.tracks[id]``) builds a :class:`Track` snapshot on demand.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Iterator, Mapping
from typing import Callable

import numpy as np

from companion.config import require, require_finite, require_int
from companion.core import jit as _jit
from companion.core import ncc as _ncc
from companion.core import tracks_kernels as _tk
from companion.core.camera import CameraModel
from companion.core.harris import HarrisConfig, as_gray_u8, detect_harris
from companion.core.ncc import NCCConfig, extract_templates, match_ncc, match_templates
from companion.core.ncc_templates import _bilinear, extract_scaled_templates
from companion.errors import InputError

#: Drop reasons in :attr:`TrackFrame.drop_reason`: the NCC verdicts of :mod:`companion.core.ncc`
#: (OUT_OF_IMAGE, FLAT_TEMPLATE, LOW_SCORE, AMBIGUOUS, PEAK_AT_EDGE, EDGE_TEMPLATE) plus:
DROP_DUPLICATE = 10  # two tracks converged onto the same point: the younger one is dropped
DROP_REFERENCE = 11  # the track's reference patch no longer matches where it is: an occlusion edge or drift

#: Largest change of scale (s = 1 ± this) the drift correction may apply to a reference's warp in one frame.
_MAX_DRIFT_SCALE = 0.1

DROP_REASON_NAMES = {**_ncc.REASON_NAMES, DROP_DUPLICATE: "duplicate", DROP_REFERENCE: "reference mismatch"}
del DROP_REASON_NAMES[_ncc.OK]

def zncc_patches(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) zero-mean normalized cross-correlation of the patch pairs ``a[i]``, ``b[i]`` ((N, h, w));
    NaN where either patch is flat (no variance), which a caller must treat as "not measured"."""
    a = np.asarray(a, np.float32).reshape(len(a), -1)
    b = np.asarray(b, np.float32).reshape(len(b), -1)
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    den = np.sqrt(np.einsum("ij,ij->i", a, a) * np.einsum("ij,ij->i", b, b))
    num = np.einsum("ij,ij->i", a, b)
    out = np.full(len(a), np.nan)
    ok = den > 1e-6
    out[ok] = num[ok] / den[ok]
    return out


#: What :meth:`TrackManager.step` did about new corners (:attr:`TrackFrame.refill`).
REFILL_NONE, REFILL_RUN, REFILL_PAUSED = 0, 1, 2

Predictor = Callable[[np.ndarray, np.ndarray], "tuple[np.ndarray, np.ndarray | float] | tuple[np.ndarray, np.ndarray | float, np.ndarray]"]


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """The ``[tracks]`` table."""

    max_tracks: int = 300  # hard bound on live tracks
    redetect_fraction: float = 0.8  # detect new corners when live tracks < fraction × max_tracks
    max_history: int = 64  # observations kept per track (the anchor is kept separately)
    min_new_distance_px: float = 10.0  # new corners at least this far from live tracks
    max_failures: int = 1  # consecutive failed matches before a track is dropped (1 = at once)
    duplicate_distance_px: float = 1.0  # two tracks closer than this: the younger is dropped
    template_rescale_threshold: float = 0.05  # |predicted scale change − 1| beyond this: template resampled to it (0 = never)
    priority_share: float = 0.5  # share of a refill's budget given first to corners inside the caller's priority region (0 = off)
    priority_min_tracks: int = 20  # refill (into the region only) when it holds fewer live tracks than this, whatever the total (0 = off)
    priority_band_range_m: float = 8.0  # the flight-path band of the region: rows within ± band_half_height_m at this range (pipeline)
    priority_path_half_width_deg: float = 15.0  # ... and the columns within this bearing of the flight path (pipeline)
    reference_min_ncc: float = 0.0  # a track whose reference patch correlates below this where it now is is dropped (0 = off)
    reference_half: int = 5  # half size of the reference patch: (2h+1)² px
    reference_refresh_frames: int = 1000  # a passing reference patch is re-cut after this many frames
    reference_correct_px: float = 0.5  # > 0: each match re-aligned to the reference patch, by at most this, px (0 = off)
    reference_correct_min_ncc: float = 0.9  # ... only where the reference then correlates at least this well
    reference_refresh_scale: float = 1.3  # > 1: with the correction, a reference is re-cut once its scale change leaves [1/this, this] (0 = never)
    refill_backoff_frames: int = 0  # after a refill that found little, this many frames without one (0 = refill whenever short)
    refill_backoff_yield: float = 0.25  # "found little": fewer corners than this share of those asked for
    refill_backoff_priority: bool = True  # the priority region's top-up (priority_min_tracks) still runs during a pause

    def __post_init__(self) -> None:
        require_int("max_tracks", self.max_tracks, minimum=1)
        require_finite("redetect_fraction", self.redetect_fraction, nonnegative=True)
        require(self.redetect_fraction <= 1.0, f"redetect_fraction must be <= 1, got {self.redetect_fraction}")
        require_int("max_history", self.max_history, minimum=2)
        require_finite("min_new_distance_px", self.min_new_distance_px, nonnegative=True)
        require_int("max_failures", self.max_failures, minimum=1)
        require_finite("duplicate_distance_px", self.duplicate_distance_px, nonnegative=True)
        require_finite("template_rescale_threshold", self.template_rescale_threshold, nonnegative=True)
        require_finite("priority_share", self.priority_share, nonnegative=True)
        require(self.priority_share <= 1.0, f"priority_share must be <= 1, got {self.priority_share}")
        require(isinstance(self.priority_min_tracks, int) and not isinstance(self.priority_min_tracks, bool)
                and 0 <= self.priority_min_tracks <= self.max_tracks,
                f"priority_min_tracks must be an integer in 0..max_tracks, got {self.priority_min_tracks!r}")
        require_finite("priority_band_range_m", self.priority_band_range_m, positive=True)
        require_finite("priority_path_half_width_deg", self.priority_path_half_width_deg, nonnegative=True)
        require(self.priority_path_half_width_deg <= 180, "priority_path_half_width_deg must be <= 180")
        require_finite("reference_min_ncc", self.reference_min_ncc, nonnegative=True)
        require(self.reference_min_ncc < 1.0, f"reference_min_ncc must be < 1, got {self.reference_min_ncc}")
        require_int("reference_half", self.reference_half, minimum=2)
        require_int("reference_refresh_frames", self.reference_refresh_frames, minimum=1)
        require_finite("reference_correct_px", self.reference_correct_px, nonnegative=True)
        require_finite("reference_correct_min_ncc", self.reference_correct_min_ncc)
        require(-1.0 <= self.reference_correct_min_ncc < 1.0,
                f"reference_correct_min_ncc must be in [-1, 1), got {self.reference_correct_min_ncc}")
        require_finite("reference_refresh_scale", self.reference_refresh_scale, nonnegative=True)
        require(self.reference_refresh_scale == 0.0 or self.reference_refresh_scale > 1.0,
                f"reference_refresh_scale must be 0 (never) or > 1, got {self.reference_refresh_scale}")
        require_int("refill_backoff_frames", self.refill_backoff_frames, minimum=0)
        require_finite("refill_backoff_yield", self.refill_backoff_yield, nonnegative=True)
        require(self.refill_backoff_yield <= 1.0, f"refill_backoff_yield must be <= 1, got {self.refill_backoff_yield}")
        require(isinstance(self.refill_backoff_priority, bool),
                f"refill_backoff_priority must be true or false, got {self.refill_backoff_priority!r}")


@dataclasses.dataclass(frozen=True, eq=False)
class Track:
    """Snapshot of one track (built on demand by :meth:`TrackManager.track`)."""

    id: int
    anchor_frame: int  # frame index of the first observation
    anchor_t: float
    anchor_uv: np.ndarray  # (2,) first observed pixel
    observations: list[tuple[int, float, np.ndarray]]  # (frame_index, t, uv), oldest first, ≤ max_history
    n_observations: int  # total, including those no longer in ``observations``
    age: int  # frames since the anchor (latest processed frame index − anchor_frame)
    last_score: float  # NCC score of the last match (1.0 at birth)
    failures: int  # consecutive failed matches (0 while tracked)
    alive: bool


@dataclasses.dataclass
class TrackFrame:
    """What one :meth:`TrackManager.step` produced (arrays, sorted by track id)."""

    frame_index: int
    t: float
    ids: np.ndarray  # (M,) int64, tracks observed in this frame (matched ones and new ones)
    uv: np.ndarray  # (M, 2) their pixels
    score: np.ndarray  # (M,) NCC score (1.0 for tracks born in this frame)
    new_ids: np.ndarray  # (K,) int64, tracks born in this frame
    dropped_ids: np.ndarray  # (D,) int64, tracks dropped in this frame
    drop_reason: np.ndarray  # (D,) int8, see DROP_REASON_NAMES
    scale: np.ndarray | None = None  # (M,) patch scale change since the previous frame (looming), NaN = not measured
    scale_sigma: np.ndarray | None = None  # (M,) its σ, NaN = not measured
    refill: int = 0  # REFILL_NONE (no refill needed), REFILL_RUN (Harris ran) or REFILL_PAUSED (needed, held by the back-off)

    def __post_init__(self) -> None:
        if self.scale is None:
            self.scale = np.full(len(self.ids), np.nan)
        if self.scale_sigma is None:
            self.scale_sigma = np.full(len(self.ids), np.nan)


class _TrackView(Mapping):
    """``manager.tracks``: read-only mapping id -> :class:`Track` over the live tracks."""

    def __init__(self, manager: "TrackManager"):
        self._m = manager

    def __getitem__(self, track_id) -> Track:
        return self._m.track(track_id)

    def __iter__(self) -> Iterator[int]:
        return iter(self._m.live_ids().tolist())

    def __len__(self) -> int:
        return self._m.n_live

    def __contains__(self, track_id) -> bool:
        return isinstance(track_id, numbers.Integral) and int(track_id) in self._m._slot_of


class TrackManager:
    """Harris + NCC tracker with bounded, id-stable tracks (seed 004, Harris corners and NCC matching)."""

    def __init__(self, camera: CameraModel, harris: HarrisConfig, ncc: NCCConfig, config: TrackConfig):
        require(
            harris.border >= ncc.template_half + 1,
            f"harris.border ({harris.border}) must be >= ncc.template_half + 1 ({ncc.template_half + 1}) "
            "so every new corner has a full template",
        )
        self.camera = camera
        self.harris = harris
        self.ncc = ncc
        self.config = config
        s, hlen, tr = config.max_tracks, config.max_history, 2 * ncc.template_half + 3
        self._id = np.full(s, -1, np.int64)
        self._uv = np.zeros((s, 2))
        self._last_frame = np.zeros(s, np.int64)
        self._anchor_frame = np.zeros(s, np.int64)
        self._anchor_t = np.zeros(s)
        self._anchor_uv = np.zeros((s, 2))
        self._n_obs = np.zeros(s, np.int64)
        self._score = np.zeros(s)
        self._fail = np.zeros(s, np.int64)
        self._scale = np.full(s, np.nan)  # scale change measured in the latest match (NaN = none)
        self._scale_sigma = np.full(s, np.nan)
        self._scale_rate = np.ones(s)  # last measured scale change: the prediction for the next frame
        self._tpl = np.zeros((s, tr, tr), np.uint8)  # kept only for tracks that missed a frame
        self._tpl_frac = np.zeros((s, 2))
        self._tpl_ok = np.zeros(s, bool)
        self._h_uv = np.zeros((s, hlen, 2))
        self._h_frame = np.zeros((s, hlen), np.int64)
        self._h_t = np.zeros((s, hlen))
        rr = 2 * config.reference_half + 1
        self._ref = np.zeros((s, rr, rr), np.float32)  # reference patch (see _check_reference)
        self._ref_ok = np.zeros(s, bool)  # the reference patch fitted in the image when cut
        self._ref_uv = np.zeros((s, 2))  # the pixel it was cut at
        self._ref_frame = np.zeros(s, np.int64)  # frame it was cut in
        self._ref_scale = np.ones(s)  # patch scale change since then
        self._ref_R = np.tile(np.eye(3), (s, 1, 1))  # camera attitude R_world_cam when it was cut (identity: unknown)
        self._ref_R_ok = np.zeros(s, bool)
        # the drift correction's kernel keeps, per reference, what changes only when it is cut
        # (tracks_kernels.prepare_reference_k, run by _cut_reference)
        self._ref_T = np.zeros((s, rr * rr))  # the reference at zero mean and unit variance
        self._ref_G = np.zeros((s, 3, rr * rr))  # its steepest-descent images (shift x, shift y, scale)
        self._ref_Nc = np.zeros((s, 7))  # cofactors and determinant of its 3 × 3 normal matrix
        self._ref_fit = np.zeros(s, bool)  # it can be aligned (not flat, not an edge)
        off = np.arange(-config.reference_half, config.reference_half + 1, dtype=float)
        self._ref_grid = np.meshgrid(off, off)
        self._R_now: np.ndarray | None = None
        self._slot_of: dict[int, int] = {}
        self._next_id = 0
        self._prev_gray: np.ndarray | None = None
        self._prev_t: float | None = None
        self._prev_frame: int | None = None
        self._no_refill_before = -1  # frame index: refill back-off (see refill_backoff_frames)
        self._just_dropped: dict[int, int] = {}  # id → row of _dropped, the tracks dropped in the latest step
        self._dropped: dict = {}
        self._dropped_frame = 0
        self._label: np.ndarray | None = None  # scratch image of the duplicate test
        self.tracks = _TrackView(self)

    # -- reading -------------------------------------------------------------------------------
    @property
    def n_live(self) -> int:
        return len(self._slot_of)

    def live_ids(self) -> np.ndarray:
        """Ids of the live tracks, ascending."""
        return np.sort(self._id[self._id >= 0])

    def track(self, track_id: int) -> Track:
        """Snapshot of a live track, or of one dropped in the latest step; KeyError otherwise."""
        if not isinstance(track_id, numbers.Integral):
            raise KeyError(track_id)
        track_id = int(track_id)
        if track_id in self._slot_of:
            return self._snapshot(self._slot_of[track_id], alive=True)
        if track_id in self._just_dropped:  # built on demand from the copy kept at the drop
            row = self._just_dropped[track_id]
            return self._snapshot(row, alive=False, latest=self._dropped_frame, src=self._dropped)
        raise KeyError(f"no live track with id {track_id} (it may have been dropped earlier)")

    #: per-slot arrays a :class:`Track` snapshot is built from
    _SNAPSHOT_FIELDS = ("_id", "_anchor_frame", "_anchor_t", "_anchor_uv", "_n_obs", "_h_frame", "_h_t", "_h_uv",
                        "_score", "_fail")

    def _snapshot(self, slot: int, alive: bool, latest: int | None = None, src: dict | None = None) -> Track:
        """:class:`Track` of ``slot``; ``src`` (field → array, as :data:`_SNAPSHOT_FIELDS`) reads a copy
        kept when the track was dropped instead of the live arrays (``slot`` then indexes that copy)."""
        a = src if src is not None else {name: getattr(self, name) for name in self._SNAPSHOT_FIELDS}
        hlen = self.config.max_history
        n = int(a["_n_obs"][slot])
        k = np.arange(max(0, n - hlen), n) % hlen
        obs = [
            (int(f), float(t), uv.copy())
            for f, t, uv in zip(a["_h_frame"][slot, k], a["_h_t"][slot, k], a["_h_uv"][slot, k])
        ]
        if latest is None:
            latest = self._prev_frame if self._prev_frame is not None else int(a["_anchor_frame"][slot])
        return Track(
            id=int(a["_id"][slot]),
            anchor_frame=int(a["_anchor_frame"][slot]),
            anchor_t=float(a["_anchor_t"][slot]),
            anchor_uv=a["_anchor_uv"][slot].copy(),
            observations=obs,
            n_observations=n,
            age=int(latest - a["_anchor_frame"][slot]),
            last_score=float(a["_score"][slot]),
            failures=int(a["_fail"][slot]),
            alive=alive,
        )

    # -- the step ------------------------------------------------------------------------------
    def kill(self, ids) -> int:
        """End the listed live tracks now (e.g. the estimator found them inconsistent with a static
        point); their slots are refilled by the next detection.  Unknown ids are ignored; returns
        how many tracks ended."""
        slots = [self._slot_of.pop(int(i)) for i in np.asarray(ids, np.int64).reshape(-1) if int(i) in self._slot_of]
        if slots:
            s = np.asarray(slots, np.int64)
            self._id[s] = -1
            self._tpl_ok[s] = False
        return len(slots)

    def _check_inputs(self, gray, t, frame_index) -> tuple[np.ndarray, float, int]:
        gray = as_gray_u8(gray, "gray")
        c = self.camera.config
        if gray.shape != (c.height, c.width):
            raise InputError(f"gray has shape {gray.shape}, the camera is {c.height}×{c.width} (rows × columns)")
        if isinstance(t, bool) or not isinstance(t, numbers.Real) or not math.isfinite(float(t)):
            raise InputError(f"t must be a finite number of seconds, got {t!r}")
        t = float(t)
        if self._prev_t is not None and not t > self._prev_t:
            raise InputError(f"timestamps must be strictly increasing: t = {t!r} after {self._prev_t!r}")
        if isinstance(frame_index, bool) or not isinstance(frame_index, numbers.Integral):
            raise InputError(f"frame_index must be an integer, got {frame_index!r}")
        frame_index = int(frame_index)
        if self._prev_frame is not None and frame_index <= self._prev_frame:
            raise InputError(f"frame_index must increase: {frame_index} after {self._prev_frame}")
        return gray, t, frame_index

    def _prediction(self, predict: Predictor | None, uv_prev: np.ndarray,
                    ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        n = len(uv_prev)
        if predict is None:
            return uv_prev.copy(), np.full(n, float(self.ncc.search_half)), None
        out = predict(uv_prev.copy(), ids.copy())
        if not isinstance(out, tuple) or len(out) not in (2, 3):
            raise InputError("predict must return a tuple (uv_pred (N, 2), radius (N,) or scalar[, parallax (N,)])")
        parallax = None
        if len(out) == 3:
            parallax = np.asarray(out[2], dtype=float)
            if parallax.shape != (n,) or np.any(np.isnan(parallax)):
                raise InputError(f"predict returned an invalid parallax (shape {parallax.shape}; must be ({n},) without NaN)")
        uv_pred = np.asarray(out[0], dtype=float)
        radius = np.asarray(out[1], dtype=float)
        if uv_pred.shape != (n, 2):
            raise InputError(f"predict returned uv_pred of shape {uv_pred.shape}, expected ({n}, 2)")
        if not np.all(np.isfinite(uv_pred)):
            raise InputError("predict returned NaN or inf pixels")
        if radius.ndim == 0:
            radius = np.full(n, float(radius))
        if radius.shape != (n,) or not np.all(np.isfinite(radius)) or np.any(radius < 0):
            raise InputError(f"predict returned an invalid radius (shape {radius.shape}; must be finite, >= 0, scalar or ({n},))")
        return uv_pred, radius, parallax

    def step(self, gray: np.ndarray, t: float, frame_index: int, predict: Predictor | None = None,
             priority_mask: np.ndarray | None = None, R_world_cam: np.ndarray | None = None) -> TrackFrame:
        """Track all live tracks into ``gray``, drop failures, refill with Harris corners.

        ``gray``: 2-D uint8 frame of the camera's size; ``t``: capture time in seconds, strictly
        increasing; ``frame_index``: strictly increasing integer.  ``predict(uv_prev, ids)`` gets
        the (N, 2) last pixels and ids of the live tracks and returns ``(uv_pred, radius)``: the
        search-window centres in this frame and their radii (px, scalar or (N,)).

        ``priority_mask``: optional (H, W) bool/uint8 image, non-zero where new corners are wanted
        most (sectors without live points, the band around the flight path; see
        :func:`companion.core.priority.detection_priority`).  A refill then gives up to
        ``priority_share`` of its budget to corners inside it first and the rest anywhere; with
        ``priority_min_tracks`` > 0 a refill into the region alone also runs when it holds fewer
        live tracks than that, even with enough tracks in total.

        ``R_world_cam``: optional camera attitude of this frame (telemetry); the reference-patch check
        (``reference_min_ncc`` > 0) then undoes the camera's rotation since each reference was cut.
        """
        gray, t, frame_index = self._check_inputs(gray, t, frame_index)
        if R_world_cam is not None:
            R_world_cam = np.asarray(R_world_cam, float)
            if R_world_cam.shape != (3, 3) or not np.all(np.isfinite(R_world_cam)):
                raise InputError("R_world_cam must be a finite 3×3 rotation matrix")
        self._R_now = R_world_cam
        if priority_mask is not None:
            priority_mask = np.asarray(priority_mask)
            if priority_mask.shape != gray.shape:
                raise InputError(f"priority_mask must have the frame's shape {gray.shape}, got {priority_mask.shape}")
            if not np.any(priority_mask):
                priority_mask = None
        cfg = self.config
        hlen = cfg.max_history
        self._just_dropped = {}
        matched_slots = np.zeros(0, np.int64)
        drop_slots: list[np.ndarray] = []
        drop_codes: list[np.ndarray] = []

        live = np.flatnonzero(self._id >= 0)
        if len(live) and self._prev_gray is not None:
            uv_prev = self._uv[live]
            uv_pred, radius, parallax = self._prediction(predict, uv_prev, self._id[live])
            scale_key = parallax if self.ncc.scale_order == "parallax" else None
            fresh = self._last_frame[live] == self._prev_frame
            # Tracks that already missed frames search a wider window (their motion is older).
            radius = radius * (1 + self._fail[live])
            pts = np.zeros((len(live), 2))
            score = np.zeros(len(live))
            reason = np.zeros(len(live), np.int8)
            scale = np.full(len(live), np.nan)
            scale_sigma = np.full(len(live), np.nan)
            f = np.flatnonzero(fresh)
            if len(f):
                r = match_ncc(self._prev_gray, gray, uv_prev[f], uv_pred[f], self.ncc, radius[f],
                              scale_pred=self._scale_rate[live[f]], rescale_threshold=cfg.template_rescale_threshold,
                              scale_key=None if scale_key is None else scale_key[f])
                pts[f], score[f], reason[f] = r.pts, r.score, r.reason
                scale[f], scale_sigma[f] = r.scale, r.scale_sigma
            c = np.flatnonzero(~fresh)
            if len(c):
                sl = live[c]
                r = match_templates(self._tpl[sl], self._tpl_frac[sl], gray, uv_pred[c], self.ncc, radius[c], valid=self._tpl_ok[sl])
                pts[c], score[c], reason[c] = r.pts, r.score, r.reason
            ok = reason == _ncc.OK

            # Successful matches: new position, one more observation in the ring buffer.
            s_ok = live[ok]
            self._uv[s_ok] = pts[ok]
            self._last_frame[s_ok] = frame_index
            self._score[s_ok] = score[ok]
            self._fail[s_ok] = 0
            self._scale[s_ok] = scale[ok]
            self._scale_sigma[s_ok] = scale_sigma[ok]
            measured = np.isfinite(scale[ok])
            self._scale_rate[s_ok[measured]] = scale[ok][measured]
            self._tpl_ok[s_ok] = False
            k = self._n_obs[s_ok] % hlen
            self._h_uv[s_ok, k] = pts[ok]
            self._h_frame[s_ok, k] = frame_index
            self._h_t[s_ok, k] = t
            self._n_obs[s_ok] += 1

            # Failures: drop at once when the point has left the image or the template is flat or
            # an edge (it will not become a corner again), otherwise after max_failures consecutive misses.
            s_bad = live[~ok]
            self._fail[s_bad] += 1
            self._score[s_bad] = score[~ok]
            hard = np.isin(reason[~ok], (_ncc.OUT_OF_IMAGE, _ncc.FLAT_TEMPLATE, _ncc.EDGE_TEMPLATE))
            drop = hard | (self._fail[s_bad] >= cfg.max_failures)
            drop_slots.append(s_bad[drop])
            drop_codes.append(reason[~ok][drop])
            # Coasting tracks that were seen in the previous frame keep that frame's template.
            keep_fresh = ~drop & fresh[~ok]
            if np.any(keep_fresh):
                sk = s_bad[keep_fresh]
                tpl, frac, inside = extract_templates(self._prev_gray, self._uv[sk], self.ncc.template_half)
                self._tpl[sk], self._tpl_frac[sk], self._tpl_ok[sk] = tpl, frac, inside

            # Duplicates: two matched tracks on the same point -> keep the older (smaller id).
            if cfg.duplicate_distance_px > 0 and len(s_ok) > 1:
                dup = self._duplicates(s_ok, cfg.duplicate_distance_px)
                if len(dup):
                    drop_slots.append(dup)
                    drop_codes.append(np.full(len(dup), DROP_DUPLICATE, np.int8))
                    s_ok = np.setdiff1d(s_ok, dup)
            if self._keeps_reference and len(s_ok):
                bad = self._check_reference(gray, s_ok, frame_index)
                if len(bad):
                    drop_slots.append(bad)
                    drop_codes.append(np.full(len(bad), DROP_REFERENCE, np.int8))
                    s_ok = np.setdiff1d(s_ok, bad)
            matched_slots = s_ok

        dropped_ids = np.zeros(0, np.int64)
        drop_reason = np.zeros(0, np.int8)
        if drop_slots:
            ds = np.concatenate(drop_slots)
            drop_reason = np.concatenate(drop_codes).astype(np.int8)
            dropped_ids = self._id[ds].copy()
            # keep a copy of their rows; their Track snapshots are built only if asked for
            self._dropped = {name: getattr(self, name)[ds] for name in self._SNAPSHOT_FIELDS}
            self._dropped_frame = frame_index
            self._just_dropped = {i: row for row, i in enumerate(dropped_ids.tolist())}
            for i in self._just_dropped:
                del self._slot_of[i]
            self._id[ds] = -1
            self._tpl_ok[ds] = False

        # Refill with Harris corners away from the survivors.
        new_slots = np.zeros(0, np.int64)
        n_live = self.n_live
        use_pri = priority_mask is not None and (cfg.priority_share > 0 or cfg.priority_min_tracks > 0)
        short = n_live < cfg.redetect_fraction * cfg.max_tracks or self._prev_gray is None
        # the last refill found the image full: no plain refill for now (the region's top-up may run)
        paused = self._prev_gray is not None and frame_index < self._no_refill_before
        full = short and not paused
        refill = REFILL_PAUSED if short and paused else REFILL_NONE
        starving = False
        if use_pri and not full and (not paused or cfg.refill_backoff_priority) and cfg.priority_min_tracks > 0:
            q = np.rint(self._uv[self._id >= 0]).astype(np.int64)
            h, w = gray.shape
            inb = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
            n_in = int(np.count_nonzero(priority_mask[q[inb, 1], q[inb, 0]]))
            starving = n_in < cfg.priority_min_tracks
        if full or starving:
            want = cfg.max_tracks - n_live
            if want > 0:
                survivors = self._uv[self._id >= 0]
                kw = {}
                if use_pri:
                    # a full refill: the share first inside the region; a top-up of a starving
                    # region: inside it only
                    n_pri = int(math.ceil(cfg.priority_share * want)) if full else want
                    kw = {"priority": priority_mask, "priority_max": n_pri}
                    if not full:
                        kw["mask"] = priority_mask
                pts, _ = detect_harris(
                    gray, self.harris, exclude_pts=survivors, exclude_radius=cfg.min_new_distance_px, max_corners=want, **kw
                )
                refill = REFILL_RUN
                if cfg.refill_backoff_frames > 0 and len(pts) < cfg.refill_backoff_yield * want:
                    self._no_refill_before = frame_index + 1 + cfg.refill_backoff_frames
                if len(pts):
                    new_slots = np.flatnonzero(self._id < 0)[: len(pts)]
                    pts = pts[: len(new_slots)]
                    self._birth(new_slots, pts, t, frame_index, gray)

        self._prev_gray = gray.copy()  # the caller may reuse its frame buffer
        self._prev_t = t
        self._prev_frame = frame_index

        obs = np.concatenate([matched_slots, new_slots])
        ids = self._id[obs]
        order = np.argsort(ids, kind="stable")
        obs = obs[order]
        order_d = np.argsort(dropped_ids, kind="stable")
        return TrackFrame(
            frame_index=frame_index,
            t=t,
            ids=self._id[obs].copy(),
            uv=self._uv[obs].copy(),
            score=self._score[obs].copy(),
            new_ids=np.sort(self._id[new_slots]),
            dropped_ids=dropped_ids[order_d],
            drop_reason=drop_reason[order_d],
            scale=self._scale[obs].copy(),
            scale_sigma=self._scale_sigma[obs].copy(),
            refill=refill,
        )

    def _birth(self, slots: np.ndarray, pts: np.ndarray, t: float, frame_index: int, gray: np.ndarray) -> None:
        n = len(slots)
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        self._id[slots] = ids
        self._uv[slots] = pts
        self._last_frame[slots] = frame_index
        self._anchor_frame[slots] = frame_index
        self._anchor_t[slots] = t
        self._anchor_uv[slots] = pts
        self._n_obs[slots] = 1
        self._score[slots] = 1.0
        self._fail[slots] = 0
        self._scale[slots] = np.nan
        self._scale_sigma[slots] = np.nan
        self._scale_rate[slots] = 1.0
        self._tpl_ok[slots] = False
        self._h_uv[slots, 0] = pts
        self._h_frame[slots, 0] = frame_index
        self._h_t[slots, 0] = t
        self._slot_of.update(zip(ids.tolist(), slots.tolist()))
        if self._keeps_reference:
            self._cut_reference(gray, slots, frame_index)

    @property
    def _keeps_reference(self) -> bool:
        """Tracks keep their reference patch: for the check (``reference_min_ncc``) or the drift correction
        (``reference_correct_px``)."""
        return self.config.reference_min_ncc > 0 or self.config.reference_correct_px > 0

    def _cut_reference(self, gray: np.ndarray, slots: np.ndarray, frame_index: int) -> None:
        """Cut the reference patch of ``slots`` at their current pixels (sub-pixel centred); with kernels and the drift
        correction on, also what the correction's kernel needs of each reference (``prepare_reference_k``; the numpy
        reference, :meth:`_drift_parameters`, derives it from the patch each call)."""
        if len(slots) == 0:
            return
        if _jit.ENABLED:
            sl = np.ascontiguousarray(slots, dtype=np.int64)
            _tk.cut_reference_k(np.ascontiguousarray(gray), np.ascontiguousarray(self._uv[slots]), sl,
                                self.config.reference_half, self._ref, self._ref_ok)
            if self.config.reference_correct_px > 0:
                _tk.prepare_reference_k(self._ref, sl, self._ref_T, self._ref_G, self._ref_Nc, self._ref_fit)
        else:
            tpl, _, inside = extract_scaled_templates(gray, self._uv[slots], self.config.reference_half, np.ones(len(slots)))
            self._ref[slots] = tpl[:, 1:-1, 1:-1]
            self._ref_ok[slots] = inside
        self._ref_frame[slots] = frame_index
        self._ref_uv[slots] = self._uv[slots]
        self._ref_scale[slots] = 1.0
        self._ref_R_ok[slots] = self._R_now is not None
        if self._R_now is not None:
            self._ref_R[slots] = self._R_now

    def _reference_warp(self, slots: np.ndarray) -> np.ndarray:
        """(N, 2, 2) the warp S·J of the slots' reference offsets into the current frame: S the scale
        change since the reference and J the 2×2 Jacobian, at the reference pixel, of the infinite
        homography K R K⁻¹ of the camera's rotation since then (R = R_world_cam,nowᵀ R_world_cam,ref;
        J = I where either attitude is unknown).  The compiled kernel (``reference_warp_k``) when kernels are enabled;
        these lines are its reference."""
        if _jit.ENABLED:
            A = np.empty((len(slots), 2, 2))
            c = self.camera.config
            has_R = self._R_now is not None
            _tk.reference_warp_k(self._R_now if has_R else np.eye(3), has_R, self._ref_R, self._ref_R_ok, self._ref_uv,
                                 self._ref_scale, np.ascontiguousarray(slots, dtype=np.int64), c.fx, c.fy, c.cx, c.cy, A)
            return A
        n = len(slots)
        J = np.tile(np.eye(2), (n, 1, 1))
        rot = self._ref_R_ok[slots] if self._R_now is not None else np.zeros(n, bool)
        if np.any(rot):
            sr = slots[rot]
            R = np.einsum("ji,njk->nik", self._R_now, self._ref_R[sr])  # reference camera → current camera
            c = self.camera.config
            uv_ref = self._ref_uv[sr]
            x_ref = np.column_stack([(uv_ref[:, 0] - c.cx) / c.fx, (uv_ref[:, 1] - c.cy) / c.fy, np.ones(len(sr))])
            q = np.einsum("nij,nj->ni", R, x_ref)
            # d(q[:2]/q[2]) / d(x, y) in normalized units, then to pixels
            Jn = (R[:, :2, :2] * q[:, 2, None, None] - q[:, :2, None] * R[:, 2, None, :2]) / (q[:, 2] ** 2)[:, None, None]
            Jp = Jn * np.array([[1.0, c.fx / c.fy], [c.fy / c.fx, 1.0]])
            J[rot] = np.where(np.isfinite(Jp) & (q[:, 2] > 1e-6)[:, None, None], Jp, J[rot])
        return J * self._ref_scale[slots, None, None]

    def _warped_patches(self, gray: np.ndarray, slots: np.ndarray, A: np.ndarray,
                        uv: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The numpy reference of the check's sampling: the patches at the slots' current pixels (or at ``uv``,
        (N, 2)) sampled where the reference offsets d land, uv + A·d (bilinear, border replicated).  Returns
        the (N, 2h+1, 2h+1) float32 patches and whether each grid lies inside the image."""
        h = self.config.reference_half
        uv = self._uv[slots] if uv is None else uv
        u, v = uv[:, 0, None, None], uv[:, 1, None, None]
        # the grid is an affine image of the offsets: its extremes are at the four corners (same arithmetic)
        cx, cy = np.array([[[-h, h, -h, h]]], float), np.array([[[-h, -h, h, h]]], float)
        Xc = u + A[:, 0, 0, None, None] * cx + A[:, 0, 1, None, None] * cy
        Yc = v + A[:, 1, 0, None, None] * cx + A[:, 1, 1, None, None] * cy
        H, W = gray.shape
        inside = (Xc.min(axis=(1, 2)) >= 0) & (Xc.max(axis=(1, 2)) <= W - 1) & (Yc.min(axis=(1, 2)) >= 0) & (Yc.max(axis=(1, 2)) <= H - 1)
        dx, dy = self._ref_grid  # (rows = y, cols = x)
        X = u + A[:, 0, 0, None, None] * dx + A[:, 0, 1, None, None] * dy
        Y = v + A[:, 1, 0, None, None] * dx + A[:, 1, 1, None, None] * dy
        return _bilinear(gray.astype(np.float32), X, Y), inside

    def _reference_ncc(self, gray: np.ndarray, slots: np.ndarray, A: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(N,) NCC of the slots' reference patches with the frame where they now map to, and (N,) bool
        whether that grid lies in the image: the compiled kernel (companion/core/tracks_kernels.py)
        when kernels are enabled, else :meth:`_warped_patches` and :func:`zncc_patches`."""
        A = self._reference_warp(slots) if A is None else A
        if _jit.ENABLED:
            ncc = np.empty(len(slots))
            inside = np.empty(len(slots), bool)
            _tk.reference_ncc_k(np.ascontiguousarray(gray), self._ref[slots], np.ascontiguousarray(self._uv[slots]),
                                np.ascontiguousarray(A), ncc, inside)
            return ncc, inside
        cur, inside = self._warped_patches(gray, slots, A)
        return zncc_patches(self._ref[slots], cur), inside

    def _check_reference(self, gray: np.ndarray, slots: np.ndarray, frame_index: int) -> np.ndarray:
        """The reference patch of the matched ``slots``: drift correction, check and refresh
        (docs/derivations/tracking.md, "Reference patch").  Returns the slots whose reference no longer
        matches (feature monitoring, Shi & Tomasi 1994, "Good features to track": compare the feature's
        patch now with the one it started from, warped by the motion since).

        Frame-to-frame matching re-cuts the template every frame, so a track follows whatever its
        window holds: each match's sub-pixel error is inherited by the next template (the track
        drifts as a random walk), and at an occlusion edge (a T-junction of a near edge over a far
        texture) the two layers slide apart and the track rides between them, its triangulated range
        between the two surfaces.  The patch cut at birth (or at the last refresh), resampled by the
        scale change measured since (the product of the per-frame scale changes, the predicted rate
        where one was not measured) and by the camera's rotation since, is the reference:

        * with ``reference_correct_px`` > 0 each match is first re-aligned to it (:meth:`_correct_drift`), so the
          track no longer drifts (the template update problem; Matthews, Ishikawa and Baker 2004);
        * with ``reference_min_ncc`` > 0 it is correlated (zero-mean NCC) with the patch at the match, and below
          ``reference_min_ncc`` the track is returned.

        Passing references older than ``reference_refresh_frames``, or, with the correction, whose scale change
        has left [1/``reference_refresh_scale``, ``reference_refresh_scale``], are re-cut at the match (bounding the
        rotation, perspective and resampling a reference must tolerate); references that did not fit in the
        image are re-cut and neither used nor checked."""
        cfg = self.config
        self._ref_scale[slots] *= self._scale_rate[slots]
        has = self._ref_ok[slots]
        sl = slots[has]
        bad = np.zeros(0, np.int64)
        A = self._reference_warp(sl) if len(sl) else None
        if len(sl) and cfg.reference_correct_px > 0:
            A = A * self._correct_drift(gray, sl, A)[:, None, None]  # the warp at the corrected scale
        if len(sl) and cfg.reference_min_ncc > 0:
            ncc, inside = self._reference_ncc(gray, sl, A)
            bad = sl[inside & (ncc < cfg.reference_min_ncc)]
        due = ~has | (frame_index - self._ref_frame[slots] >= cfg.reference_refresh_frames)
        if cfg.reference_refresh_scale > 0 and cfg.reference_correct_px > 0:
            ls = np.abs(np.log(self._ref_scale[slots]))
            due |= ~(ls <= math.log(cfg.reference_refresh_scale))
        self._cut_reference(gray, np.setdiff1d(slots[due], bad), frame_index)
        return bad

    def _correct_drift(self, gray: np.ndarray, slots: np.ndarray, A: np.ndarray, iterations: int = 1) -> np.ndarray:
        """Re-align the matches of ``slots`` (with references; ``A`` their :meth:`_reference_warp`) to their reference
        patches, in place (docs/derivations/tracking.md, "Drift correction"); returns (n,) the factor each slot's scale
        since the reference took (1 where the match stands).

        Inverse-compositional Gauss–Newton (Baker and Matthews 2004) over a shift Δ and a scale factor s of the
        reference's warp, on the zero-mean, unit-variance patches (a change of gain and offset is no residual): the
        frame is sampled at uv + Δ + s·A·d (A = :meth:`_reference_warp`, d the reference offsets), and the step is
        solved on the reference's own gradients, so each step samples the frame once and the normal matrix is the
        reference's.  One step a frame (``iterations``): the correction runs every frame, so what one step leaves is
        taken up in the next.  The scale is estimated with the shift because a patch whose texture lies off its
        centre moves its best alignment when the scale is wrong (the scale since the reference is a product of
        per-frame estimates, and wanders).  A correction is taken where the reference's 2×2 normal matrix is not an
        edge's (λmin/λmax ≥ 0.05), every sample lies in the frame, |Δ| ≤ ``reference_correct_px``, |s − 1| ≤ 0.1 and
        the reference correlates (zero-mean NCC, where the last step started) at ``reference_correct_min_ncc`` or
        better; the match moves to uv + Δ, the scale since the reference takes the factor s, and the frame's entry
        of the track's history is the corrected pixel.  Elsewhere the match stands."""
        cfg = self.config
        A = np.ascontiguousarray(A)
        uv0 = np.ascontiguousarray(self._uv[slots])
        if _jit.ENABLED:
            par = np.empty((len(slots), 3))
            ncc = np.empty(len(slots))
            _tk.correct_drift_k(np.ascontiguousarray(gray), self._ref_T, self._ref_G, self._ref_Nc, self._ref_fit,
                                np.ascontiguousarray(slots, dtype=np.int64), uv0, A, float(cfg.reference_correct_px),
                                _MAX_DRIFT_SCALE, iterations, par, ncc)
        else:
            par, ncc = self._drift_parameters(gray, slots, uv0, A, iterations)
        ok = np.isfinite(ncc) & (ncc >= cfg.reference_correct_min_ncc)
        factor = np.where(ok, par[:, 2], 1.0)
        keep = slots[ok]
        self._uv[keep] = uv0[ok] + par[ok, :2]
        self._ref_scale[keep] *= factor[ok]
        k = (self._n_obs[keep] - 1) % cfg.max_history
        self._h_uv[keep, k] = self._uv[keep]
        return factor

    def _drift_parameters(self, gray, slots, uv0, A, iterations):
        """The numpy reference of the drift correction (:meth:`_correct_drift`; the kernel is
        :func:`companion.core.tracks_kernels.correct_drift_k`): (n, 3) parameters (Δx, Δy, s) and (n,) the NCC of the
        reference with the frame where the last step started; (0, 0, 1) and NaN where a track fails.  The frame is
        sampled by :meth:`_warped_patches` (at uv + Δ, with the warp s·A)."""
        cfg = self.config
        n = len(slots)

        def standardized(V):  # (n, samples) to zero mean and unit variance, and whether each was not flat
            V = V - V.mean(axis=1, keepdims=True)
            sd = np.sqrt(np.mean(V * V, axis=1))
            return V / np.where(sd > 1e-6, sd, 1.0)[:, None], sd > 1e-6

        Tf, ok = standardized(self._ref[slots].reshape(n, -1).astype(np.float64))
        T = Tf.reshape(self._ref[slots].shape)
        gx, gy = np.gradient(T, axis=2), np.gradient(T, axis=1)  # central inside, one-sided at the border
        dx, dy = self._ref_grid
        J = np.stack([gx, gy, gx * dx + gy * dy], -1).reshape(n, -1, 3)
        Hm = np.einsum("nsi,nsj->nij", J, J)
        a_, b_, c_ = Hm[:, 0, 0], Hm[:, 0, 1], Hm[:, 1, 1]
        det2 = a_ * c_ - b_ * b_
        disc = np.sqrt(np.maximum((a_ + c_) ** 2 / 4 - det2, 0.0))
        ok &= (det2 > 1e-12) & ((a_ + c_) / 2 - disc >= 0.05 * np.maximum((a_ + c_) / 2 + disc, 1e-12))
        Hm = np.where(ok[:, None, None], Hm, np.eye(3))
        ok &= np.abs(np.linalg.det(Hm)) > 1e-12
        Hinv = np.linalg.inv(np.where(ok[:, None, None], Hm, np.eye(3)))
        d = np.zeros((n, 2))
        s = np.ones(n)
        ncc = np.full(n, np.nan)
        for _ in range(iterations):
            cur, inside = self._warped_patches(gray, slots, A * s[:, None, None], uv=uv0 + d)
            C, flat_free = standardized(cur.reshape(n, -1).astype(np.float64))
            ok &= inside & flat_free
            ncc = np.mean(C * Tf, axis=1)
            q = np.einsum("nij,nj->ni", Hinv, np.einsum("nsi,ns->ni", J, C - Tf))
            k = s / (1.0 + q[:, 2])  # compose with the inverse of the reference's warp d → (1 + q2)·d + q
            d = d - k[:, None] * np.einsum("nij,nj->ni", A, q[:, :2])
            s = k
            ok &= (np.all(np.isfinite(d), axis=1) & np.isfinite(s) & (np.hypot(d[:, 0], d[:, 1]) <= cfg.reference_correct_px)
                   & (np.abs(s - 1.0) <= _MAX_DRIFT_SCALE))
            d = np.where(ok[:, None], d, 0.0)
            s = np.where(ok, s, 1.0)
        ncc = np.where(ok, ncc, np.nan)
        return np.column_stack([np.where(ok[:, None], d, 0.0), np.where(ok, s, 1.0)]), ncc

    def _duplicates(self, slots: np.ndarray, dist: float) -> np.ndarray:
        """Slots whose track lies within ``dist`` px of an older (smaller id) matched track.

        The slot numbers are written into a label image at the rounded positions; each point then
        reads its (2r+1)² neighbourhood (r = ⌈dist⌉) — a point hidden by another on the same pixel
        sees the other's label on its own pixel.  Candidate pairs get an exact distance check.
        No all-pairs distance matrix, no loop over points.
        """
        c = self.camera.config
        r = int(math.ceil(dist))
        if self._label is None:
            self._label = np.full((c.height + 2 * r, c.width + 2 * r), -1, np.int64)
        lab = self._label
        uv = self._uv[slots]
        q = np.clip(np.rint(uv).astype(np.int64), 0, [c.width - 1, c.height - 1]) + r
        idx = np.arange(len(slots))
        lab[q[:, 1], q[:, 0]] = idx
        off = np.arange(-r, r + 1)
        nb = lab[q[:, 1, None, None] + off[None, :, None], q[:, 0, None, None] + off[None, None, :]].reshape(len(slots), -1)
        lab[q[:, 1], q[:, 0]] = -1
        pair = (nb >= 0) & (nb != idx[:, None])
        if not pair.any():  # the usual case: no two tracks within r px
            return np.zeros(0, np.int64)
        i_idx, col = np.nonzero(pair)
        j_idx = nb[i_idx, col]
        # Same-pixel pairs: the overwritten point sees the survivor; add the reverse direction too.
        i_idx, j_idx = np.concatenate([i_idx, j_idx]), np.concatenate([j_idx, i_idx])
        close = np.linalg.norm(uv[i_idx] - uv[j_idx], axis=1) < dist
        ids = self._id[slots]
        younger = np.where(ids[i_idx[close]] > ids[j_idx[close]], i_idx[close], j_idx[close])
        return np.unique(slots[younger])
