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
from typing import NamedTuple

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.run import RunOutput, smooth_and_evaluate
from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight
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


class GrossOutliers(NamedTuple):
    """A flight with 2% of its observations moved 15-25 px (:func:`gross_outliers`)."""

    clean: FlightLog
    corrupted: FlightLog
    bad: np.ndarray  # (N,) bool: the moved rows of ``clean.tracks``
    dtm: Dtm


def gross_outliers() -> GrossOutliers:
    """The innovation gate test's flight: 30 frames, 80 features, 2% of the observations
    moved 15-25 px in a random direction. Its literal seeds are the point (the gate test's
    measured counts, and the IMU walk check's bias steps bent by these outliers)."""
    flight, dtm = simulate_flight(SimulationSettings(frames=30, n_features=80, seed=6))
    rng = np.random.default_rng(8)
    uv = flight.tracks.uv_px.copy()
    bad = rng.random(len(uv)) < 0.02
    angle = rng.uniform(0, 2 * np.pi, int(bad.sum()))
    shift = rng.uniform(15, 25, angle.size)[:, None] * np.c_[np.cos(angle), np.sin(angle)]
    uv[bad] = np.clip(uv[bad] + shift, 0, 399)
    corrupted = dataclasses.replace(flight, tracks=dataclasses.replace(flight.tracks, uv_px=uv))
    return GrossOutliers(flight, corrupted, bad, dtm)
