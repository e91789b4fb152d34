"""Configuration of the flight-dynamics layer: aircraft, start, atmosphere, gains and route.

All dataclasses are frozen and validate themselves (``require`` → :class:`ConfigError` naming the
key), so :func:`companion.config.from_mapping` can fill them straight from a scenario TOML table.
Units: metres, seconds, degrees where the name says ``_deg``; positions in the world frame (local
NED at the origin, docs/derivations/frames.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from companion.config import require, require_finite

#: Aircraft shipped inside the jsbsim package that flightsim can fly, and their vehicle class.
AIRCRAFT: dict[str, str] = {"J3Cub": "fixedwing", "F450": "quad"}

#: Turbulence models (JSBSim ``atmosphere/turb-type``): none, MIL-F-8785C Dryden, Tustin-discretised Dryden.
TURBULENCE_TYPES: dict[str, int] = {"none": 0, "milspec": 3, "tustin": 4}


def _require_vec3(name: str, v: tuple) -> None:
    require(isinstance(v, (tuple, list)) and len(v) == 3, f"{name} must have 3 elements, got {v!r}")
    for i, x in enumerate(v):
        require_finite(f"{name}[{i}]", x)


def check_aircraft(name: str) -> str:
    """Return the vehicle class of ``name``; :class:`ConfigError` naming it and the allowed ones otherwise."""
    require(
        isinstance(name, str) and name in AIRCRAFT,
        f"unknown aircraft {name!r}; allowed: {', '.join(sorted(AIRCRAFT))}",
    )
    return AIRCRAFT[name]


@dataclass(frozen=True)
class AtmosphereConfig:
    """Steady wind and turbulence (JSBSim atmosphere model).

    ``wind_ned_mps`` is the velocity of the air mass in the world frame (where the wind blows *to*:
    (0, 5, 0) is a 5 m/s westerly).  Turbulence is JSBSim's MIL-F-8785C Dryden model
    (``milspec``, or its Tustin discretisation ``tustin``): below 1000 ft its intensity comes from
    the wind speed at 20 ft (σ_w = 0.1·W20), above 2000 ft from the severity (probability-of-
    exceedance index 1 light … 7 extreme), blended in between.  JSBSim picks the band from the
    height above *sea level*, not above ground, which is one reason the default origin is at sea
    level: with an origin at 500 m the severity table governs even 10 m above the ground.  Its
    random numbers come from the run's seed, so the same seed gives the same gusts.
    """

    wind_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    turbulence: str = "none"
    turbulence_wind_20ft_mps: float = 0.0
    turbulence_severity: int = 3

    def __post_init__(self) -> None:
        _require_vec3("wind_ned_mps", self.wind_ned_mps)
        require(
            self.turbulence in TURBULENCE_TYPES,
            f"turbulence must be one of {', '.join(TURBULENCE_TYPES)}, got {self.turbulence!r}",
        )
        require_finite("turbulence_wind_20ft_mps", self.turbulence_wind_20ft_mps, nonnegative=True)
        require(
            isinstance(self.turbulence_severity, int) and 0 <= self.turbulence_severity <= 7,
            f"turbulence_severity must be an integer 0..7, got {self.turbulence_severity!r}",
        )
        require(math.hypot(*self.wind_ned_mps) < 30.0, f"wind_ned_mps {self.wind_ned_mps} is over 30 m/s")


@dataclass(frozen=True)
class FixedWingGains:
    """J3Cub autopilot: L1 guidance / heading → bank → aileron, altitude → climb → pitch → elevator,
    airspeed → throttle.  Surface commands are JSBSim normalized units (−1…1) added to the trim."""

    control_rate_hz: float = 40.0
    # lateral: guidance
    l1_period_s: float = 18.0  #: L1 guidance period (Park-Deyst-How); shorter = tighter tracking
    l1_damping: float = 0.75
    heading_kp: float = 0.35  #: commanded turn rate per heading error (1/s)
    max_bank_deg: float = 30.0
    # lateral: bank → aileron, yaw damper
    roll_kp: float = 1.5  #: aileron per rad of bank error
    roll_ki: float = 0.05  #: aileron per rad·s
    roll_kd: float = 0.2  #: aileron per rad/s of roll rate (damping)
    yaw_damper: float = 0.6  #: rudder per rad/s of yaw-rate error from the coordinated-turn rate
    # longitudinal
    alt_kp: float = 0.25  #: commanded climb rate per metre of altitude error (1/s)
    max_climb_mps: float = 1.5
    max_sink_mps: float = 3.0
    climb_kp: float = 0.06  #: pitch (rad) per m/s of climb-rate error
    climb_ki: float = 0.03  #: pitch (rad) per m of integrated climb-rate error
    max_pitch_deg: float = 15.0
    pitch_kp: float = 2.5  #: elevator per rad of pitch error
    pitch_ki: float = 0.8
    pitch_kd: float = 0.5  #: elevator per rad/s of pitch rate (damping)
    speed_kp: float = 0.15  #: throttle per m/s of airspeed error
    speed_ki: float = 0.04
    throttle_per_climb: float = 0.05  #: throttle feed-forward per m/s of commanded climb
    underspeed_margin_mps: float = 2.0  #: airspeed below command − margin takes priority over altitude
    underspeed_pitch: float = 0.12  #: pitch-down (rad) per m/s below that

    def __post_init__(self) -> None:
        for f in self.__dataclass_fields__:
            require_finite(f, getattr(self, f), nonnegative=True)
        require(self.control_rate_hz > 0, f"control_rate_hz must be > 0, got {self.control_rate_hz}")
        require(self.l1_period_s > 0 and self.l1_damping > 0, "l1_period_s and l1_damping must be > 0")
        require(0 < self.max_bank_deg <= 60, f"max_bank_deg must be in (0, 60], got {self.max_bank_deg}")
        require(0 < self.max_pitch_deg <= 30, f"max_pitch_deg must be in (0, 30], got {self.max_pitch_deg}")
        require(self.max_climb_mps > 0 and self.max_sink_mps > 0, "max_climb_mps and max_sink_mps must be > 0")


@dataclass(frozen=True)
class QuadGains:
    """F450 position/velocity/attitude loops on top of the model's own body-rate loop.

    The F450 FCS turns ``fcs/{aileron,elevator,rudder}-cmd-norm`` into body-rate demands of
    0.75 rad/s per unit and closes a PID on the gyro; these loops produce those demands and the
    collective ``fcs/throttle-cmd-norm``.
    """

    control_rate_hz: float = 120.0
    pos_kp: float = 1.0  #: velocity (m/s) per metre of position error
    max_pos_correction_mps: float = 3.0
    #: on a leg flown with avoidance, while the avoidance lets the vehicle move on: the reference runs at
    #: most this far ahead of the vehicle along the pilot's demand (so the velocity demand exceeds the
    #: avoidance's output by at most pos_kp × this), m
    avoid_leash_m: float = 0.3
    vel_kp_xy: float = 1.8  #: acceleration (m/s²) per m/s of horizontal velocity error
    vel_ki_xy: float = 0.4
    vel_kp_z: float = 3.0
    vel_ki_z: float = 1.5
    max_tilt_deg: float = 25.0
    att_kp: float = 5.0  #: attitude-rate demand (rad/s) per rad of roll/pitch error
    yaw_kp: float = 1.5  #: yaw-rate demand per rad of heading error
    max_rate_rps: float = 0.75  #: the F450 FCS maps ±1 command to ±0.75 rad/s
    hover_throttle: float = 0.415  #: collective that balances the weight (feed-forward)
    max_accel_mps2: float = 2.0  #: acceleration of the reference along a line
    max_speed_mps: float = 10.0  #: horizontal speed limit
    climb_speed_mps: float = 2.0
    descent_speed_mps: float = 1.0
    yaw_rate_dps: float = 30.0  #: heading slew of the reference when turning to face a leg

    def __post_init__(self) -> None:
        for f in self.__dataclass_fields__:
            require_finite(f, getattr(self, f), nonnegative=True)
        for f in ("control_rate_hz", "max_rate_rps", "max_accel_mps2", "max_speed_mps", "climb_speed_mps", "descent_speed_mps", "yaw_rate_dps"):
            require(getattr(self, f) > 0, f"{f} must be > 0, got {getattr(self, f)}")
        require(0 < self.max_tilt_deg <= 45, f"max_tilt_deg must be in (0, 45], got {self.max_tilt_deg}")
        require(0 < self.hover_throttle < 1, f"hover_throttle must be in (0, 1), got {self.hover_throttle}")
        require(self.max_speed_mps <= 15, f"max_speed_mps must be <= 15 for the F450, got {self.max_speed_mps}")


@dataclass(frozen=True)
class RouteConfig:
    """Waypoints in the world frame (NED metres; altitude = −d).

    The fixed-wing follows the legs start → wp1 → wp2 … with L1 guidance at ``speed_mps`` airspeed
    (0 = keep the start airspeed), switching within ``acceptance_radius_m``; after the last one it
    holds the last leg's course (or starts over when ``loop``).  The quad flies each leg as a
    straight line at up to ``speed_mps`` (0 = its ``max_speed_mps``), stops at the waypoint, and
    holds the last one (hovering there, on its last heading, until the flight ends); with
    ``face_travel`` it first turns in place to face along the leg (forward camera).

    Quad only, per waypoint (one value per waypoint, or empty for none), the hovering and turning
    in place where docs/derivations/sectors.md says avoidance needs ranges most:

    * ``hold_s[i]`` — after arriving at waypoint i, hover there for this many seconds;
    * ``turn_deg[i]`` — then turn in place by this signed angle (positive = clockwise seen from
      above, i.e. to the right; any size: 360 is a full turn, 720 two);

    then it turns to face the next leg (``face_travel``) and flies on.  ``yaw_rate_dps`` is the
    heading rate of every turn in place of the route (0 = ``QuadGains.yaw_rate_dps``); the F450's
    rate loop saturates at 0.75 rad/s (43°/s), hence the bound of 40°/s.  The defaults (no holds,
    no turns, 0) leave a route's flight exactly as without these keys.
    """

    waypoints: tuple[tuple[float, float, float], ...] = ()
    speed_mps: float = 0.0
    acceptance_radius_m: float = 30.0
    loop: bool = False
    face_travel: bool = True
    hold_s: tuple[float, ...] = ()
    turn_deg: tuple[float, ...] = ()
    yaw_rate_dps: float = 0.0

    #: longest hover at one waypoint, s; largest turn in place at one waypoint, degrees
    MAX_HOLD_S = 3600.0
    MAX_TURN_DEG = 1080.0
    MAX_YAW_RATE_DPS = 40.0

    def __post_init__(self) -> None:
        for i, wp in enumerate(self.waypoints):
            _require_vec3(f"waypoints[{i}]", wp)
        require_finite("speed_mps", self.speed_mps, nonnegative=True)
        require_finite("acceptance_radius_m", self.acceptance_radius_m, positive=True)
        require(isinstance(self.loop, bool), f"loop must be true/false, got {self.loop!r}")
        require(isinstance(self.face_travel, bool), f"face_travel must be true/false, got {self.face_travel!r}")
        require(not self.loop or len(self.waypoints) >= 2, "loop needs at least 2 waypoints")
        n = len(self.waypoints)
        for key, bound, unit in (("hold_s", self.MAX_HOLD_S, "s"), ("turn_deg", self.MAX_TURN_DEG, "degrees")):
            vals = getattr(self, key)
            require(isinstance(vals, (tuple, list)), f"{key} must be a list with one number per waypoint, got {vals!r}")
            require(
                len(vals) in (0, n),
                f"{key} must have one value per waypoint ({n}), or be empty for none; got {len(vals)}",
            )
            for i, v in enumerate(vals):
                require_finite(f"{key}[{i}]", v, nonnegative=key == "hold_s")
                require(abs(v) <= bound, f"{key}[{i}] must be within {bound:g} {unit}, got {v!r}")
        require_finite("yaw_rate_dps", self.yaw_rate_dps, nonnegative=True)
        require(
            self.yaw_rate_dps <= self.MAX_YAW_RATE_DPS,
            f"yaw_rate_dps must be <= {self.MAX_YAW_RATE_DPS:g} (the F450 turns at most 43°/s), got {self.yaw_rate_dps!r}",
        )

    @property
    def has_holds(self) -> bool:
        """True when some waypoint has a hover time."""
        return any(v > 0 for v in self.hold_s)

    @property
    def has_turns(self) -> bool:
        """True when some waypoint has a turn in place."""
        return any(v != 0 for v in self.turn_deg)

    def hold_at(self, i: int) -> float:
        """Hover time at waypoint ``i``, s (0 when ``hold_s`` is empty)."""
        return float(self.hold_s[i]) if self.hold_s else 0.0

    def turn_at(self, i: int) -> float:
        """Turn in place at waypoint ``i``, degrees (0 when ``turn_deg`` is empty)."""
        return float(self.turn_deg[i]) if self.turn_deg else 0.0


@dataclass(frozen=True)
class DynamicsConfig:
    """One simulated vehicle: which aircraft, where it starts, the air it flies in, its gains.

    ``origin_*`` is the geodetic point (WGS-84 height) of the world frame's origin, which is also
    the ground level (sea level by default, see :class:`AtmosphereConfig` on turbulence bands).  ``start_ned_m`` is the centre of gravity at start: the fixed-wing starts
    there trimmed at ``start_airspeed_mps`` on ``start_heading_deg``; the quad starts at rest, on
    its gear when ``start_ned_m[2]`` is within 0.5 m of the ground, else hovering.
    """

    aircraft: str = "J3Cub"
    sim_rate_hz: float = 120.0
    origin_lat_deg: float = 47.397742
    origin_lon_deg: float = 8.545594
    origin_alt_m: float = 0.0
    start_ned_m: tuple[float, float, float] = (0.0, 0.0, -100.0)
    start_heading_deg: float = 0.0
    start_airspeed_mps: float = 30.0
    seed: int = 0
    atmosphere: AtmosphereConfig = field(default_factory=AtmosphereConfig)
    fixedwing: FixedWingGains = field(default_factory=FixedWingGains)
    quad: QuadGains = field(default_factory=QuadGains)
    route: RouteConfig = field(default_factory=RouteConfig)

    def __post_init__(self) -> None:
        kind = check_aircraft(self.aircraft)
        require_finite("sim_rate_hz", self.sim_rate_hz, positive=True)
        require(30 <= self.sim_rate_hz <= 1000, f"sim_rate_hz must be in [30, 1000], got {self.sim_rate_hz}")
        require_finite("origin_lat_deg", self.origin_lat_deg)
        require(-85 <= self.origin_lat_deg <= 85, f"origin_lat_deg must be in [-85, 85], got {self.origin_lat_deg}")
        require_finite("origin_lon_deg", self.origin_lon_deg)
        require(-180 <= self.origin_lon_deg <= 180, f"origin_lon_deg must be in [-180, 180], got {self.origin_lon_deg}")
        require_finite("origin_alt_m", self.origin_alt_m)
        require(-400 <= self.origin_alt_m <= 5000, f"origin_alt_m must be in [-400, 5000], got {self.origin_alt_m}")
        _require_vec3("start_ned_m", self.start_ned_m)
        require_finite("start_heading_deg", self.start_heading_deg)
        require_finite("start_airspeed_mps", self.start_airspeed_mps, nonnegative=True)
        require(isinstance(self.seed, int) and not isinstance(self.seed, bool) and 0 <= self.seed < 2**31, f"seed must be an integer in [0, 2^31), got {self.seed!r}")
        gains = self.fixedwing if kind == "fixedwing" else self.quad
        ratio = self.sim_rate_hz / gains.control_rate_hz
        require(
            abs(ratio - round(ratio)) < 1e-9 and round(ratio) >= 1,
            f"{kind} control_rate_hz ({gains.control_rate_hz}) must divide sim_rate_hz ({self.sim_rate_hz})",
        )
        if kind == "fixedwing":
            require(-self.start_ned_m[2] >= 20.0, f"the J3Cub starts in flight: start_ned_m[2] must be <= -20 (20 m above ground), got {self.start_ned_m[2]}")
            require(20.0 <= self.start_airspeed_mps <= 45.0, f"start_airspeed_mps for the J3Cub must be in [20, 45], got {self.start_airspeed_mps}")
            require(self.route.speed_mps == 0 or 20.0 <= self.route.speed_mps <= 45.0, f"route.speed_mps for the J3Cub must be 0 or in [20, 45], got {self.route.speed_mps}")
            for i, wp in enumerate(self.route.waypoints):
                require(-wp[2] >= 20.0, f"route.waypoints[{i}] is below 20 m above ground for the J3Cub: {wp}")
            require(not self.route.has_holds, "route.hold_s: the J3Cub cannot hover at a waypoint (quad only); leave hold_s empty")
            require(not self.route.has_turns, "route.turn_deg: the J3Cub cannot turn in place (quad only); leave turn_deg empty")
            require(self.route.yaw_rate_dps == 0, "route.yaw_rate_dps: the J3Cub has no turn in place (quad only); leave it 0")
        else:
            require(self.start_ned_m[2] <= 0.5, f"start_ned_m[2] = {self.start_ned_m[2]} is below the ground (z > 0 is underground)")
            require(self.route.speed_mps <= self.quad.max_speed_mps, f"route.speed_mps ({self.route.speed_mps}) exceeds quad.max_speed_mps ({self.quad.max_speed_mps})")
            for i, wp in enumerate(self.route.waypoints):
                require(wp[2] <= 0.0, f"route.waypoints[{i}] is below the ground: {wp}")

    @property
    def kind(self) -> str:
        """``"fixedwing"`` or ``"quad"``."""
        return AIRCRAFT[self.aircraft]
