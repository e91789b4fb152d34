"""Scenario files: ``configs/scenarios/*.toml``.

A scenario names everything a flight needs, one table per part, each filled into the frozen config
dataclass of its module (unknown or misspelt keys stop with an error naming them):

* ``[scenario]`` — name, duration, the one random seed, the world file, frame rate, recording clock,
  and optionally the companion configuration the scenario is meant for (``companion_config``);
* ``[vehicle]`` — :class:`flightsim.dynamics.DynamicsConfig` (aircraft, start, route, atmosphere);
* ``[camera]`` — :class:`companion.core.camera.CameraConfig`, the companion's own camera table;
* ``[render]`` — :class:`flightsim.render.RenderOptions` (pixel noise, blur, exposure);
* ``[telemetry]`` — :class:`flightsim.telemetry.TelemetryConfig` (rates, noise, latency);
* ``[avoidance]`` — :class:`flightsim.avoidance.AvoidanceConfig` (the simulated autopilot's
  obstacle avoidance, docs/derivations/sectors.md: ``model`` "ardupilot", "px4" or "none").  With a model the quad's
  route is the pilot's intent and may cross obstacles; without one the route must be clear.

The ``[scenario] seed`` seeds everything (turbulence, gyro bias, GPS noise, pixel noise); the
tables may not carry seeds of their own, so one number reproduces a flight.  Every check that
can fail before take-off runs in :func:`load_scenario`: TOML keys, the aircraft, a start inside or
too close to an obstacle, a quad route whose waypoints or straight legs pass within 1 m of an
obstacle (:func:`check_route_clear`), a camera that sees nothing but sky, a ``companion_config``
that names no file.

Hard flights (docs/derivations/sectors.md: hovering and turning in place are where avoidance needs
ranges most) use the quad route's per-waypoint ``hold_s`` (hover) and ``turn_deg`` (turn in place,
360 = a full turn) at ``yaw_rate_dps`` (:class:`flightsim.dynamics.RouteConfig`).

``companion_config`` (a path relative to the scenario file, like ``world``) is the companion TOML
that ``flightsim sitl``, ``flightsim campaign`` and ``flightsim score`` use when none is given on
the command line (:func:`resolve_companion_config`; :func:`default_companion_config` reads it
without loading the world); without it they use ``configs/companion.toml``.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np

from companion.config import from_mapping, require, require_finite
from companion.core.camera import CameraConfig, CameraModel
from companion.core.frames import euler_zyx_to_R
from companion.errors import ConfigError
from companion.io.config_files import read_toml, shipped_config
from flightsim.avoidance import AvoidanceConfig
from flightsim.dynamics import DynamicsConfig
from flightsim.render import RenderOptions
from flightsim.telemetry import TelemetryConfig
from flightsim.world import World, check_camera_sees_something, load_world


EPOCH_2026 = 1_767_225_600.0  # 2026-01-01T00:00:00Z
#: the shipped companion configuration: what a run uses when neither the user nor the scenario names one
DEFAULT_COMPANION_CONFIG = shipped_config("companion.toml")


@dataclasses.dataclass(frozen=True)
class ScenarioMeta:
    """The ``[scenario]`` table."""

    name: str = "scenario"  # label used in files and reports
    world: str = ""  # world TOML, relative to the scenario file (required)
    duration_s: float = 10.0  # flight time simulated, s
    seed: int = 0  # seeds every random process of the flight
    fps: float = 30.0  # camera frame rate, frames/s
    epoch_s: float = EPOCH_2026  # recording clock (Unix seconds) at simulation time 0
    sector_max_distance_m: float = 40.0  # farthest range of the sector truth (OBSTACLE_DISTANCE max), m
    video_quality: int = 95  # MJPG quality of video.avi (1–100)
    companion_config: str = ""  # companion TOML for this scenario, relative to the scenario file ("" = the default)

    def __post_init__(self) -> None:
        require(bool(self.world), "world must name a world TOML file")
        require_finite("duration_s", self.duration_s, positive=True)
        require(self.duration_s <= 3600, f"duration_s must be <= 3600, got {self.duration_s}")
        require(isinstance(self.seed, int) and self.seed >= 0, f"seed must be an integer >= 0, got {self.seed!r}")
        require_finite("fps", self.fps, positive=True)
        require(self.fps <= 240, f"fps must be <= 240, got {self.fps}")
        require_finite("epoch_s", self.epoch_s, nonnegative=True)
        require_finite("sector_max_distance_m", self.sector_max_distance_m, positive=True)
        require(isinstance(self.video_quality, int) and 1 <= self.video_quality <= 100, "video_quality must be in 1..100")
        require(isinstance(self.companion_config, str), f"companion_config must be a path string, got {self.companion_config!r}")


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A loaded, validated scenario and its world."""

    path: Path
    meta: ScenarioMeta
    vehicle: DynamicsConfig
    camera: CameraConfig
    render: RenderOptions
    telemetry: TelemetryConfig
    world: World
    avoidance: AvoidanceConfig = AvoidanceConfig()

    @property
    def telemetry_seed(self) -> int:
        return self.meta.seed * 3 + 2

    @property
    def companion_config_path(self) -> Path | None:
        """The companion TOML named by ``[scenario] companion_config`` (absolute), or None."""
        return companion_config_of(self.path, self.meta)


_TABLES = {"scenario": ScenarioMeta, "vehicle": DynamicsConfig, "camera": CameraConfig,
           "render": RenderOptions, "telemetry": TelemetryConfig, "avoidance": AvoidanceConfig}


def start_pose(vehicle: DynamicsConfig) -> tuple[np.ndarray, np.ndarray]:
    """(R_world_body, p_ned) at take-off: level, on the start heading."""
    R = euler_zyx_to_R(0.0, 0.0, math.radians(vehicle.start_heading_deg))
    return R, np.asarray(vehicle.start_ned_m, float)


#: least distance from a quad's waypoints and straight legs to any obstacle surface, m
ROUTE_CLEARANCE_M = 1.0
#: spacing of the points checked along a quad's legs, m
_ROUTE_STEP_M = 0.25


def check_route_clear(world: World, vehicle: DynamicsConfig, what: str = "route", clearance_m: float = ROUTE_CLEARANCE_M) -> None:
    """Raise :class:`ConfigError` naming the waypoint and the obstacle if a quad's route passes
    within ``clearance_m`` of an obstacle (or below the ground).

    The quad flies straight lines (the take-off, if any, straight up; then start → waypoint 0 →
    waypoint 1 …; turns and holds happen in place at the waypoints), so the whole path is known
    before take-off; points every 0.25 m along it are checked.  The fixed-wing's L1 curves depend on
    its speed and the wind, so its route is not checked here.
    """
    if vehicle.kind != "quad" or not vehicle.route.waypoints:
        return
    p = np.asarray(vehicle.start_ned_m, float)
    wps = [np.asarray(wp, float) for wp in vehicle.route.waypoints]
    legs: list[tuple[np.ndarray, np.ndarray, str]] = []
    if -p[2] < 0.5:  # on its gear: straight up to the first waypoint's altitude first
        top = np.array([p[0], p[1], wps[0][2]])
        legs.append((p, top, "the take-off"))
        p = top
    for i, wp in enumerate(wps):
        legs.append((p, wp, f"the leg to route.waypoints[{i}]"))
        p = wp
    for a, b, label in legs:
        n = max(1, int(math.ceil(float(np.linalg.norm(b - a)) / _ROUTE_STEP_M)))
        for k in range(n + 1):
            world.check_start_clear(a + (b - a) * (k / n), min_clearance_m=clearance_m, what=f"{what}: {label}, at")


def companion_config_of(path: str | os.PathLike, meta: ScenarioMeta) -> Path | None:
    """``meta.companion_config`` resolved against the scenario file's folder; ConfigError if it names no file."""
    if not meta.companion_config:
        return None
    p = (Path(path).parent / meta.companion_config).resolve()
    if not p.is_file():
        raise ConfigError(f"{path}: [scenario] companion_config = {meta.companion_config!r}: no such file ({p})")
    return p


def default_companion_config(scenario_path: str | os.PathLike, given: str | os.PathLike | None = None) -> Path | None:
    """The companion TOML a command should use: ``given`` (the user's option) when not None, else the
    scenario's ``[scenario] companion_config``, else None (the caller's own default).

    Reads only the ``[scenario]`` table (no world, no pre-flight checks) but validates it: a missing
    or unreadable scenario, or a ``companion_config`` that names no file, raises ConfigError.
    """
    if given is not None:
        return Path(given)
    path = Path(scenario_path)
    data = read_toml(path, "scenario")
    try:
        meta = from_mapping(ScenarioMeta, data.get("scenario"), "scenario")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return companion_config_of(path, meta)


def resolve_companion_config(sc: Scenario, given: str | os.PathLike | None = None) -> Path | None:
    """The companion TOML a run of ``sc`` uses: ``given`` (the user's option), else the scenario's
    ``[scenario] companion_config``, else the shipped :data:`DEFAULT_COMPANION_CONFIG`.  The one
    place this chain lives (sitl, campaign)."""
    if given is not None:
        return Path(given)
    return sc.companion_config_path or DEFAULT_COMPANION_CONFIG


def set_path_key(text: str, key: str, value: str) -> tuple[str, str | None]:
    """Scenario TOML text with the first ``key = "…"`` line (``world``, ``companion_config``) set to
    ``value``, comments kept, and the value it had (None: no such line, text unchanged).  For
    copies of a scenario that live elsewhere (a campaign's variants, a Ray task's directory)."""
    import re

    m = re.search(rf'^({re.escape(key)}\s*=\s*)"([^"]*)"', text, re.M)
    if m is None:
        return text, None
    return text[: m.start()] + f'{m.group(1)}"{value}"' + text[m.end():], m.group(2)


def parse_camera_size(text: str) -> tuple[int, int]:
    """``"640x480"`` → (640, 480); a clear :class:`ConfigError` for anything else."""
    import re

    m = re.fullmatch(r"\s*([0-9]+)\s*[xX]\s*([0-9]+)\s*", str(text))
    if m is None or int(m.group(1)) < 16 or int(m.group(2)) < 16:
        raise ConfigError(f"a camera size is WIDTHxHEIGHT in pixels, at least 16x16 (e.g. 640x480), got {text!r}")
    return int(m.group(1)), int(m.group(2))


def scale_camera_text(text: str, camera: tuple[int, int], where: str = "scenario") -> str:
    """Scenario TOML text with its ``[camera]`` at ``camera`` = (width, height) pixels and the same
    field of view: fx, fy scaled with the width, the principal point with the pixel centres
    (``(c + 0.5)·k − 0.5``).  The aspect ratio must stay (:class:`ConfigError` otherwise)."""
    import re

    def value(key: str) -> float:
        m = re.search(rf"^{key} = ([0-9.]+)", text, flags=re.M)
        if m is None:
            raise ConfigError(f"{where}: no [camera] {key} line to scale")
        return float(m.group(1))

    w0, h0 = value("width"), value("height")
    w, h = camera
    if abs(w / w0 - h / h0) > 1e-9:
        raise ConfigError(f"{where}: a camera of {w}x{h} changes the aspect ratio of {w0:g}x{h0:g}; keep it")
    k = w / w0
    new = {"width": f"{w:d}", "height": f"{h:d}", "fx": f"{value('fx') * k:.2f}", "fy": f"{value('fy') * k:.2f}",
           "cx": f"{(value('cx') + 0.5) * k - 0.5:.2f}", "cy": f"{(value('cy') + 0.5) * k - 0.5:.2f}"}
    for key, v in new.items():
        text = re.sub(rf"^{key} = [0-9.]+", f"{key} = {v}", text, count=1, flags=re.M)
    return text


def scenario_at_camera(path: str | os.PathLike, camera: tuple[int, int], out_dir: str | os.PathLike) -> Path:
    """A copy of the scenario at ``camera`` = (width, height) with the same field of view
    (:func:`scale_camera_text`), written as ``out_dir/<stem>_WxH.toml``: its ``world`` and
    ``companion_config`` made absolute and its name suffixed ``_WxH``.  Loaded once to check it."""
    import re

    src = Path(path)
    text = src.read_text(encoding="utf-8")
    for key in ("world", "companion_config"):
        value = set_path_key(text, key, "")[1]
        if value:
            text, _ = set_path_key(text, key, (src.parent / value).resolve().as_posix())
    text = scale_camera_text(text, camera, str(src))
    tag = f"_{camera[0]}x{camera[1]}"
    text, n = re.subn(r'^(name\s*=\s*)"([^"]*)"', lambda m: f'{m.group(1)}"{m.group(2)}{tag}"', text, count=1, flags=re.M)
    if n != 1:
        raise ConfigError(f"{src}: no [scenario] name line to suffix")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    dst = out / f"{src.stem}{tag}.toml"
    dst.write_text(text, encoding="utf-8")
    load_scenario(dst)
    return dst


def load_scenario(path: str | os.PathLike, seed: int | None = None, avoidance: str | None = None) -> Scenario:
    """Read, validate and pre-flight-check a scenario; ``seed`` overrides ``[scenario] seed``,
    ``avoidance`` the ``[avoidance] model``."""
    path = Path(path)
    data = read_toml(path, "scenario")
    unknown = sorted(set(data) - set(_TABLES))
    if unknown:
        raise ConfigError(f"{path}: unknown table(s) {', '.join(map(repr, unknown))}; known: {', '.join(_TABLES)}")
    for table in ("vehicle", "render"):
        if "seed" in data.get(table, {}):
            raise ConfigError(f"{path}: [{table}] seed is not allowed: [scenario] seed seeds the whole flight")
    try:
        meta = from_mapping(ScenarioMeta, data.get("scenario"), "scenario")
        if seed is not None:
            meta = dataclasses.replace(meta, seed=int(seed))
        vehicle = from_mapping(DynamicsConfig, data.get("vehicle"), "vehicle")
        vehicle = dataclasses.replace(vehicle, seed=meta.seed * 3)
        camera = from_mapping(CameraConfig, data.get("camera"), "camera")
        render = from_mapping(RenderOptions, data.get("render"), "render")
        render = dataclasses.replace(render, seed=meta.seed * 3 + 1)
        telemetry = from_mapping(TelemetryConfig, data.get("telemetry"), "telemetry")
        avoid = from_mapping(AvoidanceConfig, data.get("avoidance"), "avoidance")
        if avoidance is not None:
            avoid = dataclasses.replace(avoid, model=avoidance)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    if avoid.model != "none" and vehicle.kind != "quad":
        raise ConfigError(f"{path}: [avoidance] model = {avoid.model!r} needs a multicopter: neither autopilot has "
                          "obstacle avoidance for a fixed-wing (use \"none\"; its ranges are scored on the messages)")
    world_path = (path.parent / meta.world).resolve()
    if not world_path.is_file():
        raise ConfigError(f"{path}: [scenario] world = {meta.world!r}: no such file ({world_path})")
    companion_config_of(path, meta)  # a companion_config that names no file stops here, before take-off
    world = load_world(world_path)
    # pre-flight checks: the start must be clear and the camera must see something
    R_wb, p0 = start_pose(vehicle)
    world.check_start_clear(p0, what=f"{path.name}: start position")
    if avoid.model == "none":  # with avoidance the route is the pilot's intent and may cross obstacles
        check_route_clear(world, vehicle, what=f"{path.name}: [vehicle.route]")
    R_wc, p_wc = CameraModel(camera).camera_pose(R_wb, p0)
    check_camera_sees_something(world, camera, R_wc, p_wc, what=f"{path.name}: camera at the start")
    return Scenario(path, meta, vehicle, camera, render, telemetry, world, avoid)
