"""The simulated autopilot's obstacle avoidance (flightsim.avoidance) and the closed-loop outcome
(flightsim.outcome): exact braking curves, the rules each autopilot applies to unknown / clear /
stale sectors, and whole flights that stop short with true ranges and crash without any."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from companion.errors import ConfigError
from companion.mavlink.dialect import mavlink
from flightsim.avoidance import (
    F450_RADIUS_M,
    ArduPilotAvoidance,
    AvoidanceConfig,
    NoAvoidance,
    PX4Avoidance,
    jerk_limited_speed,
    make_avoidance,
    sqrt_controller,
    stopping_distance,
)
from flightsim.outcome import OutcomeConfig, evaluate_outcome, horizontal_route, read_trajectory, route_progress

ROOT = Path(__file__).resolve().parents[1]
WALL6 = ROOT / "configs" / "scenarios" / "quad_avoid_wall_6.toml"
MAX_CM = 4000


def od(distances_m, min_cm=20, max_cm=MAX_CM):
    """OBSTACLE_DISTANCE with 72 sectors of 5° from a (72,) array in metres (NaN = unknown, inf = clear)."""
    d = np.asarray(distances_m, float)
    cm = np.where(np.isnan(d), 65535, np.where(np.isinf(d), max_cm + 1, np.rint(np.nan_to_num(d, posinf=0) * 100)))
    return mavlink.MAVLink_obstacle_distance_message(0, 4, [int(x) for x in cm], 5, min_cm, max_cm, 5.0, 0.0,
                                                     mavlink.MAV_FRAME_BODY_FRD)


def wall_ahead(dist_m, half_width_deg=30.0):
    """Sectors of a wall dist_m ahead spanning ±half_width_deg (the rest unknown)."""
    d = np.full(72, np.nan)
    for i in range(72):
        b = math.radians(i * 5.0 if i * 5.0 <= 180 else i * 5.0 - 360)
        if abs(math.degrees(b)) <= half_width_deg:
            d[i] = dist_m / math.cos(b)
    return d


EXACT = AvoidanceConfig(model="ardupilot", prx_filt_hz=0.0, avoid_accel_max_mss=0.0)


# ------------------------------------------------------------------------------------ shaping ---
def test_sqrt_controller_is_continuous_monotonic_and_inverts_stopping_distance():
    kp, a = 1.0, 1.0
    d = np.linspace(0.0, 40.0, 4001)
    v = np.array([sqrt_controller(x, kp, a, 0.0) for x in d])
    assert np.all(np.diff(v) >= 0)
    assert abs(sqrt_controller(1.0 - 1e-9, kp, a, 0) - sqrt_controller(1.0 + 1e-9, kp, a, 0)) < 1e-6  # a/kp² = 1 m
    assert sqrt_controller(3.0, kp, a, 0.0) == pytest.approx(math.sqrt(5.0))  # √(2·1·(3 − ½))
    for x in (0.3, 2.0, 7.5, 30.0):
        assert stopping_distance(sqrt_controller(x, kp, a, 0.0), kp, a) == pytest.approx(x, rel=1e-9)
    assert sqrt_controller(5.0, kp, a, 0.01) == pytest.approx(min(math.sqrt(2 * 4.5), 5.0 / 0.01))
    assert sqrt_controller(-1.0, kp, a, 0.0) == 0.0


def test_jerk_limited_speed_stops_within_the_distance():
    j, a = 8.0, 3.0
    for d in (0.5, 2.0, 10.0, 40.0):
        v = jerk_limited_speed(j, a, d)
        # the formula inverts d = v²/(2a) + 2·v·a/j (braking at a after the jerk-limited ramp-up)
        assert v * v / (2 * a) + 2 * v * a / j == pytest.approx(d, rel=1e-9)
        assert v < math.sqrt(2 * a * d)
    assert jerk_limited_speed(j, a, 0.0) == 0.0


# ------------------------------------------------------------------------------------ ArduPilot --
def test_ardupilot_limits_the_speed_towards_a_wall_to_its_braking_curve():
    av = ArduPilotAvoidance(EXACT)
    av.receive(1.0, od(wall_ahead(10.0)))
    v = av.limit(1.0, (0, 0, -5), (6, 0, 0), 0.0, (6.0, 0.0, 0.0))
    # face 0 holds the wall's minimum, 10 m (the sector at 0°); its obstacle is the segment between the
    # boundary points on its edges (bearings ±22.5°, each at the nearer neighbouring face: 10 m), so its
    # closest point lies 10·cos 22.5° ahead: allowed speed = sqrt_controller(10·cos 22.5° − margin)
    assert v[0] == pytest.approx(sqrt_controller(10.0 * math.cos(math.radians(22.5)) - 2.0, 1.0, 1.0, 0.0), rel=1e-6)
    assert v[1] == pytest.approx(0.0, abs=1e-9) and v[2] == 0.0


def test_ardupilot_unknown_and_clear_sectors_apply_no_constraint():
    for d in (np.full(72, np.nan), np.full(72, np.inf)):
        av = ArduPilotAvoidance(EXACT)
        av.receive(1.0, od(d))
        assert av.limit(1.0, (0, 0, -5), (0, 0, 0), 0.0, (6.0, 1.0, -0.5)) == (6.0, 1.0, -0.5)
        assert not av.has_data(1.0)


def _towards(v_body, obstacles):
    """Velocity component towards each obstacle's closest point and the speed it allows (margin 2 m)."""
    out = []
    for _, _, o in obstacles:
        no = math.hypot(*o)
        out.append((float(np.dot(v_body, o / no)), sqrt_controller(no - 2.0, 1.0, 1.0, 0.0)))
    return out


def test_ardupilot_slide_and_stop_never_exceed_the_stopping_speed_towards_any_obstacle():
    narrow = np.full(72, np.nan)
    narrow[[0, 1, 2, 3, 4, 68, 69, 70, 71]] = 6.0  # a wall ahead within ±20°: face 0 only
    for behave in ("slide", "stop"):
        av = ArduPilotAvoidance(dataclasses.replace(EXACT, avoid_behave=behave))
        av.receive(0.0, od(narrow))
        obstacles = av.obstacles_body(0.0)
        assert len(obstacles) == 3  # face 0 and, through the boundary's "cup", faces 7 and 1
        for demand in ((5.0, 0.0), (3.0, 3.0), (0.0, 4.0), (-2.0, 1.0)):
            v = av.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (*demand, 0.0))
            for comp, allowed in _towards(np.array(v[:2]), obstacles):
                assert comp <= allowed + 1e-9
        # moving away is never limited
        assert av.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (-3.0, 0.0, 0.0))[:2] == (-3.0, 0.0)
    slide = ArduPilotAvoidance(EXACT)
    slide.receive(0.0, od(narrow))
    v = slide.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (1.0, 2.0, 0.0))  # oblique: the tangential part is kept
    assert v[1] > 1.0
    stop = ArduPilotAvoidance(dataclasses.replace(EXACT, avoid_behave="stop", avoid_backup_spd_mps=0.0))
    stop.receive(0.0, od(wall_ahead(1.9, 60.0)))  # inside the 2 m margin, demand towards the wall: zero
    assert stop.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (3.0, 1.0, 0.0))[:2] == (0.0, 0.0)


def test_ardupilot_backs_away_inside_the_margin_at_most_backup_speed():
    av = ArduPilotAvoidance(EXACT)
    av.receive(0.0, od(wall_ahead(1.0, 60.0)))
    av.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (0.0, 0.0, 0.0))
    v = av.limit(0.01, (0, 0, -5), (0, 0, 0), 0.0, (0.0, 0.0, 0.0))  # hovering 1 m from the wall
    assert -0.75 - 1e-9 <= v[0] < -0.05


def test_ardupilot_works_in_the_body_frame_at_the_current_yaw():
    av = ArduPilotAvoidance(EXACT)
    av.receive(0.0, od(wall_ahead(6.0)))  # ahead of the nose
    east = math.pi / 2
    v = av.limit(0.0, (0, 0, -5), (0, 0, 0), east, (0.0, 5.0, 0.0))  # facing east, flying east: at the wall
    assert v[1] == pytest.approx(sqrt_controller(6.0 * math.cos(math.radians(22.5)) - 2.0, 1.0, 1.0, 0.0), rel=1e-6)
    assert abs(v[0]) < 1e-9
    assert av.limit(0.01, (0, 0, -5), (0, 0, 0), east, (0.0, -5.0, 0.0))[:2] == (0.0, -5.0)  # flying west: away
    assert av.limit(0.02, (0, 0, -5), (0, 0, 0), 0.0, (-5.0, 0.0, 0.0))[:2] == (-5.0, 0.0)  # facing north it lies north


def test_ardupilot_takes_messages_at_arrival_and_drops_stale_data():
    av = ArduPilotAvoidance(EXACT)
    av.receive(5.0, od(wall_ahead(5.0)))
    assert av.limit(4.99, (0, 0, -5), (0, 0, 0), 0.0, (5.0, 0, 0))[0] == 5.0  # not arrived yet
    assert av.limit(5.0, (0, 0, -5), (0, 0, 0), 0.0, (5.0, 0, 0))[0] < 3.0
    assert av.has_data(5.49) and not av.has_data(5.51)  # stale_s = 0.5 after the last message
    assert av.limit(5.6, (0, 0, -5), (0, 0, 0), 0.0, (5.0, 0, 0))[0] == 5.0


def test_ardupilot_filter_makes_an_approaching_wall_look_farther():
    av = ArduPilotAvoidance(dataclasses.replace(EXACT, prx_filt_hz=0.25))
    for k, d in enumerate((20.0, 15.0)):
        av.receive(0.1 * k, od(wall_ahead(d)))
    av.has_data(0.1)  # messages take effect when the autopilot next looks at its data
    f = av.face_filt[0]
    alpha = 0.1 / (0.1 + 1 / (2 * math.pi * 0.25))
    assert f == pytest.approx(20.0 + alpha * (15.0 - 20.0))


def test_ardupilot_output_changes_at_most_avoid_accel_max():
    av = ArduPilotAvoidance(dataclasses.replace(EXACT, avoid_accel_max_mss=3.0))
    av.receive(0.0, od(wall_ahead(4.0)))
    v0 = av.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (8.0, 0, 0))
    v1 = av.limit(0.01, (0, 0, -5), (0, 0, 0), 0.0, (8.0, 0, 0))
    assert abs(v1[0] - v0[0]) <= 3.0 * 0.01 + 1e-9
    assert v0[0] == pytest.approx(8.0)  # the first modified output starts from the unmodified demand


# ------------------------------------------------------------------------------------ PX4 ----------
PX4 = AvoidanceConfig(model="px4", cp_dist_m=2.0)


def test_px4_refuses_to_move_without_data_and_into_unknown():
    av = PX4Avoidance(PX4)
    assert av.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (3.0, 0.0, 0.0)) == (0.0, 0.0, 0.0)
    d = np.full(72, np.nan)
    d[36] = 20.0  # only behind has data
    av.receive(0.0, od(d))
    assert av.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (3.0, 0.0, 0.0))[:2] == (0.0, 0.0)
    go = PX4Avoidance(dataclasses.replace(PX4, cp_go_no_data=True))  # allowed where the sensor never saw
    go.receive(0.0, od(d))
    assert go.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (3.0, 0.0, 0.0))[0] == pytest.approx(3.0)


def test_px4_speed_towards_a_wall_is_the_stopping_room_curve():
    av = PX4Avoidance(dataclasses.replace(PX4, cp_guide_ang_deg=0.0))
    d = np.full(72, np.inf)
    d[0] = 12.0
    av.receive(0.0, od(d))
    v = av.limit(0.0, (0, 0, -5), (2.0, 0, 0), 0.0, (8.0, 0.0, 0.0))
    room = 12.0 - 2.0 - 2.0 * 0.4  # d − CP_DIST − v∥·CP_DELAY (data age 0)
    want = min(0.95 * room, jerk_limited_speed(8.0, 3.0, room))
    assert v[0] == pytest.approx(want, rel=1e-9) and abs(v[1]) < 1e-12
    # clear sectors count as obstacles at max_distance + 1 (PX4 stores them), still far beyond a stop
    assert av.bins(0.0)[9] == MAX_CM + 1


def test_px4_ignores_what_lies_behind_and_goes_stale_per_bin():
    d = np.full(72, np.inf)
    d[36] = 1.0  # 1 m behind
    av = PX4Avoidance(PX4)
    av.receive(0.0, od(d))
    assert av.limit(0.1, (0, 0, -5), (0, 0, 0), 0.0, (3.0, 0.0, 0.0))[0] == pytest.approx(3.0)
    assert av.limit(0.6, (0, 0, -5), (0, 0, 0), 0.0, (3.0, 0.0, 0.0))[0] == 0.0  # every bin stale after 0.5 s


def test_px4_guidance_turns_the_setpoint_towards_free_space():
    d = np.full(72, np.inf)
    d[70:72] = 3.0
    d[0:3] = 3.0  # blocked from −10° to +10°
    av = PX4Avoidance(PX4)
    av.receive(0.0, od(d))
    v = av.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (3.0, 0.0, 0.0))
    assert math.hypot(v[0], v[1]) > 1.0 and abs(math.degrees(math.atan2(v[1], v[0]))) >= 10.0 - 1e-9


# ------------------------------------------------------------------------------------ config ------
def test_avoidance_config_is_validated_and_models_are_built():
    for bad in ({"model": "inav"}, {"avoid_behave": "swerve"}, {"cp_dist_m": 0.0}, {"cp_delay_s": 2.0},
                {"avoid_margin_m": float("nan")}, {"cp_go_no_data": 1}):
        with pytest.raises(ConfigError):
            AvoidanceConfig(**bad)
    assert isinstance(make_avoidance(AvoidanceConfig(model="px4")), PX4Avoidance)
    assert type(make_avoidance(AvoidanceConfig())) is NoAvoidance


def test_scenario_avoidance_table_route_check_and_fixed_wing(tmp_path):
    from flightsim.scenario import load_scenario

    sc = load_scenario(WALL6)
    assert sc.avoidance.model == "ardupilot"
    assert load_scenario(WALL6, avoidance="px4").avoidance.model == "px4"
    with pytest.raises(ConfigError, match="only .* from obstacle 'warehouse'"):  # through the wall without avoidance
        load_scenario(WALL6, avoidance="none")
    fw = (ROOT / "configs" / "scenarios" / "fixedwing_pass.toml").read_text()
    p = tmp_path / "fw.toml"
    p.write_text(fw.replace('world = "../worlds/', f'world = "{ROOT}/configs/worlds/') + '\n[avoidance]\nmodel = "ardupilot"\n')
    with pytest.raises(ConfigError, match="fixed-wing"):
        load_scenario(p)


# ------------------------------------------------------------------------------------ outcome -----
def test_route_progress_is_exact_along_a_polyline():
    route = np.array([[0, 0, -5], [10, 0, -5], [10, 10, -5]], float)
    p = np.array([[5, 1, -5], [10, 4, -5], [12, 10, -5], [-3, 0, -5]], float)
    assert route_progress(p, route) == pytest.approx([5.0, 14.0, 20.0, 0.0])


def test_progress_leaves_out_a_take_off_straight_up():
    route = np.array([[0, 0, 0], [0, 0, -5], [0, 0, -5], [10, 0, -5], [10, 10, -5]], float)
    assert horizontal_route(route).tolist() == [[0, 0, -5], [10, 0, -5], [10, 10, -5]]
    up = np.array([[0, 0, 0], [0, 0, -5]], float)  # vertical throughout: unchanged
    assert horizontal_route(up).tolist() == up.tolist()
    flat = np.array([[0, 0, -5], [10, 0, -5]], float)
    assert horizontal_route(flat).tolist() == flat.tolist()
    # a flight that took off and flew 5 m of a 20 m horizontal route: 25 %, not (5 + 5) / 25
    tr = _synthetic(lambda t: 1.0 if t < 5 else 0.0, lambda x: 50.0)
    tr["route_ned"] = np.array([[0, 0, 0], [0, 0, -5], [20, 0, -5]], float)
    assert evaluate_outcome(tr)["progress"] == pytest.approx(0.25, abs=0.002)


def _synthetic(v_profile, clear, t_end=10.0, dt=0.01, demand=3.0):
    t = np.arange(0.0, t_end, dt)
    vx = np.array([v_profile(x) for x in t])
    px = np.concatenate([[0.0], np.cumsum(vx[:-1] * dt)])
    n = len(t)
    return {"t_sim_s": t, "p_ned": np.stack([px, np.zeros(n), np.full(n, -5.0)], 1),
            "v_ned": np.stack([vx, np.zeros(n), np.zeros(n)], 1),
            "v_des_ned": np.stack([np.full(n, demand), np.zeros(n), np.zeros(n)], 1),
            "clearance_m": np.array([clear(x) for x in px]), "route_ned": np.array([[0, 0, -5], [100, 0, -5.0]]),
            "body_radius_m": np.array(F450_RADIUS_M), "avoid_margin_m": np.array(2.0),
            "avoidance_model": np.array("ardupilot"), "collision_t_s": np.array(np.nan),
            "braking_kp": np.array(1.0), "braking_accel_mss": np.array(1.0), "braking_delay_s": np.array(0.0),
            "avoidance_data": np.ones(n, bool)}


def test_outcome_stop_false_stop_progress_and_collision():
    # flies at 3 m/s, stops at 5 s in front of a wall 2 m away: a stop, not a false stop
    tr = _synthetic(lambda t: 3.0 if t < 5 else 0.0, lambda x: 17.0 - x)
    o = evaluate_outcome(tr)
    assert not o["collision"] and o["stop_t_s"] == pytest.approx(5.0, abs=0.02)
    assert o["stop_clearance_m"] == pytest.approx(2.0, abs=0.05) and not o["false_stop"]
    assert o["progress"] == pytest.approx(0.15, abs=0.002) and o["time_to_goal_s"] is None
    # the same stop with the wall 30 m away: a false stop (nothing within the margins + stopping distance)
    o = evaluate_outcome(_synthetic(lambda t: 3.0 if t < 5 else 0.0, lambda x: 45.0 - x))
    assert o["false_stop"] and o["false_stop_t_s"] == pytest.approx(5.0, abs=0.02) and o["false_stop_s"] > 4.5
    # a slowdown counts only when the avoidance held the demand back: with its output recorded
    # (v_cmd_ned) equal to the pilot's demand the same slow spell is the vehicle, not a false stop
    slow_start = _synthetic(lambda t: min(3.0, 0.5 * t), lambda x: 45.0 - x)  # 1 s below 1.5 m/s
    assert evaluate_outcome(slow_start)["false_stop"]  # without v_cmd_ned: the speed alone decides
    slow_start["v_cmd_ned"] = slow_start["v_des_ned"].copy()
    assert not evaluate_outcome(slow_start)["false_stop"]
    held = _synthetic(lambda t: 3.0 if t < 5 else 0.0, lambda x: 45.0 - x)
    held["v_cmd_ned"] = np.where(held["t_sim_s"][:, None] < 5, held["v_des_ned"], 0.0)
    o = evaluate_outcome(held)
    assert o["false_stop"] and o["false_stop_t_s"] == pytest.approx(5.0, abs=0.02)
    # flying on into the wall: a collision where the clearance reaches zero
    o = evaluate_outcome(_synthetic(lambda t: 3.0, lambda x: 12.0 - x))
    assert o["collision"] and o["collision_t_s"] == pytest.approx(4.0, abs=0.02) and o["min_clearance_m"] < 0
    with pytest.raises(ConfigError):
        OutcomeConfig(min_stop_s=0.0)


# ------------------------------------------------------------------------------------ closed loop -
def _fly_with_true_ranges(model: str, feed: bool, seconds: float = 20.0):
    """Fly quad_avoid_wall_6 step by step; with ``feed`` the autopilot gets OBSTACLE_DISTANCE built
    from the true sectors at 10 Hz (arriving 50 ms after the state they describe)."""
    from flightsim.fly import Flight
    from flightsim.scenario import load_scenario
    from flightsim.world.truth import sector_truth_360

    sc = load_scenario(WALL6, avoidance=model)
    sc = dataclasses.replace(sc, meta=dataclasses.replace(sc.meta, duration_s=seconds))
    fl = Flight(sc)
    next_msg = 0.0
    while (st := fl.physics_step()) is not None:
        if feed and st.time_s >= next_msg - 1e-9:
            d, _ = sector_truth_360(sc.world, st.R_world_body, st.p_ned, None, 40.0)
            fl.avoidance.receive(st.time_s + 0.05, od(np.where(np.isfinite(d), d, np.inf)))
            next_msg += 0.1
    return fl, evaluate_outcome(fl.trajectory_arrays(), sc.world)


@pytest.mark.parametrize("model", ["ardupilot", "px4"])
def test_closed_loop_with_true_ranges_stops_short_of_the_wall(model):
    fl, o = _fly_with_true_ranges(model, feed=True)
    assert not o["collision"], o
    assert o["stop_t_s"] is not None and o["stop_obstacle"] and "warehouse" in o["stop_obstacle"]
    margin = 2.0
    # the autopilot keeps its margin from the vehicle's centre: the body stops margin − radius away, give or take
    assert margin - F450_RADIUS_M - 0.4 <= o["stop_clearance_m"] <= margin - F450_RADIUS_M + 1.0, o
    assert o["max_speed_mps"] > 5.0 and not o["false_stop"]


def test_closed_loop_without_data_crashes_with_ardupilot_and_stalls_with_px4():
    _, o = _fly_with_true_ranges("ardupilot", feed=False, seconds=16.0)
    assert o["collision"] and "warehouse" in (o["collision_with"] or "")  # no data = no constraint: the harness can fail
    fl, o = _fly_with_true_ranges("px4", feed=False, seconds=7.0)
    assert not o["collision"] and o["progress"] < 0.01 and o["false_stop"]  # no data = refuses to move ...
    tr = fl.trajectory_arrays()
    assert tr["p_ned"][0][2] > -0.3 and tr["p_ned"][-1][2] == pytest.approx(-5.0, abs=0.3)  # ... but takes off: PX4 limits only the horizontal demand


def test_avoidance_scenarios_take_off_straight_up_before_the_horizontal_leg():
    from flightsim.scenario import load_scenario

    for path in sorted((ROOT / "configs" / "scenarios").glob("quad_avoid_*.toml")):
        v = load_scenario(path).vehicle
        start, first = np.asarray(v.start_ned_m), np.asarray(v.route.waypoints[0])
        assert start[2] == 0.0 and np.allclose(first[:2], start[:2]) and first[2] < -3.0, path.name


def test_fly_writes_the_trajectory_and_reports_the_outcome(tmp_path, capsys):
    from flightsim.cli import main

    rc = main(["fly", str(WALL6), "--out", str(tmp_path / "f"), "--no-plot", "--avoidance", "ardupilot"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "COLLISION with 'warehouse'" in out
    tr = read_trajectory(tmp_path / "f" / "trajectory.npz")
    assert np.isfinite(tr["collision_t_s"]) and tr["p_ned"][-1][0] == pytest.approx(50.0 - F450_RADIUS_M, abs=0.15)


# ------------------------------------------------------------------------------------ campaigns ---
def test_wilson_interval_is_exact_at_the_edges_and_contains_the_estimate():
    from flightsim.campaign import wilson_interval

    z2 = 1.959963984540054 ** 2
    lo, hi = wilson_interval(0, 20)
    assert lo == 0.0 and hi == pytest.approx(z2 / (20 + z2), rel=1e-9)
    lo, hi = wilson_interval(20, 20)
    assert lo == pytest.approx(20 / (20 + z2), rel=1e-9) and hi == 1.0
    for k in range(0, 21):
        lo, hi = wilson_interval(k, 20)
        assert lo <= k / 20 <= hi
    assert wilson_interval(0, 0) == (None, None)


def test_pool_outcomes_counts_collisions_stops_and_false_stops():
    from flightsim.campaign import pool_outcomes

    base = {"model": "ardupilot", "collision": False, "false_stop": False, "stop_clearance_m": 2.0, "min_clearance_m": 1.9,
            "progress": 0.7, "time_to_goal_s": None, "max_speed_mps": 6.0, "data_while_pushing": 0.9}
    runs = [dict(base), dict(base, stop_clearance_m=1.0), dict(base, collision=True, stop_clearance_m=None, min_clearance_m=-0.1),
            dict(base, false_stop=True)]
    p = pool_outcomes(runs)
    assert p["runs"] == 4 and p["collisions"] == 1 and p["collision_rate"] == 0.25 and p["false_stops"] == 1
    assert p["stopped_short"] == 3 and p["stop_clearance_m"]["min"] == 1.0 and p["min_clearance_m"]["min"] == -0.1
    lo, hi = p["collision_ci95"]
    assert lo < 0.25 < hi


def test_campaign_refuses_replay_mode_with_avoidance(tmp_path):
    from flightsim.campaign import run_campaign

    with pytest.raises(ConfigError, match="replay"):
        run_campaign(WALL6, tmp_path / "c", runs=1, mode="replay")


# ------------------------------------------------------------------------------------ SITL --------
def test_sitl_closed_loop_stops_short_of_the_wall_on_the_companions_ranges(tmp_path):
    """The whole loop: the live companion ranges the wall, the simulated ArduPilot limits the pilot's
    6 m/s demand with the OBSTACLE_DISTANCE it receives, and the quad stops short."""
    import json

    from flightsim.sitl import run_sitl

    s = run_sitl(WALL6, tmp_path / "s", mavlink_port=0, camera_port=0)
    o = s["score"]["avoidance"]
    assert not o["collision"], o
    assert o["stop_t_s"] is not None and "warehouse" in (o["stop_obstacle"] or "")
    assert o["stop_clearance_m"] >= 2.0 - 0.5 and o["min_clearance_m"] > 1.0  # AVOID_MARGIN − 0.5 m
    assert not o["false_stop"] and o["max_speed_mps"] > 5.0
    assert s["checks"].get("avoidance_late", 0) == 0  # the physics never ran past a message's arrival
    assert s["avoidance"]["model"] == "ardupilot" and s["avoidance"]["messages"] > 100
    assert (tmp_path / "s" / "avoidance.png").stat().st_size > 10_000
    score = json.loads((tmp_path / "s" / "score.json").read_text())
    assert score["avoidance"]["collision"] is False
    assert "## Avoidance (closed loop)" in (tmp_path / "s" / "score.md").read_text()


def ds(distance_m, orientation=0, min_cm=20, max_cm=MAX_CM):
    return mavlink.MAVLink_distance_sensor_message(0, min_cm, max_cm, int(round(distance_m * 100)), 4, 0, orientation, 255)


def test_distance_sensor_is_one_reading_at_its_orientation_in_both_models():
    ap = ArduPilotAvoidance(EXACT)
    ap.receive(0.0, ds(8.0))
    v = ap.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (6.0, 0.0, 0.0))
    assert v[0] == pytest.approx(sqrt_controller(8.0 * math.cos(math.radians(22.5)) - 2.0, 1.0, 1.0, 0.0), rel=1e-6)
    ap2 = ArduPilotAvoidance(EXACT)
    ap2.receive(0.0, ds(8.0, orientation=2))  # YAW_90: to the right — a demand to the left is free, to the right limited
    assert ap2.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (0.0, -6.0, 0.0))[:2] == (0.0, -6.0)
    assert ap2.limit(0.01, (0, 0, -5), (0, 0, 0), 0.0, (0.0, 6.0, 0.0))[1] == pytest.approx(
        sqrt_controller(8.0 * math.cos(math.radians(22.5)) - 2.0, 1.0, 1.0, 0.0), rel=1e-6)
    px = PX4Avoidance(dataclasses.replace(PX4, cp_guide_ang_deg=0.0))
    px.receive(0.0, ds(8.0))
    assert px.bins(0.0)[0] == 800 and px.limit(0.0, (0, 0, -5), (0, 0, 0), 0.0, (6.0, 0.0, 0.0))[0] < 6.0
    up = ArduPilotAvoidance(EXACT)
    up.receive(0.0, ds(3.0, orientation=24))  # upward: not a horizontal reading
    assert not up.has_data(0.0)


def test_malformed_obstacle_distance_is_ignored_not_fatal():
    for model in (ArduPilotAvoidance(EXACT), PX4Avoidance(PX4)):
        bad = od(wall_ahead(5.0))
        bad.increment, bad.increment_f = 0, 0.0
        model.receive(0.0, bad)
        assert not model.has_data(0.0)
        model.receive(0.1, od(np.where(np.isnan(wall_ahead(5.0)), np.nan, 0.0)))  # zeros: "touching" is skipped by ArduPilot
        model.limit(0.1, (0, 0, -5), (0, 0, 0), 0.0, (1.0, 0.0, 0.0))  # never raises


def test_closest_point_between_segments_is_exact():
    from flightsim.avoidance.common import _closest_between_segments

    o = np.zeros(2)
    # crossing: the intersection
    c = _closest_between_segments(o, np.array([10.0, 0.0]), np.array([4.0, -2.0]), np.array([4.0, 2.0]))
    assert c == pytest.approx([4.0, 0.0])
    # apart: brute force over both segments agrees
    rng = np.random.default_rng(3)
    for _ in range(200):
        p0, p1, q0, q1 = rng.uniform(-5, 5, (4, 2))
        c = _closest_between_segments(p0, p1, q0, q1)
        u = np.linspace(0, 1, 401)
        P = p0 + u[:, None] * (p1 - p0)
        Q = q0 + u[:, None] * (q1 - q0)
        D = np.linalg.norm(P[:, None] - Q[None], axis=2)
        dmin = D.min()
        dc = np.min(np.linalg.norm(P - c, axis=1))
        assert dc <= dmin + 0.03 and np.min(np.linalg.norm(Q - c, axis=1)) < 0.02


def test_sitl_closed_loop_is_deterministic_in_lockstep(tmp_path):
    """Same seed, same flight: the avoidance acts on messages at their simulated arrival, not at wall-clock luck."""
    import re

    from flightsim.sitl import run_sitl

    text = WALL6.read_text()
    text = re.sub(r'^world = "\.\./worlds/', f'world = "{(ROOT / "configs" / "worlds").as_posix()}/', text, flags=re.M)
    text = re.sub(r"^duration_s = .*$", "duration_s = 12.5", text, flags=re.M)  # take-off (~3.5 s) and far enough to be braking for the wall
    sp = tmp_path / "short.toml"
    sp.write_text(text)
    outs = []
    for k in range(2):
        run_sitl(sp, tmp_path / f"r{k}", mavlink_port=0, camera_port=0, score=False)
        outs.append(read_trajectory(tmp_path / f"r{k}" / "trajectory.npz"))
    a, b = outs
    limited = np.hypot(*a["v_cmd_ned"][:, :2].T) < np.hypot(*a["v_des_ned"][:, :2].T) - 0.1
    assert np.any(limited)  # the avoidance did act in this window
    for key in ("p_ned", "v_ned", "v_cmd_ned", "boundary_ne_m"):
        np.testing.assert_array_equal(a[key], b[key])
    assert (tmp_path / "r0" / "received.tlog").read_bytes() == (tmp_path / "r1" / "received.tlog").read_bytes()


def test_stop_clearance_sweeps_the_bodys_width():
    from flightsim.outcome import _ahead_clearance
    from flightsim.scenario import load_scenario

    world = load_scenario(ROOT / "configs" / "scenarios" / "quad_avoid_pole.toml").world  # pole r = 0.3 at (30, 0)
    d, name = _ahead_clearance(world, np.array([27.0, 0.0, -5.0]), np.array([1.0, 0.0, 0.0]), F450_RADIUS_M)
    assert "pole" in name and d == pytest.approx(3.0 - 0.3 - F450_RADIUS_M, abs=0.01)  # head-on
    # 0.49 m beside the line: the centre ray misses the pole, the body does not
    d, name = _ahead_clearance(world, np.array([27.0, -0.49, -5.0]), np.array([1.0, 0.0, 0.0]), F450_RADIUS_M)
    gap = math.sqrt((0.3 + F450_RADIUS_M) ** 2 - 0.49 ** 2)  # exact sphere-past-cylinder contact
    assert "pole" in name and d == pytest.approx(3.0 - gap, abs=0.03)
    # 1 m beside it the body passes: the hall behind is what it meets
    d, name = _ahead_clearance(world, np.array([27.0, -1.0, -5.0]), np.array([1.0, 0.0, 0.0]), F450_RADIUS_M)
    assert "hall" in name


def test_released_after_a_hold_the_quad_never_flies_faster_than_the_demand():
    """Stop-go (an autopilot holding, then letting the pilot's 6 m/s through, again and again): a
    position controller catching up with its own reference must not push the vehicle past what the
    avoidance let through (before: 1.6x the demand after a few cycles)."""
    from flightsim.fly import Flight
    from flightsim.scenario import load_scenario

    class StopGo:
        def limit(self, t, p_ned, v_ned, yaw, v_des):
            return (0.0, 0.0, v_des[2]) if int(t / 1.5) % 2 else tuple(v_des)

    sc = load_scenario(WALL6, avoidance="ardupilot")
    sc = dataclasses.replace(sc, meta=dataclasses.replace(sc.meta, duration_s=16.0))
    fl = Flight(sc)
    fl.vehicle.avoidance = StopGo()
    v_max_h, v_cmd_max_h = 0.0, 0.0
    while (st := fl.physics_step()) is not None:
        if st.time_s > 4.0:  # after the climb
            v_max_h = max(v_max_h, float(np.hypot(st.v_ned[0], st.v_ned[1])))
            v_cmd_max_h = max(v_cmd_max_h, float(np.hypot(*fl.vehicle.v_cmd[:2])))
    assert v_cmd_max_h == pytest.approx(6.0, abs=0.05)
    assert v_max_h <= 1.08 * v_cmd_max_h, (v_max_h, v_cmd_max_h)


def test_held_by_the_avoidance_the_quad_stays_where_it_stopped():
    """Held at zero demand after flying at 6 m/s, the quad brakes and then holds its position (the
    position controller's hold, not a creep on the velocity loop's wound-up integrator)."""
    from flightsim.fly import Flight
    from flightsim.scenario import load_scenario

    class HoldAfter:
        def limit(self, t, p_ned, v_ned, yaw, v_des):
            return tuple(v_des) if t < 9.0 else (0.0, 0.0, v_des[2])

    sc = load_scenario(WALL6, avoidance="ardupilot")
    sc = dataclasses.replace(sc, meta=dataclasses.replace(sc.meta, duration_s=18.0))
    fl = Flight(sc)
    fl.vehicle.avoidance = HoldAfter()
    at, far = {}, 0.0
    while (st := fl.physics_step()) is not None:
        far = max(far, float(st.p_ned[0]))
        for mark in (9.0, 15.5, 18.0):
            if mark not in at and st.time_s >= mark - 1e-9:
                at[mark] = (np.array(st.p_ned[:2], float), float(np.hypot(st.v_ned[0], st.v_ned[1])))
    assert at[9.0][1] > 4.0  # it was flying
    assert far - at[9.0][0][0] < 7.0  # braking from 6 m/s at the tilt limit (overshoot included)
    assert at[15.5][1] < 0.1 and at[18.0][1] < 0.05  # stopped ...
    assert np.linalg.norm(at[18.0][0] - at[15.5][0]) < 0.1  # ... and stays there (no creep)


class _FlipGuidance:
    """PX4-like guidance flipping the setpoint ±30° off the demand every control tick."""

    def __init__(self):
        self.sign = 1.0

    def limit(self, t, p_ned, v_ned, yaw, v_des):
        self.sign = -self.sign
        a = math.radians(30.0) * self.sign
        c, s = math.cos(a), math.sin(a)
        return (c * v_des[0] - s * v_des[1], s * v_des[0] + c * v_des[1], v_des[2])


class _SlideStopGo:
    """ArduPilot-like slide: the demand turned sideways (held towards the obstacle) for 1.5 s, then let through."""

    def limit(self, t, p_ned, v_ned, yaw, v_des):
        if int(t / 1.5) % 2:
            return (-v_des[1], v_des[0], v_des[2])
        return tuple(v_des)


@pytest.mark.parametrize("guidance", [_FlipGuidance, _SlideStopGo], ids=["flip", "slide"])
def test_turned_sideways_by_the_avoidance_the_quad_never_flies_faster_than_the_demand(guidance):
    """The leash holds in every horizontal direction: a setpoint the avoidance turns sideways (a slide, a
    guidance that flips from side to side) must not let the position controller push the vehicle past
    the speed the avoidance let through (before: 1.54x in front of a wide wall)."""
    from flightsim.fly import Flight
    from flightsim.scenario import load_scenario

    sc = load_scenario(WALL6, avoidance="ardupilot")
    sc = dataclasses.replace(sc, meta=dataclasses.replace(sc.meta, duration_s=14.0))
    fl = Flight(sc)
    fl.vehicle.avoidance = guidance()
    v_max_h, v_cmd_max_h = 0.0, 0.0
    while (st := fl.physics_step()) is not None:
        if st.time_s > 4.0:  # after the climb
            v_max_h = max(v_max_h, float(np.hypot(st.v_ned[0], st.v_ned[1])))
            v_cmd_max_h = max(v_cmd_max_h, float(np.hypot(*fl.vehicle.v_cmd[:2])))
    assert v_cmd_max_h == pytest.approx(6.0, abs=0.05)
    assert v_max_h <= 1.08 * v_cmd_max_h, (v_max_h, v_cmd_max_h)


# ------------------------------------------------------------ the slide path against the loop ---
class _LoopArduPilot(ArduPilotAvoidance):
    """ArduPilotAvoidance as it was written first: one obstacle at a time, numpy 2-vectors (the
    reference the vectorised slide path and the cached boundary must equal bit for bit)."""

    def boundary_body(self, t, ok=None):
        n = self.N_FACES
        ok = self.valid_faces(t) if ok is None else ok
        d = np.where(ok, self.face_filt, np.inf)
        pts = np.empty((n, 2))
        for k in range(n):
            dk = min(d[k], d[(k + 1) % n])
            if not np.isfinite(dk):
                dk = min(d[(k - 1) % n], d[(k + 2) % n])
            dk = self.BOUNDARY_DEFAULT_M if not np.isfinite(dk) else max(dk, self.BOUNDARY_MIN_M)
            b = math.radians(k * self.FACE_DEG + 0.5 * self.FACE_DEG)
            pts[k] = dk * math.cos(b), dk * math.sin(b)
        return pts

    def obstacles_body(self, t):
        def closest_on_segment(a, b, p):
            ab = b - a
            L2 = float(ab @ ab)
            u = 0.0 if L2 <= 0 else min(max(float((p - a) @ ab) / L2, 0.0), 1.0)
            return a + u * ab

        n = self.N_FACES
        ok = self.valid_faces(t)
        if not np.any(ok):
            return []
        pts = self.boundary_body(t, ok)
        out = []
        zero = np.zeros(2)
        for f in range(n):
            if ok[(f - 1) % n] or ok[f] or ok[(f + 1) % n]:
                a, b = pts[(f - 1) % n], pts[f]
                out.append((a, b, closest_on_segment(a, b, zero)))
        return out

    def _limit(self, t, p_ned, v_ned, yaw, v_des):
        from flightsim.avoidance import ned_to_body, body_to_ned

        cfg = self.config
        dt = 0.0 if self._t_prev is None else max(t - self._t_prev, 0.0)
        self._t_prev = t
        obstacles = self.obstacles_body(t)
        if not obstacles:
            return tuple(float(x) for x in v_des)
        a = self.ACCEL_CLAMP
        kp, margin = cfg.pos_kp, cfg.avoid_margin_m
        v_in = ned_to_body(v_des[:2], yaw)
        v = v_in.copy()
        backups = []
        moving = float(np.hypot(*v_in)) > 0
        for _s, _e, o in obstacles:
            no = float(np.hypot(*o))
            breach = margin - no
            if breach > cfg.avoid_backup_dz_m and no > 0:
                back = sqrt_controller(breach, kp, 0.4 * a, dt)
                backups.append(-o / no * back)
            if not moving or no <= 0:
                continue
            n_hat = o / no
            vmax = sqrt_controller(max(no - cfg.avoid_margin_m, 0.0), kp, a, dt)
            s = float(v @ n_hat)
            v = v + n_hat * (vmax - s) if s > vmax else v
        if backups and cfg.avoid_backup_spd_mps > 0:
            b = self._combine_backups(backups)
            nb = float(np.hypot(*b))
            if nb > cfg.avoid_backup_spd_mps:
                b *= cfg.avoid_backup_spd_mps / nb
            for i in range(2):
                if b[i] > 0:
                    v[i] = max(v[i], b[i])
                elif b[i] < 0:
                    v[i] = min(v[i], b[i])
        out = body_to_ned(v, yaw)
        v_in, v_out = v_des[:2], out
        amax = cfg.avoid_accel_max_mss
        if not (amax <= 0 or np.allclose(v_in, v_out)):
            if self._accel_mem is None or t - self._accel_mem_t > 0.2:
                self._accel_mem = v_in.copy()
            dv = v_out - self._accel_mem
            ndv = float(np.hypot(*dv))
            if ndv > amax * dt and ndv > 0:
                v_out = self._accel_mem + dv * (amax * dt / ndv)
            self._accel_mem = v_out.copy()
            self._accel_mem_t = t
        return float(v_out[0]), float(v_out[1]), float(v_des[2])


@pytest.mark.parametrize("cfg", [AvoidanceConfig(model="ardupilot"), EXACT,
                                 AvoidanceConfig(model="ardupilot", avoid_margin_m=4.0, avoid_backup_dz_m=0.0, prx_filt_hz=1.0)],
                         ids=["shipped", "no-filter-no-accel-limit", "wide-margin-backups"])
def test_ardupilot_slide_path_equals_the_obstacle_by_obstacle_loop(cfg):
    """Random ranges (near, far, unknown, clear), headings and demands: the velocity let through,
    the obstacles and the boundary are bit for bit those of the loop over obstacles."""
    rng = np.random.default_rng(7)
    fast, ref = ArduPilotAvoidance(cfg), _LoopArduPilot(cfg)
    t, n_diff_inputs, clipped = 0.0, 0, 0
    for step in range(3000):
        t += 1.0 / 120.0
        if step % 4 == 0 and rng.random() < 0.8:
            d = rng.choice([np.nan, np.inf, 0.5, 1.5, 2.5, 6.0, 15.0], 72, p=[0.3, 0.1, 0.1, 0.1, 0.15, 0.15, 0.1])
            d = np.where(np.isfinite(d), d * rng.uniform(0.8, 1.2, 72), d)
            msg = od(d)
            arrival = t + rng.uniform(0.0, 0.02)
            fast.receive(arrival, msg)
            ref.receive(arrival, msg)
        yaw = float(rng.uniform(-math.pi, math.pi))
        v_des = rng.normal(0.0, 4.0, 3) * (rng.random() < 0.9)
        p = rng.normal(0, 10, 3)
        a = fast.limit(t, p, v_des, yaw, v_des)
        b = ref.limit(t, p, v_des, yaw, v_des)
        assert a == b, (step, a, b)
        assert all(type(x) is float for x in a)
        clipped += not np.allclose(a[:2], v_des[:2])
        n_diff_inputs += 1
        if step % 50 == 0:
            ob_a, ob_b = fast.obstacles_body(t), ref.obstacles_body(t)
            assert len(ob_a) == len(ob_b)
            assert all(np.array_equal(x, y) for u, w in zip(ob_a, ob_b) for x, y in zip(u, w))
            assert np.array_equal(fast.boundary_points(t), ref.boundary_points(t))
    assert clipped > 300  # the avoidance did limit the demand often enough for the comparison to mean something
