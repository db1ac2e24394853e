"""One smoothing run of a flight log: smooth, judge, evaluate against ground truth, report.

No file I/O: :func:`smooth_and_evaluate` returns everything the CLI writes, the verdict
(:mod:`cdtm_graph.verdict.rules`) included.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.imu import dead_reckoning, shared_preintegrations
from cdtm_graph.results import SmootherResult, TrajectoryEstimate
from cdtm_graph.smoother import Progress, SmootherSettings, smooth
from cdtm_graph.verdict.evaluation import ErrorReport, free_vs_compensated, trajectory_errors
from cdtm_graph.verdict.imu_faults import check_imu, sample_noise
from cdtm_graph.verdict.outcome import Verdict
from cdtm_graph.verdict.rules import VerdictSettings, assess

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunOutput:
    """A smoothing run and, with ground truth, its errors beside IMU-only navigation.

    Attributes:
        result: the smoother's result, its ``flags`` those of the verdict.
        errors: the smoothed trajectory's errors ("Compensated"), or None.
        free: the IMU-only dead-reckoning trajectory from the same initial state.
        free_errors: its errors ("Free"), or None.
        report: report.json content beyond what ``write_run`` adds (``verdict``,
            ``reasons``, ``self_checks``, ``evaluation``, timings).
        verdict: trusted, degraded or failed, and why.
    """

    result: SmootherResult
    errors: ErrorReport | None
    free: TrajectoryEstimate | None
    free_errors: ErrorReport | None
    report: dict
    verdict: Verdict


@shared_preintegrations()  # the smoothing and the dead reckoning: one IMU pass
def smooth_and_evaluate(flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
                        progress: Progress | None = None,
                        verdict_settings: VerdictSettings | None = None) -> RunOutput:
    """Smooth ``flight``, judge the run (:func:`cdtm_graph.verdict.rules`: the result's
    flags become the verdict's) and, if it has ground truth, evaluate it as the paper's
    Table 1."""
    start = time.perf_counter()
    result = smooth(flight, dtm, settings, progress)
    report: dict = {"input": str(flight.root), "timings_s": {"smooth": time.perf_counter() - start}}
    # IMU faults (gaps, rate, stuck, saturated), named with the frames they touch
    imu = flight.imu
    findings = check_imu(imu.t_ns, imu.gyro_radps, imu.acc_mps2, flight.config.imu.rate_hz)
    for finding in findings:
        logger.warning("%s", finding.message)
    report["imu_findings"] = [f.to_dict(flight.frames.t_ns) for f in findings]
    noise = sample_noise(imu.t_ns, imu.gyro_radps, imu.acc_mps2,
                         flight.config.imu.gyroscope_noise_density,
                         flight.config.imu.accelerometer_noise_density)
    report["imu_noise"] = noise.to_dict() if noise is not None else None
    errors = free = free_errors = None
    if flight.groundtruth is not None:
        errors = trajectory_errors(result.estimate, result.covariances, flight.groundtruth)
        free = dead_reckoning(flight.config, flight.imu, flight.frames.t_ns,
                              settings.graph.imu_hold, settings.graph.earth_physics)
        free_errors = trajectory_errors(free, None, flight.groundtruth)
        report["evaluation"] = {
            "compensated": errors.to_dict(),
            "free": free_errors.to_dict(),
            "table1": free_vs_compensated(errors, free_errors),
        }
    verdict = assess(result, errors, flight.imu.t_ns, verdict_settings, noise)
    if result.calibration is None and (flight.config.camera.calibration is not None
                                       or settings.graph.calibration_online):
        # asked for, not estimated (the incremental modes): never silent
        message = ("calibration_not_estimated: the calibration was asked for online, which "
                   "only the batch mode estimates; this run held flight.yaml's and checked it "
                   "in a batch side solve (report.json: calibration_check)")
        logger.warning("%s", message)
        verdict = replace(verdict, notes=verdict.notes + (message,))
    result = replace(result, flags=verdict.flags)
    report["verdict"] = verdict.status.value
    report["reasons"] = [r.to_dict() for r in verdict.reasons]
    report["notes"] = list(verdict.notes)
    report["self_checks"] = verdict.self_checks.to_dict()
    if result.calibration_check is not None:
        report["calibration_check"] = result.calibration_check.to_dict()
    if result.position_prior is not None:
        conflict = result.initial_position_conflict()
        report["initial_position"] = {
            "prior": result.position_prior.to_dict(),
            "conflict": None if conflict is None else conflict.to_dict()}
    if result.convergence_check is not None:
        report["convergence_check"] = result.convergence_check.to_dict()
    if result.map_error is not None:
        report["map_error"] = result.map_error.to_dict()
    if result.imu_random_walk is not None:
        report["imu_random_walk"] = result.imu_random_walk.to_dict()
    if result.broad_map_error is not None:
        report["broad_map_error"] = result.broad_map_error.to_dict()
    if result.broad_map_error_whole is not None:
        report["broad_map_error_whole"] = result.broad_map_error_whole.to_dict()
    if result.considered_principal_point is not None:
        report["considered_principal_point"] = result.considered_principal_point.to_dict()
    report["timings_s"]["total"] = time.perf_counter() - start
    return RunOutput(result, errors, free, free_errors, report, verdict)
