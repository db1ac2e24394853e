"""The whole log's graph: priors, IMU factors and C-DTM factors of every frame.

Built once from an initial guess for the batch solver (:func:`~cdtm_graph.smoother.smooth`)
and for the calibration check's side solve (:mod:`cdtm_graph.calibration.check`); the
batch's track tests (:class:`~cdtm_graph.robust.track_tests.BatchTrackTests`) take tracks
out of it between solves.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from cdtm_graph.calibration.online import CALIBRATION_KEY, body_twists
from cdtm_graph.calibration.online import prior_factor as calibration_prior
from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import CalibrationSigmas, FlightLog
from cdtm_graph.graph.builders import (
    GraphSettings,
    feature_noise,
    imu_factor,
    prior_factors,
    track_observations,
    without_tracks,
)
from cdtm_graph.imu import ImuIntervals, initial_bias
from cdtm_graph.replay import replay
from cdtm_graph.results import GraphCounts, Rejection, Rejections
from cdtm_graph.robust.stages import BuildFactors, FrameWork, Stages, batch_stages
from cdtm_graph.tracks import SightingPairs
from factors import CdtmPairFactor


@dataclass
class LogGraph:
    """Everything the batch solver builds from a log."""

    base: gtsam.NonlinearFactorGraph  # priors and IMU factors
    values: gtsam.Values
    counts: GraphCounts
    cdtm: list[CdtmPairFactor]
    track_ids: list[np.ndarray]  # each C-DTM factor's features'
    rejections: Rejections
    # every observation that entered a factor (the tracks dropped since too: the shares of
    # off-map tracks are of everything a frame saw)
    observed: tuple[np.ndarray, np.ndarray, np.ndarray] = (
        np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))
    # the online calibration's body twists (K, 6), when the calibration is estimated
    twists: np.ndarray | None = None
    stages: Stages | None = None  # what the sightings passed through (report.json)

    @property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(self.base)
        for f in self.cdtm:
            graph.add(f.factor)
        return graph

    def at_calibration(self, values: gtsam.Values) -> list[CdtmPairFactor]:
        """The C-DTM factors held at the calibration in ``values`` (for the checks after
        a solve, which see the poses alone); the factors themselves without one."""
        if self.twists is None:
            return self.cdtm
        c = values.atVector(CALIBRATION_KEY)
        return [f.with_calibration(f.calibration.fixed_at(c)) if f.calibration else f
                for f in self.cdtm]

    def drop_tracks(self, drop: np.ndarray, reason: Rejection) -> None:
        """Take the ``drop`` tracks' features out of the C-DTM factors, counted for
        ``reason``."""
        if drop.size == 0:
            return
        changed, replacements, kept = without_tracks(self.cdtm, self.track_ids, drop,
                                                     reason, self.rejections)
        swap = dict(zip(changed, zip(replacements, kept)))
        cdtm, track_ids = [], []
        for i, (f, ids) in enumerate(zip(self.cdtm, self.track_ids)):
            g, g_ids = swap.get(i, (f, ids))
            if g is not None:
                cdtm.append(g)
                track_ids.append(g_ids)
        self.cdtm, self.track_ids = cdtm, track_ids

    def refresh_noise(self, values: gtsam.Values) -> None:
        """Re-linearize every C-DTM factor's planes and noise at ``values``."""
        poses = {k: values.atPose3(X(k)).matrix() for k in range(self.counts.n_frames)}
        self.cdtm = [f.refreshed(poses[int(gtsam.Symbol(f.key_a).index())],
                                 poses[int(gtsam.Symbol(f.key_b).index())]) for f in self.cdtm]


def build_log_graph(flight: FlightLog, dtm: Dtm, settings: GraphSettings,
                    initial: gtsam.Values, off_map: np.ndarray | None = None,
                    unfixed_frames: np.ndarray | None = None,
                    calibration: CalibrationSigmas | None = None,
                    imu_rotations: bool = False) -> LogGraph:
    """Priors, IMU factors and C-DTM factors of the whole log, planes cast from ``initial``.

    Sightings are paired frame by frame as the incremental smoother pairs them
    (:class:`~cdtm_graph.tracks.SightingPairs`: wrong matches left out against the
    initial guess's relative poses). Tracks in ``off_map`` (found off the DTM by the
    incremental pass) are left out, counted as ``Rejection.MAP_MISMATCH``, and so are
    the sightings of ``unfixed_frames`` (``Rejection.NO_FIX``: the pass never found the fix
    their linearization needs). With ``calibration`` (prior sigmas), the camera calibration
    is estimated too (``C(0)``, :mod:`cdtm_graph.calibration.online`; ``initial`` must hold it).
    With ``imu_rotations``, the epipolar check takes the relative rotations from the IMU
    (each interval's preintegrated rotation, chained; anew after an IMU gap) instead of
    from ``initial``: a nav.csv's attitudes may be noisy frame to frame (GNSS with a
    compass), and 0.5 deg of white noise there left 4% of a clean log's features out as
    wrong matches.
    """
    K = len(flight.frames)
    t = flight.frames.t_ns
    graph = prior_factors(flight.config.initial_state)
    intervals = ImuIntervals(flight.config, flight.imu, settings.imu_hold,
                             settings.earth_physics, settings.imu_gap_noise)
    bias0 = initial_bias(flight.config.initial_state)
    poses = [initial.atPose3(X(k)).matrix() for k in range(K)]
    checked = [p.copy() for p in poses]  # the poses the epipolar check sees
    for k in range(K - 1):  # (the Earth model places each interval from the initial guess)
        start = (initial.atPose3(X(k)).matrix(), initial.atVector(V(k)))
        pim = intervals.preintegrate(int(t[k]), int(t[k + 1]), bias0, start)
        graph.add(imu_factor(k, pim))
        if imu_rotations and not pim.spans_gap:
            checked[k + 1][:3, :3] = checked[k][:3, :3] @ pim.deltaRij().matrix()
    twists = None
    if calibration is not None:
        graph.add(calibration_prior(calibration))
        twists = body_twists(t, flight.imu, initial_bias(flight.config.initial_state).gyroscope(),
                             np.stack(poses), np.stack([initial.atVector(V(k)) for k in range(K)]))
    rejections = Rejections()
    camera = flight.config.camera
    pairing = SightingPairs(camera.camera, camera.body_T_cam, dtm, camera.pixel_sigma_px,
                            settings.epipolar, rejections)
    build = BuildFactors(camera.body_T_cam, dtm, feature_noise(flight.config, dtm, settings),
                         settings, rejections,
                         None if twists is None else (CALIBRATION_KEY, twists))
    stages = batch_stages(pairing, build, unfixed_frames, off_map, rejections)
    view = _BeforeSolving(checked.__getitem__, poses)
    factors: list[CdtmPairFactor] = []
    track_ids: list[np.ndarray] = []
    per_frame = np.zeros(K, dtype=int)
    for frame in replay(flight):
        work = stages.run(FrameWork(frame.k, frame.track_id, frame.uv_px), view)
        factors += work.factors
        track_ids += work.track_ids
        per_frame[frame.k] += work.n_features
    counts = GraphCounts(
        K, pairing.table.n_tracks, pairing.n_observations, pairing.n_pairs,
        int(per_frame.sum()), len(factors), K - 1, per_frame,
        outliers_per_frame=np.zeros(K, dtype=int), rejected_per_frame=rejections.per_frame(K))
    observed = track_observations(factors, track_ids)
    return LogGraph(graph, initial, counts, factors, track_ids, rejections, observed,
                    twists=twists, stages=stages)


class _BeforeSolving:
    """The :class:`~cdtm_graph.robust.stages.SolverView` of a graph built from an initial
    guess: no solver runs yet, nothing has left it, nothing is judged."""

    def __init__(self, pose_guess: Callable[[int], np.ndarray], poses: list[np.ndarray]):
        self._pose_guess, self._poses = pose_guess, poses

    settled = property(lambda self: 0)
    lagged = property(lambda self: False)
    converging = property(lambda self: False)

    @property
    def poses(self) -> Sequence[np.ndarray]:
        return self._poses

    def pose_guess(self, j: int) -> np.ndarray:
        return self._pose_guess(j)

    def pair_prior(self) -> None:
        return None

    def position_sigma_m(self) -> float:
        return float("inf")

    def forget_tracks(self, track_ids: np.ndarray, reason: Rejection) -> None:
        raise AssertionError("a graph built from an initial guess judges no tracks")
