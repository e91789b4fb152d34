"""The companion's clock in lockstep with a simulator: ``companion run --clock sim``.

In a lockstep software-in-the-loop run (``flightsim sitl --clock lockstep``) the simulator does
not follow the wall clock: it runs as fast as the CPU allows and waits for the companion's
acknowledgement of each camera frame (:meth:`companion.camera_sources.SimFrameServer.wait_ack`)
before it advances.  Everything in the companion that reads ``clock()`` — rate limiters,
HEARTBEAT, TIMESYNC requests, telemetry staleness, frame age, the health state — must then follow
*simulation* time, or a fast simulation would look like a frozen vehicle and a slow one like a
fast one.  :class:`SimClock` is that clock.

Definition.  The sim clock *is* the autopilot's boot clock as the companion has heard it::

    now = max(newest autopilot boot time heard, end of the companion's own work)

* *heard*: every ``time_boot_ms`` of a message from the vehicle (ATTITUDE, LOCAL_POSITION_NED,
  GLOBAL_POSITION_INT, and SYSTEM_TIME, which the simulator sends just before each frame as its
  clock tick) and the capture stamp of each frame (clock 1 of the frame transport);
* *work*: each processed frame advances the clock by its processing time — a fixed
  ``--sim-processing-ms`` (deterministic; what ``flightsim sitl`` passes) or, without it, the
  measured wall time of that frame — exactly as :mod:`companion.replay` stamps its messages at
  capture + processing.  A companion slower than the frame rate therefore falls behind in
  simulation time and drops stale frames, as it would on a real vehicle.

The clock never goes backwards and stands still while the companion waits for the simulator.
The offset between the companion clock and the autopilot clock is 0 by construction, so the link
uses that fixed offset (``MavLink(clock_offset_s=0.0)``) for telemetry and frame stamps; TIMESYNC
is still exchanged and its estimate logged, as a check of the transport.

Rounds.  With this clock the companion runs in *rounds*, one per frame
(:meth:`companion.app.Companion.step_lockstep`): wait for a frame → poll the MAVLink link
(everything the simulator sent before the frame is there) → process → publish → periodic duties
→ acknowledge the frame.  Nothing is sent between rounds, so a lockstep run is deterministic in
simulation time: the same flight gives the same messages at the same simulated instants.

Pure (no I/O): the wall clock is only read to measure processing when no fixed time is given.
"""

from __future__ import annotations

import math

from companion.config import require


class SimClock:
    """``clock()`` for ``companion run --clock sim`` (see the module docstring).

    ``processing_s``: fixed simulated processing time per frame (None = use the measured one).
    """

    def __init__(self, processing_s: float | None = None):
        if processing_s is not None:
            require(isinstance(processing_s, (int, float)) and math.isfinite(processing_s) and processing_s >= 0,
                    f"processing time must be a finite number >= 0 s, got {processing_s!r}")
        self.processing_s = None if processing_s is None else float(processing_s)
        self._heard: float | None = None
        self._busy = -math.inf
        self.observations = 0

    @property
    def started(self) -> bool:
        """Something from the simulator has been heard (before that the clock reads 0)."""
        return self._heard is not None

    def observe(self, t_boot_s: float) -> None:
        """The autopilot's boot clock read ``t_boot_s`` (a message stamp, a frame's capture time)."""
        try:
            t = float(t_boot_s)
        except (TypeError, ValueError):
            return
        if not math.isfinite(t) or t < 0:
            return
        self.observations += 1
        if self._heard is None or t > self._heard:
            self._heard = t

    def work(self, measured_s: float) -> float:
        """The frame in hand was processed (``measured_s`` of wall time): advance; returns the step."""
        dt = self.processing_s if self.processing_s is not None else max(0.0, float(measured_s))
        if not math.isfinite(dt):
            dt = 0.0
        self._busy = self() + dt
        return dt

    def __call__(self) -> float:
        heard = 0.0 if self._heard is None else self._heard
        return max(heard, self._busy)


__all__ = ["SimClock"]
