"""bench.campaign_diff: before → after rows from two synthetic campaigns with known figures."""

import json

import pytest

from bench import campaign_diff


def _campaign(path, det, too_near, nees, first):
    path.mkdir(parents=True)
    agg = {"targets": [{"key": "detection_in_view", "pooled": det}, {"key": "detection_near_in_view", "pooled": 0.99},
                       {"key": "remembered", "pooled": None}, {"key": "dangerous_clear", "pooled": 0.0},
                       {"key": "false_obstacle_clear_cells", "pooled": 0.003},
                       {"key": "messages_without_false_obstacle", "pooled": 0.97}],
           "pooled_rates": {"too_near": too_near, "over_range": 0.005},
           "nees": {"mean": nees, "band": [0.76, 1.27], "consistent": 0.76 <= nees <= 1.27, "coverage": {"rate_2sigma": 0.923}},
           "obstacles": [{"name": "mast", "time_to_first_valid_s": {"mean": first}},
                         {"name": "building", "time_to_first_valid_s": {"mean": None}}]}
    (path / "campaign.json").write_text(json.dumps({"scenario_name": "quad_approach", "aggregate": agg}))


def test_rows_before_and_after(tmp_path, capsys):
    _campaign(tmp_path / "a_quad_approach", 0.829, 0.111, 1.33, 0.56)
    _campaign(tmp_path / "b_quad_approach", 0.891, 0.061, 1.10, 0.25)
    assert campaign_diff.main(["--before-prefix", str(tmp_path / "a_"), "--after-prefix", str(tmp_path / "b_"),
                               "quad_approach"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| quad_approach"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "82.9 % → 89.1 %" and cells[3] == "– → –" and cells[4] == "11.1 % → 6.1 %"
    assert cells[9] == "1.33 (0.76–1.27 ✗) → 1.10 (0.76–1.27 ✓)" and cells[10] == "92.3 % → 92.3 %"
    assert "- quad_approach: mast 0.56 → 0.25; building – → –" in out
    # the same pair given as two directories, and as JSON
    assert campaign_diff.main([str(tmp_path / "a_quad_approach"), str(tmp_path / "b_quad_approach"), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got[0]["after"]["too_near"] == pytest.approx(0.061) and got[0]["before"]["first_valid_s"]["mast"] == 0.56


def test_a_missing_campaign_is_exit_code_2_and_pairs_are_checked(tmp_path, capsys):
    _campaign(tmp_path / "a", 0.8, 0.1, 1.0, 0.5)
    assert campaign_diff.main([str(tmp_path / "a"), str(tmp_path / "nope")]) == 2
    assert "no campaign.json" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        campaign_diff.main([str(tmp_path / "a")])
    assert e.value.code == 2


def test_a_share_of_no_cells_prints_as_none(tmp_path, capsys):
    """A pooled share that is NaN (no cells of its kind, e.g. no obstacle within 10 m) prints as "–", not "nan %"."""
    _campaign(tmp_path / "a_quad_approach", 0.829, float("nan"), 1.33, 0.56)
    _campaign(tmp_path / "b_quad_approach", 0.891, 0.061, 1.10, 0.25)
    assert campaign_diff.main([str(tmp_path / "a_quad_approach"), str(tmp_path / "b_quad_approach")]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| quad_approach"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[4] == "– → 6.1 %" and "nan" not in row
