"""Camera sources: grey frames with their capture time on the companion's clock (frames: docs/derivations/frames.md).

Every source is a :class:`FrameSource`.  It hands out :class:`Frame` tuples ``(index, t, gray)``:

* ``index`` — the source's own frame counter (strictly increasing; a gap means frames were lost
  or dropped before the pipeline saw them);
* ``t`` — the capture (mid-exposure) time in seconds on the companion's monotonic clock, the clock
  the MAVLink link maps the autopilot's ``time_boot_ms`` onto through TIMESYNC (for
  :class:`RecordedSource`: the recording's clock, which its tlog shares);
* ``gray`` — a C-contiguous ``uint8`` array of the configured ``height × width``.

A live source never queues: :meth:`FrameSource.read` returns the newest frame not yet returned
and counts the older ones it skipped as ``dropped`` (a late frame is worth less than a fresh one,
docs/derivations/sectors.md).  Corrupt, empty or wrongly sized images are rejected and counted by reason in
:attr:`SourceStatus.rejected`, never raised.  Live sources that stop delivering are reopened with
exponential backoff; :meth:`FrameSource.drain_events` reports "camera lost" / "camera restored"
for STATUSTEXT.

Sources
-------
:class:`OpenCVSource`
    ``cv2.VideoCapture`` on a device index (``0``), a device path (``/dev/video0``), a URL
    (``rtsp://…``, ``http://…/stream.mjpg``) or a video file.  The capture time is the moment
    ``grab()`` returned on the companion clock minus ``capture_latency_s`` (exposure + transfer
    delay of the camera, measured once per camera model).  Files play either paced at their frame
    rate like a live camera (``file_pacing = "realtime"``, stamped when delivered) or as fast as
    they are read (``"fast"``, stamped with the file's own timeline from the moment it was opened).
:class:`SimFrameSource` / :class:`SimFrameServer`
    The simulator's frame transport over TCP on loopback, ``sim://127.0.0.1:5600`` (protocol below).
:class:`RecordedSource`
    A recorded flight: ``video.avi`` + ``frames.csv`` (``index,t_s``), for replay.

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

import abc
import collections
import csv
import dataclasses
import io
import logging
import math
import os
import re
import select
import socket
import struct
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple

import cv2
import numpy as np

from companion.config import require, require_finite
from companion.errors import ConfigError
from companion.io.inputs import check_input_file, read_input_text

log = logging.getLogger(__name__)

# MAV_SEVERITY values (kept numeric here so this module does not import pymavlink)
_SEV_ERROR = 3
_SEV_WARNING = 4
_SEV_NOTICE = 5
_SEV_INFO = 6


# ---------------------------------------------------------------------- configuration ----------
@dataclasses.dataclass(frozen=True)
class CameraSourceConfig:
    """The ``[camera_source]`` table: how frames are acquired (intrinsics stay in ``[camera]``)."""

    capture_latency_s: float = 0.0  # exposure-to-delivery delay subtracted from the arrival time, s (measure it per camera)
    file_pacing: str = "realtime"  # video files: "realtime" (paced at the file's rate, stamped when delivered) or "fast"
    file_fps: float = 0.0  # frame rate of video files; 0 = the rate stored in the file (30 if it has none)
    device_fps: float = 0.0  # frame rate asked of a camera device; 0 = the device's default
    request_resolution: bool = True  # ask a camera device for [camera] width × height
    buffer_size: int = 1  # capture buffer length asked of the backend (1 = newest frame; not every backend obeys)
    open_timeout_s: float = 5.0  # network streams: give up opening after this long
    read_timeout_s: float = 2.0  # network streams: a read blocking longer than this fails
    stall_timeout_s: float = 2.0  # a live source that delivers nothing for this long is reopened, s
    reconnect_min_s: float = 0.5  # first reopen delay after a live source dropped, s ...
    reconnect_max_s: float = 8.0  # ... doubled after each failed attempt up to this, s
    sim_max_pixels: int = 16_777_216  # simulator transport: frames larger than this are a protocol error

    def __post_init__(self) -> None:
        require_finite("capture_latency_s", self.capture_latency_s, nonnegative=True)
        require(self.capture_latency_s < 1.0, f"capture_latency_s must be < 1 s, got {self.capture_latency_s}")
        require(self.file_pacing in ("realtime", "fast"), f"file_pacing must be 'realtime' or 'fast', got {self.file_pacing!r}")
        require_finite("file_fps", self.file_fps, nonnegative=True)
        require_finite("device_fps", self.device_fps, nonnegative=True)
        require(isinstance(self.request_resolution, bool), "request_resolution must be true or false")
        require(isinstance(self.buffer_size, int) and not isinstance(self.buffer_size, bool) and self.buffer_size >= 0,
                f"buffer_size must be an integer >= 0, got {self.buffer_size!r}")
        for name in ("open_timeout_s", "read_timeout_s", "stall_timeout_s", "reconnect_min_s", "reconnect_max_s"):
            require_finite(name, getattr(self, name), positive=True)
        require(self.reconnect_max_s >= self.reconnect_min_s, "reconnect_max_s must be >= reconnect_min_s")
        require(isinstance(self.sim_max_pixels, int) and self.sim_max_pixels >= 1, "sim_max_pixels must be a positive integer")


# ---------------------------------------------------------------------- frames and status -----
class Frame(NamedTuple):
    """One camera frame: unpacks as ``index, t, gray``."""

    index: int
    t: float  # capture time, s (companion clock; recording clock for RecordedSource)
    gray: np.ndarray  # (height, width) uint8, C-contiguous


@dataclasses.dataclass(frozen=True)
class SourceStatus:
    name: str  # what was opened (device, URL, file, sim address)
    kind: str  # "device" | "url" | "file" | "sim" | "recorded" | other
    connected: bool  # frames are arriving (live) / the file is open
    ended: bool  # a finite source reached its end (or was closed)
    frames: int  # good frames produced
    delivered: int  # frames handed to the caller
    dropped: int  # good frames overwritten by a newer one before the caller read them
    rejected: dict[str, int]  # bad frames by reason (empty, corrupt, wrong_size, dtype, no_clock, protocol, bad_time)
    reconnects: int  # successful reopenings after a loss
    last_frame_t: float | None  # companion-clock time of the newest good frame
    error: str  # the latest problem, "" if none


class SourceError(ConfigError):
    """A camera source specification that cannot work (missing file, malformed address)."""


def check_gray(img: Any, width: int, height: int) -> tuple[np.ndarray | None, str]:
    """``(gray, "ok")`` for a usable image, else ``(None, reason)``.

    Colour (BGR / BGRA) is converted to grey; anything else that is not ``uint8`` of exactly
    ``height × width`` is rejected: ``empty`` (None / no pixels), ``corrupt`` (not an image array),
    ``dtype`` (not 8-bit), ``wrong_size`` (another resolution — the intrinsics would not apply).
    """
    if img is None:
        return None, "empty"
    if not isinstance(img, np.ndarray):
        return None, "corrupt"
    if img.size == 0:
        return None, "empty"
    if img.dtype != np.uint8:
        return None, "dtype"
    if img.ndim == 3:
        ch = img.shape[2]
        try:
            if ch == 1:
                img = img[:, :, 0]
            elif ch == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            elif ch == 4:
                img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
            else:
                return None, "corrupt"
        except cv2.error:
            return None, "corrupt"
    elif img.ndim != 2:
        return None, "corrupt"
    if img.shape != (height, width):
        return None, "wrong_size"
    return np.ascontiguousarray(img), "ok"


class _RateLog:
    """Warn once per key and then at most every ``period`` seconds."""

    def __init__(self, period: float = 10.0):
        self.period = period
        self._last: dict[str, float] = {}

    def warn(self, key: str, fmt: str, *args) -> None:
        now = time.monotonic()
        last = self._last.get(key)
        if last is None or now - last >= self.period:
            self._last[key] = now
            log.warning(fmt, *args)


# ---------------------------------------------------------------------- base class ------------
class FrameSource(abc.ABC):
    """Base of every source (see module docstring).

    Subclasses either run a reader thread that calls :meth:`_publish` (live sources: the newest
    frame waits in a one-slot buffer) or implement :meth:`_pull` (offline sources: the caller's
    :meth:`read` produces the next frame itself, nothing is ever dropped).
    """

    kind = "source"

    def __init__(self, name: str, width: int, height: int, clock: Callable[[], float] = time.monotonic):
        require(isinstance(width, int) and width > 0 and isinstance(height, int) and height > 0,
                f"frame size must be positive integers, got {width}×{height}")
        self.name = name
        self.width = width
        self.height = height
        self.clock = clock
        self._cv = threading.Condition()
        self._slot: Frame | None = None
        self._frames = 0
        self._delivered = 0
        self._dropped = 0
        self._rejected: collections.Counter[str] = collections.Counter()
        self._reconnects = 0
        self._connected = False
        self._ended = False
        self._closed = False
        self._last_frame_t: float | None = None
        self._error = ""
        self._events: collections.deque[tuple[int, str]] = collections.deque(maxlen=32)
        self._was_connected = False
        self._rlog = _RateLog()
        self._size_error: str | None = None

    # -- for subclasses --------------------------------------------------------------------------
    def _reject(self, reason: str, detail: str = "") -> None:
        with self._cv:
            self._rejected[reason] += 1
            if detail:
                self._error = f"{reason}: {detail}"
        self._rlog.warn("reject_" + reason, "camera %s: frame rejected (%s)%s", self.name, reason, f": {detail}" if detail else "")

    def _wrong_size(self, width: int, height: int) -> None:
        """Reject a frame of another size than configured.  If no good frame came before, the
        configuration does not fit the camera: :attr:`size_error` says so once (a STATUSTEXT event
        too) and the caller stops; later (the camera changed mode in flight) each is rejected and
        logged at most every 10 s, like any bad frame."""
        with self._cv:
            first = self._frames == 0 and self._size_error is None
            if first:
                self._size_error = (f"camera {self.name} delivers {width}×{height} frames but the [camera] table says "
                                    f"{self.width}×{self.height}: configure the camera's own resolution and intrinsics "
                                    "(--config, --camera-config or --calibration)")
                self._events.append((_SEV_ERROR, f"Camera {width}x{height}, config {self.width}x{self.height}"))
                self._rejected["wrong_size"] += 1
                self._cv.notify_all()
        if not first:
            self._reject("wrong_size", f"got {width}×{height}, configured {self.width}×{self.height}")

    def _accept(self, index: int, t: float, img: Any) -> Frame | None:
        """Validate an image; returns the frame (counted) or None (rejected, counted)."""
        gray, why = check_gray(img, self.width, self.height)
        if gray is None:
            if why == "wrong_size":
                self._wrong_size(img.shape[1], img.shape[0])
            else:
                self._reject(why)
            return None
        if not math.isfinite(t):
            self._reject("bad_time")
            return None
        with self._cv:
            self._frames += 1
            self._last_frame_t = t
        return Frame(int(index), float(t), gray)

    def _publish(self, frame: Frame) -> None:
        with self._cv:
            old, self._slot = self._slot, frame
            if old is not None:
                self._dropped += 1
            self._cv.notify_all()
        if old is not None:
            self._superseded(old)

    def _superseded(self, frame: Frame) -> None:
        """``frame`` was overwritten by a newer one before the caller read it (hook; see SimFrameSource)."""

    def _set_connected(self, connected: bool, why: str = "") -> None:
        with self._cv:
            if connected == self._connected:
                return
            self._connected = connected
            if connected:
                if self._was_connected:
                    self._reconnects += 1
                    self._events.append((_SEV_NOTICE, "Camera restored"))
                    log.info("camera %s restored", self.name)
                else:
                    log.info("camera %s open", self.name)
                self._was_connected = True
                self._error = ""
            else:
                if why:
                    self._error = why
                if self._was_connected and not self._closed:
                    self._events.append((_SEV_WARNING, "Camera lost" + (f": {why}"[:38] if why else "")))
                    log.warning("camera %s lost%s", self.name, f": {why}" if why else "")
            self._cv.notify_all()

    def _set_ended(self) -> None:
        with self._cv:
            self._ended = True
            self._connected = False
            self._cv.notify_all()

    def _pull(self) -> Frame | None:  # pragma: no cover - overridden by pull sources
        """Pull sources: produce the next frame (None = nothing now / end, see ``ended``)."""
        return None

    _pull_mode = False

    # -- public ----------------------------------------------------------------------------------
    def read(self, timeout: float = 0.0) -> Frame | None:
        """The newest frame not yet returned, waiting up to ``timeout`` s; None if none (or ended)."""
        if self._pull_mode:
            while True:
                if self._ended or self._closed:
                    return None
                f = self._pull()
                if f is not None:
                    with self._cv:
                        self._delivered += 1
                    return f
                if self._ended:
                    return None
        deadline = time.monotonic() + max(0.0, timeout)
        with self._cv:
            while self._slot is None and not self._closed and not self._ended:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cv.wait(remaining)
            f, self._slot = self._slot, None
            if f is not None:
                self._delivered += 1
            return f

    def __iter__(self) -> Iterator[Frame]:
        """Every frame until the source ends or is closed (blocking)."""
        while True:
            f = self.read(timeout=0.5)
            if f is not None:
                yield f
            elif self.ended or self._closed:
                return

    def done(self, frame: Frame, status: str = "processed") -> None:
        """The caller has finished with ``frame`` ("processed", "dropped", "rejected")."""

    def drain_events(self) -> list[tuple[int, str]]:
        """(MAV_SEVERITY, text) of state changes since the last call (for STATUSTEXT)."""
        with self._cv:
            out = list(self._events)
            self._events.clear()
            return out

    @property
    def ended(self) -> bool:
        return self._ended

    @property
    def connected(self) -> bool:
        return self._connected

    @property
    def last_frame_t(self) -> float | None:
        return self._last_frame_t

    @property
    def size_error(self) -> str | None:
        """Set when the source's first frame had another size than configured (a configuration
        error: the intrinsics do not apply); None otherwise."""
        return self._size_error

    def status(self) -> SourceStatus:
        with self._cv:
            return SourceStatus(self.name, self.kind, self._connected, self._ended, self._frames, self._delivered,
                                self._dropped, dict(self._rejected), self._reconnects, self._last_frame_t, self._error)

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _Backoff:
    def __init__(self, lo: float, hi: float):
        self.lo, self.hi = lo, hi
        self.delay = lo

    def next(self) -> float:
        d = self.delay
        self.delay = min(self.hi, self.delay * 2.0)
        return d

    def reset(self) -> None:
        self.delay = self.lo


# ---------------------------------------------------------------------- OpenCV ----------------
def parse_camera_spec(spec: str) -> tuple[str, Any]:
    """``(kind, value)`` of a camera argument: ``("device", 0)``, ``("device", "/dev/video0")``,
    ``("url", "rtsp://…")``, ``("sim", ("127.0.0.1", 5600))`` or ``("file", Path)``."""
    if not isinstance(spec, str) or not spec.strip():
        raise SourceError("camera source is empty")
    s = spec.strip()
    if re.fullmatch(r"\d+", s):
        return "device", int(s)
    if s.startswith("/dev/"):
        return "device", s
    if s.lower().startswith("sim://"):
        m = re.fullmatch(r"sim://\[?([^\]/]+?)\]?:(\d+)/?", s, flags=re.IGNORECASE)
        if not m or not 0 < int(m.group(2)) < 65536:
            raise SourceError(f"simulator frame address {s!r} must look like sim://127.0.0.1:5600")
        return "sim", (m.group(1), int(m.group(2)))
    if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*://", s):
        return "url", s
    p = Path(s)
    if p.is_dir():
        raise SourceError(f"camera source {s!r}: is a directory, not a video file")
    if not p.is_file():
        raise SourceError(f"camera source {s!r}: no such video file (or give a device index, /dev/videoN, a URL or sim://HOST:PORT)")
    return "file", p


def _has_ffmpeg() -> bool:
    try:
        return cv2.CAP_FFMPEG in cv2.videoio_registry.getStreamBackends()
    except Exception:  # very old OpenCV: assume it is there
        return True


def _default_capture(kind: str, value: Any, config: CameraSourceConfig):
    if kind == "url":
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(config.open_timeout_s * 1000),
                  cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(config.read_timeout_s * 1000)]
        if _has_ffmpeg():
            return cv2.VideoCapture(value, cv2.CAP_FFMPEG, params)
        return cv2.VideoCapture(value)  # another backend (e.g. GStreamer builds) takes the URL as it is
    if kind == "file":
        return cv2.VideoCapture(str(value))
    return cv2.VideoCapture(value)


class OpenCVSource(FrameSource):
    """``cv2.VideoCapture`` source: device, URL or video file (see module docstring).

    ``capture_factory(kind, value, config)`` opens the capture (tests inject fakes); it must
    return an object with ``isOpened``, ``grab``, ``retrieve``, ``get``, ``set`` and ``release``.
    """

    def __init__(self, spec: str, width: int, height: int, config: CameraSourceConfig = CameraSourceConfig(),
                 clock: Callable[[], float] = time.monotonic, capture_factory: Callable | None = None,
                 start: bool = True):
        kind, value = parse_camera_spec(spec)
        if kind == "sim":
            raise SourceError("sim:// addresses are served by SimFrameSource (use open_source)")
        super().__init__(str(value), width, height, clock)
        self.kind = kind
        self.value = value
        self.config = config
        self._factory = capture_factory or _default_capture
        self._cap = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._index = 0
        self._file_fps = 0.0
        self._t_open: float | None = None
        self._pull_mode = kind == "file" and config.file_pacing == "fast"
        if kind == "file":
            # a file that OpenCV cannot decode is a usage error, found now rather than in the loop
            if not self._open():
                raise SourceError(f"camera source {value}: OpenCV cannot open this video file")
        if start and not self._pull_mode:
            self.start()

    # -- opening ---------------------------------------------------------------------------------
    def _open(self) -> bool:
        cfg = self.config
        try:
            cap = self._factory(self.kind, self.value, cfg)
        except Exception as exc:  # a backend exception is a failed attempt, not a crash
            self._error = f"open failed: {exc}"
            return False
        if cap is None or not cap.isOpened():
            if cap is not None:
                try:
                    cap.release()
                except Exception:
                    pass
            self._error = "open failed"
            return False
        if self.kind == "device":
            try:
                if cfg.request_resolution:
                    cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
                    cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
                if cfg.device_fps > 0:
                    cap.set(cv2.CAP_PROP_FPS, cfg.device_fps)
                if cfg.buffer_size > 0:
                    cap.set(cv2.CAP_PROP_BUFFERSIZE, cfg.buffer_size)
            except Exception:  # properties are hints; a backend that refuses them is still usable
                pass
        elif self.kind == "url" and cfg.buffer_size > 0:
            try:
                cap.set(cv2.CAP_PROP_BUFFERSIZE, cfg.buffer_size)
            except Exception:
                pass
        if self.kind == "file":
            fps = cfg.file_fps
            if fps <= 0:
                try:
                    fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
                except Exception:
                    fps = 0.0
            self._file_fps = fps if math.isfinite(fps) and 0 < fps < 1000 else 30.0
        self._cap = cap
        self._t_open = self.clock()
        return True

    def _release(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            try:
                cap.release()
            except Exception:
                pass

    # -- one frame -------------------------------------------------------------------------------
    def _grab_one(self) -> tuple[bool, Frame | None]:
        """(grab succeeded, frame or None if rejected)."""
        cap = self._cap
        try:
            ok = bool(cap.grab())
        except Exception as exc:
            self._error = f"grab failed: {exc}"
            ok = False
        if not ok:
            return False, None
        t_arrival = self.clock()
        pos_ms = None
        if self._pull_mode:
            try:
                pos_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
            except Exception:
                pos_ms = None
        try:
            ok, img = cap.retrieve()
        except Exception as exc:  # a decoder error on one frame
            self._reject("corrupt", str(exc)[:80])
            return True, None
        if not ok:
            self._reject("corrupt", "retrieve failed")
            return True, None
        self._index += 1
        if self._pull_mode:
            t = self._t_open + (pos_ms / 1000.0 if pos_ms is not None and math.isfinite(pos_ms) and pos_ms >= 0
                                else (self._index - 1) / self._file_fps)
        else:
            t = t_arrival - self.config.capture_latency_s
        return True, self._accept(self._index - 1, t, img)

    # -- pull mode (files as fast as possible) ------------------------------------------------------
    def _pull(self) -> Frame | None:
        if self._cap is None:
            self._set_ended()
            return None
        self._set_connected(True)
        ok, frame = self._grab_one()
        if not ok:
            self._release()
            self._set_ended()
            return None
        return frame

    # -- reader thread -------------------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is None and not self._pull_mode:
            self._thread = threading.Thread(target=self._run, name=f"camera:{self.name}", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        cfg = self.config
        backoff = _Backoff(cfg.reconnect_min_s, cfg.reconnect_max_s)
        last_good = self.clock()
        next_due: float | None = None
        try:
            while not self._stop.is_set():
                if self._cap is None:
                    if self.kind == "file":
                        self._set_ended()
                        return
                    if self._open():
                        backoff.reset()
                        last_good = self.clock()
                    else:
                        self._set_connected(False, self._error or "cannot open")
                        delay = backoff.next()
                        self._rlog.warn("open", "camera %s: cannot open (%s); retrying in %.1f s", self.name,
                                        self._error or "open failed", delay)
                        self._stop.wait(delay)
                        continue
                if self.kind == "file":  # pace like a live camera
                    now = time.monotonic()
                    period = 1.0 / self._file_fps
                    if next_due is None:
                        next_due = now
                    if now < next_due:
                        self._stop.wait(next_due - now)
                        if self._stop.is_set():
                            return
                    next_due = max(next_due + period, time.monotonic() - period)
                ok, frame = self._grab_one()
                now = self.clock()
                if ok:
                    if frame is not None:
                        last_good = now
                        self._set_connected(True)
                        self._publish(frame)
                    elif now - last_good > cfg.stall_timeout_s:
                        self._reopen(f"only bad frames for {now - last_good:.1f} s")
                    continue
                if self.kind == "file":
                    log.info("camera %s: end of file after %d frames", self.name, self._index)
                    self._release()
                    self._set_ended()
                    return
                # a live source failed to grab: short retries, then reopen
                if now - last_good > cfg.stall_timeout_s:
                    self._reopen(f"no frame for {now - last_good:.1f} s")
                    last_good = self.clock()
                    self._stop.wait(backoff.next())
                else:
                    self._stop.wait(0.01)
        except Exception as exc:  # pragma: no cover - the thread must never die silently
            log.exception("camera %s reader failed: %r", self.name, exc)
            self._set_connected(False, f"reader failed: {exc!r}")

    def _reopen(self, why: str) -> None:
        self._set_connected(False, why)
        self._release()

    def close(self) -> None:
        self._stop.set()
        super().close()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)
        self._release()
        with self._cv:
            self._ended = True


# ---------------------------------------------------------------------- recorded flights -------
def read_frames_csv(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """``(index, t_s)`` arrays of a ``frames.csv`` (header ``index,t_s``); ConfigError naming the problem."""
    p = Path(path)
    text = read_input_text(p, "frames file", error=SourceError)
    idx: list[int] = []
    ts: list[float] = []
    try:
        rows = list(csv.reader(io.StringIO(text, newline="")))
    except csv.Error as exc:
        raise SourceError(f"{p}: not a frames file ({exc})") from None
    header = rows[0] if rows else None
    if header is None or [h.strip() for h in header[:2]] != ["index", "t_s"]:
        raise SourceError(f"{p}: first line must be the header 'index,t_s', got {header!r}")
    for line_no, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        try:
            i, t = int(row[0]), float(row[1])
        except (ValueError, IndexError):
            raise SourceError(f"{p}:{line_no}: expected 'index,t_s', got {row!r}") from None
        if not math.isfinite(t):
            raise SourceError(f"{p}:{line_no}: capture time is not finite")
        idx.append(i)
        ts.append(t)
    if not idx:
        raise SourceError(f"{p}: no frames listed")
    return np.asarray(idx, np.int64), np.asarray(ts, float)


class RecordedSource(FrameSource):
    """Replay of ``video.avi`` + ``frames.csv``: row k of the CSV stamps the k-th video frame.

    Frames are returned in file order, never dropped; ``t`` is on the recording's clock.  A row
    whose index or time does not increase is rejected (``bad_time``); if the video and the CSV
    disagree in length, the shorter one wins (logged).
    """

    kind = "recorded"

    def __init__(self, video: str | os.PathLike, frames_csv: str | os.PathLike, width: int, height: int,
                 capture_factory: Callable | None = None):
        vp = check_input_file(video, "video file", error=SourceError)
        super().__init__(str(vp), width, height, clock=time.monotonic)
        self.index, self.t = read_frames_csv(frames_csv)
        self._cap = (capture_factory or _default_capture)("file", vp, CameraSourceConfig())
        if self._cap is None or not self._cap.isOpened():
            raise SourceError(f"{vp}: OpenCV cannot open this video file")
        try:
            n_video = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            self.video_size = (int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH) or 0), int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT) or 0))
        except Exception:
            n_video, self.video_size = 0, (0, 0)
        if n_video > 0 and n_video != len(self.index):
            log.warning("%s has %d frames but %s lists %d: using the first %d", vp, n_video, frames_csv, len(self.index),
                        min(n_video, len(self.index)))
        self.n_frames = min(n_video, len(self.index)) if n_video > 0 else len(self.index)
        self._k = 0
        self._last_idx: int | None = None
        self._last_t: float | None = None
        self._pull_mode = True
        self._set_connected(True)

    def __len__(self) -> int:
        return self.n_frames

    def _pull(self) -> Frame | None:
        while self._k < len(self.index):
            k = self._k
            self._k += 1
            try:
                ok, img = self._cap.read()
            except Exception as exc:
                self._reject("corrupt", str(exc)[:80])
                continue
            if not ok:
                if k < len(self.index):
                    log.warning("%s ended after %d frames (frames.csv lists %d)", self.name, k, len(self.index))
                break
            i, t = int(self.index[k]), float(self.t[k])
            if (self._last_idx is not None and i <= self._last_idx) or (self._last_t is not None and t <= self._last_t):
                self._reject("bad_time", f"row {k}: index {i}, t {t:.6f} does not increase")
                continue
            f = self._accept(i, t, img)
            if f is None:
                continue
            self._last_idx, self._last_t = i, t
            return f
        self._set_ended()
        try:
            self._cap.release()
        except Exception:
            pass
        return None

    def close(self) -> None:
        super().close()
        try:
            self._cap.release()
        except Exception:
            pass


# ---------------------------------------------------------------------- simulator transport -----
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
        backoff = _Backoff(cfg.reconnect_min_s, cfg.reconnect_max_s)
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


# ---------------------------------------------------------------------- factory ---------------
def open_source(spec: str, width: int, height: int, config: CameraSourceConfig = CameraSourceConfig(),
                clock: Callable[[], float] = time.monotonic,
                clock_map: Callable[[float], float | None] | None = None) -> FrameSource:
    """The source for a ``--camera`` argument (device index, /dev/videoN, URL, file, sim://HOST:PORT)."""
    kind, _ = parse_camera_spec(spec)
    if kind == "sim":
        return SimFrameSource(spec, width, height, config, clock=clock, clock_map=clock_map)
    return OpenCVSource(spec, width, height, config, clock=clock)


__all__ = [
    "CameraSourceConfig", "Frame", "FrameSource", "SourceStatus", "SourceError", "OpenCVSource", "RecordedSource",
    "SimFrameSource", "SimFrameServer", "open_source", "parse_camera_spec", "check_gray", "read_frames_csv",
    "pack_sim_header", "CLOCK_AUTOPILOT_BOOT", "CLOCK_HOST_MONOTONIC", "ACK_PROCESSED", "ACK_DROPPED", "ACK_REJECTED",
]
