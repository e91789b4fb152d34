"""The simulator frame transport: :class:`SimFrameSource` (the companion, client) and
:class:`SimFrameServer` (the simulator, ``flightsim sitl``), frames: docs/derivations/frames.md.

Simulator frame transport (``sim://HOST:PORT``), version 1
---------------------------------------------------------
The simulator (``flightsim``) is the TCP server (:class:`SimFrameServer`); the companion connects
as the client (:class:`SimFrameSource`) and reconnects with backoff while the server is away, so
either side may start first.  The server accepts one client at a time (a new client replaces the
old one).  All integers little-endian.  Each frame is a 40-byte header followed by the pixels:

====== ====== ========== =========================================================================
offset size   type       field
====== ====== ========== =========================================================================
0      4      bytes      magic ``b"MRFR"``
4      2      uint16     version = 1
6      2      uint16     header length = 40 (a reader skips any extra header bytes)
8      8      uint64     frame index (strictly increasing)
16     8      int64      capture time (mid-exposure), nanoseconds, on the clock named by ``clock``
24     1      uint8      clock: 1 = the autopilot's boot clock (the clock of ``time_boot_ms`` in the
                         simulated ATTITUDE and of its TIMESYNC ``tc1`` replies); 2 = the receiving
                         host's CLOCK_MONOTONIC (``time.monotonic_ns()`` of the same machine)
25     1      uint8      pixel format: 1 = GRAY8
26     2      uint16     reserved, 0
28     4      uint32     width, px
32     4      uint32     height, px
36     4      uint32     payload length = width × height
40     …      bytes      pixels, row-major, no padding
====== ====== ========== =========================================================================

Clock mapping: with clock 1 the receiver maps the stamp onto its own clock with the function it is
given (the companion passes the TIMESYNC mapping, ``t_companion = t_boot + offset``), exactly as
it maps ATTITUDE stamps — so frames and telemetry are aligned by the same estimate.  Frames that
arrive before the mapping exists are rejected (``no_clock``).  Clock 2 needs no mapping (sender
and receiver on one host, e.g. a real-time SITL).

Acknowledgement (receiver → server), 16 bytes: magic ``b"MRAK"``, uint16 version = 1, uint8
status (0 = processed, 1 = dropped as stale, 2 = rejected), uint8 reserved, uint64 frame index.
The companion sends one after it has finished with each frame, so a lockstep simulator can wait
for it (:meth:`SimFrameServer.wait_ack`) before advancing its clock.
"""

from __future__ import annotations

import logging
import select
import socket
import struct
import threading
import time
from typing import Callable

import numpy as np

from companion.camera_sources.base import Backoff, CameraSourceConfig, Frame, FrameSource, SourceError, parse_camera_spec

log = logging.getLogger(__name__)


SIM_MAGIC = b"MRFR"
SIM_ACK_MAGIC = b"MRAK"
SIM_VERSION = 1
SIM_HEADER = struct.Struct("<4sHHQqBBHIII")  # 40 bytes
SIM_ACK = struct.Struct("<4sHBBQ")  # 16 bytes
CLOCK_AUTOPILOT_BOOT = 1
CLOCK_HOST_MONOTONIC = 2
PIXEL_GRAY8 = 1
ACK_PROCESSED, ACK_DROPPED, ACK_REJECTED = 0, 1, 2
_ACK_CODES = {"processed": ACK_PROCESSED, "dropped": ACK_DROPPED, "rejected": ACK_REJECTED}

assert SIM_HEADER.size == 40 and SIM_ACK.size == 16


def pack_sim_header(index: int, t_ns: int, width: int, height: int, clock: int = CLOCK_AUTOPILOT_BOOT) -> bytes:
    return SIM_HEADER.pack(SIM_MAGIC, SIM_VERSION, SIM_HEADER.size, int(index), int(t_ns), int(clock), PIXEL_GRAY8, 0,
                           int(width), int(height), int(width) * int(height))


class _ProtocolError(Exception):
    pass


_SOCK_BUF = 1 << 22  # frame transport socket buffers: a whole frame fits, the sender never waits for the reader


def _recv_exact(sock: socket.socket, n: int, stop: threading.Event) -> bytes | None:
    """n bytes, or None when the peer closed / we are stopping; socket timeouts just retry."""
    buf = bytearray(n)
    return bytes(buf) if _recv_into(sock, memoryview(buf), stop) else None


def _recv_into(sock: socket.socket, view: memoryview, stop: threading.Event) -> bool:
    """Fill ``view`` from the socket (no intermediate copies); False when the peer closed / we are stopping."""
    got, n = 0, len(view)
    while got < n:
        if stop.is_set():
            return False
        try:
            k = sock.recv_into(view[got:], n - got)
        except socket.timeout:
            continue
        except OSError:
            return False
        if not k:
            return False
        got += k
    return True


class SimFrameSource(FrameSource):
    """Receiver of the simulator frame transport (see module docstring).

    ``clock_map(t_boot_s) -> t_companion | None`` maps clock-1 stamps (the companion passes the
    TIMESYNC mapping of its autopilot link); without it clock-1 frames are rejected ``no_clock``.
    """

    kind = "sim"

    def __init__(self, address: str, width: int, height: int, config: CameraSourceConfig = CameraSourceConfig(),
                 clock: Callable[[], float] = time.monotonic, clock_map: Callable[[float], float | None] | None = None,
                 start: bool = True):
        kind, value = parse_camera_spec(address)
        if kind != "sim":
            raise SourceError(f"{address!r} is not a sim://HOST:PORT address")
        super().__init__(address, width, height, clock)
        self.host, self.port = value
        self.config = config
        self.clock_map = clock_map
        self._sock: socket.socket | None = None
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_index: int | None = None
        self.acks_sent = 0
        if start:
            self.start()

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"simframes:{self.port}", daemon=True)
            self._thread.start()

    def _connect(self) -> socket.socket | None:
        s = None
        try:
            infos = socket.getaddrinfo(self.host, self.port, 0, socket.SOCK_STREAM)
            af, kind, proto, _, addr = infos[0]
            s = socket.socket(af, kind, proto)
            try:  # before connect, so the receive window can open to a whole frame at once
                s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _SOCK_BUF)
            except OSError:
                pass
            s.settimeout(self.config.open_timeout_s)
            s.connect(addr)
        except OSError as exc:
            if s is not None:
                s.close()
            self._error = f"connect failed: {exc}"
            return None
        s.settimeout(0.2)
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return s

    def _run(self) -> None:
        cfg = self.config
        backoff = Backoff(cfg.reconnect_min_s, cfg.reconnect_max_s)
        while not self._stop.is_set():
            sock = self._connect()
            if sock is None:
                self._set_connected(False, self._error)
                delay = backoff.next()
                self._rlog.warn("connect", "simulator frames %s: %s; retrying in %.1f s", self.name, self._error, delay)
                self._stop.wait(delay)
                continue
            with self._send_lock:
                self._sock = sock
            self._last_index = None  # a restarted simulator may count from 0 again
            backoff.reset()
            self._set_connected(True)
            why = "connection closed by the simulator"
            try:
                self._receive(sock)
            except _ProtocolError as exc:
                why = f"protocol error: {exc}"
                self._reject("protocol", str(exc))
            except Exception as exc:  # pragma: no cover - never let the reader die
                why = f"reader error: {exc!r}"
                log.exception("simulator frame reader failed")
            with self._send_lock:
                self._sock = None
            try:
                sock.close()
            except OSError:
                pass
            if self._stop.is_set():
                break
            self._set_connected(False, why)
            self._stop.wait(backoff.next())

    def _receive(self, sock: socket.socket) -> None:
        while not self._stop.is_set():
            raw = _recv_exact(sock, SIM_HEADER.size, self._stop)
            if raw is None:
                return
            magic, version, hlen, index, t_ns, clk, fmt, _res, w, h, n = SIM_HEADER.unpack(raw)
            if magic != SIM_MAGIC:
                raise _ProtocolError(f"bad magic {magic!r}")
            if version != SIM_VERSION:
                raise _ProtocolError(f"unsupported version {version}")
            if hlen < SIM_HEADER.size or hlen > 4096:
                raise _ProtocolError(f"bad header length {hlen}")
            if hlen > SIM_HEADER.size and _recv_exact(sock, hlen - SIM_HEADER.size, self._stop) is None:
                return
            if n != w * h or n > self.config.sim_max_pixels:
                raise _ProtocolError(f"payload of {n} bytes for {w}×{h}")
            payload = np.empty(n, np.uint8)  # the frame's own buffer (handed on to the consumer)
            if n and not _recv_into(sock, memoryview(payload), self._stop):
                return
            if fmt != PIXEL_GRAY8:
                self._reject("corrupt", f"pixel format {fmt}")
                self._ack_code(index, ACK_REJECTED)
                continue
            if n == 0:
                self._reject("empty", f"got {w}×{h}, configured {self.width}×{self.height}")
                self._ack_code(index, ACK_REJECTED)
                continue
            if (w, h) != (self.width, self.height):
                self._wrong_size(w, h)
                self._ack_code(index, ACK_REJECTED)
                continue
            if self._last_index is not None and index <= self._last_index:
                self._reject("bad_time", f"frame index {index} after {self._last_index}")
                self._ack_code(index, ACK_REJECTED)
                continue
            t_s = t_ns * 1e-9
            if clk == CLOCK_AUTOPILOT_BOOT:
                t = self.clock_map(t_s) if self.clock_map is not None else None
                if t is None:
                    self._reject("no_clock", "autopilot clock not synchronised yet")
                    self._ack_code(index, ACK_REJECTED)
                    continue
            elif clk == CLOCK_HOST_MONOTONIC:
                t = t_s
            else:
                self._reject("corrupt", f"unknown clock {clk}")
                self._ack_code(index, ACK_REJECTED)
                continue
            img = payload.reshape(h, w)
            frame = self._accept(index, t, img)
            if frame is None:
                self._ack_code(index, ACK_REJECTED)
                continue
            self._last_index = index
            self._publish(frame)

    def _ack_code(self, index: int, code: int) -> None:
        with self._send_lock:
            sock = self._sock
            if sock is None:
                return
            try:
                sock.sendall(SIM_ACK.pack(SIM_ACK_MAGIC, SIM_VERSION, code, 0, int(index)))
                self.acks_sent += 1
            except OSError:
                pass  # the reader notices the broken connection

    def done(self, frame: Frame, status: str = "processed") -> None:
        self._ack_code(frame.index, _ACK_CODES.get(status, ACK_PROCESSED))

    def _superseded(self, frame: Frame) -> None:
        self._ack_code(frame.index, ACK_DROPPED)  # every frame is acknowledged, also one nobody read

    def close(self) -> None:
        self._stop.set()
        super().close()
        with self._send_lock:
            sock = self._sock
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)
        with self._cv:
            self._ended = True


class SimFrameServer:
    """Sender of the simulator frame transport (used by flightsim's SITL; see module docstring).

    ``SimFrameServer(port=0)`` listens on 127.0.0.1 (an ephemeral port; :attr:`address` gives
    ``sim://127.0.0.1:PORT``).  :meth:`send` writes one frame to the connected client (False if
    none is connected or the write failed); :meth:`wait_ack` blocks until the client acknowledged a
    frame (lockstep).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, send_timeout_s: float = 2.0):
        self._lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._lsock.bind((host, port))
        self._lsock.listen(2)
        self._lsock.settimeout(0.1)
        self.host, self.port = self._lsock.getsockname()[:2]
        self.send_timeout_s = send_timeout_s
        self._client: socket.socket | None = None
        self._cv = threading.Condition()
        self._acks: dict[int, int] = {}
        self._stop = threading.Event()
        self.frames_sent = 0
        self.clients = 0
        self._accept_thread = threading.Thread(target=self._accept_loop, name=f"simserver:{self.port}", daemon=True)
        self._accept_thread.start()

    @property
    def address(self) -> str:
        return f"sim://{self.host}:{self.port}"

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._lsock.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            conn.settimeout(self.send_timeout_s)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            try:
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SOCK_BUF)
            except OSError:
                pass
            with self._cv:
                old, self._client = self._client, conn
                self.clients += 1
                self._acks.clear()
                self._cv.notify_all()
            if old is not None:
                try:
                    old.close()
                except OSError:
                    pass
            threading.Thread(target=self._ack_loop, args=(conn,), daemon=True).start()

    def _ack_loop(self, conn: socket.socket) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([conn], [], [], 0.1)
                if not r:
                    continue
                chunk = conn.recv(4096)
            except (OSError, ValueError):
                break
            if not chunk:
                break
            buf += chunk
            while len(buf) >= SIM_ACK.size:
                magic, version, status, _r, index = SIM_ACK.unpack(buf[:SIM_ACK.size])
                buf = buf[SIM_ACK.size:]
                if magic != SIM_ACK_MAGIC or version != SIM_VERSION:
                    buf = b""
                    break
                with self._cv:
                    self._acks[index] = status
                    if len(self._acks) > 4096:
                        for k in sorted(self._acks)[:2048]:
                            del self._acks[k]
                    self._cv.notify_all()
        with self._cv:
            if self._client is conn:
                self._client = None
            self._cv.notify_all()

    @property
    def connected(self) -> bool:
        return self._client is not None

    def wait_client(self, timeout: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout
        with self._cv:
            while self._client is None:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cv.wait(remaining)
            return True

    def send(self, gray: np.ndarray, index: int, t_ns: int, clock: int = CLOCK_AUTOPILOT_BOOT) -> bool:
        """Send one GRAY8 frame captured at ``t_ns`` (on ``clock``); False if no client took it."""
        img = np.ascontiguousarray(gray, dtype=np.uint8)
        if img.ndim != 2:
            raise ValueError(f"gray must be a 2-D uint8 image, got shape {img.shape}")
        h, w = img.shape
        return self._send_parts(pack_sim_header(index, t_ns, w, h, clock), memoryview(img).cast("B"))

    def send_raw(self, data: bytes) -> bool:
        """Write raw bytes to the client (tests use it for malformed frames)."""
        return self._send_parts(data)

    def _send_parts(self, *parts) -> bool:
        with self._cv:
            conn = self._client
        if conn is None:
            return False
        try:
            _sendall_parts(conn, parts)
        except OSError:
            with self._cv:
                if self._client is conn:
                    self._client = None
            try:
                conn.close()
            except OSError:
                pass
            return False
        self.frames_sent += 1
        return True

    def wait_ack(self, index: int, timeout: float = 1.0) -> int | None:
        """Status the client acknowledged ``index`` with (ACK_*), or None on timeout / no client."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while index not in self._acks:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._client is None:
                    return None
                self._cv.wait(min(remaining, 0.1))
            return self._acks[index]

    def disconnect_client(self) -> None:
        """Drop the current client (it will reconnect)."""
        with self._cv:
            conn, self._client = self._client, None
        if conn is not None:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            conn.close()

    def close(self) -> None:
        self._stop.set()
        self.disconnect_client()
        try:
            self._lsock.close()
        except OSError:
            pass
        self._accept_thread.join(timeout=1.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _sendall_parts(conn: socket.socket, parts) -> None:
    """``sendall`` of the concatenated ``parts`` without concatenating them (one ``sendmsg`` as a rule)."""
    views = [memoryview(p).cast("B") for p in parts if len(p)]
    while views:
        sent = conn.sendmsg(views)
        while views and sent >= len(views[0]):
            sent -= len(views[0])
            views.pop(0)
        if views and sent:
            views[0] = views[0][sent:]
