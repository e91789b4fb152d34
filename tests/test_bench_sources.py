"""bench.sources: the claims-by-source tables of finished campaigns (hand-built campaign.json / score.json)."""

import json

from bench import sources as B


def _cbs(live_fo, rem_fo, inf_tn):
    row = lambda ranges, on, valid, tn, fo, beside: {"ranges": ranges, "on_obstacles": on, "valid": valid, "too_near": tn,  # noqa: E731
                                                     "over_range": 0, "false_obstacles": fo, "beside_obstacle": beside}
    return {"messages_scored": 10, "messages_matched": 10,
            "in_view": {"live": row(20, 18, 9, 3, live_fo, 0), "inferred": row(5, 5, 4, inf_tn, 0, 0), "vertical": row(0, 0, 0, 0, 0, 0),
                        "unattributed": row(0, 0, 0, 0, 0, 0)},
            "out_of_view": {"remembered": row(30, 20, 20, 0, rem_fo, rem_fo - 1)}}


def test_tables_from_a_campaign_and_a_run(tmp_path, capsys):
    camp, run, old = tmp_path / "camp", tmp_path / "run", tmp_path / "old"
    for d in (camp, run, old):
        d.mkdir()
    (camp / "campaign.json").write_text(json.dumps({"scenario_name": "quad_x", "aggregate": {"claims_by_source": _cbs(2, 6, 1)}}))
    (run / "score.json").write_text(json.dumps({"claims_by_source": _cbs(0, 4, 3)}))
    (old / "campaign.json").write_text(json.dumps({"scenario_name": "quad_old", "aggregate": {}}))
    assert B.main([str(camp), str(run), str(old)]) == 0
    out = capsys.readouterr().out
    assert "| quad_x | in view | live | 20 | 50.0 % | 3 | 2 (0 beside) |" in out
    assert "| quad_x | out of view | remembered | 30 | 100.0 % | 0 | 6 (5 beside) |" in out
    assert "unattributed |" not in out.split("\n\n")[0]  # no ranges: no row
    # shares of the false obstacles (2 live + 6 remembered) and of the too near (3 live + 1 inferred)
    assert "| quad_x | 25.0 % / 0.0 % / 75.0 % / 0.0 % / 0.0 % / 0.0 % (of 8) | 75.0 % / 0.0 % / 0.0 % / 25.0 % / 0.0 % / 0.0 % (of 4) |" in out
    assert "| run | " in out and "no sector log in: quad_old" in out


def test_a_directory_without_results_exits_2(tmp_path, capsys):
    assert B.main([str(tmp_path)]) == 2
    assert "neither campaign.json nor score.json" in capsys.readouterr().err


def test_unknown_cells_by_reason_across_campaigns(tmp_path, capsys):
    """Two campaigns' ``unknown_by_reason``: one row per group with unknown cells, a column only for the reasons that
    occur in any of them, shares of that group's unknown cells; a campaign flown before the reasons adds no row."""
    def ubr(ranging, not_seen):
        zero = {"not_seen": 0, "no_points": 0, "beside_band": 0, "few_far": 0, "vetoed": 0, "ranging": 0, "few_near": 0,
                "partly_in_view": 0, "held": 0, "turned": 0, "unattributed": 0}
        return {"messages_scored": 10, "messages_matched": 10,
                "obstacle_in_view": zero | {"cells": ranging + 1, "ranging": ranging, "no_points": 1},
                "obstacle_out_of_view": zero | {"cells": not_seen, "not_seen": not_seen},
                "remembered": zero | {"cells": 0}, "clear_in_view": zero | {"cells": 0}}

    for name, u in (("a", ubr(3, 5)), ("b", ubr(1, 0)), ("c", None)):
        d = tmp_path / name
        d.mkdir()
        agg = {"claims_by_source": _cbs(0, 1, 0)} | ({"unknown_by_reason": u} if u else {})
        (d / "campaign.json").write_text(json.dumps({"scenario_name": f"quad_{name}", "aggregate": agg}))
    assert B.main([str(tmp_path / n) for n in "abc"]) == 0
    out = capsys.readouterr().out
    table = out[out.index("Unknown cells by the companion's reason"):]
    assert "| scenario | cells | unknown | not seen | no points | ranging |" in table  # only the reasons that occur
    assert "| quad_a | obstacle cells in view | 4 | 0.0 % | 25.0 % | 75.0 % |" in table
    assert "| quad_a | obstacle cells out of view | 5 | 100.0 % | 0.0 % | 0.0 % |" in table
    assert "| quad_b | obstacle cells in view | 2 | 0.0 % | 50.0 % | 50.0 % |" in table
    assert "quad_b | obstacle cells out of view" not in table and "quad_c" not in table and "remembered" not in table
    assert B.main([str(tmp_path / "a"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["quad_a"]["unknown_by_reason"]["obstacle_in_view"]["ranging"] == 3
