"""A recorded flight as a camera source: ``video.avi`` + ``frames.csv`` (``index,t_s``), for ``companion replay``.

:func:`read_frames_csv` reads and checks the frame times; :class:`RecordedSource` returns the
video's frames in file order, stamped on the recording's clock (the clock its tlog shares), never
dropping one.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import os
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from companion.camera_sources.base import CameraSourceConfig, Frame, FrameSource, SourceError
from companion.camera_sources.opencv import default_capture
from companion.io.inputs import check_input_file, read_input_text

log = logging.getLogger(__name__)


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
        self._cap = (capture_factory or default_capture)("file", vp, CameraSourceConfig())
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
