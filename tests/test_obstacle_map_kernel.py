"""The compiled obstacle-map kernels against the pure-numpy reference (docs/derivations/obstacle_map.md).

Every step of a frame (map_entries, forget, observe, live_view, check_view, prune, remembered) runs
twice from the same map state — kernels on, kernels off — over seeded random flights past walls and
poles and over a short flight through the pipeline.  Decisions must be identical: which landmarks
enter, merge or are refused and why, which remembered points are found again, seen through,
absorbed or dropped, the usage counts, the support counts (the kernel repeats the reference's
float32 expansion; the tests include maps a kilometre from the origin, where that float32 rounding
decides) and which points are published.  Numbers agree to rounding:

* rtol 1e-12 (atol 1e-12) for what the kernel computes by the reference's own expressions in a
  fixed order where numpy may use BLAS (covariances, σ, depths): a few ulps;
* rtol 1e-9 (atol 1e-9 m, m²) for a merged point and its covariance, fused through three 3×3
  inverses (Gauss–Jordan in the kernel, LAPACK in numpy): error ~ cond(P) · 1e-16 with cond up to
  ~1e5 for a range σ a hundred times the bearing σ.

With ``COMPANION_KERNELS=numpy`` the kernels run uncompiled (plain Python): the same comparisons on
fewer, smaller flights.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import types

import numpy as np
import pytest

from companion.core import jit
from companion.core import obstacle_map as OM
from companion.core import obstacle_map_kernels as OMK
from companion.core.camera import CameraConfig, CameraModel
from companion.core.frames import euler_zyx_to_R
from companion.core.obstacle_map import MapConfig, ObstacleMap

R_CAM_BODY = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
CAM = CameraModel(CameraConfig.from_fov(320, 240, 60.0))
FLIGHTS = 12 if jit.ENABLED else 3
FRAMES = 60 if jit.ENABLED else 25
_FIELDS = ObstacleMap._fields  # every per-point array, r_seen included


def run_both(monkeypatch, fn, *objs):
    """``fn(*copies)`` with kernels on and off, each on its own deep copy of ``objs``: (kernel, reference)."""
    out = []
    for enabled in (True, False):
        monkeypatch.setattr(jit, "ENABLED", enabled)
        c = copy.deepcopy(objs)
        out.append((fn(*c), c))
    monkeypatch.setattr(jit, "ENABLED", True)
    return out


def assert_close(a, b, what, rtol=1e-12, atol=1e-12):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape, f"{what}: shape {a.shape} vs {b.shape}"
    if a.dtype.kind in "biu" or b.dtype.kind in "biu":
        assert a.dtype == b.dtype and np.array_equal(a, b), f"{what} differs"
    else:
        np.testing.assert_allclose(a, b, rtol=rtol, atol=atol, err_msg=what)


def assert_same_map(a: ObstacleMap, b: ObstacleMap, what: str, merged_rows=()) -> None:
    for f in _FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        if f in ("p", "P") and len(merged_rows):  # fused through 3×3 inverses: LAPACK vs Gauss–Jordan
            keep = np.ones(len(x), bool)
            keep[list(merged_rows)] = False
            assert_close(x[~keep], y[~keep], f"{what} merged {f}", rtol=1e-9, atol=1e-9)
            x, y = x[keep], y[keep]
        assert_close(x, y, f"{what} {f}")
    assert (a.rejected, a.evicted, a.merged, a.superseded, a.absorbed) == (b.rejected, b.evicted, b.merged, b.superseded, b.absorbed), what


def assert_same_remembered(a, b, what):
    assert_close(a.keys, b.keys, f"{what} keys")
    for f in ("p_world", "range_sigma", "tangential_sigma", "age_s"):
        assert_close(getattr(a, f), getattr(b, f), f"{what} {f}")


class World:
    """Seeded surfaces (walls, poles, a ground patch) and a vehicle flying past them, yawing and rocking;
    each frame yields what the pipeline hands the map (landmark ids, points, σ, tracks' pixels)."""

    def __init__(self, rng: np.random.Generator, origin_m: float = 0.0):
        self.rng = rng
        pts = []
        for _ in range(int(rng.integers(1, 4))):  # walls
            c, yaw = rng.uniform(8, 30), rng.uniform(-1.0, 1.0)
            t, h = rng.uniform(-12, 12, 120), rng.uniform(-4, 2, 120)
            pts.append(np.stack([c + t * math.sin(yaw), t * math.cos(yaw) + rng.uniform(-10, 10), h], 1))
        for _ in range(int(rng.integers(0, 5))):  # poles
            x, y = rng.uniform(5, 25), rng.uniform(-10, 10)
            h = rng.uniform(-6, 0.5, 15)
            pts.append(np.stack([np.full(15, x), np.full(15, y), h], 1) + rng.normal(0, 0.05, (15, 3)))
        self.points = np.concatenate(pts) + np.array([origin_m, origin_m, 0.0])
        self.origin = origin_m
        self.track_of = np.full(len(self.points), -1)  # current track id of each world point (-1: untracked)
        self.next_id = 1

    def frame(self, k: int):
        rng = self.rng
        t = 0.1 * k
        p_wb = np.array([self.origin + 0.6 * k * 0.1 * 10, self.origin + math.sin(0.2 * k), -2.0 + 0.1 * math.sin(0.3 * k)])
        R_wb = euler_zyx_to_R(0.1 * math.sin(0.5 * k), 0.05 * math.cos(0.4 * k), 0.35 * math.sin(0.08 * k))
        R_wc = R_wb @ R_CAM_BODY.T
        p_wc = p_wb
        p_cam = (self.points - p_wc) @ R_wc
        z = p_cam[:, 2]
        vis = z > 0.5
        uv = np.full((len(self.points), 2), np.nan)
        uv[vis] = CAM.project(p_cam[vis])
        vis &= CAM.in_image(np.where(np.isfinite(uv), uv, -1.0))
        vis &= rng.random(len(vis)) < 0.85
        lost = ~vis | (rng.random(len(vis)) < 0.03)  # tracks end (out of view, or lost)
        self.track_of[lost] = -1
        start = vis & (self.track_of < 0)
        self.track_of[start] = np.arange(self.next_id, self.next_id + int(start.sum()))
        self.next_id += int(start.sum())
        idx = np.flatnonzero(vis)
        idx = idx[np.argsort(self.track_of[idx])]
        ids = self.track_of[idx].astype(np.int64)
        n = len(ids)
        rng_true = np.linalg.norm(self.points[idx] - p_wc, axis=1)
        rel = rng.uniform(0.01, 0.25, n)
        est = self.points[idx] + rng.normal(0, 1, (n, 3)) * (rel * rng_true / 3)[:, None]
        out = types.SimpleNamespace(
            ids=ids, p_world=est, range=np.linalg.norm(est - p_wc, axis=1), range_sigma=rel * rng_true,
            converged=rng.random(n) < 0.85, valid=rng.random(n) < 0.97,
            mean_nis=np.where(rng.random(n) < 0.1, np.nan, rng.gamma(2.0, 1.0, n) * np.where(rng.random(n) < 0.05, 30, 1)),
            retired_ids=ids[rng.random(n) < 0.02],
        )
        tf = types.SimpleNamespace(ids=ids.copy(), uv=uv[idx] + rng.normal(0, 0.3, (n, 2)))
        return t, out, tf, R_wb, p_wb, R_wc, p_wc


def map_step(monkeypatch, m: ObstacleMap, t, out, tf, R_wc, p_wc, p_wb, key_base, what):
    """One frame of Pipeline._update_map, each step kernel vs reference from the same state;
    the map goes on from the reference's state.  Returns the map and what happened."""
    cfg = m.config
    (ek, _), (er, _) = run_both(monkeypatch, lambda: OM.map_entries(out.ids, key_base, out.converged, out.valid, out.range_sigma,
                                                                    out.range, out.p_world, p_wc, 0.0036, cfg, out.mean_nis))
    for f in ("keys", "good", "forget", "entry_keys", "p_world", "P_world"):
        assert_close(getattr(ek, f), getattr(er, f), f"{what} map_entries {f}")
    e = er
    if len(e.forget):
        (nk, mk), (nr, mr) = run_both(monkeypatch, lambda mm: mm.forget(e.forget), m)
        assert nk == nr
        assert_same_map(mk[0], mr[0], f"{what} forget")
        m = mr[0]
    (rk, mk), (rr, mr) = run_both(monkeypatch, lambda mm: mm.observe(t, e.entry_keys, e.p_world, e.P_world, live_keys=e.keys, p_world_cam=p_wc), m)
    assert rk == rr, f"{what} observe refusals"
    merged = np.flatnonzero((mr[0].o[: len(m)] > m.o) & ~np.isin(mr[0].keys[: len(m)], m.keys)) if len(m) else ()
    assert_same_map(mk[0], mr[0], f"{what} observe", merged)
    m = mr[0]
    if len(out.retired_ids):
        (nk, mk), (nr, mr) = run_both(monkeypatch, lambda mm: mm.forget(out.retired_ids + key_base), m)
        assert nk == nr
        assert_same_map(mk[0], mr[0], f"{what} forget retired")
        m = mr[0]
    (lk, _), (lr, _) = run_both(monkeypatch, lambda: OM.live_view(out.ids, tf.ids, tf.uv, e.keys, e.good, out.p_world, out.range_sigma,
                                                                  out.range, R_wc, p_wc, CAM))
    for a, b, f in zip(lk, lr, ("uv", "depth", "sigma", "keys")):
        assert_close(a, b, f"{what} live_view {f}")
    c = CAM.config
    (vk, mk), (vr, mr) = run_both(monkeypatch, lambda mm: mm.check_view(t, R_wc, p_wc, c.fx, c.fy, c.cx, c.cy, c.width, c.height,
                                                                        *lr[:3], live_keys=lr[3]), m)
    assert vk == vr, f"{what} check_view {vk} vs {vr}"
    assert_same_map(mk[0], mr[0], f"{what} check_view")
    m = mr[0]
    (pk, mk), (pr, mr) = run_both(monkeypatch, lambda mm: mm.prune(t, p_wb), m)
    assert pk == pr, f"{what} prune"
    assert_same_map(mk[0], mr[0], f"{what} prune")
    m = mr[0]
    (remk, _), (remr, _) = run_both(monkeypatch, lambda mm: mm.remembered(t + 0.05, p_wb), m)
    assert_same_remembered(remk, remr, f"{what} remembered")
    return m, vr, len(merged), len(remr)


@pytest.mark.parametrize("variant", ["shipped", "far from the origin", "small cap, support off", "support from the range seen"])
def test_kernels_equal_reference_on_seeded_flights(monkeypatch, variant):
    """Seeded flights: every step's decisions identical, numbers to rounding (module docstring)."""
    from companion.io.config_files import load_companion_config

    from flight_inputs import ROOT

    cfg = load_companion_config(ROOT / "configs" / "companion.toml").map
    origin = 0.0
    if variant == "far from the origin":
        origin = 1500.0  # |p|² ~ 5e6 m²: the float32 support test rounds at ~1 m², the kernel must round alike
    elif variant == "support from the range seen":
        cfg = dataclasses.replace(cfg, support_seen_ratio=2.0)
    elif variant == "small cap, support off":
        cfg = MapConfig(max_landmarks=60, min_support=1, max_age_s=2.0, radius_m=20.0, max_entry_nis_ratio=0.0)
    seen = {"found": 0, "missed": 0, "merged": 0, "remembered": 0, "evicted": 0, "absorbed": 0}
    for flight in range(FLIGHTS):
        rng = np.random.default_rng(1000 * flight + len(variant))
        world = World(rng, origin)
        m = ObstacleMap(cfg)
        for k in range(FRAMES):
            t, out, tf, R_wb, p_wb, R_wc, p_wc = world.frame(k)
            m, vc, n_merged, n_rem = map_step(monkeypatch, m, t, out, tf, R_wc, p_wc, p_wb, 1 << 40, f"{variant} {flight}/{k}")
            seen["found"] += vc.found
            seen["missed"] += vc.missed
            seen["merged"] += n_merged
            seen["remembered"] += n_rem
        seen["evicted"] += sum(m.evicted.values())
        seen["absorbed"] += m.absorbed
    # the flights exercise what is compared (a vacuous comparison would pass anything)
    assert all(v > 0 for v in seen.values()), seen


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_column_support_kernel_matches_the_numpy_reference(monkeypatch, seed):
    """support_column_radius_m: the kernel's column counts (the larger of sphere and column decides)
    equal the numpy reference's, on clustered points with pairs right at the column's edges."""
    rng = np.random.default_rng(seed)
    cfg = MapConfig(min_support=2, support_radius_m=0.6, support_radius_rel=0.15, support_column_radius_m=0.3,
                    support_column_half_height_m=1.2)
    m = ObstacleMap(cfg)
    base = np.array([200.0, -150.0, -5.0]) * rng.uniform(0, 10)
    q = base + rng.uniform(-4, 4, (300, 3)) * np.array([1.0, 1.0, 0.5])
    ang = rng.uniform(0, 2 * np.pi, (300, 1))
    edge = np.concatenate([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1) * 0.3 + np.array([0, 0, 1.0]) * rng.choice([-1.2, 1.2, 0.5], (300, 1))
    p = np.concatenate([q, q + edge])
    m.observe(0.0, np.arange(len(p)), p, np.broadcast_to(np.eye(3) * 0.01, (len(p), 3, 3)))
    rows = np.arange(len(p))
    pv = base + np.array([10.0, 0.0, 0.0])
    monkeypatch.setattr(jit, "ENABLED", False)
    ref = m.support(rows, p_world_vehicle=pv)
    ref_rem = m.remembered(1.0, pv).keys
    monkeypatch.setattr(jit, "ENABLED", True)
    np.testing.assert_array_equal(m.support(rows, p_world_vehicle=pv), ref)
    np.testing.assert_array_equal(m.remembered(1.0, pv).keys, ref_rem)
    sphere_only = ObstacleMap(dataclasses.replace(cfg, support_column_radius_m=0.0))
    sphere_only.observe(0.0, np.arange(len(p)), p, np.broadcast_to(np.eye(3) * 0.01, (len(p), 3, 3)))
    assert np.any(m.support(rows, p_world_vehicle=pv) > sphere_only.support(rows, p_world_vehicle=pv))  # the column counts


def test_support_matches_the_float32_reference_far_from_the_origin(monkeypatch):
    """Pairs right at the support radius, far from the origin: the reference's float32 expansion
    decides them (an exact float64 distance would not agree); the kernel repeats it exactly."""
    rng = np.random.default_rng(5)
    m = ObstacleMap(MapConfig(min_support=2, support_radius_m=0.6, support_radius_rel=0.0))
    base = np.array([2000.0, -1500.0, -30.0])
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    q = base + rng.uniform(-5, 5, (400, 3))
    p = np.concatenate([q, q + d * (0.6 + rng.uniform(-2e-4, 2e-4, (400, 1)))])  # each q has a neighbour ~at the radius
    m.observe(0.0, np.arange(len(p)), p, np.broadcast_to(np.eye(3) * 0.01, (len(p), 3, 3)))
    rows = np.arange(len(p))
    monkeypatch.setattr(jit, "ENABLED", False)
    ref = m.support(rows, p_world_vehicle=base)
    monkeypatch.setattr(jit, "ENABLED", True)
    ker = m.support(rows, p_world_vehicle=base)
    np.testing.assert_array_equal(ker, ref)
    exact = np.count_nonzero(np.sum((p[:, None] - p[None]) ** 2, axis=2) <= 0.36, axis=1)
    assert np.any(exact != ref)  # the float32 rounding matters here: the test discriminates


def _support_bruteforce(p, rows, pv, radius_m, rel, r_seen, seen_ratio):
    """Every pair, numpy, the float32 expansion with sgemm's fused q·p chain (products exact in float64)."""
    radius = np.full(rows.size, radius_m)
    if rel > 0:
        d = np.linalg.norm(p[rows] - pv, axis=1)
        radius = np.maximum(radius, rel * np.maximum(d, np.minimum(r_seen[rows], seen_ratio * d)))
    P = p.astype(np.float32)
    q = P[rows]
    qq = np.sum(q * q, 1)
    pp = np.sum(P * P, 1)
    Q, R = q.astype(float)[:, None, :], P.astype(float)[None, :, :]
    dot = (Q[..., 0] * R[..., 0]).astype(np.float32)
    dot = (Q[..., 1] * R[..., 1] + dot).astype(np.float32)
    dot = (Q[..., 2] * R[..., 2] + dot).astype(np.float32)
    return np.count_nonzero((qq[:, None] + pp[None, :]) - np.float32(2.0) * dot <= (radius**2).astype(np.float32)[:, None], axis=1)


@pytest.mark.parametrize("scale", [1e-3, 1.0, 30.0, 3000.0])
def test_support_slab_counts_every_pair(scale):
    """The kernel tests only a slab of points along one axis: its counts must be those of every pair
    (clusters at every scale, points near the origin where the slab's rounding margin is thinnest)."""
    rng = np.random.default_rng(int(scale * 10) + 1)
    for trial in range(20):
        centres = rng.normal(0, scale, (5, 3)) + rng.choice([0.0, 2000.0]) * rng.random(3)
        p = np.concatenate([c + rng.normal(0, rng.uniform(0.05, 3.0), (80, 3)) for c in centres])
        rows = np.sort(rng.choice(len(p), 150, replace=False))
        pv = centres[0] + rng.normal(0, 10, 3)
        seen = rng.uniform(0.0, 40.0, len(p)) * (rng.random(len(p)) < 0.5)  # ranges when entered, half not known (0)
        for radius_m, rel, r_seen, ratio in ((0.6, 0.15, np.zeros(len(p)), 0.0), (0.6, 0.15, seen, 1000.0), (0.6, 0.15, seen, 2.0),
                                             (0.6, 0.0, seen, 2.0), (rng.uniform(0.01, 5.0), 0.0, np.zeros(len(p)), 0.0)):
            np.testing.assert_array_equal(OMK._support_k(p, rows, pv, radius_m, rel, r_seen, ratio),
                                          _support_bruteforce(p, rows, pv, radius_m, rel, r_seen, ratio))


@pytest.mark.parametrize("case", ["empty map", "nothing in", "one landmark", "bad inputs", "absorb", "duplicate keys", "no live",
                                  "live_keys None"])
def test_kernel_edge_cases(monkeypatch, case):
    """Inputs the reference handles: empty, single, NaN / inf / non-PD covariances, duplicates."""
    cov = np.eye(3) * 0.04
    m = ObstacleMap(MapConfig(min_support=1))
    R_wb = np.eye(3)
    R_wc, p_wc = R_wb @ R_CAM_BODY.T, np.zeros(3)
    c = CAM.config
    if case != "empty map":
        m.observe(0.0, [1, 2, 3], [[10, 0, 0], [10, 0.5, 0], [12, -1, 0.2]], np.broadcast_to(cov, (3, 3, 3)))
        m.observe(0.1, [4], [[10.01, 0.0, 0.0]], [cov], live_keys=[4])  # 1..3 remembered, 4 lands on 1: merged
    keys, p, P, live = {
        "empty map": ([], np.zeros((0, 3)), np.zeros((0, 3, 3)), None),
        "nothing in": ([], np.zeros((0, 3)), np.zeros((0, 3, 3)), [4]),
        "one landmark": ([9], [[20.0, 3.0, 0.0]], [cov], None),
        "bad inputs": ([5, 6, 7, 8, 9, 10], [[np.nan, 0, 0], [1, 2, 3], [1, 2, 3], [1, 2, 3], [np.inf, 1, 1], [4, 4, 4]],
                       [cov, -cov, np.diag([1.0, 1.0, 0.0]), cov + np.triu(np.full((3, 3), 1e-3), 1), cov, cov * np.nan], None),
        "absorb": ([4, 11], [[10.0, 0.0, 0.0], [10.0, 0.5, 0.0]], [cov, cov], [4, 11]),
        "duplicate keys": ([12, 12, 4], [[15.0, 0, 0], [15.1, 0, 0], [10.0, 0, 0]], [cov, cov, cov], None),
        "no live": ([], np.zeros((0, 3)), np.zeros((0, 3, 3)), []),
        "live_keys None": ([4, 13], [[10.0, 0.0, 0.0], [30.0, 0.0, 0.0]], [cov, cov], None),
    }[case]
    P = np.asarray(P, float).reshape(-1, 3, 3)
    (rk, mk), (rr, mr) = run_both(monkeypatch, lambda mm: mm.observe(0.2, keys, p, P, live_keys=live), m)
    assert rk == rr
    assert_same_map(mk[0], mr[0], f"{case} observe", merged_rows=range(len(m)))
    if case == "bad inputs":
        assert rr == {OM.REJECT_NOT_FINITE: 3, OM.REJECT_NOT_PD: 3}
    m = mr[0]
    luv = {"absorb": np.array([[159.5, 119.5], [159.5 + 277.1 * 0.05, 119.5]]), "no live": np.zeros((0, 2))}.get(
        case, np.array([[159.5, 119.5]]))
    depth = np.full(len(luv), 10.0)
    lkeys = None if case == "live_keys None" else np.array([4, 11][: len(luv)])
    for fn in (lambda mm: mm.check_view(0.2, R_wc, p_wc, c.fx, c.fy, c.cx, c.cy, c.width, c.height, luv, depth, np.full(len(luv), 0.1),
                                        live_keys=lkeys),
               lambda mm: mm.prune(0.2, p_wc), lambda mm: mm.forget([2, 2, 99]), lambda mm: mm.remembered(0.3, p_wc)):
        (a, mk), (b, mr) = run_both(monkeypatch, fn, m)
        if isinstance(a, OM.Remembered):
            assert_same_remembered(a, b, case)
        else:
            assert a == b, case
        assert_same_map(mk[0], mr[0], case)
        m = mr[0]


def test_kernel_fuses_and_supersedes_merges_as_the_reference(monkeypatch):
    """New landmarks landing on remembered points: some agree with them (fused), some disagree across
    their narrow axes (superseded by the new estimate), after different ages (the drift grows the
    remembered covariance).  Same rows, points, covariances and counts from the kernel and the
    reference, and both kinds occur."""
    rng = np.random.default_rng(7)
    m = ObstacleMap(MapConfig(min_support=1, max_age_s=60.0))
    n = 40
    p0 = np.column_stack([rng.uniform(5, 30, n), rng.uniform(-10, 10, n), rng.uniform(-6, -2, n)])
    P0 = np.empty((n, 3, 3))
    for i in range(n):  # long along a random line of sight: range σ 0.3–2 m, bearing σ 0.02–0.05 m
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        s_r, s_b = rng.uniform(0.3, 2.0), rng.uniform(0.02, 0.05)
        P0[i] = s_r**2 * np.outer(u, u) + s_b**2 * (np.eye(3) - np.outer(u, u))
    m.observe(0.0, np.arange(1, n + 1), p0, P0, live_keys=[])
    m.t_seen[:] = rng.uniform(-30.0, 0.0, n)  # remembered for up to 30 s
    p1 = p0 + rng.normal(0, 0.4, (n, 3))
    P1 = P0[rng.permutation(n)]  # the new landmarks' lines of sight differ from the old ones'
    keys = np.arange(101, 101 + n)
    (rk, mk), (rr, mr) = run_both(monkeypatch, lambda mm: mm.observe(1.0, keys, p1, P1, live_keys=keys), m)
    assert rk == rr
    assert_same_map(mk[0], mr[0], "fuse or supersede", merged_rows=range(len(m)))
    ref = mr[0]
    assert 0 < ref.superseded < ref.merged, (ref.merged, ref.superseded)
    rows = np.flatnonzero(np.isin(ref.keys, keys) & (ref.o > 0))  # merged rows (appended ones have o = 0)
    superseded = [r for r in rows if np.allclose(ref.p[r], p1[ref.keys[r] - 101]) and np.allclose(ref.P[r], P1[ref.keys[r] - 101])]
    assert len(superseded) == ref.superseded  # a superseded row holds the new estimate exactly


def _edge_map(cov00=0.25):
    """Remembered points straight ahead of a camera looking north (R_world_cam = R_cam_bodyᵀ at the
    origin), with a covariance whose σ along the optical axis is exactly 0.5 m."""
    m = ObstacleMap(MapConfig(min_support=1))
    P = np.diag([cov00, 1.0, 1.0])
    m.observe(0.0, [1, 2], [[16.0, 0.0, 0.0], [16.0, -9.75, 0.0]], [P, P], live_keys=[])
    return m


@pytest.mark.parametrize("edge", ["depth gate", "pixel radius", "image margin", "prune radius", "prune age", "entry sigma",
                                  "merge tie", "duplicate keys"])
def test_kernels_decide_rule_edges_as_the_reference(monkeypatch, edge):
    """Quantities exactly on a rule's edge (≤ vs <, first vs last of equals): the kernel decides as
    the reference does.  Each case is built so that the two sides of the edge give different maps."""
    cam = CameraConfig(width=320, height=240, fx=256.0, fy=256.0, cx=160.0, cy=120.0)
    R_wc, p_wc = R_CAM_BODY.T, np.zeros(3)  # looking north: depth = north, u = 256·east/north + 160

    def view(m, luv, depth, sigma=0.0, t=0.0):
        return m.check_view(t, R_wc, p_wc, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, np.asarray(luv, float),
                            np.asarray(depth, float), np.full(len(luv), sigma), live_keys=np.arange(100, 100 + len(luv)))

    results = []
    for enabled in (True, False):
        monkeypatch.setattr(jit, "ENABLED", enabled)
        m = _edge_map()
        if edge == "depth gate":  # gate = 3·√(0.25 + 0) = 1.5 m exactly: a live point 1.5 m beyond agrees (found)
            got = view(m, [[160.0, 120.0]], [17.5])
        elif edge == "pixel radius":  # 6 px exactly: near
            got = view(m, [[166.0, 120.0]], [16.0])
        elif edge == "image margin":  # point 2 projects to u = 4 = the margin exactly: predicted in view
            got = view(m, [[4.0, 120.0]], [16.0])
        elif edge == "prune radius":  # 16 m exactly
            m.config = MapConfig(min_support=1, radius_m=16.0)
            got = m.prune(0.0, np.zeros(3))
        elif edge == "prune age":
            got = m.prune(20.0, np.zeros(3))  # seen at 0, max_age 20 s exactly: kept
        elif edge == "entry sigma":
            c = MapConfig()
            rng_m = np.array([10.0, 7.0, 3.0])
            got = OM.map_entries(np.arange(3), 0, np.ones(3, bool), np.ones(3, bool), c.max_rel_sigma * rng_m, rng_m,
                                 np.eye(3) * rng_m[:, None], p_wc, 0.003, c).good
        elif edge == "merge tie":  # a new landmark exactly between the two remembered points: the first wins
            got = m.observe(0.1, [7], [[16.0, -4.875, 0.0]], [np.diag([0.25, 100.0, 1.0])], live_keys=[7])
        elif edge == "duplicate keys":  # a key passed twice: both rows enter; later steps take the first row
            m.observe(0.1, [12, 12], [[5.0, 0.0, 0.0], [6.0, 0.0, 0.0]], [np.eye(3), np.eye(3)])
            m.observe(0.2, [12], [[5.5, 0.0, 0.0]], [np.eye(3) * 2], live_keys=[])
            got = m.forget([12])
        results.append((got, m))
    monkeypatch.setattr(jit, "ENABLED", True)
    (gk, mk), (gr, mr) = results
    if isinstance(gk, np.ndarray):
        assert_close(gk, gr, edge)
    else:
        assert gk == gr, edge
    assert_same_map(mk, mr, edge, merged_rows=range(len(mr)) if edge == "merge tie" else ())
    expected = {"depth gate": 1, "pixel radius": 1, "image margin": 1}  # found again on the edge (reference)
    if edge in expected:
        assert gr.found == expected[edge], (edge, gr)
    elif edge == "prune radius":
        assert mr.keys.tolist() == [1]  # 16 m exactly stays, the other (18.7 m) goes
    elif edge == "prune age":
        assert len(mr) == 2
    elif edge == "entry sigma":
        assert gr.all()
    elif edge == "merge tie":
        assert mr.merged == 1 and mr.keys.tolist() == [7, 2]
    elif edge == "duplicate keys":
        assert gr == 1 and mr.keys.tolist() == [1, 2, 12] and mr.p[2, 0] == 6.0


def test_entry_checks_agree_on_clear_cut_covariances():
    """Positive definiteness by Cholesky pivots (kernel) and by the smallest eigenvalue (reference)
    agree wherever the answer is not at the rounding edge: λ_min/λ_max ≥ 1e-10 or ≤ −1e-10, and
    exactly singular matrices (both refuse)."""
    rng = np.random.default_rng(3)
    Ps = []
    for _ in range(3000):
        Q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        lam = rng.uniform(1e-3, 10, 3) * rng.choice([1, 1, 1, -1], 3) * 10.0 ** rng.integers(-6, 3)
        if rng.random() < 0.2:
            lam[rng.integers(3)] = lam.max() * rng.choice([1e-10, -1e-10, 1e-8, -1e-8])
        P = (Q * lam) @ Q.T
        Ps.append(0.5 * (P + P.T))
    Ps += [np.diag([1.0, 2.0, 0.0]), np.zeros((3, 3)), np.diag([1.0, -1e-3, 1.0]), np.eye(3)]
    P = np.array(Ps)
    p = np.zeros((len(P), 3))
    ok, n_bad, n_not_pd = OMK._entry_checks_k(p, P)
    eig = np.linalg.eigvalsh(P)[:, 0]
    np.testing.assert_array_equal(ok, eig > 0)
    assert n_bad == 0 and n_not_pd == np.count_nonzero(eig <= 0) and 0 < n_not_pd < len(P)


def test_reference_functions_directly():
    """The references themselves, called directly: the documented behaviour the kernels follow."""
    nis = np.array([1.0, 1.2, 0.9, 1.1, 50.0, np.nan, 1.0, 1.05, 0.95, 1.0, 1.3])
    ok = OM.consistent_for_entry_reference(nis, np.ones(nis.size, bool), 10.0)
    assert ok.tolist() == [True, True, True, True, False, False, True, True, True, True, True]
    assert OM.consistent_for_entry_reference(nis[:5], np.ones(5, bool), 10.0).all()  # fewer than 10: no reference
    P = OM.landmark_covariance_reference([[10.0, 0.0, 0.0]], np.zeros(3), [0.5], 0.01)
    np.testing.assert_allclose(P[0], np.diag([0.25, 0.01, 0.01]))
    p = OM.points_on_current_rays_reference(np.array([1, 2]), [[5.0, 0, 0], [6.0, 0, 0]], np.array([4.0, 6.0]), np.array([2]),
                                            np.array([[0.0, 0.0, 1.0]]), R_CAM_BODY.T, np.zeros(3))
    np.testing.assert_allclose(p, [[5.0, 0, 0], [6.0, 0, 0]])  # landmark 2 on its current ray (forward), at 6 m


@pytest.mark.parametrize("fn, args", [
    ("consistent_for_entry", lambda rng: (np.where(rng.random(300) < 0.03, np.nan, rng.gamma(2, 1, 300))
                                          * np.where(rng.random(300) < 0.02, np.inf, 1.0), rng.random(300) < 0.8, 8.0)),
    ("landmark_covariance", lambda rng: (rng.uniform(-50, 50, (300, 3)), rng.normal(0, 5, 3), rng.uniform(0, 3, 300), 0.004)),
    ("points_on_current_rays", lambda rng: (np.sort(rng.choice(1000, 200, replace=False)), rng.normal(0, 20, (200, 3)),
                                            rng.uniform(1, 50, 200), np.sort(rng.choice(1000, 300, replace=False)),
                                            CAM.unproject(rng.uniform(0, 320, (300, 2))), euler_zyx_to_R(0.1, -0.2, 2.0),
                                            rng.normal(0, 5, 3))),
])
def test_functions_equal_reference_seeded(monkeypatch, fn, args):
    """The module-level kernels on seeded inputs (NaN NIS and exactly tied medians included)."""
    for seed in range(20):
        a = args(np.random.default_rng(seed))
        (k, _), (r, _) = run_both(monkeypatch, lambda: getattr(OM, fn)(*a))
        assert_close(k, r, f"{fn} seed {seed}")
    (k, _), (r, _) = run_both(monkeypatch, lambda: getattr(OM, fn)(*[x[:0] if isinstance(x, np.ndarray) and x.ndim and x.size > 3
                                                                    else x for x in a]))
    assert_close(k, r, f"{fn} empty")


def test_dispatch_follows_jit_enabled(monkeypatch):
    calls = []
    monkeypatch.setattr(OM, "_prune_k", lambda *a: calls.append("kernel") or (np.ones(1, bool), 0, 0, 0))
    m = ObstacleMap()
    m.observe(0.0, [1], [[1.0, 2.0, 3.0]], [np.eye(3)])
    monkeypatch.setattr(jit, "ENABLED", True)
    m.prune(0.0, np.zeros(3))
    monkeypatch.setattr(jit, "ENABLED", False)
    m.prune(0.0, np.zeros(3))
    assert calls == ["kernel"]


@pytest.mark.skipif(not jit.ENABLED, reason="whole flight: compiled kernels only")
def test_update_map_equals_reference_on_a_flight(monkeypatch):
    """Pipeline._update_map on a short turning flight: each frame from the same map, kernels on and
    off give the same map and the same remembered points."""
    import companion.pipeline as P
    from flight_inputs import fly

    orig = P.Pipeline._update_map
    frames = []

    def both(self, *a):
        before = copy.deepcopy(self.map)
        monkeypatch.setattr(jit, "ENABLED", False)
        ref = orig(self, *copy.deepcopy(a))
        m_ref, self.map = self.map, before
        monkeypatch.setattr(jit, "ENABLED", True)
        ker = orig(self, *a)
        assert_same_map(self.map, m_ref, f"frame {len(frames)}", merged_rows=range(len(self.map)) if self.map.merged else ())
        assert_same_remembered(ker, ref, f"frame {len(frames)}")
        frames.append((len(self.map), len(ker)))
        return ker

    monkeypatch.setattr(P.Pipeline, "_update_map", both)
    fly(frames=60)
    assert len(frames) >= 55 and max(f[1] for f in frames) > 0


def test_warm_up_is_registered():
    assert OMK._warm_up in jit._WARMUPS
    OMK._warm_up()
