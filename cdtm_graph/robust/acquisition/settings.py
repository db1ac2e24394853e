"""Settings of an acquisition: how far and how finely to search, and how sure to be."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class AcquisitionSettings:
    """How far and how finely to search, and how sure to be.

    Attributes:
        n_sigma: the search covers the prior out to this many sigmas (the horizontal
            ellipse of the position covariance, and the heading).
        offset_step_m: spacing of the horizontal offset grid; ``None``: the DTM's.
        heading_step_deg: spacing of the heading profile (ray consistency).
        search_heading_step_deg: spacing of the headings whose offsets are searched: a
            cloud turned by half a step about the first frame moves its far points
            (~1.5 km away on the issue's flight) by ~13 m, under half a 30 m DTM cell.
        drift_sigma_rad: angular error of a sighting against the IMU's relative poses
            besides its pixel noise (dead-reckoning drift over the window: a velocity
            error of 1 m/s moves a camera 5 m in 5 s, 2.8 mrad at 1800 m), 1 sigma.
        height_sigma_m: height error of a triangulated point against the DTM besides its
            triangulation error (DTM error, terrain slope times the offset grid's half
            step), 1 sigma.
        truncation_sigma: robust costs are quadratic up to this many sigmas, flat beyond
            (wrong matches, terrain the DTM lacks).
        max_modes: how many modes are refined with the C-DTM factors.
        merge_radius_m: modes of the search are at least this far apart, and a mode's
            refinement stays within half of it; fixes closer than this are one fix (the
            smoothers pull in from there: :attr:`pull_in_m`).
        separation_z: how many standard errors (:func:`~cdtm_graph.robust.acquisition.
            separation_z`) the best fix must beat every other by to be ACQUIRED (and a
            heading's rays the best heading's by to be rejected).
        information_z: how many standard errors the best offset must beat a typical one
            (the median cost of the region) by for the terrain to carry information.
        min_tracks: fewer tracks triangulated under the best heading: NO_INFORMATION.
        refine_iterations: Levenberg-Marquardt iterations of each mode's refinement.
        pull_in_m: horizontal error every smoother (batch, iSAM2, 10 s fixed lag) still
            converges from on the issue's flight (:func:`~cdtm_graph.robust.acquisition.
            needs_acquisition`): 150 m in 21/21 runs at 1 and 3 sigma, 3 seeds; the
            fixed lag failed 9 of 21 at 200 m, batch and iSAM2 held to 300 m
            (``scripts/pull_in.py``).
        pull_in_heading_deg: heading error every smoother still converges from: 9 deg at
            offsets up to 150 m, at 1 and 3 sigma (the largest tried).
        window_frames: the smoothers search on this many frames (6 at 1 fps held a
            margin of 7.3-9.0 standard errors with 30% wrong matches; 4 gave 5.2-6.8).
        retry_every_frames: without a fix, the smoothers search again on the newest
            window this many frames later, and twice as long after each further failed
            search (terrain that could not tell the fix apart rarely can a few frames on;
            a search costs about a second).
    """

    n_sigma: float = 3.0
    offset_step_m: float | None = None
    heading_step_deg: float = 0.25
    search_heading_step_deg: float = 1.0
    drift_sigma_rad: float = 1.0e-3
    height_sigma_m: float = 8.0
    truncation_sigma: float = 3.0
    max_modes: int = 6
    merge_radius_m: float = 150.0
    separation_z: float = 5.0
    information_z: float = 5.0
    min_tracks: int = 30
    refine_iterations: int = 20
    pull_in_m: float = 150.0
    pull_in_heading_deg: float = 9.0
    window_frames: int = 6
    retry_every_frames: int = 3

    def __post_init__(self) -> None:
        for name in ("n_sigma", "heading_step_deg", "search_heading_step_deg",
                     "drift_sigma_rad", "height_sigma_m", "truncation_sigma",
                     "merge_radius_m", "pull_in_m", "pull_in_heading_deg"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"AcquisitionSettings.{name} = {value!r}, expected a "
                                 "finite number > 0")
        if self.offset_step_m is not None and not self.offset_step_m > 0:
            raise ValueError(f"AcquisitionSettings.offset_step_m = {self.offset_step_m!r}, "
                             "expected None or a number > 0")
        if not (isinstance(self.window_frames, int) and self.window_frames >= 2):
            raise ValueError(f"AcquisitionSettings.window_frames = {self.window_frames!r}, "
                             "expected an integer >= 2")
        for name in ("max_modes", "min_tracks", "refine_iterations", "retry_every_frames"):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 1):
                raise ValueError(f"AcquisitionSettings.{name} = {getattr(self, name)!r}, "
                                 "expected an integer >= 1")
