"""The outcome of a closed-loop flight: did the vehicle using the companion's ranges stop short?

docs/derivations/sectors.md judges ranges by what an autopilot does with them; with the simulated autopilot's
avoidance on (:mod:`flightsim.avoidance`) a flight has an outcome, read from ``trajectory.npz``
(every physics step: position, velocity, the pilot's demand and what the avoidance let through,
the body's clearance to the nearest obstacle).  :func:`evaluate_outcome` gives score.json's
``"avoidance"`` table:

* ``collision`` — the body (a sphere of the F450's radius) touched an obstacle (the flight ends
  there), with ``collision_t_s`` and the obstacle;
* ``min_clearance_m`` — the smallest distance from the body to any obstacle surface;
* ``stop_clearance_m`` — where the vehicle first came to rest (horizontal speed below
  ``rest_speed_mps`` for ``min_stop_s``) while the pilot still demanded ≥ ``push_speed_mps``: how
  far the body could still move along the demanded direction before touching the obstacle it was
  flying at (its whole width swept, so a thin pole just beside the centre line counts), with
  ``stop_t_s``, ``stop_p_ned`` and ``stop_obstacle``;
* ``false_stop`` — it stopped or slowed below half the demanded speed for ``min_stop_s`` or longer
  with nothing within twice the margin *plus the distance the autopilot needs to stop from the
  demanded speed* (``false_stop_s``: total time so, ``false_stop_t_s``: first).  The stopping
  distance is the model's own (:func:`flightsim.avoidance.stopping_distance` at its braking
  acceleration and gain): ArduPilot brakes at 1 m/s² and starts slowing from 6 m/s about 20 m
  before the margin — that is its documented curve, not a false stop.  Only a slowdown the
  avoidance caused counts: the demand it let through (``v_cmd_ned``) was also below half the
  pilot's (a vehicle still accelerating from rest towards a new leg's demand is not stopped).
  A no-data stall of the PX4 model is one (it also shows in ``progress``);
* ``progress`` — fraction of the route's length flown (the farthest point along the route
  polyline the vehicle reached); a take-off straight up from the start (a first leg with no
  horizontal extent) is not part of it: avoidance acts horizontally, and counting the climb would
  credit every run with it;
* ``time_to_goal_s`` — first time within ``goal_radius_m`` of the last waypoint (None: never).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from companion.config import require_finite
from companion.errors import ConfigError
from flightsim.avoidance import stopping_distance


@dataclasses.dataclass(frozen=True)
class OutcomeConfig:
    """Thresholds of the outcome score."""

    rest_speed_mps: float = 0.3  # horizontal speed below which the vehicle is at rest, m/s
    push_speed_mps: float = 0.5  # the pilot demands motion when the demand is at least this, m/s
    min_stop_s: float = 0.5  # a stop or a slow-down lasts at least this long to count, s
    goal_radius_m: float = 0.5  # the goal is reached within this distance of the last waypoint, m
    false_stop_margin_factor: float = 2.0  # a stop is false with nothing within this × the margin

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            require_finite(f.name, getattr(self, f.name), positive=True)


def read_trajectory(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of a ``trajectory.npz`` (:data:`flightsim.fly.TRAJECTORY_FIELDS` and the route);
    ConfigError naming the file if it is missing or not one."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: no such trajectory file")
    try:
        with np.load(p, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except Exception as exc:
        raise ConfigError(f"{p}: cannot read as trajectory.npz: {exc}") from None
    missing = [k for k in ("t_sim_s", "p_ned", "v_ned", "v_des_ned", "clearance_m", "route_ned") if k not in out]
    if missing:
        raise ConfigError(f"{p}: not a flightsim trajectory.npz (missing {', '.join(missing)})")
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index pairs of the True runs of ``mask``."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(d[0::2].tolist(), d[1::2].tolist()))


def route_progress(p_ned: np.ndarray, route_ned: np.ndarray) -> np.ndarray:
    """(T,) arc length along the route polyline of the point of it nearest each position, m."""
    p = np.asarray(p_ned, float).reshape(-1, 3)
    r = np.asarray(route_ned, float).reshape(-1, 3)
    if len(r) < 2:
        return np.zeros(len(p))
    a, b = r[:-1], r[1:]
    seg = b - a
    L = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(L)])[:-1]
    rel = p[:, None, :] - a[None]
    u = np.einsum("tkj,kj->tk", rel, seg) / np.where(L > 0, L * L, 1.0)
    u = np.clip(u, 0.0, 1.0)
    closest = a[None] + u[..., None] * seg[None]
    d = np.linalg.norm(p[:, None, :] - closest, axis=2)
    k = np.argmin(d, axis=1)
    return cum[k] + u[np.arange(len(p)), k] * L[k]


def horizontal_route(route_ned: np.ndarray, tol_m: float = 1e-3) -> np.ndarray:
    """The route without its leading vertical legs (a take-off straight up from the start): the
    part of it the avoidance acts on.  A route that is vertical throughout is returned unchanged."""
    r = np.asarray(route_ned, float).reshape(-1, 3)
    k = 0
    while k + 1 < len(r) and np.hypot(*(r[k + 1, :2] - r[k, :2])) <= tol_m:
        k += 1
    return r if k + 1 >= len(r) else r[k:]


def evaluate_outcome(traj: dict, world=None, config: OutcomeConfig = OutcomeConfig()) -> dict:
    """score.json's ``"avoidance"`` table from a trajectory (module docstring); ``world`` (a
    :class:`flightsim.world.World`) lets the stop clearance be measured along the demanded direction."""
    cfg = config
    t = np.asarray(traj["t_sim_s"], float)
    p = np.asarray(traj["p_ned"], float).reshape(-1, 3)
    v = np.asarray(traj["v_ned"], float).reshape(-1, 3)
    v_des = np.asarray(traj["v_des_ned"], float).reshape(-1, 3)
    clear = np.asarray(traj["clearance_m"], float)
    route = horizontal_route(traj["route_ned"])
    radius = float(traj.get("body_radius_m", 0.0))
    margin = float(traj.get("avoid_margin_m", 2.0))
    model = str(traj.get("avoidance_model", "none"))
    if len(t) == 0:
        raise ConfigError("trajectory has no steps")
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    n_min = max(1, int(math.ceil(cfg.min_stop_s / dt))) if dt > 0 else 1
    speed = np.hypot(v[:, 0], v[:, 1])
    demand = np.hypot(v_des[:, 0], v_des[:, 1])
    pushing = np.isfinite(demand) & (demand >= cfg.push_speed_mps)
    coll_t = float(traj.get("collision_t_s", np.nan))
    collided = bool(np.isfinite(coll_t) or np.any(clear <= 0.0))
    if collided and not np.isfinite(coll_t):
        coll_t = float(t[np.argmax(clear <= 0.0)])

    # where it first came to rest with the pilot pushing
    stop = None
    for a, b in _runs(pushing & (speed < cfg.rest_speed_mps)):
        if b - a >= n_min and np.any(speed[:a] > 1.0):
            stop = a
            break
    stop_info: dict = {"stop_t_s": None, "stop_p_ned": None, "stop_clearance_m": None, "stop_obstacle": None}
    if stop is not None:
        k = stop
        ahead, name = _ahead_clearance(world, p[k], v_des[k], radius)
        stop_info = {"stop_t_s": round(float(t[k]), 3), "stop_p_ned": [round(float(x), 3) for x in p[k]],
                     "stop_clearance_m": round(float(ahead if ahead is not None else clear[k]), 3),
                     "stop_obstacle": name}
    # false stops: slowed below half the demand with nothing within the margins plus the model's stopping distance
    kp = float(traj.get("braking_kp", 1.0))
    acc = float(traj.get("braking_accel_mss", 1.0))
    delay = float(traj.get("braking_delay_s", 0.0))
    dem = np.where(np.isfinite(demand), demand, 0.0)
    reach = np.array([stopping_distance(float(x), kp, acc) for x in dem]) + dem * delay
    slow = pushing & (speed < 0.5 * dem) & (clear > cfg.false_stop_margin_factor * margin + reach)
    if "v_cmd_ned" in traj:  # ... and the avoidance held it back (not the dynamics accelerating from rest)
        v_cmd = np.asarray(traj["v_cmd_ned"], float).reshape(-1, 3)
        cmd = np.hypot(v_cmd[:, 0], v_cmd[:, 1])
        slow &= ~(np.isfinite(cmd) & (cmd >= 0.5 * dem))
    false_runs = [(a, b) for a, b in _runs(slow) if b - a >= n_min]
    false_s = sum(b - a for a, b in false_runs) * dt
    # progress along the route
    along = route_progress(p, route)
    total = float(np.sum(np.linalg.norm(np.diff(route, axis=0), axis=1))) if len(route) > 1 else 0.0
    progress = float(np.max(along) / total) if total > 0 else 1.0
    goal = np.linalg.norm(p - route[-1], axis=1) <= cfg.goal_radius_m
    return {
        "model": model,
        "margin_m": margin,
        "body_radius_m": radius,
        "collision": collided,
        "collision_t_s": round(coll_t, 3) if collided else None,
        "collision_with": (str(traj["collision_with"]) or None) if collided and "collision_with" in traj else None,
        "min_clearance_m": round(float(np.min(clear)), 3),
        **stop_info,
        "false_stop": bool(false_runs),
        "false_stop_s": round(false_s, 3),
        "false_stop_t_s": round(float(t[false_runs[0][0]]), 3) if false_runs else None,
        "progress": round(min(progress, 1.0), 4),
        "time_to_goal_s": round(float(t[np.argmax(goal)]), 3) if np.any(goal) else None,
        "max_speed_mps": round(float(np.max(speed)), 3),
        "demanded_speed_mps": round(float(np.nanmax(demand)), 3) if np.any(np.isfinite(demand)) else None,
        "data_while_pushing": (round(float(np.mean(np.asarray(traj["avoidance_data"], bool)[pushing])), 4)
                               if "avoidance_data" in traj and np.any(pushing) else None),
        "flight_s": round(float(t[-1] - t[0]), 3),
        "config": dataclasses.asdict(cfg),
    }


def _ahead_clearance(world, p: np.ndarray, v_des: np.ndarray, radius: float, n_offsets: int = 15) -> tuple[float | None, str | None]:
    """How far the body (a sphere of ``radius``) can move along the horizontal demand direction before it
    touches an obstacle, and that obstacle's name: parallel rays at lateral offsets o ∈ [−radius, radius];
    a surface hit at distance d on the ray at offset o is touched after d − √(radius² − o²)."""
    if world is None or not np.all(np.isfinite(v_des[:2])) or np.hypot(v_des[0], v_des[1]) <= 0:
        return None, None
    bearing = math.atan2(v_des[1], v_des[0])
    n = np.array([-math.sin(bearing), math.cos(bearing), 0.0])  # to the right of the direction
    best, name = math.inf, None
    for o in np.linspace(-radius, radius, n_offsets) if radius > 0 else [0.0]:
        d = world.horizontal_distances(p + o * n, [bearing], band_half_height_m=0.0)[0]
        if not np.any(np.isfinite(d)):
            continue
        k = int(np.argmin(d))
        touch = float(d[k]) - math.sqrt(max(radius * radius - o * o, 0.0))
        if touch < best:
            best, name = touch, world.obstacles[k].label
    return (best, name) if math.isfinite(best) else (None, None)


def outcome_verdict(o: dict) -> str:
    """One phrase for the outcome: the collision, or where it stopped (score.md and the command lines)."""
    if o["collision"]:
        return "COLLISION" + (f" with {o['collision_with']}" if o.get("collision_with") else "") + f" at {o['collision_t_s']:.2f} s"
    if o["stop_t_s"] is not None:
        return (f"stopped {o['stop_clearance_m']:.2f} m short" + (f" of {o['stop_obstacle']}" if o.get("stop_obstacle") else "")
                + f" at {o['stop_t_s']:.2f} s")
    return "no stop in front of an obstacle"


def outcome_markdown(o: dict) -> list[str]:
    """score.md lines for the ``"avoidance"`` table."""
    def f(x, fmt="{:.2f}"):
        return "–" if x is None else fmt.format(x)

    verdict = outcome_verdict(o).replace("COLLISION", "**COLLISION**")
    return [
        "## Avoidance (closed loop)", "",
        f"The simulated autopilot's `{o['model']}` avoidance (margin {o['margin_m']:g} m) flew on the companion's "
        f"ranges: {verdict}.", "",
        "| outcome | value |", "|---|---|",
        f"| collision | {'yes' if o['collision'] else 'no'} |",
        f"| min clearance (body to obstacle) | {f(o['min_clearance_m'])} m |",
        f"| stop clearance (along the demanded direction) | {f(o['stop_clearance_m'])} m |",
        f"| stop time | {f(o['stop_t_s'])} s |",
        f"| false stop (avoidance held it below ½ demand, nothing within {o['config']['false_stop_margin_factor']:g}× margin + stopping distance) | "
        f"{'yes' if o['false_stop'] else 'no'} ({f(o['false_stop_s'])} s) |",
        f"| progress along the route | {100 * o['progress']:.1f} % |",
        f"| time to goal | {f(o['time_to_goal_s'])} s |",
        f"| max speed / demanded | {f(o['max_speed_mps'])} / {f(o['demanded_speed_mps'])} m/s |",
        f"| obstacle data held while the pilot pushed | {f(None if o['data_while_pushing'] is None else 100 * o['data_while_pushing'], '{:.1f} %')} |",
        "",
    ]


__all__ = ["OutcomeConfig", "evaluate_outcome", "read_trajectory", "route_progress", "horizontal_route", "outcome_markdown", "outcome_verdict"]
