"""The companion's MAVLink connection to the autopilot (or to a ground station) — docs/derivations/link.md.

:class:`MavLink` is a thin, single-owner I/O shell around ``mavutil.mavlink_connection``
(serial device with baud, ``udpin:``, ``udpout:``, ``tcp:``) that delegates every decision to pure
pieces: :class:`~companion.telemetry.TelemetryBuffer` (telemetry history),
:class:`~companion.mavlink.timesync.TimesyncEstimator` (clock mapping), :class:`StreamRequester`
(which telemetry to ask for, how, and whether it arrives) and :class:`RateMeter`.

What it does (docs/derivations/link.md; each item fixes a flaw of the wiki depth-camera script):

* MAVLink 2, ardupilotmega; own component 196 (MAV_COMP_ID_OBSTACLE_AVOIDANCE) with the
  vehicle's system id, learnt from the first HEARTBEAT of the autopilot component (1) whose type
  is a vehicle (ground stations, gimbals, other companions and MAV_AUTOPILOT_INVALID are ignored),
  or fixed by ``autopilot_system_id``; then locked: only that (system, component) feeds the
  telemetry, the clock, TIMESYNC and the stream state; everything else is only counted, per source
  in a bounded table (``max_sources``, :class:`~companion.mavlink.guard.SourceTable`);
* HEARTBEAT at 1 Hz: MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, ``system_status``
  ACTIVE only after :meth:`MavLink.set_producing` (True) — the owner decides, the link never
  claims health on its own;
* asks for ATTITUDE, LOCAL_POSITION_NED and GLOBAL_POSITION_INT with MAV_CMD_SET_MESSAGE_INTERVAL
  (COMMAND_LONG 511, one command in flight at a time since COMMAND_ACK carries only the command
  id), retries, falls back to REQUEST_DATA_STREAM when refused, unanswered, or accepted but the
  measured rate stays below ``min_rate_fraction`` of the request; re-requests a stream that stops
  and everything after the link returns or the autopilot reboots — all of it within a request
  budget (``stream_request_burst`` at once, then one per ``stream_request_interval_s``);
* every ``time_boot_ms`` of the autopilot passes :class:`~companion.mavlink.guard.BootClockGuard`:
  a stamp off the autopilot's clock (spoofed, or a noisy radio's CRC collision) is rejected and
  counted (``rx_clock_<reason>``); a reboot (telemetry cleared, TIMESYNC and stream requests
  restarted) is declared only on consistent evidence from several stamps and the heartbeat, at
  most once per ``reboot_min_interval_s``;
* TIMESYNC: sends requests, matches the replies, answers the autopilot's requests (at most
  ``timesync_answer_max_hz``);
* :meth:`MavLink.poll` is non-blocking, parses everything available, and never raises on what
  comes off the wire: random bytes, bad CRC, truncated packets (on UDP each datagram is parsed
  on its own), unknown ids, foreign systems, bad signatures, non-finite payloads — each is
  counted in :attr:`MavLink.counters` and logged (rate limited);
* optional MAVLink 2 signing from a key file (:mod:`companion.mavlink.signing`): everything sent
  is signed; wrongly signed and replayed packets are refused, unsigned ones too with
  ``require_signing`` (counted ``rx_signing_rejected``, the reasons under ``signing.*``);
* link loss = no vehicle HEARTBEAT for ``link_timeout_s``: reported through
  :meth:`MavLink.drain_events` (for STATUSTEXT), serial and TCP connections are reopened every
  ``reconnect_interval_s`` until the vehicle is heard again;
* bounded memory: the event queue (``max_events``), rate meters, per-source table, clock
  candidates, signing streams and — on ``udpin`` — the addresses we send to (``max_udp_peers``,
  only senders of valid MAVLink from the vehicle; pymavlink would add every sender) all have caps.

Threading: one internal lock serializes :meth:`poll`, :meth:`send` and the status accessors, so
a pipeline thread may send while another polls (the wiki script shared state unlocked).
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import errno
import logging
import math
import threading
import time
from typing import Any, Callable

from companion.mavlink.dialect import mavlink, mavutil  # first: MAVLink 2 + ardupilotmega
from companion.config import require, require_finite
from companion.errors import ConfigError
from companion.mavlink import messages as msgs
from companion.mavlink.guard import BootClockGuard, RequestBudget, SourceTable
from companion.mavlink.signing import SigningPolicy, load_signing_key
from companion.mavlink.timesync import TimesyncConfig, TimesyncEstimator, handle_timesync, timesync_request
from companion.telemetry import AddResult, TelemetryBuffer

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------- configuration ----------
@dataclasses.dataclass(frozen=True)
class LinkConfig:
    """The ``[link]`` table (TIMESYNC settings in ``[link.timesync]``)."""

    baud: int = 921600  # serial baud rate (ignored by udp/tcp connection strings)
    system_id: int = 0  # own system id; 0 = use the vehicle's, learnt from its HEARTBEAT
    provisional_system_id: int = 1  # system id of our HEARTBEAT until the vehicle's is known (udpout must talk first)
    component_id: int = 196  # own component id (MAV_COMP_ID_OBSTACLE_AVOIDANCE)
    autopilot_component_id: int = 1  # component whose HEARTBEAT identifies the vehicle (MAV_COMP_ID_AUTOPILOT1)
    heartbeat_hz: float = 1.0  # own HEARTBEAT rate
    attitude_hz: float = 50.0  # ATTITUDE rate requested
    local_position_hz: float = 20.0  # LOCAL_POSITION_NED rate requested
    global_position_hz: float = 5.0  # GLOBAL_POSITION_INT rate requested
    command_timeout_s: float = 1.0  # wait this long for the COMMAND_ACK of SET_MESSAGE_INTERVAL
    command_retries: int = 3  # SET_MESSAGE_INTERVAL attempts per stream before falling back to REQUEST_DATA_STREAM
    rate_check_s: float = 2.5  # after an accepted request, the stream must reach its rate within this long
    rate_window_s: float = 2.0  # arrival rates are measured over this window
    min_rate_fraction: float = 0.5  # a stream below this fraction of its requested rate counts as not arriving
    fallback_repeat_s: float = 5.0  # REQUEST_DATA_STREAM is repeated this often while a fallback stream is missing
    link_timeout_s: float = 3.0  # no vehicle HEARTBEAT for this long = link lost
    reconnect_interval_s: float = 2.0  # serial / tcp reopen attempts while the link is lost or broken
    autopilot_system_id: int = 0  # system id of the autopilot to follow; 0 = the first vehicle HEARTBEAT's (then locked until restart)
    signing_key_file: str = ""  # MAVLink 2 signing key file; "" = no signing (32 raw bytes, 64 hex digits, or a passphrase hashed with SHA-256 like MAVProxy)
    require_signing: bool = False  # with a key: true = reject every unsigned packet; false = accept unsigned ones too (counted; wrongly signed are always rejected)
    signing_link_id: int = 1  # link id written into our signatures (the ground-station output uses the next one)
    max_signing_streams: int = 64  # signing timestamps remembered per (link id, system, component), oldest forgotten first
    max_messages_per_poll: int = 2000  # bound on messages handled by one poll()
    clock_jitter_s: float = 0.5  # time_boot_ms may go back, or run ahead of our clock, by this much and still be the autopilot's clock, s
    clock_lock_messages: int = 3  # agreeing time_boot_ms stamps needed to lock onto the autopilot's clock at start
    reboot_confirm_messages: int = 10  # stamps on a new clock needed before a reboot is declared ...
    reboot_confirm_s: float = 0.5  # ... spanning this long, with the old clock silent this long, s
    reboot_heartbeat_gap_s: float = 1.5  # a HEARTBEAT silence this long that ended after the old clock stopped confirms a reboot (else two message types must agree), s
    reboot_min_interval_s: float = 5.0  # at most one declared reboot per this long, s
    max_clock_candidates: int = 4  # time_boot_ms clocks other than the autopilot's tracked at once (for reboot detection)
    stream_request_interval_s: float = 2.0  # SET_MESSAGE_INTERVAL / REQUEST_DATA_STREAM: at most one per this long on average ...
    stream_request_burst: int = 5  # ... after a burst of at most this many (one per stream and data stream at start-up)
    timesync_answer_max_hz: float = 20.0  # answers to the autopilot's TIMESYNC requests at most this often
    max_sources: int = 32  # (system, component) sources counted in the per-source table; least recently heard evicted first
    max_udp_peers: int = 4  # udpin: addresses we send to (those that sent valid MAVLink from the vehicle), least recently heard evicted first
    max_events: int = 64  # state changes (for STATUSTEXT) held between two drains; older ones are dropped and counted
    timesync: TimesyncConfig = dataclasses.field(default_factory=TimesyncConfig)  # [link.timesync]

    def __post_init__(self) -> None:
        def _int(name: str, lo: int, hi: int) -> None:
            v = getattr(self, name)
            require(isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi, f"{name} must be an integer in [{lo}, {hi}], got {v!r}")

        _int("baud", 1, 100_000_000)
        _int("system_id", 0, 255)
        _int("provisional_system_id", 1, 255)
        _int("component_id", 1, 255)
        _int("autopilot_component_id", 1, 255)
        _int("command_retries", 1, 100)
        _int("autopilot_system_id", 0, 255)
        _int("signing_link_id", 0, 254)
        _int("max_signing_streams", 1, 65536)
        _int("max_messages_per_poll", 1, 1_000_000)
        _int("clock_lock_messages", 1, 1000)
        _int("reboot_confirm_messages", 2, 10000)
        _int("max_clock_candidates", 1, 64)
        _int("stream_request_burst", 1, 100)
        _int("max_sources", 2, 65536)
        _int("max_udp_peers", 1, 256)
        _int("max_events", 1, 100_000)
        for name in ("heartbeat_hz", "attitude_hz", "local_position_hz", "global_position_hz", "command_timeout_s",
                     "rate_check_s", "rate_window_s", "fallback_repeat_s", "link_timeout_s", "reconnect_interval_s",
                     "clock_jitter_s", "reboot_confirm_s", "reboot_heartbeat_gap_s", "reboot_min_interval_s",
                     "stream_request_interval_s", "timesync_answer_max_hz"):
            require_finite(name, getattr(self, name), positive=True)
        require_finite("min_rate_fraction", self.min_rate_fraction, positive=True)
        require(self.min_rate_fraction <= 1.0, "min_rate_fraction must be <= 1")
        require(self.clock_jitter_s <= 10.0, f"clock_jitter_s must be <= 10 s, got {self.clock_jitter_s}")
        require(self.reboot_min_interval_s >= self.reboot_confirm_s,
                "reboot_min_interval_s must be >= reboot_confirm_s")
        require(isinstance(self.signing_key_file, str), "signing_key_file must be a string")
        require(isinstance(self.require_signing, bool), "require_signing must be true or false")
        require(not self.require_signing or bool(self.signing_key_file.strip()),
                "require_signing = true needs signing_key_file (a 32-byte key: raw, or 64 hex digits)")
        require(isinstance(self.timesync, TimesyncConfig), "timesync must be a [link.timesync] table")


# ---------------------------------------------------------------------- streams (pure) ---------
@dataclasses.dataclass(frozen=True)
class StreamSpec:
    name: str  # MAVLink message name, e.g. "ATTITUDE"
    msg_id: int
    rate_hz: float
    data_stream_id: int  # MAV_DATA_STREAM carrying it for REQUEST_DATA_STREAM


class StreamState(str, enum.Enum):
    IDLE = "idle"  # to be requested
    WAIT_ACK = "wait_ack"  # SET_MESSAGE_INTERVAL sent
    WAIT_RATE = "wait_rate"  # accepted; measuring the rate
    OK = "ok"  # arriving at the requested rate
    FALLBACK = "fallback"  # asked with REQUEST_DATA_STREAM


class RateMeter:
    """Arrival rates per message name over a sliding window (pure; caller's clock).

    Bounded: at most ``max_names`` names (others are not measured) and ``max_per_name`` arrivals
    per name in the window (rates above ``max_per_name / window_s`` read as that)."""

    def __init__(self, window_s: float = 2.0, max_per_name: int = 4096, max_names: int = 16):
        self.window_s = window_s
        self.max_per_name = max_per_name
        self.max_names = max_names
        self._t: dict[str, collections.deque[float]] = {}

    def tick(self, name: str, now: float) -> None:
        q = self._t.get(name)
        if q is None:
            if len(self._t) >= self.max_names:
                return
            q = self._t[name] = collections.deque(maxlen=self.max_per_name)
        q.append(now)
        self._trim(q, now)

    def _trim(self, q: collections.deque, now: float) -> None:
        while q and (now - q[0] >= self.window_s or q[0] > now):
            q.popleft()

    def rate(self, name: str, now: float) -> float:
        q = self._t.get(name)
        if not q:
            return 0.0
        self._trim(q, now)
        return len(q) / self.window_s

    def rates(self, now: float) -> dict[str, float]:
        return {k: self.rate(k, now) for k in list(self._t)}

    def clear(self) -> None:
        self._t.clear()


@dataclasses.dataclass
class _Stream:
    spec: StreamSpec
    state: StreamState = StreamState.IDLE
    attempts: int = 0
    sent_at: float = -math.inf
    acked_at: float = -math.inf
    fallback_at: float = -math.inf
    confirmation: int = 0


class StreamRequester:
    """Decides the SET_MESSAGE_INTERVAL / REQUEST_DATA_STREAM traffic (pure; docs/derivations/link.md).

    ``step(now)`` returns actions ``("interval", spec, confirmation)`` or ``("data_stream",
    stream_id, rate_hz)``; ``on_ack(result, now)`` feeds the COMMAND_ACK of the one command in
    flight.  ``events`` collects (severity, text) for STATUSTEXT.

    Every action spends a token of a :class:`~companion.mavlink.guard.RequestBudget`
    (``stream_request_burst`` at once, then one per ``stream_request_interval_s``): whatever
    restarts the requests (reboots, link losses, dropouts) the autopilot never gets more than that.
    An action without a token waits (``rate_limited`` counts the steps that held one back); a
    waiting REQUEST_DATA_STREAM is kept once per data stream.
    """

    def __init__(self, specs: list[StreamSpec], config: LinkConfig, meter: RateMeter):
        self.config = config
        self.meter = meter
        self._streams = {s.name: _Stream(s) for s in specs}
        self._outstanding: str | None = None
        self.counters: collections.Counter[str] = collections.Counter()
        self.events: collections.deque[tuple[int, str]] = collections.deque(maxlen=32)
        self._pending_actions: list = []  # REQUEST_DATA_STREAMs decided but not yet sent (at most one per data stream)
        self.budget = RequestBudget(config.stream_request_interval_s, config.stream_request_burst)

    def restart(self) -> None:
        """Request everything again (link regained, autopilot rebooted)."""
        for st in self._streams.values():
            st.state, st.attempts, st.fallback_at = StreamState.IDLE, 0, -math.inf
        self._outstanding = None
        self.counters["restarts"] += 1

    def state(self, name: str) -> StreamState:
        return self._streams[name].state

    def specs(self) -> list[StreamSpec]:
        """The streams requested, with their rates (what ``companion check`` measures against)."""
        return [st.spec for st in self._streams.values()]

    def states(self) -> dict[str, str]:
        return {k: v.state.value for k, v in self._streams.items()}

    def _ok(self, st: _Stream, now: float) -> bool:
        return self.meter.rate(st.spec.name, now) >= self.config.min_rate_fraction * st.spec.rate_hz

    def _fallback(self, st: _Stream, now: float, why: str, actions: list) -> None:
        st.state = StreamState.FALLBACK
        st.fallback_at = now
        self.counters["fallbacks"] += 1
        self.events.append((mavlink.MAV_SEVERITY_WARNING, f"{st.spec.name}: {why}, using REQUEST_DATA_STREAM"))
        log.warning("%s: %s; falling back to REQUEST_DATA_STREAM", st.spec.name, why)
        actions.append(("data_stream", st.spec.data_stream_id, self._stream_rate(st.spec.data_stream_id)))

    def _stream_rate(self, stream_id: int) -> float:
        return max(s.spec.rate_hz for s in self._streams.values() if s.spec.data_stream_id == stream_id)

    def on_ack(self, result: int, now: float) -> None:
        name = self._outstanding
        if name is None:
            self.counters["unexpected_acks"] += 1
            return
        st = self._streams[name]
        if result == mavlink.MAV_RESULT_IN_PROGRESS:
            return
        self._outstanding = None
        if result == mavlink.MAV_RESULT_ACCEPTED:
            st.state, st.acked_at = StreamState.WAIT_RATE, now
            self.counters["accepted"] += 1
            return
        self.counters["refused"] += 1
        if result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED and st.attempts + 1 < self.config.command_retries:
            st.attempts += 1
            st.state = StreamState.IDLE
            return
        self._fallback(st, now, f"SET_MESSAGE_INTERVAL refused ({result})", self._pending_actions)

    def step(self, now: float) -> list:
        cfg = self.config
        actions: list = self._pending_actions  # REQUEST_DATA_STREAMs waiting for a token come first
        self._pending_actions = []
        if self._outstanding is not None:
            st = self._streams[self._outstanding]
            if now - st.sent_at >= cfg.command_timeout_s:
                self._outstanding = None
                st.attempts += 1
                self.counters["ack_timeouts"] += 1
                if st.attempts >= cfg.command_retries:
                    self._fallback(st, now, "no COMMAND_ACK", actions)
                else:
                    st.state = StreamState.IDLE
        repeat: set[int] = set()
        for st in self._streams.values():
            ok = self._ok(st, now)
            if st.state == StreamState.WAIT_RATE and now - st.acked_at >= cfg.rate_check_s:
                if ok:
                    st.state = StreamState.OK
                    st.attempts = 0
                else:
                    st.attempts += 1
                    self.counters["rate_misses"] += 1
                    rate = self.meter.rate(st.spec.name, now)
                    if st.attempts >= cfg.command_retries:
                        self._fallback(st, now, f"accepted but {rate:.1f} Hz", actions)
                    else:
                        st.state = StreamState.IDLE
            elif st.state == StreamState.OK and not ok:
                rate = self.meter.rate(st.spec.name, now)
                self.counters["dropouts"] += 1
                self.events.append((mavlink.MAV_SEVERITY_WARNING, f"{st.spec.name} at {rate:.1f} Hz, re-requesting"))
                log.warning("%s dropped to %.1f Hz (requested %.1f): re-requesting", st.spec.name, rate, st.spec.rate_hz)
                st.state, st.attempts = StreamState.IDLE, 0
            elif st.state == StreamState.FALLBACK and not ok and now - st.fallback_at >= cfg.fallback_repeat_s:
                st.fallback_at = now
                repeat.add(st.spec.data_stream_id)
        for sid in sorted(repeat):
            self.counters["fallback_repeats"] += 1
            actions.append(("data_stream", sid, self._stream_rate(sid)))
        out: list = []
        waiting: set[int] = set()
        for a in actions:  # one REQUEST_DATA_STREAM per data stream; each needs a token
            if a[1] in waiting or any(o[1] == a[1] for o in out):
                continue
            if self.budget.take(now):
                out.append(a)
            else:
                waiting.add(a[1])
                self._pending_actions.append(a)
        if self._outstanding is None:
            for st in self._streams.values():
                if st.state == StreamState.IDLE:
                    if not self.budget.take(now):
                        waiting.add(-1)
                        break
                    st.state, st.sent_at = StreamState.WAIT_ACK, now
                    st.confirmation = st.attempts
                    self._outstanding = st.spec.name
                    self.counters["interval_requests"] += 1
                    out.append(("interval", st.spec, min(st.confirmation, 255)))
                    break
        if waiting:
            self.counters["rate_limited"] += 1
        return out


# ---------------------------------------------------------------------- status -----------------
@dataclasses.dataclass(frozen=True)
class LinkStatus:
    connected: bool  # a vehicle (or, for a GCS output, a ground station) HEARTBEAT within link_timeout_s
    system_id: int | None  # the system id we send with (the vehicle's, once learnt)
    heartbeat_age_s: float  # seconds since the peer's last HEARTBEAT (inf if never)
    rates_hz: dict[str, float]  # measured arrival rates of the telemetry streams
    streams: dict[str, str]  # request state per stream
    clock_source: str | None  # "timesync", "arrival" or None
    clock_offset_s: float | None  # t_companion − t_autopilot
    timesync_rtt_s: float  # best round trip in the TIMESYNC window
    telemetry_age_s: float  # seconds since the newest ATTITUDE sample (inf if none or no clock)
    signing: bool
    system_status: int  # what our HEARTBEAT says
    counters: dict[str, int]
    vehicle_system_id: int | None = None  # the autopilot's system id we follow (locked)
    sources: dict[str, dict[str, int]] = dataclasses.field(default_factory=dict)  # "SYS/COMP" -> message counts (bounded table)


_NOT_A_VEHICLE = frozenset(
    t for t in (
        getattr(mavlink, n, None)
        for n in ("MAV_TYPE_GCS", "MAV_TYPE_ONBOARD_CONTROLLER", "MAV_TYPE_GIMBAL", "MAV_TYPE_ADSB", "MAV_TYPE_CAMERA",
                  "MAV_TYPE_ANTENNA_TRACKER", "MAV_TYPE_SERVO", "MAV_TYPE_ODID", "MAV_TYPE_BATTERY", "MAV_TYPE_LOG",
                  "MAV_TYPE_OSD", "MAV_TYPE_IMU", "MAV_TYPE_GPS", "MAV_TYPE_WINCH", "MAV_TYPE_GENERIC_MULTIROTOR_COMPONENT")
    ) if t is not None
)

_TELEMETRY = ("ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT")
#: float fields that must be finite before a telemetry message may touch the clock or the buffer
_TELEMETRY_FLOATS = {
    "ATTITUDE": ("roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed"),
    "LOCAL_POSITION_NED": ("x", "y", "z", "vx", "vy", "vz"),
}
#: "Telemetry off the autopilot clock rejected" goes out at most this often (the counters keep the rest)
_CLOCK_WARNING_PERIOD_S = 10.0


class _Disconnected(Exception):
    pass


def _default_factory(conn_str: str, baud: int, source_system: int, source_component: int):
    # retries=0: one TCP connect attempt (pymavlink would otherwise sleep between retries inside poll)
    return mavutil.mavlink_connection(conn_str, baud=baud, source_system=source_system,
                                      source_component=source_component, autoreconnect=False, retries=0)


class _LogLimiter:
    """Log the first occurrence of a key at WARNING, then at most every ``period`` s with a count."""

    def __init__(self, period: float = 10.0):
        self.period = period
        self._last: dict[str, float] = {}
        self._suppressed: collections.Counter[str] = collections.Counter()

    def warn(self, key: str, now: float, fmt: str, *args) -> None:
        last = self._last.get(key)
        if last is None or now - last >= self.period or now < last:
            extra = self._suppressed.pop(key, 0)
            self._last[key] = now
            log.warning(fmt + (f" (+{extra} more since last report)" if extra else ""), *args)
        else:
            self._suppressed[key] += 1


# ---------------------------------------------------------------------- the link ---------------
class MavLink:
    """MAVLink connection of the companion (see module docstring).

    ``role="autopilot"`` (default) follows a vehicle: learns its system id, requests telemetry,
    runs TIMESYNC.  ``role="gcs"`` is a ground-station output: it only sends (with the system id
    given to :meth:`set_system_id`) and watches for a GCS HEARTBEAT.
    """

    def __init__(self, conn_str: str, config: LinkConfig = LinkConfig(), clock: Callable[[], float] = time.monotonic, *,
                 role: str = "autopilot", telemetry: TelemetryBuffer | None = None,
                 connection_factory: Callable[..., Any] | None = None,
                 boot_time_observer: Callable[[float], None] | None = None, clock_offset_s: float | None = None):
        """``boot_time_observer(t_boot_s)`` is told every ``time_boot_ms`` heard from the vehicle
        (ATTITUDE, positions, SYSTEM_TIME, …); ``clock_offset_s`` fixes ``t_companion − t_autopilot``
        instead of the TIMESYNC estimate (TIMESYNC still runs and is logged) — both for the lockstep
        clock of :mod:`companion.simclock`, whose offset is 0 by construction."""
        if role not in ("autopilot", "gcs"):
            raise ConfigError(f"role must be 'autopilot' or 'gcs', got {role!r}")
        if not isinstance(conn_str, str) or not conn_str:
            raise ConfigError(f"connection string must be a non-empty string, got {conn_str!r}")
        self.conn_str = conn_str
        self.config = config
        self.role = role
        self._clock = clock
        self._factory = connection_factory or _default_factory
        self._boot_observer = boot_time_observer
        if clock_offset_s is not None and not (isinstance(clock_offset_s, (int, float)) and math.isfinite(clock_offset_s)):
            raise ConfigError(f"clock_offset_s must be a finite number, got {clock_offset_s!r}")
        self._fixed_offset = None if clock_offset_s is None else float(clock_offset_s)
        self._lock = threading.RLock()
        self.counters: collections.Counter[str] = collections.Counter()
        self.telemetry = telemetry if telemetry is not None else TelemetryBuffer()
        if self._fixed_offset is not None:
            self.telemetry.set_clock_offset(self._fixed_offset)
        self.telemetry.auto_reset = False  # reboots of the autopilot are declared by the clock guard, not by one stamp
        self.timesync = TimesyncEstimator(config.timesync)
        self.meter = RateMeter(config.rate_window_s)
        self.streams = StreamRequester(
            [
                StreamSpec("ATTITUDE", mavlink.MAVLINK_MSG_ID_ATTITUDE, config.attitude_hz, mavlink.MAV_DATA_STREAM_EXTRA1),
                StreamSpec("LOCAL_POSITION_NED", mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, config.local_position_hz,
                           mavlink.MAV_DATA_STREAM_POSITION),
                StreamSpec("GLOBAL_POSITION_INT", mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, config.global_position_hz,
                           mavlink.MAV_DATA_STREAM_POSITION),
            ],
            config,
            self.meter,
        )
        self._events: collections.deque[tuple[int, str]] = collections.deque(maxlen=config.max_events)
        self._logs = _LogLimiter()
        self._signing_key = load_signing_key(config.signing_key_file) if config.signing_key_file else None
        self.signing_policy = (SigningPolicy(self._signing_key, config.require_signing, config.max_signing_streams)
                               if self._signing_key is not None else None)
        # a ground-station output signs on its own link id: the same (link id, system, component) from two
        # links with separate timestamp counters would look like replays to a receiver that hears both
        self._signing_link_id = config.signing_link_id + (1 if role == "gcs" else 0)
        if self._signing_key is not None and not config.require_signing:
            log.warning("%s: MAVLink signing on (outgoing signed), but require_signing = false: unsigned packets are "
                        "accepted (wrongly signed ones are not)", conn_str)
        self.guard = BootClockGuard(
            jitter_s=config.clock_jitter_s, lock_messages=config.clock_lock_messages,
            reboot_confirm_messages=config.reboot_confirm_messages, reboot_confirm_s=config.reboot_confirm_s,
            heartbeat_gap_s=config.reboot_heartbeat_gap_s, reboot_min_interval_s=config.reboot_min_interval_s,
            max_candidates=config.max_clock_candidates)
        self.sources = SourceTable(config.max_sources)
        self._udp_peers: collections.OrderedDict[Any, float] = collections.OrderedDict()  # udpin: address -> last heard
        self._rx_addr = None  # sender of the datagram being parsed (udpin)
        self._rx_trusted = False  # that datagram carried a message from the vehicle (or, before the lock, any valid one)
        self._ts_answers = msgs.RateLimiter(config.timesync_answer_max_hz)
        self._clock_warned = -math.inf
        # the vehicle we follow (locked from config or its first HEARTBEAT) and the system id we send with
        self._vehicle_sysid: int | None = config.autopilot_system_id or None
        self._vehicle_announced = False
        self._sysid: int | None = config.system_id or self._vehicle_sysid
        self._connected = False
        self._ever_connected = False
        self._last_hb = -math.inf
        self._system_status = mavlink.MAV_STATE_STANDBY
        self._hb_limiter = msgs.RateLimiter(config.heartbeat_hz)
        self._last_open_try = -math.inf
        # serial and tcp are reopened while the vehicle is silent; a UDP socket only if it fails
        self._reopenable = conn_str.startswith("tcp:") or ":" not in conn_str
        self._mavlink1_warned = False
        self.global_position = None  # last GLOBAL_POSITION_INT from the vehicle (message object)
        self.vehicle_heartbeat = None  # last HEARTBEAT of the vehicle's autopilot component (message object)
        self.open_error = ""  # why the latest attempt to open the connection failed ("" after a success)
        self._conn = None
        now = self._clock()
        self._open(now, first=True)

    # ------------------------------------------------------------------ connection -----------
    def _open(self, now: float, first: bool = False) -> bool:
        self._last_open_try = now
        src = self._sysid or self.config.provisional_system_id
        try:
            conn = self._factory(self.conn_str, self.config.baud, src, self.config.component_id)
        except ImportError as exc:  # serial connections need pyserial: a setup error, not a flaky link
            self.open_error = str(exc)
            if first:
                raise ConfigError(f"MAVLink connection {self.conn_str!r} needs a missing module: {exc} "
                                  "(serial links need pyserial: pip install pyserial)") from None
            conn = None
            self.counters["open_failures"] += 1
        except ValueError as exc:  # pymavlink's verdict on a malformed connection string
            self.open_error = str(exc)
            if first:
                raise ConfigError(f"MAVLink connection {self.conn_str!r}: {exc}") from None
            conn = None
            self.counters["open_failures"] += 1
            self._logs.warn("open", now, "cannot open %s: %s", self.conn_str, exc)
        except Exception as exc:  # device missing, port busy, connection refused: try again later
            self.open_error = str(exc)
            conn = None
            self.counters["open_failures"] += 1
            self._logs.warn("open", now, "cannot open %s: %s (retrying every %.1f s)", self.conn_str, exc,
                            self.config.reconnect_interval_s)
        if conn is None:
            return False
        conn.mav.robust_parsing = True
        conn.mav.srcSystem = src
        conn.mav.srcComponent = self.config.component_id
        if self.signing_policy is not None:
            conn.setup_signing(self._signing_key, sign_outgoing=True, link_id=self._signing_link_id)
            self.signing_policy.install(conn.mav)
        self._conn = conn
        self.open_error = ""
        self._udp_peers.clear()
        self._reopenable = isinstance(conn, (mavutil.mavserial, mavutil.mavtcp))
        if not first:
            self.counters["reconnects"] += 1
            log.info("reopened %s", self.conn_str)
        return True

    def _close_conn(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except Exception:  # already broken: nothing to do
                pass

    def close(self) -> None:
        with self._lock:
            self._close_conn()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _transport_error(self, now: float, why: str) -> None:
        self.counters["transport_errors"] += 1
        self._logs.warn("transport", now, "%s: %s", self.conn_str, why)
        self._close_conn()  # reopened by _service every reconnect_interval_s

    # ------------------------------------------------------------------ reading --------------
    def _read_bytes(self) -> bytes:
        conn = self._conn
        if isinstance(conn, mavutil.mavtcp):
            if conn.port is None:
                raise _Disconnected("socket closed")
            try:
                data = conn.port.recv(4096)
            except (BlockingIOError, InterruptedError):
                return b""
            except OSError as exc:
                raise _Disconnected(str(exc)) from None
            if not data:
                raise _Disconnected("connection closed by peer")
            return data
        if isinstance(conn, mavutil.mavserial):
            try:
                return bytes(conn.port.read(4096))
            except Exception as exc:  # serial.SerialException when the device vanishes
                raise _Disconnected(str(exc)) from None
        self._rx_addr = None
        try:
            if isinstance(conn, mavutil.mavudp) and conn.udp_server:
                # read the socket ourselves: pymavlink's recv() would add every sender to the set of
                # addresses it sends to (unbounded, and random bytes from anyone would redirect our traffic);
                # a sender becomes a peer only through _register_peer
                data, self._rx_addr = conn.port.recvfrom(65535)
            else:
                data = conn.recv(4096)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                return b""
            raise _Disconnected(str(exc)) from None
        return bytes(data) if data else b""

    def _register_peer(self, addr, now: float) -> None:
        """udpin: ``addr`` sent valid MAVLink from the vehicle: send to it (at most ``max_udp_peers``)."""
        conn = self._conn
        if addr is None or not (isinstance(conn, mavutil.mavudp) and conn.udp_server):
            return
        peers = self._udp_peers
        if addr in peers:
            peers.move_to_end(addr)
        peers[addr] = now
        conn.clients.add(addr)
        conn.clients_last_alive[addr] = time.time()
        while len(peers) > self.config.max_udp_peers:
            old, _ = peers.popitem(last=False)
            conn.clients.discard(old)
            conn.clients_last_alive.pop(old, None)
            self.counters["udp_peers_evicted"] += 1

    def _reset_parser(self) -> None:
        mav = self._conn.mav
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2

    def _parse(self, data: bytes, datagram: bool) -> list:
        mav = self._conn.mav
        if datagram and mav.buf_len() > 0:
            # a packet cut short in the previous datagram: MAVLink over UDP never spans datagrams
            self.counters["rx_truncated"] += 1
            self._reset_parser()
        try:
            out = mav.parse_buffer(data) or []
        except Exception as exc:  # robust_parsing turns errors into BAD_DATA; anything else is a parser bug
            self.counters["rx_parser_errors"] += 1
            self._logs.warn("parser", self._clock(), "MAVLink parser error: %r", exc)
            self._reset_parser()
            return []
        if datagram and mav.buf_len() > 0:
            self.counters["rx_truncated"] += 1
            self._reset_parser()
        return out

    def poll(self) -> int:
        """Read and handle everything available, then run the periodic duties; never blocks or raises
        on wire input.  Returns the number of messages handled."""
        with self._lock:
            now = self._clock()
            handled = 0
            datagram = isinstance(self._conn, mavutil.mavudp) or bool(getattr(self._conn, "mavlink_datagrams", False))
            for _ in range(self.config.max_messages_per_poll):
                if self._conn is None:
                    break
                try:
                    data = self._read_bytes()
                except _Disconnected as exc:
                    self._transport_error(now, str(exc))
                    break
                except Exception as exc:  # pragma: no cover - defensive
                    self.counters["rx_errors"] += 1
                    self._logs.warn("read", now, "read error on %s: %r", self.conn_str, exc)
                    break
                if not data:
                    break
                self.counters["rx_bytes"] += len(data)
                addr, self._rx_trusted = self._rx_addr, False
                for m in self._parse(data, datagram):
                    handled += 1
                    try:
                        self._dispatch(m, now)
                    except Exception as exc:  # a handler must never take the process down
                        self.counters["rx_handler_errors"] += 1
                        self._logs.warn("handler", now, "error handling %s: %r", getattr(m, "get_type", lambda: "?")(), exc)
                if self._rx_trusted and addr is not None:
                    self._register_peer(addr, now)
                if handled >= self.config.max_messages_per_poll:
                    self.counters["poll_budget_exhausted"] += 1
                    break
            try:
                self._service(now)
            except Exception as exc:  # pragma: no cover - defensive
                self.counters["service_errors"] += 1
                self._logs.warn("service", now, "link service error: %r", exc)
            return handled

    # ------------------------------------------------------------------ dispatch -------------
    def _classify_bad(self, m, now: float) -> None:
        reason = str(getattr(m, "reason", ""))
        if "signature" in reason:
            key = "rx_signing_rejected"
        elif "CRC" in reason:
            key = "rx_bad_crc"
        elif "prefix" in reason:
            key = "rx_bad_prefix"
        elif "length" in reason or "Bad message" in reason:
            key = "rx_bad_length"
        else:
            key = "rx_bad_data"
        self.counters[key] += 1
        self._logs.warn(key, now, "%s: %s", key, reason[:120])

    def _from_vehicle(self, m) -> bool:
        return (self._vehicle_sysid is not None and m.get_srcSystem() == self._vehicle_sysid
                and m.get_srcComponent() == self.config.autopilot_component_id)

    def _dispatch(self, m, now: float) -> None:
        """One parsed message: count it (per source), then act on it only if it is the autopilot's.

        Only the locked autopilot (its system and ``autopilot_component_id``) feeds telemetry, the
        clock, TIMESYNC and the stream state; every message with a ``time_boot_ms`` passes the
        :class:`~companion.mavlink.guard.BootClockGuard` first, so a packet off the autopilot's clock is
        rejected (counted ``rx_clock_<reason>``) and a reboot is declared only on consistent evidence."""
        t = m.get_type()
        if t == "BAD_DATA":
            self._classify_bad(m, now)
            return
        if t.startswith("UNKNOWN_"):
            self.counters["rx_unknown_id"] += 1
            self._logs.warn("unknown", now, "message with unknown id: %s", t)
            return
        self.counters["rx_messages"] += 1
        src = (m.get_srcSystem(), m.get_srcComponent())
        from_vehicle = self._from_vehicle(m)
        self.sources.count(src, "autopilot" if from_vehicle else "other")
        if self.role == "gcs" or self._vehicle_sysid is None or src[0] == self._vehicle_sysid:
            self._rx_trusted = True
        buf = m.get_msgbuf()
        if buf and buf[0] == mavlink.PROTOCOL_MARKER_V1:
            self.counters["rx_mavlink1"] += 1
            if not self._mavlink1_warned:
                self._mavlink1_warned = True
                log.warning("%s speaks MAVLink 1: OBSTACLE_DISTANCE needs MAVLink 2 on this port", self.conn_str)
        if t == "HEARTBEAT":
            self._on_heartbeat(m, now)
            return
        if self.role != "autopilot":
            return
        if not from_vehicle:
            self.counters["rx_foreign"] += 1
            return
        tb = getattr(m, "time_boot_ms", None)
        if isinstance(tb, int):
            if t in _TELEMETRY_FLOATS and not all(math.isfinite(getattr(m, f, math.nan)) for f in _TELEMETRY_FLOATS[t]):
                self.counters["rx_nonfinite"] += 1  # never let a NaN sample move the clock
                self._logs.warn("nonfinite", now, "%s with a non-finite field refused", t)
                return
            verdict = self.guard.check(t, tb, now)
            if not verdict.accepted:
                self.counters["rx_clock_rejected"] += 1
                self.counters[f"rx_clock_{verdict.reason}"] += 1
                self.sources.count(src, "clock_rejected")
                if verdict.reason != "acquiring":
                    self._clock_warning(now, t, tb, verdict.reason)
                return
            if verdict.reboot:
                self._vehicle_rebooted(now)
            if self._boot_observer is not None:
                self._boot_observer(tb * 1e-3)
        if t == "ATTITUDE":
            self.meter.tick(t, now)
            r = self.telemetry.add_attitude(m.time_boot_ms, m.roll, m.pitch, m.yaw, m.rollspeed, m.pitchspeed, m.yawspeed)
            self._after_telemetry(r, m.time_boot_ms, now)
        elif t == "LOCAL_POSITION_NED":
            self.meter.tick(t, now)
            r = self.telemetry.add_local_position(m.time_boot_ms, m.x, m.y, m.z, m.vx, m.vy, m.vz)
            self._after_telemetry(r, m.time_boot_ms, now)
        elif t == "GLOBAL_POSITION_INT":
            self.meter.tick(t, now)
            self.global_position = m
        elif t == "TIMESYNC":
            reply = handle_timesync(self.timesync, m, now)
            if reply is not None:
                if self._ts_answers.ready(now):
                    self._send(reply)
                else:
                    self.counters["tx_timesync_answers_limited"] += 1
        elif t == "COMMAND_ACK":
            self._on_ack(m, now)

    def _clock_warning(self, now: float, t: str, tb: int, reason: str) -> None:
        newest = self.guard.newest_s
        self._logs.warn("clock", now, "%s with time_boot_ms %d refused (%s; autopilot clock at %s ms)", t, tb, reason,
                        "?" if newest is None else f"{newest * 1000:.0f}")
        if now - self._clock_warned >= _CLOCK_WARNING_PERIOD_S or now < self._clock_warned:
            self._clock_warned = now
            self._event(mavlink.MAV_SEVERITY_WARNING, "Telemetry off the autopilot clock rejected")

    def _after_telemetry(self, result: AddResult, time_boot_ms: int, now: float) -> None:
        self.counters[f"telemetry_{result.value}"] += 1
        if result in (AddResult.APPENDED, AddResult.RESET):
            self.timesync.observe_stamp(time_boot_ms * 1e-3, now)

    def _vehicle_rebooted(self, now: float) -> None:
        """The clock guard declared a reboot (consistent evidence, rate limited): clear the telemetry
        (the pipeline restarts on it), restart TIMESYNC and the stream requests, tell the operator."""
        self.counters["vehicle_reboots"] += 1
        self._event(mavlink.MAV_SEVERITY_WARNING, "Autopilot reboot seen: resync, re-request")
        log.warning("autopilot reboot declared (%s)", self.guard.history[-1][2] if self.guard.history else "")
        self.telemetry.declare_reset("autopilot reboot")
        self.timesync.reset("autopilot reboot")
        self.meter.clear()
        self.streams.restart()

    def _on_ack(self, m, now: float) -> None:
        if m.command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        tc = getattr(m, "target_component", 0)
        ts = getattr(m, "target_system", 0)
        if tc not in (0, self.config.component_id) or ts not in (0, self._sysid):
            self.counters["rx_ack_for_others"] += 1  # a GCS's command on a shared link
            return
        self.streams.on_ack(m.result, now)

    def _on_heartbeat(self, m, now: float) -> None:
        src, comp = m.get_srcSystem(), m.get_srcComponent()
        if self.role == "gcs":
            if m.type == mavlink.MAV_TYPE_GCS:
                self._peer_alive(now, "ground station")
            return
        is_vehicle = (comp == self.config.autopilot_component_id and m.type not in _NOT_A_VEHICLE
                      and m.autopilot != mavlink.MAV_AUTOPILOT_INVALID)
        if not is_vehicle:
            self.counters["rx_heartbeat_other"] += 1
            return
        if self._vehicle_sysid is None:
            self._vehicle_sysid = src
        elif src != self._vehicle_sysid:
            self.counters["rx_heartbeat_other_vehicle"] += 1
            return
        if not self._vehicle_announced:
            self._vehicle_announced = True
            self.sources.protected = (src, comp)
            self._event(mavlink.MAV_SEVERITY_INFO, f"Vehicle system id {src}")
            log.info("vehicle system id %d %s", src,
                     "(from [link] autopilot_system_id)" if self.config.autopilot_system_id else "learnt from its HEARTBEAT")
        if self._sysid is None:
            self._sysid = src
            if self._conn is not None:
                self._conn.mav.srcSystem = src
            self._hb_limiter.reset()  # announce ourselves under the vehicle's system id now, not a period later
        self._rx_trusted = True
        self.guard.heartbeat(now)
        self.vehicle_heartbeat = m
        self._peer_alive(now, "vehicle")

    def _peer_alive(self, now: float, who: str) -> None:
        self._last_hb = now
        self.counters["rx_heartbeats"] += 1
        if not self._connected:
            self._connected = True
            if self._ever_connected:
                self._event(mavlink.MAV_SEVERITY_NOTICE, f"Link to {who} restored")
                log.info("link to %s restored", who)
            self._ever_connected = True
            if self.role == "autopilot":
                self.streams.restart()

    # ------------------------------------------------------------------ periodic duties ------
    def _service(self, now: float) -> None:
        cfg = self.config
        if self._connected and now - self._last_hb > cfg.link_timeout_s:
            self._connected = False
            self.counters["link_lost"] += 1
            self._event(mavlink.MAV_SEVERITY_WARNING, f"No heartbeat for {cfg.link_timeout_s:.0f}s: link lost")
            log.warning("%s: no HEARTBEAT for %.1f s, link lost", self.conn_str, cfg.link_timeout_s)
        need_open = self._conn is None or (self._reopenable and self._ever_connected and not self._connected)
        if need_open and now - self._last_open_try >= cfg.reconnect_interval_s:
            self._close_conn()
            self._open(now)
        if self._conn is None:
            return
        if self._hb_limiter.ready(now):
            self._send(msgs.heartbeat(self._system_status))
        if self.role != "autopilot" or self._vehicle_sysid is None or self._sysid is None or not self._connected:
            self.telemetry.set_clock_offset(self._clock_offset())
            return
        if self.timesync.request_due(now):
            self._send(timesync_request(self.timesync, now))
        for action in self.streams.step(now):
            if action[0] == "interval":
                _, spec, conf = action
                self._send(msgs.set_message_interval(self._vehicle_sysid, cfg.autopilot_component_id, spec.msg_id, spec.rate_hz, conf))
            else:
                _, sid, rate = action
                self.counters["tx_request_data_stream"] += 1
                self._send(msgs.request_data_stream(self._vehicle_sysid, cfg.autopilot_component_id, sid, rate))
        for ev in self.streams.events:
            self._event(*ev)
        self.streams.events.clear()
        self.telemetry.set_clock_offset(self._clock_offset())

    def _clock_offset(self) -> float | None:
        """``t_companion − t_autopilot`` in use: the fixed one if given, else the TIMESYNC estimate."""
        return self._fixed_offset if self._fixed_offset is not None else self.timesync.offset_s

    def _event(self, severity: int, text: str) -> None:
        if len(self._events) == self._events.maxlen:
            self.counters["events_dropped"] += 1  # the oldest goes: nobody drained for a long time
        self._events.append((severity, text))

    # ------------------------------------------------------------------ sending --------------
    def _write(self, buf: bytes) -> None:
        conn = self._conn
        if isinstance(conn, mavutil.mavtcp):
            if conn.port is None:
                raise _Disconnected("socket closed")
            try:
                conn.port.sendall(buf)
            except (BlockingIOError, InterruptedError):
                self.counters["tx_dropped_busy"] += 1
            except OSError as exc:
                raise _Disconnected(str(exc)) from None
        elif isinstance(conn, mavutil.mavserial):
            try:
                conn.port.write(buf)
            except Exception as exc:
                raise _Disconnected(str(exc)) from None
        else:
            conn.write(buf)

    def _send(self, msg) -> bool:
        conn = self._conn
        if conn is None:
            self.counters["tx_dropped_no_link"] += 1
            return False
        try:
            buf = msg.pack(conn.mav)
        except Exception as exc:
            self.counters["tx_pack_errors"] += 1
            self._logs.warn("pack", self._clock(), "cannot pack %s: %r", getattr(msg, "get_type", lambda: "?")(), exc)
            return False
        conn.mav.seq = (conn.mav.seq + 1) % 256
        try:
            self._write(bytes(buf))
        except _Disconnected as exc:
            self._transport_error(self._clock(), str(exc))
            return False
        except Exception as exc:  # pragma: no cover - defensive
            self.counters["tx_errors"] += 1
            self._logs.warn("write", self._clock(), "write error on %s: %r", self.conn_str, exc)
            return False
        self.counters["tx_messages"] += 1
        self.counters[f"tx_{msg.get_type()}"] += 1
        return True

    def send(self, msg) -> bool:
        """Send a message from :mod:`companion.mavlink.messages` with our system / component id.

        Dropped (False, counted) while the system id is unknown or the connection is down.
        """
        with self._lock:
            if self._sysid is None:
                self.counters["tx_dropped_no_sysid"] += 1
                return False
            return self._send(msg)

    def send_many(self, messages) -> int:
        with self._lock:
            return sum(1 for m in messages if self.send(m))

    # ------------------------------------------------------------------ owner controls -------
    def set_producing(self, valid: bool) -> None:
        """HEARTBEAT system_status: ACTIVE while valid ranges are produced, STANDBY otherwise."""
        with self._lock:
            self._system_status = mavlink.MAV_STATE_ACTIVE if valid else mavlink.MAV_STATE_STANDBY

    def set_system_status(self, state: int) -> None:
        """Any MAV_STATE (e.g. CRITICAL when the camera is gone)."""
        with self._lock:
            if not (isinstance(state, int) and 0 <= state < mavlink.MAV_STATE_ENUM_END):
                raise ConfigError(f"not a MAV_STATE: {state!r}")
            self._system_status = state

    def set_system_id(self, sysid: int) -> None:
        """Fix the system id we send with (the GCS output takes the vehicle's from the autopilot link)."""
        with self._lock:
            if not (isinstance(sysid, int) and 1 <= sysid <= 255):
                raise ConfigError(f"system id must be in 1..255, got {sysid!r}")
            self._sysid = sysid
            if self._conn is not None:
                self._conn.mav.srcSystem = sysid

    def drain_events(self) -> list[tuple[int, str]]:
        """State changes since the last call, as (MAV_SEVERITY, text ≤ 50 chars) for STATUSTEXT."""
        with self._lock:
            out = list(self._events)
            self._events.clear()
            return out

    # ------------------------------------------------------------------ state ----------------
    @property
    def system_id(self) -> int | None:
        """The system id we send with (the vehicle's, once learnt, unless ``[link] system_id`` is set)."""
        return self._sysid

    @property
    def vehicle_system_id(self) -> int | None:
        """The autopilot's system id we follow (locked from config or its first HEARTBEAT)."""
        return self._vehicle_sysid

    @property
    def connected(self) -> bool:
        return self._connected

    @property
    def is_open(self) -> bool:
        """The connection (serial device, socket) is open now; :attr:`open_error` says why not."""
        return self._conn is not None

    @property
    def system_status(self) -> int:
        return self._system_status

    @property
    def signing(self) -> bool:
        return self._signing_key is not None

    def rates(self) -> dict[str, float]:
        with self._lock:
            now = self._clock()
            return {n: self.meter.rate(n, now) for n in _TELEMETRY}

    def autopilot_time_usec(self, t_companion: float) -> int | None:
        """Companion time mapped onto the autopilot's boot clock, µs (None before TIMESYNC)."""
        with self._lock:
            t = (t_companion - self._fixed_offset) if self._fixed_offset is not None else \
                self.timesync.companion_to_autopilot(t_companion)
        return None if t is None or t < 0 else int(round(t * 1e6))

    def autopilot_time_boot_ms(self, t_companion: float) -> int | None:
        us = self.autopilot_time_usec(t_companion)
        return None if us is None else us // 1000

    def status(self) -> LinkStatus:
        with self._lock:
            now = self._clock()
            counters = dict(self.counters)
            groups = [("telemetry.", self.telemetry.counters), ("timesync.", self.timesync.counters),
                      ("streams.", self.streams.counters), ("clock.", self.guard.counters)]
            if self.signing_policy is not None:
                groups.append(("signing.", self.signing_policy.counters))
                counters["rx_bad_signature"] = self.signing_policy.counters.get("bad_signature", 0)
            for prefix, c in groups:
                counters.update({prefix + k: v for k, v in c.items()})
            counters["sources_tracked"] = len(self.sources)
            counters["sources_evicted"] = self.sources.evicted
            return LinkStatus(
                connected=self._connected,
                system_id=self._sysid,
                heartbeat_age_s=now - self._last_hb,
                rates_hz={n: self.meter.rate(n, now) for n in _TELEMETRY},
                streams=self.streams.states(),
                clock_source=self.timesync.source,
                clock_offset_s=self.timesync.offset_s,
                timesync_rtt_s=self.timesync.best_rtt_s,
                telemetry_age_s=self.telemetry.age(now),
                signing=self._signing_key is not None,
                system_status=self._system_status,
                counters=counters,
                vehicle_system_id=self._vehicle_sysid,
                sources=self.sources.snapshot(),
            )
