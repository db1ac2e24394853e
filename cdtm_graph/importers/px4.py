"""A PX4 flight log (ULog ``.ulg``) as a sensor recording (``cdtm import px4``), with pyulog.

Read with ``pyulog`` (``pip install "cdtm-graph[px4]"``), the PX4 project's own reader of
the format (https://docs.px4.io/main/en/dev_log/ulog_file_format.html). Every topic is
stamped in microseconds since the flight controller booted: one clock, which becomes the
log's IMU clock (``t_ns = 1000 t_us``). What is read, each piece a function testable alone:

* **IMU** (:func:`extract_imu`): ``sensor_combined`` (calibrated, what PX4's estimator
  integrates): ``gyro_rad`` (rad/s) and ``accelerometer_m_s2`` (specific force, m/s^2),
  each the average over its last sampling period ``*_integral_dt`` (microseconds; seconds
  in logs before 2018) ending at ``timestamp`` for the gyro and at ``timestamp +
  accelerometer_timestamp_relative`` for the accelerometer. A sample is placed at the
  middle of its gyro period; accelerometer values on another clock phase are interpolated
  to those times. Or the raw ``sensor_gyro`` / ``sensor_accel`` topics (``x, y, z`` at
  ``timestamp_sample``; uncalibrated: their offsets go into the estimated biases).
* **Axes**: PX4's body frame is FRD (x forward, y right, z down): at rest the
  accelerometer reads about (0, 0, -9.8). The log's body is the IMU in these axes
  (:attr:`ImuAxes.FRD`), or rotated into FLU (:attr:`ImuAxes.FLU`, x forward, y left,
  z up: ROS's ``base_link``, the axes mavros publishes, in which a Kalibr calibration
  recorded through mavros gives ``T_cam_imu``). The world is ENU (README, Conventions).
* **Frames** (:func:`extract_triggers`, :func:`match_triggers`): ``camera_capture`` (the
  camera's capture feedback; failed captures left out) or else ``camera_trigger``, matched
  in time order to the images of ``--images DIR`` in file-name order.
* **GNSS** (:func:`extract_gnss`): ``vehicle_gps_position`` or ``sensor_gps`` (3-D fixes
  only; latitude, longitude, ellipsoidal height, NED velocity), or the estimator's
  ``vehicle_global_position``. With ``vehicle_attitude`` (FRD -> NED quaternion) it makes
  the ground truth and the initial state (:func:`groundtruth_states`): a geodetic log
  (docs/flightlog.md, a flight in latitude and longitude; the origin defaults to the
  first fix). A GNSS track is metres from the truth: errors against it include the GNSS's.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cdtm_graph.errors import SensorDataError
from cdtm_graph.flightlog.model import FlightLog, ImuSamples, States
from cdtm_graph.geodesy import GeodeticOrigin, LocalFrame, geoid_undulation_m, local_frame
from cdtm_graph.geometry import quat_wxyz_to_rotation, rotation_to_quat_wxyz
from cdtm_graph.importers.calibration import CameraCalibration, ImuCalibration
from cdtm_graph.importers.options import GnssSource, ImuAxes, ImuTopics
from cdtm_graph.importers.recording import (
    IMAGE_DIR,
    ImportSettings,
    SensorRecording,
    assemble_flightlog,
    check_image_size,
    check_prior,
    write_imported_log,
)

logger = logging.getLogger(__name__)

INSTALL_HINT = 'pip install "cdtm-graph[px4]" (pyulog, the PX4 project\'s ULog reader)'
NS_PER_US = 1000
#: FLU axes from FRD ones (and back): a half turn about x.
FLU_R_FRD = np.diag([1.0, -1.0, -1.0])
#: ENU from NED.
ENU_R_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: uORB's mark of a relative timestamp that is not valid (``RELATIVE_TIMESTAMP_INVALID``).
RELATIVE_TIMESTAMP_INVALID = 0x7FFFFFFF
#: GNSS fix types kept: 3-D fixes and better (3 3D, 4 DGPS, 5 RTK float, 6 RTK fixed).
MIN_FIX_TYPE = 3
#: Image files ``--images`` may hold (case-insensitive).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm")
GPS_TOPICS = ("vehicle_gps_position", "sensor_gps")
TRIGGER_TOPICS = ("camera_capture", "camera_trigger")


@dataclass(frozen=True, eq=False)
class GnssTrack:
    """A GNSS track on the flight controller's clock.

    Attributes:
        t_ns: (N,) int64 times, strictly increasing.
        latitude_deg, longitude_deg: (N,) WGS84.
        height_m: (N,) ellipsoidal height (EGM96 added to a mean-sea-level height where the
            topic has no ellipsoidal one).
        velocity_ned_mps: (N, 3) north, east, down, or None (the topic has none).
        topic: where it came from.
    """

    t_ns: np.ndarray
    latitude_deg: np.ndarray
    longitude_deg: np.ndarray
    height_m: np.ndarray
    velocity_ned_mps: np.ndarray | None
    topic: str

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass(frozen=True, eq=False)
class CameraTriggers:
    """Camera trigger or capture times on the flight controller's clock.

    Attributes:
        t_ns: (K,) int64, increasing. seq: (K,) the camera's image counter.
        topic: where they came from. failed: captures reported failed (left out).
    """

    t_ns: np.ndarray
    seq: np.ndarray
    topic: str
    failed: int = 0


def _pyulog() -> Any:
    try:
        import pyulog
    except ImportError:
        raise SensorDataError(f"reading PX4 logs needs the pyulog package; expected "
                              f"{INSTALL_HINT}") from None
    return pyulog


def read_ulog(path: str | os.PathLike, topics: tuple[str, ...] | None = None) -> Any:
    """A ULog file read by pyulog (only ``topics``, if given).

    Raises:
        SensorDataError: pyulog is missing; the file is missing or not a ULog file.
    """
    pyulog = _pyulog()
    path = Path(path)
    if not path.is_file():
        raise SensorDataError(f"{path}: {'a folder' if path.is_dir() else 'does not exist'}; "
                              "expected a PX4 log file (.ulg)")
    try:
        return pyulog.ULog(str(path), list(topics) if topics is not None else None)
    except Exception as exc:  # pyulog raises ULogException, struct.error, IndexError...
        raise SensorDataError(f"{path}: cannot be read as a ULog file ({exc or type(exc)}); "
                              "expected a PX4 flight log (.ulg)") from None


def _dataset(ulog: Any, name: str) -> dict[str, np.ndarray] | None:
    """The fields of a topic's first instance, or None."""
    for d in ulog.data_list:
        if d.name == name and d.multi_id == 0:
            return d.data
    return None


def _require(ulog: Any, name: str, shown: str, what: str) -> dict[str, np.ndarray]:
    data = _dataset(ulog, name)
    if data is None or len(data["timestamp"]) == 0:
        held = ", ".join(sorted({d.name for d in ulog.data_list})) or "no topics"
        raise SensorDataError(f"{shown}: no {name} topic; expected {what} (the log holds "
                              f"{held})")
    return data


def _vector(data: dict[str, np.ndarray], name: str) -> np.ndarray:
    return np.column_stack([np.asarray(data[f"{name}[{i}]"], dtype=float) for i in range(3)])


def _period_us(data: dict[str, np.ndarray], key: str) -> np.ndarray:
    """A ``*_integral_dt`` field in microseconds (float seconds in logs before 2018)."""
    dt = np.asarray(data[key])
    if dt.dtype.kind == "f":
        return np.round(dt.astype(float) * 1e6).astype(np.int64)
    return dt.astype(np.int64)


def extract_imu(ulog: Any, topics: ImuTopics = ImuTopics.SENSOR_COMBINED,
                axes: ImuAxes = ImuAxes.FRD, shown: str = "the log") -> tuple[ImuSamples, int]:
    """The IMU samples of a log, in the body axes asked for.

    Returns:
        The samples (strictly increasing times, ns on the flight controller's clock), and
        how many were left out (a time not after the previous one, an invalid
        accelerometer stamp).

    Raises:
        SensorDataError: the topics are missing or hold non-finite values.
    """
    if topics is ImuTopics.SENSOR_COMBINED:
        data = _require(ulog, "sensor_combined", shown, "PX4's IMU samples")
        t_us = np.asarray(data["timestamp"], dtype=np.int64)
        gyro = _vector(data, "gyro_rad")
        acc = _vector(data, "accelerometer_m_s2")
        t_ns = t_us * NS_PER_US - _period_us(data, "gyro_integral_dt") * (NS_PER_US // 2)
        relative = np.asarray(data["accelerometer_timestamp_relative"], dtype=np.int64)
        valid = relative != RELATIVE_TIMESTAMP_INVALID
        acc_t_ns = ((t_us + relative) * NS_PER_US
                    - _period_us(data, "accelerometer_integral_dt") * (NS_PER_US // 2))
        t_ns, gyro, acc, acc_t_ns = t_ns[valid], gyro[valid], acc[valid], acc_t_ns[valid]
        left_out = int((~valid).sum())
    else:
        gyro_data = _require(ulog, "sensor_gyro", shown, "the raw gyro samples")
        acc_data = _require(ulog, "sensor_accel", shown, "the raw accelerometer samples")
        t_ns = _sample_times_ns(gyro_data)
        acc_t_ns = _sample_times_ns(acc_data)
        gyro = np.column_stack([np.asarray(gyro_data[k], dtype=float) for k in "xyz"])
        acc_raw = np.column_stack([np.asarray(acc_data[k], dtype=float) for k in "xyz"])
        order = np.argsort(acc_t_ns, kind="stable")
        acc_t_ns, acc_raw = acc_t_ns[order], acc_raw[order]
        inside = (t_ns >= acc_t_ns[0]) & (t_ns <= acc_t_ns[-1])
        t_ns, gyro = t_ns[inside], gyro[inside]
        acc = _interpolate(acc_t_ns, acc_raw, t_ns)
        acc_t_ns = t_ns
        left_out = int((~inside).sum())
    if not np.array_equal(acc_t_ns, t_ns):  # the accelerometer on another phase
        acc = _interpolate(acc_t_ns, acc, t_ns)
    order = np.argsort(t_ns, kind="stable")
    t_ns, gyro, acc = t_ns[order], gyro[order], acc[order]
    keep = np.concatenate([[True], np.diff(t_ns) > 0])
    left_out += int((~keep).sum())
    t_ns, gyro, acc = t_ns[keep], gyro[keep], acc[keep]
    bad = ~(np.isfinite(gyro).all(axis=1) & np.isfinite(acc).all(axis=1))
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise SensorDataError(f"{shown}: IMU sample at {int(t_ns[k]) // NS_PER_US} us is "
                              f"not finite (gyro {gyro[k].tolist()}, accelerometer "
                              f"{acc[k].tolist()}); expected finite rates and accelerations")
    if axes is ImuAxes.FLU:
        gyro, acc = gyro @ FLU_R_FRD.T, acc @ FLU_R_FRD.T
    return ImuSamples(t_ns, gyro, acc), left_out


def _sample_times_ns(data: dict[str, np.ndarray]) -> np.ndarray:
    """``timestamp_sample`` where the topic has it and it is set, else ``timestamp`` (ns)."""
    t_us = np.asarray(data["timestamp"], dtype=np.int64)
    if "timestamp_sample" in data:
        sample = np.asarray(data["timestamp_sample"], dtype=np.int64)
        t_us = np.where(sample > 0, sample, t_us)
    return t_us * NS_PER_US


def _interpolate(t_from: np.ndarray, values: np.ndarray, t_to: np.ndarray) -> np.ndarray:
    base = int(t_from[0])  # differences of int64 ns are exact in float64
    x_from, x_to = (t_from - base).astype(float), (t_to - base).astype(float)
    return np.column_stack([np.interp(x_to, x_from, values[:, j])
                            for j in range(values.shape[1])])


def extract_gnss(ulog: Any, source: GnssSource = GnssSource.GPS,
                 shown: str = "the log") -> GnssTrack | None:
    """The GNSS track of a log (3-D fixes only), or None if the log has none.

    Raises:
        SensorDataError: the topic is there but holds no 3-D fix.
    """
    if source is GnssSource.GPS:
        for topic in GPS_TOPICS:
            data = _dataset(ulog, topic)
            if data is not None and len(data["timestamp"]):
                return _gps_track(data, topic, shown)
        return None
    data = _dataset(ulog, "vehicle_global_position")
    if data is None or not len(data["timestamp"]):
        return None
    t_ns = _sample_times_ns(data)
    lat, lon = np.asarray(data["lat"], float), np.asarray(data["lon"], float)
    if "alt_ellipsoid" in data:
        height = np.asarray(data["alt_ellipsoid"], float)
    else:
        height = np.asarray(data["alt"], float) + geoid_undulation_m(lat, lon)
    velocity = None
    if "vel_n" in data:  # PX4 before v1.14
        velocity = np.column_stack([np.asarray(data[k], float)
                                    for k in ("vel_n", "vel_e", "vel_d")])
    else:
        local = _dataset(ulog, "vehicle_local_position")
        if local is not None and len(local["timestamp"]):
            local_t = _sample_times_ns(local)
            ned = np.column_stack([np.asarray(local[k], float) for k in ("vx", "vy", "vz")])
            order = np.argsort(local_t, kind="stable")
            velocity = _interpolate(local_t[order], ned[order], t_ns)
    return _track(t_ns, lat, lon, height, velocity, "vehicle_global_position", shown)


def _gps_track(data: dict[str, np.ndarray], topic: str, shown: str) -> GnssTrack:
    t_ns = _sample_times_ns(data)
    if "latitude_deg" in data:  # PX4 v1.14 and later
        lat = np.asarray(data["latitude_deg"], float)
        lon = np.asarray(data["longitude_deg"], float)
        height = np.asarray(data["altitude_ellipsoid_m"], float)
    else:                       # earlier: 1e-7 degrees, millimetres
        lat = np.asarray(data["lat"], float) * 1e-7
        lon = np.asarray(data["lon"], float) * 1e-7
        height = (np.asarray(data["alt_ellipsoid"], float) * 1e-3 if "alt_ellipsoid" in data
                  else np.asarray(data["alt"], float) * 1e-3 + geoid_undulation_m(lat, lon))
    velocity = np.column_stack([np.asarray(data[k], float)
                                for k in ("vel_n_m_s", "vel_e_m_s", "vel_d_m_s")])
    fix = np.asarray(data["fix_type"], dtype=np.int64) >= MIN_FIX_TYPE
    if not fix.any():
        raise SensorDataError(f"{shown}: {topic} holds {len(fix)} messages but no 3-D fix "
                              f"(fix_type >= {MIN_FIX_TYPE}); expected a GNSS track, or "
                              "--initial-* flags without one")
    return _track(t_ns[fix], lat[fix], lon[fix], height[fix], velocity[fix], topic, shown)


def _track(t_ns, lat, lon, height, velocity, topic: str, shown: str) -> GnssTrack:
    order = np.argsort(t_ns, kind="stable")
    t_ns = np.asarray(t_ns, dtype=np.int64)[order]
    keep = np.concatenate([[True], np.diff(t_ns) > 0])
    pick = order[keep]
    t_ns = t_ns[keep]
    columns = [lat[pick], lon[pick], height[pick]]
    if velocity is not None:
        velocity = velocity[pick]
    finite = np.isfinite(np.column_stack(columns)).all(axis=1)
    if velocity is not None:
        finite &= np.isfinite(velocity).all(axis=1)
    if not finite.all():
        logger.warning("%s: %d %s messages with non-finite values left out", shown,
                       int((~finite).sum()), topic)
    lat, lon, height = (c[finite] for c in columns)
    return GnssTrack(t_ns[finite], lat, lon, height,
                     velocity[finite] if velocity is not None else None, topic)


def extract_attitude(ulog: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """``vehicle_attitude``: (N,) times (ns) and (N, 4) FRD -> NED quaternions w x y z, or
    None if the log has none."""
    data = _dataset(ulog, "vehicle_attitude")
    if data is None or not len(data["timestamp"]):
        return None
    t_ns = _sample_times_ns(data)
    quat = np.column_stack([np.asarray(data[f"q[{i}]"], float) for i in range(4)])
    order = np.argsort(t_ns, kind="stable")
    t_ns, quat = t_ns[order], quat[order]
    keep = np.concatenate([[True], np.diff(t_ns) > 0]) & np.isfinite(quat).all(axis=1)
    quat = quat[keep] / np.linalg.norm(quat[keep], axis=1, keepdims=True)
    return t_ns[keep], quat


def extract_triggers(ulog: Any, shown: str = "the log") -> CameraTriggers:
    """The camera's capture (``camera_capture``) or trigger (``camera_trigger``) times.

    Raises:
        SensorDataError: neither topic is in the log.
    """
    for topic in TRIGGER_TOPICS:
        data = _dataset(ulog, topic)
        if data is None or not len(data["timestamp"]):
            continue
        t_ns = np.asarray(data["timestamp"], dtype=np.int64) * NS_PER_US
        seq = np.asarray(data["seq"], dtype=np.int64)
        ok = (np.asarray(data["result"], dtype=np.int64) != 0 if "result" in data
              else np.ones(len(t_ns), bool))  # camera_capture.result: 0 a failed capture
        order = np.argsort(t_ns[ok], kind="stable")
        return CameraTriggers(t_ns[ok][order], seq[ok][order], topic, int((~ok).sum()))
    held = ", ".join(sorted({d.name for d in ulog.data_list})) or "no topics"
    raise SensorDataError(f"{shown}: no camera_capture or camera_trigger topic; expected the "
                          f"camera's trigger times (the log holds {held})")


def image_files(images_dir: str | os.PathLike) -> list[Path]:
    """The image files of a folder in file-name order (numbers in names compared as
    numbers: IMG_9 before IMG_10).

    Raises:
        SensorDataError: not a folder, or no image in it.
    """
    folder = Path(images_dir)
    if not folder.is_dir():
        raise SensorDataError(f"{folder}: {'a file' if folder.exists() else 'does not exist'}"
                              "; expected the folder of the flight's images (--images DIR)")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if not files:
        raise SensorDataError(f"{folder}: no image files; expected the flight's images "
                              f"({', '.join(IMAGE_SUFFIXES)})")
    return sorted(files, key=lambda p: [int(s) if s.isdigit() else s.lower()
                                        for s in re.split(r"(\d+)", p.name)])


def match_triggers(triggers: CameraTriggers, images: list[Path],
                   shown: str = "the log") -> tuple[np.ndarray, list[Path]]:
    """The frame times of the images: one trigger per image, both in time (name) order.

    When the log lost trigger messages (gaps in ``seq``) and the images are as many as the
    triggers' ``seq`` span, image ``i`` is the one of ``seq[0] + i``, and images without a
    logged trigger are left out (a warning says how many).

    Returns:
        (K,) frame times (ns, strictly increasing) and their K images.

    Raises:
        SensorDataError: the counts do not match (naming both), or two triggers share a
            time.
    """
    t_ns, seq = triggers.t_ns, triggers.seq
    if len(images) == len(t_ns):
        chosen, times = images, t_ns
    elif len(t_ns) and len(images) == int(seq[-1] - seq[0]) + 1 and np.all(np.diff(seq) > 0):
        chosen = [images[int(s - seq[0])] for s in seq]
        times = t_ns
        logger.warning("%s: %d of %d images have no logged %s (seq gaps) and are left out",
                       shown, len(images) - len(chosen), len(images), triggers.topic)
    else:
        span = f", seq {int(seq[0])}..{int(seq[-1])}" if len(seq) else ""
        raise SensorDataError(
            f"{shown}: {len(images)} images in {images[0].parent} but {len(t_ns)} "
            f"{triggers.topic} messages{span}; expected one image per trigger, in file-name "
            "order")
    if np.any(np.diff(times) <= 0):
        k = int(np.flatnonzero(np.diff(times) <= 0)[0])
        raise SensorDataError(f"{shown}: two {triggers.topic} messages at "
                              f"{int(times[k + 1]) // NS_PER_US} us; expected one trigger "
                              "per image, at increasing times")
    return np.asarray(times, dtype=np.int64), list(chosen)


def groundtruth_states(gnss: GnssTrack, attitude: tuple[np.ndarray, np.ndarray],
                       frame: LocalFrame, axes: ImuAxes = ImuAxes.FRD) -> States | None:
    """Body states in the world frame from a GNSS track and ``vehicle_attitude``.

    At the GNSS times inside the attitude's span: the position from latitude, longitude
    and ellipsoidal height, the velocity from NED into ENU, the attitude slerped from the
    FRD -> NED quaternions and turned into body (``axes``) -> local ENU.

    Returns:
        The states, or None without a GNSS velocity or with fewer than 2 such times.
    """
    from scipy.spatial.transform import Rotation, Slerp

    if gnss.velocity_ned_mps is None:
        return None
    att_t, att_q = attitude
    inside = (gnss.t_ns >= att_t[0]) & (gnss.t_ns <= att_t[-1])
    if inside.sum() < 2 or len(att_t) < 2:
        return None
    base = int(att_t[0])
    rotations = Rotation.from_quat(att_q[:, [1, 2, 3, 0]])  # scipy: x y z w
    ned_R_frd = Slerp((att_t - base).astype(float), rotations)(
        (gnss.t_ns[inside] - base).astype(float)).as_matrix()
    enu_R_body = ENU_R_NED @ ned_R_frd
    if axes is ImuAxes.FLU:
        enu_R_body = enu_R_body @ FLU_R_FRD.T
    velocity_enu = gnss.velocity_ned_mps[inside] @ ENU_R_NED.T
    position, quat, velocity = frame.states_from_geodetic(
        gnss.latitude_deg[inside], gnss.longitude_deg[inside], gnss.height_m[inside],
        rotation_to_quat_wxyz(enu_R_body), velocity_enu)
    return States(gnss.t_ns[inside], position, quat, velocity)


def gnss_origin(path: str | os.PathLike,
                source: GnssSource = GnssSource.GPS) -> GeodeticOrigin:
    """The first GNSS fix of a log, as the world origin of its import.

    Raises:
        SensorDataError: the log has no GNSS track (then ``--origin`` is needed).
    """
    topics = (GPS_TOPICS if source is GnssSource.GPS
              else ("vehicle_global_position", "vehicle_local_position"))
    track = extract_gnss(read_ulog(path, topics), source, str(path))
    if track is None or not len(track):
        raise SensorDataError(f"{path}: no GNSS track ({', '.join(topics[:2])}) to place the "
                              "world origin; expected --origin LAT LON H")
    return GeodeticOrigin(float(track.latitude_deg[0]), float(track.longitude_deg[0]),
                          float(track.height_m[0]))


@dataclass(frozen=True)
class Px4Options:
    """How a PX4 log is read (``cdtm import px4``'s options)."""

    axes: ImuAxes = ImuAxes.FRD
    imu_topics: ImuTopics = ImuTopics.SENSOR_COMBINED
    gnss: GnssSource = GnssSource.GPS


def read_px4(path: str | os.PathLike, images_dir: str | os.PathLike, origin: GeodeticOrigin,
             *, camera: CameraCalibration, imu: ImuCalibration,
             options: Px4Options = Px4Options()) -> tuple[SensorRecording, list[Path]]:
    """Read a ULog file's IMU, camera triggers, GNSS ground truth, and match the images.

    Returns:
        The recording (ground truth in the world of ``origin``), and each frame's image.
    """
    shown = str(path)
    images = image_files(images_dir)  # before a long read
    ulog = read_ulog(path)
    samples, left_out = extract_imu(ulog, options.imu_topics, options.axes, shown)
    if left_out:
        logger.warning("%s: %d IMU samples left out (a time not after the previous one, or "
                       "an invalid accelerometer stamp)", shown, left_out)
    triggers = extract_triggers(ulog, shown)
    frame_t_ns, chosen = match_triggers(triggers, images, shown)
    gnss = extract_gnss(ulog, options.gnss, shown)
    attitude = extract_attitude(ulog)
    truth = (groundtruth_states(gnss, attitude, local_frame(origin), options.axes)
             if gnss is not None and attitude is not None else None)
    if gnss is not None and truth is None:
        logger.warning("%s: the GNSS track (%s) gives no ground truth (no velocity, or no "
                       "vehicle_attitude over it)", shown, gnss.topic)
    provenance = {"format": "px4", "imu_topic": options.imu_topics.value,
                  "imu_axes": options.axes.value, "trigger_topic": triggers.topic,
                  "failed_captures": triggers.failed,
                  "groundtruth": (f"{gnss.topic} + vehicle_attitude"
                                  if gnss is not None and truth is not None else None),
                  "imu_samples_left_out": left_out}
    recording = SensorRecording(shown, samples, frame_t_ns, camera, imu.imu, truth, None,
                                provenance)
    return recording, chosen


#: At the first frame the camera's optical axis must point at least this far below the
#: horizon (deg): a downward camera. A calibration in the other body axes (FLU for FRD)
#: turns the mount half a turn about x, and the camera then looks up.
MIN_CAMERA_DEPRESSION_DEG = 0.0


def _check_camera_looks_down(log: FlightLog, axes: ImuAxes, shown: str) -> None:
    """The camera looks below the horizon at the first frame, at the initial attitude.

    Raises:
        SensorDataError: it looks up, naming the likely cause (the calibration's axes).
    """
    state = log.config.initial_state
    world_R_body = quat_wxyz_to_rotation(state.quaternion_wxyz)
    frame = log.config.local_frame
    up = (frame.world_R_enu_at(state.position_m[None])[0][:, 2] if frame is not None
          else np.array([0.0, 0.0, 1.0]))  # the local vertical in the world frame
    optical_axis = world_R_body @ log.config.camera.body_T_cam[:3, 2]
    elevation_deg = float(np.degrees(np.arcsin(np.clip(optical_axis @ up, -1.0, 1.0))))
    if -elevation_deg < MIN_CAMERA_DEPRESSION_DEG:
        other = ImuAxes.FLU if axes is ImuAxes.FRD else ImuAxes.FRD
        raise SensorDataError(
            f"{shown}: with --imu-axes {axes.value} the camera looks {elevation_deg:.0f} deg "
            f"above the horizon at the first frame; expected a camera looking down: is the "
            f"Kalibr calibration in {other.value.upper()} axes (--imu-axes {other.value}; "
            "mavros publishes the IMU in FLU)?")


def import_px4(path: str | os.PathLike, images_dir: str | os.PathLike,
               directory: str | os.PathLike, final_dir: str | os.PathLike,
               settings: ImportSettings, *, camera: CameraCalibration, imu: ImuCalibration,
               options: Px4Options = Px4Options(),
               progress: Callable[[int, int], None] | None = None) -> FlightLog:
    """Read a PX4 log and its images and write them as a flight log into ``directory`` (a
    staging directory published as ``final_dir``): images copied into ``images/``.

    Args:
        settings: its DTM must have a geodetic origin (:func:`gnss_origin` gives the first
            fix's) and a vertical datum: PX4 positions are latitude and longitude.

    Returns:
        The log as written and read back: its initial state and groundtruth.csv in
        latitude, longitude and height, as GNSS gives them.
    """
    origin = settings.dtm.origin
    if origin is None:
        raise SensorDataError(f"{path}: a PX4 import makes a geodetic log; expected a "
                              "geodetic origin (--origin, default the first GNSS fix) and a "
                              "DEM with --vertical-datum")
    recording, sources = read_px4(path, images_dir, origin, camera=camera, imu=imu,
                                  options=options)
    check_prior(settings, recording.groundtruth is not None, recording.source)
    check_image_size(sources[0], camera)
    directory = Path(directory)
    source_of = {f"{IMAGE_DIR}/{source.name}": source for source in sources}
    log = assemble_flightlog(recording, tuple(source_of), settings)
    _check_camera_looks_down(log, options.axes, str(path))
    (directory / IMAGE_DIR).mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(log.frames.image):
        shutil.copyfile(source_of[name], directory / name)
        if progress is not None:
            progress(k + 1, len(log.frames))
    return write_imported_log(log, settings, directory, final_dir, geodetic=True)


__all__ = ["CameraTriggers", "GnssSource", "GnssTrack", "ImuAxes", "ImuTopics", "Px4Options",
           "extract_attitude", "extract_gnss", "extract_imu", "extract_triggers", "gnss_origin",
           "groundtruth_states", "image_files", "import_px4", "match_triggers", "read_px4",
           "read_ulog"]
