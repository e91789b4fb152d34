"""What the score reads, as arrays: :class:`RangeMessages` (the companion's OBSTACLE_DISTANCE,
DISTANCE_SENSOR, HEARTBEAT and STATUSTEXT messages with their record stamps) and
:class:`SectorTruth` (the parts of ``truth.npz`` the score needs).  :mod:`flightsim.score.files`
reads them from files; tests build them directly.  Definitions: :mod:`flightsim.score`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from companion.errors import InputError
from flightsim.score.config import N_SECTORS


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
