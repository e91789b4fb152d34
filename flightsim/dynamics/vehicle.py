"""JSBSim plumbing shared by the fixed-wing and the quad: loading, frames, stepping, state.

JSBSim runs with the aircraft data shipped inside the ``jsbsim`` wheel
(``jsbsim.get_default_root_dir()``); nothing is copied into this repository.  Its console output
is silenced: the static debug level is 0 and every call into JSBSim goes through a logger that
keeps the messages (``JSBSimVehicle.jsbsim_messages``) instead of printing them, so a load failure
can still say why.
"""

from __future__ import annotations

import collections
import contextlib
import math
from typing import Iterator

import jsbsim
import numpy as np

from companion.errors import CompanionError, ConfigError

from .config import TURBULENCE_TYPES, DynamicsConfig
from .geodesy import LocalNED
from .state import VehicleState

FT = 0.3048  #: metres per foot
G = 9.80665


def _euler_zyx_to_R(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Scalar fast path of :func:`companion.core.frames.euler_zyx_to_R` (R_world_body)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _R_to_euler_zyx(R: np.ndarray) -> np.ndarray:
    """Scalar fast path of :func:`companion.core.frames.R_to_euler_zyx`."""
    (r00, _, _), (r10, _, _), (r20, r21, r22) = R.tolist()
    return np.array([math.atan2(r21, r22), -math.asin(max(-1.0, min(1.0, r20))), math.atan2(r10, r00)])


class SimulationError(CompanionError, RuntimeError):
    """JSBSim could not load, trim or continue the flight (the message says which and why)."""


class _JSBSimLog(jsbsim.FGLogger):
    """Collects JSBSim's log records (bounded) instead of printing them."""

    def __init__(self, keep: int = 200) -> None:
        super().__init__()
        self.records: collections.deque[str] = collections.deque(maxlen=keep)
        self._parts: list[str] = []
        self._level = None

    def set_level(self, level) -> None:  # noqa: D401 - FGLogger interface
        self._level = level
        self._parts = []

    def file_location(self, filename: str, line: int) -> None:
        self._parts.append(f"{filename}:{line}: ")

    def message(self, message: str) -> None:
        self._parts.append(message)

    def format(self, fmt) -> None:
        pass

    def flush(self) -> None:
        text = "".join(self._parts).strip()
        if text:
            self.records.append(text)
        self._parts = []

    @contextlib.contextmanager
    def active(self) -> Iterator[None]:
        """Route JSBSim's output (of this thread) here for the duration of the block."""
        previous = jsbsim.get_logger()
        jsbsim.set_logger(self)
        try:
            yield
        finally:
            jsbsim.set_logger(previous)


def _silence_jsbsim() -> None:
    """Set JSBSim's static debug level to 0 (no banner, no echo of the configuration files)."""
    jsbsim.FGJSBBase().debug_lvl = 0


class JSBSimVehicle:
    """One JSBSim aircraft flown in the world frame, advanced in whole JSBSim frames.

    Subclasses implement :meth:`_setup` (initial conditions, trim) and :meth:`_control` (the
    autopilot tick, called every ``sim_rate_hz / control_rate_hz`` frames, before the frame).
    Time is the frame count divided by the JSBSim rate, so it is exact (frame 4·k at 120 Hz is
    exactly k/30 s) and does not drift with floating-point sums.
    """

    kind = ""

    def __init__(self, config: DynamicsConfig) -> None:
        if not isinstance(config, DynamicsConfig):
            raise ConfigError(f"expected a DynamicsConfig, got {type(config).__name__}")
        if config.kind != self.kind:
            raise ConfigError(
                f"aircraft {config.aircraft!r} is a {config.kind}; use "
                f"{'FixedWingSim' if config.kind == 'fixedwing' else 'QuadSim'} (or make_vehicle)"
            )
        self.config = config
        self.world = LocalNED(config.origin_lat_deg, config.origin_lon_deg, config.origin_alt_m)
        self.rate_hz = float(config.sim_rate_hz)
        self._frame = 0
        self._log = _JSBSimLog()
        _silence_jsbsim()
        with self._log.active():
            fdm = jsbsim.FGFDMExec(jsbsim.get_default_root_dir())
            fdm.set_debug_level(0)
            fdm.disable_output()
            if not fdm.load_model(config.aircraft):
                raise SimulationError(f"JSBSim could not load aircraft {config.aircraft!r}: {self._last_messages()}")
            fdm.set_dt(1.0 / self.rate_hz)
            self.fdm = fdm
            self._pm = fdm.get_property_manager()
            self._bind_state_nodes()
            self._set_initial_conditions()
            self._setup()
            self._apply_wind()
            # evaluate the models once without integrating, so derived values (airspeed, alpha)
            # at t = 0 already see the wind (before the turbulence filters exist: with dt = 0
            # JSBSim's Tustin filter would divide by zero)
            if fdm.integration_suspended():  # (suspending twice would lose the saved dt)
                fdm.run()
            else:
                fdm.suspend_integration()
                fdm.run()
                fdm.resume_integration()
            self._apply_turbulence()
        self._check_finite()

    # ------------------------------------------------------------------ properties
    def _node(self, name: str):
        node = self._pm.get_node(name)
        if node is None:
            raise SimulationError(f"{self.config.aircraft}: JSBSim property {name!r} does not exist")
        return node

    def _getter(self, name: str):
        return self._node(name).get_double_value

    def _setter(self, name: str):
        return self._node(name).set_double_value

    def _bind_state_nodes(self) -> None:
        g = self._getter
        self._g_lat = g("position/lat-geod-rad")
        self._g_lon = g("position/long-gc-rad")
        self._g_alt = g("position/geod-alt-ft")
        self._g_vn, self._g_ve, self._g_vd = g("velocities/v-north-fps"), g("velocities/v-east-fps"), g("velocities/v-down-fps")
        self._g_phi, self._g_theta, self._g_psi = g("attitude/phi-rad"), g("attitude/theta-rad"), g("attitude/psi-rad")
        self._g_p, self._g_q, self._g_r = g("velocities/p-rad_sec"), g("velocities/q-rad_sec"), g("velocities/r-rad_sec")
        self._g_vt = g("velocities/vt-fps")
        self._g_wow = []
        i = 0
        while self._pm.hasNode(f"gear/unit[{i}]/WOW"):
            self._g_wow.append(g(f"gear/unit[{i}]/WOW"))
            i += 1

    def _set_initial_conditions(self) -> None:
        c = self.config
        fdm = self.fdm
        lat, lon, alt = self.world.to_geodetic(*c.start_ned_m)
        fdm["ic/lat-geod-rad"] = lat
        fdm["ic/long-gc-rad"] = lon
        fdm["ic/terrain-elevation-ft"] = c.origin_alt_m / FT
        fdm["ic/h-sl-ft"] = alt / FT
        fdm["ic/psi-true-deg"] = c.start_heading_deg
        fdm["ic/phi-deg"] = 0.0
        # same seed -> same random numbers (turbulence, and any noisy JSBSim sensor)
        fdm["simulation/randomseed"] = c.seed
        fdm["atmosphere/randomseed"] = c.seed
        fdm["atmosphere/turb-type"] = 0  # wind and turbulence start after the trim

    def _apply_wind(self) -> None:
        """Steady wind, set after the initial conditions and the trim.

        (``run_ic`` resets the atmosphere's wind to the IC's own, whose direction convention
        differs from ``atmosphere/wind-*-fps``; setting the atmosphere properties afterwards is
        unambiguous: they are the air mass velocity in local NED.)
        """
        a = self.config.atmosphere
        wn, we, wd = a.wind_ned_mps
        self.fdm["atmosphere/wind-north-fps"] = wn / FT
        self.fdm["atmosphere/wind-east-fps"] = we / FT
        self.fdm["atmosphere/wind-down-fps"] = wd / FT

    def _apply_turbulence(self) -> None:
        a = self.config.atmosphere
        if a.turbulence == "none":
            return
        self.fdm["atmosphere/turb-type"] = TURBULENCE_TYPES[a.turbulence]
        self.fdm["atmosphere/turbulence/milspec/windspeed_at_20ft_AGL-fps"] = a.turbulence_wind_20ft_mps / FT
        self.fdm["atmosphere/turbulence/milspec/severity"] = a.turbulence_severity

    def _last_messages(self, n: int = 4) -> str:
        recs = list(self._log.records)[-n:]
        return " | ".join(r.replace("\n", " ") for r in recs) or "(no message from JSBSim)"

    @property
    def jsbsim_messages(self) -> list[str]:
        """JSBSim's log records so far (most recent last, bounded)."""
        return list(self._log.records)

    # ------------------------------------------------------------------ subclass hooks
    def _setup(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _control(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _control_divider(self) -> int:  # pragma: no cover - abstract
        raise NotImplementedError

    def _check_flight(self) -> None:
        """Hook called after each control tick to stop a run that left the envelope."""

    # ------------------------------------------------------------------ time and stepping
    @property
    def time_s(self) -> float:
        return self._frame / self.rate_hz

    @property
    def dt(self) -> float:
        """JSBSim integration step, s."""
        return 1.0 / self.rate_hz

    def step(self, dt: float | None = None, *, until: float | None = None) -> VehicleState:
        """Advance by ``dt`` seconds, or to time ``until``; returns the state there.

        Time advances in whole JSBSim frames: the target is rounded to the nearest frame.
        """
        if (dt is None) == (until is None):
            raise ValueError("give exactly one of dt or until")
        if dt is not None:
            if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt >= 0):
                raise ValueError(f"dt must be a finite number >= 0, got {dt!r}")
            target = self._frame + int(round(dt * self.rate_hz))
        else:
            if not (isinstance(until, (int, float)) and math.isfinite(until)):
                raise ValueError(f"until must be a finite number, got {until!r}")
            target = int(round(until * self.rate_hz))
            if target < self._frame:
                raise ValueError(f"until={until} s is before the current time {self.time_s} s")
        div = self._control_divider()
        run = self.fdm.run
        with self._log.active():
            while self._frame < target:
                if self._frame % div == 0:
                    self._control()
                    self._check_flight()
                if not run():
                    raise SimulationError(f"JSBSim stopped at t={self.time_s:.3f} s: {self._last_messages()}")
                self._frame += 1
        self._check_finite()
        return self.state()

    def run(self, duration_s: float, sample_dt_s: float) -> list[VehicleState]:
        """Fly ``duration_s`` more seconds, returning the state every ``sample_dt_s`` (start included)."""
        if not (sample_dt_s > 0 and duration_s >= 0):
            raise ValueError("need duration_s >= 0 and sample_dt_s > 0")
        t0 = self.time_s
        n = int(math.floor(duration_s / sample_dt_s + 1e-9))
        out = [self.state()]
        for k in range(1, n + 1):
            out.append(self.step(until=t0 + k * sample_dt_s))
        return out

    def _check_finite(self) -> None:
        vals = (self._g_lat(), self._g_lon(), self._g_alt(), self._g_vn(), self._g_phi(), self._g_theta(), self._g_psi())
        if not all(math.isfinite(v) for v in vals):
            raise SimulationError(f"{self.config.aircraft}: the JSBSim state became NaN/inf at t={self.time_s:.3f} s")

    # ------------------------------------------------------------------ state
    def _read(self) -> tuple[float, ...]:
        """Fast state for the control loop: (pn, pe, pd, vn, ve, vd, phi, theta, psi, p, q, r, vt).

        Position is exact in the world frame; velocity and attitude are relative to the local
        level frame at the vehicle (within 1e-4 rad of the world frame near the origin).
        """
        pn, pe, pd = self.world.from_geodetic(self._g_lat(), self._g_lon(), self._g_alt() * FT)
        return (
            pn, pe, pd,
            self._g_vn() * FT, self._g_ve() * FT, self._g_vd() * FT,
            self._g_phi(), self._g_theta(), self._g_psi(),
            self._g_p(), self._g_q(), self._g_r(),
            self._g_vt() * FT,
        )  # fmt: skip

    def on_ground(self) -> bool:
        return any(g() > 0.5 for g in self._g_wow)

    def state(self) -> VehicleState:
        """Ground truth now, in the world frame (docs/derivations/frames.md).

        Velocity and attitude, which JSBSim gives relative to the local level frame under the
        vehicle, are rotated into the world frame (the origin's tangent plane), so position,
        velocity and attitude share one frame.
        """
        lat, lon, alt = self._g_lat(), self._g_lon(), self._g_alt() * FT
        p = self.world.from_geodetic(lat, lon, alt)
        R_w_l = self.world.R_world_localned(lat, lon)
        v = R_w_l @ np.array([self._g_vn(), self._g_ve(), self._g_vd()]) * FT
        R_w_b = R_w_l @ _euler_zyx_to_R(self._g_phi(), self._g_theta(), self._g_psi())
        return VehicleState(
            time_s=self.time_s,
            p_ned=np.array(p),
            v_ned=v,
            rpy=_R_to_euler_zyx(R_w_b),
            pqr=np.array([self._g_p(), self._g_q(), self._g_r()]),
            lat_deg=math.degrees(lat),
            lon_deg=math.degrees(lon),
            alt_m=alt,
            airspeed_mps=self._g_vt() * FT,
            on_ground=self.on_ground(),
        )
