"""A scenario names its companion configuration (``[scenario] companion_config``): validated when the
scenario loads, and the default of ``flightsim sitl --config``, ``flightsim campaign
--companion-config`` and ``flightsim score --companion-config``.  Fast: no flight is flown."""

import json
import re
from pathlib import Path

import pytest

from companion.errors import ConfigError
from flightsim import campaign as C
from flightsim import cli as fcli
from flightsim.cli import main as flightsim_main
from flightsim.scenario import DEFAULT_COMPANION_CONFIG, companion_config_of, default_companion_config, load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "configs" / "scenarios"
FIXEDWING_CFG = (ROOT / "configs" / "companion_fixedwing.toml").resolve()


def scenario_with(tmp_path: Path, companion_config: str | None, name: str = "quad_approach", out: str = "s.toml") -> Path:
    """A copy of a shipped scenario (world path made absolute) with ``companion_config`` set (or removed)."""
    text = (SCEN / f"{name}.toml").read_text()
    text = re.sub(r'^world = "\.\./worlds/', f'world = "{(ROOT / "configs" / "worlds").as_posix()}/', text, flags=re.M)
    text = re.sub(r"^companion_config = .*\n(^\s+#.*\n)?", "", text, flags=re.M)
    if companion_config is not None:
        text = text.replace("[scenario]\n", f'[scenario]\ncompanion_config = "{companion_config}"\n', 1)
    p = tmp_path / out
    p.write_text(text)
    return p


def test_shipped_fixedwing_pass_names_the_fixed_wing_config():
    sc = load_scenario(SCEN / "fixedwing_pass.toml")
    assert sc.companion_config_path == FIXEDWING_CFG
    assert default_companion_config(SCEN / "fixedwing_pass.toml") == FIXEDWING_CFG
    assert load_scenario(SCEN / "quad_approach.toml").companion_config_path is None
    assert default_companion_config(SCEN / "quad_approach.toml") is None


def test_companion_config_is_relative_to_the_scenario_file(tmp_path):
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "mine.toml").write_text("[sectors]\nmax_distance_m = 80.0\n")
    (tmp_path / "scen").mkdir()
    p = scenario_with(tmp_path / "scen", "../cfg/mine.toml")
    assert load_scenario(p).companion_config_path == (tmp_path / "cfg" / "mine.toml").resolve()
    # an explicit choice always wins, even over a scenario that names one
    assert default_companion_config(p, "other.toml") == Path("other.toml")


def test_missing_companion_config_stops_before_take_off(tmp_path, capsys):
    p = scenario_with(tmp_path, "../nowhere/companion.toml")
    with pytest.raises(ConfigError, match=r"\[scenario\] companion_config = '\.\./nowhere/companion\.toml': no such file"):
        load_scenario(p)
    with pytest.raises(ConfigError, match="no such file"):
        default_companion_config(p)
    assert flightsim_main(["fly", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "companion_config" in capsys.readouterr().err and not (tmp_path / "o" / "truth.npz").exists()
    bad_type = scenario_with(tmp_path, None, out="t.toml")
    bad_type.write_text(bad_type.read_text().replace("[scenario]\n", "[scenario]\ncompanion_config = 3\n", 1))
    with pytest.raises(ConfigError, match="companion_config"):
        load_scenario(bad_type)


# ---------------------------------------------------------------------- flightsim sitl ----------
class _Stop(ConfigError):
    pass


@pytest.fixture
def fake_run_sitl(monkeypatch):
    """flightsim.sitl.run_sitl replaced by a recorder that stops the command (exit 2) before any flight."""
    import flightsim.sitl

    calls = []

    def fake(scenario, out, **kw):
        calls.append(kw)
        raise _Stop("stopped by the test")

    monkeypatch.setattr(flightsim.sitl, "run_sitl", fake)
    return calls


def test_sitl_uses_the_scenarios_companion_config_unless_given(tmp_path, fake_run_sitl, capsys):
    out = str(tmp_path / "o")
    assert flightsim_main(["sitl", str(SCEN / "fixedwing_pass.toml"), "--out", out]) == 2
    assert Path(fake_run_sitl[-1]["companion_config"]) == FIXEDWING_CFG
    mine = tmp_path / "mine.toml"
    mine.write_text("")
    assert flightsim_main(["sitl", str(SCEN / "fixedwing_pass.toml"), "--out", out, "--config", str(mine)]) == 2
    assert Path(fake_run_sitl[-1]["companion_config"]) == mine
    # a scenario without the key: run_sitl gets None and picks configs/companion.toml itself
    assert flightsim_main(["sitl", str(SCEN / "quad_approach.toml"), "--out", out]) == 2
    assert fake_run_sitl[-1]["companion_config"] is None
    # a scenario naming a missing file stops before run_sitl
    n = len(fake_run_sitl)
    assert flightsim_main(["sitl", str(scenario_with(tmp_path, "gone.toml")), "--out", out]) == 2
    assert len(fake_run_sitl) == n and "gone.toml" in capsys.readouterr().err


# ---------------------------------------------------------------------- flightsim campaign ------
def record_config(job: C.RunJob) -> dict:
    """A run that only reports the companion configuration it was given (no flight)."""
    return {"seed": job.seed, "dir": job.run_dir, "status": "failed", "error": f"config {job.companion_config}",
            "wall_s": 0.0, "score": None}


def test_campaign_uses_the_scenarios_companion_config_unless_given(tmp_path):
    c = C.run_campaign(SCEN / "fixedwing_pass.toml", tmp_path / "a", runs=1, workers=1, mode="replay", run_fn=record_config)
    assert Path(c["companion_config"]) == FIXEDWING_CFG and c["runs"][0]["error"] == f"config {FIXEDWING_CFG}"
    c = C.run_campaign(SCEN / "fixedwing_pass.toml", tmp_path / "b", runs=1, workers=1, mode="replay",
                       companion_config=ROOT / "configs" / "companion.toml", run_fn=record_config)
    assert Path(c["companion_config"]) == (ROOT / "configs" / "companion.toml").resolve()
    c = C.run_campaign(SCEN / "quad_approach.toml", tmp_path / "c", runs=1, workers=1, mode="replay", run_fn=record_config)
    assert Path(c["companion_config"]) == DEFAULT_COMPANION_CONFIG
    with pytest.raises(ConfigError, match="companion_config"):
        C.run_campaign(scenario_with(tmp_path, "gone.toml"), tmp_path / "d", runs=1, workers=1, mode="replay",
                       run_fn=record_config)
    assert not (tmp_path / "d").exists()


# ---------------------------------------------------------------------- flightsim score ---------
def test_score_finds_the_companion_config_of_the_run(tmp_path):
    mine = tmp_path / "mine.toml"
    mine.write_text("")
    # SITL run: the --config of the recorded companion command is the one the run used
    sitl = tmp_path / "sitl"
    sitl.mkdir()
    (sitl / "sitl.json").write_text(json.dumps({"scenario_file": str(SCEN / "fixedwing_pass.toml"),
                                                "companion_command": ["python", "-m", "companion", "run", "--config", str(mine)]}))
    rec = fcli._run_record(sitl)
    assert rec["scenario_file"] == str(SCEN / "fixedwing_pass.toml")
    assert fcli._score_companion_config(None, None, rec) == str(mine)
    assert fcli._score_companion_config("given.toml", None, rec) == "given.toml"
    # a fly export (flight.json names only the scenario): the scenario's companion_config
    fly = tmp_path / "fly"
    fly.mkdir()
    (fly / "flight.json").write_text(json.dumps({"scenario_file": str(SCEN / "fixedwing_pass.toml")}))
    assert fcli._score_companion_config(None, None, fcli._run_record(fly)) == FIXEDWING_CFG
    assert fcli._score_companion_config(None, str(SCEN / "quad_approach.toml"), fcli._run_record(fly)) is None
    # a campaign's run directory: campaign.json two levels up records the configuration of every run
    run = tmp_path / "camp" / "runs" / "seed_0002"
    run.mkdir(parents=True)
    (tmp_path / "camp" / "campaign.json").write_text(json.dumps({"scenario": str(SCEN / "quad_approach.toml"),
                                                                 "companion_config": str(mine)}))
    rec = fcli._run_record(run)
    assert rec == {"scenario_file": str(SCEN / "quad_approach.toml"), "companion_config": str(mine)}
    assert fcli._score_companion_config(None, None, rec) == str(mine)
    # nothing recorded: built-in defaults
    assert fcli._score_companion_config(None, None, fcli._run_record(tmp_path)) is None


def test_fixed_wing_config_differs_from_the_default_only_where_a_fixed_wing_needs_it():
    import dataclasses

    from companion.io.config_files import load_companion_config

    base, fw = load_companion_config(ROOT / "configs" / "companion.toml"), load_companion_config(FIXEDWING_CFG)

    def flat(obj, prefix=""):
        if dataclasses.is_dataclass(obj):
            out = {}
            for f in dataclasses.fields(obj):
                out.update(flat(getattr(obj, f.name), f"{prefix}{f.name}."))
            return out
        return {prefix[:-1]: obj}

    a, b = flat(base), flat(fw)
    changed = {k for k in a if a[k] != b[k]}
    assert changed == {"sectors.max_distance_m", "sectors.band_half_height_m", "ekf_anchored.position_sigma_m",
                       "ekf_anchored.position_tau_s",
                       "triangulation.min_baseline_m", "triangulation.min_depth_m", "prediction.depth_min_m",
                       "map.radius_m", "map.position_drift_max_m", "ekf_anchored.max_mean_nis", "ekf_anchored.max_drift_chi2", "map.support_radius_rel",
                       "map.support_column_radius_m",
                       "sectors.infer_vertical", "sectors.cap_above_m", "sectors.unconverged_cap_k",
                       "sectors.clear_line_of_sight", "sectors.clear_corridor_m",
                       "sectors.infer_vertical_one_side", "ekf_anchored.looming_sigma_floor", "sectors.sigma_k_taper_to_m",
                       "tracks.reference_correct_px"}
    assert fw.tracks.reference_correct_px == 0.0 and base.tracks.reference_correct_px > 0  # the quads only
    assert fw.sectors.max_distance_m == 150.0 and round(fw.sectors.max_distance_m * 100) + 1 < 65535
    sc = load_scenario(SCEN / "fixedwing_pass.toml")
    assert sc.meta.sector_max_distance_m > fw.sectors.max_distance_m  # the truth reaches beyond the companion's range
