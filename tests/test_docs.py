"""The derivation pages under docs/derivations/ stay reachable and point at real code.

Reads files relative to this test file only (no package import), so it runs from any checkout.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DERIV = ROOT / "docs" / "derivations"
INDEX = DERIV / "README.md"

#: relative Markdown links to .md files, optionally with an #anchor: [text](page.md) or (page.md#x)
_LINK = re.compile(r"\]\(([^)#\s]+\.md)(?:#[^)\s]*)?\)")
#: source paths named in the pages, e.g. `companion/core/sectors.py`
_SOURCE = re.compile(r"\b((?:companion|flightsim|tests)/[\w/]+\.py)\b")


def _pages() -> set[str]:
    return {p.name for p in DERIV.glob("*.md") if p.name != "README.md"}


def _local_links(path: Path) -> set[str]:
    return {m for m in _LINK.findall(path.read_text(encoding="utf-8")) if "://" not in m}


def test_index_exists_and_pages_exist():
    assert INDEX.is_file(), f"missing index {INDEX.relative_to(ROOT)}"
    assert _pages(), "no derivation pages in docs/derivations/"


def test_every_page_is_in_the_index():
    missing = sorted(_pages() - _local_links(INDEX))
    assert not missing, f"docs/derivations/README.md does not link to: {missing}"


def test_every_link_points_at_an_existing_page():
    broken = []
    for page in [INDEX, *sorted(DERIV.glob("*.md"))]:
        for link in _local_links(page):
            if not (page.parent / link).resolve().is_file():
                broken.append(f"{page.name} -> {link}")
    assert not broken, f"links to missing files: {broken}"


def test_source_files_named_in_the_pages_exist():
    missing = []
    for page in sorted(DERIV.glob("*.md")):
        for src in set(_SOURCE.findall(page.read_text(encoding="utf-8"))):
            if not (ROOT / src).is_file():
                missing.append(f"{page.name}: {src}")
    assert not missing, f"pages name source files that do not exist: {missing}"
