"""The compiled sector kernel against the pure-numpy reference (docs/derivations/sectors.md).

Sector outputs are safety-relevant: the product must never claim a sector clear in front of an
obstacle.  So every integer and flag the kernel returns (distances, states, view masks, point
counts, inferred flags, the published value of each obstacle point, the forward state) must equal
the reference's *exactly*, on seeded random scenes built like real ones (walls, poles through and
above the band, the ground, far clear evidence, unconverged and broken points, remembered points
spread over their bearing σ, roll / pitch, climbing flight) under the shipped configuration and
variants of it, and on a short flight through the whole pipeline.

Floats (ranges, σ, bearings, the 3-D nearest points) agree within rtol = atol = 1e-12: the kernel
evaluates the same expressions in the same order, except ``atan2`` of the bearing (libm in the
kernel, numpy's own loop in the reference) and the body coordinates of the spread copies (a fixed
order of summation in the kernel, BLAS in the reference), each at most an ulp or two (~1e-16
relative).  1e-12 leaves a margin of ~10⁴ over that and still catches any rule that differs (the
published values move by centimetres, 1e-4 relative and more).

With ``COMPANION_KERNELS=numpy`` the kernel is plain Python; the comparisons then run on fewer
scenes (the loops are slow uncompiled) and still check the logic.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from companion.core import jit
from companion.core import sectors as S
from companion.core import sectors_kernels as SK
from companion.core.frames import mount_rotation
from companion.core.sectors import SectorConfig, SectorState, compute_sectors, compute_sectors_reference
from companion.errors import InputError
from conftest import sectors_optional_rules_off

ROOT = Path(__file__).resolve().parent.parent
HFOV = math.radians(60.0)
VFOV = math.radians(46.8)
N_SCENES = 300 if jit.ENABLED else 30
RTOL = ATOL = 1e-12

_INT_FIELDS = ("distances_cm", "state", "in_view", "fully_in_view", "obstacle_points", "clear_points", "obstacle_cm",
               "remembered_points", "inferred", "inferred_vertical", "unknown_reason")
_FLOAT_FIELDS = ("range_m", "sigma_m", "obstacle_bearing_rad")


def sectors_kernel(p_body, range_sigma, converged, valid, hfov_rad, R_cam_body, config=SectorConfig(), *, roll_pitch_rad=None,
                   velocity_body=None, vfov_rad=None, remembered_p_body=None, remembered_sigma=None,
                   remembered_tangential_sigma=None, ground_height_m=None) -> S.Sectors:
    """The kernel path of :func:`compute_sectors` whatever jit.ENABLED says (uncompiled without numba)."""
    return S._sectors_kernel(p_body, range_sigma, converged, valid, hfov_rad, R_cam_body, config, roll_pitch_rad, velocity_body,
                             vfov_rad, remembered_p_body, remembered_sigma, remembered_tangential_sigma, ground_height_m)


def shipped_config() -> SectorConfig:
    from companion.io.config_files import load_companion_config

    return load_companion_config(ROOT / "configs" / "companion.toml").sectors


def assert_same_sectors(k: S.Sectors, r: S.Sectors, where="") -> None:
    """Integers and flags exactly (dtype too), floats within rounding (module docstring)."""
    for f in _INT_FIELDS:
        a, b = getattr(k, f), getattr(r, f)
        assert a.dtype == b.dtype and a.shape == b.shape, f"{where} {f}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}"
        assert np.array_equal(a, b), f"{where} {f} differs at {np.flatnonzero(a != b)[:10]}"
    for f in _FLOAT_FIELDS:
        a, b = getattr(k, f), getattr(r, f)
        assert a.shape == b.shape, f"{where} {f}"
        np.testing.assert_allclose(a, b, rtol=RTOL, atol=ATOL, err_msg=f"{where} {f}")
    for f in ("points_used", "points_rejected", "min_distance_cm", "max_distance_cm", "obstacle_rank"):
        assert getattr(k, f) == getattr(r, f), f"{where} {f}"
    assert k.forward.state == r.forward.state, where
    np.testing.assert_allclose([k.forward.distance_m, k.forward.sigma_m, k.forward.estimate_m],
                               [r.forward.distance_m, r.forward.sigma_m, r.forward.estimate_m], rtol=RTOL, atol=ATOL,
                               err_msg=f"{where} forward")
    assert [o.sector for o in k.nearest] == [o.sector for o in r.nearest], f"{where} nearest sectors"
    for a, b in zip(k.nearest, r.nearest):
        np.testing.assert_allclose([*a.p_body, a.range_m, a.sigma_m], [*b.p_body, b.range_m, b.sigma_m], rtol=RTOL, atol=ATOL,
                                   err_msg=f"{where} nearest")


def scene(rng: np.random.Generator, ground_m: float):
    """One seeded scene like the pipeline's (body FRD, vehicle at the origin): a wall, poles, the
    ground, far points (evidence of clear), unconverged and broken points, and remembered points
    all around with grown σ.  Returns the keyword arguments of :func:`compute_sectors` but the camera
    and attitude, and ``level``: the far points need a near-level flight to lie in the band."""
    parts, sig, conv, val = [], [], [], []
    open_view = rng.random() < 0.25  # nothing near in view: far points only (where "clear" is claimed)

    def add(p, s, c=None, v=None):
        p = np.asarray(p, float).reshape(-1, 3)
        parts.append(p)
        sig.append(np.broadcast_to(s, len(p)).astype(float))
        conv.append(rng.random(len(p)) < 0.85 if c is None else np.broadcast_to(c, len(p)))
        val.append(np.ones(len(p), bool) if v is None else np.broadcast_to(v, len(p)))

    if not open_view and rng.random() < 0.8:  # a wall across the view at 2–45 m, possibly oblique
        d, yaw = rng.uniform(2.0, 45.0), rng.uniform(-0.7, 0.7)
        t = rng.uniform(-15.0, 15.0, int(rng.integers(5, 120)))
        h = rng.uniform(-4.0, 4.0, t.size)
        p = np.stack([d + t * math.sin(yaw), t * math.cos(yaw), h], 1)
        add(p, np.abs(rng.normal(0.05, 0.05, t.size)) * d / 5)
    for _ in range(0 if open_view else int(rng.integers(0, 4))):  # poles: from the ground up through and above the band
        d, b = rng.uniform(1.0, 30.0), rng.uniform(-0.6, 0.6)
        h = rng.uniform(-ground_m, 8.0, int(rng.integers(2, 15)))  # height above the vehicle, m
        add(np.stack([np.full(h.size, d * math.cos(b)), np.full(h.size, d * math.sin(b)), -h], 1),
            rng.uniform(0.02, 0.6, h.size))
    n = 0 if open_view else int(rng.integers(0, 40))  # the ground ahead
    d = rng.uniform(2.0, 60.0, n)
    b = rng.uniform(-0.6, 0.6, n)
    add(np.stack([d * np.cos(b), d * np.sin(b), np.full(n, ground_m) + rng.normal(0, 0.3, n)], 1), rng.uniform(0.05, 2, n))
    n = int(rng.integers(20, 100) if open_view else rng.integers(0, 30))  # far points (evidence of clear), some ranged badly
    d = rng.uniform(35.0, 200.0, n)
    b = rng.uniform(-0.6, 0.6, n)
    add(np.stack([d * np.cos(b), d * np.sin(b), rng.uniform(-2, 2, n)], 1), rng.uniform(0.1, 10.0, n))
    n = 0 if open_view else int(rng.integers(0, 20))  # anything, anywhere
    add(rng.uniform(-30, 30, (n, 3)), rng.uniform(0, 5, n), rng.random(n) < 0.5, rng.random(n) < 0.9)
    if rng.random() < 0.3:  # broken points: NaN / inf coordinates, NaN or negative σ, zero range
        add([[np.nan, 1, 0], [np.inf, 0, 0], [5, 0, 0], [6, 0, 0], [0, 0, 0]], [0.1, 0.1, np.nan, -1.0, 0.1])
    if rng.random() < 0.5:  # on the rules' edges when level (R_level_body = I): max_distance, band and window edges
        e = [[40.0, 0.0, 0.0], [40.0, 0.0, -1.5], [20.0, 0.0, 1.5], [15.0, 0.0, -6.5], [15.0, 0.0, 6.5], [8.0, 0.0, -4.0],
             [41.0, 0.0, 0.0], [41.0, 0.1, 0.0], [41.0, -0.1, 0.0]]
        add(e, np.where(rng.random(len(e)) < 0.5, 0.0, 0.5), True)
    if rng.random() < 0.3:  # a pole whose points share (x, y): with sigma_k = 0 equal ranges, the first candidate wins
        x, y = rng.uniform(3, 30), rng.uniform(-5, 5)
        add([[x, y, -2.2], [x, y, -3.1], [x, y, 2.2], [x, y, 3.4], [x, y, -2.9]], [0.1, 0.3, 0.2, 0.4, 0.05], True)
    if rng.random() < 0.3:  # the same above the band only (one-sided pairs, the cap)
        x, y = rng.uniform(3, 30), rng.uniform(-5, 5)
        add([[x, y, -2.2], [x, y, -3.1], [x, y, -2.4], [x, y, -3.3], [x, y, -1.9]], [0.1, 0.3, 0.2, 0.4, 0.05], True)
    if rng.random() < 0.2:  # exact ties: repeated points (equal ranges in one sector)
        q = np.repeat(rng.uniform(3, 20, (2, 3)) * [1, 0.3, 0.1], 3, axis=0)
        add(q, 0.2, True)
    kw = dict(p_body=np.concatenate(parts), range_sigma=np.concatenate(sig), converged=np.concatenate(conv),
              valid=np.concatenate(val), level=open_view)
    if rng.random() < 0.8:  # remembered points all around, σ grown since last seen
        m = int(rng.integers(0, 150))
        d = rng.uniform(0.5, 50.0, m)
        b = rng.uniform(1.6, 4.7, m) if open_view else rng.uniform(-math.pi, math.pi, m)
        mp = np.stack([d * np.cos(b), d * np.sin(b), rng.uniform(-6, 6, m)], 1)
        mt = rng.uniform(0.0, 3.0, m) * (rng.random(m) < 0.7)
        ms = rng.uniform(0.01, 1.5, m)
        if m and rng.random() < 0.2:
            mp[0, 1], mt[-1] = np.nan, np.nan  # broken remembered points are not published
        if m > 3 and rng.random() < 0.2:
            mt[1] = -1.0
        kw.update(remembered_p_body=mp, remembered_sigma=ms, remembered_tangential_sigma=mt)
    return kw


def configs():
    base = shipped_config()
    yield "shipped", base
    yield "optional rules off", sectors_optional_rules_off(remembered_spread_k=2.0)  # and a wider spread than shipped (k = 1)
    yield "degrees band", dataclasses.replace(base, band_mode="degrees", band_half_angle_deg=8.0)
    yield "n-th nearest", dataclasses.replace(base, min_points_obstacle=3, min_points_clear=1, infer_max_gap_sectors=3)
    yield "touching, no veto", dataclasses.replace(base, touching_distance_m=0.4, unconverged_veto_clear=False,
                                                   forward_half_width_deg=12.5, nearest_count=12)
    yield "wide spread", dataclasses.replace(base, remembered_spread_k=3.0, remembered_max_spread_deg=40.0,
                                             remembered_drop_spread_deg=20.0, infer_narrow_max_sectors=12,
                                             infer_narrow_gap_m=12.0, infer_vertical_window_m=1.5, cap_above_m=0.0)
    yield "two-sided only", dataclasses.replace(base, infer_vertical_one_side=False, ground_margin_m=0.0, sigma_k=0.0)
    yield "exact ranges", dataclasses.replace(base, sigma_k=0.0)  # d_cons = d_h: points sharing (x, y) tie
    yield "cap only", dataclasses.replace(base, sigma_k=0.0, infer_vertical=False)
    yield "cap and vertical gated", dataclasses.replace(base, cap_gate_k=2.0)
    yield "unconverged cap", dataclasses.replace(base, unconverged_cap_k=2.0)
    yield "unconverged cap, n-th nearest", dataclasses.replace(base, unconverged_cap_k=1.0, min_points_obstacle=2, sigma_k=0.0)
    yield "drop across the line of sight only", dataclasses.replace(base, remembered_drop_spread_deg=3.0, remembered_drop_across_only=True)
    yield "no surface fusion", dataclasses.replace(base, fuse_gate_k=0.0)
    yield "edge margin", dataclasses.replace(base, clear_edge_margin_deg=1.0, min_points_clear=1)
    yield "clear along the line of sight", dataclasses.replace(base, clear_line_of_sight=True, min_points_clear=1)
    yield "line of sight, degrees band", dataclasses.replace(base, clear_line_of_sight=True, band_mode="degrees")
    yield "corridor", dataclasses.replace(base, clear_line_of_sight=True, clear_corridor_m=0.5, min_points_clear=1)
    yield "wide corridor, no edge margin", dataclasses.replace(base, clear_line_of_sight=True, clear_corridor_m=3.0,
                                                               clear_edge_margin_deg=0.0, min_points_clear=2)
    yield "corridor, far claims capped", dataclasses.replace(base, clear_corridor_m=1.5, corridor_far_ratio=1.5)
    yield "wide corridor, far claims capped, no fusion", dataclasses.replace(base, clear_corridor_m=4.0, corridor_far_ratio=1.0,
                                                                            fuse_gate_k=0.0, sigma_k=0.0)
    yield "veto beside the band", dataclasses.replace(base, unconverged_veto_margin_m=2.5, min_points_clear=1)
    yield "veto beside a degrees band", dataclasses.replace(base, unconverged_veto_margin_m=1.0, band_mode="degrees")
    yield "ranged veto beside the band", dataclasses.replace(base, converged_veto_margin_m=2.5, min_points_clear=1)
    yield "ranged veto beside a degrees band, no other", dataclasses.replace(base, converged_veto_margin_m=1.0, band_mode="degrees",
                                                                              unconverged_veto_clear=False)
    yield "fusion: wide gate, independent", dataclasses.replace(base, fuse_gate_k=5.0, fuse_correlation=0.0)
    yield "fusion: narrow gate, shared", dataclasses.replace(base, fuse_gate_k=0.5, fuse_correlation=1.0, min_points_obstacle=2)
    yield "margin tapered", dataclasses.replace(base, sigma_k_far=1.0, sigma_k_taper_from_m=5.0, sigma_k_taper_to_m=15.0)
    yield "margin tapered, gated, wide fusion", dataclasses.replace(base, sigma_k_far=0.5, sigma_k_taper_from_m=2.0,
                                                                    sigma_k_taper_to_m=8.0, cap_gate_k=1.0, fuse_gate_k=4.0)


@pytest.mark.parametrize("name, config", list(configs()))
def test_kernel_equals_reference_on_seeded_scenes(name, config):
    """Seeded random scenes, every rule on or off by config: the kernel is the reference."""
    rng = np.random.default_rng(20240611 + len(name))
    seen = {"clear": 0, "obstacle": 0, "inferred": 0, "remembered": 0, "rejected": 0}
    if config.infer_vertical or config.cap_above_m > 0:
        seen["inferred_vertical"] = 0
    mounts = [0.0, math.radians(-20.0), mount_rotation(0.0, 15.0, 10.0), mount_rotation(5.0, -10.0, 180.0)]
    for i in range(N_SCENES):
        ground = rng.uniform(0.5, 20.0)
        kw = scene(rng, ground)
        tilt = 0.02 if kw.pop("level") else 0.25
        cam = mounts[i % len(mounts)]
        opt = dict(
            roll_pitch_rad=None if rng.random() < 0.15 else tuple(rng.normal(0, tilt, 2)),
            velocity_body=None if rng.random() < 0.2 else rng.normal(0, 4, 3) * [1, 1, tilt],
            vfov_rad=None if rng.random() < 0.3 else VFOV,
            ground_height_m=None if rng.random() < 0.2 else (math.nan if rng.random() < 0.1 else -ground),
        )
        args = (kw.pop("p_body"), kw.pop("range_sigma"), kw.pop("converged"), kw.pop("valid"), HFOV, cam, config)
        k = sectors_kernel(*args, **opt, **kw)
        r = compute_sectors_reference(*args, **opt, **kw)
        assert_same_sectors(k, r, f"{name} scene {i}")
        seen["clear"] += int(np.sum(r.state == SectorState.CLEAR))
        seen["obstacle"] += int(np.sum(r.state == SectorState.OBSTACLE))
        seen["inferred"] += r.n_inferred
        if "inferred_vertical" in seen:
            seen["inferred_vertical"] += int(np.sum(r.inferred_vertical))
        else:  # neither rule on: none set by them
            assert not np.any(r.inferred_vertical)
        seen["remembered"] += int(np.sum(r.remembered_points))
        seen["rejected"] += r.points_rejected
        if config.corridor_far_ratio > 0:  # the far part of rule 10 acts in these scenes (else the comparison is idle)
            r0 = compute_sectors_reference(*args[:-1], dataclasses.replace(config, corridor_far_ratio=0.0), **opt, **kw)
            seen["far_capped"] = seen.get("far_capped", 0) + int(np.sum(r0.distances_cm != r.distances_cm))
        if config.sigma_k_taper_to_m > 0 and config.sigma_k_far < config.sigma_k:  # the taper moves claims here
            r0 = compute_sectors_reference(*args[:-1], dataclasses.replace(config, sigma_k_taper_to_m=0.0), **opt, **kw)
            both = (r0.state == SectorState.OBSTACLE) & (r.state == SectorState.OBSTACLE)
            seen["tapered"] = seen.get("tapered", 0) + int(np.sum(r0.distances_cm[both] != r.distances_cm[both]))
    # the scenes exercise what is compared (a vacuous comparison would pass anything)
    assert all(v > 0 for v in seen.values()), seen
    assert config.corridor_far_ratio == 0 or "far_capped" in seen
    assert not (config.sigma_k_taper_to_m > 0 and config.sigma_k_far < config.sigma_k) or "tapered" in seen


def _edge_scenes(c: SectorConfig):
    """(name, points, σ, nudge, ground): the first point lies exactly on a rule's edge (level flight:
    every quantity exact), ``nudge`` the direction that moves it off the edge; ground height, m."""
    h, w, far = c.band_half_height_m, c.infer_vertical_window_m, [[60.0, 0.0, 0.0], [61.0, 0.0, 0.0], [62.0, 0.0, 0.0]]
    up, reach = (0, 0, -1), c.infer_vertical_reach_m
    yield "max_distance", [[c.max_distance_m, 0.0, 0.0], *far], [0.0, 0.5, 0.5, 0.5], (1, 0, 0), -20.0
    yield "band edge", [[20.0, 0.0, -h]], [0.0], up, -20.0
    yield "band edge below", [[20.0, 0.0, h]], [0.0], (0, 0, 1), -20.0
    yield "window above", [[15.0, 0.0, -(h + w)], [15.0, 0.0, h + 1.0]], [0.0, 0.0], up, -20.0
    yield "window below", [[15.0, 0.0, h + w], [15.0, 0.0, -(h + 1.0)]], [0.0, 0.0], (0, 0, 1), -20.0
    yield "cap edge", [[12.0, 0.0, -(h + c.cap_above_m)], *far], [0.0, 0.5, 0.5, 0.5], up, -20.0
    yield "reach edge", [[10.0, 0.0, -(h + reach)], [10.0, 0.0, -(h + reach + 2.0)]], [0.0, 0.0], up, -20.0
    yield "extent edge", [[10.0, 0.0, -(h + 0.5)], [10.0, 0.0, -(h + 0.5 + c.infer_vertical_min_extent_m)]], [0.0, 0.0], \
        up, -20.0
    yield "ground margin", [[9.0, 0.0, 1.75 - c.ground_margin_m], [30.0, 0.0, 0.0]], [0.0, 0.0], (0, 0, 1), -1.75
    yield "vertical ground margin", [[15.0, 0.0, 5.0 - c.infer_vertical_ground_margin_m], [15.0, 0.0, -(h + 1.0)]], \
        [0.0, 0.0], (0, 0, 1), -5.0
    yield "consistent ranges", [[10.0 * (1 + c.infer_rel_tol), 0.0, h + 1.0], [10.0, 0.0, -(h + 1.0)]], [0.0, 0.0], \
        (1, 0, 0), -20.0


@pytest.mark.parametrize("variant", ["shipped", "one-sided off"])
def test_kernel_equals_reference_on_rule_edges(variant):
    """A point exactly on each rule's edge (≤ vs <): the kernel decides as the reference does.  Each
    scene is checked to be discriminating: moving the point off the edge by 1 µm changes the
    reference's sectors, so a kernel that got the edge wrong would differ."""
    c = dataclasses.replace(shipped_config(), sigma_k=0.0)
    if variant == "one-sided off":
        c = dataclasses.replace(c, infer_vertical_one_side=False)
    for name, pts, sig, nudge, ground in _edge_scenes(c):
        pts, sig = np.asarray(pts, float), np.asarray(sig, float)
        conv, val = np.ones(len(pts), bool), np.ones(len(pts), bool)
        opt = dict(vfov_rad=VFOV, ground_height_m=ground)
        r = compute_sectors_reference(pts, sig, conv, val, HFOV, 0.0, c, **opt)
        k = sectors_kernel(pts, sig, conv, val, HFOV, 0.0, c, **opt)
        assert_same_sectors(k, r, f"{variant}: {name}")
        moved = pts.copy()
        moved[0] += 1e-6 * np.asarray(nudge, float)
        r2 = compute_sectors_reference(moved, sig, conv, val, HFOV, 0.0, c, **opt)
        if variant == "shipped" or name not in ("reach edge", "extent edge"):
            assert not (np.array_equal(r.state, r2.state) and np.array_equal(r.distances_cm, r2.distances_cm)
                        and np.array_equal(r.inferred, r2.inferred)), f"{variant}: {name} is not on an edge"


def test_public_entry_dispatches_on_jit_enabled(monkeypatch):
    """compute_sectors runs the kernel when kernels are on and the reference when they are off."""
    calls = []
    monkeypatch.setattr(S, "_sectors_kernel", lambda *a: calls.append("kernel"))
    monkeypatch.setattr(S, "_sectors_reference", lambda *a: calls.append("reference"))
    p = np.array([[10.0, 0.0, 0.0]])
    monkeypatch.setattr(jit, "ENABLED", True)
    compute_sectors(p, [0.5], [True], [True], HFOV, 0.0)
    monkeypatch.setattr(jit, "ENABLED", False)
    compute_sectors(p, [0.5], [True], [True], HFOV, 0.0)
    assert calls == ["kernel", "reference"]


@pytest.mark.parametrize("case", ["empty", "empty with empty memory", "only memory", "one point", "all broken",
                                  "one remembered, spread", "far only"])
def test_kernel_edge_cases(case):
    """Inputs the reference handles: nothing, a single point, only broken points, only memory."""
    cfg = shipped_config()
    p, sig, conv, val, kw = np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool), np.zeros(0, bool), {}
    if case == "empty with empty memory":
        kw = dict(remembered_p_body=np.zeros((0, 3)), remembered_sigma=np.zeros(0), remembered_tangential_sigma=np.zeros(0))
    elif case == "only memory":
        kw = dict(remembered_p_body=[[5.0, 5.0, 0.0], [-8.0, 0.0, 0.5]], remembered_sigma=[0.2, 0.3],
                  remembered_tangential_sigma=[0.1, 0.2])
    elif case == "one point":
        p, sig, conv, val = np.array([[7.0, 0.3, 0.2]]), np.array([0.3]), np.ones(1, bool), np.ones(1, bool)
    elif case == "all broken":
        p = np.array([[np.nan, 0, 0], [0, 0, 0], [np.inf, 1, 1]])
        sig, conv, val = np.array([0.1, 0.1, np.nan]), np.ones(3, bool), np.ones(3, bool)
    elif case == "one remembered, spread":
        kw = dict(remembered_p_body=[[3.0, 0.5, 0.0]], remembered_sigma=[0.2], remembered_tangential_sigma=[1.5])
    elif case == "far only":
        p = np.array([[80.0, 0.0, 0.0], [90.0, 1.0, 0.0], [100.0, -1.0, 0.2]])
        sig, conv, val = np.full(3, 0.5), np.ones(3, bool), np.ones(3, bool)
    args = (p, sig, conv, val, HFOV, 0.0, cfg)
    rp = (0.0, 0.0) if case == "far only" else (0.05, -0.1)  # level, so the far points lie in the band
    opt = dict(roll_pitch_rad=rp, velocity_body=[3.0, 0.0, 0.0], vfov_rad=VFOV, ground_height_m=-10.0)
    k = sectors_kernel(*args, **opt, **kw)
    r = compute_sectors_reference(*args, **opt, **kw)
    assert_same_sectors(k, r, case)
    if case == "far only":
        assert np.any(r.state == SectorState.CLEAR)


def test_kernel_raises_what_the_reference_raises(monkeypatch):
    monkeypatch.setattr(jit, "ENABLED", True)
    p = np.array([[10.0, 0.0, 0.0]])
    for bad in (dict(hfov_rad=0.0), dict(hfov_rad=math.nan), dict(R_cam_body=np.full((3, 3), np.nan)),
                dict(R_cam_body=math.inf)):
        a = dict(hfov_rad=HFOV, R_cam_body=0.0) | bad
        with pytest.raises(InputError):
            compute_sectors(p, [0.5], [True], [True], a["hfov_rad"], a["R_cam_body"])
        with pytest.raises(InputError):
            compute_sectors_reference(p, [0.5], [True], [True], a["hfov_rad"], a["R_cam_body"])
    with pytest.raises(InputError):
        compute_sectors(p, [0.5, 1.0], [True], [True], HFOV, 0.0)


def test_reference_rules_directly():
    """The reference itself, called directly (it stays the documented behaviour): a wall at 10 m
    is an obstacle at 10 m − 2σ in the sectors it spans (its nearest point; fused with the other four
    points of sector 0, 10 m − 2σ̄); far points alone make a fully seen sector clear."""
    b = np.radians(np.arange(-20, 21, 1.0))
    wall = np.stack([np.full(b.shape, 10.0), 10.0 * np.tan(b), np.zeros(b.shape)], 1)
    args = (wall, np.full(len(b), 0.5), np.ones(len(b), bool), np.ones(len(b), bool), HFOV, 0.0)
    r = compute_sectors_reference(*args, SectorConfig(fuse_gate_k=0.0))
    assert r.state[0] == SectorState.OBSTACLE and r.distances_cm[0] == 900
    r = compute_sectors_reference(*args)
    d = (10.0 / np.cos(np.radians([-2, -1, 0, 1, 2]))).mean()  # ≈ 10.003 m (equal weights)
    rho = SectorConfig().fuse_correlation
    assert r.distances_cm[0] == pytest.approx(100 * (d - 2 * 0.5 * np.sqrt(rho + (1 - rho) / 5)), abs=1.0)
    assert np.all(r.state[[10, 36, 60]] == SectorState.UNKNOWN)
    far = np.array([[60.0, 0.0, 0.0], [61.0, 0.1, 0.0], [62.0, -0.1, 0.0]])
    r = compute_sectors_reference(far, np.full(3, 0.5), np.ones(3, bool), np.ones(3, bool), HFOV, 0.0)
    assert r.state[0] == SectorState.CLEAR and r.distances_cm[0] == r.clear_cm


@pytest.mark.skipif(not jit.ENABLED, reason="whole flight: compiled kernels only")
def test_kernel_equals_reference_on_a_flight(monkeypatch):
    """The pipeline's own inputs (live and remembered points, rocking attitude, ground known) on a
    short turning flight past a wall: every frame's sectors from the kernel equal the reference's."""
    import companion.pipeline as P
    from flight_inputs import fly

    frames = []

    def both(*a, **kw):
        k, r = compute_sectors(*a, **kw), compute_sectors_reference(*a, **kw)
        assert_same_sectors(k, r, f"frame {len(frames)}")
        out_of_view = r.remembered_points * ~r.in_view
        frames.append((r.n_inferred, int(np.sum(out_of_view)), int(np.sum(r.state == SectorState.OBSTACLE))))
        return k

    monkeypatch.setattr(P, "compute_sectors", both)
    fly(frames=75)
    assert len(frames) >= 70
    n_inferred, n_remembered, n_obstacle = np.sum(frames, axis=0)
    assert n_remembered > 0 and n_inferred > 0 and n_obstacle > 0, (n_inferred, n_remembered, n_obstacle)


def test_kernel_helpers_equal_the_reference_bit_for_bit():
    """The kernel path's level rotation (math instead of numpy) and view masks (cos / sin of the
    reference's own bearings) are the reference's exactly."""
    rng = np.random.default_rng(9)
    for _ in range(2000):
        roll, pitch = rng.normal(0, 0.5, 2)
        R = S._R_level_body(roll, pitch)
        assert np.array_equal(R, S.euler_zyx_to_R_scalar(roll, pitch, 0.0))
        g = rng.uniform(-0.5, 0.5)
        cam = mount_rotation(*rng.normal(0, 20, 3))
        hfov, vfov = rng.uniform(0.3, 2.5), rng.uniform(0.3, 2.0)
        ref = S.sector_view_masks(hfov, cam, roll_pitch_rad=(roll, pitch), flight_path_rad=g, vfov_rad=vfov)
        ker = SK._view_masks_kernel(math.tan(hfov / 2), math.tan(vfov / 2), True, R, cam, g)
        assert np.array_equal(ref[0], ker[0]) and np.array_equal(ref[1], ker[1])


def test_warm_up_is_registered():
    assert SK._warm_up in jit._WARMUPS
    SK._warm_up()  # runs on tiny inputs (compiled or not)
