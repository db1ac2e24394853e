"""What a fresh install compiles: the count of numba kernels (issue 22, "The first run")."""

from __future__ import annotations

import ast
import hashlib
import importlib
import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from factors.jit import COMPILE_ALL, GENERIC_CPU, PACKAGES, PREBUILT

ROOT = Path(__file__).resolve().parents[2]

#: Functions compiled on their own (``@njit`` without ``inline="always"``) in the package,
#: counted 2026-11-27 after issue 22's cut (38; 52 before it). Each costs ~0.2-3 s of CPU on
#: every fresh install's first run (docs/design.md, "The first run"): a new one is added
#: knowingly (raise this with the reason), one removed lowers it. 39 since 2026-11-28:
#: ``factors.kernel.principal_point_kernel`` (the calibration check's cx, cy; shipped
#: prebuilt, so a first run on x86-64 loads it). 40 since 2026-11-28 (stop 42):
#: ``verdict.window_counts.count_flags`` (the frame flags from counts, the run's verdict's
#: and each live update's: numpy's per-call cost was 0.29 ms an update; prebuilt).
KERNEL_BUDGET = 40


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


# The kernels shipped compiled (factors/jit.py)


def _prebuilt_indices() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package / PREBUILT).rglob("*.nbi"))


def _read_index(path: Path) -> tuple[str, bytes, dict]:
    """numba's index file: its numba version, the source stamp it holds, its entries."""
    with path.open("rb") as f:
        version = pickle.load(f)
        stamp, overloads = pickle.loads(f.read())
    return version, stamp, overloads


def _source_of(index: Path) -> Path:
    """The module an index's kernel is in (``<package>/_prebuilt/<below>/<module>.<kernel>
    -<line>.py311.nbi`` -> ``<package>/<below>/<module>.py``)."""
    package, _prebuilt, *below = index.parent.relative_to(ROOT).parts
    return ROOT.joinpath(package, *below, index.name.split(".", 1)[0] + ".py")


def test_every_prebuilt_kernel_is_of_its_source_as_it_is():
    """Each prebuilt index holds the content hash of its module as it is now, for this numba,
    compiled for the generic CPU only.

    Catches a kernel module changed without ``python scripts/prebuild_kernels.py``
    (mutation tried: a comment added to ``factors/kernel.py``: 7 stale indices named). Not
    a wrong result (numba compiles a stale kernel instead of loading it) but every fresh
    install paying its compilation again. Also a build for the host's CPU, which no other
    machine would load (mutation tried: ``triangularize``'s index keyed on this CPU, as
    a build without ``NUMBA_CPU_NAME`` writes it: named)."""
    import numba

    indices = _prebuilt_indices()
    assert len(indices) >= KERNEL_BUDGET, f"{len(indices)} prebuilt kernels"
    versions = {_read_index(i)[0] for i in indices}
    if versions != {numba.__version__}:
        pytest.skip(f"prebuilt for numba {sorted(versions)}, this is {numba.__version__}")
    stale, specific, mismatched, svml = [], [], [], []
    for index in indices:
        _version, stamp, overloads = _read_index(index)
        if stamp != hashlib.sha256(_source_of(index).read_bytes()).digest():
            stale.append(str(index.relative_to(ROOT)))
        for (signature, (_triple, *cpu), _code), name in overloads.items():
            specific += [] if tuple(cpu) == GENERIC_CPU else [index.name]
            data = (index.parent / name).read_bytes()
            mismatched += [] if pickle.loads(data)[3].args == signature else [name]
            svml += [name] if b"__svml_" in data else []
    assert not stale, "stale (run python scripts/prebuild_kernels.py):\n" + "\n".join(stale)
    assert not specific, specific
    assert not mismatched, mismatched  # (two builders writing one index at once)
    assert not svml, svml  # (Intel's SVML, which a machine without it cannot load)


def test_every_kernel_is_prebuilt_under_the_key_its_code_asks_for():
    """Each kernel of the packages (not inlined) is decorated by :func:`factors.jit.njit`,
    has a prebuilt index, and every entry there is under the key the kernel's dispatcher
    computes for it now (its bytecode's hash, this machine's triple) with the generic CPU.

    Catches a kernel decorated with numba's ``njit`` (mutation tried: ``from numba import
    njit`` back in ``cdtm_graph/robust/gating.py``: named, and no prebuilt fallback), a
    kernel the build missed (mutation tried: ``gating``'s index removed: named) and keys
    that the code would never ask for (mutation tried: a byte of the bytecode hash changed
    in one index: named)."""
    from numba.core.registry import cpu_target

    from factors.jit import _PrebuiltFallback

    if os.environ.get(COMPILE_ALL) == "1":
        pytest.skip(f"{COMPILE_ALL}=1: the prebuilt kernels are off (the build runs so)")
    codegen = cpu_target.target_context.codegen()
    prebuilt = {p.name: p for p in _prebuilt_indices()}
    unfallen, missing, foreign = [], [], []
    for name in own_kernels():
        path, function = name.split(":")
        module = importlib.import_module(".".join(Path(path).with_suffix("").parts))
        dispatcher = getattr(module, function)
        if not isinstance(dispatcher._cache, _PrebuiltFallback):
            unfallen.append(name)
            continue
        index = prebuilt.get(dispatcher._cache._impl.filename_base + ".nbi")
        if index is None:
            missing.append(name)
            continue
        for signature, (triple, *_cpu), code in _read_index(index)[2]:
            wanted_signature, (wanted_triple, *_host), wanted_code = \
                dispatcher._cache._index_key(signature, codegen)
            if (triple, code) != (wanted_triple, wanted_code):
                foreign.append(name)
    assert not unfallen, f"not decorated with factors.jit.njit: {unfallen}"
    assert not missing, f"not prebuilt (python scripts/prebuild_kernels.py): {missing}"
    assert not foreign, foreign


_KERNEL_MODULE = '''
from factors.jit import njit

@njit(cache=True)
def triple(x):
    return 3.0 * x
'''

_CALL = r"""
import json, sys
from pathlib import Path
from numba.core import event
from factors.jit import use_prebuilt

compiled = []

class Listener(event.Listener):
    def on_start(self, ev):
        compiled.append(ev.data["dispatcher"].py_func.__qualname__)
    def on_end(self, ev):
        pass

event.register("numba:compile", Listener())
sys.path.insert(0, str(Path(sys.argv[1]).parent))
import probe as module
if len(sys.argv) > 2:
    use_prebuilt(module.triple, Path(sys.argv[2]))
print(json.dumps({"value": module.triple(2.0), "compiled": compiled}))
"""


@pytest.mark.slow  # compiles a kernel three times in subprocesses (5 s)
def test_a_generic_kernel_loads_here_while_its_source_is_unchanged(tmp_path):
    """A kernel compiled for the generic CPU (another numba cache, as the build does) loads
    through the fallback on this machine's CPU without compiling; once its module is
    edited, it is compiled and the new code runs.

    Catches the fallback asking for the host's key (nothing would ever load; mutation
    tried: ``GENERIC_CPU`` in place of the host's dropped from ``_load_overload``), a
    damaged prebuilt file failing the run instead of being compiled (mutation tried: the
    ``try`` around the prebuilt load removed: the run ends in an unpickling error) and a
    stale kernel loaded (mutation tried: the prebuilt index read with its own stamp in
    place of the module's: ``triple`` returns 6.0 after the edit to ``4.0 * x``)."""
    module = tmp_path / "probe.py"
    module.write_text(_KERNEL_MODULE)
    base = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CPU_NAME", COMPILE_ALL)}

    def call(cache: str, *extra: str, **env: str) -> dict:
        done = subprocess.run([sys.executable, "-c", _CALL, str(module), *extra],
                              env={**base, "NUMBA_CACHE_DIR": str(tmp_path / cache), **env},
                              cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        return json.loads(done.stdout.strip().splitlines()[-1])

    built = call("build", NUMBA_CPU_NAME="generic")
    assert built == {"value": 6.0, "compiled": ["triple"]}
    shipped = next((tmp_path / "build").iterdir())  # numba's folder for the module's
    assert call("user", str(shipped)) == {"value": 6.0, "compiled": []}
    damaged = tmp_path / "damaged"
    shutil.copytree(shipped, damaged)
    for data in damaged.glob("*.nbc"):
        data.write_bytes(data.read_bytes()[:100])
    assert call("damaged-user", str(damaged)) == {"value": 6.0, "compiled": ["triple"]}

    module.write_text(_KERNEL_MODULE.replace("3.0 * x", "4.0 * x"))
    assert call("new-user", str(shipped)) == {"value": 8.0, "compiled": ["triple"]}
