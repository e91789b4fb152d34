"""The monitor's view model: :class:`MonitorState` and its immutable :class:`Snapshot` (pure; the caller's clock).

:class:`MonitorState` folds decoded pymavlink messages from the companion (component 196 by
default, one system: the first heard or ``system_id``) into the latest sectors, the forward
DISTANCE_SENSOR, the companion's HEARTBEAT, NAMED_VALUE_FLOAT / _INT diagnostics, the last
STATUSTEXTs (chunked texts reassembled), message rates and counts, and the errors met on the wire
(bad CRC, bad prefix, unknown ids, truncated datagrams).  :meth:`MonitorState.snapshot` turns it
into a :class:`Snapshot` with ages, stale flags (sectors / forward range older than ``stale_s`` =
0.5 s, where both autopilots drop them) and the link state ("lost" after ``link_timeout_s`` = 3 s
without a HEARTBEAT); :meth:`Snapshot.to_json` gives one JSON-ready dict.  What the messages mean
is decoded by :mod:`.decode`; :mod:`.view` draws snapshots.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
from typing import Any

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.config import require, require_finite
from companion.monitor.decode import (
    DecodedSectors,
    DecodeError,
    ForwardReading,
    decode_distance_sensor,
    decode_obstacle_distance,
    severity_name,
    state_name,
)

log = logging.getLogger(__name__)

STATUSTEXT_LEN = 50
#: A chunked STATUSTEXT still missing its last chunk after this long is shown as it is (marked incomplete).
CHUNK_TIMEOUT_S = 2.0
#: At most this many NAMED_VALUE names / foreign sources are remembered (a flood cannot grow memory).
MAX_NAMES = 32
MAX_SOURCES = 64


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


# ---------------------------------------------------------------------- wire text ------------
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
