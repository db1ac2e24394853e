"""The seam between the estimator and the harness around it.

The estimator core (everything in ``cdtm_graph`` outside ``sim``, ``studies``, ``cli`` and
``plots``, plus ``factors``) must not import the simulation and study harness, the CLI
or the plots; ``factors`` must not import ``cdtm_graph`` at all. Checked twice: on the
source (every import statement, including those inside functions) and by importing the
core in a fresh interpreter and listing what it loaded. README's layout section, the map a
newcomer reads, is checked to name every module and subpackage once.
"""

from __future__ import annotations

import ast
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


def _imported_modules(path: Path) -> set[str]:
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
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
            "cdtm_graph.outputs", "cdtm_graph.run", "cdtm_graph.evaluation",
            "cdtm_graph.analysis.two_frame", "cdtm_graph.analysis.accuracy_map"]
    code = ("import sys\n" + "".join(f"import {m}\n" for m in core)
            + "print('\\n'.join(m for m in sys.modules if m.startswith('cdtm_graph')))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True, cwd=ROOT).stdout.split()
    assert "cdtm_graph.smoother" in loaded  # the listing works
    assert not [m for m in loaded if _reaches(m, HARNESS)]


def test_readme_layout_lists_every_module_once():
    """README's layout section names each module and subpackage of cdtm_graph exactly once."""
    readme = (ROOT / "README.md").read_text()
    section = readme.split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]
    block = section.split("```\n", 2)[1]
    entries = sorted(f"{p.stem}.py" for p in PACKAGE.glob("*.py")
                     if p.stem not in ("__init__", "__main__"))
    entries += sorted(f"{p.name}/" for p in PACKAGE.iterdir() if (p / "__init__.py").exists())
    assert len(entries) > 30  # the listing works
    counts = {e: len(re.findall(rf"(?<![\w/.]){re.escape(e)}(?!\w)", block)) for e in entries}
    assert {e: n for e, n in counts.items() if n != 1} == {}
