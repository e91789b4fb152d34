"""Scored runs with a known forward error, written as files (ranges.tlog + truth.npz), for the
scorer's and the campaign's tests of the NEES, its effective sample size and the coverage."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from companion.mavlink import messages as M
from companion.replay import TlogOut

U = 65535
MAX_CM, MIN_CM = 4000, 50


def write_correlated_run(run_dir: Path, noise_scale: float, seed: int = 2, frames: int = 1500, gap=(800, 830),
                         phi: float = 0.9, sigma: float = 0.1, k: float = 2.0) -> None:
    """A run directory (ranges.tlog + truth.npz) whose forward estimate errs by a Gaussian AR(1)
    series (φ) of standard deviation ``noise_scale``·σ while σ is reported: one filter's slowly
    wandering error.  No message is sent for the frames in ``gap`` (a second stretch)."""
    from flightsim.fly import save_npz_deterministic

    rng = np.random.default_rng(seed)
    fps, t0, boot0 = 30.0, 1000.0, 900.0
    t = t0 + np.arange(frames) / fps
    T = 25.0 - 0.005 * np.arange(frames)  # slowly approaching the obstacle ahead
    z = np.empty(frames)
    z[0] = rng.standard_normal()
    for i in range(1, frames):
        z[i] = phi * z[i - 1] + math.sqrt(1 - phi * phi) * rng.standard_normal()
    run_dir.mkdir(parents=True, exist_ok=True)
    sec = np.full((frames, 72), np.nan)
    sec[:, 0] = T
    save_npz_deterministic(run_dir / "truth.npz", {"t_s": t, "sector_m": sec, "p_ned": np.zeros((frames, 3)),
                                                   "rpy": np.zeros((frames, 3)), "sector_max_m": np.array(60.0)})
    w = TlogOut(run_dir / "ranges.tlog", system_id=1, component_id=196)
    for f in range(frames):
        if gap[0] <= f < gap[1]:
            continue
        pub = T[f] + noise_scale * sigma * z[f] - k * sigma
        ts = t[f] + 0.01
        w.write(ts, M.obstacle_distance(np.r_[[int(round(pub * 100))], np.full(71, U)], MIN_CM, MAX_CM,
                                        int(round((t[f] - boot0) * 1e6))))
        w.write(ts, M.distance_sensor("obstacle", pub, sigma, MIN_CM, MAX_CM, int(round((ts - boot0) * 1000))))
    w.close()
