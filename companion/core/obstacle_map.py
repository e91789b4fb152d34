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
``support_radius_rel`` × its distance) — or, counted apart (the larger count decides), within
``support_column_radius_m`` horizontally and ``support_column_half_height_m`` vertically: a thin mast
leaves its corners stacked one above another, farther apart than across a surface.

Retention (seed 003 §3.6, docs/derivations/obstacle_map.md)
-----------------------------------------------------------
Usage score s = (o − 0.5·u)/(1 + o), o = re-observations (a remembered point predicted in view
and found again: a live converged landmark within ``reobserve_radius_px`` of its predicted pixel
whose depth agrees within ``gate_k`` σ; or a newly converged landmark that lands within ``gate_k``
σ of it, which then takes the point over instead of adding another: fused with it when their
covariances agree, else replacing it), u = missed predictions (predicted in view, and a live
converged landmark near its pixel lies clearly *beyond* it: the camera sees through where the point
should be — it moved, or it was a mismatch).  No live landmark near the pixel is no evidence either
way (a texture-less patch, an unconverged track), and a live landmark clearly *nearer* is an
occluder; neither changes the counts.  A point leaves the map when s < ``min_score``, when it is
farther than ``radius_m`` from the vehicle, or older (since last observed) than ``max_age_s``; the
count is capped at ``max_landmarks``, lowest score evicted first (then the longest unseen).
Memory is bounded by the cap: every array is sized by the number of points held.

Layout: this module holds :class:`MapConfig`, :class:`ObstacleMap` (steps 2–5) and
:func:`world_to_body` (step 6); the functions that prepare the frame's landmarks for it
(:func:`points_on_current_rays`, :func:`map_entries` with :func:`landmark_covariance` and
:func:`consistent_for_entry`, :func:`live_view`) are in :mod:`companion.core.obstacle_map_landmarks`
(re-exported here), the compiled kernels in :mod:`companion.core.obstacle_map_kernels`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion.config import require, require_finite
from companion.core import jit as _jit
# the landmarks as the map takes them, re-exported: every public name stays importable from here
from companion.core.obstacle_map_landmarks import (  # noqa: F401
    MapEntries,
    consistent_for_entry,
    consistent_for_entry_reference,
    landmark_covariance,
    landmark_covariance_reference,
    live_view,
    live_view_reference,
    map_entries,
    map_entries_reference,
    points_on_current_rays,
    points_on_current_rays_reference,
)
from companion.core.obstacle_map_kernels import (_check_view_k, _column_support_k, _observe_k, _prune_k, _remembered_k, _rows_of_k,
                                                 _support_k)
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
    gate_k: float = 3.0  # depths agree when within gate_k combined σ (found); a live point beyond that is "seen through" (missed); a new landmark within it takes a remembered point over (fused only when Mahalanobis ≤ gate_k)
    image_margin_px: float = 4.0  # a remembered point is predicted in view only this far inside the image border, px
    min_support: int = 2  # a remembered point is published only with at least this many map points (itself included) within support_radius_m
    support_radius_m: float = 0.6  # neighbourhood of that support test, m (at least)
    support_radius_rel: float = 0.15  # ... or this fraction of the point's distance from the vehicle, if larger (corners are spaced in pixels, so neighbours lie farther apart far away)
    support_column_radius_m: float = 0.3  # ... or, counted apart, the map points within this horizontally and support_column_half_height_m vertically (a thin mast or pole leaves its corners stacked one above another, farther apart than on a surface), m; 0 = off
    support_column_half_height_m: float = 1.2  # vertical reach of that column, m
    support_seen_ratio: float = 0.0  # > 0: the relative radius scales with the larger of the point's distance now and its range when last entered, the latter at most this many times the distance now (corners are spaced in pixels where they were ranged: coming closer does not bring a surface's points closer together); 0 = the distance now alone

    def __post_init__(self) -> None:
        require(isinstance(self.enabled, bool), "enabled must be true or false")
        require(isinstance(self.max_landmarks, int) and not isinstance(self.max_landmarks, bool) and self.max_landmarks >= 1,
                f"max_landmarks must be an integer >= 1, got {self.max_landmarks!r}")
        require(isinstance(self.min_support, int) and not isinstance(self.min_support, bool) and self.min_support >= 1,
                f"min_support must be an integer >= 1, got {self.min_support!r}")
        for name in ("radius_m", "max_age_s", "max_rel_sigma", "reobserve_radius_px", "gate_k", "support_radius_m",
                     "support_column_half_height_m"):
            require_finite(name, getattr(self, name), positive=True)
        for name in ("position_drift_mps", "position_drift_max_m", "heading_drift_deg_s", "image_margin_px", "support_radius_rel",
                     "support_column_radius_m", "support_seen_ratio",
                     "max_entry_nis_ratio"):
            require_finite(name, getattr(self, name), nonnegative=True)
        require_finite("min_score", self.min_score)
        require(-2.0 < self.min_score < 1.0, f"min_score must be in (-2, 1) (s lies in (-inf, 1)), got {self.min_score}")


def usage_score(o: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Seed 003's usage score s = (o − 0.5·u)/(1 + o) (docs/derivations/obstacle_map.md)."""
    o = np.asarray(o, float)
    return (o - 0.5 * np.asarray(u, float)) / (1.0 + o)


def world_to_body(p_world: np.ndarray, R_world_body: np.ndarray, p_world_body: np.ndarray) -> np.ndarray:
    """Points (N, 3) from local NED into body FRD at the pose (R_world_body, p_world_body) (docs/derivations/frames.md)."""
    return (np.asarray(p_world, float).reshape(-1, 3) - np.asarray(p_world_body, float)) @ np.asarray(R_world_body, float)


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

    _fields = ("keys", "p", "P", "t_seen", "o", "u", "live", "r_seen")

    def __init__(self, config: MapConfig = MapConfig()):
        self.config = config
        self.keys = np.zeros(0, np.int64)
        self.p = np.zeros((0, 3))
        self.P = np.zeros((0, 3, 3))
        self.t_seen = np.zeros(0)
        self.o = np.zeros(0, np.int64)
        self.u = np.zeros(0, np.int64)
        self.live = np.zeros(0, bool)
        self.r_seen = np.zeros(0)  # range from the camera when each point was last entered, m (0: not known)
        self.rejected: dict[str, int] = {REJECT_NOT_FINITE: 0, REJECT_NOT_PD: 0}
        self.evicted: dict[str, int] = {"score": 0, "radius": 0, "age": 0, "cap": 0, "retired": 0}
        self.merged = 0  # new landmarks that landed on a remembered point (counted as its re-observation)
        self.superseded = 0  # ... of which disagreed with it (Mahalanobis beyond gate_k): the new estimate replaced the old, not fused
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
    def observe(self, t: float, keys, p_world, P_world, live_keys=None, p_world_cam=None) -> dict[str, int]:
        """Converged landmarks observed at ``t`` enter the map or refresh their point.

        ``keys`` (M,), ``p_world`` (M, 3), ``P_world`` (M, 3, 3).  ``live_keys``: every landmark the
        estimator still runs (default ``keys``); their map points are not *remembered* (the live
        estimate stands for them).  ``p_world_cam`` (3,): the camera position they were ranged from;
        each entered point keeps its range from it (``r_seen``, the support radius's scale,
        docs/derivations/obstacle_map.md § Support); without it the range is not known (0).  Landmarks
        with a non-finite point or a covariance that is not symmetric positive definite are refused
        and counted by reason (returned), never raised on.
        """
        if not math.isfinite(t):
            raise InputError("observe: t must be finite")
        keys = np.asarray(keys, np.int64).reshape(-1)
        m = len(keys)
        p = np.asarray(p_world, float).reshape(m, 3)
        P = np.asarray(P_world, float).reshape(m, 3, 3)
        n_old, r_old = len(self.keys), self.r_seen
        rej = self._observe_kernel(t, keys, p, P, live_keys) if _jit.ENABLED else self._observe_reference(t, keys, p, P, live_keys)
        # rows keep their places and new ones are appended (both paths); every entry accepted now
        # holds a row under its own key seen at t (refreshed, merged or new)
        r_seen = np.zeros(len(self.keys))
        r_seen[:n_old] = r_old[:n_old]
        if p_world_cam is not None and m:
            with np.errstate(invalid="ignore"):
                r_in = np.linalg.norm(p - np.asarray(p_world_cam, float).reshape(3), axis=1)
            held, rows = self._rows(keys)
            now = held & np.isfinite(r_in)
            now[now] = self.t_seen[rows[now]] == t
            r_seen[rows[now]] = r_in[now]
        self.r_seen = r_seen
        return rej

    def _observe_reference(self, t: float, keys: np.ndarray, p: np.ndarray, P: np.ndarray, live_keys) -> dict[str, int]:
        """:meth:`observe`'s numpy reference (checks, rows, merges and entries; not ``r_seen``)."""
        m = len(keys)
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
        (self.keys, self.p, self.P, self.t_seen, self.o, self.u, self.live, n_bad, n_not_pd, n_merged, n_sup) = _observe_k(
            self.keys, self.p, self.P, self.t_seen, self.o, self.u, keys, np.ascontiguousarray(p), np.ascontiguousarray(P), live,
            live_keys is None, float(t), self.config.gate_k**2, self.config.position_drift_mps, self.config.position_drift_max_m)
        rej = {REJECT_NOT_FINITE: int(n_bad), REJECT_NOT_PD: int(n_not_pd)}
        for k, v in rej.items():
            self.rejected[k] += v
        self.merged += int(n_merged)
        self.superseded += int(n_sup)
        return rej

    def _merge(self, t: float, keys, p, P, new, live) -> np.ndarray:
        """A new landmark that lands on a remembered point is that point observed again: the row
        takes the new key and its count ``o`` grows.  "Lands on": within ``gate_k`` combined σ,
        ‖d‖² ≤ k² (tr P_new + tr P'_rem)/3, P'_rem = P_rem + σ_drift² I (the remembered point's
        covariance grown by the position drift since it was last observed, § Drift), the nearest such
        point.  The row's point: the two estimates fused (information form) when they agree,
        dᵀ (P_new + P'_rem)⁻¹ d ≤ k²; otherwise the new estimate alone (two estimates that disagree
        across their narrow axes fuse where their long axes cross, far from both).  Keeps one point
        per surface patch, so the map's size follows the scene, not the time spent in it.  Returns the
        still-new mask (docs/derivations/obstacle_map.md, "Merging")."""
        rem = np.flatnonzero(~self.live)
        cand = np.flatnonzero(new)
        if rem.size == 0 or cand.size == 0:
            return new
        s_pos, _ = self._drift(np.maximum(t - self.t_seen[rem], 0.0))
        P_rem = self.P[rem] + (s_pos**2)[:, None, None] * np.eye(3)
        var_new = np.trace(P[cand], axis1=1, axis2=2) / 3.0
        var_rem = np.trace(P_rem, axis1=1, axis2=2) / 3.0
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
        P_old = P_rem[np.searchsorted(rem, rj)]  # rj ⊂ rem (sorted): their drift-grown covariances
        d = p[ci] - self.p[rj]
        m2 = np.einsum("ni,ni->n", d, np.linalg.solve(P_old + P[ci], d[..., None])[..., 0])
        fused = m2 <= self.config.gate_k**2
        # information-form fusion of the two Gaussian estimates of the same static point; where they
        # disagree, the new estimate supersedes the old
        p_f, P_f = p[ci].copy(), P[ci].copy()
        if np.any(fused):
            I_old, I_new = np.linalg.inv(P_old[fused]), np.linalg.inv(P[ci[fused]])
            Pf = np.linalg.inv(I_old + I_new)
            Pf = 0.5 * (Pf + np.swapaxes(Pf, 1, 2))
            p_f[fused] = np.einsum("nij,nj->ni", Pf, np.einsum("nij,nj->ni", I_old, self.p[rj[fused]])
                                   + np.einsum("nij,nj->ni", I_new, p[ci[fused]]))
            P_f[fused] = Pf
        self.keys[rj], self.p[rj], self.P[rj], self.t_seen[rj] = keys[ci], p_f, P_f, t
        self.live[rj] = np.isin(keys[ci], live)
        self.o[rj] += 1
        new = new.copy()
        new[ci] = False
        self.merged += int(ci.size)
        self.superseded += int(np.count_nonzero(~fused))
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
        ``p_world_vehicle`` when that is larger (given); with ``support_column_radius_m`` > 0, the
        larger of that count and the column's (points within the column radius horizontally and
        ``support_column_half_height_m`` vertically)."""
        if rows.size == 0:
            return np.zeros(0, np.int64)
        c = self.config
        if _jit.ENABLED:
            pv = np.zeros(3) if p_world_vehicle is None else np.asarray(p_world_vehicle, float).reshape(3)
            rel = c.support_radius_rel if p_world_vehicle is not None else 0.0
            rows = np.asarray(rows, np.int64)
            sup = _support_k(self.p, rows, pv, c.support_radius_m, rel, self.r_seen, c.support_seen_ratio)
            if c.support_column_radius_m > 0:
                sup = np.maximum(sup, _column_support_k(self.p, rows, c.support_column_radius_m, c.support_column_half_height_m))
            return sup
        sup = self._sphere_support(rows, p_world_vehicle)
        if c.support_column_radius_m > 0:
            q = self.p[rows]
            dx = self.p[None, :, 0] - q[:, None, 0]
            dy = self.p[None, :, 1] - q[:, None, 1]
            inside = (dx * dx + dy * dy <= c.support_column_radius_m * c.support_column_radius_m) & (
                np.abs(self.p[None, :, 2] - q[:, None, 2]) <= c.support_column_half_height_m)
            sup = np.maximum(sup, np.count_nonzero(inside, axis=1))  # the point itself is inside
        return sup

    def _sphere_support(self, rows: np.ndarray, p_world_vehicle=None) -> np.ndarray:
        """The sphere's count of :meth:`support` (numpy reference, float32 as the kernel)."""
        c = self.config
        radius = np.full(rows.size, c.support_radius_m)
        if p_world_vehicle is not None and c.support_radius_rel > 0:
            dist = np.linalg.norm(self.p[rows] - np.asarray(p_world_vehicle, float).reshape(3), axis=1)
            # the range the point was ranged from, bounded by support_seen_ratio × d (0: d alone)
            seen = np.minimum(self.r_seen[rows], c.support_seen_ratio * dist)
            radius = np.maximum(radius, c.support_radius_rel * np.maximum(dist, seen))
        q = self.p[rows].astype(np.float32)
        P = self.p.astype(np.float32)
        d2 = np.sum(q * q, 1)[:, None] + np.sum(P * P, 1)[None, :] - 2.0 * (q @ P.T)
        return np.count_nonzero(d2 <= (radius**2).astype(np.float32)[:, None], axis=1)

    def memory(self, t: float, published_keys=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every remembered point (landmark no longer live), for diagnostics: ``(p_world (M, 3), published (M,) bool:
        its key is in ``published_keys`` (those :meth:`remembered` handed on), age since last seen (M,) s)``."""
        rows = np.flatnonzero(~self.live)
        published = (np.isin(self.keys[rows], published_keys) if published_keys is not None
                     else np.zeros(len(rows), bool))
        return self.p[rows].copy(), published, np.maximum(t - self.t_seen[rows], 0.0)

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
                                               c.support_radius_rel, self.r_seen, c.support_seen_ratio, c.position_drift_mps,
                                               c.position_drift_max_m,
                                               math.radians(c.heading_drift_deg_s), c.support_column_radius_m,
                                               c.support_column_half_height_m)
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
