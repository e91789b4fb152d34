"""Formatting of benchmark results: the machine-readable JSON forms and the markdown tables."""

from __future__ import annotations

import datetime
import platform

from bench.seed004 import EVAL_FRAMES, PAPER

SEED004_KEYS = (
    "ekf_anchored_mean_abs_m", "ekf_landmark_mean_abs_m", "tri_longest_mean_abs_m",
    "tri_consecutive_mean_abs_m", "crlb_mean_m", "nees_mean", "nees_band",
)
LABELS = {
    "ekf_anchored": "anchored inverse-depth EKF (§3.4)",
    "ekf_landmark": "seed-000 EKF (§3.5)",
    "tri_longest": "triangulation, longest baseline",
    "tri_consecutive": "triangulation, consecutive frames",
}


def _f(v, digits=2) -> str:
    if v is None:
        return "–"
    if isinstance(v, float) and abs(v) >= 1000:
        return f"{v:,.0f}"
    return f"{v:.{digits}f}"


def seed004_json(res: dict) -> dict:
    """The documented machine-readable form: every σ keeps the fixed key names (plus details)."""
    out = {"runs": res["runs"], "scenario": res["scenario"]}
    for group in ("sigma_px", "with_gyro_model"):
        out[group] = {}
        for sigma, r in res[group].items():
            out[group][sigma] = {k: r[k] for k in SEED004_KEYS} | {
                "by_frame": r["by_frame"],
                "tri_consecutive_median_abs_m": r["tri_consecutive_median_abs_m"],
                "ekf_anchored_per_point_mean_abs_m": r["ekf_anchored_per_point_mean_abs_m"],
                "convergence_frame_10pct": r["convergence_frame_10pct"],
                **{k: r[k] for k in ("nees_per_point", "nees_median", "nees_trimmed_mean", "nees_trim_share", "nees_samples",
                                     "chi2_median", "chi2_trimmed_mean")},
            }
    return out


def seed004_markdown(res: dict, runs: int) -> str:
    sc = res["scenario"]
    lines = [
        f"Scenario: {sc['width']}×{sc['height']} px, {sc['hfov_deg']:g}° FOV (f = {sc['focal_px']:.1f} px), "
        f"{sc['fps']:g} fps, {sc['speed_mps']:g} m/s along the optical axis for {sc['duration_s']:g} s, "
        f"points at x = {', '.join(f'{x:g}' for x in sc['lateral_m'])} m, {sc['distance_m']:g} m ahead. "
        f"{runs} Monte Carlo runs per case. Mean absolute range error (eq. 15) over the six points, metres, "
        "from the camera of that frame (points that have left the view keep their last estimate). "
        "Before convergence an estimate can sit anywhere its wide prior allows (capped at max_range_m); "
        "the converged share and the filter's σ say so, which is why early means are large."
        + ("" if res.get("ekf_iterations", 2) == 2 else
           f" Anchored EKF with {res['ekf_iterations']} iteration(s) of its update (`--ekf-iterations`; the benchmark's default: 2).")
        + ("" if res.get("tri_max_rel_sigma", 0.3) == 0.3 else
           f" Triangulation gate max_rel_sigma = {res['tri_max_rel_sigma']:g} (`--tri-max-rel-sigma`; shipped and default: 0.3).")
        + (" Anchored EKF with its batch refinement (`[ekf_anchored] refine_max_obs = 128`, an option the flight configurations"
           " leave off; `--no-refine` measures the EKF alone)." if res.get("refine", True)
           else " Anchored EKF without its batch refinement (`--no-refine`), as the flight configurations ship it."),
        "",
    ]
    for group, title in (("sigma_px", "Camera poses exact, pixel noise only"),
                         ("with_gyro_model", f"With the paper's gyro model on the attitude (bias ≤ {sc['gyro_bias_deg_s']:g} °/s, random {sc['gyro_random_deg_s']:g} °/s)")):
        lines += [f"#### {title}", ""]
        for sigma, r in res[group].items():
            bf = r["by_frame"]
            hdr = "| σ = " + sigma + " px | " + " | ".join(f"frame {k}" for k in EVAL_FRAMES) + " | paper (frame 150) |"
            lines += [hdr, "|---|" + "---:|" * (len(EVAL_FRAMES) + 1)]
            for m, label in LABELS.items():
                paper = PAPER["ekf_final"].get(sigma) if m.startswith("ekf") else PAPER["tri"].get(sigma)
                cells = []
                for k in EVAL_FRAMES:
                    v = bf[str(k)][f"{m}_mean_abs_m"]
                    avail = bf[str(k)][f"{m}_available"]
                    cells.append(_f(v) + ("" if avail > 0.999 else f" ({avail:.0%} of points)"))
                lines.append(f"| {label} | " + " | ".join(cells) + f" | {_f(paper, 0)} |")
            lines.append("| Cramér–Rao bound (σ of range) | " + " | ".join(_f(bf[str(k)]["crlb_mean_m"]) for k in EVAL_FRAMES) + " | |")
            lines.append("| share of anchored-EKF estimates flagged converged | " + " | ".join(f"{bf[str(k)]['ekf_anchored_converged_share']:.0%}" for k in EVAL_FRAMES) + " | |")
            lo, hi = r["nees_band"]
            crlb = r["crlb_mean_m"]
            best = min(r["ekf_anchored_mean_abs_m"], r["ekf_landmark_mean_abs_m"])
            ratio = f"{best / crlb:.2f} × the bound" if crlb > 0 else "bound is 0 without noise"
            conv = r["convergence_frame_10pct"]["ekf_anchored"]
            lines += [
                "",
                f"Anchored EKF NEES at frame 150: {r['nees_mean']:.2f} (95 % band for the mean of χ²₃: [{lo:.2f}, {hi:.2f}]). "
                f"Better EKF at frame 150: {ratio}. Consecutive-frame triangulation median |error|: {_f(r['tri_consecutive_median_abs_m'])} m. "
                f"Anchored EKF per point at frame 150 (x = {', '.join(f'{x:g}' for x in r['lateral_m'])}): "
                f"{', '.join(_f(v) for v in r['ekf_anchored_per_point_mean_abs_m'])} m. "
                f"Frame from which the mean error stays within 10 % of the range, per point: {conv}."
                + _nees_breakdown_text(r),
                "",
            ]
    return "\n".join(lines)


def _nees_breakdown_text(r: dict) -> str:
    """The NEES per point, its median and its trimmed mean (bench.seed004.nees_breakdown), when the run has them."""
    if not r["nees_samples"]:
        return ""
    return (f" NEES per point: {', '.join(_f(v) for v in r['nees_per_point'])}; median {r['nees_median']:.2f} "
            f"(χ²₃: {r['chi2_median']:.2f}); mean without the largest {r['nees_trim_share']:.0%} of the {r['nees_samples']} "
            f"samples {r['nees_trimmed_mean']:.2f} (χ²₃: {r['chi2_trimmed_mean']:.2f}).")


def seed000_markdown(res: dict) -> str:
    a = res["cases"][0]["assumptions"]
    lines = [
        f"Point at {tuple(a['point_cam'])} m in the camera frame (range {a['initial_range_m']:.2f} m), camera advancing "
        f"{a['speed_mps']} m/s along its axis, Δt = {a['dt']} s, σ_ω = {a['sigma_w']} rad/s/√Hz on ω_y, σ_V = {a['sigma_v']} m/s/√Hz on V_z "
        f"(the paper's planar input model), initial range error {a['initial_range_error_m']:g} m, f = {a['focal_px']:g} px; "
        f"{res['runs']} runs per case. The paper does not state its pixel noise: two assumptions are shown. "
        "Relative range error |d̂ − d|/d (mean over runs) when L = V·T/D0 is reached. The bound is the pixel-only "
        "Cramér–Rao bound (exact motion), a floor the input noise keeps the filters above. The anchored EKF gets poses "
        "dead-reckoned from the same noisy inputs; it models attitude error as a constant gyro bias, so the random-walk "
        "attitude of this scenario lies outside its model.",
        "",
        "| pixel σ | L | seed-000 EKF | anchored EKF | Cramér–Rao bound (σ/d) | paper table 2 |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for case in res["cases"]:
        s = case["assumptions"]["sigma_px"]
        for row in case["rows"]:
            lines.append(
                f"| {s:g} px | {row['L']:.2f} | {row['ekf_landmark_rel_err_pct']:.2f} % | {row['ekf_anchored_rel_err_pct']:.2f} % | "
                f"{row['crlb_rel_pct']:.2f} % | {row['paper_pct']:.2f} % |"
            )
    return "\n".join(lines)


def timing_json(res: dict) -> dict:
    return {k: res[k] for k in ("harris_640x480_ms", "ncc_per_track_us", "ekf_update_per_landmark_us_at_300",
                                "frontend_640x480_300_tracks_ms")} | {"details": res}


def timing_markdown(res: dict) -> str:
    lines = [
        f"One core (OpenCV threads = 1), median of {res['repeats']} repeats, {res['machine']}.",
        "",
        "| stage | this code | seed papers |",
        "|---|---:|---:|",
        f"| Harris, 320×240 | {res['harris_320x240_ms']:.2f} ms | 0.2 ms (seed 004, MATLAB) |",
        f"| Harris, 640×480 | {res['harris_640x480_ms']:.2f} ms | |",
        f"| NCC per track, ±8 px window (no telemetry) | {res['ncc_per_track_us']:.1f} µs | 0.531 ms descriptors + matching (seed 004) |",
        f"| NCC per track, ±3 px around the telemetry prediction | {res['ncc_predicted_per_track_us']:.1f} µs | |",
        f"| tracker step, 640×480, 300 tracks, no telemetry (steady state) | {res['frontend_640x480_300_tracks_ms']:.2f} ms | |",
        f"| tracker step, 640×480, 300 tracks, telemetry prediction (steady state) | {res['frontend_640x480_300_tracks_predicted_ms']:.2f} ms | |",
        f"| tracker step, 320×240, 300 tracks, telemetry prediction | {res['frontend_320x240_300_tracks_predicted_ms']:.2f} ms | |",
        f"| worst frame: full Harris + 300 NCC matches, no telemetry / with prediction | {res['harris_plus_ncc_300_ms']:.2f} / {res['harris_plus_ncc_300_predicted_ms']:.2f} ms | |",
        f"| triangulation per point (batch of 300) | {res['triangulation_per_point_us']:.2f} µs | < 0.1 ms (seed 004) |",
        f"| anchored EKF update per landmark at 300 (6 states with gyro bias, 2 iterations) | {res['ekf_update_per_landmark_us_at_300']:.2f} µs | 3.1 ms / 6 points (seed 004) |",
        f"| seed-000 EKF predict + update per landmark at 300 | {res['ekf_landmark_per_landmark_us_at_300']:.2f} µs | 60 µs (seed 000) |",
        "",
        "Per-frame filter cost against the number of landmarks (predict + update of every landmark):",
        "",
        "| landmarks | anchored EKF, ms/frame | µs/landmark | seed-000 EKF, ms/frame | µs/landmark |",
        "|---:|---:|---:|---:|---:|",
    ]
    for n, a, l in zip(res["scaling_n"], res["scaling_anchored_ms"], res["scaling_landmark_ms"]):
        lines.append(f"| {n} | {a:.3f} | {1000 * a / n:.2f} | {l:.3f} | {1000 * l / n:.2f} |")
    return "\n".join(lines)


def full_markdown(res: dict, runs: int, repeats: int) -> str:
    today = datetime.date.today().isoformat()
    return "\n".join([
        "# Benchmarks",
        "",
        f"Generated by `python -m bench all --runs {runs} --repeats {repeats} --write docs/BENCHMARKS.md` "
        f"(what `make bench` runs) on {today}, Python {platform.python_version()}, {platform.machine()}. "
        "Every figure in the sections it writes comes from that command; rerun it to reproduce them. The other "
        "sections were produced by the commands named in them, on the dates and commits given there; the command "
        "keeps them as they are, each after the section it followed.",
        "",
        "## Seed-004 scenario (DESIGN.md §4)",
        "",
        f"Machine-readable: `python -m bench seed004 --runs {runs} --json`.",
        "",
        seed004_markdown(res["seed004"], runs),
        "",
        "## Seed-000 scenario (DESIGN.md §4)",
        "",
        f"Machine-readable: `python -m bench seed000 --runs {runs} --json`.",
        "",
        seed000_markdown(res["seed000"]),
        "",
        "## Timing",
        "",
        "Machine-readable: `python -m bench timing --json`.",
        "",
        timing_markdown(res["timing"]),
        "",
        "## Seed-004 through the whole pipeline (flightsim → companion replay)",
        "",
        pipeline004_markdown(res),
        "",
        "## Companion pipeline latency",
        "",
        latency_markdown(res["latency"]),
        "",
        "## Simulator (flightsim)",
        "",
        flightsim_markdown(res["flightsim"]),
        "",
        "## Software in the loop (flightsim sitl, companion as a separate process)",
        "",
        sitl_markdown(res["sitl"]),
        "",
    ])


def pipeline004_markdown(res: dict) -> str:
    from bench.pipeline_seed004 import markdown

    try:  # measurement level: anchored EKF, σ = 2 px, gyro model, frame 150, mean |error| (eq. 15)
        ref = float(res["seed004"]["with_gyro_model"]["2"]["ekf_anchored_mean_abs_m"])
    except (KeyError, TypeError, ValueError):
        ref = None
    return markdown(res["pipeline004"], ref)


def latency_markdown(res: dict) -> str:
    from bench.latency import markdown

    return markdown(res)


def sitl_markdown(res: dict) -> str:
    from bench.sitl_bench import markdown

    return markdown(res)


def flightsim_markdown(res: dict) -> str:
    from bench.flightsim_bench import markdown

    return markdown(res)


def write_section(doc, heading: str, text: str) -> None:
    """Replace (or append) the section that starts with the line ``heading`` (``## …``) in ``doc``
    with ``heading`` and ``text``; the section ends at the next ``## `` heading outside a code block
    (the same split as :func:`merge_document`; blank lines between sections come out as one)."""
    from pathlib import Path

    doc = Path(doc)
    head, blocks = _split_sections(doc.read_text(encoding="utf-8") if doc.is_file() else "", 2)
    headings = [h for h, _ in blocks]
    at = headings.index(heading) if heading in headings else len(blocks)
    blocks[at:at + 1] = [(heading, text)]
    doc.write_text(_join_sections(head, blocks), encoding="utf-8")


def _split_sections(text: str, level: int) -> tuple[str, list[tuple[str, str]]]:
    """``text`` as (the part before its first heading of ``level`` hashes, [(heading line, body), …]).
    Headings inside fenced code blocks (``` … ```) are not headings."""
    mark = "#" * level + " "
    head: list[str] = []
    blocks: list[tuple[str, list[str]]] = []
    fenced = False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        if not fenced and line.startswith(mark):
            blocks.append((line.rstrip(), []))
        elif blocks:
            blocks[-1][1].append(line)
        else:
            head.append(line)
    return "\n".join(head), [(h, "\n".join(body)) for h, body in blocks]


def _join_sections(head: str, blocks: list[tuple[str, str]]) -> str:
    parts = [head.rstrip("\n")] if head.strip() else []
    parts += [f"{h}\n\n{body.strip(chr(10))}".rstrip("\n") for h, body in blocks]
    return "\n\n".join(parts) + "\n"


def _merge_level(existing: str, generated: str, level: int) -> str:
    """The generated text with the existing text's hand-written sections of this level (headings the generator
    does not write) kept after the section they followed; sections both have are merged one level down."""
    old_head, old_blocks = _split_sections(existing, level)
    new_head, new_blocks = _split_sections(generated, level)
    generated_headings = {h for h, _ in new_blocks}
    old_by_heading = {h: body for h, body in old_blocks if h in generated_headings}
    kept_after: dict[str | None, list[tuple[str, str]]] = {}
    anchor = None
    for h, body in old_blocks:
        if h in generated_headings:
            anchor = h
        else:
            kept_after.setdefault(anchor, []).append((h, body))
    out = list(kept_after.get(None, []))
    for h, body in new_blocks:
        if h in old_by_heading and level < 3:
            body = _merge_level(old_by_heading[h], body, level + 1)
        out.append((h, body))
        out += kept_after.get(h, [])
    return _join_sections(new_head, out)


def merge_document(existing: str, generated: str) -> str:
    """The benchmarks document rewritten by ``bench all --write``: every ``##`` and ``###`` section the generator
    writes replaced by its new text (in the generator's order), every section it does not write — the ones
    other commands produced, named in them — kept as it is, after the generated section it followed."""
    if not existing.strip():
        return generated.rstrip("\n") + "\n"
    return _merge_level(existing, generated, 2)


def print_campaign_readings(prog: str, read, campaigns, as_json: bool, markdown) -> int:
    """The thin end of the commands that read finished campaigns (``bench.too_near``,
    ``bench.motion_split``): ``read(Path)`` each campaign directory, print the JSON or the
    ``markdown(results)``; a campaign that cannot be read is reported on stderr with exit code 2."""
    import json
    import sys
    from pathlib import Path

    try:
        results = [read(Path(c)) for c in campaigns]
    except (FileNotFoundError, KeyError, ValueError) as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return 2
    print(json.dumps(results, indent=1) if as_json else markdown(results), end="")
    return 0


def landmark_run_parser(command: str, doc: str):
    """The argument parser shared by the commands that read SITL runs flown with ``--landmark-log``
    (``bench.landmark_truth``, ``bench.map_cells``): the module docstring as description and epilog, the run or
    campaign directories, ``--scenario``; callers add their own options."""
    import argparse

    ap = argparse.ArgumentParser(prog=command, description=doc.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=doc.split("\n\n", 1)[1])
    ap.add_argument("runs", nargs="+", metavar="DIR",
                    help="flightsim sitl output directories flown with --landmark-log, or SITL campaign directories "
                         "(flightsim campaign … --mode sitl --landmark-log): all their runs")
    ap.add_argument("--scenario", help="the scenario file, if not the one sitl.json names (relative to the run's working directory)")
    return ap


def rendered_flight_parser(command: str, doc: str, defaults, example: str):
    """The argument parser shared by the commands that fly scenarios in-process and run the companion's tracker on
    the rendered frames (``bench.looming_truth``, ``bench.track_drift``): the module docstring's first paragraph as
    description, ``--scenario`` (repeatable; ``defaults`` when absent) and ``--seed``; callers add their own options."""
    import argparse

    ap = argparse.ArgumentParser(prog=command, description=doc.split("\n\n")[0] + " Flies each scenario once, in-process.",
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=f"Example:\n  {example}")
    ap.add_argument("--scenario", action="append", help=f"scenario name in configs/scenarios or a .toml path (repeatable; "
                                                        f"default: {', '.join(defaults)})")
    ap.add_argument("--seed", type=int, default=1, help="the flight's seed (default 1)")
    return ap


def rendered_frames(flight, max_frames: int | None = None, progress=None):
    """The camera frames of an in-process flight (``flightsim.fly.Flight``), at most ``max_frames``: yields
    ``(k, frame, R_world_cam, p_world_cam, pose_prev)`` with the true camera pose of the frame and that of the
    previous frame (None for the first), then advances ``progress`` by one."""
    pose_prev = None
    k = 0
    while flight.step() is not None and (max_frames is None or k < max_frames):
        if not flight.frame_due():
            continue
        frame = flight.capture()
        R_wc = flight.truth["R_world_cam"][-1]
        p_wc = flight.truth["p_world_cam"][-1]
        yield k, frame, R_wc, p_wc, pose_prev
        pose_prev = (R_wc, p_wc)
        k += 1
        if progress:
            progress(1)


def run_dirs(path) -> list:
    """The run directories a path stands for: a campaign's ``runs/seed_*``, else the path itself."""
    from pathlib import Path

    d = Path(path)
    return sorted((d / "runs").glob("seed_*")) if (d / "runs").is_dir() else [d]
