"""ArduPilot Copter simple avoidance on MAVLink proximity, the simulated autopilot (docs/derivations/sectors.md).

``PRX1_TYPE = 2``, ``AVOID_ENABLE`` with the proximity bit; Loiter / Guided velocity:
``AP_Proximity_MAV`` → ``AP_Proximity_Boundary_3D`` (8 faces of 45°, per-face minimum,
``PRX_FILT`` low-pass, face time-out) → ``AC_Avoid::adjust_velocity_proximity`` (slide or stop,
back-up, ``AVOID_ACCEL_MAX`` output rate limit).  The rules and the source they follow are in
:class:`ArduPilotAvoidance`'s docstring and each method's.
"""

from __future__ import annotations

import math

import numpy as np

from flightsim.avoidance.base import NoAvoidance
from flightsim.avoidance.common import (
    UINT16_MAX,
    _closest_between_segments,
    _increment_deg,
    _isclose,
    _wrap360,
    body_to_ned,
    ned_to_body,
    sqrt_controller,
    stopping_distance,
)
from flightsim.avoidance.config import AvoidanceConfig


class ArduPilotAvoidance(NoAvoidance):
    """ArduPilot Copter simple avoidance fed by OBSTACLE_DISTANCE / DISTANCE_SENSOR (docs/derivations/sectors.md).

    Proximity (``AP_Proximity_MAV::handle_obstacle_distance_msg``, ``AP_Proximity_Boundary_3D``):
    each reading (0, UINT16_MAX, below ``min_distance`` or above ``max_distance`` are skipped — so
    "clear" (max + 1) is no reading) goes to one of 8 faces of 45° centred on 0°, 45°, …; a face
    takes the minimum of a message's readings in it, low-pass filtered (``PRX_FILT``, reset after 1
    s without a write); faces without readings keep their value until ``face_timeout_s`` and
    everything is dropped when no message came for ``stale_s``.  A DISTANCE_SENSOR
    (``handle_distance_sensor_msg``) is one reading at its orientation that *replaces* its face's
    value; one outside [min_distance, max_distance] (unknown, "clear") *resets* the face: whatever
    OBSTACLE_DISTANCE put there is gone until the next message writes it (the filter keeps its
    state).  Boundary (``Boundary_3D::update_boundary``): a point on each edge between faces at the
    nearer valid face's filtered distance (≥ 0.6 m), a face without data bordering a valid one taking
    the valid one's distance ("cup"), else 100 m; each face's obstacle is the segment between its two
    edge points, used when it or a neighbour holds data.

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
        self.face_valid = np.zeros(n, bool)  # False after a reset (``reset_face``) until the next write
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
        self.face_valid[f] = True
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
            f = self._face_of(45.0 * msg.orientation)
            if d < msg.min_distance or d > msg.max_distance:  # ``boundary.reset_face``
                if self.face_valid[f]:
                    self.face_valid[f] = False
                    self._faces_version += 1
                return
            self._write_face(f, d / 100.0, t)

    def valid_faces(self, t: float) -> np.ndarray:
        """Faces holding data at ``t`` (face time-out, and nothing once the sensor went stale)."""
        self._apply_due(t)
        if t - self.last_msg_t > self.config.stale_s:
            return np.zeros(self.N_FACES, bool)
        return self.face_valid & np.isfinite(self.face_filt) & (t - self.face_t <= self.config.face_timeout_s)

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


__all__ = ["ArduPilotAvoidance"]
