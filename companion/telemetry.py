"""Autopilot telemetry ring buffer interpolated to camera exposure times (docs/derivations/frames.md, docs/derivations/link.md).

Pure logic: no I/O, no globals.  The MAVLink link feeds it ATTITUDE (roll, pitch, yaw and body
rates, ZYX, rad) and LOCAL_POSITION_NED (NED position and velocity) samples keyed by the
autopilot's ``time_boot_ms``; the pipeline asks :meth:`TelemetryBuffer.pose_at` for the pose at a
frame's capture time on the companion clock.

Clock.  Samples are kept on the autopilot clock and mapped onto the companion's monotonic clock
through the TIMESYNC offset (``t_companion = t_boot + offset``, :meth:`set_clock_offset`).  Every
sample therefore carries a companion-clock stamp, and a refined offset re-stamps the whole buffer
consistently instead of leaving samples stamped with different estimates.  Without an offset the
buffer refuses companion-clock queries (reason ``no_clock``); :meth:`pose_at_boot` queries on the
autopilot clock directly (replay, tests).

Refusals are results, not exceptions: :class:`PoseResult` has ``ok`` and a ``reason``
(``empty``, ``no_clock``, ``before_buffer``, ``after_buffer``, ``gap``, ``stale``, ``bad_time``),
prefixed ``position:`` when only the position stream failed.

Robustness: non-finite samples are refused; a duplicated stamp is ignored; an
out-of-order sample is inserted where it belongs (or dropped if older than the whole full
buffer); ``time_boot_ms`` going back by more than ``reset_threshold_s`` means the autopilot
rebooted: the buffer is cleared and the caller is told (:data:`AddResult.RESET`) so it can reset
TIMESYNC and re-request the streams.  Every outcome is counted in :attr:`TelemetryBuffer.counters`.

A live MAVLink link decides reboots itself, on consistent evidence rather than one stamp
(:class:`companion.mavlink.guard.BootClockGuard`): it sets :attr:`TelemetryBuffer.auto_reset` False
and calls :meth:`TelemetryBuffer.declare_reset`, which clears the buffer and counts ``reset`` (what
the pipeline watches to restart its tracks).
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import logging
import math

import numpy as np

from companion.config import require, require_finite, require_int
from companion.core.frames import (R_to_euler_zyx_scalar, R_to_quat, R_to_quat_scalar, euler_zyx_to_R_scalar,
                                   quat_slerp_scalar, quat_to_R, quat_to_R_scalar, so3_exp)

log = logging.getLogger(__name__)


#: Resolution of the autopilot's time_boot_ms stamps: an exposure less than this after the newest
#: sample is not after it (a sample stamped 20133 ms may describe any instant up to 20133.999 ms).
STAMP_RESOLUTION_S = 0.001


@dataclasses.dataclass(frozen=True)
class TelemetryConfig:
    """The ``[telemetry]`` table."""

    capacity: int = 512  # samples kept per stream (512 = 10 s of 50 Hz ATTITUDE)
    max_gap_s: float = 0.25  # two bracketing samples farther apart than this are not interpolated
    max_age_s: float = 0.5  # newest sample older than this (vs. now) = telemetry stale (docs/derivations/link.md: 0.5 s)
    max_extrapolation_s: float = 0.0  # pose_at may extrapolate this far past the newest sample (rates / velocity); 0 = never
    reset_threshold_s: float = 1.0  # time_boot_ms going back by more than this = autopilot reboot: buffer cleared

    def __post_init__(self) -> None:
        require_int("capacity", self.capacity, minimum=2)
        require_finite("max_gap_s", self.max_gap_s, positive=True)
        require_finite("max_age_s", self.max_age_s, positive=True)
        require_finite("max_extrapolation_s", self.max_extrapolation_s, nonnegative=True)
        require_finite("reset_threshold_s", self.reset_threshold_s, positive=True)


class AddResult(str, enum.Enum):
    """What happened to one sample handed to the buffer."""

    APPENDED = "appended"
    INSERTED = "inserted"  # out of order, put in its place
    DUPLICATE = "duplicate"  # same stamp already held: ignored
    TOO_OLD = "too_old"  # older than everything in a full buffer: dropped
    INVALID = "invalid"  # NaN/inf or a negative stamp: refused
    RESET = "reset"  # time went back: autopilot reboot, buffer cleared, sample kept


@dataclasses.dataclass(frozen=True, eq=False)
class Pose:
    """Vehicle state at one instant (world = local NED, body = FRD)."""

    t: float  # companion clock (or autopilot boot time for pose_at_boot), s
    q_world_body: np.ndarray  # (4,) unit quaternion (w, x, y, z)
    rates_body: np.ndarray  # (3,) body rates p, q, r, rad/s
    p_world: np.ndarray | None  # (3,) NED position, m (None when not requested / available)
    v_world: np.ndarray | None  # (3,) NED velocity, m/s

    @property
    def R_world_body(self) -> np.ndarray:
        return quat_to_R_scalar(self.q_world_body)

    @property
    def rpy(self) -> np.ndarray:
        """roll, pitch, yaw (ZYX, rad)."""
        return R_to_euler_zyx_scalar(self.R_world_body)

    @property
    def yaw(self) -> float:
        return float(self.rpy[2])


@dataclasses.dataclass(frozen=True)
class PoseResult:
    ok: bool
    reason: str  # "ok" or why not
    pose: Pose | None = None

    def __bool__(self) -> bool:
        return self.ok


class _Stream:
    """Sorted ring of (t_boot_s, values) with bounded capacity.

    ``t``, ``v`` and ``ms`` are views of the newest ≤ ``capacity`` samples in backing arrays twice
    that long: an in-order sample is written after the last one (the oldest falls off the front by
    moving the view), and only when the backing end is reached are the kept samples moved back to
    its start — each sample is copied about once, not the whole history on every message."""

    def __init__(self, width: int, capacity: int):
        self.capacity = capacity
        self._t = np.empty(2 * capacity)
        self._v = np.empty((2 * capacity, width))
        self._ms = np.empty(2 * capacity, dtype=np.int64)
        self._lo = self._hi = 0
        self._view()

    def _view(self) -> None:
        lo, hi = self._lo, self._hi
        self.t, self.v, self.ms = self._t[lo:hi], self._v[lo:hi], self._ms[lo:hi]

    def __len__(self) -> int:
        return self._hi - self._lo

    def clear(self) -> None:
        self._lo = self._hi = 0
        self._view()

    def _store(self, t: np.ndarray, v: np.ndarray, ms: np.ndarray) -> None:
        """Replace the contents by these (sorted) samples, the newest ``capacity`` kept."""
        k = max(len(t) - self.capacity, 0)
        n = len(t) - k
        self._t[:n], self._v[:n], self._ms[:n] = t[k:], v[k:], ms[k:]
        self._lo, self._hi = 0, n
        self._view()

    def add(self, ms: int, values: np.ndarray) -> AddResult:
        t = ms * 1e-3
        n = self._hi - self._lo
        last = int(self._ms[self._hi - 1]) if n else 0
        if n and ms == last:
            return AddResult.DUPLICATE
        if n == 0 or ms > last:
            if self._hi == len(self._t):  # backing end reached: move the kept samples to the start
                self._store(self.t.copy(), self.v.copy(), self.ms.copy())
            i = self._hi
            self._t[i], self._v[i], self._ms[i] = t, values, ms
            self._hi += 1
            if self._hi - self._lo > self.capacity:
                self._lo += 1
            self._view()
            return AddResult.APPENDED
        i = int(np.searchsorted(self.ms, ms))
        if i < n and self.ms[i] == ms:
            return AddResult.DUPLICATE
        if i == 0 and n >= self.capacity:
            return AddResult.TOO_OLD
        self._store(np.insert(self.t, i, t), np.insert(self.v, i, values, axis=0), np.insert(self.ms, i, ms))
        return AddResult.INSERTED

    def bracket(self, t: float, max_gap: float, max_extrap: float):
        """(i0, i1, s) with value = lerp(v[i0], v[i1], s), or (None, reason) on refusal."""
        n = self.t.size
        if n == 0:
            return None, "empty"
        if t < self.t[0]:
            return None, "before_buffer"
        if t > self.t[-1]:
            if t - self.t[-1] <= STAMP_RESOLUTION_S:  # within the 1 ms quantum of time_boot_ms: the newest sample
                return (n - 1, n - 1, 0.0), "ok"
            if t - self.t[-1] <= max_extrap:
                return (n - 1, n - 1, t - self.t[-1]), "extrapolate"
            return None, "after_buffer"
        i1 = int(np.searchsorted(self.t, t, side="left"))
        if self.t[i1] == t:
            return (i1, i1, 0.0), "ok"
        i0 = i1 - 1
        dt = self.t[i1] - self.t[i0]
        if dt > max_gap:
            return None, "gap"
        return (i0, i1, (t - self.t[i0]) / dt), "ok"


class TelemetryBuffer:
    """Attitude and position/velocity history with interpolation (see module docstring)."""

    # attitude row: qw qx qy qz p q r ; position row: x y z vx vy vz
    def __init__(self, config: TelemetryConfig = TelemetryConfig()):
        self.config = config
        self._att = _Stream(7, config.capacity)
        self._pos = _Stream(6, config.capacity)
        self._offset_s: float | None = None
        self.counters: collections.Counter[str] = collections.Counter()
        #: True: a stamp more than reset_threshold_s older than the newest clears the buffer (a reboot);
        #: False: the feeder decides reboots (declare_reset) and such a stamp is only inserted or dropped
        self.auto_reset = True

    # ------------------------------------------------------------------ clock ----------------
    def set_clock_offset(self, offset_s: float | None) -> None:
        """``t_companion = t_boot + offset_s`` (from TIMESYNC); None = unknown."""
        if offset_s is not None and not math.isfinite(offset_s):
            offset_s = None
        self._offset_s = offset_s

    @property
    def clock_offset_s(self) -> float | None:
        return self._offset_s

    def to_companion(self, t_boot_s: float) -> float | None:
        return None if self._offset_s is None else t_boot_s + self._offset_s

    def to_boot(self, t_companion: float) -> float | None:
        return None if self._offset_s is None else t_companion - self._offset_s

    # ------------------------------------------------------------------ input ----------------
    def clear(self) -> None:
        self._att.clear()
        self._pos.clear()

    def declare_reset(self, reason: str = "autopilot reboot") -> None:
        """The feeder established that the autopilot's clock restarted: clear, count ``reset``."""
        log.warning("telemetry buffer cleared: %s", reason)
        self.clear()
        self.counters["reset"] += 1

    def _check_reset(self, ms: int) -> bool:
        if not self.auto_reset:
            return False
        newest = max((int(s.ms[-1]) for s in (self._att, self._pos) if len(s)), default=None)
        if newest is not None and (newest - ms) * 1e-3 > self.config.reset_threshold_s:
            log.warning("time_boot_ms went back from %d to %d ms: autopilot reboot, telemetry buffer cleared", newest, ms)
            self.clear()
            return True
        return False

    def _add(self, stream: _Stream, kind: str, time_boot_ms, values) -> AddResult:
        try:
            ms = int(time_boot_ms)
            vals = np.asarray(values, dtype=float)
        except (TypeError, ValueError, OverflowError):
            ms, vals = -1, np.array([np.nan])
        if ms < 0 or not np.all(np.isfinite(vals)):
            self.counters[f"{kind}_invalid"] += 1
            return AddResult.INVALID
        reset = self._check_reset(ms)
        result = stream.add(ms, vals)
        if reset:
            self.counters["reset"] += 1
            result = AddResult.RESET
        self.counters[f"{kind}_{result.value}"] += 1
        return result

    def add_attitude(self, time_boot_ms: int, roll: float, pitch: float, yaw: float,
                     rollspeed: float, pitchspeed: float, yawspeed: float) -> AddResult:
        """One ATTITUDE message (rad, rad/s)."""
        try:
            vals = [float(a) for a in (roll, pitch, yaw, rollspeed, pitchspeed, yawspeed)]
        except (TypeError, ValueError, OverflowError):
            self.counters["attitude_invalid"] += 1
            return AddResult.INVALID
        if not all(math.isfinite(a) for a in vals):
            self.counters["attitude_invalid"] += 1
            return AddResult.INVALID
        q = R_to_quat_scalar(euler_zyx_to_R_scalar(*vals[:3]))  # = R_to_quat(euler_zyx_to_R(…)) bit for bit
        return self._add(self._att, "attitude", time_boot_ms, np.concatenate([q, vals[3:]]))

    def add_local_position(self, time_boot_ms: int, x: float, y: float, z: float,
                           vx: float, vy: float, vz: float) -> AddResult:
        """One LOCAL_POSITION_NED message (m, m/s)."""
        return self._add(self._pos, "position", time_boot_ms, (x, y, z, vx, vy, vz))

    # ------------------------------------------------------------------ state ----------------
    @property
    def attitude_count(self) -> int:
        return len(self._att)

    @property
    def position_count(self) -> int:
        return len(self._pos)

    def newest_boot_s(self, stream: str = "attitude") -> float | None:
        s = self._att if stream == "attitude" else self._pos
        return float(s.t[-1]) if len(s) else None

    def age(self, now: float, stream: str = "attitude") -> float:
        """Seconds since the newest sample of a stream (companion clock); inf if unknown."""
        tb = self.newest_boot_s(stream)
        if tb is None or self._offset_s is None:
            return math.inf
        return now - (tb + self._offset_s)

    def is_fresh(self, now: float, need_position: bool = True) -> bool:
        """Both needed streams have a sample younger than ``max_age_s``."""
        if self.age(now, "attitude") > self.config.max_age_s:
            return False
        return not need_position or self.age(now, "position") <= self.config.max_age_s

    # ------------------------------------------------------------------ queries --------------
    def pose_at(self, t: float, now: float | None = None, need_position: bool = True) -> PoseResult:
        """Pose at companion-clock time ``t``; ``now`` (companion clock) enables the staleness check."""
        if not (isinstance(t, (int, float)) and math.isfinite(t)):
            return self._refuse("bad_time")
        if self._offset_s is None:
            return self._refuse("no_clock")
        tb = t - self._offset_s
        if now is not None:
            if self.age(now, "attitude") > self.config.max_age_s:
                return self._refuse("stale")
            if need_position and self.age(now, "position") > self.config.max_age_s:
                return self._refuse("position:stale")
        res = self._interp(tb, need_position)
        if res.ok:
            return PoseResult(True, "ok", dataclasses.replace(res.pose, t=float(t)))
        return res

    def pose_at_boot(self, t_boot_s: float, need_position: bool = True) -> PoseResult:
        """Pose at autopilot boot time ``t_boot_s`` (no clock mapping, no staleness check)."""
        if not (isinstance(t_boot_s, (int, float)) and math.isfinite(t_boot_s)):
            return self._refuse("bad_time")
        return self._interp(float(t_boot_s), need_position)

    def yaw_at(self, t: float) -> float | None:
        """Yaw (rad) at companion time ``t`` or None (for rotating sectors by the yaw change)."""
        r = self.pose_at(t, need_position=False)
        return r.pose.yaw if r.ok else None

    def _refuse(self, reason: str) -> PoseResult:
        self.counters[f"refused_{reason}"] += 1
        return PoseResult(False, reason)

    def _interp(self, tb: float, need_position: bool) -> PoseResult:
        cfg = self.config
        br, why = self._att.bracket(tb, cfg.max_gap_s, cfg.max_extrapolation_s)
        if br is None:
            return self._refuse(why)
        i0, i1, s = br
        a = self._att.v
        if why == "extrapolate":
            q0 = a[i0, :4]
            w = a[i0, 4:7]
            R = quat_to_R(q0) @ so3_exp(w * s)  # body rates integrated over the extrapolation
            q = R_to_quat(R)
            rates = w.copy()
        else:
            q = quat_slerp_scalar(a[i0, :4], a[i1, :4], s)
            rates = (1 - s) * a[i0, 4:7] + s * a[i1, 4:7]
        p = v = None
        if need_position:
            brp, whyp = self._pos.bracket(tb, cfg.max_gap_s, cfg.max_extrapolation_s)
            if brp is None:
                return self._refuse(f"position:{whyp}")
            j0, j1, sp = brp
            b = self._pos.v
            if whyp == "extrapolate":
                p = b[j0, :3] + b[j0, 3:6] * sp
                v = b[j0, 3:6].copy()
            else:
                row = (1 - sp) * b[j0] + sp * b[j1]
                p, v = row[:3], row[3:6]
        self.counters["pose_ok"] += 1
        return PoseResult(True, "ok", Pose(float(tb), np.asarray(q, float), np.asarray(rates, float), p, v))
