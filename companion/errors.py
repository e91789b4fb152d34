"""Exceptions shared by the package, and the exit codes the command lines map them to.

Every module raises a subclass of :class:`CompanionError` so a caller can catch the whole family,
and the message always names the offending input (which key, which array, which index).

Exit codes (``companion`` and ``flightsim``): :data:`EXIT_OK` done, :data:`EXIT_RUNTIME` a failure
at run time (:class:`CompanionError`), :data:`EXIT_USAGE` bad arguments, configuration or input
files (:class:`ConfigError`: the message names the file and what is wrong with it),
:data:`EXIT_INTERRUPTED` Ctrl-C (SIGINT, :class:`KeyboardInterrupt`) and :data:`EXIT_TERMINATED`
SIGTERM (:class:`Terminated`, see :mod:`companion.interrupts`) while writing outputs: 128 + the
signal's number, as a shell reports a process the signal killed.
"""

EXIT_OK = 0
EXIT_RUNTIME = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT
EXIT_TERMINATED = 143  # 128 + SIGTERM


class CompanionError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(CompanionError, ValueError):
    """A configuration value or file is invalid (unknown key, wrong type, out of range), or an input
    file cannot be used (missing, a directory, unreadable, empty, not the format it should be)."""


class InputError(CompanionError, ValueError):
    """Data handed to an estimator is unusable (NaN, wrong shape, unsorted time, empty frame)."""


class Terminated(BaseException):
    """SIGTERM arrived (:func:`companion.interrupts.raise_on_sigterm`).

    A :class:`BaseException`, like :class:`KeyboardInterrupt`, so that ``except Exception`` blocks
    let it through and the stack unwinds through every ``finally`` (temporary outputs removed,
    child processes stopped) to the command line, which exits with :data:`EXIT_TERMINATED`.
    """
