"""Telemetry ring buffer: slerp / linear interpolation, refusals, duplicates, reordering, reboots."""

import math

import numpy as np
import pytest

from companion.core.frames import euler_zyx_to_R
from companion.errors import ConfigError
from companion.telemetry import AddResult, TelemetryBuffer, TelemetryConfig


def filled(offset=None, config=TelemetryConfig(), t0_ms=10_000, n=50, dt_ms=20, yaw_rate=0.5):
    buf = TelemetryBuffer(config)
    for i in range(n):
        ms = t0_ms + i * dt_ms
        t = ms * 1e-3
        buf.add_attitude(ms, 0.1, -0.05, yaw_rate * (t - t0_ms * 1e-3), 0.0, 0.0, yaw_rate)
        if i % 2 == 0:  # position at half the rate
            buf.add_local_position(ms, 2.0 * t, -1.0 * t, -10.0, 2.0, -1.0, 0.0)
    if offset is not None:
        buf.set_clock_offset(offset)
    return buf


def test_attitude_slerp_and_linear_position():
    buf = filled()
    r = buf.pose_at_boot(10.31)
    assert r.ok and r.reason == "ok"
    roll, pitch, yaw = r.pose.rpy
    assert roll == pytest.approx(0.1, abs=1e-9) and pitch == pytest.approx(-0.05, abs=1e-9)
    assert yaw == pytest.approx(0.5 * 0.31, abs=1e-9)  # slerp about one axis is linear in the angle
    assert r.pose.rates_body == pytest.approx([0, 0, 0.5])
    assert r.pose.p_world == pytest.approx([2 * 10.31, -10.31, -10.0])
    assert r.pose.v_world == pytest.approx([2.0, -1.0, 0.0])
    assert r.pose.R_world_body == pytest.approx(euler_zyx_to_R(0.1, -0.05, 0.5 * 0.31))


def test_slerp_across_the_yaw_wrap():
    buf = TelemetryBuffer()
    buf.add_attitude(1000, 0, 0, math.radians(179), 0, 0, 0)
    buf.add_attitude(1020, 0, 0, math.radians(-179), 0, 0, 0)
    r = buf.pose_at_boot(1.010, need_position=False)
    assert r.ok
    assert abs(abs(r.pose.yaw) - math.pi) < 1e-9  # half way is 180°, not 0°


def test_companion_clock_mapping_and_refusals():
    buf = filled()
    assert buf.pose_at(5.0).reason == "no_clock"
    buf.set_clock_offset(100.0)  # t_companion = t_boot + 100
    ok = buf.pose_at(110.31)
    assert ok.ok and ok.pose.t == 110.31 and ok.pose.yaw == pytest.approx(0.155)
    assert buf.pose_at(109.0).reason == "before_buffer"
    assert buf.pose_at(111.5).reason == "after_buffer"
    assert buf.pose_at(math.nan).reason == "bad_time"
    newest = 100.0 + 10.98
    assert buf.pose_at(110.5, now=newest + 0.1).ok
    assert buf.pose_at(110.5, now=newest + 0.6).reason == "stale"  # DESIGN §5: older than 0.5 s
    assert not buf.is_fresh(newest + 0.6) and buf.is_fresh(newest + 0.1)
    assert buf.yaw_at(110.31) == pytest.approx(0.155)
    # a refined offset re-stamps the whole buffer consistently
    buf.set_clock_offset(100.002)
    assert buf.pose_at(110.312).pose.yaw == pytest.approx(0.155)
    assert buf.counters["refused_no_clock"] == 1


def test_gap_between_samples_is_refused():
    buf = TelemetryBuffer(TelemetryConfig(max_gap_s=0.1))
    buf.add_attitude(1000, 0, 0, 0, 0, 0, 0)
    buf.add_attitude(1300, 0, 0, 0.3, 0, 0, 0)
    assert buf.pose_at_boot(1.15, need_position=False).reason == "gap"
    assert buf.pose_at_boot(1.3, need_position=False).ok  # exactly on a sample
    # position stream missing → refused with a position: prefix, attitude alone is fine
    assert buf.pose_at_boot(1.3).reason == "position:empty"


def test_duplicates_out_of_order_and_too_old():
    buf = TelemetryBuffer(TelemetryConfig(capacity=4))
    assert buf.add_attitude(1000, 0, 0, 0.0, 0, 0, 0) == AddResult.APPENDED
    assert buf.add_attitude(1040, 0, 0, 0.4, 0, 0, 0) == AddResult.APPENDED
    assert buf.add_attitude(1040, 0, 0, 9.9, 0, 0, 0) == AddResult.DUPLICATE
    assert buf.add_attitude(1020, 0, 0, 0.2, 0, 0, 0) == AddResult.INSERTED  # late packet
    r = buf.pose_at_boot(1.030, need_position=False)
    assert r.pose.yaw == pytest.approx(0.3)
    assert buf.add_attitude(1020, 0, 0, 0.2, 0, 0, 0) == AddResult.DUPLICATE
    buf.add_attitude(1060, 0, 0, 0.6, 0, 0, 0)  # buffer full (4)
    buf.add_attitude(1080, 0, 0, 0.8, 0, 0, 0)  # oldest (1000) falls out
    assert buf.attitude_count == 4
    assert buf.add_attitude(1001, 0, 0, 0.0, 0, 0, 0) == AddResult.TOO_OLD
    assert buf.counters["attitude_duplicate"] == 2 and buf.counters["attitude_inserted"] == 1
    assert buf.counters["attitude_too_old"] == 1


def test_ring_keeps_the_newest_samples_in_order_over_many_wraps():
    """The stream's backing arrays (twice the capacity) are compacted now and then: over a long
    stream with late and duplicate packets the kept samples are exactly the newest ``capacity`` of
    a plain sorted model, and interpolation reads them."""
    cap = 8
    buf = TelemetryBuffer(TelemetryConfig(capacity=cap, reset_threshold_s=1e9))
    rng = np.random.default_rng(5)
    model: dict[int, float] = {}
    ms = 1000
    for k in range(500):
        ms += 20
        stamp = ms - int(rng.choice([0, 0, 0, 10, 30, 20]))  # some late (inserted), some duplicates
        yaw = 1e-5 * stamp
        res = buf.add_attitude(stamp, 0, 0, yaw, 0, 0, 0)
        kept = sorted(model)[-cap:]
        if stamp in model:
            assert res == AddResult.DUPLICATE
        elif len(kept) >= cap and stamp < kept[0]:
            assert res == AddResult.TOO_OLD
        else:
            model[stamp] = yaw
        kept = sorted(model)[-cap:]
        model = {m: model[m] for m in kept}
        assert buf._att.ms.tolist() == kept
        assert buf.attitude_count == len(kept)
    a, b = kept[-2], kept[-1]
    r = buf.pose_at_boot(0.5e-3 * (a + b), need_position=False)
    assert r.ok and r.pose.yaw == pytest.approx(0.5e-5 * (a + b), abs=1e-9)
    buf.clear()
    assert buf.attitude_count == 0 and buf.add_attitude(5, 0, 0, 0, 0, 0, 0) == AddResult.APPENDED


def test_invalid_samples_are_refused_and_counted():
    buf = TelemetryBuffer()
    assert buf.add_attitude(1000, math.nan, 0, 0, 0, 0, 0) == AddResult.INVALID
    assert buf.add_attitude(-5, 0, 0, 0, 0, 0, 0) == AddResult.INVALID
    assert buf.add_local_position(1000, 0, math.inf, 0, 0, 0, 0) == AddResult.INVALID
    assert buf.add_attitude("x", 0, 0, 0, 0, 0, 0) == AddResult.INVALID
    assert buf.attitude_count == 0 and buf.position_count == 0
    assert buf.counters["attitude_invalid"] == 3 and buf.counters["position_invalid"] == 1


def test_time_boot_ms_reset_clears_the_buffer():
    buf = filled(offset=50.0)
    assert buf.attitude_count == 50
    assert buf.add_attitude(300, 0, 0, 0, 0, 0, 0) == AddResult.RESET  # autopilot rebooted
    assert buf.attitude_count == 1 and buf.position_count == 0
    assert buf.counters["reset"] == 1
    # a small step back (reordering) is not a reboot
    buf.add_attitude(400, 0, 0, 0, 0, 0, 0)
    assert buf.add_attitude(350, 0, 0, 0, 0, 0, 0) == AddResult.INSERTED


def test_extrapolation_only_when_configured():
    strict = filled()
    assert strict.pose_at_boot(10.99).reason == "after_buffer"
    buf = filled(config=TelemetryConfig(max_extrapolation_s=0.05))
    r = buf.pose_at_boot(11.0)  # newest attitude 10.98 s, position 10.96 s
    assert r.ok
    # body rates (0, 0, 0.5 rad/s) integrated over 20 ms from the newest attitude
    from companion.core.frames import so3_exp

    expected = euler_zyx_to_R(0.1, -0.05, 0.5 * 0.98) @ so3_exp(np.array([0.0, 0.0, 0.5 * 0.02]))
    assert r.pose.R_world_body == pytest.approx(expected, abs=1e-12)
    assert r.pose.p_world == pytest.approx([22.0, -11.0, -10.0])
    assert buf.pose_at_boot(11.2).reason == "after_buffer"


def test_config_validation():
    with pytest.raises(ConfigError):
        TelemetryConfig(capacity=1)
    with pytest.raises(ConfigError):
        TelemetryConfig(max_age_s=0)


def test_exposure_within_the_millisecond_of_the_newest_stamp_is_not_after_it():
    # time_boot_ms has 1 ms resolution: a sample stamped 10 980 ms may describe 10.98033 s, the
    # exposure of a 30 fps frame (the SITL lockstep rejected every third frame before this)
    buf = filled()  # newest attitude 10.980 s, newest position 10.960 s
    r = buf.pose_at_boot(10.98033, need_position=False)
    assert r.ok and r.pose.yaw == pytest.approx(0.5 * 0.98)
    assert buf.pose_at_boot(10.9815, need_position=False).reason == "after_buffer"  # past the quantum: still refused
    assert buf.pose_at_boot(10.9615).reason == "position:after_buffer"  # position holds the same rule
    assert buf.pose_at_boot(10.9603).ok
