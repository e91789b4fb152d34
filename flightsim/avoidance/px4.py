"""PX4 collision prevention in Position mode, as the simulated autopilot (docs/derivations/sectors.md).

``CP_DIST > 0``; the velocity form of ``CollisionPrevention::_calculateConstrainedSetpoint`` (PX4
releases up to about v1.14; newer releases shape the stick acceleration with the same stopping
distance): 36 bins of 10°, ``CP_DELAY``, ``CP_GUIDE_ANG``, ``CP_GO_NO_DATA``.  The rules and the
source they follow are in :class:`PX4Avoidance`'s docstring.
"""

from __future__ import annotations

import math

import numpy as np

from flightsim.avoidance.base import NoAvoidance
from flightsim.avoidance.common import UINT16_MAX, _increment_deg, _wrap360, jerk_limited_speed
from flightsim.avoidance.config import AvoidanceConfig


class PX4Avoidance(NoAvoidance):
    """PX4 collision prevention, velocity form (``CollisionPrevention::_calculateConstrainedSetpoint``).

    Map (``_addObstacleSensorData``, ``_enterData``, ``_updateObstacleData``): 36 bins of 10° in
    the body frame; bin i takes the one message element at ``ceil(wrap360(10i − angle_offset) /
    increment)`` (no minimum over the 5° sectors in it); UINT16_MAX elements are skipped (the bin
    keeps its value until stale); any other value is stored, "clear" (≥ max_distance) as an
    obstacle at max_distance + 1; a bin older than ``stale_s`` holds no data.  A DISTANCE_SENSOR
    (``_addDistanceSensorData``) fills the bins its horizontal field of view spans about its
    orientation with ``min(current_distance, max_distance)``, discarded only at or below
    min_distance: an out-of-range reading (UINT16_MAX, "clear") is data, free space out to
    max_distance.  ``d_keep = max(min_distance, CP_DIST)``.

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
            d = min(int(msg.current_distance), int(msg.max_distance))
            if d <= int(msg.min_distance):
                return
            yaw = _wrap360(45.0 * msg.orientation)
            half = math.degrees(float(msg.horizontal_fov)) / 2.0
            lo, hi = math.floor((yaw - half) / self.BIN_DEG), math.floor((yaw + half) / self.BIN_DEG)
            lo, hi = lo + (lo < 0), hi + (hi < 0)  # PX4: floor above zero, ceil below
            for i in range(lo, hi + 1):
                self._enter(i % self.N_BINS, d, int(msg.max_distance), t)

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


__all__ = ["PX4Avoidance"]
