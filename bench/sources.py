"""Which mechanism the published ranges of finished SITL campaigns came from, by the companion's sector log.

Every SITL run records the companion's sector log (``sectors.jsonl``: per OBSTACLE_DISTANCE, the
source of each sector's claim — live points, live and remembered, remembered only, inferred across
sectors, inferred from points above or below the band; docs/derivations/sectors.md, "Where a claim
comes from"), and the score pools the ranges by
source into ``claims_by_source`` (``flightsim/score/summary.py``).  This prints, per campaign, the
ranges of each source in view and out of view, the share within tolerance, and where the false
obstacles and the too-near ranges came from; then the cells left unknown by why the companion says each was
unknown (``unknown_by_reason``: docs/derivations/sectors.md, "Why a sector is unknown"):

    python -m bench.sources out/bench/campaign_quad_slalom out/bench/campaign_quad_corner …

Reads each campaign's ``campaign.json`` (or a single run's ``score.json``); nothing is flown.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from flightsim.score.markdown import unknown_reason_table
from flightsim.score.summary import SOURCE_NAMES

SOURCES = (*SOURCE_NAMES[1:], "unattributed")  # the companion's sources ("none" has no ranges), then no log line


def load(path: Path, block: str = "claims_by_source") -> tuple[str, dict | None]:
    """(name, ``block``) of a campaign directory (its ``campaign.json``) or a run's (``score.json``):
    ``claims_by_source`` or ``unknown_by_reason``."""
    for name, key in (("campaign.json", "aggregate"), ("score.json", None)):
        f = path / name
        if f.is_file():
            d = json.loads(f.read_text(encoding="utf-8"))
            label = d.get("scenario_name") or d.get("scenario") or path.name
            return str(label), (d.get(key) or {}).get(block) if key else d.get(block)
    raise FileNotFoundError(f"{path}: neither campaign.json nor score.json")


def _pc(num: int, den: int) -> str:
    return "–" if den == 0 else f"{100.0 * num / den:.1f} %"


def rows(label: str, cbs: dict) -> list[str]:
    """Table rows: one per view × source with ranges."""
    out = []
    for view in ("in_view", "out_of_view"):
        for src in SOURCES:
            r = (cbs.get(view) or {}).get(src)
            if not r or not r["ranges"]:
                continue
            out.append(f"| {label} | {view.replace('_', ' ')} | {src} | {r['ranges']} | {_pc(r['valid'], r['on_obstacles'])} | "
                       f"{r['too_near']} | {r['false_obstacles']} ({r['beside_obstacle']} beside) |")
    return out


def totals(cbs: dict) -> dict[str, dict[str, int]]:
    """False obstacles and too-near ranges per source, both views together."""
    t = {s: {"false_obstacles": 0, "too_near": 0, "ranges": 0} for s in SOURCES}
    for view in ("in_view", "out_of_view"):
        for src, r in (cbs.get(view) or {}).items():
            if src in t:
                for k in t[src]:
                    t[src][k] += int(r[k])
    return t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.sources", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dirs", nargs="+", type=Path, help="campaign directories (campaign.json) or run directories (score.json)")
    ap.add_argument("--json", action="store_true", help="print the claims by source as JSON instead of the tables")
    args = ap.parse_args(argv)
    loaded, reasons = [], []
    for d in args.dirs:
        try:
            loaded.append(load(d))
            reasons.append(load(d, "unknown_by_reason"))
        except (FileNotFoundError, json.JSONDecodeError) as e:
            print(f"bench.sources: {e}", file=sys.stderr)
            return 2
    if args.json:
        print(json.dumps({label: {"claims_by_source": cbs, "unknown_by_reason": ubr}
                          for (label, cbs), (_, ubr) in zip(loaded, reasons)}, indent=2))
        return 0
    L = ["| scenario | view | source | ranges | within tolerance (of those on obstacles) | too near | false obstacles |",
         "|---|---|---|---|---|---|---|"]
    share = ["", "| scenario | false obstacles: live / mixed / remembered / inferred / vertical / unattributed | too near: the same |",
             "|---|---|---|"]
    missing = []
    for label, cbs in loaded:
        if not cbs:
            missing.append(label)
            continue
        L += rows(label, cbs)
        t = totals(cbs)
        fo, tn = sum(v["false_obstacles"] for v in t.values()), sum(v["too_near"] for v in t.values())
        share.append(f"| {label} | " + " / ".join(_pc(t[s]["false_obstacles"], fo) for s in SOURCES) + f" (of {fo}) | "
                     + " / ".join(_pc(t[s]["too_near"], tn) for s in SOURCES) + f" (of {tn}) |")
    why = unknown_reason_table(reasons)
    if why:
        share += ["", "Unknown cells by the companion's reason (shares of the unknown cells of each group):", ""] + why
    print("\n".join(L + share))
    if missing:
        print(f"\nno sector log in: {', '.join(missing)} (flown before the companion wrote one)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
