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
