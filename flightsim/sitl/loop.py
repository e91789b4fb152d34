"""One SITL run (:class:`Run`): the simulator's side of the sockets, stepped under one of two clocks.

:meth:`Run.setup` opens the MAVLink endpoint (:class:`flightsim.autopilot.UdpEndpoint`) and the
frame server (:class:`companion.camera_sources.SimFrameServer`), starts the companion
(:mod:`flightsim.sitl.process`) and waits for it; :meth:`Run.loop` flies the scenario with two
cursors over the steps — the physics and camera (run ahead in lockstep while the companion works)
and the autopilot (requests, telemetry, frames; strictly in order); :meth:`Run.close` stops the
companion and closes everything.  :func:`flightsim.sitl.run_sitl` drives it.

Clocks
------
``lockstep`` (default): deterministic in simulation time and as fast as the CPU allows.  After
each frame the simulator waits for the companion's acknowledgement (:meth:`SimFrameServer.wait_ack`)
before it advances; the companion runs with ``--clock sim`` (:mod:`companion.simclock`): its clock
is the autopilot clock it has heard plus ``processing_ms`` per processed frame, and it works in one
round per frame (poll the link, process, publish, acknowledge), sending nothing between rounds.
The simulator reads the companion's datagrams only at these acknowledgements and dates them
where the companion's clock put them: ``max(delivery, companion busy until) + processing_ms`` for
a processed frame (``+ 0`` for a frame dropped as stale); requests are handled at the first
physics step at or after that instant.  Every DISTANCE_SENSOR's and NAMED_VALUE_FLOAT's ``time_boot_ms`` is checked
against this model (``clock_mismatches`` in the summary).  While the companion works on a
frame the simulator already runs the physics and renders the next frame (nothing in them depends
on the companion) and builds the telemetry of those steps, in step order, as if no request came
in between; a change of the stream schedule (a stream request handled, or a new companion's
HEARTBEAT restart) first rewinds the telemetry model and the schedule to the step at which it
happens and that step is built again, so the random draws and messages are those of the
step-by-step loop (``telemetry_ahead`` in the summary counts both).  Frames are rendered in that
window too: with avoidance the physics may not run past the companion's answer, so a frame captured
by the steps computed after an acknowledgement is only posed then, and rendered (with its truth)
during the next frame's wait (``Flight.capture(defer=True)``; the pixels do not depend on when).
After the acknowledgement only the requests, the physics steps up to the next frame's delivery
and the sending are left before the next frame goes out; on two cores the processes overlap; no fixed sleeps lie in this path.  Determinism rests on loopback ordering: a
datagram sent before the frame (or the acknowledgement) is queued at the receiver before the
frame (acknowledgement) is — true of Linux loopback, where ``sendto`` delivers before it returns.

``realtime``: the simulator paces itself to the wall clock and never waits for the companion,
which runs on its normal monotonic clock with TIMESYNC; a datagram is dated when it is read
(``select`` between physics steps).
"""

from __future__ import annotations

import collections
import dataclasses
import heapq
import logging
import math
import shlex
import sys
import time
from pathlib import Path

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.camera_sources import ACK_DROPPED, ACK_PROCESSED, ACK_REJECTED, SimFrameServer
from companion.io.atomic import StagedFiles, write_text_atomic
from flightsim.autopilot import AutopilotLogic, PortBusyError, UdpEndpoint
from flightsim.fly import EPS_T, Flight, StreamSchedule, camera_toml, open_video
from flightsim.hostile import HostileInjector
from flightsim.scenario import Scenario
from flightsim.sitl.config import SitlConfig, SitlError
from flightsim.score.files import LANDMARK_LOG, SECTOR_LOG
from flightsim.sitl.process import (CompanionProcess, companion_command, companion_rss_kib, cpu_seconds,
                                    process_cpu_seconds)
from flightsim.tlog import TlogWriter

log = logging.getLogger(__name__)

_ACK_NAMES = {ACK_PROCESSED: "processed", ACK_DROPPED: "dropped", ACK_REJECTED: "rejected"}


# ---------------------------------------------------------------------- the run ---------------------
@dataclasses.dataclass
class _Received:
    t: float  # arrival, simulation clock
    raw: bytes
    msg: object


class Run:
    """One SITL run (see the module docstring); :func:`run_sitl` is the entry point."""

    def __init__(self, sc: Scenario, staged: StagedFiles, clock: str, cfg: SitlConfig, companion_config: Path | None,
                 attach: bool, video: bool, progress, mavlink_port: int, camera_port: int):
        self.sc, self.staged, self.out, self.clock, self.cfg = sc, staged, staged.directory, clock, cfg
        self.lockstep = clock == "lockstep"
        self.companion_config = companion_config
        self.attach, self.want_video, self.progress = attach, video, progress
        self.mavlink_port, self.camera_port = mavlink_port, camera_port
        self.tel = sc.telemetry
        self.boot0 = sc.telemetry.boot_time_s
        self.epoch = sc.meta.epoch_s
        self.P = cfg.processing_ms / 1000.0
        self.counts_rx: collections.Counter[str] = collections.Counter()
        self.counts_tx: collections.Counter[str] = collections.Counter()
        self.acks: collections.Counter[str] = collections.Counter()
        self.checks: collections.Counter[str] = collections.Counter()
        self.timing: collections.Counter[str] = collections.Counter()
        self.inbox: collections.deque[_Received] = collections.deque()
        self.outq: list = []  # heap of (t_emit, seq, name, state_t, msg)
        self._seq = 0
        self.comp_free = -math.inf  # lockstep: the companion is busy until then (simulation time)
        self.frames_sent = 0
        self.frames_unsent = 0
        self.att_state_sent = -math.inf  # state time of the newest ATTITUDE sent
        self.speculated = 0  # lockstep: steps whose telemetry was built ahead (_speculate) ...
        self.rewound = 0  # ... and how many of those were rebuilt after a request changed the streams
        self._playing_snap = None  # lockstep: the state before the step being played, while its requests are handled
        self.t_now = 0.0  # the autopilot's step (simulation time)
        self._ack_wall: float | None = None
        self._last_rx_t = -math.inf
        self._last_tx_t = -math.inf
        self.companion: CompanionProcess | None = None
        self.hostile_cfg = cfg.hostile
        self.injector: HostileInjector | None = None
        self.blackout_dropped: collections.Counter[str] = collections.Counter()  # vehicle messages not sent in blackouts
        self.companion_cpu_loop: float | None = None  # the companion's CPU over the flight loop (Linux /proc), s
        self.rss: list[list[float]] = []  # [simulation s, wall s since the loop started, companion VmRSS kiB]
        self._next_rss = 0.0
        self.endpoint: UdpEndpoint | None = None
        self.server: SimFrameServer | None = None
        self.video = None

    # -- helpers -----------------------------------------------------------------------------------
    def boot_s(self, t: float) -> float:
        return self.boot0 + t

    def _record_tx(self, t: float, name: str, buf: bytes | None) -> None:
        if buf is None:
            self.counts_tx["unsent_" + name] += 1
            return
        self.counts_tx[name] += 1
        self._last_tx_t = max(t, self._last_tx_t)  # real time: an immediate answer may be dated between steps
        self.tx_log.write_raw(self._last_tx_t, buf)

    def _send(self, t: float, msg) -> None:
        name = msg.get_type()
        if self.hostile_cfg.blackouts and self.hostile_cfg.silenced(name, t) is not None:
            self.blackout_dropped[name] += 1
            return
        self._record_tx(t, name, self.endpoint.send(msg))

    def _inject(self, t: float) -> None:
        """Hostile datagrams due at ``t`` (:mod:`flightsim.hostile`), before the step's own messages."""
        inj = self.injector
        for kind, buf, parts in inj.due(t, self.flight.tm.time_boot_ms(t)):
            if self.endpoint.send_raw(buf):
                inj.record(kind, buf, parts)
            else:
                inj.record_unsent(kind)

    def _sample_rss(self, t: float) -> None:
        if self.companion is None or t < self._next_rss:
            return
        self._next_rss = t + self.cfg.rss_sample_s
        kib = companion_rss_kib(self.companion.pid)
        if kib is not None:
            self.rss.append([round(t, 3), round(time.perf_counter() - self.wall0, 3), kib])

    def partial(self) -> dict:
        """What the run measured so far (for :attr:`SitlError.partial`)."""
        return {"t_s": self.t_now, "frames": self.frames_sent,
                "hostile": None if self.injector is None else self.injector.summary(),
                "blackout_dropped": dict(sorted(self.blackout_dropped.items())),
                "companion_rss_kib": list(self.rss),
                "companion_exit_code": None if self.companion is None else self.companion.proc.poll()}

    def _receive(self, arrival: float) -> None:
        """Read every waiting datagram, date it ``arrival`` (simulation time), record and queue it."""
        w0 = time.perf_counter()
        peers = self.endpoint.counters["peers"]
        got = self.endpoint.receive()
        if self.endpoint.counters["peers"] != peers:  # a new companion: HEARTBEAT at once, then every second
            self._rewind()
            self.streams.restart_at("HEARTBEAT", arrival)
        for raw, msg in got:
            t = max(arrival, self._last_rx_t)
            self._last_rx_t = t
            self.rx_log.write_raw(t, raw)
            self._inspect(t, msg)
            if msg.get_type() in ("OBSTACLE_DISTANCE", "DISTANCE_SENSOR"):  # to the autopilot's avoidance, dated on arrival
                if self.flight.state is not None and t <= self.flight.state.time_s - self.flight.dt + EPS_T:
                    self.checks["avoidance_late"] += 1  # the physics already ran past its arrival (see _run_ahead)
                self.flight.avoidance.receive(t, msg)
            if not self.lockstep and msg.get_type() == "TIMESYNC":  # real time: answered on arrival, like an
                for reply in self.logic.handle(msg, t):          # autopilot's fast loop (a short round trip)
                    self._send(t, reply)
                continue
            self.inbox.append(_Received(t, raw, msg))
        self.timing["ipc_recv"] += time.perf_counter() - w0

    def _inspect(self, t: float, msg) -> None:
        """Count and check what the companion sends (the fields of docs/derivations/sectors.md, the lockstep clock model)."""
        typ = msg.get_type()
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        self.counts_rx[typ] += 1
        self.checks[f"from_{src[0]}_{src[1]}"] += 1
        if typ == "OBSTACLE_DISTANCE":
            ok = (len(msg.distances) == 72 and msg.increment == 5 and abs(msg.increment_f - 5.0) < 1e-6
                  and msg.frame == mavlink.MAV_FRAME_BODY_FRD and msg.angle_offset == 0)
            self.checks["obstacle_distance_ok" if ok else "obstacle_distance_bad_fields"] += 1
            if any(d != 65535 for d in msg.distances):
                self.checks["obstacle_distance_valid"] += 1
        elif typ in ("DISTANCE_SENSOR", "NAMED_VALUE_FLOAT") and self.lockstep and msg.time_boot_ms > 0:
            expected_ms = self.boot_s(t) * 1000.0
            if abs(msg.time_boot_ms - expected_ms) > 1.5:
                self.checks["clock_mismatches"] += 1
                if self.checks["clock_mismatches"] <= 3:
                    log.warning("%s stamped %d ms, lockstep model says %.1f ms (is the companion on "
                                "--clock sim --sim-processing-ms %g?)", typ, msg.time_boot_ms, expected_ms, self.cfg.processing_ms)

    def _handle_inbox(self, t: float) -> None:
        while self.inbox and self.inbox[0].t <= t + EPS_T:
            item = self.inbox.popleft()
            for reply in self.logic.handle(item.msg, t):
                self._send(t, reply)

    # -- setup ----------------------------------------------------------------------------------------
    def setup(self) -> None:
        out = self.out
        write_text_atomic(out / "camera.toml", camera_toml(self.sc.camera))  # the companion needs it at start
        (out / SECTOR_LOG).unlink(missing_ok=True)  # a previous run's log must not be read as this one's
        (out / LANDMARK_LOG).unlink(missing_ok=True)
        self.endpoint = UdpEndpoint(self.mavlink_port, self.tel.system_id)
        if self.hostile_cfg.rate_hz > 0:
            self.injector = HostileInjector(self.hostile_cfg, self.tel.system_id)
        try:
            self.server = SimFrameServer("127.0.0.1", self.camera_port)
        except OSError as exc:
            raise PortBusyError(f"TCP port {self.camera_port} on 127.0.0.1 is not available for the camera frames "
                                f"({exc.strerror or exc}); pick another with --camera-port, or 0 for any free port") from None
        self.cmd = companion_command(self.endpoint.port, self.server.port, (out / "camera.toml").resolve(),
                                     lockstep=self.lockstep, processing_ms=self.cfg.processing_ms,
                                     companion_config=self.companion_config, sector_log=(out / SECTOR_LOG).resolve(),
                                     landmark_log=(out / LANDMARK_LOG).resolve() if self.cfg.landmark_log else None)
        if self.attach:
            print("flightsim sitl: waiting for the companion; start it with\n  " + shlex.join(self.cmd), file=sys.stderr,
                  flush=True)
        else:
            self.companion = CompanionProcess(self.cmd, out / "companion.log")
            log.info("companion started (pid %d): %s", self.companion.pid, shlex.join(self.cmd))
        w0 = time.perf_counter()
        self.flight = Flight(self.sc)  # builds the world textures while the companion starts
        self.timing["setup_flight"] += time.perf_counter() - w0
        b = self.flight.telemetry_builders()
        b["SYSTEM_TIME"] = self._system_time
        lat = self.tel.latency_s
        self.streams = StreamSchedule()
        self.streams.add("HEARTBEAT", 1.0, b["HEARTBEAT"], 0.0)
        for name in ("ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "SYSTEM_TIME"):
            self.streams.add(name, None, b[name], 0.0 if name == "SYSTEM_TIME" else lat)
        defaults = {"ATTITUDE": 1.0 / self.tel.attitude_rate_hz, "LOCAL_POSITION_NED": 1.0 / self.tel.position_rate_hz,
                    "GLOBAL_POSITION_INT": 1.0 / self.tel.global_rate_hz, "SYSTEM_TIME": 1.0}
        self.logic = AutopilotLogic(self.tel.system_id, self._set_period, defaults, self.boot_s)
        self.tx_log = TlogWriter(self.staged.path("telemetry.tlog"), self.epoch)
        self.rx_log = TlogWriter(self.staged.path("received.tlog"), self.epoch)
        if self.want_video:
            self.video = open_video(self.staged.path("video.avi"), self.sc)
        self._wait_for_companion()

    def _set_period(self, name: str, period: float | None, t: float) -> None:
        """The autopilot's only way to change the streams: the telemetry built ahead is dropped first."""
        self._rewind()
        self.streams.set_period(name, period, t)

    def _system_time(self, state):
        return self._system_time_at(state.time_s)

    def _system_time_at(self, t: float):
        return mavlink.MAVLink_system_time_message(int(round((self.epoch + t) * 1e6)), self.flight.tm.time_boot_ms(t))

    def _wait_for_companion(self) -> None:
        """Wait for the companion's frame connection: ``connect_timeout_s`` once it is ready to connect.
        While its log says it is compiling its kernels (a first start: minutes on a small computer or a
        busy machine) the clock restarts, up to ``compile_timeout_s`` in all."""
        timeout = self.cfg.connect_timeout_s * (5 if self.attach else 1)
        t0 = time.monotonic()
        deadline = t0 + timeout
        compiling_logged = False
        while not self.server.wait_client(timeout=0.1):
            if self.companion is not None and not self.companion.alive():
                raise self.companion.failure(f"the companion exited with code {self.companion.proc.returncode} "
                                             "before connecting")
            now = time.monotonic()
            if self.companion is not None and now - t0 < self.cfg.compile_timeout_s and self.companion.compiling():
                if not compiling_logged:
                    compiling_logged = True
                    log.info("the companion is compiling its kernels (first start); waiting up to %.0f s",
                             self.cfg.compile_timeout_s)
                deadline = now + timeout
                continue
            if now > deadline:
                what = f"the companion did not connect to the camera frames ({self.server.address}) within {timeout:.0f} s"
                raise self.companion.failure(what) if self.companion is not None else SitlError(what)
        log.info("companion connected to the camera frames (%s)", self.server.address)

    # -- the loop -------------------------------------------------------------------------------------
    def _deliver(self, frame, t: float) -> None:
        """SYSTEM_TIME tick + the frame; in lockstep wait for its acknowledgement and read the replies."""
        w0 = time.perf_counter()
        if self._ack_wall is not None:  # lockstep: acknowledgement → next frame (the simulator's serial part)
            self.timing["turnaround"] += w0 - self._ack_wall
            self._ack_wall = None
        self._send(t, self._system_time_at(t))
        w0 = time.perf_counter()
        ok = self.server.send(frame.image, frame.index, int(round(self.boot_s(frame.t_s) * 1e9)))
        self.timing["ipc_send"] += time.perf_counter() - w0
        if not ok:
            self.frames_unsent += 1
            if self.companion is not None and not self.companion.alive():
                raise self.companion.failure(f"the companion exited with code {self.companion.proc.returncode} during the run")
            if self.lockstep:
                raise self._lost(f"frame {frame.index} could not be sent (the companion closed the frame connection)")
            return
        self.frames_sent += 1
        if not self.lockstep:
            return
        self._run_ahead()  # the physics and the next frame's rendering overlap the companion's work
        w0 = time.perf_counter()
        status = self.server.wait_ack(frame.index, timeout=self.cfg.ack_timeout_s)
        self._ack_wall = time.perf_counter()
        self.timing["ipc_wait_ack"] += self._ack_wall - w0
        if status is None:
            raise self._lost(f"no acknowledgement of frame {frame.index} (t = {t:.3f} s) within {self.cfg.ack_timeout_s:g} s")
        self.acks[_ACK_NAMES.get(status, str(status))] += 1
        start = max(t, self.comp_free)
        self.comp_free = start + (self.P if status in (ACK_PROCESSED, ACK_REJECTED) else 0.0)
        self._receive(self.comp_free)

    def _lost(self, what: str) -> SitlError:
        if self.companion is not None:
            if not self.companion.alive():
                return self.companion.failure(f"the companion exited with code {self.companion.proc.returncode} during the run")
            return self.companion.failure(what)
        return SitlError(what)

    def _pace(self, t_next: float, wall0: float) -> None:
        """Real time: wait for the wall clock, reading the companion's datagrams as they come."""
        target = wall0 + t_next
        while True:
            now = time.perf_counter()
            if now >= target:
                break
            if self.endpoint.wait_readable(target - now):
                self._receive(time.perf_counter() - wall0)

    def _physics_one(self) -> bool:
        """Run the physics (and the camera, if a frame is due) one step ahead of the autopilot."""
        fl = self.flight
        state = fl.physics_step()
        if state is None:
            return False
        # lockstep: the frame is rendered (and its truth taken) while the companion works
        # (_run_ahead), not between its acknowledgement and the next frame (Flight.capture)
        frame = fl.capture(state, defer=self.lockstep) if fl.frame_due(state) else None
        if frame is not None and self.video is not None:
            w0 = time.perf_counter()
            self.video.write(frame.image)
            self.timing["video"] += time.perf_counter() - w0
        self.ahead.append([state, frame, None])
        return True

    def _run_ahead(self) -> None:
        """Lockstep, while the companion works on a frame: compute the physics and the camera up to
        the next frame and the steps its delivery waits for (the bracketing ATTITUDE)."""
        cfg, dt = self.cfg, self.flight.dt
        period = self.streams.period("ATTITUDE")
        margin = cfg.frame_latency_s if period is None else self.tel.latency_s + period + dt
        margin = min(max(margin, cfg.frame_latency_s), cfg.frame_wait_max_s)
        # With avoidance the physics depends on the companion's answer to this frame, which arrives
        # at comp_free (the companion's busy-until time after it; see _deliver): run ahead only to there.
        horizon = max(self.t_now, self.comp_free) + self.P if self.sc.avoidance.model != "none" else math.inf
        while True:
            nxt = next((e[1] for e in self.ahead if e[1] is not None), None)
            if nxt is not None and self.ahead[-1][0].time_s + EPS_T >= nxt.t_s + margin:
                break
            last = self.ahead[-1][0].time_s if self.ahead else (self.flight.state.time_s if self.flight.state is not None else -math.inf)
            if last + dt > horizon + EPS_T:
                break
            if not self._physics_one():
                break
        if self.cfg.build_ahead:
            self._speculate()
        self.flight.finish_frames()  # render the frames captured since the last acknowledgement, too

    def _speculate(self) -> None:
        """Lockstep, while the companion works: advance the telemetry model and build the stream
        messages of the steps computed ahead, as if no request changed the streams in between —
        so that after the acknowledgement only the sending is left (the companion waits for that).

        Each step keeps the telemetry model's and the schedule's state from before it; a change of
        the schedule rewinds to the step it happens at (:meth:`_rewind`), so every message, random
        draw and stamp is the one the step-by-step loop gives."""
        for entry in self.ahead:
            if entry[2] is None:
                snap = (self.flight.tm.snapshot(), self.streams.snapshot())
                entry[2] = (snap, self._build_telemetry(entry[0]))
                self.speculated += 1

    def _build_telemetry(self, state) -> list:
        """Advance the telemetry model to ``state`` and build the streams due at it."""
        self.flight.advance_telemetry(state)
        w0 = time.perf_counter()
        due = self.streams.due(state)
        self.timing["telemetry_build"] += time.perf_counter() - w0
        return due

    def _rewind(self) -> None:
        """The stream schedule is about to change: drop the telemetry built ahead, back to the state
        before the step being played (its requests are being handled) or, between steps, before
        the first step not yet played (no-op when nothing was built ahead)."""
        snap, self._playing_snap = self._playing_snap, None
        if snap is not None:
            self.rewound += 1
        else:
            snap = next((e[2][0] for e in self.ahead if e[2] is not None), None)
            if snap is None:
                return
        tm_snap, streams_snap = snap
        self.flight.tm.restore(tm_snap)
        self.streams.restore(streams_snap)
        for e in self.ahead:
            if e[2] is not None:
                e[2] = None
                self.rewound += 1

    def _play(self, state, frame, spec=None) -> None:
        """The autopilot's side of one step: requests due, telemetry (built ahead in ``spec`` by
        :meth:`_speculate` unless a request rewound it, or now), frames ready to leave."""
        cfg, fl = self.cfg, self.flight
        t = state.time_s
        self.t_now = t
        self._playing_snap = None if spec is None else spec[0]
        self._handle_inbox(t)  # a stream request rewinds (_set_period → _rewind)
        due = spec[1] if self._playing_snap is not None else self._build_telemetry(state)
        self._playing_snap = None
        for t_emit, name, msg in due:
            heapq.heappush(self.outq, (t_emit, self._seq, name, t, msg))
            self._seq += 1
        if frame is not None:
            self.pending.append(frame)
        w0 = time.perf_counter()
        if self.injector is not None:
            self._inject(t)
        while self.outq and self.outq[0][0] <= t + EPS_T:
            _t_emit, _seq, name, state_t, msg = heapq.heappop(self.outq)
            self._send(t, msg)
            if name == "ATTITUDE":
                self.att_state_sent = state_t
        self.timing["send"] += time.perf_counter() - w0
        att_on = self.streams.period("ATTITUDE") is not None
        while self.pending:
            f = self.pending[0]
            age = t - f.t_s
            bracketed = self.att_state_sent >= f.t_s - EPS_T or not att_on
            if age + EPS_T < cfg.frame_latency_s or (not bracketed and age + EPS_T < cfg.frame_wait_max_s):
                break
            self.pending.popleft()
            self._deliver(f, t)
            if self.progress:
                self.progress(self.frames_sent, fl.n_frames)

    def loop(self) -> None:
        """Two cursors over the steps: the physics and camera (:meth:`_physics_one`, run ahead in
        lockstep while the companion works) and the autopilot (:meth:`_play`, strictly in order)."""
        fl, cfg = self.flight, self.cfg
        self.ahead: collections.deque = collections.deque()
        self.pending: collections.deque = collections.deque()
        self.wall0 = time.perf_counter()
        cpu0 = cpu_seconds()
        comp0 = None if self.companion is None else process_cpu_seconds(self.companion.pid)
        next_alive_check = 0.0
        while self.ahead or self._physics_one():
            state, frame, spec = self.ahead.popleft()
            self._play(state, frame, spec)
            if self.cfg.rss_sample_s > 0:
                self._sample_rss(state.time_s)
            if not self.lockstep:
                t = state.time_s
                if t >= next_alive_check:
                    next_alive_check = t + 0.5
                    if self.companion is not None and not self.companion.alive():
                        raise self.companion.failure(
                            f"the companion exited with code {self.companion.proc.returncode} during the run")
                self._pace(t + fl.dt, self.wall0)
        self.frames_unsent += len(self.pending)  # captured too late in the flight to be delivered
        self.wall_loop = time.perf_counter() - self.wall0
        self.cpu_loop = cpu_seconds() - cpu0
        comp1 = None if self.companion is None else process_cpu_seconds(self.companion.pid)
        self.companion_cpu_loop = None if comp0 is None or comp1 is None else comp1 - comp0
        if not self.lockstep:  # the last messages still on their way
            self._pace(self.t_now + cfg.tail_s, self.wall0)
        while self.inbox:  # arrived after the last step: counted, no longer answered
            self.logic.handle(self.inbox.popleft().msg, self.t_now)
            self.checks["after_flight"] += 1

    # -- the end ----------------------------------------------------------------------------------------
    def close(self) -> None:
        for thing in (self.video,):
            if thing is not None:
                thing.release()
        self.video = None
        if self.companion is not None and self.companion.exit_code is None:
            code = self.companion.stop(self.cfg.stop_timeout_s)
            log.info("companion stopped with exit code %d%s", code, " (killed)" if self.companion.killed else "")
        for thing in (self.server, self.endpoint):
            if thing is not None:
                try:
                    thing.close()
                except Exception:  # best effort
                    pass
        for w in ("tx_log", "rx_log"):
            if hasattr(self, w):
                getattr(self, w).close()
