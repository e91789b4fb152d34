"""Exceptions shared by the package.

Every module raises a subclass of :class:`CompanionError` so a caller can catch the whole family,
and the message always names the offending input (which key, which array, which index).
"""


class CompanionError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(CompanionError, ValueError):
    """A configuration value or file is invalid (unknown key, wrong type, out of range)."""


class InputError(CompanionError, ValueError):
    """Data handed to an estimator is unusable (NaN, wrong shape, unsorted time, empty frame)."""
