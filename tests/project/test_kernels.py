"""What a fresh install compiles: the count of numba kernels (issue 22, "The first run")."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: Functions compiled on their own (``@njit`` without ``inline="always"``) in the package,
#: counted 2026-11-27 after issue 22's cut (38; 52 before it). Each costs ~0.2-3 s of CPU on
#: every fresh install's first run (docs/design.md, "The first run"): a new one is added
#: knowingly (raise this with the reason), one removed lowers it.
KERNEL_BUDGET = 38


def own_kernels() -> list[str]:
    """``module:function`` of every function decorated ``@njit(...)``/``@numba.njit(...)``
    without ``inline="always"`` (an inlined one is compiled inside its callers only)."""
    found = []
    for path in sorted([*(ROOT / "cdtm_graph").rglob("*.py"), *(ROOT / "factors").rglob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.FunctionDef):
                continue
            for decorator in node.decorator_list:
                call = decorator if isinstance(decorator, ast.Call) else None
                target = call.func if call else decorator
                if getattr(target, "attr", getattr(target, "id", "")) != "njit":
                    continue
                inline = any(k.arg == "inline" and isinstance(k.value, ast.Constant)
                             and k.value.value == "always" for k in (call.keywords if call else []))
                if not inline:
                    found.append(f"{path.relative_to(ROOT)}:{node.name}")
    return found


def test_no_more_kernels_compile_on_a_first_run_than_counted():
    """Catches: a kernel added or brought back (``@njit`` on ``tracks._in_sorted`` again)
    or a one-caller helper no longer inlined (``inline="always"`` dropped from
    ``geometry._well_conditioned``), each a second or so more on every fresh install."""
    kernels = own_kernels()
    assert len(kernels) <= KERNEL_BUDGET, "\n".join(kernels)
