"""``flightsim`` command line (also ``python -m flightsim``).

  flightsim fly configs/scenarios/X.toml --out DIR [--seed N] [--no-plot]

Exit codes: 0 done, 2 a bad scenario/world/argument (the message names it), 1 a failure in flight.
"""

from __future__ import annotations

import argparse
import logging
import sys

from companion.errors import ConfigError

log = logging.getLogger("flightsim")


def _progress_bar(label: str):
    if not sys.stderr.isatty():
        return None, None
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    bar = Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(), transient=True)
    task = bar.add_task(label, total=None)

    def tick(done: int, total: int) -> None:
        bar.update(task, completed=done, total=total)

    return bar, tick


def cmd_fly(args) -> int:
    from flightsim.fly import fly
    from flightsim.scenario import load_scenario

    sc = load_scenario(args.scenario, seed=args.seed)
    log.info("flying %s (%s, %.1f s, seed %d) into %s", sc.meta.name, sc.vehicle.aircraft, sc.meta.duration_s, sc.meta.seed, args.out)
    bar, tick = _progress_bar(f"fly {sc.meta.name}")
    if bar:
        bar.start()
    try:
        res = fly(sc, args.out, progress=tick, plot=not args.no_plot)
    finally:
        if bar:
            bar.stop()
    print(f"{sc.meta.name}: {res.frames} frames, {res.messages} MAVLink messages, {res.duration_s:g} s flown "
          f"in {res.wall_s:.1f} s ({res.realtime_factor:.1f}× real time) → {res.out_dir}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="flightsim",
        description="JSBSim flights with a rendered camera, autopilot-grade MAVLink telemetry and ground truth.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example:\n  flightsim fly configs/scenarios/quad_approach.toml --out out/quad\n\n"
               "Output: telemetry.tlog (MAVLink 2), video.avi + frames.csv (capture times on the tlog's clock),\n"
               "truth.npz, camera.toml, summary.png, flight.json.",
    )
    ap.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"], help="logging level (default INFO)")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("fly", help="fly a scenario and export a replayable flight log",
                       description="Fly a scenario (configs/scenarios/*.toml) as fast as the CPU allows and write "
                                   "telemetry.tlog, video.avi, frames.csv, truth.npz and a summary plot into --out.")
    p.add_argument("scenario", help="scenario TOML file")
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument("--seed", type=int, default=None, help="override the scenario's [scenario] seed")
    p.add_argument("--no-plot", action="store_true", help="skip summary.png")
    args = ap.parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        if args.cmd == "fly":
            return cmd_fly(args)
    except ConfigError as exc:
        print(f"flightsim: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("flightsim: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
