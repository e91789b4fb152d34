"""The scorer's sector of a world direction under a heading, the remembered cells of a vehicle that
saw its obstacle while facing east, and the single camera's ceiling (`rangeable_cells`:
docs/derivations/sectors.md, DESIGN.md §3 and §7) — exact geometry on hand-built truths."""

import math

import numpy as np
import pytest

from flightsim.score.config import ScoreConfig
from flightsim.score.evaluation import evaluate, rangeable_cells, sector_of
from flightsim.score.inputs import RangeMessages, SectorTruth
from flightsim.score.markdown import markdown
from flightsim.score.summary import summarize

U = 65535
NOWARM = ScoreConfig(warmup_s=0.0)
RATE = 10.0


def od(t, values: dict):
    d = np.full(72, U)
    for i, v in values.items():
        d[i] = v
    return (t, 0, d, 50, 4000)


def front_view(F: int, half_sectors: int = 7) -> np.ndarray:
    view = np.zeros((F, 72), bool)
    view[:, np.r_[np.arange(0, half_sectors + 1), np.arange(72 - half_sectors, 72)]] = True
    return view


def truth_of(p_ned: np.ndarray, yaw: np.ndarray, obstacle_ne, view: np.ndarray | None = None) -> SectorTruth:
    """A point obstacle at ``obstacle_ne`` (world NE, the vehicle's altitude): its true distance in
    the sector of its bearing, every other sector clear."""
    F = len(yaw)
    sec = np.full((F, 72), np.inf)
    d = np.asarray(obstacle_ne, float)[None, :] - p_ned[:, :2]
    s = sector_of(d[:, 0], d[:, 1], yaw)
    sec[np.arange(F), s] = np.hypot(d[:, 0], d[:, 1])
    t = 1000.0 + np.arange(F) / RATE
    return SectorTruth(t, sec, p_ned, yaw, 60.0, front_view(F) if view is None else view)


def lateral_pass(F: int) -> SectorTruth:
    """Moving east at 1 m/s, facing north, with the obstacle 20 m north of the start."""
    p = np.zeros((F, 3))
    p[:, 1] = np.arange(F) / RATE
    return truth_of(p, np.zeros(F), (20.0, 0.0))


def obstacle_sectors(truth: SectorTruth) -> list[int]:
    """The sector of the obstacle in each frame."""
    return [int(np.flatnonzero(np.isfinite(truth.sector_m[f]))[0]) for f in range(len(truth.t_s))]


def rangeable_of(truth: SectorTruth, cfg: ScoreConfig = NOWARM) -> np.ndarray:
    """Per frame: whether the obstacle's cell (where it is in view) is rangeable."""
    F = len(truth.t_s)
    cand = np.isfinite(truth.sector_m) & truth.view
    out = rangeable_cells(truth, truth.view, np.arange(F), cand, cfg)
    return np.array([bool(out[f][cand[f]].any()) if cand[f].any() else False for f in range(F)])


# ---------------------------------------------------------------------- sector of a direction ----
def test_sector_of_turns_with_the_heading():
    yaw = np.radians(np.array([0.0, 30.0, 30.0, -90.0, 170.0]))
    d_n = np.cos(np.radians([0.0, 40.0, 20.0, -90.0, -175.0]))
    d_e = np.sin(np.radians([0.0, 40.0, 20.0, -90.0, -175.0]))
    # body bearings 0°, +10°, −10°, 0°, +15° (−175° from a heading of 170° wraps to 15°)
    assert sector_of(d_n, d_e, yaw).tolist() == [0, 2, 70, 0, 3]


def test_remembered_counts_an_obstacle_seen_while_facing_east():
    # facing east (yaw 90°) with the obstacle 20 m east (sector 0, in view), then turned to face west:
    # the obstacle is behind (sector 36).  Its point was in view: the cells behind are remembered.
    F0, F1 = 5, 5
    yaw = np.r_[np.full(F0, math.pi / 2), np.full(F1, -math.pi / 2)]
    truth = truth_of(np.zeros((F0 + F1, 3)), yaw, (0.0, 20.0))
    assert truth.sector_m[0, 0] == 20.0 and truth.sector_m[-1, 36] == 20.0
    rows = [od(t + 0.02, {0: 2000} if f < F0 else {36: 2000}) for f, t in enumerate(truth.t_s)]
    s = summarize(evaluate(RangeMessages.build(od=rows), truth, NOWARM))
    assert s["remembered"]["cells"] == F1 and s["remembered"]["rate"] == 1.0


# ---------------------------------------------------------------------- rangeable --------------
def test_turning_in_place_ranges_nothing():
    # a vehicle at rest turning 40°/s with an obstacle 15 m away: it sweeps through the view, never rangeable
    F = 60
    yaw = np.radians(-60.0 + 4.0 * np.arange(F))
    truth = truth_of(np.zeros((F, 3)), yaw, (15.0, 0.0))
    in_view = np.isfinite(truth.sector_m).any(1) & (truth.view & np.isfinite(truth.sector_m)).any(1)
    assert in_view.sum() >= 15
    assert not rangeable_of(truth).any()


def test_a_lateral_pass_is_rangeable_once_the_parallax_reaches_the_threshold():
    # moving east at 1 m/s with the obstacle 20 m north: the parallax after x metres is atan(x / 20);
    # 1° is reached at x = 0.349 m, i.e. from the frame at 0.4 s
    F = 12
    truth = lateral_pass(F)
    got = rangeable_of(truth)
    assert got.tolist() == [False] * 4 + [True] * (F - 4)
    # a 2° threshold needs x ≥ 0.698 m: from 0.7 s
    assert rangeable_of(truth, ScoreConfig(warmup_s=0.0, rangeable_parallax_deg=2.0)).tolist() == [False] * 7 + [True] * (F - 7)


def test_a_head_on_approach_is_rangeable_by_looming():
    # straight at the obstacle 20 m ahead at 2 m/s: no parallax, but the distance shrinks; 10 % (20 / r ≥ 1.1)
    # from r ≤ 18.18 m, i.e. from the frame at 1.0 s (18.0 m), not at 0.9 s (18.2 m)
    F = 15
    p = np.zeros((F, 3))
    p[:, 0] = 2.0 * np.arange(F) / RATE
    truth = truth_of(p, np.zeros(F), (20.0, 0.0))
    assert rangeable_of(truth).tolist() == [False] * 10 + [True] * (F - 10)
    assert not rangeable_of(truth, ScoreConfig(warmup_s=0.0, rangeable_scale=0.5)).any()


def test_a_climb_gives_vertical_parallax():
    # climbing 1 m/s with the obstacle 20 m north at the present altitude (the band's centre)
    F = 8
    p = np.zeros((F, 3))
    p[:, 2] = -np.arange(F) / RATE
    truth = truth_of(p, np.zeros(F), (20.0, 0.0))
    assert rangeable_of(truth).tolist() == [False] * 4 + [True] * (F - 4)


def test_only_views_within_the_window_and_in_view_count():
    # the pass of the lateral test, but the camera sees the obstacle only at the first frame and from 2.5 s on,
    # standing still from 0.5 s: the early view gives the parallax while within the window (1 s here)
    F = 40
    p = np.zeros((F, 3))
    p[:5, 1] = np.arange(5) / RATE * 4.0  # 1.6 m east in 0.4 s
    p[5:, 1] = p[4, 1]
    view = front_view(F)
    view[1:25] = False
    truth = truth_of(p, np.zeros(F), (20.0, 0.0), view)
    got = rangeable_of(truth, ScoreConfig(warmup_s=0.0, rangeable_window_s=1.0))
    assert not got[25:].any()  # the only parallax view (frame 0) is 2.5 s back: outside the window
    wide = rangeable_of(truth, ScoreConfig(warmup_s=0.0, rangeable_window_s=5.0))
    assert wide[25:].all() and not wide[0]


def test_summary_reports_the_ceiling_and_detection_among_the_rangeable():
    F = 12
    truth = lateral_pass(F)
    secs = obstacle_sectors(truth)
    # ranged right in every frame but the last; the first four frames are not rangeable
    rows = [od(t + 0.02, {secs[f]: 2000} if f < F - 1 else {}) for f, t in enumerate(truth.t_s)]
    s = summarize(evaluate(RangeMessages.build(od=rows), truth, NOWARM))
    rg = s["rangeable"]
    assert (rg["obstacle_cells_in_view"], rg["cells"], rg["within_tolerance"], rg["unknown"]) == (F, F - 4, F - 5, 1)
    assert rg["not_rangeable_within_tolerance"] == 4
    assert rg["share"] == pytest.approx((F - 4) / F) and rg["rate"] == pytest.approx((F - 5) / (F - 4))
    assert "Rangeable in view" in markdown(s)


def test_rangeable_config_is_validated():
    for bad in (dict(rangeable_window_s=0.0), dict(rangeable_parallax_deg=-1.0), dict(rangeable_parallax_deg=90.0),
                dict(rangeable_scale=float("nan"))):
        with pytest.raises(Exception, match="rangeable"):
            ScoreConfig(**bad)


def test_remembered_cells_are_rangeable_only_if_their_point_was_when_last_seen():
    # facing east at the obstacle 20 m away, then turned to face west (the obstacle behind, remembered)
    F0, F1 = 10, 5
    yaw = np.r_[np.full(F0, math.pi / 2), np.full(F1, -math.pi / 2)]
    rows_of = lambda truth: [od(t + 0.02, {}) for t in truth.t_s]  # nothing published: only the cells' sets matter
    still = truth_of(np.zeros((F0 + F1, 3)), yaw, (0.0, 20.0))
    s = summarize(evaluate(RangeMessages.build(od=rows_of(still)), still, NOWARM))
    assert s["remembered"]["cells"] == F1 and s["remembered"]["rangeable_cells"] == 0  # seen from one place only
    # the same, but sliding 1 m north while facing it: 2.9° of parallax before the turn
    p = np.zeros((F0 + F1, 3))
    p[:F0, 0] = np.arange(F0) / (F0 - 1)
    p[F0:, 0] = 1.0
    slid = truth_of(p, yaw, (0.0, 20.0))
    s = summarize(evaluate(RangeMessages.build(od=rows_of(slid)), slid, NOWARM))
    assert s["remembered"]["cells"] == F1 and s["remembered"]["rangeable_cells"] == F1
    assert s["remembered"]["rangeable_within_tolerance"] == 0 and s["remembered"]["rangeable_rate"] == 0.0
    assert "of them rangeable when last in view 5" in markdown(s)


def test_time_to_the_first_valid_range_is_also_counted_from_when_the_obstacle_could_be_ranged():
    # the lateral pass: in view from 0 s, rangeable from 0.4 s (1° of parallax); ranged right from 0.6 s
    F = 12
    truth = lateral_pass(F)
    secs = obstacle_sectors(truth)
    rows = [od(t + 0.02, {secs[f]: 2000} if f >= 6 else {}) for f, t in enumerate(truth.t_s)]
    s = summarize(evaluate(RangeMessages.build(od=rows), truth, NOWARM))
    (o,) = s["obstacles"]
    assert o["in_range_at_s"] == pytest.approx(0.02) and o["first_rangeable_at_s"] == pytest.approx(0.42)
    assert o["time_to_first_valid_s"] == pytest.approx(0.6)
    assert o["time_to_first_valid_after_rangeable_s"] == pytest.approx(0.2)
    # turning in place: never rangeable, never ranged
    yaw = np.radians(-20.0 + 4.0 * np.arange(F))
    spin = truth_of(np.zeros((F, 3)), yaw, (15.0, 0.0))
    s = summarize(evaluate(RangeMessages.build(od=[od(t + 0.02, {}) for t in spin.t_s]), spin, NOWARM))
    assert all(o["first_rangeable_at_s"] is None and o["time_to_first_valid_after_rangeable_s"] is None for o in s["obstacles"])


def test_a_view_that_did_not_see_the_point_does_not_make_it_rangeable():
    """The lateral pass again, but the first 0.5 s of views were blocked (a line-of-sight test that says no from
    east < 0.45 m): the parallax must now build up from the first view that saw the point, at 0.5 s, so the cell
    becomes rangeable at 0.9 s instead of 0.4 s; with rangeable_visible off the world's answer is ignored."""
    F = 14
    truth = lateral_pass(F)

    def visible(origins, points):
        return np.asarray(origins)[:, 1] >= 0.45

    cand = np.isfinite(truth.sector_m) & truth.view

    def per_frame(cfg):
        out = rangeable_cells(truth, truth.view, np.arange(F), cand, cfg, visible=visible)
        return [bool(out[f][cand[f]].any()) for f in range(F)]

    # from 0.5 m (seen) the parallax reaches 1° at 0.5 + 0.349 m: the frame at 0.9 s
    assert per_frame(NOWARM) == [False] * 9 + [True] * (F - 9)
    off = ScoreConfig(warmup_s=0.0, rangeable_visible=False)
    assert per_frame(off) == [False] * 4 + [True] * (F - 4)
