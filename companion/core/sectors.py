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
  ``max_distance``, no point (converged or, by default, not) that may be nearer, and nothing else:
  absence of features is not free space, so every other in-view sector is ``UINT16_MAX``;
* 0 ("touching") only when the estimate itself is at or below ``touching_distance_m`` (off by
  default: ArduPilot ignores 0).

:meth:`Sectors.rotated` turns the sectors by the yaw change between exposure and sending (docs/derivations/sectors.md:
the autopilots stamp with arrival time): obstacle *points* are re-binned at their turned bearings
(an obstacle inside one sector stays in one sector; turning a whole sector array would smear every
obstacle into a neighbour on any fractional yaw change, a phantom beside every real obstacle), while
"clear" and "unknown" are turned with :func:`rotate_sectors`, which never invents "clear".
"""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import NamedTuple

import numpy as np

from companion.config import require, require_finite
from companion.core import jit as _jit
from companion.core.frames import euler_zyx_to_R, euler_zyx_to_R_scalar, mount_rotation
from companion.errors import InputError

#: OBSTACLE_DISTANCE holds 72 distances; 72 × 5° covers 360° (docs/derivations/sectors.md).
SECTOR_COUNT = 72
#: Width of one sector, degrees (``increment`` / ``increment_f`` of OBSTACLE_DISTANCE).
SECTOR_DEG = 5.0
#: "Unknown" in OBSTACLE_DISTANCE / DISTANCE_SENSOR (MAVLink spec).
UNKNOWN_CM = 65535

_SAMPLES_PER_SECTOR = 5  # bearings tested per sector for the field-of-view mask (edges + inside)


class SectorState(enum.IntEnum):
    """What a sector claims."""

    UNKNOWN = 0  # UINT16_MAX: not seen, or seen without evidence
    OBSTACLE = 1  # a distance in [min_distance, max_distance] (or 0 = touching)
    CLEAR = 2  # max_distance + 1: evidence of free space up to max_distance


@dataclasses.dataclass(frozen=True)
class SectorConfig:
    """The ``[sectors]`` table."""

    min_distance_m: float = 0.5  # nearest range reported; nearer obstacles are reported at this distance
    max_distance_m: float = 40.0  # farthest range claimed; beyond it, with evidence, a sector is "clear" (max + 1 cm)
    sigma_k: float = 2.0  # conservative range = estimate − k·σ
    band_mode: str = "metres"  # vertical band around the flight path: "metres" (fixed height) or "degrees" (cone)
    band_half_height_m: float = 1.5  # half height of the band, metres mode
    band_half_angle_deg: float = 10.0  # half angle of the band, degrees mode
    min_points_obstacle: int = 1  # converged in-band points a sector needs to report an obstacle (the n-th nearest is reported)
    min_points_clear: int = 3  # converged in-band points beyond max_distance a sector needs to be "clear"
    unconverged_veto_clear: bool = True  # a valid but unconverged point that may lie within max_distance forbids "clear"
    touching_distance_m: float = 0.0  # estimate at or below this is sent as 0 (touching); 0 = never (ArduPilot discards 0)
    forward_half_width_deg: float = 2.5  # DISTANCE_SENSOR forward window: sectors centred within ± this (2.5 = sector 0 only)
    nearest_count: int = 5  # nearest obstacles (one per sector) kept for OBSTACLE_DISTANCE_3D
    flight_path_min_speed_mps: float = 1.0  # below this speed the band is centred on the horizontal
    flight_path_max_angle_deg: float = 30.0  # the band centre climbs or descends at most this steeply
    remembered_spread_k: float = 1.0  # a remembered point is spread over bearings ± remembered_spread_k·σ_tangential/range ...
    remembered_max_spread_deg: float = 15.0  # ... at most this far, degrees
    remembered_drop_spread_deg: float = 90.0  # a remembered point whose k·σ_tangential/range exceeds this is not published (its bearing is too uncertain to place it), degrees
    infer_max_gap_sectors: int = 1  # unknown gaps up to this many sectors between two consistent obstacle sectors are inferred obstacles (0 = off)
    infer_rel_tol: float = 0.15  # the two sides are consistent when their ranges differ by at most this fraction of the nearer
    infer_narrow_gap_m: float = 4.0  # an unknown gap (up to infer_narrow_max_sectors) between two obstacle sectors whose points lie at most this far apart is filled with the straight line between them (too narrow to fly through); 0 = off
    infer_narrow_max_sectors: int = 6  # widest such gap, sectors
    infer_vertical: bool = True  # a sector with converged points both just above and just below the band whose horizontal ranges agree within infer_rel_tol claims an obstacle at the nearer of them (a pole, mast or trunk standing through the band whose own points in the band did not converge)
    infer_vertical_window_m: float = 5.0  # ... "just": within this of the band's upper and lower edges, m (keeps the ground out while it lies farther below the band than this)
    infer_vertical_ground_margin_m: float = 1.0  # with the ground's height known (the autopilot's altitude above its origin), points below the band count only this far above the ground, m
    infer_vertical_one_side: bool = True  # with infer_vertical: points above the band alone suffice when they show a vertical structure reaching down towards it (two at consistent ranges whose heights differ by infer_vertical_min_extent_m, the lower within infer_vertical_reach_m of the band's edge): a pole standing on the ground, whose foot is no evidence
    infer_vertical_min_extent_m: float = 0.5  # ... the two points' heights differ by at least this, m
    infer_vertical_reach_m: float = 2.5  # ... and the lower one lies within this above the band's edge, m
    cap_above_m: float = 2.5  # a converged point up to this far above the band caps the range its sector claims (an obstacle sector reports no farther than it, a clear one becomes an obstacle at it; unknown stays unknown), m; 0 = off
    ground_margin_m: float = 0.5  # with the ground's height known, points less than this above it are the ground: never an obstacle nor evidence of clear (taking off, landing, flying low); 0 = off

    def __post_init__(self) -> None:
        require_finite("min_distance_m", self.min_distance_m, positive=True)
        require_finite("max_distance_m", self.max_distance_m, positive=True)
        require(self.max_distance_m > self.min_distance_m, "max_distance_m must exceed min_distance_m")
        require(
            round(self.max_distance_m * 100) + 1 < UNKNOWN_CM,
            f"max_distance_m must be < 655.33 m (max_distance + 1 cm must stay below UINT16_MAX), got {self.max_distance_m}",
        )
        require_finite("sigma_k", self.sigma_k, nonnegative=True)
        require(self.band_mode in ("metres", "degrees"), f"band_mode must be 'metres' or 'degrees', got {self.band_mode!r}")
        require_finite("band_half_height_m", self.band_half_height_m, positive=True)
        require_finite("band_half_angle_deg", self.band_half_angle_deg, positive=True)
        require(self.band_half_angle_deg < 90, f"band_half_angle_deg must be < 90, got {self.band_half_angle_deg}")
        for name in ("min_points_obstacle", "min_points_clear", "nearest_count"):
            v = getattr(self, name)
            require(isinstance(v, int) and not isinstance(v, bool) and v >= 1, f"{name} must be an integer >= 1, got {v!r}")
        require(isinstance(self.unconverged_veto_clear, bool), "unconverged_veto_clear must be true or false")
        require_finite("touching_distance_m", self.touching_distance_m, nonnegative=True)
        require(self.touching_distance_m < self.min_distance_m, "touching_distance_m must be below min_distance_m")
        require_finite("forward_half_width_deg", self.forward_half_width_deg, nonnegative=True)
        require(self.forward_half_width_deg < 180, "forward_half_width_deg must be < 180")
        require_finite("flight_path_min_speed_mps", self.flight_path_min_speed_mps, nonnegative=True)
        require_finite("flight_path_max_angle_deg", self.flight_path_max_angle_deg, nonnegative=True)
        require(self.flight_path_max_angle_deg < 90, "flight_path_max_angle_deg must be < 90")
        require_finite("remembered_max_spread_deg", self.remembered_max_spread_deg, nonnegative=True)
        require(self.remembered_max_spread_deg <= 90, "remembered_max_spread_deg must be <= 90")
        require_finite("remembered_spread_k", self.remembered_spread_k, nonnegative=True)
        require_finite("remembered_drop_spread_deg", self.remembered_drop_spread_deg, positive=True)
        require(self.remembered_drop_spread_deg <= 90, "remembered_drop_spread_deg must be <= 90")
        require(isinstance(self.infer_max_gap_sectors, int) and not isinstance(self.infer_max_gap_sectors, bool)
                and 0 <= self.infer_max_gap_sectors <= 6, f"infer_max_gap_sectors must be an integer in 0..6, got {self.infer_max_gap_sectors!r}")
        require_finite("infer_rel_tol", self.infer_rel_tol, nonnegative=True)
        require_finite("infer_narrow_gap_m", self.infer_narrow_gap_m, nonnegative=True)
        require(isinstance(self.infer_narrow_max_sectors, int) and not isinstance(self.infer_narrow_max_sectors, bool)
                and 0 <= self.infer_narrow_max_sectors <= 12,
                f"infer_narrow_max_sectors must be an integer in 0..12, got {self.infer_narrow_max_sectors!r}")
        require(isinstance(self.infer_vertical, bool), "infer_vertical must be true or false")
        require_finite("infer_vertical_window_m", self.infer_vertical_window_m, positive=True)
        require_finite("infer_vertical_ground_margin_m", self.infer_vertical_ground_margin_m, nonnegative=True)
        require(isinstance(self.infer_vertical_one_side, bool), "infer_vertical_one_side must be true or false")
        require_finite("infer_vertical_min_extent_m", self.infer_vertical_min_extent_m, positive=True)
        require_finite("infer_vertical_reach_m", self.infer_vertical_reach_m, nonnegative=True)
        require_finite("cap_above_m", self.cap_above_m, nonnegative=True)
        require_finite("ground_margin_m", self.ground_margin_m, nonnegative=True)

    @property
    def min_distance_cm(self) -> int:
        return int(round(self.min_distance_m * 100))

    @property
    def max_distance_cm(self) -> int:
        return int(round(self.max_distance_m * 100))


@dataclasses.dataclass(frozen=True)
class ForwardRange:
    """The forward direction for DISTANCE_SENSOR (orientation NONE)."""

    state: SectorState
    distance_m: float  # conservative range (obstacle), max_distance + 0.01 (clear) or nan (unknown)
    sigma_m: float  # σ of the range estimate behind ``distance_m`` (nan unless obstacle)
    estimate_m: float  # the (non-conservative) horizontal range estimate (nan unless obstacle)

    @property
    def variance_m2(self) -> float:
        return self.sigma_m**2


@dataclasses.dataclass(frozen=True)
class Obstacle3D:
    """One obstacle for OBSTACLE_DISTANCE_3D: the nearest point of one sector."""

    p_body: tuple[float, float, float]  # body FRD, metres, moved to the conservative range along its ray
    range_m: float  # conservative 3-D range, clamped up to min_distance
    sigma_m: float  # σ of the range estimate
    sector: int


@dataclasses.dataclass(frozen=True, eq=False)
class Sectors:
    """Result of :func:`compute_sectors`; ``distances_cm`` is ready for OBSTACLE_DISTANCE."""

    distances_cm: np.ndarray  # (72,) uint16
    state: np.ndarray  # (72,) int8 SectorState
    range_m: np.ndarray  # (72,) conservative horizontal range of obstacle sectors, nan elsewhere
    sigma_m: np.ndarray  # (72,) σ of the point defining ``range_m``, nan elsewhere
    in_view: np.ndarray  # (72,) bool: the camera sees part of the sector (at the band centre)
    fully_in_view: np.ndarray  # (72,) bool: the camera sees all of it
    obstacle_points: np.ndarray  # (72,) int: converged in-band points within max_distance
    clear_points: np.ndarray  # (72,) int: converged in-band points beyond max_distance
    forward: ForwardRange
    nearest: tuple[Obstacle3D, ...]
    min_distance_cm: int
    max_distance_cm: int
    points_used: int  # points that passed validity, convergence and the band
    points_rejected: int  # points with NaN/inf/negative σ/zero range (bad input, ignored)
    # obstacle points behind the OBSTACLE sectors, for re-binning in :meth:`rotated`
    obstacle_bearing_rad: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))  # levelled body bearing
    obstacle_cm: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))  # published value of each
    obstacle_rank: int = 1  # the n-th nearest point of a sector is published (``min_points_obstacle``)
    remembered_points: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(SECTOR_COUNT, np.int64))  # (72,) map points behind each sector's claim
    inferred: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(SECTOR_COUNT, bool))  # (72,) obstacle inferred between two sides

    @property
    def n_inferred(self) -> int:
        return int(np.count_nonzero(self.inferred))

    @property
    def clear_cm(self) -> int:
        return self.max_distance_cm + 1

    @property
    def any_valid(self) -> bool:
        """True when at least one sector makes a claim (obstacle or clear)."""
        return bool(np.any(self.state != SectorState.UNKNOWN))

    @property
    def nearest_m(self) -> float:
        """Nearest conservative obstacle range over all sectors (nan if none)."""
        r = self.range_m[np.isfinite(self.range_m)]
        return float(r.min()) if r.size else math.nan

    def rotated(self, yaw_change_rad: float) -> np.ndarray:
        """``distances_cm`` as seen after the vehicle turned by ``yaw_change_rad`` since exposure.

        Obstacle points are re-binned at bearing − Δψ (the same n-th-nearest rule as at exposure);
        "clear" and "unknown" sectors are turned by :func:`rotate_sectors` (clear only where every
        overlapped sector was clear).  An obstacle point always wins over clear or unknown.
        """
        if not math.isfinite(yaw_change_rad):
            return np.full(SECTOR_COUNT, UNKNOWN_CM, dtype=np.uint16)
        base = np.where(self.state == SectorState.OBSTACLE, UNKNOWN_CM, self.distances_cm.astype(np.int64))
        out = rotate_sectors(base, yaw_change_rad, self.max_distance_cm).astype(np.int64)
        if self.obstacle_cm.size:
            idx = sector_index(self.obstacle_bearing_rad - yaw_change_rad)
            pick = SectorRanking(idx, self.obstacle_cm).nth(self.obstacle_rank)
            has = pick >= 0
            out[has] = self.obstacle_cm[pick[has]]
        return out.astype(np.uint16)


def sector_index(bearing_rad) -> np.ndarray:
    """Sector of each bearing (rad, clockwise from forward): sector ``i`` spans ``i·5° ± 2.5°``."""
    return np.mod(np.rint(np.degrees(np.asarray(bearing_rad, float)) / SECTOR_DEG).astype(np.int64), SECTOR_COUNT)


class SectorRanking:
    """Points sorted by (sector, value) once: :meth:`nth` picks the ``k``-th smallest per sector.

    ``ids`` names the points in the caller's numbering (default 0..N−1)."""

    def __init__(self, idx: np.ndarray, value: np.ndarray, ids: np.ndarray | None = None):
        idx = np.asarray(idx, np.int64)
        order = np.lexsort((value, idx))
        self.count = np.bincount(idx, minlength=SECTOR_COUNT)
        self.starts = np.searchsorted(idx[order], np.arange(SECTOR_COUNT), side="left")
        self.order = order if ids is None else np.asarray(ids, np.int64)[order]

    def nth(self, k: int) -> np.ndarray:
        """(72,) id of each sector's ``k``-th smallest point, −1 where it has fewer than ``k``."""
        pick = np.full(SECTOR_COUNT, -1, dtype=np.int64)
        has = self.count >= k
        pick[has] = self.order[self.starts[has] + k - 1]
        return pick


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
    bearing = np.arctan2(p_level[:, 1], p_level[:, 0])
    idx = sector_index(bearing)
    in_band &= in_view[idx] | mem  # remembered points claim over 360° (docs/derivations/sectors.md)

    r_cons = np.maximum(r - config.sigma_k * np.where(usable, sig, 0.0), 0.0)
    d_cons = d_h * (r_cons / r_safe)  # conservative horizontal range
    max_m = config.max_distance_m
    near = d_cons <= max_m

    obs_pts = in_band & conv & near
    clr_pts = in_band & conv & ~near & ~mem  # "clear" only from what the camera sees now
    veto_pts = in_band & ~conv & near if config.unconverged_veto_clear else np.zeros(n, bool)

    n_clr = np.bincount(idx[clr_pts], minlength=SECTOR_COUNT)
    n_veto = np.bincount(idx[veto_pts], minlength=SECTOR_COUNT)

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

    # published value of every obstacle point (clamped to [min, max]; 0 = touching if enabled)
    d_pub = np.clip(d_cons, config.min_distance_m, max_m)
    pt_cm = np.clip(np.rint(d_pub * 100).astype(np.int64), min_cm, max_cm)
    if config.touching_distance_m > 0:
        pt_cm = np.where(d_h <= config.touching_distance_m, 0, pt_cm)
    obs_sec = np.flatnonzero(has_obs)
    xy_m = np.full((SECTOR_COUNT, 2), np.nan)  # levelled horizontal position of each obstacle sector's point
    if obs_sec.size:
        pts = pick[obs_sec]
        dist[obs_sec] = pt_cm[pts]
        state[obs_sec] = SectorState.OBSTACLE
        range_m[obs_sec] = d_pub[pts]
        sigma_m[obs_sec] = sig[pts]
        xy_m[obs_sec] = d_pub[pts, None] * np.stack([np.cos(bearing[pts]), np.sin(bearing[pts])], 1)

    clear_sec = fully & (n_obs == 0) & (n_veto == 0) & (n_clr >= config.min_points_clear)
    dist[clear_sec] = max_cm + 1
    state[clear_sec] = SectorState.CLEAR
    n_mem = np.bincount(idx[obs_pts & mem], minlength=SECTOR_COUNT)

    inferred = _infer_between(state, dist, range_m, sigma_m, config)
    inferred |= _infer_narrow(state, dist, range_m, sigma_m, xy_m, config, ~inferred)
    if config.infer_vertical:
        # a structure standing through the band (docs/derivations/sectors.md: inference only adds obstacles): converged
        # points just above and just below it in one sector at consistent ranges; the nearer one is claimed
        win = config.infer_vertical_window_m
        span = usable & conv & near & (in_view[idx] | mem)
        above, below = span & (off > lim) & (off <= lim + win), span & (off < -lim) & (off >= -lim - win)
        if ground_known:  # the ground itself is no evidence
            below &= height >= ground_height_m + config.infer_vertical_ground_margin_m
        cand = _infer_vertical(idx, d_cons, above, below, config.infer_rel_tol)
        if config.infer_vertical_one_side:
            cand = np.concatenate([cand, _infer_vertical_one_side(idx, d_cons, above, off - lim, config.infer_rel_tol,
                                                                  config.infer_vertical_min_extent_m, config.infer_vertical_reach_m)])
        vpick = _nearest_per_sector(idx, d_cons, cand)  # two-sided pairs first: they win ties
        vert = vpick >= 0
        vert[vert] &= ~has_obs[vert] | (d_pub[vpick[vert]] < range_m[vert])
        pick = _claim_inferred(vert, vpick, state, dist, range_m, sigma_m, pick, inferred, pt_cm, d_pub, sig)

    if config.cap_above_m > 0:
        # a surface just above the band limits what the band may claim (docs/derivations/sectors.md: only nearer, never
        # "clear"): a thin pole whose in-band points did not range (or ranged the background through
        # a patch straddling its edge) but whose upper part did
        cap_pts = np.flatnonzero(usable & conv & near & (in_view[idx] | mem) & (off > lim) & (off <= lim + config.cap_above_m))
        if cap_pts.size:
            cap = SectorRanking(idx[cap_pts], d_cons[cap_pts], ids=cap_pts).nth(1)
            capped = (cap >= 0) & ((state == SectorState.CLEAR) | (state == SectorState.OBSTACLE))
            capped[capped] &= (state[capped] == SectorState.CLEAR) | (d_pub[cap[capped]] < range_m[capped])
            pick = _claim_inferred(capped, cap, state, dist, range_m, sigma_m, pick, inferred, pt_cm, d_pub, sig)

    # ---- forward window (DISTANCE_SENSOR) ------------------------------------------------------
    centres = np.arange(SECTOR_COUNT) * SECTOR_DEG
    rel = (centres + 180.0) % 360.0 - 180.0
    fwd = np.flatnonzero(np.abs(rel) <= config.forward_half_width_deg + 1e-9)
    fwd_obs = fwd[state[fwd] == SectorState.OBSTACLE]
    if fwd_obs.size:
        j = fwd_obs[np.argmin(range_m[fwd_obs])]
        pt = pick[j]  # −1 where the sector was inferred between two others: its own σ, no single point's estimate
        if pt >= 0:
            forward = ForwardRange(SectorState.OBSTACLE, float(range_m[j]), float(sig[pt]), float(d_h[pt]))
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
            rc = max(float(r_cons[pt]), config.min_distance_m)
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
        obstacle_cm=np.concatenate([pt_cm[obs_pts], np.repeat(dist[inferred], k)]),
        obstacle_rank=k,
        remembered_points=n_mem,
        inferred=inferred,
    )


def _spread_remembered(p, p_level, sig, conv, usable, mem, r, mem_tan, n_live, config: SectorConfig, R_lb):
    """Copies of each remembered point at bearings covering β ± k·σ_t/d (k = ``remembered_spread_k``,
    at most ``remembered_max_spread_deg``), turned about the levelled vertical through the vehicle (range and height unchanged).
    A point with k·σ_t/d beyond ``remembered_drop_spread_deg`` is marked unusable: spread over that
    many sectors it would claim obstacles in the clear sectors beside a thin one (docs/derivations/sectors.md)."""
    d_h = np.hypot(p_level[n_live:, 0], p_level[n_live:, 1])
    w_raw = config.remembered_spread_k * mem_tan / np.maximum(d_h, 1e-6)
    usable = usable.copy()
    usable[n_live:] &= w_raw <= math.radians(config.remembered_drop_spread_deg)  # bearing too uncertain: not published
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


def unknown_sectors(config: SectorConfig = SectorConfig()) -> np.ndarray:
    """All sectors unknown (what to send while no valid ranges are produced)."""
    return np.full(SECTOR_COUNT, UNKNOWN_CM, dtype=np.uint16)


def rotate_sectors(distances, yaw_change_rad: float, max_distance_cm: int, increment_deg: float = SECTOR_DEG) -> np.ndarray:
    """Turn sector distances by the vehicle's yaw change since exposure (docs/derivations/sectors.md).

    ``yaw_change_rad`` = yaw now − yaw at exposure (NED yaw, + = turned right).  An obstacle seen
    at bearing β is now at β − Δψ, so new sector ``i`` takes what old bearing ``i·inc + Δψ`` held.
    For a fractional shift a new sector overlaps two old ones and takes, conservatively: the
    nearest obstacle of either; else "unknown" if either is unknown; "clear" only if both are
    clear.  Values outside the ring come from the (circular) array itself, where the camera's
    unseen sectors already hold ``UINT16_MAX``; nothing becomes clear that was not clear before.
    """
    d = np.asarray(distances)
    if d.ndim != 1 or d.size == 0:
        raise InputError(f"distances must be a 1-D array, got shape {d.shape}")
    d = d.astype(np.int64)
    if not math.isfinite(yaw_change_rad):
        return np.full(d.shape, UNKNOWN_CM, dtype=np.uint16)
    n = d.size
    shift = math.degrees(yaw_change_rad) / increment_deg
    shift = (shift + n / 2) % n - n / 2  # wrap to [-n/2, n/2)
    lo = math.floor(shift)
    frac = shift - lo
    a = np.roll(d, -lo)  # new[i] = old[i + lo]
    tol = 1e-6
    if frac < tol:
        return a.astype(np.uint16)
    b = np.roll(d, -(lo + 1))  # old[i + lo + 1]
    if frac > 1 - tol:
        return b.astype(np.uint16)
    return _combine_conservative(a, b, max_distance_cm).astype(np.uint16)


def _combine_conservative(a: np.ndarray, b: np.ndarray, max_distance_cm: int) -> np.ndarray:
    a_obs = a <= max_distance_cm
    b_obs = b <= max_distance_cm
    out = np.full(a.shape, UNKNOWN_CM, dtype=np.int64)
    both_clear = (a == max_distance_cm + 1) & (b == max_distance_cm + 1)
    out[both_clear] = max_distance_cm + 1
    obs = a_obs | b_obs
    out[obs] = np.minimum(np.where(a_obs, a, UNKNOWN_CM), np.where(b_obs, b, UNKNOWN_CM))[obs]
    return out


# ---------------------------------------------------------------------- compiled kernel ----------
# The same rules as :func:`_sectors_reference`, as loops over points and sectors in one numba
# kernel (docs/derivations/sectors.md); used when :data:`companion.core.jit.ENABLED`.  The levelled
# points are the reference's own (the same BLAS product), so ranges, heights and ties are
# bit-identical; what is computed otherwise agrees to an ulp: the bearing (libm's atan2 here,
# numpy's loop there), the view directions and the body coordinates of spread copies (a fixed order
# of summation here, BLAS there).  A sector decision could therefore differ only for a point within
# an ulp of a sector edge; the tests compare every integer and flag array exactly on seeded scenes,
# points placed on every rule's edge and a flight through the pipeline.

_S_UNKNOWN, _S_OBSTACLE, _S_CLEAR = int(SectorState.UNKNOWN), int(SectorState.OBSTACLE), int(SectorState.CLEAR)  # plain ints for numba
_DEG2RAD = math.pi / 180.0  # = numpy's radians() factor (NPY_PI / 180)
_RAD2DEG = 180.0 / math.pi  # = numpy's degrees() factor
_VIEW_OFFSETS = np.radians(np.linspace(-SECTOR_DEG / 2, SECTOR_DEG / 2, _SAMPLES_PER_SECTOR))

# indices into the packed configuration vector of the kernel (:func:`_kernel_config`)
(_K_MIN_M, _K_MAX_M, _K_SIGMA_K, _K_BAND_METRES, _K_HALF_H, _K_HALF_ANGLE_RAD, _K_TAN_HALF_ANGLE, _K_N_OBS, _K_N_CLR,
 _K_VETO, _K_TOUCH, _K_SPREAD_K, _K_MAX_SPREAD_RAD, _K_DROP_SPREAD_RAD, _K_GAP, _K_REL_TOL, _K_NARROW_M, _K_NARROW_N,
 _K_VERT, _K_VERT_WIN, _K_VERT_GROUND, _K_ONE_SIDE, _K_MIN_EXTENT, _K_REACH, _K_CAP, _K_GROUND_MARGIN, _K_MIN_CM,
 _K_MAX_CM, _K_FWD_HALF, _K_NEAREST, _K_SIZE) = range(31)


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
    v[_K_GAP], v[_K_NARROW_N] = c.infer_max_gap_sectors, c.infer_narrow_max_sectors
    v[_K_MIN_CM], v[_K_MAX_CM] = c.min_distance_cm, c.max_distance_cm
    v.flags.writeable = False
    _KERNEL_CONFIGS[id(config)] = (config, v)  # the config is kept alive with its id: no reuse while cached
    if len(_KERNEL_CONFIGS) > 64:  # bounded: configs are few (one per process, a handful in tests)
        _KERNEL_CONFIGS.pop(next(iter(_KERNEL_CONFIGS)))
    return v


_KERNEL_CONFIGS: dict[int, tuple[SectorConfig, np.ndarray]] = {}
_STATES = tuple(SectorState)  # by value
_EMPTY = np.zeros(0)
_EMPTY_P = np.zeros((0, 3))


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
     near_p, near_vals, near_sector) = _sectors_core(
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
        obstacle_rank=config.min_points_obstacle, remembered_points=n_mem, inferred=inferred,
    )


_I3 = np.eye(3)
_I3.flags.writeable = False
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
            if not (w_raw <= cfg[_K_DROP_SPREAD_RAD]):
                usable_in[i] = False  # bearing too uncertain: not published
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
    for i in range(n):
        d_h[i] = np.hypot(pl[i, 0], pl[i, 1])
        height[i] = -pl[i, 2]
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
        seen[i] = in_view[idx[i]] or mem[i]
        in_band[i] = band and usable[i] and seen[i]
        r_cons[i] = max(r[i] - cfg[_K_SIGMA_K] * (sig[i] if usable[i] else 0.0), 0.0)
        d_cons[i] = d_h[i] * (r_cons[i] / r_safe[i])
        near[i] = d_cons[i] <= max_m

    # ---- per sector: counts, n-th nearest obstacle point -----------------------------------------
    veto_on = cfg[_K_VETO] != 0
    n_obs = np.zeros(SECTOR_COUNT, np.int64)
    n_clr = np.zeros(SECTOR_COUNT, np.int64)
    n_veto = np.zeros(SECTOR_COUNT, np.int64)
    n_mem = np.zeros(SECTOR_COUNT, np.int64)
    obs_pts = np.zeros(n, np.bool_)
    used = 0
    for i in range(n):
        if in_band[i] and conv[i]:
            used += 1
            if near[i]:
                obs_pts[i] = True
                n_obs[idx[i]] += 1
                if mem[i]:
                    n_mem[idx[i]] += 1
            elif not mem[i]:
                n_clr[idx[i]] += 1
        elif in_band[i] and veto_on and near[i]:
            n_veto[idx[i]] += 1
    sel = np.flatnonzero(obs_pts)
    order = sel[np.argsort(d_cons[sel], kind="mergesort")]  # by range, ties by index (the reference's lexsort)
    starts = np.zeros(SECTOR_COUNT + 1, np.int64)
    for s in range(SECTOR_COUNT):
        starts[s + 1] = starts[s] + n_obs[s]
    fill = starts[:SECTOR_COUNT].copy()
    ranked = np.empty(sel.size, np.int64)
    for i in order:
        ranked[fill[idx[i]]] = i
        fill[idx[i]] += 1
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
        d_pub[i] = min(max(d_cons[i], min_m), max_m)
        pt_cm[i] = min(max(np.int64(np.rint(d_pub[i] * 100)), min_cm), max_cm)
        if touch > 0 and d_h[i] <= touch:
            pt_cm[i] = 0
    xy_m = np.full((SECTOR_COUNT, 2), np.nan)
    has_obs = n_obs >= k
    for s in range(SECTOR_COUNT):
        if has_obs[s]:
            pt = pick[s]
            dist[s] = pt_cm[pt]
            state[s] = _S_OBSTACLE
            range_m[s] = d_pub[pt]
            sigma_m[s] = sig[pt]
            xy_m[s, 0] = d_pub[pt] * math.cos(bearing[pt])
            xy_m[s, 1] = d_pub[pt] * math.sin(bearing[pt])
        elif fully[s] and n_obs[s] == 0 and n_veto[s] == 0 and n_clr[s] >= cfg[_K_N_CLR]:
            dist[s] = max_cm + 1
            state[s] = _S_CLEAR

    inferred = _infer_between_k(state, dist, range_m, sigma_m, np.int64(cfg[_K_GAP]), cfg[_K_REL_TOL])
    narrow = _infer_narrow_k(state, dist, range_m, sigma_m, xy_m, ~inferred, np.int64(cfg[_K_NARROW_N]), cfg[_K_NARROW_M],
                             min_m, max_m, min_cm, max_cm)
    inferred |= narrow

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
            if pt >= 0 and (not has_obs[s] or d_pub[pt] < range_m[s]):
                state[s] = _S_OBSTACLE
                dist[s], range_m[s], sigma_m[s] = pt_cm[pt], d_pub[pt], sig[pt]
                inferred[s] = True
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
            if state[s] == _S_CLEAR or (state[s] == _S_OBSTACLE and d_pub[pt] < range_m[s]):
                state[s] = _S_OBSTACLE
                dist[s], range_m[s], sigma_m[s] = pt_cm[pt], d_pub[pt], sig[pt]
                inferred[s] = True
                pick[s] = pt

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
            fwd_vals[1], fwd_vals[2] = sig[pt], d_h[pt]
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
        rc = min_m if min_m > r_cons[pt] else r_cons[pt]  # Python's max(r_cons, min_distance_m)
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
        ob_bearing[q], ob_cm[q] = bearing[sel[q]], pt_cm[sel[q]]
    o = sel.size
    for s in range(SECTOR_COUNT):
        if inferred[s]:
            for _ in range(k):
                ob_bearing[o], ob_cm[o] = (s * SECTOR_DEG) * _DEG2RAD, dist[s]
                o += 1
    return (dist, state, range_m, sigma_m, n_obs, n_clr, n_mem, inferred, used, ob_bearing, ob_cm, fwd_state, fwd_vals, near_p,
            near_vals, near_sector)


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
    """Compile the sector kernels on a tiny scene (live, remembered with spread, every rule on)."""
    cfg = SectorConfig(infer_vertical=True, infer_vertical_one_side=True, cap_above_m=2.5, ground_margin_m=0.5,
                       infer_narrow_gap_m=4.0)
    p = np.array([[10.0, 0.0, 0.0], [10.0, 1.0, -2.0], [50.0, 0.5, 0.0]])
    compute_sectors(p, np.full(3, 0.5), np.ones(3, bool), np.ones(3, bool), math.radians(60.0), 0.0, cfg,
                    roll_pitch_rad=(0.1, 0.05), velocity_body=(2.0, 0.0, -0.5), vfov_rad=math.radians(45.0),
                    remembered_p_body=np.array([[5.0, -3.0, 0.0]]), remembered_sigma=np.array([0.3]),
                    remembered_tangential_sigma=np.array([1.0]), ground_height_m=-5.0)
