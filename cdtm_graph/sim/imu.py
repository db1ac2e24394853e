"""IMU synthesis: exact samples along a flight plan, plus white noise and bias random walks.

Measurement model (body frame, docs/flightlog.md units)::

    gyro_radps = omega_body + gyro_bias + n_g
    acc_mps2   = R^T (a_world + g e_z) + accel_bias + n_a     (specific force)

so an IMU at rest, level, reads +g on z. ``n_g``, ``n_a`` are discrete white noise with
sigma = density * sqrt(rate); the biases are random walks whose per-step sigma is
random_walk * sqrt(dt). Samples are instantaneous values (what the smoother's
``SampleHold.MIDPOINT`` assumes).

With a :class:`~cdtm_graph.geodesy.LocalFrame` (a geodetic flight) the world is the ENU
tangent plane at the origin, fixed to the rotating Earth, and the IMU senses the Earth's
rotation and WGS84 normal gravity (:func:`earth_imu`)::

    gyro_radps = omega_body + R^T Omega_world + ...
    acc_mps2   = R^T (a_world - g_world(p) + 2 Omega_world x v_world) + ...
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cdtm_graph.constants import NS_PER_S
from cdtm_graph.geodesy import LocalFrame
from cdtm_graph.imu import ImuNoise
from cdtm_graph.sim.trajectory import FlightPlan, Trajectory, evaluate


@dataclass(frozen=True)
class ImuData:
    """IMU samples with the true biases that corrupted them.

    Attributes:
        t_ns: (N,) int64 sample times, ns, strictly increasing.
        gyro_radps: (N, 3) measured angular rate, body frame.
        acc_mps2: (N, 3) measured specific force, body frame.
        gyro_bias: (N, 3) true gyro bias at each sample, rad/s (ground truth).
        accel_bias: (N, 3) true accelerometer bias at each sample, m/s^2 (ground truth).
    """

    t_ns: np.ndarray
    gyro_radps: np.ndarray
    acc_mps2: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray

    def __post_init__(self) -> None:
        n = self.t_ns.shape[0]
        for name in ("gyro_radps", "acc_mps2", "gyro_bias", "accel_bias"):
            shape = getattr(self, name).shape
            if shape != (n, 3):
                raise ValueError(f"ImuData.{name} must have shape ({n}, 3), got {shape}")


def ideal_imu(traj: Trajectory, gravity_mps2: float,
              frame: LocalFrame | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact, noiseless, bias-free IMU readings along a trajectory.

    Args:
        traj: true body states, N samples.
        gravity_mps2: gravity magnitude; gravity points along -z of world (flat world).
        frame: where the world is on the Earth: then the readings are :func:`earth_imu`'s
            and ``gravity_mps2`` is not used.

    Returns:
        gyro_radps (N, 3): body angular rate in body.
        acc_mps2 (N, 3): specific force ``R^T (a_world + g e_z)`` in body.
    """
    R = traj.rotation_world_body
    if frame is not None:
        return earth_imu(frame, R, traj.position_m, traj.velocity_mps, traj.accel_world_mps2,
                         traj.omega_body_radps)
    f_world = traj.accel_world_mps2 + np.array([0.0, 0.0, gravity_mps2])
    acc = np.einsum("nji,nj->ni", R, f_world)
    return traj.omega_body_radps.copy(), acc


def earth_imu(frame: LocalFrame, world_R_body: np.ndarray, position_m: np.ndarray,
              velocity_mps: np.ndarray, accel_world_mps2: np.ndarray,
              omega_body_radps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Perfect IMU readings of states given in a geodetic log's world frame.

    The world frame turns with the Earth (rate ``Omega``, :attr:`~cdtm_graph.geodesy.
    LocalFrame.earth_rate_world_radps`), so the gyro adds ``R^T Omega`` to the body's rate
    relative to the world, and the specific force is ``a - g(p) + 2 Omega x v`` with
    WGS84 normal gravity ``g`` (gravitation plus centrifugal,
    :meth:`~cdtm_graph.geodesy.LocalFrame.gravity_world_mps2`) at each position.

    Args:
        frame: the world frame on the Earth.
        world_R_body: (N, 3, 3). position_m, velocity_mps, accel_world_mps2: (N, 3) in the
            world (velocity and acceleration relative to the world frame).
        omega_body_radps: (N, 3) the body's angular rate relative to the world, in body.

    Returns:
        gyro_radps (N, 3), acc_mps2 (N, 3) in body.
    """
    earth_rate = frame.earth_rate_world_radps
    g = frame.gravity_world_mps2(position_m)
    f_world = accel_world_mps2 - g + 2.0 * np.cross(earth_rate, velocity_mps)
    gyro = omega_body_radps + np.einsum("nji,j->ni", world_R_body, earth_rate)
    acc = np.einsum("nji,nj->ni", world_R_body, f_world)
    return gyro, acc


def _check_times_ns(t_ns: np.ndarray, name: str) -> np.ndarray:
    t = np.asarray(t_ns)
    if t.ndim != 1 or not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"{name} must be a 1-D integer array of ns, got {t.dtype} {t.shape}")
    t = t.astype(np.int64)
    if t.size >= 2 and np.any(np.diff(t) <= 0):
        raise ValueError(f"{name} must be strictly increasing")
    return t


def simulate_imu(
    plan: FlightPlan,
    t_ns: np.ndarray,
    gravity_mps2: float,
    noise: ImuNoise | None,
    rng: np.random.Generator,
    initial_gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0),
    initial_accel_bias: tuple[float, float, float] = (0.0, 0.0, 0.0),
    frame: LocalFrame | None = None,
) -> ImuData:
    """IMU samples along a flight plan: exact instantaneous values plus bias and noise.

    Args:
        plan: the flight plan.
        t_ns: (N,) int sample times, ns, strictly increasing.
        gravity_mps2: gravity magnitude the accelerometer senses.
        noise: noise densities; None gives noiseless samples whose biases stay at
            their initial values (still added to the measurements).
        rng: source of all randomness; draws are made in a fixed order (gyro white
            noise, accel white noise, gyro bias steps, accel bias steps).
        initial_gyro_bias: gyro bias at the first sample, rad/s.
        initial_accel_bias: accelerometer bias at the first sample, m/s^2.
        frame: the world on the Earth (a geodetic flight): the IMU senses the Earth's
            rotation and normal gravity (:func:`earth_imu`); None: the flat world.

    Returns:
        The samples and the true biases. White noise sigma = density * sqrt(rate) with
        rate = 1 / median sample spacing; the bias steps from sample k-1 to k have
        sigma = random_walk * sqrt(t_k - t_k-1).
    """
    t = _check_times_ns(t_ns, "t_ns")
    n = t.shape[0]
    traj = evaluate(plan, t.astype(float) / NS_PER_S)
    gyro, acc = ideal_imu(traj, gravity_mps2, frame)
    gyro_bias = np.tile(np.asarray(initial_gyro_bias, dtype=float), (n, 1))
    accel_bias = np.tile(np.asarray(initial_accel_bias, dtype=float), (n, 1))
    if noise is not None:
        if n < 2:
            raise ValueError("simulating IMU noise needs at least two samples (for the rate)")
        dt_s = np.diff(t).astype(float) / NS_PER_S
        sqrt_rate = 1.0 / math.sqrt(float(np.median(dt_s)))
        gyro_white = rng.standard_normal((n, 3)) * noise.gyroscope_noise_density * sqrt_rate
        acc_white = rng.standard_normal((n, 3)) * noise.accelerometer_noise_density * sqrt_rate
        step_scale = np.sqrt(dt_s)[:, None]
        gyro_steps = rng.standard_normal((n - 1, 3)) * noise.gyroscope_random_walk * step_scale
        acc_steps = rng.standard_normal((n - 1, 3)) * noise.accelerometer_random_walk * step_scale
        gyro_bias[1:] += np.cumsum(gyro_steps, axis=0)
        accel_bias[1:] += np.cumsum(acc_steps, axis=0)
        gyro = gyro + gyro_white
        acc = acc + acc_white
    return ImuData(t_ns=t, gyro_radps=gyro + gyro_bias, acc_mps2=acc + accel_bias,
                   gyro_bias=gyro_bias, accel_bias=accel_bias)


