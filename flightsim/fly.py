"""Fly a scenario and export it as a replayable flight log.

``fly(scenario, out_dir)`` steps JSBSim frame by frame and, on the simulation clock:

* emits the autopilot's streams (HEARTBEAT 1 Hz, ATTITUDE, LOCAL_POSITION_NED, GLOBAL_POSITION_INT
  at their configured rates), each leaving the autopilot ``latency_s`` after the state it
  describes, with the telemetry model's errors;
* renders a camera frame at each frame period from the *true* camera pose (mid-exposure) through
  the companion's camera model;
* records the truth of that frame: vehicle and camera pose, per-sector nearest obstacle, targets.

The per-step loop itself — dynamics, telemetry error states, stream schedule, camera frames and
their truth — is :class:`Flight` with :class:`StreamSchedule`, shared with the software-in-the-loop
run (:mod:`flightsim.sitl`), which plays the same flight to a live companion.

Files written to ``out_dir``:

* ``telemetry.tlog`` — MAVLink 2 (ardupilotmega) tlog, record stamps on the recording clock
  (``[scenario] epoch_s`` + simulation time);
* ``video.avi`` (MJPG) and ``frames.csv`` (``index,t_s``: capture time on that same clock);
* ``truth.npz`` — per-frame truth arrays (see :data:`TRUTH_FIELDS`), written deterministically;
* ``camera.toml`` — the ``[camera]`` table the frames were rendered with (for the companion);
* ``summary.png`` — track, altitude, attitude and speed, with the obstacles;
* ``flight.json`` — what was flown and how fast.

The same scenario and seed give byte-identical tlog, video, frames.csv and truth.npz.  The files
are written under temporary names and renamed onto theirs together when the flight is complete
(:class:`companion.io.atomic.StagedFiles`): an interrupted ``fly`` leaves none of them behind
(and a previous flight's set in ``out_dir`` untouched).
"""

from __future__ import annotations

import collections
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
from companion.io.atomic import StagedFiles, prepare_output_dir
from companion.mavlink.dialect import mavlink
from flightsim.avoidance import F450_RADIUS_M, body_to_ned, make_avoidance
from flightsim.dynamics import LocalNED, make_vehicle
from flightsim.render import Renderer
from flightsim.scenario import Scenario
from flightsim.telemetry import TelemetryModel
from flightsim.tlog import TlogWriter
from flightsim.world import target_truth
from flightsim.world.truth import sector_truth_360

#: trajectory.npz: every physics step (120 Hz), for the outcome of avoidance (collision, clearance, stops)
TRAJECTORY_FIELDS = {
    "t_sim_s": "simulation time of the step, s",
    "p_ned": "vehicle position, world NED, m",
    "v_ned": "vehicle velocity, world NED, m/s",
    "v_des_ned": "the pilot's velocity demand (avoidance on; NaN otherwise), m/s",
    "v_cmd_ned": "the demand the avoidance let through, m/s",
    "clearance_m": "distance from the vehicle's body (sphere) to the nearest obstacle surface, m",
    "avoidance_data": "the autopilot held fresh obstacle data at that step",
}

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
    "sector_all_m": "true horizontal distance per sector over all 72 sectors (360°, body FRD), in view or not; inf = nothing within sector_max_m",
    "in_view": "sector's centre bearing in the camera's image (72 bools per frame); sector_m = sector_all_m where in_view, else NaN",
    "sector_max_m": "max distance of the sector truth (m)",
    "target_names": "names of the world's targets",
    "target_p_world": "target positions, world NED (m)",
    "target_range_m": "range from the camera centre to each target (m)",
    "target_visible": "target inside the image and not occluded",
}

EPS_T = 1e-9  # tolerance of "is it due" comparisons on the simulation clock, s


def _mav_type(vehicle_kind: str) -> int:
    return mavlink.MAV_TYPE_FIXED_WING if vehicle_kind == "fixedwing" else mavlink.MAV_TYPE_QUADROTOR


def _mav_autopilot(avoidance_model: str) -> int:
    """The HEARTBEAT's MAV_AUTOPILOT: PX4 when the simulated avoidance is PX4's, ArduPilot otherwise."""
    return mavlink.MAV_AUTOPILOT_PX4 if avoidance_model == "px4" else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA


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


# ---------------------------------------------------------------------- the shared flight loop ---
class StreamSchedule:
    """Periodic autopilot streams on the simulation clock.

    Each stream has a period (None = off), a builder ``build(state) -> message`` and a delay
    (the message leaves ``delay`` s after the state it describes).  :meth:`due` is called once per
    physics step after :meth:`Flight.step`; a due stream is built from that step's state and its
    next time advances by one period (the grid stays fixed: a stream faster than the physics step
    is sent once per step).  ``fly`` uses the scenario's rates; ``sitl`` the companion's requests.
    """

    def __init__(self) -> None:
        self._streams: dict[str, list] = {}  # name -> [period | None, next_t, build, delay]

    def add(self, name: str, period: float | None, build: Callable, delay: float = 0.0, start_t: float = 0.0) -> None:
        self._streams[name] = [period, start_t, build, delay]

    def names(self) -> list[str]:
        return list(self._streams)

    def period(self, name: str) -> float | None:
        return self._streams[name][0]

    def set_period(self, name: str, period: float | None, t_now: float) -> None:
        """Change a stream's period (None = stop); a (re)started stream sends at the next step."""
        s = self._streams[name]
        if period is not None and (s[0] is None or period != s[0]):
            s[1] = t_now
        s[0] = period

    def restart_at(self, name: str, t: float) -> None:
        """Send ``name`` at the first step at or after ``t`` (and then on its period)."""
        self._streams[name][1] = t

    def snapshot(self) -> dict[str, tuple]:
        """Every stream's period and next time, for :meth:`restore`."""
        return {name: (s[0], s[1]) for name, s in self._streams.items()}

    def restore(self, snap: dict[str, tuple]) -> None:
        """Return to a :meth:`snapshot` (builders and delays are unchanged)."""
        for name, (period, next_t) in snap.items():
            s = self._streams[name]
            s[0], s[1] = period, next_t

    def due(self, state) -> list[tuple[float, str, object]]:
        """``(t_emit, name, message)`` for every stream due at ``state.time_s``, in stream order."""
        t = state.time_s
        out = []
        for name, s in self._streams.items():
            period, next_t, build, delay = s
            if period is not None and t + EPS_T >= next_t:
                out.append((t + delay, name, build(state)))
                s[1] = next_t + period
        return out


class CapturedFrame:
    """A camera frame of the frame grid: ``index``, capture (mid-exposure) time ``t_s`` on the
    simulation clock and ``image`` ((H, W) uint8).

    A frame captured with ``Flight.capture(defer=True)`` holds only the pose it is rendered from;
    its image (and its truth row) is made by :meth:`Flight.finish_frames` or, at the latest, on
    the first access to :attr:`image` — the pixels are the same whenever that happens (the
    renderer draws each frame from its own pose and frame index alone)."""

    __slots__ = ("index", "t_s", "_image", "_flight")

    def __init__(self, index: int, t_s: float, image: np.ndarray | None = None, flight: "Flight | None" = None):
        if image is None and flight is None:
            raise ValueError("a CapturedFrame needs its image or the Flight that renders it")
        self.index, self.t_s, self._image, self._flight = index, t_s, image, flight

    @property
    def rendered(self) -> bool:
        return self._image is not None

    @property
    def image(self) -> np.ndarray:
        if self._image is None:
            self._flight.finish_frames(self.index)
        return self._image

    def __repr__(self) -> str:
        return f"CapturedFrame(index={self.index}, t_s={self.t_s!r}, {'rendered' if self.rendered else 'not rendered yet'})"


class Flight:
    """A scenario in flight, one JSBSim step at a time (shared by ``fly`` and ``sitl``).

    :meth:`step` advances the dynamics and the telemetry model's error states (the first call
    gives the start state); :attr:`tm` builds the autopilot's messages from the state of the step
    (:meth:`telemetry_builders`); :meth:`frame_due` / :meth:`capture` render the camera frame of
    the frame grid from the true camera pose and record its truth; :meth:`truth_arrays` and
    :meth:`write_common` produce the export files both commands share.

    :meth:`step` = :meth:`physics_step` + :meth:`advance_telemetry`.  Nothing in the dynamics, the
    camera or the truth depends on the telemetry, so ``sitl`` runs the physics and the camera
    ahead (while the companion works on the previous frame) and advances the telemetry model
    later, in the same step order — the random draws, and so every message, stay the same.
    """

    def __init__(self, sc: Scenario):
        self.sc = sc
        meta = sc.meta
        self.vehicle = make_vehicle(sc.vehicle)
        self.tm = TelemetryModel(sc.telemetry, sc.telemetry_seed, _mav_type(sc.vehicle.kind), _mav_autopilot(sc.avoidance.model))
        self.origin = LocalNED(sc.vehicle.origin_lat_deg, sc.vehicle.origin_lon_deg, sc.vehicle.origin_alt_m)
        self.renderer = Renderer(sc.world, sc.camera, sc.render)
        self.cam = CameraModel(sc.camera)
        self.R_cam_body = sc.camera.R_cam_body
        self.dt = self.vehicle.dt
        self.n_steps = int(round(meta.duration_s / self.vehicle.dt))
        self.n_frames = int(math.floor(meta.duration_s * meta.fps + 1e-9)) + 1
        self.next_frame = 0
        self.frame_times: list[float] = []  # capture times (simulation clock) of the frames so far
        self._unfinished: collections.deque = collections.deque()  # (CapturedFrame, state) captured with defer, in order
        self.truth: dict[str, list] = {k: [] for k in TRUTH_FIELDS if k not in ("sector_max_m", "target_names", "target_p_world")}
        self.state = None
        self.step_index = -1
        self.timing = {"dynamics": 0.0, "telemetry": 0.0, "render": 0.0, "truth": 0.0}  # wall seconds per part
        # the simulated autopilot's obstacle avoidance (docs/derivations/sectors.md), fed by whoever hears the companion
        self.avoidance = make_avoidance(sc.avoidance)
        self.avoiding = sc.avoidance.model != "none"
        if self.avoiding:
            self.vehicle.avoidance = self.avoidance
        self._boundary_every = max(1, int(round(0.2 / self.dt)))  # steps between boundary snapshots (5 Hz)
        self.body_radius_m = F450_RADIUS_M if sc.vehicle.kind == "quad" else 0.0
        self.collision_t: float | None = None  # simulation time the body first touched an obstacle (the flight ends)
        self.collision_with: str | None = None
        self.traj: dict[str, list] = {k: [] for k in TRAJECTORY_FIELDS}
        self.boundary: list[tuple[float, np.ndarray]] = []  # (t, (K, 2) world NE points) at 5 Hz, for plots

    @property
    def finished(self) -> bool:
        return self.step_index >= self.n_steps or self.collision_t is not None

    def step(self):
        """Advance one physics step (the first call gives the start state) and the telemetry model's
        error states; None after the last step."""
        state = self.physics_step()
        if state is not None:
            self.advance_telemetry(state)
        return state

    def physics_step(self):
        """Advance the dynamics only (see the class docstring); None after the last step."""
        if self.finished:
            return None
        w0 = time.perf_counter()
        self.step_index += 1
        self.state = st = self.vehicle.state() if self.step_index == 0 else self.vehicle.step(self.vehicle.dt)
        clear, obstacle = self.sc.world.clearance(st.p_ned)
        clear -= self.body_radius_m
        tr = self.traj
        tr["t_sim_s"].append(st.time_s)
        tr["p_ned"].append(st.p_ned)
        tr["v_ned"].append(st.v_ned)
        tr["v_des_ned"].append(self.vehicle.v_des if self.avoiding else (np.nan,) * 3)
        tr["v_cmd_ned"].append(self.vehicle.v_cmd if self.avoiding else (np.nan,) * 3)
        tr["clearance_m"].append(clear)
        tr["avoidance_data"].append(self.avoidance.has_data(st.time_s))
        if self.avoiding and self.step_index % self._boundary_every == 0:
            ne = st.p_ned[:2] + body_to_ned(self.avoidance.boundary_points(st.time_s), float(st.rpy[2]))
            self.boundary.append((st.time_s, ne))
        if clear <= 0.0 and self.body_radius_m > 0 and self.collision_t is None:
            self.collision_t = st.time_s
            self.collision_with = obstacle.label if obstacle is not None else None
        self.timing["dynamics"] += time.perf_counter() - w0
        return self.state

    def advance_telemetry(self, state) -> None:
        """Integrate the telemetry model's error states to ``state`` (once per step, in step order)."""
        w0 = time.perf_counter()
        self.tm.advance(state)
        self.timing["telemetry"] += time.perf_counter() - w0

    def telemetry_builders(self) -> dict[str, Callable]:
        """Message builders of the autopilot's streams, in the order they are built each step."""
        tm, origin = self.tm, self.origin
        return {
            "HEARTBEAT": lambda s: tm.heartbeat(),
            "ATTITUDE": tm.attitude,
            "LOCAL_POSITION_NED": tm.local_position,
            "GLOBAL_POSITION_INT": lambda s: tm.global_position(s, origin),
        }

    def scenario_streams(self) -> StreamSchedule:
        """The scenario's fixed streams: HEARTBEAT 1 Hz and the ``[telemetry]`` rates with its latency."""
        tel = self.sc.telemetry
        b = self.telemetry_builders()
        sched = StreamSchedule()
        sched.add("HEARTBEAT", 1.0, b["HEARTBEAT"], 0.0)
        sched.add("ATTITUDE", 1.0 / tel.attitude_rate_hz, b["ATTITUDE"], tel.latency_s)
        sched.add("LOCAL_POSITION_NED", 1.0 / tel.position_rate_hz, b["LOCAL_POSITION_NED"], tel.latency_s)
        sched.add("GLOBAL_POSITION_INT", 1.0 / tel.global_rate_hz, b["GLOBAL_POSITION_INT"], tel.latency_s)
        return sched

    def frame_due(self, state=None) -> bool:
        """A frame of the frame grid is due at ``state`` (default: the newest physics step)."""
        state = self.state if state is None else state
        return (state is not None and self.next_frame < self.n_frames
                and state.time_s + EPS_T >= self.next_frame / self.sc.meta.fps)

    def capture(self, state=None, *, defer: bool = False) -> CapturedFrame:
        """Take the due frame at ``state`` (default: the newest physics step): render it from the
        true camera pose and record its truth — now, or with ``defer`` when
        :meth:`finish_frames` (or the first access to its image) asks for it.  Frames are finished
        in capture order, so the truth rows and the pixels do not depend on when that happens
        (``flightsim sitl`` renders the frames captured between two acknowledgements while the
        companion works)."""
        state = self.state if state is None else state
        out = CapturedFrame(self.next_frame, state.time_s, None, self)
        self._unfinished.append((out, state))
        self.frame_times.append(state.time_s)
        self.next_frame += 1
        if not defer:
            self.finish_frames(out.index)
        return out

    def finish_frames(self, upto: int | None = None) -> int:
        """Render and record the truth of the deferred frames, oldest first, up to frame index
        ``upto`` (None: all of them); returns how many were finished."""
        n = 0
        while self._unfinished and (upto is None or self._unfinished[0][0].index <= upto):
            frame, state = self._unfinished.popleft()
            frame._image = self._render_frame(frame.index, state)
            n += 1
        return n

    def _render_frame(self, index: int, state) -> np.ndarray:
        """Frame ``index`` from the true camera pose at ``state``: its image; its truth row is appended."""
        sc, meta = self.sc, self.sc.meta
        cam_cfg = sc.camera
        t = state.time_s
        w0 = time.perf_counter()
        R_wb = state.R_world_body
        R_wc, p_wc = self.cam.camera_pose(R_wb, state.p_ned)
        frame = self.renderer.render(R_wc, p_wc, v_world_cam=state.v_ned, w_cam=self.R_cam_body @ state.pqr,
                                     frame_index=index, depth=False)
        w1 = time.perf_counter()
        if sc.world.targets:
            tt = target_truth(sc.world, p_wc, R_wc, cam_cfg)
            t_range, t_visible = tt.range_m, (tt.visible if tt.visible is not None else np.zeros(len(tt.names), bool))
        else:  # what target_truth gives for a world without targets
            t_range, t_visible = np.zeros(0), np.zeros(0, bool)
        sector_all, in_view = sector_truth_360(sc.world, R_wb, state.p_ned, cam_cfg, meta.sector_max_distance_m)
        truth = self.truth
        for key, val in (("t_s", meta.epoch_s + t), ("t_sim_s", t), ("p_ned", state.p_ned), ("v_ned", state.v_ned),
                         ("rpy", state.rpy), ("pqr", state.pqr), ("R_world_body", R_wb), ("R_world_cam", R_wc),
                         ("p_world_cam", p_wc),
                         ("sector_m", np.where(in_view, sector_all, np.nan)), ("sector_all_m", sector_all), ("in_view", in_view),
                         ("target_range_m", t_range), ("target_visible", t_visible)):
            truth[key].append(np.asarray(val))
        self.timing["render"] += w1 - w0
        self.timing["truth"] += time.perf_counter() - w1
        return frame.image

    def truth_arrays(self) -> dict[str, np.ndarray]:
        self.finish_frames()  # a frame captured but never asked for still has its truth row
        tt0 = target_truth(self.sc.world, np.zeros(3))
        arrays = {k: np.array(v) for k, v in self.truth.items()}
        arrays["sector_max_m"] = np.array(self.sc.meta.sector_max_distance_m)
        arrays["target_names"] = np.array(tt0.names, dtype="U64")
        arrays["target_p_world"] = np.asarray(tt0.p_world, float).reshape(-1, 3)
        return arrays

    def trajectory_arrays(self) -> dict[str, np.ndarray]:
        """The physics-rate trajectory and what the avoidance did (:data:`TRAJECTORY_FIELDS`)."""
        arrays = {k: np.asarray(v, float if k != "avoidance_data" else bool) for k, v in self.traj.items()}
        sc = self.sc
        route = [tuple(sc.vehicle.start_ned_m)] + [tuple(w) for w in sc.vehicle.route.waypoints]
        arrays["route_ned"] = np.asarray(route, float).reshape(-1, 3)
        arrays["body_radius_m"] = np.array(self.body_radius_m)
        arrays["avoid_margin_m"] = np.array(self.avoidance.margin_m)
        arrays["avoidance_model"] = np.array(sc.avoidance.model, dtype="U16")
        arrays["collision_t_s"] = np.array(np.nan if self.collision_t is None else self.collision_t)
        arrays["collision_with"] = np.array(self.collision_with or "", dtype="U64")
        arrays["route_speed_mps"] = np.array(sc.vehicle.route.speed_mps or np.nan)
        k = max((len(b) for _, b in self.boundary), default=0)
        arrays["boundary_t_s"] = np.array([t for t, _ in self.boundary], float)
        bw = np.full((len(self.boundary), k, 2), np.nan)
        for i, (_, b) in enumerate(self.boundary):
            bw[i, : len(b)] = b
        arrays["boundary_ne_m"] = bw  # what the autopilot held as obstacles, world north/east, NaN-padded
        kp, accel, delay = self.avoidance.braking()  # the model's stopping curve, for the outcome's false-stop rule
        arrays["braking_kp"] = np.array(kp)
        arrays["braking_accel_mss"] = np.array(accel)
        arrays["braking_delay_s"] = np.array(delay)
        return arrays

    def write_common(self, staged: StagedFiles) -> dict[str, np.ndarray]:
        """Write frames.csv, truth.npz, trajectory.npz and camera.toml (the files fly and sitl share)
        to their staged paths; returns the truth."""
        epoch = self.sc.meta.epoch_s
        rows = ["index,t_s"] + [f"{i},{epoch + t:.6f}" for i, t in enumerate(self.frame_times)]
        staged.path("frames.csv").write_text("\n".join(rows) + "\n")
        arrays = self.truth_arrays()
        save_npz_deterministic(staged.path("truth.npz"), arrays)
        save_npz_deterministic(staged.path("trajectory.npz"), self.trajectory_arrays())
        staged.path("camera.toml").write_text(camera_toml(self.sc.camera))
        return arrays


def open_video(path: Path, sc: Scenario):
    """An MJPG grey VideoWriter for the scenario's camera (RuntimeError if OpenCV cannot write it)."""
    cam_cfg, meta = sc.camera, sc.meta
    video = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), meta.fps, (cam_cfg.width, cam_cfg.height),
                            isColor=False)
    if not video.isOpened():
        raise RuntimeError(f"cannot open {path} for MJPG writing")
    video.set(cv2.VIDEOWRITER_PROP_QUALITY, meta.video_quality)
    return video


# ---------------------------------------------------------------------- fly ----------------------
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
    """Fly ``sc`` and write the export files into ``out_dir`` (created if missing), all of them
    at once when the flight is complete (module docstring)."""
    out = prepare_output_dir(out_dir)
    wall0 = time.perf_counter()
    meta = sc.meta
    # summary.png / avoidance.png of a previous flight in out_dir would no longer match: removed with the commit
    with StagedFiles(out, obsolete=("summary.png", "avoidance.png")) as staged:
        flight = Flight(sc)
        queue = _fly_loop(flight, staged, progress)
        with TlogWriter(staged.path("telemetry.tlog"), meta.epoch_s) as w:
            for t_emit, _, msg in queue:
                w.write(t_emit, msg, sysid=sc.telemetry.system_id, compid=1)
        arrays = flight.write_common(staged)
        wall = time.perf_counter() - wall0
        result = FlightResult(out, flight.next_frame, len(queue), meta.duration_s, wall)
        staged.path("flight.json").write_text(json.dumps({
            "scenario": meta.name, "scenario_file": str(sc.path), "seed": meta.seed, "aircraft": sc.vehicle.aircraft,
            "duration_s": meta.duration_s, "frames": result.frames, "messages": result.messages,
            "wall_time_s": round(wall, 3), "realtime_factor": round(result.realtime_factor, 2),
            "truth_fields": TRUTH_FIELDS,
        }, indent=2) + "\n")
        if plot:
            from flightsim.plots import flight_summary_plot

            flight_summary_plot(sc, arrays, staged.path("summary.png"))
    return result


def _fly_loop(flight: Flight, staged: StagedFiles, progress: Callable[[int, int], None] | None) -> list:
    """Step the whole flight, writing the frames to the staged video.avi; returns the autopilot's
    messages as ``(t_emit, order, message)``, sorted by time (the order they leave)."""
    streams = flight.scenario_streams()
    queue: list[tuple[float, int, object]] = []
    video = open_video(staged.path("video.avi"), flight.sc)
    try:
        while (state := flight.step()) is not None:
            for t_emit, _name, msg in streams.due(state):
                queue.append((t_emit, len(queue), msg))
            if flight.frame_due():
                frame = flight.capture()
                video.write(frame.image)
                if progress:
                    progress(flight.next_frame, flight.n_frames)
    finally:
        video.release()
    queue.sort(key=lambda item: (item[0], item[1]))
    return queue
