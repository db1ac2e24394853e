"""Terrain the DTM lacks: tracks whose ground point is not where the map says.

Buildings, forest, a quarry, changed ground: a feature on them lies metres off the DTM.
One C-DTM pair barely sees it (a 20 m height error moves a feature by half a pixel at
1800 m with a 150 m baseline, within the noise), but the features on it agree with each
other and pull the estimate along together. A track seen over several frames has the
baseline to tell: triangulated from its observations at the current pose estimates, its
ground point's height against the DTM's there is a direct measure of the mismatch
(``dh``), with an uncertainty from the triangulation geometry and the DTM's own error.

Two views decide:

* a track whose ``dh`` fails a chi-square(1) test is a mismatch (a building, a tree);
* neighbouring tracks share a mismatch (a pit, changed ground): the weighted mean ``dh``
  of the tracks around each track is tested too (short tracks, too weak alone, count by
  their weight), and a neighbourhood that fails goes whole. The mean's uncertainty
  keeps a floor of the DTM's own error: a DTM may be off by that much over a region, and
  the estimate's own small bias must not condemn good ground.

A third view comes with the triangulation: a track whose rays do not meet in a point
(their misses fail a chi-square test) holds a wrong match the epipolar check of single
pairs let by (the random pixel fell near its epipolar line); it goes as such, and is no
evidence about the ground (:func:`inconsistent`). A population of tracks each within
its noise but many on the same side (a forest) is :mod:`cdtm_graph.robust.clutter`'s view.

The smoothers drop the features of mismatched tracks (counted per frame as
``Rejection.MAP_MISMATCH``, or ``WRONG_MATCH``) and solve again: the estimate then rests
on the IMU and the ground the DTM knows, and where nothing is left its covariance grows
honestly.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cdtm_graph.constants import chi2_quantile
from cdtm_graph.dtm import Dtm
from cdtm_graph.geometry import rays_in_world, triangulate
from cdtm_graph.robust.neighbours import ball_sums, near_any
from cdtm_graph.tracks import frames_seen, track_groups
from factors import FeatureNoise
from factors.jit import njit

#: chi-square(1) at 99.9%.
CHI2_1DOF_999 = 10.827566170662733


@dataclass(frozen=True)
class MismatchSettings:
    """How tracks are tested against the DTM.

    Attributes:
        min_observations: tracks seen fewer times are not tested (too little baseline).
        max_sigma_m: tracks whose height is known worse than this are not tested alone
            (they still count in their cell).
        gate: squared ``dh / sigma`` a track must pass.
        radius_m: radius of a track's neighbourhood in the spatial view (m).
        min_neighbours: neighbourhoods with fewer tracks are not judged.
        neighbourhood_gate: squared ``mean dh / sigma`` a neighbourhood must pass
            (5 sigma: overlapping neighbourhoods make many tests).
        frame_fraction: a frame whose tracks are off the DTM for more than this fraction
            sees a region the map lacks; its other tracks are not trusted either
            (:func:`untrusted`).
        fit_probability: a track whose rays miss their common point beyond this
            chi-square probability holds a wrong match (one the epipolar check let by).
    """

    min_observations: int = 3
    max_sigma_m: float = 15.0
    gate: float = CHI2_1DOF_999
    radius_m: float = 300.0
    min_neighbours: int = 5
    neighbourhood_gate: float = 25.0
    frame_fraction: float = 0.3
    fit_probability: float = 0.999


@dataclass(frozen=True)
class TrackHeights:
    """Tracks triangulated at the current poses and compared with the DTM.

    Attributes:
        track_id: (T,) ids. point_m: (T, 3) ground points. n_observations: (T,).
        dh_m: (T,) point height minus the DTM's there (NaN off the DTM).
        sigma_m: (T,) 1-sigma of ``dh`` (triangulation and DTM error).
        fit_chi2: (T,) how far the rays miss the point, chi-square with ``2 n - 3``
            degrees of freedom for a consistent track.
    """

    track_id: np.ndarray
    point_m: np.ndarray
    n_observations: np.ndarray
    dh_m: np.ndarray
    sigma_m: np.ndarray
    fit_chi2: np.ndarray

    @classmethod
    def empty(cls) -> TrackHeights:
        return cls(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64),
                   np.zeros(0), np.zeros(0), np.zeros(0))

    def subset(self, keep: np.ndarray) -> TrackHeights:
        """The tracks where ``keep`` (T,) is True."""
        return TrackHeights(self.track_id[keep], self.point_m[keep],
                            self.n_observations[keep], self.dh_m[keep], self.sigma_m[keep],
                            self.fit_chi2[keep])


def track_heights(track_id: np.ndarray, centre_m: np.ndarray, ray_world: np.ndarray,
                  sigma_rad: float, dtm: Dtm, sigma_h_m: float,
                  pose_sigma_m: float | np.ndarray = 0.0) -> TrackHeights:
    """Triangulate every track of a set of observations and compare it with the DTM.

    Args:
        track_id: (M,) each observation's track. centre_m, ray_world: (M, 3) its camera
            centre and ray (world). sigma_rad: one observation's angular 1-sigma.
        dtm: the map. sigma_h_m: its height 1-sigma.
        pose_sigma_m: 1-sigma of the camera positions, scalar or (M,) per observation (a
            shift of a track's cameras moves its point by as much): each track's largest
            is added to its ``sigma``.
    """
    ids, index, counts = track_groups(track_id)
    m = index.size
    points, cov, chi2_fit = triangulate(index, ids.size, centre_m, ray_world, sigma_rad)
    ground, normal = dtm.height_and_normal(points[:, 0], points[:, 1])
    # (writable: a read-only view would compile the kernel a second time)
    dh, sigma = _height_sigma(index, points, cov, ground, normal,
                              np.require(np.broadcast_to(np.asarray(pose_sigma_m, float), (m,)),
                                         requirements=["C", "W"]), float(sigma_h_m))
    return TrackHeights(ids, points, counts, dh, sigma, chi2_fit)


@njit(cache=True)
def _height_sigma(index, points, cov, ground, normal, pose_sigma, sigma_h):
    """Each track's ``dh`` and its 1-sigma: the triangulation's along the DTM's normal, the
    DTM's own and the largest of its cameras' position sigmas (NaN if any is)."""
    n_tracks = points.shape[0]
    pose_var = np.zeros(n_tracks)
    for i in range(index.shape[0]):
        t, v = index[i], pose_sigma[i] ** 2
        if np.isnan(v) or np.isnan(pose_var[t]):
            pose_var[t] = np.nan
        elif v > pose_var[t]:
            pose_var[t] = v
    dh, sigma = np.empty(n_tracks), np.empty(n_tracks)
    for t in range(n_tracks):
        dh[t] = points[t, 2] - ground[t]
        # d(dh) = n . dX with n = (-dh/dx, -dh/dy, 1), the DTM's upward normal
        var = 0.0
        for r in range(3):
            for c in range(3):
                var += normal[t, r] * cov[t, r, c] * normal[t, c]
        sigma[t] = np.sqrt(var + sigma_h**2 + pose_var[t])
    return dh, sigma


def mismatched(heights: TrackHeights, sigma_h_m: float,
               settings: MismatchSettings | None = None,
               wrong: np.ndarray | None = None) -> np.ndarray:
    """Which tracks lie off the DTM, (T,) bool: alone, or with their neighbourhood.

    Args:
        heights: the tracks. sigma_h_m: the DTM's height 1-sigma (the floor of a
            neighbourhood mean's uncertainty). settings: the tests.
        wrong: (T,) :func:`inconsistent`'s answer, if known already.
    """
    s = settings or MismatchSettings()
    wrong = inconsistent(heights, s) if wrong is None else wrong
    known = np.isfinite(heights.dh_m) & np.isfinite(heights.sigma_m) & ~wrong
    tested = known & (heights.n_observations >= s.min_observations)
    z2 = np.where(known, (heights.dh_m / np.where(known, heights.sigma_m, 1.0)) ** 2, 0.0)
    out = tested & (heights.sigma_m <= s.max_sigma_m) & (z2 > s.gate)
    # The neighbourhood means are taken over the tracks within their own gate: a wild
    # untested track (a wrong match that slipped through, rays almost parallel) is no
    # evidence about its neighbours' ground, and one such would condemn them all.
    rest = np.flatnonzero(known & ~out & (z2 <= s.gate))
    if rest.size >= s.min_neighbours:
        xy = heights.point_m[rest]
        w = 1.0 / heights.sigma_m[rest] ** 2
        # each track's neighbourhood holds itself too
        sums, count = ball_sums(xy, xy, np.stack([w, w * heights.dh_m[rest]], axis=1),
                                s.radius_m)
        mean = sums[:, 1] / sums[:, 0]
        var_mean = 1.0 / sums[:, 0] + sigma_h_m**2
        bad = (count >= s.min_neighbours) & (mean**2 / var_mean > s.neighbourhood_gate)
        if bad.any():
            # a failed neighbourhood goes whole, the wild tracks in it too: they share it
            out[rest[near_any(xy, xy[bad], s.radius_m)]] = True
            wild = np.flatnonzero(known & ~out & (z2 > s.gate))
            out[wild[near_any(heights.point_m[wild], xy[bad], s.radius_m)]] = True
    return out


def inconsistent(heights: TrackHeights, settings: MismatchSettings | None = None
                 ) -> np.ndarray:
    """(T,) tracks whose rays do not meet in a point: one of the observations is a wrong
    match (the epipolar check of single pairs let it by)."""
    s = settings or MismatchSettings()
    dof = 2 * heights.n_observations - 3
    limit = _chi2_quantiles(s.fit_probability, int(max(dof.max(initial=1), 1)))[
        np.maximum(dof, 1) - 1] if dof.size else np.zeros(0)
    return (dof >= 1) & np.isfinite(heights.fit_chi2) & (heights.fit_chi2 > limit)


@functools.lru_cache(maxsize=16)
def _chi2_quantiles(probability: float, max_dof: int) -> np.ndarray:
    """(max_dof,) chi-square quantiles for 1..max_dof degrees of freedom (scipy's ppf
    costs more than the rest of a judgement of a frame's tracks)."""
    return chi2_quantile(probability, np.arange(1, max_dof + 1))


@dataclass(frozen=True)
class TrackJudgement:
    """What the tests found in a set of tracks (sorted ids).

    Attributes:
        off_map: tracks off the DTM, alone or with their neighbourhood.
        inconsistent: tracks whose rays do not meet (a wrong match).
    """

    off_map: np.ndarray
    inconsistent: np.ndarray

    @classmethod
    def none(cls) -> TrackJudgement:
        empty = np.zeros(0, np.int64)
        return cls(empty, empty)


def judge(heights: TrackHeights, sigma_h_m: float,
          settings: MismatchSettings | None = None) -> TrackJudgement:
    """Every test on a set of tracks (:func:`mismatched`, :func:`inconsistent`)."""
    s = settings or MismatchSettings()
    wrong = inconsistent(heights, s)
    return TrackJudgement(heights.track_id[mismatched(heights, sigma_h_m, s, wrong)],
                          heights.track_id[wrong])


def untrusted(track_id: np.ndarray, frame: np.ndarray, off: np.ndarray,
              fraction: float) -> np.ndarray:
    """``off`` (track ids) and every track seen in a frame where more than ``fraction`` of
    the tracks are off: where most of the ground is not what the DTM says (a pit, a new
    quarry), the rest of it in view is not to be trusted either, and the estimate, pulled
    by what was not caught, must not be left to the remainder. ``off`` must hold only
    tracks found off by the tests themselves (not earlier distrust): distrust must not
    feed on itself.

    Args:
        track_id, frame: (M,) the observations' tracks and frames (the tracks already
            left out too, so the shares are of everything the frames saw).
        off: ids of the tracks the tests found off the DTM (now or earlier).
        fraction: the share beyond which a frame's tracks are all distrusted.
    """
    if off.size == 0 or track_id.size == 0:
        return off
    frames, index = frames_seen(frame)
    bad = np.isin(track_id, off)
    share = np.bincount(index, weights=bad, minlength=frames.size) / np.bincount(
        index, minlength=frames.size)
    return np.union1d(off, track_id[share[index] > fraction])


def heights_at(track_id: np.ndarray, frame: np.ndarray, ray_cam: np.ndarray,
               world_T_body: Callable[[int], np.ndarray], body_T_cam: np.ndarray,
               dtm: Dtm, noise: FeatureNoise, pose_sigma_m: float | np.ndarray = 0.0
               ) -> TrackHeights:
    """Tracks triangulated from their observations ((M,) ids, (M,) frames, (M, 3) rays in
    the camera) at the given poses, against the DTM (:func:`cdtm_graph.robust.mismatch.
    track_heights`); the frames' position 1-sigma ``pose_sigma_m`` is a scalar or one per
    frame of ``np.unique(frame)``."""
    if track_id.size == 0:
        return TrackHeights.empty()
    frames, at = frames_seen(frame)
    world_T_cam = np.empty((frames.size, 4, 4))
    for i, k in enumerate(frames.tolist()):
        world_T_cam[i] = world_T_body(k)
    world_T_cam = world_T_cam @ body_T_cam
    centre, ray = rays_in_world(world_T_cam, at, ray_cam)
    sigma = np.asarray(pose_sigma_m, dtype=float)
    return track_heights(track_id, centre, ray, float(np.mean(noise.sigma_q_xy)), dtm,
                         noise.sigma_h_m, sigma[at] if sigma.ndim else sigma)
