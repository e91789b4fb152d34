"""F450 quadcopter: the model's own body-rate loop plus our position / velocity / attitude loops.

What the F450 shipped with JSBSim exposes (``aircraft/F450/FlightControl.xml``): with
``fcs/ScasEngage`` = 1, ``fcs/{aileron,elevator,rudder}-cmd-norm`` (±1) become body-rate demands
of ±0.75 rad/s (roll right, pitch up, yaw right positive) that a PID closes on the gyro, mixed with
the collective ``fcs/throttle-cmd-norm`` into the four ESCs.  Its attitude loop is commented out,
so the attitude loop is ours too.

Cascade (every ``QuadGains.control_rate_hz``):

* reference: a queue of legs — turn to face the next leg, then a straight line with a trapezoidal
  speed profile (rest to rest); at a waypoint, optionally a hover of a set time and a turn in place
  by a set angle (``RouteConfig.hold_s`` / ``turn_deg``: hovering and turning in place are where
  avoidance needs ranges most, docs/derivations/sectors.md) — giving position, velocity, acceleration and
  heading references;
* position P → velocity demand (+ reference velocity); velocity PI → acceleration demand
  (+ reference acceleration); acceleration → thrust vector → roll/pitch demand (tilt-limited) and
  collective (hover throttle × thrust ratio);
* attitude P → Euler-rate demand → body rates → the model's rate loop.
"""

from __future__ import annotations

import math
from typing import Sequence

from .config import RouteConfig
from .control import Integrator, LineProfile, clip, wrap_pi
from .vehicle import FT, G, JSBSimVehicle, SimulationError


class QuadSim(JSBSimVehicle):
    """The F450, on its gear or hovering at the start, flown by :meth:`takeoff`, :meth:`goto`,
    :meth:`hold_for`, :meth:`turn_in_place`, :meth:`hold` or a route (each waypoint a straight leg
    that ends at rest, then the waypoint's hover and turn in place).

    With route waypoints in the config it takes off (if on the ground) to the first waypoint's
    altitude and flies the route.
    """

    kind = "quad"

    # ------------------------------------------------------------------ setup
    def _setup(self) -> None:
        c = self.config
        fdm = self.fdm
        on_ground = -c.start_ned_m[2] < 0.5
        fdm["ic/vt-fps"] = 0.0
        if on_ground:
            # Put the gear on the ground: the lowest contact point's height above the terrain,
            # measured at a trial height, gives the CG height at touch-down.
            lat, lon, _ = self.world.to_geodetic(c.start_ned_m[0], c.start_ned_m[1], 0.0)
            fdm["ic/lat-geod-rad"], fdm["ic/long-gc-rad"] = lat, lon
            fdm["ic/h-agl-ft"] = 1.0 / FT
            if not fdm.run_ic():
                raise SimulationError(f"F450: JSBSim rejected the initial conditions: {self._last_messages()}")
            n_gear = len(self._g_wow)
            lowest = min(fdm[f"gear/unit[{i}]/AGL-ft"] for i in range(n_gear)) if n_gear else fdm["position/h-agl-ft"]
            fdm["ic/h-agl-ft"] = fdm["position/h-agl-ft"] - lowest - 0.001 / FT  # 1 mm into the springs
        if not fdm.run_ic():
            raise SimulationError(f"F450: JSBSim rejected the initial conditions: {self._last_messages()}")
        fdm["propulsion/set-running"] = -1
        q = c.quad
        s = self._setter
        self._s_ail, self._s_elev = s("fcs/aileron-cmd-norm"), s("fcs/elevator-cmd-norm")
        self._s_rud, self._s_thr = s("fcs/rudder-cmd-norm"), s("fcs/throttle-cmd-norm")
        self._s_scas = s("fcs/ScasEngage")
        self._div = int(round(c.sim_rate_hz / q.control_rate_hz))
        self._cdt = self._div / c.sim_rate_hz
        self._i_n, self._i_e = Integrator(3.0), Integrator(3.0)
        self._i_d = Integrator(4.0)
        if on_ground:
            # Resting on the gear, motors off: JSBSim's integration is suspended until the first
            # command arms the vehicle (a 1.4 kg body on stiff BOGEY contacts would otherwise
            # chatter on the ground), so the state stays exactly at rest.
            self._s_scas(0.0)
            self._s_thr(0.0)
            fdm.suspend_integration()
            self.armed = False
        else:
            self._s_scas(1.0)
            self._s_thr(q.hover_throttle)
            self.armed = True
        pn, pe, pd = self._read()[:3]
        self._hold_p = (pn, pe, pd)
        self._yaw_ref = math.radians(c.start_heading_deg) if not on_ground else self._g_psi()
        self._legs: list[tuple] = []
        self._active: tuple | None = None
        self._active_t0 = 0.0
        self._ref = ((pn, pe, pd), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        self._face_travel = c.route.face_travel
        self._turn_rate = math.radians(c.route.yaw_rate_dps or q.yaw_rate_dps)  # rad/s of turns in place
        #: the autopilot's obstacle avoidance (``limit(t, p_ned, v_ned, yaw, v_des_ned) -> v_cmd_ned``), or
        #: None: with it, straight legs are flown as a pilot's velocity demand it may limit (:meth:`_fly_line_avoiding`)
        self.avoidance = None
        self.v_des = (0.0, 0.0, 0.0)  # the pilot's velocity demand of the last control tick (avoidance on), NED m/s
        self.v_cmd = (0.0, 0.0, 0.0)  # ... and what the avoidance let through
        if c.route.waypoints:
            self.set_route(c.route)

    def _control_divider(self) -> int:
        return self._div

    # ------------------------------------------------------------------ commands
    def _current_target(self) -> tuple[float, float, float]:
        """Where the reference will be once the queued legs are flown."""
        for leg in reversed(self._legs):
            if leg[0] == "line":
                return leg[1]
        if self._active is not None and self._active[0] == "line":
            return self._active[1]
        return self._hold_p

    def takeoff(self, altitude_m: float) -> None:
        """Arm and climb vertically to ``altitude_m`` above the origin, then hold."""
        if not (isinstance(altitude_m, (int, float)) and math.isfinite(altitude_m) and 0.5 <= altitude_m <= 500):
            raise ValueError(f"take-off altitude_m must be in [0.5, 500], got {altitude_m!r}")
        n, e, _ = self._current_target()
        self.armed = True
        self._legs.append(("line", (n, e, -float(altitude_m)), None, False))

    def goto(self, p_ned: Sequence[float], speed_mps: float | None = None, face_travel: bool | None = None) -> None:
        """Queue a straight leg to ``p_ned`` (world NED) at up to ``speed_mps``, ending at rest."""
        p = tuple(float(x) for x in p_ned)
        if len(p) != 3 or not all(math.isfinite(x) for x in p):
            raise ValueError(f"p_ned must be 3 finite numbers, got {p_ned!r}")
        if p[2] > 0.0:
            raise ValueError(f"p_ned {p} is below the ground")
        vmax = self.config.quad.max_speed_mps
        if speed_mps is not None and not (0 < speed_mps <= vmax):
            raise ValueError(f"speed_mps must be in (0, {vmax}], got {speed_mps!r}")
        self.armed = True
        self._legs.append(("line", p, speed_mps, self._face_travel if face_travel is None else face_travel))

    def hold_for(self, seconds: float) -> None:
        """Queue a hover of ``seconds`` where the queued legs end (on the heading reached there)."""
        if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and 0 <= seconds <= RouteConfig.MAX_HOLD_S):
            raise ValueError(f"hold seconds must be in [0, {RouteConfig.MAX_HOLD_S:g}], got {seconds!r}")
        if seconds > 0:
            self._legs.append(("hold", float(seconds)))

    def turn_in_place(self, delta_deg: float, rate_dps: float | None = None) -> None:
        """Queue a turn in place by ``delta_deg`` (signed, positive = clockwise from above; 360 = a
        full turn) at ``rate_dps`` (None = the route's / the gains' rate), hovering where the queued
        legs end."""
        if not (isinstance(delta_deg, (int, float)) and math.isfinite(delta_deg) and abs(delta_deg) <= RouteConfig.MAX_TURN_DEG):
            raise ValueError(f"delta_deg must be within ±{RouteConfig.MAX_TURN_DEG:g}, got {delta_deg!r}")
        if rate_dps is not None and not (isinstance(rate_dps, (int, float)) and 0 < rate_dps <= RouteConfig.MAX_YAW_RATE_DPS):
            raise ValueError(f"rate_dps must be in (0, {RouteConfig.MAX_YAW_RATE_DPS:g}], got {rate_dps!r}")
        if delta_deg != 0:
            rate = self._turn_rate if rate_dps is None else math.radians(rate_dps)
            self._legs.append(("turn", math.radians(delta_deg), rate))

    def hold(self) -> None:
        """Drop the queued legs and hold the current reference position at rest."""
        self._legs.clear()
        if self._active is not None:
            self._hold_p = self._ref[0]
        self._active = None
        self._ref = (self._hold_p, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))

    def set_route(self, route: RouteConfig | Sequence[Sequence[float]]) -> None:
        """Fly waypoints one straight leg after another (taking off first if on the ground); at
        each waypoint hover ``route.hold_s[i]`` seconds, then turn in place by ``route.turn_deg[i]``."""
        if not isinstance(route, RouteConfig):
            route = RouteConfig(waypoints=tuple(tuple(float(x) for x in wp) for wp in route))
        if not route.waypoints:
            raise ValueError("route has no waypoints")
        self._face_travel = route.face_travel
        self._turn_rate = math.radians(route.yaw_rate_dps or self.config.quad.yaw_rate_dps)
        speed = route.speed_mps or None
        if self.on_ground() or not self.armed:
            self.takeoff(-route.waypoints[0][2])
        for i, wp in enumerate(route.waypoints):
            self.goto(wp, speed)
            self.hold_for(route.hold_at(i))
            self.turn_in_place(route.turn_at(i))

    @property
    def busy(self) -> bool:
        """True while legs remain to be flown."""
        return self._active is not None or bool(self._legs)

    @property
    def reference(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """Current reference position and velocity (world NED)."""
        return self._ref[0], self._ref[1]

    # ------------------------------------------------------------------ reference generator
    def _start_next_leg(self, t: float, psi: float) -> None:
        q = self.config.quad
        while self._legs:
            leg = self._legs.pop(0)
            if leg[0] == "hold":
                self._active = ("hold", t + leg[1])
                self._active_t0 = t
                return
            if leg[0] == "turn":
                self._active = ("turn", [leg[1]], leg[2])  # [heading change still to command, rad], rate
                self._active_t0 = t
                return
            kind, target, speed, face = leg
            a = self._hold_p
            dn, de = target[0] - a[0], target[1] - a[1]
            if face and math.hypot(dn, de) > 1.0:
                want = math.atan2(de, dn)
                if abs(wrap_pi(want - self._yaw_ref)) > math.radians(1.0):
                    # turn first, then fly the line
                    self._legs.insert(0, (kind, target, speed, False))
                    self._active = ("yaw", want)
                    self._active_t0 = t
                    return
            prof = LineProfile(a, target, speed or q.max_speed_mps, q.climb_speed_mps, q.descent_speed_mps, q.max_accel_mps2)
            if prof.length < 1e-3:
                self._hold_p = target
                continue
            self._active = ("line", target, prof, speed or q.max_speed_mps)
            self._active_t0 = t
            return
        self._active = None

    def _update_reference(self, t: float, psi: float, dt: float, p_ned, v_ned) -> None:
        v_des_prev = self.v_des
        self.v_des = self.v_cmd = (0.0, 0.0, 0.0)  # no demand outside a leg flown with avoidance
        if self._active is None and self._legs:
            self._start_next_leg(t, psi)
        act = self._active
        if act is None:
            self._ref = (self._hold_p, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            return
        if act[0] == "hold":
            self._ref = (self._hold_p, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            if t >= act[1] - 1e-9:
                self._active = None
                self._start_next_leg(t, psi)
            return
        if act[0] == "turn":
            left = act[1]
            step = act[2] * dt
            inc = clip(left[0], -step, step)
            self._yaw_ref = wrap_pi(self._yaw_ref + inc)
            left[0] -= inc
            self._ref = (self._hold_p, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            if left[0] == 0.0 and abs(wrap_pi(self._yaw_ref - psi)) < math.radians(3.0):
                self._active = None
                self._start_next_leg(t, psi)
            return
        if act[0] == "yaw":
            step = self._turn_rate * dt
            err = wrap_pi(act[1] - self._yaw_ref)
            self._yaw_ref = wrap_pi(self._yaw_ref + clip(err, -step, step))
            self._ref = (self._hold_p, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            if abs(err) <= step and abs(wrap_pi(act[1] - psi)) < math.radians(3.0):
                self._active = None
                self._start_next_leg(t, psi)
            return
        if self.avoidance is not None:
            self._fly_line_avoiding(act, t, psi, dt, p_ned, v_ned, v_des_prev)
            return
        prof: LineProfile = act[2]
        tl = t - self._active_t0
        self._ref = prof.sample(tl)
        if tl >= prof.duration:
            self._hold_p = act[1]
            self._active = None
            self._start_next_leg(t, psi)

    def _fly_line_avoiding(self, act, t: float, psi: float, dt: float, p_ned, v_ned, v_des_prev) -> None:
        """A straight leg flown as a pilot's velocity demand that the avoidance may limit (docs/derivations/sectors.md).

        With avoidance on, the leg is the pilot's intent (as a pilot pushing the stick towards the
        waypoint in Loiter, or a companion sending Guided velocity targets): the demand points from
        the reference position to the waypoint at the leg's speed, ramped at ``max_accel_mps2`` and
        slowed to stop at the waypoint (v ≤ √(2·a·d)).  The avoidance limits it from the ranges the
        autopilot holds now (:mod:`flightsim.avoidance`); the reference position moves
        with the limited velocity, so a vehicle held in front of an obstacle stays there and the leg
        ends only when the waypoint is reached (at rest within 5 cm).  The reference velocity follows
        the limited demand at up to the tilt-limited acceleration (a braking demand is not softened).

        While the avoidance lets the vehicle move on, the reference stays within ``avoid_leash_m`` of
        it horizontally, in every direction (as an autopilot's position controller limits its
        position error), so the velocity demand exceeds the limited one by at most
        ``pos_kp·avoid_leash_m``.  Held, the reference stays where it stopped and the vehicle holds
        that position.  Without the leash the vehicle, released after a hold, chased a reference
        that had run ahead at the tilt limit and flew up to 1.6× the pilot's demand; with a leash
        along the demand only, a sideways slide (ArduPilot's slide, PX4's guidance) still let the
        reference run off to the side (up to 1.5× the demand in front of a wide wall).
        """
        q = self.config.quad
        target, speed = act[1], act[3]
        (rn, re, rd), (rvn, rve, rvd), _ = self._ref
        dn, de, dd = target[0] - rn, target[1] - re, target[2] - rd
        dist = math.sqrt(dn * dn + de * de + dd * dd)
        v_ref = math.sqrt(rvn * rvn + rve * rve + rvd * rvd)
        if dist < 0.05 and v_ref < 0.05:
            self._hold_p = target
            self._ref = (target, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            self.v_des = self.v_cmd = (0.0, 0.0, 0.0)
            self._active = None
            self._start_next_leg(t, psi)
            return
        u = (dn / dist, de / dist, dd / dist) if dist > 1e-9 else (0.0, 0.0, 0.0)
        h, vz = math.hypot(u[0], u[1]), abs(u[2])
        vmax = speed / h if h > 1e-9 else speed  # the leg's horizontal and vertical speed limits along u
        if vz > 1e-9:
            vmax = min(vmax, (q.climb_speed_mps if u[2] < 0 else q.descent_speed_mps) / vz)
        v_prev = math.sqrt(sum(x * x for x in v_des_prev))
        sp = min(vmax, math.sqrt(2.0 * q.max_accel_mps2 * dist), v_prev + q.max_accel_mps2 * dt)
        v_des = (u[0] * sp, u[1] * sp, u[2] * sp)
        self.v_des = v_des
        v_cmd = tuple(float(x) for x in self.avoidance.limit(t, p_ned, v_ned, psi, v_des))
        self.v_cmd = v_cmd
        # the reference velocity follows the limited demand within the vehicle's acceleration
        a_lim = G * math.tan(math.radians(q.max_tilt_deg))
        dv = (v_cmd[0] - rvn, v_cmd[1] - rve, v_cmd[2] - rvd)
        ndv = math.sqrt(sum(x * x for x in dv))
        k = min(1.0, a_lim * dt / ndv) if ndv > 0 else 1.0
        nv = (rvn + dv[0] * k, rve + dv[1] * k, rvd + dv[2] * k)
        acc = ((nv[0] - rvn) / dt, (nv[1] - rve) / dt, (nv[2] - rvd) / dt)
        rn, re, rd = rn + nv[0] * dt, re + nv[1] * dt, rd + nv[2] * dt
        if math.hypot(v_cmd[0], v_cmd[1]) > 0.05:  # moving on: the reference stays within the leash, every way
            en, ee = rn - p_ned[0], re - p_ned[1]
            off = math.hypot(en, ee)
            if off > q.avoid_leash_m:
                k = q.avoid_leash_m / off
                rn, re = p_ned[0] + en * k, p_ned[1] + ee * k
        self._ref = ((rn, re, rd), nv, acc)

    # ------------------------------------------------------------------ autopilot tick
    def _control(self) -> None:
        q = self.config.quad
        dt = self._cdt
        t = self.time_s
        pn, pe, pd, vn, ve, vd, phi, theta, psi, p, qr, r, _ = self._read()
        self._update_reference(t, psi, dt, (pn, pe, pd), (vn, ve, vd))
        if not self.armed:
            self._s_scas(0.0)
            self._s_thr(0.0)
            return
        if self.fdm.integration_suspended():
            self.fdm.resume_integration()
        (rn, re, rd), (rvn, rve, rvd), (ran, rae, rad) = self._ref
        near_ground = self.on_ground()  # on the gear: level attitude, horizontal integrators frozen
        # position -> velocity demand
        cn, ce = q.pos_kp * (rn - pn), q.pos_kp * (re - pe)
        ch = math.hypot(cn, ce)
        if ch > q.max_pos_correction_mps:
            cn, ce = cn * q.max_pos_correction_mps / ch, ce * q.max_pos_correction_mps / ch
        cd = clip(q.pos_kp * (rd - pd), -q.max_pos_correction_mps, q.max_pos_correction_mps)
        vcn, vce, vcd = rvn + cn, rve + ce, rvd + cd
        # velocity -> acceleration demand (integrators frozen while sitting on the gear)
        en, ee, ed = vcn - vn, vce - ve, vcd - vd
        an = ran + q.vel_kp_xy * en + self._i_n.update(en, q.vel_ki_xy, dt, hold=near_ground)
        ae = rae + q.vel_kp_xy * ee + self._i_e.update(ee, q.vel_ki_xy, dt, hold=near_ground)
        ad = rad + q.vel_kp_z * ed + self._i_d.update(ed, q.vel_ki_z, dt, hold=near_ground and ed > 0)
        # acceleration -> thrust vector -> attitude + collective
        fz = clip(G - ad, 0.3 * G, 1.8 * G)  # upward specific thrust needed
        max_h = fz * math.tan(math.radians(q.max_tilt_deg))
        ah = math.hypot(an, ae)
        if ah > max_h:
            an, ae = an * max_h / ah, ae * max_h / ah
        cy, sy = math.cos(psi), math.sin(psi)
        a_fwd = cy * an + sy * ae
        a_rgt = -sy * an + cy * ae
        theta_cmd = math.atan2(-a_fwd, fz)
        phi_cmd = math.atan2(a_rgt * math.cos(theta_cmd), fz)
        if near_ground:
            phi_cmd = theta_cmd = 0.0
        ratio = math.sqrt(fz * fz + an * an + ae * ae) / G
        thr = q.hover_throttle * ratio
        # attitude -> Euler rates -> body rates -> the F450 rate loop
        phid = q.att_kp * (phi_cmd - phi)
        thed = q.att_kp * (theta_cmd - theta)
        psid = q.yaw_kp * wrap_pi(self._yaw_ref - psi)
        sphi, cphi = math.sin(phi), math.cos(phi)
        sthe, cthe = math.sin(theta), math.cos(theta)
        p_cmd = phid - sthe * psid
        q_cmd = cphi * thed + sphi * cthe * psid
        r_cmd = -sphi * thed + cphi * cthe * psid
        k = 1.0 / q.max_rate_rps
        self._s_scas(1.0)
        self._s_ail(clip(p_cmd * k, -1.0, 1.0))
        self._s_elev(clip(q_cmd * k, -1.0, 1.0))
        self._s_rud(clip(r_cmd * k, -1.0, 1.0))
        self._s_thr(clip(thr, 0.0, 1.0))

    def _check_flight(self) -> None:
        if abs(self._g_phi()) > 1.2 or abs(self._g_theta()) > 1.2:
            raise SimulationError(f"F450 lost control (attitude beyond 70°) at t={self.time_s:.2f} s")
