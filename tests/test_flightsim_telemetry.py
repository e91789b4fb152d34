"""Autopilot-grade telemetry and the tlog: read back with pymavlink, truth-consistent, seeded."""

import math

import numpy as np
import pytest

from companion.core.frames import euler_zyx_to_R, so3_log
from companion.errors import ConfigError
from companion.mavlink.dialect import mavlink, mavutil
from flightsim.dynamics import DynamicsConfig, LocalNED, make_vehicle
from flightsim.telemetry import TelemetryConfig, TelemetryModel
from flightsim.tlog import TlogWriter

EPOCH = 1_767_225_600.0  # 2026-01-01T00:00:00Z


def fly(tmp_path, cfg: TelemetryConfig, seed=3, seconds=4.0, name="t.tlog"):
    dyn = DynamicsConfig()
    veh = make_vehicle(dyn)
    origin = LocalNED(dyn.origin_lat_deg, dyn.origin_lon_deg, dyn.origin_alt_m)
    tm = TelemetryModel(cfg, seed, mavlink.MAV_TYPE_FIXED_WING)
    states = []
    path = tmp_path / name
    with TlogWriter(path, EPOCH) as w:
        n = int(seconds * 50)
        for k in range(n):
            s = veh.step(1 / 50)
            tm.advance(s)
            states.append(s)
            w.write(s.time_s + cfg.latency_s, tm.attitude(s))
            if k % 5 == 0:
                w.write(s.time_s + cfg.latency_s, tm.local_position(s))
                w.write(s.time_s + cfg.latency_s, tm.global_position(s, origin))
    return path, states, tm


def read(path):
    m = mavutil.mavlink_connection(str(path))
    out = []
    while (msg := m.recv_match()) is not None:
        out.append((msg.get_type(), msg._timestamp, msg))
    return out


def test_tlog_reads_back_and_attitude_matches_truth(tmp_path):
    cfg = TelemetryConfig(attitude_noise_deg=0.0, gyro_bias_deg_s=0.0, gyro_noise_deg_s=0.0, latency_s=0.02)
    path, states, _ = fly(tmp_path, cfg)
    msgs = read(path)
    att = [m for m in msgs if m[0] == "ATTITUDE"]
    assert len(att) == len(states)
    for (_, ts, m), s in zip(att, states):
        np.testing.assert_allclose([m.roll, m.pitch, m.yaw], s.rpy, atol=1e-6)  # float32 on the wire
        np.testing.assert_allclose([m.rollspeed, m.pitchspeed, m.yawspeed], s.pqr, atol=1e-6)
        assert m.time_boot_ms == round((cfg.boot_time_s + s.time_s) * 1000)  # the vehicle's own clock
        assert ts == pytest.approx(EPOCH + s.time_s + cfg.latency_s, abs=1e-6)  # the recording's clock
    lpos = [m for m in msgs if m[0] == "LOCAL_POSITION_NED"]
    s = states[0]
    np.testing.assert_allclose([lpos[0][2].x, lpos[0][2].y, lpos[0][2].z], s.p_ned, atol=1e-3)
    gpos = [m for m in msgs if m[0] == "GLOBAL_POSITION_INT"][0][2]
    assert gpos.relative_alt == pytest.approx(-s.p_ned[2] * 1000, abs=2)


def test_gyro_bias_drifts_the_attitude_as_modelled(tmp_path):
    cfg = TelemetryConfig(attitude_noise_deg=0.0, gyro_bias_deg_s=0.05, gyro_noise_deg_s=0.0)
    path, states, tm = fly(tmp_path, cfg, seconds=6.0)
    att = [m[2] for m in read(path) if m[0] == "ATTITUDE"]
    err = so3_log(euler_zyx_to_R(att[-1].roll, att[-1].pitch, att[-1].yaw) @ states[-1].R_world_body.T)
    drift = np.linalg.norm(err)
    expected = np.linalg.norm(tm.gyro_bias) * (states[-1].time_s - states[0].time_s)
    assert drift == pytest.approx(expected, rel=0.05)  # level flight: w ≈ R·b·t
    assert np.all(np.abs(np.degrees(tm.gyro_bias)) <= 0.05)
    rates = np.array([[m.rollspeed, m.pitchspeed, m.yawspeed] for m in att])
    truth = np.array([s.pqr for s in states])
    np.testing.assert_allclose(rates - truth, np.broadcast_to(tm.gyro_bias, truth.shape), atol=1e-6)


def test_attitude_correction_bounds_the_drift_of_a_long_flight():
    """With the estimator's correction the world-frame error settles at τ·(R b) per axis (tilt on
    the north/east components, heading on down) instead of growing with flight time."""
    import types

    level = np.eye(3)
    def run(cfg, seconds, dt=0.02):
        tm = TelemetryModel(cfg, 7, mavlink.MAV_TYPE_QUADROTOR)
        for k in range(int(seconds / dt) + 1):
            tm.advance(types.SimpleNamespace(time_s=k * dt, R_world_body=level))
        return tm

    base = dict(attitude_noise_deg=0.0, gyro_bias_deg_s=0.05, gyro_noise_deg_s=0.0)
    free = run(TelemetryConfig(**base), 600.0)
    np.testing.assert_allclose(free.w_err, free.gyro_bias * 600.0, rtol=1e-6)  # uncorrected: the bias integrated
    held = run(TelemetryConfig(**base, attitude_tilt_tau_s=20.0, attitude_yaw_tau_s=60.0), 600.0)
    b = held.gyro_bias
    np.testing.assert_allclose(held.w_err, [20.0 * b[0], 20.0 * b[1], 60.0 * b[2]], rtol=0.02)
    assert np.degrees(np.abs(held.w_err[:2])).max() <= 1.0 and np.degrees(abs(held.w_err[2])) <= 3.0
    # over a few seconds (a landmark's life) it still drifts at the bias rate, as the companion models it
    short = run(TelemetryConfig(**base, attitude_tilt_tau_s=20.0, attitude_yaw_tau_s=60.0), 1.0)
    np.testing.assert_allclose(short.w_err, short.gyro_bias * 1.0, rtol=0.03)
    with pytest.raises(ConfigError, match="attitude_tilt_tau_s"):
        TelemetryConfig(attitude_tilt_tau_s=-1.0)


def test_same_seed_same_bytes(tmp_path):
    cfg = TelemetryConfig(position_noise_m=0.5, velocity_noise_mps=0.1)
    a, _, _ = fly(tmp_path, cfg, seed=5, seconds=1.0, name="a.tlog")
    b, _, _ = fly(tmp_path, cfg, seed=5, seconds=1.0, name="b.tlog")
    c, _, _ = fly(tmp_path, cfg, seed=6, seconds=1.0, name="c.tlog")
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()


def test_out_of_order_write_refused(tmp_path):
    with TlogWriter(tmp_path / "x.tlog", EPOCH) as w:
        w.write(1.0, mavlink.MAVLink_heartbeat_message(1, 3, 0, 0, 4, 3))
        with pytest.raises(ValueError, match="time order"):
            w.write(0.5, mavlink.MAVLink_heartbeat_message(1, 3, 0, 0, 4, 3))


def test_config_validation():
    with pytest.raises(ConfigError, match="latency_s"):
        TelemetryConfig(latency_s=2.0)
    with pytest.raises(ConfigError, match="attitude_rate_hz"):
        TelemetryConfig(attitude_rate_hz=0.0)


def test_snapshot_restore_repeats_draws_and_messages():
    """The SITL builds telemetry ahead and rewinds on a stream request: after restore the
    telemetry model gives the same messages (the same random draws) again."""
    cfg = TelemetryConfig(position_noise_m=0.1, velocity_noise_mps=0.05)
    dyn = DynamicsConfig()
    veh = make_vehicle(dyn)
    states = [veh.step(1 / 50) for _ in range(6)]
    tm = TelemetryModel(cfg, 5, mavlink.MAV_TYPE_QUADROTOR)
    tm.advance(states[0])
    snap = tm.snapshot()

    def run():
        out = []
        for s in states[1:]:
            tm.advance(s)
            out.append(tm.attitude(s).pack(mavlink.MAVLink(None)))
            out.append(tm.local_position(s).pack(mavlink.MAVLink(None)))
        return out

    first = run()
    tm.restore(snap)
    assert run() == first


def test_tlog_records_carry_a_sequence_per_source(tmp_path):
    """Every record of one (system, component) gets the next MAVLink sequence number, wrapping at 256,
    so a ground station replaying the tlog sees no packet loss; each source counts on its own."""
    path = tmp_path / "seq.tlog"
    with TlogWriter(path, EPOCH) as w:
        for k in range(300):
            w.write(k * 0.01, mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3), sysid=1, compid=1)
            if k % 3 == 0:
                w.write(k * 0.01, mavlink.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3), sysid=1, compid=196)
    conn = mavutil.mavlink_connection(str(path))
    seqs: dict[int, list[int]] = {1: [], 196: []}
    while (m := conn.recv_match()) is not None:
        seqs[m.get_srcComponent()].append(m.get_seq())
    assert seqs[1] == [k % 256 for k in range(300)]
    assert seqs[196] == list(range(100))
