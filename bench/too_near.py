"""Where "too near" comes from: a breakdown of the too-near cells of finished SITL campaigns.

A cell is *too near* when the published range r lies below the true distance T by more than the
tolerance (``flightsim.score``: obstacle cell, ``T − r > max(2 m, 20 % T)``).  The published range
is conservative, r = d − kσ (``[sectors] sigma_k``), so a too-near cell has one of three causes:

* **beside**: r matches, within tolerance, the true distance of an obstacle cell at most
  ``beside_sectors`` sectors away in the same message — a real obstacle (a pole, a building edge)
  published on a neighbouring bearing over a farther background;
* **offset** (forward sector only, where DISTANCE_SENSOR carries the estimate d and σ): the estimate
  itself is within tolerance and only the k·σ offset takes r out of it — with σ/d up to
  ``converged_rel_sigma`` (0.1), 2σ alone is the whole 20 % tolerance;
* **short**: the rest — an estimate short of the truth (an occlusion-edge track whose range lies
  between a near edge and the far surface behind it, a point spilled from a nearer obstacle that
  is not within tolerance of its neighbour's truth either).

For the forward sector it also republishes the recorded estimate and σ with other k, to show what
k trades: too near against "beyond the truth" (r > T, the unsafe side) and over-range (r − T > tol).

    python -m bench.too_near out/bench/campaign_quad_approach out/bench/campaign_quad_slalom …

Reads each run's ``score_series.npz`` (written by ``flightsim score``, ``sitl`` and ``campaign``);
nothing is flown.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.report import print_campaign_readings
from flightsim.score.config import REP_RANGE, ScoreConfig
from flightsim.score.evaluation import range_errors
from flightsim.score.summary import matches_neighbour

#: k values the forward sector is republished with
K_VALUES = (2.0, 1.5, 1.0)


def _runs(campaign: Path) -> list[Path]:
    runs = sorted(campaign.glob("runs/*/score_series.npz"))
    if not runs and (campaign / "score_series.npz").is_file():  # a single run's directory
        runs = [campaign / "score_series.npz"]
    return runs


def cell_breakdown(z, cfg: ScoreConfig) -> dict[str, int]:
    """Counts of one run's scored obstacle cells with a range (after the warm-up): too near, and of
    those beside an obstacle; split in view / out of view."""
    r = np.asarray(z["od_cm"], float) / 100.0
    T = np.asarray(z["od_truth"], float)
    mx = np.asarray(z["od_max_m"], float)[:, None]
    scored = (np.asarray(z["od_scored"], bool) & ~np.asarray(z["od_warmup"], bool))[:, None]
    with np.errstate(invalid="ignore"):
        obstacle = scored & np.isfinite(T) & (T <= mx)
        rng = obstacle & (np.asarray(z["od_rep"]) == REP_RANGE)
        near = rng & range_errors(T, r, cfg)[0]
    beside = matches_neighbour(r, np.where(obstacle, T, np.nan), cfg.beside_sectors, cfg) & near
    iv = np.asarray(z["od_in_view"], bool)
    out = {}
    for name, sel in (("in_view", iv), ("out_of_view", ~iv)):
        out[f"ranges_{name}"] = int((rng & sel).sum())
        out[f"too_near_{name}"] = int((near & sel).sum())
        out[f"beside_{name}"] = int((beside & sel).sum())
    return out


def forward_samples(z, cfg: ScoreConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The forward sector's (estimate, σ, truth at arrival) where a range was published on an obstacle,
    after the warm-up (as the score's forward NEES)."""
    d = np.asarray(z["ds_estimate_m"], float)
    s = np.asarray(z["ds_sigma_m"], float)
    T = np.asarray(z["ds_truth_arrival"], float)
    mx = np.asarray(z["ds_max_m"], float)
    with np.errstate(invalid="ignore"):
        ok = (np.asarray(z["ds_state"]) == REP_RANGE) & np.isfinite(d) & np.isfinite(s) & (s >= 0) & np.isfinite(T) & (T <= mx)
        ok &= np.asarray(z["ds_t"], float) - float(z["t0"]) >= cfg.warmup_s - 1e-9
    return d[ok], s[ok], T[ok]


def forward_table(d: np.ndarray, s: np.ndarray, T: np.ndarray, k_pub: float, cfg: ScoreConfig) -> dict:
    """The forward sector republished as r = max(d − kσ, 0) for each k in :data:`K_VALUES`, and its
    too-near cells at the published ``k_pub`` split into offset (estimate within tolerance) and short."""
    tol = cfg.tolerance(T)
    n = len(T)
    rows = {}
    for k in K_VALUES:
        r = np.maximum(d - k * s, 0.0)
        rows[f"{k:g}"] = {"too_near": int(np.sum(T - r > tol)), "beyond_truth": int(np.sum(r > T)), "over_range": int(np.sum(r - T > tol))}
    r = np.maximum(d - k_pub * s, 0.0)
    near = T - r > tol
    offset = near & (np.abs(d - T) <= tol)
    rel = s[near] / np.maximum(d[near], 1e-9)
    return {"n": n, "k_published": k_pub, "too_near": int(near.sum()), "offset": int(offset.sum()), "short": int((near & ~offset).sum()),
            "median_rel_sigma_too_near": float(np.median(rel)) if rel.size else None, "republished": rows}


def analyse(campaign: Path, k_pub: float = 2.0, cfg: ScoreConfig | None = None) -> dict:
    """Pooled breakdown of one campaign directory (or one run's directory)."""
    cfg = cfg or ScoreConfig()
    runs = _runs(campaign)
    if not runs:
        raise FileNotFoundError(f"{campaign}: no runs/*/score_series.npz (nor score_series.npz) there")
    cells: dict[str, int] = {}
    D, S, TT = [], [], []
    for p in runs:
        with np.load(p) as z:
            for key, v in cell_breakdown(z, cfg).items():
                cells[key] = cells.get(key, 0) + v
            d, s, T = forward_samples(z, cfg)
        D.append(d), S.append(s), TT.append(T)
    fwd = forward_table(np.concatenate(D), np.concatenate(S), np.concatenate(TT), k_pub, cfg)
    name = campaign.name.removeprefix("campaign_")
    return {"campaign": name, "runs": len(runs), "cells": cells, "forward": fwd}


def _pct(a: int, b: int) -> str:
    return f"{100.0 * a / b:.1f} %" if b else "–"


def markdown(results: list[dict]) -> str:
    """Two tables: the too-near cells by cause, and the forward sector republished with other k."""
    lines = ["| scenario | ranges on obstacles (in view / out) | too near in view | of which beside an obstacle | too near out of view "
             "| of which beside an obstacle | forward too near | of which offset only (estimate within tolerance) | forward σ/d when too near (median) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        c, f = r["cells"], r["forward"]
        med = f"{f['median_rel_sigma_too_near']:.3f}" if f["median_rel_sigma_too_near"] is not None else "–"
        lines.append(f"| {r['campaign']} | {c['ranges_in_view']} / {c['ranges_out_of_view']} "
                     f"| {_pct(c['too_near_in_view'], c['ranges_in_view'])} | {_pct(c['beside_in_view'], c['too_near_in_view'])} "
                     f"| {_pct(c['too_near_out_of_view'], c['ranges_out_of_view'])} | {_pct(c['beside_out_of_view'], c['too_near_out_of_view'])} "
                     f"| {_pct(f['too_near'], f['n'])} (n {f['n']}) | {_pct(f['offset'], f['too_near'])} | {med} |")
    lines += ["", "Forward sector republished from its recorded estimate and σ, r = d − k·σ (share of its published ranges):", "",
              "| scenario | " + " | ".join(f"k = {k:g}: too near / beyond the truth / over-range" for k in K_VALUES) + " |",
              "|---|" + "---|" * len(K_VALUES)]
    for r in results:
        f = r["forward"]
        cols = []
        for k in K_VALUES:
            row = f["republished"][f"{k:g}"]
            cols.append(f"{_pct(row['too_near'], f['n'])} / {_pct(row['beyond_truth'], f['n'])} / {_pct(row['over_range'], f['n'])}")
        lines.append(f"| {r['campaign']} | " + " | ".join(cols) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.too_near", description=__doc__.split("\n")[0],
                                 epilog="Reads finished campaigns (flightsim campaign … --out DIR); flies nothing.")
    ap.add_argument("campaigns", nargs="+", help="campaign directories (with runs/*/score_series.npz) or single-run directories")
    ap.add_argument("--sigma-k", type=float, default=2.0,
                    help="the k the campaigns were published with ([sectors] sigma_k; default 2)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of the tables")
    args = ap.parse_args(argv)
    return print_campaign_readings("bench.too_near", lambda c: analyse(c, args.sigma_k), args.campaigns, args.json, markdown)


if __name__ == "__main__":
    sys.exit(main())
