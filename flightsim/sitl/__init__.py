"""Software-in-the-loop run: the simulator plays the autopilot and the camera to a live companion.

``flightsim sitl configs/scenarios/X.toml --out DIR`` (:func:`run_sitl`) flies the scenario with
the same per-step loop as ``flightsim fly`` (:class:`flightsim.fly.Flight`) and, instead of
writing the autopilot's messages to a file, speaks them over real sockets on 127.0.0.1:

* MAVLink 2 over UDP (:mod:`flightsim.autopilot`): the simulator binds ``127.0.0.1:PORT`` (14550
  on the command line, like ArduPilot SITL's ground-station port; a free port from the API) and
  the companion connects with ``udpout:127.0.0.1:PORT``.  HEARTBEAT 1 Hz as system
  ``[telemetry] system_id`` component 1, the streams the companion asks for at the rates it asks
  (SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM), TIMESYNC answers, ``time_boot_ms`` on the
  vehicle's own boot clock, with the telemetry model's noise, drift and latency;
* camera frames through the simulator frame transport (:class:`companion.camera_sources.SimFrameServer`,
  ``sim://127.0.0.1:PORT``), each stamped with its capture (mid-exposure) time on the autopilot
  boot clock (clock 1).  A frame leaves once the ATTITUDE sample that brackets its exposure has
  been sent (at least ``frame_latency_s``, at most ``frame_wait_max_s`` after capture) — the
  readout and transfer delay of a real camera — preceded by a SYSTEM_TIME carrying the vehicle's
  clock at that instant;
* the companion: ``python -m companion run`` started as a separate process (stdout and stderr to
  ``DIR/companion.log``) and stopped with SIGTERM at the end (SIGKILL after ``stop_timeout_s``);
  with ``attach`` the user runs it and the command line is printed.  A companion that exits,
  never connects or stops acknowledging frames ends the run with :class:`SitlError` naming the log.

Layers: :mod:`.config` (:class:`SitlConfig`, :class:`SitlError`), :mod:`.process` (the companion
as a child process), :mod:`.loop` (one run: the sockets, the physics and the autopilot stepped
under the ``lockstep`` or ``realtime`` clock — the clocks are described there) and, here,
:func:`run_sitl`, the entry point (``flightsim sitl``, ``flightsim campaign --mode sitl``, the
benchmarks): it sets a run up, flies it, writes the files and ``sitl.json``, and scores them.

Hostile link (off by default): ``SitlConfig.hostile`` (:class:`flightsim.hostile.HostileConfig`)
interleaves seeded hostile datagrams with the telemetry at each step they fall due (random bytes,
bad CRC, truncated, unknown ids, NaN/inf payloads, glued packets, spoofed ATTITUDE; packed apart from
the vehicle's own messages, whose sequence numbers they leave alone, and not recorded in ``telemetry.tlog``) and
silences the vehicle's telemetry (optionally its HEARTBEAT and answers) in blackout windows;
``sitl.json`` ``hostile`` counts them by kind.  ``SitlConfig.rss_sample_s`` samples the companion's
resident set (``/proc/PID/status`` VmRSS) into ``companion_rss_kib``.  A failed run's
:class:`SitlError` carries what was measured until then (``partial``).

Output in ``DIR``: the same export as ``flightsim fly`` — ``truth.npz``, ``frames.csv``,
``camera.toml``, ``telemetry.tlog`` (every MAVLink message the vehicle sent, stamped when it was
sent) and, with ``video``, ``video.avi`` — plus ``received.tlog`` (every MAVLink message received
from the companion, stamped with its arrival on the recording clock of truth.npz ``t_s`` and
frames.csv), ``companion.log`` and ``sitl.json`` (the summary); the received ranges are scored
against the truth (:mod:`flightsim.score.files`: ``score.json``, ``score.md``).  Everything but
``camera.toml`` (the companion reads it at start) and ``companion.log`` is written under a
temporary name and appears when the flight is complete (:class:`companion.io.atomic.StagedFiles`);
a run that fails or is interrupted leaves the two tlogs as ``telemetry.tlog.partial`` and
``received.tlog.partial`` and nothing at the other names.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from pathlib import Path
from typing import Callable

import cv2

from companion.errors import ConfigError
from companion.io.atomic import StagedFiles, prepare_output_dir, write_text_atomic
from companion.io.config_files import load_companion_config
from flightsim.scenario import load_scenario, resolve_companion_config
from flightsim.sitl.config import CLOCKS, SitlConfig, SitlError
from flightsim.sitl.loop import Run

log = logging.getLogger(__name__)


def _score(out: Path, companion_config: Path | None, world) -> tuple[dict | None, str]:
    """Score received.tlog against truth.npz (:mod:`flightsim.score.files`): (score, note).

    The companion's own configuration (its sector σ factor) and the world (obstacle names) are
    handed to the scorer.
    """
    from flightsim.score.files import score_run, write_score

    opts = {"world": world}
    if companion_config is not None:
        opts["companion_config"] = companion_config
    score = score_run(out / "received.tlog", out / "truth.npz", plot_dir=out, **opts)
    write_score(out, score)
    return score, "scored"


def _fly_against_companion(run: Run) -> None:
    """Set the run up, fly it, and stop the companion and close the sockets and files whatever happened."""
    failure: BaseException | None = None
    # OpenCV on one thread in the simulator for the run (as the companion is started with): its
    # worker threads split each warp of the renderer across both cores and then preempt the
    # companion's process; the results are the same row by row
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        run.setup()
        run.loop()
    except BaseException as exc:  # stop the companion whatever happened, then re-raise
        failure = exc
        if isinstance(exc, SitlError):
            try:
                exc.partial = run.partial()  # what was measured up to the failure
            except Exception:  # the report of a failure must not hide it
                pass
        raise
    finally:
        run.close()
        cv2.setNumThreads(cv_threads)
        if failure is not None and run.companion is not None:
            log.info("companion log: %s", run.companion.log_path)


def _free_or(port: int | None) -> int:
    return 0 if port is None else int(port)


def run_sitl(scenario_path: str | Path, out_dir: str | Path, *, seed: int | None = None, clock: str = "lockstep",
             companion_config: str | Path | None = None, attach: bool = False, video: bool = False,
             progress: Callable[[int, int], None] | None = None, port_base: int | None = None,
             mavlink_port: int | None = None, camera_port: int | None = None, processing_ms: float | None = None,
             config: SitlConfig | None = None, score: bool = True, avoidance: str | None = None) -> dict:
    """Fly ``scenario_path`` against a live companion and write ``out_dir``; returns the summary dict.

    Ports: ``mavlink_port`` / ``camera_port`` when given, else ``port_base`` and ``port_base + 1``,
    else free ports chosen by the system (parallel runs do not collide).  ``companion_config``:
    the companion's TOML (default: the scenario's ``[scenario] companion_config``, else the
    repository's ``configs/companion.toml``; :func:`flightsim.scenario.resolve_companion_config`).  ``processing_ms``
    overrides ``config.processing_ms``.  Raises :class:`ConfigError` for a bad scenario, argument
    or busy port and :class:`SitlError` when the companion fails.  ``avoidance`` overrides the
    scenario's ``[avoidance] model`` (:mod:`flightsim.avoidance`).
    """
    if clock not in CLOCKS:
        raise ConfigError(f"clock must be one of {', '.join(CLOCKS)}, got {clock!r}")
    cfg = config or SitlConfig()
    if processing_ms is not None:
        cfg = dataclasses.replace(cfg, processing_ms=float(processing_ms))
    if port_base is not None:
        if not (isinstance(port_base, int) and 1 <= port_base <= 65534):
            raise ConfigError(f"port_base must be in 1..65534, got {port_base!r}")
        mavlink_port = port_base if mavlink_port is None else mavlink_port
        camera_port = port_base + 1 if camera_port is None else camera_port
    for name, p in (("mavlink_port", mavlink_port), ("camera_port", camera_port)):
        if p is not None and not (isinstance(p, int) and 0 <= p <= 65535):
            raise ConfigError(f"{name} must be in 0..65535, got {p!r}")
    sc = load_scenario(scenario_path, seed=seed, avoidance=avoidance)
    companion_config = resolve_companion_config(sc, companion_config)
    if companion_config is not None:
        companion_config = Path(companion_config).resolve()
        load_companion_config(companion_config)  # a bad file stops here, not in the companion's log
    out = prepare_output_dir(out_dir)
    # the names a previous run here may have left that this one writes after the commit (or not at all)
    staged = StagedFiles(out, keep_partial=("telemetry.tlog", "received.tlog"),
                         obsolete=("video.avi", "avoidance.png", "score.json", "score.md", "score_series.npz", "nees.png",
                                  "sitl.json"))
    run = Run(sc, staged, clock, cfg, companion_config, attach, video, progress, _free_or(mavlink_port),
               _free_or(camera_port))
    wall0 = time.perf_counter()
    try:
        _fly_against_companion(run)
        wall = time.perf_counter() - wall0
        w0 = time.perf_counter()
        run.flight.write_common(staged)
        staged.commit()
        write_s = time.perf_counter() - w0
    except BaseException:
        staged.abort()
        raise
    sc_result, note, score_failed = None, "not requested", False
    if score:
        try:
            sc_result, note = _score(out, companion_config, sc.world)
        except Exception as exc:  # the run itself is recorded; say loudly that its verdict is missing
            log.exception("scoring %s failed", out)
            sc_result, note, score_failed = None, f"scoring failed: {exc!r}", True
    if sc_result is not None and sc_result.get("avoidance") and not score_failed:
        from flightsim.plots import plot_run_outcome

        plot_run_outcome(out, sc.world, sc_result["avoidance"], title=sc.meta.name)
    fl = run.flight
    sim_s = fl.state.time_s
    timing = {k: round(v, 3) for k, v in sorted({**fl.timing, **run.timing, "write_files": write_s}.items())}
    sim_work = sum(v for k, v in timing.items() if k not in ("ipc_wait_ack", "setup_flight", "write_files", "turnaround"))
    summary = {
        "scenario": sc.meta.name, "scenario_file": str(sc.path), "seed": sc.meta.seed, "clock": clock,
        "processing_ms": cfg.processing_ms if clock == "lockstep" else None,
        "duration_s": sim_s, "frames": run.frames_sent, "frames_captured": fl.next_frame, "frames_unsent": run.frames_unsent,
        "acks": dict(run.acks), "messages_received": dict(sorted(run.counts_rx.items())),
        "messages_sent": dict(sorted(run.counts_tx.items())),
        "received_from": {k[5:]: v for k, v in sorted(run.checks.items()) if k.startswith("from_")},
        "checks": {k: v for k, v in sorted(run.checks.items()) if not k.startswith("from_")},
        "streams": {k: (None if v is None else round(1.0 / v, 3)) for k, v in run.logic.periods.items()},
        "stream_requests": [{"t_s": round(t, 4), "how": how, "stream": s, "rate_hz": None if p is None else round(1.0 / p, 3)}
                            for t, how, s, p in run.logic.requests],
        "timesync_answered": run.logic.counters["timesync_answered"],
        "telemetry_ahead": {"steps": run.speculated, "rebuilt": run.rewound},
        "autopilot_counters": dict(sorted(run.logic.counters.items())),
        "endpoint_counters": dict(sorted(run.endpoint.counters.items())),
        "wall_s": round(wall, 3), "loop_wall_s": round(run.wall_loop, 3),
        "realtime_factor": round(sim_s / run.wall_loop, 3) if run.wall_loop > 0 else None,
        "timing_s": timing,  # wall seconds per part of the simulator (ipc_wait_ack: waiting for the companion)
        "sim_work_s": round(sim_work, 3),
        "cpu_s": {  # user + system CPU: the simulator's flight loop (all its threads), the whole companion process
            "simulator_loop": _round_or_none(run.cpu_loop),  # and the companion over the same loop (Linux /proc; None elsewhere)
            "companion": None if run.companion is None else _round_or_none(run.companion.cpu_s),
            "companion_loop": _round_or_none(run.companion_cpu_loop)},
        "cpu_ms_per_frame": {  # the two above over the loop, per frame sent: which side limits lockstep
            "simulator": _round_or_none(1000 * run.cpu_loop / run.frames_sent, 2) if run.frames_sent else None,
            "companion": (_round_or_none(1000 * run.companion_cpu_loop / run.frames_sent, 2)
                          if run.frames_sent and run.companion_cpu_loop is not None else None)},
        "companion": None if run.companion is None else {
            "command": run.cmd, "pid": run.companion.pid, "exit_code": run.companion.exit_code,
            "killed": run.companion.killed, "log": str(run.companion.log_path)},
        "companion_command": run.cmd, "companion_exit_code": None if run.companion is None else run.companion.exit_code,
        "ports": {"mavlink_udp": run.endpoint.port, "camera_tcp": run.server.port},
        "avoidance": {"model": sc.avoidance.model, **run.flight.avoidance.counters},
        "hostile": ({**(run.injector.summary() if run.injector is not None else run.hostile_cfg.to_json()),
                     "blackout_dropped": dict(sorted(run.blackout_dropped.items()))}
                    if run.hostile_cfg.active else None),
        "companion_rss_kib": run.rss if cfg.rss_sample_s > 0 else None,  # [simulation s, loop wall s, VmRSS kiB]
        "paths": {name: str(out / name) for name in ("truth.npz", "trajectory.npz", "avoidance.png", "frames.csv", "camera.toml", "telemetry.tlog",
                                                     "received.tlog", "sectors.jsonl", "companion.log", "sitl.json", "video.avi",
                                                     "score.json", "score.md") if (out / name).exists() or name == "sitl.json"},
        "score": sc_result, "score_note": note, "score_failed": score_failed,
    }
    write_text_atomic(out / "sitl.json", json.dumps(summary, indent=2, default=_json_default) + "\n")
    if not run.counts_rx.get("HEARTBEAT"):
        what = (f"the companion never spoke MAVLink to the simulated autopilot (UDP 127.0.0.1:{run.endpoint.port}): "
                "no HEARTBEAT received")
        raise SitlError(f"{what}; see {run.companion.log_path}" if run.companion is not None else what)
    return summary


def _round_or_none(v: float | None, nd: int = 3) -> float | None:
    return None if v is None or not math.isfinite(v) else round(v, nd)


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(o, Path):
        return str(o)
    return repr(o)

__all__ = ["run_sitl", "SitlConfig", "SitlError", "CLOCKS"]
