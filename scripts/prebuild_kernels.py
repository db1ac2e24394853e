"""Compile every numba kernel of the packages for the generic x86-64 target and put them
in ``<package>/_prebuilt/`` (:mod:`factors.jit`), so that a first run loads them.

Run after changing a module that holds a kernel, or what a kernel reads from another
module, or numba (``tests/project/test_kernels.py`` names the stale ones):
``python scripts/prebuild_kernels.py``. It runs the test suite on one worker (every
kernel at every signature the tests call it with; one process, so no two write one
kernel's index at once) in a fresh numba cache with the prebuilt kernels off,
``NUMBA_CPU_NAME=generic``, no other ``NUMBA_*`` setting of yours and Intel's SVML off (a
kernel calling it would not load where it is missing). Then, if every kernel of the
packages was compiled, it replaces each package's ``_prebuilt/`` with the result; if not,
it names the missing ones and replaces nothing. ``--command CMD ...`` runs those shell
commands instead of the suite (what they do not call is then missing). The result is for
this Python (``py311`` in the names) and this numba version (in each index); any other
loads none of them and compiles as before.
"""

from __future__ import annotations

import argparse
import importlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from numba.core.caching import _CacheLocator
from numba.core.dispatcher import Dispatcher

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from factors.jit import COMPILE_ALL, PACKAGES, PREBUILT, prebuilt_dir  # noqa: E402  (the checkout's)


def module_dirs() -> dict[str, Path]:
    """numba's folder name under ``NUMBA_CACHE_DIR`` for each of the packages' folders."""
    found = {}
    for package in PACKAGES:
        for folder in [ROOT / package, *(ROOT / package).rglob("*")]:
            if folder.is_dir() and (folder / "__init__.py").is_file():
                found[_CacheLocator.get_suitable_cache_subpath(str(folder / "x.py"))] = folder
    return found


def own_kernels() -> dict[str, Path]:
    """The index file name each kernel of the packages is cached under (inlined helpers
    aside: compiled inside their callers) -> its module's folder."""
    names = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if "njit" not in path.read_text():
                continue
            module = importlib.import_module(".".join(path.relative_to(ROOT).with_suffix("").parts))
            for value in vars(module).values():
                if (isinstance(value, Dispatcher) and value.__module__ == module.__name__
                        and value.targetoptions.get("inline") != "always"):
                    names[value._cache._impl.filename_base + ".nbi"] = path.parent
    return names


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--command", nargs="+", metavar="CMD",
                        help="shell commands to run instead of the test suite")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="cdtm-prebuild-") as tmp:
        cache = Path(tmp) / "cache"
        env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
        env.update({"NUMBA_CACHE_DIR": str(cache), "NUMBA_CPU_NAME": "generic",
                    "NUMBA_DISABLE_INTEL_SVML": "1", COMPILE_ALL: "1"})
        commands = args.command or [f"{sys.executable} -m pytest -q -p no:cacheprovider -n 0"]
        for command in commands:
            print(f"prebuild: {command}", flush=True)
            done = subprocess.run(command, shell=True, cwd=ROOT, env=env)
            # (a failing test still ran its kernels: the stale-kernel test fails until
            # this build is done; pytest's other codes mean the suite did not run)
            if done.returncode not in (0, 1):
                print(f"prebuild: `{command}` exited {done.returncode}; nothing replaced",
                      file=sys.stderr)
                return 1
        folders = module_dirs()
        staged = Path(tmp) / "staged"
        built: dict[str, Path] = {}
        for subdir in cache.iterdir() if cache.is_dir() else ():
            if subdir.name not in folders:
                continue
            source = folders[subdir.name]
            shipped = prebuilt_dir(source / "__init__.py")  # (where the fallback reads them)
            assert shipped is not None, source
            for path in sorted(subdir.glob("*.nb[ic]")):
                target = staged / shipped.relative_to(ROOT) / path.name
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(path, target)
                if path.suffix == ".nbi":
                    built[path.name] = source
        missing = sorted(set(own_kernels()) - set(built))
        if missing:
            print("prebuild: not compiled by the run (nothing replaced):\n  "
                  + "\n  ".join(missing), file=sys.stderr)
            return 1
        for package in PACKAGES:
            shutil.rmtree(ROOT / package / PREBUILT, ignore_errors=True)
            if (staged / package / PREBUILT).is_dir():
                shutil.copytree(staged / package / PREBUILT, ROOT / package / PREBUILT)
        size = sum(p.stat().st_size for p in staged.rglob("*.nb[ic]"))
    print(f"prebuild: {len(built)} kernels, {size / 1e6:.1f} MB in "
          + ", ".join(f"{p}/{PREBUILT}" for p in PACKAGES))
    return 0


if __name__ == "__main__":
    sys.exit(main())
