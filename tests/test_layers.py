"""The layout's rules, checked on the source: the companion never imports the simulator or the
benchmarks, the pure core does no I/O, and no two modules import each other at load time."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("companion", "flightsim")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def _load_time_imports(path: Path, name: str, known: dict[str, Path]) -> set[str]:
    """Modules of ours imported while ``name`` loads: module-level statements only (not inside
    functions, not under ``if TYPE_CHECKING``), ``from a import b`` counted as ``a.b`` when that is a module."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    is_pkg = path.name == "__init__.py"
    out: set[str] = set()

    def visit(stmts):
        for node in stmts:
            if isinstance(node, ast.If):
                test = ast.unparse(node.test)
                if "TYPE_CHECKING" in test:
                    continue
                visit(node.body)
                visit(node.orelse)
            elif isinstance(node, ast.Try):
                visit(node.body)
                for h in node.handlers:
                    visit(h.body)
                visit(node.orelse)
                visit(node.finalbody)
            elif isinstance(node, ast.Import):
                out.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    pkg = name if is_pkg else name.rpartition(".")[0]
                    for _ in range(node.level - 1):
                        pkg = pkg.rpartition(".")[0]
                    base = f"{pkg}.{base}" if base else pkg
                out.add(base)
                out.update(f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in known)

    visit(tree.body)
    ours = set()
    for m in out:
        while m and m not in known:  # a name inside a module: the module
            m = m.rpartition(".")[0]
        if m and m != name:
            ours.add(m)
    return ours


def _graph() -> dict[str, set[str]]:
    known = _modules()
    # explicit imports only: a submodule's implicit load of its (already loading) parent package is
    # how packages work; a submodule that imports *names* from its package is an edge and counts
    return {name: _load_time_imports(path, name, known) for name, path in known.items()}


def test_the_companion_never_imports_the_simulator_or_the_benchmarks():
    offenders = []
    for pkg_file in sorted((ROOT / "companion").rglob("*.py")):
        tree = ast.parse(pkg_file.read_text(encoding="utf-8"))
        for node in ast.walk(tree):  # anywhere, functions included
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
            offenders += [f"{pkg_file.relative_to(ROOT)}: {n}" for n in names if n.split(".")[0] in ("flightsim", "bench")]
    assert not offenders, offenders


@pytest.mark.parametrize("forbidden", ["companion.io", "companion.mavlink", "companion.camera_sources", "companion.monitor",
                                       "companion.cli", "companion.app", "pymavlink", "socket", "threading", "serial"])
def test_the_core_does_no_io(forbidden):
    """companion/core is pure estimation: no link, camera, files or threads (DEVELOPERS: core vs I/O)."""
    offenders = []
    for p in sorted((ROOT / "companion" / "core").rglob("*.py")):
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
            offenders += [f"{p.relative_to(ROOT)}: {n}" for n in names if n == forbidden or n.startswith(forbidden + ".")]
    assert not offenders, offenders


def test_no_import_cycle_at_load_time():
    g = _graph()
    cycles, state, stack = [], {}, []

    def dfs(u):
        state[u] = 1
        stack.append(u)
        for v in sorted(g.get(u, ())):
            if v not in g:
                continue
            if state.get(v) == 1:
                cycles.append(" → ".join(stack[stack.index(v):] + [v]))
            elif state.get(v) is None:
                dfs(v)
        stack.pop()
        state[u] = 2

    for u in sorted(g):
        if state.get(u) is None:
            dfs(u)
    assert not cycles, "\n".join(cycles[:10])


def test_the_cycle_check_can_fail(tmp_path, monkeypatch):
    """The checker itself: two modules importing each other are reported."""
    pkg = tmp_path / "companion"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from companion import b\n")
    (pkg / "b.py").write_text("import companion.a\n")
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    monkeypatch.setattr(__import__(__name__), "PACKAGES", ("companion",))
    with pytest.raises(AssertionError, match="companion.a → companion.b → companion.a|companion.b → companion.a → companion.b"):
        test_no_import_cycle_at_load_time()
