"""A scenario flown at another camera resolution (flightsim.scenario.scenario_at_camera, `flightsim
campaign --camera`): the same field of view, the same flight, paths that still resolve, and bad
sizes refused with a clear error."""

from pathlib import Path

import pytest

from companion.config import ConfigError
from flightsim.cli import main as flightsim_main
from flightsim.scenario import load_scenario, parse_camera_size, scale_camera_text, scenario_at_camera

SCEN = Path(__file__).resolve().parents[1] / "configs" / "scenarios"


@pytest.mark.parametrize("name", ["quad_slalom", "fixedwing_tower"])
def test_the_variant_keeps_the_field_of_view_and_the_flight(tmp_path, name):
    src = SCEN / f"{name}.toml"
    path = scenario_at_camera(src, (640, 480), tmp_path / "elsewhere")
    assert path == tmp_path / "elsewhere" / f"{name}_640x480.toml"
    sc, base = load_scenario(path), load_scenario(src)  # the world resolves from its new place
    k = 640 / base.camera.width
    assert (sc.camera.width, sc.camera.height) == (640, 480)
    assert sc.camera.fx == pytest.approx(k * base.camera.fx, abs=0.01) and sc.camera.fy == pytest.approx(k * base.camera.fy, abs=0.01)
    assert sc.camera.cx + 0.5 == pytest.approx(k * (base.camera.cx + 0.5), abs=0.01)
    assert sc.camera.cy + 0.5 == pytest.approx(k * (base.camera.cy + 0.5), abs=0.01)
    assert sc.meta.name == f"{base.meta.name}_640x480" and sc.meta.seed == base.meta.seed
    assert sc.vehicle == base.vehicle and [o.name for o in sc.world.obstacles] == [o.name for o in base.world.obstacles]
    assert sc.companion_config_path == base.companion_config_path  # the fixed-wing's own companion TOML still found
    assert (base.companion_config_path is not None) == name.startswith("fixedwing")


def test_bad_sizes_are_refused():
    assert parse_camera_size("640x480") == (640, 480) and parse_camera_size(" 1280X960 ") == (1280, 960)
    for bad in ("640", "640x", "x480", "8x6", "640x480x3", "-640x480"):
        with pytest.raises(ConfigError, match="WIDTHxHEIGHT"):
            parse_camera_size(bad)
    with pytest.raises(ConfigError, match="aspect ratio"):
        scale_camera_text((SCEN / "quad_slalom.toml").read_text(encoding="utf-8"), (640, 360))


def test_campaign_refuses_a_bad_camera_before_flying(tmp_path, capsys):
    rc = flightsim_main(["campaign", str(SCEN / "quad_slalom.toml"), "--runs", "1", "--camera", "640x360",
                         "--out", str(tmp_path / "c")])
    assert rc == 2 and "aspect ratio" in capsys.readouterr().err
    assert not (tmp_path / "c" / "runs").exists()
