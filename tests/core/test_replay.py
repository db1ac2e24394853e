"""The one log replay: frames in order with their tracks, every IMU sample delivered once.

The oracle is the log's own files, parsed here with numpy (not by the reader), and the
contract of :class:`~cdtm_graph.replay.FrameInput`: a frame brings the samples before
its time not yet delivered, then the first sample at or after its time (unless an
earlier frame already took it).
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from cdtm_graph.flightlog import FlightLog, Frames, ImuSamples, read_flightlog
from cdtm_graph.replay import FrameInput, replay
from cdtm_graph.sim.simulate import SimulationSettings, write_simulated_log

#: A small flight: 6 frames at 1 fps, IMU at 50 Hz (a 20 ms period).
SETTINGS = SimulationSettings(frames=6, n_features=25, imu_rate_hz=50.0)
PERIOD_NS = 20_000_000


@pytest.fixture(scope="module")
def log_dir(tmp_path_factory, seed: int) -> Path:
    return write_simulated_log(dataclasses.replace(SETTINGS, seed=seed),
                               tmp_path_factory.mktemp("replay") / "log")


def _tracks_csv(log_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """tracks.csv as written: frame, track_id (int64) and (M, 2) uv."""
    ids = np.loadtxt(log_dir / "tracks.csv", delimiter=",", usecols=(0, 1), dtype=np.int64)
    uv = np.loadtxt(log_dir / "tracks.csv", delimiter=",", usecols=(2, 3))
    return ids[:, 0], ids[:, 1], uv


def _joined(parts: list[ImuSamples]) -> ImuSamples:
    return ImuSamples(np.concatenate([p.t_ns for p in parts]),
                      np.concatenate([p.gyro_radps for p in parts]),
                      np.concatenate([p.acc_mps2 for p in parts]))


def _check_imu_split(flight: FlightLog, inputs: list[FrameInput]) -> None:
    """Every sample up to the last frame's closing one arrives once, in order, at its frame."""
    imu, t_frames = flight.imu, flight.frames.t_ns
    delivered = 0
    for f in inputs:
        before, closing = f.imu_before, f.imu_closing
        assert np.all(before.t_ns < f.t_ns)
        if f.k > 0:  # nothing that was due at the previous frame arrives late
            assert np.all(before.t_ns >= t_frames[f.k - 1])
        delivered += len(before)
        first_at_or_after = int(np.searchsorted(imu.t_ns, f.t_ns, side="left"))
        if first_at_or_after < delivered or first_at_or_after == len(imu):
            assert len(closing) == 0  # already delivered, or past the end of the IMU
        else:
            assert len(closing) == 1 and first_at_or_after == delivered
            assert closing.t_ns[0] >= f.t_ns
            delivered += 1
    n_in_range = min(int(np.searchsorted(imu.t_ns, t_frames[-1], side="left")) + 1, len(imu))
    assert delivered == n_in_range
    parts = [p for f in inputs for p in (f.imu_before, f.imu_closing)]
    assert sum(len(p) for p in parts) == n_in_range
    got = _joined(parts)
    np.testing.assert_array_equal(got.t_ns, imu.t_ns[:n_in_range])
    np.testing.assert_array_equal(got.gyro_radps, imu.gyro_radps[:n_in_range])
    np.testing.assert_array_equal(got.acc_mps2, imu.acc_mps2[:n_in_range])


def test_frames_arrive_in_order_with_their_tracks_csv_rows(log_dir):
    flight = read_flightlog(log_dir)
    frame_t_ns = np.loadtxt(log_dir / "frames.csv", delimiter=",", usecols=0, dtype=np.int64)
    frame, track_id, uv = _tracks_csv(log_dir)
    assert flight.config.camera.time_offset_s == 0.0  # frames.csv stamps are IMU times
    inputs = list(replay(flight))
    assert [f.k for f in inputs] == list(range(SETTINGS.frames))
    assert [f.t_ns for f in inputs] == frame_t_ns.tolist()
    for f in inputs:
        rows = frame == f.k
        assert rows.sum() >= SETTINGS.n_features  # the frame's rows, not an empty match
        np.testing.assert_array_equal(f.track_id, track_id[rows])
        np.testing.assert_array_equal(f.uv_px, uv[rows])
    assert sum(f.track_id.size for f in inputs) == frame.size  # no row twice, none lost


def _frames_at(flight: FlightLog, layout: str) -> FlightLog:
    t = flight.frames.t_ns.copy()
    imu_t = flight.imu.t_ns
    if layout == "between_samples":
        t += PERIOD_NS // 2
    elif layout == "two_in_one_interval":  # frames 2 and 3 between the same two samples
        t[2] += PERIOD_NS // 8
        t[3] = t[2] + PERIOD_NS // 8
    elif layout == "last_past_the_imu":
        t[-1] = imu_t[-1] + PERIOD_NS
    elif layout == "first_before_the_imu":
        t[0] = imu_t[0] - PERIOD_NS
    return dataclasses.replace(flight, frames=Frames(t, flight.frames.image))


@pytest.mark.parametrize("layout", ["on_samples", "between_samples", "two_in_one_interval",
                                    "last_past_the_imu", "first_before_the_imu"])
def test_imu_samples_split_exactly_at_frame_times(log_dir, layout):
    flight = _frames_at(read_flightlog(log_dir), layout)
    assert np.all(np.diff(flight.frames.t_ns) > 0)
    inputs = list(replay(flight))
    _check_imu_split(flight, inputs)
    closing = [len(f.imu_closing) for f in inputs]
    if layout in ("on_samples", "between_samples"):
        assert closing == [1] * SETTINGS.frames
        # on a sample the frame's own sample closes it; between, the next one does
        gap = 0 if layout == "on_samples" else PERIOD_NS // 2
        assert [f.imu_closing.t_ns[0] - f.t_ns for f in inputs] == [gap] * SETTINGS.frames
        # 1 s of 50 Hz between frames: 49 samples strictly between two closing ones
        assert [len(f.imu_before) for f in inputs[1:]] == [49] * (SETTINGS.frames - 1)
    elif layout == "two_in_one_interval":
        assert closing[2] == 1 and closing[3] == 0 and len(inputs[3].imu_before) == 0
    elif layout == "last_past_the_imu":
        assert closing[-1] == 0 and inputs[-1].imu_before.t_ns[-1] == flight.imu.t_ns[-1]
    elif layout == "first_before_the_imu":
        assert len(inputs[0].imu_before) == 0 and inputs[0].imu_closing.t_ns[0] == 0


def test_frames_without_tracks(log_dir, tmp_path):
    """Frames with no rows in tracks.csv (first, middle, last), and a log with no tracks."""
    copy = tmp_path / "log"
    shutil.copytree(log_dir, copy)
    lines = (copy / "tracks.csv").read_text().splitlines(keepends=True)
    empty = {0, 2, SETTINGS.frames - 1}
    kept = [line for line in lines[1:] if int(line.split(",", 1)[0]) not in empty]
    (copy / "tracks.csv").write_text(lines[0] + "".join(kept))
    frame, track_id, uv = _tracks_csv(copy)
    assert not set(frame.tolist()) & empty
    flight = read_flightlog(copy)
    inputs = list(replay(flight))
    for f in inputs:
        rows = frame == f.k
        assert (f.k in empty) == (not rows.any())
        assert f.track_id.dtype == np.int64 and f.uv_px.shape == (rows.sum(), 2)
        np.testing.assert_array_equal(f.track_id, track_id[rows])
        np.testing.assert_array_equal(f.uv_px, uv[rows])
    _check_imu_split(flight, inputs)

    bare = dataclasses.replace(flight, tracks=None)  # images not tracked yet
    inputs_bare = list(replay(bare))
    assert [f.t_ns for f in inputs_bare] == [f.t_ns for f in inputs]
    assert all(f.track_id.shape == (0,) and f.uv_px.shape == (0, 2) for f in inputs_bare)
    _check_imu_split(bare, inputs_bare)
