"""Campaign report: plots (matplotlib, Agg) and a markdown index.

``write_report(report_dir, campaign, series)`` writes into ``report_dir``:

* ``range_vs_truth.png`` — range estimate vs truth over time with ±σ bands, every run overlaid:
  the forward DISTANCE_SENSOR (``obstacle="forward"``: estimate = published + k·σ, its σ band, the
  conservative published value, the forward truth at arrival), or one named obstacle (nearest
  true distance over its sectors, nearest published range over them, and the forward estimate ±σ
  while the forward sector belongs to it);
* ``error_vs_range.png`` — range error against the true range L, pooled over runs: signed error
  of every detection and of the forward estimate, binned median and 5–95 % band; |error| in % of L;
* ``radar.png`` — polar sector plots of one run at chosen times: truth vs published (ranges,
  "clear", unknown left blank); over 360° with the out-of-view sectors hatched when the truth
  covers them;
* ``latency_hist.png`` — exposure → message latency, pooled;
* ``nees.png`` — consistency of the forward σ: the pooled normalized errors against the standard
  normal (±σ / ±2σ coverage) and every run's NEES mean with its band for n_eff beside the pooled
  mean and band (each run's own ``nees.png`` shows its error and NEES over time);
* ``index.md`` — the tables of campaign.json (targets ✓/✗, pooled rates, per-run mean ± std,
  in view / out of view (docs/derivations/obstacle_map.md), detection and unknown by true-range bin,
  remembered obstacles, range error by bin, time to the first valid range per obstacle, latency, NEES with the pooled
  n_eff and its band, ±2σ coverage, runs) linking
  the plots and each run's score.md.

Only reads what it is handed (campaign dict, per-run series arrays); no figure here comes from
anywhere but those arrays.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from flightsim.score.config import REP_CLEAR, REP_RANGE, SECTOR_DEG, TRUTH_OBSTACLE
from flightsim.score.markdown import (claims_by_source_lines, mark, nees_lines, remembered_errors_text, remembered_rangeable_text,
                                      unknown_by_reason_lines)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _empty(ax, text: str = "no scored runs") -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4")


# ---------------------------------------------------------------------- plots -------------------
def plot_range_vs_truth(series: dict[int, dict], path: Path, obstacle: str = "forward") -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 5.5))
    drawn = False
    cmap = plt.get_cmap("tab10")
    for n, (seed, s) in enumerate(sorted(series.items())):
        c = cmap(n % 10)
        t0 = float(s["t0"])
        lab = f"seed {seed}" if n < 6 else None
        ds_t = np.asarray(s["ds_t"]) - t0
        est, sig = np.asarray(s["ds_estimate_m"]), np.asarray(s["ds_sigma_m"])
        if obstacle == "forward":
            truth_t, truth = ds_t, np.asarray(s["ds_truth_arrival"])
            sel = np.ones(len(ds_t), bool)
            pub_t, pub = ds_t, np.asarray(s["ds_published_m"])
        else:
            names = [str(x) for x in s["obstacle_names"]]
            if obstacle not in names:
                continue
            k = names.index(obstacle)
            cells = (np.asarray(s["od_label"]) == k) & (np.asarray(s["od_tcls"]) == TRUTH_OBSTACLE)
            od_t = np.asarray(s["od_t"]) - t0
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: the obstacle is not in range then
                truth = np.nanmin(np.where(cells, np.asarray(s["od_truth"], float), np.nan), axis=1) if cells.size else np.zeros(0)
                rng = cells & (np.asarray(s["od_rep"]) == REP_RANGE)
                pub = np.nanmin(np.where(rng, np.asarray(s["od_cm"]) / 100.0, np.nan), axis=1) if rng.size else np.zeros(0)
            truth_t = pub_t = od_t
            j = np.searchsorted(np.asarray(s["od_t"]), np.asarray(s["ds_t"]) + 1e-9, side="right") - 1
            sel = np.zeros(len(j), bool)
            if len(j) and len(od_t):
                sel = (j >= 0) & (np.asarray(s["od_label"])[np.maximum(j, 0), 0] == k)
        ax.plot(truth_t, truth, color="k", lw=1.0, alpha=0.6, label="truth" if n == 0 else None)
        ok = sel & np.isfinite(est) & np.isfinite(sig)
        if np.any(ok):
            e = np.where(ok, est, np.nan)
            ax.plot(ds_t, e, color=c, lw=1.0, label=None if lab is None else f"{lab}: estimate ± σ")
            ax.fill_between(ds_t, e - np.where(ok, sig, np.nan), e + np.where(ok, sig, np.nan), color=c, alpha=0.15, lw=0)
            drawn = True
        if np.any(np.isfinite(pub)):
            ax.plot(pub_t, pub, ".", ms=2, color=c, alpha=0.5, label=None if lab is None else f"{lab}: published")
            drawn = True
    if not drawn:
        _empty(ax, "no ranges for this obstacle" if series else "no scored runs")
    what = "forward sector (DISTANCE_SENSOR)" if obstacle == "forward" else f"obstacle {obstacle!r}"
    ax.set_title(f"Range estimate ± σ vs truth, {what}; dots: conservative published value")
    ax.set_xlabel("time since the first frame, s")
    ax.set_ylabel("horizontal range, m")
    if drawn:
        ax.legend(fontsize=8, loc="upper right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _binned(x: np.ndarray, y: np.ndarray, width: float = 2.5):
    if x.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)
    edges = np.arange(0.0, float(np.nanmax(x)) + width, width)
    idx = np.digitize(x, edges) - 1
    cs, med, lo, hi = [], [], [], []
    for i in range(len(edges)):
        v = y[idx == i]
        if v.size >= 5:
            cs.append(edges[i] + width / 2)
            med.append(np.median(v))
            lo.append(np.percentile(v, 5))
            hi.append(np.percentile(v, 95))
    return np.array(cs), np.array(med), np.array(lo), np.array(hi)


def plot_error_vs_range(series: dict[int, dict], path: Path) -> Path:
    plt = _plt()
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 8), sharex=True)
    cat = lambda k: np.concatenate([np.asarray(s[k], float).reshape(-1) for s in series.values()]) if series else np.zeros(0)  # noqa: E731
    T, r = cat("det_true_m"), cat("det_published_m")
    dT, dest, dstate = cat("ds_truth_exposure"), cat("ds_estimate_m"), cat("ds_state")
    ok = np.isfinite(dT) & np.isfinite(dest) & (dstate == REP_RANGE)
    dT, dest = dT[ok], dest[ok]
    if T.size == 0 and dT.size == 0:
        _empty(a1)
        _empty(a2)
    rng = np.random.default_rng(0)
    if T.size:
        sub = rng.choice(T.size, min(T.size, 20000), replace=False)
        a1.plot(T[sub], (r - T)[sub], ".", ms=2, alpha=0.2, color="tab:blue", label="published (conservative), all sectors")
        c, m, lo, hi = _binned(T, r - T)
        a1.plot(c, m, "-", color="tab:blue", lw=2)
        a1.fill_between(c, lo, hi, color="tab:blue", alpha=0.15)
        c, m, lo, hi = _binned(T, 100 * np.abs(r - T) / T)
        a2.plot(c, m, "-o", ms=3, color="tab:blue", label="published, median")
        a2.fill_between(c, 0 * c, hi, color="tab:blue", alpha=0.1, label="published, 95th percentile")
    if dT.size:
        a1.plot(dT, dest - dT, ".", ms=3, alpha=0.4, color="tab:orange", label="forward estimate (published + k·σ)")
        c, m, lo, hi = _binned(dT, dest - dT)
        a1.plot(c, m, "-", color="tab:orange", lw=2)
        c, m, lo, hi = _binned(dT, 100 * np.abs(dest - dT) / dT)
        a2.plot(c, m, "-o", ms=3, color="tab:orange", label="forward estimate, median")
    a1.axhline(0, color="k", lw=0.8)
    a1.set_ylabel("error (value − true), m")
    a1.set_title("Range error vs true range L (lines: binned median; band: 5–95 %), pooled over runs")
    a2.set_ylabel("|error|, % of L")
    a2.set_xlabel("true horizontal range L, m")
    for a in (a1, a2):
        a.grid(alpha=0.3)
        if T.size or dT.size:
            a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def radar_times(s: dict, n: int = 4) -> list[float]:
    t = np.asarray(s["od_t"]) - float(s["t0"])
    if t.size == 0:
        return []
    return [float(x) for x in np.linspace(t[-1] * 0.25, t[-1], n)]


def plot_radar(s: dict | None, seed: int | None, path: Path, times: list[float] | None = None) -> Path:
    plt = _plt()
    times = list(times) if times else (radar_times(s) if s is not None else [])
    k = max(1, len(times))
    cols = min(k, 4)
    rows = math.ceil(k / cols)
    fig = plt.figure(figsize=(4.2 * cols, 2.9 * rows + 1.0))
    if s is None or not times:
        ax = fig.add_subplot(1, 1, 1)
        _empty(ax)
        ax.axis("off")
    else:
        t = np.asarray(s["od_t"]) - float(s["t0"])
        scored = np.asarray(s["od_scored"], bool)
        theta = np.radians(np.arange(72) * SECTOR_DEG)
        width = np.radians(SECTOR_DEG)
        for i, tau in enumerate(times):
            ax = fig.add_subplot(rows, cols, i + 1, projection="polar")
            ax.set_theta_zero_location("N")
            ax.set_theta_direction(-1)
            cand = np.flatnonzero(scored & (t >= tau - 1e-9))
            j = cand[0] if cand.size else (np.flatnonzero(scored)[-1] if np.any(scored) else None)
            if j is None:
                _empty(ax, "no message")
                continue
            mx = float(s["od_max_m"][j])
            T = np.asarray(s["od_truth"][j], float)
            rep = np.asarray(s["od_rep"][j])
            r = np.asarray(s["od_cm"][j]) / 100.0
            seen = ~np.isnan(T)
            fin = np.isfinite(T)
            full = "od_in_view" in s  # a 360° truth: draw every sector, shade the ones out of view
            view = np.asarray(s["od_in_view"][j], bool) if full else seen
            ax.bar(theta[seen & ~fin], mx, width=width, color="0.92", edgecolor="none", label="truth: nothing within range")
            if full and np.any(~view):
                ax.bar(theta[~view], mx, width=width, color="none", edgecolor="0.75", hatch="///", lw=0,
                       label="out of the camera's view")
            clear = rep == REP_CLEAR
            if np.any(clear):
                ax.bar(theta[clear], mx, width=width, color="tab:green", alpha=0.35, label="published: clear")
            arc = np.linspace(-width / 2, width / 2, 6)
            rr = rep == REP_RANGE
            for k_, (idx, val, col, lw) in enumerate(((np.flatnonzero(fin), T, "k", 2.5), (np.flatnonzero(rr), r, "tab:red", 1.6))):
                for q in idx:
                    ax.plot(theta[q] + arc, np.full(arc.shape, min(val[q], mx * 1.05)), "-", color=col, lw=lw,
                            label=(None if q != idx[0] else ("truth: nearest obstacle" if k_ == 0 else "published range")))
            ax.set_rticks(np.arange(10.0, mx + 1e-9, 10.0))
            ax.tick_params(labelsize=7)
            ax.set_rmax(mx * 1.05)
            if not full:
                ax.set_thetamin(-90)
                ax.set_thetamax(90)
            ax.set_title(f"t = {t[j]:.2f} s", fontsize=9)
        seen_labels: dict[str, object] = {}
        for ax_ in fig.axes:
            for h_, l_ in zip(*ax_.get_legend_handles_labels()):
                seen_labels.setdefault(l_, h_)
        labels, handles = list(seen_labels), list(seen_labels.values())
        if handles:
            fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8, frameon=False)
        fig.suptitle(f"Sectors, body frame (0° = forward, clockwise), seed {seed}: truth at arrival vs published")
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_latency(series: dict[int, dict], path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    lat = np.concatenate([np.asarray(s["od_latency_s"], float) for s in series.values()]) if series else np.zeros(0)
    lat = lat[np.isfinite(lat)] * 1000.0
    if lat.size:
        lo, hi = float(lat.min()), float(lat.max())
        bins = np.linspace(lo - 0.5, hi + 0.5, 41) if hi - lo > 1 else np.linspace(lo - 2, hi + 2, 9)
        ax.hist(lat, bins=bins, color="tab:blue", alpha=0.8)
        for q, ls in ((50, "-"), (99, "--")):
            v = float(np.percentile(lat, q))
            ax.axvline(v, color="k", ls=ls, lw=1, label=f"p{q} {v:.1f} ms")
        ax.legend()
    else:
        _empty(ax, "no exposure times known")
    ax.set_xlabel("exposure → message stamp, ms")
    ax.set_ylabel("OBSTACLE_DISTANCE messages")
    ax.set_title(f"Latency, pooled over runs (n = {lat.size})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_nees(series: dict[int, dict], campaign: dict, path: Path) -> Path:
    """Pooled consistency of the forward σ: the normalized errors (estimate − truth)/σ of every run
    against the standard normal, with the ±σ / ±2σ coverage; and each run's NEES mean with its band
    for n_eff (the verdict) and, thin, for n independent samples, beside the pooled mean and band."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.8), gridspec_kw={"width_ratios": [1, 1.3]})
    z = [np.asarray(s["nees_exposure_error_m"], float) / np.asarray(s["nees_exposure_sigma_m"], float)
         for s in series.values() if "nees_exposure_error_m" in s]
    z = np.concatenate(z) if z else np.zeros(0)
    z = z[np.isfinite(z)]
    ne = (campaign.get("aggregate") or {}).get("nees") or {}
    if z.size:
        lim = max(4.0, min(12.0, float(np.percentile(np.abs(z), 99.5)) * 1.1))
        a1.hist(np.clip(z, -lim, lim), bins=np.linspace(-lim, lim, 61), density=True, color="tab:blue", alpha=0.6,
                label=f"(estimate − truth) / σ, n = {z.size}")
        g = np.linspace(-lim, lim, 400)
        a1.plot(g, np.exp(-0.5 * g * g) / math.sqrt(2 * math.pi), "k-", lw=1.2, label="standard normal (σ right)")
        for k_, ls in ((1, ":"), (2, "--")):
            a1.axvline(k_, color="0.3", ls=ls, lw=0.9)
            a1.axvline(-k_, color="0.3", ls=ls, lw=0.9)
        cov = ne.get("coverage") or {}
        if cov.get("rate_2sigma") is not None:
            a1.set_title(f"within ±σ {100 * cov['rate_1sigma']:.1f} % (normal 68.3 %), within ±2σ "
                         f"{100 * cov['rate_2sigma']:.1f} % (95.4 %)", fontsize=10)
        a1.legend(fontsize=8, loc="upper left")
    else:
        _empty(a1, "no forward range with a known σ and truth")
    a1.set_xlabel("normalized forward error (at exposure)")
    a1.set_ylabel("density")
    runs = [r for r in campaign.get("runs", []) if (r.get("key_figures") or {}).get("nees_mean") is not None]
    if runs:
        for i, r in enumerate(runs):
            kf = r["key_figures"]
            b = kf.get("nees_band")
            col = "tab:green" if kf.get("nees_consistent") else "tab:red"
            if b:
                a2.plot([i, i], b, "-", color=col, lw=4, alpha=0.35, solid_capstyle="butt")
            a2.plot(i, kf["nees_mean"], "o", color=col, ms=5)
        band = ne.get("band")
        if band:
            a2.axhspan(band[0], band[1], color="tab:purple", alpha=0.12,
                       label=f"pooled band, n_eff = {ne['n_eff']:.1f}: mean {ne['mean']:.2f} {mark(ne.get('consistent'))}")
        bi = ne.get("band_independent")
        if bi:
            a2.axhline(bi[0], color="tab:purple", ls="--", lw=0.8, label=f"pooled band as if independent (n = {ne['n']})")
            a2.axhline(bi[1], color="tab:purple", ls="--", lw=0.8)
        if ne.get("mean") is not None:
            a2.axhline(ne["mean"], color="tab:purple", lw=1.2)
        a2.axhline(1.0, color="k", lw=0.8)
        a2.set_xticks(range(len(runs)))
        a2.set_xticklabels([str(r["seed"]) for r in runs], rotation=90 if len(runs) > 20 else 0, fontsize=7)
        a2.set_yscale("log")
        vals = [v for r in runs for v in [r["key_figures"]["nees_mean"], *(r["key_figures"].get("nees_band") or [])]]
        vals += [v for v in [ne.get("mean"), *(band or []), *(bi or [])] if v is not None]
        vals = [v for v in vals if v is not None and v > 0]
        lo_y, hi_y = (min(vals) / 1.4, max(vals) * 1.4) if vals else (0.1, 10.0)
        a2.set_ylim(lo_y, hi_y)
        from matplotlib.ticker import FormatStrFormatter, NullFormatter

        a2.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        # minor ticks labelled only within about a decade (else the labels run into each other)
        a2.yaxis.set_minor_formatter(FormatStrFormatter("%g") if hi_y / lo_y < 15 else NullFormatter())
        a2.tick_params(axis="y", which="minor", labelsize=7)
        a2.legend(fontsize=8, loc="best")
        a2.set_title("NEES mean per run with its n_eff band (green: inside, red: outside)", fontsize=10)
    else:
        _empty(a2, "no run with forward NEES samples")
    a2.set_xlabel("seed")
    a2.set_ylabel("NEES mean (log)")
    for a in (a1, a2):
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------- index.md ----------------
def _pc(v, d: int = 2) -> str:
    """A share as "12.34 %"; "–" where there is none (None, or NaN: a share of no cells)."""
    return "–" if v is None or v != v else f"{100 * v:.{d}f} %"


def _f(v, fmt: str = "{:.2f}") -> str:
    return "–" if v is None else fmt.format(v)


def _ms(d: dict, fmt: str = "{:.2f}", pct: bool = False) -> str:
    if not d or d.get("mean") is None:
        return "–"
    if pct:
        return f"{100 * d['mean']:.2f} ± {100 * (d['std'] or 0):.2f} %"
    return f"{fmt.format(d['mean'])} ± {fmt.format(d['std'] or 0)}"


def mean_std_text(d: dict | None, fmt: str = "{:.2f}", with_max: bool = True) -> str:
    """``mean ± std (min …, max …)`` of a :func:`flightsim.campaign._mean_std` summary; "–" when empty."""
    if not d or not d.get("n"):
        return "–"
    tail = f"min {fmt.format(d['min'])}" + (f", max {fmt.format(d['max'])}" if with_max else "")
    return f"{fmt.format(d['mean'])} ± {fmt.format(d['std'])} ({tail})"


def _avoidance_lines(c: dict) -> list[str]:
    """The closed-loop outcome pooled over the runs (flightsim.outcome; campaign.pool_outcomes)."""
    av = (c.get("aggregate") or {}).get("avoidance")
    if not av:
        return []
    ci, fci = av["collision_ci95"], av["false_stop_ci95"]
    ms = mean_std_text

    return ["## Avoidance outcome (closed loop), pooled over runs", "",
            f"The simulated autopilot's `{c.get('avoidance')}` avoidance flew on the companion's ranges (each run's "
            "`avoidance.png`: track, the autopilot's obstacle data where it stopped, clearance and speeds).", "",
            "| outcome | value |", "|---|---|",
            f"| collisions | {av['collisions']} of {av['runs']} ({_pc(av['collision_rate'], 1)}; 95 % CI {_pc(ci[0], 1)}–{_pc(ci[1], 1)}) |",
            f"| stopped short of the obstacle | {av['stopped_short']} of {av['runs']} |",
            f"| stop clearance, m (body to obstacle, along the demand) | {ms(av['stop_clearance_m'])} |",
            f"| min clearance, m | {ms(av['min_clearance_m'])} |",
            f"| false stops | {av['false_stops']} of {av['runs']} (95 % CI {_pc(fci[0], 1)}–{_pc(fci[1], 1)}) |",
            f"| progress along the route | {ms(av['progress'], '{:.1%}')} |",
            f"| reached the goal | {av['reached_goal']} of {av['runs']} |",
            f"| max speed, m/s | {ms(av['max_speed_mps'])} |",
            f"| obstacle data held while the pilot pushed | {ms(av['data_while_pushing'], '{:.1%}')} |", ""]


def index_markdown(c: dict, files: dict[str, Path], report_dir: Path) -> str:
    a = c["aggregate"]
    L = [f"# Campaign: {c['scenario_name']}", "",
         f"Scenario `{c['scenario']}`, mode **{c['mode']}**, seeds {c['seeds'][0]}…{c['seeds'][-1]} ({len(c['seeds'])} runs, "
         f"{a['runs_ok']} scored, {a['runs_failed']} failed), {c['workers']} workers, {c['wall_s']:.0f} s wall; processing "
         f"time {c['fixed_processing_ms']:g} ms per frame; companion config `{c['companion_config']}`.", "",
         "Reproduce: `flightsim campaign " + f"{c['scenario']} --runs {len(c['seeds'])} --seed0 {c['seeds'][0]} "
         f"--mode {c['mode']} --fixed-processing-ms {c['fixed_processing_ms']:g}"
         + (f" --avoidance {c['avoidance']}" if c.get("avoidance") not in (None, "none") else "") + " --out DIR`.", "",
         "Definitions (cells, tolerance, false obstacle, dangerous clear, NEES, latency): the module docstring of "
         "`flightsim/score/__init__.py`, repeated at the end of every run's score.md.", "",
         *_avoidance_lines(c),
         f"## Targets, pooled over runs (after a {c.get('score_config', {}).get('warmup_s', 0):g} s warm-up; "
         f"{a.get('warmup_messages_excluded', 0)} messages excluded)", "",
         "| target | pooled | threshold | n | met | runs meeting it |", "|---|---|---|---|---|---|"]
    for t in a["targets"]:
        L.append(f"| {t['name']} | {_pc(t['pooled'])} | {t['op']} {100 * t['threshold']:g} % | {t['n']} | {mark(t['met'])} | "
                 f"{t['runs_met']} of {t['runs_scored']} |")
    cells, pr, per = a["cells"], a["pooled_rates"], a["per_run_rates"]
    L += ["", "## Rates", "", "| rate | pooled | per run (mean ± std) | cells |", "|---|---|---|---|"]
    rows = (("detection (range in an obstacle cell)", "detection", "detections", "obstacle"),
            ("valid range (within tolerance)", "valid_range", "valid_ranges", "obstacle"),
            ("dangerous clear", "dangerous_clear", "dangerous_clears", "obstacle"),
            ("too near (false obstacle in an obstacle cell)", "too_near", "too_near", "obstacle"),
            ("over range", "over_range", "over_range", "obstacle"),
            ("false obstacle in clear cells", "false_obstacle_clear_cells", "false_obstacles_clear_cells", "clear"),
            ("messages without a false obstacle in clear sectors", "messages_without_false_obstacle",
             "messages_without_false_obstacle", "messages_eligible_no_false"))
    for label, key, num, den in rows:
        L.append(f"| {label} | {_pc(pr.get(key))} | {_ms(per.get(key), pct=True)} | {cells.get(num, 0)} / {cells.get(den, 0)} |")
    civ, cov = a.get("cells_in_view") or {}, a.get("cells_out_of_view") or {}
    piv, pov = a.get("pooled_rates_in_view") or {}, a.get("pooled_rates_out_of_view") or {}
    if civ or cov:
        L += ["", "In view and out of view (out of view only cells with a claim count; unknown there is neutral), pooled:", "",
              "| rate | in view | cells | out of view | cells |", "|---|---|---|---|---|"]
        for label, key, num, den in rows[:6]:
            L.append(f"| {label} | {_pc(piv.get(key))} | {civ.get(num, 0)} / {civ.get(den, 0)} | {_pc(pov.get(key))} | "
                     f"{cov.get(num, 0)} / {cov.get(den, 0)} |")
        L.append(f"| unknown in obstacle cells | {_pc(piv.get('unknown_in_obstacle_cells'))} | "
                 f"{civ.get('unknown_in_obstacle_cells', 0)} / {civ.get('obstacle', 0)} | neutral | "
                 f"{cov.get('unknown_neutral', 0)} cells |")
    rem = a.get("remembered")
    if rem:
        L += ["", f"Remembered obstacles out of view: {rem['cells']} cells, within tolerance {rem['within_tolerance']} "
              f"({_pc(rem['rate'])}), unknown {rem['unknown']}, dangerous clears {rem['dangerous_clears']}"
              + remembered_errors_text(rem) + remembered_rangeable_text(rem) + "."]
    rg = a.get("rangeable")
    if rg and rg.get("obstacle_cells_in_view"):
        L += ["", f"Rangeable in view (the single camera's ceiling: the cell's point seen within {rg.get('window_s', 0):g} s from a "
              f"place with ≥ {rg.get('parallax_deg', 0):g}° parallax or ≥ {100 * (rg.get('scale') or 0):g} % change of distance; "
              f"geometry only, a diagnostic): {rg['cells']} of {rg['obstacle_cells_in_view']} in-view obstacle cells "
              f"({_pc(rg['share'])}); within tolerance {rg['within_tolerance']} of them ({_pc(rg['rate'])}), unknown "
              f"{rg['unknown']}; within tolerance among the others: {rg['not_rangeable_within_tolerance']}."]
    cbs = a.get("claims_by_source")
    if cbs:
        L += [""] + claims_by_source_lines(cbs)
    ubr = a.get("unknown_by_reason")
    if ubr:
        L += [""] + unknown_by_reason_lines(ubr)
    dbr = a.get("detection_by_range")
    if dbr:
        L += ["", "## Detection by true range, pooled", "",
              "Detection = a range within tolerance; out of view all obstacle cells are listed (unknown included), "
              "'of claimed' = within tolerance among cells with a range or clear.", ""]
        for key, label in (("in_view", "In view"), ("out_of_view", "Out of view")):
            L += [f"{label}:", "", "| true range | obstacle cells | detection | range reported | unknown | clear (dangerous) | of claimed |",
                  "|---|---|---|---|---|---|---|"]
            for b in dbr.get(key, []):
                L.append(f"| {b['bin']} | {b['obstacle_cells']} | {_pc(b['valid_rate'], 1)} | {_pc(b['range_rate'], 1)} | "
                         f"{_pc(b['unknown_rate'], 1)} | {b['clear']} | {_pc(b['valid_of_claimed'], 1)} |")
            L.append("")
    L += ["", f"Ranges beyond the truth horizon (unverifiable): {cells.get('unverifiable_beyond_truth', 0)}; claims in "
          f"unseen sectors: {cells.get('unscored_claims', 0)}; first claim {_ms(a['first_claim_at_s'])} s after the first frame.", ""]
    L += ["## Range error (value − true) by true range, pooled", ""]
    for key, label in (("published_all_sectors", "Conservative published value, all sectors"),
                       ("published_forward", "Conservative published value, forward DISTANCE_SENSOR"),
                       ("estimate_forward", "Estimate (published + k·σ), forward DISTANCE_SENSOR")):
        L += [f"{label}:", "", "| true range | n | bias m | mean abs m | median abs m | p95 abs m | mean abs % | median abs % |",
              "|---|---|---|---|---|---|---|---|"]
        for r in a["range_error"][key]:
            L.append(f"| {r['bin']} | {r['n']} | {_f(r['bias_m'])} | {_f(r['mae_m'])} | {_f(r['median_abs_m'])} | "
                     f"{_f(r['p95_abs_m'])} | {_f(r['mae_pct'], '{:.1f}')} | {_f(r['median_abs_pct'], '{:.1f}')} |")
        L.append("")
    L += ["## Obstacles: time to the first valid range", "",
          "| obstacle | runs in range | in range at s | time to first valid s (mean ± std) | runs never valid | detected share |",
          "|---|---|---|---|---|---|"]
    for o in a["obstacles"]:
        L.append(f"| {o['name']} | {o['runs_in_range']} | {_ms(o['in_range_at_s'])} | {_ms(o['time_to_first_valid_s'])} | "
                 f"{o['runs_never_valid']} | {_ms(o['detected_fraction'], pct=True)} |")
    la, ne = a["latency"], a["nees"]
    L += ["", "## Latency", "",
          f"Latency exposure → message (n = {la['n']}): p50 {_f(la['p50_ms'], '{:.1f}')} ms, p95 {_f(la['p95_ms'], '{:.1f}')} ms, "
          f"p99 {_f(la['p99_ms'], '{:.1f}')} ms, max {_f(la['max_ms'], '{:.1f}')} ms.", "",
          "## NEES and coverage of the forward σ, pooled over runs", "",
          "Every run's NEES series has its own effective sample size n_eff (autocorrelation within the run's gap-free "
          "stretches; each run's score.md and nees.png); the runs are independent, so the pooled mean has "
          "n_eff = N² / Σ (n_run² / n_eff,run) — the sum of the runs' n_eff when they share one correlation time"
          + (f" (here the plain sum would be {_f(ne.get('n_eff_sum_of_runs'), '{:.1f}')})" if ne.get("n_eff_sum_of_runs") else "")
          + ".", ""]
    L += nees_lines(ne, "Pooled, against the truth at exposure")
    L += [f"Per run: mean {_ms(ne['per_run_mean'])}; consistent with its own n_eff band in {ne.get('runs_consistent', '–')} of "
          f"{ne.get('runs_with_samples', '–')} runs with forward samples.  At arrival, pooled: n = {ne['arrival']['n']}, "
          f"n_eff = {_f(ne['arrival'].get('n_eff'), '{:.1f}')}, mean {_f(ne['arrival']['mean'])}.", ""]
    lm = a.get("landmarks")
    if lm:
        from flightsim.score.landmarks import markdown as landmark_table

        L += ["## Each landmark against the truth (landmark log)", "",
              f"Every converged landmark of every logged frame of {lm['runs']} runs, its measured ray cast from the true camera "
              "into the world: z = (range − true range) / σ by true range (flightsim/score/landmarks.py; samples are "
              "landmark-frames, correlated within a landmark).", "", landmark_table(lm["bins"]), ""]
    L += ["## Plots", ""]
    for key, title in (("range_vs_truth", "Range estimate ± σ vs truth"), ("error_vs_range", "Error vs true range L"),
                       ("nees", "Normalized forward error and NEES per run"),
                       ("radar", "Sector radar"), ("latency", "Latency histogram")):
        if key in files:
            L += [f"### {title}", "", f"![{title}]({files[key].name})", ""]
    L += ["## Runs", "", "| seed | status | detection | detection in view (within tol.) | remembered | no false obstacle (msgs) | "
          "dangerous clear | latency p50 ms | NEES (n_eff, in its band) | within ±2σ | wall s | score |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in c["runs"]:
        kf = r.get("key_figures") or {}
        rel = Path(r["dir"])
        try:
            rel = Path("..") / rel.relative_to(report_dir.parent)
        except ValueError:
            pass
        link = f"[score.md]({rel.as_posix()}/score.md)" if r["status"] == "ok" else (r.get("error") or "").replace("|", "/")[:120]
        L.append(f"| {r['seed']} | {r['status']} | {_pc(kf.get('detection'), 1)} | {_pc(kf.get('detection_in_view'), 1)} | "
                 f"{_pc(kf.get('remembered'), 1)} | {_pc(kf.get('messages_without_false_obstacle'), 1)} | "
                 f"{_pc(kf.get('dangerous_clear'))} | {_f(kf.get('latency_p50_ms'), '{:.1f}')} | {_f(kf.get('nees_mean'))}"
                 + (f" ({kf['nees_n_eff']:.1f}, {mark(kf.get('nees_consistent'))})" if kf.get("nees_n_eff") else "")
                 + f" | {_pc(kf.get('coverage_2sigma'), 1)} | {_f(r.get('wall_s'), '{:.0f}')} | {link} |")
    return "\n".join(L) + "\n"


def write_report(report_dir: str | Path, campaign: dict, series: dict[int, dict], *, obstacle: str = "forward",
                 times: list[float] | None = None) -> dict[str, Path]:
    """Plots and index.md (module docstring); returns the files written by key."""
    d = Path(report_dir)
    d.mkdir(parents=True, exist_ok=True)
    files = {
        "range_vs_truth": plot_range_vs_truth(series, d / "range_vs_truth.png", obstacle),
        "error_vs_range": plot_error_vs_range(series, d / "error_vs_range.png"),
    }
    first = min(series) if series else None
    files["radar"] = plot_radar(series[first] if first is not None else None, first, d / "radar.png", times)
    files["latency"] = plot_latency(series, d / "latency_hist.png")
    files["nees"] = plot_nees(series, campaign, d / "nees.png")
    idx = d / "index.md"
    idx.write_text(index_markdown(campaign, files, d), encoding="utf-8")
    files["index"] = idx
    return files
