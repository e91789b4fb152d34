"""The live companion process: the app loop (docs/derivations/frames.md, docs/derivations/sectors.md).

:class:`Companion` owns the MAVLink link(s), the camera source, a :class:`~companion.pipeline.Pipeline`
and a :class:`~companion.reporter.Reporter` and runs the main loop: poll the links often, take the
newest frame (older unread frames are dropped by the source), drop a frame older than
``max_frame_age_s`` when processing would start, let a frame wait at most ``telemetry_wait_s`` for
the ATTITUDE sample that brackets it, process, publish, then the periodic duties (state, STATUSTEXT,
unknown messages while invalid, diagnostics, the HEARTBEAT's ``system_status``, a status log line
every 10 s).  In lockstep with a simulator (``companion run --clock sim``, :mod:`companion.simclock`)
it runs one round per frame instead (:meth:`Companion.step_lockstep`) on a clock that follows
simulation time, so a SITL run is deterministic and as fast as the CPU allows.

``companion run`` (:mod:`companion.cli`) builds it; the name stays importable from :mod:`companion.pipeline`.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from typing import Callable

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.camera_sources import Frame, FrameSource
from companion.core.camera import CameraConfig
from companion.pipeline import FrameResult, Pipeline, PipelineConfig
from companion.reporter import Reporter

log = logging.getLogger(__name__)


def _autopilot_name(value: int) -> str:
    e = mavlink.enums.get("MAV_AUTOPILOT", {}).get(int(value))
    return e.name if e is not None else f"MAV_AUTOPILOT {int(value)}"


# ---------------------------------------------------------------------- the live process ---------
class Companion:
    """The running companion: links + camera + pipeline + reporter (see module docstring).

    ``step()`` is one non-blocking iteration (tests drive it with a simulated clock); ``run()``
    loops it until ``stop`` is set.  Nothing that comes from the wire, the camera or the pipeline
    ends the loop: errors are logged, counted and the pipeline restarts — except a camera whose
    first frame does not have the configured size (a configuration error, see :meth:`run`).
    """

    def __init__(self, config, source: FrameSource, link, gcs=None, pipeline: PipelineConfig = PipelineConfig(),
                 camera: CameraConfig | None = None, clock: Callable[[], float] = time.monotonic, sector_sink=None):
        self.config = config
        self.pcfg = pipeline
        self.source = source
        self.link = link
        self.gcs = gcs
        self.clock = clock
        self.telemetry = link.telemetry
        self.pipeline = Pipeline(camera or config.camera, config, pipeline, self.telemetry)
        self.reporter = Reporter(config, pipeline, outputs=("autopilot", "gcs") if gcs is not None else ("autopilot",),
                                 start=clock(), sector_sink=sector_sink)
        self._pending: Frame | None = None
        self._last_frame_at: float | None = None
        self.counters: collections.Counter[str] = collections.Counter()
        self.latencies: collections.deque[float] = collections.deque(maxlen=1000)
        self._status_t = clock()
        self._errors_logged = 0
        self._lockstep_started = False
        # rounds; wall s waiting / working; this thread's CPU s per round, of which the pipeline's and its stages'
        self.lockstep_wall: collections.Counter[str] = collections.Counter()

    # -- helpers ------------------------------------------------------------------------------------
    def _send(self, msgs) -> None:
        for out, m in msgs:
            target = self.link if out == "autopilot" else self.gcs
            if target is None:
                continue
            if target.send(m):
                self.counters[f"sent_{out}"] += 1
            else:
                self.counters[f"unsent_{out}"] += 1

    def _boot_ms(self, now: float) -> int:
        v = self.link.autopilot_time_boot_ms(now)
        return int(v) if v is not None else 0

    def _done(self, frame: Frame, status: str) -> None:
        try:
            self.source.done(frame, status)
        except Exception:  # an acknowledgement must never stop the loop
            self.counters["ack_errors"] += 1

    # -- the loop ------------------------------------------------------------------------------------
    def _poll_links(self) -> None:
        """Read what the autopilot (and the ground station) sent; the ground-station link speaks as the
        vehicle's system id once the autopilot's is known."""
        self.link.poll()
        hb = self.link.vehicle_heartbeat
        if hb is not None and hb.autopilot != self.reporter.vehicle_autopilot:  # the locked vehicle's: changes are rare
            self.reporter.vehicle_autopilot = int(hb.autopilot)
            log.info("vehicle autopilot %s: OBSTACLE_DISTANCE %s", _autopilot_name(hb.autopilot),
                     "folded into PX4's 10° bins" if self.reporter.fold_for_px4() else "as measured, 72 × 5°")
        if self.gcs is not None:
            self.gcs.poll()
            sid = self.link.system_id
            if sid is not None and self.gcs.system_id != sid:
                self.gcs.set_system_id(sid)

    def step(self, wait: float = 0.0) -> None:
        """One iteration: poll links, take a frame, maybe process it, periodic duties."""
        now = self.clock()
        self._poll_links()
        frame = self.source.read(timeout=wait)
        now = self.clock()
        if frame is not None:
            self._last_frame_at = now
            self.counters["frames_in"] += 1
            if self._pending is not None:
                self.counters["frames_superseded"] += 1
                self._done(self._pending, "dropped")
            self._pending = frame
        if self._pending is not None:
            self._maybe_process(now)
        self._tick(self.clock())

    def _maybe_process(self, now: float) -> None:
        f = self._pending
        if now - f.t > self.pcfg.max_frame_age_s:
            self.counters["frames_stale"] += 1
            self._pending = None
            self._done(f, "dropped")
            return
        if self.pipeline.readiness(f.t, now) == "wait":
            return
        self._pending = None
        res = self._run_pipeline(f, now)
        self._done(f, "processed" if res.ok else "rejected")
        self._publish(res)

    def _run_pipeline(self, f: Frame, now: float) -> FrameResult:
        try:
            res = self.pipeline.process(f, now)
        except Exception as exc:  # a bug must not take the process down: log, restart the pipeline
            self.counters["pipeline_errors"] += 1
            if self._errors_logged < 20:
                self._errors_logged += 1
                log.exception("pipeline failed on frame %d: %r", f.index, exc)
            self.pipeline.reset("internal error")
            res = FrameResult(f.index, f.t, now, 0.0, False, "error: internal", restart="internal error")
            self.pipeline.last_result = res
        self.counters["frames_processed" if res.ok else "frames_failed"] += 1
        return res

    def _publish(self, res: FrameResult) -> None:
        """Send the messages of a processed frame, stamped when processing ended (``clock()``)."""
        t_send = self.clock()
        msgs = self.reporter.on_result(
            res, t_send, yaw_now=self.pipeline.yaw_now(t_send), last_frame_at=self._last_frame_at,
            link_ok=self.link.connected, telemetry_problem=self.pipeline.telemetry_problem(t_send),
            time_boot_ms=self._boot_ms(t_send),
        )
        if res.ok:
            self.latencies.append(t_send - res.t_capture)
        self._send(msgs)

    # -- lockstep ------------------------------------------------------------------------------------
    def step_lockstep(self, timeout: float = 0.2) -> bool:
        """One lockstep round with a simulator (``companion run --clock sim``, :mod:`companion.simclock`).

        ``self.clock`` must be a :class:`~companion.simclock.SimClock` fed by the link.  Waits up to
        ``timeout`` wall seconds for a frame; then polls the links (the simulator sent everything
        up to the frame before it), processes the frame without waiting for telemetry (nothing more
        comes until it is acknowledged), publishes at capture start + processing time, runs the
        periodic duties and acknowledges the frame last, so the simulator's next step sees every
        message of this round.  Nothing is sent between rounds.  Returns False if no frame came.
        """
        w0 = time.perf_counter()
        f = self.source.read(timeout=timeout)
        w1 = time.perf_counter()
        c1 = time.thread_time()
        self.lockstep_wall["wait_s"] += w1 - w0
        if f is None:
            return False
        clock = self.clock
        clock.observe(f.t)  # the companion clock is the autopilot boot clock (offset 0)
        if not self._lockstep_started:  # the clock read 0 before the simulator was heard
            self._lockstep_started = True
            self.reporter.health.start = clock()
            self._status_t = clock()
        self._poll_links()
        now = clock()
        self._last_frame_at = now
        self.counters["frames_in"] += 1
        if now - f.t > self.pcfg.max_frame_age_s:  # the companion fell behind in simulation time
            self.counters["frames_stale"] += 1
            status = "dropped"
        else:
            res = self._run_pipeline(f, now)
            clock.work(res.processing_s)
            status = "processed" if res.ok else "rejected"
            self._publish(res)
            self.lockstep_wall["pipeline_cpu_s"] += res.cpu_s
            for stage, cpu in res.stage_cpu_s.items():
                self.lockstep_wall[f"{stage}_cpu_s"] += cpu
        self._tick(clock())
        self._done(f, status)
        self.lockstep_wall["rounds"] += 1
        self.lockstep_wall["work_s"] += time.perf_counter() - w1
        self.lockstep_wall["cpu_s"] += time.thread_time() - c1
        return True

    def _tick(self, now: float) -> None:
        events = self.link.drain_events() + self.source.drain_events()
        if self.gcs is not None:
            events += self.gcs.drain_events()
        msgs = self.reporter.tick(
            now, yaw_now=self.pipeline.yaw_now(now), last_frame_at=self._last_frame_at, link_ok=self.link.connected,
            telemetry_problem=self.pipeline.telemetry_problem(now), time_boot_ms=self._boot_ms(now), events=events,
        )
        status = self.reporter.health.system_status
        self.link.set_system_status(status)
        if self.gcs is not None:
            self.gcs.set_system_status(status)
        self._send(msgs)
        if now - self._status_t >= 10.0:
            self._status_t = now
            self._log_status(now)

    def _log_status(self, now: float) -> None:
        lat = sorted(self.latencies)
        p50 = lat[len(lat) // 2] * 1000 if lat else math.nan
        src = self.source.status()
        res = self.pipeline.last_result
        log.info("state %s (%s); %.1f fps; tracks %d; converged %d; latency p50 %.0f ms; frames in %d, stale %d, "
                 "superseded %d, source dropped %d, rejected %s; telemetry %s",
                 self.reporter.health.state.value, self.reporter.health.reason, self.reporter.fps(now),
                 res.n_tracks if res else 0, res.n_converged if res else 0, p50, self.counters["frames_in"],
                 self.counters["frames_stale"], self.counters["frames_superseded"], src.dropped, src.rejected or "{}",
                 {k: round(v, 1) for k, v in self.link.rates().items()})

    def run(self, stop: threading.Event | None = None, duration: float | None = None, wait: float = 0.002,
            lockstep: bool = False) -> None:
        """Loop until ``stop`` is set (or ``duration`` seconds passed on ``clock``).

        ``lockstep``: run :meth:`step_lockstep` rounds (``clock`` a SimClock); ``duration`` then
        counts simulation time from the first frame.  The loop also ends when the camera's first
        frame has another size than configured (``source.size_error``, after one STATUSTEXT): a
        configuration error the caller reports.
        """
        stop = stop or threading.Event()
        t_end = None if duration is None or lockstep else self.clock() + duration
        log.info("companion running%s: camera %s, autopilot %s%s", " in lockstep with the simulator" if lockstep else "",
                 self.source.name, self.link.conn_str, f", ground station {self.gcs.conn_str}" if self.gcs is not None else "")
        while not stop.is_set():
            if lockstep:
                if self.step_lockstep(timeout=0.2) and duration is not None and t_end is None:
                    t_end = self.clock() + duration
            else:
                self.step(wait=wait)
            if t_end is not None and self.clock() >= t_end:
                break
            if self.source.size_error:  # the configuration does not fit the camera: say so once and stop
                self._tick(self.clock())
                break
            if self.source.ended:
                log.info("camera source %s ended", self.source.name)
                break

    def close(self) -> None:
        for thing in (self.source, self.link, self.gcs):
            if thing is None:
                continue
            try:
                thing.close()
            except Exception:  # closing is best effort
                pass


__all__ = ["Companion"]
