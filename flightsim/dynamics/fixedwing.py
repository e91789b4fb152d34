"""J3Cub with a small autopilot of our own.

Cascades (all at ``FixedWingGains.control_rate_hz``):

* lateral: L1 guidance on the current route leg (or heading error → commanded turn rate) gives a
  lateral acceleration; bank = atan(a/g), limited; bank error → aileron (PI + roll-rate damping);
  rudder as a yaw damper around the coordinated-turn yaw rate;
* longitudinal: altitude error → climb-rate demand (limited); climb error → pitch (PI around the
  trim pitch plus the flight-path angle of the demand); pitch error → elevator (PI + pitch-rate
  damping); airspeed error → throttle (PI around the trim throttle plus a climb feed-forward).

All surface commands are JSBSim's normalized ``fcs/*-cmd-norm`` added to the values found by
``simulation/do_simple_trim`` at the start airspeed.  JSBSim sign conventions used here (checked
on the model): +aileron rolls right, +elevator pitches nose down, +rudder yaws left.
"""

from __future__ import annotations

import math
from typing import Sequence

from .config import RouteConfig
from .control import Integrator, clip, l1_lateral_accel, wrap_pi
from .vehicle import FT, G, JSBSimVehicle, SimulationError


class FixedWingSim(JSBSimVehicle):
    """The J3Cub, trimmed in level flight at the start, flown by heading/altitude/speed holds or a route.

    After construction it holds the start heading, altitude and airspeed; if the config has route
    waypoints it follows them instead.
    """

    kind = "fixedwing"

    # ------------------------------------------------------------------ setup
    def _setup(self) -> None:
        c = self.config
        fdm = self.fdm
        fdm["ic/vt-fps"] = c.start_airspeed_mps / FT
        fdm["ic/gamma-deg"] = 0.0
        if not fdm.run_ic():
            raise SimulationError(f"J3Cub: JSBSim rejected the initial conditions: {self._last_messages()}")
        fdm["propulsion/set-running"] = -1
        fdm["fcs/mixture-cmd-norm"] = 1.0
        try:
            fdm["simulation/do_simple_trim"] = 1  # full trim: level flight at the given airspeed
        except Exception as exc:  # jsbsim.TrimFailureError and friends
            raise SimulationError(
                f"J3Cub failed to trim at {c.start_airspeed_mps} m/s, {-c.start_ned_m[2]:.0f} m: {exc}"
            ) from None
        if fdm["simulation/trim-completed"] != 1:
            raise SimulationError(f"J3Cub failed to trim at {c.start_airspeed_mps} m/s: {self._last_messages()}")
        wn, we, wd = c.atmosphere.wind_ned_mps
        if (wn, we, wd) != (0.0, 0.0, 0.0):
            # Trimmed in still air; restart from the same attitude with the ground velocity
            # shifted by the wind, so the air-relative state (hence the trim) is unchanged once
            # the wind is switched on.
            v = [fdm[f"velocities/v-{k}-fps"] for k in ("north", "east", "down")]
            att = [fdm[f"attitude/{k}-rad"] for k in ("phi", "theta", "psi")]
            fdm["ic/vn-fps"], fdm["ic/ve-fps"], fdm["ic/vd-fps"] = v[0] + wn / FT, v[1] + we / FT, v[2] + wd / FT
            fdm["ic/phi-rad"], fdm["ic/theta-rad"], fdm["ic/psi-true-rad"] = att
            if not fdm.run_ic():
                raise SimulationError(f"J3Cub: JSBSim rejected the wind-shifted initial conditions: {self._last_messages()}")
        self.trim = {
            "throttle": fdm["fcs/throttle-cmd-norm"],
            "aileron": fdm["fcs/aileron-cmd-norm"],
            "elevator": fdm["fcs/elevator-cmd-norm"],
            "rudder": fdm["fcs/rudder-cmd-norm"],
            "pitch_trim": fdm["fcs/pitch-trim-cmd-norm"],
            "theta": fdm["attitude/theta-rad"],
        }
        s = self._setter
        self._s_ail, self._s_elev = s("fcs/aileron-cmd-norm"), s("fcs/elevator-cmd-norm")
        self._s_rud, self._s_thr = s("fcs/rudder-cmd-norm"), s("fcs/throttle-cmd-norm")
        g = self.config.fixedwing
        self._div = int(round(c.sim_rate_hz / g.control_rate_hz))
        self._cdt = self._div / c.sim_rate_hz
        self._i_roll = Integrator(0.3)
        self._i_climb = Integrator(math.radians(8.0))
        self._i_pitch = Integrator(0.3)
        self._i_speed = Integrator(0.4)
        self.heading_cmd = math.radians(c.start_heading_deg)
        self.altitude_cmd = -c.start_ned_m[2]
        self.airspeed_cmd = c.start_airspeed_mps
        self.cruise_airspeed = c.start_airspeed_mps
        self._route: list[tuple[float, float, float]] = []
        self._leg = 0
        self._leg_start = (c.start_ned_m[0], c.start_ned_m[1], c.start_ned_m[2])
        self._route_cfg = c.route
        self.mode = "hold"
        self.cross_track_m = 0.0
        if c.route.waypoints:
            self.set_route(c.route)

    def _control_divider(self) -> int:
        return self._div

    # ------------------------------------------------------------------ commands
    def command(self, heading_deg: float | None = None, altitude_m: float | None = None, airspeed_mps: float | None = None) -> None:
        """Hold a heading (deg from north), an altitude (m above the origin) and/or an airspeed.

        A heading stops route following; altitude and airspeed apply in either mode (until the
        next waypoint sets its own altitude).
        """
        for name, v in (("heading_deg", heading_deg), ("altitude_m", altitude_m), ("airspeed_mps", airspeed_mps)):
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
        if heading_deg is not None:
            self.heading_cmd = wrap_pi(math.radians(heading_deg))
            self.mode = "hold"
        if altitude_m is not None:
            if altitude_m < 20.0:
                raise ValueError(f"altitude_m {altitude_m} is below the J3Cub's 20 m floor")
            self.altitude_cmd = float(altitude_m)
        if airspeed_mps is not None:
            if not 20.0 <= airspeed_mps <= 45.0:
                raise ValueError(f"airspeed_mps {airspeed_mps} outside the J3Cub's 20..45 m/s")
            self.airspeed_cmd = float(airspeed_mps)

    def set_route(self, route: RouteConfig | Sequence[Sequence[float]]) -> None:
        """Follow waypoints (world NED) from the current position with L1 guidance."""
        if not isinstance(route, RouteConfig):
            route = RouteConfig(waypoints=tuple(tuple(float(x) for x in wp) for wp in route))
        if not route.waypoints:
            raise ValueError("route has no waypoints")
        if route.has_holds or route.has_turns:
            raise ValueError("route hold_s / turn_deg: the J3Cub cannot hover or turn in place (quad only)")
        for i, wp in enumerate(route.waypoints):
            if -wp[2] < 20.0:
                raise ValueError(f"waypoint {i} {wp} is below the J3Cub's 20 m floor")
        self._route_cfg = route
        self._route = [tuple(wp) for wp in route.waypoints]
        self._leg = 0
        pn, pe, pd = self._read()[:3]
        self._leg_start = (pn, pe, pd)
        self.altitude_cmd = -self._route[0][2]
        if route.speed_mps > 0:
            self.airspeed_cmd = route.speed_mps
        self.mode = "route"

    @property
    def waypoint_index(self) -> int:
        """Index of the waypoint being flown to (== number of waypoints once past the last)."""
        return self._leg

    # ------------------------------------------------------------------ autopilot tick
    def _lateral_accel_route(self, pn: float, pe: float, vn: float, ve: float) -> float:
        g = self.config.fixedwing
        r = self._route
        n = len(r)
        if self._leg >= n:  # past the last waypoint: keep the last leg's line
            a = self._route[-2] if n >= 2 else self._leg_start
            b = r[-1]
            ext = (b[0] + (b[0] - a[0]) * 1000.0, b[1] + (b[1] - a[1]) * 1000.0)
            acc, _, xt = l1_lateral_accel(pn, pe, vn, ve, b[0], b[1], ext[0], ext[1], g.l1_period_s, g.l1_damping)
            self.cross_track_m = xt
            return acc
        a = self._leg_start if self._leg == 0 else r[self._leg - 1]
        b = r[self._leg]
        acc, along, xt = l1_lateral_accel(pn, pe, vn, ve, a[0], a[1], b[0], b[1], g.l1_period_s, g.l1_damping)
        self.cross_track_m = xt
        seg = math.hypot(b[0] - a[0], b[1] - a[1])
        if math.hypot(b[0] - pn, b[1] - pe) <= self._switch_distance(a, b, math.hypot(vn, ve)) or along >= seg:
            self._leg += 1
            if self._leg >= n and self._route_cfg.loop:
                self._leg = 0
                self._leg_start = b
            if self._leg < n:
                self.altitude_cmd = -r[self._leg][2]
        return acc

    def _switch_distance(self, a: tuple, b: tuple, v: float) -> float:
        """Distance before waypoint ``b`` at which to turn onto the next leg (fly-by).

        At least the acceptance radius; for a course change Δχ the turn at the bank limit
        (radius R = V²/(g·tan φmax)) starts R·tan(Δχ/2) before the corner, so the aircraft rolls
        out on the next leg instead of overshooting it.
        """
        radius = self._route_cfg.acceptance_radius_m
        nxt = self._leg + 1
        r = self._route
        if nxt < len(r) or self._route_cfg.loop:
            c = r[nxt % len(r)]
            chi1 = math.atan2(b[1] - a[1], b[0] - a[0])
            chi2 = math.atan2(c[1] - b[1], c[0] - b[0])
            turn = min(abs(wrap_pi(chi2 - chi1)), math.radians(120.0))
            r_turn = v * v / (G * math.tan(math.radians(self.config.fixedwing.max_bank_deg)))
            radius = max(radius, r_turn * math.tan(turn / 2.0))
        return radius

    def _control(self) -> None:
        g = self.config.fixedwing
        dt = self._cdt
        pn, pe, pd, vn, ve, vd, phi, theta, psi, p, q, r, vt = self._read()
        V = max(vt, 10.0)
        max_bank = math.radians(g.max_bank_deg)
        # --- lateral guidance -> bank
        if self.mode == "route":
            a_lat = self._lateral_accel_route(pn, pe, vn, ve)
        else:
            turn_rate = g.heading_kp * wrap_pi(self.heading_cmd - psi)
            a_lat = V * turn_rate
        bank_cmd = clip(math.atan2(a_lat, G), -max_bank, max_bank)
        e_phi = bank_cmd - phi
        ail = self.trim["aileron"] + g.roll_kp * e_phi + self._i_roll.update(e_phi, g.roll_ki, dt) - g.roll_kd * p
        r_coord = G * math.sin(phi) * math.cos(theta) / V
        rud = self.trim["rudder"] + g.yaw_damper * (r - r_coord)
        # --- altitude -> climb rate -> pitch -> elevator
        h = -pd
        climb = -vd
        climb_cmd = clip(g.alt_kp * (self.altitude_cmd - h), -g.max_sink_mps, g.max_climb_mps)
        e_climb = climb_cmd - climb
        max_pitch = math.radians(g.max_pitch_deg)
        # airspeed has priority over altitude: below (command − margin) the pitch-up demand is
        # cut and the climb integrator frozen, so a downdraft costs height rather than a stall
        underspeed = max(0.0, self.airspeed_cmd - g.underspeed_margin_mps - vt)
        theta_cmd = self.trim["theta"] + math.asin(clip(climb_cmd / V, -0.5, 0.5)) + g.climb_kp * e_climb
        theta_cmd += self._i_climb.update(e_climb, g.climb_ki, dt, hold=underspeed > 0 and e_climb > 0)
        theta_cmd -= g.underspeed_pitch * underspeed
        theta_cmd = clip(theta_cmd, -max_pitch, max_pitch)
        e_theta = theta_cmd - theta
        elev = self.trim["elevator"] - (g.pitch_kp * e_theta + self._i_pitch.update(e_theta, g.pitch_ki, dt)) + g.pitch_kd * q
        # --- airspeed -> throttle
        e_v = self.airspeed_cmd - vt
        thr_raw = self.trim["throttle"] + g.speed_kp * e_v + self._i_speed.value + g.throttle_per_climb * climb_cmd
        saturated = (thr_raw >= 1.0 and e_v > 0) or (thr_raw <= 0.0 and e_v < 0)
        self._i_speed.update(e_v, g.speed_ki, dt, hold=saturated)
        thr = thr_raw
        self._s_ail(clip(ail, -1.0, 1.0))
        self._s_elev(clip(elev, -1.0, 1.0))
        self._s_rud(clip(rud, -1.0, 1.0))
        self._s_thr(clip(thr, 0.0, 1.0))

    def _check_flight(self) -> None:
        if self._g_alt() * FT - self.config.origin_alt_m < 2.0:
            raise SimulationError(f"J3Cub hit the ground at t={self.time_s:.2f} s")
