"""The sector ring's constants and types (docs/derivations/sectors.md): 72 sectors of 5°, the
``[sectors]`` table (:class:`SectorConfig`), the result of :func:`companion.core.sectors.compute_sectors`
(:class:`Sectors`, :class:`ForwardRange`, :class:`Obstacle3D`) and the operations on published sectors
that result needs (:func:`sector_index`, :class:`SectorRanking`, :func:`rotate_sectors`).

Shared by the numpy reference (:mod:`companion.core.sectors`, which re-exports every public name
defined here), its inference rules (:mod:`companion.core.sectors_infer`) and the compiled kernels
(:mod:`companion.core.sectors_kernels`); it imports none of them.
"""

from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np

from companion.config import require, require_finite
from companion.errors import InputError

#: OBSTACLE_DISTANCE holds 72 distances; 72 × 5° covers 360° (docs/derivations/sectors.md).
SECTOR_COUNT = 72
#: Width of one sector, degrees (``increment`` / ``increment_f`` of OBSTACLE_DISTANCE).
SECTOR_DEG = 5.0
#: "Unknown" in OBSTACLE_DISTANCE / DISTANCE_SENSOR (MAVLink spec).
UNKNOWN_CM = 65535

_SAMPLES_PER_SECTOR = 5  # bearings tested per sector for the field-of-view mask (edges + inside)
#: each sector's centre bearing, degrees, signed (−180, 180]: right of forward positive
SECTOR_BEARING_DEG = (np.arange(SECTOR_COUNT) * SECTOR_DEG + 180.0) % 360.0 - 180.0
SECTOR_BEARING_DEG.flags.writeable = False


class SectorState(enum.IntEnum):
    """What a sector claims."""

    UNKNOWN = 0  # UINT16_MAX: not seen, or seen without evidence
    OBSTACLE = 1  # a distance in [min_distance, max_distance] (or 0 = touching)
    CLEAR = 2  # max_distance + 1: evidence of free space up to max_distance


class SectorSource(enum.IntEnum):
    """Where an obstacle sector's claim comes from (:meth:`Sectors.sources`; the sector log,
    docs/derivations/sectors.md "Where a claim comes from")."""

    NONE = 0  # no obstacle claimed (unknown or clear)
    LIVE = 1  # converged points the camera tracks now, no map point among them
    MIXED = 2  # live points and remembered (map) points: the published one may be either
    REMEMBERED = 3  # remembered (map) points only: out of view, or in view where no live point is
    INFERRED = 4  # inferred across sectors: between two consistent sides, or a narrow gap
    VERTICAL = 5  # inferred from points above or below the band: a vertical structure through it, the cap from above


class UnknownReason(enum.IntEnum):
    """Why a sector is unknown (UINT16_MAX), the first rule it fell short of (:func:`unknown_reasons`;
    docs/derivations/sectors.md, "Why a sector is unknown").  :attr:`NONE` where it makes a claim."""

    NONE = 0  # the sector claims an obstacle or "clear"
    NOT_SEEN = 1  # out of the camera's view and no remembered obstacle published there
    NO_POINTS = 2  # in view, but no tracked point in the sector at any height (a texture-poor surface, a refill pending)
    BESIDE_BAND = 3  # tracked points, none of them in the band around the flight path (all above or below it)
    FEW_FAR = 4  # converged points beyond max_distance in the band, fewer than min_points_clear: no evidence of "clear"
    VETOED = 5  # enough far points for "clear", but a point that may lie nearer forbids it (unconverged, beside the band, across an edge)
    RANGING = 6  # points in the band not yet converged (the filter is still ranging them)
    FEW_NEAR = 7  # converged points within max_distance, fewer than min_points_obstacle
    PARTLY_IN_VIEW = 8  # evidence of "clear", but part of the sector lies outside the view
    HELD = 9  # "clear" withheld: beside a near obstacle (clear_corridor_m) or not yet confirmed (clear_confirm_frames)
    TURNED = 10  # the vehicle turned since exposure and the obstacle that held this bearing moved to a neighbouring sector


def unknown_reasons(state, in_view, fully_in_view, n_obstacle, n_clear, n_veto, n_ranging, n_tracked,
                    min_points_obstacle: int, min_points_clear: int) -> np.ndarray:
    """(72,) int8 :class:`UnknownReason` of each sector from the counts the rules made
    (docs/derivations/sectors.md, "Why a sector is unknown"): ``n_obstacle`` converged in-band points within
    max_distance, ``n_clear`` evidence of "clear", ``n_veto`` vetoes of "clear", ``n_ranging`` unconverged live
    points in the band, ``n_tracked`` usable live points at any height.  A later cause in this list wins
    over an earlier one: no points, beside the band, few far, vetoed, ranging, few near, partly in view,
    held; out of view without a claim is :attr:`~UnknownReason.NOT_SEEN`; a claim is
    :attr:`~UnknownReason.NONE`."""
    R = UnknownReason
    enough = np.asarray(n_clear) >= min_points_clear
    veto = np.asarray(n_veto) > 0
    why = np.full(SECTOR_COUNT, R.NO_POINTS, np.int8)
    why[np.asarray(n_tracked) > 0] = R.BESIDE_BAND
    why[np.asarray(n_clear) > 0] = R.FEW_FAR
    why[enough & veto] = R.VETOED
    why[np.asarray(n_ranging) > 0] = R.RANGING
    n_obs = np.asarray(n_obstacle)
    why[(n_obs > 0) & (n_obs < min_points_obstacle)] = R.FEW_NEAR
    clear_ok = enough & ~veto & (n_obs == 0)
    why[clear_ok & ~np.asarray(fully_in_view, bool)] = R.PARTLY_IN_VIEW
    why[clear_ok & np.asarray(fully_in_view, bool)] = R.HELD  # the clear rule held; a later rule withheld it
    why[~np.asarray(in_view, bool)] = R.NOT_SEEN
    why[np.asarray(state) != SectorState.UNKNOWN] = R.NONE
    return why


def forward_unknown_reason(sectors: "Sectors", forward_half_width_deg: float) -> UnknownReason:
    """Why the forward reading (:attr:`Sectors.forward`) is unknown: the reason of the first unknown sector of its
    window (± ``forward_half_width_deg``, nearest the axis first); :attr:`UnknownReason.NONE` when it claims."""
    if SectorState(sectors.forward.state) != SectorState.UNKNOWN:
        return UnknownReason.NONE
    fwd = np.flatnonzero(np.abs(SECTOR_BEARING_DEG) <= forward_half_width_deg + 1e-9)
    fwd = fwd[np.argsort(np.abs(SECTOR_BEARING_DEG[fwd]), kind="stable")]
    why = np.asarray(sectors.unknown_reason)[fwd]
    why = why[why > 0]
    return UnknownReason(int(why[0])) if why.size else UnknownReason.NONE


@dataclasses.dataclass(frozen=True)
class SectorConfig:
    """The ``[sectors]`` table."""

    min_distance_m: float = 0.5  # nearest range reported; nearer obstacles are reported at this distance
    max_distance_m: float = 40.0  # farthest range claimed; beyond it, with evidence, a sector is "clear" (max + 1 cm)
    sigma_k: float = 2.0  # conservative range = estimate − k·σ
    sigma_k_far: float = 1.0  # k of the conservative range far away: k falls linearly from sigma_k at sigma_k_taper_from_m to this at sigma_k_taper_to_m (the point's horizontal estimate) and stays there beyond; a value above sigma_k acts as sigma_k (the taper only narrows)
    sigma_k_taper_from_m: float = 10.0  # ... where the taper starts, m: nearer, the full sigma_k margin (where a vehicle brakes)
    sigma_k_taper_to_m: float = 20.0  # ... where it ends, m; 0 = off (sigma_k at every range)
    band_mode: str = "metres"  # vertical band around the flight path: "metres" (fixed height) or "degrees" (cone)
    band_half_height_m: float = 1.5  # half height of the band, metres mode
    band_half_angle_deg: float = 10.0  # half angle of the band, degrees mode
    min_points_obstacle: int = 1  # converged in-band points a sector needs to report an obstacle (the n-th nearest is reported)
    min_points_clear: int = 3  # converged in-band points beyond max_distance a sector needs to be "clear"
    unconverged_veto_clear: bool = True  # a valid but unconverged point that may lie within max_distance forbids "clear"
    unconverged_veto_margin_m: float = 2.5  # ... also when it lies up to this far above or below the band (a structure seen just outside the band, as the cap and vertical rules read it, may stand through it), m; 0 = in the band only
    converged_veto_margin_m: float = 2.5  # a converged point that lies (conservatively) within max_distance up to this far above or below the band forbids "clear" in its sector (a pole seen just outside the band, whose own in-band corners ride its silhouette at the background's depth), m; 0 = off
    clear_confirm_frames: int = 1  # "clear" is published only once a sector has been clear in this many consecutive frames (counted over the world's bearings as the vehicle turns); before that it is sent as unknown; 1 = at once
    clear_line_of_sight: bool = True  # metres mode: a converged point beyond max_distance is also evidence of "clear" when its line of sight stays inside the band out to max_distance (|offset|·max_distance/d ≤ half height), not only when the point itself is in the band; off = in-band points only
    clear_edge_margin_deg: float = 1.0  # a point that claims or vetoes its sector within this of the sector's edge also forbids "clear" across that edge (a surface goes on past its last corner), degrees; 0 = off
    clear_corridor_m: float = 0.5  # no "clear" in a sector whose nearer edge lies within asin(this / r) of an obstacle sector's edge (r its published range): a clear bearing beside a near obstacle is no way through for a vehicle this wide on each side, and PX4 steers into it, m; 0 = off
    corridor_far_ratio: float = 2.0  # a neighbour within that corridor whose claim lies more than this many times farther than the obstacle sector's range and out of the camera's view is capped at that range (marked inferred): the surface seen past a near obstacle's edge is no way through either, and the remembered obstacle may reach into the neighbour; nothing while clear_corridor_m is 0; 0 = off
    touching_distance_m: float = 0.0  # estimate at or below this is sent as 0 (touching); 0 = never (ArduPilot discards 0)
    forward_half_width_deg: float = 2.5  # DISTANCE_SENSOR forward window: sectors centred within ± this (2.5 = sector 0 only)
    nearest_count: int = 5  # nearest obstacles (one per sector) kept for OBSTACLE_DISTANCE_3D
    flight_path_min_speed_mps: float = 1.0  # below this speed the band is centred on the horizontal
    flight_path_max_angle_deg: float = 30.0  # the band centre climbs or descends at most this steeply
    remembered_spread_k: float = 1.0  # a remembered point is spread over bearings ± remembered_spread_k·σ_tangential/range ...
    remembered_max_spread_deg: float = 15.0  # ... at most this far, degrees
    remembered_drop_spread_deg: float = 90.0  # a remembered point whose k·σ_tangential/range exceeds this is not published (its bearing is too uncertain to place it), degrees
    remembered_drop_across_only: bool = False  # ... only when its σ_tangential also exceeds its range σ: uncertain across the line of sight (ranged from afar, passed close by), not a point whose whole σ grew with time (hovered before)
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
    unconverged_cap_k: float = 2.0  # a live in-band point not yet converged bounds its obstacle sector's claim from above at r/(1 − k·σ_r/r) (k σ in inverse depth), horizontal: the claim gets no farther than it (only nearer; clear and unknown unchanged); 0 = off
    cap_gate_k: float = 0.0  # a point above or below the band (cap, vertical structure) replaces an obstacle sector's claim only when its estimate lies nearer than the claim's by more than this many combined σ (a different, nearer surface); 0 = whenever its conservative range is nearer
    ground_margin_m: float = 0.5  # with the ground's height known, points less than this above it are the ground: never an obstacle nor evidence of clear (taking off, landing, flying low); 0 = off
    fuse_gate_k: float = 2.0  # a sector's live obstacle points whose horizontal ranges agree with its nearest one within this many combined σ are one surface: their fused range replaces the nearest of them (the nearest of many noisy points is biased near); 0 = off (the n-th nearest point)
    fuse_correlation: float = 0.3  # correlation of those points' range errors through the shared pose: the fused σ never falls below √ρ of theirs

    def __post_init__(self) -> None:
        require_finite("min_distance_m", self.min_distance_m, positive=True)
        require_finite("max_distance_m", self.max_distance_m, positive=True)
        require(self.max_distance_m > self.min_distance_m, "max_distance_m must exceed min_distance_m")
        require(
            round(self.max_distance_m * 100) + 1 < UNKNOWN_CM,
            f"max_distance_m must be < 655.33 m (max_distance + 1 cm must stay below UINT16_MAX), got {self.max_distance_m}",
        )
        require_finite("sigma_k", self.sigma_k, nonnegative=True)
        require_finite("sigma_k_far", self.sigma_k_far, nonnegative=True)
        require_finite("sigma_k_taper_from_m", self.sigma_k_taper_from_m, nonnegative=True)
        require_finite("sigma_k_taper_to_m", self.sigma_k_taper_to_m, nonnegative=True)
        if self.sigma_k_taper_to_m > 0:
            require(self.sigma_k_taper_to_m > self.sigma_k_taper_from_m,
                    f"sigma_k_taper_to_m must exceed sigma_k_taper_from_m ({self.sigma_k_taper_from_m}) or be 0 (off), got {self.sigma_k_taper_to_m}")
        require(self.band_mode in ("metres", "degrees"), f"band_mode must be 'metres' or 'degrees', got {self.band_mode!r}")
        require_finite("band_half_height_m", self.band_half_height_m, positive=True)
        require_finite("band_half_angle_deg", self.band_half_angle_deg, positive=True)
        require(self.band_half_angle_deg < 90, f"band_half_angle_deg must be < 90, got {self.band_half_angle_deg}")
        for name in ("min_points_obstacle", "min_points_clear", "nearest_count", "clear_confirm_frames"):
            v = getattr(self, name)
            require(isinstance(v, int) and not isinstance(v, bool) and v >= 1, f"{name} must be an integer >= 1, got {v!r}")
        require(isinstance(self.unconverged_veto_clear, bool), "unconverged_veto_clear must be true or false")
        require(isinstance(self.clear_line_of_sight, bool), f"clear_line_of_sight must be true or false, got {self.clear_line_of_sight!r}")
        require_finite("unconverged_veto_margin_m", self.unconverged_veto_margin_m, nonnegative=True)
        require_finite("converged_veto_margin_m", self.converged_veto_margin_m, nonnegative=True)
        require_finite("clear_edge_margin_deg", self.clear_edge_margin_deg, nonnegative=True)
        require(self.clear_edge_margin_deg < SECTOR_DEG / 2, f"clear_edge_margin_deg must be < {SECTOR_DEG / 2}")
        require_finite("clear_corridor_m", self.clear_corridor_m, nonnegative=True)
        require_finite("corridor_far_ratio", self.corridor_far_ratio, nonnegative=True)
        require(self.corridor_far_ratio == 0 or self.corridor_far_ratio >= 1, f"corridor_far_ratio must be 0 (off) or >= 1, got {self.corridor_far_ratio}")
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
        require(isinstance(self.remembered_drop_across_only, bool), f"remembered_drop_across_only must be true or false, got {self.remembered_drop_across_only!r}")
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
        require_finite("cap_gate_k", self.cap_gate_k, nonnegative=True)
        require_finite("unconverged_cap_k", self.unconverged_cap_k, nonnegative=True)
        require_finite("ground_margin_m", self.ground_margin_m, nonnegative=True)
        require_finite("fuse_gate_k", self.fuse_gate_k, nonnegative=True)
        require_finite("fuse_correlation", self.fuse_correlation, nonnegative=True)
        require(self.fuse_correlation <= 1.0, f"fuse_correlation must be in [0, 1], got {self.fuse_correlation}")

    @property
    def min_distance_cm(self) -> int:
        return int(round(self.min_distance_m * 100))

    @property
    def max_distance_cm(self) -> int:
        return int(round(self.max_distance_m * 100))


def margin_k(d_m, k_near: float, k_far: float, from_m: float, to_m: float):
    """k of the conservative value d − k·σ at horizontal estimate ``d_m`` (docs/derivations/sectors.md,
    "The margin's taper"): ``k_near`` up to ``from_m``, falling linearly to ``k_far`` at ``to_m`` and ``k_far``
    beyond; ``k_near`` everywhere when ``to_m`` is 0 (off).  ``k_far`` above ``k_near`` acts as ``k_near``
    (the taper only narrows).  A distance that is not a number counts as far (such a point's σ enters no
    value).  Scalar in, scalar out; the compiled kernel computes the same expression in the same order."""
    if not to_m > 0:
        return np.full(np.shape(d_m), k_near) if np.ndim(d_m) else k_near
    k_far = min(k_far, k_near)
    d = np.asarray(d_m, float)
    frac = np.where(np.isnan(d), 1.0, np.clip((d - from_m) / (to_m - from_m), 0.0, 1.0))
    k = k_near + (k_far - k_near) * frac
    return k if np.ndim(d_m) else float(k)


def estimate_from_conservative(value_m, sigma_m, k_near: float, k_far: float, from_m: float, to_m: float):
    """The estimate d whose conservative value d − k(d)·σ (:func:`margin_k`) is ``value_m``: the inverse of
    the publication (docs/derivations/sectors.md, "The margin's taper").  Unique, because k never grows
    with d (d − k(d)·σ increases with d).  Piecewise: d = v + k_near·σ where that lies at or before
    ``from_m``, d = v + k_far·σ where that lies at or beyond ``to_m``, else the linear piece solved for d."""
    v, s = np.asarray(value_m, float), np.asarray(sigma_m, float)
    if not to_m > 0:
        out = v + k_near * s
    else:
        k_far = min(k_far, k_near)
        slope = (k_far - k_near) / (to_m - from_m)  # ≤ 0
        d_near, d_far = v + k_near * s, v + k_far * s
        d_mid = (v + (k_near - slope * from_m) * s) / (1.0 - slope * s)
        out = np.where(d_near <= from_m, d_near, np.where(d_far >= to_m, d_far, d_mid))
    return out if np.ndim(value_m) or np.ndim(sigma_m) else float(out)


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
    """Result of :func:`~companion.core.sectors.compute_sectors`; ``distances_cm`` is ready for OBSTACLE_DISTANCE."""

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
    inferred_vertical: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(SECTOR_COUNT, bool))  # (72,) of those, set by a rule on points above or below the band (a vertical structure, the cap from above)
    unknown_reason: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(SECTOR_COUNT, np.int8))  # (72,) UnknownReason of each unknown sector (0 where it claims)

    @property
    def n_inferred(self) -> int:
        return int(np.count_nonzero(self.inferred))

    def sources(self) -> np.ndarray:
        """(72,) int8 :class:`SectorSource` of each sector's claim, from the points counted behind it
        (``obstacle_points``, of which ``remembered_points`` are map points) and ``inferred``
        (docs/derivations/sectors.md, "Where a claim comes from")."""
        n, mem = np.asarray(self.obstacle_points), np.asarray(self.remembered_points)
        src = np.where(mem == 0, SectorSource.LIVE, np.where(mem < n, SectorSource.MIXED, SectorSource.REMEMBERED))
        src = np.where(self.inferred, np.where(self.inferred_vertical, SectorSource.VERTICAL, SectorSource.INFERRED), src)
        return np.where(self.state == SectorState.OBSTACLE, src, SectorSource.NONE).astype(np.int8)

    def rotated_sources(self, yaw_change_rad: float, rotated_cm=None) -> np.ndarray:
        """:meth:`sources` for the distances of :meth:`rotated` (the same yaw change; pass them as
        ``rotated_cm`` when already computed).

        New sector ``i`` holds what old sectors ``i + lo`` and ``i + lo + 1`` held (``lo`` = ⌊Δψ / 5°⌋,
        as in :func:`rotate_sectors`; a point re-binned at bearing − Δψ lands in one of them): it takes
        the source of the one whose published value it now carries, else of the nearer obstacle of
        the two; :attr:`SectorSource.NONE` where the turned sector claims no obstacle."""
        if not math.isfinite(yaw_change_rad):
            return np.zeros(SECTOR_COUNT, np.int8)
        d_new = np.asarray(self.rotated(yaw_change_rad) if rotated_cm is None else rotated_cm).astype(np.int64)
        src = self.sources()
        lo, _ = sector_shift(yaw_change_rad)
        i = np.arange(SECTOR_COUNT)
        a, b = (i + lo) % SECTOR_COUNT, (i + lo + 1) % SECTOR_COUNT
        old = self.distances_cm.astype(np.int64)
        obs = self.state == SectorState.OBSTACLE
        take_a = obs[a] & (old[a] == d_new)
        take_b = ~take_a & obs[b] & (old[b] == d_new)
        nearer_a = obs[a] & (~obs[b] | (old[a] <= old[b]))
        out = np.where(take_a, src[a], np.where(take_b, src[b], np.where(nearer_a, src[a], np.where(obs[b], src[b], 0))))
        out = out.astype(np.int8)
        out[d_new > self.max_distance_cm] = SectorSource.NONE
        return out

    def rotated_reasons(self, yaw_change_rad: float, rotated_cm=None) -> np.ndarray:
        """:attr:`unknown_reason` for the distances of :meth:`rotated` (the same yaw change; pass them as
        ``rotated_cm`` when already computed): a turned sector that is unknown takes the reason of the old
        sector it overlaps that was unknown (the first of the two, as :func:`rotate_sectors` reads them);
        where neither was (an obstacle whose points now lie in the sector beside), :attr:`UnknownReason.TURNED`;
        :attr:`UnknownReason.NONE` where the turned sector makes a claim."""
        if not math.isfinite(yaw_change_rad):
            return np.full(SECTOR_COUNT, UnknownReason.TURNED, np.int8)
        d_new = np.asarray(self.rotated(yaw_change_rad) if rotated_cm is None else rotated_cm).astype(np.int64)
        why = np.asarray(self.unknown_reason, np.int8)
        lo, frac = sector_shift(yaw_change_rad)
        i = np.arange(SECTOR_COUNT)
        a, b = (i + lo) % SECTOR_COUNT, (i + lo + 1) % SECTOR_COUNT
        if frac < 1e-6:
            b = a
        elif frac > 1 - 1e-6:
            a = b
        out = np.where(why[a] > 0, why[a], np.where(why[b] > 0, why[b], UnknownReason.TURNED)).astype(np.int8)
        out[d_new != UNKNOWN_CM] = UnknownReason.NONE
        return out

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

def unknown_sectors(config: SectorConfig = SectorConfig()) -> np.ndarray:
    """All sectors unknown (what to send while no valid ranges are produced)."""
    return np.full(SECTOR_COUNT, UNKNOWN_CM, dtype=np.uint16)


def sector_shift(yaw_change_rad: float, n: int = SECTOR_COUNT, increment_deg: float = SECTOR_DEG) -> tuple[int, float]:
    """(lo, frac) of a yaw change Δψ (+ = turned right): new sector ``i`` covers the bearings old sectors ``i + lo``
    and ``i + lo + 1`` covered, the second by the fraction ``frac`` of a sector (Δψ / increment wrapped to
    [−n/2, n/2) = lo + frac)."""
    shift = math.degrees(yaw_change_rad) / increment_deg
    shift = (shift + n / 2) % n - n / 2  # wrap to [-n/2, n/2)
    lo = math.floor(shift)
    return lo, shift - lo


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
    lo, frac = sector_shift(yaw_change_rad, n, increment_deg)
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


#: PX4's collision prevention keeps 36 bins of 10° and reads, for bin ``i``, the one
#: OBSTACLE_DISTANCE element at ``ceil((10 i − angle_offset) / increment)``: with 5° sectors the even
#: ones only (``CollisionPrevention::_addObstacleSensorData``; docs/derivations/sectors.md, "PX4's 10° bins").
PX4_BIN_DEG = 10.0


def fold_into_bins(distances, max_distance_cm: int, sources=None, bin_deg: float = PX4_BIN_DEG):
    """Distances for a reader that samples one element per ``bin_deg`` bin (PX4: the even elements)
    and treats it as the whole bin (docs/derivations/sectors.md, "PX4's 10° bins").

    The element read for bin ``i`` (``k = i·bin_deg / 5°``), when it makes a claim (an obstacle or
    clear), takes the nearest obstacle of the sectors the bin overlaps, ``k − h … k + h`` with
    ``h = bin_deg / 10°`` (the odd sectors beside it lie half inside it); where none of them holds an
    obstacle it keeps its own value ("clear" is only ever the sector's own).  An *unknown* element
    stays unknown: PX4 refuses to move into a bin without data, and a range from beside it must not
    lift that (the centre may be a texture-less wall nobody ranged).  Elements no bin reads are
    unchanged, so a reader of all 72 (ArduPilot, a ground station) sees each obstacle where it was
    plus, at most, its value one sector over.  Returns ``(distances uint16, sources)`` with
    ``sources`` (the :class:`SectorSource` of each element, optional) following the value each
    element now carries.
    """
    d = np.asarray(distances)
    if d.ndim != 1 or d.size != SECTOR_COUNT:
        raise InputError(f"distances must be a ({SECTOR_COUNT},) array, got shape {d.shape}")
    step = bin_deg / SECTOR_DEG
    if not (step >= 1 and abs(step - round(step)) < 1e-9 and SECTOR_COUNT % round(step) == 0):
        raise InputError(f"bin_deg must be a multiple of {SECTOR_DEG:g}° that divides 360°, got {bin_deg!r}")
    step = int(round(step))
    d = d.astype(np.int64)
    src = None if sources is None else np.asarray(sources).astype(np.int8)
    if step == 1:
        return d.astype(np.uint16), src
    h = step // 2
    read = np.arange(0, SECTOR_COUNT, step)  # the elements a bin reads
    offs = np.arange(-h, h + 1)
    cand = (read[:, None] + offs[None, :]) % SECTOR_COUNT  # (bins, 2h + 1) sectors each bin overlaps
    vals = np.where(d[cand] <= max_distance_cm, d[cand], np.iinfo(np.int64).max)
    j = np.argmin(vals, axis=1)
    j = np.where(vals[np.arange(len(read)), h] == vals[np.arange(len(read)), j], h, j)  # a tie goes to the own sector
    has = (vals[np.arange(len(read)), j] <= max_distance_cm) & (d[read] != UNKNOWN_CM)
    take = cand[np.arange(len(read)), j]
    out = d.copy()
    out[read[has]] = d[take[has]]
    if src is not None:
        src = src.copy()
        src[read[has]] = src[take[has]]
    return out.astype(np.uint16), src


#: ArduPilot's proximity boundary keeps 8 faces of 45°; a DISTANCE_SENSOR *replaces* its face's value
#: and one outside [min, max] *resets* the face (``AP_Proximity_MAV::handle_distance_sensor_msg``).
ARDUPILOT_FACE_HALF_DEG = 22.5


def forward_reading_consistent(state: str, distance_cm: int, distances, max_distance_cm: int, rel_tol: float = 0.1,
                               face_half_deg: float = ARDUPILOT_FACE_HALF_DEG) -> bool:
    """Whether a forward DISTANCE_SENSOR reading (``state`` "obstacle" at ``distance_cm``, "clear" or
    "unknown") leaves an autopilot holding what the OBSTACLE_DISTANCE ``distances`` already tell it
    about the region the reading is merged into (docs/derivations/sectors.md, "The forward
    DISTANCE_SENSOR and the autopilots"):

    * ArduPilot writes it over its whole front face (±22.5°), into the face's low-pass filter: an
      obstacle reading must not lie farther than the nearest obstacle of the sectors in that face by
      more than ``rel_tol`` of that one (the same surface, its sectors' conservative values scatter;
      a nearer pole or edge beside the axis withholds it); a reading outside [min, max] wipes the
      face, so "clear" only when no sector there holds an obstacle;
    * PX4 reads an out-of-range reading (UINT16_MAX, "clear") as free space out to max_distance:
      "clear" only where sector 0 itself is clear, and "unknown" never.
    """
    d = np.asarray(distances).astype(np.int64)
    face = d[np.abs(SECTOR_BEARING_DEG) < face_half_deg]
    face_obs = face[face <= max_distance_cm]
    if state == "obstacle":
        return bool(face_obs.size == 0 or int(distance_cm) <= (1.0 + rel_tol) * int(face_obs.min()))
    if state == "clear":
        return bool(face_obs.size == 0 and int(d[0]) == max_distance_cm + 1)
    return False
