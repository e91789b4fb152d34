"""Every message against the truth (definitions: :mod:`flightsim.score`).

:func:`evaluate` turns :class:`~flightsim.score.inputs.RangeMessages` and
:class:`~flightsim.score.inputs.SectorTruth` into an :class:`Evaluation`: per OBSTACLE_DISTANCE
and sector, what was published and what the truth at arrival says, in view or not, warm-up,
obstacle id and *remembered* (:func:`remembered_cells`); per message, the exposure mapped onto the
truth clock and the latency; per forward DISTANCE_SENSOR, σ (from ``covariance`` or
``signal_quality``), the estimate behind the published value and the truth at arrival and at
exposure.  :func:`cell_masks` sorts the counted cells into the categories
(:class:`CellMasks`) that :mod:`flightsim.score.summary` counts.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

from companion.core.sectors_types import estimate_from_conservative

from flightsim.score.config import (
    N_SECTORS,
    REP_CLEAR,
    REP_INVALID,
    REP_RANGE,
    REP_UNKNOWN,
    SECTOR_DEG,
    TRUTH_CLEAR,
    TRUTH_NONE,
    TRUTH_OBSTACLE,
    TRUTH_UNSEEN,
    UNKNOWN_CM,
    ScoreConfig,
)
from flightsim.score.inputs import RangeMessages, SectorTruth
from flightsim.score.obstacles import group_obstacles, name_obstacles


# ---------------------------------------------------------------------- evaluation -------------
@dataclasses.dataclass(eq=False)
class Evaluation:
    """Per-message, per-cell results of :func:`evaluate` (arrays; see :func:`series_arrays`)."""

    config: ScoreConfig
    t0: float  # first truth frame, recording clock
    frame_period_s: float
    sector_max_m: float
    # OBSTACLE_DISTANCE
    od_t: np.ndarray
    od_frame: np.ndarray  # truth frame at arrival (−1: none)
    od_scored: np.ndarray  # geometry ok and truth available
    od_rep: np.ndarray  # (N, 72) REP_*
    od_r: np.ndarray  # (N, 72) published range, m (NaN unless REP_RANGE)
    od_cm: np.ndarray  # (N, 72) published value, cm
    od_truth: np.ndarray  # (N, 72) truth at arrival (NaN where unseen or no truth)
    od_tcls: np.ndarray  # (N, 72) TRUTH_*
    od_max_m: np.ndarray  # (N,)
    od_label: np.ndarray  # (N, 72) obstacle id of obstacle cells (−1 elsewhere)
    od_capture_t: np.ndarray  # (N,) exposure, recording clock (NaN unknown)
    od_capture_frame: np.ndarray  # (N,) truth frame of the exposure (−1 unknown / not matched)
    od_latency_s: np.ndarray  # (N,)
    od_in_view: np.ndarray  # (N, 72) bool, the truth frame's sector is in the camera's view
    od_warmup: np.ndarray  # (N,) bool, stamped within warmup_s of the first truth frame (not scored)
    od_remember: np.ndarray  # (N, 72) bool, out-of-view obstacle cell of an obstacle seen recently nearby ("remembered")
    od_rangeable: np.ndarray  # (N, 72) bool, in-view or remembered obstacle cell a single camera could have ranged (rangeable_cells)
    # DISTANCE_SENSOR (forward)
    ds_t: np.ndarray
    ds_frame: np.ndarray
    ds_state: np.ndarray  # REP_*
    ds_published_m: np.ndarray
    ds_sigma_m: np.ndarray
    ds_sigma_source: np.ndarray  # 0 none, 1 covariance, 2 signal_quality
    ds_estimate_m: np.ndarray
    ds_truth_arrival: np.ndarray
    ds_truth_exposure: np.ndarray
    ds_max_m: np.ndarray
    # obstacles and clock
    obstacle_names: list[str]
    obstacle_centroids: np.ndarray
    boot_offset_s: float
    capture_residual_s: np.ndarray  # |mapped exposure − nearest frame| of matched messages
    messages: RangeMessages
    notes: list[str]
    truth_360: bool = False  # the truth knows the sectors out of view (truth.npz in_view / sector_all_m)


def _classify_published(cm: np.ndarray, min_cm: np.ndarray, max_cm: np.ndarray) -> np.ndarray:
    rep = np.full(cm.shape, REP_INVALID, np.int8)
    rep[cm == UNKNOWN_CM] = REP_UNKNOWN
    rep[cm == max_cm + 1] = REP_CLEAR
    rep[(cm >= min_cm) & (cm <= max_cm)] = REP_RANGE
    return rep


def sector_of(d_n: np.ndarray, d_e: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Sector index (0…71, body FRD from forward, clockwise) of the horizontal direction ``(d_n, d_e)``
    (world NE) seen from a vehicle at heading ``yaw`` (rad): the nearest sector centre."""
    rel_deg = np.degrees(np.arctan2(d_e, d_n) - yaw)
    return np.mod(np.rint(rel_deg / SECTOR_DEG).astype(np.int64), N_SECTORS)


def cell_points(truth: SectorTruth, j: np.ndarray, ii: np.ndarray) -> np.ndarray:
    """(C, 3) world NED point behind each cell (truth frame ``j``, sector ``ii``): at the cell's true
    distance on its centre bearing, at the vehicle's altitude (the band's centre)."""
    p = np.asarray(truth.p_ned, float)
    b = np.asarray(truth.yaw, float)[j] + np.radians(ii * SECTOR_DEG)
    dist = np.asarray(truth.sector_m, float)[j, ii]
    return np.column_stack([p[j, 0] + dist * np.cos(b), p[j, 1] + dist * np.sin(b), p[j, 2]])


def remembered_cells(truth: SectorTruth, labels: np.ndarray, view_f: np.ndarray, frame: np.ndarray, lab: np.ndarray,
                     candidates: np.ndarray, config: ScoreConfig,
                     visible: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The *remembered* cells among ``candidates`` (out-of-view obstacle cells of the messages; the
    coverage targets, docs/derivations/obstacle_map.md): ``(remembered (N, 72) bool, seen (N, 72)
    int)``, ``seen`` the truth frame in which the cell was last in view (−1 elsewhere).

    Rule (per obstacle, by the grouping of :func:`group_obstacles`): the cell's obstacle ``k``
    (``lab``) occupied an in-view finite truth cell in some truth frame at most
    ``remember_window_s`` before the message's truth frame (``frame``), and the vehicle moved less
    than ``remember_max_travel_m`` (3-D) from its position in the *latest* such frame.  One group
    may be large (a long wall): a part of it that never was in view counts when another part was.
    With ``remember_point`` the cell's own point must have been in view (:func:`_point_seen`; with
    ``remember_visible`` and ``visible`` also in the line of sight), and ``seen`` is that frame; without,
    ``seen`` is the obstacle's.
    """
    cfg = config
    n = len(frame)
    out = np.zeros((n, N_SECTORS), bool)
    seen_at = np.full((n, N_SECTORS), -1, np.int64)
    K = int(labels.max()) + 1 if labels.size else 0
    if K == 0 or n == 0 or not np.any(candidates):
        return out, seen_at
    F = len(truth.t_s)
    seen = np.zeros((F, K), bool)
    ff, ss = np.nonzero((labels >= 0) & view_f)
    seen[ff, labels[ff, ss]] = True
    last = np.maximum.accumulate(np.where(seen, np.arange(F)[:, None], -1), axis=0)  # latest in-view frame, (F, K)
    nn, ii = np.nonzero(candidates & (lab >= 0) & (frame >= 0)[:, None])
    j = frame[nn]
    ls = last[j, lab[nn, ii]]
    lsj = np.maximum(ls, 0)
    ok = (ls >= 0) & (truth.t_s[j] - truth.t_s[lsj] <= cfg.remember_window_s + 1e-9)
    ok &= np.linalg.norm(np.asarray(truth.p_ned, float)[j] - np.asarray(truth.p_ned, float)[lsj], axis=1) < cfg.remember_max_travel_m
    nn, ii, j, ref = nn[ok], ii[ok], j[ok], lsj[ok]
    if cfg.remember_point:
        ref = _point_seen(truth, view_f, j, cell_points(truth, j, ii), cfg, visible)
        nn, ii, ref = nn[ref >= 0], ii[ref >= 0], ref[ref >= 0]
    out[nn, ii] = True
    seen_at[nn, ii] = ref
    return out, seen_at


def _window(truth: SectorTruth, j: np.ndarray, window_s: float) -> tuple[np.ndarray, int]:
    """First truth frame within ``window_s`` before each frame ``j``, and the widest window in frames."""
    t = np.asarray(truth.t_s, float)
    lo = np.searchsorted(t, t[j] - window_s - 1e-9, side="left")
    return lo, int(np.max(j - lo)) + 1


def _keep_visible(mask: np.ndarray, visible: Callable[[np.ndarray, np.ndarray], np.ndarray], p: np.ndarray,
                  f: np.ndarray, pt: np.ndarray) -> None:
    """In place: ``mask`` (C, W) of (point, frame) pairs keeps only those where the vehicle at truth frame ``f[c, w]``
    (positions ``p``) had the point ``pt[c]`` in its line of sight (``visible``); only the pairs set are tested."""
    cc, ww = np.nonzero(mask)
    if cc.size:
        mask[cc, ww] = visible(p[f[cc, ww]], pt[cc])


def _point_seen(truth: SectorTruth, view_f: np.ndarray, j: np.ndarray, pt: np.ndarray, cfg: ScoreConfig,
                visible: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """(len(j),) int: the latest truth frame at most ``remember_window_s`` before (or at) frame ``j`` in
    which the world point ``pt`` (C, 3) lay in an in-view sector within ``sector_max_m`` of the vehicle,
    from where the vehicle has since moved less than ``remember_max_travel_m``, and — with ``visible`` and
    ``remember_visible``
    (``visible(origins (K, 3), points (K, 3)) -> (K,) bool``, :func:`flightsim.score.obstacles.world_visibility`)
    — in the line of sight from the vehicle then; −1 if none.  A long wall counts only where its own part
    was in view; without ``visible`` a point hidden behind a solid (another obstacle, or the far side of
    its own) counts as seen."""
    out = np.full(len(j), -1, np.int64)
    if len(j) == 0:
        return out
    p = np.asarray(truth.p_ned, float)
    yaw = np.asarray(truth.yaw, float)
    lo, W = _window(truth, j, cfg.remember_window_s)
    for c0 in range(0, len(j), 2048):  # chunks of cells, vectorized over cells × frames of the window
        c = slice(c0, c0 + 2048)
        f = j[c, None] - np.arange(W)[None, :]  # (c, W) frames back from the cell's own
        inwin = f >= lo[c, None]
        f = np.maximum(f, 0)
        rel = pt[c, None, :2] - p[f, :2]
        r = np.hypot(rel[..., 0], rel[..., 1])
        sec = sector_of(rel[..., 0], rel[..., 1], yaw[f])
        moved = np.linalg.norm(p[j[c], None, :] - p[f], axis=2) < cfg.remember_max_travel_m
        hit = inwin & view_f[f, sec] & (r <= truth.sector_max_m) & moved
        if visible is not None and cfg.remember_visible:  # in view is not seen: the line of sight must be free
            _keep_visible(hit, visible, p, f, pt[c])
        first = np.argmax(hit, axis=1)  # the latest such frame (f runs backwards)
        out[c] = np.where(hit.any(axis=1), f[np.arange(len(first)), first], -1)
    return out


def points_rangeable(truth: SectorTruth, view_f: np.ndarray, pt: np.ndarray, j: np.ndarray, config: ScoreConfig,
                     visible: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """(C,) bool: could a single camera have ranged the world point ``pt`` (C, 3) by truth frame ``j``?

    Yes when, in some truth frame ``f`` at most ``rangeable_window_s`` before ``j`` and no later, the
    point lay in an in-view sector within ``sector_max_m``, and either the lines of sight to it from
    the vehicle at ``f`` and at ``j`` differ by at least ``rangeable_parallax_deg`` (the bearing
    parallax of DESIGN.md §3's triangulation) or its distances from the two differ by at least the
    fraction ``rangeable_scale`` (looming, DESIGN.md §7).  A vehicle turning in place gains neither:
    a bearing and a scale that do not change carry no range.  With ``visible`` (and ``rangeable_visible``)
    that earlier view must also have had the point in its line of sight
    (:func:`flightsim.score.obstacles.world_visibility`).  Texture is not checked, and the camera is taken
    at the vehicle's centre: an upper bound for any monocular method.
    """
    cfg = config
    ok = np.zeros(len(j), bool)
    if len(j) == 0:
        return ok
    p = np.asarray(truth.p_ned, float)
    yaw = np.asarray(truth.yaw, float)
    los_j = pt - p[j]
    r_j = np.linalg.norm(los_j, axis=1)
    cos_min = math.cos(math.radians(cfg.rangeable_parallax_deg))
    log_scale = math.log1p(cfg.rangeable_scale)
    lo, W = _window(truth, j, cfg.rangeable_window_s)
    for c0 in range(0, len(j), 1024):  # chunks of points, vectorized over points × frames of the window
        c = slice(c0, c0 + 1024)
        f = j[c, None] - np.arange(W)[None, :]  # (c, W) this frame and those before it
        inwin = f >= lo[c, None]
        f = np.maximum(f, 0)
        los = pt[c, None, :] - p[f]  # (c, W, 3)
        r = np.linalg.norm(los, axis=2)
        r_h = np.hypot(los[..., 0], los[..., 1])
        seen = inwin & view_f[f, sector_of(los[..., 0], los[..., 1], yaw[f])] & (r_h <= truth.sector_max_m)
        with np.errstate(invalid="ignore", divide="ignore"):
            cosang = np.einsum("cwk,ck->cw", los, los_j[c]) / (r * r_j[c, None])
            loom = np.abs(np.log(r / r_j[c, None]))
        cand = seen & ((cosang <= cos_min) | (loom >= log_scale))
        if visible is not None and cfg.rangeable_visible:  # that view must have seen the point
            _keep_visible(cand, visible, p, f, pt[c])
        ok[c] = np.any(cand, axis=1)
    return ok


def rangeable_cells(truth: SectorTruth, view_f: np.ndarray, frame: np.ndarray, candidates: np.ndarray,
                    config: ScoreConfig, ref: np.ndarray | None = None,
                    visible: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """(N, 72) bool: the *rangeable* cells among ``candidates``: cells whose point
    (:func:`cell_points`, at the message's truth frame ``frame``) a single camera could have ranged
    (:func:`points_rangeable`) by the frame ``ref`` (N, 72) — the message's own for cells in view
    (default), the one in which the point was last seen for remembered cells.  A diagnostic: the
    ceiling of any monocular method (definitions in :mod:`flightsim.score`)."""
    n = len(frame)
    out = np.zeros((n, N_SECTORS), bool)
    if ref is None:
        ref = np.broadcast_to(frame[:, None], (n, N_SECTORS))
    nn, ii = np.nonzero(candidates & (frame >= 0)[:, None] & (ref >= 0))
    if nn.size == 0:
        return out
    j, jr = frame[nn], ref[nn, ii]
    key, inv = np.unique(np.stack([j, ii, jr], 1), axis=0, return_inverse=True)  # one test per distinct cell
    pt = cell_points(truth, key[:, 0], key[:, 1])
    out[nn, ii] = points_rangeable(truth, view_f, pt, key[:, 2], config, visible)[inv.reshape(-1)]
    return out


def _boot_offset(msgs: RangeMessages) -> float:
    ok = msgs.boot_ms > 0
    if not np.any(ok):
        return math.nan
    return float(np.min(msgs.boot_t[ok] - msgs.boot_ms[ok] * 1e-3))


def evaluate(msgs: RangeMessages, truth: SectorTruth, config: ScoreConfig = ScoreConfig(), *,
             namer: Callable[[np.ndarray], list] | None = None,
             visible: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> Evaluation:
    """Compare every message with the truth (definitions in the module docstring); ``namer`` names the
    obstacles, ``visible`` tests lines of sight in the world (:func:`flightsim.score.obstacles.world_visibility`:
    a remembered cell's point must have been seen, not only in view; without it, a note says so)."""
    cfg = config
    notes: list[str] = []
    fp = truth.frame_period_s
    # --- OBSTACLE_DISTANCE cells ----------------------------------------------------------------
    n = len(msgs.od_t)
    cm = msgs.od_distances_cm.reshape(n, N_SECTORS)
    min_cm = msgs.od_min_cm[:, None]
    max_cm = msgs.od_max_cm[:, None]
    rep = _classify_published(cm, min_cm, max_cm)
    r = np.where(rep == REP_RANGE, cm / 100.0, np.nan)
    frame = truth.frame_at(msgs.od_t, cfg.truth_max_age_s)
    has_truth = msgs.od_geometry_ok & (frame >= 0)
    warm = np.asarray(msgs.od_t, float) - float(truth.t_s[0]) < cfg.warmup_s - 1e-9
    scored = has_truth & ~warm
    T = np.full((n, N_SECTORS), np.nan)
    T[has_truth] = truth.sector_m[frame[has_truth]]
    view_f = truth.view
    view = np.zeros((n, N_SECTORS), bool)
    view[has_truth] = view_f[frame[has_truth]]
    if cfg.warmup_s > 0 and np.any(has_truth & warm):
        notes.append(f"{int(np.sum(has_truth & warm))} OBSTACLE_DISTANCE messages in the first {cfg.warmup_s:g} s "
                     "(warm-up) were not scored")
    max_m = msgs.od_max_cm / 100.0
    tcls = np.full((n, N_SECTORS), TRUTH_NONE, np.int8)
    tcls[scored] = TRUTH_UNSEEN
    fin = np.isfinite(T)
    tcls[scored[:, None] & fin & (T <= max_m[:, None])] = TRUTH_OBSTACLE
    tcls[scored[:, None] & ~np.isnan(T) & ~(fin & (T <= max_m[:, None]))] = TRUTH_CLEAR
    if n and np.any(max_m[scored] > truth.sector_max_m + 1e-9):
        notes.append(f"messages claim up to {max_m[scored].max():g} m but the truth only reaches {truth.sector_max_m:g} m: "
                     "cells whose truth is inf may hide an obstacle between the two")
    if np.any(~msgs.od_geometry_ok):
        notes.append(f"{int(np.sum(~msgs.od_geometry_ok))} OBSTACLE_DISTANCE messages not in 72 × 5° BODY_FRD were not scored")
    # --- obstacles --------------------------------------------------------------------------------
    labels, centroids, points = group_obstacles(truth, cfg)
    names = name_obstacles(centroids, points, namer)
    lab = np.full((n, N_SECTORS), -1, np.int64)
    lab[scored] = labels[frame[scored]]
    lab[tcls != TRUTH_OBSTACLE] = -1
    remember, seen_at = remembered_cells(truth, labels, view_f, frame, lab, (tcls == TRUTH_OBSTACLE) & ~view, cfg, visible)
    if cfg.remember_point and cfg.remember_visible and visible is None and np.any(remember):
        notes.append("remembered cells: lines of sight not checked (no world given), so a point hidden behind a solid "
                     "counts as seen")
    rangeable = rangeable_cells(truth, view_f, frame, (tcls == TRUTH_OBSTACLE) & view, cfg, visible=visible)
    rangeable |= rangeable_cells(truth, view_f, frame, remember, cfg, ref=seen_at, visible=visible)
    # --- exposure and latency -----------------------------------------------------------------
    off = _boot_offset(msgs)
    cap_t = np.full(n, np.nan)
    cap_f = np.full(n, -1, np.int64)
    resid = np.zeros(0)
    has_exp = msgs.od_time_usec > 0
    if n and np.any(has_exp):
        if math.isfinite(off):
            mapped = msgs.od_time_usec * 1e-6 + off
            k = np.clip(np.searchsorted(truth.t_s, mapped), 1, max(len(truth.t_s) - 1, 1))
            k0 = np.clip(k - 1, 0, len(truth.t_s) - 1)
            k1 = np.clip(k, 0, len(truth.t_s) - 1)
            near = np.where(np.abs(mapped - truth.t_s[k0]) <= np.abs(mapped - truth.t_s[k1]), k0, k1)
            d = np.abs(mapped - truth.t_s[near])
            snap = has_exp & (d <= cfg.capture_snap * (fp if math.isfinite(fp) else 0.0) + 1e-9)
            cap_t = np.where(snap, truth.t_s[near], np.where(has_exp, mapped, np.nan))
            cap_f = np.where(snap, near, -1)
            resid = d[snap]
            if np.any(has_exp & ~snap):
                notes.append(f"{int(np.sum(has_exp & ~snap))} exposures did not map onto a truth frame "
                             f"(within {cfg.capture_snap:g} frame periods); their latency uses the mapped time")
        else:
            notes.append("no message carries the companion's sending time_boot_ms: exposure times and latency unknown")
    latency = msgs.od_t - cap_t
    # --- DISTANCE_SENSOR (forward) --------------------------------------------------------------
    fwd = msgs.ds_orientation == 0
    if np.any(~fwd):
        notes.append(f"{int(np.sum(~fwd))} DISTANCE_SENSOR messages not facing forward were ignored")
    ds_t = msgs.ds_t[fwd]
    dcm = msgs.ds_distance_cm[fwd]
    dmin, dmax = msgs.ds_min_cm[fwd], msgs.ds_max_cm[fwd]
    cov, q = msgs.ds_covariance[fwd], msgs.ds_quality[fwd]
    ds_state = _classify_published(dcm, dmin, dmax)
    pub = np.where(ds_state == REP_RANGE, dcm / 100.0, np.nan)
    sig = np.full(len(ds_t), np.nan)
    src = np.zeros(len(ds_t), np.int8)
    rng_ok = (ds_state == REP_RANGE) & (dcm > dmin) & (dcm < dmax)  # clamped values cannot be undone
    by_cov = rng_ok & (cov > 0) & (cov < 255)
    sig[by_cov] = np.sqrt(cov[by_cov]) / 100.0
    src[by_cov] = 1
    by_q = rng_ok & ~by_cov & (q >= 3) & (q <= 99)
    sig[by_q] = pub[by_q] * cfg.quality_zero_rel_sigma * (1.0 - q[by_q] / 100.0)
    src[by_q] = 2
    est = estimate_from_conservative(pub, sig, cfg.sigma_k, cfg.sigma_k_far, cfg.sigma_k_taper_from_m, cfg.sigma_k_taper_to_m)
    ds_frame = truth.frame_at(ds_t, cfg.truth_max_age_s)
    ds_frame[ds_t - float(truth.t_s[0]) < cfg.warmup_s - 1e-9] = -1  # warm-up: not scored
    t_arr = np.where(ds_frame >= 0, truth.sector_m[np.maximum(ds_frame, 0), 0], np.nan)
    # pair each DISTANCE_SENSOR with the OBSTACLE_DISTANCE sent just before it (same result)
    t_exp = np.full(len(ds_t), np.nan)
    if n and len(ds_t):
        j = np.searchsorted(msgs.od_t, ds_t + 1e-9, side="right") - 1
        jj = np.maximum(j, 0)
        paired = (j >= 0) & (ds_t - msgs.od_t[jj] <= cfg.pair_window_s + 1e-9) & (cap_f[jj] >= 0) & (ds_frame >= 0)
        t_exp[paired] = truth.sector_m[cap_f[jj[paired]], 0]
    ds_max_m = dmax / 100.0
    return Evaluation(
        config=cfg, t0=float(truth.t_s[0]), frame_period_s=fp, sector_max_m=float(truth.sector_max_m),
        od_t=msgs.od_t, od_frame=frame, od_scored=scored, od_rep=rep, od_r=r, od_cm=cm, od_truth=T, od_tcls=tcls,
        od_max_m=max_m, od_label=lab, od_capture_t=cap_t, od_capture_frame=cap_f, od_latency_s=latency,
        od_in_view=view, od_warmup=warm, od_remember=remember, od_rangeable=rangeable,
        ds_t=ds_t, ds_frame=ds_frame, ds_state=ds_state, ds_published_m=pub, ds_sigma_m=sig, ds_sigma_source=src,
        ds_estimate_m=est, ds_truth_arrival=t_arr, ds_truth_exposure=t_exp, ds_max_m=ds_max_m,
        obstacle_names=names, obstacle_centroids=centroids, boot_offset_s=off, capture_residual_s=resid,
        messages=msgs, notes=notes, truth_360=truth.in_view is not None,
    )


# ---------------------------------------------------------------------- cell masks -------------
@dataclasses.dataclass(frozen=True, eq=False)
class CellMasks:
    """Boolean (N, 72) masks of the cell categories (module docstring), over all *counted* cells:
    every cell in view, and out of view the cells with a claim (a range or "clear"; unknown out of
    view is neutral).  ``in_view`` splits them."""

    obstacle: np.ndarray
    clear: np.ndarray
    detection: np.ndarray
    valid: np.ndarray
    dangerous: np.ndarray
    false_clear: np.ndarray  # false obstacle in a clear cell
    unverifiable: np.ndarray  # range in a cell whose truth is inf, within tolerance of the truth horizon
    too_near: np.ndarray  # false obstacle in an obstacle cell
    over_range: np.ndarray
    missed_unknown: np.ndarray  # unknown in an obstacle cell
    claimed_clear: np.ndarray  # clear reported in a clear cell
    unscored_claim: np.ndarray  # range or clear in an unseen cell
    invalid: np.ndarray  # published value neither unknown, clear nor a range (scored messages)
    in_view: np.ndarray  # the cell's sector is in the camera's view
    obstacle_any: np.ndarray  # obstacle truth, counted or not (out of view: with unknown too)
    clear_any: np.ndarray  # clear truth, counted or not
    unknown_out_of_view: np.ndarray  # unknown in an out-of-view cell whose truth is known (neutral)
    remembered: np.ndarray  # out-of-view obstacle cells of an obstacle in view recently nearby (remembered_cells)
    rangeable: np.ndarray  # in-view obstacle cells a single camera could have ranged (rangeable_cells)
    remembered_rangeable: np.ndarray  # remembered cells whose point was rangeable when last in view


def range_errors(T: np.ndarray, r: np.ndarray, config: ScoreConfig) -> tuple[np.ndarray, np.ndarray]:
    """(too near, too far): the published range ``r`` nearer / farther than the true distance ``T``
    by more than ``tol(T)``; both False where ``T`` is not finite or there is no range (NaN)."""
    T = np.asarray(T, float)
    with np.errstate(invalid="ignore"):
        tol = np.where(np.isfinite(T), config.tolerance(np.where(np.isfinite(T), T, 0.0)), np.inf)
        return T - r > tol, r - T > tol


def cell_masks(ev: Evaluation) -> CellMasks:
    cfg = ev.config
    rep, T, tc = ev.od_rep, ev.od_truth, ev.od_tcls
    view = ev.od_in_view
    rng = rep == REP_RANGE
    claim = rng | (rep == REP_CLEAR)
    counted = view | claim
    obstacle_any = tc == TRUTH_OBSTACLE
    clear_any = tc == TRUTH_CLEAR
    obstacle = obstacle_any & counted
    clear = clear_any & counted
    under, over = range_errors(T, ev.od_r, cfg)
    detection = obstacle & rng
    too_near = detection & under
    over_range = detection & over
    H = ev.sector_max_m
    beyond = clear & rng & np.isinf(T)
    horizon_under = (H - ev.od_r) > cfg.tolerance(H)
    false_clear = clear & rng & (np.where(np.isinf(T), horizon_under, under))
    unverifiable = beyond & ~horizon_under
    scored = ev.od_scored[:, None]
    return CellMasks(
        obstacle=obstacle, clear=clear, detection=detection, valid=detection & ~too_near & ~over_range,
        dangerous=obstacle & (rep == REP_CLEAR), false_clear=false_clear, unverifiable=unverifiable, too_near=too_near, over_range=over_range,
        missed_unknown=obstacle & (rep == REP_UNKNOWN), claimed_clear=clear & (rep == REP_CLEAR),
        unscored_claim=(tc == TRUTH_UNSEEN) & claim, invalid=scored & (rep == REP_INVALID),
        in_view=view, obstacle_any=obstacle_any, clear_any=clear_any,
        unknown_out_of_view=(obstacle_any | clear_any) & ~view & (rep == REP_UNKNOWN),
        remembered=ev.od_remember & obstacle_any,
        rangeable=ev.od_rangeable & obstacle & view,
        remembered_rangeable=ev.od_rangeable & ev.od_remember & obstacle_any,
    )
