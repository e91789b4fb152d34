"""MAVLink 2 telemetry logs (``.tlog``) as ground stations write them.

A tlog is a plain sequence of records: an 8-byte big-endian unsigned timestamp in microseconds
since the Unix epoch, then one packed MAVLink frame.  pymavlink's ``mavlink_connection(path)``
and ground-station tools read it (with MAVLink 2 enabled: import :mod:`companion.mavlink.dialect`
or set ``MAVLINK20=1`` before pymavlink).  Timestamps here are on the *recording's* clock:
``epoch_s`` + simulation time, so frames.csv and the tlog share one clock.
"""

from __future__ import annotations

import struct
from pathlib import Path

from companion.mavlink.dialect import mavlink


class TlogWriter:
    """Append messages with their recording-clock time; packs each with a per-source sequence."""

    def __init__(self, path: str | Path, epoch_s: float):
        self.path = Path(path)
        self.epoch_s = float(epoch_s)
        self._fh = self.path.open("wb")
        self._senders: dict[tuple[int, int], mavlink.MAVLink] = {}
        self.count = 0
        self._last_us = -1

    def _sender(self, sysid: int, compid: int):
        key = (sysid, compid)
        if key not in self._senders:
            self._senders[key] = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        return self._senders[key]

    def write(self, t_s: float, msg, sysid: int = 1, compid: int = 1) -> None:
        """Record ``msg`` as sent by (sysid, compid) at simulation time ``t_s``."""
        us = int(round((self.epoch_s + t_s) * 1e6))
        if us < self._last_us:
            raise ValueError(f"tlog records must be in time order ({us} µs after {self._last_us} µs)")
        self._last_us = us
        mav = self._sender(sysid, compid)
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256  # pack() alone does not advance it (MAVLink.send does): a reader would see loss
        self._fh.write(struct.pack(">Q", us) + buf)
        self.count += 1

    def write_raw(self, t_s: float, buf: bytes) -> None:
        """Record an already packed MAVLink frame (as it went over a wire) at simulation time ``t_s``."""
        us = int(round((self.epoch_s + t_s) * 1e6))
        if us < self._last_us:
            raise ValueError(f"tlog records must be in time order ({us} µs after {self._last_us} µs)")
        self._last_us = us
        self._fh.write(struct.pack(">Q", us) + bytes(buf))
        self.count += 1

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self) -> "TlogWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
