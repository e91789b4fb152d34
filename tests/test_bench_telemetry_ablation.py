"""bench.telemetry_ablation's scenario variants: the [telemetry] keys are set (replaced or added), the
paths made absolute, and the copy loads as a scenario with exactly those telemetry errors."""

from pathlib import Path

import pytest

from bench import telemetry_ablation as TA
from flightsim.scenario import load_scenario

SCEN = Path(__file__).resolve().parents[1] / "configs" / "scenarios"


@pytest.mark.parametrize("scenario", ["quad_approach", "fixedwing_pass"])
@pytest.mark.parametrize("variant", list(TA.VARIANTS))
def test_variant_copies_load_with_the_telemetry_set(tmp_path, scenario, variant):
    src = SCEN / f"{scenario}.toml"
    dst = tmp_path / "elsewhere" / f"{scenario}.toml"
    dst.parent.mkdir()
    dst.write_text(TA.variant_text(src.read_text(encoding="utf-8"), TA.VARIANTS[variant], src), encoding="utf-8")
    orig, copy = load_scenario(src), load_scenario(dst)
    for key, value in TA.VARIANTS[variant].items():
        assert getattr(copy.telemetry, key) == value
    untouched = set(vars(orig.telemetry)) - set(TA.VARIANTS[variant])
    assert {k: getattr(copy.telemetry, k) for k in untouched} == {k: getattr(orig.telemetry, k) for k in untouched}
    same = ("name", "seed", "duration_s", "fps", "sector_max_distance_m")
    assert all(getattr(copy.meta, k) == getattr(orig.meta, k) for k in same) and copy.camera == orig.camera
    assert copy.companion_config_path == orig.companion_config_path  # the fixed-wing's companion_config still found
    assert len(copy.world.obstacles) == len(orig.world.obstacles)


def test_a_scenario_without_a_telemetry_table_gets_one(tmp_path):
    text = '[scenario]\nname = "x"\n'
    out = TA.variant_text(text, {"position_noise_m": 0.0}, tmp_path / "x.toml")
    assert "[telemetry]\nposition_noise_m = 0.0" in out


def test_unknown_variant_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        TA.main(["--variants", "no such thing"])
    assert exc.value.code == 2
    assert "unknown variant" in capsys.readouterr().err
