"""SITL benchmarks (issue 5): lockstep speed and Monte Carlo campaigns scored against truth.

* lockstep ``flightsim sitl`` of ``quad_approach`` (320×240): wall time, real-time factor (target
  ≥ 10×) and the companion's work per lockstep round;
* campaigns (:func:`flightsim.campaign.run_campaign`, SITL mode) of ``quad_approach`` and
  ``fixedwing_pass``: pooled detection, false-obstacle and dangerous-clear rates against the issue's
  targets, range error by bin, latency and NEES.  Reports (plots + index.md) go to ``out/bench/``.
  Each campaign runs the companion configuration its scenario names (``[scenario]
  companion_config``: ``fixedwing_pass`` flies ``configs/companion_fixedwing.toml``, max_distance
  150 m), else ``configs/companion.toml``.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCEN = ROOT / "configs" / "scenarios"
OUT = ROOT / "out" / "bench"


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
            "companion_cpu_ms_per_frame": per_frame_ms(cpu.get("companion")),
            "simulator_cpu_ms_per_frame": per_frame_ms(cpu.get("simulator_loop"))}


def campaign(scenario: str, runs: int, workers: int = 2) -> dict:
    from flightsim.campaign import run_campaign

    out = OUT / f"campaign_{scenario}"
    t0 = time.perf_counter()
    # no companion_config: run_campaign takes the scenario's [scenario] companion_config, else configs/companion.toml
    c = run_campaign(SCEN / f"{scenario}.toml", out, runs=runs, workers=workers, mode="sitl")
    c["_wall_s"] = time.perf_counter() - t0
    return c


def run_all(quad_runs: int = 8, fixedwing_runs: int = 4) -> dict:
    return {"lockstep": lockstep_speed("quad_approach"),
            "campaigns": {"quad_approach": campaign("quad_approach", quad_runs),
                          "fixedwing_pass": campaign("fixedwing_pass", fixedwing_runs)}}


def _config_label(path) -> str:
    """``companion_fixedwing.toml (150 m)``: the campaign's companion config and its [sectors] max_distance_m."""
    if not path:
        return "built-in defaults"
    try:
        from companion.io.config_files import load_companion_config

        return f"`{Path(path).name}` ({load_companion_config(path).sectors.max_distance_m:g} m)"
    except Exception:  # a report line must not fail the bench
        return f"`{Path(path).name}`"


def _num(v, d: int = 2) -> str:
    return "–" if v is None else f"{v:.{d}f}"


def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.2f} %"


def _ms(v) -> str:
    return "n/a" if v is None else f"{v:.1f}"


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
        "(plots and index.md in `out/bench/campaign_X/report/`). Pooled over the runs; cell definitions in `flightsim/score.py`.",
        "",
        "| scenario | companion config (max_distance) | runs ok | detection | valid range | too near | false obstacles in clear cells | messages with no false obstacle (≥ 95 %) | dangerous clears (≤ 1 %) | obstacle cells | forward estimate mean abs error | latency p50 / p99 ms | NEES |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, c in res["campaigns"].items():
        a = c.get("aggregate", {})
        p = a.get("pooled_rates", {})
        t_nf = next((t for t in a.get("targets", []) if "false" in t["name"]), None)
        t_dc = next((t for t in a.get("targets", []) if "dangerous" in t["name"]), None)

        def tcell(t):
            if t is None or t.get("pooled") is None:
                return "–"
            return f"{100 * t['pooled']:.2f} % {'✓' if t['met'] else '✗'}"

        err = a.get("range_error", {}).get("estimate_forward", [])
        fe = "; ".join(f"{b['bin']}: {b['mae_m']:.2f} m ({b['mae_pct']:.1f} %)" for b in err
                       if isinstance(b, dict) and b.get("n")) or "–"
        lat = a.get("latency", {})
        nees = a.get("nees", {})
        lo_hi = nees.get("band") or [float("nan"), float("nan")]
        lines.append(
            f"| {name} | {_config_label(c.get('companion_config'))} | {a.get('runs_ok', '?')}/{a.get('runs', '?')} | {_pct(p.get('detection'))} | {_pct(p.get('valid_range'))} | "
            f"{_pct(p.get('too_near'))} | {_pct(p.get('false_obstacle_clear_cells'))} | {tcell(t_nf)} | {tcell(t_dc)} | "
            f"{t_dc['n'] if t_dc else '–'} | {fe} | "
            f"{_num(lat.get('p50_ms'), 0)} / {_num(lat.get('p99_ms'), 0)} | "
            f"{_num(nees.get('mean'))} (band {_num(lo_hi[0])}–{_num(lo_hi[1])}) |")
    for name, c in res["campaigns"].items():
        t_dc = next((t for t in c.get("aggregate", {}).get("targets", []) if "dangerous" in t["name"]), None)
        if t_dc is not None and not t_dc.get("n"):
            lines += ["", f"{name}: no obstacle came within the companion's max_distance ({_config_label(c.get('companion_config'))}) "
                      "of the flight path, so detection and the dangerous-clear target are not exercised on this route."]
    return "\n".join(lines)


if __name__ == "__main__":
    r = run_all(2, 1)
    print(json.dumps(r["lockstep"], indent=2))
    print(markdown(r))
