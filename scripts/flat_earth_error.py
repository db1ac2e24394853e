"""How far a flat-world mechanization drifts on a long flight that a perfect IMU measures.

The truth is a straight, level flight along a WGS84 geodesic at constant ellipsoidal
height (default: 60 km in 240 s at 36.5 deg N, heading 060), placed by PROJ (pyproj's
Geod and the local frame's conversions) in the world frame, the ENU tangent plane at its
start. A perfect IMU on it measures the Earth's rotation and WGS84 normal gravity::

    gyro = omega_wb_body + R^T Omega_world
    acc  = R^T (a_world - g_world(p) + 2 Omega_world x v_world)

(the world frame turns with the Earth; g holds the centrifugal term). The samples are
integrated back from the true initial state four ways:

- ``flat``: today's model: gravity (0, 0, -g0) everywhere, g0 the normal gravity at the
  start, no Earth rate (RK4 at the IMU rate, IMU values exact at the RK4 nodes);
- ``flat + Earth rate``: the same, with the Earth rate removed from the gyro and the
  Coriolis term, but gravity still constant: what the curvature alone costs;
- ``earth``: the same RK4 with :meth:`cdtm_graph.geodesy.LocalFrame.gravity_world_mps2`
  and the Earth rate: the mechanization's model error, which should be ~0;
- ``gtsam``: GTSAM preintegration over 1 s intervals, as a per-interval IMU factor would
  use :meth:`~cdtm_graph.geodesy.LocalFrame.imu_environment`: gravity at the interval's
  predicted midpoint (``gtsam_n_gravity``), ``omegaCoriolis`` the Earth rate (samples at
  the middle of each 5 ms step; GTSAM holds each over its step);
- ``gtsam, centrifugal twice``: the same with the plain normal gravity as ``n_gravity``,
  which GTSAM's own centrifugal term then counts again.

Prints the horizontal and vertical position error of each at a few times. Run:
``python scripts/flat_earth_error.py [--length-km 60 --duration-s 240 --lat 36.5]``.
"""

from __future__ import annotations

import argparse
import math

import gtsam
import numpy as np
from pyproj import Geod

from cdtm_graph.geodesy import GeodeticOrigin, LocalFrame, normal_gravity_mps2
from cdtm_graph.geometry import so3_exp, so3_log
from cdtm_graph.sim.imu import earth_imu

#: Finite-difference step of the truth's derivatives (s): the path is analytic on the
#: scale of seconds, and PROJ's round-off (~1e-9 m) over (0.5 s)^2 stays below 1e-8 m/s^2.
DIFF_STEP_S = 0.5


class Truth:
    """The true flight: geodesic at constant height, body x along the track, level."""

    def __init__(self, frame: LocalFrame, azimuth_deg: float, speed_mps: float,
                 height_m: float):
        self.frame = frame
        self.geod = Geod(ellps="WGS84")
        self.azimuth_deg = azimuth_deg
        self.speed_mps = speed_mps
        self.height_m = height_m

    def _geodetic(self, t_s: np.ndarray):
        o = self.frame.origin
        n = t_s.size
        lon, lat, back_azimuth = self.geod.fwd(np.full(n, o.longitude_deg),
                                               np.full(n, o.latitude_deg),
                                               np.full(n, self.azimuth_deg), self.speed_mps * t_s)
        forward = (np.asarray(back_azimuth) + 180.0) % 360.0
        return np.asarray(lat), np.asarray(lon), forward

    def position(self, t_s: np.ndarray) -> np.ndarray:
        lat, lon, _ = self._geodetic(t_s)
        return self.frame.geodetic_to_world(lat, lon, self.height_m)

    def rotation(self, t_s: np.ndarray) -> np.ndarray:
        """(N, 3, 3) world_R_body: body x forward, y left, z up, level in the local ENU."""
        lat, lon, azimuth = self._geodetic(t_s)
        yaw = np.radians(90.0 - azimuth)  # from east, counter-clockwise
        enu_R_body = np.zeros((t_s.size, 3, 3))
        enu_R_body[:, 0, 0] = enu_R_body[:, 1, 1] = np.cos(yaw)
        enu_R_body[:, 1, 0] = np.sin(yaw)
        enu_R_body[:, 0, 1] = -np.sin(yaw)
        enu_R_body[:, 2, 2] = 1.0
        return self.frame.world_R_enu(lat, lon) @ enu_R_body

    def state(self, t_s: np.ndarray):
        """Position, velocity, acceleration (world) and body rate w.r.t. the world."""
        h = DIFF_STEP_S
        p = {k: self.position(t_s + k * h) for k in (-2, -1, 0, 1, 2)}
        v = (p[-2] - 8 * p[-1] + 8 * p[1] - p[2]) / (12 * h)
        a = (-p[-2] + 16 * p[-1] - 30 * p[0] + 16 * p[1] - p[2]) / (12 * h * h)

        def rate(step):
            r0, r1 = self.rotation(t_s - step), self.rotation(t_s + step)
            return np.array([so3_log(x.T @ y) for x, y in zip(r0, r1)]) / (2 * step)

        omega = (4 * rate(h / 2) - rate(h)) / 3  # Richardson: fourth order
        return p[0], v, a, omega

    def imu(self, t_s: np.ndarray):
        """Perfect gyro (rad/s) and accelerometer (m/s^2) readings, (N, 3) each: the
        simulator's Earth-aware IMU (:func:`cdtm_graph.sim.imu.earth_imu`)."""
        p, v, a, omega_wb = self.state(t_s)
        return earth_imu(self.frame, self.rotation(t_s), p, v, a, omega_wb)


def integrate_rk4(frame: LocalFrame, truth: Truth, duration_s: float, rate_hz: float,
                  gravity: str, earth_rate_on: bool):
    """RK4 of p, v with exact IMU values at the nodes; attitude by exponential steps."""
    dt = 1.0 / rate_hz
    n = int(round(duration_s * rate_hz))
    omega = frame.earth_rate_world_radps if earth_rate_on else np.zeros(3)
    t_nodes = np.arange(2 * n + 1) * (dt / 2)
    gyro, acc = truth.imu(t_nodes)
    p0, v0, _, _ = truth.state(np.array([0.0]))
    p, v, R = p0[0].copy(), v0[0].copy(), truth.rotation(np.array([0.0]))[0]
    g0 = np.array([0.0, 0.0, -float(normal_gravity_mps2(frame.origin.latitude_deg,
                                                        truth.height_m))])

    def grav(x):
        return frame.gravity_world_mps2(x)[0] if gravity == "earth" else g0

    def rotate(Rk, i0, i1, step):
        # Earth rate in the world (exact: constant), body rate at the step's midpoint.
        mid = gyro[(i0 + i1) // 2] if (i1 - i0) == 2 else 0.5 * (gyro[i0] + gyro[i1])
        return so3_exp(-omega * step) @ Rk @ so3_exp(mid * step)

    out_t, out_p = [0.0], [p.copy()]
    for k in range(n):
        i0, im, i1 = 2 * k, 2 * k + 1, 2 * k + 2
        R_half = rotate(R, i0, im, dt / 2)
        R_next = rotate(R, i0, i1, dt)

        def accel(x, vel, Rx, i):
            return Rx @ acc[i] + grav(x) - 2 * np.cross(omega, vel)

        k1v = accel(p, v, R, i0)
        k1p = v
        k2v = accel(p + dt / 2 * k1p, v + dt / 2 * k1v, R_half, im)
        k2p = v + dt / 2 * k1v
        k3v = accel(p + dt / 2 * k2p, v + dt / 2 * k2v, R_half, im)
        k3p = v + dt / 2 * k2v
        k4v = accel(p + dt * k3p, v + dt * k3v, R_next, i1)
        k4p = v + dt * k3v
        p = p + dt / 6 * (k1p + 2 * k2p + 2 * k3p + k4p)
        v = v + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        R = R_next
        out_t.append((k + 1) * dt)
        out_p.append(p.copy())
    return np.array(out_t), np.array(out_p)


def integrate_gtsam(frame: LocalFrame, truth: Truth, duration_s: float, rate_hz: float,
                    interval_s: float = 1.0, compensate: bool = True):
    """GTSAM preintegration per interval with the interval's gravity and the Earth rate."""
    dt = 1.0 / rate_hz
    steps = int(round(interval_s * rate_hz))
    n_intervals = int(round(duration_s / interval_s))
    t_mid = (np.arange(n_intervals * steps) + 0.5) * dt  # midpoint samples: second order
    gyro, acc = truth.imu(t_mid)
    p0, v0, _, _ = truth.state(np.array([0.0]))
    state = gtsam.NavState(gtsam.Rot3(truth.rotation(np.array([0.0]))[0]), p0[0], v0[0])
    bias = gtsam.imuBias.ConstantBias()
    out_t, out_p = [0.0], [p0[0]]

    def predict(gravity_mps2):
        params = gtsam.PreintegrationParams(gravity_mps2)
        params.setAccelerometerCovariance(1e-6 * np.eye(3))
        params.setGyroscopeCovariance(1e-8 * np.eye(3))
        params.setIntegrationCovariance(1e-8 * np.eye(3))
        params.setOmegaCoriolis(env.earth_rate_radps)
        pim = gtsam.PreintegratedImuMeasurements(params, bias)
        for j in range(i * steps, (i + 1) * steps):
            pim.integrateMeasurement(acc[j], gyro[j], dt)
        return pim.predict(state, bias)

    for i in range(n_intervals):
        start = state.position()
        env = frame.imu_environment(start)
        guess = predict(env.gtsam_n_gravity(start) if compensate else env.gravity_mps2)
        env = frame.imu_environment(0.5 * (start + guess.position()))
        state = predict(env.gtsam_n_gravity(start) if compensate else env.gravity_mps2)
        out_t.append((i + 1) * interval_s)
        out_p.append(state.position())
    return np.array(out_t), np.array(out_p)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--length-km", type=float, default=60.0)
    parser.add_argument("--duration-s", type=float, default=240.0)
    parser.add_argument("--lat", type=float, default=36.5)
    parser.add_argument("--lon", type=float, default=127.0)
    parser.add_argument("--height-m", type=float, default=1000.0)
    parser.add_argument("--azimuth-deg", type=float, default=60.0)
    parser.add_argument("--rate-hz", type=float, default=200.0)
    args = parser.parse_args()

    frame = LocalFrame(GeodeticOrigin(args.lat, args.lon, args.height_m))
    speed = args.length_km * 1e3 / args.duration_s
    truth = Truth(frame, args.azimuth_deg, speed, args.height_m)
    runs = {
        "flat": integrate_rk4(frame, truth, args.duration_s, args.rate_hz, "flat", False),
        "flat + Earth rate": integrate_rk4(frame, truth, args.duration_s, args.rate_hz, "flat",
                                           True),
        "earth": integrate_rk4(frame, truth, args.duration_s, args.rate_hz, "earth", True),
        "gtsam (1 s intervals)": integrate_gtsam(frame, truth, args.duration_s, args.rate_hz),
        "gtsam, centrifugal twice": integrate_gtsam(frame, truth, args.duration_s,
                                                    args.rate_hz, compensate=False),
    }
    print(f"{args.length_km:g} km in {args.duration_s:g} s at {speed:g} m/s, latitude "
          f"{args.lat:g}, azimuth {args.azimuth_deg:g}, {args.height_m:g} m above the "
          f"ellipsoid; perfect IMU at {args.rate_hz:g} Hz")
    checkpoints = [t for t in (30.0, 60.0, 120.0, 180.0, 240.0) if t <= args.duration_s]
    print("position error, horizontal / vertical (m)")
    print(f"{'':26}" + "".join(f"{f't = {t:g} s':>20}" for t in checkpoints))
    for name, (t, p) in runs.items():
        err = p - truth.position(t)
        cells = []
        for tc in checkpoints:
            k = int(np.argmin(np.abs(t - tc)))
            cells.append(f"{math.hypot(*err[k, :2]):.3g} / {err[k, 2]:+.2g}")
        print(f"{name:26}" + "".join(f"{c:>20}" for c in cells))
    far = truth.position(np.array([args.duration_s]))[0]
    print(f"\nat the end: {np.hypot(*far[:2]) / 1e3:.1f} km from the origin, ground "
          f"{-far[2]:.0f} m below the tangent plane; the local vertical turned by "
          f"{math.degrees(math.acos(frame.world_R_enu_at(far)[0][2, 2])):.3f} deg")


if __name__ == "__main__":
    main()
