"""Smoother speed at scale: batch LM with marginals, full-history iSAM2, fixed-lag.

Run: ``python benchmarks/bench_smoother.py --frames 1000``. Simulates a flight with ~170
features per frame pair (a nav.csv INS solution as the batch initial guess). Incremental
runs replay the log as it would arrive live: each frame interval's IMU samples first
(``add_imu`` preintegrates them), then the frame (``add_frame``, the timed update; the
IMU part is printed beside it). Ends with one line:
``batch_s=... batch_held_s=... peak_mb=... isam2_median_ms=... isam2_p99_ms=...``
``fixedlag_median_ms=... fixedlag_p99_ms=...`` (one line).
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cdtm_graph.graph import GraphSettings  # noqa: E402
from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight  # noqa: E402
from cdtm_graph.smoother import SmootherMode, SmootherSettings, smooth  # noqa: E402

#: iSAM2 figures are taken around the end of the flight ("around frame 1000"), fixed-lag
#: ones from frame 200 to the end, as the issue states them.
ISAM2_WINDOW = 100
FIXED_LAG_FROM = 200


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--fps", type=float, default=2.0)
    parser.add_argument("--features", type=int, default=170)
    parser.add_argument("--lag-s", type=float, default=10.0)
    args = parser.parse_args(argv)

    t0 = time.perf_counter()
    flight, dtm = simulate_flight(SimulationSettings(
        frames=args.frames, fps=args.fps, n_features=args.features, nav="noisy_truth", seed=5))
    print(f"simulated {args.frames} frames at {args.fps} fps, {len(flight.tracks)} observations "
          f"in {time.perf_counter() - t0:.1f} s")
    smooth(flight, dtm, SmootherSettings(max_iterations=1))  # warm-up: numba caches, imports

    t0 = time.perf_counter()
    batch = smooth(flight, dtm, SmootherSettings())
    batch_s = time.perf_counter() - t0
    # Process peak (simulation included, so an upper bound on the smoother's own peak).
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"batch: {batch_s:.2f} s ({batch.stats.iterations} LM iterations in "
          f"{batch.stats.time_s:.2f} s, marginals {batch.stats.marginals_time_s:.2f} s), "
          f"process peak RSS {peak_mb:.0f} MB")
    # flight.yaml's calibration held unchecked: the estimator without issue 10's side solve
    t0 = time.perf_counter()
    smooth(flight, dtm, SmootherSettings(graph=GraphSettings(calibration=None)))
    held_s = time.perf_counter() - t0
    print(f"batch, calibration held unchecked (--calibration held): {held_s:.2f} s; the "
          f"check costs {batch_s - held_s:.2f} s")

    inc = smooth(flight, dtm, SmootherSettings(mode=SmootherMode.INCREMENTAL))
    u = 1e3 * np.asarray(inc.stats.update_times_s)
    tail = u[-ISAM2_WINDOW:]
    print(f"iSAM2 full history: median {np.median(tail):.2f} ms, "
          f"p99 {np.percentile(tail, 99):.1f} ms "
          f"over the last {ISAM2_WINDOW} frames; total {inc.stats.time_s:.1f} s")

    # A live system needs the newest covariance only (keep_exit_covariances=False); an
    # offline run keeps each frame's covariance as it leaves the window (~1 ms more).
    lag = smooth(flight, dtm, SmootherSettings(mode=SmootherMode.INCREMENTAL, lag_s=args.lag_s,
                                               keep_exit_covariances=False))
    lag_offline = smooth(flight, dtm, SmootherSettings(mode=SmootherMode.INCREMENTAL,
                                                       lag_s=args.lag_s))
    w = 1e3 * np.asarray(lag_offline.stats.update_times_s)[FIXED_LAG_FROM:]
    print(f"fixed-lag {args.lag_s:g} s keeping exit covariances: median {np.median(w):.2f} ms")
    v = 1e3 * np.asarray(lag.stats.update_times_s)[FIXED_LAG_FROM:]
    print(f"fixed-lag {args.lag_s:g} s: median {np.median(v):.2f} ms, p99 "
          f"{np.percentile(v, 99):.1f} ms from frame {FIXED_LAG_FROM}")
    thirds = np.array_split(v, 3)  # flat: no growth along the flight
    print("  fixed-lag median by third of frames 200-end: "
          + ", ".join(f"{np.median(t):.2f}" for t in thirds) + " ms")
    # The log is fed as it would arrive: each interval's IMU samples through add_imu
    # (preintegrated then), then the frame. Both parts of the per-frame work:
    imu = 1e3 * np.asarray(lag.stats.imu_times_s)[FIXED_LAG_FROM:]
    print(f"  IMU preintegration as samples arrive: median {np.median(imu):.2f} ms per frame "
          f"interval; update + IMU: median {np.median(v + imu):.2f} ms, "
          f"p99 {np.percentile(v + imu, 99):.1f} ms")
    print(f"batch_s={batch_s:.2f} batch_held_s={held_s:.2f} peak_mb={peak_mb:.0f} "
          f"isam2_median_ms={np.median(tail):.2f} isam2_p99_ms={np.percentile(tail, 99):.1f} "
          f"fixedlag_median_ms={np.median(v):.2f} fixedlag_p99_ms={np.percentile(v, 99):.1f}")


if __name__ == "__main__":
    main()
