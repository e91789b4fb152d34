"""Shared test helpers and fixtures.

Test modules import the helpers directly (``from conftest import free_port``): pytest puts this
directory on ``sys.path`` (rootdir-relative test modules without ``__init__.py``).
"""

from __future__ import annotations

import signal
import socket


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A loopback port that was free a moment ago (UDP by default; ``socket.SOCK_STREAM`` for TCP)."""
    s = socket.socket(socket.AF_INET, kind)
    try:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
    finally:
        s.close()


# A shell that starts the test run in the background without job control (CI runners, `cmd &` in a
# script) makes SIGINT ignored, and an ignored signal stays ignored in every child process: the
# Ctrl-C tests (`companion replay` / `monitor` / campaigns interrupted) would then test nothing. The
# tests run with Python's own Ctrl-C handler, whatever started them; children get the default.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


# ---- configurations for tests of one mechanism in isolation ------------------------------------
# The modules' dataclass defaults are the shipped configuration (configs/companion.toml), with the
# optional rules and error models it turns on.  A test of one mechanism starts from one of these and
# switches on, by name, what it exercises.

class FullDisk:
    """A file whose every write fails as on a full disk: what a diagnostic log must survive without costing a frame."""

    def write(self, _):
        raise OSError(28, "No space left on device")

    def close(self):
        pass


def sectors_optional_rules_off(**changes):
    """``[sectors]`` as shipped with its optional rules switched off: narrow-gap and vertical-span
    inference, the cap above the band, the bound from unconverged points, the ground margin and the far part of the
    corridor (the same-range gap rule, ``infer_max_gap_sectors``, stays as shipped).  ``changes`` are applied on top."""
    import dataclasses

    from companion.core.sectors import SectorConfig

    off = dict(infer_narrow_gap_m=0.0, infer_vertical=False, infer_vertical_one_side=False, cap_above_m=0.0,
               ground_margin_m=0.0, unconverged_cap_k=0.0, corridor_far_ratio=0.0)
    return dataclasses.replace(SectorConfig(), **{**off, **changes})


def ekf_for_exact_telemetry(**changes):
    """``[ekf_anchored]`` as shipped without the telemetry error models (no gyro-bias states, no
    position noise), for synthetic flights whose telemetry is exact: a filter that models errors the
    flight does not have is rightly under-confident (NEES below its band).  ``changes`` on top."""
    import dataclasses

    from companion.core.ekf_anchored import AnchoredEKFConfig

    return dataclasses.replace(AnchoredEKFConfig(), **{"attitude_drift_deg_s": 0.0, "position_sigma_m": 0.0, **changes})
