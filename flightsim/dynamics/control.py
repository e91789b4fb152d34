"""Small control building blocks shared by the autopilots (plain floats: they run every tick)."""

from __future__ import annotations

import math


def wrap_pi(a: float) -> float:
    """Angle wrapped into (−π, π]."""
    a = math.fmod(a + math.pi, 2.0 * math.pi)
    if a <= 0.0:
        a += 2.0 * math.pi
    return a - math.pi


def clip(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


class Integrator:
    """Clamped integrator (anti-windup by limit and by an explicit ``hold`` flag)."""

    __slots__ = ("value", "limit")

    def __init__(self, limit: float) -> None:
        self.value = 0.0
        self.limit = limit

    def update(self, err: float, ki: float, dt: float, hold: bool = False) -> float:
        if not hold and ki > 0.0:
            self.value = clip(self.value + ki * err * dt, -self.limit, self.limit)
        return self.value

    def reset(self, value: float = 0.0) -> None:
        self.value = value


def l1_lateral_accel(
    pn: float, pe: float, vn: float, ve: float, an: float, ae: float, bn: float, be: float, l1_period: float, l1_damping: float
) -> tuple[float, float, float]:
    """L1 path-following lateral acceleration towards the line A→B (horizontal plane).

    The vehicle at P with ground velocity V aims at the point of the line at distance
    L1 = ζ·T·|V|/π ahead (or at the nearest point of the line when farther than L1 from it) and
    commands a = 2|V|²/L1 · sin η, η being the angle from V to the aim direction (Park, Deyst and
    How, 2004).  Returns (lateral acceleration m/s², positive = to the right; along-track distance
    from A; cross-track error, positive = right of the line).
    """
    dn, de = bn - an, be - ae
    seg = math.hypot(dn, de)
    if seg < 1e-6:  # degenerate leg: aim straight at B
        tn, te = (bn - pn, be - pe)
        nrm = math.hypot(tn, te) or 1.0
        tn, te = tn / nrm, te / nrm
    else:
        tn, te = dn / seg, de / seg
    rn, re = pn - an, pe - ae
    along = rn * tn + re * te
    cross = tn * re - te * rn  # >0: P is to the right of the directed line
    v = max(math.hypot(vn, ve), 1.0)
    l1 = max(l1_damping * l1_period * v / math.pi, 1.0)
    if abs(cross) < l1:
        ahead = along + math.sqrt(l1 * l1 - cross * cross)
    else:
        ahead = along
    qn, qe = an + tn * ahead - pn, ae + te * ahead - pe
    if math.hypot(vn, ve) < 1.0:  # too slow for a course: use the leg direction as velocity
        vn, ve = tn * v, te * v
    eta = wrap_pi(math.atan2(qe, qn) - math.atan2(ve, vn))
    eta = clip(eta, -math.pi / 2, math.pi / 2)
    return 2.0 * v * v / l1 * math.sin(eta), along, cross


class LineProfile:
    """Straight-line reference from A to B with a trapezoidal speed profile (rest to rest).

    ``sample(t)`` gives position, velocity and acceleration (3-tuples, world NED) at time ``t``
    since the start of the leg; after the end it holds B at rest.
    """

    def __init__(self, a: tuple[float, float, float], b: tuple[float, float, float], v_h: float, v_up: float, v_down: float, acc: float) -> None:
        self.a = a
        self.b = b
        d = [b[i] - a[i] for i in range(3)]
        self.length = math.sqrt(sum(x * x for x in d))
        self.u = tuple(x / self.length for x in d) if self.length > 1e-9 else (0.0, 0.0, 0.0)
        # speed limit along the line from the horizontal and vertical limits
        h = math.hypot(self.u[0], self.u[1])
        vz = abs(self.u[2])
        lim = [v_h / h] if h > 1e-9 else []
        if vz > 1e-9:
            lim.append((v_up if self.u[2] < 0 else v_down) / vz)
        vmax = min(lim) if lim else v_h
        self.acc = acc
        # trapezoid (or triangle when the leg is too short to reach vmax)
        if self.length <= vmax * vmax / acc:
            vmax = math.sqrt(self.length * acc)
        self.vmax = vmax
        self.t_acc = vmax / acc if acc > 0 else 0.0
        d_acc = 0.5 * acc * self.t_acc**2
        self.t_cruise = (self.length - 2 * d_acc) / vmax if vmax > 1e-9 else 0.0
        self.duration = 2 * self.t_acc + max(self.t_cruise, 0.0)

    def sample(self, t: float) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        acc, vmax, ta, tc = self.acc, self.vmax, self.t_acc, max(self.t_cruise, 0.0)
        if t <= 0.0:
            s, v, a = 0.0, 0.0, 0.0
        elif t < ta:
            s, v, a = 0.5 * acc * t * t, acc * t, acc
        elif t < ta + tc:
            s, v, a = 0.5 * acc * ta * ta + vmax * (t - ta), vmax, 0.0
        elif t < self.duration:
            td = self.duration - t
            s, v, a = self.length - 0.5 * acc * td * td, acc * td, -acc
        else:
            s, v, a = self.length, 0.0, 0.0
        u = self.u
        return (
            (self.a[0] + u[0] * s, self.a[1] + u[1] * s, self.a[2] + u[2] * s),
            (u[0] * v, u[1] * v, u[2] * v),
            (u[0] * a, u[1] * a, u[2] * a),
        )
