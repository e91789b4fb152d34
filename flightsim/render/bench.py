"""Renderer speed: frames per second at 640×480 with 20 obstacles on one core.

``python -m flightsim.render.bench [--frames N] [--width W --height H] [--obstacles M]`` prints
the frame rate of a quad flying a street at 10 m between buildings, masts, trees and walls
(ground textured, 60° lens), for the ideal camera and with each optional effect switched on.
``cv2.setNumThreads(1)`` keeps OpenCV on one core; numpy's element-wise work is single-threaded.
"""

from __future__ import annotations

import argparse
import math
import time

import cv2
import numpy as np

from companion.core.camera import CameraConfig
from companion.core.frames import euler_zyx_to_R

from ..world.config import BoxConfig, CylinderConfig, GroundConfig, WallConfig, WorldConfig
from ..world.geometry import World
from .renderer import Renderer, RenderOptions


def bench_world(n_obstacles: int = 20, seed: int = 1) -> World:
    """A street 300 m long: buildings on both sides, masts and trees along it, walls across plots.

    Obstacles cycle box, box, cylinder (mast), box, cylinder (tree), wall; they stand beside the
    path the benchmark flies (north along east = 0, 10 m up), spread over 30–330 m ahead.
    """
    rng = np.random.default_rng(seed)
    boxes, cyls, walls = [], [], []
    kinds = ["box", "box", "mast", "box", "tree", "wall"]
    for i in range(n_obstacles):
        kind = kinds[i % len(kinds)]
        n = 30.0 + 300.0 * (i + 0.5) / n_obstacles + rng.uniform(-5, 5)
        side = -1.0 if i % 2 else 1.0
        if kind == "box":
            w = rng.uniform(12, 25)
            boxes.append(BoxConfig(centre_ne_m=(n, side * (12 + w / 2)), size_m=(rng.uniform(10, 25), w), height_m=rng.uniform(12, 40), yaw_deg=rng.uniform(-10, 10)))
        elif kind == "mast":
            cyls.append(CylinderConfig(centre_ne_m=(n, side * rng.uniform(5, 8)), radius_m=rng.uniform(0.2, 0.5), height_m=rng.uniform(15, 30)))
        elif kind == "tree":
            cyls.append(CylinderConfig(centre_ne_m=(n, side * rng.uniform(6, 10)), radius_m=rng.uniform(1.5, 3.0), height_m=rng.uniform(6, 12)))
        else:
            e = side * rng.uniform(8, 12)
            walls.append(WallConfig(start_ne_m=(n - 8, e), end_ne_m=(n + 8, e + side * 4), thickness_m=0.3, height_m=rng.uniform(2, 4)))
    cfg = WorldConfig(name="bench", seed=seed, texel_m=0.05, ground=GroundConfig(texel_m=0.05, tile_px=4096), box=tuple(boxes), cylinder=tuple(cyls), wall=tuple(walls))
    return World(cfg)


def measure_fps(
    world: World | None = None,
    camera: CameraConfig | None = None,
    options: RenderOptions | None = None,
    *,
    frames: int = 120,
    motion: bool = False,
    warmup: int = 3,
    cpu_time: bool = False,
) -> float:
    """Frames per second rendering ``frames`` poses along the street (one core).

    By wall-clock time, or with ``cpu_time`` by the CPU time this process used (steadier on a
    machine busy with other work)."""
    cv2.setNumThreads(1)
    world = world or bench_world()
    camera = camera or CameraConfig()
    r = Renderer(world, camera, options)
    poses = []
    for k in range(frames + warmup):
        s = k / max(frames + warmup - 1, 1)
        yaw = math.radians(8.0 * math.sin(2 * math.pi * 1.5 * s))
        R_body = euler_zyx_to_R(math.radians(3.0 * math.sin(7 * s)), math.radians(-4.0), yaw)
        p_body = np.array([250.0 * s, 1.5 * math.sin(3 * s), -10.0])
        poses.append(r.model.camera_pose(R_body, p_body))
    kw = dict(v_world_cam=np.array([5.0, 0.0, 0.0]), w_cam=np.array([0.0, 0.3, 0.0])) if motion else {}
    for R, p in poses[:warmup]:
        r.render(R, p, **kw)
    t0 = time.process_time() if cpu_time else time.perf_counter()
    for R, p in poses[warmup:]:
        r.render(R, p, **kw)
    return frames / ((time.process_time() if cpu_time else time.perf_counter()) - t0)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m flightsim.render.bench", description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--obstacles", type=int, default=20)
    ap.add_argument("--all", action="store_true", help="also time distortion, noise and motion blur")
    a = ap.parse_args(argv)
    world = bench_world(a.obstacles)
    cam = CameraConfig.from_fov(a.width, a.height, 60.0)
    fps = measure_fps(world, cam, frames=a.frames)
    cpu = measure_fps(world, cam, frames=a.frames, cpu_time=True)
    print(
        f"renderer: {fps:.1f} frames/s at {a.width}x{a.height}, {len(world.obstacles)} obstacles, one core "
        f"(by CPU time {cpu:.1f} frames/s; target >= 60)"
    )
    if a.all:
        cam_d = CameraConfig.from_fov(a.width, a.height, 60.0, distortion=(-0.25, 0.08, 0.0, 0.0, 0.0))
        print(f"  with lens distortion:        {measure_fps(world, cam_d, frames=a.frames):.1f} frames/s")
        print(f"  with pixel noise σ = 2:      {measure_fps(world, cam, RenderOptions(noise_sigma=2.0), frames=a.frames):.1f} frames/s")
        blur = RenderOptions(exposure_s=0.01, max_blur_subframes=4)
        print(f"  with motion blur (≤4 sub):   {measure_fps(world, cam, blur, frames=a.frames, motion=True):.1f} frames/s")


if __name__ == "__main__":
    main()
