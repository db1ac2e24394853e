"""flight.yaml's IMU bias random walks tested at the calibration check's first solve (the
run's graph at its optimum), and grown in side solves of their own
(:mod:`cdtm_graph.robust.imu_walk` has the test and why; the calibration check and the
convergence check make their side solves alike)."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import gtsam
import numpy as np

from cdtm_graph.calibration.check import (
    MAX_FRAMES,
    CalibrationCheck,
    PinnedSolve,
    estimate_values,
    thinned,
)
from cdtm_graph.calibration.online import CALIBRATION_KEY
from cdtm_graph.constants import NS_PER_S
from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.graph import GraphSettings
from cdtm_graph.graph.log_graph import build_log_graph
from cdtm_graph.imu import gap_threshold_ns
from cdtm_graph.optimizer import LinearSolver, levenberg_marquardt
from cdtm_graph.results import RandomWalkEstimate, SmootherResult
from cdtm_graph.robust.imu_walk import (
    BiasSteps,
    RandomWalkSettings,
    bias_steps,
    exceeds,
    with_random_walks,
)
from cdtm_graph.verdict.imu_faults import imu_gaps
from cdtm_graph.verdict.rules import walk_confounders


def check_random_walks(flight: FlightLog, dtm: Dtm, graph_settings: GraphSettings,
                       result: SmootherResult,
                       left_out: np.ndarray | None = None,
                       unfixed_frames: np.ndarray | None = None,
                       settings: RandomWalkSettings | None = None, max_iterations: int = 30,
                       relative_error_tol: float = 1e-6,
                       pinned: PinnedSolve | None = None,
                       calibration: CalibrationCheck | None = None) -> RandomWalkEstimate:
    """flight.yaml's random walks tested at a batch solve of the run's graph, and grown
    while the bias steps exceed them (module docstring).

    Args:
        flight, dtm, graph_settings: the run's (how its graph is built).
        result: the run's result. left_out: tracks the run left out; unfixed_frames:
            frames whose sightings waited for a fix never found: both stay out.
        settings: when to grow. max_iterations, relative_error_tol: the side solves'
            Levenberg-Marquardt limits.
        pinned: the calibration check's first solve (flight.yaml's calibration held: the
            run's graph at its optimum), whose linearization the test reads; None: a side
            solve of its own. The growth's rounds are side solves of their own.
        calibration: the run's calibration check, made already: a ``calibration_suspect``
            it leads the verdict to name is a fault the test yields to.
    """
    s = settings or RandomWalkSettings()
    start = time.perf_counter()
    stated = np.array([flight.config.imu.gyroscope_random_walk,
                       flight.config.imu.accelerometer_random_walk])
    # (the pinned solve's own thinning: the side solves count the same frames)
    sub, kept = thinned(flight, MAX_FRAMES) if pinned is None else (pinned.log, pinned.kept)
    values = estimate_values(result.estimate, kept)
    if unfixed_frames is not None:  # the kept ones, as the thinned log numbers them
        unfixed_frames = np.searchsorted(kept, unfixed_frames[np.isin(unfixed_frames, kept)])
    t_ns = sub.frames.t_ns
    inside_s, _ = imu_gaps(t_ns, sub.imu.t_ns)
    counted = inside_s[1:] <= gap_threshold_ns(sub.config.imu.rate_hz) / NS_PER_S

    def solve(walks: np.ndarray, start_values: gtsam.Values
              ) -> tuple[gtsam.Values, BiasSteps]:
        log = with_random_walks(sub, float(walks[0]), float(walks[1]))
        built = build_log_graph(log, dtm, graph_settings, start_values, left_out,
                                unfixed_frames)
        solver = LinearSolver()
        solved, _ = levenberg_marquardt(built.graph, start_values, max_iterations,
                                        relative_error_tol, solver=solver)
        linear = solver.linearized_at(solved) or built.graph.linearize(solved)
        return solved, bias_steps(linear, solved, t_ns, float(walks[0]), float(walks[1]),
                                  counted, s)

    if pinned is not None:
        first = bias_steps(pinned.linear, pinned.values, t_ns, float(stated[0]),
                           float(stated[1]), counted, s)
        values = gtsam.Values(pinned.values)  # the growth's start: its states, no C(0)
        values.erase(CALIBRATION_KEY)
    else:
        values, first = solve(stated, values)
    scale = np.ones(2)  # of the variances
    steps, rounds = first, 0
    # too short a flight to tell a wander through it from a few bent frames: not judged
    judged = first.chi2.shape[0] >= s.min_segments
    exceeded = judged and exceeds(first, s.grow_ratio, s.probability)
    # another fault the verdict names bends the steps too (a bias beyond its prior, which
    # grown walks would hide by widening the prior's spread over the flight; a calibration
    # the flight contradicts; outliers...): not grown, that fault is named
    yielded_to = confounders(result, calibration) if exceeded else ()
    grow = exceeded and not yielded_to
    while grow and rounds < s.max_rounds and np.any(scale < s.max_scale**2):
        # (the spread decided; the growth settles the whole, each sensor by its ratio)
        scale = np.minimum(scale * np.maximum(steps.whole_ratios, 1.0), s.max_scale**2)
        values, steps = solve(stated * np.sqrt(scale), values)
        rounds += 1
        grow = bool(np.any(steps.whole_ratios > s.settle_ratio))
    grown = rounds > 0
    at_bound = (scale >= s.max_scale**2) & (steps.whole_ratios > s.settle_ratio)
    return RandomWalkEstimate(
        stated_gyro=float(stated[0]), stated_accel=float(stated[1]),
        ratio_gyro=float(first.ratios[0]), ratio_accel=float(first.ratios[1]),
        chi2=_pair(first.spread_chi2), expected=_pair(first.spread_chi2 / np.maximum(
            first.ratios, 1e-300)),
        chi2_bound=_pair(first.bounds(s.probability)),
        n_steps=first.n_steps,
        used_gyro=float(stated[0] * math.sqrt(scale[0])) if grown else float(stated[0]),
        used_accel=float(stated[1] * math.sqrt(scale[1])) if grown else float(stated[1]),
        final_ratios=_pair(steps.whole_ratios),
        bound_scale=s.max_scale,
        held=not exceeded or bool(yielded_to) or not (
            exceeds(steps, s.grow_ratio, s.probability) or bool(np.any(at_bound))),
        rounds=rounds, time_s=time.perf_counter() - start,
        yielded_to=tuple(str(code) for code in yielded_to))


def confounders(result: SmootherResult, calibration: CalibrationCheck | None = None
                ) -> tuple[str, ...]:
    """The reasons the verdict names for the run that bend the bias steps as well
    (:data:`cdtm_graph.verdict.rules.WALK_CONFOUNDERS`; the run's calibration check, made
    already, counted)."""
    judged = result if calibration is None else replace(result, calibration_check=calibration)
    return tuple(str(code) for code in walk_confounders(judged))


def _pair(values: np.ndarray) -> tuple[float, float]:
    """(gyro, accelerometer) as plain floats."""
    return float(values[0]), float(values[1])
