"""The hostile-traffic and soak benchmark (bench/hostile.py): its measurements on synthetic input (they
can fail), and a short lockstep SITL flight with hostile traffic and one blackout measured end to end."""

from __future__ import annotations

import math

import pytest

from bench import hostile as H
from flightsim.hostile import KINDS, Blackout


def test_windows():
    ts = [0.0, 0.1, 0.2, 1.5, 3.0, 3.05, 3.1, 3.9]
    assert H.worst_window(ts, 1.0) == 4  # 3.0 … 3.9
    assert H.worst_window(ts, 1.0, t0=0.05, t1=3.0) == 2
    assert H.worst_window([], 1.0) == 0
    even = [k / 15 for k in range(15 * 10)]
    assert H.min_window(even, 1.0, 1.0, 9.0) == 15
    holed = [t for t in even if not 4.0 <= t < 4.5]
    assert H.min_window(holed, 1.0, 1.0, 9.0) == 7


def _od(pattern):
    """OBSTACLE_DISTANCE arrivals at 15 Hz over 0–20 s, valid where ``pattern(t)``."""
    return [(k / 15, bool(pattern(k / 15))) for k in range(15 * 20)]


def test_blackout_response_can_fail():
    b = Blackout(8.0, 3.0)
    good = H.blackout_response(_od(lambda t: not 8.2 <= t < 11.6), b, math.inf)
    assert good["to_all_unknown_s"] == pytest.approx(0.2, abs=0.07) and good["resume_s"] == pytest.approx(0.6, abs=0.07)
    # a range still published inside the blackout after a first unknown message: unknown counts from after it
    late = H.blackout_response(_od(lambda t: not (8.1 <= t < 8.3 or 8.9 <= t < 11.2)), b, math.inf)
    assert late["to_all_unknown_s"] == pytest.approx(0.9, abs=0.07) and late["valid_messages_inside"] > 0
    # ranges never stop: no "all unknown" at all; ranges never come back: no resume
    assert H.blackout_response(_od(lambda t: True), b, math.inf)["to_all_unknown_s"] is None
    assert H.blackout_response(_od(lambda t: t < 8.1), b, math.inf)["resume_s"] is None
    # a resume only counts before the next blackout
    assert H.blackout_response(_od(lambda t: t < 8.1 or t > 15.0), b, 14.0)["resume_s"] is None


def test_rss_growth():
    flat = [[t, t, 100_000 + (5_000 if t < 20 else 0)] for t in range(0, 200)]
    r = H.rss_stats(flat, 120)
    assert r["growth_mib"] == 0 and r["slope_mib_per_h"] == 0
    leak = [[t, t, 100_000 + 100 * t] for t in range(0, 600)]  # ~0.1 MiB per simulated second
    r = H.rss_stats(leak, 120)
    assert r["growth_mib"] == pytest.approx(479 * 100 / 1024, abs=0.01)
    assert r["slope_mib_per_h"] == pytest.approx(100 / 1024 * 3600, rel=1e-3)
    assert H.rss_stats([], 120) == {"samples": 0}


def test_blackout_plan_and_scenario(tmp_path):
    p = H.Params(minutes=10, blackouts=4, blackout_s=4)
    plan = H.blackout_plan(p)
    assert len(plan) == 4 and [b.heartbeat for b in plan] == [False, True, False, True]
    assert plan[0].start_s >= p.warmup_s and plan[-1].end_s + p.settle_s <= p.duration_s
    with pytest.raises(ValueError):
        H.blackout_plan(H.Params(minutes=0.5, blackouts=4))
    from flightsim.scenario import load_scenario

    sc = load_scenario(H.write_scenario(p, tmp_path))
    assert sc.meta.duration_s == 600 and sum(sc.vehicle.route.hold_s) >= 600
    assert sc.vehicle.route.waypoints[-2:] == ((28.0, 1.0, -5.0), (28.0, -1.0, -5.0))


def test_write_section(tmp_path):
    doc = tmp_path / "B.md"
    doc.write_text("# Benchmarks\n\n## A\n\na\n\n## Z\n\nz\n")
    H.write_section(doc, "first\n")
    assert doc.read_text().endswith(f"{H.SECTION}\n\nfirst\n")
    text = doc.read_text().replace(f"{H.SECTION}\n\nfirst\n", f"{H.SECTION}\n\nfirst\n\n## After\n\nafter\n")
    doc.write_text(text)
    H.write_section(doc, "second")
    out = doc.read_text()
    assert "first" not in out and f"{H.SECTION}\n\nsecond\n\n## After\n\nafter\n" in out and out.count(H.SECTION) == 1
    assert out.startswith("# Benchmarks\n\n## A\n\na\n\n## Z\n\nz\n")


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """16 s of the hover with 100 hostile datagrams per second and one 2-s blackout from 7.5 s.  Every kind but
    ``spoof_attitude_own``: an ATTITUDE from the vehicle's own ids with a random time_boot_ms moves the companion's
    lockstep clock (``--clock sim`` follows the autopilot time it hears), which stops its output altogether (see
    the benchmark's report)."""
    p = H.Params(minutes=16 / 60, rate=100.0, seed=3, blackouts=1, blackout_s=2.0, warmup_s=6.0, settle_s=3.0,
                 kinds=tuple(k for k in KINDS if k != "spoof_attitude_own"))
    return p, H.run(p, tmp_path_factory.mktemp("hostile"), command="test")


def test_short_run_is_measured(short_run):
    p, res = short_run
    m = res["metrics"]
    assert res["crashes"] == 0 and res["companion_exit_code"] == 0 and m["log"]["tracebacks"] == 0
    assert res["flown_s"] == pytest.approx(16.0, abs=0.05)
    h = res["hostile"]
    assert set(h["by_kind"]) == set(p.kinds)
    n = h["datagrams"]
    assert abs(n - 1600) < 5 * 40 and sum(h["by_kind"].values()) == n  # Poisson, ~16 s at 100/s (minus the start)
    assert h["packets"] == n - h["by_kind"]["glued"] + sum(h["glued_parts"].values())
    assert h["blackout_dropped"]["ATTITUDE"] == pytest.approx(100, abs=2)  # 2 s of 50 Hz
    assert "HEARTBEAT" not in h["blackout_dropped"]
    # the blackout: every sector unknown soon after it starts, ranges back soon after it ends
    (b,) = m["blackouts"]
    assert (b["start_s"], b["end_s"], b["heartbeat"]) == (7.5, 9.5, False)
    assert b["to_all_unknown_s"] is not None and b["to_all_unknown_s"] <= H.BLACKOUT_UNKNOWN_MAX_S
    assert b["resume_s"] is not None and b["resume_s"] <= p.settle_s
    assert b["messages_inside"] >= 25  # unknown messages keep coming at the configured rate
    od = m["obstacle_distance"]
    assert od["configured_hz"] == 15.0 and od["worst_1s_after_warmup"] >= 12 and od["longest_gap_s"] < 0.2
    vg = m["valid_while_good"]
    assert vg["good_seconds"] >= 3 and vg["share"] == 1.0
    assert m["rss"]["samples"] >= 15 and 20 < m["rss"]["end_mib"] < 2000
    assert m["messages"]["by_type"]["HEARTBEAT"]["count"] >= 14
    names = [t["name"] for t in res["targets"]]
    assert any("crashes" in n for n in names) and any("RSS" in n for n in names) and any("blackout 1" in n for n in names)
    text = H.markdown(res)
    assert "| target | measured | bound | |" in text and "spoof_attitude_own" not in text.split("| target")[0].split("| hostile kind")[1]
