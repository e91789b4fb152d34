"""Seed-004 through the whole pipeline: rendered frames, real Harris/NCC, telemetry from a tlog.

Each run flies ``configs/scenarios/seed004_straight.toml`` with its own seed (JSBSim J3Cub at
30 m/s towards the six checker targets of seed 004, the paper's gyro model on the attitude,
rendered 320×240 / 45° frames) and replays the export through :func:`companion.replay.replay` with
``configs/companion.toml`` — the same code path as the live companion.  At the frame nearest to
``t_eval_s`` (5 s: the paper's frame 150) each target is matched to the landmark whose estimated
point lies nearest to the target's true bearing (within ``match_px`` pixels in the current
image); its range is compared with the true range from ``truth.npz``.

Figure of merit: RMS range error per target over the runs, and over all targets, next to the
measurement-level anchored EKF of the seed-004 benchmark (same targets and time, pixels with
σ = 2 px, gyro model).  Target: within 1.5× of that error.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "configs" / "scenarios" / "seed004_straight.toml"
CONFIG = ROOT / "configs" / "companion.toml"


def run_one(seed: int, t_eval_s: float = 5.0, match_px: float = 3.0, workdir: Path | None = None) -> dict:
    """Fly and replay one seed; per-target estimated and true range at ``t_eval_s`` (NaN: no match)."""
    from companion.cli import load_config
    from companion.core.camera import CameraModel
    from companion.replay import replay
    from flightsim.fly import fly
    from flightsim.scenario import load_scenario

    sc = load_scenario(SCENARIO, seed=seed)
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        d = Path(tmp)
        fly(sc, d, plot=False)
        truth = np.load(d / "truth.npz")
        rc = load_config(str(CONFIG), None, str(d / "camera.toml"))
        cam = CameraModel(rc.companion.camera)
        t0 = float(truth["t_s"][0])
        k_eval = int(np.argmin(np.abs(truth["t_s"] - (t0 + t_eval_s))))
        outs: dict[int, object] = {}

        def on_frame(pipe, res):
            if res.ok and pipe.landmarks is not None:
                outs[int(res.frame_index)] = pipe.landmarks

        replay(d / "telemetry.tlog", d / "video.avi", d / "frames.csv", d / "ranges.tlog", rc.companion,
               camera=rc.companion.camera, pipeline=rc.pipeline, fixed_processing_s=0.01, on_frame=on_frame)
        names = [str(n) for n in truth["target_names"]]
        p_t = truth["target_p_world"]
        true_all, R_all, p_all = truth["target_range_m"], truth["R_world_cam"], truth["p_world_cam"]
    n = len(names)
    est, sig, true_rng = np.full(n, math.nan), np.full(n, math.nan), np.full(n, math.nan)
    frame = np.full(n, -1)
    cfg = rc.companion.camera
    margin = 8.0
    for i in range(n):
        # the latest processed frame ≤ t_eval in which the target is well inside the image
        for k in sorted((k for k in outs if k <= k_eval), reverse=True):
            uv_t = cam.project(cam.world_to_camera(p_t[i:i + 1], R_all[k], p_all[k]))[0]
            if margin <= uv_t[0] <= cfg.width - 1 - margin and margin <= uv_t[1] <= cfg.height - 1 - margin:
                break
        else:
            continue
        out = outs[k]
        frame[i], true_rng[i] = k, true_all[k, i]
        ok = out.valid & out.converged
        if not np.any(ok):
            continue
        pc = cam.world_to_camera(out.p_world, R_all[k], p_all[k])
        front = pc[:, 2] > 1.0
        uv_l = cam.project(np.where(front[:, None], pc, [0.0, 0.0, 1.0]))
        dist = np.linalg.norm(uv_l - uv_t, axis=1)
        dist[~(ok & front)] = np.inf
        j = int(np.argmin(dist))
        if dist[j] <= match_px:
            est[i], sig[i] = out.range[j], out.range_sigma[j]
    return {"seed": seed, "names": names, "true": true_rng.tolist(), "est": est.tolist(), "sigma": sig.tolist(),
            "frame": frame.tolist()}


def run(runs: int = 20, progress=None, seed0: int = 100) -> dict:
    rows = []
    for k in range(runs):
        rows.append(run_one(seed0 + k))
        if progress:
            progress(1)
    names = rows[0]["names"]
    est = np.array([r["est"] for r in rows])
    true = np.array([r["true"] for r in rows])
    sig = np.array([r["sigma"] for r in rows])
    err = est - true
    found = np.isfinite(err)
    frames = np.array([r["frame"] for r in rows])
    per = {}
    for i, n in enumerate(names):
        e = err[found[:, i], i]
        per[n] = {"rms_m": float(np.sqrt(np.mean(e**2))) if len(e) else math.nan, "found": int(found[:, i].sum()),
                  "mean_m": float(np.mean(e)) if len(e) else math.nan,
                  "mean_abs_m": float(np.mean(np.abs(e))) if len(e) else math.nan,
                  "nees": float(np.mean((e / sig[found[:, i], i]) ** 2)) if len(e) else math.nan,
                  "frame": int(np.median(frames[:, i]))}
    e_all = err[found]
    return {"runs": runs, "seed0": seed0, "per_target": per,
            "rms_all_m": float(np.sqrt(np.mean(e_all**2))) if len(e_all) else math.nan,
            "mean_abs_all_m": float(np.mean(np.abs(e_all))) if len(e_all) else math.nan,
            "found_share": float(found.mean()), "nees_all": float(np.mean((e_all / sig[found]) ** 2)) if len(e_all) else math.nan}


def markdown(res: dict, reference_rms_m: float | None = None) -> str:
    """Table for docs/BENCHMARKS.md; ``reference_rms_m``: the measurement-level mean |error| to compare with."""
    lines = [
        f"`seed004_straight` flown {res['runs']} times (seeds {res['seed0']}…{res['seed0'] + res['runs'] - 1}) and replayed "
        "through the whole companion pipeline (rendered 320×240 frames, Harris + NCC tracks, anchored EKF, "
        "`configs/companion.toml`); range of the landmark on each target's centre corner vs truth, at frame 150 (5 s) or, "
        "for targets that leave the 45° view earlier, at the last frame they are inside it. "
        "Standalone: `python -m bench pipeline004 --runs N`.",
        "",
        "| target | frame (median) | matched runs | mean error m | mean abs error m (eq. 15) | RMS error m | NEES (1 dof) |",
        "|---|---|---|---|---|---|---|",
    ]
    for n, r in res["per_target"].items():
        lines.append(f"| {n} | {r['frame']} | {r['found']}/{res['runs']} | {r['mean_m']:+.2f} | {r['mean_abs_m']:.2f} | {r['rms_m']:.2f} | {r['nees']:.2f} |")
    lines.append(f"| all | | {100 * res['found_share']:.0f} % | | **{res['mean_abs_all_m']:.2f}** | {res['rms_all_m']:.2f} | {res['nees_all']:.2f} |")
    if reference_rms_m is not None and math.isfinite(reference_rms_m):
        ratio = res["mean_abs_all_m"] / reference_rms_m
        lines += ["", f"Measurement-level anchored EKF on the same geometry (seed-004 benchmark above: σ = 2 px, gyro model, "
                  f"frame 150): mean |error| {reference_rms_m:.2f} m → full pipeline / measurement level = **{ratio:.2f}** "
                  f"(target ≤ 1.5: {'✓' if ratio <= 1.5 else '✗'}). The outer targets P1 and P6 leave the 45° view "
                  "near frame 108 and are scored there, earlier than the measurement-level figure (frame 150)."]
    return "\n".join(lines)
