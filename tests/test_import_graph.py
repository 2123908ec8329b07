"""The package's import graph is acyclic and layered.

Every ``import`` between softcrawl modules is read with ``ast``. Importing ``a.b.c`` also runs
``a/__init__.py`` and ``a/b/__init__.py``; those implicit edges to the target's parent
packages are counted too (edges to a module's *own* parent packages are not: Python has run
them before the module). ``if TYPE_CHECKING:`` blocks are not imports.

* Import-time graph (module and class bodies, if/try/with blocks): acyclic, no exception.
* With the imports inside functions (deferred) counted as well: acyclic, no exception.
* No module imports another package's private (``_name``) symbol.
* Layers the package docstrings promise: :mod:`softcrawl.gaits` imports nothing of the
  simulator; the reduction core imports no robot code and the robot imports only the reduction
  core (the build pipeline sits above the robot: :mod:`softcrawl.reduction`); evaluation and
  the report do not import the training driver, nor training the report.
"""

from __future__ import annotations

import ast
import sys
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
    imports inside functions), including the parent packages of each target (which Python
    imports implicitly); edges to a module's own parent packages are left out."""
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
                while t:  # the target and, run implicitly before it, its parent packages
                    if t in mods and t != name and not name.startswith(t + "."):
                        deps.add(t)
                    t = t.rpartition(".")[0]
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


def test_graph_counts_the_parent_packages_a_target_runs():
    """``from softcrawl.gaits.pressure import X`` runs ``softcrawl/gaits/__init__.py`` too."""
    g = import_graph()
    assert {"softcrawl.gaits.pressure", "softcrawl.gaits"} <= g["softcrawl.robot.actuation"]
    assert "softcrawl.reduction" in g["softcrawl.robot.assembly"]  # via softcrawl.reduction.model
    assert "softcrawl.robot" not in g["softcrawl.robot.sweep"]  # its own package: already run
    assert find_cycle({"a.x": {"b.y"}, "b": {"a.z"}, "b.y": set(), "a": set(), "a.z": set()}) is None


def test_deferred_imports_close_no_cycle():
    """Counting imports inside functions too, the graph is acyclic (no exception list): a lazy
    lookup (the env backends' factory) names its modules by string instead of importing them."""
    cycle = find_cycle(import_graph(deferred=True))
    assert cycle is None, "import cycle through deferred imports: " + " -> ".join(cycle)


def test_backend_factory_imports_no_backend():
    """The env backends' factory imports only the interface; its registry's modules exist and
    name their backend classes."""
    import importlib

    from softcrawl.envs.backends.factory import BACKENDS

    g = import_graph(deferred=True)
    assert g["softcrawl.envs.backends.factory"] == {"softcrawl.envs.backends.base"}
    for target, _ in BACKENDS.values():
        module, _, name = target.partition(":")
        assert isinstance(getattr(importlib.import_module(module), name), type)


def _package(module: str, mods: dict[str, Path]) -> str:
    """The package a module belongs to (a package's ``__init__``: the package itself)."""
    return module if mods[module].name == "__init__.py" else module.rpartition(".")[0]


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_imports_across_packages() -> list[str]:
    """``"importer: target.name"`` for every ``from target import _name`` (or import of a
    private module) of a softcrawl module whose package is not the importer's (``ast``, imports
    inside functions included; dunders such as ``__version__`` are public)."""
    mods = _modules()
    found = []
    for name, path in mods.items():
        own = _package(name, mods)
        for stmt in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(stmt, ast.ImportFrom):
                base = stmt.module or ""
                if stmt.level:
                    pkg = own.split(".")
                    base = ".".join(pkg[:len(pkg) - (stmt.level - 1)] + ([base] if base else []))
                pairs = [(base, a.name) for a in stmt.names]
            elif isinstance(stmt, ast.Import):
                pairs = [tuple(a.name.rsplit(".", 1)) for a in stmt.names if "." in a.name]
            else:
                continue
            for target, sym in pairs:
                if not target.startswith("softcrawl") or not (_private(sym) or any(map(_private, target.split(".")))):
                    continue
                module = f"{target}.{sym}" if f"{target}.{sym}" in mods else target
                while module not in mods:
                    module = module.rpartition(".")[0]
                if _package(module, mods) != own:
                    found.append(f"{name}: {target}.{sym}")
    return found


def test_no_module_imports_another_packages_private_name():
    found = private_imports_across_packages()
    assert not found, "private names imported across packages: " + ", ".join(found)


def test_private_import_check_sees_the_import_forms(tmp_path, monkeypatch):
    """The checker catches a private name imported from another package (plain, relative and
    inside a function, and a private module), and lets a package's own modules share theirs."""
    pkg = tmp_path / "softcrawl"
    for sub in ("a", "b"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("__version__ = '0'\n")
    (pkg / "a" / "x.py").write_text("_hidden = 1\n")
    (pkg / "a" / "_impl.py").write_text("")
    (pkg / "a" / "y.py").write_text("from softcrawl.a.x import _hidden\nfrom softcrawl import __version__\n")
    (pkg / "b" / "z.py").write_text("from ..a.x import _hidden\ndef f():\n    from softcrawl.a.x import _hidden\n"
                                    "import softcrawl.a._impl\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", pkg)
    assert sorted(private_imports_across_packages()) == [
        "softcrawl.b.z: softcrawl.a._impl", "softcrawl.b.z: softcrawl.a.x._hidden", "softcrawl.b.z: softcrawl.a.x._hidden"]


def test_batched_stepping_uses_only_public_solver_members():
    """The batched stepper and the compiled constraint stage drive each robot's
    :class:`~softcrawl.reduction.solver.ReducedSolver` through its public phases: they read no
    ``_private`` attribute of any object but their own (``self``)."""
    for module in ("softcrawl.reduction.batch", "softcrawl.reduction.constrain", "softcrawl.envs.backends.batched"):
        tree = ast.parse(_modules()[module].read_text(encoding="utf-8"))
        private = sorted({f"{ast.unparse(n.value)}.{n.attr}" for n in ast.walk(tree)
                          if isinstance(n, ast.Attribute) and _private(n.attr) and ast.unparse(n.value) != "self"})
        assert not private, f"{module} reads {private}"


def _reach(g, start):
    seen, todo = set(), [start]
    while todo:
        for m in g.get(todo.pop(), ()):
            if m not in seen:
                seen.add(m)
                todo.append(m)
    return seen


def test_run_folder_consumers_do_not_import_training():
    """Evaluation and the report read runs through codesign.run / codesign.factory: neither
    imports the training driver, and training does not import the report, at any depth and
    counting imports inside functions."""
    g = import_graph(deferred=True)
    assert "softcrawl.codesign.training" not in _reach(g, "softcrawl.codesign.evaluation")
    assert "softcrawl.codesign.training" not in _reach(g, "softcrawl.codesign.report")
    assert "softcrawl.codesign.report" not in _reach(g, "softcrawl.codesign.training")
    assert "softcrawl.codesign.run" in g["softcrawl.codesign.evaluation"]


_SIMULATOR = ("softcrawl.robot", "softcrawl.envs", "softcrawl.fem", "softcrawl.reduction", "softcrawl.codesign",
              "softcrawl.hardware")


def _in(mod: str, packages) -> bool:
    return any(mod == p or mod.startswith(p + ".") for p in packages)


def test_gaits_import_nothing_of_the_simulator():
    """The gaits sit below the simulator: their command range is ``softcrawl.gaits.pressure``,
    not the robot package."""
    g = import_graph(deferred=True)
    for m in g:
        if _in(m, ["softcrawl.gaits"]):
            up = sorted(d for d in _reach(g, m) if _in(d, _SIMULATOR))
            assert not up, f"{m} imports {up}"


#: The reduction's build pipeline (snapshot scenes, their runs, the build and the validation):
#: it drives whole robots, so it sits above :mod:`softcrawl.robot` (softcrawl.reduction's docstring).
REDUCTION_PIPELINE = {"softcrawl.reduction.animations", "softcrawl.reduction.scenes", "softcrawl.reduction.runs",
                      "softcrawl.reduction.build", "softcrawl.reduction.validate"}


def test_reduction_pipeline_is_the_only_arrow_up_to_the_robot():
    """The reduction core imports no robot code; the robot imports only the core (never the
    pipeline), at any depth and counting deferred imports, so ``reduction -> robot`` closes no cycle."""
    g = import_graph(deferred=True)
    reduction = {m for m in g if _in(m, ["softcrawl.reduction"])}
    assert REDUCTION_PIPELINE <= reduction
    for m in sorted(reduction - REDUCTION_PIPELINE):
        up = sorted(d for d in _reach(g, m) if _in(d, ["softcrawl.robot", "softcrawl.envs", "softcrawl.codesign"]))
        assert not up, f"reduction core module {m} imports {up}"
    for m in sorted(x for x in g if _in(x, ["softcrawl.robot"])):
        pipeline = sorted(_reach(g, m) & REDUCTION_PIPELINE)
        assert not pipeline, f"{m} imports the reduction's build pipeline {pipeline}"
