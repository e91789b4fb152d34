"""Where a sector's claim comes from (docs/derivations/sectors.md, "Where a claim comes from"): the sources of
:meth:`Sectors.sources` on hand-built points whose answer is known, their turn with the published distances,
the sector log that carries them (companion/sector_log.py), the reporter that feeds it, and the score's
claims by source (flightsim/score/summary.py)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from companion.mavlink.dialect import UINT16_MAX  # noqa: I001 (first: MAVLink 2)
from companion.core.sectors import SectorConfig, SectorSource, SectorState, compute_sectors, compute_sectors_reference
from companion.errors import ConfigError, InputError
from companion.io.config_files import CompanionConfig
from companion.pipeline import FrameResult, PipelineConfig
from companion.reporter import Reporter
from companion.sector_log import SectorLog, read_sector_forward, read_sector_log
from flightsim.score.config import ScoreConfig
from flightsim.score.evaluation import evaluate
from flightsim.score.inputs import RangeMessages, SectorTruth
from flightsim.score.markdown import markdown
from flightsim.score.summary import summarize

from conftest import FullDisk

HFOV = math.radians(60.0)
CFG = SectorConfig()


def at(d, bearing_deg, z=0.0):
    b = math.radians(bearing_deg)
    return [d * math.cos(b), d * math.sin(b), z]


def scene(fn=compute_sectors):
    """Live points: 10 m ahead (sector 0), 12 m at 10° (sector 2), 15 m at −20° and −10° (sectors 68, 70: the
    gaps at −15° and at 5° between them are inferred).  Remembered points: 12.2 m at 10.5° (sector 2: live and
    remembered), 8 m behind (sector 36: remembered only)."""
    live = np.array([at(10, 0), at(10, 0.5), at(12, 10), at(15, -20), at(15, -10)])
    mem = np.array([at(12.2, 10.5), at(8, 180), at(8, 180.5)])
    n = len(live)
    return fn(live, np.full(n, 0.1), np.ones(n, bool), np.ones(n, bool), HFOV, 0.0, CFG,
              remembered_p_body=mem, remembered_sigma=np.full(len(mem), 0.1),
              remembered_tangential_sigma=np.full(len(mem), 0.01))


@pytest.mark.parametrize("fn", [compute_sectors, compute_sectors_reference])
def test_each_claim_names_its_source(fn):
    sec = scene(fn)
    src = sec.sources()
    assert src.dtype == np.int8 and src.shape == (72,)
    assert src[0] == SectorSource.LIVE
    assert src[2] == SectorSource.MIXED
    assert src[36] == SectorSource.REMEMBERED
    assert src[68] == SectorSource.LIVE and src[70] == SectorSource.LIVE
    assert sec.inferred[69] and src[69] == SectorSource.INFERRED
    assert sec.inferred[1] and src[1] == SectorSource.INFERRED  # the narrow gap between the points at 0° and 10°, 2.8 m apart
    # a source exactly where an obstacle is claimed
    assert np.array_equal(src != SectorSource.NONE, sec.state == SectorState.OBSTACLE)
    assert set(np.flatnonzero(src)) == {0, 1, 2, 36, 68, 69, 70}


@pytest.mark.parametrize("fn", [compute_sectors, compute_sectors_reference])
def test_claims_from_points_above_the_band_are_told_apart(fn):
    """A pole at 6 m, 30° right, ranged only above the band (2.0 and 2.7 m above the vehicle: a vertical structure
    reaching down to it) and, 60° left, a wall at 20 m in the band under a point 8 m away just above it (the cap)."""
    live = np.array([at(6, 30, -2.0), at(6, 30.3, -2.7), at(20, -60), at(20, -59.5), at(8, -60.2, -1.8)])
    n = len(live)
    sec = fn(live, np.full(n, 0.1), np.ones(n, bool), np.ones(n, bool), math.radians(170), 0.0, CFG)
    src = sec.sources()
    assert src[6] == SectorSource.VERTICAL and sec.inferred_vertical[6] and sec.range_m[6] < 6
    assert src[60] == SectorSource.VERTICAL and sec.range_m[60] < 8  # capped at the point above: 8 m, not 20
    off = fn(live, np.full(n, 0.1), np.ones(n, bool), np.ones(n, bool), math.radians(170), 0.0,
             dataclasses.replace(CFG, infer_vertical=False, cap_above_m=0.0))
    assert off.sources()[6] == SectorSource.NONE and off.sources()[60] == SectorSource.LIVE
    assert not np.any(off.inferred_vertical)


def test_kernel_and_reference_agree_on_the_sources():
    assert np.array_equal(scene(compute_sectors).sources(), scene(compute_sectors_reference).sources())


@pytest.mark.parametrize("dyaw_deg", [10.0, -15.0, 7.0, -3.2, 0.4, 180.0])
def test_sources_turn_with_the_published_distances(dyaw_deg):
    sec = scene()
    src, dyaw = sec.sources(), math.radians(dyaw_deg)
    d_new = sec.rotated(dyaw).astype(np.int64)
    s_new = sec.rotated_sources(dyaw)
    obstacle = d_new <= sec.max_distance_cm
    assert np.array_equal(s_new != SectorSource.NONE, obstacle)
    lo = math.floor(dyaw_deg / 5.0)
    for i in np.flatnonzero(obstacle):  # a turned sector holds what old sectors i + lo and i + lo + 1 held
        a, b = (i + lo) % 72, (i + lo + 1) % 72
        assert s_new[i] in (src[a], src[b])
        if sec.distances_cm[a] == d_new[i] and sec.state[a] == SectorState.OBSTACLE:
            assert s_new[i] == src[a]
    if dyaw_deg % 5.0 == 0.0:  # a whole number of sectors: the ring is shifted as it is
        assert np.array_equal(s_new, np.roll(src, -int(dyaw_deg / 5.0)))


def test_a_turn_that_is_not_a_number_leaves_no_source():
    assert not np.any(scene().rotated_sources(math.nan))


# ---------------------------------------------------------------------- the sector log -----------
def test_the_log_holds_what_was_sent_to_the_autopilot_and_reads_back(tmp_path):
    sec = scene()
    path = tmp_path / "logs" / "sectors.jsonl"
    sl = SectorLog(path)
    sl("autopilot", 1_234_000, sec.distances_cm, sec.sources())
    sl("gcs", 1_234_000, sec.distances_cm, sec.sources())  # only the autopilot's output is logged
    sl("autopilot", 1_267_000, sec.rotated(math.radians(10)), sec.rotated_sources(math.radians(10)))
    sl.close()
    with open(path, "a", encoding="ascii") as fh:
        fh.write('{"out": "autopilot", "time_usec": 13000')  # a companion killed mid-line
    lines = path.read_text().splitlines()
    head = json.loads(lines[0])
    assert head["sector_log"] == 1 and head["sources"]["3"] == "remembered" and sl.lines == 2
    got = read_sector_log(path)
    assert len(got) == 2
    key = (1_234_000, sec.distances_cm.astype(np.uint16).tobytes())
    assert np.array_equal(got[key], sec.sources())
    assert read_sector_log(path, output="gcs") == {}
    assert read_sector_forward(path) == {}  # lines without a forward reading


def test_the_log_keeps_the_forward_reading_and_reads_it_back(tmp_path):
    sec = scene()
    path = tmp_path / "sectors.jsonl"
    sl = SectorLog(path)
    sl("autopilot", 1_000, sec.distances_cm, sec.sources(), (1950, 255, 88))
    sl("autopilot", 2_000, sec.distances_cm, sec.sources(), (1950, 300, 88))  # not a uint8 covariance: skipped
    sl.close()
    fwd = read_sector_forward(path)
    assert fwd == {(1_000, sec.distances_cm.astype(np.uint16).tobytes()): (1950, 255, 88)}
    assert len(read_sector_log(path)) == 2  # the sources read as before


def test_a_file_that_is_not_a_sector_log_is_refused(tmp_path):
    p = tmp_path / "x.jsonl"
    p.write_text("hello\n")
    with pytest.raises(InputError, match="not a sector log"):
        read_sector_log(p)


def test_an_unwritable_log_is_a_configuration_error(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(ConfigError, match="--sector-log"):
        SectorLog(tmp_path / "d")


def test_a_failing_write_ends_the_log_and_nothing_else(tmp_path):
    sec = scene()
    sl = SectorLog(tmp_path / "s.jsonl")

    sl._fh = FullDisk()
    sl("autopilot", 1, sec.distances_cm, sec.sources())  # no exception
    assert sl.failed and sl.lines == 0
    sl("autopilot", 2, sec.distances_cm, sec.sources())  # later calls do nothing
    assert sl.lines == 0


def test_the_reporter_logs_every_obstacle_distance_with_its_turned_sources():
    cfg = CompanionConfig()
    got = []
    rep = Reporter(cfg, PipelineConfig(), start=9.0, sector_sink=lambda *a: got.append(a))
    sec = scene(lambda *a, **k: compute_sectors(*a[:6], cfg.sectors, **k))
    res = FrameResult(1, 10.0, 10.0, 0.005, True, "ok", sectors=sec, yaw=0.0, n_tracks=10, t_boot_capture=10.0)
    msgs = rep.on_result(res, 10.03, yaw_now=math.radians(10.0), last_frame_at=10.0)
    od = [m for _, m in msgs if m.get_type() == "OBSTACLE_DISTANCE"]
    assert len(od) == 1 and len(got) == 1
    out, time_usec, d, src, fwd, why = got[0]
    assert out == "autopilot" and time_usec == od[0].time_usec == 10_000_000
    # the forward reading of the same result, here withheld from the autopilot (turned 10°: unknown) but logged
    assert fwd == (UINT16_MAX, 255, 1) and not [m for _, m in msgs if m.get_type() == "DISTANCE_SENSOR"]
    assert np.array_equal(np.asarray(d), np.asarray(od[0].distances))
    assert np.array_equal(src, sec.rotated_sources(math.radians(10.0)))
    assert np.array_equal(src != 0, np.asarray(od[0].distances) <= sec.max_distance_cm)


def test_a_sink_that_fails_does_not_stop_the_message():
    cfg = CompanionConfig()

    def broken(*_):
        raise RuntimeError("boom")

    rep = Reporter(cfg, PipelineConfig(), start=9.0, sector_sink=broken)
    sec = scene(lambda *a, **k: compute_sectors(*a[:6], cfg.sectors, **k))
    res = FrameResult(1, 10.0, 10.0, 0.005, True, "ok", sectors=sec, yaw=0.0, n_tracks=10, t_boot_capture=10.0)
    msgs = rep.on_result(res, 10.03, yaw_now=0.0, last_frame_at=10.0)
    assert [m for _, m in msgs if m.get_type() == "OBSTACLE_DISTANCE"]
    assert rep.counters["sector_log_errors"] == 1


# ---------------------------------------------------------------------- the score by source ------
def test_the_score_splits_claims_by_source():
    """Five messages facing north, an obstacle 20 m ahead (sector 0, in view), everything else clear.  Each
    message claims the obstacle (live: within tolerance), one also a false obstacle out of view at 100°
    (remembered), one a false obstacle in view at −10° (inferred); the last message has no log line."""
    F = 5
    sec_m = np.full((F, 72), np.inf)
    sec_m[:, 0] = 20.0
    view = np.zeros((F, 72), bool)
    view[:, np.r_[0:8, 64:72]] = True
    t = 1000.0 + np.arange(F) / 10.0
    truth = SectorTruth(t, sec_m, np.zeros((F, 3)), np.zeros(F), 60.0, view)
    rows, log = [], {}
    for f in range(F):
        d = np.full(72, UINT16_MAX)
        src = np.zeros(72, np.int8)
        d[0], src[0] = 1950, SectorSource.LIVE
        if f == 1:
            d[20], src[20] = 500, SectorSource.REMEMBERED
        if f == 2:
            d[70], src[70] = 800, SectorSource.INFERRED
        tu = 1_000_000 * (f + 1)
        rows.append((t[f] + 0.02, tu, d, 50, 4000))
        if f < F - 1:
            log[(tu, d.astype(np.uint16).tobytes())] = src
    s = summarize(evaluate(RangeMessages.build(od=rows), truth, ScoreConfig(warmup_s=0.0)), log)
    cbs = s["claims_by_source"]
    assert cbs["messages_scored"] == 5 and cbs["messages_matched"] == 4
    iv, oov = cbs["in_view"], cbs["out_of_view"]
    assert iv["live"] == {"ranges": 4, "on_obstacles": 4, "valid": 4, "too_near": 0, "over_range": 0, "false_obstacles": 0,
                          "beside_obstacle": 0}
    assert iv["inferred"]["ranges"] == 1 and iv["inferred"]["false_obstacles"] == 1
    assert oov["remembered"]["ranges"] == 1 and oov["remembered"]["false_obstacles"] == 1
    assert iv["unattributed"]["ranges"] == 1 and iv["unattributed"]["valid"] == 1  # the message without a line
    assert sum(r["false_obstacles"] for v in (iv, oov) for r in v.values()) == s["cells"]["false_obstacles_clear_cells"]
    assert "Claims by source" in markdown(s, "t")
    # forward readings from the log replace the DISTANCE_SENSORs received (here none reached the autopilot)
    from flightsim.score.files import forward_from_sector_log

    fwd = {(r[1], np.asarray(r[2]).astype(np.uint16).tobytes()): (1950, 255, 90) for r in rows[:4]}
    msgs = forward_from_sector_log(RangeMessages.build(od=rows), fwd)
    assert msgs.ds_t.tolist() == [r[0] for r in rows[:4]] and set(msgs.ds_distance_cm) == {1950}
    assert msgs.counts["forward_from_sector_log"] == 4 and msgs.counts["distance_sensor_received"] == 0
    ev = evaluate(msgs, truth, ScoreConfig(warmup_s=0.0))
    assert np.allclose(ev.ds_published_m, 19.5) and np.allclose(ev.ds_truth_arrival, 20.0)
    # without a log the score has no split, and the rest is the same
    plain = summarize(evaluate(RangeMessages.build(od=rows), truth, ScoreConfig(warmup_s=0.0)))
    assert plain["claims_by_source"] is None and plain["cells"] == s["cells"]
