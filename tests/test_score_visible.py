"""Remembered cells must have been *seen*, not only in view (`[score] remember_visible`): a box passed along
one face, whose far faces the camera never saw — exact geometry with the simulator's own world and sector truth."""

import dataclasses
import math

import numpy as np
import pytest

from companion.core.camera import CameraConfig
from companion.errors import ConfigError
from flightsim.score.config import ScoreConfig
from flightsim.score.evaluation import evaluate
from flightsim.score.inputs import RangeMessages, SectorTruth
from flightsim.score.obstacles import world_visibility
from flightsim.score.summary import summarize
from flightsim.world import BoxConfig, CylinderConfig, GroundConfig, World, WorldConfig
from flightsim.world.truth import sector_truth_360

RATE = 10.0
CAM = CameraConfig(width=320, height=240, fx=277.1, fy=277.1, cx=159.5, cy=119.5)  # 60° across, facing forward
CFG = ScoreConfig(warmup_s=0.0)
#: block_a of quad_corner: north 5…25, east 5…25, 12 m tall; the vehicle flies north along east 0 at 5 m altitude
BOX = World(WorldConfig(ground=GroundConfig(enabled=False),
                        box=(BoxConfig(name="block", centre_ne_m=(15.0, 15.0), size_m=(20.0, 20.0), height_m=12.0),)))


def flight(world: World):
    """North along east 0 from N 0 to N 30 at 5 m/s, facing north (60 frames), then 40 frames held at N 30.
    Returns the truth (the simulator's sector truth over 360°, its in-view mask) and the vehicle's poses."""
    n = np.r_[np.arange(60) * 0.5, np.full(40, 30.0)]
    p = np.stack([n, np.zeros_like(n), np.full_like(n, -5.0)], 1)
    sec, view = zip(*(sector_truth_360(world, np.eye(3), q, CAM, 40.0, band_half_height_m=1.5) for q in p))
    t = 1000.0 + np.arange(len(n)) / RATE
    return SectorTruth(t, np.array(sec), p, np.zeros(len(n)), 40.0, np.array(view))


def claim_everything(truth: SectorTruth) -> RangeMessages:
    """Every finite truth cell claimed at its true distance (a perfect memory)."""
    rows = []
    for f, t in enumerate(truth.t_s):
        d = np.full(72, 65535)
        fin = np.isfinite(truth.sector_m[f])
        d[fin] = np.rint(truth.sector_m[f][fin] * 100).astype(int)
        rows.append((t + 0.02, 0, d, 50, 4000))
    return RangeMessages.build(od=rows)


def test_the_far_faces_of_a_box_passed_along_one_face_are_not_remembered():
    truth = flight(BOX)
    msgs = claim_everything(truth)
    plain = evaluate(msgs, truth, CFG)  # no world: in view counts as seen
    seen = evaluate(msgs, truth, CFG, visible=world_visibility(BOX))
    assert any("lines of sight not checked" in n for n in plain.notes)
    assert not any("lines of sight" in n for n in seen.notes)
    R0, R1 = plain.od_remember, seen.od_remember
    assert R1.sum() < R0.sum() and not np.any(R1 & ~R0)  # only ever fewer
    # held at N 30, 5 m north of the box's north face: the box's nearest point is its north-west corner (bearing
    # 135°, 7.07 m).  Sectors 120° and 125° look at the north face, which faced away from the vehicle the whole way:
    # in view earlier, never seen, so dropped.  Sectors 135–160° look at the west face, seen on the way: remembered.
    last = len(truth.t_s) - 1
    assert truth.sector_m[last, 27] == pytest.approx(math.hypot(5.0, 5.0))
    north_face, west_face = [24, 25], [27, 28, 29, 30, 31, 32]
    assert np.all(R0[last, north_face]) and not np.any(R1[last, north_face])
    assert np.all(R0[last, west_face]) and np.all(R1[last, west_face])
    # the score says so in its remembered counts
    a, b = summarize(plain)["remembered"], summarize(seen)["remembered"]
    assert b["cells"] == int(R1.sum()) < a["cells"] == int(R0.sum()) and b["rate"] == a["rate"] == 1.0
    # switched off, the world changes nothing
    off = evaluate(msgs, truth, dataclasses.replace(CFG, remember_visible=False), visible=world_visibility(BOX))
    assert np.array_equal(off.od_remember, R0) and not any("lines of sight" in n for n in off.notes)


def test_a_thin_pole_does_not_hide_its_own_far_side_but_another_obstacle_hides_what_is_behind():
    pole = World(WorldConfig(ground=GroundConfig(enabled=False),
                             cylinder=(CylinderConfig(name="pole", centre_ne_m=(10.0, 0.0), radius_m=0.6, height_m=8.0),
                                       CylinderConfig(name="far", centre_ne_m=(20.0, 0.0), radius_m=0.3, height_m=8.0))))
    vis = world_visibility(pole)
    o = np.array([[0.0, 0.0, -4.0]] * 4)
    pts = np.array([[9.4, 0.0, -4.0],    # the pole's near face: seen
                    [10.6, 0.0, -4.0],   # its far face, 1.2 m behind the near one: within the 1.5 m tolerance
                    [19.7, 0.0, -4.0],   # the far pole's face, straight behind the near pole: hidden
                    [19.7, 3.0, -4.0]])  # a point beside both, in free space: seen
    assert vis(o, pts).tolist() == [True, True, False, True]
    strict = world_visibility(pole, tolerance_m=0.5, tolerance_rel=0.0)
    assert strict(o, pts).tolist() == [True, False, False, True]
    assert vis(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)
    assert vis(o[:1], o[:1]).tolist() == [True]  # the point itself: nothing in between


@pytest.mark.parametrize("bad", [{"remember_visible": "yes"}, {"visible_tolerance_m": -1.0}, {"visible_tolerance_rel": 1.0},
                                 {"visible_tolerance_m": math.nan}])
def test_visibility_settings_are_validated(bad):
    with pytest.raises(ConfigError):
        ScoreConfig(**bad)
