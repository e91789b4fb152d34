"""``companion monitor``: the pure view model (decoding, stale data, heartbeat timeout,
STATUSTEXT ring and chunks, rates, errors), the text renderer, and real processes listening on
UDP loopback to a sender of OBSTACLE_DISTANCE, HEARTBEAT and garbage."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from conftest import free_port
import numpy as np
import pytest

from companion.mavlink.dialect import UINT16_MAX, mavlink  # noqa: I001 (first: MAVLink 2)
from companion.cli import main
from companion.core.sectors import SectorState
from companion.errors import ConfigError
from companion.mavlink import messages as M
from companion.monitor.decode import DecodeError, bin_sectors, decode_distance_sensor, decode_obstacle_distance
from companion.monitor.runner import Reader
from companion.monitor.state import MonitorConfig, MonitorState
from companion.monitor.view import render_text

ROOT = Path(__file__).resolve().parents[1]
SYS, COMP = 7, 196


def wire(msg, sysid: int = SYS, comp: int = COMP):
    """Pack ``msg`` as (sysid, comp) sends it and parse it back: a message exactly as received."""
    buf = msg.pack(mavlink.MAVLink(None, sysid, comp))
    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True
    (m,) = rx.parse_buffer(buf)
    return m


def packed(msg, sysid: int = SYS, comp: int = COMP) -> bytes:
    return msg.pack(mavlink.MAVLink(None, sysid, comp))


def sectors_msg(values: dict[int, int], min_cm: int = 50, max_cm: int = 4000):
    d = np.full(72, UINT16_MAX, dtype=np.int64)
    for i, v in values.items():
        d[i] = v
    return M.obstacle_distance(d, min_cm, max_cm)


# ---------------------------------------------------------------------- decoding ---------------
def test_decode_unknown_clear_and_obstacle_sectors():
    d = decode_obstacle_distance(wire(sectors_msg({0: 1234, 1: 4001, 71: 250, 36: 0, 10: 30})))
    assert d.state[0] == SectorState.OBSTACLE and d.range_m[0] == pytest.approx(12.34)
    assert d.state[1] == SectorState.CLEAR and math.isnan(d.range_m[1])  # max_distance + 1
    assert d.state[71] == SectorState.OBSTACLE and d.bearing_deg[71] == pytest.approx(-5.0)
    assert d.state[36] == SectorState.OBSTACLE and d.range_m[36] == 0.0  # 0 = touching, a real value
    assert d.state[10] == SectorState.OBSTACLE and any("below min_distance" in w for w in d.warnings)
    assert d.state[5] == SectorState.UNKNOWN  # UINT16_MAX
    assert d.counts() == {"obstacle": 4, "clear": 1, "unknown": 67}
    assert d.increment_deg == 5.0 and d.frame_name == "BODY_FRD" and d.reference == "forward"
    r, b, i = d.nearest()
    assert (r, b, i) == (0.0, -180.0, 36)
    assert (d.min_distance_m, d.max_distance_m) == (0.5, 40.0)


def test_decode_uses_increment_f_angle_offset_and_frame():
    m = sectors_msg({0: 500, 3: 800})
    m.increment, m.increment_f, m.angle_offset, m.frame = 2, 2.5, -30.0, mavlink.MAV_FRAME_GLOBAL
    d = decode_obstacle_distance(wire(m))
    assert d.increment_deg == 2.5  # increment_f wins when non-zero
    assert d.bearing_deg[0] == pytest.approx(-30.0) and d.bearing_deg[3] == pytest.approx(-22.5)
    assert d.reference == "north" and any("GLOBAL" in w for w in d.warnings)
    assert not any("disagrees" in w for w in d.warnings)  # 2 vs 2.5: within rounding of the uint8
    m.increment_f = 0.0
    d = decode_obstacle_distance(wire(m))
    assert d.increment_deg == 2.0 and d.bearing_deg[3] == pytest.approx(-24.0)
    m.increment, m.increment_f = 10, 5.0
    assert any("disagrees" in w for w in decode_obstacle_distance(wire(m)).warnings)
    # display bins: 72 × 5°, obstacle = nearest in the bin, 18 bins combine four
    state, rng = bin_sectors(decode_obstacle_distance(wire(sectors_msg({0: 900, 1: 700, 2: 4001}))), 18)
    assert state[0] == SectorState.OBSTACLE and rng[0] == pytest.approx(7.0)
    state, _ = bin_sectors(decode_obstacle_distance(wire(sectors_msg({i: 4001 for i in range(8)}))), 18)
    assert state[1] == SectorState.CLEAR and state[0] == SectorState.UNKNOWN  # bin 0 also holds unknown sector 70/71


def test_decode_rejects_what_no_receiver_can_read():
    m = sectors_msg({0: 500})
    m.increment, m.increment_f = 0, 0.0
    with pytest.raises(DecodeError, match="increment"):
        decode_obstacle_distance(wire(m))
    m = sectors_msg({0: 500})
    m.min_distance, m.max_distance = 4000, 4000
    with pytest.raises(DecodeError, match="min_distance"):
        decode_obstacle_distance(wire(m))
    m = sectors_msg({0: 5000})  # above max + 1 (the encoder refuses it; build it by hand)
    m.distances = list(m.distances)
    m.distances[0] = 5000
    d = decode_obstacle_distance(wire(m))
    assert d.state[0] == SectorState.UNKNOWN and any("above max_distance" in w for w in d.warnings)


def test_decode_distance_sensor_sigma_quality_and_states():
    f = decode_distance_sensor(wire(M.distance_sensor("obstacle", 12.0, 0.1, 50, 4000)))
    assert f.state == "obstacle" and f.distance_m == pytest.approx(12.0)
    assert f.covariance_cm2 == 100 and f.sigma_m == pytest.approx(0.1) and f.signal_quality > 90
    f = decode_distance_sensor(wire(M.distance_sensor("obstacle", 12.0, 0.5, 50, 4000)))
    assert f.covariance_cm2 == 255 and math.isnan(f.sigma_m)  # 2500 cm² does not fit: 255 = unknown
    f = decode_distance_sensor(wire(M.distance_sensor("clear", math.nan, math.nan, 50, 4000)))
    assert f.state == "clear" and math.isnan(f.distance_m)
    f = decode_distance_sensor(wire(M.distance_sensor("unknown", math.nan, math.nan, 50, 4000)))
    assert f.state == "unknown" and f.signal_quality == 1


# ---------------------------------------------------------------------- state folding ----------
def test_sectors_go_stale_after_half_a_second_and_link_is_lost_after_three():
    st = MonitorState(MonitorConfig(), start=100.0)
    assert st.snapshot(100.5).link_state == "waiting"
    assert st.snapshot(103.5).link_state == "lost"  # 3 s without hearing anything
    st.add(wire(M.heartbeat(mavlink.MAV_STATE_ACTIVE)), 104.0)
    st.add(wire(sectors_msg({0: 800})), 104.0)
    s = st.snapshot(104.4)
    assert s.link_state == "ok" and s.health_current and s.system_status == mavlink.MAV_STATE_ACTIVE
    assert not s.sectors_stale and s.sectors_age_s == pytest.approx(0.4)
    s = st.snapshot(104.6)
    assert s.sectors_stale and s.link_state == "ok"
    js = s.to_json()
    assert js["sectors"]["stale"] is True and js["sectors"]["age_s"] == pytest.approx(0.6)
    assert js["health"] == {"status": "ACTIVE", "system_status": 4, "mav_type": 18, "current": True}
    assert st.snapshot(106.9).link_state == "ok"
    s = st.snapshot(107.1)  # 3.1 s since the HEARTBEAT
    assert s.link_state == "lost" and not s.health_current and s.to_json()["health"]["current"] is False
    # a fresh OBSTACLE_DISTANCE after the link is lost: messages arrive, HEARTBEAT does not
    st.add(wire(sectors_msg({0: 800})), 107.2)
    s = st.snapshot(107.3)
    assert s.link_state == "no_heartbeat" and not s.sectors_stale and not s.health_current and s.heard
    # sectors before the first 1 Hz HEARTBEAT: waiting for it, not yet "no heartbeat"
    st = MonitorState(MonitorConfig(), start=0.0)
    st.add(wire(sectors_msg({0: 800})), 0.2)
    s = st.snapshot(0.3)
    assert s.link_state == "waiting" and s.heard and not s.sectors_stale
    st.add(wire(sectors_msg({0: 800})), 3.1)
    assert st.snapshot(3.2).link_state == "no_heartbeat"


def test_only_the_companion_component_of_one_system_is_followed():
    st = MonitorState(MonitorConfig(), start=0.0)
    assert not st.add(wire(M.heartbeat(mavlink.MAV_STATE_CRITICAL), SYS, 1), 0.1)  # the autopilot, not us
    assert st.add(wire(M.heartbeat(mavlink.MAV_STATE_STANDBY)), 0.2)
    assert not st.add(wire(M.heartbeat(mavlink.MAV_STATE_ACTIVE), 9, COMP), 0.3)  # another vehicle's companion
    s = st.snapshot(0.5)
    assert s.system_id == SYS and s.system_status == mavlink.MAV_STATE_STANDBY
    assert s.other_companions == (9,) and s.other_messages == 2 and (SYS, 1) in s.other_sources
    st2 = MonitorState(MonitorConfig(system_id=9, component_id=196), start=0.0)
    st2.add(wire(M.heartbeat(mavlink.MAV_STATE_STANDBY)), 0.2)
    st2.add(wire(M.heartbeat(mavlink.MAV_STATE_ACTIVE), 9, COMP), 0.3)
    assert st2.snapshot(0.5).system_status == mavlink.MAV_STATE_ACTIVE


def test_statustext_ring_keeps_the_last_five_and_reassembles_chunks():
    st = MonitorState(MonitorConfig(), start=0.0)
    for k in range(7):
        for m in M.statustext(f"text {k}", mavlink.MAV_SEVERITY_INFO):
            st.add(wire(m), float(k))
    long = "Ranging restarted: " + "x" * 60 + " end"
    for m in M.statustext(long, mavlink.MAV_SEVERITY_WARNING, chunk_id=42):
        st.add(wire(m), 8.0)
    s = st.snapshot(9.0)
    assert [t for _, _, t, _ in s.statustext] == ["text 3", "text 4", "text 5", "text 6", long]
    assert s.statustext[-1][1] == mavlink.MAV_SEVERITY_WARNING and s.statustext[-1][3] is True
    assert s.statustext[0][0] == pytest.approx(6.0)  # age
    # a chunked text whose end never comes is shown after 2 s, marked incomplete
    first = M.statustext("y" * 120, mavlink.MAV_SEVERITY_ERROR, chunk_id=5)[0]
    st.add(wire(first), 10.0)
    assert st.snapshot(11.0).statustext[-1][2] == long
    last = st.snapshot(12.5).statustext[-1]
    assert last[2] == "y" * 50 + "…" and last[3] is False
    # a text cannot inject terminal escapes
    st.add(wire(mavlink.MAVLink_statustext_message(6, b"\x1b[2Jhi", 0, 0)), 13.0)
    assert st.snapshot(13.0).statustext[-1][2] == "?[2Jhi"


def test_rates_and_counts_over_the_window():
    st = MonitorState(MonitorConfig(rate_window_s=2.0), start=0.0)
    msg = wire(sectors_msg({0: 800}))
    hb = wire(M.heartbeat())
    for k in range(40):  # 10 Hz for 4 s
        st.add(msg, 0.1 * k)
        if k % 10 == 0:
            st.add(hb, 0.1 * k)
    s = st.snapshot(3.95)  # window (1.95, 3.95]: 20 messages
    assert s.rates_hz["OBSTACLE_DISTANCE"] == pytest.approx(10.0)
    assert s.rates_hz["HEARTBEAT"] == pytest.approx(1.0)
    assert s.counts == {"HEARTBEAT": 4, "OBSTACLE_DISTANCE": 40}
    early = MonitorState(MonitorConfig(), start=0.0)
    for k in range(10):
        early.add(msg, 0.1 * k)
    assert early.snapshot(1.0).rates_hz["OBSTACLE_DISTANCE"] == pytest.approx(10.0)  # not 5: 1 s listened
    assert math.isnan(early.snapshot(0.3).rates_hz["OBSTACLE_DISTANCE"])  # too early to say
    assert st.snapshot(7.0).rates_hz["OBSTACLE_DISTANCE"] == 0.0  # stopped


def test_diagnostics_forward_and_errors_from_garbage():
    st = MonitorState(MonitorConfig(), start=0.0)
    for name, v in (("MR_FPS", 14.5), ("MR_TRACKS", 42), ("MR_NEAR_M", 3.25)):
        st.add(wire(M.named_value_float(name, v)), 1.0)
    st.add(wire(M.distance_sensor("obstacle", 3.4, 0.12, 50, 4000)), 1.0)
    side = M.distance_sensor("obstacle", 1.0, 0.1, 50, 4000, orientation=mavlink.MAV_SENSOR_ROTATION_YAW_90)
    st.add(wire(side), 1.0)  # not forward: counted, not shown as the forward range
    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True
    good = packed(M.heartbeat())
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    rng = np.random.default_rng(3)
    for m in rx.parse_buffer(bytes(rng.integers(0, 256, 200, dtype=np.uint8)) + bytes(bad_crc) + good) or []:
        st.add(m, 1.0)
    bad = sectors_msg({0: 500})
    bad.increment, bad.increment_f = 0, 0.0
    assert not st.add(wire(bad), 1.0)
    s = st.snapshot(1.2)
    assert [(n, v) for n, v, _ in s.diagnostics] == [("MR_FPS", 14.5), ("MR_NEAR_M", 3.25), ("MR_TRACKS", 42.0)]
    assert s.forward.distance_m == pytest.approx(3.4) and s.forward.sigma_m == pytest.approx(0.12)
    assert s.counts["DISTANCE_SENSOR"] == 2 and s.system_status == mavlink.MAV_STATE_STANDBY
    assert s.errors["bad_crc"] >= 1 and s.errors["invalid_OBSTACLE_DISTANCE"] == 1
    assert s.sectors is None  # the undecodable message did not become the current sectors


# ---------------------------------------------------------------------- rendering --------------
def _known_state() -> MonitorState:
    st = MonitorState(MonitorConfig(), start=0.0)
    st.add(wire(M.heartbeat(mavlink.MAV_STATE_ACTIVE)), 9.5)
    # forward (sector 0) 3.2 m, +5° 12 m, +10° 30 m, +15°/+20° clear, −5° 30 m, rest unknown
    st.add(wire(sectors_msg({0: 320, 1: 1200, 2: 3000, 3: 4001, 4: 4001, 71: 3000})), 9.9)
    st.add(wire(M.distance_sensor("obstacle", 3.2, 0.15, 50, 4000)), 9.9)
    st.add(wire(M.named_value_float("MR_FPS", 15.0)), 9.0)
    st.add(wire(M.named_value_float("MR_NEAR_M", 3.2)), 9.0)
    for m in M.statustext("Ranging: ACTIVE", mavlink.MAV_SEVERITY_NOTICE):
        st.add(wire(m), 8.0)
    return st


def test_render_known_state_to_text():
    text = render_text(_known_state().snapshot(10.0), "udpin:127.0.0.1:14550", width=110)
    lines = text.splitlines()
    strip = next(line for line in lines if "█" in line)
    glyphs = strip[strip.index("·"):strip.rindex("·") + 1]
    assert len(glyphs) == 72
    # display column 36 is forward (sector 0), 37 = +5°, 38 = +10°, 39/40 = +15°/+20°, 35 = −5°;
    # bar level = floor(8 · range / 40 m): 3.2 m → 0 (█), 12 m → 2 (▆), 30 m → 6 (▂)
    assert glyphs[36] == "█" and glyphs[37] == "▆" and glyphs[38] == "▂" and glyphs[39:41] == "○○" and glyphs[35] == "▂"
    assert glyphs.count("·") == 66
    axis = lines[lines.index(strip) + 1]
    off = strip.index(glyphs)
    assert axis[off + 36] == "F" and axis[off + 54] == "R" and axis[off] == "B" and axis[off + 18] == "L"
    assert "ACTIVE" in text and "heartbeat 0.50 s ago" in text and "link OK" in text
    assert "nearest     3.20 m at +0° from forward" in text
    assert "3.20 m ± 0.15 m · quality" in text
    assert "diagnostics fps 15  nearest m 3.2" in text
    assert "NOTICE" in text and "Ranging: ACTIVE" in text
    assert "obstacle 4 · clear 2 · unknown 66" in text and "BODY_FRD" in text and "0.50–40.00 m" in text
    assert "STALE" not in text


def test_render_marks_stale_data_and_lost_link_never_as_current():
    st = _known_state()
    text = render_text(st.snapshot(10.6), width=110)  # sectors 0.7 s old, heartbeat 1.1 s
    assert "STALE · last OBSTACLE_DISTANCE 0.70 s ago" in text
    assert "nearest     — STALE (was 3.20 m" in text and "ACTIVE" in text
    text = render_text(st.snapshot(13.0), width=110)  # 3.5 s without a HEARTBEAT
    assert "LINK LOST" in text and "unknown" in text and "said ACTIVE" in text
    assert "STALE" in text
    text = render_text(MonitorState(MonitorConfig(), start=0.0).snapshot(0.1), width=110)
    assert "waiting for the companion" in text and "no OBSTACLE_DISTANCE received" in text
    narrow = render_text(st.snapshot(10.0), width=60)  # 36 bins of 10° when 72 do not fit
    strip = next(line for line in narrow.splitlines() if "█" in line)
    assert strip.count("·") + strip.count("█") + strip.count("○") + sum(strip.count(g) for g in "▇▆▅▄▃▂▁") == 36


# ---------------------------------------------------------------------- I/O --------------------
class _Sender:
    """Sends the companion's messages (and some garbage) to a UDP port at ~10 Hz until stopped."""

    def __init__(self, port: int, garbage: bool = True):
        self.port = port
        self.garbage = garbage
        self.stop = threading.Event()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.mav = mavlink.MAVLink(None, SYS, COMP)
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _send(self, msg) -> None:
        try:
            self.sock.sendto(msg.pack(self.mav), ("127.0.0.1", self.port))
        except OSError:
            pass

    def _run(self) -> None:
        k = 0
        while not self.stop.is_set():
            self._send(sectors_msg({0: 640, 1: 4001, 2: 1500}))
            if k % 5 == 0:
                self._send(M.heartbeat(mavlink.MAV_STATE_ACTIVE))
                self._send(M.named_value_float("MR_FPS", 9.5))
                for m in M.statustext(f"tick {k}", mavlink.MAV_SEVERITY_INFO):
                    self._send(m)
                if self.garbage:
                    bad = bytearray(packed(M.heartbeat(mavlink.MAV_STATE_CRITICAL)))
                    bad[-2] ^= 0x55  # CRC broken: must not count as a CRITICAL heartbeat
                    for junk in (bytes(bad), os.urandom(37), packed(M.heartbeat())[:7]):
                        try:
                            self.sock.sendto(junk, ("127.0.0.1", self.port))
                        except OSError:
                            pass
            k += 1
            time.sleep(0.1)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(2)
        self.sock.close()


def _env():
    return {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "110"}


def test_end_to_end_once_json_over_udp_loopback():
    port = free_port()
    with _Sender(port):
        p = subprocess.run([sys.executable, "-m", "companion", "monitor", f"udpin:127.0.0.1:{port}", "--once", "--json",
                            "--duration", "1.5"], capture_output=True, text=True, timeout=30, cwd=ROOT, env=_env())
    assert p.returncode == 0, p.stderr
    lines = p.stdout.strip().splitlines()
    assert len(lines) == 1
    js = json.loads(lines[0])
    assert js["link"]["state"] == "ok" and js["link"]["system_id"] == SYS
    assert js["health"]["status"] == "ACTIVE" and js["health"]["current"] is True  # the bad-CRC CRITICAL never counted
    sec = js["sectors"]
    assert sec["stale"] is False and sec["counts"] == {"obstacle": 2, "clear": 1, "unknown": 69}
    assert sec["nearest_m"] == pytest.approx(6.4) and sec["nearest_bearing_deg"] == 0.0
    assert sec["distances_cm"][:3] == [640, 4001, 1500] and sec["frame"] == "BODY_FRD"
    assert 5.0 < js["rates_hz"]["OBSTACLE_DISTANCE"] < 13.0
    assert js["diagnostics"]["MR_FPS"]["value"] == 9.5
    assert js["statustext"] and js["statustext"][-1]["text"].startswith("tick")
    assert js["errors"].get("bad_crc", 0) >= 1 and sum(js["errors"].values()) >= 3


def test_text_snapshots_without_a_tty_and_ctrl_c_exits_0():
    port = free_port()
    with _Sender(port, garbage=False):
        p = subprocess.Popen([sys.executable, "-m", "companion", "monitor", f"udpin:127.0.0.1:{port}", "--interval", "0.4"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=_env())
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(iter(p.stdout.readline, "")), daemon=True)
        reader.start()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and sum(line.startswith("╭") for line in lines) < 3 and p.poll() is None:
            time.sleep(0.05)
        p.send_signal(signal.SIGINT)
        p.wait(timeout=10)
        reader.join(5)
        err = p.stderr.read()
    out = "".join(lines)
    assert p.returncode == 0, err
    assert out.count("╭") >= 3  # a snapshot per --interval, no Live animation (no cursor movement)
    assert "\x1b[" not in out
    assert "6.40 m at +0° from forward" in out and "ACTIVE" in out


def test_bad_connection_strings_exit_2(capsys, tmp_path):
    log = tmp_path / "flight.tlog"
    log.write_bytes(b"\x00" * 10)
    for conn, fragment in (("udpin:127.0.0.1", "KIND:HOST:PORT"), ("udpin:127.0.0.1:99999", "out of range"),
                           ("/dev/tty_no_such_device", "cannot open"), (str(log), "is a file")):
        assert main(["monitor", conn, "--once", "--duration", "0.1"]) == 2
        assert fragment in capsys.readouterr().err, conn
    assert main(["monitor", "udpin:127.0.0.1:0", "--duration", "-1"]) == 2
    assert "--duration" in capsys.readouterr().err
    assert main(["monitor", "udpin:127.0.0.1:0", "--component", "300"]) == 2
    assert "component_id" in capsys.readouterr().err
    with pytest.raises(ConfigError):
        MonitorConfig(near_m=20.0, mid_m=10.0)


def test_once_exits_1_when_nothing_is_heard(capsys):
    rc = main(["monitor", f"udpin:127.0.0.1:{free_port()}", "--once", "--duration", "0.3", "--passive"])
    assert rc == 1
    assert "waiting for the companion" in capsys.readouterr().out


def test_reader_counts_truncated_datagrams_and_keeps_going():
    class FakeUDP:
        def __init__(self, datagrams):
            self.datagrams = list(datagrams)
            self.mav = mavlink.MAVLink(None)
            self.mav.robust_parsing = True

        def recv(self, n=None):
            return self.datagrams.pop(0) if self.datagrams else b""

    hb = packed(M.heartbeat(mavlink.MAV_STATE_ACTIVE))
    fake = FakeUDP([hb[:9], hb, b"\xfd\xfd\xfd", hb])
    reader = Reader(fake)
    reader.datagram = True
    st = MonitorState(MonitorConfig(), start=0.0)
    assert reader.pump(st, 1.0) >= 2
    s = st.snapshot(1.0)
    assert s.counts["HEARTBEAT"] == 2 and s.errors["truncated"] == 2 and s.system_status == mavlink.MAV_STATE_ACTIVE


def test_why_the_forward_sector_is_unknown_in_words():
    """MR_FWD_WHY (an UnknownReason code) is shown as words, and not at all while the forward sector claims."""
    st = _known_state()
    st.add(wire(M.named_value_float("MR_FWD_WHY", 4.0)), 9.0)
    assert "forward unknown: few far" in render_text(st.snapshot(10.0), "udpin:127.0.0.1:14550", width=110)
    st.add(wire(M.named_value_float("MR_FWD_WHY", 0.0)), 9.5)
    assert "forward unknown" not in render_text(st.snapshot(10.0), "udpin:127.0.0.1:14550", width=110)
    st.add(wire(M.named_value_float("MR_FWD_WHY", 99.0)), 9.6)
    assert "forward unknown: code 99" in render_text(st.snapshot(10.0), "udpin:127.0.0.1:14550", width=110)
