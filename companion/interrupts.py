"""Interrupted commands: SIGTERM unwinds like Ctrl-C, and a few steps are not cut in the middle.

A command that writes outputs (``companion replay``, every ``flightsim`` command) runs inside
:func:`raise_on_sigterm`: SIGTERM then raises :class:`~companion.errors.Terminated` in the main
thread, as SIGINT raises :class:`KeyboardInterrupt`, so every ``finally`` on the way out runs
(temporary outputs removed or kept as ``*.partial``, :mod:`companion.io.atomic`; child processes
stopped) and the command line exits with :func:`interrupt_exit_code` (130 or 143).

``companion run`` and ``companion monitor`` install their own handlers: for them a signal is the
normal way to stop (exit 0).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

from companion.errors import EXIT_INTERRUPTED, EXIT_TERMINATED, Terminated

_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _raise_terminated(signum, _frame) -> None:
    raise Terminated(f"{signal.Signals(signum).name} received")


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def raise_on_sigterm() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` while the block runs (the previous handler afterwards).
    Outside the main thread, where no handler can be installed, it does nothing."""
    if not _in_main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM arriving inside the block take effect when it ends (raised again then,
    with the handlers from before): a commit of several renames is either done or not started.
    Outside the main thread it does nothing."""
    if not _in_main_thread():
        yield
        return
    pending: list[int] = []
    old = {s: signal.signal(s, lambda signum, _frame: pending.append(signum)) for s in _STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
        if pending:
            signal.raise_signal(pending[0])


def interrupt_exit_code(exc: BaseException) -> int | None:
    """130 for Ctrl-C (:class:`KeyboardInterrupt`), 143 for SIGTERM (:class:`Terminated`), else None."""
    if isinstance(exc, Terminated):
        return EXIT_TERMINATED
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    return None


def interrupt_name(exc: BaseException) -> str:
    """How the command line names the interruption: "interrupted (Ctrl-C)" or "terminated (SIGTERM)"."""
    return "terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted (Ctrl-C)"


__all__ = ["raise_on_sigterm", "signals_deferred", "interrupt_exit_code", "interrupt_name"]


def interrupt_in(exc: BaseException) -> BaseException | None:
    """The Ctrl-C / SIGTERM hidden inside ``exc``, if any (else None).

    A signal whose handler raises while a C extension has control (a compiled kernel, OpenCV)
    surfaces as a ``SystemError`` ("returned a result with an exception set") caused by the
    :class:`KeyboardInterrupt` or :class:`~companion.errors.Terminated`; an ``except Exception``
    that treats it as a bug would swallow the signal.  Such blocks re-raise what this returns.
    """
    seen = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if not isinstance(e, Exception):
            return e
        e = e.__cause__ or e.__context__
    return None
