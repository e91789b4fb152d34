"""Input files checked before they are parsed: one clear error naming the file and what is wrong.

Every reader of a file the user names (configurations, calibrations, scenarios, tlogs, videos,
``frames.csv``, ``truth.npz``) starts here, so a missing file, a directory, an empty or unreadable
file or bytes that are not text stop with a :class:`~companion.errors.ConfigError` (or the
reader's own subclass of it) — exit code 2 with one line — instead of a traceback from deep inside
a parser.
"""

from __future__ import annotations

import os
from pathlib import Path

from companion.errors import ConfigError


def check_input_file(path: str | os.PathLike, what: str = "file", *, allow_empty: bool = False,
                     error: type[ConfigError] = ConfigError) -> Path:
    """``path`` as a :class:`Path` if it is an existing regular file (non-empty unless
    ``allow_empty``); else ``error`` saying "PATH: no such WHAT", "is a directory, not a WHAT",
    "WHAT is empty" or why it cannot be read."""
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise error(f"{p}: no such {what}") from None
    except OSError as exc:
        raise error(f"{p}: cannot be read ({exc.strerror or exc})") from None
    if p.is_dir():
        raise error(f"{p}: is a directory, not a {what}")
    if not p.is_file():
        raise error(f"{p}: is not a regular file (a {what} is expected)")
    if st.st_size == 0 and not allow_empty:
        raise error(f"{p}: the {what} is empty")
    return p


def read_input_bytes(path: str | os.PathLike, what: str = "file", *, allow_empty: bool = False,
                     error: type[ConfigError] = ConfigError) -> bytes:
    """The bytes of an input file (:func:`check_input_file`, then read; an OS error becomes ``error``)."""
    p = check_input_file(path, what, allow_empty=allow_empty, error=error)
    try:
        return p.read_bytes()
    except OSError as exc:
        raise error(f"{p}: cannot be read ({exc.strerror or exc})") from None


def decode_text(data: bytes, path: str | os.PathLike, what: str = "file",
                error: type[ConfigError] = ConfigError) -> str:
    """UTF-8 text of an input file's bytes; bytes that are not UTF-8 become ``error`` naming where."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise error(f"{path}: not a {what}: byte 0x{data[exc.start]:02x} on line {line} is not UTF-8 text") from None


def read_input_text(path: str | os.PathLike, what: str = "file", *, allow_empty: bool = False,
                    error: type[ConfigError] = ConfigError) -> str:
    """The UTF-8 text of an input file (:func:`read_input_bytes` + :func:`decode_text`)."""
    data = read_input_bytes(path, what, allow_empty=allow_empty, error=error)
    return decode_text(data, path, what, error)


__all__ = ["check_input_file", "read_input_bytes", "decode_text", "read_input_text"]
