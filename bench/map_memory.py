"""Memory of the local obstacle map over a long hover in front of a wall (docs/derivations/obstacle_map.md).

A synthetic feed (:class:`bench.latency.SyntheticFlight`'s textured wall, exact telemetry):
the vehicle approaches the wall from 20 m to 5 m at 1.5 m/s, then hovers 5 m in front of it for
``minutes`` of simulated time, wandering on a 0.3 m circle every 8 s as a real hover does (enough
parallax for new tracks to converge and enter the map all the time, the worst case for its size).
The whole pipeline runs (tracks, estimator, map, sectors) one frame at a time at ``fps``.  Sampled
once per simulated minute: the points held by the map, the process's resident set (VmRSS), and
whether the forward sector still holds the wall.  Pass: the map never exceeds its cap, RSS grows by
less than ``rss_tolerance_mb`` from minute 2 to the end, and the wall stays ranged while hovering.

``python -m bench.map_memory --minutes 30 --fps 5``
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time

import numpy as np

from bench.latency import SyntheticFlight, _one_core, feed_telemetry
from companion.core.camera import CameraConfig

APPROACH_S = 10.0
WANDER_R_M = 0.3
WANDER_PERIOD_S = 8.0


@dataclasses.dataclass
class HoverFlight(SyntheticFlight):
    """Approach to 5 m from the wall (x = 20 m), then a hover that wanders on a small circle."""

    def position(self, t: float) -> np.ndarray:
        p0 = np.asarray(self.start_ned, float)
        if t <= APPROACH_S:
            return p0 + np.array([1.5 * t, 0.0, 0.0])
        w = 2 * math.pi / WANDER_PERIOD_S
        a = w * (t - APPROACH_S)
        return p0 + np.array([1.5 * APPROACH_S, WANDER_R_M * math.sin(a), -WANDER_R_M * (1 - math.cos(a))])

    def velocity_at(self, t: float) -> np.ndarray:
        if t <= APPROACH_S:
            return np.array([1.5, 0.0, 0.0])
        w = 2 * math.pi / WANDER_PERIOD_S
        a = w * (t - APPROACH_S)
        return np.array([0.0, WANDER_R_M * w * math.cos(a), -WANDER_R_M * w * math.sin(a)])

    def local_position_fields(self, t: float):
        p, v = self.position(t), self.velocity_at(t)
        return (float(p[0]), float(p[1]), float(p[2]), float(v[0]), float(v[1]), float(v[2]))


def rss_mb() -> float:
    """Resident set size of this process now (Linux /proc), MB."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


def run(minutes: float = 30.0, fps: float = 5.0, rss_tolerance_mb: float = 20.0, seed: int = 0, progress=None) -> dict:
    """Fly the hover and sample the map and memory once per simulated minute (module docstring)."""
    from companion.camera_sources import Frame
    from companion.io.config_files import CompanionConfig
    from companion.pipeline import Pipeline, PipelineConfig
    from companion.telemetry import TelemetryBuffer

    cam = CameraConfig.from_fov(320, 240, 60.0)
    cfg = dataclasses.replace(CompanionConfig(), camera=cam)
    flight = HoverFlight(camera=cam, wall_north_m=20.0, start_ned=(0.0, 0.0, -10.0), velocity_ned=(0.0, 0.0, 0.0),
                         noise_sigma=1.0, seed=seed)
    tel = TelemetryBuffer(cfg.telemetry)
    tel.set_clock_offset(0.0)
    pipe = Pipeline(cam, cfg, PipelineConfig(), tel)
    cap = cfg.map.max_landmarks
    total_s = APPROACH_S + minutes * 60.0
    n_frames = int(total_s * fps)
    samples: list[dict] = []
    map_max = 0
    hover_frames = hover_fwd = 0
    fed = 0.0
    t_next_sample = 60.0
    wall0 = time.perf_counter()
    prev = _one_core()
    try:
        for k in range(n_frames):
            t = 1.0 + k / fps
            now = t + 0.021
            feed_telemetry(tel, flight, fed, now)
            fed = now
            res = pipe.process(Frame(k, t, flight.render(t)), now)
            n_map = len(pipe.map) if pipe.map is not None else 0
            map_max = max(map_max, n_map)
            if t - 1.0 > APPROACH_S + 2.0:
                hover_frames += 1
                if res.ok and res.sectors is not None and res.sectors.state[0] == 1:
                    hover_fwd += 1
            if t - 1.0 >= t_next_sample or k == n_frames - 1:
                samples.append({"minute": round((t - 1.0) / 60.0, 2), "map": n_map, "rss_mb": round(rss_mb(), 1),
                                "remembered": res.n_remembered, "tracks": res.n_tracks})
                t_next_sample += 60.0
                if progress:
                    progress(samples[-1])
    finally:
        import cv2

        cv2.setNumThreads(prev)
    wall = time.perf_counter() - wall0
    after2 = [s["rss_mb"] for s in samples if s["minute"] >= 2.0]
    growth = (after2[-1] - after2[0]) if len(after2) >= 2 else math.nan
    return {
        "minutes": minutes, "fps": fps, "frames": n_frames, "cap": cap, "map_max": map_max,
        "map_final": samples[-1]["map"] if samples else 0, "rss_growth_mb": growth, "rss_tolerance_mb": rss_tolerance_mb,
        "forward_ranged_while_hovering": hover_fwd / hover_frames if hover_frames else math.nan,
        "samples": samples, "wall_s": wall,
        "ok": bool(map_max <= cap and math.isfinite(growth) and growth <= rss_tolerance_mb),
    }


def markdown(r: dict) -> str:
    mark = "✓" if r["ok"] else "✗"
    lines = [
        f"Synthetic hover 5 m in front of a textured wall for {r['minutes']:g} min of simulated time (after a 10 s approach), "
        f"{r['fps']:g} frames/s through the whole pipeline, wandering on a 0.3 m circle (new tracks converge and enter the map "
        f"all the time). Command: `python -m bench.map_memory --minutes {r['minutes']:g} --fps {r['fps']:g}` "
        f"({r['wall_s']:.0f} s wall).",
        "",
        f"- map points: at most {r['map_max']} (cap {r['cap']}), {r['map_final']} at the end",
        f"- resident memory growth from minute 2 to the end: {r['rss_growth_mb']:+.1f} MB (tolerance {r['rss_tolerance_mb']:g} MB) {mark}",
        f"- forward sector holding the wall while hovering: {100 * r['forward_ranged_while_hovering']:.1f} % of frames",
        "",
        "| minute | map points | remembered | tracks | RSS MB |",
        "|---|---|---|---|---|",
    ]
    for s in r["samples"]:
        lines.append(f"| {s['minute']:g} | {s['map']} | {s['remembered']} | {s['tracks']} | {s['rss_mb']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    import argparse
    import json

    ap = argparse.ArgumentParser(prog="python -m bench.map_memory",
                                 description="Map size and resident memory over a long hover in front of a wall (synthetic feed).")
    ap.add_argument("--minutes", type=float, default=30.0, help="simulated hover time, minutes (default 30)")
    ap.add_argument("--fps", type=float, default=5.0, help="frames per simulated second (default 5)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of markdown")
    a = ap.parse_args(argv)
    r = run(a.minutes, a.fps, progress=lambda s: print(f"  minute {s['minute']:g}: map {s['map']} points, RSS {s['rss_mb']} MB",
                                                        file=sys.stderr, flush=True))
    print(json.dumps(r, indent=2) if a.json else markdown(r))
    return 0 if r["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
