"""The monitor's thin I/O layer: listen on a MAVLink connection and show the companion.

:func:`open_connection` (pymavlink, robust parsing; files refused), :class:`Reader` (non-blocking
reads, one datagram parsed on its own, parser errors counted, never raised) and
:func:`run_monitor` (rich ``Live`` at ~5 Hz on a terminal; otherwise a text or JSON snapshot every
``interval`` seconds, or one snapshot with ``once``).  A GCS HEARTBEAT is sent once a second
unless ``passive`` (a ``udpout:`` companion output only learns where to send once it hears one).
:func:`cmd_monitor` is ``companion monitor``.  Everything it shows comes from :mod:`.state` and :mod:`.view`.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable

from companion.mavlink.dialect import mavlink, mavutil  # first: MAVLink 2 + ardupilotmega
from companion.errors import ConfigError
from companion.monitor.state import MonitorConfig, MonitorState, Snapshot
from companion.monitor.view import render, render_text

log = logging.getLogger(__name__)


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
