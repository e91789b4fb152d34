"""One progress bar for every long-running command (replay, fly, sitl, campaign, the benchmarks).

A bar is drawn on stderr with ``rich`` when stderr is a terminal and rich is installed (the ``sim``
and ``gcs`` extras bring it; the onboard install does not), and is silent otherwise, so logs and
pipes stay clean and a missing extra never stops a command.  Use it as a context manager::

    with ProgressBar("replay", total=n) as bar:
        for i in ...:
            bar.update(done=i + 1)            # or bar.advance(1); total may also come with update()
"""

from __future__ import annotations

import importlib.util
import sys


def installed(module: str) -> bool:
    """True when ``module`` can be imported: the optional extras (rich, matplotlib, jsbsim) are not on
    the onboard install."""
    return importlib.util.find_spec(module) is not None


def rich_available() -> bool:
    """True when the optional ``rich`` package can be imported."""
    return installed("rich")


class ProgressBar:
    """A transient (or kept, ``transient=False``) bar labelled ``label``; ``enabled=None`` means: on
    a terminal with rich installed.  ``elapsed`` adds the elapsed time column.  Every method is a
    no-op when the bar is off."""

    def __init__(self, label: str, total: float | None = None, *, enabled: bool | None = None,
                 transient: bool = True, elapsed: bool = False):
        self.label = label
        self.total = total
        self.enabled = (sys.stderr.isatty() if enabled is None else enabled) and rich_available()
        self.transient = transient
        self.elapsed = elapsed
        self._p = None
        self._task = None

    def __enter__(self) -> "ProgressBar":
        if self.enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            cols = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn()]
            cols += [TimeElapsedColumn()] if self.elapsed else []
            self._p = Progress(*cols, TimeRemainingColumn(), transient=self.transient)
            self._p.start()
            self._task = self._p.add_task(self.label, total=self.total)
        return self

    def update(self, done: float | None = None, total: float | None = None, description: str | None = None) -> None:
        """Set the count done (and the total or the label, when given)."""
        if self._p is None:
            return
        kw = {k: v for k, v in (("completed", done), ("total", total), ("description", description)) if v is not None}
        self._p.update(self._task, **kw)

    def advance(self, n: float = 1) -> None:
        """Count ``n`` more done."""
        if self._p is not None:
            self._p.advance(self._task, n)

    def __exit__(self, *exc) -> bool:
        if self._p is not None:
            self._p.stop()
            self._p = None
        return False
