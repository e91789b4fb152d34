"""The per-frame ranging pipeline and the live companion process (docs/derivations/frames.md, docs/derivations/sectors.md).

Three layers, each usable on its own:

:class:`Pipeline` (pure apart from what it is handed: the camera config, the module configs and a
:class:`~companion.telemetry.TelemetryBuffer`)
    frame → vehicle pose at the capture time from the telemetry buffer (attitude by quaternion
    slerp between the bracketing ATTITUDE samples, position linearly, or extrapolated with the
    reported velocity for at most ``position_extrapolation_s``) → camera pose through the mount →
    :class:`~companion.core.tracks.TrackManager` guided by the telemetry prediction (epipolar
    window, narrowed by converged landmark depths) → :class:`~companion.core.estimator.RangeEstimator`
    (``[estimator] filter``) → the local obstacle map (:mod:`companion.core.obstacle_map`: points on
    the current rays, converged landmarks kept after their tracks end, re-observation, retention)
    → live and remembered points into body FRD at exposure → :func:`compute_sectors` over 360°.
    A frame without a usable pose is skipped and its :class:`FrameResult` says why (``ok`` False);
    a frame stamped before the previous one, a jump of the TIMESYNC mapping, an autopilot reboot or
    a long gap restart tracks and filters so no range survives a clock it was not measured on.

:class:`Reporter` (pure; the caller's clock)
    turns results and the state of the inputs into messages per output (``"autopilot"``,
    ``"gcs"``): OBSTACLE_DISTANCE / DISTANCE_SENSOR / OBSTACLE_DISTANCE_3D for every valid result,
    rotated by the yaw change between exposure and sending, at the ``[outputs]`` rates;
    NAMED_VALUE_FLOAT diagnostics (≤ 1 Hz); STATUSTEXT on every state change; all-unknown
    messages (UINT16_MAX) while no valid range exists.  Its :class:`Health` decides the HEARTBEAT
    ``system_status``: ACTIVE only while valid ranges are being produced, STANDBY while starting or
    while no sector can make a claim, CRITICAL on a fault (telemetry stale > 0.5 s or missing,
    no clock sync, camera lost, link lost, frames not processed in time).

:class:`Companion`
    owns the MAVLink link(s), the camera source and the two pieces above and runs the main loop:
    poll the links often, take the newest frame (older unread frames are dropped by the source),
    drop a frame older than ``max_frame_age_s`` when processing would start, let a frame wait at
    most ``telemetry_wait_s`` for the ATTITUDE sample that brackets it, process, publish.
    In lockstep with a simulator (``companion run --clock sim``, :mod:`companion.simclock`) it runs
    one round per frame instead (:meth:`Companion.step_lockstep`) on a clock that follows
    simulation time, so a SITL run is deterministic and as fast as the CPU allows.

The replay tool (:mod:`companion.replay`) drives the same Pipeline and Reporter offline.
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import logging
import math
import threading
import time
from typing import Callable

import numpy as np

from companion.mavlink.dialect import UINT16_MAX, mavlink  # first: MAVLink 2 + ardupilotmega
from companion.camera_sources import Frame, FrameSource, check_gray
from companion.config import require, require_finite
from companion.core.camera import CameraConfig, CameraModel
from companion.core.estimator import RangeEstimator, RangeOutput
from companion.core import jit
from companion.interrupts import interrupt_in
from companion.core.frames import R_to_euler_zyx
from companion.core.obstacle_map import ObstacleMap, live_view, map_entries, points_on_current_rays, world_to_body
from companion.core.prediction import make_track_predictor
from companion.core.priority import detection_priority, live_points_per_sector
from companion.core.sectors import SECTOR_COUNT, Sectors, SectorState, compute_sectors
from companion.core.tracks import TrackManager
from companion.errors import CompanionError
from companion.mavlink import messages as M
from companion.telemetry import TelemetryBuffer

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------- configuration ----------
@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """The ``[pipeline]`` table: timing rules of the live loop and of the published output."""

    max_frame_age_s: float = 0.2  # a frame older than this when processing would start is dropped, s
    telemetry_wait_s: float = 0.06  # a frame newer than the newest ATTITUDE waits at most this long (after exposure) for it, s
    position_extrapolation_s: float = 0.1  # position may be extrapolated with the reported velocity this far past the newest LOCAL_POSITION_NED, s
    max_frame_gap_s: float = 0.5  # a longer gap between processed frames restarts tracks and filters, s
    clock_jump_s: float = 0.1  # the TIMESYNC mapping moving by more than this between frames is a clock jump (restart, reported), s
    future_tolerance_s: float = 0.05  # a frame stamped later than now + this is a clock fault, s
    result_max_age_s: float = 0.3  # ranges older than this (exposure → sending) are never published as valid, s
    camera_timeout_s: float = 0.3  # no frame from the camera for this long = camera lost, s
    startup_grace_s: float = 5.0  # until the first valid frame, problems are reported as "starting" for this long, s
    active_hold_s: float = 1.0  # HEARTBEAT stays ACTIVE this long after the last sector that made a claim, s
    status_debounce_s: float = 0.2  # a state must hold this long before STATUSTEXT announces it (the HEARTBEAT changes at once), s
    statustext_min_interval_s: float = 1.0  # the same STATUSTEXT is sent at most once per this interval; repeats in between are counted and the next one says how many, s
    statustext_interval_s: float = 1.0  # all texts together: at most one STATUSTEXT per this interval (the most severe first; the rest wait in a short queue), s; 0 = no overall limit
    statustext_queue: int = 8  # texts waiting for their turn; beyond this the least severe is dropped (counted)
    rotate_sectors: bool = True  # rotate sectors by the yaw change between exposure and sending
    depth_prediction: bool = True  # converged landmark depths narrow the NCC search windows

    def __post_init__(self) -> None:
        for name in ("max_frame_age_s", "telemetry_wait_s", "max_frame_gap_s", "clock_jump_s", "result_max_age_s",
                     "camera_timeout_s", "active_hold_s", "startup_grace_s"):
            require_finite(name, getattr(self, name), positive=True)
        for name in ("position_extrapolation_s", "future_tolerance_s", "status_debounce_s", "statustext_min_interval_s",
                     "statustext_interval_s"):
            require_finite(name, getattr(self, name), nonnegative=True)
        require(isinstance(self.statustext_queue, int) and not isinstance(self.statustext_queue, bool)
                and 1 <= self.statustext_queue <= 64, f"statustext_queue must be an integer in [1, 64], got {self.statustext_queue!r}")
        require(self.telemetry_wait_s < self.max_frame_age_s, "telemetry_wait_s must be < max_frame_age_s")
        require(self.result_max_age_s <= 0.5, "result_max_age_s must be <= 0.5 s (both autopilots treat older data as stale)")
        require(isinstance(self.rotate_sectors, bool), "rotate_sectors must be true or false")
        require(isinstance(self.depth_prediction, bool), "depth_prediction must be true or false")


# ---------------------------------------------------------------------- results -----------------
@dataclasses.dataclass
class FrameResult:
    """What :meth:`Pipeline.process` made of one frame."""

    frame_index: int
    t_capture: float  # capture time, companion clock (recording clock in replay)
    t_start: float  # when processing started, same clock
    processing_s: float  # measured processing time (wall clock)
    ok: bool  # sectors are valid for this exposure
    reason: str  # "ok" or why the frame gave no valid sectors
    sectors: Sectors | None = None
    roll: float = math.nan
    pitch: float = math.nan
    yaw: float = math.nan  # vehicle yaw at exposure, rad
    n_tracks: int = 0
    n_new_tracks: int = 0
    n_landmarks: int = 0
    n_converged: int = 0
    restart: str = ""  # non-empty: tracks and filters restarted on this frame, and why
    n_map: int = 0  # points held by the local obstacle map
    n_remembered: int = 0  # map points no longer tracked (published from memory)
    n_looming: int = 0  # looming (patch scale) updates fused in this frame
    t_boot_capture: float | None = None  # capture time on the autopilot's boot clock (s), if mapped
    cpu_s: float = 0.0  # CPU time this thread spent on the frame (time.thread_time), s
    stage_cpu_s: dict[str, float] = dataclasses.field(default_factory=dict)  # of which: track, estimate, map, sectors

    @property
    def claims(self) -> bool:
        return bool(self.ok and self.sectors is not None and self.sectors.any_valid)


# ---------------------------------------------------------------------- the pipeline -------------
class Pipeline:
    """Frame → sectors (see module docstring).  Owns the tracker and the estimator."""

    def __init__(self, camera: CameraConfig, config, pipeline: PipelineConfig, telemetry: TelemetryBuffer,
                 wall_clock: Callable[[], float] = time.perf_counter):
        """``config`` is a :class:`~companion.io.config_files.CompanionConfig` (its ``camera`` is
        replaced by ``camera``, e.g. from a calibration file).  Compiles the numba kernels (or loads
        them from the disk cache) so that the first frame does not pay for it."""
        jit.warm_up()
        self.camera_config = camera
        self.camera = CameraModel(camera)
        self.config = config
        self.pcfg = pipeline
        self.telemetry = telemetry
        self._wall = wall_clock
        self._R_cam_body = camera.R_cam_body
        self.hfov = camera.hfov_rad
        self.vfov = math.atan((camera.height - 1 - camera.cy + 0.5) / camera.fy) + math.atan((camera.cy + 0.5) / camera.fy)
        self.counters: collections.Counter[str] = collections.Counter()
        self.last_result: FrameResult | None = None
        self.last_ok: FrameResult | None = None
        self._reset_seen = telemetry.counters.get("reset", 0)
        self._offset: float | None = None
        self._epoch = 0
        mcfg = getattr(config, "map", None)
        self.map = ObstacleMap(mcfg) if mcfg is not None and mcfg.enabled else None
        self._bearing_sigma = config.ekf_anchored.sigma_px / min(camera.fx, camera.fy)
        self._new_state()

    # -- state -------------------------------------------------------------------------------------
    def _new_state(self) -> None:
        c = self.config
        self.tracks = TrackManager(self.camera, c.harris, c.ncc, c.tracks)
        self.estimator = RangeEstimator(self.camera_config, c.estimator, c.triangulation, c.ekf_anchored, c.ekf_landmark)
        self._k = 0  # frame counter handed to the tracker (the source's index may restart)
        self._t_prev: float | None = None
        self._cam_prev: tuple[np.ndarray, np.ndarray] | None = None
        self._out_prev: RangeOutput | None = None
        self._epoch += 1  # track ids restart with a new tracker: map keys carry the epoch
        self._key_base = self._epoch << 40

    def reset(self, why: str) -> None:
        """Forget all tracks and landmarks (clock jump, reboot, long gap).  The obstacle map is kept
        across a gap (the local NED frame is unchanged and its points age with the drift model) and
        cleared on everything else (a reboot or a clock change may move the frame or the clock)."""
        self.counters[f"restart_{why.split(':')[0].replace(' ', '_')}"] += 1
        log.info("ranging restarted: %s", why)
        if self.map is not None and why != "gap":
            self.map.clear()
        self._new_state()

    # -- telemetry helpers ------------------------------------------------------------------------
    def telemetry_problem(self, now: float) -> str:
        """"" when attitude and position are fresh, else a stable reason (no numbers)."""
        tel = self.telemetry
        if tel.attitude_count == 0 and tel.position_count == 0:
            return "no telemetry"
        if tel.clock_offset_s is None:
            return "no clock sync"
        max_age = tel.config.max_age_s
        if tel.age(now, "attitude") > max_age:
            return "attitude stale"
        if tel.age(now, "position") > max_age:
            return "position stale"
        return ""

    def yaw_now(self, now: float) -> float | None:
        """Vehicle yaw at ``now`` from the newest ATTITUDE (None if stale or unknown)."""
        tel = self.telemetry
        tb = tel.newest_boot_s("attitude")
        if tb is None or tel.age(now, "attitude") > tel.config.max_age_s:
            return None
        r = tel.pose_at_boot(tb, need_position=False)
        if not r.ok:
            return None
        rpy = r.pose.rpy  # once (R from the quaternion, then Euler angles)
        yaw = float(rpy[2])
        rates = r.pose.rates_body
        dt = now - (tb + tel.clock_offset_s)
        if 0 < dt < 0.1 and np.all(np.isfinite(rates)):  # bridge the telemetry latency with the yaw rate
            roll, pitch = rpy[:2]
            if abs(math.cos(pitch)) > 1e-3:
                yaw_rate = (rates[1] * math.sin(roll) + rates[2] * math.cos(roll)) / math.cos(pitch)
                yaw += yaw_rate * dt
        return float(yaw)

    def readiness(self, t_capture: float, now: float) -> str:
        """"ready" (process now), "wait" (the bracketing ATTITUDE may still come) or "fail"."""
        tel = self.telemetry
        if tel.clock_offset_s is None:
            return "fail"
        r = tel.pose_at(t_capture, now=now, need_position=False)
        if r.ok:
            return "ready"
        if r.reason == "after_buffer" and now - t_capture < self.pcfg.telemetry_wait_s:
            return "wait"
        return "fail"

    def _pose(self, t: float, now: float):
        """(R_world_body, p_world, v_world, rates) at ``t`` or a reason string."""
        tel = self.telemetry
        if tel.clock_offset_s is None:
            return "telemetry: no clock sync" if (tel.attitude_count or tel.position_count) else "telemetry: none received"
        att = tel.pose_at(t, now=now, need_position=False)
        if not att.ok:
            return f"telemetry: attitude {att.reason}"
        pos = tel.pose_at(t, now=now, need_position=True)
        if pos.ok:
            p, v = pos.pose.p_world, pos.pose.v_world
        elif pos.reason == "position:after_buffer":
            tb_new = tel.newest_boot_s("position")
            dt = t - tel.to_companion(tb_new)
            if not 0 <= dt <= self.pcfg.position_extrapolation_s:
                return "telemetry: position after buffer"
            last = tel.pose_at_boot(tb_new, need_position=True)
            if not last.ok:
                return f"telemetry: position {last.reason}"
            p = last.pose.p_world + last.pose.v_world * dt
            v = last.pose.v_world
            self.counters["position_extrapolated"] += 1
        else:
            return f"telemetry: {pos.reason.replace(':', '')}"
        return att.pose.R_world_body, np.asarray(p, float), np.asarray(v, float), att.pose.rates_body

    # -- depth of tracked points for the predictor -----------------------------------------------------
    def _depth_of(self, out: RangeOutput, cam_prev):
        if out is None or len(out.ids) == 0:
            return None
        use = out.converged & out.valid
        if not np.any(use):
            return None
        ids_sorted = out.ids[use]
        order = np.argsort(ids_sorted)
        ids_sorted = ids_sorted[order]
        R_prev, p_prev = cam_prev
        z = ((out.p_world[use][order] - p_prev) @ R_prev[:, 2])
        sig = out.range_sigma[use][order]

        def depth_of(ids: np.ndarray):
            d = np.zeros(len(ids))
            s = np.zeros(len(ids))
            if len(ids):
                pos = np.minimum(np.searchsorted(ids_sorted, ids), len(ids_sorted) - 1)
                hit = (ids_sorted[pos] == ids) & (z[pos] > 0)
                d[hit] = z[pos][hit]
                s[hit] = sig[pos][hit]
            return d, s

        return depth_of

    def _detection_priority(self, res: FrameResult, R_wb, v_w):
        """Where the tracker's refill looks first: the band around the flight path,
        in the direction of travel and in the in-view sectors without a live point in the previous
        frame (:func:`companion.core.priority.detection_priority`); None when switched off."""
        tc = self.config.tracks
        if tc.priority_share <= 0 and tc.priority_min_tracks <= 0:
            return None
        prev = self.last_ok.sectors if self.last_ok is not None and self._t_prev is not None else None
        return detection_priority(
            self.camera, self.config.sectors, roll_pitch_rad=(res.roll, res.pitch), velocity_body=R_wb.T @ v_w,
            live_points=live_points_per_sector(prev), band_range_m=tc.priority_band_range_m,
            path_half_width_deg=tc.priority_path_half_width_deg,
        )

    # -- one frame ----------------------------------------------------------------------------------
    def process(self, frame: Frame, now: float) -> FrameResult:
        """Run one frame captured at ``frame.t``; ``now`` = processing start (same clock)."""
        w0 = self._wall()
        c0 = time.thread_time()
        index, t, gray = frame
        res = FrameResult(int(index), float(t), float(now), 0.0, False, "")
        try:
            self._process(res, gray, now)
        except CompanionError as exc:  # bad input somewhere in the core: skip the frame, start afresh
            self.counters["errors"] += 1
            res.ok, res.reason, res.sectors = False, f"error: {exc}"[:120], None
            log.warning("frame %d skipped: %s; ranging restarts", index, exc)
            if self.map is not None:
                self.map.clear()
            self._new_state()
            res.restart = res.restart or "error"
        except Exception as exc:  # a bug: never take the process down, say so loudly, start afresh
            stop = interrupt_in(exc)
            if stop is not None:  # Ctrl-C / SIGTERM that arrived inside a compiled call: not a bug
                raise stop from None
            self.counters["internal_errors"] += 1
            if self.counters["internal_errors"] <= 5:
                log.exception("internal error on frame %d: %r; ranging restarts", index, exc)
            res.ok, res.reason, res.sectors = False, "error: internal", None
            if self.map is not None:
                self.map.clear()
            self._new_state()
            res.restart = "internal error"
        res.processing_s = self._wall() - w0
        res.cpu_s = time.thread_time() - c0
        self.counters["frames_ok" if res.ok else "frames_failed"] += 1
        self.last_result = res
        if res.ok:
            self.last_ok = res
        return res

    @property
    def landmarks(self) -> RangeOutput | None:
        """The estimator's output for the latest processed frame (world points, ranges, σ)."""
        return self._out_prev

    def _update_map(self, t, out: RangeOutput, tf, p_world, R_wc, p_wc, p_wb):
        """The local obstacle map's steps for this frame, in order (docs/derivations/obstacle_map.md; see
        :mod:`companion.core.obstacle_map`); returns the remembered points (None without a map)."""
        omap = self.map
        if omap is None:
            return None
        e = map_entries(out.ids, self._key_base, out.converged, out.valid, out.range_sigma, out.range, p_world, p_wc,
                        self._bearing_sigma, omap.config, out.mean_nis)
        if len(e.forget):  # converged but inconsistent: not a point the map should keep, forget what it left there
            omap.forget(e.forget)
        rej = omap.observe(t, e.entry_keys, e.p_world, e.P_world, live_keys=e.keys)
        for why, n in rej.items():
            if n:
                self.counters[f"map_rejected_{why}"] += n
        if len(out.retired_ids):
            omap.forget(np.asarray(out.retired_ids, np.int64) + self._key_base)
        # live converged landmarks seen in this frame: pinhole pixel, depth and its σ
        *live, live_keys = live_view(out.ids, tf.ids, tf.uv, e.keys, e.good, p_world, out.range_sigma, out.range, R_wc, p_wc,
                                     self.camera)
        c = self.camera_config
        vc = omap.check_view(t, R_wc, p_wc, c.fx, c.fy, c.cx, c.cy, c.width, c.height, *live, live_keys=live_keys)
        self.counters["map_found"] += vc.found
        self.counters["map_missed"] += vc.missed
        omap.prune(t, p_wb)
        return omap.remembered(t, p_wb)

    def _process(self, res: FrameResult, gray, now: float) -> None:
        cfg, tel = self.pcfg, self.telemetry
        t = res.t_capture
        gray, why = check_gray(gray, self.camera_config.width, self.camera_config.height)
        if gray is None:
            res.reason = f"bad frame: {why}"
            return
        if not gray.flags.writeable:  # e.g. a frame viewed in a receive buffer: the compiled kernels are
            gray = gray.copy()  # specialized for writable arrays (a read-only one would compile anew, mid-flight)
        if not math.isfinite(t):
            res.reason = "bad frame: time not finite"
            return
        # clock and reboot guards: restart rather than mix clocks
        resets = tel.counters.get("reset", 0)
        if resets != self._reset_seen:
            self._reset_seen = resets
            res.restart = "autopilot reboot"
            self.reset(res.restart)
        off = tel.clock_offset_s
        if off is not None and self._offset is not None and abs(off - self._offset) > cfg.clock_jump_s and not res.restart:
            res.restart = f"clock jump {off - self._offset:+.2f} s"
            self.reset("clock jump")
        if off is not None:
            self._offset = off
        if t > now + cfg.future_tolerance_s:
            res.reason = "clock fault: frame stamped in the future"
            return
        if self._t_prev is not None:
            if t <= self._t_prev:
                res.restart = res.restart or "frame time went back"
                self.reset("frame time went back")
            elif t - self._t_prev > cfg.max_frame_gap_s:
                res.restart = res.restart or "gap"
                self.reset("gap")
        pose = self._pose(t, now)
        if isinstance(pose, str):
            res.reason = pose
            return
        R_wb, p_wb, v_w, _rates = pose
        res.t_boot_capture = tel.to_boot(t)
        rpy = R_to_euler_zyx(R_wb)
        res.roll, res.pitch, res.yaw = (float(a) for a in rpy)
        R_wc, p_wc = self.camera.camera_pose(R_wb, p_wb)

        predict = None
        if self._cam_prev is not None:
            depth_of = self._depth_of(self._out_prev, self._cam_prev) if cfg.depth_prediction else None
            predict = make_track_predictor(self.camera, self.config.prediction, self._cam_prev, (R_wc, p_wc), depth_of)
        stage = res.stage_cpu_s
        c0 = time.thread_time()
        tf = self.tracks.step(gray, t, self._k, predict, priority_mask=self._detection_priority(res, R_wb, v_w))
        c1 = time.thread_time()
        stage["track"] = c1 - c0
        self._k += 1
        if len(tf.dropped_ids):
            self.estimator.drop(tf.dropped_ids)
        out = self.estimator.process(t, R_wc, p_wc, tf.ids, tf.uv, scale=tf.scale, scale_sigma=tf.scale_sigma)  # looming (§7)
        if len(out.retired_ids):
            self.tracks.kill(out.retired_ids)
        self._t_prev, self._cam_prev, self._out_prev = t, (R_wc, p_wc), out
        c0, c1 = c1, time.thread_time()
        stage["estimate"] = c1 - c0

        rays_cam = self.camera.unproject(tf.uv) if len(tf.ids) else np.zeros((0, 3))
        p_world = points_on_current_rays(out.ids, out.p_world, out.range, tf.ids, rays_cam, R_wc, p_wc)
        rem = self._update_map(t, out, tf, p_world, R_wc, p_wc, p_wb)
        c0, c1 = c1, time.thread_time()
        stage["map"] = c1 - c0
        sectors = compute_sectors(
            world_to_body(p_world, R_wb, p_wb), out.range_sigma, out.converged, out.valid, self.hfov, self._R_cam_body,
            self.config.sectors, roll_pitch_rad=(res.roll, res.pitch), velocity_body=R_wb.T @ v_w, vfov_rad=self.vfov,
            remembered_p_body=None if rem is None else world_to_body(rem.p_world, R_wb, p_wb),
            remembered_sigma=None if rem is None else rem.range_sigma,
            remembered_tangential_sigma=None if rem is None else rem.tangential_sigma,
            ground_height_m=float(p_wb[2]),  # NED: the origin's level (take-off ground) relative to the vehicle
        )
        stage["sectors"] = time.thread_time() - c1
        if self.map is not None:
            res.n_map, res.n_remembered = len(self.map), len(rem)
        res.sectors = sectors
        res.n_tracks = len(tf.ids)
        res.n_new_tracks = len(tf.new_ids)
        res.n_landmarks = len(out.ids)
        res.n_looming = out.n_looming
        res.n_converged = int(np.count_nonzero(out.converged & out.valid))
        res.ok, res.reason = True, "ok"


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
    #: obstacle map, sectors claimed from memory only (no live point), sectors inferred between two sides (docs/derivations/obstacle_map.md, sectors.md)
    STATE_PREFIX = ("Ranging active", "Ranging:", "Ranging starting:", "Ranging invalid:")  # the texts of the ranging state (Health)
    DIAG_NAMES = ("MR_FPS", "MR_TRACKS", "MR_NEAR_M", "MR_LAT_MS", "MR_MAP", "MR_MEM_SEC", "MR_INFER", "MR_FWD_M", "MR_FWD_SIG")

    def __init__(self, config, pipeline: PipelineConfig, outputs=("autopilot",), start: float = 0.0,
                 heartbeat: bool = False):
        self.config = config
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
        if self.schedule.due(out, "obstacle_distance", now):
            if good:
                d = sec.rotated(dyaw) if dyaw else sec.distances_cm
                msgs.append(M.obstacle_distance(d, self.min_cm, self.max_cm, self._boot_ms(res.t_boot_capture) * 1000,
                                                o.sensor_type))
            else:
                msgs.append(M.obstacle_distance(self._unknown, self.min_cm, self.max_cm, 0, o.sensor_type))
                self.counters["unknown_sent"] += 1
        if self.schedule.due(out, "distance_sensor", now):
            if good and abs(dyaw) < math.radians(2.5):
                msgs.append(M.distance_sensor_from_sectors(sec, time_boot_ms, sensor_id=o.distance_sensor_id,
                                                           sensor_type=o.sensor_type, zero_rel_sigma=o.quality_zero_rel_sigma))
            else:  # unknown (or turned so far that the forward sector no longer holds what it saw)
                msgs.append(M.distance_sensor("unknown", math.nan, math.nan, self.min_cm, self.max_cm, time_boot_ms,
                                              sensor_id=o.distance_sensor_id, sensor_type=o.sensor_type,
                                              horizontal_fov_rad=math.radians(5.0)))
        if good and sec.nearest and self.schedule.due(out, "obstacle_3d", now):
            lo, hi = self.min_cm / 100.0, self.max_cm / 100.0
            for ob in sec.nearest:
                x, y, z = _rot_z(ob.p_body, dyaw)
                msgs.append(M.obstacle_distance_3d(x, y, z, ob.sector, lo, hi, time_boot_ms, o.sensor_type))
        return msgs

    def _diagnostics(self, now: float, time_boot_ms: int) -> list:
        res = self._result
        nearest = fwd_m = fwd_sigma = -1.0  # -1: unknown
        tracks = n_map = mem_sec = inferred = 0.0
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
        lat = self.last_latency_s * 1000.0 if math.isfinite(self.last_latency_s) else -1.0
        vals = (self.fps(now), tracks, nearest, lat, n_map, mem_sec, inferred, fwd_m, fwd_sigma)
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


# ---------------------------------------------------------------------- the live process ---------
class Companion:
    """The running companion: links + camera + pipeline + reporter (see module docstring).

    ``step()`` is one non-blocking iteration (tests drive it with a simulated clock); ``run()``
    loops it until ``stop`` is set.  Nothing that comes from the wire, the camera or the pipeline
    ends the loop: errors are logged, counted and the pipeline restarts — except a camera whose
    first frame does not have the configured size (a configuration error, see :meth:`run`).
    """

    def __init__(self, config, source: FrameSource, link, gcs=None, pipeline: PipelineConfig = PipelineConfig(),
                 camera: CameraConfig | None = None, clock: Callable[[], float] = time.monotonic):
        self.config = config
        self.pcfg = pipeline
        self.source = source
        self.link = link
        self.gcs = gcs
        self.clock = clock
        self.telemetry = link.telemetry
        self.pipeline = Pipeline(camera or config.camera, config, pipeline, self.telemetry)
        self.reporter = Reporter(config, pipeline, outputs=("autopilot", "gcs") if gcs is not None else ("autopilot",),
                                 start=clock())
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
    def step(self, wait: float = 0.0) -> None:
        """One iteration: poll links, take a frame, maybe process it, periodic duties."""
        now = self.clock()
        self.link.poll()
        if self.gcs is not None:
            self.gcs.poll()
            sid = self.link.system_id
            if sid is not None and self.gcs.system_id != sid:
                self.gcs.set_system_id(sid)
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
        self.link.poll()
        if self.gcs is not None:
            self.gcs.poll()
            sid = self.link.system_id
            if sid is not None and self.gcs.system_id != sid:
                self.gcs.set_system_id(sid)
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


__all__ = ["PipelineConfig", "FrameResult", "Pipeline", "HealthState", "Health", "Reporter", "Companion"]
