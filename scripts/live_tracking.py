"""Live navigation from images: the feature tracker feeds the incremental smoother frame by frame.

A live system receives IMU samples and camera images. For each image the
:class:`~cdtm_graph.frontend.FeatureTracker` predicts the features' motion with the
gyro's rotation since the previous image, tracks and verifies them, and hands the
features seen to :class:`~cdtm_graph.smoother.IncrementalSmoother`, which returns the
newest pose and its covariance at once (iSAM2; ``--lag-s`` for a fixed lag). Nothing
needs the whole flight: the tracker keeps one image, the smoother its window.

With a LOG (a flight log whose frames.csv names images), its images and IMU are
replayed; without one, a small flight is simulated and rendered in memory first (the
paper's geometry: 1000 m, 200 m/s, 60 deg FOV, 1 fps, 640x480).

Each line gives the newest frame's position 1-sigma; until the estimate has settled under
the C-DTM factors (from the prior's 50 m), it is the prior's carried by the IMU, marked
``settling``. Where the tracks read the DTM worse than flight.yaml states, the line says
to what its height 1-sigma grew (``FrameUpdate.map_sigma_h_m`` from there), and a frame
the update flags says why (``FrameUpdate.flags``: ``map_mismatch``, ``few_features``...,
the verdict's frame flags as far as they are known then). With ground
truth each line gives the error, and the summary the share of frames whose position error
lies inside 3 sigma (chi-square(3) at 99.73%).

Run: ``python scripts/live_tracking.py [LOG] [--frames 20] [--lag-s 10] [--seed 0]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from cdtm_graph.dtm import load_dtm
from cdtm_graph.flightlog import ImuSamples, read_flightlog
from cdtm_graph.frontend import FeatureTracker, camera_rotation_from_imu, load_image
from cdtm_graph.imu import ImuIntervals, SampleHold, initial_bias
from cdtm_graph.smoother import IncrementalSmoother, SmootherSettings
from cdtm_graph.verdict.evaluation import share_inside_three_sigma


def _simulated(frames: int, seed: int):
    """A rendered flight in memory: (log, DTM, images)."""
    from cdtm_graph.sim.render import render_flight
    from cdtm_graph.sim.simulate import SimulationSettings, simulate

    result = simulate(SimulationSettings(frames=frames, resolution_px=(640, 480), seed=seed))
    return result.log, result.dtm, render_flight(result).images


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", nargs="?", help="a flight log with images (default: simulate)")
    parser.add_argument("--frames", type=int, default=20, help="frames to simulate")
    parser.add_argument("--lag-s", type=float, default=None, help="fixed-lag smoother")
    parser.add_argument("--seed", type=int, default=0, help="the simulated flight's seed")
    args = parser.parse_args(argv)

    images: list[np.ndarray] | None = None
    if args.log is None:
        flight, dtm, images = _simulated(args.frames, args.seed)
    else:
        flight = read_flightlog(args.log, read_tracks=False)
        cfg = flight.config.dtm
        dtm = load_dtm(cfg.path, origin_enu_m=cfg.origin_enu_m, sigma_h_m=cfg.sigma_h_m)
    config, imu, t_frames = flight.config, flight.imu, flight.frames.t_ns
    frame_interval_s = float(np.median(np.diff(t_frames))) * 1e-9
    smoother = IncrementalSmoother(config, dtm, SmootherSettings(lag_s=args.lag_s,
                                                                 keep_exit_covariances=False),
                                   frame_interval_s=frame_interval_s)
    tracker = FeatureTracker(config.camera.camera)
    bias = initial_bias(config.initial_state)
    sent = 0  # IMU samples received so far

    def samples(a: int, b: int) -> ImuSamples:
        return ImuSamples(imu.t_ns[a:b], imu.gyro_radps[a:b], imu.acc_mps2[a:b])

    errors, updates, tracking_s = [], [], []
    for k, t_ns in enumerate(t_frames):
        # The IMU samples up to the frame arrive first; the frame comes with the one at
        # or after its time, which closes the interval.
        before = int(np.searchsorted(imu.t_ns, t_ns, side="left"))
        if before > sent:
            smoother.add_imu(samples(sent, before))
            sent = before
        upto = max(min(before + 1, len(imu.t_ns)), sent)
        closing, sent = samples(sent, upto), upto
        rotation = None
        if k > 0:  # the gyro's rotation over the frame interval, from the samples received
            # (from two samples before the previous frame: its hold starts there)
            lo = max(int(np.searchsorted(imu.t_ns, t_frames[k - 1], side="left")) - 2, 0)
            received = ImuIntervals(config, samples(lo, sent), SampleHold.MIDPOINT)
            rotation = camera_rotation_from_imu(received, config.camera.body_T_cam,
                                                int(t_frames[k - 1]), int(t_ns), bias)
        image = (images[k] if images is not None
                 else load_image(flight.root / flight.frames.image[k]))
        start = time.perf_counter()
        seen = tracker.track(image, rotation)
        tracking_s.append(time.perf_counter() - start)
        update = smoother.add_frame(int(t_ns), seen.track_id, seen.uv_px, closing)
        sigma_pos = np.sqrt(np.diag(update.pose_covariance)[3:])
        line = (f"frame {k:3d}: {seen.track_id.size:3d} features ({int(seen.is_new.sum())} "
                f"new), {update.n_features:3d} C-DTM factors, tracking "
                f"{1e3 * tracking_s[-1]:.1f} ms, update {1e3 * update.update_time_s:.1f} ms, "
                f"1-sigma {np.array2string(sigma_pos, precision=2)} m"
                f"{'' if update.converged else ' (settling)'}")
        if smoother.map_grown and smoother.map_grown[-1][0] == k:  # the map read worse
            line += f", DTM height 1-sigma grown to {update.map_sigma_h_m:.2f} m"
        if update.flags:  # why this frame's fix is weak or not to be trusted, known now
            line += f", flagged {', '.join(update.flags)}"
        if flight.groundtruth is not None:
            truth = flight.groundtruth.interpolate(np.array([t_ns])).position_m[0]
            errors.append(update.world_T_body[:3, 3] - truth)
            updates.append(update)
            line += f", error {np.linalg.norm(errors[-1]):.2f} m"
        print(line)
    smoother.finalize()
    summary = {"frames": len(t_frames),
               "median_tracking_ms": 1e3 * float(np.median(tracking_s)),
               "median_update_ms": 1e3 * float(np.median(smoother.update_times_s))}
    if errors:  # the newest frame's estimate as it came, and the whole flight smoothed
        summary["filter_rms_error_m"] = float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1))))
        truth = flight.groundtruth.interpolate(t_frames).position_m
        smoothed = smoother.estimate().world_T_body[:, :3, 3] - truth
        summary["smoothed_rms_error_m"] = float(np.sqrt(np.mean(np.sum(smoothed ** 2, axis=1))))
        # the share of frames whose error lies inside 3 sigma of the covariance printed
        summary["filter_inside_3_sigma"] = share_inside_three_sigma(
            np.stack([u.world_T_body for u in updates]),
            np.stack([u.pose_covariance for u in updates]), np.stack(errors))
    print(summary)
    return summary


if __name__ == "__main__":
    main()
