"""The IMU in the estimator: noise, sample holds, preintegration as samples arrive, dead reckoning.

Measurement model (body frame, docs/flightlog.md units)::

    gyro_radps = omega_body + gyro_bias + n_g
    acc_mps2   = R^T (a_world + g e_z) + accel_bias + n_a     (specific force)

so an IMU at rest, level, reads +g on z. ``n_g``, ``n_a`` are discrete white noise with
sigma = density * sqrt(rate); the biases are random walks whose per-step sigma is
random_walk * sqrt(dt). GTSAM's ``imuBias.ConstantBias`` takes (accel, gyro) in that order.

How a sample relates to time (``SampleHold``). GTSAM's ``integrateMeasurement(acc,
gyro, dt)`` holds one measurement constant over ``dt`` and updates
``p += v dt + R_k a dt^2/2; v += R_k a dt; R_k+1 = R_k Exp(w dt)`` with the rotation at
the *start* of the step. ``integrate_interval`` covers exactly a frame interval
[t0, t1]: each sample gets a hold interval, the holds are cut at t0 and t1 (a sample
whose hold straddles a frame time is split, one part in each frame interval), and the
durations are integer ns, so consecutive intervals tile time exactly.

- ``SampleHold.ZERO_ORDER`` holds sample k over [t_k, t_k+1) and passes it to GTSAM
  unchanged. It is first order in dt, for two reasons: the hold lags the signal by
  dt/2 (attitude error ~ change of body rate * dt/2, ~2.5e-4 rad across a bank ramp at
  200 Hz), and GTSAM's start-of-step rotation integrates the world-frame specific
  force with another dt/2 lag (a velocity error of ~|w x f| dt/2 per second: 1.4e-3 m/s
  per s in a steady 3 deg/s turn at 200 m/s, ~2e-2 m/s per s while rolling into it).
- ``SampleHold.MIDPOINT`` treats samples as instantaneous values (what
  ``simulate_imu`` writes): sample k is held over the half-way points to its
  neighbours, and its bias-corrected specific force is rotated forward by half the
  piece's rotation, ``Exp((w - b_g) dt/2) (f - b_a) + b_a``, so GTSAM's start-of-step
  update integrates ``R(mid) f(mid)``. That is the midpoint rule: second order in dt,
  ~1e-4 m after 3 s through a bank ramp at 200 Hz. The tweak is exact at the
  preintegration's bias estimate; GTSAM's bias Jacobians ignore the half-step rotation,
  a relative error of |w| dt/2 (~2e-3 at 0.7 rad/s, 200 Hz) on a bias correction.

GTSAM 4.3's default ``PreintegratedCombinedMeasurements`` (the type ``CombinedImuFactor``
takes) behaves as tangent-space preintegration: rotation is integrated by Euler steps
in the tangent space of the preintegrated rotation, not as the exact product of
per-step exponentials (``PreintegratedCombinedMeasurementsManifold`` is exact). That adds
a small first-order rotation error (about a third of the MIDPOINT figure above) and makes
two consecutive preintegrations composed differ from one over the union by ~1e-6.
``integrate_interval`` works with either class. ``tests/core/test_imu.py`` measures all of
this against the analytic trajectory.

**The Earth** (a log with a geodetic ``origin:``; ``ImuIntervals(.., earth=True)``). The
world frame is then the ENU tangent plane at the origin, fixed to the rotating Earth, and
the IMU senses the Earth's rotation and WGS84 normal gravity, whose direction follows the
local vertical (0.45 deg off the world's -z at 50 km from the origin)::

    gyro_radps = omega_body + R^T Omega_world + gyro_bias + n_g
    acc_mps2   = R^T (a_world - g_world(p) + 2 Omega_world x v_world) + accel_bias + n_a

Each frame interval then gets its own GTSAM parameters (:class:`EarthImu`):
``omegaCoriolis`` the Earth rate in the world frame, and as ``n_gravity`` normal gravity at
the interval's midpoint as the start state predicts it (gravity turns by 1.6e-7 rad per
metre along the track, so a midpoint a few metres off changes nothing measurable; the
start point's gravity would: :class:`EarthImu`), corrected for the centrifugal term GTSAM
4.3 adds on its own (:meth:`~cdtm_graph.geodesy.ImuEnvironment.gtsam_n_gravity`). The
parameters are fixed when the interval is closed (:meth:`ImuIntervals.place`), from the
estimate of the interval's first state then. ``earth=False`` is the flat model above
(constant ``gravity_mps2`` along -z, no Earth rate), for comparisons: on a 50 km flight
it is hundreds of metres off where the Earth-aware model is not (docs/geodesy.md).

**Gaps** (:mod:`cdtm_graph.verdict.imu_faults`). Across consecutive samples more than a few
nominal periods apart the samples on either side are held as always, but nothing says
how the aircraft moved in between. The pieces those samples hold get the noise of a
maneuver model (:class:`GapNoise`), in steps of at most ``GAP_STEP_S`` so GTSAM's
covariance propagation carries the growing attitude uncertainty into velocity and
position: the factor's covariance stays honest where its mean is a guess.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from enum import Enum
from typing import NamedTuple, Protocol

import gtsam
import numpy as np

from cdtm_graph.constants import NS_PER_S
from cdtm_graph.errors import FlightLogError, SolverError
from cdtm_graph.flightlog import FlightConfig, InitialState
from cdtm_graph.geodesy import LocalFrame
from cdtm_graph.results import TrajectoryEstimate
from factors.jit import njit

#: A gap: consecutive samples more than this many nominal periods apart. One or two
#: dropped samples (2 or 3 periods) are routine on a busy bus and cost nothing measurable
#: (each neighbour is held a period longer); three or more are named and modelled.
IMU_GAP_PERIODS = 3.0


def gap_threshold_ns(rate_hz: float, gap_periods: float = IMU_GAP_PERIODS) -> int:
    """The largest spacing (ns) that is not a gap at a nominal rate."""
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    return int(gap_periods * NS_PER_S / rate_hz)


def gap_after(t_ns: np.ndarray, rate_hz: float,
              gap_periods: float = IMU_GAP_PERIODS) -> np.ndarray:
    """Which consecutive samples have a gap between them.

    Args:
        t_ns: (N,) sample times, ns.
        rate_hz: the nominal rate (flight.yaml ``imu.rate_hz``).
        gap_periods: the threshold in nominal periods.

    Returns:
        (N-1,) bool: ``t[i+1] - t[i]`` is a gap. The IMU model and :func:`check_imu` both
        use this, so what is named is what is modelled.
    """
    return np.diff(np.asarray(t_ns, dtype=np.int64)) > gap_threshold_ns(rate_hz, gap_periods)



PreintegratedCombined = (gtsam.PreintegratedCombinedMeasurements
                         | gtsam.PreintegratedCombinedMeasurementsManifold
                         | gtsam.PreintegratedCombinedMeasurementsLieGroup)

# Continuous-time covariance of GTSAM's velocity-to-position integration, m^2/s
# (GTSAM adds dt * this per step): ~1e-4 m after 1 s, far below any noise here.
INTEGRATION_COVARIANCE = 1e-8


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise densities, Kalibr names (flight.yaml ``imu:``).

    Attributes:
        gyroscope_noise_density: rad/s/sqrt(Hz).
        accelerometer_noise_density: m/s^2/sqrt(Hz).
        gyroscope_random_walk: gyro bias random walk, rad/s^2/sqrt(Hz).
        accelerometer_random_walk: accel bias random walk, m/s^3/sqrt(Hz).
    """

    gyroscope_noise_density: float = 1.7e-4
    accelerometer_noise_density: float = 2.0e-3
    gyroscope_random_walk: float = 1.9e-5
    accelerometer_random_walk: float = 3.0e-3

    def __post_init__(self) -> None:
        for name in ("gyroscope_noise_density", "accelerometer_noise_density",
                     "gyroscope_random_walk", "accelerometer_random_walk"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")


class SampleHold(Enum):
    """How an IMU sample stands for time in ``integrate_interval`` (module docstring)."""

    ZERO_ORDER = "zero_order"  # sample k over [t_k, t_k+1), given to GTSAM as is
    MIDPOINT = "midpoint"      # sample k over the half-way points; half-step rotation


#: Gap pieces are integrated in steps of at most this long (s): GTSAM propagates the
#: covariance per step, and only across steps does attitude uncertainty built up inside a
#: gap reach velocity and position (``|f| sigma_theta`` per second).
GAP_STEP_S = 0.05


@dataclass(frozen=True)
class GapNoise:
    """What an IMU gap may hide: how far the true motion may stray from the held samples.

    A maneuver model. Across a gap of ``T`` seconds the true specific force and angular
    rate differ from the samples held there by an unknown amount that builds up over a
    maneuver's onset and is then bounded: ``sigma(T) = max * min(T / onset_s, 1)`` for
    each. Taken as constant over the gap, such an error gives a velocity error of
    ``sigma T`` and an attitude error of ``sigma_rate T``; white noise of density
    ``q^2 = sigma(T)^2 T`` over the gap's pieces gives the same variance at the gap's
    end (and a little more in position: ``T^4/3`` against ``T^4/4``), which is what the
    pieces get on top of the sensor's own noise.

    The defaults are a transport or survey aircraft's maneuvers: a coordinated turn at 30
    deg of bank changes the specific force by g (1/cos 30 - 1) = 1.5 m/s^2, throttle and
    pitch changes by under 1 m/s^2, so 2 m/s^2; a bank ramp rolls at 10-15 deg/s for 2 s
    and a rate-one turn is 3 deg/s, so an attitude that may be 25 deg off after a 5 s gap
    (5 deg/s): the simulated flights roll 22 deg into their turns in 2 s. Onset 1 s: a
    roll or a pull-up takes about that long to develop, so a gap of a few samples costs
    little (10 ms: 0.02 m/s^2 and 0.05 deg/s, comparable to the sensor noise).

    Attributes:
        accel_mps2: bound of the specific-force error, m/s^2.
        rate_radps: bound of the angular-rate error, rad/s.
        onset_s: time over which the errors reach their bounds, s.
    """

    accel_mps2: float = 2.0
    rate_radps: float = math.radians(5.0)
    onset_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("accel_mps2", "rate_radps", "onset_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"GapNoise.{name} must be finite and > 0, got {value}")

    def densities(self, gap_s: float) -> tuple[float, float]:
        """Continuous-time variance densities (accelerometer (m/s^2)^2 s, gyroscope
        (rad/s)^2 s) for the pieces of a gap of ``gap_s`` seconds."""
        scale = min(gap_s / self.onset_s, 1.0)
        return ((self.accel_mps2 * scale) ** 2 * gap_s, (self.rate_radps * scale) ** 2 * gap_s)


def preintegration_params(noise: ImuNoise, gravity_mps2: float,
                          rate_hz: float | None = None) -> gtsam.PreintegrationCombinedParams:
    """GTSAM combined-preintegration parameters from continuous-time noise densities.

    GTSAM takes continuous-time covariances: each ``integrateMeasurement(.., dt)`` uses
    ``accelerometerCovariance / dt`` (gyro likewise) as the covariance of that step's
    held measurement and adds ``dt * biasAccCovariance`` (omega likewise) for the bias
    random walk (CombinedImuFactor.cpp; ``tests/core/test_imu.py`` checks that 1 s of
    preintegration gives density^2 * 1 s at 100 Hz and at 400 Hz). So the densities are
    squared and passed as they are; the sample rate is not needed, and ``rate_hz`` is
    only checked, for callers that have it at hand. Every covariance is set because
    4.3's ``MakeSharedU`` defaults them all to identity. 4.3 has no ``biasAccOmegaInt``
    (neither in the Python API nor in the library).

    Args:
        noise: continuous-time densities (Kalibr names).
        gravity_mps2: gravity magnitude; ``MakeSharedU``: gravity along -z (ENU).
        rate_hz: optional IMU rate, Hz; must be > 0 when given; does not change the result.

    Returns:
        Params with gyro/accel covariance density^2 I, bias random-walk covariance
        rw^2 I and integration covariance ``INTEGRATION_COVARIANCE`` I.
    """
    if rate_hz is not None and not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(gravity_mps2)
    eye = np.eye(3)
    params.setGyroscopeCovariance(noise.gyroscope_noise_density ** 2 * eye)
    params.setAccelerometerCovariance(noise.accelerometer_noise_density ** 2 * eye)
    params.setBiasOmegaCovariance(noise.gyroscope_random_walk ** 2 * eye)
    params.setBiasAccCovariance(noise.accelerometer_random_walk ** 2 * eye)
    # Velocity-to-position integration is exact in GTSAM's model; a tiny value keeps
    # the position block positive definite even with zero accelerometer noise.
    params.setIntegrationCovariance(INTEGRATION_COVARIANCE * eye)
    return params


def hold_segments(t_ns_samples: np.ndarray, t0_ns: int, t1_ns: int,
                  hold: SampleHold = SampleHold.ZERO_ORDER) -> tuple[np.ndarray, np.ndarray]:
    """Which sample is held over which part of [t0, t1], in integer nanoseconds.

    Args:
        t_ns_samples: (N,) int sample times, strictly increasing, N >= 2.
        t0_ns: interval start, ns.
        t1_ns: interval end, ns, > t0_ns.
        hold: hold interval of each sample (``SampleHold``). The first sample is never
            held before its own time nor the last after its own, so the samples cover
            exactly [t_ns_samples[0], t_ns_samples[-1]].

    Returns:
        sample_index (M,) int: index of the sample held over each piece, in time order.
        dt_ns (M,) int64: piece durations, all > 0; they sum to ``t1_ns - t0_ns`` exactly.

    Raises:
        ValueError: if the samples do not cover [t0, t1] or the inputs are malformed.
    """
    t = np.asarray(t_ns_samples)
    if t.ndim != 1 or not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"t_ns_samples must be a 1-D integer array of ns, got {t.dtype} {t.shape}")
    n = t.shape[0]
    t0, t1 = int(t0_ns), int(t1_ns)
    if n < 2:
        raise ValueError("need at least two IMU samples")
    if t1 <= t0:
        raise ValueError(f"empty interval: t1_ns={t1} <= t0_ns={t0}")
    if t0 < t[0] or t1 > t[-1]:
        raise ValueError(f"IMU samples span [{t[0]}, {t[-1]}] ns, which does not cover "
                         f"the interval [{t0}, {t1}] ns")
    if not isinstance(hold, SampleHold):
        raise ValueError(f"unknown hold {hold!r}")
    a, b = _near(t, t0, t1)
    index, dt_ns, increasing = _hold_segments(
        np.ascontiguousarray(t[a:b], dtype=np.int64), t0, t1, hold is SampleHold.MIDPOINT)
    if not increasing:
        raise ValueError("t_ns_samples must be strictly increasing")
    return index + a, dt_ns


def _near(t: np.ndarray, t0: int, t1: int) -> tuple[int, int]:
    """The slice of samples near [t0, t1], so a per-frame call on a long log costs
    O(samples in the interval). Two extra samples on each side: the holds of the
    outermost ones end before t0 / start after t1 in either mode."""
    return (max(int(np.searchsorted(t, t0, side="right")) - 2, 0),
            min(int(np.searchsorted(t, t1, side="left")) + 2, t.shape[0]))


def _hold_segments(ts: np.ndarray, t0: int, t1: int, midpoint: bool
                   ) -> tuple[np.ndarray, np.ndarray, bool]:
    """Pieces of [t0, t1] held by each of the samples ``ts`` (local indices), and whether
    ``ts`` is strictly increasing. ZERO_ORDER: sample j holds [ts[j], ts[j+1]); MIDPOINT:
    from the integer half-way point to its previous neighbour to the one to its next (the
    first from its own time, the last to its own time), so the pieces telescope exactly.
    (numpy, integers only: a few whole-array operations, not worth a kernel's compilation.)
    """
    if (ts[1:] <= ts[:-1]).any():
        return ts[:0], ts[:0], False
    if midpoint:
        halfway = ts[:-1] + (ts[1:] - ts[:-1]) // 2
        lo, hi = np.concatenate((ts[:1], halfway)), np.concatenate((halfway, ts[-1:]))
    else:
        lo, hi = ts[:-1], ts[1:]
    start, end = np.maximum(lo, t0), np.minimum(hi, t1)
    index = np.flatnonzero(end > start)
    return index, (end - start)[index], True


def _interval_measurements(t: np.ndarray, gyro: np.ndarray, acc: np.ndarray, t0: int,
                           t1: int, midpoint: bool, b_a: np.ndarray, b_g: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """``hold_segments`` then ``_held_measurements`` for a covered interval (the samples
    near it); ``ok`` is False if they are not strictly increasing."""
    index, dt_ns, increasing = _hold_segments(t, t0, t1, midpoint)
    f, w, dt_s = _held_measurements(gyro, acc, index, dt_ns, midpoint, b_a, b_g)
    return f, w, dt_s, increasing

@njit(cache=True)
def _held_measurements(gyro, acc, index, dt_ns, midpoint, b_a, b_g):
    """What GTSAM integrates per piece: ``(acc (M, 3), gyro (M, 3), dt_s (M,))``; with
    the midpoint hold, the bias-corrected specific force turned forward by half the
    piece's rotation, ``Exp((w - b_g) dt/2) (f - b_a) + b_a`` (module docstring)."""
    m = index.shape[0]
    f_out = np.empty((m, 3))
    w_out = np.empty((m, 3))
    dt_s = np.empty(m)
    for k in range(m):
        i = index[k]
        dt = dt_ns[k] / NS_PER_S
        dt_s[k] = dt
        for c in range(3):
            w_out[k, c] = gyro[i, c]
            f_out[k, c] = acc[i, c]
        if not midpoint:
            continue
        # Rodrigues: Exp(phi) x = x + a (phi x x) + b phi x (phi x x)
        p0 = (gyro[i, 0] - b_g[0]) * 0.5 * dt
        p1 = (gyro[i, 1] - b_g[1]) * 0.5 * dt
        p2 = (gyro[i, 2] - b_g[2]) * 0.5 * dt
        x0, x1, x2 = acc[i, 0] - b_a[0], acc[i, 1] - b_a[1], acc[i, 2] - b_a[2]
        th2 = p0 * p0 + p1 * p1 + p2 * p2
        th = np.sqrt(th2)
        if th < 1e-8:
            a, b = 1.0, 0.5
        else:
            a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th2
        c0, c1, c2 = p1 * x2 - p2 * x1, p2 * x0 - p0 * x2, p0 * x1 - p1 * x0
        d0, d1, d2 = p1 * c2 - p2 * c1, p2 * c0 - p0 * c2, p0 * c1 - p1 * c0
        f_out[k, 0] = x0 + a * c0 + b * d0 + b_a[0]
        f_out[k, 1] = x1 + a * c1 + b * d1 + b_a[1]
        f_out[k, 2] = x2 + a * c2 + b * d2 + b_a[2]
    return f_out, w_out, dt_s


def integrate_interval(pim: PreintegratedCombined, t_ns_samples: np.ndarray,
                       gyro: np.ndarray, acc: np.ndarray, t0_ns: int, t1_ns: int,
                       hold: SampleHold = SampleHold.ZERO_ORDER) -> None:
    """Add IMU measurements covering exactly [t0, t1] to a preintegration.

    Each sample is held constant over its hold interval (by default from its time to
    the next sample's, the zero-order hold), cut at t0 and t1: a sample whose hold
    straddles a frame time is split, one part in each frame interval. Durations are
    integer ns (``hold_segments``), so consecutive intervals tile time exactly and
    integrating [t0, tm] then [tm, t1] feeds GTSAM the same pieces as [t0, t1] whenever
    tm is a hold boundary. Accuracy of the two holds: module docstring.

    Args:
        pim: preintegration to add to (in place), any of the combined classes.
            ``SampleHold.MIDPOINT`` uses its bias estimate ``biasHat()``.
        t_ns_samples: (N,) int sample times, ns, strictly increasing.
        gyro: (N, 3) measured angular rate, rad/s, body.
        acc: (N, 3) measured specific force, m/s^2, body.
        t0_ns: interval start, ns.
        t1_ns: interval end, ns, > t0_ns.
        hold: which time interval a sample stands for.

    Raises:
        ValueError: if the samples do not cover [t0, t1] or shapes disagree.
    """
    t = np.asarray(t_ns_samples)
    gyro = np.asarray(gyro, dtype=float)
    acc = np.asarray(acc, dtype=float)
    if t.ndim != 1 or gyro.shape != (t.shape[0], 3) or acc.shape != (t.shape[0], 3):
        raise ValueError(f"gyro {gyro.shape} and acc {acc.shape} must be (N, 3) for "
                         f"t_ns_samples {t.shape}")
    midpoint = hold is SampleHold.MIDPOINT
    if midpoint:
        # GTSAM rotates the step's specific force with the rotation at the step's start;
        # pre-rotating by half the step makes that the rotation at its middle.
        bias = pim.biasHatVector()  # (accelerometer, gyroscope)
        b_a, b_g = np.ascontiguousarray(bias[:3]), np.ascontiguousarray(bias[3:])
    else:
        b_a = b_g = np.zeros(3)
    if np.issubdtype(t.dtype, np.integer) and t.shape[0] >= 2 and int(t1_ns) > int(t0_ns) \
            and t[0] <= t0_ns and t1_ns <= t[-1] and isinstance(hold, SampleHold):
        # the usual case; hold_segments explains what is wrong otherwise
        lo, hi = _near(t, int(t0_ns), int(t1_ns))
        f, w, dt_s, ok = _interval_measurements(
            np.ascontiguousarray(t[lo:hi], dtype=np.int64), gyro[lo:hi], acc[lo:hi],
            int(t0_ns), int(t1_ns), midpoint, b_a, b_g)
    else:
        ok = False
    if not ok:
        index, dt_ns = hold_segments(t, t0_ns, t1_ns, hold)
        f, w, dt_s = _held_measurements(gyro, acc, index, dt_ns, midpoint, b_a, b_g)
    integrate = pim.integrateMeasurement
    for f_k, w_k, dt_k in zip(list(f), list(w), dt_s.tolist()):
        integrate(f_k, w_k, dt_k)


def imu_noise(config: FlightConfig) -> ImuNoise:
    """The log's continuous-time noise densities (flight.yaml ``imu:``)."""
    imu = config.imu
    return ImuNoise(imu.gyroscope_noise_density, imu.accelerometer_noise_density,
                    imu.gyroscope_random_walk, imu.accelerometer_random_walk)


def initial_bias(initial: InitialState) -> gtsam.imuBias.ConstantBias:
    """The prior mean of the biases, as GTSAM's (accel, gyro) bias."""
    return gtsam.imuBias.ConstantBias(np.asarray(initial.accel_bias, dtype=float),
                                      np.asarray(initial.gyro_bias, dtype=float))


class ImuArrays(Protocol):
    """IMU samples as arrays (``ImuSamples`` or any object with its three fields)."""

    @property
    def t_ns(self) -> np.ndarray: ...

    @property
    def gyro_radps(self) -> np.ndarray: ...

    @property
    def acc_mps2(self) -> np.ndarray: ...


class Preintegration(gtsam.PreintegratedCombinedMeasurements):
    """A frame interval's preintegration with the parameters it was made with.

    GTSAM's Python API does not hand a preintegration's parameters back, and the Earth
    model sets each interval's gravity when the interval is closed, the gap model its
    noise while it integrates: both need them. A ``CombinedImuFactor`` made from it
    shares them (GTSAM keeps a shared pointer), so they are never changed once a factor
    exists.

    Attributes:
        interval_params: the parameters GTSAM reads while integrating and predicting.
        spans_gap: some of it was held across an IMU gap (:class:`GapNoise`): its mean is
            a guess, and a prediction through it a poor linearization point.
    """

    def __init__(self, params: gtsam.PreintegrationCombinedParams,
                 bias: gtsam.imuBias.ConstantBias):
        super().__init__(params, bias)
        self.interval_params = params
        self.spans_gap = False


class EarthImu:
    """The rotating, curved Earth under a geodetic log's IMU: per-interval GTSAM parameters.

    Every interval gets parameters of its own (``omegaCoriolis`` the Earth rate in the
    world frame) whose ``n_gravity`` :meth:`place` sets from the interval's start state:
    normal gravity at the interval's midpoint, corrected for GTSAM's own centrifugal term
    (module docstring).

    The midpoint is ``p + v T / 2`` from the start state. Dead reckoning a noiseless
    50 km, 200 s geodetic flight (``scripts/earth_imu_error.py``) ends 0.477 m off with
    it, 0.478 m with GTSAM's predicted midpoint instead (and 0.486 m on the same flight in
    a flat world: the samples' hold, not the Earth), 3.3 m with gravity at the start
    position, 4.7 m with gravity 141 m from the midpoint: a few metres of midpoint error
    do not matter, a start-point gravity does.
    """

    def __init__(self, frame: LocalFrame, noise: ImuNoise, gravity_mps2: float):
        self.frame = frame
        self.noise = noise
        self.gravity_mps2 = gravity_mps2
        self.earth_rate_radps = frame.earth_rate_world_radps

    def params(self) -> gtsam.PreintegrationCombinedParams:
        """Fresh parameters for one interval (gravity still the flat placeholder)."""
        params = preintegration_params(self.noise, self.gravity_mps2)
        params.setOmegaCoriolis(self.earth_rate_radps)
        return params

    def place(self, pim: Preintegration, world_T_body: np.ndarray,
              velocity_mps: np.ndarray) -> None:
        """Set the interval's gravity from its start state (after integrating it).

        Args:
            pim: the interval's preintegration (its ``interval_params`` change).
            world_T_body: (4, 4) the start state's pose. velocity_mps: (3,) its velocity.
        """
        start = np.asarray(world_T_body, dtype=float)[:3, 3]
        midpoint = start + 0.5 * pim.deltaTij() * np.asarray(velocity_mps, dtype=float)
        pim.interval_params.n_gravity = self.frame.imu_environment(midpoint).gtsam_n_gravity(
            start)


#: The preintegrations :func:`shared_preintegrations` keeps (None: outside it).
_SHARED: contextvars.ContextVar[dict[tuple, Preintegration] | None] = contextvars.ContextVar(
    "shared_preintegrations", default=None)


@contextlib.contextmanager
def shared_preintegrations() -> Iterator[None]:
    """Within the block, each frame interval is preintegrated once (:meth:`ImuIntervals.
    preintegrate`).

    A run builds the same flight's IMU factors more than once (the graph, the calibration
    check's side graph, the dead reckoning it is compared with), each a ~5 us GTSAM call
    per sample. A preintegration is not changed once made (the flat model: the Earth
    model places each one, and is never shared), and a factor copies it, so one object
    serves them all. Kept for the block only (nested blocks share the outer one's).
    """
    if _SHARED.get() is not None:
        yield
        return
    token = _SHARED.set({})
    try:
        yield
    finally:
        _SHARED.reset(token)


class ImuIntervals:
    """Preintegrates the IMU over frame intervals of one flight.

    Args:
        config: flight.yaml (IMU noise and rate, gravity, origin).
        imu: the samples (``imu`` may be replaced as more arrive: ``ImuFeed``).
        hold: how a sample stands for time.
        earth: with a geodetic origin, the Earth-aware model (module docstring);
            False, or no origin: the flat model.
        gap_noise: the maneuver model of IMU gaps; None integrates gaps with the sensor's
            noise only (the old, overconfident behaviour, for comparisons).
    """

    def __init__(self, config: FlightConfig, imu: ImuArrays, hold: SampleHold,
                 earth: bool = True, gap_noise: GapNoise | None = GapNoise()):
        noise = imu_noise(config)
        self.params = preintegration_params(noise, config.gravity_mps2, config.imu.rate_hz)
        self._params_key = (noise, float(config.gravity_mps2), float(config.imu.rate_hz))
        self.imu = imu
        self.hold = hold
        frame = config.local_frame if earth else None
        self.earth = (EarthImu(frame, noise, config.gravity_mps2) if frame is not None
                      else None)
        self.rate_hz = config.imu.rate_hz
        self.gap_noise = gap_noise

    def new_preintegration(self, bias: gtsam.imuBias.ConstantBias) -> Preintegration:
        """An empty preintegration linearized at ``bias``: the shared parameters (flat
        model), or the interval's own (Earth)."""
        return Preintegration(self.params if self.earth is None else self.earth.params(), bias)

    def preintegrate(self, t0_ns: int, t1_ns: int, bias: gtsam.imuBias.ConstantBias,
                     start: tuple[np.ndarray, np.ndarray] | None = None) -> Preintegration:
        """IMU over exactly [t0, t1], linearized at ``bias``, placed (:meth:`place`).

        Inside :func:`shared_preintegrations`, an interval already integrated alike (same
        samples, parameters, hold and bias; flat model, no gap) is handed back as it was.

        Args:
            start: ``(world_T_body (4, 4), velocity_mps (3,))`` at t0: where the interval
                is on the Earth; needed by the Earth model (ignored by the flat one).

        Raises:
            SolverError: the samples do not cover the interval.
            ValueError: Earth model without ``start``.
        """
        memo = _SHARED.get()
        key = None if memo is None else self._shared_key(int(t0_ns), int(t1_ns), bias)
        if memo is not None and key in memo:
            return memo[key]
        pim = self.new_preintegration(bias)
        self.integrate(pim, t0_ns, t1_ns)
        self.place(pim, start)
        if memo is not None and key is not None and not pim.spans_gap:
            memo[key] = pim
        return pim

    def _shared_key(self, t0_ns: int, t1_ns: int,
                    bias: gtsam.imuBias.ConstantBias) -> tuple | None:
        """What makes an interval's preintegration what it is (None: never shared: the
        Earth model places each interval from a start state)."""
        if self.earth is not None:
            return None
        t = np.asarray(self.imu.t_ns)
        if t.ndim != 1 or t.shape[0] < 2:
            return None
        lo, hi = _near(t, t0_ns, t1_ns)
        lo, hi = max(lo - 1, 0), min(hi + 1, t.shape[0])  # the gap test's samples too
        samples = hashlib.blake2b(digest_size=16)
        for array in (t, self.imu.gyro_radps, self.imu.acc_mps2):
            samples.update(np.ascontiguousarray(np.asarray(array)[lo:hi]).tobytes())
        return (t0_ns, t1_ns, samples.digest(), bias.vector().tobytes(), self._params_key,
                self.hold, self.gap_noise)

    def place(self, pim: Preintegration, start: tuple[np.ndarray, np.ndarray] | None) -> None:
        """Fix an integrated interval's gravity from its start state (Earth model; the
        flat model has one gravity for all intervals and ignores ``start``).

        Raises:
            ValueError: Earth model without ``start``.
        """
        if self.earth is None:
            return
        if start is None:
            raise ValueError("an Earth-aware IMU interval needs its start state "
                             "(world_T_body, velocity_mps) to place its gravity")
        self.earth.place(pim, *start)

    def integrate(self, pim: gtsam.PreintegratedCombinedMeasurements, t0_ns: int,
                  t1_ns: int) -> None:
        """Add the IMU over exactly [t0, t1] to ``pim``. Stopping and resuming on a hold
        boundary (:meth:`hold_boundary_before`) feeds GTSAM the same pieces as one call.
        Pieces held across a gap get the gap's noise (:class:`GapNoise`): ``pim`` must
        then come from :meth:`new_preintegration`.

        Raises:
            SolverError: the samples do not cover the interval.
        """
        t0_ns, t1_ns = int(t0_ns), int(t1_ns)
        try:  # (it works on the samples near the interval only)
            gaps = self._gaps_near(t0_ns, t1_ns) if self.gap_noise is not None else None
            if gaps is None:
                integrate_interval(pim, self.imu.t_ns, self.imu.gyro_radps, self.imu.acc_mps2,
                                   t0_ns, t1_ns, self.hold)
            else:
                self._integrate_across_gaps(pim, t0_ns, t1_ns, gaps)
        except ValueError as exc:
            raise SolverError(f"imu.csv does not cover the frame interval "
                              f"[{t0_ns}, {t1_ns}] ns: {exc}") from None

    def _gaps_near(self, t0_ns: int, t1_ns: int) -> np.ndarray | None:
        """(N,) the gap (s) after each sample, 0 for none; None when no sample near
        [t0, t1] borders a gap (the usual case: nothing to do)."""
        t = np.asarray(self.imu.t_ns)
        if t.ndim != 1 or t.shape[0] < 2:
            return None
        lo, hi = _near(t, t0_ns, t1_ns)
        lo, hi = max(lo - 1, 0), min(hi + 1, t.shape[0])
        gap = gap_after(t[lo:hi], self.rate_hz)
        if not gap.any():
            return None
        after_s = np.zeros(t.shape[0])
        after_s[lo:hi - 1] = np.where(gap, np.diff(t[lo:hi]) / NS_PER_S, 0.0)
        return after_s

    def _integrate_across_gaps(self, pim: gtsam.PreintegratedCombinedMeasurements,
                               t0_ns: int, t1_ns: int, after_s: np.ndarray) -> None:
        """Like ``integrate_interval``, with the pieces that lie inside a gap (between
        the two samples around it: a hold piece is cut at its sample's time) integrated
        in steps of at most ``GAP_STEP_S`` under the gap's noise."""
        if not isinstance(pim, Preintegration):
            raise ValueError("an interval with an IMU gap needs a preintegration made by "
                             "ImuIntervals.new_preintegration (its noise changes per piece)")
        assert self.gap_noise is not None
        t = np.asarray(self.imu.t_ns, dtype=np.int64)
        index, dt_ns = hold_segments(t, t0_ns, t1_ns, self.hold)
        pieces: list[tuple[int, int, float]] = []  # (sample, duration ns, gap s)
        begin = t0_ns
        for j, d in zip(index.tolist(), dt_ns.tolist()):
            t_j, end = int(t[j]), begin + d
            before_s, next_s = (float(after_s[j - 1]) if j > 0 else 0.0), float(after_s[j])
            if begin < t_j < end and before_s != next_s:  # a midpoint hold by a gap: the
                pieces += [(j, t_j - begin, before_s), (j, end - t_j, next_s)]  # two sides
            else:
                pieces.append((j, d, next_s if begin >= t_j else before_s))
            begin = end
        index = np.array([p[0] for p in pieces], dtype=np.int64)
        dt_ns = np.array([p[1] for p in pieces], dtype=np.int64)
        piece_gap = np.array([p[2] for p in pieces])
        steps = np.where(piece_gap > 0,
                         np.ceil(dt_ns / (GAP_STEP_S * NS_PER_S)).astype(np.int64), 1)
        index, dt_ns = np.repeat(index, steps), _split_ns(dt_ns, steps)
        piece_gap = np.repeat(piece_gap, steps)
        midpoint = self.hold is SampleHold.MIDPOINT
        bias = pim.biasHatVector()  # (accelerometer, gyroscope)
        b_a, b_g = ((np.ascontiguousarray(bias[:3]), np.ascontiguousarray(bias[3:]))
                    if midpoint else (np.zeros(3), np.zeros(3)))
        f, w, dt_s = _held_measurements(np.asarray(self.imu.gyro_radps, dtype=float),
                                        np.asarray(self.imu.acc_mps2, dtype=float),
                                        index, dt_ns, midpoint, b_a, b_g)
        params = pim.interval_params
        # copies: the getters return views of GTSAM's matrices, which the setters change
        acc_cov = np.array(params.getAccelerometerCovariance(), copy=True)
        gyro_cov = np.array(params.getGyroscopeCovariance(), copy=True)
        eye = np.eye(3)
        try:
            for a, b in _equal_runs(piece_gap):
                q_acc, q_gyro = (self.gap_noise.densities(float(piece_gap[a]))
                                 if piece_gap[a] > 0 else (0.0, 0.0))
                params.setAccelerometerCovariance(acc_cov + q_acc * eye)
                params.setGyroscopeCovariance(gyro_cov + q_gyro * eye)
                for k in range(a, b):
                    pim.integrateMeasurement(f[k], w[k], float(dt_s[k]))
            pim.spans_gap = pim.spans_gap or bool(np.any(piece_gap > 0))
        finally:
            params.setAccelerometerCovariance(acc_cov)
            params.setGyroscopeCovariance(gyro_cov)

    def hold_boundary_before(self, limit_ns: int) -> int | None:
        """The latest hold boundary at or before ``limit_ns`` up to which the samples held
        fix every hold piece (the newest sample's own hold needs the sample after it);
        ``None`` if there is none."""
        t = self.imu.t_ns
        n = t.shape[0]
        j = int(np.searchsorted(t, limit_ns, side="right")) - 1  # t[j] <= limit
        if n < 2 or j < 0:
            return None
        if self.hold is SampleHold.ZERO_ORDER:
            return int(t[j])
        # MIDPOINT: boundaries are the integer half-way points between neighbours
        if j + 1 <= n - 1 and t[j] + (t[j + 1] - t[j]) // 2 <= limit_ns:
            return int(t[j] + (t[j + 1] - t[j]) // 2)
        return int(t[j - 1] + (t[j] - t[j - 1]) // 2) if j >= 1 else None


def _split_ns(dt_ns: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Each duration cut into ``steps`` integer-ns parts that sum to it exactly."""
    out = np.repeat(dt_ns // steps, steps)
    remainder = np.repeat(dt_ns % steps, steps)
    rank = np.arange(out.size) - np.repeat(np.cumsum(steps) - steps, steps)
    return out + (rank < remainder)


def _equal_runs(values: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of equal consecutive values."""
    cuts = np.flatnonzero(values[1:] != values[:-1]) + 1
    edges = np.r_[0, cuts, values.size]
    return list(zip(edges[:-1].tolist(), edges[1:].tolist()))


class ImuStream:
    """The preintegration after the newest frame, advanced as IMU samples arrive.

    A live system receives ~100 IMU samples between two frames at 2 fps. Each hold
    piece can be integrated once the sample after it is known, which leaves the frame
    update one or two pieces. Integration only ever stops on hold boundaries, so the
    result is exactly :meth:`ImuIntervals.preintegrate` over the frame interval. If
    samples ran past the next frame time before that frame arrived (camera latency),
    :meth:`finish` redoes the interval from the samples, and from then on the stream
    holds back by that lead so it does not happen again.
    """

    def __init__(self, intervals: ImuIntervals):
        self.intervals = intervals
        self._pim: Preintegration | None = None
        self._bias = gtsam.imuBias.ConstantBias()
        self._t0_ns = self._done_ns = 0
        self.holdback_ns = 0  # how far the IMU has been seen to run ahead of a frame

    @property
    def done_ns(self) -> int:
        """How far the current interval is integrated (ns)."""
        return self._done_ns

    def start(self, t0_ns: int, bias: gtsam.imuBias.ConstantBias) -> None:
        """Begin the interval after a frame at ``t0_ns``, linearized at ``bias``."""
        self._pim = self.intervals.new_preintegration(bias)
        self._bias = bias
        self._t0_ns = self._done_ns = int(t0_ns)

    def advance(self) -> None:
        """Integrate every piece the samples held so far fix (less the hold-back)."""
        t = self.intervals.imu.t_ns
        if self._pim is None or t.shape[0] < 2 or t[0] > self._done_ns:
            return  # nothing to do yet, or a gap that finish() will report
        horizon = self.intervals.hold_boundary_before(int(t[-1]) - self.holdback_ns)
        if horizon is not None and horizon > self._done_ns:
            self.intervals.integrate(self._pim, self._done_ns, horizon)
            self._done_ns = horizon

    def finish(self, t1_ns: int, start: tuple[np.ndarray, np.ndarray] | None = None
               ) -> Preintegration:
        """The preintegration over [t0, t1], t1 the next frame's time, placed from
        ``start`` (``ImuIntervals.place``: the state at t0, needed by the Earth model).
        The stream is spent on success only: after an error (samples missing), feed them
        and retry.

        Raises:
            SolverError: the samples do not cover the interval.
        """
        if self._pim is None:
            raise ValueError("ImuStream.finish before start")
        t1_ns = int(t1_ns)
        if self._done_ns > t1_ns:  # integrated past the frame: redo the interval
            pim = self.intervals.preintegrate(self._t0_ns, t1_ns, self._bias, start)
            self.holdback_ns = max(self.holdback_ns, int(self.intervals.imu.t_ns[-1]) - t1_ns)
        else:
            pim = self._pim
            if t1_ns > self._done_ns:  # checks everything before it integrates
                self.intervals.integrate(pim, self._done_ns, t1_ns)
            self.intervals.place(pim, start)
        self._pim = None
        return pim


class _HeldSamples(NamedTuple):
    """IMU samples already checked (the fields of ``ImuSamples``, without re-validation)."""

    t_ns: np.ndarray
    gyro_radps: np.ndarray
    acc_mps2: np.ndarray


class ImuFeed:
    """IMU samples as a live system receives them: held, preintegrated ahead, closed per frame.

    Samples come in with :meth:`add` (integrated at once as far as they fix the hold
    pieces) or :meth:`hold` (kept, not yet integrated: samples that come with a frame
    may run past it). :meth:`start` opens the interval after a frame, :meth:`finish`
    closes it at the next frame (``ImuStream``). Samples before the newest frame are
    dropped as new ones arrive (two kept for the holds), so a live feed does not grow.

    Args:
        config, hold, earth, gap_noise: as :class:`ImuIntervals`.
        imu: samples known up front (a log), or None (fed with :meth:`add`).

    Attributes:
        time_s: time spent preintegrating (``add`` only) since :meth:`take_time_s`.
    """

    def __init__(self, config: FlightConfig, hold: SampleHold, imu: ImuArrays | None = None,
                 earth: bool = True, gap_noise: GapNoise | None = GapNoise()):
        empty = _HeldSamples(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
        self.intervals = ImuIntervals(config, imu if imu is not None else empty, hold, earth,
                                      gap_noise)
        self.stream = ImuStream(self.intervals)
        self.given_up_front = imu is not None and len(imu.t_ns) > 0
        self._frame_ns: int | None = None  # the newest frame's time
        self.time_s = 0.0

    @property
    def samples(self) -> ImuArrays:
        return self.intervals.imu

    def add(self, imu: ImuArrays) -> None:
        """Append samples (after the ones held) and preintegrate what they fix.

        Raises:
            FlightLogError: the samples do not come after the ones already held.
        """
        start = time.perf_counter()
        self.hold(imu)
        self.stream.advance()
        self.time_s += time.perf_counter() - start

    def hold(self, imu: ImuArrays) -> None:
        """Append samples without integrating them.

        Raises:
            FlightLogError: the samples do not come after the ones already held.
        """
        old = self.intervals.imu
        if not len(imu.t_ns):
            return
        if old.t_ns.size and imu.t_ns[0] <= old.t_ns[-1]:
            raise FlightLogError("IMU samples must arrive in increasing time order")
        keep = 0
        if self._frame_ns is not None:
            keep = max(int(np.searchsorted(old.t_ns, self._frame_ns, side="right")) - 2, 0)
        self.intervals.imu = _HeldSamples(
            np.concatenate((old.t_ns[keep:], np.asarray(imu.t_ns, dtype=np.int64))),
            np.concatenate((old.gyro_radps[keep:], imu.gyro_radps)),
            np.concatenate((old.acc_mps2[keep:], imu.acc_mps2)))

    def start(self, t_ns: int, bias: gtsam.imuBias.ConstantBias) -> None:
        """Open the interval after the frame at ``t_ns``, linearized at ``bias``."""
        self._frame_ns = int(t_ns)
        self.stream.start(t_ns, bias)

    def advance(self) -> None:
        """Integrate what the samples held already fix (e.g. after a restart)."""
        self.stream.advance()

    def take_time_s(self) -> float:
        """The preintegration time spent since the last call (``add`` only)."""
        spent, self.time_s = self.time_s, 0.0
        return spent

    def finish(self, t_ns: int, start: tuple[np.ndarray, np.ndarray] | None = None
               ) -> Preintegration:
        """The preintegration from the newest frame to the next one at ``t_ns``.

        Args:
            start: ``(world_T_body, velocity_mps)`` of the newest frame (the interval's
                start): needed by the Earth model, ignored by the flat one.

        Raises:
            SolverError: the samples do not cover the interval (nothing changes: feed
                the missing samples and retry).
        """
        return self.stream.finish(t_ns, start)


def navstate_predict(pim: gtsam.PreintegratedCombinedMeasurements, world_T_body: np.ndarray,
                     velocity: np.ndarray, bias: gtsam.imuBias.ConstantBias
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Propagate a body state over one preintegrated interval."""
    state = pim.predict(gtsam.NavState(gtsam.Pose3(world_T_body), np.asarray(velocity)), bias)
    return state.pose().matrix(), np.asarray(state.velocity())


def dead_reckoning(config: FlightConfig, imu: ImuArrays, t_ns: np.ndarray,
                   hold: SampleHold = SampleHold.MIDPOINT, earth: bool = True
                   ) -> TrajectoryEstimate:
    """IMU-only navigation from the initial state, no corrections: the paper's "Free".

    From ``initial_state`` (position, attitude, velocity, biases) at the first frame,
    each frame interval is preintegrated (``ImuIntervals``, the smoother's own) and
    predicted with ``pim.predict(NavState, bias)``; the biases stay at their prior means.

    Args:
        config: flight.yaml (initial state, IMU noise, gravity, origin).
        imu: the samples; they must cover the frame times.
        t_ns: (K,) frame times.
        hold: how a sample stands for time; the default is the smoother's
            (``GraphSettings.imu_hold``), so "Free" and "Compensated" integrate alike.
        earth: the Earth-aware model for a log with a geodetic origin (module docstring;
            ``GraphSettings.earth_physics``); False: the flat model.

    Returns:
        K states at the frame times (biases constant).

    Raises:
        FlightLogError: the IMU samples do not cover the frames.
    """
    init = config.initial_state
    t_frames = np.asarray(t_ns, dtype=np.int64)
    k_frames = t_frames.shape[0]
    t_imu = np.asarray(imu.t_ns, dtype=np.int64)
    if k_frames and (t_imu.size < 2 or t_frames[0] < t_imu[0] or t_frames[-1] > t_imu[-1]):
        span = f"[{t_imu[0]}, {t_imu[-1]}]" if t_imu.size else "nothing"
        raise FlightLogError(f"imu.csv: samples span {span} ns; expected them to cover the "
                             f"frames [{t_frames[0]}, {t_frames[-1]}] ns")
    intervals = ImuIntervals(config, imu, hold, earth)
    bias = initial_bias(init)
    poses = np.empty((k_frames, 4, 4))
    velocities = np.empty((k_frames, 3))
    pose, velocity = init.world_T_body, np.asarray(init.velocity_mps, dtype=float)
    for k in range(k_frames):
        if k:
            pim = intervals.preintegrate(int(t_frames[k - 1]), int(t_frames[k]), bias,
                                         (pose, velocity))
            pose, velocity = navstate_predict(pim, pose, velocity, bias)
        poses[k], velocities[k] = pose, velocity
    return TrajectoryEstimate(
        t_ns=t_frames, world_T_body=poses, velocity_mps=velocities,
        gyro_bias=np.tile(np.asarray(init.gyro_bias, dtype=float), (k_frames, 1)),
        accel_bias=np.tile(np.asarray(init.accel_bias, dtype=float), (k_frames, 1)))


#: Columns of a ``CombinedImuFactor``'s Jacobian (keys X(k), V(k), X(k+1), V(k+1), B(k),
#: B(k+1)) that belong to the earlier and to the later state, each ordered [X, V, B].
_EARLIER_COLUMNS = np.r_[0:9, 18:24]
_LATER_COLUMNS = np.r_[9:18, 24:30]


def propagate_covariance(factor: gtsam.CombinedImuFactor, values: gtsam.Values,
                         covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The later state's covariance from the earlier one's through an IMU factor.

    Linearized at ``values`` (the earlier state's estimate, the later state's
    prediction), the factor's whitened Jacobian ``[A_0 A_1]`` gives
    ``dx_1 = -A_1^-1 (A_0 dx_0 + w)``, ``w ~ N(0, I)``: a Kalman prediction step, without
    a solver update.

    Args:
        factor: the IMU factor between the two frames.
        values: both states' X, V, B.
        covariance: (15, 15) of the earlier state, order [pose (rot, trans), velocity,
            bias (accel, gyro)].

    Returns:
        The later state's (15, 15) covariance and the (15, 15) transition ``M``
        (``dx_1 = M dx_0 + noise``): its covariance with anything correlated with the
        earlier state, ``C``, is ``M C``.
    """
    A, _ = factor.linearize(values).jacobian()
    A_1_inv = np.linalg.inv(A[:, _LATER_COLUMNS])
    M = -A_1_inv @ A[:, _EARLIER_COLUMNS]
    later = M @ covariance @ M.T + A_1_inv @ A_1_inv.T
    return 0.5 * (later + later.T), M
