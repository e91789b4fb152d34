"""Hostile traffic and telemetry blackouts on the simulated autopilot's MAVLink link.

``flightsim sitl`` plays a well-behaved autopilot.  A real link is not that clean: radios and
routers deliver noise, cut and glued packets, other systems share the link, a faulty or spoofed
sender writes garbage into valid frames, and the telemetry itself drops out.  Two optional parts,
both off by default and both seeded (the same seed gives the same packets at the same simulated
instants; the flight — physics, telemetry model, its random draws — is that of the same scenario
seed without them):

:class:`HostileInjector`
    datagrams sent to the companion *interleaved* with the real telemetry, Poisson arrivals at
    ``rate_hz`` per simulated second, each of one kind drawn uniformly from ``kinds``:

    ``random_bytes``   1–300 random bytes (half of them starting with a MAVLink 2 or 1 start byte);
    ``bad_crc``        a valid ATTITUDE / LOCAL_POSITION_NED / HEARTBEAT from the vehicle's ids
                       with its checksum altered;
    ``truncated``      such a packet cut short (1 … length − 1 bytes);
    ``unknown_id``     a MAVLink 2 frame whose message id is not in the ardupilotmega dialect;
    ``nan_payload``    a valid packet (correct checksum) from the vehicle's own system and
                       component: ATTITUDE or LOCAL_POSITION_NED stamped with the vehicle's current
                       ``time_boot_ms``, with NaN, ±inf or ±3e38 in its float fields (at least one
                       non-finite) — what a faulty autopilot or a spoofer could send;
    ``glued``          2–5 packets in one datagram: parts drawn from the other kinds selected among
                       ``bad_crc``, ``truncated`` (only ever last), ``unknown_id``, ``nan_payload``
                       and the two spoofs (all of them when ``glued`` is the only kind), and a valid
                       ground-station HEARTBEAT (system 255, component 190);
    ``spoof_attitude_own``      a valid ATTITUDE from the vehicle's own system and component 1
                       with a random ``time_boot_ms`` (uniform over 0 … 2³²−1) and random finite angles;
    ``spoof_attitude_foreign``  the same from another system (component 1) or another component
                       of the vehicle's system.

    Hostile packets are packed by a packer of their own (its own sequence numbers: the vehicle's
    messages keep theirs) and are not written to ``telemetry.tlog``; :attr:`HostileInjector.counts` counts
    every datagram sent by kind and :attr:`HostileInjector.part_counts` the parts of the glued ones.

:class:`Blackout`
    a window ``[start_s, start_s + duration_s)`` of simulation time in which the vehicle's
    telemetry streams (ATTITUDE, LOCAL_POSITION_NED, GLOBAL_POSITION_INT) are not sent; with
    ``heartbeat`` the whole downlink is silent: HEARTBEAT and the answers to the companion's
    requests (COMMAND_ACK, TIMESYNC) too.  The SYSTEM_TIME sent just before each camera frame —
    the lockstep clock tick of the frame transport — continues, as do the frames.  The telemetry
    model keeps running (the messages are built and dropped), so the flight and its random draws are
    those of the same run without the blackout.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import struct

import numpy as np

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.config import require, require_finite

KINDS = ("random_bytes", "bad_crc", "truncated", "unknown_id", "nan_payload", "glued",
         "spoof_attitude_own", "spoof_attitude_foreign")
#: kinds a glued datagram is made of (``gcs_heartbeat``: a valid HEARTBEAT of a ground station)
GLUE_PARTS = ("bad_crc", "unknown_id", "nan_payload", "spoof_attitude_own", "spoof_attitude_foreign", "gcs_heartbeat")
#: the vehicle's messages a blackout stops (plus HEARTBEAT, COMMAND_ACK and TIMESYNC with ``heartbeat``)
BLACKOUT_TELEMETRY = frozenset({"ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"})
BLACKOUT_LINK = frozenset({"HEARTBEAT", "COMMAND_ACK", "TIMESYNC"})
_NONFINITE = (math.nan, math.inf, -math.inf)


@dataclasses.dataclass(frozen=True)
class Blackout:
    """The vehicle's telemetry stops for ``duration_s`` from ``start_s`` (simulation time)."""

    start_s: float
    duration_s: float
    heartbeat: bool = False  # the whole downlink: HEARTBEAT and the answers to requests too

    def __post_init__(self) -> None:
        require_finite("blackout start_s", self.start_s, nonnegative=True)
        require_finite("blackout duration_s", self.duration_s, positive=True)

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    def silences(self, name: str, t: float) -> bool:
        """Whether the vehicle's message ``name`` is not sent at simulation time ``t``."""
        if not (self.start_s <= t < self.end_s):
            return False
        return name in BLACKOUT_TELEMETRY or (self.heartbeat and name in BLACKOUT_LINK)

    @classmethod
    def parse(cls, text: str) -> "Blackout":
        """``START:DURATION`` or ``START:DURATION:hb`` (seconds; ``hb`` = the HEARTBEAT too)."""
        parts = [p.strip() for p in str(text).split(":")]
        if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2].lower() not in ("hb", "heartbeat")):
            raise ValueError(f"blackout {text!r}: expected START:DURATION or START:DURATION:hb (seconds)")
        try:
            start, dur = float(parts[0]), float(parts[1])
        except ValueError:
            raise ValueError(f"blackout {text!r}: START and DURATION must be numbers (seconds)") from None
        return cls(start, dur, heartbeat=len(parts) == 3)


@dataclasses.dataclass(frozen=True)
class HostileConfig:
    """Hostile traffic and blackouts of a SITL run (all off by default)."""

    rate_hz: float = 0.0  # hostile datagrams per simulated second (Poisson arrivals); 0 = none
    seed: int = 0  # seeds the arrivals and the contents (independent of the scenario's seed)
    kinds: tuple[str, ...] = KINDS  # kinds drawn from, uniformly
    blackouts: tuple[Blackout, ...] = ()  # telemetry blackout windows

    def __post_init__(self) -> None:
        require_finite("hostile rate_hz", self.rate_hz, nonnegative=True)
        require(self.rate_hz <= 10_000, "hostile rate_hz must be <= 10000")
        require(isinstance(self.seed, int) and not isinstance(self.seed, bool) and self.seed >= 0,
                f"hostile seed must be an integer >= 0, got {self.seed!r}")
        kinds = tuple(self.kinds)
        require(bool(kinds), "hostile kinds must not be empty")
        unknown = sorted(set(kinds) - set(KINDS))
        require(not unknown, f"unknown hostile kind(s) {', '.join(unknown)}; known: {', '.join(KINDS)}")
        object.__setattr__(self, "kinds", kinds)
        b = tuple(self.blackouts)
        require(all(isinstance(x, Blackout) for x in b), "blackouts must be Blackout windows")
        object.__setattr__(self, "blackouts", tuple(sorted(b, key=lambda x: x.start_s)))

    @property
    def active(self) -> bool:
        return self.rate_hz > 0 or bool(self.blackouts)

    def silenced(self, name: str, t: float) -> Blackout | None:
        """The blackout that stops the vehicle's message ``name`` at ``t`` (None: it is sent)."""
        for b in self.blackouts:
            if b.silences(name, t):
                return b
        return None

    def to_json(self) -> dict:
        return {"rate_hz": self.rate_hz, "seed": self.seed, "kinds": list(self.kinds),
                "blackouts": [dataclasses.asdict(b) | {"end_s": b.end_s} for b in self.blackouts]}


class HostileInjector:
    """Seeded hostile datagrams at Poisson instants (module docstring).

    ``system_id``: the vehicle's; ``due(t, time_boot_ms)`` returns the ``(kind, bytes)`` whose
    arrival falls at or before simulation time ``t``; the caller sends them and calls
    :meth:`record` for each one sent (or :meth:`record_unsent`).
    """

    def __init__(self, config: HostileConfig, system_id: int, component_id: int = 1):
        self.config = config
        self.system_id = int(system_id)
        self.component_id = int(component_id)
        self.rng = np.random.default_rng(config.seed)
        self._mav = mavlink.MAVLink(None, srcSystem=self.system_id, srcComponent=self.component_id)
        self._next = self._draw_gap() if config.rate_hz > 0 else math.inf
        self.counts: collections.Counter[str] = collections.Counter()  # datagrams sent, by kind
        self.part_counts: collections.Counter[str] = collections.Counter()  # parts of the glued datagrams sent
        self.unsent: collections.Counter[str] = collections.Counter()  # generated before the companion was heard
        self.bytes_sent = 0
        sel = set(config.kinds) - {"glued"}
        self._glue_parts = tuple(k for k in GLUE_PARTS if k in sel or k == "gcs_heartbeat" or not sel)
        self._glue_truncated = "truncated" in sel or not sel

    # -- schedule ---------------------------------------------------------------------------------
    def _draw_gap(self) -> float:
        return float(self.rng.exponential(1.0 / self.config.rate_hz))

    def due(self, t: float, time_boot_ms: int) -> list[tuple[str, bytes, list[str]]]:
        """Datagrams due at or before ``t``: ``(kind, bytes, parts)`` (parts: the glued ones' kinds)."""
        out = []
        while self._next <= t + 1e-9:
            kind = self.config.kinds[int(self.rng.integers(len(self.config.kinds)))]
            parts: list[str] = []
            out.append((kind, self.make(kind, time_boot_ms, parts), parts))
            self._next += self._draw_gap()
        return out

    def record(self, kind: str, buf: bytes, parts: list[str]) -> None:
        self.counts[kind] += 1
        self.bytes_sent += len(buf)
        for p in parts:
            self.part_counts[p] += 1

    def record_unsent(self, kind: str) -> None:
        self.unsent[kind] += 1

    @property
    def datagrams(self) -> int:
        return sum(self.counts.values())

    @property
    def packets(self) -> int:
        """Hostile packets sent: every datagram, a glued one counting each of its parts."""
        return sum(v for k, v in self.counts.items() if k != "glued") + sum(self.part_counts.values())

    def summary(self) -> dict:
        return {**self.config.to_json(), "datagrams": self.datagrams, "packets": self.packets,
                "bytes": self.bytes_sent, "by_kind": dict(sorted(self.counts.items())),
                "glued_parts": dict(sorted(self.part_counts.items())),
                "unsent_before_peer": dict(sorted(self.unsent.items()))}

    # -- packets ------------------------------------------------------------------------------------
    def _pack(self, msg, sysid: int | None = None, compid: int | None = None) -> bytes:
        m = self._mav
        m.srcSystem = self.system_id if sysid is None else sysid
        m.srcComponent = self.component_id if compid is None else compid
        buf = bytes(msg.pack(m))
        m.seq = (m.seq + 1) % 256
        return buf

    def _f(self, lo: float, hi: float) -> float:
        return float(self.rng.uniform(lo, hi))

    def _plausible(self, time_boot_ms: int) -> bytes:
        """A valid packet from the vehicle's ids (the raw material of ``bad_crc`` and ``truncated``)."""
        which = int(self.rng.integers(3))
        tb = int(time_boot_ms) & 0xFFFFFFFF
        if which == 0:
            msg = mavlink.MAVLink_attitude_message(tb, self._f(-0.3, 0.3), self._f(-0.3, 0.3), self._f(-math.pi, math.pi),
                                                   self._f(-1, 1), self._f(-1, 1), self._f(-1, 1))
        elif which == 1:
            msg = mavlink.MAVLink_local_position_ned_message(tb, self._f(-50, 50), self._f(-50, 50), self._f(-20, 0),
                                                             self._f(-5, 5), self._f(-5, 5), self._f(-2, 2))
        else:
            msg = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                    0, 0, mavlink.MAV_STATE_ACTIVE, 3)
        return self._pack(msg)

    def _bad_float(self) -> float:
        r = self.rng.random()
        if r < 0.5:
            return _NONFINITE[int(self.rng.integers(3))]
        if r < 0.65:
            return float(self.rng.choice([3e38, -3e38]))
        return self._f(-1.0, 1.0)

    def _nan_payload(self, time_boot_ms: int) -> bytes:
        n = 6
        vals = [self._bad_float() for _ in range(n)]
        k = int(self.rng.integers(n))
        vals[k] = _NONFINITE[int(self.rng.integers(3))]  # at least one non-finite value
        tb = int(time_boot_ms) & 0xFFFFFFFF
        if self.rng.random() < 0.5:
            msg = mavlink.MAVLink_attitude_message(tb, *vals)
        else:
            msg = mavlink.MAVLink_local_position_ned_message(tb, *vals)
        return self._pack(msg)

    def _spoof_attitude(self, own: bool) -> bytes:
        msg = mavlink.MAVLink_attitude_message(int(self.rng.integers(0, 2**32)), self._f(-math.pi, math.pi),
                                               self._f(-math.pi / 2, math.pi / 2), self._f(-math.pi, math.pi),
                                               self._f(-5, 5), self._f(-5, 5), self._f(-5, 5))
        if own:
            return self._pack(msg)
        if self.rng.random() < 0.5:  # another vehicle
            sysid = int(self.rng.integers(1, 255))
            if sysid == self.system_id:
                sysid = sysid % 254 + 1
            return self._pack(msg, sysid, self.component_id)
        compid = int(self.rng.integers(1, 256))  # another component of this vehicle
        if compid == self.component_id:
            compid = compid % 255 + 1
        return self._pack(msg, self.system_id, compid)

    def _unknown_id(self) -> bytes:
        while True:
            msgid = int(self.rng.integers(0, 1 << 24))
            if msgid not in mavlink.mavlink_map:
                break
        n = int(self.rng.integers(1, 256))
        m = self._mav
        hdr = struct.pack("<BBBBBBBHB", mavlink.PROTOCOL_MARKER_V2, n, 0, 0, m.seq, self.system_id, self.component_id,
                          msgid & 0xFFFF, msgid >> 16)
        m.seq = (m.seq + 1) % 256
        return hdr + self.rng.bytes(n) + self.rng.bytes(2)

    def _bad_crc(self, time_boot_ms: int) -> bytes:
        b = bytearray(self._plausible(time_boot_ms))
        b[-2:] = (struct.unpack("<H", bytes(b[-2:]))[0] ^ int(self.rng.integers(1, 1 << 16))).to_bytes(2, "little")
        return bytes(b)

    def _truncated(self, time_boot_ms: int) -> bytes:
        b = self._plausible(time_boot_ms)
        return b[: int(self.rng.integers(1, len(b)))]

    def _random_bytes(self) -> bytes:
        n = int(self.rng.integers(1, 301))
        b = bytearray(self.rng.bytes(n))
        r = self.rng.random()
        if r < 0.35:
            b[0] = mavlink.PROTOCOL_MARKER_V2
        elif r < 0.5:
            b[0] = mavlink.PROTOCOL_MARKER_V1
        return bytes(b)

    def _gcs_heartbeat(self) -> bytes:
        return self._pack(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                                                            mavlink.MAV_STATE_ACTIVE, 3), 255, 190)

    def make(self, kind: str, time_boot_ms: int, parts: list[str] | None = None) -> bytes:
        """One datagram of ``kind``; a glued one appends its parts' kinds to ``parts``."""
        if kind == "random_bytes":
            return self._random_bytes()
        if kind == "bad_crc":
            return self._bad_crc(time_boot_ms)
        if kind == "truncated":
            return self._truncated(time_boot_ms)
        if kind == "unknown_id":
            return self._unknown_id()
        if kind == "nan_payload":
            return self._nan_payload(time_boot_ms)
        if kind == "spoof_attitude_own":
            return self._spoof_attitude(True)
        if kind == "spoof_attitude_foreign":
            return self._spoof_attitude(False)
        if kind == "gcs_heartbeat":
            return self._gcs_heartbeat()
        if kind == "glued":
            n = int(self.rng.integers(2, 6))
            gp = self._glue_parts
            chosen = [gp[int(self.rng.integers(len(gp)))] for _ in range(n)]
            if self._glue_truncated and self.rng.random() < 0.25:
                chosen[-1] = "truncated"  # a cut packet can only end a datagram
            bufs = [self.make(k, time_boot_ms) for k in chosen]
            if parts is not None:
                parts.extend(chosen)
            return b"".join(bufs)
        raise ValueError(f"unknown hostile kind {kind!r}")


__all__ = ["HostileConfig", "HostileInjector", "Blackout", "KINDS", "GLUE_PARTS", "BLACKOUT_TELEMETRY", "BLACKOUT_LINK"]
