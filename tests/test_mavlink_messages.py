"""Encoders: every field per DESIGN §5, checked after packing and decoding with a separate parser."""

import math

import numpy as np
import pytest

from companion.mavlink.dialect import COMP_ID_OBSTACLE_AVOIDANCE, UINT16_MAX, mavlink  # noqa: I001 (first)
from companion.core.sectors import SectorConfig, compute_sectors
from companion.mavlink import messages as M


def roundtrip(msg, sysid=7):
    """Pack as (sysid, 196) and decode with an independent parser; returns the decoded message."""
    sender = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=COMP_ID_OBSTACLE_AVOIDANCE)
    buf = msg.pack(sender)
    assert buf[0] == mavlink.PROTOCOL_MARKER_V2  # MAVLink 2 only
    parser = mavlink.MAVLink(None)
    out = parser.parse_buffer(bytes(buf))
    assert out and len(out) == 1 and out[0].get_type() == msg.get_type()
    d = out[0]
    assert d.get_srcSystem() == sysid and d.get_srcComponent() == 196
    return d


def test_obstacle_distance_fields():
    dist = np.full(72, UINT16_MAX, np.uint16)
    dist[0], dist[1], dist[71] = 900, 4001, 0
    d = roundtrip(M.obstacle_distance(dist, 50, 4000, time_usec=123456789))
    assert d.get_msgId() == 330
    assert len(d.distances) == 72 and d.distances[0] == 900 and d.distances[1] == 4001 and d.distances[71] == 0
    assert d.distances[5] == UINT16_MAX
    assert d.increment == 5 and d.increment_f == 5.0  # both set and consistent (Mission Planner / ArduPilot)
    assert d.angle_offset == 0.0
    assert d.frame == mavlink.MAV_FRAME_BODY_FRD == 12  # an unset frame would decode as GLOBAL
    assert d.min_distance == 50 and d.max_distance == 4000
    assert d.time_usec == 123456789
    assert d.sensor_type == mavlink.MAV_DISTANCE_SENSOR_UNKNOWN


def test_obstacle_distance_never_sends_ambiguous_values():
    dist = np.full(72, 500.0)
    dist[3] = 5000  # > max + 1 would read as "no obstacle": replaced by unknown
    dist[4] = np.nan
    dist[5] = -1
    d = roundtrip(M.obstacle_distance(dist, 50, 4000))
    assert d.distances[3] == UINT16_MAX and d.distances[4] == UINT16_MAX and d.distances[5] == UINT16_MAX
    assert d.distances[0] == 500
    with pytest.raises(M.MessageError):
        M.obstacle_distance(np.zeros(71), 50, 4000)
    with pytest.raises(M.MessageError):
        M.obstacle_distance(np.zeros(72), 4000, 50)


def test_encoders_from_sectors():
    p = np.array([[10.0, 0.0, 0.0], [12.0, 1.0, 0.5]])
    s = compute_sectors(p, np.array([0.1, 0.5]), np.ones(2, bool), np.ones(2, bool), math.radians(60), 0.0, SectorConfig())
    od = roundtrip(M.obstacle_distance_from_sectors(s, time_usec=1))
    assert od.distances[0] == 980 and od.max_distance == 4000 and od.min_distance == 50
    ds = roundtrip(M.distance_sensor_from_sectors(s, time_boot_ms=42))
    assert ds.current_distance == 980 and ds.orientation == mavlink.MAV_SENSOR_ROTATION_NONE
    assert ds.covariance == 100  # σ = 10 cm → 100 cm²
    assert ds.horizontal_fov == pytest.approx(math.radians(5))
    batch = [roundtrip(m) for m in M.obstacles_3d_from_sectors(s, time_boot_ms=77)]
    assert len(batch) == 2 and {m.time_boot_ms for m in batch} == {77}  # one stamp per batch (ArduPilot)
    assert all(m.frame == mavlink.MAV_FRAME_BODY_FRD for m in batch)
    assert batch[0].x == pytest.approx(9.8) and batch[0].obstacle_id == 0
    assert batch[0].min_distance == pytest.approx(0.5) and batch[0].max_distance == pytest.approx(40.0)


def test_distance_sensor_states_covariance_and_quality():
    d = roundtrip(M.distance_sensor("obstacle", 12.34, 0.1, 50, 4000, 1000))
    assert d.current_distance == 1234 and d.covariance == 100 and d.min_distance == 50 and d.max_distance == 4000
    assert 2 <= d.signal_quality <= 100 and d.type == mavlink.MAV_DISTANCE_SENSOR_UNKNOWN and d.time_boot_ms == 1000
    big = roundtrip(M.distance_sensor("obstacle", 20.0, 1.0, 50, 4000))
    assert big.covariance == 255  # 10 000 cm² does not fit uint8: "unknown", not a false 254
    clear = roundtrip(M.distance_sensor("clear", math.nan, math.nan, 50, 4000))
    assert clear.current_distance == 4001
    unknown = roundtrip(M.distance_sensor("unknown", math.nan, math.nan, 50, 4000))
    assert unknown.current_distance == UINT16_MAX and unknown.signal_quality == 1 and unknown.covariance == 255
    right = roundtrip(M.distance_sensor("obstacle", 3.0, 0.05, 50, 4000, orientation=mavlink.MAV_SENSOR_ROTATION_YAW_90))
    assert right.orientation == 2  # YAW_90 = right
    assert M.signal_quality(10.0, 0.0) == 100 and M.signal_quality(10.0, 5.0) == 2 and M.signal_quality(10, math.nan) == 0
    assert M.covariance_cm2(0.15) == 225 and M.covariance_cm2(0.2) == 255
    with pytest.raises(M.MessageError):
        M.distance_sensor("maybe", 1.0, 0.1, 50, 4000)


def test_obstacle_distance_3d_fields():
    d = roundtrip(M.obstacle_distance_3d(5.0, -1.0, 0.5, 12, 0.5, 40.0, time_boot_ms=99))
    assert d.get_msgId() == 11037 and d.frame == 12 and d.obstacle_id == 12
    assert (d.x, d.y, d.z) == pytest.approx((5.0, -1.0, 0.5)) and d.time_boot_ms == 99
    with pytest.raises(M.MessageError):
        M.obstacle_distance_3d(math.nan, 0, 0, 1, 0.5, 40)


def test_named_value_float():
    d = roundtrip(M.named_value_float("nearest_m", 12.5, 10))
    assert d.name == "nearest_m" and d.value == 12.5 and d.time_boot_ms == 10
    assert roundtrip(M.named_value_float("abcdefghij", 1.0)).name == "abcdefghij"  # exactly 10
    for bad in ("", "abcdefghijk", "naïve"):
        with pytest.raises(M.MessageError):
            M.named_value_float(bad, 1.0)


def test_statustext_short_and_chunked():
    (one,) = M.statustext("Telemetry lost", mavlink.MAV_SEVERITY_WARNING)
    d = roundtrip(one)
    assert d.text == "Telemetry lost" and d.id == 0 and d.chunk_seq == 0 and d.severity == 4
    text = "".join(chr(65 + i % 26) for i in range(120))
    chunks = [roundtrip(m) for m in M.statustext(text, mavlink.MAV_SEVERITY_INFO, chunk_id=9)]
    assert [c.chunk_seq for c in chunks] == [0, 1, 2] and {c.id for c in chunks} == {9}
    assert "".join(c.text for c in chunks) == text
    exact = [roundtrip(m) for m in M.statustext("x" * 100, chunk_id=3)]
    assert [len(c.text) for c in exact] == [50, 50, 0]  # empty chunk terminates a multiple of 50
    with pytest.raises(M.MessageError):
        M.statustext("y" * 60)  # chunking needs an id
    ids = M.StatusTextIds()
    a, b = ids.encode("z" * 60), ids.encode("z" * 60)
    assert a[0].id != b[0].id and a[0].id != 0
    assert roundtrip(M.statustext("é ok")[0]).text == "? ok"
    assert len(M.statustext("q" * 20000, chunk_id=1)) == 256


def test_heartbeat_fields():
    d = roundtrip(M.heartbeat(mavlink.MAV_STATE_ACTIVE))
    assert d.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER == 18
    assert d.autopilot == mavlink.MAV_AUTOPILOT_INVALID == 8
    assert d.system_status == mavlink.MAV_STATE_ACTIVE and d.base_mode == 0 and d.custom_mode == 0
    assert d.mavlink_version == 3
    assert roundtrip(M.heartbeat()).system_status == mavlink.MAV_STATE_STANDBY


def test_stream_request_encoders():
    d = roundtrip(M.set_message_interval(1, 1, mavlink.MAVLINK_MSG_ID_ATTITUDE, 50.0, confirmation=2))
    assert d.command == 511 and d.param1 == 30 and d.param2 == 20000 and d.param7 == 0 and d.confirmation == 2
    assert d.target_system == 1 and d.target_component == 1
    r = roundtrip(M.request_data_stream(1, 1, mavlink.MAV_DATA_STREAM_EXTRA1, 50.0))
    assert r.req_stream_id == mavlink.MAV_DATA_STREAM_EXTRA1 and r.req_message_rate == 50 and r.start_stop == 1


def test_rate_limiters():
    lim = M.RateLimiter(10.0)
    frames = np.arange(0, 3.0, 1 / 30) + np.random.default_rng(0).normal(0, 0.002, 90)
    sent = [t for t in frames if lim.ready(t)]
    assert len(sent) == 30  # every third frame of a jittery 30 fps camera
    assert not any(M.RateLimiter(0).ready(t) for t in frames)
    sched = M.OutputSchedule(M.OutputConfig())
    t = np.arange(0, 10, 0.01)
    n_gcs = sum(sched.due("gcs", "obstacle_distance", x) for x in t)
    n_ap = sum(sched.due("autopilot", "obstacle_distance", x) for x in t)
    assert 19 <= n_gcs <= 21 and 140 <= n_ap <= 160  # 2 Hz to the radio, 15 Hz to the autopilot
    with pytest.raises(M.MessageError):
        sched.due("radio", "obstacle_distance", 0.0)
    with pytest.raises(Exception):
        M.OutputConfig(named_value_hz=5.0)
