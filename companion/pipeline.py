"""The per-frame ranging pipeline (docs/derivations/frames.md, docs/derivations/sectors.md).

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

:class:`PipelineConfig` is the ``[pipeline]`` table (timing rules of the live loop and of the
published output).  What uses the results, each layer usable on its own:

* :mod:`companion.reporter` — :class:`~companion.reporter.Reporter` and its
  :class:`~companion.reporter.Health` (pure; the caller's clock): results and the state of the
  inputs → MAVLink messages per output, STATUSTEXT, the HEARTBEAT's ``system_status``;
* :mod:`companion.app` — :class:`~companion.app.Companion`, the live process: links, camera,
  pipeline and reporter in the main loop (or in lockstep with a simulator).

The replay tool (:mod:`companion.replay`) drives the same Pipeline and Reporter offline.
``HealthState``, ``Health``, ``Reporter`` and ``Companion`` stay importable from here (loaded on first
use: those modules import this one).
"""

from __future__ import annotations

import collections
import dataclasses
import importlib
import logging
import math
import time
from typing import Callable

import numpy as np

from companion.camera_sources import Frame, check_gray
from companion.config import require, require_finite
from companion.core.camera import CameraConfig, CameraModel
from companion.core.estimator import RangeEstimator, RangeOutput
from companion.core import jit
from companion.interrupts import interrupt_in
from companion.core.frames import R_to_euler_zyx_scalar
from companion.core.obstacle_map import ObstacleMap, live_view, map_entries, points_on_current_rays, world_to_body
from companion.core.prediction import make_track_predictor
from companion.core.priority import detection_priority, live_points_per_sector
from companion.core.sectors import Sectors, compute_sectors
from companion.core.sectors_confirm import confirm_clear
from companion.core.tracks import DROP_REFERENCE, REFILL_NONE, REFILL_RUN, TrackManager
from companion.errors import CompanionError
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
        #: called once per processed frame with (t, R_world_cam, p_world_cam, the estimator's RangeOutput, its points on
        #: the current rays, the tracks' patch scales and their σ, the map's remembered points as (p_world, published,
        #: age) or None), e.g. a :class:`companion.landmark_log.LandmarkLog`; an exception in it is logged and ends it
        self.landmark_sink: Callable | None = None
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
        self._clear_run: np.ndarray | None = None  # consecutive frames each sector was clear ([sectors] clear_confirm_frames)
        self._clear_yaw = 0.0  # the vehicle's yaw at that count's frame, rad
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
            return f"telemetry: {pos.reason.replace(':', ' ')}"  # "position:stale" → "telemetry: position stale"
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

    def _log_landmarks(self, t, R_wc, p_wc, out: RangeOutput, p_world, tf, rem=None) -> None:
        """Hand this frame's landmarks (and their tracks' patch scales) to ``landmark_sink``, with the map's remembered
        points (``rem``: those handed to the sectors; the rest were withheld); a sink that raises is dropped (logged),
        ranging goes on."""
        try:
            scale, scale_sigma = np.full(len(out.ids), np.nan), np.full(len(out.ids), np.nan)
            if len(tf.ids) and len(out.ids):
                order = np.argsort(tf.ids)
                j = np.clip(np.searchsorted(tf.ids, out.ids, sorter=order), 0, len(order) - 1)
                hit = tf.ids[order[j]] == out.ids
                scale[hit], scale_sigma[hit] = tf.scale[order[j[hit]]], tf.scale_sigma[order[j[hit]]]
            memory = None if self.map is None else self.map.memory(t, None if rem is None else rem.keys)
            self.landmark_sink(t, R_wc, p_wc, out, p_world, scale, scale_sigma, memory)
        except Exception as exc:  # a diagnostic must never cost a frame
            log.error("landmark sink failed (%r): no more landmarks are logged; ranging goes on", exc)
            self.counters["landmark_sink_errors"] += 1
            self.landmark_sink = None

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
        merged, superseded = omap.merged, omap.superseded
        rej = omap.observe(t, e.entry_keys, e.p_world, e.P_world, live_keys=e.keys, p_world_cam=p_wc)
        self.counters["map_merged"] += omap.merged - merged  # new landmarks that landed on a remembered point ...
        self.counters["map_superseded"] += omap.superseded - superseded  # ... and disagreed with it: not fused
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
        rpy = R_to_euler_zyx_scalar(R_wb)  # = R_to_euler_zyx(R_wb) bit for bit
        res.roll, res.pitch, res.yaw = (float(a) for a in rpy)
        R_wc, p_wc = self.camera.camera_pose(R_wb, p_wb)

        predict = None
        if self._cam_prev is not None:
            depth_of = self._depth_of(self._out_prev, self._cam_prev) if cfg.depth_prediction else None
            predict = make_track_predictor(self.camera, self.config.prediction, self._cam_prev, (R_wc, p_wc), depth_of,
                                           with_parallax=self.config.ncc.scale_order == "parallax")
        stage = res.stage_cpu_s
        c0 = time.thread_time()
        tf = self.tracks.step(gray, t, self._k, predict, priority_mask=self._detection_priority(res, R_wb, v_w), R_world_cam=R_wc)
        c1 = time.thread_time()
        stage["track"] = c1 - c0
        self._k += 1
        if tf.refill != REFILL_NONE:  # new corners searched for, or that search held back (refill back-off)
            self.counters["refills_run" if tf.refill == REFILL_RUN else "refills_paused"] += 1
        if len(tf.dropped_ids):
            self.estimator.drop(tf.dropped_ids)
            inconsistent = tf.dropped_ids[tf.drop_reason == DROP_REFERENCE]
            if len(inconsistent):  # an occlusion edge or a drifted track: what it left in the map goes too
                self.counters["tracks_reference_mismatch"] += len(inconsistent)
                if self.map is not None:
                    self.map.forget(inconsistent + self._key_base)
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
        if self.config.sectors.clear_confirm_frames > 1:  # "clear" only once it has lasted (sectors.md, rule 11)
            yaw = math.atan2(R_wb[1, 0], R_wb[0, 0])
            turned = math.remainder(yaw - self._clear_yaw, math.tau) if self._clear_run is not None else math.nan
            sectors, self._clear_run = confirm_clear(sectors, self._clear_run, turned, self.config.sectors)
            self._clear_yaw = yaw
        stage["sectors"] = time.thread_time() - c1
        if self.landmark_sink is not None:  # a diagnostic: after the stages, so their timings stay the ranging's own
            self._log_landmarks(t, R_wc, p_wc, out, p_world, tf, rem)
        if self.map is not None:
            res.n_map, res.n_remembered = len(self.map), len(rem)
        res.sectors = sectors
        res.n_tracks = len(tf.ids)
        res.n_new_tracks = len(tf.new_ids)
        res.n_landmarks = len(out.ids)
        res.n_looming = out.n_looming
        res.n_converged = int(np.count_nonzero(out.converged & out.valid))
        res.ok, res.reason = True, "ok"


# ---------------------------------------------------------------------- moved names --------------
#: names that lived in this module, now in the modules that use the pipeline (they import this one,
#: so they are loaded when first asked for here rather than imported above: no import cycle)
_MOVED = {"HealthState": "companion.reporter", "Health": "companion.reporter", "Reporter": "companion.reporter",
          "_STATE_STATUS": "companion.reporter", "_rot_z": "companion.reporter", "Companion": "companion.app"}


def __getattr__(name: str):
    home = _MOVED.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(home), name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_MOVED))


__all__ = ["PipelineConfig", "FrameResult", "Pipeline", "HealthState", "Health", "Reporter", "Companion"]
