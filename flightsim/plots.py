"""Flight summary plot (matplotlib, Agg): track with obstacles, altitude, attitude, speed."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def flight_summary_plot(sc, truth: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Polygon

    t = truth["t_sim_s"]
    p = truth["p_ned"]
    fig, ax = plt.subplots(2, 2, figsize=(11, 8), constrained_layout=True)
    a = ax[0, 0]
    for ob in sc.world.obstacles:
        if ob.is_cylinder:
            a.add_patch(Circle((ob.centre[1], ob.centre[0]), max(ob.radius, 1.0), color="tab:gray", alpha=0.7))
        else:
            ne = np.ascontiguousarray(np.asarray(ob.corners(), np.float32)[:, :2])
            hull = cv2.convexHull(ne)[:, 0, :]  # footprint of the oriented box
            a.add_patch(Polygon(hull[:, [1, 0]], closed=True, color="tab:gray", alpha=0.6))
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
