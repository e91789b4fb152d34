"""Property-based tests of the file readers and the configuration loader (hypothesis): random and
mutated inputs never raise anything but the documented errors — a :class:`ConfigError` (exit 2,
one line naming the file) — and valid inputs read back exactly.

The MAVLink input path has its own property tests in tests/test_link_security.py.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from companion.camera_sources import read_frames_csv
from companion.errors import ConfigError
from companion.io.config_files import CompanionConfig, load_companion_config, load_opencv_calibration
from companion.io.tlog import read_tlog

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = (ROOT / "configs" / "companion.toml").read_bytes()
SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _write(tmp_path, name: str, data: bytes) -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


def _mutate(data: bytes, edits) -> bytes:
    """Apply (position fraction, kind, byte) edits: flip, delete, insert, truncate."""
    b = bytearray(data)
    for frac, kind, val in edits:
        if not b:
            break
        i = min(len(b) - 1, int(frac * len(b)))
        if kind == 0:
            b[i] ^= val or 1
        elif kind == 1:
            del b[i]
        elif kind == 2:
            b.insert(i, val)
        else:
            del b[i:]
    return bytes(b)


EDITS = st.lists(st.tuples(st.floats(0, 1), st.integers(0, 3), st.integers(0, 255)), min_size=1, max_size=8)


# ---------------------------------------------------------------------- configuration ----------
@SETTINGS
@given(edits=EDITS)
def test_mutated_companion_config_loads_or_names_the_problem(tmp_path, edits):
    p = _write(tmp_path, "c.toml", _mutate(SHIPPED, edits))
    try:
        cfg = load_companion_config(p)
    except ConfigError as exc:
        assert str(p) in str(exc) and "\n" not in str(exc).strip()
    else:
        assert isinstance(cfg, CompanionConfig)


@SETTINGS
@given(table=st.sampled_from([f.name for f in __import__("dataclasses").fields(CompanionConfig)]),
       key=st.text(st.characters(min_codepoint=97, max_codepoint=122) | st.just("_"), min_size=1, max_size=30),
       value=st.one_of(st.integers(-10**12, 10**12), st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
                       st.text(max_size=20), st.lists(st.integers(-5, 5), max_size=4)))
def test_any_key_and_value_in_any_table_loads_or_is_a_config_error(tmp_path, table, key, value):
    def lit(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float):
            return "nan" if math.isnan(v) else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
        if isinstance(v, str):
            return '"' + v.encode("unicode_escape").decode("ascii").replace('"', '\\"') + '"'
        if isinstance(v, list):
            return "[" + ", ".join(lit(x) for x in v) + "]"
        return str(v)

    p = _write(tmp_path, "c.toml", f'extends = "companion.toml"\n[{table}]\n{key} = {lit(value)}\n'.encode())
    try:
        tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError:
        pass
    try:
        load_companion_config(p)
    except ConfigError as exc:
        assert str(p) in str(exc)


# ---------------------------------------------------------------------- frames.csv -------------
@SETTINGS
@given(rows=st.lists(st.tuples(st.integers(0, 10**6), st.floats(-1e9, 1e9, allow_nan=False)), min_size=1, max_size=40))
def test_valid_frames_csv_reads_back_exactly(tmp_path, rows):
    text = "index,t_s\n" + "".join(f"{i},{t!r}\n" for i, t in rows)
    idx, t = read_frames_csv(_write(tmp_path, "frames.csv", text.encode()))
    assert idx.tolist() == [i for i, _ in rows] and t.tolist() == [t for _, t in rows]


@SETTINGS
@given(data=st.one_of(st.binary(max_size=400),
                      st.builds(lambda edits: _mutate(b"index,t_s\n0,1.0\n1,1.033\n2,1.067\n", edits), EDITS)))
def test_random_or_mutated_frames_csv_reads_or_is_a_config_error(tmp_path, data):
    p = _write(tmp_path, "frames.csv", data)
    try:
        idx, t = read_frames_csv(p)
    except ConfigError as exc:
        assert str(p) in str(exc)
    else:
        assert len(idx) == len(t) >= 1 and np.all(np.isfinite(t))


# ---------------------------------------------------------------------- calibration ------------
def _calibration_yaml(fx=300.0, fy=301.0, cx=160.0, cy=120.0, d=(0.01, 0.0, 0.0, 0.0, 0.0)) -> bytes:
    dist = ", ".join(f"{v!r}" for v in d)
    return (f"%YAML:1.0\n---\nimage_width: 320\nimage_height: 240\n"
            f"camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
            f"   data: [ {fx!r}, 0., {cx!r}, 0., {fy!r}, {cy!r}, 0., 0., 1. ]\n"
            f"distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: {len(d)}\n   dt: d\n   data: [ {dist} ]\n").encode()


def test_calibration_yaml_reads_back():
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        cam = load_opencv_calibration(_write(Path(d), "cal.yaml", _calibration_yaml()))
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (300.0, 301.0, 160.0, 120.0, 320, 240)
    assert cam.distortion[0] == 0.01


def test_a_matrix_without_cols_is_a_config_error_not_a_corrupted_heap(tmp_path):
    """OpenCV 5.0's FileNode.mat() on an !!opencv-matrix without ``cols`` corrupts the heap; the process
    aborted later (``free(): invalid next size``), e.g. in an unrelated test after this file's fuzzing.
    Loaded 300 times in a child process: the loader must never hand such a node to OpenCV."""
    import subprocess
    import sys

    bad = _calibration_yaml().replace(b"   cols: 3\n", b"   cols4: 3\n", 1)
    p = _write(tmp_path, "cal.yaml", bad)
    code = ("import sys\nfrom companion.io.config_files import load_opencv_calibration\nfrom companion.errors import ConfigError\n"
            "for _ in range(300):\n    try:\n        load_opencv_calibration(sys.argv[1])\n"
            "    except ConfigError as exc:\n        msg = str(exc)\nprint(msg)\n")
    r = subprocess.run([sys.executable, "-c", code, str(p)], capture_output=True, text=True, timeout=120,
                       env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-500:]
    assert "camera_matrix is not an OpenCV matrix" in r.stdout


def test_calibration_written_by_opencv_reads_back_in_every_format(tmp_path):
    import cv2

    K = np.array([[612.5, 0, 331.2], [0, 611.9, 242.7], [0, 0, 1]])
    D = np.array([[0.1, -0.2, 0.001, 0.002, 0.05]])
    for ext in ("yaml", "xml", "json"):
        p = tmp_path / f"cal.{ext}"
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", K)
        fs.write("distortion_coefficients", D)
        fs.write("image_width", 640)
        fs.release()
        cam = load_opencv_calibration(p)
        assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width) == (612.5, 611.9, 331.2, 242.7, 640), ext
        assert cam.distortion == (0.1, -0.2, 0.001, 0.002, 0.05), ext


@SETTINGS
@given(data=st.one_of(st.binary(max_size=300), st.builds(lambda e: _mutate(_calibration_yaml(), e), EDITS)))
@example(data=b"-")  # a YAML sequence at the top level: OpenCV 5 asserts in getNode (was an uncaught cv2.error)
@example(data=b"%YAML:1.0\n---\n- 1")
def test_random_or_mutated_calibration_reads_or_is_a_config_error(tmp_path, data):
    p = _write(tmp_path, "cal.yaml", data)
    try:
        cam = load_opencv_calibration(p)
    except ConfigError as exc:
        assert str(p) in str(exc)
    else:
        assert cam.fx > 0 and cam.fy > 0 and all(math.isfinite(v) for v in cam.distortion)


# ---------------------------------------------------------------------- tlog -------------------
@SETTINGS
@given(data=st.binary(max_size=600))
def test_random_bytes_as_a_tlog_read_or_are_a_config_error(tmp_path, data):
    p = _write(tmp_path, "x.tlog", data)
    try:
        read_tlog(p)
    except ConfigError as exc:
        assert str(p) in str(exc)



@SETTINGS
@given(why=st.text(max_size=80), src=st.text(alphabet="0123456789abcdefz", max_size=80))
@example(why=("0123456789a" * 7)[:72], src="012345" * 12)  # both valid: read
@example(why="b" * 72, src="6" * 72)  # one past the last code of each: skipped
@example(why="A" * 72, src=":" * 72)  # upper case, and the character after '9': skipped
def test_sector_log_digit_fields_read_or_are_skipped(tmp_path, why, src):
    """Any text in a sector-log line's ``why`` or ``src`` (companion/sector_log.py): the line is read only when it is
    72 digits within the field's range, and nothing raises; a valid line written by the log reads back exactly."""
    import json

    from companion.core.sectors_types import SectorSource, UnknownReason
    from companion.sector_log import SectorLog, read_sector_log, read_sector_reasons

    path = tmp_path / "s.jsonl"
    path.unlink(missing_ok=True)
    log = SectorLog(path)
    good_src, good_why = np.arange(72) % (max(SectorSource) + 1), np.arange(72) % (max(UnknownReason) + 1)
    log("autopilot", 1, np.full(72, 65535), good_src, None, good_why)
    log.close()
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps({"out": "autopilot", "time_usec": 2, "d": [65535] * 72, "src": src, "why": why}) + "\n")
    reasons, sources = read_sector_reasons(path), read_sector_log(path)
    key1 = (1, np.full(72, 65535, np.uint16).tobytes())
    assert np.array_equal(reasons[key1], good_why) and np.array_equal(sources[key1], good_src)
    key2 = (2, key1[1])
    hexval = lambda t, top: len(t) == 72 and all(c in "0123456789abcdef"[: top + 1] for c in t)  # noqa: E731
    assert (key2 in reasons) == hexval(why, int(max(UnknownReason)))
    assert (key2 in sources) == hexval(src, int(max(SectorSource)))
