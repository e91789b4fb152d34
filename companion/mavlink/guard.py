"""Link hardening: the autopilot clock guard, per-source accounting, a request budget.

Pure logic (no I/O, no globals, the caller's clock); :class:`companion.mavlink.link.MavLink` wires
them in.  Everything here is bounded in memory by construction.

:class:`BootClockGuard` — which ``time_boot_ms`` stamps are the autopilot's clock
    The autopilot's boot clock only moves forward, at the pace of the companion's clock.  The
    guard locks onto it once ``lock_messages`` stamps agree, then accepts a stamp ``t`` arriving at
    companion time ``now`` only if

        t_newest − jitter  ≤  t  ≤  t_newest + (now − arrival of t_newest) + jitter

    (``t_newest``: the newest accepted stamp; re-anchored on every accepted stamp, so clock drift
    and a slow or fast simulation never accumulate).  Anything else — a packet with a random
    ``time_boot_ms`` (spoofing, or a noisy radio's CRC collision), a stale replay — is *rejected
    with a reason* (``went_back`` / ``jumped_ahead``) and changes nothing but a counter.

    A rejected stamp also starts or extends a *candidate* clock (at most ``max_candidates`` are
    tracked; the one with the fewest stamps is evicted; a candidate not extended for
    ``max(2 s, 4 × reboot_confirm_s)`` is dropped).  A candidate becomes the autopilot's new clock —
    a declared **reboot** — only on consistent evidence, all of:

    * ``reboot_confirm_messages`` stamps on the candidate clock, spanning ``reboot_confirm_s``;
    * the old clock silent for ``reboot_confirm_s`` (an autopilot that rebooted cannot keep its old
      clock running; interleaved spoofed packets never meet this while the real one streams);
    * the heartbeat agrees: the vehicle's HEARTBEAT went silent for ``heartbeat_gap_s`` and came
      back after the old clock's last stamp, *or* the candidate is confirmed by two different
      message types (ATTITUDE and the position stream's ``time_boot_ms`` agree);
    * no other reboot within ``reboot_min_interval_s`` (rejected as ``reboot_rate_limited`` until then).

    A single or sporadic time-jumping packet can therefore never reset anything.

:class:`SourceTable` — per (system, component) message counts, at most ``capacity`` sources
    (the least recently heard one is evicted, never the locked autopilot), for diagnostics.

:class:`RequestBudget` — a token bucket: ``burst`` requests at once, then one per ``interval_s``.
"""

from __future__ import annotations

import collections
import dataclasses
import math

#: Most message-type names remembered per candidate clock (only "two or more" matters).
_MAX_KINDS = 4


@dataclasses.dataclass
class _Clock:
    """One boot clock as heard: its newest stamp and when that arrived."""

    t_max: float  # newest stamp, autopilot s
    a_max: float  # arrival of t_max, companion s
    first: float  # arrival of the first stamp on this clock
    last: float  # arrival of the latest stamp on this clock
    count: int = 1
    kinds: set = dataclasses.field(default_factory=set)

    def matches(self, t: float, now: float, jitter: float) -> bool:
        return self.t_max - jitter <= t <= self.t_max + max(0.0, now - self.a_max) + jitter

    def add(self, t: float, now: float, kind: str) -> None:
        if t >= self.t_max:
            self.t_max, self.a_max = t, now
        self.last = max(self.last, now)
        self.count += 1
        if len(self.kinds) < _MAX_KINDS:
            self.kinds.add(kind)


@dataclasses.dataclass(frozen=True)
class ClockVerdict:
    """What :meth:`BootClockGuard.check` made of one stamp."""

    accepted: bool  # the stamp is on the autopilot's clock: use the message
    reason: str  # "ok", "locked", "reboot", or why it was rejected
    reboot: bool = False  # a reboot was declared by this stamp (it starts the new clock)


class BootClockGuard:
    """Accepts only ``time_boot_ms`` stamps on the autopilot's clock (see the module docstring)."""

    def __init__(self, *, jitter_s: float = 0.5, lock_messages: int = 3, reboot_confirm_messages: int = 10,
                 reboot_confirm_s: float = 0.5, heartbeat_gap_s: float = 1.5, reboot_min_interval_s: float = 5.0,
                 max_candidates: int = 4, history: int = 32):
        self.jitter_s = float(jitter_s)
        self.lock_messages = int(lock_messages)
        self.reboot_confirm_messages = int(reboot_confirm_messages)
        self.reboot_confirm_s = float(reboot_confirm_s)
        self.heartbeat_gap_s = float(heartbeat_gap_s)
        self.reboot_min_interval_s = float(reboot_min_interval_s)
        self.max_candidates = int(max_candidates)
        self.candidate_timeout_s = max(2.0, 4.0 * self.reboot_confirm_s)
        self._clock: _Clock | None = None
        self._candidates: list[_Clock] = []
        self._last_accept = -math.inf  # arrival of the newest accepted stamp
        self._last_reboot = -math.inf
        self._last_hb: float | None = None
        self._hb_return = -math.inf  # arrival of a HEARTBEAT that ended a silence of heartbeat_gap_s or more
        self.counters: collections.Counter[str] = collections.Counter()
        #: the guard's state changes, newest last: (companion time, "locked" | "reboot", detail)
        self.history: collections.deque[tuple[float, str, str]] = collections.deque(maxlen=history)

    # ------------------------------------------------------------------ state ----------------
    @property
    def locked(self) -> bool:
        return self._clock is not None

    @property
    def newest_s(self) -> float | None:
        """Newest accepted autopilot stamp, s (None before the lock)."""
        return None if self._clock is None else self._clock.t_max

    @property
    def candidate_count(self) -> int:
        return len(self._candidates)

    # ------------------------------------------------------------------ input ----------------
    def heartbeat(self, now: float) -> None:
        """A HEARTBEAT of the locked autopilot arrived at ``now``."""
        if self._last_hb is not None and now - self._last_hb >= self.heartbeat_gap_s:
            self._hb_return = now
        self._last_hb = now if self._last_hb is None else max(self._last_hb, now)

    def check(self, kind: str, time_boot_ms: int, now: float) -> ClockVerdict:
        """One stamp (``kind`` = the message type) from the autopilot's system/component at ``now``."""
        t = float(time_boot_ms) * 1e-3
        if not (math.isfinite(t) and t >= 0 and math.isfinite(now)):
            return self._reject("invalid")
        self._expire(now)
        clk = self._clock
        if clk is None:
            cand = self._candidate(t, now, kind)
            if cand.count < self.lock_messages:
                return self._reject("acquiring")
            self._adopt(cand, now)
            self.history.append((now, "locked", f"time_boot_ms {time_boot_ms}"))
            self.counters["locked"] += 1
            return ClockVerdict(True, "locked")
        if clk.matches(t, now, self.jitter_s):
            clk.add(t, now, kind)
            self._last_accept = now
            self.counters["accepted"] += 1
            return ClockVerdict(True, "ok")
        reason = "went_back" if t < clk.t_max - self.jitter_s else "jumped_ahead"
        cand = self._candidate(t, now, kind)
        if self._confirmed(cand, now):
            if now - self._last_reboot < self.reboot_min_interval_s:
                return self._reject("reboot_rate_limited")
            self._last_reboot = now
            self.history.append((now, "reboot", f"time_boot_ms {int(clk.t_max * 1000)} -> {time_boot_ms}"))
            self.counters["reboots"] += 1
            self._adopt(cand, now)
            return ClockVerdict(True, "reboot", reboot=True)
        return self._reject(reason)

    # ------------------------------------------------------------------ internals ------------
    def _reject(self, reason: str) -> ClockVerdict:
        self.counters[f"rejected_{reason}"] += 1
        return ClockVerdict(False, reason)

    def _adopt(self, cand: _Clock, now: float) -> None:
        self._clock = cand
        self._candidates.clear()
        self._last_accept = now

    def _expire(self, now: float) -> None:
        if self._candidates:
            self._candidates = [c for c in self._candidates if 0.0 <= now - c.last <= self.candidate_timeout_s]

    def _candidate(self, t: float, now: float, kind: str) -> _Clock:
        best = None
        for c in self._candidates:
            if c.matches(t, now, self.jitter_s) and (best is None or c.count > best.count):
                best = c
        if best is not None:
            best.add(t, now, kind)
            return best
        if len(self._candidates) >= self.max_candidates:
            weakest = min(self._candidates, key=lambda c: (c.count, c.last))
            self._candidates.remove(weakest)
            self.counters["candidates_evicted"] += 1
        c = _Clock(t, now, now, now, 1, {kind})
        self._candidates.append(c)
        return c

    def _confirmed(self, cand: _Clock, now: float) -> bool:
        if cand.count < self.reboot_confirm_messages or cand.last - cand.first < self.reboot_confirm_s:
            return False
        if now - self._last_accept < self.reboot_confirm_s:
            self.counters["candidate_old_clock_alive"] += 1
            return False
        if len(cand.kinds) >= 2:
            return True
        return self._hb_return > self._last_accept  # the heartbeat went silent and came back after the old clock stopped


class SourceTable:
    """Messages per (system, component), at most ``capacity`` sources (see the module docstring)."""

    def __init__(self, capacity: int = 32):
        self.capacity = int(capacity)
        self._t: collections.OrderedDict[tuple[int, int], collections.Counter] = collections.OrderedDict()
        self.protected: tuple[int, int] | None = None  # never evicted (the locked autopilot)
        self.evicted = 0

    def count(self, src: tuple[int, int], what: str, now: float | None = None) -> None:
        c = self._t.get(src)
        if c is None:
            if len(self._t) >= self.capacity:
                victim = next((k for k in self._t if k != self.protected), None)
                if victim is None:
                    return
                del self._t[victim]
                self.evicted += 1
            c = self._t[src] = collections.Counter()
        else:
            self._t.move_to_end(src)
        c[what] += 1

    def __len__(self) -> int:
        return len(self._t)

    def __contains__(self, src) -> bool:
        return src in self._t

    def snapshot(self) -> dict[str, dict[str, int]]:
        """``{"SYS/COMP": {what: count}}``, least recently heard first."""
        return {f"{s}/{c}": dict(v) for (s, c), v in self._t.items()}


class RequestBudget:
    """Start-up burst, then strictly one per ``interval_s`` (caller's clock).

    The first ``burst`` requests may go at once (asking for every stream at start-up); what the
    start-up leaves of the burst expires ``burst × interval_s`` after the first request.  From then
    on the bucket holds at most one token, refilled over ``interval_s``, so no window of
    ``interval_s`` sees two requests again — however the link misbehaves (a blackout ending,
    streams stopping together, a reboot)."""

    def __init__(self, interval_s: float, burst: int):
        self.interval_s = float(interval_s)
        self.burst = int(burst)
        self._tokens = float(burst)
        self._t: float | None = None
        self._burst_until: float | None = None  # set by the first request

    def _refill(self, now: float) -> None:
        if self._t is None or now < self._t:  # first call, or the clock went back: no credit
            self._t = now
            return
        # what is left of the start-up burst is kept until it expires; refilling never goes above one token
        if self._burst_until is not None and now >= self._burst_until:
            self._tokens = min(self._tokens, 1.0)
        self._tokens = max(self._tokens, min(1.0, self._tokens + (now - self._t) / self.interval_s))
        self._t = now

    def available(self, now: float) -> bool:
        self._refill(now)
        return self._tokens >= 1.0 - 1e-9

    def take(self, now: float) -> bool:
        if not self.available(now):
            return False
        if self._burst_until is None:
            self._burst_until = now + self.burst * self.interval_s
        self._tokens -= 1.0
        return True


__all__ = ["BootClockGuard", "ClockVerdict", "SourceTable", "RequestBudget"]
