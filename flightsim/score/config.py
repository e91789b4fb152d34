"""The ``[score]`` table (:class:`ScoreConfig`, configs/score.toml) and the codes of a cell: what
was published (``REP_*``) and what the truth says (``TRUTH_*``).  Definitions: :mod:`flightsim.score`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from companion.config import require, require_finite


N_SECTORS = 72
SECTOR_DEG = 5.0
UNKNOWN_CM = 65535

# published value of a cell
REP_UNKNOWN, REP_RANGE, REP_CLEAR, REP_INVALID = 0, 1, 2, 3
# truth of a cell
TRUTH_NONE, TRUTH_UNSEEN, TRUTH_OBSTACLE, TRUTH_CLEAR = -1, 0, 1, 2


# ---------------------------------------------------------------------- configuration ----------
@dataclasses.dataclass(frozen=True)
class ScoreConfig:
    """The ``[score]`` table (configs/score.toml)."""

    tolerance_m: float = 2.0  # absolute part of the range tolerance, m
    tolerance_rel: float = 0.2  # relative part of the range tolerance, fraction of the true distance
    sigma_k: float = 2.0  # k of the companion's conservative value (estimate − k·σ), [sectors] sigma_k
    sigma_k_far: float = 2.0  # the companion's [sectors] sigma_k_far (k far away, with its taper on)
    sigma_k_taper_from_m: float = 10.0  # the companion's [sectors] sigma_k_taper_from_m, m
    sigma_k_taper_to_m: float = 0.0  # the companion's [sectors] sigma_k_taper_to_m, m (0 = no taper: k = sigma_k at every range)
    quality_zero_rel_sigma: float = 0.5  # the companion's [outputs] quality_zero_rel_sigma (σ from signal_quality)
    range_bins_m: tuple[float, ...] = (0.0, 10.0, 20.0, 40.0)  # lower edges of the range bins, m (the last bin is open)
    detection_bins_m: tuple[float, ...] = (0.0, 5.0, 10.0, 20.0, 30.0, 40.0)  # lower edges of the detection-by-true-range bins, m
    warmup_s: float = 2.0  # cells of messages stamped within this long after the first truth frame are not scored, s
    near_range_m: float = 10.0  # "near" obstacle cells: true range below this (target_detection_near), m
    remember_window_s: float = 10.0  # remembered: the obstacle was in view at most this long before, s
    remember_max_travel_m: float = 20.0  # ... and the vehicle moved less than this since, m
    remember_point: bool = True  # remembered also needs the cell's own world point to have been in view then (a long wall counts only where seen)
    remember_visible: bool = True  # ... and in the line of sight then: no solid of the world between the vehicle and the point (a box's far faces were never seen; needs the world)
    visible_tolerance_m: float = 1.5  # a point counts as in the line of sight when the first solid on the ray lies no nearer than this short of it, m (a thin pole hides its own far side: 1.5 m covers the thickest pole or trunk of the scenarios) ...
    visible_tolerance_rel: float = 0.05  # ... or this fraction of its distance, whichever is larger (the cell's point sits on its sector's centre bearing, not on the surface's nearest point)
    truth_max_age_s: float = 0.1  # the truth frame used for a message may be at most this much older than its stamp, s
    capture_snap: float = 0.5  # a mapped exposure time snaps to the nearest truth frame within this many frame periods
    pair_window_s: float = 0.005  # a DISTANCE_SENSOR pairs with the OBSTACLE_DISTANCE sent at most this much before it, s
    obstacle_link_m: float = 3.0  # truth points this close (m) belong to one obstacle
    obstacle_link_rel: float = 0.12  # ... or this fraction of their distance, whichever is larger (sector spacing is 8.7 %)
    target_no_false_obstacle: float = 0.98  # target: share of messages with no false obstacle in a clear sector (>=)
    target_dangerous_clear: float = 0.005  # target: share of obstacle cells reported clear (<=)
    target_false_obstacle: float = 0.01  # target: share of clear cells with a false obstacle (<=)
    target_detection: float = 0.90  # target: share of in-view obstacle cells with a range within tolerance (>=)
    target_detection_near: float = 0.95  # target: the same for in-view obstacle cells nearer than near_range_m (>=)
    target_remembered: float = 0.90  # target: share of remembered out-of-view obstacle cells within tolerance (>=)
    rangeable_window_s: float = 20.0  # rangeable: the camera's views of the cell's point over at most this long before the message, s
    rangeable_parallax_deg: float = 1.0  # ... rangeable when its line of sight from one of those views differs from today's by at least this (parallax), deg
    rangeable_scale: float = 0.1  # ... or its distance from one of them differs from today's by at least this fraction (looming: image scale changed by it)
    rangeable_visible: bool = True  # ... and that view had the point in its line of sight (visible_tolerance_*; needs the world)
    beside_sectors: int = 2  # a false obstacle within this many sectors of an obstacle at its range is reported as "beside an obstacle" (diagnostic only)
    nees_confidence: float = 0.95  # two-sided probability of the NEES band
    nees_gap_s: float = 0.5  # forward NEES samples further apart than this start a new stretch (effective sample size), s

    def __post_init__(self) -> None:
        require_finite("tolerance_m", self.tolerance_m, nonnegative=True)
        require_finite("tolerance_rel", self.tolerance_rel, nonnegative=True)
        require_finite("sigma_k", self.sigma_k, nonnegative=True)
        for name in ("sigma_k_far", "sigma_k_taper_from_m", "sigma_k_taper_to_m"):
            require_finite(name, getattr(self, name), nonnegative=True)
        if self.sigma_k_taper_to_m > 0:
            require(self.sigma_k_taper_to_m > self.sigma_k_taper_from_m,
                    "the margin's taper needs sigma_k_taper_to_m > sigma_k_taper_from_m")
        require_finite("quality_zero_rel_sigma", self.quality_zero_rel_sigma, positive=True)
        for name in ("range_bins_m", "detection_bins_m"):
            b = getattr(self, name)
            require(isinstance(b, tuple) and len(b) >= 1, f"{name} must be a non-empty list of lower edges")
            for v in b:
                require_finite(name, v, nonnegative=True)
            require(all(b[i] < b[i + 1] for i in range(len(b) - 1)), f"{name} must increase, got {list(b)}")
        require_finite("warmup_s", self.warmup_s, nonnegative=True)
        require_finite("near_range_m", self.near_range_m, positive=True)
        require_finite("remember_window_s", self.remember_window_s, positive=True)
        require_finite("remember_max_travel_m", self.remember_max_travel_m, positive=True)
        for name in ("remember_point", "remember_visible", "rangeable_visible"):
            require(isinstance(getattr(self, name), bool), f"{name} must be true or false, got {getattr(self, name)!r}")
        require_finite("visible_tolerance_m", self.visible_tolerance_m, nonnegative=True)
        require_finite("visible_tolerance_rel", self.visible_tolerance_rel, nonnegative=True)
        require(self.visible_tolerance_rel < 1, f"visible_tolerance_rel must be below 1, got {self.visible_tolerance_rel}")
        require_finite("rangeable_window_s", self.rangeable_window_s, positive=True)
        require_finite("rangeable_parallax_deg", self.rangeable_parallax_deg, positive=True)
        require(self.rangeable_parallax_deg < 90, f"rangeable_parallax_deg must be below 90, got {self.rangeable_parallax_deg}")
        require_finite("rangeable_scale", self.rangeable_scale, positive=True)
        require(isinstance(self.beside_sectors, int) and not isinstance(self.beside_sectors, bool) and 0 <= self.beside_sectors <= 36,
                f"beside_sectors must be an integer in 0..36, got {self.beside_sectors!r}")
        require_finite("truth_max_age_s", self.truth_max_age_s, positive=True)
        require_finite("capture_snap", self.capture_snap, positive=True)
        require(self.capture_snap <= 0.5, f"capture_snap must be <= 0.5 (half a frame), got {self.capture_snap}")
        require_finite("pair_window_s", self.pair_window_s, nonnegative=True)
        require_finite("obstacle_link_m", self.obstacle_link_m, positive=True)
        require_finite("obstacle_link_rel", self.obstacle_link_rel, nonnegative=True)
        for name in ("target_no_false_obstacle", "target_dangerous_clear", "target_false_obstacle", "target_detection",
                     "target_detection_near", "target_remembered", "nees_confidence"):
            v = getattr(self, name)
            require_finite(name, v)
            require(0 <= v <= 1, f"{name} must be in [0, 1], got {v}")
        require(0 < self.nees_confidence < 1, "nees_confidence must be in (0, 1)")
        require_finite("nees_gap_s", self.nees_gap_s, positive=True)

    def tolerance(self, true_m: np.ndarray) -> np.ndarray:
        return np.maximum(self.tolerance_m, self.tolerance_rel * np.asarray(true_m, float))
