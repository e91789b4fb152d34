"""The sector log: where each published sector's claim came from (``companion run --sector-log FILE``).

One JSON object per line.  The first line is a header::

    {"sector_log": 1, "sectors": 72, "increment_deg": 5.0, "sources": {"0": "none", "1": "live", ...},
     "reasons": {"0": "none", "1": "not_seen", "2": "no_points", ...}}

then one line per OBSTACLE_DISTANCE the companion built from a result, for the outputs logged
(the autopilot's by default)::

    {"out": "autopilot", "time_usec": 1234000, "d": [65535, 812, ...], "src": "000011133300...", "fwd": [812, 255, 71],
     "why": "600000000001..."}

``time_usec`` and ``d`` are the message's own fields (exposure on the autopilot's boot clock, the
72 distances in cm, after the turn since exposure), so a reader finds the line of any
OBSTACLE_DISTANCE in a tlog by those two; ``src`` holds one digit per sector, a
:class:`~companion.core.sectors_types.SectorSource` (0 none, 1 live points, 2 live and remembered,
3 remembered only, 4 inferred across sectors, 5 inferred from points above or below the band;
docs/derivations/sectors.md, "Where a claim comes from"); ``fwd`` is the forward DISTANCE_SENSOR computed
from the same result (``current_distance`` cm, ``covariance`` cm², ``signal_quality``), whether it was sent
to the autopilot or withheld (docs/derivations/sectors.md, "The forward DISTANCE_SENSOR and the
autopilots"): a score of the forward range does not depend on which readings the autopilot was sent.
``why`` holds one hexadecimal digit per sector, an :class:`~companion.core.sectors_types.UnknownReason`:
why an unknown sector is unknown (1 not seen, 2 no tracked point, 3 points beside the band only, 4 too
few far points for "clear", 5 "clear" vetoed, 6 still ranging, 7 too few near points, 8 partly in view,
9 "clear" held back, a turned since exposure; docs/derivations/sectors.md, "Why a sector is unknown"), 0 where
the sector claims.  Logs written before it have no ``why``; readers skip what they do not know.

About 0.4 kB a line: at 15 Hz some 20 MB an hour.  A write that fails (disk full, a vanished
mount) is logged once and ends the log; the companion flies on.  I/O only: the sources themselves
are :meth:`companion.core.sectors_types.Sectors.sources`.
"""

from __future__ import annotations

import json
from typing import NamedTuple

import numpy as np

from companion.core.sectors_types import SECTOR_COUNT, SECTOR_DEG, SectorSource, UnknownReason
from companion.errors import InputError
from companion.jsonl_log import JsonlLog

FORMAT_VERSION = 1


class SectorLog(JsonlLog):
    """Writes the sector log (module docstring); call it as the reporter's ``sector_sink``."""

    NAME = "sector log"
    OPTION = "--sector-log"

    def __init__(self, path, outputs=("autopilot",)):
        self.outputs = tuple(outputs)
        super().__init__(path, {"sector_log": FORMAT_VERSION, "sectors": SECTOR_COUNT, "increment_deg": SECTOR_DEG,
                                "sources": {str(int(s)): s.name.lower() for s in SectorSource},
                                "reasons": {format(int(r), "x"): r.name.lower() for r in UnknownReason}})

    def __call__(self, out: str, time_usec: int, distances_cm, sources, forward=None, reasons=None) -> None:
        if not self.open or out not in self.outputs:
            return
        d = np.asarray(distances_cm).astype(np.int64).reshape(-1)
        src = np.asarray(sources).astype(np.int64).reshape(-1)
        rec = {"out": out, "time_usec": int(time_usec), "d": d.tolist(), "src": "".join(str(int(v)) for v in src)}
        if forward is not None:
            rec["fwd"] = [int(v) for v in forward]
        if reasons is not None:
            rec["why"] = "".join(format(int(v), "x") for v in np.asarray(reasons).astype(np.int64).reshape(-1))
        self.write(rec)


def _records(path, output: str):
    """The JSON objects of ``output``'s lines after a valid header (a line cut short is skipped); a file
    that is not a sector log raises :class:`~companion.errors.InputError`."""
    with open(path, encoding="ascii", errors="replace") as fh:
        head = fh.readline()
        try:
            h = json.loads(head)
        except json.JSONDecodeError:
            h = None
        if not isinstance(h, dict) or h.get("sector_log") != FORMAT_VERSION:
            raise InputError(f"{path}: not a sector log (version {FORMAT_VERSION} header expected)")
        for line in fh:
            try:
                r = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(r, dict) and r.get("out") == output:
                yield r


def _digits(text, top: int) -> np.ndarray | None:
    """A per-sector digit string (hexadecimal digits 0…``top``) as (72,) int8, None when malformed."""
    if not isinstance(text, str):
        return None
    try:
        c = np.frombuffer(text.encode("ascii"), np.uint8).astype(np.int16)
    except UnicodeEncodeError:
        return None
    row = np.where(c >= ord("a"), c - (ord("a") - 10), np.where(c <= ord("9"), c - ord("0"), -1)).astype(np.int8)
    return row if row.shape == (SECTOR_COUNT,) and not np.any((row < 0) | (row > top)) else None


class SectorLogLines(NamedTuple):
    """The fields of a sector log's lines for one output, each keyed by ``(time_usec, distances as uint16 bytes)``:
    ``sources`` (72,) int8 :class:`SectorSource`, ``forward`` ``(current_distance cm, covariance cm², signal_quality)``,
    ``reasons`` (72,) int8 :class:`UnknownReason`; a line that lacks a field, or whose field is malformed, is
    missing from that field's dict only."""

    sources: dict
    forward: dict
    reasons: dict


def read_sector_lines(path, output: str = "autopilot") -> SectorLogLines:
    """Every field of ``output``'s lines in one pass over the file (:class:`SectorLogLines`).  A line cut short (a
    companion killed mid-write) is skipped; a file that is not a sector log raises
    :class:`~companion.errors.InputError`."""
    out = SectorLogLines({}, {}, {})
    top_src, top_why = max(SectorSource), max(UnknownReason)
    for r in _records(path, output):
        try:
            d = np.asarray(r["d"], np.int64)
            key = (int(r["time_usec"]), d.astype(np.uint16).tobytes())
        except (KeyError, TypeError, ValueError, AttributeError):
            continue
        if d.shape != (SECTOR_COUNT,):
            continue
        if (src := _digits(r.get("src"), top_src)) is not None:
            out.sources[key] = src
        if (why := _digits(r.get("why"), top_why)) is not None:
            out.reasons[key] = why
        try:
            cm, cov, q = (int(v) for v in r["fwd"])
        except (KeyError, TypeError, ValueError):
            continue
        if 0 <= cm <= 65535 and 0 <= cov <= 255 and 0 <= q <= 100:
            out.forward[key] = (cm, cov, q)
    return out


def read_sector_log(path, output: str = "autopilot") -> dict[tuple[int, bytes], np.ndarray]:
    """The lines of ``output`` in a sector log, keyed by ``(time_usec, distances as uint16 bytes)``
    → the (72,) int8 sources (:func:`read_sector_lines`)."""
    return read_sector_lines(path, output).sources


def read_sector_reasons(path, output: str = "autopilot") -> dict[tuple[int, bytes], np.ndarray]:
    """The reasons of ``output``'s lines (those that carry ``why``), keyed like :func:`read_sector_log`
    → the (72,) int8 :class:`~companion.core.sectors_types.UnknownReason` of each sector (0 where it claims)."""
    return read_sector_lines(path, output).reasons


def read_sector_forward(path, output: str = "autopilot") -> dict[tuple[int, bytes], tuple[int, int, int]]:
    """The forward readings of ``output``'s lines (those that carry ``fwd``), keyed like
    :func:`read_sector_log` → ``(current_distance cm, covariance cm², signal_quality)``."""
    return read_sector_lines(path, output).forward


__all__ = ["FORMAT_VERSION", "SectorLog", "SectorLogLines", "read_sector_forward", "read_sector_lines", "read_sector_log",
           "read_sector_reasons"]
