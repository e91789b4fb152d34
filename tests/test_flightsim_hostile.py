"""Hostile traffic and telemetry blackouts on the simulated autopilot's link (flightsim/hostile.py), and the
hostile-traffic benchmark's measurements (bench/hostile.py): the injector makes every kind, its counts
match what went over the wire, and a short SITL flight with hostile traffic and a blackout is measured."""

from __future__ import annotations

import collections
import math
import socket

import pytest

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.errors import ConfigError
from flightsim.autopilot import UdpEndpoint
from flightsim.hostile import BLACKOUT_LINK, BLACKOUT_TELEMETRY, GLUE_PARTS, KINDS, Blackout, HostileConfig, HostileInjector

SYSID = 1


def _parse(buf: bytes) -> list:
    """Every message a robust MAVLink parser gets from one datagram (as the companion parses UDP)."""
    p = mavlink.MAVLink(None)
    p.robust_parsing = True
    try:
        return list(p.parse_buffer(buf) or [])
    except Exception as exc:  # pragma: no cover - would be a parser bug the companion must survive
        return [exc]


@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_is_what_it_says(kind):
    inj = HostileInjector(HostileConfig(rate_hz=1.0, seed=3, kinds=(kind,)), SYSID)
    for _ in range(60):
        parts: list[str] = []
        buf = inj.make(kind, 123_456, parts)
        assert isinstance(buf, bytes) and buf
        msgs = _parse(buf)
        types = [m.get_type() for m in msgs]
        if kind == "bad_crc":
            assert types == ["BAD_DATA"] and "CRC" in msgs[0].reason
        elif kind == "truncated":
            assert all(t == "BAD_DATA" for t in types)  # at most garbage: never a whole message
        elif kind == "unknown_id":
            assert len(types) == 1 and types[0].startswith("UNKNOWN_")
        elif kind == "nan_payload":
            (m,) = msgs
            assert m.get_type() in ("ATTITUDE", "LOCAL_POSITION_NED")
            assert (m.get_srcSystem(), m.get_srcComponent()) == (SYSID, 1) and m.time_boot_ms == 123_456
            vals = [v for k, v in m.to_dict().items() if k not in ("mavpackettype", "time_boot_ms")]
            assert any(not math.isfinite(v) for v in vals)
        elif kind in ("spoof_attitude_own", "spoof_attitude_foreign"):
            (m,) = msgs
            assert m.get_type() == "ATTITUDE"
            src = (m.get_srcSystem(), m.get_srcComponent())
            assert (src == (SYSID, 1)) == (kind == "spoof_attitude_own")
            assert all(math.isfinite(v) for v in (m.roll, m.pitch, m.yaw))
        elif kind == "glued":
            assert 2 <= len(parts) <= 5 and set(parts) <= set(GLUE_PARTS) | {"truncated"}
            # every whole part comes out as one message (a cut one, last, as garbage at most)
            whole = [p for p in parts if p != "truncated"]
            assert len([t for t in types if t != "BAD_DATA"]) >= sum(1 for p in whole if p != "bad_crc") - 1
        else:
            assert kind == "random_bytes" and 1 <= len(buf) <= 300


def test_the_injector_is_seeded_and_follows_its_rate():
    cfg = HostileConfig(rate_hz=200.0, seed=7)
    a, b = HostileInjector(cfg, SYSID), HostileInjector(cfg, SYSID)
    got_a = [x for k in range(1, 101) for x in a.due(k * 0.1, k * 100)]
    got_b = [x for k in range(1, 101) for x in b.due(k * 0.1, k * 100)]
    assert [(k, buf) for k, buf, _ in got_a] == [(k, buf) for k, buf, _ in got_b]
    assert 2000 - 4 * math.sqrt(2000) < len(got_a) < 2000 + 4 * math.sqrt(2000)  # Poisson, 10 s at 200/s
    assert {k for k, _, _ in got_a} == set(KINDS)
    other = HostileInjector(HostileConfig(rate_hz=200.0, seed=8), SYSID)
    assert [buf for _, buf, _ in other.due(10.0, 0)] != [buf for _, buf, _ in got_a]


def test_counts_match_what_went_over_the_wire():
    """Sent through the simulator's endpoint to a socket: every datagram arrives, the counts by kind and the
    glued parts match a count made from the wire, and the parser's view agrees (whole messages per kind)."""
    ep = UdpEndpoint(0, SYSID)
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    rx.settimeout(2.0)
    try:
        ep.peer = rx.getsockname()
        inj = HostileInjector(HostileConfig(rate_hz=300.0, seed=11), SYSID)
        sent: list[tuple[str, bytes, list[str]]] = []
        for k in range(1, 51):  # 5 s
            for kind, buf, parts in inj.due(k * 0.1, k * 100):
                assert ep.send_raw(buf)
                inj.record(kind, buf, parts)
                sent.append((kind, buf, parts))
        wire = [rx.recv(65536) for _ in sent]
    finally:
        rx.close()
        ep.close()
    assert wire == [buf for _, buf, _ in sent]  # loopback keeps order and nothing is lost
    assert inj.datagrams == len(sent) and inj.bytes_sent == sum(len(b) for b in wire)
    assert dict(inj.counts) == dict(collections.Counter(k for k, _, _ in sent))
    assert set(inj.counts) == set(KINDS) and all(v > 0 for v in inj.counts.values())
    assert dict(inj.part_counts) == dict(collections.Counter(p for k, _, parts in sent if k == "glued" for p in parts))
    assert inj.packets == sum(v for k, v in inj.counts.items() if k != "glued") + sum(inj.part_counts.values())
    s = inj.summary()
    assert s["by_kind"] == dict(sorted(inj.counts.items())) and s["packets"] == inj.packets
    # the parser agrees: one valid ATTITUDE per spoof, one UNKNOWN per unknown id, one BAD_DATA (CRC) per bad CRC
    for kind, buf, _ in sent:
        types = [m.get_type() for m in _parse(buf)]
        if kind.startswith("spoof_attitude"):
            assert types == ["ATTITUDE"]
        elif kind == "unknown_id":
            assert len(types) == 1 and types[0].startswith("UNKNOWN_")
        elif kind == "bad_crc":
            assert types == ["BAD_DATA"]


def test_unsent_before_the_peer_is_known():
    ep = UdpEndpoint(0, SYSID)
    try:
        assert ep.send_raw(b"\xfd\x00") is False
    finally:
        ep.close()


def test_blackout_windows():
    b = Blackout(10.0, 3.0)
    assert b.end_s == 13.0
    assert b.silences("ATTITUDE", 10.0) and b.silences("LOCAL_POSITION_NED", 12.99) and not b.silences("ATTITUDE", 13.0)
    assert not b.silences("HEARTBEAT", 11.0) and not b.silences("SYSTEM_TIME", 11.0)
    hb = Blackout.parse("20:4:hb")
    assert (hb.start_s, hb.duration_s, hb.heartbeat) == (20.0, 4.0, True)
    assert all(hb.silences(n, 21.0) for n in BLACKOUT_TELEMETRY | BLACKOUT_LINK)
    assert not hb.silences("SYSTEM_TIME", 21.0)
    cfg = HostileConfig(blackouts=(hb, b))
    assert cfg.active and cfg.blackouts == (b, hb) and cfg.silenced("ATTITUDE", 11.0) == b
    assert cfg.silenced("HEARTBEAT", 11.0) is None and cfg.silenced("HEARTBEAT", 22.0) == hb
    assert not HostileConfig().active
    for bad in ("5", "a:b", "1:2:x", "1:0"):
        with pytest.raises((ValueError, ConfigError)):
            Blackout.parse(bad)
    with pytest.raises(ConfigError):
        HostileConfig(rate_hz=10, kinds=("no_such_kind",))
    with pytest.raises(ConfigError):
        HostileConfig(rate_hz=-1)


def test_glued_parts_follow_the_kinds_selected():
    inj = HostileInjector(HostileConfig(rate_hz=1.0, seed=2, kinds=("glued", "bad_crc", "unknown_id")), SYSID)
    seen: set[str] = set()
    for _ in range(200):
        parts: list[str] = []
        inj.make("glued", 0, parts)
        seen.update(parts)
    assert seen == {"bad_crc", "unknown_id", "gcs_heartbeat"}
