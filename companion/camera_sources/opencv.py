"""``cv2.VideoCapture`` frames: :class:`OpenCVSource` on a camera device, a network stream or a video file.

Devices (``0``, ``/dev/video0``: V4L2) are asked for the configured resolution, frame rate and a
one-frame buffer; URLs (``rtsp://…``, ``http://…``) open through FFmpeg with open / read timeouts
(another backend, e.g. a GStreamer build, takes the URL as it is); all of them are read by a
thread that reopens a stalled or lost source with backoff.  A file plays paced like a live
camera (``file_pacing = "realtime"``) or, with ``"fast"``, in pull mode stamped with its own
timeline.  :func:`default_capture` opens the capture (:class:`~companion.camera_sources.recorded.RecordedSource`
uses it too; tests inject fakes instead).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any, Callable

import cv2

from companion.camera_sources.base import Backoff, CameraSourceConfig, Frame, FrameSource, SourceError, parse_camera_spec

log = logging.getLogger(__name__)


def _has_ffmpeg() -> bool:
    try:
        return cv2.CAP_FFMPEG in cv2.videoio_registry.getStreamBackends()
    except Exception:  # very old OpenCV: assume it is there
        return True


def default_capture(kind: str, value: Any, config: CameraSourceConfig):
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
        self._factory = capture_factory or default_capture
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
        backoff = Backoff(cfg.reconnect_min_s, cfg.reconnect_max_s)
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
