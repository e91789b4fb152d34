"""``companion monitor CONN``: a ground-station view of a running companion in the terminal.

What the messages mean is in docs/derivations/sectors.md; this module only listens and shows.

Pure layer (no I/O; the caller's clock)
    :func:`decode_obstacle_distance` / :func:`decode_distance_sensor` read one message the way the
    MAVLink spec defines it (UINT16_MAX = unknown, ``max_distance + 1`` = clear, ``increment_f``
    used when non-zero, else ``increment``; ``angle_offset``; ``frame``: BODY_FRD = forward-aligned,
    GLOBAL / LOCAL_NED = north-aligned; DISTANCE_SENSOR ``covariance`` in cm², 255 = unknown).
    :class:`MonitorState` folds decoded pymavlink messages from the companion (component 196 by
    default, one system: the first heard or ``system_id``) into the latest sectors, the forward
    DISTANCE_SENSOR, the companion's HEARTBEAT, NAMED_VALUE_FLOAT / _INT diagnostics, the last
    STATUSTEXTs (chunked texts reassembled), message rates and counts, and the errors met on the
    wire (bad CRC, bad prefix, unknown ids, truncated datagrams).  :meth:`MonitorState.snapshot`
    turns it into an immutable :class:`Snapshot` with ages, stale flags (sectors / forward range
    older than ``stale_s`` = 0.5 s, where both autopilots drop them) and the link state ("lost"
    after ``link_timeout_s`` = 3 s without a HEARTBEAT).
    :func:`render` turns a snapshot into a rich renderable (a 72-sector strip, red near / yellow
    mid / green far and clear / grey unknown; stale data drawn grey and labelled STALE, never as
    current); :meth:`Snapshot.to_json` into one JSON-ready dict.

I/O layer (thin)
    :func:`open_connection` (pymavlink, robust parsing), :class:`Reader` (non-blocking reads,
    one datagram parsed on its own, parser errors counted, never raised) and :func:`run_monitor`
    (rich ``Live`` at ~5 Hz on a terminal; otherwise a text or JSON snapshot every ``interval``
    seconds, or one snapshot with ``once``).  A GCS HEARTBEAT is sent once a second unless
    ``passive`` (a ``udpout:`` companion output only learns where to send once it hears one).
"""

from __future__ import annotations

import collections
import dataclasses
import io
import json
import logging
import math
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from companion.mavlink.dialect import UINT16_MAX, mavlink, mavutil  # first: MAVLink 2 + ardupilotmega
from companion.config import require, require_finite
from companion.core.sectors import SECTOR_COUNT, SectorState
from companion.errors import ConfigError

log = logging.getLogger(__name__)

UINT8_MAX = 255
STATUSTEXT_LEN = 50
#: A chunked STATUSTEXT still missing its last chunk after this long is shown as it is (marked incomplete).
CHUNK_TIMEOUT_S = 2.0
#: At most this many NAMED_VALUE names / foreign sources are remembered (a flood cannot grow memory).
MAX_NAMES = 32
MAX_SOURCES = 64

#: Friendly labels for the companion's own diagnostics (:attr:`companion.pipeline.Reporter.DIAG_NAMES`).
DIAG_LABELS = {"MR_FPS": "fps", "MR_TRACKS": "tracks", "MR_NEAR_M": "nearest m", "MR_LAT_MS": "latency ms",
               "MR_MAP": "map points", "MR_MEM_SEC": "sectors from memory", "MR_INFER": "inferred sectors",
               "MR_FWD_M": "forward m", "MR_FWD_SIG": "forward σ m"}


# ---------------------------------------------------------------------- configuration ----------
@dataclasses.dataclass(frozen=True)
class MonitorConfig:
    """What the monitor listens to and how it judges age."""

    component_id: int = 196  # component of the companion (MAV_COMP_ID_OBSTACLE_AVOIDANCE)
    system_id: int = 0  # 0 = any: follow the first system heard with that component
    stale_s: float = 0.5  # sectors / forward range older than this are stale (ArduPilot and PX4 drop them after 0.5 s)
    link_timeout_s: float = 3.0  # "link lost" after this long without a HEARTBEAT from the companion
    rate_window_s: float = 2.0  # message rates are measured over this sliding window
    statustext_lines: int = 5  # STATUSTEXT lines kept and shown
    near_m: float = 5.0  # obstacles nearer than this are red
    mid_m: float = 15.0  # obstacles nearer than this (and >= near_m) are yellow; farther ones and "clear" green

    def __post_init__(self) -> None:
        for name in ("component_id", "system_id"):
            v = getattr(self, name)
            require(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 255, f"{name} must be 0..255, got {v!r}")
        require(self.component_id > 0, "component_id must be 1..255 (0 is not a component)")
        for name in ("stale_s", "link_timeout_s", "rate_window_s", "near_m", "mid_m"):
            require_finite(name, getattr(self, name), positive=True)
        require(self.near_m < self.mid_m, f"near_m ({self.near_m}) must be < mid_m ({self.mid_m})")
        require(isinstance(self.statustext_lines, int) and 1 <= self.statustext_lines <= 100,
                f"statustext_lines must be 1..100, got {self.statustext_lines!r}")


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


def classify_bad_data(reason: str) -> str:
    """Error counter for a pymavlink BAD_DATA reason."""
    r = str(reason)
    if "signature" in r:
        return "bad_signature"
    if "CRC" in r:
        return "bad_crc"
    if "prefix" in r:
        return "bad_prefix"
    if "length" in r or "Bad message" in r:
        return "bad_length"
    return "bad_data"


def _clean_text(value) -> str:
    """Printable text only: a STATUSTEXT must not carry terminal escapes into the view."""
    if isinstance(value, (bytes, bytearray)):
        value = bytes(value).split(b"\x00", 1)[0].decode("ascii", errors="replace")
    s = str(value).split("\x00", 1)[0]
    return "".join(c if c.isprintable() else "?" for c in s)


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


# ---------------------------------------------------------------------- state ------------------
class _Rates:
    """Arrivals per message name over a sliding window; before a full window has passed since the
    start, the rate is taken over the time listened so far (not under-reported)."""

    MIN_ELAPSED_S = 0.5

    def __init__(self, window_s: float, start: float):
        self.window_s = window_s
        self.start = start
        self._t: dict[str, collections.deque[float]] = {}

    def tick(self, name: str, now: float) -> None:
        q = self._t.setdefault(name, collections.deque())
        q.append(now)
        while q and now - q[0] >= self.window_s:
            q.popleft()

    def rates(self, now: float) -> dict[str, float]:
        span = min(self.window_s, now - self.start)
        out = {}
        for name, q in self._t.items():
            while q and (now - q[0] >= self.window_s or q[0] > now):
                q.popleft()
            out[name] = len(q) / span if span >= self.MIN_ELAPSED_S else math.nan
        return out


@dataclasses.dataclass(frozen=True)
class StatusLine:
    t: float  # arrival (last chunk), caller's clock
    severity: int
    text: str
    complete: bool = True  # False: a chunked text with missing chunks


@dataclasses.dataclass
class _Pending:
    severity: int
    t: float
    parts: dict[int, str]


class MonitorState:
    """The view model: fold messages in with :meth:`add`, read it with :meth:`snapshot` (pure)."""

    def __init__(self, config: MonitorConfig = MonitorConfig(), start: float = 0.0):
        self.config = config
        self.start = start
        self.system_id: int | None = config.system_id or None
        self.counts: collections.Counter[str] = collections.Counter()  # per message type from the companion
        self.errors: collections.Counter[str] = collections.Counter()
        self.other_sources: collections.Counter[tuple[int, int]] = collections.Counter()
        self.other_companions: set[int] = set()
        self.rx_bytes = 0
        self._rates = _Rates(config.rate_window_s, start)
        self.last_message_t: float | None = None
        self.heartbeat: tuple[float, Any] | None = None  # (t, HEARTBEAT)
        self.sectors: tuple[float, DecodedSectors] | None = None
        self.forward: tuple[float, ForwardReading] | None = None
        self.diagnostics: dict[str, tuple[float, float]] = {}
        self.texts: collections.deque[StatusLine] = collections.deque(maxlen=config.statustext_lines)
        self._chunks: dict[int, _Pending] = {}

    # -- input ------------------------------------------------------------------------------------
    def add_error(self, kind: str, n: int = 1) -> None:
        """An error seen by the I/O layer (truncated datagram, parser exception, read error)."""
        self.errors[kind] += n

    def add_bytes(self, n: int) -> None:
        self.rx_bytes += n

    def add(self, m, now: float) -> bool:
        """Fold one decoded pymavlink message in; True when it came from the companion and was used.

        Never raises on what came off the wire: BAD_DATA and unknown ids are counted, a message
        that cannot be decoded is counted (``invalid_<TYPE>``) and leaves the state as it was.
        """
        t = m.get_type()
        if t == "BAD_DATA":
            self.errors[classify_bad_data(getattr(m, "reason", ""))] += 1
            return False
        if t.startswith("UNKNOWN_"):
            self.errors["unknown_id"] += 1
            return False
        src = (int(m.get_srcSystem()), int(m.get_srcComponent()))
        if src[1] != self.config.component_id:
            self._other(src)
            return False
        if self.system_id is None:
            self.system_id = src[0]
        elif src[0] != self.system_id:
            if len(self.other_companions) < MAX_SOURCES:
                self.other_companions.add(src[0])
            self._other(src)
            return False
        try:
            used = self._fold(t, m, now)
        except (DecodeError, TypeError, ValueError, AttributeError, OverflowError) as exc:
            self.errors[f"invalid_{t}"] += 1
            log.debug("undecodable %s: %s", t, exc)
            return False
        self.counts[t] += 1
        self._rates.tick(t, now)
        self.last_message_t = now
        return used

    def _other(self, src: tuple[int, int]) -> None:
        if src in self.other_sources or len(self.other_sources) < MAX_SOURCES:
            self.other_sources[src] += 1
        else:
            self.other_sources[(-1, -1)] += 1  # "others"

    def _fold(self, t: str, m, now: float) -> bool:
        if t == "OBSTACLE_DISTANCE":
            self.sectors = (now, decode_obstacle_distance(m))
        elif t == "DISTANCE_SENSOR":
            if int(m.orientation) != mavlink.MAV_SENSOR_ROTATION_NONE:
                return False  # only the forward one is shown (rates still count the others)
            self.forward = (now, decode_distance_sensor(m))
        elif t == "HEARTBEAT":
            self.heartbeat = (now, m)
        elif t in ("NAMED_VALUE_FLOAT", "NAMED_VALUE_INT"):
            name = _clean_text(m.name)[:10] or "?"
            if name in self.diagnostics or len(self.diagnostics) < MAX_NAMES:
                self.diagnostics[name] = (now, float(m.value))
            else:
                self.errors["diagnostics_dropped"] += 1
        elif t == "STATUSTEXT":
            self._statustext(m, now)
        else:
            return False
        return True

    def _statustext(self, m, now: float) -> None:
        sev, text = int(m.severity), _clean_text(m.text)
        cid, seq = int(getattr(m, "id", 0) or 0), int(getattr(m, "chunk_seq", 0) or 0)
        self._flush_chunks(now)
        if cid == 0:
            self.texts.append(StatusLine(now, sev, text))
            return
        p = self._chunks.get(cid)
        if p is not None and seq in p.parts:  # the id came round again: the old text lost its end
            self._emit(cid, complete=False)
            p = None
        if p is None:
            if len(self._chunks) >= 16:
                self._emit(min(self._chunks, key=lambda k: self._chunks[k].t), complete=False)
            p = self._chunks[cid] = _Pending(sev, now, {})
        p.parts[seq] = text
        p.t = now
        if len(text) < STATUSTEXT_LEN:  # the last chunk (shorter than 50, possibly empty)
            self._emit(cid, complete=all(i in p.parts for i in range(seq + 1)))

    def _emit(self, cid: int, complete: bool) -> None:
        p = self._chunks.pop(cid)
        last = max(p.parts)
        text = "".join(p.parts.get(i, "…") for i in range(last + 1))
        self.texts.append(StatusLine(p.t, p.severity, text if complete else text + "…", complete))

    def _flush_chunks(self, now: float) -> None:
        for cid in [c for c, p in self._chunks.items() if now - p.t > CHUNK_TIMEOUT_S]:
            self._emit(cid, complete=False)

    # -- output ------------------------------------------------------------------------------------
    def snapshot(self, now: float) -> "Snapshot":
        c = self.config
        self._flush_chunks(now)
        hb_age = now - self.heartbeat[0] if self.heartbeat else None
        msg_age = now - self.last_message_t if self.last_message_t is not None else None
        early = now - self.start < c.link_timeout_s  # a 1 Hz HEARTBEAT may not have come yet
        if hb_age is not None and hb_age <= c.link_timeout_s:
            link = "ok"
        elif msg_age is not None and msg_age <= c.link_timeout_s:
            link = "waiting" if hb_age is None and early else "no_heartbeat"
        elif self.last_message_t is None and early:
            link = "waiting"
        else:
            link = "lost"
        hb = self.heartbeat[1] if self.heartbeat else None
        return Snapshot(
            config=c,
            elapsed_s=now - self.start,
            link_state=link,
            system_id=self.system_id,
            heartbeat_age_s=hb_age,
            last_message_age_s=msg_age,
            system_status=int(hb.system_status) if hb is not None else None,
            mav_type=int(hb.type) if hb is not None else None,
            sectors=self.sectors[1] if self.sectors else None,
            sectors_age_s=now - self.sectors[0] if self.sectors else None,
            forward=self.forward[1] if self.forward else None,
            forward_age_s=now - self.forward[0] if self.forward else None,
            diagnostics=tuple((k, v, now - t) for k, (t, v) in sorted(self.diagnostics.items())),
            statustext=tuple((now - s.t, s.severity, s.text, s.complete) for s in self.texts),
            rates_hz=dict(sorted(self._rates.rates(now).items())),
            counts=dict(sorted(self.counts.items())),
            errors=dict(sorted((k, v) for k, v in self.errors.items() if v)),
            other_messages=sum(self.other_sources.values()),
            other_sources=tuple(sorted(s for s in self.other_sources if s[0] >= 0)),
            other_companions=tuple(sorted(self.other_companions)),
            rx_bytes=self.rx_bytes,
        )


# ---------------------------------------------------------------------- snapshot ---------------
def _num(x, nd: int = 3):
    """JSON-safe number: None for None / nan / inf, rounded floats."""
    if x is None:
        return None
    x = float(x)
    return round(x, nd) if math.isfinite(x) else None


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """Everything the view shows at one instant (ages in seconds at that instant)."""

    config: MonitorConfig
    elapsed_s: float
    link_state: str  # "waiting" | "ok" | "no_heartbeat" | "lost"
    system_id: int | None
    heartbeat_age_s: float | None
    last_message_age_s: float | None
    system_status: int | None
    mav_type: int | None
    sectors: DecodedSectors | None
    sectors_age_s: float | None
    forward: ForwardReading | None
    forward_age_s: float | None
    diagnostics: tuple  # (name, value, age_s)
    statustext: tuple  # (age_s, severity, text, complete), oldest first
    rates_hz: dict
    counts: dict
    errors: dict
    other_messages: int
    other_sources: tuple
    other_companions: tuple
    rx_bytes: int

    @property
    def sectors_stale(self) -> bool:
        return self.sectors is not None and (self.sectors_age_s > self.config.stale_s or self.link_state == "lost")

    @property
    def forward_stale(self) -> bool:
        return self.forward is not None and (self.forward_age_s > self.config.stale_s or self.link_state == "lost")

    @property
    def health_current(self) -> bool:
        """The HEARTBEAT status is current only while the link is up."""
        return self.system_status is not None and self.link_state == "ok"

    @property
    def heard(self) -> bool:
        """Anything from the companion within the link timeout."""
        return self.last_message_age_s is not None and self.last_message_age_s <= self.config.link_timeout_s

    def to_json(self) -> dict:
        c = self.config
        sec = None
        if self.sectors is not None:
            d = self.sectors
            r, b, i = d.nearest()
            sec = {
                "age_s": _num(self.sectors_age_s), "stale": self.sectors_stale,
                "rate_hz": _num(self.rates_hz.get("OBSTACLE_DISTANCE"), 2),
                "frame": d.frame_name, "reference": d.reference,
                "increment_deg": _num(d.increment_deg), "increment": d.increment, "increment_f": _num(d.increment_f),
                "angle_offset_deg": _num(d.angle_offset_deg),
                "min_distance_m": _num(d.min_distance_m), "max_distance_m": _num(d.max_distance_m),
                "counts": d.counts(),
                "nearest_m": _num(r), "nearest_bearing_deg": _num(b, 1), "nearest_index": i if i >= 0 else None,
                "distances_cm": [int(x) for x in d.raw_cm],
                "warnings": list(d.warnings),
            }
        fwd = None
        if self.forward is not None:
            f = self.forward
            fwd = {"state": f.state, "distance_m": _num(f.distance_m), "sigma_m": _num(f.sigma_m),
                   "covariance_cm2": f.covariance_cm2, "signal_quality": f.signal_quality,
                   "age_s": _num(self.forward_age_s), "stale": self.forward_stale}
        health = None
        if self.system_status is not None:
            health = {"status": state_name(self.system_status), "system_status": self.system_status,
                      "mav_type": self.mav_type, "current": self.health_current}
        return {
            "t_s": _num(self.elapsed_s),
            "link": {"state": self.link_state, "system_id": self.system_id, "component_id": c.component_id,
                     "heartbeat_age_s": _num(self.heartbeat_age_s), "last_message_age_s": _num(self.last_message_age_s),
                     "other_companions": list(self.other_companions)},
            "health": health,
            "sectors": sec,
            "forward": fwd,
            "diagnostics": {n: {"value": _num(v, 4), "age_s": _num(a)} for n, v, a in self.diagnostics},
            "statustext": [{"age_s": _num(a), "severity": s, "severity_name": severity_name(s), "text": t, "complete": ok}
                           for a, s, t, ok in self.statustext],
            "rates_hz": {k: _num(v, 2) for k, v in self.rates_hz.items()},
            "messages": dict(self.counts),
            "other_messages": self.other_messages,
            "rx_bytes": self.rx_bytes,
            "errors": dict(self.errors),
        }


# ---------------------------------------------------------------------- rendering --------------
GLYPH_UNKNOWN = "·"
GLYPH_CLEAR = "○"
GLYPHS_NEAR_TO_FAR = "█▇▆▅▄▃▂▁"
STYLE_NEAR, STYLE_MID, STYLE_FAR, STYLE_UNKNOWN, STYLE_STALE = "bold red", "yellow", "green", "grey50", "grey42"


def sector_cells(state: np.ndarray, range_m: np.ndarray, max_m: float, near_m: float, mid_m: float) -> list[tuple[str, str]]:
    """(glyph, style) per bin: obstacles as a bar that is taller the nearer (8 levels up to
    ``max_m``), red below ``near_m``, yellow below ``mid_m``, green beyond; clear ○ green;
    unknown · grey."""
    frac = np.clip(np.nan_to_num(range_m, nan=max_m) / max_m, 0.0, 1.0)
    level = np.minimum((frac * len(GLYPHS_NEAR_TO_FAR)).astype(int), len(GLYPHS_NEAR_TO_FAR) - 1)
    out = []
    for s, r, lv in zip(state, range_m, level):
        if s == SectorState.OBSTACLE:
            out.append((GLYPHS_NEAR_TO_FAR[lv], STYLE_NEAR if r < near_m else STYLE_MID if r < mid_m else STYLE_FAR))
        elif s == SectorState.CLEAR:
            out.append((GLYPH_CLEAR, STYLE_FAR))
        else:
            out.append((GLYPH_UNKNOWN, STYLE_UNKNOWN))
    return out


class SectorStrip:
    """The sectors as one text line from −180° through the reference (centre) to +180°, with an
    axis line under it; 72 bins of 5° when there is room, else 36 or 18 (combined conservatively).
    Indented by ``indent`` columns (to line up with the view's values) when that still fits."""

    def __init__(self, sectors: DecodedSectors, config: MonitorConfig, stale: bool, indent: int = 0):
        self.sectors = sectors
        self.config = config
        self.stale = stale
        self.indent = indent

    def __rich_measure__(self, console, options):
        from rich.measure import Measurement

        return Measurement(SECTOR_COUNT // 4, min(options.max_width, SECTOR_COUNT + self.indent))

    def lines(self, width: int = SECTOR_COUNT):
        from rich.text import Text

        bins = next((b for b in (SECTOR_COUNT, SECTOR_COUNT // 2) if width >= b), SECTOR_COUNT // 4)
        pad = " " * max(0, min(self.indent, width - bins))
        state, rng = bin_sectors(self.sectors, bins)
        order = (np.arange(bins) + bins // 2) % bins  # display column k shows bearing −180° + k·360/bins
        cells = sector_cells(state[order], rng[order], self.sectors.max_distance_m, self.config.near_m, self.config.mid_m)
        strip = Text(pad, no_wrap=True)
        for glyph, style in cells:
            strip.append(glyph, STYLE_STALE if self.stale else style)
        north = self.sectors.reference == "north"
        marks = ("S", "W", "N", "E") if north else ("B", "L", "F", "R")
        axis = [" "] * bins
        for q, mark in enumerate(marks):
            axis[q * bins // 4] = mark
        for q in range(4):  # 45° ticks between the letters
            axis[q * bins // 4 + bins // 8] = "'"
        return [strip, Text(pad + "".join(axis), style="dim", no_wrap=True)]

    def __rich_console__(self, console, options):
        yield from self.lines(options.max_width)


def _age(a: float | None) -> str:
    if a is None:
        return "never"
    return f"{a:.2f} s ago" if a < 10 else f"{a:.0f} s ago"


def _bearing(b: float) -> str:
    return f"{b:+.0f}°"


def render(snap: Snapshot, source: str = ""):
    """A rich renderable (a Panel) of the snapshot; stale data is drawn grey and labelled STALE."""
    from rich.columns import Columns
    from rich.console import Group
    from rich.panel import Panel
    from rich.table import Table
    from rich.text import Text

    c = snap.config
    label_w = 11

    def new_grid():
        g = Table.grid(padding=(0, 1))
        g.add_column(style="bold", no_wrap=True, min_width=label_w)
        g.add_column()
        return g

    parts = []
    grid = new_grid()

    # health / link
    link_style = {"ok": "green", "no_heartbeat": "yellow", "waiting": "grey50", "lost": "bold red"}[snap.link_state]
    h = Text()
    if snap.system_status is None:
        h.append("unknown", "grey50")
        h.append(" · no HEARTBEAT from the companion yet" if snap.link_state != "lost" else "")
    elif snap.health_current:
        st = state_name(snap.system_status)
        h.append(st, {"ACTIVE": "bold green", "STANDBY": "bold yellow"}.get(st, "bold red"))
        h.append(f" · heartbeat {_age(snap.heartbeat_age_s)}")
    else:
        h.append("unknown", "bold red")
        h.append(f" · last heartbeat {_age(snap.heartbeat_age_s)} said {state_name(snap.system_status)}", "grey50")
    link_text = {"ok": "link OK", "no_heartbeat": "NO HEARTBEAT", "lost": "LINK LOST",
                 "waiting": "waiting for its HEARTBEAT" if snap.heard else "waiting for the companion"}[snap.link_state]
    if snap.link_state == "lost":
        h.append(f" · LINK LOST (nothing for > {c.link_timeout_s:g} s)", "bold red")
    elif snap.link_state == "no_heartbeat":
        h.append(f" · NO HEARTBEAT for > {c.link_timeout_s:g} s (other messages arrive)", "bold yellow")
    grid.add_row("health", h)

    # sectors
    d = snap.sectors
    if d is None:
        grid.add_row("sectors", Text("no OBSTACLE_DISTANCE received", "grey50"))
    else:
        stale = snap.sectors_stale
        head = Text()
        if stale:
            head.append(f"STALE · last OBSTACLE_DISTANCE {_age(snap.sectors_age_s)}", "bold red")
        else:
            head.append(f"{_age(snap.sectors_age_s)}", "green")
            rate = snap.rates_hz.get("OBSTACLE_DISTANCE", math.nan)
            if math.isfinite(rate):
                head.append(f" · {rate:.1f} Hz")
        n = d.counts()
        head.append(f" · obstacle {n['obstacle']} · clear {n['clear']} · unknown {n['unknown']}", "grey50" if stale else "")
        grid.add_row("sectors", head)
        parts += [grid, SectorStrip(d, c, stale, indent=label_w + 1)]  # a row of its own: 72 columns fit in 80
        grid = new_grid()
        grid.add_row("", Text(f"{GLYPHS_NEAR_TO_FAR[0]} near … {GLYPHS_NEAR_TO_FAR[-1]} far  {GLYPH_CLEAR} clear  "
                              f"{GLYPH_UNKNOWN} unknown · red < {c.near_m:g} m, yellow < {c.mid_m:g} m", "dim"))
        grid.add_row("", Text(f"{SECTOR_COUNT} × {d.increment_deg:g}° (increment {d.increment}, increment_f {d.increment_f:g}) "
                              f"from {d.angle_offset_deg:g}°, frame {d.frame_name}, {d.min_distance_m:.2f}–{d.max_distance_m:.2f} m",
                              "dim"))
        for w in d.warnings:
            grid.add_row("", Text(f"! {w}", "yellow"))
        r, b, _ = d.nearest()
        near = Text()
        if not math.isfinite(r):
            near.append("none", "grey50" if stale else "green")
            near.append(" (no sector reports an obstacle)" + (" · STALE" if stale else ""), "grey50")
        elif stale:
            near.append("— STALE", "bold red")
            near.append(f" (was {r:.2f} m at {_bearing(b)} from {d.reference}, {_age(snap.sectors_age_s)})", "grey50")
        else:
            near.append(f"{r:.2f} m", STYLE_NEAR if r < c.near_m else STYLE_MID if r < c.mid_m else STYLE_FAR)
            near.append(f" at {_bearing(b)} from {d.reference}")
        grid.add_row("nearest", near)

    # forward DISTANCE_SENSOR
    f = snap.forward
    fw = Text()
    if f is None:
        fw.append("no forward DISTANCE_SENSOR received", "grey50")
    else:
        stale = snap.forward_stale
        if stale:
            fw.append("STALE ", "bold red")
        style = "grey50" if stale else ""
        if f.state == "obstacle":
            sig = f"± {f.sigma_m:.2f} m" if math.isfinite(f.sigma_m) else "± ? (σ unknown)"
            fw.append(f"{f.distance_m:.2f} m {sig}", style or "bold")
            q = {0: "unknown"}.get(f.signal_quality, str(f.signal_quality))
            fw.append(f" · quality {q}", style)
        elif f.state == "clear":
            fw.append(f"clear (beyond {f.max_distance_m:g} m)", style or "green")
        else:
            fw.append("unknown", style or "grey50")
        fw.append(f" · {_age(snap.forward_age_s)}", style)
    grid.add_row("forward", fw)

    # diagnostics
    diags = []
    for name, value, age in snap.diagnostics:
        label = DIAG_LABELS.get(name, name)
        old = age > max(3.0, c.link_timeout_s)
        if name == "MR_NEAR_M" and value < 0:
            shown = "none"
        elif math.isfinite(value) and value == int(value) and abs(value) < 1e9:
            shown = str(int(value))
        else:
            shown = f"{value:.4g}"
        diags.append(Text.assemble((f"{label} ", "grey50"), (shown, "grey50" if old else "bold"),
                                   (f" ({_age(age)})" if old else "", "grey50"), no_wrap=True))
    grid.add_row("diagnostics", Columns(diags, padding=(0, 2)) if diags else Text("none received", "grey50"))

    # STATUSTEXT
    if snap.statustext:
        st = Text()
        for k, (age, sev, text, _) in enumerate(snap.statustext):
            if k:
                st.append("\n")
            sev_style = "bold red" if sev <= mavlink.MAV_SEVERITY_ERROR else "yellow" if sev == mavlink.MAV_SEVERITY_WARNING else ""
            st.append(f"{_age(age):>11} ", "grey50")
            st.append(f"{severity_name(sev):<9} ", sev_style)
            st.append(text)
        grid.add_row("status text", st)
    else:
        grid.add_row("status text", Text("none received", "grey50"))

    # rates, traffic and errors
    rates = [Text.assemble(f"{name} ", (f"{hz:.1f} Hz" if math.isfinite(hz) else "… Hz", "bold"), no_wrap=True)
             for name, hz in snap.rates_hz.items()]
    grid.add_row("rates", Columns(rates, padding=(0, 2)) if rates else Text("nothing from the companion", "grey50"))
    if snap.other_messages or snap.other_companions:
        ot = Text(f"{snap.other_messages} message(s) from other components/systems", "grey50")
        if snap.other_sources:
            shown = ", ".join(f"{s}/{cc}" for s, cc in snap.other_sources[:6])
            ot.append(f" ({shown}{', …' if len(snap.other_sources) > 6 else ''})", "grey50")
        if snap.other_companions:
            ot.append(f" · other systems with component {c.component_id}: "
                      + ", ".join(map(str, snap.other_companions)) + " (choose one with --system)", "yellow")
        grid.add_row("other", ot)
    errs = [Text(f"{name.replace('_', ' ').replace('crc', 'CRC')} {n}", "yellow", no_wrap=True) for name, n in snap.errors.items()]
    grid.add_row("errors", Columns(errs, padding=(0, 2)) if errs else Text("none", "grey50"))

    who = f"{snap.system_id}/{c.component_id}" if snap.system_id is not None else f"?/{c.component_id}"
    title = Text.assemble((f"companion {who}", "bold"), " — ", (link_text, link_style))
    sub = f"{source} · {snap.elapsed_s:.1f} s · {snap.rx_bytes} bytes" if source else f"{snap.elapsed_s:.1f} s"
    parts.append(grid)
    return Panel(Group(*parts), title=title, title_align="left", subtitle=sub, subtitle_align="right", border_style=link_style,
                 expand=False)


def render_text(snap: Snapshot, source: str = "", width: int = 110, color: bool = False) -> str:
    """The view as text (no colour by default): for ``--once``, pipes and tests."""
    from rich.console import Console

    buf = io.StringIO()
    console = Console(file=buf, width=width, force_terminal=color, color_system="truecolor" if color else None,
                      legacy_windows=False, emoji=False, highlight=False)
    console.print(render(snap, source))
    return buf.getvalue()


# ---------------------------------------------------------------------- I/O ----------------------
#: Ground-station identity of the monitor's own HEARTBEAT (sysid 255, MAV_COMP_ID_MISSIONPLANNER).
GCS_SYSTEM_ID = 255
GCS_COMPONENT_ID = mavlink.MAV_COMP_ID_MISSIONPLANNER
_LOG_SUFFIXES = (".tlog", ".bin", ".log", ".px4log", ".mavlink", ".raw")


def open_connection(conn_str: str, baud: int = 57600):
    """A pymavlink connection for listening (robust parsing); :class:`ConfigError` when it cannot be opened.

    A file is refused: pymavlink would read it as a log (or even run an ``.elf``), not a live link.
    """
    if not isinstance(conn_str, str) or not conn_str.strip():
        raise ConfigError("CONN must be a pymavlink connection string, e.g. udpin:0.0.0.0:14550")
    low = conn_str.lower()
    if low.startswith("csv:") or (":" not in conn_str and (Path(conn_str).is_file() or low.endswith(_LOG_SUFFIXES))):
        raise ConfigError(f"{conn_str!r} is a file: monitor reads a live link (udpin:…, udpout:…, tcp:…, a serial device); "
                          "for a recorded flight use mavlogdump.py or companion replay")
    try:
        conn = mavutil.mavlink_connection(conn_str, baud=baud, source_system=GCS_SYSTEM_ID, source_component=GCS_COMPONENT_ID,
                                          autoreconnect=False, retries=0)
    except Exception as exc:  # ValueError (syntax), OSError (bind, device), serial.SerialException, ImportError
        raise ConfigError(f"cannot open {conn_str!r}: {exc}") from None
    if not hasattr(conn, "mav") or not hasattr(conn, "recv"):
        raise ConfigError(f"{conn_str!r} is not a live MAVLink link")
    conn.mav.robust_parsing = True
    return conn


class Reader:
    """Non-blocking reads from a pymavlink connection into a :class:`MonitorState`.

    Each UDP datagram is parsed on its own (MAVLink over UDP never spans datagrams): a packet cut
    short is counted as ``truncated`` and dropped instead of swallowing the next datagram.
    """

    MAX_READS = 500

    def __init__(self, conn):
        self.conn = conn
        self.datagram = isinstance(conn, mavutil.mavudp)

    def _reset(self) -> None:
        mav = self.conn.mav
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2

    def pump(self, state: MonitorState, now: float) -> int:
        """Read and fold everything available; returns the number of messages parsed."""
        n = 0
        mav = self.conn.mav
        for _ in range(self.MAX_READS):
            try:
                data = self.conn.recv(65535)
            except Exception as exc:  # a socket or device error: count it, try again next time
                state.add_error("read_errors")
                log.debug("read error: %r", exc)
                break
            if not data:
                break
            data = bytes(data)
            state.add_bytes(len(data))
            try:
                msgs = mav.parse_buffer(data) or []
            except Exception as exc:  # robust parsing returns BAD_DATA; anything else is a parser bug
                state.add_error("parser_errors")
                log.debug("parser error: %r", exc)
                self._reset()
                continue
            if self.datagram and mav.buf_len() > 0:
                state.add_error("truncated")
                self._reset()
            for m in msgs:
                n += 1
                try:
                    state.add(m, now)
                except Exception as exc:  # pragma: no cover - the fold validates; defensive
                    state.add_error("internal_errors")
                    log.warning("could not fold %s: %r", getattr(m, "get_type", lambda: "?")(), exc)
        return n

    def send_heartbeat(self) -> None:
        try:
            self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE)
        except Exception as exc:  # nowhere to send yet (udpin before the first datagram) or a broken link
            log.debug("GCS heartbeat not sent: %r", exc)

    def wait(self, timeout: float) -> None:
        try:
            self.conn.select(max(0.0, timeout))
        except Exception:
            time.sleep(max(0.0, min(timeout, 0.05)))

    def close(self) -> None:
        try:
            self.conn.close()
        except Exception:
            pass


def run_monitor(conn_str: str, config: MonitorConfig = MonitorConfig(), *, once: bool = False, duration: float | None = None,
                interval: float = 1.0, json_lines: bool = False, passive: bool = False, live: bool | None = None,
                out=None, clock: Callable[[], float] = time.monotonic, stop: threading.Event | None = None,
                refresh_hz: float = 5.0) -> int:
    """Listen on ``conn_str`` and show the companion (see module docstring). Returns the exit code:
    0, or with ``once`` 1 when nothing was heard from the companion within the link timeout."""
    out = out if out is not None else sys.stdout
    if live is None:
        live = (not once) and (not json_lines) and out.isatty()
    if once and duration is None:
        duration = 3.0
    conn = open_connection(conn_str)
    reader = Reader(conn)
    stop = stop or threading.Event()
    t0 = clock()
    state = MonitorState(config, t0)
    log.info("listening on %s for component %d (%s)", conn_str, config.component_id,
             f"system {config.system_id}" if config.system_id else "any system")

    def emit(now: float) -> Snapshot:
        snap = state.snapshot(now)
        if json_lines:
            out.write(json.dumps(snap.to_json(), separators=(",", ":")) + "\n")
        else:  # COLUMNS when set, else 110 (stdout is not a terminal here)
            out.write(render_text(snap, conn_str, width=max(40, shutil.get_terminal_size((110, 24)).columns)))
        out.flush()
        return snap

    live_view = None
    next_hb = t0
    next_emit = t0 + (duration if once else interval)
    try:
        if live:
            from rich.console import Console
            from rich.live import Live

            console = Console(file=out)
            live_view = Live(render(state.snapshot(t0), conn_str), console=console, refresh_per_second=refresh_hz,
                             auto_refresh=False, transient=False)
            live_view.start()
            next_emit = t0
        while not stop.is_set():
            now = clock()
            reader.pump(state, now)
            if not passive and now >= next_hb:
                reader.send_heartbeat()
                next_hb = max(next_hb + 1.0, now + 0.5)
            end = duration is not None and now - t0 >= duration
            if live_view is not None:
                if now >= next_emit or end:
                    live_view.update(render(state.snapshot(now), conn_str), refresh=True)
                    next_emit = now + 1.0 / refresh_hz
            elif once:
                if end:
                    snap = emit(now)
                    return 0 if snap.heard else 1
            elif now >= next_emit:
                emit(now)
                next_emit = max(next_emit + interval, now + interval * 0.5)
            if end:
                break
            reader.wait(min(0.05, max(0.0, next_emit - clock())))
        return 0
    except KeyboardInterrupt:  # Ctrl-C: a normal way to stop
        return 0
    finally:
        if live_view is not None:
            live_view.stop()
        reader.close()


def cmd_monitor(args) -> int:
    """``companion monitor``: validate the arguments (:class:`ConfigError` → exit 2) and run."""
    for name in ("duration", "interval"):
        v = getattr(args, name)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ConfigError(f"--{name} must be a positive number of seconds, got {v}")
    if args.interval < 0.05:
        raise ConfigError(f"--interval must be >= 0.05 s, got {args.interval}")
    cfg = MonitorConfig(component_id=args.component, system_id=args.system, near_m=args.near, mid_m=args.mid)
    stop = threading.Event()
    old = None
    if threading.current_thread() is threading.main_thread():  # SIGTERM stops like Ctrl-C (KeyboardInterrupt)
        old = signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    try:
        return run_monitor(args.conn, cfg, once=args.once, duration=args.duration, interval=args.interval,
                           json_lines=args.json, passive=args.passive, stop=stop)
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)
