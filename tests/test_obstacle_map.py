"""Local obstacle map (DESIGN §7): retention, re-observation, drift, sectors over 360°, inference."""

import dataclasses
import math

import numpy as np
import pytest

from companion.core.frames import euler_zyx_to_R
from companion.core.obstacle_map import (
    REJECT_NOT_FINITE,
    REJECT_NOT_PD,
    MapConfig,
    ObstacleMap,
    landmark_covariance,
    usage_score,
    world_to_body,
)
from companion.core.sectors import SECTOR_COUNT, UNKNOWN_CM, SectorConfig, SectorState, compute_sectors
from companion.errors import ConfigError
from conftest import sectors_optional_rules_off

HFOV = math.radians(60.0)
# camera looking along body x (forward): R_cam_body maps body (x fwd, y right, z down) to cam (x right, y down, z fwd)
R_CAM_BODY = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
FX = FY = 277.1
CX, CY, W, H = 159.5, 119.5, 320, 240


def cov(n, s=0.2):
    return np.broadcast_to(np.eye(3) * s * s, (n, 3, 3)).copy()


def camera_pose(yaw=0.0, p=(0.0, 0.0, -10.0)):
    R_wb = euler_zyx_to_R(0.0, 0.0, yaw)
    return R_wb, R_wb @ R_CAM_BODY.T, np.asarray(p, float)


def test_usage_score_is_seed_003s():
    assert usage_score(0, 0) == 0.0
    assert usage_score(3, 2) == pytest.approx((3 - 1) / 4)
    assert usage_score(0, 2) == pytest.approx(-1.0)


def test_config_validation_names_the_key():
    with pytest.raises(ConfigError, match="max_landmarks"):
        MapConfig(max_landmarks=0)
    with pytest.raises(ConfigError, match="radius_m"):
        MapConfig(radius_m=-1.0)
    with pytest.raises(ConfigError, match="min_score"):
        MapConfig(min_score=1.5)


def test_observe_upserts_and_live_points_are_not_remembered():
    m = ObstacleMap(MapConfig(min_support=1))
    m.observe(1.0, [1, 2], [[10, 0, -10], [12, 1, -10]], cov(2))
    assert len(m) == 2 and len(m.remembered(1.0, np.zeros(3))) == 0  # both live
    m.observe(1.1, [2], [[12.5, 1, -10]], cov(1), live_keys=[2])  # track 1 ended
    rem = m.remembered(1.1, np.array([0.0, 0.0, -10.0]))
    assert rem.keys.tolist() == [1]
    np.testing.assert_allclose(m.p[m.keys == 2][0], [12.5, 1, -10])  # refreshed


def test_bad_landmarks_are_rejected_with_a_named_reason():
    m = ObstacleMap()
    P = cov(4)
    P[1] = np.diag([1.0, -0.1, 1.0])  # not positive definite
    P[2] = np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # not symmetric
    p = np.array([[10, 0, 0], [11, 0, 0], [12, 0, 0], [np.nan, 0, 0]], float)
    rej = m.observe(0.0, [1, 2, 3, 4], p, P)
    assert rej == {REJECT_NOT_FINITE: 1, REJECT_NOT_PD: 2}
    assert m.keys.tolist() == [1] and m.rejected[REJECT_NOT_PD] == 2


def test_uncertainty_grows_with_time_since_observed():
    cfg = MapConfig(position_drift_mps=0.1, position_drift_max_m=1.0, heading_drift_deg_s=0.1, min_support=1)
    m = ObstacleMap(cfg)
    m.observe(0.0, [1], [[20.0, 0.0, -10.0]], cov(1, 0.3), live_keys=[])
    pv = np.array([0.0, 0.0, -10.0])
    r0, r5, r30 = (m.remembered(t, pv) for t in (0.0, 5.0, 30.0))
    assert r0.range_sigma[0] == pytest.approx(0.3)
    assert r5.range_sigma[0] == pytest.approx(math.hypot(0.3, 0.5))
    assert r30.range_sigma[0] == pytest.approx(math.hypot(0.3, 1.0))  # drift bounded
    # heading drift: 0.1°/s for 5 s at 20 m across the line of sight
    assert r5.tangential_sigma[0] == pytest.approx(math.sqrt(0.09 + 0.25 + (20 * math.radians(0.5)) ** 2))


def test_retention_by_age_radius_and_cap():
    m = ObstacleMap(MapConfig(max_age_s=10.0, radius_m=50.0, max_landmarks=3))
    m.observe(0.0, [1], [[10, 0, 0]], cov(1), live_keys=[])
    m.observe(8.0, [2, 3, 4], [[70, 0, 0], [20, 0, 0], [30, 0, 0]], cov(3), live_keys=[])
    out = m.prune(10.5, np.zeros(3))
    assert out["age"] == 1 and out["radius"] == 1 and sorted(m.keys.tolist()) == [3, 4]
    # cap: 5 more points, the lowest score goes first, then the longest unseen
    m.o[m.keys == 3] = 2  # re-observed twice: high score, survives
    m.observe(9.0, [5, 6], [[5, 5, 0], [6, 6, 0]], cov(2), live_keys=[])
    m.observe(10.0, [7], [[7, 7, 0]], cov(1), live_keys=[7])
    out = m.prune(10.5, np.zeros(3))
    assert out["cap"] == 2 and len(m) == 3
    assert sorted(m.keys.tolist()) == [3, 6, 7]  # 4 (t 8) and 5 (t 9) were the oldest at score 0


def test_memory_stays_at_the_cap_on_a_long_stream():
    rng = np.random.default_rng(3)
    m = ObstacleMap(MapConfig(max_landmarks=200))
    for k in range(300):  # 300 frames of 50 new converged landmarks each, the old tracks ending
        keys = np.arange(50) + 50 * k
        p = np.column_stack([rng.uniform(5, 30, 50), rng.uniform(-10, 10, 50), rng.uniform(-12, -8, 50)])
        m.observe(k / 30, keys, p, cov(50), live_keys=keys)
        m.prune(k / 30, np.array([0.0, 0.0, -10.0]))
        assert len(m) <= 200
    assert m.P.shape == (200, 3, 3)


def _wall_point_in_view(z=15.0):
    """A remembered point 15 m straight ahead of a camera at the origin looking north."""
    m = ObstacleMap(MapConfig(min_score=-0.75))
    m.observe(0.0, [1], [[z, 0.0, -10.0]], cov(1, 0.3), live_keys=[])
    return m


def test_a_point_predicted_in_view_and_found_again_is_reobserved():
    m = _wall_point_in_view()
    _, R_wc, p_wc = camera_pose()
    vc = m.check_view(2.0, R_wc, p_wc, FX, FY, CX, CY, W, H, np.array([[CX + 2.0, CY]]), np.array([15.3]), np.array([0.4]))
    assert (vc.predicted, vc.found, vc.missed) == (1, 1, 0)
    assert m.o[0] == 1 and m.t_seen[0] == 2.0


def test_a_point_predicted_in_view_and_seen_through_loses_score_and_goes():
    m = _wall_point_in_view()
    _, R_wc, p_wc = camera_pose()
    for k in range(2):  # a live converged point at 30 m where the remembered one should be at 15 m
        vc = m.check_view(1.0 + k, R_wc, p_wc, FX, FY, CX, CY, W, H, np.array([[CX, CY + 1]]), np.array([30.0]), np.array([1.0]))
        assert vc.missed == 1
    assert m.u[0] == 2 and m.score[0] == pytest.approx(-1.0)
    assert m.prune(3.0, p_wc)["score"] == 1 and len(m) == 0


def test_no_evidence_and_occluders_change_nothing():
    m = _wall_point_in_view()
    _, R_wc, p_wc = camera_pose()
    # a live point far from the predicted pixel, and one nearer (an occluder): neither counts
    vc = m.check_view(1.0, R_wc, p_wc, FX, FY, CX, CY, W, H, np.array([[CX + 40, CY], [CX, CY]]), np.array([30.0, 5.0]),
                      np.array([1.0, 0.2]))
    assert (vc.predicted, vc.found, vc.missed) == (1, 0, 0) and m.u[0] == 0 and m.o[0] == 0
    # out of view (behind the camera): not predicted at all
    _, R_back, _ = camera_pose(math.pi)
    assert m.check_view(1.0, R_back, p_wc, FX, FY, CX, CY, W, H, np.array([[CX, CY]]), np.array([30.0]), np.array([1.0])).predicted == 0


def test_sectors_from_the_map_over_360_after_a_yaw():
    """Points ranged ahead are published beside and behind after the vehicle turns 90° / 180°."""
    m = ObstacleMap(MapConfig(heading_drift_deg_s=0.0, position_drift_mps=0.0))
    p_v = np.array([0.0, 0.0, -10.0])
    # a wall 12 m north of the vehicle, points at bearings −10…10°, seen while facing north
    b = np.radians(np.arange(-10, 11, 2.0))
    pts = np.column_stack([np.full(b.shape, 12.0), 12.0 * np.tan(b), np.full(b.shape, -10.0)])
    m.observe(0.0, np.arange(len(b)), pts, cov(len(b), 0.2), live_keys=[])
    cfg = SectorConfig(sigma_k_taper_to_m=0.0)  # values r − 2σ at any range (the margin's taper off)
    for yaw_deg, expect_sector in ((90.0, 54), (180.0, 36), (-90.0, 18)):
        R_wb = euler_zyx_to_R(0.0, 0.0, math.radians(yaw_deg))
        rem = m.remembered(1.0, p_v)
        s = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, 0.0, cfg, roll_pitch_rad=(0.0, 0.0),
                            remembered_p_body=world_to_body(rem.p_world, R_wb, p_v), remembered_sigma=rem.range_sigma,
                            remembered_tangential_sigma=rem.tangential_sigma)
        assert s.state[expect_sector] == SectorState.OBSTACLE
        assert s.distances_cm[expect_sector] == round((12.0 - 2 * 0.2) * 100)
        assert s.remembered_points[expect_sector] >= 1
        # the wall spans ±10° around the north bearing: at most sectors within ±3 of it hold it
        claimed = np.flatnonzero(s.state == SectorState.OBSTACLE)
        off = (claimed - expect_sector + 36) % 72 - 36
        assert np.all(np.abs(off) <= 3), claimed
        assert not np.any(s.state == SectorState.CLEAR)  # memory never claims clear
        assert not s.in_view[expect_sector] or yaw_deg == 0.0


def test_remembered_point_with_uncertain_bearing_spreads_into_neighbours():
    p = np.array([[10.0, 0.0, 0.0]])
    kw = dict(roll_pitch_rad=(0.0, 0.0), remembered_p_body=p, remembered_sigma=[0.2])
    spread_alone = sectors_optional_rules_off(infer_max_gap_sectors=0, remembered_spread_k=2.0)
    s_sharp = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi, spread_alone,
                              remembered_tangential_sigma=[0.05], **kw)
    s_wide = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi, spread_alone,
                             remembered_tangential_sigma=[0.8], **kw)  # k·σ/r = 9.2° (k = 2)
    assert np.flatnonzero(s_sharp.state == SectorState.OBSTACLE).tolist() == [0]
    assert np.flatnonzero(s_wide.state == SectorState.OBSTACLE).tolist() == [0, 1, 2, 70, 71]


def test_inference_fills_a_consistent_gap_and_is_marked():
    # camera looking backwards (yaw offset π) so every forward sector is outside the view; two remembered
    # points 10 m away at 0° and 10° (sectors 0 and 2), sector 1 has no evidence
    p = np.array([[10.0, 0.0, 0.0], [10.0 * math.cos(math.radians(10)), 10.0 * math.sin(math.radians(10)), 0.0]])
    kw = dict(roll_pitch_rad=(0.0, 0.0), remembered_p_body=p, remembered_sigma=[0.2, 0.2], remembered_tangential_sigma=[0.0, 0.0])
    same_range_alone = sectors_optional_rules_off()  # the narrow-gap rule would fill sector 1 too (1.7 m apart)
    s = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi, same_range_alone, **kw)
    assert s.state[1] == SectorState.OBSTACLE and s.inferred.tolist() == [i == 1 for i in range(SECTOR_COUNT)]
    assert s.distances_cm[1] == min(s.distances_cm[0], s.distances_cm[2]) and s.n_inferred == 1
    assert s.rotated(0.0)[1] == s.distances_cm[1]  # survives the re-binning at sending time
    off = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi, sectors_optional_rules_off(infer_max_gap_sectors=0), **kw)
    assert off.distances_cm[1] == UNKNOWN_CM and not off.inferred.any()
    # inconsistent sides (10 m and 20 m): no inference
    p2 = p.copy()
    p2[1] *= 2.0
    s2 = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi, same_range_alone, roll_pitch_rad=(0.0, 0.0),
                         remembered_p_body=p2, remembered_sigma=[0.2, 0.2], remembered_tangential_sigma=[0.0, 0.0])
    assert s2.distances_cm[1] == UNKNOWN_CM


def _check_inference_only_adds_obstacles(cfg_on, cfg_off, seed, max_remembered, max_remembered_range_m) -> int:
    """Seeded Monte Carlo over random scenes (live points, remembered points up to the given count and
    range): with ``cfg_on`` every sector that was clear or an obstacle under ``cfg_off`` stays exactly
    so, the only changes are unknown → obstacle, and they are all marked.  Returns how many changed."""
    rng = np.random.default_rng(seed)
    changed = 0
    for _ in range(300):
        n = int(rng.integers(0, 40))
        b = rng.uniform(-math.pi, math.pi, n)
        r = rng.uniform(2.0, 80.0, n)
        p = np.column_stack([r * np.cos(b), r * np.sin(b), rng.normal(0, 1.0, n)])
        sig = rng.uniform(0.05, 2.0, n)
        conv = rng.random(n) < 0.8
        m = int(rng.integers(0, max_remembered))
        bm = rng.uniform(-math.pi, math.pi, m)
        rm = rng.uniform(2.0, max_remembered_range_m, m)
        pm = np.column_stack([rm * np.cos(bm), rm * np.sin(bm), np.zeros(m)])
        kw = dict(roll_pitch_rad=(0.0, 0.0), remembered_p_body=pm, remembered_sigma=np.full(m, 0.3),
                  remembered_tangential_sigma=rng.uniform(0, 1, m))
        a = compute_sectors(p, sig, conv, np.ones(n, bool), HFOV, 0.0, cfg_on, **kw)
        o = compute_sectors(p, sig, conv, np.ones(n, bool), HFOV, 0.0, cfg_off, **kw)
        diff = a.distances_cm != o.distances_cm
        assert np.all(o.state[diff] == SectorState.UNKNOWN) and np.all(a.state[diff] == SectorState.OBSTACLE)
        assert np.array_equal(diff, a.inferred)
        assert np.array_equal(a.state == SectorState.CLEAR, o.state == SectorState.CLEAR)
        changed += int(diff.sum())
    return changed


def test_inference_never_produces_clear_and_only_adds_obstacles():
    """The same-range rule only ever turns unknown into obstacle (seeded Monte Carlo)."""
    changed = _check_inference_only_adds_obstacles(
        sectors_optional_rules_off(infer_max_gap_sectors=3, infer_rel_tol=0.5), sectors_optional_rules_off(infer_max_gap_sectors=0),
        11, 10, 40.0)
    assert changed > 0  # the property was exercised


def _wall_points(bearings_deg, lateral_m=5.0):
    """Points of a straight wall parallel to the track, ``lateral_m`` to the right, at these bearings."""
    b = np.radians(np.asarray(bearings_deg, float))
    r = lateral_m / np.sin(b)
    return np.column_stack([r * np.cos(b), r * np.sin(b), np.zeros(len(b))])


def test_narrow_gap_inference_follows_a_wall_beside_the_vehicle_conservatively():
    """A wall 5 m to the right seen (remembered) only at 50° and 70°: the unknown sectors between
    (55°, 60°, 65°) are filled along the straight line between the two points, each no farther than
    the wall really is anywhere in its sector (exact geometry) and within 15 % of it; the ranges on
    the two sides differ by 22 %, so the same-range rule alone leaves the gap unknown."""
    p = _wall_points([50.0, 70.0])
    kw = dict(roll_pitch_rad=(0.0, 0.0), remembered_p_body=p, remembered_sigma=[0.0, 0.0], remembered_tangential_sigma=[0.0, 0.0])
    base = sectors_optional_rules_off(infer_max_gap_sectors=1, sigma_k=0.0)
    off = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi, base, **kw)
    assert np.all(off.distances_cm[11:14] == UNKNOWN_CM)
    on = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi,
                         sectors_optional_rules_off(infer_max_gap_sectors=1, sigma_k=0.0, infer_narrow_gap_m=3.0,
                                                    infer_narrow_max_sectors=4), **kw)
    assert on.inferred.tolist() == [i in (11, 12, 13) for i in range(SECTOR_COUNT)]
    assert np.all(on.state[11:14] == SectorState.OBSTACLE)
    for i in (11, 12, 13):
        edges = np.radians([i * 5.0 - 2.5, i * 5.0 + 2.5])
        nearest_true = float(np.min(5.0 / np.sin(edges)))  # the wall's nearest point within the sector
        assert on.range_m[i] <= nearest_true + 1e-6
        assert on.range_m[i] >= 0.85 * nearest_true
    # the measured sides are untouched, and the result survives the re-binning at sending time
    assert np.array_equal(on.distances_cm[[10, 14]], off.distances_cm[[10, 14]])
    assert np.array_equal(on.rotated(0.0)[11:14], on.distances_cm[11:14])
    # two points farther apart than infer_narrow_gap_m: no fill
    far = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi,
                          sectors_optional_rules_off(sigma_k=0.0, infer_narrow_gap_m=2.0, infer_narrow_max_sectors=4), **kw)
    assert np.hypot(*(p[1, :2] - p[0, :2])) > 2.0 and np.all(far.distances_cm[11:14] == UNKNOWN_CM)
    # a gap wider than infer_narrow_max_sectors: no fill
    narrow = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi,
                             sectors_optional_rules_off(sigma_k=0.0, infer_narrow_gap_m=3.0, infer_narrow_max_sectors=2), **kw)
    assert np.all(narrow.distances_cm[11:14] == UNKNOWN_CM)


def test_narrow_gap_inference_does_not_chain_on_inferred_sectors():
    # points at 0°, 10° (same range: sector 1 inferred by the same-range rule) and 30°: the 15–25° gap is
    # bounded by the inferred sector 1 on no side, by the measured 10° and 30° sides: fills only if
    # those two are close enough, never from sector 1
    p = np.array([[10.0, 0.0, 0.0], [10.0 * math.cos(math.radians(10)), 10.0 * math.sin(math.radians(10)), 0.0],
                  [10.0 * math.cos(math.radians(30)), 10.0 * math.sin(math.radians(30)), 0.0]])
    kw = dict(roll_pitch_rad=(0.0, 0.0), remembered_p_body=p, remembered_sigma=[0.0] * 3, remembered_tangential_sigma=[0.0] * 3)
    s = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi,
                        SectorConfig(sigma_k=0.0, infer_narrow_gap_m=3.0, infer_narrow_max_sectors=4), **kw)
    assert s.inferred[1] and not s.inferred[3:6].any()  # 10°→30° chord is 3.47 m > 3 m
    s2 = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi,
                         SectorConfig(sigma_k=0.0, infer_narrow_gap_m=3.6, infer_narrow_max_sectors=4), **kw)
    assert s2.inferred[3:6].all() and np.all(s2.range_m[3:6] <= 10.0 + 1e-9)


def test_narrow_gap_inference_never_produces_clear_and_only_adds_obstacles():
    """The narrow-gap rule likewise (remembered points within 12 m, where gaps are narrow)."""
    changed = _check_inference_only_adds_obstacles(
        sectors_optional_rules_off(infer_max_gap_sectors=0, infer_narrow_gap_m=3.0, infer_narrow_max_sectors=6),
        sectors_optional_rules_off(infer_max_gap_sectors=0), 12, 12, 12.0)
    assert changed > 0


def test_narrow_gap_config_is_validated():
    with pytest.raises(ConfigError):
        SectorConfig(infer_narrow_gap_m=-1.0)
    with pytest.raises(ConfigError):
        SectorConfig(infer_narrow_max_sectors=13)
    with pytest.raises(ConfigError):
        SectorConfig(infer_narrow_max_sectors=2.0)


def test_landmark_covariance_is_range_along_the_ray_and_bearing_across():
    P = landmark_covariance(np.array([[10.0, 0.0, 0.0]]), np.zeros(3), np.array([0.5]), 0.01)
    np.testing.assert_allclose(P[0], np.diag([0.25, 0.01, 0.01]), atol=1e-12)


def _hover_run(map_enabled: bool, yaw_turn: bool = False):
    """Pipeline on a synthetic approach to 5 m from a wall, then a still hover (optionally turning 90°
    in place): fraction of hover frames whose sectors hold the wall."""
    import dataclasses

    from bench.latency import feed_telemetry
    from bench.map_memory import APPROACH_S, HoverFlight
    from companion.camera_sources import Frame
    from companion.core.camera import CameraConfig
    from companion.io.config_files import CompanionConfig
    from companion.pipeline import Pipeline, PipelineConfig
    from companion.telemetry import TelemetryBuffer

    class StillHover(HoverFlight):
        def position(self, t):
            return super().position(min(t, APPROACH_S))

        def velocity_at(self, t):
            return super().velocity_at(t) if t <= APPROACH_S else np.zeros(3)

        def rpy(self, t):
            if not yaw_turn or t <= APPROACH_S + 1.0:
                return 0.0, 0.0, 0.0
            return 0.0, 0.0, min(t - APPROACH_S - 1.0, 3.0) * math.radians(30.0)  # 90° right at 30°/s

        def rates(self):
            return 0.0, 0.0, 0.0

    cam = CameraConfig.from_fov(320, 240, 60.0)
    base = CompanionConfig()
    cfg = dataclasses.replace(base, camera=cam, map=dataclasses.replace(base.map, enabled=map_enabled),
                              tracks=dataclasses.replace(base.tracks, max_tracks=120),
                              harris=dataclasses.replace(base.harris, max_corners=120))
    flight = StillHover(camera=cam, wall_north_m=20.0, start_ned=(0.0, 0.0, -10.0), velocity_ned=(0.0, 0.0, 0.0),
                        noise_sigma=1.0, seed=2)
    tel = TelemetryBuffer(cfg.telemetry)
    tel.set_clock_offset(0.0)
    pipe = Pipeline(cam, cfg, PipelineConfig(), tel)
    fps, fed, held, n, sectors, looming = 10.0, 0.0, 0, 0, None, 0
    for k in range(int((APPROACH_S + 8.0) * fps)):
        t = k / fps
        feed_telemetry(tel, flight, fed, t + 0.021)
        fed = t + 0.021
        res = pipe.process(Frame(k, t, flight.render(t)), t + 0.021)
        looming += res.n_looming
        if t > APPROACH_S + (5.0 if yaw_turn else 1.0):
            n += 1
            s = res.sectors
            # the wall is north: sector 0 while facing it, sector 54 (−90°) after turning 90° right
            sec = 54 if yaw_turn else 0
            held += bool(res.ok and s is not None and s.state[sec] == SectorState.OBSTACLE
                         and s.distances_cm[sec] <= 500 + 10)  # never farther than the wall (5 m)
            sectors = s
    assert looming > 0  # the pipeline hands the matcher's scales to the estimator (head-on approach)
    return held / n, sectors


def test_hovering_in_front_of_a_wall_keeps_its_range():
    held, s = _hover_run(True)
    assert held >= 0.95, held
    assert not np.any(s.state == SectorState.CLEAR)


def test_turning_in_place_keeps_the_wall_beside_the_vehicle():
    """After a 90° turn in place the wall, out of view on the left, is still published there."""
    held, s = _hover_run(True, yaw_turn=True)
    assert held >= 0.9, held
    assert not s.in_view[54]
    off, _ = _hover_run(False, yaw_turn=True)
    assert off < 0.1  # without the map nothing is published out of view


def test_a_new_landmark_on_a_remembered_point_takes_it_over_fused():
    m = ObstacleMap(MapConfig(gate_k=3.0))
    m.observe(0.0, [1], [[20.0, 0.0, -10.0]], cov(1, 0.4), live_keys=[])
    m.observe(1.0, [7, 8], [[20.3, 0.1, -10.0], [25.0, 3.0, -10.0]], cov(2, 0.3), live_keys=[7, 8])
    assert len(m) == 2 and sorted(m.keys.tolist()) == [7, 8] and m.merged == 1
    row = np.flatnonzero(m.keys == 7)[0]
    assert m.o[row] == 1 and m.t_seen[row] == 1.0 and m.live[row]
    # fused: between the two, nearer the more certain new one; variance below both (the remembered
    # point's variance grown by 1 s of position drift, 0.02 m)
    v_rem = 0.4**2 + (MapConfig().position_drift_mps * 1.0) ** 2
    w = v_rem / (v_rem + 0.3**2)
    np.testing.assert_allclose(m.p[row], np.array([20.0, 0.0, -10.0]) + w * np.array([0.3, 0.1, 0.0]), atol=1e-9)
    assert m.P[row][0, 0] < 0.3**2
    # a live point is never taken over (its own estimate stands)
    m.observe(2.0, [9], [[20.3, 0.1, -10.0]], cov(1, 0.3), live_keys=[7, 8, 9])
    assert len(m) == 3


def _long(axis, s_long, s_short=0.05):
    """A covariance long along one world axis (a range σ along a line of sight), short across."""
    d = np.full(3, s_short**2)
    d[axis] = s_long**2
    return np.diag(d)[None]


def test_a_new_landmark_that_disagrees_with_a_remembered_point_supersedes_it_unfused():
    """Two estimates long along crossing lines of sight that disagree across their narrow axes:
    fused, they land where the axes cross, far from both (a phantom point in the flight band,
    docs/derivations/obstacle_map.md, "Merging").  The new landmark takes the row over with its own
    estimate instead."""
    m = ObstacleMap(MapConfig(gate_k=3.0))
    m.observe(0.0, [1], [[20.0, 0.0, -10.0]], _long(0, 2.0), live_keys=[])  # seen along x
    d = np.array([1.0, 1.0, 0.5])  # within the round gate, 25 σ apart across the narrow z axes
    p_new = np.array([20.0, 0.0, -10.0]) + d
    m.observe(0.1, [2], [p_new], _long(1, 2.0), live_keys=[2])  # seen along y
    assert m.merged == 1 and m.superseded == 1 and len(m) == 1 and m.keys.tolist() == [2] and m.o[0] == 1
    np.testing.assert_allclose(m.p[0], p_new)
    np.testing.assert_allclose(m.P[0], _long(1, 2.0)[0])
    # the same pair agreeing across the narrow axes (differing along the long ones) is fused
    m2 = ObstacleMap(MapConfig(gate_k=3.0))
    m2.observe(0.0, [1], [[20.0, 0.0, -10.0]], _long(0, 2.0), live_keys=[])
    m2.observe(0.1, [2], [[21.5, 0.0, -10.0]], _long(0, 2.0), live_keys=[2])
    assert m2.merged == 1 and m2.superseded == 0 and len(m2) == 1 and m2.keys.tolist() == [2]
    np.testing.assert_allclose(m2.p[0], [20.75, 0.0, -10.0], atol=0.01)
    assert m2.P[0][0, 0] < 2.0**2 / 2 + 0.01


def test_merging_allows_for_the_drift_since_the_point_was_last_seen():
    """A point 0.6 m off is a different point a second later (σ 0.1 each) but the same one after
    30 s of 0.02 m/s position drift."""
    for t_new, merged in ((1.0, 0), (30.0, 1)):
        m = ObstacleMap(MapConfig(gate_k=3.0, position_drift_mps=0.02, position_drift_max_m=1.5, max_age_s=60.0))
        m.observe(0.0, [1], [[20.0, 0.0, -10.0]], cov(1, 0.1), live_keys=[])
        m.observe(t_new, [2], [[20.0, 0.6, -10.0]], cov(1, 0.1), live_keys=[2])
        assert m.merged == merged and m.superseded == 0, t_new


def test_a_point_found_again_by_a_live_map_landmark_is_absorbed_by_it():
    m = ObstacleMap()
    m.observe(0.0, [5], [[15.3, 0.05, -10.0]], cov(1, 0.1), live_keys=[5])  # live, in the map
    m.observe(0.5, [1], [[15.0, 0.0, -10.0]], cov(1, 0.3), live_keys=[5])  # 1: remembered (a live point is never merged)
    m.o[m.keys == 1] = 2
    _, R_wc, p_wc = camera_pose()
    vc = m.check_view(2.0, R_wc, p_wc, FX, FY, CX, CY, W, H, np.array([[CX + 1.0, CY]]), np.array([15.3]),
                      np.array([0.1]), live_keys=[5])
    assert vc.found == 1 and m.keys.tolist() == [5] and m.o[0] == 3 and m.absorbed == 1


def test_a_lone_remembered_point_is_not_published_a_surface_is():
    m = ObstacleMap(MapConfig(min_support=2, support_radius_m=0.6))
    lone = [[19.0, 0.2, -5.0]]
    patch = [[30.0, 0.0, -5.0], [30.0, 0.3, -5.0], [30.0, 0.3, -5.4]]
    m.observe(0.0, [1, 2, 3, 4], lone + patch, cov(4), live_keys=[])
    assert sorted(m.remembered(0.5, np.zeros(3)).keys.tolist()) == [2, 3, 4]
    assert m.support(np.arange(4)).tolist() == [1, 3, 3, 3]


def test_support_radius_grows_with_distance_when_asked():
    # two wall points 1.5 m apart: lone at 0.6 m; neighbours when the radius is 10 % of their distance
    pts = [[20.0, 0.0, -5.0], [20.0, 1.5, -5.0], [4.0, 0.0, -5.0], [4.0, 1.5, -5.0]]
    vehicle = np.array([0.0, 0.0, -5.0])
    fixed = ObstacleMap(MapConfig(min_support=2, support_radius_m=0.6, support_radius_rel=0.0))
    fixed.observe(0.0, [1, 2, 3, 4], pts, cov(4), live_keys=[])
    assert len(fixed.remembered(0.5, vehicle)) == 0
    rel = ObstacleMap(MapConfig(min_support=2, support_radius_m=0.6, support_radius_rel=0.1))
    rel.observe(0.0, [1, 2, 3, 4], pts, cov(4), live_keys=[])
    # far pair: radius 0.1 × 20 m = 2 m ≥ 1.5 m; near pair: 0.1 × 4 m = 0.4 m → still the 0.6 m floor
    assert sorted(rel.remembered(0.5, vehicle).keys.tolist()) == [1, 2]
    assert rel.support(np.arange(4), vehicle).tolist() == [2, 2, 1, 1]
    with pytest.raises(ConfigError, match="support_radius_rel"):
        MapConfig(support_radius_rel=-0.1)


def test_support_scales_with_the_range_a_point_was_entered_from():
    """Two wall points 1.5 m apart ranged from 12 m support each other (0.15 × 12 m = 1.8 m); hovering 5 m
    from them the distance now gives 0.75 m and they would go lone.  With ``support_radius_seen`` the
    range they were entered from keeps the radius (``support_seen_ratio``, which bounds that range by a multiple
    of the distance now); a point re-entered from nearer takes that range."""
    wall = [[12.0, 0.0, -5.0], [12.0, 1.5, -5.0]]
    cam_far, near = np.array([0.0, 0.75, -5.0]), np.array([7.0, 0.75, -5.0])
    r_far = float(np.linalg.norm(np.array(wall[0]) - cam_far))
    maps = {}
    for ratio in (0.0, 1.5, 3.0):
        m = ObstacleMap(MapConfig(min_support=2, support_radius_m=0.6, support_radius_rel=0.15, support_column_radius_m=0.0,
                                  support_seen_ratio=ratio))
        m.observe(0.0, [1, 2], wall, cov(2), live_keys=[], p_world_cam=cam_far)
        np.testing.assert_allclose(m.r_seen, [r_far, r_far])
        assert len(m.remembered(0.5, cam_far)) == 2  # from where they were ranged: supported either way
        maps[ratio] = m
    # 5.06 m away: 3 × 5.06 m ≥ 12 m keeps the whole range (1.8 m radius); 1.5 × 5.06 m = 7.6 m gives 1.14 m < 1.5 m
    assert sorted(maps[3.0].remembered(0.5, near).keys.tolist()) == [1, 2]
    assert len(maps[1.5].remembered(0.5, near)) == 0
    assert len(maps[0.0].remembered(0.5, near)) == 0
    # without the camera position the range is not known (0): the distance now decides, as before
    m = ObstacleMap(MapConfig(min_support=2, support_radius_m=0.6, support_radius_rel=0.15, support_column_radius_m=0.0,
                              support_seen_ratio=3.0))
    m.observe(0.0, [1, 2], wall, cov(2), live_keys=[])
    assert m.r_seen.tolist() == [0.0, 0.0] and len(m.remembered(0.5, near)) == 0
    # re-entered from 4 m: that is the range now, and 0.15 × 4 m no longer reaches the neighbour
    m = maps[3.0]
    cam_close = np.array([8.0, 0.0, -5.0])
    m.observe(1.0, [1], wall[:1], cov(1), live_keys=[], p_world_cam=cam_close)
    assert m.r_seen[0] == pytest.approx(4.0) and m.r_seen[1] == pytest.approx(r_far)
    assert m.keys[m.support(np.arange(2), near) >= 2].tolist() == [2]  # 2 still reaches 1 (its own radius), 1 not 2
    # a refused entry (covariance not positive definite) leaves its row's range alone
    bad = cov(1)
    bad[0, 2, 2] = -1.0
    m.observe(2.0, [2], [[12.0, 1.5, -5.0]], bad, live_keys=[], p_world_cam=cam_close)
    assert m.r_seen[1] == pytest.approx(r_far)
    # a new landmark that lands on a remembered point takes it over, with its own range
    m.observe(3.0, [7], [[12.05, 1.5, -5.0]], cov(1), live_keys=[7], p_world_cam=np.array([2.0, 1.5, -5.0]))
    row = int(np.flatnonzero(m.keys == 7)[0])
    assert len(m) == 2 and m.r_seen[row] == pytest.approx(10.05)
    for bad in (-1.0, float("nan")):
        with pytest.raises(ConfigError, match="support_seen_ratio"):
            MapConfig(support_seen_ratio=bad)


def test_a_thin_masts_stacked_points_support_each_other_in_a_column():
    """A 0.15 m mast leaves corners one above another, ~1 m apart at 3 m range: lone under a 0.6 m
    sphere, supported by a column 0.3 m wide and 1.2 m up and down; the same spacing across a
    surface stays lone, and so does a point 1.5 m below another."""
    mast = [[18.0, -2.9, -4.5], [18.05, -2.95, -5.5], [17.95, -3.0, -6.5]]  # 1 m apart vertically
    across = [[30.0, 0.0, -5.0], [30.0, 1.0, -5.0]]  # 1 m apart horizontally
    far_below = [[40.0, 5.0, -5.0], [40.1, 5.0, -3.5]]  # 1.5 m apart vertically
    vehicle = np.array([15.0, -1.0, -5.0])
    rows = np.arange(7)
    sphere = ObstacleMap(MapConfig(min_support=2, support_radius_m=0.6, support_radius_rel=0.0, support_column_radius_m=0.0))
    column = ObstacleMap(MapConfig(min_support=2, support_radius_m=0.6, support_radius_rel=0.0, support_column_radius_m=0.3,
                                   support_column_half_height_m=1.2))
    for m in (sphere, column):
        m.observe(0.0, [1, 2, 3, 4, 5, 6, 7], mast + across + far_below, cov(7), live_keys=[])
    assert len(sphere.remembered(0.5, vehicle)) == 0
    assert sorted(column.remembered(0.5, vehicle).keys.tolist()) == [1, 2, 3]
    assert sphere.support(rows).tolist() == [1] * 7
    assert column.support(rows).tolist() == [2, 3, 2, 1, 1, 1, 1]  # 1 and 3 are 2 m apart: beyond the column
    for bad in (dict(support_column_radius_m=-0.1), dict(support_column_half_height_m=0.0),
                dict(support_column_radius_m=float("nan"))):
        with pytest.raises(ConfigError, match="support_column"):
            MapConfig(**bad)


def test_remembered_point_with_too_uncertain_a_bearing_is_dropped_not_spread():
    p = np.array([[10.0, 0.0, 0.0], [-10.0, 0.0, 0.0]])
    kw = dict(roll_pitch_rad=(0.0, 0.0), remembered_p_body=p, remembered_sigma=[0.2, 0.2],
              remembered_tangential_sigma=[0.8, 0.05])  # k·σ/r = 9.2° and 0.6° (k = 2)
    spread_alone = sectors_optional_rules_off(infer_max_gap_sectors=0, remembered_spread_k=2.0)
    cfg = sectors_optional_rules_off(infer_max_gap_sectors=0, remembered_spread_k=2.0, remembered_drop_spread_deg=5.0)
    s = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi, cfg, **kw)
    assert np.flatnonzero(s.state == SectorState.OBSTACLE).tolist() == [36]  # only the sharp point, behind
    assert s.state[0] == SectorState.UNKNOWN  # never "clear" for a dropped point either
    keep = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, math.pi, spread_alone, **kw)
    assert np.flatnonzero(keep.state == SectorState.OBSTACLE).tolist() == [0, 1, 2, 36, 70, 71]
    with pytest.raises(ConfigError, match="remembered_drop_spread_deg"):
        SectorConfig(remembered_drop_spread_deg=0.0)


def test_map_entry_needs_a_nis_near_the_frames_median():
    from companion.core.obstacle_map import consistent_for_entry

    rng = np.random.default_rng(3)
    nis = np.r_[rng.uniform(0.05, 0.2, 30), 2.9, 3.9, np.nan]  # 30 well-explained points, two occlusion-edge tracks, one without updates
    conv = np.ones(nis.size, bool)
    ok = consistent_for_entry(nis, conv, 10.0)
    assert ok[:30].all() and not ok[30] and not ok[31] and not ok[32]
    # relative: the same scene with a 3× larger real pixel noise (NIS 9× larger) gives the same verdicts
    np.testing.assert_array_equal(consistent_for_entry(9.0 * nis, conv, 10.0), ok)
    # off, or too few converged landmarks to form a median: no gate
    assert consistent_for_entry(nis, conv, 0.0).all()
    assert consistent_for_entry(nis[:5], conv[:5], 10.0).all()
    with pytest.raises(ConfigError, match="max_entry_nis_ratio"):
        MapConfig(max_entry_nis_ratio=-1.0)


def _remembered_claims(points, P, vehicle, t_now, cfg):
    """Obstacle sectors that ``points`` (entered at t = 0 with covariance ``P`` each, no longer live) claim at
    ``t_now`` from ``vehicle`` (NED, heading north), through the map's ``remembered`` and ``compute_sectors``."""
    m = ObstacleMap(MapConfig())
    m.observe(0.0, np.arange(1, len(points) + 1), points, np.repeat(P[None], len(points), 0), live_keys=[])
    rem = m.remembered(t_now, vehicle)
    assert len(rem) == len(points)
    s = compute_sectors(np.zeros((0, 3)), [], [], [], HFOV, 0.0, cfg, roll_pitch_rad=(0.0, 0.0),
                        remembered_p_body=world_to_body(rem.p_world, np.eye(3), vehicle), remembered_sigma=rem.range_sigma,
                        remembered_tangential_sigma=rem.tangential_sigma)
    return s, rem


def test_a_point_ranged_from_afar_and_passed_close_by_is_withheld_by_the_drop_rule():
    """``remembered_drop_spread_deg`` = 5 (measured, not shipped; docs/BENCHMARKS.md, "The quads on the
    position-error states, with the cap gated and uncertain remembered points withheld"): three points on a pole 10 m
    north, ranged from the south with a 0.6 m range σ, then passed 1.5 m beside.  Their old range σ now lies across the
    line of sight (σ_t ≈ 0.43 m at 1.5 m: a 16° spread), so they say nothing about the bearing and are not published,
    with ``remembered_drop_across_only`` too; the same points ranged from close by (σ along the new line of sight)
    still are.  With the rule off (90°, shipped) the uncertain ones claim sectors."""
    pole = np.array([[10.0, 0.0, 0.0], [10.0, 0.05, -0.4], [10.0, -0.05, 0.4]])
    covariances = {"afar": np.diag([0.6**2, 0.03**2, 0.03**2]), "close": np.diag([0.03**2, 0.1**2, 0.03**2])}
    vehicle = np.array([10.0, -1.5, 0.0])
    drop = dataclasses.replace(SectorConfig(), remembered_drop_spread_deg=5.0)
    configs = {"5": drop, "90": dataclasses.replace(drop, remembered_drop_spread_deg=90.0),
               "5 across": dataclasses.replace(drop, remembered_drop_across_only=True)}
    claimed = {(name, c): np.flatnonzero(_remembered_claims(pole, P, vehicle, 1.0, cfg)[0].state == SectorState.OBSTACLE).tolist()
               for name, P in covariances.items() for c, cfg in configs.items()}
    assert claimed["afar", "5"] == [] and claimed["afar", "5 across"] == []  # dropped: unknown, never "clear"
    assert claimed["close", "5"] == claimed["close", "90"] and 18 in claimed["close", "5"]  # east, 1.5 m: kept as it was
    assert len(claimed["afar", "90"]) > len(claimed["close", "90"])  # the rule off: spread over the sectors around


def test_the_drop_rule_across_the_line_of_sight_only_keeps_a_pole_hovered_before():
    """``remembered_drop_across_only``: a pole 1.9 m ahead, its points last seen 10 s ago from where the vehicle still
    hovers.  Their σ has grown with the drift model (0.02 m/s) along and across the line of sight alike, so their
    bearing σ (≈ 6°) exceeds a 5° drop: the plain rule withholds them and the sector goes unknown (what let a
    simulated PX4 fly into the slalom's pole, docs/BENCHMARKS.md, "The quads on the position-error states"); across
    the line of sight only, they stay.  (The pole ranged from afar and passed close by is still withheld: the test
    above.)"""
    pole = np.array([[1.9, 0.0, 0.0], [1.9, 0.03, -0.4], [1.9, -0.03, 0.4]])
    seen_here = np.diag([0.15**2, 0.02**2, 0.02**2])  # ranged from here: its σ along the line of sight
    plain = dataclasses.replace(SectorConfig(), remembered_drop_spread_deg=5.0)
    s_plain, rem = _remembered_claims(pole, seen_here, np.zeros(3), 10.0, plain)
    s_across, _ = _remembered_claims(pole, seen_here, np.zeros(3), 10.0, dataclasses.replace(plain, remembered_drop_across_only=True))
    assert np.all(rem.tangential_sigma / 1.9 > math.radians(5.0)) and np.all(rem.tangential_sigma <= rem.range_sigma)
    assert s_plain.state[0] == SectorState.UNKNOWN
    assert s_across.state[0] == SectorState.OBSTACLE and s_across.distances_cm[0] < 190
    with pytest.raises(ConfigError, match="remembered_drop_across_only"):
        SectorConfig(remembered_drop_across_only=1)
