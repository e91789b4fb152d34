"""The estimator's landmarks as the local obstacle map takes them (docs/derivations/obstacle_map.md).

Pure functions of one frame's landmarks, used by the pipeline around :class:`companion.core.obstacle_map.ObstacleMap`
(the steps of that module's docstring):

* :func:`points_on_current_rays` — each landmark seen in this frame placed at its estimated range
  along the ray measured now (step 1);
* :func:`map_entries` — which landmarks enter the map and with what world covariance
  (:func:`landmark_covariance`, :func:`consistent_for_entry`; step 2);
* :func:`live_view` — the live landmarks that :meth:`~companion.core.obstacle_map.ObstacleMap.check_view`
  compares the remembered points with (step 3).

Each is a compiled kernel of :mod:`companion.core.obstacle_map_kernels` when
:data:`companion.core.jit.ENABLED`, and ``<name>_reference`` is its pure-numpy reference.
:mod:`companion.core.obstacle_map` re-exports every public name defined here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from companion.core import jit as _jit
from companion.core.obstacle_map_kernels import (
    _consistent_for_entry_k,
    _landmark_covariance_k,
    _live_view_k,
    _map_entries_k,
    _points_on_current_rays_k,
)

if TYPE_CHECKING:  # only an annotation here; the map module imports this one
    from companion.core.obstacle_map import MapConfig


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
