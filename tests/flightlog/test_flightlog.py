"""Tests of cdtm_graph.flightlog: round trip, EuRoC files, and every malformed case.

Every malformed-log test asserts that the error names the file and the line
(``"<file>:<line>:"``) and says what was expected.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from cdtm_graph.camera import DistortionModel, PinholeCamera
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import (
    CameraConfig,
    DtmConfig,
    FlightConfig,
    FlightLog,
    Frames,
    ImuSamples,
    InitialState,
    States,
    Tracks,
    read_flightlog,
    write_flightlog,
)
from cdtm_graph.flightlog import tables as fl
from cdtm_graph.geometry import make_pose, quat_wxyz_to_rotation, so3_exp, so3_log

ROTATION_ROUND_TRIP_TOL = 1e-15  # body_T_cam is stored as a quaternion
ANGLE_TOL_RAD = 1e-12


# --------------------------------------------------------------------------- fixtures


@pytest.fixture
def log(small_log: FlightLog) -> FlightLog:
    """The small valid log of ``tests/support/flightlogs.py``, written with its DTM."""
    return small_log


# --------------------------------------------------------------------------- round trip


def test_round_trip_is_exact(flightlog_files, log: FlightLog) -> None:
    back = read_flightlog(log.root)
    assert back == log
    # Spot checks that equality really compares contents (and int64 times survive).
    assert back.imu.t_ns.dtype == np.int64 and back.imu.t_ns[0] == flightlog_files.T0_NS
    assert np.array_equal(back.groundtruth.quaternion_wxyz, log.groundtruth.quaternion_wxyz)
    assert back.config.extra == {"aircraft": "test", "notes": {"anything": [1, 2.5, "x"]}}
    assert back.config.dtm.path == log.root / "dtm.npz"


def test_equality_notices_a_one_ulp_change(log: FlightLog) -> None:
    gyro = log.imu.gyro_radps.copy()
    gyro[3, 1] = np.nextafter(gyro[3, 1], np.inf)
    changed = ImuSamples(log.imu.t_ns, gyro, log.imu.acc_mps2)
    assert changed != log.imu
    assert FlightLog(log.root, log.config, changed, log.frames, log.tracks, log.nav,
                     log.groundtruth) != log


def test_written_files_have_euroc_style_headers(flightlog_files, log: FlightLog) -> None:
    assert (
        flightlog_files.text_lines(log.root / "imu.csv")[0]
        == "#t_ns,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z"
    )
    assert flightlog_files.text_lines(log.root / "frames.csv")[0] == "#t_ns,image"
    assert flightlog_files.text_lines(log.root / "tracks.csv")[0] == "#frame,track_id,u,v"
    assert (
        flightlog_files.text_lines(log.root / "nav.csv")[0] == "#t_ns,px,py,pz,qw,qx,qy,qz,vx,vy,vz"
    )
    assert flightlog_files.text_lines(log.root / "imu.csv")[1].startswith(
        f"{flightlog_files.T0_NS},"
    )
    assert (log.root / "flight.yaml").read_text().startswith("format: cdtm-flightlog/1\n")


def test_optional_files_absent_read_as_none(flightlog_files, tmp_path: Path, rng) -> None:
    the_log = flightlog_files.make_log(tmp_path / "log", rng)
    images = tuple(f"images/{k}.png" for k in range(flightlog_files.N_FRAMES))
    bare = FlightLog(the_log.root, the_log.config, the_log.imu,
                     Frames(the_log.frames.t_ns, images))
    write_flightlog(bare, bare.root)
    flightlog_files.write_dtm(bare.root / "dtm.npz")
    (bare.root / "images").mkdir()
    for name in images:
        (bare.root / name).write_bytes(b"")
    back = read_flightlog(bare.root)
    assert back == bare
    assert back.tracks is None and back.nav is None and back.groundtruth is None


def test_general_body_T_cam_rotation_round_trips_to_rounding(
    flightlog_files, tmp_path: Path, rng
) -> None:
    the_log = flightlog_files.make_log(tmp_path / "log", rng)
    body_T_cam = make_pose(so3_exp(np.array([0.3, -1.1, 2.0])), [0.1, 0.2, 0.3])
    cfg = the_log.config
    camera = CameraConfig(cfg.camera.camera, cfg.camera.pixel_sigma_px, body_T_cam)
    config = FlightConfig(cfg.gravity_mps2, cfg.dtm, camera, cfg.imu, cfg.initial_state)
    write_flightlog(FlightLog(the_log.root, config, the_log.imu, the_log.frames, the_log.tracks),
                    the_log.root)
    flightlog_files.write_dtm(the_log.root / "dtm.npz")
    back = read_flightlog(the_log.root).config.camera.body_T_cam
    assert np.max(np.abs(back - body_T_cam)) <= ROTATION_ROUND_TRIP_TOL
    assert np.array_equal(back[:3, 3], body_T_cam[:3, 3])


# --------------------------------------------------------------------------- writer


def test_write_into_a_directory_holding_the_dtm_removes_stale_log_files(
    flightlog_files, log: FlightLog
) -> None:
    assert (log.root / "tracks.csv").exists()
    images = tuple(f"{k}.png" for k in range(flightlog_files.N_FRAMES))
    for name in images:
        (log.root / name).write_bytes(b"")
    smaller = FlightLog(log.root, log.config, log.imu, Frames(log.frames.t_ns, images))
    write_flightlog(smaller, log.root)
    assert not (log.root / "tracks.csv").exists()  # a stale one would be read as this log's
    assert not (log.root / "groundtruth.csv").exists()
    assert (log.root / "dtm.npz").exists()  # not the writer's file: left alone
    assert read_flightlog(log.root) == smaller
    assert [p.name for p in log.root.parent.iterdir()] == ["log"]  # no staging left


def test_write_failure_leaves_nothing_behind(flightlog_files, tmp_path: Path, rng) -> None:
    the_log = flightlog_files.make_log(tmp_path / "log", rng)
    cfg = the_log.config
    bad = FlightConfig(cfg.gravity_mps2, cfg.dtm, cfg.camera, cfg.imu, cfg.initial_state,
                       extra={"not yaml": object()})
    with pytest.raises(Exception):  # noqa: B017 - PyYAML's own error type
        write_flightlog(FlightLog(the_log.root, bad, the_log.imu, the_log.frames), the_log.root)
    assert list(tmp_path.iterdir()) == []


def test_dtm_outside_the_log_is_written_absolute(flightlog_files, tmp_path: Path, rng) -> None:
    the_log = flightlog_files.make_log(tmp_path / "log", rng)
    outside = tmp_path / "terrain" / "dem.npz"
    outside.parent.mkdir()
    flightlog_files.write_dtm(outside)
    cfg = the_log.config
    config = FlightConfig(cfg.gravity_mps2, DtmConfig(outside), cfg.camera, cfg.imu,
                          cfg.initial_state)
    written = FlightLog(the_log.root, config, the_log.imu, the_log.frames, the_log.tracks)
    write_flightlog(written, the_log.root)
    assert f"path: {outside}" in (the_log.root / "flight.yaml").read_text()
    back = read_flightlog(the_log.root)
    assert back.config.dtm == DtmConfig(outside, None, (0.0, 0.0, 0.0))


# --------------------------------------------------------------------------- CSV dialects


EUROC_IMU = """\
#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],\
a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]
1403636579758555392,-0.099134701513277898,0.14730578886832138,0.02722713633111154,\
8.1476917083333333,-0.37592158333333331,-2.4026292499999999
1403636579763555584,-0.099134701513277898,0.14032447186034408,0.029321531433504278,\
8.033280791666666,-0.40861041666666664,-2.4026292499999999
1403636579768555520,-0.098436569812480182,0.12775810124598494,0.037699111843077518,\
7.8861810416666662,-0.42495483333333334,-2.4844780833333332
"""
EUROC_CAM = """\
#timestamp [ns],filename
1403636579763555584,1403636579763555584.png
1403636579813555456,1403636579813555456.png
"""
EUROC_GROUNDTRUTH = """\
#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], \
q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], \
b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], \
b_a_RS_S_z [m s^-2]
1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152,\
-0.027876,0.033207,0.800006,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593
1403636580843555328,4.688177,-1.786770,0.787350,0.534640,-0.152990,-0.826976,-0.082863,\
-0.029272,0.033992,0.804771,-0.003172,0.021267,0.078502,-0.025266,0.136696,0.075593
"""


@pytest.mark.parametrize("newline", ["\n", "\r\n"], ids=["lf", "crlf"])
def test_euroc_files_copied_in_as_they_are(log: FlightLog, newline: str) -> None:
    root = log.root
    for name, text in (("imu.csv", EUROC_IMU), ("frames.csv", EUROC_CAM),
                       ("groundtruth.csv", EUROC_GROUNDTRUTH)):
        (root / name).write_bytes(text.replace("\n", newline).encode())
    (root / "tracks.csv").unlink()
    (root / "nav.csv").unlink()
    for line in EUROC_CAM.splitlines()[1:]:
        (root / line.split(",")[1]).write_bytes(b"")  # frames name images: they must exist

    back = read_flightlog(root)
    assert back.imu.t_ns.tolist() == [1403636579758555392, 1403636579763555584,
                                      1403636579768555520]
    assert back.imu.gyro_radps[0].tolist() == [-0.099134701513277898, 0.14730578886832138,
                                               0.02722713633111154]
    assert back.imu.acc_mps2[2, 2] == -2.4844780833333332
    assert back.frames.image == ("1403636579763555584.png", "1403636579813555456.png")
    gt = back.groundtruth
    assert gt.t_ns.tolist() == [1403636580838555648, 1403636580843555328]
    assert gt.position_m[1].tolist() == [4.688177, -1.786770, 0.787350]
    assert gt.velocity_mps[0].tolist() == [-0.027876, 0.033207, 0.800006]  # not the biases
    raw = np.array([0.534108, -0.153029, -0.827383, -0.082152])
    assert abs(np.linalg.norm(raw) - 1.0) > 1e-7  # six printed digits: not unit ...
    np.testing.assert_allclose(np.linalg.norm(gt.quaternion_wxyz, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(gt.quaternion_wxyz[0], raw / np.linalg.norm(raw), atol=1e-15)


def test_files_without_header_read(flightlog_files, log: FlightLog) -> None:
    for name in ("imu.csv", "frames.csv", "tracks.csv", "nav.csv", "groundtruth.csv"):
        flightlog_files.delete_line(log.root / name, 1)
    assert read_flightlog(log.root) == log


def test_clean_files_take_the_fast_path(log: FlightLog, monkeypatch) -> None:
    def no_scan(*args, **kwargs):
        raise AssertionError("line-by-line scan used on a clean file")

    monkeypatch.setattr(fl, "_scan_numeric_csv", no_scan)
    assert read_flightlog(log.root) == log


def test_the_line_scan_reads_what_numpy_reads(log: FlightLog, monkeypatch) -> None:
    # Force the slow path everywhere: same numbers, bit for bit.
    monkeypatch.setattr(fl, "_count_lines", lambda path, shown: fl._LineCount(
        fl._is_header(path.read_text().split("\n", 1)[0]), -1, True))
    assert read_flightlog(log.root) == log


def test_bad_value_deep_in_a_large_file_is_located(flightlog_files, tmp_path: Path, rng) -> None:
    the_log = flightlog_files.make_log(tmp_path / "log", rng)
    n = 20_000
    t = flightlog_files.T0_NS + flightlog_files.IMU_DT_NS * np.arange(n, dtype=np.int64)
    imu = ImuSamples(t, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)))
    write_flightlog(FlightLog(the_log.root, the_log.config, imu, the_log.frames,
                              the_log.tracks), the_log.root)
    flightlog_files.write_dtm(the_log.root / "dtm.npz")
    flightlog_files.set_value(the_log.root / "imu.csv", 15_321, 4, "8.1x")
    flightlog_files.expect_error(the_log.root, "imu.csv", 15_321, "acc_x", "'8.1x'")


# --------------------------------------------------------------------------- flight.yaml errors


def test_unknown_top_level_key(flightlog_files, log: FlightLog) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "dtm:")
    flightlog_files.insert_line(path, line, "gravity: 9.81")
    flightlog_files.expect_error(log.root, "flight.yaml", line, "unknown key 'gravity'")


@pytest.mark.parametrize("after, text, key", [
    ("body_T_cam:", "    rotation_deg: [0.0, 0.0, 0.0]", "camera.body_T_cam.rotation_deg"),
    ("imu:", "  gyro_noise_density: 1.0e-4", "imu.gyro_noise_density"),
    ("dtm:", "  sigma_h: 2.0", "dtm.sigma_h"),
    ("initial_state:", "  sigma_attitude_rad: 0.01", "initial_state.sigma_attitude_rad"),
])
def test_unknown_nested_key(
    flightlog_files, log: FlightLog, after: str, text: str, key: str
) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, after) + 1
    flightlog_files.insert_line(path, line, text)
    flightlog_files.expect_error(log.root, "flight.yaml", line, f"unknown key '{key}'")


def test_anything_goes_under_extra(flightlog_files, log: FlightLog) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "extra:") + 1
    flightlog_files.insert_line(path, line, "  whatever_key: {nested: [1, 2]}")
    assert read_flightlog(log.root).config.extra["whatever_key"] == {"nested": [1, 2]}


@pytest.mark.parametrize("value", ["cdtm-flightlog/2", "euroc"])
def test_wrong_format_string(flightlog_files, log: FlightLog, value: str) -> None:
    flightlog_files.set_line(log.root / "flight.yaml", 1, f"format: {value}")
    flightlog_files.expect_error(log.root, "flight.yaml", 1, value, "cdtm-flightlog/1")


def test_missing_format(flightlog_files, log: FlightLog) -> None:
    flightlog_files.delete_line(log.root / "flight.yaml", 1)
    flightlog_files.expect_error(log.root, "flight.yaml", 1, "missing key 'format'")


def test_missing_required_key(flightlog_files, log: FlightLog) -> None:
    path = log.root / "flight.yaml"
    flightlog_files.delete_line(path, flightlog_files.line_of(path, "pixel_sigma_px:"))
    flightlog_files.expect_error(log.root, "flight.yaml", flightlog_files.line_of(path, "camera:"),
                  "missing key 'camera.pixel_sigma_px'")


def test_duplicate_key(flightlog_files, log: FlightLog) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "gravity_mps2:") + 1
    flightlog_files.insert_line(path, line, "gravity_mps2: 9.81")
    flightlog_files.expect_error(log.root, "flight.yaml", line, "duplicate key 'gravity_mps2'")


@pytest.mark.parametrize("model", ["radtan8", "fisheye", "kannala_brandt"])
def test_bad_distortion_model(flightlog_files, log: FlightLog, model: str) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "distortion_model:")
    flightlog_files.set_line(path, line, f"  distortion_model: {model}")
    flightlog_files.expect_error(log.root, "flight.yaml", line, model, "radtan", "equidistant")


def test_equidistant_lens_round_trips_and_needs_four_coefficients(
    flightlog_files, tmp_path: Path, rng
) -> None:
    the_log = flightlog_files.make_log(tmp_path / "log", rng)
    cam = the_log.config.camera.camera
    fisheye = PinholeCamera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                            (0.0034, 0.0007, -0.0021, 0.0002), "equidistant")
    the_log = dataclasses.replace(the_log, config=dataclasses.replace(
        the_log.config, camera=dataclasses.replace(the_log.config.camera, camera=fisheye)))
    write_flightlog(the_log, the_log.root)
    flightlog_files.write_dtm(the_log.root / "dtm.npz")
    path = the_log.root / "flight.yaml"
    assert "  distortion_model: equidistant\n" in path.read_text()
    back = read_flightlog(the_log.root)
    assert back == the_log and back.config.camera.camera.model is DistortionModel.EQUIDISTANT
    line = flightlog_files.line_of(path, "distortion_coeffs:")
    flightlog_files.set_line(path, line, "  distortion_coeffs: [0.1, 0.2, 0.0, 0.0, 0.0]")
    flightlog_files.expect_error(
        the_log.root,
        "flight.yaml",
        line,
        "camera.distortion_coeffs has 5 values",
        "4 finite numbers",
    )


def _with_time_offset(the_log: FlightLog, offset_s: float) -> FlightLog:
    camera = dataclasses.replace(the_log.config.camera, time_offset_s=offset_s)
    return dataclasses.replace(the_log, config=dataclasses.replace(the_log.config,
                                                                    camera=camera))


@pytest.mark.parametrize("offset_s", [0.0123456789, -0.25])
def test_time_offset_moves_frames_onto_the_imu_clock(flightlog_files, tmp_path: Path, rng,
                                                     offset_s: float) -> None:
    # In memory frames are on the IMU clock (nav.csv's times equal them); frames.csv holds
    # the camera's stamps, t_cam = t_imu - offset, and reads back to the same log.
    the_log = _with_time_offset(flightlog_files.make_log(tmp_path / "log", rng), offset_s)
    write_flightlog(the_log, the_log.root)
    flightlog_files.write_dtm(the_log.root / "dtm.npz")
    offset_ns = round(offset_s * 1e9)
    stamps = [
        int(line.split(",")[0])
        for line in flightlog_files.text_lines(the_log.root / "frames.csv")[1:-1]
    ]
    assert stamps == (the_log.frames.t_ns - offset_ns).tolist()
    back = read_flightlog(the_log.root)
    assert back == the_log
    assert back.config.camera.time_offset_s == offset_s
    np.testing.assert_array_equal(back.frame_t_cam_ns, stamps)
    np.testing.assert_array_equal(back.frames.t_ns, back.nav.t_ns)


def test_time_offset_absent_is_zero_and_not_written(log: FlightLog) -> None:
    assert "time_offset_s" not in (log.root / "flight.yaml").read_text()
    back = read_flightlog(log.root)
    assert back.config.camera.time_offset_s == 0.0
    np.testing.assert_array_equal(back.frame_t_cam_ns, back.frames.t_ns)


@pytest.mark.parametrize(("key", "value", "expected"), [
    *(("time_offset_s", v, "[-10, 10] s") for v in ("12.0", "-10.5", "nan", "fast")),
    *(("principal_point_sigma_px", v, "[0, 30] px") for v in ("31", "-0.1", "nan", "one")),
])
def test_a_camera_number_out_of_range_or_not_a_number(
    flightlog_files, log: FlightLog, key: str, value: str, expected: str
) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "pixel_sigma_px:") + 1
    flightlog_files.insert_line(path, line, f"  {key}: {value}")
    flightlog_files.expect_error(log.root, "flight.yaml", line, f"camera.{key}", expected)


def test_the_principal_point_sigma_round_trips_and_is_absent_by_default(
        flightlog_files, tmp_path: Path, rng, log: FlightLog) -> None:
    """``camera.principal_point_sigma_px``: read, written back bit for bit, and neither
    written nor read where a log does not declare it (nothing considered)."""
    assert "principal_point_sigma_px" not in (log.root / "flight.yaml").read_text()
    assert read_flightlog(log.root).config.camera.principal_point_sigma_px is None
    the_log = flightlog_files.make_log(tmp_path / "log", rng)
    camera = dataclasses.replace(the_log.config.camera, principal_point_sigma_px=0.35)
    the_log = dataclasses.replace(the_log, config=dataclasses.replace(the_log.config,
                                                                      camera=camera))
    write_flightlog(the_log, the_log.root)
    flightlog_files.write_dtm(the_log.root / "dtm.npz")
    back = read_flightlog(the_log.root)
    assert back == the_log and back.config.camera.principal_point_sigma_px == 0.35


def test_a_stamp_the_time_offset_pushes_out_of_int64_is_refused(
    flightlog_files, tmp_path: Path, rng
) -> None:
    the_log = _with_time_offset(flightlog_files.make_log(tmp_path / "log", rng), 0.5)
    write_flightlog(the_log, the_log.root)
    flightlog_files.write_dtm(the_log.root / "dtm.npz")
    path = the_log.root / "frames.csv"
    last = flightlog_files.data_line(flightlog_files.N_FRAMES - 1)
    flightlog_files.set_value(path, last, 0, str(np.iinfo(np.int64).max - 1000))
    flightlog_files.expect_error(the_log.root, "frames.csv", last, "int64")


def test_distortion_model_none_or_absent_means_no_distortion(
    flightlog_files, log: FlightLog
) -> None:
    path = log.root / "flight.yaml"
    flightlog_files.delete_line(path, flightlog_files.line_of(path, "distortion_coeffs:"))
    flightlog_files.set_line(
        path, flightlog_files.line_of(path, "distortion_model:"), "  distortion_model: none"
    )
    assert read_flightlog(log.root).config.camera.camera.distortion == ()
    flightlog_files.delete_line(path, flightlog_files.line_of(path, "distortion_model:"))
    assert read_flightlog(log.root).config.camera.camera.distortion == ()


def test_distortion_coeffs_of_wrong_length(flightlog_files, log: FlightLog) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "distortion_coeffs:")
    flightlog_files.set_line(path, line, "  distortion_coeffs: [0.1, 0.2, 0.0]")
    flightlog_files.expect_error(log.root, "flight.yaml", line, "3 values", "4 or 5")


def test_non_unit_quaternion_in_yaml(flightlog_files, log: FlightLog) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "quaternion_wxyz:")  # body_T_cam's comes first
    flightlog_files.set_line(path, line, "    quaternion_wxyz: [0.0, 1.1, 0.0, 0.0]")
    flightlog_files.expect_error(
        log.root, "flight.yaml", line, "camera.body_T_cam.quaternion_wxyz", "unit"
    )


def test_slightly_off_unit_quaternion_is_normalized(flightlog_files, log: FlightLog) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "quaternion_wxyz:")
    flightlog_files.set_line(path, line, "    quaternion_wxyz: [0.0, 1.0004, 0.0, 0.0]")
    np.testing.assert_array_equal(read_flightlog(log.root).config.camera.body_T_cam[:3, :3],
                                  np.diag([1.0, -1.0, -1.0]))


def test_deg_key_is_degrees(flightlog_files, log: FlightLog) -> None:
    path = log.root / "flight.yaml"
    flightlog_files.set_line(
        path, flightlog_files.line_of(path, "sigma_attitude_deg:"), "  sigma_attitude_deg: 2.0"
    )
    state = read_flightlog(log.root).config.initial_state
    assert state.sigma_attitude_deg == 2.0
    assert state.sigma_attitude_rad == pytest.approx(math.radians(2.0), rel=1e-15)


def test_exponent_without_dot_is_a_number(flightlog_files, log: FlightLog) -> None:
    # PyYAML reads 2e-5 as a string (YAML 1.1); Kalibr files write it that way.
    path = log.root / "flight.yaml"
    flightlog_files.set_line(
        path,
        flightlog_files.line_of(path, "gyroscope_random_walk:"),
        "  gyroscope_random_walk: 2e-5",
    )
    assert read_flightlog(log.root).config.imu.gyroscope_random_walk == 2e-5


@pytest.mark.parametrize("key, value, words", [
    ("gravity_mps2:", "gravity_mps2: .nan", ("gravity_mps2", "a number in [1, 30] m/s^2")),
    ("gravity_mps2:", "gravity_mps2: -9.8", ("gravity_mps2", "a number in [1, 30] m/s^2")),
    ("pixel_sigma_px:", "  pixel_sigma_px: abc", ("pixel_sigma_px", "in [0.001, 100] px")),
    ("rate_hz:", "  rate_hz: 0", ("imu.rate_hz", "in [1, 100000] Hz")),
    ("resolution:", "  resolution: [400.5, 300]", ("resolution", "positive integer")),
    ("intrinsics:", "  intrinsics: [-310.5, 309.25, 201.3, 148.7]", ("fx", "fx in [")),
    ("position_m:", "  position_m: [0.0, 0.0]", ("initial_state.position_m", "3")),
    ("sigma_h_m:", "  sigma_h_m: [1.0]", ("dtm.sigma_h_m", "a list")),
])
def test_bad_yaml_values(
    flightlog_files, log: FlightLog, key: str, value: str, words: tuple[str, ...]
) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, key)
    flightlog_files.set_line(path, line, value)
    flightlog_files.expect_error(log.root, "flight.yaml", line, *words)


def test_yaml_syntax_error(flightlog_files, log: FlightLog) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "imu:") + 1
    flightlog_files.insert_line(path, line, "  rate_hz: [200")
    with pytest.raises(FlightLogError, match=r"flight\.yaml:\d+: YAML error"):
        read_flightlog(log.root)


def test_missing_dtm_file(flightlog_files, log: FlightLog) -> None:
    (log.root / "dtm.npz").unlink()
    line = flightlog_files.line_of(log.root / "flight.yaml", "path:")
    flightlog_files.expect_error(log.root, "flight.yaml", line, "dtm.path", "does not exist")


def test_dtm_path_naming_a_folder_says_so(flightlog_files, log: FlightLog) -> None:
    """Catches a folder where the DTM file belongs reported as missing (a2fce1e: "does not
    exist", while the user sees it right there)."""
    (log.root / "dtm.npz").unlink()
    (log.root / "dtm.npz").mkdir()
    line = flightlog_files.line_of(log.root / "flight.yaml", "path:")
    message = flightlog_files.expect_error(log.root, "flight.yaml", line, "dtm.path",
                            "is a directory, not a file")
    assert "does not exist" not in message


def test_dtm_with_unknown_suffix(flightlog_files, log: FlightLog) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "path:")
    (log.root / "dtm.png").write_bytes(b"")
    flightlog_files.set_line(path, line, "  path: dtm.png")
    flightlog_files.expect_error(log.root, "flight.yaml", line, ".png", ".npz")


# --------------------------------------------------------------------------- missing files


def _expect_path_error(path: Path, *words: str) -> str:
    """A problem with a path itself: named without a line number, one line."""
    with pytest.raises(FlightLogError) as info:
        read_flightlog(path.parent if path.suffix in (".csv", ".yaml") else path)
    message = str(info.value)
    assert message.startswith(f"{path}: "), message
    assert ":1:" not in message and "\n" not in message and "; expected " in message, message
    for word in words:
        assert word in message, message
    return message


@pytest.mark.parametrize("name", ["flight.yaml", "imu.csv", "frames.csv"])
def test_missing_required_file(log: FlightLog, name: str) -> None:
    """Catches a line number on a file that is not there (a2fce1e: ``imu.csv:1:``)."""
    (log.root / name).unlink()
    _expect_path_error(log.root / name, "required file is missing")


@pytest.mark.parametrize("name", ["flight.yaml", "imu.csv"])
def test_required_file_that_is_a_folder_says_so(log: FlightLog, name: str) -> None:
    """Catches a folder in a required file's place reported as missing."""
    (log.root / name).unlink()
    (log.root / name).mkdir()
    _expect_path_error(log.root / name, "is a directory, not a file")


def test_missing_tracks_when_frames_have_no_images(flightlog_files, log: FlightLog) -> None:
    (log.root / "tracks.csv").unlink()
    flightlog_files.expect_error(
        log.root, "frames.csv", flightlog_files.data_line(0), "no image", "tracks.csv"
    )


def test_missing_image_file_without_tracks(flightlog_files, log: FlightLog) -> None:
    (log.root / "tracks.csv").unlink()
    path = log.root / "frames.csv"
    for k in range(flightlog_files.N_FRAMES):
        flightlog_files.set_value(path, flightlog_files.data_line(k), 1, f"{k}.png")
        if k != 2:
            (log.root / f"{k}.png").write_bytes(b"")
    flightlog_files.expect_error(
        log.root, "frames.csv", flightlog_files.data_line(2), "'2.png'", "does not exist"
    )


@pytest.mark.parametrize("name", ["tracks.csv", "nav.csv", "groundtruth.csv"])
def test_an_optional_file_that_is_a_folder_is_not_taken_for_absent(log: FlightLog,
                                                                   name: str) -> None:
    """Catches a folder in an optional file's place read as its absence (a2fce1e: a
    tracks.csv folder read as 'frame 0 has no image and there is no tracks.csv', a
    groundtruth.csv folder silently gave a run without ground truth)."""
    if (log.root / name).exists():
        (log.root / name).unlink()
    (log.root / name).mkdir()
    _expect_path_error(log.root / name, "is a directory, not a file")


def test_not_a_directory(tmp_path: Path) -> None:
    """Catches a line number on a folder (a2fce1e: ``nowhere:1: not a directory``) and a
    missing folder and a file in its place told apart."""
    _expect_path_error(tmp_path / "nowhere", "does not exist", "flight log directory")
    (tmp_path / "a_file").write_text("x")
    _expect_path_error(tmp_path / "a_file", "is a file, not a directory")


# --------------------------------------------------------------------------- CSV errors


@pytest.mark.parametrize("token", ["nan", "NaN", "inf", "-inf", "Infinity"])
def test_nan_and_inf_in_imu(flightlog_files, log: FlightLog, token: str) -> None:
    flightlog_files.set_value(log.root / "imu.csv", 6, 2, token)
    flightlog_files.expect_error(log.root, "imu.csv", 6, "gyro_y", "finite")


@pytest.mark.parametrize("name, column, field", [
    ("groundtruth.csv", 8, "vx"), ("nav.csv", 1, "px"), ("tracks.csv", 3, "v"),
])
def test_nan_in_other_files(
    flightlog_files, log: FlightLog, name: str, column: int, field: str
) -> None:
    flightlog_files.set_value(log.root / name, 3, column, "nan")
    flightlog_files.expect_error(log.root, name, 3, field, "finite")


def test_non_increasing_imu_times(flightlog_files, log: FlightLog) -> None:
    path = log.root / "imu.csv"
    previous = flightlog_files.text_lines(path)[5].split(",")[0]  # line 6
    flightlog_files.set_value(path, 7, 0, previous)
    flightlog_files.expect_error(log.root, "imu.csv", 7, "strictly increasing")


def test_decreasing_frame_times(flightlog_files, log: FlightLog) -> None:
    path = log.root / "frames.csv"
    flightlog_files.set_value(path, flightlog_files.data_line(2), 0, str(flightlog_files.T0_NS - 1))
    flightlog_files.expect_error(
        log.root, "frames.csv", flightlog_files.data_line(2), "strictly increasing"
    )


def test_non_increasing_groundtruth_times(flightlog_files, log: FlightLog) -> None:
    path = log.root / "groundtruth.csv"
    flightlog_files.set_value(path, 30, 0, str(flightlog_files.T0_NS))
    flightlog_files.expect_error(log.root, "groundtruth.csv", 30, "strictly increasing")


@pytest.mark.parametrize("name, line", [
    ("imu.csv", 9), ("frames.csv", 3), ("tracks.csv", 5), ("nav.csv", 2), ("groundtruth.csv", 40),
])
def test_short_rows(flightlog_files, log: FlightLog, name: str, line: int) -> None:
    path = log.root / name
    fields = flightlog_files.text_lines(path)[line - 1].split(",")
    flightlog_files.set_line(
        path, line, ",".join(fields[:-1]) if name != "frames.csv" else fields[0]
    )
    flightlog_files.expect_error(log.root, name, line, "short row")


def test_too_many_values_in_imu(flightlog_files, log: FlightLog) -> None:
    path = log.root / "imu.csv"
    flightlog_files.set_line(path, 4, flightlog_files.text_lines(path)[3] + ",0.0")
    flightlog_files.expect_error(log.root, "imu.csv", 4, "too many")


@pytest.mark.parametrize("name, line, column, token, field", [
    ("imu.csv", 4, 3, "abc", "gyro_z"),
    ("imu.csv", 5, 0, "1403636579778555392.0", "t_ns"),  # times are integers
    ("imu.csv", 5, 0, "1e18", "t_ns"),
    ("imu.csv", 5, 0, "99999999999999999999", "t_ns"),  # beyond int64
    ("imu.csv", 5, 1, "1_000", "gyro_x"),
    ("tracks.csv", 4, 1, "seven", "track_id"),
    ("nav.csv", 3, 5, "", "qx"),  # a missing value
    ("frames.csv", 3, 0, "12x", "t_ns"),
])
def test_non_numeric_tokens(
    flightlog_files, log: FlightLog, name, line, column, token, field
) -> None:
    flightlog_files.set_value(log.root / name, line, column, token)
    flightlog_files.expect_error(log.root, name, line, field)


def test_blank_line_in_the_middle(flightlog_files, log: FlightLog) -> None:
    flightlog_files.insert_line(log.root / "imu.csv", 10, "")
    flightlog_files.expect_error(log.root, "imu.csv", 10, "empty line")


def test_earliest_problem_is_reported(flightlog_files, log: FlightLog) -> None:
    path = log.root / "imu.csv"
    flightlog_files.set_value(path, 20, 1, "nan")
    flightlog_files.set_value(
        path, 8, 0, flightlog_files.text_lines(path)[5].split(",")[0]
    )  # goes back in time on line 8
    flightlog_files.expect_error(log.root, "imu.csv", 8, "strictly increasing")


def test_track_naming_a_frame_that_does_not_exist(flightlog_files, log: FlightLog) -> None:
    path = log.root / "tracks.csv"
    last = len(flightlog_files.text_lines(path)) - 1  # the file ends with a newline
    flightlog_files.set_value(path, last, 0, str(flightlog_files.N_FRAMES))
    flightlog_files.expect_error(
        log.root, "tracks.csv", last, f"frame {flightlog_files.N_FRAMES} does not exist"
    )


def test_negative_frame_index(flightlog_files, log: FlightLog) -> None:
    flightlog_files.set_value(log.root / "tracks.csv", 2, 0, "-1")
    flightlog_files.expect_error(log.root, "tracks.csv", 2, "frame -1 does not exist")


def test_tracks_not_sorted_by_frame(flightlog_files, log: FlightLog) -> None:
    line = flightlog_files.data_line(flightlog_files.N_TRACKS + 2)  # a row of frame 1
    flightlog_files.set_value(log.root / "tracks.csv", line, 0, "0")
    flightlog_files.expect_error(log.root, "tracks.csv", line, "sorted by frame")


def test_track_seen_twice_in_one_frame(flightlog_files, log: FlightLog) -> None:
    path = log.root / "tracks.csv"
    first_id = flightlog_files.text_lines(path)[flightlog_files.data_line(0) - 1].split(",")[1]
    flightlog_files.set_value(path, flightlog_files.data_line(3), 1, first_id)
    flightlog_files.expect_error(
        log.root, "tracks.csv", flightlog_files.data_line(3), f"track {first_id} is seen twice"
    )


_MARGIN = fl.IMAGE_BORDER_MARGIN_PX


@pytest.mark.parametrize("column, far_edge, beyond_px", [
    (2, True, 1e-9), (2, False, 0.1), (3, True, 1e-6), (3, False, 29.5 - _MARGIN),
])
def test_pixels_outside_the_image(flightlog_files, log: FlightLog, column: int, far_edge: bool,
                                  beyond_px: float) -> None:
    """Beyond the border margin a pixel is a data error naming its line (u beyond the right
    or the left edge, v beyond the bottom or the top)."""
    camera = log.config.camera.camera
    size = camera.width if column == 2 else camera.height
    value = size - 0.5 + _MARGIN + beyond_px if far_edge else -0.5 - _MARGIN - beyond_px
    flightlog_files.set_value(log.root / "tracks.csv", 7, column, f"{value!r}")
    flightlog_files.expect_error(log.root, "tracks.csv", 7, "outside",
                                 f"{camera.width}x{camera.height}",
                                 f"{_MARGIN:g} px border margin")


def test_pixels_on_the_outer_edges_are_inside(flightlog_files, log: FlightLog) -> None:
    path = log.root / "tracks.csv"
    flightlog_files.set_value(path, 7, 2, "-0.5")
    flightlog_files.set_value(path, 8, 3, f"{flightlog_files.HEIGHT - 0.5!r}")
    read_flightlog(log.root)


def test_pixels_within_the_border_margin_are_kept_as_they_are(
    flightlog_files, log: FlightLog
) -> None:
    """Detection noise at the border (a fraction of a pixel out) is not an error: the
    observations are read unchanged, up to the margin itself."""
    path = log.root / "tracks.csv"
    flightlog_files.set_value(path, 7, 2, f"{-0.5 - _MARGIN!r}")
    flightlog_files.set_value(path, 8, 3, f"{flightlog_files.HEIGHT - 0.5 + _MARGIN!r}")
    flightlog_files.set_value(path, 9, 2, "-0.85")
    tracks = read_flightlog(log.root).tracks
    assert tracks.uv_px[7 - 2, 0] == -0.5 - _MARGIN
    assert tracks.uv_px[8 - 2, 1] == flightlog_files.HEIGHT - 0.5 + _MARGIN
    assert tracks.uv_px[9 - 2, 0] == -0.85


def test_nav_with_a_row_missing(flightlog_files, log: FlightLog) -> None:
    flightlog_files.delete_line(
        log.root / "nav.csv", flightlog_files.data_line(flightlog_files.N_FRAMES - 1)
    )
    flightlog_files.expect_error(
        log.root,
        "nav.csv",
        flightlog_files.data_line(flightlog_files.N_FRAMES - 1),
        "one row per frame",
    )


def test_nav_with_a_row_too_many(flightlog_files, log: FlightLog) -> None:
    path = log.root / "nav.csv"
    row = flightlog_files.text_lines(path)[
        flightlog_files.data_line(flightlog_files.N_FRAMES - 1) - 1
    ].split(",")
    row[0] = str(int(row[0]) + 1)
    flightlog_files.insert_line(
        path, flightlog_files.data_line(flightlog_files.N_FRAMES), ",".join(row)
    )
    flightlog_files.expect_error(
        log.root,
        "nav.csv",
        flightlog_files.data_line(flightlog_files.N_FRAMES),
        "beyond the last frame",
    )


def test_nav_with_a_wrong_time(flightlog_files, log: FlightLog) -> None:
    path = log.root / "nav.csv"
    flightlog_files.set_value(
        path, flightlog_files.data_line(1), 0, str(int(log.frames.t_ns[1]) + 1)
    )
    flightlog_files.expect_error(
        log.root, "nav.csv", flightlog_files.data_line(1), "one row per frame"
    )


@pytest.mark.parametrize("name", ["nav.csv", "groundtruth.csv"])
def test_non_unit_quaternion_in_csv(flightlog_files, log: FlightLog, name: str) -> None:
    path = log.root / name
    for column in range(4, 8):  # scale the quaternion by 1.01
        value = float(flightlog_files.text_lines(path)[2].split(",")[column])
        flightlog_files.set_value(path, 3, column, repr(1.01 * value))
    flightlog_files.expect_error(log.root, name, 3, "norm 1.01", "unit quaternion")


# --------------------------------------------------------------------------- Tracks.pairs


def test_pairs_on_a_hand_made_example() -> None:
    tracks = Tracks(frame=np.array([0, 0, 0, 1, 1, 2, 2, 3]),
                    track_id=np.array([7, 3, 5, 3, 7, 7, 5, 3]),
                    uv_px=np.zeros((8, 2)))
    rows_a, rows_b = tracks.pairs()
    # track 3: rows 1 -> 3 -> 7; track 5: rows 2 -> 6 (skips frame 1); track 7: 0 -> 4 -> 5.
    # Sorted by (frame_a, frame_b, track): (0,1,t3) (0,1,t7) (0,2,t5) (1,2,t7) (1,3,t3).
    assert rows_a.tolist() == [1, 0, 2, 4, 3]
    assert rows_b.tolist() == [3, 4, 6, 5, 7]
    assert rows_a.dtype == np.int64


def test_pairs_of_empty_and_single_observation_tracks() -> None:
    empty = Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
    assert [a.tolist() for a in empty.pairs()] == [[], []]
    single = Tracks(np.array([0, 1]), np.array([1, 2]), np.zeros((2, 2)))
    assert [a.tolist() for a in single.pairs()] == [[], []]


def test_pairs_of_the_fixture_log(flightlog_files, log: FlightLog) -> None:
    rows_a, rows_b = log.tracks.pairs()
    assert rows_a.size == flightlog_files.N_TRACKS * (flightlog_files.N_FRAMES - 1)
    np.testing.assert_array_equal(log.tracks.track_id[rows_a], log.tracks.track_id[rows_b])
    np.testing.assert_array_equal(log.tracks.frame[rows_b], log.tracks.frame[rows_a] + 1)


# --------------------------------------------------------------------------- interpolation


def _yaw_quaternion(angle_rad: float) -> np.ndarray:
    return np.array([math.cos(angle_rad / 2), 0.0, 0.0, math.sin(angle_rad / 2)])


def _two_states(q1_sign: float = 1.0) -> States:
    return States(t_ns=np.array([1_000, 3_000]),
                  position_m=np.array([[0.0, 0.0, 100.0], [10.0, -4.0, 90.0]]),
                  quaternion_wxyz=np.array([_yaw_quaternion(0.0),
                                            q1_sign * _yaw_quaternion(math.pi / 2)]),
                  velocity_mps=np.array([[1.0, 2.0, 3.0], [3.0, 2.0, 1.0]]))


def _angle_between(q_a: np.ndarray, q_b: np.ndarray) -> float:
    R = quat_wxyz_to_rotation(q_a).T @ quat_wxyz_to_rotation(q_b)
    return float(np.linalg.norm(so3_log(R)))


@pytest.mark.parametrize("q1_sign", [1.0, -1.0], ids=["same_hemisphere", "antipodal_sign"])
def test_slerp_midpoint_and_quarter_point(q1_sign: float) -> None:
    states = _two_states(q1_sign)
    out = states.interpolate(np.array([2_000, 1_500]))
    np.testing.assert_allclose(out.position_m[0], [5.0, -2.0, 95.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.velocity_mps[0], [2.0, 2.0, 2.0], rtol=0, atol=1e-12)
    # Slerp turns at a constant rate: 45 deg at the midpoint, 22.5 deg at a quarter
    # (normalized linear interpolation would give 26.57 deg at the quarter).
    assert _angle_between(out.quaternion_wxyz[0], _yaw_quaternion(math.pi / 4)) < ANGLE_TOL_RAD
    assert _angle_between(out.quaternion_wxyz[1], _yaw_quaternion(math.pi / 8)) < ANGLE_TOL_RAD
    np.testing.assert_allclose(np.linalg.norm(out.quaternion_wxyz, axis=1), 1.0, atol=1e-15)
    np.testing.assert_array_equal(out.t_ns, [2_000, 1_500])


def test_interpolation_at_sample_times_is_exact(flightlog_files, rng) -> None:
    n = 5
    states = States(
        np.arange(n, dtype=np.int64) * 7 + flightlog_files.T0_NS,
        rng.normal(size=(n, 3)),
        flightlog_files.random_quaternions(rng, n),
        rng.normal(size=(n, 3)),
    )
    assert states.interpolate(states.t_ns) == states
    single = states.interpolate(int(states.t_ns[-1]))
    assert len(single) == 1 and np.array_equal(single.position_m[0], states.position_m[-1])


@pytest.mark.parametrize("t", [999, 3_001])
def test_interpolation_outside_the_range_raises(t: int) -> None:
    with pytest.raises(FlightLogError, match=f"t_ns={t}"):
        _two_states().interpolate(np.array([2_000, t]))


# --------------------------------------------------------------------------- dataclasses


def test_dataclasses_check_shapes() -> None:
    with pytest.raises(ValueError, match="gyro_radps"):
        ImuSamples(np.arange(3), np.zeros((3, 2)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="integer"):
        ImuSamples(np.arange(3.0), np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="length"):
        Tracks(np.arange(3), np.arange(2), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="shape"):
        CameraConfig(PinholeCamera.from_fov(10, 10, 60.0), 0.5, np.eye(3))


def test_initial_state_world_T_body() -> None:
    q = _yaw_quaternion(0.3)
    state = InitialState([1.0, 2.0, 3.0], q, [0.0] * 3, [0.0] * 3, [0.0] * 3,
                         1.0, 1.0, 1.0, 1.0, 1.0)
    expected = make_pose(quat_wxyz_to_rotation(q), [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(state.world_T_body, expected)


# --------------------------------------------------------------------------- odd bytes and headers


def test_bytes_that_are_not_utf8_are_located(flightlog_files, log: FlightLog) -> None:
    path = log.root / "imu.csv"
    data = path.read_bytes().split(b"\n")
    data[4] = data[4].replace(b",", b",\xff", 1)  # line 5
    path.write_bytes(b"\n".join(data))
    flightlog_files.expect_error(log.root, "imu.csv", 5, "UTF-8")


def test_a_first_row_with_a_number_first_is_data_not_a_header(
    flightlog_files, log: FlightLog
) -> None:
    # A corrupt first data row must be reported, not skipped as if it were a header.
    path = log.root / "imu.csv"
    flightlog_files.delete_line(path, 1)
    flightlog_files.set_value(path, 1, 3, "oops")
    flightlog_files.expect_error(log.root, "imu.csv", 1, "gyro_z", "'oops'")


def test_header_only_imu_has_no_samples(flightlog_files, log: FlightLog) -> None:
    (log.root / "imu.csv").write_text("#t_ns,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z\n")
    flightlog_files.expect_error(log.root, "imu.csv", 2, "no IMU samples")


def test_writer_refuses_image_names_it_could_not_read_back(log: FlightLog) -> None:
    frames = Frames(log.frames.t_ns, ("a.png", "b,c.png", "", ""))
    with pytest.raises(ValueError, match="comma"):
        write_flightlog(FlightLog(log.root, log.config, log.imu, frames, log.tracks),
                        log.root.parent / "other")
    assert not (log.root.parent / "other").exists()


# --------------------------------------------------------------------------- hostile numbers


@pytest.mark.parametrize("digits, words", [
    (400, ("imu.rate_hz is '1000", "expected a number in [1, 100000] Hz")),  # > float max
    (5000, ("value '1000", "Exceeds the limit (4300 digits)", "expected a number")),
])
def test_an_integer_too_large_for_a_float_is_one_line(flightlog_files, log: FlightLog, digits: int,
                                                      words: tuple[str, ...]) -> None:
    path = log.root / "flight.yaml"
    line = flightlog_files.line_of(path, "rate_hz:")
    flightlog_files.set_line(path, line, "  rate_hz: 1" + "0" * digits)
    message = flightlog_files.expect_error(log.root, "flight.yaml", line, *words)
    assert len(message) < 300


def _geodetic_log(the_log: FlightLog) -> FlightLog:
    """The log with a geodetic origin whose DEM (never read here) is an empty dem.tif."""
    from cdtm_graph.geodesy import GeodeticOrigin, VerticalDatum

    root = the_log.root
    config = dataclasses.replace(
        the_log.config, origin=GeodeticOrigin(36.5, 127.25, 120.0),
        dtm=DtmConfig(root / "dem.tif", 2.4, vertical_datum=VerticalDatum.EGM96,
                      margin_m=2000.0, spacing_m=15.0))
    the_log = dataclasses.replace(the_log, config=config, nav=None, groundtruth=None)
    write_flightlog(the_log, root)
    (root / "dem.tif").write_bytes(b"")
    return the_log


@pytest.mark.parametrize("key, value, words", [
    ("margin_m", "1e12", ("dtm.margin_m is 1000000000000.0", "[1, 1e+06] m")),
    ("margin_m", "0.5", ("dtm.margin_m is 0.5", "[1, 1e+06] m")),
    ("spacing_m", "0.001", ("dtm.spacing_m is 0.001", "[0.01, 10000] m")),
    ("spacing_m", "1e5", ("dtm.spacing_m is 100000.0", "[0.01, 10000] m")),
])
def test_dem_margin_and_spacing_out_of_range_name_the_key(
    flightlog_files, tmp_path: Path, rng, key: str, value: str, words: tuple[str, ...]
) -> None:
    the_log = _geodetic_log(flightlog_files.make_log(tmp_path / "geo", rng))
    assert read_flightlog(the_log.root).config.dtm.spacing_m == 15.0  # as written: valid
    path = the_log.root / "flight.yaml"
    line = flightlog_files.line_of(path, f"{key}:")
    flightlog_files.set_line(path, line, f"  {key}: {value}")
    flightlog_files.expect_error(the_log.root, "flight.yaml", line, *words)


@pytest.mark.parametrize("name", ["groundtruth.csv", "nav.csv"])
def test_a_zero_quaternion_is_one_line_and_no_warning(flightlog_files, log: FlightLog,
                                                      name: str) -> None:
    """A row's qw,qx,qy,qz all 0: the one error line, and no numpy warning before it.
    Mutation tried: every row off the exact tolerance normalized (as before: "invalid
    value encountered in divide" printed above the line, a hostile-input hunt's find,
    2026-11-28)."""
    path = log.root / name
    header = [c.strip().lstrip("#").strip() for c in
              flightlog_files.text_lines(path)[0].split(",")]
    line = 3
    for column in ("qw", "qx", "qy", "qz"):
        flightlog_files.set_value(path, line, header.index(column), "0")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        flightlog_files.expect_error(log.root, name, line, "norm 0")
