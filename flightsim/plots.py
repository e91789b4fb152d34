"""Flight summary plot (matplotlib, Agg): track with obstacles, altitude, attitude, speed."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def _obstacles(a, world, min_radius_m: float = 0.0) -> None:
    """Obstacle footprints, top-down (east right, north up); cylinders drawn at least ``min_radius_m``."""
    from matplotlib.patches import Circle, Polygon

    for ob in world.obstacles:
        if ob.is_cylinder:
            a.add_patch(Circle((ob.centre[1], ob.centre[0]), max(ob.radius, min_radius_m), color="tab:gray", alpha=0.8))
        else:
            ne = np.ascontiguousarray(np.asarray(ob.corners(), np.float32)[:, :2])
            hull = cv2.convexHull(ne)[:, 0, :]  # footprint of the oriented box
            a.add_patch(Polygon(hull[:, [1, 0]], closed=True, color="tab:gray", alpha=0.6))


def avoidance_plot(world, traj: dict, outcome: dict, path: Path, title: str = "") -> None:
    """Closed-loop flight: top-down track with the obstacles, the route, what the autopilot
    held as obstacles where it stopped (or was nearest) and the stop / collision point; clearance and
    speeds over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    t, p, v = traj["t_sim_s"], traj["p_ned"], traj["v_ned"]
    fig = plt.figure(figsize=(12, 6.5), constrained_layout=True)
    gs = fig.add_gridspec(2, 2, width_ratios=[1.2, 1])
    a = fig.add_subplot(gs[:, 0])
    _obstacles(a, world)
    r = traj["route_ned"]
    a.plot(r[:, 1], r[:, 0], "k--", lw=1, label="route (pilot's intent)")
    a.plot(p[:, 1], p[:, 0], "b-", lw=1.5, label="track")
    a.plot(p[0, 1], p[0, 0], "go", label="start")
    k_at = None
    if outcome.get("stop_t_s") is not None:
        k_at = int(np.searchsorted(t, outcome["stop_t_s"]))
    elif outcome.get("collision"):
        k_at = len(t) - 1
    else:
        k_at = int(np.argmin(traj["clearance_m"]))
    bt = traj.get("boundary_t_s")
    if bt is not None and len(bt):
        j = int(np.argmin(np.abs(bt - t[k_at])))
        b = traj["boundary_ne_m"][j]
        b = b[np.all(np.isfinite(b), 1)]
        if len(b):
            a.plot(b[:, 1], b[:, 0], "m.", ms=4, label=f"autopilot's obstacle data at {bt[j]:.1f} s")
    marg = float(outcome.get("margin_m", 0.0))
    if outcome.get("collision"):
        a.plot(p[-1, 1], p[-1, 0], "rx", ms=12, mew=3, label=f"collision at {outcome['collision_t_s']:.1f} s")
    elif outcome.get("stop_p_ned") is not None:
        sp = outcome["stop_p_ned"]
        a.plot(sp[1], sp[0], "r*", ms=12, label=f"stop, {outcome['stop_clearance_m']:.2f} m clear")
        a.add_patch(Circle((sp[1], sp[0]), marg, fill=False, ls=":", color="r"))
    a.set_xlabel("east (m)")
    a.set_ylabel("north (m)")
    lo = np.minimum(p[:, :2].min(0), r[:, :2].min(0)) - 8
    hi = np.maximum(p[:, :2].max(0), r[:, :2].max(0)) + 8
    span = 0.6 * max(hi - lo)  # keep the picture from becoming a sliver along a straight route
    for i in range(2):
        if hi[i] - lo[i] < span:
            mid = 0.5 * (hi[i] + lo[i])
            lo[i], hi[i] = mid - span / 2, mid + span / 2
    a.set_xlim(lo[1], hi[1])
    a.set_ylim(lo[0], hi[0])
    a.set_aspect("equal", adjustable="box")
    a.set_title((title + ": " if title else "") + f"{outcome.get('model')} avoidance, margin {marg:g} m")
    a.legend(loc="best", fontsize=8)
    b1 = fig.add_subplot(gs[0, 1])
    b1.plot(t, traj["clearance_m"], label="clearance (body to nearest obstacle)")
    b1.axhline(0.0, color="r", lw=1)
    b1.axhline(marg - float(outcome.get("body_radius_m", 0.0)), color="m", ls=":", lw=1, label="margin (from the centre)")
    b1.set_ylim(-0.5, max(10.0, marg * 3))
    b1.set_ylabel("m")
    b1.legend(fontsize=8)
    b1.set_title("clearance")
    b2 = fig.add_subplot(gs[1, 1], sharex=b1)
    b2.plot(t, np.hypot(v[:, 0], v[:, 1]), label="ground speed")
    vd, vc = traj["v_des_ned"], traj["v_cmd_ned"]
    b2.plot(t, np.hypot(vd[:, 0], vd[:, 1]), "k--", lw=1, label="pilot's demand")
    b2.plot(t, np.hypot(vc[:, 0], vc[:, 1]), "g-", lw=1, label="after avoidance")
    if "avoidance_data" in traj:
        nod = ~np.asarray(traj["avoidance_data"], bool)
        b2.fill_between(t, 0, np.where(nod, np.nanmax(np.hypot(vd[:, 0], vd[:, 1])) if np.any(np.isfinite(vd)) else 1, 0),
                        color="orange", alpha=0.2, step="post", label="no obstacle data")
    b2.set_xlabel("t (s)")
    b2.set_ylabel("m/s")
    b2.legend(fontsize=8)
    b2.set_title("speed")
    fig.savefig(path, dpi=90, metadata={"Software": None})
    plt.close(fig)


def plot_run_outcome(run_dir: Path, world, outcome: dict, title: str = "") -> Path | None:
    """``run_dir/avoidance.png`` from the run's trajectory.npz (:func:`avoidance_plot`); a failure is
    logged and None returned — a plot is not the verdict."""
    import logging

    from flightsim.outcome import read_trajectory

    from companion.io.atomic import atomic_path

    path = Path(run_dir) / "avoidance.png"
    try:
        with atomic_path(path) as tmp:
            avoidance_plot(world, read_trajectory(Path(run_dir) / "trajectory.npz"), outcome, tmp, title=title)
    except Exception:
        logging.getLogger(__name__).exception("avoidance plot of %s failed", run_dir)
        return None
    return path


def flight_summary_plot(sc, truth: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = truth["t_sim_s"]
    p = truth["p_ned"]
    fig, ax = plt.subplots(2, 2, figsize=(11, 8), constrained_layout=True)
    a = ax[0, 0]
    _obstacles(a, sc.world, min_radius_m=1.0)  # thin poles drawn wider so they show at flight scale
    a.plot(p[:, 1], p[:, 0], "b-", lw=1.5, label="track")
    a.plot(p[0, 1], p[0, 0], "go", label="start")
    if len(truth.get("target_p_world", [])):
        tp = truth["target_p_world"]
        a.plot(tp[:, 1], tp[:, 0], "r+", ms=8, label="targets")
    a.set_xlabel("east (m)")
    a.set_ylabel("north (m)")
    a.set_aspect("equal", adjustable="datalim")
    a.set_title(f"{sc.meta.name}: track and obstacles")
    a.legend(loc="best", fontsize=8)
    ax[0, 1].plot(t, -p[:, 2])
    ax[0, 1].set_xlabel("t (s)")
    ax[0, 1].set_ylabel("altitude above origin (m)")
    ax[0, 1].set_title("altitude")
    rpy = np.degrees(truth["rpy"])
    for i, name in enumerate(("roll", "pitch", "yaw")):
        ax[1, 0].plot(t, rpy[:, i], label=name)
    ax[1, 0].set_xlabel("t (s)")
    ax[1, 0].set_ylabel("deg")
    ax[1, 0].set_title("attitude")
    ax[1, 0].legend(fontsize=8)
    v = truth["v_ned"]
    ax[1, 1].plot(t, np.hypot(v[:, 0], v[:, 1]), label="ground speed")
    ax[1, 1].plot(t, -v[:, 2], label="climb rate")
    ax[1, 1].set_xlabel("t (s)")
    ax[1, 1].set_ylabel("m/s")
    ax[1, 1].set_title("speed")
    ax[1, 1].legend(fontsize=8)
    fig.savefig(path, dpi=90, metadata={"Software": None})
    plt.close(fig)
