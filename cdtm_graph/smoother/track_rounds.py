"""The incremental smoother's rounds over its recent tracks, every few frames and as a run
ends: the track judge's (terrain the DTM lacks, wrong matches, clutter:
:class:`~cdtm_graph.robust.track_judge.TrackJudge`) and, in a fixed lag, the map's shape
across the footprints at the same poses (:class:`~cdtm_graph.robust.map_error.
BroadMapWatch`), and the map's height error (:class:`~cdtm_graph.smoother.map_growth.
MapGrowth`), each charged to its own entry of report.json's ``stages``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cdtm_graph.results import Rejection
from cdtm_graph.robust.map_error import BroadMapWatch
from cdtm_graph.robust.stages import Stages
from cdtm_graph.robust.track_judge import TrackJudge
from cdtm_graph.smoother.map_growth import MapGrowth
from cdtm_graph.smoother.window import SolverWindow

#: The track tests' rounds over many frames, charged apart from the frames' stages.
TRACK_ROUNDS = "track_rounds"
#: ... and the fixed lag's shape of the map at them.
BROAD_MAP_WATCH = "broad_map_watch"
#: ... and the map's height error read as the flight goes.
MAP_ERROR_WATCH = "map_error_watch"


class TrackRounds:
    """One round: the tracks seen since a frame judged at the current estimate, the ones
    left out taken out of the solver (``forget``: track ids, reason); then the shape and
    the map's height error.

    Args:
        judge: the run's track judge. watch: the fixed lag's shape watch, or None.
        window: the solver's side. stages: where the rounds are charged.
        forget: keeps tracks out from now on and takes their features out of the solver.
        map_growth: reads the map's height error and grows it, or None.
    """

    def __init__(self, judge: TrackJudge, watch: BroadMapWatch | None, window: SolverWindow,
                 stages: Stages, forget: Callable[[np.ndarray, Rejection], None],
                 map_growth: MapGrowth | None = None):
        self.judge, self.watch, self.window = judge, watch, window
        self.stages, self.forget, self.map_growth = stages, forget, map_growth

    def run(self, k: int, since_frame: int) -> int:
        """The round at frame k over the tracks seen since ``since_frame``, then the map's
        shape over the frames whose windows have closed, at the poses held then
        (:meth:`BroadMapWatch.round`), and, when due, its height error from the round's
        tracks (:meth:`MapGrowth.read`); how many tracks it left out, one more if the map
        grew (a run's end iterates while a round changes anything)."""
        with self.stages.charged(TRACK_ROUNDS, (Rejection.MAP_MISMATCH, Rejection.WRONG_MATCH)):
            n = self._judged(k, since_frame)
        if self.watch is not None:
            w = self.window
            with self.stages.charged(BROAD_MAP_WATCH, ()):
                self.watch.round(self.judge, w.t_ns, w.pose_guess, w.frame_position_sigma_m,
                                 w.frame_pose_covariance)
        if self.map_growth is not None and self.map_growth.watch.due():
            with self.stages.charged(MAP_ERROR_WATCH, ()):
                n += self.map_growth.read(k)  # (a grown map asks the solver to iterate too)
        return n

    def _judged(self, k: int, since_frame: int) -> int:
        w = self.window
        off, wrong = self.judge.round(since_frame, w.pose_guess, w.frame_position_sigma_m)
        if off.size:
            self.forget(off, Rejection.MAP_MISMATCH)
        if wrong.size:
            self.forget(wrong, Rejection.WRONG_MATCH)
        if off.size or wrong.size:
            w.fetch(k)
        recent = w.since(since_frame)
        self.judge.consider(since_frame, k, w.cdtm[recent:], w.ids[recent:])
        return int(off.size + wrong.size)
