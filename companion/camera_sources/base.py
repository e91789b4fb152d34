"""What every camera source shares (see :mod:`companion.camera_sources` for the whole package;
frames: docs/derivations/frames.md).

* :class:`CameraSourceConfig` — the ``[camera_source]`` table: how frames are acquired;
* :class:`Frame` ``(index, t, gray)``, :class:`SourceStatus` and :class:`SourceError`;
* :func:`check_gray` — a usable image or the reason it is rejected (empty, corrupt, dtype, wrong_size);
* :func:`parse_camera_spec` — what a ``--camera`` argument names (device, URL, file, ``sim://``);
* :class:`FrameSource` — the base class: a one-slot buffer for live sources (the newest frame
  wins, older ones are counted ``dropped``) or pull mode for offline ones, the counters behind
  :class:`SourceStatus`, and the "camera lost" / "camera restored" events for STATUSTEXT;
* :class:`RateLog` and :class:`Backoff` — rate-limited warnings and the reopen delays the live
  sources share.
"""

from __future__ import annotations

import abc
import collections
import dataclasses
import logging
import math
import re
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple

import cv2
import numpy as np

from companion.config import require, require_finite
from companion.errors import ConfigError


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


class RateLog:
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
        self._rlog = RateLog()
        self._size_error: str | None = None

    # -- for subclasses --------------------------------------------------------------------------
    def _reject(self, reason: str, detail: str = "", log_it: bool = True) -> None:
        with self._cv:
            self._rejected[reason] += 1
            if detail:
                self._error = f"{reason}: {detail}"
        if log_it:
            self._rlog.warn("reject_" + reason, "camera %s: frame rejected (%s)%s", self.name, reason, f": {detail}" if detail else "")

    def _wrong_size(self, width: int, height: int) -> None:
        """Reject a frame of another size than configured.  If no good frame came before, the
        configuration does not fit the camera: :attr:`size_error` says so once (a STATUSTEXT event
        too) and the caller stops; later (the camera changed mode in flight) each is rejected and
        logged at most every 10 s, like any bad frame."""
        with self._cv:
            never_good = self._frames == 0
        # before any good frame the size error is said once (below): a reader thread that reads on before the caller
        # stops only counts its frames (under load it logged one more); counted and its detail kept before the caller
        # is woken, so what it reads is complete
        self._reject("wrong_size", f"got {width}×{height}, configured {self.width}×{self.height}", log_it=not never_good)
        if never_good:
            with self._cv:
                if self._size_error is None:
                    self._size_error = (f"camera {self.name} delivers {width}×{height} frames but the [camera] table "
                                        f"says {self.width}×{self.height}: configure the camera's own resolution and "
                                        "intrinsics (--config, --camera-config or --calibration)")
                    self._events.append((_SEV_ERROR, f"Camera {width}x{height}, config {self.width}x{self.height}"))
                    self._cv.notify_all()

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


class Backoff:
    """Reopen delays of a live source: ``lo`` first, doubled after each failed attempt up to ``hi``; :meth:`reset` after a success."""

    def __init__(self, lo: float, hi: float):
        self.lo, self.hi = lo, hi
        self.delay = lo

    def next(self) -> float:
        d = self.delay
        self.delay = min(self.hi, self.delay * 2.0)
        return d

    def reset(self) -> None:
        self.delay = self.lo


# ---------------------------------------------------------------------- camera specification --
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
