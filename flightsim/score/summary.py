"""The JSON-ready score of one run (:func:`summarize`: the contents of ``score.json``) from an
:class:`~flightsim.score.evaluation.Evaluation`: cell counts and rates in view, out of view and
pooled (:func:`cell_counts`), detection by true range (:func:`detection_table`), remembered cells,
the targets, per-sector rows, range error by bin (:func:`error_table`), latency, NEES
(:func:`nees_summary`), the forward DISTANCE_SENSOR and the obstacles; and the per-message arrays a
campaign pools over runs (:func:`series_arrays`).  Definitions: :mod:`flightsim.score`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from companion.core.sectors_types import SectorSource, UnknownReason
from flightsim.score.config import N_SECTORS, REP_CLEAR, REP_RANGE, REP_UNKNOWN, SECTOR_DEG, TRUTH_OBSTACLE
from flightsim.score.evaluation import CellMasks, Evaluation, cell_masks
from flightsim.score.stats import EffectiveSize, effective_sample_size, nees_band, normal_coverage, stretch_labels


# ---------------------------------------------------------------------- helpers and range error --
def _rate(num: int, den: int) -> float | None:
    return None if den == 0 else num / den


def _pct(x: np.ndarray, q: float) -> float | None:
    return None if x.size == 0 else float(np.percentile(x, q))


def error_table(true_m: np.ndarray, value_m: np.ndarray, bins_m: Sequence[float]) -> list[dict]:
    """Range error ``value − true`` by bin of the true distance: n, bias, mean/median/p95 |error|
    (m) and mean/median |error| in % of the true distance."""
    T = np.asarray(true_m, float)
    v = np.asarray(value_m, float)
    ok = np.isfinite(T) & np.isfinite(v)
    T, v = T[ok], v[ok]
    edges = list(bins_m)
    rows = []
    for i, lo in enumerate(edges):
        hi = edges[i + 1] if i + 1 < len(edges) else math.inf
        sel = (T >= lo) & (T < hi)
        e = v[sel] - T[sel]
        a = np.abs(e)
        rel = 100.0 * a / np.maximum(T[sel], 1e-9)
        rows.append({
            "bin": f"{lo:g}–{hi:g} m" if math.isfinite(hi) else f"{lo:g}+ m",
            "lo_m": lo, "hi_m": hi if math.isfinite(hi) else None, "n": int(sel.sum()),
            "bias_m": float(e.mean()) if e.size else None,
            "mae_m": float(a.mean()) if a.size else None,
            "median_abs_m": _pct(a, 50), "p95_abs_m": _pct(a, 95),
            "mae_pct": float(rel.mean()) if rel.size else None,
            "median_abs_pct": _pct(rel, 50),
        })
    return rows


# ---------------------------------------------------------------------- summary ----------------
def _bearing(i: int) -> float:
    b = i * SECTOR_DEG
    return b - 360.0 if b >= 180.0 else b


def _obstacle_rows(ev: Evaluation, m: CellMasks) -> list[dict]:
    rows = []
    t_rel = ev.od_t - ev.t0
    for k, name in enumerate(ev.obstacle_names):
        cells = (ev.od_label == k) & m.in_view  # in view: time to the first valid range after it comes into view
        in_msgs = np.flatnonzero(np.any(cells & m.obstacle, axis=1))
        row = {"id": k, "name": name, "centroid_ne_m": [round(float(v), 2) for v in ev.obstacle_centroids[k]],
               "messages_in_range": int(in_msgs.size), "in_range_at_s": None, "last_in_range_at_s": None,
               "first_detection_at_s": None, "first_valid_at_s": None, "time_to_first_valid_s": None,
               "first_rangeable_at_s": None, "time_to_first_valid_after_rangeable_s": None,
               "detected_fraction": None, "valid_fraction": None, "nearest_true_m": None}
        if in_msgs.size:
            row["in_range_at_s"] = float(t_rel[in_msgs[0]])
            row["last_in_range_at_s"] = float(t_rel[in_msgs[-1]])
            row["nearest_true_m"] = float(np.nanmin(np.where(cells, ev.od_truth, np.nan)[in_msgs]))
            det = np.any(cells & m.detection, axis=1)
            val = np.any(cells & m.valid, axis=1)
            row["detected_fraction"] = float(det[in_msgs].mean())
            row["valid_fraction"] = float(val[in_msgs].mean())
            first_det = np.flatnonzero(det)
            first_val = np.flatnonzero(val)
            if first_det.size:
                row["first_detection_at_s"] = float(t_rel[first_det[0]])
            if first_val.size:
                row["first_valid_at_s"] = float(t_rel[first_val[0]])
                row["time_to_first_valid_s"] = float(t_rel[first_val[0]] - t_rel[in_msgs[0]])
            # the single camera's ceiling: from the first message in which one of its cells could be ranged at all
            first_rg = np.flatnonzero(np.any(cells & m.rangeable, axis=1))
            if first_rg.size:
                row["first_rangeable_at_s"] = float(t_rel[first_rg[0]])
                if first_val.size:  # 0 when it was ranged first (from a neighbouring point, or memory)
                    row["time_to_first_valid_after_rangeable_s"] = max(0.0, float(t_rel[first_val[0]] - t_rel[first_rg[0]]))
        rows.append(row)
    return rows


def _target(key: str, name: str, num: int, den: int, op: str, threshold: float) -> dict:
    v = _rate(num, den)
    return {"key": key, "name": name, "value": v, "num": int(num), "n": int(den), "op": op, "threshold": threshold,
            "met": None if v is None else bool(v >= threshold if op == ">=" else v <= threshold)}


def cell_counts(m: CellMasks, sel: np.ndarray, claims: np.ndarray) -> tuple[dict, dict]:
    """Cell counts and rates over the counted cells selected by ``sel`` (N, 72) (all, in view, out
    of view).  Per message: messages with a claim (``claims``, (N,)) and a clear cell in ``sel``;
    of those, the ones without a false obstacle in a clear cell of ``sel``."""
    ob, cl = m.obstacle & sel, m.clear & sel
    c = {
        "obstacle": int(ob.sum()), "clear": int(cl.sum()), "detections": int((m.detection & sel).sum()),
        "valid_ranges": int((m.valid & sel).sum()), "dangerous_clears": int((m.dangerous & sel).sum()),
        "false_obstacles_clear_cells": int((m.false_clear & sel).sum()), "unverifiable_beyond_truth": int((m.unverifiable & sel).sum()),
        "too_near": int((m.too_near & sel).sum()), "over_range": int((m.over_range & sel).sum()),
        "unknown_in_obstacle_cells": int((m.missed_unknown & sel).sum()),
        "clear_claimed_in_clear_cells": int((m.claimed_clear & sel).sum()), "unscored_claims": int((m.unscored_claim & sel).sum()),
        "invalid_values": int((m.invalid & sel).sum()),
    }
    eligible = claims & np.any(cl, axis=1)
    c["messages_eligible_no_false"] = int(eligible.sum())
    c["messages_without_false_obstacle"] = int((eligible & ~np.any(m.false_clear & sel, axis=1)).sum())
    n_obs, n_clear = c["obstacle"], c["clear"]
    r = {
        "detection": _rate(c["detections"], n_obs), "valid_range": _rate(c["valid_ranges"], n_obs),
        "dangerous_clear": _rate(c["dangerous_clears"], n_obs), "unknown_in_obstacle_cells": _rate(c["unknown_in_obstacle_cells"], n_obs),
        "false_obstacle_clear_cells": _rate(c["false_obstacles_clear_cells"], n_clear), "too_near": _rate(c["too_near"], n_obs),
        "over_range": _rate(c["over_range"], n_obs), "clear_claimed_in_clear_cells": _rate(c["clear_claimed_in_clear_cells"], n_clear),
        "messages_without_false_obstacle": _rate(c["messages_without_false_obstacle"], c["messages_eligible_no_false"]),
    }
    return c, r


def _bin_labels(bins_m: Sequence[float]) -> list[tuple[str, float, float]]:
    edges = list(bins_m)
    out = []
    for i, lo in enumerate(edges):
        hi = edges[i + 1] if i + 1 < len(edges) else math.inf
        out.append((f"{lo:g}–{hi:g} m" if math.isfinite(hi) else f"{lo:g}+ m", lo, hi))
    return out


def detection_table(true_m: np.ndarray, rep: np.ndarray, valid: np.ndarray, cells: np.ndarray,
                    bins_m: Sequence[float]) -> list[dict]:
    """Per bin of the true range (lower edges ``bins_m``, the last open) over the ``cells`` mask:
    obstacle cells, ranges, ranges within tolerance (``valid``: *detection*),
    unknown, "clear" (dangerous) and their shares of the bin's cells; ``claimed`` = ranges + clear
    and ``valid_of_claimed`` (what matters out of view, where unknown is neutral)."""
    T = np.asarray(true_m, float)[cells]
    rp = np.asarray(rep)[cells]
    ok = np.asarray(valid, bool)[cells]
    lab = _bin_labels(bins_m)
    idx = np.searchsorted(np.asarray(bins_m, float), T, side="right") - 1  # below the first edge: −1, dropped
    keep = idx >= 0
    idx, rp, ok = idx[keep], rp[keep], ok[keep]
    nb = len(lab)
    cnt = lambda w: np.bincount(idx, weights=w.astype(float), minlength=nb).astype(int)  # noqa: E731
    n = np.bincount(idx, minlength=nb)
    rng, unk, clr, val = cnt(rp == REP_RANGE), cnt(rp == REP_UNKNOWN), cnt(rp == REP_CLEAR), cnt(ok)
    rows = []
    for b, (name, lo, hi) in enumerate(lab):
        rows.append({"bin": name, "lo_m": lo, "hi_m": hi if math.isfinite(hi) else None, "obstacle_cells": int(n[b]),
                     "ranges": int(rng[b]), "valid": int(val[b]), "unknown": int(unk[b]), "clear": int(clr[b]),
                     "claimed": int(rng[b] + clr[b]), "valid_rate": _rate(int(val[b]), int(n[b])),
                     "range_rate": _rate(int(rng[b]), int(n[b])), "unknown_rate": _rate(int(unk[b]), int(n[b])),
                     "dangerous_rate": _rate(int(clr[b]), int(n[b])),
                     "valid_of_claimed": _rate(int(val[b]), int(rng[b] + clr[b]))})
    return rows


def false_obstacles_beside(ev: Evaluation, m: CellMasks, sectors: int) -> np.ndarray:
    """(N, 72) bool: false obstacles in clear cells whose published range matches (within tolerance)
    the true range of an obstacle cell at most ``sectors`` sectors away in the same message — a
    real obstacle claimed at the right range on a neighbouring bearing (a thin pole's remembered
    point spread over its bearing σ), as opposed to a phantom range."""
    if sectors < 1 or not np.any(m.false_clear):
        return np.zeros(m.false_clear.shape, bool)
    T = np.where(ev.od_tcls == TRUTH_OBSTACLE, ev.od_truth, np.nan)
    return matches_neighbour(ev.od_r, T, sectors, ev.config) & m.false_clear


def matches_neighbour(r: np.ndarray, T_obstacle: np.ndarray, sectors: int, cfg) -> np.ndarray:
    """(N, 72) bool: the published range ``r`` of a cell matches, within ``cfg.tolerance``, the true range of an
    obstacle cell at most ``sectors`` sectors away in the same message (``T_obstacle``: the truth of obstacle
    cells, NaN elsewhere) — a real obstacle reported on a neighbouring bearing."""
    out = np.zeros(np.shape(r), bool)
    for k in range(1, sectors + 1):
        for shift in (k, -k):
            Tn = np.roll(T_obstacle, shift, axis=1)  # the truth of the sector k away
            with np.errstate(invalid="ignore"):
                out |= np.isfinite(Tn) & (np.abs(r - Tn) <= cfg.tolerance(np.where(np.isfinite(Tn), Tn, 0.0)))
    return out


#: the companion's sector sources by code ("none", "live", "mixed", "remembered", "inferred", "vertical")
SOURCE_NAMES = tuple(s.name.lower() for s in SectorSource)


#: why an unknown sector is unknown, by code ("none", "not_seen", "no_points", …; docs/derivations/sectors.md)
REASON_NAMES = tuple(r.name.lower() for r in UnknownReason)


def message_sources(ev: Evaluation, sector_log: dict) -> np.ndarray:
    """(N, 72) int8: the source of each cell of each OBSTACLE_DISTANCE from the companion's sector log
    (:func:`companion.sector_log.read_sector_log`: its lines by ``(time_usec, distances)``), or any other
    per-sector row of it keyed the same way (the reasons, :func:`companion.sector_log.read_sector_reasons`);
    −1 for a message that has no line there."""
    msgs = ev.messages
    n = len(ev.od_t)
    src = np.full((n, N_SECTORS), -1, np.int8)
    cm = np.asarray(msgs.od_distances_cm).reshape(n, N_SECTORS).astype(np.uint16)
    for i in range(n):
        row = sector_log.get((int(msgs.od_time_usec[i]), cm[i].tobytes()))
        if row is not None:
            src[i] = row
    return src


def claims_by_source(ev: Evaluation, m: CellMasks, src: np.ndarray, beside: np.ndarray) -> dict:
    """The scored range claims split by where the companion says each came from (``src``,
    :func:`message_sources`), in view and out of view: ranges, those on obstacle cells, within
    tolerance, too near, over range, false obstacles in clear cells (and of them beside an
    obstacle).  ``unattributed``: a range in a message without a log line, or whose line names no
    source for that sector."""
    rng = (ev.od_rep == REP_RANGE) & ev.od_scored[:, None]
    counted = m.obstacle | m.clear
    out = {"messages_scored": int(ev.od_scored.sum()),
           "messages_matched": int(np.sum(ev.od_scored & np.all(src >= 0, axis=1)))}
    groups = [(name, src == code) for code, name in enumerate(SOURCE_NAMES) if code > 0]
    groups.append(("unattributed", (src <= 0)))
    for view, vm in (("in_view", m.in_view), ("out_of_view", ~m.in_view)):
        rows = {}
        for name, sel in groups:
            c = rng & counted & sel & vm
            rows[name] = {"ranges": int(c.sum()), "on_obstacles": int((c & m.obstacle).sum()), "valid": int((c & m.valid).sum()),
                          "too_near": int((c & m.too_near).sum()), "over_range": int((c & m.over_range).sum()),
                          "false_obstacles": int((c & m.false_clear).sum()), "beside_obstacle": int((c & beside).sum())}
        out[view] = rows
    return out


def unknown_by_reason(ev: Evaluation, m: CellMasks, why: np.ndarray) -> dict:
    """The unknown cells split by why the companion says each sector was unknown (``why``, :func:`message_sources`
    of :func:`companion.sector_log.read_sector_reasons`; docs/derivations/sectors.md, "Why a sector is unknown"):
    obstacle cells in view (missed detections), out of view (neutral) and of them the remembered ones (the
    remembered target's misses), and clear cells in view (where PX4 refuses to move).  ``unattributed``: a
    message without a log line, or a line that names no reason for that sector."""
    unknown = ev.od_rep == REP_UNKNOWN
    groups = {"obstacle_in_view": m.missed_unknown & m.in_view, "obstacle_out_of_view": m.obstacle_any & ~m.in_view & unknown,
              "remembered": m.remembered & unknown, "clear_in_view": m.clear & m.in_view & unknown}
    out: dict = {"messages_scored": int(ev.od_scored.sum()),
                 "messages_matched": int(np.sum(ev.od_scored & np.all(why >= 0, axis=1)))}
    for g, sel in groups.items():
        out[g] = {"cells": int(sel.sum())} | reason_counts(sel, why)
    return out


def reason_counts(sel: np.ndarray, why: np.ndarray) -> dict[str, int]:
    """The cells ``sel`` counted by reason (``why``: :class:`UnknownReason` codes, −1 without a sector-log line):
    one count per reason name, then ``unattributed`` (no line, or a line naming no reason for the cell)."""
    out = {name: int((sel & (why == code)).sum()) for code, name in enumerate(REASON_NAMES) if code > 0}
    out["unattributed"] = int((sel & (why <= 0)).sum())
    return out


def summarize(ev: Evaluation, sector_log: dict | None = None, reasons: dict | None = None) -> dict:
    """The JSON-ready score of one run (the contents of ``score.json``); with the companion's
    ``sector_log`` (:func:`companion.sector_log.read_sector_log`) also its claims by source, and with its
    ``reasons`` (:func:`companion.sector_log.read_sector_reasons`) the unknown cells by reason."""
    cfg = ev.config
    m = cell_masks(ev)
    msgs = ev.messages
    scored = ev.od_scored
    claims = np.any((ev.od_rep == REP_RANGE) | (ev.od_rep == REP_CLEAR), axis=1) & scored
    everywhere = np.ones(m.obstacle.shape, bool)
    cells, rates = cell_counts(m, everywhere, claims)
    cells_iv, rates_iv = cell_counts(m, m.in_view, claims)
    cells_oov, rates_oov = cell_counts(m, ~m.in_view, claims)
    oov = ~m.in_view
    cells_oov.update({"obstacle_cells_total": int((m.obstacle_any & oov).sum()), "clear_cells_total": int((m.clear_any & oov).sum()),
                      "unknown_neutral": int(m.unknown_out_of_view.sum())})
    rates["messages_with_claims"] = _rate(int(claims.sum()), int(scored.sum()))
    n_obs, n_clear, dang, fclear = cells["obstacle"], cells["clear"], cells["dangerous_clears"], cells["false_obstacles_clear_cells"]
    n_elig, n_ok_msgs = cells["messages_eligible_no_false"], cells["messages_without_false_obstacle"]
    # detection by true range: in view, and out of view (every out-of-view obstacle cell, unknown included)
    det_tables = {
        "in_view": detection_table(ev.od_truth, ev.od_rep, m.valid, m.obstacle_any & m.in_view, cfg.detection_bins_m),
        "out_of_view": detection_table(ev.od_truth, ev.od_rep, m.valid, m.obstacle_any & oov, cfg.detection_bins_m),
    }
    near = m.obstacle & m.in_view & (ev.od_truth < cfg.near_range_m)
    n_near, v_near = int(near.sum()), int((near & m.valid).sum())
    n_rem, v_rem = int(m.remembered.sum()), int((m.remembered & m.valid).sum())
    remembered = {
        "cells": n_rem, "within_tolerance": v_rem, "rate": _rate(v_rem, n_rem),
        "ranges": int((m.remembered & (ev.od_rep == REP_RANGE)).sum()),
        "unknown": int((m.remembered & (ev.od_rep == REP_UNKNOWN)).sum()),
        "dangerous_clears": int((m.remembered & (ev.od_rep == REP_CLEAR)).sum()),
        "too_near": int((m.remembered & m.too_near).sum()), "over_range": int((m.remembered & m.over_range).sum()),
        "rangeable_cells": int(m.remembered_rangeable.sum()),
        "rangeable_within_tolerance": int((m.remembered_rangeable & m.valid).sum()),
        "rangeable_rate": _rate(int((m.remembered_rangeable & m.valid).sum()), int(m.remembered_rangeable.sum())),
        "window_s": cfg.remember_window_s, "max_travel_m": cfg.remember_max_travel_m,
    }
    iv_obs = m.obstacle & m.in_view
    n_rg, v_rg = int(m.rangeable.sum()), int((m.rangeable & m.valid).sum())
    n_iv = int(iv_obs.sum())
    rangeable = {
        "obstacle_cells_in_view": n_iv, "cells": n_rg, "share": _rate(n_rg, n_iv),
        "within_tolerance": v_rg, "rate": _rate(v_rg, n_rg),
        "unknown": int((m.rangeable & (ev.od_rep == REP_UNKNOWN)).sum()),
        "not_rangeable_within_tolerance": int((iv_obs & ~m.rangeable & m.valid).sum()),
        "window_s": cfg.rangeable_window_s, "parallax_deg": cfg.rangeable_parallax_deg, "scale": cfg.rangeable_scale,
    }
    beside = false_obstacles_beside(ev, m, cfg.beside_sectors)
    false_beside = {
        "sectors": cfg.beside_sectors,
        "in_view": int((beside & m.in_view).sum()), "in_view_total": int((m.false_clear & m.in_view).sum()),
        "out_of_view": int((beside & oov).sum()), "out_of_view_total": int((m.false_clear & oov).sum()),
    }
    targets = [
        _target("messages_without_false_obstacle", "no false obstacle in clear sectors (in and out of view), share of messages",
                n_ok_msgs, n_elig, ">=", cfg.target_no_false_obstacle),
        _target("dangerous_clear", "dangerous clear (max_distance + 1 in an obstacle cell, in and out of view), share of "
                "obstacle cells", dang, n_obs, "<=", cfg.target_dangerous_clear),
        _target("false_obstacle_clear_cells", "false obstacle in clear cells (in and out of view), share of clear cells",
                fclear, n_clear, "<=", cfg.target_false_obstacle),
        _target("detection_in_view", "detection (a range within tolerance), share of in-view obstacle cells",
                cells_iv["valid_ranges"], cells_iv["obstacle"], ">=", cfg.target_detection),
        _target("detection_near_in_view", f"detection within 0–{cfg.near_range_m:g} m, share of in-view obstacle cells",
                v_near, n_near, ">=", cfg.target_detection_near),
        _target("remembered", f"remembered obstacles out of view (in view within {cfg.remember_window_s:g} s, vehicle moved "
                f"< {cfg.remember_max_travel_m:g} m): share of their cells within tolerance", v_rem, n_rem, ">=",
                cfg.target_remembered),
    ]
    # per sector
    sectors = []
    for i in range(N_SECTORS):
        no, nc = int(m.obstacle[:, i].sum()), int(m.clear[:, i].sum())
        if no == 0 and nc == 0:
            continue
        sectors.append({
            "sector": i, "bearing_deg": _bearing(i), "obstacle_cells": no, "detections": int(m.detection[:, i].sum()),
            "detection_rate": _rate(int(m.detection[:, i].sum()), no), "dangerous_clears": int(m.dangerous[:, i].sum()),
            "too_near": int(m.too_near[:, i].sum()), "clear_cells": nc, "false_obstacles": int(m.false_clear[:, i].sum()),
            "false_obstacle_rate": _rate(int(m.false_clear[:, i].sum()), nc),
            "clear_claimed": int(m.claimed_clear[:, i].sum()),
        })
    # range error
    dT, dr = ev.od_truth[m.detection], ev.od_r[m.detection]
    ds_rng = (ev.ds_state == REP_RANGE) & np.isfinite(ev.ds_truth_arrival) & (ev.ds_truth_arrival <= ev.ds_max_m)
    est_ok = ds_rng & np.isfinite(ev.ds_estimate_m)
    range_error = {
        "published_all_sectors": error_table(dT, dr, cfg.range_bins_m),
        "published_forward": error_table(ev.ds_truth_arrival[ds_rng], ev.ds_published_m[ds_rng], cfg.range_bins_m),
        "estimate_forward": error_table(ev.ds_truth_arrival[est_ok], ev.ds_estimate_m[est_ok], cfg.range_bins_m),
    }
    # latency
    lat = ev.od_latency_s[np.isfinite(ev.od_latency_s)] * 1000.0
    latency = {"n": int(lat.size), "p50_ms": _pct(lat, 50), "p95_ms": _pct(lat, 95), "p99_ms": _pct(lat, 99),
               "max_ms": float(lat.max()) if lat.size else None,
               "unmatched_exposures": int(np.sum((ev.od_capture_frame < 0) & np.isfinite(ev.od_capture_t))),
               "boot_offset_s": ev.boot_offset_s if math.isfinite(ev.boot_offset_s) else None,
               "exposure_mapping_residual_ms_p50": _pct(ev.capture_residual_s * 1000.0, 50)}
    # NEES
    nees = nees_summary(ev)
    # DISTANCE_SENSOR
    ds_obs = np.isfinite(ev.ds_truth_arrival) & (ev.ds_truth_arrival <= ev.ds_max_m)
    ds = {
        "messages": int(len(ev.ds_t)), "scored": int(np.sum(ev.ds_frame >= 0)),
        "ranges": int(np.sum(ev.ds_state == REP_RANGE)), "clear": int(np.sum(ev.ds_state == REP_CLEAR)),
        "unknown": int(np.sum(ev.ds_state == REP_UNKNOWN)), "obstacle_messages": int(ds_obs.sum()),
        "detection_rate": _rate(int(np.sum(ds_obs & (ev.ds_state == REP_RANGE))), int(ds_obs.sum())),
        "dangerous_clears": int(np.sum(ds_obs & (ev.ds_state == REP_CLEAR))),
        "sigma_from_covariance": int(np.sum(ev.ds_sigma_source == 1)),
        "sigma_from_signal_quality": int(np.sum(ev.ds_sigma_source == 2)),
    }
    any_claim = np.any((ev.od_rep == REP_RANGE) | (ev.od_rep == REP_CLEAR), axis=1) & msgs.od_geometry_ok & (ev.od_frame >= 0)
    first_claim = np.flatnonzero(any_claim)  # warm-up included: how soon the companion claims anything
    hb = msgs.heartbeat_status
    counts = dict(msgs.counts)
    out = {
        "version": 1,
        "definitions": {
            "truth": "latest truth frame at or before the message stamp (arrival), at most truth_max_age_s old",
            "obstacle_cell": "truth finite and <= the message's max_distance",
            "clear_cell": "truth inf or > max_distance",
            "tolerance": f"max({cfg.tolerance_m:g} m, {100 * cfg.tolerance_rel:g} % of the true distance)",
            "false_obstacle": "range in a clear cell nearer than the truth by more than the tolerance (truth inf taken at "
                              "sector_max_m, the most favourable case; within tolerance of it = unverifiable); too_near: the same "
                              "in an obstacle cell",
            "dangerous_clear": "max_distance + 1 reported in an obstacle cell",
            "messages_without_false_obstacle": "over messages with a claim and at least one scored clear cell",
            "in_view": "the sector's centre bearing projects into the camera image (truth.npz in_view); truth files "
                       "without it: the sectors whose truth is known",
            "out_of_view": "cells outside the camera's view are scored only where a claim (a range or clear) is made: "
                           "a range within tolerance on an obstacle is a (remembered) detection, too near in a clear cell "
                           "a false obstacle, clear on an obstacle a dangerous clear; unknown there is neutral (not a miss)",
            "detection_within_tolerance": "a range within tolerance (valid range)",
            "remembered": f"out-of-view obstacle cells whose obstacle (grouped by position) occupied an in-view cell "
                          f"within the last {cfg.remember_window_s:g} s, the vehicle having moved < {cfg.remember_max_travel_m:g} m "
                          "since the latest such frame; unknown there counts as not reported",
            "rangeable": f"in-view obstacle cells whose world point the camera saw within the last {cfg.rangeable_window_s:g} s "
                         f"from a place whose line of sight to it differs from the present one by >= {cfg.rangeable_parallax_deg:g}° "
                         f"or whose distance to it differs by >= {100 * cfg.rangeable_scale:g} %: the cells any single camera could "
                         "have ranged (geometry only: no occlusion, no texture; a diagnostic, not a target)",
            "warmup": f"messages stamped within {cfg.warmup_s:g} s of the first truth frame are not scored (latency and "
                      "first claim include them)",
            "nees": "(estimate − truth at exposure)² / σ² of each forward DISTANCE_SENSOR range with a known σ; its mean "
                    "against the band of the mean of n_eff χ²₁ samples, χ²(n_eff)/n_eff (n_eff: the effective sample size, "
                    "from the autocorrelation within stretches without a gap over "
                    f"{cfg.nees_gap_s:g} s, truncated by Geyer's initial monotone sequence); band_independent: as if the n "
                    "samples were independent (reference only: consecutive samples are correlated)",
            "coverage": "share of the same samples with the truth within estimate ± σ / ± 2σ (a normal error with the right "
                        "σ: 68.27 % / 95.45 %)",
        },
        "config": dataclasses.asdict(cfg),
        "duration_s": float(ev.od_t[-1] - ev.t0) if len(ev.od_t) else 0.0,
        "truth_horizon_m": ev.sector_max_m,
        "messages": {
            "by_type": counts.get("by_type", {}),
            "obstacle_distance": int(len(ev.od_t)), "obstacle_distance_scored": int(scored.sum()),
            "in_warmup": int(np.sum(ev.od_warmup & msgs.od_geometry_ok & (ev.od_frame >= 0))),
            "without_truth": int(np.sum(msgs.od_geometry_ok & (ev.od_frame < 0))),
            "with_claims": int(claims.sum()),
            "reader": {k: v for k, v in counts.items() if k != "by_type"},
            "heartbeat_active_share": _rate(int(np.sum(hb == 4)), int(hb.size)),  # MAV_STATE_ACTIVE = 4
            "statustext": [f"{t - ev.t0:.2f} s: {txt}" for t, _, txt in msgs.texts][:50],
        },
        "first_claim_at_s": float(ev.od_t[first_claim[0]] - ev.t0) if first_claim.size else None,
        "warmup": {"s": cfg.warmup_s, "messages_excluded": int(np.sum(ev.od_warmup & msgs.od_geometry_ok & (ev.od_frame >= 0)))},
        "truth_360": ev.truth_360,
        "cells": cells,
        "rates": rates,
        "cells_in_view": cells_iv,
        "rates_in_view": rates_iv,
        "cells_out_of_view": cells_oov,
        "rates_out_of_view": rates_oov,
        "detection_by_range": det_tables,
        "remembered": remembered,
        "rangeable": rangeable,
        "false_obstacles_beside_obstacle": false_beside,
        "claims_by_source": None if sector_log is None else claims_by_source(ev, m, message_sources(ev, sector_log), beside),
        "unknown_by_reason": unknown_by_reason(ev, m, message_sources(ev, reasons)) if reasons else None,
        "targets": targets,
        "sectors": sectors,
        "range_error": range_error,
        "obstacles": _obstacle_rows(ev, m),
        "latency": latency,
        "nees": nees,
        "distance_sensor": ds,
        "notes": list(ev.notes),
    }
    return _jsonable(out)


def forward_samples(ev: Evaluation, at: str = "exposure") -> dict[str, np.ndarray]:
    """The scored forward samples behind the NEES and the coverage: stamp ``t`` (recording clock),
    ``error_m`` (estimate − truth) and ``sigma_m`` of every forward DISTANCE_SENSOR range with a known
    σ and truth (``at`` = ``"exposure"`` or ``"arrival"`` truth), in message order."""
    T = ev.ds_truth_exposure if at == "exposure" else ev.ds_truth_arrival
    ok = (ev.ds_state == REP_RANGE) & np.isfinite(ev.ds_sigma_m) & (ev.ds_sigma_m > 0) & np.isfinite(T) & np.isfinite(ev.ds_estimate_m)
    return {"t": ev.ds_t[ok], "error_m": ev.ds_estimate_m[ok] - T[ok], "sigma_m": ev.ds_sigma_m[ok]}


def nees_samples(ev: Evaluation, at: str = "exposure") -> np.ndarray:
    """NEES samples of the forward estimate (``at`` = ``"exposure"`` or ``"arrival"`` truth)."""
    f = forward_samples(ev, at)
    return (f["error_m"] / f["sigma_m"]) ** 2


def nees_stats(samples: np.ndarray, confidence: float, n_eff: float | None = None, ess: EffectiveSize | None = None) -> dict:
    """Mean, median, bands and coverage of NEES ``samples``.

    ``band`` (and ``consistent``) is the band of the mean for ``n_eff`` effective samples (from
    ``ess`` when given; ``n_eff`` alone for a pooled figure); ``band_independent`` (and
    ``consistent_independent``) the band as if the ``n`` samples were independent, for reference.
    Without an effective size the first is unknown (None).  ``coverage``: the share of samples whose
    truth lies within ``estimate ± σ`` / ``± 2σ`` (NEES ≤ 1 / ≤ 4) and what a normal error with the
    right σ gives.
    """
    s = np.asarray(samples, float)
    n = int(s.size)
    if ess is not None:
        n_eff = ess.n_eff
    mean = float(s.mean()) if n else None
    lo_i, hi_i = nees_band(n, confidence)
    lo, hi = nees_band(n_eff, confidence) if n and n_eff else (math.nan, math.nan)
    have = n > 0 and math.isfinite(lo)
    out = {"n": n, "n_eff": float(n_eff) if n and n_eff else None, "mean": mean, "median": _pct(s, 50),
           "band": [lo, hi] if have else None, "consistent": bool(lo <= mean <= hi) if have else None,
           "band_independent": [lo_i, hi_i] if n else None,
           "consistent_independent": None if mean is None else bool(lo_i <= mean <= hi_i)}
    if ess is not None:
        out.update({"autocorrelation_time": ess.tau if n else None, "autocorrelation_lags": ess.lags, "stretches": ess.stretches})
    n1, n2 = int(np.sum(s <= 1.0)), int(np.sum(s <= 4.0))
    out["coverage"] = {"n": n, "within_1sigma": n1, "within_2sigma": n2,
                       "rate_1sigma": _rate(n1, n), "rate_2sigma": _rate(n2, n),
                       "expected_1sigma": normal_coverage(1.0), "expected_2sigma": normal_coverage(2.0)}
    return out


def nees_summary(ev: Evaluation) -> dict:
    """NEES and coverage of the forward σ against the truth at exposure (and at arrival), with the
    effective sample size of each series (gaps longer than ``nees_gap_s`` break it)."""
    cfg = ev.config
    per = {}
    for at in ("exposure", "arrival"):
        f = forward_samples(ev, at)
        x = (f["error_m"] / f["sigma_m"]) ** 2
        per[at] = nees_stats(x, cfg.nees_confidence, ess=effective_sample_size(x, f["t"], cfg.nees_gap_s))
    out = per["exposure"]
    out["at"] = "exposure (paired OBSTACLE_DISTANCE time_usec)"
    out["arrival"] = per["arrival"]
    out["confidence"] = cfg.nees_confidence
    out["gap_s"] = cfg.nees_gap_s
    return out


def series_arrays(ev: Evaluation, why: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per-message arrays a campaign report pools over runs (saved as ``score_series.npz``); with ``why``
    (:func:`message_sources` of the sector log's reasons) also ``od_why``, each cell's reason for being unknown."""
    m = cell_masks(ev)
    fwd = forward_samples(ev, "exposure")
    extra = {} if why is None else {"od_why": np.asarray(why, np.int8)}
    return extra | {
        "t0": np.array(ev.t0), "sector_max_m": np.array(ev.sector_max_m),
        "od_t": ev.od_t, "od_scored": ev.od_scored, "od_rep": ev.od_rep, "od_cm": ev.od_cm.astype(np.int32), "od_truth": ev.od_truth.astype(np.float32),
        "od_tcls": ev.od_tcls, "od_label": ev.od_label.astype(np.int16), "od_max_m": ev.od_max_m,
        "od_latency_s": ev.od_latency_s, "od_in_view": ev.od_in_view, "od_remember": ev.od_remember,
        "od_rangeable": ev.od_rangeable,
        "od_warmup": ev.od_warmup, "det_true_m": ev.od_truth[m.detection], "det_published_m": ev.od_r[m.detection],
        "ds_t": ev.ds_t, "ds_state": ev.ds_state, "ds_published_m": ev.ds_published_m, "ds_sigma_m": ev.ds_sigma_m,
        "ds_estimate_m": ev.ds_estimate_m, "ds_truth_arrival": ev.ds_truth_arrival, "ds_truth_exposure": ev.ds_truth_exposure,
        "ds_max_m": ev.ds_max_m, "nees_exposure": nees_samples(ev, "exposure"), "nees_arrival": nees_samples(ev, "arrival"),
        "nees_exposure_t": fwd["t"], "nees_exposure_error_m": fwd["error_m"], "nees_exposure_sigma_m": fwd["sigma_m"],
        "nees_exposure_stretch": stretch_labels(fwd["t"], ev.config.nees_gap_s).astype(np.int32),
        "obstacle_names": np.array(ev.obstacle_names, dtype="U128"),
    }


def _jsonable(x):
    """NaN/inf → None, numpy scalars → Python, recursively."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return [_jsonable(v) for v in x.tolist()]
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        v = float(x)
        return v if math.isfinite(v) else None
    return x
