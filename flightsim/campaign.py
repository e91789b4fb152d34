"""Monte Carlo campaigns over seeds, scored and reported (``flightsim campaign``).

``run_campaign(scenario, out, runs=N, workers=W)`` runs seeds ``seed0 … seed0+N−1`` (``seed0`` = the
scenario's own ``[scenario] seed`` unless given), each in a worker process
(:class:`concurrent.futures.ProcessPoolExecutor`, ``spawn`` start method) into
``out/runs/seed_NNNN/``:

* mode ``replay``: :func:`flightsim.fly.fly` then :func:`companion.replay.replay` in-process with a
  fixed processing time (deterministic), ranges in ``ranges.tlog``;
* mode ``sitl``: :func:`flightsim.sitl.run_sitl` (lockstep clock, free ports), ranges in
  ``received.tlog`` (stamped on arrival);
* then :func:`flightsim.score.files.score_run` (obstacles named from the scenario's world) writes
  ``score.json``, ``score.md`` and ``score_series.npz``.

The companion configuration of every run (and of the scoring: its ``sigma_k``) is the one given,
else the scenario's ``[scenario] companion_config``, else ``configs/companion.toml``.

A run that raises is recorded (``status = "failed"``, the error, ``error.txt`` with the traceback)
and the campaign goes on; each run logs into its own ``run.log``.  Afterwards the runs are pooled
(:func:`aggregate`) into ``out/campaign.json`` and ``out/report/`` (:mod:`flightsim.report`), each
appearing whole (:mod:`companion.io.atomic`).  A campaign starting in ``out`` first removes the
``campaign.json`` and ``report/`` of an earlier one there (their runs are about to be replaced).
Interrupted (Ctrl-C, SIGTERM), it stops the workers (SIGTERM: each run unwinds and leaves none of
its outputs), pools the runs that finished into ``campaign.json.partial`` and ``report.partial/``
— names that say what they hold — and re-raises.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import importlib
import json
import logging
import math
import multiprocessing
import os
import shutil
import signal
import time
import traceback
from pathlib import Path
from typing import Callable

import numpy as np

from companion.errors import EXIT_TERMINATED, ConfigError, Terminated
from companion.io.atomic import atomic_dir, partial_path, prepare_output_dir, write_text_atomic
from flightsim.score.config import ScoreConfig
from flightsim.score.markdown import mark
from flightsim.score.stats import pooled_n_eff
from flightsim.score.summary import _jsonable, nees_stats

log = logging.getLogger(__name__)

MODES = ("auto", "replay", "sitl")
BACKENDS = ("process", "ray")
_BIN_COUNTS = ("obstacle_cells", "ranges", "valid", "unknown", "clear", "claimed")
RATE_KEYS = ("detection", "valid_range", "dangerous_clear", "false_obstacle_clear_cells", "too_near", "over_range",
             "messages_without_false_obstacle", "messages_with_claims")


@dataclasses.dataclass(frozen=True)
class RunJob:
    """One run of a campaign (picklable: it crosses into the worker process)."""

    scenario: str
    seed: int
    run_dir: str
    mode: str  # "replay" | "sitl"
    companion_config: str | None
    score_config: ScoreConfig
    fixed_processing_ms: float
    keep_video: bool = False
    avoidance: str | None = None  # overrides the scenario's [avoidance] model (closed loop: SITL only)
    landmark_log: bool = False  # each run also writes the companion's landmark log, landmarks.jsonl (companion/landmark_log.py)


# ---------------------------------------------------------------------- one run (worker) --------
def _log_to(path: Path) -> logging.Handler:
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    h = logging.FileHandler(path, encoding="utf-8")
    h.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root.addHandler(h)
    root.setLevel(logging.INFO)
    return h


def _replay_run(job: RunJob, sc, run_dir: Path) -> Path:
    from companion.cli import load_config
    from companion.replay import replay
    from flightsim.fly import fly

    fly(sc, run_dir, plot=False)
    rc = load_config(job.companion_config, None, str(run_dir / "camera.toml"))
    out = run_dir / "ranges.tlog"
    sink = None
    if job.landmark_log:
        from companion.landmark_log import LandmarkLog
        from flightsim.score.files import LANDMARK_LOG

        sink = LandmarkLog(run_dir / LANDMARK_LOG)
    try:
        replay(run_dir / "telemetry.tlog", run_dir / "video.avi", run_dir / "frames.csv", out, rc.companion,
               camera=rc.companion.camera, pipeline=rc.pipeline, fixed_processing_s=job.fixed_processing_ms / 1000.0,
               landmark_sink=sink)
    finally:
        if sink is not None:
            sink.close()
    return out


def _sitl_run(job: RunJob, run_dir: Path) -> Path:
    from flightsim.sitl import SitlConfig, run_sitl

    run_sitl(job.scenario, run_dir, seed=job.seed, clock="lockstep", port_base=None, companion_config=job.companion_config,
             processing_ms=job.fixed_processing_ms, score=False, avoidance=job.avoidance,
             config=SitlConfig(landmark_log=job.landmark_log))
    return run_dir / "received.tlog"


def run_one(job: RunJob) -> dict:
    """Fly, range and score one seed (in a worker process); never raises for a failed run."""
    from flightsim.scenario import load_scenario
    from flightsim.score.files import score_run, write_score

    run_dir = Path(job.run_dir)
    if run_dir.exists():  # a previous campaign's run of this seed: start clean (the directory belongs to the campaign)
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    handler = _log_to(run_dir / "run.log")
    t0 = time.perf_counter()
    res = {"seed": job.seed, "dir": str(run_dir), "status": "failed", "error": None, "wall_s": None, "score": None}
    try:
        logging.getLogger(__name__).info("run seed %d, mode %s", job.seed, job.mode)
        sc = load_scenario(job.scenario, seed=job.seed, avoidance=job.avoidance)
        ranges = _replay_run(job, sc, run_dir) if job.mode == "replay" else _sitl_run(job, run_dir)
        score = score_run(ranges, run_dir / "truth.npz", config=job.score_config, companion_config=job.companion_config,
                          world=sc.world, series_out=run_dir / "score_series.npz", plot_dir=run_dir)
        write_score(run_dir, score)
        if score.get("avoidance"):
            from flightsim.plots import plot_run_outcome

            plot_run_outcome(run_dir, sc.world, score["avoidance"], title=f"{sc.meta.name} seed {job.seed}")
        res.update(status="ok", score=score)
    except Exception as exc:  # recorded, the campaign goes on
        res["error"] = f"{type(exc).__name__}: {exc}"
        (run_dir / "error.txt").write_text(traceback.format_exc(), encoding="utf-8")
        logging.getLogger(__name__).error("run seed %d failed: %s", job.seed, res["error"])
    finally:
        res["wall_s"] = round(time.perf_counter() - t0, 2)
        video = run_dir / "video.avi"
        if not job.keep_video and video.exists():
            video.unlink()
        handler.close()
        logging.getLogger().removeHandler(handler)
    return res


# ---------------------------------------------------------------------- aggregation -------------
def wilson_interval(k: int, n: int, confidence: float = 0.95) -> tuple[float | None, float | None]:
    """Wilson score interval of a binomial proportion k/n (sound at k = 0 and at k = n, where the
    normal approximation collapses to a point)."""
    if n <= 0:
        return None, None
    from statistics import NormalDist

    z = NormalDist().inv_cdf(0.5 + confidence / 2.0)
    p = k / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    lo = 0.0 if k == 0 else max(0.0, centre - half)  # exact at the edges (the formula gives them up to rounding)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return lo, hi


def pool_outcomes(outcomes: list[dict]) -> dict:
    """Closed-loop outcomes of several runs pooled (:mod:`flightsim.outcome`): collision and false-stop
    rates with 95 % Wilson intervals, stop clearance, minimum clearance, progress, time to goal."""
    n = len(outcomes)
    coll = sum(1 for o in outcomes if o["collision"])
    fstop = sum(1 for o in outcomes if o["false_stop"])
    stopped = [o["stop_clearance_m"] for o in outcomes if o["stop_clearance_m"] is not None and not o["collision"]]
    goal = [o["time_to_goal_s"] for o in outcomes if o["time_to_goal_s"] is not None]
    lo, hi = wilson_interval(coll, n)
    flo, fhi = wilson_interval(fstop, n)
    return {
        "runs": n, "model": sorted({o["model"] for o in outcomes}),
        "collisions": coll, "collision_rate": coll / n if n else None, "collision_ci95": [lo, hi],
        "false_stops": fstop, "false_stop_rate": fstop / n if n else None, "false_stop_ci95": [flo, fhi],
        "stopped_short": len(stopped), "stop_clearance_m": _mean_std(stopped),
        "min_clearance_m": _mean_std(o["min_clearance_m"] for o in outcomes),
        "progress": _mean_std(o["progress"] for o in outcomes),
        "reached_goal": len(goal), "time_to_goal_s": _mean_std(goal),
        "max_speed_mps": _mean_std(o["max_speed_mps"] for o in outcomes),
        "data_while_pushing": _mean_std(o.get("data_while_pushing") for o in outcomes),
    }


def _mean_std(values) -> dict:
    v = np.array([x for x in values if x is not None], float)
    return {"n": int(v.size), "mean": float(v.mean()) if v.size else None,
            "std": float(v.std(ddof=1)) if v.size > 1 else (0.0 if v.size == 1 else None),
            "min": float(v.min()) if v.size else None, "max": float(v.max()) if v.size else None}


def pooled_nees(scores: list[dict], samples: np.ndarray, confidence: float) -> dict:
    """The NEES of the runs' forward samples pooled (``samples``: their NEES series, concatenated),
    against the band of the mean with the pooled effective size
    (:func:`~flightsim.score.stats.pooled_n_eff` of the runs' ``n`` and ``n_eff``: the sum of the
    runs' n_eff when they share one correlation time, less when a long correlated run dominates;
    ``n_eff_sum_of_runs`` beside it), the independent-sample band, and the pooled ±σ / ±2σ coverage.
    The effective size is unknown (no band) if a run with samples has none (an older score)."""
    runs = [(int(s["nees"].get("n") or 0), s["nees"].get("n_eff")) for s in scores if (s.get("nees") or {}).get("n")]
    known = bool(runs) and all(e for _, e in runs)
    n_eff = pooled_n_eff([m for m, _ in runs], [e for _, e in runs]) if known else None
    out = nees_stats(samples, confidence, n_eff=n_eff)
    out["n_eff_sum_of_runs"] = float(sum(e for _, e in runs)) if known else None
    return out


def _sum_nested(blocks: list[dict]) -> dict:
    """Dicts of counts (nested dicts of counts too) summed key by key; a key missing from a block adds 0."""
    out: dict = {}
    for b in blocks:
        for k, v in b.items():
            out[k] = _sum_nested([out.get(k) or {}, v]) if isinstance(v, dict) else out.get(k, 0) + int(v)
    return out


def pool_log_counts(per_run: list) -> dict | None:
    """The runs' counts from the companion's sector log summed — ``claims_by_source``
    (:func:`flightsim.score.summary.claims_by_source`) or ``unknown_by_reason``
    (:func:`flightsim.score.summary.unknown_by_reason`) — with ``runs``, the runs that had them; None when none had."""
    have = [c for c in per_run if c]
    return {"runs": len(have), **_sum_nested(have)} if have else None


def _sum_counts(scores: list[dict], block: str, keys) -> dict[str, int]:
    """The runs' counts ``score[block][key]`` summed (a run without the block, or the key, adds 0)."""
    return {k: sum(int((s.get(block) or {}).get(k) or 0) for s in scores) for k in keys}


def aggregate(results: list[dict], series: dict[int, dict], config: ScoreConfig = ScoreConfig()) -> dict:
    """Pool the scored runs: summed cell counts and pooled rates, mean ± std of per-run rates, the
    targets on the pooled rates (and how many runs meet each), pooled range error, latency, NEES and
    time to the first valid range per obstacle name.  ``series``: seed → score_series arrays."""
    from flightsim.score.summary import error_table

    ok = [r for r in results if r["status"] == "ok" and r.get("score")]
    scores = [r["score"] for r in ok]
    def sum_cells(key: str) -> dict[str, int]:
        out: dict[str, int] = {}
        for s in scores:
            for k, v in (s.get(key) or {}).items():
                out[k] = out.get(k, 0) + int(v or 0)
        return out

    cells = sum_cells("cells")
    cells_iv, cells_oov = sum_cells("cells_in_view"), sum_cells("cells_out_of_view")

    def rate(num, den):
        return None if not cells.get(den) else cells.get(num, 0) / cells[den]

    pooled = {
        "detection": rate("detections", "obstacle"), "valid_range": rate("valid_ranges", "obstacle"),
        "dangerous_clear": rate("dangerous_clears", "obstacle"), "too_near": rate("too_near", "obstacle"),
        "over_range": rate("over_range", "obstacle"), "false_obstacle_clear_cells": rate("false_obstacles_clear_cells", "clear"),
        "messages_without_false_obstacle": rate("messages_without_false_obstacle", "messages_eligible_no_false"),
    }
    def pooled_of(c: dict) -> dict:
        r = lambda num, den: None if not c.get(den) else c.get(num, 0) / c[den]  # noqa: E731
        return {"detection": r("detections", "obstacle"), "valid_range": r("valid_ranges", "obstacle"),
                "dangerous_clear": r("dangerous_clears", "obstacle"), "unknown_in_obstacle_cells": r("unknown_in_obstacle_cells", "obstacle"),
                "false_obstacle_clear_cells": r("false_obstacles_clear_cells", "clear"), "too_near": r("too_near", "obstacle"),
                "over_range": r("over_range", "obstacle"), "messages_without_false_obstacle": r("messages_without_false_obstacle", "messages_eligible_no_false")}

    per_run = {k: _mean_std(s["rates"].get(k) for s in scores) for k in RATE_KEYS}
    per_run_in_view = {k: _mean_std((s.get("rates_in_view") or {}).get(k) for s in scores) for k in RATE_KEYS}
    targets = []
    for i, t in enumerate(scores[0]["targets"] if scores else []):
        same = all(len(s["targets"]) > i and s["targets"][i].get("key") == t.get("key") for s in scores)
        if t.get("key") is not None and "num" in t and same:  # rate targets: pool numerators and denominators
            num = sum(int(s["targets"][i]["num"] or 0) for s in scores)
            n = sum(int(s["targets"][i]["n"] or 0) for s in scores)
            v = num / n if n else None
        else:  # older scores: their first two targets only
            key = "messages_without_false_obstacle" if i == 0 else "dangerous_clear"
            v = pooled[key]
            n = cells.get("messages_eligible_no_false" if i == 0 else "obstacle", 0)
        met = None if v is None else (v >= t["threshold"] if t["op"] == ">=" else v <= t["threshold"])
        runs_met = sum(1 for s in scores if s["targets"][i]["met"])
        runs_known = sum(1 for s in scores if s["targets"][i]["met"] is not None)
        targets.append({"key": t.get("key"), "name": t["name"], "op": t["op"], "threshold": t["threshold"], "pooled": v, "n": n, "met": met,
                        "runs_met": runs_met, "runs_scored": runs_known})
    cat = lambda key: np.concatenate([np.asarray(series[s][key], float).reshape(-1) for s in series]) if series else np.zeros(0)  # noqa: E731
    bins = config.range_bins_m
    ds_T, ds_max = cat("ds_truth_arrival"), cat("ds_max_m")
    ds_pub, ds_est, ds_state = cat("ds_published_m"), cat("ds_estimate_m"), cat("ds_state")
    fwd = (ds_state == 1) & np.isfinite(ds_T) & (ds_T <= ds_max)
    range_error = {
        "published_all_sectors": error_table(cat("det_true_m"), cat("det_published_m"), bins),
        "published_forward": error_table(ds_T[fwd], ds_pub[fwd], bins),
        "estimate_forward": error_table(ds_T[fwd & np.isfinite(ds_est)], ds_est[fwd & np.isfinite(ds_est)], bins),
    }
    lat = cat("od_latency_s")
    lat = lat[np.isfinite(lat)] * 1000.0
    pct = lambda q: float(np.percentile(lat, q)) if lat.size else None  # noqa: E731
    latency = {"n": int(lat.size), "p50_ms": pct(50), "p95_ms": pct(95), "p99_ms": pct(99),
               "max_ms": float(lat.max()) if lat.size else None}
    nees = pooled_nees(scores, cat("nees_exposure"), config.nees_confidence)
    nees["arrival"] = pooled_nees([{"nees": s["nees"].get("arrival") or {}} for s in scores], cat("nees_arrival"),
                                  config.nees_confidence)
    nees["per_run_mean"] = _mean_std(s["nees"]["mean"] for s in scores)
    nees["runs_consistent"] = sum(1 for s in scores if s["nees"].get("consistent"))
    nees["runs_with_samples"] = sum(1 for s in scores if s["nees"].get("n"))
    nees["confidence"] = config.nees_confidence
    obstacles: dict[str, dict] = {}
    for s in scores:
        for o in s["obstacles"]:
            d = obstacles.setdefault(o["name"], {"name": o["name"], "runs_in_range": 0, "runs_valid": 0, "ttfv": [],
                                                 "detected_fraction": [], "in_range_at_s": [], "runs_rangeable": 0,
                                                 "ttfv_rangeable": []})
            if o["in_range_at_s"] is not None:
                d["runs_in_range"] += 1
                d["in_range_at_s"].append(o["in_range_at_s"])
                d["detected_fraction"].append(o["detected_fraction"])
                if o["time_to_first_valid_s"] is not None:
                    d["runs_valid"] += 1
                    d["ttfv"].append(o["time_to_first_valid_s"])
                if o.get("first_rangeable_at_s") is not None:
                    d["runs_rangeable"] += 1
                    if o.get("time_to_first_valid_after_rangeable_s") is not None:
                        d["ttfv_rangeable"].append(o["time_to_first_valid_after_rangeable_s"])
    obs_rows = []
    for d in obstacles.values():
        obs_rows.append({"name": d["name"], "runs_in_range": d["runs_in_range"], "runs_with_valid_range": d["runs_valid"],
                         "runs_never_valid": d["runs_in_range"] - d["runs_valid"],
                         "in_range_at_s": _mean_std(d["in_range_at_s"]), "time_to_first_valid_s": _mean_std(d["ttfv"]),
                         "runs_never_rangeable": d["runs_in_range"] - d["runs_rangeable"],
                         "time_to_first_valid_after_rangeable_s": _mean_std(d["ttfv_rangeable"]),
                         "detected_fraction": _mean_std(d["detected_fraction"])})
    # detection by true range: the runs' bin counts summed (same bins: one score config per campaign)
    det_by_range: dict[str, list[dict]] = {}
    for view in ("in_view", "out_of_view"):
        rows: list[dict] = []
        for s in scores:
            for b, row in enumerate((s.get("detection_by_range") or {}).get(view, [])):
                if b >= len(rows):
                    rows.append({k: row[k] for k in ("bin", "lo_m", "hi_m")} | {k: 0 for k in _BIN_COUNTS})
                for k in _BIN_COUNTS:
                    rows[b][k] += int(row.get(k) or 0)
        for row in rows:
            n_ = row["obstacle_cells"]
            row.update({"valid_rate": row["valid"] / n_ if n_ else None, "range_rate": row["ranges"] / n_ if n_ else None,
                        "unknown_rate": row["unknown"] / n_ if n_ else None, "dangerous_rate": row["clear"] / n_ if n_ else None,
                        "valid_of_claimed": row["valid"] / row["claimed"] if row["claimed"] else None})
        det_by_range[view] = rows
    rem = _sum_counts(scores, "remembered", ("cells", "within_tolerance", "ranges", "unknown", "dangerous_clears",
                                             "too_near", "over_range", "rangeable_cells", "rangeable_within_tolerance"))
    rem["rate"] = rem["within_tolerance"] / rem["cells"] if rem["cells"] else None
    rem["rangeable_rate"] = rem["rangeable_within_tolerance"] / rem["rangeable_cells"] if rem["rangeable_cells"] else None
    rng = _sum_counts(scores, "rangeable", ("obstacle_cells_in_view", "cells", "within_tolerance", "unknown",
                                            "not_rangeable_within_tolerance"))
    rng["share"] = rng["cells"] / rng["obstacle_cells_in_view"] if rng["obstacle_cells_in_view"] else None
    rng["rate"] = rng["within_tolerance"] / rng["cells"] if rng["cells"] else None
    first_rng = next((s["rangeable"] for s in scores if s.get("rangeable")), None)
    if first_rng:
        rng.update({k: first_rng.get(k) for k in ("window_s", "parallax_deg", "scale")})
    beside = _sum_counts(scores, "false_obstacles_beside_obstacle", ("in_view", "in_view_total", "out_of_view", "out_of_view_total"))
    by_source = pool_log_counts([s.get("claims_by_source") for s in scores])
    outcomes = [s["avoidance"] for s in scores if s.get("avoidance")]
    return _jsonable({
        "avoidance": pool_outcomes(outcomes) if outcomes else None,
        "runs": len(results), "runs_ok": len(ok), "runs_failed": len(results) - len(ok),
        "cells": cells, "pooled_rates": pooled, "per_run_rates": per_run, "targets": targets,
        "cells_in_view": cells_iv, "cells_out_of_view": cells_oov, "pooled_rates_in_view": pooled_of(cells_iv),
        "pooled_rates_out_of_view": pooled_of(cells_oov), "per_run_rates_in_view": per_run_in_view,
        "detection_by_range": det_by_range, "remembered": rem, "rangeable": rng if first_rng else None,
        "false_obstacles_beside_obstacle": beside,
        "claims_by_source": by_source,
        "unknown_by_reason": pool_log_counts([s.get("unknown_by_reason") for s in scores]),
        "warmup_messages_excluded": sum(int((s.get("warmup") or {}).get("messages_excluded") or 0) for s in scores),
        "range_error": range_error, "latency": latency, "nees": nees, "obstacles": obs_rows,
        "first_claim_at_s": _mean_std(s.get("first_claim_at_s") for s in scores),
    })


def run_key_figures(score: dict) -> dict:
    """The per-run line of campaign.json (the full score is in the run's score.json)."""
    r = score["rates"]
    return _jsonable({
        "detection": r["detection"], "valid_range": r["valid_range"], "dangerous_clear": r["dangerous_clear"],
        "false_obstacle_clear_cells": r["false_obstacle_clear_cells"], "too_near": r["too_near"],
        "messages_without_false_obstacle": r["messages_without_false_obstacle"],
        "targets_met": [t["met"] for t in score["targets"]],
        "detection_in_view": (score.get("rates_in_view") or {}).get("valid_range"),
        "remembered": (score.get("remembered") or {}).get("rate"),
        "rangeable_share": (score.get("rangeable") or {}).get("share"),
        "detection_rangeable": (score.get("rangeable") or {}).get("rate"), "latency_p50_ms": score["latency"]["p50_ms"],
        "latency_p99_ms": score["latency"]["p99_ms"], "nees_mean": score["nees"]["mean"], "nees_n": score["nees"]["n"],
        "nees_n_eff": score["nees"].get("n_eff"), "nees_band": score["nees"].get("band"),
        "nees_consistent": score["nees"].get("consistent"),
        "coverage_2sigma": (score["nees"].get("coverage") or {}).get("rate_2sigma"),
        "first_claim_at_s": score["first_claim_at_s"],
        "time_to_first_valid_s": {o["name"]: o["time_to_first_valid_s"] for o in score["obstacles"]},
        "avoidance": None if not score.get("avoidance") else {
            k: score["avoidance"][k] for k in ("collision", "min_clearance_m", "stop_clearance_m", "false_stop", "progress",
                                               "time_to_goal_s")},
    })


# ---------------------------------------------------------------------- the campaign ------------
def sitl_available() -> bool:
    try:
        mod = importlib.import_module("flightsim.sitl")
    except ImportError:
        return False
    return callable(getattr(mod, "run_sitl", None))


def resolve_mode(mode: str) -> str:
    if mode not in MODES:
        raise ConfigError(f"--mode must be one of {', '.join(MODES)}, got {mode!r}")
    if mode == "auto":
        return "sitl" if sitl_available() else "replay"
    if mode == "sitl" and not sitl_available():
        raise ConfigError("--mode sitl: flightsim.sitl.run_sitl is not available in this checkout yet; use --mode replay")
    return mode


def parse_times(text: str | None) -> list[float] | None:
    if text is None or not str(text).strip():
        return None
    try:
        vals = [float(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--times {text!r}: expected comma-separated seconds, e.g. 3,6,9") from None
    if not vals or not all(math.isfinite(v) and v >= 0 for v in vals):
        raise ConfigError(f"--times {text!r}: times must be finite and >= 0")
    return vals


def run_campaign(scenario: str | Path, out: str | Path, *, runs: int, workers: int | None = None, mode: str = "auto",
                 seed0: int | None = None, companion_config: str | Path | None = None,
                 score_config: ScoreConfig | None = None, fixed_processing_ms: float = 30.0, keep_video: bool = False,
                 obstacle: str = "forward", times: list[float] | None = None,
                 progress: Callable[[int, int, int], None] | None = None,
                 run_fn: Callable[[RunJob], dict] = run_one, avoidance: str | None = None,
                 backend: str = "process", address: str | None = None, landmark_log: bool = False) -> dict:
    """Run, score and report a campaign (module docstring); returns the campaign.json contents.

    ``progress(done, total, failed)`` is called as runs finish.  ``run_fn`` runs one job in the
    worker (a picklable module-level function; :func:`run_one` by default).  ``backend``: "process"
    (a local process pool, the default) or "ray" (Ray tasks, at ``address`` or a local Ray; inputs
    and outputs travel as data, no shared file system: :mod:`flightsim.campaign_ray`).  ``landmark_log``: each run
    also writes the companion's landmark log (``python -m bench landmark_truth`` reads it).
    """
    from flightsim.report import write_report
    from flightsim.scenario import load_scenario, resolve_companion_config
    from flightsim.score.files import load_series

    if not (isinstance(runs, int) and runs >= 1):
        raise ConfigError(f"--runs must be an integer >= 1, got {runs!r}")
    if backend not in BACKENDS:
        raise ConfigError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "ray":
        from flightsim.campaign_ray import require_ray

        require_ray()
    cpu = os.cpu_count() or 1
    workers = min(runs, cpu) if workers is None else workers
    if not (isinstance(workers, int) and workers >= 1):
        raise ConfigError(f"--workers must be an integer >= 1, got {workers!r}")
    if not (math.isfinite(fixed_processing_ms) and fixed_processing_ms >= 0):
        raise ConfigError(f"--fixed-processing-ms must be >= 0, got {fixed_processing_ms}")
    scenario = Path(scenario).resolve()
    sc = load_scenario(scenario, avoidance=avoidance)  # a bad scenario stops here, before any worker starts
    if sc.avoidance.model != "none":  # the closed loop needs the live companion: SITL
        if mode == "replay":
            raise ConfigError(f"{scenario.name}: avoidance {sc.avoidance.model!r} closes the loop through the live companion; "
                              "use --mode sitl (or auto), not replay")
        mode = "sitl"
    mode = resolve_mode(mode)
    base = sc.meta.seed if seed0 is None else int(seed0)
    if base < 0:
        raise ConfigError(f"--seed0 must be >= 0, got {base}")
    companion_config = resolve_companion_config(sc, companion_config)
    if companion_config is not None:
        from flightsim.score.files import companion_score_params

        companion_config = Path(companion_config).resolve()
        if not companion_config.is_file():
            raise ConfigError(f"--companion-config {companion_config}: no such file")
        companion_score_params(companion_config)  # validates the file before the runs
    cfg = score_config or ScoreConfig()
    out = prepare_output_dir(out)
    (out / "runs").mkdir(exist_ok=True)
    _remove_stale_results(out)
    jobs = [RunJob(str(scenario), base + i, str(out / "runs" / f"seed_{base + i:04d}"), mode,
                   None if companion_config is None else str(companion_config), cfg, float(fixed_processing_ms), keep_video,
                   avoidance, bool(landmark_log))
            for i in range(runs)]
    log.info("campaign %s: %d runs (seeds %d…%d), mode %s, %d workers, companion config %s → %s", sc.meta.name, runs, base,
             base + runs - 1, mode, workers, companion_config or "built-in defaults", out)
    wall0 = time.perf_counter()
    results: dict[int, dict] = {}
    failed = 0
    interrupted: BaseException | None = None  # the KeyboardInterrupt / Terminated that stopped the campaign

    def record(job: RunJob, res: dict) -> None:
        nonlocal failed
        results[job.seed] = res
        if res["status"] != "ok":
            failed += 1
            log.warning("seed %d failed: %s", job.seed, res["error"])
        else:
            log.info("seed %d scored in %.1f s", job.seed, res["wall_s"] or 0.0)
        if progress:
            progress(len(results), runs, failed)

    if backend == "ray":
        from flightsim.campaign_ray import run_jobs

        try:
            run_jobs(jobs, scenario, companion_config, address, record, None if run_fn is run_one else run_fn)
        except (KeyboardInterrupt, Terminated) as exc:
            interrupted = exc
            log.warning("interrupted: %d of %d runs done; writing what there is", len(results), runs)
    else:
        interrupted = _run_in_processes(jobs, workers, run_fn, record)
        if interrupted is not None:
            log.warning("interrupted: %d of %d runs done; writing what there is", len(results), runs)
    ordered = [results[j.seed] for j in jobs if j.seed in results]
    series = {}
    for r in ordered:
        p = Path(r["dir"]) / "score_series.npz"
        if r["status"] == "ok" and p.is_file():
            series[r["seed"]] = load_series(p)
    agg = aggregate(ordered, series, cfg)
    if landmark_log:
        agg["landmarks"] = landmark_rows(ordered)
    campaign = {
        "scenario": str(scenario), "scenario_name": sc.meta.name, "mode": mode, "seeds": [j.seed for j in jobs],
        "avoidance": sc.avoidance.model,
        "workers": workers, "backend": backend, "fixed_processing_ms": fixed_processing_ms,
        "companion_config": None if companion_config is None else str(companion_config),
        "score_config": dataclasses.asdict(cfg), "wall_s": round(time.perf_counter() - wall0, 2), "interrupted": interrupted is not None,
        "runs": [{k: v for k, v in r.items() if k != "score"} | ({"key_figures": run_key_figures(r["score"])} if r["score"] else {})
                 for r in ordered],
        "aggregate": agg,
    }
    campaign = _jsonable(campaign)
    report_dir = out / "report" if interrupted is None else partial_path(out / "report")
    with atomic_dir(report_dir) as tmp:
        report_files = write_report(tmp, campaign, series, obstacle=obstacle, times=times)
    campaign["report"] = {k: str(report_dir / Path(v).name) for k, v in report_files.items()}
    summary = out / "campaign.json" if interrupted is None else partial_path(out / "campaign.json")
    write_text_atomic(summary, json.dumps(campaign, indent=2, ensure_ascii=False) + "\n")
    if interrupted is not None:
        raise interrupted
    return campaign


def landmark_rows(results: list[dict]) -> dict | None:
    """Each converged landmark against the truth, pooled over the runs that finished and wrote a landmark log
    (:mod:`flightsim.score.landmarks`): ``{"runs": n, "bins": [...]}``; None when no run has a log.  A run whose log
    cannot be read is left out and named in the campaign's log."""
    from flightsim.score.landmarks import landmark_z, load_run, summarize

    samples, used = [], 0
    for r in results:
        if r["status"] != "ok":
            continue
        try:
            frames, t, R, p, raycast = load_run(Path(r["dir"]))
        except Exception as exc:  # a missing or broken log costs the table a run, not the campaign
            log.warning("seed %s: no landmark table (%s)", r.get("seed"), exc)
            continue
        samples.append(landmark_z(frames, t, R, p, raycast))
        used += 1
    if not used:
        return None
    return {"runs": used, "bins": summarize(np.concatenate(samples))}


def _remove_stale_results(out: Path) -> None:
    """Remove an earlier campaign's pooled results in ``out``: its runs are about to be replaced."""
    for name in ("campaign.json", partial_path("campaign.json").name):
        (out / name).unlink(missing_ok=True)
    for name in ("report", partial_path("report").name):
        if (out / name).is_dir():
            shutil.rmtree(out / name)


_JOB_RUNNING = False  # in a worker process: a run is in progress (SIGTERM unwinds it) or not (SIGTERM ends the worker)


def _worker_init() -> None:
    """Worker processes leave Ctrl-C to the campaign, which stops them with SIGTERM (:func:`_stop_workers`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _worker_sigterm)


def _worker_sigterm(signum, _frame) -> None:
    """A running run unwinds (:class:`Terminated`: its temporary outputs removed, its companion stopped,
    then the worker exits in :func:`_run_job`); an idle worker exits at once."""
    if _JOB_RUNNING:
        raise Terminated(f"{signal.Signals(signum).name} received")
    os._exit(EXIT_TERMINATED)


def _run_job(run_fn: Callable[[RunJob], dict], job: RunJob) -> dict:
    """``run_fn(job)`` in a worker process; stopped by SIGTERM, the worker exits once the run has unwound."""
    global _JOB_RUNNING
    _JOB_RUNNING = True
    try:
        return run_fn(job)
    except Terminated:
        os._exit(EXIT_TERMINATED)  # no further queued run: the campaign is stopping
    finally:
        _JOB_RUNNING = False


def _stop_workers(procs: list, timeout_s: float = 60.0) -> None:
    """SIGTERM to the worker processes ``procs``; wait for their runs to unwind (SIGKILL after ``timeout_s``)."""
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    deadline = time.monotonic() + timeout_s
    for proc in procs:
        proc.join(max(0.0, deadline - time.monotonic()))
        if proc.is_alive():
            log.warning("worker process %d did not stop within %.0f s of SIGTERM: killing it", proc.pid, timeout_s)
            proc.kill()
            proc.join()


def _run_in_processes(jobs: list[RunJob], workers: int, run_fn: Callable[[RunJob], dict],
                      record: Callable[[RunJob, dict], None]) -> BaseException | None:
    """Run ``jobs`` in a process pool, ``record``-ing each result as it comes; returns the
    KeyboardInterrupt / Terminated that stopped it early (the workers stopped first), else None."""
    ex = cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                initializer=_worker_init)
    try:
        futs = {ex.submit(_run_job, run_fn, job): job for job in jobs}
        for fut in cf.as_completed(futs):
            job = futs[fut]
            try:
                res = fut.result()
            except Exception as exc:  # the worker process died (BrokenProcessPool) or run_fn raised
                res = {"seed": job.seed, "dir": job.run_dir, "status": "failed", "error": f"{type(exc).__name__}: {exc}",
                       "wall_s": None, "score": None}
            record(job, res)
    except (KeyboardInterrupt, Terminated) as exc:
        procs = list((getattr(ex, "_processes", None) or {}).values())  # shutdown() forgets them
        ex.shutdown(wait=False, cancel_futures=True)
        _stop_workers(procs)
        return exc
    ex.shutdown(wait=True)
    return None


def campaign_from_args(args) -> int:
    """``flightsim campaign`` (see flightsim/cli.py for the options)."""
    from flightsim.score.files import load_score_config

    times = parse_times(args.times)
    cfg = load_score_config(args.score_config)
    scenario = args.scenario
    if getattr(args, "camera", None):
        from flightsim.scenario import parse_camera_size, scenario_at_camera

        scenario = str(scenario_at_camera(args.scenario, parse_camera_size(args.camera), args.out))
    from companion.io.progress import ProgressBar

    with ProgressBar("campaign", total=args.runs, transient=False, elapsed=True) as bar:
        def tick(done: int, total: int, failed: int) -> None:
            bar.update(done, total, "campaign" + (f" ({failed} failed)" if failed else ""))

        c = run_campaign(scenario, args.out, runs=args.runs, workers=args.workers, mode=args.mode, seed0=args.seed0,
                         companion_config=args.companion_config, score_config=cfg,
                         fixed_processing_ms=args.fixed_processing_ms, keep_video=args.keep_video, obstacle=args.obstacle,
                         times=times, progress=tick, avoidance=args.avoidance, backend=args.backend, address=args.address,
                         landmark_log=args.landmark_log)
    a = c["aggregate"]
    print(f"{c['scenario_name']}: {a['runs_ok']} of {a['runs']} runs scored ({c['mode']} mode) in {c['wall_s']:.0f} s")
    av = a.get("avoidance")
    if av:
        ci = av["collision_ci95"]
        sc_ = av["stop_clearance_m"]
        print(f"avoidance {c['avoidance']}: {av['collisions']} collisions in {av['runs']} runs (rate {100 * av['collision_rate']:.1f} %, "
              f"95 % CI {100 * ci[0]:.1f}–{100 * ci[1]:.1f} %); stopped short in {av['stopped_short']} "
              + (f"(clearance {sc_['mean']:.2f} ± {sc_['std']:.2f} m, min {sc_['min']:.2f})" if sc_["n"] else "")
              + f"; false stops {av['false_stops']}; progress {100 * av['progress']['mean']:.0f} %")
    pr = a["pooled_rates"]
    pc = lambda v: "–" if v is None else f"{100 * v:.2f} %"  # noqa: E731
    print(f"pooled: detection {pc(pr['detection'])}, false obstacle (clear cells) {pc(pr['false_obstacle_clear_cells'])}, "
          f"too near {pc(pr['too_near'])}; latency p50 {a['latency']['p50_ms'] or float('nan'):.1f} ms")
    for t in a["targets"]:
        print(f"  {mark(t['met'])} {t['name']}: {pc(t['pooled'])} (target {t['op']} {100 * t['threshold']:g} %; "
              f"met in {t['runs_met']} of {t['runs_scored']} runs)")
    ne = a["nees"]
    if ne["n"]:
        band = ne.get("band") or [math.nan, math.nan]
        print(f"  {mark(ne['consistent'])} NEES pooled {ne['mean']:.2f} (n = {ne['n']}, n_eff = {ne['n_eff'] or math.nan:.1f}: "
              f"{100 * ne['confidence']:g} % band [{band[0]:.2f}, {band[1]:.2f}]); truth within ±2σ in "
              f"{pc(ne['coverage']['rate_2sigma'])} (normal {pc(ne['coverage']['expected_2sigma'])})")
    for r in c["runs"]:
        if r["status"] != "ok":
            print(f"  seed {r['seed']} FAILED: {r['error']} (see {r['dir']}/error.txt)")
    print(f"report: {Path(args.out) / 'report' / 'index.md'}; machine-readable: {Path(args.out) / 'campaign.json'}")
    return 0 if a["runs_failed"] == 0 else 1
