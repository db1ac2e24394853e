"""Flight logs in the ``cdtm-flightlog/1`` format (docs/flightlog.md): model, readers, writer.

A flight log is a directory: ``flight.yaml`` (camera, IMU, DTM, initial state),
``imu.csv``, ``frames.csv`` and optionally ``tracks.csv``, ``nav.csv``,
``groundtruth.csv``. The CSV files follow the EuRoC/ASL column order, so EuRoC
files can be copied in as they are.

- :mod:`~cdtm_graph.flightlog.model`: the dataclasses (plain numpy, no GTSAM types).
- :mod:`~cdtm_graph.flightlog.tables` and :mod:`~cdtm_graph.flightlog.config`: the CSV
  and flight.yaml parsers; :mod:`~cdtm_graph.flightlog.reader` reads a whole directory.
- :mod:`~cdtm_graph.flightlog.writer`: writes one, bit-exact on the round trip.

Every problem in a log raises :class:`~cdtm_graph.errors.FlightLogError` with a
one-line message ``"<file>:<line>: <what is wrong>; expected <what>"``.
"""

from cdtm_graph.flightlog.model import (
    FLIGHT_YAML,
    FORMAT,
    FRAMES_CSV,
    GROUNDTRUTH_CSV,
    IMU_CSV,
    LOG_FILES,
    NAV_CSV,
    TRACKS_CSV,
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
from cdtm_graph.flightlog.writer import write_flightlog, write_flightlog_files, write_tracks

__all__ = [
    "FLIGHT_YAML", "FORMAT", "FRAMES_CSV", "GROUNDTRUTH_CSV", "IMU_CSV", "LOG_FILES", "NAV_CSV",
    "TRACKS_CSV", "CalibrationSigmas", "CameraConfig", "DtmConfig", "FlightConfig",
    "FlightLog", "Frames",
    "ImuConfig", "ImuSamples", "InitialState", "States", "Tracks",
    "read_flightlog", "write_flightlog", "write_flightlog_files",
    "write_tracks",
]
