"""Scoring the companion's published ranges against the simulator's truth (docs/derivations/sectors.md).

Pure logic: arrays in, arrays and a JSON-ready dict out.  Reading the tlog and ``truth.npz`` and
writing ``score.json`` / ``score.md`` live in :mod:`flightsim.score_io` (``score_run``,
``write_score``), which imports this module and never the other way round.

What is scored
--------------
Every OBSTACLE_DISTANCE (and forward DISTANCE_SENSOR) the companion sent is compared with the
truth *of the moment it arrives*: the record stamp of the message in the ranges tlog (the time it
left the companion in a replay, its arrival in SITL) picks the latest truth frame at or before
that stamp (``truth.npz`` ``t_s``, the same recording clock), if that frame is at most
``truth_max_age_s`` old; messages without such a frame are counted, not scored.  The companion
already turns its sectors to the yaw at sending time, so the truth sectors of that frame (body
FRD at the frame's own yaw, at most one frame period earlier) are compared as they are.

A *cell* is one (message, sector).  With ``T`` the true horizontal distance of the sector
(:mod:`flightsim.world.truth`: nearest obstacle footprint inside the ±2.5° wedge, within the
vertical band) and ``max`` the message's own ``max_distance``:

* **unknown-truth cell**: ``T`` is NaN (an older truth.npz knows only the sectors the camera
  sees); claims there are counted as *unscored claims*, nothing else;
* **obstacle cell**: ``T`` finite and ``T ≤ max``;
* **clear cell**: ``T`` is inf (nothing within the truth's ``sector_max_m``) or ``T > max``.

The published value of a sector is one of: *unknown* (UINT16_MAX), *clear* (``max + 1``), a
*range* ``r`` (``min_distance ≤ r ≤ max``, conservative: estimate − k·σ), or *invalid* (anything
else, e.g. below ``min_distance``; ArduPilot discards it).  The tolerance is
``tol(T) = max(tolerance_m, tolerance_rel · T)`` (defaults: max(2 m, 20 %)).

* **detection**: a range reported in an obstacle cell;
* **valid range**: a detection with ``|r − T| ≤ tol(T)``;
* **false obstacle**: a range reported in a clear cell nearer than the truth by more than ``tol``
  (``T − r > tol(T)``), or the same in an obstacle cell ("too near"); the first kind is the *false
  obstacle in a clear sector*.  Where ``T`` is inf the truth only says "beyond ``sector_max_m``",
  so it is taken at ``sector_max_m`` (the most favourable case): a range there is false when
  ``sector_max_m − r > tol(sector_max_m)`` and otherwise *unverifiable* (counted apart, neither
  right nor wrong; a truth horizon beyond the companion's ``max_distance`` removes the case);
* **over-range**: a detection farther than the truth by more than ``tol`` (``r − T > tol``);
* **dangerous clear**: "clear" (``max + 1``) reported in an obstacle cell — the most dangerous
  error: the autopilot is told the way is free while an obstacle stands within range.

Rates: detection rate = detections / obstacle cells; dangerous-clear rate = dangerous clears /
obstacle cells; false-obstacle rate (clear sectors) = false obstacles in clear cells / clear cells.
Per message: the share of messages *with no false obstacle in a clear sector*, over the messages
that make at least one claim (a range or "clear" in any sector) and have at least one clear cell
in view (an all-unknown message claims nothing and is not counted).

Over 360° (docs/derivations/sectors.md — an unknown sector means no constraint — and docs/derivations/obstacle_map.md — the
local map publishes remembered obstacles beside and behind the vehicle).  A truth.npz with
``sector_all_m`` and ``in_view`` knows every sector.  Cells in the camera's view are scored as
above.  Out of view only a *claim* is scored (a range or "clear"): a range within tolerance on an
obstacle cell is a (remembered) detection, too near in a clear cell a false obstacle, "clear" on
an obstacle cell a dangerous clear; unknown there is neutral (neither a cell nor a miss).  Counts
and rates are reported in view, out of view and pooled (``cells``/``rates`` are pooled), and the
safety targets are judged pooled.

*Remembered* cells (:func:`remembered_cells`): out-of-view obstacle cells whose obstacle (the
grouping below) was in view within ``remember_window_s`` with the vehicle moved less than
``remember_max_travel_m`` since; their share reported within tolerance (unknown counts as not
reported).  Detection by true range (``detection_bins_m``): per bin, in view and out of view (all
out-of-view obstacle cells), the share within tolerance, the share with any range, unknown and
clear.  Warm-up: messages stamped within ``warmup_s`` of the first truth frame are not scored
(cells, the forward DISTANCE_SENSOR and NEES); latency and the first claim include them.

Targets (thresholds in configs/score.toml): no false obstacle in clear sectors in
≥ 98 % of messages; dangerous clears ≤ 0.5 % of obstacle cells; false obstacles ≤ 1 % of clear
cells; detection (within tolerance) ≥ 90 % of in-view obstacle cells and ≥ 95 % of those within
``near_range_m``; remembered ≥ 90 %.  "Detection" in the issue-11 targets and the by-range tables
means a range *within tolerance* (``valid``); the ``detection`` rate below keeps its issue-5
meaning (any range in an obstacle cell).

Range error by range bin (of the true distance ``T``), absolute and in % of ``T``: of the
conservative published value over all detections, and for the forward sector of the estimate
behind it, from DISTANCE_SENSOR: ``estimate = published + k·σ`` (``k`` = the companion's
``[sectors] sigma_k``).  σ comes from the message's ``covariance`` (variance in cm², 1…254) or,
since a uint8 variance cannot hold a σ above 16 cm (255 = unknown), from ``signal_quality``
``q = 100·(1 − (σ/d)/z)`` (``z`` = ``[outputs] quality_zero_rel_sigma``, ``d`` the published
range) when ``3 ≤ q ≤ 99`` (2 and 100 are saturated bounds); σ is then known to ±0.5 % of ``d``·z.
Published values clamped at ``min_distance`` or ``max_distance`` are not undone.  σ is the
companion's 3-D range σ applied to the horizontal range (rays within the flight band are nearly
horizontal).

NEES of the reported σ (forward sector): ``(estimate − T)² / σ²`` averaged, against the two-sided
95 % band of the mean of ``n`` χ²₁ samples, ``[χ²(n, 2.5 %), χ²(n, 97.5 %)] / n``.
The estimate describes the exposure, so ``T`` is the truth of the capture frame when it is known
(the DISTANCE_SENSOR is paired with the OBSTACLE_DISTANCE sent with it, whose ``time_usec`` is the
exposure); the NEES against the truth at arrival is reported beside it.  Consecutive samples are
correlated (one filter over many frames), so the band is narrower than a band for the effective
number of independent samples would be.

Obstacles and time to the first valid range.  Truth sectors are grouped into obstacles by
position: the world point of every obstacle cell of every truth frame (vehicle position + ``T``
along the sector's centre bearing) is linked to every point within ``max(obstacle_link_m,
obstacle_link_rel · T)``; connected groups are obstacles (two solids closer than the link distance
merge into one).  With a world at hand (:func:`world_namer`) each group takes the name of the
solid nearest most of its points.  For each obstacle: the first message in which it occupies an
obstacle cell (``in range``), the first message with a valid range in one of its cells, the
difference (time to the first valid range), and the share of its in-range messages in which at
least one of its cells was detected.

Latency.  OBSTACLE_DISTANCE ``time_usec`` is the exposure on the autopilot's boot clock (µs; 0 =
no exposure behind it).  The companion's boot→recording offset is the lower envelope of
``stamp − time_boot_ms`` over its DISTANCE_SENSOR / NAMED_VALUE_FLOAT / OBSTACLE_DISTANCE_3D
messages (their ``time_boot_ms`` is the sending time); the mapped exposure snaps to the nearest
truth frame within ``capture_snap`` frame periods (its true capture time), and latency = stamp −
capture time.  p50 / p95 / p99 over messages with an exposure.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from companion.config import require, require_finite
from companion.errors import InputError

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
    quality_zero_rel_sigma: float = 0.5  # the companion's [outputs] quality_zero_rel_sigma (σ from signal_quality)
    range_bins_m: tuple[float, ...] = (0.0, 10.0, 20.0, 40.0)  # lower edges of the range bins, m (the last bin is open)
    detection_bins_m: tuple[float, ...] = (0.0, 5.0, 10.0, 20.0, 30.0, 40.0)  # lower edges of the detection-by-true-range bins, m
    warmup_s: float = 2.0  # cells of messages stamped within this long after the first truth frame are not scored, s
    near_range_m: float = 10.0  # "near" obstacle cells: true range below this (target_detection_near), m
    remember_window_s: float = 10.0  # remembered: the obstacle was in view at most this long before, s
    remember_max_travel_m: float = 20.0  # ... and the vehicle moved less than this since, m
    remember_point: bool = True  # remembered also needs the cell's own world point to have been in view then (a long wall counts only where seen)
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
    beside_sectors: int = 2  # a false obstacle within this many sectors of an obstacle at its range is reported as "beside an obstacle" (diagnostic only)
    nees_confidence: float = 0.95  # two-sided probability of the NEES band

    def __post_init__(self) -> None:
        require_finite("tolerance_m", self.tolerance_m, nonnegative=True)
        require_finite("tolerance_rel", self.tolerance_rel, nonnegative=True)
        require_finite("sigma_k", self.sigma_k, nonnegative=True)
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

    def tolerance(self, true_m: np.ndarray) -> np.ndarray:
        return np.maximum(self.tolerance_m, self.tolerance_rel * np.asarray(true_m, float))


# ---------------------------------------------------------------------- inputs -----------------
@dataclasses.dataclass(frozen=True, eq=False)
class RangeMessages:
    """The companion's messages as arrays (built by :func:`flightsim.score_io.read_ranges_tlog`).

    Times are record stamps on the recording clock (s).  ``od_geometry_ok``: the message uses 72
    sectors of 5° from forward in MAV_FRAME_BODY_FRD (others are counted, not scored).
    """

    od_t: np.ndarray  # (N,)
    od_time_usec: np.ndarray  # (N,) int64, exposure on the boot clock (0 = none)
    od_distances_cm: np.ndarray  # (N, 72) int64
    od_min_cm: np.ndarray  # (N,) int64
    od_max_cm: np.ndarray  # (N,) int64
    od_geometry_ok: np.ndarray  # (N,) bool
    ds_t: np.ndarray  # (D,)
    ds_distance_cm: np.ndarray  # (D,) int64
    ds_min_cm: np.ndarray
    ds_max_cm: np.ndarray
    ds_covariance: np.ndarray  # (D,) int64, cm² (255 = unknown)
    ds_quality: np.ndarray  # (D,) int64, signal_quality
    ds_orientation: np.ndarray  # (D,) int64
    boot_t: np.ndarray  # (K,) stamps of messages whose time_boot_ms is their sending time
    boot_ms: np.ndarray  # (K,) int64, their time_boot_ms
    heartbeat_t: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    heartbeat_status: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    texts: tuple[tuple[float, int, str], ...] = ()  # (stamp, severity, text) of STATUSTEXT
    counts: dict = dataclasses.field(default_factory=dict)  # messages by type and reader counters

    @staticmethod
    def build(od: Sequence[tuple] = (), ds: Sequence[tuple] = (), boot: Sequence[tuple] = (), heartbeats=(), texts=(),
              counts=None) -> "RangeMessages":
        """From tuples (for the reader and for tests).

        ``od``: ``(t, time_usec, distances_cm[72], min_cm, max_cm[, geometry_ok])``;
        ``ds``: ``(t, distance_cm, min_cm, max_cm, covariance, signal_quality[, orientation])``;
        ``boot``: ``(t, time_boot_ms)``; ``heartbeats``: ``(t, system_status)``.
        """
        od = list(od)
        for row in od:
            if len(np.asarray(row[2]).reshape(-1)) != N_SECTORS:
                raise InputError(f"OBSTACLE_DISTANCE needs {N_SECTORS} distances, got {len(np.asarray(row[2]).reshape(-1))}")
        ds = list(ds)
        boot = list(boot)
        hb = list(heartbeats)
        return RangeMessages(
            od_t=np.array([r[0] for r in od], float),
            od_time_usec=np.array([r[1] for r in od], np.int64),
            od_distances_cm=np.array([np.asarray(r[2], np.int64).reshape(-1) for r in od], np.int64).reshape(-1, N_SECTORS),
            od_min_cm=np.array([r[3] for r in od], np.int64),
            od_max_cm=np.array([r[4] for r in od], np.int64),
            od_geometry_ok=np.array([bool(r[5]) if len(r) > 5 else True for r in od], bool),
            ds_t=np.array([r[0] for r in ds], float),
            ds_distance_cm=np.array([r[1] for r in ds], np.int64),
            ds_min_cm=np.array([r[2] for r in ds], np.int64),
            ds_max_cm=np.array([r[3] for r in ds], np.int64),
            ds_covariance=np.array([r[4] for r in ds], np.int64),
            ds_quality=np.array([r[5] for r in ds], np.int64),
            ds_orientation=np.array([r[6] if len(r) > 6 else 0 for r in ds], np.int64),
            boot_t=np.array([r[0] for r in boot], float),
            boot_ms=np.array([r[1] for r in boot], np.int64),
            heartbeat_t=np.array([r[0] for r in hb], float),
            heartbeat_status=np.array([r[1] for r in hb], np.int64),
            texts=tuple(texts),
            counts=dict(counts or {}),
        )


@dataclasses.dataclass(frozen=True, eq=False)
class SectorTruth:
    """The parts of ``truth.npz`` the score needs (see flightsim/fly.py TRUTH_FIELDS).

    ``sector_m`` is the truth of every sector known (NaN = unknown: not scored); ``in_view`` says
    which sectors the camera sees.  A 360° truth (``truth.npz`` with ``sector_all_m`` and
    ``in_view``; docs/derivations/obstacle_map.md) knows every sector; an older one knows only the sectors in
    view (``in_view`` None: in view = known).
    """

    t_s: np.ndarray  # (F,) capture time of each frame, recording clock
    sector_m: np.ndarray  # (F, 72) true horizontal distance per sector; inf = nothing within sector_max_m; NaN = unknown
    p_ned: np.ndarray  # (F, 3) vehicle position, world NED
    yaw: np.ndarray  # (F,) vehicle yaw, rad
    sector_max_m: float
    in_view: np.ndarray | None = None  # (F, 72) bool, sector in the camera's view (None: the known sectors)

    @property
    def view(self) -> np.ndarray:
        """(F, 72) bool: sectors in the camera's view."""
        if self.in_view is None:
            return ~np.isnan(np.asarray(self.sector_m, float))
        return np.asarray(self.in_view, bool)

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, float)
        f = t.shape[0] if t.ndim == 1 else -1
        if f < 1:
            raise InputError(f"truth t_s must be a non-empty 1-D array, got shape {t.shape}")
        if np.asarray(self.sector_m).shape != (f, N_SECTORS):
            raise InputError(f"truth sector_m must be ({f}, {N_SECTORS}), got {np.asarray(self.sector_m).shape}")
        if np.asarray(self.p_ned).shape != (f, 3) or np.asarray(self.yaw).shape != (f,):
            raise InputError("truth p_ned / yaw do not match t_s")
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise InputError("truth t_s must be finite and strictly increasing")
        if not (math.isfinite(self.sector_max_m) and self.sector_max_m > 0):
            raise InputError(f"truth sector_max_m must be > 0, got {self.sector_max_m}")
        if self.in_view is not None and np.asarray(self.in_view).shape != (f, N_SECTORS):
            raise InputError(f"truth in_view must be ({f}, {N_SECTORS}), got {np.asarray(self.in_view).shape}")

    @property
    def frame_period_s(self) -> float:
        return float(np.median(np.diff(self.t_s))) if len(self.t_s) > 1 else math.inf

    def frame_at(self, t: np.ndarray, max_age_s: float) -> np.ndarray:
        """Index of the latest frame at or before each ``t`` (−1 if none or older than ``max_age_s``)."""
        t = np.asarray(t, float)
        j = np.searchsorted(self.t_s, t + 1e-9, side="right") - 1
        ok = (j >= 0) & np.isfinite(t)
        jj = np.where(ok, j, 0)
        ok &= t - self.t_s[jj] <= max_age_s + 1e-9
        return np.where(ok, j, -1)


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


# ---------------------------------------------------------------------- statistics helpers -----
def _gamma_p(a: float, x: float) -> float:
    """Regularized lower incomplete gamma P(a, x): series below a + 1, Lentz continued fraction above."""
    if x <= 0:
        return 0.0
    log_pre = -x + a * math.log(x) - math.lgamma(a)
    if x < a + 1:
        term = total = 1.0 / a
        ap = a
        for _ in range(10000):
            ap += 1
            term *= x / ap
            total += term
            if abs(term) < abs(total) * 1e-15:
                break
        return min(1.0, total * math.exp(log_pre))
    tiny = 1e-300
    b_ = x + 1 - a
    c = 1 / tiny
    d = 1 / b_
    h = d
    for i in range(1, 10000):
        an = -i * (i - a)
        b_ += 2
        d = an * d + b_
        d = tiny if abs(d) < tiny else d
        c = b_ + an / c
        c = tiny if abs(c) < tiny else c
        d = 1 / d
        delta = d * c
        h *= delta
        if abs(delta - 1) < 1e-15:
            break
    return max(0.0, 1.0 - math.exp(log_pre) * h)


def chi2_quantile(p: float, dof: float) -> float:
    """χ² quantile: the χ² CDF P(dof/2, x/2) inverted by bisection (no SciPy at run time)."""
    if dof <= 0 or not 0 < p < 1:
        return math.nan
    lo, hi = 0.0, dof + 20.0 * math.sqrt(2.0 * dof) + 100.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _gamma_p(dof / 2.0, mid / 2.0) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-12 * max(1.0, hi):
            break
    return 0.5 * (lo + hi)


def nees_band(n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band for the mean of ``n`` χ²₁ samples."""
    if n <= 0:
        return (math.nan, math.nan)
    lo = (1 - confidence) / 2
    return chi2_quantile(lo, n) / n, chi2_quantile(1 - lo, n) / n


def _rate(num: int, den: int) -> float | None:
    return None if den == 0 else num / den


def _pct(x: np.ndarray, q: float) -> float | None:
    return None if x.size == 0 else float(np.percentile(x, q))


def error_table(true_m: np.ndarray, value_m: np.ndarray, bins_m: Sequence[float]) -> list[dict]:
    """Range error ``value − true`` by bin of the true distance: n, bias, mean/median/p95 |error|
    (m) and mean/median |error| in % of the true distance."""
    T = np.asarray(true_m, float)
    v = np.asarray(value_m, float)
    ok = np.isfinite(T) & np.isfinite(v)
    T, v = T[ok], v[ok]
    edges = list(bins_m)
    rows = []
    for i, lo in enumerate(edges):
        hi = edges[i + 1] if i + 1 < len(edges) else math.inf
        sel = (T >= lo) & (T < hi)
        e = v[sel] - T[sel]
        a = np.abs(e)
        rel = 100.0 * a / np.maximum(T[sel], 1e-9)
        rows.append({
            "bin": f"{lo:g}–{hi:g} m" if math.isfinite(hi) else f"{lo:g}+ m",
            "lo_m": lo, "hi_m": hi if math.isfinite(hi) else None, "n": int(sel.sum()),
            "bias_m": float(e.mean()) if e.size else None,
            "mae_m": float(a.mean()) if a.size else None,
            "median_abs_m": _pct(a, 50), "p95_abs_m": _pct(a, 95),
            "mae_pct": float(rel.mean()) if rel.size else None,
            "median_abs_pct": _pct(rel, 50),
        })
    return rows


# ---------------------------------------------------------------------- evaluation -------------
@dataclasses.dataclass(eq=False)
class Evaluation:
    """Per-message, per-cell results of :func:`evaluate` (arrays; see :func:`series_arrays`)."""

    config: ScoreConfig
    t0: float  # first truth frame, recording clock
    frame_period_s: float
    sector_max_m: float
    # OBSTACLE_DISTANCE
    od_t: np.ndarray
    od_frame: np.ndarray  # truth frame at arrival (−1: none)
    od_scored: np.ndarray  # geometry ok and truth available
    od_rep: np.ndarray  # (N, 72) REP_*
    od_r: np.ndarray  # (N, 72) published range, m (NaN unless REP_RANGE)
    od_cm: np.ndarray  # (N, 72) published value, cm
    od_truth: np.ndarray  # (N, 72) truth at arrival (NaN where unseen or no truth)
    od_tcls: np.ndarray  # (N, 72) TRUTH_*
    od_max_m: np.ndarray  # (N,)
    od_label: np.ndarray  # (N, 72) obstacle id of obstacle cells (−1 elsewhere)
    od_capture_t: np.ndarray  # (N,) exposure, recording clock (NaN unknown)
    od_capture_frame: np.ndarray  # (N,) truth frame of the exposure (−1 unknown / not matched)
    od_latency_s: np.ndarray  # (N,)
    od_in_view: np.ndarray  # (N, 72) bool, the truth frame's sector is in the camera's view
    od_warmup: np.ndarray  # (N,) bool, stamped within warmup_s of the first truth frame (not scored)
    od_remember: np.ndarray  # (N, 72) bool, out-of-view obstacle cell of an obstacle seen recently nearby ("remembered")
    # DISTANCE_SENSOR (forward)
    ds_t: np.ndarray
    ds_frame: np.ndarray
    ds_state: np.ndarray  # REP_*
    ds_published_m: np.ndarray
    ds_sigma_m: np.ndarray
    ds_sigma_source: np.ndarray  # 0 none, 1 covariance, 2 signal_quality
    ds_estimate_m: np.ndarray
    ds_truth_arrival: np.ndarray
    ds_truth_exposure: np.ndarray
    ds_max_m: np.ndarray
    # obstacles and clock
    obstacle_names: list[str]
    obstacle_centroids: np.ndarray
    boot_offset_s: float
    capture_residual_s: np.ndarray  # |mapped exposure − nearest frame| of matched messages
    messages: RangeMessages
    notes: list[str]
    truth_360: bool = False  # the truth knows the sectors out of view (truth.npz in_view / sector_all_m)


def _classify_published(cm: np.ndarray, min_cm: np.ndarray, max_cm: np.ndarray) -> np.ndarray:
    rep = np.full(cm.shape, REP_INVALID, np.int8)
    rep[cm == UNKNOWN_CM] = REP_UNKNOWN
    rep[cm == max_cm + 1] = REP_CLEAR
    rep[(cm >= min_cm) & (cm <= max_cm)] = REP_RANGE
    return rep


def remembered_cells(truth: SectorTruth, labels: np.ndarray, view_f: np.ndarray, frame: np.ndarray, lab: np.ndarray,
                     candidates: np.ndarray, config: ScoreConfig) -> np.ndarray:
    """(N, 72) bool: the *remembered* cells among ``candidates`` (out-of-view obstacle cells of the
    messages; the coverage targets, docs/derivations/obstacle_map.md).

    Rule (per obstacle, by the grouping of :func:`group_obstacles`): the cell's obstacle ``k``
    (``lab``) occupied an in-view finite truth cell in some truth frame at most
    ``remember_window_s`` before the message's truth frame (``frame``), and the vehicle moved less
    than ``remember_max_travel_m`` (3-D) from its position in the *latest* such frame.  One group
    may be large (a long wall): a part of it that never was in view counts when another part was.
    """
    cfg = config
    n = len(frame)
    out = np.zeros((n, N_SECTORS), bool)
    K = int(labels.max()) + 1 if labels.size else 0
    if K == 0 or n == 0 or not np.any(candidates):
        return out
    F = len(truth.t_s)
    seen = np.zeros((F, K), bool)
    ff, ss = np.nonzero((labels >= 0) & view_f)
    seen[ff, labels[ff, ss]] = True
    last = np.maximum.accumulate(np.where(seen, np.arange(F)[:, None], -1), axis=0)  # latest in-view frame, (F, K)
    nn, ii = np.nonzero(candidates & (lab >= 0) & (frame >= 0)[:, None])
    j = frame[nn]
    ls = last[j, lab[nn, ii]]
    lsj = np.maximum(ls, 0)
    ok = (ls >= 0) & (truth.t_s[j] - truth.t_s[lsj] <= cfg.remember_window_s + 1e-9)
    ok &= np.linalg.norm(np.asarray(truth.p_ned, float)[j] - np.asarray(truth.p_ned, float)[lsj], axis=1) < cfg.remember_max_travel_m
    if cfg.remember_point:
        nn, ii, j = nn[ok], ii[ok], j[ok]
        ok = _point_seen(truth, view_f, j, ii, cfg)
    out[nn[ok], ii[ok]] = True
    return out


def _point_seen(truth: SectorTruth, view_f: np.ndarray, j: np.ndarray, ii: np.ndarray, cfg: ScoreConfig) -> np.ndarray:
    """(len(j),) bool: the world point behind cell (truth frame ``j``, sector ``ii``) — at the cell's true
    distance on its centre bearing — lay in an in-view sector within ``sector_max_m`` of the vehicle in a
    truth frame at most ``remember_window_s`` earlier, from which the vehicle has moved less than
    ``remember_max_travel_m``.  A long wall counts only where its own part was in view (occlusion by
    other obstacles is not checked)."""
    out = np.zeros(len(j), bool)
    if len(j) == 0:
        return out
    p = np.asarray(truth.p_ned, float)
    yaw = np.asarray(truth.yaw, float)
    b = yaw[j] + np.radians(ii * SECTOR_DEG)
    dist = np.asarray(truth.sector_m, float)[j, ii]
    pt = p[j, :2] + dist[:, None] * np.stack([np.cos(b), np.sin(b)], 1)  # (C, 2)
    t = np.asarray(truth.t_s, float)
    lo = np.searchsorted(t, t[j] - cfg.remember_window_s - 1e-9, side="left")
    W = int(np.max(j - lo)) + 1
    for c0 in range(0, len(j), 2048):  # chunks of cells, vectorized over cells × frames of the window
        c = slice(c0, c0 + 2048)
        f = j[c, None] - np.arange(W)[None, :]  # (c, W) frames back from the cell's own
        inwin = f >= lo[c, None]
        f = np.maximum(f, 0)
        rel = pt[c, None, :] - p[f, :2]
        r = np.hypot(rel[..., 0], rel[..., 1])
        sec = np.mod(np.rint((np.degrees(np.arctan2(rel[..., 1], rel[..., 0]) - np.degrees(yaw[f]))) / SECTOR_DEG).astype(np.int64), N_SECTORS)
        moved = np.linalg.norm(p[j[c], None, :] - p[f], axis=2) < cfg.remember_max_travel_m
        out[c] = np.any(inwin & view_f[f, sec] & (r <= truth.sector_max_m) & moved, axis=1)
    return out


def _boot_offset(msgs: RangeMessages) -> float:
    ok = msgs.boot_ms > 0
    if not np.any(ok):
        return math.nan
    return float(np.min(msgs.boot_t[ok] - msgs.boot_ms[ok] * 1e-3))


def evaluate(msgs: RangeMessages, truth: SectorTruth, config: ScoreConfig = ScoreConfig(), *,
             namer: Callable[[np.ndarray], list] | None = None) -> Evaluation:
    """Compare every message with the truth (definitions in the module docstring)."""
    cfg = config
    notes: list[str] = []
    fp = truth.frame_period_s
    # --- OBSTACLE_DISTANCE cells ----------------------------------------------------------------
    n = len(msgs.od_t)
    cm = msgs.od_distances_cm.reshape(n, N_SECTORS)
    min_cm = msgs.od_min_cm[:, None]
    max_cm = msgs.od_max_cm[:, None]
    rep = _classify_published(cm, min_cm, max_cm)
    r = np.where(rep == REP_RANGE, cm / 100.0, np.nan)
    frame = truth.frame_at(msgs.od_t, cfg.truth_max_age_s)
    has_truth = msgs.od_geometry_ok & (frame >= 0)
    warm = np.asarray(msgs.od_t, float) - float(truth.t_s[0]) < cfg.warmup_s - 1e-9
    scored = has_truth & ~warm
    T = np.full((n, N_SECTORS), np.nan)
    T[has_truth] = truth.sector_m[frame[has_truth]]
    view_f = truth.view
    view = np.zeros((n, N_SECTORS), bool)
    view[has_truth] = view_f[frame[has_truth]]
    if cfg.warmup_s > 0 and np.any(has_truth & warm):
        notes.append(f"{int(np.sum(has_truth & warm))} OBSTACLE_DISTANCE messages in the first {cfg.warmup_s:g} s "
                     "(warm-up) were not scored")
    max_m = msgs.od_max_cm / 100.0
    tcls = np.full((n, N_SECTORS), TRUTH_NONE, np.int8)
    tcls[scored] = TRUTH_UNSEEN
    fin = np.isfinite(T)
    tcls[scored[:, None] & fin & (T <= max_m[:, None])] = TRUTH_OBSTACLE
    tcls[scored[:, None] & ~np.isnan(T) & ~(fin & (T <= max_m[:, None]))] = TRUTH_CLEAR
    if n and np.any(max_m[scored] > truth.sector_max_m + 1e-9):
        notes.append(f"messages claim up to {max_m[scored].max():g} m but the truth only reaches {truth.sector_max_m:g} m: "
                     "cells whose truth is inf may hide an obstacle between the two")
    if np.any(~msgs.od_geometry_ok):
        notes.append(f"{int(np.sum(~msgs.od_geometry_ok))} OBSTACLE_DISTANCE messages not in 72 × 5° BODY_FRD were not scored")
    # --- obstacles --------------------------------------------------------------------------------
    labels, centroids, points = group_obstacles(truth, cfg)
    names = name_obstacles(centroids, points, namer)
    lab = np.full((n, N_SECTORS), -1, np.int64)
    lab[scored] = labels[frame[scored]]
    lab[tcls != TRUTH_OBSTACLE] = -1
    remember = remembered_cells(truth, labels, view_f, frame, lab, (tcls == TRUTH_OBSTACLE) & ~view, cfg)
    # --- exposure and latency -----------------------------------------------------------------
    off = _boot_offset(msgs)
    cap_t = np.full(n, np.nan)
    cap_f = np.full(n, -1, np.int64)
    resid = np.zeros(0)
    has_exp = msgs.od_time_usec > 0
    if n and np.any(has_exp):
        if math.isfinite(off):
            mapped = msgs.od_time_usec * 1e-6 + off
            k = np.clip(np.searchsorted(truth.t_s, mapped), 1, max(len(truth.t_s) - 1, 1))
            k0 = np.clip(k - 1, 0, len(truth.t_s) - 1)
            k1 = np.clip(k, 0, len(truth.t_s) - 1)
            near = np.where(np.abs(mapped - truth.t_s[k0]) <= np.abs(mapped - truth.t_s[k1]), k0, k1)
            d = np.abs(mapped - truth.t_s[near])
            snap = has_exp & (d <= cfg.capture_snap * (fp if math.isfinite(fp) else 0.0) + 1e-9)
            cap_t = np.where(snap, truth.t_s[near], np.where(has_exp, mapped, np.nan))
            cap_f = np.where(snap, near, -1)
            resid = d[snap]
            if np.any(has_exp & ~snap):
                notes.append(f"{int(np.sum(has_exp & ~snap))} exposures did not map onto a truth frame "
                             f"(within {cfg.capture_snap:g} frame periods); their latency uses the mapped time")
        else:
            notes.append("no message carries the companion's sending time_boot_ms: exposure times and latency unknown")
    latency = msgs.od_t - cap_t
    # --- DISTANCE_SENSOR (forward) --------------------------------------------------------------
    fwd = msgs.ds_orientation == 0
    if np.any(~fwd):
        notes.append(f"{int(np.sum(~fwd))} DISTANCE_SENSOR messages not facing forward were ignored")
    ds_t = msgs.ds_t[fwd]
    dcm = msgs.ds_distance_cm[fwd]
    dmin, dmax = msgs.ds_min_cm[fwd], msgs.ds_max_cm[fwd]
    cov, q = msgs.ds_covariance[fwd], msgs.ds_quality[fwd]
    ds_state = _classify_published(dcm, dmin, dmax)
    pub = np.where(ds_state == REP_RANGE, dcm / 100.0, np.nan)
    sig = np.full(len(ds_t), np.nan)
    src = np.zeros(len(ds_t), np.int8)
    rng_ok = (ds_state == REP_RANGE) & (dcm > dmin) & (dcm < dmax)  # clamped values cannot be undone
    by_cov = rng_ok & (cov > 0) & (cov < 255)
    sig[by_cov] = np.sqrt(cov[by_cov]) / 100.0
    src[by_cov] = 1
    by_q = rng_ok & ~by_cov & (q >= 3) & (q <= 99)
    sig[by_q] = pub[by_q] * cfg.quality_zero_rel_sigma * (1.0 - q[by_q] / 100.0)
    src[by_q] = 2
    est = pub + cfg.sigma_k * sig
    ds_frame = truth.frame_at(ds_t, cfg.truth_max_age_s)
    ds_frame[ds_t - float(truth.t_s[0]) < cfg.warmup_s - 1e-9] = -1  # warm-up: not scored
    t_arr = np.where(ds_frame >= 0, truth.sector_m[np.maximum(ds_frame, 0), 0], np.nan)
    # pair each DISTANCE_SENSOR with the OBSTACLE_DISTANCE sent just before it (same result)
    t_exp = np.full(len(ds_t), np.nan)
    if n and len(ds_t):
        j = np.searchsorted(msgs.od_t, ds_t + 1e-9, side="right") - 1
        jj = np.maximum(j, 0)
        paired = (j >= 0) & (ds_t - msgs.od_t[jj] <= cfg.pair_window_s + 1e-9) & (cap_f[jj] >= 0) & (ds_frame >= 0)
        t_exp[paired] = truth.sector_m[cap_f[jj[paired]], 0]
    ds_max_m = dmax / 100.0
    return Evaluation(
        config=cfg, t0=float(truth.t_s[0]), frame_period_s=fp, sector_max_m=float(truth.sector_max_m),
        od_t=msgs.od_t, od_frame=frame, od_scored=scored, od_rep=rep, od_r=r, od_cm=cm, od_truth=T, od_tcls=tcls,
        od_max_m=max_m, od_label=lab, od_capture_t=cap_t, od_capture_frame=cap_f, od_latency_s=latency,
        od_in_view=view, od_warmup=warm, od_remember=remember,
        ds_t=ds_t, ds_frame=ds_frame, ds_state=ds_state, ds_published_m=pub, ds_sigma_m=sig, ds_sigma_source=src,
        ds_estimate_m=est, ds_truth_arrival=t_arr, ds_truth_exposure=t_exp, ds_max_m=ds_max_m,
        obstacle_names=names, obstacle_centroids=centroids, boot_offset_s=off, capture_residual_s=resid,
        messages=msgs, notes=notes, truth_360=truth.in_view is not None,
    )


# ---------------------------------------------------------------------- cell masks -------------
@dataclasses.dataclass(frozen=True, eq=False)
class CellMasks:
    """Boolean (N, 72) masks of the cell categories (module docstring), over all *counted* cells:
    every cell in view, and out of view the cells with a claim (a range or "clear"; unknown out of
    view is neutral).  ``in_view`` splits them."""

    obstacle: np.ndarray
    clear: np.ndarray
    detection: np.ndarray
    valid: np.ndarray
    dangerous: np.ndarray
    false_clear: np.ndarray  # false obstacle in a clear cell
    unverifiable: np.ndarray  # range in a cell whose truth is inf, within tolerance of the truth horizon
    too_near: np.ndarray  # false obstacle in an obstacle cell
    over_range: np.ndarray
    missed_unknown: np.ndarray  # unknown in an obstacle cell
    claimed_clear: np.ndarray  # clear reported in a clear cell
    unscored_claim: np.ndarray  # range or clear in an unseen cell
    invalid: np.ndarray  # published value neither unknown, clear nor a range (scored messages)
    in_view: np.ndarray  # the cell's sector is in the camera's view
    obstacle_any: np.ndarray  # obstacle truth, counted or not (out of view: with unknown too)
    clear_any: np.ndarray  # clear truth, counted or not
    unknown_out_of_view: np.ndarray  # unknown in an out-of-view cell whose truth is known (neutral)
    remembered: np.ndarray  # out-of-view obstacle cells of an obstacle in view recently nearby (remembered_cells)


def cell_masks(ev: Evaluation) -> CellMasks:
    cfg = ev.config
    rep, T, tc = ev.od_rep, ev.od_truth, ev.od_tcls
    view = ev.od_in_view
    rng = rep == REP_RANGE
    claim = rng | (rep == REP_CLEAR)
    counted = view | claim
    obstacle_any = tc == TRUTH_OBSTACLE
    clear_any = tc == TRUTH_CLEAR
    obstacle = obstacle_any & counted
    clear = clear_any & counted
    with np.errstate(invalid="ignore"):
        tol = np.where(np.isfinite(T), cfg.tolerance(np.where(np.isfinite(T), T, 0.0)), np.inf)
        under = T - ev.od_r > tol
        over = ev.od_r - T > tol
    detection = obstacle & rng
    too_near = detection & under
    over_range = detection & over
    H = ev.sector_max_m
    beyond = clear & rng & np.isinf(T)
    horizon_under = (H - ev.od_r) > cfg.tolerance(H)
    false_clear = clear & rng & (np.where(np.isinf(T), horizon_under, under))
    unverifiable = beyond & ~horizon_under
    scored = ev.od_scored[:, None]
    return CellMasks(
        obstacle=obstacle, clear=clear, detection=detection, valid=detection & ~too_near & ~over_range,
        dangerous=obstacle & (rep == REP_CLEAR), false_clear=false_clear, unverifiable=unverifiable, too_near=too_near, over_range=over_range,
        missed_unknown=obstacle & (rep == REP_UNKNOWN), claimed_clear=clear & (rep == REP_CLEAR),
        unscored_claim=(tc == TRUTH_UNSEEN) & claim, invalid=scored & (rep == REP_INVALID),
        in_view=view, obstacle_any=obstacle_any, clear_any=clear_any,
        unknown_out_of_view=(obstacle_any | clear_any) & ~view & (rep == REP_UNKNOWN),
        remembered=ev.od_remember & obstacle_any,
    )


# ---------------------------------------------------------------------- summary ----------------
def _bearing(i: int) -> float:
    b = i * SECTOR_DEG
    return b - 360.0 if b >= 180.0 else b


def _obstacle_rows(ev: Evaluation, m: CellMasks) -> list[dict]:
    rows = []
    t_rel = ev.od_t - ev.t0
    for k, name in enumerate(ev.obstacle_names):
        cells = (ev.od_label == k) & m.in_view  # in view: time to the first valid range after it comes into view
        in_msgs = np.flatnonzero(np.any(cells & m.obstacle, axis=1))
        row = {"id": k, "name": name, "centroid_ne_m": [round(float(v), 2) for v in ev.obstacle_centroids[k]],
               "messages_in_range": int(in_msgs.size), "in_range_at_s": None, "last_in_range_at_s": None,
               "first_detection_at_s": None, "first_valid_at_s": None, "time_to_first_valid_s": None,
               "detected_fraction": None, "valid_fraction": None, "nearest_true_m": None}
        if in_msgs.size:
            row["in_range_at_s"] = float(t_rel[in_msgs[0]])
            row["last_in_range_at_s"] = float(t_rel[in_msgs[-1]])
            row["nearest_true_m"] = float(np.nanmin(np.where(cells, ev.od_truth, np.nan)[in_msgs]))
            det = np.any(cells & m.detection, axis=1)
            val = np.any(cells & m.valid, axis=1)
            row["detected_fraction"] = float(det[in_msgs].mean())
            row["valid_fraction"] = float(val[in_msgs].mean())
            first_det = np.flatnonzero(det)
            first_val = np.flatnonzero(val)
            if first_det.size:
                row["first_detection_at_s"] = float(t_rel[first_det[0]])
            if first_val.size:
                row["first_valid_at_s"] = float(t_rel[first_val[0]])
                row["time_to_first_valid_s"] = float(t_rel[first_val[0]] - t_rel[in_msgs[0]])
        rows.append(row)
    return rows


def _target(key: str, name: str, num: int, den: int, op: str, threshold: float) -> dict:
    v = _rate(num, den)
    return {"key": key, "name": name, "value": v, "num": int(num), "n": int(den), "op": op, "threshold": threshold,
            "met": None if v is None else bool(v >= threshold if op == ">=" else v <= threshold)}


def cell_counts(m: CellMasks, sel: np.ndarray, claims: np.ndarray) -> tuple[dict, dict]:
    """Cell counts and rates over the counted cells selected by ``sel`` (N, 72) (all, in view, out
    of view).  Per message: messages with a claim (``claims``, (N,)) and a clear cell in ``sel``;
    of those, the ones without a false obstacle in a clear cell of ``sel``."""
    ob, cl = m.obstacle & sel, m.clear & sel
    c = {
        "obstacle": int(ob.sum()), "clear": int(cl.sum()), "detections": int((m.detection & sel).sum()),
        "valid_ranges": int((m.valid & sel).sum()), "dangerous_clears": int((m.dangerous & sel).sum()),
        "false_obstacles_clear_cells": int((m.false_clear & sel).sum()), "unverifiable_beyond_truth": int((m.unverifiable & sel).sum()),
        "too_near": int((m.too_near & sel).sum()), "over_range": int((m.over_range & sel).sum()),
        "unknown_in_obstacle_cells": int((m.missed_unknown & sel).sum()),
        "clear_claimed_in_clear_cells": int((m.claimed_clear & sel).sum()), "unscored_claims": int((m.unscored_claim & sel).sum()),
        "invalid_values": int((m.invalid & sel).sum()),
    }
    eligible = claims & np.any(cl, axis=1)
    c["messages_eligible_no_false"] = int(eligible.sum())
    c["messages_without_false_obstacle"] = int((eligible & ~np.any(m.false_clear & sel, axis=1)).sum())
    n_obs, n_clear = c["obstacle"], c["clear"]
    r = {
        "detection": _rate(c["detections"], n_obs), "valid_range": _rate(c["valid_ranges"], n_obs),
        "dangerous_clear": _rate(c["dangerous_clears"], n_obs), "unknown_in_obstacle_cells": _rate(c["unknown_in_obstacle_cells"], n_obs),
        "false_obstacle_clear_cells": _rate(c["false_obstacles_clear_cells"], n_clear), "too_near": _rate(c["too_near"], n_obs),
        "over_range": _rate(c["over_range"], n_obs), "clear_claimed_in_clear_cells": _rate(c["clear_claimed_in_clear_cells"], n_clear),
        "messages_without_false_obstacle": _rate(c["messages_without_false_obstacle"], c["messages_eligible_no_false"]),
    }
    return c, r


def _bin_labels(bins_m: Sequence[float]) -> list[tuple[str, float, float]]:
    edges = list(bins_m)
    out = []
    for i, lo in enumerate(edges):
        hi = edges[i + 1] if i + 1 < len(edges) else math.inf
        out.append((f"{lo:g}–{hi:g} m" if math.isfinite(hi) else f"{lo:g}+ m", lo, hi))
    return out


def detection_table(true_m: np.ndarray, rep: np.ndarray, valid: np.ndarray, cells: np.ndarray,
                    bins_m: Sequence[float]) -> list[dict]:
    """Per bin of the true range (lower edges ``bins_m``, the last open) over the ``cells`` mask:
    obstacle cells, ranges, ranges within tolerance (``valid``: *detection*),
    unknown, "clear" (dangerous) and their shares of the bin's cells; ``claimed`` = ranges + clear
    and ``valid_of_claimed`` (what matters out of view, where unknown is neutral)."""
    T = np.asarray(true_m, float)[cells]
    rp = np.asarray(rep)[cells]
    ok = np.asarray(valid, bool)[cells]
    lab = _bin_labels(bins_m)
    idx = np.searchsorted(np.asarray(bins_m, float), T, side="right") - 1  # below the first edge: −1, dropped
    keep = idx >= 0
    idx, rp, ok = idx[keep], rp[keep], ok[keep]
    nb = len(lab)
    cnt = lambda w: np.bincount(idx, weights=w.astype(float), minlength=nb).astype(int)  # noqa: E731
    n = np.bincount(idx, minlength=nb)
    rng, unk, clr, val = cnt(rp == REP_RANGE), cnt(rp == REP_UNKNOWN), cnt(rp == REP_CLEAR), cnt(ok)
    rows = []
    for b, (name, lo, hi) in enumerate(lab):
        rows.append({"bin": name, "lo_m": lo, "hi_m": hi if math.isfinite(hi) else None, "obstacle_cells": int(n[b]),
                     "ranges": int(rng[b]), "valid": int(val[b]), "unknown": int(unk[b]), "clear": int(clr[b]),
                     "claimed": int(rng[b] + clr[b]), "valid_rate": _rate(int(val[b]), int(n[b])),
                     "range_rate": _rate(int(rng[b]), int(n[b])), "unknown_rate": _rate(int(unk[b]), int(n[b])),
                     "dangerous_rate": _rate(int(clr[b]), int(n[b])),
                     "valid_of_claimed": _rate(int(val[b]), int(rng[b] + clr[b]))})
    return rows


def false_obstacles_beside(ev: Evaluation, m: CellMasks, sectors: int) -> np.ndarray:
    """(N, 72) bool: false obstacles in clear cells whose published range matches (within tolerance)
    the true range of an obstacle cell at most ``sectors`` sectors away in the same message — a
    real obstacle claimed at the right range on a neighbouring bearing (a thin pole's remembered
    point spread over its bearing σ), as opposed to a phantom range."""
    out = np.zeros(m.false_clear.shape, bool)
    if sectors < 1 or not np.any(m.false_clear):
        return out
    cfg = ev.config
    T = np.where(ev.od_tcls == TRUTH_OBSTACLE, ev.od_truth, np.nan)
    r = ev.od_r
    for k in range(1, sectors + 1):
        for shift in (k, -k):
            Tn = np.roll(T, shift, axis=1)  # the truth of the sector k away
            with np.errstate(invalid="ignore"):
                out |= np.isfinite(Tn) & (np.abs(r - Tn) <= cfg.tolerance(np.where(np.isfinite(Tn), Tn, 0.0)))
    return out & m.false_clear


def summarize(ev: Evaluation) -> dict:
    """The JSON-ready score of one run (the contents of ``score.json``)."""
    cfg = ev.config
    m = cell_masks(ev)
    msgs = ev.messages
    scored = ev.od_scored
    claims = np.any((ev.od_rep == REP_RANGE) | (ev.od_rep == REP_CLEAR), axis=1) & scored
    everywhere = np.ones(m.obstacle.shape, bool)
    cells, rates = cell_counts(m, everywhere, claims)
    cells_iv, rates_iv = cell_counts(m, m.in_view, claims)
    cells_oov, rates_oov = cell_counts(m, ~m.in_view, claims)
    oov = ~m.in_view
    cells_oov.update({"obstacle_cells_total": int((m.obstacle_any & oov).sum()), "clear_cells_total": int((m.clear_any & oov).sum()),
                      "unknown_neutral": int(m.unknown_out_of_view.sum())})
    rates["messages_with_claims"] = _rate(int(claims.sum()), int(scored.sum()))
    n_obs, n_clear, dang, fclear = cells["obstacle"], cells["clear"], cells["dangerous_clears"], cells["false_obstacles_clear_cells"]
    n_elig, n_ok_msgs = cells["messages_eligible_no_false"], cells["messages_without_false_obstacle"]
    # detection by true range: in view, and out of view (every out-of-view obstacle cell, unknown included)
    det_tables = {
        "in_view": detection_table(ev.od_truth, ev.od_rep, m.valid, m.obstacle_any & m.in_view, cfg.detection_bins_m),
        "out_of_view": detection_table(ev.od_truth, ev.od_rep, m.valid, m.obstacle_any & oov, cfg.detection_bins_m),
    }
    near = m.obstacle & m.in_view & (ev.od_truth < cfg.near_range_m)
    n_near, v_near = int(near.sum()), int((near & m.valid).sum())
    n_rem, v_rem = int(m.remembered.sum()), int((m.remembered & m.valid).sum())
    remembered = {
        "cells": n_rem, "within_tolerance": v_rem, "rate": _rate(v_rem, n_rem),
        "ranges": int((m.remembered & (ev.od_rep == REP_RANGE)).sum()),
        "unknown": int((m.remembered & (ev.od_rep == REP_UNKNOWN)).sum()),
        "dangerous_clears": int((m.remembered & (ev.od_rep == REP_CLEAR)).sum()),
        "window_s": cfg.remember_window_s, "max_travel_m": cfg.remember_max_travel_m,
    }
    beside = false_obstacles_beside(ev, m, cfg.beside_sectors)
    false_beside = {
        "sectors": cfg.beside_sectors,
        "in_view": int((beside & m.in_view).sum()), "in_view_total": int((m.false_clear & m.in_view).sum()),
        "out_of_view": int((beside & oov).sum()), "out_of_view_total": int((m.false_clear & oov).sum()),
    }
    targets = [
        _target("messages_without_false_obstacle", "no false obstacle in clear sectors (in and out of view), share of messages",
                n_ok_msgs, n_elig, ">=", cfg.target_no_false_obstacle),
        _target("dangerous_clear", "dangerous clear (max_distance + 1 in an obstacle cell, in and out of view), share of "
                "obstacle cells", dang, n_obs, "<=", cfg.target_dangerous_clear),
        _target("false_obstacle_clear_cells", "false obstacle in clear cells (in and out of view), share of clear cells",
                fclear, n_clear, "<=", cfg.target_false_obstacle),
        _target("detection_in_view", "detection (a range within tolerance), share of in-view obstacle cells",
                cells_iv["valid_ranges"], cells_iv["obstacle"], ">=", cfg.target_detection),
        _target("detection_near_in_view", f"detection within 0–{cfg.near_range_m:g} m, share of in-view obstacle cells",
                v_near, n_near, ">=", cfg.target_detection_near),
        _target("remembered", f"remembered obstacles out of view (in view within {cfg.remember_window_s:g} s, vehicle moved "
                f"< {cfg.remember_max_travel_m:g} m): share of their cells within tolerance", v_rem, n_rem, ">=",
                cfg.target_remembered),
    ]
    # per sector
    sectors = []
    for i in range(N_SECTORS):
        no, nc = int(m.obstacle[:, i].sum()), int(m.clear[:, i].sum())
        if no == 0 and nc == 0:
            continue
        sectors.append({
            "sector": i, "bearing_deg": _bearing(i), "obstacle_cells": no, "detections": int(m.detection[:, i].sum()),
            "detection_rate": _rate(int(m.detection[:, i].sum()), no), "dangerous_clears": int(m.dangerous[:, i].sum()),
            "too_near": int(m.too_near[:, i].sum()), "clear_cells": nc, "false_obstacles": int(m.false_clear[:, i].sum()),
            "false_obstacle_rate": _rate(int(m.false_clear[:, i].sum()), nc),
            "clear_claimed": int(m.claimed_clear[:, i].sum()),
        })
    # range error
    dT, dr = ev.od_truth[m.detection], ev.od_r[m.detection]
    ds_rng = (ev.ds_state == REP_RANGE) & np.isfinite(ev.ds_truth_arrival) & (ev.ds_truth_arrival <= ev.ds_max_m)
    est_ok = ds_rng & np.isfinite(ev.ds_estimate_m)
    range_error = {
        "published_all_sectors": error_table(dT, dr, cfg.range_bins_m),
        "published_forward": error_table(ev.ds_truth_arrival[ds_rng], ev.ds_published_m[ds_rng], cfg.range_bins_m),
        "estimate_forward": error_table(ev.ds_truth_arrival[est_ok], ev.ds_estimate_m[est_ok], cfg.range_bins_m),
    }
    # latency
    lat = ev.od_latency_s[np.isfinite(ev.od_latency_s)] * 1000.0
    latency = {"n": int(lat.size), "p50_ms": _pct(lat, 50), "p95_ms": _pct(lat, 95), "p99_ms": _pct(lat, 99),
               "max_ms": float(lat.max()) if lat.size else None,
               "unmatched_exposures": int(np.sum((ev.od_capture_frame < 0) & np.isfinite(ev.od_capture_t))),
               "boot_offset_s": ev.boot_offset_s if math.isfinite(ev.boot_offset_s) else None,
               "exposure_mapping_residual_ms_p50": _pct(ev.capture_residual_s * 1000.0, 50)}
    # NEES
    nees = nees_summary(ev)
    # DISTANCE_SENSOR
    ds_obs = np.isfinite(ev.ds_truth_arrival) & (ev.ds_truth_arrival <= ev.ds_max_m)
    ds = {
        "messages": int(len(ev.ds_t)), "scored": int(np.sum(ev.ds_frame >= 0)),
        "ranges": int(np.sum(ev.ds_state == REP_RANGE)), "clear": int(np.sum(ev.ds_state == REP_CLEAR)),
        "unknown": int(np.sum(ev.ds_state == REP_UNKNOWN)), "obstacle_messages": int(ds_obs.sum()),
        "detection_rate": _rate(int(np.sum(ds_obs & (ev.ds_state == REP_RANGE))), int(ds_obs.sum())),
        "dangerous_clears": int(np.sum(ds_obs & (ev.ds_state == REP_CLEAR))),
        "sigma_from_covariance": int(np.sum(ev.ds_sigma_source == 1)),
        "sigma_from_signal_quality": int(np.sum(ev.ds_sigma_source == 2)),
    }
    any_claim = np.any((ev.od_rep == REP_RANGE) | (ev.od_rep == REP_CLEAR), axis=1) & msgs.od_geometry_ok & (ev.od_frame >= 0)
    first_claim = np.flatnonzero(any_claim)  # warm-up included: how soon the companion claims anything
    hb = msgs.heartbeat_status
    counts = dict(msgs.counts)
    out = {
        "version": 1,
        "definitions": {
            "truth": "latest truth frame at or before the message stamp (arrival), at most truth_max_age_s old",
            "obstacle_cell": "truth finite and <= the message's max_distance",
            "clear_cell": "truth inf or > max_distance",
            "tolerance": f"max({cfg.tolerance_m:g} m, {100 * cfg.tolerance_rel:g} % of the true distance)",
            "false_obstacle": "range in a clear cell nearer than the truth by more than the tolerance (truth inf taken at "
                              "sector_max_m, the most favourable case; within tolerance of it = unverifiable); too_near: the same "
                              "in an obstacle cell",
            "dangerous_clear": "max_distance + 1 reported in an obstacle cell",
            "messages_without_false_obstacle": "over messages with a claim and at least one scored clear cell",
            "in_view": "the sector's centre bearing projects into the camera image (truth.npz in_view); truth files "
                       "without it: the sectors whose truth is known",
            "out_of_view": "cells outside the camera's view are scored only where a claim (a range or clear) is made: "
                           "a range within tolerance on an obstacle is a (remembered) detection, too near in a clear cell "
                           "a false obstacle, clear on an obstacle a dangerous clear; unknown there is neutral (not a miss)",
            "detection_within_tolerance": "a range within tolerance (valid range)",
            "remembered": f"out-of-view obstacle cells whose obstacle (grouped by position) occupied an in-view cell "
                          f"within the last {cfg.remember_window_s:g} s, the vehicle having moved < {cfg.remember_max_travel_m:g} m "
                          "since the latest such frame; unknown there counts as not reported",
            "warmup": f"messages stamped within {cfg.warmup_s:g} s of the first truth frame are not scored (latency and "
                      "first claim include them)",
        },
        "config": dataclasses.asdict(cfg),
        "duration_s": float(ev.od_t[-1] - ev.t0) if len(ev.od_t) else 0.0,
        "truth_horizon_m": ev.sector_max_m,
        "messages": {
            "by_type": counts.get("by_type", {}),
            "obstacle_distance": int(len(ev.od_t)), "obstacle_distance_scored": int(scored.sum()),
            "in_warmup": int(np.sum(ev.od_warmup & msgs.od_geometry_ok & (ev.od_frame >= 0))),
            "without_truth": int(np.sum(msgs.od_geometry_ok & (ev.od_frame < 0))),
            "with_claims": int(claims.sum()),
            "reader": {k: v for k, v in counts.items() if k != "by_type"},
            "heartbeat_active_share": _rate(int(np.sum(hb == 4)), int(hb.size)),  # MAV_STATE_ACTIVE = 4
            "statustext": [f"{t - ev.t0:.2f} s: {txt}" for t, _, txt in msgs.texts][:50],
        },
        "first_claim_at_s": float(ev.od_t[first_claim[0]] - ev.t0) if first_claim.size else None,
        "warmup": {"s": cfg.warmup_s, "messages_excluded": int(np.sum(ev.od_warmup & msgs.od_geometry_ok & (ev.od_frame >= 0)))},
        "truth_360": ev.truth_360,
        "cells": cells,
        "rates": rates,
        "cells_in_view": cells_iv,
        "rates_in_view": rates_iv,
        "cells_out_of_view": cells_oov,
        "rates_out_of_view": rates_oov,
        "detection_by_range": det_tables,
        "remembered": remembered,
        "false_obstacles_beside_obstacle": false_beside,
        "targets": targets,
        "sectors": sectors,
        "range_error": range_error,
        "obstacles": _obstacle_rows(ev, m),
        "latency": latency,
        "nees": nees,
        "distance_sensor": ds,
        "notes": list(ev.notes),
    }
    return _jsonable(out)


def nees_samples(ev: Evaluation, at: str = "exposure") -> np.ndarray:
    """NEES samples of the forward estimate (``at`` = ``"exposure"`` or ``"arrival"`` truth)."""
    T = ev.ds_truth_exposure if at == "exposure" else ev.ds_truth_arrival
    ok = (ev.ds_state == REP_RANGE) & np.isfinite(ev.ds_sigma_m) & (ev.ds_sigma_m > 0) & np.isfinite(T) & np.isfinite(ev.ds_estimate_m)
    return ((ev.ds_estimate_m[ok] - T[ok]) / ev.ds_sigma_m[ok]) ** 2


def nees_stats(samples: np.ndarray, confidence: float) -> dict:
    s = np.asarray(samples, float)
    lo, hi = nees_band(int(s.size), confidence)
    mean = float(s.mean()) if s.size else None
    return {"n": int(s.size), "mean": mean, "median": _pct(s, 50), "band": [lo, hi] if s.size else None,
            "consistent": None if mean is None else bool(lo <= mean <= hi)}


def nees_summary(ev: Evaluation) -> dict:
    out = nees_stats(nees_samples(ev, "exposure"), ev.config.nees_confidence)
    arr = nees_stats(nees_samples(ev, "arrival"), ev.config.nees_confidence)
    out["at"] = "exposure (paired OBSTACLE_DISTANCE time_usec)"
    out["arrival"] = arr
    out["confidence"] = ev.config.nees_confidence
    return out


def series_arrays(ev: Evaluation) -> dict[str, np.ndarray]:
    """Per-message arrays a campaign report pools over runs (saved as ``score_series.npz``)."""
    m = cell_masks(ev)
    return {
        "t0": np.array(ev.t0), "sector_max_m": np.array(ev.sector_max_m),
        "od_t": ev.od_t, "od_scored": ev.od_scored, "od_rep": ev.od_rep, "od_cm": ev.od_cm.astype(np.int32), "od_truth": ev.od_truth.astype(np.float32),
        "od_tcls": ev.od_tcls, "od_label": ev.od_label.astype(np.int16), "od_max_m": ev.od_max_m,
        "od_latency_s": ev.od_latency_s, "od_in_view": ev.od_in_view, "od_remember": ev.od_remember,
        "od_warmup": ev.od_warmup, "det_true_m": ev.od_truth[m.detection], "det_published_m": ev.od_r[m.detection],
        "ds_t": ev.ds_t, "ds_state": ev.ds_state, "ds_published_m": ev.ds_published_m, "ds_sigma_m": ev.ds_sigma_m,
        "ds_estimate_m": ev.ds_estimate_m, "ds_truth_arrival": ev.ds_truth_arrival, "ds_truth_exposure": ev.ds_truth_exposure,
        "ds_max_m": ev.ds_max_m, "nees_exposure": nees_samples(ev, "exposure"), "nees_arrival": nees_samples(ev, "arrival"),
        "obstacle_names": np.array(ev.obstacle_names, dtype="U128"),
    }


def _jsonable(x):
    """NaN/inf → None, numpy scalars → Python, recursively."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return [_jsonable(v) for v in x.tolist()]
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        v = float(x)
        return v if math.isfinite(v) else None
    return x


# ---------------------------------------------------------------------- markdown ---------------
def _f(v, fmt: str = "{:.2f}", none: str = "–") -> str:
    return none if v is None else fmt.format(v)


def _pc(v, digits: int = 1) -> str:
    return "–" if v is None else f"{100 * v:.{digits}f} %"


def mark(met) -> str:
    return "–" if met is None else ("✓" if met else "✗")


def markdown(score: dict, title: str = "Score") -> str:
    """``score.md``: the definitions, the targets with ✓/✗ and the tables of one run."""
    s = score
    c, r = s["cells"], s["rates"]
    cfg = s["config"]
    L = [f"# {title}", ""]
    if s.get("inputs"):
        L += [f"Ranges: `{s['inputs'].get('ranges')}`  ", f"Truth: `{s['inputs'].get('truth')}`", ""]
    wu = s.get("warmup") or {"s": cfg.get("warmup_s", 0.0), "messages_excluded": 0}
    if s.get("avoidance"):
        from flightsim.outcome import outcome_markdown

        L += outcome_markdown(s["avoidance"])
    L += ["## Targets", "",
          f"Warm-up: cells of the first {wu['s']:g} s of the run are not scored ({wu['messages_excluded']} messages).  "
          + ("Truth over 360°: out-of-view claims are scored, unknown out of view is neutral." if s.get("truth_360")
             else "Truth of the sectors in view only (an older truth.npz): out-of-view claims are not scored."), "",
          "| target | value | threshold | n | met |", "|---|---|---|---|---|"]
    for t in s["targets"]:
        L.append(f"| {t['name']} | {_pc(t['value'], 2)} | {t['op']} {100 * t['threshold']:g} % | {t['n']} | {mark(t['met'])} |")
    civ, cov = s.get("cells_in_view") or {}, s.get("cells_out_of_view") or {}
    riv, rov = s.get("rates_in_view") or {}, s.get("rates_out_of_view") or {}

    def row(label, key, rkey=None, d=1):
        def one(cc, rr):
            v = f"{cc.get(key, 0)}"
            return v + (f" ({_pc(rr.get(rkey), d)})" if rkey and rr.get(rkey) is not None else "")
        return f"| {label} | {one(civ, riv)} | {one(cov, rov)} | {one(c, r)} |"

    L += ["", "## Cells", "",
          f"Scored OBSTACLE_DISTANCE messages: {s['messages']['obstacle_distance_scored']} of "
          f"{s['messages']['obstacle_distance']} ({s['messages']['without_truth']} without a truth frame, "
          f"{s['messages'].get('in_warmup', 0)} in the warm-up); "
          f"with a claim: {s['messages']['with_claims']}; first claim {_f(s['first_claim_at_s'], '{:.2f} s')} after the first frame.  "
          "Out of view only cells with a claim count (unknown there is neutral).", "",
          "| quantity | in view | out of view | all scored |", "|---|---|---|---|",
          row("obstacle cells", "obstacle"),
          row("detections (range reported)", "detections", "detection"),
          row("valid ranges (within tolerance)", "valid_ranges", "valid_range"),
          row("unknown in obstacle cells", "unknown_in_obstacle_cells", "unknown_in_obstacle_cells"),
          row("**dangerous clears**", "dangerous_clears", "dangerous_clear", 2),
          row("too near (false obstacle in an obstacle cell)", "too_near", "too_near"),
          row("over range", "over_range", "over_range"),
          row("clear cells", "clear"),
          row("false obstacles in clear cells", "false_obstacles_clear_cells", "false_obstacle_clear_cells", 2),
          row(f"ranges beyond the truth horizon ({s['truth_horizon_m']:g} m), unverifiable", "unverifiable_beyond_truth"),
          row("clear claimed in clear cells", "clear_claimed_in_clear_cells", "clear_claimed_in_clear_cells"),
          "| messages without a false obstacle / eligible | " + " | ".join(
              f"{cc.get('messages_without_false_obstacle', 0)} / {cc.get('messages_eligible_no_false', 0)} "
              f"({_pc(rr.get('messages_without_false_obstacle'))})" for cc, rr in ((civ, riv), (cov, rov), (c, r))) + " |",
          row("claims in cells of unknown truth (not scored)", "unscored_claims"),
          row("invalid values", "invalid_values"), ""]
    if cov:
        L += [f"Out of view in total: {cov.get('obstacle_cells_total', 0)} obstacle cells and {cov.get('clear_cells_total', 0)} "
              f"clear cells; unknown there (neutral): {cov.get('unknown_neutral', 0)}.", ""]
    rem = s.get("remembered")
    if rem:
        L += [f"Remembered obstacles out of view (in view within {rem['window_s']:g} s, vehicle moved < {rem['max_travel_m']:g} m): "
              f"{rem['cells']} cells, within tolerance {rem['within_tolerance']} ({_pc(rem['rate'])}), ranges {rem['ranges']}, "
              f"unknown {rem['unknown']}, dangerous clears {rem['dangerous_clears']}.", ""]
    fb = s.get("false_obstacles_beside_obstacle")
    if fb and (fb["in_view_total"] or fb["out_of_view_total"]):
        L += [f"False obstacles beside an obstacle (the range of a true obstacle cell within {fb['sectors']} sectors, within "
              f"tolerance: a real obstacle on a neighbouring bearing, not a phantom): in view {fb['in_view']} of "
              f"{fb['in_view_total']}, out of view {fb['out_of_view']} of {fb['out_of_view_total']}.", ""]
    dbr = s.get("detection_by_range")
    if dbr:
        L += ["## Detection by true range", "",
              "Detection = a range within tolerance.  Out of view every obstacle cell is listed (unknown included); "
              "'of claimed' is the share within tolerance of the cells with a range or clear.", ""]
        for key, label in (("in_view", "In view"), ("out_of_view", "Out of view")):
            L += [f"{label}:", "", "| true range | obstacle cells | detection | range reported | unknown | clear (dangerous) | of claimed |",
                  "|---|---|---|---|---|---|---|"]
            for b in dbr[key]:
                L.append(f"| {b['bin']} | {b['obstacle_cells']} | {_pc(b['valid_rate'])} | {_pc(b['range_rate'])} | "
                         f"{_pc(b['unknown_rate'])} | {b['clear']} | {_pc(b['valid_of_claimed'])} |")
            L.append("")
    L += ["## Range error (published − true), by true range", ""]
    for key, label in (("published_all_sectors", "Conservative published value, all sectors (detections)"),
                       ("published_forward", "Conservative published value, forward DISTANCE_SENSOR"),
                       ("estimate_forward", f"Estimate (published + {cfg['sigma_k']:g}·σ), forward DISTANCE_SENSOR")):
        L += [f"{label}:", "", "| true range | n | bias m | mean abs m | median abs m | p95 abs m | mean abs % | median abs % |",
              "|---|---|---|---|---|---|---|---|"]
        for row in s["range_error"][key]:
            L.append(f"| {row['bin']} | {row['n']} | {_f(row['bias_m'])} | {_f(row['mae_m'])} | {_f(row['median_abs_m'])} | "
                     f"{_f(row['p95_abs_m'])} | {_f(row['mae_pct'], '{:.1f}')} | {_f(row['median_abs_pct'], '{:.1f}')} |")
        L.append("")
    ne = s["nees"]
    band = ne["band"] or [None, None]
    L += ["## NEES of the reported σ (forward)", "",
          f"Against the truth at exposure: n = {ne['n']}, mean {_f(ne['mean'])}, median {_f(ne['median'])}, "
          f"{100 * ne['confidence']:g} % band [{_f(band[0], '{:.3f}')}, {_f(band[1], '{:.3f}')}] {mark(ne['consistent'])}; "
          f"at arrival: n = {ne['arrival']['n']}, mean {_f(ne['arrival']['mean'])}.  σ from covariance: "
          f"{s['distance_sensor']['sigma_from_covariance']}, from signal_quality: {s['distance_sensor']['sigma_from_signal_quality']}.  "
          "Consecutive samples are correlated, so the band is optimistic.", ""]
    la = s["latency"]
    L += ["## Latency (exposure → message stamp)", "",
          f"n = {la['n']}: p50 {_f(la['p50_ms'], '{:.1f}')} ms, p95 {_f(la['p95_ms'], '{:.1f}')} ms, "
          f"p99 {_f(la['p99_ms'], '{:.1f}')} ms, max {_f(la['max_ms'], '{:.1f}')} ms; exposures not matched to a frame: "
          f"{la['unmatched_exposures']}.", ""]
    L += ["## Obstacles (time to the first valid range)", "",
          "| obstacle | in range at s | first valid at s | time to first valid s | detected | valid | nearest true m |",
          "|---|---|---|---|---|---|---|"]
    for o in s["obstacles"]:
        L.append(f"| {o['name']} | {_f(o['in_range_at_s'])} | {_f(o['first_valid_at_s'])} | "
                 f"{_f(o['time_to_first_valid_s'], '{:.2f}', 'never')} | {_pc(o['detected_fraction'], 0)} | "
                 f"{_pc(o['valid_fraction'], 0)} | {_f(o['nearest_true_m'], '{:.1f}')} |")
    ds = s["distance_sensor"]
    L += ["", "## Forward DISTANCE_SENSOR", "",
          f"{ds['messages']} messages: {ds['ranges']} ranges, {ds['clear']} clear, {ds['unknown']} unknown; obstacle ahead in "
          f"{ds['obstacle_messages']}, detected in {_pc(ds['detection_rate'])}, dangerous clears {ds['dangerous_clears']}.", ""]
    L += ["## Per sector", "", "| sector | bearing ° | obstacle cells | detection | dangerous | too near | clear cells | "
          "false obstacle | clear claimed |", "|---|---|---|---|---|---|---|---|---|"]
    for row in s["sectors"]:
        L.append(f"| {row['sector']} | {row['bearing_deg']:+.0f} | {row['obstacle_cells']} | {_pc(row['detection_rate'], 0)} | "
                 f"{row['dangerous_clears']} | {row['too_near']} | {row['clear_cells']} | {_pc(row['false_obstacle_rate'])} | "
                 f"{row['clear_claimed']} |")
    d = s["definitions"]
    L += ["", "## Definitions", ""] + [f"- **{k.replace('_', ' ')}**: {v}" for k, v in d.items()]
    L += [f"- **range bins**: lower edges {cfg['range_bins_m']} m; σ from DISTANCE_SENSOR covariance (cm²) or "
          f"signal_quality (zero at σ/d = {cfg['quality_zero_rel_sigma']:g}); k = {cfg['sigma_k']:g}",
          "- **obstacles**: truth cells grouped by world position (link max("
          f"{cfg['obstacle_link_m']:g} m, {100 * cfg['obstacle_link_rel']:g} % of range)); in range = first message with one of its "
          "cells an obstacle cell; valid = a range within tolerance in one of its cells",
          "- **latency**: stamp − exposure (OBSTACLE_DISTANCE time_usec mapped to the recording clock by the companion's own "
          "time_boot_ms, snapped to the truth frame)"]
    if s.get("notes"):
        L += ["", "## Notes", ""] + [f"- {n}" for n in s["notes"]]
    return "\n".join(L) + "\n"


# ---------------------------------------------------------------------- entry points (I/O) -----
