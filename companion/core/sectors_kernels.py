"""Compiled kernels of the sectors (docs/derivations/sectors.md, docs/derivations/compute.md).

The same rules as the numpy reference :func:`companion.core.sectors._sectors_reference`, as loops
over points and sectors in numba kernels; used when :data:`companion.core.jit.ENABLED`.
:func:`companion.core.sectors._sectors_kernel` (the kernel path of ``compute_sectors``) makes the
reference's input checks, packs the configuration (:func:`_kernel_config`) and calls
:func:`_join_points_k`, :func:`_view_masks_kernel`, :func:`_usable_points_k` and :func:`_sectors_core`;
:func:`_infer_between_k`, :func:`_infer_narrow_k` and :func:`_vertical_pick_k` are the compiled forms of
the inference rules of :mod:`companion.core.sectors_infer`.

The levelled points are the reference's own (the same BLAS product, computed by the caller), so
ranges, heights and ties are bit-identical; what is computed otherwise agrees to an ulp: the
bearing (libm's atan2 here, numpy's loop there), the view directions and the body coordinates of
spread copies (a fixed order of summation here, BLAS there).  A sector decision could therefore
differ only for a point within an ulp of a sector edge; tests/test_sectors_kernel.py compares every
integer and flag array exactly on seeded scenes, points placed on every rule's edge and a flight
through the pipeline.
"""

from __future__ import annotations

import math

import numpy as np

from companion.core import jit as _jit
from companion.core.frames import euler_zyx_to_R_scalar, mount_rotation
from companion.core.sectors_types import _SAMPLES_PER_SECTOR, SECTOR_COUNT, SECTOR_DEG, UNKNOWN_CM, SectorConfig, SectorState

_S_UNKNOWN, _S_OBSTACLE, _S_CLEAR = int(SectorState.UNKNOWN), int(SectorState.OBSTACLE), int(SectorState.CLEAR)  # plain ints for numba
_DEG2RAD = math.pi / 180.0  # = numpy's radians() factor (NPY_PI / 180)
_RAD2DEG = 180.0 / math.pi  # = numpy's degrees() factor
_VIEW_OFFSETS = np.radians(np.linspace(-SECTOR_DEG / 2, SECTOR_DEG / 2, _SAMPLES_PER_SECTOR))

# indices into the packed configuration vector of the kernel (:func:`_kernel_config`)
(_K_MIN_M, _K_MAX_M, _K_SIGMA_K, _K_BAND_METRES, _K_HALF_H, _K_HALF_ANGLE_RAD, _K_TAN_HALF_ANGLE, _K_N_OBS, _K_N_CLR,
 _K_VETO, _K_TOUCH, _K_SPREAD_K, _K_MAX_SPREAD_RAD, _K_DROP_SPREAD_RAD, _K_GAP, _K_REL_TOL, _K_NARROW_M, _K_NARROW_N,
 _K_VERT, _K_VERT_WIN, _K_VERT_GROUND, _K_ONE_SIDE, _K_MIN_EXTENT, _K_REACH, _K_CAP, _K_GROUND_MARGIN, _K_MIN_CM,
 _K_MAX_CM, _K_FWD_HALF, _K_NEAREST, _K_FUSE_G, _K_FUSE_RHO, _K_EDGE, _K_CAP_GATE, _K_DROP_ACROSS, _K_UCAP, _K_LOS,
 _K_CORRIDOR, _K_VETO_MARGIN, _K_CVETO_MARGIN, _K_FAR_RATIO, _K_K_FAR, _K_TAPER_FROM, _K_TAPER_TO, _K_SIZE) = range(45)


def _kernel_config(config: SectorConfig) -> np.ndarray:
    """The ``[sectors]`` numbers the kernel reads, packed (angles converted as the reference does);
    computed once per config object."""
    got = _KERNEL_CONFIGS.get(id(config))
    if got is not None and got[0] is config:
        return got[1]
    c = config
    v = np.zeros(_K_SIZE)
    v[[_K_MIN_M, _K_MAX_M, _K_SIGMA_K, _K_HALF_H, _K_TOUCH, _K_SPREAD_K, _K_REL_TOL, _K_NARROW_M, _K_VERT_WIN,
       _K_VERT_GROUND, _K_MIN_EXTENT, _K_REACH, _K_CAP, _K_GROUND_MARGIN, _K_FWD_HALF]] = (
        c.min_distance_m, c.max_distance_m, c.sigma_k, c.band_half_height_m, c.touching_distance_m,
        c.remembered_spread_k, c.infer_rel_tol, c.infer_narrow_gap_m, c.infer_vertical_window_m,
        c.infer_vertical_ground_margin_m, c.infer_vertical_min_extent_m, c.infer_vertical_reach_m, c.cap_above_m,
        c.ground_margin_m, c.forward_half_width_deg)
    v[_K_BAND_METRES] = c.band_mode == "metres"
    v[_K_HALF_ANGLE_RAD] = math.radians(c.band_half_angle_deg)
    v[_K_TAN_HALF_ANGLE] = math.tan(math.radians(c.band_half_angle_deg))
    v[_K_N_OBS], v[_K_N_CLR], v[_K_NEAREST] = c.min_points_obstacle, c.min_points_clear, c.nearest_count
    v[_K_VETO], v[_K_VERT], v[_K_ONE_SIDE] = c.unconverged_veto_clear, c.infer_vertical, c.infer_vertical_one_side
    v[_K_MAX_SPREAD_RAD] = math.radians(c.remembered_max_spread_deg)
    v[_K_DROP_SPREAD_RAD] = math.radians(c.remembered_drop_spread_deg)
    v[_K_DROP_ACROSS] = c.remembered_drop_across_only
    v[_K_GAP], v[_K_NARROW_N] = c.infer_max_gap_sectors, c.infer_narrow_max_sectors
    v[_K_MIN_CM], v[_K_MAX_CM] = c.min_distance_cm, c.max_distance_cm
    v[_K_FUSE_G], v[_K_FUSE_RHO] = c.fuse_gate_k, c.fuse_correlation
    v[_K_EDGE] = c.clear_edge_margin_deg
    v[_K_CAP_GATE] = c.cap_gate_k
    v[_K_UCAP] = c.unconverged_cap_k
    v[_K_VETO_MARGIN] = c.unconverged_veto_margin_m
    v[_K_CVETO_MARGIN] = c.converged_veto_margin_m
    v[_K_LOS] = c.clear_line_of_sight and c.band_mode == "metres"
    v[_K_CORRIDOR] = c.clear_corridor_m
    v[_K_FAR_RATIO] = c.corridor_far_ratio
    v[_K_K_FAR], v[_K_TAPER_FROM], v[_K_TAPER_TO] = c.sigma_k_far, c.sigma_k_taper_from_m, c.sigma_k_taper_to_m
    v.flags.writeable = False
    _KERNEL_CONFIGS[id(config)] = (config, v)  # the config is kept alive with its id: no reuse while cached
    if len(_KERNEL_CONFIGS) > 64:  # bounded: configs are few (one per process, a handful in tests)
        _KERNEL_CONFIGS.pop(next(iter(_KERNEL_CONFIGS)))
    return v


_KERNEL_CONFIGS: dict[int, tuple[SectorConfig, np.ndarray]] = {}

# the bearings of sector_view_masks (centres + offsets) and their cos / sin, by numpy as the reference computes them
_VIEW_BETA = np.radians(np.arange(SECTOR_COUNT) * SECTOR_DEG)[:, None] + _VIEW_OFFSETS[None, :]
_VIEW_COS, _VIEW_SIN = np.cos(_VIEW_BETA), np.sin(_VIEW_BETA)


@_jit.njit
def _join_points_k(p, sig, conv, val, mp, ms, mt):
    """Live then remembered points as the reference joins them: remembered ones converged, valid when
    finite with a finite σ_t ≥ 0; their σ_t (0 where not finite)."""
    n, m = p.shape[0], mp.shape[0]
    P = np.empty((n + m, 3))
    S = np.empty(n + m)
    C = np.empty(n + m, np.bool_)
    V = np.empty(n + m, np.bool_)
    mem_tan = np.empty(m)
    for i in range(n):
        P[i, 0], P[i, 1], P[i, 2], S[i], C[i], V[i] = p[i, 0], p[i, 1], p[i, 2], sig[i], conv[i], val[i]
    for q in range(m):
        i = n + q
        P[i, 0], P[i, 1], P[i, 2], S[i], C[i] = mp[q, 0], mp[q, 1], mp[q, 2], ms[q], True
        V[i] = (math.isfinite(mp[q, 0]) and math.isfinite(mp[q, 1]) and math.isfinite(mp[q, 2]) and math.isfinite(mt[q])
                and mt[q] >= 0)
        mem_tan[q] = mt[q] if math.isfinite(mt[q]) else 0.0
    return P, S, C, V, mem_tan


@_jit.njit
def _view_masks_kernel(tan_h, tan_v, has_v, R_lb, R_cb, gamma):
    """:func:`sector_view_masks` at the band centre (elevation ``gamma``): ``(in_view, fully_in_view)``."""
    in_view = np.zeros(SECTOR_COUNT, np.bool_)
    fully = np.ones(SECTOR_COUNT, np.bool_)
    cg, sg = math.cos(gamma), math.sin(gamma)
    eps = 1e-9
    dl = np.empty(3)
    db = np.empty(3)
    for i in range(SECTOR_COUNT):
        for s in range(_VIEW_OFFSETS.size):
            dl[0], dl[1], dl[2] = cg * _VIEW_COS[i, s], cg * _VIEW_SIN[i, s], -sg
            for j in range(3):  # levelled → body: d_level @ R_level_body
                db[j] = dl[0] * R_lb[0, j] + dl[1] * R_lb[1, j] + dl[2] * R_lb[2, j]
            x = db[0] * R_cb[0, 0] + db[1] * R_cb[0, 1] + db[2] * R_cb[0, 2]
            y = db[0] * R_cb[1, 0] + db[1] * R_cb[1, 1] + db[2] * R_cb[1, 2]
            z = db[0] * R_cb[2, 0] + db[1] * R_cb[2, 1] + db[2] * R_cb[2, 2]
            inside = z > eps and abs(x) <= tan_h * z + eps
            if has_v:
                inside = inside and abs(y) <= tan_v * z + eps
            if inside:
                in_view[i] = True
            else:
                fully[i] = False
    return in_view, fully


@_jit.njit
def _sector_of(bearing):
    """:func:`sector_index` of one bearing (rad): round half to even of degrees / 5, on the ring."""
    return np.int64(np.rint(bearing * _RAD2DEG / SECTOR_DEG)) % SECTOR_COUNT


@_jit.njit
def _across_edge(bearing, sector, half_deg):
    """The sector across the nearer edge of ``sector`` when ``bearing`` (rad) lies more than ``half_deg`` from its
    centre, else −1 (``sectors._edge_vetoes`` for one point)."""
    off = (bearing * _RAD2DEG - sector * SECTOR_DEG + 180.0) % 360.0 - 180.0
    if off > half_deg:
        return (sector + 1) % SECTOR_COUNT
    if off < -half_deg:
        return (sector - 1) % SECTOR_COUNT
    return -1


@_jit.njit
def _corridor_reach(range_m, corridor_m):
    """How many neighbours on each side an obstacle sector at ``range_m`` keeps from "clear" (``sectors._corridor``
    for one sector): the j-th when 5(j − 1) < asin(corridor / range), degrees; at most 36."""
    r = range_m if range_m == range_m else 0.0  # NaN: the widest
    mu = math.degrees(math.asin(min(1.0, corridor_m / max(r, 1e-9))))
    return np.int64(min(math.ceil(mu / SECTOR_DEG), SECTOR_COUNT // 2))


@_jit.njit
def _line_distance_k(a0, a1, b0, b1, bearing):
    """:func:`_line_distance` for one bearing."""
    u0, u1 = b0 - a0, b1 - a1
    den = math.cos(bearing) * u1 - math.sin(bearing) * u0
    num = a0 * u1 - a1 * u0
    if den == 0.0:
        return np.inf
    t = num / den
    if math.isfinite(t) and t > 0:
        return t
    return np.inf


@_jit.njit
def _usable_points_k(p, sig, val):
    """Per point: usable (finite, σ ≥ 0, range > 0, valid), its range |p| and the count of valid points rejected."""
    n = p.shape[0]
    usable = np.zeros(n, np.bool_)
    r = np.zeros(n)
    rejected = 0
    for i in range(n):
        x, y, z, s = p[i, 0], p[i, 1], p[i, 2], sig[i]
        finite = math.isfinite(x) and math.isfinite(y) and math.isfinite(z) and math.isfinite(s) and s >= 0
        r[i] = math.sqrt(x * x + y * y + z * z) if finite else 0.0  # numpy's norm: ((x² + y²) + z²)
        ok = finite and r[i] > 1e-9
        if val[i] and not ok:
            rejected += 1
        usable[i] = ok and val[i]
    return usable, r, rejected


@_jit.njit
def _sectors_core(p_in, sig_in, conv_in, usable_in, r_in, pl_in, n_live, mem_tan, R_lb, in_view, fully, gamma, tan_gamma, ground,
                  ground_known, cfg):
    """Every rule of :func:`_sectors_reference` after the view masks and the levelled points
    (docs/derivations/sectors.md), in the same order."""
    n_in = p_in.shape[0]
    min_m, max_m = cfg[_K_MIN_M], cfg[_K_MAX_M]
    min_cm, max_cm = np.int64(cfg[_K_MIN_CM]), np.int64(cfg[_K_MAX_CM])
    k = np.int64(cfg[_K_N_OBS])
    usable_in = usable_in.copy()

    # ---- remembered points spread over their bearing uncertainty (_spread_remembered) ------------
    m = n_in - n_live
    spread_J = np.zeros(max(m, 0), np.int64)
    spread_w = np.zeros(max(m, 0))
    any_spread = False
    if mem_tan.size:
        half = (SECTOR_DEG / 2) * _DEG2RAD
        for q in range(m):
            i = n_live + q
            dh = np.hypot(pl_in[i, 0], pl_in[i, 1])
            w_raw = cfg[_K_SPREAD_K] * mem_tan[q] / max(dh, 1e-6)
            if not (w_raw <= cfg[_K_DROP_SPREAD_RAD]) and (cfg[_K_DROP_ACROSS] == 0.0 or not (mem_tan[q] <= sig_in[i])):
                usable_in[i] = False  # bearing too uncertain (across the line of sight): not published
            w = min(w_raw, cfg[_K_MAX_SPREAD_RAD])
            spread_w[q] = w
            if usable_in[i] and w > half:
                spread_J[q] = np.int64(math.ceil(w / (SECTOR_DEG * _DEG2RAD)))
                any_spread = True
    if any_spread:
        n = n_live
        for q in range(m):
            n += 2 * spread_J[q] + 1
    else:
        n = n_in
    p = np.empty((n, 3))
    pl = np.empty((n, 3))
    sig = np.empty(n)
    conv = np.empty(n, np.bool_)
    usable = np.empty(n, np.bool_)
    mem = np.zeros(n, np.bool_)
    r = np.empty(n)
    n_copy = n_live if any_spread else n_in
    for i in range(n_copy):
        for j in range(3):
            p[i, j] = p_in[i, j]
            pl[i, j] = pl_in[i, j]
        sig[i], conv[i], usable[i], r[i] = sig_in[i], conv_in[i], usable_in[i], r_in[i]
        mem[i] = i >= n_live
    if any_spread:
        o = n_live
        for q in range(m):
            i = n_live + q
            J = spread_J[q]
            for jj in range(-J, J + 1):
                off = spread_w[q] * jj / max(J, 1) if J > 0 else 0.0
                c, s_ = math.cos(off), math.sin(off)
                q0, q1, q2 = pl_in[i, 0], pl_in[i, 1], pl_in[i, 2]
                pl[o, 0], pl[o, 1], pl[o, 2] = c * q0 - s_ * q1, s_ * q0 + c * q1, q2
                for j in range(3):  # levelled → body: q_level @ R_level_body
                    p[o, j] = pl[o, 0] * R_lb[0, j] + pl[o, 1] * R_lb[1, j] + pl[o, 2] * R_lb[2, j]
                sig[o], conv[o], usable[o], r[o], mem[o] = sig_in[i], conv_in[i], usable_in[i], r_in[i], True
                o += 1

    # ---- per point: band, sector, conservative range ----------------------------------------------
    ground_cut = ground_known and cfg[_K_GROUND_MARGIN] > 0
    metres = cfg[_K_BAND_METRES] != 0
    d_h = np.empty(n)
    height = np.empty(n)
    off_b = np.empty(n)
    lim = np.empty(n)
    bearing = np.empty(n)
    idx = np.empty(n, np.int64)
    in_band = np.empty(n, np.bool_)
    seen = np.empty(n, np.bool_)  # in a sector in view, or remembered
    r_cons = np.empty(n)
    r_safe = np.empty(n)
    d_cons = np.empty(n)
    near = np.empty(n, np.bool_)
    n_tracked = np.zeros(SECTOR_COUNT, np.int64)  # live points in view at any height, the ground's too ("why unknown")
    taper = cfg[_K_TAPER_TO] > 0
    for i in range(n):
        d_h[i] = np.hypot(pl[i, 0], pl[i, 1])
        height[i] = -pl[i, 2]
        tracked = usable[i] and not mem[i]  # before the ground cut: the ground's points are tracked too
        if ground_cut and not (height[i] >= ground + cfg[_K_GROUND_MARGIN]):
            usable[i] = False
        r_safe[i] = r[i] if usable[i] else 1.0
        off_b[i] = height[i] - d_h[i] * tan_gamma
        if metres:
            lim[i] = cfg[_K_HALF_H]
            band = abs(off_b[i]) <= lim[i]
        else:
            lim[i] = d_h[i] * cfg[_K_TAN_HALF_ANGLE]
            band = abs(math.atan2(height[i], d_h[i]) - gamma) <= cfg[_K_HALF_ANGLE_RAD]
        bearing[i] = math.atan2(pl[i, 1], pl[i, 0])
        idx[i] = _sector_of(bearing[i])
        if tracked and in_view[idx[i]]:
            n_tracked[idx[i]] += 1
        seen[i] = in_view[idx[i]] or mem[i]
        in_band[i] = band and usable[i] and seen[i]
        r_cons[i] = max(r[i] - cfg[_K_SIGMA_K] * (sig[i] if usable[i] else 0.0), 0.0)
        d_cons[i] = d_h[i] * (r_cons[i] / r_safe[i])
        near[i] = d_cons[i] <= max_m

    # ---- per sector: counts, n-th nearest obstacle point -----------------------------------------
    veto_on = cfg[_K_VETO] != 0
    los_on = cfg[_K_LOS] != 0
    sig_pub, est = sig, d_h  # published σ and estimate of each point: its own unless fused
    fused = np.zeros(n, np.bool_)
    if cfg[_K_FUSE_G] > 0:
        sig_pub, est = sig.copy(), d_h.copy()
        _fuse_nearest_surface_k(idx, d_h, sig, r_safe, d_cons, in_band & conv & near & ~mem, cfg[_K_FUSE_G],
                                cfg[_K_FUSE_RHO], cfg[_K_SIGMA_K], max_m, sig_pub, est, fused)
    n_obs = np.zeros(SECTOR_COUNT, np.int64)
    n_clr = np.zeros(SECTOR_COUNT, np.int64)
    n_veto = np.zeros(SECTOR_COUNT, np.int64)
    n_mem = np.zeros(SECTOR_COUNT, np.int64)
    n_ranging = np.zeros(SECTOR_COUNT, np.int64)  # unconverged live points in the band ("why unknown")
    obs_pts = np.zeros(n, np.bool_)
    used = 0
    edge_half = SECTOR_DEG / 2 - cfg[_K_EDGE]  # a point beyond this from its sector's centre vetoes "clear" next door
    margin_u = cfg[_K_VETO_MARGIN] if veto_on and cfg[_K_VETO_MARGIN] > 0 else -np.inf  # veto margins beside the band
    margin_c = cfg[_K_CVETO_MARGIN] if cfg[_K_CVETO_MARGIN] > 0 else -np.inf  # (−inf: off)
    for i in range(n):
        claims = False  # claims or vetoes its own sector
        if in_band[i] and not conv[i] and not mem[i]:
            n_ranging[idx[i]] += 1
        if in_band[i] and conv[i]:
            used += 1
            if near[i]:
                obs_pts[i] = True
                n_obs[idx[i]] += 1
                claims = True
                if mem[i]:
                    n_mem[idx[i]] += 1
            elif not mem[i]:
                n_clr[idx[i]] += 1
        elif near[i] and ((in_band[i] and veto_on) or (  # unconverged in the band (the branch above took the converged)
                usable[i] and seen[i] and not in_band[i] and abs(off_b[i]) <= lim[i] + (margin_c if conv[i] else margin_u)
                and not (conv[i] and off_b[i] > lim[i] and off_b[i] <= lim[i] + cfg[_K_CAP]))):
            n_veto[idx[i]] += 1  # … or just beside it, up to its kind's margin, outside the cap's zone (rule 3)
            claims = True
        elif (los_on and conv[i] and not near[i] and not mem[i] and usable[i] and in_view[idx[i]]
              and abs(off_b[i]) * max_m <= lim[i] * d_h[i]):
            n_clr[idx[i]] += 1  # its line of sight runs inside the band out to max_distance (rule 3)
        if claims and cfg[_K_EDGE] > 0:  # a surface goes on past its last corner: no "clear" just across an edge
            j = _across_edge(bearing[i], idx[i], edge_half)
            if j >= 0:
                n_veto[j] += 1
    sel = np.flatnonzero(obs_pts)
    starts, ranked = _rank_in_sectors(idx, d_cons, sel)
    pick = np.full(SECTOR_COUNT, -1, np.int64)
    nearest_pick = np.full(SECTOR_COUNT, -1, np.int64)
    for s in range(SECTOR_COUNT):
        if n_obs[s] >= k:
            pick[s] = ranked[starts[s] + k - 1]
        if n_obs[s] >= 1:
            nearest_pick[s] = ranked[starts[s]]

    state = np.full(SECTOR_COUNT, _S_UNKNOWN, np.int8)
    dist = np.full(SECTOR_COUNT, UNKNOWN_CM, np.int64)
    range_m = np.full(SECTOR_COUNT, np.nan)
    sigma_m = np.full(SECTOR_COUNT, np.nan)
    d_pub = np.empty(n)
    pt_cm = np.empty(n, np.int64)
    touch = cfg[_K_TOUCH]
    for i in range(n):
        d_pub[i], pt_cm[i] = _published_k(d_cons[i], d_h[i], min_m, max_m, min_cm, max_cm, touch)
    # the values published: tapered far away when the taper is on (sectors._tapered_values)
    d_pub_t, pt_cm_t, r_cons_t = d_pub, pt_cm, r_cons
    if taper:
        d_pub_t, pt_cm_t, r_cons_t = np.empty(n), np.empty(n, np.int64), np.empty(n)
        for i in range(n):
            r_cons_t[i] = max(r[i] - _k_at_k(d_h[i], cfg) * (sig[i] if usable[i] else 0.0), 0.0)
            d_t = d_h[i] * (r_cons_t[i] / r_safe[i])
            if fused[i]:
                d_t = min(max(est[i] - _k_at_k(est[i], cfg) * sig_pub[i], 0.0), max_m)
            d_pub_t[i], pt_cm_t[i] = _published_k(d_t, d_h[i], min_m, max_m, min_cm, max_cm, touch)
    xy_m = np.full((SECTOR_COUNT, 2), np.nan)
    has_obs = n_obs >= k
    for s in range(SECTOR_COUNT):
        if has_obs[s]:
            pt = pick[s]
            dist[s] = pt_cm[pt]
            state[s] = _S_OBSTACLE
            range_m[s] = d_pub[pt]
            sigma_m[s] = sig_pub[pt]
            xy_m[s, 0] = d_pub[pt] * math.cos(bearing[pt])
            xy_m[s, 1] = d_pub[pt] * math.sin(bearing[pt])
        elif fully[s] and n_obs[s] == 0 and n_veto[s] == 0 and n_clr[s] >= cfg[_K_N_CLR]:
            dist[s] = max_cm + 1
            state[s] = _S_CLEAR

    inferred = _infer_between_k(state, dist, range_m, sigma_m, np.int64(cfg[_K_GAP]), cfg[_K_REL_TOL])
    narrow = _infer_narrow_k(state, dist, range_m, sigma_m, xy_m, ~inferred, np.int64(cfg[_K_NARROW_N]), cfg[_K_NARROW_M],
                             min_m, max_m, min_cm, max_cm)
    inferred |= narrow
    vertical = np.zeros(SECTOR_COUNT, np.bool_)  # set by a rule on points above or below the band (vertical, cap)

    if cfg[_K_VERT] != 0:
        # a structure standing through the band: the nearer point of consistent pairs above and below it
        win = cfg[_K_VERT_WIN]
        above = np.zeros(n, np.bool_)
        below = np.zeros(n, np.bool_)
        for i in range(n):
            span = usable[i] and conv[i] and near[i] and seen[i]
            above[i] = span and off_b[i] > lim[i] and off_b[i] <= lim[i] + win
            below[i] = span and off_b[i] < -lim[i] and off_b[i] >= -lim[i] - win
            if ground_known and below[i]:
                below[i] = height[i] >= ground + cfg[_K_VERT_GROUND]
        vpick = _vertical_pick_k(idx, d_cons, off_b, lim, above, below, cfg[_K_REL_TOL], cfg[_K_ONE_SIDE] != 0,
                                 cfg[_K_MIN_EXTENT], cfg[_K_REACH])
        for s in range(SECTOR_COUNT):
            pt = vpick[s]
            if pt >= 0 and (not has_obs[s] or (d_pub[pt] < range_m[s] and
                                               _nearer_surface_k(d_h[pt], sig[pt], range_m[s], sigma_m[s], cfg))):
                state[s] = _S_OBSTACLE
                dist[s], range_m[s], sigma_m[s] = pt_cm[pt], d_pub[pt], sig[pt]
                inferred[s] = True
                vertical[s] = True
                pick[s] = pt

    if cfg[_K_CAP] > 0:
        # the nearest converged point just above the band caps what its sector claims (only nearer, never clear)
        cap = np.full(SECTOR_COUNT, -1, np.int64)
        for i in range(n):
            if usable[i] and conv[i] and near[i] and seen[i] and off_b[i] > lim[i] and off_b[i] <= lim[i] + cfg[_K_CAP]:
                s = idx[i]
                if cap[s] < 0 or d_cons[i] < d_cons[cap[s]]:
                    cap[s] = i
        for s in range(SECTOR_COUNT):
            pt = cap[s]
            if pt < 0:
                continue
            if state[s] == _S_CLEAR or (state[s] == _S_OBSTACLE and d_pub[pt] < range_m[s] and
                                        _nearer_surface_k(d_h[pt], sig[pt], range_m[s], sigma_m[s], cfg)):
                state[s] = _S_OBSTACLE
                dist[s], range_m[s], sigma_m[s] = pt_cm[pt], d_pub[pt], sig[pt]
                inferred[s] = True
                vertical[s] = True
                pick[s] = pt

    if cfg[_K_UCAP] > 0:
        # a point not yet converged bounds its obstacle sector's claim from above (only nearer, never clear)
        kk = cfg[_K_UCAP]
        ubest = np.full(SECTOR_COUNT, -1, np.int64)
        ud = np.full(SECTOR_COUNT, np.inf)
        for i in range(n):
            if in_band[i] and not conv[i] and not mem[i] and kk * sig[i] < r_safe[i]:
                d_up = d_h[i] / (1.0 - kk * sig[i] / r_safe[i])
                s = idx[i]
                if ubest[s] < 0 or d_up < ud[s]:
                    ubest[s], ud[s] = i, d_up
        for s in range(SECTOR_COUNT):
            pt = ubest[s]
            if pt >= 0 and state[s] == _S_OBSTACLE and ud[s] < range_m[s]:
                range_m[s] = min(max(ud[s], min_m), max_m)
                dist[s] = min(max(np.int64(np.rint(range_m[s] * 100)), min_cm), max_cm)
                sigma_m[s] = sig[pt] * d_h[pt] / r_safe[pt]
                pick[s] = -1
                inferred[s] = True

    if cfg[_K_FAR_RATIO] > 0:
        # no far claim beside a near obstacle either (rule 10's far part; sectors._corridor_far): from the claims as
        # they stand, each capped at the nearest obstacle sector whose corridor reaches it
        src_far = np.full(SECTOR_COUNT, -1, np.int64)
        best_far = np.full(SECTOR_COUNT, np.inf)
        for s in range(SECTOR_COUNT):
            if state[s] == _S_OBSTACLE:
                rs = range_m[s] if range_m[s] == range_m[s] else 0.0
                reach = _corridor_reach(range_m[s], cfg[_K_CORRIDOR])
                for j in range(1, reach + 1):
                    for d in ((s + j) % SECTOR_COUNT, (s - j) % SECTOR_COUNT):
                        if state[d] == _S_OBSTACLE and range_m[d] > cfg[_K_FAR_RATIO] * rs and rs < best_far[d]:
                            best_far[d], src_far[d] = rs, s
        r0, d0, s0 = range_m.copy(), dist.copy(), sigma_m.copy()
        for d in range(SECTOR_COUNT):
            s = src_far[d]
            if s >= 0 and not in_view[d]:  # out of view only
                range_m[d], dist[d], sigma_m[d] = r0[s], d0[s], s0[s]
                pick[d] = -1
                inferred[d] = True

    if cfg[_K_CORRIDOR] > 0:
        # no "clear" beside a near obstacle claim: the neighbours within asin(corridor / range) of its sector's edges
        veto_c = np.zeros(SECTOR_COUNT, np.bool_)
        for s in range(SECTOR_COUNT):
            if state[s] == _S_OBSTACLE:
                reach = _corridor_reach(range_m[s], cfg[_K_CORRIDOR])
                for j in range(1, reach + 1):
                    veto_c[(s + j) % SECTOR_COUNT] = True
                    veto_c[(s - j) % SECTOR_COUNT] = True
        for s in range(SECTOR_COUNT):
            if veto_c[s] and state[s] == _S_CLEAR:
                state[s] = _S_UNKNOWN
                dist[s] = UNKNOWN_CM

    if taper:
        # every rule above decided with the full margin; a sector claimed by a point (or a fused surface) takes that
        # point's tapered value (states, picks and σ unchanged)
        for s in range(SECTOR_COUNT):
            if state[s] == _S_OBSTACLE and pick[s] >= 0:
                range_m[s], dist[s] = d_pub_t[pick[s]], pt_cm_t[pick[s]]

    # ---- forward window (DISTANCE_SENSOR) ---------------------------------------------------------
    fwd_state = _S_UNKNOWN
    fwd_vals = np.full(3, np.nan)
    j_best = -1
    n_fwd = 0
    all_clear = True
    for s in range(SECTOR_COUNT):
        rel = (s * SECTOR_DEG + 180.0) % 360.0 - 180.0
        if abs(rel) <= cfg[_K_FWD_HALF] + 1e-9:
            n_fwd += 1
            if state[s] == _S_OBSTACLE:
                if j_best < 0 or range_m[s] < range_m[j_best]:
                    j_best = s
            if state[s] != _S_CLEAR:
                all_clear = False
    if j_best >= 0:
        fwd_state = _S_OBSTACLE
        pt = pick[j_best]
        fwd_vals[0] = range_m[j_best]
        if pt >= 0:
            fwd_vals[1], fwd_vals[2] = sig_pub[pt], est[pt]
        else:
            fwd_vals[1] = sigma_m[j_best]
    elif n_fwd > 0 and all_clear:
        fwd_state = _S_CLEAR
        fwd_vals[0] = (max_cm + 1) / 100.0

    # ---- nearest obstacles, one per sector (OBSTACLE_DISTANCE_3D) -------------------------------
    cand = np.flatnonzero(n_obs > 0)
    pts = nearest_pick[cand]
    order3 = np.argsort(d_cons[pts], kind="mergesort")[: np.int64(cfg[_K_NEAREST])]
    near_p = np.empty((order3.size, 3))
    near_vals = np.empty((order3.size, 2))
    near_sector = np.empty(order3.size, np.int64)
    for q in range(order3.size):
        pt = pts[order3[q]]
        rc = min_m if min_m > r_cons_t[pt] else r_cons_t[pt]  # Python's max(r_cons, min_distance_m)
        scale = rc / r_safe[pt]
        for j in range(3):
            near_p[q, j] = p[pt, j] * scale
        near_vals[q, 0], near_vals[q, 1] = rc, sig[pt]
        near_sector[q] = cand[order3[q]]

    # ---- obstacle points behind the claims, for re-binning in Sectors.rotated ---------------------
    n_inf = 0
    for s in range(SECTOR_COUNT):
        if inferred[s]:
            n_inf += 1
    ob_bearing = np.empty(sel.size + n_inf * k)
    ob_cm = np.empty(sel.size + n_inf * k, np.int64)
    for q in range(sel.size):
        ob_bearing[q], ob_cm[q] = bearing[sel[q]], pt_cm_t[sel[q]]
    o = sel.size
    for s in range(SECTOR_COUNT):
        if inferred[s]:
            for _ in range(k):
                ob_bearing[o], ob_cm[o] = (s * SECTOR_DEG) * _DEG2RAD, dist[s]
                o += 1
    return (dist, state, range_m, sigma_m, n_obs, n_clr, n_mem, inferred, used, ob_bearing, ob_cm, fwd_state, fwd_vals, near_p,
            near_vals, near_sector, vertical, n_veto, n_ranging, n_tracked)


@_jit.njit(inline="always")
def _rank_in_sectors(idx, value, sel):
    """Points ``sel`` grouped by sector, each group by ``value`` (ties by index: the reference's
    lexsort): (starts (73,), ranked): sector s holds ``ranked[starts[s]:starts[s + 1]]``."""
    order = sel[np.argsort(value[sel], kind="mergesort")]
    starts = np.zeros(SECTOR_COUNT + 1, np.int64)
    for i in order:
        starts[idx[i] + 1] += 1
    for s in range(SECTOR_COUNT):
        starts[s + 1] += starts[s]
    fill = starts[:SECTOR_COUNT].copy()
    ranked = np.empty(sel.size, np.int64)
    for i in order:
        ranked[fill[idx[i]]] = i
        fill[idx[i]] += 1
    return starts, ranked


@_jit.njit
def _fuse_nearest_surface_k(idx, d_h, sig, r_safe, d_cons, cand, gate_k, rho, sigma_k, max_m, sig_pub, est, fused):
    """:func:`companion.core.sectors._fuse_nearest_surface` in place on ``d_cons``, ``sig_pub``, ``est`` and ``fused``
    (docs/derivations/sectors.md, "Nearest surface"); sums in the reference's order (sector, then
    conservative range, ties by index) so the results are the same to the bit."""
    sel = np.flatnonzero(cand)
    if sel.size < 2:
        return
    count, ranked = _rank_in_sectors(idx, d_cons, sel)
    member = np.zeros(sel.size, np.bool_)
    for s in range(SECTOR_COUNT):
        lo, hi = count[s], count[s + 1]
        if hi - lo < 2:
            continue
        a = ranked[lo]
        s_a = max(sig[a] * d_h[a] / r_safe[a], 1e-9)
        n_m = 0
        sw = 0.0
        swd = 0.0
        sis = 0.0
        for q in range(lo, hi):
            i = ranked[q]
            s_i = max(sig[i] * d_h[i] / r_safe[i], 1e-9)
            member[q] = abs(d_h[i] - d_h[a]) <= gate_k * np.hypot(s_i, s_a)
            if member[q]:
                w = 1.0 / (s_i * s_i)
                n_m += 1
                sw += w
                swd += w * d_h[i]
                sis += 1.0 / s_i
        if n_m < 2:
            continue
        d_bar = swd / sw
        s_bar = math.sqrt(((1.0 - rho) * sw + rho * (sis * sis)) / (sw * sw))
        value = min(max(d_bar - sigma_k * s_bar, 0.0), max_m)
        for q in range(lo, hi):
            if member[q]:
                i = ranked[q]
                d_cons[i], sig_pub[i], est[i] = value, s_bar, d_bar
                fused[i] = True


@_jit.njit(inline="always")
def _nearer_surface_k(est_m, sigma, range_m, sigma_m, cfg):
    """:func:`companion.core.sectors._nearer_surface` for one point and its sector."""
    g = cfg[_K_CAP_GATE]
    if g <= 0:
        return True
    return not (est_m + g * math.hypot(sigma, sigma_m) >= range_m + cfg[_K_SIGMA_K] * sigma_m)


@_jit.njit(inline="always")
def _published_k(d_cons, d_h, min_m, max_m, min_cm, max_cm, touch):
    """:func:`companion.core.sectors._published` for one point: (metres, cm)."""
    d_pub = min(max(d_cons, min_m), max_m)
    cm = min(max(np.int64(np.rint(d_pub * 100)), min_cm), max_cm)
    if touch > 0 and d_h <= touch:
        cm = np.int64(0)
    return d_pub, cm


@_jit.njit(inline="always")
def _k_at_k(d, cfg):
    """:func:`companion.core.sectors_types.margin_k` with the kernel's config: the same expression in the
    same order (docs/derivations/sectors.md, "The margin's taper")."""
    k0 = cfg[_K_SIGMA_K]
    to = cfg[_K_TAPER_TO]
    if not to > 0:
        return k0
    fr = cfg[_K_TAPER_FROM]
    k1 = min(cfg[_K_K_FAR], k0)
    frac = 1.0 if d != d else min(max((d - fr) / (to - fr), 0.0), 1.0)
    return k0 + (k1 - k0) * frac


@_jit.njit
def _infer_between_k(state, dist, range_m, sigma_m, G, rel_tol):
    """:func:`_infer_between` (in place; returns the inferred mask)."""
    inferred = np.zeros(SECTOR_COUNT, np.bool_)
    if G == 0:
        return inferred
    obs = state == _S_OBSTACLE
    unk = state == _S_UNKNOWN
    for gap in range(1, G + 1):
        for i in range(SECTOR_COUNT):
            jr = (i + gap + 1) % SECTOR_COUNT
            if not (obs[i] and obs[jr]):
                continue
            between = True
            for a in range(1, gap + 1):
                between = between and unk[(i + a) % SECTOR_COUNT]
            if not between:
                continue
            rl, rr = range_m[i], range_m[jr]
            if not (abs(rl - rr) <= rel_tol * min(rl, rr)):
                continue
            near = i if range_m[i] <= range_m[jr] else jr
            d = min(dist[i], dist[jr])
            sg = sigma_m[jr] if sigma_m[jr] > sigma_m[i] else sigma_m[i]  # Python's max(sigma_m[i], sigma_m[jr])
            for a in range(1, gap + 1):
                f = (i + a) % SECTOR_COUNT
                if inferred[f]:
                    continue
                state[f] = _S_OBSTACLE
                dist[f] = d
                range_m[f] = range_m[near]
                sigma_m[f] = sg
                inferred[f] = True
    return inferred


@_jit.njit
def _infer_narrow_k(state, dist, range_m, sigma_m, xy_m, measured, G, gap_m, min_m, max_m, min_cm, max_cm):
    """:func:`_infer_narrow` (in place; returns the mask of sectors filled)."""
    inferred = np.zeros(SECTOR_COUNT, np.bool_)
    if G == 0 or gap_m <= 0:
        return inferred
    half = SECTOR_DEG * _DEG2RAD / 2
    obs = (state == _S_OBSTACLE) & measured
    known = np.flatnonzero(state != _S_UNKNOWN)
    if known.size < 2 or not np.any(obs):
        return inferred
    # maximal unknown runs on the ring between two known sectors: decided before any is filled
    n_k = known.size
    sel = np.zeros(n_k, np.bool_)
    chord = np.zeros(n_k)
    for q in range(n_k):
        i, j = known[q], known[(q + 1) % n_k]
        gap = (j - i - 1) % SECTOR_COUNT
        if gap >= 1 and gap <= G and obs[i] and obs[j]:
            chord[q] = np.hypot(xy_m[j, 0] - xy_m[i, 0], xy_m[j, 1] - xy_m[i, 1])
            sel[q] = chord[q] <= gap_m  # NaN (no point) compares False
    for q in range(n_k):
        if not sel[q]:
            continue
        i, j = known[q], known[(q + 1) % n_k]
        gap = (j - i - 1) % SECTOR_COUNT
        a0, a1, b0, b1 = xy_m[i, 0], xy_m[i, 1], xy_m[j, 0], xy_m[j, 1]
        c_ab = chord[q]
        cab = max(c_ab, 1e-12)
        u0, u1 = (b0 - a0) / cab, (b1 - a1) / cab
        dot = a0 * u0 + a1 * u1
        f0, f1 = a0 - dot * u0, a1 - dot * u1
        foot_b = math.atan2(f1, f0)
        d_foot = np.hypot(f0, f1)
        far = range_m[j] if range_m[j] > range_m[i] else range_m[i]  # Python's max(range_m[i], range_m[j])
        sg = sigma_m[j] if sigma_m[j] > sigma_m[i] else sigma_m[i]
        for a in range(1, gap + 1):
            f = (i + a) % SECTOR_COUNT
            centre = (f * SECTOR_DEG) * _DEG2RAD
            t = min(_line_distance_k(a0, a1, b0, b1, centre - half), _line_distance_k(a0, a1, b0, b1, centre + half))
            if abs((foot_b - centre + math.pi) % (2 * math.pi) - math.pi) <= half:
                t = min(t, d_foot)
            t = min(max(min(t, far), min_m), max_m)
            state[f] = _S_OBSTACLE
            dist[f] = min(max(np.int64(np.rint(t * 100)), min_cm), max_cm)
            range_m[f] = t
            sigma_m[f] = sg
            xy_m[f, 0] = t * math.cos(centre)
            xy_m[f, 1] = t * math.sin(centre)
            inferred[f] = True
    return inferred


@_jit.njit
def _vertical_pick_k(idx, d_cons, off_b, lim, above, below, rel_tol, one_side, min_extent, reach):
    """(72,) the point each sector claims from a vertical span (:func:`_infer_vertical`, then
    :func:`_infer_vertical_one_side` when ``one_side``), −1 where none: the nearest candidate, the
    first in the reference's candidate order on ties (two-sided pairs first, each in row-major
    order of the pair; only the order within a sector matters)."""
    vpick = np.full(SECTOR_COUNT, -1, np.int64)
    n = idx.size
    # the points above or below the band, grouped by sector in ascending index
    count = np.zeros(SECTOR_COUNT + 1, np.int64)
    for i in range(n):
        if above[i] or below[i]:
            count[idx[i] + 1] += 1
    for s in range(SECTOR_COUNT):
        count[s + 1] += count[s]
    fill = count[:SECTOR_COUNT].copy()
    pts = np.empty(count[SECTOR_COUNT], np.int64)
    for i in range(n):
        if above[i] or below[i]:
            pts[fill[idx[i]]] = i
            fill[idx[i]] += 1
    for s in range(SECTOR_COUNT):  # two-sided: (above, below) pairs in one sector
        for qa in range(count[s], count[s + 1]):
            ia = pts[qa]
            if not above[ia]:
                continue
            for qb in range(count[s], count[s + 1]):
                ib = pts[qb]
                if not below[ib]:
                    continue
                da, db = d_cons[ia], d_cons[ib]
                if abs(da - db) <= rel_tol * min(da, db):
                    c = ia if da <= db else ib
                    if vpick[s] < 0 or d_cons[c] < d_cons[vpick[s]]:
                        vpick[s] = c
    if one_side:  # pairs of points above the band in one sector reaching down towards it
        for s in range(SECTOR_COUNT):
            for qa in range(count[s], count[s + 1]):
                ia = pts[qa]
                if not above[ia]:
                    continue
                for qb in range(qa + 1, count[s + 1]):
                    ib = pts[qb]
                    if not above[ib]:
                        continue
                    da, db = d_cons[ia], d_cons[ib]
                    ha, hb = off_b[ia] - lim[ia], off_b[ib] - lim[ib]
                    if abs(da - db) <= rel_tol * min(da, db) and abs(ha - hb) >= min_extent and min(ha, hb) <= reach:
                        c = ia if da <= db else ib
                        if vpick[s] < 0 or d_cons[c] < d_cons[vpick[s]]:
                            vpick[s] = c
    return vpick


@_jit.register_warmup
def _warm_up() -> None:
    """Compile the sector kernels on a tiny scene (live, remembered with spread, every rule on), in the
    argument types :func:`companion.core.sectors._sectors_kernel` passes them."""
    cfg = _kernel_config(SectorConfig(infer_vertical=True, infer_vertical_one_side=True, cap_above_m=2.5, ground_margin_m=0.5,
                                      infer_narrow_gap_m=4.0))
    R_lb = euler_zyx_to_R_scalar(0.1, 0.05, 0.0)
    gamma = 0.2
    in_view, fully = _view_masks_kernel(math.tan(math.radians(60.0) / 2), math.tan(math.radians(45.0) / 2), True, R_lb,
                                        mount_rotation(0.0, 0.0, 0.0), gamma)
    p = np.array([[10.0, 0.0, 0.0], [10.0, 1.0, -2.0], [50.0, 0.5, 0.0]])
    p, sig, conv, val, mem_tan = _join_points_k(p, np.full(3, 0.5), np.ones(3, bool), np.ones(3, bool),
                                                np.array([[5.0, -3.0, 0.0]]), np.array([0.3]), np.array([1.0]))
    usable, r, _ = _usable_points_k(p, sig, val)
    p_level = np.where(usable[:, None], p, 0.0) @ R_lb.T
    _sectors_core(p, sig, conv, usable, r, p_level, 3, mem_tan, R_lb, in_view, fully, gamma, math.tan(gamma), -5.0, True, cfg)
