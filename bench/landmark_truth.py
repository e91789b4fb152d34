"""Each landmark's range and σ against the truth, on a SITL flight with a landmark log (issue 15).

``python -m bench landmark_truth DIR… [--young S] [--axis DEG] [--bins 0,3,5,8,12,20,40] [--json]``

The scorer judges the *published* sector values; this looks one level down, at what the estimator
believed about each landmark.  DIR is the output of ``flightsim sitl … --landmark-log`` (it holds
``landmarks.jsonl``, ``truth.npz`` and ``sitl.json``), or a campaign flown with ``flightsim campaign … --mode sitl
--landmark-log`` (all its runs pooled).  For every converged, valid landmark of every
logged frame, the landmark's measured ray (from the logged, i.e. the telemetry's, camera pose to its
logged point) is turned into the camera frame and cast from the *true* camera pose into the scenario's
world (``World.raycast``); where it hits something within 100 m, the distance to the hit is the
landmark's true range, and z = (range − true range) / σ.  Reported per true-range bin: the number of
samples, mean and median z, NEES (mean z², 1 when σ is honest), the share within ±2σ and the shares
beyond +3σ (long) and −3σ (short).  The samples of one landmark in consecutive frames are strongly
correlated: read the counts as frames, not as independent draws.

``--young S`` keeps only landmarks first logged less than S seconds before the frame (new points,
not tracks carried since take-off); ``--axis DEG`` only those within DEG of the camera's optical axis
(the direction of travel on a straight approach).  docs/BENCHMARKS.md, "Why the pole ahead was ranged
long", measured the same thing with a hook, before this tool existed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

COMMAND = "python -m bench landmark_truth"
DEFAULT_BINS = (0.0, 3.0, 5.0, 8.0, 12.0, 20.0, 40.0)
MAX_TRUTH_M = 100.0


def landmark_z(frames, t_truth, R_truth, p_truth, raycast, *, young_s: float | None = None,
               axis_deg: float | None = None, tol_s: float = 1e-3):
    """(z, true range, range, σ, landmark id, frame time) of the converged, valid landmarks of ``frames``
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
        m = f["converged"] & f["valid"] & np.isfinite(f["range"]) & np.isfinite(f["range_sigma"]) & (f["range_sigma"] > 0)
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
    """Per true-range bin [lo, hi): n, mean and median z, NEES, within ±2σ, beyond +3σ and −3σ."""
    out = []
    z, truth = samples[:, 0], samples[:, 1]
    for lo, hi in zip(bins[:-1], bins[1:]):
        sel = (truth >= lo) & (truth < hi)
        n = int(sel.sum())
        zz = z[sel]
        out.append(dict(lo=float(lo), hi=float(hi), n=n, landmarks=int(len(np.unique(samples[sel, 4]))),
                        mean_z=float(zz.mean()) if n else None, median_z=float(np.median(zz)) if n else None,
                        nees=float(np.mean(zz**2)) if n else None, within_2sigma=float(np.mean(np.abs(zz) <= 2)) if n else None,
                        long_3sigma=float(np.mean(zz > 3)) if n else None, short_3sigma=float(np.mean(zz < -3)) if n else None))
    return out


def markdown(rows: list[dict]) -> str:
    lines = ["| true range | samples (landmarks) | mean z | median z | NEES | within ±2σ | beyond +3σ (long) | beyond −3σ (short) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if not r["n"]:
            lines.append(f"| {r['lo']:g}–{r['hi']:g} m | 0 | – | – | – | – | – | – |")
            continue
        lines.append(f"| {r['lo']:g}–{r['hi']:g} m | {r['n']} ({r['landmarks']}) | {r['mean_z']:+.2f} | {r['median_z']:+.2f} | "
                     f"{r['nees']:.2f} | {100 * r['within_2sigma']:.1f} % | {100 * r['long_3sigma']:.1f} % | "
                     f"{100 * r['short_3sigma']:.1f} % |")
    return "\n".join(lines)


def load_run(run_dir: Path, scenario: str | None = None):
    """(frames, t_truth, R_truth, p_truth, raycast) of a ``flightsim sitl --landmark-log`` output directory."""
    from companion.errors import InputError
    from companion.landmark_log import read_landmark_log
    from flightsim.scenario import load_scenario
    from flightsim.score.files import LANDMARK_LOG

    log_path = run_dir / LANDMARK_LOG
    if not log_path.is_file():
        raise InputError(f"{run_dir}: no {LANDMARK_LOG} (fly it with flightsim sitl … --landmark-log)")
    meta = json.loads((run_dir / "sitl.json").read_text())
    sc = load_scenario(scenario or meta["scenario_file"], seed=meta.get("seed"))
    tr = np.load(run_dir / "truth.npz")
    t_truth = tr["t_sim_s"] + sc.telemetry.boot_time_s  # the companion's clock in lockstep: the autopilot's boot clock

    def raycast(origin, dirs):
        h = sc.world.raycast(np.broadcast_to(origin, dirs.shape), dirs, MAX_TRUTH_M)
        return np.where(np.isfinite(h.distance) & (h.distance > 0), h.distance, np.inf)

    return read_landmark_log(log_path), t_truth, tr["R_world_cam"], tr["p_world_cam"], raycast


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog=COMMAND, description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("runs", nargs="+", metavar="DIR",
                    help="flightsim sitl output directories flown with --landmark-log, or SITL campaign directories "
                         "(flightsim campaign … --mode sitl --landmark-log): all their runs")
    ap.add_argument("--scenario", help="the scenario file, if not the one sitl.json names (relative to the run's working directory)")
    ap.add_argument("--young", type=float, metavar="S", help="only landmarks first logged less than S seconds before the frame")
    ap.add_argument("--axis", type=float, metavar="DEG", help="only landmarks within DEG of the optical axis")
    ap.add_argument("--bins", default=",".join(f"{b:g}" for b in DEFAULT_BINS), help="true-range bin edges, m")
    ap.add_argument("--json", action="store_true", help="print JSON instead of the table")
    args = ap.parse_args(argv)
    try:
        bins = tuple(float(b) for b in args.bins.split(","))
    except ValueError:
        ap.error(f"--bins: comma-separated numbers, got {args.bins!r}")
    if len(bins) < 2 or any(b >= c for b, c in zip(bins, bins[1:])):
        ap.error("--bins: at least two increasing edges")
    from companion.errors import CompanionError

    dirs = []
    for d in map(Path, args.runs):  # a campaign directory stands for its runs
        dirs += sorted((d / "runs").glob("seed_*")) if (d / "runs").is_dir() else [d]
    samples = []
    try:
        for d in dirs:
            frames, t, R, p, raycast = load_run(d, args.scenario)
            samples.append(landmark_z(frames, t, R, p, raycast, young_s=args.young, axis_deg=args.axis))
    except (CompanionError, OSError, KeyError, json.JSONDecodeError) as e:
        print(f"{COMMAND}: {e}", file=sys.stderr)
        return 2
    rows = summarize(np.concatenate(samples), bins)
    print(json.dumps(rows, indent=1) if args.json else markdown(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
