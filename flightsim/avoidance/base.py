"""The base of every avoidance model, and ``model = "none"`` (docs/derivations/sectors.md).

:class:`NoAvoidance` queues the companion's messages by their arrival time on the simulation clock
(:meth:`~NoAvoidance.receive`) and hands each to the model when it takes effect; the quad's
controller asks :meth:`~NoAvoidance.limit` every control tick.  On its own it lets the pilot's
demand pass unchanged; :class:`~flightsim.avoidance.ardupilot.ArduPilotAvoidance` and
:class:`~flightsim.avoidance.px4.PX4Avoidance` override ``_handle``, ``_has_data`` and ``_limit``.
"""

from __future__ import annotations

import heapq
import math

import numpy as np

from flightsim.avoidance.config import AvoidanceConfig


class NoAvoidance:
    """``model = "none"``: the pilot's demand passes unchanged."""

    name = "none"

    @property
    def margin_m(self) -> float:
        """Distance the model keeps from obstacles (from the vehicle's centre), m."""
        return 0.0

    def braking(self) -> tuple[float, float, float]:
        """(position gain 1/s, braking acceleration m/s², delay s) of the model's stopping curve, for
        :func:`stopping_distance` (the outcome's false-stop rule)."""
        return 1.0, math.inf, 0.0

    def __init__(self, config: AvoidanceConfig | None = None):
        self.config = config or AvoidanceConfig()
        self.counters: dict[str, int] = {"messages": 0}
        self._queue: list[tuple[float, int, object]] = []  # (arrival, order, message) not yet in effect
        self._order = 0

    def receive(self, t: float, msg) -> None:
        """A message from the companion that arrives at simulation time ``t``; it takes effect for
        every :meth:`limit` / :meth:`has_data` call at or after ``t`` (queued until then)."""
        self.counters["messages"] += 1
        heapq.heappush(self._queue, (float(t), self._order, msg))
        self._order += 1

    def _apply_due(self, t: float) -> None:
        while self._queue and self._queue[0][0] <= t:
            ta, _, msg = heapq.heappop(self._queue)
            self._handle(ta, msg)

    def _handle(self, t: float, msg) -> None:
        """Take one message into the model's state (models override)."""

    def has_data(self, t: float) -> bool:
        """The autopilot holds fresh obstacle data at ``t``."""
        self._apply_due(t)
        return self._has_data(t)

    def _has_data(self, t: float) -> bool:
        return False

    def limit(self, t: float, p_ned, v_ned, yaw: float, v_des_ned) -> tuple[float, float, float]:
        """The velocity (NED, m/s) the autopilot lets through for the pilot's demand ``v_des_ned``, with
        the vehicle at ``p_ned`` moving at ``v_ned`` on heading ``yaw`` (rad) at time ``t``."""
        self._apply_due(t)
        return self._limit(t, np.asarray(p_ned, float), np.asarray(v_ned, float), float(yaw), np.asarray(v_des_ned, float))

    def _limit(self, t, p_ned, v_ned, yaw, v_des) -> tuple[float, float, float]:
        return tuple(float(x) for x in v_des)

    def boundary_points(self, t: float) -> np.ndarray:
        """(K, 2) points (forward, right; body frame, m) of what the autopilot holds as obstacles at
        ``t`` (for plots); empty without data."""
        return np.zeros((0, 2))


__all__ = ["NoAvoidance"]
