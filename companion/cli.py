"""``companion`` command line: ``run`` (the live process), ``replay`` (a recorded flight offline) and
``monitor`` (a ground-station view of a running companion, :mod:`companion.monitor`).

Exit codes (:mod:`companion.errors`): 0 = done (``run`` and ``monitor``: also a clean stop by
Ctrl-C / SIGTERM), 2 = usage, configuration or input-file error (the message names the argument,
file, table or key), 1 = runtime failure; ``replay`` interrupted: 130 (Ctrl-C) or 143 (SIGTERM),
with nothing at the output path (the ranges so far in ``OUT.partial``).
"""

from __future__ import annotations

import os

# One thread for the BLAS behind numpy (set before numpy is imported): the companion's matrices are
# tiny, and an idle OpenBLAS worker spinning on a second core burns CPU the onboard computer needs
# (several seconds per minute of flight were measured). A value set by the user is kept.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402 (after the thread settings)
import dataclasses
import logging
import math
import signal
import sys
import threading
import time
from pathlib import Path

from companion.errors import EXIT_OK, EXIT_RUNTIME, EXIT_USAGE, CompanionError, ConfigError, Terminated
from companion.interrupts import interrupt_exit_code, interrupt_in, interrupt_name, raise_on_sigterm

log = logging.getLogger("companion")

#: commands for which Ctrl-C / SIGTERM is the normal way to stop (exit 0); the others exit 130 / 143
_SIGNAL_STOPS_CLEANLY = ("run", "monitor")

_DESCRIPTION = """\
Monocular obstacle ranging for a drone companion computer.

Reads the autopilot's telemetry over MAVLink and frames from one camera, tracks Harris corners
with NCC, ranges them by triangulation and an inverse-depth EKF, and publishes obstacle sectors
to the autopilot as OBSTACLE_DISTANCE (72 × 5°, body FRD) and DISTANCE_SENSOR (forward), plus
diagnostics and STATUSTEXT; HEARTBEAT is ACTIVE only while valid ranges are produced.
"""

_RUN_EPILOG = """\
connection strings (pymavlink):
  /dev/ttyAMA0 (baud from [link] baud, or /dev/ttyAMA0,921600), udpin:0.0.0.0:14550,
  udpout:192.168.1.10:14550, tcp:127.0.0.1:5760
camera sources:
  0 (device index), /dev/video0, rtsp://host/stream, http://host/stream.mjpg, video.avi,
  sim://127.0.0.1:5600 (the simulator's frame transport)

clocks (--clock):
  monotonic  the host's monotonic clock, mapped onto the autopilot's by TIMESYNC (real flights,
             real-time simulation).
  sim        lockstep with flightsim (flightsim sitl --clock lockstep): "now" is the autopilot's
             boot clock as heard (SYSTEM_TIME / time_boot_ms of its messages / frame capture
             stamps) plus the companion's own processing, --sim-processing-ms per frame (or the
             measured time without it). The companion runs one round per frame: poll the link,
             process, publish, acknowledge the frame; the simulator waits for that acknowledgement,
             so the run is deterministic and as fast as the CPU allows. Needs --camera sim://.
             Details: companion/simclock.py.

examples:
  companion run --mavlink /dev/ttyAMA0,921600 --camera 0 --config configs/companion.toml
  companion run --mavlink udpin:0.0.0.0:14550 --camera sim://127.0.0.1:5600 --gcs udpout:10.0.0.2:14550
  companion run --mavlink udpout:127.0.0.1:14550 --camera sim://127.0.0.1:5600 --clock sim \\
      --sim-processing-ms 25 --camera-config out/sitl/camera.toml --config configs/companion.toml
"""

_REPLAY_EPILOG = """\
The output tlog holds what the companion would have sent to the autopilot, from the vehicle's
system id and component 196, each message stamped on the recording's clock when it would have
left (frame capture + wait for telemetry + measured processing time).

example:
  companion replay --tlog out/telemetry.tlog --video out/video.avi --frames out/frames.csv \\
      --out out/ranges.tlog --config configs/companion.toml --plot out/ranges.png
"""


_MONITOR_EPILOG = """\
exit codes: 0 = done (also Ctrl-C), 2 = bad arguments or a connection that cannot be opened,
1 = with --once: nothing heard from the companion.

examples:
  companion monitor udpin:0.0.0.0:14550
  companion monitor udpin:0.0.0.0:14550 --once --json          # one JSON snapshot after 3 s
  companion monitor udpin:0.0.0.0:14550 --json --interval 0.5 > monitor.jsonl
"""


_CHECK_EPILOG = """\
checks (one line each, PASS / WARN / FAIL with the measured numbers):
  link                 the MAVLink connection opens
  heartbeat            a HEARTBEAT arrives from the vehicle's autopilot component (WARN: MAVLink 1)
  ATTITUDE             arrives at >= [link] min_rate_fraction of the rate the companion asks for
  LOCAL_POSITION_NED   likewise (the pipeline needs both)
  GLOBAL_POSITION_INT  likewise, but only WARN when missing (not used for the ranges)
  timesync             the companion's TIMESYNC estimate converged and held steady
  camera               frames of the configured size arrive at the expected rate (--fps, else
                       [camera_source] device_fps; at least one per [pipeline] camera_timeout_s)
  calibration          focal lengths plausible for the image size, principal point inside the image,
                       distortion finite and invertible over the image

Ends as soon as everything passed, else after --timeout seconds.
exit codes: 0 = the companion would produce ranges (warnings allowed), 1 = a check failed,
2 = bad arguments or input files (configuration, calibration, camera TOML).

examples:
  companion check --mavlink /dev/ttyAMA0,921600 --camera 0 --config configs/companion.toml
  companion check --mavlink udpin:0.0.0.0:14550 --camera sim://127.0.0.1:5600 --json --timeout 5
"""


class _Parser(argparse.ArgumentParser):
    """argparse that names the command in errors and exits 2 (usage)."""

    def error(self, message):  # pragma: no cover - exercised through main()
        self.print_usage(sys.stderr)
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="companion", description=_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=_version())
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    r = sub.add_parser("run", help="run the companion process (live MAVLink link and camera)",
                       description="Run the companion: range obstacles from the camera and publish them to the autopilot.",
                       epilog=_RUN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    r.add_argument("--mavlink", required=True, metavar="CONN", help="autopilot connection (pymavlink connection string)")
    r.add_argument("--camera", required=True, metavar="SRC",
                   help="camera: device index, /dev/videoN, RTSP/HTTP URL, video file or sim://HOST:PORT")
    _common(r)
    r.add_argument("--gcs", metavar="CONN", help="extra ground-station output with its own rate limits ([outputs] gcs_*)")
    r.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: run until Ctrl-C / SIGTERM)")
    r.add_argument("--sector-log", metavar="FILE",
                   help="write one JSON line per OBSTACLE_DISTANCE sent to the autopilot: its time_usec and distances and, "
                        "per sector, where the claim came from (live points, live and remembered, remembered only, inferred across "
                        "sectors, inferred from points above or below the band); "
                        "~20 MB an hour at 15 Hz (companion/sector_log.py)")
    r.add_argument("--landmark-log", metavar="FILE",
                   help="write one JSON line per processed frame with every landmark the estimator holds: its point, range, "
                        "σ, mean NIS, converged and valid flags, the camera pose and the map's remembered points; ~15 MB a minute at 15 Hz "
                        "with 300 landmarks, more with a full map, "
                        "for the flights that need explaining (companion/landmark_log.py)")
    r.add_argument("--camera-config", metavar="TOML",
                   help="a TOML whose [camera] table replaces the config's (e.g. the camera.toml flightsim writes)")
    r.add_argument("--clock", choices=("monotonic", "sim"), default="monotonic",
                   help="monotonic (default) or sim: lockstep with the flightsim simulator (see 'clocks' below)")
    r.add_argument("--sim-processing-ms", type=float, metavar="MS",
                   help="with --clock sim: each processed frame advances the clock by MS (deterministic runs); "
                        "default: the measured processing time")
    r.set_defaults(func=cmd_run)

    q = sub.add_parser("replay", help="run the same pipeline offline on a recorded flight",
                       description="Replay a recorded flight (tlog + video + frames.csv) through the pipeline and write "
                                   "what would have been sent as a MAVLink 2 tlog.",
                       epilog=_REPLAY_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    q.add_argument("--tlog", required=True, help="the flight's telemetry.tlog (MAVLink 2)")
    q.add_argument("--video", required=True, help="the flight's video (e.g. video.avi, MJPG)")
    q.add_argument("--frames", required=True, help="frames.csv: 'index,t_s' per frame, capture time on the tlog's clock")
    q.add_argument("--out", required=True, help="output tlog (ranges.tlog); written when the replay is complete "
                                                "(interrupted: nothing there, the ranges so far in OUT.partial)")
    _common(q)
    q.add_argument("--camera-config", metavar="TOML",
                   help="a TOML whose [camera] table replaces the config's (default: camera.toml next to the video, if present)")
    q.add_argument("--plot", metavar="PNG", help="plot of the ranges over time (default: the --out path with .png)")
    q.add_argument("--no-plot", action="store_true", help="do not draw the plot")
    q.add_argument("--truth", metavar="NPZ", help="flightsim truth.npz drawn on the plot (default: truth.npz next to the video, "
                                                  "if present)")
    q.add_argument("--fixed-processing-ms", type=float, metavar="MS",
                   help="stamp messages with this processing time instead of the measured one (deterministic output)")
    q.add_argument("--telemetry-latency-ms", type=float, default=0.0, metavar="MS",
                   help="transport delay of the logged telemetry, removed from the clock mapping (default 0)")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.add_argument("--sector-log", metavar="FILE", help="also write the sector log (as 'companion run --sector-log': "
                   "per OBSTACLE_DISTANCE, where each sector's claim came from)")
    q.add_argument("--landmark-log", metavar="FILE", help="also write the landmark log (as 'companion run --landmark-log': "
                   "per processed frame, every landmark's point, range, σ and flags)")
    q.set_defaults(func=cmd_replay)

    c = sub.add_parser("check", help="pre-flight check: link, heartbeat, telemetry rates, TIMESYNC, camera, calibration",
                       description="Open the link and the camera as 'companion run' would and check, one line each, that the "
                                   "companion would produce ranges.",
                       epilog=_CHECK_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("--mavlink", required=True, metavar="CONN", help="autopilot connection (pymavlink connection string)")
    c.add_argument("--camera", required=True, metavar="SRC",
                   help="camera: device index, /dev/videoN, RTSP/HTTP URL, video file or sim://HOST:PORT")
    c.add_argument("--config", metavar="TOML", help="companion configuration TOML, as for 'companion run'; default: the shipped "
                                                    "configs/companion.toml")
    c.add_argument("--calibration", metavar="YAML", help="OpenCV calibration file (camera_matrix, distortion_coefficients); "
                                                         "replaces the intrinsics of [camera]")
    c.add_argument("--camera-config", metavar="TOML",
                   help="a TOML whose [camera] table replaces the config's (e.g. the camera.toml flightsim writes)")
    c.add_argument("--timeout", type=float, default=8.0, metavar="S",
                   help="give up on what has not passed after S seconds (default 8)")
    c.add_argument("--fps", type=float, metavar="HZ",
                   help="the camera's expected frame rate (default: [camera_source] device_fps if set, else only the "
                        "companion's minimum, one frame per camera_timeout_s)")
    c.add_argument("--json", action="store_true", help="print the results as one JSON object instead of lines")
    c.add_argument("--log-level", default="WARNING", type=str.upper, choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="log verbosity on stderr (default WARNING)")
    c.set_defaults(func=cmd_check)

    k = sub.add_parser("kernels", help="compile (or load from the cache) the compiled kernels and say which ones run",
                       description="Compile the companion's numba kernels into their disk cache (NUMBA_CACHE_DIR, else next "
                                   "to the installed modules), or load them when they are already there, and print which "
                                   "kernels this machine runs. Run it once after an install, as the user and with the "
                                   "environment the service uses: compiling takes a minute or more on a small computer, and a "
                                   "process that compiled keeps LLVM's memory (~250 MiB more than one that loaded them), so "
                                   "the flight process should only load them.",
                       epilog="exit codes: 0 = kernels ready (or the numpy reference in use, said so), 1 = compiling failed.\n"
                              "example:\n  NUMBA_CACHE_DIR=/var/cache/companion companion kernels",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    k.add_argument("--log-level", default="WARNING", type=str.upper, choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="log verbosity on stderr (default WARNING)")
    k.set_defaults(func=cmd_kernels)

    mo = sub.add_parser("monitor", help="ground-station view of a running companion: sectors, nearest range, health",
                        description="Listen where the companion's messages arrive and show its live sectors, nearest range, "
                                    "forward DISTANCE_SENSOR, HEARTBEAT health, diagnostics, STATUSTEXT and message rates "
                                    "Sectors older than 0.5 s are shown STALE; no HEARTBEAT for 3 s = LINK LOST.",
                        epilog=_MONITOR_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    mo.add_argument("conn", metavar="CONN", help="pymavlink connection string, e.g. udpin:0.0.0.0:14550 (the companion's "
                                                 "--gcs udpout:HOST:14550), tcp:127.0.0.1:5760, /dev/ttyUSB0,57600")
    mo.add_argument("--component", type=int, default=196, metavar="ID", help="the companion's component id (default 196)")
    mo.add_argument("--system", type=int, default=0, metavar="ID", help="its system id (default 0: the first one heard)")
    mo.add_argument("--once", action="store_true", help="print one snapshot after --duration seconds (default 3) and exit; "
                                                        "exit 1 if the companion was not heard")
    mo.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    mo.add_argument("--interval", type=float, default=1.0, metavar="S",
                    help="seconds between snapshots when stdout is not a terminal or with --json (default 1)")
    mo.add_argument("--json", action="store_true", help="one JSON object per line instead of the view")
    mo.add_argument("--passive", action="store_true", help="send nothing (by default a GCS HEARTBEAT goes out at 1 Hz)")
    mo.add_argument("--near", type=float, default=5.0, metavar="M", help="obstacles nearer than M metres are red (default 5)")
    mo.add_argument("--mid", type=float, default=15.0, metavar="M", help="nearer than M metres yellow, farther green (default 15)")
    mo.add_argument("--log-level", default="WARNING", type=str.upper, choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                    help="log verbosity on stderr (default WARNING)")
    mo.set_defaults(func=cmd_monitor)
    return p


def _common(sp) -> None:
    sp.add_argument("--config", metavar="TOML", help="companion configuration TOML (a full file, or an overlay: extends = \"companion.toml\" plus the keys it changes); default: the shipped configs/companion.toml")
    sp.add_argument("--calibration", metavar="YAML", help="OpenCV calibration file (camera_matrix, distortion_coefficients); "
                                                          "replaces the intrinsics of [camera]")
    sp.add_argument("--log-level", default="INFO", type=str.upper,
                    choices=("DEBUG", "INFO", "WARNING", "ERROR"), help="log verbosity (default INFO)")


def _version() -> str:
    """``companion X.Y.Z`` from the installed distribution's metadata."""
    from companion import DISTRIBUTION, package_version

    return f"companion {package_version()} ({DISTRIBUTION})"


# ---------------------------------------------------------------------- configuration ----------
@dataclasses.dataclass(frozen=True)
class RunConfig:
    companion: object  # CompanionConfig
    camera_source: object  # CameraSourceConfig
    pipeline: object  # PipelineConfig


def load_config(path: str | None, calibration: str | None = None, camera_config: str | None = None) -> RunConfig:
    """The whole :class:`CompanionConfig` from ``path`` (the shipped ``companion.toml`` when None),
    with the camera replaced by a flightsim ``camera.toml`` and/or an OpenCV calibration file when given."""
    from companion.config import from_mapping
    from companion.io.config_files import load_companion_config, load_opencv_calibration, read_toml

    cfg = load_companion_config(path or None)
    if camera_config:
        cam_data = read_toml(camera_config)
        if "camera" not in cam_data:
            raise ConfigError(f"{camera_config}: no [camera] table")
        from companion.core.camera import CameraConfig

        try:
            cam = from_mapping(CameraConfig, cam_data["camera"], "camera")
        except ConfigError as exc:
            raise ConfigError(f"{camera_config}: {exc}") from None
        cfg = dataclasses.replace(cfg, camera=cam)
    if calibration:
        cfg = dataclasses.replace(cfg, camera=load_opencv_calibration(calibration, cfg.camera))
    return RunConfig(cfg, cfg.camera_source, cfg.pipeline)


def check_connection_string(option: str, conn: str) -> None:
    """Catch malformed UDP/TCP connection strings up front (a missing serial device is retried instead)."""
    low = conn.lower()
    if low.startswith(("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:")):
        parts = conn.split(":")
        if len(parts) != 3 or not parts[1]:
            raise ConfigError(f"{option} {conn!r}: expected KIND:HOST:PORT, e.g. udpin:0.0.0.0:14550")
        try:
            port = int(parts[2])
        except ValueError:
            raise ConfigError(f"{option} {conn!r}: port {parts[2]!r} is not a number") from None
        if not 0 <= port <= 65535 or (port == 0 and not low.startswith("udpin:")):
            raise ConfigError(f"{option} {conn!r}: port {port} out of range")


def _setup_logging(level: str) -> None:
    logging.basicConfig(level=getattr(logging, level), stream=sys.stderr,
                        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s", datefmt="%H:%M:%S")


# ---------------------------------------------------------------------- run --------------------
def cmd_run(args) -> int:
    from companion.mavlink.dialect import mavlink  # noqa: F401  (first: MAVLink 2)
    from companion.camera_sources import open_source
    from companion.mavlink.link import MavLink
    from companion.app import Companion
    from companion.telemetry import TelemetryBuffer

    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ConfigError(f"--duration must be a positive number of seconds, got {args.duration}")
    check_connection_string("--mavlink", args.mavlink)
    if args.gcs:
        check_connection_string("--gcs", args.gcs)
    sim_clock = None
    clock = time.monotonic
    if args.clock == "sim":
        from companion.camera_sources import parse_camera_spec
        from companion.simclock import SimClock

        if parse_camera_spec(args.camera)[0] != "sim":
            raise ConfigError(f"--clock sim needs the simulator's frames (--camera sim://HOST:PORT), got {args.camera!r}")
        p_ms = args.sim_processing_ms
        if p_ms is not None and not (math.isfinite(p_ms) and 0 <= p_ms < 10_000):
            raise ConfigError(f"--sim-processing-ms must be in [0, 10000), got {p_ms}")
        sim_clock = clock = SimClock(None if p_ms is None else p_ms / 1000.0)
    elif args.sim_processing_ms is not None:
        raise ConfigError("--sim-processing-ms needs --clock sim")
    if args.camera_config is not None and not Path(args.camera_config).is_file():
        raise ConfigError(f"--camera-config {args.camera_config}: no such file")
    rc = load_config(args.config, args.calibration, args.camera_config)
    cfg = rc.companion
    cam = cfg.camera
    log.info("camera %d×%d, fx %.1f fy %.1f, filter %s, outputs: OBSTACLE_DISTANCE %.0f Hz to the autopilot%s",
             cam.width, cam.height, cam.fx, cam.fy, cfg.estimator.filter, cfg.outputs.autopilot_obstacle_distance_hz,
             f", {cfg.outputs.gcs_obstacle_distance_hz:.0f} Hz to the ground station" if args.gcs else "")
    # compile (or load from the cache) the kernels before the link and the camera open: a simulator
    # or an autopilot sees the companion only once it can process frames at full speed
    from companion.core import jit

    t0 = time.perf_counter()
    if jit.ENABLED:
        log.info("%s (the first start after an install compiles them: a minute or more)", jit.WARMUP_STARTED)
        jit.warm_up()
        log.info("%s; %s %.1f s", jit.describe(), jit.WARMUP_DONE, time.perf_counter() - t0)
    else:
        log.info("%s", jit.describe())
    link = gcs = source = sector_log = landmark_log = None
    stop = threading.Event()

    def _stop(signum, _frame):
        log.info("%s received: stopping", signal.Signals(signum).name)
        stop.set()

    old = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        link = MavLink(args.mavlink, cfg.link, clock=clock, telemetry=TelemetryBuffer(cfg.telemetry),
                       boot_time_observer=sim_clock.observe if sim_clock is not None else None,
                       clock_offset_s=0.0 if sim_clock is not None else None)
        if args.gcs:
            gcs = MavLink(args.gcs, cfg.link, clock=clock, role="gcs")
        source = open_source(args.camera, cam.width, cam.height, rc.camera_source, clock=clock,
                             clock_map=link.telemetry.to_companion)
        if args.sector_log:
            from companion.sector_log import SectorLog

            sector_log = SectorLog(args.sector_log)
        companion = Companion(cfg, source, link, gcs, rc.pipeline, camera=cam, clock=clock, sector_sink=sector_log)
        if args.landmark_log:
            from companion.landmark_log import LandmarkLog

            landmark_log = LandmarkLog(args.landmark_log)
            companion.pipeline.landmark_sink = landmark_log
        if sim_clock is not None:
            log.info("lockstep clock (--clock sim): simulation time, %s per processed frame",
                     "measured processing time" if sim_clock.processing_s is None else f"{sim_clock.processing_s * 1000:g} ms")
        companion.run(stop, duration=args.duration, lockstep=sim_clock is not None)
        if source.size_error:
            raise ConfigError(source.size_error)
        log.info("stopped: %s; pipeline: %s; outputs: %s", dict(companion.counters), dict(sorted(companion.pipeline.counters.items())),
                 dict(sorted(companion.reporter.counters.items())))
        if sector_log is not None:
            log.info("sector log %s: %d lines%s", sector_log.path, sector_log.lines, " (ended by a write error)" if sector_log.failed else "")
        if landmark_log is not None:
            log.info("landmark log %s: %d frames%s", landmark_log.path, landmark_log.lines,
                     " (ended by a write error)" if landmark_log.failed else "")
        if sim_clock is not None:
            ts = link.timesync
            off = ts.offset_s
            log.info("lockstep clock at %.3f s; TIMESYNC: %d requests, %d answers accepted, estimate %s (0 by construction)",
                     sim_clock(), ts.counters.get("requests", 0), ts.counters.get("accepted", 0),
                     "none" if off is None else f"{off * 1000:+.1f} ms")
            lw = companion.lockstep_wall
            n = max(1, lw["rounds"])
            log.info("lockstep rounds: %d, wall %.3f s working (%.1f ms per round), %.3f s waiting for frames",
                     lw["rounds"], lw["work_s"], 1000 * lw["work_s"] / n, lw["wait_s"])
            stages = ", ".join(f"{k} {1000 * lw[f'{k}_cpu_s'] / n:.1f}" for k in ("track", "estimate", "map", "sectors")
                               if f"{k}_cpu_s" in lw)
            log.info("lockstep CPU per round: %.1f ms in the loop's thread: pipeline %.1f ms (%s), the rest %.1f ms "
                     "(frame receive, MAVLink in and out, telemetry, reporter, acknowledgement)",
                     1000 * lw["cpu_s"] / n, 1000 * lw["pipeline_cpu_s"] / n, stages or "-",
                     1000 * (lw["cpu_s"] - lw["pipeline_cpu_s"]) / n)
        return EXIT_OK
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        for thing in (source, link, gcs, sector_log, landmark_log):
            if thing is not None:
                try:
                    thing.close()
                except Exception:
                    pass


# ---------------------------------------------------------------------- replay ------------------



def cmd_replay(args) -> int:
    from companion.io.progress import installed
    from companion.io.atomic import partial_path
    from companion.io.inputs import check_input_file
    from companion.replay import replay

    for name, what in (("tlog", "tlog"), ("video", "video file"), ("frames", "frames file")):
        try:
            check_input_file(getattr(args, name), what)
        except ConfigError as exc:
            raise ConfigError(f"--{name} {exc}") from None
    out = Path(args.out)
    if not out.parent.is_dir():
        raise ConfigError(f"--out {out}: directory {out.parent} does not exist")
    if out.is_dir():
        raise ConfigError(f"--out {out}: is a directory; give the file to write (e.g. {out / 'ranges.tlog'})")
    if args.fixed_processing_ms is not None and not (math.isfinite(args.fixed_processing_ms) and args.fixed_processing_ms >= 0):
        raise ConfigError(f"--fixed-processing-ms must be >= 0, got {args.fixed_processing_ms}")
    if not (math.isfinite(args.telemetry_latency_ms) and 0 <= args.telemetry_latency_ms < 1000):
        raise ConfigError(f"--telemetry-latency-ms must be in [0, 1000), got {args.telemetry_latency_ms}")
    cam_cfg = args.camera_config
    if cam_cfg is None:
        beside = Path(args.video).with_name("camera.toml")
        if beside.is_file() and not args.calibration:
            cam_cfg = str(beside)
            log.info("using the camera of %s (next to the video); --camera-config overrides", beside)
    if args.no_plot:
        args.plot = None
    elif not installed("matplotlib"):  # the onboard install has no plotting (the `sim` extra brings it)
        if args.plot is not None:
            raise ConfigError(f"--plot {args.plot}: plotting needs matplotlib (pip install 'monorange[sim]'), "
                              "or leave out --plot")
        log.info("no plot: matplotlib is not installed (pip install 'monorange[sim]')")
    elif args.plot is None:
        args.plot = str(out.with_suffix(".png"))
    truth = args.truth
    if truth is None and args.plot:
        beside = Path(args.video).with_name("truth.npz")
        truth = str(beside) if beside.is_file() else None
    elif truth is not None and not Path(truth).is_file():
        raise ConfigError(f"--truth {truth}: no such file")
    rc = load_config(args.config, args.calibration, cam_cfg)
    cam = rc.companion.camera
    log.info("replaying %s with a %d×%d camera (fx %.1f), %s EKF", args.video, cam.width, cam.height, cam.fx,
             rc.companion.estimator.filter)
    from companion.io.progress import ProgressBar

    sector_log = landmark_log = None
    if args.sector_log:
        from companion.sector_log import SectorLog

        sector_log = SectorLog(args.sector_log)
    if args.landmark_log:
        from companion.landmark_log import LandmarkLog

        landmark_log = LandmarkLog(args.landmark_log)
    try:
        with ProgressBar("replay", enabled=None if not args.quiet else False) as bar:
            s = replay(args.tlog, args.video, args.frames, out, rc.companion, camera=cam, pipeline=rc.pipeline,
                       plot=args.plot, telemetry_latency_s=args.telemetry_latency_ms / 1000.0,
                       progress=lambda done, total: bar.update(done, total), truth=truth, sector_sink=sector_log,
                       landmark_sink=landmark_log,
                       fixed_processing_s=None if args.fixed_processing_ms is None else args.fixed_processing_ms / 1000.0)
    except BaseException as exc:
        if interrupt_exit_code(exc) is not None:
            part = partial_path(out)
            log.warning("%s not written%s", out, f"; the ranges so far are in {part}" if part.is_file() else "")
        raise
    finally:
        for sink in (sector_log, landmark_log):
            if sink is not None:
                sink.close()
    fails = ", ".join(f"{k}: {v}" for k, v in sorted(s.failed.items())) or "none"
    print(f"replayed {s.frames} frames ({s.recording_s:.1f} s of flight) in {s.wall_s:.1f} s: {s.processed} with valid sectors, "
          f"{s.stale} stale, {s.superseded} superseded; without ranges: {fails}")
    if s.rejected:
        print(f"rejected video frames: {s.rejected}")
    print(f"latency capture → send: p50 {s.latency_p50_ms:.1f} ms, p99 {s.latency_p99_ms:.1f} ms; first valid sector after "
          + (f"{s.first_valid_s:.2f} s" if s.first_valid_s is not None else "never"))
    if s.processed:
        from companion.core import jit

        stages = ", ".join(f"{k} {v:.1f}" for k, v in s.stage_cpu_ms.items())
        print(f"CPU per frame: mean {s.cpu_ms_mean:.1f} ms, p99 {s.cpu_ms_p99:.1f} ms ({stages}); {jit.describe()}")
    print(f"wrote {sum(s.messages.values())} messages to {s.out} as system {s.system_id}: "
          + ", ".join(f"{k} {v}" for k, v in sorted(s.messages.items())))
    if s.plot:
        print(f"plot: {s.plot}")
    return EXIT_OK


# ---------------------------------------------------------------------- check -------------------
def cmd_check(args) -> int:
    """``companion check``: exit 0 when the companion would produce ranges, 1 when a check failed."""
    import json

    from companion.camera_sources import parse_camera_spec
    from companion.check import run_check

    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise ConfigError(f"--timeout must be a positive number of seconds, got {args.timeout}")
    if args.fps is not None and not (math.isfinite(args.fps) and 0 < args.fps < 1000):
        raise ConfigError(f"--fps must be a frame rate in (0, 1000), got {args.fps}")
    check_connection_string("--mavlink", args.mavlink)
    parse_camera_spec(args.camera)  # a malformed address or a missing video file is a usage error
    if args.camera_config is not None and not Path(args.camera_config).is_file():
        raise ConfigError(f"--camera-config {args.camera_config}: no such file")
    cfg = load_config(args.config, args.calibration, args.camera_config).companion
    fps = args.fps if args.fps is not None else cfg.camera_source.device_fps
    report = run_check(args.mavlink, args.camera, cfg, timeout_s=args.timeout, expected_fps=fps)
    print(json.dumps(report.to_json(), indent=2) if args.json else report.text(), flush=True)
    return report.exit_code


def cmd_kernels(args) -> int:
    """``companion kernels``: compile or load every kernel now (docs/derivations/compute.md)."""
    import companion.app  # noqa: F401  (registers every kernel's warm-up, as `companion run` does)
    from companion.core import jit

    t0 = time.perf_counter()
    try:
        n = jit.warm_up()
    except Exception as exc:  # a broken numba / llvmlite install: say so, the reference still works
        print(f"companion kernels: compiling failed: {exc!r}; run with COMPANION_KERNELS=numpy to use the numpy reference",
              file=sys.stderr)
        return EXIT_RUNTIME
    if n:
        print(f"{jit.describe()}: {n} kernel groups ready in {time.perf_counter() - t0:.1f} s")
    else:
        print(jit.describe())
    return EXIT_OK


# ---------------------------------------------------------------------- monitor -----------------
def cmd_monitor(args) -> int:
    from companion.io.progress import installed

    if not args.json and not installed("rich"):
        raise ConfigError("companion monitor's view needs rich (pip install 'monorange[gcs]'); --json works without it")
    from companion.monitor.runner import cmd_monitor as run

    check_connection_string("CONN", args.conn)
    return run(args)


# ---------------------------------------------------------------------- entry point -------------
def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # exits 2 on usage errors
    _setup_logging(args.log_level)
    try:
        with raise_on_sigterm():  # SIGTERM unwinds like Ctrl-C (run and monitor install their own handlers)
            return args.func(args)
    except ConfigError as exc:
        print(f"companion {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (KeyboardInterrupt, Terminated) as exc:
        if args.command in _SIGNAL_STOPS_CLEANLY:
            log.info("interrupted")
            return EXIT_OK
        print(f"companion {args.command}: {interrupt_name(exc)}", file=sys.stderr)
        return interrupt_exit_code(exc)
    except CompanionError as exc:
        log.error("%s", exc)
        return EXIT_RUNTIME
    except Exception as exc:  # a bug: say so, with the traceback in the log
        stop = interrupt_in(exc)
        if stop is not None:  # a signal that surfaced inside a C extension's call
            if args.command in _SIGNAL_STOPS_CLEANLY:
                log.info("interrupted")
                return EXIT_OK
            print(f"companion {args.command}: {interrupt_name(stop)}", file=sys.stderr)
            return interrupt_exit_code(stop)
        log.exception("companion %s failed: %r", args.command, exc)
        return EXIT_RUNTIME


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
