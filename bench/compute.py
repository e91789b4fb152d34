"""Compute budget of the whole pipeline on one core (docs/derivations/compute.md).

Target: ≤ 8 ms of CPU per 640×480 frame with 300 tracks on one core, so that 30 frames/s fit on a
companion computer several times slower than this machine.

What is measured: the CPU time of the thread that runs :meth:`companion.pipeline.Pipeline.process`
(``time.thread_time``: tracking — Harris, NCC, Lucas–Kanade, scale —, the estimator, the local map,
the sectors), per frame, in a fresh process with one thread for OpenCV and for BLAS (so the thread's
CPU time is all the work there is), with the shipped configuration (configs/companion.toml, 300
tracks).  Two flights:

* ``synthetic`` — :mod:`bench.latency`'s flight past a textured wall (~270 live tracks, ~220
  converged landmarks), 240 frames after 30 of warm-up;
* ``replay`` — ``quad_approach`` flown by flightsim with its camera at 640×480 (the F450 hovering,
  then flying at 5 m/s towards a mast and a building), replayed through ``companion replay``'s loop.

Each runs with the compiled kernels and with the numpy reference (``COMPANION_KERNELS=numpy``).
``python -m bench compute [--write docs/BENCHMARKS.md]``.
"""

from __future__ import annotations

import json
import os
import platform
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SECTION = "## Compute budget per frame (issue 13)"
TARGET_MS = 8.0
SCENARIO = ROOT / "configs" / "scenarios" / "quad_approach.toml"
OUT = ROOT / "out" / "bench" / "compute"
_ONE_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}


def scenario_640(src: Path = SCENARIO) -> str:
    """``src`` with its camera at 640×480 (same 60° field of view) and its world path made absolute."""
    text = src.read_text(encoding="utf-8")
    scale = {"width": 2.0, "height": 2.0, "fx": 2.0, "fy": 2.0}

    def cam(m: re.Match) -> str:
        key, val = m.group(1), float(m.group(2))
        new = val * scale[key] if key in scale else (val + 0.5) * 2 - 0.5
        return f"{key} = {int(new) if key in ('width', 'height') else round(new, 2)}"

    head, sep, rest = text.partition("[camera]")
    body, sep2, tail = rest.partition("\n[")
    body = re.sub(r"^(width|height|fx|fy|cx|cy)\s*=\s*([0-9.]+)", cam, body, flags=re.M)
    world = re.search(r'^world\s*=\s*"([^"]+)"', head, flags=re.M)
    head = head.replace(world.group(0), f'world = "{(src.parent / world.group(1)).resolve()}"')
    return head + sep + body + sep2 + tail


def fly_recording(out: Path) -> Path:
    """Fly the 640×480 quad_approach once (flightsim fly) into ``out``; returns the flight directory."""
    out.mkdir(parents=True, exist_ok=True)
    scen = out / "quad_approach_640.toml"
    scen.write_text(scenario_640(), encoding="utf-8")
    flight = out / "flight"
    if not (flight / "frames.csv").is_file():
        subprocess.run([sys.executable, "-m", "flightsim", "fly", str(scen), "--out", str(flight), "--no-plot"],
                       check=True, stdout=subprocess.DEVNULL)
    return flight


def _worker_synthetic(frames: int, config: str | None = None) -> dict:
    from bench.latency import measure_latency
    from companion.io.config_files import load_companion_config

    r = measure_latency(640, 480, 300, frames, config=load_companion_config(config))
    return {"frames": r["frames"], "cpu_mean_ms": r["cpu_mean_ms"], "cpu_p50_ms": r["cpu_p50_ms"], "cpu_p99_ms": r["cpu_p99_ms"],
            "stage_cpu_ms": r["stage_cpu_ms"], "mean_tracks": r["mean_tracks"], "mean_converged": r["mean_converged"]}


def _worker_replay(flight: Path, config: str | None = None) -> dict:
    import logging

    import numpy as np

    from companion.io.config_files import load_companion_config
    from companion.replay import replay

    from flightsim.scenario import load_scenario

    logging.disable(logging.WARNING)
    cfg = load_companion_config(config)
    cam = load_scenario(flight.parent / "quad_approach_640.toml").camera
    cpu, tracks, conv = [], [], []
    stage: dict[str, float] = {}

    def on_frame(_pipe, res):
        if res.ok:
            cpu.append(res.cpu_s)
            tracks.append(res.n_tracks)
            conv.append(res.n_converged)
            for k, v in res.stage_cpu_s.items():
                stage[k] = stage.get(k, 0.0) + v

    with tempfile.TemporaryDirectory() as tmp:
        replay(flight / "telemetry.tlog", flight / "video.avi", flight / "frames.csv", Path(tmp) / "ranges.tlog", cfg,
               camera=cam, fixed_processing_s=0.03, on_frame=on_frame)
    a = np.asarray(cpu) * 1000
    return {"frames": len(a), "cpu_mean_ms": float(a.mean()), "cpu_p50_ms": float(np.percentile(a, 50)),
            "cpu_p99_ms": float(np.percentile(a, 99)), "stage_cpu_ms": {k: v * 1000 / len(a) for k, v in stage.items()},
            "mean_tracks": float(np.mean(tracks)), "mean_converged": float(np.mean(conv))}


def _run_worker(case: str, kernels: str, flight: Path | None, frames: int, config: str | None = None) -> dict:
    env = dict(os.environ, **_ONE_THREAD)
    if kernels == "numpy":
        env["COMPANION_KERNELS"] = "numpy"
    else:
        env.pop("COMPANION_KERNELS", None)
    cmd = [sys.executable, "-m", "bench.compute", "--worker", case, "--frames", str(frames)]
    if flight is not None:
        cmd += ["--flight", str(flight)]
    if config is not None:
        cmd += ["--config", str(Path(config).resolve())]
    out = subprocess.run(cmd, check=True, env=env, cwd=ROOT, capture_output=True, text=True)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["kernels"] = kernels
    return res


def run(frames: int = 240, out: Path = OUT, progress=None, config: str | None = None) -> dict:
    """Both flights × (kernels, reference); each measurement in its own one-thread process; ``config`` a
    companion configuration file (default: the shipped one)."""
    import numba

    flight = fly_recording(Path(out))
    rows = []
    for case in ("synthetic", "replay"):
        for kernels in ("numba", "numpy"):
            rows.append(dict(_run_worker(case, kernels, flight if case == "replay" else None, frames, config), case=case))
            if progress:
                progress(1)
    return {"rows": rows, "target_ms": TARGET_MS, "config": config, "numba": numba.__version__, "machine": platform.processor() or platform.machine(),
            "python": platform.python_version()}


def markdown(res: dict) -> str:
    stages = ("track", "estimate", "map", "sectors")
    L = [
        "Whole pipeline (Harris, NCC and Lucas–Kanade tracking, scale, estimator, local map, sectors) on one core: CPU "
        "time of the pipeline's thread per frame, in a fresh process with one OpenCV and one BLAS thread, "
        + ("shipped configuration" if not res.get("config") else f"configuration `{res['config']}`")
        + " (300 tracks), 640×480. `synthetic`: the latency flight past a textured wall; `replay`: "
        "quad_approach flown at 640×480 and replayed through `companion replay`'s loop. `numba`: the compiled kernels; "
        "`numpy`: the reference (`COMPANION_KERNELS=numpy`). Target ≤ 8 ms. "
        f"numba {res['numba']}, Python {res['python']}. Command: `python -m bench compute "
        + (f"--config {res['config']}`." if res.get("config") else "--write docs/BENCHMARKS.md`."),
        "",
        "| flight | kernels | frames | tracks | converged | CPU mean ms | p50 | p99 | " + " | ".join(stages) + " | ≤ 8 ms |",
        "|---|---|---|---|---|---|---|---|" + "---|" * len(stages) + "---|",
    ]
    for r in res["rows"]:
        st = " | ".join(f"{r['stage_cpu_ms'].get(s, float('nan')):.2f}" for s in stages)
        ok = "✓" if r["cpu_mean_ms"] <= res["target_ms"] else "✗"
        L.append(f"| {r['case']} | {r['kernels']} | {r['frames']} | {r['mean_tracks']:.0f} | {r['mean_converged']:.0f} | "
                 f"{r['cpu_mean_ms']:.2f} | {r['cpu_p50_ms']:.2f} | {r['cpu_p99_ms']:.2f} | {st} | {ok} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m bench.compute", description=__doc__.split("\n")[0],
                                 epilog="example: python -m bench compute --write docs/BENCHMARKS.md")
    ap.add_argument("--frames", type=int, default=240, help="timed frames of the synthetic flight (default 240)")
    ap.add_argument("--out", default=str(OUT), help=f"where the 640×480 flight is recorded (default {OUT})")
    ap.add_argument("--write", metavar="FILE", help="replace the section in FILE (docs/BENCHMARKS.md) with the table")
    ap.add_argument("--json", action="store_true", help="print JSON instead of the table")
    ap.add_argument("--worker", choices=("synthetic", "replay"), help=argparse.SUPPRESS)
    ap.add_argument("--config", metavar="TOML", help="companion configuration to measure (default: the shipped "
                                                      "configs/companion.toml), e.g. configs/companion_refine.toml")
    ap.add_argument("--flight", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.config is not None and not Path(a.config).is_file():
        ap.error(f"--config: no such file: {a.config}")
    if a.worker:
        import cv2

        cv2.setNumThreads(1)
        res = _worker_synthetic(a.frames, a.config) if a.worker == "synthetic" else _worker_replay(Path(a.flight), a.config)
        print(json.dumps(res))
        return 0
    from bench.__main__ import _progress

    with _progress(4, "compute budget", a.json) as tick:
        res = run(a.frames, Path(a.out), progress=tick, config=a.config)
    text = markdown(res)
    print(json.dumps(res) if a.json else text)
    if a.write:
        from bench import report

        report.write_section(a.write, SECTION, text)
        print(f"wrote {a.write}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
