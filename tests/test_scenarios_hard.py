"""Hard-flight scenarios and the quad route keys they need: hover and turn in place.

DESIGN.md §6–§7: avoidance needs ranges most where a single camera gains least — hovering close to
a wall, turning in place, head-on.  The scenarios in ``configs/scenarios/`` fly exactly that; these
tests check, against the simulator's own state, that the route keys do what they say
(``hold_s``: hover at a waypoint; ``turn_deg``: turn in place by a signed angle at ``yaw_rate_dps``)
and that each scenario flies the flight its comment promises (dynamics only, no rendering: fast).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from companion.config import from_mapping
from companion.errors import ConfigError
from companion.io.config_files import load_companion_config
from flightsim.dynamics import DynamicsConfig, FixedWingSim, QuadSim, RouteConfig, make_vehicle, stack_states
from flightsim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = sorted((ROOT / "configs" / "scenarios").glob("*.toml"))
HARD = ["quad_wall_hover", "quad_slalom", "quad_corner", "quad_yaw_spin", "fixedwing_tower"]
VARIANTS = ["quad_wall_hover_dim"]  # same world and route as quad_wall_hover, a third of the light


def _fly(cfg: DynamicsConfig, duration_s: float, dt: float = 0.05) -> dict:
    return stack_states(make_vehicle(cfg).run(duration_s, dt))


def _quad(route: RouteConfig, start=(0.0, 0.0, -5.0), heading=0.0) -> DynamicsConfig:
    return DynamicsConfig(aircraft="F450", start_ned_m=start, start_heading_deg=heading, route=route)


def _yaw_unwrapped_deg(h: dict) -> np.ndarray:
    return np.degrees(np.unwrap(h["rpy"][:, 2]))


# ---------------------------------------------------------------------- every scenario file


@pytest.mark.parametrize("path", SCENARIOS, ids=[p.stem for p in SCENARIOS])
def test_every_scenario_loads_and_passes_its_preflight_checks(path):
    sc = load_scenario(path)
    assert sc.meta.name == path.stem
    assert sc.world.obstacles or sc.world.ground_z is not None


def test_the_hard_scenarios_exist_with_their_worlds():
    names = {p.stem for p in SCENARIOS}
    assert set(HARD) <= names and {"quad_approach", "fixedwing_pass"} <= names
    for name in HARD:
        assert (ROOT / "configs" / "worlds" / f"{name}.toml").is_file()


@pytest.mark.parametrize("name", HARD + VARIANTS)
def test_hard_scenarios_are_short_and_every_key_is_commented(name):
    path = ROOT / "configs" / "scenarios" / f"{name}.toml"
    sc = load_scenario(path)
    assert sc.meta.duration_s <= 22.0  # short enough for campaigns of ≥ 8 seeds
    for p in (path, (path.parent / sc.meta.world).resolve()):
        for line in p.read_text(encoding="utf-8").splitlines():
            s = line.strip()
            if "=" in s and not s.startswith("#"):
                assert "#" in s, f"{p.name}: key without a comment: {s}"


# ---------------------------------------------------------------------- route keys: validation


@pytest.mark.parametrize(
    "route, needle",
    [
        ({"waypoints": [[5, 0, -5], [9, 0, -5]], "hold_s": [1.0]}, "hold_s must have one value per waypoint"),
        ({"waypoints": [[5, 0, -5]], "hold_s": [-1.0]}, r"hold_s\[0\]"),
        ({"waypoints": [[5, 0, -5]], "hold_s": [float("nan")]}, r"hold_s\[0\]"),
        ({"waypoints": [[5, 0, -5]], "turn_deg": [2000.0]}, r"turn_deg\[0\]"),
        ({"waypoints": [[5, 0, -5]], "turn_deg": [90.0, 90.0]}, "turn_deg must have one value per waypoint"),
        ({"waypoints": [[5, 0, -5]], "yaw_rate_dps": 60.0}, "yaw_rate_dps"),
        ({"waypoints": [[5, 0, -5]], "yaw_rate_dps": -5.0}, "yaw_rate_dps"),
        ({"waypoints": [[5, 0, -5]], "hold_s": 3.0}, "hold_s"),
        ({"waypoints": [[5, 0, -5]], "hold_time": [3.0]}, "hold_time"),
    ],
)
def test_bad_route_keys_name_the_key(route, needle):
    with pytest.raises(ConfigError, match=needle) as exc:
        from_mapping(DynamicsConfig, {"aircraft": "F450", "start_ned_m": [0, 0, -5], "route": route}, "vehicle")
    assert "[vehicle.route]" in str(exc.value)


@pytest.mark.parametrize("key, value", [("hold_s", [2.0]), ("turn_deg", [90.0]), ("yaw_rate_dps", 20.0)])
def test_the_j3cub_cannot_hover_or_turn_in_place(key, value):
    route = {"waypoints": [[1000, 0, -60]], key: value}
    with pytest.raises(ConfigError, match=f"route.{key}"):
        from_mapping(DynamicsConfig, {"aircraft": "J3Cub", "start_ned_m": [0, 0, -60], "route": route}, "vehicle")
    sim = FixedWingSim(DynamicsConfig(aircraft="J3Cub", start_ned_m=(0.0, 0.0, -60.0)))
    if key != "yaw_rate_dps":
        with pytest.raises(ValueError, match="quad only"):
            sim.set_route(RouteConfig(waypoints=((1000.0, 0.0, -60.0),), **{key: tuple(value)}))


def test_route_through_an_obstacle_is_refused_before_take_off(tmp_path):
    src = ROOT / "configs" / "scenarios" / "quad_slalom.toml"
    text = src.read_text(encoding="utf-8").replace(
        "waypoints = [[8.0, 2.5, -4.0], [16.0, -2.5, -4.0], [24.0, 2.5, -4.0]]", "waypoints = [[8.0, 2.5, -4.0], [24.0, 0.0, -4.0], [26.0, 2.5, -4.0]]"
    )
    text = text.replace('world = "../worlds/quad_slalom.toml"', f'world = "{(ROOT / "configs" / "worlds" / "quad_slalom.toml").as_posix()}"')
    bad = tmp_path / "bad.toml"
    bad.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as exc:
        load_scenario(bad)
    msg = str(exc.value)
    assert "route.waypoints[1]" in msg and "pole_2" in msg


# ---------------------------------------------------------------------- route keys: on JSBSim flights


def test_defaults_leave_a_route_flight_bit_identical():
    wps = ((10.0, 5.0, -5.0), (10.0, -5.0, -6.0))
    plain = _fly(_quad(RouteConfig(waypoints=wps, speed_mps=4.0)), 12.0)
    zeros = _fly(_quad(RouteConfig(waypoints=wps, speed_mps=4.0, hold_s=(0.0, 0.0), turn_deg=(0.0, 0.0), yaw_rate_dps=0.0)), 12.0)
    for key in ("p_ned", "v_ned", "rpy"):
        assert np.array_equal(plain[key], zeros[key])


def test_hold_s_hovers_at_the_waypoint_for_the_hold_time_then_goes_on():
    wp1, wp2 = np.array([6.0, 0.0, -5.0]), np.array([6.0, 6.0, -5.0])
    route = RouteConfig(waypoints=(tuple(wp1), tuple(wp2)), speed_mps=3.0, hold_s=(4.0, 0.0), face_travel=False)
    h = _fly(_quad(route), 13.0)
    t, p = h["time_s"], h["p_ned"]
    # the leg's reference (6 m at ≤ 3 m/s, 2 m/s², rest to rest) arrives at t = 3.5 s; the hover lasts 4 s
    hover = (t >= 3.5) & (t <= 7.5)
    assert np.linalg.norm(p[hover] - wp1, axis=1).max() <= 0.5
    # no move towards wp2 before the hold time is over, and it got there afterwards
    assert np.all(np.abs(p[t <= 7.5, 1]) < 0.05)
    assert p[(t > 8.0) & (t < 8.5), 1].max() > 0.1
    assert np.linalg.norm(p[-1] - wp2) < 0.5


@pytest.mark.parametrize("turn_deg, rate", [(360.0, 40.0), (-90.0, 30.0)])
def test_turn_deg_turns_in_place_by_the_commanded_angle(turn_deg, rate):
    wp = np.array([0.0, 0.0, -5.0])
    route = RouteConfig(waypoints=(tuple(wp),), hold_s=(0.5,), turn_deg=(turn_deg,), yaw_rate_dps=rate)
    dur = 0.5 + abs(turn_deg) / rate + 3.0
    h = _fly(_quad(route, start=tuple(wp), heading=20.0), dur)
    yaw = _yaw_unwrapped_deg(h)
    # the whole signed turn (a full circle is a full circle, not nothing), settled at the end
    assert yaw[-1] - yaw[0] == pytest.approx(turn_deg, abs=3.0)
    assert abs(yaw[-20:].max() - yaw[-20:].min()) < 1.0
    # not before the hold time was over
    assert np.all(np.abs(yaw[h["time_s"] <= 0.5] - 20.0) < 0.5)
    # at the commanded rate: the middle of the turn moves at ±rate
    rate_meas = np.gradient(yaw, h["time_s"])
    mid = (yaw - yaw[0]) / turn_deg
    steady = (mid > 0.25) & (mid < 0.75)
    assert np.median(rate_meas[steady]) == pytest.approx(math.copysign(rate, turn_deg), rel=0.1)
    # in place: negligible translation
    assert np.linalg.norm(h["p_ned"] - wp, axis=1).max() < 0.3


def test_hold_then_turn_then_face_the_next_leg():
    route = RouteConfig(waypoints=((6.0, 0.0, -5.0), (6.0, 8.0, -5.0)), speed_mps=3.0, hold_s=(1.0, 0.0), turn_deg=(-180.0, 0.0), yaw_rate_dps=40.0)
    sim = QuadSim(_quad(route))
    states = []
    while sim.busy and sim.time_s < 30.0:
        states.append(sim.step(0.05))
    h = stack_states(states + sim.run(1.0, 0.05))
    t, yaw, p = h["time_s"], _yaw_unwrapped_deg(h), h["p_ned"]
    # the leg's reference arrives at 3.5 s; 1 s of hover on the leg's heading, then the turn starts
    assert np.all(np.abs(yaw[t <= 4.5]) < 0.5)
    assert np.any(np.abs(yaw[(t > 4.5) & (t < 5.0)]) > 0.5)
    # −180° in place (to face south), then the shortest turn to face the next leg (east): −90° more
    assert np.all(np.diff(yaw) < 0.1)
    assert yaw[-1] == pytest.approx(-270.0, abs=3.0)
    turning = (yaw < -1.0) & (yaw > -265.0)
    assert np.linalg.norm(p[turning] - np.array([6.0, 0.0, -5.0]), axis=1).max() < 0.5
    assert np.linalg.norm(p[-1] - np.array([6.0, 8.0, -5.0])) < 0.5


def test_quad_api_rejects_bad_hold_and_turn():
    sim = QuadSim(_quad(RouteConfig()))
    for bad in (-1.0, float("inf"), 1e6):
        with pytest.raises(ValueError, match="hold"):
            sim.hold_for(bad)
    with pytest.raises(ValueError, match="delta_deg"):
        sim.turn_in_place(float("nan"))
    with pytest.raises(ValueError, match="rate_dps"):
        sim.turn_in_place(90.0, rate_dps=90.0)


# ---------------------------------------------------------------------- each scenario flies as described


def _scenario(name: str):
    return load_scenario(ROOT / "configs" / "scenarios" / f"{name}.toml")


def _distance_to(sc, obstacle: str, p: np.ndarray) -> np.ndarray:
    k = next(ob.index for ob in sc.world.obstacles if ob.name == obstacle)
    return np.array([sc.world.signed_distances(x)[k] for x in p])


def _quad_max_distance() -> float:
    return load_companion_config(ROOT / "configs" / "companion.toml").sectors.max_distance_m


def test_quad_wall_hover_hovers_3_to_5_m_from_the_wall_for_6_s_or_more():
    sc = _scenario("quad_wall_hover")
    assert sc.vehicle.route.speed_mps == 4.0 and sc.camera.width == 320
    h = _fly(sc.vehicle, sc.meta.duration_s, 0.1)
    d = _distance_to(sc, "warehouse", h["p_ned"])
    assert d[0] <= _quad_max_distance()  # the wall is within range from the start
    hovering = (d >= 3.0) & (d <= 5.0) & (np.linalg.norm(h["v_ned"], axis=1) < 0.5)
    assert hovering.sum() * 0.1 >= 6.0
    assert np.linalg.norm(h["v_ned"], axis=1).max() == pytest.approx(4.0, abs=0.5)


def test_quad_slalom_stops_and_turns_in_place_beside_each_pole():
    sc = _scenario("quad_slalom")
    radii = [ob.radius for ob in sc.world.obstacles if ob.is_cylinder]
    assert len(radii) >= 3 and min(radii) >= 0.2 - 1e-9 and max(radii) <= 0.6 + 1e-9
    h = _fly(sc.vehicle, sc.meta.duration_s, 0.05)
    speed = np.linalg.norm(h["v_ned"], axis=1)
    yaw = _yaw_unwrapped_deg(h)
    rate = np.abs(np.gradient(yaw, h["time_s"]))
    turning_in_place = (rate > 15.0) & (speed < 0.8)
    for wp in sc.vehicle.route.waypoints:
        near = np.linalg.norm(h["p_ned"] - np.array(wp), axis=1) < 0.8
        assert (turning_in_place & near).sum() * 0.05 >= 0.8, f"no turn in place at {wp}"
    for ob in sc.world.obstacles:
        assert _distance_to(sc, ob.name, h["p_ned"]).min() > 1.0


def test_quad_corner_turns_the_corner_and_stops_short_of_the_second_building():
    sc = _scenario("quad_corner")
    h = _fly(sc.vehicle, sc.meta.duration_s, 0.1)
    yaw = _yaw_unwrapped_deg(h)
    assert yaw[-1] - yaw[0] == pytest.approx(90.0, abs=3.0)
    a = _distance_to(sc, "block_a", h["p_ned"])
    b = _distance_to(sc, "block_b", h["p_ned"])
    assert a.min() >= 4.0 and (a < 6.0).sum() * 0.1 >= 8.0  # along block_a, ~5 m from it, for a while
    assert 4.0 <= b[-1] <= 6.0 and np.linalg.norm(h["v_ned"][-1]) < 0.5


def test_quad_yaw_spin_turns_a_full_circle_in_place_among_obstacles():
    sc = _scenario("quad_yaw_spin")
    h = _fly(sc.vehicle, sc.meta.duration_s, 0.05)
    yaw = _yaw_unwrapped_deg(h)
    assert yaw.max() - yaw.min() >= 355.0
    spin = (yaw - yaw[0] > 5.0) & (yaw - yaw[0] < 355.0)
    p_spin = h["p_ned"][spin]
    assert np.linalg.norm(p_spin - p_spin.mean(axis=0), axis=1).max() < 0.3
    assert np.linalg.norm(h["p_ned"][-1, :2] - p_spin.mean(axis=0)[:2]) > 4.0  # then a short flight
    # obstacles at several bearings within 5–30 m of the spin point
    c = p_spin.mean(axis=0)
    bearings = []
    for ob in sc.world.obstacles:
        d = sc.world.signed_distances(c)[ob.index]
        if 5.0 <= d <= 30.0:
            bearings.append(math.degrees(math.atan2(ob.centre[1] - c[1], ob.centre[0] - c[0])) % 360.0)
    assert len(bearings) >= 5
    assert np.diff(np.sort(bearings)).max() < 120.0 and (360.0 - max(bearings) + min(bearings)) < 120.0


def test_fixedwing_tower_flies_fast_past_towers_beside_the_track():
    sc = _scenario("fixedwing_tower")
    assert sc.companion_config_path is not None and sc.companion_config_path.name == "companion_fixedwing.toml"
    max_d = load_companion_config(sc.companion_config_path).sectors.max_distance_m
    h = _fly(sc.vehicle, sc.meta.duration_s, 0.25)
    assert h["airspeed_mps"].min() >= 25.0
    towers = [ob for ob in sc.world.obstacles if ob.is_cylinder]
    passed = 0
    for ob in towers:
        d = np.array([sc.world.signed_distances(x)[ob.index] for x in h["p_ned"]])
        lateral = abs(ob.centre[1] - h["p_ned"][:, 1].mean()) - ob.radius
        assert lateral > 5.0  # off the track
        if d.min() < 40.0 and d[0] > max_d:
            passed += 1
    assert passed >= 2


def test_scenario_runs_are_reproducible_with_the_new_keys():
    sc = _scenario("quad_yaw_spin")
    a = _fly(sc.vehicle, 6.0, 0.1)
    b = _fly(dataclasses.replace(sc.vehicle), 6.0, 0.1)
    assert np.array_equal(a["p_ned"], b["p_ned"]) and np.array_equal(a["rpy"], b["rpy"])


# ---------------------------------------------------------------------- make bench: the SITL campaigns


def test_bench_campaigns_cover_every_flight_scenario_with_its_aircraft_class():
    from bench.sitl_bench import CAMPAIGNS

    assert set(HARD) | {"quad_approach", "fixedwing_pass"} == set(CAMPAIGNS)
    for name, (kind, what) in CAMPAIGNS.items():
        assert _scenario(name).vehicle.kind == kind and what


def test_bench_run_all_checks_its_arguments_before_flying():
    from bench.sitl_bench import run_all

    with pytest.raises(ValueError, match="quad_nope"):
        run_all(scenarios=["quad_nope"])
    with pytest.raises(ValueError, match="quad_runs"):
        run_all(quad_runs=0, scenarios=["quad_slalom"])


def test_bench_markdown_lists_the_scenarios_with_unknown_and_target_thresholds():
    from bench.sitl_bench import markdown

    agg = {"runs": 8, "runs_ok": 8, "cells": {"obstacle": 1000, "unknown_in_obstacle_cells": 125},
           "pooled_rates": {"detection": 0.875, "valid_range": 0.8, "too_near": 0.05, "false_obstacle_clear_cells": 0.004},
           "targets": [{"name": "no false obstacle in clear sectors", "op": ">=", "threshold": 0.98, "pooled": 0.99, "n": 300, "met": True},
                       {"name": "dangerous clear", "op": "<=", "threshold": 0.005, "pooled": 0.0, "n": 1000, "met": True}],
           "range_error": {}, "latency": {"p50_ms": 30.0, "p99_ms": 45.0}, "nees": {"mean": 2.0, "band": [0.9, 1.1]}}
    res = {"lockstep": {"scenario": "quad_approach", "duration_s": 14.0, "frames": 420, "wall_s": 9.46, "wall_with_startup_s": 13.8,
                        "realtime_factor": 1.48},
           "campaigns": {"quad_yaw_spin": {"aggregate": agg, "companion_config": None}}}
    text = markdown(res)
    assert "- `quad_yaw_spin`: F450 turning a full circle in place" in text
    row = next(line for line in text.splitlines() if line.startswith("| quad_yaw_spin |"))
    assert "| 87.50 % | 12.50 % |" in row
    assert "99.00 % (≥ 98 %) ✓" in row and "0.00 % (≤ 0.5 %) ✓" in row


def test_dim_variant_differs_from_quad_wall_hover_only_in_the_light():
    base, dim = _scenario("quad_wall_hover"), _scenario("quad_wall_hover_dim")
    assert dim.world.source == base.world.source and dim.vehicle == base.vehicle and dim.camera == base.camera
    assert dim.render.gain < 0.5 * base.render.gain
    assert dataclasses.replace(dim.meta, name=base.meta.name) == base.meta
