"""A short synthetic flight through the whole pipeline, for tests that compare compiled kernels
with their numpy reference on the inputs the pipeline really produces (imported by test modules).

The vehicle flies past a textured wall (``bench.latency.SyntheticFlight``) and yaws fast enough that
the wall leaves the view: the local obstacle map then holds remembered points out of view, the
sectors claim them over 360°, and the tracker's predictions cover a turning camera.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def fly(frames: int = 60, width: int = 320, height: int = 240, max_tracks: int = 150, yaw_rate_rad_s: float = 0.5,
        roll_pitch: bool = True):
    """Run the shipped configuration on ``frames`` frames; returns the pipeline's results.

    With ``roll_pitch`` the flight's attitude rocks (±6° roll, ±4° pitch), so levelled sectors and
    tilted cameras are exercised.  Test code hooks the pipeline's functions (monkeypatch) before calling.
    """
    import math

    import numpy as np

    from bench.latency import SyntheticFlight, feed_telemetry
    from companion.camera_sources import Frame
    from companion.core.camera import CameraConfig
    from companion.io.config_files import load_companion_config
    from companion.pipeline import Pipeline, PipelineConfig
    from companion.telemetry import TelemetryBuffer

    class Rocking(SyntheticFlight):
        def rpy(self, t):
            r, p, y = super().rpy(t)
            if not roll_pitch:
                return r, p, y
            return math.radians(6.0) * math.sin(1.3 * t), math.radians(4.0) * math.sin(0.9 * t + 0.5), y

        def rates(self):
            return 0.0, 0.0, self.yaw_rate_rad_s

    base = load_companion_config(ROOT / "configs" / "companion.toml")
    cam = CameraConfig.from_fov(width, height, 60.0)
    cfg = dataclasses.replace(base, camera=cam, tracks=dataclasses.replace(base.tracks, max_tracks=max_tracks),
                              harris=dataclasses.replace(base.harris, max_corners=max_tracks))
    flight = Rocking(camera=cam, wall_north_m=25.0, start_ned=(0.0, 0.0, -3.0), velocity_ned=(3.0, 1.0, -0.3),
                     yaw_rate_rad_s=yaw_rate_rad_s, noise_sigma=1.0, seed=3)
    tel = TelemetryBuffer(cfg.telemetry)
    tel.set_clock_offset(0.0)
    pipe = Pipeline(cam, cfg, PipelineConfig(), tel)
    results, fed = [], 0.0
    for k in range(frames):
        t = 1.0 + k / 30.0
        now = t + 0.021
        feed_telemetry(tel, flight, fed, now)
        fed = now
        results.append(pipe.process(Frame(k, t, flight.render(t)), now))
    assert all(r.ok for r in results[1:]), [r.reason for r in results if not r.ok]
    return results
