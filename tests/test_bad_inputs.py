"""Bad input files: every command that reads a file stops with exit code 2 and one line naming the
file and what is wrong with it (no traceback); a tlog cut while being written, or cut mid-flight,
is replayed with a warning naming the truncation; ``companion run`` with a camera whose frames do
not have the configured size stops once, with exit code 2."""

from __future__ import annotations

import re
import struct
import threading
import time

import cv2
import numpy as np
import pytest

from companion.mavlink.dialect import mavlink  # noqa: I001 (first: MAVLink 2)
from bench.latency import SyntheticFlight
from companion.camera_sources import CLOCK_HOST_MONOTONIC, SimFrameServer, SimFrameSource
from companion.cli import load_config, main as companion_main
from companion.core.camera import CameraConfig
from companion.io.tlog import TlogError, read_tlog, scan_tlog_end
from companion.replay import replay, write_recording
from flightsim.cli import main as flightsim_main
from test_flightsim_fly import ROOT, variant

CAM = CameraConfig.from_fov(160, 120, 60.0)
EPOCH = 1.7e9


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 1.5-s synthetic recording (tlog, video, frames.csv, camera.toml) to break one file at a time."""
    d = tmp_path_factory.mktemp("rec")
    write_recording(d, SyntheticFlight(camera=CAM, wall_north_m=15.0, velocity_ned=(1.0, 3.0, 0.0)), 1.5, epoch_s=EPOCH)
    return d


@pytest.fixture(scope="module")
def bad(tmp_path_factory):
    """Broken files by kind: empty, binary garbage, a directory, text that is not UTF-8, malformed YAML."""
    d = tmp_path_factory.mktemp("bad")
    (d / "empty").write_bytes(b"")
    (d / "garbage").write_bytes(np.random.default_rng(7).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    (d / "a_directory").mkdir()
    (d / "latin1.toml").write_bytes("[camera]\n# Kamera für außen\n".encode("latin-1"))
    (d / "broken.yaml").write_text("%YAML:1.0\ncamera_matrix: [1, 2\n  rows: }{\n")
    (d / "not_a_matrix.yaml").write_text("%YAML:1.0\ncamera_matrix: 3\ndistortion_coefficients: 0\n")
    (d / "frames.csv").write_text("index,t_s\n0,soon\n")
    return d


def one_error_line(err: str, *fragments: str) -> None:
    """``err`` holds the error as one line naming every fragment, and no traceback."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ": error: " in ln]
    assert len(lines) == 1, err
    for f in fragments:
        assert f in lines[0], (f, lines[0])


# ---------------------------------------------------------------------- companion ----------------
def _replay_args(rec, tmp_path, **swap):
    files = {"tlog": rec / "telemetry.tlog", "video": rec / "video.avi", "frames": rec / "frames.csv"}
    files.update(swap)
    return ["replay", *(a for k, v in files.items() for a in (f"--{k}", str(v))), "--out", str(tmp_path / "r.tlog"),
            "--camera-config", str(rec / "camera.toml"), "--no-plot", "--quiet"]


@pytest.mark.parametrize("which, name, says", [
    ("tlog", "empty", "the tlog is empty"),
    ("tlog", "garbage", "not a MAVLink tlog"),
    ("tlog", "a_directory", "is a directory"),
    ("tlog", "missing", "no such tlog"),
    ("video", "empty", "the video file is empty"),
    ("video", "garbage", "OpenCV cannot open"),
    ("frames", "empty", "the frames file is empty"),
    ("frames", "garbage", "not a frames file"),
    ("frames", "frames.csv", "expected 'index,t_s'"),
    ("frames", "a_directory", "is a directory"),
])
def test_replay_bad_recording_files_exit_2(recording, bad, tmp_path, capsys, which, name, says):
    rc = companion_main(_replay_args(recording, tmp_path, **{which: bad / name}))
    assert rc == 2
    one_error_line(capsys.readouterr().err, name, says)
    assert not list(tmp_path.iterdir()), "nothing may be written for bad input"


@pytest.mark.parametrize("option, name, says", [
    ("--calibration", "broken.yaml", "not a calibration file OpenCV can read (line "),  # was SystemError, exit 1
    ("--calibration", "garbage", "not a calibration file OpenCV can read"),
    ("--calibration", "empty", "the calibration file is empty"),
    ("--calibration", "not_a_matrix.yaml", "camera_matrix is not an OpenCV matrix"),
    ("--calibration", "a_directory", "is a directory"),
    ("--config", "latin1.toml", "byte 0xfc on line 2 is not UTF-8"),
    ("--config", "garbage", "not a configuration file"),
    ("--config", "a_directory", "is a directory"),
    ("--camera-config", "garbage", "not a configuration file"),
])
@pytest.mark.parametrize("command", ["run", "replay"])
def test_companion_bad_configuration_files_exit_2(recording, bad, tmp_path, capsys, command, option, name, says):
    if command == "run":  # fails while loading the configuration, before any connection
        argv = ["run", "--mavlink", "udpin:127.0.0.1:0", "--camera", "sim://127.0.0.1:9", option, str(bad / name)]
    else:
        argv = [a for a in _replay_args(recording, tmp_path) if a != str(recording / "camera.toml")]
        argv.remove("--camera-config")
        argv += [option, str(bad / name)]
    rc = companion_main(argv)
    assert rc == 2
    one_error_line(capsys.readouterr().err, name, says)


def test_replay_output_path_that_is_a_directory_exits_2(recording, tmp_path, capsys):
    argv = _replay_args(recording, tmp_path)
    argv[argv.index("--out") + 1] = str(tmp_path)
    assert companion_main(argv) == 2
    one_error_line(capsys.readouterr().err, "is a directory")


# ---------------------------------------------------------------------- truncated tlogs -----------
def record_offsets(data: bytes) -> list[int]:
    """Where each record of a (MAVLink 2, unsigned) tlog starts."""
    at, out = 0, []
    while at < len(data):
        out.append(at)
        at += 8 + 12 + data[at + 9]  # stamp + 10-byte header + payload + CRC
    return out


def test_scan_tlog_end_finds_a_cut_at_every_byte_of_the_last_record(recording):
    data = (recording / "telemetry.tlog").read_bytes()
    whole = scan_tlog_end(data)
    assert whole.framed and whole.truncated_bytes == 0 and whole.complete_bytes == len(data) and whole.records > 50
    last = scan_tlog_end(data[:-1]).complete_bytes  # where the last record starts
    for cut in range(last + 1, len(data)):  # inside its timestamp, its header, its payload, its CRC
        end = scan_tlog_end(data[:cut])
        assert end.truncated_bytes == cut - last and end.records == whole.records - 1, cut
    lost = scan_tlog_end(data[:100] + b"\x00" * 9 + data[100:])  # framing lost: no verdict on the end
    assert not lost.framed and lost.truncated_bytes == 0


def test_read_tlog_refuses_what_is_not_a_tlog(tmp_path, bad):
    with pytest.raises(TlogError, match="empty"):
        read_tlog(bad / "empty")
    with pytest.raises(TlogError, match="not a MAVLink tlog"):
        read_tlog(bad / "garbage")
    with pytest.raises(TlogError, match="no such tlog"):
        read_tlog(tmp_path / "nope.tlog")


def test_replay_of_a_tlog_cut_mid_flight_warns_and_replays(recording, tmp_path, caplog):
    """The tlog ends 0.6 s into the 1.5-s video, inside a record: the replay runs to the end of the
    video and says both that the file is truncated and that the telemetry stops before the frames."""
    data = (recording / "telemetry.tlog").read_bytes()
    at = next(k for k in record_offsets(data) if struct.unpack(">Q", data[k:k + 8])[0] > (EPOCH + 0.6) * 1e6)
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[:at + 20])  # 20 bytes into the first record after 0.6 s
    rc = load_config(None, None, str(recording / "camera.toml"))
    with caplog.at_level("WARNING"):
        s = replay(cut, recording / "video.avi", recording / "frames.csv", tmp_path / "r.tlog", rc.companion,
                   pipeline=rc.pipeline, fixed_processing_s=0.02)
    assert s.frames == int(1.5 * 30) + 1  # every frame of the video was replayed
    assert len(s.warnings) == 2
    assert "truncated" in s.warnings[0] and "20 bytes" in s.warnings[0] and str(cut) in s.warnings[0]
    assert "cut mid-flight" in s.warnings[1] and re.search(r"ends 0\.9\d s before the last frame", s.warnings[1])
    assert [r.getMessage() for r in caplog.records if r.name == "companion.replay"] == s.warnings
    assert (tmp_path / "r.tlog").is_file()


def test_replay_of_a_complete_recording_warns_of_nothing(recording, tmp_path):
    rc = load_config(None, None, str(recording / "camera.toml"))
    s = replay(recording / "telemetry.tlog", recording / "video.avi", recording / "frames.csv", tmp_path / "r.tlog",
               rc.companion, pipeline=rc.pipeline, fixed_processing_s=0.02)
    assert s.warnings == []


# ---------------------------------------------------------------------- camera size in `run` ----
def test_run_stops_once_with_exit_2_when_the_first_frame_has_another_size(tmp_path, capsys, caplog):
    """A video file of 64×48 frames against a 640×480 configuration: one error, exit 2 (before:
    a warning per rejected frame and exit 0 when the file ended)."""
    video = tmp_path / "small.avi"
    vw = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48), isColor=False)
    for k in range(60):
        vw.write(np.full((48, 64), 4 * k, np.uint8))
    vw.release()
    with caplog.at_level("WARNING"):
        rc = companion_main(["run", "--mavlink", "udpin:127.0.0.1:0", "--camera", str(video), "--duration", "20"])
    assert rc == 2
    one_error_line(capsys.readouterr().err, str(video), "delivers 64×48 frames", "says 640×480")
    assert not [r for r in caplog.records if "frame rejected" in r.getMessage()]


def test_live_camera_at_the_wrong_size_stops_the_run(capsys):
    """The simulator's frame transport (a live source) sending 80×60 frames to a 640×480 companion."""
    server = SimFrameServer()
    stop = threading.Event()

    def send():
        k = 0
        while not stop.is_set():
            server.send(np.zeros((60, 80), np.uint8), k, time.monotonic_ns(), CLOCK_HOST_MONOTONIC)
            k += 1
            time.sleep(0.03)

    th = threading.Thread(target=send, daemon=True)
    th.start()
    try:
        t0 = time.monotonic()
        rc = companion_main(["run", "--mavlink", "udpin:127.0.0.1:0", "--camera", server.address, "--duration", "30"])
        assert rc == 2 and time.monotonic() - t0 < 20
        one_error_line(capsys.readouterr().err, "delivers 80×60 frames")
    finally:
        stop.set()
        th.join(timeout=2)
        server.close()


def test_a_size_change_after_good_frames_is_rejected_not_fatal():
    """In flight (good frames came first), frames of another size are rejected and counted: the
    companion keeps running with its sectors unknown, as for a lost camera."""
    with SimFrameServer() as server:
        src = SimFrameSource(server.address, 80, 60)
        try:
            assert server.wait_client(5.0)
            server.send(np.zeros((60, 80), np.uint8), 0, time.monotonic_ns(), CLOCK_HOST_MONOTONIC)
            assert src.read(timeout=5.0) is not None
            server.send(np.zeros((48, 64), np.uint8), 1, time.monotonic_ns(), CLOCK_HOST_MONOTONIC)
            deadline = time.monotonic() + 5.0
            while not src.status().rejected and time.monotonic() < deadline:
                time.sleep(0.01)
            assert src.status().rejected == {"wrong_size": 1}
            assert src.size_error is None
        finally:
            src.close()


# ---------------------------------------------------------------------- flightsim ----------------
@pytest.mark.parametrize("command", ["fly", "sitl", "campaign"])
@pytest.mark.parametrize("name, says", [
    ("garbage", "not a scenario file: byte"),
    ("latin1.toml", "is not UTF-8"),
    ("a_directory", "is a directory, not a scenario file"),
])
def test_flightsim_bad_scenario_files_exit_2(bad, tmp_path, capsys, command, name, says):
    argv = [command, str(bad / name), "--out", str(tmp_path / "out")] + (["--runs", "1"] if command == "campaign" else [])
    assert flightsim_main(argv) == 2
    one_error_line(capsys.readouterr().err, name, says)


def test_flightsim_bad_world_and_companion_config_exit_2(bad, tmp_path, capsys):
    scen = variant(tmp_path, "quad_approach", {"world": f'"{(bad / "garbage").as_posix()}"'})
    assert flightsim_main(["fly", str(scen), "--out", str(tmp_path / "o")]) == 2
    one_error_line(capsys.readouterr().err, "garbage", "not a world file")
    good = variant(tmp_path, "quad_approach", {"duration_s": "1.0"}, out_name="good.toml")
    for command in ("sitl", "campaign"):  # the companion's TOML is checked before anything starts
        option = "--config" if command == "sitl" else "--companion-config"
        argv = [command, str(good), "--out", str(tmp_path / command), option, str(bad / "latin1.toml")]
        assert flightsim_main(argv + (["--runs", "1"] if command == "campaign" else [])) == 2
        one_error_line(capsys.readouterr().err, "latin1.toml", "is not UTF-8")
    assert flightsim_main(["fly", str(good), "--out", str(bad / "garbage")]) == 2
    one_error_line(capsys.readouterr().err, "is a file, not a directory")


@pytest.mark.parametrize("option, name, says", [
    ("--ranges", "empty", "the tlog is empty"),  # scored as "no ranges" with exit 0 before
    ("--ranges", "garbage", "not a MAVLink tlog"),
    ("--truth", "garbage", "not a truth.npz"),
    ("--truth", "empty", "the truth file is empty"),
    ("--config", "a_directory", "is a directory"),
    ("--companion-config", "garbage", "not a configuration file"),
    ("--scenario", "garbage", "not a scenario file"),
])
def test_flightsim_score_bad_files_exit_2(recording, bad, tmp_path, capsys, option, name, says):
    truth = tmp_path / "truth.npz"
    np.savez(truth, t_s=np.arange(3.0))
    args = {"--ranges": str(recording / "telemetry.tlog"), "--truth": str(truth), option: str(bad / name)}
    rc = flightsim_main(["score", *(a for kv in args.items() for a in kv), "--out", str(tmp_path / "s")])
    assert rc == 2
    one_error_line(capsys.readouterr().err, name, says)
    assert not (tmp_path / "s" / "score.json").exists()


def test_flightsim_score_warns_of_a_truncated_ranges_tlog(recording, tmp_path, caplog):
    from flightsim.score.files import read_ranges_tlog

    cut = tmp_path / "cut.tlog"
    cut.write_bytes((recording / "telemetry.tlog").read_bytes()[:-5])
    with caplog.at_level("WARNING"):
        read_ranges_tlog(cut)
    assert any("truncated" in r.getMessage() and str(cut) in r.getMessage() for r in caplog.records)


def test_shipped_files_are_still_accepted():
    assert load_config(str(ROOT / "configs" / "companion.toml")).companion.camera.width > 0
