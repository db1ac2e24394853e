"""The clean simulated flights several test folders smooth, each made and smoothed once per
session (the ``clean_flights`` and ``nominal_runs`` fixtures).

A flight is the robustness study's base flight (:data:`cdtm_graph.studies.robustness.BASE`:
the issue's 1800 m, 150 m/s, ~150 features, 1 fps) of ``frames`` frames and ``seed``, with
no fault; a run is that flight smoothed and judged with default settings in a
:class:`~cdtm_graph.studies.robustness.Mode` (``Mode.BATCH`` is ``SmootherSettings()``).
Imported by ``tests/conftest.py`` only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.run import RunOutput, smooth_and_evaluate
from cdtm_graph.sim.simulate import simulate_flight
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, Mode


@dataclasses.dataclass
class CleanFlights:
    """Clean flights and their runs, cached by (seed, frames) and (seed, frames, mode).

    The runs are shared: a test reads them and never changes them.
    """

    flights: dict[tuple[int, int], tuple[FlightLog, Dtm]] = dataclasses.field(
        default_factory=dict)
    runs: dict[tuple[int, int, Mode], RunOutput] = dataclasses.field(default_factory=dict)

    def flight(self, seed: int, frames: int) -> tuple[FlightLog, Dtm]:
        """The clean flight (log, DTM) of ``seed`` and ``frames``."""
        key = (seed, frames)
        if key not in self.flights:
            self.flights[key] = simulate_flight(dataclasses.replace(BASE, frames=frames,
                                                                    seed=seed))
        return self.flights[key]

    def run(self, seed: int, frames: int, mode: Mode = Mode.BATCH) -> RunOutput:
        """The clean flight smoothed and judged in ``mode`` with default settings."""
        key = (seed, frames, mode)
        if key not in self.runs:
            self.runs[key] = smoothed(self.flight(seed, frames), mode)
        return self.runs[key]

    def runs_of(self, seeds: Iterable[int], frames: int,
                mode: Mode = Mode.BATCH) -> list[RunOutput]:
        """:meth:`run` of each seed, in order."""
        return [self.run(seed, frames, mode) for seed in seeds]


@dataclasses.dataclass
class FlightRuns:
    """One flight's runs, one per mode, each made once (``nominal_runs``)."""

    flight: tuple[FlightLog, Dtm]
    runs: dict[Mode, RunOutput] = dataclasses.field(default_factory=dict)

    def run(self, mode: Mode = Mode.BATCH) -> RunOutput:
        """The flight smoothed and judged in ``mode`` with default settings."""
        if mode not in self.runs:
            self.runs[mode] = smoothed(self.flight, mode)
        return self.runs[mode]


def smoothed(flight: tuple[FlightLog, Dtm], mode: Mode) -> RunOutput:
    """``flight`` (log, DTM) smoothed and judged in ``mode`` with default settings
    (``Mode.BATCH``: ``SmootherSettings()``; ``ISAM2``: ``mode=INCREMENTAL``; ``FIXED_LAG``:
    ``lag_s=10``)."""
    return smooth_and_evaluate(*flight, mode.settings(SmootherSettings()))
