"""One MAVLink connection of the companion's link, below :class:`~companion.mavlink.link.MavLink` (docs/derivations/link.md).

:class:`Connection` opens ``mavutil.mavlink_connection`` (serial device with baud, ``udpin:``,
``udpout:``, ``tcp:``) with robust parsing, our system / component ids and, with a key, MAVLink 2
signing; reopens it when the link asks; reads and writes raw bytes itself (pymavlink's ``recv`` on
``udpin`` would add every sender to the addresses it sends to: here a sender becomes a peer only
when the link says it sent the vehicle's MAVLink, at most ``max_udp_peers``); and parses each UDP
datagram on its own (MAVLink over UDP never spans datagrams: a packet cut short is counted, not
glued to the next one).  A broken socket or device raises :class:`Disconnected` from
:meth:`Connection.read` / :meth:`Connection.write`; :meth:`Connection.fail` closes it.

It counts in the link's ``counters`` and warns through the link's :class:`LogLimiter` (shared with
:class:`~companion.mavlink.link.MavLink`, so its status and log read as one).  It holds no lock:
the link serializes every call.
"""

from __future__ import annotations

import collections
import errno
import logging
import math
import time
from typing import Any, Callable

from companion.mavlink.dialect import mavlink, mavutil  # first: MAVLink 2 + ardupilotmega
from companion.errors import ConfigError
from companion.mavlink.config import LinkConfig
from companion.mavlink.signing import SigningPolicy

log = logging.getLogger(__name__)


class Disconnected(Exception):
    """The connection broke (socket closed or reset, device gone): close it, the link reopens it later."""


def default_factory(conn_str: str, baud: int, source_system: int, source_component: int):
    # retries=0: one TCP connect attempt (pymavlink would otherwise sleep between retries inside poll)
    return mavutil.mavlink_connection(conn_str, baud=baud, source_system=source_system,
                                      source_component=source_component, autoreconnect=False, retries=0)


class LogLimiter:
    """Log the first occurrence of a key at WARNING, then at most every ``period`` s with a count."""

    def __init__(self, logger: logging.Logger, period: float = 10.0):
        self.log = logger
        self.period = period
        self._last: dict[str, float] = {}
        self._suppressed: collections.Counter[str] = collections.Counter()

    def warn(self, key: str, now: float, fmt: str, *args) -> None:
        last = self._last.get(key)
        if last is None or now - last >= self.period or now < last:
            extra = self._suppressed.pop(key, 0)
            self._last[key] = now
            self.log.warning(fmt + (f" (+{extra} more since last report)" if extra else ""), *args)
        else:
            self._suppressed[key] += 1


class Connection:
    """The pymavlink connection of one :class:`~companion.mavlink.link.MavLink` (see module docstring).

    ``conn`` is the pymavlink connection, None while closed; :attr:`open_error` says why the latest
    attempt to open it failed ("" after a success).
    """

    def __init__(self, conn_str: str, config: LinkConfig, counters: collections.Counter, logs: LogLimiter,
                 clock: Callable[[], float], factory: Callable[..., Any] | None = None, *,
                 signing_key: bytes | None = None, signing_policy: SigningPolicy | None = None, signing_link_id: int = 0):
        self.conn_str = conn_str
        self.config = config
        self.counters = counters
        self._logs = logs
        self._clock = clock
        self._factory = factory or default_factory
        self._signing_key = signing_key
        self.signing_policy = signing_policy
        self._signing_link_id = signing_link_id
        self.udp_peers: collections.OrderedDict[Any, float] = collections.OrderedDict()  # udpin: address -> last heard
        self.rx_addr = None  # sender of the datagram being parsed (udpin)
        self.last_open_try = -math.inf
        # serial and tcp are reopened while the vehicle is silent; a UDP socket only if it fails
        self.reopenable = conn_str.startswith("tcp:") or ":" not in conn_str
        self.open_error = ""  # why the latest attempt to open the connection failed ("" after a success)
        self.conn = None

    @property
    def datagram(self) -> bool:
        """Each read is one datagram (UDP, or a connection that says so), parsed on its own."""
        return isinstance(self.conn, mavutil.mavudp) or bool(getattr(self.conn, "mavlink_datagrams", False))

    def set_source_system(self, sysid: int) -> None:
        """The system id we send with from now on."""
        if self.conn is not None:
            self.conn.mav.srcSystem = sysid

    # -- opening and closing ------------------------------------------------------------------
    def open(self, now: float, source_system: int, first: bool = False) -> bool:
        """Open the connection with our ids (``source_system``, the link's component); False (counted,
        logged, :attr:`open_error` set) when it cannot be opened now.  ``first``: a missing module or a
        malformed connection string is a :class:`ConfigError` instead (a setup error, not a flaky link)."""
        self.last_open_try = now
        src = source_system
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
        self.conn = conn
        self.open_error = ""
        self.udp_peers.clear()
        self.reopenable = isinstance(conn, (mavutil.mavserial, mavutil.mavtcp))
        if not first:
            self.counters["reconnects"] += 1
            log.info("reopened %s", self.conn_str)
        return True

    def close(self) -> None:
        conn, self.conn = self.conn, None
        if conn is not None:
            try:
                conn.close()
            except Exception:  # already broken: nothing to do
                pass

    def fail(self, now: float, why: str) -> None:
        """The connection broke: count and log it, and close it (the link reopens it)."""
        self.counters["transport_errors"] += 1
        self._logs.warn("transport", now, "%s: %s", self.conn_str, why)
        self.close()  # reopened by MavLink._service every reconnect_interval_s

    # -- reading ------------------------------------------------------------------------------
    def read(self) -> bytes:
        """What is available now (b"" if nothing); :class:`Disconnected` when the connection broke."""
        conn = self.conn
        if isinstance(conn, mavutil.mavtcp):
            if conn.port is None:
                raise Disconnected("socket closed")
            try:
                data = conn.port.recv(4096)
            except (BlockingIOError, InterruptedError):
                return b""
            except OSError as exc:
                raise Disconnected(str(exc)) from None
            if not data:
                raise Disconnected("connection closed by peer")
            return data
        if isinstance(conn, mavutil.mavserial):
            try:
                return bytes(conn.port.read(4096))
            except Exception as exc:  # serial.SerialException when the device vanishes
                raise Disconnected(str(exc)) from None
        self.rx_addr = None
        try:
            if isinstance(conn, mavutil.mavudp) and conn.udp_server:
                # read the socket ourselves: pymavlink's recv() would add every sender to the set of
                # addresses it sends to (unbounded, and random bytes from anyone would redirect our traffic);
                # a sender becomes a peer only through register_peer
                data, self.rx_addr = conn.port.recvfrom(65535)
            else:
                data = conn.recv(4096)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                return b""
            raise Disconnected(str(exc)) from None
        return bytes(data) if data else b""

    def register_peer(self, addr, now: float) -> None:
        """udpin: ``addr`` sent valid MAVLink from the vehicle: send to it (at most ``max_udp_peers``)."""
        conn = self.conn
        if addr is None or not (isinstance(conn, mavutil.mavudp) and conn.udp_server):
            return
        peers = self.udp_peers
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

    def reset_parser(self) -> None:
        mav = self.conn.mav
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2

    def parse(self, data: bytes, datagram: bool) -> list:
        """The messages in ``data`` (``datagram``: one UDP datagram, parsed on its own)."""
        mav = self.conn.mav
        if datagram and mav.buf_len() > 0:
            # a packet cut short in the previous datagram: MAVLink over UDP never spans datagrams
            self.counters["rx_truncated"] += 1
            self.reset_parser()
        try:
            out = mav.parse_buffer(data) or []
        except Exception as exc:  # robust_parsing turns errors into BAD_DATA; anything else is a parser bug
            self.counters["rx_parser_errors"] += 1
            self._logs.warn("parser", self._clock(), "MAVLink parser error: %r", exc)
            self.reset_parser()
            return []
        if datagram and mav.buf_len() > 0:
            self.counters["rx_truncated"] += 1
            self.reset_parser()
        return out


    # -- sending ------------------------------------------------------------------------------
    def write(self, buf: bytes) -> None:
        """Write a packed message; :class:`Disconnected` when the connection broke."""
        conn = self.conn
        if isinstance(conn, mavutil.mavtcp):
            if conn.port is None:
                raise Disconnected("socket closed")
            try:
                conn.port.sendall(buf)
            except (BlockingIOError, InterruptedError):
                self.counters["tx_dropped_busy"] += 1
            except OSError as exc:
                raise Disconnected(str(exc)) from None
        elif isinstance(conn, mavutil.mavserial):
            try:
                conn.port.write(buf)
            except Exception as exc:
                raise Disconnected(str(exc)) from None
        else:
            conn.write(buf)

