"""The first run after an install compiles the numerical kernels (numba; a minute or so,
cached for every later run): say so on stderr, once, with what it cost.

Only where a person watches (stderr a terminal) and not with ``--quiet``: a log file or a
test's captured stderr gets no such line.
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Iterator
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


@contextlib.contextmanager
def announced(command: str, quiet: bool = False,
              stream: TextIO | None = None) -> Iterator[_Counter | None]:
    """Within the block, compilations are announced on ``stream`` (stderr), if it is a
    terminal and not ``quiet``; at its end, one line with their count and time."""
    stream = sys.stderr if stream is None else stream
    if quiet or not stream.isatty():
        yield None
        return
    from numba.core import event  # (only a command that computes pays for numba here)

    counter = _Counter(command, stream)

    class Listener(event.Listener):  # a compilation's start and end (not a cache load)
        def on_start(self, ev: Any) -> None:
            counter.start()

        def on_end(self, ev: Any) -> None:
            counter.end()

    listener = Listener()
    event.register("numba:compile", listener)
    try:
        yield counter
    finally:
        event.unregister("numba:compile", listener)
        if counter.compiled:
            print(f"{command}: compiled {counter.compiled} kernels in {counter.spent_s:.0f} s "
                  "(cached now)", file=stream, flush=True)
