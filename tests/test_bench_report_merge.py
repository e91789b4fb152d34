"""`bench all --write` rewrites only its own sections of docs/BENCHMARKS.md (bench/report.py, merge_document)."""

import re

from bench.report import merge_document

OLD = """# Benchmarks

Generated on an old day.

## Seed-004 scenario (DESIGN.md §4)

old seed-004 table

## A hand-run study (issue 15)

hand figures, command: `flightsim campaign …`

```sh
## not a heading: a comment in a fenced block
```

### Its subsection

more hand figures

## Software in the loop

old sitl intro

### Lockstep speed

old lockstep figures

### A hand-run note under a generated section

kept note

### Campaigns

old campaign table

## Closing hand section

last words
"""

NEW = """# Benchmarks

Generated today.

## Seed-004 scenario (DESIGN.md §4)

new seed-004 table

## Software in the loop

new sitl intro

### Lockstep speed

new lockstep figures

### Campaigns

new campaign table

## A new generated section

brand new
"""


def _headings(text):
    text = re.sub(r"```.*?```", "", text, flags=re.S)  # fenced blocks hold no headings
    return [line for line in text.splitlines() if line.startswith("## ") or line.startswith("### ")]


def test_generated_sections_replaced_and_hand_sections_kept_in_place():
    out = merge_document(OLD, NEW)
    for old in ("old seed-004 table", "old sitl intro", "old lockstep figures", "old campaign table", "Generated on an old day"):
        assert old not in out
    for new in ("new seed-004 table", "new sitl intro", "new lockstep figures", "new campaign table", "brand new", "Generated today"):
        assert new in out
    for kept in ("hand figures", "## not a heading: a comment in a fenced block", "more hand figures", "kept note", "last words"):
        assert kept in out
    assert _headings(out) == [
        "## Seed-004 scenario (DESIGN.md §4)",
        "## A hand-run study (issue 15)",
        "### Its subsection",
        "## Software in the loop",
        "### Lockstep speed",
        "### A hand-run note under a generated section",
        "### Campaigns",
        "## Closing hand section",
        "## A new generated section",
    ]


def test_merge_is_idempotent_and_a_missing_document_gets_the_generated_text():
    once = merge_document(OLD, NEW)
    assert merge_document(once, NEW) == once
    assert merge_document("", NEW) == NEW
    norm = lambda s: re.sub(r"\n{2,}", "\n\n", s).strip()  # noqa: E731
    assert norm(merge_document(OLD, OLD)) == norm(OLD)
