"""Typed configuration: one small dataclass per module, filled from a TOML table.

Each module defines a frozen dataclass with validated defaults (``__post_init__`` calls
:func:`require`).  :func:`from_mapping` builds one from a TOML table and rejects unknown keys
and wrong types by name, so a misspelt key stops the program instead of being ignored.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any, Mapping, TypeVar

from companion.errors import ConfigError

T = TypeVar("T")


def require(condition: bool, message: str) -> None:
    """Raise :class:`ConfigError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise ConfigError(message)


def require_finite(name: str, value: float, *, positive: bool = False, nonnegative: bool = False) -> None:
    """Check a scalar config value is a finite number (optionally > 0 or ≥ 0)."""
    require(isinstance(value, (int, float)) and not isinstance(value, bool), f"{name} must be a number, got {value!r}")
    require(math.isfinite(value), f"{name} must be finite, got {value!r}")
    if positive:
        require(value > 0, f"{name} must be > 0, got {value!r}")
    if nonnegative:
        require(value >= 0, f"{name} must be >= 0, got {value!r}")


def require_int(name: str, value: Any, *, minimum: int) -> None:
    """Check a config value is an integer (a bool is not) and at least ``minimum``."""
    require(isinstance(value, int) and not isinstance(value, bool) and value >= minimum,
            f"{name} must be an integer >= {minimum}, got {value!r}")


def _type_ok(value: Any, annotation: Any) -> bool:
    origin = typing.get_origin(annotation)
    if annotation is Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return value is None
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if annotation is str:
        return isinstance(value, str)
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            return False
        args = typing.get_args(annotation)
        if origin is tuple and args and args[-1] is not Ellipsis:
            return len(value) == len(args) and all(_type_ok(v, a) for v, a in zip(value, args))
        inner = args[0] if args else Any
        return all(_type_ok(v, inner) for v in value)
    return True


def _coerce(value: Any, annotation: Any) -> Any:
    """Turn TOML lists into tuples (dataclasses here are frozen and hashable)."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        for a in typing.get_args(annotation):
            if a is not type(None) and _type_ok(value, a):
                return _coerce(value, a)
        return value
    if origin is tuple and isinstance(value, list):
        args = typing.get_args(annotation)
        if args and args[-1] is Ellipsis:
            return tuple(_coerce(v, args[0]) for v in value)
        return tuple(_coerce(v, a) for v, a in zip(value, args))
    if annotation is float and isinstance(value, int):
        return float(value)
    return value


def from_mapping(cls: type[T], mapping: Mapping[str, Any] | None, where: str) -> T:
    """Build dataclass ``cls`` from ``mapping``; ``where`` names the TOML table in errors.

    Unknown keys, wrong types and failed validations raise :class:`ConfigError` naming the key.
    Nested dataclass fields are filled from nested tables.
    """
    mapping = dict(mapping or {})
    label = f"[{where}]" if where else "top level"
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(mapping) - set(fields))
    if unknown:
        raise ConfigError(
            f"{label}: unknown key(s) {', '.join(repr(k) for k in unknown)}; "
            f"known keys: {', '.join(sorted(fields))}"
        )
    kwargs: dict[str, Any] = {}
    for name, value in mapping.items():
        annotation = hints[name]
        if dataclasses.is_dataclass(annotation):
            if not isinstance(value, Mapping):
                raise ConfigError(f"{label} {name} must be a table, got {value!r}")
            kwargs[name] = from_mapping(annotation, value, f"{where}.{name}" if where else name)
            continue
        if not _type_ok(value, annotation):
            raise ConfigError(f"{label} {name} = {value!r} has the wrong type (expected {annotation})")
        kwargs[name] = _coerce(value, annotation)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{label} {exc}") from None
