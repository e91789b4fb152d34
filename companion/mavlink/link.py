"""The companion's MAVLink connection to the autopilot (or to a ground station) — docs/derivations/link.md.

:class:`MavLink` is a thin, single-owner I/O shell around ``mavutil.mavlink_connection``
(serial device with baud, ``udpin:``, ``udpout:``, ``tcp:``) that delegates every decision to pure
pieces: :class:`~companion.telemetry.TelemetryBuffer` (telemetry history),
:class:`~companion.mavlink.timesync.TimesyncEstimator` (clock mapping),
:class:`~companion.mavlink.streams.StreamRequester` (which telemetry to ask for, how, and whether
it arrives) and :class:`~companion.mavlink.streams.RateMeter`.  Below it,
:class:`~companion.mavlink.transport.Connection` opens and reopens the pymavlink connection and
moves the raw bytes; its settings are :class:`~companion.mavlink.config.LinkConfig` (``[link]``).
This module holds the rest: the receive loop (:meth:`MavLink.poll`: parse, dispatch by message
and source), the periodic duties (HEARTBEAT, link loss, TIMESYNC and stream requests), sending,
and the status.

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
import logging
import math
import threading
import time
from typing import Any, Callable

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.errors import ConfigError
from companion.mavlink import messages as msgs
from companion.mavlink.config import LinkConfig
from companion.mavlink.guard import BootClockGuard, SourceTable
from companion.mavlink.signing import SigningPolicy, load_signing_key
from companion.mavlink.streams import RateMeter, StreamRequester, StreamSpec
from companion.mavlink.timesync import TimesyncEstimator, handle_timesync, timesync_request
from companion.mavlink.transport import Connection, Disconnected, LogLimiter
from companion.telemetry import AddResult, TelemetryBuffer

log = logging.getLogger(__name__)


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
        self._logs = LogLimiter(log)
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
        self._mavlink1_warned = False
        self.global_position = None  # last GLOBAL_POSITION_INT from the vehicle (message object)
        self.vehicle_heartbeat = None  # last HEARTBEAT of the vehicle's autopilot component (message object)
        self.transport = Connection(conn_str, config, self.counters, self._logs, clock, connection_factory,
                                    signing_key=self._signing_key, signing_policy=self.signing_policy,
                                    signing_link_id=self._signing_link_id)
        now = self._clock()
        self._open(now, first=True)

    # ------------------------------------------------------------------ connection -----------
    def _open(self, now: float, first: bool = False) -> bool:
        return self.transport.open(now, self._sysid or self.config.provisional_system_id, first)

    # ------------------------------------------------------------------ connection -----------
    def close(self) -> None:
        with self._lock:
            self.transport.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def poll(self) -> int:
        """Read and handle everything available, then run the periodic duties; never blocks or raises
        on wire input.  Returns the number of messages handled."""
        with self._lock:
            now = self._clock()
            handled = 0
            datagram = self.transport.datagram
            for _ in range(self.config.max_messages_per_poll):
                if self.transport.conn is None:
                    break
                try:
                    data = self.transport.read()
                except Disconnected as exc:
                    self.transport.fail(now, str(exc))
                    break
                except Exception as exc:  # pragma: no cover - defensive
                    self.counters["rx_errors"] += 1
                    self._logs.warn("read", now, "read error on %s: %r", self.conn_str, exc)
                    break
                if not data:
                    break
                self.counters["rx_bytes"] += len(data)
                addr, self._rx_trusted = self.transport.rx_addr, False
                for m in self.transport.parse(data, datagram):
                    handled += 1
                    try:
                        self._dispatch(m, now)
                    except Exception as exc:  # a handler must never take the process down
                        self.counters["rx_handler_errors"] += 1
                        self._logs.warn("handler", now, "error handling %s: %r", getattr(m, "get_type", lambda: "?")(), exc)
                if self._rx_trusted and addr is not None:
                    self.transport.register_peer(addr, now)
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
            self.transport.set_source_system(src)
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
        need_open = self.transport.conn is None or (self.transport.reopenable and self._ever_connected and not self._connected)
        if need_open and now - self.transport.last_open_try >= cfg.reconnect_interval_s:
            self.transport.close()
            self._open(now)
        if self.transport.conn is None:
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
    def _send(self, msg) -> bool:
        conn = self.transport.conn
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
            self.transport.write(bytes(buf))
        except Disconnected as exc:
            self.transport.fail(self._clock(), str(exc))
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
            self.transport.set_source_system(sysid)

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
        return self.transport.conn is not None

    @property
    def open_error(self) -> str:
        """Why the latest attempt to open the connection failed ("" after a success)."""
        return self.transport.open_error

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
