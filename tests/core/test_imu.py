"""Tests of IMU synthesis, noise, and preintegration of exact samples with GTSAM.

Noiseless preintegration cannot match the analytic truth to round-off: GTSAM
integrates one held measurement per step with the rotation at the step's start, which
is first order in dt. The tests measure that error against its analytic prediction,
check its convergence order (first order for ``SampleHold.ZERO_ORDER``, second for
``SampleHold.MIDPOINT``), and bound it at 200 Hz with tolerances derived from
those measurements (each named constant says where its number comes from).

GTSAM 4.3's default ``PreintegratedCombinedMeasurements`` (the one ``CombinedImuFactor``
takes) integrates rotation by Euler steps in tangent coordinates: it is not the exact
product of per-step exponentials (``PreintegratedCombinedMeasurementsManifold`` is). That
adds a small first-order rotation error and makes two composed preintegrations differ
from one by ~1e-6. Tests that isolate our own arithmetic (convergence order, exact
composition) therefore use the Manifold variant; tests of the accuracy a smoother gets
use the default.
"""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
import pytest

from cdtm_graph.flightlog import ImuSamples
from cdtm_graph.imu import (
    NS_PER_S,
    GapNoise,
    ImuIntervals,
    ImuNoise,
    ImuStream,
    SampleHold,
    hold_segments,
    integrate_interval,
    preintegration_params,
    shared_preintegrations,
)
from cdtm_graph.sim.faults import with_imu_gap
from cdtm_graph.sim.imu import ImuData, ideal_imu, simulate_imu
from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight
from cdtm_graph.sim.trajectory import FlightPlan, evaluate, plan_trajectory

G_MPS2 = 9.80665
RATE_HZ = 200.0
# Sample grid offset so frame times fall between samples and boundary holds are split.
SAMPLE_OFFSET_NS = 1_700_000
# Near-zero covariances: the tests here look at the mean, not the noise model.
TINY_NOISE = ImuNoise(1e-6, 1e-6, 1e-6, 1e-6)

PLAN = FlightPlan(camera_wobble_deg=2.0, camera_wobble_period_s=7.0)
LEVEL_PLAN = FlightPlan()
# Default plan: straight 0-10 s, bank ramp 10-12 s, 3 deg/s arc 12-40 s, ramp 40-42 s.
STRAIGHT_S = (2.0, 3.0)
RAMP_S = (10.3, 11.3)
ARC_S = (20.0, 21.0)
THROUGH_RAMP_S = (9.5, 12.5)

# Constant signals (level straight flight) are integrated exactly: round-off only.
EXACT_POS_TOL_M = 1e-9
EXACT_VEL_TOL_MPS = 1e-9
EXACT_ROT_TOL_RAD = 1e-12
# Steady turn, zero-order hold: the error equals its first-order prediction to ~0.5 %
# (the velocity error vector turns by 3 deg over the second); 5 % leaves margin.
PREDICTION_RTOL = 0.05
# Zero-order hold through 1 s of bank ramp at 200 Hz: measured 1.07e-2 m, 2.32e-2 m/s,
# 2.5e-4 rad. The error is GTSAM's first-order integration (see the order test), not a
# modelling error; the bounds are the measurements plus 50 %.
ZOH_RAMP_POS_TOL_M = 1.6e-2
ZOH_RAMP_VEL_TOL_MPS = 3.5e-2
ZOH_RAMP_ROT_TOL_RAD = 4e-4
# Midpoint hold through a whole bank ramp entry (3 s) at 200 Hz, default (tangent)
# preintegration: measured 1.0e-4 m, 1.2e-4 m/s, 6.4e-6 rad, of which the tangent-space
# rotation update causes about a third (Manifold variant: 5.8e-5 m). Bounds = the
# measurements plus ~60 %. Millimetre-class: accelerometer noise alone gives ~3e-3 m/s.
MIDPOINT_POS_TOL_M = 2e-4
MIDPOINT_VEL_TOL_MPS = 2e-4
MIDPOINT_ROT_TOL_RAD = 1e-5
# Halving dt divides a first-order error by 2 and a second-order one by 4 (measured
# 2.00 and 4.00 with the Manifold variant and frame times on the sample grid).
FIRST_ORDER_RATIO = (1.9, 2.1)
SECOND_ORDER_RATIO = (3.8, 4.2)
# Composing two preintegrations split at a hold boundary feeds GTSAM identical steps:
# with the Manifold variant only round-off on ~1e4 m coordinates remains; the default
# tangent-space variant re-linearizes its rotation at the split (measured 2.5e-6 m/s,
# 1e-6 rad over a 1 s bank-ramp interval split in two).
COMPOSE_TOL = 1e-9
TANGENT_COMPOSE_TOL = 1e-5
# Monte Carlo: 40 000 samples give a relative std of the sample std of 1/sqrt(2N) =
# 0.35 %, so 3 % is > 8 sigma yet fails for any wrong sqrt(rate) factor.
MC_SAMPLES = 40_000
MC_RTOL = 0.03
# Preintegrated covariance vs its continuous-time formula: GTSAM's discrete sums of the
# T^3 terms differ by ~1.5 dt relative (< 1 % at 100 Hz); a missing 1/dt would be off
# by a factor of the rate.
COV_RTOL = 0.02


def _sample_times_ns(t0_s: float, t1_s: float, rate_hz: float,
                     offset_ns: int = SAMPLE_OFFSET_NS) -> np.ndarray:
    """A uniform grid of IMU times covering [t0 - 1 s, t1 + 1 s], shifted by offset_ns."""
    step = round(NS_PER_S / rate_hz)
    n = int(math.ceil((t1_s - t0_s + 2.0) * rate_hz)) + 1
    return round((t0_s - 1.0) * NS_PER_S) + offset_ns + step * np.arange(n, dtype=np.int64)


def _nav_state(plan: FlightPlan, t_ns: int) -> gtsam.NavState:
    s = evaluate(plan, np.array([t_ns / NS_PER_S]))
    return gtsam.NavState(gtsam.Rot3.Quaternion(*s.quaternion_wxyz[0]), s.position_m[0],
                          s.velocity_mps[0])


DEFAULT_PIM = gtsam.PreintegratedCombinedMeasurements
MANIFOLD_PIM = gtsam.PreintegratedCombinedMeasurementsManifold


def _new_pim(bias: gtsam.imuBias.ConstantBias | None = None, pim_class=DEFAULT_PIM):
    params = preintegration_params(TINY_NOISE, G_MPS2)
    return pim_class(params, bias or gtsam.imuBias.ConstantBias())


def _errors(pred: gtsam.NavState, true: gtsam.NavState) -> tuple[float, float, float]:
    """Position (m), velocity (m/s) and rotation (rad) differences."""
    rot = np.linalg.norm(gtsam.Rot3.Logmap(true.attitude().between(pred.attitude())))
    return (float(np.linalg.norm(pred.position() - true.position())),
            float(np.linalg.norm(pred.velocity() - true.velocity())), float(rot))


def _preintegration_errors(plan, interval_s, rate_hz, hold, gyro_bias=(0.0, 0.0, 0.0),
                           accel_bias=(0.0, 0.0, 0.0), pim_class=DEFAULT_PIM,
                           offset_ns=SAMPLE_OFFSET_NS):
    """Noiseless samples -> integrate_interval -> predict from truth; errors at the end."""
    t = _sample_times_ns(*interval_s, rate_hz, offset_ns)
    # noiseless (noise None): the generator is never drawn from, its seed is moot
    imu = simulate_imu(plan, t, G_MPS2, None, np.random.default_rng(0), gyro_bias, accel_bias)
    t0, t1 = (round(x * NS_PER_S) for x in interval_s)
    bias = gtsam.imuBias.ConstantBias(np.array(accel_bias), np.array(gyro_bias))
    pim = _new_pim(bias, pim_class)
    integrate_interval(pim, imu.t_ns, imu.gyro_radps, imu.acc_mps2, t0, t1, hold)
    return _errors(pim.predict(_nav_state(plan, t0), bias), _nav_state(plan, t1))


# --- ideal and simulated samples ---------------------------------------------------

def test_level_straight_flight_reads_plus_g_on_z_and_no_rate():
    traj = plan_trajectory(LEVEL_PLAN, 5.0, RATE_HZ)
    gyro, acc = ideal_imu(traj, G_MPS2)
    np.testing.assert_allclose(gyro, 0.0, atol=1e-15)
    np.testing.assert_allclose(acc, np.tile([0.0, 0.0, G_MPS2], (len(traj), 1)), atol=1e-12)


def test_steady_turn_reads_tilted_gravity_and_yaw_rate_in_body():
    t = np.array([np.mean(ARC_S)])
    gyro, acc = ideal_imu(evaluate(LEVEL_PLAN, t), G_MPS2)
    w = math.radians(LEVEL_PLAN.turn_rate_dps)
    a_c = LEVEL_PLAN.speed_mps * w
    # Coordinated: all specific force along body z; the world yaw rate (0, 0, w) seen
    # from a body banked left by atan(a_c / g).
    np.testing.assert_allclose(acc[0], [0.0, 0.0, math.hypot(G_MPS2, a_c)], atol=1e-12)
    bank = math.atan(a_c / G_MPS2)
    np.testing.assert_allclose(gyro[0], [0.0, -w * math.sin(bank), w * math.cos(bank)],
                               atol=1e-15)


def test_noiseless_simulation_is_ideal_plus_constant_bias(rng):
    t = _sample_times_ns(0.0, 3.0, RATE_HZ)
    bg, ba = (1e-3, -2e-3, 3e-3), (0.1, -0.2, 0.3)
    imu = simulate_imu(PLAN, t, G_MPS2, None, rng, bg, ba)
    gyro, acc = ideal_imu(evaluate(PLAN, t / NS_PER_S), G_MPS2)
    np.testing.assert_allclose(imu.gyro_radps, gyro + bg, atol=1e-15)
    np.testing.assert_allclose(imu.acc_mps2, acc + ba, atol=1e-14)
    np.testing.assert_array_equal(imu.gyro_bias, np.tile(bg, (t.size, 1)))
    assert imu.t_ns.dtype == np.int64


def test_white_noise_std_is_density_times_sqrt_rate(rng):
    noise = ImuNoise(gyroscope_random_walk=0.0, accelerometer_random_walk=0.0)
    t = round(NS_PER_S / RATE_HZ) * np.arange(MC_SAMPLES, dtype=np.int64)
    imu = simulate_imu(LEVEL_PLAN, t, G_MPS2, noise, rng)
    # Ideal values are known exactly, so the residual is the noise and nothing else.
    gyro, acc = ideal_imu(evaluate(LEVEL_PLAN, t / NS_PER_S), G_MPS2)
    std_g = np.std(imu.gyro_radps - gyro, axis=0, ddof=1)
    std_a = np.std(imu.acc_mps2 - acc, axis=0, ddof=1)
    np.testing.assert_allclose(std_g, noise.gyroscope_noise_density * math.sqrt(RATE_HZ),
                               rtol=MC_RTOL)
    np.testing.assert_allclose(std_a, noise.accelerometer_noise_density * math.sqrt(RATE_HZ),
                               rtol=MC_RTOL)


def test_bias_random_walk_steps_have_sigma_rw_sqrt_dt(rng):
    noise = ImuNoise()
    t = round(NS_PER_S / RATE_HZ) * np.arange(MC_SAMPLES, dtype=np.int64)
    imu = simulate_imu(LEVEL_PLAN, t, G_MPS2, noise, rng, (0.01, 0.0, 0.0), (0.0, 0.2, 0.0))
    dt = 1.0 / RATE_HZ
    np.testing.assert_allclose(imu.gyro_bias[0], [0.01, 0.0, 0.0])
    np.testing.assert_allclose(np.std(np.diff(imu.gyro_bias, axis=0), axis=0, ddof=1),
                               noise.gyroscope_random_walk * math.sqrt(dt), rtol=MC_RTOL)
    np.testing.assert_allclose(np.std(np.diff(imu.accel_bias, axis=0), axis=0, ddof=1),
                               noise.accelerometer_random_walk * math.sqrt(dt), rtol=MC_RTOL)
    # Measurements carry the walking bias.
    gyro, _ = ideal_imu(evaluate(LEVEL_PLAN, t / NS_PER_S), G_MPS2)
    residual = imu.gyro_radps - gyro - imu.gyro_bias
    np.testing.assert_allclose(np.mean(residual, axis=0), 0.0, atol=5e-4)


def test_simulation_is_reproducible_from_the_seed(seed):
    t = _sample_times_ns(0.0, 1.0, RATE_HZ)
    a = simulate_imu(PLAN, t, G_MPS2, ImuNoise(), np.random.default_rng(seed))
    b = simulate_imu(PLAN, t, G_MPS2, ImuNoise(), np.random.default_rng(seed))
    np.testing.assert_array_equal(a.acc_mps2, b.acc_mps2)
    np.testing.assert_array_equal(a.gyro_bias, b.gyro_bias)


def test_simulation_rejects_bad_times(rng):
    with pytest.raises(ValueError):
        simulate_imu(PLAN, np.array([0, 10, 10]), G_MPS2, None, rng)
    with pytest.raises(ValueError):
        simulate_imu(PLAN, np.array([0.0, 0.1]), G_MPS2, None, rng)
    with pytest.raises(ValueError):
        ImuData(np.zeros(3, np.int64), np.zeros((3, 3)), np.zeros((2, 3)),
                np.zeros((3, 3)), np.zeros((3, 3)))


# --- GTSAM parameters ----------------------------------------------------------------

def test_preintegration_params_hold_the_densities_squared():
    noise = ImuNoise()
    p = preintegration_params(noise, G_MPS2, rate_hz=RATE_HZ)
    eye = np.eye(3)
    np.testing.assert_allclose(p.getGyroscopeCovariance(), noise.gyroscope_noise_density ** 2 * eye)
    np.testing.assert_allclose(p.getAccelerometerCovariance(),
                               noise.accelerometer_noise_density ** 2 * eye)
    np.testing.assert_allclose(p.getBiasOmegaCovariance(), noise.gyroscope_random_walk ** 2 * eye)
    np.testing.assert_allclose(p.getBiasAccCovariance(),
                               noise.accelerometer_random_walk ** 2 * eye)
    np.testing.assert_allclose(p.n_gravity.ravel(), [0.0, 0.0, -G_MPS2])
    with pytest.raises(ValueError):
        preintegration_params(noise, G_MPS2, rate_hz=0.0)


@pytest.mark.parametrize("rate_hz", [100.0, 400.0])
def test_gtsam_reads_the_covariances_as_continuous_time(rate_hz):
    """Without motion, T of preintegration must give density^2 T at any rate.

    This is what makes passing the densities unscaled right: GTSAM divides by dt. The
    combined factor also integrates the bias random walks (rw^2 T^3 / 3), and the
    tilt uncertainty leaks gravity into horizontal velocity (g^2 of the integrated
    attitude variance).
    """
    noise = ImuNoise()
    pim = gtsam.PreintegratedCombinedMeasurements(preintegration_params(noise, G_MPS2))
    for _ in range(int(rate_hz)):
        pim.integrateMeasurement(np.array([0.0, 0.0, G_MPS2]), np.zeros(3), 1.0 / rate_hz)
    var = np.diag(pim.preintMeasCov())  # order: rotation, position, velocity, b_acc, b_gyro
    T = 1.0
    sg, sa = noise.gyroscope_noise_density ** 2, noise.accelerometer_noise_density ** 2
    wg, wa = noise.gyroscope_random_walk ** 2, noise.accelerometer_random_walk ** 2
    rot = sg * T + wg * T ** 3 / 3
    vel_z = sa * T + wa * T ** 3 / 3
    vel_xy = vel_z + G_MPS2 ** 2 * (sg * T ** 3 / 3 + wg * T ** 5 / 20)
    np.testing.assert_allclose(var[0:3], rot, rtol=COV_RTOL)
    np.testing.assert_allclose(var[6:9], [vel_xy, vel_xy, vel_z], rtol=COV_RTOL)
    np.testing.assert_allclose(var[9:12], wa * T, rtol=1e-12)
    np.testing.assert_allclose(var[12:15], wg * T, rtol=1e-12)


# --- splitting samples over intervals ------------------------------------------------

@pytest.mark.parametrize("hold", list(SampleHold))
def test_hold_segments_tile_the_interval_exactly(hold, rng):
    t = np.cumsum(rng.integers(3_000_000, 7_000_000, size=400)).astype(np.int64)
    for _ in range(50):
        t0, t1 = np.sort(rng.integers(t[0], t[-1], size=2))
        if t1 == t0:
            continue
        index, dt_ns = hold_segments(t, int(t0), int(t1), hold)
        assert dt_ns.dtype == np.int64
        assert int(dt_ns.sum()) == t1 - t0
        assert np.all(dt_ns > 0) and np.all(np.diff(index) == 1)
        # Each piece lies inside its sample's hold interval.
        ends = t0 + np.cumsum(dt_ns)
        starts = ends - dt_ns
        if hold is SampleHold.ZERO_ORDER:
            assert np.all(starts >= t[index]) and np.all(ends <= t[index + 1])
        else:
            assert np.all(np.abs(starts - t[index]) <= np.diff(t).max() // 2 + 1)
            assert np.all(np.abs(ends - t[index]) <= np.diff(t).max() // 2 + 1)
    # The float durations GTSAM receives add up to the interval to round-off.
    index, dt_ns = hold_segments(t, int(t[3]) + 1, int(t[-3]) - 1, hold)
    assert math.fsum(dt_ns / NS_PER_S) == pytest.approx((t[-3] - t[3] - 2) / NS_PER_S,
                                                        rel=1e-15)


def test_zero_order_hold_pieces_by_hand():
    t = np.arange(0, 100, 10, dtype=np.int64)
    index, dt_ns = hold_segments(t, 3, 47, SampleHold.ZERO_ORDER)
    np.testing.assert_array_equal(index, [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(dt_ns, [7, 10, 10, 10, 7])
    index, dt_ns = hold_segments(t, 3, 47, SampleHold.MIDPOINT)
    np.testing.assert_array_equal(index, [0, 1, 2, 3, 4, 5])
    np.testing.assert_array_equal(dt_ns, [2, 10, 10, 10, 10, 2])


@pytest.mark.parametrize("t0, t1", [(-1, 50), (10, 91), (50, 50), (60, 40)])
def test_uncovered_or_empty_interval_raises(t0, t1):
    t = np.arange(0, 100, 10, dtype=np.int64)
    pim = _new_pim()
    with pytest.raises(ValueError):
        integrate_interval(pim, t, np.zeros((10, 3)), np.zeros((10, 3)), t0, t1)


def test_bad_sample_arrays_raise():
    t = np.arange(0, 100, 10, dtype=np.int64)
    with pytest.raises(ValueError):
        integrate_interval(_new_pim(), t, np.zeros((9, 3)), np.zeros((10, 3)), 0, 50)
    with pytest.raises(ValueError):
        hold_segments(np.array([0, 10, 5, 20, 30]), 0, 20)
    with pytest.raises(ValueError):
        hold_segments(t.astype(float), 0, 20)


# --- noiseless preintegration against the analytic truth ----------------------------

@pytest.mark.parametrize("hold", list(SampleHold))
def test_level_straight_flight_preintegrates_exactly(hold):
    pos, vel, rot = _preintegration_errors(LEVEL_PLAN, STRAIGHT_S, RATE_HZ, hold)
    assert pos < EXACT_POS_TOL_M and vel < EXACT_VEL_TOL_MPS and rot < EXACT_ROT_TOL_RAD


def test_zero_order_hold_error_in_a_steady_turn_matches_its_prediction():
    """GTSAM's v += R_k f dt lags the world-frame specific force by dt/2.

    In a steady coordinated turn the body rate and specific force are constant in body,
    so that lag is the whole error: |w x f_world| = v w^2 gives a velocity error of
    v w^2 dt T / 2 and a position error of v w^2 dt T^2 / 4 (0.69 mm after 1 s).
    """
    pos, vel, rot = _preintegration_errors(LEVEL_PLAN, ARC_S, RATE_HZ, SampleHold.ZERO_ORDER)
    w = math.radians(LEVEL_PLAN.turn_rate_dps)
    T, dt = ARC_S[1] - ARC_S[0], 1.0 / RATE_HZ
    rate = LEVEL_PLAN.speed_mps * w ** 2
    assert vel == pytest.approx(rate * dt * T / 2, rel=PREDICTION_RTOL)
    assert pos == pytest.approx(rate * dt * T ** 2 / 4, rel=PREDICTION_RTOL)
    assert rot < EXACT_ROT_TOL_RAD * 1e3  # constant body rate: rotation is exact


def test_zero_order_hold_error_through_a_bank_ramp_is_bounded():
    pos, vel, rot = _preintegration_errors(PLAN, RAMP_S, RATE_HZ, SampleHold.ZERO_ORDER)
    assert pos < ZOH_RAMP_POS_TOL_M
    assert vel < ZOH_RAMP_VEL_TOL_MPS
    assert rot < ZOH_RAMP_ROT_TOL_RAD


def test_midpoint_hold_reaches_sub_millimetre_through_a_bank_ramp():
    pos, vel, rot = _preintegration_errors(PLAN, THROUGH_RAMP_S, RATE_HZ, SampleHold.MIDPOINT)
    assert pos < MIDPOINT_POS_TOL_M
    assert vel < MIDPOINT_VEL_TOL_MPS
    assert rot < MIDPOINT_ROT_TOL_RAD


@pytest.mark.parametrize("hold", list(SampleHold))
def test_known_bias_is_removed_exactly(hold):
    """Biased samples with the true bias as estimate integrate like unbiased ones.

    GTSAM subtracts its bias estimate itself; the midpoint hold must rotate the
    *bias-corrected* force by the *bias-corrected* rate, or it would leave
    (|w| |b_a| + |b_g| |f|) dt/2 ~ 1e-3 m/s^2 behind.
    """
    clean = _preintegration_errors(PLAN, THROUGH_RAMP_S, RATE_HZ, hold)
    biased = _preintegration_errors(PLAN, THROUGH_RAMP_S, RATE_HZ, hold,
                                    gyro_bias=(0.01, -0.02, 0.015), accel_bias=(0.5, -0.3, 0.4))
    np.testing.assert_allclose(biased, clean, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("hold, ratio", [(SampleHold.ZERO_ORDER, FIRST_ORDER_RATIO),
                                         (SampleHold.MIDPOINT, SECOND_ORDER_RATIO)])
def test_error_converges_at_the_order_of_the_hold(hold, ratio):
    """Proves the residual errors are discretization, not a modelling mistake.

    Frame times sit on both sample grids (offset 0) so the partial pieces at the ends
    are the same fraction of dt at both rates, and the Manifold variant keeps GTSAM's
    own first-order tangent-space rotation error out of the measurement.
    """
    kwargs = {"pim_class": MANIFOLD_PIM, "offset_ns": 0}
    coarse = _preintegration_errors(PLAN, THROUGH_RAMP_S, RATE_HZ, hold, **kwargs)
    fine = _preintegration_errors(PLAN, THROUGH_RAMP_S, 2 * RATE_HZ, hold, **kwargs)
    for c, f in zip(coarse, fine, strict=True):
        assert ratio[0] < c / f < ratio[1]


# --- composing intervals -------------------------------------------------------------

def _compose_vs_single(hold, tm_ns, pim_class):
    """(position, velocity, rotation) gap between [t0, tm] + [tm, t1] and [t0, t1]."""
    plan, t = PLAN, _sample_times_ns(*RAMP_S, RATE_HZ)
    # noiseless (noise None): the generator is never drawn from, its seed is moot
    imu = simulate_imu(plan, t, G_MPS2, None, np.random.default_rng(0))
    t0, t1 = (round(x * NS_PER_S) for x in RAMP_S)
    x0, bias = _nav_state(plan, t0), gtsam.imuBias.ConstantBias()
    samples = (imu.t_ns, imu.gyro_radps, imu.acc_mps2)
    whole, first, second = (_new_pim(pim_class=pim_class) for _ in range(3))
    integrate_interval(whole, *samples, t0, t1, hold)
    integrate_interval(first, *samples, t0, tm_ns, hold)
    integrate_interval(second, *samples, tm_ns, t1, hold)
    assert first.deltaTij() + second.deltaTij() == pytest.approx(whole.deltaTij(), rel=1e-15)
    composed = second.predict(first.predict(x0, bias), bias)
    return _errors(composed, whole.predict(x0, bias))


def _hold_boundary_ns(hold: SampleHold) -> int:
    """A hold boundary in the middle of RAMP_S."""
    t = _sample_times_ns(*RAMP_S, RATE_HZ)
    k = int(np.searchsorted(t, round(np.mean(RAMP_S) * NS_PER_S)))
    return int(t[k] if hold is SampleHold.ZERO_ORDER else t[k] + (t[k + 1] - t[k]) // 2)


@pytest.mark.parametrize("hold", list(SampleHold))
def test_split_at_a_hold_boundary_gives_the_same_pieces(hold):
    t = _sample_times_ns(*RAMP_S, RATE_HZ)
    t0, t1 = (round(x * NS_PER_S) for x in RAMP_S)
    tm = _hold_boundary_ns(hold)
    whole = hold_segments(t, t0, t1, hold)
    parts = [hold_segments(t, a, b, hold) for a, b in ((t0, tm), (tm, t1))]
    for i in range(2):
        np.testing.assert_array_equal(whole[i], np.concatenate([p[i] for p in parts]))


@pytest.mark.parametrize("hold", list(SampleHold))
def test_split_at_a_hold_boundary_composes_exactly(hold):
    assert max(_compose_vs_single(hold, _hold_boundary_ns(hold), MANIFOLD_PIM)) < COMPOSE_TOL
    # GTSAM's default tangent-space preintegration is only close (module docstring).
    assert max(_compose_vs_single(hold, _hold_boundary_ns(hold), DEFAULT_PIM)) < \
        TANGENT_COMPOSE_TOL


@pytest.mark.parametrize("hold", list(SampleHold))
def test_split_inside_a_hold_composes_to_gtsam_step_accuracy(hold):
    """Splitting one held sample changes GTSAM's arithmetic, not the model.

    Zero-order: v += R f d1; R' = R Exp(w d1); v += R' f d2 differs from v += R f (d1+d2)
    by |w x f| d1 d2 to first order. Midpoint: each part is its own midpoint step, a
    difference of third order (~|w|^2 |f| d^3), far below that.
    """
    t = _sample_times_ns(*RAMP_S, RATE_HZ)
    tm = _hold_boundary_ns(SampleHold.ZERO_ORDER) + 1_234_567  # inside a hold for both
    k = int(np.searchsorted(t, tm)) - 1
    d1, d2 = (tm - t[k]) / NS_PER_S, (t[k + 1] - tm) / NS_PER_S
    gyro, acc = ideal_imu(evaluate(PLAN, t[k:k + 1] / NS_PER_S), G_MPS2)
    step_gap = np.linalg.norm(np.cross(gyro[0], acc[0])) * d1 * d2
    assert step_gap > 1e-6  # the split has rotation to show
    _, vel, _ = _compose_vs_single(hold, tm, MANIFOLD_PIM)
    if hold is SampleHold.ZERO_ORDER:
        assert vel == pytest.approx(step_gap, rel=0.05)
    else:
        assert vel < 0.01 * step_gap


def _pim_state(pim):
    return np.r_[pim.deltaRij().matrix().ravel(), pim.deltaPij(), pim.deltaVij(),
                 pim.preintMeasCov().ravel(), pim.deltaTij()]


@pytest.mark.parametrize("hold", list(SampleHold))
def test_imu_stream_gives_the_interval_preintegration_exactly(seed, hold, rng):
    """Samples fed in random chunks, integrated as far as they fix the holds, give the
    same preintegration as the whole interval at once, also when they ran past the frame."""
    flight, _ = simulate_flight(SimulationSettings(frames=4, n_features=10, seed=seed))
    imu, t_frames = flight.imu, flight.frames.t_ns
    reference = ImuIntervals(flight.config, imu, hold)
    bias = gtsam.imuBias.ConstantBias(np.array([0.01, -0.02, 0.03]), np.array([1e-3, 0, -2e-3]))
    stream_intervals = ImuIntervals(flight.config, ImuSamples(imu.t_ns[:0], imu.gyro_radps[:0],
                                                              imu.acc_mps2[:0]), hold)
    stream = ImuStream(stream_intervals)
    sent = 0
    for k in range(len(t_frames) - 1):
        stream.start(int(t_frames[k]), bias)
        # live: chunks up to the next frame; the last interval also overshoots it
        end = int(np.searchsorted(imu.t_ns, t_frames[k + 1])) + (1 if k < 2 else 40)
        while sent < end:
            step = min(int(rng.integers(1, 30)), end - sent)
            stream_intervals.imu = ImuSamples(imu.t_ns[:sent + step], imu.gyro_radps[:sent + step],
                                              imu.acc_mps2[:sent + step])
            sent += step
            stream.advance()
        got = stream.finish(int(t_frames[k + 1]))
        want = reference.preintegrate(int(t_frames[k]), int(t_frames[k + 1]), bias)
        np.testing.assert_array_equal(_pim_state(got), _pim_state(want))


# --- one pass a run ---------------------------------------------------------------------


def test_a_run_shares_an_interval_integrated_alike_and_nothing_else(gap_flight):
    """Inside ``shared_preintegrations`` an interval integrated alike (another
    ``ImuIntervals`` of the same log) is the same object; a different bias, noise, hold or
    log, a gap interval, or the block's end each make a new one. Mutations: the bias left
    out of the key (the second bias gets the first one's object), the block not closed
    (the last assertion), gap intervals kept (the gap's object is shared)."""
    flight, gappy = gap_flight
    t0, t1 = 0, 1 * NS_PER_S
    zero = gtsam.imuBias.ConstantBias()
    other = gtsam.imuBias.ConstantBias(np.array([0.01, 0.0, 0.0]), np.zeros(3))
    louder = dataclasses.replace(flight.config, imu=dataclasses.replace(
        flight.config.imu, gyroscope_random_walk=10 * flight.config.imu.gyroscope_random_walk))

    def fresh(log=flight, config=None, hold=SampleHold.ZERO_ORDER):
        return ImuIntervals(config or log.config, log.imu, hold)

    with shared_preintegrations():
        first = fresh().preintegrate(t0, t1, zero)
        assert fresh().preintegrate(t0, t1, zero) is first
        with shared_preintegrations():  # nested: the outer block's
            assert fresh().preintegrate(t0, t1, zero) is first
        assert fresh().preintegrate(t0, t1, other) is not first
        assert fresh(config=louder).preintegrate(t0, t1, zero) is not first
        assert fresh(hold=SampleHold.MIDPOINT).preintegrate(t0, t1, zero) is not first
        assert fresh().preintegrate(t0, 2 * NS_PER_S, zero) is not first
        gap = fresh(gappy).preintegrate(NS_PER_S, 3 * NS_PER_S, zero)
        assert gap.spans_gap and fresh(gappy).preintegrate(NS_PER_S, 3 * NS_PER_S, zero) is not gap
        # the gappy log's samples differ only inside the gap: its first interval is shared
        assert fresh(gappy).preintegrate(t0, t1, zero) is first
    assert fresh().preintegrate(t0, t1, zero) is not first
    np.testing.assert_array_equal(_pim_state(fresh().preintegrate(t0, t1, zero)),
                                  _pim_state(first))


def test_a_batch_run_preintegrates_each_interval_twice_at_most(seed, monkeypatch):
    """The batch smoother's robust start streams the IMU once, and the graph, the
    calibration check's side graph and the dead reckoning share one more pass (issue 22:
    each was its own). Mutation: ``smooth`` without ``shared_preintegrations``: 4 passes."""
    import cdtm_graph.imu as imu_module
    from cdtm_graph.run import smooth_and_evaluate
    from cdtm_graph.smoother import SmootherSettings

    short, dtm = simulate_flight(SimulationSettings(frames=12, seed=seed))
    calls = []
    real = imu_module.integrate_interval
    monkeypatch.setattr(imu_module, "integrate_interval",
                        lambda *a, **k: calls.append(a[4:6]) or real(*a, **k))
    smooth_and_evaluate(short, dtm, SmootherSettings())
    integrated_ns = sum(int(t1) - int(t0) for t0, t1 in calls)  # (the stream's in pieces)
    span_ns = int(short.frames.t_ns[-1] - short.frames.t_ns[0])
    # 2.004x measured (the stream redoes an interval it ran past); unshared: 4.0x, and
    # 3x with the dead reckoning alone apart
    assert integrated_ns < 2.5 * span_ns


# --- gaps ------------------------------------------------------------------------------

#: The gap's variance density lands on the pieces between the two samples around it:
#: measured against GTSAM's preintegrated covariance to this relative tolerance (the
#: flight turns a little, so the rotation noise is not summed in exactly one frame).
GAP_COV_RTOL = 0.02


@pytest.fixture(scope="module")
def gap_flight(seed):
    """6 s at 1 fps (a straight leg and the roll into a turn) and the same with the IMU
    samples of [1.3 s, 2.3 s) missing: a spacing of 1.005 s from 1.295 s to 2.3 s."""
    flight, _ = simulate_flight(SimulationSettings(frames=7, n_features=10, seed=seed))
    return flight, with_imu_gap(flight, 1.3, 1.0)


@pytest.mark.parametrize("hold", list(SampleHold))
def test_a_gap_gets_the_maneuver_models_noise(gap_flight, hold):
    flight, gappy = gap_flight
    gap_s, gap_noise = 1.005, GapNoise()
    t0, t1 = 1 * NS_PER_S, 3 * NS_PER_S
    bias = gtsam.imuBias.ConstantBias()
    cov = {name: ImuIntervals(log.config, log.imu, hold, gap_noise=noise).preintegrate(
        t0, t1, bias).preintMeasCov()
        for name, log, noise in (("clean", flight, gap_noise), ("modelled", gappy, gap_noise),
                                 ("unmodelled", gappy, None))}
    q_acc, q_gyro = gap_noise.densities(gap_s)
    rotation = np.diag(cov["modelled"])[0:3] - np.diag(cov["clean"])[0:3]
    np.testing.assert_allclose(rotation, q_gyro * gap_s, rtol=GAP_COV_RTOL)
    # velocity along the start's body z (gravity's): the accelerometer's part alone
    vertical = cov["modelled"][8, 8] - cov["clean"][8, 8]
    assert vertical == pytest.approx(q_acc * gap_s, rel=GAP_COV_RTOL)
    # ... across it (x, y) the attitude's random walk turns g into velocity as well:
    # var(g int dtheta) = g^2 q (T^3/3 + T^2 r + T r^2), r the time after the gap (0.7 s);
    # GTSAM's 50 ms steps couple a step's own rotation noise one step late (-4%)
    rest = 0.7
    coupling = G_MPS2 ** 2 * q_gyro * (gap_s ** 3 / 3 + gap_s ** 2 * rest + gap_s * rest ** 2)
    horizontal = np.diag(cov["modelled"])[6:8] - np.diag(cov["clean"])[6:8]
    np.testing.assert_allclose(horizontal, q_acc * gap_s + coupling, rtol=0.05)
    # the sensor's noise alone claims to know the held motion as well as measured motion
    # (or better: one long GTSAM step couples less noise than many short ones)
    assert np.all(np.diag(cov["unmodelled"]) <= 1.01 * np.diag(cov["clean"]))


@pytest.mark.parametrize("hold", list(SampleHold))
def test_intervals_beside_a_gap_keep_the_sensors_noise(gap_flight, hold):
    """Before and after the gap the preintegration is exactly the gapless log's, also
    after a gap interval was integrated with the same (shared) parameters."""
    flight, gappy = gap_flight
    bias = gtsam.imuBias.ConstantBias()
    clean = ImuIntervals(flight.config, flight.imu, hold)
    faulty = ImuIntervals(gappy.config, gappy.imu, hold)
    faulty.preintegrate(1 * NS_PER_S, 3 * NS_PER_S, bias)  # the gap, first
    for t0, t1 in ((0, 1), (3, 4), (4, 5)):
        np.testing.assert_array_equal(
            _pim_state(faulty.preintegrate(t0 * NS_PER_S, t1 * NS_PER_S, bias)),
            _pim_state(clean.preintegrate(t0 * NS_PER_S, t1 * NS_PER_S, bias)))


def test_gap_noise_grows_with_the_gap_to_its_bounds():
    g = GapNoise(accel_mps2=2.0, rate_radps=0.1, onset_s=1.0)
    q_acc, q_gyro = g.densities(0.01)
    assert q_acc == pytest.approx((2.0 * 0.01) ** 2 * 0.01)
    assert q_gyro == pytest.approx((0.1 * 0.01) ** 2 * 0.01)
    q_acc, q_gyro = g.densities(5.0)  # past the onset: a bounded error held 5 s
    assert q_acc * 5.0 == pytest.approx((2.0 * 5.0) ** 2)
    assert q_gyro * 5.0 == pytest.approx((0.1 * 5.0) ** 2)
    with pytest.raises(ValueError):
        GapNoise(accel_mps2=0.0)
