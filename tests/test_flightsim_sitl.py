"""flightsim sitl: a real companion process against the simulated autopilot and camera.

The loop runs in lockstep with ``python -m companion run --clock sim`` as a subprocess over real
sockets on 127.0.0.1: messages arrive and decode (OBSTACLE_DISTANCE with the DESIGN §5 fields,
DISTANCE_SENSOR, HEARTBEAT from component 196), the companion asked for its streams and got
TIMESYNC answers, it stops cleanly on SIGTERM, the published ranges agree with the truth within
loose bounds, and two runs with one seed give the same messages at the same simulated instants.
"""

from __future__ import annotations

import re
import socket
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.mavlink.dialect import mavlink, mavutil  # first: MAVLink 2 + ardupilotmega
from companion.errors import ConfigError
from companion.sector_log import read_sector_forward
from companion.simclock import SimClock
from flightsim.autopilot import AutopilotLogic, UdpEndpoint
from flightsim.cli import main as flightsim_main
from flightsim.sitl import SitlConfig, SitlError, run_sitl

ROOT = Path(__file__).resolve().parents[1]
DURATION_S = 4.5


def short_scenario(tmp_path: Path, duration_s: float = DURATION_S) -> Path:
    """quad_approach cut to a few seconds (world path made absolute)."""
    text = (ROOT / "configs" / "scenarios" / "quad_approach.toml").read_text()
    text = re.sub(r'^world = "\.\./worlds/', f'world = "{(ROOT / "configs" / "worlds").as_posix()}/', text, flags=re.M)
    text, n = re.subn(r"^duration_s = .*$", f"duration_s = {duration_s}", text, count=1, flags=re.M)
    assert n == 1
    p = tmp_path / "quad_short.toml"
    p.write_text(text)
    return p


def read_tlog(path: Path) -> list:
    m = mavutil.mavlink_connection(str(path))
    out = []
    while (msg := m.recv_match()) is not None:
        out.append(msg)
    return out


def ranges_sequence(msgs) -> list:
    return [(round(m._timestamp, 6), tuple(m.distances)) for m in msgs if m.get_type() == "OBSTACLE_DISTANCE"]


@pytest.fixture(scope="module")
def lockstep_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sitl")
    scen = short_scenario(tmp)
    a = run_sitl(scen, tmp / "a", seed=1)
    # run b: telemetry step by step, and the companion writes its landmark log too (flightsim sitl --landmark-log)
    b = run_sitl(scen, tmp / "b", seed=1, score=False, config=SitlConfig(build_ahead=False, landmark_log=True))
    return scen, a, tmp / "a", b, tmp / "b"


def test_lockstep_loop_messages_arrive_and_decode(lockstep_runs):
    _scen, s, out, _b, _ = lockstep_runs
    n_frames = int(DURATION_S * 30) + 1
    # every frame but the last (captured at the final step, its bracketing ATTITUDE never leaves) went out
    assert s["frames"] == n_frames - 1 and s["frames_unsent"] == 1
    assert sum(s["acks"].values()) == s["frames"]
    assert s["acks"].get("processed", 0) > 0.7 * s["frames"]
    for name in ("truth.npz", "frames.csv", "camera.toml", "telemetry.tlog", "received.tlog", "companion.log", "sitl.json"):
        assert (out / name).is_file(), name
    rx = read_tlog(out / "received.tlog")
    kinds = {m.get_type() for m in rx}
    assert {"HEARTBEAT", "OBSTACLE_DISTANCE", "TIMESYNC", "COMMAND_LONG"} <= kinds
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in rx} == {(1, 196)}
    hb = [m for m in rx if m.get_type() == "HEARTBEAT"]
    assert all(m.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER and m.autopilot == mavlink.MAV_AUTOPILOT_INVALID for m in hb)
    od = [m for m in rx if m.get_type() == "OBSTACLE_DISTANCE"]
    assert len(od) >= 0.8 * 15 * (DURATION_S - 0.5)  # 15 Hz once the vehicle is known
    for m in od:  # DESIGN §5
        assert len(m.distances) == 72 and m.increment == 5 and m.increment_f == 5.0 and m.angle_offset == 0
        assert m.frame == mavlink.MAV_FRAME_BODY_FRD and m.min_distance > 0 and m.max_distance > m.min_distance
        assert 0 not in m.distances  # 0 is "touching", never a filler
    assert any(d != 65535 for m in od for d in m.distances), "no sector was ever claimed"
    # the forward DISTANCE_SENSOR reaches the autopilot only when it agrees with OBSTACLE_DISTANCE, never "unknown";
    # the sector log keeps every forward reading computed, which the score uses (docs/derivations/sectors.md)
    ds = [m for m in rx if m.get_type() == "DISTANCE_SENSOR"]
    assert all(m.orientation == mavlink.MAV_SENSOR_ROTATION_NONE and m.current_distance != 65535 for m in ds)
    fwd = read_sector_forward(out / "sectors.jsonl")
    assert len(fwd) >= 0.9 * len(od) and len(fwd) > len(ds)
    assert s["checks"].get("obstacle_distance_bad_fields", 0) == 0
    # arrivals are on the truth clock: inside the flight (plus the companion's processing time)
    t_truth = np.load(out / "truth.npz")["t_s"]
    stamps = np.array([m._timestamp for m in rx])
    assert np.all(np.diff(stamps) >= 0)
    assert stamps[0] >= t_truth[0] and stamps[-1] <= t_truth[-1] + 0.2
    # the lockstep clock: every DISTANCE_SENSOR and NAMED_VALUE_FLOAT time_boot_ms is where the simulator dated its arrival
    assert s["checks"].get("clock_mismatches", 0) == 0


def test_companion_requested_streams_and_got_timesync(lockstep_runs):
    _scen, s, out, _b, _ = lockstep_runs
    req = {r["stream"]: r for r in s["stream_requests"]}
    assert {"ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"} <= set(req)
    assert all(r["how"] == "SET_MESSAGE_INTERVAL" for r in req.values())
    assert s["streams"]["ATTITUDE"] == pytest.approx(50.0) and s["streams"]["LOCAL_POSITION_NED"] == pytest.approx(20.0)
    assert s["streams"]["GLOBAL_POSITION_INT"] == pytest.approx(5.0)
    tx = read_tlog(out / "telemetry.tlog")
    att = [m for m in tx if m.get_type() == "ATTITUDE"]
    span = DURATION_S - req["ATTITUDE"]["t_s"]
    assert abs(len(att) - 50 * span) <= 3  # the requested rate, on the simulation clock
    assert all(m.get_srcComponent() == 1 and m.get_srcSystem() == 1 for m in tx)
    acks = [m for m in tx if m.get_type() == "COMMAND_ACK"]
    assert len(acks) == 3 and all(m.result == mavlink.MAV_RESULT_ACCEPTED and m.target_component == 196 for m in acks)
    assert s["timesync_answered"] >= 2
    log = (out / "companion.log").read_text()
    m = re.search(r"TIMESYNC: (\d+) requests, (\d+) answers accepted", log)
    assert m and int(m.group(2)) >= 2, log[-2000:]
    # the loop's CPU per round, with the pipeline's share and its stages (what limits lockstep speed)
    m = re.search(r"lockstep CPU per round: ([\d.]+) ms in the loop's thread: pipeline ([\d.]+) ms "
                  r"\(track ([\d.]+), estimate ([\d.]+), map ([\d.]+), sectors ([\d.]+)\), the rest ([\d.]+) ms", log)
    assert m, log[-2000:]
    total, pipe, *stages, rest = (float(g) for g in m.groups())
    assert 0 < pipe <= total and sum(stages) <= pipe + 0.25 and abs(total - pipe - rest) <= 0.15


def test_companion_stopped_cleanly(lockstep_runs):
    _scen, s, out, b, _ = lockstep_runs
    for run in (s, b):
        assert run["companion_exit_code"] == 0 and not run["companion"]["killed"]
    assert "SIGTERM received: stopping" in (out / "companion.log").read_text()


def test_published_ranges_agree_with_truth(lockstep_runs):
    """Loose bounds: the conservative published range of a claimed sector is rarely beyond the truth."""
    _scen, s, out, _b, _ = lockstep_runs
    z = np.load(out / "truth.npz")
    t_s, sector_m = z["t_s"], z["sector_m"]
    n = over = 0
    err = []
    for m in read_tlog(out / "received.tlog"):
        if m.get_type() != "OBSTACLE_DISTANCE":
            continue
        i = np.searchsorted(t_s, m._timestamp, side="right") - 1  # truth of the moment it arrived
        d = np.asarray(m.distances)
        for k in np.flatnonzero((d != 65535) & (d <= m.max_distance)):
            true = sector_m[i, k]
            if np.isnan(true):
                continue
            n += 1
            r = d[k] / 100.0
            if np.isfinite(true):
                err.append(r - true)
            if r > true + max(2.0, 0.3 * true):
                over += 1
    assert n >= 10, "too few claimed sectors to judge"
    # a range beyond the obstacle is the dangerous direction; the few allowed are sector-boundary cases
    # (the mast straddles two sectors while its one tracked point lies in the first: the second sees the building)
    assert over / n <= 0.10
    assert err and np.median(np.abs(err)) < 10.0
    score = s["score"]
    if score is not None:  # flightsim/score/ present: its verdict within loose bounds
        msgs = score["messages"]  # every message is scored or falls in the scorer's 2 s warm-up
        assert msgs["obstacle_distance_scored"] + msgs["in_warmup"] == s["messages_received"]["OBSTACLE_DISTANCE"]
        assert msgs["obstacle_distance_scored"] > 0
        assert score["rates"]["dangerous_clear"] <= 0.05
        # no phantom beside the mast (a yaw-jitter smear of its sector once put one in ~4 of 10 messages)
        assert (score["rates"]["false_obstacle_clear_cells"] or 0.0) <= 0.05
        assert (out / "score.json").is_file() and (out / "score.md").is_file()
        # the companion's sector log names a source for every range it published (companion/sector_log.py)
        cbs = score["claims_by_source"]
        assert (out / "sectors.jsonl").is_file() and cbs is not None
        assert cbs["messages_matched"] == cbs["messages_scored"] == msgs["obstacle_distance_scored"]
        counted = score["cells"]["obstacle"] + score["cells"]["clear"]
        attributed = sum(r["ranges"] for v in ("in_view", "out_of_view") for k, r in cbs[v].items() if k != "unattributed")
        assert attributed > 0 and all(cbs[v]["unattributed"]["ranges"] == 0 for v in ("in_view", "out_of_view"))
        assert attributed <= counted


def test_cpu_of_both_processes_per_frame(lockstep_runs):
    """sitl.json: the CPU of the simulator's loop and of the companion over the same loop, per frame."""
    _scen, s, _out, _b, _ = lockstep_runs
    cpu, per = s["cpu_s"], s["cpu_ms_per_frame"]
    if sys.platform.startswith("linux"):
        assert 0 < cpu["companion_loop"] <= cpu["companion"]  # the loop is part of the process's life
        assert per["companion"] == pytest.approx(1000 * cpu["companion_loop"] / s["frames"], abs=0.01)
    assert per["simulator"] == pytest.approx(1000 * cpu["simulator_loop"] / s["frames"], abs=0.01)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc")
def test_process_cpu_seconds_reads_proc():
    import os
    import time as _time

    from flightsim.sitl.process import cpu_seconds, process_cpu_seconds

    c0 = _time.process_time()
    while _time.process_time() - c0 < 0.05:  # burn some CPU
        pass
    mine = process_cpu_seconds(os.getpid())
    assert mine is not None and abs(mine - cpu_seconds()) < 0.05  # clock ticks (10 ms) apart
    assert process_cpu_seconds(2**22 + 12345) is None  # no such process


def test_lockstep_is_deterministic(lockstep_runs):
    _scen, a, out_a, b, out_b = lockstep_runs
    seq_a, seq_b = ranges_sequence(read_tlog(out_a / "received.tlog")), ranges_sequence(read_tlog(out_b / "received.tlog"))
    assert len(seq_a) > 20
    assert seq_a == seq_b  # same distances at the same simulated arrival instants
    assert (out_a / "received.tlog").read_bytes() == (out_b / "received.tlog").read_bytes()
    assert (out_a / "telemetry.tlog").read_bytes() == (out_b / "telemetry.tlog").read_bytes()
    assert (out_a / "truth.npz").read_bytes() == (out_b / "truth.npz").read_bytes()
    # run a built its telemetry ahead while the companion worked and rebuilt it after the stream
    # requests; run b built it step by step: the bytes above are the same
    assert a["telemetry_ahead"]["steps"] > 0 and a["telemetry_ahead"]["rebuilt"] > 0
    assert b["telemetry_ahead"] == {"steps": 0, "rebuilt": 0}
    # run b's companion also logged its landmarks, and sent the same bytes (above): the log changes nothing
    from companion.landmark_log import read_landmark_log

    frames = read_landmark_log(out_b / "landmarks.jsonl")
    assert len(frames) > 20 and sum(int(f["converged"].sum()) for f in frames) > 0
    assert not (out_a / "landmarks.jsonl").exists()


def test_landmark_truth_reads_a_sitl_run(lockstep_runs, capsys):
    """python -m bench landmark_truth on the run flown with --landmark-log: every logged frame finds its truth pose
    (the companion's clock is the autopilot's boot clock), the converged landmarks hit the world, and their z is
    that of a working filter (most within ±3σ); a run without the log is refused with exit code 2."""
    from bench import landmark_truth

    _scen, _a, out_a, _b, out_b = lockstep_runs
    frames, t, R, p, raycast = landmark_truth.load_run(out_b)
    assert all(np.min(np.abs(t - f["t"])) < 1e-3 for f in frames)
    z = landmark_truth.landmark_z(frames, t, R, p, raycast)
    assert len(z) > 50 and np.mean(np.abs(z[:, 0]) <= 3) > 0.8
    assert landmark_truth.main([str(out_b)]) == 0
    assert "| true range | samples" in capsys.readouterr().out
    assert landmark_truth.main([str(out_a)]) == 2
    assert "--landmark-log" in capsys.readouterr().err


def test_realtime_clock(tmp_path):
    s = run_sitl(short_scenario(tmp_path, 2.0), tmp_path / "rt", clock="realtime", score=False)
    assert s["companion_exit_code"] == 0
    assert 0.5 < s["realtime_factor"] <= 1.05  # paced by the wall clock (never faster)
    assert s["messages_received"].get("OBSTACLE_DISTANCE", 0) >= 10
    assert s["timesync_answered"] >= 2 and s["acks"] == {}  # nobody waits for acknowledgements


def test_a_bad_companion_config_stops_before_the_companion_starts(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[harris]\nno_such_key = 1\n")
    rc = flightsim_main(["sitl", str(short_scenario(tmp_path, 1.0)), "--out", str(tmp_path / "o"), "--config", str(bad),
                         "--mavlink-port", "0", "--camera-port", "0"])
    err = capsys.readouterr().err
    assert rc == 2  # bad input, named at once (it used to surface as the companion's exit code 2 in its log: exit 1)
    assert "no_such_key" in err and str(bad) in err and "Traceback" not in err
    assert not (tmp_path / "o" / "companion.log").exists()


def test_companion_that_cannot_start_is_a_clear_error(tmp_path, capsys):
    cfg = tmp_path / "keyless.toml"  # valid TOML, but the companion cannot open its signing key when it starts
    cfg.write_text(f'[link]\nsigning_key_file = "{(tmp_path / "no_such.key").as_posix()}"\n')
    rc = flightsim_main(["sitl", str(short_scenario(tmp_path, 1.0)), "--out", str(tmp_path / "o"), "--config", str(cfg),
                         "--mavlink-port", "0", "--camera-port", "0"])
    err = capsys.readouterr().err
    assert rc == 1
    assert "exited with code 2 before connecting" in err and str(tmp_path / "o" / "companion.log") in err
    assert "no_such.key" in err  # the tail of its log says why
    with pytest.raises(SitlError, match="companion.log"):
        run_sitl(short_scenario(tmp_path, 1.0), tmp_path / "o2", companion_config=cfg)


def test_busy_port_is_a_usage_error(tmp_path, capsys):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    try:
        port = sock.getsockname()[1]
        rc = flightsim_main(["sitl", str(short_scenario(tmp_path, 1.0)), "--out", str(tmp_path / "o"),
                             "--mavlink-port", str(port), "--camera-port", "0"])
    finally:
        sock.close()
    assert rc == 2
    assert f"UDP port {port}" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="clock must be"):
        run_sitl(short_scenario(tmp_path, 1.0), tmp_path / "o3", clock="fast")


def test_companion_run_clock_sim_needs_the_simulator_camera(capsys):
    from companion.cli import main as companion_main

    assert companion_main(["run", "--mavlink", "udpout:127.0.0.1:14999", "--camera", "0", "--clock", "sim"]) == 2
    assert "--clock sim needs" in capsys.readouterr().err
    assert companion_main(["run", "--mavlink", "udpout:127.0.0.1:14999", "--camera", "sim://127.0.0.1:5999",
                           "--sim-processing-ms", "5"]) == 2


# ---------------------------------------------------------------------- pure pieces ---------------
def test_sim_clock_follows_heard_time_and_work():
    c = SimClock(processing_s=0.025)
    assert c() == 0.0 and not c.started
    c.observe(20.0)
    c.observe(19.5)  # older stamps never move it back
    assert c() == 20.0 and c.started
    assert c.work(0.9) == 0.025  # fixed processing time, whatever was measured
    assert c() == pytest.approx(20.025)
    c.observe(20.01)  # heard time behind the companion's own work: the clock stays
    assert c() == pytest.approx(20.025)
    c.observe(20.033)
    assert c() == pytest.approx(20.033)
    c.observe(float("nan"))
    assert c() == pytest.approx(20.033)
    m = SimClock()  # measured processing time
    m.observe(5.0)
    assert m.work(0.012) == 0.012 and m() == pytest.approx(5.012)
    with pytest.raises(ConfigError):
        SimClock(processing_s=-1)


class _Periods:
    def __init__(self):
        self.calls = []

    def __call__(self, name, period, t):
        self.calls.append((name, period, t))


def _logic():
    periods = _Periods()
    defaults = {"ATTITUDE": 0.02, "LOCAL_POSITION_NED": 0.05, "GLOBAL_POSITION_INT": 0.2, "SYSTEM_TIME": 1.0}
    return AutopilotLogic(1, periods, defaults, lambda t: 20.0 + t), periods


def _from_companion(msg):
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=196)
    return mav.parse_char(msg.pack(mav))


def test_autopilot_answers_set_message_interval_and_request_data_stream():
    logic, periods = _logic()
    cmd = mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                               mavlink.MAVLINK_MSG_ID_ATTITUDE, 20000.0, 0, 0, 0, 0, 0)
    (ack,) = logic.handle(_from_companion(cmd), 0.5)
    assert ack.get_type() == "COMMAND_ACK" and ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert (ack.command, ack.target_system, ack.target_component) == (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 1, 196)
    assert periods.calls[-1] == ("ATTITUDE", pytest.approx(0.02), 0.5)
    default = mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                   mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 0.0, 0, 0, 0, 0, 0)
    assert logic.handle(_from_companion(default), 0.6)[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert periods.calls[-1] == ("LOCAL_POSITION_NED", 0.05, 0.6)  # interval 0 = the default rate
    stop = mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                mavlink.MAVLINK_MSG_ID_ATTITUDE, -1.0, 0, 0, 0, 0, 0)
    logic.handle(_from_companion(stop), 0.7)
    assert periods.calls[-1] == ("ATTITUDE", None, 0.7)
    unknown = mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 147.0, 1e5, 0, 0, 0, 0, 0)
    assert logic.handle(_from_companion(unknown), 0.8)[0].result == mavlink.MAV_RESULT_DENIED
    other_cmd = mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    assert logic.handle(_from_companion(other_cmd), 0.8)[0].result == mavlink.MAV_RESULT_UNSUPPORTED
    for_others = mavlink.MAVLink_command_long_message(2, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                      mavlink.MAVLINK_MSG_ID_ATTITUDE, 1e4, 0, 0, 0, 0, 0)
    n = len(periods.calls)
    assert logic.handle(_from_companion(for_others), 0.9) == [] and len(periods.calls) == n
    rds = mavlink.MAVLink_request_data_stream_message(1, 1, mavlink.MAV_DATA_STREAM_POSITION, 10, 1)
    assert logic.handle(_from_companion(rds), 1.0) == []
    assert periods.calls[-2:] == [("LOCAL_POSITION_NED", 0.1, 1.0), ("GLOBAL_POSITION_INT", 0.1, 1.0)]
    rds_stop = mavlink.MAVLink_request_data_stream_message(1, 1, mavlink.MAV_DATA_STREAM_EXTRA1, 10, 0)
    logic.handle(_from_companion(rds_stop), 1.1)
    assert periods.calls[-1] == ("ATTITUDE", None, 1.1)


def test_autopilot_answers_timesync_on_its_boot_clock():
    logic, _ = _logic()
    (reply,) = logic.handle(_from_companion(mavlink.MAVLink_timesync_message(0, 123456789)), 2.5)
    assert reply.tc1 == int(22.5e9) and reply.ts1 == 123456789
    assert logic.handle(_from_companion(mavlink.MAVLink_timesync_message(5, 7)), 2.6) == []  # a reply: not ours to answer
    assert logic.counters["timesync_answered"] == 1


def test_udp_endpoint_learns_its_peer_and_survives_garbage():
    ep = UdpEndpoint(0, system_id=1)
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        peer.bind(("127.0.0.1", 0))
        assert ep.send(mavlink.MAVLink_timesync_message(0, 1)) is None  # nobody to talk to yet
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=196)
        peer.sendto(b"\xfd\x09garbage", ("127.0.0.1", ep.port))
        peer.sendto(bytes(mavlink.MAVLink_heartbeat_message(18, 8, 0, 0, 3, 3).pack(mav)), ("127.0.0.1", ep.port))
        got = []
        for _ in range(50):
            ep.wait_readable(0.05)
            got += ep.receive()
            if got:
                break
        assert [m.get_type() for _, m in got] == ["HEARTBEAT"]
        assert ep.peer == peer.getsockname()
        assert ep.send(mavlink.MAVLink_timesync_message(0, 1)) is not None
        peer.settimeout(2.0)
        data = peer.recv(1024)
        assert mavlink.MAVLink(None).parse_char(data).get_type() == "TIMESYNC"
    finally:
        peer.close()
        ep.close()


def _slow_start_command(real_command, started_then_sleep_s: float):
    """companion_command wrapped: the child first logs that it is compiling its kernels and sleeps (a
    first start after an install), then runs the real companion."""
    from companion.core import jit

    def command(*args, **kwargs):
        real = real_command(*args, **kwargs)
        script = (f"import os, sys, time; print({jit.WARMUP_STARTED!r}, flush=True); time.sleep({started_then_sleep_s}); "
                  "os.execv(sys.argv[1], sys.argv[1:])")
        return [sys.executable, "-c", script, *real]
    return command


def test_a_first_start_compiling_its_kernels_is_waited_for(tmp_path, monkeypatch):
    import flightsim.sitl.loop as loop

    monkeypatch.setattr(loop, "companion_command", _slow_start_command(loop.companion_command, 4.0))
    cfg = SitlConfig(connect_timeout_s=2.0)  # shorter than the "compilation": only the compile wait lets it through
    s = run_sitl(short_scenario(tmp_path, 1.0), tmp_path / "slow", config=cfg, score=False)
    assert s["companion_exit_code"] == 0 and s["frames"] > 0


def test_a_companion_compiling_for_ever_is_given_up(tmp_path, monkeypatch):
    import time

    import flightsim.sitl.loop as loop

    monkeypatch.setattr(loop, "companion_command", _slow_start_command(loop.companion_command, 120.0))
    cfg = SitlConfig(connect_timeout_s=1.0, compile_timeout_s=3.0)
    t0 = time.monotonic()
    with pytest.raises(SitlError, match="did not connect to the camera frames"):
        run_sitl(short_scenario(tmp_path, 1.0), tmp_path / "never", config=cfg, score=False)
    assert time.monotonic() - t0 < 30


def test_map_cells_reads_a_sitl_run(lockstep_runs, capsys):
    """python -m bench map_cells on the run flown with --landmark-log: every OBSTACLE_DISTANCE of the sector log finds
    its landmark-log frame (with the map's points) and its truth frame; the run without the log is refused (exit 2)."""
    from bench import map_cells

    _scen, _a, out_a, _b, out_b = lockstep_runs
    c = map_cells.analyse_run(out_b, within_m=40.0)
    assert c["messages"] > 20 and c["messages_matched"] == c["messages"] and c["frames_without_map"] == 0
    assert map_cells.main([str(out_b), "--within", "40"]) == 0
    assert "| b | 1 |" in capsys.readouterr().out
    assert map_cells.main([str(out_a)]) == 2
    assert "--landmark-log" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        map_cells.main([str(out_b), "--within", "0"])
