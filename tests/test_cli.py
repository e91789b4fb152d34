"""The ``companion`` command line: help, usage and configuration errors (exit 2), and a real
``python -m companion run`` process against a loopback vehicle and the simulator frame transport,
stopped cleanly with SIGINT (exit 0)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from companion.mavlink.dialect import UINT16_MAX, mavlink  # noqa: I001 (first: MAVLink 2)
from bench.latency import SyntheticFlight
from companion.camera_sources import CLOCK_AUTOPILOT_BOOT, SimFrameServer
from companion.cli import build_parser, load_config, main
from test_pipeline import CAM, LoopbackVehicle, free_port

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------- help and usage ---------
@pytest.mark.parametrize("argv, expect", [
    (["--help"], ["run", "replay", "OBSTACLE_DISTANCE"]),
    (["run", "--help"], ["--mavlink", "--camera", "--config", "--calibration", "--gcs", "--log-level", "sim://"]),
    (["replay", "--help"], ["--tlog", "--video", "--frames", "--out", "--plot", "recording's clock"]),
    (["kernels", "--help"], ["NUMBA_CACHE_DIR", "LLVM"]),
])
def test_help_explains_and_exits_0(argv, expect, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 0
    out = capsys.readouterr().out
    for word in expect:
        assert word in out, word


def test_kernels_command_loads_every_kernel_and_says_which(tmp_path):
    """`companion kernels` in a fresh process: compiled kernels ready (from this checkout's cache), or the
    numpy reference said so when forced; exit 0 either way."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "companion", "kernels"], capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stderr
    from companion.core import jit

    if jit.ENABLED:
        assert "compiled kernels: numba" in r.stdout and "kernel groups ready in" in r.stdout
    env["COMPANION_KERNELS"] = "numpy"
    r = subprocess.run([sys.executable, "-m", "companion", "kernels"], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0 and "numpy reference" in r.stdout, r.stdout + r.stderr


@pytest.mark.parametrize("argv, fragment", [
    ([], "COMMAND"),
    (["fly"], "invalid choice"),
    (["run", "--camera", "0"], "--mavlink"),
    (["run", "--mavlink", "udpin:127.0.0.1:14550"], "--camera"),
    (["replay", "--tlog", "a.tlog"], "--video"),
    (["run", "--mavlink", "x", "--camera", "0", "--log-level", "LOUD"], "--log-level"),
    (["run", "--mavlink", "x", "--camera", "0", "--duration", "soon"], "--duration"),
])
def test_bad_arguments_exit_2_with_a_message(argv, fragment, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert fragment in capsys.readouterr().err


def _run(argv, capsys) -> tuple[int, str]:
    rc = main(argv)
    return rc, capsys.readouterr().err


def test_configuration_errors_exit_2_naming_the_problem(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[pipeline]\nmax_frame_age = 0.2\n")
    rc, err = _run(["run", "--mavlink", "udpin:127.0.0.1:0", "--camera", "sim://127.0.0.1:1", "--config", str(cfg)], capsys)
    assert rc == 2 and "max_frame_age" in err and "[pipeline]" in err
    cfg.write_text('[camera_source]\nfile_pacing = "slow"\n')
    rc, err = _run(["run", "--mavlink", "udpin:127.0.0.1:0", "--camera", "sim://127.0.0.1:1", "--config", str(cfg)], capsys)
    assert rc == 2 and "file_pacing" in err
    cfg.write_text("[sectors]\nmax_distance_m = -1\n")
    rc, err = _run(["run", "--mavlink", "udpin:127.0.0.1:0", "--camera", "sim://127.0.0.1:1", "--config", str(cfg)], capsys)
    assert rc == 2 and "max_distance_m" in err
    rc, err = _run(["run", "--mavlink", "udpin:127.0.0.1:0", "--camera", "sim://127.0.0.1:1", "--config",
                    str(tmp_path / "missing.toml")], capsys)
    assert rc == 2 and "missing.toml" in err
    rc, err = _run(["run", "--mavlink", "udpin:127.0.0.1:0", "--camera", str(tmp_path / "nope.avi")], capsys)
    assert rc == 2 and "nope.avi" in err
    rc, err = _run(["run", "--mavlink", "udpin:127.0.0.1:notaport", "--camera", "sim://127.0.0.1:1"], capsys)
    assert rc == 2 and "notaport" in err
    rc, err = _run(["run", "--mavlink", "udpin:127.0.0.1:99999", "--camera", "sim://127.0.0.1:1"], capsys)
    assert rc == 2 and "99999" in err
    rc, err = _run(["run", "--mavlink", "udpin:127.0.0.1:0", "--camera", "sim://127.0.0.1:1", "--duration", "-3"], capsys)
    assert rc == 2 and "--duration" in err
    rc, err = _run(["run", "--mavlink", "udpin:127.0.0.1:0", "--camera", "sim://127.0.0.1:1", "--calibration",
                    str(tmp_path / "cal.yaml")], capsys)
    assert rc == 2 and "cal.yaml" in err


def test_config_loader_reads_the_new_tables_and_the_shipped_file(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[camera]\nwidth = 320\nheight = 240\n[camera_source]\ncapture_latency_s = 0.03\n"
                   "[pipeline]\nmax_frame_age_s = 0.15\n")
    rc = load_config(str(cfg))
    assert rc.companion.camera.width == 320
    assert rc.camera_source.capture_latency_s == 0.03 and rc.pipeline.max_frame_age_s == 0.15
    shipped = load_config(str(ROOT / "configs" / "companion.toml"))
    assert shipped.companion.camera.width > 0
    cal = tmp_path / "cal.yaml"
    import cv2

    fs = cv2.FileStorage(str(cal), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[300.0, 0, 160], [0, 301.0, 120], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[0.01, 0.0, 0.0, 0.0, 0.0]]))
    fs.write("image_width", 320)
    fs.write("image_height", 240)
    fs.release()
    rc = load_config(str(cfg), str(cal))
    assert rc.companion.camera.fx == 300.0 and rc.companion.camera.distortion[0] == 0.01


def test_parser_is_buildable_without_side_effects():
    p = build_parser()
    a = p.parse_args(["run", "--mavlink", "udpin:0.0.0.0:14550", "--camera", "0"])
    assert a.command == "run" and a.log_level == "INFO" and a.gcs is None


# ---------------------------------------------------------------------- a real process ---------
def test_companion_run_process_ranges_over_the_sim_transport_and_stops_on_sigint(tmp_path):
    """The whole thing as a separate process: the loopback vehicle streams telemetry on its own boot
    clock and answers TIMESYNC; the frame server sends 30 fps stamped on that boot clock (clock 1),
    so every frame reaches the pipeline through the TIMESYNC mapping."""
    flight = SyntheticFlight(camera=CAM, wall_north_m=25.0, velocity_ned=(1.0, 3.0, 0.0))
    port = free_port()
    server = SimFrameServer()
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[camera]\nwidth = {CAM.width}\nheight = {CAM.height}\nfx = {CAM.fx}\nfy = {CAM.fy}\n"
                   f"cx = {CAM.cx}\ncy = {CAM.cy}\n[tracks]\nmax_tracks = 100\n[harris]\nmax_corners = 100\n")
    stop = threading.Event()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "companion", "run", "--mavlink", f"udpin:127.0.0.1:{port}",
                             "--camera", server.address, "--config", str(cfg), "--log-level", "INFO"],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    # Its log, read as it comes: the flight starts once the companion has its kernels (loading them
    # from the cache takes a second or two, much longer on a loaded machine, and the flight reaches the
    # wall in 25 s, so a flight clock started at spawn could end before the companion is ready).
    err_lines: list[str] = []
    ready = threading.Event()

    def read_log():
        for line in proc.stderr:
            err_lines.append(line)
            if "kernels ready in" in line or "compiled kernels: off" in line:
                ready.set()

    reader = threading.Thread(target=read_log, daemon=True)
    reader.start()
    threads = []
    vehicle = None
    try:
        assert ready.wait(300) or proc.poll() is not None, "the companion did not load its kernels within 300 s"
        assert proc.poll() is None, "".join(err_lines)
        t0 = time.monotonic()
        boot = t0 - 50.0
        vehicle = LoopbackVehicle(port, flight, boot=boot, t0=t0)

        def vehicle_loop():
            while not stop.is_set():
                vehicle.step(time.monotonic())
                time.sleep(0.002)

        def camera_loop():
            k = 0
            while not stop.is_set():
                t = t0 + k / 30.0
                delay = t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                server.send(flight.render(t - t0), k, int((t - boot) * 1e9), CLOCK_AUTOPILOT_BOOT)
                k += 1

        threads = [threading.Thread(target=vehicle_loop, daemon=True), threading.Thread(target=camera_loop, daemon=True)]
        for th in threads:
            th.start()
        deadline = time.monotonic() + 20.0  # the wall is 25 m ahead at 1 m/s
        valid = []
        while time.monotonic() < deadline and len(valid) < 5:
            time.sleep(0.1)
            valid = [m for m in vehicle.received("OBSTACLE_DISTANCE") if m.distances[0] != UINT16_MAX]
            if proc.poll() is not None:
                break
        assert proc.poll() is None, "".join(err_lines)
        assert len(valid) >= 5, "no valid ranges from the companion process"
        truth = flight.wall_distance(time.monotonic() - t0)
        assert valid[-1].distances[0] / 100 == pytest.approx(truth, rel=0.25)
        hb = vehicle.received("HEARTBEAT")
        assert hb and hb[-1].get_srcComponent() == 196 and hb[-1].get_srcSystem() == vehicle.sysid
        # the receiver acknowledges frames: one of the last ten sent is acknowledged within 5 s (polled:
        # one stalled frame or a reconnect, which restarts the acknowledgements, is not a failure)
        def recent_ack() -> bool:
            n = server.frames_sent
            return any(server.wait_ack(i, 0.02) is not None for i in range(max(n - 10, 0), n))

        ack_deadline = time.monotonic() + 5.0
        while not recent_ack() and time.monotonic() < ack_deadline:
            time.sleep(0.1)
        assert recent_ack(), "the companion acknowledged none of the last ten frames within 5 s"
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=10)
        reader.join(timeout=5)
        err = "".join(err_lines)
        assert proc.returncode == 0, err
        assert "SIGINT received" in err and "stopped" in err
    finally:
        stop.set()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for th in threads:
            th.join(timeout=2)
        server.close()
        if vehicle is not None:
            vehicle.conn.close()
