"""Shared test helpers and fixtures.

Test modules import the helpers directly (``from conftest import free_port``): pytest puts this
directory on ``sys.path`` (rootdir-relative test modules without ``__init__.py``).
"""

from __future__ import annotations

import socket


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A loopback port that was free a moment ago (UDP by default; ``socket.SOCK_STREAM`` for TCP)."""
    s = socket.socket(socket.AF_INET, kind)
    try:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
    finally:
        s.close()
