"""Each landmark's range and σ against the truth, from a run's landmark log (issue 15; ``python -m bench landmark_truth``).

The scorer judges the *published* sector values; this looks one level down, at what the estimator
believed about each landmark (:mod:`companion.landmark_log`).  For every converged, valid landmark of every
logged frame, the landmark's measured ray (from the logged, i.e. the telemetry's, camera pose to its logged
point) is turned into the camera frame and cast from the *true* camera pose into the scenario's world
(``World.raycast``); where it hits something within 100 m, the distance to the hit is the landmark's true
range, and z = (range − true range) / σ.  Summarized per true-range bin: samples, mean and median z, NEES
(mean z², 1 when σ is honest), the share within ±2σ and beyond ±3σ.  The samples of one landmark in
consecutive frames are strongly correlated: read the counts as frames, not as independent draws.
``flightsim campaign … --landmark-log`` puts the table in its report.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from flightsim.score.files import LANDMARK_LOG

DEFAULT_BINS = (0.0, 3.0, 5.0, 8.0, 12.0, 20.0, 40.0)
MAX_TRUTH_M = 100.0


def landmark_z(frames, t_truth, R_truth, p_truth, raycast, *, young_s: float | None = None,
               axis_deg: float | None = None, tol_s: float = 1e-3, converged: bool | None = True):
    """(z, true range, range, σ, landmark id, frame time) of the converged (``converged=False``: the not yet
    converged; None: all), valid landmarks of ``frames``
    (:func:`companion.landmark_log.read_landmark_log`) against the truth poses (``t_truth`` (K,) on the
    companion's clock, ``R_truth`` (K,3,3) camera to world, ``p_truth`` (K,3)); ``raycast(origin (3,), dirs (N,3))``
    returns the distance along each unit direction, inf where nothing is hit.  A frame with no truth
    pose within ``tol_s`` is skipped.  Arrays, one row per sample."""
    first: dict[int, float] = {}
    rows = []
    for f in frames:
        for i in f["ids"]:
            first.setdefault(int(i), f["t"])
        k = int(np.argmin(np.abs(t_truth - f["t"]))) if len(t_truth) else -1
        if k < 0 or abs(t_truth[k] - f["t"]) > tol_s:
            continue
        conv = np.asarray(f["converged"], bool)
        m = (np.ones_like(conv) if converged is None else conv if converged else ~conv) & f["valid"] & np.isfinite(f["range"]) & np.isfinite(f["range_sigma"]) & (f["range_sigma"] > 0)
        if young_s is not None:
            m &= np.array([f["t"] - first[int(i)] < young_s for i in f["ids"]], bool)
        d_world = f["p_world"] - f["p_world_cam"]
        norm = np.linalg.norm(d_world, axis=1)
        m &= np.isfinite(norm) & (norm > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            d_cam = (d_world / norm[:, None]) @ f["R_world_cam"]  # R^T d per row: the measured ray in the camera frame
        if axis_deg is not None:
            m &= d_cam[:, 2] >= np.cos(np.radians(axis_deg))
        idx = np.flatnonzero(m)
        if not len(idx):
            continue
        truth = np.asarray(raycast(p_truth[k], d_cam[idx] @ R_truth[k].T), float)  # the same ray from the true camera
        hit = np.isfinite(truth) & (truth < MAX_TRUTH_M)
        idx, truth = idx[hit], truth[hit]
        r, s = f["range"][idx], f["range_sigma"][idx]
        rows.append(np.column_stack([(r - truth) / s, truth, r, s, f["ids"][idx], np.full(len(idx), f["t"])]))
    if not rows:
        return np.zeros((0, 6))
    return np.concatenate(rows)


def summarize(samples: np.ndarray, bins=DEFAULT_BINS) -> list[dict]:
    """Per true-range bin [lo, hi): n, mean and median z, NEES, within ±2σ, beyond +3σ and −3σ, and the median σ / range
    and |range − true range| / true range."""
    out = []
    z, truth = samples[:, 0], samples[:, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        rel_sigma, rel_err = samples[:, 3] / samples[:, 2], np.abs(samples[:, 2] - truth) / truth
    for lo, hi in zip(bins[:-1], bins[1:]):
        sel = (truth >= lo) & (truth < hi)
        n = int(sel.sum())
        zz = z[sel]
        out.append(dict(lo=float(lo), hi=float(hi), n=n, landmarks=int(len(np.unique(samples[sel, 4]))),
                        mean_z=float(zz.mean()) if n else None, median_z=float(np.median(zz)) if n else None,
                        nees=float(np.mean(zz**2)) if n else None, within_2sigma=float(np.mean(np.abs(zz) <= 2)) if n else None,
                        long_3sigma=float(np.mean(zz > 3)) if n else None, short_3sigma=float(np.mean(zz < -3)) if n else None,
                        median_rel_sigma=float(np.median(rel_sigma[sel])) if n else None,
                        median_rel_error=float(np.median(rel_err[sel])) if n else None))
    return out


def markdown(rows: list[dict]) -> str:
    lines = ["| true range | samples (landmarks) | mean z | median z | NEES | within ±2σ | beyond +3σ (long) | beyond −3σ (short) "
             "| median σ / range | median abs. error / range |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if not r["n"]:
            lines.append(f"| {r['lo']:g}–{r['hi']:g} m | 0 | – | – | – | – | – | – | – | – |")
            continue
        lines.append(f"| {r['lo']:g}–{r['hi']:g} m | {r['n']} ({r['landmarks']}) | {r['mean_z']:+.2f} | {r['median_z']:+.2f} | "
                     f"{r['nees']:.2f} | {100 * r['within_2sigma']:.1f} % | {100 * r['long_3sigma']:.1f} % | "
                     f"{100 * r['short_3sigma']:.1f} % | {r['median_rel_sigma']:.3f} | {r['median_rel_error']:.3f} |")
    return "\n".join(lines)


def load_run(run_dir: Path, scenario: str | None = None):
    """(frames, t_truth, R_truth, p_truth, raycast) of a run directory with a landmark log: a ``flightsim sitl
    --landmark-log`` output (``sitl.json``; the companion's clock in lockstep is the autopilot's boot clock) or a
    replay-mode campaign run (``flight.json``; the replay's clock is the recording's, the truth's ``t_s``)."""
    from companion.errors import InputError
    from companion.landmark_log import read_landmark_log
    from flightsim.scenario import load_scenario

    run_dir = Path(run_dir)
    log_path = run_dir / LANDMARK_LOG
    if not log_path.is_file():
        raise InputError(f"{run_dir}: no {LANDMARK_LOG} (fly it with flightsim sitl … --landmark-log, or a campaign with "
                         "--landmark-log)")
    sitl = (run_dir / "sitl.json").is_file()
    meta = json.loads((run_dir / ("sitl.json" if sitl else "flight.json")).read_text())
    sc = load_scenario(scenario or meta["scenario_file"], seed=meta.get("seed"))
    tr = np.load(run_dir / "truth.npz")
    t_truth = tr["t_sim_s"] + sc.telemetry.boot_time_s if sitl else tr["t_s"]

    def raycast(origin, dirs):
        h = sc.world.raycast(np.broadcast_to(origin, dirs.shape), dirs, MAX_TRUTH_M)
        return np.where(np.isfinite(h.distance) & (h.distance > 0), h.distance, np.inf)

    return read_landmark_log(log_path), t_truth, tr["R_world_cam"], tr["p_world_cam"], raycast
