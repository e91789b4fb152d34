"""Scoring over 360° (docs/derivations/sectors.md, obstacle_map.md): out-of-view claims scored against a 360°
truth, unknown out of view neutral, remembered obstacles, detection by true-range bin and the 2-s
warm-up — hand-built truths and messages whose answers are known exactly."""

import math
from pathlib import Path

import numpy as np
import pytest

from flightsim import campaign as C
from flightsim.score.config import ScoreConfig
from flightsim.score.evaluation import evaluate
from flightsim.score.inputs import RangeMessages, SectorTruth
from flightsim.score.markdown import markdown
from flightsim.score.summary import summarize
from flightsim.fly import save_npz_deterministic
from flightsim.score.files import read_truth_npz, write_score

U = 65535
MAX_CM, MIN_CM = 4000, 50
CLEAR = MAX_CM + 1
NOWARM = ScoreConfig(warmup_s=0.0)
FRONT = np.r_[np.arange(0, 8), np.arange(64, 72)]  # a ±37.5° camera: sectors −40°…+35°


def od(t, values: dict):
    d = np.full(72, U)
    for i, v in values.items():
        d[i] = v
    return (t, 0, d, MIN_CM, MAX_CM)


def turn_truth(n_before=5, n_after=5, rate=10.0, dist=20.0, p_after=None):
    """A vehicle at the origin facing north with an obstacle 20 m ahead (sector 0, in view), then
    turned round (yaw π): the same obstacle is behind (sector 36, out of view).  Every other sector
    is clear (inf).  ``p_after`` moves the vehicle for the frames after the turn (the obstacle point
    stays where it is: the distance is recomputed)."""
    F = n_before + n_after
    sec = np.full((F, 72), np.inf)
    view = np.zeros((F, 72), bool)
    view[:, FRONT] = True
    yaw = np.r_[np.zeros(n_before), np.full(n_after, math.pi)]
    p = np.zeros((F, 3))
    sec[:n_before, 0] = dist
    if p_after is not None:
        p[n_before:] = p_after
    obst = np.array([dist, 0.0])
    sec[n_before:, 36] = np.hypot(*(obst - p[n_before:, :2]).T)
    t = 1000.0 + np.arange(F) / rate
    return SectorTruth(t, sec, p, yaw, 60.0, view)


def msgs_after_turn(truth, n_before, value_behind, value_front=2000):
    rows = []
    for f, t in enumerate(truth.t_s):
        rows.append(od(t + 0.02, {0: value_front} if f < n_before else {36: value_behind}))
    return RangeMessages.build(od=rows)


def score(truth, msgs, cfg=NOWARM):
    return summarize(evaluate(msgs, truth, cfg))


# ---------------------------------------------------------------------- out of view --------------
def test_remembered_obstacle_behind_within_tolerance_is_a_detection():
    truth = turn_truth()
    s = score(truth, msgs_after_turn(truth, 5, 1950))  # 19.5 m behind: within max(2 m, 4 m) of 20 m
    iv, oov, c = s["cells_in_view"], s["cells_out_of_view"], s["cells"]
    assert iv["obstacle"] == 5 and iv["valid_ranges"] == 5
    assert oov["obstacle"] == 5 and oov["valid_ranges"] == 5 and oov["obstacle_cells_total"] == 5
    assert c["obstacle"] == 10 and c["valid_ranges"] == 10 and c["dangerous_clears"] == 0
    assert s["remembered"]["cells"] == 5 and s["remembered"]["within_tolerance"] == 5 and s["remembered"]["rate"] == 1.0
    rem = next(t for t in s["targets"] if t["key"] == "remembered")
    assert rem["value"] == 1.0 and rem["met"] is True and rem["n"] == 5
    # by true range: the obstacle (20 m) falls in the 20–30 m bin, in view and out of view
    b_iv = {b["bin"]: b for b in s["detection_by_range"]["in_view"]}
    b_oov = {b["bin"]: b for b in s["detection_by_range"]["out_of_view"]}
    assert b_iv["20–30 m"]["obstacle_cells"] == 5 and b_iv["20–30 m"]["valid_rate"] == 1.0
    assert b_oov["20–30 m"]["obstacle_cells"] == 5 and b_oov["20–30 m"]["valid"] == 5


def test_clear_behind_on_an_obstacle_is_dangerous():
    truth = turn_truth()
    msgs = msgs_after_turn(truth, 5, U)
    rows = list(zip(msgs.od_t, msgs.od_time_usec, msgs.od_distances_cm, msgs.od_min_cm, msgs.od_max_cm))
    rows[7] = od(truth.t_s[7] + 0.02, {36: CLEAR})  # one message says "clear" behind, where the obstacle stands
    s = score(truth, RangeMessages.build(od=rows))
    assert s["cells_out_of_view"]["dangerous_clears"] == 1 and s["cells_out_of_view"]["obstacle"] == 1
    assert s["cells"]["dangerous_clears"] == 1 and s["cells"]["obstacle"] == 6  # 5 in view + the claimed one
    assert s["rates"]["dangerous_clear"] == pytest.approx(1 / 6)
    dang = next(t for t in s["targets"] if t["key"] == "dangerous_clear")
    assert dang["num"] == 1 and dang["n"] == 6 and dang["met"] is False
    assert s["remembered"]["dangerous_clears"] == 1 and s["remembered"]["unknown"] == 4 and s["remembered"]["rate"] == 0.0


def test_remembered_ranges_beyond_the_tolerance_are_told_apart():
    """A remembered obstacle 20 m behind claimed at 24.5 m (beyond max(2 m, 4 m): the building seen past a mast's edge)
    is "too far", at 15.5 m "too near"; at 23.5 m within tolerance, neither.  Pooled over a campaign."""
    truth = turn_truth()
    far, near, ok = (score(truth, msgs_after_turn(truth, 5, v))["remembered"] for v in (2450, 1550, 2350))
    assert (far["over_range"], far["too_near"], far["within_tolerance"], far["ranges"]) == (5, 0, 0, 5)
    assert (near["over_range"], near["too_near"], near["within_tolerance"]) == (0, 5, 0)
    assert (ok["over_range"], ok["too_near"], ok["within_tolerance"]) == (0, 0, 5)
    s = score(truth, msgs_after_turn(truth, 5, 2450))
    assert "too near 0, too far 5" in markdown(s)
    results = [{"seed": i, "status": "ok", "score": score(truth, msgs_after_turn(truth, 5, v))} for i, v in enumerate((2450, 1550), 1)]
    a = C.aggregate(results, {}, NOWARM)["remembered"]
    assert (a["over_range"], a["too_near"], a["cells"]) == (5, 5, 10)


def test_unknown_out_of_view_changes_nothing():
    truth = turn_truth()
    msgs = msgs_after_turn(truth, 5, U)  # nothing published behind
    s = score(truth, msgs)
    # the same messages against an old truth that knows only the sectors in view
    old = SectorTruth(truth.t_s, np.where(truth.in_view, truth.sector_m, np.nan), truth.p_ned, truth.yaw, 60.0)
    s_old = score(old, msgs)
    assert s["cells"] == s_old["cells"] == s["cells_in_view"]
    assert {k: v for k, v in s["rates"].items()} == s_old["rates"]
    assert [t["value"] for t in s["targets"][:4]] == [t["value"] for t in s_old["targets"][:4]]
    oov = s["cells_out_of_view"]
    assert oov["obstacle"] == 0 and oov["clear"] == 0 and oov["unknown_neutral"] == 5 * 56 + 5 * 56
    # the remembered metric does see the silence: 5 remembered cells, none reported
    assert s["remembered"]["cells"] == 5 and s["remembered"]["rate"] == 0.0
    assert s_old["remembered"]["cells"] == 0 and s_old["truth_360"] is False and s["truth_360"] is True


def test_false_obstacle_out_of_view_counts_against_the_message():
    truth = turn_truth()
    rows = [od(t + 0.02, {0: 2000, 20: 500} if f == 2 else {0: 2000}) for f, t in enumerate(truth.t_s[:5])]
    s = score(truth, RangeMessages.build(od=rows))  # sector 20 (100°, out of view) is clear: 5 m there is false
    assert s["cells_out_of_view"]["false_obstacles_clear_cells"] == 1 and s["cells_out_of_view"]["clear"] == 1
    assert s["cells"]["false_obstacles_clear_cells"] == 1
    assert s["cells"]["messages_without_false_obstacle"] == 4 and s["cells"]["messages_eligible_no_false"] == 5
    assert s["cells_in_view"]["messages_without_false_obstacle"] == 5  # in view alone: no false obstacle


def test_false_obstacle_beside_an_obstacle_is_told_apart_from_a_phantom():
    truth = turn_truth()  # after the turn the obstacle is behind at 20 m (sector 36), every other sector clear
    rows = []
    for f, t in enumerate(truth.t_s):
        if f < 5:
            rows.append(od(t + 0.02, {0: 2000}))
        elif f == 5:
            rows.append(od(t + 0.02, {36: 2000, 37: 1950}))  # the obstacle's range one sector off: beside
        elif f == 6:
            rows.append(od(t + 0.02, {36: 2000, 38: 1000}))  # 10 m two sectors off: a phantom (range does not match)
        else:
            rows.append(od(t + 0.02, {36: 2000, 40: 2000}))  # the right range four sectors off: beyond 2 sectors
    s = score(truth, RangeMessages.build(od=rows))
    fb = s["false_obstacles_beside_obstacle"]
    assert fb["out_of_view_total"] == 1 + 1 + 3 and fb["out_of_view"] == 1
    assert fb["in_view"] == 0 and fb["in_view_total"] == 0 and fb["sectors"] == 2
    wide = score(truth, RangeMessages.build(od=rows), ScoreConfig(warmup_s=0.0, beside_sectors=4))
    assert wide["false_obstacles_beside_obstacle"]["out_of_view"] == 1 + 3
    off = score(truth, RangeMessages.build(od=rows), ScoreConfig(warmup_s=0.0, beside_sectors=0))
    assert off["false_obstacles_beside_obstacle"]["out_of_view"] == 0
    assert s["cells"]["false_obstacles_clear_cells"] == 5  # the diagnostic never changes the score
    with pytest.raises(Exception, match="beside_sectors"):
        ScoreConfig(beside_sectors=-1)


def test_remembered_only_within_the_window_and_the_travel():
    # an obstacle 10 m ahead; turned round and moved south: 19 m → remembered, 21 m → not (still within 40 m)
    near = turn_truth(dist=10.0, p_after=np.array([-19.0, 0.0, 0.0]))
    assert near.sector_m[-1, 36] == 29.0
    assert score(near, msgs_after_turn(near, 5, 2900))["remembered"]["cells"] == 5
    farther = turn_truth(dist=10.0, p_after=np.array([-21.0, 0.0, 0.0]))
    s = score(farther, msgs_after_turn(farther, 5, U))
    assert s["remembered"]["cells"] == 0 and s["cells_out_of_view"]["obstacle_cells_total"] == 5
    # in view 0.0–0.4 s, behind from 0.5 s to 11.4 s at 10 Hz: cells later than 10 s after 0.4 s are not remembered
    long = turn_truth(n_before=5, n_after=110)
    s = score(long, msgs_after_turn(long, 5, 2000))
    assert s["remembered"]["cells"] == 100  # frames 5…104 (t − 0.4 s ≤ 10 s)
    assert s["cells_out_of_view"]["valid_ranges"] == 110  # the claims still count as detections


# ---------------------------------------------------------------------- bins and warm-up --------
def test_detection_by_true_range_bins_are_exact():
    dists = [3.0, 5.0, 7.0, 15.0, 25.0, 35.0, 39.0]  # sectors 0…6, all in view; 5.0 m belongs to the 5–10 m bin
    F = 4
    sec = np.full((F, 72), np.inf)
    sec[:, :7] = dists
    truth = SectorTruth(1000.0 + np.arange(F) / 10, sec, np.zeros((F, 3)), np.zeros(F), 60.0, np.ones((F, 72), bool))
    rows = []
    for f, t in enumerate(truth.t_s):
        vals = {0: 300, 1: 500 if f < 2 else U, 2: 1500, 3: 1500, 4: CLEAR if f == 0 else 2500, 5: U, 6: 3900}
        rows.append(od(t + 0.01, vals))  # sector 2: 15 m for a 7-m obstacle = over range; sector 3: exact
    s = score(truth, RangeMessages.build(od=rows))
    b = {r["bin"]: r for r in s["detection_by_range"]["in_view"]}
    assert list(b) == ["0–5 m", "5–10 m", "10–20 m", "20–30 m", "30–40 m", "40+ m"]
    assert (b["0–5 m"]["obstacle_cells"], b["0–5 m"]["valid"]) == (4, 4)
    assert (b["5–10 m"]["obstacle_cells"], b["5–10 m"]["valid"], b["5–10 m"]["ranges"], b["5–10 m"]["unknown"]) == (8, 2, 6, 2)
    assert b["5–10 m"]["valid_rate"] == pytest.approx(2 / 8) and b["5–10 m"]["unknown_rate"] == pytest.approx(2 / 8)
    assert (b["10–20 m"]["valid"], b["20–30 m"]["valid"], b["20–30 m"]["clear"]) == (4, 3, 1)
    assert b["20–30 m"]["dangerous_rate"] == pytest.approx(1 / 4)
    assert (b["30–40 m"]["obstacle_cells"], b["30–40 m"]["valid"], b["30–40 m"]["unknown"]) == (8, 4, 4)
    assert b["40+ m"]["obstacle_cells"] == 0 and b["40+ m"]["valid_rate"] is None
    near = next(t for t in s["targets"] if t["key"] == "detection_near_in_view")
    assert (near["num"], near["n"]) == (6, 12)  # 3 m ×4, 5 m ×2 valid of 3/5/7 m ×4
    det = next(t for t in s["targets"] if t["key"] == "detection_in_view")
    assert (det["num"], det["n"]) == (4 + 2 + 4 + 3 + 4, 28)


def test_warmup_cells_are_not_scored():
    F = 30  # 3 s at 10 Hz
    sec = np.full((F, 72), np.inf)
    sec[:, 0] = 20.0
    truth = SectorTruth(1000.0 + np.arange(F) / 10, sec, np.zeros((F, 3)), np.zeros(F), 60.0, np.ones((F, 72), bool))
    rows = [od(t + 0.01, {0: CLEAR} if f < 20 else {0: 2000}) for f, t in enumerate(truth.t_s)]  # dangerous only in the warm-up
    s = score(truth, RangeMessages.build(od=rows), ScoreConfig())
    assert s["config"]["warmup_s"] == 2.0 and s["warmup"]["messages_excluded"] == 20
    assert s["messages"]["obstacle_distance_scored"] == 10 and s["cells"]["obstacle"] == 10
    assert s["cells"]["dangerous_clears"] == 0 and s["cells"]["valid_ranges"] == 10
    assert s["first_claim_at_s"] == pytest.approx(0.01)  # the first claim counts from the start, warm-up included
    s0 = score(truth, RangeMessages.build(od=rows), NOWARM)
    assert s0["cells"]["dangerous_clears"] == 20 and s0["cells"]["obstacle"] == 30


# ---------------------------------------------------------------------- files and reports ------
def test_truth_npz_new_keys_and_old_files(tmp_path):
    truth = turn_truth()
    base = {"t_s": truth.t_s, "p_ned": truth.p_ned, "rpy": np.c_[np.zeros((10, 2)), truth.yaw], "sector_max_m": np.array(60.0),
            "sector_m": np.where(truth.in_view, truth.sector_m, np.nan)}
    save_npz_deterministic(tmp_path / "old.npz", base)
    save_npz_deterministic(tmp_path / "new.npz", base | {"sector_all_m": truth.sector_m, "in_view": truth.in_view})
    old, new = read_truth_npz(tmp_path / "old.npz"), read_truth_npz(tmp_path / "new.npz")
    assert old.in_view is None and np.isnan(old.sector_m[:, 36]).all() and np.array_equal(old.view, truth.in_view)
    assert np.array_equal(new.in_view, truth.in_view) and np.array_equal(new.sector_m, truth.sector_m)
    with pytest.raises(Exception, match="in_view must be"):
        SectorTruth(truth.t_s, truth.sector_m, truth.p_ned, truth.yaw, 60.0, np.ones((10, 71), bool))


def test_score_md_and_json_carry_the_new_figures(tmp_path):
    truth = turn_truth()
    s = score(truth, msgs_after_turn(truth, 5, 1950))
    write_score(tmp_path / "out", s)
    md = (tmp_path / "out" / "score.md").read_text()
    assert "Warm-up: cells of the first 0 s" in md and "## Detection by true range" in md and "| 20–30 m | 5 |" in md
    assert "Remembered obstacles out of view" in md and "| in view | out of view | all scored |" in md
    line = next(x for x in md.splitlines() if x.startswith("| remembered obstacles out of view"))
    assert line.endswith("| ✓ |")
    assert markdown(score(truth, msgs_after_turn(truth, 5, 1950), ScoreConfig())).count("Warm-up: cells of the first 2 s") == 1


def test_campaign_pools_bins_remembered_and_targets():
    truth = turn_truth()
    good = score(truth, msgs_after_turn(truth, 5, 1950))
    bad = score(truth, msgs_after_turn(truth, 5, U))
    results = [{"seed": 1, "status": "ok", "score": good}, {"seed": 2, "status": "ok", "score": bad}]
    a = C.aggregate(results, {}, NOWARM)
    assert a["remembered"]["cells"] == 10 and a["remembered"]["rate"] == pytest.approx(0.5)
    rem = next(t for t in a["targets"] if t["key"] == "remembered")
    assert rem["pooled"] == pytest.approx(0.5) and rem["n"] == 10 and rem["runs_met"] == 1 and rem["met"] is False
    b = {r["bin"]: r for r in a["detection_by_range"]["out_of_view"]}
    assert b["20–30 m"]["obstacle_cells"] == 10 and b["20–30 m"]["valid"] == 5 and b["20–30 m"]["unknown_rate"] == 0.5
    assert a["cells_out_of_view"]["obstacle"] == 5 and a["pooled_rates_out_of_view"]["valid_range"] == 1.0
    assert a["cells"]["obstacle"] == good["cells"]["obstacle"] + bad["cells"]["obstacle"]
    # the vehicle only turns: its obstacle was never rangeable in either run, and the rangeable counts pool to 0
    (o,) = a["obstacles"]
    assert o["runs_in_range"] == 2 and o["runs_never_rangeable"] == 2 and o["time_to_first_valid_after_rangeable_s"]["n"] == 0
    assert a["rangeable"]["obstacle_cells_in_view"] == 10 and a["rangeable"]["cells"] == 0
    assert a["remembered"]["rangeable_cells"] == 0
    from flightsim.report import index_markdown

    camp = {"scenario_name": "x", "scenario": "x.toml", "mode": "replay", "seeds": [1, 2], "workers": 1, "wall_s": 1.0,
            "fixed_processing_ms": 30.0, "companion_config": None, "score_config": {"warmup_s": 0.0}, "aggregate": a,
            "runs": [{"seed": 1, "status": "ok", "dir": "/tmp/r1", "key_figures": C.run_key_figures(good)}]}
    idx = index_markdown(camp, {}, Path("/tmp/rep"))
    assert "## Detection by true range, pooled" in idx and "Remembered obstacles out of view: 10 cells" in idx
    assert "| 20–30 m | 10 | 50.0 % |" in idx


def test_remembered_needs_the_cell_s_own_point_in_view_not_only_its_obstacle():
    """A wall 10 m north seen only straight ahead (sector 0); after a quarter turn left a cell 35° west of
    north holds another part of the same wall: the obstacle was in view, that part never was."""
    F = 10
    sec = np.full((F, 72), np.inf)
    view = np.zeros((F, 72), bool)
    view[:, [0, 1, 71]] = True  # a narrow ±7.5° camera
    yaw = np.r_[np.zeros(5), np.full(5, -math.pi / 2)]
    sec[:5, [0, 1, 71]] = 10.0
    # after turning left 90° (facing west) the wall north is at sectors 11…18: sector k is 90° − 5k° west of north
    for k in range(11, 19):
        sec[5:, k] = 10.0 / math.cos(math.radians(90.0 - 5.0 * k))  # one wall; only its part at sector 18 was in view
    truth = SectorTruth(1000.0 + np.arange(F) / 10, sec, np.zeros((F, 3)), yaw, 60.0, view)
    rows = [od(t + 0.02, {0: 1000} if f < 5 else {18: 1000, 11: 1220}) for f, t in enumerate(truth.t_s)]
    msgs = RangeMessages.build(od=rows)
    ev = evaluate(msgs, truth, NOWARM)
    assert ev.od_remember[5:, 18].all() and not ev.od_remember[5:, 11].any()
    ev_group = evaluate(msgs, truth, ScoreConfig(warmup_s=0.0, remember_point=False))
    assert ev_group.od_label[5, 11] == ev_group.od_label[5, 18]  # one obstacle to the grouping
    assert ev_group.od_remember[5:, 11].all()  # the obstacle-level rule counted the unseen part
