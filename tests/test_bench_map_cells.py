"""bench.map_cells: what the map held in a sector, on exact geometry (a vehicle at the origin, 5 m up, heading east)."""

import math

import numpy as np

from bench.map_cells import KINDS, classify

P = np.array([0.0, 0.0, -5.0])  # NED: 5 m above the origin
YAW = math.pi / 2  # facing east: body sector 0 looks east, sector 18 south, sector 54 north


def at(bearing_body_deg, dist, height_above_vehicle):
    b = YAW + math.radians(bearing_body_deg)
    return [dist * math.cos(b), dist * math.sin(b), P[2] - height_above_vehicle]


def test_each_kind_from_the_points_in_the_sector():
    pts = np.array([at(90.0, 6.0, 0.5),     # sector 18, in the band, published
                    at(180.0, 6.0, 1.0),    # sector 36, in the band, withheld
                    at(181.0, 6.0, 4.0),    # sector 36 too, off the band
                    at(270.0, 6.0, -3.0),   # sector 54, 3 m below: off the band only
                    at(272.4, 6.0, 2.0)])   # sector 54 (272.4° rounds to 270°), 2 m above: off the band
    pub = np.array([True, False, True, False, True])
    kinds = classify(P, YAW, pts, pub, np.array([18, 36, 54, 0, 55]), band_m=1.5)
    assert [KINDS[k] for k in kinds] == ["published", "withheld", "off_band_only", "no_map_point", "no_map_point"]
    # a wider band takes the 2 m point in: published
    assert KINDS[classify(P, YAW, pts, pub, np.array([54]), band_m=2.5)[0]] == "published"
    # no map at all, or no sector asked for
    assert [KINDS[k] for k in classify(P, YAW, np.zeros((0, 3)), np.zeros(0, bool), np.array([18]), 1.5)] == ["no_map_point"]
    assert classify(P, YAW, pts, pub, np.zeros(0, np.int64), 1.5).shape == (0,)
