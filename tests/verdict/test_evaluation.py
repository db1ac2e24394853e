"""Tests of cdtm_graph.verdict.evaluation: errors, NEES/ANEES, dead reckoning, Table 1."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import gtsam
import numpy as np
import pytest

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import (
    CameraConfig,
    DtmConfig,
    FlightConfig,
    FlightLog,
    Frames,
    ImuConfig,
    ImuSamples,
    InitialState,
    States,
)
from cdtm_graph.geometry import make_pose, rotation_to_quat_wxyz, so3_exp, so3_log
from cdtm_graph.imu import SampleHold, dead_reckoning
from cdtm_graph.results import StateCovariances, TrajectoryEstimate
from cdtm_graph.sim.imu import simulate_imu
from cdtm_graph.sim.trajectory import STANDARD_GRAVITY_MPS2, FlightPlan, evaluate
from cdtm_graph.verdict.evaluation import (
    POSE_DOF,
    POSITION_DOF,
    CovarianceVerdict,
    NeesConsistency,
    anees_band,
    covariance_verdict,
    free_vs_compensated,
    trajectory_errors,
)

NS_PER_S = 1_000_000_000
T0_NS = 1_700_000_000 * NS_PER_S
EXACT_TOL = 1e-9  # metres / radians: sums of a few float64 round-offs
N_NEES_FRAMES = 2000
#: A covariance this many times too small must push the ANEES out of its band.
OVERCONFIDENCE = 10.0

# Dead reckoning on noiseless simulated IMU (200 Hz, midpoint hold, 20 s, a 45 deg turn at
# a 47 deg bank, 2 deg wobble). Measured: 5.6e-3 m, 2.4e-4 deg, 5.6e-4 m/s (the midpoint
# rule and GTSAM's tangent-space preintegration, see cdtm_graph/imu.py); the zero-order
# hold gives 0.8 m and 0.1 deg here. Tolerances leave ~3x margin.
DR_DURATION_S = 20.0
DR_IMU_RATE_HZ = 200.0
DR_FRAME_RATE_HZ = 10.0
DR_POSITION_TOL_M = 0.02
DR_ATTITUDE_TOL_DEG = 7e-4
DR_VELOCITY_TOL_MPS = 2e-3


def _states_from_poses(t_ns: np.ndarray, T: np.ndarray, v: np.ndarray | None = None) -> States:
    v = np.zeros((T.shape[0], 3)) if v is None else v
    return States(t_ns, T[:, :3, 3], rotation_to_quat_wxyz(T[:, :3, :3]), v)


def _estimate(t_ns: np.ndarray, T: np.ndarray, v: np.ndarray | None = None
              ) -> TrajectoryEstimate:
    k = T.shape[0]
    return TrajectoryEstimate(t_ns, T, np.zeros((k, 3)) if v is None else v,
                              np.zeros((k, 3)), np.zeros((k, 3)))


@pytest.fixture
def random_poses(manifold):
    """Factory: _random_poses"""
    def make(rng: np.random.Generator, k: int) -> np.ndarray:
        return np.stack([make_pose(manifold.random_rotation(rng, math.pi * 0.9),
                                   rng.uniform(-1000, 1000, 3)) for _ in range(k)])

    return make


def _random_spd(rng: np.random.Generator, k: int, sigma: np.ndarray) -> np.ndarray:
    n = sigma.size
    a = rng.normal(size=(k, n, n))
    c = a @ np.swapaxes(a, 1, 2) / n + 0.2 * np.eye(n)
    return sigma[:, None] * c * sigma[None, :]


# --------------------------------------------------------------------------- errors


def test_a_known_offset_is_exactly_the_error(random_poses, rng: np.random.Generator):
    k = 30
    t_ns = T0_NS + 100_000_000 * np.arange(k, dtype=np.int64)
    T_true = random_poses(rng, k)
    offset = np.array([3.0, -4.0, 12.0])
    T_est = T_true.copy()
    T_est[:, :3, 3] += offset
    report = trajectory_errors(_estimate(t_ns, T_est), None, _states_from_poses(t_ns, T_true))
    np.testing.assert_allclose(report.position_error_world_m, np.tile(offset, (k, 1)),
                               rtol=0, atol=EXACT_TOL)
    np.testing.assert_allclose(report.rmse_position_m, np.abs(offset), rtol=1e-12)
    np.testing.assert_allclose(report.max_abs_position_error_m, np.abs(offset), rtol=1e-12)
    assert report.rmse_position_3d_m == pytest.approx(13.0, rel=1e-12)
    assert report.max_attitude_deg < EXACT_TOL
    assert report.n_frames_evaluated == k and report.n_frames_outside_groundtruth == 0
    assert report.position_nees is None and report.anees_pose is None


def test_a_known_rotation_offset_is_exactly_the_attitude_error(
    random_poses, rng: np.random.Generator
):
    k = 20
    t_ns = T0_NS + 50_000_000 * np.arange(k, dtype=np.int64)
    T_true = random_poses(rng, k)
    angle_deg = 2.5
    T_est = T_true.copy()
    for i in range(k):  # a body-frame rotation about a random axis: same angle either way
        axis = rng.normal(size=3)
        T_est[i, :3, :3] = T_true[i, :3, :3] @ so3_exp(
            axis / np.linalg.norm(axis) * math.radians(angle_deg))
    report = trajectory_errors(_estimate(t_ns, T_est), None, _states_from_poses(t_ns, T_true))
    np.testing.assert_allclose(report.attitude_error_deg, angle_deg, rtol=1e-9)
    assert report.rmse_attitude_deg == pytest.approx(angle_deg, rel=1e-9)
    np.testing.assert_allclose(report.position_error_world_m, 0.0, atol=EXACT_TOL)


def test_frames_outside_groundtruth_are_excluded_and_counted(
    random_poses, rng: np.random.Generator
):
    t_frames = T0_NS + 100_000_000 * np.arange(10, dtype=np.int64)
    T = random_poses(rng, 10)
    # Ground truth from frame 2 to frame 7 only (at 4x the frame rate, linear motion).
    t_gt = np.arange(t_frames[2], t_frames[7] + 1, 25_000_000, dtype=np.int64)
    gt = States(t_gt, np.zeros((t_gt.size, 3)), np.tile([1.0, 0, 0, 0], (t_gt.size, 1)),
                np.zeros((t_gt.size, 3)))
    report = trajectory_errors(_estimate(t_frames, T), None, gt)
    assert report.n_frames_evaluated == 6 and report.n_frames_outside_groundtruth == 4
    frame = np.arange(10)
    np.testing.assert_array_equal(report.evaluated, (frame >= 2) & (frame <= 7))
    np.testing.assert_array_equal(report.t_ns, t_frames[2:8])
    np.testing.assert_allclose(report.position_error_world_m, T[2:8, :3, 3], atol=EXACT_TOL)


def test_no_frame_inside_groundtruth_gives_a_json_safe_empty_report(random_poses, rng):
    t_frames = T0_NS + np.arange(3, dtype=np.int64)
    gt = States(t_frames[:1] - 10, np.zeros((1, 3)), [[1.0, 0, 0, 0]], np.zeros((1, 3)))
    report = trajectory_errors(_estimate(t_frames, random_poses(rng, 3)), None, gt)
    assert report.n_frames_evaluated == 0 and report.n_frames_outside_groundtruth == 3
    d = report.to_dict(per_frame=True)
    json.dumps(d, allow_nan=False)
    assert d["rmse_position_3d_m"] is None


# --------------------------------------------------------------------------- NEES


def test_pose_error_is_gtsam_local_coordinates_which_is_logmap_of_the_relative_pose(
    random_poses, rng
):
    """The docstring's claim: the wheel's Pose3 retraction is Expmap."""
    T_est = gtsam.Pose3(random_poses(rng, 1)[0])
    xi = np.array([0.3, -0.2, 0.4, 20.0, -5.0, 8.0])
    T_true = T_est.retract(xi)
    np.testing.assert_allclose(T_est.localCoordinates(T_true), xi, atol=1e-12)
    np.testing.assert_allclose(gtsam.Pose3.Logmap(T_est.between(T_true)), xi, atol=1e-12)
    # ...whose translation part is not the plain (body-frame) translation difference.
    plain = T_est.rotation().matrix().T @ (T_true.translation() - T_est.translation())
    assert np.max(np.abs(plain - xi[3:])) > 1.0


@pytest.fixture
def consistent_case(random_poses, rng: np.random.Generator):
    """Estimates whose true poses are drawn from their own covariances (right perturbation)."""
    k = N_NEES_FRAMES
    t_ns = T0_NS + 100_000_000 * np.arange(k, dtype=np.int64)
    T_est = random_poses(rng, k)
    pose_cov = _random_spd(rng, k, np.array([2e-3, 2e-3, 5e-3, 10.0, 10.0, 30.0]))
    xi = np.einsum("kij,kj->ki", np.linalg.cholesky(pose_cov), rng.normal(size=(k, 6)))
    T_true = np.stack([(gtsam.Pose3(T_est[i]) * gtsam.Pose3.Expmap(xi[i])).matrix()
                       for i in range(k)])
    cov = StateCovariances(pose_cov, np.tile(np.eye(3), (k, 1, 1)),
                           np.tile(np.eye(6), (k, 1, 1)))
    return t_ns, T_est, T_true, xi, cov


def test_consistent_covariance_gives_anees_inside_the_chi2_band(consistent_case):
    t_ns, T_est, T_true, xi, cov = consistent_case
    report = trajectory_errors(_estimate(t_ns, T_est), cov, _states_from_poses(t_ns, T_true))
    np.testing.assert_allclose(report.pose_error_tangent, xi, atol=1e-8)
    expected_pose_nees = np.einsum("ki,ki->k", xi,
                                   np.linalg.solve(cov.pose, xi[:, :, None])[:, :, 0])
    np.testing.assert_allclose(report.pose_nees, expected_pose_nees, rtol=1e-6)
    lo, hi = report.anees_pose_band
    assert (lo, hi) == anees_band(N_NEES_FRAMES, POSE_DOF)
    assert lo < report.anees_pose < hi and report.anees_pose_inside_band
    lo, hi = report.anees_position_band
    assert lo < report.anees_position < hi and report.anees_position_inside_band
    # independent frames drawn from their covariance: the one decision agrees
    assert report.pose_consistent and report.position_consistent
    assert report.to_dict()["anees_pose_consistent"] is True


def test_overconfident_covariance_falls_outside_the_band(consistent_case):
    t_ns, T_est, T_true, _, cov = consistent_case
    small = StateCovariances(cov.pose / OVERCONFIDENCE, cov.velocity, cov.bias)
    report = trajectory_errors(_estimate(t_ns, T_est), small, _states_from_poses(t_ns, T_true))
    assert report.anees_pose > report.anees_pose_band[1]
    assert report.anees_position > report.anees_position_band[1]
    assert report.anees_pose_inside_band is False
    assert report.anees_position_inside_band is False
    assert report.pose_consistent is False and report.position_consistent is False


def test_anees_band_is_the_chi2_quantile_over_k():
    lo, hi = anees_band(1, POSITION_DOF)
    assert lo == pytest.approx(0.2158, abs=1e-4) and hi == pytest.approx(9.3484, abs=1e-4)
    lo, hi = anees_band(1000, POSITION_DOF)
    assert lo < 3.0 < hi and hi - lo < 0.5


# --------------------------------------------------------------------------- dead reckoning


def _flight_log(tmp_path: Path, t_imu: np.ndarray, gyro: np.ndarray, acc: np.ndarray,
                t_frames: np.ndarray, T0: np.ndarray, v0: np.ndarray,
                gyro_bias=(0.0, 0.0, 0.0), accel_bias=(0.0, 0.0, 0.0)) -> FlightLog:
    config = FlightConfig(
        gravity_mps2=STANDARD_GRAVITY_MPS2,
        dtm=DtmConfig(tmp_path / "dtm.npz"),
        camera=CameraConfig(PinholeCamera(400, 400, 346.4, 346.4, 199.5, 199.5), 0.5,
                            np.eye(4)),
        imu=ImuConfig(DR_IMU_RATE_HZ, 1.7e-4, 2.0e-3, 1.9e-5, 3.0e-3),
        initial_state=InitialState(
            position_m=T0[:3, 3], quaternion_wxyz=rotation_to_quat_wxyz(T0[:3, :3]),
            velocity_mps=v0, gyro_bias=gyro_bias, accel_bias=accel_bias,
            sigma_position_m=50.0, sigma_attitude_deg=1.0, sigma_velocity_mps=1.0,
            sigma_gyro_bias=1e-4, sigma_accel_bias=1e-2))
    return FlightLog(tmp_path, config, ImuSamples(t_imu, gyro, acc),
                     Frames(t_frames, ("",) * t_frames.size))


def _simulated_log(tmp_path: Path, rng: np.random.Generator, gyro_bias, accel_bias):
    plan = FlightPlan(legs=((1000.0, 45.0), (3000.0, 0.0)), camera_wobble_deg=2.0)
    t_imu = np.arange(int(DR_DURATION_S * DR_IMU_RATE_HZ) + 1, dtype=np.int64) * (
        NS_PER_S // int(DR_IMU_RATE_HZ))
    imu = simulate_imu(plan, t_imu, STANDARD_GRAVITY_MPS2, None, rng,
                       initial_gyro_bias=gyro_bias, initial_accel_bias=accel_bias)
    t_frames = t_imu[:: int(DR_IMU_RATE_HZ / DR_FRAME_RATE_HZ)]
    truth = evaluate(plan, t_frames / NS_PER_S)
    T_true = np.stack([make_pose(R, p) for R, p in
                       zip(truth.rotation_world_body, truth.position_m, strict=True)])
    log = _flight_log(tmp_path, t_imu, imu.gyro_radps, imu.acc_mps2, t_frames, T_true[0],
                      truth.velocity_mps[0], gyro_bias, accel_bias)
    return log, T_true, truth.velocity_mps


@pytest.mark.parametrize("gyro_bias, accel_bias", [
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    ((2e-3, -1e-3, 5e-4), (0.05, -0.02, 0.1)),  # known biases must be removed
])
def test_dead_reckoning_on_noiseless_imu_follows_the_truth(tmp_path, rng, gyro_bias,
                                                           accel_bias):
    log, T_true, v_true = _simulated_log(tmp_path, rng, gyro_bias, accel_bias)
    est = dead_reckoning(log.config, log.imu, log.frames.t_ns)  # default: midpoint hold
    assert len(est) == T_true.shape[0]
    np.testing.assert_array_equal(est.t_ns, log.frames.t_ns)
    # The flight goes somewhere: errors are small against ~4 km and a 45 deg turn.
    assert np.linalg.norm(T_true[-1, :3, 3] - T_true[0, :3, 3]) > 3000.0
    position_error = np.linalg.norm(est.position_m - T_true[:, :3, 3], axis=1)
    assert position_error.max() < DR_POSITION_TOL_M
    attitude_error = np.degrees(np.linalg.norm(
        so3_log(np.swapaxes(est.world_T_body[:, :3, :3], 1, 2) @ T_true[:, :3, :3]), axis=1))
    assert attitude_error.max() < DR_ATTITUDE_TOL_DEG
    assert np.abs(est.velocity_mps - v_true).max() < DR_VELOCITY_TOL_MPS
    np.testing.assert_array_equal(est.gyro_bias, np.tile(gyro_bias, (len(est), 1)))
    np.testing.assert_array_equal(est.accel_bias, np.tile(accel_bias, (len(est), 1)))


@pytest.mark.parametrize("hold", list(SampleHold))
def test_dead_reckoning_drifts_by_the_initial_velocity_error(tmp_path, hold):
    """Straight level flight, IMU reading exactly gravity: Free navigation drifts as dv t."""
    n_imu, dt_ns = 2001, 5_000_000
    t_imu = T0_NS + dt_ns * np.arange(n_imu, dtype=np.int64)
    gyro = np.zeros((n_imu, 3))
    acc = np.tile([0.0, 0.0, STANDARD_GRAVITY_MPS2], (n_imu, 1))
    t_frames = t_imu[::20]
    T0 = make_pose(np.eye(3), [100.0, 200.0, 1000.0])
    v_true = np.array([200.0, 0.0, 0.0])
    dv = np.array([0.0, 0.5, -0.1])
    log = _flight_log(tmp_path, t_imu, gyro, acc, t_frames, T0, v_true + dv)
    est = dead_reckoning(log.config, log.imu, log.frames.t_ns, hold)
    elapsed_s = (t_frames - t_frames[0]) / NS_PER_S
    expected = T0[:3, 3] + np.outer(elapsed_s, v_true + dv)
    np.testing.assert_allclose(est.position_m, expected, rtol=0, atol=1e-6)
    truth = States(t_frames, T0[:3, 3] + np.outer(elapsed_s, v_true),
                   np.tile([1.0, 0, 0, 0], (t_frames.size, 1)),
                   np.tile(v_true, (t_frames.size, 1)))
    errors = trajectory_errors(est, None, truth)
    np.testing.assert_allclose(errors.max_abs_position_error_m, np.abs(dv) * elapsed_s[-1],
                               rtol=1e-6, atol=1e-6)


def test_dead_reckoning_needs_imu_over_the_frames(tmp_path):
    t_imu = T0_NS + 5_000_000 * np.arange(10, dtype=np.int64)
    log = _flight_log(tmp_path, t_imu, np.zeros((10, 3)), np.zeros((10, 3)),
                      np.array([t_imu[0], t_imu[-1] + 1]), np.eye(4), np.zeros(3))
    with pytest.raises(FlightLogError, match="imu.csv"):
        dead_reckoning(log.config, log.imu, log.frames.t_ns)


# --------------------------------------------------------------------------- Table 1


def _offset_report(random_poses, rng, offset: np.ndarray):
    k = 5
    t_ns = T0_NS + np.arange(k, dtype=np.int64)
    T_true = random_poses(rng, k)
    T_est = T_true.copy()
    T_est[:, :3, 3] += offset * np.linspace(-1.0, 1.0, k)[:, None]  # max |error| = |offset|
    return trajectory_errors(_estimate(t_ns, T_est), None, _states_from_poses(t_ns, T_true))


def test_free_vs_compensated_is_table_1(random_poses, rng):
    free = _offset_report(random_poses, rng, np.array([900.0, 1000.0, 250.0]))
    comp = _offset_report(random_poses, rng, np.array([25.0, 25.0, 0.0]))
    table = free_vs_compensated(comp, free)
    assert list(table["rows"]) == ["Free-x", "Compensated-x", "Free-y", "Compensated-y",
                                   "Free-z", "Compensated-z"]
    assert table["rows"]["Free-x"] == pytest.approx(900.0)
    assert table["rows"]["Compensated-y"] == pytest.approx(25.0)
    assert table["ratio_free_over_compensated"]["x"] == pytest.approx(36.0)
    assert table["ratio_free_over_compensated"]["y"] == pytest.approx(40.0)
    assert table["ratio_free_over_compensated"]["z"] is None  # compensated error is zero
    json.dumps(table, allow_nan=False)


# --------------------------------------------------------------------------- one decision


#: Constructed per-frame position NEES of 90 frames (a flight's length): the decision's
#: cases. ``split``: 75 frames at 3 and 15 at 9 (83% inside 7.81, ANEES 4.0 outside the
#: band for 90 independent frames [2.41, 3.65]): the case the console and report.json
#: used to name differently.
NEES_CASES = {
    "split": (np.r_[np.full(75, 3.0), np.full(15, 9.0)], CovarianceVerdict.CONSISTENT),
    "at_the_bound": (np.r_[np.full(72, 3.0), np.full(18, 9.0)], CovarianceVerdict.CONSISTENT),
    "optimistic": (np.r_[np.full(71, 3.0), np.full(19, 9.0)], CovarianceVerdict.OPTIMISTIC),
    "conservative": (np.full(90, 0.2), CovarianceVerdict.CONSERVATIVE),
    "honest": (np.full(90, 2.4), CovarianceVerdict.CONSISTENT),
}


@pytest.mark.parametrize("case", sorted(NEES_CASES))
def test_one_decision_of_consistent_on_constructed_nees(case):
    """The one decision (:func:`covariance_verdict`): optimistic below 80% of the frames
    inside chi-square(3)'s 95% bound (72 of 90 = 80% is not, 71 is), conservative when the
    median is under chi-square(3)'s 5% quantile (0.35), consistent otherwise, whatever
    ANEES's band for independent frames says; ``consistent``, report.json's
    ``anees_position_consistent`` and the summary's first word agree. Mutations: the
    decision taken from the ANEES band (``split`` and ``at_the_bound`` fail); the 80%
    compared with <= (``at_the_bound`` fails); report.json's key back to the band test
    (``split`` fails)."""
    nees, word = NEES_CASES[case]
    c = NeesConsistency.of(nees, POSITION_DOF)
    assert c is not None and c.verdict is word
    assert covariance_verdict(c.inside_fraction, c.percentiles[50.0], POSITION_DOF) is word
    assert c.consistent is (word is CovarianceVerdict.CONSISTENT)
    d = c.to_dict()
    assert d["verdict"] == word.value and d["consistent"] is c.consistent
    assert d["summary"] == c.summary() and c.summary().startswith(f"{word.value}: ")
    # the report of an estimate with these NEES: its keys read the same decision
    k = nees.size
    report = dataclasses.replace(
        _report_of_nees_frames(k), position_nees=nees, anees_position=float(nees.mean()),
        anees_position_band=anees_band(k, POSITION_DOF))
    out = report.to_dict()
    assert out["anees_position_consistent"] is c.consistent is report.position_consistent
    assert out["position_consistency"]["summary"] == c.summary()
    lo, hi = anees_band(k, POSITION_DOF)
    inside_band = bool(lo <= nees.mean() <= hi)
    assert out["anees_position_inside_band_95"] is inside_band
    if case == "split":  # the case the two old rules split
        assert not inside_band and c.consistent


def _report_of_nees_frames(k: int):
    """An error report of ``k`` frames at rest on their ground truth (its NEES replaced)."""
    t_ns = T0_NS + 1_000_000_000 * np.arange(k, dtype=np.int64)
    T = np.tile(np.eye(4), (k, 1, 1))
    cov = StateCovariances(np.tile(np.eye(6), (k, 1, 1)), np.tile(np.eye(3), (k, 1, 1)),
                           np.tile(np.eye(6), (k, 1, 1)))
    return trajectory_errors(_estimate(t_ns, T), cov, _states_from_poses(t_ns, T))
