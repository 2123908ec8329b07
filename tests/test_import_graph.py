"""The package's import graph is acyclic (issue 22): every module-level ``import`` between
softcrawl modules, read with ``ast`` (imports inside functions are deferred on purpose and not
counted; ``if TYPE_CHECKING:`` blocks neither)."""

from __future__ import annotations

import ast
from pathlib import Path

import softcrawl

ROOT = Path(softcrawl.__file__).parent


def _modules() -> dict[str, Path]:
    mods = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        mods[name] = path
    return mods


def _top_level_imports(node) -> list:
    """Import statements executed at import time (module and class bodies, if/try blocks)."""
    out = []
    for stmt in node.body if hasattr(node, "body") else []:
        if isinstance(stmt, (ast.Import, ast.ImportFrom)):
            out.append(stmt)
        elif isinstance(stmt, ast.If):
            test = ast.unparse(stmt.test)
            if "TYPE_CHECKING" not in test:
                out += _top_level_imports(stmt)
            out += _top_level_imports(ast.Module(body=stmt.orelse, type_ignores=[]))
        elif isinstance(stmt, (ast.Try, ast.ClassDef, ast.With)):
            out += _top_level_imports(stmt)
            for h in getattr(stmt, "handlers", []):
                out += _top_level_imports(h)
            for extra in ("orelse", "finalbody"):
                out += _top_level_imports(ast.Module(body=getattr(stmt, extra, []), type_ignores=[]))
    return out


def import_graph(deferred: bool = False) -> dict[str, set[str]]:
    """``module -> softcrawl modules it imports at import time`` (with ``deferred``, also the
    imports inside functions); edges to a module's own parent packages, which Python imports
    implicitly, are left out."""
    mods = _modules()
    graph = {}
    for name, path in mods.items():
        is_pkg = path.name == "__init__.py"
        deps = set()
        tree = ast.parse(path.read_text(encoding="utf-8"))
        stmts = ([n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))] if deferred
                 else _top_level_imports(tree))
        for stmt in stmts:
            if isinstance(stmt, ast.Import):
                targets = [a.name for a in stmt.names]
            else:
                base = stmt.module or ""
                if stmt.level:
                    pkg = name.split(".") if is_pkg else name.split(".")[:-1]
                    pkg = pkg[:len(pkg) - (stmt.level - 1)]
                    base = ".".join(pkg + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in stmt.names]
            for t in targets:
                while t and t not in mods:
                    t = t.rpartition(".")[0]
                if t and t != name and not name.startswith(t + "."):
                    deps.add(t)
        graph[name] = deps
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a module list (first == last), or None."""
    state, stack = {}, []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state:
                found = visit(m)
                if found:
                    return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


def test_cycle_finder_finds_cycles():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_graph_sees_the_codesign_modules():
    g = import_graph()
    assert "softcrawl.codesign.run" in g["softcrawl.codesign.training"]
    assert "softcrawl.codesign.factory" in g["softcrawl.codesign.training"]


def test_package_import_graph_is_acyclic():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def _reach(g, start):
    seen, todo = set(), [start]
    while todo:
        for m in g.get(todo.pop(), ()):
            if m not in seen:
                seen.add(m)
                todo.append(m)
    return seen


def test_codesign_has_no_cycle_even_through_deferred_imports():
    """Issue 22's cycle (training -> report -> evaluation -> training) ran through imports
    inside functions; counting those too, no codesign module reaches itself."""
    g = import_graph(deferred=True)
    for name in g:
        if name.startswith("softcrawl.codesign"):
            assert name not in _reach(g, name), f"{name} imports itself through {sorted(_reach(g, name) & set(g))}"


def test_run_folder_consumers_do_not_import_training():
    """Evaluation and the report read runs through codesign.run / codesign.factory (issue 22):
    neither imports the training driver, and training does not import the report, at any
    depth and counting imports inside functions."""
    g = import_graph(deferred=True)
    assert "softcrawl.codesign.training" not in _reach(g, "softcrawl.codesign.evaluation")
    assert "softcrawl.codesign.training" not in _reach(g, "softcrawl.codesign.report")
    assert "softcrawl.codesign.report" not in _reach(g, "softcrawl.codesign.training")
    assert "softcrawl.codesign.run" in g["softcrawl.codesign.evaluation"]
