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
- :mod:`~cdtm_graph.importers.options`: the named choices (light: ``cdtm import --help``).

The choices are loaded with the package, the rest on first use of one of its names: an
import of one kind of recording loads only its reader.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from cdtm_graph.importers.options import GnssSource, ImuAxes, ImuNoiseSource, ImuTopics

if TYPE_CHECKING:
    from cdtm_graph.importers.calibration import (
        CameraCalibration,
        ImuCalibration,
        read_euroc_sensor,
        read_kalibr_camchain,
        read_kalibr_imu,
        read_kalibr_principal_point_sigma,
    )
    from cdtm_graph.importers.euroc import import_euroc, read_euroc
    from cdtm_graph.importers.px4 import (
        Px4Options,
        import_px4,
        read_px4,
    )
    from cdtm_graph.importers.recording import (
        DtmSource,
        ImportSettings,
        InitialPrior,
        SensorRecording,
        assemble_flightlog,
        read_groundtruth,
        write_imported_log,
    )
    from cdtm_graph.importers.rosbag import (
        BagTopics,
        StampSource,
        import_rosbag,
        read_bag,
    )

_WHERE = {"CameraCalibration": "calibration", "ImuCalibration": "calibration",
          "read_euroc_sensor": "calibration", "read_kalibr_camchain": "calibration",
          "read_kalibr_imu": "calibration",
          "read_kalibr_principal_point_sigma": "calibration", "import_euroc": "euroc",
          "read_euroc": "euroc",
          "Px4Options": "px4", "import_px4": "px4", "read_px4": "px4", "DtmSource": "recording",
          "ImportSettings": "recording", "InitialPrior": "recording",
          "SensorRecording": "recording", "assemble_flightlog": "recording",
          "read_groundtruth": "recording", "write_imported_log": "recording",
          "BagTopics": "rosbag", "StampSource": "rosbag", "import_rosbag": "rosbag",
          "read_bag": "rosbag"}
__all__ = [
    "GnssSource", "ImuAxes", "ImuTopics", "Px4Options", "import_px4", "read_px4",
    "BagTopics", "CameraCalibration", "DtmSource", "ImportSettings", "ImuCalibration",
    "ImuNoiseSource", "InitialPrior", "SensorRecording", "StampSource", "assemble_flightlog",
    "import_euroc", "import_rosbag", "read_bag", "read_euroc", "read_euroc_sensor",
    "read_groundtruth", "read_kalibr_camchain", "read_kalibr_imu",
    "read_kalibr_principal_point_sigma", "write_imported_log",
]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        import importlib
        return getattr(importlib.import_module(f"cdtm_graph.importers.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
