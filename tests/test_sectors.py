"""Obstacle sectors (DESIGN §5): hand-computed geometry for every OBSTACLE_DISTANCE rule."""

import dataclasses
import math

import numpy as np
import pytest

from companion.core.frames import euler_zyx_to_R
from companion.core.sectors import (
    SECTOR_COUNT,
    UNKNOWN_CM,
    SectorConfig,
    SectorState,
    compute_sectors,
    rotate_sectors,
    sector_view_masks,
)
from companion.errors import ConfigError, InputError
from conftest import sectors_optional_rules_off

HFOV = math.radians(60.0)
# as shipped (min 0.5 m, max 40 m, k = 2, band ±1.5 m, 1 point per obstacle, 3 per clear) but with the margin's
# taper off, so every value below is r − 2σ at any range; the taper acts only on final values (its own tests below)
CFG = SectorConfig(sigma_k_taper_to_m=0.0)
CLEAR = CFG.max_distance_cm + 1
NEAREST_POINT = dataclasses.replace(CFG, fuse_gate_k=0.0)  # each sector publishes its nearest point (no surface fusion)
NO_CORRIDOR = dataclasses.replace(CFG, clear_corridor_m=0.0)  # "clear" may stand beside an obstacle (rule 10 off)


def run(points, sigma=0.5, converged=True, valid=True, cam=0.0, config=CFG, **kw):
    p = np.asarray(points, float).reshape(-1, 3)
    n = len(p)
    sig = np.broadcast_to(np.asarray(sigma, float), (n,)).copy()
    conv = np.broadcast_to(np.asarray(converged, bool), (n,)).copy()
    val = np.broadcast_to(np.asarray(valid, bool), (n,)).copy()
    return compute_sectors(p, sig, conv, val, HFOV, cam, config, **kw)


def wall(x=10.0, bearings_deg=range(-20, 21)):
    b = np.radians(np.asarray(list(bearings_deg), float))
    return np.stack([np.full(b.shape, x), x * np.tan(b), np.zeros(b.shape)], 1)


def random_scenes(seed: int, n_scenes: int = 200, max_height: float = 8.0):
    """Seeded random scenes for the only-adds / only-lowers Monte Carlo tests: (points, σ, converged)."""
    rng = np.random.default_rng(seed)
    for _ in range(n_scenes):
        n = int(rng.integers(1, 40))
        d = rng.uniform(1.0, 60.0, n)
        b = rng.uniform(-0.6, 0.6, n)
        h = rng.uniform(-max_height, max_height, n)
        yield np.stack([d * np.cos(b), d * np.sin(b), h], 1), rng.uniform(0.05, 3.0, n), rng.random(n) < 0.8


def test_fov_mask_forward_60deg():
    in_view, full = sector_view_masks(HFOV, 0.0)
    # sectors centred at −30…30° touch the 60° field of view; −25…25° lie entirely inside it
    assert np.flatnonzero(in_view).tolist() == [0, 1, 2, 3, 4, 5, 6, 66, 67, 68, 69, 70, 71]
    assert np.flatnonzero(full).tolist() == [0, 1, 2, 3, 4, 5, 67, 68, 69, 70, 71]


def test_no_points_is_unknown_never_clear():
    s = run(np.zeros((0, 3)))
    assert s.distances_cm.dtype == np.uint16 and s.distances_cm.shape == (SECTOR_COUNT,)
    assert np.all(s.distances_cm == UNKNOWN_CM)
    assert np.all(s.state == SectorState.UNKNOWN)
    assert not s.any_valid
    assert s.forward.state == SectorState.UNKNOWN


def test_wall_gives_conservative_centimetres():
    s = run(wall(10.0), sigma=0.5, config=NEAREST_POINT)
    # on the horizontal (z = 0) the conservative range is r − 2·0.5 = r − 1 m, nearest point per sector
    # (the fused surface of the same points: tests/test_sectors_fusion.py)
    assert s.distances_cm[0] == 900  # bearing 0°: r = 10
    assert s.distances_cm[1] == round((10 / math.cos(math.radians(3)) - 1) * 100)  # nearest bearing 3°
    assert s.distances_cm[71] == s.distances_cm[1]  # symmetric
    assert s.distances_cm[4] == round((10 / math.cos(math.radians(18)) - 1) * 100)  # bearings 18…20°
    assert s.distances_cm[5] == UNKNOWN_CM and s.distances_cm[67] == UNKNOWN_CM  # in view, no evidence
    assert np.all(s.distances_cm[6:66] == UNKNOWN_CM)  # not seen
    assert s.forward.state == SectorState.OBSTACLE
    assert s.forward.distance_m == pytest.approx(9.0) and s.forward.sigma_m == pytest.approx(0.5)
    assert s.forward.estimate_m == pytest.approx(10.0)
    assert s.nearest[0].sector == 0 and s.nearest[0].range_m == pytest.approx(9.0)
    assert s.nearest[0].p_body == pytest.approx((9.0, 0.0, 0.0))
    assert len(s.nearest) == CFG.nearest_count
    assert s.nearest_m == pytest.approx(9.0)


def test_far_points_claim_clear_only_with_enough_evidence():
    far = wall(100.0, [-1, 0, 1])
    s = run(far, sigma=1.0)  # conservative 98 m > 40 m
    assert s.distances_cm[0] == CLEAR and s.state[0] == SectorState.CLEAR
    assert s.forward.state == SectorState.CLEAR
    assert np.all(np.delete(s.distances_cm, 0) == UNKNOWN_CM)
    # two points are not enough evidence (min_points_clear = 3)
    s2 = run(far[:2], sigma=1.0)
    assert s2.distances_cm[0] == UNKNOWN_CM
    # a far point whose σ makes it possibly near is not evidence of free space: 50 − 2·10 = 30 m
    s3 = run(wall(50.0, [-1, 0, 1]), sigma=10.0, config=NEAREST_POINT)
    assert s3.distances_cm[0] == 3000
    # fused, the three points (correlation ρ) give σ̄ = 10·√(ρ + (1 − ρ)/3): still an obstacle, never clear
    s4 = run(wall(50.0, [-1, 0, 1]), sigma=10.0)
    sig_bar = 10.0 * math.sqrt(CFG.fuse_correlation + (1 - CFG.fuse_correlation) / 3)
    assert s4.state[0] == SectorState.OBSTACLE
    assert int(s4.distances_cm[0]) == pytest.approx((50.0 - CFG.sigma_k * sig_bar) * 100, abs=2)


def test_one_near_point_among_far_ones_wins():
    pts = np.vstack([wall(100.0, [-2, -1, 0, 1, 2]), [[8.0, 0.0, 0.0]]])
    s = run(pts, sigma=0.5)
    assert s.distances_cm[0] == 700
    assert s.state[0] == SectorState.OBSTACLE


def test_unconverged_near_point_vetoes_clear_but_claims_nothing():
    pts = np.vstack([wall(100.0, [-1, 0, 1]), [[20.0, 0.0, 0.0]]])
    s = run(pts, sigma=[1, 1, 1, 5.0], converged=[True, True, True, False])
    assert s.distances_cm[0] == UNKNOWN_CM
    cfg = SectorConfig(unconverged_veto_clear=False)
    assert run(pts, sigma=[1, 1, 1, 5.0], converged=[True, True, True, False], config=cfg).distances_cm[0] == cfg.max_distance_cm + 1


def test_clear_from_lines_of_sight_that_stay_in_the_band():
    """Rule 3, the line of sight: three background points at 80 m, 2.5 m above the vehicle (the band is ±1.5 m).
    Off, they are out of the band and the sector stays unknown. On (as shipped), each one's line
    of sight rises 2.5·40/80 = 1.25 m over the first 40 m, inside the band: the band is free along it, so the sector
    is clear. 3.5 m up (1.75 m at 40 m) it leaves the band before max_distance and proves nothing; a near point
    still wins, an unconverged one still vetoes, and a degrees band (a cone, which already holds such rays) is
    unchanged."""
    on = SectorConfig(clear_line_of_sight=True, sigma_k_taper_to_m=0.0)
    assert CFG.clear_line_of_sight
    high = wall(80.0, [-1, 0, 1]) + [0.0, 0.0, -2.5]  # body FRD: z down
    assert run(high, sigma=1.0, config=SectorConfig(clear_line_of_sight=False, sigma_k_taper_to_m=0.0)).state[0] == SectorState.UNKNOWN
    s = run(high, sigma=1.0, config=on)
    assert s.state[0] == SectorState.CLEAR and s.distances_cm[0] == CLEAR
    assert np.all(np.delete(s.state, 0) == SectorState.UNKNOWN)
    higher = wall(80.0, [-1, 0, 1]) + [0.0, 0.0, -3.5]
    assert run(higher, sigma=1.0, config=on).state[0] == SectorState.UNKNOWN
    below = wall(80.0, [-1, 0, 1]) + [0.0, 0.0, 2.5]
    assert run(below, sigma=1.0, config=on).state[0] == SectorState.CLEAR
    assert run(np.vstack([high, [[12.0, 0.0, 0.0]]]), sigma=1.0, config=on).distances_cm[0] == 1000
    vetoed = run(np.vstack([high, [[20.0, 0.0, 0.0]]]), sigma=[1, 1, 1, 5.0], converged=[True] * 3 + [False], config=on)
    assert vetoed.state[0] == SectorState.UNKNOWN
    cone = dataclasses.replace(on, band_mode="degrees")
    cone_off = dataclasses.replace(cone, clear_line_of_sight=False)
    assert run(higher, sigma=1.0, config=cone).state[0] == run(higher, sigma=1.0, config=cone_off).state[0]
    with pytest.raises(ConfigError, match="clear_line_of_sight"):
        SectorConfig(clear_line_of_sight=1)


def test_no_clear_within_the_corridor_of_a_near_obstacle():
    """Rule 10, the corridor: a pole 4 m ahead at −3.5° (sector 71, 4.01 m horizontally; σ 0.2, published at
    3.61 m) and the background at 100 m in sectors 68, 69, 70, 0, 1 and 2. Without the corridor every one of them is
    clear (the pole's corner is 1.5° from its sector's centre, inside the edge margin). With 0.5 m,
    asin(0.5/3.61) = 7.96°: the first neighbour
    on each side (edge 0° away) and the second (5° away) lose "clear", the third (10° away) keeps it. The same pole
    at 30 m (0.97°) takes only the first neighbours; obstacle and unknown sectors are never changed. Shipped: 0.5 m."""
    background = wall(100.0, [-21, -20, -19, -16, -15, -14, -11, -10, -9, -1, 0, 1, 4, 5, 6, 9, 10, 11])
    pole = wall(4.0, [-3.5])
    off = run(np.vstack([background, pole]), sigma=0.2, config=SectorConfig(clear_corridor_m=0.0))
    assert off.state[71] == SectorState.OBSTACLE
    assert [off.state[k] for k in (68, 69, 70, 0, 1, 2)] == [SectorState.CLEAR] * 6
    on = SectorConfig(clear_corridor_m=0.5)
    assert CFG.clear_corridor_m == 0.5
    s = run(np.vstack([background, pole]), sigma=0.2, config=on)
    assert s.state[71] == SectorState.OBSTACLE and s.distances_cm[71] == 361
    assert [s.state[k] for k in (68, 69, 70, 0, 1, 2)] == [SectorState.CLEAR, *[SectorState.UNKNOWN] * 4, SectorState.CLEAR]
    assert all(s.distances_cm[k] == UNKNOWN_CM for k in (69, 70, 0, 1))
    far = run(np.vstack([background, wall(30.0, [-3.5])]), sigma=0.2, config=on)
    assert [far.state[k] for k in (68, 69, 70, 0, 1, 2)] == [SectorState.CLEAR] * 2 + [SectorState.UNKNOWN] * 2 + [SectorState.CLEAR] * 2
    with pytest.raises(ConfigError, match="clear_corridor_m"):
        SectorConfig(clear_corridor_m=-1.0)


def _ring(d_m, bearings_deg, z=0.0):
    """Points at horizontal distance ``d_m`` and the given body bearings (clockwise from forward), height z."""
    b = np.radians(np.asarray(list(bearings_deg), float))
    return np.stack([d_m * np.cos(b), d_m * np.sin(b), np.full(b.shape, z)], 1)


def test_far_claim_out_of_view_within_the_corridor_of_a_near_obstacle_is_capped():
    """Rule 10's far part (``corridor_far_ratio``), out of view: the map remembers a mast 4 m away at 86.5°
    (sector 17, published 3.60 m) and a building 28 m away behind and beside it, at 73–105° (sectors 15, 16 and
    18–21). asin(0.5/3.60) = 7.98°: the mast's corridor reaches two sectors on each side (15, 16, 18, 19), whose
    building claims (more than twice 3.60 m) are capped at the mast's value and marked inferred; sectors 20 and 21,
    beyond the corridor, keep the building. A claim less than the ratio farther (a surface going on, 6 m in sector
    18) stays. In view the same scene moves nothing (a sector's own points place the edge there); off (0) nothing
    moves, nor without a corridor; no sector changes state. Shipped: 2."""
    mast, building = _ring(4.0, [86.5]), _ring(28.0, [73.0, 78.0, 90.5, 95.0, 100.0, 105.0])
    live = np.zeros((0, 3))

    def remembered(*parts, config):
        mem = np.vstack(parts)
        return run(live, config=config, remembered_p_body=mem, remembered_sigma=np.full(len(mem), 0.2),
                   remembered_tangential_sigma=np.full(len(mem), 0.01))

    on = SectorConfig(clear_corridor_m=0.5, corridor_far_ratio=2.0)
    off_cfg = SectorConfig(clear_corridor_m=0.5, corridor_far_ratio=0.0)
    assert CFG.corridor_far_ratio == 2.0  # as shipped
    off, s = remembered(building, mast, config=off_cfg), remembered(building, mast, config=on)
    assert not np.any(s.in_view[15:22])
    assert s.state[17] == SectorState.OBSTACLE and off.distances_cm[17] == s.distances_cm[17] < 400
    for k in (15, 16, 18, 19):
        assert off.state[k] == SectorState.OBSTACLE and off.distances_cm[k] > 2700
        assert s.distances_cm[k] == s.distances_cm[17] and s.inferred[k]
        assert s.range_m[k] == pytest.approx(s.range_m[17]) and s.sigma_m[k] == pytest.approx(s.sigma_m[17])
    for k in (20, 21):
        assert s.distances_cm[k] == off.distances_cm[k] > 2700 and not s.inferred[k]
    assert np.array_equal(s.state, off.state)  # only far claims get nearer
    wall_on = _ring(6.0, [90.5])
    near_on, near_off = remembered(building, mast, wall_on, config=on), remembered(building, mast, wall_on, config=off_cfg)
    assert near_on.distances_cm[18] == near_off.distances_cm[18] < 600 and not near_on.inferred[18]
    # in view (the same scene turned to straight ahead): unchanged
    turned = [_ring(28.0, np.array([73.0, 78.0, 90.5, 95.0, 100.0, 105.0]) - 90.0), _ring(4.0, [-3.5])]
    a, b = run(np.vstack(turned), sigma=0.2, config=on), run(np.vstack(turned), sigma=0.2, config=off_cfg)
    assert np.all(a.in_view[[69, 70, 71, 0, 1]]) and np.array_equal(a.distances_cm, b.distances_cm)
    with pytest.raises(ConfigError, match="corridor_far_ratio"):
        SectorConfig(corridor_far_ratio=0.5)
    no_corridor = SectorConfig(clear_corridor_m=0.0, corridor_far_ratio=2.0)  # no corridor, nothing to cap within
    assert np.array_equal(remembered(building, mast, config=no_corridor).distances_cm,
                          remembered(building, mast, config=SectorConfig(clear_corridor_m=0.0, corridor_far_ratio=0.0)).distances_cm)


def test_point_near_a_sector_edge_forbids_clear_across_it():
    """Rule 3, the edge margin: a tower's last corner 0.3° inside sector 2's edge (12.5°) and the background at
    100 m in sector 3 (13–17°). Off, sector 3 is clear beside the tower; with the shipped 1° it stays unknown, and
    so it does for an unconverged point there too; a corner 2° inside the edge forbids nothing; sector 1, across
    the far edge of sector 2, keeps its own evidence of clear. (Rule 10, the corridor, off: it would take sectors 1
    and 3 beside the tower at 30 m whatever the margin.)"""
    background = wall(100.0, [3.5, 5.0, 6.5, 13.0, 15.0, 17.0])
    tower = wall(30.0, [12.2])
    on = SectorConfig(clear_edge_margin_deg=1.0, clear_corridor_m=0.0)
    assert CFG.clear_edge_margin_deg == 1.0  # as shipped
    pts = np.vstack([background, tower])
    off = run(pts, sigma=1.0, config=SectorConfig(clear_edge_margin_deg=0.0, clear_corridor_m=0.0))
    assert off.state[3] == SectorState.CLEAR and off.state[2] == SectorState.OBSTACLE
    s = run(pts, sigma=1.0, config=on)
    assert s.state[3] == SectorState.UNKNOWN and s.distances_cm[3] == UNKNOWN_CM
    assert s.state[2] == SectorState.OBSTACLE and s.state[1] == SectorState.CLEAR
    assert run(pts, sigma=[1.0] * 6 + [8.0], converged=[True] * 6 + [False], config=on).state[3] == SectorState.UNKNOWN
    inside = np.vstack([background, wall(30.0, [10.5])])
    assert run(inside, sigma=1.0, config=on).state[3] == SectorState.CLEAR
    left = np.vstack([wall(100.0, [-6.5, -5.0, -3.5, 3.5, 5.0, 6.5]), wall(30.0, [-2.2])])  # edge −2.5°: sector 71
    s = run(left, sigma=1.0, config=on)
    assert s.state[71] == SectorState.UNKNOWN and s.state[1] == SectorState.CLEAR
    with pytest.raises(ConfigError, match="clear_edge_margin_deg"):
        SectorConfig(clear_edge_margin_deg=2.5)


def test_points_outside_the_band_are_ignored():
    above = [[10.0, 0.0, -3.0], [10.0, 0.0, 2.0]]  # 3 m above, 2 m below: outside ±1.5 m
    band_alone = sectors_optional_rules_off()
    assert np.all(run(above, config=band_alone).distances_cm == UNKNOWN_CM)
    # (as shipped, the vertical-span rule reads that pair as a pole through the band: see its test)
    assert run(above).state[0] == SectorState.OBSTACLE and run(above).inferred[0]
    inside = [[10.0, 0.0, -1.0]]
    r = math.sqrt(101.0)
    assert run(inside).distances_cm[0] == round(10.0 * (r - 1.0) / r * 100)
    # degrees mode: ±10° cone — 3 m above at 10 m (16.7°) is out, at 20 m (8.5°) is in
    deg = SectorConfig(band_mode="degrees", band_half_angle_deg=10.0)
    assert run([[10.0, 0.0, -3.0]], config=deg).distances_cm[0] == UNKNOWN_CM
    assert run([[20.0, 0.0, -3.0]], config=deg).distances_cm[0] != UNKNOWN_CM


def test_invalid_and_garbage_points_are_ignored_and_counted():
    pts = [[10.0, 0.0, 0.0], [np.nan, 0, 0], [5.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    s = run(pts, sigma=[0.5, 0.5, np.inf, 0.5], valid=[True, True, True, True])
    assert s.distances_cm[0] == 900
    assert s.points_rejected == 3
    s2 = run([[5.0, 0, 0]], valid=False)
    assert s2.distances_cm[0] == UNKNOWN_CM and s2.points_rejected == 0
    with pytest.raises(InputError):
        compute_sectors(np.zeros((3, 2)), np.zeros(3), np.ones(3, bool), np.ones(3, bool), HFOV, 0.0)
    with pytest.raises(InputError):
        compute_sectors(np.zeros((3, 3)), np.zeros(2), np.ones(3, bool), np.ones(3, bool), HFOV, 0.0)


def test_fov_masking_and_camera_yaw_offset():
    p = [[10 * math.cos(math.radians(60)), 10 * math.sin(math.radians(60)), 0.0]]  # bearing 60° (sector 12)
    assert run(p).distances_cm[12] == UNKNOWN_CM  # outside a forward 60° camera
    s = run(p, cam=math.radians(60))  # camera turned 60° right
    assert s.distances_cm[12] == 900
    assert s.in_view[12] and not s.in_view[0]
    # the same through an explicit R_cam_body
    from companion.core.frames import mount_rotation

    assert run(p, cam=mount_rotation(0, 0, 60)).distances_cm[12] == 900
    # a sector only partly in view can hold an obstacle, but never "clear"
    edge = wall(10.0, [29])
    assert run(edge).distances_cm[6] != UNKNOWN_CM
    assert run(wall(100.0, [28, 29, 29.5]), sigma=1.0).distances_cm[6] == UNKNOWN_CM


def test_near_obstacles_are_clamped_not_dropped():
    s = run([[0.6, 0.0, 0.0]], sigma=0.2)  # conservative 0.2 m < min 0.5 m
    assert s.distances_cm[0] == CFG.min_distance_cm
    s = run([[0.6, 0.0, 0.0]], sigma=5.0)  # conservative below zero
    assert s.distances_cm[0] == CFG.min_distance_cm  # never 0: ArduPilot discards 0
    touch = SectorConfig(touching_distance_m=0.3)
    assert run([[0.2, 0.0, 0.0]], sigma=0.01, config=touch).distances_cm[0] == 0
    # an obstacle just inside max_distance is reported at most max_distance
    assert run([[40.5, 0.0, 0.0]], sigma=0.5).distances_cm[0] == 3950
    assert run([[41.0, 0.0, 0.0]], sigma=0.5).distances_cm[0] == CFG.max_distance_cm  # exactly at max: an obstacle
    assert run([[41.0, 0.0, 0.0]], sigma=0.4, config=SectorConfig(min_points_clear=1)).distances_cm[0] == CLEAR


def test_min_points_obstacle_reports_nth_nearest():
    cfg = SectorConfig(min_points_obstacle=2, sigma_k_taper_to_m=0.0)
    pts = [[8.0, 0.0, 0.0], [12.0, 0.0, 0.0], [15.0, 0.0, 0.0]]
    assert run(pts, config=cfg).distances_cm[0] == 1100  # second nearest: 12 − 1
    assert run(pts[:1], config=cfg).distances_cm[0] == UNKNOWN_CM  # one point: no claim, and no clear either


def test_attitude_levels_the_sectors():
    # nose 20° up: a level obstacle 10 m ahead appears 3.4 m "below" the body x axis
    R_lb = euler_zyx_to_R(0.0, math.radians(20), 0.0)
    p_body = R_lb.T @ np.array([10.0, 0.0, 0.0])
    assert run([p_body]).distances_cm[0] == UNKNOWN_CM  # taken as level: outside the band
    assert run([p_body], roll_pitch_rad=(0.0, math.radians(20))).distances_cm[0] == 900
    # rolled 30° right: a point 20° right, level, is still in sector 4 after levelling
    R_lb = euler_zyx_to_R(math.radians(30), 0.0, 0.0)
    p_level = np.array([10 * math.cos(math.radians(20)), 10 * math.sin(math.radians(20)), 0.0])
    s = run([R_lb.T @ p_level], roll_pitch_rad=(math.radians(30), 0.0))
    assert s.distances_cm[4] == 900


def test_band_follows_the_flight_path():
    gamma = math.radians(10)
    p = [[20.0, 0.0, -20.0 * math.tan(gamma)]]  # on a 10° climb line, 3.5 m above
    assert run(p).distances_cm[0] == UNKNOWN_CM
    v = [10 * math.cos(gamma), 0.0, -10 * math.sin(gamma)]
    s = run(p, velocity_body=v)
    r = math.hypot(20.0, 20.0 * math.tan(gamma))
    assert s.distances_cm[0] == round(20.0 * (r - 1.0) / r * 100)
    assert run(p, velocity_body=[0.1, 0, -0.5]).distances_cm[0] == UNKNOWN_CM  # too slow: level band


def test_rotation_by_yaw_change():
    d = np.full(SECTOR_COUNT, UNKNOWN_CM, np.uint16)
    d[0] = 900
    r = rotate_sectors(d, math.radians(10), CFG.max_distance_cm)  # turned right 10°: obstacle now at −10°
    assert r[70] == 900 and np.count_nonzero(r != UNKNOWN_CM) == 1
    r = rotate_sectors(d, math.radians(-15), CFG.max_distance_cm)
    assert r[3] == 900
    r = rotate_sectors(d, math.radians(2.5), CFG.max_distance_cm)  # half a sector: both neighbours keep it
    assert r[0] == 900 and r[71] == 900 and np.count_nonzero(r != UNKNOWN_CM) == 2
    assert np.array_equal(rotate_sectors(d, 0.0, CFG.max_distance_cm), d)
    assert np.all(rotate_sectors(d, math.nan, CFG.max_distance_cm) == UNKNOWN_CM)


def test_rotation_never_invents_clear():
    d = np.full(SECTOR_COUNT, UNKNOWN_CM, np.uint16)
    d[0:3] = CLEAR
    d[3] = 1500
    r = rotate_sectors(d, math.radians(2.5), CFG.max_distance_cm)
    assert r[0] == CLEAR and r[1] == CLEAR  # both overlapped sectors clear
    assert r[2] == 1500  # clear + obstacle → the obstacle
    assert r[71] == UNKNOWN_CM  # unknown + clear → unknown
    rng = np.random.default_rng(3)
    for _ in range(200):
        d = rng.choice([UNKNOWN_CM, CLEAR, 500, 2000], size=SECTOR_COUNT).astype(np.uint16)
        yaw = rng.uniform(-math.pi, math.pi)
        r = rotate_sectors(d, yaw, CFG.max_distance_cm)
        assert np.count_nonzero(r == CLEAR) <= np.count_nonzero(d == CLEAR)
        # every obstacle distance still present (nothing near is lost) unless it merged with a nearer one
        assert (r[r <= CFG.max_distance_cm].min(initial=UNKNOWN_CM) == d[d <= CFG.max_distance_cm].min(initial=UNKNOWN_CM))


def test_sectors_rotated_helper_and_config_validation():
    s = run(wall(10.0, [0]))
    assert s.rotated(math.radians(5))[71] == 900
    with pytest.raises(ConfigError):
        SectorConfig(min_distance_m=5, max_distance_m=4)
    with pytest.raises(ConfigError):
        SectorConfig(max_distance_m=700)  # max + 1 cm would collide with UINT16_MAX
    with pytest.raises(ConfigError):
        SectorConfig(band_mode="feet")


def test_rotation_rebins_obstacle_points_instead_of_smearing_them():
    # a mast 3 m right at 30 m (bearing 5.7°, well inside sector 1) seen through a tiny yaw jitter
    s = run([[30.0, 3.0, 0.0], [30.0, 3.05, 0.2]], sigma=0.5)
    assert s.state[1] == SectorState.OBSTACLE and s.distances_cm[0] == UNKNOWN_CM and s.distances_cm[2] == UNKNOWN_CM
    for dyaw_deg in (0.1, -0.1, 0.7, -0.7):
        r = s.rotated(math.radians(dyaw_deg))
        assert r[1] == s.distances_cm[1]
        assert r[0] == UNKNOWN_CM and r[2] == UNKNOWN_CM, dyaw_deg  # no phantom beside it
    # turned far enough, the point itself crosses into the next sector: exactly one sector holds it
    r = s.rotated(math.radians(-2.0))  # turned left 2°: bearing now 7.7° → sector 2
    assert r[2] == s.distances_cm[1] and r[1] == UNKNOWN_CM
    # a turn moves the clear sectors conservatively and keeps the obstacle where its points are
    far = wall(60.0, np.arange(-25.0, 25.5, 0.5))
    s = run(np.concatenate([far, [[30.0, 3.0, 0.0]]]), sigma=0.5, config=NO_CORRIDOR)
    assert s.state[1] == SectorState.OBSTACLE and s.state[0] == SectorState.CLEAR
    r = s.rotated(math.radians(1.0))
    assert r[1] == s.distances_cm[1]
    assert r[0] in (CLEAR, UNKNOWN_CM) and r[2] in (CLEAR, UNKNOWN_CM)
    assert np.all(s.rotated(math.nan) == UNKNOWN_CM)


def test_rotated_with_min_points_obstacle_uses_the_nth_nearest_point():
    cfg = SectorConfig(min_points_obstacle=2, sigma_k_taper_to_m=0.0)
    s = run([[10.0, 0.0, 0.0], [12.0, 0.1, 0.0], [15.0, 0.2, 0.0]], sigma=0.5, config=cfg)
    assert s.distances_cm[0] == 1100  # second nearest: 12 − 2·0.5
    assert s.rotated(math.radians(0.3))[0] == 1100


def test_vertical_span_infers_a_pole_through_the_band():
    """infer_vertical: converged points just above and just below the band at consistent ranges in one
    sector claim an obstacle at the nearer conservative range (a thin pole whose in-band points did not
    converge); the ground far below, inconsistent ranges, one side only or the option off claim nothing."""
    cfg = sectors_optional_rules_off(infer_vertical=True, infer_vertical_window_m=1.5, sigma_k=0.0)
    pole = [[12.0, 0.2, -2.5], [11.0, -0.1, 2.2]]  # FRD: 2.5 m above and 2.2 m below, 11–12 m ahead
    s = run(pole, config=cfg)
    assert s.state[0] == SectorState.OBSTACLE and s.inferred[0]
    assert s.distances_cm[0] == round(math.hypot(11.0, 0.1) * 100)  # the nearer of the two
    assert np.all(s.state[1:] != SectorState.OBSTACLE)
    assert np.array_equal(s.rotated(0.0), s.distances_cm)  # re-binned like any other claim
    assert np.all(run(pole, config=sectors_optional_rules_off(sigma_k=0.0)).distances_cm == UNKNOWN_CM)  # off
    assert np.all(run(pole[:1], config=cfg).distances_cm == UNKNOWN_CM)  # one side only
    assert np.all(run([[12.0, 0.2, -2.5], [16.0, 0.0, 2.2]], config=cfg).distances_cm == UNKNOWN_CM)  # ranges disagree
    assert np.all(run([[12.0, 0.2, -2.5], [12.0, 0.0, 5.0]], config=cfg).distances_cm == UNKNOWN_CM)  # ground 5 m below
    # never clear: a sector with far in-band points and a near vertical span is an obstacle
    far = [[60.0, b, 0.0] for b in (-1.0, 0.0, 1.0)]
    s2 = run(far + pole, config=cfg)
    assert s2.state[0] == SectorState.OBSTACLE
    # a nearer in-band point keeps its own claim
    s3 = run(pole + [[6.0, 0.0, 0.0]], config=cfg)
    assert s3.distances_cm[0] == 600 and not s3.inferred[0]


def test_vertical_span_ignores_the_ground_with_its_height_known():
    """With ``ground_height_m`` (the take-off ground relative to the vehicle, up positive: −5 m for a vehicle 5 m up) a
    point below the band counts only ``infer_vertical_ground_margin_m`` above the ground: texture on
    the ground 12 m ahead pairs with nothing, a pole's point 1.5 m above the ground still does."""
    cfg = sectors_optional_rules_off(infer_vertical=True, infer_vertical_window_m=5.0, infer_vertical_ground_margin_m=1.0,
                                     sigma_k=0.0)
    above = [12.0, 0.1, -3.0]
    on_ground = [12.0, 0.0, 5.0]  # vehicle 5 m up: this point lies on the ground
    on_pole = [12.0, 0.0, 3.5]  # 1.5 m above the ground
    assert np.all(run([above, on_ground], config=cfg, ground_height_m=-5.0).distances_cm == UNKNOWN_CM)
    s = run([above, on_pole], config=cfg, ground_height_m=-5.0)
    assert s.state[0] == SectorState.OBSTACLE and s.inferred[0]
    # without the ground's height the same pair is taken (the window alone keeps the ground out)
    assert run([above, on_ground], config=cfg).state[0] == SectorState.OBSTACLE


def test_vertical_span_only_ever_adds_obstacles_seeded():
    """Seeded Monte Carlo over random scenes: with ``infer_vertical`` on, no sector becomes clear or
    unknown that was an obstacle, none becomes clear that was not, and no claimed range grows."""
    on = sectors_optional_rules_off(infer_vertical=True, infer_vertical_window_m=5.0)
    off = sectors_optional_rules_off()
    for pts, sig, conv in random_scenes(11, max_height=8.0):
        a = run(pts, sigma=sig, converged=conv, config=off, ground_height_m=-5.0)
        v = run(pts, sigma=sig, converged=conv, config=on, ground_height_m=-5.0)
        was_obs = a.state == SectorState.OBSTACLE
        assert np.all(v.state[was_obs] == SectorState.OBSTACLE)
        assert np.all(v.distances_cm[was_obs] <= a.distances_cm[was_obs])
        assert not np.any((v.state == SectorState.CLEAR) & (a.state != SectorState.CLEAR))
        changed = v.state != a.state
        assert np.all(v.state[changed] == SectorState.OBSTACLE) and np.all(v.inferred[changed])


def test_ground_points_are_dropped_with_the_ground_height_known():
    """``ground_margin_m``: a vehicle 1 m up (taking off) sees the ground ahead inside its height band;
    with the ground's height known those points are neither an obstacle nor evidence of clear, while a
    point 0.6 m above the ground still claims; off (0) or without the height, the old behaviour."""
    cfg = sectors_optional_rules_off(ground_margin_m=0.5, sigma_k=0.0)
    ground = [[12.0, 0.0, 1.0], [50.0, 0.0, 1.0], [55.0, 0.5, 1.0], [60.0, -0.5, 1.0]]  # FRD: 1 m below = the ground
    assert np.all(run(ground, config=cfg, ground_height_m=-1.0).distances_cm == UNKNOWN_CM)
    s = run(ground, config=cfg)  # height unknown: as before, the near one claims
    assert s.distances_cm[0] == 1200
    assert run(ground, config=sectors_optional_rules_off(sigma_k=0.0), ground_height_m=-1.0).distances_cm[0] == 1200  # off
    low = run([[12.0, 0.0, 0.4]], config=cfg, ground_height_m=-1.0)  # 0.6 m above the ground
    assert low.distances_cm[0] == 1200
    with pytest.raises(ConfigError):
        SectorConfig(ground_margin_m=-1.0)


def test_points_just_above_the_band_cap_what_the_sector_claims():
    """cap_above_m: a converged point just above the band (a thin pole's upper part, ranged against the
    sky) caps the sector's claim: a farther in-band obstacle (the background through a patch straddling
    the pole's edge) is reported at the pole, a clear sector becomes an obstacle, an unknown one stays
    unknown; points farther above, below the band or unconverged cap nothing; off (0), no cap."""
    cfg = sectors_optional_rules_off(cap_above_m=2.5, sigma_k=0.0)
    far_in_band = [25.0, 0.0, 0.0]
    pole_top = [8.0, 0.1, -3.0]  # FRD: 3 m above the vehicle, 1.5 m above the band's upper edge
    s = run([far_in_band, pole_top], config=cfg)
    assert s.state[0] == SectorState.OBSTACLE and s.inferred[0]
    assert s.distances_cm[0] == round(math.hypot(8.0, 0.1) * 100)
    assert s.forward.distance_m == pytest.approx(math.hypot(8.0, 0.1), abs=0.01)  # DISTANCE_SENSOR too
    assert run([far_in_band, pole_top], config=sectors_optional_rules_off(sigma_k=0.0)).distances_cm[0] == 2500  # off
    # a nearer in-band claim stands
    s2 = run([[6.0, 0.0, 0.0], pole_top], config=cfg)
    assert s2.distances_cm[0] == 600 and not s2.inferred[0]
    # clear becomes an obstacle at the cap; unknown stays unknown
    clear = [[60.0, b, 0.0] for b in (-1.0, 0.0, 1.0)]
    assert run(clear, config=cfg).state[0] == SectorState.CLEAR
    s3 = run(clear + [pole_top], config=cfg)
    assert s3.state[0] == SectorState.OBSTACLE and s3.distances_cm[0] == round(math.hypot(8.0, 0.1) * 100)
    assert np.all(run([pole_top], config=cfg).distances_cm == UNKNOWN_CM)
    # too far above (4.5 m: 3 m past the edge), below the band, or not converged: no cap
    assert run([far_in_band, [8.0, 0.1, -4.5]], config=cfg).distances_cm[0] == 2500
    assert run([far_in_band, [8.0, 0.1, 3.0]], config=cfg).distances_cm[0] == 2500
    assert run([far_in_band, pole_top], converged=[True, False], config=cfg).distances_cm[0] == 2500
    with pytest.raises(ConfigError):
        SectorConfig(cap_above_m=-1.0)


def test_a_4m_cap_covers_a_remembered_mast_whose_band_points_fell_in_the_next_sector():
    """quad_approach, the mast beside the path out of view (docs/BENCHMARKS.md, "The cap from above the band at
    4 m"): its remembered in-band points all lie in the 30° sector, the 35° sector holds only a remembered point
    on the building behind and the mast's point 2.8 m above the band's edge.  A 4 m cap reports the mast there;
    the 2.5 m cap alone claims the building, 23 m too far (4 m was measured and not shipped).  As shipped, rule 10's
    far part (``corridor_far_ratio``) brings that claim in to the mast's sector's value instead ("No far claim beside a
    near remembered obstacle")."""
    def at(d, bearing_deg, z):
        b = math.radians(bearing_deg)
        return [d * math.cos(b), d * math.sin(b), z]

    mast_band = [at(5.8, 31.0, 0.4), at(5.8, 31.9, -0.3), at(5.8, 32.3, 1.0)]
    mast_top = at(5.8, 35.2, -4.3)  # FRD: 4.3 m above the vehicle, 2.8 m above the band's upper edge
    building = at(28.7, 35.0, 0.0)
    mem = np.array(mast_band + [mast_top, building])
    kw = dict(remembered_p_body=mem, remembered_sigma=np.full(len(mem), 0.1), remembered_tangential_sigma=np.full(len(mem), 0.01),
              roll_pitch_rad=(0.0, 0.0), ground_height_m=-10.0)  # 10 m up
    none = np.zeros((0, 3))
    assert CFG.cap_above_m == 2.5
    no_far = dataclasses.replace(CFG, corridor_far_ratio=0.0)
    cap4 = run(none, config=dataclasses.replace(no_far, cap_above_m=4.0), **kw)
    cap25 = run(none, config=no_far, **kw)
    assert not cap4.in_view[7] and cap4.remembered_points[6] >= 3
    assert cap25.range_m[7] == pytest.approx(28.7 - 2 * 0.1, abs=0.1)  # the building behind the mast
    assert cap4.state[7] == SectorState.OBSTACLE and cap4.inferred[7]
    assert cap4.range_m[7] == pytest.approx(5.8 - 2 * 0.1, abs=0.1)  # the mast
    assert cap4.range_m[6] == pytest.approx(cap25.range_m[6])  # its own sector as before
    shipped = run(none, config=CFG, **kw)
    assert CFG.corridor_far_ratio == 2.0 and shipped.inferred[7]
    assert shipped.range_m[7] == pytest.approx(shipped.range_m[6]) == pytest.approx(cap25.range_m[6])  # the mast's sector's value


def test_an_unconverged_point_just_outside_the_band_vetoes_clear():
    """A thin pole 30 m ahead between far points of a hall (the closed-loop pole take-off, docs/BENCHMARKS.md,
    "Clear in front of a thin pole"): its only tracked corner lies 1 m below the band and has not converged.
    With ``unconverged_veto_margin_m`` it forbids "clear" in its sector; beyond the margin, converged, or
    conservatively beyond max_distance it does not; it never creates an obstacle."""
    cfg = sectors_optional_rules_off(clear_line_of_sight=False, clear_edge_margin_deg=0.0, unconverged_veto_margin_m=0.0,
                                     converged_veto_margin_m=0.0)
    assert CFG.unconverged_veto_margin_m == 2.5  # shipped
    hall = wall(80.0, [-1.5, -0.5, 0.8, 1.7])  # in the band (z = 0), far beyond 40 m
    pole = np.array([[30.0, 0.3, 2.5]])  # FRD: 2.5 m below the vehicle, 1 m below the ±1.5 m band
    assert run(hall, sigma=1.0, config=cfg).state[0] == SectorState.CLEAR
    assert run(np.vstack([hall, pole]), sigma=[1.0] * 4 + [8.0], converged=[True] * 4 + [False], config=cfg).state[0] \
        == SectorState.CLEAR  # no margin: the band alone, as before
    veto = dataclasses.replace(cfg, unconverged_veto_margin_m=2.5)
    s = run(np.vstack([hall, pole]), sigma=[1.0] * 4 + [8.0], converged=[True] * 4 + [False], config=veto)
    assert s.state[0] == SectorState.UNKNOWN and not np.any(s.state == SectorState.OBSTACLE)
    above = pole * [1, 1, -1]  # 1 m above the band: the same
    assert run(np.vstack([hall, above]), sigma=[1.0] * 4 + [8.0], converged=[True] * 4 + [False], config=veto).state[0] \
        == SectorState.UNKNOWN
    low = np.array([[30.0, 0.3, 4.5]])  # 3 m below the band: beyond the margin
    assert run(np.vstack([hall, low]), sigma=[1.0] * 4 + [8.0], converged=[True] * 4 + [False], config=veto).state[0] \
        == SectorState.CLEAR
    far = np.array([[60.0, 0.3, 2.5]])  # 60 − 2·8 = 44 m conservatively: cannot lie within max_distance
    assert run(np.vstack([hall, far]), sigma=[1.0] * 4 + [8.0], converged=[True] * 4 + [False], config=veto).state[0] \
        == SectorState.CLEAR
    conv = run(np.vstack([hall, pole]), sigma=[1.0] * 4 + [0.5], converged=True, config=veto)  # converged: not this veto
    assert conv.state[0] == SectorState.CLEAR  # (converged_veto_margin_m, off here, and the cap and vertical rules read it)
    with pytest.raises(ConfigError, match="unconverged_veto_margin_m"):
        dataclasses.replace(CFG, unconverged_veto_margin_m=-1.0)


def test_a_converged_point_just_outside_the_band_vetoes_clear():
    """The closed-loop pole approach (docs/BENCHMARKS.md, "A ranged point beside the band"): the pole's in-band
    corners ride its silhouette and are ranged at the hall's depth, so they count as evidence of "clear"; its own
    corners just below and above the band are ranged right, at 30 m.  With ``converged_veto_margin_m`` such a point
    forbids "clear"; beyond the margin, in the band (an obstacle), or conservatively beyond max_distance it does not;
    it never creates or moves an obstacle.  Above the band within ``cap_above_m`` the cap (rule 8) makes the point an
    obstacle instead, which the veto must not pre-empt."""
    cfg = sectors_optional_rules_off(clear_line_of_sight=False, clear_edge_margin_deg=0.0, unconverged_veto_margin_m=0.0,
                                     converged_veto_margin_m=0.0, sigma_k_taper_to_m=0.0)
    assert CFG.converged_veto_margin_m == 2.5  # shipped
    hall = wall(80.0, [-1.5, -0.5, 0.8, 1.7])  # in the band (z = 0), far beyond 40 m
    pole = np.array([[30.0, 0.3, 2.8]])  # FRD: 2.8 m below the vehicle, 1.3 m below the ±1.5 m band, converged
    both = dict(sigma=[1.0] * 4 + [1.0], converged=True)
    assert run(np.vstack([hall, pole]), config=cfg, **both).state[0] == SectorState.CLEAR  # off: as before
    veto = dataclasses.replace(cfg, converged_veto_margin_m=2.5)
    s = run(np.vstack([hall, pole]), config=veto, **both)
    assert s.state[0] == SectorState.UNKNOWN and not np.any(s.state == SectorState.OBSTACLE)
    assert run(np.vstack([hall, pole * [1, 1, -1]]), config=veto, **both).state[0] == SectorState.UNKNOWN  # above
    low = np.array([[30.0, 0.3, 4.5]])  # 3 m below the band: beyond the margin
    assert run(np.vstack([hall, low]), config=veto, **both).state[0] == SectorState.CLEAR
    far = np.array([[44.0, 0.3, 2.8]])  # 44 − 2·1 = 42 m conservatively: not within max_distance
    assert run(np.vstack([hall, far]), config=veto, **both).state[0] == SectorState.CLEAR
    unconv = run(np.vstack([hall, pole]), sigma=[1.0] * 4 + [8.0], converged=[True] * 4 + [False], config=veto)
    assert unconv.state[0] == SectorState.CLEAR  # unconverged: the other margin's (off here)
    ranged = np.array([[30.0, 0.3, 0.5]])  # in the band: an obstacle at 30 − 2 = 28 m, with or without the margin
    a, v = run(np.vstack([hall, ranged]), config=cfg, **both), run(np.vstack([hall, ranged]), config=veto, **both)
    assert a.state[0] == v.state[0] == SectorState.OBSTACLE and a.distances_cm[0] == v.distances_cm[0]
    capped = dataclasses.replace(veto, cap_above_m=2.5)  # above the band within the cap: rule 8's, an obstacle at it
    s = run(np.vstack([hall, pole * [1, 1, -1]]), config=capped, **both)
    assert s.state[0] == SectorState.OBSTACLE and s.inferred[0] and s.range_m[0] == pytest.approx(math.hypot(30.0, 0.3) - 2.0, abs=0.05)
    assert run(np.vstack([hall, pole]), config=capped, **both).state[0] == SectorState.UNKNOWN  # below: the veto's
    with pytest.raises(ConfigError, match="converged_veto_margin_m"):
        dataclasses.replace(CFG, converged_veto_margin_m=-0.5)


@pytest.mark.parametrize("margin", ["unconverged_veto_margin_m", "converged_veto_margin_m"])
def test_veto_margin_only_ever_removes_clear_seeded(margin):
    """Seeded Monte Carlo: either veto margin only takes "clear" away.  A changed sector was clear and is now
    unknown, or it is now an obstacle inferred between two consistent obstacle sectors (a sector no longer
    claimed clear is a gap the inference may fill: the corridor rule, applied after the inference, had turned
    such a clear sector unknown before); no sector becomes clear and no obstacle sector changes."""
    base = sectors_optional_rules_off(unconverged_veto_margin_m=0.0, converged_veto_margin_m=0.0)
    on = dataclasses.replace(base, **{margin: 2.5})
    changed_any = 0
    rng = np.random.default_rng(17)
    for pts, sig, conv in random_scenes(17, max_height=6.0):
        # and a far background in the band in every scene (three or more points per sector: "clear" to remove)
        b = rng.uniform(-0.5, 0.5, 60)
        far = np.stack([70.0 * np.cos(b), 70.0 * np.sin(b), rng.uniform(-1.0, 1.0, 60)], 1)
        pts, sig, conv = np.vstack([pts, far]), np.concatenate([sig, np.full(60, 1.0)]), np.concatenate([conv, np.ones(60, bool)])
        a = run(pts, sigma=sig, converged=conv, config=base)
        v = run(pts, sigma=sig, converged=conv, config=on)
        changed = v.distances_cm != a.distances_cm
        assert not np.any(v.state[changed] == SectorState.CLEAR) and not np.any(a.state[changed] == SectorState.OBSTACLE)
        assert np.all((v.state[changed] == SectorState.UNKNOWN) | v.inferred[changed])
        assert np.all((a.state[changed] == SectorState.CLEAR) | v.inferred[changed])
        changed_any += int(np.sum(changed & (a.state == SectorState.CLEAR)))
    assert changed_any > 0  # the scenes exercise it


def test_cap_above_only_ever_lowers_a_claim_seeded():
    """Seeded Monte Carlo: with ``cap_above_m`` on, an unknown sector stays unknown, nothing becomes clear,
    an obstacle's range never grows, and every changed sector is an inferred obstacle."""
    on = sectors_optional_rules_off(cap_above_m=2.5)
    off = sectors_optional_rules_off()
    for pts, sig, conv in random_scenes(12, max_height=6.0):
        a = run(pts, sigma=sig, converged=conv, config=off)
        v = run(pts, sigma=sig, converged=conv, config=on)
        assert np.all(v.state[a.state == SectorState.UNKNOWN] == SectorState.UNKNOWN)
        assert not np.any((v.state == SectorState.CLEAR) & (a.state != SectorState.CLEAR))
        was_obs = a.state == SectorState.OBSTACLE
        assert np.all(v.state[was_obs] == SectorState.OBSTACLE)
        assert np.all(v.distances_cm[was_obs] <= a.distances_cm[was_obs])
        changed = v.distances_cm != a.distances_cm
        assert np.all(v.state[changed] == SectorState.OBSTACLE) and np.all(v.inferred[changed])


def test_one_sided_vertical_structure_claims_a_pole_standing_on_the_ground():
    """infer_vertical_one_side: with the pole's foot on the ground (no evidence), two converged points
    above the band at consistent ranges, spanning ``infer_vertical_min_extent_m`` of height with the
    lower within ``infer_vertical_reach_m`` of the band's edge, claim the nearer; one point, a short
    span, a structure high above the band or disagreeing ranges claim nothing."""
    cfg = sectors_optional_rules_off(infer_vertical=True, infer_vertical_window_m=5.0, infer_vertical_one_side=True,
                                     infer_vertical_min_extent_m=0.5, infer_vertical_reach_m=2.5, sigma_k=0.0)
    top = [[10.2, 0.0, -3.8], [10.0, 0.1, -3.0]]  # FRD: 3.8 and 3.0 m above the vehicle (band edge 1.5 m)
    s = run(top, config=cfg, ground_height_m=-5.0)
    assert s.state[0] == SectorState.OBSTACLE and s.inferred[0]
    assert s.distances_cm[0] == round(math.hypot(10.0, 0.1) * 100)
    assert np.all(s.state[1:] == SectorState.UNKNOWN)
    two_sided_only = sectors_optional_rules_off(infer_vertical=True, infer_vertical_window_m=5.0, sigma_k=0.0)
    assert np.all(run(top, config=two_sided_only, ground_height_m=-5.0).distances_cm == UNKNOWN_CM)
    assert np.all(run(top[:1], config=cfg).distances_cm == UNKNOWN_CM)  # one point
    assert np.all(run([[10.2, 0.0, -3.2], [10.0, 0.1, -3.0]], config=cfg).distances_cm == UNKNOWN_CM)  # 0.2 m span
    assert np.all(run([[10.2, 0.0, -5.5], [10.0, 0.1, -4.5]], config=cfg).distances_cm == UNKNOWN_CM)  # 3 m over the edge
    assert np.all(run([[14.0, 0.0, -3.8], [10.0, 0.1, -3.0]], config=cfg).distances_cm == UNKNOWN_CM)  # ranges disagree
    assert np.all(run([[10.2, 0.0, 3.8], [10.0, 0.1, 3.0]], config=cfg).distances_cm == UNKNOWN_CM)  # below: not this rule


def test_one_sided_vertical_structure_only_ever_adds_obstacles_seeded():
    """Seeded Monte Carlo as for the two-sided rule: nothing becomes clear or unknown, no claim grows."""
    on = sectors_optional_rules_off(infer_vertical=True, infer_vertical_window_m=5.0, infer_vertical_one_side=True,
                                    infer_vertical_reach_m=2.5)
    off = sectors_optional_rules_off()
    for pts, sig, conv in random_scenes(13, max_height=8.0):
        a = run(pts, sigma=sig, converged=conv, config=off, ground_height_m=-5.0)
        v = run(pts, sigma=sig, converged=conv, config=on, ground_height_m=-5.0)
        was_obs = a.state == SectorState.OBSTACLE
        assert np.all(v.state[was_obs] == SectorState.OBSTACLE)
        assert np.all(v.distances_cm[was_obs] <= a.distances_cm[was_obs])
        assert not np.any((v.state == SectorState.CLEAR) & (a.state != SectorState.CLEAR))
        changed = v.state != a.state
        assert np.all(v.state[changed] == SectorState.OBSTACLE) and np.all(v.inferred[changed])


def test_forward_reading_of_an_inferred_sector_carries_that_sector_sigma():
    """A forward sector filled by inference has no point of its own: DISTANCE_SENSOR's σ is the sector's
    (the larger of its two sides), never that of whatever point happens to be last in the array."""
    cfg = SectorConfig(infer_max_gap_sectors=1, sigma_k=0.0)
    b = np.radians([-5.0, 5.0, 30.0])
    pts = np.stack([[10.0, 10.0, 30.0] * np.cos(b), [10.0, 10.0, 30.0] * np.sin(b), np.zeros(3)], 1)
    s = run(pts, sigma=[0.2, 0.3, 3.0], config=cfg)
    assert s.inferred[0] and s.state[0] == SectorState.OBSTACLE
    assert s.forward.sigma_m == pytest.approx(0.3)
    assert math.isnan(s.forward.estimate_m)


def test_the_cap_gate_keeps_a_walls_fused_range_and_still_caps_a_pole():
    """``cap_gate_k`` (docs/derivations/sectors.md, rule 8): a wall at 20 m ranged in the band by ten points and
    just above it by one point of the same wall.  Without the gate the single nearest conservative value above the
    band replaces the sector's fused one (an order statistic: short of the wall by its own 2σ); with it the fused
    range stays.  A pole at 6 m ranged only above the band, before a background the band ranged at 26 m, is a
    different, nearer surface: capped either way."""
    rng = np.random.default_rng(5)
    wall_band = [[20.0 + e, 0.05 * k - 0.25, 0.3] for k, e in enumerate(rng.normal(0.0, 0.4, 10))]
    above = [[19.6, 0.1, -2.0]]  # 2.0 m above the vehicle, 0.5 m above the band's edge: the same wall
    sig = [0.4] * 10 + [0.4]
    c0 = dataclasses.replace(CFG, cap_gate_k=0.0, infer_vertical=False)
    c2 = dataclasses.replace(CFG, cap_gate_k=2.0, infer_vertical=False)
    no_cap = dataclasses.replace(CFG, cap_above_m=0.0, infer_vertical=False)
    fused = run(wall_band + above, sigma=sig, config=no_cap).range_m[0]
    capped = run(wall_band + above, sigma=sig, config=c0).range_m[0]
    gated = run(wall_band + above, sigma=sig, config=c2).range_m[0]
    assert capped == pytest.approx(19.6 - 2 * 0.4, abs=0.05) and capped < fused - 0.3
    assert gated == fused
    pole = [[26.0, 0.0, 0.0], [26.3, 0.1, 0.2], [6.0, 0.05, -2.0]]
    for c in (c0, c2):
        s = run(pole, sigma=[2.0, 2.0, 0.2], config=c)
        assert s.range_m[0] == pytest.approx(6.0 - 2 * 0.2, abs=0.05) and s.inferred_vertical[0]


@pytest.mark.parametrize("kernels", [False, True], ids=["reference", "kernels"])
def test_an_unconverged_point_bounds_a_far_claim_from_above(kernels, monkeypatch):
    """unconverged_cap_k (rule 9): a live in-band point not yet converged, at r ± σ, bounds its obstacle sector's
    claim at r / (1 − k σ / r) (k σ in inverse depth).  A take-off track riding a pole's edge, converged at 24 m,
    and the pole's own point at 6.3 ± 1.7 m ahead: the sector says 6.3 / (1 − 2·1.7/6.3) = 13.7 m, marked inferred,
    DISTANCE_SENSOR too.  Nearer claims stand; unknown and clear sectors stay as they are; a point whose bound is
    infinite (k σ ≥ r), a remembered or an invalid one bounds nothing; off (0), nothing changes."""
    from companion.core import jit
    monkeypatch.setattr(jit, "ENABLED", kernels)
    cfg = sectors_optional_rules_off(unconverged_cap_k=2.0, sigma_k=0.0)
    far, pole = [24.0, 0.0, 0.0], [6.3, 0.1, 0.2]
    r = math.hypot(*pole)
    bound = math.hypot(6.3, 0.1) / (1 - 2 * 1.7 / r)
    s = run([far, pole], sigma=[0.8, 1.7], converged=[True, False], config=cfg)
    assert s.state[0] == SectorState.OBSTACLE and s.inferred[0]
    assert s.distances_cm[0] == round(bound * 100) and s.range_m[0] == pytest.approx(bound, abs=1e-9)
    assert s.forward.distance_m == pytest.approx(bound) and math.isnan(s.forward.estimate_m)
    off = run([far, pole], sigma=[0.8, 1.7], converged=[True, False], config=sectors_optional_rules_off(sigma_k=0.0))
    assert off.distances_cm[0] == 2400 and not off.inferred[0]
    assert run([[12.0, 0.0, 0.0], pole], sigma=[0.8, 1.7], converged=[True, False], config=cfg).distances_cm[0] == 1200
    assert np.all(run([pole], sigma=1.7, converged=False, config=cfg).distances_cm == UNKNOWN_CM)  # unknown stays
    clear = [[60.0, b, 0.0] for b in (-1.0, 0.0, 1.0)]
    no_veto = dataclasses.replace(cfg, unconverged_veto_clear=False)
    c = run(clear + [pole], sigma=[0.5, 0.5, 0.5, 1.7], converged=[True, True, True, False], config=no_veto)
    assert c.state[0] == SectorState.CLEAR  # clear stays clear (with the veto on it would not have been clear)
    assert run([far, pole], sigma=[0.8, 3.2], converged=[True, False], config=cfg).distances_cm[0] == 2400  # 2σ ≥ r
    assert run([far, pole], sigma=[0.8, 1.7], converged=[True, False], valid=[True, False], config=cfg).distances_cm[0] == 2400
    with pytest.raises(ConfigError, match="unconverged_cap_k"):
        SectorConfig(unconverged_cap_k=-1.0)


def test_the_unconverged_cap_only_ever_lowers_an_obstacle_claim_seeded():
    """Seeded Monte Carlo: with ``unconverged_cap_k`` on, no sector changes state, an obstacle's range never grows,
    and every changed sector is an inferred obstacle."""
    on = sectors_optional_rules_off(unconverged_cap_k=2.0)
    off = sectors_optional_rules_off()
    n_changed = 0
    for pts, sig, conv in random_scenes(13, max_height=2.0):
        a = run(pts, sigma=sig, converged=conv, config=off)
        v = run(pts, sigma=sig, converged=conv, config=on)
        np.testing.assert_array_equal(v.state, a.state)
        was_obs = a.state == SectorState.OBSTACLE
        assert np.all(v.distances_cm[was_obs] <= a.distances_cm[was_obs])
        changed = v.distances_cm != a.distances_cm
        assert np.all(v.inferred[changed])
        n_changed += int(np.count_nonzero(changed))
    assert n_changed > 20


# ---------------------------------------------------------------------- the margin's taper --------
TAPER = dataclasses.replace(NEAREST_POINT, sigma_k_far=1.0, sigma_k_taper_from_m=10.0, sigma_k_taper_to_m=20.0)


def test_the_margin_tapers_from_sigma_k_near_to_sigma_k_far_far_away():
    """Single points straight ahead at 6, 15 and 30 m (σ/d = 0.1): near the full k = 2 margin, d − 2σ;
    half-way through the taper k = 1.5; beyond it k = 1.  Off (the shipped default), k = 2 everywhere."""
    for d, k in ((6.0, 2.0), (15.0, 1.5), (30.0, 1.0)):
        s = run([[d, 0.0, 0.0]], sigma=0.1 * d, config=TAPER)
        assert s.state[0] == SectorState.OBSTACLE
        assert s.range_m[0] == pytest.approx(d - k * 0.1 * d, abs=1e-9)
        assert s.distances_cm[0] == round(100 * (d - k * 0.1 * d))
        assert s.forward.estimate_m == pytest.approx(d) and s.forward.sigma_m == pytest.approx(0.1 * d)
        off = run([[d, 0.0, 0.0]], sigma=0.1 * d, config=NEAREST_POINT)
        assert off.range_m[0] == pytest.approx(0.8 * d, abs=1e-9)
    # a fused surface narrows by k at its fused estimate: a wall 30 m ahead, 41 points, σ 3 m each
    w = wall(30.0, range(-2, 3))
    fused = run(w, sigma=3.0, config=dataclasses.replace(TAPER, fuse_gate_k=2.0))
    plain = run(w, sigma=3.0, config=dataclasses.replace(CFG, fuse_gate_k=2.0))
    assert fused.state[0] == plain.state[0] == SectorState.OBSTACLE
    est, sig = fused.forward.estimate_m, fused.forward.sigma_m
    assert plain.forward.estimate_m == pytest.approx(est) and plain.forward.sigma_m == pytest.approx(sig)
    assert fused.range_m[0] == pytest.approx(est - 1.0 * sig) and plain.range_m[0] == pytest.approx(est - 2.0 * sig)


def test_a_tapered_margin_changes_no_state_and_moves_claims_only_farther():
    """Monte Carlo over random scenes (points 1–60 m, σ up to 3 m), every rule as shipped: every rule
    decides with the full margin, so the taper changes no sector's state, σ or forward estimate (the
    point or surface behind each claim is the same); an obstacle claim moves only farther, by at
    most (sigma_k − sigma_k_far)·σ, and only where its estimate lies beyond the taper's start."""
    tapered = dataclasses.replace(CFG, sigma_k_far=1.0, sigma_k_taper_from_m=10.0, sigma_k_taper_to_m=20.0)
    moved_total = 0
    for pts, sig, conv in random_scenes(3, 150):
        a = run(pts, sigma=sig, converged=conv, config=CFG)
        b = run(pts, sigma=sig, converged=conv, config=tapered)
        assert np.array_equal(a.state, b.state) and np.array_equal(a.inferred, b.inferred)
        assert np.array_equal(a.sigma_m, b.sigma_m, equal_nan=True)
        assert a.forward.state == b.forward.state and a.forward.sigma_m == b.forward.sigma_m or (
            math.isnan(a.forward.sigma_m) and math.isnan(b.forward.sigma_m))
        obs = a.state == SectorState.OBSTACLE
        assert np.all(b.distances_cm[obs] >= a.distances_cm[obs])
        assert np.all(b.range_m[obs] <= a.range_m[obs] + 1.0 * b.sigma_m[obs] + 0.01)
        moved = obs & (b.distances_cm != a.distances_cm)
        moved_total += int(np.sum(moved))
        assert np.all(a.range_m[moved] + 2.0 * a.sigma_m[moved] > tapered.sigma_k_taper_from_m - 0.01)
    assert moved_total > 50  # the scenes exercise the taper


def test_a_margin_below_sigma_k_far_is_never_widened_by_the_taper():
    """sigma_k below sigma_k_far (a user's overlay asks for a thin margin): k stays sigma_k at every range."""
    for k in (0.0, 0.5):
        cfg = SectorConfig(sigma_k=k, fuse_gate_k=0.0)  # the shipped taper: sigma_k_far 1 from 10 to 20 m
        assert cfg.sigma_k_far == 1.0 and cfg.sigma_k_taper_to_m == 20.0
        for d in (6.0, 15.0, 30.0):
            s = run([[d, 0.0, 0.0]], sigma=0.1 * d, config=cfg)
            assert s.range_m[0] == pytest.approx(d - k * 0.1 * d, abs=1e-9)


@pytest.mark.parametrize("kw, msg", [
    (dict(sigma_k_taper_from_m=20.0, sigma_k_taper_to_m=10.0), "sigma_k_taper_to_m must exceed"),
    (dict(sigma_k_far=-1.0), "sigma_k_far"),
    (dict(sigma_k_taper_to_m=math.nan), "sigma_k_taper_to_m"),
])
def test_a_bad_taper_is_refused(kw, msg):
    with pytest.raises(ConfigError, match=msg):
        SectorConfig(**kw)
