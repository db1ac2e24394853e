"""Compile every numba kernel of the packages for the generic x86-64 target and put them
in ``<package>/_prebuilt/`` (:mod:`factors.jit`), so that a first run loads them.

Run after changing a module that holds a kernel (``tests/project/test_prebuilt_kernels.py``
names the stale ones): ``python scripts/prebuild_kernels.py``. It runs the test suite
(every kernel at every signature the tests call it with) in a fresh numba cache with the
prebuilt kernels off and ``NUMBA_CPU_NAME=generic``, then replaces each package's
``_prebuilt/`` with what was compiled. ``--command CMD ...`` runs that instead of the suite
(each a shell command; the kernels they compile are added). The result is for this
Python (``py311`` in the names) and this numba version (in each index); any other loads
none of them and compiles as before.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from numba.core.caching import _CacheLocator

from factors.jit import COMPILE_ALL, PACKAGES, PREBUILT

ROOT = Path(__file__).resolve().parents[1]


def module_dirs() -> dict[str, Path]:
    """numba's folder name under ``NUMBA_CACHE_DIR`` for each of the packages' folders."""
    found = {}
    for package in PACKAGES:
        for folder in [ROOT / package, *(ROOT / package).rglob("*")]:
            if folder.is_dir() and (folder / "__init__.py").is_file():
                found[_CacheLocator.get_suitable_cache_subpath(str(folder / "x.py"))] = folder
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--command", nargs="+", metavar="CMD",
                        help="shell commands to run instead of the test suite")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="cdtm-prebuild-") as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "NUMBA_CPU_NAME": "generic",
               COMPILE_ALL: "1"}
        env.pop("NUMBA_CPU_FEATURES", None)
        commands = args.command or [f"{sys.executable} -m pytest -q -p no:cacheprovider"]
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
        compiled = [p for p in Path(cache).iterdir() if p.name in folders]
        for package in PACKAGES:
            shutil.rmtree(ROOT / package / PREBUILT, ignore_errors=True)
        count = size = 0
        for subdir in compiled:
            source = folders[subdir.name]
            package, *below = source.relative_to(ROOT).parts
            target = ROOT.joinpath(package, PREBUILT, *below)
            target.mkdir(parents=True, exist_ok=True)
            for path in sorted(subdir.glob("*.nb[ic]")):
                shutil.copyfile(path, target / path.name)
                count += path.suffix == ".nbi"
                size += path.stat().st_size
    print(f"prebuild: {count} kernels, {size / 1e6:.1f} MB in "
          + ", ".join(f"{p}/{PREBUILT}" for p in PACKAGES))
    return 0


if __name__ == "__main__":
    sys.exit(main())
