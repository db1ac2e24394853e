"""The package's numba kernels, shipped compiled: a first run loads them instead of
compiling them (25-40 s of CPU before this, against a 3-4 s warm run).

Every kernel of ``factors`` and ``cdtm_graph`` is decorated with :func:`njit` from here
(numba's, with ``cache=True``). Its cache is numba's own (``__pycache__`` beside the
source, or ``NUMBA_CACHE_DIR``) with one fallback: on a miss, the kernel is read from
``<package>/_prebuilt/`` (the same layout below the package's root), where
``scripts/prebuild_kernels.py`` put it. Only then does numba compile.

Why it is sound on any machine:
- The prebuilt kernels are compiled for the generic x86-64 target (``NUMBA_CPU_NAME=
  generic``: no instruction beyond the baseline), which every x86-64 CPU runs; numba keys
  a cached kernel on the CPU it was compiled for, so the fallback asks for the generic
  key in place of the host's.
- numba still checks everything else: the source file's content hash (a kernel edited
  since the build is compiled, not loaded), the bytecode's hash, the signature, the
  Python version (in the file name) and numba's version (in the index). Like numba's own
  cache, it does not see a global a kernel reads from another module (a constant of
  :mod:`cdtm_graph.constants` changed needs the kernels rebuilt).

What it does not do: write anything, or fail a run. A kernel numba compiles goes to
numba's own cache; the prebuilt files are only read, and one that cannot be read is
compiled instead. ``CDTM_COMPILE_KERNELS=1`` turns the fallback off (the build script runs
so, to compile every kernel afresh).
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
from numba.core.caching import FunctionCache, IndexDataCacheFile, _cache_log
from numba.core.dispatcher import Dispatcher

#: The folder of a package's prebuilt kernels, below the package's root.
PREBUILT = "_prebuilt"

#: The CPU the prebuilt kernels are compiled for (numba's name, and its feature list).
GENERIC_CPU = ("generic", "")

#: The environment variable that turns the prebuilt kernels off (``1``).
COMPILE_ALL = "CDTM_COMPILE_KERNELS"

#: The packages whose kernels ship prebuilt (the directory that holds them: the checkout's
#: root, or site-packages).
_TOP = Path(__file__).resolve().parent.parent
PACKAGES = ("cdtm_graph", "factors")


def prebuilt_dir(source: Path) -> Path | None:
    """Where the prebuilt kernels of the module at ``source`` are: ``<package>/_prebuilt/``
    then the module's folder below the package (None: not a module of ours)."""
    try:
        parts = source.resolve().parent.relative_to(_TOP).parts
    except ValueError:
        return None
    if not parts or parts[0] not in PACKAGES:
        return None
    return _TOP.joinpath(parts[0], PREBUILT, *parts[1:])


class _PrebuiltFallback(FunctionCache):
    """numba's cache of a function, then, on a miss, its prebuilt generic kernel."""

    def __init__(self, py_func: Callable[..., Any], shipped: Path):
        super().__init__(py_func)
        self._shipped = IndexDataCacheFile(cache_path=str(shipped),
                                           filename_base=self._impl.filename_base,
                                           source_stamp=self._cache_file._source_stamp)

    def _load_overload(self, sig: Any, target_context: Any) -> Any:
        data = super()._load_overload(sig, target_context)
        if data is not None or not self._enabled:
            return data
        try:
            signature, (triple, *_host_cpu), code = self._index_key(
                sig, target_context.codegen())
            shipped = self._shipped.load((signature, (triple, *GENERIC_CPU), code))
            return None if shipped is None else self._impl.rebuild(target_context, shipped)
        except Exception as error:  # (a damaged file, another numba: compiled, as without)
            _cache_log("[cache] prebuilt kernel not loaded: %r", error)
            return None


def use_prebuilt(dispatcher: Any, shipped: Path) -> None:
    """Give the numba ``dispatcher`` numba's cache with the fallback on ``shipped`` (numba's
    cache alone if the fallback cannot be made: a numba whose cache differs)."""
    try:
        dispatcher._cache = _PrebuiltFallback(dispatcher.py_func, shipped)
    except Exception as error:
        _cache_log("[cache] no prebuilt kernels: %r", error)
        dispatcher.enable_caching()


def njit(*args: Any, **options: Any) -> Any:
    """``numba.njit(**options)``; with ``cache=True`` the kernel's cache falls back on its
    prebuilt copy. Used as ``@njit(cache=True, ...)``, like numba's (no signature: the
    kernels are compiled for the types they are called with)."""

    def decorate(py_func: Callable[..., Any]) -> Any:
        dispatcher = numba.njit(**{**options, "cache": False})(py_func)
        if not isinstance(dispatcher, Dispatcher):  # NUMBA_DISABLE_JIT: the function itself
            return dispatcher
        if options.get("cache"):
            shipped = prebuilt_dir(Path(inspect.getfile(py_func)))
            if shipped is None or not shipped.is_dir() or os.environ.get(COMPILE_ALL) == "1":
                dispatcher.enable_caching()
            else:
                use_prebuilt(dispatcher, shipped)
        return dispatcher

    if args and callable(args[0]):
        return decorate(args[0])
    if args:
        raise TypeError("factors.jit.njit takes no signature: the kernels are compiled for "
                        "the types they are called with, the prebuilt ones at the build's")
    return decorate
