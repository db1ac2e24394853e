"""A flight log replayed frame by frame, as a live system would receive it."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from cdtm_graph.flightlog import FlightLog, ImuSamples


@dataclass(frozen=True)
class FrameInput:
    """One frame and the IMU samples that arrive with it.

    Attributes:
        k: frame index (row of frames.csv). t_ns: its time.
        track_id: (m,) ids of the features seen in it. uv_px: (m, 2) their pixels.
        imu_before: the samples after the previous delivery and before the frame time
            (a live system receives them one by one: ``IncrementalSmoother.add_imu``).
        imu_closing: the sample at or after the frame time, which closes its interval
            (``add_frame(..., imu=...)``); empty past the end of the IMU.
    """

    k: int
    t_ns: int
    track_id: np.ndarray
    uv_px: np.ndarray
    imu_before: ImuSamples
    imu_closing: ImuSamples


def replay(flight: FlightLog) -> Iterator[FrameInput]:
    """The log's frames in order, each with its tracks and newly arrived IMU samples."""
    imu, tracks, t_frames = flight.imu, flight.tracks, flight.frames.t_ns
    n_frames = len(flight.frames)
    if tracks is not None:
        bounds = np.searchsorted(tracks.frame, np.arange(n_frames + 1))
    first_at_or_after = np.searchsorted(imu.t_ns, t_frames, side="left")
    no_ids, no_uv = np.zeros(0, np.int64), np.zeros((0, 2))

    def samples(a: int, b: int) -> ImuSamples:
        return ImuSamples(imu.t_ns[a:b], imu.gyro_radps[a:b], imu.acc_mps2[a:b])

    sent = 0
    for k in range(n_frames):
        first = int(first_at_or_after[k])
        before = max(first, sent)
        closing = max(min(first + 1, len(imu)), before)
        ids, uv = no_ids, no_uv
        if tracks is not None:
            rows = slice(int(bounds[k]), int(bounds[k + 1]))
            ids, uv = tracks.track_id[rows], tracks.uv_px[rows]
        yield FrameInput(k, int(t_frames[k]), ids, uv, samples(sent, before),
                         samples(before, closing))
        sent = closing
