"""The anchored EKF under a correlated (Gauss–Markov) telemetry position error: white model vs the
position-error states (docs/derivations/ekf_anchored.md § Position error states; issue 15 item 1).

A seeded Monte Carlo with exact geometry: a camera flies along its optical axis with a gentle sway,
landmarks ahead in a 62° field of view are tracked with 1 px of pixel noise for a few seconds, and
the telemetry reports the camera position with a first-order Gauss–Markov error (σ_p, τ = 30 s),
the simulator's model.  At the end the range of every landmark still in view is compared with the
truth (from the *true* camera): NEES (ideal 1), the share within ±σ and ±2σ (68.3 %, 95.4 %), RMS
error and the median σ.  The landmarks of one run share the position error, so the band of the mean
NEES is the χ²₁ band of ``runs`` independent samples, not of every landmark.

Cases: a quad (σ_p 0.1 m, 4 m/s, landmarks 10–40 m ahead, 6 s), a fixed-wing (σ_p 0.5 m, 30 m/s,
100–250 m, 5 s) and a quad that approaches at 1 m/s for 3 s and then hovers 6 s in front of
landmarks 2–6 m away (σ_p 0.1 m, a few centimetres of sway), each with the error treated as white
noise (``position_tau_s`` = 0: R gets 2 (ρ σ_p)²), estimated as states (``position_tau_s`` = 30) and
carried as consider states (``position_consider``: their covariance only, mean 0).

    python -m bench.position_states --runs 100
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

#: case → (σ_p m, speed m/s, landmark depth range m, lateral half width m, seconds tracked)
CASES = {
    "quad": dict(sigma=0.1, speed=4.0, dist=(10.0, 40.0), lat=5.0, T=6.0),
    "fixed-wing": dict(sigma=0.5, speed=30.0, dist=(100.0, 250.0), lat=30.0, T=5.0),
    "hover": dict(sigma=0.1, speed=1.0, dist=(5.0, 9.0), lat=1.5, T=9.0, stop=3.0, sway=0.03),
}
#: model → (position_tau_s, position_consider)
MODELS = {"white": (0.0, False), "states": (30.0, False), "consider": (30.0, True)}


def gauss_markov_flight(cfg, runs: int, sigma: float, tau: float = 30.0, speed: float = 8.0, dist=(30.0, 80.0),
                        lat: float = 8.0, n: int = 8, T: float = 3.0, hz: float = 20.0, seed0: int = 1000,
                        stop: float | None = None, sway: float = 1.0):
    """Range errors of the landmarks in view at the end of ``runs`` seeded flights (module docstring).

    ``cfg`` is the :class:`AnchoredEKFConfig`; the camera flies at ``speed`` until ``stop`` s (None: to the end)
    and sways ``sway`` m sideways; returns (error m, σ m, run index) per landmark, arrays."""
    from companion.core.ekf_anchored import AnchoredInverseDepthEKF
    from companion.core.frames import so3_exp

    K, dt, f = int(T * hz), 1.0 / hz, 500.0
    t = np.arange(K) * dt
    C = np.stack([np.zeros(K), sway * np.sin(2 * t), speed * np.minimum(t, T if stop is None else stop)], 1)  # true camera
    # centre: along z (the optical axis), swaying
    R = so3_exp(np.stack([0.02 * np.sin(t), 0.03 * np.sin(1.3 * t), 0.02 * t], 1))
    a = np.exp(-dt / tau)
    err, sig, run = [], [], []
    for r in range(runs):
        g = np.random.default_rng(seed0 + r)
        p = np.stack([g.uniform(-lat, lat, n), g.uniform(-lat / 2, lat / 2, n), g.uniform(*dist, n)], 1)
        e = np.zeros((K, 3))
        e[0] = g.normal(scale=sigma, size=3)
        for k in range(1, K):  # first-order Gauss–Markov error of the reported position
            e[k] = a * e[k - 1] + sigma * np.sqrt(1 - a * a) * g.standard_normal(3)
        C_rep = C + e
        ekf = AnchoredInverseDepthEKF(cfg, f, f)
        ids = np.arange(n)
        for k in range(K):
            pc = (p - C[k]) @ R[k]
            xy = pc[:, :2] / pc[:, 2:3] + g.normal(scale=1.0 / f, size=(n, 2))
            seen = (pc[:, 2] > 0) & np.all(np.abs(xy) < 0.6, 1)  # in a 62° field of view
            if k == 0:
                ekf.add(ids, xy, R[0], C_rep[0], t[0], 1.0 / np.mean(dist), 1.0 / dist[0])
            else:
                ekf.update(ids[seen], xy[seen], R[k], C_rep[k], t[k])
        est = ekf.estimates(C_rep[-1])
        err.append((est.range - np.linalg.norm(p - C[-1], axis=1))[seen])
        sig.append(est.range_sigma[seen])
        run.append(np.full(int(seen.sum()), r))
    return np.concatenate(err), np.concatenate(sig), np.concatenate(run)


def run(runs: int = 100) -> dict:
    """Every case × model: NEES (mean, median, band), coverage, RMS error, median σ."""
    from companion.core.ekf_anchored import AnchoredEKFConfig
    from flightsim.score.stats import coverage, nees_band

    out = {}
    band = nees_band(runs)  # the mean of `runs` independent χ²₁ samples (one per run: its landmarks share the error)
    for case, kw in CASES.items():
        for model, (tau, consider) in MODELS.items():
            cfg = AnchoredEKFConfig(attitude_drift_deg_s=0.0, max_mean_nis=0.0, max_drift_chi2=0.0, position_sigma_m=kw["sigma"],
                                    position_tau_s=tau, position_consider=consider)
            e, s, _ = gauss_markov_flight(cfg, runs, **kw)
            nees = e**2 / s**2
            out[f"{case}/{model}"] = dict(
                case=case, model=model, landmarks=int(len(e)), runs=runs, nees_mean=float(nees.mean()),
                nees_median=float(np.median(nees)), band=band, consistent=bool(band[0] <= nees.mean() <= band[1]),
                within_1sigma=coverage(e, s, 1.0), within_2sigma=coverage(e, s, 2.0),
                rms_error_m=float(np.sqrt(np.mean(e**2))), median_sigma_m=float(np.median(s)))
    return out


def markdown(res: dict) -> str:
    lines = ["| case | position error model | landmarks (runs) | range NEES mean (95 % band of the runs) | median | "
             "within ±σ / ±2σ | RMS error | median σ |", "|---|---|---|---|---|---|---|---|"]
    for r in res.values():
        lo, hi = r["band"]
        model = {"white": "white, 2 (ρ σ_p)² in R", "states": "states δ (τ 30 s)",
                 "consider": "consider states δ (τ 30 s, mean 0)"}[r["model"]]
        lines.append(f"| {r['case']} | {model} | {r['landmarks']} ({r['runs']}) | {r['nees_mean']:.2f} ({lo:.2f}–{hi:.2f} "
                     f"{'✓' if r['consistent'] else '✗'}) | {r['nees_median']:.2f} | {100 * r['within_1sigma']:.1f} % / "
                     f"{100 * r['within_2sigma']:.1f} % | {r['rms_error_m']:.3f} m | {r['median_sigma_m']:.3f} m |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.position_states", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=100, help="seeded flights per case and model (default 100)")
    ap.add_argument("--json", action="store_true", help="print JSON instead of the table")
    args = ap.parse_args(argv)
    if args.runs < 2:
        ap.error("--runs must be >= 2")
    res = run(args.runs)
    print(json.dumps(res, indent=1) if args.json else markdown(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
