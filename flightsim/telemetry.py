"""Telemetry as an autopilot reports it (docs/derivations/frames.md, seed 004 gyro model, docs/derivations/sectors.md).

From the true :class:`~flightsim.dynamics.VehicleState` this builds the MAVLink messages an
ArduPilot/PX4 vehicle streams — HEARTBEAT, ATTITUDE (with body rates), LOCAL_POSITION_NED,
GLOBAL_POSITION_INT — with the error an integrator should expect:

* attitude: a gyro with a constant per-axis bias b ~ U(−bound, bound) and white rate noise,
  integrated like an AHRS between corrections: the reported attitude is Exp(w)·R_true with
  ẇ = R_world_body (b + n) (world-frame error of a body-frame rate error), plus white noise;
  the reported body rates are the true rates plus b + n;
* position: GPS-like first-order Gauss–Markov error (σ, correlation time) plus the same in
  velocity as white noise;
* latency: each message leaves the autopilot ``latency_s`` after the state it describes;
* time_boot_ms runs on the vehicle's own clock: ``boot_time_s`` of uptime at simulation start.

Everything is seeded: the same config and seed give the same messages, bit for bit.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion.config import require, require_finite
from companion.core.frames import R_to_euler_zyx, so3_exp
from companion.mavlink.dialect import mavlink


@dataclasses.dataclass(frozen=True)
class TelemetryConfig:
    """The ``[telemetry]`` table of a scenario."""

    attitude_rate_hz: float = 50.0  # ATTITUDE stream rate
    position_rate_hz: float = 20.0  # LOCAL_POSITION_NED stream rate
    global_rate_hz: float = 5.0  # GLOBAL_POSITION_INT stream rate
    attitude_noise_deg: float = 0.02  # white noise on each reported angle
    gyro_bias_deg_s: float = 0.05  # bound of the constant per-axis gyro bias (uniform ±)
    gyro_noise_deg_s: float = 0.01  # σ of the white gyro rate noise
    # The autopilot's attitude estimator pulls the gyro-integrated attitude back towards its references
    # (gravity for roll and pitch, compass / GNSS heading for yaw): a first-order correction of the error
    # with these time constants, so the error settles near τ·bias instead of growing with flight time.
    # 0 = no correction: the error is the gyro bias integrated for the whole flight (a harsher case,
    # harmless in flights of a minute; a 30-minute flight would report tens of degrees of roll error).
    attitude_tilt_tau_s: float = 0.0  # roll/pitch correction time constant, s (0 = none)
    attitude_yaw_tau_s: float = 0.0  # yaw correction time constant, s (0 = none)
    position_noise_m: float = 0.0  # σ of the Gauss–Markov position error per axis
    position_noise_tau_s: float = 30.0  # its correlation time
    velocity_noise_mps: float = 0.0  # σ of the white velocity noise per axis
    latency_s: float = 0.0  # state → message delay
    boot_time_s: float = 20.0  # vehicle uptime when the simulation starts
    system_id: int = 1  # MAVLink system id of the vehicle

    def __post_init__(self) -> None:
        for name in ("attitude_rate_hz", "position_rate_hz", "global_rate_hz"):
            require_finite(name, getattr(self, name), positive=True)
            require(getattr(self, name) <= 400, f"{name} must be <= 400 Hz")
        for name in ("attitude_noise_deg", "gyro_bias_deg_s", "gyro_noise_deg_s", "attitude_tilt_tau_s",
                     "attitude_yaw_tau_s", "position_noise_m", "velocity_noise_mps", "latency_s", "boot_time_s"):
            require_finite(name, getattr(self, name), nonnegative=True)
        require_finite("position_noise_tau_s", self.position_noise_tau_s, positive=True)
        require(self.latency_s < 1.0, f"latency_s must be < 1 s, got {self.latency_s}")
        require(isinstance(self.system_id, int) and 1 <= self.system_id <= 255, "system_id must be in 1..255")


class TelemetryModel:
    """Error states of the autopilot's estimate and the messages it sends.

    Call :meth:`advance` once per simulation step (any step size) *before* building messages
    for that state; message builders read the current error states.
    """

    def __init__(self, config: TelemetryConfig, seed: int, mav_type: int, autopilot: int = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA):
        self.config = config
        self.rng = np.random.default_rng(seed)
        self.mav_type = mav_type
        self.autopilot = autopilot  # MAV_AUTOPILOT of the HEARTBEAT: PX4 when the simulated avoidance is PX4's
        self.gyro_bias = np.radians(self.rng.uniform(-config.gyro_bias_deg_s, config.gyro_bias_deg_s, 3))
        self.w_err = np.zeros(3)  # world-frame attitude error (rotation vector)
        self.gyro_noise = np.zeros(3)  # rate noise of the current step
        self.pos_err = self.rng.normal(scale=config.position_noise_m, size=3) if config.position_noise_m > 0 else np.zeros(3)
        self.t: float | None = None

    def advance(self, state) -> None:
        """Integrate the error states up to ``state.time_s``."""
        cfg = self.config
        t = float(state.time_s)
        if self.t is None:
            self.t = t
            return
        dt = t - self.t
        if dt <= 0:
            return
        self.t = t
        # white rate noise of density σ·√dt_ref: sample its step average (σ per sample at 1/dt)
        self.gyro_noise = np.radians(cfg.gyro_noise_deg_s) * self.rng.standard_normal(3)
        self.w_err = self._corrected(self.w_err, dt) + state.R_world_body @ (self.gyro_bias + self.gyro_noise) * dt
        if cfg.position_noise_m > 0:
            a = math.exp(-dt / cfg.position_noise_tau_s)
            self.pos_err = a * self.pos_err + cfg.position_noise_m * math.sqrt(1 - a * a) * self.rng.standard_normal(3)

    def _corrected(self, w_err: np.ndarray, dt: float) -> np.ndarray:
        """The world-frame attitude error (rotation vector, NED axes) after ``dt`` of the estimator's
        correction: the north and east components (tilt) decay with ``attitude_tilt_tau_s``, the down
        component (heading) with ``attitude_yaw_tau_s``; a τ of 0 leaves its components alone."""
        cfg = self.config
        if cfg.attitude_tilt_tau_s <= 0 and cfg.attitude_yaw_tau_s <= 0:
            return w_err
        a_tilt = math.exp(-dt / cfg.attitude_tilt_tau_s) if cfg.attitude_tilt_tau_s > 0 else 1.0
        a_yaw = math.exp(-dt / cfg.attitude_yaw_tau_s) if cfg.attitude_yaw_tau_s > 0 else 1.0
        return w_err * np.array([a_tilt, a_tilt, a_yaw])

    def snapshot(self) -> tuple:
        """The error states and the random generator's state, for :meth:`restore` (the SITL
        builds telemetry ahead while the companion works and rewinds when a request changes it)."""
        return (self.rng.bit_generator.state, self.w_err.copy(), self.gyro_noise.copy(), self.pos_err.copy(), self.t)

    def restore(self, snap: tuple) -> None:
        """Return to a :meth:`snapshot`: the following draws and messages repeat exactly."""
        rng_state, w_err, gyro_noise, pos_err, t = snap
        self.rng.bit_generator.state = rng_state
        self.w_err, self.gyro_noise, self.pos_err, self.t = w_err.copy(), gyro_noise.copy(), pos_err.copy(), t

    # -- what the autopilot believes --------------------------------------------------------------
    def reported_rpy(self, state) -> np.ndarray:
        R = so3_exp(self.w_err) @ state.R_world_body
        rpy = R_to_euler_zyx(R)
        if self.config.attitude_noise_deg > 0:
            rpy = rpy + np.radians(self.config.attitude_noise_deg) * self.rng.standard_normal(3)
        rpy[2] = (rpy[2] + math.pi) % (2 * math.pi) - math.pi
        return rpy

    def reported_rates(self, state) -> np.ndarray:
        return np.asarray(state.pqr) + self.gyro_bias + self.gyro_noise

    def reported_position(self, state) -> tuple[np.ndarray, np.ndarray]:
        v = np.asarray(state.v_ned, float)
        if self.config.velocity_noise_mps > 0:
            v = v + self.config.velocity_noise_mps * self.rng.standard_normal(3)
        return np.asarray(state.p_ned, float) + self.pos_err, v

    def time_boot_ms(self, t: float) -> int:
        return int(round((self.config.boot_time_s + t) * 1000.0))

    # -- messages ---------------------------------------------------------------------------------
    def heartbeat(self, armed: bool = True):
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        return mavlink.MAVLink_heartbeat_message(
            self.mav_type, self.autopilot, base, 0, mavlink.MAV_STATE_ACTIVE, 3
        )

    def attitude(self, state):
        rpy = self.reported_rpy(state)
        pqr = self.reported_rates(state)
        return mavlink.MAVLink_attitude_message(self.time_boot_ms(state.time_s), *map(float, rpy), *map(float, pqr))

    def local_position(self, state):
        p, v = self.reported_position(state)
        return mavlink.MAVLink_local_position_ned_message(self.time_boot_ms(state.time_s), *map(float, p), *map(float, v))

    def global_position(self, state, origin) -> object:
        """GLOBAL_POSITION_INT from the (noisy) local position through ``origin`` (a LocalNED)."""
        p, v = self.reported_position(state)
        lat_rad, lon_rad, alt = origin.to_geodetic(*map(float, p))  # alt: ellipsoid height stands in for AMSL
        lat, lon = math.degrees(lat_rad), math.degrees(lon_rad)
        hdg = int(round(math.degrees(self.reported_rpy(state)[2]) % 360 * 100)) % 36000
        return mavlink.MAVLink_global_position_int_message(
            self.time_boot_ms(state.time_s), int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            int(round(-p[2] * 1000)), *(int(round(c * 100)) for c in v), hdg,
        )
