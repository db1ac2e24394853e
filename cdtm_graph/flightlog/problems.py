"""One-line problem reports of the flight-log readers: ``<file>:<line>: <what>; expected <what>``
(``<path>: <what>; expected <what>`` for a path that is missing or of the wrong kind).

When a file has several problems, the one on the earliest line is reported.
"""

from __future__ import annotations

from typing import NoReturn

import numpy as np

from cdtm_graph.errors import FlightLogError


def _fail(file: str, line: int, what: str, expected: str) -> NoReturn:
    raise FlightLogError(_one_line(f"{file}:{line}: {what}; expected {expected}"))


def _fail_path(path: str, what: str, expected: str) -> NoReturn:
    """A problem with a path itself (missing, a folder where a file belongs): no line."""
    raise FlightLogError(_one_line(f"{path}: {what}; expected {expected}"))


def _one_line(text: str) -> str:
    return " ".join(text.split("\n"))


def _show(token: str, limit: int = 40) -> str:
    """A token as it appears in a message: quoted, one line, truncated."""
    text = repr(token)
    return text if len(text) <= limit else text[: limit - 4] + "...'"


def _first(mask: np.ndarray) -> int | None:
    hits = np.flatnonzero(mask)
    return int(hits[0]) if hits.size else None


class _Problems:
    """Collects the first failing row of each check; reports the earliest in the file."""

    def __init__(self, file: str, first_line: int):
        self.file = file
        self.first_line = first_line
        self.found: list[tuple[int, int, str, str]] = []

    def add(self, row: int | None, what: str, expected: str) -> None:
        if row is not None:
            self.found.append((row, len(self.found), what, expected))

    def check(self, mask: np.ndarray, describe, expected: str) -> None:
        """Add the first row where ``mask`` is True, described by ``describe(row)``."""
        row = _first(mask)
        if row is not None:
            self.add(row, describe(row), expected)

    def raise_first(self) -> None:
        if self.found:
            row, _, what, expected = min(self.found)
            _fail(self.file, self.first_line + row, what, expected)


