"""Importers: a EuRoC folder (with or without Kalibr files) and ROS1/ROS2 bags written from
the rendered sample log read back as that log, and smooth to its result.

The native log is ``cdtm_graph/data/sample_images`` (4 rendered frames, 200 Hz IMU, ground
truth). The tests write its sensor files as EuRoC, Kalibr and ``rosbags`` write them
(:mod:`tests.sensor_files`), import them, and compare: IMU samples and frame times bit for
bit, images pixel for pixel, the calibration, and the smoothed trajectory after tracking.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import cv2
import gtsam
import numpy as np
import pytest
import yaml

from cdtm_graph.cli import main
from cdtm_graph.data import egm96_grid_file, sample_images_path
from cdtm_graph.errors import FlightLogError, SensorDataError
from cdtm_graph.flightlog import FlightLog, read_flightlog, write_tracks
from cdtm_graph.frontend import track_log
from cdtm_graph.geometry import invert_pose
from cdtm_graph.importers import (
    BagTopics,
    DtmSource,
    ImportSettings,
    InitialPrior,
    StampSource,
    import_euroc,
    import_rosbag,
    read_groundtruth,
    read_kalibr_camchain,
    read_kalibr_imu,
)
from cdtm_graph.run.prepare import load_log_and_dtm
from cdtm_graph.smoother import smooth

ROOT = Path(__file__).resolve().parents[2]
NATIVE = sample_images_path()
#: body_T_cam goes through Kalibr's T_cam_imu (inverted twice) or EuRoC's 16 numbers.
MOUNT_TOL = 1e-15
#: The smoothed poses of an imported log against the native log's: the logs differ only in
#: body_T_cam's last bits, so the trajectories agree to rounding (measured: 4.3e-12 m,
#: 2.1e-15 rad; covariances 1.5e-12 relative).
POSITION_TOL_M = 1e-9
ROTATION_TOL_RAD = 1e-12
#: A camera clock 23.4 ms ahead of the IMU (Kalibr: t_imu = t_cam + timeshift_cam_imu).
TIMESHIFT_S = -0.0234


@pytest.fixture(scope="module")
def native() -> FlightLog:
    return read_flightlog(NATIVE, read_tracks=False)


@pytest.fixture(scope="module")
def files(seed, sensor_files, native, tmp_path_factory) -> Path:
    """The native log's sensor files: EuRoC (plain and with a shifted camera clock), Kalibr
    (plain and with the shift), ROS1 and ROS2 bags."""
    root = tmp_path_factory.mktemp("sensor_files")
    sensor_files.write_euroc(native, root / "plain" / "mav0")
    shift_ns = -round(TIMESHIFT_S * 1e9)  # camera stamps = t_imu - timeshift
    sensor_files.write_euroc(native, root / "shifted" / "mav0", camera_stamp_shift_ns=shift_ns)
    sensor_files.write_kalibr(native, root / "camchain.yaml", root / "imu.yaml")
    sensor_files.write_kalibr(native, root / "camchain_shift.yaml", root / "imu_shift.yaml",
                 timeshift_s=TIMESHIFT_S)
    sensor_files.write_bag(native, root / "flight.bag", ros=1)
    sensor_files.write_bag(native, root / "flight_ros2", ros=2)
    sensor_files.write_bag(
        native, root / "shuffled_compressed", ros=2, compressed=True, shuffle_seed=seed
    )
    return root


def _settings(native: FlightLog, prior: InitialPrior | None = None) -> ImportSettings:
    return ImportSettings(DtmSource((native.config.dtm.path,), native.config.dtm.sigma_h_m),
                          native.config.camera.pixel_sigma_px,
                          initial=prior or InitialPrior())


def _native_prior(native: FlightLog) -> InitialPrior:
    s = native.config.initial_state
    return InitialPrior(s.position_m, None, s.quaternion_wxyz, s.velocity_mps, s.gyro_bias,
                        s.accel_bias)


def _import(kind: str, files: Path, out: Path, settings: ImportSettings) -> FlightLog:
    out.mkdir()
    if kind == "euroc":
        return import_euroc(files / "plain", out, out, settings)
    if kind == "euroc_kalibr":
        return import_euroc(files / "shifted" / "mav0", out, out, settings,
                            kalibr=files / "camchain_shift.yaml",
                            kalibr_imu=files / "imu_shift.yaml")
    bag = {"ros1": "flight.bag", "ros2": "flight_ros2",
           "ros2_shuffled_compressed": "shuffled_compressed"}[kind]
    truth = read_groundtruth(NATIVE / "groundtruth.csv", None)
    log, _ = import_rosbag(files / bag, out, out, settings,
                           camera=read_kalibr_camchain(files / "camchain.yaml"),
                           imu=read_kalibr_imu(files / "imu.yaml"), groundtruth=truth)
    return log


KINDS = ("euroc", "euroc_kalibr", "ros1", "ros2", "ros2_shuffled_compressed")


@pytest.mark.parametrize("kind", KINDS)
def test_an_import_reads_back_as_the_native_log(kind, native, files, tmp_path):
    log = _import(kind, files, tmp_path / "log", _settings(native))
    assert log.imu == native.imu                      # bit for bit
    np.testing.assert_array_equal(log.frames.t_ns, native.frames.t_ns)  # on the IMU clock
    assert log.groundtruth == native.groundtruth
    assert log.config.camera.camera == native.config.camera.camera
    assert log.config.imu == native.config.imu
    np.testing.assert_allclose(log.config.camera.body_T_cam, native.config.camera.body_T_cam,
                               rtol=0, atol=MOUNT_TOL)
    for ours, theirs in zip(log.frames.image, native.frames.image):
        mine = cv2.imread(str(log.root / ours), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(mine, cv2.imread(str(NATIVE / theirs),
                                                       cv2.IMREAD_UNCHANGED))
    # Without a prior on the command line the initial state is the ground truth at frame 0.
    truth = native.groundtruth.interpolate(native.frames.t_ns[0])
    init = log.config.initial_state
    np.testing.assert_array_equal(init.position_m, truth.position_m[0])
    np.testing.assert_array_equal(init.quaternion_wxyz, truth.quaternion_wxyz[0])
    np.testing.assert_array_equal(init.velocity_mps, truth.velocity_mps[0])
    assert log.tracks is None and not (log.root / "tracks.csv").exists()


def test_kalibr_timeshift_becomes_the_time_offset_and_frames_csv_keeps_camera_stamps(
        native, files, tmp_path):
    log = _import("euroc_kalibr", files, tmp_path / "log", _settings(native))
    assert log.config.camera.time_offset_s == TIMESHIFT_S
    stamps = [int(line.split(",")[0]) for line in
              (tmp_path / "log" / "frames.csv").read_text().splitlines()[1:]]
    assert stamps == (native.frames.t_ns - round(TIMESHIFT_S * 1e9)).tolist()
    np.testing.assert_array_equal(log.frame_t_cam_ns, stamps)
    assert "time_offset_s: -0.0234" in (tmp_path / "log" / "flight.yaml").read_text()


def test_kalibr_files_read_as_their_names_say(sensor_files, native, files):
    cam = read_kalibr_camchain(files / "camchain_shift.yaml")
    chain = yaml.safe_load((files / "camchain_shift.yaml").read_text())["cam0"]
    np.testing.assert_allclose(invert_pose(cam.body_T_cam), chain["T_cam_imu"], rtol=0,
                               atol=1e-15)
    assert cam.time_offset_s == chain["timeshift_cam_imu"] == TIMESHIFT_S
    assert cam.rostopic == sensor_files.IMAGE_TOPIC
    imu = read_kalibr_imu(files / "imu.yaml")
    assert imu.imu.rate_hz == 200.0 and imu.rostopic == sensor_files.IMU_TOPIC
    assert imu.imu == native.config.imu


@pytest.fixture(scope="module")
def native_smoothed(native):
    """The native log tracked (images -> tracks) and smoothed."""
    tracks = track_log(native).tracks
    flight, dtm = load_log_and_dtm(NATIVE)
    flight = dataclasses.replace(flight, tracks=tracks)
    return tracks, smooth(flight, dtm)


@pytest.mark.parametrize("kind", ("euroc_kalibr", "ros1", "ros2"))
def test_an_import_smooths_to_the_native_result(kind, native, files, native_smoothed,
                                                tmp_path):
    log = _import(kind, files, tmp_path / "log", _settings(native, _native_prior(native)))
    tracked = track_log(log).tracks
    native_tracks, native_result = native_smoothed
    assert tracked == native_tracks  # same images, same gyro: the same tracks
    write_tracks(tracked, log.root / "tracks.csv")
    flight, dtm = load_log_and_dtm(log.root)
    result = smooth(flight, dtm)
    assert result.counts.n_cdtm_features == native_result.counts.n_cdtm_features > 100
    for ours, theirs in zip(result.estimate.world_T_body, native_result.estimate.world_T_body):
        xi = gtsam.Pose3(theirs).localCoordinates(gtsam.Pose3(ours))
        assert np.abs(xi[:3]).max() < ROTATION_TOL_RAD and np.abs(xi[3:]).max() < POSITION_TOL_M
    np.testing.assert_allclose(result.covariances.pose, native_result.covariances.pose,
                               rtol=1e-9, atol=1e-15)


# --------------------------------------------------------------------------- the CLI


def test_cli_imports_tracks_and_the_log_smooths(native, files, tmp_path, capsys):
    out = tmp_path / "imported"
    code = main(["import", "rosbag", str(files / "flight.bag"), "--kalibr",
                 str(files / "camchain.yaml"), "--kalibr-imu", str(files / "imu.yaml"),
                 "--dtm", str(native.config.dtm.path), "--copy-dtm", "--out", str(out),
                 "--groundtruth", str(NATIVE / "groundtruth.csv"), "--track", "--quiet"])
    assert code == 0
    manifest = (out / ".cdtm-run.json").read_text()
    assert '"images/1000000000.png": "import rosbag"' in manifest
    assert '"tracks.csv": "import rosbag"' in manifest and '"dtm.npz"' in manifest
    assert main(["smooth", str(out), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    assert (tmp_path / "run" / "trajectory.tum").is_file()
    # A rerun replaces the import's own files, tracks.csv included.
    assert main(["import", "rosbag", str(files / "flight.bag"), "--kalibr",
                 str(files / "camchain.yaml"), "--kalibr-imu", str(files / "imu.yaml"),
                 "--dtm", str(native.config.dtm.path), "--out", str(out), "--quiet",
                 "--groundtruth", str(NATIVE / "groundtruth.csv")]) == 0
    assert not (out / "tracks.csv").exists() and not (out / "dtm.npz").exists()


def test_cli_says_what_comes_next_and_refuses_foreign_tracks(native, files, tmp_path, capsys):
    out = tmp_path / "log"
    args = ["import", "euroc", str(files / "plain"), "--dtm", str(native.config.dtm.path),
            "--out", str(out)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert f"next: cdtm track {out}" in printed and "ground truth" in printed
    assert main(["track", str(out), "--quiet"]) == 0
    assert main(args) == 1  # cdtm track's tracks.csv would not match a new import
    assert "holds tracks.csv that this import did not write" in capsys.readouterr().err
    assert (out / "tracks.csv").is_file()
    (out / "tracks.csv").unlink()
    (out / "nav.csv").write_text("#t_ns,px,py,pz,qw,qx,qy,qz,vx,vy,vz\n")  # by hand
    assert main(args + ["--force"]) == 1  # not even with --force: it would be read too
    assert "holds nav.csv" in capsys.readouterr().err


def test_cli_names_the_missing_initial_state(native, files, tmp_path, capsys):
    args = ["import", "rosbag", str(files / "flight_ros2"), "--kalibr",
            str(files / "camchain.yaml"), "--kalibr-imu", str(files / "imu.yaml"),
            "--dtm", str(native.config.dtm.path), "--out", str(tmp_path / "log"),
            "--initial-quaternion", "1", "0", "0", "0"]
    assert main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("cdtm import: error: ") and "--initial-position X Y Z" in err
    assert "--initial-velocity" in err and "--initial-quaternion" not in err
    assert not (tmp_path / "log").exists()


# --------------------------------------------------------------------------- bad input


def test_a_missing_topic_lists_the_bag_s_topics(native, files, tmp_path):
    with pytest.raises(SensorDataError, match=r"no topic /cam1.*/cam0/image_raw"):
        import_rosbag(files / "flight.bag", tmp_path, tmp_path, _settings(native),
                      camera=read_kalibr_camchain(files / "camchain.yaml"),
                      imu=read_kalibr_imu(files / "imu.yaml"),
                      topics=BagTopics(image="/cam1"),
                      groundtruth=read_groundtruth(NATIVE / "groundtruth.csv", None))


def test_a_topic_of_the_wrong_type_is_refused(sensor_files, native, files, tmp_path):
    with pytest.raises(SensorDataError, match="holds sensor_msgs/msg/Image; expected "
                                              "sensor_msgs/msg/Imu"):
        import_rosbag(files / "flight.bag", tmp_path, tmp_path, _settings(native),
                      camera=read_kalibr_camchain(files / "camchain.yaml"),
                      imu=read_kalibr_imu(files / "imu.yaml"),
                      topics=BagTopics(imu=sensor_files.IMAGE_TOPIC),
                      groundtruth=read_groundtruth(NATIVE / "groundtruth.csv", None))


def test_a_camchain_of_another_camera_size_is_refused(native, files, tmp_path):
    chain = yaml.safe_load((files / "camchain.yaml").read_text())
    chain["cam0"]["resolution"] = [640, 480]
    (tmp_path / "chain.yaml").write_text(yaml.safe_dump(chain))
    with pytest.raises(SensorDataError, match="320x240 px but the camchain says 640x480"):
        import_rosbag(files / "flight.bag", tmp_path / "out", tmp_path / "out",
                      _settings(native), camera=read_kalibr_camchain(tmp_path / "chain.yaml"),
                      imu=read_kalibr_imu(files / "imu.yaml"),
                      groundtruth=read_groundtruth(NATIVE / "groundtruth.csv", None))


def _camchain_line(path: Path, key: str) -> int:
    return next(i for i, line in enumerate(path.read_text().splitlines(), start=1)
                if line.strip().startswith(key))


@pytest.mark.parametrize("key, value, words", [
    ("distortion_model:", "fov", ("distortion_model 'fov' is not supported", "equidistant")),
    ("camera_model:", "omni", ("camera_model 'omni' is not supported", "pinhole")),
    ("timeshift_cam_imu:", "30.0", ("camera.time_offset_s is 30.0", "[-10, 10] s")),
])
def test_bad_camchain_values_name_the_line(files, tmp_path, key, value, words):
    path = tmp_path / "chain.yaml"
    shutil.copyfile(files / "camchain.yaml", path)
    line = _camchain_line(path, key)
    lines = path.read_text().splitlines()
    lines[line - 1] = f"  {key} {value}"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(FlightLogError) as info:
        read_kalibr_camchain(path)
    message = str(info.value)
    assert message.startswith(f"{path}:{line}: ") and "; expected " in message
    assert all(word in message for word in words), message


def test_a_t_cam_imu_that_is_not_a_rotation_names_its_line(files, tmp_path):
    chain = yaml.safe_load((files / "camchain.yaml").read_text())
    chain["cam0"]["T_cam_imu"][0][0] *= 1.01  # a scaled axis: not a rotation
    path = tmp_path / "chain.yaml"
    path.write_text(yaml.safe_dump(chain, sort_keys=False))
    line = _camchain_line(path, "T_cam_imu:") + 1  # the matrix starts on the next line
    with pytest.raises(FlightLogError, match=rf"chain.yaml:{line}: cam0.T_cam_imu's rotation "
                                             "is not a rotation"):
        read_kalibr_camchain(path)


def test_euroc_names_the_row_of_a_missing_image(native, files, tmp_path):
    shutil.copytree(files / "plain" / "mav0", tmp_path / "mav0")
    victim = sorted((tmp_path / "mav0" / "cam0" / "data").iterdir())[2]
    victim.unlink()
    with pytest.raises(FlightLogError, match=rf"cam0/data.csv:4: image '{victim.name}' does "
                                             "not exist"):
        import_euroc(tmp_path / "mav0", tmp_path / "out", tmp_path / "out", _settings(native))


def test_euroc_initial_state_outside_the_ground_truth_needs_the_flags(native, files, tmp_path):
    shutil.copytree(files / "plain" / "mav0", tmp_path / "mav0")
    gt = tmp_path / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:1] + lines[3:]) + "\n")  # starts 0.2 s after frame 0
    (tmp_path / "out").mkdir()
    with pytest.raises(SensorDataError, match=r"initial state at the first frame \(t_ns 0 on "
                                              r"the IMU clock\) is unknown \(the ground truth "
                                              r"spans 200000000\.\.3000000000 ns\)"):
        import_euroc(tmp_path / "mav0", tmp_path / "out", tmp_path / "out", _settings(native))
    prior = InitialPrior(position_m=[1.0, 2.0, 1000.0], quaternion_wxyz=[1.0, 0, 0, 0],
                         velocity_mps=[190.0, -50.0, 0.0])
    log = import_euroc(tmp_path / "mav0", tmp_path / "out", tmp_path / "out",
                       _settings(native, prior))
    np.testing.assert_array_equal(log.config.initial_state.position_m, [1.0, 2.0, 1000.0])


def test_an_imu_without_accelerations_is_refused(sensor_files, native, tmp_path):
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    t = store.types
    msg = t["sensor_msgs/msg/Imu"](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                        frame_id="imu"),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9),
        angular_velocity=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        linear_acceleration_covariance=np.array([-1.0] + [0.0] * 8))
    with Writer(tmp_path / "bag", version=9) as writer:
        conn = writer.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=store)
        writer.write(conn, 1, store.serialize_cdr(msg, "sensor_msgs/msg/Imu"))
        writer.add_connection(sensor_files.IMAGE_TOPIC, "sensor_msgs/msg/Image", typestore=store)
    from cdtm_graph.importers import read_bag

    with pytest.raises(SensorDataError, match="has no linear_acceleration"):
        read_bag(
            tmp_path / "bag",
            BagTopics(sensor_files.IMU_TOPIC, sensor_files.IMAGE_TOPIC),
            tmp_path / "images",
        )


def test_without_rosbags_the_error_says_what_to_install(sensor_files, monkeypatch, tmp_path):
    import sys

    from cdtm_graph.importers import read_bag

    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(SensorDataError, match=r'pip install "cdtm-graph\[rosbag\]"'):
        read_bag(
            tmp_path / "bag",
            BagTopics(sensor_files.IMU_TOPIC, sensor_files.IMAGE_TOPIC),
            tmp_path / "images",
        )


def test_a_geodetic_import_places_the_prior_by_latitude_and_longitude(native, files, tmp_path):
    from cdtm_graph.geodesy import GeodeticOrigin, VerticalDatum, local_frame, normal_gravity_mps2

    origin = GeodeticOrigin(36.5, 127.25, 120.0)
    dem = egm96_grid_file()  # any EPSG:4326 GeoTIFF will do here
    start = (36.501, 127.249, 1100.0)
    quat_enu = np.array([0.9914448613738104, 0.0, 0.0, -0.13052619222005157])
    prior = InitialPrior(geodetic=start, quaternion_wxyz=quat_enu,
                         velocity_mps=[193.0, -51.8, 0.0])
    settings = ImportSettings(DtmSource((dem,), None, origin, VerticalDatum.EGM96),
                              initial=prior)
    shutil.copytree(files / "plain" / "mav0", tmp_path / "mav0")
    shutil.rmtree(tmp_path / "mav0" / "state_groundtruth_estimate0")
    log = import_euroc(tmp_path / "mav0", tmp_path / "out", tmp_path / "out", settings)
    assert log.config.origin == origin
    assert log.config.gravity_mps2 == pytest.approx(float(normal_gravity_mps2(36.5, 120.0)),
                                                    abs=1e-12)
    position = local_frame(origin).geodetic_to_world(*[np.array([v]) for v in start])[0]
    np.testing.assert_allclose(log.config.initial_state.position_m, position, atol=1e-6)
    assert "vertical_datum: egm96" in (tmp_path / "out" / "flight.yaml").read_text()


def test_euroc_coefficients_without_a_model_are_refused(native, files, tmp_path):
    shutil.copytree(files / "plain" / "mav0", tmp_path / "mav0")
    path = tmp_path / "mav0" / "cam0" / "sensor.yaml"
    sensor = yaml.safe_load(path.read_text())
    del sensor["distortion_model"]
    sensor["distortion_coefficients"] = [-0.28, 0.07, 0.0002, 0.00002]
    path.write_text(yaml.safe_dump(sensor, sort_keys=False))
    with pytest.raises(FlightLogError, match=r"sensor.yaml:\d+: distortion_coefficients "
                                             "without a distortion_model"):
        import_euroc(tmp_path / "mav0", tmp_path / "out", tmp_path / "out", _settings(native))


def test_frames_before_the_imu_starts_are_left_out(sensor_files, native, files, tmp_path):
    late = dataclasses.replace(native, imu=dataclasses.replace(
        native.imu, t_ns=native.imu.t_ns[300:], gyro_radps=native.imu.gyro_radps[300:],
        acc_mps2=native.imu.acc_mps2[300:]))  # the IMU starts at 1.5 s
    sensor_files.write_bag(late, tmp_path / "late.bag", ros=1)
    log, contents = import_rosbag(
        tmp_path / "late.bag", tmp_path / "out", tmp_path / "out", _settings(native),
        camera=read_kalibr_camchain(files / "camchain.yaml"),
        imu=read_kalibr_imu(files / "imu.yaml"),
        groundtruth=read_groundtruth(NATIVE / "groundtruth.csv", None))
    assert len(contents.images) == 4
    np.testing.assert_array_equal(log.frames.t_ns, native.frames.t_ns[2:])
    assert sorted(p.name for p in (tmp_path / "out" / "images").iterdir()) == [
        "2000000000.png", "3000000000.png"]
    assert log.config.extra["import"]["frames_outside_imu"] == 2
    truth = native.groundtruth.interpolate(native.frames.t_ns[2])
    np.testing.assert_array_equal(log.config.initial_state.position_m, truth.position_m[0])


def test_recording_times_on_request_and_zero_stamps_refused(sensor_files, native, files, tmp_path):
    delay_ns = 5_000_000  # the recorder gets each message 5 ms after its stamp
    sensor_files.write_bag(native, tmp_path / "late.bag", ros=1, record_delay_ns=delay_ns)
    kwargs = dict(camera=read_kalibr_camchain(files / "camchain.yaml"),
                  imu=read_kalibr_imu(files / "imu.yaml"),
                  groundtruth=read_groundtruth(NATIVE / "groundtruth.csv", None))
    header, _ = import_rosbag(tmp_path / "late.bag", tmp_path / "a", tmp_path / "a",
                              _settings(native), **kwargs)
    recorded, _ = import_rosbag(tmp_path / "late.bag", tmp_path / "b", tmp_path / "b",
                                _settings(native), stamps=StampSource.BAG, **kwargs)
    np.testing.assert_array_equal(header.frames.t_ns, native.frames.t_ns)
    np.testing.assert_array_equal(recorded.frames.t_ns, native.frames.t_ns + delay_ns)
    np.testing.assert_array_equal(recorded.imu.t_ns, native.imu.t_ns + delay_ns)
    sensor_files.write_bag(native, tmp_path / "unstamped.bag", ros=1, zero_stamps=True)
    with pytest.raises(SensorDataError, match="header stamps are zero.*--stamps bag"):
        import_rosbag(tmp_path / "unstamped.bag", tmp_path / "c", tmp_path / "c",
                      _settings(native), **kwargs)


# --------------------------------------------------------------------------- damaged DTM


def _damaged_dtm(native: FlightLog, tmp_path: Path, kind: str) -> Path:
    """The native DTM cut in half (.npz), or as an .asc whose header claims 10^11 columns."""
    if kind == "npz":
        data = native.config.dtm.path.read_bytes()
        path = tmp_path / "dtm.npz"
        path.write_bytes(data[: len(data) // 2])
        return path
    path = tmp_path / "dtm.asc"
    path.write_text("ncols 99999999999\nnrows 2\nxllcenter 0\nyllcenter 0\ncellsize 30\n"
                    "1 2 3\n4 5 6\n")
    return path


@pytest.mark.parametrize("source, kind, copy", [
    ("euroc", "npz", True), ("euroc", "npz", False), ("euroc", "asc", False),
    ("rosbag", "npz", True)])
def test_an_unreadable_dtm_fails_the_import_and_publishes_nothing(native, files, tmp_path,
                                                                  capsys, source, kind, copy):
    dtm = _damaged_dtm(native, tmp_path, kind)
    out = tmp_path / "imported"
    args = (["import", "euroc", str(files / "plain")] if source == "euroc" else
            ["import", "rosbag", str(files / "flight.bag"), "--kalibr",
             str(files / "camchain.yaml"), "--kalibr-imu", str(files / "imu.yaml"),
             "--groundtruth", str(NATIVE / "groundtruth.csv")])
    code = main(args + ["--dtm", str(dtm), "--out", str(out), "--quiet"]
                + (["--copy-dtm"] if copy else []))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"cdtm import: error: {dtm}: "), err[0]
    assert ("not a readable .npz archive (File is not a zip file)" if kind == "npz" else
            "line 6: 3 values, expected ncols = 99999999999") in err[0]
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [dtm.name]  # no staging left


def test_an_unreadable_image_met_by_track_is_named_as_the_user_s_file(files, native, tmp_path,
                                                                      capsys):
    mav0 = tmp_path / "mav0"
    shutil.copytree(files / "plain" / "mav0", mav0)
    image = mav0 / "cam0" / "data" / "2000000000.png"  # not the first: read for its size
    image.write_bytes(image.read_bytes()[:300])
    out = tmp_path / "imported"
    code = main(["import", "euroc", str(mav0), "--dtm", str(native.config.dtm.path),
                 "--out", str(out), "--track", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"cdtm import: error: {image}: cannot be read as an image"), err[0]
    assert "staging" not in err[0]
    assert not out.exists()


@pytest.mark.parametrize("back_ns", [402_500_000, 400_000_000], ids=["between", "on"])
def test_an_imu_clock_that_jumps_back_is_refused(sensor_files, native, tmp_path, back_ns):
    """The IMU driver's clock jumps back 0.4 s a third of the way in: the stamps after the
    jump fall between the earlier ones (0.4025 s) or on them (0.4 s). Either way two
    stretches of the flight overlap: one line, nothing imported. Jitter and a lone
    repeated stamp stay accepted (the other tests' bags, a shuffled one among them).
    Mutation tried: the check off (the samples were merged in stamp order, exit 0, or
    read as 80 harmless repeats: a hostile-input hunt's find, 2026-11-28)."""
    from cdtm_graph.importers import read_bag

    t = native.imu.t_ns.copy()
    t[len(t) // 3:] -= back_ns
    jumped = dataclasses.replace(native, imu=dataclasses.replace(native.imu, t_ns=t))
    sensor_files.write_bag(jumped, tmp_path / "jump.bag", ros=1)
    with pytest.raises(SensorDataError, match=r"topic /imu0: the stamps from \d+ to \d+ ns "
                                              r"come twice, or .* two stretches of the "
                                              r"recording overlap"):
        read_bag(tmp_path / "jump.bag",
                 BagTopics(sensor_files.IMU_TOPIC, sensor_files.IMAGE_TOPIC), tmp_path / "images")


def test_euroc_names_the_row_of_an_image_named_twice(native, files, tmp_path):
    """Two rows of cam0/data.csv naming one image file: one line naming both rows.
    Mutation tried: the check off (a traceback, "Frames: N times but N-1 images": a
    hostile-input hunt's find, 2026-11-28)."""
    shutil.copytree(files / "plain" / "mav0", tmp_path / "mav0")
    csv_path = tmp_path / "mav0" / "cam0" / "data.csv"
    lines = csv_path.read_text().splitlines()
    stamp, _ = lines[3].split(",", 1)
    lines[3] = f"{stamp},{lines[2].split(',', 1)[1]}"  # row 4 names row 3's image
    csv_path.write_text("\n".join(lines) + "\n")
    with pytest.raises(FlightLogError, match=r"cam0/data.csv:4: image '.*' is named again "
                                             r"\(first on line 3\)"):
        import_euroc(tmp_path / "mav0", tmp_path / "out", tmp_path / "out", _settings(native))


def test_a_camchain_value_the_log_refuses_says_nothing_was_written(native, files, tmp_path):
    """A camchain whose cx lies far off the image (1e6 px): refused when the log it would
    write is read back, naming that log's flight.yaml line and saying it was never
    written. Mutation tried: the note left out (the message named a flight.yaml that does
    not exist: a hostile-input hunt's find, 2026-11-28)."""
    chain = tmp_path / "chain.yaml"
    text = (files / "camchain_shift.yaml").read_text()
    data = yaml.safe_load(text)
    data["cam0"]["intrinsics"][2] = 1e6
    chain.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(FlightLogError, match=r"flight\.yaml:\d+: camera\.intrinsics cx .*"
                                             r"\(in the log the import would write from its "
                                             r"inputs: nothing was written\)"):
        import_euroc(files / "shifted" / "mav0", out, out, _settings(native), kalibr=chain,
                     kalibr_imu=files / "imu_shift.yaml")


def test_an_imu_rate_the_samples_do_not_have_is_said_at_import(native, files, tmp_path,
                                                                 capsys):
    """The IMU's sensor.yaml states half the samples' rate: the import writes it (the
    calibration file's word) and says on stderr, with --quiet too, that the samples come at
    another rate, as the verdict's imu_rate_mismatch will. Mutation tried: the warning off
    (nothing said until a smoothing run's verdict: a hostile-input hunt's find,
    2026-11-28)."""
    shutil.copytree(files / "plain", tmp_path / "euroc")
    sensor = next((tmp_path / "euroc").rglob("imu0/sensor.yaml"))
    data = yaml.safe_load(sensor.read_text())
    stated = data["rate_hz"] / 2
    data["rate_hz"] = stated
    sensor.write_text(yaml.safe_dump(data))
    out = tmp_path / "log"
    assert main(["import", "euroc", str(tmp_path / "euroc"), "--dtm",
                 str(native.config.dtm.path), "--out", str(out), "--quiet"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(err) == 1 and f"imu.rate_hz {stated:g}" in err[0]
    assert "flight.yaml: IMU: samples come at" in err[0]
