"""Batch smoothing of a whole log: Levenberg-Marquardt from a good initial guess, marginals.

``smooth(log, dtm, settings) -> SmootherResult`` does no file I/O. The solver drives
Levenberg-Marquardt from Python over ``graph.linearize(values)`` (:mod:`~cdtm_graph.
optimizer`): GTSAM's own optimizers hand every ``CustomFactor`` call a fresh copy of all
values, which makes an iteration quadratic in the flight length.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from cdtm_graph.calibration.check import (
    CalibrationCheck,
    PinnedSolve,
    check_calibration,
    pinned_solve,
)
from cdtm_graph.calibration.considered import FIXED_LAG_RESPONSE_MISFIT, considered
from cdtm_graph.calibration.noise_bias import debiased
from cdtm_graph.calibration.online import CALIBRATION_KEY
from cdtm_graph.calibration.online import estimate as calibration_estimate
from cdtm_graph.codes import Code
from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import CalibrationSigmas, FlightLog
from cdtm_graph.graph import feature_noise, insert_state
from cdtm_graph.graph.builders import DEFAULT_CALIBRATION_SIGMAS
from cdtm_graph.graph.log_graph import LogGraph, build_log_graph
from cdtm_graph.imu import initial_bias, shared_preintegrations
from cdtm_graph.optimizer import LinearSolver, key_marginals, levenberg_marquardt, marginals
from cdtm_graph.results import (
    MapErrorEstimate,
    Rejection,
    SmootherResult,
    Solver,
    SolverStats,
    StateCovariances,
    TrajectoryEstimate,
)
from cdtm_graph.robust.clutter import considered_offsets
from cdtm_graph.robust.imu_walk import with_random_walks
from cdtm_graph.robust.map_error import (
    estimate_map_error,
    grown_map,
    run_broad_map_error,
    run_heights,
)
from cdtm_graph.robust.track_tests import BatchTrackTests
from cdtm_graph.smoother.assembly import ClutterOutcome, assemble_result
from cdtm_graph.smoother.convergence import check_convergence
from cdtm_graph.smoother.incremental import IncrementalSmoother
from cdtm_graph.smoother.random_walks import check_random_walks
from cdtm_graph.smoother.settings import Progress, SmootherMode, SmootherSettings
from cdtm_graph.verdict.preflight import check_constraints
from factors.calibration import CALIBRATION_DIM

logger = logging.getLogger(__name__)

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
    # (the batch grows the map from its own run's tracks: the pass does not as it goes)
    incremental = replace(_map_held(settings), mode=SmootherMode.INCREMENTAL, lag_s=None)
    smoother = IncrementalSmoother(flight.config, dtm, incremental, imu=flight.imu)
    smoother.feed(flight, progress)  # (no result: every frame's marginals are not wanted)
    unfixed = smoother.unfixed_frames  # (flagged no_fix once each)
    return InitialGuess(smoother.values(), "incremental pass", smoother.mismatched_tracks,
                        unfixed, smoother.acquisitions, {int(k): [Code.NO_FIX] for k in unfixed})


@shared_preintegrations()  # the graph, its side solves and re-runs: one IMU pass
def smooth(flight: FlightLog, dtm: Dtm, settings: SmootherSettings | None = None,
           progress: Progress | None = None) -> SmootherResult:
    """Smooth a flight log (batch LM, or the incremental smoother's pass).

    Args:
        flight: the log (``read_flightlog``). dtm: its terrain (``load_dtm``).
        settings: solver settings. progress: per-frame callback on long runs.

    When the tracks show the DTM's height error beyond its stated sigma_h (ground detail
    the map lacks, :mod:`cdtm_graph.robust.map_error`), the run is made again with the
    sigma_h they show and its tangent planes' slopes regional (:func:`_grown`), and so is
    every check after it (``settings.graph.map_error``; ``result.map_error`` says what was
    estimated and used; ``progress`` then runs through the frames twice). Likewise when a
    side solve's bias steps show the IMU biases wandering beyond flight.yaml's random walks
    (:mod:`cdtm_graph.robust.imu_walk`; ``result.imu_random_walk``).

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
    run = _smooth_once(flight, dtm, settings, progress)
    map_error = None
    if settings.graph.map_error is not None and run.checked:
        # the map worse than it says: the run again with the sigma_h the tracks show
        noise = feature_noise(flight.config, dtm, settings.graph)
        heights = run_heights(flight, dtm, noise, run.result.estimate, run.unfixed_frames)
        map_error = estimate_map_error(heights, noise.sigma_h_m, settings.graph.map_error,
                                       settings.graph.mismatch)
        first, again_settings = run, _map_held(settings)
        if map_error.grown:
            flight, dtm = with_sigma_h(flight, map_error.used_m), _grown(dtm, settings)
            run = _smooth_once(flight, dtm, again_settings, progress)
            map_error = replace(map_error, slope_sigma_posts=dtm.slope_sigma_posts)
        elif map_error.beyond:
            # beyond the bound: a map wrong (a fault), or a run the stated sigma_h drove off
            # (the ground dropped as off the map until the estimate drifted, which the
            # tracks then read as map error). Once more at the bound: kept only if the
            # tracks then read the map within it.
            capped, grown_dtm = with_sigma_h(flight, map_error.bound_m), _grown(dtm, settings)
            again = _smooth_once(capped, grown_dtm, again_settings, progress)
            second = estimate_map_error(
                run_heights(capped, dtm, noise, again.result.estimate, again.unfixed_frames),
                noise.sigma_h_m,
                settings.graph.map_error, settings.graph.mismatch)
            logger.info("map error %.2f m beyond its bound %.2f m; at the bound: %.2f m",
                        map_error.estimated_m, map_error.bound_m, second.estimated_m)
            if second.estimated_m <= map_error.bound_m:
                flight, run, dtm = capped, again, grown_dtm
                map_error = replace(second, used_m=map_error.bound_m,
                                    first_estimated_m=map_error.estimated_m,
                                    slope_sigma_posts=dtm.slope_sigma_posts)
            else:
                map_error = replace(map_error, bound_estimated_m=second.estimated_m)
        flight, dtm, map_error = _as_it_ended(run, flight, dtm, settings, map_error)
    walks, calibration = None, None
    pinned: list[PinnedSolve] = []  # the calibration check's first solve, of the run kept
    if settings.graph.imu_random_walk is not None and run.checked:
        # the IMU biases wander more than flight.yaml says: the run again with the walks
        # the bias steps show, read at the calibration check's first solve (the run's
        # graph at its optimum, flight.yaml's calibration held)
        calibration = _calibration_check(flight, dtm, settings, run.result, run.left_out,
                                         run.unfixed_frames, pinned.append)
        walks = check_random_walks(flight, dtm, settings.graph, run.result, run.left_out,
                                   run.unfixed_frames, settings.graph.imu_random_walk,
                                   settings.max_iterations, settings.relative_error_tol,
                                   pinned[0] if pinned else None, calibration)
        if walks.grown:
            logger.info("IMU random walks grown %.3gx (gyro), %.3gx (accelerometer)",
                        *walks.scales)
            flight = with_random_walks(flight, walks.used_gyro, walks.used_accel)
            grown = map_error is not None and map_error.grown  # (then held as it is)
            run = _smooth_once(flight, dtm, _map_held(settings) if grown else settings,
                               progress)
            if map_error is not None:
                flight, dtm, map_error = _as_it_ended(run, flight, dtm, settings,
                                                      replace(map_error, grown_at=()))
            calibration = None  # of the run before
            pinned.clear()
    result = run.result
    if (map_error is not None and settings.graph.broad_map_error is not None
            and settings.lag_s is None):  # (a fixed lag takes it as it goes, or not at all)
        result = replace(result, broad_map_error=run_broad_map_error(
            flight, dtm, noise, result, run.unfixed_frames, run.left_out,
            heights if run is first else None, settings.graph.broad_map_error,
            settings.graph.mismatch))
    if run.checked:
        result = _checked(flight, dtm, settings, result, run.left_out, run.unfixed_frames,
                          calibration, pinned.append)
    if (map_error is not None and settings.graph.broad_map_error is not None
            and settings.lag_s is not None and pinned
            and pinned[-1].kept.size == len(flight.frames)):
        # a fixed lag's shape at the poses its window held misses what the whole flight
        # shows (hill15, seed 8): read it too at the calibration check's batch solve
        # (verdict: either; 15-30 ms, 2026-11-28); a thinned solve's frames are not the run's
        whole = replace(result, estimate=_estimate_from_values(pinned[-1].values,
                                                               flight.frames.t_ns))
        result = replace(result, broad_map_error_whole=run_broad_map_error(
            flight, dtm, noise, whole, run.unfixed_frames, run.left_out, None,
            settings.graph.broad_map_error, settings.graph.mismatch))
    if flight.config.camera.principal_point_sigma_px:
        result = _principal_point_considered(flight, dtm, settings, result, run,
                                             pinned[-1] if pinned else None)
    if map_error is not None:
        result = replace(result, map_error=map_error)
    return result if walks is None else replace(result, imu_random_walk=walks)


def _as_it_ended(run: _Run, flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
                 map_error: MapErrorEstimate) -> tuple[FlightLog, Dtm, MapErrorEstimate]:
    """The log and map the checks after ``run`` (and a run made again) hold, and its
    ``map_error``: if its incremental pass grew the map as it went, as it ended."""
    if not run.grown_at:
        return flight, dtm, map_error
    used = run.grown_at[-1][1]
    flight, dtm = with_sigma_h(flight, used), _grown(dtm, settings)
    return flight, dtm, replace(map_error, used_m=used, grown_at=run.grown_at,
                                slope_sigma_posts=dtm.slope_sigma_posts)


def _map_held(settings: SmootherSettings) -> SmootherSettings:
    """``settings`` for a run made again with the map error the whole run showed: an
    incremental pass then does not grow it again as it goes (``live_every_rounds``)."""
    map_error = settings.graph.map_error
    if map_error is None or map_error.live_every_rounds is None:
        return settings
    return replace(settings, graph=replace(settings.graph, map_error=replace(
        map_error, live_every_rounds=None)))


def _grown(dtm: Dtm, settings: SmootherSettings) -> Dtm:
    """:func:`~cdtm_graph.robust.map_error.grown_map` of the run's settings."""
    return grown_map(dtm, settings.graph.map_error)


def _principal_point_considered(flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
                                result: SmootherResult, run: _Run,
                                pinned: PinnedSolve | None) -> SmootherResult:
    """``result`` with flight.yaml's declared principal-point uncertainty in its pose
    covariances (:mod:`cdtm_graph.calibration.considered`), from the calibration check's
    first solve (one of its own where the calibration is not checked: held unchecked, or
    estimated online, its sensitivity then taken with the rest of the calibration held)."""
    if np.isnan(result.covariances.pose).all():  # (none to add to: marginals=False)
        return result
    start = time.perf_counter()
    if pinned is None:
        sigmas = (flight.config.camera.calibration or settings.graph.calibration
                  or DEFAULT_CALIBRATION_SIGMAS)
        pinned = pinned_solve(flight, dtm, settings.graph, result, sigmas, run.left_out,
                              run.unfixed_frames, settings.max_iterations,
                              settings.relative_error_tol)
    covariances, added = considered(
        result.covariances, flight.frames.t_ns, pinned, flight.config.camera.camera,
        float(flight.config.camera.principal_point_sigma_px or 0),
        FIXED_LAG_RESPONSE_MISFIT if result.stats.solver is Solver.FIXED_LAG else 0.0)
    if added is not None:  # (its own solve's time too, where the check made none)
        added = replace(added, time_s=time.perf_counter() - start)
    return replace(result, covariances=covariances, considered_principal_point=added)


@dataclass
class _Run:
    """One smoothing of a log, before the checks of its result (:func:`_checked`)."""

    result: SmootherResult
    left_out: np.ndarray  # tracks left out (off the map, wrong matches)
    unfixed_frames: np.ndarray
    checked: bool  # the calibration was held (not estimated online): check the result
    grown_at: tuple[tuple[int, float], ...] = ()  # an incremental pass's map grown as it went


def with_sigma_h(flight: FlightLog, sigma_h_m: float) -> FlightLog:
    """``flight`` whose flight.yaml states the DTM's height 1-sigma as ``sigma_h_m``."""
    config = flight.config
    return replace(flight, config=replace(config, dtm=replace(config.dtm, sigma_h_m=sigma_h_m)))


def _smooth_once(flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
                 progress: Progress | None) -> _Run:
    """:func:`smooth`'s run, without the checks of its result."""
    if settings.mode is SmootherMode.INCREMENTAL:
        # the expected interval, not the longest: one dropped stretch of frames must not
        # stand for the log (the fix search's window, the relinearization rate)
        dt_s = float(np.median(np.diff(flight.frames.t_ns))) * 1e-9
        smoother = IncrementalSmoother(flight.config, dtm, settings, frame_interval_s=dt_s)
        return _Run(smoother.run(flight, progress), smoother.mismatched_tracks,
                    smoother.unfixed_frames, True, smoother.map_grown)
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
    built = build_log_graph(flight, dtm, settings.graph, initial, off_map,
                            guess.unfixed_frames, calibration,
                            imu_rotations=guess.source == "nav.csv")
    mismatch = settings.graph.mismatch
    tests = None if mismatch is None else BatchTrackTests(
        dtm, feature_noise(flight.config, dtm, settings.graph),
        flight.config.camera.body_T_cam, mismatch, settings.graph.clutter)
    solver = LinearSolver()
    values, graph, stats, assessed = _solve(built, initial, settings, tests, solver)
    linear = solver.linearized_at(values)
    if calibration is not None:  # the focal scale takes the noise's bias whole
        values, _ = debiased(graph, values, built.cdtm, linear=linear)
        # (the states' and the calibration's marginals at the moved values: one linearization)
        linear = graph.linearize(values) if settings.marginals else None
    K = len(flight.frames)
    start = time.perf_counter()
    covariances = (marginals(graph, values, K, linear=linear)
                   if settings.marginals else
                   StateCovariances(np.full((K, 6, 6), np.nan), np.full((K, 3, 3), np.nan),
                                    np.full((K, 6, 6), np.nan)))
    calibrated = None
    if calibration is not None:
        c_cov = (key_marginals(graph, values, [CALIBRATION_KEY], linear=linear)[0]
                 if settings.marginals
                 else np.full((CALIBRATION_DIM, CALIBRATION_DIM), np.nan))
        calibrated = calibration_estimate(values.atVector(CALIBRATION_KEY), c_cov,
                                          calibration, flight.config)
    estimate = _estimate_from_values(values, flight.frames.t_ns)
    # what clutter may remain in the features: a considered vertical bias per frame
    clutter = None
    if tests is not None and settings.graph.clutter is not None:
        if not assessed:
            tests.assess(built, values)
        clutter = ClutterOutcome(tests.clutter, considered_offsets(
            tests.clutter, [f.key_a for f in built.cdtm], [f.key_b for f in built.cdtm],
            built.track_ids, K), settings.graph.clutter)
    stats = replace(stats, marginals_time_s=time.perf_counter() - start)
    per_frame = np.zeros(K, dtype=int)
    for f in built.cdtm:
        per_frame[int(gtsam.Symbol(f.key_b).index())] += f.features.n
    counts = replace(built.counts, n_cdtm_features=int(per_frame.sum()),
                     n_cdtm_factors=len(built.cdtm), features_per_frame=per_frame,
                     rejected_per_frame=built.rejections.per_frame(K))
    settings_dict = {**settings.to_dict(), "initial_values": guess.source,
                     "acquisitions": guess.acquisitions}
    # the factors as the poses alone see them (held at an estimated calibration)
    result = assemble_result(flight.config, estimate, covariances, stats, counts, settings_dict,
                             guess.frame_flags, built.at_calibration(values), clutter,
                             calibrated, stages=built.stages.summary() if built.stages else [])
    found_off = np.zeros(0, np.int64) if tests is None else tests.found_off
    return _Run(result, np.union1d(guess.off_map, found_off), guess.unfixed_frames,
                calibrated is None)


def _solve(built: LogGraph, initial: gtsam.Values, settings: SmootherSettings,
           tests: BatchTrackTests | None, solver: LinearSolver
           ) -> tuple[gtsam.Values, gtsam.NonlinearFactorGraph, SolverStats, bool]:
    """Levenberg-Marquardt over the log's graph, with rounds of the track tests between
    solves (terrain the DTM lacks: drop the tracks off the map and solve again, until none
    is). Returns the solution, its graph, the statistics (the iterations of every solve)
    and whether the latest clutter fit is of the solution."""
    # The first solve only finds the basin for the first mismatch round and the noise
    # refresh; the last one converges to the tolerance. (Its last iteration was a
    # linearization that confirmed a step already taken.)
    values, first = levenberg_marquardt(built.graph, initial, settings.max_iterations,
                                        max(settings.relative_error_tol, FIRST_SOLVE_TOL),
                                        solver=solver)
    # The first round judges the first solution, so that its drops and the refreshed
    # noise share one solve (a clean log then needs two solves, not three).
    rounds = MISMATCH_ROUNDS if tests is not None else 0
    if tests is not None:
        with _charged(built):
            tests.drop_mismatched(built, values)
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
        assert tests is not None
        with _charged(built):
            dropped = tests.drop_mismatched(built, values)
        if not dropped:
            assessed = True
            break
        graph = built.graph
        values, more = levenberg_marquardt(graph, values, settings.max_iterations,
                                           settings.relative_error_tol, solver=solver)
        iterations += more.iterations
        stats = replace(more, time_s=stats.time_s + more.time_s)
    stats = SolverStats(stats.solver, iterations, first.initial_error, stats.final_error,
                        stats.converged, first.time_s + stats.time_s, 0.0)
    return values, graph, stats, assessed


def _charged(built: LogGraph) -> contextlib.AbstractContextManager:
    """The track tests' rounds, charged to their own entry of report.json's ``stages``."""
    assert built.stages is not None
    return built.stages.charged(TRACK_TESTS, (Rejection.WRONG_MATCH, Rejection.MAP_MISMATCH))


#: The batch's track-test rounds between solves, charged apart from the frames' stages.
TRACK_TESTS = "track_tests"


def _online_calibration(flight: FlightLog, settings: SmootherSettings
                        ) -> CalibrationSigmas | None:
    """The calibration's prior when the batch estimates it (flight.yaml asks, or the
    settings), else None."""
    asked = flight.config.camera.calibration
    if asked is not None:
        return asked
    return settings.graph.calibration if settings.graph.calibration_online else None


def _checked(flight: FlightLog, dtm: Dtm, settings: SmootherSettings, result: SmootherResult,
             left_out: np.ndarray, unfixed_frames: np.ndarray,
             calibration: CalibrationCheck | None = None,
             on_pinned: Callable[[PinnedSolve], None] | None = None) -> SmootherResult:
    """``result`` (which held flight.yaml's calibration) with the side solve's check of it
    (:mod:`cdtm_graph.calibration.check`; ``calibration``: made already), unless the
    settings hold it unchecked (``on_pinned`` given its first solve, when it makes it);
    and, if its solver did not report convergence, with one more solve's move
    (:mod:`cdtm_graph.smoother.convergence`)."""
    if not result.stats.converged:
        result = replace(result, convergence_check=check_convergence(
            flight, dtm, settings.graph, result, left_out, unfixed_frames,
            settings.max_iterations, settings.relative_error_tol))
    if calibration is None:
        calibration = _calibration_check(flight, dtm, settings, result, left_out,
                                         unfixed_frames, on_pinned)
    return result if calibration is None else replace(result, calibration_check=calibration)


def _calibration_check(flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
                       result: SmootherResult, left_out: np.ndarray,
                       unfixed_frames: np.ndarray,
                       on_pinned: Callable[[PinnedSolve], None] | None = None
                       ) -> CalibrationCheck | None:
    """The calibration check's side solve of ``result`` (None: the settings hold it
    unchecked); ``on_pinned`` given its first solve."""
    sigmas = flight.config.camera.calibration or settings.graph.calibration
    if sigmas is None:
        return None
    return check_calibration(flight, dtm, settings.graph, result, sigmas, left_out,
                             unfixed_frames, settings.max_iterations,
                             settings.relative_error_tol, on_pinned)
