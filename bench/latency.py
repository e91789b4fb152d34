"""Frame-to-OBSTACLE_DISTANCE latency and sustained frame rate of the whole pipeline.

Target: p99 ≤ 30 ms and ≥ 30 frames/s at 640×480 with 300 tracks on one core.

What is timed: for each frame, from the moment :meth:`~companion.pipeline.Pipeline.process` is
called (the frame and the telemetry that brackets it are in memory) until the OBSTACLE_DISTANCE
built from it is packed into MAVLink bytes — pose interpolation, tracking (Harris + NCC guided by
telemetry), estimator, sectors, yaw rotation and encoding.  Rendering the synthetic frame and
feeding telemetry are outside the timed region.  What the live loop adds on top (waiting for the
ATTITUDE sample that brackets the exposure, ~½ sample period on average, and the camera's own
delivery delay) is not a cost of the pipeline and is not included.

One core: ``cv2.setNumThreads(1)`` for the duration (numpy's BLAS only sees small matrices here).

The scene (:class:`SyntheticFlight`, also used by the tests): a vehicle flying level past a
textured vertical wall (a plane of constant north, band-limited noise texture), with constant
velocity and optionally a constant yaw rate; frames are ray-cast through the companion's camera
model, telemetry comes from the same analytic trajectory.
"""

from __future__ import annotations

import dataclasses
import math
import time

import cv2
import numpy as np

from companion.core.camera import CameraConfig, CameraModel
from companion.core.frames import euler_zyx_to_R


@dataclasses.dataclass
class SyntheticFlight:
    """Level flight with constant velocity (and yaw rate) facing a textured wall at ``wall_north_m``.

    World NED; the wall is the plane x = ``wall_north_m``, seen from the south.  ``textured=False``
    paints it one flat grey (nothing a camera can range).
    """

    camera: CameraConfig = dataclasses.field(default_factory=lambda: CameraConfig.from_fov(320, 240, 60.0))
    wall_north_m: float = 20.0
    start_ned: tuple[float, float, float] = (0.0, 0.0, -10.0)
    velocity_ned: tuple[float, float, float] = (1.0, 3.0, 0.0)
    yaw0_rad: float = 0.0
    yaw_rate_rad_s: float = 0.0
    textured: bool = True
    texel_m: float = 0.05
    noise_sigma: float = 0.0
    seed: int = 0

    def __post_init__(self):
        rng = np.random.default_rng(self.seed)
        n = 1024  # periodic band-limited noise: white noise low-passed in the Fourier domain (wraps seamlessly)
        f = np.fft.fftfreq(n)
        gain = np.exp(-2.0 * (np.pi * 1.6) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))  # Gaussian blur, σ = 1.6 texels
        tex = np.fft.ifft2(np.fft.fft2(rng.standard_normal((n, n))) * gain).real.astype(np.float32)
        tex = (tex - tex.mean()) / tex.std()
        self._tex = np.clip(128 + 50 * tex, 0, 255).astype(np.float32)
        c = self.camera
        model = CameraModel(c)
        u, v = np.meshgrid(np.arange(c.width, dtype=float), np.arange(c.height, dtype=float))
        self._rays = model.unproject(np.stack([u.ravel(), v.ravel()], 1))  # (N, 3) unit, camera frame
        self._model = model
        self._rng = np.random.default_rng(self.seed + 1)

    # -- trajectory ---------------------------------------------------------------------------------
    def rpy(self, t: float) -> tuple[float, float, float]:
        return 0.0, 0.0, self.yaw0_rad + self.yaw_rate_rad_s * t

    def R_world_body(self, t: float) -> np.ndarray:
        return euler_zyx_to_R(*self.rpy(t))

    def position(self, t: float) -> np.ndarray:
        return np.asarray(self.start_ned, float) + np.asarray(self.velocity_ned, float) * t

    def velocity(self) -> np.ndarray:
        return np.asarray(self.velocity_ned, float)

    def rates(self) -> tuple[float, float, float]:
        return 0.0, 0.0, self.yaw_rate_rad_s

    def wall_distance(self, t: float) -> float:
        """Distance from the vehicle to the wall along north, m."""
        return self.wall_north_m - float(self.position(t)[0])

    def attitude_fields(self, t: float) -> tuple[float, float, float, float, float, float]:
        """roll, pitch, yaw, rollspeed, pitchspeed, yawspeed (ATTITUDE)."""
        return (*self.rpy(t), *self.rates())

    def local_position_fields(self, t: float) -> tuple[float, float, float, float, float, float]:
        """x, y, z, vx, vy, vz (LOCAL_POSITION_NED)."""
        p, v = self.position(t), self.velocity()
        return (float(p[0]), float(p[1]), float(p[2]), float(v[0]), float(v[1]), float(v[2]))

    # -- rendering ----------------------------------------------------------------------------------
    def render(self, t: float) -> np.ndarray:
        """The grey frame the camera sees at ``t`` (uint8, camera size)."""
        c = self.camera
        R_wc, p_wc = self._model.camera_pose(self.R_world_body(t), self.position(t))
        d = self._rays @ R_wc.T
        dx = d[:, 0]
        hit = dx > 1e-6
        s = np.where(hit, (self.wall_north_m - p_wc[0]) / np.where(hit, dx, 1.0), 0.0)
        hit &= s > 0
        e = p_wc[1] + s * d[:, 1]
        z = p_wc[2] + s * d[:, 2]
        if self.textured:
            mx = (e / self.texel_m).astype(np.float32).reshape(c.height, c.width)
            my = (z / self.texel_m).astype(np.float32).reshape(c.height, c.width)
            img = cv2.remap(self._tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        else:
            img = np.full((c.height, c.width), 120.0, np.float32)
        img = np.where(hit.reshape(c.height, c.width), img, 200.0)
        if self.noise_sigma > 0:
            img = img + self._rng.normal(0.0, self.noise_sigma, img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def feed_telemetry(buffer, flight: SyntheticFlight, t0: float, t1: float, boot_offset_s: float = 0.0,
                   attitude_hz: float = 50.0, position_hz: float = 20.0) -> None:
    """Add the flight's ATTITUDE / LOCAL_POSITION_NED samples stamped in [t0, t1) to a TelemetryBuffer.

    Sample k of a stream sits at k / rate; its ``time_boot_ms`` is (t + ``boot_offset_s``) in ms.
    """
    samples = []
    for order, (rate, add, fields) in enumerate(((attitude_hz, buffer.add_attitude, flight.attitude_fields),
                                                  (position_hz, buffer.add_local_position, flight.local_position_fields))):
        for k in range(math.ceil(t0 * rate - 1e-9), math.ceil(t1 * rate - 1e-9)):
            samples.append((k / rate, order, add, fields))
    for t, _, add, fields in sorted(samples, key=lambda s: (s[0], s[1])):  # time order, as a link delivers them
        add(int(round((t + boot_offset_s) * 1000)), *fields(t))


def _one_core():
    prev = cv2.getNumThreads()
    cv2.setNumThreads(1)
    return prev


def measure_latency(width: int = 640, height: int = 480, max_tracks: int = 300, frames: int = 240, warmup: int = 30,
                    fps: float = 30.0, estimator_filter: str = "anchored", seed: int = 0, config=None) -> dict:
    """Run the pipeline on a synthetic flight and time every frame (see the module docstring).

    ``config``: the CompanionConfig to start from (default: the shipped configs/companion.toml);
    camera, track count and filter are set from the arguments.

    Returns a dict: ``latency_p50_ms`` / ``latency_p99_ms`` / ``latency_max_ms`` over the frames that
    produced an OBSTACLE_DISTANCE, ``processing_p50_ms`` / ``processing_p99_ms`` over every frame,
    ``sustained_fps`` (frames per second of pipeline time, one core), the pipeline's CPU time per
    frame (``cpu_mean_ms``, ``cpu_p50_ms``, ``cpu_p99_ms``; this thread only) and its stages
    (``stage_cpu_ms``), the mean number of live tracks and of converged landmarks, and the setup.
    """
    from companion.mavlink.dialect import mavlink  # first: MAVLink 2
    from companion.io.config_files import load_companion_config
    from companion.pipeline import Pipeline, PipelineConfig
    from companion.reporter import Reporter
    from companion.camera_sources import Frame
    from companion.telemetry import TelemetryBuffer

    cam = CameraConfig.from_fov(width, height, 60.0)
    base = load_companion_config(None) if config is None else config
    cfg = dataclasses.replace(
        base, camera=cam,
        tracks=dataclasses.replace(base.tracks, max_tracks=max_tracks),
        harris=dataclasses.replace(base.harris, max_corners=max_tracks),
        estimator=dataclasses.replace(base.estimator, filter=estimator_filter),
    )
    flight = SyntheticFlight(camera=cam, wall_north_m=40.0, start_ned=(0.0, 0.0, -10.0), velocity_ned=(3.0, 2.0, 0.0),
                             yaw_rate_rad_s=0.05, noise_sigma=1.0, seed=seed)
    pcfg = PipelineConfig()
    tel = TelemetryBuffer(cfg.telemetry)
    tel.set_clock_offset(0.0)
    pipe = Pipeline(cam, cfg, pcfg, tel)
    rep = Reporter(cfg, pcfg, outputs=("autopilot",), start=0.0)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=196)
    lat_od: list[float] = []
    proc: list[float] = []
    tracks: list[int] = []
    conv: list[int] = []
    cpu: list[float] = []
    stage_cpu: dict[str, float] = {}
    t_start = 1.0
    fed = 0.0
    prev = _one_core()
    try:
        for k in range(frames + warmup):
            t = t_start + k / fps
            gray = flight.render(t)
            now = t + 0.021  # the ATTITUDE after the exposure has arrived
            feed_telemetry(tel, flight, fed, now)
            fed = now
            w0 = time.perf_counter()
            res = pipe.process(Frame(k, t, gray), now)
            msgs = rep.on_result(res, now + res.processing_s, yaw_now=pipe.yaw_now(now), last_frame_at=now,
                                 telemetry_problem=pipe.telemetry_problem(now), time_boot_ms=int(now * 1000))
            sent_od = False
            for _, m in msgs:
                m.pack(mav)
                if m.get_type() == "OBSTACLE_DISTANCE":
                    sent_od = True
            dt = time.perf_counter() - w0
            if k < warmup:
                continue
            if not res.ok:
                raise RuntimeError(f"benchmark frame {k} failed: {res.reason}")
            proc.append(dt)
            cpu.append(res.cpu_s)
            for name, v in res.stage_cpu_s.items():
                stage_cpu[name] = stage_cpu.get(name, 0.0) + v
            if sent_od:
                lat_od.append(dt)
            tracks.append(res.n_tracks)
            conv.append(res.n_converged)
    finally:
        cv2.setNumThreads(prev)
    lat = np.asarray(lat_od) * 1000
    pr = np.asarray(proc) * 1000
    return {
        "width": width, "height": height, "max_tracks": max_tracks, "filter": estimator_filter, "frames": frames,
        "latency_p50_ms": float(np.percentile(lat, 50)), "latency_p99_ms": float(np.percentile(lat, 99)),
        "latency_max_ms": float(lat.max()),
        "processing_p50_ms": float(np.percentile(pr, 50)), "processing_p99_ms": float(np.percentile(pr, 99)),
        "sustained_fps": float(len(pr) / (pr.sum() / 1000)),
        "cpu_mean_ms": float(np.mean(cpu)) * 1000, "cpu_p50_ms": float(np.percentile(cpu, 50)) * 1000,
        "cpu_p99_ms": float(np.percentile(cpu, 99)) * 1000,
        "stage_cpu_ms": {k: v * 1000 / len(cpu) for k, v in stage_cpu.items()},
        "mean_tracks": float(np.mean(tracks)), "mean_converged": float(np.mean(conv)),
        "targets": {"latency_p99_ms": 30.0, "sustained_fps": 30.0},
    }


def run_all(frames: int = 240) -> dict:
    """Both filters at 640×480 with 300 tracks (the latency benchmark)."""
    return {f: measure_latency(640, 480, 300, frames, estimator_filter=f) for f in ("anchored", "landmark")}


def markdown(res: dict) -> str:
    """Table for docs/BENCHMARKS.md."""
    lines = [
        "Frame-to-OBSTACLE_DISTANCE latency of the whole pipeline (pose interpolation, Harris + NCC tracking guided by "
        "telemetry, triangulation, EKF, sectors, yaw rotation, MAVLink encoding) on one core "
        "(`cv2.setNumThreads(1)`), synthetic flight past a textured wall at 640×480 with up to 300 tracks. "
        "Targets: p99 ≤ 30 ms, ≥ 30 frames/s. Standalone: `python -m bench.latency [--filter landmark]`.",
        "",
        "| filter | frames | mean tracks | mean converged | p50 ms | p99 ms | max ms | sustained frames/s | p99 ≤ 30 | ≥ 30 fps |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in res.items():
        ok_lat = "✓" if r["latency_p99_ms"] <= 30.0 else "✗"
        ok_fps = "✓" if r["sustained_fps"] >= 30.0 else "✗"
        lines.append(f"| {name} | {r['frames']} | {r['mean_tracks']:.0f} | {r['mean_converged']:.0f} | "
                     f"{r['latency_p50_ms']:.1f} | {r['latency_p99_ms']:.1f} | {r['latency_max_ms']:.1f} | "
                     f"{r['sustained_fps']:.1f} | {ok_lat} | {ok_fps} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    import argparse
    import json

    ap = argparse.ArgumentParser(prog="python -m bench.latency",
                                 description="Frame-to-OBSTACLE_DISTANCE latency of the companion pipeline on one core.")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--tracks", type=int, default=300)
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--filter", choices=("anchored", "landmark"), default="anchored")
    ap.add_argument("--json", action="store_true", help="print JSON instead of a table")
    a = ap.parse_args(argv)
    r = measure_latency(a.width, a.height, a.tracks, a.frames, estimator_filter=a.filter)
    if a.json:
        print(json.dumps(r, indent=2))
    else:
        print(f"{r['width']}×{r['height']}, {r['max_tracks']} tracks, {r['filter']} EKF, one core, {r['frames']} frames")
        print(f"  frame → OBSTACLE_DISTANCE latency: p50 {r['latency_p50_ms']:.1f} ms, p99 {r['latency_p99_ms']:.1f} ms "
              f"(max {r['latency_max_ms']:.1f}; target p99 ≤ 30)")
        print(f"  sustained: {r['sustained_fps']:.1f} frames/s (target ≥ 30); mean tracks {r['mean_tracks']:.0f}, "
              f"converged {r['mean_converged']:.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
