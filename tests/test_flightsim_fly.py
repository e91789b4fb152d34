"""flightsim fly: the export is complete, reads back, lines up on one clock, and is reproducible."""

import csv
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.core.frames import euler_zyx_to_R, so3_log
from companion.errors import ConfigError
from companion.mavlink.dialect import mavutil
from flightsim.cli import main as flightsim_main
from flightsim.fly import fly
from flightsim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "configs" / "scenarios"


def variant(tmp_path: Path, name: str, edits: dict[str, str], extra: str = "", out_name: str = "s.toml") -> Path:
    """A copy of a shipped scenario with some ``key = value`` lines replaced (world path kept valid)."""
    text = (SCEN / f"{name}.toml").read_text()
    text = re.sub(r'^world = "\.\./worlds/', f'world = "{(ROOT / "configs" / "worlds").as_posix()}/', text, flags=re.M)
    for key, value in edits.items():
        text, n = re.subn(rf"^{key} = .*$", f"{key} = {value}", text, count=1, flags=re.M)
        assert n == 1, key
    p = tmp_path / out_name
    p.write_text(text + extra)
    return p


def read_tlog(path):
    m = mavutil.mavlink_connection(str(path))
    out = []
    while (msg := m.recv_match()) is not None:
        out.append(msg)
    return out


@pytest.fixture(scope="module")
def seed004_flight(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fly")
    sc = load_scenario(variant(tmp, "seed004_straight", {"duration_s": "2.0"}))
    res = fly(sc, tmp / "out")
    return sc, res, tmp / "out"


def test_export_is_complete_and_on_one_clock(seed004_flight):
    sc, res, out = seed004_flight
    for name in ("telemetry.tlog", "video.avi", "frames.csv", "truth.npz", "camera.toml", "summary.png", "flight.json"):
        assert (out / name).is_file(), name
    n_frames = int(2.0 * 30) + 1
    rows = list(csv.DictReader((out / "frames.csv").open()))
    assert [int(r["index"]) for r in rows] == list(range(n_frames))
    t_frames = np.array([float(r["t_s"]) for r in rows])
    np.testing.assert_allclose(np.diff(t_frames), 1 / 30, atol=1e-3)
    cap = cv2.VideoCapture(str(out / "video.avi"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == n_frames
    ok, img = cap.read()
    assert ok and img.shape[:2] == (240, 320)
    msgs = read_tlog(out / "telemetry.tlog")
    stamps = np.array([m._timestamp for m in msgs])
    assert np.all(np.diff(stamps) >= 0)
    # frames and telemetry share the recording clock: both start at epoch_s and span the flight
    assert abs(t_frames[0] - sc.meta.epoch_s) < 1e-6 and abs(stamps[0] - sc.meta.epoch_s) < 0.05
    assert abs(t_frames[-1] - stamps[-1]) < 0.1
    kinds = {m.get_type() for m in msgs}
    assert {"HEARTBEAT", "ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"} <= kinds
    n_att = sum(m.get_type() == "ATTITUDE" for m in msgs)
    assert abs(n_att - 2.0 * 50) <= 2


def test_tlog_sequence_numbers_count_up_per_sender(seed004_flight):
    """Each (system, component) numbers its records 0, 1, 2, … wrapping at 256, as a real link does:
    a ground station replaying the tlog sees no packet loss (before: every record had sequence 0)."""
    sc, res, out = seed004_flight
    msgs = read_tlog(out / "telemetry.tlog")
    by_sender: dict[tuple[int, int], list[int]] = {}
    for m in msgs:
        by_sender.setdefault((m.get_srcSystem(), m.get_srcComponent()), []).append(m.get_seq())
    assert list(by_sender) == [(sc.telemetry.system_id, 1)]
    seqs = by_sender[(sc.telemetry.system_id, 1)]
    assert len(seqs) > 100 and seqs == [k % 256 for k in range(len(seqs))]  # the wrap: test_flightsim_telemetry
    # what pymavlink's loss counter sees reading the file in order, as a ground station replaying it
    conn = mavutil.mavlogfile(str(out / "telemetry.tlog"))
    while conn.recv_msg() is not None:
        pass
    assert conn.mav_loss == 0 and conn.mav_count == len(msgs)


def test_attitude_matches_jsbsim_within_the_gyro_model(seed004_flight):
    sc, res, out = seed004_flight
    truth = np.load(out / "truth.npz")
    att = {m.time_boot_ms: m for m in read_tlog(out / "telemetry.tlog") if m.get_type() == "ATTITUDE"}
    boot = sc.telemetry.boot_time_s
    matched = 0
    for t, rpy in zip(truth["t_sim_s"], truth["rpy"]):
        m = att.get(int(round((boot + t) * 1000)))
        if m is None:
            continue
        matched += 1
        err = np.linalg.norm(so3_log(euler_zyx_to_R(m.roll, m.pitch, m.yaw) @ euler_zyx_to_R(*rpy).T))
        bound = math.radians(0.05) * math.sqrt(3) * t + math.radians(0.01) * 0.5 + 1e-5  # bias·t + noise
        assert err <= bound, (t, math.degrees(err))
    assert matched >= 15  # every third frame coincides with a 50-Hz ATTITUDE sample


def test_truth_matches_the_world(seed004_flight):
    sc, res, out = seed004_flight
    truth = np.load(out / "truth.npz")
    assert list(truth["target_names"]) == ["P1", "P2", "P3", "P4", "P5", "P6"]
    # range to each target from the camera centre, recomputed from the stored poses
    rng = np.linalg.norm(truth["target_p_world"][None] - truth["p_world_cam"][:, None], axis=2)
    np.testing.assert_allclose(truth["target_range_m"], rng, rtol=1e-9)
    assert truth["sector_m"].shape == (len(truth["t_s"]), 72)
    # sectors behind the camera are unseen (NaN); the forward sector sees P3/P4's row within 400 m
    assert np.isnan(truth["sector_m"][:, 36]).all()
    assert truth["target_visible"][0].all()


def test_same_seed_same_files(tmp_path):
    p = variant(tmp_path, "seed004_straight", {"duration_s": "0.5"})
    a, b = tmp_path / "a", tmp_path / "b"
    fly(load_scenario(p), a, plot=False)
    fly(load_scenario(p), b, plot=False)
    for name in ("telemetry.tlog", "video.avi", "frames.csv", "truth.npz"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    c = tmp_path / "c"
    fly(load_scenario(p, seed=99), c, plot=False)
    assert (a / "telemetry.tlog").read_bytes() != (c / "telemetry.tlog").read_bytes()


def test_bad_scenarios_stop_before_flight(tmp_path):
    with pytest.raises(ConfigError, match="unknown aircraft 'Cessna'"):
        load_scenario(variant(tmp_path, "quad_approach", {"aircraft": '"Cessna"'}))
    with pytest.raises(ConfigError, match=r"\[scenario\]: unknown key\(s\) 'duraton_s'"):
        load_scenario(_misspelt(tmp_path))
    with pytest.raises(ConfigError, match="inside obstacle 'building'|building"):
        load_scenario(variant(tmp_path, "quad_approach", {"start_ned_m": "[72.0, 0.0, -10.0]"}))
    with pytest.raises(ConfigError, match="sees nothing but sky"):
        load_scenario(variant(tmp_path, "seed004_straight", {"start_heading_deg": "180.0"}))
    with pytest.raises(ConfigError, match="seed is not allowed"):
        load_scenario(variant(tmp_path, "quad_approach", {"aircraft": '"F450"\nseed = 3'}))
    bad = tmp_path / "broken.toml"
    bad.write_text("[scenario\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scenario(bad)


def _misspelt(tmp_path):
    text = (SCEN / "quad_approach.toml").read_text().replace("duration_s =", "duraton_s =")
    text = text.replace('world = "../worlds/', f'world = "{(ROOT / "configs" / "worlds").as_posix()}/')
    p = tmp_path / "misspelt.toml"
    p.write_text(text)
    return p


def test_cli_exit_codes(tmp_path, capsys):
    assert flightsim_main(["fly", str(_misspelt(tmp_path)), "--out", str(tmp_path / "o")]) == 2
    assert "duraton_s" in capsys.readouterr().err
    p = variant(tmp_path, "seed004_straight", {"duration_s": "0.2"})
    assert flightsim_main(["fly", str(p), "--out", str(tmp_path / "ok"), "--no-plot"]) == 0
    with pytest.raises(SystemExit) as e:
        flightsim_main(["fly"])
    assert e.value.code == 2


def test_deferred_capture_gives_the_same_frames_and_truth(tmp_path):
    """Flight.capture(defer=True) poses a frame and renders it (with its truth row) later, oldest
    first: the images and truth.npz arrays are those of capturing step by step, however the
    rendering is interleaved with the physics (sitl renders while the companion works)."""
    from flightsim.fly import Flight

    sc = load_scenario(variant(tmp_path, "quad_approach", {"duration_s": "2.0"}))

    def fly_frames(defer: bool, finish_every: int):
        fl = Flight(sc)
        frames, k = [], 0
        while (st := fl.step()) is not None:
            if fl.frame_due(st):
                frames.append(fl.capture(st, defer=defer))
            k += 1
            if finish_every and k % finish_every == 0:
                fl.finish_frames()
        images = [f.image for f in frames]  # the rest on access
        return images, fl.truth_arrays()

    ref_img, ref_truth = fly_frames(False, 0)
    for every in (0, 3, 7):
        img, truth = fly_frames(True, every)
        assert len(img) == len(ref_img) == 61
        assert all(np.array_equal(a, b) for a, b in zip(img, ref_img))
        assert truth.keys() == ref_truth.keys()
        for key in truth:
            assert np.array_equal(truth[key], ref_truth[key], equal_nan=truth[key].dtype.kind == "f"), key


def test_deferred_frame_renders_the_older_ones_first(tmp_path):
    from flightsim.fly import Flight

    fl = Flight(load_scenario(variant(tmp_path, "quad_approach", {"duration_s": "0.5"})))
    frames = []
    while (st := fl.step()) is not None:
        if fl.frame_due(st):
            frames.append(fl.capture(st, defer=True))
    assert len(frames) == 16 and not any(f.rendered for f in frames)
    frames[4].image  # noqa: B018 - the access renders frames 0..4, in order
    assert [f.rendered for f in frames[:6]] == [True] * 5 + [False]
    assert fl.finish_frames(9) == 5 and fl.finish_frames() == 6 and fl.finish_frames() == 0
    assert len(fl.truth_arrays()["t_sim_s"]) == 16
