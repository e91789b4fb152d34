"""Scoring against truth: hand-built messages with known answers, the tlog reader, NEES
of correctly scaled noise in a seeded Monte Carlo, obstacles from a real world, and one short
fly + replay scored end to end."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from companion.core.sectors_types import margin_k
from companion.mavlink import messages as M
from companion.mavlink.dialect import mavlink
from companion.replay import TlogOut
from flightsim.score.config import ScoreConfig
from flightsim.score.evaluation import evaluate
from flightsim.score.inputs import RangeMessages, SectorTruth
from flightsim.score.obstacles import group_obstacles, name_obstacles, world_namer
from flightsim.score.stats import chi2_quantile, nees_band
from flightsim.score.summary import error_table, summarize
from flightsim.cli import main as flightsim_main
from flightsim.score.files import load_score_config, load_series, read_ranges_tlog, read_truth_npz, score_run, write_score

ROOT = Path(__file__).resolve().parents[1]
U = 65535
MAX_CM, MIN_CM = 4000, 50
CLEAR = MAX_CM + 1
NOWARM = ScoreConfig(warmup_s=0.0)  # hand-built runs start scoring at once (the 2-s warm-up has its own test)


def truth_of(sector_rows, t0=1000.0, rate=10.0, sector_max_m=60.0, yaw=None, p_ned=None):
    """SectorTruth whose frames all (or each) have the given sector distances (dict sector → m, rest NaN)."""
    rows = sector_rows if isinstance(sector_rows, list) else [sector_rows]
    F = len(rows)
    sec = np.full((F, 72), np.nan)
    for f, row in enumerate(rows):
        for i, v in row.items():
            sec[f, i] = v
    t = t0 + np.arange(F) / rate
    return SectorTruth(t, sec, np.zeros((F, 3)) if p_ned is None else p_ned, np.zeros(F) if yaw is None else yaw, sector_max_m)


def od(t, values: dict, time_usec=0):
    d = np.full(72, U)
    for i, v in values.items():
        d[i] = v
    return (t, time_usec, d, MIN_CM, MAX_CM)


# ---------------------------------------------------------------------- cells -------------------
def four_messages():
    """Sector 0: obstacle 20 m; 1: nothing (inf); 2: obstacle 35 m; 3: 50 m (beyond max → clear cell)."""
    truth = truth_of([{0: 20.0, 1: np.inf, 2: 35.0, 3: 50.0}] * 10)
    msgs = RangeMessages.build(od=[
        od(1000.05, {0: 1900, 1: CLEAR, 2: CLEAR, 3: 3000}),  # valid, correct clear, DANGEROUS, false (50 − 30 > 10)
        od(1000.15, {0: 1000, 1: 1500, 2: 3400, 3: CLEAR}),  # too near, false (inf), valid, correct clear
        od(1000.25, {}),  # no claim
        od(1000.35, {0: 3000, 1: 5800}),  # over range, invalid value; sector 2 unknown in an obstacle cell
    ])
    return truth, msgs


def test_cells_are_classified_as_defined():
    truth, msgs = four_messages()
    s = summarize(evaluate(msgs, truth, NOWARM))
    c, r = s["cells"], s["rates"]
    assert c["obstacle"] == 8 and c["clear"] == 8
    assert c["detections"] == 4 and c["valid_ranges"] == 2
    assert c["dangerous_clears"] == 1 and c["too_near"] == 1 and c["over_range"] == 1
    assert c["unknown_in_obstacle_cells"] == 3
    assert c["false_obstacles_clear_cells"] == 2 and c["clear_claimed_in_clear_cells"] == 2
    assert c["invalid_values"] == 1 and c["unverifiable_beyond_truth"] == 0
    assert r["detection"] == pytest.approx(4 / 8) and r["dangerous_clear"] == pytest.approx(1 / 8)
    assert r["false_obstacle_clear_cells"] == pytest.approx(2 / 8)
    # per message: A and B have a false obstacle in a clear sector, D does not, C claims nothing
    assert c["messages_eligible_no_false"] == 3 and c["messages_without_false_obstacle"] == 1
    t_msg, t_dang = s["targets"][:2]
    assert [t["key"] for t in s["targets"]] == ["messages_without_false_obstacle", "dangerous_clear", "false_obstacle_clear_cells",
                                               "detection_in_view", "detection_near_in_view", "remembered"]
    assert t_msg["value"] == pytest.approx(1 / 3) and t_msg["met"] is False and t_msg["n"] == 3
    assert t_dang["value"] == pytest.approx(1 / 8) and t_dang["met"] is False
    sec0 = next(x for x in s["sectors"] if x["sector"] == 0)
    assert sec0["obstacle_cells"] == 4 and sec0["detection_rate"] == pytest.approx(0.75) and sec0["too_near"] == 1
    sec1 = next(x for x in s["sectors"] if x["sector"] == 1)
    assert sec1["clear_cells"] == 4 and sec1["false_obstacle_rate"] == pytest.approx(0.25)


def test_range_error_bins():
    truth, msgs = four_messages()
    rows = summarize(evaluate(msgs, truth, NOWARM))["range_error"]["published_all_sectors"]
    assert [r["bin"] for r in rows] == ["0–10 m", "10–20 m", "20–40 m", "40+ m"]
    assert [r["n"] for r in rows] == [0, 0, 4, 0]
    b = rows[2]  # errors −1 (19 vs 20), −10, −1 (34 vs 35), +10
    assert b["bias_m"] == pytest.approx(-0.5) and b["mae_m"] == pytest.approx(5.5)
    assert b["mae_pct"] == pytest.approx(100 * np.mean([1 / 20, 10 / 20, 1 / 35, 10 / 20]))
    rows = error_table([5.0, 15.0, 45.0], [5.5, 14.0, 49.0], (0.0, 10.0, 40.0))
    assert [r["n"] for r in rows] == [1, 1, 1] and rows[1]["bias_m"] == pytest.approx(-1.0) and rows[2]["hi_m"] is None


def test_no_false_obstacle_and_no_dangerous_clear_meet_the_targets():
    truth = truth_of([{0: 20.0, 1: np.inf}] * 5)
    msgs = RangeMessages.build(od=[od(1000.05 + 0.1 * k, {0: 1800, 1: CLEAR}) for k in range(5)])
    s = summarize(evaluate(msgs, truth, NOWARM))
    assert [t["met"] for t in s["targets"]] == [True, True, True, True, None, None]  # nothing near, nothing out of view
    assert s["rates"]["messages_without_false_obstacle"] == 1.0 and s["cells"]["valid_ranges"] == 5


def test_truth_horizon_makes_near_horizon_ranges_unverifiable():
    truth = truth_of([{1: np.inf}] * 3, sector_max_m=40.0)  # "inf" = nothing within 40 m only
    msgs = RangeMessages.build(od=[od(1000.05, {1: 3800}), od(1000.15, {1: 2000})])
    ev = evaluate(msgs, truth, NOWARM)
    s = summarize(ev)
    # 38 m: the truth may be 40.1 m, within tolerance (8 m) → unverifiable; 20 m: false in any case
    assert s["cells"]["unverifiable_beyond_truth"] == 1 and s["cells"]["false_obstacles_clear_cells"] == 1


def test_messages_without_truth_are_counted_not_scored():
    truth = truth_of([{0: 20.0}] * 3)  # frames at 1000.0, 1000.1, 1000.2
    msgs = RangeMessages.build(od=[od(999.9, {0: 2000}), od(1000.05, {0: 2000}), od(1000.35, {0: 2000}),
                                     od(1000.1, {0: 2000}, ) + (False,)])
    s = summarize(evaluate(msgs, truth, ScoreConfig(truth_max_age_s=0.1, warmup_s=0.0)))
    # before the first frame, 0.15 s after the last frame, and a message not in 72 × 5° BODY_FRD
    assert s["messages"]["obstacle_distance_scored"] == 1 and s["messages"]["without_truth"] == 2
    assert s["cells"]["obstacle"] == 1 and any("not in 72" in n for n in s["notes"])


def test_truth_is_the_latest_frame_at_or_before_the_stamp():
    truth = truth_of([{0: 30.0}, {0: 20.0}, {0: 10.0}])
    assert list(truth.frame_at(np.array([1000.0, 1000.099, 1000.1, 1000.25, 1000.31]), 0.1)) == [0, 0, 1, 2, -1]
    msgs = RangeMessages.build(od=[od(1000.199, {0: 2000}), od(1000.2, {0: 1000})])
    ev = evaluate(msgs, truth, NOWARM)
    assert list(ev.od_truth[:, 0]) == [20.0, 10.0]


# ---------------------------------------------------------------------- latency ----------------
def test_latency_maps_exposure_through_the_companions_boot_clock():
    fps, t0, boot0 = 30.0, 1000.0, 990.0  # recording = boot + 990 s
    truth = truth_of([{0: 20.0}] * 60, t0=t0, rate=fps)
    lat = np.array([0.030, 0.045, 0.060, 0.090] * 5)
    od_rows, boot = [], []
    for k, L in enumerate(lat):
        f = 3 * k
        t_cap = truth.t_s[f]
        usec = int(round((t_cap - boot0) * 1e6)) + 4000  # the companion's mapping is 4 ms off: snaps to the frame
        od_rows.append(od(t_cap + L, {0: 2000}, usec))
        boot.append((t_cap + L + 0.0005, int(round((t_cap + L - boot0) * 1000))))  # DISTANCE_SENSOR send stamps
    od_rows.append(od(truth.t_s[-1], {}, 0))  # an all-unknown message without an exposure
    ev = evaluate(RangeMessages.build(od=od_rows, boot=boot), truth, NOWARM)
    s = summarize(ev)["latency"]
    assert s["n"] == 20 and s["unmatched_exposures"] == 0
    assert s["p50_ms"] == pytest.approx(np.percentile(lat * 1000, 50), abs=1e-6)
    assert s["p99_ms"] == pytest.approx(np.percentile(lat * 1000, 99), abs=1e-6)
    assert s["boot_offset_s"] == pytest.approx(boot0, abs=1e-3)
    assert list(ev.od_capture_frame[:20]) == list(range(0, 60, 3))


def test_latency_unknown_without_sending_times():
    truth = truth_of([{0: 20.0}] * 3)
    ev = evaluate(RangeMessages.build(od=[od(1000.05, {0: 2000}, 10_000_000)]), truth, NOWARM)
    s = summarize(ev)
    assert s["latency"]["n"] == 0 and any("time_boot_ms" in n for n in s["notes"])


# ---------------------------------------------------------------------- σ and NEES -------------
def nees_campaign(noise_scale: float, n: int = 3000, seed: int = 7, delay_s: float = 0.04, taper=None, scored_taper=None):
    """Forward estimates with σ reported via covariance (σ < 16 cm) or signal_quality, noise = scale·σ.
    ``taper`` (k_far, from_m, to_m): the companion narrows its margin far away ([sectors] sigma_k_taper_*);
    ``scored_taper``: the taper the scorer is told of (default: the one published with)."""
    rng = np.random.default_rng(seed)
    fps, t0, boot0 = 30.0, 2000.0, 1900.0
    T = rng.uniform(2.0, 35.0, n)  # true forward distance per frame, jumping frame to frame
    truth = truth_of([{0: v} for v in T], t0=t0, rate=fps)
    od_rows, ds_rows, boot = [], [], []
    k, zrel = 2.0, 0.5
    k_far, t_from, t_to = taper or (k, 10.0, 0.0)
    for f in range(n - 1):
        t_cap, t_send = truth.t_s[f], truth.t_s[f] + delay_s  # 40 ms: arrives after the next frame
        if f % 2:
            sigma = 0.1  # covariance = 100 cm²
            est = T[f] + noise_scale * sigma * rng.standard_normal()
            pub = est - margin_k(est, k, k_far, t_from, t_to) * sigma
            cm = int(round(pub * 100))
            cov, q = 100, M.signal_quality(cm / 100, sigma, zrel)
        else:
            sigma = 0.04 * T[f]
            est = T[f] + noise_scale * sigma * rng.standard_normal()
            pub = est - margin_k(est, k, k_far, t_from, t_to) * sigma
            cm = int(round(pub * 100))
            cov, q = 255, M.signal_quality(cm / 100, sigma, zrel)
        if not MIN_CM < cm < MAX_CM:
            continue
        od_rows.append(od(t_send, {0: cm}, int(round((t_cap - boot0) * 1e6))))
        ds_rows.append((t_send, cm, MIN_CM, MAX_CM, cov, q))
        boot.append((t_send, int(round((t_send - boot0) * 1000))))
    sk_far, s_from, s_to = scored_taper or (k_far, t_from, t_to)
    cfg = ScoreConfig(sigma_k=k, sigma_k_far=sk_far, sigma_k_taper_from_m=s_from, sigma_k_taper_to_m=s_to, warmup_s=0.0)
    ev = evaluate(RangeMessages.build(od=od_rows, ds=ds_rows, boot=boot), truth, cfg)
    return summarize(ev)


def test_nees_is_one_for_correctly_scaled_noise():
    s = nees_campaign(1.0)
    ne = s["nees"]
    assert ne["n"] > 2500
    assert s["distance_sensor"]["sigma_from_covariance"] > 1000 and s["distance_sensor"]["sigma_from_signal_quality"] > 1000
    assert ne["band"][0] <= ne["mean"] <= ne["band"][1] and ne["consistent"] is True
    assert ne["mean"] == pytest.approx(1.0, abs=0.1)
    # the truth at arrival is another frame (the distance jumps): against it the σ is not consistent
    assert ne["arrival"]["mean"] > 10
    # arriving within the exposure's frame: the estimate (published + k·σ) is centred, the published value k·σ short
    s = nees_campaign(1.0, delay_s=0.01)
    assert s["nees"]["arrival"]["mean"] == pytest.approx(s["nees"]["mean"])
    est = s["range_error"]["estimate_forward"][2]
    pub = s["range_error"]["published_forward"][2]
    assert est["n"] > 500 and abs(est["bias_m"]) < 0.05 and pub["bias_m"] == pytest.approx(
        -2 * (0.5 * 0.1 + 0.5 * 0.04 * 27.5), rel=0.1)  # half σ = 0.1 m, half σ = 0.04·T with T ~ U(20, 35) in this bin


def test_the_scorer_undoes_a_tapered_margin():
    """The companion's margin narrowed far away (k 2 up to 10 m, 1 from 20 m): told of the taper, the
    scorer recovers the estimate behind each published value (centred, NEES ≈ 1, as with one k); told
    of one k only, it puts the far estimates σ too far (biased, NEES off its band)."""
    s = nees_campaign(1.0, delay_s=0.01, taper=(1.0, 10.0, 20.0))
    est = s["range_error"]["estimate_forward"][2]
    pub = s["range_error"]["published_forward"][2]
    assert est["n"] > 500 and abs(est["bias_m"]) < 0.05
    assert pub["bias_m"] == pytest.approx(-(0.5 * 0.1 + 0.5 * 0.04 * 27.5), rel=0.1)  # k = 1 in this bin (20–40 m)
    assert s["nees"]["band"][0] <= s["nees"]["mean"] <= s["nees"]["band"][1]
    wrong = nees_campaign(1.0, delay_s=0.01, taper=(1.0, 10.0, 20.0), scored_taper=(2.0, 10.0, 0.0))
    assert wrong["range_error"]["estimate_forward"][2]["bias_m"] > 0.3 and wrong["nees"]["mean"] > wrong["nees"]["band"][1]


def test_nees_flags_a_sigma_reported_twice_too_small():
    ne = nees_campaign(2.0)["nees"]
    assert ne["mean"] == pytest.approx(4.0, rel=0.15) and ne["consistent"] is False


def test_sigma_sources_and_clamped_values():
    truth = truth_of([{0: 20.0}] * 3)
    ds = [(1000.05, 1950, MIN_CM, MAX_CM, 100, 99),  # covariance: σ = 0.10 m
          (1000.10, 1900, MIN_CM, MAX_CM, 255, 90),  # quality: σ = 19·0.5·0.1 = 0.95 m
          (1000.15, 1900, MIN_CM, MAX_CM, 255, 2),  # saturated quality: σ unknown
          (1000.20, MAX_CM, MIN_CM, MAX_CM, 255, 50),  # clamped at max: not undone
          (1000.25, CLEAR, MIN_CM, MAX_CM, 255, 100)]  # "clear" while an obstacle is ahead
    ev = evaluate(RangeMessages.build(ds=ds), truth, NOWARM)
    assert ev.ds_sigma_m[0] == pytest.approx(0.1) and ev.ds_sigma_m[1] == pytest.approx(0.95)
    assert np.isnan(ev.ds_sigma_m[2:]).all() and list(ev.ds_sigma_source) == [1, 2, 0, 0, 0]
    assert ev.ds_estimate_m[1] == pytest.approx(19.0 + 2 * 0.95)
    s = summarize(ev)
    assert s["distance_sensor"]["dangerous_clears"] == 1 and s["distance_sensor"]["ranges"] == 4


def test_chi2_band_matches_scipy():
    stats = pytest.importorskip("scipy.stats")
    for n in (1, 2, 5, 30, 200, 3000, 100000):
        lo, hi = nees_band(n, 0.95)
        assert lo == pytest.approx(stats.chi2.ppf(0.025, n) / n, rel=1e-6)
        assert hi == pytest.approx(stats.chi2.ppf(0.975, n) / n, rel=1e-6)
    assert chi2_quantile(0.5, 3) == pytest.approx(stats.chi2.ppf(0.5, 3), rel=1e-9)


# ---------------------------------------------------------------------- obstacles ---------------
@pytest.fixture(scope="module")
def approach_truth():
    """Truth of a straight approach in the quad_approach world (building + mast), all sectors."""
    from flightsim.world import load_world, sector_truth
    from companion.core.frames import euler_zyx_to_R

    world = load_world(ROOT / "configs" / "worlds" / "quad_approach.toml")
    xs = np.linspace(0.0, 34.0, 69)
    p = np.stack([xs, np.zeros_like(xs), np.full_like(xs, -10.0)], 1)
    R = euler_zyx_to_R(0.0, 0.0, 0.0)
    sec = np.stack([sector_truth(world, R, pi, None, 40.0) for pi in p])
    sec[:, 8:64] = np.nan  # a ±37.5° camera
    return world, SectorTruth(1000.0 + 0.1 * np.arange(len(xs)), sec, p, np.zeros(len(xs)), 40.0)


def test_obstacles_are_grouped_and_named(approach_truth):
    world, truth = approach_truth
    labels, centroids, points = group_obstacles(truth)
    names = name_obstacles(centroids, points, world_namer(world))
    assert sorted(names) == ["building", "mast"]
    mast = names.index("mast")
    assert np.hypot(*(centroids[mast] - [40.0, 3.0])) < 1.5
    # every finite cell got a group, nothing else did
    assert np.array_equal(labels >= 0, np.isfinite(truth.sector_m))
    assert name_obstacles(centroids, points, None)[0].startswith("obstacle 1 (N ")


def test_time_to_first_valid_range(approach_truth):
    world, truth = approach_truth
    labels, _, _ = group_obstacles(truth)
    names = name_obstacles(*group_obstacles(truth)[1:], world_namer(world))
    k_mast = names.index("mast")
    rows = []
    for f, t in enumerate(truth.t_s):
        vals = {}
        for i in np.flatnonzero(labels[f] == k_mast):
            T = truth.sector_m[f, i]
            if f >= 30:
                vals[int(i)] = int(round(T * 100))  # exact from frame 30 on
            elif f >= 20:
                vals[int(i)] = int(round(0.5 * T * 100))  # half the distance: a detection, not valid
        rows.append(od(t + 0.02, vals))
    s = summarize(evaluate(RangeMessages.build(od=rows), truth, NOWARM, namer=world_namer(world)))
    o = next(x for x in s["obstacles"] if x["name"] == "mast")
    first_in = np.flatnonzero(np.any(labels == k_mast, axis=1) & np.any(truth.sector_m <= 40.0, axis=1))[0]
    assert o["in_range_at_s"] == pytest.approx(truth.t_s[first_in] + 0.02 - truth.t_s[0])
    assert o["first_detection_at_s"] == pytest.approx(truth.t_s[20] + 0.02 - truth.t_s[0])
    assert o["time_to_first_valid_s"] == pytest.approx(truth.t_s[30] - truth.t_s[first_in])
    b = next(x for x in s["obstacles"] if x["name"] == "building")
    assert b["time_to_first_valid_s"] is None and b["detected_fraction"] == 0.0


# ---------------------------------------------------------------------- files -------------------
def write_ranges_tlog(path, truth_t0=1000.0):
    w = TlogOut(path, system_id=1, component_id=196)
    other = TlogOut(path.with_suffix(".other"), system_id=1, component_id=1)
    w.write(truth_t0 + 0.05, M.heartbeat(mavlink.MAV_STATE_ACTIVE))
    w.write(truth_t0 + 0.05, M.obstacle_distance(np.r_[[1900], [CLEAR], np.full(70, U)], MIN_CM, MAX_CM, 0))
    w.write(truth_t0 + 0.05, M.distance_sensor("obstacle", 19.0, 0.1, MIN_CM, MAX_CM, 12345))
    w.write(truth_t0 + 0.06, M.named_value_float("MR_FPS", 30.0, 12355))
    for m in M.statustext("Ranging active"):
        w.write(truth_t0 + 0.07, m)
    w.write(truth_t0 + 0.15, M.obstacle_distance(np.r_[[CLEAR], [1500], np.full(70, U)], MIN_CM, MAX_CM, 0))
    w.close()
    # an autopilot message from component 1 and some garbage in between
    other.write(truth_t0 + 0.1, mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3))
    other.close()
    data = path.read_bytes() + path.with_suffix(".other").read_bytes() + b"\x00\x00\x00\x01garbage!!"
    path.write_bytes(data)


def test_reader_and_writers_round_trip(tmp_path):
    tlog = tmp_path / "ranges.tlog"
    write_ranges_tlog(tlog)
    msgs = read_ranges_tlog(tlog)
    assert msgs.counts["by_type"] == {"HEARTBEAT": 1, "OBSTACLE_DISTANCE": 2, "DISTANCE_SENSOR": 1,
                                      "NAMED_VALUE_FLOAT": 1, "STATUSTEXT": 1}
    assert msgs.counts["foreign"] == 1
    assert msgs.od_distances_cm[0, 0] == 1900 and msgs.od_geometry_ok.all() and msgs.od_t[1] == pytest.approx(1000.15)
    assert list(msgs.ds_covariance) == [100] and list(msgs.boot_ms) == [12345, 12355]
    assert msgs.texts[0][2] == "Ranging active" and list(msgs.heartbeat_status) == [mavlink.MAV_STATE_ACTIVE]
    from flightsim.fly import save_npz_deterministic

    truth = truth_of([{0: 20.0, 1: np.inf}] * 5)
    save_npz_deterministic(tmp_path / "truth.npz", {"t_s": truth.t_s, "sector_m": truth.sector_m, "p_ned": truth.p_ned,
                                                    "rpy": np.zeros((5, 3)), "sector_max_m": np.array(60.0)})
    s = score_run(tlog, tmp_path / "truth.npz", series_out=tmp_path / "score_series.npz", warmup_s=0.0)
    assert s["cells"]["detections"] == 1 and s["cells"]["dangerous_clears"] == 1
    assert s["cells"]["false_obstacles_clear_cells"] == 1 and s["cells"]["clear_claimed_in_clear_cells"] == 1
    write_score(tmp_path / "out", s)
    back = json.loads((tmp_path / "out" / "score.json").read_text())  # strict JSON: no NaN
    assert back["cells"] == s["cells"]
    md = (tmp_path / "out" / "score.md").read_text()
    assert "✗" in md and "## Definitions" in md and "max(2 m, 20 % of the true distance)" in md
    assert "## NEES and coverage of the reported σ" in md and "nees.png" not in md  # no plot asked for
    assert not (tmp_path / "out" / "nees.png").exists() and "plots" not in s
    assert set(load_series(tmp_path / "score_series.npz")) >= {"od_t", "od_cm", "nees_exposure", "obstacle_names"}
    with pytest.raises(Exception, match="unknown option"):
        score_run(tlog, tmp_path / "truth.npz", toleranse_m=3.0)


def test_bad_inputs_are_named(tmp_path):
    from companion.errors import ConfigError

    with pytest.raises(ConfigError, match="no such tlog"):
        read_ranges_tlog(tmp_path / "nope.tlog")
    bad = tmp_path / "t.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ConfigError, match="not a truth.npz"):
        read_truth_npz(bad)
    np.savez(bad, t_s=np.arange(3.0))
    with pytest.raises(ConfigError, match="missing sector_m"):
        read_truth_npz(tmp_path / "t.npz")
    cfg = tmp_path / "s.toml"
    cfg.write_text("[score]\ntolerance_m = -1.0\n")
    with pytest.raises(ConfigError, match="tolerance_m must be >= 0"):
        load_score_config(cfg)
    cfg.write_text("[score]\ntolerence_m = 1.0\n")
    with pytest.raises(ConfigError, match="unknown key"):
        load_score_config(cfg)
    assert load_score_config(ROOT / "configs" / "score.toml") == ScoreConfig()
    # an empty tlog, or one that is not MAVLink, is bad input (exit 2), not a run without ranges
    (tmp_path / "empty.tlog").write_bytes(b"")
    with pytest.raises(ConfigError, match="empty"):
        read_ranges_tlog(tmp_path / "empty.tlog")
    (tmp_path / "junk.tlog").write_bytes(bytes(range(256)) * 8)
    with pytest.raises(ConfigError, match="not a MAVLink tlog"):
        read_ranges_tlog(tmp_path / "junk.tlog")
    # a tlog without a message from the companion scores to zero counts, never crashes
    w = TlogOut(tmp_path / "autopilot.tlog", system_id=1, component_id=1)
    w.write(1000.0, mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3))
    w.close()
    msgs = read_ranges_tlog(tmp_path / "autopilot.tlog")
    s = summarize(evaluate(msgs, truth_of([{0: 20.0}] * 3), NOWARM))
    assert s["cells"]["obstacle"] == 0 and s["targets"][0]["met"] is None


# ---------------------------------------------------------------------- end to end -------------
@pytest.fixture(scope="module")
def flown_and_replayed(tmp_path_factory):
    """A 3-s quad_approach flight, replayed through the companion with a fixed processing time."""
    from companion.cli import load_config
    from companion.replay import replay
    from flightsim.fly import fly
    from flightsim.scenario import load_scenario

    tmp = tmp_path_factory.mktemp("score_e2e")
    text = (ROOT / "configs" / "scenarios" / "quad_approach.toml").read_text()
    text = re.sub(r'^world = "\.\./worlds/', f'world = "{(ROOT / "configs" / "worlds").as_posix()}/', text, flags=re.M)
    text = re.sub(r"^duration_s = .*$", "duration_s = 3.0", text, flags=re.M)
    sp = tmp / "short.toml"
    sp.write_text(text)
    sc = load_scenario(sp)
    run = tmp / "run"
    fly(sc, run, plot=False)
    rc = load_config(str(ROOT / "configs" / "companion.toml"), None, str(run / "camera.toml"))
    summary = replay(run / "telemetry.tlog", run / "video.avi", run / "frames.csv", run / "ranges.tlog", rc.companion,
                     camera=rc.companion.camera, pipeline=rc.pipeline, fixed_processing_s=0.03)
    return sp, run, summary


def test_end_to_end_fly_replay_score(flown_and_replayed, capsys):
    sp, run, summary = flown_and_replayed
    assert flightsim_main(["--log-level", "WARNING", "score", str(run), "--scenario", str(sp),
                           "--companion-config", str(ROOT / "configs" / "companion.toml")]) == 0
    out = capsys.readouterr().out
    assert "wrote" in out and "dangerous clear" in out
    s = json.loads((run / "score.json").read_text())
    c = s["cells"]
    # latency from the tlog's own stamps equals the replay's capture → send latency
    assert s["latency"]["n"] > 0 and s["latency"]["unmatched_exposures"] == 0
    assert s["latency"]["p50_ms"] == pytest.approx(summary.latency_p50_ms, abs=1.0)
    # every obstacle cell is a detection, a dangerous clear, unknown or invalid
    assert c["obstacle"] > 0  # the mast stands 39.8 m ahead from the start
    assert c["detections"] + c["dangerous_clears"] + c["unknown_in_obstacle_cells"] <= c["obstacle"]
    assert s["messages"]["by_type"]["OBSTACLE_DISTANCE"] == s["messages"]["obstacle_distance"]
    assert any(o["name"] == "mast" for o in s["obstacles"])
    # NEES with its effective sample size and the coverage of the reported σ, and the plot of both (this
    # short flight has no forward range yet: the keys are there, empty; test_correlated_run_scored_from_files
    # has the numbers)
    ne, ser = s["nees"], load_series(run / "score_series.npz")
    assert {"n", "n_eff", "band", "band_independent", "consistent", "consistent_independent", "autocorrelation_time",
            "stretches", "gap_s", "coverage"} <= set(ne)
    assert ne["n"] == ser["nees_exposure"].size == ser["nees_exposure_t"].size == ne["coverage"]["n"]
    assert ne["coverage"]["expected_2sigma"] == pytest.approx(0.9545, abs=1e-4)
    if ne["n"] == 0:
        assert ne["n_eff"] is None and ne["band"] is None and ne["consistent"] is None and ne["coverage"]["rate_2sigma"] is None
    else:
        assert 1.0 <= ne["n_eff"] <= ne["n"]
    assert s["plots"] == {"nees": "nees.png"} and (run / "nees.png").stat().st_size > 5_000
    assert "## NEES and coverage of the reported σ" in (run / "score.md").read_text()
    # one cell recomputed independently from the files: the latest frame at or before the stamp
    msgs = read_ranges_tlog(run / "ranges.tlog")
    with np.load(run / "truth.npz") as z:
        t_s, sec = z["t_s"], z["sector_m"]
    j = np.searchsorted(t_s, msgs.od_t[5], side="right") - 1
    i = int(np.flatnonzero(np.isfinite(sec[j]))[0])
    ev = evaluate(msgs, read_truth_npz(run / "truth.npz"))
    assert ev.od_truth[5, i] == sec[j, i]
    # missing inputs: exit 2 naming them
    assert flightsim_main(["score", str(run / "nope")]) == 2
    assert "no such run directory" in capsys.readouterr().err


# ---------------------------------------------------------------------- NEES from files ---------
from score_inputs import write_correlated_run  # noqa: E402  (tests/score_inputs.py: shared with the campaign tests)


def test_correlated_run_scored_from_files(tmp_path, capsys):
    """A correctly scaled but strongly correlated forward error, scored from its files: the samples
    are worth about n (1 − φ²)/(1 + φ²) independent ones, the mean sits in the band for n_eff but
    not in the one for n independent samples, ±2σ covers about 95.4 %, nees.png is drawn; σ
    reported half the truth fails even the wide band and covers far less."""
    k = 2.0
    cfg = tmp_path / "score.toml"
    cfg.write_text(f"[score]\nsigma_k = {k}\n")
    write_correlated_run(tmp_path / "ok", 1.0, k=k)
    assert flightsim_main(["--log-level", "WARNING", "score", str(tmp_path / "ok"), "--config", str(cfg)]) == 0
    out = capsys.readouterr().out
    ne = json.loads((tmp_path / "ok" / "score.json").read_text())["nees"]
    n = ne["n"]
    assert 1350 < n < 1420 and ne["stretches"] == 2
    assert ne["n_eff"] == pytest.approx(n * (1 - 0.81) / (1 + 0.81), rel=0.35)
    assert ne["consistent"] is True and ne["consistent_independent"] is False  # the latter: this seed (about half of them)
    assert ne["coverage"]["rate_2sigma"] == pytest.approx(0.954, abs=0.04)
    assert ne["coverage"]["rate_1sigma"] == pytest.approx(0.683, abs=0.12)
    assert ne["arrival"]["n_eff"] == pytest.approx(ne["n_eff"], rel=0.05)  # arrives within the exposure's frame
    assert (tmp_path / "ok" / "nees.png").stat().st_size > 10_000 and "nees.png" in out and "n_eff" in out
    ser = load_series(tmp_path / "ok" / "score_series.npz")
    assert sorted(set(ser["nees_exposure_stretch"].tolist())) == [0, 1]
    write_correlated_run(tmp_path / "half", 2.0, k=k)
    assert flightsim_main(["--log-level", "WARNING", "score", str(tmp_path / "half"), "--config", str(cfg), "--no-plot"]) == 0
    ne = json.loads((tmp_path / "half" / "score.json").read_text())["nees"]
    assert ne["consistent"] is False and ne["mean"] > ne["band"][1]
    assert ne["coverage"]["rate_2sigma"] < 0.8 and not (tmp_path / "half" / "nees.png").exists()
    assert math.isfinite(ne["autocorrelation_time"]) and ne["autocorrelation_time"] > 3
