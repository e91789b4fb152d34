"""``score.md``: :func:`markdown` writes one run's score (a :func:`~flightsim.score.summary.summarize`
dict) as text — the avoidance outcome when there is one, the targets with ✓/✗ (:func:`mark`), the
cell tables in view / out of view / pooled, detection by true range, range error, NEES, latency,
obstacles, the forward DISTANCE_SENSOR, the per-sector table and the definitions.
"""

from __future__ import annotations

from flightsim.score.summary import REASON_NAMES


# ---------------------------------------------------------------------- markdown ---------------
def _f(v, fmt: str = "{:.2f}", none: str = "–") -> str:
    return none if v is None else fmt.format(v)


def remembered_rangeable_text(rem: dict) -> str:
    """The remembered cells whose point was rangeable when last in view (the single camera's ceiling)."""
    if rem.get("rangeable_cells") is None:
        return ""
    return (f"; of them rangeable when last in view {rem['rangeable_cells']}, within tolerance "
            f"{rem['rangeable_within_tolerance']} ({_pc(rem.get('rangeable_rate'))})")


def remembered_errors_text(rem: dict) -> str:
    """The remembered cells ranged beyond the tolerance: nearer (conservative) and farther (the obstacle missed
    behind a valid-looking range); older scores lack them."""
    if rem.get("over_range") is None:
        return ""
    return f", too near {rem['too_near']}, too far {rem['over_range']}"


def _k_text(cfg: dict) -> str:
    """k of the companion's conservative value as the score's config gives it: one number, or its taper
    (older scores have no taper keys)."""
    if not cfg.get("sigma_k_taper_to_m", 0.0) > 0:
        return f"{cfg['sigma_k']:g}"
    return (f"k(d) ({cfg['sigma_k']:g} to {cfg['sigma_k_taper_from_m']:g} m, {cfg['sigma_k_far']:g} from "
            f"{cfg['sigma_k_taper_to_m']:g} m)")


def _pc(v, digits: int = 1) -> str:
    return "–" if v is None else f"{100 * v:.{digits}f} %"


def mark(met) -> str:
    return "–" if met is None else ("✓" if met else "✗")


def nees_lines(ne: dict, what: str = "Against the truth at exposure") -> list[str]:
    """The NEES paragraph of a :func:`~flightsim.score.summary.nees_stats` dict (one run or pooled):
    n and n_eff, the mean against its band with n_eff (the verdict) and, for reference, the band
    of n independent samples; the ±1σ / ±2σ coverage against a normal error's."""
    band, bi = ne.get("band") or [None, None], ne.get("band_independent") or [None, None]
    conf = 100 * ne.get("confidence", 0.95)
    how = ""
    if ne.get("autocorrelation_time") is not None:
        gap = f", a gap over {ne['gap_s']:g} s starting a new one" if ne.get("gap_s") is not None else ""
        how = (f" in {ne.get('stretches')} stretch{'es' if ne.get('stretches') != 1 else ''}{gap}; autocorrelation "
               f"time {ne['autocorrelation_time']:.2f} samples (Geyer's initial monotone sequence, lags ≤ "
               f"{ne.get('autocorrelation_lags')})")
    L = [f"{what}: n = {ne['n']} samples{how}, effective n_eff = {_f(ne.get('n_eff'), '{:.1f}')}; mean "
         f"{_f(ne['mean'])}, median {_f(ne['median'])}.  {conf:g} % band of the mean with n_eff "
         f"[{_f(band[0], '{:.3f}')}, {_f(band[1], '{:.3f}')}] {mark(ne.get('consistent'))}; as if the n samples were "
         f"independent [{_f(bi[0], '{:.3f}')}, {_f(bi[1], '{:.3f}')}] {mark(ne.get('consistent_independent'))} "
         "(for reference only: consecutive samples come from one filter and are correlated).", ""]
    cov = ne.get("coverage")
    if cov:
        L += [f"Coverage: the truth lies within estimate ± σ in {_pc(cov['rate_1sigma'])} ({cov['within_1sigma']} of "
              f"{cov['n']}; a normal error with the right σ: {_pc(cov['expected_1sigma'])}) and within ± 2σ in "
              f"{_pc(cov['rate_2sigma'])} ({cov['within_2sigma']}; normal: {_pc(cov['expected_2sigma'])}).", ""]
    return L


def markdown(score: dict, title: str = "Score") -> str:
    """``score.md``: the definitions, the targets with ✓/✗ and the tables of one run."""
    s = score
    c, r = s["cells"], s["rates"]
    cfg = s["config"]
    L = [f"# {title}", ""]
    if s.get("inputs"):
        L += [f"Ranges: `{s['inputs'].get('ranges')}`  ", f"Truth: `{s['inputs'].get('truth')}`", ""]
    wu = s.get("warmup") or {"s": cfg.get("warmup_s", 0.0), "messages_excluded": 0}
    if s.get("avoidance"):
        from flightsim.outcome import outcome_markdown

        L += outcome_markdown(s["avoidance"])
    L += ["## Targets", "",
          f"Warm-up: cells of the first {wu['s']:g} s of the run are not scored ({wu['messages_excluded']} messages).  "
          + ("Truth over 360°: out-of-view claims are scored, unknown out of view is neutral." if s.get("truth_360")
             else "Truth of the sectors in view only (an older truth.npz): out-of-view claims are not scored."), "",
          "| target | value | threshold | n | met |", "|---|---|---|---|---|"]
    for t in s["targets"]:
        L.append(f"| {t['name']} | {_pc(t['value'], 2)} | {t['op']} {100 * t['threshold']:g} % | {t['n']} | {mark(t['met'])} |")
    civ, cov = s.get("cells_in_view") or {}, s.get("cells_out_of_view") or {}
    riv, rov = s.get("rates_in_view") or {}, s.get("rates_out_of_view") or {}

    def row(label, key, rkey=None, d=1):
        def one(cc, rr):
            v = f"{cc.get(key, 0)}"
            return v + (f" ({_pc(rr.get(rkey), d)})" if rkey and rr.get(rkey) is not None else "")
        return f"| {label} | {one(civ, riv)} | {one(cov, rov)} | {one(c, r)} |"

    L += ["", "## Cells", "",
          f"Scored OBSTACLE_DISTANCE messages: {s['messages']['obstacle_distance_scored']} of "
          f"{s['messages']['obstacle_distance']} ({s['messages']['without_truth']} without a truth frame, "
          f"{s['messages'].get('in_warmup', 0)} in the warm-up); "
          f"with a claim: {s['messages']['with_claims']}; first claim {_f(s['first_claim_at_s'], '{:.2f} s')} after the first frame.  "
          "Out of view only cells with a claim count (unknown there is neutral).", "",
          "| quantity | in view | out of view | all scored |", "|---|---|---|---|",
          row("obstacle cells", "obstacle"),
          row("detections (range reported)", "detections", "detection"),
          row("valid ranges (within tolerance)", "valid_ranges", "valid_range"),
          row("unknown in obstacle cells", "unknown_in_obstacle_cells", "unknown_in_obstacle_cells"),
          row("**dangerous clears**", "dangerous_clears", "dangerous_clear", 2),
          row("too near (false obstacle in an obstacle cell)", "too_near", "too_near"),
          row("over range", "over_range", "over_range"),
          row("clear cells", "clear"),
          row("false obstacles in clear cells", "false_obstacles_clear_cells", "false_obstacle_clear_cells", 2),
          row(f"ranges beyond the truth horizon ({s['truth_horizon_m']:g} m), unverifiable", "unverifiable_beyond_truth"),
          row("clear claimed in clear cells", "clear_claimed_in_clear_cells", "clear_claimed_in_clear_cells"),
          "| messages without a false obstacle / eligible | " + " | ".join(
              f"{cc.get('messages_without_false_obstacle', 0)} / {cc.get('messages_eligible_no_false', 0)} "
              f"({_pc(rr.get('messages_without_false_obstacle'))})" for cc, rr in ((civ, riv), (cov, rov), (c, r))) + " |",
          row("claims in cells of unknown truth (not scored)", "unscored_claims"),
          row("invalid values", "invalid_values"), ""]
    if cov:
        L += [f"Out of view in total: {cov.get('obstacle_cells_total', 0)} obstacle cells and {cov.get('clear_cells_total', 0)} "
              f"clear cells; unknown there (neutral): {cov.get('unknown_neutral', 0)}.", ""]
    rem = s.get("remembered")
    if rem:
        L += [f"Remembered obstacles out of view (in view within {rem['window_s']:g} s, vehicle moved < {rem['max_travel_m']:g} m): "
              f"{rem['cells']} cells, within tolerance {rem['within_tolerance']} ({_pc(rem['rate'])}), ranges {rem['ranges']}, "
              f"unknown {rem['unknown']}, dangerous clears {rem['dangerous_clears']}" + remembered_errors_text(rem)
              + remembered_rangeable_text(rem) + ".", ""]
    rg = s.get("rangeable")
    if rg and rg.get("obstacle_cells_in_view"):
        L += [f"Rangeable in view (the single camera's ceiling: the cell's point seen within {rg.get('window_s', 0):g} s from a "
              f"place with ≥ {rg.get('parallax_deg', 0):g}° parallax or ≥ {100 * (rg.get('scale') or 0):g} % change of distance; "
              f"geometry only, a diagnostic): {rg['cells']} of {rg['obstacle_cells_in_view']} in-view obstacle cells "
              f"({_pc(rg['share'])}); within tolerance {rg['within_tolerance']} of them ({_pc(rg['rate'])}), unknown "
              f"{rg['unknown']}; within tolerance among the others: {rg['not_rangeable_within_tolerance']}.", ""]
    fb = s.get("false_obstacles_beside_obstacle")
    if fb and (fb["in_view_total"] or fb["out_of_view_total"]):
        L += [f"False obstacles beside an obstacle (the range of a true obstacle cell within {fb['sectors']} sectors, within "
              f"tolerance: a real obstacle on a neighbouring bearing, not a phantom): in view {fb['in_view']} of "
              f"{fb['in_view_total']}, out of view {fb['out_of_view']} of {fb['out_of_view_total']}.", ""]
    L += claims_by_source_lines(s.get("claims_by_source"))
    L += unknown_by_reason_lines(s.get("unknown_by_reason"))
    dbr = s.get("detection_by_range")
    if dbr:
        L += ["## Detection by true range", "",
              "Detection = a range within tolerance.  Out of view every obstacle cell is listed (unknown included); "
              "'of claimed' is the share within tolerance of the cells with a range or clear.", ""]
        for key, label in (("in_view", "In view"), ("out_of_view", "Out of view")):
            L += [f"{label}:", "", "| true range | obstacle cells | detection | range reported | unknown | clear (dangerous) | of claimed |",
                  "|---|---|---|---|---|---|---|"]
            for b in dbr[key]:
                L.append(f"| {b['bin']} | {b['obstacle_cells']} | {_pc(b['valid_rate'])} | {_pc(b['range_rate'])} | "
                         f"{_pc(b['unknown_rate'])} | {b['clear']} | {_pc(b['valid_of_claimed'])} |")
            L.append("")
    L += ["## Range error (published − true), by true range", ""]
    for key, label in (("published_all_sectors", "Conservative published value, all sectors (detections)"),
                       ("published_forward", "Conservative published value, forward DISTANCE_SENSOR"),
                       ("estimate_forward", f"Estimate (published + {_k_text(cfg)}·σ), forward DISTANCE_SENSOR")):
        L += [f"{label}:", "", "| true range | n | bias m | mean abs m | median abs m | p95 abs m | mean abs % | median abs % |",
              "|---|---|---|---|---|---|---|---|"]
        for row in s["range_error"][key]:
            L.append(f"| {row['bin']} | {row['n']} | {_f(row['bias_m'])} | {_f(row['mae_m'])} | {_f(row['median_abs_m'])} | "
                     f"{_f(row['p95_abs_m'])} | {_f(row['mae_pct'], '{:.1f}')} | {_f(row['median_abs_pct'], '{:.1f}')} |")
        L.append("")
    ne = s["nees"]
    L += ["## NEES and coverage of the reported σ (forward)", ""] + nees_lines(ne) + [
          f"At arrival: n = {ne['arrival']['n']}, n_eff = {_f(ne['arrival'].get('n_eff'), '{:.1f}')}, mean "
          f"{_f(ne['arrival']['mean'])}.  σ from covariance: {s['distance_sensor']['sigma_from_covariance']}, from "
          f"signal_quality: {s['distance_sensor']['sigma_from_signal_quality']}." + (
              "  Plot: [nees.png](nees.png)." if s.get("plots", {}).get("nees") else ""), ""]
    la = s["latency"]
    L += ["## Latency (exposure → message stamp)", "",
          f"n = {la['n']}: p50 {_f(la['p50_ms'], '{:.1f}')} ms, p95 {_f(la['p95_ms'], '{:.1f}')} ms, "
          f"p99 {_f(la['p99_ms'], '{:.1f}')} ms, max {_f(la['max_ms'], '{:.1f}')} ms; exposures not matched to a frame: "
          f"{la['unmatched_exposures']}.", ""]
    L += ["## Obstacles (time to the first valid range)", "",
          "| obstacle | in range at s | first valid at s | time to first valid s | detected | valid | nearest true m |",
          "|---|---|---|---|---|---|---|"]
    for o in s["obstacles"]:
        L.append(f"| {o['name']} | {_f(o['in_range_at_s'])} | {_f(o['first_valid_at_s'])} | "
                 f"{_f(o['time_to_first_valid_s'], '{:.2f}', 'never')} | {_pc(o['detected_fraction'], 0)} | "
                 f"{_pc(o['valid_fraction'], 0)} | {_f(o['nearest_true_m'], '{:.1f}')} |")
    ds = s["distance_sensor"]
    L += ["", "## Forward DISTANCE_SENSOR", "",
          f"{ds['messages']} messages: {ds['ranges']} ranges, {ds['clear']} clear, {ds['unknown']} unknown; obstacle ahead in "
          f"{ds['obstacle_messages']}, detected in {_pc(ds['detection_rate'])}, dangerous clears {ds['dangerous_clears']}.", ""]
    L += ["## Per sector", "", "| sector | bearing ° | obstacle cells | detection | dangerous | too near | clear cells | "
          "false obstacle | clear claimed |", "|---|---|---|---|---|---|---|---|---|"]
    for row in s["sectors"]:
        L.append(f"| {row['sector']} | {row['bearing_deg']:+.0f} | {row['obstacle_cells']} | {_pc(row['detection_rate'], 0)} | "
                 f"{row['dangerous_clears']} | {row['too_near']} | {row['clear_cells']} | {_pc(row['false_obstacle_rate'])} | "
                 f"{row['clear_claimed']} |")
    d = s["definitions"]
    L += ["", "## Definitions", ""] + [f"- **{k.replace('_', ' ')}**: {v}" for k, v in d.items()]
    L += [f"- **range bins**: lower edges {cfg['range_bins_m']} m; σ from DISTANCE_SENSOR covariance (cm²) or "
          f"signal_quality (zero at σ/d = {cfg['quality_zero_rel_sigma']:g}); k = {_k_text(cfg)}",
          "- **obstacles**: truth cells grouped by world position (link max("
          f"{cfg['obstacle_link_m']:g} m, {100 * cfg['obstacle_link_rel']:g} % of range)); in range = first message with one of its "
          "cells an obstacle cell; valid = a range within tolerance in one of its cells",
          "- **latency**: stamp − exposure (OBSTACLE_DISTANCE time_usec mapped to the recording clock by the companion's own "
          "time_boot_ms, snapped to the truth frame)"]
    if s.get("notes"):
        L += ["", "## Notes", ""] + [f"- {n}" for n in s["notes"]]
    return "\n".join(L) + "\n"


#: the reasons of ``unknown_by_reason`` as table columns, in code order, then "unattributed" (no log line)
REASON_COLUMNS = (*REASON_NAMES[1:], "unattributed")
#: the groups of ``unknown_by_reason`` as table rows
_UNKNOWN_GROUPS = (("obstacle_in_view", "obstacle cells in view"), ("obstacle_out_of_view", "obstacle cells out of view"),
                   ("remembered", "of them remembered"), ("clear_in_view", "clear cells in view"))


def unknown_reason_table(items) -> list[str]:
    """A table of unknown cells by reason for ``items`` = [(scenario label or None, ``unknown_by_reason``)]: one row
    per group with unknown cells, the share of each reason that occurs in any of them (docs/derivations/sectors.md,
    "Why a sector is unknown"); a scenario column when a label is given.  [] when nothing is unknown."""
    items = [(label, u) for label, u in items if u]
    names = [n for n in REASON_COLUMNS if any((u.get(k) or {}).get(n) for _, u in items for k, _ in _UNKNOWN_GROUPS)]
    if not names:
        return []
    lead = "| scenario " if any(label for label, _ in items) else ""
    L = [lead + "| cells | unknown | " + " | ".join(n.replace("_", " ") for n in names) + " |",
         ("|---" if lead else "") + "|---|---|" + "---|" * len(names)]
    for label, u in items:
        for key, group in _UNKNOWN_GROUPS:
            g = u.get(key) or {}
            n = int(g.get("cells") or 0)
            if n:
                L.append((f"| {label} " if lead else "") + f"| {group} | {n} | "
                         + " | ".join(f"{100.0 * int(g.get(k) or 0) / n:.1f} %" for k in names) + " |")
    return L


def unknown_by_reason_lines(ubr) -> list[str]:
    """The "Unknown cells by reason" section (the companion's sector log; ``unknown_by_reason`` of a score or a
    campaign): per group, the unknown cells and the share of each reason (:func:`unknown_reason_table`)."""
    if not ubr:
        return []
    L = ["## Unknown cells by reason (the companion's sector log)", "",
         f"Messages scored {ubr['messages_scored']}, of them found in the sector log {ubr['messages_matched']}. "
         "Why each unknown sector was unknown, the first rule it fell short of: not seen (out of view, nothing "
         "remembered there), no points (no tracked point in the sector), beside band (points above or below the "
         "band only), few far (too few far points for clear), vetoed (clear forbidden by a point that may be "
         "nearer), ranging (points in the band not yet converged), few near, partly in view, held (clear held "
         "back), turned (the vehicle turned since exposure); unattributed = no log line.", ""]
    return L + (unknown_reason_table([(None, ubr)]) or ["No unknown cells."]) + [""]


def claims_by_source_lines(cbs) -> list[str]:
    """The "Claims by source" table (the companion's sector log; ``claims_by_source`` of a score or a campaign)."""
    if not cbs:
        return []
    L = ["## Claims by source (the companion's sector log)", "",
         f"Messages scored {cbs['messages_scored']}, of them found in the sector log {cbs['messages_matched']}. "
         "Source of a sector's claim: live points only, live and remembered (mixed), remembered (map) points only, "
         "inferred across sectors (between two sides, a narrow gap), inferred from points above or below the band "
         "(vertical: a structure through the band, the cap from above); unattributed = no log line.", "",
         "| view | source | ranges | on obstacles | within tolerance | too near | over range | false obstacles | of them beside an obstacle |",
         "|---|---|---|---|---|---|---|---|---|"]
    for view in ("in_view", "out_of_view"):
        for name, row in (cbs.get(view) or {}).items():
            if row["ranges"]:
                L.append(f"| {view.replace('_', ' ')} | {name} | {row['ranges']} | {row['on_obstacles']} | {row['valid']} | "
                         f"{row['too_near']} | {row['over_range']} | {row['false_obstacles']} | {row['beside_obstacle']} |")
    return L + [""]
