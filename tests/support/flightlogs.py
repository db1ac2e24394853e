"""A small flight log written to disk, and the line editing its malformed-input tests use.

Imported by ``tests/conftest.py`` only (the ``flightlog_files`` and ``small_log`` fixtures).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import (
    CameraConfig,
    DtmConfig,
    FlightConfig,
    FlightLog,
    Frames,
    ImuConfig,
    ImuSamples,
    InitialState,
    States,
    Tracks,
    read_flightlog,
)
from cdtm_graph.geometry import make_pose

T0_NS = 1_403_636_579_758_555_392  # a EuRoC MH_01 epoch: needs int64, not float64
IMU_DT_NS = 5_000_000
N_IMU = 60
FRAME_EVERY = 12
N_FRAMES = 4
N_TRACKS = 6
WIDTH, HEIGHT = 400, 300


def random_quaternions(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def make_log(root: Path, rng: np.random.Generator) -> FlightLog:
    """A small log in memory: every track in every frame, random values of the right shapes."""
    camera = PinholeCamera(WIDTH, HEIGHT, 310.5, 309.25, 201.3, 148.7,
                           (-0.12, 0.03, 8e-4, -5e-4, -0.004))
    # Downward camera: x along body x, z along -body z (a half turn about x: exact floats).
    body_T_cam = make_pose(np.diag([1.0, -1.0, -1.0]), [0.25, -0.1, 0.05])
    config = FlightConfig(
        gravity_mps2=9.80665,
        dtm=DtmConfig(root / "dtm.npz", 2.4, (500000.0, 4100000.0, 12.5)),
        camera=CameraConfig(camera, 0.5, body_T_cam),
        imu=ImuConfig(200.0, 1.7e-4, 2.0e-3, 1.9e-5, 3.0e-3),
        initial_state=InitialState(
            position_m=[10.0, -20.0, 1000.0], quaternion_wxyz=random_quaternions(rng, 1)[0],
            velocity_mps=[200.0, 0.5, -1.0], gyro_bias=[1e-4, -2e-4, 3e-5],
            accel_bias=[0.01, -0.02, 0.005], sigma_position_m=50.0, sigma_attitude_deg=1.0,
            sigma_velocity_mps=1.0, sigma_gyro_bias=1.0e-4, sigma_accel_bias=1.0e-2),
        extra={"aircraft": "test", "notes": {"anything": [1, 2.5, "x"]}},
    )
    t_imu = T0_NS + IMU_DT_NS * np.arange(N_IMU, dtype=np.int64)
    imu = ImuSamples(t_imu, rng.normal(scale=0.01, size=(N_IMU, 3)),
                     rng.normal(scale=0.1, size=(N_IMU, 3)) + [0.0, 0.0, 9.80665])
    t_frames = t_imu[::FRAME_EVERY][:N_FRAMES]
    frames = Frames(t_frames, ("",) * N_FRAMES)
    # Every track in every frame, rows sorted by frame then track.
    frame = np.repeat(np.arange(N_FRAMES), N_TRACKS)
    track_id = np.tile(np.arange(N_TRACKS) * 10 + 3, N_FRAMES)
    uv = np.column_stack([rng.uniform(0.0, WIDTH - 1.0, frame.size),
                          rng.uniform(0.0, HEIGHT - 1.0, frame.size)])
    tracks = Tracks(frame, track_id, uv)
    nav = States(t_frames, rng.normal(size=(N_FRAMES, 3)), random_quaternions(rng, N_FRAMES),
                 rng.normal(size=(N_FRAMES, 3)))
    groundtruth = States(t_imu, rng.normal(size=(N_IMU, 3)), random_quaternions(rng, N_IMU),
                         rng.normal(size=(N_IMU, 3)))
    return FlightLog(root, config, imu, frames, tracks, nav, groundtruth)


def write_dtm(path: Path) -> None:
    """A 3x3 flat DTM (the log's ``dtm.npz``)."""
    np.savez(path, elevation=np.zeros((3, 3)), x0=0.0, y0=0.0, dx=30.0, dy=30.0)


def text_lines(path: Path) -> list[str]:
    return path.read_text().split("\n")


def insert_line(path: Path, line_no: int, text: str) -> None:
    """Insert so that ``text`` becomes line ``line_no``."""
    lines = text_lines(path)
    lines.insert(line_no - 1, text)
    path.write_text("\n".join(lines))


def line_of(path: Path, startswith: str) -> int:
    """1-based number of the first line whose stripped text starts with ``startswith``."""
    for i, line in enumerate(text_lines(path), start=1):
        if line.strip().startswith(startswith):
            return i
    raise AssertionError(f"no line starting with {startswith!r} in {path}")


def expect_error(root: Path, file: str, line: int, *words: str) -> str:
    with pytest.raises(FlightLogError) as info:
        read_flightlog(root)
    message = str(info.value)
    assert f"{file}:{line}: " in message, message
    assert "; expected " in message, message
    assert "\n" not in message
    for word in words:
        assert word in message, message
    return message


def set_line(path: Path, line_no: int, text: str) -> None:
    lines = text_lines(path)
    lines[line_no - 1] = text
    path.write_text("\n".join(lines))


def delete_line(path: Path, line_no: int) -> None:
    lines = text_lines(path)
    del lines[line_no - 1]
    path.write_text("\n".join(lines))


def set_value(path: Path, line_no: int, column: int, value: str) -> None:
    fields = text_lines(path)[line_no - 1].split(",")
    fields[column] = value
    set_line(path, line_no, ",".join(fields))


def data_line(row: int) -> int:
    """Line of 0-based data row ``row`` in a file written with a header."""
    return row + 2
