"""Flight logs in the ``cdtm-flightlog/1`` format (docs/flightlog.md): model, readers, writer.

A flight log is a directory: ``flight.yaml`` (camera, IMU, DTM, initial state),
``imu.csv``, ``frames.csv`` and optionally ``tracks.csv``, ``nav.csv``,
``groundtruth.csv``. The CSV files follow the EuRoC/ASL column order, so EuRoC
files can be copied in as they are.

- :mod:`~cdtm_graph.flightlog.model`: the dataclasses (plain numpy, no GTSAM types).
- :mod:`~cdtm_graph.flightlog.tables` and :mod:`~cdtm_graph.flightlog.config`: the CSV
  and flight.yaml parsers; :mod:`~cdtm_graph.flightlog.reader` reads a whole directory.
- :mod:`~cdtm_graph.flightlog.writer`: writes one, bit-exact on the round trip.
- :mod:`~cdtm_graph.flightlog.names`: the file names (light: the command line's help).

Every problem in a log raises :class:`~cdtm_graph.errors.FlightLogError` with a
one-line message ``"<file>:<line>: <what is wrong>; expected <what>"``.

The file names are loaded with the package, the rest on first use of one of its names.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from cdtm_graph.flightlog.names import (
    FLIGHT_YAML,
    FORMAT,
    FRAMES_CSV,
    GROUNDTRUTH_CSV,
    IMU_CSV,
    LOG_FILES,
    NAV_CSV,
    TRACKS_CSV,
)

if TYPE_CHECKING:
    from cdtm_graph.flightlog.model import (
        CalibrationSigmas,
        CameraConfig,
        DtmConfig,
        FlightConfig,
        FlightLog,
        Frames,
        ImuConfig,
        ImuSamples,
        InitialState,
        States,
        Tracks,
    )
    from cdtm_graph.flightlog.reader import read_flightlog
    from cdtm_graph.flightlog.writer import (
        write_flightlog,
        write_flightlog_files,
        write_tracks,
    )

_WHERE = {"CalibrationSigmas": "model", "CameraConfig": "model", "DtmConfig": "model",
          "FlightConfig": "model", "FlightLog": "model", "Frames": "model", "ImuConfig": "model",
          "ImuSamples": "model", "InitialState": "model", "States": "model", "Tracks": "model",
          "read_flightlog": "reader", "write_flightlog": "writer",
          "write_flightlog_files": "writer", "write_tracks": "writer"}
__all__ = [
    "FLIGHT_YAML", "FORMAT", "FRAMES_CSV", "GROUNDTRUTH_CSV", "IMU_CSV", "LOG_FILES", "NAV_CSV",
    "TRACKS_CSV", "CalibrationSigmas", "CameraConfig", "DtmConfig", "FlightConfig",
    "FlightLog", "Frames",
    "ImuConfig", "ImuSamples", "InitialState", "States", "Tracks",
    "read_flightlog", "write_flightlog", "write_flightlog_files",
    "write_tracks",
]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        import importlib
        return getattr(importlib.import_module(f"cdtm_graph.flightlog.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
