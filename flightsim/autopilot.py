"""The simulated autopilot's side of MAVLink for the software-in-the-loop run (docs/derivations/link.md).

``flightsim sitl`` plays an ArduPilot-like vehicle to a live companion over UDP on 127.0.0.1.
Two layers:

:class:`AutopilotLogic` (pure: no sockets, the caller's simulation clock)
    what the vehicle answers and streams —

    * HEARTBEAT at 1 Hz from system ``[telemetry] system_id``, component 1
      (MAV_COMP_ID_AUTOPILOT1), with the scenario's MAV_TYPE and MAV_AUTOPILOT_ARDUPILOTMEGA
      (MAV_AUTOPILOT_PX4 when the simulated avoidance is PX4's; built by
      :class:`flightsim.telemetry.TelemetryModel`);
    * nothing else until asked: COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL (511) for ATTITUDE,
      LOCAL_POSITION_NED, GLOBAL_POSITION_INT or SYSTEM_TIME is answered with COMMAND_ACK
      ACCEPTED and the stream runs at the requested interval (param2 µs; 0 = the scenario's
      default rate, −1 = stop) from the next physics step; other message ids are refused
      (MAV_RESULT_DENIED), other commands MAV_RESULT_UNSUPPORTED; commands for another system or
      component are ignored, as an autopilot does;
    * REQUEST_DATA_STREAM (the fallback of older ArduPilot) is honoured with ArduPilot's grouping:
      EXTRA1 → ATTITUDE, POSITION → LOCAL_POSITION_NED + GLOBAL_POSITION_INT, EXTENDED_STATUS →
      SYSTEM_TIME, ALL → all of them; rate 0 or start_stop 0 stops them;
    * TIMESYNC: a request (``tc1 = 0``) is answered with ``tc1`` = the vehicle's boot clock in ns
      when it is handled and ``ts1`` echoed; replies addressed to others are ignored;
    * the messages themselves (ATTITUDE, LOCAL_POSITION_NED, GLOBAL_POSITION_INT) come from the
      telemetry model with its noise, gyro drift and latency, ``time_boot_ms`` on the vehicle's
      own boot clock (``[telemetry] boot_time_s`` of uptime at simulation start).

:class:`UdpEndpoint` (thin I/O)
    a UDP socket bound to ``127.0.0.1:PORT`` (the companion connects with
    ``udpout:127.0.0.1:PORT``; the vehicle answers whoever spoke last, as a UDP server does),
    packing with the vehicle's ids and parsing each datagram on its own with pymavlink's robust
    parser (bad data is counted, never raised).
"""

from __future__ import annotations

import collections
import errno
import logging
import math
import select
import socket
from typing import Callable

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.errors import ConfigError

log = logging.getLogger(__name__)

COMPONENT_ID = 1  # MAV_COMP_ID_AUTOPILOT1

# messages the vehicle can stream on request: id -> name (StreamSchedule names)
STREAMABLE = {
    mavlink.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: "LOCAL_POSITION_NED",
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "GLOBAL_POSITION_INT",
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: "SYSTEM_TIME",
}
# REQUEST_DATA_STREAM groups (ArduPilot's GCS_MAVLink stream assignment for these messages)
DATA_STREAMS = {
    mavlink.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    mavlink.MAV_DATA_STREAM_POSITION: ("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"),
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYSTEM_TIME",),
    mavlink.MAV_DATA_STREAM_ALL: ("ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "SYSTEM_TIME"),
}


class AutopilotLogic:
    """Answers to the companion's requests, on the simulation clock (see the module docstring).

    ``set_period(name, period_s | None, t)`` is called when a stream changes (the caller's
    :class:`flightsim.fly.StreamSchedule`); ``default_period_s`` gives each streamable message's
    rate for an interval of 0; ``boot_s(t)`` maps simulation time onto the vehicle's boot clock.
    :meth:`handle` returns the replies to send.
    """

    def __init__(self, system_id: int, set_period: Callable[[str, float | None, float], None],
                 default_period_s: dict[str, float], boot_s: Callable[[float], float]):
        self.system_id = system_id
        self._set_period = set_period
        self.default_period_s = dict(default_period_s)
        self._boot_s = boot_s
        self.periods: dict[str, float | None] = {name: None for name in STREAMABLE.values()}
        self.counters: collections.Counter[str] = collections.Counter()
        self.requests: list[tuple[float, str, str, float | None]] = []  # (t, how, stream, period) in order
        self.peers: dict[tuple[int, int], int] = {}  # (sysid, compid) -> MAV_TYPE of HEARTBEATs heard

    def _for_us(self, target_system: int, target_component: int) -> bool:
        return target_system in (0, self.system_id) and target_component in (0, COMPONENT_ID)

    def _stream(self, name: str, period: float | None, t: float, how: str) -> None:
        self.periods[name] = period
        self._set_period(name, period, t)
        self.requests.append((t, how, name, period))
        log.info("t=%.3f s: %s %s", t, name, "stopped" if period is None else f"every {period * 1000:.1f} ms ({how})")

    def handle(self, msg, t: float) -> list:
        """Handle one message received from the companion at simulation time ``t``; returns replies."""
        typ = msg.get_type()
        self.counters[f"rx_{typ}"] += 1
        if typ == "HEARTBEAT":
            self.peers[(msg.get_srcSystem(), msg.get_srcComponent())] = msg.type
            return []
        if typ == "COMMAND_LONG":
            if not self._for_us(msg.target_system, msg.target_component):
                self.counters["commands_for_others"] += 1
                return []
            return [self._command(msg, t)]
        if typ == "REQUEST_DATA_STREAM":
            if not self._for_us(msg.target_system, msg.target_component):
                self.counters["commands_for_others"] += 1
                return []
            names = DATA_STREAMS.get(msg.req_stream_id)
            if names is None:
                self.counters["data_stream_unknown"] += 1
                return []
            on = msg.start_stop != 0 and msg.req_message_rate > 0
            for name in names:
                self._stream(name, 1.0 / msg.req_message_rate if on else None, t, "REQUEST_DATA_STREAM")
            return []
        if typ == "TIMESYNC":
            if msg.tc1 == 0 and msg.ts1 > 0:
                self.counters["timesync_answered"] += 1
                tc1 = max(1, int(round(self._boot_s(t) * 1e9)))
                return [mavlink.MAVLink_timesync_message(tc1, int(msg.ts1))]
            return []
        return []

    def _command(self, msg, t: float):
        cmd = msg.command
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()

        def ack(result: int):
            self.counters[f"ack_{result}"] += 1
            return mavlink.MAVLink_command_ack_message(cmd, result, 0, 0, src_sys, src_comp)

        if cmd != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return ack(mavlink.MAV_RESULT_UNSUPPORTED)
        p1, p2 = msg.param1, msg.param2
        if not (math.isfinite(p1) and math.isfinite(p2)):
            return ack(mavlink.MAV_RESULT_DENIED)
        name = STREAMABLE.get(int(p1))
        if name is None or int(p1) != p1:
            return ack(mavlink.MAV_RESULT_DENIED)
        if p2 < 0:
            period = None
        elif p2 == 0:
            period = self.default_period_s[name]
        else:
            period = p2 * 1e-6
            if period < 1e-3:  # faster than 1 kHz: refuse like an autopilot that cannot keep up
                return ack(mavlink.MAV_RESULT_DENIED)
        self._stream(name, period, t, "SET_MESSAGE_INTERVAL")
        return ack(mavlink.MAV_RESULT_ACCEPTED)


class PortBusyError(ConfigError):
    """A requested port cannot be bound (another SITL, ground station or companion holds it)."""


class UdpEndpoint:
    """The vehicle's UDP socket on ``host:port`` (port 0 = any free port; see :attr:`port`)."""

    def __init__(self, port: int, system_id: int, component_id: int = COMPONENT_ID, host: str = "127.0.0.1"):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, int(port)))
        except OSError as exc:
            self.sock.close()
            if exc.errno == errno.EADDRINUSE:
                raise PortBusyError(f"UDP port {port} on {host} is busy (another SITL, ground station or companion?); "
                                    "pick another with --mavlink-port, or 0 for any free port") from None
            raise ConfigError(f"cannot bind UDP {host}:{port}: {exc.strerror or exc}") from None
        self.sock.setblocking(False)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 21)
        self.host, self.port = self.sock.getsockname()[:2]
        self.peer: tuple[str, int] | None = None
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self.counters: collections.Counter[str] = collections.Counter()

    def pack(self, msg) -> bytes:
        buf = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def send(self, msg) -> bytes | None:
        """Pack and send to the peer; the packed bytes (None if no peer is known yet: not sent)."""
        if self.peer is None:
            self.counters["tx_no_peer"] += 1
            return None
        buf = self.pack(msg)
        try:
            self.sock.sendto(buf, self.peer)
        except OSError as exc:  # the peer went away (ECONNREFUSED) or the buffer is full
            self.counters["tx_errors"] += 1
            log.debug("send to %s failed: %s", self.peer, exc)
            return None
        self.counters["tx_messages"] += 1
        return buf

    def send_raw(self, buf: bytes) -> bool:
        """Send bytes as one datagram to the peer, as they are (hostile traffic, :mod:`flightsim.hostile`);
        False if no peer is known yet or the send failed."""
        if self.peer is None:
            return False
        try:
            self.sock.sendto(buf, self.peer)
        except OSError as exc:
            self.counters["tx_raw_errors"] += 1
            log.debug("raw send to %s failed: %s", self.peer, exc)
            return False
        self.counters["tx_raw_datagrams"] += 1
        return True

    def wait_readable(self, timeout: float) -> bool:
        if timeout <= 0:
            return False
        r, _, _ = select.select([self.sock], [], [], timeout)
        return bool(r)

    def receive(self) -> list[tuple[bytes, object]]:
        """Every message waiting now, as ``(raw frame, parsed message)``; learns the peer address."""
        out = []
        while True:
            try:
                data, addr = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:  # ICMP errors surface here on Linux: nothing to read
                if exc.errno in (errno.ECONNREFUSED, errno.EAGAIN):
                    continue
                raise
            if addr != self.peer:
                if self.peer is not None:
                    log.info("MAVLink peer changed from %s:%d to %s:%d", *self.peer, *addr)
                self.peer = addr
                self.counters["peers"] += 1
            self.counters["rx_datagrams"] += 1
            p = self._parser
            try:
                msgs = p.parse_buffer(data) or []
            except Exception as exc:  # robust parsing reports BAD_DATA; anything else: count and go on
                self.counters["rx_parser_errors"] += 1
                log.debug("parser error: %r", exc)
                msgs = []
            if p.buf_len() > 0:  # a datagram never continues in the next one
                self.counters["rx_truncated"] += 1
                p.buf = bytearray()
                p.buf_index = 0
                p.expected_length = mavlink.HEADER_LEN_V1 + 2
            for m in msgs:
                if m.get_type() == "BAD_DATA" or m.get_type().startswith("UNKNOWN"):
                    self.counters["rx_bad"] += 1
                    continue
                out.append((bytes(m.get_msgbuf()), m))
        return out

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass


__all__ = ["AutopilotLogic", "UdpEndpoint", "PortBusyError", "STREAMABLE", "DATA_STREAMS", "COMPONENT_ID"]
