"""What the companion's messages say, decoded the way the MAVLink spec defines them (docs/derivations/sectors.md).

Pure (no I/O).  :func:`decode_obstacle_distance` reads an OBSTACLE_DISTANCE into
:class:`DecodedSectors`: UINT16_MAX = unknown, ``max_distance + 1`` = clear, ``increment_f`` used
when non-zero, else ``increment``; ``angle_offset``; ``frame``: BODY_FRD = forward-aligned, GLOBAL
/ LOCAL_NED = north-aligned.  :func:`decode_distance_sensor` reads the forward DISTANCE_SENSOR
(``covariance`` in cm², 255 = unknown) into a :class:`ForwardReading`.  :func:`bin_sectors` folds
the 72 elements into fewer display bins, conservatively.  The enum names (:func:`state_name`, …)
are shared with :mod:`.state` and :mod:`.view`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion.mavlink.dialect import UINT16_MAX, mavlink  # first: MAVLink 2 + ardupilotmega
from companion.core.sectors import SECTOR_COUNT, SectorState

UINT8_MAX = 255


# ---------------------------------------------------------------------- names ------------------
def _enum_name(enum: str, value: int, prefix: str) -> str:
    e = mavlink.enums.get(enum, {}).get(value)
    return e.name[len(prefix):] if e is not None and e.name.startswith(prefix) else str(value)


def state_name(system_status: int) -> str:
    """MAV_STATE value → "ACTIVE", "STANDBY", … (the number when unknown)."""
    return _enum_name("MAV_STATE", system_status, "MAV_STATE_")


def severity_name(severity: int) -> str:
    return _enum_name("MAV_SEVERITY", severity, "MAV_SEVERITY_")


def frame_name(frame: int) -> str:
    return _enum_name("MAV_FRAME", frame, "MAV_FRAME_")


# ---------------------------------------------------------------------- decoding ---------------
class DecodeError(ValueError):
    """A message no receiver could interpret (e.g. OBSTACLE_DISTANCE with increment 0)."""


@dataclasses.dataclass(frozen=True, eq=False)
class DecodedSectors:
    """One OBSTACLE_DISTANCE as the spec defines it (element ``i`` at ``angle_offset + i·increment``)."""

    raw_cm: np.ndarray  # (72,) distances as sent, cm
    bearing_deg: np.ndarray  # (72,) clockwise from the frame's reference (forward / north), in [-180, 180)
    state: np.ndarray  # (72,) SectorState
    range_m: np.ndarray  # (72,) metres where state == OBSTACLE, nan elsewhere
    min_distance_m: float
    max_distance_m: float
    increment: int  # uint8 field
    increment_f: float  # float field (used when > 0)
    increment_deg: float  # the one that applies
    angle_offset_deg: float
    frame: int
    warnings: tuple[str, ...] = ()

    @property
    def frame_name(self) -> str:
        return frame_name(self.frame)

    @property
    def reference(self) -> str:
        """What bearing 0 means: "forward" (BODY_FRD), "north" (GLOBAL / LOCAL_NED) or the frame name."""
        if self.frame == mavlink.MAV_FRAME_BODY_FRD:
            return "forward"
        if self.frame in (mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_LOCAL_NED):
            return "north"
        return self.frame_name

    def counts(self) -> dict[str, int]:
        return {"obstacle": int(np.count_nonzero(self.state == SectorState.OBSTACLE)),
                "clear": int(np.count_nonzero(self.state == SectorState.CLEAR)),
                "unknown": int(np.count_nonzero(self.state == SectorState.UNKNOWN))}

    def nearest(self) -> tuple[float, float, int]:
        """(range m, bearing deg, element index) of the nearest obstacle; (nan, nan, -1) if none."""
        r = np.where(self.state == SectorState.OBSTACLE, self.range_m, np.inf)
        if not np.isfinite(r).any():
            return math.nan, math.nan, -1
        i = int(np.argmin(r))
        return float(r[i]), float(self.bearing_deg[i]), i


def _wrap_deg(a):
    """Degrees into [-180, 180)."""
    return np.mod(np.asarray(a, dtype=float) + 180.0, 360.0) - 180.0


def decode_obstacle_distance(m) -> DecodedSectors:
    """Decode an OBSTACLE_DISTANCE message (docs/derivations/sectors.md); :class:`DecodeError` when it cannot be read.

    * UINT16_MAX = unknown; ``max_distance + 1`` = clear; a value above that (other than
      UINT16_MAX) has no defined meaning and is shown as unknown (with a warning);
    * a value at or below ``max_distance`` is an obstacle, including 0 ("touching") and values
      below ``min_distance`` (which ArduPilot ignores: warned, but shown, the safe direction);
    * ``increment_f`` applies when non-zero, else ``increment``; both zero cannot be decoded; a
      disagreement between them is warned (Mission Planner reads ``increment``).
    """
    raw = np.asarray(list(m.distances), dtype=np.int64)
    if raw.shape != (SECTOR_COUNT,):
        raise DecodeError(f"OBSTACLE_DISTANCE with {raw.size} distances (72 expected)")
    min_cm, max_cm = int(m.min_distance), int(m.max_distance)
    if not max_cm > min_cm:
        raise DecodeError(f"OBSTACLE_DISTANCE with min_distance {min_cm} cm >= max_distance {max_cm} cm")
    inc_i = int(m.increment)
    inc_f = float(m.increment_f) if math.isfinite(float(m.increment_f)) else 0.0
    inc = inc_f if inc_f > 0 else float(inc_i)
    if not inc > 0:
        raise DecodeError("OBSTACLE_DISTANCE with increment 0 and increment_f 0")
    offset = float(m.angle_offset)
    if not math.isfinite(offset):
        raise DecodeError(f"OBSTACLE_DISTANCE with angle_offset {m.angle_offset}")
    warnings = []
    if inc_f > 0 and inc_i > 0 and abs(inc_i - inc_f) > 0.5:
        warnings.append(f"increment {inc_i} disagrees with increment_f {inc_f:g}")
    frame = int(m.frame)
    if frame != mavlink.MAV_FRAME_BODY_FRD:
        warnings.append(f"frame {frame_name(frame)} (bearings from {'north' if frame in (0, 1) else 'that frame'})")
    unknown = raw == UINT16_MAX
    clear = raw == max_cm + 1
    beyond = (raw > max_cm + 1) & ~unknown
    obstacle = raw <= max_cm
    if beyond.any():
        warnings.append(f"{int(beyond.sum())} distance(s) above max_distance + 1 shown as unknown")
    below = obstacle & (raw < min_cm)
    if below.any():
        warnings.append(f"{int(below.sum())} distance(s) below min_distance")
    state = np.full(SECTOR_COUNT, int(SectorState.UNKNOWN), dtype=np.int8)
    state[clear] = SectorState.CLEAR
    state[obstacle] = SectorState.OBSTACLE
    range_m = np.where(obstacle, raw / 100.0, np.nan)
    bearing = _wrap_deg(offset + inc * np.arange(SECTOR_COUNT))
    return DecodedSectors(raw, bearing, state, range_m, min_cm / 100.0, max_cm / 100.0, inc_i, inc_f, inc, offset, frame,
                          tuple(warnings))


def bin_sectors(d: DecodedSectors, bins: int = SECTOR_COUNT) -> tuple[np.ndarray, np.ndarray]:
    """Elements into ``bins`` equal display bins over 360° (bin ``j`` centred on ``j·360/bins``).

    A bin is an obstacle at the nearest range of the elements in it, clear only when every element
    in it is clear, unknown otherwise (also when no element falls in it: a narrow ``increment``).
    Returns ``(state, range_m)``.
    """
    width = 360.0 / bins
    j = np.floor(np.mod(d.bearing_deg + width / 2.0, 360.0) / width).astype(np.int64) % bins
    obst = d.state == SectorState.OBSTACLE
    rng = np.full(bins, np.inf)
    np.minimum.at(rng, j[obst], d.range_m[obst])
    n_all = np.bincount(j, minlength=bins)
    n_clear = np.bincount(j[d.state == SectorState.CLEAR], minlength=bins)
    state = np.where(np.isfinite(rng), int(SectorState.OBSTACLE),
                     np.where((n_all > 0) & (n_clear == n_all), int(SectorState.CLEAR), int(SectorState.UNKNOWN)))
    return state.astype(np.int8), np.where(np.isfinite(rng), rng, np.nan)


@dataclasses.dataclass(frozen=True)
class ForwardReading:
    """One DISTANCE_SENSOR (orientation forward) as the companion encodes it (docs/derivations/sectors.md)."""

    state: str  # "obstacle", "clear" (beyond max_distance) or "unknown" (UINT16_MAX or signal_quality 1)
    distance_m: float  # nan unless obstacle
    sigma_m: float  # from covariance (cm²); nan when 255 = unknown
    covariance_cm2: int
    signal_quality: int  # 0 unknown, 1 invalid, 2…100
    min_distance_m: float
    max_distance_m: float
    sensor_id: int


def decode_distance_sensor(m) -> ForwardReading:
    d, cov, q = int(m.current_distance), int(m.covariance), int(m.signal_quality)
    lo, hi = int(m.min_distance) / 100.0, int(m.max_distance) / 100.0
    sigma = math.sqrt(cov) / 100.0 if cov < UINT8_MAX else math.nan
    if d == UINT16_MAX or q == 1:
        state, dist, sigma = "unknown", math.nan, math.nan
    elif d > int(m.max_distance):
        state, dist, sigma = "clear", math.nan, math.nan
    else:
        state, dist = "obstacle", d / 100.0
    return ForwardReading(state, dist, sigma, cov, q, lo, hi, int(m.id))
