"""Closed-loop avoidance campaigns: does a vehicle flying on the companion's ranges stop short?

Each campaign is ``flightsim campaign configs/scenarios/<scenario>.toml --avoidance MODEL --runs N``
(lockstep SITL, the companion live): the simulated autopilot's avoidance (:mod:`flightsim.avoidance`)
limits the pilot's velocity with the OBSTACLE_DISTANCE / DISTANCE_SENSOR it receives, and every run
is scored on its outcome (:mod:`flightsim.outcome`: collision, clearance where it stopped, false
stops, progress) as well as on the messages.  Scenarios (:data:`SCENARIOS`): the quad commanded
through a textured wall at 3, 6 and 10 m/s, through a 0.3 m pole and past a building corner at 3, 5
and 6 m/s (the 3 and 6 m/s ones written from the 5 m/s files, :data:`VARIANTS`), and along a slalom
line that crosses four poles.  Models: ``ardupilot`` (Copter simple avoidance,
defaults as shipped), ``px4`` (collision prevention, CP_DIST = 2 m, CP_GO_NO_DATA = 0 as shipped)
and, with ``--models``, ``px4_go_no_data`` (the same with CP_GO_NO_DATA = 1, written as a scenario variant in the
campaign's directory: what a PX4 user of a forward camera sets so that directions the sensor never
covered do not stall the vehicle).

``python -m bench avoidance --runs 20`` (in ``make bench``): the pooled table of
docs/BENCHMARKS.md — collision rate with a 95 % Wilson interval per scenario × model.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "configs" / "scenarios"
OUT = ROOT / "out" / "bench" / "avoidance"

#: scenario → what the pilot commands
SCENARIOS: dict[str, str] = {
    "quad_avoid_wall_3": "through a textured wall 50 m ahead at 3 m/s",
    "quad_avoid_wall_6": "through the wall at 6 m/s",
    "quad_avoid_wall_10": "through the wall at 10 m/s",
    "quad_avoid_pole": "through a 0.3 m pole 30 m ahead at 5 m/s",
    "quad_avoid_pole_3": "through the pole at 3 m/s",
    "quad_avoid_pole_6": "through the pole at 6 m/s",
    "quad_avoid_corner": "a straight line at 5 m/s that clips a building's corner",
    "quad_avoid_corner_3": "past the corner at 3 m/s",
    "quad_avoid_corner_6": "past the corner at 6 m/s",
    "quad_avoid_slalom": "straight along a slalom line through four poles (0.2–0.6 m) at 4 m/s",
    "quad_avoid_pass": "a route that avoids everything: past a building 5 m right and a mast 3 m left at 5 m/s",
}
#: scenarios whose route goes through nothing: flown without the companion they cannot show a collision
CLEAR_ROUTES = ("quad_avoid_pass",)
#: speed variants: scenario → (the scenario file it is written from, commanded speed m/s)
VARIANTS: dict[str, tuple[str, float]] = {
    "quad_avoid_pole_3": ("quad_avoid_pole", 3.0),
    "quad_avoid_pole_6": ("quad_avoid_pole", 6.0),
    "quad_avoid_corner_3": ("quad_avoid_corner", 3.0),
    "quad_avoid_corner_6": ("quad_avoid_corner", 6.0),
}
MODELS = ("ardupilot", "px4", "px4_go_no_data")
DEFAULT_MODELS = ("ardupilot", "px4")  # what make bench runs; px4_go_no_data on request (--models)


def base_file(scenario: str) -> Path:
    """The scenario TOML in configs/scenarios a scenario (or speed variant) is flown from."""
    return SCEN / f"{VARIANTS.get(scenario, (scenario,))[0]}.toml"


def _scale_camera(text: str, camera: tuple[int, int], src: Path) -> str:
    """The scenario's ``[camera]`` at ``camera`` = (width, height) with the same field of view
    (:func:`flightsim.scenario.scale_camera_text`); a ``ValueError`` if the aspect ratio changes."""
    from flightsim.scenario import scale_camera_text

    try:
        return scale_camera_text(text, camera, str(src))
    except Exception as e:  # ConfigError, as the ValueError this bench reports
        raise ValueError(str(e)) from e


def camera_tag(camera: tuple[int, int] | None) -> str:
    """The suffix of a campaign flown at another resolution than its scenario's (``""`` for the scenario's own)."""
    return "" if camera is None else f"_{camera[0]}x{camera[1]}"


def scenario_file(scenario: str, model: str, out: Path, camera: tuple[int, int] | None = None) -> tuple[Path, str]:
    """The scenario TOML and the ``--avoidance`` model of a campaign.  A speed variant
    (:data:`VARIANTS`), ``px4_go_no_data`` (the scenario with ``cp_go_no_data = true``) and another
    camera resolution (``camera`` = (width, height), the same field of view) are written to ``out``
    from the scenario file they change (world path made absolute, the name, the commanded speed and
    the camera replaced)."""
    src = base_file(scenario)
    if model != "px4_go_no_data" and scenario not in VARIANTS and camera is None:
        return src, model
    from flightsim.scenario import set_path_key

    text = src.read_text(encoding="utf-8")
    world = set_path_key(text, "world", "")[1]
    text, _ = set_path_key(text, "world", (SCEN / world).resolve().as_posix())
    if scenario in VARIANTS:
        speed = VARIANTS[scenario][1]
        text, n = re.subn(r"^speed_mps = [0-9.]+", f"speed_mps = {speed:g}", text, count=1, flags=re.M)
        text, m = re.subn(r'^name = "[^"]*"', f'name = "{scenario}"', text, count=1, flags=re.M)
        if n != 1 or m != 1:
            raise ValueError(f"{src}: no speed_mps / name line to write the variant {scenario}")
    tag = scenario
    if camera is not None:
        text = _scale_camera(text, camera, src)
        text, _ = re.subn(r'^name = "[^"]*"', f'name = "{scenario}{camera_tag(camera)}"', text, count=1, flags=re.M)
        tag += camera_tag(camera)
    if model == "px4_go_no_data":
        text = re.sub(r"^(cp_dist_m = .*)$", r"\1\ncp_go_no_data = true                # CP_GO_NO_DATA = 1: directions never covered do not stall",
                      text, count=1, flags=re.M)
        tag += "_px4_go_no_data"
    out.mkdir(parents=True, exist_ok=True)
    dst = out / f"{tag}.toml"
    dst.write_text(text, encoding="utf-8")
    return dst, "px4" if model == "px4_go_no_data" else model


def _fly_no_companion(args: tuple[str, int, str]) -> dict:
    """One ``flightsim fly`` of a scenario file with ArduPilot avoidance and no companion (worker process)."""
    path, seed, out = args
    from flightsim.fly import fly
    from flightsim.outcome import evaluate_outcome, read_trajectory
    from flightsim.scenario import load_scenario

    sc = load_scenario(path, seed=seed, avoidance="ardupilot")
    fly(sc, out, plot=False)
    return evaluate_outcome(read_trajectory(Path(out) / "trajectory.npz"), sc.world)


def no_companion(runs: int = 20, workers: int = 2, scenarios=None) -> dict:
    """The harness can fail: every avoidance scenario flown with ArduPilot avoidance and no companion
    (no obstacle data, so no constraint) — a collision is expected in every run."""
    import concurrent.futures as cf
    import multiprocessing
    import shutil

    from flightsim.campaign import pool_outcomes

    names = [n for n in (list(SCENARIOS) if scenarios is None else list(scenarios)) if n not in CLEAR_ROUTES]
    res = {}
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as ex:
        for name in names:
            base = OUT / f"{name}_no_companion"
            path = str(scenario_file(name, "ardupilot", OUT / "scenarios")[0])
            jobs = [(path, 1 + i, str(base / f"seed_{1 + i:04d}")) for i in range(runs)]
            outs = list(ex.map(_fly_no_companion, jobs))
            for _, _, d in jobs:  # keep only the outcome: the videos of these flights are not needed
                shutil.rmtree(d, ignore_errors=True)
            res[name] = pool_outcomes(outs)
    return res


def run_all(runs: int = 20, workers: int = 2, scenarios=None, models=DEFAULT_MODELS, progress=None,
            variant_models=("ardupilot",), checkpoint=None, with_no_companion: bool = True,
            camera: tuple[int, int] | None = None) -> dict:
    """The campaigns of ``scenarios`` × ``models`` with ``runs`` seeds each (speed variants only with the
    models also in ``variant_models``; every scenario at ``camera`` = (width, height) when given), then the
    flights without the companion; returns their results.  ``checkpoint(res)`` is called after each
    campaign with the results so far (a long bench cut short keeps what it finished)."""
    from flightsim.campaign import run_campaign

    names = list(SCENARIOS) if scenarios is None else list(scenarios)
    bad = [n for n in names if n not in SCENARIOS] + [m for m in models if m not in MODELS]
    if bad:
        raise ValueError(f"unknown scenario(s) or model(s): {', '.join(bad)}")
    res: dict = {"runs": runs, "campaigns": {}, "no_companion": {}}
    for model in models:  # one model's campaigns after the other's
        for name in names:
            if name in VARIANTS and model not in variant_models:
                continue
            out = OUT / f"{name}_{model}{camera_tag(camera)}"
            path, av = scenario_file(name, model, OUT / "scenarios", camera)
            t0 = time.perf_counter()
            c = run_campaign(path, out, runs=runs, workers=workers, mode="sitl", avoidance=av)
            res["campaigns"][f"{name}{camera_tag(camera)}/{model}"] = {
                "scenario": name + camera_tag(camera), "model": model, "wall_s": round(time.perf_counter() - t0, 1), "dir": str(out),
                "avoidance": c["aggregate"]["avoidance"], "runs_ok": c["aggregate"]["runs_ok"], "runs": c["aggregate"]["runs"],
                "detection_in_view": next((t["pooled"] for t in c["aggregate"]["targets"]
                                           if t["name"].startswith("detection (a range")), None),
                "dangerous_clears": dangerous_clears(c),
            }
            if progress:
                progress(name + camera_tag(camera), model, res["campaigns"][f"{name}{camera_tag(camera)}/{model}"])
            if checkpoint:
                checkpoint(res)
    if with_no_companion and camera is None:  # the flights without the companion do not depend on its camera
        res["no_companion"] = no_companion(runs, workers, names)
    return res


def dangerous_clears(campaign: dict) -> dict:
    """What a closed-loop campaign's own scorer cells say about "clear" in front of an obstacle (DESIGN §6: the
    failure a vehicle pays for): ``cells`` (scored obstacle cells claimed clear, pooled over the runs),
    ``obstacle_cells``, ``rate`` and ``runs_with`` (runs with at least one), from the campaign's result
    (``campaign.json``).  The flight's outcome can hide them: a pole claimed clear 25 m ahead is ranged a few
    metres later and the run still stops short."""
    cells = campaign["aggregate"]["cells"]
    n, total = int(cells["dangerous_clears"]), int(cells["obstacle"])
    runs = [r for r in campaign.get("runs", []) if r.get("status") == "ok"]
    with_one = sum(1 for r in runs if ((r.get("key_figures") or {}).get("dangerous_clear") or 0) > 0)
    return {"cells": n, "obstacle_cells": total, "rate": n / total if total else None, "runs_with": with_one,
            "runs": len(runs)}


def merge_results(parts: list[dict]) -> dict:
    """Results of several runs of :func:`run_all` as one (in order: a later cell replaces an earlier one)."""
    runs = {p["runs"] for p in parts}
    if len(runs) != 1:
        raise ValueError(f"results with different seeds per case cannot be merged: {sorted(runs)}")
    out: dict = {"runs": runs.pop(), "campaigns": {}, "no_companion": {}}
    for p in parts:
        out["campaigns"].update(p.get("campaigns") or {})
        out["no_companion"].update(p.get("no_companion") or {})
    return out


def rescore(res: dict) -> dict:
    """The outcomes of a finished run of :func:`run_all` scored again from each run's trajectory.npz with
    the current :mod:`flightsim.outcome` (no flight is repeated), pooled again; the dangerous clears read again
    from each campaign's ``campaign.json``."""
    import json

    from flightsim.campaign import pool_outcomes
    from flightsim.outcome import evaluate_outcome, read_trajectory
    from flightsim.scenario import load_scenario

    for c in res["campaigns"].values():
        world = load_scenario(base_file(c["scenario"])).world
        outs = [evaluate_outcome(read_trajectory(t), world) for t in sorted(Path(c["dir"]).glob("runs/*/trajectory.npz"))]
        if outs:
            c["avoidance"] = pool_outcomes(outs)
        camp = Path(c["dir"]) / "campaign.json"
        if camp.is_file():  # results written before the column existed get it from the campaign's own record
            c["dangerous_clears"] = dangerous_clears(json.loads(camp.read_text(encoding="utf-8")))
    return res


def _pc(v) -> str:
    from flightsim.report import _pc as pc

    return pc(v, 1)


def _m(d, fmt="{:.2f}") -> str:
    from flightsim.report import mean_std_text

    return mean_std_text(d, fmt, with_max=False)


def _dc(d) -> str:
    if not d:
        return "–"
    return f"{d['cells']} / {d['obstacle_cells']} ({_pc(d['rate'])}); {d['runs_with']} of {d['runs']} runs"


def markdown(res: dict) -> str:
    """The closed-loop section of docs/BENCHMARKS.md."""
    L = ["Command: `python -m bench avoidance --runs " + str(res["runs"]) + "` (in `make bench`); each cell is "
         "`flightsim campaign configs/scenarios/<scenario>.toml --avoidance <model> --runs N --mode sitl` (lockstep SITL, "
         "the companion live with configs/companion.toml, seeds from the scenario's own).  The simulated autopilot limits "
         "the pilot's velocity with the messages as they arrive (flightsim/avoidance/: ArduPilot Copter simple "
         "avoidance with its shipped defaults — AVOID_MARGIN 2 m, slide, PRX_FILT 0.25 Hz, braking at 1 m/s²; PX4 "
         "collision prevention with CP_DIST 2 m, CP_DELAY 0.4 s, CP_GUIDE_ANG 30°, CP_GO_NO_DATA 0 as shipped"
         + (", and a variant with CP_GO_NO_DATA 1" if any(c["model"] == "px4_go_no_data" for c in res["campaigns"].values()) else "")
         + ").  Outcome per run (flightsim/outcome.py): collision = the body (0.35 m sphere) "
         "touched an obstacle; stop clearance = body to the obstacle along the demanded direction where it first came to "
         "rest; false stop = slowed below half the demand for ≥ 0.5 s with nothing within 2 × margin + the model's "
         "stopping distance; progress = share of the route flown.  Collision rate with a 95 % Wilson interval.  Dangerous "
         "clears = the runs' scored obstacle cells (after the 2 s warm-up) claimed clear (max_distance + 1), pooled, and the "
         "runs with one: no collision can hide them.", "",
         "| scenario | model | runs | collisions (95 % CI) | stopped short | stop clearance m | min clearance m | false stops | "
         "progress | data while pushing | detection in view | dangerous clears |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, c in res["campaigns"].items():
        a = c["avoidance"]
        if not a:
            L.append(f"| {c['scenario']} | {c['model']} | {c['runs_ok']} of {c['runs']} | – | – | – | – | – | – | – | – | "
                     f"{_dc(c.get('dangerous_clears'))} |")
            continue
        ci = a["collision_ci95"]
        L.append(f"| {c['scenario']} | {c['model']} | {a['runs']} | {a['collisions']} ({_pc(a['collision_rate'])}; "
                 f"{_pc(ci[0])}–{_pc(ci[1])}) | {a['stopped_short']} | {_m(a['stop_clearance_m'])} | "
                 f"{_m(a['min_clearance_m'])} | {a['false_stops']} | {_m(a['progress'], '{:.0%}')} | "
                 f"{_m(a['data_while_pushing'], '{:.0%}')} | {_pc(c['detection_in_view'])} | {_dc(c.get('dangerous_clears'))} |")
    nc = res.get("no_companion") or {}
    if nc:
        L += ["", "The harness can fail: the same scenarios flown by `flightsim fly … --avoidance ardupilot` without the companion "
              "(no obstacle data, so ArduPilot applies no constraint), same seeds:", "",
              "| scenario | runs | collisions (95 % CI) | min clearance m |", "|---|---|---|---|"]
        for name, a in nc.items():
            ci = a["collision_ci95"]
            L.append(f"| {name} | {a['runs']} | {a['collisions']} ({_pc(a['collision_rate'])}; {_pc(ci[0])}–{_pc(ci[1])}) | "
                     f"{_m(a['min_clearance_m'])} |")
    L += ["", "Reports per campaign (each run's avoidance.png, pooled index.md): `out/bench/avoidance/<scenario>_<model>/`."]
    return "\n".join(L) + "\n"


def compare_markdown(before: dict, after: dict) -> str:
    """Before → after, cell by cell (the cells of ``after``; "–" where ``before`` has none): collisions, runs
    stopped short, stop and least clearance, false stops, progress, data while the pilot pushed, detection in
    view and dangerous clears, in :func:`markdown`'s forms."""
    def cells(c):
        a = (c or {}).get("avoidance")
        if not a:
            return ["–"] * 9
        return [str(a["collisions"]), str(a["stopped_short"]), _m(a["stop_clearance_m"]), _m(a["min_clearance_m"]),
                str(a["false_stops"]), _m(a["progress"], "{:.0%}"), _m(a["data_while_pushing"], "{:.0%}"),
                _pc(c["detection_in_view"]), _dc(c.get("dangerous_clears"))]

    L = ["| scenario | model | collisions | stopped short | stop clearance m | min clearance m | false stops | progress | "
         "data while pushing | detection in view | dangerous clears |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, c in after["campaigns"].items():
        b = before["campaigns"].get(key)
        L.append(f"| {c['scenario']} | {c['model']} | " + " | ".join(
            f"{x} → {y}" for x, y in zip(cells(b), cells(c))) + " |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    import argparse
    import json

    ap = argparse.ArgumentParser(prog="python -m bench.avoidance", description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=20, help="seeds per scenario × model (default 20)")
    ap.add_argument("--workers", type=int, default=2, help="worker processes per campaign (default 2)")
    ap.add_argument("--scenarios", default=None, help=f"comma-separated subset of: {', '.join(SCENARIOS)}")
    ap.add_argument("--models", default=",".join(DEFAULT_MODELS),
                    help=f"comma-separated subset of: {', '.join(MODELS)} (default {','.join(DEFAULT_MODELS)})")
    ap.add_argument("--variant-models", default="ardupilot",
                    help="models the 3 and 6 m/s variants of the pole and the corner are flown with (default ardupilot)")
    ap.add_argument("--no-companion-flights", choices=("on", "off"), default="on",
                    help="also fly each scenario without the companion (the harness must show a collision; default on)")
    ap.add_argument("--camera", metavar="WxH", default=None,
                    help="fly every scenario at this camera resolution, the same field of view (e.g. 640x480; default the "
                         "scenario's own, 320x240); campaigns go to out/bench/avoidance/<scenario>_<model>_WxH")
    ap.add_argument("--json-out", metavar="FILE", default=None,
                    help="where the results go (default out/bench/avoidance/avoidance.json; written after each campaign)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of the table")
    ap.add_argument("--from-json", metavar="FILE", nargs="+",
                    help="print the table of previous runs' results (out/bench/avoidance/avoidance.json); several files "
                         "are merged in order (a later file's campaign or no-companion cell replaces an earlier one's)")
    ap.add_argument("--rescore", action="store_true", help="with --from-json: score the outcomes again from the runs' "
                                                           "trajectory.npz with the current scorer (no flight repeated)")
    ap.add_argument("--before", metavar="FILE", nargs="+",
                    help="with --from-json: results of an earlier run (merged likewise); print before → after for the "
                         "cells of --from-json instead of the table")
    args = ap.parse_args(argv)
    if args.before and not args.from_json:
        ap.error("--before needs --from-json (the results after)")
    if args.from_json:
        res = merge_results([json.loads(Path(f).read_text(encoding="utf-8")) for f in args.from_json])
        res = rescore(res) if args.rescore else res
        if args.before:
            print(compare_markdown(merge_results([json.loads(Path(f).read_text(encoding="utf-8")) for f in args.before]), res))
        else:
            print(markdown(res))
        return 0
    names = [n.strip() for n in args.scenarios.split(",") if n.strip()] if args.scenarios else None
    models = tuple(m.strip() for m in args.models.split(",") if m.strip() and m.strip() != "none")  # none: only the no-companion flights
    variant_models = tuple(m.strip() for m in args.variant_models.split(",") if m.strip())
    camera = None
    if args.camera:
        from flightsim.scenario import parse_camera_size

        try:
            camera = parse_camera_size(args.camera)
        except Exception as e:
            ap.error(f"--camera: {e}")
    json_out = Path(args.json_out) if args.json_out else OUT / f"avoidance{camera_tag(camera)}.json"

    def checkpoint(r: dict) -> None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(r, default=str, indent=1), encoding="utf-8")

    try:
        if camera is not None:  # the aspect ratio is checked before any flight
            for n in names or SCENARIOS:
                _scale_camera(base_file(n).read_text(encoding="utf-8"), camera, base_file(n))
    except ValueError as e:
        ap.error(str(e))
    res = run_all(args.runs, args.workers, names, models, variant_models=variant_models, checkpoint=checkpoint,
                  with_no_companion=args.no_companion_flights == "on", camera=camera,
                  progress=lambda n, m, c: print(f"{n} {m}: {c['avoidance'] and c['avoidance']['collisions']} collisions "
                                                 f"in {c['runs_ok']} runs ({c['wall_s']:.0f} s)", flush=True))
    checkpoint(res)
    print(json.dumps(res, default=str) if args.json else markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
