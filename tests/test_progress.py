"""The one progress bar of every long command (companion/io/progress.py)."""

from __future__ import annotations

import companion.io.progress as progress
from companion.io.progress import ProgressBar


def test_bar_counts_when_on_and_is_silent_when_off(capsys):
    with ProgressBar("work", total=10, enabled=True) as bar:
        assert bar.enabled
        bar.update(3)
        bar.advance(2)
        assert bar._p.tasks[0].completed == 5 and bar._p.tasks[0].total == 10
        bar.update(7, total=20, description="work (1 failed)")
        assert bar._p.tasks[0].total == 20 and bar._p.tasks[0].description == "work (1 failed)"
    assert bar._p is None  # stopped
    with ProgressBar("quiet", total=3, enabled=False) as bar:
        bar.update(1)
        bar.advance()
    assert bar._p is None and capsys.readouterr().err == ""


def test_bar_is_off_without_rich_or_a_terminal(monkeypatch):
    assert not ProgressBar("x").enabled  # pytest's stderr is not a terminal
    monkeypatch.setattr(progress, "rich_available", lambda: False)
    with ProgressBar("x", enabled=True) as bar:  # the onboard install: no rich, no bar, no error
        bar.update(1, 2)
    assert not bar.enabled
