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
