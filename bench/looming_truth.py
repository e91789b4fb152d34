"""The matcher's scale changes against the truth on rendered flights (docs/derivations/looming.md).

``python -m bench looming_truth [--scenario S …] [--seed N] [--json]``

Looming fuses each track's patch scale change between consecutive frames, with the matcher's σ
(``ncc.estimate_scale``) and a floor (``[ekf_anchored] looming_sigma_floor``), as independent
measurements.  This benchmark checks both assumptions where the estimator meets them: on the
scenarios' rendered frames.

It flies a scenario in-process (``flightsim.fly.Flight``: JSBSim, the renderer, no companion and no
avoidance) and runs the companion's tracker on every frame (``TrackManager`` with the scenario's
companion configuration; the search windows predicted from the *true* camera poses, without the
depth prediction the pipeline adds).  For each scale the tracker reports, the true scale change is
the depth ratio Z_prev/Z_now of the world point that the track's current pixel sees, found by
casting that pixel's ray from the true camera pose into the world (``World.raycast``; the sky is
skipped).  Reported per scenario:

* the scale error e = s − s_true: mean, σ, and the **z-score σ** against the σ the filter uses,
  √(σ_matcher² + σ_floor²) (1 when that σ is honest);
* the correlation of one track's errors across frames (lags 1–30 frames): the filter assumes 0;
* the σ of each track's **mean error** against the σ it would have if the errors were independent
  (σ_e/√n per track): a shared per-track part of the error shows as a larger spread;
* split by the true depth Z, and by what the pixel sees (an obstacle or the ground).

Nothing here changes the estimator; the figures say how far the looming noise model is from the
rendered flights' real errors.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
COMMAND = "python -m bench looming_truth"
DEFAULT_SCENARIOS = ("quad_approach", "quad_wall_hover", "fixedwing_tower")
LAGS = (1, 2, 3, 5, 8, 12, 20, 30)
DEPTH_BINS = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 80.0), (80.0, 150.0), (150.0, math.inf))
MIN_TRACK_SCALES = 10  # a track's mean error is compared only with this many scales or more
MIN_ROW_SCALES = 20  # the markdown table leaves out a depth band with fewer scales


def fly_and_track(scenario: str | Path, seed: int, progress=None, max_frames: int | None = None) -> dict[str, np.ndarray]:
    """Fly ``scenario`` with ``seed`` (its first ``max_frames`` frames, default all); every scale the
    tracker measured with its truth: a dict of (N,) arrays t, track, k (frame index), s, sigma (the
    matcher's σ), s_true, depth (true Z now), ground, and the filter's floor."""
    from bench.report import rendered_frames
    from companion.core.prediction import make_track_predictor
    from companion.core.tracks import TrackManager
    from companion.io.config_files import load_companion_config
    from flightsim.fly import Flight
    from flightsim.scenario import load_scenario, resolve_companion_config
    from flightsim.world.geometry import GROUND, SKY

    sc = load_scenario(scenario, seed=seed)
    cfg_path = resolve_companion_config(sc) or ROOT / "configs" / "companion.toml"
    cfg = load_companion_config(cfg_path)
    flight = Flight(sc)
    cam = flight.cam
    tracks = TrackManager(cam, cfg.harris, cfg.ncc, cfg.tracks)
    out: dict[str, list] = {k: [] for k in ("t", "track", "k", "s", "sigma", "s_true", "depth", "ground")}
    for k, frame, R_wc, p_wc, pose_prev in rendered_frames(flight, max_frames, progress):
        predict = None if pose_prev is None else make_track_predictor(cam, cfg.prediction, pose_prev, (R_wc, p_wc))
        tf = tracks.step(frame.image, frame.t_s, k, predict, R_world_cam=R_wc)
        have = np.flatnonzero(np.isfinite(tf.scale)) if pose_prev is not None else np.zeros(0, int)
        if have.size:
            xy = cam.pixels_to_normalized(tf.uv[have])
            d_world = np.column_stack([xy, np.ones(len(xy))]) @ R_wc.T  # unit optical-axis component: distance = depth
            hits = sc.world.raycast(p_wc, d_world)
            seen = hits.index != SKY
            P = p_wc + hits.distance[seen, None] * d_world[seen]
            Z = hits.distance[seen]
            Z_prev = (P - pose_prev[1]) @ pose_prev[0][:, 2]
            idx = have[seen]
            out["t"].append(np.full(idx.size, frame.t_s))
            out["track"].append(tf.ids[idx])
            out["k"].append(np.full(idx.size, k))
            out["s"].append(tf.scale[idx])
            out["sigma"].append(tf.scale_sigma[idx])
            out["s_true"].append(Z_prev / Z)
            out["depth"].append(Z)
            out["ground"].append(hits.index[seen] == GROUND)
    return {name: (np.concatenate(v) if v else np.zeros(0)) for name, v in out.items()} | {"floor": float(cfg.ekf_anchored.looming_sigma_floor)}


def _track_stats(track: np.ndarray, k: np.ndarray, e: np.ndarray) -> tuple[dict[str, float], float, float]:
    """Correlation of a track's errors at each lag (keyed by the lag as text, as in the JSON); σ of the
    tracks' mean errors and the σ those means would have with independent errors (root mean of
    σ_e²/n over the same tracks)."""
    var = float(np.var(e)) if e.size else float("nan")
    order = np.lexsort((k, track))
    track, k, e = track[order], k[order], e[order]
    corr = {}
    for lag in LAGS:
        # pairs (i, j) of the same track exactly `lag` frames apart
        j = np.searchsorted(k + track * 10**7, k + lag + track * 10**7)
        j = np.minimum(j, len(k) - 1)
        ok = (track[j] == track) & (k[j] == k + lag)
        corr[str(lag)] = float(np.mean((e[ok] - e.mean()) * (e[j[ok]] - e.mean())) / var) if np.any(ok) and var > 0 else float("nan")
    _, start, count = np.unique(track, return_index=True, return_counts=True)
    keep = count >= MIN_TRACK_SCALES
    if not np.any(keep):
        return corr, float("nan"), float("nan")
    means = np.add.reduceat(e, start)[keep] / count[keep]
    white = math.sqrt(float(np.mean(var / count[keep])))
    return corr, float(np.std(means)), white


def summarize(d: dict) -> dict:
    """The figures of one flight (module docstring)."""
    e = d["s"] - d["s_true"]
    sig = np.sqrt(d["sigma"] ** 2 + d["floor"] ** 2)
    z = e / sig

    def block(m):
        if not np.any(m):
            return {"n": 0}
        corr, sd_means, sd_white = _track_stats(d["track"][m], d["k"][m], e[m])
        return {"n": int(m.sum()), "tracks": int(np.unique(d["track"][m]).size),
                "true_s_minus_1": float(np.mean(d["s_true"][m] - 1)), "mean_error": float(np.mean(e[m])),
                "sd_error": float(np.std(e[m])), "median_sigma": float(np.median(sig[m])), "sd_z": float(np.std(z[m])),
                "corr": corr, "sd_track_means": sd_means, "sd_track_means_if_white": sd_white}

    res = {"all": block(np.ones(e.size, bool)), "obstacles": block(~d["ground"].astype(bool)),
           "ground": block(d["ground"].astype(bool)), "by_depth": []}
    for lo, hi in DEPTH_BINS:
        b = block(~d["ground"].astype(bool) & (d["depth"] >= lo) & (d["depth"] < hi))
        if b["n"]:
            res["by_depth"].append({"depth_m": [lo, hi], **b})
    return res


def run(scenarios, seed: int, progress=None) -> dict:
    out = []
    for name in scenarios:
        path = Path(name) if name.endswith(".toml") else ROOT / "configs" / "scenarios" / f"{name}.toml"
        d = fly_and_track(path, seed, progress)
        out.append({"scenario": path.stem, "seed": seed, "floor": d["floor"], **summarize(d)})
    return {"seed": seed, "scenarios": out}


def _f(v, spec=".4f"):
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def markdown(res: dict, command: str = COMMAND) -> str:
    lines = [
        "Every scale change the tracker reported on a rendered flight, against the true depth ratio of the point its pixel "
        "sees (module doc of bench/looming_truth.py). σ used = √(σ_matcher² + floor²), what the filter assumes; z σ = the σ "
        "of error/σ used (1 = honest); corr = correlation of one track's errors 1, 3, 8 and 20 frames apart (the filter "
        "assumes 0); track means = σ of each track's mean error (tracks with ≥ 10 scales) against what it would be with "
        "independent errors. Depth bands with fewer than 20 scales are left out.",
        "",
        "| scenario | points | scales (tracks) | true s − 1 | mean error | σ error | σ used | z σ | corr 1 / 3 / 8 / 20 | σ of track means (if independent) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for sc in res["scenarios"]:
        rows = [("obstacles", sc["obstacles"]), ("ground", sc["ground"])] + [
            (f"obstacles at {b['depth_m'][0]:g}–{b['depth_m'][1]:g} m", b) for b in sc["by_depth"]]
        for label, b in rows:
            if b.get("n", 0) < MIN_ROW_SCALES:  # a handful of scales says nothing (kept in --json)
                continue
            c = b["corr"]
            lines.append(
                f"| {sc['scenario']} (seed {sc['seed']}) | {label} | {b['n']} ({b['tracks']}) | {_f(b['true_s_minus_1'])} | "
                f"{_f(b['mean_error'], '+.4f')} | {_f(b['sd_error'])} | {_f(b['median_sigma'])} | {_f(b['sd_z'], '.2f')} | "
                f"{' / '.join(_f(c[str(l)], '+.2f') for l in (1, 3, 8, 20))} | {_f(b['sd_track_means'])} ({_f(b['sd_track_means_if_white'])}) |")
    lines += ["", f"Command: `{command}`"]
    return "\n".join(lines)


def main(argv=None) -> int:
    from bench.report import rendered_flight_parser

    ap = rendered_flight_parser(COMMAND, __doc__, DEFAULT_SCENARIOS, "python -m bench looming_truth --scenario quad_approach --scenario fixedwing_tower --seed 1")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON instead of markdown")
    a = ap.parse_args(argv)
    scenarios = a.scenario or list(DEFAULT_SCENARIOS)
    from companion.io.progress import ProgressBar

    with ProgressBar("frames tracked", total=None, enabled=False if a.json else None) as bar:
        res = run(scenarios, a.seed, progress=bar.advance)
    cmd = COMMAND + "".join(f" --scenario {s}" for s in (a.scenario or [])) + f" --seed {a.seed}"
    print(json.dumps(res, indent=2) if a.json else markdown(res, cmd))
    return 0


if __name__ == "__main__":
    sys.exit(main())
