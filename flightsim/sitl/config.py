"""Settings and failure of a SITL run: :class:`SitlConfig`, :class:`SitlError`, the two clocks (:data:`CLOCKS`)."""

from __future__ import annotations

import dataclasses

from companion.config import require, require_finite
from companion.errors import CompanionError
from flightsim.hostile import HostileConfig

CLOCKS = ("lockstep", "realtime")


@dataclasses.dataclass(frozen=True)
class SitlConfig:
    """Settings of a SITL run (defaults suit CI and the benchmark)."""

    processing_ms: float = 25.0  # lockstep: the companion's simulated compute time per frame (--sim-processing-ms), ms; its log reports the measured "ms per round"
    frame_latency_s: float = 0.0  # a frame leaves at least this long after its capture, s
    frame_wait_max_s: float = 0.1  # ... and at most this long, even if the ATTITUDE that brackets it has not been sent, s
    connect_timeout_s: float = 60.0  # the companion must connect to the frame transport within this long (wall), s
    compile_timeout_s: float = 1200.0  # ... not counting a first start's kernel compilation, up to this long (wall), s
    ack_timeout_s: float = 30.0  # lockstep: a frame not acknowledged within this long (wall) is a failure, s
    stop_timeout_s: float = 5.0  # SIGTERM, then SIGKILL after this long (wall), s
    tail_s: float = 0.5  # realtime: keep listening this long (wall) after the flight for the last messages, s
    build_ahead: bool = True  # lockstep: build the telemetry of the steps ahead while the companion works (same messages; False = step by step, for tests)
    hostile: HostileConfig = HostileConfig()  # hostile traffic and telemetry blackouts (flightsim/hostile.py; off by default)
    rss_sample_s: float = 0.0  # sample the companion's resident set (/proc/PID/status VmRSS) every this many simulated seconds; 0 = off
    landmark_log: bool = False  # the companion also writes its landmark log, landmarks.jsonl (companion run --landmark-log; ~15 MB a minute)

    def __post_init__(self) -> None:
        require_finite("processing_ms", self.processing_ms, nonnegative=True)
        require(self.processing_ms < 10_000, "processing_ms must be < 10000")
        require_finite("frame_latency_s", self.frame_latency_s, nonnegative=True)
        require_finite("frame_wait_max_s", self.frame_wait_max_s, nonnegative=True)
        require(self.frame_wait_max_s >= self.frame_latency_s, "frame_wait_max_s must be >= frame_latency_s")
        for name in ("connect_timeout_s", "compile_timeout_s", "ack_timeout_s", "stop_timeout_s"):
            require_finite(name, getattr(self, name), positive=True)
        require_finite("tail_s", self.tail_s, nonnegative=True)
        require(isinstance(self.hostile, HostileConfig), "hostile must be a HostileConfig")
        require_finite("rss_sample_s", self.rss_sample_s, nonnegative=True)
        require(isinstance(self.landmark_log, bool), "landmark_log must be true or false")


class SitlError(CompanionError, RuntimeError):
    """The run failed (companion crashed, never connected, stopped answering); the message names the log.

    ``partial``: what the run had measured until then (set by :func:`run_sitl`: simulation time
    reached, hostile traffic counts, the companion's RSS samples, its exit code), else None."""

    partial: dict | None = None
