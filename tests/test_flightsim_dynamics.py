"""flightsim.dynamics: JSBSim J3Cub and F450 with our autopilots."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import from_mapping
from companion.errors import ConfigError
from flightsim.dynamics import (
    AtmosphereConfig,
    DynamicsConfig,
    FixedWingSim,
    LocalNED,
    QuadSim,
    RouteConfig,
    VehicleState,
    make_vehicle,
    stack_states,
)


def _wrap_deg(a):
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def _cub(**kw) -> FixedWingSim:
    base = dict(aircraft="J3Cub", start_ned_m=(0.0, 0.0, -150.0), start_heading_deg=30.0, start_airspeed_mps=30.0)
    base.update(kw)
    return FixedWingSim(DynamicsConfig(**base))


# ---------------------------------------------------------------------- fixed-wing


def test_j3cub_starts_trimmed_at_its_start_pose():
    sim = _cub()
    s = sim.state()
    assert s.time_s == 0.0
    np.testing.assert_allclose(s.p_ned, [0.0, 0.0, -150.0], atol=0.01)
    assert s.airspeed_mps == pytest.approx(30.0, abs=0.05)
    assert math.degrees(s.rpy[2]) == pytest.approx(30.0, abs=0.01)
    np.testing.assert_allclose(s.v_ned, 30.0 * np.array([math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0]), atol=0.05)
    assert not s.on_ground
    assert sim.jsbsim_messages is not None  # JSBSim's chatter is captured, not printed


def test_j3cub_holds_altitude_and_heading_60s_calm_air():
    sim = _cub()
    states = sim.run(60.0, 0.25)
    h = stack_states(states)
    assert h["time_s"][-1] == pytest.approx(60.0)
    assert np.max(np.abs(-h["p_ned"][:, 2] - 150.0)) <= 5.0
    assert np.max(np.abs(_wrap_deg(np.degrees(h["rpy"][:, 2]) - 30.0))) <= 3.0
    assert np.max(np.abs(h["airspeed_mps"] - 30.0)) <= 2.0
    # it really flew: 60 s at 30 m/s along 030°
    assert np.linalg.norm(h["p_ned"][-1, :2]) == pytest.approx(1800.0, rel=0.03)
    # the state is self-consistent: velocity integrates to the track
    dp = np.diff(h["p_ned"], axis=0) / 0.25
    vmid = 0.5 * (h["v_ned"][1:] + h["v_ned"][:-1])
    assert np.max(np.abs(dp - vmid)) < 0.05


def test_j3cub_turns_to_new_heading_then_follows_waypoints():
    sim = _cub()
    sim.step(2.0)
    sim.command(heading_deg=120.0)
    h = stack_states(sim.run(30.0, 0.5))
    hdg = np.degrees(h["rpy"][:, 2])
    assert np.max(np.abs(np.degrees(h["rpy"][:, 0]))) <= 35.0  # bank limit (30°) plus overshoot
    tail = h["time_s"] >= h["time_s"][0] + 20.0
    assert np.max(np.abs(_wrap_deg(hdg[tail] - 120.0))) <= 3.0
    # route: a waypoint 1 km ahead-left, then a leg due east at 170 m
    p = sim.state().p_ned
    wp1 = (p[0] + 300.0, p[1] + 900.0, -170.0)
    wp2 = (wp1[0], wp1[1] + 1500.0, -170.0)
    sim.set_route(RouteConfig(waypoints=(wp1, wp2)))
    states = sim.run(95.0, 0.5)
    h = stack_states(states)
    d1 = np.linalg.norm(h["p_ned"][:, :2] - np.array(wp1[:2]), axis=1)
    assert d1.min() < 40.0  # flew by the first waypoint
    assert sim.waypoint_index >= 1
    # settled on the second leg: on the line (north = wp1 north), at its altitude
    on_leg2 = (h["p_ned"][:, 1] > wp1[1] + 600.0) & (h["p_ned"][:, 1] < wp2[1])
    assert on_leg2.sum() >= 20
    assert np.max(np.abs(h["p_ned"][on_leg2, 0] - wp1[0])) < 5.0
    assert np.max(np.abs(-h["p_ned"][on_leg2, 2] - 170.0)) < 5.0


def test_j3cub_crabs_into_a_crosswind():
    sim = _cub(start_heading_deg=0.0, atmosphere=AtmosphereConfig(wind_ned_mps=(0.0, 6.0, 0.0)))
    s0 = sim.state()
    assert s0.airspeed_mps == pytest.approx(30.0, abs=0.05)  # trimmed relative to the air
    np.testing.assert_allclose(s0.v_ned, [30.0, 6.0, 0.0], atol=0.05)
    sim.set_route([(3000.0, 0.0, -150.0)])
    s = sim.run(40.0, 1.0)[-1]
    assert abs(s.p_ned[1]) < 5.0  # held the line due north...
    assert math.degrees(s.rpy[2]) == pytest.approx(-math.degrees(math.asin(6.0 / 30.0)), abs=2.0)  # ...crabbing left


# ---------------------------------------------------------------------- quadcopter


@pytest.fixture(scope="module")
def quad_hover():
    """An F450 that took off from the ground to 10 m and finished the climb."""
    sim = QuadSim(DynamicsConfig(aircraft="F450", start_ned_m=(0.0, 0.0, 0.0), start_heading_deg=0.0))
    s0 = sim.state()
    sim.takeoff(10.0)
    t = 0.0
    while sim.busy and t < 20.0:
        t += 0.5
        sim.step(0.5)
    assert not sim.busy, "take-off did not finish in 20 s"
    sim.step(2.0)
    return sim, s0


def test_f450_starts_on_its_gear_at_rest(quad_hover):
    _, s0 = quad_hover
    assert s0.on_ground
    assert -0.3 < s0.p_ned[2] < 0.0
    np.testing.assert_allclose(s0.v_ned, 0.0, atol=1e-9)


def test_f450_hovers_within_half_a_metre_for_20s(quad_hover):
    sim, _ = quad_hover
    h = stack_states(sim.run(20.0, 0.1))
    err = np.linalg.norm(h["p_ned"] - np.array([0.0, 0.0, -10.0]), axis=1)
    assert err.max() <= 0.5
    assert not h["on_ground"].any()


def test_f450_flies_a_line_at_5mps_and_stops_on_target(quad_hover):
    sim, _ = quad_hover
    target = np.array([40.0, 30.0, -12.0])
    start = sim.state().p_ned
    sim.goto(target, speed_mps=5.0)
    states = []
    t_end = sim.time_s + 40.0
    while sim.busy and sim.time_s < t_end:
        states.append(sim.step(0.1))
    assert not sim.busy
    states += sim.run(3.0, 0.1)
    h = stack_states(states)
    speed = np.linalg.norm(h["v_ned"], axis=1)
    assert 4.7 <= speed.max() <= 5.4
    # it faced along the leg (forward camera) while cruising
    cruising = speed > 4.5
    course = math.degrees(math.atan2(target[1] - start[1], target[0] - start[0]))
    assert np.max(np.abs(_wrap_deg(np.degrees(h["rpy"][cruising, 2]) - course))) < 3.0
    # stayed on the line and stopped within 1 m of the target
    u = (target - start) / np.linalg.norm(target - start)
    rel = h["p_ned"] - start
    off_line = np.linalg.norm(rel - np.outer(rel @ u, u), axis=1)
    assert off_line.max() < 1.0
    assert np.linalg.norm(h["p_ned"][-1] - target) <= 1.0
    assert np.linalg.norm(h["v_ned"][-1]) < 0.3


def test_f450_route_from_config_takes_off_and_flies_it():
    route = RouteConfig(waypoints=((0.0, 0.0, -5.0), (15.0, 0.0, -5.0)), speed_mps=3.0)
    sim = make_vehicle(DynamicsConfig(aircraft="F450", start_ned_m=(0.0, 0.0, 0.0), route=route))
    assert isinstance(sim, QuadSim)
    while sim.busy and sim.time_s < 30.0:
        sim.step(0.5)
    s = sim.step(2.0)
    assert np.linalg.norm(s.p_ned - np.array([15.0, 0.0, -5.0])) < 0.5


# ---------------------------------------------------------------------- determinism, wind, config


def _turbulent(aircraft: str, seed: int) -> list[VehicleState]:
    start = (0.0, 0.0, -120.0) if aircraft == "J3Cub" else (0.0, 0.0, -10.0)
    atm = AtmosphereConfig(wind_ned_mps=(2.0, -3.0, 0.0), turbulence="milspec", turbulence_wind_20ft_mps=8.0, turbulence_severity=4)
    sim = make_vehicle(DynamicsConfig(aircraft=aircraft, start_ned_m=start, seed=seed, atmosphere=atm))
    return sim.run(10.0, 0.5)


@pytest.mark.parametrize("aircraft", ["J3Cub", "F450"])
def test_same_seed_same_trajectory_with_turbulence(aircraft):
    a = _turbulent(aircraft, 11)
    b = _turbulent(aircraft, 11)
    c = _turbulent(aircraft, 12)
    assert all(x == y for x, y in zip(a, b)) and len(a) == len(b)
    assert any(x != y for x, y in zip(a, c))


def test_turbulence_actually_disturbs_the_cub():
    calm = _cub(start_ned_m=(0.0, 0.0, -120.0), start_heading_deg=0.0).run(10.0, 0.5)
    rough = _turbulent("J3Cub", 11)
    roll_calm = max(abs(s.rpy[0]) for s in calm)
    roll_rough = max(abs(s.rpy[0]) for s in rough)
    assert roll_calm < math.radians(0.5) < roll_rough


def test_unknown_aircraft_is_a_config_error_naming_it_and_the_allowed_ones():
    with pytest.raises(ConfigError) as exc:
        DynamicsConfig(aircraft="Cessna172")
    msg = str(exc.value)
    assert "Cessna172" in msg and "J3Cub" in msg and "F450" in msg
    with pytest.raises(ConfigError, match="Cessna172"):
        from_mapping(DynamicsConfig, {"aircraft": "Cessna172"}, "vehicle")


@pytest.mark.parametrize(
    "mapping, needle",
    [
        ({"aircraft": "J3Cub", "start_ned_m": [0, 0, -5]}, "start_ned_m"),
        ({"aircraft": "J3Cub", "start_airspeed_mps": 80}, "start_airspeed_mps"),
        ({"aircraft": "F450", "start_ned_m": [0, 0, 3]}, "below the ground"),
        ({"atmosphere": {"turbulence": "hurricane"}}, "turbulence"),
        ({"atmosphere": {"wind_ned_mps": [1, 2]}}, "wind_ned_mps"),
        ({"fixedwing": {"max_bank_deg": 80}}, "max_bank_deg"),
        ({"quad": {"hover_throttle": 1.5}}, "hover_throttle"),
        ({"sim_rate_hz": 100, "fixedwing": {"control_rate_hz": 30}}, "control_rate_hz"),
        ({"route": {"waypoints": [[0, 0]]}}, "waypoints"),
        ({"aircraft": "F450", "route": {"waypoints": [[5, 0, -5]], "hold_s": [1.0, 2.0]}}, "hold_s"),
        ({"aircraft": "F450", "route": {"waypoints": [[5, 0, -5]], "turn_deg": [1e4]}}, "turn_deg"),
        ({"aircraft": "F450", "route": {"waypoints": [[5, 0, -5]], "yaw_rate_dps": 90.0}}, "yaw_rate_dps"),
        ({"aircraft": "J3Cub", "route": {"waypoints": [[900, 0, -100]], "hold_s": [5.0]}}, "hold_s"),
        ({"seed": -1}, "seed"),
        ({"aircraft": "J3Cub", "wind": [0, 0, 0]}, "wind"),
    ],
)
def test_bad_config_names_the_key(mapping, needle):
    with pytest.raises(ConfigError, match=needle):
        from_mapping(DynamicsConfig, mapping, "vehicle")


def test_config_from_toml_like_mapping():
    cfg = from_mapping(
        DynamicsConfig,
        {
            "aircraft": "F450",
            "start_ned_m": [1, 2, 0],
            "seed": 3,
            "atmosphere": {"wind_ned_mps": [0, 3, 0], "turbulence": "milspec", "turbulence_wind_20ft_mps": 5},
            "route": {"waypoints": [[0, 0, -5], [10, 0, -5]], "speed_mps": 4},
        },
        "vehicle",
    )
    assert cfg.kind == "quad" and cfg.route.waypoints[1] == (10.0, 0.0, -5.0)
    with pytest.raises(ConfigError, match="FixedWingSim|QuadSim"):
        FixedWingSim(cfg)


def test_step_lands_on_exact_frame_times():
    sim = _cub()
    assert sim.step(until=1.0 / 30.0).time_s == pytest.approx(1.0 / 30.0, abs=1e-12)
    for k in range(2, 31):
        assert abs(sim.step(until=k / 30.0).time_s - k / 30.0) < 1e-12
    assert sim.step(0.5).time_s == pytest.approx(1.5, abs=1e-12)
    with pytest.raises(ValueError):
        sim.step(until=0.5)
    with pytest.raises(ValueError):
        sim.step(0.1, until=2.0)


def test_local_ned_round_trip():
    w = LocalNED(47.4, 8.5, 400.0)
    for p in [(0.0, 0.0, 0.0), (1234.5, -987.6, -150.0), (-20.0, 3000.0, 12.0)]:
        lat, lon, alt = w.to_geodetic(*p)
        np.testing.assert_allclose(w.from_geodetic(lat, lon, alt), p, atol=1e-6)
    lat, lon, alt = w.to_geodetic(0.0, 0.0, -100.0)
    assert math.degrees(lat) == pytest.approx(47.4, abs=1e-9) and alt == pytest.approx(500.0, abs=1e-6)
    # 1 km north is ~0.009° of latitude
    lat, _, _ = w.to_geodetic(1000.0, 0.0, 0.0)
    assert math.degrees(lat) - 47.4 == pytest.approx(1000.0 / 111_200.0, rel=0.01)
