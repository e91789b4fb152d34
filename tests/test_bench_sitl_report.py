"""The SITL section of docs/BENCHMARKS.md states the loop's own wall time and CPU per frame."""

from bench.sitl_bench import markdown


def test_lockstep_line_uses_the_loop_wall_and_per_frame_cpu():
    res = {"lockstep": {"scenario": "quad_approach", "duration_s": 14.0, "frames": 420, "wall_s": 9.46,
                        "wall_with_startup_s": 13.8, "realtime_factor": 1.48, "companion_ms_per_round": 20.6,
                        "companion_cpu_ms_per_frame": 21.2, "simulator_cpu_ms_per_frame": 10.1},
           "campaigns": {}}
    text = markdown(res)
    assert "420 frames in 9.5 s → **1.48× real time** (13.8 s with start-up)" in text
    assert "companion 21.2 ms, simulator 10.1 ms" in text
    assert "Target ≥ 10×: ✗" in text
    res["lockstep"].update(realtime_factor=12.0, companion_cpu_ms_per_frame=None)
    text = markdown(res)
    assert "Target ≥ 10×: ✓" in text and "companion n/a ms" in text


def test_campaign_nees_cell_shows_n_eff_and_coverage():
    from bench.sitl_bench import _nees_cell

    new = {"mean": 14.29, "n_eff": 123.4, "band": [0.78, 1.27], "consistent": False, "coverage": {"rate_2sigma": 0.8012}}
    assert _nees_cell(new) == "14.29 (n_eff 123, band 0.78–1.27 ✗; ±2σ 80.12 %)"
    assert _nees_cell({"mean": 1.5, "band": [0.9, 1.1]}) == "1.50 (band 0.90–1.10)"  # a campaign.json from before n_eff
