"""PX4 ULog files written from a flight log, as a PX4 flight controller logs them.

pyulog reads ULog files; its ``write_ulog`` only writes back a ``ULog`` it has read (its
objects are built from parsed bytes), so the tests write their own with this small writer
of the documented format (https://docs.px4.io/main/en/dev_log/ulog_file_format.html): the
16-byte header, a flag-bits message, one format ('F') and one subscription ('A') message
per topic, an info message, then the data ('D') messages in time order. Field layouts
are PX4 v1.14's (``msg/*.msg``, packed, little-endian).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cdtm_graph.flightlog import FlightLog
from cdtm_graph.geometry import quat_wxyz_to_rotation, rotation_to_quat_wxyz
from cdtm_graph.importers.px4 import ENU_R_NED, FLU_R_FRD

MAGIC = b"ULog\x01\x12\x35"
_TYPES = {"uint64_t": "<u8", "int64_t": "<i8", "uint32_t": "<u4", "int32_t": "<i4",
          "uint16_t": "<u2", "int16_t": "<i2", "uint8_t": "u1", "int8_t": "i1", "bool": "u1",
          "float": "<f4", "double": "<f8"}

#: PX4 v1.14's topics, (type, name, array length or 0).
SENSOR_COMBINED = [("uint64_t", "timestamp", 0), ("float", "gyro_rad", 3),
                   ("uint32_t", "gyro_integral_dt", 0),
                   ("int32_t", "accelerometer_timestamp_relative", 0),
                   ("float", "accelerometer_m_s2", 3),
                   ("uint32_t", "accelerometer_integral_dt", 0),
                   ("uint8_t", "accelerometer_clipping", 0), ("uint8_t", "gyro_clipping", 0),
                   ("uint8_t", "accel_calibration_count", 0),
                   ("uint8_t", "gyro_calibration_count", 0)]
VEHICLE_ATTITUDE = [("uint64_t", "timestamp", 0), ("uint64_t", "timestamp_sample", 0),
                    ("float", "q", 4), ("float", "delta_q_reset", 4),
                    ("uint8_t", "quat_reset_counter", 0)]
SENSOR_GPS = [("uint64_t", "timestamp", 0), ("uint64_t", "timestamp_sample", 0),
              ("double", "latitude_deg", 0), ("double", "longitude_deg", 0),
              ("double", "altitude_msl_m", 0), ("double", "altitude_ellipsoid_m", 0),
              ("float", "vel_m_s", 0), ("float", "vel_n_m_s", 0), ("float", "vel_e_m_s", 0),
              ("float", "vel_d_m_s", 0), ("float", "eph", 0), ("float", "epv", 0),
              ("uint8_t", "fix_type", 0), ("bool", "vel_ned_valid", 0),
              ("uint8_t", "satellites_used", 0)]
CAMERA_CAPTURE = [("uint64_t", "timestamp", 0), ("uint64_t", "timestamp_utc", 0),
                  ("double", "lat", 0), ("double", "lon", 0), ("float", "alt", 0),
                  ("float", "ground_distance", 0), ("float", "q", 4), ("uint32_t", "seq", 0),
                  ("int8_t", "result", 0)]


@dataclass
class Topic:
    """One logged topic: its layout and its values by field name ((N,) or (N, k))."""

    name: str
    fields: list[tuple[str, str, int]]
    values: dict[str, np.ndarray]

    def records(self) -> np.ndarray:
        dtype = np.dtype([(name, _TYPES[kind], (n,)) if n else (name, _TYPES[kind])
                          for kind, name, n in self.fields])
        n = len(self.values["timestamp"])
        out = np.zeros(n, dtype=dtype)
        for name, value in self.values.items():
            out[name] = value
        return out

    def format_text(self) -> str:
        return self.name + ":" + "".join(f"{kind}[{n}] {name};" if n else f"{kind} {name};"
                                         for kind, name, n in self.fields)


def _message(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


def write_ulog(path: Path, topics: list[Topic], start_us: int = 0) -> None:
    """A ULog file of ``topics`` (each logged as instance 0)."""
    parts = [MAGIC, b"\x01", struct.pack("<Q", start_us),
             _message(b"B", bytes(16) + struct.pack("<QQQ", 0, 0, 0))]
    parts += [_message(b"F", t.format_text().encode()) for t in topics]
    key = b"char[3] sys_name"
    parts.append(_message(b"I", bytes([len(key)]) + key + b"PX4"))
    parts += [_message(b"A", struct.pack("<BH", 0, i) + t.name.encode())
              for i, t in enumerate(topics)]
    data: list[tuple[int, int, bytes]] = []
    for i, topic in enumerate(topics):
        records = topic.records()
        raw = records.tobytes()
        size = records.dtype.itemsize
        head = struct.pack("<H", i)
        data += [(int(t), i, _message(b"D", head + raw[k * size:(k + 1) * size]))
                 for k, t in enumerate(records["timestamp"])]
    data.sort(key=lambda item: (item[0], item[1]))
    path.write_bytes(b"".join(parts) + b"".join(m for _, _, m in data))


def px4_topics(log: FlightLog, *, imu_period_us: int = 5000) -> list[Topic]:
    """The topics a PX4 flight controller logs of a geodetic flight log's flight.

    The log's body is taken as FLU (the simulator's: x forward, z up) and written in PX4's
    FRD; ``sensor_combined`` stamps each sample at the end of its period (the sample's
    time plus half a period); GNSS and ``vehicle_attitude`` at the ground truth's times;
    ``camera_capture`` at the frame times (the camera's clock is the IMU's), ``seq`` from 0.
    """
    frame = log.config.local_frame
    assert frame is not None and log.groundtruth is not None
    imu = log.imu
    assert np.all(imu.t_ns % 1000 == 0)
    n = len(imu)
    combined = Topic("sensor_combined", SENSOR_COMBINED, {
        "timestamp": imu.t_ns // 1000 + imu_period_us // 2,
        "gyro_rad": imu.gyro_radps @ FLU_R_FRD.T,
        "gyro_integral_dt": np.full(n, imu_period_us),
        "accelerometer_timestamp_relative": np.zeros(n, dtype=np.int32),
        "accelerometer_m_s2": imu.acc_mps2 @ FLU_R_FRD.T,
        "accelerometer_integral_dt": np.full(n, imu_period_us),
        "accel_calibration_count": np.ones(n), "gyro_calibration_count": np.ones(n)})
    truth = log.groundtruth
    lat, lon, h, enu_quat, enu_velocity = frame.states_to_geodetic(
        truth.position_m, quat_wxyz_to_rotation(truth.quaternion_wxyz), truth.velocity_mps)
    ned_R_frd = ENU_R_NED.T @ quat_wxyz_to_rotation(enu_quat) @ FLU_R_FRD
    t_us = truth.t_ns // 1000
    m = len(truth)
    attitude = Topic("vehicle_attitude", VEHICLE_ATTITUDE, {
        "timestamp": t_us, "timestamp_sample": t_us, "q": rotation_to_quat_wxyz(ned_R_frd)})
    ned_velocity = enu_velocity @ ENU_R_NED.T
    gps = Topic("vehicle_gps_position", SENSOR_GPS, {
        "timestamp": t_us, "timestamp_sample": t_us, "latitude_deg": lat,
        "longitude_deg": lon, "altitude_msl_m": h, "altitude_ellipsoid_m": h,
        "vel_m_s": np.linalg.norm(ned_velocity, axis=1), "vel_n_m_s": ned_velocity[:, 0],
        "vel_e_m_s": ned_velocity[:, 1], "vel_d_m_s": ned_velocity[:, 2],
        "eph": np.full(m, 0.5), "epv": np.full(m, 0.8), "fix_type": np.full(m, 3),
        "vel_ned_valid": np.ones(m), "satellites_used": np.full(m, 12)})
    k = len(log.frames)
    capture = Topic("camera_capture", CAMERA_CAPTURE, {
        "timestamp": log.frames.t_ns // 1000, "seq": np.arange(k), "result": np.ones(k),
        "q": np.tile([1.0, 0.0, 0.0, 0.0], (k, 1))})
    return [combined, attitude, gps, capture]
