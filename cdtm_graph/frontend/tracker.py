"""Feature tracking over a downward camera's images: KLT with checks, one image at a time.

:class:`FeatureTracker` takes the images of a flight in order and returns, for each, the
tracks seen in it (``track_id``, pixel). Per image:

1. **Exposure.** The image is mapped to a fixed mean and contrast (an affine photometric
   normalization), so a global exposure change between frames does not bias the
   Lucas-Kanade sum of squared differences, which has no gain term.
2. **Prediction.** Each live feature's position is predicted through the camera model:
   its ray rotated by the camera rotation between the frames, when one is given (the
   IMU's preintegrated gyro: :func:`camera_rotations_from_imu`), then shifted by the
   median translational flow of the previous frame pair. Lucas-Kanade starts there, so
   the pyramid has to absorb only the prediction error, not a 100 px flight-direction
   flow or a fast roll.
3. **Pyramidal Lucas-Kanade** (``cv2.calcOpticalFlowPyrLK``) with a **forward-backward
   check**: tracked back into the previous image, a feature must land within
   ``forward_backward_px`` of where it started (only the forward pass's matches are
   tracked back: the others are lost whatever the backward pass says). Each call builds
   its own pyramids: OpenCV's Python binding takes no precomputed ones
   (opencv/opencv#4777; still so in OpenCV 5.0).
4. **Geometric verification** of the frame pair: matches are turned into rays by the
   camera model (so the lens model, whatever it is, is undone there) and fitted by
   RANSAC: the translation direction given the IMU rotation
   (:func:`~cdtm_graph.frontend.two_view.fit_translation_given_rotation`), or the
   five-point essential matrix without one or when the IMU's rotation explains too few
   matches (:func:`~cdtm_graph.frontend.two_view.fit_essential`: judged on the fitted
   matrix, so a focal length known only roughly and a near-planar scene far away keep
   their matches). Matches off their epipolar geometry by more than
   ``epipolar_threshold_px`` (over the focal length: an angle) end. docs/frontend.md
   says how each check depends on the intrinsics.
5. **Replenishment** with spatial bucketing: the image is divided into a grid of cells,
   each with a share of ``max_features``; Shi-Tomasi corners
   (``cv2.goodFeaturesToTrack``) are added, strongest first, to the cells below their
   share, away from live features. Corners whose predicted position in the next image
   falls outside it are not started (they would be single sightings).

Tracks are never revived: a feature that fails a check ends, and the ground it showed may
start a new track. The tracker keeps nothing of earlier images but the previous one.

The core of the package: this module imports nothing from the simulation harness.
"""

from __future__ import annotations

import enum
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from cdtm_graph.errors import ImageError
from cdtm_graph.frontend.settings import Replenishment, TrackerSettings
from cdtm_graph.frontend.two_view import (
    MIN_MATCHES,
    EpipolarFit,
    FitMethod,
    fit_essential,
    fit_translation_given_rotation,
)

logger = logging.getLogger(__name__)

__all__ = [
    "CameraModel",
    "FeatureTracker",
    "FrameTracks",
    "ImageError",
    "MatchStatus",
    "Replenishment",
    "TrackerSettings",
]


class CameraModel(Protocol):
    """What the tracker needs of a camera model (:class:`~cdtm_graph.camera.PinholeCamera`
    or any other model with the same ray functions)."""

    @property
    def width(self) -> int: ...

    @property
    def height(self) -> int: ...

    @property
    def fx(self) -> float: ...

    @property
    def fy(self) -> float: ...

    def pixels_to_rays(self, uv: np.ndarray) -> np.ndarray: ...

    def rays_to_pixels(self, rays_cam: np.ndarray) -> np.ndarray: ...


class MatchStatus(enum.IntEnum):
    """What happened to a live feature between the previous image and this one."""

    TRACKED = 0           # passed every check
    LOST = 1              # Lucas-Kanade failed (flat patch, no convergence, unusable ray)
    FORWARD_BACKWARD = 2  # tracked back, it did not return to where it started
    LEFT_IMAGE = 3        # left the image (or came within the border of it)
    EPIPOLAR = 4          # off its epipolar plane (or behind a camera)


@dataclass(frozen=True)
class FrameTracks:
    """The tracker's output for one image.

    Attributes:
        frame: 0-based index of the image in the sequence.
        track_id: (n,) ids of the features seen in this image, sorted.
        uv_px: (n, 2) their pixels (OpenCV convention: (0, 0) is the centre of the
            top-left pixel; distorted, as in the image).
        is_new: (n,) True for features started in this image.
        prev_track_id: (m,) the features live after the previous image (all of them) ...
        prev_uv_px: (m, 2) ... their pixels there,
        matched_uv_px: (m, 2) ... where Lucas-Kanade put them in this image (NaN: lost),
        status: (m,) ... and their :class:`MatchStatus` values (diagnostics: the matches
            before and after each check).
        fit: the epipolar fit of the frame pair (None for the first image or too few matches).
        seconds: wall time of this image.
    """

    frame: int
    track_id: np.ndarray
    uv_px: np.ndarray
    is_new: np.ndarray
    prev_track_id: np.ndarray
    prev_uv_px: np.ndarray
    matched_uv_px: np.ndarray
    status: np.ndarray
    fit: EpipolarFit | None
    seconds: float = field(default=0.0)

    def counts(self) -> dict[str, int]:
        """Number of previous features per :class:`MatchStatus` and of new features."""
        out = {s.name.lower(): int(np.sum(self.status == s)) for s in MatchStatus}
        out["new"] = int(self.is_new.sum())
        return out


#: The global shift of the first frame pair is found on images halved this many times.
PHASE_CORRELATION_REDUCTION = 2
#: ... and trusted when the normalized correlation peak reaches this (noise: ~0.01-0.03).
PHASE_CORRELATION_MIN_RESPONSE = 0.05

#: Exposure normalization targets (8-bit): mid-grey mean, a contrast that uses the range
#: without clipping much of a textured image.
_NORMALIZED_MEAN = 128.0
_NORMALIZED_STD = 48.0


class FeatureTracker:
    """KLT feature tracker fed one image at a time (module docstring).

    Example::

        tracker = FeatureTracker(flight.config.camera.camera)
        for k, image in enumerate(images):
            out = tracker.track(image, cam_prev_R_cam=rotations[k])  # None for k = 0
            smoother.add_frame(t_ns[k], out.track_id, out.uv_px, imu_k)

    Args:
        camera: the camera model of the images.
        settings: tracker settings.
    """

    def __init__(self, camera: CameraModel, settings: TrackerSettings | None = None):
        self.camera = camera
        self.settings = settings or TrackerSettings()
        s = self.settings
        self._rng = np.random.default_rng(np.random.SeedSequence([s.seed, 0x7AC4]))
        self._window = (s.window_px, s.window_px)
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, s.klt_iterations,
                          s.klt_epsilon_px)
        self._focal_px = math.sqrt(camera.fx * camera.fy)
        self._frame = 0
        self._previous: np.ndarray | None = None  # the last image, normalized
        self._ids = np.zeros(0, dtype=np.int64)
        self._uv = np.zeros((0, 2), dtype=np.float32)
        self._next_id = 0
        self._shift_px = np.zeros(2)  # median translational flow of the last pair
        self._has_shift = False

    @property
    def frame(self) -> int:
        """Index the next image will get."""
        return self._frame

    def track(self, image: np.ndarray, cam_prev_R_cam: np.ndarray | None = None) -> FrameTracks:
        """Track the live features into the next image and replenish them.

        Args:
            image: (height, width) 8- or 16-bit grayscale, or (height, width, 3) BGR.
            cam_prev_R_cam: (3, 3) rotation of this image's camera in the previous one's
                (``x_prev = R x_this`` for directions), e.g. from the IMU; None: unknown
                (the five-point essential matrix verifies the matches).

        Returns:
            The features seen in this image and what happened to the previous ones.

        Raises:
            ImageError: the image has the wrong size or type.
        """
        start = time.perf_counter()
        gray = self._normalized(image)
        R = None if cam_prev_R_cam is None else np.asarray(cam_prev_R_cam, dtype=float)
        if R is not None and R.shape != (3, 3):
            raise ValueError(f"cam_prev_R_cam has shape {R.shape}, expected (3, 3)")
        prev_ids, prev_uv = self._ids, self._uv.astype(float)
        matched = np.full((prev_ids.size, 2), np.nan)
        status = np.zeros(prev_ids.size, dtype=np.int8)
        fit = None
        if self._previous is not None and prev_ids.size:
            matched, status, fit = self._match(gray, prev_uv, R)
        kept = status == MatchStatus.TRACKED
        ids, uv = prev_ids[kept], matched[kept]
        new_uv = self._detect(gray, uv)
        new_ids = np.arange(self._next_id, self._next_id + new_uv.shape[0], dtype=np.int64)
        self._next_id += new_uv.shape[0]
        self._ids = np.concatenate([ids, new_ids])
        self._uv = np.concatenate([uv, new_uv]).astype(np.float32)
        self._previous = gray
        frame = self._frame
        self._frame += 1
        is_new = np.concatenate([np.zeros(ids.size, bool), np.ones(new_ids.size, bool)])
        return FrameTracks(frame, self._ids.copy(), self._uv.astype(float), is_new, prev_ids,
                           prev_uv, matched, status, fit, time.perf_counter() - start)

    # -- steps ------------------------------------------------------------------------

    def _normalized(self, image: np.ndarray) -> np.ndarray:
        """8-bit grayscale with a fixed mean and contrast (or as given, 8-bit)."""
        img = np.asarray(image)
        cam = self.camera
        if img.ndim == 3 and img.shape[2] in (3, 4):
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3
                               else cv2.COLOR_BGRA2GRAY)
        if img.ndim != 2 or img.shape != (cam.height, cam.width):
            raise ImageError(f"image of shape {img.shape}, expected {cam.height} rows x "
                             f"{cam.width} columns (the camera's resolution)")
        if img.dtype not in (np.uint8, np.uint16):
            raise ImageError(f"image of type {img.dtype}, expected 8- or 16-bit integers")
        if not self.settings.normalize_exposure:
            return img if img.dtype == np.uint8 else (img >> 8).astype(np.uint8)
        mean, std = cv2.meanStdDev(img)
        alpha = _NORMALIZED_STD / max(float(std[0, 0]), 1e-6)
        beta = _NORMALIZED_MEAN - alpha * float(mean[0, 0])
        return cv2.addWeighted(img, alpha, img, 0.0, beta, dtype=cv2.CV_8U)

    def _predict(self, prev_uv: np.ndarray, R: np.ndarray | None) -> np.ndarray:
        """Where the features should be in the new image: rotated, then shifted."""
        predicted = prev_uv.copy()
        if R is not None:
            rays = self.camera.pixels_to_rays(prev_uv)
            rotated = self.camera.rays_to_pixels(rays @ R)  # R^T q for each row q
            ok = np.isfinite(rotated).all(axis=1)
            predicted[ok] = rotated[ok]
        return predicted

    def _match(self, gray: np.ndarray, prev_uv: np.ndarray, R: np.ndarray | None
               ) -> tuple[np.ndarray, np.ndarray, EpipolarFit | None]:
        s = self.settings
        cam = self.camera
        previous = self._previous
        assert previous is not None  # (only called with a previous image)
        rotated = self._predict(prev_uv, R)
        if not self._has_shift:  # no flow known yet: the images' global shift ...
            shift = self._global_shift(gray)
            # ... holds the rotation's flow too: only the rest is added to the rotated
            # positions (counted twice, a 1.2 deg turn read at twice the focal length put
            # the first pair's prediction 90 px off)
            self._shift_px = (np.zeros(2) if shift is None else
                              shift - np.median(rotated - prev_uv, axis=0))
        guess = (rotated + self._shift_px).astype(np.float32)
        p0 = prev_uv.astype(np.float32)
        # (the minimum eigenvalue as the error: OpenCV skips the window's residual, which
        # is not used; positions and status are the same)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW | cv2.OPTFLOW_LK_GET_MIN_EIGENVALS
        p1, st, _ = cv2.calcOpticalFlowPyrLK(previous, gray, p0, guess.copy(),
                                             winSize=self._window, maxLevel=s.pyramid_levels,
                                             criteria=self._criteria, flags=flags)
        matched = p1.astype(float).reshape(-1, 2)
        forward = (st.ravel() == 1) & np.isfinite(matched).all(axis=1)
        # Tracked back: only what the forward pass kept (the rest is lost whatever the
        # backward pass does: ~1 in 5 features a frame, mostly leaving the image).
        # Lucas-Kanade tracks each point alone: the others' results do not change.
        back_rows = np.flatnonzero(forward)
        back = np.full((prev_uv.shape[0], 2), np.nan, np.float32)
        st_back = np.zeros(prev_uv.shape[0], np.uint8)
        if back_rows.size:
            back_p, back_st, _ = cv2.calcOpticalFlowPyrLK(
                gray, previous, p1[back_rows], p0[back_rows], winSize=self._window,
                maxLevel=s.pyramid_levels, criteria=self._criteria, flags=flags)
            back[back_rows], st_back[back_rows] = back_p.reshape(-1, 2), back_st.ravel()
        status = np.full(prev_uv.shape[0], MatchStatus.TRACKED, dtype=np.int8)
        lost = ~forward | (st_back == 0)
        fb_error = np.linalg.norm(back - p0, axis=1)
        status[~(fb_error <= s.forward_backward_px)] = MatchStatus.FORWARD_BACKWARD
        status[lost] = MatchStatus.LOST
        # Lucas-Kanade loses what leaves the image too: judged by the prediction then.
        status[~self._inside(np.where(lost[:, None], guess, matched))] = MatchStatus.LEFT_IMAGE
        matched[lost] = np.nan

        candidates = np.flatnonzero(status == MatchStatus.TRACKED)
        rays_prev = cam.pixels_to_rays(prev_uv[candidates])
        rays_new = cam.pixels_to_rays(matched[candidates])
        usable = np.isfinite(rays_prev).all(axis=1) & np.isfinite(rays_new).all(axis=1)
        status[candidates[~usable]] = MatchStatus.LOST
        candidates, rays_prev, rays_new = (candidates[usable], rays_prev[usable],
                                           rays_new[usable])
        fit = self._verify(rays_prev, rays_new, R)
        status[candidates[~fit.inliers]] = MatchStatus.EPIPOLAR

        good = status == MatchStatus.TRACKED
        if good.sum() >= MIN_MATCHES:  # the translational flow, for the next prediction
            self._shift_px = np.asarray(np.median(matched[good] - rotated[good], axis=0), float)
            self._has_shift = True
        else:  # tracking broke down: find the flow by phase correlation next time
            self._has_shift = False
        return matched, status, fit if fit.method is not FitMethod.NONE else None

    def _global_shift(self, gray: np.ndarray) -> np.ndarray | None:
        """Translation of the whole image since the previous one (phase correlation).

        On images reduced ``2**PHASE_CORRELATION_REDUCTION`` times (the flow of a few
        hundred pixels fits and it costs ~1 ms); None when the correlation peak is weak.
        """
        assert self._previous is not None
        a, b = self._previous, gray
        for _ in range(PHASE_CORRELATION_REDUCTION):
            a, b = cv2.pyrDown(a), cv2.pyrDown(b)
        a, b = a.astype(np.float32), b.astype(np.float32)
        window = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_32F)
        (du, dv), response = cv2.phaseCorrelate(a, b, window)
        if not response >= PHASE_CORRELATION_MIN_RESPONSE:
            return None
        return np.array([du, dv]) * 2.0 ** PHASE_CORRELATION_REDUCTION

    def _inside(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """(N,) whether pixels lie at least ``border_px + margin_px`` inside the image."""
        b = self.settings.border_px + margin_px
        cam = self.camera
        return ((uv[:, 0] >= b) & (uv[:, 0] <= cam.width - 1 - b)
                & (uv[:, 1] >= b) & (uv[:, 1] <= cam.height - 1 - b))

    def _verify(self, rays_prev: np.ndarray, rays_new: np.ndarray,
                R: np.ndarray | None) -> EpipolarFit:
        s = self.settings
        threshold_rad = s.epipolar_threshold_px / self._focal_px
        if rays_prev.shape[0] < MIN_MATCHES:
            return fit_essential(rays_prev, rays_new, threshold_rad)  # NONE: too few
        if R is not None:
            fit = fit_translation_given_rotation(rays_prev, rays_new, R, threshold_rad,
                                                 self._rng, s.ransac_confidence)
            if fit.inlier_fraction >= s.min_rotation_inlier_fraction:
                return fit
            free = fit_essential(rays_prev, rays_new, threshold_rad, s.ransac_confidence)
            logger.info("frame %d: the rotation prior explains %.0f%% of the matches, the "
                        "five-point fit %.0f%%", self._frame, 100 * fit.inlier_fraction,
                        100 * free.inlier_fraction)
            return free if free.inliers.sum() > fit.inliers.sum() else fit
        return fit_essential(rays_prev, rays_new, threshold_rad, s.ransac_confidence)

    def _detect(self, gray: np.ndarray, live_uv: np.ndarray) -> np.ndarray:
        """New corners for the cells below their share, away from live features.

        The emptiest cells are served first (a corner's fill level is its cell's count
        with it), per cell the strongest corners first. With
        ``Replenishment.WHOLE_IMAGE``, Shi-Tomasi corners (``cv2.goodFeaturesToTrack``)
        of the whole image, the full cells masked. With ``Replenishment.NEEDED_CELLS``,
        corners are looked for only in the cells at or below the fill level that
        ``need`` corners reach when every cell has enough, and one level more at a time
        when they do not; per cell, on the cell and the pixels around it the filters
        reach (so the whole image's eigenvalues), then the whole image's rules over the
        cells looked at: the quality bound relative to the strongest corner, and
        ``min_distance_px`` across cell borders (the weaker goes). Issue 22: the
        whole-image detection every frame is about half of the tracker's time.
        """
        s = self.settings
        cam = self.camera
        need = s.max_features - live_uv.shape[0]
        if need <= 0:
            return np.zeros((0, 2))
        per_cell = math.ceil(s.max_features / s.cells)
        occupied = np.bincount(self._cell_of(live_uv), minlength=s.cells)
        mask = np.zeros((cam.height, cam.width), np.uint8)
        b = int(math.ceil(s.border_px))
        mask[b:cam.height - b, b:cam.width - b] = 255
        radius = int(math.ceil(s.min_distance_px))
        # one OpenCV call per feature: 0.1 ms for 115 at 640x480 over Python ints (0.3 ms
        # unpacking numpy rows), a dilation 1.9 ms
        for u, v in np.rint(live_uv).astype(int).tolist():
            cv2.circle(mask, (u, v), radius, 0, -1)
        deficit = per_cell - occupied  # (cells at their share: 0)
        if s.replenishment is Replenishment.WHOLE_IMAGE:
            cell_w, cell_h = cam.width / s.grid_cols, cam.height / s.grid_rows
            for c in np.flatnonzero(deficit <= 0):  # full cells: no detection there at all
                x0, y0 = int((c % s.grid_cols) * cell_w), int((c // s.grid_cols) * cell_h)
                mask[y0:int(y0 + cell_h + 1), x0:int(x0 + cell_w + 1)] = 0
            corners = cv2.goodFeaturesToTrack(gray, maxCorners=4 * s.max_features,
                                              qualityLevel=s.quality_level,
                                              minDistance=s.min_distance_px, mask=mask,
                                              blockSize=s.block_size_px)
            uv = np.zeros((0, 2)) if corners is None else corners.reshape(-1, 2).astype(float)
            return self._fill(uv, occupied, per_cell - 1)[:need]
        # the fill level the need reaches if every cell has corners enough
        level = 0
        while (level < per_cell - 1
               and np.clip(level + 1 - occupied, 0, deficit).sum() < need):
            level += 1
        found_uv, found_quality = [], []
        looked = np.zeros(s.cells, bool)
        while True:
            to_look = np.flatnonzero((occupied <= level) & (deficit > 0) & ~looked)
            looked[to_look] = True
            for cell in to_look.tolist():
                uv, quality = self._cell_corners(gray, mask, cell, 3 * per_cell)
                found_uv.append(uv)
                found_quality.append(quality)
            chosen = self._fill(self._spaced(found_uv, found_quality), occupied, level)
            if chosen.shape[0] >= need or level >= per_cell - 1:
                return chosen[:need]
            level += 1

    def _cell_of(self, uv: np.ndarray) -> np.ndarray:
        """(N,) grid cell of each pixel (row-major)."""
        s = self.settings
        cell_w, cell_h = self.camera.width / s.grid_cols, self.camera.height / s.grid_rows
        col = np.clip((uv[:, 0] + 0.5) // cell_w, 0, s.grid_cols - 1).astype(np.int64)
        row = np.clip((uv[:, 1] + 0.5) // cell_h, 0, s.grid_rows - 1).astype(np.int64)
        return row * s.grid_cols + col

    def _cell_corners(self, gray: np.ndarray, mask: np.ndarray, cell: int,
                      max_corners: int) -> tuple[np.ndarray, np.ndarray]:
        """(n, 2) Shi-Tomasi corners of one grid cell where ``mask`` is set, strongest
        first, and their (n,) minimum eigenvalues. The cell's pixels are those
        :meth:`_cell_of` puts in it; the image is read with the rows and columns around
        them that the Sobel derivative, the block and the 3x3 local-maximum test reach."""
        s = self.settings
        height, width = gray.shape
        row, col = divmod(cell, s.grid_cols)
        cell_w, cell_h = width / s.grid_cols, height / s.grid_rows
        x0, x1 = (min(max(math.ceil(k * cell_w - 0.5), 0), width) for k in (col, col + 1))
        y0, y1 = (min(max(math.ceil(k * cell_h - 0.5), 0), height) for k in (row, row + 1))
        if col == s.grid_cols - 1:
            x1 = width
        if row == s.grid_rows - 1:
            y1 = height
        margin = 1 + s.block_size_px // 2 + 1 + 1
        left, top = max(x0 - margin, 0), max(y0 - margin, 0)
        right, bottom = min(x1 + margin, width), min(y1 + margin, height)
        sub_mask = np.zeros((bottom - top, right - left), np.uint8)
        sub_mask[y0 - top:y1 - top, x0 - left:x1 - left] = mask[y0:y1, x0:x1]
        if not sub_mask.any():
            return np.zeros((0, 2)), np.zeros(0)
        corners, quality = cv2.goodFeaturesToTrackWithQuality(
            gray[top:bottom, left:right], max_corners, s.quality_level, s.min_distance_px,
            sub_mask, blockSize=s.block_size_px)
        if corners is None or corners.size == 0:
            return np.zeros((0, 2)), np.zeros(0)
        return (corners.reshape(-1, 2).astype(float) + (left, top),
                quality.ravel().astype(float))

    def _spaced(self, found_uv: list[np.ndarray], found_quality: list[np.ndarray]
                ) -> np.ndarray:
        """(n, 2) the corners of the cells looked at, strongest first, the whole image's
        rules applied: the quality bound relative to the strongest, ``min_distance_px``
        across cell borders (the weaker goes; within a cell OpenCV kept it)."""
        s = self.settings
        uv, quality = np.concatenate(found_uv), np.concatenate(found_quality)
        if uv.shape[0] == 0:
            return uv
        order = np.argsort(-quality, kind="stable")
        uv, quality = uv[order], quality[order]
        keep = quality > s.quality_level * quality[0]
        # only corners that near a cell border can clash
        cell_w, cell_h = self.camera.width / s.grid_cols, self.camera.height / s.grid_rows
        du = np.abs((uv[:, 0] + 0.5 + cell_w / 2) % cell_w - cell_w / 2)
        dv = np.abs((uv[:, 1] + 0.5 + cell_h / 2) % cell_h - cell_h / 2)
        near = np.flatnonzero(keep & ((du < s.min_distance_px) | (dv < s.min_distance_px)))
        min_d2 = s.min_distance_px ** 2
        kept_near: list[int] = []
        for i in near.tolist():
            if kept_near:
                d = uv[kept_near] - uv[i]
                if np.any(d[:, 0] ** 2 + d[:, 1] ** 2 < min_d2):
                    keep[i] = False
                    continue
            kept_near.append(i)
        return uv[keep]

    def _fill(self, uv: np.ndarray, occupied: np.ndarray, level: int) -> np.ndarray:
        """Of corners ``uv`` (strongest first), those that fill the cells up to fill level
        ``level``: per cell strongest first, the emptiest cells first."""
        if self._has_shift:  # predicted to leave the image before the next one: skip
            uv = uv[self._inside(uv + self._shift_px, margin_px=1.0)]
        # A corner's fill level is the cell's count with it, so every cell gets one
        # before any gets two more than the others.
        cell = self._cell_of(uv)
        order = np.argsort(cell, kind="stable")
        sorted_cell = cell[order]
        first = np.searchsorted(sorted_cell, sorted_cell, side="left")
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size) - first
        fill = occupied[cell] + rank
        keep = np.flatnonzero(fill <= level)
        keep = keep[np.argsort(fill[keep], kind="stable")]
        return uv[keep]
