"""The closed-loop bench's scenario variants (companion.bench.avoidance): written from the files they
change, only the named lines changed, loadable, and a typo refused."""

import pytest

from companion.bench import avoidance as A
from flightsim.scenario import load_scenario


@pytest.mark.parametrize("name", sorted(A.VARIANTS))
def test_speed_variants_change_only_the_speed_and_name(tmp_path, name):
    base_name, speed = A.VARIANTS[name]
    path, model = A.scenario_file(name, "ardupilot", tmp_path)
    assert model == "ardupilot" and path.parent == tmp_path
    sc, base = load_scenario(path), load_scenario(A.SCEN / f"{base_name}.toml")
    assert sc.vehicle.route.speed_mps == speed != base.vehicle.route.speed_mps
    assert sc.vehicle.route.waypoints == base.vehicle.route.waypoints
    assert sc.vehicle.start_ned_m == base.vehicle.start_ned_m
    assert [o.name for o in sc.world.obstacles] == [o.name for o in base.world.obstacles]
    assert sc.avoidance == base.avoidance
    assert name in path.read_text()
    # the base text but for the three lines the variant rewrites
    a, b = path.read_text().splitlines(), (A.SCEN / f"{base_name}.toml").read_text().splitlines()
    assert len(a) == len(b) and sum(x != y for x, y in zip(a, b)) == 3


def test_go_no_data_variant_of_a_speed_variant(tmp_path):
    path, model = A.scenario_file("quad_avoid_pole_6", "px4_go_no_data", tmp_path)
    sc = load_scenario(path)
    assert model == "px4" and sc.avoidance.cp_go_no_data and sc.vehicle.route.speed_mps == 6.0


def test_plain_scenarios_are_flown_from_their_file(tmp_path):
    assert A.scenario_file("quad_avoid_wall_3", "px4", tmp_path) == (A.SCEN / "quad_avoid_wall_3.toml", "px4")
    assert not list(tmp_path.iterdir())
    with pytest.raises(ValueError):
        A.run_all(1, 1, ["quad_avoid_pole_4"], ("ardupilot",))
