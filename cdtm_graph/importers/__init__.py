"""Sensor recordings into ``cdtm-flightlog/1`` logs: EuRoC folders, ROS bags, Kalibr files.

- :mod:`~cdtm_graph.importers.calibration`: Kalibr camchain and IMU files, EuRoC
  ``sensor.yaml`` (``T_cam_imu`` inverted into ``body_T_cam``, ``timeshift_cam_imu`` as
  ``camera.time_offset_s``, ``update_rate`` as ``imu.rate_hz``).
- :mod:`~cdtm_graph.importers.recording`: what every importer shares: the DTM,
  the prior, assembling and writing the log.
- :mod:`~cdtm_graph.importers.euroc`,
  :mod:`~cdtm_graph.importers.rosbag` (needs the ``rosbag`` extra) and
  :mod:`~cdtm_graph.importers.px4` (PX4 ULog files; the ``px4`` extra): the
  readers.
"""

from cdtm_graph.importers.calibration import (
    CameraCalibration,
    ImuCalibration,
    read_euroc_sensor,
    read_kalibr_camchain,
    read_kalibr_imu,
)
from cdtm_graph.importers.euroc import import_euroc, read_euroc
from cdtm_graph.importers.px4 import (
    GnssSource,
    ImuAxes,
    ImuTopics,
    Px4Options,
    import_px4,
    read_px4,
)
from cdtm_graph.importers.recording import (
    DtmSource,
    ImportSettings,
    ImuNoiseSource,
    InitialPrior,
    SensorRecording,
    assemble_flightlog,
    read_groundtruth,
    write_imported_log,
)
from cdtm_graph.importers.rosbag import BagTopics, StampSource, import_rosbag, read_bag

__all__ = [
    "GnssSource", "ImuAxes", "ImuTopics", "Px4Options", "import_px4", "read_px4",
    "BagTopics", "CameraCalibration", "DtmSource", "ImportSettings", "ImuCalibration",
    "ImuNoiseSource", "InitialPrior", "SensorRecording", "StampSource", "assemble_flightlog",
    "import_euroc", "import_rosbag", "read_bag", "read_euroc", "read_euroc_sensor",
    "read_groundtruth", "read_kalibr_camchain", "read_kalibr_imu", "write_imported_log",
]
