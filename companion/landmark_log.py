"""The landmark log: every landmark the estimator holds, frame by frame (``companion run --landmark-log FILE``).

The sector log (:mod:`companion.sector_log`) says where each published sector came from; this one
says what the estimator believed about each landmark when it did: the question behind most "why did it
say 4 m?" investigations (docs/BENCHMARKS.md, "Why the pole ahead was ranged long", was done with an
external hook that wrote the same thing).

One JSON object per line.  The first line is a header::

    {"landmark_log": 1, "frame": "world NED, metres; camera pose R_world_cam row-major", ...}

then one line per processed frame::

    {"t": 31.2, "p_world_cam": [x, y, z], "R_world_cam": [9 values], "ids": [...],
     "p_world": [[x, y, z], ...], "range": [...], "range_sigma": [...], "mean_nis": [...],
     "converged": "0110...", "valid": "1111...", "scale": [...], "scale_sigma": [...]}

With the local obstacle map on, each line also carries the map's *remembered* points (those whose landmark is no
longer tracked) as the sectors saw them in that frame::

     "map_p_world": [[x, y, z], ...], "map_published": "1101...", "map_age": [...]

``map_published`` says whether a point was handed to the sectors (1) or withheld (0: no ``min_support``),
``map_age`` the time since it was last observed, s (docs/derivations/obstacle_map.md).  ``python -m bench
map_cells`` reads them: what the map held where a remembered obstacle was reported unknown.

``t`` is the frame's capture time on the companion clock; ``p_world`` is each landmark's point on
the ray measured in this frame (where the map and the sectors take it from,
:func:`companion.core.obstacle_map.points_on_current_rays`), ``range`` and ``range_sigma`` the
estimator's (m), ``mean_nis`` its filter's mean NIS (NaN before any update), ``scale`` and ``scale_sigma`` the
patch scale change the tracker measured between the previous frame and this one (looming, DESIGN §7; null where
none was measured: not fitted within ``[ncc] max_scale_points``, or not measurable; both fields absent from logs
written before they existed).  Positions are rounded to
the millimetre, ranges and σ to the millimetre, NIS to 0.01.

Size: ~60 B per landmark, so ~15 MB a minute with 300 landmarks at 15 Hz (~1 GB an hour), and ~33 B per remembered
map point (quad_corner, 115 landmarks and 310 map points a frame at 30 Hz: 11.5 MB in 21 s); CPU: ~7 µs per
landmark and frame (the slalom's SITL, ~85 landmarks: 0.6 ms a frame, outside the pipeline's stage timings).  A
tool for a flight that needs explaining, not for every flight.  A write that fails is logged once and ends the log; the
companion flies on.  I/O only.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from companion.errors import InputError
from companion.jsonl_log import JsonlLog

FORMAT_VERSION = 1


def _rounded(a, digits: int) -> list:
    """A list of floats rounded to ``digits``, NaN and ±inf written as null (JSON has neither)."""
    a = np.round(np.asarray(a, float), digits)
    if a.ndim > 1:
        return [_rounded(row, digits) for row in a]
    return [v if math.isfinite(v) else None for v in a.reshape(-1).tolist()]


class LandmarkLog(JsonlLog):
    """Writes the landmark log (module docstring); the pipeline calls it once per processed frame as its
    ``landmark_sink`` with (t, R_world_cam, p_world_cam, the estimator's RangeOutput, points on current rays)."""

    NAME = "landmark log"
    OPTION = "--landmark-log"

    def __init__(self, path):
        super().__init__(path, {"landmark_log": FORMAT_VERSION, "frame": "world NED, metres; camera pose R_world_cam row-major",
                                "fields": ["t", "p_world_cam", "R_world_cam", "ids", "p_world", "range", "range_sigma",
                                           "mean_nis", "converged", "valid", "scale", "scale_sigma", "map_p_world",
                                           "map_published", "map_age"]})

    def __call__(self, t: float, R_world_cam, p_world_cam, out, p_world, scale=None, scale_sigma=None, memory=None) -> None:
        """One frame; ``memory``: the map's remembered points as ``(p_world (M, 3), published (M,) bool, age_s (M,))``
        (None without a map)."""
        if not self.open:
            return
        n = len(out.ids)
        nis = out.mean_nis if out.mean_nis is not None else np.full(n, np.nan)
        scale = np.full(n, np.nan) if scale is None else np.asarray(scale, float).reshape(n)
        scale_sigma = np.full(n, np.nan) if scale_sigma is None else np.asarray(scale_sigma, float).reshape(n)
        extra = {}
        if memory is not None:
            mp, pub, age = memory
            mp = np.asarray(mp, float).reshape(-1, 3)
            extra = {"map_p_world": _rounded(mp, 3),
                     "map_published": "".join("1" if v else "0" for v in np.asarray(pub, bool).reshape(len(mp))),
                     "map_age": _rounded(np.asarray(age, float).reshape(len(mp)), 3)}
        self.write(extra | {
            "t": round(float(t), 6),
            "p_world_cam": _rounded(p_world_cam, 3),
            "R_world_cam": _rounded(np.asarray(R_world_cam, float).reshape(-1), 7),
            "ids": np.asarray(out.ids, np.int64).tolist(),
            "p_world": _rounded(np.asarray(p_world, float).reshape(n, 3), 3),
            "range": _rounded(out.range, 3),
            "range_sigma": _rounded(out.range_sigma, 3),
            "mean_nis": _rounded(nis, 2),
            "converged": "".join("1" if c else "0" for c in np.asarray(out.converged, bool)),
            "valid": "".join("1" if v else "0" for v in np.asarray(out.valid, bool)),
            "scale": _rounded(scale, 5),
            "scale_sigma": _rounded(scale_sigma, 5),
        })


def read_landmark_log(path) -> list[dict]:
    """The frames of a landmark log, in order: dicts with the fields of the module docstring, arrays as
    numpy (``p_world`` (N, 3), ``R_world_cam`` (3, 3), ``converged`` and ``valid`` bool (N,), null → NaN).
    A truncated last line (a killed process) is skipped; anything else malformed raises InputError."""
    path = Path(path)
    frames = []
    with open(path, encoding="ascii") as fh:
        lines = fh.read().split("\n")
    if not lines or not lines[0].strip():
        raise InputError(f"{path}: empty landmark log")
    try:
        head = json.loads(lines[0])
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not a landmark log (bad header: {e})") from None
    if head.get("landmark_log") != FORMAT_VERSION:
        raise InputError(f"{path}: not a landmark log of format {FORMAT_VERSION} (header {head!r:.80})")
    cut = lines[-1] != ""  # a complete log ends with a newline; otherwise its last line was cut off by a kill
    body = lines[1:-1] if not cut else lines[1:]
    for k, s in enumerate(body):
        try:
            r = json.loads(s)
        except json.JSONDecodeError as e:
            if cut and k == len(body) - 1:
                break
            raise InputError(f"{path}: line {k + 2}: {e}") from None

        try:
            frames.append(_frame(r))
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"{path}: line {k + 2}: not a landmark-log frame ({e!r})") from None
    return frames


def _nan_for_null(v) -> np.ndarray:
    return np.asarray([np.nan if x is None else x for x in v], float)


def _frame(r: dict) -> dict:
    """One parsed line as arrays (:func:`read_landmark_log`)."""
    n = len(r["ids"])
    flags = {}
    for name in ("converged", "valid"):
        flags[name] = np.frombuffer(r[name].encode("ascii"), np.uint8) == ord("1")
        if len(flags[name]) != n:
            raise ValueError(f"{name} has {len(flags[name])} flags for {n} landmarks")
    frame = {
        "t": float(r["t"]), "p_world_cam": _nan_for_null(r["p_world_cam"]),
        "R_world_cam": _nan_for_null(r["R_world_cam"]).reshape(3, 3), "ids": np.asarray(r["ids"], np.int64),
        "p_world": np.asarray([_nan_for_null(p) for p in r["p_world"]], float).reshape(n, 3),
        "range": _nan_for_null(r["range"]), "range_sigma": _nan_for_null(r["range_sigma"]),
        "mean_nis": _nan_for_null(r["mean_nis"]), **flags,
        "scale": _nan_for_null(r["scale"]) if "scale" in r else np.full(n, np.nan),
        "scale_sigma": _nan_for_null(r["scale_sigma"]) if "scale_sigma" in r else np.full(n, np.nan),
    }
    for name in ("range", "range_sigma", "mean_nis", "scale", "scale_sigma"):
        if len(frame[name]) != n:
            raise ValueError(f"{name} has {len(frame[name])} values for {n} landmarks")
    if "map_p_world" in r:  # the map's remembered points (logs written before them, or without a map, have none)
        m = len(r["map_p_world"])
        frame["map_p_world"] = np.asarray([_nan_for_null(q) for q in r["map_p_world"]], float).reshape(m, 3)
        frame["map_published"] = np.frombuffer(r["map_published"].encode("ascii"), np.uint8) == ord("1")
        frame["map_age"] = _nan_for_null(r["map_age"])
        if len(frame["map_published"]) != m or len(frame["map_age"]) != m:
            raise ValueError(f"map_published / map_age do not match the {m} map points")
    return frame
