"""SITL benchmarks: lockstep speed and Monte Carlo campaigns scored against truth.

* lockstep ``flightsim sitl`` of ``quad_approach`` (320×240): wall time, real-time factor (target
  ≥ 10×) and the companion's work per lockstep round;
* campaigns (:func:`flightsim.campaign.run_campaign`, SITL mode) of every scenario in
  :data:`CAMPAIGNS`: ``quad_approach`` and ``fixedwing_pass``, and the hard flights
  where docs/derivations/sectors.md says avoidance needs ranges most and a single camera gains least
  (hovering at a wall, turning in place, head-on, close in): ``quad_wall_hover``, ``quad_slalom``,
  ``quad_corner``, ``quad_yaw_spin``, ``fixedwing_tower``.  Pooled detection, unknown,
  false-obstacle and dangerous-clear rates against the targets, range error by bin, latency and
  NEES.  Reports (plots + index.md) go to ``out/bench/``.  Each campaign runs the companion
  configuration its scenario names (``[scenario] companion_config``: the fixed-wing scenarios fly
  ``configs/companion_fixedwing.toml``, max_distance 150 m), else ``configs/companion.toml``.

Seeds: :func:`run_all` runs ``quad_runs`` seeds of each quad scenario and ``fixedwing_runs`` of
each fixed-wing one (8 each by default, the targets ask ≥ 8 per scenario); fewer, or a subset of
the scenarios, from Python or ``python -m bench.sitl_bench --runs 2 --scenarios quad_slalom``.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "configs" / "scenarios"
OUT = ROOT / "out" / "bench"

#: The SITL campaigns of ``make bench``, in report order: scenario → (aircraft class, what it flies).
CAMPAIGNS: dict[str, tuple[str, str]] = {
    "quad_approach": ("quad", "F450 at 5 m/s towards a building, past a mast 3 m beside the path, stopping 5 m short of the mast"),
    "quad_wall_hover": ("quad", "F450 at 4 m/s straight at a warehouse face, then hovering 4 m from it for 8 s"),
    "quad_slalom": ("quad", "F450 weaving between poles of 0.2–0.6 m radius, stopping and turning in place beside each"),
    "quad_corner": ("quad", "F450 along a building 5 m beside it, turning in place at its corner, stopping 5 m short of a second one"),
    "quad_yaw_spin": ("quad", "F450 turning a full circle in place with obstacles 8–24 m away all round, then 6 m on"),
    "fixedwing_pass": ("fixedwing", "J3Cub at 30 m/s past masts and a hangar corner 18–35 m beside the track"),
    "fixedwing_tower": ("fixedwing", "J3Cub at 28 m/s past towers 8–20 m beside the track"),
}


def lockstep_speed(scenario: str = "quad_approach") -> dict:
    from flightsim.sitl import run_sitl

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        s = run_sitl(SCEN / f"{scenario}.toml", tmp, clock="lockstep", score=False)
        wall = time.perf_counter() - t0
        log = (Path(tmp) / "companion.log").read_text(encoding="utf-8", errors="replace")
    per_round = None
    for line in log.splitlines():
        if "lockstep rounds:" in line and "ms per round" in line:
            try:
                per_round = float(line.split("(")[1].split(" ms per round")[0])
            except (IndexError, ValueError):
                pass
    cpu = s.get("cpu_s") or {}
    frames = s.get("frames") or 0

    def per_frame_ms(seconds):
        return 1000.0 * seconds / frames if seconds is not None and frames else None

    return {"scenario": scenario, "duration_s": s.get("duration_s"), "frames": frames,
            "wall_s": s.get("loop_wall_s"), "wall_with_startup_s": wall, "realtime_factor": s.get("realtime_factor"),
            "companion_ms_per_round": per_round,
            # over the flight loop (sitl.json cpu_s.companion_loop, Linux); the whole process (its start-up too) elsewhere
            "companion_cpu_ms_per_frame": per_frame_ms(cpu["companion_loop"] if cpu.get("companion_loop") is not None
                                                       else cpu.get("companion")),
            "simulator_cpu_ms_per_frame": per_frame_ms(cpu.get("simulator_loop"))}


def campaign(scenario: str, runs: int, workers: int = 2) -> dict:
    """One SITL campaign of ``runs`` seeds of ``configs/scenarios/<scenario>.toml`` into ``out/bench/campaign_<scenario>``."""
    from flightsim.campaign import run_campaign

    out = OUT / f"campaign_{scenario}"
    t0 = time.perf_counter()
    # no companion_config: run_campaign takes the scenario's [scenario] companion_config, else configs/companion.toml
    c = run_campaign(SCEN / f"{scenario}.toml", out, runs=runs, workers=workers, mode="sitl")
    c["_wall_s"] = time.perf_counter() - t0
    return c


def run_all(quad_runs: int = 8, fixedwing_runs: int = 8, scenarios=None, workers: int = 2) -> dict:
    """Lockstep speed and the campaigns of ``scenarios`` (default: every one in :data:`CAMPAIGNS`),
    ``quad_runs`` seeds per quad scenario and ``fixedwing_runs`` per fixed-wing one."""
    names = list(CAMPAIGNS) if scenarios is None else list(scenarios)
    unknown = [n for n in names if n not in CAMPAIGNS]
    if unknown:
        raise ValueError(f"unknown SITL campaign(s) {', '.join(unknown)}; known: {', '.join(CAMPAIGNS)}")
    for label, n in (("quad_runs", quad_runs), ("fixedwing_runs", fixedwing_runs)):
        if not (isinstance(n, int) and n >= 1):
            raise ValueError(f"{label} must be an integer >= 1, got {n!r}")
    runs = {"quad": quad_runs, "fixedwing": fixedwing_runs}
    return {"lockstep": lockstep_speed("quad_approach"),
            "campaigns": {n: campaign(n, runs[CAMPAIGNS[n][0]], workers) for n in names}}


def _config_label(path) -> str:
    """``companion_fixedwing.toml (150 m)``: the campaign's companion config and its [sectors] max_distance_m."""
    if not path:
        return "built-in defaults"
    try:
        from companion.io.config_files import load_companion_config

        return f"`{Path(path).name}` ({load_companion_config(path).sectors.max_distance_m:g} m)"
    except Exception:  # a report line must not fail the bench
        return f"`{Path(path).name}`"


def _nees_cell(nees: dict) -> str:
    """The pooled NEES of a campaign: mean (n_eff, its band ✓/✗; ±2σ coverage); an older campaign
    without n_eff: mean (band of n independent samples)."""
    lo_hi = nees.get("band") or [float("nan"), float("nan")]
    if nees.get("n_eff") is None:
        return f"{_num(nees.get('mean'))} (band {_num(lo_hi[0])}–{_num(lo_hi[1])})"
    cov = (nees.get("coverage") or {}).get("rate_2sigma")
    ok = {True: " ✓", False: " ✗"}.get(nees.get("consistent"), "")
    return (f"{_num(nees.get('mean'))} (n_eff {_num(nees['n_eff'], 0)}, band {_num(lo_hi[0])}–{_num(lo_hi[1])}{ok}; "
            f"±2σ {_pct(cov)})")


def _num(v, d: int = 2) -> str:
    return "–" if v is None else f"{v:.{d}f}"


def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.2f} %"


def _ms(v) -> str:
    return "n/a" if v is None else f"{v:.1f}"


_TARGET_COLUMNS = (("detection_in_view", "detection in view"), ("detection_near_in_view", "detection 0–10 m"),
                   ("remembered", "remembered out of view"), ("dangerous_clear", "dangerous clears"),
                   ("false_obstacle_clear_cells", "false obstacles in clear cells"),
                   ("messages_without_false_obstacle", "messages without a false obstacle"))


def _range_target_tables(res: dict) -> list[str]:
    """The range targets per scenario (pooled over the runs, after the scorer's warm-up), time to the
    first valid range per obstacle, and detection by true range in view."""
    lines = ["", "Range targets, pooled over each campaign's runs (cells after the 2 s warm-up; detection = a range "
             "within tolerance; remembered = out-of-view obstacle cells whose own point was in view within 10 s, the "
             "vehicle having moved < 20 m since; definitions in `flightsim/score/__init__.py`):", "",
             "| scenario | " + " | ".join(f"{label} ({_bound(res, key)})" for key, label in _TARGET_COLUMNS)
             + " | time to first valid range per obstacle, s (mean over runs; target ≤ 1.0) |",
             "|---|" + "---|" * (len(_TARGET_COLUMNS) + 1)]
    for name, c in res["campaigns"].items():
        a = c.get("aggregate", {})
        by_key = {t.get("key"): t for t in a.get("targets", [])}
        cells = []
        for key, _ in _TARGET_COLUMNS:
            t = by_key.get(key)
            if t is None or t.get("pooled") is None:
                cells.append("–")
            else:
                cells.append(f"{100 * t['pooled']:.1f} % {'✓' if t['met'] else '✗'} (n {t.get('n', '?')})")
        ttfv = []
        for o in a.get("obstacles", []):
            m = (o.get("time_to_first_valid_s") or {}).get("mean")
            never = o.get("runs_never_valid", 0)
            unrangeable = o.get("runs_never_rangeable", 0)
            mr = (o.get("time_to_first_valid_after_rangeable_s") or {}).get("mean")
            if m is not None or never:
                note = [f"{never} runs never"] if never else []
                if unrangeable:
                    note.append(f"never rangeable in {unrangeable}")
                if mr is not None and m is not None and abs(mr - m) >= 0.005:
                    note.append(f"{mr:.2f} once rangeable")
                ttfv.append(f"{o['name']} {'–' if m is None else f'{m:.2f}'}" + (f" ({'; '.join(note)})" if note else ""))
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {'; '.join(ttfv) or '–'} |")
    fb_rows = []
    for name, c in res["campaigns"].items():
        fb = c.get("aggregate", {}).get("false_obstacles_beside_obstacle") or {}
        if fb.get("in_view_total") or fb.get("out_of_view_total"):
            fb_rows.append(f"| {name} | {fb.get('in_view', 0)} of {fb.get('in_view_total', 0)} | "
                           f"{fb.get('out_of_view', 0)} of {fb.get('out_of_view_total', 0)} |")
    if fb_rows:
        lines += ["", "False obstacles beside an obstacle (the range of a true obstacle cell at most 2 sectors away, within "
                  "tolerance: a real obstacle claimed on a neighbouring bearing, not a phantom range), pooled:", "",
                  "| scenario | in view | out of view |", "|---|---|---|"] + fb_rows
    rg_rows, rg_def = [], {}
    for name, c in res["campaigns"].items():
        rg = c.get("aggregate", {}).get("rangeable") or {}
        if rg.get("obstacle_cells_in_view"):
            rg_def = rg_def or rg
            rem = c.get("aggregate", {}).get("remembered") or {}
            rem_txt = ("–" if not rem.get("rangeable_cells") else
                       f"{_pct(rem.get('rangeable_rate'))} ({rem['rangeable_cells']} of {rem.get('cells', 0)} rangeable)")
            rg_rows.append(f"| {name} | {_pct(rg.get('share'))} ({rg['cells']} of {rg['obstacle_cells_in_view']}) | "
                           f"{_pct(rg.get('rate'))} | {rg.get('not_rangeable_within_tolerance', 0)} | {rem_txt} |")
    if rg_rows:
        lines += ["", "The single camera's ceiling (diagnostic, `[score] rangeable_*`): the in-view obstacle cells whose point "
                  f"the camera saw within {rg_def.get('window_s') or 0:g} s from a place with ≥ {rg_def.get('parallax_deg') or 0:g}° "
                  f"parallax or ≥ {100 * (rg_def.get('scale') or 0):g} % change of distance — the only cells any monocular "
                  "method can range (geometry only) — and the detection within tolerance among them; out of view, the remembered "
                  "cells whose point was rangeable when last in view, and the share of them within tolerance; pooled:", "",
                  "| scenario | rangeable of in-view obstacle cells | detection of the rangeable | within tolerance among the others (cells) "
                  "| remembered within tolerance, of the rangeable |",
                  "|---|---|---|---|---|"] + rg_rows
    bins = None
    rows = []
    for name, c in res["campaigns"].items():
        det = (c.get("aggregate", {}).get("detection_by_range") or {}).get("in_view") or []
        if not det:
            continue
        bins = bins or [r["bin"] for r in det]
        rows.append(f"| {name} | " + " | ".join(
            "–" if not r.get("obstacle_cells") else f"{_pct(r.get('valid_rate'))} / {_pct(r.get('unknown_rate'))} ({r['obstacle_cells']})"
            for r in det) + " |")
    if bins:
        lines += ["", "Detection by true range, in view: a range within tolerance / unknown (obstacle cells), pooled:", "",
                  "| scenario | " + " | ".join(bins) + " |", "|---|" + "---|" * len(bins)] + rows
    return lines


def _bound(res: dict, key: str) -> str:
    for c in res["campaigns"].values():
        for t in c.get("aggregate", {}).get("targets", []):
            if t.get("key") == key and "threshold" in t:
                return f"{t['op'].replace('>=', '≥').replace('<=', '≤')} {100 * t['threshold']:g} %"
    return "–"


def markdown(res: dict) -> str:
    ls = res["lockstep"]
    rtf = ls["realtime_factor"]
    lines = [
        "### Lockstep speed",
        "",
        f"`flightsim sitl configs/scenarios/{ls['scenario']}.toml` (lockstep, 320×240, companion as a separate process "
        f"over UDP and the frame transport): {ls['duration_s']:g} s of flight, {ls['frames']} frames in {ls['wall_s']:.1f} s "
        f"→ **{rtf:.2f}× real time** ({ls['wall_with_startup_s']:.1f} s with start-up); the companion works "
        f"{_ms(ls.get('companion_ms_per_round'))} ms per round (wall); CPU per frame: companion "
        f"{_ms(ls.get('companion_cpu_ms_per_frame'))} ms, simulator {_ms(ls.get('simulator_cpu_ms_per_frame'))} ms "
        f"(the simulator renders the next frame while the companion works, so the slower of the two sets the pace; "
        f"10× real time at 30 frames/s leaves 3.3 ms per frame for each). "
        f"Target ≥ 10×: {'✓' if rtf >= 10 else '✗'}.",
        "",
        "### Campaigns (SITL, scored against truth)",
        "",
        "`flightsim campaign configs/scenarios/X.toml --runs N --workers 2 --mode sitl --out out/bench/campaign_X` "
        "(plots and index.md in `out/bench/campaign_X/report/`). Pooled over the runs (N seeds from the scenario's own); "
        "cell definitions in `flightsim/score/__init__.py`. What each scenario flies (the hard flights hover, turn in "
        "place and come close, where DESIGN.md §6–§7 say avoidance needs ranges most and a single camera gains least):",
        "",
    ]
    for name in res["campaigns"]:
        what = CAMPAIGNS.get(name, ("", ""))[1]
        lines.append(f"- `{name}`: {what}." if what else f"- `{name}`.")
    lines += [
        "",
        "Detection: a range reported in an obstacle cell; unknown: no data (UINT16_MAX) there, which ArduPilot treats "
        "as no constraint and PX4 as a direction it refuses to move into.",
        "",
        "| scenario | companion config (max_distance) | runs ok | detection | unknown in obstacle cells | valid range | too near | false obstacles in clear cells | messages with no false obstacle (target) | dangerous clears (target) | obstacle cells | forward estimate mean abs error | latency p50 / p99 ms | NEES (pooled n_eff, its band; truth within ±2σ) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, c in res["campaigns"].items():
        a = c.get("aggregate", {})
        p = a.get("pooled_rates", {})
        t_nf = next((t for t in a.get("targets", []) if "false" in t["name"]), None)
        t_dc = next((t for t in a.get("targets", []) if "dangerous" in t["name"]), None)

        def tcell(t):
            if t is None or t.get("pooled") is None:
                return "–"
            bound = f" ({t['op'].replace('>=', '≥').replace('<=', '≤')} {100 * t['threshold']:g} %)" if "threshold" in t and "op" in t else ""
            return f"{100 * t['pooled']:.2f} %{bound} {'✓' if t['met'] else '✗'}"

        cells = a.get("cells", {})
        unknown = cells.get("unknown_in_obstacle_cells") / cells["obstacle"] if cells.get("obstacle") and "unknown_in_obstacle_cells" in cells else None

        err = a.get("range_error", {}).get("estimate_forward", [])
        fe = "; ".join(f"{b['bin']}: {b['mae_m']:.2f} m ({b['mae_pct']:.1f} %)" for b in err
                       if isinstance(b, dict) and b.get("n")) or "–"
        lat = a.get("latency", {})
        nees = a.get("nees", {})
        lines.append(
            f"| {name} | {_config_label(c.get('companion_config'))} | {a.get('runs_ok', '?')}/{a.get('runs', '?')} | {_pct(p.get('detection'))} | {_pct(unknown)} | {_pct(p.get('valid_range'))} | "
            f"{_pct(p.get('too_near'))} | {_pct(p.get('false_obstacle_clear_cells'))} | {tcell(t_nf)} | {tcell(t_dc)} | "
            f"{t_dc['n'] if t_dc else '–'} | {fe} | "
            f"{_num(lat.get('p50_ms'), 0)} / {_num(lat.get('p99_ms'), 0)} | "
            f"{_nees_cell(nees)} |")
    lines += _range_target_tables(res)
    for name, c in res["campaigns"].items():
        t_dc = next((t for t in c.get("aggregate", {}).get("targets", []) if "dangerous" in t["name"]), None)
        if t_dc is not None and not t_dc.get("n"):
            lines += ["", f"{name}: no obstacle came within the companion's max_distance ({_config_label(c.get('companion_config'))}) "
                      "of the flight path, so detection and the dangerous-clear target are not exercised on this route."]
    return "\n".join(lines)


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m bench.sitl_bench",
                                 description="Lockstep SITL speed and the SITL campaigns of make bench (fewer seeds or scenarios for a quick look).")
    ap.add_argument("--runs", type=int, default=8, help="seeds per quad scenario (default 8)")
    ap.add_argument("--fixedwing-runs", type=int, default=None, help="seeds per fixed-wing scenario (default: --runs)")
    ap.add_argument("--scenarios", default=None, help=f"comma-separated subset of: {', '.join(CAMPAIGNS)}")
    ap.add_argument("--workers", type=int, default=2, help="worker processes per campaign (default 2)")
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.scenarios.split(",") if n.strip()] if args.scenarios else None
    r = run_all(args.runs, args.fixedwing_runs or args.runs, scenarios=names, workers=args.workers)
    print(json.dumps(r["lockstep"], indent=2))
    print(markdown(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
