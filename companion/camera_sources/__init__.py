"""Camera sources: grey frames with their capture time on the companion's clock (frames: docs/derivations/frames.md).

Every source is a :class:`FrameSource`.  It hands out :class:`Frame` tuples ``(index, t, gray)``:

* ``index`` — the source's own frame counter (strictly increasing; a gap means frames were lost
  or dropped before the pipeline saw them);
* ``t`` — the capture (mid-exposure) time in seconds on the companion's monotonic clock, the clock
  the MAVLink link maps the autopilot's ``time_boot_ms`` onto through TIMESYNC (for
  :class:`RecordedSource`: the recording's clock, which its tlog shares);
* ``gray`` — a C-contiguous ``uint8`` array of the configured ``height × width``.

A live source never queues: :meth:`FrameSource.read` returns the newest frame not yet returned
and counts the older ones it skipped as ``dropped`` (a late frame is worth less than a fresh one,
docs/derivations/sectors.md).  Corrupt, empty or wrongly sized images are rejected and counted by reason in
:attr:`SourceStatus.rejected`, never raised.  Live sources that stop delivering are reopened with
exponential backoff; :meth:`FrameSource.drain_events` reports "camera lost" / "camera restored"
for STATUSTEXT.

Layers (each module imports only the ones above it; this package's names are re-exported here)
---------------------------------------------------------------------------------------------
:mod:`.base`
    What every source shares: the ``[camera_source]`` table (:class:`CameraSourceConfig`),
    :class:`Frame`, :class:`SourceStatus`, :class:`SourceError`, the image check
    (:func:`check_gray`), the ``--camera`` argument parser (:func:`parse_camera_spec`) and the
    :class:`FrameSource` base class with its one-slot buffer, counters and events.
:mod:`.opencv` — :class:`OpenCVSource`
    ``cv2.VideoCapture`` on a device index (``0``), a device path (``/dev/video0``), a URL
    (``rtsp://…``, ``http://…/stream.mjpg``, GStreamer builds included) or a video file.  The capture
    time is the moment ``grab()`` returned on the companion clock minus ``capture_latency_s``
    (exposure + transfer delay of the camera, measured once per camera model).  Files play either
    paced at their frame rate like a live camera (``file_pacing = "realtime"``, stamped when
    delivered) or as fast as they are read (``"fast"``, stamped with the file's own timeline from
    the moment it was opened).
:mod:`.recorded` — :class:`RecordedSource`
    A recorded flight: ``video.avi`` + ``frames.csv`` (``index,t_s``, :func:`read_frames_csv`), for replay.
:mod:`.sim_transport` — :class:`SimFrameSource` / :class:`SimFrameServer`
    The simulator's frame transport over TCP on loopback, ``sim://127.0.0.1:5600`` (the wire
    protocol is in that module's docstring); the server is the simulator's side (``flightsim sitl``).

:func:`open_source` (below) picks the source for a ``--camera`` argument.
"""

from __future__ import annotations

import time
from typing import Callable

from companion.camera_sources.base import (
    CameraSourceConfig,
    Frame,
    FrameSource,
    SourceError,
    SourceStatus,
    check_gray,
    parse_camera_spec,
)
from companion.camera_sources.opencv import OpenCVSource
from companion.camera_sources.recorded import RecordedSource, read_frames_csv
from companion.camera_sources.sim_transport import (
    ACK_DROPPED,
    ACK_PROCESSED,
    ACK_REJECTED,
    CLOCK_AUTOPILOT_BOOT,
    CLOCK_HOST_MONOTONIC,
    SimFrameServer,
    SimFrameSource,
    pack_sim_header,
)


# ---------------------------------------------------------------------- factory ---------------
def open_source(spec: str, width: int, height: int, config: CameraSourceConfig = CameraSourceConfig(),
                clock: Callable[[], float] = time.monotonic,
                clock_map: Callable[[float], float | None] | None = None) -> FrameSource:
    """The source for a ``--camera`` argument (device index, /dev/videoN, URL, file, sim://HOST:PORT)."""
    kind, _ = parse_camera_spec(spec)
    if kind == "sim":
        return SimFrameSource(spec, width, height, config, clock=clock, clock_map=clock_map)
    return OpenCVSource(spec, width, height, config, clock=clock)


__all__ = [
    "CameraSourceConfig", "Frame", "FrameSource", "SourceStatus", "SourceError", "OpenCVSource", "RecordedSource",
    "SimFrameSource", "SimFrameServer", "open_source", "parse_camera_spec", "check_gray", "read_frames_csv",
    "pack_sim_header", "CLOCK_AUTOPILOT_BOOT", "CLOCK_HOST_MONOTONIC", "ACK_PROCESSED", "ACK_DROPPED", "ACK_REJECTED",
]
