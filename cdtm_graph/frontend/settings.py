"""Settings of the feature tracker, in a module that imports no numerics (``cdtm track
--help`` shows their defaults without loading OpenCV). Re-exported by
:mod:`~cdtm_graph.frontend.tracker`, which uses them.
"""

from __future__ import annotations

import enum
import math
import numbers
from dataclasses import dataclass

from cdtm_graph.errors import CdtmError


class Replenishment(enum.Enum):
    """Where new corners are looked for (``FeatureTracker._detect``)."""

    #: goodFeaturesToTrack over the whole image, the full cells masked.
    WHOLE_IMAGE = "whole_image"
    #: cell by cell, only in the cells the fill level of the need reaches (about half of
    #: them at 150 features over 8x6 cells): 0.86-0.90x the tracker's time per frame on
    #: the rendered 640x480 flights, 0.65x on the CLIF frames; the corners chosen are nearly
    #: all the whole image's (the rest differ next to the cells not looked at), and the
    #: benchmark's figures moved by up to 0.13 % (docs/frontend.md, 2026-11-27).
    NEEDED_CELLS = "needed_cells"


@dataclass(frozen=True)
class TrackerSettings:
    """Settings of :class:`FeatureTracker`.

    Attributes:
        max_features: live features kept per image (after replenishment).
        grid_cols, grid_rows: buckets of the spatial grid; each holds at most
            ``ceil(max_features / cells)`` features.
        min_distance_px: new corners keep this distance from each other and from live
            features.
        quality_level: Shi-Tomasi threshold, relative to the image's strongest corner.
        block_size_px: Shi-Tomasi neighbourhood.
        window_px: Lucas-Kanade window side (odd). Small on purpose: over relief the
            flow varies inside the window (parallax), and Lucas-Kanade returns the
            window's gradient-weighted mean motion, not its centre's. Measured on
            rendered flights at 1000 m, 1 fps: along-flow error std 0.21-0.26 px with 15 px,
            0.27-0.34 px with 21, 0.40-0.48 px with 31 at 320x240 (and a position ANEES of
            17-35 with 31); at 640x480, 15 and 21 px did alike.
        pyramid_levels: Lucas-Kanade pyramid levels above the image (OpenCV's maxLevel):
            the residual flow after prediction the pyramid can absorb is about
            ``window_px / 2 * 2**levels``.
        klt_iterations, klt_epsilon_px: Lucas-Kanade stopping rule per level.
        forward_backward_px: bound of the forward-backward check.
        border_px: features closer than this to the image edge end (their window is cut).
        epipolar_threshold_px: bound of the epipolar residual, in pixels at the focal length.
        ransac_confidence: RANSAC confidence.
        min_rotation_inlier_fraction: with a rotation prior, a fit keeping fewer matches
            than this share is checked against the five-point fit (the prior may be
            wrong: a bad mounting or time offset; or read through a focal length known
            only roughly); the fit keeping more matches wins. A correct prior keeps
            99-100 % of the matches that pass the forward-backward check on rendered
            flights and on real aerial frames (2026-11-27); read through half the focal
            length it kept 64-88 % of them on the real frames, all correct (the
            five-point fit kept 95-100 %).
        normalize_exposure: map each image to a fixed mean and contrast before tracking.
        replenishment: where new corners are looked for (:class:`Replenishment`).
        seed: seeds the RANSAC draws (one stream per tracker).
    """

    max_features: int = 200
    grid_cols: int = 8
    grid_rows: int = 6
    min_distance_px: float = 12.0
    quality_level: float = 0.01
    block_size_px: int = 7
    window_px: int = 15
    pyramid_levels: int = 4
    klt_iterations: int = 30
    klt_epsilon_px: float = 0.01
    forward_backward_px: float = 0.5
    border_px: float = 5.0
    epipolar_threshold_px: float = 1.0
    ransac_confidence: float = 0.999
    min_rotation_inlier_fraction: float = 0.95
    normalize_exposure: bool = True
    replenishment: Replenishment = Replenishment.WHOLE_IMAGE
    seed: int = 0

    def __post_init__(self) -> None:
        ints = {"max_features": 1, "grid_cols": 1, "grid_rows": 1, "block_size_px": 3,
                "window_px": 5, "pyramid_levels": 0, "klt_iterations": 1}
        for name, low in ints.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
                raise CdtmError(f"tracker {name} = {value!r}, expected an integer >= {low}")
        if self.window_px % 2 == 0:
            raise CdtmError(f"tracker window_px = {self.window_px}, expected an odd size")
        positive = ("min_distance_px", "quality_level", "klt_epsilon_px", "forward_backward_px",
                    "epipolar_threshold_px")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise CdtmError(f"tracker {name} = {value!r}, expected a finite value > 0")
        if not (math.isfinite(self.border_px) and self.border_px >= 0):
            raise CdtmError(f"tracker border_px = {self.border_px!r}, expected >= 0")
        for name in ("ransac_confidence", "min_rotation_inlier_fraction"):
            value = getattr(self, name)
            if not 0 < value < 1:
                raise CdtmError(f"tracker {name} = {value!r}, expected a value in (0, 1)")

    @property
    def cells(self) -> int:
        return self.grid_cols * self.grid_rows
