"""The package's layout: seams, wings, no cycles, sizes.

The estimator core (everything in ``cdtm_graph`` outside ``sim``, ``studies``, ``cli`` and
``plots``, plus ``factors``) must not import the simulation and study harness, the CLI
or the plots; ``factors`` must not import ``cdtm_graph`` at all. Checked twice: on the
source (every import statement, including those inside functions) and by importing the
core in a fresh interpreter and listing what it loaded. The wings that keep bad data out
(``robust``) and judge a run (``verdict``) never import the smoothers; results never do.
No import cycle among the package's modules, imports inside functions counted (and the
package ``__init__`` every import of a submodule runs), ``TYPE_CHECKING`` blocks aside.
At most 18 modules directly in ``cdtm_graph/``; no class over 400 lines. README's layout
section, the map a newcomer reads, is checked to name every module and subpackage once.
"""

from __future__ import annotations

import ast
import functools
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "cdtm_graph"
#: Subpackages the core may not reach into.
HARNESS = ("cdtm_graph.sim", "cdtm_graph.studies", "cdtm_graph.cli", "cdtm_graph.plots")


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _core_files() -> list[Path]:
    files = sorted(PACKAGE.rglob("*.py")) + sorted((ROOT / "factors").rglob("*.py"))
    # __main__ is the entry point of ``python -m cdtm_graph``: a leaf like the CLI it calls
    return [f for f in files if not _reaches(_module_name(f), HARNESS + ("cdtm_graph.__main__",))]


def _imported_modules(path: Path, type_checking: bool = True) -> set[str]:
    """Every module name an import statement of ``path`` names (and, for ``from X import
    Y``, both ``X`` and ``X.Y``); with ``type_checking=False``, not those under ``if
    TYPE_CHECKING:``."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    tree = _parsed(path)
    skipped: set[int] = set()
    if not type_checking:
        for node in ast.walk(tree):
            if isinstance(node, ast.If) and getattr(node.test, "id", "") == "TYPE_CHECKING":
                skipped.update(id(sub) for sub in ast.walk(node))
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


@functools.cache
def _parsed(path: Path) -> ast.Module:
    """The module's syntax tree, parsed once per session (the checks below walk every
    module several times: parsing them each time cost ~8 s of the suite)."""
    return ast.parse(path.read_text(), str(path))


def _reaches(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


@pytest.mark.parametrize("path", _core_files(), ids=lambda p: _module_name(p))
def test_core_module_imports_no_harness(path):
    prefixes = ("cdtm_graph",) if _module_name(path).startswith("factors") else HARNESS
    bad = sorted(m for m in _imported_modules(path) if _reaches(m, prefixes))
    assert not bad, f"{_module_name(path)} imports {bad}"


def test_the_check_sees_a_violation(tmp_path, monkeypatch):
    """An import hidden in a function, or relative, is found (so the check can fail)."""
    probe = tmp_path / "cdtm_graph" / "probe.py"
    probe.parent.mkdir()
    probe.write_text("def f():\n    from cdtm_graph.sim.simulate import simulate\n"
                     "    from .plots import trajectory\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    found = _imported_modules(probe)
    assert _reaches("cdtm_graph.sim.simulate", HARNESS) and "cdtm_graph.sim.simulate" in found
    assert "cdtm_graph.plots.trajectory" in found


@pytest.mark.slow
def test_importing_the_core_loads_no_harness():
    core = ["cdtm_graph.smoother", "cdtm_graph.flightlog", "cdtm_graph.dtm", "factors",
            "cdtm_graph.outputs", "cdtm_graph.run", "cdtm_graph.verdict.evaluation",
            "cdtm_graph.analysis.two_frame", "cdtm_graph.analysis.accuracy_map"]
    code = ("import sys\n" + "".join(f"import {m}\n" for m in core)
            + "print('\\n'.join(m for m in sys.modules if m.startswith('cdtm_graph')))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True, cwd=ROOT).stdout.split()
    assert "cdtm_graph.smoother" in loaded  # the listing works
    assert not [m for m in loaded if _reaches(m, HARNESS)]


def test_readme_layout_lists_every_module_once():
    """README's layout section names each module and subpackage of cdtm_graph, and each
    module of its wings, exactly once."""
    readme = (ROOT / "README.md").read_text()
    section = readme.split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]
    block = section.split("```\n", 2)[1]
    entries = sorted(f"{p.stem}.py" for p in PACKAGE.glob("*.py")
                     if p.stem not in ("__init__", "__main__"))
    entries += sorted(f"{p.name}/" for p in PACKAGE.iterdir() if (p / "__init__.py").exists())
    # the wings' and the graph's and run's modules too: where each defence lives
    for wing in ("robust", "calibration", "verdict", "graph", "run"):
        entries += sorted(f"{p.stem}.py" for p in (PACKAGE / wing).glob("*.py")
                          if p.stem != "__init__")
    assert len(entries) > 45  # the listing works
    counts = {e: len(re.findall(rf"(?<![\w/.]){re.escape(e)}(?!\w)", block)) for e in entries}
    assert {e: n for e, n in counts.items() if n != 1} == {}


def _modules() -> dict[str, Path]:
    files = sorted(PACKAGE.rglob("*.py")) + sorted((ROOT / "factors").rglob("*.py"))
    return {_module_name(f): f for f in files}


def _import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the package modules it imports at run time (inside functions too): the
    deepest module each import names, and the packages above it whose ``__init__`` the
    import runs (not the importer's own)."""
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        own = {".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 2)}
        edges: set[str] = set()
        for imported in _imported_modules(path, type_checking=False):
            target = imported
            while target and target not in modules:
                target = target.rpartition(".")[0]
            parts = target.split(".")
            for i in range(1, len(parts) + 1):
                ancestor = ".".join(parts[:i])
                if ancestor in modules and ancestor not in own:
                    edges.add(ancestor)
        graph[name] = edges - {name}
    return graph


@functools.cache
def _package_graph() -> dict[str, set[str]]:
    """The package's own import graph, built once per session (read, never changed)."""
    return _import_graph(_modules())


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle():
    """No import cycle among the package's modules, counting imports inside functions."""
    graph = _package_graph()
    assert len(graph) > 100 and sum(map(len, graph.values())) > 300  # the graph is read
    assert _cycles(graph) == []


def test_the_cycle_check_sees_a_cycle(tmp_path, monkeypatch):
    """A cycle through an import inside a function, and one through a package's
    ``__init__``, are found; one under ``TYPE_CHECKING`` is not (so the check can fail, and
    does not cry wolf)."""
    pkg = tmp_path / "cdtm_graph"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from cdtm_graph import b\n")
    (pkg / "b.py").write_text("import cdtm_graph.a\n")
    (pkg / "sub" / "__init__.py").write_text("from cdtm_graph.sub.c import x\n")
    (pkg / "sub" / "c.py").write_text("x = 1\n")
    (pkg / "d.py").write_text("import cdtm_graph.sub.c\n")
    (pkg / "sub" / "e.py").write_text("from cdtm_graph import d\n")
    (pkg / "sub" / "c.py").write_text("from cdtm_graph.sub import e\nx = 1\n")
    (pkg / "g.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                              "    from cdtm_graph import h\n")
    (pkg / "h.py").write_text("from cdtm_graph import g\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    modules = {_module_name(f): f for f in sorted(pkg.rglob("*.py"))}
    cycles = _cycles(_import_graph(modules))
    assert ["cdtm_graph.a", "cdtm_graph.b"] in cycles
    assert any("cdtm_graph.d" in c and "cdtm_graph.sub" in c for c in cycles)
    assert not any("cdtm_graph.g" in c for c in cycles)


#: The wings that must not depend on how a run is solved.
SOLVER_FREE = ("cdtm_graph.robust", "cdtm_graph.verdict", "cdtm_graph.results")


@pytest.mark.parametrize("prefix", SOLVER_FREE)
def test_wings_never_import_the_smoothers(prefix):
    """The defences and the verdict judge what a solver gives them; they never import it
    (nor ``run``, which does)."""
    graph = _package_graph()
    bad = {m: sorted(e for e in edges if _reaches(e, ("cdtm_graph.smoother", "cdtm_graph.run")))
           for m, edges in graph.items() if _reaches(m, (prefix,))}
    assert any(_reaches(m, (prefix,)) for m in graph)
    assert {m: e for m, e in bad.items() if e} == {}


def test_at_most_18_modules_in_the_package_root():
    modules = sorted(p.name for p in PACKAGE.glob("*.py") if p.stem not in ("__init__",
                                                                           "__main__"))
    assert 10 < len(modules) <= 18, modules


def test_no_class_over_400_lines():
    """A class that outgrows 400 lines does several things: split it."""
    long = {}
    for name, path in _modules().items():
        for node in ast.walk(_parsed(path)):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > 400:
                long[f"{name}.{node.name}"] = node.end_lineno - node.lineno + 1
    assert long == {}
