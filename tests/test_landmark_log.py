"""The landmark log (companion/landmark_log.py): what the estimator held, frame by frame.

Checked: the round trip (rounding, NaN as null, flags), what a reader refuses and what it forgives (a line
cut off by a kill), that a failing disk or a failing sink costs no frame, and, through ``companion replay
--landmark-log`` on a synthetic recording, that each logged point lies at its logged range from the logged
camera and that logging changes nothing the companion sends.
"""

from __future__ import annotations

import json
import types

import numpy as np
import pytest

from companion.cli import load_config, main
from companion.errors import ConfigError, InputError
from companion.landmark_log import LandmarkLog, read_landmark_log
from companion.replay import replay

from conftest import FullDisk
from test_replay import read_out, recording, small  # noqa: F401 (the module-scoped recording fixture)


def _out(n=4, seed=0, nis=True):
    g = np.random.default_rng(seed)
    ids = np.arange(10, 10 + n)
    p = g.uniform(-20, 20, (n, 3))
    return types.SimpleNamespace(ids=ids, range=np.linalg.norm(p, axis=1), range_sigma=g.uniform(0.1, 2.0, n),
                                 converged=g.random(n) < 0.5, valid=g.random(n) < 0.8,
                                 mean_nis=np.r_[np.nan, g.uniform(0, 5, n - 1)] if nis else None), p


def test_round_trip(tmp_path):
    path = tmp_path / "l.jsonl"
    lg = LandmarkLog(path)
    frames = []
    for k in range(3):
        out, p = _out(seed=k, nis=k != 1)
        R = np.eye(3)
        scale = (np.r_[np.nan, np.linspace(0.95, 1.05, len(out.ids) - 1)], np.r_[np.nan, np.full(len(out.ids) - 1, 0.01)])
        lg(10.0 + k / 30, R, np.array([1.0, 2.0, -3.0]), out, p, *(scale if k == 0 else ()))
        frames.append((out, p))
    lg.close()
    head = json.loads(path.read_text().split("\n")[0])
    assert head["landmark_log"] == 1 and "range" in head["fields"] and lg.lines == 3
    got = read_landmark_log(path)
    assert len(got) == 3
    for (out, p), g in zip(frames, got):
        np.testing.assert_array_equal(g["ids"], out.ids)
        np.testing.assert_allclose(g["p_world"], p, atol=5e-4)
        np.testing.assert_allclose(g["range"], out.range, atol=5e-4)
        np.testing.assert_allclose(g["range_sigma"], out.range_sigma, atol=5e-4)
        np.testing.assert_array_equal(g["converged"], out.converged)
        np.testing.assert_array_equal(g["valid"], out.valid)
        np.testing.assert_allclose(g["R_world_cam"], np.eye(3))
        np.testing.assert_allclose(g["p_world_cam"], [1.0, 2.0, -3.0])
        assert np.isnan(g["mean_nis"][0])  # NaN (no update yet, or no NIS at all) is written as null, read as NaN
    assert np.all(np.isnan(got[1]["mean_nis"]))
    np.testing.assert_allclose(got[0]["mean_nis"][1:], frames[0][0].mean_nis[1:], atol=5e-3)
    assert got[1]["t"] == pytest.approx(10.0 + 1 / 30, abs=1e-6)
    np.testing.assert_allclose(got[0]["scale"][1:], np.linspace(0.95, 1.05, 3), atol=1e-5)
    np.testing.assert_allclose(got[0]["scale_sigma"][1:], 0.01, atol=1e-5)
    assert np.isnan(got[0]["scale"][0]) and np.all(np.isnan(got[1]["scale"])) and np.all(np.isnan(got[2]["scale_sigma"]))
    # a log written before the scale fields existed reads with NaN scales
    lines = path.read_text().split("\n")
    r = json.loads(lines[1])
    del r["scale"], r["scale_sigma"]
    old = tmp_path / "old.jsonl"
    old.write_text("\n".join([lines[0], json.dumps(r), ""]))
    (g,) = read_landmark_log(old)
    assert g["scale"].shape == (4,) and np.all(np.isnan(g["scale"])) and np.all(np.isnan(g["scale_sigma"]))


def test_a_line_cut_off_by_a_kill_is_skipped_anything_else_malformed_is_refused(tmp_path):
    path = tmp_path / "l.jsonl"
    lg = LandmarkLog(path)
    out, p = _out()
    for k in range(3):
        lg(float(k), np.eye(3), np.zeros(3), out, p)
    lg.close()
    text = path.read_text()
    cut = tmp_path / "cut.jsonl"
    cut.write_text(text[: len(text) - 40])  # the last line half written
    assert len(read_landmark_log(cut)) == 2
    lines = text.split("\n")
    bad = tmp_path / "bad.jsonl"
    bad.write_text("\n".join([lines[0], lines[1][:-30], lines[2], ""]))  # a broken line in the middle
    with pytest.raises(InputError, match="line 2"):
        read_landmark_log(bad)
    short = tmp_path / "short.jsonl"
    r = json.loads(lines[1])
    r["range"] = r["range"][:-1]
    short.write_text("\n".join([lines[0], json.dumps(r), ""]))
    with pytest.raises(InputError, match="range has 3 values for 4 landmarks"):
        read_landmark_log(short)
    other = tmp_path / "other.jsonl"
    other.write_text('{"sector_log": 1}\n')
    with pytest.raises(InputError, match="not a landmark log"):
        read_landmark_log(other)
    (tmp_path / "empty.jsonl").write_text("")
    with pytest.raises(InputError, match="empty"):
        read_landmark_log(tmp_path / "empty.jsonl")


def test_the_maps_remembered_points_round_trip_and_are_optional(tmp_path):
    path = tmp_path / "l.jsonl"
    lg = LandmarkLog(path)
    out, p = _out()
    mp = np.array([[1.0, 2.0, -3.0], [4.12345, -5.0, -6.0], [7.0, 8.0, -9.0]])
    lg(1.0, np.eye(3), np.zeros(3), out, p, memory=(mp, np.array([True, False, True]), np.array([0.0, 1.25, 19.5])))
    lg(2.0, np.eye(3), np.zeros(3), out, p)  # no map (or [map] enabled = false)
    lg(3.0, np.eye(3), np.zeros(3), out, p, memory=(np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0)))
    lg.close()
    a, b, c = read_landmark_log(path)
    np.testing.assert_allclose(a["map_p_world"], mp.round(3))
    assert a["map_published"].tolist() == [True, False, True] and a["map_age"].tolist() == [0.0, 1.25, 19.5]
    assert "map_p_world" not in b and c["map_p_world"].shape == (0, 3) and c["map_published"].shape == (0,)
    bad = path.read_text().splitlines()
    bad[1] = bad[1].replace('"map_published": "101"', '"map_published": "10"')
    path.write_text("\n".join(bad) + "\n")
    with pytest.raises(InputError, match="map_published"):
        read_landmark_log(path)


def test_an_unwritable_log_is_a_configuration_error_and_a_failing_write_ends_only_the_log(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(ConfigError, match="--landmark-log"):
        LandmarkLog(tmp_path / "d")
    lg = LandmarkLog(tmp_path / "l.jsonl")

    lg._fh = FullDisk()
    out, p = _out()
    lg(1.0, np.eye(3), np.zeros(3), out, p)  # no exception
    assert lg.failed and lg.lines == 0
    lg(2.0, np.eye(3), np.zeros(3), out, p)
    assert lg.lines == 0


def test_replay_logs_each_landmark_at_its_range_and_logging_changes_nothing_sent(recording, tmp_path):  # noqa: F811
    rc = load_config(None, None, str(recording / "camera.toml"))
    args = (recording / "telemetry.tlog", recording / "video.avi", recording / "frames.csv")
    lg = LandmarkLog(tmp_path / "l.jsonl")
    s = replay(*args, tmp_path / "a.tlog", small(rc.companion), pipeline=rc.pipeline, fixed_processing_s=0.010,
               landmark_sink=lg)
    lg.close()
    replay(*args, tmp_path / "b.tlog", small(rc.companion), pipeline=rc.pipeline, fixed_processing_s=0.010)
    a = [m.get_msgbuf() for m in read_out(tmp_path / "a.tlog")]
    b = [m.get_msgbuf() for m in read_out(tmp_path / "b.tlog")]
    assert a == b and len(a) > 0
    frames = read_landmark_log(tmp_path / "l.jsonl")
    assert len(frames) == s.processed == lg.lines
    assert all(b["t"] > a["t"] for a, b in zip(frames, frames[1:]))
    n_conv = 0
    for f in frames:
        d = np.linalg.norm(f["p_world"] - f["p_world_cam"], axis=1)
        np.testing.assert_allclose(d, f["range"], rtol=1e-3, atol=2e-3)  # the point on its ray, at its range
        n_conv += int(np.count_nonzero(f["converged"] & f["valid"]))
    assert n_conv > 0 and len(frames[-1]["ids"]) > 10
    scales = np.concatenate([f["scale"] for f in frames])  # the tracker's patch scales, where it measured one
    fit = np.isfinite(scales)
    assert 0 < np.count_nonzero(fit) < len(scales) and np.all(np.abs(scales[fit] - 1) < 0.3)
    assert np.array_equal(fit, np.isfinite(np.concatenate([f["scale_sigma"] for f in frames])))
    # the map's remembered points ride along (the map is on): some published, ages never negative
    assert all("map_p_world" in f for f in frames)
    assert sum(len(f["map_p_world"]) for f in frames) > 0 and all(np.all(f["map_age"] >= 0) for f in frames)


def test_a_sink_that_raises_is_dropped_and_costs_no_frame(recording, tmp_path):  # noqa: F811
    rc = load_config(None, None, str(recording / "camera.toml"))
    calls, seen = [], {}

    def broken(*a):
        calls.append(a[0])
        raise RuntimeError("boom")

    def on_frame(pipe, res):
        seen["counters"] = dict(pipe.counters)
        seen["sink"] = pipe.landmark_sink

    s = replay(recording / "telemetry.tlog", recording / "video.avi", recording / "frames.csv", tmp_path / "r.tlog",
               small(rc.companion), pipeline=rc.pipeline, fixed_processing_s=0.010, landmark_sink=broken,
               on_frame=on_frame)
    assert len(calls) == 1 and seen["sink"] is None
    assert seen["counters"]["landmark_sink_errors"] == 1 and seen["counters"].get("internal_errors", 0) == 0
    assert s.processed >= 70


def test_cli_replay_writes_the_landmark_log(recording, tmp_path, capsys):  # noqa: F811
    cfg = tmp_path / "c.toml"
    cfg.write_text("[tracks]\nmax_tracks = 100\n[harris]\nmax_corners = 100\n")
    rc = main(["replay", "--tlog", str(recording / "telemetry.tlog"), "--video", str(recording / "video.avi"),
               "--frames", str(recording / "frames.csv"), "--out", str(tmp_path / "r.tlog"), "--config", str(cfg),
               "--no-plot", "--quiet", "--landmark-log", str(tmp_path / "l.jsonl")])
    assert rc == 0
    assert len(read_landmark_log(tmp_path / "l.jsonl")) >= 70
    rc = main(["replay", "--tlog", str(recording / "telemetry.tlog"), "--video", str(recording / "video.avi"),
               "--frames", str(recording / "frames.csv"), "--out", str(tmp_path / "r2.tlog"), "--no-plot", "--quiet",
               "--landmark-log", str(tmp_path)])
    assert rc == 2 and "--landmark-log" in capsys.readouterr().err
