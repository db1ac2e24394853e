"""Visual front-end speed and accuracy on a rendered flight (640x480, the paper's geometry).

* **Rendering**: seconds per 640x480 frame of :func:`cdtm_graph.sim.render.render_flight`
  (after a warm-up frame: numba compiles once per install).
* **Tracking speed**: per-frame time of :class:`cdtm_graph.frontend.FeatureTracker` (~150
  features) beside a bare OpenCV loop on the same images in the same run: pyramidal
  Lucas-Kanade with the same window and levels, five-point RANSAC on the essential
  matrix (``cv2.findEssentialMat``), ``cv2.goodFeaturesToTrack`` to top up to the same
  count. The two alternate over ``--repeats`` passes; medians over frames 1..K-1.
  Also, as issue 22 measured it, the tracker without the IMU's rotation beside the
  textbook loop of the issue (``run_bare_fb``): ``goodFeaturesToTrack`` (150),
  Lucas-Kanade 21x21 over 5 levels forward and back (< 1 px), ``findEssentialMat``
  RANSAC (1 px), refilled to 150 when fewer than 100 remain.
* **Tracking accuracy** against the renderer's truth
  (:func:`cdtm_graph.sim.tracking_truth.match_errors`): pair error median / 95th
  percentile of the kept matches, drift along tracks, wrong-match fractions (> 2 px)
  of the raw Lucas-Kanade output, before and after the epipolar verification; clean
  images, with +-10 % exposure jitter and 1 px motion blur, and a harder flight
  (600 m over the 300 m relief, 4 DN of noise, jitter and blur).

Times are wall and CPU (``time.process_time``: all of the process's threads; steadier
than wall time on a shared machine). Run: ``python benchmarks/bench_tracking.py [--frames 60]
[--repeats 3] [--speed-only]``; ends with one line
``render_s_per_frame=... tracker_ms=... bare_ms=... ratio=... tracker_no_imu_ms=...
bare_fb_ms=... ratio_no_imu_fb=... tracker_cpu_ms=... bare_cpu_ms=... tracker_no_imu_cpu_ms=...
bare_fb_cpu_ms=...``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cdtm_graph.frontend import (  # noqa: E402
    FeatureTracker,
    TrackerSettings,
    camera_rotations_from_imu,
)
from cdtm_graph.sim.render import Renderer, RenderSettings, render_flight  # noqa: E402
from cdtm_graph.sim.simulate import SimulationSettings, simulate  # noqa: E402
from cdtm_graph.sim.tracking_truth import match_errors  # noqa: E402

FEATURES = 150


def run_tracker(camera, images, rotations, settings: TrackerSettings):
    tracker = FeatureTracker(camera, settings)
    outputs, times = [], []
    for image, rotation in zip(images, rotations):
        start, cpu = time.perf_counter(), time.process_time()
        outputs.append(tracker.track(image, rotation))
        times.append((time.perf_counter() - start, time.process_time() - cpu))
    return outputs, np.array(times)


def _refilled(image: np.ndarray, pts: np.ndarray, settings: TrackerSettings) -> np.ndarray:
    """The bare loops' points (N, 1, 2) topped up to ``max_features`` with new corners kept
    ``min_distance_px`` from them."""
    mask = np.full(image.shape, 255, np.uint8)
    for u, v in pts.reshape(-1, 2).tolist():
        cv2.circle(mask, (int(u), int(v)), int(settings.min_distance_px), 0, -1)
    new = cv2.goodFeaturesToTrack(image, settings.max_features - len(pts),
                                  settings.quality_level, settings.min_distance_px,
                                  mask=mask, blockSize=settings.block_size_px)
    if new is None:
        return pts
    return np.concatenate([pts.reshape(-1, 1, 2), new.astype(np.float32)])


def run_bare(camera, images, settings: TrackerSettings) -> tuple[np.ndarray, np.ndarray]:
    """The bare loop: KLT, five-point RANSAC, top up with Shi-Tomasi corners."""
    window = (settings.window_px, settings.window_px)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, settings.klt_iterations,
                settings.klt_epsilon_px)
    K = camera.K
    prev, pts = None, np.zeros((0, 1, 2), np.float32)
    times, counts = [], []
    for image in images:
        start, cpu = time.perf_counter(), time.process_time()
        if prev is not None and len(pts):
            nxt, status, _ = cv2.calcOpticalFlowPyrLK(prev, image, pts, None, winSize=window,
                                                      maxLevel=settings.pyramid_levels,
                                                      criteria=criteria)
            ok = status.ravel() == 1
            p0, p1 = pts[ok], nxt[ok]
            if len(p0) >= 8:
                _, inliers = cv2.findEssentialMat(p0, p1, K, cv2.RANSAC,
                                                  settings.ransac_confidence,
                                                  settings.epipolar_threshold_px)
                if inliers is not None:
                    p1 = p1[inliers.ravel() == 1]
            pts = p1
        counts.append(len(pts))
        if len(pts) < settings.max_features:
            pts = _refilled(image, pts, settings)
        prev = image
        times.append((time.perf_counter() - start, time.process_time() - cpu))
    return np.array(times), np.array(counts)


#: Issue 22's textbook loop: Lucas-Kanade window and levels, forward-backward bound (px),
#: the RANSAC bound (px) and the count below which it tops up (of FEATURES).
FB_WINDOW_PX, FB_LEVELS, FB_BOUND_PX, FB_RANSAC_PX, FB_REFILL_BELOW = 21, 5, 1.0, 1.0, 100


def run_bare_fb(camera, images, settings: TrackerSettings) -> tuple[np.ndarray, np.ndarray]:
    """Issue 22's loop: KLT forward and back, five-point RANSAC, top up below 100."""
    lk = {"winSize": (FB_WINDOW_PX, FB_WINDOW_PX), "maxLevel": FB_LEVELS,
          "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                       settings.klt_iterations, settings.klt_epsilon_px)}
    K = camera.K
    prev, pts = None, np.zeros((0, 1, 2), np.float32)
    times, counts = [], []
    for image in images:
        start, cpu = time.perf_counter(), time.process_time()
        if prev is not None and len(pts):
            nxt, status, _ = cv2.calcOpticalFlowPyrLK(prev, image, pts, None, **lk)
            back, status_back, _ = cv2.calcOpticalFlowPyrLK(image, prev, nxt, None, **lk)
            fb_px = np.linalg.norm((back - pts).reshape(-1, 2), axis=1)
            ok = (status.ravel() == 1) & (status_back.ravel() == 1) & (fb_px < FB_BOUND_PX)
            p0, p1 = pts[ok], nxt[ok]
            if len(p0) >= 8:
                _, inliers = cv2.findEssentialMat(p0, p1, K, cv2.RANSAC,
                                                  settings.ransac_confidence, FB_RANSAC_PX)
                if inliers is not None:
                    p1 = p1[inliers.ravel() == 1]
            pts = p1
        counts.append(len(pts))
        if len(pts) < FB_REFILL_BELOW:
            pts = _refilled(image, pts, settings)
        prev = image
        times.append((time.perf_counter() - start, time.process_time() - cpu))
    return np.array(times), np.array(counts)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--speed-only", action="store_true",
                        help="time the clean flight only (no accuracy, no other flights)")
    args = parser.parse_args(argv)

    result = simulate(SimulationSettings(frames=args.frames, resolution_px=(640, 480),
                                         seed=args.seed))
    camera = result.log.config.camera.camera
    Renderer(result.terrain, camera).render(result.world_T_cam[0])  # compile / cache load
    clean = render_flight(result, RenderSettings(seed=args.seed))
    print(f"rendering: {clean.seconds_per_frame:.3f} s per 640x480 frame "
          f"({args.frames} frames)")
    rotations = camera_rotations_from_imu(result.log)
    settings = TrackerSettings(max_features=FEATURES)

    no_rotations = [None] * len(clean.images)
    times: dict[str, list[np.ndarray]] = {"tracker": [], "bare": [], "tracker_no_imu": [],
                                          "bare_fb": []}
    for r in range(args.repeats):
        order = list(times) if r % 2 == 0 else list(times)[::-1]
        for which in order:
            if which == "tracker":
                outputs, t = run_tracker(camera, clean.images, rotations, settings)
            elif which == "tracker_no_imu":
                outputs_no_imu, t = run_tracker(camera, clean.images, no_rotations, settings)
            elif which == "bare":
                t, counts = run_bare(camera, clean.images, settings)
            else:
                t, counts_fb = run_bare_fb(camera, clean.images, settings)
            times[which].append(1e3 * t[1:])
    # (frames x (wall, CPU)) over the passes: medians of each
    medians = {k: float(np.median(np.concatenate(v)[:, 0])) for k, v in times.items()}
    cpu = {k: float(np.median(np.concatenate(v)[:, 1])) for k, v in times.items()}
    tracker_median, bare_median = medians["tracker"], medians["bare"]
    live = np.array([o.track_id.size for o in outputs])
    kept = np.array([o.counts()["tracked"] for o in outputs[1:]])
    print(f"tracking (median per frame, {args.repeats} passes each, alternating): tracker "
          f"{tracker_median:.2f} ms ({live.mean():.0f} features live, {kept.mean():.0f} "
          f"matched per pair), bare KLT + RANSAC {bare_median:.2f} ms ({counts.mean():.0f} "
          f"features live); ratio {tracker_median / bare_median:.2f}")
    kept_no_imu = np.array([o.counts()["tracked"] for o in outputs_no_imu[1:]])
    ratio_fb = medians["tracker_no_imu"] / medians["bare_fb"]
    print(f"issue 22's comparison: tracker without the IMU {medians['tracker_no_imu']:.2f} ms "
          f"({kept_no_imu.mean():.0f} matched per pair), KLT forward and back 21x21/5 + "
          f"RANSAC, refilled below {FB_REFILL_BELOW} {medians['bare_fb']:.2f} ms "
          f"({counts_fb[1:].mean():.0f} kept per pair); ratio {ratio_fb:.2f}")
    print(f"CPU time (process, all threads; steadier than wall time on a loaded machine): "
          f"tracker {cpu['tracker']:.2f} ms, bare {cpu['bare']:.2f} ms, ratio "
          f"{cpu['tracker'] / cpu['bare']:.2f}; tracker without the IMU "
          f"{cpu['tracker_no_imu']:.2f} ms, issue 22's loop {cpu['bare_fb']:.2f} ms, ratio "
          f"{cpu['tracker_no_imu'] / cpu['bare_fb']:.2f}")

    summary = {"render_s_per_frame": clean.seconds_per_frame, "tracker_ms": tracker_median,
               "bare_ms": bare_median, "ratio": tracker_median / bare_median,
               "tracker_no_imu_ms": medians["tracker_no_imu"], "bare_fb_ms": medians["bare_fb"],
               "ratio_no_imu_fb": ratio_fb, "cpu_ms": cpu}
    line = (f"render_s_per_frame={clean.seconds_per_frame:.3f} tracker_ms={tracker_median:.2f} "
            f"bare_ms={bare_median:.2f} ratio={tracker_median / bare_median:.2f} "
            f"tracker_no_imu_ms={medians['tracker_no_imu']:.2f} "
            f"bare_fb_ms={medians['bare_fb']:.2f} ratio_no_imu_fb={ratio_fb:.2f} "
            f"tracker_cpu_ms={cpu['tracker']:.2f} bare_cpu_ms={cpu['bare']:.2f} "
            f"tracker_no_imu_cpu_ms={cpu['tracker_no_imu']:.2f} "
            f"bare_fb_cpu_ms={cpu['bare_fb']:.2f}")
    if args.speed_only:
        print(line)
        return summary
    accuracy = {"clean": match_errors(result.terrain, camera, result.world_T_cam,
                                      outputs).to_dict()}
    jittered = render_flight(result, RenderSettings(seed=args.seed, exposure_jitter=0.1,
                                                    motion_blur_px=1.0))
    outputs_j, _ = run_tracker(camera, jittered.images, rotations, settings)
    accuracy["jitter_10pct_blur_1px"] = match_errors(result.terrain, camera, result.world_T_cam,
                                                     outputs_j).to_dict()
    # A harder flight: 600 m over the same 300 m relief (more parallax and occlusion,
    # ~185 px of flow per frame), 4 DN of sensor noise, jitter and blur.
    low = simulate(SimulationSettings(frames=args.frames, resolution_px=(640, 480),
                                      seed=args.seed, altitude_m=600.0))
    hard = render_flight(low, RenderSettings(seed=args.seed, noise_sigma_dn=4.0,
                                             exposure_jitter=0.1, motion_blur_px=1.0))
    outputs_h, _ = run_tracker(camera, hard.images, camera_rotations_from_imu(low.log), settings)
    accuracy["alt_600m_noise_4dn_jitter_blur"] = match_errors(
        low.terrain, camera, low.world_T_cam, outputs_h).to_dict()
    print("accuracy against the renderer's truth:")
    print(json.dumps(accuracy, indent=2))
    summary["accuracy"] = accuracy
    print(line)
    return summary


if __name__ == "__main__":
    main()
