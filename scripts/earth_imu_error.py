"""What the Earth-aware IMU model buys on a long geodetic flight (issue 11, item 3).

A simulated flight (default 200 s at 250 m/s: 50 km, zig-zagging about east, 1000 m
above fractal terrain) placed at a geodetic origin, its IMU sensing the Earth's rotation
and WGS84 normal gravity (``SimulationSettings(origin=...)``), and the same flight in a
flat world (the same seed: the same terrain, tracks and noise draws). Two tables:

1. **Dead reckoning of the noiseless flight** from the true initial state: the flat
   world's (the samples' hold error only), the geodetic flight with the Earth model
   (gravity at the interval's midpoint ``p + v T/2``), with gravity at GTSAM's predicted
   midpoint instead, at each interval's start, at a point 141 m from the midpoint, and
   with the flat model (no Earth rate, gravity along the world's -z).
2. **Smoothing the noisy flight** (batch, iSAM2, fixed lag 10 s): the flat world, the
   geodetic flight with the Earth model and without (``GraphSettings(earth_physics=
   False)``): position RMSE, maximum error, position ANEES and the accelerometer bias
   error (where the flat model's misfit goes). With ``--dem`` also the geodetic log
   written with its DEM as an EPSG:4326 (1", EGM96) and a UTM 52N (30 m) GeoTIFF, read
   back and smoothed in batch, and its ``trajectory_geodetic.csv`` against the truth.

Run: ``python scripts/earth_imu_error.py [--duration-s 200 --speed-mps 250 --fps 1
--features 170 --seed 3 --dem | --no-smoothing]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import tempfile
import time
from pathlib import Path

import gtsam
import numpy as np
import yaml

from cdtm_graph.geodesy import GeodeticOrigin
from cdtm_graph.graph import GraphSettings
from cdtm_graph.imu import EarthImu, ImuIntervals, SampleHold, dead_reckoning, navstate_predict
from cdtm_graph.outputs import TRAJECTORY_GEODETIC_CSV, write_run
from cdtm_graph.run.prepare import load_log_and_dtm
from cdtm_graph.sim.simulate import SimulationSettings, simulate, write_geodetic_simulation
from cdtm_graph.smoother import SmootherMode, SmootherSettings, smooth
from cdtm_graph.verdict.evaluation import trajectory_errors

ORIGIN = GeodeticOrigin(36.5, 127.25, 120.0)
CHECKPOINTS_S = (30.0, 60.0, 120.0, 200.0)


class _GravityAt(EarthImu):
    """The Earth model with each interval's gravity somewhere else (for the comparison)."""

    def __init__(self, base: EarthImu, where: str):
        super().__init__(base.frame, base.noise, base.gravity_mps2)
        self.where = where

    def place(self, pim, world_T_body, velocity_mps) -> None:
        start = np.asarray(world_T_body)[:3, 3]
        if self.where == "start":
            point = start
        elif self.where == "offset":
            point = start + 0.5 * pim.deltaTij() * velocity_mps + np.array([100.0, 100.0, 0.0])
        else:  # "predicted": GTSAM's prediction from the start state, gravity at the start
            pim.interval_params.n_gravity = self.frame.imu_environment(start).gtsam_n_gravity(
                start)
            state = gtsam.NavState(gtsam.Pose3(world_T_body), velocity_mps)
            point = 0.5 * (start + pim.predict(state, pim.biasHat()).position())
        pim.interval_params.n_gravity = self.frame.imu_environment(point).gtsam_n_gravity(start)


def _dead_reckoning_with(log, where: str) -> np.ndarray:
    intervals = ImuIntervals(log.config, log.imu, SampleHold.MIDPOINT)
    assert intervals.earth is not None
    intervals.earth = _GravityAt(intervals.earth, where)
    init = log.config.initial_state
    t = log.frames.t_ns
    pose, velocity = init.world_T_body, np.asarray(init.velocity_mps, dtype=float)
    positions = [pose[:3, 3]]
    bias = gtsam.imuBias.ConstantBias()
    for k in range(1, t.size):
        pim = intervals.preintegrate(int(t[k - 1]), int(t[k]), bias, (pose, velocity))
        pose, velocity = navstate_predict(pim, pose, velocity, bias)
        positions.append(pose[:3, 3])
    return np.array(positions)


def _row(name: str, log, positions: np.ndarray) -> str:
    truth = log.groundtruth.interpolate(log.frames.t_ns).position_m
    err = np.linalg.norm(positions - truth, axis=1)
    t_s = (log.frames.t_ns - log.frames.t_ns[0]) / 1e9
    cells = [f"{err[int(np.argmin(np.abs(t_s - c)))]:12.3g}" for c in CHECKPOINTS_S
             if c <= t_s[-1] + 1e-9]
    return f"{name:48}" + "".join(cells)


def dead_reckoning_table(settings: SimulationSettings) -> None:
    clean = dataclasses.replace(settings, noiseless=True, n_features=10)
    flat = simulate(clean).log
    geo = simulate(dataclasses.replace(clean, origin=ORIGIN)).log
    t = flat.frames.t_ns
    print("1. dead reckoning of the noiseless flight: position error (m) at t =",
          ", ".join(f"{c:g}" for c in CHECKPOINTS_S), "s")
    print(_row("flat world (the same flight, flat IMU)", flat,
               dead_reckoning(flat.config, flat.imu, t).position_m))
    print(_row("geodetic, Earth model (gravity at p + vT/2)", geo,
               dead_reckoning(geo.config, geo.imu, t).position_m))
    print(_row("geodetic, gravity at GTSAM's predicted midpoint", geo,
               _dead_reckoning_with(geo, "predicted")))
    print(_row("geodetic, gravity at the interval start", geo,
               _dead_reckoning_with(geo, "start")))
    print(_row("geodetic, gravity 141 m from the midpoint", geo,
               _dead_reckoning_with(geo, "offset")))
    print(_row("geodetic, flat model (earth_physics=False)", geo,
               dead_reckoning(geo.config, geo.imu, t, earth=False).position_m))


def _smooth_row(name: str, result, log, truth_bias: np.ndarray, seconds: float) -> str:
    e = trajectory_errors(result.estimate, result.covariances, log.groundtruth)
    err = np.linalg.norm(e.position_error_world_m, axis=1)
    bias_err = np.sqrt(np.mean(np.sum((result.estimate.accel_bias - truth_bias) ** 2, axis=1)))
    return (f"{name:40}{np.linalg.norm(e.rmse_position_m):8.2f} "
            f"{np.array2string(e.rmse_position_m, precision=2):>20} {err.max():8.2f} "
            f"{e.anees_position:7.2f} {bias_err:10.4f} {seconds:7.1f}")


def smoothing_table(settings: SimulationSettings, dem: bool) -> None:
    flat = simulate(settings)
    geo = simulate(dataclasses.replace(settings, origin=ORIGIN))
    k = np.searchsorted(geo.imu.t_ns, geo.log.frames.t_ns)
    truth_bias = geo.imu.accel_bias[k]
    print("\n2. smoothing the noisy flight")
    print(f"{'':40}{'rmse_3d':>8} {'rmse x/y/z':>20} {'max_3d':>8} {'anees':>7} "
          f"{'accel_bias':>10} {'time_s':>7}")
    modes = (("batch", SmootherMode.BATCH, None), ("iSAM2", SmootherMode.INCREMENTAL, None),
             ("fixed lag 10 s", SmootherMode.INCREMENTAL, 10.0))
    for label, mode, lag in modes:
        for name, sim, earth in (("flat world", flat, True), ("geodetic, Earth model", geo, True),
                                 ("geodetic, flat model", geo, False)):
            start = time.perf_counter()
            result = smooth(sim.log, sim.dtm, SmootherSettings(
                graph=GraphSettings(earth_physics=earth), mode=mode, lag_s=lag))
            print(_smooth_row(f"{label}: {name}", result, sim.log, truth_bias,
                              time.perf_counter() - start), flush=True)
    if not dem:
        return
    truth = geo.log.groundtruth.interpolate(geo.log.frames.t_ns).position_m
    with tempfile.TemporaryDirectory() as tmp:
        for crs, pixel in (("EPSG:4326", None), ("EPSG:32652", 30.0)):
            root = Path(tmp) / crs.replace(":", "")
            write_geodetic_simulation(geo, root, dem_crs=crs, pixel_size=pixel)
            doc = yaml.safe_load((root / "flight.yaml").read_text())
            doc["dtm"].update(margin_m=1500.0, spacing_m=15.0)
            (root / "flight.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
            log, dtm = load_log_and_dtm(root)
            start = time.perf_counter()
            result = smooth(log, dtm)
            print(_smooth_row(f"batch: DEM {crs}", result, log, truth_bias,
                              time.perf_counter() - start), flush=True)
            run = Path(tmp) / f"run_{crs.replace(':', '')}"
            write_run(run, result, {}, frame=log.config.local_frame)
            table = np.loadtxt(run / TRAJECTORY_GEODETIC_CSV, delimiter=",", skiprows=1)
            position = log.config.local_frame.geodetic_to_world(table[:, 1], table[:, 2],
                                                                table[:, 3])
            err = np.linalg.norm(position - truth, axis=1)
            print(f"{'  its trajectory_geodetic.csv':40}{np.sqrt(np.mean(err ** 2)):8.2f} "
                  f"{'':>20} {err.max():8.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--duration-s", type=float, default=200.0)
    parser.add_argument("--speed-mps", type=float, default=250.0)
    parser.add_argument("--fps", type=float, default=1.0)
    parser.add_argument("--features", type=int, default=170)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--dem", action="store_true",
                        help="also smooth the log written with EPSG:4326 and UTM DEM tiles")
    parser.add_argument("--no-smoothing", action="store_true",
                        help="the dead-reckoning table only")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    settings = SimulationSettings(frames=int(round(args.duration_s * args.fps)) + 1,
                                  fps=args.fps, speed_mps=args.speed_mps,
                                  n_features=args.features, seed=args.seed)
    length_km = args.duration_s * args.speed_mps / 1e3
    print(f"{args.duration_s:g} s at {args.speed_mps:g} m/s ({length_km:g} km), origin "
          f"{ORIGIN.latitude_deg} N {ORIGIN.longitude_deg} E, {args.fps:g} fps, "
          f"{args.features} features, seed {args.seed}\n")
    dead_reckoning_table(settings)
    if not args.no_smoothing:
        smoothing_table(settings, args.dem)


if __name__ == "__main__":
    main()
