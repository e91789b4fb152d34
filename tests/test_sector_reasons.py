"""Why a sector is unknown (docs/derivations/sectors.md, "Why a sector is unknown"): every reason from a
hand-built scene with exact geometry, through the compiled kernel and the numpy reference; the reasons
turned with the vehicle, withheld "clear", the forward reading's reason, the sector log and the score."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.mavlink.dialect import UINT16_MAX  # noqa: I001 (first: MAVLink 2)
from companion.core.sectors import (
    SectorConfig,
    SectorState,
    UnknownReason as R,
    compute_sectors,
    compute_sectors_reference,
    forward_unknown_reason,
)
from companion.core.sectors_confirm import confirm_clear
from companion.io.config_files import CompanionConfig
from companion.pipeline import FrameResult, PipelineConfig
from companion.reporter import Reporter
from companion.sector_log import SectorLog, read_sector_log, read_sector_reasons
from flightsim.campaign import pool_log_counts
from flightsim.score.config import ScoreConfig
from flightsim.score.evaluation import evaluate
from flightsim.score.inputs import RangeMessages, SectorTruth
from flightsim.score.markdown import markdown
from flightsim.score.summary import summarize

HFOV = math.radians(60.0)
CFG = SectorConfig()  # shipped defaults: band ±1.5 m, max 40 m, 3 far points for "clear", corridor 0.5 m
BOTH = pytest.mark.parametrize("fn", [compute_sectors, compute_sectors_reference])


def at(d, bearing_deg, z=0.0):
    """A point ``d`` m away (horizontally) at a body bearing, ``z`` m below the vehicle (FRD)."""
    b = math.radians(bearing_deg)
    return [d * math.cos(b), d * math.sin(b), z]


def run(fn, pts, conv, config=CFG, **kw):
    p = np.asarray(pts, float).reshape(-1, 3)
    n = len(p)
    return fn(p, np.full(n, 0.2), np.broadcast_to(np.asarray(conv, bool), (n,)).copy(), np.ones(n, bool), HFOV, 0.0,
              config, **kw)


@BOTH
def test_every_reason_from_one_scene(fn):
    """Sectors (5° each, the camera sees −30…30°; the sector at ±30° partly):
    0: a converged point 10 m ahead (a claim); 1 (5°): nothing; 2 (10°): points 8 m above the vehicle only;
    3 (15°): two converged points 60 m away (clear needs 3); 4 (20°): three far points and a converged point
    12 m away 2 m below the band (within the veto margin beside it); 5 (25°): three far points and one in the
    band not yet converged; 6 (30°, partly in view): three far points; 70 (−10°): three far points beside
    sector 71's obstacle 2 m away (the corridor holds "clear" back); 66 (−30°) partly in view, nothing;
    36 (behind): out of view."""
    far = lambda b: [at(60, b - 1), at(60, b), at(60, b + 1)]  # noqa: E731
    pts = [at(10, 0)] + [at(12, 10, -8.0), at(12, 10.5, -8.5)] + [at(60, 14), at(60, 16)]
    conv = [True] * 5
    pts += far(20) + [at(12, 20, 3.5)]
    conv += [True] * 4
    pts += far(25) + [at(15, 25)]
    conv += [True] * 3 + [False]
    pts += [at(60, 29.5), at(60, 30), at(60, 31)]
    conv += [True] * 3
    pts += far(-10) + [at(2.0, -5)]
    conv += [True] * 4
    sec = run(fn, pts, conv)
    why = sec.unknown_reason
    assert why.dtype == np.int8 and why.shape == (72,)
    assert sec.state[0] == SectorState.OBSTACLE and why[0] == R.NONE
    assert sec.state[71] == SectorState.OBSTACLE and why[71] == R.NONE
    expect = {1: R.NO_POINTS, 2: R.BESIDE_BAND, 3: R.FEW_FAR, 4: R.VETOED, 5: R.RANGING, 6: R.PARTLY_IN_VIEW,
              70: R.HELD, 66: R.NO_POINTS, 36: R.NOT_SEEN, 12: R.NOT_SEEN}
    for s, r in expect.items():
        assert sec.state[s] == SectorState.UNKNOWN, s
        assert why[s] == r, (s, R(int(why[s])).name, r.name)
    # a reason exactly where a sector is unknown
    assert np.array_equal(why != R.NONE, sec.state == SectorState.UNKNOWN)
    # without the corridor sector 70 is clear, and so is sector 6 once the camera sees all of it (a wider lens)
    open_ = run(fn, pts, conv, dataclasses.replace(CFG, clear_corridor_m=0.0))
    assert open_.state[70] == SectorState.CLEAR and open_.unknown_reason[70] == R.NONE
    wide = fn(np.asarray(pts, float), np.full(len(pts), 0.2), np.asarray(conv), np.ones(len(pts), bool),
              math.radians(70.0), 0.0, CFG)
    assert wide.state[6] == SectorState.CLEAR


@BOTH
def test_too_few_near_points_and_a_pole_below_the_band_on_the_ground(fn):
    cfg2 = dataclasses.replace(CFG, min_points_obstacle=2)
    sec = run(fn, [at(10, 0)], [True], cfg2)
    assert sec.state[0] == SectorState.UNKNOWN and sec.unknown_reason[0] == R.FEW_NEAR
    # the ground (known 4 m below) is no obstacle and no evidence, but it is tracked: beside the band, not "no points"
    sec = run(fn, [at(8, 0, 4.0), at(9, 0, 4.0)], [True, True], ground_height_m=4.0)
    assert sec.state[0] == SectorState.UNKNOWN and sec.unknown_reason[0] == R.BESIDE_BAND


@BOTH
def test_a_remembered_obstacle_out_of_view_is_a_claim_and_the_rest_is_not_seen(fn):
    mem = np.array([at(8, 90), at(8, 90.5)])
    sec = fn(np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool), np.zeros(0, bool), HFOV, 0.0, CFG,
             remembered_p_body=mem, remembered_sigma=np.full(2, 0.1), remembered_tangential_sigma=np.full(2, 0.01))
    assert sec.state[18] == SectorState.OBSTACLE and sec.unknown_reason[18] == R.NONE
    assert sec.unknown_reason[17] == R.NOT_SEEN and sec.unknown_reason[0] == R.NO_POINTS


def test_reasons_turn_with_the_vehicle():
    """Sector 0 claims 10 m, sector 1 has nothing, sector 2 points beside the band.  New sector i covers the
    bearings old i + Δψ/5° covered: after a right turn of 5° each takes the reason of the one to its right; after
    2.5° it overlaps two old sectors, and an unknown one takes the reason of the first unknown of them."""
    sec = run(compute_sectors, [at(10, 0), at(12, 10, -8.0)], [True, True])
    w = sec.unknown_reason
    assert (w[0], w[1], w[2]) == (R.NONE, R.NO_POINTS, R.BESIDE_BAND)
    five = sec.rotated_reasons(math.radians(5.0))
    assert five[71] == R.NONE and five[0] == R.NO_POINTS and five[1] == R.BESIDE_BAND
    d_half = sec.rotated(math.radians(2.5))
    half = sec.rotated_reasons(math.radians(2.5), d_half)
    assert np.array_equal(half != R.NONE, d_half == UINT16_MAX)
    assert half[0] == R.NONE and half[1] == R.NO_POINTS and half[2] == R.BESIDE_BAND
    assert np.array_equal(half, sec.rotated_reasons(math.radians(2.5)))  # the distances computed on the way or given


def test_an_obstacle_turned_out_of_its_sector_leaves_turned():
    """Sector 71 (−5°) clear, sector 0 an obstacle at 2.4°.  Turned 1° left, new sector 0 overlaps old 71 and 0:
    "clear" needs both clear, and the obstacle point now lies at 3.4°, in sector 1: unknown for no reason of its own."""
    cfg = dataclasses.replace(CFG, clear_corridor_m=0.0)
    sec = run(compute_sectors, [at(10, 2.4), at(60, -6), at(60, -5), at(60, -4)], [True] * 4, cfg)
    assert sec.state[0] == SectorState.OBSTACLE and sec.state[71] == SectorState.CLEAR
    d = sec.rotated(math.radians(-1.0))
    r = sec.rotated_reasons(math.radians(-1.0), d)
    assert d[0] == UINT16_MAX and r[0] == R.TURNED
    assert d[1] != UINT16_MAX and r[1] == R.NONE
    assert np.array_equal(r != R.NONE, d == UINT16_MAX)
    assert np.all(sec.rotated_reasons(math.nan) == R.TURNED)


def test_withheld_clear_is_held_and_the_forward_reason():
    far = [at(60, -1), at(60, 0), at(60, 1)]
    sec = run(compute_sectors, far, [True] * 3)
    assert sec.state[0] == SectorState.CLEAR and forward_unknown_reason(sec, 2.5) == R.NONE
    held, run_ = confirm_clear(sec, None, 0.0, dataclasses.replace(CFG, clear_confirm_frames=3))
    assert held.state[0] == SectorState.UNKNOWN and held.unknown_reason[0] == R.HELD and run_[0] == 1
    assert forward_unknown_reason(held, 2.5) == R.HELD
    ranging = run(compute_sectors, [at(8, 0)], [False])
    assert forward_unknown_reason(ranging, 2.5) == R.RANGING
    assert forward_unknown_reason(run(compute_sectors, [at(8, 0)], [True]), 2.5) == R.NONE


def test_the_reporter_logs_the_turned_reasons_and_sends_the_forward_one():
    cfg = CompanionConfig()
    got = []
    rep = Reporter(cfg, PipelineConfig(), start=9.0, sector_sink=lambda *a: got.append(a))
    sec = run(compute_sectors, [at(10, 0), at(12, 10, -8.0), at(9, -20)], [False, True, True], cfg.sectors)
    res = FrameResult(1, 10.0, 10.0, 0.005, True, "ok", sectors=sec, yaw=0.0, n_tracks=10, t_boot_capture=10.0)
    msgs = rep.on_result(res, 10.03, yaw_now=math.radians(5.0), last_frame_at=10.0)
    od = [m for _, m in msgs if m.get_type() == "OBSTACLE_DISTANCE"]
    assert len(od) == 1 and len(got) == 1
    why = got[0][5]
    assert np.array_equal(why, sec.rotated_reasons(math.radians(5.0)))
    assert np.array_equal(why != R.NONE, np.asarray(od[0].distances) == UINT16_MAX)
    msgs += rep.tick(10.04, yaw_now=math.radians(5.0), last_frame_at=10.0)  # the diagnostics fall due (≤ 1 Hz)
    nv = {m.name: m.value for _, m in msgs if m.get_type() == "NAMED_VALUE_FLOAT"}
    assert nv["MR_FWD_WHY"] == float(R.RANGING) and nv["MR_FWD_M"] == -1.0


def test_the_sector_log_round_trip_and_bad_lines(tmp_path):
    sec = run(compute_sectors, [at(10, 0), at(12, 10, -8.0)], [True, True])
    path = tmp_path / "s.jsonl"
    sl = SectorLog(path)
    sl("autopilot", 7, sec.distances_cm, sec.sources(), (1000, 255, 80), sec.unknown_reason)
    sl("autopilot", 8, sec.distances_cm, sec.sources())  # an older writer: no reasons
    sl("autopilot", 9, sec.distances_cm, sec.sources(), None, np.full(72, R.TURNED, np.int8))
    sl.close()
    with open(path, "a", encoding="ascii") as fh:
        bad = '{"out": "autopilot", "time_usec": 10, "d": ' + str([65535] * 72) + ', "src": "' + "0" * 72 + '", "why": "'
        fh.write(bad + "z" * 72 + '"}\n')  # not a hexadecimal reason
        fh.write(bad + "b" * 72 + '"}\n')  # beyond the last reason
        fh.write(bad + "1" * 71 + '"}\n')  # one short
    reasons = read_sector_reasons(path)
    key = (7, sec.distances_cm.astype(np.uint16).tobytes())
    assert set(reasons) == {key, (9, key[1])}
    assert np.array_equal(reasons[key], sec.unknown_reason) and reasons[key].dtype == np.int8
    assert np.all(reasons[(9, key[1])] == R.TURNED)  # "a" is read as 10
    assert sorted(k[0] for k in read_sector_log(path)) == [7, 8, 9, 10]  # the sources of every line, those without reasons too
    head = path.read_text().splitlines()[0]
    assert '"a": "turned"' in head and '"6": "ranging"' in head


def test_the_score_splits_unknown_cells_by_reason():
    """Four messages facing north: an obstacle 20 m ahead (sector 0) and 20 m to the right (sector 18, out of view),
    clear elsewhere.  Sector 0 is unknown in the first three (ranging, ranging, no points) and claimed in the last;
    sector 18 is unknown (not seen) in all; sector 2 (clear, in view) unknown for too few far points; the last
    message has no log line."""
    F = 4
    sec_m = np.full((F, 72), np.inf)
    sec_m[:, 0] = sec_m[:, 18] = 20.0
    view = np.zeros((F, 72), bool)
    view[:, np.r_[0:7, 66:72]] = True
    t = 1000.0 + np.arange(F) / 10.0
    truth = SectorTruth(t, sec_m, np.zeros((F, 3)), np.zeros(F), 60.0, view)
    rows, log, reasons = [], {}, {}
    for f in range(F):
        d = np.full(72, 4001)  # clear
        d[[0, 18, 2]] = UINT16_MAX
        why = np.zeros(72, np.int8)
        why[0] = (R.RANGING, R.RANGING, R.NO_POINTS, R.NONE)[f]
        why[18], why[2] = R.NOT_SEEN, R.FEW_FAR
        if f == 3:
            d[0] = 1950
        tu = 1_000_000 * (f + 1)
        rows.append((t[f] + 0.02, tu, d, 50, 4000))
        if f < F - 1:
            key = (tu, d.astype(np.uint16).tobytes())
            log[key], reasons[key] = np.zeros(72, np.int8), why
    s = summarize(evaluate(RangeMessages.build(od=rows), truth, ScoreConfig(warmup_s=0.0)), log, reasons)
    u = s["unknown_by_reason"]
    assert u["messages_scored"] == 4 and u["messages_matched"] == 3
    assert u["obstacle_in_view"]["cells"] == 3 and u["obstacle_in_view"]["ranging"] == 2
    assert u["obstacle_in_view"]["no_points"] == 1 and u["obstacle_in_view"]["unattributed"] == 0
    assert u["obstacle_out_of_view"]["cells"] == 4 and u["obstacle_out_of_view"]["not_seen"] == 3
    assert u["obstacle_out_of_view"]["unattributed"] == 1  # the message without a line
    assert u["clear_in_view"]["cells"] == 4 and u["clear_in_view"]["few_far"] == 3
    md = markdown(s, "t")
    assert "Unknown cells by reason" in md and "| obstacle cells in view | 3 |" in md and "66.7 %" in md
    # campaigns sum the runs' counts
    pooled = pool_log_counts([u, None, u])
    assert pooled["runs"] == 2 and pooled["obstacle_in_view"]["ranging"] == 4 and pooled["messages_matched"] == 6
    # without reasons in the log there is no split
    assert summarize(evaluate(RangeMessages.build(od=rows), truth, ScoreConfig(warmup_s=0.0)), log)["unknown_by_reason"] is None


def test_folding_for_px4_keeps_every_unknown_sector_unknown_and_nothing_else():
    """The reporter logs the turned reasons unchanged when it folds OBSTACLE_DISTANCE into PX4's 10° bins: that holds
    only if folding never turns an unknown element into a claim nor a claim into unknown (seeded random rings)."""
    from companion.core.sectors_types import fold_into_bins

    rng = np.random.default_rng(11)
    max_cm = CFG.max_distance_cm
    for _ in range(500):
        kind = rng.integers(0, 3, 72)
        d = np.where(kind == 0, UINT16_MAX, np.where(kind == 1, max_cm + 1, rng.integers(50, max_cm + 1, 72)))
        folded, _ = fold_into_bins(d.astype(np.uint16), max_cm)
        assert np.array_equal(folded == UINT16_MAX, d == UINT16_MAX)
