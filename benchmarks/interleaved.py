"""Run times of smoother variants side by side, for the benchmarks that compare them."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.results import SmootherResult
from cdtm_graph.smoother import SmootherSettings, smooth


@dataclass
class Timings:
    """Each variant's run times (s) and its last result."""

    times_s: dict[str, list[float]] = field(default_factory=dict)
    last: dict[str, SmootherResult] = field(default_factory=dict)


def interleaved(flight: FlightLog, dtm: Dtm, runs: dict[str, SmootherSettings],
                repeats: int) -> Timings:
    """Smooth the log with every variant in turn, ``repeats`` times: interleaved, so the
    machine's drift hits every variant alike."""
    out = Timings({name: [] for name in runs})
    for _ in range(repeats):
        for name, settings in runs.items():
            start = time.perf_counter()
            out.last[name] = smooth(flight, dtm, settings)
            out.times_s[name].append(time.perf_counter() - start)
    return out
