"""Obstacles of the truth: every finite truth cell as a world point, linked into obstacles by
position (:func:`group_obstacles`) and named after the world's solids (:func:`name_obstacles`,
:func:`world_namer`).  Definitions (``Obstacles and time to the first valid range``): :mod:`flightsim.score`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from flightsim.score.config import SECTOR_DEG, ScoreConfig
from flightsim.score.inputs import SectorTruth


# ---------------------------------------------------------------------- obstacles --------------
def truth_points(truth: SectorTruth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World NE points of every finite truth cell: ``(frame, sector, ne (P, 2))``."""
    f, s = np.nonzero(np.isfinite(truth.sector_m))
    T = truth.sector_m[f, s]
    b = truth.yaw[f] + np.radians(s * SECTOR_DEG)
    ne = truth.p_ned[f, :2] + T[:, None] * np.stack([np.cos(b), np.sin(b)], 1)
    return f, s, ne


def _connected_components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Labels (min index of each component) of an undirected graph, by vectorized label propagation."""
    lab = np.arange(n)
    if a.size == 0:
        return lab
    while True:
        old = lab.copy()
        m = np.minimum(lab[a], lab[b])
        np.minimum.at(lab, a, m)
        np.minimum.at(lab, b, m)
        lab = lab[lab]  # pointer jumping
        if np.array_equal(lab, old):
            return lab


def group_obstacles(truth: SectorTruth, config: ScoreConfig = ScoreConfig(), *, quantum_m: float = 0.25,
                    chunk: int = 1024) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Obstacle id of every truth cell (see the module docstring).

    Returns ``labels`` (F, 72) int (−1 where the truth is not finite), ``centroids`` (K, 2) world
    NE, and ``points`` (per obstacle, its de-duplicated world NE points).  Ids are ordered by the
    first frame in which the obstacle appears.
    """
    f, s, ne = truth_points(truth)
    labels = np.full(truth.sector_m.shape, -1, np.int64)
    if f.size == 0:
        return labels, np.zeros((0, 2)), []
    T = truth.sector_m[f, s]
    key = np.round(ne / quantum_m).astype(np.int64)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    pts = uniq * quantum_m
    radius = np.zeros(len(uniq))
    np.maximum.at(radius, inv, np.maximum(config.obstacle_link_m, config.obstacle_link_rel * T))
    ea, eb = [], []
    n = len(pts)
    for i0 in range(0, n, chunk):  # pairwise distances in row blocks (bounded memory)
        blk = pts[i0:i0 + chunk]
        d = np.hypot(blk[:, None, 0] - pts[None, :, 0], blk[:, None, 1] - pts[None, :, 1])
        close = d <= np.maximum(radius[i0:i0 + chunk, None], radius[None, :]) + 1e-9
        ii, jj = np.nonzero(close)
        keep = jj > ii + i0
        ea.append(ii[keep] + i0)
        eb.append(jj[keep])
    comp = _connected_components(n, np.concatenate(ea), np.concatenate(eb))
    cell_comp = comp[inv]
    # order components by first appearance (frame, then sector)
    order = np.lexsort((s, f))
    first_seen: dict[int, int] = {}
    for c in cell_comp[order]:
        if int(c) not in first_seen:
            first_seen[int(c)] = len(first_seen)
    remap = np.full(n, -1, np.int64)
    for c, k in first_seen.items():
        remap[c] = k
    ids = remap[cell_comp]
    labels[f, s] = ids
    k = len(first_seen)
    uid = remap[comp]
    centroids = np.array([pts[uid == i].mean(axis=0) for i in range(k)]).reshape(-1, 2)
    points = [pts[uid == i] for i in range(k)]
    return labels, centroids, points


def name_obstacles(centroids: np.ndarray, points: list[np.ndarray],
                   namer: Callable[[np.ndarray], list] | None, max_points: int = 64) -> list[str]:
    """Names of the grouped obstacles: the namer's majority over (up to ``max_points`` of) each
    group's points, else ``obstacle N`` with its centroid; repeated names get ``#2``, ``#3``…"""
    names = []
    for i, (c, p) in enumerate(zip(centroids, points)):
        name = None
        if namer is not None and len(p):
            sel = p[np.linspace(0, len(p) - 1, min(len(p), max_points)).astype(int)]
            votes = [v for v in namer(sel) if v]
            if votes:
                vals, cnt = np.unique(np.array(votes, dtype=object).astype(str), return_counts=True)
                name = str(vals[np.argmax(cnt)])
        names.append(name or f"obstacle {i + 1} (N {c[0]:.0f} E {c[1]:.0f})")
    seen: dict[str, int] = {}
    out = []
    for n in names:
        seen[n] = seen.get(n, 0) + 1
        out.append(n if seen[n] == 1 else f"{n} #{seen[n]}")
    return out


def world_visibility(world, tolerance_m: float = 1.5, tolerance_rel: float = 0.05) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """A line-of-sight test for :func:`flightsim.score.evaluation.evaluate`: ``visible(origins (K, 3), points (K, 3))``
    → (K,) bool, True where the first solid on the ray from the origin towards the point (the world's obstacles,
    :meth:`flightsim.world.World.raycast`; the ground is left out, both ends lie above it) lies no nearer than
    max(``tolerance_m``, ``tolerance_rel`` · distance) short of the point.  The scorer's cell points sit on their
    sector's centre bearing at the sector's true distance, on the surface or just in front of it (the wedge's
    nearest point may lie off the centre bearing): the tolerance keeps a surface from hiding itself."""

    def visible(origins: np.ndarray, points: np.ndarray) -> np.ndarray:
        o = np.asarray(origins, float).reshape(-1, 3)
        d = np.asarray(points, float).reshape(-1, 3) - o
        dist = np.linalg.norm(d, axis=1)
        out = np.ones(len(d), bool)
        ok = dist > 1e-9
        if np.any(ok):
            hit = world.raycast(o[ok], d[ok] / dist[ok, None], ground=False).distance
            out[ok] = hit >= dist[ok] - np.maximum(tolerance_m, tolerance_rel * dist[ok])
        return out

    return visible


def world_namer(world, max_distance_m: float = 2.0) -> Callable[[np.ndarray], list]:
    """A namer for :func:`name_obstacles`: the world solid whose footprint is nearest each point
    (within ``max_distance_m``), using :meth:`flightsim.world.World.closest_horizontal`."""
    obstacles = list(world.obstacles)

    def namer(ne: np.ndarray) -> list:
        out = []
        for n_, e_ in np.asarray(ne, float).reshape(-1, 2):
            if not obstacles:
                out.append(None)
                continue
            dist, _ = world.closest_horizontal(np.array([n_, e_, 0.0]), None)
            k = int(np.argmin(dist))
            out.append(obstacles[k].name if dist[k] <= max_distance_m else None)
        return out

    return namer
