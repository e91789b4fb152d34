"""``companion check`` (the pre-flight check) end to end and its pure evaluators.

End to end: flightsim's autopilot side of MAVLink (:class:`flightsim.autopilot.AutopilotLogic` behind its
:class:`~flightsim.autopilot.UdpEndpoint`, streaming on the wall clock at the rates the companion asks
for, answering TIMESYNC on its own boot clock) and the simulator frame transport
(:class:`~companion.camera_sources.SimFrameServer`, 30 fps of 160×120 stamped on that boot clock), on
free loopback ports; ``companion check`` runs in-process through its command line.
"""

from __future__ import annotations

import json
import math
import threading
import time

import cv2
import numpy as np
import pytest

from companion.mavlink.dialect import mavlink  # noqa: I001 (first: MAVLink 2)
from companion.camera_sources import CLOCK_AUTOPILOT_BOOT, SimFrameServer, SourceStatus
from companion.check import (FAIL, PASS, WARN, check_calibration, evaluate_camera, evaluate_heartbeat, evaluate_stream,
                             evaluate_timesync)
from companion.cli import main
from companion.core.camera import CameraConfig
from flightsim.autopilot import AutopilotLogic, UdpEndpoint

W, H, FPS = 160, 120, 30.0
BOOT_S = 120.0  # the vehicle has been up this long when the rig starts
CAM = CameraConfig.from_fov(W, H, 60.0)


class SimAutopilot:
    """flightsim's autopilot logic and UDP endpoint, stepped on the wall clock: HEARTBEAT at 1 Hz (at once
    for a new peer), the streams at the periods the companion requested, TIMESYNC answers."""

    def __init__(self):
        self.t0 = time.monotonic()
        self.endpoint = UdpEndpoint(0, system_id=1)
        self.periods: dict[str, float] = {}
        self.due: dict[str, float] = {}
        defaults = {"ATTITUDE": 0.1, "LOCAL_POSITION_NED": 0.2, "GLOBAL_POSITION_INT": 0.5, "SYSTEM_TIME": 1.0}
        self.logic = AutopilotLogic(1, self._set_period, defaults, self.boot_s)
        self.next_hb = math.inf

    def boot_s(self, t: float) -> float:
        return BOOT_S + t

    def _set_period(self, name: str, period: float | None, t: float) -> None:
        if period is None:
            self.periods.pop(name, None)
        else:
            self.periods[name], self.due[name] = period, t

    def _message(self, name: str, t: float):
        ms = int(self.boot_s(t) * 1000)
        if name == "ATTITUDE":
            return mavlink.MAVLink_attitude_message(ms, 0.0, 0.0, 0.3, 0.0, 0.0, 0.0)
        if name == "LOCAL_POSITION_NED":
            return mavlink.MAVLink_local_position_ned_message(ms, 1.0, 2.0, -10.0, 0.0, 0.0, 0.0)
        if name == "GLOBAL_POSITION_INT":
            return mavlink.MAVLink_global_position_int_message(ms, 473977420, 85455940, 500000, 10000, 0, 0, 0, 1700)
        return mavlink.MAVLink_system_time_message(0, ms)

    def step(self) -> None:
        t = time.monotonic() - self.t0
        peers = self.endpoint.counters["peers"]
        for _raw, msg in self.endpoint.receive():
            for reply in self.logic.handle(msg, t):
                self.endpoint.send(reply)
        if self.endpoint.counters["peers"] != peers:
            self.next_hb = t  # a new companion: HEARTBEAT at once, as flightsim sitl does
        if t >= self.next_hb:
            self.next_hb = t + 1.0
            self.endpoint.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                                 0, 0, mavlink.MAV_STATE_STANDBY, 3))
        for name, period in list(self.periods.items()):
            if t >= self.due[name]:
                self.due[name] = max(self.due[name] + period, t)
                self.endpoint.send(self._message(name, t))


class Rig:
    """The simulated autopilot and camera, each in its own thread, until :meth:`close`."""

    def __init__(self):
        self.autopilot = SimAutopilot()
        self.server = SimFrameServer()
        self.stop = threading.Event()
        rng = np.random.default_rng(0)
        self.image = rng.integers(0, 255, (H, W), dtype=np.uint8)
        self.threads = [threading.Thread(target=self._vehicle, daemon=True), threading.Thread(target=self._camera, daemon=True)]
        for th in self.threads:
            th.start()

    @property
    def mavlink(self) -> str:
        return f"udpout:127.0.0.1:{self.autopilot.endpoint.port}"

    def _vehicle(self) -> None:
        while not self.stop.is_set():
            self.autopilot.step()
            self.autopilot.endpoint.wait_readable(0.002)

    def _camera(self) -> None:
        k = 0
        while not self.stop.is_set():
            t = k / FPS
            delay = self.autopilot.t0 + t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            self.server.send(self.image, k, int(self.autopilot.boot_s(t) * 1e9), CLOCK_AUTOPILOT_BOOT)
            k += 1

    def close(self) -> None:
        self.stop.set()
        for th in self.threads:
            th.join(timeout=2)
        self.server.close()
        self.autopilot.endpoint.close()


@pytest.fixture(scope="module")
def rig():
    r = Rig()
    yield r
    r.close()


def camera_toml(tmp_path, cam: CameraConfig = CAM, name: str = "c.toml"):
    p = tmp_path / name
    p.write_text(f"[camera]\nwidth = {cam.width}\nheight = {cam.height}\nfx = {cam.fx}\nfy = {cam.fy}\ncx = {cam.cx}\n"
                 f"cy = {cam.cy}\n")
    return p


def run_json(argv, capsys) -> tuple[int, dict]:
    rc = main(argv + ["--json"])
    out = capsys.readouterr().out
    return rc, json.loads(out)


def by_name(report: dict) -> dict:
    return {c["name"]: c for c in report["checks"]}


# ---------------------------------------------------------------------- end to end -----------------
def test_everything_passes_against_the_simulated_autopilot_and_camera(rig, tmp_path, capsys):
    t = time.monotonic()
    rc, rep = run_json(["check", "--mavlink", rig.mavlink, "--camera", rig.server.address, "--config", str(camera_toml(tmp_path)),
                        "--fps", "30", "--timeout", "15"], capsys)
    wall = time.monotonic() - t
    checks = by_name(rep)
    assert rc == 0 and rep["ok"] and rep["exit_code"] == 0, json.dumps(rep, indent=1)
    assert list(checks) == ["link", "heartbeat", "ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "timesync",
                            "camera", "calibration"]
    assert all(c["status"] == PASS for c in rep["checks"])
    assert wall < 8.0 and rep["elapsed_s"] < 8.0  # ends once everything passed (~2.2 s), not at the timeout
    hb = checks["heartbeat"]["values"]
    assert hb["system_id"] == 1 and hb["type"] == "MAV_TYPE_QUADROTOR" and hb["mavlink_version"] == 2
    att = checks["ATTITUDE"]["values"]
    assert att["requested_hz"] == 50.0 and 25.0 <= att["rate_hz"] <= 55.0 and att["needed_for_ranges"]
    assert 10.0 <= checks["LOCAL_POSITION_NED"]["values"]["rate_hz"] <= 22.0
    ts = checks["timesync"]["values"]
    assert ts["source"] == "timesync" and ts["accepted"] >= 3 and ts["offset_spread_ms"] <= 50.0
    # t_companion − t_autopilot: the rig's monotonic clock at the vehicle's boot
    assert ts["offset_s"] == pytest.approx(rig.autopilot.t0 - BOOT_S, abs=0.03)  # within max_rtt_s / 2
    cam = checks["camera"]["values"]
    assert (cam["width"], cam["height"]) == (W, H) and 24.0 <= cam["fps"] <= 33.0 and cam["max_gap_s"] <= 0.3
    assert "fps" in checks["camera"]["detail"] and "Hz" in checks["ATTITUDE"]["detail"]


def test_no_autopilot_fails_the_heartbeat_and_exits_1(rig, tmp_path, capsys):
    silent = UdpEndpoint(0, system_id=1)  # a port where nobody answers
    try:
        rc = main(["check", "--mavlink", f"udpout:127.0.0.1:{silent.port}", "--camera", rig.server.address,
                   "--config", str(camera_toml(tmp_path)), "--timeout", "1.5"])
    finally:
        silent.close()
    out = capsys.readouterr().out
    assert rc == 1
    lines = {ln.split()[1]: ln for ln in out.splitlines() if ln[:4] in (PASS, WARN, FAIL)}
    assert lines["link"].startswith(PASS)
    assert lines["heartbeat"].startswith(FAIL) and "no HEARTBEAT from an autopilot" in lines["heartbeat"]
    assert lines["ATTITUDE"].startswith(FAIL) and lines["timesync"].startswith(FAIL)
    # the frames are stamped on the autopilot's clock: without it the companion cannot use them
    assert lines["camera"].startswith(FAIL) and "no_clock" in lines["camera"]
    assert lines["calibration"].startswith(PASS)
    assert "would not produce ranges" in out.splitlines()[-1]


def test_wrong_camera_size_in_the_config_fails_the_camera(rig, tmp_path, capsys):
    big = CameraConfig.from_fov(2 * W, 2 * H, 60.0)
    rc, rep = run_json(["check", "--mavlink", rig.mavlink, "--camera", rig.server.address,
                        "--config", str(camera_toml(tmp_path, big)), "--timeout", "4.5"], capsys)
    checks = by_name(rep)
    assert rc == 1 and not rep["ok"]
    assert [c["name"] for c in rep["checks"] if c["status"] == FAIL] == ["camera"]
    cam = checks["camera"]
    assert cam["values"]["rejected"].get("wrong_size", 0) > 10
    assert f"got {W}×{H}, configured {2 * W}×{2 * H}" in cam["detail"]


def test_a_bad_calibration_fails(rig, tmp_path, capsys):
    cal = tmp_path / "cal.yaml"
    fs = cv2.FileStorage(str(cal), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[10.0, 0, 79.5], [0, 10.0, 59.5], [0, 0, 1]]))  # 166° across 160 px
    fs.write("distortion_coefficients", np.zeros((1, 5)))
    fs.write("image_width", W)
    fs.write("image_height", H)
    fs.release()
    rc = main(["check", "--mavlink", rig.mavlink, "--camera", rig.server.address, "--calibration", str(cal), "--timeout", "10"])
    out = capsys.readouterr().out
    assert rc == 1
    (line,) = [ln for ln in out.splitlines() if ln.split()[1:2] == ["calibration"]]
    assert line.startswith(FAIL) and "fx 10 px" in line and "horizontal field of view" in line
    others = [ln for ln in out.splitlines() if ln[:4] in (PASS, WARN, FAIL) and "calibration" not in ln.split()[1]]
    assert others and all(ln.startswith(PASS) for ln in others), out  # the live checks passed: only the calibration failed
    assert out.splitlines()[-1].startswith("companion check: 1 of 8 checks failed (calibration)")


@pytest.mark.parametrize("extra, fragment", [
    (["--timeout", "0"], "--timeout"),
    (["--timeout", "nan"], "--timeout"),
    (["--fps", "-5"], "--fps"),
    (["--calibration", "/nonexistent/cal.yaml"], "cal.yaml"),
    (["--camera-config", "/nonexistent/camera.toml"], "camera.toml"),
    (["--config", "/nonexistent/companion.toml"], "companion.toml"),
])
def test_bad_arguments_and_input_files_exit_2(extra, fragment, capsys):
    rc = main(["check", "--mavlink", "udpout:127.0.0.1:14999", "--camera", "sim://127.0.0.1:5999"] + extra)
    assert rc == 2 and fragment in capsys.readouterr().err


def test_bad_connection_or_camera_exit_2(tmp_path, capsys):
    assert main(["check", "--mavlink", "udpout:127.0.0.1:notaport", "--camera", "sim://127.0.0.1:5999"]) == 2
    assert "notaport" in capsys.readouterr().err
    assert main(["check", "--mavlink", "udpout:127.0.0.1:14999", "--camera", str(tmp_path / "nope.avi")]) == 2
    assert "nope.avi" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["check", "--camera", "0"])
    assert e.value.code == 2 and "--mavlink" in capsys.readouterr().err


def test_help_lists_the_checks(capsys):
    with pytest.raises(SystemExit) as e:
        main(["check", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for word in ("--mavlink", "--camera", "--calibration", "--camera-config", "--timeout", "--json", "heartbeat",
                 "timesync", "exit codes"):
        assert word in out, word


# ---------------------------------------------------------------------- pure evaluators -----------
def test_calibration_of_the_shipped_camera_passes():
    r = check_calibration(CameraConfig())
    assert r.status == PASS and r.values["hfov_deg"] == pytest.approx(60.0, abs=0.1)
    r = check_calibration(CameraConfig(distortion=(-0.3, 0.1, 0.0, 0.0, 0.0)))  # a wide-angle lens's barrel distortion
    assert r.status == PASS and r.values["roundtrip_px"] < 0.05 and not r.values["folds"]


@pytest.mark.parametrize("kw, fragment", [
    (dict(fx=10.0, fy=10.0), "horizontal field of view"),
    (dict(fx=20000.0, fy=20000.0), "horizontal field of view"),
    (dict(cx=700.0), "principal point"),
    (dict(cy=-3.0), "principal point"),
    (dict(fy=800.0), "fy/fx"),
    (dict(distortion=(-2.0, 0.0, 0.0, 0.0, 0.0)), "not invertible"),
])
def test_implausible_calibrations_fail(kw, fragment):
    r = check_calibration(CameraConfig(**kw))
    assert r.status == FAIL and fragment in r.detail


def test_stream_verdicts():
    ok = evaluate_stream("ATTITUDE", 50.0, 48.0, 2.5, 2.0, 0.5, "ok", True, True, final=False)
    assert ok.status == PASS and "48.0 Hz" in ok.detail
    assert evaluate_stream("ATTITUDE", 50.0, 48.0, 1.0, 2.0, 0.5, "ok", True, True, final=False) is None  # window not full
    slow = evaluate_stream("ATTITUDE", 50.0, 10.0, 3.0, 2.0, 0.5, "wait_rate", True, True, final=True)
    assert slow.status == FAIL and "too slow" in slow.detail and "needs >= 25 Hz" in slow.detail
    gone = evaluate_stream("GLOBAL_POSITION_INT", 5.0, 0.0, 0.0, 2.0, 0.5, "fallback", False, True, final=True)
    assert gone.status == WARN and "none received" in gone.detail and "REQUEST_DATA_STREAM" in gone.detail


def test_heartbeat_in_mavlink1_is_a_warning():
    packer = mavlink.MAVLink(None, srcSystem=7, srcComponent=1)
    raw = bytes(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 3, 3)
                .pack(packer, force_mavlink1=True))
    hb = mavlink.MAVLink(None).parse_char(raw)
    r = evaluate_heartbeat(hb, 7, 0.4, 1.0, {}, 1, final=False)
    assert r.status == WARN and "MAVLink 2" in r.detail and r.values["autopilot"] == "MAV_AUTOPILOT_PX4"
    none = evaluate_heartbeat(None, None, None, 3.0, {"rx_messages": 12, "rx_heartbeat_other": 3}, 1, final=True)
    assert none.status == FAIL and "12 messages received" in none.detail and "3 HEARTBEATs of other components" in none.detail
    assert evaluate_heartbeat(None, None, None, 1.0, {}, 1, final=False) is None


def test_timesync_verdicts():
    common = dict(source="timesync", offset_s=12.5, counters={"requests": 6, "accepted": 5}, best_rtt_s=0.001,
                  last_rtt_s=0.001, max_rtt_s=0.05, settle_s=1.5)
    assert evaluate_timesync(True, converged_for_s=2.0, offset_spread_s=0.0002, final=False, **common).status == PASS
    assert evaluate_timesync(True, converged_for_s=1.0, offset_spread_s=0.0, final=False, **common) is None
    jumpy = evaluate_timesync(True, converged_for_s=2.0, offset_spread_s=0.2, final=True, **common)
    assert jumpy.status == FAIL and "not stable" in jumpy.detail
    common.update(source="arrival", offset_s=12.6, counters={"requests": 9, "rejected_rtt": 9}, last_rtt_s=0.12)
    slow = evaluate_timesync(False, converged_for_s=0.0, offset_spread_s=0.0, final=True, **common)
    assert slow.status == FAIL and "round trip 120 ms" in slow.detail and "arrival times" in slow.detail


def test_camera_verdicts():
    def status(frames=60, rejected=None, error=""):
        return SourceStatus("sim", "sim", True, False, frames, frames, 0, rejected or {}, 0, 10.0, error)

    ok = evaluate_camera("0", W, H, status(), 30.0, 2.0, 0.04, 0.01, 30.0, 2.0, 0.3, final=False)
    assert ok.status == PASS and "30.0 fps" in ok.detail
    slow = evaluate_camera("0", W, H, status(), 15.0, 2.0, 0.07, 0.01, 30.0, 2.0, 0.3, final=True)
    assert slow.status == FAIL and "too slow" in slow.detail and "needs >= 24.0 fps" in slow.detail
    gap = evaluate_camera("0", W, H, status(), 29.0, 2.0, 0.45, 0.01, 0.0, 2.0, 0.3, final=True)
    assert gap.status == FAIL and "gap of 0.45 s" in gap.detail
    wrong = evaluate_camera("0", W, H, status(0, {"wrong_size": 40}, "wrong_size: got 640×480, configured 160×120"),
                            0.0, 0.0, 0.0, math.inf, 0.0, 2.0, 0.3, final=True)
    assert wrong.status == FAIL and "wrong_size 40" in wrong.detail and "got 640×480" in wrong.detail


def test_a_vehicle_that_went_silent_fails_the_heartbeat():
    hb = mavlink.MAVLink(None).parse_char(bytes(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(
        mavlink.MAVLink(None, srcSystem=1, srcComponent=1))))
    assert evaluate_heartbeat(hb, 1, 0.2, 6.0, {}, 1, final=False, connected=False, silent_s=4.0) is None
    r = evaluate_heartbeat(hb, 1, 0.2, 6.0, {}, 1, final=True, connected=False, silent_s=4.0)
    assert r.status == FAIL and "link lost" in r.detail and "4.0 s" in r.detail
