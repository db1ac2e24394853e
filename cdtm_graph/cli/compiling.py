"""The first run after an install compiles the numerical kernels (numba; a minute or so,
cached for every later run): say so on stderr, once, with what it cost.

Only where a person watches (stderr a terminal) and not with ``--quiet``: a log file or a
test's captured stderr gets no such line. Numba is not imported for it: the listener is
registered when the command itself loads numba (at once if it is loaded already), so a
command that fails on its options, or never computes, pays nothing.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.util
import sys
import time
from collections.abc import Callable, Iterator
from types import ModuleType
from typing import Any, TextIO


class _Counter:
    """What compiled inside the block: how many kernels, how long (s)."""

    def __init__(self, command: str, stream: TextIO):
        self.command, self.stream = command, stream
        self.compiled = 0
        self.depth = 0
        self.started = 0.0
        self.spent_s = 0.0

    def start(self) -> None:
        if self.compiled == 0:
            print(f"{self.command}: compiling the numerical kernels (once after an install: "
                  "cached for every later run) ...", file=self.stream, flush=True)
        self.compiled += 1
        if self.depth == 0:
            self.started = time.perf_counter()
        self.depth += 1

    def end(self) -> None:
        self.depth = max(self.depth - 1, 0)
        if self.depth == 0:
            self.spent_s += time.perf_counter() - self.started


#: The numba module whose listeners see compilations.
_EVENTS = "numba.core.event"


class _WhenImported(importlib.abc.MetaPathFinder):
    """Calls ``then(module)`` once the module ``name`` has been imported (a one-shot
    finder first in ``sys.meta_path``: the module's own loader runs, then ``then``)."""

    def __init__(self, name: str, then: Callable[[ModuleType], None]):
        self.name, self.then = name, then

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        if fullname != self.name:
            return None
        self.remove()
        spec = importlib.util.find_spec(fullname)
        if spec is None or spec.loader is None:
            return spec
        loader, then = spec.loader, self.then
        execute = loader.exec_module

        def exec_module(module: ModuleType) -> None:
            execute(module)
            then(module)

        loader.exec_module = exec_module  # type: ignore[method-assign]
        return spec

    def remove(self) -> None:
        if self in sys.meta_path:
            sys.meta_path.remove(self)


@contextlib.contextmanager
def announced(command: str, quiet: bool = False,
              stream: TextIO | None = None) -> Iterator[_Counter | None]:
    """Within the block, compilations are announced on ``stream`` (stderr), if it is a
    terminal and not ``quiet``; at its end, one line with their count and time."""
    stream = sys.stderr if stream is None else stream
    if quiet or not stream.isatty():
        yield None
        return
    counter = _Counter(command, stream)
    registered: list[tuple[Any, Any]] = []

    def register(event: Any) -> None:
        class Listener(event.Listener):  # a compilation's start and end (not a cache load)
            def on_start(self, ev: Any) -> None:
                counter.start()

            def on_end(self, ev: Any) -> None:
                counter.end()

        listener = Listener()
        event.register("numba:compile", listener)
        registered.append((event, listener))

    hook = None
    if _EVENTS in sys.modules:
        register(sys.modules[_EVENTS])
    else:  # (only a command that computes pays for numba: when it imports it)
        hook = _WhenImported(_EVENTS, register)
        sys.meta_path.insert(0, hook)
    try:
        yield counter
    finally:
        if hook is not None:
            hook.remove()
        for event, listener in registered:
            event.unregister("numba:compile", listener)
        if counter.compiled:
            print(f"{command}: compiled {counter.compiled} kernels in {counter.spent_s:.0f} s "
                  "(cached now)", file=stream, flush=True)
