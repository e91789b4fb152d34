"""The closed-loop bench's scenario variants (bench.avoidance): written from the files they
change, only the named lines changed, loadable, and a typo refused."""

import pytest

from bench import avoidance as A
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


def test_the_clear_route_keeps_off_everything_and_the_others_go_through_something():
    """quad_avoid_pass is what the no-stall target is judged on: its route (sampled every 0.1 m) keeps
    the body more than AVOID_MARGIN from every obstacle; every other avoidance scenario's route goes
    through one (the pilot's intent), so flown without the companion it must collide."""
    import numpy as np

    def route_clearance(name):
        sc = load_scenario(A.base_file(name))
        wps = np.array([sc.vehicle.start_ned_m] + [list(w) for w in sc.vehicle.route.waypoints], float)
        pts = np.concatenate([np.linspace(a, b, max(2, int(np.linalg.norm(b - a) / 0.1)))
                              for a, b in zip(wps[:-1], wps[1:])])
        pts = pts[pts[:, 2] < -1.0]  # in the air (the take-off starts on the ground)
        return min(sc.world.clearance(p)[0] for p in pts) - 0.35, sc.avoidance.avoid_margin_m

    for name in A.CLEAR_ROUTES:
        c, margin = route_clearance(name)
        assert c > margin, (name, c)
    for name in A.SCENARIOS:
        if name not in A.CLEAR_ROUTES and name not in A.VARIANTS:
            assert route_clearance(name)[0] < 0.0, name


def test_results_of_a_bench_run_in_parts_merge_in_order():
    a = {"runs": 20, "campaigns": {"x/ardupilot": {"v": 1}, "y/px4": {"v": 2}}, "no_companion": {"x": {"c": 20}}}
    b = {"runs": 20, "campaigns": {"y/px4": {"v": 3}}, "no_companion": {}}
    m = A.merge_results([a, b])
    assert m == {"runs": 20, "campaigns": {"x/ardupilot": {"v": 1}, "y/px4": {"v": 3}}, "no_companion": {"x": {"c": 20}}}
    with pytest.raises(ValueError):
        A.merge_results([a, dict(b, runs=8)])


def _campaign(dangerous_per_run, obstacle_cells=1000):
    """A closed-loop campaign's result as flightsim campaign writes it, with these dangerous clear cells per run."""
    runs = [{"seed": i + 1, "status": "ok", "key_figures": {"dangerous_clear": n / obstacle_cells}}
            for i, n in enumerate(dangerous_per_run)] + [{"seed": 99, "status": "failed", "key_figures": None}]
    return {"runs": runs, "aggregate": {"cells": {"dangerous_clears": sum(dangerous_per_run),
                                                  "obstacle": obstacle_cells * len(dangerous_per_run)}}}


def test_dangerous_clears_of_a_campaign_count_cells_and_runs():
    d = A.dangerous_clears(_campaign([0, 3, 0, 10]))
    assert d == {"cells": 13, "obstacle_cells": 4000, "rate": 13 / 4000, "runs_with": 2, "runs": 4}
    assert A.dangerous_clears(_campaign([]))["rate"] is None


def test_the_table_lists_dangerous_clears_and_a_dash_where_they_were_not_recorded():
    av = {"runs": 4, "collisions": 0, "collision_rate": 0.0, "collision_ci95": [0.0, 0.49], "stopped_short": 4,
          "stop_clearance_m": None, "min_clearance_m": None, "false_stops": 0, "progress": None, "data_while_pushing": None}
    res = {"runs": 4, "no_companion": {}, "campaigns": {
        "quad_avoid_pole/px4": {"scenario": "quad_avoid_pole", "model": "px4", "runs_ok": 4, "runs": 4, "avoidance": av,
                                "detection_in_view": 0.9, "dangerous_clears": A.dangerous_clears(_campaign([0, 3, 0, 10]))},
        "quad_avoid_wall_6/px4": {"scenario": "quad_avoid_wall_6", "model": "px4", "runs_ok": 4, "runs": 4, "avoidance": av,
                                  "detection_in_view": 0.9}}}
    rows = [line for line in A.markdown(res).splitlines() if line.startswith("| quad_avoid")]
    assert rows[0].endswith("| 13 / 4000 (0.3 %); 2 of 4 runs |")
    assert rows[1].endswith("| – |")
    assert "dangerous clears |" in A.markdown(res)


def test_before_and_after_cell_by_cell(tmp_path, capsys):
    """``--from-json AFTER --before BEFORE``: one row per cell of AFTER, each figure before → after; a cell
    BEFORE lacks shows dashes."""
    import json

    def av(coll, stop):
        return {"runs": 20, "collisions": coll, "collision_rate": coll / 20, "collision_ci95": [0.0, 0.2], "stopped_short": 20,
                "stop_clearance_m": {"mean": stop, "std": 0.1, "min": stop - 0.2, "n": 20},
                "min_clearance_m": {"mean": stop - 0.1, "std": 0.1, "min": stop - 0.3, "n": 20}, "false_stops": 0,
                "progress": {"mean": 0.68, "std": 0.0, "min": 0.67, "n": 20},
                "data_while_pushing": {"mean": 0.84, "std": 0.01, "min": 0.83, "n": 20}}

    def res(cells):
        return {"runs": 20, "no_companion": {}, "campaigns": {
            f"{s}/{m}": {"scenario": s, "model": m, "runs_ok": 20, "runs": 20, "avoidance": a, "detection_in_view": 0.9}
            for (s, m), a in cells.items()}}

    before = res({("quad_avoid_wall_6", "ardupilot"): av(0, 2.23)})
    after = res({("quad_avoid_wall_6", "ardupilot"): av(0, 2.09), ("quad_avoid_pole", "px4"): av(1, 1.8)})
    (tmp_path / "b.json").write_text(json.dumps(before))
    (tmp_path / "a.json").write_text(json.dumps(after))
    assert A.main(["--from-json", str(tmp_path / "a.json"), "--before", str(tmp_path / "b.json")]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| quad_avoid")]
    assert len(rows) == 2
    wall = [c.strip() for c in rows[0].strip("|").split("|")]
    assert wall[:4] == ["quad_avoid_wall_6", "ardupilot", "0 → 0", "20 → 20"]
    assert wall[4].startswith("2.23 ± 0.10") and "→ 2.09 ± 0.10" in wall[4]
    pole = [c.strip() for c in rows[1].strip("|").split("|")]
    assert pole[2] == "– → 1" and pole[-1] == "– → –"
    with pytest.raises(SystemExit):
        A.main(["--before", str(tmp_path / "b.json")])


def test_rescore_reads_the_dangerous_clears_from_each_campaign(tmp_path):
    import json

    (tmp_path / "campaign.json").write_text(json.dumps(_campaign([1, 0])))
    res = {"runs": 2, "no_companion": {}, "campaigns": {"quad_avoid_pole/px4": {
        "scenario": "quad_avoid_pole", "model": "px4", "dir": str(tmp_path), "avoidance": None}}}
    c = A.rescore(res)["campaigns"]["quad_avoid_pole/px4"]
    assert c["dangerous_clears"]["cells"] == 1 and c["dangerous_clears"]["runs_with"] == 1
    assert c["avoidance"] is None  # no trajectory to score again: the outcome stays as it was


@pytest.mark.parametrize("name", ["quad_avoid_wall_6", "quad_avoid_pole_3"])
def test_a_camera_variant_keeps_the_field_of_view_and_changes_nothing_else(tmp_path, name):
    path, model = A.scenario_file(name, "px4", tmp_path, (640, 480))
    assert model == "px4" and path.name == f"{name}_640x480.toml"
    sc, base = load_scenario(path), load_scenario(A.scenario_file(name, "px4", tmp_path / "base")[0])
    assert (sc.camera.width, sc.camera.height) == (640, 480) and (base.camera.width, base.camera.height) == (320, 240)
    # the same field of view and principal point (pixel centres: (c + 0.5) scales with the image)
    assert sc.camera.fx == pytest.approx(2 * base.camera.fx) and sc.camera.fy == pytest.approx(2 * base.camera.fy)
    assert sc.camera.cx + 0.5 == pytest.approx(2 * (base.camera.cx + 0.5))
    assert sc.camera.cy + 0.5 == pytest.approx(2 * (base.camera.cy + 0.5))
    assert sc.vehicle.route.speed_mps == base.vehicle.route.speed_mps and sc.avoidance == base.avoidance
    assert sc.meta.name == f"{name}_640x480"
    assert A.camera_tag((640, 480)) == "_640x480" and A.camera_tag(None) == ""


def test_a_camera_of_another_aspect_ratio_is_refused_before_any_flight(capsys):
    with pytest.raises(SystemExit) as e:
        A.main(["--camera", "640x360", "--scenarios", "quad_avoid_wall_3", "--runs", "1"])
    assert e.value.code == 2 and "aspect ratio" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        A.main(["--camera", "640", "--runs", "1"])
