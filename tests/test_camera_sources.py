"""Camera sources: OpenCV (file, URL, device via an injected fake), the simulator transport, recordings.

Loopback only: the HTTP MJPEG camera and the simulator's frame server run in this process on
127.0.0.1.  Nothing here may raise on bad input: bad frames are rejected and counted, dropped
sources come back with backoff.
"""

from __future__ import annotations

import http.server
import socket
import socketserver
import struct
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.camera_sources import (
    ACK_PROCESSED, ACK_REJECTED, CLOCK_AUTOPILOT_BOOT, CLOCK_HOST_MONOTONIC, CameraSourceConfig, Frame,
    OpenCVSource, RecordedSource, SimFrameServer, SimFrameSource, SourceError, check_gray, open_source,
    pack_sim_header, parse_camera_spec, read_frames_csv,
)
from companion.camera_sources.sim_transport import SIM_HEADER
from companion.errors import ConfigError

W, H = 160, 120
FAST = CameraSourceConfig(open_timeout_s=1.0, read_timeout_s=0.5, stall_timeout_s=0.3, reconnect_min_s=0.05,
                          reconnect_max_s=0.2)


def frame_img(k: int, w: int = W, h: int = H) -> np.ndarray:
    img = np.zeros((h, w), np.uint8)
    img[:, :] = (np.arange(w)[None, :] * 2 + k * 5) % 256
    img[: h // 2] //= 2
    return img


def read_n(src, n: int, timeout: float = 5.0) -> list[Frame]:
    out, t_end = [], time.monotonic() + timeout
    while len(out) < n and time.monotonic() < t_end:
        f = src.read(timeout=0.05)
        if f is not None:
            out.append(f)
    return out


def wait_until(cond, timeout: float = 5.0) -> bool:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


def write_video(path: Path, n: int, fps: float = 30.0, size=(W, H)) -> Path:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size, isColor=False)
    for k in range(n):
        vw.write(frame_img(k, *size))
    vw.release()
    return path


# ---------------------------------------------------------------------- checks ----------------
def test_check_gray_accepts_grey_and_colour_and_rejects_the_rest():
    g, why = check_gray(frame_img(0), W, H)
    assert why == "ok" and g.dtype == np.uint8 and g.shape == (H, W) and g.flags.c_contiguous
    g, why = check_gray(np.dstack([frame_img(0)] * 3), W, H)
    assert why == "ok" and g.shape == (H, W)
    g, why = check_gray(np.zeros((H, W, 4), np.uint8), W, H)
    assert why == "ok"
    for img, reason in ((None, "empty"), (np.zeros((0, 0), np.uint8), "empty"), (np.zeros((H, W), np.float32), "dtype"),
                        (np.zeros((H, W + 1), np.uint8), "wrong_size"), (np.zeros((H, W, 2), np.uint8), "corrupt"),
                        (np.zeros((2, H, W, 1), np.uint8), "corrupt"), (b"jpeg?", "corrupt")):
        g, why = check_gray(img, W, H)
        assert g is None and why == reason, (reason, why)


def test_camera_spec_parsing():
    assert parse_camera_spec("0") == ("device", 0)
    assert parse_camera_spec("/dev/video2") == ("device", "/dev/video2")
    assert parse_camera_spec("rtsp://10.0.0.5:8554/cam") == ("url", "rtsp://10.0.0.5:8554/cam")
    assert parse_camera_spec("http://cam.local/stream.mjpg")[0] == "url"
    assert parse_camera_spec("sim://127.0.0.1:5600") == ("sim", ("127.0.0.1", 5600))
    for bad in ("", "   ", "sim://127.0.0.1", "sim://host:0", "sim://host:99999", "no/such/video.avi"):
        with pytest.raises(ConfigError):
            parse_camera_spec(bad)


# ---------------------------------------------------------------------- files -----------------
def test_video_file_as_fast_as_possible_keeps_every_frame_on_the_file_timeline(tmp_path):
    path = write_video(tmp_path / "v.avi", 20, fps=25.0)
    src = OpenCVSource(str(path), W, H, CameraSourceConfig(file_pacing="fast"), clock=lambda: 100.0)
    frames = list(src)
    assert [f.index for f in frames] == list(range(20))
    assert np.allclose(np.diff([f.t for f in frames]), 1 / 25.0, atol=1e-3)
    assert frames[0].t == pytest.approx(100.0)
    assert src.ended and src.status().dropped == 0 and src.status().delivered == 20
    assert all(f.gray.shape == (H, W) and f.gray.dtype == np.uint8 for f in frames)


def test_video_file_paced_like_a_live_camera(tmp_path):
    path = write_video(tmp_path / "v.avi", 12, fps=30.0)
    src = OpenCVSource(str(path), W, H, CameraSourceConfig(file_pacing="realtime"))
    t0 = time.monotonic()
    frames = list(src)
    wall = time.monotonic() - t0
    assert len(frames) == 12 and wall >= 11 / 30.0 - 0.02
    assert np.median(np.diff([f.t for f in frames])) == pytest.approx(1 / 30.0, abs=0.01)
    assert src.ended
    src.close()


def test_video_file_of_the_wrong_size_is_rejected_frame_by_frame(tmp_path, caplog):
    """Before any good frame the size is a configuration error: said once (``size_error``), every frame counted, no
    "frame rejected" warning for the ones a reader reads on before the caller stops."""
    path = write_video(tmp_path / "v.avi", 5, size=(W * 2, H * 2))
    src = OpenCVSource(str(path), W, H, CameraSourceConfig(file_pacing="fast"))
    with caplog.at_level("WARNING"):
        assert list(src) == []
    assert src.status().rejected == {"wrong_size": 5}
    assert "delivers" in src.size_error
    assert not [r for r in caplog.records if "frame rejected" in r.getMessage()]


def test_missing_or_undecodable_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="no such video file"):
        OpenCVSource(str(tmp_path / "nope.avi"), W, H)
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"\x00" * 100)
    with pytest.raises(ConfigError, match="cannot open"):
        OpenCVSource(str(junk), W, H)


# ---------------------------------------------------------------------- live sources (fake capture) --
class FakeCapture:
    """A scripted cv2.VideoCapture: each script entry is a frame (array), 'fail' (grab fails) or 'bad' (retrieve fails)."""

    def __init__(self, script):
        self.script = list(script)
        self.props = {}
        self.released = False

    def isOpened(self):
        return True

    def set(self, prop, value):
        self.props[prop] = value
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def grab(self):
        if not self.script:
            time.sleep(0.01)
            return False
        item = self.script[0]
        if isinstance(item, str) and item == "fail":
            self.script.pop(0)
            time.sleep(0.01)
            return False
        return True

    def retrieve(self):
        item = self.script.pop(0)
        if isinstance(item, str) and item == "bad":
            return False, None
        return True, item

    def release(self):
        self.released = True


class FakeFactory:
    """Opens: a list of FakeCapture scripts, or None for a failed open."""

    def __init__(self, opens):
        self.opens = list(opens)
        self.calls = []

    def __call__(self, kind, value, config):
        self.calls.append((kind, value))
        if not self.opens:
            return None
        script = self.opens.pop(0)
        return None if script is None else FakeCapture(script)


def test_live_device_drops_reconnects_with_backoff_and_rejects_bad_frames():
    good = [frame_img(k) for k in range(5)]
    factory = FakeFactory([
        good[:3] + ["bad", np.zeros((10, 10), np.uint8), None] + good[3:],  # then silence: stall -> reopen
        None, None,  # the device is gone for two attempts
        [frame_img(k) for k in range(10, 15)],
    ])
    src = OpenCVSource("0", W, H, FAST, capture_factory=factory)
    try:
        assert src.kind == "device"
        assert wait_until(lambda: src.status().frames == 10, timeout=5.0)  # 5 before the drop, 5 after
        f = src.read(timeout=0.5)
        assert f is not None and np.array_equal(f.gray, frame_img(14))  # the newest one
        st = src.status()
        assert st.rejected == {"corrupt": 1, "wrong_size": 1, "empty": 1}
        assert st.reconnects == 1 and st.connected
        events = [text for _, text in src.drain_events()]
        assert any(t.startswith("Camera lost") for t in events) and "Camera restored" in events
        assert len(factory.calls) == 4  # first open, two failures, success
        assert factory.calls[0] == ("device", 0)
    finally:
        src.close()


def test_device_resolution_and_buffer_are_requested():
    cap_holder = {}

    def factory(kind, value, config):
        cap = FakeCapture([frame_img(0)])
        cap_holder["cap"] = cap
        return cap

    src = OpenCVSource("/dev/video7", W, H, CameraSourceConfig(device_fps=60.0), capture_factory=factory)
    try:
        assert read_n(src, 1)
        props = cap_holder["cap"].props
        assert props[cv2.CAP_PROP_FRAME_WIDTH] == W and props[cv2.CAP_PROP_FRAME_HEIGHT] == H
        assert props[cv2.CAP_PROP_FPS] == 60.0 and props[cv2.CAP_PROP_BUFFERSIZE] == 1
    finally:
        src.close()


def test_a_slow_reader_gets_the_newest_frame_and_older_ones_are_counted_dropped():
    frames = [frame_img(k) for k in range(30)]
    src = OpenCVSource("0", W, H, FAST, capture_factory=FakeFactory([frames]))
    try:
        assert wait_until(lambda: src.status().frames == 30)
        f = src.read(timeout=0.5)
        assert f is not None and f.index == 29
        st = src.status()
        assert st.dropped == 29 and st.delivered == 1
    finally:
        src.close()


def test_capture_timestamps_subtract_the_configured_latency():
    src = OpenCVSource("0", W, H, CameraSourceConfig(capture_latency_s=0.04), clock=lambda: 50.0,
                       capture_factory=FakeFactory([[frame_img(0)]]))
    try:
        f = read_n(src, 1)[0]
        assert f.t == pytest.approx(49.96)
    finally:
        src.close()


# ---------------------------------------------------------------------- HTTP MJPEG over loopback ----
class _MJPEGHandler(http.server.BaseHTTPRequestHandler):
    def log_message(self, *a):
        pass

    def do_GET(self):
        self.send_response(200)
        self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
        self.end_headers()
        k = 0
        try:
            while not self.server.stopping:
                ok, jpg = cv2.imencode(".jpg", frame_img(k))
                b = jpg.tobytes()
                self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(b) + b + b"\r\n")
                self.wfile.flush()
                k += 1
                time.sleep(1 / 50)
        except OSError:
            pass


class _MJPEGServer(socketserver.ThreadingMixIn, http.server.HTTPServer):
    daemon_threads = True
    allow_reuse_address = True


def _start_mjpeg(port: int = 0) -> _MJPEGServer:
    srv = _MJPEGServer(("127.0.0.1", port), _MJPEGHandler)
    srv.stopping = False
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv


def _stop_mjpeg(srv: _MJPEGServer) -> None:
    srv.stopping = True
    srv.shutdown()
    srv.server_close()


def test_http_mjpeg_camera_stops_and_comes_back():
    srv = _start_mjpeg()
    port = srv.server_address[1]
    src = open_source(f"http://127.0.0.1:{port}/stream.mjpg", W, H, FAST)
    try:
        assert src.kind == "url"
        assert len(read_n(src, 10, timeout=8.0)) == 10
        _stop_mjpeg(srv)
        assert wait_until(lambda: not src.connected, timeout=5.0)
        srv = _start_mjpeg(port)
        assert wait_until(lambda: src.connected and src.status().reconnects == 1, timeout=8.0)
        assert len(read_n(src, 5, timeout=5.0)) == 5
        texts = [t for _, t in src.drain_events()]
        assert any(t.startswith("Camera lost") for t in texts) and "Camera restored" in texts
    finally:
        src.close()
        _stop_mjpeg(srv)


# ---------------------------------------------------------------------- simulator transport ------
def test_sim_transport_round_trip_with_both_clocks_and_acks():
    offset = 1234.5  # companion = boot + offset (what TIMESYNC would say)
    with SimFrameServer() as server:
        src = SimFrameSource(server.address, W, H, FAST, clock_map=lambda tb: tb + offset)
        try:
            assert server.wait_client(3.0)
            assert server.send(frame_img(1), 1, 10_500_000_000, CLOCK_AUTOPILOT_BOOT)
            f = read_n(src, 1)[0]
            assert f.index == 1 and f.t == pytest.approx(10.5 + offset)
            assert np.array_equal(f.gray, frame_img(1))
            src.done(f, "processed")
            assert server.wait_ack(1, 2.0) == ACK_PROCESSED
            assert server.send(frame_img(2), 2, 77_000_000_000, CLOCK_HOST_MONOTONIC)
            f = read_n(src, 1)[0]
            assert f.t == pytest.approx(77.0)
        finally:
            src.close()


def test_sim_frames_nobody_read_are_acknowledged_dropped():
    # a frame overwritten by a newer one before the pipeline read it still gets its acknowledgement
    from companion.camera_sources import ACK_DROPPED

    with SimFrameServer() as server:
        src = SimFrameSource(server.address, W, H, FAST, clock_map=lambda tb: tb)
        try:
            assert server.wait_client(3.0)
            for k in range(3):  # nobody reads: 0 and 1 are superseded
                assert server.send(frame_img(k), k, (10 + k) * 1_000_000_000, CLOCK_AUTOPILOT_BOOT)
            assert server.wait_ack(0, 2.0) == ACK_DROPPED and server.wait_ack(1, 2.0) == ACK_DROPPED
            f = read_n(src, 1)[0]
            assert f.index == 2 and src.status().dropped == 2
            src.done(f, "processed")
            assert server.wait_ack(2, 2.0) == ACK_PROCESSED
        finally:
            src.close()


def test_sim_transport_rejects_bad_frames_and_resyncs_after_garbage():
    with SimFrameServer() as server:
        src = SimFrameSource(server.address, W, H, FAST)  # no clock map: clock-1 frames cannot be placed
        try:
            assert server.wait_client(3.0)
            assert server.send(frame_img(0), 0, 1_000_000_000, CLOCK_AUTOPILOT_BOOT)  # no_clock
            assert server.wait_ack(0, 2.0) == ACK_REJECTED
            assert server.send(np.zeros((H // 2, W), np.uint8), 1, 1, CLOCK_HOST_MONOTONIC)  # wrong size
            assert server.wait_ack(1, 2.0) == ACK_REJECTED
            assert server.send(frame_img(2), 2, 2_000_000_000, clock=9)  # unknown clock
            assert server.wait_ack(2, 2.0) == ACK_REJECTED
            assert server.send(frame_img(3), 3, 3_000_000_000, CLOCK_HOST_MONOTONIC)
            assert read_n(src, 1)[0].index == 3
            assert server.send(frame_img(4), 3, 3_100_000_000, CLOCK_HOST_MONOTONIC)  # index did not increase
            assert server.wait_ack(3, 2.0) is not None
            # garbage on the stream: protocol error, the receiver drops the connection and reconnects
            clients = server.clients
            server.send_raw(b"\xde\xad\xbe\xef" * 10 + b"\x00" * 24)
            assert wait_until(lambda: server.clients > clients and server.connected, timeout=5.0)
            # a header announcing an absurd payload is refused too (no allocation of it)
            clients = server.clients
            server.send_raw(SIM_HEADER.pack(b"MRFR", 1, 40, 9, 0, 2, 1, 0, 100_000, 100_000, 10_000_000_000 % 2**32))
            assert wait_until(lambda: server.clients > clients and server.connected, timeout=5.0)
            assert server.send(frame_img(5), 10, 5_000_000_000, CLOCK_HOST_MONOTONIC)
            f = read_n(src, 1)[0]
            assert f.index == 10
            rej = src.status().rejected
            assert rej["no_clock"] == 1 and rej["wrong_size"] == 1 and rej["corrupt"] == 1 and rej["bad_time"] == 1
            assert rej["protocol"] == 2
        finally:
            src.close()


def test_sim_source_waits_for_the_server_and_survives_its_restart():
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    src = SimFrameSource(f"sim://127.0.0.1:{port}", W, H, FAST)
    try:
        time.sleep(0.3)  # nobody listening yet: connect attempts fail quietly
        assert not src.connected
        server = SimFrameServer(port=port)
        assert server.wait_client(5.0)
        assert server.send(frame_img(0), 0, 1_000_000, CLOCK_HOST_MONOTONIC)
        assert read_n(src, 1)
        server.close()  # the simulator goes away ...
        assert wait_until(lambda: not src.connected, 3.0)
        server = SimFrameServer(port=port)  # ... and comes back, counting from 0 again
        assert server.wait_client(5.0)
        assert server.send(frame_img(1), 0, 2_000_000, CLOCK_HOST_MONOTONIC)
        f = read_n(src, 1)
        assert f and f[0].index == 0
        texts = [t for _, t in src.drain_events()]
        assert any(t.startswith("Camera lost") for t in texts) and "Camera restored" in texts
        server.close()
    finally:
        src.close()


def test_sim_header_layout():
    h = pack_sim_header(7, 123, 320, 240, CLOCK_AUTOPILOT_BOOT)
    assert len(h) == 40 and h[:4] == b"MRFR"
    assert struct.unpack_from("<HHQq", h, 4) == (1, 40, 7, 123)
    assert struct.unpack_from("<BBHIII", h, 24) == (1, 1, 0, 320, 240, 320 * 240)


# ---------------------------------------------------------------------- recordings ----------------
def test_recorded_source_pairs_video_frames_with_csv_times(tmp_path):
    write_video(tmp_path / "v.avi", 6)
    (tmp_path / "frames.csv").write_text("index,t_s\n" + "".join(f"{k},{1.7e9 + k / 30:.6f}\n" for k in range(6)))
    src = RecordedSource(tmp_path / "v.avi", tmp_path / "frames.csv", W, H)
    frames = list(src)
    assert [f.index for f in frames] == list(range(6))
    assert frames[3].t == pytest.approx(1.7e9 + 0.1, abs=1e-6)
    assert len(src) == 6 and src.ended


def test_recorded_source_tolerates_mismatched_lengths_and_bad_rows(tmp_path):
    write_video(tmp_path / "v.avi", 6)
    rows = "index,t_s\n0,10.0\n1,10.1\n2,10.05\n3,10.3\n"  # row 2 goes back in time; csv shorter than the video
    (tmp_path / "frames.csv").write_text(rows)
    src = RecordedSource(tmp_path / "v.avi", tmp_path / "frames.csv", W, H)
    frames = list(src)
    assert [f.index for f in frames] == [0, 1, 3]
    assert src.status().rejected == {"bad_time": 1}


@pytest.mark.parametrize("text, match", [
    ("idx,time\n0,1.0\n", "header"),
    ("index,t_s\n", "no frames"),
    ("index,t_s\n0,abc\n", "expected"),
    ("index,t_s\n0,nan\n", "not finite"),
])
def test_frames_csv_errors_name_the_problem(tmp_path, text, match):
    p = tmp_path / "frames.csv"
    p.write_text(text)
    with pytest.raises(SourceError, match=match):
        read_frames_csv(p)
    with pytest.raises(SourceError, match="no such frames file"):
        read_frames_csv(tmp_path / "missing.csv")


def test_config_table_validation():
    for bad in ({"file_pacing": "slow"}, {"reconnect_min_s": 0}, {"reconnect_min_s": 5.0, "reconnect_max_s": 1.0},
                {"capture_latency_s": 2.0}, {"buffer_size": -1}):
        with pytest.raises(ConfigError):
            CameraSourceConfig(**bad)
