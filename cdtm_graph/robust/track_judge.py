"""The incremental smoother's judge of tracks: terrain the DTM lacks, clutter, wrong matches.

:class:`TrackJudge` keeps the observations that entered the solver and, at the solver's
current poses, judges tracks with the views of :mod:`cdtm_graph.robust.mismatch` (alone, with
their neighbourhood, their rays' fit) and :mod:`cdtm_graph.robust.clutter` (the population of
heights). It decides; the smoother takes the features out of its solver.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import gtsam
import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.results import Rejection, Rejections
from cdtm_graph.robust.clutter import (
    Clutter,
    ClutterSettings,
    considered_offsets,
    judge_with_clutter,
)
from cdtm_graph.robust.mismatch import (
    MismatchSettings,
    TrackHeights,
    heights_at,
    judge,
    untrusted,
)
from cdtm_graph.tracks import TrackObservations
from factors import CdtmPairFactor, FeatureNoise

#: Frame index -> the solver's pose of that frame now (4x4 world_T_body).
PoseOf = Callable[[int], np.ndarray]


def _frame(key: int) -> int:
    return int(gtsam.Symbol(key).index())


def _frame_sigmas(frame: np.ndarray, position_sigma_of: Callable[[int], float]) -> np.ndarray:
    """Each frame's own position 1-sigma, one per ``np.unique(frame)``: where features
    went, the poses are weak."""
    return np.array([position_sigma_of(int(j)) for j in np.unique(frame)])


class TrackJudge:
    """Which tracks to leave out, judged as the flight goes.

    Args:
        mismatch: the track tests. clutter: the population view (``None``: none).
        dtm, noise, body_T_cam: the map, the features' noise, the camera mount.
        rejections: where the features left out of new factors are counted.
    """

    #: Every this many frames, the tracks of the last ``WINDOW_FRAMES`` frames are judged
    #: together at the current estimate (a pit the first frames' features pulled the
    #: estimate into shows once some of them are gone).
    EVERY_FRAMES = 5
    WINDOW_FRAMES = 20

    def __init__(self, mismatch: MismatchSettings, clutter: ClutterSettings | None, dtm: Dtm,
                 noise: FeatureNoise, body_T_cam: np.ndarray, rejections: Rejections,
                 observations: TrackObservations | None = None):
        self.mismatch = mismatch
        self.clutter_settings = clutter
        self.dtm = dtm
        self.noise = noise
        self.body_T_cam = body_T_cam
        self.rejections = rejections
        self.left_out = np.zeros(0, np.int64)  # sorted: tracks kept out from now on
        # what entered the solver (a full history's: :class:`~cdtm_graph.robust.
        # observations.TieredObservations`)
        self.observations = TrackObservations() if observations is None else observations
        self.clutter = Clutter.none()  # the latest fit of the tracks' heights
        self.considered_m: dict[int, float] = {}  # frame -> vertical offset it may carry
        self._found_off = np.zeros(0, np.int64)  # tracks the tests themselves found off
        self._judge_from: int | None = None  # tracks seen from this frame on are judged
        # the latest round's heights, its observations' tracks and frames, the frames'
        # position sigmas (:meth:`last_round_heights`)
        self._last_round: tuple[TrackHeights, np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def judging(self) -> bool:
        return self._judge_from is not None

    @property
    def judged_from(self) -> int | None:
        """The first frame whose tracks are judged (the poses settled there), if any."""
        return self._judge_from

    def settle(self, k: int, position_sigma_m: float) -> bool:
        """Whether the poses are known well enough to judge a track's height against the
        DTM: frame k's within twice the DTM's height error (after the first frames under
        a loose prior; tracks seen before the first such frame are never judged)."""
        if self._judge_from is None and position_sigma_m <= 2 * self.noise.sigma_h_m:
            self._judge_from = k
        return self.judging

    def due(self, k: int) -> bool:
        """Whether frame k holds a round over the window's tracks."""
        return self.judging and k % self.EVERY_FRAMES == 0

    def window_start(self, k: int) -> int:
        assert self._judge_from is not None
        return max(self._judge_from, k - self.WINDOW_FRAMES)

    def record(self, k: int, factors: Sequence[CdtmPairFactor],
               track_ids: Sequence[np.ndarray]) -> None:
        """The observations of factors that entered the solver, frame k their later one."""
        for f, ids in zip(factors, track_ids):
            self.observations.add(np.concatenate((ids, ids)),
                                  np.repeat([_frame(f.key_a), k], ids.size),
                                  np.concatenate((f.features.q_a, f.features.q_b)))

    def first_recorded(self, track_ids: np.ndarray) -> int:
        """The earliest frame at which any of these tracks entered the solver (as recorded,
        from the oldest frame still held on); past every frame if none has."""
        _, frame, _ = self.observations.of(track_ids)
        return int(frame.min()) if frame.size else np.iinfo(np.int64).max

    def leave_out(self, track_ids: np.ndarray) -> None:
        """Keep these tracks out from now on (off the map, or holding a wrong match)."""
        self.left_out = np.union1d(self.left_out, track_ids)

    def judge_new(self, k: int, factors: list[CdtmPairFactor], track_ids: list[np.ndarray],
                  pose_of: PoseOf, position_sigma_m: float
                  ) -> tuple[list[CdtmPairFactor], list[np.ndarray], np.ndarray, np.ndarray]:
        """Frame k's factors without the tracks that, triangulated from everything seen of
        them so far and this frame, lie off the DTM or hold a wrong match (counted); and
        the ids of both (for the smoother to take their earlier features out)."""
        none = np.zeros(0, np.int64)
        # this frame's observations (and the earlier ones of tracks seen for the first
        # time) with everything recorded of their tracks
        tid, frame, q = self.observations.of(none, extra=(
            np.concatenate((*track_ids, *track_ids)),
            np.concatenate((*(np.full(i.size, k) for i in track_ids),
                            *(np.full(i.size, _frame(f.key_a))
                              for f, i in zip(factors, track_ids)))),
            np.concatenate((*(f.features.q_b for f in factors),
                            *(f.features.q_a for f in factors)))))
        # tracks seen before the poses settled are not judged (their early poses were off)
        assert self._judge_from is not None
        early = frame < self._judge_from
        if early.any():
            judged = ~np.isin(tid, tid[early])
            tid, frame, q = tid[judged], frame[judged], q[judged]
        if tid.size == 0:
            return factors, track_ids, none, none
        judgement = judge(self._heights(tid, frame, q, pose_of, position_sigma_m),
                          self.noise.sigma_h_m, self.mismatch)
        off, wrong = judgement.off_map, judgement.inconsistent
        self._found_off = np.union1d(self._found_off, off)
        if off.size == 0 and wrong.size == 0:
            return factors, track_ids, off, wrong
        kept, kept_ids = [], []
        for f, ids in zip(factors, track_ids):
            hit_off, hit_wrong = np.isin(ids, off), np.isin(ids, wrong)
            self.rejections.add(Rejection.MAP_MISMATCH, k, int(hit_off.sum()))
            self.rejections.add(Rejection.WRONG_MATCH, k, int((hit_wrong & ~hit_off).sum()))
            hit = hit_off | hit_wrong
            if not hit.all():
                kept.append(f.with_features(~hit) if hit.any() else f)
                kept_ids.append(ids[~hit])
        return kept, kept_ids, off, wrong

    def round(self, since_frame: int, pose_of: PoseOf,
              position_sigma_of: Callable[[int], float]) -> tuple[np.ndarray, np.ndarray]:
        """Judge every track seen since ``since_frame`` (after the poses settled) at the
        current poses, each frame with its own position 1-sigma: the ids to leave out as
        off the map (with the crowded frames' and the likely clutter) and as wrong matches.
        """
        none = np.zeros(0, np.int64)
        self._last_round = None
        if self._judge_from is None:
            return none, none
        # every observation of them, the tracks left out too (crowding, clutter)
        all_tid, all_frame, all_q = self._seen_since(since_frame)
        tid, frame, q = self._settled(all_tid, all_frame, all_q)
        if tid.size == 0:
            return none, none
        sigmas = _frame_sigmas(frame, position_sigma_of)
        heights = self._heights(tid, frame, q, pose_of, sigmas)
        self._last_round = (heights, tid, frame, sigmas)
        judgement, self.clutter = judge_with_clutter(
            heights, self.noise.sigma_h_m, self.mismatch, self.clutter_settings)
        self._found_off = np.union1d(self._found_off, judgement.off_map)
        off = np.setdiff1d(np.union1d(untrusted(all_tid, all_frame, self._found_off,
                                                self.mismatch.frame_fraction),
                                      self.clutter.likely(self.clutter_settings)),
                           self.left_out)
        wrong = np.setdiff1d(judgement.inconsistent, np.r_[self.left_out, off])
        return off, wrong

    def last_round_heights(self) -> TrackHeights | None:
        """The latest :meth:`round`'s tracks, the left out ones too (a map worse than
        stated is what the tests drop first), their ``sigma_m`` with the cameras taken as
        exact (:func:`~cdtm_graph.robust.map_error.run_heights`' convention: each track's
        largest camera position variance taken out); None if it judged none, or found
        clutter on the ground (trees, buildings: what the map lacks above it, which the
        tests drop and the map's error must not take in)."""
        if self._last_round is None or (self.clutter.significant
                                        and self.clutter.height_m > 0.0):
            return None
        heights, tid, frame, sigmas = self._last_round
        pose_var = np.zeros(heights.track_id.size)
        np.maximum.at(pose_var, np.searchsorted(heights.track_id, tid),
                      sigmas[np.searchsorted(np.unique(frame), frame)] ** 2)
        return dataclasses.replace(heights, sigma_m=np.sqrt(np.maximum(
            heights.sigma_m**2 - pose_var, 0.0)))

    def heights_since(self, since_frame: int, pose_of: PoseOf,
                      position_sigma_of: Callable[[int], float]
                      ) -> tuple[TrackHeights, np.ndarray, np.ndarray]:
        """The tracks seen since ``since_frame`` (after the poses settled) triangulated
        at the current poses as :meth:`round` has them, but the ones left out; with the
        (M,) tracks and frames of their observations (their times). Nothing before the
        poses settled."""
        none = np.zeros(0, np.int64)
        if self._judge_from is None:
            return TrackHeights.empty(), none, none
        tid, frame, q = self._settled(*self._seen_since(since_frame))
        if tid.size == 0:
            return TrackHeights.empty(), none, none
        heights = self._heights(tid, frame, q, pose_of,
                                _frame_sigmas(frame, position_sigma_of))
        return heights.subset(~np.isin(heights.track_id, self.left_out)), tid, frame

    def _seen_since(self, since_frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every recorded observation of the tracks seen since ``since_frame`` (and since
        the poses settled)."""
        assert self._judge_from is not None
        return self.observations.of(self.observations.since(max(since_frame,
                                                                self._judge_from)))

    def _settled(self, tid: np.ndarray, frame: np.ndarray, q: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """These observations but those of tracks seen before the poses settled."""
        assert self._judge_from is not None
        judged = ~np.isin(tid, tid[frame < self._judge_from])
        return tid[judged], frame[judged], q[judged]

    def consider(self, since_frame: int, k: int, factors: Sequence[CdtmPairFactor | None],
                 track_ids: Sequence[np.ndarray]) -> None:
        """The clutter the live factors ending since ``since_frame`` may still hold, frame
        by frame (:func:`~cdtm_graph.robust.clutter.considered_offsets`)."""
        live = [(f, ids) for f, ids in zip(factors, track_ids)
                if f is not None and _frame(f.key_b) >= since_frame]
        offsets = considered_offsets(self.clutter, [f.key_a for f, _ in live],
                                     [f.key_b for f, _ in live], [i for _, i in live], k + 1)
        for j in range(since_frame, k + 1):
            self.considered_m[j] = float(offsets[j])

    def considered(self, n_frames: int) -> np.ndarray:
        """(K,) each frame's considered vertical offset (m)."""
        return np.array([self.considered_m.get(k, 0.0) for k in range(n_frames)])

    def _heights(self, tid: np.ndarray, frame: np.ndarray, q: np.ndarray, pose_of: PoseOf,
                 position_sigma_m: float | np.ndarray) -> TrackHeights:
        """These observations' tracks triangulated at the given poses (the frames' position
        1-sigma scalar or per frame of ``np.unique(frame)``)."""
        return heights_at(tid, frame, q, pose_of, self.body_T_cam, self.dtm, self.noise,
                          position_sigma_m)
