"""Incremental smoothing, one frame at a time, with the IncrementalSmoother API.

Feeds the bundled sample log as a live system would: IMU samples as they arrive
(``add_imu`` preintegrates them at once), then each frame with its tracked features and
the sample that closes its interval. ``add_frame`` returns the newest pose with its
covariance (iSAM2 underneath; pass ``--lag-s`` for GTSAM's incremental fixed-lag smoother).

Run: ``python scripts/isam2_incremental.py [LOG] [--lag-s 10]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cdtm_graph.flightlog import ImuSamples, load_log_and_dtm
from cdtm_graph.smoother import IncrementalSmoother

SAMPLE_LOG = Path(__file__).resolve().parents[1] / "data" / "sample_flight"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", nargs="?", default=str(SAMPLE_LOG))
    parser.add_argument("--lag-s", type=float, default=None)
    args = parser.parse_args(argv)

    flight, dtm = load_log_and_dtm(args.log)
    imu, tracks, t_frames = flight.imu, flight.tracks, flight.frames.t_ns
    # The camera rate lets a fixed lag relinearize a few times per window, not every frame.
    frame_interval_s = float(np.median(np.diff(t_frames))) * 1e-9
    smoother = IncrementalSmoother(flight.config, dtm, lag_s=args.lag_s,
                                   frame_interval_s=frame_interval_s)
    sent = 0  # IMU samples handed over so far

    def samples(a: int, b: int) -> ImuSamples:
        return ImuSamples(imu.t_ns[a:b], imu.gyro_radps[a:b], imu.acc_mps2[a:b])

    errors = []
    for k, t_ns in enumerate(t_frames):
        # The samples before the frame arrive first, one by one in a live system (here
        # in one call); the frame then comes with the sample at or after its time, which
        # the smoother splits between the two intervals.
        before = int(np.searchsorted(imu.t_ns, t_ns, side="left"))
        if before > sent:
            smoother.add_imu(samples(sent, before))
            sent = before
        upto = max(min(before + 1, len(imu.t_ns)), sent)
        closing, sent = samples(sent, upto), upto
        seen = tracks.frame == k
        update = smoother.add_frame(int(t_ns), tracks.track_id[seen], tracks.uv_px[seen], closing)
        sigma_pos = np.sqrt(np.diag(update.pose_covariance)[3:])
        line = (f"frame {k:3d}: {update.n_features:3d} features, position "
                f"{np.array2string(update.world_T_body[:3, 3], precision=1)} m, "
                f"1-sigma {np.array2string(sigma_pos, precision=2)} m (body axes), "
                f"{1e3 * update.update_time_s:.1f} ms (+ IMU {1e3 * update.imu_time_s:.1f} ms)")
        if flight.groundtruth is not None:
            truth = flight.groundtruth.interpolate(np.array([t_ns])).position_m[0]
            errors.append(update.world_T_body[:3, 3] - truth)
            line += f", error {np.linalg.norm(errors[-1]):.2f} m"
        print(line)
    smoother.finalize()
    final = smoother.estimate()
    summary = {"frames": len(final),
               "median_update_ms": 1e3 * float(np.median(smoother.update_times_s)),
               "median_imu_ms": 1e3 * float(np.median(smoother.imu_times_s))}
    if errors:
        summary["filter_rms_error_m"] = float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1))))
    print(summary)
    return summary


if __name__ == "__main__":
    main()
