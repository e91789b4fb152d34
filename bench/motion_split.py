"""Detection in view by what the vehicle was doing: turning in place, hovering, or moving.

Issue 11 asks for ranges "hovering and turning in place included"; a campaign's pooled detection
hides which of the three costs it.  This splits the in-view obstacle cells of finished SITL
campaigns (after the warm-up; ``flightsim.score``) by the vehicle's motion in the cell's truth
frame, and by true range:

* **turning**: heading rate above ``--turn-dps`` (default 10°/s), whatever the speed;
* **hovering**: horizontal speed below ``--hover-mps`` (default 0.5 m/s), not turning;
* **moving**: the rest.

For each: obstacle cells, the share with a range within tolerance (detection), unknown, too near,
too far, "clear", and the share the single camera could have ranged at all (``od_rangeable``, the
scorer's ceiling; absent from series written before it).  Speed and heading rate are the truth's
(``truth.npz`` ``p_ned`` and ``rpy``), differentiated over the frames.  A second table splits the
unknown cells by why the companion says each was unknown (``od_why``, from its sector log;
docs/derivations/sectors.md, "Why a sector is unknown"), when the series carry it.

    python -m bench.motion_split out/bench/campaign_quad_slalom out/bench/campaign_quad_yaw_spin …

Reads each run's ``score_series.npz`` and ``truth.npz``; nothing is flown.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.report import print_campaign_readings
from flightsim.score.config import REP_CLEAR, REP_RANGE, REP_UNKNOWN, TRUTH_OBSTACLE, ScoreConfig
from flightsim.score.evaluation import range_errors
from flightsim.score.inputs import SectorTruth
from flightsim.score.markdown import REASON_COLUMNS
from flightsim.score.summary import reason_counts

MOTIONS = ("turning", "hovering", "moving")
KINDS = ("valid", "unknown", "too_near", "too_far", "clear")


def motion_of(truth: SectorTruth, turn_dps: float = 10.0, hover_mps: float = 0.5) -> np.ndarray:
    """(F,) index into :data:`MOTIONS` of each truth frame: turning (|heading rate| > ``turn_dps``),
    hovering (horizontal speed < ``hover_mps``, not turning), else moving."""
    t = np.asarray(truth.t_s, float)
    if len(t) < 2:
        return np.full(len(t), MOTIONS.index("hovering"), np.int64)
    v = np.gradient(np.asarray(truth.p_ned, float)[:, :2], t, axis=0)
    rate = np.degrees(np.gradient(np.unwrap(np.asarray(truth.yaw, float)), t))
    out = np.full(len(t), MOTIONS.index("moving"), np.int64)
    out[np.hypot(v[:, 0], v[:, 1]) < hover_mps] = MOTIONS.index("hovering")
    out[np.abs(rate) > turn_dps] = MOTIONS.index("turning")
    return out


def split_cells(series: dict, truth: SectorTruth, cfg: ScoreConfig = ScoreConfig(), turn_dps: float = 10.0,
                hover_mps: float = 0.5) -> dict:
    """Counts of one run's in-view obstacle cells after the warm-up, by motion × true-range bin
    (``cfg.detection_bins_m``) × outcome (:data:`KINDS`), and the rangeable ones."""
    T = np.asarray(series["od_truth"], float)
    rep = np.asarray(series["od_rep"])
    r = np.where(rep == REP_RANGE, np.asarray(series["od_cm"], float) / 100.0, np.nan)
    cells = (np.asarray(series["od_tcls"]) == TRUTH_OBSTACLE) & np.asarray(series["od_in_view"], bool)
    cells &= (np.asarray(series["od_scored"], bool) & ~np.asarray(series["od_warmup"], bool))[:, None]
    frame = truth.frame_at(np.asarray(series["od_t"], float), cfg.truth_max_age_s)
    cells &= (frame >= 0)[:, None]
    motion = np.broadcast_to(motion_of(truth, turn_dps, hover_mps)[np.maximum(frame, 0)][:, None], T.shape)
    rangeable = np.asarray(series["od_rangeable"], bool) if "od_rangeable" in series else None
    why = np.asarray(series["od_why"]) if "od_why" in series else None
    near, far = range_errors(T, r, cfg)  # the scorer's own test (flightsim.score.evaluation)
    rng = rep == REP_RANGE
    kind = {"valid": rng & ~near & ~far, "unknown": rep == REP_UNKNOWN, "too_near": rng & near, "too_far": rng & far,
            "clear": rep == REP_CLEAR}
    edges = list(cfg.detection_bins_m) + [np.inf]
    out: dict = {}
    for mi, m in enumerate(MOTIONS):
        for b in range(len(edges) - 1):
            sel = cells & (motion == mi) & (T >= edges[b]) & (T < edges[b + 1])
            row = {"cells": int(sel.sum())} | {k: int((sel & kind[k]).sum()) for k in KINDS}
            row["rangeable"] = None if rangeable is None else int((sel & rangeable).sum())
            if why is not None:  # the unknown cells by the companion's reason (−1: no sector-log line)
                row["why"] = reason_counts(sel & kind["unknown"], why)
            out[f"{m}/{b}"] = row
    return out


def _bin_label(cfg: ScoreConfig, b: int) -> str:
    e = list(cfg.detection_bins_m)
    return f"{e[b]:g}–{e[b + 1]:g} m" if b + 1 < len(e) else f"{e[b]:g}+ m"


def analyse(campaign: Path, cfg: ScoreConfig = ScoreConfig(), turn_dps: float = 10.0, hover_mps: float = 0.5) -> dict:
    """:func:`split_cells` pooled over a campaign's runs (``runs/*/``) or one run's directory."""
    from flightsim.score.files import load_series, read_truth_npz

    runs = sorted(p.parent for p in campaign.glob("runs/*/score_series.npz"))
    if not runs and (campaign / "score_series.npz").is_file():
        runs = [campaign]
    if not runs:
        raise FileNotFoundError(f"{campaign}: no runs/*/score_series.npz (a finished campaign) nor score_series.npz")
    pooled: dict = {}
    for run in runs:
        for key, row in split_cells(load_series(run / "score_series.npz"), read_truth_npz(run / "truth.npz"), cfg,
                                    turn_dps, hover_mps).items():
            acc = pooled.setdefault(key, {k: 0 for k in row if k != "why"} | {"why": {} if "why" in row else None})
            for k, v in row.items():
                if k != "why":
                    acc[k] = None if v is None or acc[k] is None else acc[k] + v
            # the reasons pooled only while every run so far had them (a split of some runs would mislead)
            acc["why"] = None if acc["why"] is None or "why" not in row else {
                name: acc["why"].get(name, 0) + c for name, c in row["why"].items()}
    return {"campaign": str(campaign), "runs": len(runs), "turn_dps": turn_dps, "hover_mps": hover_mps, "cells": pooled}


def _pc(num, den) -> str:
    return "–" if num is None or not den else f"{100.0 * num / den:.0f} %"


def markdown(results: list[dict], cfg: ScoreConfig = ScoreConfig()) -> str:
    L = []
    for res in results:
        L += [f"{res['campaign']} ({res['runs']} runs; turning: heading rate > {res['turn_dps']:g}°/s; hovering: "
              f"< {res['hover_mps']:g} m/s, not turning):", "",
              "| motion | true range | obstacle cells in view | detection | unknown | too near | too far | clear | rangeable |",
              "|---|---|---|---|---|---|---|---|---|"]
        for key, row in res["cells"].items():
            if not row["cells"]:
                continue
            m, b = key.split("/")
            n = row["cells"]
            L.append(f"| {m} | {_bin_label(cfg, int(b))} | {n} | " + " | ".join(_pc(row[k], n) for k in KINDS)
                     + f" | {_pc(row['rangeable'], n)} |")
        L.append("")
        L += _reasons_table(res, cfg)
    return "\n".join(L)


def _reasons_table(res: dict, cfg: ScoreConfig) -> list[str]:
    """The unknown cells of each motion × range row by the companion's reason (only reasons that occur)."""
    rows = [(key, row) for key, row in res["cells"].items() if row.get("why") and row["unknown"]]
    names = [n for n in REASON_COLUMNS if any(r["why"].get(n) for _, r in rows)]
    if not rows or not names:
        return []
    L = ["Unknown cells by the companion's reason (its sector log; docs/derivations/sectors.md, \"Why a sector is "
         "unknown\"):", "", "| motion | true range | unknown cells | " + " | ".join(n.replace("_", " ") for n in names) + " |",
         "|---|---|---|" + "---|" * len(names)]
    for key, row in rows:
        m, b = key.split("/")
        u = row["unknown"]
        L.append(f"| {m} | {_bin_label(cfg, int(b))} | {u} | " + " | ".join(_pc(row["why"].get(n, 0), u) for n in names) + " |")
    return L + [""]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.motion_split", description=__doc__.split("\n")[0],
                                 epilog="Reads finished campaigns (flightsim campaign … --out DIR); flies nothing.")
    ap.add_argument("campaigns", nargs="+", help="campaign directories (with runs/*/score_series.npz and truth.npz) or single-run directories")
    ap.add_argument("--turn-dps", type=float, default=10.0, help="heading rate above which a frame counts as turning, °/s (default 10)")
    ap.add_argument("--hover-mps", type=float, default=0.5, help="horizontal speed below which a frame counts as hovering, m/s (default 0.5)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of the tables")
    args = ap.parse_args(argv)
    if not (np.isfinite(args.turn_dps) and args.turn_dps > 0 and np.isfinite(args.hover_mps) and args.hover_mps > 0):
        ap.error("--turn-dps and --hover-mps must be positive numbers")
    return print_campaign_readings("bench.motion_split", lambda c: analyse(c, turn_dps=args.turn_dps, hover_mps=args.hover_mps),
                                   args.campaigns, args.json, markdown)


if __name__ == "__main__":
    sys.exit(main())
