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


def _stretch_nan(t: np.ndarray, y: np.ndarray, stretch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``t``, ``y`` with a NaN between stretches, so a line is not drawn across a gap."""
    if t.size == 0:
        return t, y
    cut = np.flatnonzero(np.diff(stretch) != 0) + 1
    return np.insert(t.astype(float), cut, np.nan), np.insert(y.astype(float), cut, np.nan)


def running_nees_bands(n_samples: int, n_eff: float | None, confidence: float, points: int = 60):
    """The band of the running NEES mean after 1 … ``n_samples`` samples: with the effective size
    growing in proportion (``j · n_eff / n``, at least 1) and as if independent (``j``).  Evaluated at
    up to ``points`` counts spread logarithmically and interpolated.  Returns (lo, hi, lo_ind, hi_ind),
    each (n_samples,); the first two NaN without ``n_eff``."""
    from flightsim.score.stats import nees_band

    n = int(n_samples)
    if n == 0:
        return (np.zeros(0),) * 4
    j = np.arange(1, n + 1, dtype=float)
    at = np.unique(np.round(np.geomspace(1, n, min(n, points))).astype(int))
    ind = np.array([nees_band(int(k), confidence) for k in at])
    lo_i, hi_i = np.interp(j, at, ind[:, 0]), np.interp(j, at, ind[:, 1])
    if not n_eff:
        return np.full(n, np.nan), np.full(n, np.nan), lo_i, hi_i
    ratio = min(1.0, float(n_eff) / n)
    eff = np.array([nees_band(max(1.0, k * ratio), confidence) for k in at])
    return np.interp(j, at, eff[:, 0]), np.interp(j, at, eff[:, 1]), lo_i, hi_i


def nees_plot(series: dict, nees: dict, path, title: str = "") -> None:
    """One run's forward σ against the truth: the error (estimate − truth) over time with the ±σ and
    ±2σ envelopes the companion reported (samples outside ±2σ marked), and the NEES samples with
    their running mean against the band of the mean with n_eff (and, dashed, as if independent)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = float(series["t0"])
    t = np.asarray(series["nees_exposure_t"], float) - t0
    err, sig = np.asarray(series["nees_exposure_error_m"], float), np.asarray(series["nees_exposure_sigma_m"], float)
    st = np.asarray(series["nees_exposure_stretch"])
    x = (err / sig) ** 2 if t.size else np.zeros(0)
    conf = float(nees.get("confidence", 0.95))
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 7.5), sharex=True, constrained_layout=True)
    if t.size == 0:
        for a in (a1, a2):
            a.text(0.5, 0.5, "no forward range with a known σ and truth", ha="center", va="center", transform=a.transAxes,
                   color="0.4")
    else:
        tt, s2 = _stretch_nan(t, 2 * sig, st)
        _, s1 = _stretch_nan(t, sig, st)
        a1.fill_between(tt, -s2, s2, color="tab:blue", alpha=0.15, lw=0, label="± 2σ (reported)")
        a1.fill_between(tt, -s1, s1, color="tab:blue", alpha=0.2, lw=0, label="± σ")
        te, ee = _stretch_nan(t, err, st)
        a1.plot(te, ee, "-", color="k", lw=0.8, alpha=0.7)
        out = np.abs(err) > 2 * sig
        a1.plot(t[~out], err[~out], ".", ms=3, color="k", label="estimate − truth (at exposure)")
        a1.plot(t[out], err[out], ".", ms=5, color="tab:red", label="outside ± 2σ")
        a1.axhline(0, color="0.3", lw=0.8)
        mag = np.abs(np.r_[err, 2 * sig])
        lim = min(float(mag.max()), 3.0 * float(np.percentile(mag, 99))) * 1.1 or 1.0  # a wild outlier may leave the axes
        a1.set_ylim(-lim, lim)
        cov = nees.get("coverage") or {}
        if cov.get("rate_2sigma") is not None:
            a1.set_title(f"Forward range error with the reported σ: within ± σ {100 * cov['rate_1sigma']:.1f} % "
                         f"(normal {100 * cov['expected_1sigma']:.1f} %), within ± 2σ {100 * cov['rate_2sigma']:.1f} % "
                         f"(normal {100 * cov['expected_2sigma']:.1f} %)", fontsize=10)
        a1.legend(fontsize=8, loc="upper right")
        floor = 1e-4
        a2.plot(t, np.maximum(x, floor), ".", ms=2.5, color="0.55", label="NEES sample (e/σ)²")
        run = np.cumsum(x) / np.arange(1, x.size + 1)
        lo, hi, lo_i, hi_i = running_nees_bands(x.size, nees.get("n_eff"), conf)
        if np.any(np.isfinite(lo)):
            a2.fill_between(t, lo, hi, color="tab:green", alpha=0.25, lw=0,
                            label=f"{100 * conf:g} % band of the mean, n_eff (∝ samples so far)")
        a2.plot(t, lo_i, "--", color="tab:green", lw=0.9, label="band as if independent (reference)")
        a2.plot(t, hi_i, "--", color="tab:green", lw=0.9)
        a2.plot(t, run, "-", color="tab:purple", lw=1.6, label="running mean")
        a2.axhline(1.0, color="k", lw=0.8)
        a2.set_yscale("log")
        a2.set_ylim(floor, max(10.0, float(np.max(x)) * 2))
        a2.legend(fontsize=8, loc="lower right")
        ne = nees.get("n_eff")
        k = nees.get("stretches")
        a2.set_title(f"NEES: mean {np.mean(x):.2f} over n = {x.size} (n_eff = {ne:.1f}, {k} stretch{'' if k == 1 else 'es'})"
                     if ne else f"NEES: mean {np.mean(x):.2f} over n = {x.size}", fontsize=10)
    a1.set_ylabel("estimate − truth, m")
    a2.set_ylabel("NEES (log)")
    a2.set_xlabel("time since the first frame, s")
    for a in (a1, a2):
        a.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=100, format="png", metadata={"Software": None})
    plt.close(fig)


def plot_run_nees(path, series: dict, nees: dict, title: str = "") -> Path | None:
    """``nees.png`` of one scored run (:func:`nees_plot`), written atomically; without matplotlib (an
    onboard install) or on any failure it is skipped with a log line and None returned — a plot is
    not the verdict."""
    import logging

    from companion.io.atomic import atomic_path

    log = logging.getLogger(__name__)
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        log.info("matplotlib is not installed: %s not drawn", path)
        return None
    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            nees_plot(series, nees, tmp, title=title)
    except Exception:
        log.exception("NEES plot %s failed", path)
        return None
    return path
