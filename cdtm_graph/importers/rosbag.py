"""A ROS1 or ROS2 bag as a sensor recording (``cdtm import rosbag``), with ``rosbags``.

Read with the pure-Python ``rosbags`` package (``pip install "cdtm-graph[rosbag]"``), so no
ROS installation is needed; ROS1 ``.bag`` files and ROS2 bag directories (sqlite3 or mcap)
alike. Two topics are read:

* the IMU, ``sensor_msgs/Imu``: ``angular_velocity`` (rad/s) and ``linear_acceleration``
  (m/s^2, specific force) in the message's frame, which is the body frame of the log;
* the camera, ``sensor_msgs/Image`` (any encoding ``rosbags-image`` converts: mono images
  are kept as they are, 8 or 16 bit; colour and Bayer images become BGR) or
  ``sensor_msgs/CompressedImage``: written as PNG into ``images/``, named by their stamps.

Times are the messages' ``header.stamp`` (the sensor's time), or with ``stamps="bag"`` the
time each message was recorded. A stamp repeated on a topic (a driver's duplicate) keeps
the first message and is counted; stamps repeated, or much denser than the rest, several
in a row are two stretches of the recording at once (a clock that jumped back) and refused.
The bag holds no calibration: a Kalibr camchain gives the
camera, its mounting (``T_cam_imu``) and clock offset (``timeshift_cam_imu``), and a Kalibr
IMU file the noise model; their ``rostopic`` keys name the topics when not given.
"""

from __future__ import annotations

import enum
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cdtm_graph.errors import SensorDataError
from cdtm_graph.flightlog.model import FlightLog, ImuSamples, States
from cdtm_graph.importers.calibration import CameraCalibration, ImuCalibration
from cdtm_graph.importers.recording import (
    IMAGE_DIR,
    ImportSettings,
    SensorRecording,
    assemble_flightlog,
    check_prior,
    write_imported_log,
)

IMU_TYPES = ("sensor_msgs/msg/Imu",)
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
#: rosbags' error for a bag it cannot read, and what to install without it.
INSTALL_HINT = 'pip install "cdtm-graph[rosbag]" (the pure-Python rosbags and rosbags-image)'
#: Mono encodings kept as they are; anything else is converted to BGR.
MONO_ENCODINGS = ("mono8", "mono16", "8UC1", "16UC1")


class StampSource(enum.Enum):
    """Which time a message gets."""

    HEADER = "header"  # header.stamp: when the sensor sampled (the default)
    BAG = "bag"        # when the recorder received it


@dataclass(frozen=True)
class BagTopics:
    """The topics to read; None: the one the Kalibr file names."""

    imu: str | None = None
    image: str | None = None


@dataclass(frozen=True)
class BagContents:
    """What was read from a bag: the samples, the frames, and what was left out."""

    imu: ImuSamples
    frame_t_cam_ns: np.ndarray
    images: tuple[str, ...]
    duplicate_imu: int
    duplicate_frames: int


def _rosbags() -> Any:
    try:
        import rosbags.highlevel
        import rosbags.image
        import rosbags.typesys
    except ImportError as exc:
        raise SensorDataError(f"reading ROS bags needs the rosbags package ({exc.name} is "
                              f"missing); expected {INSTALL_HINT}") from None
    return rosbags


def read_bag(bag: str | os.PathLike, topics: BagTopics, images_dir: str | os.PathLike, *,
             stamps: StampSource = StampSource.HEADER,
             progress: Callable[[int, int], None] | None = None) -> BagContents:
    """Read the IMU and image topics of a bag; write each image as it is read.

    Args:
        bag: a ROS1 ``.bag`` file or a ROS2 bag directory.
        topics: both topics, given.
        images_dir: where the images go (``<log>/images``; created).
        stamps: which time each message gets.
        progress: called with (messages read, messages in the two topics).

    Returns:
        The samples and frames in time order; image paths relative to the log directory.

    Raises:
        SensorDataError: the bag cannot be read, a topic is missing, of another type or
            empty, an IMU message lacks rates or accelerations, an image cannot be decoded.
    """
    rb = _rosbags()
    from rosbags.typesys import Stores, get_typestore

    bag = Path(bag)
    images_dir = Path(images_dir)
    images_dir.mkdir(parents=True, exist_ok=True)
    assert topics.imu is not None and topics.image is not None
    imu_t: list[int] = []
    imu_rows: list[list[float]] = []
    frame_t: list[int] = []
    names: list[str] = []
    seen_frames: set[int] = set()
    duplicate_frames = 0
    try:
        reader_cls = rb.highlevel.AnyReader
        with reader_cls([bag], default_typestore=get_typestore(Stores.LATEST)) as reader:
            imu_conn = _connections(reader, bag, topics.imu, IMU_TYPES, "IMU")
            image_conn = _connections(reader, bag, topics.image, IMAGE_TYPES, "image")
            total = sum(c.msgcount for c in imu_conn + image_conn)
            imu_ids = {id(c) for c in imu_conn}
            for done, (conn, bag_t_ns, raw) in enumerate(
                    reader.messages(connections=imu_conn + image_conn), start=1):
                msg = reader.deserialize(raw, conn.msgtype)
                t_ns = _stamp_ns(msg, bag_t_ns, stamps)
                if id(conn) in imu_ids:
                    imu_t.append(t_ns)
                    imu_rows.append(_imu_row(msg, bag, topics.imu, t_ns))
                elif t_ns in seen_frames:
                    duplicate_frames += 1
                else:
                    seen_frames.add(t_ns)
                    name = f"{IMAGE_DIR}/{t_ns}.png"
                    _write_image(msg, images_dir.parent / name, bag, topics.image, t_ns)
                    frame_t.append(t_ns)
                    names.append(name)
                if progress is not None:
                    progress(done, total)
    except SensorDataError:
        raise
    except Exception as exc:  # rosbags' reader errors have no common base worth naming
        if type(exc).__module__.startswith("rosbags"):
            raise SensorDataError(f"{bag}: cannot be read as a ROS bag ({exc}); expected a "
                                  "ROS1 .bag file or a ROS2 bag directory") from None
        raise
    if not imu_t:
        raise SensorDataError(f"{bag}: topic {topics.imu} has no messages; expected IMU samples")
    if not frame_t:
        raise SensorDataError(f"{bag}: topic {topics.image} has no messages; expected images")
    _check_clock(np.asarray(imu_t, dtype=np.int64), bag, topics.imu)
    _check_clock(np.asarray(frame_t, dtype=np.int64), bag, topics.image)
    imu_order = np.argsort(np.asarray(imu_t, dtype=np.int64), kind="stable")
    t_imu = np.asarray(imu_t, dtype=np.int64)[imu_order]
    keep = np.concatenate([[True], np.diff(t_imu) > 0])  # first of each repeated stamp
    rows = np.asarray(imu_rows)[imu_order][keep]
    frame_order = np.argsort(np.asarray(frame_t, dtype=np.int64), kind="stable")
    if stamps is StampSource.HEADER and (t_imu[-1] <= 0 or max(frame_t) <= 0):
        raise SensorDataError(f"{bag}: header stamps are zero; expected stamped messages, or "
                              "--stamps bag to use the recording times")
    return BagContents(
        ImuSamples(t_imu[keep], rows[:, :3], rows[:, 3:]),
        np.asarray(frame_t, dtype=np.int64)[frame_order],
        tuple(names[i] for i in frame_order),
        int((~keep).sum()), duplicate_frames)


#: Sorted by stamp, a topic's samples this much closer than its usual spacing...
DENSE_SPACING = 0.6
#: ...this many steps in a row hold two stretches of the recording at once (a clock that
#: jumped back, a second publisher): jitter makes one short step beside a long one, not
#: a run of them, and a driver's duplicate is one stamp repeated.
DENSE_RUN = 3


def _check_clock(t_ns: np.ndarray, bag: Path, topic: str) -> None:
    """Refuse a topic whose stamps hold two stretches of time at once: stamps repeated, or
    closer than ``DENSE_SPACING`` of the usual spacing, at ``DENSE_RUN`` samples in a row
    (the messages may be recorded in any order: their stamps are put in order)."""
    unique, count = np.unique(t_ns, return_counts=True)
    if unique.size < 2:
        return
    step = np.diff(unique)
    overlap = (count > 1) | np.r_[False, step < DENSE_SPACING * np.median(step)]
    edges = np.flatnonzero(np.diff(np.r_[0, overlap.astype(np.int64), 0]))
    starts, ends = edges[::2], edges[1::2]
    long = np.flatnonzero(ends - starts >= DENSE_RUN)
    if long.size:
        a, b = int(starts[long[0]]), int(ends[long[0]]) - 1
        raise SensorDataError(
            f"{bag}: topic {topic}: the stamps from {int(unique[a])} to {int(unique[b])} ns "
            f"come twice, or at least {1 / DENSE_SPACING:.3g} times as dense as the rest: two "
            "stretches of the recording overlap; expected one clock that does not jump back "
            "(fix the recording, or --stamps bag for the recording times)")


def _connections(reader: Any, bag: Path, topic: str, types: tuple[str, ...],
                 what: str) -> list:
    found = [c for c in reader.connections if c.topic == topic]
    if not found:
        available = ", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in reader.connections))
        raise SensorDataError(f"{bag}: no topic {topic}; expected the {what} topic, one of: "
                              f"{available or 'none (an empty bag)'}")
    wrong = [c.msgtype for c in found if c.msgtype not in types]
    if wrong:
        raise SensorDataError(f"{bag}: topic {topic} holds {wrong[0]}; expected "
                              f"{' or '.join(types)} for the {what} topic")
    return found


def _stamp_ns(msg: Any, bag_t_ns: int, stamps: StampSource) -> int:
    if stamps is StampSource.BAG:
        return int(bag_t_ns)
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _imu_row(msg: Any, bag: Path, topic: str, t_ns: int) -> list[float]:
    # REP 145: -1 as the first covariance element marks a quantity the driver does not give.
    for name in ("angular_velocity", "linear_acceleration"):
        if float(getattr(msg, f"{name}_covariance")[0]) == -1.0:
            raise SensorDataError(f"{bag}: topic {topic} at {t_ns} ns has no {name} "
                                  "(covariance[0] = -1); expected gyro rates and "
                                  "accelerations in every IMU message")
    w, a = msg.angular_velocity, msg.linear_acceleration
    row = [float(w.x), float(w.y), float(w.z), float(a.x), float(a.y), float(a.z)]
    if not all(np.isfinite(row)):
        raise SensorDataError(f"{bag}: topic {topic} at {t_ns} ns has a non-finite value "
                              f"{row}; expected finite rates and accelerations")
    return row


def _write_image(msg: Any, path: Path, bag: Path, topic: str, t_ns: int) -> None:
    from rosbags.image import ImageError, message_to_cvimage

    encoding = getattr(msg, "encoding", None)  # None: a CompressedImage
    color = None if encoding is None or encoding in MONO_ENCODINGS else "bgr8"
    try:
        pixels = message_to_cvimage(msg, color)
    except (ImageError, AssertionError, ValueError, cv2.error) as exc:
        what = f"encoding {encoding}" if encoding else f"format {getattr(msg, 'format', '?')}"
        raise SensorDataError(f"{bag}: topic {topic} at {t_ns} ns: the image ({what}) cannot "
                              f"be decoded ({exc or 'corrupt data'}); expected an image "
                              "rosbags-image converts") from None
    if not cv2.imwrite(str(path), np.ascontiguousarray(pixels)):
        raise SensorDataError(f"{path}: could not write the image")


def import_rosbag(bag: str | os.PathLike, directory: str | os.PathLike,
                  final_dir: str | os.PathLike, settings: ImportSettings, *,
                  camera: CameraCalibration, imu: ImuCalibration, topics: BagTopics = BagTopics(),
                  groundtruth: tuple[States, np.ndarray | None] | None = None,
                  stamps: StampSource = StampSource.HEADER,
                  progress: Callable[[int, int], None] | None = None) -> tuple[FlightLog,
                                                                                BagContents]:
    """Read a bag and write it as a flight log into ``directory`` (a staging directory
    published as ``final_dir``).

    Args:
        bag: a ROS1 ``.bag`` file or a ROS2 bag directory.
        settings: DTM, pixel noise, prior.
        camera: from a Kalibr camchain (:func:`read_kalibr_camchain`).
        imu: from a Kalibr IMU file (:func:`read_kalibr_imu`).
        topics: the topics; None: the calibration files' ``rostopic``.
        groundtruth: ground truth on the IMU clock (:func:`read_groundtruth`), or None.
        stamps: header stamps or recording times.

    Returns:
        The log as written and read back, and what was read from the bag.
    """
    resolved = BagTopics(topics.imu or imu.rostopic, topics.image or camera.rostopic)
    if resolved.imu is None:
        raise SensorDataError("no IMU topic; expected --imu-topic, or rostopic in the Kalibr "
                              "IMU file")
    if resolved.image is None:
        raise SensorDataError("no image topic; expected --image-topic, or rostopic in the "
                              "Kalibr camchain")
    check_prior(settings, groundtruth is not None, str(bag))  # before minutes of reading
    directory = Path(directory)
    contents = read_bag(bag, resolved, directory / IMAGE_DIR, stamps=stamps, progress=progress)
    first = cv2.imread(str(directory / contents.images[0]), cv2.IMREAD_UNCHANGED)
    assert first is not None  # written just now by read_bag
    height, width = first.shape[:2]
    c = camera.camera
    if (width, height) != (c.width, c.height):
        raise SensorDataError(f"{bag}: the images on {resolved.image} are {width}x{height} px "
                              f"but the camchain says {c.width}x{c.height}; expected the "
                              "calibration of this camera")
    truth, bias = groundtruth if groundtruth is not None else (None, None)
    provenance = {"format": "rosbag", "imu_topic": resolved.imu, "image_topic": resolved.image,
                  "stamps": stamps.value}
    recording = SensorRecording(str(bag), contents.imu, contents.frame_t_cam_ns, camera,
                                imu.imu, truth, bias, provenance)
    log = assemble_flightlog(recording, contents.images, settings)
    for name in set(contents.images) - set(log.frames.image):  # outside the IMU's span
        (directory / name).unlink()
    return write_imported_log(log, settings, directory, final_dir), contents
