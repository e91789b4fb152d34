"""Results → MAVLink messages, and the health of the ranging output (docs/derivations/sectors.md).

:class:`Reporter` (pure; the caller's clock)
    turns the :class:`~companion.pipeline.FrameResult` of each frame and the state of the inputs
    into messages per output (``"autopilot"``, ``"gcs"``): OBSTACLE_DISTANCE / DISTANCE_SENSOR /
    OBSTACLE_DISTANCE_3D for every valid result, rotated by the yaw change between exposure and
    sending, at the ``[outputs]`` rates; NAMED_VALUE_FLOAT diagnostics (≤ 1 Hz); STATUSTEXT on
    every state change; all-unknown messages (UINT16_MAX) while no valid range exists.
:class:`Health`
    decides the HEARTBEAT ``system_status``: ACTIVE only while valid ranges are being produced,
    STANDBY while starting or while no sector can make a claim, CRITICAL on a fault (telemetry
    stale > 0.5 s or missing, no clock sync, camera lost, link lost, frames not processed in time).

The live loop (:class:`companion.app.Companion`) and the replay tool (:mod:`companion.replay`)
feed the same Reporter.  These names stay importable from :mod:`companion.pipeline`.
"""

from __future__ import annotations

import collections
import enum
import logging
import math

import numpy as np

from companion.mavlink.dialect import UINT16_MAX, mavlink  # first: MAVLink 2 + ardupilotmega
from companion.core.sectors import SECTOR_COUNT, SectorState, fold_into_bins, forward_reading_consistent, forward_unknown_reason
from companion.mavlink import messages as M
from companion.pipeline import FrameResult, PipelineConfig

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------- health -------------------
class HealthState(str, enum.Enum):
    STARTING = "starting"  # STANDBY: waiting for the first valid frame
    ACTIVE = "active"  # ACTIVE: valid ranges produced (some sector makes a claim)
    NO_RANGES = "no_ranges"  # STANDBY: running, but no sector can make a claim (no texture, not converged)
    FAULT = "fault"  # CRITICAL: an input is missing or stale; every sector is published unknown


_STATE_STATUS = {
    HealthState.STARTING: mavlink.MAV_STATE_STANDBY,
    HealthState.ACTIVE: mavlink.MAV_STATE_ACTIVE,
    HealthState.NO_RANGES: mavlink.MAV_STATE_STANDBY,
    HealthState.FAULT: mavlink.MAV_STATE_CRITICAL,
}


class Health:
    """State of the ranging output, from the inputs and the latest result (pure; caller's clock)."""

    def __init__(self, config: PipelineConfig, start: float):
        self.cfg = config
        self.start = start
        self.state = HealthState.STARTING
        self.reason = "starting"
        self._announced: tuple[HealthState, str] | None = None
        self._pending_since: float | None = None
        self._last_claim: float | None = None
        self._ever_valid = False

    @property
    def system_status(self) -> int:
        return _STATE_STATUS[self.state]

    @property
    def valid(self) -> bool:
        """Ranges may be published as valid."""
        return self.state in (HealthState.ACTIVE, HealthState.NO_RANGES)

    def evaluate(self, now: float, result: FrameResult | None, last_frame_at: float | None, link_ok: bool,
                 telemetry_problem: str) -> tuple[HealthState, str]:
        cfg = self.cfg
        if result is not None and result.ok:
            self._ever_valid = True
        if result is not None and result.restart:
            self._last_claim = None  # whatever was claimed before the restart is gone
        if result is not None and result.claims:
            self._last_claim = max(self._last_claim or -math.inf, result.t_capture)
        problem = self._problem(now, result, last_frame_at, link_ok, telemetry_problem)
        if problem:
            if not self._ever_valid and now - self.start < cfg.startup_grace_s:
                return HealthState.STARTING, problem
            return HealthState.FAULT, problem
        if self._last_claim is not None and now - self._last_claim <= cfg.active_hold_s:
            return HealthState.ACTIVE, "ranging"
        return HealthState.NO_RANGES, "no converged features"

    def _problem(self, now, result, last_frame_at, link_ok, telemetry_problem) -> str:
        """Why no valid range can be published now ("" if nothing is wrong)."""
        cfg = self.cfg
        if not link_ok:
            return "no autopilot heartbeat"
        if telemetry_problem:
            return telemetry_problem
        if last_frame_at is None:
            return "no camera frames"
        if now - last_frame_at > cfg.camera_timeout_s:
            return "camera lost"
        if result is None:
            return "waiting for a frame"
        if not result.ok:
            return "error" if result.reason.startswith("error") else result.reason
        if now - result.t_capture > cfg.result_max_age_s:
            # frames still arriving but none processed in time (CPU overload, telemetry late), or the camera went quiet
            return "camera lost" if now - last_frame_at > 0.1 else "frames not processed in time"
        return ""

    def update(self, now: float, result: FrameResult | None, last_frame_at: float | None, link_ok: bool,
               telemetry_problem: str) -> list[tuple[int, str]]:
        """Re-evaluate; returns the STATUSTEXT events (severity, text) due now."""
        state, reason = self.evaluate(now, result, last_frame_at, link_ok, telemetry_problem)
        events: list[tuple[int, str]] = []
        if (state, reason) != (self.state, self.reason):
            self._pending_since = now
            if state != self.state:
                log.debug("ranging state %s -> %s (%s)", self.state.value, state.value, reason)
        self.state, self.reason = state, reason
        if self._announced != (state, reason) and self._pending_since is not None:
            if now - self._pending_since >= self.cfg.status_debounce_s:
                self._announced = (state, reason)
                self._pending_since = None
                events.append(self._text(state, reason))
        return events

    @staticmethod
    def _text(state: HealthState, reason: str) -> tuple[int, str]:
        if state == HealthState.ACTIVE:
            return mavlink.MAV_SEVERITY_INFO, "Ranging active"
        if state == HealthState.NO_RANGES:
            return mavlink.MAV_SEVERITY_NOTICE, f"Ranging: {reason}"
        if state == HealthState.STARTING:
            return mavlink.MAV_SEVERITY_INFO, f"Ranging starting: {reason}"
        return mavlink.MAV_SEVERITY_WARNING, f"Ranging invalid: {reason}"


# ---------------------------------------------------------------------- reporter -----------------
def _rot_z(p: tuple[float, float, float], dyaw: float) -> tuple[float, float, float]:
    """A body-frame point seen after the vehicle yawed by ``dyaw`` (rad, + right)."""
    c, s = math.cos(dyaw), math.sin(dyaw)
    x, y, z = p
    return (c * x + s * y, -s * x + c * y, z)


class Reporter:
    """Results and input state → messages per output (see module docstring).

    ``outputs``: the outputs present (``"autopilot"`` always, ``"gcs"`` optional).  With
    ``heartbeat=True`` it also emits HEARTBEAT itself (replay; live, the MavLink does it).
    Every method returns a list of ``(output, message)``.
    """

    #: NAMED_VALUE_FLOAT diagnostics: frame rate, live tracks, nearest range, latency, points held by the
    #: obstacle map, sectors claimed from memory only (no live point), sectors inferred between two sides (docs/derivations/obstacle_map.md, sectors.md),
    #: the forward range and its σ, and why the forward sector is unknown (an UnknownReason code, 0 when it claims;
    #: docs/derivations/sectors.md, "Why a sector is unknown")
    STATE_PREFIX = ("Ranging active", "Ranging:", "Ranging starting:", "Ranging invalid:")  # the texts of the ranging state (Health)
    DIAG_NAMES = ("MR_FPS", "MR_TRACKS", "MR_NEAR_M", "MR_LAT_MS", "MR_MAP", "MR_MEM_SEC", "MR_INFER", "MR_FWD_M", "MR_FWD_SIG",
                  "MR_FWD_WHY")

    def __init__(self, config, pipeline: PipelineConfig, outputs=("autopilot",), start: float = 0.0,
                 heartbeat: bool = False, sector_sink=None):
        self.config = config
        #: called as ``sector_sink(output, time_usec, distances_cm, sources, forward, reasons)`` for every OBSTACLE_DISTANCE
        #: built (``forward``: the forward DISTANCE_SENSOR's current_distance, covariance, signal_quality, sent or not;
        #: ``reasons``: each unknown sector's UnknownReason) from a result (:class:`companion.sector_log.SectorLog`:
        #: where each sector's claim came from, and why the others have none)
        self.sector_sink = sector_sink
        self.pcfg = pipeline
        self.outputs = tuple(outputs)
        self.schedule = M.OutputSchedule(config.outputs)
        self.health = Health(pipeline, start)
        self.text_ids = M.StatusTextIds()
        self._text_last: dict[str, float] = {}  # text -> when it was last sent (bounded: see _texts)
        self._text_repeats: collections.Counter[str] = collections.Counter()  # repeats suppressed since
        self._text_queue: list[tuple[int, int, str]] = []  # (severity, arrival order, text) waiting for the overall budget
        self._text_seq = 0
        self._text_next_at = -math.inf  # when the overall budget allows the next STATUSTEXT
        self._hb = M.RateLimiter(config.link.heartbeat_hz) if heartbeat else None
        self._frame_times: collections.deque[float] = collections.deque()
        self.last_latency_s = math.nan
        self.counters: collections.Counter[str] = collections.Counter()
        self._result: FrameResult | None = None
        s = config.sectors
        self.min_cm, self.max_cm = s.min_distance_cm, s.max_distance_cm
        self._unknown = np.full(SECTOR_COUNT, UINT16_MAX, dtype=np.uint16)
        #: MAV_AUTOPILOT of the vehicle's HEARTBEAT (None until known): with ``[outputs] px4_bin_fold =
        #: "auto"`` a PX4 gets OBSTACLE_DISTANCE folded into its 10° bins (docs/derivations/sectors.md)
        self.vehicle_autopilot: int | None = None

    def fold_for_px4(self) -> bool:
        """Whether OBSTACLE_DISTANCE to the autopilot is folded into PX4's 10° bins now."""
        mode = self.config.outputs.px4_bin_fold
        return mode == "on" or (mode == "auto" and self.vehicle_autopilot == mavlink.MAV_AUTOPILOT_PX4)

    # -- inputs -----------------------------------------------------------------------------------
    def _count_frame(self, t: float) -> None:
        q = self._frame_times
        q.append(t)
        while q and t - q[0] > 2.0:
            q.popleft()

    def fps(self, now: float) -> float:
        q = self._frame_times
        while q and now - q[0] > 2.0:
            q.popleft()
        return len(q) / 2.0

    @staticmethod
    def _boot_ms(t_boot_s: float | None) -> int:
        return int(round(t_boot_s * 1000)) if t_boot_s is not None and math.isfinite(t_boot_s) and t_boot_s >= 0 else 0

    # -- messages -----------------------------------------------------------------------------------
    def _range_messages(self, out: str, now: float, res: FrameResult | None, yaw_now: float | None,
                        valid: bool, time_boot_ms: int) -> list:
        o = self.config.outputs
        msgs = []
        good = valid and res is not None and res.ok and res.sectors is not None and yaw_now is not None
        sec = res.sectors if good else None
        dyaw = 0.0
        if good and self.pcfg.rotate_sectors and math.isfinite(res.yaw):
            dyaw = math.remainder(yaw_now - res.yaw, 2 * math.pi)
        fold = out == "autopilot" and self.fold_for_px4()
        # computed when first needed, once: the distances turned to now and as sent (folded for a PX4), the forward reading
        turned = sent = forward = None

        def published():
            nonlocal turned, sent
            if sent is None and good:
                turned = sec.rotated(dyaw) if dyaw else sec.distances_cm
                sent = fold_into_bins(turned, self.max_cm)[0] if fold else turned
            return sent

        def forward_reading():
            nonlocal forward
            if forward is None:
                forward = self._forward_message(sec, dyaw, time_boot_ms, good)
            return forward

        if self.schedule.due(out, "obstacle_distance", now):
            if good:
                time_usec = self._boot_ms(res.t_boot_capture) * 1000
                msgs.append(M.obstacle_distance(published(), self.min_cm, self.max_cm, time_usec, o.sensor_type))
                if fold:
                    self.counters["px4_folded_sent"] += 1
                if self.sector_sink is not None:
                    try:  # diagnostics: never in the way of the message
                        src = sec.rotated_sources(dyaw, turned) if dyaw else sec.sources()
                        if fold:
                            src = fold_into_bins(turned, self.max_cm, src)[1]
                        why = sec.rotated_reasons(dyaw, turned) if dyaw else sec.unknown_reason  # folding keeps unknown as it was
                        f = forward_reading()
                        self.sector_sink(out, time_usec, sent, src, (f.current_distance, f.covariance, f.signal_quality), why)
                    except Exception:
                        self.counters["sector_log_errors"] += 1
            else:
                msgs.append(M.obstacle_distance(self._unknown, self.min_cm, self.max_cm, 0, o.sensor_type))
                self.counters["unknown_sent"] += 1
        if self.schedule.due(out, "distance_sensor", now):
            m = forward_reading()
            if out != "autopilot" or self._forward_consistent(m, published()):
                msgs.append(m)
            else:  # it would undo what OBSTACLE_DISTANCE says ahead (docs/derivations/sectors.md)
                self.counters["distance_sensor_withheld"] += 1
        if good and sec.nearest and self.schedule.due(out, "obstacle_3d", now):
            lo, hi = self.min_cm / 100.0, self.max_cm / 100.0
            for ob in sec.nearest:
                x, y, z = _rot_z(ob.p_body, dyaw)
                msgs.append(M.obstacle_distance_3d(x, y, z, ob.sector, lo, hi, time_boot_ms, o.sensor_type))
        return msgs

    def _forward_message(self, sec, dyaw: float, time_boot_ms: int, good: bool):
        """The forward DISTANCE_SENSOR of a result: unknown without one, or when the vehicle turned so far
        since exposure (≥ 2.5°) that the forward sector no longer holds what it saw."""
        o = self.config.outputs
        if good and abs(dyaw) < math.radians(2.5):
            return M.distance_sensor_from_sectors(sec, time_boot_ms, sensor_id=o.distance_sensor_id,
                                                  sensor_type=o.sensor_type, zero_rel_sigma=o.quality_zero_rel_sigma)
        return M.distance_sensor("unknown", math.nan, math.nan, self.min_cm, self.max_cm, time_boot_ms,
                                 sensor_id=o.distance_sensor_id, sensor_type=o.sensor_type,
                                 horizontal_fov_rad=math.radians(5.0))

    def _forward_consistent(self, m, d) -> bool:
        """A forward DISTANCE_SENSOR goes to the autopilot only when it leaves the autopilot holding
        what OBSTACLE_DISTANCE ``d`` says about the region it is merged into: never "unknown" (PX4
        reads UINT16_MAX as free space), "clear" only with nothing ahead, an obstacle only when no
        obstacle of ArduPilot's front face lies distinctly nearer (``[outputs] distance_sensor_face_rel_tol``;
        docs/derivations/sectors.md, "The forward DISTANCE_SENSOR and the autopilots")."""
        cm = int(m.current_distance)
        if d is None or cm == UINT16_MAX:
            return False
        state = "clear" if cm > self.max_cm else "obstacle"
        return forward_reading_consistent(state, cm, d, self.max_cm, self.config.outputs.distance_sensor_face_rel_tol)

    def _diagnostics(self, now: float, time_boot_ms: int) -> list:
        res = self._result
        nearest = fwd_m = fwd_sigma = -1.0  # -1: unknown
        tracks = n_map = mem_sec = inferred = fwd_why = 0.0
        if res is not None and res.ok and res.sectors is not None:
            sec = res.sectors
            f = sec.forward  # the forward DISTANCE_SENSOR's range and its σ, in metres (the σ a uint8 covariance cannot carry)
            if SectorState(f.state) == SectorState.OBSTACLE and math.isfinite(f.distance_m):
                fwd_m = float(f.distance_m)
                fwd_sigma = float(f.sigma_m) if math.isfinite(f.sigma_m) else -1.0
            tracks, n_map = float(res.n_tracks), float(res.n_map)
            n = sec.nearest_m
            nearest = float(n) if math.isfinite(n) else -1.0
            mem_only = (sec.remembered_points > 0) & (sec.remembered_points == sec.obstacle_points)
            mem_sec, inferred = float(np.count_nonzero(mem_only)), float(sec.n_inferred)
            fwd_why = float(forward_unknown_reason(sec, self.config.sectors.forward_half_width_deg))
        lat = self.last_latency_s * 1000.0 if math.isfinite(self.last_latency_s) else -1.0
        vals = (self.fps(now), tracks, nearest, lat, n_map, mem_sec, inferred, fwd_m, fwd_sigma, fwd_why)
        return [M.named_value_float(name, v, time_boot_ms) for name, v in zip(self.DIAG_NAMES, vals)]

    def _texts(self, events, now: float) -> list:
        """STATUSTEXT for the events, within two limits (a fault repeating every frame, or a link
        misbehaving, must not flood a 57600-baud radio, the operator or the log):

        * the same text at most once per ``statustext_min_interval_s``; the next one sent says how
          many were held back;
        * all texts together at most one per ``statustext_interval_s``: texts wait in a queue of
          ``statustext_queue`` and leave most severe first (then oldest first); when it is full the
          least severe is dropped and counted (``statustext_dropped``); a ranging state
          (``Ranging active`` / ``invalid: …`` / …) replaces one still waiting (it would announce a state already left).
          Every text is logged when it arrives, sent or not.
        """
        gap = self.pcfg.statustext_min_interval_s
        queued = {t for _, _, t in self._text_queue}
        for sev, text in events:
            last = self._text_last.get(text)
            if text in queued or (last is not None and 0.0 <= now - last < gap):
                self._text_repeats[text] += 1
                self.counters["statustext_suppressed"] += 1
                continue
            if len(self._text_last) >= 64:  # texts with numbers in them (clock jumps) must not grow this
                for k in [k for k, t in self._text_last.items() if not 0.0 <= now - t < gap]:
                    del self._text_last[k]
                    self._text_repeats.pop(k, None)
            self._text_last[text] = now
            log.log(logging.WARNING if sev <= mavlink.MAV_SEVERITY_WARNING else logging.INFO, "STATUSTEXT: %s", text)
            if text.startswith(self.STATE_PREFIX):  # a newer ranging state makes a waiting one obsolete
                for e in [e for e in self._text_queue if e[2].startswith(self.STATE_PREFIX)]:
                    self._text_queue.remove(e)
                    queued.discard(e[2])
                    self.counters["statustext_superseded"] += 1
            self._text_seq += 1
            self._text_queue.append((int(sev), self._text_seq, text))
            queued.add(text)
            if len(self._text_queue) > self.pcfg.statustext_queue:  # drop the least severe, the newest of those
                worst = max(self._text_queue, key=lambda e: (e[0], e[1]))
                self._text_queue.remove(worst)
                queued.discard(worst[2])
                self.counters["statustext_dropped"] += 1
        out = []
        while self._text_queue and now >= self._text_next_at:
            sev, _, text = best = min(self._text_queue)
            self._text_queue.remove(best)
            self._text_next_at = now + self.pcfg.statustext_interval_s
            n = self._text_repeats.pop(text, 0)
            if n:
                text = f"{text} (+{n})"
            for m in self.text_ids.encode(text, sev):
                for o in self.outputs:
                    out.append((o, m))
        return out

    def on_result(self, res: FrameResult, now: float, *, yaw_now: float | None, last_frame_at: float | None,
                  link_ok: bool = True, telemetry_problem: str = "", time_boot_ms: int = 0) -> list:
        """A frame was processed; ``now`` = when its messages leave (after processing)."""
        self._result = res
        if res.ok:
            self._count_frame(now)
            self.last_latency_s = now - res.t_capture
        events = []
        if res.restart and res.restart != "gap":
            events.append((mavlink.MAV_SEVERITY_WARNING, f"Ranging restarted: {res.restart}"))
        events += self.health.update(now, res, last_frame_at, link_ok, telemetry_problem)
        msgs = self._texts(events, now)
        valid = self.health.valid and res.ok and now - res.t_capture <= self.pcfg.result_max_age_s
        if valid:
            for o in self.outputs:
                msgs += [(o, m) for m in self._range_messages(o, now, res, yaw_now, True, time_boot_ms)]
            self.counters["results_published"] += 1
        return msgs

    def tick(self, now: float, *, yaw_now: float | None, last_frame_at: float | None, link_ok: bool = True,
             telemetry_problem: str = "", time_boot_ms: int = 0, events=()) -> list:
        """Periodic duties: state, STATUSTEXT, unknown messages while invalid, diagnostics, HEARTBEAT."""
        evs = list(events) + self.health.update(now, self._result, last_frame_at, link_ok, telemetry_problem)
        msgs = self._texts(evs, now)
        res = self._result
        valid = self.health.valid and res is not None and res.ok and now - res.t_capture <= self.pcfg.result_max_age_s
        for o in self.outputs:
            if not valid:  # explicit "unknown" at the normal rate: nothing may keep looking valid
                msgs += [(o, m) for m in self._range_messages(o, now, None, None, False, time_boot_ms)]
            if self.schedule.due(o, "named_value", now):
                msgs += [(o, m) for m in self._diagnostics(now, time_boot_ms)]
        if self._hb is not None and self._hb.ready(now):
            hb = M.heartbeat(self.health.system_status)
            msgs += [(o, hb) for o in self.outputs]
        return msgs


__all__ = ["HealthState", "Health", "Reporter"]
