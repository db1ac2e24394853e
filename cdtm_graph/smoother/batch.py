"""Batch smoothing of a whole log: Levenberg-Marquardt from a good initial guess, marginals.

``smooth(log, dtm, settings) -> SmootherResult`` does no file I/O. The solver drives
Levenberg-Marquardt from Python over ``graph.linearize(values)`` (:mod:`~cdtm_graph.
optimizer`): GTSAM's own optimizers hand every ``CustomFactor`` call a fresh copy of all
values, which makes an iteration quadratic in the flight length.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.gating import residual_test
from cdtm_graph.graph import (
    cdtm_factors,
    cdtm_information,
    feature_noise,
    imu_factor,
    insert_state,
    mismatched_tracks,
    prior_factors,
    without_tracks,
)
from cdtm_graph.imu import ImuIntervals, initial_bias
from cdtm_graph.mismatch import MismatchSettings
from cdtm_graph.optimizer import LinearSolver, explain_indeterminant, levenberg_marquardt
from cdtm_graph.preflight import check_constraints
from cdtm_graph.replay import replay
from cdtm_graph.results import (
    GraphCounts,
    Rejection,
    Rejections,
    SmootherResult,
    SolverStats,
    StateCovariances,
    TrajectoryEstimate,
    frame_flags,
)
from cdtm_graph.smoother.incremental import IncrementalSmoother
from cdtm_graph.smoother.settings import Progress, SmootherMode, SmootherSettings
from cdtm_graph.tracks import SightingPairs
from factors import CdtmPairFactor, FeatureNoise

#: Rounds of "drop the tracks off the DTM, solve again" (each finds what the last one's
#: estimate, no longer pulled by the worst, reveals).
MISMATCH_ROUNDS = 8


def _estimate_from_values(values: gtsam.Values, t_ns: np.ndarray) -> TrajectoryEstimate:
    K = t_ns.shape[0]
    poses = np.stack([values.atPose3(X(k)).matrix() for k in range(K)])
    vel = np.stack([values.atVector(V(k)) for k in range(K)])
    biases = [values.atConstantBias(B(k)) for k in range(K)]
    return TrajectoryEstimate(
        t_ns=np.asarray(t_ns, dtype=np.int64), world_T_body=poses, velocity_mps=vel,
        gyro_bias=np.stack([b.gyroscope() for b in biases]),
        accel_bias=np.stack([b.accelerometer() for b in biases]))


def marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
              K: int, qr_only: bool = False) -> StateCovariances:
    """Per-frame marginals from a Bayes tree of the graph linearized at ``values``.

    Cholesky first (as ``gtsam.Marginals``); where it declares the system indeterminant,
    which happens on these wide-range systems (information from ~1e-4 for the pose prior
    to ~1e10 for the bias random walk), QR, which does not square the condition number.
    """
    linear = graph.linearize(values)
    for qr in (True,) if qr_only else (False, True):
        try:
            tree = (linear.eliminateMultifrontal(function=gtsam.EliminateQR) if qr
                    else linear.eliminateMultifrontal())

            def cov(key: int, tree=tree, qr=qr) -> np.ndarray:
                marginal = (tree.marginalFactor(key, gtsam.EliminateQR) if qr
                            else tree.marginalFactor(key))
                # information() includes the conditional's noise model (QR leaves sigmas)
                return np.linalg.inv(marginal.information())

            pose = np.stack([cov(X(k)) for k in range(K)])
            vel = np.stack([cov(V(k)) for k in range(K)])
            bias = np.stack([cov(B(k)) for k in range(K)])
            return StateCovariances(pose, vel, bias)
        except RuntimeError as exc:
            error = exc
    raise explain_indeterminant(error) from None


@dataclass
class LogGraph:
    """Everything the batch solver builds from a log."""

    base: gtsam.NonlinearFactorGraph  # priors and IMU factors
    values: gtsam.Values
    counts: GraphCounts
    cdtm: list[CdtmPairFactor]
    track_ids: list[np.ndarray]  # each C-DTM factor's features'
    rejections: Rejections

    @property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(self.base)
        for f in self.cdtm:
            graph.add(f.factor)
        return graph

    def drop_mismatched(self, values: gtsam.Values, dtm: Dtm, noise: FeatureNoise,
                        body_T_cam: np.ndarray, settings: MismatchSettings) -> int:
        """Drop the features of tracks that lie off the DTM at ``values``; how many."""
        drop = mismatched_tracks(self.cdtm, self.track_ids,
                                 lambda k: values.atPose3(X(k)).matrix(), body_T_cam, dtm,
                                 noise, settings)
        if drop.size == 0:
            return 0
        before = self.rejections.total(Rejection.MAP_MISMATCH)
        changed, replacements, kept = without_tracks(self.cdtm, self.track_ids, drop,
                                                     Rejection.MAP_MISMATCH, self.rejections)
        swap = dict(zip(changed, zip(replacements, kept)))
        cdtm, track_ids = [], []
        for i, (f, ids) in enumerate(zip(self.cdtm, self.track_ids)):
            g, g_ids = swap.get(i, (f, ids))
            if g is not None:
                cdtm.append(g)
                track_ids.append(g_ids)
        self.cdtm, self.track_ids = cdtm, track_ids
        return self.rejections.total(Rejection.MAP_MISMATCH) - before

    def refresh_noise(self, values: gtsam.Values) -> None:
        """Re-linearize every C-DTM factor's planes and noise at ``values``."""
        poses = {k: values.atPose3(X(k)).matrix() for k in range(self.counts.n_frames)}
        self.cdtm = [f.refreshed(poses[int(gtsam.Symbol(f.key_a).index())],
                                 poses[int(gtsam.Symbol(f.key_b).index())]) for f in self.cdtm]


def _initial_values(flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
                    progress: Progress | None) -> tuple[gtsam.Values, str, np.ndarray]:
    """Initial guess: nav.csv if present, else the incremental pass (dead reckoning
    corrected frame by frame); and the tracks that pass found off the DTM."""
    if flight.nav is not None:
        values = gtsam.Values()
        bias = initial_bias(flight.config.initial_state)
        for k in range(len(flight.frames)):
            insert_state(values, k, flight.nav.world_T_body[k], flight.nav.velocity_mps[k],
                         bias)
        return values, "nav.csv", np.zeros(0, np.int64)
    incremental = replace(settings, mode=SmootherMode.INCREMENTAL, lag_s=None)
    smoother = IncrementalSmoother(flight.config, dtm, incremental, imu=flight.imu)
    smoother.run(flight, progress)
    return smoother.values(), "incremental pass", smoother.mismatched_tracks


def build_log_graph(flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
                    initial: gtsam.Values, off_map: np.ndarray | None = None) -> LogGraph:
    """Priors, IMU factors and C-DTM factors of the whole log, planes cast from ``initial``.

    Sightings are paired frame by frame as the incremental smoother pairs them
    (:class:`~cdtm_graph.tracks.SightingPairs`: wrong matches left out against the
    initial guess's relative poses). Tracks in ``off_map`` (found off the DTM by the
    incremental pass) are left out, counted as ``Rejection.MAP_MISMATCH``.
    """
    K = len(flight.frames)
    t = flight.frames.t_ns
    graph = prior_factors(flight.config.initial_state)
    intervals = ImuIntervals(flight.config, flight.imu, settings.graph.imu_hold)
    bias0 = initial_bias(flight.config.initial_state)
    for k in range(K - 1):
        graph.add(imu_factor(k, intervals.preintegrate(int(t[k]), int(t[k + 1]), bias0)))
    poses = [initial.atPose3(X(k)).matrix() for k in range(K)]
    rejections = Rejections()
    camera = flight.config.camera
    pairing = SightingPairs(camera.camera, camera.body_T_cam, dtm, camera.pixel_sigma_px,
                            settings.graph.epipolar, rejections)
    pairs = []
    for frame in replay(flight):
        if len(frame.track_id):
            for pair in pairing.add_frame(frame.k, frame.track_id, frame.uv_px,
                                          poses.__getitem__):
                off = (np.isin(pair.track_id, off_map) if off_map is not None
                       else np.zeros(pair.track_id.size, dtype=bool))
                rejections.add(Rejection.MAP_MISMATCH, frame.k, int(off.sum()))
                if not off.all():
                    pairs.append(pair.subset(~off) if off.any() else pair)
    build = cdtm_factors(pairs, poses, camera.body_T_cam, dtm,
                         feature_noise(flight.config, dtm, settings.graph), settings.graph,
                         rejections)
    per_frame = np.zeros(K, dtype=int)
    for k, n in build.features_per_frame.items():
        per_frame[k] = n
    counts = GraphCounts(
        K, pairing.table.n_tracks, pairing.n_observations, pairing.n_pairs, build.n_features,
        len(build.factors), K - 1, per_frame, outliers_per_frame=np.zeros(K, dtype=int),
        rejected_per_frame=rejections.per_frame(K))
    return LogGraph(graph, initial, counts, build.factors, build.track_ids, rejections)


def smooth(flight: FlightLog, dtm: Dtm, settings: SmootherSettings | None = None,
           progress: Progress | None = None) -> SmootherResult:
    """Smooth a flight log (batch LM, or the incremental smoother's pass).

    Args:
        flight: the log (``read_flightlog``). dtm: its terrain (``load_dtm``).
        settings: solver settings. progress: per-frame callback on long runs.

    Returns:
        Smoothed states, per-frame covariances, statistics and counts.

    Raises:
        SolverError: indeterminant system (names the variable and the likely cause).
        FlightLogError: the log has fewer than two frames.
        NoConstraintError: no camera or DTM constraint at all (``preflight``).
    """
    settings = settings or SmootherSettings()
    if len(flight.frames) < 2:
        raise FlightLogError(f"{flight.root / 'frames.csv'}: {len(flight.frames)} frame(s); "
                             "expected at least 2")
    check_constraints(flight, dtm)  # no camera/DTM constraint at all: refuse, not IMU-only
    if settings.mode is SmootherMode.INCREMENTAL:
        dt_s = float(np.max(np.diff(flight.frames.t_ns))) * 1e-9
        smoother = IncrementalSmoother(flight.config, dtm, settings, frame_interval_s=dt_s)
        return smoother.run(flight, progress)
    initial, source, off_map = _initial_values(flight, dtm, settings, progress)
    built = build_log_graph(flight, dtm, settings, initial, off_map)
    solver = LinearSolver()
    values, first = levenberg_marquardt(built.graph, initial, settings.max_iterations,
                                        settings.relative_error_tol, solver=solver)
    # The C-DTM noise (eqs. 19-26) was linearized at the initial guess; evaluate it at the
    # estimate and finish there, so the solution does not depend on the initial guess.
    built.refresh_noise(values)
    graph = built.graph
    values, stats = levenberg_marquardt(graph, values, settings.max_iterations,
                                        settings.relative_error_tol, solver=solver)
    iterations = first.iterations + stats.iterations
    # Terrain the DTM lacks: drop the tracks off the map and solve again, until none is.
    mismatch = settings.graph.mismatch
    noise = feature_noise(flight.config, dtm, settings.graph)
    for _ in range(MISMATCH_ROUNDS if mismatch is not None else 0):
        assert mismatch is not None
        if not built.drop_mismatched(values, dtm, noise, flight.config.camera.body_T_cam,
                                     mismatch):
            break
        graph = built.graph
        values, more = levenberg_marquardt(graph, values, settings.max_iterations,
                                           settings.relative_error_tol, solver=solver)
        iterations += more.iterations
        stats = replace(more, time_s=stats.time_s + more.time_s)
    K = len(flight.frames)
    start = time.perf_counter()
    covariances = (marginals(graph, values, K) if settings.marginals else
                   StateCovariances(np.full((K, 6, 6), np.nan), np.full((K, 3, 3), np.nan),
                                    np.full((K, 6, 6), np.nan)))
    stats = SolverStats(stats.solver, iterations, first.initial_error,
                        stats.final_error, stats.converged, first.time_s + stats.time_s,
                        time.perf_counter() - start)
    settings_dict = settings.to_dict()
    settings_dict["initial_values"] = source
    estimate = _estimate_from_values(values, flight.frames.t_ns)
    residuals = residual_test(built.cdtm, estimate.world_T_body, K)
    per_frame = np.zeros(K, dtype=int)
    for f in built.cdtm:
        per_frame[int(gtsam.Symbol(f.key_b).index())] += f.features.n
    counts = replace(built.counts, n_cdtm_features=int(per_frame.sum()),
                     n_cdtm_factors=len(built.cdtm), features_per_frame=per_frame,
                     n_outliers=residuals.n_outliers,
                     outliers_per_frame=residuals.outliers_per_frame,
                     rejected_per_frame=built.rejections.per_frame(K),
                     residual_chi2_per_frame=residuals.chi2_within_per_frame)
    return SmootherResult(estimate, covariances, stats, counts, settings_dict,
                          frame_flags(counts), cdtm_information(
                              built.cdtm, estimate.world_T_body.__getitem__, K))
