"""Compiled kernels: numba when it is installed, the pure-numpy reference otherwise (docs/derivations/compute.md).

The estimation core is written twice where numpy's per-call overhead dominates (many small
arrays per frame): a pure-numpy *reference* — the readable form the derivations describe and the
tests compare against — and a loop *kernel* compiled by numba, which does the same arithmetic
per landmark without allocating.  Which one runs is decided once per process:

* ``COMPANION_KERNELS=numpy`` in the environment forces the reference everywhere (for debugging,
  or on a platform whose numba misbehaves);
* otherwise the kernels run when ``numba`` imports, and the reference when it does not.

Kernels agree with the reference to float rounding (the tests bound the difference), not bit for
bit: two runs with the same kernels are deterministic, a run with kernels and one without are not
byte-identical.  Kernels are compiled on first use and cached on disk (``cache=True``; numba
writes next to the module or to ``NUMBA_CACHE_DIR``), so only the first start after an install
pays the compile time; :func:`warm_up` compiles every registered kernel ahead of the first frame.

This module holds no state a caller can change: the choice is read from the environment at
import and reported by :func:`describe` (``companion --version``, ``companion check``).
"""

from __future__ import annotations

import os
from typing import Callable

_ENV = "COMPANION_KERNELS"

try:  # numba is a dependency of the companion; tolerate its absence (reference path)
    import numba as _numba
except Exception:  # ImportError, or a broken llvmlite on an odd platform
    _numba = None

_FORCED_NUMPY = os.environ.get(_ENV, "").strip().lower() == "numpy"

#: True when compiled kernels are in use in this process.
ENABLED: bool = _numba is not None and not _FORCED_NUMPY

_WARMUPS: list[Callable[[], None]] = []


def njit(*args, **kwargs):
    """``numba.njit(cache=True, nogil=True, ...)`` when kernels are enabled, else the undecorated function.

    Used as ``@njit`` or ``@njit(fastmath=False)``.  Without numba the function is returned as is
    (it still runs, as slow Python loops): callers dispatch on :data:`ENABLED` and use the numpy
    reference instead, so the undecorated loops only run in tests that call them on tiny inputs.
    """
    opts = {"cache": True, "nogil": True}
    opts.update(kwargs)

    def deco(fn):
        if not ENABLED:
            return fn
        return _numba.njit(**opts)(fn)

    if len(args) == 1 and callable(args[0]) and not kwargs:
        return deco(args[0])
    return deco


def register_warmup(fn: Callable[[], None]) -> Callable[[], None]:
    """Register a no-argument function that calls a module's kernels once on tiny inputs (compiles them)."""
    _WARMUPS.append(fn)
    return fn


#: Log lines of ``companion run`` around :func:`warm_up`: a supervisor (the simulator's SITL harness)
#: that sees the first without the second knows the companion is compiling, not hung.
WARMUP_STARTED = "loading the compiled kernels"
WARMUP_DONE = "kernels ready in"


def warm_up() -> int:
    """Compile (or load from the disk cache) every registered kernel now; returns how many warm-ups ran."""
    if not ENABLED:
        return 0
    for fn in _WARMUPS:
        fn()
    return len(_WARMUPS)


def describe() -> str:
    """One line for ``--version`` and ``companion check``: which kernels this process uses."""
    if ENABLED:
        return f"compiled kernels: numba {_numba.__version__}"
    if _numba is not None:
        return f"compiled kernels: off ({_ENV}=numpy), numpy reference"
    return "compiled kernels: off (numba not installed), numpy reference"
