"""``flightsim`` command line (also ``python -m flightsim``).

  flightsim fly configs/scenarios/X.toml --out DIR [--seed N] [--no-plot]
  flightsim sitl configs/scenarios/X.toml --out DIR [--clock lockstep|realtime] [--attach] [--video] …
  flightsim score DIR | --ranges R.tlog --truth truth.npz [--out DIR]
  flightsim campaign configs/scenarios/X.toml --runs N --workers W --out DIR [--mode auto|replay|sitl]

Exit codes (:mod:`companion.errors`): 0 done, 2 a bad scenario/world/argument/input file or a busy
port (the message names it), 1 a failure in flight or of the companion (the message names its log),
130 interrupted by Ctrl-C, 143 by SIGTERM.  Outputs appear when complete (temporary names until
then, :mod:`companion.io.atomic`): an interrupted command leaves nothing at their names; the tlogs
of an interrupted ``sitl`` are kept as ``*.tlog.partial``, an interrupted campaign's pooled results
as ``campaign.json.partial`` and ``report.partial/``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys

from pathlib import Path

from companion.errors import EXIT_OK, EXIT_RUNTIME, EXIT_USAGE, CompanionError, ConfigError, Terminated
from companion.interrupts import interrupt_exit_code, interrupt_name, raise_on_sigterm
from companion.io.progress import ProgressBar
from flightsim.avoidance import MODELS as AVOIDANCE_MODELS

log = logging.getLogger("flightsim")


def cmd_fly(args) -> int:
    from flightsim.fly import fly
    from flightsim.scenario import load_scenario

    sc = load_scenario(args.scenario, seed=args.seed, avoidance=args.avoidance)
    log.info("flying %s (%s, %.1f s, seed %d) into %s", sc.meta.name, sc.vehicle.aircraft, sc.meta.duration_s, sc.meta.seed, args.out)
    with ProgressBar(f"fly {sc.meta.name}") as bar:
        res = fly(sc, args.out, progress=lambda done, total: bar.update(done, total), plot=not args.no_plot)
    print(f"{sc.meta.name}: {res.frames} frames, {res.messages} MAVLink messages, {res.duration_s:g} s flown "
          f"in {res.wall_s:.1f} s ({res.realtime_factor:.1f}× real time) → {res.out_dir}")
    if sc.avoidance.model != "none":
        from flightsim.outcome import evaluate_outcome, outcome_verdict, read_trajectory

        o = evaluate_outcome(read_trajectory(Path(args.out) / "trajectory.npz"), sc.world)
        if not args.no_plot:
            from flightsim.plots import plot_run_outcome

            plot_run_outcome(Path(args.out), sc.world, o, title=sc.meta.name)
        print(f"avoidance {o['model']} (no companion, so no obstacle data): {outcome_verdict(o)}; min clearance "
              f"{o['min_clearance_m']:.2f} m, progress {100 * o['progress']:.0f} % of the route")
    return EXIT_OK


def cmd_sitl(args) -> int:
    import shlex

    from flightsim.scenario import default_companion_config
    from flightsim.sitl import SitlConfig, run_sitl

    from flightsim.hostile import KINDS, Blackout, HostileConfig

    try:
        kinds = tuple(k.strip() for k in args.hostile_kinds.split(",") if k.strip()) if args.hostile_kinds else KINDS
        hostile = HostileConfig(rate_hz=args.hostile_rate, seed=args.hostile_seed, kinds=kinds,
                                blackouts=tuple(Blackout.parse(b) for b in args.blackout or ()))
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    cfg = SitlConfig(processing_ms=args.processing_ms, connect_timeout_s=args.connect_timeout, hostile=hostile,
                     rss_sample_s=args.rss_sample_s, landmark_log=args.landmark_log)
    # --config, else the scenario's [scenario] companion_config, else (None) the shipped configs/companion.toml
    companion_config = default_companion_config(args.scenario, args.config)
    log.info("SITL %s (%s clock) into %s, companion config %s", args.scenario, args.clock, args.out,
             companion_config or "configs/companion.toml")
    with ProgressBar(f"sitl {args.clock}") as bar:
        s = run_sitl(args.scenario, args.out, seed=args.seed, clock=args.clock, companion_config=companion_config,
                     attach=args.attach, video=args.video, progress=lambda done, total: bar.update(done, total),
                     mavlink_port=args.mavlink_port, camera_port=args.camera_port, config=cfg, score=not args.no_score,
                     avoidance=args.avoidance)
    rx = s["messages_received"]
    print(f"{s['scenario']}: {s['frames']} frames to the companion ({s['clock']}"
          + (f", {s['processing_ms']:g} ms per frame" if s["processing_ms"] is not None else "") + f"), "
          f"{s['duration_s']:g} s flown in {s['loop_wall_s']:.1f} s ({s['realtime_factor']:.2f}× real time; "
          f"{s['wall_s']:.1f} s with start-up)")
    if s["acks"]:
        print("frames acknowledged: " + ", ".join(f"{k} {v}" for k, v in sorted(s["acks"].items())))
    print(f"received {sum(rx.values())} MAVLink messages: " + (", ".join(f"{k} {v}" for k, v in rx.items()) or "none"))
    print("streams: " + ", ".join(f"{k} {'off' if v is None else f'{v:g} Hz'}" for k, v in s["streams"].items())
          + f"; TIMESYNC answered {s['timesync_answered']}")
    h = s.get("hostile")
    if h:
        print(f"hostile traffic: {h.get('datagrams', 0)} datagrams ({h.get('packets', 0)} packets) at {h['rate_hz']:g}/s: "
              + (", ".join(f"{k} {v}" for k, v in (h.get("by_kind") or {}).items()) or "none")
              + (f"; blackouts {len(h['blackouts'])}, vehicle messages dropped: "
                 + (", ".join(f"{k} {v}" for k, v in h["blackout_dropped"].items()) or "none") if h["blackouts"] else ""))
    bad = {k: v for k, v in s["checks"].items() if k in ("obstacle_distance_bad_fields", "clock_mismatches") and v}
    if bad:
        print("checks FAILED: " + ", ".join(f"{k} {v}" for k, v in bad.items()))
    if s["companion"] is not None:
        print(f"companion exit code {s['companion_exit_code']}; log {s['companion']['log']}")
    else:
        print("companion attached (not started by flightsim): " + shlex.join(s["companion_command"]))
    if s["score"] is not None:
        md = Path(args.out) / "score.md"
        text = md.read_text(encoding="utf-8") if md.is_file() else ""
        cut = text.find("## Range error")
        if text:
            print()
            print((text[:cut] if cut > 0 else text).strip())
            print()
        print(f"score: {md} (full report: range error by bin, time to first range, latency, NEES)")
    else:
        print(f"not scored: {s['score_note']}")
    print(f"files in {args.out}: " + ", ".join(Path(p).name for p in s["paths"].values()))
    o = (s["score"] or {}).get("avoidance")
    if o:
        from flightsim.outcome import outcome_verdict

        print(f"closed loop ({o['model']} avoidance on the companion's ranges): {outcome_verdict(o)}; min clearance "
              f"{o['min_clearance_m']:.2f} m, progress {100 * o['progress']:.0f} % of the route; plot {Path(args.out) / 'avoidance.png'}")
    if s["score_failed"]:
        print(f"flightsim: error: {s['score_note']}", file=sys.stderr)
        return EXIT_RUNTIME
    if s["companion"] is not None and s["companion_exit_code"] not in (0, None):
        print(f"flightsim: error: the companion exited with code {s['companion_exit_code']} (see {s['companion']['log']})",
              file=sys.stderr)
        return EXIT_RUNTIME
    return EXIT_OK


def _run_record(run_dir: Path | None) -> dict:
    """What a run directory says about itself (best effort): ``scenario_file`` (flight.json, sitl.json or,
    for a campaign's ``runs/seed_NNNN``, the campaign.json two levels up) and ``companion_config``, the
    companion TOML the run was made with (sitl.json's companion command, campaign.json)."""
    rec: dict = {"scenario_file": None, "companion_config": None}
    if run_dir is None:
        return rec
    files = [run_dir / "sitl.json", run_dir / "flight.json"]
    if run_dir.parent.name == "runs":
        files.append(run_dir.parent.parent / "campaign.json")
    for f in files:
        if not f.is_file():
            continue
        try:
            d = json.loads(f.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            log.warning("%s unreadable: %s", f, exc)
            continue
        rec["scenario_file"] = rec["scenario_file"] or d.get("scenario_file") or (d.get("scenario") if f.name == "campaign.json" else None)
        used = d.get("companion_config") if f.name == "campaign.json" else None
        cmd = d.get("companion_command") if f.name == "sitl.json" else None
        if isinstance(cmd, list) and "--config" in cmd[:-1]:
            used = cmd[cmd.index("--config") + 1]
        rec["companion_config"] = rec["companion_config"] or used
    return rec


def _score_companion_config(given: str | None, scenario: str | None, rec: dict) -> str | Path | None:
    """The companion TOML whose ``sigma_k`` the score undoes: ``--companion-config``, else the one the run
    recorded using, else the scenario's ``[scenario] companion_config`` (``--scenario``, else the recorded
    scenario file), else None (the score's built-in defaults)."""
    from flightsim.scenario import default_companion_config

    if given is not None:
        return given
    used = rec.get("companion_config")
    if used and Path(used).is_file():
        log.info("companion config %s (the one the run used)", used)
        return used
    path = scenario or rec.get("scenario_file")
    if path and (scenario or Path(path).is_file()):
        found = default_companion_config(path)  # ConfigError if it names a missing file
        if found is not None:
            log.info("companion config %s (the scenario's [scenario] companion_config)", found)
        return found
    return None


def _world_for_names(scenario: str | None, run_dir: Path | None, rec: dict | None = None):
    """The world that names the obstacles: ``--scenario``, else the one the run directory names (best effort)."""
    from flightsim.scenario import load_scenario

    if scenario:
        return load_scenario(scenario).world
    path = (rec or _run_record(run_dir)).get("scenario_file")
    if path:
        try:
            if Path(path).is_file():
                return load_scenario(path).world
            log.info("obstacles are not named: %s (from the run's records) not found; give --scenario", path)
        except Exception as exc:  # naming is optional: never fail the score for it
            log.warning("obstacles are not named: %s", exc)
    return None


def cmd_score(args) -> int:
    from companion.io.atomic import StagedFiles, prepare_output_dir
    from flightsim.score.markdown import mark
    from flightsim.score.files import load_score_config, score_run, stage_score

    run_dir = Path(args.dir) if args.dir else None
    if run_dir is not None and not run_dir.is_dir():
        raise ConfigError(f"{run_dir}: no such run directory")
    ranges = Path(args.ranges) if args.ranges else None
    if ranges is None:
        if run_dir is None:
            raise ConfigError("give a run directory or --ranges and --truth")
        ranges = next((c for c in (run_dir / "received.tlog", run_dir / "ranges.tlog") if c.is_file()), None)
        if ranges is None:
            raise ConfigError(f"{run_dir}: neither received.tlog (SITL) nor ranges.tlog (replay); give --ranges")
    truth = Path(args.truth) if args.truth else (run_dir / "truth.npz" if run_dir else None)
    if truth is None:
        raise ConfigError("--truth is required without a run directory")
    out = prepare_output_dir(args.out) if args.out else (run_dir or ranges.parent)
    cfg = load_score_config(args.config)
    rec = _run_record(run_dir)
    companion_config = _score_companion_config(args.companion_config, args.scenario, rec)
    world = _world_for_names(args.scenario, run_dir, rec)
    log.info("scoring %s against %s", ranges, truth)
    # score.json, score.md, score_series.npz and nees.png appear together (a previous series or plot goes with
    # --no-series / --no-plot)
    with StagedFiles(out, obsolete=("score_series.npz", "nees.png")) as staged:
        score = score_run(ranges, truth, config=cfg, companion_config=companion_config, world=world,
                          series_out=None if args.no_series else staged.path("score_series.npz"),
                          plot_dir=None if args.no_plot else staged)
        stage_score(staged, score)
    r = score["rates"]

    def pc(v):
        return "–" if v is None else f"{100 * v:.2f} %"

    rv = score.get("rates_in_view", r)
    print(f"{score['messages']['obstacle_distance_scored']} OBSTACLE_DISTANCE scored: in view, a range within tolerance "
          f"{pc(rv['valid_range'])} and unknown {pc(rv['unknown_in_obstacle_cells'])} of obstacle cells; "
          f"false obstacle (clear cells) {pc(r['false_obstacle_clear_cells'])}, too near {pc(r['too_near'])}")
    for t in score["targets"]:
        print(f"  {mark(t['met'])} {t['name']}: {pc(t['value'])} (target {t['op']} {100 * t['threshold']:g} %, n = {t['n']})")
    la, ne = score["latency"], score["nees"]
    if la["n"]:
        print(f"  latency p50 {la['p50_ms']:.1f} ms, p99 {la['p99_ms']:.1f} ms")
    if ne["n"]:
        band, bi, cov = ne.get("band") or [math.nan, math.nan], ne["band_independent"], ne["coverage"]
        print(f"  {mark(ne['consistent'])} NEES {ne['mean']:.2f} (n = {ne['n']}, n_eff = {ne['n_eff'] or math.nan:.1f}: "
              f"{100 * ne['confidence']:g} % band [{band[0]:.2f}, {band[1]:.2f}]; as if independent "
              f"[{bi[0]:.2f}, {bi[1]:.2f}]); truth within ±2σ in {pc(cov['rate_2sigma'])} (normal "
              f"{pc(cov['expected_2sigma'])}), ±σ in {pc(cov['rate_1sigma'])} ({pc(cov['expected_1sigma'])})")
    plots = f" and {out / 'nees.png'}" if score.get("plots", {}).get("nees") else ""
    print(f"wrote {out / 'score.json'}, {out / 'score.md'}{plots}")
    return EXIT_OK


def cmd_campaign(args) -> int:
    from flightsim.campaign import campaign_from_args

    return campaign_from_args(args)


def missing_sim_modules() -> list[str]:
    """The simulator's own dependencies (the ``sim`` extra) that are not installed: the companion's
    onboard install ships flightsim's code but not JSBSim, matplotlib or rich."""
    from companion.io.progress import installed

    return [m for m in ("jsbsim", "matplotlib", "rich") if not installed(m)]


def _version() -> str:
    """``flightsim X.Y.Z`` from the installed distribution's metadata."""
    from companion import DISTRIBUTION, package_version

    return f"flightsim {package_version()} ({DISTRIBUTION})"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="flightsim",
        description="JSBSim flights with a rendered camera, autopilot-grade MAVLink telemetry and ground truth.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example:\n  flightsim fly configs/scenarios/quad_approach.toml --out out/quad\n\n"
               "Output: telemetry.tlog (MAVLink 2), video.avi + frames.csv (capture times on the tlog's clock),\n"
               "truth.npz, camera.toml, summary.png, flight.json.",
    )
    ap.add_argument("--version", action="version", version=_version())
    ap.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"], help="logging level (default INFO)")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("fly", help="fly a scenario and export a replayable flight log",
                       description="Fly a scenario (configs/scenarios/*.toml) as fast as the CPU allows and write "
                                   "telemetry.tlog, video.avi, frames.csv, truth.npz and a summary plot into --out.")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument("--seed", type=int, default=None, help="override the scenario's [scenario] seed")
    p.add_argument("--no-plot", action="store_true", help="skip summary.png")
    p.add_argument("--avoidance", choices=AVOIDANCE_MODELS, default=None,
                   help="override the scenario's [avoidance] model (no companion here: the autopilot holds no obstacle "
                        "data, so ardupilot flies the route as commanded and px4 refuses to move)")
    q = sub.add_parser(
        "sitl", help="software in the loop: play the autopilot and camera to a live companion and score its ranges",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Fly a scenario while playing the autopilot over MAVLink 2 (UDP on 127.0.0.1: HEARTBEAT, the streams the "
                    "companion requests, TIMESYNC) and the camera (sim:// frame transport), with the companion "
                    "(python -m companion run) as a separate process; record every message it sends and score its "
                    "OBSTACLE_DISTANCE / DISTANCE_SENSOR against the truth of the moment they arrive.",
        epilog="clocks:\n"
               "  lockstep  (default) deterministic, as fast as the CPU allows: the simulator waits for the companion's\n"
               "            acknowledgement of each frame; the companion runs with --clock sim and advances its clock\n"
               "            by --processing-ms per processed frame (see companion/simclock.py).\n"
               "  realtime  the simulator follows the wall clock; the companion runs on its own clock with TIMESYNC.\n\n"
               "output in --out: truth.npz, frames.csv, camera.toml, telemetry.tlog (sent), received.tlog (from the\n"
               "companion, stamped on arrival on the truth clock), companion.log, sitl.json, score.json/score.md when\n"
               "flightsim/score/ is present, video.avi with --video.\n\n"
               "example:\n  flightsim sitl configs/scenarios/quad_approach.toml --out out/sitl\n"
               "  flightsim sitl configs/scenarios/quad_approach.toml --out out/sitl --attach   # you start the companion")
    q.add_argument("scenario", help="scenario TOML file")
    q.add_argument("--out", required=True, help="output directory (created if missing)")
    q.add_argument("--seed", type=int, default=None, help="override the scenario's [scenario] seed")
    q.add_argument("--clock", choices=("lockstep", "realtime"), default="lockstep", help="lockstep (default) or realtime")
    q.add_argument("--config", metavar="TOML", default=None,
                   help="companion configuration (default: the scenario's [scenario] companion_config, else "
                        "the shipped configs/companion.toml)")
    q.add_argument("--attach", action="store_true",
                   help="do not start the companion: print the command line to run and wait for it to connect")
    q.add_argument("--video", action="store_true", help="also write video.avi (MJPG)")
    q.add_argument("--mavlink-port", type=int, default=14550, metavar="PORT",
                   help="UDP port the simulated autopilot listens on, 127.0.0.1 (default 14550; 0 = any free port)")
    q.add_argument("--camera-port", type=int, default=5600, metavar="PORT",
                   help="TCP port of the camera frame transport, 127.0.0.1 (default 5600; 0 = any free port)")
    q.add_argument("--processing-ms", type=float, default=25.0, metavar="MS",
                   help="lockstep: simulated processing time per frame of the companion (default 25)")
    q.add_argument("--connect-timeout", type=float, default=60.0, metavar="S",
                   help="seconds the companion has to connect (×5 with --attach; default 60)")
    q.add_argument("--no-score", action="store_true", help="do not score the received ranges")
    q.add_argument("--landmark-log", action="store_true",
                   help="the companion also writes landmarks.jsonl: per frame, every landmark's point, range, σ, mean NIS and "
                        "flags with the camera pose (companion run --landmark-log; ~15 MB a minute)")
    q.add_argument("--hostile-rate", type=float, default=0.0, metavar="HZ",
                   help="hostile datagrams per simulated second interleaved with the telemetry: random bytes, bad CRC, "
                        "truncated, unknown ids, NaN/inf payloads, glued packets, spoofed ATTITUDE (flightsim/hostile.py; "
                        "default 0 = none)")
    q.add_argument("--hostile-seed", type=int, default=0, metavar="N", help="seed of the hostile traffic (default 0)")
    q.add_argument("--hostile-kinds", default=None, metavar="LIST",
                   help="comma-separated subset of the hostile kinds (default all: random_bytes, bad_crc, truncated, "
                        "unknown_id, nan_payload, glued, spoof_attitude_own, spoof_attitude_foreign)")
    q.add_argument("--blackout", action="append", metavar="START:DURATION[:hb]",
                   help="telemetry blackout: no ATTITUDE / LOCAL_POSITION_NED / GLOBAL_POSITION_INT from START for "
                        "DURATION simulated seconds; ':hb' silences the HEARTBEAT and the answers to requests too "
                        "(repeatable)")
    q.add_argument("--rss-sample-s", type=float, default=0.0, metavar="S",
                   help="sample the companion's resident set (VmRSS) every S simulated seconds into sitl.json (default 0 = off)")
    q.add_argument("--avoidance", choices=AVOIDANCE_MODELS, default=None,
                   help="the simulated autopilot's obstacle avoidance fed by the companion's ranges, overriding the "
                        "scenario's [avoidance] model (quad only; docs/derivations/sectors.md): ardupilot = Copter simple avoidance, "
                        "px4 = collision prevention, none = fly the route as commanded")
    p = sub.add_parser("score", help="score a recorded run against its truth (score.json, score.md)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Compare the companion's OBSTACLE_DISTANCE / DISTANCE_SENSOR (a ranges tlog: companion "
                                   "replay's ranges.tlog or SITL's received.tlog) with the flight's truth.npz and write "
                                   "score.json and score.md (detection and false-obstacle rates per sector, dangerous "
                                   "clears, range error by range bin, time to the first valid range per obstacle, "
                                   "latency, NEES of the reported σ against the band for its effective sample size and "
                                   "the ±σ / ±2σ coverage, the scorer's targets), score_series.npz and nees.png.",
                       epilog="examples:\n  flightsim score out/quad        # out/quad/{received,ranges}.tlog + truth.npz\n"
                              "  flightsim score --ranges r.tlog --truth truth.npz --out scores/\n\n"
                              "exit codes: 0 scored, 2 missing or unreadable inputs / bad options.")
    p.add_argument("dir", nargs="?", help="run directory (flightsim fly output with ranges.tlog or received.tlog)")
    p.add_argument("--ranges", help="ranges tlog (default DIR/received.tlog, else DIR/ranges.tlog)")
    p.add_argument("--truth", help="truth.npz (default DIR/truth.npz)")
    p.add_argument("--out", help="where score.json / score.md go (default DIR, else the tlog's directory)")
    p.add_argument("--config", help="TOML with a [score] table (default: built-in defaults, as configs/score.toml)")
    p.add_argument("--companion-config", help="companion TOML the run used: its [sectors] sigma_k and [outputs] "
                                              "quality_zero_rel_sigma undo the conservative offset (default: the one "
                                              "sitl.json / campaign.json record, else the scenario's [scenario] "
                                              "companion_config, else built-in defaults)")
    p.add_argument("--scenario", help="scenario TOML whose world names the obstacles (default: the one flight.json names)")
    p.add_argument("--no-series", action="store_true", help="do not write score_series.npz (per-message arrays)")
    p.add_argument("--no-plot", action="store_true", help="do not draw nees.png (forward error with its ±2σ envelope, "
                                                         "running NEES against its n_eff band)")
    p = sub.add_parser("campaign", help="Monte Carlo over seeds in worker processes, scored, with a report",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Fly a scenario with seeds seed0 … seed0+N−1 (default seed0 = the scenario's seed), run "
                                   "the companion on each (replay in-process, or SITL), score every run, and write "
                                   "DIR/campaign.json and DIR/report/ (index.md with pooled tables and the targets, plots). "
                                   "Runs go to DIR/runs/seed_NNNN/; a failed run is recorded and the rest go on.",
                       epilog="example:\n  flightsim campaign configs/scenarios/quad_approach.toml --runs 20 --workers 2 "
                              "--out out/camp\n\nexit codes: 0 all runs scored, 1 some runs failed (the report covers "
                              "the others), 2 bad arguments or scenario.")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("--runs", type=int, required=True, help="number of runs (seeds)")
    p.add_argument("--workers", type=int, default=None, help="worker processes (default: min(runs, CPU count))")
    p.add_argument("--out", required=True, help="campaign directory (created; runs/, report/, campaign.json)")
    p.add_argument("--mode", choices=["auto", "replay", "sitl"], default="auto",
                   help="replay: fly + companion replay in-process; sitl: flightsim.sitl.run_sitl (lockstep clock, free "
                        "ports); auto (default): sitl if available, else replay")
    p.add_argument("--seed0", type=int, default=None, help="first seed (default: the scenario's [scenario] seed)")
    p.add_argument("--companion-config", default=None,
                   help="companion TOML for the runs and for undoing k·σ (default: the scenario's [scenario] "
                        "companion_config, else the shipped configs/companion.toml)")
    p.add_argument("--score-config", default=None, help="TOML with a [score] table (default: built-in defaults)")
    p.add_argument("--fixed-processing-ms", type=float, default=30.0,
                   help="processing time per frame, ms: replay stamps it on every frame, SITL lockstep advances the "
                        "companion's clock by it (deterministic runs; default 30)")
    p.add_argument("--obstacle", default="forward",
                   help="obstacle drawn in range_vs_truth.png: an obstacle name from the scores, or 'forward' (default: "
                        "the forward DISTANCE_SENSOR)")
    p.add_argument("--times", default=None, help="comma-separated times (s after the first frame) of the sector radar "
                                                  "plots (default: 4 times spread over the flight)")
    p.add_argument("--backend", choices=("process", "ray"), default="process",
                   help="where runs execute: a local process pool (default) or Ray tasks (pip install '.[ray]'; "
                        "inputs and results travel as data, no shared file system)")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help="--backend ray: the Ray cluster to join (e.g. ray://head:10001 or auto; default: start a local Ray)")
    p.add_argument("--avoidance", choices=AVOIDANCE_MODELS, default=None,
                   help="override the scenario's [avoidance] model: the simulated autopilot avoids obstacles with the "
                        "companion's ranges (closed loop; runs in SITL) and every run gets an outcome (collision, stop "
                        "clearance, false stop, progress), pooled with 95 %% confidence intervals")
    p.add_argument("--landmark-log", action="store_true",
                   help="each run also writes the companion's landmark log, landmarks.jsonl (per frame, every landmark's "
                        "point, range, σ and flags; ~15 MB a minute); python -m bench landmark_truth reads them")
    p.add_argument("--camera", metavar="WxH", default=None,
                   help="fly the scenario with its camera at this resolution and the same field of view (e.g. 640x480; "
                        "the aspect ratio must stay): the scenario is written to DIR/<scenario>_WxH.toml and flown from there")
    p.add_argument("--keep-video", action="store_true", help="keep each run's video.avi (default: deleted after scoring; "
                                                             "the seed reproduces it)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    missing = missing_sim_modules()
    if missing:
        print(f"flightsim: the simulator needs the 'sim' extra ({', '.join(missing)} not installed): "
              "pip install 'monorange[sim]'", file=sys.stderr)
        return EXIT_USAGE
    commands = {"fly": cmd_fly, "sitl": cmd_sitl, "score": cmd_score, "campaign": cmd_campaign}
    try:
        with raise_on_sigterm():  # SIGTERM unwinds like Ctrl-C: temporary outputs removed, the companion stopped
            return commands[args.cmd](args)
    except ConfigError as exc:
        print(f"flightsim: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except CompanionError as exc:  # a failure in flight or of the companion (SitlError names its log)
        print(f"flightsim: error: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    except (KeyboardInterrupt, Terminated) as exc:
        print(f"flightsim {args.cmd}: {interrupt_name(exc)}; nothing written under the output names (partial data, if any, "
              "in *.partial)", file=sys.stderr)
        return interrupt_exit_code(exc)


if __name__ == "__main__":
    sys.exit(main())
