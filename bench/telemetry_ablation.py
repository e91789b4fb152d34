"""Which telemetry error makes the published σ over-confident?  SITL campaigns of a scenario flown
as it is and with parts of the simulated telemetry error switched off.

The anchored EKF models the gyro bias with states and the position error as white noise
(docs/derivations/ekf_anchored.md, "Measurement noise"); the simulator's position error is
Gauss–Markov (correlated over ``position_noise_tau_s``).  If the white model were what makes the
forward σ over-confident in flight, removing the position error from the telemetry would bring the
forward NEES into its band and the ±2σ coverage near 95 %; if it barely moves, the cause lies
elsewhere (the vision side: occlusion-edge tracks, mismatches).  Variants (each a copy of the
scenario with its ``[telemetry]`` keys replaced, written to the campaign's directory):

* ``as flown``: the scenario unchanged;
* ``no position error``: ``position_noise_m`` = ``velocity_noise_mps`` = 0;
* ``no attitude error``: ``gyro_bias_deg_s`` = ``gyro_noise_deg_s`` = ``attitude_noise_deg`` = 0;
* ``exact telemetry``: both.

The companion runs its usual configuration (the scenario's ``companion_config``, else
configs/companion.toml): this measures the world, not a retuned filter.  Seeds are the scenario's
own (the same flights in every variant, up to the telemetry error).

    python -m bench.telemetry_ablation --runs 8 --scenarios quad_approach
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "configs" / "scenarios"
OUT = ROOT / "out" / "bench" / "telemetry_ablation"

#: variant name → the [telemetry] keys it sets
VARIANTS: dict[str, dict[str, float]] = {
    "as flown": {},
    "no position error": {"position_noise_m": 0.0, "velocity_noise_mps": 0.0},
    "no attitude error": {"gyro_bias_deg_s": 0.0, "gyro_noise_deg_s": 0.0, "attitude_noise_deg": 0.0},
    "exact telemetry": {"position_noise_m": 0.0, "velocity_noise_mps": 0.0, "gyro_bias_deg_s": 0.0, "gyro_noise_deg_s": 0.0,
                        "attitude_noise_deg": 0.0},
}


def variant_text(text: str, keys: dict[str, float], src: Path) -> str:
    """The scenario TOML ``text`` (read from ``src``) with its paths made absolute and the ``[telemetry]``
    keys set: an existing ``key = …`` line of that table is replaced, a missing key added after its header."""
    from flightsim.scenario import set_path_key

    for path_key in ("world", "companion_config"):
        value = set_path_key(text, path_key, "")[1]
        if value:
            text, _ = set_path_key(text, path_key, (src.parent / value).resolve().as_posix())
    head = re.search(r"^\[telemetry\][^\n]*\n", text, re.M)
    if head is None:
        text += "\n[telemetry]\n"
        head = re.search(r"^\[telemetry\][^\n]*\n", text, re.M)
    nxt = re.search(r"^\[", text[head.end():], re.M)
    end = head.end() + (nxt.start() if nxt else len(text) - head.end())
    body = text[head.end():end]
    for key, value in keys.items():
        line = f"{key} = {value!r}  # telemetry ablation (bench.telemetry_ablation)"
        body, n = re.subn(rf"^{re.escape(key)}\s*=.*$", line, body, count=1, flags=re.M)
        if n == 0:
            body = line + "\n" + body
    return text[:head.end()] + body + text[end:]


def run(scenario: str = "quad_approach", runs: int = 8, workers: int = 2, variants=None) -> dict:
    """Campaigns of every variant of ``configs/scenarios/<scenario>.toml``; their pooled forward NEES,
    ±σ / ±2σ coverage, detection and too-near shares."""
    from flightsim.campaign import run_campaign
    from flightsim.scenario import default_companion_config

    src = SCEN / f"{scenario}.toml"
    companion = default_companion_config(src)
    out = {}
    for name in variants or VARIANTS:
        d = OUT / scenario / name.replace(" ", "_")
        d.mkdir(parents=True, exist_ok=True)
        path = d / f"{scenario}.toml"
        path.write_text(variant_text(src.read_text(encoding="utf-8"), VARIANTS[name], src), encoding="utf-8")
        c = run_campaign(path, d / "campaign", runs=runs, workers=workers, mode="sitl", companion_config=companion)
        a = c.get("aggregate", {})
        nees = a.get("nees", {})
        targets = {t.get("key"): t.get("pooled") for t in a.get("targets", [])}
        rates = a.get("pooled_rates", {})
        out[name] = {"keys": VARIANTS[name], "runs_ok": a.get("runs_ok"), "nees": nees.get("mean"), "n_eff": nees.get("n_eff"),
                     "band": nees.get("band"), "consistent": nees.get("consistent"),
                     "coverage_1sigma": (nees.get("coverage") or {}).get("rate_1sigma"),
                     "coverage_2sigma": (nees.get("coverage") or {}).get("rate_2sigma"),
                     "detection_in_view": targets.get("detection_in_view"), "too_near": rates.get("too_near"),
                     "valid_range": rates.get("valid_range")}
    return out


def markdown(scenario: str, res: dict) -> str:
    def pct(v):
        return "–" if v is None else f"{100 * v:.1f} %"

    def num(v):
        return "–" if v is None else f"{v:.2f}"

    lines = [f"| {scenario}: telemetry | runs ok | forward NEES (n_eff; band) | truth within ±σ / ±2σ | detection in view | too near | valid range |",
             "|---|---|---|---|---|---|---|"]
    for name, r in res.items():
        band = r.get("band") or [None, None]
        ok = {True: " ✓", False: " ✗"}.get(r.get("consistent"), "")
        lines.append(f"| {name} | {r.get('runs_ok')} | {num(r['nees'])} ({num(r['n_eff'])}; {num(band[0])}–{num(band[1])}{ok}) | "
                     f"{pct(r['coverage_1sigma'])} / {pct(r['coverage_2sigma'])} | {pct(r['detection_in_view'])} | "
                     f"{pct(r['too_near'])} | {pct(r['valid_range'])} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.telemetry_ablation", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=8, help="seeds per variant (default 8)")
    ap.add_argument("--workers", type=int, default=2, help="worker processes per campaign (default 2)")
    ap.add_argument("--scenarios", default="quad_approach", help="comma-separated scenarios of configs/scenarios (default quad_approach)")
    ap.add_argument("--variants", default=None, help=f"comma-separated subset of: {', '.join(VARIANTS)}")
    ap.add_argument("--json", action="store_true", help="print JSON instead of the tables")
    args = ap.parse_args(argv)
    variants = [v.strip() for v in args.variants.split(",")] if args.variants else None
    unknown = [v for v in variants or [] if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {', '.join(unknown)}; known: {', '.join(VARIANTS)}")
    if args.runs < 1:
        ap.error("--runs must be >= 1")
    res = {}
    for s in [s.strip() for s in args.scenarios.split(",") if s.strip()]:
        if not (SCEN / f"{s}.toml").is_file():
            ap.error(f"no scenario {s!r} in {SCEN}")
        res[s] = run(s, args.runs, args.workers, variants)
        if not args.json:
            print(markdown(s, res[s]), flush=True)
            print()
    if args.json:
        print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
