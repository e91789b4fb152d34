"""Fly a scenario and export it as a replayable flight log (issue 3).

``fly(scenario, out_dir)`` steps JSBSim frame by frame and, on the simulation clock:

* emits the autopilot's streams (HEARTBEAT 1 Hz, ATTITUDE, LOCAL_POSITION_NED, GLOBAL_POSITION_INT
  at their configured rates), each leaving the autopilot ``latency_s`` after the state it
  describes, with the telemetry model's errors;
* renders a camera frame at each frame period from the *true* camera pose (mid-exposure) through
  the companion's camera model;
* records the truth of that frame: vehicle and camera pose, per-sector nearest obstacle, targets.

Files written to ``out_dir``:

* ``telemetry.tlog`` — MAVLink 2 (ardupilotmega) tlog, record stamps on the recording clock
  (``[scenario] epoch_s`` + simulation time);
* ``video.avi`` (MJPG) and ``frames.csv`` (``index,t_s``: capture time on that same clock);
* ``truth.npz`` — per-frame truth arrays (see :data:`TRUTH_FIELDS`), written deterministically;
* ``camera.toml`` — the ``[camera]`` table the frames were rendered with (for the companion);
* ``summary.png`` — track, altitude, attitude and speed, with the obstacles;
* ``flight.json`` — what was flown and how fast.

The same scenario and seed give byte-identical tlog, video, frames.csv and truth.npz.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import time
import zipfile
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from companion.core.camera import CameraModel
from companion.mavlink.dialect import mavlink
from flightsim.dynamics import LocalNED, make_vehicle
from flightsim.render import Renderer
from flightsim.scenario import Scenario
from flightsim.telemetry import TelemetryModel
from flightsim.tlog import TlogWriter
from flightsim.world import sector_truth, target_truth

TRUTH_FIELDS = {
    "t_s": "capture time of each frame, recording clock (Unix s)",
    "t_sim_s": "capture time, simulation clock (s)",
    "p_ned": "vehicle position, world NED (m)",
    "v_ned": "vehicle velocity, world NED (m/s)",
    "rpy": "roll, pitch, yaw ZYX (rad)",
    "pqr": "body rates FRD (rad/s)",
    "R_world_body": "body FRD → world NED",
    "R_world_cam": "camera → world NED",
    "p_world_cam": "camera centre, world NED (m)",
    "sector_m": "true horizontal distance to the nearest obstacle per OBSTACLE_DISTANCE sector (72 × 5°, body FRD); inf = nothing within sector_max_m, NaN = not in the camera's view",
    "sector_max_m": "max distance of the sector truth (m)",
    "target_names": "names of the world's targets",
    "target_p_world": "target positions, world NED (m)",
    "target_range_m": "range from the camera centre to each target (m)",
    "target_visible": "target inside the image and not occluded",
}


def _mav_type(vehicle_kind: str) -> int:
    return mavlink.MAV_TYPE_FIXED_WING if vehicle_kind == "fixedwing" else mavlink.MAV_TYPE_QUADROTOR


def save_npz_deterministic(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez`` with fixed zip timestamps, so equal arrays give equal bytes."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(name + ".npy", date_time=(2026, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, buf.getvalue())


def camera_toml(camera) -> str:
    """The ``[camera]`` table of a CameraConfig, in the companion's TOML schema."""
    def fmt(v):
        if isinstance(v, (tuple, list)):
            return "[" + ", ".join(repr(float(x)) for x in v) + "]"
        return repr(v)

    lines = ["# Camera the frames were rendered with (flightsim); same schema as configs/companion.toml [camera]", "[camera]"]
    for f in dataclasses.fields(camera):
        lines.append(f"{f.name} = {fmt(getattr(camera, f.name))}")
    return "\n".join(lines) + "\n"


@dataclasses.dataclass
class FlightResult:
    out_dir: Path
    frames: int
    messages: int
    duration_s: float
    wall_s: float

    @property
    def realtime_factor(self) -> float:
        return self.duration_s / self.wall_s if self.wall_s > 0 else math.inf


def fly(sc: Scenario, out_dir: str | Path, progress: Callable[[int, int], None] | None = None,
        plot: bool = True) -> FlightResult:
    """Fly ``sc`` and write the export files into ``out_dir`` (created if missing)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    wall0 = time.perf_counter()
    meta, cam_cfg = sc.meta, sc.camera
    vehicle = make_vehicle(sc.vehicle)
    tm = TelemetryModel(sc.telemetry, sc.telemetry_seed, _mav_type(sc.vehicle.kind))
    origin = LocalNED(sc.vehicle.origin_lat_deg, sc.vehicle.origin_lon_deg, sc.vehicle.origin_alt_m)
    renderer = Renderer(sc.world, cam_cfg, sc.render)
    cam = CameraModel(cam_cfg)
    R_cam_body = cam_cfg.R_cam_body
    lat = sc.telemetry.latency_s

    n_steps = int(round(meta.duration_s / vehicle.dt))
    n_frames = int(math.floor(meta.duration_s * meta.fps + 1e-9)) + 1
    streams = [  # (period, builder, latency)
        (1.0, lambda s: tm.heartbeat(), 0.0),
        (1.0 / sc.telemetry.attitude_rate_hz, tm.attitude, lat),
        (1.0 / sc.telemetry.position_rate_hz, tm.local_position, lat),
        (1.0 / sc.telemetry.global_rate_hz, lambda s: tm.global_position(s, origin), lat),
    ]
    next_t = [0.0] * len(streams)
    next_frame = 0
    queue: list[tuple[float, int, object]] = []
    truth: dict[str, list] = {k: [] for k in TRUTH_FIELDS if k not in ("sector_max_m", "target_names", "target_p_world")}
    fourcc = cv2.VideoWriter_fourcc(*"MJPG")
    video = cv2.VideoWriter(str(out / "video.avi"), fourcc, meta.fps, (cam_cfg.width, cam_cfg.height), isColor=False)
    if not video.isOpened():
        raise RuntimeError(f"cannot open {out / 'video.avi'} for MJPG writing")
    video.set(cv2.VIDEOWRITER_PROP_QUALITY, meta.video_quality)
    rows = ["index,t_s"]
    eps = 1e-9
    state = vehicle.state()
    try:
        for step in range(n_steps + 1):
            if step > 0:
                state = vehicle.step(vehicle.dt)
            tm.advance(state)
            t = state.time_s
            for i, (period, build, delay) in enumerate(streams):
                if t + eps >= next_t[i]:
                    queue.append((t + delay, len(queue), build(state)))
                    next_t[i] += period
            if next_frame < n_frames and t + eps >= next_frame / meta.fps:
                R_wb = state.R_world_body
                R_wc, p_wc = cam.camera_pose(R_wb, state.p_ned)
                frame = renderer.render(R_wc, p_wc, v_world_cam=state.v_ned, w_cam=R_cam_body @ state.pqr,
                                        frame_index=next_frame)
                video.write(frame.image)
                rows.append(f"{next_frame},{meta.epoch_s + t:.6f}")
                tt = target_truth(sc.world, p_wc, R_wc, cam_cfg)
                for key, val in (("t_s", meta.epoch_s + t), ("t_sim_s", t), ("p_ned", state.p_ned), ("v_ned", state.v_ned),
                                 ("rpy", state.rpy), ("pqr", state.pqr), ("R_world_body", R_wb), ("R_world_cam", R_wc),
                                 ("p_world_cam", p_wc),
                                 ("sector_m", sector_truth(sc.world, R_wb, state.p_ned, cam_cfg, meta.sector_max_distance_m)),
                                 ("target_range_m", tt.range_m),
                                 ("target_visible", tt.visible if tt.visible is not None else np.zeros(len(tt.names), bool))):
                    truth[key].append(np.asarray(val))
                next_frame += 1
                if progress:
                    progress(next_frame, n_frames)
    finally:
        video.release()
    queue.sort(key=lambda item: (item[0], item[1]))
    with TlogWriter(out / "telemetry.tlog", meta.epoch_s) as w:
        for t_emit, _, msg in queue:
            w.write(t_emit, msg, sysid=sc.telemetry.system_id, compid=1)
    (out / "frames.csv").write_text("\n".join(rows) + "\n")
    tt0 = target_truth(sc.world, np.zeros(3))
    arrays = {k: np.array(v) for k, v in truth.items()}
    arrays["sector_max_m"] = np.array(meta.sector_max_distance_m)
    arrays["target_names"] = np.array(tt0.names, dtype="U64")
    arrays["target_p_world"] = np.asarray(tt0.p_world, float).reshape(-1, 3)
    save_npz_deterministic(out / "truth.npz", arrays)
    (out / "camera.toml").write_text(camera_toml(cam_cfg))
    wall = time.perf_counter() - wall0
    result = FlightResult(out, next_frame, len(queue), meta.duration_s, wall)
    (out / "flight.json").write_text(json.dumps({
        "scenario": meta.name, "scenario_file": str(sc.path), "seed": meta.seed, "aircraft": sc.vehicle.aircraft,
        "duration_s": meta.duration_s, "frames": result.frames, "messages": result.messages,
        "wall_time_s": round(wall, 3), "realtime_factor": round(result.realtime_factor, 2),
        "truth_fields": TRUTH_FIELDS,
    }, indent=2) + "\n")
    if plot:
        from flightsim.plots import flight_summary_plot

        flight_summary_plot(sc, arrays, out / "summary.png")
    return result
