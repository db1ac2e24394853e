"""Batch smoothing of a whole log: Levenberg-Marquardt from a good initial guess, marginals.

``smooth(log, dtm, settings) -> SmootherResult`` does no file I/O. The solver drives
Levenberg-Marquardt from Python over ``graph.linearize(values)`` (:mod:`~cdtm_graph.
optimizer`): GTSAM's own optimizers hand every ``CustomFactor`` call a fresh copy of all
values, which makes an iteration quadratic in the flight length.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from cdtm_graph.calibration import CALIBRATION_KEY, body_twists, calibrated_cameras
from cdtm_graph.calibration import estimate as calibration_estimate
from cdtm_graph.calibration import prior_factor as calibration_prior
from cdtm_graph.clutter import (
    Clutter,
    ClutterSettings,
    assess,
    clutter_flags,
    considered_offsets,
    findings,
    with_vertical_bias,
)
from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import CalibrationSigmas, FlightLog
from cdtm_graph.gating import residual_test
from cdtm_graph.graph import (
    cdtm_factors,
    cdtm_information,
    feature_noise,
    heights_at,
    imu_factor,
    insert_state,
    prior_factors,
    track_observations,
    without_tracks,
)
from cdtm_graph.imu import ImuIntervals, initial_bias
from cdtm_graph.mismatch import MismatchSettings, TrackJudgement, untrusted
from cdtm_graph.noise_bias import debiased
from cdtm_graph.optimizer import LinearSolver, explain_indeterminant, levenberg_marquardt
from cdtm_graph.preflight import check_constraints
from cdtm_graph.replay import replay
from cdtm_graph.results import (
    BiasPrior,
    GraphCounts,
    MapOffset,
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
from cdtm_graph.tracks import SightingPairs, pairs_without
from factors import CdtmPairFactor, FeatureNoise
from factors.calibration import CALIBRATION_DIM

#: Rounds of "drop the tracks off the DTM, solve again" (each finds what the last one's
#: estimate, no longer pulled by the worst, reveals).
MISMATCH_ROUNDS = 8

#: The first solve's relative tolerance: it stops where a step gains less than this.
FIRST_SOLVE_TOL = 1e-4


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
              K: int, qr_only: bool = False,
              linear: gtsam.GaussianFactorGraph | None = None) -> StateCovariances:
    """Per-frame marginals from a Bayes tree of the graph linearized at ``values``
    (``linear``, if the caller has it already).

    Cholesky first (as ``gtsam.Marginals``); where it declares the system indeterminant,
    which happens on these wide-range systems (information from ~1e-4 for the pose prior
    to ~1e10 for the bias random walk), QR, which does not square the condition number.
    """
    keys = [X(k) for k in range(K)] + [V(k) for k in range(K)] + [B(k) for k in range(K)]
    cov = key_marginals(graph, values, keys, qr_only, linear)
    return StateCovariances(np.stack(cov[:K]), np.stack(cov[K:2 * K]), np.stack(cov[2 * K:]))


def key_marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                  keys: list[int], qr_only: bool = False,
                  linear: gtsam.GaussianFactorGraph | None = None) -> list[np.ndarray]:
    """The marginal covariance of each key (as :func:`marginals`)."""
    if linear is None:
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

            return [cov(key) for key in keys]
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
    # every observation that entered a factor (the tracks dropped since too: the shares of
    # off-map tracks are of everything a frame saw), and the tracks the tests found off
    observed: tuple[np.ndarray, np.ndarray, np.ndarray] = (
        np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)))
    found_off: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    clutter: Clutter = field(default_factory=Clutter.none)  # the latest fit
    # the online calibration's body twists (K, 6), when the calibration is estimated
    twists: np.ndarray | None = None

    @property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(self.base)
        for f in self.cdtm:
            graph.add(f.factor)
        return graph

    def assess(self, values: gtsam.Values, dtm: Dtm, noise: FeatureNoise,
               body_T_cam: np.ndarray, mismatch: MismatchSettings,
               clutter: ClutterSettings | None) -> TrackJudgement:
        """Judge every track that entered at ``values`` (the ones dropped since too: a
        population's clutter is seen with its tallest members); keeps the clutter fit."""
        track_id, frame, ray = self.observed

        def at_stamp(k: int) -> np.ndarray:
            return values.atPose3(X(k)).matrix()

        pose: Callable[[int], np.ndarray] = at_stamp
        if self.twists is not None:  # the cameras as calibrated
            pose, body_T_cam, ray = calibrated_cameras(
                pose, body_T_cam, ray, self.twists, values.atVector(CALIBRATION_KEY))
        judged, self.clutter = assess(
            heights_at(track_id, frame, ray, pose, body_T_cam, dtm, noise), noise.sigma_h_m,
            mismatch, clutter)
        return judged

    def at_calibration(self, values: gtsam.Values) -> list[CdtmPairFactor]:
        """The C-DTM factors held at the calibration in ``values`` (for the checks after
        a solve, which see the poses alone); the factors themselves without one."""
        if self.twists is None:
            return self.cdtm
        c = values.atVector(CALIBRATION_KEY)
        return [f.with_calibration(f.calibration.fixed_at(c)) if f.calibration else f
                for f in self.cdtm]

    def drop_mismatched(self, values: gtsam.Values, dtm: Dtm, noise: FeatureNoise,
                        body_T_cam: np.ndarray, mismatch: MismatchSettings,
                        clutter: ClutterSettings | None) -> int:
        """Drop the features of tracks judged at ``values`` off the DTM (or not to be
        trusted beside those, :func:`~cdtm_graph.mismatch.untrusted`), likely on clutter
        (:mod:`cdtm_graph.clutter`) or holding a wrong match; how many features went."""
        judged = self.assess(values, dtm, noise, body_T_cam, mismatch, clutter)
        self.found_off = np.union1d(self.found_off, judged.off_map)
        off = untrusted(*self.observed[:2], self.found_off, mismatch.frame_fraction)
        before = self.rejections.total()
        self._drop(judged.inconsistent, Rejection.WRONG_MATCH)
        self._drop(np.union1d(off, self.clutter.likely(clutter)), Rejection.MAP_MISMATCH)
        return self.rejections.total() - before

    def _drop(self, drop: np.ndarray, reason: Rejection) -> None:
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


@dataclass
class InitialGuess:
    """The batch solver's starting point, and what the incremental pass learned."""

    values: gtsam.Values
    source: str  # "nav.csv" or "incremental pass"
    off_map: np.ndarray  # tracks found off the DTM
    unfixed_frames: np.ndarray  # frames whose sightings wait for a fix never found
    acquisitions: list[dict]  # the pass's fix searches
    frame_flags: dict[int, list[str]]


def _initial_values(flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
                    progress: Progress | None) -> InitialGuess:
    """Initial guess: nav.csv if present, else the incremental pass (dead reckoning
    corrected frame by frame, the fix acquired where the prior is too loose)."""
    if flight.nav is not None:
        values = gtsam.Values()
        bias = initial_bias(flight.config.initial_state)
        world_T_body = flight.nav.world_T_body  # (a property: every pose made anew)
        for k in range(len(flight.frames)):
            insert_state(values, k, world_T_body[k], flight.nav.velocity_mps[k], bias)
        none = np.zeros(0, np.int64)
        return InitialGuess(values, "nav.csv", none, none, [], {})
    incremental = replace(settings, mode=SmootherMode.INCREMENTAL, lag_s=None)
    smoother = IncrementalSmoother(flight.config, dtm, incremental, imu=flight.imu)
    result = smoother.run(flight, progress)
    flags = {k: [f for f in v if f == "no_fix"] for k, v in result.flags.items()}
    return InitialGuess(smoother.values(), "incremental pass", smoother.mismatched_tracks,
                        smoother.unfixed_frames, smoother.acquisitions,
                        {k: v for k, v in flags.items() if v})


def build_log_graph(flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
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
    is estimated too (``C(0)``, :mod:`cdtm_graph.calibration`; ``initial`` must hold it).
    With ``imu_rotations``, the epipolar check takes the relative rotations from the IMU
    (each interval's preintegrated rotation, chained; anew after an IMU gap) instead of
    from ``initial``: a nav.csv's attitudes may be noisy frame to frame (GNSS with a
    compass), and 0.5 deg of white noise there left 4% of a clean log's features out as
    wrong matches.
    """
    K = len(flight.frames)
    t = flight.frames.t_ns
    graph = prior_factors(flight.config.initial_state)
    intervals = ImuIntervals(flight.config, flight.imu, settings.graph.imu_hold,
                             settings.graph.earth_physics, settings.graph.imu_gap_noise)
    bias0 = initial_bias(flight.config.initial_state)
    poses = [initial.atPose3(X(k)).matrix() for k in range(K)]
    checked = [p.copy() for p in poses]  # the poses the epipolar check sees
    for k in range(K - 1):  # (the Earth model places each interval from the initial guess)
        start = (initial.atPose3(X(k)).matrix(), initial.atVector(V(k)))
        pim = intervals.preintegrate(int(t[k]), int(t[k + 1]), bias0, start)
        graph.add(imu_factor(k, pim))
        if imu_rotations and not pim.spans_gap:
            checked[k + 1][:3, :3] = checked[k][:3, :3] @ pim.deltaRij().matrix()
    rejections = Rejections()
    camera = flight.config.camera
    pairing = SightingPairs(camera.camera, camera.body_T_cam, dtm, camera.pixel_sigma_px,
                            settings.graph.epipolar, rejections)
    pairs = []
    unfixed = set() if unfixed_frames is None else set(unfixed_frames.tolist())
    for frame in replay(flight):
        if frame.k in unfixed:
            rejections.add(Rejection.NO_FIX, frame.k, len(frame.track_id))
        elif len(frame.track_id):
            pairs += pairs_without(
                pairing.add_frame(frame.k, frame.track_id, frame.uv_px, checked.__getitem__),
                np.zeros(0, np.int64) if off_map is None else off_map, frame.k,
                Rejection.MAP_MISMATCH, rejections)
    twists = None
    if calibration is not None:
        graph.add(calibration_prior(calibration))
        twists = body_twists(t, flight.imu, initial_bias(flight.config.initial_state).gyroscope(),
                             np.stack(poses), np.stack([initial.atVector(V(k)) for k in range(K)]))
    build = cdtm_factors(pairs, poses, camera.body_T_cam, dtm,
                         feature_noise(flight.config, dtm, settings.graph), settings.graph,
                         rejections, None if twists is None else (CALIBRATION_KEY, twists))
    per_frame = np.zeros(K, dtype=int)
    for k, n in build.features_per_frame.items():
        per_frame[k] = n
    counts = GraphCounts(
        K, pairing.table.n_tracks, pairing.n_observations, pairing.n_pairs, build.n_features,
        len(build.factors), K - 1, per_frame, outliers_per_frame=np.zeros(K, dtype=int),
        rejected_per_frame=rejections.per_frame(K))
    observed = track_observations(build.factors, build.track_ids)
    return LogGraph(graph, initial, counts, build.factors, build.track_ids, rejections,
                    observed, twists=twists)


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
        # the expected interval, not the longest: one dropped stretch of frames must not
        # stand for the log (the fix search's window, the relinearization rate)
        dt_s = float(np.median(np.diff(flight.frames.t_ns))) * 1e-9
        smoother = IncrementalSmoother(flight.config, dtm, settings, frame_interval_s=dt_s)
        result = smoother.run(flight, progress)
        return _checked(flight, dtm, settings, result, smoother.mismatched_tracks,
                        smoother.unfixed_frames)
    guess = _initial_values(flight, dtm, settings, progress)
    initial = guess.values
    calibration = _online_calibration(flight, settings)
    if calibration is not None:
        initial = gtsam.Values(initial)
        initial.insert(CALIBRATION_KEY, np.zeros(CALIBRATION_DIM))
    # The pass judged the tracks against the DTM with the nominal calibration, whose error
    # makes good tracks look off the map (a 20 ms offset: a third of the features); with
    # the calibration estimated, the mismatch rounds below judge them as calibrated.
    off_map = guess.off_map if calibration is None else None
    built = build_log_graph(flight, dtm, settings, initial, off_map,
                            guess.unfixed_frames, calibration,
                            imu_rotations=guess.source == "nav.csv")
    solver = LinearSolver()
    # The first solve only finds the basin for the first mismatch round and the noise
    # refresh; the last one converges to the tolerance. (Its last iteration was a
    # linearization that confirmed a step already taken.)
    values, first = levenberg_marquardt(built.graph, initial, settings.max_iterations,
                                        max(settings.relative_error_tol, FIRST_SOLVE_TOL),
                                        solver=solver)
    # Terrain the DTM lacks: drop the tracks off the map and solve again, until none is.
    # The first round judges the first solution, so that its drops and the refreshed
    # noise share one solve (a clean log then needs two solves, not three).
    mismatch = settings.graph.mismatch
    noise = feature_noise(flight.config, dtm, settings.graph)
    body_T_cam = flight.config.camera.body_T_cam
    rounds = MISMATCH_ROUNDS if mismatch is not None else 0
    if rounds:
        assert mismatch is not None
        built.drop_mismatched(values, dtm, noise, body_T_cam, mismatch, settings.graph.clutter)
        rounds -= 1
    # The C-DTM noise (eqs. 19-26) was linearized at the initial guess; evaluate it at the
    # estimate and finish there, so the solution does not depend on the initial guess.
    built.refresh_noise(values)
    graph = built.graph
    values, stats = levenberg_marquardt(graph, values, settings.max_iterations,
                                        settings.relative_error_tol, solver=solver)
    iterations = first.iterations + stats.iterations
    assessed = False  # the latest clutter fit is of the final values
    for _ in range(rounds):
        assert mismatch is not None
        if not built.drop_mismatched(values, dtm, noise, body_T_cam, mismatch,
                                     settings.graph.clutter):
            assessed = True
            break
        graph = built.graph
        values, more = levenberg_marquardt(graph, values, settings.max_iterations,
                                           settings.relative_error_tol, solver=solver)
        iterations += more.iterations
        stats = replace(more, time_s=stats.time_s + more.time_s)
    if calibration is not None:  # the focal scale takes the noise's bias whole
        values = debiased(graph, values, built.cdtm)
    K = len(flight.frames)
    start = time.perf_counter()
    covariances = (marginals(graph, values, K, linear=solver.linearized_at(values))
                   if settings.marginals else
                   StateCovariances(np.full((K, 6, 6), np.nan), np.full((K, 3, 3), np.nan),
                                    np.full((K, 6, 6), np.nan)))
    calibrated = None
    if calibration is not None:
        c_cov = (key_marginals(graph, values, [CALIBRATION_KEY])[0] if settings.marginals
                 else np.full((CALIBRATION_DIM, CALIBRATION_DIM), np.nan))
        calibrated = calibration_estimate(values.atVector(CALIBRATION_KEY), c_cov,
                                          calibration, flight.config)
    checked = built.at_calibration(values)  # the factors as the poses alone see them
    estimate = _estimate_from_values(values, flight.frames.t_ns)
    # what clutter may remain in the features: a considered vertical bias per frame
    terrain, flags = None, dict(guess.frame_flags)
    if mismatch is not None and settings.graph.clutter is not None:
        if not assessed:
            built.assess(values, dtm, noise, body_T_cam, mismatch, settings.graph.clutter)
        offsets = considered_offsets(built.clutter, [f.key_a for f in built.cdtm],
                                     [f.key_b for f in built.cdtm], built.track_ids, K)
        covariances = with_vertical_bias(covariances, estimate.world_T_body, offsets)
        terrain = findings(built.clutter, offsets)
        for k, v in clutter_flags(offsets, settings.graph.clutter).items():
            flags.setdefault(k, []).extend(v)
    stats = SolverStats(stats.solver, iterations, first.initial_error,
                        stats.final_error, stats.converged, first.time_s + stats.time_s,
                        time.perf_counter() - start)
    settings_dict = settings.to_dict()
    settings_dict["initial_values"] = guess.source
    settings_dict["acquisitions"] = guess.acquisitions
    residuals = residual_test(checked, estimate.world_T_body, K)
    per_frame = np.zeros(K, dtype=int)
    for f in built.cdtm:
        per_frame[int(gtsam.Symbol(f.key_b).index())] += f.features.n
    counts = replace(built.counts, n_cdtm_features=int(per_frame.sum()),
                     n_cdtm_factors=len(built.cdtm), features_per_frame=per_frame,
                     n_outliers=residuals.n_outliers,
                     outliers_per_frame=residuals.outliers_per_frame,
                     rejected_per_frame=built.rejections.per_frame(K),
                     residual_chi2_per_frame=residuals.chi2_within_per_frame)
    map_offset = MapOffset.of(flight.config.dtm)
    result = SmootherResult(estimate, map_offset.added_to(covariances, estimate.world_T_body),
                            stats, counts, settings_dict, frame_flags(counts, flags),
                            cdtm_information(checked, estimate.world_T_body.__getitem__, K),
                            terrain, calibrated, map_offset=map_offset,
                            bias_prior=BiasPrior.of(flight.config))
    if calibrated is not None:
        return result
    return _checked(flight, dtm, settings, result, np.union1d(guess.off_map, built.found_off),
                    guess.unfixed_frames)


def _online_calibration(flight: FlightLog, settings: SmootherSettings
                        ) -> CalibrationSigmas | None:
    """The calibration's prior when the batch estimates it (flight.yaml asks, or the
    settings), else None."""
    asked = flight.config.camera.calibration
    if asked is not None:
        return asked
    return settings.graph.calibration if settings.graph.calibration_online else None


def _checked(flight: FlightLog, dtm: Dtm, settings: SmootherSettings, result: SmootherResult,
             left_out: np.ndarray, unfixed_frames: np.ndarray) -> SmootherResult:
    """``result`` (which held flight.yaml's calibration) with the side solve's check of it
    (:mod:`cdtm_graph.smoother.calibration_check`), unless the settings hold it unchecked."""
    sigmas = flight.config.camera.calibration or settings.graph.calibration
    if sigmas is None:
        return result
    # (imported here: the check builds on this module)
    from cdtm_graph.smoother.calibration_check import check_calibration
    return replace(result, calibration_check=check_calibration(
        flight, dtm, settings, result, sigmas, left_out, unfixed_frames))
