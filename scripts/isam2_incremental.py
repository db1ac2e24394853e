"""Incremental smoothing, one frame at a time, with the IncrementalSmoother API.

Feeds the bundled sample log frame by frame, as a live system would: each call gets the
new frame's time, its tracked features and the IMU samples since the previous frame,
and returns the newest pose with its covariance (iSAM2 underneath; pass ``--lag-s`` for
GTSAM's incremental fixed-lag smoother).

Run: ``python scripts/isam2_incremental.py [LOG] [--lag-s 10]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cdtm_graph.flightlog import ImuSamples
from cdtm_graph.loading import load_log_and_dtm
from cdtm_graph.smoother import IncrementalSmoother

SAMPLE_LOG = Path(__file__).resolve().parents[1] / "data" / "sample_flight"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", nargs="?", default=str(SAMPLE_LOG))
    parser.add_argument("--lag-s", type=float, default=None)
    args = parser.parse_args(argv)

    flight, dtm = load_log_and_dtm(args.log)
    smoother = IncrementalSmoother(flight.config, dtm, lag_s=args.lag_s)
    imu, tracks, t_frames = flight.imu, flight.tracks, flight.frames.t_ns
    sent = 0  # IMU samples handed over so far
    errors = []
    for k, t_ns in enumerate(t_frames):
        # IMU samples up to (and one past) this frame: the smoother splits boundary samples.
        upto = min(int(np.searchsorted(imu.t_ns, t_ns, side="right")) + 1, len(imu.t_ns))
        new_imu = ImuSamples(imu.t_ns[sent:upto], imu.gyro_radps[sent:upto],
                             imu.acc_mps2[sent:upto])
        sent = upto
        seen = tracks.frame == k
        update = smoother.add_frame(int(t_ns), tracks.track_id[seen], tracks.uv_px[seen], new_imu)
        sigma_pos = np.sqrt(np.diag(update.pose_covariance)[3:])
        line = (f"frame {k:3d}: {update.n_features:3d} features, position "
                f"{np.array2string(update.world_T_body[:3, 3], precision=1)} m, "
                f"1-sigma {np.array2string(sigma_pos, precision=2)} m (body axes), "
                f"{1e3 * update.update_time_s:.1f} ms")
        if flight.groundtruth is not None:
            truth = flight.groundtruth.interpolate(np.array([t_ns])).position_m[0]
            errors.append(update.world_T_body[:3, 3] - truth)
            line += f", error {np.linalg.norm(errors[-1]):.2f} m"
        print(line)
    smoother.finalize()
    final = smoother.estimate()
    summary = {"frames": len(final),
               "median_update_ms": 1e3 * float(np.median(smoother.update_times_s))}
    if errors:
        summary["filter_rms_error_m"] = float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1))))
    print(summary)
    return summary


if __name__ == "__main__":
    main()
