"""Encoders for every message the companion sends, with each field set per docs/derivations/link.md (the sectors: sectors.md).

Each function returns a pymavlink message object (ardupilotmega dialect, MAVLink 2) that
:meth:`companion.mavlink.link.MavLink.send` packs with the companion's system / component ids.
Arguments are validated; a programming error (wrong array length, a name over 10 characters)
raises :class:`MessageError`, while *data* outside what a field can hold is saturated in the
safe direction and logged, never sent as a value that means something else.

* OBSTACLE_DISTANCE (330): 72 × uint16 cm clockwise from forward; ``increment = 5`` and
  ``increment_f = 5.0`` (Mission Planner reads the integer, ArduPilot the float), ``angle_offset
  = 0``, ``frame = MAV_FRAME_BODY_FRD`` (an unset frame decodes as GLOBAL); UINT16_MAX = unknown,
  ``max_distance + 1`` = clear, values in between that would read as "clear" are replaced by
  UINT16_MAX.
* DISTANCE_SENSOR (132): forward (MAV_SENSOR_ROTATION_NONE), ``covariance`` = variance in cm²
  (uint8: 255 = unknown, also used when the variance does not fit, since 254 cm² would claim a
  precision of 16 cm we do not have), ``signal_quality`` 1 = invalid, 2…100 from σ / range.
* OBSTACLE_DISTANCE_3D (11037): one obstacle, metres, MAV_FRAME_BODY_FRD.  ArduPilot starts a new
  obstacle set whenever ``time_boot_ms`` changes: send one batch with one stamp, back to back.
* NAMED_VALUE_FLOAT (251): name ≤ 10 ASCII characters.
* STATUSTEXT (253): ≤ 50 characters per message; longer text is chunked with a non-zero ``id``
  and ``chunk_seq`` 0, 1, …; a final chunk of exactly 50 characters is followed by an empty one
  (a NUL marks the end).
* HEARTBEAT (0): MAV_TYPE_ONBOARD_CONTROLLER (18), MAV_AUTOPILOT_INVALID (8), ``system_status``
  ACTIVE only while valid ranges are produced (decided by the caller).

:class:`RateLimiter` and :class:`OutputSchedule` keep each output at its own rate (docs/derivations/link.md: a
57600-baud radio cannot carry OBSTACLE_DISTANCE at 10 Hz next to everything else).
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from companion.mavlink.dialect import UINT16_MAX, mavlink  # first: MAVLink 2 + ardupilotmega
from companion.config import require, require_finite
from companion.core.sectors import SECTOR_DEG, SectorState
from companion.errors import InputError

log = logging.getLogger(__name__)

OBSTACLE_SECTORS = 72
INCREMENT_DEG = 5
UINT8_MAX = 255
STATUSTEXT_LEN = 50
NAMED_VALUE_LEN = 10


class MessageError(InputError):
    """An encoder was called with arguments no message can carry (a programming error)."""


@dataclasses.dataclass(frozen=True)
class OutputConfig:
    """The ``[outputs]`` table: what is sent where, how often."""

    autopilot_obstacle_distance_hz: float = 15.0  # OBSTACLE_DISTANCE to the autopilot, Hz (10–20: both autopilots drop data older than 0.5 s)
    autopilot_distance_sensor_hz: float = 15.0  # forward DISTANCE_SENSOR to the autopilot, Hz (0 = off); only when it agrees with OBSTACLE_DISTANCE about what lies ahead (Reporter._forward_consistent)
    autopilot_obstacle_3d_hz: float = 0.0  # OBSTACLE_DISTANCE_3D batches to the autopilot, Hz (0 = off: ArduPilot's 3-D messages reset the boundary OBSTACLE_DISTANCE fills)
    gcs_obstacle_distance_hz: float = 2.0  # OBSTACLE_DISTANCE to the ground-station output, Hz (a 57600-baud radio)
    gcs_distance_sensor_hz: float = 2.0  # forward DISTANCE_SENSOR to the ground station (QGroundControl's proximity radar), Hz
    gcs_obstacle_3d_hz: float = 0.0  # OBSTACLE_DISTANCE_3D batches to the ground station, Hz (0 = off)
    named_value_hz: float = 1.0  # NAMED_VALUE_FLOAT diagnostics (fps, tracks, nearest range) to each output, Hz (<= 1)
    sensor_type: int = 4  # MAV_DISTANCE_SENSOR of the messages: 4 = UNKNOWN (MAVLink has no camera type)
    distance_sensor_id: int = 0  # DISTANCE_SENSOR "id" field (distinguishes it from other rangefinders)
    quality_zero_rel_sigma: float = 0.5  # DISTANCE_SENSOR signal_quality falls to its minimum when σ / range reaches this
    distance_sensor_face_rel_tol: float = 0.1  # a forward DISTANCE_SENSOR obstacle goes to the autopilot only when it lies no farther than this fraction beyond the nearest obstacle OBSTACLE_DISTANCE reports within ±22.5° (ArduPilot's front face takes its value)
    px4_bin_fold: str = "auto"  # OBSTACLE_DISTANCE to the autopilot: each element PX4 reads (one per 10° bin, the even ones) that makes a claim carries the nearest obstacle of the bin (unknown stays unknown): "auto" = when the vehicle's HEARTBEAT says PX4, "on", "off"

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if f.name.endswith("_hz"):
                require_finite(f.name, getattr(self, f.name), nonnegative=True)
        require(self.named_value_hz <= 1.0, f"named_value_hz must be <= 1, got {self.named_value_hz}")
        require(isinstance(self.sensor_type, int) and 0 <= self.sensor_type <= 255, f"sensor_type must be a uint8, got {self.sensor_type!r}")
        require(isinstance(self.distance_sensor_id, int) and 0 <= self.distance_sensor_id <= 255,
                f"distance_sensor_id must be a uint8, got {self.distance_sensor_id!r}")
        require_finite("quality_zero_rel_sigma", self.quality_zero_rel_sigma, positive=True)
        require_finite("distance_sensor_face_rel_tol", self.distance_sensor_face_rel_tol, nonnegative=True)
        require(self.px4_bin_fold in ("auto", "on", "off"), f"px4_bin_fold must be \"auto\", \"on\" or \"off\", got {self.px4_bin_fold!r}")


# ---------------------------------------------------------------------- rate limiting ----------
class RateLimiter:
    """At most ``rate_hz`` events per second on the caller's clock (0 = never, inf = always).

    ``ready(now)`` consumes a slot.  Slots lie on a fixed grid of the nominal period and a call up
    to 10 % of a period early still takes the next slot, so a 10 Hz output lands on every third
    frame of a jittery 30 fps camera (instead of slipping to every fourth) while the long-run rate
    never exceeds ``rate_hz``.  After a pause the grid restarts (no burst of catch-up sends).
    """

    TOLERANCE = 0.1

    def __init__(self, rate_hz: float):
        if not (isinstance(rate_hz, (int, float)) and not isinstance(rate_hz, bool) and rate_hz >= 0 and not math.isnan(rate_hz)):
            raise MessageError(f"rate_hz must be a number >= 0, got {rate_hz!r}")
        self.rate_hz = float(rate_hz)
        self.period = math.inf if rate_hz == 0 else 1.0 / rate_hz
        self._next: float | None = None
        self._last: float | None = None

    def ready(self, now: float) -> bool:
        if self.rate_hz == 0:
            return False
        early = self.TOLERANCE * self.period
        if self._next is None or (self._last is not None and now < self._last):  # first call, or clock went back
            self._next = now
        if now < self._next - early:
            return False
        self._last = now
        self._next = max(self._next + self.period, now + self.period - early)
        return True

    def reset(self) -> None:
        self._next = None
        self._last = None


class OutputSchedule:
    """One :class:`RateLimiter` per (output, message kind) from :class:`OutputConfig`.

    Outputs are ``"autopilot"`` and ``"gcs"``; kinds ``"obstacle_distance"``,
    ``"distance_sensor"``, ``"obstacle_3d"``, ``"named_value"``.
    """

    def __init__(self, config: OutputConfig = OutputConfig()):
        c = config
        self._limiters = {
            ("autopilot", "obstacle_distance"): RateLimiter(c.autopilot_obstacle_distance_hz),
            ("autopilot", "distance_sensor"): RateLimiter(c.autopilot_distance_sensor_hz),
            ("autopilot", "obstacle_3d"): RateLimiter(c.autopilot_obstacle_3d_hz),
            ("autopilot", "named_value"): RateLimiter(c.named_value_hz),
            ("gcs", "obstacle_distance"): RateLimiter(c.gcs_obstacle_distance_hz),
            ("gcs", "distance_sensor"): RateLimiter(c.gcs_distance_sensor_hz),
            ("gcs", "obstacle_3d"): RateLimiter(c.gcs_obstacle_3d_hz),
            ("gcs", "named_value"): RateLimiter(c.named_value_hz),
        }

    def due(self, output: str, kind: str, now: float) -> bool:
        try:
            return self._limiters[(output, kind)].ready(now)
        except KeyError:
            raise MessageError(f"unknown output/kind {output!r}/{kind!r}") from None


# ---------------------------------------------------------------------- helpers ----------------
def _uint(name: str, value, bits: int) -> int:
    try:
        v = int(value)
    except (TypeError, ValueError, OverflowError):
        raise MessageError(f"{name} must be an integer, got {value!r}") from None
    if not 0 <= v < (1 << bits):
        raise MessageError(f"{name} = {v} does not fit uint{bits}")
    return v


def _ascii(text: str) -> bytes:
    return str(text).encode("ascii", errors="replace")


def _time_boot_ms(value) -> int:
    # wraps like the autopilot's own counter (2^32 ms = 49.7 days)
    try:
        v = int(value)
    except (TypeError, ValueError, OverflowError):
        raise MessageError(f"time_boot_ms must be an integer, got {value!r}") from None
    return v % (1 << 32) if v >= 0 else 0


# ---------------------------------------------------------------------- encoders ---------------
def obstacle_distance(distances_cm, min_distance_cm: int, max_distance_cm: int, time_usec: int = 0,
                      sensor_type: int = mavlink.MAV_DISTANCE_SENSOR_UNKNOWN):
    """OBSTACLE_DISTANCE with the 72 sector distances (cm) of :mod:`companion.core.sectors`."""
    d = np.asarray(distances_cm)
    if d.shape != (OBSTACLE_SECTORS,):
        raise MessageError(f"OBSTACLE_DISTANCE needs {OBSTACLE_SECTORS} distances, got shape {d.shape}")
    min_cm = _uint("min_distance", min_distance_cm, 16)
    max_cm = _uint("max_distance", max_distance_cm, 16)
    if not min_cm < max_cm < UINT16_MAX - 1:
        raise MessageError(f"need min_distance < max_distance < {UINT16_MAX - 1} cm, got {min_cm}, {max_cm}")
    try:
        df = d.astype(float)
    except (TypeError, ValueError):
        raise MessageError("distances must be numbers") from None
    bad = ~np.isfinite(df) | (df < 0) | (df > UINT16_MAX)
    v = np.where(bad, UINT16_MAX, np.rint(np.where(bad, 0, df))).astype(np.int64)
    # a value above max+1 (other than UINT16_MAX) reads as "no obstacle" to ArduPilot: never send one
    ambiguous = (v > max_cm + 1) & (v != UINT16_MAX)
    if np.any(bad | ambiguous):
        log.warning("OBSTACLE_DISTANCE: %d invalid / ambiguous distances replaced by UINT16_MAX (unknown)",
                    int(np.count_nonzero(bad | ambiguous)))
        v[ambiguous] = UINT16_MAX
    return mavlink.MAVLink_obstacle_distance_message(
        _uint("time_usec", time_usec, 64),
        _uint("sensor_type", sensor_type, 8),
        [int(x) for x in v],
        INCREMENT_DEG,
        min_cm,
        max_cm,
        float(INCREMENT_DEG),
        0.0,
        mavlink.MAV_FRAME_BODY_FRD,
    )


def obstacle_distance_from_sectors(sectors, time_usec: int = 0, sensor_type: int = mavlink.MAV_DISTANCE_SENSOR_UNKNOWN,
                                   distances_cm=None):
    """OBSTACLE_DISTANCE from a :class:`~companion.core.sectors.Sectors` (optionally rotated distances)."""
    d = sectors.distances_cm if distances_cm is None else distances_cm
    return obstacle_distance(d, sectors.min_distance_cm, sectors.max_distance_cm, time_usec, sensor_type)


def signal_quality(distance_m: float, sigma_m: float, zero_rel_sigma: float = 0.5) -> int:
    """2…100 from σ / range (100 = σ → 0); 0 and 1 are reserved (unknown / invalid)."""
    if not (math.isfinite(distance_m) and math.isfinite(sigma_m) and distance_m > 0 and sigma_m >= 0):
        return 0
    q = 100.0 * (1.0 - min(1.0, (sigma_m / distance_m) / zero_rel_sigma))
    return int(max(2, min(100, round(q))))


def covariance_cm2(sigma_m: float) -> int:
    """DISTANCE_SENSOR covariance: variance in cm² (uint8); 255 = unknown or too large to represent."""
    if not (math.isfinite(sigma_m) and sigma_m >= 0):
        return UINT8_MAX
    var = (sigma_m * 100.0) ** 2
    return int(round(var)) if var <= UINT8_MAX - 1 else UINT8_MAX


def distance_sensor(state: str, distance_m: float, sigma_m: float, min_distance_cm: int, max_distance_cm: int,
                    time_boot_ms: int = 0, *, orientation: int = mavlink.MAV_SENSOR_ROTATION_NONE, sensor_id: int = 0,
                    sensor_type: int = mavlink.MAV_DISTANCE_SENSOR_UNKNOWN, horizontal_fov_rad: float = 0.0,
                    vertical_fov_rad: float = 0.0, zero_rel_sigma: float = 0.5):
    """DISTANCE_SENSOR for one direction (default forward).

    ``state`` is ``"obstacle"`` (``distance_m`` with σ ``sigma_m``), ``"clear"`` (sent as
    ``max_distance + 1``) or ``"unknown"`` (UINT16_MAX, signal_quality 1 = invalid).
    """
    min_cm = _uint("min_distance", min_distance_cm, 16)
    max_cm = _uint("max_distance", max_distance_cm, 16)
    if not min_cm < max_cm < UINT16_MAX - 1:
        raise MessageError(f"need min_distance < max_distance < {UINT16_MAX - 1} cm, got {min_cm}, {max_cm}")
    state = str(state).lower()
    if state == "obstacle" and math.isfinite(distance_m):
        cm = int(min(max(round(distance_m * 100.0), min_cm), max_cm))
        cov = covariance_cm2(sigma_m)
        quality = signal_quality(distance_m, sigma_m, zero_rel_sigma) if math.isfinite(sigma_m) else 0
    elif state == "clear":
        cm, cov, quality = max_cm + 1, UINT8_MAX, 100
    elif state in ("unknown", "obstacle"):
        cm, cov, quality = UINT16_MAX, UINT8_MAX, 1
    else:
        raise MessageError(f"state must be 'obstacle', 'clear' or 'unknown', got {state!r}")
    for name, val in (("horizontal_fov_rad", horizontal_fov_rad), ("vertical_fov_rad", vertical_fov_rad)):
        if not (math.isfinite(val) and val >= 0):
            raise MessageError(f"{name} must be finite and >= 0, got {val!r}")
    return mavlink.MAVLink_distance_sensor_message(
        _time_boot_ms(time_boot_ms),
        min_cm,
        max_cm,
        cm,
        _uint("sensor_type", sensor_type, 8),
        _uint("id", sensor_id, 8),
        _uint("orientation", orientation, 8),
        cov,
        float(horizontal_fov_rad),
        float(vertical_fov_rad),
        [0.0, 0.0, 0.0, 0.0],  # only used with MAV_SENSOR_ROTATION_CUSTOM
        quality,
    )


def distance_sensor_from_sectors(sectors, time_boot_ms: int = 0, *, sensor_id: int = 0,
                                 sensor_type: int = mavlink.MAV_DISTANCE_SENSOR_UNKNOWN,
                                 horizontal_fov_rad: float | None = None, zero_rel_sigma: float = 0.5):
    """Forward DISTANCE_SENSOR from ``sectors.forward`` (conservative range and its σ)."""
    f = sectors.forward
    state = {SectorState.OBSTACLE: "obstacle", SectorState.CLEAR: "clear"}.get(SectorState(f.state), "unknown")
    if horizontal_fov_rad is None:
        horizontal_fov_rad = math.radians(SECTOR_DEG)
    return distance_sensor(state, f.distance_m, f.sigma_m, sectors.min_distance_cm, sectors.max_distance_cm, time_boot_ms,
                           sensor_id=sensor_id, sensor_type=sensor_type, horizontal_fov_rad=horizontal_fov_rad,
                           zero_rel_sigma=zero_rel_sigma)


def obstacle_distance_3d(x_m: float, y_m: float, z_m: float, obstacle_id: int, min_distance_m: float, max_distance_m: float,
                         time_boot_ms: int = 0, sensor_type: int = mavlink.MAV_DISTANCE_SENSOR_UNKNOWN):
    """OBSTACLE_DISTANCE_3D: one obstacle in body FRD, metres."""
    vals = (x_m, y_m, z_m, min_distance_m, max_distance_m)
    if not all(isinstance(v, (int, float, np.floating, np.integer)) and math.isfinite(v) for v in vals):
        raise MessageError(f"OBSTACLE_DISTANCE_3D needs finite numbers, got {vals!r}")
    if not 0 <= min_distance_m < max_distance_m:
        raise MessageError(f"need 0 <= min_distance < max_distance, got {min_distance_m}, {max_distance_m}")
    return mavlink.MAVLink_obstacle_distance_3d_message(
        _time_boot_ms(time_boot_ms),
        _uint("sensor_type", sensor_type, 8),
        mavlink.MAV_FRAME_BODY_FRD,
        _uint("obstacle_id", obstacle_id, 16),
        float(x_m), float(y_m), float(z_m),
        float(min_distance_m), float(max_distance_m),
    )


def obstacles_3d_from_sectors(sectors, time_boot_ms: int = 0, sensor_type: int = mavlink.MAV_DISTANCE_SENSOR_UNKNOWN) -> list:
    """One OBSTACLE_DISTANCE_3D per entry of ``sectors.nearest``, all with the same stamp (one batch).

    ``obstacle_id`` is the sector index, so the same direction keeps its id from batch to batch.
    """
    lo, hi = sectors.min_distance_cm / 100.0, sectors.max_distance_cm / 100.0
    return [obstacle_distance_3d(*o.p_body, o.sector, lo, hi, time_boot_ms, sensor_type) for o in sectors.nearest]


def named_value_float(name: str, value: float, time_boot_ms: int = 0):
    """NAMED_VALUE_FLOAT; ``name`` is 1…10 ASCII characters."""
    if not isinstance(name, str) or not 1 <= len(name) <= NAMED_VALUE_LEN or not name.isascii():
        raise MessageError(f"NAMED_VALUE_FLOAT name must be 1..{NAMED_VALUE_LEN} ASCII characters, got {name!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise MessageError(f"NAMED_VALUE_FLOAT value must be a number, got {value!r}") from None
    return mavlink.MAVLink_named_value_float_message(_time_boot_ms(time_boot_ms), name.encode("ascii"), v)


def statustext(text: str, severity: int = mavlink.MAV_SEVERITY_INFO, chunk_id: int = 0) -> list:
    """STATUSTEXT message(s) for ``text`` (ASCII; other characters become '?').

    Up to 50 characters: one message with ``id = 0``.  Longer: chunks of 50 with ``id =
    chunk_id`` (1…65535, required) and ``chunk_seq`` 0, 1, …; an empty final chunk terminates a
    text whose length is a multiple of 50.  At most 256 chunks (chunk_seq is uint8); the rest is cut.
    """
    sev = _uint("severity", severity, 8)
    if sev > mavlink.MAV_SEVERITY_DEBUG:
        raise MessageError(f"severity must be a MAV_SEVERITY (0..7), got {sev}")
    raw = _ascii(text)
    if len(raw) <= STATUSTEXT_LEN:
        return [mavlink.MAVLink_statustext_message(sev, raw, 0, 0)]
    cid = _uint("chunk_id", chunk_id, 16)
    if cid == 0:
        raise MessageError("a STATUSTEXT longer than 50 characters needs a non-zero chunk_id")
    max_len = 256 * STATUSTEXT_LEN
    if len(raw) >= max_len:
        raw = raw[: max_len - 1]  # leave room for the terminating NUL inside the last chunk
    chunks = [raw[i:i + STATUSTEXT_LEN] for i in range(0, len(raw), STATUSTEXT_LEN)]
    if len(chunks[-1]) == STATUSTEXT_LEN:
        chunks.append(b"")
    return [mavlink.MAVLink_statustext_message(sev, c, cid, i) for i, c in enumerate(chunks)]


class StatusTextIds:
    """Allocates STATUSTEXT chunk ids 1…65535 (wrapping) for one sender."""

    def __init__(self):
        self._next = 1

    def encode(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> list:
        if len(_ascii(text)) <= STATUSTEXT_LEN:
            return statustext(text, severity)
        cid = self._next
        self._next = self._next % 65535 + 1
        return statustext(text, severity, cid)


def heartbeat(system_status: int = mavlink.MAV_STATE_STANDBY):
    """Companion HEARTBEAT: MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, no modes."""
    st = _uint("system_status", system_status, 8)
    if st >= mavlink.MAV_STATE_ENUM_END:
        raise MessageError(f"system_status must be a MAV_STATE, got {st}")
    return mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, st, 3
    )


def set_message_interval(target_system: int, target_component: int, message_id: int, rate_hz: float, confirmation: int = 0):
    """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL (511): param1 = message id, param2 = interval µs
    (−1 disables), param7 = 0 (response target: the requesting link)."""
    if not (math.isfinite(rate_hz) and rate_hz >= 0):
        raise MessageError(f"rate_hz must be finite and >= 0, got {rate_hz!r}")
    interval_us = -1.0 if rate_hz == 0 else float(round(1e6 / rate_hz))
    return mavlink.MAVLink_command_long_message(
        _uint("target_system", target_system, 8), _uint("target_component", target_component, 8),
        mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, _uint("confirmation", min(int(confirmation), 255), 8),
        float(_uint("message_id", message_id, 24)), interval_us, 0.0, 0.0, 0.0, 0.0, 0.0,
    )


def request_data_stream(target_system: int, target_component: int, stream_id: int, rate_hz: float, start: bool = True):
    """REQUEST_DATA_STREAM (66), the fallback for autopilots that ignore SET_MESSAGE_INTERVAL."""
    rate = int(max(1, min(65535, round(rate_hz)))) if start else 0
    return mavlink.MAVLink_request_data_stream_message(
        _uint("target_system", target_system, 8), _uint("target_component", target_component, 8),
        _uint("stream_id", stream_id, 8), rate, 1 if start else 0,
    )


def timesync(tc1: int, ts1: int):
    return mavlink.MAVLink_timesync_message(int(tc1), int(ts1))
