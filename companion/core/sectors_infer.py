"""The sectors' inference rules: obstacles claimed in unknown sectors (docs/derivations/sectors.md:
inference only ever adds an obstacle, never "clear").

The numpy reference, called by :func:`companion.core.sectors._sectors_reference` after the measured
sectors are decided, in this order:

* :func:`_infer_between` — an unknown gap between two obstacle sectors whose ranges agree;
* :func:`_infer_narrow` (with :func:`_line_distance`) — an unknown gap between two obstacle sectors
  whose points lie close together: the straight line between them;
* :func:`_infer_vertical`, :func:`_infer_vertical_one_side` and :func:`_nearest_per_sector` — a
  structure standing through the band, seen just above and below it (or reaching down towards it);
* :func:`_claim_inferred` — a sector taking such a point (also used by ``cap_above_m``).

Their compiled forms (``_infer_between_k``, ``_infer_narrow_k``, ``_vertical_pick_k``) are in
:mod:`companion.core.sectors_kernels`.
"""

from __future__ import annotations

import math

import numpy as np

from companion.core.sectors_types import SECTOR_COUNT, SECTOR_DEG, SectorConfig, SectorState


def _infer_between(state, dist, range_m, sigma_m, config: SectorConfig) -> np.ndarray:
    """Fill unknown gaps between two consistent obstacle sectors (in place); returns the mask of
    inferred sectors.  Never touches a "clear" or obstacle sector: inference only adds obstacles."""
    inferred = np.zeros(SECTOR_COUNT, bool)
    G = config.infer_max_gap_sectors
    if G == 0:
        return inferred
    obs = state == SectorState.OBSTACLE
    unk = state == SectorState.UNKNOWN
    for gap in range(1, G + 1):
        # sectors i+1..i+gap unknown, i and i+gap+1 obstacles (indices on the ring)
        left = obs.copy()
        right = np.roll(obs, -(gap + 1))
        between = np.ones(SECTOR_COUNT, bool)
        for a in range(1, gap + 1):
            between &= np.roll(unk, -a)
        cand = np.flatnonzero(left & right & between)
        if cand.size == 0:
            continue
        rl = range_m[cand]
        rr = range_m[(cand + gap + 1) % SECTOR_COUNT]
        ok = np.abs(rl - rr) <= config.infer_rel_tol * np.minimum(rl, rr)
        for i in cand[ok]:
            jr = (i + gap + 1) % SECTOR_COUNT
            near = i if range_m[i] <= range_m[jr] else jr
            fill = (i + np.arange(1, gap + 1)) % SECTOR_COUNT
            fill = fill[~inferred[fill]]
            state[fill] = SectorState.OBSTACLE
            dist[fill] = min(dist[i], dist[jr])
            range_m[fill] = range_m[near]
            sigma_m[fill] = max(sigma_m[i], sigma_m[jr])
            inferred[fill] = True
    return inferred


def _infer_vertical(idx: np.ndarray, d_cons: np.ndarray, above: np.ndarray, below: np.ndarray, rel_tol: float) -> np.ndarray:
    """Candidate points (indices) a sector may claim from a vertical span: the nearer point of each
    pair, one point above the band and one below it in the same sector, whose conservative
    horizontal ranges differ by at most ``rel_tol`` of the nearer (a pole, mast or trunk whose points in
    the band itself were not ranged: an 11 px template on a pole a few px wide in front of a textured
    background mixes two depths).  Only ever adds an obstacle."""
    both = (np.bincount(idx[above], minlength=SECTOR_COUNT) > 0) & (np.bincount(idx[below], minlength=SECTOR_COUNT) > 0)
    a = np.flatnonzero(above & both[idx])  # only sectors with points on both sides
    b = np.flatnonzero(below & both[idx])
    da, db = d_cons[a][:, None], d_cons[b][None, :]
    ia, ib = np.nonzero((idx[a][:, None] == idx[b][None, :]) & (np.abs(da - db) <= rel_tol * np.minimum(da, db)))
    return np.where(d_cons[a[ia]] <= d_cons[b[ib]], a[ia], b[ib])  # the nearer point of each agreeing pair


def _nearest_per_sector(idx: np.ndarray, d_cons: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(72,) the nearest of candidate points ``pts`` in each sector, −1 where none (stable: the first
    candidate wins ties)."""
    out = np.full(SECTOR_COUNT, -1, np.int64)
    if pts.size == 0:
        return out
    order = np.lexsort((d_cons[pts], idx[pts]))  # by sector, then range
    sec = idx[pts[order]]
    first = np.r_[True, sec[1:] != sec[:-1]]
    out[sec[first]] = pts[order][first]
    return out


def _claim_inferred(mask, point_of, state, dist, range_m, sigma_m, pick, inferred, pt_cm, d_pub, sig) -> np.ndarray:
    """Sectors ``mask`` become inferred obstacles at their points ``point_of[mask]`` (``state``, ``dist``,
    ``range_m``, ``sigma_m`` and ``inferred`` updated in place); returns ``pick`` with those points."""
    if not np.any(mask):
        return pick
    pts = point_of[mask]
    state[mask] = SectorState.OBSTACLE
    dist[mask] = pt_cm[pts]
    range_m[mask] = d_pub[pts]
    sigma_m[mask] = sig[pts]
    inferred |= mask
    pick = pick.copy()
    pick[mask] = pts
    return pick


def _infer_vertical_one_side(idx: np.ndarray, d_cons: np.ndarray, above: np.ndarray, over: np.ndarray, rel_tol: float,
                             min_extent: float, reach: float) -> np.ndarray:
    """Candidate points (indices) a sector may claim from a vertical structure standing above the band:
    the nearer point of each pair of points in ``above`` (in one sector) whose
    conservative horizontal ranges agree within ``rel_tol`` of the nearer, whose heights differ by at
    least ``min_extent`` (``over``: metres above the band's upper edge) and of which the lower lies within
    ``reach`` of the edge.  A pole standing on the ground shows its upper part against the sky while its
    in-band part, in front of a textured background, does not range and its foot is the ground (no
    evidence); a structure that spans that much height at one range and comes that close to the band is
    taken to stand through it.  Only ever adds an obstacle; an overhead structure whose face is that tall
    that low over the path (a bridge deck, a low canopy) is claimed too: a stop where there may be a way
    under it."""
    a = np.flatnonzero(above)
    a = a[np.bincount(idx[a], minlength=SECTOR_COUNT)[idx[a]] >= 2]  # sectors with two such points
    da, ha = d_cons[a], over[a]
    pair = (idx[a][:, None] == idx[a][None, :]) & (np.arange(a.size)[:, None] < np.arange(a.size)[None, :])
    pair &= np.abs(da[:, None] - da[None, :]) <= rel_tol * np.minimum(da[:, None], da[None, :])
    pair &= np.abs(ha[:, None] - ha[None, :]) >= min_extent
    pair &= np.minimum(ha[:, None], ha[None, :]) <= reach
    ia, ib = np.nonzero(pair)
    return np.where(da[ia] <= da[ib], a[ia], a[ib])  # the nearer point of each qualifying pair


def _line_distance(a: np.ndarray, b: np.ndarray, bearing: np.ndarray) -> np.ndarray:
    """Distance along rays at ``bearing`` (K,) rad from the origin to the line through points ``a``
    and ``b`` (2,) (horizontal plane, x forward, y right): t = (a × u)/(e × u), u = b − a; inf where the
    ray is parallel to the line or meets it behind the origin."""
    u = b - a
    e = np.stack([np.cos(bearing), np.sin(bearing)], 1)
    den = e[:, 0] * u[1] - e[:, 1] * u[0]
    num = a[0] * u[1] - a[1] * u[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / den
    return np.where(np.isfinite(t) & (t > 0), t, np.inf)


def _infer_narrow(state, dist, range_m, sigma_m, xy_m, config: SectorConfig, measured: np.ndarray) -> np.ndarray:
    """Fill unknown gaps of up to ``infer_narrow_max_sectors`` between two obstacle sectors whose
    points (``xy_m`` (72, 2), levelled horizontal plane) lie at most ``infer_narrow_gap_m`` apart with
    the segment between them (in place); returns the mask of sectors filled.  Each gap sector takes
    the segment's nearest distance over its ±half-sector bearings (the ends of its span or the foot
    of the perpendicular): conservative.  Both sides must be ``measured`` (72,) obstacle sectors (not
    inferred ones: no chains).  Only unknown sectors change: inference only adds obstacles."""
    inferred = np.zeros(SECTOR_COUNT, bool)
    G, gap_m = config.infer_narrow_max_sectors, config.infer_narrow_gap_m
    if G == 0 or gap_m <= 0:
        return inferred
    half = math.radians(SECTOR_DEG) / 2
    obs = (state == SectorState.OBSTACLE) & measured
    known = np.flatnonzero(state != SectorState.UNKNOWN)
    if known.size < 2 or not np.any(obs):
        return inferred
    # maximal unknown runs on the ring, each between two known sectors (disjoint: one pass suffices)
    nxt = np.roll(known, -1)
    gaps = (nxt - known - 1) % SECTOR_COUNT
    sel = (gaps >= 1) & (gaps <= G) & obs[known] & obs[nxt]
    if not np.any(sel):
        return inferred
    chord = np.hypot(*(xy_m[nxt[sel]] - xy_m[known[sel]]).T)
    near = chord <= gap_m  # NaN (no point) compares False
    for i, j, gap, c_ab in zip(known[sel][near], nxt[sel][near], gaps[sel][near], chord[near]):
        a, b = xy_m[i], xy_m[j]
        fill = (i + np.arange(1, gap + 1)) % SECTOR_COUNT
        centre = np.radians(fill * SECTOR_DEG)
        t = np.minimum(_line_distance(a, b, centre - half), _line_distance(a, b, centre + half))
        # the perpendicular foot, where it falls inside a sector's span, is the nearest point
        u = (b - a) / max(float(c_ab), 1e-12)
        foot = a - np.dot(a, u) * u
        foot_b = math.atan2(foot[1], foot[0])
        d_foot = float(np.hypot(*foot))
        inside = np.abs((foot_b - centre + math.pi) % (2 * math.pi) - math.pi) <= half
        t = np.where(inside, np.minimum(t, d_foot), t)
        # never farther than the farther side (also bounds a ray that runs parallel to the line)
        t = np.clip(np.minimum(t, max(range_m[i], range_m[j])), config.min_distance_m, config.max_distance_m)
        state[fill] = SectorState.OBSTACLE
        dist[fill] = np.clip(np.rint(t * 100).astype(np.int64), config.min_distance_cm, config.max_distance_cm)
        range_m[fill] = t
        sigma_m[fill] = max(sigma_m[i], sigma_m[j])
        xy_m[fill] = t[:, None] * np.stack([np.cos(centre), np.sin(centre)], 1)
        inferred[fill] = True
    return inferred
