"""TIMESYNC: the autopilot's clock on the companion's monotonic clock (docs/derivations/link.md).

Protocol (MAVLink TIMESYNC, id 111): a request carries ``tc1 = 0`` and ``ts1`` = the sender's time
in ns; the peer answers ``tc1`` = its own time in ns and ``ts1`` copied from the request.  ArduPilot
and PX4 answer with their time since boot, the same clock as ``time_boot_ms`` / ``time_usec`` in
ATTITUDE and LOCAL_POSITION_NED.

For a request sent at companion time ``t0`` and answered at ``t3`` the round trip is
``rtt = t3 − t0`` and, assuming the autopilot stamped ``tc1`` half way,

    offset = (t0 + t3) / 2 − tc1          (t_companion = t_autopilot + offset)

whose error is at most ``rtt / 2`` (all of it from delay asymmetry).  :class:`TimesyncEstimator`
therefore rejects samples whose round trip exceeds ``max_rtt_s``, keeps a window of recent samples,
takes the median offset of the ``best_count`` samples with the shortest round trip, and low-passes
that.  A reply stamped earlier than a previous one by more than ``reset_threshold_s`` means the
autopilot rebooted (its clock went backwards): the estimate restarts.  Sustained jumps in the
other direction (``reset_confirm`` consecutive samples) restart it too.

Until TIMESYNC converges (or if the autopilot never answers) the estimator can fall back on the
lower envelope of ``arrival time − message stamp`` over a window, which is ``offset`` plus the
smallest transport delay seen: biased late by a few ms but never wildly wrong.  :attr:`source`
says which estimate is in use.

Pure logic (no I/O, no globals).  The two tiny message helpers at the end turn estimator calls
into pymavlink TIMESYNC messages.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math

import numpy as np

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.config import require, require_finite

log = logging.getLogger(__name__)

NS = 1_000_000_000
#: bound on the arrival-envelope deque (it is also trimmed to arrival_window_s)
MAX_ARRIVALS = 4096


@dataclasses.dataclass(frozen=True)
class TimesyncConfig:
    """The ``[link.timesync]`` table."""

    interval_s: float = 1.0  # TIMESYNC request period once converged
    fast_interval_s: float = 0.2  # request period until min_samples are collected
    max_rtt_s: float = 0.05  # samples with a longer round trip are rejected (error bound = rtt / 2)
    window: int = 30  # most recent accepted samples kept
    best_count: int = 5  # the offset is the median of this many lowest-round-trip samples
    min_samples: int = 3  # accepted samples before the TIMESYNC estimate is used
    smoothing: float = 0.3  # low-pass gain toward each new median (1 = no smoothing)
    reset_threshold_s: float = 0.5  # autopilot clock going back by more than this = reboot (estimate restarts)
    reset_confirm: int = 3  # consecutive samples disagreeing by more than reset_threshold_s also restart it
    request_timeout_s: float = 2.0  # an unanswered request is forgotten after this long
    max_pending: int = 16  # unanswered requests remembered
    arrival_fallback: bool = True  # before TIMESYNC converges, estimate the offset from message arrival times
    arrival_window_s: float = 10.0  # window of the arrival-time lower envelope

    def __post_init__(self) -> None:
        for name in ("interval_s", "fast_interval_s", "max_rtt_s", "reset_threshold_s", "request_timeout_s", "arrival_window_s"):
            require_finite(name, getattr(self, name), positive=True)
        for name in ("window", "best_count", "min_samples", "reset_confirm", "max_pending"):
            v = getattr(self, name)
            require(isinstance(v, int) and not isinstance(v, bool) and v >= 1, f"{name} must be an integer >= 1, got {v!r}")
        require(self.best_count <= self.window, "best_count must not exceed window")
        require(self.min_samples <= self.window, "min_samples must not exceed window")
        require_finite("smoothing", self.smoothing, positive=True)
        require(self.smoothing <= 1.0, f"smoothing must be in (0, 1], got {self.smoothing}")
        require(isinstance(self.arrival_fallback, bool), "arrival_fallback must be true or false")


@dataclasses.dataclass(frozen=True)
class TimesyncSample:
    t_companion: float  # reply arrival time, s
    rtt_s: float
    offset_s: float


class TimesyncEstimator:
    """Offset between the autopilot's boot clock and the companion's monotonic clock."""

    def __init__(self, config: TimesyncConfig = TimesyncConfig()):
        self.config = config
        self.counters: collections.Counter[str] = collections.Counter()
        self._pending: dict[int, float] = {}  # ts1 (ns) -> send time (s)
        self._last_ns = 0
        self._last_request_t: float | None = None
        self._samples: collections.deque[TimesyncSample] = collections.deque(maxlen=config.window)
        self._offset: float | None = None
        self._last_tc1: int | None = None
        self._disagree = 0
        # lower envelope of the arrival offsets over the window, as a monotonic deque of
        # (arrival, offset) with offsets increasing: the front is the window's minimum, the back the
        # newest stamp (so it is empty exactly when no stamp lies in the window); O(1) per stamp
        self._arrivals: collections.deque[tuple[float, float]] = collections.deque()
        self.last_rtt_s: float = math.nan

    # ------------------------------------------------------------------ state ----------------
    @property
    def converged(self) -> bool:
        return self._offset is not None and len(self._samples) >= self.config.min_samples

    @property
    def source(self) -> str | None:
        """"timesync", "arrival" or None (no estimate yet)."""
        if self.converged:
            return "timesync"
        if self.config.arrival_fallback and self._arrivals:
            return "arrival"
        return None

    @property
    def offset_s(self) -> float | None:
        """``t_companion − t_autopilot`` in seconds, or None."""
        if self.converged:
            return self._offset
        if self.config.arrival_fallback and self._arrivals:
            return self._arrivals[0][1]
        return None

    @property
    def sample_count(self) -> int:
        return len(self._samples)

    @property
    def best_rtt_s(self) -> float:
        return min((s.rtt_s for s in self._samples), default=math.nan)

    def autopilot_to_companion(self, t_autopilot_s: float) -> float | None:
        off = self.offset_s
        return None if off is None else t_autopilot_s + off

    def companion_to_autopilot(self, t_companion_s: float) -> float | None:
        off = self.offset_s
        return None if off is None else t_companion_s - off

    def boot_ms_to_companion(self, time_boot_ms: int) -> float | None:
        return self.autopilot_to_companion(time_boot_ms * 1e-3)

    def reset(self, reason: str = "reset") -> None:
        """Forget everything (autopilot reboot, link change)."""
        log.info("timesync estimate reset (%s)", reason)
        self.counters["resets"] += 1
        self._pending.clear()
        self._samples.clear()
        self._offset = None
        self._last_tc1 = None
        self._disagree = 0
        self._arrivals.clear()

    # ------------------------------------------------------------------ requests -------------
    def request_due(self, now: float) -> bool:
        period = self.config.interval_s if self.converged else self.config.fast_interval_s
        return self._last_request_t is None or now - self._last_request_t >= period - 1e-9

    def make_request(self, now: float) -> tuple[int, int]:
        """(tc1, ts1) of a new request sent at ``now`` (companion clock, s)."""
        ts1 = max(int(round(now * NS)), 1)
        if ts1 <= self._last_ns:  # unique and increasing, even with a coarse or frozen clock
            ts1 = self._last_ns + 1
        self._last_ns = ts1
        self._last_request_t = now
        self._expire(now)
        if len(self._pending) >= self.config.max_pending:
            self._pending.pop(next(iter(self._pending)))
        self._pending[ts1] = now
        self.counters["requests"] += 1
        return 0, ts1

    def _expire(self, now: float) -> None:
        old = [k for k, t in self._pending.items() if now - t > self.config.request_timeout_s]
        for k in old:
            del self._pending[k]
        self.counters["requests_unanswered"] += len(old)

    @staticmethod
    def answer(ts1: int, now: float) -> tuple[int, int]:
        """(tc1, ts1) answering a peer's request received at ``now``."""
        return max(int(round(now * NS)), 1), int(ts1)

    # ------------------------------------------------------------------ replies --------------
    def handle_reply(self, tc1: int, ts1: int, now: float) -> TimesyncSample | None:
        """Process a reply received at ``now``; returns the accepted sample or None."""
        try:
            tc1, ts1 = int(tc1), int(ts1)
        except (TypeError, ValueError, OverflowError):
            self.counters["invalid"] += 1
            return None
        sent = self._pending.pop(ts1, None)
        if sent is None:
            self.counters["unmatched"] += 1  # someone else's request, or a duplicate / late reply
            return None
        if tc1 <= 0:
            self.counters["invalid"] += 1
            return None
        rtt = now - sent
        if rtt < 0:
            self.counters["invalid"] += 1
            return None
        self.last_rtt_s = rtt
        if self._last_tc1 is not None and (self._last_tc1 - tc1) / NS > self.config.reset_threshold_s:
            log.warning("autopilot clock went back %.3f s (reboot?): timesync restarts", (self._last_tc1 - tc1) / NS)
            self.counters["clock_backwards"] += 1
            self.reset("autopilot clock went backwards")
        self._last_tc1 = tc1 if self._last_tc1 is None else max(self._last_tc1, tc1)
        if rtt > self.config.max_rtt_s:
            self.counters["rejected_rtt"] += 1
            return None
        offset = (sent + now) / 2.0 - tc1 / NS
        if self._offset is not None and abs(offset - self._offset) > self.config.reset_threshold_s:
            self._disagree += 1
            self.counters["disagreeing"] += 1
            if self._disagree < self.config.reset_confirm:
                return None
            log.warning("timesync offset jumped by %.3f s: estimate restarts", offset - self._offset)
            self.reset("offset jump")
        self._disagree = 0
        sample = TimesyncSample(now, rtt, offset)
        self._samples.append(sample)
        self._update()
        self.counters["accepted"] += 1
        return sample

    def _update(self) -> None:
        s = list(self._samples)
        rtts = np.array([x.rtt_s for x in s])
        offs = np.array([x.offset_s for x in s])
        best = np.argsort(rtts, kind="stable")[: self.config.best_count]
        raw = float(np.median(offs[best]))
        if self._offset is None or len(s) <= self.config.min_samples:
            self._offset = raw  # start from the data, do not crawl from an arbitrary value
        else:
            self._offset += self.config.smoothing * (raw - self._offset)

    # ------------------------------------------------------------------ arrival fallback -----
    def observe_stamp(self, t_autopilot_s: float, arrival: float) -> None:
        """A message stamped ``t_autopilot_s`` (e.g. time_boot_ms / 1000) arrived at ``arrival``."""
        if not self.config.arrival_fallback:
            return
        if not (math.isfinite(t_autopilot_s) and math.isfinite(arrival)):
            return
        v = arrival - t_autopilot_s
        if self._arrivals and abs(v - self._arrivals[0][1]) > 10 * self.config.reset_threshold_s + 1.0:
            # a stamp far off the envelope: stale data from before a reboot or garbage; restart the envelope
            self._arrivals.clear()
            self.counters["arrival_restart"] += 1
        env = self._arrivals
        while env and env[-1][1] >= v:  # never the minimum again while v is in the window
            env.pop()
        env.append((arrival, v))
        while arrival - env[0][0] > self.config.arrival_window_s or len(env) > MAX_ARRIVALS:
            env.popleft()  # (the length cap only bites on a flood of stamps: the envelope then spans less time)


# ---------------------------------------------------------------------- message glue -------------
def timesync_request(est: TimesyncEstimator, now: float):
    """A TIMESYNC request message (tc1 = 0, ts1 = now in ns), registered with ``est``."""
    tc1, ts1 = est.make_request(now)
    return mavlink.MAVLink_timesync_message(tc1, ts1)


def handle_timesync(est: TimesyncEstimator, msg, now: float):
    """Feed a received TIMESYNC to ``est``; returns the reply message to send for a request, else None."""
    try:
        tc1, ts1 = int(msg.tc1), int(msg.ts1)
    except (AttributeError, TypeError, ValueError, OverflowError):
        est.counters["invalid"] += 1
        return None
    if tc1 == 0:
        if ts1 <= 0:
            est.counters["invalid"] += 1
            return None
        est.counters["answered"] += 1
        return mavlink.MAVLink_timesync_message(*est.answer(ts1, now))
    est.handle_reply(tc1, ts1, now)
    return None
