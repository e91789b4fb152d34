"""Reading MAVLink tlogs as ground stations write them, with a verdict on the file itself.

A tlog is a sequence of records: an 8-byte big-endian timestamp (µs since the Unix epoch) and one
packed MAVLink frame (v2: ``0xFD``, 10-byte header, payload, CRC, optional 13-byte signature; v1:
``0xFE``, 6-byte header, payload, CRC).  :func:`read_tlog` decodes every message with pymavlink's
robust parser (corrupt records are skipped and counted, never raised on) and checks the file:

* missing, a directory, empty, or not one decodable MAVLink message: :class:`TlogError`, a
  :class:`~companion.errors.ConfigError` (exit code 2 on the command line);
* cut while it was being written (the recorder died, the card was pulled, a copy stopped short):
  the records walk cleanly to a last one the file ends inside.  The complete records are read, and
  :attr:`TlogContents.truncation` says so, for the caller to warn.

Import :mod:`companion.mavlink.dialect` (MAVLink 2, ardupilotmega) before pymavlink, as here.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import mmap
import os
from pathlib import Path

from companion.mavlink.dialect import mavutil  # first: MAVLink 2 + ardupilotmega
from companion.errors import ConfigError
from companion.io.inputs import check_input_file

log = logging.getLogger(__name__)

_STAMP = 8  # bytes of the record timestamp
_V2_STX, _V1_STX = 0xFD, 0xFE
_V2_HEADER, _V1_HEADER, _CRC, _SIGNATURE = 10, 6, 2, 13
_V2_SIGNED = 0x01  # incompat_flags bit: a signature follows the CRC


class TlogError(ConfigError):
    """A tlog that cannot be used: missing, a directory, empty, unreadable or not MAVLink."""


@dataclasses.dataclass(frozen=True)
class TlogEnd:
    """Where the record framing of a tlog ends (:func:`scan_tlog_end`)."""

    size: int  # bytes in the file
    records: int  # whole records walked from the start
    complete_bytes: int  # end of the last whole record (== size for a complete file)
    framed: bool  # the framing held up to the end (False: bytes that are not a record were met first)

    @property
    def truncated_bytes(self) -> int:
        """Bytes of an incomplete last record (0 when complete, or when the framing was lost before)."""
        return self.size - self.complete_bytes if self.framed else 0


def _frame_length(data, at: int) -> int | None:
    """Length of the MAVLink frame starting at ``at`` (None: not a frame start; -1: its header is cut off)."""
    stx = data[at]
    if stx not in (_V2_STX, _V1_STX):
        return None
    if at + 3 > len(data):
        return -1
    payload = data[at + 1]
    if stx == _V1_STX:
        return _V1_HEADER + payload + _CRC
    signed = data[at + 2] & _V2_SIGNED
    return _V2_HEADER + payload + _CRC + (_SIGNATURE if signed else 0)


def scan_tlog_end(data) -> TlogEnd:
    """Walk the records of a tlog's bytes (``bytes`` or an ``mmap``) from the start: how many are
    whole and where the last ends."""
    n, at, records = len(data), 0, 0
    while at < n:
        if n - at <= _STAMP:  # the file ends inside a timestamp
            return TlogEnd(n, records, at, True)
        length = _frame_length(data, at + _STAMP)
        if length is None:
            return TlogEnd(n, records, at, False)
        if length < 0 or at + _STAMP + length > n:
            return TlogEnd(n, records, at, True)
        at += _STAMP + length
        records += 1
    return TlogEnd(n, records, n, True)


@dataclasses.dataclass
class TlogContents:
    """The decodable messages of a tlog, what was skipped, and how the file ends."""

    path: Path
    messages: list  # pymavlink messages in file order, each with a finite ``_timestamp`` (record time, s)
    counters: dict[str, int]  # messages, bad_records, bad_timestamps, parser_errors
    end: TlogEnd

    @property
    def truncation(self) -> str | None:
        """A warning naming the truncation of a file cut while being written, else None."""
        k = self.end.truncated_bytes
        if not k:
            return None
        span = self.messages[-1]._timestamp - self.messages[0]._timestamp if self.messages else 0.0
        return (f"{self.path}: truncated: the file ends inside a record ({k} bytes of it, after {self.end.records} "
                f"complete records covering {span:.2f} s); was it cut while being written? Using the complete records")


def read_tlog(path: str | os.PathLike, what: str = "tlog") -> TlogContents:
    """Every decodable message of the tlog at ``path`` (see the module docstring).

    Raises :class:`TlogError` for a missing, empty or unreadable file, or one in which no MAVLink
    message decodes.  Records the parser cannot decode (``BAD_DATA``, unknown message ids) and
    records without a finite timestamp are skipped and counted.
    """
    p = check_input_file(path, what, error=TlogError)
    try:
        with p.open("rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
            end = scan_tlog_end(data)
        conn = mavutil.mavlogfile(str(p), robust_parsing=True)  # sequential reader (not the mmap index)
    except OSError as exc:
        raise TlogError(f"{p}: cannot be read ({exc.strerror or exc})") from None
    counters: collections.Counter[str] = collections.Counter()
    messages = []
    try:
        while True:
            try:
                m = conn.recv_msg()
            except Exception as exc:  # a parser exception on garbage: count and stop at this point
                counters["parser_errors"] += 1
                log.warning("%s: parser error %r; reading stops here", p, exc)
                break
            if m is None:
                break
            typ = m.get_type()
            if typ == "BAD_DATA" or typ.startswith("UNKNOWN"):
                counters["bad_records"] += 1
                continue
            if not math.isfinite(float(getattr(m, "_timestamp", math.nan))):
                counters["bad_timestamps"] += 1
                continue
            counters["messages"] += 1
            messages.append(m)
    finally:
        try:
            conn.close()
        except Exception:
            pass
    if not messages:
        raise TlogError(f"{p}: not a MAVLink tlog: no message in its {end.size} bytes decodes "
                        "(8-byte timestamp + MAVLink frame per record expected)")
    return TlogContents(p, messages, dict(counters), end)


__all__ = ["read_tlog", "scan_tlog_end", "TlogContents", "TlogEnd", "TlogError"]
