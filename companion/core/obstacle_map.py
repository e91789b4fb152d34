"""Local obstacle map: converged landmarks kept as world points after their tracks end (docs/derivations/obstacle_map.md).

Pure logic, no I/O, no globals.  The pipeline calls, in order, once per frame:

1. :func:`points_on_current_rays` — each landmark seen in this frame placed at its estimated range
   along the ray measured now (the filter's own point lies on its *anchor* ray, docs/derivations/ekf_anchored.md);
2. :meth:`ObstacleMap.observe` — converged landmarks enter (or refresh) the map with a world
   covariance (:func:`landmark_covariance`); retired (diverged) landmarks are forgotten;
3. :meth:`ObstacleMap.check_view` — remembered points predicted in view are compared with the live
   converged landmarks near their predicted pixel: found again (re-observed, ``o``) or seen through
   (``u``: a live point lies clearly beyond where the remembered one should be);
4. :meth:`ObstacleMap.prune` — retention (see below);
5. :meth:`ObstacleMap.remembered` — remembered points relative to the vehicle, with their range and
   tangential σ grown since they were last observed, for
   :func:`companion.core.sectors.compute_sectors` (over 360°);
6. :func:`world_to_body` — points into body FRD at exposure.

Model (docs/derivations/obstacle_map.md)
----------------------------------------
The point is static in the world (local NED); what grows is its uncertainty *relative to the
vehicle*: the vehicle's position estimate drifts after the point was last observed (σ_drift =
min(position_drift_mps · Δt, position_drift_max_m) per axis, a random-walk bound of the correlated
GPS error) and its heading drifts (σ_ψ = heading_drift_deg_s · Δt, seen as r_h · σ_ψ across the
line of sight).  With u the unit vector from the vehicle to the point,

    σ_r² = uᵀ P u + σ_drift²,        σ_t² = (tr P − uᵀ P u)/2 + σ_drift² + (r_h σ_ψ)²,

P the point's world covariance when it was last observed.  A landmark's covariance at entry is that
of its filter: σ_range² along the line of sight and (r · σ_bearing)² across it
(:func:`landmark_covariance`).  Only landmarks their filter explains as static points enter
(:func:`consistent_for_entry`: mean NIS within ``max_entry_nis_ratio`` × the frame's median); a
remembered point is published only with ``min_support`` map points within max(``support_radius_m``,
``support_radius_rel`` × its distance).

Retention (seed 003 §3.6, docs/derivations/obstacle_map.md)
-----------------------------------------------------------
Usage score s = (o − 0.5·u)/(1 + o), o = re-observations (a remembered point predicted in view
and found again: a live converged landmark within ``reobserve_radius_px`` of its predicted pixel
whose depth agrees within ``gate_k`` σ; or a newly converged landmark that lands within ``gate_k``
σ of it, which then takes the point over, fused, instead of adding another), u = missed predictions (predicted in view, and a live
converged landmark near its pixel lies clearly *beyond* it: the camera sees through where the point
should be — it moved, or it was a mismatch).  No live landmark near the pixel is no evidence either
way (a texture-less patch, an unconverged track), and a live landmark clearly *nearer* is an
occluder; neither changes the counts.  A point leaves the map when s < ``min_score``, when it is
farther than ``radius_m`` from the vehicle, or older (since last observed) than ``max_age_s``; the
count is capped at ``max_landmarks``, lowest score evicted first (then the longest unseen).
Memory is bounded by the cap: every array is sized by the number of points held.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np

from companion.config import require, require_finite
from companion.core import jit as _jit
from companion.errors import InputError

#: Reasons an input landmark is refused by :meth:`ObstacleMap.observe` (counted, never raised).
REJECT_NOT_FINITE = "not_finite"
REJECT_NOT_PD = "covariance_not_positive_definite"


@dataclasses.dataclass(frozen=True)
class MapConfig:
    """The ``[map]`` table."""

    enabled: bool = True  # keep converged landmarks after their tracks end and publish them over 360°
    max_landmarks: int = 1500  # hard cap on points held (lowest usage score evicted first)
    radius_m: float = 60.0  # points farther than this from the vehicle are dropped, m
    max_age_s: float = 20.0  # points not observed for this long are dropped, s
    min_score: float = -0.75  # usage score s = (o − 0.5u)/(1 + o) below this drops a point
    max_rel_sigma: float = 0.15  # a converged landmark enters the map only when its σ/range is at most this
    max_entry_nis_ratio: float = 10.0  # ... and its filter's mean NIS is at most this many times the median over the converged landmarks of the frame (occlusion-edge mismatches sit far above the points their filters explain; relative, so it follows the camera's real pixel noise); 0 = off
    position_drift_mps: float = 0.02  # growth of the vehicle's position error relative to a remembered point, m per s
    position_drift_max_m: float = 1.5  # ... bounded by this (the correlated GPS error does not grow without bound), m
    heading_drift_deg_s: float = 0.05  # heading drift since a point was last observed, degrees per s
    reobserve_radius_px: float = 6.0  # a live landmark within this of a remembered point's predicted pixel can confirm or contradict it, px
    gate_k: float = 3.0  # depths agree when within gate_k combined σ (found); a live point beyond that is "seen through" (missed)
    image_margin_px: float = 4.0  # a remembered point is predicted in view only this far inside the image border, px
    min_support: int = 2  # a remembered point is published only with at least this many map points (itself included) within support_radius_m
    support_radius_m: float = 0.6  # neighbourhood of that support test, m (at least)
    support_radius_rel: float = 0.15  # ... or this fraction of the point's distance from the vehicle, if larger (corners are spaced in pixels, so neighbours lie farther apart far away)

    def __post_init__(self) -> None:
        require(isinstance(self.enabled, bool), "enabled must be true or false")
        require(isinstance(self.max_landmarks, int) and not isinstance(self.max_landmarks, bool) and self.max_landmarks >= 1,
                f"max_landmarks must be an integer >= 1, got {self.max_landmarks!r}")
        require(isinstance(self.min_support, int) and not isinstance(self.min_support, bool) and self.min_support >= 1,
                f"min_support must be an integer >= 1, got {self.min_support!r}")
        for name in ("radius_m", "max_age_s", "max_rel_sigma", "reobserve_radius_px", "gate_k", "support_radius_m"):
            require_finite(name, getattr(self, name), positive=True)
        for name in ("position_drift_mps", "position_drift_max_m", "heading_drift_deg_s", "image_margin_px", "support_radius_rel",
                     "max_entry_nis_ratio"):
            require_finite(name, getattr(self, name), nonnegative=True)
        require_finite("min_score", self.min_score)
        require(-2.0 < self.min_score < 1.0, f"min_score must be in (-2, 1) (s lies in (-inf, 1)), got {self.min_score}")


def consistent_for_entry(mean_nis: np.ndarray, converged: np.ndarray, ratio: float, min_count: int = 10) -> np.ndarray:
    """(N,) bool: landmarks whose filter's mean NIS is at most ``ratio`` × the median mean NIS of the
    ``converged`` ones (docs/derivations/obstacle_map.md: a static point is well explained by its filter; a track at an
    occlusion edge mixes two depths and is not).  All True when ``ratio`` is 0 or fewer than
    ``min_count`` converged landmarks have a NIS (no reference); NaN (no update yet) is False.
    A compiled kernel when :data:`companion.core.jit.ENABLED` (the same median, the same comparison)."""
    if _jit.ENABLED:
        nis = np.asarray(mean_nis, float).reshape(-1)
        conv = np.asarray(converged, bool).reshape(-1)
        if conv.shape == nis.shape:
            return _consistent_for_entry_k(nis, conv, float(ratio), int(min_count))
    return consistent_for_entry_reference(mean_nis, converged, ratio, min_count)


def consistent_for_entry_reference(mean_nis: np.ndarray, converged: np.ndarray, ratio: float, min_count: int = 10) -> np.ndarray:
    """:func:`consistent_for_entry` by the pure-numpy reference."""
    nis = np.asarray(mean_nis, float).reshape(-1)
    ok = np.ones(nis.shape, bool)
    ref = nis[np.asarray(converged, bool).reshape(-1) & np.isfinite(nis)]
    if ratio <= 0 or ref.size < min_count:
        return ok
    with np.errstate(invalid="ignore"):
        return nis <= ratio * float(np.median(ref))


def usage_score(o: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Seed 003's usage score s = (o − 0.5·u)/(1 + o) (docs/derivations/obstacle_map.md)."""
    o = np.asarray(o, float)
    return (o - 0.5 * np.asarray(u, float)) / (1.0 + o)


def landmark_covariance(p_world: np.ndarray, p_world_cam: np.ndarray, range_sigma: np.ndarray, bearing_sigma_rad: float) -> np.ndarray:
    """(N, 3, 3) world covariance of landmarks from their filter: σ_range² along the line of sight
    from the camera, (r·σ_bearing)² across it (docs/derivations/ekf_anchored.md: the ray is measured to the pixel σ).
    A compiled kernel when :data:`companion.core.jit.ENABLED` (the same expressions per landmark)."""
    if _jit.ENABLED:
        p = np.asarray(p_world, float).reshape(-1, 3)
        sig = np.asarray(range_sigma, float).reshape(-1)
        if sig.shape[0] == p.shape[0]:
            return _landmark_covariance_k(p, np.asarray(p_world_cam, float).reshape(3), sig, float(bearing_sigma_rad))
    return landmark_covariance_reference(p_world, p_world_cam, range_sigma, bearing_sigma_rad)


def landmark_covariance_reference(p_world: np.ndarray, p_world_cam: np.ndarray, range_sigma: np.ndarray,
                                  bearing_sigma_rad: float) -> np.ndarray:
    """:func:`landmark_covariance` by the pure-numpy reference."""
    p = np.asarray(p_world, float).reshape(-1, 3)
    d = p - np.asarray(p_world_cam, float).reshape(3)
    r = np.linalg.norm(d, axis=1)
    u = d / np.maximum(r, 1e-9)[:, None]
    uu = u[:, :, None] * u[:, None, :]
    s_r2 = np.asarray(range_sigma, float).reshape(-1) ** 2
    s_t2 = (r * float(bearing_sigma_rad)) ** 2
    return s_r2[:, None, None] * uu + s_t2[:, None, None] * (np.eye(3) - uu)


def points_on_current_rays(out_ids: np.ndarray, out_p_world: np.ndarray, out_range: np.ndarray, track_ids: np.ndarray,
                           rays_cam: np.ndarray, R_world_cam: np.ndarray, p_world_cam: np.ndarray) -> np.ndarray:
    """World points for the sectors: each landmark observed in this frame at its estimated range
    along the ray measured now (``rays_cam``: unit rays of the tracks' current pixels, camera frame),
    the others where the filter puts them.

    The filter's point lies on the *anchor* ray (docs/derivations/ekf_anchored.md), so a range error moves it sideways
    as seen from the current camera (≈ range error × baseline / range): on a fast pass a mast edge's
    point drifts into the neighbouring sector.  The current pixel measures the bearing directly (to
    ~σ_px/f); only the range is the filter's.  Both id arrays must be sorted.
    A compiled kernel when :data:`companion.core.jit.ENABLED` (the same lookup and product).
    """
    if _jit.ENABLED:
        p = np.asarray(out_p_world, float).reshape(-1, 3)
        ids, tids = np.asarray(out_ids), np.asarray(track_ids)
        rays = np.asarray(rays_cam, float).reshape(-1, 3)
        rng = np.asarray(out_range, float).reshape(-1)
        if (ids.ndim == 1 and tids.ndim == 1 and ids.dtype.kind in "iu" and tids.dtype.kind in "iu" and len(ids) == len(p)
                and len(rng) == len(p) and len(rays) == len(tids)):
            return _points_on_current_rays_k(ids.astype(np.int64, copy=False), p, rng, tids.astype(np.int64, copy=False), rays,
                                             np.asarray(R_world_cam, float), np.asarray(p_world_cam, float).reshape(3))
    return points_on_current_rays_reference(out_ids, out_p_world, out_range, track_ids, rays_cam, R_world_cam, p_world_cam)


def points_on_current_rays_reference(out_ids: np.ndarray, out_p_world: np.ndarray, out_range: np.ndarray, track_ids: np.ndarray,
                                     rays_cam: np.ndarray, R_world_cam: np.ndarray, p_world_cam: np.ndarray) -> np.ndarray:
    """:func:`points_on_current_rays` by the pure-numpy reference."""
    p_world = np.array(out_p_world, float, copy=True).reshape(-1, 3)
    out_ids = np.asarray(out_ids)
    track_ids = np.asarray(track_ids)
    if len(out_ids) == 0 or len(track_ids) == 0:
        return p_world
    pos = np.minimum(np.searchsorted(track_ids, out_ids), len(track_ids) - 1)
    seen = track_ids[pos] == out_ids
    if np.any(seen):
        d_cam = np.asarray(rays_cam, float)[pos[seen]]
        p_world[seen] = np.asarray(p_world_cam, float) + (d_cam @ np.asarray(R_world_cam, float).T) * np.asarray(out_range, float)[seen][:, None]
    return p_world


def world_to_body(p_world: np.ndarray, R_world_body: np.ndarray, p_world_body: np.ndarray) -> np.ndarray:
    """Points (N, 3) from local NED into body FRD at the pose (R_world_body, p_world_body) (docs/derivations/frames.md)."""
    return (np.asarray(p_world, float).reshape(-1, 3) - np.asarray(p_world_body, float)) @ np.asarray(R_world_body, float)


class MapEntries(NamedTuple):
    """The landmarks of one frame as the map takes them (:func:`map_entries`)."""

    keys: np.ndarray  # (N,) map key of every landmark the estimator runs (its live keys)
    good: np.ndarray  # (N,) bool: converged, valid, σ/range ≤ max_rel_sigma and consistent: may enter
    forget: np.ndarray  # keys of converged landmarks refused for their NIS: what they left in the map goes
    entry_keys: np.ndarray  # (M,) keys of the ``good`` ones
    p_world: np.ndarray  # (M, 3) their points
    P_world: np.ndarray  # (M, 3, 3) their covariances (:func:`landmark_covariance`)


def map_entries(ids, key_base: int, converged, valid, range_sigma, range_m, p_world, p_world_cam, bearing_sigma_rad: float,
                config: MapConfig, mean_nis=None) -> MapEntries:
    """Which landmarks of this frame enter the map, with their world covariance (step 2 of the module
    doc; docs/derivations/obstacle_map.md, "Entry covariance and consistency"): converged and valid,
    σ_range ≤ ``max_rel_sigma`` × range, and (``max_entry_nis_ratio`` > 0, NIS given) consistent by
    :func:`consistent_for_entry`.  A compiled kernel when :data:`companion.core.jit.ENABLED`."""
    if _jit.ENABLED:
        ids = np.asarray(ids).reshape(-1)
        n = ids.size
        arrays = (np.asarray(converged, bool).reshape(-1), np.asarray(valid, bool).reshape(-1),
                  np.asarray(range_sigma, float).reshape(-1), np.asarray(range_m, float).reshape(-1),
                  np.asarray(p_world, float).reshape(-1, 3))
        nis = np.zeros(n) if mean_nis is None else np.asarray(mean_nis, float).reshape(-1)
        if ids.dtype.kind in "iu" and all(a.shape[0] == n for a in arrays) and nis.size == n:
            keys, good, forget, P = _map_entries_k(ids.astype(np.int64), int(key_base), *arrays, nis, mean_nis is not None,
                                                   float(config.max_rel_sigma), float(config.max_entry_nis_ratio),
                                                   np.asarray(p_world_cam, float).reshape(3), float(bearing_sigma_rad))
            return MapEntries(keys, good, forget, keys[good], arrays[4][good], P)
    return map_entries_reference(ids, key_base, converged, valid, range_sigma, range_m, p_world, p_world_cam, bearing_sigma_rad,
                                 config, mean_nis)


def map_entries_reference(ids, key_base: int, converged, valid, range_sigma, range_m, p_world, p_world_cam, bearing_sigma_rad: float,
                          config: MapConfig, mean_nis=None) -> MapEntries:
    """:func:`map_entries` by the pure-numpy reference."""
    keys = ids.astype(np.int64) + key_base
    good = converged & valid & (range_sigma <= config.max_rel_sigma * range_m)
    forget = np.zeros(0, np.int64)
    if config.max_entry_nis_ratio > 0 and mean_nis is not None:
        inconsistent = good & ~consistent_for_entry(mean_nis, converged & valid, config.max_entry_nis_ratio)
        if np.any(inconsistent):  # not a point the map should keep: forget what it left there
            forget = keys[inconsistent]
        good &= ~inconsistent
    P = landmark_covariance(p_world[good], p_world_cam, range_sigma[good], bearing_sigma_rad)
    return MapEntries(keys, good, forget, keys[good], p_world[good], P)


def live_view(ids, track_ids, track_uv, keys, good, p_world, range_sigma, range_m, R_world_cam, p_world_cam, camera):
    """The live landmarks with a point in the map seen in this frame, for :meth:`ObstacleMap.check_view`:
    ``(uv, depth, sigma, keys)`` — pinhole pixel (``camera``'s distortion removed), depth along the
    optical axis and its σ (σ_range · |depth| / range).  ``ids`` and ``track_ids`` sorted.
    A compiled kernel when :data:`companion.core.jit.ENABLED`."""
    if _jit.ENABLED:
        ids, tids = np.asarray(ids).reshape(-1), np.asarray(track_ids).reshape(-1)
        if ids.dtype.kind in "iu" and tids.dtype.kind in "iu":
            c = camera.config
            pinhole = _PINHOLE.get(c)
            if pinhole is None:  # once per camera
                pinhole = _PINHOLE[c] = not c.has_distortion
            rows, uv, depth, sig, lkeys = _live_view_k(
                ids.astype(np.int64), tids.astype(np.int64), np.asarray(track_uv, float).reshape(-1, 2), keys, good,
                np.asarray(p_world, float).reshape(-1, 3), np.asarray(range_sigma, float).reshape(-1),
                np.asarray(range_m, float).reshape(-1), np.asarray(R_world_cam, float), np.asarray(p_world_cam, float).reshape(3),
                float(c.fx), float(c.fy), float(c.cx), float(c.cy), pinhole)
            if rows.size and not pinhole:
                uv = camera.undistort_to_pinhole(np.asarray(track_uv, float)[rows])
            return uv, depth, sig, lkeys
    return live_view_reference(ids, track_ids, track_uv, keys, good, p_world, range_sigma, range_m, R_world_cam, p_world_cam, camera)


_PINHOLE: dict = {}  # camera config -> no distortion (a handful of cameras per process)


def live_view_reference(ids, track_ids, track_uv, keys, good, p_world, range_sigma, range_m, R_world_cam, p_world_cam, camera):
    """:func:`live_view` by the pure-numpy reference."""
    live = np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    live_keys = np.zeros(0, np.int64)
    if len(ids) and len(track_ids):
        pos = np.minimum(np.searchsorted(track_ids, ids), len(track_ids) - 1)
        seen = (track_ids[pos] == ids) & good  # live landmarks with a point in the map
        if np.any(seen):
            depth = (p_world[seen] - p_world_cam) @ R_world_cam[:, 2]
            sig = range_sigma[seen] * np.abs(depth) / np.maximum(range_m[seen], 1e-9)
            live = camera.undistort_to_pinhole(track_uv[pos[seen]]), depth, sig
            live_keys = keys[seen]
    return (*live, live_keys)


@dataclasses.dataclass(frozen=True, eq=False)
class Remembered:
    """Remembered points relative to the vehicle (output of :meth:`ObstacleMap.remembered`)."""

    keys: np.ndarray  # (M,) map keys
    p_world: np.ndarray  # (M, 3)
    range_sigma: np.ndarray  # (M,) σ of the range from the vehicle, drift included, m
    tangential_sigma: np.ndarray  # (M,) σ across the line of sight (horizontal), drift included, m
    age_s: np.ndarray  # (M,) time since last observed, s

    def __len__(self) -> int:
        return len(self.keys)


@dataclasses.dataclass(frozen=True)
class ViewCheck:
    """What :meth:`ObstacleMap.check_view` found this frame."""

    predicted: int = 0  # remembered points predicted in view
    found: int = 0  # ... found again (o += 1)
    missed: int = 0  # ... seen through (u += 1)


class ObstacleMap:
    """The local obstacle map (module docstring).  Arrays sized by the points held, at most
    ``config.max_landmarks``; ``live`` marks points whose landmark the estimator still runs."""

    _fields = ("keys", "p", "P", "t_seen", "o", "u", "live")

    def __init__(self, config: MapConfig = MapConfig()):
        self.config = config
        self.keys = np.zeros(0, np.int64)
        self.p = np.zeros((0, 3))
        self.P = np.zeros((0, 3, 3))
        self.t_seen = np.zeros(0)
        self.o = np.zeros(0, np.int64)
        self.u = np.zeros(0, np.int64)
        self.live = np.zeros(0, bool)
        self.rejected: dict[str, int] = {REJECT_NOT_FINITE: 0, REJECT_NOT_PD: 0}
        self.evicted: dict[str, int] = {"score": 0, "radius": 0, "age": 0, "cap": 0, "retired": 0}
        self.merged = 0  # new landmarks that landed on a remembered point (counted as its re-observation)
        self.absorbed = 0  # remembered points found again by a live landmark of the map, which stands for them since

    def __len__(self) -> int:
        return len(self.keys)

    @property
    def score(self) -> np.ndarray:
        return usage_score(self.o, self.u)

    def clear(self) -> None:
        for f in self._fields:
            a = getattr(self, f)
            setattr(self, f, a[:0])

    def _keep(self, mask: np.ndarray) -> None:
        for f in self._fields:
            setattr(self, f, getattr(self, f)[mask])

    def _rows(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mask of keys held, their rows)."""
        keys = np.asarray(keys, np.int64).reshape(-1)
        if len(self.keys) == 0 or len(keys) == 0:
            return np.zeros(len(keys), bool), np.zeros(len(keys), np.int64)
        order = np.argsort(self.keys, kind="stable")
        pos = np.minimum(np.searchsorted(self.keys[order], keys), len(self.keys) - 1)
        rows = order[pos]
        return self.keys[rows] == keys, rows

    # -- 2. landmarks in ---------------------------------------------------------------------------
    def observe(self, t: float, keys, p_world, P_world, live_keys=None) -> dict[str, int]:
        """Converged landmarks observed at ``t`` enter the map or refresh their point.

        ``keys`` (M,), ``p_world`` (M, 3), ``P_world`` (M, 3, 3).  ``live_keys``: every landmark the
        estimator still runs (default ``keys``); their map points are not *remembered* (the live
        estimate stands for them).  Landmarks with a non-finite point or a covariance that is not
        symmetric positive definite are refused and counted by reason (returned), never raised on.
        """
        if not math.isfinite(t):
            raise InputError("observe: t must be finite")
        keys = np.asarray(keys, np.int64).reshape(-1)
        m = len(keys)
        p = np.asarray(p_world, float).reshape(m, 3)
        P = np.asarray(P_world, float).reshape(m, 3, 3)
        if _jit.ENABLED:
            return self._observe_kernel(t, keys, p, P, live_keys)
        rej = {REJECT_NOT_FINITE: 0, REJECT_NOT_PD: 0}
        finite = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(P), axis=(1, 2))
        rej[REJECT_NOT_FINITE] = int(np.count_nonzero(~finite))
        pd = np.zeros(m, bool)
        if np.any(finite):
            Pf = P[finite]
            sym = np.all(np.abs(Pf - np.swapaxes(Pf, 1, 2)) <= 1e-9 * (1.0 + np.abs(Pf)), axis=(1, 2))
            eig_min = np.linalg.eigvalsh(0.5 * (Pf + np.swapaxes(Pf, 1, 2)))[:, 0]
            pd[finite] = sym & (eig_min > 0)
        rej[REJECT_NOT_PD] = int(np.count_nonzero(finite & ~pd))
        for k, v in rej.items():
            self.rejected[k] += v
        ok = finite & pd
        keys, p, P = keys[ok], p[ok], P[ok]
        live = keys if live_keys is None else np.asarray(live_keys, np.int64).reshape(-1)
        self.live[:] = False
        lh, lrows = self._rows(live)
        self.live[lrows[lh]] = True
        held, rows = self._rows(keys)
        if np.any(held):
            r = rows[held]
            self.p[r], self.P[r], self.t_seen[r] = p[held], P[held], t
        new = ~held
        if np.any(new):
            new = self._merge(t, keys, p, P, new, live)
        if np.any(new):
            n_new = int(np.count_nonzero(new))
            self.keys = np.concatenate([self.keys, keys[new]])
            self.p = np.concatenate([self.p, p[new]])
            self.P = np.concatenate([self.P, P[new]])
            self.t_seen = np.concatenate([self.t_seen, np.full(n_new, float(t))])
            self.o = np.concatenate([self.o, np.zeros(n_new, np.int64)])
            self.u = np.concatenate([self.u, np.zeros(n_new, np.int64)])
            self.live = np.concatenate([self.live, np.isin(keys[new], live)])
        return rej

    def _observe_kernel(self, t: float, keys: np.ndarray, p: np.ndarray, P: np.ndarray, live_keys) -> dict[str, int]:
        """:meth:`observe` through :func:`_observe_k` (same checks, rows, merges and entries as the reference)."""
        live = np.zeros(0, np.int64) if live_keys is None else np.asarray(live_keys, np.int64).reshape(-1)
        (self.keys, self.p, self.P, self.t_seen, self.o, self.u, self.live, n_bad, n_not_pd, n_merged) = _observe_k(
            self.keys, self.p, self.P, self.t_seen, self.o, self.u, keys, np.ascontiguousarray(p), np.ascontiguousarray(P), live,
            live_keys is None, float(t), self.config.gate_k**2)
        rej = {REJECT_NOT_FINITE: int(n_bad), REJECT_NOT_PD: int(n_not_pd)}
        for k, v in rej.items():
            self.rejected[k] += v
        self.merged += int(n_merged)
        return rej

    def _merge(self, t: float, keys, p, P, new, live) -> np.ndarray:
        """A new landmark that lands on a remembered point (within ``gate_k`` combined σ) is that
        point observed again: the row takes the new key, its count ``o`` grows, and its point is
        fused with the new estimate (covariance-weighted).  Keeps one point per surface patch, so the
        map's size follows the scene, not the time spent in it.  Returns the still-new mask."""
        rem = np.flatnonzero(~self.live)
        cand = np.flatnonzero(new)
        if rem.size == 0 or cand.size == 0:
            return new
        var_new = np.trace(P[cand], axis1=1, axis2=2) / 3.0
        var_rem = np.trace(self.P[rem], axis1=1, axis2=2) / 3.0
        d2 = np.sum((p[cand][:, None, :] - self.p[rem][None, :, :]) ** 2, axis=2)
        gate2 = self.config.gate_k**2 * (var_new[:, None] + var_rem[None, :])
        d2 = np.where(d2 <= gate2, d2, np.inf)
        j = np.argmin(d2, axis=1)
        hit = np.isfinite(d2[np.arange(cand.size), j])
        if not np.any(hit):
            return new
        ci, rj = cand[hit], rem[j[hit]]
        _, first = np.unique(rj, return_index=True)  # one new landmark per remembered point
        ci, rj = ci[first], rj[first]
        # information-form fusion of the two Gaussian estimates of the same static point
        I_old, I_new = np.linalg.inv(self.P[rj]), np.linalg.inv(P[ci])
        P_f = np.linalg.inv(I_old + I_new)
        P_f = 0.5 * (P_f + np.swapaxes(P_f, 1, 2))
        p_f = np.einsum("nij,nj->ni", P_f, np.einsum("nij,nj->ni", I_old, self.p[rj]) + np.einsum("nij,nj->ni", I_new, p[ci]))
        self.keys[rj], self.p[rj], self.P[rj], self.t_seen[rj] = keys[ci], p_f, P_f, t
        self.live[rj] = np.isin(keys[ci], live)
        self.o[rj] += 1
        new = new.copy()
        new[ci] = False
        self.merged += int(ci.size)
        return new

    def forget(self, keys) -> int:
        """Remove the points of these landmarks (retired by the estimator: diverged, not static)."""
        if _jit.ENABLED:
            drop = _rows_of_k(self.keys, np.asarray(keys, np.int64).reshape(-1))
            n = int(drop.size)
            if n:
                self.evicted["retired"] += n
                mask = np.ones(len(self.keys), bool)
                mask[drop] = False
                self._keep(mask)
            return n
        held, rows = self._rows(keys)
        if not np.any(held):
            return 0
        mask = np.ones(len(self.keys), bool)
        mask[rows[held]] = False
        n = int(np.count_nonzero(~mask))
        self.evicted["retired"] += n
        self._keep(mask)
        return n

    # -- 3. re-observation -------------------------------------------------------------------------
    def _drift(self, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = self.config
        s_pos = np.minimum(c.position_drift_mps * dt, c.position_drift_max_m)
        s_head = math.radians(c.heading_drift_deg_s) * dt
        return s_pos, s_head

    def check_view(self, t: float, R_world_cam: np.ndarray, p_world_cam: np.ndarray, fx: float, fy: float, cx: float,
                   cy: float, width: int, height: int, live_uv: np.ndarray, live_depth: np.ndarray,
                   live_sigma: np.ndarray, live_keys=None) -> ViewCheck:
        """Compare remembered points predicted in view with the live converged landmarks
        (``live_uv`` (L, 2) pixels in this frame — pinhole, undistorted —, ``live_depth`` (L,) depth
        along the optical axis, ``live_sigma`` (L,) its σ) and update ``o`` / ``u`` (module doc).

        A remembered point found again by a live landmark that has its own point in the map
        (``live_keys``) is absorbed by it: the live point stands for that surface patch from now on
        (its estimate is the newer, nearer one) and inherits the usage count ``o`` + 1; otherwise
        the remembered point's ``o`` grows and its age restarts."""
        c = self.config
        lk = np.zeros(0, np.int64) if live_keys is None else np.asarray(live_keys, np.int64).reshape(-1)
        if _jit.ENABLED and (live_keys is None or lk.size == np.size(live_uv) // 2):
            predicted, found, missed, absorbed = _check_view_k(
                self.keys, self.p, self.P, self.t_seen, self.o, self.u, self.live, np.asarray(R_world_cam, float),
                np.asarray(p_world_cam, float).reshape(3), float(fx), float(fy), float(cx), float(cy), float(width), float(height),
                np.asarray(live_uv, float).reshape(-1, 2), np.asarray(live_depth, float).reshape(-1),
                np.asarray(live_sigma, float).reshape(-1), lk, live_keys is not None, float(t), c.image_margin_px,
                c.reobserve_radius_px**2, c.gate_k, c.position_drift_mps, c.position_drift_max_m)
            if absorbed.size:
                self.absorbed += int(absorbed.size)
                keep = np.ones(len(self.keys), bool)
                keep[absorbed] = False
                self._keep(keep)
            return ViewCheck(predicted=int(predicted), found=int(found), missed=int(missed))
        rem = np.flatnonzero(~self.live)
        if rem.size == 0:
            return ViewCheck()
        R = np.asarray(R_world_cam, float)
        p_cam = (self.p[rem] - np.asarray(p_world_cam, float)) @ R
        z = p_cam[:, 2]
        front = z > 0.1
        uv = np.full((rem.size, 2), np.nan)
        uv[front] = np.stack([fx * p_cam[front, 0] / z[front] + cx, fy * p_cam[front, 1] / z[front] + cy], 1)
        mg = c.image_margin_px
        with np.errstate(invalid="ignore"):
            inside = front & (uv[:, 0] >= mg) & (uv[:, 0] <= width - 1 - mg) & (uv[:, 1] >= mg) & (uv[:, 1] <= height - 1 - mg)
        idx = np.flatnonzero(inside)
        if idx.size == 0:
            return ViewCheck()
        luv = np.asarray(live_uv, float).reshape(-1, 2)
        if len(luv) == 0:
            return ViewCheck(predicted=int(idx.size))
        rows = rem[idx]
        # σ of the remembered depth: its covariance along the optical axis plus the drift since seen
        a = R[:, 2]
        s_pos, _ = self._drift(t - self.t_seen[rows])
        s_map2 = np.einsum("i,nij,j->n", a, self.P[rows], a) + s_pos**2
        d2 = np.sum((uv[idx][:, None, :] - luv[None, :, :]) ** 2, axis=2)  # (K, L)
        near = d2 <= c.reobserve_radius_px**2
        dz = np.asarray(live_depth, float)[None, :] - z[idx][:, None]
        gate = c.gate_k * np.sqrt(s_map2[:, None] + np.asarray(live_sigma, float)[None, :] ** 2)
        agree = near & (np.abs(dz) <= gate)
        beyond = near & (dz > gate)
        found = np.any(agree, axis=1)
        missed = ~found & np.any(beyond, axis=1)
        self.u[rows[missed]] += 1
        n_found = int(np.count_nonzero(found))
        absorbed = np.zeros(len(self.keys), bool)
        if n_found and live_keys is not None:
            best = np.argmin(np.where(agree, d2, np.inf), axis=1)[found]  # nearest agreeing live pixel
            held, lrows = self._rows(np.asarray(live_keys, np.int64).reshape(-1)[best])
            fr = rows[found]
            np.add.at(self.o, lrows[held], self.o[fr[held]] + 1)
            absorbed[fr[held]] = True
            found_rows = fr[~held]
        else:
            found_rows = rows[found]
        self.o[found_rows] += 1
        self.t_seen[found_rows] = t
        if np.any(absorbed):
            self.absorbed += int(np.count_nonzero(absorbed))
            self._keep(~absorbed)
        return ViewCheck(predicted=int(idx.size), found=n_found, missed=int(np.count_nonzero(missed)))

    # -- 4. retention ------------------------------------------------------------------------------
    def prune(self, t: float, p_world_vehicle: np.ndarray) -> dict[str, int]:
        """Drop points by score, radius and age, then evict down to the cap (module doc)."""
        c = self.config
        out = {"score": 0, "radius": 0, "age": 0, "cap": 0}
        if len(self.keys) == 0:
            return out
        if _jit.ENABLED:
            keep, n_score, n_far, n_old = _prune_k(self.o, self.u, self.p, self.t_seen, np.asarray(p_world_vehicle, float).reshape(3),
                                                   float(t), c.min_score, c.radius_m, c.max_age_s)
            out["score"], out["radius"], out["age"] = int(n_score), int(n_far), int(n_old)
            if len(self.keys) - out["score"] - out["radius"] - out["age"] > c.max_landmarks:  # rare: the reference's cap
                score = self.score
                kept = np.flatnonzero(keep)
                order = np.lexsort((self.t_seen[kept], score[kept]))
                drop = kept[order[: len(kept) - c.max_landmarks]]
                keep[drop] = False
                out["cap"] = int(drop.size)
            for k, v in out.items():
                self.evicted[k] += v
            if not keep.all():
                self._keep(keep)
            return out
        score = self.score
        dist = np.linalg.norm(self.p - np.asarray(p_world_vehicle, float).reshape(3), axis=1)
        bad_score = score < c.min_score
        far = ~bad_score & (dist > c.radius_m)
        old = ~bad_score & ~far & ((t - self.t_seen) > c.max_age_s)
        out["score"], out["radius"], out["age"] = (int(np.count_nonzero(a)) for a in (bad_score, far, old))
        keep = ~(bad_score | far | old)
        if np.count_nonzero(keep) > c.max_landmarks:
            kept = np.flatnonzero(keep)
            # lowest score first, then the longest unseen; live points last among equals
            order = np.lexsort((self.t_seen[kept], score[kept]))
            drop = kept[order[: len(kept) - c.max_landmarks]]
            keep[drop] = False
            out["cap"] = int(drop.size)
        for k, v in out.items():
            self.evicted[k] += v
        if not np.all(keep):
            self._keep(keep)
        return out

    # -- 5. remembered points out --------------------------------------------------------------------
    def support(self, rows: np.ndarray, p_world_vehicle=None) -> np.ndarray:
        """(len(rows),) number of map points (the point itself included) within the support radius:
        ``support_radius_m``, or ``support_radius_rel`` × the point's distance from
        ``p_world_vehicle`` when that is larger (given)."""
        if rows.size == 0:
            return np.zeros(0, np.int64)
        c = self.config
        if _jit.ENABLED:
            pv = np.zeros(3) if p_world_vehicle is None else np.asarray(p_world_vehicle, float).reshape(3)
            rel = c.support_radius_rel if p_world_vehicle is not None else 0.0
            return _support_k(self.p, np.asarray(rows, np.int64), pv, c.support_radius_m, rel)
        radius = np.full(rows.size, c.support_radius_m)
        if p_world_vehicle is not None and c.support_radius_rel > 0:
            dist = np.linalg.norm(self.p[rows] - np.asarray(p_world_vehicle, float).reshape(3), axis=1)
            radius = np.maximum(radius, c.support_radius_rel * dist)
        q = self.p[rows].astype(np.float32)
        P = self.p.astype(np.float32)
        d2 = np.sum(q * q, 1)[:, None] + np.sum(P * P, 1)[None, :] - 2.0 * (q @ P.T)
        return np.count_nonzero(d2 <= (radius**2).astype(np.float32)[:, None], axis=1)

    def remembered(self, t: float, p_world_vehicle: np.ndarray) -> Remembered:
        """Points whose landmark is no longer live, with σ relative to the vehicle (module doc).

        Only points with ``min_support`` map points within ``support_radius_m`` are returned: a real
        surface leaves several landmarks, a lone point is most likely a track that converged on a
        mismatch (an occluding edge, a repeated texture), which memory would otherwise keep for
        ``max_age_s``."""
        pv = np.asarray(p_world_vehicle, float).reshape(3)
        if _jit.ENABLED:
            c = self.config
            rows, s_r, s_t, dt = _remembered_k(self.p, self.P, self.t_seen, self.live, pv, float(t), c.min_support, c.support_radius_m,
                                               c.support_radius_rel, c.position_drift_mps, c.position_drift_max_m,
                                               math.radians(c.heading_drift_deg_s))
            return Remembered(self.keys[rows], self.p[rows], s_r, s_t, dt)
        rows = np.flatnonzero(~self.live)
        if self.config.min_support > 1 and rows.size:
            rows = rows[self.support(rows, pv) >= self.config.min_support]
        d = self.p[rows] - pv
        r = np.linalg.norm(d, axis=1)
        u = d / np.maximum(r, 1e-9)[:, None]
        P = self.P[rows]
        uPu = np.einsum("ni,nij,nj->n", u, P, u)
        dt = np.maximum(t - self.t_seen[rows], 0.0)
        s_pos, s_head = self._drift(dt)
        r_h = np.hypot(d[:, 0], d[:, 1])
        s_r = np.sqrt(np.maximum(uPu, 0.0) + s_pos**2)
        s_t = np.sqrt(np.maximum(np.trace(P, axis1=1, axis2=2) - uPu, 0.0) / 2.0 + s_pos**2 + (r_h * s_head) ** 2)
        return Remembered(self.keys[rows], self.p[rows].copy(), s_r, s_t, dt)
# ---------------------------------------------------------------------- compiled kernels ---------
# Each step of the map (docs/derivations/obstacle_map.md) as one loop over landmarks, used when
# :data:`companion.core.jit.ENABLED` (the methods and functions above dispatch; their numpy bodies are
# the reference).  The kernels evaluate the reference's expressions in the same order, so the
# decisions (entry, merge, found, seen through, retention, support) are the reference's: the support
# test even repeats its float32 expansion |q|² + |p|² − 2 q·p, rounded as BLAS rounds it.  Where the
# reference multiplies through BLAS or LAPACK the numbers agree to rounding: the camera frame and the depth σ (a fixed order of
# summation here), the fused covariance of a merge (Gauss–Jordan here, LAPACK there: relative
# differences ~ cond · 1e-16) and positive definiteness (the pivots of a Cholesky factorization here,
# the smallest eigenvalue there: they can disagree only for a covariance singular to working precision).


@_jit.njit
def _consistent_for_entry_k(nis, converged, ratio, min_count):
    """:func:`consistent_for_entry_reference`: the same median of the converged finite NIS."""
    n = nis.size
    ok = np.ones(n, np.bool_)
    ref = np.empty(n)
    m = 0
    for i in range(n):
        if converged[i] and math.isfinite(nis[i]):
            ref[m] = nis[i]
            m += 1
    if ratio <= 0 or m < min_count:
        return ok
    lim = ratio * np.median(ref[:m])
    for i in range(n):
        ok[i] = nis[i] <= lim
    return ok


@_jit.njit
def _landmark_covariance_k(p, p_cam, range_sigma, bearing_sigma):
    """:func:`landmark_covariance_reference`: σ_r² u uᵀ + (r σ_b)² (I − u uᵀ) per landmark."""
    n = p.shape[0]
    P = np.empty((n, 3, 3))
    u = np.empty(3)
    for k in range(n):
        d0, d1, d2 = p[k, 0] - p_cam[0], p[k, 1] - p_cam[1], p[k, 2] - p_cam[2]
        r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        rs = max(r, 1e-9)
        u[0], u[1], u[2] = d0 / rs, d1 / rs, d2 / rs
        s_r2 = range_sigma[k] * range_sigma[k]
        s_t = r * bearing_sigma
        s_t2 = s_t * s_t
        for i in range(3):
            for j in range(3):
                uu = u[i] * u[j]
                P[k, i, j] = s_r2 * uu + s_t2 * ((1.0 if i == j else 0.0) - uu)
    return P


@_jit.njit
def _points_on_current_rays_k(out_ids, out_p, out_range, track_ids, rays_cam, R_world_cam, p_world_cam):
    """:func:`points_on_current_rays_reference`: landmarks seen now at their range along the current ray."""
    p = out_p.copy()
    nt = track_ids.size
    if out_ids.size == 0 or nt == 0:
        return p
    pos = np.searchsorted(track_ids, out_ids)
    for k in range(out_ids.size):
        j = min(pos[k], nt - 1)
        if track_ids[j] != out_ids[k]:
            continue
        for i in range(3):
            d = rays_cam[j, 0] * R_world_cam[i, 0] + rays_cam[j, 1] * R_world_cam[i, 1] + rays_cam[j, 2] * R_world_cam[i, 2]
            p[k, i] = p_world_cam[i] + d * out_range[k]
    return p


@_jit.njit
def _entry_checks_k(p, P):
    """The checks of :meth:`ObstacleMap.observe`: finite, symmetric (1e-9 relative) and positive definite (the pivots of
    the Cholesky factorization of (P + Pᵀ)/2 are positive ⇔ its eigenvalues are)."""
    m = p.shape[0]
    ok = np.zeros(m, np.bool_)
    n_bad = 0
    n_not_pd = 0
    A = np.empty((3, 3))
    for k in range(m):
        finite = True
        for i in range(3):
            finite = finite and math.isfinite(p[k, i])
            for j in range(3):
                finite = finite and math.isfinite(P[k, i, j])
        if not finite:
            n_bad += 1
            continue
        sym = True
        for i in range(3):
            for j in range(3):
                sym = sym and abs(P[k, i, j] - P[k, j, i]) <= 1e-9 * (1.0 + abs(P[k, i, j]))
                A[i, j] = 0.5 * (P[k, i, j] + P[k, j, i])
        d0 = A[0, 0]
        pd = d0 > 0
        if pd:
            l10, l20 = A[1, 0] / d0, A[2, 0] / d0
            d1 = A[1, 1] - l10 * A[1, 0]
            pd = d1 > 0
            if pd:
                l21 = (A[2, 1] - l20 * A[1, 0]) / d1
                d2 = A[2, 2] - l20 * A[2, 0] - l21 * l21 * d1
                pd = d2 > 0
        if sym and pd:
            ok[k] = True
        else:
            n_not_pd += 1
    return ok, n_bad, n_not_pd


@_jit.njit
def _inv3(A):
    """Inverse of a 3×3 matrix by Gauss–Jordan elimination with partial pivoting (as LAPACK's LU)."""
    M = A.copy()
    X = np.eye(3)
    for c in range(3):
        piv = c
        for r in range(c + 1, 3):
            if abs(M[r, c]) > abs(M[piv, c]):
                piv = r
        if piv != c:
            for j in range(3):
                M[c, j], M[piv, j] = M[piv, j], M[c, j]
                X[c, j], X[piv, j] = X[piv, j], X[c, j]
        for r in range(3):
            if r == c:
                continue
            f = M[r, c] / M[c, c]
            for j in range(3):
                M[r, j] -= f * M[c, j]
                X[r, j] -= f * X[c, j]
    for r in range(3):
        for j in range(3):
            X[r, j] /= M[r, r]
    return X


@_jit.njit
def _merge_pairs_k(p, P, cand, map_p, map_P, rem, gate_k2):
    """The pairs of :meth:`ObstacleMap._merge`: each new landmark ``cand`` nearest a remembered row
    ``rem`` within gate_k² (var_new + var_rem) (var = tr P / 3); one new landmark per remembered
    point (the first), pairs in ascending row; the information-form fusion of each pair."""
    nc, nr = cand.size, rem.size
    var_rem = np.empty(nr)
    for r in range(nr):
        q = rem[r]
        var_rem[r] = (map_P[q, 0, 0] + map_P[q, 1, 1] + map_P[q, 2, 2]) / 3.0
    taken = np.full(map_p.shape[0], -1, np.int64)  # remembered row -> first new landmark that landed on it
    for c in range(nc):
        i = cand[c]
        var_new = (P[i, 0, 0] + P[i, 1, 1] + P[i, 2, 2]) / 3.0
        best, best_d2 = -1, np.inf
        for r in range(nr):
            q = rem[r]
            dx, dy, dz = p[i, 0] - map_p[q, 0], p[i, 1] - map_p[q, 1], p[i, 2] - map_p[q, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 <= gate_k2 * (var_new + var_rem[r]) and d2 < best_d2:
                best, best_d2 = q, d2
        if best >= 0 and taken[best] < 0:
            taken[best] = i
    rj = np.flatnonzero(taken >= 0)
    ci = taken[rj]
    n = rj.size
    p_f = np.empty((n, 3))
    P_f = np.empty((n, 3, 3))
    for k in range(n):
        I_old = _inv3(map_P[rj[k]])
        I_new = _inv3(P[ci[k]])
        Pk = _inv3(I_old + I_new)
        for a in range(3):
            for b in range(3):
                P_f[k, a, b] = 0.5 * (Pk[a, b] + Pk[b, a])
        info = np.empty(3)
        for a in range(3):
            info[a] = (I_old[a, 0] * map_p[rj[k], 0] + I_old[a, 1] * map_p[rj[k], 1] + I_old[a, 2] * map_p[rj[k], 2]) + (
                I_new[a, 0] * p[ci[k], 0] + I_new[a, 1] * p[ci[k], 1] + I_new[a, 2] * p[ci[k], 2])
        for a in range(3):
            p_f[k, a] = P_f[k, a, 0] * info[0] + P_f[k, a, 1] * info[1] + P_f[k, a, 2] * info[2]
    return ci, rj, p_f, P_f


@_jit.njit
def _prune_k(o, u, p, t_seen, pv, t, min_score, radius, max_age):
    """:meth:`ObstacleMap.prune`: kept points and the counts dropped by score, radius and age (before the cap)."""
    n = o.size
    keep = np.ones(n, np.bool_)
    n_score = n_far = n_old = 0
    for i in range(n):
        oi = float(o[i])
        score = (oi - 0.5 * float(u[i])) / (1.0 + oi)
        if score < min_score:
            n_score += 1
            keep[i] = False
            continue
        d0, d1, d2 = p[i, 0] - pv[0], p[i, 1] - pv[1], p[i, 2] - pv[2]
        if math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > radius:
            n_far += 1
            keep[i] = False
        elif t - t_seen[i] > max_age:
            n_old += 1
            keep[i] = False
    return keep, n_score, n_far, n_old


@_jit.njit
def _support_k(p, rows, pv, radius_m, rel, stop_at=0):
    """:meth:`ObstacleMap.support`: map points within the support radius of each row, by the
    reference's own float32 expansion E = |q|² + |p|² − 2 q·p, rounded as numpy rounds it: |q|² summed
    in order, q·p as BLAS's sgemm accumulates it on FMA hardware (x86-64 with FMA, ARMv8), a fused
    multiply–add chain q2·p2 + (q1·p1 + q0·p0), each step rounded once to float32 (products of
    float32 are exact in float64; a double rounding could differ only on an exact float32 tie).

    Only the points within a slab along the axis of largest spread are tested: E is within
    9 u (|q|² + |p|²) of the exact squared distance of the float32 points (u = 2⁻²⁴: two or three
    roundings in each of |q|², |p|², q·p, their sum and difference), so a point farther along that
    axis than √(r² + 16 u (|q|² + max |p|²)) cannot pass; the counts are those of testing every pair.
    ``stop_at`` > 0: a count stops there (enough to decide ``count >= stop_at``)."""
    n = p.shape[0]
    X, Y, Z = np.empty(n), np.empty(n), np.empty(n)  # float32 coordinates, held exactly in float64
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    pp_max = 0.0
    for j in range(n):
        X[j], Y[j], Z[j] = np.float32(p[j, 0]), np.float32(p[j, 1]), np.float32(p[j, 2])
        lo[0], hi[0] = min(lo[0], X[j]), max(hi[0], X[j])
        lo[1], hi[1] = min(lo[1], Y[j]), max(hi[1], Y[j])
        lo[2], hi[2] = min(lo[2], Z[j]), max(hi[2], Z[j])
        pp_max = max(pp_max, X[j] * X[j] + Y[j] * Y[j] + Z[j] * Z[j])
    axis = 0
    for a in range(1, 3):
        if hi[a] - lo[a] > hi[axis] - lo[axis]:
            axis = a
    key = X if axis == 0 else (Y if axis == 1 else Z)
    order = np.argsort(key)
    Xs, Ys, Zs, ks = X[order], Y[order], Z[order], key[order]
    at = np.empty(n, np.int64)  # position of each point in the sorted order
    for j in range(n):
        at[order[j]] = j
    pp = np.empty(n, np.float32)
    for j in range(n):
        x, y, z = np.float32(Xs[j]), np.float32(Ys[j]), np.float32(Zs[j])
        pp[j] = x * x + y * y + z * z
    two = np.float32(2.0)
    u = 2.0**-24
    count = np.zeros(rows.size, np.int64)
    for k in range(rows.size):
        i = rows[k]
        radius = radius_m
        if rel > 0:
            d0, d1, d2 = p[i, 0] - pv[0], p[i, 1] - pv[1], p[i, 2] - pv[2]
            radius = max(radius, rel * math.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
        lim = np.float32(radius * radius)
        q0, q1, q2 = X[i], Y[i], Z[i]
        f0, f1, f2 = np.float32(q0), np.float32(q1), np.float32(q2)
        qq = f0 * f0 + f1 * f1 + f2 * f2
        w = math.sqrt(float(lim) + 16.0 * u * (float(qq) + pp_max))
        j0 = np.searchsorted(ks, key[i] - w)
        j1 = np.searchsorted(ks, key[i] + w, side="right")
        c = 0
        a = at[i]  # the point itself (inside its slab): visit outwards from it, nearest along the axis first
        right, left = a, a - 1
        while right < j1 or left >= j0:
            if right < j1 and (left < j0 or right - a <= a - left):
                j = right
                right += 1
            else:
                j = left
                left -= 1
            dot = np.float32(q0 * Xs[j])
            dot = np.float32(q1 * Ys[j] + dot)
            dot = np.float32(q2 * Zs[j] + dot)
            if ((qq + pp[j]) - two * dot) <= lim:
                c += 1
                if c == stop_at:
                    break
        count[k] = c
    return count


@_jit.njit
def _sorted_order(a):
    """Indices sorting ``a`` (the identity when it is already non-decreasing, as the pipeline's keys are)."""
    for i in range(1, a.size):
        if a[i] < a[i - 1]:
            return np.argsort(a)
    return np.arange(a.size)


@_jit.njit
def _first_rows(map_keys, queries):
    """(len(queries),) the first row holding each query key, −1 if none: the rows
    :meth:`ObstacleMap._rows` finds (its stable order makes the first of equal keys win), found by
    one pass over the map with a binary search in the (sorted) queries."""
    m = queries.size
    rows = np.full(m, -1, np.int64)
    if m == 0:
        return rows
    order = _sorted_order(queries)
    sq = queries[order]
    for r in range(map_keys.size):
        key = map_keys[r]
        j = np.searchsorted(sq, key)
        while j < m and sq[j] == key:
            if rows[order[j]] < 0:
                rows[order[j]] = r
            j += 1
    return rows


@_jit.njit
def _contains(sorted_keys, key):
    j = np.searchsorted(sorted_keys, key)
    return j < sorted_keys.size and sorted_keys[j] == key


@_jit.njit
def _rows_of_k(map_keys, keys):
    """Rows (ascending, each once) holding any of ``keys`` (:meth:`ObstacleMap.forget`)."""
    hit = np.zeros(map_keys.size, np.bool_)
    for r in _first_rows(map_keys, keys):
        if r >= 0:
            hit[r] = True
    return np.flatnonzero(hit)


@_jit.njit
def _observe_k(map_keys, map_p, map_P, map_t, map_o, map_u, keys_in, p_in, P_in, live_keys, live_is_keys, t, gate_k2):
    """:meth:`ObstacleMap.observe` (docs/derivations/obstacle_map.md): refuse bad landmarks, mark the
    live rows, refresh the held ones, merge new ones into remembered points (fused), append the rest.
    Rows are updated in place (as the reference does); returns the map's arrays (new ones when points
    were appended), the refusal counts and the number merged."""
    ok, n_bad, n_not_pd = _entry_checks_k(p_in, P_in)
    sel = np.flatnonzero(ok)
    keys = keys_in[sel]
    p = p_in[sel]
    P = P_in[sel]
    if live_is_keys:
        live_keys = keys
    n, m = map_keys.size, keys.size
    live = np.zeros(n, np.bool_)
    for r in _first_rows(map_keys, live_keys):
        if r >= 0:
            live[r] = True
    sl = live_keys[_sorted_order(live_keys)]
    held = _first_rows(map_keys, keys)
    key_live = np.zeros(m, np.bool_)
    new = np.ones(m, np.bool_)
    for k in range(m):
        key_live[k] = _contains(sl, keys[k])  # np.isin(keys, live_keys)
        r = held[k]
        if r >= 0:
            new[k] = False
            for a in range(3):
                map_p[r, a] = p[k, a]
                for b in range(3):
                    map_P[r, a, b] = P[k, a, b]
            map_t[r] = t
    n_merged = 0
    rem = np.flatnonzero(~live)
    cand = np.flatnonzero(new)
    if rem.size and cand.size:
        ci, rj, p_f, P_f = _merge_pairs_k(p, P, cand, map_p, map_P, rem, gate_k2)
        for k in range(ci.size):
            r, c = rj[k], ci[k]
            map_keys[r] = keys[c]
            for a in range(3):
                map_p[r, a] = p_f[k, a]
                for b in range(3):
                    map_P[r, a, b] = P_f[k, a, b]
            map_t[r] = t
            live[r] = key_live[c]
            map_o[r] += 1
            new[c] = False
        n_merged = ci.size
    add = np.flatnonzero(new)
    if add.size == 0:
        return map_keys, map_p, map_P, map_t, map_o, map_u, live, n_bad, n_not_pd, n_merged
    N = n + add.size
    out_keys = np.empty(N, np.int64)
    out_p = np.empty((N, 3))
    out_P = np.empty((N, 3, 3))
    out_t = np.empty(N)
    out_o = np.zeros(N, np.int64)
    out_u = np.zeros(N, np.int64)
    out_live = np.empty(N, np.bool_)
    for i in range(n):
        out_keys[i], out_t[i], out_o[i], out_u[i], out_live[i] = map_keys[i], map_t[i], map_o[i], map_u[i], live[i]
        for a in range(3):
            out_p[i, a] = map_p[i, a]
            for b in range(3):
                out_P[i, a, b] = map_P[i, a, b]
    for q in range(add.size):
        k, i = add[q], n + q
        out_keys[i], out_t[i], out_live[i] = keys[k], t, key_live[k]
        for a in range(3):
            out_p[i, a] = p[k, a]
            for b in range(3):
                out_P[i, a, b] = P[k, a, b]
    return out_keys, out_p, out_P, out_t, out_o, out_u, out_live, n_bad, n_not_pd, n_merged


@_jit.njit
def _check_view_k(map_keys, p, P, t_seen, o, u, live, R, p_world_cam, fx, fy, cx, cy, width, height, luv, live_depth, live_sigma,
                  live_keys, has_live_keys, t, margin, radius2, gate_k, drift_mps, drift_max):
    """:meth:`ObstacleMap.check_view`: remembered points predicted in view (pinhole, inside the margin)
    are found again (a live pixel within the radius whose depth agrees within gate_k σ: o += 1, age
    restarts, or absorbed by that live point's own row) or seen through (not found, a live point
    beyond: u += 1).  Updates o, u, t_seen in place; returns (predicted, found, missed, absorbed rows)."""
    rem = np.flatnonzero(~live)
    nr, nl = rem.size, luv.shape[0]
    rows = np.empty(nr, np.int64)
    uq = np.empty(nr)
    vq = np.empty(nr)
    z = np.empty(nr)
    k = 0
    for q in range(nr):
        i = rem[q]
        d0, d1, d2 = p[i, 0] - p_world_cam[0], p[i, 1] - p_world_cam[1], p[i, 2] - p_world_cam[2]
        zc = d0 * R[0, 2] + d1 * R[1, 2] + d2 * R[2, 2]
        if not zc > 0.1:
            continue
        xc = d0 * R[0, 0] + d1 * R[1, 0] + d2 * R[2, 0]
        yc = d0 * R[0, 1] + d1 * R[1, 1] + d2 * R[2, 1]
        uu, vv = fx * xc / zc + cx, fy * yc / zc + cy
        if uu >= margin and uu <= width - 1 - margin and vv >= margin and vv <= height - 1 - margin:
            rows[k], uq[k], vq[k], z[k] = i, uu, vv, zc
            k += 1
    none = np.zeros(0, np.int64)
    if k == 0 or nl == 0:
        return k, 0, 0, none
    found = np.zeros(k, np.bool_)
    best = np.full(k, -1, np.int64)
    n_missed = 0
    for q in range(k):
        i = rows[q]
        s_pos = min(drift_mps * (t - t_seen[i]), drift_max)
        s_map2 = 0.0
        for a in range(3):
            s_map2 += R[a, 2] * (P[i, a, 0] * R[0, 2] + P[i, a, 1] * R[1, 2] + P[i, a, 2] * R[2, 2])
        s_map2 += s_pos * s_pos
        best_d2 = np.inf
        beyond = False
        for l in range(nl):
            du, dv = uq[q] - luv[l, 0], vq[q] - luv[l, 1]
            d2 = du * du + dv * dv
            if not d2 <= radius2:
                continue
            dz = live_depth[l] - z[q]
            gate = gate_k * math.sqrt(s_map2 + live_sigma[l] * live_sigma[l])
            if abs(dz) <= gate:
                found[q] = True
                if d2 < best_d2:
                    best_d2, best[q] = d2, l
            elif dz > gate:
                beyond = True
        if beyond and not found[q]:
            u[i] += 1
            n_missed += 1
    n_found = 0
    for q in range(k):
        n_found += found[q]
    absorbed = np.zeros(map_keys.size, np.bool_)
    into = np.full(k, -1, np.int64)  # the live point's own row that absorbs a found point
    if n_found and has_live_keys:
        fq = np.flatnonzero(found)
        target = _first_rows(map_keys, live_keys[best[fq]])
        gain = np.zeros(k, np.int64)
        for f in range(fq.size):  # o of the absorbed points read before any is added (np.add.at)
            q = fq[f]
            into[q] = target[f]
            gain[q] = o[rows[q]] + 1
        for q in range(k):
            if into[q] >= 0:
                o[into[q]] += gain[q]
                absorbed[rows[q]] = True
    for q in range(k):
        if found[q] and into[q] < 0:
            o[rows[q]] += 1
            t_seen[rows[q]] = t
    return k, n_found, n_missed, np.flatnonzero(absorbed)


@_jit.njit
def _remembered_k(p, P, t_seen, live, pv, t, min_support, radius_m, rel, drift_mps, drift_max, heading_rad_s):
    """:meth:`ObstacleMap.remembered`: the rows not live with ``min_support`` map points around them,
    σ_r = √(uᵀPu + σ_drift²), σ_t = √((tr P − uᵀPu)/2 + σ_drift² + (r_h σ_ψ)²) and the time since seen."""
    rows = np.flatnonzero(~live)
    if min_support > 1 and rows.size:
        rows = rows[_support_k(p, rows, pv, radius_m, rel, min_support) >= min_support]
    n = rows.size
    s_r = np.empty(n)
    s_t = np.empty(n)
    dt = np.empty(n)
    for k in range(n):
        i = rows[k]
        d0, d1, d2 = p[i, 0] - pv[0], p[i, 1] - pv[1], p[i, 2] - pv[2]
        r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        rs = max(r, 1e-9)
        u0, u1, u2 = d0 / rs, d1 / rs, d2 / rs
        uPu = (u0 * (P[i, 0, 0] * u0 + P[i, 0, 1] * u1 + P[i, 0, 2] * u2) + u1 * (P[i, 1, 0] * u0 + P[i, 1, 1] * u1 + P[i, 1, 2] * u2)
               + u2 * (P[i, 2, 0] * u0 + P[i, 2, 1] * u1 + P[i, 2, 2] * u2))
        dt[k] = max(t - t_seen[i], 0.0)
        s_pos = min(drift_mps * dt[k], drift_max)
        s_head = heading_rad_s * dt[k]
        r_h = np.hypot(d0, d1)
        s_r[k] = math.sqrt(max(uPu, 0.0) + s_pos * s_pos)
        tr = P[i, 0, 0] + P[i, 1, 1] + P[i, 2, 2]
        s_t[k] = math.sqrt(max(tr - uPu, 0.0) / 2.0 + s_pos * s_pos + (r_h * s_head) * (r_h * s_head))
    return rows, s_r, s_t, dt


@_jit.njit
def _map_entries_k(ids, key_base, converged, valid, range_sigma, range_m, p_world, mean_nis, has_nis, max_rel_sigma, ratio,
                   p_world_cam, bearing_sigma):
    """:func:`map_entries_reference`: keys, the mask that may enter, the keys to forget and the entries' covariances."""
    n = ids.size
    keys = np.empty(n, np.int64)
    good = np.empty(n, np.bool_)
    for i in range(n):
        keys[i] = ids[i] + key_base
        good[i] = converged[i] and valid[i] and range_sigma[i] <= max_rel_sigma * range_m[i]
    forget = np.zeros(0, np.int64)
    if ratio > 0 and has_nis:
        ok = _consistent_for_entry_k(mean_nis, converged & valid, ratio, 10)
        bad = good & ~ok
        forget = keys[bad]
        good &= ~bad
    sel = np.flatnonzero(good)
    P = _landmark_covariance_k(p_world[sel], p_world_cam, range_sigma[sel], bearing_sigma)
    return keys, good, forget, P


@_jit.njit
def _live_view_k(ids, track_ids, track_uv, keys, good, p_world, range_sigma, range_m, R, p_world_cam, fx, fy, cx, cy, pinhole):
    """:func:`live_view_reference`: the track rows of the live landmarks with a point in the map, their
    pinhole pixels (when ``pinhole``: the camera has no distortion; else the caller undistorts the
    rows), depth along the optical axis, its σ and their keys."""
    n, nt = ids.size, track_ids.size
    rows = np.empty(n, np.int64)
    src = np.empty(n, np.int64)
    m = 0
    if n and nt:
        pos = np.searchsorted(track_ids, ids)
        for k in range(n):
            j = min(pos[k], nt - 1)
            if track_ids[j] == ids[k] and good[k]:
                rows[m], src[m] = j, k
                m += 1
    rows = rows[:m]
    uv = np.empty((m, 2))
    depth = np.empty(m)
    sig = np.empty(m)
    lkeys = np.empty(m, np.int64)
    for q in range(m):
        k, j = src[q], rows[q]
        depth[q] = (p_world[k, 0] - p_world_cam[0]) * R[0, 2] + (p_world[k, 1] - p_world_cam[1]) * R[1, 2] + (
            p_world[k, 2] - p_world_cam[2]) * R[2, 2]
        sig[q] = range_sigma[k] * abs(depth[q]) / max(range_m[k], 1e-9)
        lkeys[q] = keys[k]
        if pinhole:  # CameraModel.undistort_to_pinhole without distortion: K (K⁻¹ uv)
            uv[q, 0] = fx * ((track_uv[j, 0] - cx) / fx) + cx
            uv[q, 1] = fy * ((track_uv[j, 1] - cy) / fy) + cy
    return rows, uv, depth, sig, lkeys


@_jit.register_warmup
def _warm_up() -> None:
    """Compile the map kernels on a tiny map: enter, merge, re-observe, absorb, prune, remember, forget."""
    from companion.core.camera import CameraConfig, CameraModel

    m = ObstacleMap(MapConfig(min_support=2, support_radius_rel=0.1))
    R_wc = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # camera looking north
    p_wc = np.zeros(3)
    p = np.array([[10.0, 0.0, 0.0], [10.0, 0.3, 0.0], [10.0, -0.3, 0.1]])
    ok = consistent_for_entry(np.array([1.0, 1.0, 2.0]), np.ones(3, bool), 10.0, min_count=1)
    P = landmark_covariance(p[ok], p_wc, np.full(3, 0.2), 0.002)
    m.observe(0.0, [1, 2, 3], p, P)
    e = map_entries(np.array([1, 2]), 0, np.ones(2, bool), np.ones(2, bool), np.full(2, 0.2), np.full(2, 10.0), p[:2], p_wc, 0.002,
                    MapConfig(max_entry_nis_ratio=5.0), np.ones(2))
    live_view(np.array([1, 2]), np.array([2]), np.array([[160.0, 120.0]]), e.keys, e.good, p[:2], np.full(2, 0.2), np.full(2, 10.0),
              R_wc, p_wc, CameraModel(CameraConfig.from_fov(320, 240, 60.0)))
    m.observe(0.1, [4, 5], p[:2] + 0.01, P[:2], live_keys=[4, 5])
    m.check_view(0.1, R_wc, p_wc, 300.0, 300.0, 160.0, 120.0, 320, 240, np.array([[160.0, 120.0]]), np.array([10.0]),
                 np.array([0.2]), live_keys=np.array([4]))
    m.prune(0.1, p_wc)
    m.remembered(0.2, p_wc)
    m.forget([5])
    points_on_current_rays(np.array([1, 4]), p[:2], np.array([10.0, 10.0]), np.array([4]), np.array([[0.0, 0.0, 1.0]]), R_wc, p_wc)
