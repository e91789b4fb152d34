"""TIMESYNC estimator (DESIGN §5): simulated clock offset, jitter, asymmetric delays, reboots."""

import math

import numpy as np
import pytest

from companion.mavlink.dialect import mavlink  # noqa: I001 (first: MAVLink 2 + ardupilotmega)
from companion.errors import ConfigError
from companion.mavlink.timesync import NS, TimesyncConfig, TimesyncEstimator, handle_timesync, timesync_request


class SimAutopilot:
    """An autopilot clock: t_autopilot = t_companion − offset."""

    def __init__(self, offset_s):
        self.offset_s = offset_s

    def stamp_ns(self, t_companion):
        return int(round((t_companion - self.offset_s) * NS))


def exchange(est, ap, t0, up, down):
    """One request at companion time t0 with one-way delays ``up`` and ``down``."""
    _, ts1 = est.make_request(t0)
    tc1 = ap.stamp_ns(t0 + up)
    return est.handle_reply(tc1, ts1, t0 + up + down)


def run(est, ap, n, rng, up_fn, down_fn, t0=1000.0, period=1.0):
    t = t0
    for _ in range(n):
        exchange(est, ap, t, up_fn(rng), down_fn(rng))
        t += period
    return t


def test_symmetric_jitter_converges_to_the_offset():
    rng = np.random.default_rng(1)
    ap = SimAutopilot(offset_s=123.456789)
    est = TimesyncEstimator()
    assert est.offset_s is None and est.source is None
    jitter = lambda r: 0.002 + r.exponential(0.003)  # noqa: E731
    run(est, ap, 40, rng, jitter, jitter)
    assert est.converged and est.source == "timesync"
    assert est.offset_s == pytest.approx(123.456789, abs=0.001)
    assert est.boot_ms_to_companion(5000) == pytest.approx(5.0 + 123.456789, abs=0.001)
    assert est.companion_to_autopilot(200.0) == pytest.approx(200.0 - 123.456789, abs=0.001)


def test_asymmetric_delay_error_is_bounded_by_half_the_round_trip():
    rng = np.random.default_rng(2)
    ap = SimAutopilot(offset_s=-50.0)
    est = TimesyncEstimator()
    run(est, ap, 30, rng, lambda r: 0.001, lambda r: 0.009)  # slow downlink (e.g. a loaded radio)
    err = est.offset_s - ap.offset_s
    assert err == pytest.approx((0.009 - 0.001) / 2, abs=1e-6)  # the bias TIMESYNC cannot see
    assert abs(err) <= est.best_rtt_s / 2 + 1e-9


def test_long_round_trips_are_rejected():
    rng = np.random.default_rng(3)
    ap = SimAutopilot(offset_s=10.0)
    est = TimesyncEstimator(TimesyncConfig(max_rtt_s=0.05))
    t = run(est, ap, 10, rng, lambda r: 0.002, lambda r: 0.002)
    good = est.offset_s
    # very late, very asymmetric replies: would pull the offset by 100 ms if used
    run(est, ap, 10, rng, lambda r: 0.001, lambda r: 0.2, t0=t)
    assert est.counters["rejected_rtt"] == 10
    assert est.offset_s == pytest.approx(good, abs=1e-9)


def test_best_round_trips_win_over_occasional_delays():
    rng = np.random.default_rng(4)
    ap = SimAutopilot(offset_s=7.0)
    est = TimesyncEstimator()
    # one reply in three is delayed 30 ms on the way back (within max_rtt): ignored by best-of selection
    delays = iter([0.03 if i % 3 == 0 else 0.0 for i in range(60)])
    run(est, ap, 60, rng, lambda r: 0.001, lambda r: 0.001 + next(delays))
    assert est.offset_s == pytest.approx(7.0, abs=1e-4)


def test_autopilot_reboot_restarts_the_estimate():
    rng = np.random.default_rng(5)
    ap = SimAutopilot(offset_s=500.0)
    est = TimesyncEstimator()
    t = run(est, ap, 10, rng, lambda r: 0.002, lambda r: 0.002)
    ap.offset_s = t - 1.0  # rebooted: its clock restarts near 0
    run(est, ap, 10, rng, lambda r: 0.002, lambda r: 0.002, t0=t)
    assert est.counters["clock_backwards"] == 1
    assert est.offset_s == pytest.approx(ap.offset_s, abs=1e-3)


def test_forward_jump_needs_confirmation():
    ap = SimAutopilot(offset_s=0.0)
    est = TimesyncEstimator(TimesyncConfig(reset_confirm=3))
    rng = np.random.default_rng(6)
    t = run(est, ap, 10, rng, lambda r: 0.002, lambda r: 0.002, t0=5000.0)
    # a single wild sample (autopilot time ahead by 5 s) is ignored …
    _, ts1 = est.make_request(t)
    est.handle_reply(ap.stamp_ns(t) + 5 * NS, ts1, t + 0.004)
    assert est.offset_s == pytest.approx(0.0, abs=1e-3)
    # … a persistent one is adopted
    ap.offset_s = -5.0
    run(est, ap, 10, rng, lambda r: 0.002, lambda r: 0.002, t0=t + 1)
    assert est.offset_s == pytest.approx(-5.0, abs=1e-3)


def test_unmatched_invalid_and_expired_replies():
    est = TimesyncEstimator(TimesyncConfig(request_timeout_s=1.0))
    assert est.handle_reply(123, 456, 1.0) is None  # nobody asked
    assert est.counters["unmatched"] == 1
    _, ts1 = est.make_request(10.0)
    assert est.handle_reply(0, ts1, 10.01) is None and est.counters["invalid"] == 1
    _, ts1 = est.make_request(20.0)
    est.make_request(25.0)  # expires the previous one
    assert est.handle_reply(5 * NS, ts1, 25.1) is None
    assert est.counters["requests_unanswered"] >= 1
    assert est.handle_reply("x", 1, 1.0) is None


def test_request_ids_are_unique_even_with_a_frozen_clock():
    est = TimesyncEstimator()
    ids = {est.make_request(1.0)[1] for _ in range(10)}
    assert len(ids) == 10
    assert est.request_due(1.0) is False and est.request_due(1.0 + est.config.fast_interval_s)


def test_arrival_fallback_until_timesync_converges():
    est = TimesyncEstimator()
    rng = np.random.default_rng(7)
    for i in range(100):  # messages stamped on the autopilot clock (offset 30 s), 1–10 ms transport
        t_ap = 1.0 + 0.02 * i
        est.observe_stamp(t_ap, t_ap + 30.0 + 0.001 + rng.uniform(0, 0.009))
    assert est.source == "arrival"
    assert est.offset_s == pytest.approx(30.0, abs=0.002)
    assert est.offset_s >= 30.0  # the envelope is late by the smallest transport delay, never early
    ap = SimAutopilot(offset_s=30.0)
    run(est, ap, 5, rng, lambda r: 0.001, lambda r: 0.001)
    assert est.source == "timesync"
    assert TimesyncEstimator(TimesyncConfig(arrival_fallback=False)).source is None


def test_message_glue_answers_requests_and_feeds_replies():
    est = TimesyncEstimator()
    req = mavlink.MAVLink_timesync_message(0, 777)
    reply = handle_timesync(est, req, 2.5)
    assert reply.get_type() == "TIMESYNC" and reply.ts1 == 777 and reply.tc1 == int(2.5 * NS)
    out = timesync_request(est, 3.0)
    assert out.tc1 == 0 and out.ts1 == int(3.0 * NS)
    assert handle_timesync(est, mavlink.MAVLink_timesync_message(1 * NS, out.ts1), 3.004) is None
    assert est.sample_count == 1 and est.last_rtt_s == pytest.approx(0.004)
    assert handle_timesync(est, mavlink.MAVLink_timesync_message(0, -3), 1.0) is None  # malformed request
    assert handle_timesync(est, object(), 1.0) is None


def test_config_validation():
    with pytest.raises(ConfigError):
        TimesyncConfig(best_count=50, window=10)
    with pytest.raises(ConfigError):
        TimesyncConfig(smoothing=1.5)
    assert math.isnan(TimesyncEstimator().best_rtt_s)
