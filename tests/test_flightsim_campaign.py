"""flightsim campaign: a tiny replay campaign in worker processes, failed runs recorded,
pooling that matches the runs' own scores, and the CLI's exit codes."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from companion.errors import ConfigError
from companion.landmark_log import read_landmark_log
from flightsim import campaign as C
from flightsim.cli import main as flightsim_main
from flightsim.score.config import ScoreConfig

ROOT = Path(__file__).resolve().parents[1]


def short_scenario(tmp_path: Path, duration_s: float = 2.5) -> Path:
    text = (ROOT / "configs" / "scenarios" / "quad_approach.toml").read_text()
    text = re.sub(r'^world = "\.\./worlds/', f'world = "{(ROOT / "configs" / "worlds").as_posix()}/', text, flags=re.M)
    text = re.sub(r"^duration_s = .*$", f"duration_s = {duration_s}", text, flags=re.M)
    p = tmp_path / "short.toml"
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def tiny_campaign(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("campaign")
    sp = short_scenario(tmp)
    ticks = []
    c = C.run_campaign(sp, tmp / "camp", runs=2, workers=2, mode="replay", fixed_processing_ms=30.0, times=[1.0, 2.0],
                       progress=lambda done, total, failed: ticks.append((done, total, failed)), landmark_log=True)
    return tmp / "camp", c, ticks


def test_tiny_campaign_runs_scores_and_reports(tiny_campaign):
    out, c, ticks = tiny_campaign
    assert ticks[-1] == (2, 2, 0)
    assert c["mode"] == "replay" and c["seeds"] == [1, 2]  # quad_approach's own seed is 1
    assert [r["status"] for r in c["runs"]] == ["ok", "ok"]
    for seed in (1, 2):
        run = out / "runs" / f"seed_{seed:04d}"
        assert (run / "ranges.tlog").is_file() and (run / "score.md").is_file() and (run / "score_series.npz").is_file()
        assert not (run / "video.avi").exists()  # deleted after scoring (the seed reproduces it)
        assert json.loads((run / "flight.json").read_text())["seed"] == seed
        assert (run / "nees.png").is_file()  # each run's forward error and NEES over time
        frames = read_landmark_log(run / "landmarks.jsonl")  # --landmark-log: the companion's landmarks, frame by frame
        assert len(frames) > 10 and any(f["converged"].any() for f in frames)
    # ... and the report sets them against the truth (flightsim/score/landmarks.py), pooled over both runs
    lm = c["aggregate"]["landmarks"]
    assert lm["runs"] == 2 and sum(b["n"] for b in lm["bins"]) > 0
    assert "## Each landmark against the truth (landmark log)" in (out / "report" / "index.md").read_text()
    ne = c["aggregate"]["nees"]
    assert {"n", "n_eff", "n_eff_sum_of_runs", "band", "band_independent", "consistent", "coverage", "runs_consistent"} <= set(ne)
    assert "NEES and coverage of the forward σ, pooled over runs" in (out / "report" / "index.md").read_text()
    # the two seeds flew differently (different noise), so their ranges differ
    a = (out / "runs" / "seed_0001" / "ranges.tlog").read_bytes()
    b = (out / "runs" / "seed_0002" / "ranges.tlog").read_bytes()
    assert a != b
    on_disk = json.loads((out / "campaign.json").read_text())
    assert on_disk["aggregate"]["runs_ok"] == 2 and on_disk["report"]["index"].endswith("index.md")
    idx = (out / "report" / "index.md").read_text()
    for name in ("range_vs_truth.png", "error_vs_range.png", "radar.png", "latency_hist.png", "nees.png",
                 "runs/seed_0001/score.md"):
        assert name in idx
        if name.endswith(".png"):
            assert (out / "report" / name).stat().st_size > 10_000
    assert "✓" in idx or "✗" in idx


def test_pooled_figures_are_the_sums_of_the_runs(tiny_campaign):
    out, c, _ = tiny_campaign
    scores = [json.loads((out / "runs" / f"seed_{s:04d}" / "score.json").read_text()) for s in (1, 2)]
    agg = c["aggregate"]
    for key in ("obstacle", "clear", "detections", "dangerous_clears", "false_obstacles_clear_cells"):
        assert agg["cells"][key] == sum(s["cells"][key] for s in scores)
    if agg["cells"]["obstacle"]:
        assert agg["pooled_rates"]["detection"] == pytest.approx(agg["cells"]["detections"] / agg["cells"]["obstacle"])
    det = [s["rates"]["detection"] for s in scores if s["rates"]["detection"] is not None]
    if det:
        assert agg["per_run_rates"]["detection"]["mean"] == pytest.approx(np.mean(det))
    assert agg["latency"]["n"] == sum(s["latency"]["n"] for s in scores)
    assert agg["latency"]["p50_ms"] == pytest.approx(40.0, abs=15.0)  # 30 ms processing + the wait for telemetry
    t_msg = agg["targets"][0]
    assert t_msg["n"] == sum(s["cells"]["messages_eligible_no_false"] for s in scores)


def fail_or_real(job: C.RunJob) -> dict:
    """Seed 11 raises inside the worker; seed 12 runs for real with a scenario that vanished."""
    if job.seed == 11:
        raise RuntimeError("boom in the worker")
    return C.run_one(C.RunJob(str(Path(job.run_dir) / "missing.toml"), job.seed, job.run_dir, job.mode, None,
                              job.score_config, job.fixed_processing_ms))


def test_failed_runs_are_recorded_and_the_report_still_written(tmp_path):
    sp = short_scenario(tmp_path)
    c = C.run_campaign(sp, tmp_path / "camp", runs=2, workers=2, mode="replay", seed0=11, run_fn=fail_or_real)
    runs = {r["seed"]: r for r in c["runs"]}
    assert runs[11]["status"] == "failed" and "boom in the worker" in runs[11]["error"]
    assert runs[12]["status"] == "failed" and "no such scenario file" in runs[12]["error"]
    assert (tmp_path / "camp" / "runs" / "seed_0012" / "error.txt").is_file()
    assert c["aggregate"]["runs_failed"] == 2 and c["aggregate"]["targets"] == []
    idx = (tmp_path / "camp" / "report" / "index.md").read_text()
    assert "boom in the worker" in idx and (tmp_path / "camp" / "report" / "radar.png").is_file()


def test_aggregate_pools_counts_not_rates():
    def score(obst, det, elig, ok, nees):
        return {"cells": {"obstacle": obst, "detections": det, "messages_eligible_no_false": elig,
                          "messages_without_false_obstacle": ok, "dangerous_clears": 0},
                "rates": {"detection": det / obst, "messages_without_false_obstacle": ok / elig},
                "targets": [{"name": "a", "op": ">=", "threshold": 0.95, "met": ok / elig >= 0.95},
                            {"name": "b", "op": "<=", "threshold": 0.01, "met": True}],
                "obstacles": [{"name": "mast", "in_range_at_s": 0.1, "detected_fraction": 0.5, "time_to_first_valid_s": nees}],
                "nees": {"mean": nees}, "first_claim_at_s": 1.0}
    results = [{"seed": 1, "status": "ok", "score": score(10, 9, 100, 99, 1.0)},
               {"seed": 2, "status": "ok", "score": score(90, 45, 10, 5, 3.0)},
               {"seed": 3, "status": "failed", "score": None, "error": "x"}]
    a = C.aggregate(results, {}, ScoreConfig())
    assert a["pooled_rates"]["detection"] == pytest.approx(54 / 100)  # not the mean of 0.9 and 0.5
    assert a["per_run_rates"]["detection"]["mean"] == pytest.approx(0.7)
    assert a["per_run_rates"]["detection"]["std"] == pytest.approx(np.std([0.9, 0.5], ddof=1))
    assert a["targets"][0]["pooled"] == pytest.approx(104 / 110) and a["targets"][0]["met"] is False
    assert a["targets"][0]["runs_met"] == 1 and a["targets"][1]["met"] is True
    assert a["runs_failed"] == 1 and a["obstacles"][0]["time_to_first_valid_s"]["mean"] == pytest.approx(2.0)


def test_arguments_are_checked(tmp_path, capsys):
    with pytest.raises(ConfigError, match="--times"):
        C.parse_times("1,x")
    assert C.parse_times("1, 2.5") == [1.0, 2.5] and C.parse_times(None) is None
    with pytest.raises(ConfigError, match="--mode"):
        C.resolve_mode("hybrid")
    assert C.resolve_mode("replay") == "replay"
    sp = short_scenario(tmp_path)
    assert flightsim_main(["campaign", str(sp), "--runs", "0", "--out", str(tmp_path / "c")]) == 2
    assert "--runs must be an integer >= 1" in capsys.readouterr().err
    assert flightsim_main(["campaign", str(tmp_path / "nope.toml"), "--runs", "1", "--out", str(tmp_path / "c")]) == 2
    assert "no such scenario file" in capsys.readouterr().err
    assert flightsim_main(["campaign", str(sp), "--runs", "1", "--out", str(tmp_path / "c"), "--times", "a"]) == 2
    assert not (tmp_path / "c" / "campaign.json").exists()


def test_ray_backend_runs_tasks_without_a_shared_file_system(tmp_path):
    """--backend ray: inputs are shipped as data, each task runs in its own temporary directory and
    returns its files, which the driver writes under runs/ (a local Ray stands in for a cluster)."""
    pytest.importorskip("ray", reason="Ray is the optional extra of --backend ray (pip install '.[ray]'); not installed here")
    from flightsim.campaign_ray import pack_inputs

    sp = short_scenario(tmp_path)
    files = pack_inputs(sp, ROOT / "configs" / "companion.toml")
    assert set(files) == {"scenario.toml", "world.toml", "companion.toml"} and 'world = "world.toml"' in files["scenario.toml"]
    c = C.run_campaign(sp, tmp_path / "ray", runs=2, workers=2, mode="replay", fixed_processing_ms=30.0, backend="ray")
    assert c["backend"] == "ray" and c["aggregate"]["runs_ok"] == 2, c["runs"]
    for r in c["runs"]:
        d = Path(r["dir"])
        assert d.parent == tmp_path / "ray" / "runs"
        assert {"score.json", "ranges.tlog", "truth.npz", "score_series.npz"} <= {p.name for p in d.iterdir()}
        assert not (d / "video.avi").exists()
        inputs = json.loads((d / "score.json").read_text())["inputs"]
        assert all(Path(v).parent == d for v in inputs.values()), inputs  # the driver's paths, not the task's temp dir
    local = C.run_campaign(sp, tmp_path / "local", runs=2, workers=2, mode="replay", fixed_processing_ms=30.0)
    assert local["aggregate"]["cells"] == c["aggregate"]["cells"]  # same runs, same pooled counts


def test_ray_backend_without_ray_says_how_to_install(tmp_path, monkeypatch):
    import builtins

    real = builtins.__import__

    def no_ray(name, *a, **k):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("no ray here")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    with pytest.raises(ConfigError, match=r"pip install '\.\[ray\]'"):
        C.run_campaign(short_scenario(tmp_path), tmp_path / "c", runs=1, mode="replay", backend="ray")


def test_campaign_pools_nees_with_n_eff_and_coverage(tmp_path):
    """Two runs with differently correlated forward errors (the right σ): the pooled NEES has the
    runs' samples, the variance-matched pooled n_eff (below the plain sum, the runs' correlation
    times differ) and its band, the summed coverage counts; the report shows them and draws nees.png."""
    from score_inputs import write_correlated_run

    from flightsim.report import write_report
    from flightsim.score.files import load_series, score_run, write_score
    from flightsim.score.stats import nees_band, pooled_n_eff

    cfg = ScoreConfig(sigma_k=2.0)
    results, series = [], {}
    for seed, phi in ((1, 0.95), (2, 0.3)):
        d = tmp_path / "runs" / f"seed_{seed:04d}"
        write_correlated_run(d, 1.0, seed=seed, phi=phi)
        s = score_run(d / "ranges.tlog", d / "truth.npz", config=cfg, series_out=d / "score_series.npz", plot_dir=d)
        write_score(d, s)
        results.append({"seed": seed, "dir": str(d), "status": "ok", "error": None, "wall_s": 1.0, "score": s})
        series[seed] = load_series(d / "score_series.npz")
    a = C.aggregate(results, series, cfg)
    ne, runs = a["nees"], [r["score"]["nees"] for r in results]
    assert runs[0]["n_eff"] < 0.3 * runs[1]["n_eff"]  # φ = 0.95 against φ = 0.3
    assert ne["n"] == sum(r["n"] for r in runs)
    assert ne["mean"] == pytest.approx(sum(r["n"] * r["mean"] for r in runs) / ne["n"])
    assert ne["n_eff"] == pytest.approx(pooled_n_eff([r["n"] for r in runs], [r["n_eff"] for r in runs]))
    assert ne["n_eff_sum_of_runs"] == pytest.approx(sum(r["n_eff"] for r in runs)) and ne["n_eff"] < ne["n_eff_sum_of_runs"]
    assert ne["band"] == pytest.approx(list(nees_band(ne["n_eff"], 0.95)))
    assert ne["band_independent"] == pytest.approx(list(nees_band(ne["n"], 0.95)))
    assert ne["consistent"] is True and ne["runs_consistent"] == 2 and ne["runs_with_samples"] == 2
    cov = ne["coverage"]
    assert cov["within_2sigma"] == sum(r["coverage"]["within_2sigma"] for r in runs)
    assert cov["rate_2sigma"] == pytest.approx(0.954, abs=0.03)
    assert ne["arrival"]["n_eff"] == pytest.approx(
        pooled_n_eff([r["arrival"]["n"] for r in runs], [r["arrival"]["n_eff"] for r in runs]))
    campaign = {"scenario": "synthetic.toml", "scenario_name": "synthetic", "mode": "replay", "seeds": [1, 2], "workers": 1,
                "wall_s": 2.0, "fixed_processing_ms": 30.0, "companion_config": None, "score_config": {"warmup_s": 2.0},
                "runs": [{k: v for k, v in r.items() if k != "score"} | {"key_figures": C.run_key_figures(r["score"])}
                         for r in results], "aggregate": a}
    assert campaign["runs"][0]["key_figures"]["nees_n_eff"] == pytest.approx(runs[0]["n_eff"])
    files = write_report(tmp_path / "report", campaign, series)
    idx = files["index"].read_text()
    assert "nees.png" in idx and f"n_eff = {ne['n_eff']:.1f}" in idx and "within ± 2σ" in idx
    assert f"plain sum would be {ne['n_eff_sum_of_runs']:.1f}" in idx
    assert files["nees"].stat().st_size > 10_000
