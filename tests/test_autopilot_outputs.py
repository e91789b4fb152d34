"""What the autopilots make of the companion's messages (docs/derivations/sectors.md, "PX4's 10° bins"
and "The forward DISTANCE_SENSOR and the autopilots"): OBSTACLE_DISTANCE folded into PX4's 10° bins
when the vehicle is a PX4, and a forward DISTANCE_SENSOR sent to the autopilot only when it agrees with
OBSTACLE_DISTANCE about the region the autopilot writes it into.  Checked on exact sector arrays and
through the simulated autopilots of flightsim.avoidance, which follow the autopilots' code."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.mavlink.dialect import UINT16_MAX, mavlink  # noqa: I001 (first: MAVLink 2)
from companion.core.sectors import (
    SECTOR_COUNT,
    SectorSource,
    compute_sectors,
    fold_into_bins,
    forward_reading_consistent,
)
from companion.errors import ConfigError, InputError
from companion.io.config_files import CompanionConfig
from companion.mavlink import messages as M
from companion.pipeline import FrameResult, PipelineConfig
from companion.reporter import Reporter
from flightsim.avoidance import ArduPilotAvoidance, AvoidanceConfig, PX4Avoidance

MAX = 4000
CLEAR = MAX + 1
UNK = UINT16_MAX


def ring(fill=UNK, **at):
    """(72,) distances, cm: ``fill`` everywhere, ``s<i>=cm`` at sector i."""
    d = np.full(SECTOR_COUNT, fill, np.int64)
    for k, v in at.items():
        d[int(k[1:])] = v
    return d


# ---------------------------------------------------------------------- folding ---------------
def test_fold_gives_each_even_element_the_nearest_obstacle_of_its_10_degree_bin():
    d = ring(CLEAR, s3=800)  # a thin pole at 15°, claimed only in odd sector 3
    out, _ = fold_into_bins(d, MAX)
    assert out[2] == 800 and out[4] == 800  # bins 1 (10°) and 2 (20°) each overlap half of sector 3
    assert out[3] == 800  # the odd element itself is unchanged
    assert np.all(np.delete(out, [2, 3, 4]) == CLEAR)
    # an even sector's own nearer obstacle wins; a nearer neighbour wins over a farther own one
    out, _ = fold_into_bins(ring(CLEAR, s2=500, s3=800), MAX)
    assert out[2] == 500 and out[4] == 800
    out, _ = fold_into_bins(ring(CLEAR, s2=900, s1=600), MAX)
    assert out[2] == 600 and out[0] == 600
    # across the wrap: sector 71 (−5°) reaches element 0
    out, _ = fold_into_bins(ring(CLEAR, s71=700), MAX)
    assert out[0] == 700 and out[70] == 700
    # an unknown element stays unknown: PX4 must still refuse the bin whose centre nobody ranged
    out, _ = fold_into_bins(ring(UNK, s3=800, s4=CLEAR), MAX)
    assert out[2] == UNK and out[4] == 800


def test_fold_never_makes_anything_clear_or_unknown_that_was_an_obstacle():
    rng = np.random.default_rng(7)
    for _ in range(300):
        d = rng.choice([UNK, CLEAR, 300, 750, 1200, 3999], size=SECTOR_COUNT, p=[0.4, 0.3, 0.1, 0.1, 0.05, 0.05])
        out, _ = fold_into_bins(d, MAX)
        out = out.astype(np.int64)
        odd = np.arange(1, SECTOR_COUNT, 2)
        assert np.array_equal(out[odd], d[odd])
        obs = d <= MAX
        assert np.all(out[obs] <= d[obs])  # an obstacle only gets nearer
        # a clear even element changes only to an obstacle of its bin; an unknown one never changes
        ev = np.arange(0, SECTOR_COUNT, 2)
        changed = ev[out[ev] != d[ev]]
        for k in changed:
            nb = d[[(k - 1) % 72, k, (k + 1) % 72]]
            assert d[k] != UNK and out[k] == nb[nb <= MAX].min()
        assert not np.any((out == CLEAR) & (d != CLEAR))
        assert np.array_equal(out == UNK, d == UNK)


def test_fold_sources_follow_the_value_and_bad_input_is_refused():
    d = ring(CLEAR, s3=800, s10=600)
    src = np.zeros(SECTOR_COUNT, np.int8)
    src[3], src[10] = SectorSource.REMEMBERED, SectorSource.LIVE
    out, s = fold_into_bins(d, MAX, src)
    assert s[2] == s[4] == SectorSource.REMEMBERED and s[10] == SectorSource.LIVE and s[0] == SectorSource.NONE
    same, s1 = fold_into_bins(d, MAX, src, bin_deg=5.0)
    assert np.array_equal(same, d) and np.array_equal(s1, src)
    with pytest.raises(InputError, match="72"):
        fold_into_bins(np.zeros(36), MAX)
    with pytest.raises(InputError, match="bin_deg"):
        fold_into_bins(d, MAX, bin_deg=7.0)


def test_px4_sees_a_pole_in_an_odd_sector_only_when_folded():
    """The simulated PX4 reads one element per 10° bin: a pole claimed only in sector 3 is invisible to it
    unless folded; folded, it slows the vehicle flying at 15°."""
    cfg = AvoidanceConfig(model="px4", cp_dist_m=2.0, cp_guide_ang_deg=0.0)
    d = ring(CLEAR, s3=500)
    for folded, seen in ((False, False), (True, True)):
        px = PX4Avoidance(cfg)
        dd = fold_into_bins(d, MAX)[0] if folded else d
        px.receive(0.0, M.obstacle_distance(dd.astype(np.uint16), 50, MAX, 0))
        bins = px.bins(0.0)
        assert (bins[1] == 500 and bins[2] == 500) == seen
        b = math.radians(15.0)
        v = px.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (4.0 * math.cos(b), 4.0 * math.sin(b), 0.0))
        assert (math.hypot(v[0], v[1]) < 3.0) == seen


# ---------------------------------------------------------------------- forward DISTANCE_SENSOR -----
def test_forward_reading_agrees_with_the_front_face_or_is_withheld():
    wall = ring(UNK, s0=1000, s1=1010, s71=990, s2=1040)  # a wall ahead: its sectors scatter a few per cent
    assert forward_reading_consistent("obstacle", 1000, wall, MAX)
    pole = ring(CLEAR, s0=1500, s4=300)  # a pole at 20° in ArduPilot's front face, much nearer than ahead
    assert not forward_reading_consistent("obstacle", 1500, pole, MAX)
    assert forward_reading_consistent("obstacle", 1500, ring(CLEAR, s0=1500, s5=300), MAX)  # 25°: the next face
    assert forward_reading_consistent("obstacle", 1500, ring(UNK), MAX)  # nothing else in the face: adds data
    assert forward_reading_consistent("clear", CLEAR, ring(CLEAR), MAX)
    assert not forward_reading_consistent("clear", CLEAR, ring(CLEAR, s68=900), MAX)  # −20°: still the front face
    assert not forward_reading_consistent("clear", CLEAR, ring(UNK), MAX)  # PX4 would take it as free space
    for d in (ring(UNK), ring(CLEAR), wall):
        assert not forward_reading_consistent("unknown", UNK, d, MAX)


def _sectors(points_body, cfg):
    pts = np.asarray(points_body, float)
    n = len(pts)
    return compute_sectors(pts, np.full(n, 0.1), np.ones(n, bool), np.ones(n, bool), math.radians(60), 0.0, cfg.sectors)


def _result(sec):
    return FrameResult(1, 10.0, 10.0, 0.005, True, "ok", sectors=sec, yaw=0.0, n_tracks=10, t_boot_capture=10.0)


def _at(bearing_deg, dist_m, n=3):
    b = math.radians(bearing_deg)
    return [[dist_m * math.cos(b), dist_m * math.sin(b), 0.0]] * n


def test_reporter_withholds_a_forward_reading_that_would_undo_a_near_pole_in_ardupilots_front_face():
    cfg = CompanionConfig()
    sec = _sectors(_at(0.0, 15.0) + _at(15.0, 3.0), cfg)  # a wall 15 m ahead, a pole 3 m away at 15°
    rep = Reporter(cfg, PipelineConfig(), outputs=("autopilot", "gcs"), start=9.0)
    msgs = rep.on_result(_result(sec), 10.02, yaw_now=0.0, last_frame_at=10.0)
    ds = {o: m for o, m in msgs if m.get_type() == "DISTANCE_SENSOR"}
    assert "autopilot" not in ds and rep.counters["distance_sensor_withheld"] == 1
    assert ds["gcs"].current_distance == sec.distances_cm[0]  # the ground station still sees the forward range
    # the simulated ArduPilot, fed what the companion sent, holds the pole in its front face
    ap = ArduPilotAvoidance(AvoidanceConfig(model="ardupilot", prx_filt_hz=0.0))
    for o, m in msgs:
        if o == "autopilot" and m.get_type() in ("OBSTACLE_DISTANCE", "DISTANCE_SENSOR"):
            ap.receive(0.0, m)
    assert ap.valid_faces(0.0)[0] and ap.face_filt[0] == pytest.approx(sec.range_m[3], abs=0.01)
    # had the forward reading gone out too, ArduPilot's face would hold the wall and forget the pole
    ap2 = ArduPilotAvoidance(AvoidanceConfig(model="ardupilot", prx_filt_hz=0.0))
    ap2.receive(0.0, [m for o, m in msgs if o == "autopilot" and m.get_type() == "OBSTACLE_DISTANCE"][0])
    ap2.receive(0.0, ds["gcs"])
    assert ap2.valid_faces(0.0)[0] and ap2.face_filt[0] == pytest.approx(sec.range_m[0], abs=0.01)


def test_reporter_sends_the_forward_reading_when_it_is_the_nearest_ahead():
    cfg = CompanionConfig()
    sec = _sectors(_at(0.0, 8.0) + _at(5.0, 8.1) + _at(-5.0, 8.1), cfg)  # a wall ahead
    rep = Reporter(cfg, PipelineConfig(), start=9.0)
    msgs = rep.on_result(_result(sec), 10.02, yaw_now=0.0, last_frame_at=10.0)
    ds = [m for _, m in msgs if m.get_type() == "DISTANCE_SENSOR"]
    assert len(ds) == 1 and ds[0].current_distance == sec.distances_cm[0] and rep.counters["distance_sensor_withheld"] == 0


def test_an_out_of_range_forward_reading_wipes_ardupilots_face_and_frees_px4s_bin():
    """Why "unknown" never goes to the autopilot: the simulated autopilots follow their code."""
    unknown = M.distance_sensor("unknown", math.nan, math.nan, 50, MAX, 0, horizontal_fov_rad=math.radians(5.0))
    ap = ArduPilotAvoidance(AvoidanceConfig(model="ardupilot", prx_filt_hz=0.0))
    ap.receive(0.0, M.obstacle_distance(ring(UNK, s3=300).astype(np.uint16), 50, MAX, 0))
    assert ap.valid_faces(0.0)[0]
    ap.receive(0.01, unknown)
    assert not ap.valid_faces(0.02)[0]  # the pole at 15° is gone from the front face
    assert ap.limit(0.02, (0, 0, -5), (0, 0, 0), 0.0, (3.0, 0.0, 0.0))[0] == pytest.approx(3.0)
    px = PX4Avoidance(AvoidanceConfig(model="px4", cp_dist_m=2.0, cp_guide_ang_deg=0.0))
    px.receive(0.0, M.obstacle_distance(ring(UNK).astype(np.uint16), 50, MAX, 0))
    assert px.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (3.0, 0.0, 0.0))[0] == 0.0  # no data ahead: PX4 stays
    px.receive(0.01, unknown)
    assert px.bins(0.02)[0] == MAX  # read as free space out to max_distance ...
    assert px.limit(0.02, (0, 0, -5), (0, 0, 0), 0.0, (3.0, 0.0, 0.0))[0] > 2.0  # ... and PX4 flies into the unknown
    # a reading spread over its horizontal field of view fills every bin it spans (floor above 0, ceil below)
    px2 = PX4Avoidance(AvoidanceConfig(model="px4", cp_dist_m=2.0))
    px2.receive(0.0, M.distance_sensor("obstacle", 6.0, 0.1, 50, MAX, 0, horizontal_fov_rad=math.radians(45.0)))
    assert np.flatnonzero(px2.bins(0.0) < UNK).tolist() == [0, 1, 2, 34, 35]


def test_random_scenes_leave_ardupilots_front_face_no_farther_than_the_companions_claim():
    """Property: whatever the sectors, after the companion's OBSTACLE_DISTANCE and forward reading the
    simulated ArduPilot's front face holds an obstacle whenever OBSTACLE_DISTANCE claims one within ±20°,
    no farther than (1 + rel_tol) times the nearest of them."""
    cfg = CompanionConfig()
    tol = cfg.outputs.distance_sensor_face_rel_tol
    rng = np.random.default_rng(11)
    for k in range(60):
        pts = []
        for _ in range(int(rng.integers(1, 5))):
            pts += _at(float(rng.uniform(-30, 30)), float(rng.uniform(2, 45)))
        sec = _sectors(pts, cfg)
        rep = Reporter(cfg, PipelineConfig(), start=9.0)
        msgs = rep.on_result(_result(sec), 10.02, yaw_now=0.0, last_frame_at=10.0)
        ap = ArduPilotAvoidance(AvoidanceConfig(model="ardupilot", prx_filt_hz=0.0))
        for _, m in msgs:
            if m.get_type() in ("OBSTACLE_DISTANCE", "DISTANCE_SENSOR"):
                ap.receive(0.0, m)
        d = sec.distances_cm.astype(np.int64)
        face = d[np.r_[68:72, 0:5]]
        obs = face[face <= MAX]
        if obs.size:
            assert ap.valid_faces(0.0)[0], k
            assert ap.face_filt[0] <= (1 + tol) * obs.min() / 100 + 1e-9, k


# ---------------------------------------------------------------------- when to fold -----------------
def test_the_reporter_folds_for_a_px4_only_and_the_key_overrides_it():
    base = CompanionConfig()  # without the corridor (rule 10), which on the quads already takes "clear" from beside it
    cfg = dataclasses.replace(base, sectors=dataclasses.replace(base.sectors, clear_corridor_m=0.0))
    far = [p for b in (5.0, 10.0, 20.0, 25.0) for p in _at(b, 60.0)]  # a far background seen clear around it
    sec = _sectors(_at(15.0, 6.0) + far, cfg)
    assert sec.distances_cm[3] < UNK and sec.distances_cm[2] == sec.distances_cm[4] == CLEAR  # claimed only in odd sector 3

    def sent(autopilot, mode):
        c = dataclasses.replace(cfg, outputs=dataclasses.replace(cfg.outputs, px4_bin_fold=mode))
        rep = Reporter(c, PipelineConfig(), outputs=("autopilot", "gcs"), start=9.0)
        rep.vehicle_autopilot = autopilot
        msgs = rep.on_result(_result(sec), 10.02, yaw_now=0.0, last_frame_at=10.0)
        od = {o: np.asarray(m.distances) for o, m in msgs if m.get_type() == "OBSTACLE_DISTANCE"}
        return od["autopilot"], od["gcs"]

    a, g = sent(mavlink.MAV_AUTOPILOT_PX4, "auto")
    assert a[2] == a[4] == sec.distances_cm[3] and np.array_equal(g, sec.distances_cm)  # the ground station: as measured
    for autopilot, mode in ((mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, "auto"), (None, "auto"), (mavlink.MAV_AUTOPILOT_PX4, "off")):
        a, _ = sent(autopilot, mode)
        assert np.array_equal(a, sec.distances_cm)
    a, _ = sent(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, "on")
    assert a[2] == sec.distances_cm[3]
    with pytest.raises(ConfigError, match="px4_bin_fold"):
        M.OutputConfig(px4_bin_fold="yes")
    with pytest.raises(ConfigError, match="distance_sensor_face_rel_tol"):
        M.OutputConfig(distance_sensor_face_rel_tol=-0.1)
