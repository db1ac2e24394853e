"""The names of a ``cdtm-flightlog/1`` log's files, in a module that imports no numerics
(``cdtm track --help`` and ``cdtm import`` name them without loading the reader)."""

from __future__ import annotations

FORMAT = "cdtm-flightlog/1"

FLIGHT_YAML = "flight.yaml"
IMU_CSV = "imu.csv"
FRAMES_CSV = "frames.csv"
TRACKS_CSV = "tracks.csv"
NAV_CSV = "nav.csv"
GROUNDTRUTH_CSV = "groundtruth.csv"
#: Every file the writer owns; stale optional ones are removed when a log is rewritten.
LOG_FILES = (FLIGHT_YAML, IMU_CSV, FRAMES_CSV, TRACKS_CSV, NAV_CSV, GROUNDTRUTH_CSV)
