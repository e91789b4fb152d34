"""Obstacle sectors for OBSTACLE_DISTANCE / DISTANCE_SENSOR / OBSTACLE_DISTANCE_3D (docs/derivations/sectors.md).

Pure logic: 3-D points with range σ in the current body frame (FRD) in, 72 × 5° sector distances
out.  No I/O, no globals.

Geometry
--------
* Sector ``i`` is centred on bearing ``i · 5°`` clockwise from forward (``angle_offset = 0``,
  ``increment = 5``) and spans ``[i·5° − 2.5°, i·5° + 2.5°)``: ArduPilot places distance ``i`` at the
  angle ``i · increment`` and PX4 centres its 5° bins the same way.
* Bearings and heights are taken in the *levelled* body frame (yaw kept, roll and pitch removed)
  when the attitude is given, so a rolled or pitched vehicle still fills the horizontal sectors
  correctly (docs/derivations/sectors.md: the wiki script "ignores roll").  Without attitude the body is taken as
  level.
* Only points inside a vertical band around the flight path count: ``|h − d·tan γ| ≤ half height``
  (``band_mode = "metres"``) or ``|elevation − γ| ≤ half angle`` (``"degrees"``), where ``h`` is the
  point's height above the vehicle, ``d`` its horizontal distance and ``γ`` the flight-path angle
  (0 when the velocity is unknown or small).

Rules (docs/derivations/sectors.md)
--------------------------------------------
* conservative range: ``r − k·σ`` along the ray, projected on the horizontal;
* a sector that the camera's horizontal field of view does not touch: ``UINT16_MAX`` (unknown);
* a sector with at least ``min_points_obstacle`` converged in-band points ranged (conservatively)
  within ``max_distance``: the ``n``-th nearest conservative range, clamped to
  ``[min_distance, max_distance]`` (``n = min_points_obstacle``; ArduPilot discards values below
  ``min_distance`` and 0, so a too-near obstacle is reported *at* ``min_distance``, never dropped);
* "clear" (``max_distance + 1``) only for a sector *entirely* inside the field of view with at
  least ``min_points_clear`` converged in-band points ranged conservatively beyond
  ``max_distance`` (with ``clear_line_of_sight``, also points whose line of sight stays inside the
  band out to ``max_distance``), no point (converged or, by default, not) that may be nearer, and nothing else:
  absence of features is not free space, so every other in-view sector is ``UINT16_MAX``; with
  ``clear_corridor_m`` a clear sector within asin(w / r) of an obstacle sector's edge turns unknown (rule 10);
* 0 ("touching") only when the estimate itself is at or below ``touching_distance_m`` (off by
  default: ArduPilot ignores 0).

:meth:`Sectors.rotated` turns the sectors by the yaw change between exposure and sending (docs/derivations/sectors.md:
the autopilots stamp with arrival time): obstacle *points* are re-binned at their turned bearings
(an obstacle inside one sector stays in one sector; turning a whole sector array would smear every
obstacle into a neighbour on any fractional yaw change, a phantom beside every real obstacle), while
"clear" and "unknown" are turned with :func:`rotate_sectors`, which never invents "clear".

Layout: this module holds the entry point :func:`compute_sectors`, its numpy reference and the kernel
path's glue; the constants, :class:`SectorConfig` and the result types are in
:mod:`companion.core.sectors_types`, the inference rules in :mod:`companion.core.sectors_infer` and the
compiled kernels in :mod:`companion.core.sectors_kernels` (every public name is importable from here).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from companion.core import jit as _jit
from companion.core.frames import euler_zyx_to_R, euler_zyx_to_R_scalar, mount_rotation
# the sector ring's constants and types, re-exported: every public name stays importable from here
from companion.core.sectors_types import (  # noqa: F401
    _SAMPLES_PER_SECTOR,
    ARDUPILOT_FACE_HALF_DEG,
    PX4_BIN_DEG,
    SECTOR_BEARING_DEG,
    SECTOR_COUNT,
    SECTOR_DEG,
    UNKNOWN_CM,
    ForwardRange,
    Obstacle3D,
    SectorConfig,
    SectorRanking,
    Sectors,
    SectorSource,
    SectorState,
    UnknownReason,
    estimate_from_conservative,
    fold_into_bins,
    forward_reading_consistent,
    forward_unknown_reason,
    margin_k,
    rotate_sectors,
    sector_index,
    unknown_reasons,
    unknown_sectors,
)
from companion.core.sectors_infer import (
    _claim_inferred,
    _infer_between,
    _infer_narrow,
    _infer_vertical,
    _infer_vertical_one_side,
    _nearest_per_sector,
)
from companion.core.sectors_kernels import _join_points_k, _kernel_config, _sectors_core, _usable_points_k, _view_masks_kernel
from companion.errors import InputError


def _R_level_body(roll: float, pitch: float) -> np.ndarray:
    """Rotation from body FRD to the levelled body frame (yaw kept, roll and pitch removed)."""
    return euler_zyx_to_R(roll, pitch, 0.0)


def _as_R_cam_body(R_cam_body) -> np.ndarray:
    if np.ndim(R_cam_body) == 0:  # a camera yaw offset (rad, + right) on a forward-looking mount
        yaw = float(R_cam_body)
        if not math.isfinite(yaw):
            raise InputError("camera yaw offset must be finite")
        return mount_rotation(0.0, 0.0, math.degrees(yaw))
    R = np.asarray(R_cam_body, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise InputError(f"R_cam_body must be a finite 3x3 matrix or a yaw offset, got shape {R.shape}")
    return R


def sector_view_masks(hfov_rad: float, R_cam_body, *, roll_pitch_rad=None, flight_path_rad: float = 0.0, vfov_rad=None):
    """Which sectors the camera sees at the band centre: ``(in_view, fully_in_view)``, each (72,) bool.

    Directions along each sector (its two edges and three inner bearings) at elevation
    ``flight_path_rad`` in the levelled frame are rotated into the camera and tested against the
    horizontal (and, if given, vertical) field of view.
    """
    if not (isinstance(hfov_rad, (int, float)) and math.isfinite(hfov_rad) and 0 < hfov_rad < math.pi):
        raise InputError(f"hfov_rad must be in (0, pi), got {hfov_rad!r}")
    R_cb = _as_R_cam_body(R_cam_body)
    centres = np.radians(np.arange(SECTOR_COUNT) * SECTOR_DEG)
    offs = np.radians(np.linspace(-SECTOR_DEG / 2, SECTOR_DEG / 2, _SAMPLES_PER_SECTOR))
    beta = centres[:, None] + offs[None, :]  # (72, S)
    g = float(flight_path_rad)
    d_level = np.stack([math.cos(g) * np.cos(beta), math.cos(g) * np.sin(beta), np.full(beta.shape, -math.sin(g))], -1)
    if roll_pitch_rad is not None:
        R_lb = _R_level_body(*roll_pitch_rad)
        d_body = d_level @ R_lb  # R_body_level = R_level_body^T: row-vector form d @ R_lb
    else:
        d_body = d_level
    d_cam = d_body @ R_cb.T
    z = d_cam[..., 2]
    eps = 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        inside = (z > eps) & (np.abs(d_cam[..., 0]) <= math.tan(hfov_rad / 2) * z + eps)
        if vfov_rad is not None:
            inside &= np.abs(d_cam[..., 1]) <= math.tan(float(vfov_rad) / 2) * z + eps
    return inside.any(axis=1), inside.all(axis=1)


def _margin_or_off(margin_m: float) -> float:
    """A veto margin beside the band, −inf when it is 0 (off): then nothing outside the band is within it."""
    return margin_m if margin_m > 0 else -math.inf


def _flight_path_angle(config: SectorConfig, v_level) -> float:
    if v_level is None:
        return 0.0
    v = np.asarray(v_level, dtype=float).reshape(3)
    if not np.all(np.isfinite(v)):
        return 0.0
    speed = float(np.linalg.norm(v))
    if speed < config.flight_path_min_speed_mps or speed == 0.0:
        return 0.0
    gamma = math.atan2(-v[2], math.hypot(v[0], v[1]))  # climb positive (z is down)
    lim = math.radians(config.flight_path_max_angle_deg)
    return max(-lim, min(lim, gamma))


def compute_sectors(
    p_body,
    range_sigma,
    converged,
    valid,
    hfov_rad: float,
    R_cam_body,
    config: SectorConfig = SectorConfig(),
    *,
    roll_pitch_rad: tuple[float, float] | None = None,
    velocity_body=None,
    vfov_rad: float | None = None,
    remembered_p_body=None,
    remembered_sigma=None,
    remembered_tangential_sigma=None,
    ground_height_m: float | None = None,
) -> Sectors:
    """Sector distances from ranged points (OBSTACLE_DISTANCE rules, docs/derivations/sectors.md; see module doc).

    Parameters
    ----------
    p_body : (N, 3) points in body FRD relative to the vehicle reference point, metres.
    range_sigma : (N,) σ of each point's range estimate, metres.
    converged : (N,) bool, the filter's convergence flag.
    valid : (N,) bool, the point is usable at all (not diverged, not behind the camera).
    hfov_rad : horizontal field of view of the camera.
    R_cam_body : 3×3 ``R_cam_body`` of the mount, or a float yaw offset (rad, + right) of a
        forward-looking camera.
    roll_pitch_rad : vehicle roll and pitch at exposure; sectors and band are then levelled.
    velocity_body : vehicle velocity in body FRD at exposure (sets the band's flight-path angle).
    vfov_rad : vertical field of view; when given the view mask also checks the band centre is
        inside the image vertically.

    ground_height_m : height of the ground below the vehicle relative to it (levelled, up positive:
        the NED z of the vehicle in the autopilot's local frame, whose origin is the take-off ground),
        used by ``ground_margin_m`` (points that low are dropped: the ground is no obstacle and no
        evidence of clear) and by ``infer_vertical``.  Assumes level ground at the origin's height:
        rising ground ahead stays an obstacle; ground that falls away is dropped anyway.

    remembered_p_body : (M, 3) points of the local obstacle map (docs/derivations/obstacle_map.md) in body FRD: they may
        claim an obstacle in any sector over 360° (the field-of-view mask does not apply to them),
        never "clear"; ``remembered_sigma`` (M,) their range σ and ``remembered_tangential_sigma``
        (M,) their σ across the line of sight, both grown since last observed.  A point whose
        bearing is uncertain by more than half a sector (k·σ_t / range) is spread over the sectors
        that bearing interval touches (at most ``remembered_max_spread_deg``).

    After the rules above, an unknown gap of at most ``infer_max_gap_sectors`` between two obstacle
    sectors whose ranges agree within ``infer_rel_tol`` is filled with the nearer of the two and
    flagged in :attr:`Sectors.inferred` (docs/derivations/sectors.md: inference only ever adds an obstacle, never
    "clear").  Then an unknown gap of at most ``infer_narrow_max_sectors`` whose two sides' points lie
    at most ``infer_narrow_gap_m`` apart (levelled horizontal plane) is filled with the straight line
    between the two points, each sector at the line's nearest distance over its bearings: a surface
    that continues between them (a wall whose texture left no point there), or a gap too narrow to fly
    through; either way an obstacle, never "clear".

    Bad points (NaN/inf, negative σ, zero range) are ignored and counted, never raised on.
    """
    if _jit.ENABLED:
        return _sectors_kernel(p_body, range_sigma, converged, valid, hfov_rad, R_cam_body, config, roll_pitch_rad, velocity_body,
                               vfov_rad, remembered_p_body, remembered_sigma, remembered_tangential_sigma, ground_height_m)
    return compute_sectors_reference(
        p_body, range_sigma, converged, valid, hfov_rad, R_cam_body, config, roll_pitch_rad=roll_pitch_rad,
        velocity_body=velocity_body, vfov_rad=vfov_rad, remembered_p_body=remembered_p_body,
        remembered_sigma=remembered_sigma, remembered_tangential_sigma=remembered_tangential_sigma,
        ground_height_m=ground_height_m)


def compute_sectors_reference(
    p_body,
    range_sigma,
    converged,
    valid,
    hfov_rad: float,
    R_cam_body,
    config: SectorConfig = SectorConfig(),
    *,
    roll_pitch_rad: tuple[float, float] | None = None,
    velocity_body=None,
    vfov_rad: float | None = None,
    remembered_p_body=None,
    remembered_sigma=None,
    remembered_tangential_sigma=None,
    ground_height_m: float | None = None,
) -> Sectors:
    """:func:`compute_sectors` by the pure-numpy reference whatever :data:`companion.core.jit.ENABLED` says:
    the readable form of the rules of docs/derivations/sectors.md, which the compiled kernel
    (:func:`_sectors_kernel`) must reproduce (the tests compare the two)."""
    inp = _sector_inputs(p_body, range_sigma, converged, valid, config, roll_pitch_rad, velocity_body, remembered_p_body,
                         remembered_sigma, remembered_tangential_sigma)
    return _sectors_reference(inp, hfov_rad, R_cam_body, config, vfov_rad, ground_height_m)


class _SectorInputs(NamedTuple):
    """The points of :func:`compute_sectors` checked and joined (live first, then remembered), and the attitude."""

    p: np.ndarray  # (N, 3) body FRD, live then remembered
    sig: np.ndarray  # (N,) range σ
    conv: np.ndarray  # (N,) bool
    val: np.ndarray  # (N,) bool
    n_live: int  # points [0, n_live) are live, the rest remembered
    mem_tan: np.ndarray  # (N − n_live,) tangential σ of the remembered points (0 where not finite); empty without them
    mem: np.ndarray  # (N,) bool: remembered
    rp: tuple[float, float] | None  # roll, pitch
    R_lb: np.ndarray  # body → levelled
    gamma: float  # flight-path angle of the band centre


def _sector_inputs(p_body, range_sigma, converged, valid, config: SectorConfig, roll_pitch_rad, velocity_body, remembered_p_body,
                   remembered_sigma, remembered_tangential_sigma) -> _SectorInputs:
    """Checks and joins the inputs of :func:`compute_sectors` for the reference (the kernel path,
    :func:`_sectors_kernel`, makes the same checks); raises :class:`InputError` on bad shapes."""
    p = np.asarray(p_body, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        if p.size == 0:
            p = p.reshape(0, 3)
        else:
            raise InputError(f"p_body must have shape (N, 3), got {p.shape}")
    n = p.shape[0]
    sig = np.asarray(range_sigma, dtype=float).reshape(-1)
    conv = np.asarray(converged, dtype=bool).reshape(-1)
    val = np.asarray(valid, dtype=bool).reshape(-1)
    for name, a in (("range_sigma", sig), ("converged", conv), ("valid", val)):
        if a.shape[0] != n:
            raise InputError(f"{name} has {a.shape[0]} entries for {n} points")
    n_live = n
    mem_tan = np.zeros(0)
    if remembered_p_body is not None:
        mp = np.asarray(remembered_p_body, dtype=float).reshape(-1, 3)
        m = mp.shape[0]
        ms = np.asarray(remembered_sigma if remembered_sigma is not None else np.zeros(m), dtype=float).reshape(-1)
        mt = np.asarray(remembered_tangential_sigma if remembered_tangential_sigma is not None else np.zeros(m), dtype=float).reshape(-1)
        if ms.shape[0] != m or mt.shape[0] != m:
            raise InputError(f"remembered_sigma / remembered_tangential_sigma need {m} entries each")
        p = np.concatenate([p, mp])
        sig = np.concatenate([sig, ms])
        conv = np.concatenate([conv, np.ones(m, bool)])
        val = np.concatenate([val, np.all(np.isfinite(mp), axis=1) & np.isfinite(mt) & (mt >= 0)])
        mem_tan = np.where(np.isfinite(mt), mt, 0.0)
        n = p.shape[0]
    mem = np.arange(n) >= n_live

    if roll_pitch_rad is not None:
        rp = tuple(float(a) for a in roll_pitch_rad)
        if len(rp) != 2 or not all(math.isfinite(a) for a in rp):
            raise InputError(f"roll_pitch_rad must be two finite angles, got {roll_pitch_rad!r}")
        R_lb = _R_level_body(*rp)
    else:
        rp = None
        R_lb = np.eye(3)
    v_level = None if velocity_body is None else R_lb @ np.asarray(velocity_body, dtype=float).reshape(3)
    gamma = _flight_path_angle(config, v_level)
    return _SectorInputs(p, sig, conv, val, n_live, mem_tan, mem, rp, R_lb, gamma)


def _sectors_reference(inp: _SectorInputs, hfov_rad, R_cam_body, config: SectorConfig, vfov_rad, ground_height_m) -> Sectors:
    """The pure-numpy reference of :func:`compute_sectors` (docs/derivations/sectors.md, every rule in order)."""
    p, sig, conv, val, n_live, mem_tan, mem, rp, R_lb, gamma = inp
    n = p.shape[0]
    in_view, fully = sector_view_masks(hfov_rad, R_cam_body, roll_pitch_rad=rp, flight_path_rad=gamma, vfov_rad=vfov_rad)

    # ---- per point ---------------------------------------------------------------------------
    finite = np.all(np.isfinite(p), axis=1) & np.isfinite(sig) & (sig >= 0)
    r = np.linalg.norm(np.where(finite[:, None], p, 0.0), axis=1)
    usable = finite & (r > 1e-9)
    rejected = int(np.count_nonzero(val & ~usable))
    usable &= val
    p_level = np.where(usable[:, None], p, 0.0) @ R_lb.T
    if mem_tan.size:
        p, p_level, sig, conv, usable, mem, r = _spread_remembered(
            p, p_level, sig, conv, usable, mem, r, mem_tan, n_live, config, R_lb)
        n = p.shape[0]
    d_h = np.hypot(p_level[:, 0], p_level[:, 1])
    height = -p_level[:, 2]
    ground_known = ground_height_m is not None and math.isfinite(ground_height_m)
    bearing = np.arctan2(p_level[:, 1], p_level[:, 0])
    idx = sector_index(bearing)
    tracked = usable & ~mem & in_view[idx]  # live points in view at any height, the ground's too ("why unknown")
    if ground_known and config.ground_margin_m > 0:  # the ground is not an obstacle for horizontal avoidance
        usable &= height >= ground_height_m + config.ground_margin_m
    r_safe = np.where(usable, r, 1.0)
    off = height - d_h * math.tan(gamma)  # metres above the band centre (the flight path)
    lim = config.band_half_height_m if config.band_mode == "metres" else d_h * math.tan(math.radians(config.band_half_angle_deg))
    if config.band_mode == "metres":
        in_band = np.abs(off) <= lim
    else:
        elev = np.arctan2(height, d_h)
        in_band = np.abs(elev - gamma) <= math.radians(config.band_half_angle_deg)
    in_band &= usable
    seen = in_view[idx] | mem  # remembered points claim over 360° (docs/derivations/sectors.md)
    in_band &= seen

    r_cons = np.maximum(r - config.sigma_k * np.where(usable, sig, 0.0), 0.0)
    d_cons = d_h * (r_cons / r_safe)  # conservative horizontal range
    max_m = config.max_distance_m
    near = d_cons <= max_m

    obs_pts = in_band & conv & near
    # the sector's nearest surface from the live points consistent with its nearest one, not the
    # nearest of many noisy points (docs/derivations/sectors.md, "Nearest surface")
    sig_pub, est, fused = sig, d_h, np.zeros(n, bool)
    if config.fuse_gate_k > 0:
        d_cons, sig_pub, est, fused = _fuse_nearest_surface(idx, d_h, sig, r_safe, d_cons, obs_pts & ~mem, config)
    clr_band = in_band
    if config.clear_line_of_sight and config.band_mode == "metres":
        # the line of sight to a point beyond max_distance is free; it proves the band free where it runs inside
        # it, out to max_distance: |off|·max/d ≤ half height (docs/derivations/sectors.md, rule 3)
        los = np.abs(off) * max_m <= lim * d_h
        clr_band = in_band | (los & usable & in_view[idx])
    clr_pts = clr_band & conv & ~near & ~mem  # "clear" only from what the camera sees now
    cap_zone = (off > lim) & (off <= lim + config.cap_above_m)  # just above the band: rule 8's (empty when it is off)
    # rule 3's veto: a point that may lie within max_distance, unconverged in the band, or just beside the band up to
    # its kind's margin (a structure seen there may stand through it, as rules 6–8 read it), except a converged one in
    # the cap's zone, which rule 8 claims as an obstacle instead; a margin of 0 is off
    margin = np.where(conv, _margin_or_off(config.converged_veto_margin_m),
                      _margin_or_off(config.unconverged_veto_margin_m if config.unconverged_veto_clear else 0.0))
    beside = usable & seen & ~in_band & (np.abs(off) <= lim + margin) & ~(conv & cap_zone)
    veto_pts = near & ((in_band & ~conv & config.unconverged_veto_clear) | beside)

    n_clr = np.bincount(idx[clr_pts], minlength=SECTOR_COUNT)
    n_veto = np.bincount(idx[veto_pts], minlength=SECTOR_COUNT)
    if config.clear_edge_margin_deg > 0:  # a surface goes on past its last corner: no "clear" just across an edge
        n_veto += _edge_vetoes(bearing, idx, obs_pts | veto_pts, config.clear_edge_margin_deg)

    # n-th nearest conservative range per sector (vectorized: sort by (sector, range))
    k = config.min_points_obstacle
    sel = np.flatnonzero(obs_pts)
    ranking = SectorRanking(idx[sel], d_cons[sel], ids=sel)
    n_obs = ranking.count
    pick, nearest_pick = ranking.nth(k), ranking.nth(1)
    has_obs = n_obs >= k

    state = np.full(SECTOR_COUNT, SectorState.UNKNOWN, dtype=np.int8)
    dist = np.full(SECTOR_COUNT, UNKNOWN_CM, dtype=np.int64)
    range_m = np.full(SECTOR_COUNT, np.nan)
    sigma_m = np.full(SECTOR_COUNT, np.nan)
    min_cm, max_cm = config.min_distance_cm, config.max_distance_cm

    d_pub, pt_cm = _published(d_cons, d_h, config)  # published value of every obstacle point
    d_pub_t, pt_cm_t, r_cons_t = d_pub, pt_cm, r_cons  # the values published: tapered far away when the taper is on
    if config.sigma_k_taper_to_m > 0:
        d_pub_t, pt_cm_t, r_cons_t = _tapered_values(d_h, r, r_safe, sig, usable, est, sig_pub, fused, config)
    obs_sec = np.flatnonzero(has_obs)
    xy_m = np.full((SECTOR_COUNT, 2), np.nan)  # levelled horizontal position of each obstacle sector's point
    if obs_sec.size:
        pts = pick[obs_sec]
        dist[obs_sec] = pt_cm[pts]
        state[obs_sec] = SectorState.OBSTACLE
        range_m[obs_sec] = d_pub[pts]
        sigma_m[obs_sec] = sig_pub[pts]
        xy_m[obs_sec] = d_pub[pts, None] * np.stack([np.cos(bearing[pts]), np.sin(bearing[pts])], 1)

    clear_sec = fully & (n_obs == 0) & (n_veto == 0) & (n_clr >= config.min_points_clear)
    dist[clear_sec] = max_cm + 1
    state[clear_sec] = SectorState.CLEAR
    n_mem = np.bincount(idx[obs_pts & mem], minlength=SECTOR_COUNT)

    inferred = _infer_between(state, dist, range_m, sigma_m, config)
    inferred |= _infer_narrow(state, dist, range_m, sigma_m, xy_m, config, ~inferred)
    vertical = np.zeros(SECTOR_COUNT, bool)  # claims set by a rule on points above or below the band
    if config.infer_vertical:
        # a structure standing through the band (docs/derivations/sectors.md: inference only adds obstacles): converged
        # points just above and just below it in one sector at consistent ranges; the nearer one is claimed
        win = config.infer_vertical_window_m
        span = usable & conv & near & seen
        above, below = span & (off > lim) & (off <= lim + win), span & (off < -lim) & (off >= -lim - win)
        if ground_known:  # the ground itself is no evidence
            below &= height >= ground_height_m + config.infer_vertical_ground_margin_m
        cand = _infer_vertical(idx, d_cons, above, below, config.infer_rel_tol)
        if config.infer_vertical_one_side:
            cand = np.concatenate([cand, _infer_vertical_one_side(idx, d_cons, above, off - lim, config.infer_rel_tol,
                                                                  config.infer_vertical_min_extent_m, config.infer_vertical_reach_m)])
        vpick = _nearest_per_sector(idx, d_cons, cand)  # two-sided pairs first: they win ties
        vert = vpick >= 0
        vp = vpick[vert]
        vert[vert] &= ~has_obs[vert] | ((d_pub[vp] < range_m[vert]) &
                                        _nearer_surface(d_h[vp], sig[vp], range_m[vert], sigma_m[vert], config))
        pick = _claim_inferred(vert, vpick, state, dist, range_m, sigma_m, pick, inferred, pt_cm, d_pub, sig)
        vertical |= vert

    if config.cap_above_m > 0:
        # a surface just above the band limits what the band may claim (docs/derivations/sectors.md: only nearer, never
        # "clear"): a thin pole whose in-band points did not range (or ranged the background through
        # a patch straddling its edge) but whose upper part did
        cap_pts = np.flatnonzero(usable & conv & near & seen & cap_zone)
        if cap_pts.size:
            cap = SectorRanking(idx[cap_pts], d_cons[cap_pts], ids=cap_pts).nth(1)
            capped = (cap >= 0) & ((state == SectorState.CLEAR) | (state == SectorState.OBSTACLE))
            cp = cap[capped]
            capped[capped] &= (state[capped] == SectorState.CLEAR) | ((d_pub[cp] < range_m[capped]) &
                                                                     _nearer_surface(d_h[cp], sig[cp], range_m[capped],
                                                                                     sigma_m[capped], config))
            pick = _claim_inferred(capped, cap, state, dist, range_m, sigma_m, pick, inferred, pt_cm, d_pub, sig)
            vertical |= capped

    if config.unconverged_cap_k > 0:
        # a point not yet converged still bounds the range from above (docs/derivations/sectors.md, rule 9: only
        # nearer, never "clear"): a pole at the focus of expansion, ranged slowly, behind a far claim
        kk = config.unconverged_cap_k
        ucand = np.flatnonzero(in_band & ~conv & ~mem & (kk * np.where(usable, sig, np.inf) < r_safe))
        if ucand.size:
            d_up = d_h[ucand] / (1.0 - kk * sig[ucand] / r_safe[ucand])  # ρ − kσ_ρ, σ_ρ = σ_r / r²
            up = SectorRanking(idx[ucand], d_up, ids=np.arange(ucand.size)).nth(1)
            capped = (up >= 0) & (state == SectorState.OBSTACLE)
            capped[capped] &= d_up[up[capped]] < range_m[capped]
            cu = up[capped]
            pt = ucand[cu]
            range_m[capped] = np.clip(d_up[cu], config.min_distance_m, max_m)
            dist[capped] = np.clip(np.rint(range_m[capped] * 100).astype(np.int64), min_cm, max_cm)
            sigma_m[capped] = sig[pt] * d_h[pt] / r_safe[pt]
            pick[capped] = -1
            inferred |= capped

    if config.corridor_far_ratio > 0:
        # no far claim beside a near obstacle either out of view (rule 10, its far part): the surface seen past
        # the obstacle's edge is no way through, and the remembered obstacle may reach into the neighbour
        far = _corridor_far(state, range_m, config.clear_corridor_m, config.corridor_far_ratio)
        far[in_view] = -1  # out of view only: in view a sector's own points place the edge
        src = far[far >= 0]
        cap = far >= 0
        range_m[cap], dist[cap], sigma_m[cap] = range_m[src], dist[src], sigma_m[src]
        pick[cap] = -1
        inferred |= cap
    if config.clear_corridor_m > 0:
        # no "clear" beside a near obstacle (docs/derivations/sectors.md, rule 10): a clear bearing there is no way
        # through for a vehicle, and PX4 steers into it
        _corridor(state, dist, range_m, config.clear_corridor_m)
    if config.sigma_k_taper_to_m > 0:
        # every rule above decided with the full margin; a sector claimed by a point (or a fused surface) now takes
        # that point's value with the tapered margin ("The margin's taper": states, picks and σ unchanged)
        claimed = (state == SectorState.OBSTACLE) & (pick >= 0)
        range_m[claimed] = d_pub_t[pick[claimed]]
        dist[claimed] = pt_cm_t[pick[claimed]]
    why = unknown_reasons(state, in_view, fully, n_obs, n_clr, n_veto,
                          np.bincount(idx[in_band & ~conv & ~mem], minlength=SECTOR_COUNT),
                          np.bincount(idx[tracked], minlength=SECTOR_COUNT), k, config.min_points_clear)

    # ---- forward window (DISTANCE_SENSOR) ------------------------------------------------------
    fwd = np.flatnonzero(np.abs(SECTOR_BEARING_DEG) <= config.forward_half_width_deg + 1e-9)
    fwd_obs = fwd[state[fwd] == SectorState.OBSTACLE]
    if fwd_obs.size:
        j = fwd_obs[np.argmin(range_m[fwd_obs])]
        pt = pick[j]  # −1 where the sector was inferred between two others: its own σ, no single point's estimate
        if pt >= 0:
            forward = ForwardRange(SectorState.OBSTACLE, float(range_m[j]), float(sig_pub[pt]), float(est[pt]))
        else:
            forward = ForwardRange(SectorState.OBSTACLE, float(range_m[j]), float(sigma_m[j]), math.nan)
    elif fwd.size and np.all(state[fwd] == SectorState.CLEAR):
        forward = ForwardRange(SectorState.CLEAR, (max_cm + 1) / 100.0, math.nan, math.nan)
    else:
        forward = ForwardRange(SectorState.UNKNOWN, math.nan, math.nan, math.nan)

    # ---- nearest obstacles, one per sector (OBSTACLE_DISTANCE_3D) -----------------------------
    cand = np.flatnonzero(n_obs > 0)
    nearest: list[Obstacle3D] = []
    if cand.size:
        pts = nearest_pick[cand]
        order3 = np.argsort(d_cons[pts], kind="stable")[: config.nearest_count]
        for j in order3:
            pt = pts[j]
            rc = max(float(r_cons_t[pt]), config.min_distance_m)
            scale = rc / float(r_safe[pt])
            pb = p[pt] * scale
            nearest.append(Obstacle3D((float(pb[0]), float(pb[1]), float(pb[2])), rc, float(sig[pt]), int(cand[j])))

    return Sectors(
        distances_cm=dist.astype(np.uint16),
        state=state,
        range_m=range_m,
        sigma_m=sigma_m,
        in_view=in_view,
        fully_in_view=fully,
        obstacle_points=n_obs,
        clear_points=n_clr,
        forward=forward,
        nearest=tuple(nearest),
        min_distance_cm=min_cm,
        max_distance_cm=max_cm,
        points_used=int(np.count_nonzero(in_band & conv)),
        points_rejected=rejected,
        obstacle_bearing_rad=np.concatenate([bearing[obs_pts], np.repeat(np.radians(np.flatnonzero(inferred) * SECTOR_DEG), k)]),
        obstacle_cm=np.concatenate([pt_cm_t[obs_pts], np.repeat(dist[inferred], k)]),
        obstacle_rank=k,
        remembered_points=n_mem,
        inferred=inferred,
        inferred_vertical=vertical,
        unknown_reason=why,
    )


def _published(d_cons, d_h, config: SectorConfig):
    """Points' published values from their conservative horizontal ranges: (metres clamped to [min, max], the
    same in cm; 0 = touching where the estimate ``d_h`` is at or below ``touching_distance_m``, if enabled)."""
    d_pub = np.clip(d_cons, config.min_distance_m, config.max_distance_m)
    pt_cm = np.clip(np.rint(d_pub * 100).astype(np.int64), config.min_distance_cm, config.max_distance_cm)
    if config.touching_distance_m > 0:
        pt_cm = np.where(d_h <= config.touching_distance_m, 0, pt_cm)
    return d_pub, pt_cm


def _tapered_values(d_h, r, r_safe, sig, usable, est, sig_pub, fused, config: SectorConfig):
    """Each point's published value with the margin's taper (docs/derivations/sectors.md, "The margin's
    taper"): its horizontal conservative range with k(d_h), a fused surface's d̄ − k(d̄)·σ̄ (clamped as
    the fusion clamps), published as rule 1 publishes (:func:`_published`); and the slant conservative
    range.  Returns (d_pub, pt_cm, r_cons)."""
    r_cons_t = np.maximum(r - _k_at(d_h, config) * np.where(usable, sig, 0.0), 0.0)
    d_t = d_h * (r_cons_t / r_safe)
    if np.any(fused):
        f = np.flatnonzero(fused)
        d_t[f] = np.minimum(np.maximum(est[f] - _k_at(est[f], config) * sig_pub[f], 0.0), config.max_distance_m)
    return (*_published(d_t, d_h, config), r_cons_t)


def _k_at(d_m, config: SectorConfig):
    """k of the conservative value at horizontal estimates ``d_m`` (:func:`margin_k` with the config's taper)."""
    return margin_k(d_m, config.sigma_k, config.sigma_k_far, config.sigma_k_taper_from_m, config.sigma_k_taper_to_m)


def _nearer_surface(est_m, sigma, range_m, sigma_m, config: SectorConfig) -> np.ndarray:
    """Whether points above or below the band at horizontal estimates ``est_m`` (range σ ``sigma``) lie on a
    different, nearer surface than their sectors' claims (published ``range_m``, σ ``sigma_m``; the claim's
    estimate is ``range_m + sigma_k·sigma_m``): nearer by more than ``cap_gate_k`` combined σ
    (docs/derivations/sectors.md, rules 7 and 8).  Always true with ``cap_gate_k`` = 0, and where a σ is
    not a number (the rule then keeps its nearer value)."""
    if config.cap_gate_k <= 0:
        return np.ones(np.shape(est_m), bool)
    est_s = range_m + config.sigma_k * sigma_m
    return ~(est_m + config.cap_gate_k * np.hypot(sigma, sigma_m) >= est_s)


def _fuse_nearest_surface(idx, d_h, sig, r_safe, d_cons, cand, config: SectorConfig):
    """Each sector's nearest surface from its live obstacle points (docs/derivations/sectors.md, "Nearest surface").

    The anchor is the sector's candidate with the smallest conservative range; the candidates whose
    horizontal estimates agree with it within ``fuse_gate_k`` combined σ are the same surface.  Their
    inverse-variance mean d̄ with the variance of a mean of equicorrelated errors (correlation ρ =
    ``fuse_correlation``: the shared pose),
    σ̄² = ((1 − ρ) Σw + ρ (Σ 1/σ)²) / (Σw)², w = 1/σ² (horizontal σ = σ_r d_h / r),
    replaces the conservative range of every member: min(max(d̄ − k σ̄, 0), max_distance_m) with k = ``sigma_k``
    (the value published with the margin's taper: :func:`_tapered_values`); its σ̄ and
    d̄ become their published σ and estimate.  A sector whose cluster has one point is unchanged.
    Returns new (d_cons, sig_pub, est) arrays and the mask of the points fused; the inputs are not modified."""
    d_cons, sig_pub, est = d_cons.copy(), sig.copy(), d_h.copy()
    fused_pts = np.zeros(d_h.shape[0], bool)
    sel = np.flatnonzero(cand)
    if sel.size < 2:
        return d_cons, sig_pub, est, fused_pts
    sel = sel[np.lexsort((d_cons[sel], idx[sel]))]  # by sector, then conservative range (ties: index)
    sec = idx[sel]
    first = np.r_[True, sec[1:] != sec[:-1]]
    anchor = sel[first][np.cumsum(first) - 1]
    s_h = np.maximum(sig[sel] * d_h[sel] / r_safe[sel], 1e-9)
    s_a = np.maximum(sig[anchor] * d_h[anchor] / r_safe[anchor], 1e-9)
    member = np.abs(d_h[sel] - d_h[anchor]) <= config.fuse_gate_k * np.hypot(s_h, s_a)
    m_sec = sec[member]
    s_m = s_h[member]
    w = 1.0 / (s_m * s_m)
    count = np.bincount(m_sec, minlength=SECTOR_COUNT)
    sw = np.bincount(m_sec, w, minlength=SECTOR_COUNT)
    swd = np.bincount(m_sec, w * d_h[sel][member], minlength=SECTOR_COUNT)
    sis = np.bincount(m_sec, 1.0 / s_m, minlength=SECTOR_COUNT)
    rho = config.fuse_correlation
    fused = count >= 2
    safe_sw = np.where(fused, sw, 1.0)
    d_bar = swd / safe_sw
    s_bar = np.sqrt(((1.0 - rho) * safe_sw + rho * (sis * sis)) / (safe_sw * safe_sw))
    value = np.minimum(np.maximum(d_bar - config.sigma_k * s_bar, 0.0), config.max_distance_m)
    pts = sel[member]
    upd = fused[m_sec]
    pts, ps = pts[upd], m_sec[upd]
    d_cons[pts], sig_pub[pts], est[pts] = value[ps], s_bar[ps], d_bar[ps]
    fused_pts[pts] = True
    return d_cons, sig_pub, est, fused_pts


def _corridor_reach(range_m, corridor_m: float) -> np.ndarray:
    """Rule 10's corridor (docs/derivations/sectors.md): how many neighbours on each side of obstacle sectors at
    ``range_m`` (NaN: the widest) it reaches, the j-th when 5(j − 1) < asin(``corridor_m`` / r), degrees; at most 36."""
    r = np.nan_to_num(np.asarray(range_m, float), nan=0.0)
    mu = np.degrees(np.arcsin(np.minimum(1.0, corridor_m / np.maximum(r, 1e-9))))
    return np.minimum(np.ceil(mu / SECTOR_DEG), SECTOR_COUNT // 2).astype(np.int64)


def _corridor_far(state, range_m, corridor_m: float, ratio: float) -> np.ndarray:
    """Rule 10's far part (docs/derivations/sectors.md): (72,) for each obstacle sector whose range exceeds ``ratio``
    times that of an obstacle sector whose corridor (the j-th neighbour on each side when 5(j − 1) < asin(``corridor_m``
    / r)) reaches it, the nearest such sector; −1 elsewhere.  Computed from the claims as they stand (no chains)."""
    out = np.full(SECTOR_COUNT, -1, np.int64)
    obs = np.flatnonzero(state == SectorState.OBSTACLE)
    if obs.size < 2:
        return out
    reach = _corridor_reach(range_m[obs], corridor_m)
    best = np.full(SECTOR_COUNT, np.inf)
    for j in range(1, int(reach.max()) + 1):
        for side in (1, -1):
            src = obs[reach >= j]
            dst = (src + side * j) % SECTOR_COUNT
            rs = np.nan_to_num(range_m[src], nan=0.0)
            hit = (state[dst] == SectorState.OBSTACLE) & (range_m[dst] > ratio * rs)
            for s_, d_, r_ in zip(src[hit], dst[hit], rs[hit]):  # few: the neighbours of near obstacle sectors
                if r_ < best[d_] or (r_ == best[d_] and s_ < out[d_]):  # the nearest; ties: the lowest sector
                    best[d_], out[d_] = r_, s_
    return out


def _corridor(state, dist, range_m, corridor_m: float) -> None:
    """Rule 10 (docs/derivations/sectors.md), in place: every "clear" sector whose nearer edge lies within
    μ = asin(``corridor_m`` / r) of an obstacle sector's edge (r its published range; the obstacle may stand anywhere
    in its sector) becomes unknown: the j-th neighbour on each side when 5(j − 1) < μ, degrees."""
    obs = np.flatnonzero(state == SectorState.OBSTACLE)
    if not obs.size:
        return
    reach = _corridor_reach(range_m[obs], corridor_m)
    veto = np.zeros(SECTOR_COUNT, bool)
    for j in range(1, int(reach.max()) + 1):
        veto[(obs[reach >= j] + j) % SECTOR_COUNT] = True
        veto[(obs[reach >= j] - j) % SECTOR_COUNT] = True
    drop = veto & (state == SectorState.CLEAR)
    state[drop] = SectorState.UNKNOWN
    dist[drop] = UNKNOWN_CM


def _edge_vetoes(bearing, idx, pts, margin_deg: float) -> np.ndarray:
    """(72,) count of the points ``pts`` that lie within ``margin_deg`` of an edge of their sector, added to the
    sector across that edge (docs/derivations/sectors.md, rule 3: the edge margin)."""
    sel = np.flatnonzero(pts)
    off = (np.degrees(bearing[sel]) - idx[sel] * SECTOR_DEG + 180.0) % 360.0 - 180.0  # from the sector's centre
    half = SECTOR_DEG / 2 - margin_deg
    return (np.bincount((idx[sel][off > half] + 1) % SECTOR_COUNT, minlength=SECTOR_COUNT)
            + np.bincount((idx[sel][off < -half] - 1) % SECTOR_COUNT, minlength=SECTOR_COUNT))


def _spread_remembered(p, p_level, sig, conv, usable, mem, r, mem_tan, n_live, config: SectorConfig, R_lb):
    """Copies of each remembered point at bearings covering β ± k·σ_t/d (k = ``remembered_spread_k``,
    at most ``remembered_max_spread_deg``), turned about the levelled vertical through the vehicle (range and height unchanged).
    A point with k·σ_t/d beyond ``remembered_drop_spread_deg`` is marked unusable: spread over that
    many sectors it would claim obstacles in the clear sectors beside a thin one (docs/derivations/sectors.md);
    with ``remembered_drop_across_only`` only if also σ_t > its range σ (uncertain across the line of sight)."""
    d_h = np.hypot(p_level[n_live:, 0], p_level[n_live:, 1])
    w_raw = config.remembered_spread_k * mem_tan / np.maximum(d_h, 1e-6)
    usable = usable.copy()
    drop = ~(w_raw <= math.radians(config.remembered_drop_spread_deg))  # bearing too uncertain: not published ...
    if config.remembered_drop_across_only:
        drop &= ~(mem_tan <= sig[n_live:])  # ... when that uncertainty lies across the line of sight
    usable[n_live:] &= ~drop
    w = np.minimum(w_raw, math.radians(config.remembered_max_spread_deg))
    half = math.radians(SECTOR_DEG / 2)
    J = np.where(usable[n_live:] & (w > half), np.ceil(w / math.radians(SECTOR_DEG)).astype(np.int64), 0)
    if not np.any(J):
        return p, p_level, sig, conv, usable, mem, r
    reps = 2 * J + 1
    src = np.repeat(np.arange(len(J)), reps)
    start = np.cumsum(reps) - reps
    j = np.arange(len(src)) - np.repeat(start, reps) - np.repeat(J, reps)  # −J..J per point
    off = np.where(J[src] > 0, w[src] * j / np.maximum(J[src], 1), 0.0)
    c, s_ = np.cos(off), np.sin(off)
    q = p_level[n_live:][src]
    q_level = np.stack([c * q[:, 0] - s_ * q[:, 1], s_ * q[:, 0] + c * q[:, 1], q[:, 2]], 1)
    q_body = q_level @ R_lb  # levelled → body
    cat = lambda a, b: np.concatenate([a[:n_live], b])  # noqa: E731
    return (cat(p, q_body), cat(p_level, q_level), cat(sig, sig[n_live:][src]), cat(conv, conv[n_live:][src]),
            cat(usable, usable[n_live:][src]), cat(mem, np.ones(len(src), bool)), cat(r, r[n_live:][src]))


# ---------------------------------------------------------------------- kernel path ----------
# compute_sectors through the compiled kernels of companion.core.sectors_kernels (docs/derivations/sectors.md).

_STATES = tuple(SectorState)  # by value
_EMPTY = np.zeros(0)
_EMPTY_P = np.zeros((0, 3))
_I3 = np.eye(3)
_I3.flags.writeable = False


def _sectors_kernel(p_body, range_sigma, converged, valid, hfov_rad, R_cam_body, config: SectorConfig, roll_pitch_rad, velocity_body,
                    vfov_rad, remembered_p_body, remembered_sigma, remembered_tangential_sigma, ground_height_m) -> Sectors:
    """:func:`compute_sectors` through the compiled kernels: the reference's checks (the same
    errors, in the same order), then :func:`_join_points_k`, :func:`_view_masks_kernel`,
    :func:`_usable_points_k` and :func:`_sectors_core`."""
    p = np.asarray(p_body, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        if p.size == 0:
            p = p.reshape(0, 3)
        else:
            raise InputError(f"p_body must have shape (N, 3), got {p.shape}")
    n = p.shape[0]
    sig = np.asarray(range_sigma, dtype=float).reshape(-1)
    conv = np.asarray(converged, dtype=bool).reshape(-1)
    val = np.asarray(valid, dtype=bool).reshape(-1)
    for name, a in (("range_sigma", sig), ("converged", conv), ("valid", val)):
        if a.shape[0] != n:
            raise InputError(f"{name} has {a.shape[0]} entries for {n} points")
    mp, ms, mt = _EMPTY_P, _EMPTY, _EMPTY
    if remembered_p_body is not None:
        mp = np.asarray(remembered_p_body, dtype=float).reshape(-1, 3)
        m = mp.shape[0]
        ms = np.asarray(remembered_sigma if remembered_sigma is not None else np.zeros(m), dtype=float).reshape(-1)
        mt = np.asarray(remembered_tangential_sigma if remembered_tangential_sigma is not None else np.zeros(m), dtype=float).reshape(-1)
        if ms.shape[0] != m or mt.shape[0] != m:
            raise InputError(f"remembered_sigma / remembered_tangential_sigma need {m} entries each")
    R_lb = _I3
    if roll_pitch_rad is not None:
        rp = tuple(float(a) for a in roll_pitch_rad)
        if len(rp) != 2 or not all(math.isfinite(a) for a in rp):
            raise InputError(f"roll_pitch_rad must be two finite angles, got {roll_pitch_rad!r}")
        R_lb = euler_zyx_to_R_scalar(rp[0], rp[1], 0.0)  # = _R_level_body (the tests compare them bit for bit)
    v_level = None if velocity_body is None else R_lb @ np.asarray(velocity_body, dtype=float).reshape(3)
    gamma = _flight_path_angle(config, v_level)
    if not (isinstance(hfov_rad, (int, float)) and math.isfinite(hfov_rad) and 0 < hfov_rad < math.pi):
        raise InputError(f"hfov_rad must be in (0, pi), got {hfov_rad!r}")
    R_cb = _as_R_cam_body(R_cam_body)
    has_v = vfov_rad is not None
    tan_v = math.tan(float(vfov_rad) / 2) if has_v else 0.0
    in_view, fully = _view_masks_kernel(math.tan(hfov_rad / 2), tan_v, has_v, R_lb, R_cb, float(gamma))
    ground_known = ground_height_m is not None and math.isfinite(ground_height_m)
    cfg = _kernel_config(config)
    if mp.shape[0]:
        p, sig, conv, val, mem_tan = _join_points_k(p, sig, conv, val, mp, ms, mt)
    else:
        mem_tan = _EMPTY
    usable, r, rejected = _usable_points_k(p, sig, val)
    # the levelled points by the reference's own product (BLAS): bit-identical p_level, so ties between
    # equal conservative ranges (copies of one remembered point) are broken the same way
    p_level = np.where(usable[:, None], p, 0.0) @ R_lb.T
    (dist, state, range_m, sigma_m, n_obs, n_clr, n_mem, inferred, used, ob_bearing, ob_cm, fwd_state, fwd_vals,
     near_p, near_vals, near_sector, vertical, n_veto, n_ranging, n_tracked) = _sectors_core(
        p, sig, conv, usable, r, p_level, n, mem_tan, R_lb, in_view, fully, float(gamma), math.tan(gamma),
        float(ground_height_m) if ground_known else 0.0, ground_known, cfg)
    forward = ForwardRange(_STATES[fwd_state], float(fwd_vals[0]), float(fwd_vals[1]), float(fwd_vals[2]))
    nearest = tuple(Obstacle3D((float(near_p[j, 0]), float(near_p[j, 1]), float(near_p[j, 2])), float(near_vals[j, 0]),
                               float(near_vals[j, 1]), int(near_sector[j])) for j in range(len(near_sector)))
    return Sectors(
        distances_cm=dist.astype(np.uint16), state=state, range_m=range_m, sigma_m=sigma_m, in_view=in_view,
        fully_in_view=fully, obstacle_points=n_obs, clear_points=n_clr, forward=forward, nearest=nearest,
        min_distance_cm=config.min_distance_cm, max_distance_cm=config.max_distance_cm, points_used=int(used),
        points_rejected=int(rejected), obstacle_bearing_rad=ob_bearing, obstacle_cm=ob_cm,
        obstacle_rank=config.min_points_obstacle, remembered_points=n_mem, inferred=inferred, inferred_vertical=vertical,
        unknown_reason=unknown_reasons(state, in_view, fully, n_obs, n_clr, n_veto, n_ranging, n_tracked,
                                       config.min_points_obstacle, config.min_points_clear),
    )
