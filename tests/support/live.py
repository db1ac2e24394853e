"""The live API fed a log frame by frame, as a live user would see it."""

from __future__ import annotations

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.smoother import FrameUpdate, IncrementalSmoother, SmootherSettings


def live_updates(log: FlightLog, dtm: Dtm, settings: SmootherSettings
                 ) -> tuple[np.ndarray, IncrementalSmoother, list[FrameUpdate]]:
    """``IncrementalSmoother.add_frame`` over a log (:meth:`~IncrementalSmoother.feed`):
    each frame's position NEES against the log's ground truth as its update reported it,
    the smoother, and the updates."""
    dt_s = float(np.median(np.diff(log.frames.t_ns))) * 1e-9
    smoother = IncrementalSmoother(log.config, dtm, settings, frame_interval_s=dt_s)
    updates: list[FrameUpdate] = []
    add = smoother.add_frame
    smoother.add_frame = lambda *a, **k: updates.append(add(*a, **k)) or updates[-1]
    smoother.feed(log)
    truth = log.groundtruth.interpolate(np.array([u.t_ns for u in updates])).position_m
    nees = []
    for u, p in zip(updates, truth):
        e, R = u.world_T_body[:3, 3] - p, u.world_T_body[:3, :3]
        nees.append(e @ np.linalg.solve(R @ u.pose_covariance[3:, 3:] @ R.T, e))
    return np.array(nees), smoother, updates
