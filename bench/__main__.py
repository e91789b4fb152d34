"""``python -m bench``: the reproducible benchmarks (the source papers' scenarios and more).

Subcommands:
  seed004   seed-004 scenario, Monte Carlo over pixel noise (and the gyro model)
  seed000   seed-000 scenario, relative range error against L = V·T/D0
  timing    per-stage timings on one core
  looming   head-on approaches at the focus of expansion: range with and without looming (docs/derivations/looming.md)
  map_memory, map_tradeoff   the local obstacle map: memory over a long hover; its publishing trade-offs in SITL
  compute   CPU per 640×480 frame of the whole pipeline on one core (bench/compute.py)
  hostile   soak and fuzz: a long lockstep SITL hover under hostile MAVLink traffic and telemetry blackouts
            (bench/hostile.py; not part of `all`: the real run is 30 simulated minutes)
  too_near  the too-near cells of finished SITL campaigns split by cause (bench/too_near.py; reads campaigns, flies nothing)
  campaign_diff  before → after of the issue targets of SITL campaigns flown twice (bench/campaign_diff.py; flies nothing)
  motion_split  detection in view of finished SITL campaigns by what the vehicle did — turning in place, hovering,
            moving — and true range, with the single camera's ceiling (bench/motion_split.py; flies nothing)
  looming_truth  the tracker's scale changes on rendered flights against the true depth ratio: is the looming σ honest,
            are a track's errors independent (bench/looming_truth.py)
  track_drift  how far the tracker's pixels wander from the points they were born on, on rendered flights, with the
            drift correction off and on (bench/track_drift.py)
  landmark_truth  each converged landmark's range against the truth on a SITL flight with a landmark log: is its σ
            honest, by true range (bench/landmark_truth.py)
  map_cells  what the local obstacle map held where an obstacle out of view was reported unknown: no point, off the
            band, withheld, published (bench/map_cells.py; reads SITL runs flown with --landmark-log)
  all       all of these plus the simulator's speed; with --write FILE, rewrite the sections of docs/BENCHMARKS.md
            it produces and keep the sections other commands produced (report.merge_document)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

from bench import report


def _progress(total: int, label: str, quiet: bool):
    """A progress bar on stderr (silent with --json or when stderr is not a terminal); the context
    gives a ``tick(n)`` that counts n more done."""
    import contextlib

    from companion.io.progress import ProgressBar

    @contextlib.contextmanager
    def bar():
        with ProgressBar(label, total=total, enabled=False if quiet else None) as b:
            yield b.advance

    return bar()


def cmd_seed004(args) -> dict:
    from bench import seed004

    total = args.runs * sum(len(c) for c in seed004.CASES.values())
    t0 = time.perf_counter()
    with _progress(total, "seed-004 Monte Carlo", args.json) as tick:
        res = seed004.run_all(args.runs, workers=args.workers, progress=tick, ekf_iterations=getattr(args, "ekf_iterations", 2),
                              tri_max_rel_sigma=getattr(args, "tri_max_rel_sigma", 0.3),
                              refine=not getattr(args, "no_refine", False))
    res["wall_time_s"] = time.perf_counter() - t0
    return res


def cmd_seed000(args) -> dict:
    from bench import seed000

    from bench.seed000 import PIXEL_SIGMAS

    with _progress(args.runs * len(PIXEL_SIGMAS), "seed-000 Monte Carlo", args.json) as tick:
        return seed000.run(args.runs, progress=tick)


def cmd_pipeline004(args, runs: int) -> dict:
    from bench import pipeline_seed004

    import logging

    logging.disable(logging.WARNING)  # the replayed companion's STATUSTEXT log lines
    try:
        with _progress(runs, "seed-004 through the pipeline", args.json) as tick:
            return pipeline_seed004.run(runs, progress=tick)
    finally:
        logging.disable(logging.NOTSET)


def cmd_sitl(args) -> dict:
    from bench import sitl_bench

    import logging

    logging.disable(logging.WARNING)
    try:
        return sitl_bench.run_all(quad_runs=8, fixedwing_runs=8)
    finally:
        logging.disable(logging.NOTSET)


def cmd_looming(args, runs: int, rendered_runs: int) -> dict:
    from bench import looming

    n = 2 * len(looming.SYNTHETIC) * runs + 2 * rendered_runs
    with _progress(n, "looming approaches", args.json) as tick:
        return looming.run_all(runs, rendered_runs, progress=tick)


def cmd_map_memory(minutes: float, fps: float, quiet: bool) -> dict:
    from bench import map_memory

    with _progress(int(minutes), "map memory (simulated minutes)", quiet) as tick:
        return map_memory.run(minutes, fps, progress=lambda _s: tick(1))


def cmd_map_tradeoff(quiet: bool) -> dict:
    from bench import map_tradeoff

    n = len(map_tradeoff.SCENARIOS) * len(map_tradeoff.VARIANTS) * len(map_tradeoff.SEEDS)
    with _progress(n, "map trade-off flights", quiet) as tick:
        return map_tradeoff.run(progress=tick)


def cmd_timing(args) -> dict:
    from bench import timing

    return timing.run_all(repeats=args.repeats)


#: subcommands that are modules with their own argparse (``python -m bench NAME …`` = ``python -m bench.NAME …``)
OWN_COMMAND_LINE = ("hostile", "compute", "position_states", "telemetry_ablation", "too_near", "looming_truth", "campaign_diff",
                    "landmark_truth", "motion_split", "map_cells", "track_drift")


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] and argv[0] in OWN_COMMAND_LINE:  # its own command line (python -m bench.<name> --help)
        import importlib

        return importlib.import_module(f"bench.{argv[0]}").main(argv[1:])
    ap = argparse.ArgumentParser(
        prog="python -m bench",
        description="Benchmarks of the estimation core against the source papers' scenarios (seeds 000 and 004).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Examples:\n  python -m bench seed004 --runs 100\n"
               "  python -m bench timing --json\n"
               "  python -m bench looming --runs 20\n"
               "  python -m bench all --runs 200 --write docs/BENCHMARKS.md",
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    workers_default = min(2, os.cpu_count() or 1)
    for name, helptext in (("seed004", "seed-004 scenario: triangulation vs EKFs vs the Cramér–Rao bound"),
                           ("seed000", "seed-000 scenario: relative range error vs L"),
                           ("all", "every benchmark; --write rewrites its sections of the benchmarks document")):
        p = sub.add_parser(name, help=helptext, description=helptext)
        p.add_argument("--runs", type=int, default=100, help="Monte Carlo runs per case (default 100)")
        p.add_argument("--workers", type=int, default=workers_default, help=f"worker processes (default {workers_default})")
        p.add_argument("--json", action="store_true", help="print one JSON object instead of tables")
        if name == "seed004":
            p.add_argument("--ekf-iterations", type=int, default=2, choices=range(1, 21), metavar="N",
                           help="relinearizations of the anchored EKF's update (default 2, as the published tables; "
                                "1 = plain EKF; the shipped filter uses 3)")
            p.add_argument("--tri-max-rel-sigma", type=float, default=0.3, metavar="R",
                           help="the triangulation gate: a first range whose predicted σ/range exceeds R does not seed a "
                                "filter (default 0.3, the shipped [triangulation] max_rel_sigma; also gates the "
                                "longest-baseline row)")
            p.add_argument("--no-refine", action="store_true",
                           help="the anchored EKF without its batch refinement (refine_max_obs = 0, as the flight "
                                "configurations ship; the benchmark's default refines at 8, 16, 32, 64 and 128 frames)")
        if name == "all":
            p.add_argument("--write", metavar="FILE",
                           help="write the markdown report to FILE: the sections this command produces are replaced, "
                                "the sections other commands produced (hand-run campaigns) are kept where they were")
            p.add_argument("--repeats", type=int, default=50, help="timing repeats (default 50)")
    p = sub.add_parser("pipeline004", help="seed004_straight flown in flightsim and replayed through the whole pipeline",
                       description="seed004_straight flown in flightsim and replayed through the whole pipeline")
    p.add_argument("--runs", type=int, default=20, help="flights (seeds) (default 20)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p = sub.add_parser("sitl", help="lockstep SITL speed and the SITL campaigns (8 seeds per scenario)",
                       description="lockstep SITL speed and the SITL campaigns scored against truth; prints the "
                                   "'Software in the loop' section of docs/BENCHMARKS.md")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the section")
    p = sub.add_parser("looming", help="head-on approaches: range at the focus of expansion with and without looming",
                       description="head-on approaches (quad 4 m/s from 30 m, fixed-wing 25 m/s from 200 m, points 0–3° off "
                                   "the direction of travel; and a rendered wall tracked end to end): range error, "
                                   "convergence time and NEES with and without the looming measurement (docs/derivations/looming.md)")
    p.add_argument("--runs", type=int, default=20, help="Monte Carlo runs per synthetic case (default 20)")
    p.add_argument("--rendered-runs", type=int, default=3, help="rendered flights per case (default 3; 0 = skip)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p = sub.add_parser("map_memory", help="the obstacle map's size and RSS over a long synthetic hover in front of a wall",
                       description="a synthetic hover 5 m in front of a textured wall through the whole pipeline: the local "
                                   "obstacle map's size and the process's RSS once per simulated minute (docs/derivations/obstacle_map.md)")
    p.add_argument("--minutes", type=float, default=30.0, help="simulated hover, minutes (default 30)")
    p.add_argument("--fps", type=float, default=5.0, help="frames per simulated second (default 5)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the section")
    p = sub.add_parser("map_tradeoff", help="the map's publishing settings (support_radius_rel, max_entry_nis_ratio, remembered_spread_k, remembered_drop_spread_deg, infer_narrow_gap_m) in SITL",
                       description="quad_wall_hover, quad_slalom and quad_corner in lockstep SITL (2 seeds each) with "
                                   "configs/companion.toml as shipped and with one map setting changed at a time: remembered "
                                   "share, false obstacles, detection (docs/derivations/obstacle_map.md)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the section")
    p = sub.add_parser("avoidance", help="closed-loop avoidance campaigns: the simulated autopilot flies on the companion's ranges",
                       description="the quad commanded through a wall (3, 6, 10 m/s), a pole, a building corner and a slalom "
                                   "line in lockstep SITL with the simulated autopilot's avoidance (ArduPilot, PX4, PX4 with "
                                   "CP_GO_NO_DATA = 1) on the companion's ranges: collisions with 95 % intervals, stop "
                                   "clearance, false stops, progress (docs/derivations/sectors.md)")
    p.add_argument("--runs", type=int, default=20, help="seeds per scenario × model (default 20)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the section")
    sub.add_parser("hostile", help="soak and fuzz: long lockstep SITL hover under hostile MAVLink traffic and blackouts "
                                   "(options: python -m bench hostile --help)", add_help=False)
    sub.add_parser("telemetry_ablation", help="SITL campaigns with parts of the simulated telemetry error switched off: "
                                              "which error makes the forward σ over-confident (options: python -m bench "
                                              "telemetry_ablation --help)", add_help=False)
    sub.add_parser("too_near", help="the too-near cells of finished SITL campaigns split by cause (beside an obstacle, "
                                    "the k·σ offset, short) and the forward sector republished with other k (options: "
                                    "python -m bench too_near --help)", add_help=False)
    sub.add_parser("motion_split", help="detection in view of finished SITL campaigns by the vehicle's motion (turning in "
                                        "place, hovering, moving) and true range (options: python -m bench motion_split --help)",
                   add_help=False)
    sub.add_parser("looming_truth", help="the tracker's scale changes on rendered flights against the truth: the looming "
                                         "noise model checked (options: python -m bench looming_truth --help)", add_help=False)
    sub.add_parser("track_drift", help="the tracker's pixels against the points they were born on, on rendered flights, "
                                       "drift correction off and on (options: python -m bench track_drift --help)",
                   add_help=False)
    sub.add_parser("landmark_truth", help="each converged landmark's range and σ against the truth on a SITL flight "
                                          "flown with --landmark-log: z by true range (options: python -m bench "
                                          "landmark_truth --help)", add_help=False)
    sub.add_parser("map_cells", help="what the local obstacle map held where an obstacle out of view was reported unknown "
                                     "(options: python -m bench map_cells --help)", add_help=False)
    sub.add_parser("position_states", help="the anchored EKF under a Gauss–Markov position error, white model vs the "
                                           "position-error states: range NEES and coverage (options: python -m bench "
                                           "position_states --help)", add_help=False)
    sub.add_parser("compute", help="CPU per 640×480 frame of the whole pipeline on one core, compiled kernels vs the numpy "
                                   "reference (options: python -m bench compute --help)", add_help=False)
    p = sub.add_parser("timing", help="per-stage timings on one core", description="per-stage timings on one core")
    p.add_argument("--repeats", type=int, default=50, help="repeats per measurement; the median is reported")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    args = ap.parse_args(argv)
    if getattr(args, "runs", 1) < 1:
        ap.error("--runs must be >= 1")
    tri_max_rel_sigma = getattr(args, "tri_max_rel_sigma", 0.3)  # only `seed004` has the option
    if not (math.isfinite(tri_max_rel_sigma) and tri_max_rel_sigma > 0):
        ap.error("--tri-max-rel-sigma must be a positive number")

    if args.cmd == "seed004":
        res = cmd_seed004(args)
        print(json.dumps(report.seed004_json(res)) if args.json else report.seed004_markdown(res, args.runs))
    elif args.cmd == "seed000":
        res = cmd_seed000(args)
        print(json.dumps(res) if args.json else report.seed000_markdown(res))
    elif args.cmd == "pipeline004":
        from bench import pipeline_seed004

        res = cmd_pipeline004(args, args.runs)
        print(json.dumps(res) if args.json else pipeline_seed004.markdown(res))
    elif args.cmd == "sitl":
        res = cmd_sitl(args)
        print(json.dumps(res, default=str) if args.json else report.sitl_markdown(res))
    elif args.cmd == "looming":
        from bench import looming

        if args.rendered_runs < 0:
            ap.error("--rendered-runs must be >= 0")
        res = cmd_looming(args, args.runs, args.rendered_runs)
        print(json.dumps(res) if args.json else looming.markdown(res))
    elif args.cmd == "map_memory":
        from bench import map_memory

        res = cmd_map_memory(args.minutes, args.fps, args.json)
        print(json.dumps(res) if args.json else map_memory.markdown(res))
    elif args.cmd == "map_tradeoff":
        from bench import map_tradeoff

        res = cmd_map_tradeoff(args.json)
        print(json.dumps(res) if args.json else map_tradeoff.markdown(res))
    elif args.cmd == "avoidance":
        from bench import avoidance

        res = avoidance.run_all(args.runs)
        print(json.dumps(res, default=str) if args.json else avoidance.markdown(res))
    elif args.cmd == "timing":
        res = cmd_timing(args)
        print(json.dumps(report.timing_json(res)) if args.json else report.timing_markdown(res))
    else:
        from bench import avoidance, flightsim_bench, latency

        res = {"seed004": cmd_seed004(args), "seed000": cmd_seed000(args), "timing": cmd_timing(args),
               "latency": latency.run_all(), "pipeline004": cmd_pipeline004(args, max(5, args.runs // 10)),
               "flightsim": flightsim_bench.run_all(), "sitl": cmd_sitl(args),
               "looming": cmd_looming(args, max(5, args.runs // 10), 3),
               "map_memory": cmd_map_memory(30.0, 5.0, args.json), "map_tradeoff": cmd_map_tradeoff(args.json),
               "avoidance": avoidance.run_all(20)}
        if args.json:
            print(json.dumps(res))
        else:
            from bench import looming, map_memory, map_tradeoff

            text = (report.full_markdown(res, args.runs, args.repeats).rstrip("\n") + "\n\n" + looming.markdown(res["looming"])
                    + "\n\n## Local obstacle map: memory over a long hover (issue 11)\n\n" + map_memory.markdown(res["map_memory"])
                    + "\n\n## Local obstacle map: publishing trade-offs (issue 11)\n\n" + map_tradeoff.markdown(res["map_tradeoff"])
                    + "\n\n## Closed-loop avoidance (issue 12)\n\n" + avoidance.markdown(res["avoidance"]) + "\n")
            if args.write:
                existing = ""
                if os.path.isfile(args.write):
                    with open(args.write, encoding="utf-8") as fh:
                        existing = fh.read()
                with open(args.write, "w", encoding="utf-8") as fh:
                    fh.write(report.merge_document(existing, text))
                print(f"wrote {args.write} (its sections from other commands kept)", file=sys.stderr)
            print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
