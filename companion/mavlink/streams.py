"""Which telemetry the link asks the autopilot for, how, and whether it arrives (pure; the caller's clock).

docs/derivations/link.md.  :class:`StreamRequester` decides the SET_MESSAGE_INTERVAL /
REQUEST_DATA_STREAM traffic for the :class:`StreamSpec` streams (ATTITUDE, LOCAL_POSITION_NED,
GLOBAL_POSITION_INT): one command in flight at a time (COMMAND_ACK carries only the command id),
retries, the fall back to REQUEST_DATA_STREAM when refused, unanswered, or accepted but arriving
below ``min_rate_fraction`` of the request, re-requests after a dropout — all within a
:class:`~companion.mavlink.guard.RequestBudget`.  :class:`RateMeter` measures the arrival rates it
judges by.  :class:`~companion.mavlink.link.MavLink` sends what it decides and feeds it the acks.
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import logging
import math

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.mavlink.config import LinkConfig
from companion.mavlink.guard import RequestBudget

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class StreamSpec:
    name: str  # MAVLink message name, e.g. "ATTITUDE"
    msg_id: int
    rate_hz: float
    data_stream_id: int  # MAV_DATA_STREAM carrying it for REQUEST_DATA_STREAM


class StreamState(str, enum.Enum):
    IDLE = "idle"  # to be requested
    WAIT_ACK = "wait_ack"  # SET_MESSAGE_INTERVAL sent
    WAIT_RATE = "wait_rate"  # accepted; measuring the rate
    OK = "ok"  # arriving at the requested rate
    FALLBACK = "fallback"  # asked with REQUEST_DATA_STREAM


class RateMeter:
    """Arrival rates per message name over a sliding window (pure; caller's clock).

    Bounded: at most ``max_names`` names (others are not measured) and ``max_per_name`` arrivals
    per name in the window (rates above ``max_per_name / window_s`` read as that)."""

    def __init__(self, window_s: float = 2.0, max_per_name: int = 4096, max_names: int = 16):
        self.window_s = window_s
        self.max_per_name = max_per_name
        self.max_names = max_names
        self._t: dict[str, collections.deque[float]] = {}

    def tick(self, name: str, now: float) -> None:
        q = self._t.get(name)
        if q is None:
            if len(self._t) >= self.max_names:
                return
            q = self._t[name] = collections.deque(maxlen=self.max_per_name)
        q.append(now)
        self._trim(q, now)

    def _trim(self, q: collections.deque, now: float) -> None:
        while q and (now - q[0] >= self.window_s or q[0] > now):
            q.popleft()

    def rate(self, name: str, now: float) -> float:
        q = self._t.get(name)
        if not q:
            return 0.0
        self._trim(q, now)
        return len(q) / self.window_s

    def rates(self, now: float) -> dict[str, float]:
        return {k: self.rate(k, now) for k in list(self._t)}

    def clear(self) -> None:
        self._t.clear()


@dataclasses.dataclass
class _Stream:
    spec: StreamSpec
    state: StreamState = StreamState.IDLE
    attempts: int = 0
    sent_at: float = -math.inf
    acked_at: float = -math.inf
    fallback_at: float = -math.inf
    confirmation: int = 0


class StreamRequester:
    """Decides the SET_MESSAGE_INTERVAL / REQUEST_DATA_STREAM traffic (pure; docs/derivations/link.md).

    ``step(now)`` returns actions ``("interval", spec, confirmation)`` or ``("data_stream",
    stream_id, rate_hz)``; ``on_ack(result, now)`` feeds the COMMAND_ACK of the one command in
    flight.  ``events`` collects (severity, text) for STATUSTEXT.

    Every action spends a token of a :class:`~companion.mavlink.guard.RequestBudget`
    (``stream_request_burst`` at once, then one per ``stream_request_interval_s``): whatever
    restarts the requests (reboots, link losses, dropouts) the autopilot never gets more than that.
    An action without a token waits (``rate_limited`` counts the steps that held one back); a
    waiting REQUEST_DATA_STREAM is kept once per data stream.
    """

    def __init__(self, specs: list[StreamSpec], config: LinkConfig, meter: RateMeter):
        self.config = config
        self.meter = meter
        self._streams = {s.name: _Stream(s) for s in specs}
        self._outstanding: str | None = None
        self.counters: collections.Counter[str] = collections.Counter()
        self.events: collections.deque[tuple[int, str]] = collections.deque(maxlen=32)
        self._pending_actions: list = []  # REQUEST_DATA_STREAMs decided but not yet sent (at most one per data stream)
        self.budget = RequestBudget(config.stream_request_interval_s, config.stream_request_burst)

    def restart(self) -> None:
        """Request everything again (link regained, autopilot rebooted)."""
        for st in self._streams.values():
            st.state, st.attempts, st.fallback_at = StreamState.IDLE, 0, -math.inf
        self._outstanding = None
        self.counters["restarts"] += 1

    def state(self, name: str) -> StreamState:
        return self._streams[name].state

    def specs(self) -> list[StreamSpec]:
        """The streams requested, with their rates (what ``companion check`` measures against)."""
        return [st.spec for st in self._streams.values()]

    def states(self) -> dict[str, str]:
        return {k: v.state.value for k, v in self._streams.items()}

    def _ok(self, st: _Stream, now: float) -> bool:
        return self.meter.rate(st.spec.name, now) >= self.config.min_rate_fraction * st.spec.rate_hz

    def _fallback(self, st: _Stream, now: float, why: str, actions: list) -> None:
        st.state = StreamState.FALLBACK
        st.fallback_at = now
        self.counters["fallbacks"] += 1
        self.events.append((mavlink.MAV_SEVERITY_WARNING, f"{st.spec.name}: {why}, using REQUEST_DATA_STREAM"))
        log.warning("%s: %s; falling back to REQUEST_DATA_STREAM", st.spec.name, why)
        actions.append(("data_stream", st.spec.data_stream_id, self._stream_rate(st.spec.data_stream_id)))

    def _stream_rate(self, stream_id: int) -> float:
        return max(s.spec.rate_hz for s in self._streams.values() if s.spec.data_stream_id == stream_id)

    def on_ack(self, result: int, now: float) -> None:
        name = self._outstanding
        if name is None:
            self.counters["unexpected_acks"] += 1
            return
        st = self._streams[name]
        if result == mavlink.MAV_RESULT_IN_PROGRESS:
            return
        self._outstanding = None
        if result == mavlink.MAV_RESULT_ACCEPTED:
            st.state, st.acked_at = StreamState.WAIT_RATE, now
            self.counters["accepted"] += 1
            return
        self.counters["refused"] += 1
        if result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED and st.attempts + 1 < self.config.command_retries:
            st.attempts += 1
            st.state = StreamState.IDLE
            return
        self._fallback(st, now, f"SET_MESSAGE_INTERVAL refused ({result})", self._pending_actions)

    def step(self, now: float) -> list:
        cfg = self.config
        actions: list = self._pending_actions  # REQUEST_DATA_STREAMs waiting for a token come first
        self._pending_actions = []
        if self._outstanding is not None:
            st = self._streams[self._outstanding]
            if now - st.sent_at >= cfg.command_timeout_s:
                self._outstanding = None
                st.attempts += 1
                self.counters["ack_timeouts"] += 1
                if st.attempts >= cfg.command_retries:
                    self._fallback(st, now, "no COMMAND_ACK", actions)
                else:
                    st.state = StreamState.IDLE
        repeat: set[int] = set()
        for st in self._streams.values():
            ok = self._ok(st, now)
            if st.state == StreamState.WAIT_RATE and now - st.acked_at >= cfg.rate_check_s:
                if ok:
                    st.state = StreamState.OK
                    st.attempts = 0
                else:
                    st.attempts += 1
                    self.counters["rate_misses"] += 1
                    rate = self.meter.rate(st.spec.name, now)
                    if st.attempts >= cfg.command_retries:
                        self._fallback(st, now, f"accepted but {rate:.1f} Hz", actions)
                    else:
                        st.state = StreamState.IDLE
            elif st.state == StreamState.OK and not ok:
                rate = self.meter.rate(st.spec.name, now)
                self.counters["dropouts"] += 1
                self.events.append((mavlink.MAV_SEVERITY_WARNING, f"{st.spec.name} at {rate:.1f} Hz, re-requesting"))
                log.warning("%s dropped to %.1f Hz (requested %.1f): re-requesting", st.spec.name, rate, st.spec.rate_hz)
                st.state, st.attempts = StreamState.IDLE, 0
            elif st.state == StreamState.FALLBACK and not ok and now - st.fallback_at >= cfg.fallback_repeat_s:
                st.fallback_at = now
                repeat.add(st.spec.data_stream_id)
        for sid in sorted(repeat):
            self.counters["fallback_repeats"] += 1
            actions.append(("data_stream", sid, self._stream_rate(sid)))
        out: list = []
        waiting: set[int] = set()
        for a in actions:  # one REQUEST_DATA_STREAM per data stream; each needs a token
            if a[1] in waiting or any(o[1] == a[1] for o in out):
                continue
            if self.budget.take(now):
                out.append(a)
            else:
                waiting.add(a[1])
                self._pending_actions.append(a)
        if self._outstanding is None:
            for st in self._streams.values():
                if st.state == StreamState.IDLE:
                    if not self.budget.take(now):
                        waiting.add(-1)
                        break
                    st.state, st.sent_at = StreamState.WAIT_ACK, now
                    st.confirmation = st.attempts
                    self._outstanding = st.spec.name
                    self.counters["interval_requests"] += 1
                    out.append(("interval", st.spec, min(st.confirmation, 255)))
                    break
        if waiting:
            self.counters["rate_limited"] += 1
        return out
