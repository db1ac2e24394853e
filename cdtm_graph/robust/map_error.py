"""How wrong the map really is: the DTM's height error estimated from the tracks (issue 21).

The C-DTM noise takes the DTM's height 1-sigma ``sigma_h`` from flight.yaml (or the Fig. 6
model of its spacing). A real DTM may be worse than it says: ground detail between its
posts, correlated over tens to hundreds of metres (ridges, knolls, tree clumps), which no
single feature can tell from noise. The covariance then holds the stated error, not the
real one: on the robustness flight with 3 m rms of such detail over a DTM stating 2.4 m,
the batch's ANEES was 6.5 (3 expected) and the track tests, holding the ground to 2.4 m,
dropped good tracks as off the map until whole frames were empty (``wrong_fix`` on an
accurate run).

The tracks tell it. Each track triangulated from all its sightings at the run's estimate
has a height above the DTM, ``dh``, whose variance is its triangulation's and the map's
(:func:`~cdtm_graph.robust.mismatch.track_heights`; the estimate's own position error is
counted as the map's, a cautious choice); the map's is the one unknown, a variance
component. :func:`estimate_map_error` solves for the map sigma ``s`` at which the median
of ``dh^2 / (v + s^2)`` over the well-triangulated tracks is chi-square(1)'s median,
leaving out the tracks beyond the mismatch test's gate at that ``s`` and solving again
until it settles: terrain the DTM lacks (buildings, trees, a pit) and wrong matches, which
the track tests drop anyway, do not inflate it (25% of tracks 15-30 m up: 3.49 m read for
3.84 m, where the plain median read 5.16 m). Only tracks whose other variance ``v`` is below
the stated map variance count: a short track's height is mostly triangulation noise.

When the estimate exceeds the stated sigma by :attr:`MapErrorSettings.grow_ratio` and
beyond its own spread over that many tracks (a margin clean flights stay under: their map
error is what ``sigma_h`` was fitted to), the
run is made again with ``sigma_h`` grown to it (:func:`cdtm_graph.smoother.smooth`): the
features then weigh what the map is worth, the covariance holds the real map error, and
the track tests judge the ground against it. A run whose map is as good as stated is not
touched (bit for bit). The verdict notes a grown map error (``map_error_grown``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq
from scipy.special import gammainc

from cdtm_graph.constants import chi2_quantile
from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog, Tracks
from cdtm_graph.results import MapErrorEstimate, TrajectoryEstimate
from cdtm_graph.robust.mismatch import MismatchSettings, TrackHeights, heights_at, inconsistent
from factors import FeatureNoise

#: Rounds of "leave out the tracks beyond the gate, estimate again" (it settles in 3-6).
TRIM_ROUNDS = 20


@dataclass(frozen=True)
class MapErrorSettings:
    """When the map's height error is estimated from the tracks and grown.

    Attributes:
        grow_ratio: the estimate must exceed the stated sigma_h by this factor for the run
            to be made again with it (clean 90-frame flights of the robustness study:
            0.76-1.13)...
        spread_z: ...and by ``1 + spread_z / sqrt(n)`` over ``n`` tracks, when more: a
            short flight's estimate scatters more (the 20 clean 30-frame flights, ~130
            tracks each: 0.47-1.30x; the map's own correlation makes the tracks' errors
            far from independent, so the spread is about twice the independent tracks'
            ``~1.2 / sqrt(n)``).
        min_tracks: fewer well-triangulated tracks than this: no estimate.
        max_ratio: an estimate beyond this many times the stated sigma_h is not grown to:
            the map is then not "worse than stated" but wrong (a DTM of another place, a
            datum error), a fault for the track tests and the verdict to name, which a
            grown sigma_h would hide.
    """

    grow_ratio: float = 1.25
    spread_z: float = 4.5
    min_tracks: int = 50
    max_ratio: float = 3.0


def estimate_map_error(heights: TrackHeights, sigma_h_m: float,
                       settings: MapErrorSettings | None = None,
                       mismatch: MismatchSettings | None = None) -> MapErrorEstimate:
    """The map's height 1-sigma the tracks show (module docstring) and the one to use.

    Args:
        heights: tracks triangulated at the run's estimate, their ``sigma_m`` holding
            ``sigma_h_m`` (:func:`~cdtm_graph.robust.mismatch.track_heights`).
        sigma_h_m: the stated DTM height 1-sigma. settings: when to grow it.
        mismatch: which tracks count (seen often enough; rays that meet).
    """
    s = settings or MapErrorSettings()
    m = mismatch or MismatchSettings()
    other_var = heights.sigma_m**2 - sigma_h_m**2  # triangulation and camera positions
    use = (np.isfinite(heights.dh_m) & np.isfinite(other_var)
           & (heights.n_observations >= m.min_observations) & ~inconsistent(heights, m)
           & (other_var <= sigma_h_m**2))
    n = int(use.sum())
    bound = s.max_ratio * sigma_h_m
    if n < s.min_tracks:
        return MapErrorEstimate(sigma_h_m, float("nan"), n, sigma_h_m, bound)
    dh2, v = heights.dh_m[use] ** 2, np.maximum(other_var[use], 0.0)
    estimated = _trimmed_sigma(dh2, v, m.gate)
    ratio = max(s.grow_ratio, 1.0 + s.spread_z / np.sqrt(n))
    grown = ratio * sigma_h_m < estimated <= bound
    used = estimated if grown else sigma_h_m
    return MapErrorEstimate(sigma_h_m, estimated, n, used, bound)


def _median_excess(map_sigma_m: float, dh2: np.ndarray, v: np.ndarray, target: float
                   ) -> float:
    return float(np.median(dh2 / (v + map_sigma_m**2))) - target


def _trimmed_sigma(dh2: np.ndarray, v: np.ndarray, gate: float) -> float:
    """The map sigma ``s`` at which the median of ``dh^2 / (v + s^2)`` over the tracks
    inside ``gate`` (at that ``s``) is chi-square(1)'s median truncated at the gate: the
    tracks a mismatch test would drop (buildings, trees, a pit) do not count, whatever
    their share, and ``s`` is found again without them until it settles."""
    target = float(chi2_quantile(0.5 * float(gammainc(0.5, 0.5 * gate)), 1))  # (cdf)
    inside = np.ones(dh2.size, bool)
    estimated = 0.0
    for _ in range(TRIM_ROUNDS):
        d, w = dh2[inside], v[inside]
        if _median_excess(0.0, d, w, target) <= 0.0:
            estimated = 0.0
        else:
            high = float(np.sqrt(np.max(d) / target))  # the median is below target there
            estimated = float(brentq(_median_excess, 0.0, high, (d, w, target), xtol=1e-4))
        now = dh2 / (v + estimated**2) <= gate
        if np.array_equal(now, inside) or now.sum() < dh2.size // 2:
            break
        inside = now
    return estimated


def run_heights(flight: FlightLog, dtm: Dtm, noise: FeatureNoise,
                estimate: TrajectoryEstimate,
                unfixed_frames: np.ndarray | None = None) -> TrackHeights:
    """Every track of the log triangulated at a run's estimate, against the DTM, but for
    the sightings in ``unfixed_frames`` (they waited for a fix never found: the run did
    not place those frames by the ground, and a map read from them is the search's
    ambiguity, not the map's error; measured: a 1000 m start over terrain repeating every
    3 km read "beyond the bound" and was smoothed twice more for nothing).

    The cameras are taken as exact: the estimate's own position error then counts as map
    error (cautious: on clean flights the estimate stays near the stated sigma_h, 0.76-1.13
    of it, the robustness flight's seeds 1-4)."""
    tracks = flight.tracks
    if tracks is not None and unfixed_frames is not None and len(unfixed_frames):
        kept = ~np.isin(tracks.frame, unfixed_frames)
        tracks = Tracks(tracks.frame[kept], tracks.track_id[kept], tracks.uv_px[kept])
    if tracks is None or len(tracks) == 0:
        return TrackHeights.empty()
    camera = flight.config.camera
    ray_cam = camera.camera.pixels_to_rays(tracks.uv_px)
    poses = estimate.world_T_body
    return heights_at(tracks.track_id, tracks.frame, ray_cam, lambda k: poses[k],
                      camera.body_T_cam, dtm, noise)
