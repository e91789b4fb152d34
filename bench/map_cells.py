"""What the local obstacle map held where an obstacle out of view was reported unknown (issue 11).

``python -m bench map_cells DIR… [--within M] [--band M] [--json]``

The sector log says a remembered obstacle's sector was "not seen" (docs/derivations/sectors.md, "Why a sector is
unknown": no map point was published there); this looks into the map.  DIR is a ``flightsim sitl … --landmark-log``
output, or a SITL campaign flown with ``--landmark-log`` (all its runs): its landmark log carries the map's remembered
points per frame (:mod:`companion.landmark_log`), its sector log the distances each OBSTACLE_DISTANCE sent, its
``truth.npz`` the true distance of every sector and which ones the camera saw.

For each message, each sector out of the camera's view whose true obstacle lies within ``--within`` metres
(default 10) is counted: claimed (a range or "clear"), or unknown, then split by the map's remembered points in that
sector as the truth places the vehicle (bearing from the true heading, height against the true altitude):

* **no map point** in the sector at any height;
* **off the band only**: map points there, none within ``--band`` (default 1.5 m, ``[sectors] band_half_height_m``)
  of the vehicle's height;
* **withheld**: map points in the band, none handed to the sectors (no ``[map] min_support``);
* **published**: a published map point in the band, and still unknown (a sector rule dropped it: its bearing
  spread, or a range beyond ``max_distance``).

The message's distances are taken as sent (turned to the send time, a few degrees at most while turning), the truth
and the map at its exposure.  Nothing is flown.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from bench.report import landmark_run_parser, run_dirs
from flightsim.score.evaluation import sector_of

COMMAND = "python -m bench map_cells"
KINDS = ("claimed", "no_map_point", "off_band_only", "withheld", "published")
UNKNOWN_CM = 65535


def classify(p_vehicle: np.ndarray, yaw: float, map_p: np.ndarray, map_published: np.ndarray, sectors: np.ndarray,
             band_m: float) -> np.ndarray:
    """(len(sectors),) index into :data:`KINDS` (1…4: the unknown kinds) of what the map holds in each sector for a
    vehicle at ``p_vehicle`` (NED) heading ``yaw`` (rad): no point, off the band only, in the band but withheld, or
    in the band and published."""
    sectors = np.asarray(sectors, np.int64)
    out = np.full(len(sectors), KINDS.index("no_map_point"), np.int64)
    if len(map_p) == 0 or len(sectors) == 0:
        return out
    d = np.asarray(map_p, float) - np.asarray(p_vehicle, float)
    sec = sector_of(d[:, 0], d[:, 1], np.full(len(d), float(yaw)))  # the scorer's own sector of a world direction
    band = np.abs(d[:, 2]) <= band_m
    pub = np.asarray(map_published, bool)
    any_pt = np.bincount(sec, minlength=72) > 0
    in_band = np.bincount(sec[band], minlength=72) > 0
    published = np.bincount(sec[band & pub], minlength=72) > 0
    out[any_pt[sectors]] = KINDS.index("off_band_only")
    out[in_band[sectors]] = KINDS.index("withheld")
    out[published[sectors]] = KINDS.index("published")
    return out


def analyse_run(run_dir: Path, within_m: float = 10.0, band_m: float = 1.5, scenario: str | None = None) -> dict:
    """Counts of :data:`KINDS` over one run's messages (module docstring); ``frames_without_map`` counts the messages
    whose landmark-log frame carries no map points field (a log written before them, or no map)."""
    from companion.sector_log import read_sector_log
    from flightsim.score.files import SECTOR_LOG
    from flightsim.score.landmarks import load_run

    frames, t_truth, _, _, _ = load_run(run_dir, scenario)
    tr = np.load(Path(run_dir) / "truth.npz")
    sec_all, in_view, p_ned, yaw = tr["sector_all_m"], tr["in_view"], tr["p_ned"], tr["rpy"][:, 2]
    t_log = np.array([f["t"] for f in frames])
    counts = dict.fromkeys(KINDS, 0) | {"messages": 0, "messages_matched": 0, "frames_without_map": 0}
    for time_usec, d_bytes in read_sector_log(Path(run_dir) / SECTOR_LOG):
        counts["messages"] += 1
        t = time_usec / 1e6
        i = int(np.argmin(np.abs(t_log - t))) if len(t_log) else -1
        k = int(np.argmin(np.abs(t_truth - t))) if len(t_truth) else -1
        if i < 0 or k < 0 or abs(t_log[i] - t) > 2e-3 or abs(t_truth[k] - t) > 0.05:
            continue
        counts["messages_matched"] += 1
        d = np.frombuffer(d_bytes, np.uint16)
        cells = np.flatnonzero(~in_view[k] & np.isfinite(sec_all[k]) & (sec_all[k] <= within_m))
        unknown = cells[d[cells] == UNKNOWN_CM]
        counts["claimed"] += len(cells) - len(unknown)
        f = frames[i]
        if "map_p_world" not in f:
            counts["frames_without_map"] += 1
            continue
        kinds = classify(p_ned[k], float(yaw[k]), f["map_p_world"], f["map_published"], unknown, band_m)
        for j, name in enumerate(KINDS):
            if j:
                counts[name] += int(np.count_nonzero(kinds == j))
    return counts


def markdown(results: list[tuple[str, int, dict]], within_m: float, band_m: float) -> str:
    L = [f"Out-of-view obstacle cells within {within_m:g} m (truth), by what the map held in their sector when unknown "
         f"(band ± {band_m:g} m):", "",
         "| run | runs | messages (matched) | cells | claimed | unknown: no map point | off the band only | withheld | published |",
         "|---|---|---|---|---|---|---|---|---|"]
    for label, n, c in results:
        cells = sum(c[k] for k in KINDS)
        pc = lambda v: "–" if not cells else f"{100.0 * v / cells:.1f} %"  # noqa: E731
        L.append(f"| {label} | {n} | {c['messages']} ({c['messages_matched']}) | {cells} | "
                 + " | ".join(pc(c[k]) for k in KINDS) + " |")
    missing = [label for label, _, c in results if c["frames_without_map"]]
    if missing:
        L += ["", f"(messages whose landmark-log frame has no map points, not split: {', '.join(missing)})"]
    return "\n".join(L)


def main(argv=None) -> int:
    ap = landmark_run_parser(COMMAND, __doc__)
    ap.add_argument("--within", type=float, default=10.0, metavar="M", help="true distance of the cells counted, m (default 10)")
    ap.add_argument("--band", type=float, default=1.5, metavar="M",
                    help="half height of the band around the vehicle, m (default 1.5, [sectors] band_half_height_m)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of the table")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.within) and args.within > 0 and math.isfinite(args.band) and args.band > 0):
        ap.error("--within and --band must be positive numbers")
    from companion.errors import CompanionError

    results = []
    try:
        for d in map(Path, args.runs):
            dirs = run_dirs(d)
            total: dict = {}
            for r in dirs:
                for k, v in analyse_run(r, args.within, args.band, args.scenario).items():
                    total[k] = total.get(k, 0) + v
            if not dirs:
                raise FileNotFoundError(f"{d}: no runs")
            results.append((d.name, len(dirs), total))
    except (CompanionError, OSError, KeyError, json.JSONDecodeError) as e:
        print(f"{COMMAND}: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps([{"run": label, "runs": n, **c} for label, n, c in results], indent=1))
    else:
        print(markdown(results, args.within, args.band))
    return 0


if __name__ == "__main__":
    sys.exit(main())
