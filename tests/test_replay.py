"""`companion replay` on a synthetic recording in flightsim's export format.

The recording (telemetry.tlog + video.avi + frames.csv + camera.toml) is written by
:func:`companion.replay.write_recording` from a SyntheticFlight facing a textured wall; the output
tlog is read back with a *separate* pymavlink reader (``mavutil.mavlink_connection``) and every
message is checked: sender, fields, and stamps on the recording's clock.
"""

from __future__ import annotations

import csv
import dataclasses
import struct

import numpy as np
import pytest

from companion.mavlink.dialect import UINT16_MAX, mavlink, mavutil  # noqa: I001 (first: MAVLink 2)
from bench.latency import SyntheticFlight
from companion.cli import load_config, main
from companion.core.camera import CameraConfig
from companion.replay import ReplayError, read_telemetry_tlog, replay, write_recording

EPOCH = 1.7e9
CAM = CameraConfig.from_fov(320, 240, 60.0)
FLIGHT = dict(camera=CAM, wall_north_m=15.0, velocity_ned=(1.0, 3.0, 0.0))


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    d = tmp_path_factory.mktemp("flight")
    write_recording(d, SyntheticFlight(**FLIGHT), 2.5, epoch_s=EPOCH, boot_s=250.0, system_id=3, latency_s=0.004)
    return d


def small(cfg):
    return dataclasses.replace(cfg, tracks=dataclasses.replace(cfg.tracks, max_tracks=120),
                               harris=dataclasses.replace(cfg.harris, max_corners=120))


def read_out(path):
    conn = mavutil.mavlink_connection(str(path))  # a separate reader (mmap tlog index), not the replay's own
    msgs = []
    while True:
        m = conn.recv_msg()
        if m is None:
            break
        msgs.append(m)
    conn.close()
    return msgs


def frame_times(d):
    rows = list(csv.reader((d / "frames.csv").open()))[1:]
    return np.array([float(r[1]) for r in rows])


def test_replay_round_trip(recording, tmp_path):
    rc = load_config(None, None, str(recording / "camera.toml"))
    out = tmp_path / "ranges.tlog"
    s = replay(recording / "telemetry.tlog", recording / "video.avi", recording / "frames.csv", out, small(rc.companion),
               pipeline=rc.pipeline, plot=tmp_path / "ranges.png", fixed_processing_s=0.010)
    ft = frame_times(recording)
    assert s.frames == len(ft) == 76 and s.system_id == 3
    assert s.processed >= 70 and s.stale == 0 and s.superseded == 0
    msgs = read_out(out)
    assert len(msgs) == sum(s.messages.values())
    assert all(m.get_type() != "BAD_DATA" for m in msgs)
    assert all(m.get_srcSystem() == 3 and m.get_srcComponent() == 196 for m in msgs)
    stamps = np.array([m._timestamp for m in msgs])
    assert np.all(np.diff(stamps) >= 0), "records must be in time order"
    assert stamps[0] >= ft[0] and stamps[-1] <= ft[-1] + 1.1  # the recording's clock, not the replay's
    od = [m for m in msgs if m.get_type() == "OBSTACLE_DISTANCE"]
    during = [m for m in od if m._timestamp <= ft[-1] + 0.05]
    assert 30 <= len(during) <= 45  # 15 Hz over 2.5 s of flight (then unknown for the final second)
    assert all(np.all(np.asarray(m.distances) == UINT16_MAX) for m in od if m._timestamp > ft[-1] + 0.5)
    flight = SyntheticFlight(**FLIGHT)
    n_valid = 0
    for m in od:
        assert m.increment == 5 and m.increment_f == 5.0 and m.frame == mavlink.MAV_FRAME_BODY_FRD
        d = np.asarray(m.distances)
        assert not np.any(d == m.max_distance + 1)
        if d[0] != UINT16_MAX:
            n_valid += 1
            # sent = capture + wait for the bracketing ATTITUDE (<= 20 ms + 4 ms latency) + the fixed 10 ms
            k = np.searchsorted(ft, m._timestamp) - 1
            lag = m._timestamp - ft[k]
            assert 0.010 - 1e-6 <= lag <= 0.035, lag
            truth = flight.wall_distance(ft[k] - EPOCH)
            assert d[0] / 100 == pytest.approx(truth, rel=0.2)
            # time_usec: the exposure on the vehicle's boot clock
            assert m.time_usec / 1e6 == pytest.approx(ft[k] - EPOCH + 250.0, abs=0.006)
    assert n_valid >= 25
    types = {m.get_type() for m in msgs}
    assert {"OBSTACLE_DISTANCE", "DISTANCE_SENSOR", "HEARTBEAT", "NAMED_VALUE_FLOAT", "STATUSTEXT"} <= types
    hb = [m for m in msgs if m.get_type() == "HEARTBEAT"]
    assert hb and hb[0].type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert any(m.system_status == mavlink.MAV_STATE_ACTIVE for m in hb)
    assert s.first_valid_s is not None and s.first_valid_s < 1.0
    png = (tmp_path / "ranges.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_replay_is_deterministic_with_a_fixed_processing_time(recording, tmp_path):
    rc = load_config(None, None, str(recording / "camera.toml"))
    outs = []
    for i in range(2):
        out = tmp_path / f"r{i}.tlog"
        replay(recording / "telemetry.tlog", recording / "video.avi", recording / "frames.csv", out, small(rc.companion),
               pipeline=rc.pipeline, fixed_processing_s=0.005)
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]


def test_tlog_reader_skips_garbage_and_finds_boot_segments(tmp_path):
    mav = mavlink.MAVLink(None, srcSystem=5, srcComponent=1)
    other = mavlink.MAVLink(None, srcSystem=9, srcComponent=1)
    recs = []

    def rec(t, m, sender=mav):
        recs.append(struct.pack(">Q", int(t * 1e6)) + bytes(m.pack(sender)))

    rec(100.0, mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3))
    for k in range(10):
        rec(100.0 + k * 0.02 + 0.003, mavlink.MAVLink_attitude_message(5000 + k * 20, 0, 0, 0, 0, 0, 0))
    rec(100.25, mavlink.MAVLink_attitude_message(123, 0, 0, 0, 0, 0, 0), other)  # another system
    recs.append(struct.pack(">Q", int(100.3e6)) + b"\xfd\x09garbage-bytes")  # a corrupt record
    for k in range(10):  # the autopilot rebooted: time_boot_ms restarts near 0
        rec(101.0 + k * 0.02 + 0.001, mavlink.MAVLink_attitude_message(200 + k * 20, 0, 0, 0, 0, 0, 0))
    p = tmp_path / "t.tlog"
    p.write_bytes(b"".join(recs))
    tl = read_telemetry_tlog(p)
    assert tl.system_id == 5 and tl.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA  # a PX4's flight replays with PX4's fold
    assert len(tl.records) in (19, 20)  # the parser may lose the record right after the garbage while resyncing
    assert tl.counters["bad_records"] >= 1
    assert tl.counters.get("foreign", 0) == 1
    assert len(tl.segments) == 2
    assert tl.segments[0][1] == pytest.approx(100.003 - 5.0, abs=1e-6)
    assert tl.segments[1][1] == pytest.approx(101.001 - 0.2, abs=1e-6)
    assert tl.offset_at(100.1) == tl.segments[0][1] and tl.offset_at(101.5) == tl.segments[1][1]


def test_tlog_without_telemetry_is_an_error(tmp_path):
    mav = mavlink.MAVLink(None, srcSystem=5, srcComponent=1)
    p = tmp_path / "t.tlog"
    p.write_bytes(struct.pack(">Q", 10**15) + bytes(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(mav)))
    with pytest.raises(ReplayError, match="no ATTITUDE"):
        read_telemetry_tlog(p)


# ---------------------------------------------------------------------- through the CLI --------
def test_cli_replay_writes_the_tlog_and_the_plot(recording, tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[tracks]\nmax_tracks = 100\n[harris]\nmax_corners = 100\n[pipeline]\nmax_frame_age_s = 0.25\n")
    out, png = tmp_path / "r.tlog", tmp_path / "r.png"
    rc = main(["replay", "--tlog", str(recording / "telemetry.tlog"), "--video", str(recording / "video.avi"),
               "--frames", str(recording / "frames.csv"), "--out", str(out), "--config", str(cfg), "--plot", str(png),
               "--quiet", "--sector-log", str(tmp_path / "sectors.jsonl")])
    assert rc == 0
    text = capsys.readouterr().out
    assert "replayed 76 frames" in text and "OBSTACLE_DISTANCE" in text and str(out) in text
    assert out.stat().st_size > 0 and png.stat().st_size > 0
    ods = [m for m in read_out(out) if m.get_type() == "OBSTACLE_DISTANCE"]
    assert ods
    # the sector log has a line for every OBSTACLE_DISTANCE built from a result, with a source wherever it claims
    from companion.sector_log import read_sector_log

    lines = read_sector_log(tmp_path / "sectors.jsonl")
    valid = [m for m in ods if m.time_usec > 0]
    assert valid and len(lines) >= 1
    for m in valid:
        d = np.asarray(m.distances, np.uint16)
        src = lines[(int(m.time_usec), d.tobytes())]
        assert np.array_equal(src > 0, d.astype(np.int64) <= m.max_distance)


def test_cli_replay_wrong_camera_size_exits_2_naming_it(recording, tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[camera]\nwidth = 640\nheight = 480\n")
    rc = main(["replay", "--tlog", str(recording / "telemetry.tlog"), "--video", str(recording / "video.avi"),
               "--frames", str(recording / "frames.csv"), "--out", str(tmp_path / "r.tlog"), "--config", str(cfg),
               "--camera-config", str(cfg), "--quiet"])
    assert rc == 2
    assert "320×240" in capsys.readouterr().err


def test_cli_replay_missing_inputs_exit_2(recording, tmp_path, capsys):
    base = ["replay", "--tlog", str(recording / "telemetry.tlog"), "--video", str(recording / "video.avi"),
            "--frames", str(recording / "frames.csv"), "--out", str(tmp_path / "r.tlog"), "--quiet"]
    bad = list(base)
    bad[2] = str(tmp_path / "none.tlog")
    assert main(bad) == 2
    assert "--tlog" in capsys.readouterr().err
    bad = list(base)
    bad[8] = str(tmp_path / "no" / "dir" / "r.tlog")
    assert main(bad) == 2
    assert "does not exist" in capsys.readouterr().err


def test_periodic_duties_run_when_processing_outlasts_the_frame_period(recording, tmp_path):
    """40 ms per frame at 30 fps: frames queue back to back, yet HEARTBEAT stays at 1 Hz."""
    rc = load_config(None, None, str(recording / "camera.toml"))
    out = tmp_path / "slow.tlog"
    s = replay(recording / "telemetry.tlog", recording / "video.avi", recording / "frames.csv", out, small(rc.companion),
               pipeline=rc.pipeline, fixed_processing_s=0.040)
    assert s.superseded > 0  # the core really was busy
    hb = [m for m in read_out(out) if m.get_type() == "HEARTBEAT"]
    assert len(hb) >= int(s.recording_s + 1.0)  # 2.5 s of flight + the final second
