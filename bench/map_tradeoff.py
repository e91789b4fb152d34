"""The local obstacle map's publishing settings, measured in lockstep SITL (docs/derivations/obstacle_map.md).

What each setting of ``configs/companion.toml`` buys and costs, on the flights where it matters
(a wall hover past a thin mast, a slalom between poles, a corner round a building):

* ``[map] support_radius_rel`` (shipped 0.15) — the lone-point test's neighbourhood grows with
  distance, so a wall ranged from far away (corners a metre or more apart) is published from memory;
* ``[map] support_column_radius_m`` (shipped 0.3) — points within this horizontally and
  ``support_column_half_height_m`` vertically support each other too: a thin mast's corners lie one
  above another, farther apart than the sphere; 0 leaves only the sphere;
* ``[map] max_entry_nis_ratio`` (shipped 10) — a landmark enters the map only when its filter's mean
  NIS is within this factor of the frame's median: occlusion-edge mismatches behind a thin mast,
  which the wider neighbourhood would otherwise let through in clusters, stay out;
* ``[sectors] remembered_spread_k`` (shipped 1) — a remembered point is spread over ± k·σ_t of
  bearing: 2 covers more of its bearing uncertainty and claims more clear sectors beside thin
  obstacles and building edges; 0 places each point at its estimated bearing only;
* ``[sectors] remembered_drop_spread_deg`` (shipped 90 = off) — withhold remembered points whose
  bearing became too uncertain instead of spreading them;
* ``[sectors] infer_narrow_gap_m`` (shipped 4) — an unknown gap between two obstacle sectors whose
  points lie at most this far apart is filled along the line between them (a wall beside the vehicle
  whose sparse corners left sectors empty); 0 leaves only the same-range rule.

Each variant is the shipped configuration with one key changed; figures are the scorer's
(:mod:`flightsim.score`), pooled over the seeds.
"""

from __future__ import annotations

import json
import re
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "configs" / "scenarios"
BASE_CONFIG = ROOT / "configs" / "companion.toml"

SCENARIOS = ("quad_wall_hover", "quad_slalom", "quad_corner")
SEEDS = (1, 2)
#: variant name → (TOML table, key, value); None = the configuration as shipped.
VARIANTS: dict[str, tuple[str, str, str] | None] = {
    "as shipped": None,
    "support_radius_rel = 0": ("map", "support_radius_rel", "0.0"),
    "support_column_radius_m = 0": ("map", "support_column_radius_m", "0.0"),
    "max_entry_nis_ratio = 0": ("map", "max_entry_nis_ratio", "0.0"),
    "remembered_spread_k = 0": ("sectors", "remembered_spread_k", "0.0"),
    "remembered_spread_k = 2": ("sectors", "remembered_spread_k", "2.0"),
    "remembered_drop_spread_deg = 5": ("sectors", "remembered_drop_spread_deg", "5.0"),
    "infer_narrow_gap_m = 0": ("sectors", "infer_narrow_gap_m", "0.0"),
}


def variant_text(base: str, change: tuple[str, str, str] | None) -> str:
    """``base`` TOML text with ``key = value`` set in ``[table]`` (the key must exist there)."""
    if change is None:
        return base
    table, key, value = change
    start = base.index(f"\n[{table}]\n")
    end = base.find("\n[", start + 1)
    end = len(base) if end < 0 else end
    section, n = re.subn(rf"(?m)^{re.escape(key)}\s*=\s*[^#\n]*", f"{key} = {value} ", base[start:end], count=1)
    if n != 1:
        raise KeyError(f"[{table}] {key} not found in {BASE_CONFIG}")
    return base[:start] + section + base[end:]


def _one(args) -> dict:
    scenario, seed, name, text = args
    from flightsim.sitl import run_sitl

    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "companion.toml"
        cfg.write_text(text, encoding="utf-8")
        run_sitl(SCEN / f"{scenario}.toml", Path(tmp) / "run", seed=seed, companion_config=cfg)
        s = json.loads((Path(tmp) / "run" / "score.json").read_text(encoding="utf-8"))
    t = {x["key"]: x for x in s["targets"]}
    return {"scenario": scenario, "seed": seed, "variant": name,
            "remembered": (t["remembered"]["num"], t["remembered"]["n"]),
            "false_obstacle": (t["false_obstacle_clear_cells"]["num"], t["false_obstacle_clear_cells"]["n"]),
            "messages_ok": (t["messages_without_false_obstacle"]["num"], t["messages_without_false_obstacle"]["n"]),
            "detection_in_view": (t["detection_in_view"]["num"], t["detection_in_view"]["n"])}


def run(seeds=SEEDS, workers: int = 2, progress=None) -> dict:
    base = BASE_CONFIG.read_text(encoding="utf-8")
    jobs = [(sc, seed, name, variant_text(base, ch)) for sc in SCENARIOS for name, ch in VARIANTS.items() for seed in seeds]
    rows = []
    with ProcessPoolExecutor(max_workers=workers) as ex:
        for r in ex.map(_one, jobs):
            rows.append(r)
            if progress:
                progress(1)
    pooled: dict = {}
    for r in rows:
        p = pooled.setdefault((r["scenario"], r["variant"]), {k: [0, 0] for k in ("remembered", "false_obstacle", "messages_ok", "detection_in_view")})
        for k in p:
            p[k][0] += r[k][0]
            p[k][1] += r[k][1]
    return {"seeds": list(seeds), "rows": rows,
            "pooled": [{"scenario": sc, "variant": v, **{k: tuple(x) for k, x in d.items()}} for (sc, v), d in pooled.items()]}


def _pc(num_n) -> str:
    num, n = num_n
    return "–" if not n else f"{100.0 * num / n:.1f} % ({num}/{n})"


def markdown(res: dict) -> str:
    seeds = ", ".join(str(s) for s in res["seeds"])
    L = [f"Command: `python -m bench map_tradeoff` (lockstep SITL, seeds {seeds} per scenario, "
         "each variant = configs/companion.toml with one key changed; scorer cells after the 2 s warm-up).", "",
         "| scenario | variant | remembered within tolerance | false obstacles, share of scored clear cells | messages without a false obstacle | detection in view |",
         "|---|---|---|---|---|---|"]
    for p in res["pooled"]:
        L.append(f"| {p['scenario']} | {p['variant']} | {_pc(p['remembered'])} | {_pc(p['false_obstacle'])} | "
                 f"{_pc(p['messages_ok'])} | {_pc(p['detection_in_view'])} |")
    L += ["", "Out of view only claims are scored, so every remembered range in a clear cell counts as a false obstacle: "
          "on these flights they are mostly correctly ranged thin obstacles and building edges claimed one or two sectors "
          "beside their true bearing (see 'false obstacles beside an obstacle' in the SITL section), and, without the NIS "
          "gate, occlusion-edge mismatches behind the mast."]
    return "\n".join(L)


if __name__ == "__main__":
    print(markdown(run()))
