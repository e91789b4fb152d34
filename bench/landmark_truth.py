"""Each landmark's range and σ against the truth, on a SITL flight with a landmark log (issue 15).

``python -m bench landmark_truth DIR… [--young S] [--axis DEG] [--bins 0,3,5,8,12,20,40] [--json]``

The scorer judges the *published* sector values; this looks one level down, at what the estimator
believed about each landmark.  DIR is the output of ``flightsim sitl … --landmark-log`` (it holds
``landmarks.jsonl``, ``truth.npz`` and ``sitl.json``), or a campaign flown with ``flightsim campaign … --mode sitl
--landmark-log`` (all its runs pooled).  For every converged, valid landmark of every
logged frame, the landmark's measured ray (from the logged, i.e. the telemetry's, camera pose to its
logged point) is turned into the camera frame and cast from the *true* camera pose into the scenario's
world (``World.raycast``); where it hits something within 100 m, the distance to the hit is the
landmark's true range, and z = (range − true range) / σ.  Reported per true-range bin: the number of
samples, mean and median z, NEES (mean z², 1 when σ is honest), the share within ±2σ and the shares
beyond +3σ (long) and −3σ (short).  The samples of one landmark in consecutive frames are strongly
correlated: read the counts as frames, not as independent draws.

``--unconverged`` takes the valid landmarks not yet converged instead (the points behind a sector whose reason
for being unknown is "ranging"; docs/derivations/sectors.md, "Why a sector is unknown"); the last two columns, the
median σ / range and the median |range − true range| / true range, say how far they are from converging and how
good their estimates already are.  ``--young S`` keeps only landmarks first logged less than S seconds before the frame (new points,
not tracks carried since take-off); ``--axis DEG`` only those within DEG of the camera's optical axis
(the direction of travel on a straight approach).  docs/BENCHMARKS.md, "Why the pole ahead was ranged
long", measured the same thing with a hook, before this tool existed.  The computation is
:mod:`flightsim.score.landmarks` (campaign reports use it too); this is its command line.
"""

from __future__ import annotations

import json
import sys

import numpy as np

from bench.report import landmark_run_parser, run_dirs
from flightsim.score.landmarks import DEFAULT_BINS, landmark_z, load_run, markdown, summarize

COMMAND = "python -m bench landmark_truth"


def main(argv=None) -> int:
    ap = landmark_run_parser(COMMAND, __doc__)
    ap.add_argument("--young", type=float, metavar="S", help="only landmarks first logged less than S seconds before the frame")
    ap.add_argument("--axis", type=float, metavar="DEG", help="only landmarks within DEG of the optical axis")
    ap.add_argument("--unconverged", action="store_true",
                    help="the landmarks not yet converged instead of the converged ones (what a sector reads as \"ranging\")")
    ap.add_argument("--bins", default=",".join(f"{b:g}" for b in DEFAULT_BINS), help="true-range bin edges, m")
    ap.add_argument("--json", action="store_true", help="print JSON instead of the table")
    args = ap.parse_args(argv)
    try:
        bins = tuple(float(b) for b in args.bins.split(","))
    except ValueError:
        ap.error(f"--bins: comma-separated numbers, got {args.bins!r}")
    if len(bins) < 2 or any(b >= c for b, c in zip(bins, bins[1:])):
        ap.error("--bins: at least two increasing edges")
    from companion.errors import CompanionError

    dirs = [r for d in args.runs for r in run_dirs(d)]  # a campaign directory stands for its runs
    samples = []
    try:
        for d in dirs:
            frames, t, R, p, raycast = load_run(d, args.scenario)
            samples.append(landmark_z(frames, t, R, p, raycast, young_s=args.young, axis_deg=args.axis,
                                      converged=not args.unconverged))
    except (CompanionError, OSError, KeyError, json.JSONDecodeError) as e:
        print(f"{COMMAND}: {e}", file=sys.stderr)
        return 2
    rows = summarize(np.concatenate(samples), bins)
    print(json.dumps(rows, indent=1) if args.json else markdown(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
