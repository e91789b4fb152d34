"""The per-frame pipeline, the reporter and the live Companion against a loopback vehicle.

The vehicle is a separate pymavlink connection (its own parser) playing the autopilot of a
:class:`~bench.latency.SyntheticFlight`: HEARTBEAT at 1 Hz from component 1, ATTITUDE
at 50 Hz and LOCAL_POSITION_NED at 20 Hz on its own boot clock, TIMESYNC replies, COMMAND_ACKs.
Frames of the same flight are rendered at 30 fps and handed to the companion through an in-memory
source.  Everything runs on one simulated clock stepped in 5 ms (loopback UDP delivers at once),
so the tests are deterministic; every message the companion sends is decoded by the vehicle's
parser and checked against DESIGN §5.
"""

from __future__ import annotations

import dataclasses
import math

from conftest import free_port
import numpy as np
import pytest

from companion.mavlink.dialect import UINT16_MAX, mavlink, mavutil  # noqa: I001 (first: MAVLink 2)
from bench.latency import SyntheticFlight, feed_telemetry
from companion.camera_sources import Frame, FrameSource
from companion.core.camera import CameraConfig
from companion.io.config_files import CompanionConfig
from companion.mavlink.link import MavLink
from companion.mavlink.timesync import NS
from companion.app import Companion
from companion.pipeline import FrameResult, Pipeline, PipelineConfig
from companion.reporter import HealthState, Reporter
from companion.telemetry import TelemetryBuffer

DT = 0.005
FPS = 30.0
BOOT = 400.0  # the vehicle booted at companion time 400 s
T0 = 1000.0  # flight time 0 on the companion clock
SYSID = 7
CAM = CameraConfig.from_fov(320, 240, 60.0)


def small_config(**over) -> CompanionConfig:
    base = CompanionConfig()
    cfg = dataclasses.replace(
        base, camera=CAM,
        tracks=dataclasses.replace(base.tracks, max_tracks=120),
        harris=dataclasses.replace(base.harris, max_corners=120),
    )
    return dataclasses.replace(cfg, **over)


class Clock:
    def __init__(self, t: float):
        self.t = t

    def __call__(self) -> float:
        return self.t


class ListSource(FrameSource):
    """In-memory camera: the test pushes frames (validated like any source)."""

    kind = "test"

    def __init__(self, width=CAM.width, height=CAM.height):
        super().__init__("test-camera", width, height)
        self._set_connected(True)

    def push(self, index: int, t: float, img) -> None:
        f = self._accept(index, t, img)
        if f is not None:
            self._publish(f)


class LoopbackVehicle:
    """The autopilot of a SyntheticFlight over loopback UDP (see module docstring)."""

    def __init__(self, port: int, flight: SyntheticFlight, sysid: int = SYSID, boot: float = BOOT, t0: float = T0):
        self.port, self.flight, self.sysid = port, flight, sysid
        self.boot, self.t0 = boot, t0  # clock time at the vehicle's boot / at flight time 0
        self.conn = self._open()
        self.rx: list = []  # (t, message)
        self.heartbeats = True
        self.streaming = True
        self.next = {"hb": -math.inf, "att": -math.inf, "pos": -math.inf}
        self.rates = {"att": 50.0, "pos": 20.0}

    def _open(self):
        return mavutil.mavlink_connection(f"udpout:127.0.0.1:{self.port}", source_system=self.sysid, source_component=1)

    def reconnect(self) -> None:
        """A new socket (new source port), as after a radio or router restart."""
        self.conn.close()
        self.conn = self._open()

    def received(self, name: str, since: float = -math.inf) -> list:
        return [m for t, m in self.rx if m.get_type() == name and t >= since]

    def received_t(self, name: str, since: float = -math.inf) -> list:
        return [(t, m) for t, m in self.rx if m.get_type() == name and t >= since]

    def send(self, msg) -> None:
        self.conn.mav.send(msg)

    def step(self, t: float) -> None:
        while True:
            data = self.conn.recv()
            if not data:
                break
            for m in self.conn.mav.parse_buffer(data) or []:
                self.rx.append((t, m))
                self._handle(m, t)
        boot_ms = int(round((t - self.boot) * 1000))
        ft = t - self.t0
        if self.heartbeats and t >= self.next["hb"]:
            self.next["hb"] = t + 1.0
            self.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0,
                                                        mavlink.MAV_STATE_ACTIVE, 3))
        if not self.streaming:
            return
        if t + 1e-9 >= self.next["att"]:
            self.next["att"] = max(self.next["att"] + 1 / self.rates["att"], t + 0.5 / self.rates["att"])
            self.send(mavlink.MAVLink_attitude_message(boot_ms, *self.flight.attitude_fields(ft)))
        if t + 1e-9 >= self.next["pos"]:
            self.next["pos"] = max(self.next["pos"] + 1 / self.rates["pos"], t + 0.5 / self.rates["pos"])
            self.send(mavlink.MAVLink_local_position_ned_message(boot_ms, *self.flight.local_position_fields(ft)))

    def _handle(self, m, t: float) -> None:
        typ = m.get_type()
        if typ == "COMMAND_LONG" and m.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            self.send(mavlink.MAVLink_command_ack_message(m.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0,
                                                          m.get_srcSystem(), m.get_srcComponent()))
            key = {30: "att", 32: "pos"}.get(int(m.param1))
            if key and m.param2 > 0:
                self.rates[key] = 1e6 / m.param2
        elif typ == "TIMESYNC" and m.tc1 == 0:
            self.send(mavlink.MAVLink_timesync_message(int((t - self.boot) * NS), m.ts1))


class Rig:
    """Companion + loopback vehicle + in-memory camera on one simulated clock."""

    def __init__(self, flight: SyntheticFlight | None = None, config: CompanionConfig | None = None,
                 pipeline: PipelineConfig = PipelineConfig(), gcs: str | None = None):
        self.flight = flight or SyntheticFlight(camera=CAM, wall_north_m=15.0, velocity_ned=(1.0, 3.0, 0.0))
        self.config = config or small_config()
        self.clock = Clock(T0 - 0.5)
        port = free_port()
        self.link = MavLink(f"udpin:127.0.0.1:{port}", self.config.link, clock=self.clock,
                            telemetry=TelemetryBuffer(self.config.telemetry))
        self.gcs = MavLink(gcs, self.config.link, clock=self.clock, role="gcs") if gcs else None
        self.vehicle = LoopbackVehicle(port, self.flight)
        self.source = ListSource()
        self.companion = Companion(self.config, self.source, self.link, self.gcs, pipeline, clock=self.clock)
        self.camera_on = True
        self.next_frame = 0
        self.frame_hook = None  # optional: (index, t, gray) -> image to push instead

    @property
    def t(self) -> float:
        return self.clock.t

    def run(self, seconds: float) -> None:
        for _ in range(int(round(seconds / DT))):
            self.clock.t += DT
            t = self.clock.t
            self.vehicle.step(t)
            while T0 + self.next_frame / FPS <= t + 1e-9:
                tc = T0 + self.next_frame / FPS
                if self.camera_on:
                    img = self.flight.render(tc - T0)
                    if self.frame_hook is not None:
                        img = self.frame_hook(self.next_frame, tc, img)
                    self.source.push(self.next_frame, tc, img)
                self.next_frame += 1
            self.companion.step()

    def close(self) -> None:
        self.companion.close()
        self.vehicle.conn.close()


@pytest.fixture
def rig():
    made = []

    def factory(*a, **kw):
        r = Rig(*a, **kw)
        made.append(r)
        return r

    yield factory
    for r in made:
        r.close()


def valid_cm(d) -> np.ndarray:
    d = np.asarray(d)
    return d[(d != UINT16_MAX)]


def check_obstacle_distance_fields(m, config: CompanionConfig) -> None:
    assert m.get_srcSystem() == SYSID and m.get_srcComponent() == 196
    assert len(m.distances) == 72
    assert m.increment == 5 and m.increment_f == 5.0 and m.angle_offset == 0.0
    assert m.frame == mavlink.MAV_FRAME_BODY_FRD
    assert m.min_distance == config.sectors.min_distance_cm and m.max_distance == config.sectors.max_distance_cm
    d = np.asarray(m.distances)
    assert not np.any(d == 0)  # 0 is "touching", never filler
    ok = (d == UINT16_MAX) | ((d >= m.min_distance) & (d <= m.max_distance + 1))
    assert ok.all(), d


def statustexts(vehicle, since=-math.inf) -> list[str]:
    return [m.text for m in vehicle.received("STATUSTEXT", since)]


# ---------------------------------------------------------------------- end to end, live -------
def test_wall_ahead_gives_forward_ranges_with_correct_fields(rig):
    r = rig()
    r.run(3.0)
    v, cfg = r.vehicle, r.config
    ods = v.received_t("OBSTACLE_DISTANCE")
    assert ods, "no OBSTACLE_DISTANCE"
    for _, m in ods:
        check_obstacle_distance_fields(m, cfg)
    # rate: 10–20 Hz once running
    late = [t for t, _ in ods if t >= T0 + 1.0]
    rate = (len(late) - 1) / (late[-1] - late[0])
    assert 10.0 <= rate <= 20.0, rate
    # after convergence: finite, sensible ranges in the forward sectors, unknown outside the view, never "clear"
    t_end = r.t
    truth = r.flight.wall_distance(t_end - T0)
    last = [m for t, m in ods if t >= t_end - 0.5]
    for m in last:
        d = np.asarray(m.distances)
        assert not np.any(d == m.max_distance + 1), "claimed clear in front of a wall"
        fwd = [d[i] for i in (70, 71, 0, 1, 2)]
        assert all(x != UINT16_MAX for x in fwd), fwd
        assert d[0] / 100 == pytest.approx(truth, rel=0.2) and d[0] / 100 <= truth * 1.05
        # outside the 60° view: unknown, or a remembered part of the wall (DESIGN §7) no farther than the
        # wall along that bearing (conservative), and nothing at all beyond ±80° where there is no wall
        for i in range(7, 66):
            if d[i] != UINT16_MAX:
                b = math.radians(i * 5.0 if i < 36 else i * 5.0 - 360.0)
                assert abs(b) < math.radians(80), (i, d[i])
                assert d[i] / 100 <= truth / math.cos(b) * 1.05, (i, d[i], truth / math.cos(b))
    # the vehicle's HEARTBEAT says PX4: OBSTACLE_DISTANCE is folded into its 10° bins (every even element
    # that makes a claim carries the nearest obstacle of its bin; unknown stays unknown)
    rep = r.companion.reporter
    assert rep.vehicle_autopilot == mavlink.MAV_AUTOPILOT_PX4 and rep.fold_for_px4() and rep.counters["px4_folded_sent"] > 0
    for m in last:
        d = np.asarray(m.distances).astype(np.int64)
        for k in range(0, 72, 2):
            nb = d[[(k - 1) % 72, k + 1]]
            assert d[k] == UINT16_MAX or d[k] <= nb[nb <= m.max_distance].min(initial=UINT16_MAX), (k, d[k - 1:k + 2])
    # forward DISTANCE_SENSOR with its covariance (sent when no obstacle of the front face lies distinctly nearer)
    dss = [m for t, m in v.received_t("DISTANCE_SENSOR") if t >= t_end - 0.5]
    assert dss
    for m in dss:
        assert m.get_srcComponent() == 196 and m.orientation == mavlink.MAV_SENSOR_ROTATION_NONE
        assert m.current_distance / 100 == pytest.approx(truth, rel=0.2)
        assert 2 <= m.signal_quality <= 100  # covariance: cm² in a uint8, 255 when σ > 16 cm (as here)
    # heartbeat ACTIVE while producing, typed as an onboard controller
    hbs = v.received_t("HEARTBEAT")
    assert all(m.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER and m.autopilot == mavlink.MAV_AUTOPILOT_INVALID
               and m.get_srcComponent() == 196 for _, m in hbs)
    assert hbs[-1][1].system_status == mavlink.MAV_STATE_ACTIVE
    assert "Ranging active" in statustexts(v)
    # diagnostics at <= 1 Hz per name
    nv = v.received_t("NAMED_VALUE_FLOAT")
    names = {m.name for _, m in nv}
    assert {"MR_FPS", "MR_TRACKS", "MR_NEAR_M", "MR_LAT_MS", "MR_MAP", "MR_MEM_SEC", "MR_INFER", "MR_FWD_M", "MR_FWD_SIG",
            "MR_FWD_WHY"} <= names
    assert max(m.value for _, m in nv if m.name == "MR_MAP") > 0  # converged wall points entered the map
    # the forward σ in metres, where the uint8 covariance cannot carry it: it agrees with signal_quality
    ds = {round(t, 3): m for t, m in v.received_t("DISTANCE_SENSOR")}
    fwd = [(t, m.value) for t, m in nv if m.name == "MR_FWD_M" and m.value > 0]
    sig = {round(t, 3): m.value for t, m in nv if m.name == "MR_FWD_SIG"}
    assert fwd and all(sig[round(t, 3)] > 0 for t, _ in fwd)
    # the DISTANCE_SENSOR sent just before each diagnostic describes the same result
    ds_t = sorted(ds)
    checked = 0
    for t, fwd_m in fwd:
        before = [u for u in ds_t if t - 0.1 <= u <= round(t, 3)]
        d = ds[before[-1]] if before else None
        if d is not None and 3 <= d.signal_quality < 100 and d.current_distance / 100 == pytest.approx(fwd_m, abs=0.011):
            assert sig[round(t, 3)] / fwd_m == pytest.approx(0.5 * (1 - d.signal_quality / 100), abs=0.006)
            checked += 1
    assert checked >= 1
    for name in names:
        ts = [t for t, m in nv if m.name == name]
        assert all(b - a >= 0.9 for a, b in zip(ts, ts[1:])), (name, ts)
    fps = [m.value for t, m in nv if m.name == "MR_FPS" and t > T0 + 2.0]
    assert fps and fps[-1] == pytest.approx(30.0, abs=3.0)
    assert r.companion.counters["frames_processed"] >= 74  # 76 frames in 2.5 s of flight
    # every frame after the first either needed no new corners, searched for them, or had that search held back
    pc = r.companion.pipeline.counters
    assert pc["refills_run"] >= 1 and pc["refills_run"] + pc["refills_paused"] <= r.companion.counters["frames_processed"]


def test_no_texture_is_unknown_never_clear(rig):
    flat = SyntheticFlight(camera=CAM, wall_north_m=15.0, velocity_ned=(1.0, 3.0, 0.0), textured=False)
    r = rig(flat)
    r.run(2.0)
    ods = r.vehicle.received("OBSTACLE_DISTANCE")
    assert len(ods) > 10
    for m in ods:
        check_obstacle_distance_fields(m, r.config)
        assert all(x == UINT16_MAX for x in m.distances), "no features must read as unknown, not clear"
    for m in r.vehicle.received("DISTANCE_SENSOR"):
        assert m.current_distance == UINT16_MAX and m.signal_quality == 1
    hbs = r.vehicle.received("HEARTBEAT")
    assert hbs[-1].system_status == mavlink.MAV_STATE_STANDBY
    assert r.companion.reporter.health.state == HealthState.NO_RANGES
    assert any("no converged features" in s for s in statustexts(r.vehicle))


def test_telemetry_stops_then_returns(rig):
    r = rig()
    r.run(2.0)
    assert r.companion.reporter.health.state == HealthState.ACTIVE
    t_stop = r.t
    r.vehicle.streaming = False  # HEARTBEATs continue: the link is up, the telemetry is not
    r.run(2.0)
    v = r.vehicle
    # within 0.5 s no sector is published as valid any more
    for t, m in v.received_t("OBSTACLE_DISTANCE", since=t_stop + 0.5):
        assert all(x == UINT16_MAX for x in m.distances), t - t_stop
    for t, m in v.received_t("DISTANCE_SENSOR", since=t_stop + 0.5):
        assert m.current_distance == UINT16_MAX
    # ... and it keeps saying so (explicit unknown at the normal rate, not silence)
    assert len(v.received("OBSTACLE_DISTANCE", since=t_stop + 0.5)) >= 15
    hb = v.received_t("HEARTBEAT", since=t_stop + 0.5)
    assert hb and all(m.system_status != mavlink.MAV_STATE_ACTIVE for _, m in hb)
    texts = statustexts(v, since=t_stop)
    assert any(s.startswith("Ranging invalid") and ("stale" in s or "telemetry" in s) for s in texts), texts
    # recovery
    t_back = r.t
    v.streaming = True
    r.run(2.5)
    valid = [m for m in v.received("OBSTACLE_DISTANCE", since=t_back) if any(x != UINT16_MAX for x in m.distances)]
    assert valid, "no valid ranges after the telemetry returned"
    assert "Ranging active" in statustexts(v, since=t_back)
    assert v.received("HEARTBEAT", since=t_back)[-1].system_status == mavlink.MAV_STATE_ACTIVE


def test_camera_stops_then_returns(rig):
    r = rig()
    r.run(2.0)
    assert r.companion.reporter.health.state == HealthState.ACTIVE
    t_stop = r.t
    r.camera_on = False
    r.run(1.5)
    v = r.vehicle
    assert r.companion.reporter.health.state == HealthState.FAULT
    assert r.companion.reporter.health.reason == "camera lost"
    for t, m in v.received_t("OBSTACLE_DISTANCE", since=t_stop + 0.5):
        assert all(x == UINT16_MAX for x in m.distances)
    assert any("camera lost" in s for s in statustexts(v, since=t_stop))
    assert all(m.system_status == mavlink.MAV_STATE_CRITICAL for m in v.received("HEARTBEAT", since=t_stop + 0.6))
    t_back = r.t
    r.camera_on = True
    r.run(2.0)
    assert r.companion.reporter.health.state == HealthState.ACTIVE
    valid = [m for m in v.received("OBSTACLE_DISTANCE", since=t_back) if any(x != UINT16_MAX for x in m.distances)]
    assert valid
    # the gap restarted tracks and filters: no range measured before the gap survives it
    assert r.companion.pipeline.counters["restart_gap"] >= 1


def test_link_drops_then_returns(rig):
    r = rig()
    r.run(2.0)
    t_drop = r.t
    v = r.vehicle
    v.heartbeats = v.streaming = False
    r.run(4.0)  # > link_timeout_s = 3 s
    assert not r.link.connected
    assert r.companion.reporter.health.state == HealthState.FAULT
    # the silent vehicle still listens: everything it got after 0.5 s is unknown
    for t, m in v.received_t("OBSTACLE_DISTANCE", since=t_drop + 0.5):
        assert all(x == UINT16_MAX for x in m.distances)
    t_back = r.t
    v.reconnect()  # back from a new source port
    v.heartbeats = v.streaming = True
    r.run(3.0)
    assert r.link.connected
    assert r.companion.reporter.health.state == HealthState.ACTIVE
    valid = [m for m in v.received("OBSTACLE_DISTANCE", since=t_back) if any(x != UINT16_MAX for x in m.distances)]
    assert valid
    texts = statustexts(v, since=t_back)
    assert any("restored" in s for s in texts), texts


def test_bad_frames_never_crash_and_are_counted(rig):
    r = rig()
    bad = {
        5: np.zeros((0, 0), np.uint8),  # empty
        6: np.zeros((100, 100), np.uint8),  # wrong size
        7: np.zeros((240, 320), np.float32),  # wrong type
        8: None,  # nothing decoded
        9: np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8),  # colour noise: decodes, is grey-converted
        10: "garbage",
    }
    r.frame_hook = lambda i, t, img: bad.get(i, img)
    r.run(2.5)
    st = r.source.status()
    assert st.rejected == {"empty": 2, "wrong_size": 1, "dtype": 1, "corrupt": 1}
    assert r.companion.reporter.health.state == HealthState.ACTIVE
    # and directly into the pipeline: invalid results with a reason, never an exception
    p = r.companion.pipeline
    for img in (np.zeros((0,), np.uint8), np.zeros((3, 3), np.uint8), np.full((240, 320), np.nan), object()):
        res = p.process(Frame(10_000, r.t - 0.01, img), r.t)
        assert not res.ok and res.reason.startswith("bad frame"), res.reason


# ---------------------------------------------------------------------- ground-station output --
def test_gcs_output_has_its_own_rate_and_the_vehicle_sysid(rig):
    gport = free_port()
    gcs_peer = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gport}", source_system=255, source_component=190)
    try:
        r = rig(gcs=f"udpout:127.0.0.1:{gport}")
        r.run(3.0)
        got = []
        while True:
            m = gcs_peer.recv_match(blocking=False)
            if m is None:
                break
            got.append(m)
        od = [m for m in got if m.get_type() == "OBSTACLE_DISTANCE"]
        auto = r.vehicle.received("OBSTACLE_DISTANCE")
        assert od and all(m.get_srcSystem() == SYSID and m.get_srcComponent() == 196 for m in od)
        assert len(od) <= 3.0 * r.config.outputs.gcs_obstacle_distance_hz + 1 < len(auto)
        assert any(m.get_type() == "STATUSTEXT" for m in got)
    finally:
        gcs_peer.close()


# ---------------------------------------------------------------------- pipeline units ---------
def make_pipeline(flight=None, config=None, pipeline=PipelineConfig()):
    flight = flight or SyntheticFlight(camera=CAM, wall_north_m=15.0, velocity_ned=(1.0, 3.0, 0.0))
    config = config or small_config()
    tel = TelemetryBuffer(config.telemetry)
    tel.set_clock_offset(0.0)  # companion clock = vehicle boot clock = flight time
    return flight, tel, Pipeline(CAM, config, pipeline, tel)


def test_pose_is_interpolated_at_capture_time_and_frames_wait_for_the_bracketing_sample():
    flight, tel, p = make_pipeline()
    feed_telemetry(tel, flight, 0.0, 1.005)
    t = 1.01  # after the newest ATTITUDE (1.00 s): wait, then fail once the wait is over
    assert p.readiness(t, now=t + 0.005) == "wait"
    assert p.readiness(t, now=t + 0.07) == "fail"
    res = p.process(Frame(0, t, flight.render(t)), now=t + 0.07)
    assert not res.ok and res.reason == "telemetry: attitude after_buffer"
    feed_telemetry(tel, flight, 1.005, 1.03)
    assert p.readiness(t, now=t + 0.021) == "ready"
    res = p.process(Frame(1, t, flight.render(t)), now=t + 0.021)
    assert res.ok, res.reason
    # position extrapolated from the newest LOCAL_POSITION_NED (1.00 s) with its velocity
    assert p.counters["position_extrapolated"] == 1
    assert res.t_boot_capture == pytest.approx(t)


def test_stale_telemetry_refuses_frames():
    flight, tel, p = make_pipeline()
    feed_telemetry(tel, flight, 0.0, 1.0)
    res = p.process(Frame(0, 0.9, flight.render(0.9)), now=1.6)
    assert not res.ok and "stale" in res.reason


def test_stale_position_alone_is_named_in_the_reason():
    flight, tel, p = make_pipeline()
    feed_telemetry(tel, flight, 0.0, 1.0)
    feed_telemetry(tel, flight, 1.0, 1.7, position_hz=1e-9)  # ATTITUDE goes on, LOCAL_POSITION_NED stops
    res = p.process(Frame(0, 1.6, flight.render(1.6)), now=1.62)
    assert not res.ok and res.reason == "telemetry: position stale", res.reason


def test_clock_jump_and_reboot_restart_the_ranging():
    flight, tel, p = make_pipeline()
    feed_telemetry(tel, flight, 0.0, 2.0)
    for k in range(20):
        t = 1.0 + k / FPS
        assert p.process(Frame(k, t, flight.render(t)), now=t + 0.02).ok
    assert p.estimator.ekf.ids.size > 0
    # frame time goes back
    res = p.process(Frame(20, 1.2, flight.render(1.2)), now=1.7)
    assert res.restart == "frame time went back" and res.ok
    # the TIMESYNC mapping jumps by 0.3 s
    tel.set_clock_offset(0.3)
    feed_telemetry(tel, flight, 2.0, 2.2)  # (stamps are flight time; only the restart matters here)
    res = p.process(Frame(21, 1.7, flight.render(1.4)), now=1.75)
    assert res.restart.startswith("clock jump")
    # an autopilot reboot (time_boot_ms back to 0)
    tel.add_attitude(10, 0, 0, 0, 0, 0, 0)
    res = p.process(Frame(22, 1.8, flight.render(1.5)), now=1.85)
    assert res.restart == "autopilot reboot"
    assert not res.ok  # the buffer was cleared: no pose
    assert p.counters["restart_clock_jump"] == 1 and p.counters["restart_autopilot_reboot"] == 1


def test_frames_from_the_future_are_a_clock_fault():
    flight, tel, p = make_pipeline()
    feed_telemetry(tel, flight, 0.0, 2.0)
    res = p.process(Frame(0, 1.5, flight.render(1.5)), now=1.0)
    assert not res.ok and res.reason.startswith("clock fault")


def _fake_result(sectors, yaw=0.0, t=10.0):
    return FrameResult(1, t, t, 0.005, True, "ok", sectors=sectors, yaw=yaw, n_tracks=10, t_boot_capture=t)


def _sectors_with_obstacle_at(bearing_deg: float, dist_m: float, config: CompanionConfig):
    from companion.core.sectors import compute_sectors

    b = math.radians(bearing_deg)
    pts = np.array([[dist_m * math.cos(b), dist_m * math.sin(b), 0.0]] * 3)
    return compute_sectors(pts, np.full(3, 0.1), np.ones(3, bool), np.ones(3, bool), math.radians(60), 0.0, config.sectors)


def test_reporter_rotates_sectors_by_the_yaw_change_since_exposure():
    cfg = small_config()
    rep = Reporter(cfg, PipelineConfig(), outputs=("autopilot", "gcs"), start=9.0)
    sec = _sectors_with_obstacle_at(0.0, 10.0, cfg)
    assert sec.distances_cm[0] != UINT16_MAX
    res = _fake_result(sec, yaw=0.0)
    msgs = rep.on_result(res, 10.03, yaw_now=math.radians(10.0), last_frame_at=10.0)
    od = [m for o, m in msgs if m.get_type() == "OBSTACLE_DISTANCE" and o == "autopilot"]
    assert len(od) == 1
    d = np.asarray(od[0].distances)
    # the vehicle turned 10° right: the obstacle is now 10° to the left (sector 70)
    assert d[70] != UINT16_MAX and d[0] == UINT16_MAX
    # the forward reading no longer points at what was seen: "unknown" to the ground station; the autopilot
    # gets none (PX4 would read UINT16_MAX as free space, ArduPilot would wipe the obstacle at −10° from its front face)
    ds = {o: m for o, m in msgs if m.get_type() == "DISTANCE_SENSOR"}
    assert ds["gcs"].current_distance == UINT16_MAX and "autopilot" not in ds
    assert rep.counters["distance_sensor_withheld"] == 1


def test_reporter_never_publishes_an_old_result_as_valid():
    cfg = small_config()
    rep = Reporter(cfg, PipelineConfig(), start=9.0)
    sec = _sectors_with_obstacle_at(0.0, 10.0, cfg)
    res = _fake_result(sec, t=10.0)
    rep.on_result(res, 10.02, yaw_now=0.0, last_frame_at=10.0)
    late = rep.tick(10.45, yaw_now=0.0, last_frame_at=10.4)  # no newer result for 0.45 s
    od = [m for _, m in late if m.get_type() == "OBSTACLE_DISTANCE"]
    assert od and all(x == UINT16_MAX for x in od[0].distances)
    assert rep.health.state == HealthState.FAULT and rep.health.reason == "frames not processed in time"


def test_frames_older_than_the_age_limit_are_dropped(rig):
    r = rig()
    r.run(0.3)
    # a frame captured 0.25 s ago arrives now: dropped before processing
    c = r.companion
    before = c.counters["frames_stale"]
    r.source.push(10_000, r.t - 0.25, r.flight.render(r.t - 0.25 - T0))
    c.step()
    assert c.counters["frames_stale"] == before + 1


def test_garbage_duplicates_and_an_autopilot_reboot_never_stop_the_companion(rig):
    r = rig()
    r.run(1.5)
    assert r.companion.reporter.health.state == HealthState.ACTIVE
    v = r.vehicle
    rng = np.random.default_rng(3)
    t_noise = r.t
    for _ in range(20):  # random bytes, a bad CRC, a truncated packet, an unknown message id
        v.conn.write(bytes(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8)))
        good = bytearray(mavlink.MAVLink_attitude_message(1, 0, 0, 0, 0, 0, 0).pack(v.conn.mav))
        good[-1] ^= 0xFF
        v.conn.write(bytes(good))
        v.conn.write(bytes(good[:9]))
        unknown = bytearray(good)
        unknown[7:10] = (60000).to_bytes(3, "little")
        v.conn.write(bytes(unknown))
        r.run(0.02)
    # duplicated and out-of-order telemetry
    boot_ms = int(round((r.t - v.boot) * 1000))
    for ms in (boot_ms - 40, boot_ms - 40, boot_ms - 80):
        v.send(mavlink.MAVLink_attitude_message(ms, *r.flight.attitude_fields(ms / 1000 + v.boot - v.t0)))
    r.run(0.5)
    assert r.companion.reporter.health.state == HealthState.ACTIVE
    valid = [m for m in v.received("OBSTACLE_DISTANCE", since=t_noise) if m.distances[0] != UINT16_MAX]
    assert valid
    assert r.link.status().counters.get("rx_bad_crc", 0) >= 20
    # the autopilot reboots: time_boot_ms restarts from 0
    t_reboot = r.t
    v.boot = r.t
    r.run(3.0)
    texts = statustexts(v, since=t_reboot)
    assert any("autopilot reboot" in s.lower() for s in texts), texts
    assert r.companion.reporter.health.state == HealthState.ACTIVE
    valid = [m for t, m in v.received_t("OBSTACLE_DISTANCE", since=t_reboot + 1.0) if m.distances[0] != UINT16_MAX]
    assert valid and valid[-1].distances[0] / 100 == pytest.approx(r.flight.wall_distance(r.t - T0), rel=0.2)


def test_obstacle_distance_3d_when_enabled_turns_with_the_vehicle():
    base = small_config()
    cfg = dataclasses.replace(base, outputs=dataclasses.replace(base.outputs, autopilot_obstacle_3d_hz=5.0))
    rep = Reporter(cfg, PipelineConfig(), start=9.0)
    sec = _sectors_with_obstacle_at(0.0, 10.0, cfg)
    msgs = rep.on_result(_fake_result(sec), 10.02, yaw_now=math.radians(90.0), last_frame_at=10.0, time_boot_ms=1234)
    o3 = [m for _, m in msgs if m.get_type() == "OBSTACLE_DISTANCE_3D"]
    assert len(o3) == 1
    m = o3[0]
    assert m.frame == mavlink.MAV_FRAME_BODY_FRD and m.time_boot_ms == 1234 and m.obstacle_id == 0
    # seen 10 m ahead (minus 2σ), the vehicle has since turned 90° right: now on its left
    assert m.x == pytest.approx(0.0, abs=1e-6) and m.y == pytest.approx(-9.8, abs=1e-3) and m.z == pytest.approx(0.0)
    assert m.min_distance == pytest.approx(0.5) and m.max_distance == pytest.approx(40.0)


def test_sector_points_lie_on_the_rays_measured_now():
    """A landmark seen in this frame is placed at its estimated range along its current ray (the
    filter's point sits on the anchor ray, off the current one when the range is wrong); a landmark
    not seen in this frame keeps the filter's point."""
    from types import SimpleNamespace

    from companion.core.camera import CameraModel
    from companion.core.estimator import RangeOutput
    from companion.core.frames import euler_zyx_to_R
    from companion.core.obstacle_map import points_on_current_rays

    cam = CameraModel(CameraConfig(width=320, height=240, fx=277.1, fy=277.1, cx=159.5, cy=119.5))
    R_body_cam = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # camera z forward, x right, y down
    R_wc = euler_zyx_to_R(0.1, -0.2, 0.7) @ R_body_cam
    p_wc = np.array([3.0, -2.0, -10.0])
    X = np.array([[40.0, 20.0, -12.0], [30.0, 25.0, -6.0], [35.0, 18.0, -9.0]])  # true points, all in view
    Xc = (X - p_wc) @ R_wc  # camera frame
    assert np.all(Xc[:, 2] > 0)
    uv = cam.project(Xc)
    p_est = X + np.array([[4.0, -3.0, 1.0], [-2.0, 2.0, 0.5], [1.0, 1.0, 1.0]])  # off the rays
    rng = np.linalg.norm(p_est - p_wc, axis=1)
    out = RangeOutput(t=0.0, ids=np.array([3, 7, 9]), p_world=p_est, range=rng, range_sigma=np.ones(3),
                      converged=np.ones(3, bool), valid=np.ones(3, bool), n_pending=0, n_initialized_tri=0,
                      n_initialized_prior=0, n_rejected=0, tri_reasons={})
    tf = SimpleNamespace(ids=np.array([2, 3, 9]), uv=np.array([[10.0, 10.0], uv[0], uv[2]]))  # 7 not seen now
    p = points_on_current_rays(out.ids, out.p_world, out.range, tf.ids, cam.unproject(tf.uv), R_wc, p_wc)
    for i in (0, 2):
        u = (X[i] - p_wc) / np.linalg.norm(X[i] - p_wc)
        np.testing.assert_allclose(p[i], p_wc + u * rng[i], atol=1e-9)
    np.testing.assert_array_equal(p[1], p_est[1])
    np.testing.assert_allclose(np.linalg.norm(p - p_wc, axis=1), rng, rtol=1e-12)


def test_tracker_refill_gets_the_priority_region_from_the_previous_frame():
    """With priority_share > 0 the pipeline hands the tracker the band around the
    flight path and the in-view sectors without a live point (from the previous frame's sectors)."""
    base = small_config()
    cfg = dataclasses.replace(base, tracks=dataclasses.replace(base.tracks, priority_share=0.5, priority_min_tracks=10))
    flight, tel, p = make_pipeline(config=cfg)
    feed_telemetry(tel, flight, 0.0, 2.0)
    seen = []
    step = p.tracks.step

    def spy(*a, **kw):
        seen.append(kw.get("priority_mask"))
        return step(*a, **kw)

    p.tracks.step = spy
    for k in range(5):
        t = 0.5 + k / 30
        res = p.process(Frame(k, t, flight.render(t)), now=t + 0.05)
        assert res.ok, res.reason
    assert len(seen) == 5 and all(m is not None and m.shape == (CAM.height, CAM.width) and m.dtype == bool for m in seen)
    assert all(0 < np.count_nonzero(m) < m.size for m in seen), [np.count_nonzero(m) for m in seen]  # the band, not the sky or the ground
    # off (priority_share = priority_min_tracks = 0): no region computed
    off = dataclasses.replace(base, tracks=dataclasses.replace(base.tracks, priority_share=0.0, priority_min_tracks=0))
    flight, tel, p = make_pipeline(config=off)
    assert p._detection_priority(res, np.eye(3), np.zeros(3)) is None


def test_a_fault_repeating_every_frame_sends_its_statustext_at_most_once_a_second():
    """A restart on every frame (an internal error, a spoofed clock) must not flood the radio: the same
    STATUSTEXT leaves at most once per ``statustext_min_interval_s`` and the next one says how many were held."""
    cfg = small_config()
    rep = Reporter(cfg, PipelineConfig(), start=9.0)
    sent = []
    for k in range(90):  # 3 s at 30 frames/s
        t = 10.0 + k / 30.0
        res = FrameResult(k, t, t, 0.005, False, "error: internal", restart="internal error")
        sent += [m.text for _, m in rep.on_result(res, t + 0.01, yaw_now=0.0, last_frame_at=t)
                 if m.get_type() == "STATUSTEXT" and "restarted" in m.text]
    assert 3 <= len(sent) <= 4
    assert sent[0] == "Ranging restarted: internal error"
    assert sent[1].endswith("(+29)")  # the repeats held back since the last one
    assert rep.counters["statustext_suppressed"] == 90 - len(sent)
    # a different text is not held back by the first
    res = FrameResult(90, 13.0, 13.0, 0.005, False, "x", restart="clock jump +1.00 s")
    assert any("clock jump" in m.text for _, m in rep.on_result(res, 13.01, yaw_now=0.0, last_frame_at=13.0)
               if m.get_type() == "STATUSTEXT")


def test_statustext_overall_budget_sends_the_most_severe_first_and_drops_obsolete_states():
    """All texts together leave at most once per statustext_interval_s; the most severe waiting text
    goes first; a newer ranging state replaces one still waiting; a full queue drops the least severe."""
    rep = Reporter(small_config(), PipelineConfig(statustext_queue=3), start=0.0)

    def texts(t, evs):  # the text stage alone (tick() would add the health state's own texts)
        return [m.text for _, m in rep._texts(evs, t) if m.get_type() == "STATUSTEXT" and m.chunk_seq == 0]

    S = mavlink
    first = texts(100.0, [(S.MAV_SEVERITY_INFO, "info one"), (S.MAV_SEVERITY_CRITICAL, "critical one"),
                          (S.MAV_SEVERITY_INFO, "Ranging active"), (S.MAV_SEVERITY_WARNING, "Ranging invalid: x")])
    assert first == ["critical one"]  # one per second, the most severe first
    assert texts(100.5, []) == []
    # "Ranging active" was replaced by the newer state while waiting; the queue (3) keeps the rest
    assert texts(101.0, []) == ["Ranging invalid: x"] and rep.counters["statustext_superseded"] == 1
    assert texts(102.0, [(S.MAV_SEVERITY_NOTICE, "n1"), (S.MAV_SEVERITY_NOTICE, "n2"), (S.MAV_SEVERITY_ERROR, "e1")]) == ["e1"]
    assert rep.counters["statustext_dropped"] == 1  # info one, n1, n2 and e1 did not fit in 3: the least severe went
    assert texts(103.0, []) == ["n1"] and texts(104.0, []) == ["n2"] and texts(105.0, []) == []


@pytest.mark.parametrize("signal_exc", [KeyboardInterrupt, "terminated"])
def test_a_signal_surfacing_inside_a_compiled_call_stops_the_process_not_the_ranging(signal_exc, monkeypatch):
    """Ctrl-C or SIGTERM arriving while a C extension (a numba kernel, OpenCV) has control comes out
    as a SystemError caused by the interrupt; the pipeline must let the interrupt through instead of
    logging an internal error and ranging on (the process would not stop). Any other error still
    restarts the ranging."""
    from companion.errors import Terminated
    from companion.interrupts import interrupt_in

    exc_type = Terminated if signal_exc == "terminated" else signal_exc
    flight, tel, p = make_pipeline()
    feed_telemetry(tel, flight, 0.0, 2.0)
    assert p.process(Frame(0, 1.0, flight.render(1.0)), now=1.02).ok

    def wrapped(*_a, **_k):
        try:
            raise exc_type("received")
        except BaseException as inner:
            raise SystemError("CPUDispatcher(<function score_peaks>) returned a result with an exception set") from inner

    monkeypatch.setattr(p.tracks, "step", wrapped)
    with pytest.raises(exc_type):
        p.process(Frame(1, 1.0 + 1 / FPS, flight.render(1.0 + 1 / FPS)), now=1.06)
    assert p.counters["internal_errors"] == 0

    def bug(*_a, **_k):
        raise SystemError("a real bug")

    monkeypatch.setattr(p.tracks, "step", bug)
    res = p.process(Frame(2, 1.0 + 2 / FPS, flight.render(1.0 + 2 / FPS)), now=1.1)
    assert not res.ok and res.restart == "internal error" and p.counters["internal_errors"] == 1
    assert interrupt_in(ValueError("x")) is None


def test_read_only_frames_compile_no_new_kernels():
    """A frame viewed in a receive buffer is read-only; numba specializes on that, so such a frame would
    compile every image kernel anew in the middle of a flight (tens of seconds: the process test over the
    simulator transport saw no range within 20 s). The pipeline hands the kernels a writable copy."""
    from companion.core import jit, lk_kernel, ncc_kernels

    if not jit.ENABLED:
        pytest.skip("compiled kernels are off (numba missing or COMPANION_KERNELS=numpy)")
    import numba

    flight, tel, p = make_pipeline()
    feed_telemetry(tel, flight, 0.0, 2.0)
    for k in range(4):
        t = 1.0 + k / FPS
        g = flight.render(t)
        g.setflags(write=False)
        assert p.process(Frame(k, t, g), now=t + 0.02).ok
    for kernel in (ncc_kernels.score_peaks, ncc_kernels.scale_fit, lk_kernel._lk_kernel):
        assert all(t.mutable for sig in kernel.signatures for t in sig if isinstance(t, numba.types.Array)), kernel.signatures
