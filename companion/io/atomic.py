"""Outputs that appear complete or not at all.

A command that is interrupted (Ctrl-C, SIGTERM, a crash) must not leave a file at an output path
that looks like a finished result: a ``ranges.tlog`` cut after half the flight decodes cleanly and
scores as if the companion had stopped ranging.  So every output is written to a temporary file in
the same directory (hidden, ``.NAME.XXXX.tmp.SUFFIX``: the suffix kept, since OpenCV and
matplotlib pick the format from it) and renamed onto its name with :func:`os.replace` only once it
is complete.  A rename within one directory is atomic: a reader sees the previous file or the new
one, never a part.

On failure the temporary file is removed, or, for outputs whose partial data is worth keeping
(a tlog written as the run goes), renamed to ``NAME.partial``: a name that says what it is.

* :func:`atomic_path` — a temporary path for writers that take a file name (``cv2.VideoWriter``,
  ``savefig``, ``np.savez``);
* :func:`atomic_open`, :func:`write_text_atomic` — a file object, a whole text;
* :class:`StagedFiles` — several files of one run that appear together (:meth:`StagedFiles.commit`
  renames them all, with SIGINT / SIGTERM deferred for those few renames);
* :func:`atomic_dir` — a directory of files (a report) written aside and swapped in;
* :func:`prepare_output_dir` — an output directory, created, or a clear error.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from pathlib import Path
from typing import IO, Iterator

from companion.errors import ConfigError
from companion.interrupts import signals_deferred

PARTIAL_SUFFIX = ".partial"


def prepare_output_dir(path: str | os.PathLike, option: str = "--out") -> Path:
    """The output directory ``path``, created if missing; a ConfigError naming ``option`` if it is a
    file or cannot be created."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{option} {p}: is a file, not a directory")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{option} {p}: cannot create the directory ({exc.strerror or exc})") from None
    return p


def partial_path(path: str | os.PathLike) -> Path:
    """Where the partial data of an interrupted output is kept: ``NAME.partial`` beside it."""
    p = Path(path)
    return p.with_name(p.name + PARTIAL_SUFFIX)


def temp_path(path: str | os.PathLike) -> Path:
    """A hidden name for a temporary file in the directory of ``path`` that keeps its suffix:
    ``.NAME.PID-RANDOM.tmp.SUFFIX`` (nothing is created: the writer creates it, with the usual
    permissions)."""
    p = Path(path)
    return p.with_name(f".{p.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp{p.suffix}")


def _discard(tmp: Path, final: Path, keep_partial: bool) -> None:
    """Remove a temporary file, or keep it as ``final``'s ``.partial`` if it holds anything."""
    try:
        if keep_partial and tmp.is_file() and tmp.stat().st_size > 0:
            os.replace(tmp, partial_path(final))
        else:
            tmp.unlink(missing_ok=True)
    except OSError:  # best effort: never hide the error that brought us here
        pass


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, keep_partial: bool = False) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed onto ``path`` when the block ends
    normally (an older ``path.partial`` is then removed), removed (or kept as ``path.partial`` with
    ``keep_partial``) when it raises — also on Ctrl-C and SIGTERM."""
    final = Path(path)
    tmp = temp_path(final)
    try:
        yield tmp
    except BaseException:
        _discard(tmp, final, keep_partial)
        raise
    with signals_deferred():
        os.replace(tmp, final)
        if keep_partial:
            partial_path(final).unlink(missing_ok=True)  # a previous run's partial data is superseded


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", *, keep_partial: bool = False, **kwargs) -> Iterator[IO]:
    """``open(path, mode)`` through :func:`atomic_path`; the data reach the disk (fsync) before the rename."""
    if not mode.startswith("w"):
        raise ValueError(f"atomic_open writes new files: mode must start with 'w', got {mode!r}")
    with atomic_path(path, keep_partial=keep_partial) as tmp, open(tmp, mode, **kwargs) as fh:
        yield fh
        fh.flush()
        os.fsync(fh.fileno())


def write_text_atomic(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> None:
    """``Path(path).write_text(text)``, atomically."""
    with atomic_open(path, "w", encoding=encoding) as fh:
        fh.write(text)


class StagedFiles:
    """Several output files in one directory that appear together.

    :meth:`path` gives the temporary path to write each final name to; :meth:`commit` renames them
    all onto their names (and removes the ``obsolete`` names a previous run may have left that this
    one did not write), with SIGINT and SIGTERM deferred until the renames are done; :meth:`abort`
    removes them, keeping those named in ``keep_partial`` as ``NAME.partial``.  As a context
    manager it commits when the block ends normally and aborts when it raises.
    """

    def __init__(self, directory: str | os.PathLike, *, keep_partial: tuple[str, ...] = (),
                 obsolete: tuple[str, ...] = ()):
        self.directory = Path(directory)
        self.keep_partial = frozenset(keep_partial)
        self.obsolete = tuple(obsolete)
        self._staged: dict[str, Path] = {}
        self.committed = False

    def path(self, name: str) -> Path:
        """The temporary path of output ``name`` (the same one on every call)."""
        if name not in self._staged:
            self._staged[name] = temp_path(self.directory / name)
        return self._staged[name]

    def final(self, name: str) -> Path:
        return self.directory / name

    def commit(self) -> list[Path]:
        """Rename every staged file that was written onto its name; returns the final paths."""
        done = []
        with signals_deferred():
            for name, tmp in self._staged.items():
                if tmp.is_file():
                    os.replace(tmp, self.final(name))
                    done.append(self.final(name))
                    if name in self.keep_partial:
                        partial_path(self.final(name)).unlink(missing_ok=True)  # superseded
            for name in self.obsolete:
                if self.final(name) not in done:
                    self.final(name).unlink(missing_ok=True)
        self._staged.clear()
        self.committed = True
        return done

    def abort(self) -> None:
        """Remove every staged file (those in ``keep_partial`` kept as ``NAME.partial``)."""
        for name, tmp in self._staged.items():
            _discard(tmp, self.final(name), name in self.keep_partial)
        self._staged.clear()

    def __enter__(self) -> "StagedFiles":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abort()


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, *, keep_partial: bool = False) -> Iterator[Path]:
    """A temporary directory beside ``path`` to fill; swapped in for ``path`` (the old one removed)
    when the block ends normally, removed (or renamed ``path.partial`` with ``keep_partial``) when
    it raises.  The swap is two renames, with SIGINT / SIGTERM deferred between them."""
    final = Path(path)
    tmp = temp_path(final)
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        if keep_partial and any(tmp.iterdir()):
            shutil.rmtree(partial_path(final), ignore_errors=True)
            os.replace(tmp, partial_path(final))
        else:
            shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    with signals_deferred():
        if final.exists():
            old = final.with_name(f".{final.name}.old-{os.getpid()}")
            os.replace(final, old)
        os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


__all__ = ["prepare_output_dir", "atomic_path", "atomic_open", "write_text_atomic", "StagedFiles", "atomic_dir",
           "partial_path", "temp_path", "PARTIAL_SUFFIX"]
