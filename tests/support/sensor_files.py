"""Sensor recordings written from a flight log, as the field's tools write them: a EuRoC
``mav0`` folder, Kalibr camchain and IMU files, ROS1 and ROS2 bags (with ``rosbags``).

The importers' tests read these back and compare with the log they came from.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from cdtm_graph.camera import DistortionModel
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.geometry import invert_pose

IMU_TOPIC = "/imu0"
IMAGE_TOPIC = "/cam0/image_raw"


def _matrix_rows(T: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in T]


def write_kalibr(log: FlightLog, camchain: Path, imu_yaml: Path, *,
                 timeshift_s: float | None = None) -> None:
    """Kalibr's camchain-imucam and imu files of a log's camera and IMU."""
    cam = log.config.camera
    c = cam.camera
    lens = {DistortionModel.NONE: "none", DistortionModel.RADTAN: "radtan",
            DistortionModel.EQUIDISTANT: "equidistant"}[c.model]
    cam0 = {
        "T_cam_imu": _matrix_rows(invert_pose(cam.body_T_cam)),
        "cam_overlaps": [],
        "camera_model": "pinhole",
        "distortion_coeffs": list(c.distortion) or [0.0, 0.0, 0.0, 0.0],
        "distortion_model": lens if c.distortion else "radtan",
        "intrinsics": [c.fx, c.fy, c.cx, c.cy],
        "resolution": [c.width, c.height],
        "rostopic": IMAGE_TOPIC,
        "timeshift_cam_imu": cam.time_offset_s if timeshift_s is None else timeshift_s,
    }
    camchain.write_text(yaml.safe_dump({"cam0": cam0}, sort_keys=False))
    imu = log.config.imu
    imu0 = {
        "T_i_b": _matrix_rows(np.eye(4)),
        "accelerometer_noise_density": imu.accelerometer_noise_density,
        "accelerometer_random_walk": imu.accelerometer_random_walk,
        "gyroscope_noise_density": imu.gyroscope_noise_density,
        "gyroscope_random_walk": imu.gyroscope_random_walk,
        "model": "calibrated",
        "rostopic": IMU_TOPIC,
        "time_offset": 0.0,
        "update_rate": imu.rate_hz,
    }
    imu_yaml.write_text(yaml.safe_dump({"imu0": imu0}, sort_keys=False))


def write_euroc(log: FlightLog, mav0: Path, *, camera_stamp_shift_ns: int = 0) -> None:
    """A EuRoC ``mav0`` folder of a log (its images and ground truth with zero biases).

    ``camera_stamp_shift_ns`` is added to the camera stamps (a camera clock running ahead).
    """
    for sub in ("imu0", "cam0/data", "state_groundtruth_estimate0"):
        (mav0 / sub).mkdir(parents=True, exist_ok=True)
    imu = log.imu
    rows = np.column_stack([imu.gyro_radps, imu.acc_mps2])
    lines = ["#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
             "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"]
    lines += [",".join([str(t)] + [repr(v) for v in row])
              for t, row in zip(imu.t_ns.tolist(), rows.tolist())]
    (mav0 / "imu0" / "data.csv").write_text("\r\n".join(lines) + "\r\n")  # EuRoC: CRLF
    cam_lines = ["#timestamp [ns],filename"]
    for t, image in zip(log.frames.t_ns.tolist(), log.frames.image):
        stamp = t + camera_stamp_shift_ns
        (mav0 / "cam0" / "data" / f"{stamp}.png").write_bytes((log.root / image).read_bytes())
        cam_lines.append(f"{stamp},{stamp}.png")
    (mav0 / "cam0" / "data.csv").write_text("\r\n".join(cam_lines) + "\r\n")
    c = log.config.camera.camera
    cam_yaml = {
        "sensor_type": "camera", "comment": "written by the tests",
        "T_BS": {"cols": 4, "rows": 4,
                 "data": [float(v) for v in log.config.camera.body_T_cam.ravel()]},
        "rate_hz": 1, "resolution": [c.width, c.height], "camera_model": "pinhole",
        "intrinsics": [c.fx, c.fy, c.cx, c.cy],
        "distortion_model": "radial-tangential",
        "distortion_coefficients": list(c.distortion) or [0.0, 0.0, 0.0, 0.0],
    }
    (mav0 / "cam0" / "sensor.yaml").write_text(
        "# General sensor definitions.\n" + yaml.safe_dump(cam_yaml, sort_keys=False))
    n = log.config.imu
    imu_yaml = {
        "sensor_type": "imu", "comment": "written by the tests",
        "T_BS": {"cols": 4, "rows": 4, "data": [float(v) for v in np.eye(4).ravel()]},
        "rate_hz": n.rate_hz,
        "gyroscope_noise_density": n.gyroscope_noise_density,
        "gyroscope_random_walk": n.gyroscope_random_walk,
        "accelerometer_noise_density": n.accelerometer_noise_density,
        "accelerometer_random_walk": n.accelerometer_random_walk,
    }
    (mav0 / "imu0" / "sensor.yaml").write_text(yaml.safe_dump(imu_yaml, sort_keys=False))
    gt = log.groundtruth
    assert gt is not None
    gt_lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
                "q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
                "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
                "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"]
    values = np.column_stack([gt.position_m, gt.quaternion_wxyz, gt.velocity_mps,
                              np.zeros((len(gt), 6))])
    gt_lines += [",".join([str(t)] + [repr(v) for v in row])
                 for t, row in zip(gt.t_ns.tolist(), values.tolist())]
    (mav0 / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(gt_lines) + "\n")


def write_bag(log: FlightLog, path: Path, ros: int, *, compressed: bool = False,
              shuffle_seed: int | None = None, record_delay_ns: int = 0,
              zero_stamps: bool = False) -> None:
    """A ROS1 ``.bag`` (``ros=1``) or ROS2 bag directory (``ros=2``) of a log's IMU samples
    (``sensor_msgs/Imu``) and images (``sensor_msgs/Image`` mono8, or CompressedImage PNG).

    Messages are written in time order, or with ``shuffle_seed`` in a shuffled order of
    record times (the header stamps stay the sensor times). Each is recorded
    ``record_delay_ns`` after its stamp; ``zero_stamps``: a driver that leaves
    ``header.stamp`` at zero.
    """
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    types = store.types
    Time = types["builtin_interfaces/msg/Time"]
    Header = types["std_msgs/msg/Header"]
    Vector3 = types["geometry_msgs/msg/Vector3"]
    Quaternion = types["geometry_msgs/msg/Quaternion"]
    Imu = types["sensor_msgs/msg/Imu"]
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    ImageMsg = types[image_type]

    def header(t_ns: int, frame_id: str):
        t_ns = 0 if zero_stamps else t_ns
        stamp = Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        if ros == 1:
            return Header(seq=0, stamp=stamp, frame_id=frame_id)
        return Header(stamp=stamp, frame_id=frame_id)

    def serialize(msg, msgtype: str) -> bytes:
        return (store.serialize_ros1(msg, msgtype) if ros == 1
                else store.serialize_cdr(msg, msgtype))

    messages: list[tuple[int, str, bytes]] = []
    zeros = np.zeros(9)
    for t, w, a in zip(log.imu.t_ns.tolist(), log.imu.gyro_radps, log.imu.acc_mps2):
        msg = Imu(header=header(t, "imu"), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                  orientation_covariance=np.array([-1.0] + [0.0] * 8),
                  angular_velocity=Vector3(x=w[0], y=w[1], z=w[2]),
                  angular_velocity_covariance=zeros,
                  linear_acceleration=Vector3(x=a[0], y=a[1], z=a[2]),
                  linear_acceleration_covariance=zeros)
        messages.append((t, "imu", serialize(msg, Imu.__msgtype__)))
    for t, name in zip(log.frames.t_ns.tolist(), log.frames.image):
        pixels = cv2.imread(str(log.root / name), cv2.IMREAD_UNCHANGED)
        if compressed:
            ok, png = cv2.imencode(".png", pixels)
            assert ok
            msg = ImageMsg(header=header(t, "cam0"), format="png",
                           data=np.frombuffer(png.tobytes(), dtype=np.uint8))
        else:
            height, width = pixels.shape[:2]
            msg = ImageMsg(header=header(t, "cam0"), height=height, width=width,
                           encoding="mono8", is_bigendian=0, step=width,
                           data=np.ascontiguousarray(pixels).ravel())
        messages.append((t, "image", serialize(msg, image_type)))
    record_t = np.array([m[0] for m in messages], dtype=np.int64) + record_delay_ns
    order = np.argsort(record_t, kind="stable")
    if shuffle_seed is not None:
        order = np.random.default_rng(shuffle_seed).permutation(len(messages))
        record_t = np.sort(record_t)  # the recorder's times increase; the stamps do not
    writer = Writer1(path) if ros == 1 else Writer2(path, version=9)
    with writer:
        conns = {"imu": writer.add_connection(IMU_TOPIC, Imu.__msgtype__, typestore=store),
                 "image": writer.add_connection(IMAGE_TOPIC, image_type, typestore=store)}
        for i, k in enumerate(order):
            _, kind, raw = messages[k]
            writer.write(conns[kind], int(record_t[i] if shuffle_seed is not None
                                          else record_t[k]), raw)
