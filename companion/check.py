"""``companion check``: the pre-flight check — would ``companion run`` produce ranges with these settings?

It opens what ``companion run`` opens, with the companion's own code: the MAVLink link
(:class:`~companion.mavlink.link.MavLink`, which learns the vehicle, requests its telemetry streams
and runs TIMESYNC exactly as in flight) and the camera (:func:`~companion.camera_sources.open_source`,
frames stamped through the link's clock mapping), for at most ``timeout_s``, and judges:

========================= ============================================================================
check                     PASS when
========================= ============================================================================
``link``                  the connection (serial device, UDP/TCP socket) opened
``heartbeat``             a HEARTBEAT arrived from the autopilot component (``[link]
                          autopilot_component_id``) of a vehicle; WARN when it came as MAVLink 1
                          (OBSTACLE_DISTANCE needs MAVLink 2 on this port)
``ATTITUDE``,             arriving at ``[link] min_rate_fraction`` or more of the rate the link asks
``LOCAL_POSITION_NED``    for (``attitude_hz``, ``local_position_hz``), measured by the link's own
                          :class:`~companion.mavlink.streams.RateMeter` over a full ``rate_window_s``;
                          the pipeline needs both
``GLOBAL_POSITION_INT``   the same, but only WARN when it is missing: the ranges do not use it
``timesync``              the companion's :class:`~companion.mavlink.timesync.TimesyncEstimator` has
                          converged on TIMESYNC answers (not on the arrival-time fallback) and its
                          offset then moved by no more than ``[link.timesync] max_rtt_s`` over
                          1.5 × ``interval_s``
``camera``                frames of the configured width × height arrive for ``[link] rate_window_s``
                          at ``CAMERA_RATE_FRACTION`` of the expected frame rate or more (``--fps``,
                          else ``[camera_source] device_fps`` when set) and never further apart than
                          ``[pipeline] camera_timeout_s`` (beyond it the companion reports the camera
                          lost)
``calibration``           focal lengths give a horizontal field of view of 5–160° and a pixel aspect
                          within 20 % of square, the principal point lies inside the image, the
                          distortion coefficients are finite and the distortion is invertible over the
                          image (undistort → distort returns every pixel, the radial mapping never
                          folds back)
========================= ============================================================================

The check ends as soon as every live check has passed, else at the timeout, when what has not
passed fails.  Numbers are measured, never assumed: each line gives them (also in
:meth:`CheckReport.to_json`).  The evaluators (``evaluate_*``, :func:`check_calibration`) are pure;
:func:`run_check` is the thin I/O loop around them.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable

import numpy as np

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.camera_sources import FrameSource, SourceStatus, open_source
from companion.core.camera import CameraConfig, CameraModel
from companion.errors import ConfigError, InputError
from companion.mavlink.link import MavLink
from companion.telemetry import TelemetryBuffer

PASS, WARN, FAIL = "PASS", "WARN", "FAIL"

#: streams the ranges need: the pipeline takes the pose at each exposure from ATTITUDE and
#: LOCAL_POSITION_NED (TelemetryBuffer); GLOBAL_POSITION_INT is requested but only kept for reference
NEEDED_STREAMS = ("ATTITUDE", "LOCAL_POSITION_NED")
#: a camera delivering less than this fraction of its expected frame rate fails
CAMERA_RATE_FRACTION = 0.8
#: the pinhole model with OpenCV's radial-tangential distortion: a plausible horizontal field of view
MIN_HFOV_DEG, MAX_HFOV_DEG = 5.0, 160.0
#: |fy / fx − 1| beyond this: not square pixels, most likely a calibration of another resolution
MAX_ASPECT_DEVIATION = 0.2
#: undistort → distort must return every image pixel within this many pixels
MAX_ROUNDTRIP_PX = 0.5
#: the TIMESYNC estimate is watched this many request intervals after it converged
TIMESYNC_SETTLE_INTERVALS = 1.5

_STATE_TEXT = {
    "ok": "SET_MESSAGE_INTERVAL accepted",
    "wait_rate": "SET_MESSAGE_INTERVAL accepted, rate being measured",
    "wait_ack": "SET_MESSAGE_INTERVAL sent, no COMMAND_ACK yet",
    "fallback": "SET_MESSAGE_INTERVAL failed, asked with REQUEST_DATA_STREAM",
    "idle": "not requested yet",
}


# ---------------------------------------------------------------------- results ------------------
@dataclasses.dataclass(frozen=True)
class CheckResult:
    """One line of the check: what, PASS / WARN / FAIL, why (with the measured numbers)."""

    name: str
    status: str
    detail: str
    values: dict[str, Any] = dataclasses.field(default_factory=dict)

    def line(self) -> str:
        """``PASS  heartbeat            vehicle system 1: …``"""
        return f"{self.status:<4}  {self.name:<20} {self.detail}"

    def to_json(self) -> dict:
        return {"name": self.name, "status": self.status, "detail": self.detail, "values": _jsonable(self.values)}


@dataclasses.dataclass(frozen=True)
class CheckReport:
    """Every check's result; :attr:`exit_code` 0 when nothing failed (WARN passes), else 1."""

    results: tuple[CheckResult, ...]
    elapsed_s: float
    timeout_s: float

    @property
    def failed(self) -> list[CheckResult]:
        return [r for r in self.results if r.status == FAIL]

    @property
    def ok(self) -> bool:
        return not self.failed

    @property
    def exit_code(self) -> int:
        return 0 if self.ok else 1

    def summary(self) -> str:
        """The last line of the text output."""
        if self.ok:
            warned = [r.name for r in self.results if r.status == WARN]
            extra = f" ({len(warned)} warning{'s' if len(warned) != 1 else ''}: {', '.join(warned)})" if warned else ""
            return (f"companion check: all {len(self.results)} checks passed in {self.elapsed_s:.1f} s{extra}: "
                    "the companion would produce ranges")
        names = ", ".join(r.name for r in self.failed)
        return (f"companion check: {len(self.failed)} of {len(self.results)} checks failed ({names}) within "
                f"{self.timeout_s:g} s: the companion would not produce ranges")

    def text(self) -> str:
        return "\n".join([r.line() for r in self.results] + [self.summary()])

    def to_json(self) -> dict:
        return {"ok": self.ok, "exit_code": self.exit_code, "elapsed_s": round(self.elapsed_s, 3),
                "timeout_s": self.timeout_s, "checks": [r.to_json() for r in self.results]}


def _jsonable(v):
    """Floats rounded and non-finite ones as None, so the JSON is strict."""
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return round(float(v), 6) if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


# ---------------------------------------------------------------------- calibration (pure) -------
def _vfov_rad(cam: CameraConfig) -> float:
    """Vertical field of view of the undistorted pinhole (the vertical twin of ``hfov_rad``)."""
    return math.atan((cam.height - 1 - cam.cy + 0.5) / cam.fy) + math.atan((cam.cy + 0.5) / cam.fy)


def _distortion_fold(model: CameraModel, cam: CameraConfig, xy_corners: np.ndarray) -> bool:
    """True when the distorted radius stops growing somewhere between the centre and a corner's ray
    (the distortion folds the image back on itself: no unique undistortion)."""
    s = np.linspace(0.0, 1.0, 200)[1:]
    centre = np.array([cam.cx, cam.cy])
    for xy in xy_corners:
        uv = model.normalized_to_pixels(s[:, None] * xy[None, :])
        r = np.linalg.norm(uv - centre, axis=1)
        if not np.all(np.isfinite(r)) or np.any(np.diff(r) <= 0):
            return True
    return False


def distortion_roundtrip(cam: CameraConfig) -> tuple[float, bool]:
    """(largest undistort → distort error over a grid of the image in px, folds) with the companion's
    :class:`CameraModel` (``cv2.undistortPoints`` one way, its own distortion the other)."""
    model = CameraModel(cam)
    us = np.linspace(0.0, cam.width - 1.0, 9)
    vs = np.linspace(0.0, cam.height - 1.0, 7)
    uv = np.stack(np.meshgrid(us, vs), -1).reshape(-1, 2)
    try:
        xy = model.pixels_to_normalized(uv)
        back = model.normalized_to_pixels(xy)
    except (InputError, ValueError):
        return math.inf, True
    err = np.linalg.norm(back - uv, axis=1)
    worst = float(np.max(err)) if np.all(np.isfinite(err)) else math.inf
    corners = np.array([[0.0, 0.0], [cam.width - 1.0, 0.0], [0.0, cam.height - 1.0], [cam.width - 1.0, cam.height - 1.0]])
    xy_corners = model.pixels_to_normalized(corners)
    if not np.all(np.isfinite(xy_corners)):
        return worst, True
    return worst, _distortion_fold(model, cam, xy_corners)


def check_calibration(cam: CameraConfig) -> CheckResult:
    """Focal lengths, principal point and distortion of ``cam`` against its image size (pure)."""
    w, h = cam.width, cam.height
    problems = []
    hfov = math.degrees(cam.hfov_rad)
    vfov = math.degrees(_vfov_rad(cam))
    aspect = cam.fy / cam.fx
    inside = 0.0 <= cam.cx <= w - 1 and 0.0 <= cam.cy <= h - 1
    if not inside:
        problems.append(f"principal point ({cam.cx:g}, {cam.cy:g}) outside the {w}×{h} image")
    elif not MIN_HFOV_DEG <= hfov <= MAX_HFOV_DEG:
        problems.append(f"fx {cam.fx:g} px gives a {hfov:.1f}° horizontal field of view at {w} px "
                        f"(plausible: {MIN_HFOV_DEG:g}–{MAX_HFOV_DEG:g}°; calibrated at another resolution?)")
    if abs(aspect - 1.0) > MAX_ASPECT_DEVIATION:
        problems.append(f"fy/fx = {aspect:.2f} (pixels within {100 * MAX_ASPECT_DEVIATION:.0f} % of square expected)")
    finite = all(math.isfinite(c) for c in cam.distortion)
    roundtrip, folds = distortion_roundtrip(cam) if finite and inside else (math.nan, False)
    if not finite:
        problems.append("distortion coefficients not finite")
    elif inside and (folds or not roundtrip <= MAX_ROUNDTRIP_PX):
        problems.append(f"distortion {list(cam.distortion)} is not invertible over the image ("
                        + ("the radial mapping folds back" if folds else f"undistort → distort off by {roundtrip:.2f} px")
                        + f", limit {MAX_ROUNDTRIP_PX:g} px)")
    values = {"width": w, "height": h, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
              "hfov_deg": hfov, "vfov_deg": vfov, "aspect_fy_fx": aspect, "distortion": list(cam.distortion),
              "roundtrip_px": roundtrip, "folds": folds}
    if problems:
        return CheckResult("calibration", FAIL, "; ".join(problems), values)
    dist = "none" if not cam.has_distortion else f"{[round(c, 4) for c in cam.distortion]}"
    return CheckResult("calibration", PASS,
                       f"{w}×{h}, fx {cam.fx:.1f} fy {cam.fy:.1f} px ({hfov:.1f}° × {vfov:.1f}° field of view), principal "
                       f"point ({cam.cx:.1f}, {cam.cy:.1f}) {cam.cx - (w - 1) / 2:+.1f}/{cam.cy - (h - 1) / 2:+.1f} px from "
                       f"the centre, distortion {dist} (round trip {roundtrip:.3f} px)", values)


# ---------------------------------------------------------------------- live checks (pure) -------
def evaluate_link(conn: str, is_open: bool, opened_after_s: float | None, open_error: str, attempts: int,
                  final: bool) -> CheckResult | None:
    """The connection opened (None: not yet, and not final)."""
    values = {"connection": conn, "opened_after_s": opened_after_s, "open_failures": attempts}
    if opened_after_s is not None:
        return CheckResult("link", PASS, f"{conn} open" + (f" after {opened_after_s:.1f} s" if opened_after_s > 0.05 else ""),
                           values)
    if not final:
        return None
    why = open_error or "not open"
    return CheckResult("link", FAIL, f"cannot open {conn}: {why} ({attempts} attempt{'s' if attempts != 1 else ''})", values)


def _enum_name(enum: str, value: int) -> str:
    entry = mavlink.enums.get(enum, {}).get(value)
    return entry.name if entry is not None else f"{enum} {value}"


def evaluate_heartbeat(heartbeat, system_id: int | None, first_s: float | None, waited_s: float, counters: dict,
                       autopilot_component: int, final: bool, connected: bool = True,
                       silent_s: float = 0.0) -> CheckResult | None:
    """A vehicle HEARTBEAT from the autopilot component arrived (``heartbeat``: the newest) and the link
    still counts as connected (``silent_s``: seconds since the newest)."""
    if heartbeat is not None and first_s is not None and not connected:
        if not final:
            return None
        return CheckResult("heartbeat", FAIL, f"vehicle system {system_id} heard first after {first_s:.2f} s, then silent "
                           f"for {silent_s:.1f} s: link lost", {"system_id": system_id, "first_after_s": first_s,
                                                                "silent_s": silent_s})
    if heartbeat is not None and first_s is not None:
        v1 = bytes(heartbeat.get_msgbuf()[:1]) == bytes([mavlink.PROTOCOL_MARKER_V1])
        values = {"system_id": system_id, "component_id": heartbeat.get_srcComponent(),
                  "type": _enum_name("MAV_TYPE", heartbeat.type), "autopilot": _enum_name("MAV_AUTOPILOT", heartbeat.autopilot),
                  "mavlink_version": 1 if v1 else 2, "first_after_s": first_s}
        text = (f"vehicle system {system_id} component {values['component_id']}: {values['type']}, {values['autopilot']}, "
                f"MAVLink {values['mavlink_version']}, first after {first_s:.2f} s")
        if v1:
            return CheckResult("heartbeat", WARN, text + "; the autopilot sends MAVLink 1 on this port: OBSTACLE_DISTANCE "
                               "needs MAVLink 2 (ArduPilot: SERIALn_PROTOCOL = 2)", values)
        return CheckResult("heartbeat", PASS, text, values)
    if not final:
        return None
    heard = []
    if counters.get("rx_messages", 0):
        heard.append(f"{counters['rx_messages']} messages received")
    for key, what in (("rx_heartbeat_other", "HEARTBEATs of other components (not an autopilot component "
                                              f"{autopilot_component} of a vehicle)"),
                      ("rx_heartbeat_other_vehicle", "HEARTBEATs of another vehicle"),
                      ("rx_signing_rejected", "packets refused by signing"),
                      ("rx_bad_crc", "packets with a bad CRC (wrong baud rate or dialect?)"),
                      ("rx_bad_data", "unparsable packets"), ("rx_bad_prefix", "bytes that are not MAVLink (wrong baud rate?)")):
        if counters.get(key, 0):
            heard.append(f"{counters[key]} {what}")
    values = {"waited_s": waited_s, **{k: counters.get(k, 0) for k in ("rx_messages", "rx_heartbeat_other", "rx_bytes")}}
    return CheckResult("heartbeat", FAIL, f"no HEARTBEAT from an autopilot (component {autopilot_component}) in "
                       f"{waited_s:.1f} s; " + ("; ".join(heard) if heard else "nothing received at all"), values)


def evaluate_stream(name: str, requested_hz: float, rate_hz: float, arriving_s: float, window_s: float,
                    min_fraction: float, state: str, needed: bool, vehicle_known: bool, final: bool) -> CheckResult | None:
    """A telemetry stream arrives at ``min_fraction`` of its requested rate or more, measured over a full
    ``window_s`` (``arriving_s``: how long it has been arriving)."""
    need = min_fraction * requested_hz
    how = _STATE_TEXT.get(state, state)
    values = {"rate_hz": rate_hz, "requested_hz": requested_hz, "needed_hz": need, "request_state": state,
              "needed_for_ranges": needed, "measured_over_s": min(arriving_s, window_s)}
    head = f"{rate_hz:.1f} Hz (requested {requested_hz:g} Hz, needs >= {need:g} Hz; {how})"
    if arriving_s >= window_s and rate_hz >= need:
        return CheckResult(name, PASS, head, values)
    if not final:
        return None
    if not vehicle_known:
        detail = f"not requested: no vehicle heard (requested rate {requested_hz:g} Hz)"
    elif rate_hz == 0:
        detail = f"none received (requested {requested_hz:g} Hz; {how})"
    elif arriving_s < window_s:
        detail = f"{rate_hz:.1f} Hz, arriving for only {arriving_s:.1f} of the {window_s:g} s it is measured over " \
                 f"(requested {requested_hz:g} Hz; {how})"
    else:
        detail = f"{rate_hz:.1f} Hz, too slow: " + head.split(" (", 1)[1].rstrip(")")
    if not needed:
        return CheckResult(name, WARN, detail + "; not needed for the ranges", values)
    return CheckResult(name, FAIL, detail, values)


def evaluate_timesync(converged: bool, source: str | None, offset_s: float | None, converged_for_s: float,
                      offset_spread_s: float, counters: dict, best_rtt_s: float, last_rtt_s: float,
                      max_rtt_s: float, settle_s: float, final: bool) -> CheckResult | None:
    """TIMESYNC converged and its offset held within ``max_rtt_s`` for ``settle_s``."""
    req, acc = counters.get("requests", 0), counters.get("accepted", 0)
    values = {"converged": converged, "source": source, "offset_s": offset_s, "best_rtt_ms": 1000 * best_rtt_s,
              "requests": req, "accepted": acc, "rejected_rtt": counters.get("rejected_rtt", 0),
              "converged_for_s": converged_for_s, "offset_spread_ms": 1000 * offset_spread_s, "limit_ms": 1000 * max_rtt_s}
    stable = offset_spread_s <= max_rtt_s
    if converged and converged_for_s >= settle_s and stable:
        return CheckResult("timesync", PASS,
                           f"converged: offset {offset_s:+.6f} s (companion − autopilot), best round trip "
                           f"{1000 * best_rtt_s:.1f} ms, {acc} of {req} answers accepted; moved {1000 * offset_spread_s:.2f} ms "
                           f"over {converged_for_s:.1f} s (limit {1000 * max_rtt_s:g} ms)", values)
    if not final:
        return None
    fallback = " (the companion would map the clocks from message arrival times only)" if source == "arrival" else ""
    if converged and not stable:
        detail = (f"offset not stable: moved {1000 * offset_spread_s:.1f} ms in {converged_for_s:.1f} s after converging "
                  f"(limit {1000 * max_rtt_s:g} ms)")
    elif converged:
        detail = f"converged only {converged_for_s:.1f} s before the timeout (watched for {settle_s:.1f} s)"
    elif req == 0:
        detail = "no TIMESYNC request sent: no vehicle heard"
    elif counters.get("rejected_rtt", 0):
        detail = (f"{counters['rejected_rtt']} of {req} answers rejected: round trip {1000 * last_rtt_s:.0f} ms > "
                  f"max_rtt_s {1000 * max_rtt_s:g} ms{fallback}")
    elif acc == 0:
        detail = f"no answer to {req} TIMESYNC requests{fallback}"
    else:
        detail = f"{acc} of {req} answers accepted, not converged yet{fallback}"
    return CheckResult("timesync", FAIL, detail, values)


def evaluate_camera(spec: str, width: int, height: int, status: SourceStatus, fps: float, measured_s: float,
                    max_gap_s: float, last_age_s: float, expected_fps: float, window_s: float, timeout_s: float,
                    final: bool) -> CheckResult | None:
    """Frames of ``width × height`` arrive fast enough and without a gap the companion calls camera lost."""
    need = max(CAMERA_RATE_FRACTION * expected_fps, 1.0 / timeout_s)
    values = {"source": spec, "width": width, "height": height, "frames": status.frames, "fps": fps,
              "expected_fps": expected_fps or None, "needed_fps": need, "max_gap_s": max_gap_s, "gap_limit_s": timeout_s,
              "measured_over_s": measured_s, "rejected": dict(status.rejected), "dropped": status.dropped,
              "error": status.error}
    rej = ", ".join(f"{k} {v}" for k, v in sorted(status.rejected.items()))
    rate_text = f"needs >= {need:.1f} fps" + (f", expected {expected_fps:g}" if expected_fps else "")
    ok = measured_s >= window_s and fps >= need and max_gap_s <= timeout_s and last_age_s <= timeout_s
    if ok:
        return CheckResult("camera", PASS,
                           f"{spec}: {width}×{height} at {fps:.1f} fps ({rate_text}), longest gap {max_gap_s:.3f} s "
                           f"(limit {timeout_s:g} s), {status.frames} frames" + (f"; rejected: {rej}" if rej else ""), values)
    if not final:
        return None
    if status.frames == 0:
        if status.rejected:
            why = f"no usable frame: rejected {rej}" + (f" ({status.error})" if status.error else "")
            if "no_clock" in status.rejected:
                why += "; frames stamped on the autopilot's clock need its telemetry and TIMESYNC"
            if "wrong_size" in status.rejected:
                why += "; [camera] width × height (or the calibration's image_width / image_height) must match the camera"
        else:
            why = "no frame received" + (f": {status.error}" if status.error else "")
        detail = f"{spec}: {why}"
    elif measured_s < window_s:
        detail = f"{spec}: frames for only {measured_s:.1f} of the {window_s:g} s measured ({status.frames} frames)"
    elif last_age_s > timeout_s:
        detail = f"{spec}: frames stopped {last_age_s:.1f} s ago (camera_timeout_s {timeout_s:g} s)"
    elif fps < need:
        detail = f"{spec}: {fps:.1f} fps, too slow ({rate_text})"
    else:
        detail = f"{spec}: a gap of {max_gap_s:.2f} s between frames (camera_timeout_s {timeout_s:g} s: the companion " \
                 "would report the camera lost)"
    if status.frames and rej:
        detail += f"; rejected: {rej}"
    return CheckResult("camera", FAIL, detail, values)


# ---------------------------------------------------------------------- the live session (I/O) ---
class _Session:
    """The link and the camera opened as ``companion run`` opens them, and what the check tracks about them."""

    def __init__(self, conn: str, camera: str, config, clock: Callable[[], float], expected_fps: float,
                 link_factory: Callable[..., MavLink], source_factory: Callable[..., FrameSource]):
        self.conn, self.camera, self.config, self.clock = conn, camera, config, clock
        self.expected_fps = expected_fps
        self.t0 = clock()
        self.link = link_factory(conn, config.link, clock=clock, telemetry=TelemetryBuffer(config.telemetry))
        cam = config.camera
        try:
            self.source = source_factory(camera, cam.width, cam.height, config.camera_source, clock=clock,
                                         clock_map=self.link.telemetry.to_companion)
        except BaseException:
            self.link.close()
            raise
        self.opened_at: float | None = None
        self.heartbeat_at: float | None = None
        self.stream_since: dict[str, float] = {}
        self.ts_since: float | None = None
        self.ts_resets = 0
        self.ts_lo = self.ts_hi = math.nan
        self.cam_first: tuple[int, float] | None = None  # (good frames, stamp of the newest) when first seen
        self.last_frame_t: float | None = None
        self.max_gap = 0.0

    def close(self) -> None:
        for thing in (self.source, self.link):
            try:
                thing.close()
            except Exception:  # closing is best effort
                pass

    def step(self, poll_s: float) -> float:
        """Poll the link, take a frame, update what is tracked; returns the time (check clock)."""
        self.link.poll()
        frame = self.source.read(timeout=poll_s)
        now = self.clock()
        if frame is not None:
            if self.last_frame_t is not None:
                self.max_gap = max(self.max_gap, frame.t - self.last_frame_t)
            self.last_frame_t = frame.t
            self.source.done(frame, "dropped")  # looked at, not processed (a lockstep simulator may go on)
        self._track(now)
        return now

    def _track(self, now: float) -> None:
        link = self.link
        if self.opened_at is None and link.is_open:
            self.opened_at = now
        if self.heartbeat_at is None and link.vehicle_heartbeat is not None:
            self.heartbeat_at = now
        for name, rate in link.rates().items():
            if rate > 0:
                self.stream_since.setdefault(name, now)
            else:
                self.stream_since.pop(name, None)
        ts = link.timesync
        if ts.counters.get("resets", 0) != self.ts_resets:  # an autopilot reboot or an offset jump: watch anew
            self.ts_resets = ts.counters.get("resets", 0)
            self.ts_since = None
        if ts.converged:
            off = ts.offset_s
            if self.ts_since is None:
                self.ts_since, self.ts_lo, self.ts_hi = now, off, off
            self.ts_lo, self.ts_hi = min(self.ts_lo, off), max(self.ts_hi, off)
        else:
            self.ts_since = None
        st = self.source.status()
        if self.cam_first is None and st.frames > 0 and st.last_frame_t is not None:
            self.cam_first = (st.frames, st.last_frame_t)

    def evaluate(self, now: float, final: bool) -> list[CheckResult | None]:
        """Every live check at ``now`` (None: undecided and not final)."""
        link, cfg = self.link, self.config
        waited = now - self.t0
        out = [evaluate_link(self.conn, link.is_open, None if self.opened_at is None else self.opened_at - self.t0,
                             link.open_error, link.counters.get("open_failures", 0),
                             final),
               evaluate_heartbeat(link.vehicle_heartbeat, link.system_id,
                                  None if self.heartbeat_at is None else self.heartbeat_at - self.t0, waited,
                                  dict(link.counters), cfg.link.autopilot_component_id, final, link.connected,
                                  link.status().heartbeat_age_s)]
        rates = link.rates()
        for spec in link.streams.specs():
            since = self.stream_since.get(spec.name)
            out.append(evaluate_stream(spec.name, spec.rate_hz, rates.get(spec.name, 0.0), 0.0 if since is None else now - since,
                                       cfg.link.rate_window_s, cfg.link.min_rate_fraction, link.streams.state(spec.name).value,
                                       spec.name in NEEDED_STREAMS, link.system_id is not None, final))
        ts, tcfg = link.timesync, cfg.link.timesync
        out.append(evaluate_timesync(ts.converged, ts.source, ts.offset_s, 0.0 if self.ts_since is None else now - self.ts_since,
                                     0.0 if self.ts_since is None else self.ts_hi - self.ts_lo, dict(ts.counters),
                                     ts.best_rtt_s, ts.last_rtt_s, tcfg.max_rtt_s, TIMESYNC_SETTLE_INTERVALS * tcfg.interval_s,
                                     final))
        out.append(self._camera(now, final))
        return out

    def _camera(self, now: float, final: bool) -> CheckResult | None:
        st = self.source.status()
        fps = measured = 0.0
        if self.cam_first is not None and st.last_frame_t is not None:
            n0, t0 = self.cam_first
            measured = st.last_frame_t - t0
            fps = (st.frames - n0) / measured if measured > 0 else 0.0
        age = now - st.last_frame_t if st.last_frame_t is not None else math.inf
        cam = self.config.camera
        return evaluate_camera(self.camera, cam.width, cam.height, st, fps, measured, self.max_gap, age, self.expected_fps,
                               self.config.link.rate_window_s, self.config.pipeline.camera_timeout_s, final)


def run_check(conn: str, camera: str, config, *, timeout_s: float = 8.0, expected_fps: float = 0.0,
              clock: Callable[[], float] = time.monotonic, poll_s: float = 0.01,
              link_factory: Callable[..., MavLink] = MavLink,
              source_factory: Callable[..., FrameSource] = open_source) -> CheckReport:
    """Run every check (see the module docstring) for at most ``timeout_s``.

    ``config`` is a :class:`~companion.io.config_files.CompanionConfig` (its camera already replaced by
    a calibration / camera TOML, as ``companion run`` does).  Bad connection strings and camera
    specifications raise :class:`~companion.errors.ConfigError` (usage), as in ``companion run``.
    """
    if not (math.isfinite(timeout_s) and timeout_s > 0):
        raise ConfigError(f"--timeout must be a positive number of seconds, got {timeout_s}")
    calibration = check_calibration(config.camera)
    session = _Session(conn, camera, config, clock, expected_fps, link_factory, source_factory)
    try:
        deadline = session.t0 + timeout_s
        now = session.t0
        while now < deadline:
            now = session.step(poll_s)
            if all(r is not None for r in session.evaluate(now, final=False)):
                break
        results = [r for r in session.evaluate(now, final=True) if r is not None]
    finally:
        session.close()
    return CheckReport(tuple(results) + (calibration,), now - session.t0, timeout_s)


__all__ = [
    "PASS", "WARN", "FAIL", "CheckResult", "CheckReport", "check_calibration", "distortion_roundtrip",
    "evaluate_link", "evaluate_heartbeat", "evaluate_stream", "evaluate_timesync", "evaluate_camera", "run_check",
    "NEEDED_STREAMS", "CAMERA_RATE_FRACTION",
]
