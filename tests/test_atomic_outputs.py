"""Outputs appear complete or not at all; interrupted commands exit 130 (Ctrl-C) or 143 (SIGTERM)
and leave nothing at their output paths (partial tlogs under ``*.partial``).

The helpers of :mod:`companion.io.atomic` are tested directly; ``companion replay`` and
``flightsim fly`` as separate processes sent SIGINT / SIGTERM in the middle of their work; a
campaign interrupted while its workers run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from companion.mavlink.dialect import mavutil  # noqa: I001 (first: MAVLink 2)
from bench.latency import SyntheticFlight
from companion.core.camera import CameraConfig
from companion.errors import Terminated
from companion.interrupts import interrupt_exit_code, raise_on_sigterm, signals_deferred
from companion.io.atomic import StagedFiles, atomic_dir, atomic_open, atomic_path, partial_path, write_text_atomic
from companion.replay import write_recording
from test_flightsim_fly import ROOT, variant

ENV = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")


def names(d: Path) -> set[str]:
    return {p.name for p in d.iterdir()}


# ---------------------------------------------------------------------- the helpers ------------
def test_atomic_path_renames_on_success_and_removes_or_keeps_partial_on_failure(tmp_path):
    out = tmp_path / "ranges.tlog"
    out.write_bytes(b"old, complete")
    with pytest.raises(RuntimeError):
        with atomic_path(out) as tmp:
            assert tmp.parent == tmp_path and tmp.name.startswith(".ranges.tlog.") and tmp.suffix == ".tlog"
            tmp.write_bytes(b"half")
            raise RuntimeError("cut")
    assert names(tmp_path) == {"ranges.tlog"} and out.read_bytes() == b"old, complete"  # the old file untouched
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(out, keep_partial=True) as tmp:
            tmp.write_bytes(b"half")
            raise KeyboardInterrupt
    assert names(tmp_path) == {"ranges.tlog", "ranges.tlog.partial"}
    assert partial_path(out).read_bytes() == b"half" and out.read_bytes() == b"old, complete"
    with atomic_open(out, "wb", keep_partial=True) as fh:
        fh.write(b"new")
        assert out.read_bytes() == b"old, complete"  # nothing visible before the end
    assert names(tmp_path) == {"ranges.tlog"} and out.read_bytes() == b"new"  # the stale .partial is gone too


def test_staged_files_appear_together(tmp_path):
    (tmp_path / "summary.png").write_bytes(b"from an earlier run")
    with StagedFiles(tmp_path, keep_partial=("telemetry.tlog",), obsolete=("summary.png",)) as st:
        st.path("telemetry.tlog").write_bytes(b"t")
        st.path("truth.npz").write_bytes(b"n")
        st.path("never_written.csv")
        assert names(tmp_path) - {p.name for p in st._staged.values()} == {"summary.png"}
    assert names(tmp_path) == {"telemetry.tlog", "truth.npz"}
    with pytest.raises(Terminated):
        with StagedFiles(tmp_path, keep_partial=("telemetry.tlog",)) as st:
            st.path("telemetry.tlog").write_bytes(b"t2")
            st.path("truth.npz").write_bytes(b"n2")
            raise Terminated("SIGTERM received")
    assert names(tmp_path) == {"telemetry.tlog", "truth.npz", "telemetry.tlog.partial"}
    assert (tmp_path / "truth.npz").read_bytes() == b"n" and (tmp_path / "telemetry.tlog.partial").read_bytes() == b"t2"


def test_atomic_dir_swaps_a_directory_in(tmp_path):
    report = tmp_path / "report"
    with atomic_dir(report) as d:
        (d / "index.md").write_text("one")
    with pytest.raises(KeyboardInterrupt):
        with atomic_dir(report, keep_partial=True) as d:
            (d / "index.md").write_text("two, unfinished")
            raise KeyboardInterrupt
    assert names(tmp_path) == {"report", "report.partial"} and (report / "index.md").read_text() == "one"
    with atomic_dir(report) as d:
        (d / "index.md").write_text("three")
    assert names(tmp_path) == {"report", "report.partial"} and names(report) == {"index.md"}
    assert (report / "index.md").read_text() == "three"


def test_signals_are_deferred_to_the_end_of_a_commit_and_sigterm_unwinds():
    done = []
    with pytest.raises(KeyboardInterrupt):
        with signals_deferred():
            signal.raise_signal(signal.SIGINT)
            done.append("the block went on")
    assert done == ["the block went on"]
    with pytest.raises(Terminated) as e:
        with raise_on_sigterm():
            signal.raise_signal(signal.SIGTERM)
            time.sleep(1.0)  # pragma: no cover - the handler raises first
    assert interrupt_exit_code(e.value) == 143 and interrupt_exit_code(KeyboardInterrupt()) == 130
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # restored


def test_write_text_atomic_leaves_no_temporary_file(tmp_path):
    write_text_atomic(tmp_path / "sitl.json", "{}\n")
    assert names(tmp_path) == {"sitl.json"}


# ---------------------------------------------------------------------- interrupted processes -----
def _start_then_signal(cmd: list[str], watch: Path, pattern: str, sig: int, after_s: float = 0.3,
                       timeout_s: float = 60.0) -> tuple[int, str]:
    """Run ``cmd``; once a temporary file matching ``pattern`` exists in ``watch`` (its output is
    being written) wait ``after_s`` and send ``sig``; returns (exit code, stderr)."""
    proc = subprocess.Popen(cmd, cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + timeout_s
        while not list(watch.glob(pattern)):
            assert proc.poll() is None, f"finished before it could be interrupted: {proc.communicate()}"
            assert time.monotonic() < deadline, "its output never started"
            time.sleep(0.02)
        time.sleep(after_s)
        assert proc.poll() is None, "finished before it could be interrupted"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
        return proc.returncode, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.fixture(scope="module")
def long_recording(tmp_path_factory):
    """4 s of 320×240 frames: a replay that takes seconds, to be interrupted in the middle."""
    d = tmp_path_factory.mktemp("long")
    cam = CameraConfig.from_fov(320, 240, 60.0)
    write_recording(d, SyntheticFlight(camera=cam, wall_north_m=15.0, velocity_ned=(1.0, 3.0, 0.0)), 4.0, epoch_s=1.7e9)
    return d


@pytest.mark.parametrize("sig, code, says", [(signal.SIGINT, 130, "interrupted (Ctrl-C)"),
                                             (signal.SIGTERM, 143, "terminated (SIGTERM)")])
def test_interrupted_replay_leaves_no_ranges_tlog_only_a_partial(long_recording, tmp_path, sig, code, says):
    """Before: Ctrl-C exited 0 leaving a ranges.tlog that decoded cleanly, cut after part of the flight."""
    rec, out = long_recording, tmp_path / "ranges.tlog"
    cmd = [sys.executable, "-m", "companion", "replay", "--tlog", str(rec / "telemetry.tlog"), "--video",
           str(rec / "video.avi"), "--frames", str(rec / "frames.csv"), "--out", str(out), "--quiet"]
    rc, err = _start_then_signal(cmd, tmp_path, ".ranges.tlog.*.tmp.tlog", sig)
    assert rc == code, err
    assert says in err and "Traceback" not in err
    assert names(tmp_path) == {"ranges.tlog.partial"}  # no ranges.tlog, no plot, no temporary file
    conn = mavutil.mavlink_connection(str(partial_path(out)))
    kinds = set()
    while (m := conn.recv_msg()) is not None:
        kinds.add(m.get_type())
    assert "HEARTBEAT" in kinds  # what was replayed so far, kept under a name that says so


def test_interrupted_fly_leaves_none_of_its_files(tmp_path):
    scen = variant(tmp_path, "quad_approach", {"duration_s": "4.0"})
    out = tmp_path / "out"
    out.mkdir()
    (out / "flight.json").write_text("{}\n")  # a previous flight's file stays as it was
    cmd = [sys.executable, "-m", "flightsim", "fly", str(scen), "--out", str(out), "--no-plot"]
    rc, err = _start_then_signal(cmd, out, ".video.avi.*.tmp.avi", signal.SIGTERM)
    assert rc == 143, err
    assert "terminated (SIGTERM)" in err and "Traceback" not in err
    assert names(out) == {"flight.json"} and (out / "flight.json").read_text() == "{}\n"


# ---------------------------------------------------------------------- an interrupted campaign ---
def sleepy_run(job):
    """Seed 100 fails at once; the others work until they are stopped."""
    if job.seed == 100:
        return {"seed": job.seed, "dir": job.run_dir, "status": "failed", "error": "RuntimeError: planned", "wall_s": 0.0,
                "score": None}
    run_dir = Path(job.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    try:
        (run_dir / "started").write_text("yes")
        time.sleep(120)
    finally:
        (run_dir / "unwound").write_text("yes")  # the SIGTERM from the campaign unwound the run
    return {}  # pragma: no cover


def test_interrupted_campaign_stops_its_workers_and_writes_partial_results(tmp_path):
    """Ctrl-C while seed 101 runs in a worker (seed 100 already failed): the worker is stopped with
    SIGTERM and unwinds, the finished run is pooled into campaign.json.partial and report.partial/,
    and an earlier campaign's results are gone (before: campaign.json of the interrupted run)."""
    from flightsim import campaign as C

    scen = variant(tmp_path, "quad_approach", {"duration_s": "1.0"})
    out = tmp_path / "camp"
    (out / "report").mkdir(parents=True)
    (out / "campaign.json").write_text("{}")  # an earlier campaign's results: its runs are replaced, so they go
    recorded = threading.Event()
    main_thread = threading.main_thread().ident

    def interrupt_when_running():
        deadline = time.monotonic() + 60
        while not ((out / "runs" / "seed_0101" / "started").is_file() and recorded.is_set()):
            if time.monotonic() > deadline:
                return
            time.sleep(0.05)
        signal.pthread_kill(main_thread, signal.SIGINT)  # Ctrl-C reaches the campaign (its workers ignore it)

    watcher = threading.Thread(target=interrupt_when_running, daemon=True)
    watcher.start()
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        C.run_campaign(scen, out, runs=2, workers=2, mode="replay", seed0=100, run_fn=sleepy_run,
                       progress=lambda done, total, failed: recorded.set())
    watcher.join(timeout=5)
    assert time.monotonic() - t0 < 90
    assert names(out) == {"runs", "campaign.json.partial", "report.partial"}
    assert (out / "runs" / "seed_0101" / "unwound").read_text() == "yes"
    part = json.loads((out / "campaign.json.partial").read_text())
    assert part["interrupted"] is True and [r["seed"] for r in part["runs"]] == [100]
    assert (out / "report.partial" / "index.md").is_file()
