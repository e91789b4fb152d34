"""Timing of the image front end: Harris, NCC per track and a full TrackManager step.

Pure functions that return numbers (no printing); ``bench`` formats them.  Every
measurement runs on one core (``cv2.setNumThreads(1)``, restored afterwards), on a synthetic
textured scene that moves by about one pixel per frame, and reports the median over ``repeats``
of ``time.perf_counter`` differences.  Target: Harris + NCC ≤ 5 ms per 640×480 frame
with 300 tracks on one core.

The scene is band-limited noise rendered by area-averaging a 4× supersampled image, so a shift
by a multiple of 1/4 px is an exact sub-pixel translation of the same continuous texture.
"""

from __future__ import annotations

import contextlib
import time
from typing import Callable, Iterator

import cv2
import numpy as np

from companion.core.camera import CameraConfig, CameraModel
from companion.core.harris import HarrisConfig, detect_harris
from companion.core.ncc import NCCConfig, match_ncc
from companion.core.tracks import TrackConfig, TrackManager

#: Per-frame motion of the timing scene (px): about one pixel, not on the integer grid.
MOTION_PX = (0.75, 0.5)


class TextureScene:
    """A seeded band-limited texture that can be rendered at any shift that is a multiple of 1/ss px."""

    def __init__(self, width: int, height: int, seed: int = 0, margin: int = 64, supersample: int = 4, blur_px: float = 1.2):
        rng = np.random.default_rng(seed)
        ss = supersample
        big = rng.standard_normal(((height + 2 * margin) * ss, (width + 2 * margin) * ss)).astype(np.float32)
        big = cv2.GaussianBlur(big, (0, 0), blur_px * ss)
        big = (big - big.mean()) / big.std()
        self._big = big
        self.width, self.height, self.margin, self.ss = width, height, margin, ss

    def render(self, shift: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """uint8 frame whose content is the base frame moved by ``shift`` = (du, dv) px."""
        ss, mg = self.ss, self.margin
        sx, sy = int(round(shift[0] * ss)), int(round(shift[1] * ss))
        if abs(sx) > mg * ss or abs(sy) > mg * ss:
            raise ValueError(f"shift {shift} exceeds the scene margin of {mg} px")
        y0, x0 = mg * ss - sy, mg * ss - sx
        crop = self._big[y0 : y0 + self.height * ss, x0 : x0 + self.width * ss]
        img = cv2.resize(crop, (self.width, self.height), interpolation=cv2.INTER_AREA)
        return np.clip(128.0 + 45.0 * img, 0, 255).round().astype(np.uint8)


@contextlib.contextmanager
def _one_core() -> Iterator[None]:
    prev = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(prev)


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up (allocations, OpenCV lazy initialisation)
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def time_harris(width: int = 640, height: int = 480, repeats: int = 20) -> float:
    """Milliseconds per full-frame :func:`detect_harris` (default config, 300 corners)."""
    img = TextureScene(width, height).render()
    cfg = HarrisConfig()
    with _one_core():
        return 1e3 * _median_time(lambda: detect_harris(img, cfg), repeats)


def time_ncc_per_track(n_tracks: int = 300, repeats: int = 20, width: int = 640, height: int = 480) -> float:
    """Microseconds per track of :func:`match_ncc` (default config, ~1 px motion, Harris corners)."""
    scene = TextureScene(width, height)
    a, b = scene.render(), scene.render(MOTION_PX)
    pts, _ = detect_harris(a, HarrisConfig(max_corners=n_tracks))
    if len(pts) == 0:
        raise RuntimeError("the timing scene produced no corners")
    cfg = NCCConfig()
    with _one_core():
        return 1e6 * _median_time(lambda: match_ncc(a, b, pts, pts, cfg), repeats) / len(pts)


def _camera(width: int, height: int) -> CameraModel:
    return CameraModel(CameraConfig.from_fov(width, height, 60.0))


def time_frontend(
    width: int = 640,
    height: int = 480,
    n_tracks: int = 300,
    repeats: int = 5,
    frames: int = 20,
    predicted_radius_px: float | None = None,
) -> float:
    """Milliseconds per frame of :meth:`TrackManager.step` with ``n_tracks`` tracks.

    Each repeat builds a manager, fills it on a first frame (not timed) and times ``frames``
    steps of the scene moving by :data:`MOTION_PX` per frame; the result is the median over
    repeats of the mean step time.  Harris runs inside a step only when tracks must be refilled,
    so this is the steady-state (amortized) cost; :func:`frontend_timings` also reports the
    worst case of a frame that runs a full Harris detection.

    ``predicted_radius_px=None``: no prediction, every track searched in the default ±8 px
    window.  A number: a telemetry-style predictor (the known motion, as the epipolar
    prediction of :mod:`companion.core.prediction` would give) with that search radius.
    """
    scene = TextureScene(width, height, margin=max(64, int(frames * max(MOTION_PX)) + 8))
    imgs = [scene.render((k * MOTION_PX[0], k * MOTION_PX[1])) for k in range(frames + 1)]
    cam = _camera(width, height)
    predict = None
    if predicted_radius_px is not None:
        motion = np.array(MOTION_PX)

        def predict(uv: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, float]:
            return uv + motion, float(predicted_radius_px)

    per_frame = []
    with _one_core():
        for _ in range(max(1, repeats)):
            tm = TrackManager(cam, HarrisConfig(max_corners=n_tracks), NCCConfig(), TrackConfig(max_tracks=n_tracks))
            tm.step(imgs[0], 0.0, 0)
            t0 = time.perf_counter()
            for k in range(1, frames + 1):
                tm.step(imgs[k], k / 30.0, k, predict=predict)
            per_frame.append((time.perf_counter() - t0) / frames)
    return 1e3 * float(np.median(per_frame))


def time_ncc_predicted_per_track(n_tracks: int = 300, repeats: int = 20, radius_px: float = 3.0) -> float:
    """Microseconds per track of :func:`match_ncc` with a telemetry-style prediction (± ``radius_px``)."""
    scene = TextureScene(640, 480)
    a, b = scene.render(), scene.render(MOTION_PX)
    pts, _ = detect_harris(a, HarrisConfig(max_corners=n_tracks))
    pred = pts + np.array(MOTION_PX)
    cfg = NCCConfig()
    with _one_core():
        return 1e6 * _median_time(lambda: match_ncc(a, b, pts, pred, cfg, radius_px), repeats) / len(pts)


def frontend_timings(repeats: int = 10) -> dict[str, float]:
    """All front-end figures of the front-end timing benchmark, as a flat dict of numbers.

    ``*_predicted_*`` figures use a ±3 px window around a telemetry-style prediction (the
    intended operating mode); the others search the default ±8 px window around the previous
    position (no telemetry).  ``harris_plus_ncc_300_*`` add a full-frame Harris detection to
    matching 300 tracks: the worst frame, one that refills every track.
    """
    harris_640 = time_harris(640, 480, repeats)
    harris_320 = time_harris(320, 240, repeats)
    ncc_us = time_ncc_per_track(300, repeats)
    ncc_pred_us = time_ncc_predicted_per_track(300, repeats, 3.0)
    n = max(3, repeats // 2)
    return {
        "harris_640x480_ms": harris_640,
        "harris_320x240_ms": harris_320,
        "ncc_per_track_us": ncc_us,
        "ncc_predicted_per_track_us": ncc_pred_us,
        "frontend_640x480_300_tracks_ms": time_frontend(640, 480, 300, n),
        "frontend_640x480_300_tracks_predicted_ms": time_frontend(640, 480, 300, n, predicted_radius_px=3.0),
        "frontend_320x240_300_tracks_predicted_ms": time_frontend(320, 240, 300, n, predicted_radius_px=3.0),
        "harris_plus_ncc_300_ms": harris_640 + ncc_us * 300 / 1e3,
        "harris_plus_ncc_300_predicted_ms": harris_640 + ncc_pred_us * 300 / 1e3,
    }
