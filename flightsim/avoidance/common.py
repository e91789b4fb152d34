"""What both autopilot models share (docs/derivations/sectors.md): the braking curves of ArduPilot
(``sqrt_controller``, ``stopping_distance``) and PX4 (``jerk_limited_speed``), body ↔ NED turns
of horizontal vectors, segment geometry and the OBSTACLE_DISTANCE sector width.  Each function
cites the autopilot source it follows.  Pure.
"""

from __future__ import annotations

import math

import numpy as np

UINT16_MAX = 65535  # OBSTACLE_DISTANCE / PX4 bins: no reading


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


__all__ = ["UINT16_MAX", "sqrt_controller", "stopping_distance", "jerk_limited_speed", "body_to_ned", "ned_to_body"]
