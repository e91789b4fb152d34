"""Before → after: the issue targets of finished SITL campaigns flown twice (two configurations or two commits).

Each pair is a campaign directory flown before a change and the same scenario flown after it
(``flightsim campaign configs/scenarios/X.toml --runs 8 --workers 2 --mode sitl --out DIR
[--companion-config C.toml]``). For each pair this prints one table row, pooled over the runs after
the scorer's warm-up, from their ``campaign.json``: detection in view, within 0–10 m, remembered out
of view, too near and over-range (shares of obstacle cells), false obstacles in clear cells, messages
without a false obstacle, dangerous clears, the forward NEES with its band for the effective sample
size and the share of samples within ±2σ; then the time to the first valid range per obstacle:

    python -m bench.campaign_diff out/bench/campaign_quad_approach NEW/campaign_quad_approach …
    python -m bench.campaign_diff --before-prefix out/bench/campaign_ --after-prefix NEW/T1_ quad_approach quad_slalom

Reads the campaigns' ``campaign.json``; nothing is flown. Exit code 2 when a campaign cannot be read.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

#: (key, column) of the target rows, in the order of the table; shares of the pooled cells
TARGETS = (("detection_in_view", "detection in view"), ("detection_near_in_view", "0–10 m"),
           ("remembered", "remembered"))
RATES = (("too_near", "too near"), ("over_range", "over-range"))
SAFETY = (("false_obstacle_clear_cells", "false obstacles in clear cells"),
          ("messages_without_false_obstacle", "messages without one"))


def figures(campaign_dir: Path) -> dict:
    """The figures of one campaign (its ``campaign.json``): label, targets, rates, NEES, first valid ranges."""
    f = Path(campaign_dir) / "campaign.json"
    if not f.is_file():
        raise FileNotFoundError(f"{campaign_dir}: no campaign.json")
    d = json.loads(f.read_text(encoding="utf-8"))
    a = d["aggregate"]
    t = {x.get("key"): x for x in a.get("targets", [])}
    out = {"label": str(d.get("scenario_name") or d.get("scenario") or Path(campaign_dir).name)}
    for key, _ in (*TARGETS, *SAFETY, ("dangerous_clear", "")):
        out[key] = (t.get(key) or {}).get("pooled")
    rates = a.get("pooled_rates") or {}
    for key, _ in RATES:
        out[key] = rates.get(key)
    ne = a.get("nees") or {}
    out["nees"] = {"mean": ne.get("mean"), "band": ne.get("band"), "consistent": ne.get("consistent"),
                   "within_2sigma": (ne.get("coverage") or {}).get("rate_2sigma")}
    out["first_valid_s"] = {o["name"]: (o.get("time_to_first_valid_s") or {}).get("mean") for o in a.get("obstacles", [])}
    return out


def _pc(v) -> str:
    from flightsim.report import _pc as pc

    return pc(v, 1)


def _nees(n: dict) -> str:
    if n.get("mean") is None:
        return "–"
    band = n.get("band") or [math.nan, math.nan]
    return f"{n['mean']:.2f} ({band[0]:.2f}–{band[1]:.2f} {'✓' if n.get('consistent') else '✗'})"


def _s(v) -> str:
    return "–" if v is None else f"{v:.2f}"


def markdown(pairs: list[tuple[dict, dict]]) -> str:
    cols = [c for _, c in (*TARGETS, *RATES, *SAFETY)] + ["dangerous clears", "forward NEES (band)", "truth within ±2σ"]
    lines = ["| scenario | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for b, a in pairs:
        cells = [f"{_pc(b[k])} → {_pc(a[k])}" for k, _ in (*TARGETS, *RATES, *SAFETY)]
        cells += [f"{_pc(b['dangerous_clear'])} → {_pc(a['dangerous_clear'])}", f"{_nees(b['nees'])} → {_nees(a['nees'])}",
                  f"{_pc(b['nees']['within_2sigma'])} → {_pc(a['nees']['within_2sigma'])}"]
        lines.append(f"| {b['label']} | " + " | ".join(cells) + " |")
    lines += ["", "Time to the first valid range per obstacle, s (mean over runs; – never):", ""]
    for b, a in pairs:
        names = list(dict.fromkeys([*b["first_valid_s"], *a["first_valid_s"]]))
        lines.append(f"- {b['label']}: " + "; ".join(
            f"{n} {_s(b['first_valid_s'].get(n))} → {_s(a['first_valid_s'].get(n))}" for n in names))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    doc = __doc__
    ap = argparse.ArgumentParser(prog="python -m bench.campaign_diff", description=doc.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=doc.split("\n\n", 1)[1])
    ap.add_argument("dirs", nargs="+", metavar="DIR",
                    help="campaign directories in pairs (before, after); with the prefixes, scenario names")
    ap.add_argument("--before-prefix", help="campaign directories before are this prefix + each scenario name")
    ap.add_argument("--after-prefix", help="campaign directories after are this prefix + each scenario name")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON instead of the table")
    args = ap.parse_args(argv)
    if (args.before_prefix is None) != (args.after_prefix is None):
        ap.error("give both --before-prefix and --after-prefix, or neither")
    if args.before_prefix is not None:
        dirs = [(args.before_prefix + s, args.after_prefix + s) for s in args.dirs]
    else:
        if len(args.dirs) % 2:
            ap.error("campaign directories come in pairs (before, after)")
        dirs = list(zip(args.dirs[0::2], args.dirs[1::2]))
    try:
        pairs = [(figures(Path(b)), figures(Path(a))) for b, a in dirs]
    except (FileNotFoundError, KeyError, ValueError) as e:
        print(f"bench.campaign_diff: {e}", file=sys.stderr)
        return 2
    print(json.dumps([{"before": b, "after": a} for b, a in pairs], indent=1) if args.json else markdown(pairs), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
