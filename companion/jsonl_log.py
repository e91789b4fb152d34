"""A diagnostic JSON-lines log that never costs a frame: the writer shared by the sector log and the landmark log.

The file is opened line-buffered (a killed process leaves complete lines, at most the last one cut), its
first line is a header.  A file that cannot be opened is a configuration error, named by the command-line
option that asked for it; a write that fails later (disk full, a vanished mount) is logged once and ends
the log, and the companion flies on.  I/O only.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from companion.errors import ConfigError

log = logging.getLogger(__name__)


class JsonlLog:
    """``write(obj)`` appends one JSON line; ``lines`` counts them, ``failed`` says a write failed (and ended the log)."""

    #: what the log is called in messages, and the command-line option that asks for it
    NAME = "log"
    OPTION = "--log"

    def __init__(self, path, header: dict):
        self.path = Path(path)
        self.lines = 0
        self.failed = False
        self._fh = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = open(self.path, "w", encoding="ascii", buffering=1)  # line-buffered: complete lines if killed
            self._fh.write(json.dumps(header) + "\n")
        except OSError as e:
            raise ConfigError(f"{self.OPTION} {path}: cannot write: {e}") from e

    @property
    def open(self) -> bool:
        """True while lines can still be written."""
        return not self.failed and self._fh is not None

    def write(self, obj: dict) -> None:
        if not self.open:
            return
        try:
            self._fh.write(json.dumps(obj) + "\n")
            self.lines += 1
        except (OSError, ValueError) as e:
            self.failed = True
            log.error("%s %s: write failed (%s): no more lines are logged; ranging goes on", self.NAME, self.path, e)
            self.close()

    def close(self) -> None:
        fh, self._fh = self._fh, None
        if fh is not None:
            try:
                fh.close()
            except OSError:
                pass
