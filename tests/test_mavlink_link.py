"""MavLink against a fake vehicle on loopback UDP/TCP (docs/derivations/link.md).

The vehicle is a separate pymavlink connection (its own parser): it sends HEARTBEATs from
component 1, answers (or ignores, or refuses) SET_MESSAGE_INTERVAL, honours REQUEST_DATA_STREAM,
streams telemetry on its own boot clock, answers TIMESYNC, and records everything the companion
sends so each field can be checked.  Both sides run on a simulated clock stepped in 5 ms
increments; loopback delivery is immediate, so the tests are deterministic and fast.
"""

import math
import socket

from conftest import free_port
import numpy as np
import pytest

from companion.mavlink.dialect import COMP_ID_OBSTACLE_AVOIDANCE, UINT16_MAX, mavlink, mavutil  # noqa: I001 (first)
from companion.errors import ConfigError
from companion.mavlink import messages as M
from companion.mavlink.config import LinkConfig
from companion.mavlink.link import MavLink
from companion.mavlink.signing import load_signing_key
from companion.mavlink.streams import StreamState
from companion.mavlink.timesync import NS

DT = 0.005
BOOT = 900.0  # the vehicle booted at companion time 900 s: t_companion = t_autopilot + 900
VEHICLE_SYSID = 42


class Clock:
    def __init__(self, t=1000.0):
        self.t = t

    def __call__(self):
        return self.t


class FakeVehicle:
    """An ArduPilot-like peer: ``interval`` = "accept" | "ignore" | "refuse" | "accept_silent"."""

    def __init__(self, conn, interval="accept", sysid=VEHICLE_SYSID, boot=BOOT):
        self.conn = conn
        self.interval = interval
        self.sysid = sysid
        self.boot = boot
        self.rx = []
        self.intervals = {}  # msg id -> period (s)
        self.data_streams = {}  # MAV_DATA_STREAM -> rate (Hz)
        self.next_due = {}
        self.next_hb = -math.inf
        self.heartbeats = True
        self.streaming = True
        self.tboot_shift = 0.0

    def boot_ms(self, t):
        return int((t - self.boot) * 1000) + int(self.tboot_shift * 1000)

    def received(self, name):
        return [m for m in self.rx if m.get_type() == name]

    def send(self, msg):
        self.conn.mav.send(msg)

    def step(self, t):
        while True:
            data = self.conn.recv()
            if not data:
                break
            for m in self.conn.mav.parse_buffer(data) or []:
                self.rx.append(m)
                self.handle(m, t)
        if self.heartbeats and t >= self.next_hb:
            self.next_hb = t + 1.0
            self.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                        0, 0, mavlink.MAV_STATE_ACTIVE, 3))
        if self.streaming:
            self.stream(t)

    def handle(self, m, t):
        typ = m.get_type()
        if typ == "COMMAND_LONG" and m.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            if self.interval == "ignore":
                return
            if self.interval == "refuse":
                self.send(mavlink.MAVLink_command_ack_message(m.command, mavlink.MAV_RESULT_UNSUPPORTED, 0, 0,
                                                              m.get_srcSystem(), m.get_srcComponent()))
                return
            self.send(mavlink.MAVLink_command_ack_message(m.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0,
                                                          m.get_srcSystem(), m.get_srcComponent()))
            if self.interval == "accept":
                self.intervals[int(m.param1)] = m.param2 * 1e-6
        elif typ == "REQUEST_DATA_STREAM":
            self.data_streams[m.req_stream_id] = m.req_message_rate
        elif typ == "TIMESYNC" and m.tc1 == 0:
            self.send(mavlink.MAVLink_timesync_message(int((t - self.boot + self.tboot_shift) * NS), m.ts1))

    def periods(self):
        p = dict((k, v) for k, v in self.intervals.items() if v > 0)
        for sid, rate in self.data_streams.items():
            ids = {mavlink.MAV_DATA_STREAM_EXTRA1: [30], mavlink.MAV_DATA_STREAM_POSITION: [32, 33]}.get(sid, [])
            for i in ids:
                p.setdefault(i, 1.0 / rate)
        return p

    def stream(self, t):
        ms = self.boot_ms(t)
        for mid, period in self.periods().items():
            due = self.next_due.get(mid, t)
            if t + 1e-9 < due:
                continue
            self.next_due[mid] = due + period
            if mid == 30:
                self.send(mavlink.MAVLink_attitude_message(ms, 0.01, 0.02, 0.5 + 0.1 * t % 1, 0.0, 0.0, 0.1))
            elif mid == 32:
                self.send(mavlink.MAVLink_local_position_ned_message(ms, t, 0.0, -10.0, 1.0, 0.0, 0.0))
            elif mid == 33:
                self.send(mavlink.MAVLink_global_position_int_message(ms, 0, 0, 0, 10000, 100, 0, 0, 0))


def make_pair(interval="accept", config=LinkConfig(), vehicle_signing=None, **link_kw):
    port = free_port()
    clock = Clock()
    link = MavLink(f"udpin:127.0.0.1:{port}", config, clock=clock, **link_kw)
    vconn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=VEHICLE_SYSID, source_component=1)
    if vehicle_signing is not None:
        vconn.setup_signing(vehicle_signing, sign_outgoing=True, link_id=3)
    vehicle = FakeVehicle(vconn, interval)
    return link, vehicle, clock


def run(link, vehicle, clock, seconds):
    for _ in range(int(round(seconds / DT))):
        clock.t += DT
        vehicle.step(clock.t)
        link.poll()


@pytest.fixture
def pair(request):
    made = []

    def factory(*a, **kw):
        link, vehicle, clock = make_pair(*a, **kw)
        made.append((link, vehicle))
        return link, vehicle, clock

    yield factory
    for link, vehicle in made:
        link.close()
        vehicle.conn.close()


# ---------------------------------------------------------------------- happy path -------------
def test_learns_sysid_requests_streams_measures_rates_and_fills_telemetry(pair):
    link, vehicle, clock = pair("accept")
    assert link.system_id is None and not link.connected
    run(link, vehicle, clock, 8.0)
    assert link.system_id == VEHICLE_SYSID and link.connected
    # SET_MESSAGE_INTERVAL for each stream, to the autopilot component, from (vehicle sysid, 196)
    cmds = vehicle.received("COMMAND_LONG")
    asked = {int(c.param1): c.param2 for c in cmds}
    assert asked == {30: 20000.0, 32: 50000.0, 33: 200000.0}
    for c in cmds:
        assert c.command == 511 and c.target_system == VEHICLE_SYSID and c.target_component == 1
        assert c.get_srcSystem() == VEHICLE_SYSID and c.get_srcComponent() == COMP_ID_OBSTACLE_AVOIDANCE
    assert not vehicle.received("REQUEST_DATA_STREAM")
    st = link.status()
    assert st.streams == {"ATTITUDE": "ok", "LOCAL_POSITION_NED": "ok", "GLOBAL_POSITION_INT": "ok"}
    assert st.rates_hz["ATTITUDE"] == pytest.approx(50, rel=0.1)
    assert st.rates_hz["LOCAL_POSITION_NED"] == pytest.approx(20, rel=0.1)
    assert st.rates_hz["GLOBAL_POSITION_INT"] == pytest.approx(5, rel=0.2)
    # TIMESYNC: companion asked, the vehicle answered, the offset is the vehicle's boot time
    reqs = vehicle.received("TIMESYNC")
    assert reqs and all(m.tc1 == 0 and m.ts1 > 0 and m.get_srcComponent() == 196 for m in reqs)
    assert st.clock_source == "timesync"
    assert st.clock_offset_s == pytest.approx(BOOT, abs=DT)
    # telemetry interpolated at a companion-clock time
    assert link.telemetry.attitude_count > 100 and link.telemetry.position_count > 50
    r = link.telemetry.pose_at(clock.t - 0.1, now=clock.t)
    assert r.ok, r.reason
    assert r.pose.p_world[0] == pytest.approx(clock.t - 0.1, abs=0.02)  # x = t in the fake's stream
    assert link.global_position is not None
    assert link.autopilot_time_boot_ms(clock.t) == pytest.approx(vehicle.boot_ms(clock.t), abs=10)
    ev = link.drain_events()
    assert any("system id 42" in text for _, text in ev)
    assert link.status().counters.get("rx_bad_crc", 0) == 0


def test_heartbeat_fields_and_active_only_when_told(pair):
    link, vehicle, clock = pair("accept")
    run(link, vehicle, clock, 3.0)
    hbs = vehicle.received("HEARTBEAT")
    assert len(hbs) >= 2
    for hb in hbs:
        assert hb.get_srcComponent() == 196
        assert hb.type == 18 and hb.autopilot == 8  # ONBOARD_CONTROLLER, AUTOPILOT_INVALID
        assert hb.system_status == mavlink.MAV_STATE_STANDBY
    assert hbs[-1].get_srcSystem() == VEHICLE_SYSID
    link.set_producing(True)
    run(link, vehicle, clock, 2.0)
    assert vehicle.received("HEARTBEAT")[-1].system_status == mavlink.MAV_STATE_ACTIVE
    link.set_producing(False)
    run(link, vehicle, clock, 2.0)
    assert vehicle.received("HEARTBEAT")[-1].system_status == mavlink.MAV_STATE_STANDBY
    times = [m for m in vehicle.received("HEARTBEAT")]
    assert 6 <= len(times) <= 8  # 1 Hz over 7 s


def test_every_sent_message_decodes_per_design(pair):
    from companion.core.sectors import SectorConfig, compute_sectors

    link, vehicle, clock = pair("accept")
    run(link, vehicle, clock, 1.0)
    pts = np.array([[10.0, 0.0, 0.0], [12.0, 3.0, 0.0]])
    s = compute_sectors(pts, np.array([0.5, 0.5]), np.ones(2, bool), np.ones(2, bool), math.radians(60), 0.0, SectorConfig())
    t_ms = link.autopilot_time_boot_ms(clock.t) or 0
    assert link.send(M.obstacle_distance_from_sectors(s, time_usec=t_ms * 1000))
    assert link.send(M.distance_sensor_from_sectors(s, t_ms))
    assert link.send_many(M.obstacles_3d_from_sectors(s, t_ms)) == 2
    assert link.send(M.named_value_float("fps", 29.5, t_ms))
    assert link.send_many(M.StatusTextIds().encode("Ranging started: " + "x" * 60, mavlink.MAV_SEVERITY_INFO)) == 2
    run(link, vehicle, clock, 0.05)
    for m in vehicle.rx:
        assert m.get_srcSystem() == VEHICLE_SYSID and m.get_srcComponent() == 196, m
        assert m.get_msgbuf()[0] == mavlink.PROTOCOL_MARKER_V2
    (od,) = vehicle.received("OBSTACLE_DISTANCE")
    assert od.increment == 5 and od.increment_f == 5.0 and od.angle_offset == 0.0 and od.frame == 12
    assert len(od.distances) == 72 and od.distances[0] == 900 and od.distances[36] == UINT16_MAX
    assert od.min_distance == 50 and od.max_distance == 4000
    (ds,) = vehicle.received("DISTANCE_SENSOR")
    assert ds.current_distance == 900 and ds.orientation == 0 and ds.covariance == 255  # σ² = 2500 cm² > 254
    o3 = vehicle.received("OBSTACLE_DISTANCE_3D")
    assert len(o3) == 2 and all(m.frame == 12 for m in o3) and len({m.time_boot_ms for m in o3}) == 1
    (nv,) = vehicle.received("NAMED_VALUE_FLOAT")
    assert nv.name == "fps" and nv.value == 29.5
    st = vehicle.received("STATUSTEXT")
    assert [m.chunk_seq for m in st] == [0, 1] and st[0].id == st[1].id != 0


def test_sends_are_dropped_and_counted_before_the_sysid_is_known():
    link = MavLink(f"udpin:127.0.0.1:{free_port()}", clock=Clock())
    try:
        assert not link.send(M.heartbeat())
        assert link.counters["tx_dropped_no_sysid"] == 1
        link.poll()  # nothing there: returns immediately
    finally:
        link.close()


# ---------------------------------------------------------------------- stream fallbacks -------
def test_vehicle_ignoring_set_message_interval_gets_request_data_stream(pair):
    cfg = LinkConfig(command_timeout_s=0.5, command_retries=2, stream_request_interval_s=0.1)  # (the budget: below)
    link, vehicle, clock = pair("ignore", config=cfg)
    run(link, vehicle, clock, 6.0)
    # each stream: 2 unanswered attempts, then REQUEST_DATA_STREAM for its MAV_DATA_STREAM
    assert len(vehicle.received("COMMAND_LONG")) == 6
    rds = vehicle.received("REQUEST_DATA_STREAM")
    assert {m.req_stream_id for m in rds} == {mavlink.MAV_DATA_STREAM_EXTRA1, mavlink.MAV_DATA_STREAM_POSITION}
    for m in rds:
        assert m.start_stop == 1 and m.target_system == VEHICLE_SYSID and m.target_component == 1
        assert m.req_message_rate == (50 if m.req_stream_id == mavlink.MAV_DATA_STREAM_EXTRA1 else 20)
    st = link.status()
    assert set(st.streams.values()) == {"fallback"}
    assert st.rates_hz["ATTITUDE"] == pytest.approx(50, rel=0.15)
    assert st.counters["streams.fallbacks"] == 3
    assert any("REQUEST_DATA_STREAM" in text for _, text in link.drain_events())


def test_refused_set_message_interval_falls_back_at_once(pair):
    link, vehicle, clock = pair("refuse")
    run(link, vehicle, clock, 1.0)
    assert len(vehicle.received("COMMAND_LONG")) == 3  # one per stream, each refused
    assert {m.req_stream_id for m in vehicle.received("REQUEST_DATA_STREAM")} == {
        mavlink.MAV_DATA_STREAM_EXTRA1, mavlink.MAV_DATA_STREAM_POSITION}


def test_accepted_but_never_arriving_streams_fall_back(pair):
    cfg = LinkConfig(command_retries=2, rate_check_s=1.0)
    link, vehicle, clock = pair("accept_silent", config=cfg)
    run(link, vehicle, clock, 9.0)
    assert vehicle.received("REQUEST_DATA_STREAM")
    assert link.streams.state("ATTITUDE") == StreamState.FALLBACK
    assert link.status().rates_hz["ATTITUDE"] > 40  # the fallback worked


def test_a_stream_that_stops_is_requested_again(pair):
    link, vehicle, clock = pair("accept")
    run(link, vehicle, clock, 6.0)
    n = len(vehicle.received("COMMAND_LONG"))
    vehicle.intervals.pop(30)  # the autopilot forgets ATTITUDE
    run(link, vehicle, clock, 3.0)
    again = vehicle.received("COMMAND_LONG")[n:]
    assert any(int(c.param1) == 30 for c in again)
    assert link.status().counters["streams.dropouts"] >= 1


# ---------------------------------------------------------------------- robustness -------------
def raw_v2(msgid, payload, sysid=VEHICLE_SYSID, comp=1, seq=0):
    hdr = bytes([0xFD, len(payload), 0, 0, seq, sysid, comp, msgid & 0xFF, (msgid >> 8) & 0xFF, msgid >> 16])
    return hdr + payload + b"\x00\x00"


def test_garbage_never_raises_and_is_counted(pair):
    link, vehicle, clock = pair("accept")
    run(link, vehicle, clock, 3.0)
    rng = np.random.default_rng(0)
    packer = vehicle.conn.mav
    w = vehicle.conn.write
    for _ in range(20):  # random bytes
        w(rng.integers(0, 256, rng.integers(1, 300), dtype=np.uint8).tobytes())
    hb = bytearray(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(packer))
    hb[-1] ^= 0xFF  # bad CRC
    w(bytes(hb))
    att = mavlink.MAVLink_attitude_message(vehicle.boot_ms(clock.t), 0, 0, 0, 0, 0, 0).pack(packer)
    w(bytes(att[:12]))  # truncated
    w(raw_v2(60123, b"\x01\x02\x03"))  # unknown message id
    w(bytes([0xFE, 3, 0, 42, 1]))  # a truncated MAVLink 1 header
    w(bytes(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(packer, force_mavlink1=True)))  # MAVLink 1
    w(b"")
    run(link, vehicle, clock, 0.1)
    c = link.status().counters
    assert c["rx_bad_crc"] >= 1
    assert c["rx_truncated"] >= 1
    assert c["rx_unknown_id"] >= 1
    assert c["rx_bad_prefix"] >= 1
    assert c["rx_mavlink1"] == 1
    assert c.get("rx_handler_errors", 0) == 0
    # the link still works afterwards
    before = link.telemetry.attitude_count
    run(link, vehicle, clock, 1.0)
    assert link.telemetry.attitude_count > before and link.connected


def test_duplicated_out_of_order_and_reset_telemetry(pair):
    link, vehicle, clock = pair("accept")
    run(link, vehicle, clock, 6.0)
    vehicle.streaming = False
    ms = vehicle.boot_ms(clock.t) + 10
    att = lambda t_ms: mavlink.MAVLink_attitude_message(t_ms, 0, 0, 0, 0, 0, 0)  # noqa: E731
    vehicle.send(att(ms))
    vehicle.send(att(ms))  # duplicated
    vehicle.send(att(ms + 30))
    vehicle.send(att(ms + 20))  # out of order
    run(link, vehicle, clock, 0.02)
    c = link.status().counters
    assert c["telemetry.attitude_duplicate"] == 1 and c["telemetry_duplicate"] == 1
    assert c["telemetry.attitude_inserted"] == 1
    n_cmd = len(vehicle.received("COMMAND_LONG"))
    # autopilot reboot: time_boot_ms restarts near zero
    vehicle.boot = clock.t - 0.5
    vehicle.streaming = True
    vehicle.next_due.clear()
    run(link, vehicle, clock, 4.0)
    c = link.status().counters
    assert c["vehicle_reboots"] == 1 and c["telemetry.reset"] == 1
    assert c["timesync.resets"] >= 1
    assert len(vehicle.received("COMMAND_LONG")) > n_cmd  # streams requested again after the reboot
    assert link.status().clock_offset_s == pytest.approx(vehicle.boot, abs=DT)
    assert any("reboot" in text for _, text in link.drain_events())


def test_answers_the_autopilots_timesync_requests(pair):
    link, vehicle, clock = pair("accept")
    run(link, vehicle, clock, 0.5)
    vehicle.send(mavlink.MAVLink_timesync_message(0, 123456789))
    run(link, vehicle, clock, 0.01)
    replies = [m for m in vehicle.received("TIMESYNC") if m.tc1 != 0]
    assert len(replies) == 1 and replies[0].ts1 == 123456789
    assert replies[0].tc1 == pytest.approx((clock.t - DT) * NS, abs=2 * DT * NS)  # companion clock, ns
    assert link.timesync.counters["answered"] == 1


def test_foreign_heartbeats_do_not_set_the_sysid(pair):
    link, vehicle, clock = pair("accept")
    vehicle.heartbeats = False
    gcs = mavlink.MAVLink(vehicle.conn, srcSystem=255, srcComponent=190)
    companion = mavlink.MAVLink(vehicle.conn, srcSystem=9, srcComponent=1)
    gcs.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3))
    companion.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3))
    camera = mavlink.MAVLink(vehicle.conn, srcSystem=9, srcComponent=100)
    camera.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3))
    run(link, vehicle, clock, 0.05)
    assert link.system_id is None and link.counters["rx_heartbeat_other"] == 3
    vehicle.heartbeats = True
    run(link, vehicle, clock, 0.05)
    assert link.system_id == VEHICLE_SYSID


def test_telemetry_from_other_systems_is_ignored(pair):
    link, vehicle, clock = pair("accept")
    run(link, vehicle, clock, 0.5)
    other = mavlink.MAVLink(vehicle.conn, srcSystem=7, srcComponent=1)
    n = link.telemetry.attitude_count
    vehicle.streaming = False
    other.send(mavlink.MAVLink_attitude_message(vehicle.boot_ms(clock.t) + 5, 0, 0, 0, 0, 0, 0))
    run(link, vehicle, clock, 0.02)
    assert link.telemetry.attitude_count == n and link.counters["rx_foreign"] >= 1


# ---------------------------------------------------------------------- link loss --------------
def test_link_loss_and_recovery(pair):
    link, vehicle, clock = pair("accept", config=LinkConfig(link_timeout_s=2.0))
    run(link, vehicle, clock, 5.0)
    link.drain_events()
    n_cmd = len(vehicle.received("COMMAND_LONG"))
    vehicle.heartbeats = vehicle.streaming = False
    run(link, vehicle, clock, 3.0)
    assert not link.connected and link.counters["link_lost"] == 1
    assert not link.telemetry.is_fresh(clock.t)
    assert any("link lost" in text for _, text in link.drain_events())
    vehicle.heartbeats = vehicle.streaming = True
    vehicle.next_hb = -math.inf
    run(link, vehicle, clock, 3.0)
    assert link.connected
    assert any("restored" in text for _, text in link.drain_events())
    assert len(vehicle.received("COMMAND_LONG")) > n_cmd  # rates requested again
    assert link.telemetry.is_fresh(clock.t)


def test_tcp_link_reconnects_after_the_peer_drops():
    port = free_port(socket.SOCK_STREAM)
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", port))
    server.listen(2)
    clock = Clock()
    link = MavLink(f"tcp:127.0.0.1:{port}", LinkConfig(reconnect_interval_s=0.5, link_timeout_s=2.0), clock=clock)
    packer = mavlink.MAVLink(None, srcSystem=5, srcComponent=1)
    hb = bytes(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(packer))
    try:
        peer, _ = server.accept()
        peer.sendall(hb)
        for _ in range(20):
            clock.t += DT
            link.poll()
        assert link.connected and link.system_id == 5
        peer.close()  # the vehicle side goes away
        for _ in range(10):
            clock.t += DT
            link.poll()
        assert link.counters["transport_errors"] >= 1
        clock.t += 1.0
        link.poll()  # reopens
        assert link.counters["reconnects"] >= 1
        peer2, _ = server.accept()
        peer2.sendall(hb)
        for _ in range(20):
            clock.t += DT
            link.poll()
        assert link.connected
        peer2.settimeout(1.0)
        got = mavlink.MAVLink(None).parse_buffer(peer2.recv(4096)) or []
        assert any(m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 196 for m in got)
        peer2.close()
    finally:
        link.close()
        server.close()


def test_tcp_peer_absent_at_start_is_retried_without_raising():
    port = free_port(socket.SOCK_STREAM)
    clock = Clock()
    link = MavLink(f"tcp:127.0.0.1:{port}", LinkConfig(reconnect_interval_s=0.5), clock=clock)
    try:
        assert link.counters["open_failures"] == 1
        clock.t += 1.0
        link.poll()
        assert link.counters["open_failures"] == 2
        assert not link.send(M.heartbeat())
    finally:
        link.close()


def test_bad_connection_string_is_a_config_error():
    with pytest.raises(ConfigError):
        MavLink("udpin:no-port-here", clock=Clock())
    with pytest.raises(ConfigError):
        MavLink("", clock=Clock())


# ---------------------------------------------------------------------- signing ----------------
def test_signing_refuses_unsigned_input_and_signs_output(pair, tmp_path):
    keyfile = tmp_path / "mavlink.key"
    keyfile.write_text("correct horse battery staple\n")
    key = load_signing_key(keyfile)
    import hashlib

    assert key == hashlib.sha256(b"correct horse battery staple").digest()  # MAVProxy's passphrase hash
    cfg = LinkConfig(signing_key_file=str(keyfile), require_signing=True)
    # unsigned vehicle: nothing it says is accepted
    link, vehicle, clock = pair("accept", config=cfg)
    run(link, vehicle, clock, 2.0)
    assert link.system_id is None and not link.connected
    assert link.status().counters["rx_signing_rejected"] >= 2
    assert link.status().signing
    # vehicle signing with the same key: accepted, and what the companion sends is signed
    link2, vehicle2, clock2 = pair("accept", config=cfg, vehicle_signing=key)
    run(link2, vehicle2, clock2, 3.0)
    assert link2.system_id == VEHICLE_SYSID and link2.connected
    hbs = vehicle2.received("HEARTBEAT")
    assert hbs and all(m.get_signed() for m in hbs)
    assert link2.telemetry.attitude_count > 0
    # a vehicle with the wrong key is refused too
    link3, vehicle3, clock3 = pair("accept", config=cfg, vehicle_signing=b"\x01" * 32)
    run(link3, vehicle3, clock3, 1.5)
    assert link3.system_id is None and link3.status().counters["rx_signing_rejected"] >= 1


def test_signing_key_file_formats(tmp_path):
    raw = bytes(range(32))
    (tmp_path / "raw").write_bytes(raw)
    (tmp_path / "hex").write_text(raw.hex() + "\n")
    (tmp_path / "empty").write_text("  \n")
    assert load_signing_key(tmp_path / "raw") == raw
    assert load_signing_key(tmp_path / "hex") == raw
    with pytest.raises(ConfigError):
        load_signing_key(tmp_path / "empty")
    with pytest.raises(ConfigError):
        load_signing_key(tmp_path / "missing")


# ---------------------------------------------------------------------- gcs output -------------
def test_gcs_role_sends_with_the_vehicle_sysid_and_requests_nothing():
    port = free_port()
    clock = Clock()
    gcs_side = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    out = MavLink(f"udpout:127.0.0.1:{port}", clock=clock, role="gcs")
    try:
        out.set_system_id(VEHICLE_SYSID)
        for _ in range(5):
            clock.t += 0.5
            out.poll()
        assert out.send(M.obstacle_distance(np.full(72, UINT16_MAX), 50, 4000))
        got = []
        while True:
            data = gcs_side.recv()
            if not data:
                break
            got += gcs_side.mav.parse_buffer(data) or []
        types = [m.get_type() for m in got]
        assert "HEARTBEAT" in types and "OBSTACLE_DISTANCE" in types
        assert "COMMAND_LONG" not in types and "TIMESYNC" not in types
        assert all(m.get_srcSystem() == VEHICLE_SYSID and m.get_srcComponent() == 196 for m in got)
        # a GCS heartbeat marks the output connected
        gcs_side.mav.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3))
        out.poll()
        assert out.connected
    finally:
        out.close()
        gcs_side.close()


# ---------------------------------------------------------------------- serial -----------------
def _has_pyserial():
    try:
        import serial  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.mark.skipif(_has_pyserial(), reason="pyserial installed")
def test_serial_without_pyserial_is_a_clear_config_error():
    with pytest.raises(ConfigError, match="pyserial"):
        MavLink("/dev/ttyAMA0", clock=Clock())


@pytest.mark.skipif(not _has_pyserial(), reason="serial links need pyserial")
def test_serial_link_over_a_pty_and_device_loss():
    import os

    master, slave = os.openpty()
    path = os.ttyname(slave)
    clock = Clock()
    link = MavLink(path, LinkConfig(baud=921600, reconnect_interval_s=0.5), clock=clock)
    try:
        os.set_blocking(master, False)
        packer = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
        os.write(master, bytes(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(packer)))
        for _ in range(10):
            clock.t += DT
            link.poll()
        assert link.connected and link.system_id == 3
        clock.t += 1.0
        link.poll()
        out = b""
        try:
            while True:
                out += os.read(master, 4096)
        except BlockingIOError:
            pass
        got = mavlink.MAVLink(None).parse_buffer(out) or []
        assert any(m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 3 and m.get_srcComponent() == 196 for m in got)
        os.close(master)  # the device goes away
        master = None
        for _ in range(5):
            clock.t += 0.6
            link.poll()  # never raises; reopening is retried
        assert link.counters["transport_errors"] >= 1
    finally:
        link.close()
        if master is not None:
            os.close(master)
        os.close(slave)


def test_heartbeat_goes_out_under_the_vehicle_sysid_as_soon_as_it_is_learnt(pair):
    # a ground station must see component 196 under the vehicle's system at once, not a period later
    link, vehicle, clock = pair("accept")
    vehicle.heartbeats = False  # the vehicle's first packet is not its HEARTBEAT: we answer under the provisional id
    vehicle.send(mavlink.MAVLink_system_time_message(0, 1000))
    run(link, vehicle, clock, 0.2)
    assert link.system_id is None and vehicle.received("HEARTBEAT")[-1].get_srcSystem() == LinkConfig().provisional_system_id
    vehicle.heartbeats = True
    t_end = clock.t + 3.0
    while link.system_id is None and clock.t < t_end:
        run(link, vehicle, clock, DT)
    assert link.system_id == VEHICLE_SYSID
    run(link, vehicle, clock, 0.1)
    assert any(m.get_srcSystem() == VEHICLE_SYSID for m in vehicle.received("HEARTBEAT"))


# ---------------------------------------------------------------------- link hardening --
def _spoofer(vehicle, sysid=VEHICLE_SYSID, comp=1):
    """A second sender on the vehicle's socket, with its own sequence numbers (valid CRCs)."""
    return mavlink.MAVLink(vehicle.conn, srcSystem=sysid, srcComponent=comp)


def test_random_time_attitude_from_the_autopilot_resets_nothing(pair, caplog):
    """The spoofed-ATTITUDE incident: valid-CRC ATTITUDE packets with random time_boot_ms, ~340/s for 20 s,
    from the autopilot's own system/component.  Before: each was a "reboot" (STATUSTEXT and
    COMMAND_LONG storms, the telemetry cleared).  Now: rejected and counted, nothing resets."""
    link, vehicle, clock = pair("accept")
    run(link, vehicle, clock, 6.0)
    link.drain_events()
    st0 = link.status().counters
    rej0 = st0.get("rx_clock_rejected", 0)
    n_cmd, n_rds = len(vehicle.received("COMMAND_LONG")), len(vehicle.received("REQUEST_DATA_STREAM"))
    spoof = _spoofer(vehicle)
    rng = np.random.default_rng(14)
    sent, events = 0, []
    caplog.clear()
    for k in range(int(20.0 / DT)):
        clock.t += DT
        vehicle.step(clock.t)
        for _ in range(rng.poisson(340 * DT)):
            spoof.send(mavlink.MAVLink_attitude_message(int(rng.integers(0, 2**32)), *rng.normal(size=6)))
            sent += 1
        link.poll()
        events += link.drain_events()
    c = link.status().counters
    assert sent > 6000
    assert c.get("vehicle_reboots", 0) == 0 and c.get("telemetry.reset", 0) == 0
    assert c.get("timesync.resets", 0) == st0.get("timesync.resets", 0)
    assert c["streams.restarts"] == st0["streams.restarts"]
    assert c["rx_clock_rejected"] - rej0 >= sent - 5  # a random stamp lands within the jitter of the true clock ~2e-7 of the time
    assert c["rx_clock_went_back"] + c["rx_clock_jumped_ahead"] == c["rx_clock_rejected"] - rej0
    # the autopilot is asked for nothing new, the operator told once per 10 s
    assert len(vehicle.received("COMMAND_LONG")) == n_cmd and len(vehicle.received("REQUEST_DATA_STREAM")) == n_rds
    assert not any("reboot" in text for _, text in events)
    assert 1 <= sum("rejected" in text for _, text in events) <= 3
    assert len(caplog.records) <= 5  # the log: one line per 10 s with the count (it grew 2 MB in 20 s)
    # the real telemetry kept flowing, and only it is in the buffer
    assert link.telemetry.is_fresh(clock.t) and link.status().streams["ATTITUDE"] == "ok"
    ms = link.telemetry._att.ms
    assert ms.min() >= vehicle.boot_ms(clock.t) - 11_000 and ms.max() <= vehicle.boot_ms(clock.t)
    # per source: the autopilot's own entry counts the rejections
    assert link.status().sources[f"{VEHICLE_SYSID}/1"]["clock_rejected"] == c["rx_clock_rejected"]
    assert link.status().counters["clock.candidates_evicted"] > 6000 - 100  # the candidate table stayed at its cap
    assert link.guard.candidate_count <= LinkConfig().max_clock_candidates


def test_a_reboot_seen_in_one_stream_needs_the_heartbeat_gap(pair):
    link, vehicle, clock = pair("accept")
    run(link, vehicle, clock, 6.0)
    vehicle.periods = lambda: {30: 0.02}  # only ATTITUDE streams (one message type: no cross-check)
    vehicle.next_due.clear()
    # new clock in one stream, heartbeats going on: a lone stream that jumped is not a reboot
    vehicle.tboot_shift = -100.0
    run(link, vehicle, clock, 4.0)
    c = link.status().counters
    assert c.get("vehicle_reboots", 0) == 0 and c["rx_clock_went_back"] > 100
    # the autopilot really reboots: silence (no heartbeat, no telemetry) for 2 s, then a new clock
    vehicle.heartbeats = vehicle.streaming = False
    run(link, vehicle, clock, 2.0)
    vehicle.boot, vehicle.tboot_shift = clock.t, 0.0
    vehicle.heartbeats = vehicle.streaming = True
    vehicle.next_hb = -math.inf
    vehicle.next_due.clear()
    run(link, vehicle, clock, 2.0)
    c = link.status().counters
    assert c["vehicle_reboots"] == 1 and c["telemetry.reset"] == 1
    assert link.guard.history[-1][1] == "reboot"
    assert link.telemetry.attitude_count > 20  # the new clock's samples arrive again


def test_a_consistent_fake_clock_is_no_reboot_while_the_real_one_runs(pair):
    """Spoofed ATTITUDE and LOCAL_POSITION_NED on a consistent clock of their own (the cross-check
    passes) interleaved with the autopilot's: the old clock is alive, so no reboot is declared."""
    link, vehicle, clock = pair("accept")
    run(link, vehicle, clock, 6.0)
    spoof = _spoofer(vehicle)
    for k in range(int(10.0 / DT)):
        clock.t += DT
        vehicle.step(clock.t)
        ms = int((clock.t - 1000.0) * 1000) + 5_000  # a clock of its own, 5 s ahead of... nothing
        spoof.send(mavlink.MAVLink_attitude_message(ms, 0.5, 0.5, 0.5, 0, 0, 0))
        spoof.send(mavlink.MAVLink_local_position_ned_message(ms, 99.0, 99.0, 99.0, 0, 0, 0))
        link.poll()
    c = link.status().counters
    assert c.get("vehicle_reboots", 0) == 0 and c["clock.candidate_old_clock_alive"] > 0
    assert c["rx_clock_rejected"] >= 2 * int(10.0 / DT) - 2
    r = link.telemetry.pose_at(clock.t - 0.1, now=clock.t)
    assert r.ok and r.pose.p_world[0] == pytest.approx(clock.t - 0.1, abs=0.02)  # x = t: no spoofed x = 99 in the buffer


def test_reboots_are_declared_at_most_once_per_min_interval(pair):
    link, vehicle, clock = pair("accept", config=LinkConfig(reboot_min_interval_s=5.0))
    run(link, vehicle, clock, 6.0)
    vehicle.boot = clock.t - 30.0  # reboot 1 (all streams on a new clock, 30 s in; the old one, ~106 s in, silent)
    vehicle.next_due.clear()
    run(link, vehicle, clock, 2.0)
    assert link.status().counters["vehicle_reboots"] == 1
    t1 = link.guard.history[-1][0]
    vehicle.boot = clock.t - 0.2  # reboot 2, 2 s later
    vehicle.next_due.clear()
    run(link, vehicle, clock, 1.5)
    c = link.status().counters
    assert c["vehicle_reboots"] == 1 and c["rx_clock_reboot_rate_limited"] > 0
    run(link, vehicle, clock, 3.0)
    c = link.status().counters
    assert c["vehicle_reboots"] == 2 and link.guard.history[-1][0] - t1 >= 5.0
    assert link.telemetry.is_fresh(clock.t)


def test_other_systems_and_components_are_counted_per_source_and_change_nothing(pair):
    cfg = LinkConfig(max_sources=8)
    link, vehicle, clock = pair("accept", config=cfg)
    run(link, vehicle, clock, 6.0)
    before = link.status()
    n_att = link.telemetry.counters["attitude_appended"]
    n_cmd = len(vehicle.received("COMMAND_LONG"))
    for k in range(60):  # 60 sources: other vehicles, the vehicle's other components, ground stations
        other = mavlink.MAVLink(vehicle.conn, srcSystem=1 + k % 250, srcComponent=1 if k % 2 else 100 + k)
        if other.srcSystem == VEHICLE_SYSID and other.srcComponent == 1:
            continue
        ms = vehicle.boot_ms(clock.t)
        other.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3))
        other.send(mavlink.MAVLink_attitude_message(ms + 1, 1.0, 1.0, 1.0, 0, 0, 0))
        other.send(mavlink.MAVLink_attitude_message(5, 1.0, 1.0, 1.0, 0, 0, 0))  # "rebooted"
        other.send(mavlink.MAVLink_local_position_ned_message(ms + 1, 99.0, 0, 0, 0, 0, 0))
        other.send(mavlink.MAVLink_command_ack_message(511, mavlink.MAV_RESULT_DENIED, 0, 0, VEHICLE_SYSID, 196))
        other.send(mavlink.MAVLink_timesync_message(10**12, 12345))
        run(link, vehicle, clock, DT)
    run(link, vehicle, clock, 2.0)
    st = link.status()
    c = st.counters
    assert st.vehicle_system_id == VEHICLE_SYSID and st.system_id == VEHICLE_SYSID
    assert c.get("vehicle_reboots", 0) == 0 and c.get("telemetry.reset", 0) == 0
    assert c["streams.restarts"] == before.counters["streams.restarts"] and st.streams == before.streams
    assert c["rx_foreign"] >= 5 * 59 and c["rx_heartbeat_other_vehicle"] + c["rx_heartbeat_other"] >= 59
    assert link.telemetry.counters["attitude_appended"] > n_att  # the real stream went on
    assert len(vehicle.received("COMMAND_LONG")) == n_cmd
    r = link.telemetry.pose_at(clock.t - 0.1, now=clock.t)
    assert r.ok and r.pose.p_world[0] == pytest.approx(clock.t - 0.1, abs=0.02)
    # bounded table; the autopilot's entry is never evicted
    assert len(st.sources) == 8 and f"{VEHICLE_SYSID}/1" in st.sources and c["sources_evicted"] > 40


def test_stream_requests_stay_within_the_budget(pair):
    """A vehicle that never answers SET_MESSAGE_INTERVAL and never streams: the companion keeps
    trying, at most stream_request_burst at once and one per stream_request_interval_s after."""
    cfg = LinkConfig()
    link, vehicle, clock = pair("ignore", config=cfg)
    vehicle.streaming = False
    run(link, vehicle, clock, 30.0)
    reqs = vehicle.received("COMMAND_LONG") + vehicle.received("REQUEST_DATA_STREAM")
    assert len(reqs) <= cfg.stream_request_burst + 30.0 / cfg.stream_request_interval_s + 1
    assert len(reqs) >= 10  # it does keep asking
    assert link.status().counters["streams.rate_limited"] > 0


def test_udpin_sends_only_to_addresses_that_spoke_valid_mavlink_of_the_vehicle(pair):
    link, vehicle, clock = pair("accept", config=LinkConfig(max_udp_peers=2))
    run(link, vehicle, clock, 1.0)
    port = vehicle.conn.destination_addr[1]
    strangers = []
    for k in range(5):  # garbage, or valid MAVLink from another system, from five other addresses
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setblocking(False)
        s.bind(("127.0.0.1", 0))
        if k % 2:
            s.sendto(b"\xfd\x09garbage" * 3, ("127.0.0.1", port))
        else:
            other = mavlink.MAVLink(None, srcSystem=7, srcComponent=1)
            s.sendto(bytes(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(other)), ("127.0.0.1", port))
        strangers.append(s)
    run(link, vehicle, clock, 2.5)
    try:
        for s in strangers:  # none of them receives our traffic
            with pytest.raises(BlockingIOError):
                s.recv(4096)
        assert {port for _, port in link.transport.conn.clients} == {vehicle.conn.port.getsockname()[1]}
        n = len(vehicle.received("HEARTBEAT"))
        run(link, vehicle, clock, 1.0)
        assert len(vehicle.received("HEARTBEAT")) > n  # the vehicle still does
        # addresses that do send the vehicle's MAVLink (a router, a second radio) become peers, at most max_udp_peers
        for s in strangers:
            s.sendto(bytes(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(_spoofer(vehicle))), ("127.0.0.1", port))
        run(link, vehicle, clock, 0.1)
        assert len(link.transport.conn.clients) == 2 and link.counters["udp_peers_evicted"] >= 4
    finally:
        for s in strangers:
            s.close()
