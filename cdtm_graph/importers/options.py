"""The importers' named choices, in a module that imports no numerics: ``cdtm import``
offers them (``--imu-axes``, ``--imu-topics``, ``--gnss``, ``--imu-noise``) without
loading the readers. Re-exported by :mod:`~cdtm_graph.importers.px4` and
:mod:`~cdtm_graph.importers.recording`, which use them.
"""

from __future__ import annotations

import enum


class ImuAxes(enum.Enum):
    """The axes of the imported log's body (the IMU)."""

    FRD = "frd"  # PX4's body frame, as logged: x forward, y right, z down
    FLU = "flu"  # ROS base_link (mavros): x forward, y left, z up


class ImuTopics(enum.Enum):
    """Which topics give the IMU samples."""

    SENSOR_COMBINED = "sensor_combined"  # calibrated, the estimator's input (default)
    RAW = "raw"                          # sensor_gyro + sensor_accel, uncalibrated


class GnssSource(enum.Enum):
    """Which topic gives the GNSS track (ground truth, initial state, origin)."""

    GPS = "gps"                          # vehicle_gps_position, else sensor_gps
    GLOBAL_POSITION = "global_position"  # vehicle_global_position (the estimator's)


class ImuNoiseSource(enum.Enum):
    """Which white-noise densities an imported log's flight.yaml gets (``--imu-noise``)."""

    #: The calibration's (Kalibr, EuRoC sensor.yaml): a datasheet or an Allan variance at
    #: rest, without the vibration of flight.
    STATED = "stated"
    #: What the samples themselves scatter (:func:`cdtm_graph.verdict.imu_faults.sample_noise`,
    #: vibration included), the noisiest axis, where that exceeds the stated density; an
    #: IMU that filters its output reads low, so a stated density is never lowered.
    MEASURED = "measured"
