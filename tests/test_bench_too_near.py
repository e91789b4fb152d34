"""bench.too_near: the too-near cells of a run split by cause, on a synthetic score series with known cells."""

import json

import numpy as np
import pytest

from bench import too_near
from flightsim.score.config import REP_RANGE, REP_UNKNOWN, ScoreConfig


def _series(path):
    n = 3
    rep = np.full((n, 72), REP_UNKNOWN, np.int8)
    cm = np.full((n, 72), 65535, np.int32)
    T = np.full((n, 72), np.nan, np.float32)
    iv = np.zeros((n, 72), bool)
    iv[:, list(range(0, 20)) + list(range(60, 72))] = True

    def put(m, i, true_m, r_m):
        T[m, i] = true_m
        if r_m is not None:
            rep[m, i] = REP_RANGE
            cm[m, i] = int(round(r_m * 100))

    put(0, 5, 20.0, 10.0)   # too near, and 10 m is the truth of sector 6 beside it: "beside"
    put(0, 6, 10.0, 9.5)    # a good range
    put(0, 10, 30.0, 20.0)  # too near, nothing beside at 20 m: "short"
    put(0, 12, 10.0, 9.0)   # within tolerance
    put(0, 40, 10.0, 5.0)   # out of view, too near (tolerance 2 m), alone
    put(1, 5, 20.0, 10.0)   # warm-up message: not scored
    put(2, 3, 8.0, None)    # an obstacle cell left unknown: no range, not too near
    # forward sector: d = T with σ = 0.11 d (only the 2σ offset is too near), d = 0.7 T (short), a good one
    ds_T = np.array([20.0, 20.0, 20.0, 20.0])
    ds_d = np.array([20.0, 14.0, 19.5, 20.0])
    ds_s = np.array([2.2, 0.1, 0.5, 2.2])
    ds_t = np.array([3.0, 3.1, 3.2, 0.5])  # the last one in the warm-up
    np.savez(path, t0=np.float64(0.0), od_rep=rep, od_cm=cm, od_truth=T, od_max_m=np.full(n, 40.0), od_in_view=iv,
             od_scored=np.ones(n, bool), od_warmup=np.array([False, True, False]),
             ds_state=np.full(4, REP_RANGE, np.int8), ds_estimate_m=ds_d, ds_sigma_m=ds_s, ds_truth_arrival=ds_T,
             ds_max_m=np.full(4, 40.0), ds_t=ds_t)


@pytest.fixture()
def campaign(tmp_path):
    run = tmp_path / "campaign_demo" / "runs" / "seed_0001"
    run.mkdir(parents=True)
    _series(run / "score_series.npz")
    return tmp_path / "campaign_demo"


def test_cells_split_by_cause(campaign):
    res = too_near.analyse(campaign)
    c = res["cells"]
    assert res["campaign"] == "demo" and res["runs"] == 1
    assert c["ranges_in_view"] == 4 and c["ranges_out_of_view"] == 1
    assert c["too_near_in_view"] == 2 and c["beside_in_view"] == 1
    assert c["too_near_out_of_view"] == 1 and c["beside_out_of_view"] == 0


def test_forward_offset_against_short_and_republished(campaign):
    f = too_near.analyse(campaign)["forward"]
    assert f["n"] == 3  # the warm-up sample is left out
    assert f["too_near"] == 2 and f["offset"] == 1 and f["short"] == 1
    assert f["median_rel_sigma_too_near"] == pytest.approx((0.11 + 0.1 / 14) / 2)
    k1 = f["republished"]["1"]  # d − σ: 17.8 m is within tolerance; 13.9 m is still short
    assert k1 == {"too_near": 1, "beyond_truth": 0, "over_range": 0}
    k2 = f["republished"]["2"]
    assert k2["too_near"] == 2 and k2["beyond_truth"] == 0


def test_tolerance_follows_the_score_config(campaign):
    loose = ScoreConfig(tolerance_m=2.0, tolerance_rel=0.5)  # 50 %: nothing above is too near any more
    res = too_near.analyse(campaign, cfg=loose)
    assert res["cells"]["too_near_in_view"] == 0 and res["forward"]["too_near"] == 0


def test_cli_tables_and_json(campaign, capsys):
    assert too_near.main([str(campaign)]) == 0
    out = capsys.readouterr().out
    assert "| demo |" in out and "k = 1.5" in out
    assert too_near.main([str(campaign), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["forward"]["offset"] == 1


def test_cli_missing_runs_is_a_clear_error(tmp_path, capsys):
    assert too_near.main([str(tmp_path)]) == 2
    assert "no runs/*/score_series.npz" in capsys.readouterr().err


def test_python_m_bench_dispatches_to_it(campaign, capsys):
    from bench.__main__ import main

    assert main(["too_near", str(campaign), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["cells"]["too_near_in_view"] == 2
