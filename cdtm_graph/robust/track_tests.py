"""The batch smoother's track tests: terrain the DTM lacks, clutter and wrong matches,
judged over the whole flight at a solution, their tracks taken out of the log's graph.

The incremental smoothers judge the same tests frame by frame
(:class:`~cdtm_graph.robust.track_judge.TrackJudge`); both call
:func:`~cdtm_graph.robust.mismatch.heights_at` and
:func:`~cdtm_graph.robust.clutter.judge_with_clutter`.
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from cdtm_graph.calibration.online import CALIBRATION_KEY, calibrated_cameras
from cdtm_graph.dtm import Dtm
from cdtm_graph.graph.log_graph import LogGraph
from cdtm_graph.results import Rejection
from cdtm_graph.robust.clutter import Clutter, ClutterSettings, judge_with_clutter
from cdtm_graph.robust.mismatch import MismatchSettings, TrackJudgement, heights_at, untrusted
from factors import FeatureNoise


class BatchTrackTests:
    """The track tests of a batch run, between its solves.

    Attributes:
        found_off: the tracks found off the DTM so far (sorted ids).
        clutter: the latest clutter fit.
    """

    def __init__(self, dtm: Dtm, noise: FeatureNoise, body_T_cam: np.ndarray,
                 mismatch: MismatchSettings, clutter: ClutterSettings | None):
        self.dtm, self.noise, self.body_T_cam = dtm, noise, body_T_cam
        self.mismatch, self.clutter_settings = mismatch, clutter
        self.found_off = np.zeros(0, np.int64)
        self.clutter = Clutter.none()

    def assess(self, built: LogGraph, values: gtsam.Values) -> TrackJudgement:
        """Judge every track that entered ``built`` at ``values`` (the ones dropped since
        too: a population's clutter is seen with its tallest members); keeps the clutter
        fit."""
        track_id, frame, ray = built.observed

        def at_stamp(k: int) -> np.ndarray:
            return values.atPose3(X(k)).matrix()

        pose: Callable[[int], np.ndarray] = at_stamp
        body_T_cam = self.body_T_cam
        if built.twists is not None:  # the cameras as calibrated
            pose, body_T_cam, ray = calibrated_cameras(
                pose, body_T_cam, ray, built.twists, values.atVector(CALIBRATION_KEY))
        judged, self.clutter = judge_with_clutter(
            heights_at(track_id, frame, ray, pose, body_T_cam, self.dtm, self.noise),
            self.noise.sigma_h_m, self.mismatch, self.clutter_settings)
        return judged

    def drop_mismatched(self, built: LogGraph, values: gtsam.Values) -> int:
        """Drop the features of tracks judged at ``values`` off the DTM (or not to be
        trusted beside those, :func:`~cdtm_graph.robust.mismatch.untrusted`), likely on
        clutter (:mod:`cdtm_graph.robust.clutter`) or holding a wrong match; how many
        features went."""
        judged = self.assess(built, values)
        self.found_off = np.union1d(self.found_off, judged.off_map)
        off = untrusted(*built.observed[:2], self.found_off, self.mismatch.frame_fraction)
        before = built.rejections.total()
        built.drop_tracks(judged.inconsistent, Rejection.WRONG_MATCH)
        built.drop_tracks(np.union1d(off, self.clutter.likely(self.clutter_settings)),
                          Rejection.MAP_MISMATCH)
        return built.rejections.total() - before
