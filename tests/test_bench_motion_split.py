"""bench.motion_split: in-view obstacle cells split by the vehicle's motion (turning, hovering,
moving) and true range — a hand-built truth whose motion and answers are known, then the same
through files as a finished campaign leaves them."""

import math

import numpy as np
import pytest

from bench import motion_split as M
from flightsim.fly import save_npz_deterministic
from flightsim.score.config import ScoreConfig
from flightsim.score.evaluation import evaluate
from flightsim.score.files import save_series
from flightsim.score.inputs import RangeMessages, SectorTruth
from flightsim.score.summary import series_arrays

U = 65535
RATE = 10.0
CFG = ScoreConfig(warmup_s=0.0)


def flight():
    """30 frames: 10 hovering still, 10 turning in place at 40°/s, 10 moving north at 2 m/s; an obstacle
    cell at 8 m in sector 0 in view throughout (the truth's own, whatever the heading)."""
    F = 30
    yaw = np.r_[np.zeros(10), np.radians(4.0 * np.arange(1, 11)), np.full(10, math.radians(40.0))]
    p = np.zeros((F, 3))
    p[20:, 0] = 0.2 * np.arange(1, 11)
    sec = np.full((F, 72), np.inf)
    sec[:, 0] = 8.0
    view = np.zeros((F, 72), bool)
    view[:, [0, 1, 71]] = True
    return SectorTruth(1000.0 + np.arange(F) / RATE, sec, p, yaw, 60.0, view)


def messages(truth, values):
    rows = []
    for f, t in enumerate(truth.t_s):
        d = np.full(72, U)
        d[0] = values[f]
        rows.append((t + 0.01, 0, d, 50, 4000))
    return RangeMessages.build(od=rows)


def test_motion_of_tells_hovering_turning_and_moving_apart():
    m = M.motion_of(flight())
    names = [M.MOTIONS[i] for i in m]
    assert names[1:9] == ["hovering"] * 8 and names[11:19] == ["turning"] * 8 and names[22:29] == ["moving"] * 7


def test_split_counts_each_outcome_by_motion_and_range():
    truth = flight()
    # hovering: ranged right; turning: unknown; moving: 5 too near (3 m for 8 m), then right
    values = np.array([800] * 10 + [U] * 10 + [300] * 5 + [800] * 5)
    s = series_arrays(evaluate(messages(truth, values), truth, CFG))
    out = M.split_cells(s, truth, CFG)
    m = M.motion_of(truth)  # the frames at the seams take the heading rate of both sides (central differences)
    assert sum(row["cells"] for row in out.values()) == 30 and set(k for k, r in out.items() if r["cells"]) <= {
        "hovering/1", "turning/1", "moving/1"}
    for i, name in enumerate(M.MOTIONS):
        sel = m == i
        row = out[f"{name}/1"]
        assert row["cells"] == int(sel.sum())
        assert row["valid"] == int(np.sum(sel & (values == 800)))
        assert row["unknown"] == int(np.sum(sel & (values == U)))
        assert row["too_near"] == int(np.sum(sel & (values == 300)))
        assert row["too_far"] == row["clear"] == 0
    assert out["moving/1"]["too_near"] == 5 and out["turning/1"]["unknown"] == 10
    # the ceiling: 8 m ahead, heading changes alone give nothing; moving 10 % closer (0.8 m) does
    assert out["hovering/1"]["rangeable"] == 0 and out["turning/1"]["rangeable"] == 0
    assert 0 < out["moving/1"]["rangeable"] < out["moving/1"]["cells"]


def test_a_campaign_directory_is_read_and_pooled(tmp_path, capsys):
    truth = flight()
    s = series_arrays(evaluate(messages(truth, [800] * 30), truth, CFG))
    for seed in (1, 2):
        run = tmp_path / "camp" / "runs" / f"seed_{seed:04d}"
        save_series(run / "score_series.npz", s)
        save_npz_deterministic(run / "truth.npz", {"t_s": truth.t_s, "p_ned": truth.p_ned,
                                                   "rpy": np.c_[np.zeros((30, 2)), truth.yaw], "sector_max_m": np.array(60.0),
                                                   "sector_m": np.where(truth.in_view, truth.sector_m, np.nan),
                                                   "sector_all_m": truth.sector_m, "in_view": truth.in_view})
    res = M.analyse(tmp_path / "camp", CFG)
    assert res["runs"] == 2 and sum(r["cells"] for r in res["cells"].values()) == 60
    assert M.main([str(tmp_path / "camp")]) == 0
    assert "| hovering | 5–10 m |" in capsys.readouterr().out
    assert M.main([str(tmp_path / "nothing")]) == 2
    with pytest.raises(SystemExit):
        M.main([str(tmp_path / "camp"), "--turn-dps", "0"])


def test_unknown_cells_by_the_companions_reason(tmp_path, capsys):
    """The turning frames are unknown: the first five for "ranging" (6), the rest without a sector-log line (−1).
    Two runs carry the reasons, a third does not: the pooled split is then dropped, not half counted."""
    truth = flight()
    values = np.array([800] * 10 + [U] * 10 + [800] * 10)
    ev = evaluate(messages(truth, values), truth, CFG)
    why = np.zeros((30, 72), np.int8)
    why[10:20, 0] = np.r_[np.full(5, 6), np.full(5, -1)]
    s = series_arrays(ev, why)
    assert s["od_why"].dtype == np.int8 and s["od_why"].shape == (30, 72)
    out = M.split_cells(s, truth, CFG)
    m = M.motion_of(truth)
    turning = out["turning/1"]
    n_ranging = int(np.sum((m[10:15] == M.MOTIONS.index("turning"))))
    assert turning["why"]["ranging"] == n_ranging and turning["why"]["unattributed"] == turning["unknown"] - n_ranging
    assert sum(turning["why"].values()) == turning["unknown"]
    assert out["hovering/1"]["why"]["ranging"] == 0
    truth_npz = {"t_s": truth.t_s, "p_ned": truth.p_ned, "rpy": np.c_[np.zeros((30, 2)), truth.yaw],
                 "sector_max_m": np.array(60.0), "sector_m": np.where(truth.in_view, truth.sector_m, np.nan),
                 "sector_all_m": truth.sector_m, "in_view": truth.in_view}
    for seed in (1, 2):
        run = tmp_path / "camp" / "runs" / f"seed_{seed:04d}"
        save_series(run / "score_series.npz", s)
        save_npz_deterministic(run / "truth.npz", truth_npz)
    res = M.analyse(tmp_path / "camp", CFG)
    assert res["cells"]["turning/1"]["why"]["ranging"] == 2 * n_ranging
    assert M.main([str(tmp_path / "camp")]) == 0
    text = capsys.readouterr().out
    assert "Unknown cells by the companion's reason" in text and "| turning | 5–10 m |" in text and "ranging" in text
    plain = tmp_path / "camp" / "runs" / "seed_0003"
    save_series(plain / "score_series.npz", series_arrays(ev))
    save_npz_deterministic(plain / "truth.npz", truth_npz)
    assert M.analyse(tmp_path / "camp", CFG)["cells"]["turning/1"]["why"] is None  # read last
    (plain / "score_series.npz").rename(plain / "x")
    first = tmp_path / "camp" / "runs" / "seed_0000"
    save_series(first / "score_series.npz", series_arrays(ev))
    save_npz_deterministic(first / "truth.npz", truth_npz)
    assert M.analyse(tmp_path / "camp", CFG)["cells"]["turning/1"]["why"] is None  # read first
