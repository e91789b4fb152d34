"""How far the tracker's pixels wander from the points they were born on, on rendered flights, with and without
the drift correction (docs/derivations/tracking.md, "Drift correction").

``python -m bench track_drift [--scenario S …] [--seed N] [--correct-px X] [--config TOML] [--max-frames K] [--json]``

Frame-to-frame NCC re-cuts each template at its latest match, so a track inherits every match's sub-pixel error
and random-walks off its point; the estimator takes its pixels as independent errors of ``[ekf_anchored] sigma_px``.
This benchmark measures the walk where it happens: it flies a scenario in-process (``flightsim.fly.Flight``: JSBSim,
the renderer, no companion), and runs the companion's tracker (the scenario's companion configuration; search
windows predicted from the *true* camera poses; ``--config`` another companion configuration, e.g. an overlay with
another ``reference_half``) on every frame twice — with the drift correction off, and with
``[tracks] reference_correct_px`` = X (default: the configuration's value, 0.5 px where it is off).  Each track's
birth pixel is cast from the true camera into the world (``World.raycast``; the sky and the ground are skipped),
and in every later frame the track's pixel is compared with the projection of that point through the true camera.
Reported per scenario and variant, by the track's age: the median and 90th percentile of the distance (px) and the
share beyond 1 px.  A point that a nearer surface hides later is still counted (its track then follows something
else: an occlusion edge), so the tail says as much about T-junctions as about drift.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
COMMAND = "python -m bench track_drift"
DEFAULT_SCENARIOS = ("quad_wall_hover", "quad_slalom")
AGE_BINS_S = ((0.0, 1.0), (1.0, 2.0), (2.0, 4.0), (4.0, math.inf))


def fly_and_track(scenario: str | Path, seed: int, correct_px: float | None, progress=None,
                  max_frames: int | None = None, config: str | Path | None = None) -> dict:
    """Fly ``scenario`` once and track it with each variant: {variant: (N, 2) array of (age s, error px)}, where the
    variants are "off" and "on" (``reference_correct_px`` = ``correct_px``, or the configuration's, or 0.5)."""
    from bench.report import rendered_frames
    from companion.core.prediction import make_track_predictor
    from companion.core.tracks import TrackManager
    from companion.io.config_files import load_companion_config
    from flightsim.fly import Flight
    from flightsim.scenario import load_scenario, resolve_companion_config
    from flightsim.world.geometry import GROUND, SKY

    sc = load_scenario(scenario, seed=seed)
    cfg = load_companion_config(config or resolve_companion_config(sc) or ROOT / "configs" / "companion.toml")
    on_px = correct_px if correct_px is not None else (cfg.tracks.reference_correct_px or 0.5)
    variants = {"off": dataclasses.replace(cfg.tracks, reference_correct_px=0.0),
                "on": dataclasses.replace(cfg.tracks, reference_correct_px=float(on_px))}
    flight = Flight(sc)
    cam = flight.cam
    managers = {name: TrackManager(cam, cfg.harris, cfg.ncc, tc) for name, tc in variants.items()}
    born: dict[str, dict[int, tuple]] = {name: {} for name in variants}  # id → (point or None, birth time)
    rows: dict[str, list] = {name: [] for name in variants}
    n_frames = 0
    for k, frame, R_wc, p_wc, pose_prev in rendered_frames(flight, max_frames, progress):
        n_frames = k + 1
        for name, tm in managers.items():
            predict = None if pose_prev is None else make_track_predictor(cam, cfg.prediction, pose_prev, (R_wc, p_wc))
            tf = tm.step(frame.image, frame.t_s, k, predict, R_world_cam=R_wc)
            new = np.isin(tf.ids, tf.new_ids)
            if np.any(new):
                xy = cam.pixels_to_normalized(tf.uv[new])
                d_world = np.column_stack([xy, np.ones(len(xy))]) @ R_wc.T
                hits = sc.world.raycast(p_wc, d_world)
                keep = (hits.index != SKY) & (hits.index != GROUND)
                for i, ok, dist, d in zip(tf.ids[new].tolist(), keep, hits.distance, d_world):
                    born[name][i] = ((p_wc + dist * d) if ok else None, frame.t_s)
            old = ~new
            if np.any(old):
                ids = tf.ids[old].tolist()
                pts = [born[name].get(i, (None, 0.0)) for i in ids]
                have = np.array([p[0] is not None for p in pts])
                if np.any(have):
                    X = np.array([p[0] for p, h in zip(pts, have) if h])
                    age = frame.t_s - np.array([p[1] for p, h in zip(pts, have) if h])
                    p_cam = cam.world_to_camera(X, R_wc, p_wc)
                    front = p_cam[:, 2] > 0.05  # a point now behind the camera: its track follows something else
                    uv_true = cam.project(p_cam[front])
                    err = np.linalg.norm(tf.uv[old][have][front] - uv_true, axis=1)
                    rows[name].append(np.column_stack([age[front], err]))
    out = {name: (np.concatenate(v) if v else np.zeros((0, 2))) for name, v in rows.items()}
    return {"correct_px": float(on_px), "frames": n_frames, **out}


def summarize(d: dict) -> dict:
    """Per variant and age bin: samples, median and p90 error (px), share beyond 1 px."""
    res = {"correct_px": d["correct_px"], "frames": d["frames"], "variants": {}}
    for name in ("off", "on"):
        a = d[name]
        bins = []
        for lo, hi in AGE_BINS_S:
            m = (a[:, 0] > lo) & (a[:, 0] <= hi) if a.size else np.zeros(0, bool)
            e = a[m, 1] if a.size else np.zeros(0)
            bins.append({"age_s": [lo, hi], "n": int(e.size),
                         "median_px": float(np.median(e)) if e.size else float("nan"),
                         "p90_px": float(np.percentile(e, 90)) if e.size else float("nan"),
                         "beyond_1px": float(np.mean(e > 1.0)) if e.size else float("nan")})
        res["variants"][name] = bins
    return res


def run(scenarios, seed: int, correct_px: float | None = None, progress=None, max_frames: int | None = None,
        config: str | Path | None = None) -> dict:
    out = []
    for name in scenarios:
        path = Path(name) if name.endswith(".toml") else ROOT / "configs" / "scenarios" / f"{name}.toml"
        d = fly_and_track(path, seed, correct_px, progress, max_frames, config)
        out.append({"scenario": path.stem, "seed": seed, **summarize(d)})
    return {"seed": seed, "scenarios": out}


def _f(v, spec=".2f"):
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def _age(lo, hi):
    return f"> {lo:g} s" if not math.isfinite(hi) else f"{lo:g}–{hi:g} s"


def markdown(res: dict, command: str = COMMAND) -> str:
    head = " | ".join(_age(lo, hi) for lo, hi in AGE_BINS_S)
    lines = [
        "Each track's pixel against the projection, through the true camera, of the world point its birth pixel saw "
        "(module doc of bench/track_drift.py): median / 90th percentile of the distance, px, and the share beyond 1 px, "
        "by the track's age; the same rendered flight tracked with the drift correction off and on.",
        "",
        f"| scenario | drift correction | samples | {head} | beyond 1 px, all ages |",
        "|---|---|---|" + "---|" * len(AGE_BINS_S) + "---|",
    ]
    for sc in res["scenarios"]:
        for name, label in (("off", "off"), ("on", f"{sc['correct_px']:g} px")):
            bins = sc["variants"][name]
            n = sum(b["n"] for b in bins)
            beyond = sum(b["beyond_1px"] * b["n"] for b in bins if b["n"]) / n if n else float("nan")
            cells = " | ".join(f"{_f(b['median_px'])} / {_f(b['p90_px'])}" for b in bins)
            lines.append(f"| {sc['scenario']} (seed {sc['seed']}) | {label} | {n} | {cells} | {_f(100 * beyond, '.1f')} % |")
    lines += ["", f"Command: `{command}`"]
    return "\n".join(lines)


def main(argv=None) -> int:
    from bench.report import rendered_flight_parser

    ap = rendered_flight_parser(COMMAND, __doc__, DEFAULT_SCENARIOS, "python -m bench track_drift --scenario quad_approach --scenario quad_slalom --seed 1")
    ap.add_argument("--correct-px", type=float, default=None, metavar="X",
                    help="reference_correct_px of the 'on' variant (default: the configuration's, 0.5 where it is off)")
    ap.add_argument("--config", metavar="TOML", help="companion configuration to track with (default: the scenario's, else "
                                                      "configs/companion.toml); an overlay may set [tracks] reference_half")
    ap.add_argument("--max-frames", type=int, default=None, metavar="K", help="track only the first K frames (default all)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON instead of markdown")
    a = ap.parse_args(argv)
    if a.correct_px is not None and not (math.isfinite(a.correct_px) and a.correct_px > 0):
        ap.error("--correct-px must be a positive number")
    if a.config is not None and not Path(a.config).is_file():
        ap.error(f"--config: no such file: {a.config}")
    if a.max_frames is not None and a.max_frames < 2:
        ap.error("--max-frames must be at least 2")
    scenarios = a.scenario or list(DEFAULT_SCENARIOS)
    from companion.io.progress import ProgressBar

    with ProgressBar("frames tracked", total=None, enabled=False if a.json else None) as bar:
        res = run(scenarios, a.seed, a.correct_px, progress=bar.advance, max_frames=a.max_frames, config=a.config)
    cmd = (COMMAND + "".join(f" --scenario {s}" for s in (a.scenario or [])) + f" --seed {a.seed}"
           + (f" --correct-px {a.correct_px:g}" if a.correct_px is not None else "")
           + (f" --config {a.config}" if a.config is not None else "")
           + (f" --max-frames {a.max_frames}" if a.max_frames is not None else ""))
    print(json.dumps(res, indent=2) if a.json else markdown(res, cmd))
    return 0


if __name__ == "__main__":
    sys.exit(main())
