"""The companion as a child process of the simulator: its command line (:func:`companion_command`),
start, log, CPU time and stop (:class:`CompanionProcess`), and its resident set (:func:`companion_rss_kib`).
"""

from __future__ import annotations

import logging
import math
import os
import shlex
import signal
import subprocess
import sys
from pathlib import Path

from companion.core import jit
from flightsim.sitl.config import SitlError

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------- the companion process ---
class CompanionProcess:
    """``python -m companion run …`` as a child process with its output in a log file.

    On Linux the child is sent SIGTERM if the thread that started it ends (PR_SET_PDEATHSIG), so a
    killed simulator leaves no orphan: start runs from a thread that outlives them (e.g. a
    process's main thread, as the campaign workers do).
    """

    def __init__(self, cmd: list[str], log_path: Path):
        self.cmd = cmd
        self.log_path = log_path
        self._log = log_path.open("wb")
        # One thread per library: the simulator needs the other core, and OpenBLAS / OpenCV worker
        # threads on these small matrices and images only spin against it (same results, less CPU).
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        for var in _SINGLE_THREAD_ENV:
            env.setdefault(var, "1")
        self._cpu0 = cpu_seconds(children=True)
        self.cpu_s: float | None = None  # user + system CPU of the companion, s (after stop)
        try:
            self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                         env=env, start_new_session=True,  # Ctrl-C reaches us; we stop it cleanly
                                         preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
        except OSError as exc:
            self._log.close()
            raise SitlError(f"cannot start the companion ({shlex.join(cmd[:4])} …): {exc}") from None
        self.exit_code: int | None = None
        self.killed = False

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def tail(self, lines: int = 12) -> str:
        try:
            self._log.flush()
            text = self.log_path.read_text(errors="replace").rstrip().splitlines()
        except OSError:
            return ""
        return "\n".join("    " + ln for ln in text[-lines:])

    def compiling(self) -> bool:
        """True while the companion's log says it is compiling its kernels (started, not ready)."""
        try:
            self._log.flush()
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return False
        return jit.WARMUP_STARTED in text and jit.WARMUP_DONE not in text

    def failure(self, what: str) -> SitlError:
        tail = self.tail()
        return SitlError(f"{what}; see {self.log_path}" + (f" — last lines:\n{tail}" if tail else ""))

    def stop(self, timeout: float) -> int:
        """SIGTERM, wait ``timeout`` s, then SIGKILL; returns the exit code (negative = killed by a signal)."""
        if self.proc.poll() is None:
            try:
                self.proc.send_signal(signal.SIGTERM)
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                log.warning("companion (pid %d) did not stop within %.0f s of SIGTERM: killing it", self.proc.pid, timeout)
                self.killed = True
                self.proc.kill()
                self.proc.wait()
            except ProcessLookupError:
                pass
        self.exit_code = self.proc.returncode
        self.cpu_s = cpu_seconds(children=True) - self._cpu0  # the only child waited for in between
        self._log.close()
        return self.exit_code

_SINGLE_THREAD_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENCV_FOR_THREADS_NUM")


def cpu_seconds(children: bool = False) -> float:
    """User + system CPU seconds of this process (all its threads), or of its waited-for children."""
    try:
        import resource

        r = resource.getrusage(resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime
    except (ImportError, OSError):  # pragma: no cover - not POSIX
        return math.nan


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Linux: SIGTERM the companion if the simulator dies without stopping it (no orphans on CI)."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:
        pass


def companion_command(mavlink_port: int, camera_port: int, camera_config: Path, *, lockstep: bool, processing_ms: float,
                      companion_config: Path | None, python: str = sys.executable, sector_log: Path | None = None,
                      landmark_log: Path | None = None) -> list[str]:
    """The ``companion run`` command line that talks to this simulator (``sector_log``: where the
    companion writes its sector log, :mod:`companion.sector_log`, which the score reads; ``landmark_log``: its
    landmark log, :mod:`companion.landmark_log`, when asked for)."""
    cmd = [python, "-m", "companion", "run", "--mavlink", f"udpout:127.0.0.1:{mavlink_port}",
           "--camera", f"sim://127.0.0.1:{camera_port}", "--camera-config", str(camera_config)]
    if companion_config is not None:
        cmd += ["--config", str(companion_config)]
    if sector_log is not None:
        cmd += ["--sector-log", str(sector_log)]
    if landmark_log is not None:
        cmd += ["--landmark-log", str(landmark_log)]
    if lockstep:
        cmd += ["--clock", "sim", "--sim-processing-ms", f"{processing_ms:g}"]
    return cmd


def companion_rss_kib(pid: int) -> int | None:
    """Resident set of process ``pid`` (Linux ``/proc/PID/status`` VmRSS), kiB; None if unavailable."""
    try:
        with open(f"/proc/{int(pid)}/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def process_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a running process ``pid`` so far (Linux ``/proc/PID/stat``
    utime + stime, all its threads); None if unavailable.  Read at the start and the end of the
    flight loop it gives the companion's CPU over the loop alone (without its start-up)."""
    try:
        with open(f"/proc/{int(pid)}/stat", encoding="ascii", errors="replace") as fh:
            text = fh.read()
        fields = text[text.rindex(")") + 2:].split()  # after "pid (comm) ": state is field 3
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None
