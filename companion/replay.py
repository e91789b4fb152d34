"""Offline replay of a recorded flight through the live pipeline (``companion replay``).

Input: ``telemetry.tlog`` (MAVLink 2 tlog: 8-byte big-endian µs timestamp + packed frame per record;
the vehicle's ATTITUDE / LOCAL_POSITION_NED with ``time_boot_ms`` on its own clock), ``video.avi``
and ``frames.csv`` (``index,t_s``: capture times on the tlog's record clock) — flightsim's export
or a real flight's log and video.

Output: ``ranges.tlog``, every message the companion would have sent to the autopilot
(OBSTACLE_DISTANCE, DISTANCE_SENSOR, OBSTACLE_DISTANCE_3D if enabled, NAMED_VALUE_FLOAT,
STATUSTEXT, HEARTBEAT) from the vehicle's system id and component 196, each stamped on the
recording's clock at the moment it would have left: the frame's capture time, plus any wait for
the ATTITUDE sample that brackets the exposure (telemetry is fed in record-time order, so the
pipeline only knows what had arrived), plus the measured processing time.  Output and input
therefore line up on one clock.  Optionally a plot of the ranges over time.  Both appear only
when the replay is complete (:mod:`companion.io.atomic`); interrupted or failed, the messages
written so far are kept as ``ranges.tlog.partial``.  A tlog cut while being written, or whose
telemetry ends before the frames, is replayed with a warning (:attr:`ReplaySummary.warnings`).

Timeline.  The replay runs the live loop's rules on the recording clock with one core: a frame
arriving while the previous one is still being processed waits; when the core is free only the
newest waiting frame is taken (older ones are superseded, as the live source drops them); a frame
older than ``max_frame_age_s`` when processing would start is dropped; between frames the periodic
duties (HEARTBEAT, diagnostics, STATUSTEXT, unknown sectors while invalid) run every ``tick_s``.

Clock mapping.  A tlog holds no TIMESYNC exchange with the companion, so the offset between the
vehicle's boot clock and the record clock is the lower envelope of ``record time − time_boot_ms``
over each boot segment (a ``time_boot_ms`` reset starts a new one), minus the stated telemetry
latency (``telemetry_latency_s``; 0 assumes the fastest message arrived at once).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import struct
import time
from pathlib import Path
from typing import Callable

import numpy as np

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.camera_sources import RecordedSource
from companion.core.camera import CameraConfig
from companion.errors import ConfigError
from companion.io.atomic import StagedFiles, atomic_path
from companion.io.tlog import TlogError, read_tlog
from companion.pipeline import Pipeline, PipelineConfig
from companion.reporter import Reporter
from companion.telemetry import TelemetryBuffer

log = logging.getLogger(__name__)

_TELEMETRY = ("ATTITUDE", "LOCAL_POSITION_NED")
_NOT_VEHICLE_TYPES = {mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GIMBAL,
                      mavlink.MAV_TYPE_CAMERA, mavlink.MAV_TYPE_ADSB}


class ReplayError(ConfigError):
    """The recording cannot be replayed (no telemetry, unreadable files): bad input, exit code 2."""


# ---------------------------------------------------------------------- reading the tlog --------
@dataclasses.dataclass(frozen=True)
class TelemetryRecord:
    t: float  # record time, recording clock (s)
    kind: str  # "ATTITUDE" or "LOCAL_POSITION_NED"
    time_boot_ms: int
    values: tuple[float, ...]  # the six fields the TelemetryBuffer takes


@dataclasses.dataclass
class TlogTelemetry:
    records: list[TelemetryRecord]
    system_id: int
    counters: dict[str, int]
    segments: list[tuple[float, float]]  # (record time where a boot segment starts, its boot→record offset)
    truncation: str | None = None  # the file was cut while being written: a warning naming it (TlogContents.truncation)
    autopilot: int | None = None  # MAV_AUTOPILOT of the vehicle's HEARTBEAT (None without one)

    def offset_at(self, t: float) -> float:
        off = self.segments[0][1]
        for start, o in self.segments:
            if t >= start:
                off = o
        return off


def read_telemetry_tlog(path: str | Path, telemetry_latency_s: float = 0.0, reset_threshold_s: float = 1.0) -> TlogTelemetry:
    """Vehicle ATTITUDE / LOCAL_POSITION_NED of a tlog, in record order, and the clock mapping.

    The vehicle is the first component 1 whose HEARTBEAT names a real autopilot (else the system
    sending the most ATTITUDE).  Corrupt records are skipped and counted; a file cut while being
    written is read up to its last whole record (:attr:`TlogTelemetry.truncation` says so).  A
    missing, empty or non-MAVLink file, or one without the vehicle's telemetry, is a
    :class:`ReplayError` (a ConfigError: exit code 2).
    """
    try:
        contents = read_tlog(path)
    except TlogError as exc:
        raise ReplayError(str(exc)) from None
    p = contents.path
    counters: collections.Counter[str] = collections.Counter(contents.counters)
    raw: list[tuple[float, int, int, str, object]] = []
    vehicle: int | None = None
    autopilot: int | None = None
    for m in contents.messages:
        typ = m.get_type()
        src, comp = m.get_srcSystem(), m.get_srcComponent()
        if typ == "HEARTBEAT" and vehicle is None and comp == 1 and m.autopilot != mavlink.MAV_AUTOPILOT_INVALID \
                and m.type not in _NOT_VEHICLE_TYPES:
            vehicle, autopilot = src, int(m.autopilot)
        if typ in _TELEMETRY:
            raw.append((float(m._timestamp), src, comp, typ, m))
    if not raw:
        raise ReplayError(f"{p}: no ATTITUDE / LOCAL_POSITION_NED in the log")
    if vehicle is None:
        vehicle = collections.Counter(r[1] for r in raw if r[3] == "ATTITUDE").most_common(1)[0][0] if any(
            r[3] == "ATTITUDE" for r in raw) else raw[0][1]
        log.warning("%s: no autopilot HEARTBEAT; taking system %d as the vehicle", p, vehicle)
    recs: list[TelemetryRecord] = []
    for t, src, comp, typ, m in raw:
        if src != vehicle or comp != 1:
            counters["foreign"] += 1
            continue
        if typ == "ATTITUDE":
            vals = (m.roll, m.pitch, m.yaw, m.rollspeed, m.pitchspeed, m.yawspeed)
        else:
            vals = (m.x, m.y, m.z, m.vx, m.vy, m.vz)
        recs.append(TelemetryRecord(t, typ, int(m.time_boot_ms), tuple(float(v) for v in vals)))
    if not recs:
        raise ReplayError(f"{p}: no telemetry from the vehicle (system {vehicle}, component 1)")
    recs.sort(key=lambda r: r.t)  # stable: equal stamps keep file order
    # boot segments: time_boot_ms going back by more than reset_threshold_s starts a new one
    segments: list[tuple[float, float]] = []
    seg_start, seg_min, newest = recs[0].t, math.inf, None
    for r in recs:
        if newest is not None and (newest - r.time_boot_ms) * 1e-3 > reset_threshold_s:
            segments.append((seg_start, seg_min - telemetry_latency_s))
            seg_start, seg_min, newest = r.t, math.inf, None
        newest = r.time_boot_ms if newest is None else max(newest, r.time_boot_ms)
        seg_min = min(seg_min, r.t - r.time_boot_ms * 1e-3)
    segments.append((seg_start, seg_min - telemetry_latency_s))
    counters["telemetry"] = len(recs)
    return TlogTelemetry(recs, vehicle, dict(counters), segments, contents.truncation, autopilot)


# ---------------------------------------------------------------------- writing -----------------
class TlogOut:
    """Writes messages as one sender (system, component) into a MAVLink 2 tlog."""

    def __init__(self, path: str | Path, system_id: int, component_id: int = 196):
        self.path = Path(path)
        self._fh = self.path.open("wb")
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._last_us = 0
        self.counts: collections.Counter[str] = collections.Counter()

    def write(self, t: float, msg) -> None:
        us = max(int(round(t * 1e6)), self._last_us)  # records stay in time order
        self._last_us = us
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self._fh.write(struct.pack(">Q", us) + bytes(buf))
        self.counts[msg.get_type()] += 1

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()


# ---------------------------------------------------------------------- replay ------------------
@dataclasses.dataclass
class ReplaySummary:
    frames: int  # frames read from the video
    processed: int  # frames that gave valid sectors
    failed: dict[str, int]  # frames processed without valid sectors, by reason
    stale: int  # dropped: older than max_frame_age_s when the core became free
    superseded: int  # dropped: a newer frame was waiting
    rejected: dict[str, int]  # bad video frames / rows, by reason
    messages: dict[str, int]  # written to the output tlog, by type
    recording_s: float  # first to last frame, recording clock
    wall_s: float  # time the replay took
    latency_p50_ms: float  # capture → OBSTACLE_DISTANCE leaves, over valid results
    latency_p99_ms: float
    first_valid_s: float | None  # recording-clock time of the first valid OBSTACLE_DISTANCE after the first frame
    system_id: int
    out: Path
    plot: Path | None
    warnings: list[str] = dataclasses.field(default_factory=list)  # a truncated tlog, telemetry ending before the frames
    cpu_ms_mean: float = math.nan  # CPU time of the pipeline per processed frame (this thread), ms
    cpu_ms_p99: float = math.nan
    stage_cpu_ms: dict[str, float] = dataclasses.field(default_factory=dict)  # mean per frame: track, estimate, map, sectors


@dataclasses.dataclass
class _Trace:
    t: list[float] = dataclasses.field(default_factory=list)
    distances: list[np.ndarray] = dataclasses.field(default_factory=list)
    fwd_t: list[float] = dataclasses.field(default_factory=list)
    fwd_m: list[float] = dataclasses.field(default_factory=list)
    fwd_sigma: list[float] = dataclasses.field(default_factory=list)
    near_t: list[float] = dataclasses.field(default_factory=list)
    near_m: list[float] = dataclasses.field(default_factory=list)
    states: list[tuple[float, str]] = dataclasses.field(default_factory=list)


def replay(tlog: str | Path, video: str | Path, frames_csv: str | Path, out: str | Path, config, *,
           camera: CameraConfig | None = None, pipeline: PipelineConfig = PipelineConfig(), plot: str | Path | None = None,
           fixed_processing_s: float | None = None, telemetry_latency_s: float = 0.0, tick_s: float = 0.01,
           progress: Callable[[int, int], None] | None = None, truth: str | Path | None = None,
           on_frame: Callable[[Pipeline, "FrameResult"], None] | None = None, sector_sink=None,
           landmark_sink=None) -> ReplaySummary:
    """Replay a recorded flight (see the module docstring).  ``config``: a CompanionConfig.

    ``fixed_processing_s`` replaces the measured processing time (a deterministic output);
    ``progress(done, total)`` is called after each frame; ``truth``: a flightsim ``truth.npz`` whose
    forward-sector distance is drawn on the plot; ``on_frame(pipeline, result)`` is called after each
    processed frame (benchmarks read the estimator's landmarks through it); ``sector_sink``: the
    reporter's (a :class:`companion.sector_log.SectorLog`: where each sector's claim came from);
    ``landmark_sink``: the pipeline's (a :class:`companion.landmark_log.LandmarkLog`: every landmark, frame by frame).
    """
    wall0 = time.perf_counter()
    cam = camera or config.camera
    out = Path(out)
    tel_log = read_telemetry_tlog(tlog, telemetry_latency_s, config.telemetry.reset_threshold_s)
    source = open_recording(video, frames_csv, cam)
    warnings = recording_warnings(tel_log, source, tlog, config.telemetry.max_age_s)
    for w in warnings:
        log.warning("%s", w)
    total = len(source)
    tel = TelemetryBuffer(config.telemetry)
    pipe = Pipeline(cam, config, pipeline, tel)
    pipe.landmark_sink = landmark_sink
    first_frame_t = float(source.t[0])
    rep = Reporter(config, pipeline, outputs=("autopilot",), start=first_frame_t, heartbeat=True, sector_sink=sector_sink)
    rep.vehicle_autopilot = tel_log.autopilot  # the recorded vehicle's: a PX4 flight is replayed with PX4's folding
    trace = _Trace()
    recs = tel_log.records
    ri = 0
    counts: collections.Counter[str] = collections.Counter()
    failed: collections.Counter[str] = collections.Counter()
    latencies: list[float] = []
    cpu: list[float] = []
    stage_cpu: collections.Counter[str] = collections.Counter()
    first_valid: float | None = None

    def feed(until: float) -> None:
        nonlocal ri
        while ri < len(recs) and recs[ri].t <= until:
            r = recs[ri]
            tel.set_clock_offset(tel_log.offset_at(r.t))
            if r.kind == "ATTITUDE":
                tel.add_attitude(r.time_boot_ms, *r.values)
            else:
                tel.add_local_position(r.time_boot_ms, *r.values)
            ri += 1

    def boot_ms(t: float) -> int:
        b = tel.to_boot(t)
        return int(round(b * 1000)) if b is not None and b >= 0 else 0

    def emit(t: float, msgs) -> None:
        nonlocal first_valid
        for _, m in msgs:
            writer.write(t, m)
            if m.get_type() == "OBSTACLE_DISTANCE":
                d = np.asarray(m.distances, dtype=np.int64)
                trace.t.append(t)
                trace.distances.append(d)
                if first_valid is None and np.any(d != 65535):
                    first_valid = t

    last_frame_at: float | None = None
    last_state = None

    def tick(now: float) -> None:
        nonlocal last_state
        feed(now)
        msgs = rep.tick(now, yaw_now=pipe.yaw_now(now), last_frame_at=last_frame_at,
                        telemetry_problem=pipe.telemetry_problem(now), time_boot_ms=boot_ms(now))
        emit(now, msgs)
        if rep.health.state != last_state:
            last_state = rep.health.state
            trace.states.append((now, last_state.value))

    def tick_until(now: float, until: float) -> float:
        t = now
        while t + tick_s <= until:
            t += tick_s
            tick(t)
        return t

    now = first_frame_t
    feed(now)
    nxt = source.read()
    done = 0
    staged = StagedFiles(out.parent, keep_partial=(out.name,))  # ranges.tlog appears complete or as ranges.tlog.partial
    writer = TlogOut(staged.path(out.name), tel_log.system_id, config.link.component_id)
    try:
        if nxt is None:
            raise ReplayError(_no_frames(video, source))
        while nxt is not None:
            if nxt.t > now:
                tick_until(now, nxt.t)
                now = nxt.t
            f, nxt = nxt, source.read()
            done += 1
            while nxt is not None and nxt.t <= now:  # the core was busy: only the newest waiting frame is taken
                counts["superseded"] += 1
                f, nxt = nxt, source.read()
                done += 1
            last_frame_at = f.t
            feed(now)
            if now - f.t > pipeline.max_frame_age_s:
                counts["stale"] += 1
                if progress:
                    progress(done, total)
                continue
            while pipe.readiness(f.t, now) == "wait":  # wait for the ATTITUDE that brackets the exposure
                limit = f.t + pipeline.telemetry_wait_s
                nt = recs[ri].t if ri < len(recs) else math.inf
                now = min(max(nt, now), limit) if nt > now else now
                feed(now)
                if now >= limit:
                    break
            res = pipe.process(f, now)
            if on_frame is not None:
                on_frame(pipe, res)
            dt = fixed_processing_s if fixed_processing_s is not None else res.processing_s
            t_send = now + dt
            feed(t_send)
            msgs = rep.on_result(res, t_send, yaw_now=pipe.yaw_now(t_send), last_frame_at=last_frame_at,
                                 telemetry_problem=pipe.telemetry_problem(t_send), time_boot_ms=boot_ms(t_send))
            emit(t_send, msgs)
            if res.ok:
                counts["processed"] += 1
                latencies.append(t_send - res.t_capture)
                cpu.append(res.cpu_s)
                stage_cpu.update(res.stage_cpu_s)
                s = res.sectors
                trace.fwd_t.append(t_send)
                trace.fwd_m.append(s.forward.distance_m if s.forward.state == 1 else math.nan)
                trace.fwd_sigma.append(s.forward.sigma_m)
                trace.near_t.append(t_send)
                trace.near_m.append(s.nearest_m)
            else:
                failed[res.reason] += 1
            if rep.health.state != last_state:
                last_state = rep.health.state
                trace.states.append((t_send, last_state.value))
            now = t_send
            tick(now)  # periodic duties (HEARTBEAT, diagnostics) also when frames arrive back to back
            if progress:
                progress(done, total)
        # let the last result age out like a camera that stopped: a final second of periodic duties
        tick_until(now, now + 1.0)
        writer.close()
        plot_path = None if plot is None else Path(plot)
        if plot_path is not None:
            plot_path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(plot_path) as tmp:
                plot_ranges(trace, tmp, config.sectors.max_distance_m, first_frame_t,
                            load_truth(truth) if truth is not None else None)
        staged.commit()
    except BaseException:
        writer.close()
        staged.abort()
        raise
    finally:
        source.close()
    st = source.status()
    lat = np.asarray(latencies) * 1000 if latencies else np.asarray([math.nan])
    summary = ReplaySummary(
        frames=done, processed=counts["processed"], failed=dict(failed), stale=counts["stale"],
        superseded=counts["superseded"], rejected=st.rejected, messages=dict(writer.counts),
        recording_s=float(source.t[min(done, len(source.t)) - 1] - first_frame_t) if done else 0.0,
        wall_s=time.perf_counter() - wall0, latency_p50_ms=float(np.percentile(lat, 50)),
        latency_p99_ms=float(np.percentile(lat, 99)), first_valid_s=None if first_valid is None else first_valid - first_frame_t,
        system_id=tel_log.system_id, out=out, plot=plot_path, warnings=warnings,
        cpu_ms_mean=float(np.mean(cpu)) * 1000 if cpu else math.nan,
        cpu_ms_p99=float(np.percentile(cpu, 99)) * 1000 if cpu else math.nan,
        stage_cpu_ms={k: v * 1000 / len(cpu) for k, v in stage_cpu.items()} if cpu else {},
    )
    return summary


def open_recording(video: str | Path, frames_csv: str | Path, cam: CameraConfig) -> RecordedSource:
    """The recorded frames, checked against the camera: a video of another size is a ConfigError
    (the intrinsics would not apply)."""
    source = RecordedSource(video, frames_csv, cam.width, cam.height)
    vw, vh = source.video_size
    if (vw, vh) != (cam.width, cam.height) and vw > 0:
        source.close()
        raise ConfigError(f"{video} is {vw}×{vh} but the [camera] table says {cam.width}×{cam.height}: give the camera "
                          "the video was recorded with (--config, --camera-config or --calibration)")
    return source


def recording_warnings(tel_log: TlogTelemetry, source: RecordedSource, tlog: str | Path, max_age_s: float) -> list[str]:
    """What is wrong with a recording that can still be replayed: a tlog cut while being written, or
    one whose telemetry ends (more than ``max_age_s``, the staleness limit) before the frames do."""
    warnings = [tel_log.truncation] if tel_log.truncation else []
    t_end = float(tel_log.records[-1].t)
    t0, t1 = float(source.t[0]), float(source.t[len(source) - 1])
    if t1 - t_end > max_age_s:
        warnings.append(f"{tlog}: the telemetry ends {t1 - t_end:.2f} s before the last frame ({max(t_end - t0, 0.0):.2f} s "
                        f"into {t1 - t0:.2f} s of video): the tlog looks cut mid-flight; frames after its end are "
                        "replayed without telemetry (their sectors are unknown)")
    return warnings


def _no_frames(video: str | Path, source: RecordedSource) -> str:
    """Why a recording gave no frame at all (its rejections by reason, if any)."""
    if source.size_error:
        return f"{video}: {source.size_error}"
    st = source.status()
    why = ", ".join(f"{k} {v}" for k, v in sorted(st.rejected.items()))
    return f"{video}: no frame could be read" + (f" (rejected: {why})" if why else "")


# ---------------------------------------------------------------------- plot -------------------
def load_truth(path: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """``(t_s, true forward-sector distance)`` from a flightsim ``truth.npz`` (None if unusable)."""
    try:
        with np.load(path) as z:
            t = np.asarray(z["t_s"], float)
            fwd = np.asarray(z["sector_m"], float)[:, 0]
        if t.ndim != 1 or fwd.shape != t.shape:
            raise ValueError("t_s / sector_m shapes do not match")
        return t, fwd
    except Exception as exc:  # an optional overlay: never fail the replay for it
        log.warning("%s: not used as truth (%s)", path, exc)
        return None


def plot_ranges(trace: _Trace, path: Path, max_distance_m: float, t0: float,
                truth: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """Sector ranges over time (top) and the forward / nearest range (bottom), PNG via matplotlib Agg.

    ``truth``: optional ``(t, true forward distance)`` on the recording clock (see :func:`load_truth`).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(11, 7.5), sharex=True, gridspec_kw={"height_ratios": [3, 2]})
    max_cm = int(round(max_distance_m * 100))
    if trace.t:
        t = np.asarray(trace.t) - t0
        d = np.stack(trace.distances).astype(float)  # (T, 72), bearings 0..355° clockwise from forward
        order = np.r_[36:72, 0:36]  # show −180° … +175°, forward in the middle
        img = d[:, order] / 100.0
        unknown = d[:, order] == 65535
        clear = d[:, order] == max_cm + 1
        data = np.ma.masked_array(np.where(unknown | clear, np.nan, img), mask=unknown | clear)
        edges = np.r_[t, t[-1] + (t[-1] - t[-2] if len(t) > 1 else 0.1)]
        bear = np.arange(-180, 181, 5) - 2.5
        cmap = matplotlib.colormaps["viridis"].copy()
        ax1.pcolormesh(edges, bear, np.ma.masked_array(np.where(clear, 1.0, np.nan), mask=~clear).T,
                       cmap=ListedColormap(["#b6e3b6"]), shading="flat")
        mesh = ax1.pcolormesh(edges, bear, data.T, cmap=cmap, vmin=0, vmax=max_distance_m, shading="flat")
        fig.colorbar(mesh, ax=(ax1, ax2), label="published range, m", shrink=0.6, anchor=(0.0, 1.0))
        ax1.set_ylim(-60, 60)
    ax1.set_ylabel("sector bearing, ° (+ right)")
    ax1.set_title("OBSTACLE_DISTANCE over time (white: unknown, pale green: clear)")
    if trace.fwd_t:
        ft = np.asarray(trace.fwd_t) - t0
        fm = np.asarray(trace.fwd_m)
        fs = np.asarray(trace.fwd_sigma)
        ax2.plot(ft, fm, ".", ms=3, label="forward (DISTANCE_SENSOR), conservative")
        ok = np.isfinite(fm) & np.isfinite(fs)
        if np.any(ok):
            ax2.fill_between(ft, np.where(ok, fm - fs, np.nan), np.where(ok, fm + fs, np.nan), alpha=0.25, label="± σ")
        ax2.plot(np.asarray(trace.near_t) - t0, trace.near_m, "-", lw=0.8, label="nearest sector")
    if truth is not None:
        tt, fwd = truth
        ax2.plot(tt - t0, np.where(np.isfinite(fwd), fwd, np.nan), "k-", lw=1.0, alpha=0.7, label="truth, forward sector")
    for ts, state in trace.states:
        ax2.axvline(ts - t0, color="0.7", lw=0.6)
        ax2.text(ts - t0, 1.0, state, transform=ax2.get_xaxis_transform(), rotation=90, va="top", fontsize=7, color="0.4")
    ax2.set_ylim(0, max_distance_m * 1.05)
    ax2.set_xlabel("time since the first frame, s (recording clock)")
    ax2.set_ylabel("range, m")
    ax2.legend(loc="upper right", fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------- recordings for tests ----
def write_recording(out_dir: str | Path, flight, duration_s: float, fps: float = 30.0, epoch_s: float = 1.7e9,
                    boot_s: float = 100.0, attitude_hz: float = 50.0, position_hz: float = 20.0, system_id: int = 1,
                    latency_s: float = 0.0) -> Path:
    """Write a recording in flightsim's export format from a :class:`bench.latency.SyntheticFlight`.

    ``telemetry.tlog`` (HEARTBEAT 1 Hz, ATTITUDE, LOCAL_POSITION_NED from system ``system_id``
    component 1; ``time_boot_ms`` = ``boot_s`` + flight time; record stamp = ``epoch_s`` + flight
    time + ``latency_s``), ``video.avi`` (MJPG) and ``frames.csv``.  For tests and examples.
    """
    import cv2

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cam = flight.camera
    mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=1)
    events = []
    n_att, n_pos, n_hb = int(duration_s * attitude_hz) + 1, int(duration_s * position_hz) + 1, int(duration_s) + 1
    for k in range(n_hb):
        events.append((k * 1.0, 0, mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                                     0, 0, mavlink.MAV_STATE_ACTIVE, 3)))
    for k in range(n_att):
        t = k / attitude_hz
        events.append((t + latency_s, 1, mavlink.MAVLink_attitude_message(int(round((boot_s + t) * 1000)), *flight.attitude_fields(t))))
    for k in range(n_pos):
        t = k / position_hz
        events.append((t + latency_s, 2, mavlink.MAVLink_local_position_ned_message(int(round((boot_s + t) * 1000)),
                                                                                     *flight.local_position_fields(t))))
    events.sort(key=lambda e: (e[0], e[1]))
    with (out / "telemetry.tlog").open("wb") as fh:
        for t, _, m in events:
            buf = m.pack(mav)
            mav.seq = (mav.seq + 1) % 256
            fh.write(struct.pack(">Q", int(round((epoch_s + t) * 1e6))) + bytes(buf))
    vw = cv2.VideoWriter(str(out / "video.avi"), cv2.VideoWriter_fourcc(*"MJPG"), fps, (cam.width, cam.height), isColor=False)
    rows = ["index,t_s"]
    for k in range(int(duration_s * fps) + 1):
        t = k / fps
        vw.write(flight.render(t))
        rows.append(f"{k},{epoch_s + t:.6f}")
    vw.release()
    (out / "frames.csv").write_text("\n".join(rows) + "\n")
    lines = ["# camera the frames were rendered with (companion.replay.write_recording)", "[camera]"]
    for f in dataclasses.fields(cam):
        v = getattr(cam, f.name)
        lines.append(f"{f.name} = " + ("[" + ", ".join(repr(float(x)) for x in v) + "]" if isinstance(v, tuple) else repr(v)))
    (out / "camera.toml").write_text("\n".join(lines) + "\n")
    return out


__all__ = ["replay", "ReplaySummary", "open_recording", "recording_warnings", "read_telemetry_tlog", "TlogTelemetry", "TelemetryRecord", "TlogOut",
           "plot_ranges", "load_truth", "write_recording", "ReplayError"]
