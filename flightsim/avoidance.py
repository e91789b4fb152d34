"""What the autopilot does with the companion's ranges: obstacle avoidance in the simulated autopilot.

docs/derivations/sectors.md: an autopilot does not fly on ranges, it limits the pilot's velocity with them, and
the two autopilots differ exactly where a camera is weak — ArduPilot applies no constraint in a
direction without data, PX4 refuses to move into it.  This module models both from their
documented behaviour and source (rules cited per function), so a simulated flight shows whether
the vehicle stops short of an obstacle with the ranges the companion really sent:

* :class:`ArduPilotAvoidance` — Copter simple avoidance with a MAVLink proximity sensor
  (``PRX1_TYPE = 2``, ``AVOID_ENABLE`` with the proximity bit; Loiter / Guided velocity):
  ``AP_Proximity_MAV`` → ``AP_Proximity_Boundary_3D`` (8 faces of 45°, per-face minimum,
  ``PRX_FILT`` low-pass, face time-out) → ``AC_Avoid::adjust_velocity_proximity`` (slide or stop,
  back-up, ``AVOID_ACCEL_MAX`` output rate limit);
* :class:`PX4Avoidance` — collision prevention in Position mode (``CP_DIST > 0``), the velocity
  form of ``CollisionPrevention::_calculateConstrainedSetpoint`` (PX4 releases up to about v1.14;
  newer releases shape the stick acceleration with the same stopping distance): 36 bins of 10°,
  ``CP_DELAY``, ``CP_GUIDE_ANG``, ``CP_GO_NO_DATA``;
* :class:`NoAvoidance` — ``model = "none"``: the pilot's demand passes unchanged.

Messages are taken as the autopilot takes them: stamped with their *arrival* time on the
simulation clock (both autopilots ignore ``time_usec``, docs/derivations/sectors.md), in the body frame at the moment
of use (the vehicle's yaw now).  Everything here is pure: the SITL feeds received messages with
:meth:`NoAvoidance.receive` (the base of every model) and the quad's controller asks :meth:`NoAvoidance.limit` every control
tick.  Horizontal only: the vertical demand passes unchanged (the camera's sectors are horizontal).

Scenario TOML, table ``[avoidance]`` (:class:`AvoidanceConfig`); ``flightsim sitl --avoidance
MODEL`` overrides ``model``.
"""

from __future__ import annotations

import dataclasses
import heapq
import math

import numpy as np

from companion.config import require, require_finite

MODELS = ("none", "ardupilot", "px4")
BEHAVES = ("slide", "stop")
UINT16_MAX = 65535
#: F450 body radius for contact: 450 mm motor-to-motor diagonal (0.225 m to a motor axis) plus a
#: 10-inch propeller's 0.127 m radius
F450_RADIUS_M = 0.35


@dataclasses.dataclass(frozen=True)
class AvoidanceConfig:
    """``[avoidance]``: which autopilot model limits the quad's velocity, and its parameters.

    Defaults are the shipped defaults of each autopilot, except ``cp_dist_m``: PX4 ships
    ``CP_DIST = −1`` (collision prevention off), so the model needs a distance to do anything.
    """

    model: str = "none"  # "ardupilot", "px4" or "none" (no avoidance; the route must then be clear)
    # ArduPilot Copter (AC_Avoid, AP_Proximity)
    avoid_margin_m: float = 2.0  # AVOID_MARGIN: distance to keep from obstacles, m
    avoid_accel_max_mss: float = 3.0  # AVOID_ACCEL_MAX: limit on how fast avoidance changes the velocity, m/s² (0 = off)
    avoid_behave: str = "slide"  # AVOID_BEHAVE: "slide" (keep the velocity along the obstacle) or "stop"
    avoid_backup_spd_mps: float = 0.75  # AVOID_BACKUP_SPD: speed to back away when inside the margin, m/s (0 = off)
    avoid_backup_dz_m: float = 0.1  # AVOID_BACKUP_DZ: dead zone inside the margin before backing away, m
    pos_kp: float = 1.0  # PSC_POSXY_P: the position controller's gain that shapes the braking curve, 1/s
    prx_filt_hz: float = 0.25  # PRX_FILT: low-pass cut-off on each proximity face, Hz (0 = off)
    face_timeout_s: float = 1.0  # a proximity face not updated for this long is dropped (PROXIMITY_FACE_RESET_MS), s
    # PX4 (CollisionPrevention, multicopter position control)
    cp_dist_m: float = 2.0  # CP_DIST: distance to keep, m (PX4 ships −1 = disabled)
    cp_delay_s: float = 0.4  # CP_DELAY: sensor and tracking delay, s
    cp_guide_ang_deg: float = 30.0  # CP_GUIDE_ANG: how far the setpoint may be turned towards free space, degrees
    cp_go_no_data: bool = False  # CP_GO_NO_DATA: allow moving into directions without data
    mpc_xy_p: float = 0.95  # MPC_XY_P: position gain, 1/s
    mpc_acc_hor_mss: float = 3.0  # MPC_ACC_HOR: horizontal acceleration, m/s²
    mpc_jerk_max_msss: float = 8.0  # MPC_JERK_MAX: jerk limit, m/s³
    # both
    stale_s: float = 0.5  # a sensor (ArduPilot) or bin (PX4) without messages for this long has no data, s

    def __post_init__(self) -> None:
        require(self.model in MODELS, f"avoidance model must be one of {', '.join(MODELS)}, got {self.model!r}")
        require(self.avoid_behave in BEHAVES, f"avoid_behave must be one of {', '.join(BEHAVES)}, got {self.avoid_behave!r}")
        for name in ("avoid_margin_m", "avoid_accel_max_mss", "avoid_backup_spd_mps", "avoid_backup_dz_m", "prx_filt_hz",
                     "cp_delay_s", "cp_guide_ang_deg"):
            require_finite(name, getattr(self, name), nonnegative=True)
        for name in ("pos_kp", "face_timeout_s", "cp_dist_m", "mpc_xy_p", "mpc_acc_hor_mss", "mpc_jerk_max_msss", "stale_s"):
            require_finite(name, getattr(self, name), positive=True)
        require(self.avoid_margin_m <= 10, f"avoid_margin_m must be <= 10 (AVOID_MARGIN range), got {self.avoid_margin_m}")
        require(self.cp_dist_m <= 15, f"cp_dist_m must be <= 15 (CP_DIST range), got {self.cp_dist_m}")
        require(self.cp_delay_s <= 1, f"cp_delay_s must be <= 1 (CP_DELAY range), got {self.cp_delay_s}")
        require(self.cp_guide_ang_deg <= 90, f"cp_guide_ang_deg must be <= 90 (CP_GUIDE_ANG range), got {self.cp_guide_ang_deg}")
        require(isinstance(self.cp_go_no_data, bool), f"cp_go_no_data must be true or false, got {self.cp_go_no_data!r}")


# ------------------------------------------------------------------------------------ shaping --
def sqrt_controller(error: float, kp: float, accel: float, dt: float) -> float:
    """ArduPilot's square-root controller (``AP_Math/control.cpp::sqrt_controller``) for error ≥ 0:
    linear ``kp·e`` below ``a/kp²``, ``√(2a(e − a/(2kp²)))`` beyond, and never more than ``e/dt``
    (no overshoot in one step).  ``AC_Avoid::get_max_speed``: the speed from which the vehicle can
    still stop within ``error``."""
    if error <= 0.0:
        return 0.0
    if kp <= 0.0:
        v = math.sqrt(2.0 * accel * error)
    else:
        lin = accel / (kp * kp)
        v = kp * error if error <= lin else math.sqrt(2.0 * accel * (error - 0.5 * lin))
    return min(v, error / dt) if dt > 0 else v


def stopping_distance(v: float, kp: float, accel: float) -> float:
    """``AC_Avoid::get_stopping_distance``: the inverse of :func:`sqrt_controller`."""
    if accel <= 0.0 or v <= 0.0:
        return 0.0
    if v < accel / kp:
        return v / kp
    return accel / (2.0 * kp * kp) + v * v / (2.0 * accel)


def jerk_limited_speed(jerk: float, accel: float, distance: float) -> float:
    """``TrajMath::computeMaxSpeedFromDistance(j, a, d, 0)`` (PX4): the speed from which a
    jerk- and acceleration-limited stop ends within ``distance``: ½(−b + √(b² + 8·a·d)), b = 4a²/j."""
    b = 4.0 * accel * accel / jerk
    return 0.5 * (-b + math.sqrt(b * b + 8.0 * accel * max(distance, 0.0)))


def _wrap360(deg: float) -> float:
    return deg % 360.0


def body_to_ned(v_body: np.ndarray, yaw: float) -> np.ndarray:
    """Horizontal body vectors (forward, right) (..., 2) → world (north, east) at heading ``yaw``."""
    v = np.asarray(v_body, float)
    c, s = math.cos(yaw), math.sin(yaw)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def ned_to_body(v_ned: np.ndarray, yaw: float) -> np.ndarray:
    """The inverse of :func:`body_to_ned`."""
    return body_to_ned(v_ned, -yaw)


def _increment_deg(msg) -> float:
    """OBSTACLE_DISTANCE sector width: ``increment_f`` when set, else ``increment`` (both autopilots)."""
    return float(msg.increment_f) if msg.increment_f else float(msg.increment)


def _closest_on_segment(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    ab = b - a
    L2 = float(ab @ ab)
    u = 0.0 if L2 <= 0 else min(max(float((p - a) @ ab) / L2, 0.0), 1.0)
    return a + u * ab


def _closest_between_segments(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """The point of segment q0–q1 closest to segment p0–p1 (2-D): their intersection when they cross,
    else the nearest of the end points' projections (for two segments that do not cross the minimum
    distance is always reached at an end of one of them).  ``AP_Math::segment_to_segment_closest_point``."""
    r, s_ = p1 - p0, q1 - q0
    den = r[0] * s_[1] - r[1] * s_[0]
    if abs(den) > 1e-12:
        d = q0 - p0
        t = (d[0] * s_[1] - d[1] * s_[0]) / den
        u = (d[0] * r[1] - d[1] * r[0]) / den
        if 0.0 <= t <= 1.0 and 0.0 <= u <= 1.0:
            return q0 + u * s_
    cands = [_closest_on_segment(q0, q1, p0), _closest_on_segment(q0, q1, p1), q0, q1]
    best, bd = cands[0], math.inf
    for c in cands:
        d = float(np.linalg.norm(c - _closest_on_segment(p0, p1, c)))
        if d < bd:
            best, bd = c, d
    return best


def _isclose(x: float, y: float) -> bool:
    """``np.isclose(x, y)`` (rtol 1e-5, atol 1e-8) for two floats."""
    if math.isfinite(x) and math.isfinite(y):
        return abs(x - y) <= 1e-08 + 1e-05 * abs(y)
    return x == y


# ------------------------------------------------------------------------------------ models ----
class NoAvoidance:
    """``model = "none"``: the pilot's demand passes unchanged."""

    name = "none"

    @property
    def margin_m(self) -> float:
        """Distance the model keeps from obstacles (from the vehicle's centre), m."""
        return 0.0

    def braking(self) -> tuple[float, float, float]:
        """(position gain 1/s, braking acceleration m/s², delay s) of the model's stopping curve, for
        :func:`stopping_distance` (the outcome's false-stop rule)."""
        return 1.0, math.inf, 0.0

    def __init__(self, config: AvoidanceConfig | None = None):
        self.config = config or AvoidanceConfig()
        self.counters: dict[str, int] = {"messages": 0}
        self._queue: list[tuple[float, int, object]] = []  # (arrival, order, message) not yet in effect
        self._order = 0

    def receive(self, t: float, msg) -> None:
        """A message from the companion that arrives at simulation time ``t``; it takes effect for
        every :meth:`limit` / :meth:`has_data` call at or after ``t`` (queued until then)."""
        self.counters["messages"] += 1
        heapq.heappush(self._queue, (float(t), self._order, msg))
        self._order += 1

    def _apply_due(self, t: float) -> None:
        while self._queue and self._queue[0][0] <= t:
            ta, _, msg = heapq.heappop(self._queue)
            self._handle(ta, msg)

    def _handle(self, t: float, msg) -> None:
        """Take one message into the model's state (models override)."""

    def has_data(self, t: float) -> bool:
        """The autopilot holds fresh obstacle data at ``t``."""
        self._apply_due(t)
        return self._has_data(t)

    def _has_data(self, t: float) -> bool:
        return False

    def limit(self, t: float, p_ned, v_ned, yaw: float, v_des_ned) -> tuple[float, float, float]:
        """The velocity (NED, m/s) the autopilot lets through for the pilot's demand ``v_des_ned``, with
        the vehicle at ``p_ned`` moving at ``v_ned`` on heading ``yaw`` (rad) at time ``t``."""
        self._apply_due(t)
        return self._limit(t, np.asarray(p_ned, float), np.asarray(v_ned, float), float(yaw), np.asarray(v_des_ned, float))

    def _limit(self, t, p_ned, v_ned, yaw, v_des) -> tuple[float, float, float]:
        return tuple(float(x) for x in v_des)

    def boundary_points(self, t: float) -> np.ndarray:
        """(K, 2) points (forward, right; body frame, m) of what the autopilot holds as obstacles at
        ``t`` (for plots); empty without data."""
        return np.zeros((0, 2))


class ArduPilotAvoidance(NoAvoidance):
    """ArduPilot Copter simple avoidance fed by OBSTACLE_DISTANCE / DISTANCE_SENSOR (docs/derivations/sectors.md).

    Proximity (``AP_Proximity_MAV::handle_obstacle_distance_msg``, ``AP_Proximity_Boundary_3D``):
    each reading (0, UINT16_MAX, below ``min_distance`` or above ``max_distance`` are skipped — so
    "clear" (max + 1) is no reading) goes to one of 8 faces of 45° centred on 0°, 45°, …; a face
    takes the minimum of a message's readings in it, low-pass filtered (``PRX_FILT``, reset after 1
    s without a write); faces without readings keep their value until ``face_timeout_s`` and
    everything is dropped when no message came for ``stale_s``.  A DISTANCE_SENSOR is one reading
    at its orientation.  Boundary (``Boundary_3D::update_boundary``): a point on each edge between
    faces at the nearer valid face's filtered distance (≥ 0.6 m), a face without data bordering a
    valid one taking the valid one's distance ("cup"), else 100 m; each face's obstacle is the
    segment between its two edge points, used when it or a neighbour holds data.

    Velocity (``AC_Avoid::adjust_velocity_proximity`` in the body frame at the current yaw; the
    braking acceleration is the flight mode's clamped to 1 m/s² (``AC_AVOID_ACCEL_CMSS_MAX``) and
    the allowed speed towards an obstacle ``sqrt_controller(|o| − margin, PSC_POSXY_P, a)``):

    * slide: for each obstacle's closest point ``o``, the velocity component towards it is cut to
      that speed, the tangential component kept (``limit_velocity_2D``);
    * stop: only obstacles crossed by the look-ahead segment v̂·(0.02 + margin + stopping
      distance) count; within the margin the velocity is zeroed, else clipped as in slide;
    * back-up (``calc_backup_velocity_2D``): more than ``avoid_backup_dz_m`` inside the margin, a
      velocity away from the obstacle of ``sqrt_controller(breach, kP, 0.4·a)``, per-quadrant
      maxima summed, capped at ``AVOID_BACKUP_SPD``, and the demand raised to it axis by axis;
    * ``AC_Avoid::limit_accel``: the modified output changes by at most ``AVOID_ACCEL_MAX``·dt per
      tick (memory reset after 200 ms without a modification).
    """

    name = "ardupilot"
    N_FACES = 8
    FACE_DEG = 45.0
    BOUNDARY_DEFAULT_M = 100.0
    BOUNDARY_MIN_M = 0.6
    FILT_RESET_S = 1.0
    ACCEL_CLAMP = 1.0  # AC_AVOID_ACCEL_CMSS_MAX, m/s²
    #: (cos, sin) of each boundary point's bearing, 45k + 22.5° (math.radians as the loop computed it)
    _EDGE_CS = tuple((math.cos(math.radians(k * 45.0 + 0.5 * 45.0)), math.sin(math.radians(k * 45.0 + 0.5 * 45.0)))
                     for k in range(8))

    @property
    def margin_m(self) -> float:
        return self.config.avoid_margin_m

    def braking(self) -> tuple[float, float, float]:
        return self.config.pos_kp, self.ACCEL_CLAMP, 0.0

    def __init__(self, config: AvoidanceConfig | None = None):
        super().__init__(config)
        n = self.N_FACES
        self.face_raw = np.full(n, np.nan)
        self.face_filt = np.full(n, np.nan)
        self.face_t = np.full(n, -math.inf)  # last write (arrival time)
        self.last_msg_t = -math.inf
        self._t_prev: float | None = None
        self._accel_mem: np.ndarray | None = None
        self._accel_mem_t = -math.inf
        self._faces_version = 0
        self._geometry_cache: tuple | None = None  # (faces version, valid faces, boundary, obstacles arrays)

    # -- proximity ----------------------------------------------------------------------------
    def _face_of(self, angle_deg: float) -> int:
        return int(_wrap360(angle_deg + 0.5 * self.FACE_DEG) // self.FACE_DEG) % self.N_FACES

    def _write_face(self, f: int, d: float, t: float) -> None:
        dt = t - self.face_t[f]
        fc = self.config.prx_filt_hz
        if not np.isfinite(self.face_filt[f]) or dt >= self.FILT_RESET_S or fc <= 0:
            self.face_filt[f] = d
        elif dt > 0:
            alpha = dt / (dt + 1.0 / (2.0 * math.pi * fc))
            self.face_filt[f] += alpha * (d - self.face_filt[f])
        self.face_raw[f] = d
        self.face_t[f] = t
        self._faces_version += 1  # the boundary and the obstacles derived from the faces are stale

    def _handle(self, t: float, msg) -> None:
        typ = msg.get_type()
        if typ == "OBSTACLE_DISTANCE":
            inc = _increment_deg(msg)
            if inc == 0:
                return
            n = min(int(round(360.0 / abs(inc))), 72)
            best: dict[int, float] = {}
            for j in range(n):
                d = int(msg.distances[j])
                if d == 0 or d == UINT16_MAX or d < msg.min_distance or d > msg.max_distance:
                    continue
                f = self._face_of(j * inc + float(msg.angle_offset))
                best[f] = min(best.get(f, math.inf), d / 100.0)
            for f, d in best.items():
                self._write_face(f, d, t)
            self.last_msg_t = t
        elif typ == "DISTANCE_SENSOR":
            if msg.orientation > 7:  # MAV_SENSOR_ROTATION_NONE … YAW_315: horizontal orientations only
                return
            d = int(msg.current_distance)
            self.last_msg_t = t
            if d == 0 or d < msg.min_distance or d > msg.max_distance:
                return
            self._write_face(self._face_of(45.0 * msg.orientation), d / 100.0, t)

    def valid_faces(self, t: float) -> np.ndarray:
        """Faces holding data at ``t`` (face time-out, and nothing once the sensor went stale)."""
        self._apply_due(t)
        if t - self.last_msg_t > self.config.stale_s:
            return np.zeros(self.N_FACES, bool)
        return np.isfinite(self.face_filt) & (t - self.face_t <= self.config.face_timeout_s)

    def _has_data(self, t: float) -> bool:
        return bool(np.any(self.valid_faces(t)))

    def boundary_body(self, t: float, ok: np.ndarray | None = None) -> np.ndarray:
        """(8, 2) boundary points (forward, right) in the body frame, m; point k on the edge between
        faces k and k+1 (bearing 45k + 22.5°).  ``ok``: :meth:`valid_faces` at ``t`` if already known."""
        ok = self.valid_faces(t) if ok is None else ok
        return self._geometry(ok)[0].copy()

    def _geometry(self, ok: np.ndarray) -> tuple[np.ndarray, tuple | None]:
        """(boundary points, obstacles arrays or None) of the faces as they are, with valid faces
        ``ok``: computed once per change of the faces or of their validity (read-only arrays)."""
        key = ok.tobytes()
        c = self._geometry_cache
        if c is not None and c[0] == self._faces_version and c[1] == key:
            return c[2], c[3]
        pts = self._boundary(ok)
        pts.flags.writeable = False
        obst = self._obstacles_from(ok, pts)
        if obst is not None:
            for arr in obst:
                arr.flags.writeable = False
        self._geometry_cache = (self._faces_version, key, pts, obst)
        return pts, obst

    def _boundary(self, ok: np.ndarray) -> np.ndarray:
        """The boundary points of :meth:`boundary_body` for valid faces ``ok`` (computed)."""
        n = self.N_FACES
        d = np.where(ok, self.face_filt, np.inf).tolist()  # Python floats: the same values, cheaper scalars
        pts = []
        for k in range(n):
            dk = min(d[k], d[(k + 1) % n])
            if not math.isfinite(dk):  # "cup": a face without data next to a valid one takes its distance
                dk = min(d[(k - 1) % n], d[(k + 2) % n])
            dk = self.BOUNDARY_DEFAULT_M if not math.isfinite(dk) else max(dk, self.BOUNDARY_MIN_M)
            c, s = self._EDGE_CS[k]
            pts.append((dk * c, dk * s))
        return np.array(pts)

    def boundary_points(self, t: float) -> np.ndarray:
        ok = self.valid_faces(t)
        return self.boundary_body(t, ok) if np.any(ok) else np.zeros((0, 2))

    def obstacles_body(self, t: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(segment start, end, closest point to the vehicle) of each face's obstacle in use."""
        used = self._obstacles_arrays(t)
        if used is None:
            return []
        A, B, C = used
        return list(zip(A.copy(), B.copy(), C.copy()))

    def _obstacles_arrays(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """:meth:`obstacles_body` as three (K, 2) arrays (starts, ends, closest points), None without
        data.  The closest points are :func:`_closest_on_segment`'s, all faces at once: ``np.vecdot``
        gives each row numpy's own 2-vector dot (``a @ b``, bit for bit), the clamp is done on the
        same floats in Python."""
        return self._geometry(self.valid_faces(t))[1]

    def _obstacles_from(self, ok: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        n = self.N_FACES
        okl = ok.tolist()
        if not any(okl):
            return None
        faces = [f for f in range(n) if okl[(f - 1) % n] or okl[f] or okl[(f + 1) % n]]
        A = pts[[(f - 1) % n for f in faces]]
        B = pts[faces]
        AB = B - A
        L2 = np.vecdot(AB, AB).tolist()
        PA = np.vecdot(np.subtract(0.0, A), AB).tolist()  # (p − a)·ab with p = 0
        U = [0.0 if l2 <= 0 else min(max(pa / l2, 0.0), 1.0) for pa, l2 in zip(PA, L2)]
        C = A + np.array(U)[:, None] * AB
        return A, B, C

    # -- velocity -------------------------------------------------------------------------------
    def _limit(self, t, p_ned, v_ned, yaw, v_des) -> tuple[float, float, float]:
        cfg = self.config
        dt = 0.0 if self._t_prev is None else max(t - self._t_prev, 0.0)
        self._t_prev = t
        if cfg.avoid_behave == "slide":
            return self._limit_slide(t, yaw, v_des, dt)
        obstacles = self.obstacles_body(t)
        if not obstacles:
            return tuple(float(x) for x in v_des)
        a = self.ACCEL_CLAMP  # the mode's acceleration (Loiter, Guided: several m/s²) clamped to 1 m/s²
        kp, margin = cfg.pos_kp, cfg.avoid_margin_m
        v_in = ned_to_body(v_des[:2], yaw)
        v = v_in.copy()
        backups: list[np.ndarray] = []
        moving = float(np.hypot(*v_in)) > 0
        if cfg.avoid_behave == "stop" and moving:
            vhat = v_in / np.hypot(*v_in)
            look = vhat * (0.02 + margin + stopping_distance(float(np.hypot(*v_in)), kp, a))
        for s, e, o in obstacles:
            no = float(np.hypot(*o))
            breach = margin - no
            if breach > cfg.avoid_backup_dz_m and no > 0:
                back = sqrt_controller(breach, kp, 0.4 * a, dt)
                backups.append(-o / no * back)
            if not moving or no <= 0:
                continue
            if cfg.avoid_behave == "slide":
                v = self._clip(v, o, no, kp, a, dt)
            else:
                c = _closest_between_segments(np.zeros(2), look, s, e)
                nc = float(np.hypot(*c))
                if nc <= 0:
                    continue
                anchor = e if np.allclose(c, s) else s
                n_hat = c / nc
                s0 = float((np.zeros(2) - anchor) @ n_hat)
                s1 = float((look - anchor) @ n_hat)
                if s0 * s1 > 0:  # the look-ahead does not cross this obstacle's line
                    continue
                v = np.zeros(2) if nc <= margin else self._clip(v, c, nc, kp, a, dt)
        if backups and cfg.avoid_backup_spd_mps > 0:
            b = self._combine_backups(backups)
            nb = float(np.hypot(*b))
            if nb > cfg.avoid_backup_spd_mps:
                b *= cfg.avoid_backup_spd_mps / nb
            for i in range(2):
                if b[i] > 0:
                    v[i] = max(v[i], b[i])
                elif b[i] < 0:
                    v[i] = min(v[i], b[i])
        out = body_to_ned(v, yaw)
        out = self._limit_accel(v_des[:2], out, t, dt)
        return float(out[0]), float(out[1]), float(v_des[2])

    def _limit_slide(self, t: float, yaw: float, v_des: np.ndarray, dt: float) -> tuple[float, float, float]:
        """:meth:`_limit` with ``avoid_behave = "slide"`` (the default), the same arithmetic on all the
        faces' obstacles at once where it does not depend on the order: the distances (numpy's
        hypot per row), the unit vectors and stopping speeds; each obstacle's clip still sees the
        velocity the previous clips left (its dot product is numpy's, ``np.vecdot`` of that velocity
        with every remaining obstacle, recomputed after a clip), so the result is bit for bit the
        loop's (tests/test_avoidance.py keeps the loop as the reference)."""
        cfg = self.config
        used = self._obstacles_arrays(t)
        if used is None:
            return tuple(float(x) for x in v_des)
        C = used[2]
        a = self.ACCEL_CLAMP
        kp, margin = cfg.pos_kp, cfg.avoid_margin_m
        vd0, vd1 = float(v_des[0]), float(v_des[1])
        cb, sb = math.cos(-yaw), math.sin(-yaw)  # ned_to_body = body_to_ned at −yaw
        v0, v1 = cb * vd0 - sb * vd1, sb * vd0 + cb * vd1
        moving = float(np.hypot(v0, v1)) > 0
        NO = np.hypot(C[:, 0], C[:, 1])
        nol = NO.tolist()
        backups: list[np.ndarray] = []
        for k, no in enumerate(nol):
            breach = margin - no
            if breach > cfg.avoid_backup_dz_m and no > 0:
                back = sqrt_controller(breach, kp, 0.4 * a, dt)
                backups.append(-C[k] / no * back)
        if moving:
            idx = [k for k, no in enumerate(nol) if no > 0]
            if idx:
                N = C[idx] / NO[idx, None]  # each obstacle's unit vector (o / |o|)
                vmax = [sqrt_controller(max(nol[k] - margin, 0.0), kp, a, dt) for k in idx]
                v = np.array([v0, v1])
                i = 0
                while i < len(idx):
                    S = np.vecdot(v, N[i:]).tolist()  # v · n of the velocity as it is now
                    for j, sj in enumerate(S):
                        if sj > vmax[i + j]:  # the first clip from here on: v changes, the rest see the new v
                            v = v + N[i + j] * (vmax[i + j] - sj)
                            i += j + 1
                            break
                    else:
                        break
                v0, v1 = v.tolist()
        if backups and cfg.avoid_backup_spd_mps > 0:
            b = self._combine_backups(backups)
            nb = float(np.hypot(*b))
            if nb > cfg.avoid_backup_spd_mps:
                b *= cfg.avoid_backup_spd_mps / nb
            vv = [v0, v1]
            for i in range(2):
                if b[i] > 0:
                    vv[i] = max(vv[i], b[i])
                elif b[i] < 0:
                    vv[i] = min(vv[i], b[i])
            v0, v1 = float(vv[0]), float(vv[1])
        c, s = math.cos(yaw), math.sin(yaw)
        o0, o1 = c * v0 - s * v1, s * v0 + c * v1  # body_to_ned
        o0, o1 = self._limit_accel_xy(vd0, vd1, o0, o1, t, dt)
        return o0, o1, float(v_des[2])

    def _limit_accel_xy(self, i0: float, i1: float, o0: float, o1: float, t: float, dt: float) -> tuple[float, float]:
        """:meth:`_limit_accel` on floats (``np.allclose`` spelled out: |x − y| ≤ 1e-8 + 1e-5·|y|
        between finite values, equality otherwise)."""
        amax = self.config.avoid_accel_max_mss
        if amax <= 0 or (_isclose(i0, o0) and _isclose(i1, o1)):
            return o0, o1
        if self._accel_mem is None or t - self._accel_mem_t > 0.2:
            self._accel_mem = np.array([i0, i1])
        m0, m1 = self._accel_mem.tolist()
        d0, d1 = o0 - m0, o1 - m1
        ndv = float(np.hypot(d0, d1))
        if ndv > amax * dt and ndv > 0:
            k = amax * dt / ndv
            o0, o1 = m0 + d0 * k, m1 + d1 * k
        self._accel_mem = np.array([o0, o1])
        self._accel_mem_t = t
        return o0, o1

    def _clip(self, v: np.ndarray, o: np.ndarray, no: float, kp: float, a: float, dt: float) -> np.ndarray:
        """``AC_Avoid::limit_velocity_2D``: cut the component towards ``o`` to the stopping speed."""
        n_hat = o / no
        vmax = sqrt_controller(max(no - self.config.avoid_margin_m, 0.0), kp, a, dt)
        s = float(v @ n_hat)
        return v + n_hat * (vmax - s) if s > vmax else v

    @staticmethod
    def _combine_backups(backups: list[np.ndarray]) -> np.ndarray:
        """``AC_Avoid::find_max_quadrant_velocity``: largest x and y per quadrant, quadrants summed."""
        quad: dict[tuple[bool, bool], np.ndarray] = {}
        for b in backups:
            key = (b[0] >= 0, b[1] >= 0)
            q = quad.setdefault(key, np.zeros(2))
            for i in range(2):
                if abs(b[i]) > abs(q[i]):
                    q[i] = b[i]
        return sum(quad.values(), np.zeros(2))

    def _limit_accel(self, v_in: np.ndarray, v_out: np.ndarray, t: float, dt: float) -> np.ndarray:
        """``AC_Avoid::limit_accel``: a modified output changes at most AVOID_ACCEL_MAX·dt per tick."""
        amax = self.config.avoid_accel_max_mss
        if amax <= 0 or np.allclose(v_in, v_out):
            return v_out
        if self._accel_mem is None or t - self._accel_mem_t > 0.2:
            self._accel_mem = v_in.copy()
        dv = v_out - self._accel_mem
        ndv = float(np.hypot(*dv))
        if ndv > amax * dt and ndv > 0:
            v_out = self._accel_mem + dv * (amax * dt / ndv)
        self._accel_mem = v_out.copy()
        self._accel_mem_t = t
        return v_out


class PX4Avoidance(NoAvoidance):
    """PX4 collision prevention, velocity form (``CollisionPrevention::_calculateConstrainedSetpoint``).

    Map (``_addObstacleSensorData``, ``_enterData``, ``_updateObstacleData``): 36 bins of 10° in
    the body frame; bin i takes the one message element at ``ceil(wrap360(10i − angle_offset) /
    increment)`` (no minimum over the 5° sectors in it); UINT16_MAX elements are skipped (the bin
    keeps its value until stale); any other value is stored, "clear" (≥ max_distance) as an
    obstacle at max_distance + 1; a bin older than ``stale_s`` holds no data.  A DISTANCE_SENSOR
    fills the bin of its orientation.  ``d_keep = max(min_distance, CP_DIST)``.

    Setpoint: no bin with data (or none fresh) → zero.  ``CP_GUIDE_ANG`` (``_adaptSetpointDirection``)
    may turn the setpoint to a bin within ±guide angle that scores better (cost CP_DIST·50·|k − i|
    − mean of its neighbours − its distance, cm).  ``CP_GO_NO_DATA`` (``_checkSetpointDirectionFeasability``):
    no data in the setpoint's bin → zero (with 1, only bins that never held data are allowed).
    Speed: for every bin within ±90° of the setpoint, stopping room ``max(0, d − d_keep −
    v∥·(CP_DELAY + data age))`` (v∥ the measured velocity towards the bin), allowed speed
    ``min(MPC_XY_P·room, jerk-limited speed(room))``, divided by the bin's projection on the
    setpoint (where > 0.01); the setpoint keeps its direction with the smallest of these speeds.
    No push-back: bins behind are ignored, the pilot can always retreat.
    """

    name = "px4"
    N_BINS = 36
    BIN_DEG = 10.0

    @property
    def margin_m(self) -> float:
        return self.config.cp_dist_m

    def braking(self) -> tuple[float, float, float]:
        return self.config.mpc_xy_p, self.config.mpc_acc_hor_mss, self.config.cp_delay_s

    def __init__(self, config: AvoidanceConfig | None = None):
        super().__init__(config)
        n = self.N_BINS
        self.dist_cm = np.full(n, UINT16_MAX, np.int64)
        self.bin_t = np.full(n, -math.inf)
        self.maxrange_cm = np.zeros(n, np.int64)
        self.data_fov = np.zeros(n, bool)
        self.min_distance_cm = UINT16_MAX
        self.map_t = -math.inf

    def _enter(self, i: int, d_cm: int, range_cm: int, t: float) -> None:
        self.dist_cm[i] = d_cm
        self.maxrange_cm[i] = range_cm
        self.bin_t[i] = t
        self.data_fov[i] = True

    def _handle(self, t: float, msg) -> None:
        typ = msg.get_type()
        if typ == "OBSTACLE_DISTANCE":
            inc = _increment_deg(msg)
            if inc <= 0:
                return
            self.map_t = max(self.map_t, t)
            self.min_distance_cm = min(self.min_distance_cm, int(msg.min_distance))
            n_el = len(msg.distances)
            for i in range(self.N_BINS):
                j = int(math.ceil(_wrap360(self.BIN_DEG * i - float(msg.angle_offset)) / inc))
                if j >= n_el:
                    continue
                d = int(msg.distances[j])
                if d == UINT16_MAX:
                    continue
                self._enter(i, d, int(msg.max_distance), t)
        elif typ == "DISTANCE_SENSOR":
            if msg.orientation > 7:
                return
            self.map_t = max(self.map_t, t)
            self.min_distance_cm = min(self.min_distance_cm, int(msg.min_distance))
            i = int(round(45.0 * msg.orientation / self.BIN_DEG)) % self.N_BINS
            self._enter(i, int(msg.current_distance), int(msg.max_distance), t)

    def bins(self, t: float) -> np.ndarray:
        """(36,) distance of each bin at ``t``, cm; UINT16_MAX without (fresh) data."""
        self._apply_due(t)
        fresh = (t - self.bin_t) <= self.config.stale_s
        return np.where(fresh, self.dist_cm, UINT16_MAX)

    def _has_data(self, t: float) -> bool:
        return bool(np.any(self.bins(t) < UINT16_MAX)) and (t - self.map_t) <= self.config.stale_s

    def boundary_points(self, t: float) -> np.ndarray:
        d = self.bins(t)
        i = np.flatnonzero(d < UINT16_MAX)
        b = np.radians(i * self.BIN_DEG)
        return np.stack([d[i] / 100.0 * np.cos(b), d[i] / 100.0 * np.sin(b)], 1)

    def _limit(self, t, p_ned, v_ned, yaw, v_des) -> tuple[float, float, float]:
        cfg = self.config
        sp = v_des[:2]
        n_sp = float(np.hypot(*sp))
        if n_sp <= 0.001:
            return tuple(float(x) for x in v_des)
        if not self._has_data(t):
            return 0.0, 0.0, float(v_des[2])
        dist = self.bins(t)
        n = self.N_BINS
        d_keep = max(self.min_distance_cm / 100.0 if self.min_distance_cm < UINT16_MAX else 0.0, cfg.cp_dist_m)
        # setpoint bin and guidance (body frame angles)
        ang = _wrap360(math.degrees(math.atan2(sp[1], sp[0]) - yaw))
        sp_idx = int(ang // self.BIN_DEG) % n
        s_hat = sp / n_sp
        g = int(cfg.cp_guide_ang_deg // self.BIN_DEG)
        if g > 0:
            best_k, best_cost = sp_idx, 9999.0
            for off in range(-g, g + 1):
                k = (sp_idx + off) % n
                if dist[k] == UINT16_MAX:
                    continue
                nb = [dist[(k + m) % n] for m in (-1, 0, 1)]
                mean = sum(cfg.cp_dist_m * 100.0 if x == UINT16_MAX else float(x) for x in nb) / 3.0
                cost = cfg.cp_dist_m * 50.0 * abs(off) - mean - float(dist[k])
                if cost < best_cost:
                    best_k, best_cost = k, cost
            if best_k != sp_idx:
                b = math.radians(best_k * self.BIN_DEG) + yaw
                s_hat = np.array([math.cos(b), math.sin(b)])
                sp_idx = best_k
        # CP_GO_NO_DATA
        if dist[sp_idx] == UINT16_MAX and (not cfg.cp_go_no_data or self.data_fov[sp_idx]):
            return 0.0, 0.0, float(v_des[2])
        vmax = n_sp
        v_meas = v_ned[:2]
        for i in range(n):
            d_cm = dist[i]
            if d_cm == UINT16_MAX or d_cm <= self.min_distance_cm:
                continue
            b = math.radians(i * self.BIN_DEG) + yaw
            b_hat = np.array([math.cos(b), math.sin(b)])
            proj = float(b_hat @ s_hat)
            if proj <= 0.01:
                continue
            d = d_cm / 100.0
            v_par = max(0.0, float(v_meas @ b_hat))
            delay = v_par * cfg.cp_delay_s
            if d_cm < self.maxrange_cm[i]:
                delay += v_par * max(t - self.bin_t[i], 0.0)
            room = max(0.0, d - d_keep - delay)
            v_bin = min(cfg.mpc_xy_p * room, jerk_limited_speed(cfg.mpc_jerk_max_msss, cfg.mpc_acc_hor_mss, room))
            vmax = min(vmax, v_bin / proj)
        out = s_hat * vmax
        return float(out[0]), float(out[1]), float(v_des[2])


def make_avoidance(config: AvoidanceConfig) -> NoAvoidance:
    """The model ``config.model`` names."""
    return {"none": NoAvoidance, "ardupilot": ArduPilotAvoidance, "px4": PX4Avoidance}[config.model](config)


__all__ = ["AvoidanceConfig", "ArduPilotAvoidance", "PX4Avoidance", "NoAvoidance", "make_avoidance", "MODELS",
           "F450_RADIUS_M", "sqrt_controller", "stopping_distance", "jerk_limited_speed"]
