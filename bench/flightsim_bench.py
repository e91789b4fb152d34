"""Simulator figures for the benchmark report: renderer speed, dynamics speed, export throughput."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from companion.core.camera import CameraConfig

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ("seed004_straight", "quad_approach", "fixedwing_pass")


def run_all(frames: int = 120, dynamics_s: float = 60.0) -> dict:
    from flightsim.dynamics.bench import cases, realtime_factor
    from flightsim.fly import fly
    from flightsim.render import RenderOptions
    from flightsim.render.bench import bench_world, measure_fps
    from flightsim.scenario import load_scenario

    world = bench_world(20)
    cam = CameraConfig.from_fov(640, 480, 60.0)
    res: dict = {
        "render_640x480_20_obstacles_fps": measure_fps(world, cam, frames=frames),
        "render_640x480_20_obstacles_cpu_fps": measure_fps(world, cam, frames=frames, cpu_time=True),
        "render_320x240_20_obstacles_fps": measure_fps(world, CameraConfig.from_fov(320, 240, 60.0), frames=frames),
        "render_distortion_fps": measure_fps(world, CameraConfig.from_fov(640, 480, 60.0, distortion=(-0.25, 0.08, 0.0, 0.0, 0.0)), frames=frames),
        "render_blur4_fps": measure_fps(world, cam, RenderOptions(exposure_s=0.01, max_blur_subframes=4), frames=frames, motion=True),
        "obstacles": len(world.obstacles),
        "dynamics_realtime": {name: realtime_factor(make(), dynamics_s) for name, make in cases().items()},
        "fly": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        for name in SCENARIOS:
            sc = load_scenario(ROOT / "configs" / "scenarios" / f"{name}.toml")
            t0 = time.perf_counter()
            r = fly(sc, Path(tmp) / name, plot=False)
            res["fly"][name] = {"flight_s": r.duration_s, "frames": r.frames, "resolution": f"{sc.camera.width}×{sc.camera.height}",
                                "wall_s": time.perf_counter() - t0, "realtime": r.duration_s / (time.perf_counter() - t0)}
    return res


def markdown(res: dict) -> str:
    lines = [
        "One core (OpenCV threads = 1).",
        "",
        "| renderer | frames/s |",
        "|---|---:|",
        f"| 640×480, {res['obstacles']} obstacles, ground and sky (target ≥ 60) | {res['render_640x480_20_obstacles_fps']:.1f} "
        f"(by CPU time {res['render_640x480_20_obstacles_cpu_fps']:.1f}) |",
        f"| 320×240, same world | {res['render_320x240_20_obstacles_fps']:.1f} |",
        f"| 640×480 with lens distortion | {res['render_distortion_fps']:.1f} |",
        f"| 640×480 with motion blur (≤ 4 sub-frames) | {res['render_blur4_fps']:.1f} |",
        "",
        "| JSBSim flight (dynamics + our autopilot, state read at 30 Hz) | × real time |",
        "|---|---:|",
    ]
    for name, f in res["dynamics_realtime"].items():
        lines.append(f"| {name} | {f:.0f} |")
    lines += ["", "| `flightsim fly` (dynamics, rendering, truth, export) | flight | frames | wall time | × real time |",
              "|---|---:|---:|---:|---:|"]
    for name, f in res["fly"].items():
        lines.append(f"| {name} ({f['resolution']}) | {f['flight_s']:g} s | {f['frames']} | {f['wall_s']:.1f} s | {f['realtime']:.1f} |")
    return "\n".join(lines)
