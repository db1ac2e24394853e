"""A whole flight log's images to feature tracks (``cdtm track``), with a report.

:func:`track_log` reads the images named in frames.csv in order, feeds them to a
:class:`~cdtm_graph.frontend.tracker.FeatureTracker` with the camera rotation between
consecutive frames from the log's IMU (:func:`camera_rotations_from_imu`), and returns
the tracks as :class:`~cdtm_graph.flightlog.Tracks` (rows sorted by frame, then track id;
tracks seen only once are left out: they tie no frames together) with a
:class:`TrackingReport`. Writing tracks.csv is the caller's (the CLI's) business.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import gtsam
import numpy as np

from cdtm_graph.errors import CdtmError, FlightLogError, ImageError, SolverError, why_not_a_file
from cdtm_graph.flightlog import FRAMES_CSV, FlightLog, Tracks
from cdtm_graph.frontend.tracker import FeatureTracker, FrameTracks, MatchStatus, TrackerSettings
from cdtm_graph.imu import ImuIntervals, SampleHold, initial_bias

logger = logging.getLogger(__name__)

__all__ = ["WEAK_PAIR_SHARE", "TrackingReport", "TrackingResult", "camera_rotation_from_imu",
           "camera_rotations_from_imu", "load_image", "track_log"]


def load_image(path: Path) -> np.ndarray:
    """An image file as stored (8- or 16-bit, gray or colour), unchanged.

    Raises:
        ImageError: the file is missing or not an image OpenCV can read.
    """
    if not path.is_file():
        raise ImageError(f"{path}: image file {why_not_a_file(path)}")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageError(f"{path}: cannot be read as an image, expected a PNG, JPEG, TIFF "
                         "or another format OpenCV reads")
    return image


def camera_rotation_from_imu(intervals: ImuIntervals, body_T_cam: np.ndarray, t0_ns: int,
                             t1_ns: int, bias: gtsam.imuBias.ConstantBias) -> np.ndarray:
    """Rotation of the camera at ``t1`` in the camera at ``t0``, from the gyro.

    The gyro is preintegrated over the interval (:class:`~cdtm_graph.imu.ImuIntervals`,
    linearized at ``bias``) and turned into the camera frame through the mounting:
    ``cam0_R_cam1 = cam_R_body  body0_R_body1  body_R_cam``.

    Raises:
        SolverError: the IMU samples do not cover the interval.
    """
    pim = intervals.new_preintegration(bias)  # the rotation only: no gravity to place
    intervals.integrate(pim, int(t0_ns), int(t1_ns))
    body_R_cam = np.asarray(body_T_cam, dtype=float)[:3, :3]
    return body_R_cam.T @ np.asarray(pim.deltaRij().matrix()) @ body_R_cam


def camera_rotations_from_imu(flight: FlightLog) -> list[np.ndarray | None]:
    """:func:`camera_rotation_from_imu` over every frame interval of a log.

    The gyro bias is the initial state's prior mean.

    Returns:
        K entries: None for the first frame and for intervals the IMU does not cover;
        (3, 3) ``cam_prev_R_cam`` otherwise.
    """
    config = flight.config
    intervals = ImuIntervals(config, flight.imu, SampleHold.MIDPOINT)
    bias = initial_bias(config.initial_state)
    t_ns = flight.frames.t_ns
    out: list[np.ndarray | None] = [None]
    for k in range(1, t_ns.size):
        try:
            out.append(camera_rotation_from_imu(intervals, config.camera.body_T_cam,
                                                int(t_ns[k - 1]), int(t_ns[k]), bias))
        except SolverError as exc:  # not covered: verify this pair without the prior
            logger.warning("frames %d-%d: no IMU rotation (%s)", k - 1, k, exc)
            out.append(None)
    return out


#: A frame pair keeping fewer features than this share of ``max_features`` is a weak pair
#: (50 of the default 200): the smoother has little to tie the two frames with. On the
#: rendered test flights every pair keeps more than half, on the real CLIF frames 91-99 %
#: (2026-11-27).
WEAK_PAIR_SHARE = 0.25
#: Weak pairs named in the warning line; the rest are counted ("and N more").
WEAK_PAIRS_NAMED = 8


@dataclass(frozen=True)
class TrackingReport:
    """What the tracker did over a log.

    Attributes:
        n_frames: images tracked.
        n_tracks: tracks written (seen in at least two frames).
        n_single_sightings: features seen in one frame only (not written).
        features_per_frame: (K,) features written per frame.
        pairs_per_frame: (K-1,) features written in both frame k and k+1.
        track_lengths: (n_tracks,) frames each written track spans (sightings).
        rejected: previous features ended per reason (:class:`MatchStatus` names but
            ``tracked``), summed over the log.
        fits: frame pairs per epipolar fit method (``rotation_prior``, ``essential``,
            ``none``).
        imu_rotations: frame pairs that had an IMU rotation.
        seconds_per_frame: median tracking time per image (image reading excluded).
        ended_per_pair: previous features ended between frame k and k+1, per reason
            (:class:`MatchStatus` names but ``tracked``), each (K-1,).
        weak_pair_features: pairs keeping fewer features than this are weak
            (:meth:`weak_pairs`; ``WEAK_PAIR_SHARE`` of ``max_features``).
    """

    n_frames: int
    n_tracks: int
    n_single_sightings: int
    features_per_frame: np.ndarray
    pairs_per_frame: np.ndarray
    track_lengths: np.ndarray
    rejected: dict[str, int]
    fits: dict[str, int]
    imu_rotations: int
    seconds_per_frame: float
    ended_per_pair: dict[str, np.ndarray]
    weak_pair_features: int

    def weak_pairs(self) -> np.ndarray:
        """Indices k of the weak frame pairs (k, k+1), ascending."""
        return np.flatnonzero(self.pairs_per_frame < self.weak_pair_features)

    def main_reason(self, k: int) -> tuple[str, int]:
        """The reason most features of pair (k, k+1) ended for, and how many ("", 0: none)."""
        reason, count = max(((name, int(v[k])) for name, v in self.ended_per_pair.items()),
                            key=lambda item: item[1], default=("", 0))
        return (reason, count) if count else ("", 0)

    def weak_pairs_warning(self) -> str | None:
        """One line naming the weak pairs (the first ``WEAK_PAIRS_NAMED``), or None."""
        weak = self.weak_pairs()
        if weak.size == 0:
            return None
        named = []
        for k in weak[:WEAK_PAIRS_NAMED]:
            reason, count = self.main_reason(int(k))
            why = f", {count} ended {reason.replace('_', '-')}" if count else ""
            named.append(f"{k}-{k + 1} ({self.pairs_per_frame[k]} kept{why})")
        more = f" and {weak.size - WEAK_PAIRS_NAMED} more" if weak.size > WEAK_PAIRS_NAMED else ""
        return (f"{weak.size} of {self.pairs_per_frame.size} frame pairs keep fewer than "
                f"{self.weak_pair_features} features: {', '.join(named)}{more}; expected "
                f"at least {self.weak_pair_features} per pair: the smoother has little to "
                "tie these frames with (wrong intrinsics? blur, cloud, water, too much "
                "motion?); per-pair counts and reasons are in the --report")

    def to_dict(self) -> dict:
        """Plain JSON-able summary."""
        lengths = self.track_lengths
        pairs = self.pairs_per_frame
        return {
            "frames": self.n_frames,
            "tracks": self.n_tracks,
            "single_sightings_dropped": self.n_single_sightings,
            "features_per_frame": _stats(self.features_per_frame),
            "pairs_per_frame": _stats(pairs),
            "track_length_frames": {**_stats(lengths),
                                    "median": float(np.median(lengths)) if lengths.size else 0.0},
            "rejected": dict(self.rejected),
            "epipolar_fits": dict(self.fits),
            "imu_rotations": self.imu_rotations,
            "seconds_per_frame_median": self.seconds_per_frame,
            "per_pair": {
                "features": [int(v) for v in pairs],
                "ended": {name: [int(v) for v in counts]
                          for name, counts in self.ended_per_pair.items()},
            },
            "weak_pairs": {
                "below_features": self.weak_pair_features,
                "pairs": [[int(k), int(k) + 1] for k in self.weak_pairs()],
            },
        }

    def summary(self) -> str:
        """A few lines for a terminal."""
        d = self.to_dict()
        pairs, lengths = d["pairs_per_frame"], d["track_length_frames"]
        rejected = ", ".join(f"{v} {k.replace('_', '-')}" for k, v in self.rejected.items())
        fits = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in self.fits.items() if v)
        return "\n".join([
            f"{self.n_frames} frames, {self.n_tracks} tracks ({self.n_single_sightings} "
            "single sightings dropped)",
            f"features per frame pair: min {pairs['min']}, mean {pairs['mean']:.0f}, max "
            f"{pairs['max']}",
            f"track length (frames): median {lengths['median']:.0f}, mean "
            f"{lengths['mean']:.1f}, max {lengths['max']}",
            f"ended: {rejected}",
            f"epipolar fits: {fits}; {1e3 * self.seconds_per_frame:.1f} ms per frame",
        ])


def _stats(values: np.ndarray) -> dict:
    if values.size == 0:
        return {"min": 0, "mean": 0.0, "max": 0}
    return {"min": int(values.min()), "mean": float(values.mean()), "max": int(values.max())}


@dataclass(frozen=True)
class TrackingResult:
    """Tracks of a log and the report.

    Attributes:
        tracks: the tracks (tracks.csv's rows).
        report: what happened.
        frames: per-image tracker output (diagnostics; ``track_id`` as the tracker
            numbered them, before renumbering and dropping single sightings).
    """

    tracks: Tracks
    report: TrackingReport
    frames: list[FrameTracks]


def track_log(flight: FlightLog, settings: TrackerSettings | None = None,
              use_imu: bool = True, images: list[np.ndarray] | None = None,
              progress: Callable[[int, int], None] | None = None) -> TrackingResult:
    """Track the features through a log's images.

    Args:
        flight: the log; frames.csv must name an image for every frame.
        settings: tracker settings.
        use_imu: predict and verify with the gyro's rotation (else the five-point fit).
        images: the images in memory (K of them) instead of reading the files.
        progress: called with (frames done, total) after each image.

    Returns:
        The tracks and the report.

    Raises:
        FlightLogError: a frame has no image.
        ImageError: an image is missing, unreadable or of the wrong size.
    """
    k_frames = len(flight.frames)
    if images is None:
        for k, name in enumerate(flight.frames.image):
            if not name:
                raise FlightLogError(f"{flight.root / FRAMES_CSV}: frame {k} has no image; "
                                     "expected an image path for every frame to track")
    elif len(images) != k_frames:
        raise CdtmError(f"{len(images)} images for {k_frames} frames, expected one per frame")
    camera = flight.config.camera.camera
    tracker = FeatureTracker(camera, settings)
    rotations = camera_rotations_from_imu(flight) if use_imu else [None] * k_frames
    outputs: list[FrameTracks] = []
    for k in range(k_frames):
        if images is None:
            path = flight.root / flight.frames.image[k]
            image = load_image(path)
        else:
            path, image = Path(f"<image {k}>"), images[k]
        try:
            outputs.append(tracker.track(image, rotations[k]))
        except ImageError as exc:
            raise ImageError(f"frame {k}: {path}: {exc}") from None
        if progress is not None:
            progress(k + 1, k_frames)
    weak = math.ceil(WEAK_PAIR_SHARE * tracker.settings.max_features)
    return _collect(outputs, sum(r is not None for r in rotations[1:]), weak)


def _collect(outputs: list[FrameTracks], imu_rotations: int,
             weak_pair_features: int) -> TrackingResult:
    """Rows of every frame, single sightings dropped, ids renumbered by first sighting."""
    frame = np.concatenate([np.full(o.track_id.size, o.frame, np.int64) for o in outputs])
    track_id = np.concatenate([o.track_id for o in outputs])
    uv = np.concatenate([o.uv_px for o in outputs])
    ids, first, counts = np.unique(track_id, return_index=True, return_counts=True)
    multi = counts >= 2
    # New ids 0, 1, ... in order of first sighting (the tracker's ids already are, but
    # dropping single sightings leaves gaps).
    order = np.argsort(first[multi], kind="stable")
    new_id = np.full(ids.size, -1, np.int64)
    new_id[np.flatnonzero(multi)[order]] = np.arange(order.size)
    renumbered = new_id[np.searchsorted(ids, track_id)]
    keep = renumbered >= 0
    frame, renumbered, uv = frame[keep], renumbered[keep], uv[keep]
    rows = np.lexsort((renumbered, frame))
    tracks = Tracks(frame[rows], renumbered[rows], uv[rows])

    k_frames = len(outputs)
    per_frame = np.bincount(tracks.frame, minlength=k_frames)
    pairs = np.zeros(max(k_frames - 1, 0), np.int64)
    rows_a, rows_b = tracks.pairs()
    consecutive = tracks.frame[rows_b] == tracks.frame[rows_a] + 1
    np.add.at(pairs, tracks.frame[rows_a][consecutive], 1)
    ended = {s.name.lower(): np.array([int(np.sum(o.status == s)) for o in outputs[1:]],
                                      np.int64)
             for s in MatchStatus if s is not MatchStatus.TRACKED}
    rejected = {name: int(counts.sum()) for name, counts in ended.items()}
    fits = {"rotation_prior": 0, "essential": 0, "none": 0}
    for o in outputs[1:]:
        fits[o.fit.method.value if o.fit is not None else "none"] += 1
    seconds = float(np.median([o.seconds for o in outputs])) if outputs else 0.0
    report = TrackingReport(
        n_frames=k_frames, n_tracks=int(multi.sum()), n_single_sightings=int((~multi).sum()),
        features_per_frame=per_frame, pairs_per_frame=pairs,
        track_lengths=counts[multi].astype(np.int64), rejected=rejected, fits=fits,
        imu_rotations=imu_rotations, seconds_per_frame=seconds, ended_per_pair=ended,
        weak_pair_features=weak_pair_features)
    return TrackingResult(tracks, report, outputs)
